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

Memory: similarities are computed in row blocks (``block_rows`` x N), never N x N.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import sparse

from graphslam.core.radiomap.fingerprints import MAX_BLOCK_CELLS, FingerprintMatrix


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

    def top_matches(self, group: NDArray[np.int64], k: int, *, block_rows: int = 512) -> Matches:
        """For every fingerprint, its ``k`` most similar fingerprints of another group (walk)."""
        n = len(self)
        group = np.asarray(group, dtype=np.int64)
        if len(group) != n:
            raise ValueError("top_matches: one group label per fingerprint")
        k = int(min(k, max(n - 1, 0)))
        if n == 0 or k <= 0:
            z = np.zeros(0, np.int64)
            return Matches(z, z, np.zeros(0))
        rows = max(1, min(block_rows, MAX_BLOCK_CELLS // max(n, 1)))
        ut = self.unit.T.tocsc()
        out_i, out_j, out_s = [], [], []
        for a in range(0, n, rows):
            b = min(n, a + rows)
            block = (self.unit[a:b] @ ut).toarray()
            block[group[a:b, None] == group[None, :]] = -1.0
            top = np.argpartition(-block, k - 1, axis=1)[:, :k]
            s = np.take_along_axis(block, top, axis=1)
            ok = s > 0  # a partner that shares no access point is no match
            out_i.append(np.repeat(np.arange(a, b), k)[ok.ravel()])
            out_j.append(top.ravel()[ok.ravel()])
            out_s.append(s.ravel()[ok.ravel()])
        return Matches(np.concatenate(out_i), np.concatenate(out_j), np.concatenate(out_s))
