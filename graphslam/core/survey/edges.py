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

from graphslam.core.progress import Task
from graphslam.core.survey.association import FingerprintNodes
from graphslam.core.radiomap.fingerprints import DistanceEngine

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


def _row_distances(fp: FingerprintNodes, a: NDArray[np.int64], b: NDArray[np.int64]) -> NDArray[np.float64]:
    """Eq. 9 between fingerprint rows a[i] and b[i] (element-wise pairs, not all pairs)."""
    v = fp.fingerprints.values
    va, vb = v[a], v[b]
    dot = np.asarray(va.multiply(vb).sum(axis=1)).ravel()
    common = np.asarray((va > 0).multiply(vb > 0).sum(axis=1)).ravel()
    sq = np.asarray(v.multiply(v).sum(axis=1)).ravel() + fp.fingerprints.extra_sq
    n = fp.fingerprints.heard.astype(float)
    den = n[a] + n[b] - common
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.sqrt(np.maximum(sq[a] + sq[b] - 2.0 * dot, 0.0) / den)
    return np.where(den > 0, d, np.inf)


def window_thresholds(fp: FingerprintNodes, window_steps: int) -> NDArray[np.float64]:
    """d_med(k) for every fingerprint: median distance to same-session fingerprints within +-L/2 steps.

    NaN where the window holds no other fingerprint (such a fingerprint proposes no edge).
    Plain eq. 9 over the union of APs, whatever the pair shares. Banded: O(F * window), so
    long walks cost no more per fingerprint than short ones.
    """
    n = len(fp)
    half = window_steps / 2.0
    # fingerprints are grouped by session and ordered by step inside it: the window of k is
    # a run of neighbours k-o .. k+o; o never exceeds the largest number of scans per window
    cols: list[NDArray] = []
    idx = np.arange(n)
    for o in range(1, n):
        j = idx + o
        ok = j < n
        ok[ok] &= (fp.session[j[ok]] == fp.session[idx[ok]]) & (fp.step[j[ok]] - fp.step[idx[ok]] <= half)
        if not ok.any():
            break
        d = np.full(n, np.nan)
        d[ok] = _row_distances(fp, idx[ok], j[ok])
        cols.append(d)  # k -> k + o
        back = np.full(n, np.nan)
        back[j[ok]] = d[ok]  # k + o -> k
        cols.append(back)
    if not cols:
        return np.full(n, np.nan)
    m = np.sort(np.column_stack(cols), axis=1)  # NaN sort last
    c = np.isfinite(m).sum(axis=1)
    lo = np.take_along_axis(m, np.maximum((c - 1) // 2, 0)[:, None], 1)[:, 0]
    hi = np.take_along_axis(m, np.maximum(c // 2, 0)[:, None], 1)[:, 0]
    return np.where(c > 0, (lo + hi) / 2.0, np.nan)


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
    t_s = (fp.t_ns - (fp.t_ns.min() if n else 0)) / 1e9
    # fingerprints are grouped by session: a session's columns are one contiguous range
    bounds = np.searchsorted(fp.session, np.arange(fp.session.max() + 2 if n else 1))
    m = max_per_fingerprint if max_per_fingerprint > 0 else n
    task = Task("edges", total=n, unit="fingerprints")
    for start, d, common in engine.iter_blocks(fp.fingerprints, min_common=min_common_aps, block_rows=block_rows):
        task.advance(len(d))
        rows = np.arange(start, start + len(d))
        ok = d < thresholds[rows][:, None]  # NaN threshold -> False
        ok[np.arange(len(rows)), rows] = False
        for s in np.unique(fp.session[rows]):
            r = np.flatnonzero(fp.session[rows] == s)
            c0, c1 = bounds[s], bounds[s + 1]
            near = (np.abs(t_s[rows[r]][:, None] - t_s[None, c0:c1]) < exclude_same_session_s) | (
                np.abs(fp.path_m[rows[r]][:, None] - fp.path_m[None, c0:c1]) < exclude_same_session_m
            )
            ok[r[:, None], np.arange(c0, c1)[None, :]] &= ~near
        # the candidates below threshold are few per row: rank those, not the whole block
        ri, ci = np.nonzero(ok)
        candidates += len(ri)
        dv = d[ri, ci]
        order = np.lexsort((dv, ri))
        ri, ci, dv = ri[order], ci[order], dv[order]
        first = np.searchsorted(ri, ri, side="left")
        keep = (np.arange(len(ri)) - first) < m
        out_i.append(rows[ri[keep]])
        out_j.append(ci[keep])
        out_d.append(dv[keep])
        out_c.append(common[ri[keep], ci[keep]])
    task.end()
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
