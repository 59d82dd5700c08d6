"""Placing walks from UWB ranges (never from ground truth): the start of the survey's LM.

A walk's dead reckoning drifts slowly (heading ~1 deg/min), so it is placed piecewise: one
rigid transform site <- dead reckoning per ``window_s`` window of the walk, fitted to the
ranges taken in that window.

- ``fit_rigid_ranges``: the rigid T minimising sum rho(|T(q_i) - c_i| - r_i) over the ranges
  r_i from antenna positions q_i (dead-reckoning frame) to points c_i (anchors, or another
  walker's placed antenna). For a fixed rotation the range equations are linear in
  (t_x, t_y, |t|^2) (|R q - c + t|^2 = r^2); 16 rotations seed a robust Gauss-Newton on
  (theta, t). rho is one-sided (NLOS ranges are only ever too long): Cauchy for a range longer
  than predicted, Huber for a shorter one. A fit is accepted when most ranges agree (RMS of the agreeing ones small) and no
  clearly different transform fits almost as well (a straight stretch of walk between two
  anchors has a mirror solution). With a single reference point the rotation is not
  observable: such a window keeps the rotation of the walk's nearest placed window and fits
  the translation only.
- ``place_windows``: windows seeing >= 2 anchors first; then, repeatedly, windows whose ranges
  reach anchors or already placed walkers; windows still unplaced in a placed walk copy the
  nearest placed window of that walk.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from graphslam.core.common.geometry import ransac_se2

N_ROTATIONS = 16
MIN_RANGES_FULL = 8  # a free rigid fit needs this many ranges ...
MIN_RANGES_TRANSLATION = 4  # ... a translation-only fit this many
ACCEPT_RMS_M = 0.6  # RMS of the agreeing ranges of an accepted fit (drift within a window included)
ACCEPT_INLIER_FRACTION = 0.6
AMBIGUITY_COST_RATIO = 1.5  # a different transform within this factor of the best cost: ambiguous
DISTINCT_M, DISTINCT_RAD = 1.0, np.radians(15.0)


@dataclass(frozen=True)
class RangeFit:
    T: NDArray[np.float64]  # (x, y, theta): site <- dead reckoning
    rms_m: float  # over the agreeing ranges
    inlier_fraction: float
    ambiguous: bool
    n: int

    def acceptable(self) -> bool:
        return (not self.ambiguous and self.rms_m <= ACCEPT_RMS_M and self.inlier_fraction >= ACCEPT_INLIER_FRACTION)


def _rot(th: float) -> NDArray:
    c, s = np.cos(th), np.sin(th)
    return np.array([[c, -s], [s, c]])


def _residuals(T: NDArray, q: NDArray, c: NDArray, r: NDArray) -> NDArray:
    return np.linalg.norm(q @ _rot(T[2]).T + T[:2] - c, axis=1) - r


def _gauss_newton(T: NDArray, q: NDArray, c: NDArray, r: NDArray, huber_m: float, free_rotation: bool, iters: int = 15) -> NDArray:
    T = T.astype(float).copy()
    for _ in range(iters):
        R = _rot(T[2])
        u = q @ R.T + T[:2] - c
        d = np.maximum(np.linalg.norm(u, axis=1), 1e-9)
        e = d - r
        n = u / d[:, None]
        w = _weights(e, huber_m)
        dR = np.array([[-R[1, 0], -R[0, 0]], [R[0, 0], -R[1, 0]]])  # d(R q)/d theta = dR q
        cols = [n[:, 0], n[:, 1]]
        if free_rotation:
            cols = [np.sum(n * (q @ dR.T), axis=1)] + cols
        J = np.column_stack(cols)
        JtW = J.T * w
        try:
            step = -np.linalg.solve(JtW @ J + 1e-9 * np.eye(J.shape[1]), JtW @ e)
        except np.linalg.LinAlgError:
            break
        if free_rotation:
            T[2] += step[0]
            T[:2] += step[1:]
        else:
            T[:2] += step
        if np.linalg.norm(step) < 1e-6:
            break
    T[2] = float(np.arctan2(np.sin(T[2]), np.cos(T[2])))
    return T


def _weights(e: NDArray, h: float) -> NDArray:
    """IRLS weights of the one-sided loss: Huber for ranges shorter than predicted (e > 0),
    Cauchy for longer ones (e < 0: what NLOS does)."""
    a = np.maximum(np.abs(e), 1e-12)
    return np.where(e >= 0, np.minimum(1.0, h / a), 1.0 / (1.0 + (e / h) ** 2))


def _robust_cost(e: NDArray, h: float) -> float:
    a = np.abs(e)
    huber = np.where(a <= h, 0.5 * a**2, h * (a - 0.5 * h))
    cauchy = 0.5 * h**2 * np.log1p((e / h) ** 2)
    return float(np.sum(np.where(e >= 0, huber, cauchy)))


def _linear_translation(th: float, q: NDArray, c: NDArray, r: NDArray) -> NDArray | None:
    u = q @ _rot(th).T - c
    A = np.column_stack([2.0 * u, np.ones(len(u))])
    b = r**2 - np.sum(u**2, axis=1)
    if np.linalg.matrix_rank(A, tol=1e-6) < 3:
        return None
    return np.linalg.lstsq(A, b, rcond=None)[0][:2]


def fit_rigid_ranges(
    q: NDArray, c: NDArray, r: NDArray, *, huber_m: float = 0.3, theta: float | None = None
) -> RangeFit | None:
    """Rigid (or, with ``theta`` given, translation-only) fit of antenna positions ``q`` (M, 2,
    dead-reckoning frame) to ranges ``r`` from points ``c`` (M, 2, site frame). None when the
    ranges cannot determine it (too few, degenerate)."""
    q, c, r = (np.asarray(v, float) for v in (q, c, r))
    free = theta is None
    if len(r) < (MIN_RANGES_FULL if free else MIN_RANGES_TRANSLATION):
        return None
    cands = []
    for th in (np.arange(N_ROTATIONS) * 2 * np.pi / N_ROTATIONS if free else [theta]):
        t = _linear_translation(float(th), q, c, r)
        if t is None:
            if free:
                continue
            t = np.mean(c, axis=0) - np.mean(q @ _rot(float(th)).T, axis=0)
        T = _gauss_newton(np.array([t[0], t[1], th]), q, c, r, huber_m, free)
        cands.append((_robust_cost(_residuals(T, q, c, r), huber_m), T))
    if not cands:
        return None
    cands.sort(key=lambda x: x[0])
    cost, T = cands[0]
    ambiguous = False
    for other_cost, To in cands[1:]:
        far = np.linalg.norm(To[:2] - T[:2]) > DISTINCT_M or abs(np.arctan2(np.sin(To[2] - T[2]), np.cos(To[2] - T[2]))) > DISTINCT_RAD
        if far and other_cost <= AMBIGUITY_COST_RATIO * cost + 1e-9:
            ambiguous = True
            break
    e = _residuals(T, q, c, r)
    inl = np.abs(e) < 3 * huber_m
    rms = float(np.sqrt(np.mean(e[inl] ** 2))) if inl.any() else float("inf")
    return RangeFit(T, rms, float(inl.mean()), ambiguous, len(r))


@dataclass(frozen=True, eq=False)
class RangeObservations:
    """Ranges for the placement, every position in its walk's dead-reckoning frame (m); times s."""

    a_walk: NDArray[np.int64]
    a_t: NDArray[np.float64]
    a_q: NDArray[np.float64]  # (Ma, 2) antenna position
    a_anchor: NDArray[np.int64]
    a_range: NDArray[np.float64]  # planar
    p_walk: NDArray[np.int64]  # (Mp, 2)
    p_t: NDArray[np.float64]
    p_qa: NDArray[np.float64]
    p_qb: NDArray[np.float64]
    p_range: NDArray[np.float64]


