"""The shape of a survey of out-and-back routes: what the ``museum`` scenario must share with the real floor.

Every statistic here needs only what a real recording has: steps, scans and landmark
marks. Positions come from each walk's PDR rigidly fitted to its own landmarks (the
best placement a walk's own dead reckoning allows, ~1.4 m off on IPIN 2023 floor -2),
so a simulated survey and a real one are measured the same way; pass
``truth=True`` to place simulated scans at their true positions instead.

Walks are grouped by route: ``route_of`` knows the real file names
(``IPIN2023_T3_TrainingTrial21_repetition01`` -> ``route1``, trials 21-27 are routes
1-7 and 51-53 the stair/lift spots ``stairs1``-``stairs3``) and the simulator's ids
(``museum-s0-route1-rep01``).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Iterable, Mapping

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from graphslam.core.radiomap.fingerprints import DistanceEngine, FingerprintMatrix
from graphslam.core.common.geometry import fit_se2, interpolate_xy, se2_apply
from graphslam.core.types import Session, Survey

STANDSTILL_GAP_S = 3.0  # a gap between steps longer than this is the walker standing
OVERLAP_RADIUS_M = 3.0  # a scan "overlaps" another walk's scans within this distance
PHONE_PAIR_M = 2.0  # scans of two phones this close are compared for the RSS offset
COLOCATED_M = 1.5  # scans of two walks this close are "at one place"
HEADING_SPAN_S = 1.5  # walking direction at a scan: displacement from t - span to t + span


def route_of(session_id: str) -> str | None:
    """``routeN`` / ``stairsN`` of a real IPIN 2023 floor -2 file or a simulated museum walk; None otherwise."""
    m = re.search(r"-(route\d+|stairs\d+)-rep\d+$", session_id)
    if m:
        return m.group(1)
    m = re.search(r"TrainingTrial(\d+)_repetition", session_id)
    if m:
        trial = int(m.group(1))
        if 21 <= trial <= 27:
            return f"route{trial - 20}"
        if 51 <= trial <= 53:
            return f"stairs{trial - 50}"
    return None


@dataclass(frozen=True, eq=False)
class WalkShape:
    """One walk's shape figures (s, m)."""

    session_id: str
    route: str
    duration_s: float
    steps: int
    pdr_length_m: float
    pdr_step_m: float  # median PDR step length
    scan_interval_s: float  # median interval between scans
    scan_regular: float  # fraction of intervals within 10 % of that median
    standstills_s: tuple[float, ...]  # gaps between steps > STANDSTILL_GAP_S
    standstill_scans: int  # scans taken inside those gaps
    standstill_truth_moves_m: float  # largest true displacement across such a gap (nan without ground truth)
    rigid_fit_m: float  # mean landmark error of the PDR rigidly fitted to its own landmarks
    pdr_scale: float  # least-squares scale that would fit the PDR to its landmarks after that fit
    segment_heading_err_deg: NDArray[np.float64]  # per landmark-to-landmark leg >= 3 m, minus the walk's mean
    scan_xy: NDArray[np.float64]  # (S, 2) scan positions (fitted PDR, or truth)
    scan_heading: NDArray[np.float64]  # (S,) walking direction (rad, same frame), nan when not moving
    scan_standstill: NDArray[np.int64]  # (S,) index of the standstill the scan lies in, -1 if none
    readings: NDArray[np.int64]  # (S,) readings per scan


def _fit(s: Session) -> tuple[NDArray, NDArray, NDArray]:
    t = np.array([m.t_ns for m in s.landmarks], dtype=float)
    est = interpolate_xy(s.steps, t)
    true = np.array([[m.x, m.y] for m in s.landmarks], dtype=float)
    return fit_se2(est, true), est, true


