"""The k nearest references of query fingerprints: distances on candidate pairs and the top k.

eq. 9 distances come from ``DistanceEngine`` (same precomputation, same formula, same
floating-point operations); Sørensen's from the postings of each query AP (``SorensenRefs``). For sparse reference sets (typical: a scan hears a few
dozen of thousands of APs) the engine's products are kept sparse here: only pairs
that share at least one AP are ever candidates (``min_common >= 1``), so eq. 9 is
evaluated on those pairs only and the rest of the block stays ``inf``. On
UJIIndoorLoc that is ~1.8x faster than ``DistanceEngine.iter_blocks`` + top-k, with
bit-identical distances (tested). Blocks of a few queries gather postings instead
(``gather_block``): scipy's per-product overhead would dominate. A few scans (the service's
requests, ``FewQueries``) go further: no sparse matrix at all, distances on candidate cells
only, the same answers bit for bit.

``nearest``: one ``argpartition`` per block for the k nearest, ties by reference, so that
answers do not depend on k, block size or threads. The locator on top of these is
``graphslam.core.radiomap.knn``.
"""

from __future__ import annotations

from typing import Callable, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy import sparse

from graphslam.core.common.arrays import nonzero_2d
from graphslam.core.radiomap.fingerprints import DistanceEngine, FingerprintMatrix
from graphslam.core.radiomap.radiomap import RadioMap

# Torres-Sospedra et al. 2015's "powed" representation: (shifted RSS / its range) ** e.
POWED_EXPONENT = float(np.e)


def _sq_norms(m: FingerprintMatrix) -> NDArray[np.float64]:
    # Same expression as fingerprints._sq_norms, so distances are bit-identical to the engine's.
    return np.asarray(m.values.multiply(m.values).sum(axis=1)).ravel() + m.extra_sq


def candidate_block(eng: DistanceEngine, q: FingerprintMatrix, min_common: int) -> NDArray[np.float64]:
    """``DistanceEngine.block(q)[0]`` for a sparse engine, evaluating eq. 9 only on pairs that
    share an AP (the sparse products' pattern); every other cell is ``inf``."""
    qv = q.values
    qb = qv.copy()
    qb.data[:] = 1.0
    dot = qv @ eng.ref_vT
    com = qb @ eng.ref_bT
    # Both products have the same pattern (positive entries); align them if scipy ordered them differently.
    if not (np.array_equal(dot.indptr, com.indptr) and np.array_equal(dot.indices, com.indices)):
        dot.sort_indices()
        com.sort_indices()
    b, n = qv.shape[0], eng.ref_sq.shape[0]
    rows = np.repeat(np.arange(b), np.diff(dot.indptr))
    cols = dot.indices
    num = _sq_norms(q)[rows] + eng.ref_sq[cols] - 2.0 * dot.data
    den = q.heard.astype(np.float64)[rows] + eng.ref_n[cols] - com.data
    d = np.sqrt(np.maximum(num, 0.0) / den)
    out = np.full(b * n, np.inf)
    flat = rows * n + cols
    if min_common > 1:
        keep = com.data >= min_common
        flat, d = flat[keep], d[keep]
    out[flat] = d
    return out.reshape(b, n)


def _postings(
    q: sparse.csr_matrix, ref_by_ap: sparse.csr_matrix
) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
    """Every (query, reference) pair sharing an AP, once per shared AP: the flat cell index
    ``query * N + reference`` (N = ``ref_by_ap``'s columns), the query's and the reference's value
    of that AP. ``ref_by_ap``: (A, N) csr, row j = the references that heard AP j."""
    n = ref_by_ap.shape[1]
    aps = q.indices
    starts = ref_by_ap.indptr[aps]
    lens = ref_by_ap.indptr[aps + 1] - starts
    pos = np.repeat(starts - (np.cumsum(lens) - lens), lens) + np.arange(int(lens.sum()))
    key = np.repeat(np.repeat(np.arange(q.shape[0]) * n, np.diff(q.indptr)), lens) + ref_by_ap.indices[pos]
    return key, np.repeat(q.data, lens), ref_by_ap.data[pos]


