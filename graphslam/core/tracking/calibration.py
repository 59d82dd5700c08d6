"""How wrong is a kNN fix on this radio map? Leave-one-session-out errors of the map itself.

A tracker that fuses kNN fixes as position readings needs their error scale. The map can tell
it without any ground truth: locate every fingerprint of the map among the fingerprints of the
*other* sessions (same k, same weights as ``KnnLocator``) and compare with where the map puts
it. On a map whose positions are right this is the kNN error a new walk over the surveyed
area will see; on a crowdsourced map it is the error in the map's own frame (which is the
frame the tracker reports in). Why not a constant: kNN errors differ by building (UJIIndoorLoc
~5 m, ILC mall ~6 m, IPIN museum ~9 m, the simulator ~2 m: docs/tracking.md), and a fix
standard deviation chosen on one misweights fixes against steps on the others.

The same errors in time order along each of the map's walks say how correlated consecutive fixes
are (``fix_error_correlation``): a walk's fixes are fewer independent looks than their number, and
the heading bank's odds, a sum over fixes, are overstated by ``bank_temper``'s factor.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from graphslam.core.radiomap.knn import KnnConfig
from graphslam.core.radiomap.uncertainty import leave_one_session_out
from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.errors import EstimationError
from graphslam.names import DEFAULT_METRIC

if TYPE_CHECKING:
    from graphslam.core.tracking.apmodel import ApModels

RAYLEIGH_MEDIAN = float(np.sqrt(2.0 * np.log(2.0)))  # median of |e| for e ~ N(0, I_2): 1.177
CHI2_2DOF_MEDIAN = 2.0 * float(np.log(2.0))  # median of |e|^2 for e ~ N(0, I_2): 1.386
CHI2_2DOF_95 = -2.0 * float(np.log(0.05))  # P(chi^2_2 <= 5.991) = 0.95


@dataclass(frozen=True)
class FixNoise:
    """Leave-one-session-out kNN errors of a map (m): their median, p90 and the per-axis standard
    deviation ``sigma_m`` of a 2-D Gaussian with the same median error (robust to the tail,
    which a robust loss handles)."""

    n: int
    median_m: float
    p90_m: float
    sigma_m: float


def leave_one_session_out_error_vectors(
    rm: RadioMap, rows: NDArray[np.int64] | None = None, *, k: int = 3, extra: int = 30, metric: str = DEFAULT_METRIC
) -> NDArray[np.float64]:
    """(len(rows), 2) kNN error vectors (estimate - map position, m) of the map's fingerprints
    ``rows`` (default all), each located among the other sessions' fingerprints: the ``k``
    nearest of another session among its ``k + extra`` nearest overall, inverse-distance weighted
    as ``KnnLocator`` (``metric``: ``KnnConfig.metric``). NaN rows: every candidate came from the fingerprint's own session."""
    if len(rm) < 2 or len(set(rm.session_ids.tolist())) < 2:
        raise EstimationError("fix noise: the radio map needs fingerprints of at least 2 sessions")
    return leave_one_session_out(rm, rows, config=KnnConfig(k=k, metric=metric), extra=extra)[0]  # type: ignore[arg-type]


def leave_one_session_out_errors(
    rm: RadioMap, *, k: int = 3, extra: int = 30, max_queries: int = 3000, seed: int = 0, metric: str = DEFAULT_METRIC,
    vectors: NDArray | None = None,
) -> NDArray[np.float64]:
    """kNN error (m) of (up to ``max_queries``, seeded sample of) the map's fingerprints, each
    located among the other sessions' fingerprints (``leave_one_session_out_error_vectors``; or
    taken from ``vectors``, those of every fingerprint with these ``k``, ``extra``, ``metric``).
    Rows whose candidates all come from their own session are left out."""
    rows = np.arange(len(rm))
    if len(rows) > max_queries:
        rows = np.sort(np.random.default_rng(seed).choice(rows, max_queries, replace=False))
    e = vectors[rows] if vectors is not None else leave_one_session_out_error_vectors(rm, rows, k=k, extra=extra, metric=metric)
    e = e[np.isfinite(e).all(axis=1)]
    return np.linalg.norm(e, axis=1)


