"""WiFi-vicinity edges (paper section III-B.2) from the median-window threshold.

For fingerprint k of a session, the threshold d_med(k) is the median eq.-9
distance between k and the other fingerprints of the same session whose steps lie
within L/2 steps of k's step. An edge (k, q) is proposed when d(k, q) < d_med(k),
except between fingerprints of the same session that are near in time or along
the walked path (they satisfy the vicinity trivially).

Deviation from the paper (docs/method.md): of the pairs below the
threshold, each fingerprint keeps only its ``max_per_fingerprint`` most similar
partners. The paper keeps all of them; on long surveys that is ~50 edges per
fingerprint, which ties the graph into dense cliques (slow elimination) and admits
many pairs that are similar by chance.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Iterator

import numpy as np
from numpy.typing import NDArray

from graphslam.core.progress import Task
from graphslam.core.radiomap.fingerprints import DistanceEngine
from graphslam.core.survey.association import FingerprintNodes

log = logging.getLogger(__name__)

# Lloyd steps of the edge index's k-means: the clusters only choose where to look, and the
# index is built for one search; 8 steps kept the recall of 25 at a third of the build
# (paper sizes 1 and 4).
IVF_KMEANS_ITERATIONS = 8


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
    candidates: str = "exact",
    ivf_neighbours: int = 32,
    ivf_probes: int = 8,
) -> WifiEdges:
    """Pairs below each fingerprint's threshold, capped per fingerprint, symmetrised.

    ``candidates``: where the pairs compared with the threshold come from.
     * ``exact``: every pair, in row blocks (memory ``block_rows * len(fp)``, never N x N;
       time O(N^2)).
     * ``ivf``: each fingerprint's ``ivf_neighbours`` nearest by eq. 9 among the ``ivf_probes``
       nearest clusters of an IVF index (``graphslam.core.radiomap.ivf``; O(N^1.5)). The same
       threshold, exclusions and cap follow, so an edge is missed only when a partner the
       exact path keeps is not among those neighbours (its recall: lab/scripts/edge_recall.py).
       ``WifiEdges.candidates`` then counts the pairs below threshold among the neighbours.
    """
    n = len(fp)
    m = max_per_fingerprint if max_per_fingerprint > 0 else n
    t_s = (fp.t_ns - (fp.t_ns.min() if n else 0)) / 1e9
    if candidates == "ivf":
        blocks = _ivf_candidates(fp, min_common_aps, ivf_neighbours, ivf_probes, block_rows)
    elif candidates == "exact":
        blocks = _exact_candidates(fp, thresholds, min_common_aps, block_rows)
    else:
        raise ValueError(f"edge candidates must be 'exact' or 'ivf', got {candidates!r}")
    out_i, out_j, out_d = [], [], []
    n_candidates = 0
    for ri, ci, dv in blocks:
        ok = (dv < thresholds[ri]) & (ri != ci)  # NaN threshold -> False
        same = fp.session[ri] == fp.session[ci]
        near = (np.abs(t_s[ri] - t_s[ci]) < exclude_same_session_s) | (
            np.abs(fp.path_m[ri] - fp.path_m[ci]) < exclude_same_session_m
        )
        ok &= ~(same & near)
        ri, ci, dv = ri[ok], ci[ok], dv[ok]
        n_candidates += len(ri)
        # the candidates below threshold are few per row: rank those, not the whole block
        ri, ci, dv = nearest_per_row(ri, ci, dv, m)
        out_i.append(ri)
        out_j.append(ci)
        out_d.append(dv)
    if not out_i or not sum(len(x) for x in out_i):
        z = np.zeros(0, np.int64)
        return WifiEdges(z, z, np.zeros(0), z, n_candidates)
    i = np.concatenate(out_i)
    j = np.concatenate(out_j)
    dd = np.concatenate(out_d)
    a, b = np.minimum(i, j), np.maximum(i, j)
    key = a * n + b
    _, first = np.unique(key, return_index=True)
    a, b = a[first], b[first]
    log.info("WiFi edges (%s): %d candidates below threshold, %d kept", candidates, n_candidates, len(first))
    return WifiEdges(a, b, dd[first], _common_aps(fp, a, b), n_candidates)


def nearest_per_row(
    i: NDArray[np.int64], j: NDArray[np.int64], d: NDArray[np.float64], m: int
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]:
    """Of the directed pairs ``(i, j)`` at distance ``d``, each row's ``m`` nearest (ties: lower ``j``
    first), ordered by row, distance, column.

    Why not one sort of every pair: the pairs are ~30 per row and ``m`` is a few. ``m`` rounds of
    per-row minima first keep the pairs at or below each row's ``m``-th smallest distance (ties
    included), and only those are sorted (800k pairs, m = 3: 0.05 s instead of 0.4 s).
    """
    if len(i) == 0 or m <= 0:
        z = np.zeros(0, np.int64)
        return z, z, np.zeros(0, np.float64)
    rows = int(i.max()) + 1
    active = np.ones(len(i), bool)
    near = np.zeros(len(i), bool)
    left = np.full(rows, m, np.int64)  # pairs each row still needs
    for _ in range(m):
        low = np.full(rows, np.inf)
        np.minimum.at(low, i[active], d[active])
        hit = active & (d == low[i])
        near |= hit
        left -= np.bincount(i[hit], minlength=rows)
        active &= ~hit & (left[i] > 0)
        if not active.any():
            break
    k = np.flatnonzero(near)
    i, j, d = i[k], j[k], d[k]
    order = np.lexsort((j, d, i))
    i, j, d = i[order], j[order], d[order]
    keep = (np.arange(len(i)) - np.searchsorted(i, i, side="left")) < m
    return i[keep], j[keep], d[keep]


def _exact_candidates(
    fp: FingerprintNodes, thresholds: NDArray[np.float64], min_common: int, block_rows: int | None
) -> Iterator[tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]]:
    """(row, column, distance) of every pair below the row's threshold, one row block at a time."""
    engine = DistanceEngine(fp.fingerprints)
    n = len(fp)
    rows = engine.rows_per_block(block_rows)
    with Task("edges", total=n, unit="fingerprints") as task:
        for start in range(0, n, rows):
            stop = min(n, start + rows)
            ri, ci, d = engine.pairs_below(fp.fingerprints.rows(slice(start, stop)), thresholds[start:stop],
                                           min_common=min_common)
            task.advance(stop - start)
            yield ri + start, ci, d


