"""Chain compression: the IMU chain between two fingerprint nodes, as one factor.

Only step poses that carry a fingerprint (plus each walk's first and last step)
touch WiFi edges; the steps between them form plain chains. Eliminating a chain
node exactly (to first order) gives one between factor whose measurement is the
composition of the measured steps and whose covariance is the steps' covariances
moved to the segment's end by the adjoint map:

    U_ab = u_{a+1} ... u_b,   Sigma_ab = sum_k Ad(V_k^{-1}) Sigma_u Ad(V_k^{-1})^T,
    V_k = u_{k+1} ... u_b  (right-perturbation convention, as GTSAM's Pose2).

On the `paper` survey this keeps ~28 % of the poses and halves the cost of an LM
iteration. The dropped steps are restored afterwards by
re-integrating their measured steps from the optimised segment start and spreading
the segment's end mismatch linearly over it (a few millimetres on ~4-step segments).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from graphslam.core.types import wrap_angle


@dataclass(frozen=True, eq=False)
class CompressedChains:
    kept: NDArray[np.int64]  # (K,) global node ids kept as variables, ascending
    pairs: NDArray[np.int64]  # (M, 2) consecutive kept nodes of one walk
    measured: NDArray[np.float64]  # (M, 3) U_ab as (x, y, theta)
    covariance: NDArray[np.float64]  # (M, 3, 3)


def relative(xyh_a: NDArray, xyh_b: NDArray) -> NDArray:
    """Row-wise a^{-1} b for (N, 3) poses."""
    d = xyh_b[:, :2] - xyh_a[:, :2]
    c, s = np.cos(xyh_a[:, 2]), np.sin(xyh_a[:, 2])
    return np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], wrap_angle(xyh_b[:, 2] - xyh_a[:, 2])])


def adjoint(xyh: NDArray) -> NDArray:
    """(N, 3, 3) adjoint matrices of Pose2 (GTSAM's convention: [R, [y, -x]^T; 0, 1])."""
    c, s = np.cos(xyh[:, 2]), np.sin(xyh[:, 2])
    A = np.zeros((len(xyh), 3, 3))
    A[:, 0, 0], A[:, 0, 1], A[:, 0, 2] = c, -s, xyh[:, 1]
    A[:, 1, 0], A[:, 1, 1], A[:, 1, 2] = s, c, -xyh[:, 0]
    A[:, 2, 2] = 1.0
    return A


def compress(
    dr_xyh: NDArray, offsets: NDArray, keep: NDArray[np.bool_], included: NDArray[np.bool_], step_cov: NDArray
) -> CompressedChains:
    """Segments between consecutive kept nodes of every included walk.

    ``dr_xyh``: (N, 3) dead-reckoned poses (each walk in its own frame); ``keep``: (N,) nodes
    that must stay variables (first and last of every walk are added).
    """
    keep = keep.copy()
    walk_of = np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))
    inc_node = included[walk_of]
    keep[offsets[:-1][np.diff(offsets) > 0]] = True
    keep[offsets[1:][np.diff(offsets) > 0] - 1] = True
    keep &= inc_node
    kept = np.flatnonzero(keep)
    same = walk_of[kept[:-1]] == walk_of[kept[1:]]
    a, b = kept[:-1][same], kept[1:][same]
    measured = relative(dr_xyh[a], dr_xyh[b])
    # every non-first step k of an included walk belongs to the segment ending at the next kept node
    seg_end_idx = np.searchsorted(kept, np.arange(len(dr_xyh)), side="left")  # index into kept of node >= k
    steps = np.flatnonzero(inc_node & (np.arange(len(dr_xyh)) != offsets[walk_of]))
    end = kept[np.minimum(seg_end_idx[steps], len(kept) - 1)]
    V_inv = relative(dr_xyh[end], dr_xyh[steps])  # b^{-1} k = V_k^{-1}
    Ad = adjoint(V_inv)
    contrib = Ad @ step_cov @ np.transpose(Ad, (0, 2, 1))
    # sum contributions per segment end (segment ids follow kept order)
    seg = np.searchsorted(b, end)  # segment ends are ascending (kept order)
    cov = np.zeros((len(a), 3, 3))
    np.add.at(cov, seg, contrib)
    return CompressedChains(kept, np.column_stack([a, b]).astype(np.int64), measured, cov)


def expand(opt_xyh: NDArray, dr_xyh: NDArray, chains: CompressedChains) -> NDArray:
    """Fill the dropped steps of ``opt_xyh`` (kept rows optimised, others NaN) from the dead reckoning.

    Vectorised over all dropped steps at once: step k of segment (a, b) is a's optimised pose
    composed with the dead-reckoned a^-1 k, plus the fraction (k - a) / (b - a) of the
    segment's end mismatch."""
    out = opt_xyh.copy()
    pairs = chains.pairs[chains.pairs[:, 1] - chains.pairs[:, 0] >= 2]
    if not len(pairs):
        return out
    n_inner = pairs[:, 1] - pairs[:, 0] - 1
    seg = np.repeat(np.arange(len(pairs)), n_inner)
    a, b = pairs[seg, 0], pairs[seg, 1]
    k = a + 1 + (np.arange(len(seg)) - np.repeat(np.cumsum(n_inner) - n_inner, n_inner))
    rel = relative(dr_xyh[a], dr_xyh[k])  # a^{-1} k from dead reckoning
    rel_b = relative(dr_xyh[pairs[:, 0]], dr_xyh[pairs[:, 1]])  # a^{-1} b per segment
    Ta = out[pairs[:, 0]]
    c, s = np.cos(Ta[:, 2]), np.sin(Ta[:, 2])
    pb_xy = Ta[:, :2] + np.column_stack([c * rel_b[:, 0] - s * rel_b[:, 1], s * rel_b[:, 0] + c * rel_b[:, 1]])
    corr_xy = out[pairs[:, 1], :2] - pb_xy
    corr_h = wrap_angle(out[pairs[:, 1], 2] - (Ta[:, 2] + rel_b[:, 2]))
    cs, ss = c[seg], s[seg]
    pred_xy = Ta[seg, :2] + np.column_stack([cs * rel[:, 0] - ss * rel[:, 1], ss * rel[:, 0] + cs * rel[:, 1]])
    f = (k - a) / (b - a)
    out[k, :2] = pred_xy + f[:, None] * corr_xy[seg]
    out[k, 2] = wrap_angle(Ta[seg, 2] + rel[:, 2] + f * corr_h[seg])
    return out
