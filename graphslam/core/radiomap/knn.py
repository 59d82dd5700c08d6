"""kNN and weighted kNN fingerprint positioning: Sørensen on powed RSS (the default) or the
paper's RSS distance (eq. 9).

The distances and the k nearest references come from ``graphslam.core.radiomap.neighbours``
(exact) or ``graphslam.core.radiomap.ivf`` (the inverted file); ``locate`` of at most
``FEW_MAX_QUERIES`` scans (the service's requests) takes the few-query path there (``FewQueries``).

Per query block: one ``argpartition`` for the k nearest, then vectorised
inverse-distance (or uniform) weighting, neighbour spread and label votes. There is
no Python loop per reference; the few-query path loops over its (<= 16) queries.

A query is *invalid* (flagged, or ``QueryError`` with ``strict=True``) when no
reference fingerprint shares ``min_common`` APs with it; in particular when none of
its APs is known to the map.

Each answer also carries ``rss_diff_db``, the mean eq. 9 distance from the query to its neighbours
(``neighbours.pair_eq9``: the pairs only), what the map's outside test reads
(``knn_types.OutsideTest``).

The configuration and the answers (``KnnConfig``, ``KnnResult``) are in
``graphslam.core.radiomap.knn_types``, re-exported here.
"""

from __future__ import annotations

import logging
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from graphslam.core.radiomap.fingerprints import DistanceEngine, FingerprintMatrix, heard_floor
from graphslam.core.radiomap.ivf import IvfIndex
from graphslam.core.radiomap.knn_types import (
    DEFAULT_IVF_PROBES,
    STATUS_NO_CANDIDATE,
    STATUS_NO_KNOWN_AP,
    STATUS_OK,
    WEIGHT_EPS_DB,
    IndexKind,
    KnnConfig,
    KnnResult,
    KnnUncertainty,
    Metric,
)
from graphslam.core.radiomap.neighbours import (
    GATHER_MAX_ROWS,
    FewQueries,
    SorensenRefs,
    candidate_block,
    eq9_few,
    gather_block,
    nearest,
    pair_eq9,
    sorensen_block,
    sorensen_few,
)
from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.core.types import Survey
from graphslam.errors import QueryError
from graphslam.names import INDEXES, METRICS

log = logging.getLogger(__name__)

# Cells (queries x references) of one distance block: ~8 MB of float64, cache-friendly
# enough that the block loop costs less than one huge allocation.
DEFAULT_BLOCK_CELLS = 1_000_000

# index="auto" switches to the IVF index from this many references: below it exact search is
# already fast and the index would not pay off.
IVF_AUTO_MIN_REFS = 5000
# Query rows per IVF block: the IVF loop is over clusters, so its fixed cost is per block;
# bigger blocks amortise it (the candidate buffer is ~rows x 2,000 float64 on UJIIndoorLoc).
IVF_BLOCK_ROWS = 4096

