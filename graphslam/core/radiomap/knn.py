"""kNN and weighted kNN fingerprint positioning: Sørensen on powed RSS (the default) or the
paper's RSS distance (eq. 9).

eq. 9 distances come from ``DistanceEngine`` (same precomputation, same formula, same
floating-point operations); Sørensen's from the postings of each query AP (``SorensenRefs``). For sparse reference sets (typical: a scan hears a few
dozen of thousands of APs) the engine's products are kept sparse here: only pairs
that share at least one AP are ever candidates (``min_common >= 1``), so eq. 9 is
evaluated on those pairs only and the rest of the block stays ``inf``. On
UJIIndoorLoc that is ~1.8x faster than ``DistanceEngine.iter_blocks`` + top-k, with
bit-identical distances (tested). Blocks of a few queries gather postings instead
(``_gather_block``): scipy's per-product overhead would dominate. ``locate`` of at most
``FEW_MAX_QUERIES`` scans (the service's requests) goes further (``_Few``): no sparse matrix at
all, distances on candidate cells only, the same answers bit for bit.

Per query block: one ``argpartition`` for the k nearest, then vectorised
inverse-distance (or uniform) weighting, neighbour spread and label votes. There is
no Python loop per reference; the few-query path loops over its (<= 16) queries.

A query is *invalid* (flagged, or ``QueryError`` with ``strict=True``) when no
reference fingerprint shares ``min_common`` APs with it; in particular when none of
its APs is known to the map.
"""

from __future__ import annotations

import logging
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Literal, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy import sparse

from graphslam.core.radiomap.fingerprints import DistanceEngine, FingerprintMatrix
from graphslam.core.radiomap.ivf import IvfIndex
from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.core.types import Survey
from graphslam.errors import ConfigError, QueryError
from graphslam.names import DEFAULT_INDEX, DEFAULT_K, DEFAULT_METRIC, INDEXES, METRICS

if TYPE_CHECKING:
    from graphslam.core.radiomap.uncertainty import KnnUncertainty

log = logging.getLogger(__name__)

# Cells (queries x references) of one distance block: ~8 MB of float64, cache-friendly
# enough that the block loop costs less than one huge allocation.
DEFAULT_BLOCK_CELLS = 1_000_000
# Inverse-distance weights 1 / (d + eps): an exact match (d = 0) dominates without dividing by zero.
WEIGHT_EPS_DB = 1e-6

# index="auto" switches to the IVF index from this many references: below it exact search is
# already fast and the index would not pay off.
IVF_AUTO_MIN_REFS = 5000
DEFAULT_IVF_PROBES = 8
# Query rows per IVF block: the IVF loop is over clusters, so its fixed cost is per block;
# bigger blocks amortise it (the candidate buffer is ~rows x 2,000 float64 on UJIIndoorLoc).
IVF_BLOCK_ROWS = 4096

IndexKind = Literal["auto", "exact", "ivf"]
Metric = Literal["sorensen", "eq9"]
# Torres-Sospedra et al. 2015's "powed" representation: (shifted RSS / its range) ** e.
POWED_EXPONENT = float(np.e)

STATUS_OK = "ok"
STATUS_NO_KNOWN_AP = "no_known_ap"
STATUS_NO_CANDIDATE = "no_candidate"