def gather_block(eng: DistanceEngine, q: FingerprintMatrix, min_common: int) -> NDArray[np.float64]:
    """Same as ``candidate_block`` for a few queries, without sparse-matrix products: gather the
    postings (AP -> references) of each query AP and sum with ``bincount``. Why: a sparse product
    has fixed costs (format checks, a symbolic pass, two products) that one query does not amortise."""
    qv = q.values
    ref = eng.ref_vT  # (A, N) csr: row j = the references that heard AP j
    b, n = qv.shape[0], eng.ref_sq.shape[0]
    key, qval, rval = _postings(qv, ref)
    dot = np.bincount(key, weights=qval * rval, minlength=b * n).reshape(b, n)
    common = np.bincount(key, minlength=b * n).reshape(b, n)
    num = _sq_norms(q)[:, None] + eng.ref_sq[None, :] - 2.0 * dot
    den = q.heard.astype(np.float64)[:, None] + eng.ref_n[None, :] - common
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.sqrt(np.maximum(num, 0.0) / den)
    d[common < max(1, min_common)] = np.inf
    return d


# Below this many queries per block, gathering postings beats sparse products.
GATHER_MAX_ROWS = 16


class FewQueries:
    """A few query scans over the map's AP index as the arrays of ``RadioMap.encode``'s csr matrix
    (per row, APs in ascending column order: same values, same summation orders)."""

    def __init__(self, rm: RadioMap, scans: Sequence[Mapping[str, float]]) -> None:
        rows, cols, vals, self.extra_sq, self.extra_n = rm.scan_arrays(scans)
        self.n, self.n_aps = len(scans), rm.fingerprints.n_aps
        o = np.argsort(rows * self.n_aps + cols, kind="stable")
        self.indices, self.data = cols[o], vals[o]
        self.counts = np.bincount(rows, minlength=self.n)
        self.indptr = np.zeros(self.n + 1, np.int64)
        np.cumsum(self.counts, out=self.indptr[1:])

    def row_sums(self, x: NDArray[np.float64]) -> NDArray[np.float64]:
        """Per row, the sum of ``x`` (one value per stored entry) as scipy's ``csr.sum(axis=1)``
        adds it (``np.add.reduceat`` over the non-empty rows): bit-identical to the matrix path."""
        out = np.zeros(self.n)
        nz = self.counts > 0
        if nz.any():
            out[nz] = np.add.reduceat(x, self.indptr[:-1][nz])
        return out

    def dense(self) -> NDArray[np.float64]:
        """(n, A) shifted RSS: ``toarray()`` of the matrix."""
        out = np.zeros((self.n, self.n_aps))
        out[np.repeat(np.arange(self.n), self.counts), self.indices] = self.data
        return out

    def times(self, m: NDArray[np.float32]) -> NDArray[np.float32]:
        """(float32 queries) @ ``m`` (A, C), as scipy's csr @ dense adds it: per query, the rows of
        its APs scaled and added in column order (probe scores bit for bit: a different order could
        pick another cluster on a near-tie)."""
        out = np.zeros((self.n, m.shape[1]), np.float32)
        v = self.data.astype(np.float32)
        for r, (lo, hi) in enumerate(zip(self.indptr[:-1].tolist(), self.indptr[1:].tolist())):
            if hi > lo:
                out[r] = (v[lo:hi, None] * m[self.indices[lo:hi]]).sum(axis=0)
        return out

    def matrix(self, rm: RadioMap) -> FingerprintMatrix:
        """The same queries as ``rm.encode`` returns them (paths that need the matrix: IVF, dense)."""
        v = sparse.csr_matrix((self.data, self.indices, self.indptr), shape=(self.n, self.n_aps))
        return FingerprintMatrix(rm.bssids, v, rm.missing_dbm, self.extra_sq, self.extra_n)