def walk_shape(s: Session, route: str, *, truth: bool = False) -> WalkShape:
    """The shape figures of one walk (needs >= 2 landmark marks)."""
    t_steps = s.steps.t_ns
    gaps = np.diff(t_steps) / 1e9
    t_scan = np.array([x.t_ns for x in s.scans], dtype=np.int64)
    long_gaps = np.flatnonzero(gaps > STANDSTILL_GAP_S)
    inside = sum(int(np.sum((t_scan > t_steps[k]) & (t_scan < t_steps[k + 1]))) for k in long_gaps)
    moves = math.nan
    if s.ground_truth is not None:
        d = np.linalg.norm(s.ground_truth.xy[long_gaps + 1] - s.ground_truth.xy[long_gaps], axis=1)
        moves = float(d.max()) if len(d) else 0.0
    T, est, true = _fit(s)
    placed = se2_apply(T, est)
    err = np.linalg.norm(placed - true, axis=1)
    a = se2_apply(np.array([0.0, 0.0, T[2]]), est - est.mean(axis=0))
    b = true - true.mean(axis=0)
    scale = float(np.sum(a * b) / max(np.sum(a * a), 1e-12))
    de, dt = np.diff(placed, axis=0), np.diff(true, axis=0)
    legs = np.linalg.norm(dt, axis=1) >= 3.0
    ang = np.arctan2(de[legs, 1], de[legs, 0]) - np.arctan2(dt[legs, 1], dt[legs, 0])
    ang = np.angle(np.exp(1j * ang) * np.exp(-1j * np.angle(np.mean(np.exp(1j * ang))))) if len(ang) else ang
    track = s.ground_truth if truth and s.ground_truth is not None else s.steps
    fit = np.zeros(3) if track is s.ground_truth else T

    def at(dt_s: float) -> NDArray:
        return se2_apply(fit, interpolate_xy(track, t_scan.astype(float) + dt_s * 1e9))

    xy = at(0.0)
    ahead = at(HEADING_SPAN_S) - at(-HEADING_SPAN_S)  # moving >= 1.5 m in 3 s: walking
    heading = np.where(np.hypot(ahead[:, 0], ahead[:, 1]) >= 1.5, np.arctan2(ahead[:, 1], ahead[:, 0]), np.nan)
    still = np.full(len(t_scan), -1, np.int64)
    for j, k in enumerate(long_gaps):
        still[(t_scan > t_steps[k]) & (t_scan < t_steps[k + 1])] = j
    dts = np.diff(t_scan) / 1e9
    med = float(np.median(dts)) if len(dts) else math.nan
    steps = np.linalg.norm(np.diff(s.steps.xy, axis=0), axis=1)
    return WalkShape(
        session_id=s.session_id,
        route=route,
        duration_s=s.duration_s,
        steps=len(s.steps),
        pdr_length_m=s.steps.path_length,
        pdr_step_m=float(np.median(steps)) if len(steps) else math.nan,
        scan_interval_s=med,
        scan_regular=float(np.mean(np.abs(dts - med) <= 0.1 * med)) if len(dts) else math.nan,
        standstills_s=tuple(float(g) for g in gaps[long_gaps]),
        standstill_scans=inside,
        standstill_truth_moves_m=moves,
        rigid_fit_m=float(err.mean()),
        pdr_scale=scale,
        segment_heading_err_deg=np.degrees(ang),
        scan_xy=xy,
        scan_heading=heading,
        scan_standstill=still,
        readings=np.array([len(x) for x in s.scans], dtype=np.int64),
    )


def _near_count(a: NDArray, b: NDArray, r: float) -> int:
    """How many points of ``a`` lie within ``r`` of some point of ``b``."""
    if len(a) == 0 or len(b) == 0:
        return 0
    d, _ = cKDTree(b).query(a, distance_upper_bound=r)
    return int(np.sum(np.isfinite(d)))


