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
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from graphslam.core.radiomap.similarity import Matches
from graphslam.core.survey.initialise import fit_se2, se2_apply, se2_compose
from graphslam.core.survey.placement import GrowthParams, GrowthResult, grow_placement

if TYPE_CHECKING:
    from graphslam.core.survey.magnetic import LinkUnits

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
    joins: NDArray[np.bool_] | None = None,
) -> ComponentPlacement:
    """Split the survey into components by repeated map growth (module docstring).

    ``scan_xy``: fingerprint positions in their walk's dead-reckoning frame. ``rotation`` (S,):
    each walk's rotation into the common frame (its heading), applied before growth; growth
    then searches only ``params.rotation_window_deg`` about it. ``tied``: walks already placed
    in component 0's frame (walk -> dead reckoning -> frame transform, e.g. by control
    points), held fixed. ``seed``: the walk component 0 starts from (without ``tied``). ``joins`` (S,):
    the walks WiFi may join onto a component grown from others (None: every walk); the others only
    seed components of their own (or are tied)."""
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
        seed_k = seed if k == 0 else None
        cand = left
        if joins is not None:  # a component grows by the walks WiFi may join, from its seed (or ties)
            cand = left & joins
            if not (k == 0 and initial):
                seed_k = _strongest(left, scan_session, matches, params) if seed_k is None else seed_k
                cand = cand.copy()
                cand[seed_k] = True
        res = grow_placement(
            n_sessions, scan_session, xy, matches, params,
            seed=seed_k,
            initial=initial if (k == 0 and initial) else None,
            candidates=cand,
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


def _strongest(left: NDArray[np.bool_], scan_session: NDArray, matches: Matches, params: GrowthParams) -> int:
    """The walk of ``left`` with the most match weight into the others of ``left`` (map growth's seed)."""
    si, sj = scan_session[matches.i], scan_session[matches.j]
    keep = left[si] & left[sj]
    w = np.power(np.clip(matches.similarity[keep], 0.0, 1.0), params.weight_power)
    n = len(left)
    mass = np.bincount(si[keep], weights=w, minlength=n) + np.bincount(sj[keep], weights=w, minlength=n)
    return int(np.where(left, mass, -1.0).argmax())


def place_units(
    n_sessions: int,
    scan_session: NDArray[np.int64],
    scan_xy: NDArray[np.float64],
    matches: Matches,
    params: GrowthParams,
    units: "LinkUnits",
    *,
    rotation_sigma: NDArray[np.float64],
    ties: tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]] | None = None,
    seed: int | None = None,
    min_baseline_m: float = 5.0,
    reference: tuple[NDArray[np.float64], Matches] | None = None,
) -> ComponentPlacement:
    """``place_components`` over units of walks the magnetic field holds together
    (``graphslam.core.survey.magnetic.LinkUnits``): each unit is placed as one rigid body by the WiFi
    matches between its walks and the others' (the repetitions of a route pool their evidence, where one
    walk alone is weak), and no WiFi match inside a unit counts (the field placed its walks).

    ``scan_xy``: fingerprints in their walk's dead reckoning. ``rotation_sigma`` (S,): each walk's;
    a unit's is that of their mean. ``ties``: (walk, dead-reckoned xy, site xy) of control-point
    marks: a unit holding tied walks is placed by translation onto all of its marks (its rotation is
    its walks' headings, turned into the site frame) and component 0 grows from the tied units.
    ``seed``: the walk whose unit component 0 starts from (without ties). ``reference``: a surveyed map
    held in the site frame (its fingerprints' site positions, and the matches from ``scan_xy``'s rows
    to its rows): component 0 grows from it (and the ties) by each unit's reference matches alone;
    the units left form components among themselves (``graphslam.core.survey.reference``)."""
    unit = units.unit
    n_u = units.n_units
    u_scan = unit[scan_session]
    xy = se2_apply_rows(units.transforms[scan_session], scan_xy)  # in the unit's frame
    keep = u_scan[matches.i] != u_scan[matches.j]
    m = Matches(matches.i[keep], matches.j[keep], matches.similarity[keep])
    inv = np.bincount(unit, weights=1.0 / np.maximum(rotation_sigma, 1e-6) ** 2, minlength=n_u)
    sigma_u = 1.0 / np.sqrt(np.maximum(inv, 1e-12))
    tied_u: dict[int, NDArray] = {}
    if ties is not None:
        walk, dr, site = ties
        at = se2_apply_rows(units.transforms[walk], dr)  # the marks in their unit's frame
        for u in np.unique(unit[walk]).tolist():
            sel = unit[walk] == u
            q = site[sel]
            if np.linalg.norm(q - q.mean(axis=0), axis=1).max() * 2.0 >= min_baseline_m:
                # marks of two places or more: they fix the unit's rotation better than its headings do
                tied_u[int(u)] = fit_se2(at[sel], q)
                log.debug("unit %d: tied rigidly by %d marks (rotation %.1f deg)", u, int(sel.sum()), np.degrees(tied_u[int(u)][2]))
            else:
                t = (q - at[sel]).mean(axis=0)
                tied_u[int(u)] = np.array([t[0], t[1], 0.0])
    # a unit of two walks or more joins a component by its own field links only: units the field does
    # not link share no corridor (their walks only cross), and WiFi places crossings a few metres off
    # at best; a walk the field links to nothing (short, or without the field) joins by WiFi
    single = np.bincount(unit, minlength=n_u) == 1
    if reference is None:
        cp = place_components(
            n_u, u_scan, xy, m, params, rotation_sigma=sigma_u, tied=tied_u or None,
            seed=None if seed is None else int(unit[seed]), joins=single,
        )
    else:
        cp = _on_reference(n_u, u_scan, xy, m, params, sigma_u, tied_u, single, reference)
    transforms = np.array([se2_compose(cp.transforms[unit[s]], units.transforms[s]) for s in range(n_sessions)])
    transforms = transforms.reshape(n_sessions, 3)
    seeds = tuple(-1 if sd < 0 else int(units.seed[sd]) for sd in cp.seeds)
    return ComponentPlacement(
        transforms, cp.component[unit], seeds, cp.support[unit], cp.margin[unit], cp.consistency[unit], cp.reasons,
    )