def fix_noise(rm: RadioMap, *, k: int = 3, metric: str = DEFAULT_METRIC, vectors: NDArray | None = None) -> FixNoise:
    """``FixNoise`` of ``rm`` from ``leave_one_session_out_errors`` (``vectors``: see there)."""
    e = leave_one_session_out_errors(rm, k=k, metric=metric, vectors=vectors)
    if not len(e):
        raise EstimationError("fix noise: no fingerprint could be located among other sessions")
    med = float(np.median(e))
    return FixNoise(len(e), med, float(np.percentile(e, 90)), med / RAYLEIGH_MEDIAN)


def fix_error_correlation(
    rm: RadioMap, *, k: int = 3, metric: str = DEFAULT_METRIC, max_queries: int = 3000, seed: int = 0,
    vectors: NDArray | None = None,
) -> float:
    """Correlation of consecutive kNN fix errors along a walk: the leave-one-session-out error
    vectors (``leave_one_session_out_error_vectors``, or those of every fingerprint in ``vectors``)
    of each session's fingerprints in time order, every pair of neighbours, both axes pooled (each
    axis centred). Whole sessions are sampled (seeded) up to about ``max_queries`` fingerprints.
    0 when fewer than 3 pairs."""
    sid = np.asarray(rm.session_ids)
    sessions, counts = np.unique(sid, return_counts=True)  # one pass, not one scan of the map per session
    if len(sessions) < 2:
        raise EstimationError("fix error correlation: the radio map needs fingerprints of at least 2 sessions")
    order = np.random.default_rng(seed).permutation(len(sessions))
    sessions, sizes = sessions[order], counts[order]
    keep = sessions[: max(2, int(np.searchsorted(np.cumsum(sizes), max_queries, side="right")))]
    rows = np.flatnonzero(np.isin(sid, keep))
    rows = rows[np.lexsort((np.asarray(rm.t_ns)[rows], sid[rows]))]  # by session, then time
    e = vectors[rows] if vectors is not None else leave_one_session_out_error_vectors(rm, rows, k=k, metric=metric)
    pair = (sid[rows][1:] == sid[rows][:-1]) & np.isfinite(e[1:]).all(axis=1) & np.isfinite(e[:-1]).all(axis=1)
    if pair.sum() < 3:
        return 0.0
    a, b = e[:-1][pair], e[1:][pair]
    a, b = a - a.mean(axis=0), b - b.mean(axis=0)
    den = float(np.sqrt((a * a).sum() * (b * b).sum()))
    return float((a * b).sum() / den) if den > 0 else 0.0


def bank_temper(rho: float, *, rho_max: float = 0.9) -> float:
    """How much a walk's correlated fixes overstate the evidence between heading hypotheses: the
    variance of a sum of AR(1) terms with lag-1 correlation ``rho`` over that of independent ones,
    (1 + rho) / (1 - rho) (>= 1; ``rho`` clipped to [0, ``rho_max``])."""
    r = min(max(float(rho), 0.0), rho_max)
    return (1.0 + r) / (1.0 - r)