# Up to this many scans, ``locate`` takes the few-query path (``FewQueries``): scans encoded to plain
# arrays, distances evaluated on candidate references only. Why: one query's cost was mostly fixed
# costs (a scipy matrix per call, temporaries and a top-k over every reference).
FEW_MAX_QUERIES = GATHER_MAX_ROWS


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
            return sorensen_block(self._sorensen, q, self.config.min_common)
        if self.engine.dense:
            return self.engine.block(q, min_common=self.config.min_common)[0]
        if len(q) <= GATHER_MAX_ROWS:
            return gather_block(self.engine, q, self.config.min_common)
        return candidate_block(self.engine, q, self.config.min_common)

    @property
    def index_kind(self) -> str:
        """``"ivf"`` or ``"exact"``: the search actually used (``index="auto"`` resolved)."""
        return "ivf" if self.ivf is not None else "exact"

    def _block(self, q: FingerprintMatrix) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        k = self.config.k
        if self.ivf is None:
            return nearest(self.distances(q), k)
        idx, dist = self.ivf.search(q, k=k, probes=self.config.ivf_probes, min_common=self.config.min_common)
        # Fewer than k candidates in the probed clusters (a query at the edge of the map, or one
        # whose APs the probed places did not hear): answer those rows exactly, so a query is
        # flagged invalid only when the exact search would flag it too.
        short = np.flatnonzero(idx[:, min(k, len(self.radio_map)) - 1] < 0)
        if len(short):
            idx[short], dist[short] = nearest(self.distances(q.rows(short)), k)
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
        res = self._aggregate(idx, dist, n_known, q)
        err = strict_error(res, self.config.min_common) if strict else None
        if err is not None:
            raise err
        return res

    def _locate_few(self, scans: Sequence[Mapping[str, float]], strict: bool) -> KnnResult:
        """``locate`` of a few scans (``FewQueries``): the same answers, bit for bit, for less fixed cost."""
        q = FewQueries(self.radio_map, scans)
        cfg = self.config
        if self.ivf is None and self._sorensen is not None:
            idx, dist = sorensen_few(self._sorensen, q, cfg.min_common, cfg.k)
        elif self.ivf is None and not self.engine.dense:
            idx, dist = eq9_few(self.engine, q, cfg.min_common, cfg.k)
        elif self.ivf is not None:
            idx, dist = self._ivf_few(q)
        else:
            idx, dist = self._block(q.matrix(self.radio_map))
        res = self._aggregate(idx, dist, q.counts.astype(np.int64), q)
        err = strict_error(res, cfg.min_common) if strict else None
        if err is not None:
            raise err
        return res

    def _ivf_few(self, q: FewQueries) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """``_block`` with the IVF index for a ``FewQueries``: its arrays passed as they are (no matrix)."""
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
            idx[short], dist[short] = nearest(self.distances(q.matrix(self.radio_map).rows(short)), k)
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
        floor = heard_floor(rm.min_rssi_dbm, rm.missing_dbm)
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

    def rss_diff_db(self, q: FingerprintMatrix | FewQueries, idx: NDArray[np.int64], dist: NDArray[np.float64]) -> NDArray[np.float64]:
        """(len(q),) ``KnnResult.rss_diff_db`` of the queries ``q`` whose neighbours are ``idx`` (their
        distances ``dist``: eq. 9's already, when it is the metric). NaN where no neighbour."""
        d = dist if self.config.metric == "eq9" else self._pair_eq9(q, idx)
        ok = idx >= 0
        with np.errstate(invalid="ignore", divide="ignore"):
            out = np.where(ok, d, 0.0).sum(axis=1) / ok.sum(axis=1)
        out[~ok.any(axis=1)] = np.nan
        return out

    def _pair_eq9(self, q: FingerprintMatrix | FewQueries, idx: NDArray[np.int64]) -> NDArray[np.float64]:
        eng = self.engine
        if isinstance(q, FewQueries):
            return pair_eq9(eng.ref, eng.ref_sq, eng.ref_n, q.indptr, q.indices, q.data, q.extra_sq,
                            q.extra_n.astype(np.int64), idx)
        v = q.values
        return pair_eq9(eng.ref, eng.ref_sq, eng.ref_n, v.indptr, v.indices, v.data, q.extra_sq,
                        np.asarray(q.extra_n, np.int64), idx)

    def _aggregate(
        self, idx: NDArray[np.int64], dist: NDArray[np.float64], n_known: NDArray[np.int64],
        q: FingerprintMatrix | FewQueries | None = None,
    ) -> KnnResult:
        """The answers from each query's neighbours ``idx`` and distances ``dist``; with the queries
        ``q``, their ``rss_diff_db`` too."""
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
            rss_diff_db=None if q is None else self.rss_diff_db(q, idx, dist),
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


__all__ = [
    "DEFAULT_BLOCK_CELLS", "DEFAULT_IVF_PROBES", "FEW_MAX_QUERIES", "INDEXES", "IVF_AUTO_MIN_REFS", "IVF_BLOCK_ROWS",
    "METRICS", "STATUS_NO_CANDIDATE", "STATUS_NO_KNOWN_AP", "STATUS_OK", "WEIGHT_EPS_DB", "IndexKind", "KnnConfig",
    "KnnLocator", "KnnResult", "Metric", "SurveyPositions", "locate_survey", "strict_error",
]
