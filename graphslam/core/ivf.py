"""Inverted-file (IVF) approximate search for eq. 9 kNN.

Exact kNN scores every query against every reference (UJIIndoorLoc: ~40 GFlop per
1,000 queries). The IVF index partitions the references once, by k-means on their
dense shifted-RSS vectors, and scores a query only against the members of the
``probes`` clusters whose centroids are nearest to it (Euclidean, one GEMM). Inside
the probed clusters eq. 9 is evaluated *exactly*, with the same formula as
``DistanceEngine``; the only approximation is which references are looked at. With
``probes == clusters`` the answer is the exact search's (tested).

Layout, chosen so that a batch costs a loop over clusters only (never over queries or
references): per cluster, its members (ascending map rows), the union of the APs
they heard (``cols``: a cluster is a place, so this is a small subset of the AP
index) and dense (|cols|, n_c) float64 RSS / float32 heard matrices. For a batch,
queries are grouped by probed cluster; each group is one small GEMM for the dot
products and one for the shared-AP counts over the cluster's columns (APs outside
them add nothing to either), then eq. 9 and a per-cluster top k. The P partial top-k
lists of every query are merged with one lexsort.

Ties follow the exact path: equal distances are ordered by map row, so with all
clusters probed the neighbours are the same references in the same order.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
from numpy.typing import NDArray
from scipy import sparse

from graphslam.core.fingerprints import FingerprintMatrix
from graphslam.errors import ConfigError

# Dense float32 copy of the references for k-means only when it stays below this many cells
# (~256 MB); bigger maps cluster on the sparse matrix (slower, same result up to rounding).
KMEANS_DENSE_MAX_CELLS = 64_000_000
# Rows per assignment block: bounds the (rows, C) distance matrix of a k-means step.
ASSIGN_BLOCK_CELLS = 8_000_000
DEFAULT_KMEANS_ITERATIONS = 25
DEFAULT_SEED = 0


def limit_blas_threads(n: int = 1) -> bool:
    """Set the process's BLAS thread count (``threadpoolctl``); ``False`` if unavailable.

    Why: an IVF search is hundreds of tiny GEMMs, and OpenBLAS's thread hand-off made them
    ~15x slower on a 2-core machine (and far worse when two searches overlap, or when the
    count is toggled per call). A process-wide setting, so it is the caller's decision:
    ``graphslam serve`` calls this once at start-up; the service parallelises over requests."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - optional speed-up
        return False
    threadpool_limits(limits=n, user_api="blas")
    return True


def default_clusters(n_refs: int) -> int:
    """~2 sqrt(N) clusters: clusters of ~sqrt(N)/2 references (UJIIndoorLoc: 282 of ~71)."""
    return max(1, int(round(2.0 * math.sqrt(max(1, n_refs)))))


def _sq_rows(x: NDArray | sparse.csr_matrix) -> NDArray[np.float32]:
    if sparse.issparse(x):
        return np.asarray(x.multiply(x).sum(axis=1), dtype=np.float32).ravel()
    return np.einsum("ij,ij->i", x, x).astype(np.float32)