@dataclass(frozen=True)
class KnnConfig:
    """k nearest fingerprints; ``weighted``: inverse-distance weights, else uniform;
    ``min_common``: a reference is a candidate only if it shares this many APs with the query.

    ``index``: ``"exact"`` scores every reference; ``"ivf"`` searches an inverted file
    (``graphslam.core.radiomap.ivf``: k-means clusters of the references, the distance evaluated
    exactly on the members of the ``ivf_probes`` clusters nearest to the query; approximate, ~7-10x
    faster on UJIIndoorLoc's batch); ``"auto"`` (the default, ``graphslam.names``): IVF from
    ``IVF_AUTO_MIN_REFS`` references, exact below. ``ivf_clusters``: ``None`` = ~2 sqrt(N);
    ``ivf_seed`` makes the clustering reproducible.

    ``metric`` (default ``"sorensen"``, ``graphslam.names``): ``"eq9"`` (the paper's RMS dB
    difference over the union of heard APs, missing = ``missing_dbm``) or ``"sorensen"``: the
    Sørensen (Bray-Curtis) distance on the *powed*
    representation ``p = (v / -missing_dbm) ** e`` of the shifted RSS ``v`` (Torres-Sospedra et al.,
    "Comprehensive analysis of distance and similarity measures for Wi-Fi fingerprinting indoor
    positioning systems", 2015): ``1 - 2 sum min(p_q, p_r) / (sum p_q + sum p_r)`` over the map's
    APs. Strong readings dominate and a missing reading costs what it weighs, not a fixed -110 dBm
    gap; query APs the map never heard are left out (equally far from every reference). It locates
    better on every data set measured (docs/radio_map.md)."""

    k: int = DEFAULT_K
    weighted: bool = True
    min_common: int = 1
    index: IndexKind = DEFAULT_INDEX  # type: ignore[assignment]
    ivf_clusters: int | None = None
    ivf_probes: int = DEFAULT_IVF_PROBES
    ivf_seed: int = 0
    metric: Metric = DEFAULT_METRIC  # type: ignore[assignment]

    def __post_init__(self) -> None:
        if self.metric not in METRICS:
            raise ConfigError(f"kNN: metric must be one of {', '.join(METRICS)}, got {self.metric!r}")
        if self.index not in INDEXES:
            raise ConfigError(f"kNN: index must be one of {', '.join(INDEXES)}, got {self.index!r}")
        for name in ("ivf_probes", "ivf_clusters"):
            v = getattr(self, name)
            if v is None and name == "ivf_clusters":
                continue
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ConfigError(f"kNN: {name} must be an integer >= 1, got {v!r}")
        if isinstance(self.ivf_seed, bool) or not isinstance(self.ivf_seed, int):
            raise ConfigError(f"kNN: ivf_seed must be an integer, got {self.ivf_seed!r}")
        if isinstance(self.k, bool) or not isinstance(self.k, int) or self.k < 1:
            raise ConfigError(f"kNN: k must be an integer >= 1, got {self.k!r}")
        if isinstance(self.min_common, bool) or not isinstance(self.min_common, int) or self.min_common < 1:
            raise ConfigError(f"kNN: min_common must be an integer >= 1, got {self.min_common!r}")


@dataclass(frozen=True, eq=False)
class KnnResult:
    """One row per query. Invalid rows (``valid`` False) have NaN position/score/spread,
    no neighbours and an empty label."""

    xy: NDArray[np.float64]  # (Q, 2) estimate, metres in the map's frame
    score: NDArray[np.float64]  # (Q,) mean distance of the neighbours used (eq. 9: dB; sorensen: 0-1): lower = better
    spread: NDArray[np.float64]  # (Q,) weighted RMS distance (m) of neighbour positions to the estimate
    neighbours: NDArray[np.int64]  # (Q, k) radio map rows, nearest first, -1 padded
    distances: NDArray[np.float64]  # (Q, k) their distances (``config.metric``), inf padded
    n_known_aps: NDArray[np.int64]  # (Q,) query APs that the map knows
    floor: NDArray[np.str_] | None  # (Q,) weighted vote of the neighbours' labels, when the map has labels
    building: NDArray[np.str_] | None
    config: KnnConfig

    def __post_init__(self) -> None:
        for name in ("xy", "score", "spread", "neighbours", "distances", "n_known_aps", "floor", "building"):
            a = getattr(self, name)
            if a is not None:
                a.setflags(write=False)

    def __len__(self) -> int:
        return len(self.score)

    @property
    def n_neighbours(self) -> NDArray[np.int64]:
        return (self.neighbours >= 0).sum(axis=1)

    @property
    def valid(self) -> NDArray[np.bool_]:
        return self.neighbours[:, 0] >= 0 if self.neighbours.shape[1] else np.zeros(len(self), bool)

    @property
    def status(self) -> NDArray[np.str_]:
        """Per query: ``ok``, ``no_known_ap`` (no AP of the query is in the map) or
        ``no_candidate`` (known APs, but no reference shares ``min_common`` of them)."""
        s = np.full(len(self), STATUS_OK, dtype="<U12")
        s[~self.valid] = STATUS_NO_CANDIDATE
        s[self.n_known_aps == 0] = STATUS_NO_KNOWN_AP
        return s


