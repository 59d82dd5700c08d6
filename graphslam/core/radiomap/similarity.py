"""Power-cosine fingerprint similarity, and each fingerprint's most similar partners.

A reading of r dBm becomes exp(r / scale) (0 where not heard); a fingerprint is the unit
vector of those values and the similarity of two fingerprints is their cosine, in [0, 1].
Why not eq. 9 for placement:

- a constant RSS offset between two phones multiplies every value by the same factor,
  which the normalisation removes: the similarity is device-invariant by construction;
- strong readings dominate (exp), weak and missing ones barely count, so the value
  reflects the access points near the phone rather than which far ones it happened to hear.

Measured on IPIN 2023 floor -2 (lab/journal/benchmarks-history.md): near (< 4 m) vs far
(> 15 m) cross-walk pairs separate with AUC 0.96 for same-phone and different-phone pairs
alike (eq. 9: 0.92 / 0.90), and the distribution of the similarity against distance
within a walk (PDR distance) matches the one across walks up to ~20 m. ``scale_db``
10-15 dB gave the same figures; 10 dB is the default (~amplitude: exp(r / 8.7 dB)).

Memory: similarities are computed in row blocks (``block_rows`` x N), never N x N. Where the
fingerprints fit a dense matrix of ``DENSE_MAX_CELLS`` (N x A) and fill ``DENSE_MIN_FILL`` of it (many
fingerprints over few access points, as in a large simulated survey), each block is one float32 BLAS product: a sparse x sparse
product of a nearly dense result costs far more. The chosen partners' similarities are recomputed
in float64 from the sparse rows, so both paths report the same values.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import sparse

from graphslam.core.common.arrays import nonzero_2d
from graphslam.core.radiomap.fingerprints import MAX_BLOCK_CELLS, FingerprintMatrix

DENSE_MAX_CELLS = 20_000_000  # N x A of the dense float32 path (80 MB)
DENSE_MIN_FILL = 0.05  # below this share of heard readings the sparse product is cheaper


@dataclass(frozen=True, eq=False)
class Matches:
    """Directed pairs (i -> j): j is one of the most similar fingerprints of i outside i's group."""

    i: NDArray[np.int64]
    j: NDArray[np.int64]
    similarity: NDArray[np.float64]  # cosine in [0, 1]

    def __len__(self) -> int:
        return len(self.i)


