"""Inverted-file (IVF) approximate search for kNN: eq. 9, or Sørensen on powed RSS.

Exact kNN scores every query against every reference (UJIIndoorLoc: ~40 GFlop per
1,000 queries). The IVF index partitions the references once, by k-means on their
dense shifted-RSS vectors (oversized clusters split), and scores a query only against
the members of the ``probes`` clusters whose centroids are nearest to it (Euclidean).
Inside the probed clusters eq. 9 is evaluated *exactly*, with the same formula as
``DistanceEngine``; the only approximation is which references are looked at. With
``probes == clusters`` the answer is the exact search's (tested).

Layout, chosen so that a batch costs a loop over clusters only (never over queries or
references): per cluster, its members (ascending map rows), the union of the APs
they heard (``cols``: a cluster is a place, so ~50 of UJIIndoorLoc's 443 APs) and
dense (|cols|, n_c) matrices. For a batch, (query, probe) pairs are grouped by
cluster; each group is one small GEMM for eq. 9's numerators and one for the
shared-AP counts over the cluster's columns (APs outside them add nothing to
either). Distances go to a (Q, probes x largest cluster) buffer, one row per query,
and k rounds of ``argmin`` pick the k nearest.

Ties follow the exact path: equal distances are ordered by map row, so with all
clusters probed the neighbours are the same references in the same order.

Sørensen (``powed`` given: the map of shifted RSS to powed values, ``knn.KnnConfig.metric``):
the same clusters and probes (k-means on shifted RSS groups places whatever the distance), and
per cluster its members' powed values over the cluster's columns; the numerator
``sum min(p_q, p_r)`` is an element-wise minimum over (queries x members x columns), in chunks
of at most ``SORENSEN_CHUNK_CELLS`` cells, and the query's powed sum runs over all its APs the
map knows, as in the exact path (only APs both heard add to the minimum).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
from numpy.typing import NDArray
from scipy import sparse

from graphslam.core.radiomap.fingerprints import FingerprintMatrix
from graphslam.errors import ConfigError

# Dense float32 copy of the references for k-means only when it stays below this many cells
# (~256 MB); bigger maps cluster on the sparse matrix (slower, same result up to rounding).
KMEANS_DENSE_MAX_CELLS = 64_000_000
# Rows per assignment block: bounds the (rows, C) distance matrix of a k-means step.
ASSIGN_BLOCK_CELLS = 8_000_000
DEFAULT_KMEANS_ITERATIONS = 25
DEFAULT_SEED = 0
# Clusters above this multiple of the mean size are split (see split_oversized).
DEFAULT_MAX_SIZE_RATIO = 2.0
# Sørensen: cells (queries x members x columns) of one element-wise minimum (~16 MB of float64)
SORENSEN_CHUNK_CELLS = 2_000_000


def limit_blas_threads(n: int = 1) -> bool:
    """Set the process's BLAS thread count (``threadpoolctl``); ``False`` if unavailable.

    Why: an IVF search is hundreds of tiny GEMMs, and OpenBLAS's thread hand-off made them
    ~15x slower on a 2-core machine (and far worse when two searches overlap, or when the
    count is toggled per call). A process-wide setting, so it is the caller's decision:
    ``graphslam serve`` calls this once at start-up; the service parallelises over requests.
    threadpoolctl reaches only the libraries loaded so far, and scipy's wheels bring their own
    OpenBLAS, loaded by ``scipy.linalg`` (the trackers' banded solves): it is loaded here first,
    or a command that imports it later keeps two threads there (5x slower on the cart)."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - optional speed-up
        return False
    import scipy.linalg  # noqa: F401 - load scipy's OpenBLAS, so that the limit applies to it too

    threadpool_limits(limits=n, user_api="blas")
    return True


def split_oversized(
    x: NDArray | sparse.csr_matrix, cent: NDArray[np.float32], labels: NDArray[np.int64], cap: int
) -> tuple[NDArray[np.float32], NDArray[np.int64]]:
    """Split clusters of more than ``cap`` members into equal consecutive chunks along their
    principal axis, and recompute every centroid. Why: k-means leaves a few big clusters (dense
    survey spots: UJIIndoorLoc's largest holds 10x the median), and a search's candidate buffer
    is ``probes x largest cluster`` wide; big clusters also cost the most to probe."""
    sizes = np.bincount(labels, minlength=len(cent))
    big = np.flatnonzero(sizes > cap)
    if not len(big):
        return cent, labels
    labels = labels.copy()
    next_label = len(cent)
    for c in big.tolist():  # build time, a few dozen clusters at most
        mem = np.flatnonzero(labels == c)
        sub = x[mem]
        sub = np.asarray(sub.toarray() if sparse.issparse(sub) else sub, np.float64)
        sub -= sub.mean(axis=0)
        axis = np.linalg.svd(sub, full_matrices=False)[2][0]
        chunks = np.array_split(mem[np.argsort(sub @ axis, kind="stable")], -(-len(mem) // cap))
        for ch in chunks[1:]:
            labels[ch] = next_label
            next_label += 1
    n = len(labels)
    counts = np.bincount(labels, minlength=next_label).astype(np.float32)
    ind = sparse.csr_matrix((np.ones(n, np.float32), (labels, np.arange(n))), shape=(next_label, n))
    sums = ind @ x
    sums = np.asarray(sums.toarray() if sparse.issparse(sums) else sums, np.float32)
    return np.ascontiguousarray(sums / counts[:, None]), labels


def default_clusters(n_refs: int) -> int:
    """~2 sqrt(N) clusters: clusters of ~sqrt(N)/2 references (UJIIndoorLoc: 282 of ~71)."""
    return max(1, round(2.0 * math.sqrt(max(1, n_refs))))


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
    powed: NDArray[np.float64] | None = None  # Sørensen: (n_c, |cols|) members' powed values
    powed_sum: NDArray[np.float64] | None = None  # Sørensen: (n_c,) their sum over every AP


class IvfIndex:
    """k-means inverted file over a reference ``FingerprintMatrix``. Read-only after construction
    (thread-safe). ``clusters``: k-means C (``None``: ``default_clusters(N)``). The index's
    ``n_clusters`` can differ: clusters left empty (fewer distinct fingerprints than C) are
    dropped, clusters over ``max_size_ratio`` x the mean size are split. ``powed``: the powed
    representation of shifted RSS values (element-wise); given, the index scores the Sørensen
    distance of powed fingerprints instead of eq. 9 (see the module docstring)."""

    def __init__(
        self, ref: FingerprintMatrix, *, clusters: int | None = None, seed: int = DEFAULT_SEED,
        iterations: int = DEFAULT_KMEANS_ITERATIONS, max_size_ratio: float = DEFAULT_MAX_SIZE_RATIO,
        powed: Callable[[NDArray[np.float64]], NDArray[np.float64]] | None = None,
    ) -> None:
        n = len(ref)
        c_req = default_clusters(n) if clusters is None else clusters
        if isinstance(c_req, bool) or not isinstance(c_req, int) or c_req < 1:
            raise ConfigError(f"IVF: clusters must be an integer >= 1, got {clusters!r}")
        self.ref = ref
        self.seed = seed
        self.powed = powed
        v = ref.values
        x: NDArray | sparse.csr_matrix
        if n * ref.n_aps <= KMEANS_DENSE_MAX_CELLS:
            x = v.toarray().astype(np.float32)
        else:
            x = v.astype(np.float32)
        cent, labels = kmeans(x, min(c_req, max(1, n)), seed=seed, iterations=iterations)
        cap = max(1, math.ceil(max_size_ratio * n / max(1, len(cent))))
        self.centroids, self.labels = split_oversized(x, cent, labels, cap)
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
            # [q, |q|^2, 1] @ [-2 v^T; 1; |v|^2] = |q|^2 + |v|^2 - 2 q.v, eq. 9's numerator, in one
            # GEMM (a fused block-diagonal GEMM with the counts measured slower: twice the flops).
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
                    **self._powed_members(dense),
                )
            )
        self.sizes = np.array([len(c.members) for c in self.clusters], np.int64)
        self.max_size = int(self.sizes.max()) if len(self.sizes) else 0
        self.starts = np.concatenate([[0], np.cumsum(self.sizes)[:-1]]).astype(np.int64)
        self.members_flat = order.astype(np.int64)  # cluster after cluster, as ``starts`` indexes

    def _powed_members(self, dense: NDArray[np.float64]) -> dict[str, NDArray[np.float64]]:
        """Sørensen: a cluster's members' powed values over its columns and their sums (the
        columns hold every AP a member heard, so the sums are over all of them)."""
        if self.powed is None:
            return {}
        p = np.where(dense > 0, self.powed(dense), 0.0)
        return {"powed": np.ascontiguousarray(p), "powed_sum": p.sum(axis=1)}

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
        return self.probe_scores(np.asarray(q.values.astype(np.float32) @ self.centroids_T, dtype=np.float32), p)

    def probe_scores(self, g: NDArray[np.float32], p: int) -> NDArray[np.int64]:
        """``probe`` from ``g`` = (queries as float32) @ ``centroids_T`` (overwritten), ``p`` < clusters."""
        g *= -2.0
        g += self.centroid_sq[None, :]  # |q|^2 is the same for every centroid of a row
        return np.argpartition(g, p - 1, axis=1)[:, :p].astype(np.int64)

    def search(
        self, q: FingerprintMatrix, *, k: int, probes: int, min_common: int = 1
    ) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """(Q, k) map rows and distances (eq. 9, or Sørensen with ``powed``) of the k nearest
        references among the probed clusters, nearest first, ties by map row; -1 / inf padded
        (as ``neighbours.nearest``)."""
        m = len(q)
        if m == 0 or self.n_clusters == 0:
            return np.full((m, k), -1, np.int64), np.full((m, k), np.inf)
        return self._search(q, k, probes, min_common)

    def _search(
        self, q: FingerprintMatrix, k: int, probes: int, min_common: int
    ) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        qd = q.values.toarray()
        q_sq = np.asarray(q.values.multiply(q.values).sum(axis=1)).ravel() + q.extra_sq
        return self.search_dense(qd, q_sq, q.heard.astype(np.float64), self.probe(q, probes), k=k, min_common=min_common)

    def search_dense(
        self, qd: NDArray[np.float64], q_sq: NDArray[np.float64], q_n: NDArray[np.float64], probe: NDArray[np.int64],
        *, k: int, min_common: int = 1,
    ) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """``search`` from the queries' dense shifted RSS ``qd`` (Q, A), their ``|v|^2`` (with
        extra APs), APs heard and ``probe`` (Q, P) clusters: what a caller holding the queries as
        arrays passes instead of a ``FingerprintMatrix`` (``knn``'s few-query path)."""
        m = len(qd)
        if m == 0 or self.n_clusters == 0:
            return np.full((m, k), -1, np.int64), np.full((m, k), np.inf)
        # Augmented query rows [v, |v|^2, 1] (see _Cluster.aT) and heard flags.
        qa = np.empty((m, qd.shape[1] + 2))
        qa[:, :-2] = qd
        qa[:, -2] = q_sq
        qa[:, -1] = 1.0
        qb = (qd > 0).astype(np.float32)
        qp = np.where(qd > 0, self.powed(qd), 0.0) if self.powed is not None else None
        qp_sum = qp.sum(axis=1) if qp is not None else None
        p = probe.shape[1]
        width = max(1, self.max_size)
        # Candidate buffer: row q*p + s holds the distances to the members of query q's s-th probed
        # cluster (inf past its size), so a query's candidates are one contiguous row of p * width.
        buf = np.full((m * p, width), np.inf)
        # Group (query, probe slot) pairs by cluster: one sort, then contiguous runs per cluster.
        flat = probe.ravel()
        order = np.argsort(flat, kind="stable")
        bounds = np.searchsorted(flat[order], np.arange(self.n_clusters + 1))
        q_of = order // p
        need = max(1, min_common)
        with np.errstate(divide="ignore", invalid="ignore"):
            for c in np.flatnonzero(bounds[1:] > bounds[:-1]).tolist():
                cl = self.clusters[c]
                lo, hi = bounds[c], bounds[c + 1]
                rows = q_of[lo:hi]
                com = qb.take(rows, axis=0).take(cl.cols, axis=1) @ cl.bT
                if qp is not None:
                    num = _sorensen(qp.take(rows, axis=0).take(cl.cols, axis=1), qp_sum[rows], cl)  # type: ignore[index]
                else:
                    # take(rows) then take(cols): two contiguous gathers, cheaper than one 2-D fancy index
                    num = qa.take(rows, axis=0).take(cl.acols, axis=1) @ cl.aT
                    den = q_n[rows, None] + cl.ref_n - com
                    # eq. 9, clamped like the exact path (rounding can leave a tiny negative numerator)
                    np.maximum(num, 0.0, out=num)
                    num /= den
                    np.sqrt(num, out=num)
                np.copyto(num, np.inf, where=com < need)  # also every 0/0 (den is 0 only if nothing is shared)
                buf[order[lo:hi], : len(cl.members)] = num
        buf = buf.reshape(m, p * width)
        pos, dist, straddle = _k_smallest(buf, k)  # buf now holds the unselected entries only
        idx = self._rows_at(probe, pos, width)
        bad = ~np.isfinite(dist)
        idx[bad] = -1
        dist[bad] = np.inf
        # Ties: equal distances ordered by map row, as the exact path does.
        o = np.lexsort((np.where(bad, np.iinfo(np.int64).max, idx), dist), axis=1)
        idx = np.take_along_axis(idx, o, axis=1)
        dist = np.take_along_axis(dist, o, axis=1)
        _fix_straddling_ties(buf, straddle, dist, idx, lambda r, cols: self._rows_at(probe[r : r + 1], cols[None, :], width)[0])
        return idx, dist

    def _rows_at(self, probe: NDArray[np.int64], pos: NDArray[np.int64], width: int) -> NDArray[np.int64]:
        """Map rows of candidate-buffer positions (-1 for padding)."""
        slot, local = np.divmod(pos, width)
        ci = np.take_along_axis(probe, slot, axis=1)
        ok = local < self.sizes[ci]
        return np.where(ok, self.members_flat[np.where(ok, self.starts[ci] + local, 0)], -1)


def _sorensen(qp: NDArray[np.float64], qp_sum: NDArray[np.float64], cl: _Cluster) -> NDArray[np.float64]:
    """(queries, members) Sørensen distances of powed fingerprints ``qp`` (over the cluster's
    columns; ``qp_sum``: over all their APs) to the cluster's members: ``1 - 2 sum min / (sum_q +
    sum_r)``, clamped at 0 like the exact path, the minimum taken in chunks of queries."""
    assert cl.powed is not None and cl.powed_sum is not None
    m, n_c = len(qp), len(cl.members)
    both = np.empty((m, n_c))
    step = max(1, SORENSEN_CHUNK_CELLS // max(1, n_c * qp.shape[1]))
    for s in range(0, m, step):
        both[s : s + step] = np.minimum(qp[s : s + step, None, :], cl.powed[None, :, :]).sum(axis=2)
    d = 1.0 - 2.0 * both / (qp_sum[:, None] + cl.powed_sum[None, :])
    return np.maximum(d, 0.0)


def _k_smallest(buf: NDArray[np.float64], k: int) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.bool_]]:
    """Positions and values of each row's k smallest entries (first occurrence first among
    equals), and whether an unselected entry ties with the k-th (see ``_fix_straddling_ties``).
    Why k rounds of argmin: argmin is a vectorised streaming pass, much cheaper than
    argpartition for small k; the int64 view of non-negative floats (and +inf) keeps their order.
    In place: selected entries of ``buf`` are overwritten (int64 max, a NaN)."""
    m, w = buf.shape
    kk = min(k, w)
    x = buf.view(np.int64)
    r = np.arange(m)
    pos = np.zeros((m, k), np.int64)
    dist = np.full((m, k), np.inf)
    for j in range(kk):
        a = np.argmin(x, axis=1)
        pos[:, j] = a
        dist[:, j] = buf[r, a]
        x[r, a] = np.iinfo(np.int64).max
    # One more round: the best unselected entry ties with the k-th selected one -> tie straddles k.
    straddle = np.zeros(m, bool)
    if 0 < kk < w:
        nxt = buf[r, np.argmin(x, axis=1)]
        straddle = np.isfinite(dist[:, kk - 1]) & (nxt == dist[:, kk - 1])
    return pos, dist, straddle


def _fix_straddling_ties(
    rest: NDArray[np.float64], straddle: NDArray[np.bool_], dist: NDArray[np.float64], idx: NDArray[np.int64],
    rows_of: Callable[[int, NDArray[np.int64]], NDArray[np.int64]],
) -> None:
    """Rows where references tied at the k-th distance were left unselected (still in ``rest``,
    the buffer minus the selected entries): keep the lowest map rows among all the tied ones
    (the exact path's rule). Rare; in place."""
    k = dist.shape[1]
    tau = dist[:, -1]
    for r in np.flatnonzero(straddle).tolist():
        ids = np.concatenate([idx[r], rows_of(r, np.flatnonzero(rest[r] == tau[r]))])
        d = np.concatenate([dist[r], np.full(len(ids) - k, tau[r])])
        o = np.lexsort((ids, d))[:k]
        idx[r], dist[r] = ids[o], d[o]
