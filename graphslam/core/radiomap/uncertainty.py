"""A calibrated uncertainty for kNN answers, measured on the radio map itself.

A kNN answer's error grows with how far apart its neighbours lie (``KnnResult.spread``: the weighted
RMS distance of their positions to the estimate), but not one for one: neighbours can agree on a
wrong place, and a place the map covers densely is still only resolved to a few metres. It grows
too with how poorly the best matches match (``KnnResult.score``), most where the query comes from
a place the map has not walked. The model::

    sigma = scale_b * sqrt(spread^2 + floor_m^2)        (isotropic, metres; per axis)

with ``floor_m`` fixed and ``scale_b`` a step function of the answer's score (``score_edges``: bins
of the score), measured without ground truth on two sets of the map's own scans (a seeded sample of
its walks, each located with the same kNN: metric, k, weights):

- *covered*: each walk located on the map of the other walks (its own fingerprints masked, the
  access points only it heard moved out of the index): a scan where other walks have been;
- *uncovered*: the same scans located with also every fingerprint within ``UNCOVERED_RADIUS_M`` of
  the walk's path removed: a scan from a place the map has not walked (a new corridor, a route
  nobody surveyed).

Per score bin (quantiles of both sets' scores), ``scale_b`` puts 95 % of the bin's errors inside
the 95 % circle of a 2-D Gaussian (``r95 = sqrt(-2 ln 0.05) sigma = 2.448 sigma``), the uncovered
scans counted with weight ``UNCOVERED_WEIGHT`` (the share of queries from unwalked places assumed,
relative to walked ones); the scales never fall as the score worsens. ``scale`` is the covered
set's single scale (what maps calibrated before the bins use, and the answer for a score the bins
cannot place). A map of one walk has nothing to leave out: no calibration (``None``).

Why the second set: calibrated on covered scans alone, the 95 % circles of walks on a route absent
from the map held 58 % of the truths (IPIN 2023 floor -2, leave one route out); docs/radio_map.md
gives the figures per floor.

The same pass measures the outside test (``knn_types.OutsideTest``): whether an answer comes from a
place the map's walks have not been, from its ``KnnResult.rss_diff_db`` (the mean eq. 9 distance
from the query to its neighbours). Its covered scans are those of the covered set within
``NEAR_M`` of another walk's fingerprint; its *outside* set, the same scans located also without
every fingerprint within ``OUTSIDE_RADIUS_M`` of each (a disc around the scan, not the walk's path:
a map whose walks all follow one path keeps something to locate on). The threshold flags
``FALSE_ALARM`` of the covered scans; the outside sigma holds 95 % of the outside scans' errors.
Why eq. 9's distance and not the Sørensen score, and why a sample of 24 walks: lab/journal/coverage.md.

Frames and units: the radio map's frame, metres.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Mapping

import numpy as np
from numpy.typing import NDArray
from scipy import sparse
from scipy.spatial import cKDTree

from graphslam.core.radiomap.fingerprints import FingerprintMatrix
from graphslam.core.radiomap.knn import KnnLocator
from graphslam.core.radiomap.knn_types import OUTSIDE_LEVELS, WEIGHT_EPS_DB, KnnConfig, KnnUncertainty, OutsideTest
from graphslam.core.radiomap.neighbours import nearest
from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.errors import ConfigError

R95 = math.sqrt(-2.0 * math.log(0.05))  # radius / sigma of a 2-D Gaussian's 95 % circle
DEFAULT_FLOOR_M = 2.0
UNCOVERED_RADIUS_M = 5.0  # the uncovered set: map fingerprints this close to the walk's path removed
UNCOVERED_WEIGHT = 0.4  # an uncovered scan's weight in the bins' quantiles (a covered one: 1)
SCORE_BINS = 5  # quantile bins of the calibration scans' scores
OUTSIDE_RADIUS_M = 10.0  # the outside set: map fingerprints this close to the scan removed
NEAR_M = 3.0  # the outside test's covered scans: within this of another walk's fingerprint
FALSE_ALARM = 0.05  # share of those the outside test flags
# query x fingerprint distances of a batch of walks located together (2 MB of float64 a set): where one walk's
# alone are more, it is located alone (the per-call cost is small beside its searches, and a copy is not)
BATCH_CELLS = 1 << 18


def leave_one_session_out(
    rm: RadioMap, rows: NDArray[np.int64] | None = None, *, config: KnnConfig | None = None, extra: int = 30
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """((len(rows), 2) error vectors (estimate - map position, m), (len(rows),) spreads, (len(rows),)
    scores) of the map's fingerprints ``rows`` (default all), each located among the other sessions'
    fingerprints: the ``k`` nearest of another session among its ``k + extra`` nearest overall,
    weighted and scored as ``KnnLocator``. NaN rows: every candidate came from the fingerprint's own
    session."""
    cfg = config or KnnConfig()
    rows = np.arange(len(rm)) if rows is None else np.asarray(rows, np.int64)
    wide = KnnConfig(k=min(cfg.k + extra, len(rm)), metric=cfg.metric, index="exact", weighted=cfg.weighted)
    res = KnnLocator(rm, wide).locate(rm.fingerprints.rows(rows))
    idx, dist = res.neighbours, res.distances
    other = (idx >= 0) & (rm.session_ids[np.maximum(idx, 0)] != rm.session_ids[rows][:, None])
    use = other & (np.cumsum(other, axis=1) <= cfg.k)
    if cfg.weighted:
        w = np.where(use, 1.0 / (np.where(use, dist, 0.0) + WEIGHT_EPS_DB), 0.0)
    else:
        w = use.astype(float)
    wsum = w.sum(axis=1)
    ok = wsum > 0
    e = np.full((len(rows), 2), np.nan)
    spread = np.full(len(rows), np.nan)
    score = np.full(len(rows), np.nan)
    score[ok] = np.where(use[ok], dist[ok], 0.0).sum(axis=1) / use[ok].sum(axis=1)
    nxy = rm.xy[np.maximum(idx[ok], 0)]
    est = (w[ok, :, None] * nxy).sum(axis=1) / wsum[ok, None]
    e[ok] = est - rm.xy[rows[ok]]
    spread[ok] = np.sqrt((w[ok] * ((nxy - est[:, None, :]) ** 2).sum(axis=2)).sum(axis=1) / wsum[ok])
    return e, spread, score


def calibrate_uncertainty(
    rm: RadioMap, config: KnnConfig | None = None, *, floor_m: float = DEFAULT_FLOOR_M, max_queries: int = 600,
    max_sessions: int = 24, seed: int = 0, uncovered_radius_m: float = UNCOVERED_RADIUS_M,
    uncovered_weight: float = UNCOVERED_WEIGHT, bins: int = SCORE_BINS, outside_radius_m: float = OUTSIDE_RADIUS_M,
    near_m: float = NEAR_M, false_alarm: float = FALSE_ALARM,
) -> KnnUncertainty | None:
    """``KnnUncertainty`` of ``config`` on ``rm`` (module docstring): up to ``max_sessions`` walks
    (a seeded sample), up to ``max_queries`` of their scans in all, each located on the map of the
    other walks (covered) and again without the fingerprints within ``uncovered_radius_m`` of its
    walk (uncovered); ``bins`` score bins (1: one scale for all, the covered set's, and no uncovered
    set). The outside test (``OutsideTest``): the covered scans within ``near_m`` of another walk's
    fingerprint against the same scans located also without the fingerprints within
    ``outside_radius_m`` of each, flagging ``false_alarm`` of the former (``outside_radius_m`` 0: no
    test). None for a map of one walk, or when no scan can be located among the others."""
    if not (math.isfinite(floor_m) and floor_m > 0):
        raise ConfigError(f"kNN uncertainty: floor_m must be a positive number of metres, got {floor_m}")
    if not (math.isfinite(uncovered_radius_m) and uncovered_radius_m >= 0 and uncovered_weight >= 0 and bins >= 1):
        raise ConfigError("kNN uncertainty: uncovered_radius_m and uncovered_weight must be >= 0 and bins >= 1")
    if not (math.isfinite(outside_radius_m) and outside_radius_m >= 0 and near_m >= 0 and 0 < false_alarm < 1):
        raise ConfigError("kNN uncertainty: outside_radius_m and near_m must be >= 0, false_alarm between 0 and 1")
    cfg = KnnConfig(k=(config or KnnConfig()).k, weighted=(config or KnnConfig()).weighted,
                    metric=(config or KnnConfig()).metric, index="exact")
    names, codes = np.unique(rm.session_ids, return_inverse=True)
    codes = codes.reshape(-1).astype(np.int64)
    if len(rm) < 2 or len(names) < 2:
        return None
    rng = np.random.default_rng(seed)
    sessions = np.arange(len(names))
    if len(sessions) > max_sessions:
        sessions = np.sort(rng.choice(sessions, max_sessions, replace=False))
    per = max(1, max_queries // len(sessions))
    # One locator on the whole map; each walk's scans searched with the removed fingerprints masked
    # out and the APs only they heard moved outside the index: what a map without them gives
    # (``RadioMap.reindex``), without building one per walk. Walks are located a batch at a time (each
    # row's answer is its own, the same bits in any batch), the batch's distances bounded to ``BATCH_CELLS``.
    loc = KnnLocator(rm, cfg, threads=1)
    values = rm.fingerprints.values
    heard = np.bincount(values.indices, minlength=rm.fingerprints.n_aps)  # fingerprints hearing each AP
    order = np.argsort(codes, kind="stable")
    first = np.searchsorted(codes[order], np.arange(len(names) + 1))
    tree = cKDTree(rm.xy)
    picks: list[tuple[int, NDArray[np.int64], NDArray[np.int64]]] = []  # (walk, its rows, its scans drawn)
    for code in sessions:
        own_rows = order[first[code] : first[code + 1]]  # ascending: a stable sort of the codes
        picks.append((int(code), own_rows,
                      np.sort(rng.choice(own_rows, per, replace=False)) if len(own_rows) > per else own_rows))
    # per set: (error norms, spreads, scores, near another walk, rss_diff_db) of the located scans
    sets: dict[str, list[tuple[NDArray, NDArray, NDArray, NDArray, NDArray]]] = {"covered": [], "uncovered": [], "outside": []}
    per_batch = max(1, BATCH_CELLS // max(len(rm), 1))
    batch: list[tuple[int, NDArray[np.int64], NDArray[np.int64]]] = []
    for i, pick in enumerate(picks):
        batch.append(pick)
        if i + 1 == len(picks) or sum(len(b[2]) for b in batch) + len(picks[i + 1][2]) > per_batch:
            for kind, found in _calibration_batch(rm, loc, tree, codes, values, heard, batch, bins > 1 and uncovered_radius_m > 0,
                                                  uncovered_radius_m, outside_radius_m, near_m, cfg.k).items():
                sets[kind].append(found)
            batch = []
    if not sets["covered"]:
        return None
    covered = [np.concatenate(v) for v in zip(*sets["covered"])]
    if not len(covered[0]):
        return None
    e, sp = covered[0], covered[1]
    base = np.sqrt(sp**2 + floor_m**2)
    scale = max(float(np.quantile(e / (R95 * base), 0.95)), 1e-3)
    coverage = float(np.mean(e <= R95 * scale * base))
    n = len(e)
    edges: tuple[float, ...] = ()
    scales: tuple[float, ...] = ()
    if sets["uncovered"]:
        uncovered_set = [np.concatenate(v) for v in zip(*sets["uncovered"])]
        n += len(uncovered_set[0])
        edges, scales = _score_bins(covered[:3], uncovered_set[:3], floor_m, uncovered_weight, bins)
    outside = None
    if sets["outside"]:
        out_e, _, _, _, out_db = (np.concatenate(v) for v in zip(*sets["outside"]))
        outside = _outside_test(covered[4][covered[3]], out_db, out_e, outside_radius_m, near_m, false_alarm)
    return KnnUncertainty(cfg.metric, cfg.k, cfg.weighted, scale, floor_m, n, coverage, edges, scales, outside)


def _calibration_batch(
    rm: RadioMap, loc: KnnLocator, tree: cKDTree, codes: NDArray[np.int64], values: sparse.csr_matrix,
    heard: NDArray[np.int64], batch: list[tuple[int, NDArray[np.int64], NDArray[np.int64]]], uncovered: bool,
    uncovered_radius_m: float, outside_radius_m: float, near_m: float, k: int,
) -> dict[str, tuple[NDArray, NDArray, NDArray, NDArray, NDArray]]:
    """``calibrate_uncertainty``'s sets of a batch of walks ((walk, its rows, its scans drawn) each): a
    walk's scans searched on the whole map, its removed fingerprints masked and the rows that heard an AP
    only they heard searched again without it; the batch located per set in one pass."""
    found: dict[str, list[tuple[FingerprintMatrix, NDArray, NDArray, NDArray]]] = {"covered": [], "uncovered": []}
    discs: list[tuple[NDArray, NDArray]] = []  # the outside set's removals: (row in the batch, fingerprint)
    at = 0
    for code, own_rows, picked in batch:
        own = codes == code
        removed = {"covered": own}
        if uncovered:
            # only fingerprints in the walk's box widened by the radius can be that close (a large map's
            # other places are not searched)
            lo, hi = rm.xy[own_rows].min(axis=0) - uncovered_radius_m, rm.xy[own_rows].max(axis=0) + uncovered_radius_m
            box = np.flatnonzero(((rm.xy >= lo) & (rm.xy <= hi)).all(axis=1))
            unc = own.copy()
            unc[box] |= np.isfinite(cKDTree(rm.xy[own_rows]).query(rm.xy[box], distance_upper_bound=uncovered_radius_m)[0])
            removed["uncovered"] = unc
        near = np.array([bool((codes[np.asarray(c, np.int64)] != code).any())
                         for c in tree.query_ball_point(rm.xy[picked], r=near_m)], bool).reshape(-1)
        own_q = rm.fingerprints.rows(picked)
        dropped = None
        for kind, gone in removed.items():
            drop = _heard_only_by(values, heard, gone)
            if dropped is None:  # one walk's scans searched together: the APs they hear, not the map's
                q = _without_columns(own_q, drop)
                d_all = loc.distances(q)
            elif not np.array_equal(drop, dropped):
                q, d_all = _distances_again(loc, own_q, d_all, dropped, drop)
            dropped = drop
            d = d_all.copy()
            d[:, gone] = np.inf
            found[kind].append((q, d, picked, near))
            if kind == "covered" and outside_radius_m > 0:
                # outside: each scan without the fingerprints within outside_radius_m of it (the APs only
                # they heard stay in the index, heard by no fingerprint left: as far for eq. 9)
                disc = tree.query_ball_point(rm.xy[picked], r=outside_radius_m)
                discs.append((at + np.repeat(np.arange(len(picked)), [len(c) for c in disc]),
                              np.concatenate(disc).astype(np.int64)))
        at += len(picked)
    out: dict[str, tuple[NDArray, NDArray, NDArray, NDArray, NDArray]] = {}
    for kind, parts in found.items():
        if parts:
            stacked = _stacked(parts)
            out[kind] = _located(loc, *stacked, k, with_db=kind == "covered")
            if kind == "covered" and discs:  # located: its distances are the outside set's, masked
                q, d, rows, near = stacked
                d[np.concatenate([r for r, _ in discs]), np.concatenate([c for _, c in discs])] = np.inf
                out["outside"] = _located(loc, q, d, rows, near, k, with_db=True)
    return out


def _stacked(parts: list[tuple[FingerprintMatrix, NDArray, NDArray, NDArray]]) -> tuple[FingerprintMatrix, NDArray, NDArray, NDArray]:
    """(queries, distances, rows, near) of ``parts``' walks one after another (one walk's as they are)."""
    if len(parts) == 1:
        return parts[0]
    qs = [p[0] for p in parts]
    q = FingerprintMatrix(qs[0].bssids, sparse.vstack([p.values for p in qs], format="csr"), qs[0].missing_dbm,
                          np.concatenate([p.extra_sq for p in qs]), np.concatenate([p.extra_n for p in qs]))
    return q, *(np.concatenate([p[i] for p in parts]) for i in (1, 2, 3))



def _located(
    loc: KnnLocator, q: FingerprintMatrix, d: NDArray, rows: NDArray, near: NDArray, k: int, with_db: bool
) -> tuple[NDArray, NDArray, NDArray, NDArray, NDArray]:
    """(error norms, spreads, scores, ``near``, rss_diff_db (zeros without ``with_db``)) of the queries
    ``q`` (the map's fingerprints ``rows``) located by their distances ``d``, the located ones only."""
    idx, dist = nearest(d, k)
    res = loc._aggregate(idx, dist, np.diff(q.values.indptr).astype(np.int64), q if with_db else None)
    ok = res.valid
    db = res.rss_diff_db[ok] if res.rss_diff_db is not None else np.zeros(int(ok.sum()))
    return np.linalg.norm(res.xy[ok] - loc.radio_map.xy[rows[ok]], axis=1), res.spread[ok], res.score[ok], near[ok], db


def _outside_test(
    covered: NDArray, outside: NDArray, outside_err: NDArray, radius_m: float, near_m: float, false_alarm: float
) -> OutsideTest | None:
    """``OutsideTest`` from the covered scans' ``rss_diff_db`` (those near another walk) and the
    outside scans' ``rss_diff_db`` and error norms; None when either set is empty."""
    if not len(covered) or not len(outside):
        return None
    t = OutsideTest(tuple(float(v) for v in np.quantile(covered, OUTSIDE_LEVELS)),
                    max(float(np.quantile(outside_err, 0.95)) / R95, 1e-3), 0.0, len(covered), len(outside),
                    false_alarm, radius_m, near_m)
    return dataclasses.replace(t, detection=float(np.mean(t.flags(outside))))


def _score_bins(
    covered: list[NDArray], uncovered: list[NDArray], floor_m: float, weight: float, bins: int
) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """(inner score edges, per-bin scales): per quantile bin of both sets' scores, the weighted 95 %
    quantile of error / (R95 sqrt(spread^2 + floor_m^2)), made non-decreasing with the score."""
    ratio = np.concatenate([covered[0], uncovered[0]]) / (
        R95 * np.sqrt(np.concatenate([covered[1], uncovered[1]]) ** 2 + floor_m**2))
    score = np.concatenate([covered[2], uncovered[2]])
    w = np.concatenate([np.ones(len(covered[0])), np.full(len(uncovered[0]), weight)])
    edges = np.unique(np.quantile(score, np.linspace(0.0, 1.0, bins + 1)[1:-1]))
    b = np.searchsorted(edges, score, side="right")
    scales = np.full(len(edges) + 1, 1e-3)
    for k in range(len(scales)):
        m = (b == k) & (w > 0)
        if m.any():  # (an empty bin keeps the floor; the running maximum below lifts it)
            o = np.argsort(ratio[m], kind="stable")
            cum = np.cumsum(w[m][o]) / w[m].sum()
            scales[k] = max(float(ratio[m][o][min(int(np.searchsorted(cum, 0.95)), int(m.sum()) - 1)]), 1e-3)
    scales = np.maximum.accumulate(scales)
    return tuple(float(v) for v in edges), tuple(float(v) for v in scales)


def _heard_only_by(values: sparse.csr_matrix, heard: NDArray[np.int64], gone: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """Per AP column: no fingerprint outside ``gone`` (the removed rows) heard it (``values``: the
    map's fingerprints; ``heard``: how many of them hear each AP)."""
    return heard - np.bincount(values[np.flatnonzero(gone)].indices, minlength=len(heard)) == 0


def _distances_again(
    loc: KnnLocator, q: FingerprintMatrix, d: NDArray[np.float64], dropped: NDArray[np.bool_], drop: NDArray[np.bool_]
) -> tuple[FingerprintMatrix, NDArray[np.float64]]:
    """(``q`` without the AP columns ``drop``, its distances) from ``d``, its distances without
    ``dropped``: only the rows hearing an AP dropped by one and not the other are searched again (a
    row's distances are its own, the same bits in any block; a wider removal, the uncovered set's,
    drops a few more APs, which few of a walk's scans hear)."""
    v = q.values
    row = np.repeat(np.arange(len(q)), np.diff(v.indptr))
    touched = np.flatnonzero(np.bincount(row, weights=(drop != dropped)[v.indices], minlength=len(q)))
    out = _without_columns(q, drop)
    if not len(touched):
        return out, d
    d = d.copy()
    d[touched] = loc.distances(out.rows(touched))
    return out, d


def _without_columns(q: FingerprintMatrix, drop: NDArray[np.bool_]) -> FingerprintMatrix:
    """``q`` with the readings of the AP columns ``drop`` moved outside the index (``extra_*``), as
    ``RadioMap.reindex`` does for APs a map does not know; ``q`` itself when it has none of them (the
    calibration's usual case: a walk rarely hears an AP no other walk does)."""
    v = q.values
    out = drop[v.indices]
    if not out.any():
        return q
    n = len(q)
    row = np.repeat(np.arange(n), np.diff(v.indptr))
    extra_sq = q.extra_sq + np.bincount(row[out], weights=v.data[out] ** 2, minlength=n)
    extra_n = q.extra_n + np.bincount(row[out], minlength=n).astype(np.int64)
    keep = ~out
    indptr = np.concatenate([[0], np.cumsum(np.bincount(row[keep], minlength=n))])
    kept = sparse.csr_matrix((v.data[keep], v.indices[keep], indptr), shape=v.shape)
    return FingerprintMatrix(q.bssids, kept, q.missing_dbm, extra_sq, extra_n)


@dataclass(frozen=True)
class AccuracyCells:
    """The map's expected accuracy on square cells: the cells holding at least one fingerprint.

    Frame and units: those of the positions gridded (``expected_accuracy``'s ``xy``), metres.
    Cell ``(i, j)`` covers ``origin + [i, i+1) x [j, j+1) * cell_m``.
    """

    cell_m: float
    origin: NDArray[np.float64]  # (2,) lower-left corner of cell (0, 0)
    ij: NDArray[np.int64]  # (M, 2) cell indices
    centres: NDArray[np.float64]  # (M, 2)
    error_m: NDArray[np.float64]  # (M,) median leave-one-walk-out error norm; NaN: none located
    r95_m: NDArray[np.float64]  # (M,) median calibrated 95 % radius; NaN: none located, or no calibration
    n_fingerprints: NDArray[np.int64]  # (M,) all of the map's fingerprints in the cell
    n_sampled: NDArray[np.int64]  # (M,) of them, searched for (all, but on a map of over max_rows)
    n_located: NDArray[np.int64]  # (M,) of the sampled ones, located among the other walks
    n_rows: int  # fingerprints sampled in all


def expected_accuracy(
    rm: RadioMap, *, cell_m: float = 2.0, config: KnnConfig | None = None, xy: NDArray | None = None,
    origin: NDArray | None = None, uncertainty: KnnUncertainty | None = None, max_rows: int = 5000, seed: int = 0,
) -> AccuracyCells:
    """Where the map localises well: per cell of ``cell_m`` m, the median error of its fingerprints
    located among the *other* walks' fingerprints (``leave_one_session_out``: what a new walk's scan
    there would get, measured without ground truth), and, with ``uncertainty``, the median calibrated
    95 % radius ``R95 * sigma`` of those answers.

    ``xy``: the fingerprints' positions to grid (default the map's; e.g. moved into a floor plan's
    site frame by a rigid transform, which leaves the error norms unchanged); ``origin``: the grid's
    lower-left corner (default the positions' minimum). Maps of more than ``max_rows`` fingerprints:
    a seeded sample of at most ``max_rows`` is located (cost ~ ``max_rows`` x map size Sørensen
    distances), spread evenly over the cells (up to q per cell, the largest q that fits; with more
    cells than ``max_rows``, one fingerprint of each of ``max_rows`` random cells, the others not
    sampled); the coverage counts every fingerprint. A map of one walk has nothing to compare:
    every ``error_m`` is NaN.
    """
    if cell_m <= 0 or not math.isfinite(cell_m):
        raise ConfigError(f"expected accuracy: cell size must be a positive number of metres, got {cell_m}")
    if not len(rm):
        raise ConfigError("expected accuracy: the radio map has no fingerprint")
    pos = np.asarray(rm.xy if xy is None else xy, float)
    if pos.shape != (len(rm), 2):
        raise ConfigError(f"expected accuracy: xy must be ({len(rm)}, 2) positions, got {pos.shape}")
    lo = pos.min(axis=0) if origin is None else np.asarray(origin, float).reshape(2)
    ij_all = np.floor((pos - lo) / cell_m).astype(np.int64)
    cells, inverse, counts = np.unique(ij_all, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    rows = np.arange(len(rm))
    if len(rows) > max_rows:
        rows = _even_sample(inverse, counts, max_rows, seed)
    err = np.full(len(rows), np.nan)
    r95 = np.full(len(rows), np.nan)
    if len(rows) and len(np.unique(rm.session_ids)) > 1:
        e, spread, score = leave_one_session_out(rm, rows, config=config)
        err = np.linalg.norm(e, axis=1)
        if uncertainty is not None:
            r95 = R95 * uncertainty.sigma(spread, score)
    g = inverse[rows]
    return AccuracyCells(
        float(cell_m), lo, cells, lo + (cells + 0.5) * cell_m, _group_median(g, err, len(cells)),
        _group_median(g, r95, len(cells)), counts.astype(np.int64), np.bincount(g, minlength=len(cells)),
        np.bincount(g[np.isfinite(err)], minlength=len(cells)).astype(np.int64), len(rows),
    )


def _even_sample(cell: NDArray[np.int64], counts: NDArray[np.int64], n: int, seed: int) -> NDArray[np.int64]:
    """Sorted rows, at most ``n``: a seeded random q of each cell's rows (all of a smaller cell), q
    the largest that fits; with more cells than ``n``, one row of each of ``n`` random cells."""
    rng = np.random.default_rng(seed)
    order = np.lexsort((rng.random(len(cell)), cell))  # by cell, random within
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    rank = np.empty(len(cell), np.int64)
    rank[order] = np.arange(len(cell)) - np.repeat(start, counts)
    taken = np.array([np.minimum(counts, q).sum() for q in range(1, int(counts.max()) + 1)])
    q = int(np.searchsorted(taken, n, side="right"))
    if q == 0:  # more cells than rows to locate: whole cells are left out
        cells = rng.choice(len(counts), n, replace=False)
        keep = np.zeros(len(counts), bool)
        keep[cells] = True
        return np.flatnonzero((rank == 0) & keep[cell])
    return np.flatnonzero(rank < q)


def _group_median(group: NDArray[np.int64], values: NDArray[np.float64], n: int) -> NDArray[np.float64]:
    """Median of the finite ``values`` per group ``0..n-1`` (NaN for a group with none), sorted once."""
    ok = np.isfinite(values)
    g, v = group[ok], values[ok]
    order = np.lexsort((v, g))
    g, v = g[order], v[order]
    counts = np.bincount(g, minlength=n)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    out = np.full(n, np.nan)
    has = counts > 0
    lo_i, hi_i = start[has] + (counts[has] - 1) // 2, start[has] + counts[has] // 2
    out[has] = 0.5 * (v[lo_i] + v[hi_i])
    return out


METADATA_KEY = "knn_uncertainty"  # the radio map's metadata: the calibration of the default kNN


def with_uncertainty(rm: RadioMap, config: KnnConfig | None = None) -> RadioMap:
    """``rm`` with the calibration of ``config`` (default: the default kNN) in its metadata (unchanged
    when none can be measured)."""
    return with_calibration(rm, calibrate_uncertainty(rm, config))


def with_calibration(rm: RadioMap, u: KnnUncertainty | None) -> RadioMap:
    """``rm`` with the calibration ``u`` (``calibrate_uncertainty`` of it) in its metadata; ``rm`` for None."""
    return rm if u is None else rm.with_metadata(**{METADATA_KEY: u.as_dict()})


def map_uncertainty(rm: RadioMap, config: KnnConfig) -> KnnUncertainty | None:
    """The calibration of ``config`` on ``rm``: the one its metadata records when measured with the
    same kNN (and with the outside test: a record written before it is measured again), else measured
    now (None for a map of one walk)."""
    stored = rm.metadata.get(METADATA_KEY)
    if isinstance(stored, Mapping) and "outside" in stored:
        u = KnnUncertainty.from_dict(stored)
        if u is not None and u.matches(config):
            return u
    return calibrate_uncertainty(rm, config)


__all__ = [
    "AccuracyCells", "FALSE_ALARM", "KnnUncertainty", "METADATA_KEY", "NEAR_M", "OUTSIDE_RADIUS_M", "OutsideTest", "R95", "calibrate_uncertainty", "expected_accuracy",
    "leave_one_session_out", "map_uncertainty", "with_calibration", "with_uncertainty",
]