@dataclass
class WindowPlacement:
    """Per walk: window start times (s, from the walk's first step) and a transform per window
    (NaN rows: unplaced); ``method`` how the walk was placed ("" = not placed)."""

    window_s: float
    t0: NDArray[np.float64]  # (S,) first step time per walk (s)
    T: list[NDArray[np.float64]]  # per walk (W_s, 3)
    method: list[str] = field(default_factory=list)

    def window_of(self, s: int, t: NDArray) -> NDArray[np.int64]:
        return np.clip(((np.asarray(t) - self.t0[s]) // self.window_s).astype(np.int64), 0, len(self.T[s]) - 1)

    def placed(self, s: int) -> bool:
        return bool(np.isfinite(self.T[s][:, 0]).any())

    def transform_at(self, s: int, t: NDArray) -> NDArray:
        return self.T[s][self.window_of(s, t)]

    def apply(self, s: int, t: NDArray, xy: NDArray) -> NDArray:
        """Site positions of dead-reckoned points ``xy`` (K, 2) of walk ``s`` at times ``t``."""
        T = self.transform_at(s, t)
        c, sn = np.cos(T[:, 2]), np.sin(T[:, 2])
        return np.column_stack([c * xy[:, 0] - sn * xy[:, 1] + T[:, 0], sn * xy[:, 0] + c * xy[:, 1] + T[:, 1]])

    def fill(self, s: int) -> None:
        """Unplaced windows copy the nearest placed window of the walk."""
        T = self.T[s]
        ok = np.flatnonzero(np.isfinite(T[:, 0]))
        if len(ok) and len(ok) < len(T):
            near = ok[np.argmin(np.abs(np.arange(len(T))[:, None] - ok[None, :]), axis=1)]
            self.T[s] = T[near]


def place_windows(
    obs: RangeObservations,
    anchor_xy: NDArray,
    walk_span: NDArray,
    window_s: float,
    *,
    base: dict[int, NDArray] | None = None,
    huber_m: float = 0.3,
) -> WindowPlacement:
    """Window transforms for every walk the ranges can reach. ``walk_span`` (S, 2): first and
    last step time (s). ``base``: walks already placed (one rigid transform each), e.g. by WiFi
    registration when there are no anchors."""
    n_walks = len(walk_span)
    n_win = np.maximum(1, np.ceil((walk_span[:, 1] - walk_span[:, 0]) / window_s + 1e-9).astype(int))
    wp = WindowPlacement(window_s, walk_span[:, 0].astype(float), [np.full((k, 3), np.nan) for k in n_win],
                         [""] * n_walks)
    for s, T in (base or {}).items():
        wp.T[s][:] = T
        wp.method[s] = "registration"
    a_win = np.array([wp.window_of(int(s), np.array([t]))[0] for s, t in zip(obs.a_walk, obs.a_t)], np.int64)
    pa_win = np.array([wp.window_of(int(s), np.array([t]))[0] for s, t in zip(obs.p_walk[:, 0], obs.p_t)], np.int64)
    pb_win = np.array([wp.window_of(int(s), np.array([t]))[0] for s, t in zip(obs.p_walk[:, 1], obs.p_t)], np.int64)

    def refs(s: int, w: int) -> tuple[NDArray, NDArray, NDArray, int, int]:
        """(q, c, r, distinct reference points, distinct anchors) of walk s, window w, from anchors
        and placed walkers."""
        qa = obs.a_q[(obs.a_walk == s) & (a_win == w)]
        ia = (obs.a_walk == s) & (a_win == w)
        parts_q, parts_c, parts_r = [qa], [anchor_xy[obs.a_anchor[ia]]], [obs.a_range[ia]]
        n_refs = len(np.unique(obs.a_anchor[ia]))
        peers: set[int] = set()
        for side, other in ((0, 1), (1, 0)):
            win = pa_win if side == 0 else pb_win
            sel = np.flatnonzero((obs.p_walk[:, side] == s) & (win == w))
            if not len(sel):
                continue
            ob = obs.p_walk[sel, other]
            ok = np.array([wp.placed(int(b)) and np.isfinite(wp.transform_at(int(b), np.array([t]))[0, 0])
                           for b, t in zip(ob, obs.p_t[sel])], bool)
            sel, ob = sel[ok], ob[ok]
            if not len(sel):
                continue
            q_own = obs.p_qa[sel] if side == 0 else obs.p_qb[sel]
            q_oth = obs.p_qb[sel] if side == 0 else obs.p_qa[sel]
            c = np.vstack([wp.apply(int(b), np.array([t]), q[None, :]) for b, t, q in zip(ob, obs.p_t[sel], q_oth)])
            parts_q.append(q_own)
            parts_c.append(c)
            parts_r.append(obs.p_range[sel])
            peers |= set(ob.tolist())
        return np.vstack(parts_q), np.vstack(parts_c), np.concatenate(parts_r), n_refs + len(peers), n_refs

    # 1. windows that see two or more anchors; 2. repeatedly, anything the placed walks reach
    for rounds in range(6):
        progress = False
        for s in range(n_walks):
            if wp.method[s] == "registration":
                continue
            for w in range(n_win[s]):
                if np.isfinite(wp.T[s][w, 0]):
                    continue
                q, c, r, n_refs, n_anchors = refs(s, w)
                fit = None
                if n_refs >= 2:
                    fit = fit_rigid_ranges(q, c, r, huber_m=huber_m)
                elif n_refs == 1 and rounds > 0 and wp.placed(s):
                    placed_w = np.flatnonzero(np.isfinite(wp.T[s][:, 0]))
                    theta = float(wp.T[s][placed_w[np.argmin(np.abs(placed_w - w))], 2])
                    fit = fit_rigid_ranges(q, c, r, huber_m=huber_m, theta=theta)
                if fit is not None and fit.acceptable():
                    wp.T[s][w] = fit.T
                    wp.method[s] = wp.method[s] or ("anchors" if n_anchors >= 2 else "ranges")
                    progress = True
        if not progress and rounds > 0:
            break
    for s in range(n_walks):
        wp.fill(s)
    return wp


def place_by_wifi(
    wp: WindowPlacement,
    node_walk: NDArray[np.int64],
    node_t: NDArray[np.float64],
    node_xy: NDArray[np.float64],
    edge_a: NDArray[np.int64],
    edge_b: NDArray[np.int64],
    *,
    inlier_m: float = 6.0,
    min_inliers: int = 4,
    seed: int = 0,
) -> None:
    """Walks the ranges did not place, placed rigidly by their WiFi edges to placed walks (the
    registration's RANSAC, against the placed partners' positions); repeated while it helps."""
    rng = np.random.default_rng(seed)
    while True:
        placed = np.array([wp.placed(s) for s in range(len(wp.T))])
        progress = False
        for s in np.flatnonzero(~placed).tolist():
            own = np.concatenate([edge_a[node_walk[edge_a] == s], edge_b[node_walk[edge_b] == s]])
            oth = np.concatenate([edge_b[node_walk[edge_a] == s], edge_a[node_walk[edge_b] == s]])
            ok = placed[node_walk[oth]]
            own, oth = own[ok], oth[ok]
            if len(own) < min_inliers:
                continue
            p = np.vstack([wp.apply(int(node_walk[o]), node_t[o:o + 1], node_xy[o:o + 1]) for o in oth])
            T, inl = ransac_se2(p, node_xy[own], inlier_m=inlier_m, rng=rng)
            if inl.sum() >= min_inliers:
                wp.T[s][:] = T
                wp.method[s] = "wifi"
                progress = True
        if not progress:
            return