def overlaps(walks: Iterable[WalkShape], radius_m: float = OVERLAP_RADIUS_M) -> dict[tuple[str, str], float]:
    """Fraction of route A's scans within ``radius_m`` of route B's scans; (A, A) = of A's *other* walks."""
    by: dict[str, list[WalkShape]] = {}
    for w in walks:
        by.setdefault(w.route, []).append(w)
    out: dict[tuple[str, str], float] = {}
    for a, wa in by.items():
        n = sum(len(w.scan_xy) for w in wa)
        for b, wb in by.items():
            if a == b:
                rest = [np.vstack([o.scan_xy for o in wa if o is not w] or [np.zeros((0, 2))]) for w in wa]
                hit = sum(_near_count(w.scan_xy, r, radius_m) for w, r in zip(wa, rest))
            else:
                hit = _near_count(np.vstack([w.scan_xy for w in wa]), np.vstack([w.scan_xy for w in wb]), radius_m)
            out[(a, b)] = hit / max(n, 1)
    return out


@dataclass(frozen=True, eq=False)
class _Scans:
    """Every scan of the shaped walks, in survey order."""

    owner: NDArray[np.int64]  # walk index in the survey
    xy: NDArray[np.float64]
    heading: NDArray[np.float64]
    still: NDArray[np.int64]
    fast: NDArray[np.bool_]  # the phone scanning every ~2 s
    readings: list[Mapping[str, float]]

    @classmethod
    def of(cls, survey: Survey, walks: Mapping[str, WalkShape]) -> "_Scans":
        pairs = [(i, w, s) for i, s in enumerate(survey) if (w := walks.get(s.session_id)) is not None]
        n = [len(w.scan_xy) for _, w, _ in pairs]
        return cls(
            owner=np.repeat([i for i, _, _ in pairs], n).astype(np.int64),
            xy=np.vstack([w.scan_xy for _, w, _ in pairs] or [np.zeros((0, 2))]),
            heading=np.concatenate([w.scan_heading for _, w, _ in pairs] or [np.zeros(0)]),
            still=np.concatenate([w.scan_standstill for _, w, _ in pairs] or [np.zeros(0, np.int64)]),
            fast=np.repeat([w.scan_interval_s < 3.0 for _, w, _ in pairs], n).astype(bool),
            readings=[x.readings for _, _, s in pairs for x in s.scans],
        )

    def diffs(self, a: NDArray, b: NDArray) -> NDArray[np.float64]:
        """RSS differences of the APs two scans share, over the pairs (a[i], b[i])."""
        r = self.readings
        return np.array([r[i][k] - r[j][k] for i, j in zip(a, b) for k in r[i].keys() & r[j].keys()], dtype=float)


def phone_offset_db(survey: Survey, walks: Mapping[str, WalkShape]) -> float:
    """Mean RSS of the 2 s phone minus the 4 s phone, over the common APs of scans < PHONE_PAIR_M apart."""
    sc = _Scans.of(survey, walks)
    fa, fb = np.flatnonzero(sc.fast), np.flatnonzero(~sc.fast)
    if len(fa) == 0 or len(fb) == 0:
        return math.nan
    near = cKDTree(sc.xy[fa]).query_ball_tree(cKDTree(sc.xy[fb]), PHONE_PAIR_M)
    diffs = []
    for i, js in zip(fa, near):
        for j in fb[js]:
            common = sc.readings[i].keys() & sc.readings[j].keys()
            if len(common) >= 3:
                diffs.append(np.mean([sc.readings[i][k] - sc.readings[j][k] for k in common]))
    return float(np.mean(diffs)) if diffs else math.nan


def ap_prevalence(survey: Survey, walks: Mapping[str, WalkShape]) -> tuple[int, int, int]:
    """How many APs are heard in > 60 %, > 10 % and < 1 % of all scans."""
    counts: dict[str, int] = {}
    readings = _Scans.of(survey, walks).readings
    for r in readings:
        for b in r:
            counts[b] = counts.get(b, 0) + 1
    f = np.array(list(counts.values())) / max(len(readings), 1)
    return int(np.sum(f > 0.6)), int(np.sum(f > 0.1)), int(np.sum(f < 0.01))