def _assign(x: NDArray | sparse.csr_matrix, cent: NDArray[np.float32]) -> tuple[NDArray[np.int64], NDArray[np.float32]]:
    """Nearest centroid of every row and its squared distance (up to the row's own |x|^2)."""
    n = x.shape[0]
    c_sq = np.einsum("ij,ij->i", cent, cent)
    rows = max(1, ASSIGN_BLOCK_CELLS // max(1, len(cent)))
    labels = np.empty(n, np.int64)
    best = np.empty(n, np.float32)
    cT = np.ascontiguousarray(cent.T)
    for s in range(0, n, rows):
        g = np.asarray(x[s : s + rows] @ cT, dtype=np.float32)
        g *= -2.0
        g += c_sq[None, :]
        lab = np.argmin(g, axis=1)
        labels[s : s + rows] = lab
        best[s : s + rows] = g[np.arange(len(lab)), lab]
    return labels, best


def kmeans(
    x: NDArray | sparse.csr_matrix, n_clusters: int, *, seed: int = DEFAULT_SEED,
    iterations: int = DEFAULT_KMEANS_ITERATIONS,
) -> tuple[NDArray[np.float32], NDArray[np.int64]]:
    """Deterministic k-means (k-means++ seeding with ``seed``, then Lloyd steps until the
    assignment is stable or ``iterations``). Returns (centroids (C', A) float32, labels (N,)),
    C' <= ``n_clusters``: clusters left empty (e.g. fewer distinct rows than clusters) are dropped
    and labels renumbered densely."""
    n = x.shape[0]
    if n == 0:
        return np.zeros((0, x.shape[1]), np.float32), np.zeros(0, np.int64)
    rng = np.random.default_rng(seed)
    x_sq = _sq_rows(x)
    # k-means++: each new centre drawn with probability ~ squared distance to the nearest one.
    # Why not random rows: UJIIndoorLoc has dense spots (many scans at one place) that would
    # get most of the centres.
    centres = [int(rng.integers(n))]
    d2 = np.full(n, np.inf, np.float32)
    for _ in range(1, min(n_clusters, n) + 1):
        c = x[centres[-1]]
        c = c.toarray().ravel() if sparse.issparse(c) else np.asarray(c, np.float32)
        dc = x_sq - 2.0 * np.asarray(x @ c, np.float32).ravel() + float(c @ c)
        np.minimum(d2, np.maximum(dc, 0.0), out=d2)
        if len(centres) == min(n_clusters, n):
            break
        total = float(d2.sum(dtype=np.float64))
        if total <= 0.0:  # every row coincides with a centre already
            break
        p = d2.astype(np.float64) / total
        centres.append(int(rng.choice(n, p=p)))
    cent = x[np.array(centres)]
    cent = np.asarray(cent.toarray() if sparse.issparse(cent) else cent, np.float32)
    labels = np.full(n, -1, np.int64)
    for _ in range(max(1, iterations)):
        new, _ = _assign(x, cent)
        if np.array_equal(new, labels):
            break
        labels = new
        counts = np.bincount(labels, minlength=len(cent))
        # Sums per cluster as one sparse (C, N) indicator product: no loop over clusters.
        ind = sparse.csr_matrix((np.ones(n, np.float32), (labels, np.arange(n))), shape=(len(cent), n))
        sums = ind @ x
        sums = np.asarray(sums.toarray() if sparse.issparse(sums) else sums, np.float32)
        nz = counts > 0
        cent[nz] = sums[nz] / counts[nz, None].astype(np.float32)  # empty clusters keep their centre
    labels, _ = _assign(x, cent)
    used = np.unique(labels)
    remap = np.full(len(cent), -1, np.int64)
    remap[used] = np.arange(len(used))
    return np.ascontiguousarray(cent[used]), remap[labels]


@dataclass(frozen=True, eq=False)
class _Cluster:
    members: NDArray[np.int64]  # map rows, ascending (ties resolve by map row, as in the exact path)
    cols: NDArray[np.int64]  # APs heard by at least one member
    acols: NDArray[np.int64]  # cols + the two augmented query columns (|q|^2, 1)
    aT: NDArray[np.float64]  # (|cols| + 2, n_c): [-2 v; 1; |v|^2] so that [q, |q|^2, 1] @ aT = numerator
    bT: NDArray[np.float32]  # (|cols|, n_c) 1 where heard
    ref_n: NDArray[np.float64]  # (n_c,) APs heard
    arange: NDArray[np.int64]  # 0 .. n_c - 1, for scattering into the candidate buffer


class IvfIndex:
    """k-means inverted file over a reference ``FingerprintMatrix``. Read-only after construction
    (thread-safe). ``clusters``: requested C (``None``: ``default_clusters(N)``); fewer may remain
    (``n_clusters``) when the references have fewer distinct fingerprints."""

    def __init__(
        self, ref: FingerprintMatrix, *, clusters: int | None = None, seed: int = DEFAULT_SEED,
        iterations: int = DEFAULT_KMEANS_ITERATIONS,
    ) -> None:
        n = len(ref)
        c_req = default_clusters(n) if clusters is None else clusters
        if isinstance(c_req, bool) or not isinstance(c_req, int) or c_req < 1:
            raise ConfigError(f"IVF: clusters must be an integer >= 1, got {clusters!r}")
        self.ref = ref
        self.seed = seed
        v = ref.values
        x: NDArray | sparse.csr_matrix
        if n * ref.n_aps <= KMEANS_DENSE_MAX_CELLS:
            x = v.toarray().astype(np.float32)
        else:
            x = v.astype(np.float32)
        self.centroids, self.labels = kmeans(x, min(c_req, max(1, n)), seed=seed, iterations=iterations)
        self.centroids_T = np.ascontiguousarray(self.centroids.T)
        self.centroid_sq = np.einsum("ij,ij->i", self.centroids, self.centroids)
        # Same norms / counts as DistanceEngine, so distances agree with the exact path.
        ref_sq = np.asarray(v.multiply(v).sum(axis=1)).ravel() + ref.extra_sq
        ref_n = ref.heard.astype(np.float64)
        order = np.argsort(self.labels, kind="stable")  # stable: members stay in ascending map rows
        bounds = np.searchsorted(self.labels[order], np.arange(len(self.centroids) + 1))
        self.clusters: list[_Cluster] = []
        for c in range(len(self.centroids)):
            mem = order[bounds[c] : bounds[c + 1]]
            sub = v[mem]
            cols = np.unique(sub.indices).astype(np.int64)
            dense = sub[:, cols].toarray()
            a_t = np.empty((len(cols) + 2, len(mem)))
            a_t[:-2] = -2.0 * dense.T
            a_t[-2] = 1.0
            a_t[-1] = ref_sq[mem]
            self.clusters.append(
                _Cluster(
                    members=mem,
                    cols=cols,
                    acols=np.concatenate([cols, [ref.n_aps, ref.n_aps + 1]]),
                    aT=a_t,
                    bT=np.ascontiguousarray((dense.T > 0).astype(np.float32)),
                    ref_n=ref_n[mem],
                    arange=np.arange(len(mem)),
                )
            )
        self.sizes = np.array([len(c.members) for c in self.clusters], np.int64)
        self.starts = np.concatenate([[0], np.cumsum(self.sizes)[:-1]]).astype(np.int64)
        self.members_flat = order.astype(np.int64)  # cluster after cluster, as ``starts`` indexes

    @property
    def n_clusters(self) -> int:
        return len(self.clusters)

    def probe(self, q: FingerprintMatrix, probes: int) -> NDArray[np.int64]:
        """(Q, P) clusters to search per query: the P nearest centroids (Euclidean)."""
        c = self.n_clusters
        p = min(probes, c)
        if p >= c:
            return np.broadcast_to(np.arange(c), (len(q), c)).copy()
        # Sparse query rows (a few dozen APs) times dense centroids: ~25x fewer flops than dense.
        g = np.asarray(q.values.astype(np.float32) @ self.centroids_T, dtype=np.float32)
        g *= -2.0
        g += self.centroid_sq[None, :]  # |q|^2 is the same for every centroid of a row
        return np.argpartition(g, p - 1, axis=1)[:, :p].astype(np.int64)

    def search(
        self, q: FingerprintMatrix, *, k: int, probes: int, min_common: int = 1
    ) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """(Q, k) map rows and eq. 9 distances of the k nearest references among the probed
        clusters, nearest first, ties by map row; -1 / inf padded (as ``knn._nearest``)."""
        m = len(q)
        if m == 0 or self.n_clusters == 0:
            return np.full((m, k), -1, np.int64), np.full((m, k), np.inf)
        return self._search(q, k, probes, min_common)

    def _search(
        self, q: FingerprintMatrix, k: int, probes: int, min_common: int
    ) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        m = len(q)
        qd = q.values.toarray()
        q_sq = np.asarray(q.values.multiply(q.values).sum(axis=1)).ravel() + q.extra_sq
        q_n = q.heard.astype(np.float64)
        # Augmented query rows: [v, |v|^2, 1] . [-2 r, 1, |r|^2] = eq. 9's numerator in one GEMM.
        qa = np.empty((m, qd.shape[1] + 2))
        qa[:, :-2] = qd
        qa[:, -2] = q_sq
        qa[:, -1] = 1.0
        qb = (qd > 0).astype(np.float32)
        probe = self.probe(q, probes)
        p = probe.shape[1]
        # Each query's candidates laid out in one row of a (Q, L) buffer, probe after probe.
        sizes = self.sizes[probe]
        off = np.zeros_like(sizes)
        np.cumsum(sizes[:, :-1], axis=1, out=off[:, 1:])
        width = max(1, int((off[:, -1] + sizes[:, -1]).max()))
        buf = np.full((m, width), np.inf)
        # Group (query, probe slot) pairs by cluster: one sort, then contiguous runs per cluster.
        flat = probe.ravel()
        order = np.argsort(flat, kind="stable")
        bounds = np.searchsorted(flat[order], np.arange(self.n_clusters + 1))
        q_of = order // p
        off_of = off.ravel()[order]
        need = max(1, min_common)
        with np.errstate(divide="ignore", invalid="ignore"):
            for c in np.flatnonzero(bounds[1:] > bounds[:-1]).tolist():
                cl = self.clusters[c]
                lo, hi = bounds[c], bounds[c + 1]
                rows = q_of[lo:hi]
                r2 = rows[:, None]
                num = qa[r2, cl.acols] @ cl.aT
                com = qb[r2, cl.cols] @ cl.bT
                den = q_n[r2] + cl.ref_n - com
                np.maximum(num, 0.0, out=num)
                num /= den
                np.sqrt(num, out=num)
                num[com < need] = np.inf
                buf[r2, off_of[lo:hi, None] + cl.arange] = num
        pos, dist = _k_smallest(buf, k)
        # Buffer position -> (probe slot, offset in the cluster) -> map row.
        slot = (pos[:, :, None] >= off[:, None, :]).sum(axis=2) - 1
        ci = np.take_along_axis(probe, slot, axis=1)
        local = pos - np.take_along_axis(off, slot, axis=1)
        idx = self.members_flat[self.starts[ci] + local]
        bad = ~np.isfinite(dist)
        idx[bad] = -1
        # Ties: equal distances ordered by map row, as the exact path does.
        o = np.lexsort((np.where(bad, np.iinfo(np.int64).max, idx), dist), axis=1)
        idx = np.take_along_axis(idx, o, axis=1)
        dist = np.take_along_axis(dist, o, axis=1)
        _fix_straddling_ties(buf, pos, dist, idx, lambda r, cols: self._rows_of(probe[r], off[r], cols))
        return idx, dist

    def _rows_of(self, probe_r: NDArray[np.int64], off_r: NDArray[np.int64], pos: NDArray[np.int64]) -> NDArray[np.int64]:
        slot = np.searchsorted(off_r, pos, side="right") - 1
        return self.members_flat[self.starts[probe_r[slot]] + pos - off_r[slot]]


_INT_INF = np.float64(np.inf).view(np.int64)


def _k_smallest(buf: NDArray[np.float64], k: int) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Positions and values of each row's k smallest entries (first occurrence first among
    equals). Why k rounds of argmin: argmin is a vectorised streaming pass, much cheaper than
    argpartition for small k; the int64 view of non-negative floats (and +inf) keeps their order."""
    m, w = buf.shape
    kk = min(k, w)
    x = buf.copy().view(np.int64)
    r = np.arange(m)
    pos = np.empty((m, k), np.int64)
    for j in range(kk):
        a = np.argmin(x, axis=1)
        pos[:, j] = a
        x[r, a] = np.iinfo(np.int64).max
    pos[:, kk:] = pos[:, :1] if kk else 0
    dist = np.take_along_axis(buf, pos, axis=1)
    dist[:, kk:] = np.inf
    return pos, dist


def _fix_straddling_ties(
    buf: NDArray[np.float64], pos: NDArray[np.int64], dist: NDArray[np.float64], idx: NDArray[np.int64],
    rows_of: "Callable[[int, NDArray[np.int64]], NDArray[np.int64]]",
) -> None:
    """Rows where references tied at the k-th distance were not all selected: keep the lowest
    map rows among them (the exact path's rule). Rare; in place."""
    k = dist.shape[1]
    tau = dist[:, -1]
    fin = np.isfinite(tau)
    if not fin.any():
        return
    n_tied = (buf == tau[:, None]).sum(axis=1)
    straddle = fin & (n_tied > (dist == tau[:, None]).sum(axis=1))
    for r in np.flatnonzero(straddle).tolist():
        below = np.flatnonzero(buf[r] < tau[r])
        tied = np.flatnonzero(buf[r] == tau[r])
        rb, rt = rows_of(r, below), np.sort(rows_of(r, tied))[: k - len(below)]
        ids = np.concatenate([rb, rt])
        d = np.concatenate([buf[r, below], np.full(len(rt), tau[r])])
        o = np.lexsort((ids, d))
        idx[r], dist[r] = ids[o], d[o]