def _on_reference(
    n_u: int, u_scan: NDArray[np.int64], xy: NDArray, m: Matches, params: GrowthParams, sigma_u: NDArray,
    tied_u: dict[int, NDArray], single: NDArray[np.bool_], reference: tuple[NDArray[np.float64], Matches],
) -> ComponentPlacement:
    """``place_units``' placement with a reference map: component 0 = the reference (a held pseudo-unit,
    index ``n_u``), the tied units and every unit its reference matches register onto it; the rest by
    ``place_components`` among themselves."""
    ref_xy, rm = reference
    n_rows = len(u_scan)
    scan = np.concatenate([u_scan, np.full(len(ref_xy), n_u, np.int64)])
    pts = np.concatenate([xy, ref_xy])
    # a multi-walk unit registers on the reference's matches alone; a single walk also on its WiFi matches
    # into the walks placed before it (as between walks without a reference)
    one = single[u_scan[m.i]] | single[u_scan[m.j]]
    mr = Matches(np.concatenate([rm.i, m.i[one]]), np.concatenate([rm.j + n_rows, m.j[one]]),
                 np.concatenate([rm.similarity, m.similarity[one]]))
    initial = {n_u: np.zeros(3), **tied_u}
    res = grow_placement(n_u + 1, scan, pts, mr, params, initial=initial,
                         rotation_sigma=np.concatenate([sigma_u, [1e-6]]))
    main = res.placed[:n_u]
    for u, why in sorted(res.reasons.items()):
        log.debug("reference map: unit %d not placed: %s", u, why)
    component = np.full(n_u, -1, np.int64)
    component[main] = 0
    T = np.zeros((n_u, 3))
    T[main] = res.transforms[:n_u][main]
    support, margin, consistency = res.support[:n_u].copy(), res.margin[:n_u].copy(), res.consistency[:n_u].copy()
    seeds: list[int] = [-1]
    reasons: dict[int, str] = {}
    left = np.flatnonzero(~main)
    if len(left):  # the rest: components of their own, among themselves
        local = np.full(n_u, -1, np.int64)
        local[left] = np.arange(len(left))
        rows = np.flatnonzero(local[u_scan] >= 0)
        row_of = np.full(n_rows, -1, np.int64)
        row_of[rows] = np.arange(len(rows))
        keep = (row_of[m.i] >= 0) & (row_of[m.j] >= 0)
        sub = place_components(len(left), local[u_scan[rows]], xy[rows],
                               Matches(row_of[m.i[keep]], row_of[m.j[keep]], m.similarity[keep]), params,
                               rotation_sigma=sigma_u[left], joins=single[left])
        component[left] = sub.component + 1
        T[left] = sub.transforms
        support[left], margin[left], consistency[left] = sub.support, sub.margin, sub.consistency
        seeds += [int(left[sd]) for sd in sub.seeds]
        matched = np.unique(u_scan[rm.i])  # units with a reference match at all
        for k in range(sub.n_components):
            reasons[k + 1] = ("its WiFi registration onto the reference map is ambiguous"
                              if np.isin(left[sub.walks_of(k)], matched).any() else "no match onto the reference map")
    log.info("reference map: %d of %d units placed onto it", int(main.sum()), n_u)
    return ComponentPlacement(T, component, tuple(seeds), support, margin, consistency, reasons)


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


__all__ = ["Component", "ComponentPlacement", "place_components", "place_units", "se2_apply"]
