"""Batch helpers of the search workers: vectorised encoding, and splitting a batch by place.

- ``ScanEncoder.encode(flat, rows)``: ``RadioMap.encode`` of some rows of a parsed body
  (``parsing.FlatScans``), from the flattened readings the validation already built: the
  same ``FingerprintMatrix`` (same arrays, same floats), cheaper than its per-reading
  Python loop.
- ``PlaceSplit.split(flat, parts)``: the rows of a batch in ``parts`` groups of nearby
  places, for the search workers. Why: an IVF search costs a loop over the clusters its
  queries probe (~0.04 ms per cluster, ~0.03 ms per query on UJIIndoorLoc); two halves of
  a batch in request order each probe most clusters (~250 of 314), two halves by place
  ~115 and ~200: the slower half's search drops from ~23 to ~19 ms per 1,000-fingerprint
  batch. Groups are balanced on that cost, not on row counts.

How places are ordered, once at start-up: clusters probed together by the map's own
fingerprints are neighbours; the clusters are sorted along the Fiedler vector of that
graph (spectral ordering: neighbours end up close in the order), so a contiguous range of
the order is a compact region. A query's place is the cluster where its strongest AP is
heard the strongest (a proxy for its nearest centroid that costs no encoding). Splitting
only changes which worker searches a row: results are the in-process ones (see pool.py).
"""

from __future__ import annotations

from itertools import repeat
from operator import itemgetter

import numpy as np
from numpy.typing import NDArray
from scipy import sparse
from scipy.sparse.csgraph import connected_components

from graphslam.core.radiomap.fingerprints import FingerprintMatrix, heard_floor
from graphslam.core.radiomap.knn import KnnLocator
from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.errors import ConfigError, QueryError
from graphslam.service.parsing import FlatScans

# Cost of probing one more cluster, in query rows (the ratio of the two costs fitted on
# UJIIndoorLoc, with one BLAS thread).
CLUSTER_COST_ROWS = 1.3
# Map fingerprints probed to find which clusters are searched together (a strided sample above).
PLACE_GRAPH_MAX_REFS = 20_000
# Spectral ordering is a dense eigendecomposition per connected component: above this many
# clusters (~1M-fingerprint maps) it would take seconds at start-up, so batches are split in order.
PLACE_MAX_CLUSTERS = 2048


def _take(seq: list[str], pos: NDArray[np.int64]) -> list[str]:
    """``[seq[i] for i in pos]`` at C speed (itemgetter returns a bare item for one index)."""
    if len(pos) == 0:
        return []
    got = itemgetter(*pos.tolist())(seq)
    return list(got) if len(pos) > 1 else [got]


