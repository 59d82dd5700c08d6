"""Control points: landmarks a user names, with their site coordinates, tie walks to the site frame.

A walk whose ``/landmarks`` marks a listed id was at that surveyed point at the mark's time: its
pose there (the step nearest in time) gets a position prior at the point (``ControlTies``).
These ids are the one exception to "landmarks are evaluation only": the user named them.
Unlisted marks stay evaluation-only.

Placement (``tie_walks``): a walk with a rotation (its heading, rotated by the site frame's
offset from the Earth frame) and one tie is placed by translation; a walk with two ties at
points at least ``min_baseline_m`` apart is placed rigidly by them. The site frame's rotation
from east/north is one unknown per site: the circular mean over walks that mark two distinct
points of (their rigid rotation - their heading), weighted by the baseline; with no such walk
the site frame is taken as east/north (logged).

Frames: dead reckoning (each walk's) -> site (the control points'). Metres, radians.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Mapping

import numpy as np
from numpy.typing import NDArray

from graphslam.core.survey.initialise import fit_se2, se2_apply
from graphslam.core.types import Survey, wrap_angle

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class ControlTies:
    """Every mark of a control point: which walk, which step node, where (site frame)."""

    session: NDArray[np.int64]  # (C,) walk index
    node: NDArray[np.int64]  # (C,) global node index (the walk's step nearest the mark in time)
    xy: NDArray[np.float64]  # (C, 2) the control point (site metres)
    landmark_id: tuple[str, ...]

    def __len__(self) -> int:
        return len(self.session)

    @property
    def walks(self) -> NDArray[np.int64]:
        return np.unique(self.session)


def control_ties(survey: Survey, control_points: Mapping[str, tuple[float, float]], offsets: NDArray) -> ControlTies:
    """Marks of the listed ids, each on the step nearest its time (``offsets``: first node of each walk)."""
    ses, node, xy, ids = [], [], [], []
    for s, sess in enumerate(survey):
        t = sess.steps.t_ns
        for m in sess.landmarks:
            if m.landmark_id not in control_points or len(t) == 0:
                continue
            k = int(np.clip(np.searchsorted(t, m.t_ns), 0, len(t) - 1))
            if k > 0 and abs(t[k - 1] - m.t_ns) < abs(t[k] - m.t_ns):
                k -= 1
            ses.append(s)
            node.append(int(offsets[s]) + k)
            xy.append(control_points[m.landmark_id])
            ids.append(m.landmark_id)
    return ControlTies(
        np.array(ses, np.int64), np.array(node, np.int64), np.array(xy, float).reshape(-1, 2), tuple(ids)
    )


@dataclass(frozen=True, eq=False)
class TiedPlacement:
    transforms: dict[int, NDArray]  # walk -> dead reckoning -> site transform (x, y, theta)
    site_from_earth: float  # rotation of the site frame from east/north (rad); 0 when not fixed
    rotation_fixed: bool  # some walk marked two distinct points (else east/north was assumed)


def tie_walks(
    ties: ControlTies,
    dr_xyh: NDArray[np.float64],
    node_session: NDArray[np.int64],
    rotation: NDArray[np.float64] | None,
    *,
    min_baseline_m: float = 5.0,
) -> TiedPlacement:
    """Place every walk the ties can place (module docstring). ``rotation`` (S,): each walk's
    rotation from dead reckoning to east/north (its heading; NaN: none)."""
    n_s = int(node_session.max()) + 1 if len(node_session) else 0
    rot = np.full(n_s, np.nan) if rotation is None else np.asarray(rotation, float)
    rigid: dict[int, NDArray] = {}
    offs, wts = [], []
    for s in ties.walks.tolist():
        m = ties.session == s
        p, q = dr_xyh[ties.node[m], :2], ties.xy[m]
        span = np.linalg.norm(q - q.mean(0), axis=1).max() * 2.0
        if span >= min_baseline_m:
            rigid[s] = fit_se2(p, q)
            if np.isfinite(rot[s]):
                offs.append(float(wrap_angle(rigid[s][2] - rot[s])))
                wts.append(span)
    fixed = bool(offs)
    phi = float(np.angle((np.array(wts) * np.exp(1j * np.array(offs))).sum())) if fixed else 0.0
    if not fixed and len(ties) and rotation is not None:  # without headings no rotation is taken from them
        log.warning(
            "no walk marks two control points %.0f m apart: the site frame's rotation is taken as east/north "
            "(the phones' headings)", min_baseline_m,
        )
    out: dict[int, NDArray] = {}
    for s in ties.walks.tolist():
        m = ties.session == s
        p, q = dr_xyh[ties.node[m], :2], ties.xy[m]
        if np.isfinite(rot[s]):
            th = float(wrap_angle(rot[s] + phi))
            c, sn = np.cos(th), np.sin(th)
            moved = p @ np.array([[c, sn], [-sn, c]])
            t = (q - moved).mean(0)
            out[s] = np.array([t[0], t[1], th])
        elif s in rigid:
            out[s] = rigid[s]
        # one tie and no heading: the rotation is unknown; the walk is placed by WiFi, if at all
    return TiedPlacement(out, phi, fixed)


def tie_residuals_m(ties: ControlTies, xyh: NDArray[np.float64]) -> NDArray[np.float64]:
    """Distance (m) of each tied pose from its control point."""
    return np.linalg.norm(xyh[ties.node, :2] - ties.xy, axis=1)


__all__ = ["ControlTies", "TiedPlacement", "control_ties", "tie_walks", "tie_residuals_m", "se2_apply"]