def rss_differences(survey: Survey, walks: Mapping[str, WalkShape]) -> tuple[float, float, float, float]:
    """One AP's RSS difference (dB) between two scans (same phone model): mean square between
    consecutive scans of one standstill and between co-located scans (< COLOCATED_M) of two walks;
    mean |difference| of co-located walking scans of two walks going the same / opposite ways."""
    sc = _Scans.of(survey, walks)
    if len(sc.owner) < 2:
        return (math.nan,) * 4
    o, st = sc.owner, sc.still
    k = np.flatnonzero((o[:-1] == o[1:]) & (st[:-1] == st[1:]) & (st[:-1] >= 0))
    standstill = sc.diffs(k, k + 1)
    pairs = cKDTree(sc.xy).query_pairs(COLOCATED_M, output_type="ndarray")
    keep = (o[pairs[:, 0]] != o[pairs[:, 1]]) & (sc.fast[pairs[:, 0]] == sc.fast[pairs[:, 1]])
    a, b = pairs[keep, 0], pairs[keep, 1]
    turn = np.abs(np.angle(np.exp(1j * (sc.heading[a] - sc.heading[b]))))  # nan when either stands
    same, opposite = turn < math.pi / 4, turn > 3 * math.pi / 4

    def mean(v: NDArray) -> float:
        return float(v.mean()) if len(v) else math.nan

    return (
        mean(standstill**2),
        mean(sc.diffs(a, b) ** 2),
        mean(np.abs(sc.diffs(a[same], b[same]))),
        mean(np.abs(sc.diffs(a[opposite], b[opposite]))),
    )


def fingerprint_resolution(survey: Survey, walks: Mapping[str, WalkShape]) -> tuple[float, float, float]:
    """Each scan's most similar scan of another walk (eq. 9, -110 dBm fill, readings >= -100 dBm, >= 3
    common APs): (median, p90) of their distance apart (m) and the fraction within 5 m."""
    sc = _Scans.of(survey, walks)
    fp = FingerprintMatrix.from_scans(sc.readings, missing_dbm=-110.0, min_rssi_dbm=-100.0)
    dist = []
    for start, D, _ in DistanceEngine(fp).iter_blocks(fp, min_common=3):
        rows = np.arange(start, start + len(D))
        D[sc.owner[rows][:, None] == sc.owner[None, :]] = np.inf  # not the walk's own scans
        ok = np.isfinite(D).any(axis=1)
        best = np.argmin(D[ok], axis=1)
        dist.append(np.linalg.norm(sc.xy[rows[ok]] - sc.xy[best], axis=1))
    d = np.concatenate(dist) if dist else np.zeros(0)
    if len(d) == 0:
        return math.nan, math.nan, math.nan
    return float(np.median(d)), float(np.percentile(d, 90)), float(np.mean(d < 5.0))


def manhattan(survey: Survey) -> tuple[float, float, float, float]:
    """(axis deg, fraction of landmark-to-landmark legs >= 2 m within 5 deg of the axis or its normal,
    landmark extent along and across the axes, m). The axis is the legs' length-weighted mean direction mod 90 deg."""
    legs = []
    for s in survey:
        p = np.array([[m.x, m.y] for m in s.landmarks])
        d = np.diff(p, axis=0)
        legs += [(math.atan2(v[1], v[0]), float(np.hypot(*v))) for v in d if np.hypot(*v) >= 2.0]
    a = np.array(legs)
    th = math.atan2(np.sum(a[:, 1] * np.sin(4 * a[:, 0])), np.sum(a[:, 1] * np.cos(4 * a[:, 0]))) / 4
    dev = (np.degrees(a[:, 0] - th) + 45.0) % 90.0 - 45.0
    p = np.array([[m.x, m.y] for s in survey for m in s.landmarks])
    c, s_ = math.cos(th), math.sin(th)
    ext = np.ptp(p @ np.array([[c, -s_], [s_, c]]), axis=0)
    return math.degrees(th), float(np.mean(np.abs(dev) < 5.0)), float(ext.max()), float(ext.min())