@dataclass(frozen=True, eq=False)
class PowerCosine:
    """Unit rows of exp(rssi / scale_db) over an AP index (see the module docstring)."""

    unit: sparse.csr_matrix  # (N, A)
    scale_db: float

    @classmethod
    def of(cls, fm: FingerprintMatrix, scale_db: float = 10.0) -> "PowerCosine":
        if not scale_db > 0:
            raise ValueError("PowerCosine: scale_db must be > 0")
        v = fm.values.copy()
        # v = rssi - missing > 0 where heard; exp(rssi / s) is exp(v / s) up to a constant factor,
        # which the row normalisation removes
        v.data = np.exp((v.data - v.data.max(initial=0.0)) / scale_db)
        norm = np.sqrt(np.asarray(v.multiply(v).sum(axis=1)).ravel())
        inv = np.divide(1.0, norm, out=np.zeros_like(norm), where=norm > 0)
        return cls(sparse.csr_matrix(sparse.diags(inv) @ v), float(scale_db))

    def __len__(self) -> int:
        return self.unit.shape[0]

    def pairs(self, i: NDArray[np.int64], j: NDArray[np.int64]) -> NDArray[np.float64]:
        """Similarity of the given pairs (vectorised, no dense matrix)."""
        if len(i) == 0:
            return np.zeros(0)
        return np.asarray(self.unit[i].multiply(self.unit[j]).sum(axis=1)).ravel()

    def top_matches(
        self, group: NDArray[np.int64], k: int, *, block_rows: int = 512, rows: NDArray[np.int64] | None = None
    ) -> Matches:
        """For every fingerprint (``rows``: for these only), its ``k`` most similar fingerprints of
        another group (walk)."""
        n = len(self)
        group = np.asarray(group, dtype=np.int64)
        if len(group) != n:
            raise ValueError("top_matches: one group label per fingerprint")
        k = int(min(k, max(n - 1, 0)))
        if n == 0 or k <= 0 or (rows is not None and len(rows) == 0):
            z = np.zeros(0, np.int64)
            return Matches(z, z, np.zeros(0))
        if rows is not None:
            return self._top_of_rows(group, k, np.asarray(rows, np.int64), block_rows)
        rows = max(1, min(block_rows, MAX_BLOCK_CELLS // max(n, 1)))
        u, ut = self._operands()
        # groups (walks) are usually contiguous runs: mask each row's own run by slices
        runs = _runs(group)
        out_i, out_j = [], []
        for a in range(0, n, rows):
            b = min(n, a + rows)
            block = u[a:b] @ ut if u is not None else (self.unit[a:b] @ ut).toarray()
            if runs is not None:
                for g0, g1, r0, r1 in _overlaps(runs, a, b):
                    block[r0 - a:r1 - a, g0:g1] = -1.0
            else:
                block[group[a:b, None] == group[None, :]] = -1.0
            ri, ci = row_top_k(block, k)
            out_i.append(ri + a)
            out_j.append(ci)
        i, j = np.concatenate(out_i), np.concatenate(out_j)
        return Matches(i, j, self.pairs(i, j))


    def _operands(self) -> tuple[NDArray[np.float32] | None, Any]:
        """(dense float32 fingerprints or None, the right-hand side of the block products): one float32
        BLAS product per block where the fingerprints fill ``DENSE_MIN_FILL`` of a dense matrix of at
        most ``DENSE_MAX_CELLS`` (module docstring), else the sparse product."""
        u = self._dense()
        if u is not None:
            return u, np.ascontiguousarray(u.T)
        return None, self.unit.T.tocsc()

    def _dense(self) -> NDArray[np.float32] | None:
        """The fingerprints as a dense float32 matrix where they fill ``DENSE_MIN_FILL`` of one of at most
        ``DENSE_MAX_CELLS``, else None (``_operands``)."""
        cells = len(self) * self.unit.shape[1]
        if cells <= DENSE_MAX_CELLS and self.unit.nnz >= DENSE_MIN_FILL * cells:
            return self.unit.toarray().astype(np.float32)
        return None

    def _top_of_rows(self, group: NDArray[np.int64], k: int, rows: NDArray[np.int64], block_rows: int) -> Matches:
        """``top_matches`` of some rows against every fingerprint (an update's new walks)."""
        n = len(self)
        step = max(1, min(block_rows, MAX_BLOCK_CELLS // max(n, 1)))
        u, ut = self._operands()  # the same products as ``top_matches``: the same partners
        runs = _runs(group)
        out_i, out_j = [], []
        for a in range(0, len(rows), step):
            r = rows[a:a + step]
            block = u[r] @ ut if u is not None else (self.unit[r] @ ut).toarray()
            if runs is not None:  # each row's own walk is one run of columns
                for g0, g1, label in runs[np.isin(runs[:, 2], group[r])].tolist():
                    block[np.flatnonzero(group[r] == label)[:, None], np.arange(g0, g1)] = -1.0
            else:
                block[group[r][:, None] == group[None, :]] = -1.0
            ri, ci = row_top_k(block, k)
            out_i.append(r[ri])
            out_j.append(ci)
        i, j = np.concatenate(out_i), np.concatenate(out_j)
        return Matches(i, j, self.pairs(i, j))


def top_matches_between(a: PowerCosine, b: PowerCosine, k: int, *, block_rows: int = 512) -> Matches:
    """For every fingerprint of ``a``, its ``k`` most similar fingerprints of ``b`` (both over one AP
    index; ``j`` indexes ``b``), sharing at least one access point: ``top_matches``' products (one
    float32 BLAS product per block where both fill a dense matrix) and its choice of partners."""
    if a.unit.shape[1] != b.unit.shape[1]:
        raise ValueError("top_matches_between: both sets must be over one AP index")
    k = int(min(k, len(b)))
    if len(a) == 0 or k <= 0:
        z = np.zeros(0, np.int64)
        return Matches(z, z, np.zeros(0))
    ua = a._dense()  # the left side row blocks only: no transposed copy
    ub, ubt = b._operands()
    if (ua is None) != (ub is None):  # one dense, one not: both as the sparse product
        ua, ubt = None, b.unit.T.tocsc()
    step = max(1, min(block_rows, MAX_BLOCK_CELLS // max(len(b), 1)))
    out_i, out_j = [], []
    for r0 in range(0, len(a), step):
        r1 = min(len(a), r0 + step)
        block = ua[r0:r1] @ ubt if ua is not None else (a.unit[r0:r1] @ ubt).toarray()
        ri, ci = row_top_k(block, k)
        out_i.append(ri + r0)
        out_j.append(ci)
    i, j = np.concatenate(out_i), np.concatenate(out_j)
    # the chosen partners' similarities in float64 from the sparse rows, as ``pairs``
    return Matches(i, j, np.asarray(a.unit[i].multiply(b.unit[j]).sum(axis=1)).ravel())


# Columns per group of ``row_top_k``'s first pass.
TOP_K_GROUP = 64


def row_top_k(block: NDArray, k: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """(row, column) of each row's ``k`` largest positive values (a partner that shares no access
    point is no match), per row largest first, ties to the lower column.

    Why not ``argpartition`` of every row: it cost ~19 ms per block of 71 x 28k (paper size 12, 8.6 s
    of the survey). The k-th largest of the rows' maxima over groups of ``TOP_K_GROUP`` columns is at
    most the row's k-th largest value (k groups hold a value at least that large), so the values at
    or above it hold the answer, and they are few: only those are sorted. Narrower groups where the
    columns are few, so that there are 4k of them (with fewer than k every positive value is sorted)."""
    r, n = block.shape
    g = max(1, min(TOP_K_GROUP, n // (4 * max(k, 1))))
    groups = -(-n // g)
    gmax = np.empty((r, groups), block.dtype)
    full = n // g
    if full:
        gmax[:, :full] = block[:, : full * g].reshape(r, full, g).max(axis=2)
    if full < groups:
        gmax[:, full] = block[:, full * g :].max(axis=1)
    tiny = np.finfo(block.dtype).tiny
    tau = np.maximum(np.partition(gmax, groups - k, axis=1)[:, groups - k], tiny) if groups >= k else np.full(r, tiny)
    ri, ci = nonzero_2d(block >= tau[:, None])
    v = block[ri, ci]
    o = np.lexsort((ci, -v, ri))
    ri, ci = ri[o], ci[o]
    keep = (np.arange(len(ri)) - np.searchsorted(ri, ri, side="left")) < k
    return ri[keep].astype(np.int64), ci[keep].astype(np.int64)


def _runs(group: NDArray[np.int64]) -> NDArray[np.int64] | None:
    """(R, 3) start, end, label of the runs of equal labels when every label forms one run, else None."""
    if len(group) == 0:
        return None
    cut = np.flatnonzero(np.diff(group) != 0) + 1
    starts = np.concatenate([[0], cut])
    ends = np.concatenate([cut, [len(group)]])
    labels = group[starts]
    if len(np.unique(labels)) != len(labels):
        return None
    return np.column_stack([starts, ends, labels])


def _overlaps(runs: NDArray[np.int64], a: int, b: int):
    """Per run meeting rows [a, b): (run start, run end, first row, end row) of its own block."""
    k0 = int(np.searchsorted(runs[:, 1], a, side="right"))
    for g0, g1, _ in runs[k0:]:
        if g0 >= b:
            break
        yield int(g0), int(g1), max(a, int(g0)), min(b, int(g1))
