"""WiFi fingerprints and the paper's RSS distance (eq. 9).

A fingerprint set is stored as a sparse (N, A) matrix of *shifted* RSS values
``v = rssi - missing_dbm`` (> 0 where heard, 0 where not heard), over an AP index
(tuple of BSSIDs, column order). With that shift, eq. 9 over the union U of the
pair's access points becomes matrix products:

    d(i, j)^2 = (|v_i|^2 + |v_j|^2 - 2 v_i . v_j) / (n_i + n_j - c_ij)

where n is the number of APs heard and c_ij the number heard by both. Access
points that only the query heard and the reference set does not know add to
both numerator and |U| (``extra_sq``, ``extra_n``), so the distance stays exact.
Distances are computed in row blocks, so memory is bounded by
``block_rows * N`` however big the survey is.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import chain
from typing import Iterator, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy import sparse

DEFAULT_MISSING_DBM = -110.0
DEFAULT_MIN_RSSI_DBM = -100.0

# Bound on the cells of one distance block (rows x columns): 16 MB of float64, so that a block's
# arrays reuse the allocator's freed memory; larger blocks are fresh mappings, page-faulted each time
# (1,000 rows against 28k fingerprints: 1.0 s of CPU in one block, 0.3 s in blocks of this size).
MAX_BLOCK_CELLS = 2_000_000


def heard_floor(min_rssi_dbm: float, missing_dbm: float) -> float:
    """The weakest reading kept (dBm): ``min_rssi_dbm``, and always above ``missing_dbm`` (a reading
    at the "not heard" level is no reading)."""
    return max(min_rssi_dbm, missing_dbm + 1e-6)


@dataclass(frozen=True, eq=False)
class FingerprintMatrix:
    """N fingerprints over an AP index. Rows are scans; see module docstring for the encoding."""

    bssids: tuple[str, ...]
    values: sparse.csr_matrix  # (N, A) float64, shifted RSS
    missing_dbm: float = DEFAULT_MISSING_DBM
    extra_sq: NDArray[np.float64] | None = None  # (N,) sum of v^2 over APs outside the index
    extra_n: NDArray[np.int64] | None = None  # (N,) count of APs outside the index

    def __post_init__(self) -> None:
        v = sparse.csr_matrix(self.values, dtype=np.float64)
        v.eliminate_zeros()
        if v.shape[1] != len(self.bssids):
            raise ValueError("FingerprintMatrix: columns do not match the AP index")
        if v.nnz and (v.data <= 0).any():
            raise ValueError("FingerprintMatrix: shifted RSS must be > 0 (rssi above missing_dbm)")
        object.__setattr__(self, "values", v)
        n = v.shape[0]
        object.__setattr__(
            self, "extra_sq", np.zeros(n) if self.extra_sq is None else np.asarray(self.extra_sq, float)
        )
        object.__setattr__(
            self, "extra_n", np.zeros(n, np.int64) if self.extra_n is None else np.asarray(self.extra_n, np.int64)
        )

    def __len__(self) -> int:
        return self.values.shape[0]

    @property
    def n_aps(self) -> int:
        return len(self.bssids)

    @property
    def heard(self) -> NDArray[np.int64]:
        """Number of APs heard per fingerprint (inside and outside the index)."""
        return np.diff(self.values.indptr).astype(np.int64) + self.extra_n

    @classmethod
    def from_scans(
        cls,
        scans: Sequence[Mapping[str, float]],
        *,
        bssids: Sequence[str] | None = None,
        missing_dbm: float = DEFAULT_MISSING_DBM,
        min_rssi_dbm: float = DEFAULT_MIN_RSSI_DBM,
    ) -> "FingerprintMatrix":
        """Build from ``bssid -> dBm`` mappings.

        With ``bssids`` given (a reference AP index, e.g. a radio map's), readings of
        other APs go to ``extra_sq``/``extra_n``; otherwise the index is every AP seen,
        sorted.
        """
        floor = heard_floor(min_rssi_dbm, missing_dbm)
        if bssids is None:
            bssids = sorted({b for s in scans for b, r in s.items() if r >= floor})
        return cls.encode(scans, tuple(bssids), {b: i for i, b in enumerate(bssids)}, missing_dbm, min_rssi_dbm)

    @classmethod
    def encode(
        cls,
        scans: Sequence[Mapping[str, float]],
        bssids: tuple[str, ...],
        index: Mapping[str, int],
        missing_dbm: float,
        min_rssi_dbm: float,
    ) -> "FingerprintMatrix":
        """Scans over a given AP index (``index[bssids[j]] == j``, built once by the caller).
        Flattened once (every reading in scan order), then masked: the same matrix, sums and
        counts, in the same order, as a loop over the readings (~3x faster; a survey encodes
        every scan twice)."""
        rows, cols, vals, extra_sq, extra_n = scan_arrays(scans, index, missing_dbm, min_rssi_dbm)
        m = sparse.csr_matrix((vals, (rows, cols)), shape=(len(scans), len(bssids)))
        return cls(bssids, m, missing_dbm, extra_sq, extra_n)

    @classmethod
    def from_readings(
        cls,
        row: NDArray[np.int64],
        code: NDArray[np.int64],
        names: Sequence[str],
        rssi: NDArray[np.float64],
        n: int,
        *,
        missing_dbm: float = DEFAULT_MISSING_DBM,
        min_rssi_dbm: float = DEFAULT_MIN_RSSI_DBM,
    ) -> "FingerprintMatrix":
        """``from_scans`` of ``n`` scans given as columns, one entry per reading: its scan (``row``), its
        BSSID (``names[code]``, at most once per scan) and dBm: the same matrix, without a mapping per scan
        (a professional survey's millions of readings)."""
        floor = heard_floor(min_rssi_dbm, missing_dbm)
        rssi = np.asarray(rssi, np.float64)
        kept = ~(rssi < floor)  # as scan_arrays: what does not compare is kept
        code = np.asarray(code, np.int64)[kept]
        used = np.unique(code).tolist()
        bssids = tuple(sorted({names[c] for c in used}))  # every AP heard, sorted, as from_scans
        col = {b: i for i, b in enumerate(bssids)}
        col_of = np.full(len(names), -1, np.int64)
        col_of[used] = [col[names[c]] for c in used]
        m = sparse.csr_matrix((rssi[kept] - missing_dbm, (np.asarray(row, np.int64)[kept], col_of[code])),
                              shape=(n, len(bssids)))
        return cls(bssids, m, missing_dbm, np.zeros(n, np.float64), np.zeros(n, np.int64))

    @classmethod
    def from_dense(
        cls, rssi: NDArray, bssids: Sequence[str], *, missing_dbm: float = DEFAULT_MISSING_DBM,
        min_rssi_dbm: float = DEFAULT_MIN_RSSI_DBM,
    ) -> "FingerprintMatrix":
        """From an (N, A) dBm array where NaN (or anything below ``min_rssi_dbm``) means not heard."""
        a = np.asarray(rssi, dtype=float)
        floor = heard_floor(min_rssi_dbm, missing_dbm)
        heard = np.isfinite(a) & (a >= floor)
        v = np.where(heard, a - missing_dbm, 0.0)
        return cls(tuple(bssids), sparse.csr_matrix(v), missing_dbm)

    def rows(self, idx: NDArray | slice) -> "FingerprintMatrix":
        return FingerprintMatrix(
            self.bssids, self.values[idx], self.missing_dbm, self.extra_sq[idx], self.extra_n[idx]
        )

    def dense_rssi(self) -> NDArray[np.float64]:
        """(N, A) dBm with ``missing_dbm`` where not heard."""
        v = self.values.toarray()
        return np.where(v > 0, v + self.missing_dbm, self.missing_dbm)


def scan_arrays(
    scans: Sequence[Mapping[str, float]], index: Mapping[str, int], missing_dbm: float, min_rssi_dbm: float
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
    """``FingerprintMatrix.encode``'s arrays before the matrix: (rows, cols, shifted values) of the
    readings of indexed APs, in scan order, and per scan ``extra_sq``, ``extra_n``. Also what
    ``knn``'s few-query path encodes (no sparse matrix: its construction dominates one query)."""
    floor = heard_floor(min_rssi_dbm, missing_dbm)
    n = len(scans)
    counts = np.fromiter((len(s) for s in scans), np.int64, n)
    total = int(counts.sum())
    rssi = np.fromiter(chain.from_iterable(s.values() for s in scans), np.float64, total)
    col = np.fromiter((index.get(b, -1) for b in chain.from_iterable(scans)), np.int64, total)
    row = np.repeat(np.arange(n), counts)
    kept = ~(rssi < floor)  # not `>=`: a loop's `r < floor: skip` keeps what does not compare
    known, other = kept & (col >= 0), kept & (col < 0)
    rows, cols, vals = row[known], col[known], rssi[known] - missing_dbm
    # bincount adds in input order, as the loop did (squares as x * x: correctly rounded)
    extra_sq = np.bincount(row[other], weights=(rssi[other] - missing_dbm) ** 2, minlength=n).astype(np.float64)
    extra_n = np.bincount(row[other], minlength=n).astype(np.int64)
    return rows, cols, vals, extra_sq, extra_n


def _sq_norms(m: FingerprintMatrix) -> NDArray[np.float64]:
    return np.asarray(m.values.multiply(m.values).sum(axis=1)).ravel() + m.extra_sq


class DistanceEngine:
    """Eq. 9 distances from blocks of query fingerprints to a fixed reference set.

    Precomputes what depends on the reference set only; chooses dense BLAS when the
    reference matrix is dense enough, sparse products otherwise.
    """

    def __init__(self, ref: FingerprintMatrix, *, dense_threshold: float = 0.05) -> None:
        self.ref = ref
        self.ref_sq = _sq_norms(ref).astype(np.float64)
        self.ref_n = ref.heard.astype(np.float64)
        nnz_frac = ref.values.nnz / max(1, ref.values.shape[0] * ref.values.shape[1])
        # Dense BLAS wins when fingerprints hear a good share of the APs (simulated floors,
        # UJIIndoorLoc); real malls (~2,400 APs, ~5 % heard) stay sparse.
        self.dense = nnz_frac >= dense_threshold or ref.n_aps <= 64
        self._aug: NDArray[np.float32] | None = None  # ``_below_dense``'s augmented reference rows
        v = ref.values
        b = v.copy()
        b.data[:] = 1.0
        # Counts of shared APs are exact in float32 (< 2**24): half the memory traffic of float64.
        if self.dense:
            self.ref_vT = np.ascontiguousarray(v.toarray().T, dtype=np.float64)
            self.ref_bT = np.ascontiguousarray(b.toarray().T, dtype=np.float32)
        else:
            self.ref_vT = v.T.tocsr().astype(np.float64)
            self.ref_bT = b.T.tocsr().astype(np.float32)

    def _terms(self, q: FingerprintMatrix) -> tuple[NDArray, NDArray, NDArray]:
        """(sum of squared differences float64, union size float32, common-AP counts float32), each
        (len(q), len(ref)): eq. 9 is sqrt(first / second)."""
        if q.bssids is not self.ref.bssids and q.bssids != self.ref.bssids:
            raise ValueError("query and reference fingerprints use different AP indices")
        if self.dense:
            qv = q.values.toarray().astype(np.float64)
            dot = qv @ self.ref_vT
            common = (qv > 0).astype(np.float32) @ self.ref_bT
        else:
            qv = q.values.astype(np.float64)
            qb = qv.astype(np.float32)
            qb.data[:] = 1.0
            dot = (qv @ self.ref_vT).toarray()
            common = (qb @ self.ref_bT).toarray()
        # in place: these blocks are the big arrays of a survey
        num = dot
        num *= -2.0
        num += _sq_norms(q).astype(np.float64)[:, None]
        num += self.ref_sq[None, :]
        np.maximum(num, 0.0, out=num)
        den = self.ref_n.astype(np.float32)[None, :] - common
        den += q.heard.astype(np.float32)[:, None]
        return num, den, common

    def block(self, q: FingerprintMatrix, *, min_common: int = 1) -> tuple[NDArray, NDArray]:
        """(distances float64, common-AP counts float32), each (len(q), len(ref)). Pairs with fewer
        than ``min_common`` shared APs get distance ``inf``."""
        num, den, common = self._terms(q)
        bad = den <= 0
        if min_common > 0:
            bad |= common < min_common
        den[bad] = 1.0
        num /= den
        np.sqrt(num, out=num)
        num[bad] = np.inf
        return num, common

    def pairs_below(
        self, q: FingerprintMatrix, limit: NDArray[np.float64], *, min_common: int = 1
    ) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]:
        """(query row, reference row, distance) of the pairs whose eq. 9 distance is below their query
        row's ``limit`` (one per row of ``q``; NaN: no pair) and that share at least ``min_common`` APs,
        row-major: ``block``'s finite entries below the limit, without the square root and division of
        every pair (the test is num < limit^2 * den; the distances of the pairs kept only). A dense
        reference set tests every pair in one product first (``_below_dense``)."""
        lim = np.asarray(limit, np.float64)
        if self.dense:
            return self._below_dense(q, lim, min_common)
        num, den, common = self._terms(q)
        with np.errstate(invalid="ignore"):  # an infinite limit times an empty union: NaN, no pair
            ok = num < (lim * lim)[:, None] * den
        ok &= den > 0
        if min_common > 0:
            ok &= common >= min_common
        flat = np.flatnonzero(ok)  # (2-D nonzero costs 5x as much)
        ri, ci = np.divmod(flat, ok.shape[1])
        return ri, ci, np.sqrt(num.ravel()[flat] / den.ravel()[flat])

    def _below_dense(
        self, q: FingerprintMatrix, lim: NDArray[np.float64], min_common: int
    ) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]:
        """``pairs_below`` on a dense reference set. Why: ``_terms``' element-wise passes over every
        pair, not its products, were the cost (a block of 2048 x 3244 at paper size 12: ~90 ms, the
        products ~25 ms). num - lim^2 den, expanded (num = |q|^2 + |r|^2 - 2 q.r, den = n_q + n_r -
        common), is one float32 product of augmented rows [-2 q, lim^2 b_q, |q|^2 - lim^2 n_q, 1,
        -lim^2] and [r, b_r, 1, |r|^2, n_r] (b: 1 where heard); the pairs it puts below its rounding
        bound are tested again as ``_terms`` computes them (the same float64 products, gathered), so
        the pairs and distances are those of the element-wise test, bit for bit."""
        qv = q.values.toarray().astype(np.float64)
        qb = (qv > 0).astype(np.float32)
        q_sq = _sq_norms(q).astype(np.float64)
        q_n = q.heard.astype(np.float64)
        inf = np.isposinf(lim)  # every pair with a union passes: no product needed for those rows
        l2 = np.where(inf, 0.0, lim * lim)  # NaN stays NaN: no pair
        if self._aug is None:
            self._aug = np.vstack([self.ref_vT, self.ref_bT, np.ones((1, len(self.ref_sq))), self.ref_sq[None, :],
                                   self.ref_n[None, :]]).astype(np.float32)
        c0 = l2 * q_n
        left = np.hstack([-2.0 * qv, l2[:, None] * qb, (q_sq - c0)[:, None], np.ones((len(qv), 1)), -l2[:, None]])
        s = left.astype(np.float32) @ self._aug
        # a float32 product of K terms is within K 2^-23 of the sum of their magnitudes (rounding of the
        # operands included), bounded per row from the largest reference
        r_sq, r_n = float(self.ref_sq.max(initial=0.0)), float(self.ref_n.max(initial=0.0))
        mag = 2.0 * np.sqrt(q_sq * r_sq) + c0 + np.abs(q_sq - c0) + r_sq + l2 * r_n
        cand = s < (left.shape[1] * 2.0**-23 * mag)[:, None]
        if inf.any():
            cand[inf] = True
        flat = np.flatnonzero(cand)  # (2-D nonzero costs 5x as much)
        del s, cand
        ri, ci = np.divmod(flat, len(self.ref_sq))
        dot = (qv @ self.ref_vT).ravel()[flat]
        common = (qb @ self.ref_bT).ravel()[flat]
        num = dot
        num *= -2.0
        num += q_sq[ri]
        num += self.ref_sq[ci]
        np.maximum(num, 0.0, out=num)
        den = self.ref_n.astype(np.float32)[ci] - common
        den += q.heard.astype(np.float32)[ri]
        with np.errstate(invalid="ignore"):
            ok = num < (lim * lim)[ri] * den
        ok &= den > 0
        if min_common > 0:
            ok &= common >= min_common
        return ri[ok].astype(np.int64), ci[ok].astype(np.int64), np.sqrt(num[ok] / den[ok])

    def rows_per_block(self, block_rows: int | None = None) -> int:
        """Query rows per block: at most ``block_rows`` and, above 16 rows, ``MAX_BLOCK_CELLS`` cells."""
        cap = max(16, MAX_BLOCK_CELLS // max(1, len(self.ref)))
        return min(block_rows, cap) if block_rows else cap

    def iter_blocks(
        self, q: FingerprintMatrix, *, min_common: int = 1, block_rows: int | None = None
    ) -> Iterator[tuple[int, NDArray, NDArray]]:
        """Yield ``(first_row, distances, common)`` over row blocks of ``q``: at most ``block_rows`` rows
        and, above 16 rows, ``MAX_BLOCK_CELLS`` cells each."""
        rows = self.rows_per_block(block_rows)
        for start in range(0, len(q), rows):
            d, c = self.block(q.rows(slice(start, start + rows)), min_common=min_common)
            yield start, d, c


def rss_distance(a: Mapping[str, float], b: Mapping[str, float], missing_dbm: float = DEFAULT_MISSING_DBM) -> float:
    """Eq. 9 for one pair, straight from the definition (reference implementation for tests)."""
    union = set(a) | set(b)
    if not union:
        return float("inf")
    s = sum((a.get(k, missing_dbm) - b.get(k, missing_dbm)) ** 2 for k in union)
    return float(np.sqrt(s / len(union)))
