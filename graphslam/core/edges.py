"""WiFi-vicinity edges (paper section III-B.2) from the median-window threshold.

For fingerprint k of a session, the threshold d_med(k) is the median eq.-9
distance between k and the other fingerprints of the same session whose steps lie
within L/2 steps of k's step. An edge (k, q) is proposed when d(k, q) < d_med(k),
except between fingerprints of the same session that are near in time or along
the walked path (they satisfy the vicinity trivially).

Deviation from the paper, measured in docs/benchmarks.md: of the pairs below the
threshold, each fingerprint keeps only its ``max_per_fingerprint`` most similar
partners. The paper keeps all of them; on long surveys that is ~50 edges per
fingerprint, which ties the graph into dense cliques (slow elimination) and admits
many pairs that are similar by chance.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from graphslam.core.association import FingerprintNodes
from graphslam.core.fingerprints import DistanceEngine

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class WifiEdges:
    """Undirected fingerprint pairs (i < j index into ``FingerprintNodes``) with their RSS distance."""

    i: NDArray[np.int64]
    j: NDArray[np.int64]
    rss_distance: NDArray[np.float64]
    common_aps: NDArray[np.int64]
    candidates: int  # pairs below threshold before the per-fingerprint cap

    def __len__(self) -> int:
        return len(self.i)


def window_thresholds(fp: FingerprintNodes, window_steps: int) -> NDArray[np.float64]:
    """d_med(k) for every fingerprint: median distance to same-session fingerprints within +-L/2 steps.

    NaN where the window holds no other fingerprint (such a fingerprint proposes no edge).
    Plain eq. 9 over the union of APs, whatever the pair shares.
    """
    thr = np.full(len(fp), np.nan)
    half = window_steps / 2.0
    for s in np.unique(fp.session):
        idx = np.flatnonzero(fp.session == s)  # ordered by step (association keeps scan order)
        sub = fp.fingerprints.rows(idx)
        d, _ = DistanceEngine(sub).block(sub, min_common=0)
        steps = fp.step[idx].astype(float)
        in_win = np.abs(steps[:, None] - steps[None, :]) <= half
        np.fill_diagonal(in_win, False)
        d = np.where(in_win & np.isfinite(d), d, np.nan)
        has = in_win.any(axis=1) & np.isfinite(d).any(axis=1)
        if has.any():
            thr[idx[has]] = np.nanmedian(d[has], axis=1)
    return thr


def propose_edges(
    fp: FingerprintNodes,
    thresholds: NDArray[np.float64],
    *,
    exclude_same_session_s: float,
    exclude_same_session_m: float,
    max_per_fingerprint: int,
    min_common_aps: int,
    block_rows: int | None = None,
) -> WifiEdges:
    """Pairs below each fingerprint's threshold, capped per fingerprint, symmetrised.

    Computed in row blocks: memory is ``block_rows * len(fp)``, never N x N.
    """
    n = len(fp)
    engine = DistanceEngine(fp.fingerprints)
    out_i, out_j, out_d, out_c = [], [], [], []
    candidates = 0
    t_s = fp.t_ns / 1e9
    for start, d, common in engine.iter_blocks(fp.fingerprints, min_common=min_common_aps, block_rows=block_rows):
        rows = np.arange(start, start + len(d))
        thr = thresholds[rows][:, None]
        ok = d < thr  # NaN threshold -> False
        same = fp.session[rows][:, None] == fp.session[None, :]
        near = (np.abs(t_s[rows][:, None] - t_s[None, :]) < exclude_same_session_s) | (
            np.abs(fp.path_m[rows][:, None] - fp.path_m[None, :]) < exclude_same_session_m
        )
        ok &= ~(same & near)
        ok[np.arange(len(rows)), rows] = False
        candidates += int(ok.sum())
        dm = np.where(ok, d, np.inf)
        m = min(max_per_fingerprint, n - 1) if max_per_fingerprint > 0 else n - 1
        if m <= 0:
            continue
        part = np.argpartition(dm, m - 1, axis=1)[:, :m] if m < n else np.tile(np.arange(n), (len(rows), 1))
        r = np.repeat(rows, part.shape[1])
        c = part.ravel()
        dv = dm[np.repeat(np.arange(len(rows)), part.shape[1]), c]
        keep = np.isfinite(dv)
        out_i.append(r[keep])
        out_j.append(c[keep])
        out_d.append(dv[keep])
        out_c.append(common[np.repeat(np.arange(len(rows)), part.shape[1]), c][keep])
    if not out_i:
        z = np.zeros(0, np.int64)
        return WifiEdges(z, z, np.zeros(0), z, candidates)
    i = np.concatenate(out_i)
    j = np.concatenate(out_j)
    dd = np.concatenate(out_d)
    cc = np.concatenate(out_c).astype(np.int64)
    a, b = np.minimum(i, j), np.maximum(i, j)
    key = a * n + b
    _, first = np.unique(key, return_index=True)
    log.info("WiFi edges: %d candidates below threshold, %d kept", candidates // 1, len(first))
    return WifiEdges(a[first], b[first], dd[first], cc[first], candidates)