def reading_positions(
    offsets: NDArray[np.int64], rows: NDArray[np.int64]
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Flat positions of the readings of ``rows`` (in that order) and, for each, its index in ``rows``."""
    starts = offsets[rows]
    lens = offsets[rows + 1] - starts
    ends = np.cumsum(lens)
    pos = np.repeat(starts - (ends - lens), lens) + np.arange(int(ends[-1]) if len(ends) else 0)
    return pos, np.repeat(np.arange(len(rows)), lens)


class ScanEncoder:
    """``radio_map.encode`` for rows of a ``FlatScans``: the same matrix, floats and all."""

    def __init__(self, radio_map: RadioMap) -> None:
        self.bssids = radio_map.bssids
        self.index = {b: j for j, b in enumerate(radio_map.bssids)}
        self.missing_dbm = radio_map.missing_dbm
        self.floor = heard_floor(radio_map.min_rssi_dbm, radio_map.missing_dbm)  # as FingerprintMatrix.encode

    def encode(self, flat: FlatScans, rows: NDArray[np.int64]) -> FingerprintMatrix:
        """Row i of the result is ``flat.scans[rows[i]]``."""
        rows = np.asarray(rows, np.int64)
        pos, local = reading_positions(flat.offsets, rows)
        v = flat.values[pos]
        keep = v >= self.floor
        pos, local, v = pos[keep], local[keep], v[keep]
        cols = np.fromiter(map(self.index.get, _take(flat.keys, pos), repeat(-1)), np.int64, len(pos))
        known = cols >= 0
        n = len(rows)
        # Same (row, column, value) triplets in the same order as the per-reading loop: same CSR.
        m = sparse.csr_matrix(
            (v[known] - self.missing_dbm, (local[known], cols[known])), shape=(n, len(self.bssids))
        )
        extra_sq = np.zeros(n)
        extra_n = np.zeros(n, np.int64)
        # APs the map does not know: few per query; summed in Python, in reading order, exactly as
        # FingerprintMatrix.encode does (float ** 2, sequential adds), so the floats are the same.
        for i, r in zip(local[~known].tolist(), v[~known].tolist()):
            extra_sq[i] += (r - self.missing_dbm) ** 2
            extra_n[i] += 1
        fm = FingerprintMatrix(self.bssids, m, self.missing_dbm, extra_sq, extra_n)
        if not (np.isfinite(fm.values.data).all() and np.isfinite(fm.extra_sq).all()):
            raise QueryError("query scans hold a non-finite RSS value")  # as RadioMap.encode
        return fm


def _fiedler_order(w: sparse.csr_matrix) -> NDArray[np.int64]:
    """Nodes of a weighted graph in spectral order: per connected component (in order of their
    smallest node), sorted by the Fiedler vector of its normalised Laplacian."""
    n_comp, labels = connected_components(w, directed=False)
    out: list[NDArray[np.int64]] = []
    for c in range(n_comp):
        nodes = np.flatnonzero(labels == c)
        if len(nodes) < 3:
            out.append(nodes)
            continue
        a = w[nodes][:, nodes].toarray()
        np.fill_diagonal(a, 0.0)
        inv_sqrt = 1.0 / np.sqrt(a.sum(axis=1))
        lap = np.eye(len(nodes)) - inv_sqrt[:, None] * a * inv_sqrt[None, :]
        vec = np.linalg.eigh(lap)[1][:, 1] * inv_sqrt
        out.append(nodes[np.argsort(vec, kind="stable")])
    return np.concatenate(out).astype(np.int64)


class PlaceSplit:
    """Splits batches of queries by place for ``locator``'s IVF index (see the module docstring).
    Built once in the server process; the search workers inherit it. ``split`` is
    deterministic: every worker computes the same groups from the same body."""

    def __init__(self, locator: KnnLocator) -> None:
        ivf = locator.ivf
        if ivf is None or not 2 <= ivf.n_clusters <= PLACE_MAX_CLUSTERS:
            raise ConfigError(f"split by place needs an IVF index of 2 to {PLACE_MAX_CLUSTERS} clusters")
        c = ivf.n_clusters
        self.probes = min(locator.config.ivf_probes, c)
        refs = locator.radio_map.fingerprints
        sample = refs.rows(np.arange(0, len(refs), max(1, -(-len(refs) // PLACE_GRAPH_MAX_REFS))))
        probed = ivf.probe(sample, self.probes)
        inc = sparse.csr_matrix(
            (np.ones(probed.size), (np.repeat(np.arange(len(probed)), probed.shape[1]), probed.ravel())),
            shape=(len(probed), c),
        )
        order = _fiedler_order((inc.T @ inc).tocsr())
        self.rank = np.empty(c + 1, np.int64)
        self.rank[order] = np.arange(c)
        self.rank[c] = c  # "cluster" c: queries whose strongest AP the map does not know, last
        # Clusters searched from a place: those a query at the centroid would probe.
        g = ivf.centroids.astype(np.float64) @ ivf.centroids_T.astype(np.float64)
        d = ivf.centroid_sq[None, :] - 2.0 * g
        self.near = np.argpartition(d, self.probes - 1, axis=1)[:, : self.probes].astype(np.int64)
        home = np.argmax(ivf.centroids, axis=0)  # per AP: the cluster whose members hear it strongest
        self.home = dict(zip(locator.radio_map.bssids, home.tolist()))
        self.n_clusters = c

    def split(self, flat: FlatScans, parts: int) -> list[NDArray[np.int64]]:
        """``parts`` groups of row indices (each ascending; together every row once), grouped by
        place and balanced on estimated search cost."""
        n = len(flat)
        if parts <= 1 or n <= 1:
            return [np.arange(n, dtype=np.int64)] + [np.zeros(0, np.int64)] * max(0, parts - 1)
        off, v = flat.offsets, flat.values
        row_max = np.maximum.reduceat(v, off[:-1])  # every scan has >= 1 reading (validated)
        row_of = np.repeat(np.arange(n), np.diff(off))
        cand = np.flatnonzero(v == row_max[row_of])
        first = cand[np.r_[True, row_of[cand[1:]] != row_of[cand[:-1]]]]  # strongest reading, first if tied
        home = np.fromiter(
            map(self.home.get, _take(flat.keys, first), repeat(self.n_clusters)), np.int64, n
        )
        order = np.argsort(self.rank[home], kind="stable")
        # Cost of each row in that order: 1 + CLUSTER_COST_ROWS per cluster it brings into the search
        # (the clusters near its place that no earlier row's place brought).
        h = home[order]
        run_start = np.flatnonzero(np.r_[True, h[1:] != h[:-1]])
        runs = h[run_start]
        runs = runs[runs < self.n_clusters]
        cost = np.ones(n)
        if len(runs):
            _, first_seen = np.unique(self.near[runs].ravel(), return_index=True)
            fresh = np.bincount(first_seen // self.probes, minlength=len(runs))
            cost[run_start[: len(runs)]] += CLUSTER_COST_ROWS * fresh
        cum = np.cumsum(cost)
        cuts = np.searchsorted(cum, cum[-1] * np.arange(1, parts) / parts)
        bounds = np.concatenate([[0], cuts, [n]])
        return [np.sort(order[lo:hi]) for lo, hi in zip(bounds[:-1], bounds[1:])]