def shape_walks(survey: Survey, *, truth: bool = False) -> dict[str, WalkShape]:
    """``walk_shape`` of every walk that ``route_of`` knows and that has >= 2 landmark marks."""
    out = {}
    for s in survey:
        r = route_of(s.session_id)
        if r is not None and len(s.landmarks) >= 2:
            out[s.session_id] = walk_shape(s, r, truth=truth)
    return out


def _heading_shares(walks: Iterable[WalkShape]) -> tuple[float, float, float]:
    """Std (deg) of the legs' heading errors: total, the part the walks of a route share, the rest."""
    by: dict[str, list[NDArray]] = {}
    for w in walks:
        if w.route.startswith("route"):
            by.setdefault(w.route, []).append(w.segment_heading_err_deg)
    tot, shared, own = [], [], []
    for errs in by.values():
        n = min(len(e) for e in errs)
        if len(errs) < 2 or n == 0:
            continue
        a = np.array([e[:n] for e in errs])  # walks x legs
        res = a - a.mean(axis=0)
        k = len(a)
        v_own = float(np.var(res)) * k / (k - 1)
        tot.append(float(np.var(a)))
        own.append(v_own)
        shared.append(float(np.var(a.mean(axis=0))) - v_own / k)
    return (
        math.sqrt(np.mean(tot)) if tot else math.nan,
        math.sqrt(max(0.0, float(np.mean(shared)))) if shared else math.nan,
        math.sqrt(np.mean(own)) if own else math.nan,
    )