def _sq_norms(m: FingerprintMatrix) -> NDArray[np.float64]:
    # Same expression as fingerprints._sq_norms, so distances are bit-identical to the engine's.
    return np.asarray(m.values.multiply(m.values).sum(axis=1)).ravel() + m.extra_sq


def _candidate_block(eng: DistanceEngine, q: FingerprintMatrix, min_common: int) -> NDArray[np.float64]:
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


def _gather_block(eng: DistanceEngine, q: FingerprintMatrix, min_common: int) -> NDArray[np.float64]:
    """Same as ``_candidate_block`` for a few queries, without sparse-matrix products: gather the
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
# Up to this many scans, ``locate`` takes the few-query path (``_Few``): scans encoded to plain
# arrays, distances evaluated on candidate references only. Why: one query's cost was mostly fixed
# costs (a scipy matrix per call, temporaries and a top-k over every reference).
FEW_MAX_QUERIES = GATHER_MAX_ROWS


class _Few:
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
    """One query's row of ``_nearest`` from its candidates only (``refs`` ascending, distances
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
        # first ones (lowest references), as _nearest does
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
    q: _Few, qdata: NDArray[np.float64], ref_by_ap: sparse.csr_matrix, min_common: int, k: int,
    combine: Callable[[NDArray[np.float64], NDArray[np.float64]], NDArray[np.float64]],
    distance: Callable[[int, NDArray[np.int64], NDArray[np.float64], NDArray[np.int64]], NDArray[np.float64]],
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """``_nearest`` of a postings block (``_sorensen_block``, ``_gather_block``) for a ``_Few``, one
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


def _sorensen_few(refs: "SorensenRefs", q: _Few, min_common: int, k: int) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """``_nearest(_sorensen_block(...), k)`` for a ``_Few``: the same sums in the same order."""
    qp = refs.powed_values(q.data)
    qsum = q.row_sums(qp)

    def distance(r: int, c: NDArray[np.int64], both: NDArray[np.float64], _: NDArray[np.int64]) -> NDArray[np.float64]:
        return np.maximum(1.0 - 2.0 * both / (qsum[r] + refs.sum[c]), 0.0)

    return _few_nearest(q, qp, refs.pT, min_common, k, np.minimum, distance)


def _eq9_few(eng: DistanceEngine, q: _Few, min_common: int, k: int) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """``_nearest(_gather_block(...), k)`` (sparse engine) for a ``_Few``: the same sums in the same order."""
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

    def powed(self, q: FingerprintMatrix) -> sparse.csr_matrix:
        p = q.values.copy()
        p.data = self.powed_values(p.data)
        return p

    def powed_values(self, v: NDArray[np.float64]) -> NDArray[np.float64]:
        """Shifted RSS values -> powed values (element-wise; the IVF index's Sørensen too)."""
        return (v / self.scale) ** POWED_EXPONENT


# A block of queries over a map whose references hear most of the block's APs (a small site) is
# computed dense, AP by AP, when its postings would fill at least this share of the dense cells
# (block x references x the block's APs). Measured (2026-12-04; the `paper` simulator map, IPIN
# b100_f-2, ILC F2): ~3-4 ns per dense cell against 24-107 ns per posting (random-access sums).
SORENSEN_DENSE_MIN_FILL = 0.15


def _sorensen_block(refs: SorensenRefs, q: FingerprintMatrix, min_common: int) -> NDArray[np.float64]:
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
        both, common = _sorensen_dense_sums(qp, refs.pT, aps)
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
    qp: sparse.csr_matrix, ref_by_ap: sparse.csr_matrix, aps: NDArray[np.int64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``_sorensen_block``'s sums of min(p_q, p_r) and counts of common APs, (b, N) each, over
    the APs ``aps`` (ascending: every AP a query of the block heard) one at a time. A pair that
    does not share an AP adds min = 0 there, which leaves a float sum unchanged: the postings'
    sums exactly. Common APs are counted from the stored entries (as the postings count them)."""
    Q = qp[:, aps]
    R = ref_by_ap[aps]
    Qd, Rd = Q.toarray(), R.toarray()
    both = np.zeros((qp.shape[0], ref_by_ap.shape[1]))
    tmp = np.empty_like(both)
    for j in range(len(aps)):
        np.minimum(Qd[:, j, None], Rd[j, None, :], out=tmp)
        both += tmp
    Q.data, R.data = np.ones_like(Q.data), np.ones_like(R.data)
    common = Q.toarray() @ R.toarray()  # small integers: exact in float64
    return both.ravel(), common.ravel()


def _nearest(d: NDArray[np.float64], k: int) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Rows' k smallest entries, nearest first (ties by index); non-finite -> index -1."""
    b, n = d.shape
    k_eff = min(k, n)
    if k_eff == 0:
        return np.full((b, k), -1, np.int64), np.full((b, k), np.inf)
    if k_eff < n:
        idx = np.argpartition(d, k_eff - 1, axis=1)[:, :k_eff]
        dist = np.take_along_axis(d, idx, axis=1)
        # argpartition picks any of several references tied at the k-th distance; take the
        # lowest rows instead, so answers do not depend on k, block size or threads.
        tau = dist.max(axis=1)
        fin = np.isfinite(tau)
        straddle = fin & ((d == tau[:, None]).sum(axis=1) > (dist == tau[:, None]).sum(axis=1))
        for r in np.flatnonzero(straddle):  # rare: only rows with ties across the boundary
            below = np.flatnonzero(d[r] < tau[r])
            tied = np.flatnonzero(d[r] == tau[r])[: k_eff - len(below)]
            idx[r] = np.concatenate([below, tied])
    else:
        idx = np.broadcast_to(np.arange(n), (b, n)).copy()
    dist = np.take_along_axis(d, idx, axis=1)
    order = np.lexsort((idx, dist), axis=1)
    idx = np.take_along_axis(idx, order, axis=1).astype(np.int64)
    dist = np.take_along_axis(dist, order, axis=1)
    bad = ~np.isfinite(dist)
    idx[bad] = -1
    dist[bad] = np.inf
    if k_eff < k:
        idx = np.pad(idx, ((0, 0), (0, k - k_eff)), constant_values=-1)
        dist = np.pad(dist, ((0, 0), (0, k - k_eff)), constant_values=np.inf)
    return idx, dist


class _Labels:
    """Per-reference labels as integer codes, for vectorised weighted votes."""

    def __init__(self, labels: NDArray[np.str_]) -> None:
        self.names, self.codes = np.unique(labels, return_inverse=True)
        self.known = self.names[self.codes] != ""

    def vote(self, idx: NDArray[np.int64], w: NDArray[np.float64]) -> NDArray[np.str_]:
        b, k = idx.shape
        safe = np.where(idx >= 0, idx, 0)
        ww = np.where((idx >= 0) & self.known[safe], w, 0.0)
        n_lab = len(self.names)
        key = np.repeat(np.arange(b), k) * n_lab + self.codes[safe].ravel()
        votes = np.bincount(key, weights=ww.ravel(), minlength=b * n_lab).reshape(b, n_lab)
        win = self.names[np.argmax(votes, axis=1)]  # ties: first label in sorted order
        return np.where(votes.max(axis=1) > 0, win, "").astype(str)


class KnnLocator:
    """kNN positioning against one radio map. Thread-safe (read-only after construction)."""

    def __init__(
        self,
        radio_map: RadioMap,
        config: KnnConfig | None = None,
        *,
        block_cells: int = DEFAULT_BLOCK_CELLS,
        threads: int | None = None,
    ) -> None:
        self.radio_map = radio_map
        self.config = config or KnnConfig()
        self.engine = DistanceEngine(radio_map.fingerprints)
        self.block_rows = max(1, block_cells // max(1, len(radio_map)))
        cfg = self.config
        self._sorensen = SorensenRefs(radio_map.fingerprints) if cfg.metric == "sorensen" else None
        use_ivf = cfg.index == "ivf" or (cfg.index == "auto" and len(radio_map) >= IVF_AUTO_MIN_REFS)
        # The exact engine stays: IVF queries that find fewer than k candidates are re-run exactly.
        self.ivf: IvfIndex | None = (
            IvfIndex(radio_map.fingerprints, clusters=cfg.ivf_clusters, seed=cfg.ivf_seed,
                     powed=self._sorensen.powed_values if self._sorensen is not None else None)
            if use_ivf and len(radio_map) else None
        )
        if self.ivf is not None:
            self.threads = 1  # the IVF loop holds the GIL: see _rows_per_block
        # Sparse products and numpy kernels release the GIL: two blocks in flight use both cores.
        self.threads = max(1, threads if threads is not None else min(2, os.cpu_count() or 1))
        self._floors = _Labels(radio_map.floors) if radio_map.floors is not None else None
        self._buildings = _Labels(radio_map.buildings) if radio_map.buildings is not None else None
        # the answers' calibrated uncertainty (``graphslam.core.radiomap.uncertainty``), set by those who report it
        self.uncertainty: KnnUncertainty | None = None

    def distances(self, q: FingerprintMatrix) -> NDArray[np.float64]:
        """(len(q), len(map)) distances (``KnnConfig.metric``); ``inf`` for pairs sharing <
        ``min_common`` APs."""
        if len(self.radio_map) == 0:
            return np.full((len(q), 0), np.inf)
        if self._sorensen is not None:
            return _sorensen_block(self._sorensen, q, self.config.min_common)
        if self.engine.dense:
            return self.engine.block(q, min_common=self.config.min_common)[0]
        if len(q) <= GATHER_MAX_ROWS:
            return _gather_block(self.engine, q, self.config.min_common)
        return _candidate_block(self.engine, q, self.config.min_common)

    @property
    def index_kind(self) -> str:
        """``"ivf"`` or ``"exact"``: the search actually used (``index="auto"`` resolved)."""
        return "ivf" if self.ivf is not None else "exact"

    def _block(self, q: FingerprintMatrix) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        k = self.config.k
        if self.ivf is None:
            return _nearest(self.distances(q), k)
        idx, dist = self.ivf.search(q, k=k, probes=self.config.ivf_probes, min_common=self.config.min_common)
        # Fewer than k candidates in the probed clusters (a query at the edge of the map, or one
        # whose APs the probed places did not hear): answer those rows exactly, so a query is
        # flagged invalid only when the exact search would flag it too.
        short = np.flatnonzero(idx[:, min(k, len(self.radio_map)) - 1] < 0)
        if len(short):
            idx[short], dist[short] = _nearest(self.distances(q.rows(short)), k)
        return idx, dist

    def _rows_per_block(self, n_q: int) -> int:
        if self.ivf is None:
            return self.block_rows
        # The IVF loop is Python-bound (GIL): threads do not help, and each block pays the
        # loop's fixed cost, so big batches go in few big blocks.
        return IVF_BLOCK_ROWS

    def locate(
        self, queries: FingerprintMatrix | Sequence[Mapping[str, float]], *, strict: bool = False
    ) -> KnnResult:
        """Estimate a position for every query (scans ``bssid -> dBm`` or fingerprints over the
        map's AP index). ``strict``: raise ``QueryError`` if any query cannot be answered,
        instead of flagging it (``KnnResult.valid``/``status``)."""
        rm = self.radio_map
        if not isinstance(queries, FingerprintMatrix) and 0 < len(queries) <= FEW_MAX_QUERIES and len(rm):
            return self._locate_few(queries, strict)
        q = queries if isinstance(queries, FingerprintMatrix) else rm.encode(queries)
        if q.bssids is not rm.bssids and q.bssids != rm.bssids:
            q = rm.reindex(q)
        n_q, k = len(q), self.config.k
        rows = self._rows_per_block(n_q)
        starts = list(range(0, n_q, rows))
        blocks = [q.rows(slice(s, s + rows)) for s in starts] if len(starts) > 1 else [q]
        if len(blocks) > 1 and self.threads > 1 and self.ivf is None:
            with ThreadPoolExecutor(self.threads) as ex:
                parts = list(ex.map(self._block, blocks))
        else:
            parts = [self._block(b) for b in blocks]
        idx = np.concatenate([p[0] for p in parts]) if parts else np.zeros((0, k), np.int64)
        dist = np.concatenate([p[1] for p in parts]) if parts else np.zeros((0, k))
        n_known = np.diff(q.values.indptr).astype(np.int64)
        res = self._aggregate(idx, dist, n_known)
        err = strict_error(res, self.config.min_common) if strict else None
        if err is not None:
            raise err
        return res

    def _locate_few(self, scans: Sequence[Mapping[str, float]], strict: bool) -> KnnResult:
        """``locate`` of a few scans (``_Few``): the same answers, bit for bit, for less fixed cost."""
        q = _Few(self.radio_map, scans)
        cfg = self.config
        if self.ivf is None and self._sorensen is not None:
            idx, dist = _sorensen_few(self._sorensen, q, cfg.min_common, cfg.k)
        elif self.ivf is None and not self.engine.dense:
            idx, dist = _eq9_few(self.engine, q, cfg.min_common, cfg.k)
        elif self.ivf is not None:
            idx, dist = self._ivf_few(q)
        else:
            idx, dist = self._block(q.matrix(self.radio_map))
        res = self._aggregate(idx, dist, q.counts.astype(np.int64))
        err = strict_error(res, cfg.min_common) if strict else None
        if err is not None:
            raise err
        return res

    def _ivf_few(self, q: _Few) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """``_block`` with the IVF index for a ``_Few``: its arrays passed as they are (no matrix)."""
        ivf, k = self.ivf, self.config.k
        assert ivf is not None
        p = min(self.config.ivf_probes, ivf.n_clusters)
        if p >= ivf.n_clusters:
            probe = np.broadcast_to(np.arange(ivf.n_clusters), (q.n, ivf.n_clusters)).copy()
        else:
            probe = ivf.probe_scores(q.times(ivf.centroids_T), p)
        q_sq = q.row_sums(q.data * q.data) + q.extra_sq
        idx, dist = ivf.search_dense(q.dense(), q_sq, (q.counts + q.extra_n).astype(np.float64), probe, k=k,
                                     min_common=self.config.min_common)
        short = np.flatnonzero(idx[:, min(k, len(self.radio_map)) - 1] < 0)  # as in _block
        if len(short):
            idx[short], dist[short] = _nearest(self.distances(q.matrix(self.radio_map).rows(short)), k)
        return idx, dist

    def scores_over_query(self, scans: Sequence[Mapping[str, float]], res: KnnResult) -> NDArray[np.float64]:
        """Per query: ``res.score`` (this locator's answers to ``scans``) as if every AP of the query
        were in the map, the ones it does not know heard by no reference: comparable between maps
        of different AP sets (a building's floors). Sørensen drops unknown APs from the distance,
        so a map that knows one weak AP of a query would score near 0 on it alone; here each
        neighbour's distance ``num / den`` becomes ``(num + u) / (den + u)``, ``u`` the powed
        strength of the query's unknown APs. Eq. 9 already charges them (``extra_sq``): its scores
        are returned as they are. NaN where ``res`` has no answer."""
        if self._sorensen is None:
            return np.asarray(res.score, float).copy()
        rm = self.radio_map
        fm = rm.encode(scans)
        known = np.asarray(self._sorensen.powed(fm).sum(axis=1), float).ravel()
        floor = max(rm.min_rssi_dbm, rm.missing_dbm + 1e-6)
        unknown = np.array([
            float(self._sorensen.powed_values(np.array(
                [v - rm.missing_dbm for b, v in sc.items() if rm.column(b) is None and v >= floor], float)).sum())
            for sc in scans
        ])
        ok = (res.neighbours >= 0) & np.isfinite(res.distances)
        den = known[:, None] + self._sorensen.sum[np.where(ok, res.neighbours, 0)]
        d = (res.distances * den + unknown[:, None]) / (den + unknown[:, None])
        with np.errstate(invalid="ignore"):
            out = np.where(ok, d, 0.0).sum(axis=1) / ok.sum(axis=1)
        out[~np.asarray(res.valid)] = np.nan
        return out

    def _aggregate(self, idx: NDArray[np.int64], dist: NDArray[np.float64], n_known: NDArray[np.int64]) -> KnnResult:
        ok = idx >= 0
        safe = np.where(ok, idx, 0)
        if self.config.weighted:
            w = np.where(ok, 1.0 / (np.where(ok, dist, 0.0) + WEIGHT_EPS_DB), 0.0)
        else:
            w = ok.astype(np.float64)
        wsum = w.sum(axis=1)
        valid = wsum > 0
        with np.errstate(invalid="ignore", divide="ignore"):
            nxy = self.radio_map.xy[safe] if len(self.radio_map) else np.zeros(idx.shape + (2,))
            est = (w[..., None] * nxy).sum(axis=1) / wsum[:, None]
            sq = ((nxy - est[:, None, :]) ** 2).sum(axis=2)
            spread = np.sqrt((w * sq).sum(axis=1) / wsum)
            score = np.where(ok, dist, 0.0).sum(axis=1) / ok.sum(axis=1)
        est[~valid] = np.nan
        spread[~valid] = np.nan
        score[~valid] = np.nan
        return KnnResult(
            xy=est,
            score=score,
            spread=spread,
            neighbours=idx,
            distances=dist,
            n_known_aps=n_known,
            floor=self._floors.vote(idx, w) if self._floors is not None else None,
            building=self._buildings.vote(idx, w) if self._buildings is not None else None,
            config=self.config,
        )


def strict_error(res: KnnResult, min_common: int) -> QueryError | None:
    """The error ``locate(strict=True)`` raises for ``res``, or ``None`` when every query was located
    (also used by the service, which locates batches in pieces and joins them first)."""
    if res.valid.all():
        return None
    bad = np.flatnonzero(~res.valid)
    st = res.status
    detail = ", ".join(f"#{i}: {st[i]}" for i in bad[:5]) + (" ..." if len(bad) > 5 else "")
    return QueryError(
        f"{len(bad)} of {len(res)} queries cannot be located ({detail}); "
        f"a query needs an access point heard by the radio map"
        + (f" (>= {min_common} shared APs)" if min_common > 1 else "")
    )


@dataclass(frozen=True, eq=False)
class SurveyPositions:
    """Every WiFi scan of a set of query sessions, located: row i = scan (session_ids[i], t_ns[i])."""

    session_ids: NDArray[np.str_]
    t_ns: NDArray[np.int64]
    result: KnnResult

    def __len__(self) -> int:
        return len(self.t_ns)


def locate_survey(locator: KnnLocator, survey: Survey) -> SurveyPositions:
    """Answer every ``/wifi/scan`` of every session (unanswerable scans are flagged, not fatal)."""
    scans = [s for sess in survey for s in sess.scans]
    sids = np.array([sess.session_id for sess in survey for _ in sess.scans], dtype=str)
    t = np.array([s.t_ns for s in scans], dtype=np.int64)
    res = locator.locate([s.readings for s in scans])
    bad = int((~res.valid).sum())
    if bad:
        log.warning("%d of %d scans could not be located (no access point known to the radio map)", bad, len(scans))
    return SurveyPositions(sids, t, res)