def _ivf_candidates(
    fp: FingerprintNodes, min_common: int, k: int, probes: int, block_rows: int | None
) -> Iterator[tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]]:
    """(row, column, distance) of each fingerprint's k approximate nearest neighbours (self included)."""
    from threadpoolctl import threadpool_limits

    from graphslam.core.radiomap.ivf import IvfIndex

    n = len(fp)
    if n == 0:
        return
    rows = max(256, 4 * (block_rows or 1024))  # the search buffer is rows x probes x largest cluster
    # one BLAS thread: the index is hundreds of tiny GEMMs, which OpenBLAS's thread hand-off
    # made 4x slower (paper size 4, 2 busy cores); scoped to this search only
    with threadpool_limits(limits=1, user_api="blas"), Task("edges", n, "fingerprints", info="IVF index") as task:
        index = IvfIndex(fp.fingerprints, iterations=IVF_KMEANS_ITERATIONS)
        found = []
        for s in range(0, n, rows):
            found.append(index.search(fp.fingerprints.rows(slice(s, s + rows)), k=k + 1, probes=probes, min_common=min_common))
            task.advance(min(rows, n - s), info="IVF search")
    for b, (idx, dist) in enumerate(found):
        ok = idx >= 0
        ri = np.nonzero(ok)[0] + b * rows
        yield ri.astype(np.int64), idx[ok], dist[ok]


def _common_aps(fp: FingerprintNodes, a: NDArray[np.int64], b: NDArray[np.int64]) -> NDArray[np.int64]:
    v = fp.fingerprints.values
    return np.asarray((v[a] > 0).multiply(v[b] > 0).sum(axis=1)).ravel().astype(np.int64)
