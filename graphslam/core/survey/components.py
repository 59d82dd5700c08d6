"""Components: walks the data links into one frame, and only those.

Map growth (``graphslam.core.survey.placement``) places a walk onto the walks placed before
it only when its WiFi registration is unambiguous (margin over the runner-up placement).
A survey is then split honestly: growth from the strongest walk (or from the walks tied to
control points) gives component 0, the main map; growth among the walks left gives
component 1, and so on; a walk nothing links stands alone. No component is forced into
another: each keeps a frame of its own, and what is missing between them is said per component.

With headings (``graphslam.core.survey.heading``) every walk is first rotated into the Earth
frame, the registration searches rotations only near it (``GrowthParams.rotation_window_deg``)
and the joint refinement holds each walk's rotation near its heading (its sigma): every
component is then north-up, its translation relative to the others unknown.

Frames: walk dead reckoning -> component frame (Earth-aligned with headings; with control
points component 0 is the site frame). Metres, radians.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from graphslam.core.radiomap.similarity import Matches
from graphslam.core.survey.initialise import se2_apply, se2_compose
from graphslam.core.survey.placement import GrowthParams, GrowthResult, grow_placement

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Component:
    """Walks the data links into one frame. Component 0 is the main map (the radio map's frame);
    every other component stands in a frame of its own, its placement relative to component 0
    unknown (``reason`` says which links are missing)."""

    index: int
    walks: tuple[str, ...]  # session ids
    reason: str = ""  # why it stands apart from component 0 ("" for component 0)


@dataclass(frozen=True, eq=False)
class ComponentPlacement:
    """Per walk: its component and the transform from its dead reckoning into that component's frame."""

    transforms: NDArray[np.float64]  # (S, 3) x, y, theta
    component: NDArray[np.int64]  # (S,) 0 = main map; every walk has one
    seeds: tuple[int, ...]  # per component: the walk its frame starts from (component 0 with control points: -1)
    support: NDArray[np.float64]  # (S,) vote support per fingerprint (NaN: a seed or alone)
    margin: NDArray[np.float64]  # (S,) over the runner-up placement (inf: seed / tied)
    consistency: NDArray[np.float64]  # (S,) share of match weight consistent at the final placement
    reasons: dict[int, str] = field(default_factory=dict)  # component index (>= 1) -> why it stands apart

    @property
    def n_components(self) -> int:
        return len(self.seeds)

    def walks_of(self, k: int) -> NDArray[np.int64]:
        return np.flatnonzero(self.component == k)


def place_components(
    n_sessions: int,
    scan_session: NDArray[np.int64],
    scan_xy: NDArray[np.float64],
    matches: Matches,
    params: GrowthParams,
    *,
    rotation: NDArray[np.float64] | None = None,
    rotation_sigma: NDArray[np.float64] | None = None,
    tied: dict[int, NDArray] | None = None,
    seed: int | None = None,
) -> ComponentPlacement:
    """Split the survey into components by repeated map growth (module docstring).

    ``scan_xy``: fingerprint positions in their walk's dead-reckoning frame. ``rotation`` (S,):
    each walk's rotation into the common frame (its heading), applied before growth; growth
    then searches only ``params.rotation_window_deg`` about it. ``tied``: walks already placed
    in component 0's frame (walk -> dead reckoning -> frame transform, e.g. by control
    points), held fixed. ``seed``: the walk component 0 starts from (without ``tied``)."""
    pre = np.zeros((n_sessions, 3))
    if rotation is not None:
        pre[:, 2] = np.where(np.isfinite(rotation), rotation, 0.0)
    xy = se2_apply_rows(pre[scan_session], scan_xy)
    # tied walks: their transform in the pre-rotated frame
    initial = {k: se2_compose(np.asarray(T, float), _inverse_rotation(pre[k, 2])) for k, T in (tied or {}).items()}
    component = np.full(n_sessions, -1, np.int64)
    T_all = np.zeros((n_sessions, 3))
    support = np.full(n_sessions, np.nan)
    margin = np.full(n_sessions, np.nan)
    consistency = np.full(n_sessions, np.nan)
    seeds: list[int] = []
    first: GrowthResult | None = None
    k = 0
    while (component < 0).any():
        left = component < 0
        res = grow_placement(
            n_sessions, scan_session, xy, matches, params,
            seed=seed if k == 0 else None,
            initial=initial if (k == 0 and initial) else None,
            candidates=left,
            rotation_sigma=rotation_sigma,
        )
        got = res.placed & left
        if not got.any():  # cannot happen (the seed is always placed); guards the loop
            got[np.flatnonzero(left)[0]] = True
        component[got] = k
        T_all[got] = res.transforms[got]
        support[got], margin[got], consistency[got] = res.support[got], res.margin[got], res.consistency[got]
        seeds.append(-1 if (k == 0 and initial) else int(res.seed))
        if k == 0:
            first = res
        k += 1
    # back to the walks' own dead-reckoning frames: T o pre
    transforms = np.array([se2_compose(T_all[s], pre[s]) for s in range(n_sessions)]) if n_sessions else T_all
    # components by size (component 0 stays the tied / first one when it is tied)
    sizes = np.bincount(component, minlength=k)
    order = list(range(k))
    if not initial:
        order = sorted(range(k), key=lambda c: (-sizes[c], c))
    remap = np.empty(k, np.int64)
    remap[order] = np.arange(k)
    component = remap[component]
    seeds = [seeds[c] for c in order]
    reasons = _reasons(component, first, remap, sizes[order[0]] if k else 0)
    log.info(
        "components: %d walks in %d components; the main map holds %d", n_sessions, k,
        int((component == 0).sum()) if k else 0,
    )
    return ComponentPlacement(transforms, component, tuple(seeds), support, margin, consistency, reasons)


def _reasons(component: NDArray, first: GrowthResult | None, remap: NDArray, n_main: int) -> dict[int, str]:
    """Why each component k >= 1 stands apart: its walks' outcome when the first growth tried them."""
    out: dict[int, str] = {}
    first_reasons = (first.reasons if first is not None else {}) or {}
    main_is_first = bool(len(remap)) and remap[0] == 0
    for k in range(1, int(component.max()) + 1 if len(component) else 0):
        walks = np.flatnonzero(component == k)
        if main_is_first:
            why = sorted({first_reasons.get(int(s), "no WiFi matches to the main map") for s in walks})
            ambiguous = [w for w in why if w.startswith("WiFi registration ambiguous")]
            if ambiguous:
                out[k] = "its WiFi registration onto the main map is ambiguous (" + ambiguous[0].split(": ", 1)[1] + ")"
            else:
                out[k] = "no WiFi matches between its walks and the main map's"
        else:
            out[k] = f"its walks do not register onto the main map ({n_main} walks) unambiguously"
    return out


def _inverse_rotation(theta: float) -> NDArray:
    return np.array([0.0, 0.0, -theta])


def se2_apply_rows(T: NDArray, xy: NDArray) -> NDArray:
    """Row-wise ``se2_apply``: point i by transform T[i]."""
    c, s = np.cos(T[:, 2]), np.sin(T[:, 2])
    return np.column_stack([c * xy[:, 0] - s * xy[:, 1] + T[:, 0], s * xy[:, 0] + c * xy[:, 1] + T[:, 1]])


__all__ = ["Component", "ComponentPlacement", "place_components", "se2_apply"]
