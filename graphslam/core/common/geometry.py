"""Rigid 2-D transforms T = (x, y, theta): apply, compose, least-squares and RANSAC fits; tracks
interpolated in time. Pure numpy; metres, radians, nanoseconds."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from graphslam.core.types import PoseTrack


def se2_apply(T: NDArray, xy: NDArray) -> NDArray:
    c, s = np.cos(T[2]), np.sin(T[2])
    return np.column_stack([c * xy[:, 0] - s * xy[:, 1] + T[0], s * xy[:, 0] + c * xy[:, 1] + T[1]])


def se2_apply_poses(T: NDArray, xyh: NDArray) -> NDArray:
    """Poses (x, y, heading) moved by the rigid transform ``T``."""
    h = xyh[:, 2] + T[2]
    return np.column_stack([se2_apply(T, xyh[:, :2]), np.pi - np.mod(np.pi - h, 2.0 * np.pi)])


def se2_compose(a: NDArray, b: NDArray) -> NDArray:
    c, s = np.cos(a[2]), np.sin(a[2])
    return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], np.arctan2(np.sin(a[2] + b[2]), np.cos(a[2] + b[2]))])


def fit_se2(src: NDArray, dst: NDArray, w: NDArray | None = None) -> NDArray:
    """Least-squares rigid transform T (x, y, theta) with dst ~ T(src) (2-D Kabsch)."""
    w = np.ones(len(src)) if w is None else w
    ws = w.sum()
    ms, md = (w[:, None] * src).sum(0) / ws, (w[:, None] * dst).sum(0) / ws
    a, b = src - ms, dst - md
    sxx = (w * (a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1])).sum()
    sxy = (w * (a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])).sum()
    th = np.arctan2(sxy, sxx)
    c, s = np.cos(th), np.sin(th)
    t = md - np.array([c * ms[0] - s * ms[1], s * ms[0] + c * ms[1]])
    return np.array([t[0], t[1], th])


def ransac_se2(
    p: NDArray, q: NDArray, *, inlier_m: float, rng: np.random.Generator, hypotheses: int = 256, min_span_m: float = 3.0
) -> tuple[NDArray, NDArray[np.bool_]]:
    """Rigid T with p ~ T(q) maximising inliers; (T, inlier mask). Vectorised over hypotheses."""
    n = len(p)
    if n < 2:
        return np.zeros(3), np.zeros(n, bool)
    a = rng.integers(0, n, hypotheses)
    b = rng.integers(0, n, hypotheses)
    dp, dq = p[b] - p[a], q[b] - q[a]
    lp, lq = np.linalg.norm(dp, axis=1), np.linalg.norm(dq, axis=1)
    good = (a != b) & (lq > min_span_m) & (np.abs(lp - lq) < inlier_m)
    if not good.any():
        return np.zeros(3), np.zeros(n, bool)
    a, b, dp, dq = a[good], b[good], dp[good], dq[good]
    th = np.arctan2(dp[:, 1], dp[:, 0]) - np.arctan2(dq[:, 1], dq[:, 0])
    c, s = np.cos(th), np.sin(th)
    mq = (q[a] + q[b]) / 2
    mp = (p[a] + p[b]) / 2
    tx = mp[:, 0] - (c * mq[:, 0] - s * mq[:, 1])
    ty = mp[:, 1] - (s * mq[:, 0] + c * mq[:, 1])
    # residuals of every correspondence under every hypothesis: (H, n)
    px = c[:, None] * q[None, :, 0] - s[:, None] * q[None, :, 1] + tx[:, None]
    py = s[:, None] * q[None, :, 0] + c[:, None] * q[None, :, 1] + ty[:, None]
    r = np.hypot(px - p[None, :, 0], py - p[None, :, 1])
    counts = (r < inlier_m).sum(axis=1)
    best = int(np.argmax(counts))
    inl = r[best] < inlier_m
    for _ in range(3):  # refine on inliers, re-select
        if inl.sum() < 2:
            break
        T = fit_se2(q[inl], p[inl])
        inl_new = np.linalg.norm(se2_apply(T, q) - p, axis=1) < inlier_m
        if (inl_new == inl).all():
            break
        inl = inl_new
    T = fit_se2(q[inl], p[inl]) if inl.sum() >= 2 else np.zeros(3)
    return T, inl


def interpolate_xy(track: PoseTrack, t_ns: NDArray) -> NDArray:
    t = track.t_ns.astype(float)
    return np.column_stack([np.interp(t_ns, t, track.xy[:, 0]), np.interp(t_ns, t, track.xy[:, 1])])