def survey_shape(survey: Survey, walks: Mapping[str, WalkShape]) -> dict[str, object]:
    """The shape statistics (label -> number or tuple), in the order of docs/simulator.md's table."""
    ws = list(walks.values())
    routes = [w for w in ws if w.route.startswith("route")]
    stairs = [w for w in ws if w.route.startswith("stairs")]
    by: dict[str, int] = {}
    for w in ws:
        by[w.route] = by.get(w.route, 0) + 1
    sessions = [s for s in survey if s.session_id in walks]
    lm_routes: dict[str, set[str]] = {}
    for s in sessions:
        for m in s.landmarks:
            lm_routes.setdefault(m.landmark_id, set()).add(walks[s.session_id].route)
    axis, legs_on_axes, along, across = manhattan(Survey(tuple(sessions)))
    gaps = [g for w in ws for g in w.standstills_s]
    n_scans = sum(len(w.scan_xy) for w in ws)
    readings = np.concatenate([w.readings for w in ws])
    rss = np.array([r for s in sessions for x in s.scans for r in x.readings.values()])
    aps = [len(s.access_points) for s in sessions]
    ov = overlaps(ws)
    names = sorted({w.route for w in routes}, key=lambda r: int(r[5:]))
    between = [max((ov[(a, b)] for b in by if b != a), default=0.0) for a in names]
    adjacent = tuple(round(ov[(a, b)], 2) for a, b in zip(names[:-1], names[1:]))
    fp_med, fp_p90, fp_5 = fingerprint_resolution(survey, walks)
    d_still, d_walks, d_same, d_opposite = rss_differences(survey, walks)
    h_tot, h_shared, h_own = _heading_shares(ws)
    rigid = np.array([w.rigid_fit_m for w in ws])
    rigid_r = np.array([w.rigid_fit_m for w in routes])
    scale = np.array([w.pdr_scale for w in routes])
    marks_r = [len(s.landmarks) for s in sessions if walks[s.session_id].route.startswith("route")]
    long_stand = float(np.mean([max(w.standstills_s, default=0.0) >= 10.0 for w in routes]))
    mm = lambda v: (round(float(np.min(v)), 1), round(float(np.max(v)), 1))  # noqa: E731
    return {
        "walks (routes + stair/lift)": (len(routes), len(stairs)),
        "routes, stair/lift spots": (len(names), len({w.route for w in stairs})),
        "walks per route (min, max)": (min(by.values()), max(by.values())),
        "route walk duration s (min, max)": mm([w.duration_s for w in routes]),
        "stair/lift walk duration s (min, max)": mm([w.duration_s for w in stairs]) if stairs else (),
        "route walk PDR length m (min, max)": mm([w.pdr_length_m for w in routes]),
        "PDR step length m (median of walks)": round(float(np.median([w.pdr_step_m for w in ws])), 2),
        "landmarks per route walk (min, max)": mm(marks_r),
        "distinct landmarks, shared by >= 2 routes": (len(lm_routes), sum(len(v) >= 2 for v in lm_routes.values())),
        "landmark extent along x across axes m": (round(along), round(across)),
        "landmark legs within 5 deg of the axes": round(legs_on_axes, 2),
        "route walks with a standstill >= 10 s": round(long_stand, 2),
        "standstills > 3 s per walk (median, max)": (
            float(np.median([len(w.standstills_s) for w in ws])),
            max(len(w.standstills_s) for w in ws),
        ),
        "standstill s (min, median, max)": (round(min(gaps), 1), round(float(np.median(gaps)), 1), round(max(gaps), 1)),
        "scans inside standstills (fraction)": round(sum(w.standstill_scans for w in ws) / max(n_scans, 1), 2),
        "walks scanning every ~2 s, ~4 s": (
            sum(1 for w in ws if w.scan_interval_s < 3.0),
            sum(1 for w in ws if w.scan_interval_s >= 3.0),
        ),
        "scan intervals within 10 % of the walk's median": round(float(np.median([w.scan_regular for w in ws])), 2),
        "readings per scan (p10, median, p90)": tuple(float(v) for v in np.percentile(readings, [10, 50, 90])),
        "RSS dBm (p5, median, p95)": tuple(float(v) for v in np.percentile(rss, [5, 50, 95])),
        "APs heard (all, per walk min, max)": (len({b for s in sessions for b in s.access_points}), min(aps), max(aps)),
        "APs heard in > 60 %, > 10 %, < 1 % of scans": ap_prevalence(survey, walks),
        "RSS of the 2 s phone minus the 4 s phone dB": round(phone_offset_db(survey, walks), 1),
        "one AP's squared RSS difference dB^2: standstill, two walks at one place": (
            round(d_still, 1), round(d_walks, 1)
        ),
        "  mean abs RSS difference dB, two walks at one place: same way, opposite ways": (
            round(d_same, 2), round(d_opposite, 2)
        ),
        "PDR rigid fit per walk m (mean, median, max)": (
            round(float(rigid.mean()), 2), round(float(np.median(rigid)), 2), round(float(rigid.max()), 2)
        ),
        "  route walks only (mean, median, max)": (
            round(float(rigid_r.mean()), 2), round(float(np.median(rigid_r)), 2), round(float(rigid_r.max()), 2)
        ),
        "PDR scale to fit the landmarks (mean, std)": (round(float(scale.mean()), 3), round(float(scale.std()), 3)),
        "leg heading error deg (std: total, shared by a route's walks, own)": (
            round(h_tot, 1), round(h_shared, 1), round(h_own, 1)
        ),
        "scans within 3 m of the route's other walks (min over routes)": round(min(ov[(a, a)] for a in names), 2),
        "scans within 3 m of another route (per route max; median, max)": (
            round(float(np.median(between)), 2), round(max(between), 2)
        ),
        "  route i -> route i+1": adjacent,
        "nearest fingerprint of another walk m (median, p90, within 5 m)": (
            round(fp_med, 1), round(fp_p90, 1), round(fp_5, 2)
        ),
    }