def rssi_variance_factor(
    rm: RadioMap, models: "ApModels", sigma_db: NDArray, *, max_queries: int = 1000, iterations: int = 8, seed: int = 0
) -> float:
    """How over-confident are the RSSI readings under the AP models, measured on the map itself?

    For (a seeded sample of) the map's fingerprints: the position that best explains the
    fingerprint's readings of modelled APs alone (Gauss-Newton on eq. 6 from the map position,
    readings of std ``sigma_db`` per AP), its covariance (H^T R^-1 H)^-1, and the squared
    Mahalanobis distance of the map position from it. With right, independent errors these are
    chi-square with 2 dof (median 1.386); the returned factor (>= 1) is the sample median over
    that. Why: many BSSIDs per physical AP (dual band, several SSIDs) and AP-model errors shared
    by neighbouring APs make a scan's readings far less independent than the filters assume; a
    mall scan with ~200 modelled BSSIDs then claims decimetre positions that are metres off
    (docs/tracking.md). Uses only the map and its AP models."""
    pl = models.path_loss()
    index = {b: i for i, b in enumerate(pl.bssids)}
    cols = np.array([index.get(b, -1) for b in rm.bssids], np.int64)
    v = rm.fingerprints.values.tocsr()
    rows = np.arange(len(rm))
    if len(rows) > max_queries:
        rows = np.sort(np.random.default_rng(seed).choice(rows, max_queries, replace=False))
    # every query's readings of modelled APs at once: fingerprint f, AP a, RSS y (queries with >= 3 only)
    sub = v[rows]
    f = np.repeat(np.arange(len(rows)), np.diff(sub.indptr))
    a = cols[sub.indices] if sub.nnz else np.zeros(0, np.int64)
    keep = a >= 0
    f, a, y = f[keep], a[keep], sub.data[keep] + rm.missing_dbm
    enough = np.bincount(f, minlength=len(rows)) >= 3
    keep = enough[f]
    f, a, y = np.unique(f[keep], return_inverse=True)[1], a[keep], y[keep]
    q = rows[enough]
    if not len(q):
        return 1.0
    F = len(q)
    w = 1.0 / np.asarray(sigma_db, float)[a] ** 2
    law = pl.rows(a)
    p = rm.xy[q].astype(float)
    ok = np.ones(F, bool)  # Gauss-Newton has not met a singular system
    for _ in range(iterations + 1):
        gx, gy = law.gradient(p[f, 0], p[f, 1])
        A = np.stack([np.bincount(f, w * gx * gx, F), np.bincount(f, w * gx * gy, F), np.bincount(f, w * gy * gy, F)], 1)
        det = A[:, 0] * A[:, 2] - A[:, 1] * A[:, 1]
        if _ == iterations:
            break
        ok &= det != 0
        r = w * (y - law.mean(p[f, 0], p[f, 1]))
        bx, by = np.bincount(f, gx * r, F), np.bincount(f, gy * r, F)
        with np.errstate(divide="ignore", invalid="ignore"):
            step = np.stack([A[:, 2] * bx - A[:, 1] * by, A[:, 0] * by - A[:, 1] * bx], 1) / det[:, None]
        p = np.where(ok[:, None], p + step, p)
    e = p - rm.xy[q]
    d2 = A[:, 0] * e[:, 0] ** 2 + 2.0 * A[:, 1] * e[:, 0] * e[:, 1] + A[:, 2] * e[:, 1] ** 2
    d2 = d2[ok]
    if not len(d2):
        return 1.0
    return max(1.0, float(np.median(d2)) / CHI2_2DOF_MEDIAN)


def mahalanobis_sq(err_xy: NDArray, cov_xy: NDArray) -> NDArray[np.float64]:
    """Per row: ``e^T C^-1 e`` of the error ``err_xy`` (m, 2) under its covariance ``cov_xy``
    (m^2, 2 x 2); a singular covariance gives 0 for a zero error, else inf."""
    e = np.asarray(err_xy, float).reshape(-1, 2)
    C = np.asarray(cov_xy, float).reshape(-1, 2, 2)
    det = C[:, 0, 0] * C[:, 1, 1] - C[:, 0, 1] * C[:, 1, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        d2 = (C[:, 1, 1] * e[:, 0] ** 2 - (C[:, 0, 1] + C[:, 1, 0]) * e[:, 0] * e[:, 1] + C[:, 0, 0] * e[:, 1] ** 2) / det
    return np.where(det > 0, d2, np.where(np.abs(e).sum(axis=1) == 0, 0.0, np.inf))


def ellipse_coverage(err_xy: NDArray, cov_xy: NDArray, chi2: float = CHI2_2DOF_95) -> NDArray[np.bool_]:
    """Per row: is the error inside the ellipse ``e^T C^-1 e <= chi2`` of its covariance?"""
    return mahalanobis_sq(err_xy, cov_xy) <= chi2