def _top_k(refs: NDArray[np.int64], d: NDArray[np.float64], k: int) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """One query's row of ``nearest`` from its candidates only (``refs`` ascending, distances
    ``d``; every other reference ``inf``): the k smallest, ties by reference, -1 / inf padded."""
    idx = np.full(k, -1, np.int64)
    dist = np.full(k, np.inf)
    kk = min(k, len(d))
    if kk == 0:
        return idx, dist
    if kk < len(d):
        sel = np.argpartition(d, kk - 1)[:kk]
        tau = d[sel].max()
        # argpartition picks any of several candidates tied at the k-th distance: take the
        # first ones (lowest references), as nearest does
        if np.isfinite(tau) and np.count_nonzero(d <= tau) > kk:
            below = np.flatnonzero(d < tau)
            sel = np.concatenate([below, np.flatnonzero(d == tau)[: kk - len(below)]])
    else:
        sel = np.arange(kk)
    sd = d[sel]
    o = np.lexsort((sel, sd))
    sel, sd = sel[o], sd[o]
    ok = np.isfinite(sd)
    idx[:kk] = np.where(ok, refs[sel], -1)
    dist[:kk] = np.where(ok, sd, np.inf)
    return idx, dist


def _few_nearest(
    q: FewQueries, qdata: NDArray[np.float64], ref_by_ap: sparse.csr_matrix, min_common: int, k: int,
    combine: Callable[[NDArray[np.float64], NDArray[np.float64]], NDArray[np.float64]],
    distance: Callable[[int, NDArray[np.int64], NDArray[np.float64], NDArray[np.int64]], NDArray[np.float64]],
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """``nearest`` of a postings block (``sorensen_block``, ``gather_block``) for a ``FewQueries``, one
    query at a time (a loop over <= 16 queries: no (query, reference) key arithmetic, and its
    bincounts are one query wide). Per query: its APs' postings (``ref_by_ap``: (A, N) csr) copied
    as one slice per AP, in the same order as ``_postings``, so ``bincount`` adds the same terms in
    the same order (bit-identical sums); ``combine(query values, reference values)`` per posting,
    summed per reference; ``distance(query, candidates, sums, shared APs)`` evaluated on the
    references sharing ``max(1, min_common)`` APs only (every other one is ``inf``)."""
    n = ref_by_ap.shape[1]
    ip, ind, dat = ref_by_ap.indptr, ref_by_ap.indices, ref_by_ap.data
    starts, ends = ip[q.indices], ip[q.indices + 1]
    lens = ends - starts
    starts_l, ends_l, bounds = starts.tolist(), ends.tolist(), q.indptr.tolist()
    need = max(1, min_common)
    idx = np.full((q.n, k), -1, np.int64)
    dist = np.full((q.n, k), np.inf)
    for r in range(q.n):
        a, e = bounds[r], bounds[r + 1]
        if a == e:
            continue  # no known AP: no candidate
        spans = list(zip(starts_l[a:e], ends_l[a:e]))
        ref = np.concatenate([ind[s:t] for s, t in spans])
        terms = combine(np.repeat(qdata[a:e], lens[a:e]), np.concatenate([dat[s:t] for s, t in spans]))
        common = np.bincount(ref, minlength=n)
        cand = np.flatnonzero(common >= need)
        sums = np.bincount(ref, weights=terms, minlength=n)[cand]
        idx[r], dist[r] = _top_k(cand, distance(r, cand, sums, common[cand]), k)
    return idx, dist


def sorensen_few(refs: "SorensenRefs", q: FewQueries, min_common: int, k: int) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """``nearest(sorensen_block(...), k)`` for a ``FewQueries``: the same sums in the same order."""
    qp = refs.powed_values(q.data)
    qsum = q.row_sums(qp)

    def distance(r: int, c: NDArray[np.int64], both: NDArray[np.float64], _: NDArray[np.int64]) -> NDArray[np.float64]:
        return np.maximum(1.0 - 2.0 * both / (qsum[r] + refs.sum[c]), 0.0)

    return _few_nearest(q, qp, refs.pT, min_common, k, np.minimum, distance)


def eq9_few(eng: DistanceEngine, q: FewQueries, min_common: int, k: int) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """``nearest(gather_block(...), k)`` (sparse engine) for a ``FewQueries``: the same sums in the same order."""
    sq = q.row_sums(q.data * q.data) + q.extra_sq
    heard = (q.counts + q.extra_n).astype(np.float64)

    def distance(r: int, c: NDArray[np.int64], dot: NDArray[np.float64], common: NDArray[np.int64]) -> NDArray[np.float64]:
        num = sq[r] + eng.ref_sq[c] - 2.0 * dot
        den = heard[r] + eng.ref_n[c] - common
        return np.sqrt(np.maximum(num, 0.0) / den)

    return _few_nearest(q, q.data, eng.ref_vT, min_common, k, np.multiply, distance)


class SorensenRefs:
    """What the Sørensen distance needs of the reference set (``KnnConfig.metric``): powed values
    by AP (postings, (A, N) csr) and their sum per reference."""

    def __init__(self, ref: FingerprintMatrix) -> None:
        # the shifted values' range: 0 (missing_dbm) to 0 dBm; a map whose missing_dbm is not negative
        # has no such range, so its strongest reading stands in
        scale = -ref.missing_dbm if ref.missing_dbm < 0 else float(ref.values.data.max(initial=1.0))
        self.scale = scale
        p = ref.values.copy()
        p.data = self.powed_values(p.data)
        self.sum = np.asarray(p.sum(axis=1)).ravel()
        self.pT = p.T.tocsr()
        self._dense: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None

    def dense_rows(self, aps: NDArray[np.int64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(powed values, 1 where an entry is stored) of the references on the APs ``aps``, dense,
        (len(aps), N) each. Why a dense copy of every AP is kept (from the first call, where it holds at
        most ``DENSE_REFS_MAX_CELLS`` cells): the radio map's calibration asks ~50 times, and densifying
        the rows each time cost ~0.4 s of its 2.4 s on `paper` size 12's map."""
        if self._dense is None and self.pT.shape[0] * self.pT.shape[1] <= DENSE_REFS_MAX_CELLS:
            pattern = self.pT.copy()
            pattern.data = np.ones_like(pattern.data)
            self._dense = (self.pT.toarray(), pattern.toarray())
        if self._dense is not None:
            return self._dense[0][aps], self._dense[1][aps]
        r = self.pT[aps]
        values = r.toarray()
        r.data = np.ones_like(r.data)
        return values, r.toarray()

    def powed(self, q: FingerprintMatrix) -> sparse.csr_matrix:
        p = q.values.copy()
        p.data = self.powed_values(p.data)
        return p

    def powed_values(self, v: NDArray[np.float64]) -> NDArray[np.float64]:
        """Shifted RSS values -> powed values (element-wise; the IVF index's Sørensen too)."""
        return (v / self.scale) ** POWED_EXPONENT


# ``SorensenRefs.dense_rows`` keeps a dense copy of a reference set of at most this many (AP,
# reference) cells: two float64 arrays of 16 MiB at most
DENSE_REFS_MAX_CELLS = 1 << 21

# A block of queries over a map whose references hear most of the block's APs (a small site) is
# computed dense, AP by AP, when its postings would fill at least this share of the dense cells
# (block x references x the block's APs). Measured (2026-12-04; the `paper` simulator map, IPIN
# b100_f-2, ILC F2): ~3-4 ns per dense cell against 24-107 ns per posting (random-access sums).
SORENSEN_DENSE_MIN_FILL = 0.15


def sorensen_block(refs: SorensenRefs, q: FingerprintMatrix, min_common: int) -> NDArray[np.float64]:
    """(len(q), N) Sørensen distances of powed fingerprints: sum min(p_q, p_r) per (query,
    reference) pair over their common APs, accumulated in ascending AP order, either by gathering
    the postings of each query AP (``bincount``; memory: the block's postings) or dense, one AP at
    a time (``SORENSEN_DENSE_MIN_FILL``): the same sums in the same order, bit for bit. Pairs
    sharing fewer than ``max(1, min_common)`` APs are ``inf``."""
    qp = refs.powed(q)
    b, n = qp.shape[0], len(refs.sum)
    aps = np.flatnonzero(np.bincount(qp.indices, minlength=refs.pT.shape[0]))
    postings = int(np.diff(refs.pT.indptr)[qp.indices].sum())
    if b > 1 and postings >= SORENSEN_DENSE_MIN_FILL * len(aps) * b * n:
        both, common = _sorensen_dense_sums(qp, refs, aps)
    else:
        key, qval, rval = _postings(qp, refs.pT)
        both = np.bincount(key, weights=np.minimum(qval, rval), minlength=b * n)
        common = np.bincount(key, minlength=b * n)
    qsum = np.asarray(qp.sum(axis=1)).ravel()
    with np.errstate(divide="ignore", invalid="ignore"):
        d = 1.0 - 2.0 * both.reshape(b, n) / (qsum[:, None] + refs.sum[None, :])
    d = np.maximum(d, 0.0)
    d[common.reshape(b, n) < max(1, min_common)] = np.inf
    return d


def _sorensen_dense_sums(
    qp: sparse.csr_matrix, refs: SorensenRefs, aps: NDArray[np.int64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``sorensen_block``'s sums of min(p_q, p_r) and counts of common APs, (b, N) each, over
    the APs ``aps`` (ascending: every AP a query of the block heard) one at a time. A pair that
    does not share an AP adds min = 0 there, which leaves a float sum unchanged: the postings'
    sums exactly. Common APs are counted from the stored entries (as the postings count them)."""
    Q = qp[:, aps]
    Rd, R01 = refs.dense_rows(aps)
    Qd = Q.toarray()
    both = np.zeros((qp.shape[0], Rd.shape[1]))
    tmp = np.empty_like(both)
    for j in range(len(aps)):
        np.minimum(Qd[:, j, None], Rd[j, None, :], out=tmp)
        both += tmp
    Q.data = np.ones_like(Q.data)
    common = Q.toarray() @ R01  # small integers: exact in float64
    return both.ravel(), common.ravel()


# Columns per group of ``nearest``'s first pass.
NEAREST_GROUP = 64


def nearest(d: NDArray[np.float64], k: int) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Rows' k smallest entries, nearest first (ties by index); non-finite -> index -1.

    Why not ``argpartition`` of every row: ~3.7x the time on a block of 600 x 24k (the radio map
    calibration's, paper size 12). The k-th smallest of a row's minima over groups of
    ``NEAREST_GROUP`` columns is at least the row's k-th smallest value (k groups hold a value at most
    that large), so the finite entries at or below it hold the answer, ties at the k-th value included,
    and they are few: only those are sorted (``row_top_k``'s device). Narrower groups where the
    columns are few, so that there are 4k of them."""
    b, n = d.shape
    dtype = d.dtype if np.issubdtype(d.dtype, np.floating) else np.float64
    idx = np.full((b, k), -1, np.int64)
    dist = np.full((b, k), np.inf, dtype)
    k_eff = min(k, n)
    if k_eff == 0 or b == 0:
        return idx, dist
    g = max(1, min(NEAREST_GROUP, n // (4 * k_eff)))
    full, groups = n // g, -(-n // g)
    if groups > k_eff:
        gmin = np.empty((b, groups), dtype)
        if full:  # fmin: a NaN (no distance) is no group's minimum
            gmin[:, :full] = np.fmin.reduce(d[:, : full * g].reshape(b, full, g), axis=2)
        if full < groups:
            gmin[:, full] = np.fmin.reduce(d[:, full * g :], axis=1)
        tau = np.partition(gmin, k_eff - 1, axis=1)[:, k_eff - 1]
    else:
        tau = np.full(b, np.inf, dtype)
    cand = d <= tau[:, None]
    few = ~(tau < np.inf)  # fewer than k finite groups: every finite entry is a candidate, no other
    if few.any():
        cand[few] = np.isfinite(d[few])
    ri, ci = nonzero_2d(cand)
    v = d[ri, ci]
    fin = np.isfinite(v)
    ri, ci, v = ri[fin], ci[fin], v[fin]
    o = np.lexsort((ci, v, ri))
    ri, ci, v = ri[o], ci[o], v[o]
    rank = np.arange(len(ri)) - np.searchsorted(ri, ri, side="left")
    keep = rank < k_eff
    idx[ri[keep], rank[keep]] = ci[keep]
    dist[ri[keep], rank[keep]] = v[keep]
    return idx, dist


# ``pair_eq9`` holds a few queries dense over the map's APs up to this many cells (else it pairs keys)
PAIR_DENSE_MAX_CELLS = 1 << 16


def pair_eq9(
    ref: FingerprintMatrix, ref_sq: NDArray[np.float64], ref_n: NDArray[np.float64], q_indptr: NDArray[np.int64],
    q_indices: NDArray[np.int64], q_data: NDArray[np.float64], q_extra_sq: NDArray[np.float64],
    q_extra_n: NDArray[np.int64], idx: NDArray[np.int64],
) -> NDArray[np.float64]:
    """(Q, k) eq. 9 distances (dB) of each query to the references ``idx`` (Q, k) lists for it (``inf``
    where -1): a query's stored entries (csr arrays ``q_indptr``, ``q_indices``, ``q_data``; its
    readings of APs outside the index in ``q_extra_*``) against each listed reference row; no Python
    loop, no (Q, N) matrix. ``ref_sq``, ``ref_n``: the references' squared norms and APs heard
    (``DistanceEngine``'s). A few queries are held dense over the map's APs and the references'
    entries looked up in them (``PAIR_DENSE_MAX_CELLS``: the service's single fingerprints, ~3x less
    fixed cost); more, each (pair, AP) key of the query's entries searched among the references'."""
    n_q, k = idx.shape
    out = np.full((n_q, k), np.inf)
    pair_q, pair_j = np.nonzero(idx >= 0)
    if not len(pair_q):
        return out
    refs = idx[pair_q, pair_j]
    rv = ref.values
    q_len = np.diff(q_indptr)
    r_start = rv.indptr[refs]
    r_len = rv.indptr[refs + 1] - r_start
    re = _entries(r_start, r_len)
    r_pair = np.repeat(np.arange(len(refs)), r_len)
    n_aps = rv.shape[1]
    if n_q * n_aps <= PAIR_DENSE_MAX_CELLS:
        qd = np.zeros((n_q, n_aps))
        qd[np.repeat(np.arange(n_q), q_len), q_indices] = q_data
        qv = qd[pair_q[r_pair], rv.indices[re]]
        dot = np.bincount(r_pair, weights=qv * rv.data[re], minlength=len(refs))
        common = np.bincount(r_pair, weights=qv > 0, minlength=len(refs))
        q_sq = np.einsum("ij,ij->i", qd, qd)
    else:
        qe = _entries(q_indptr[:-1][pair_q], q_len[pair_q])
        q_pair = np.repeat(np.arange(len(refs)), q_len[pair_q])
        q_key = q_pair * n_aps + q_indices[qe]
        r_key = r_pair * n_aps + rv.indices[re]  # ascending when each row's columns are
        if len(r_key) > 1 and not (np.diff(r_key) >= 0).all():
            o = np.argsort(r_key, kind="stable")
            r_key, re = r_key[o], re[o]
        pos = np.minimum(np.searchsorted(r_key, q_key), max(len(r_key) - 1, 0))
        hit = (r_key[pos] == q_key) if len(r_key) else np.zeros(len(q_key), bool)
        dot = np.bincount(q_pair[hit], weights=q_data[qe][hit] * rv.data[re][pos[hit]], minlength=len(refs))
        common = np.bincount(q_pair[hit], minlength=len(refs))
        q_sq = np.bincount(np.repeat(np.arange(n_q), q_len), weights=q_data**2, minlength=n_q)
    num = q_sq[pair_q] + q_extra_sq[pair_q] + ref_sq[refs] - 2.0 * dot
    den = q_len[pair_q] + q_extra_n[pair_q] + ref_n[refs] - common
    with np.errstate(divide="ignore", invalid="ignore"):
        out[pair_q, pair_j] = np.sqrt(np.maximum(num, 0.0) / den)
    return out


def _entries(starts: NDArray[np.int64], lens: NDArray[np.int64]) -> NDArray[np.int64]:
    """The positions ``starts[i] .. starts[i] + lens[i] - 1`` of every i, concatenated."""
    return np.repeat(starts - (np.cumsum(lens) - lens), lens) + np.arange(int(lens.sum()))
