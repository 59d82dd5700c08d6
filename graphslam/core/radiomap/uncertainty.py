"""A calibrated uncertainty for kNN answers, measured on the radio map itself.

A kNN answer's error grows with how far apart its neighbours lie (``KnnResult.spread``: the weighted
RMS distance of their positions to the estimate), but not one for one: neighbours can agree on a
wrong place, and a place the map covers densely is still only resolved to a few metres. The model::

    sigma = scale * sqrt(spread^2 + floor_m^2)        (isotropic, metres; per axis)

with ``floor_m`` fixed and ``scale`` measured without ground truth: the map's walks (a seeded
sample of them) are located, one at a time, on the map of the *other* walks (the same kNN: metric,
k, weights), and each scan's error against its own map position is what a new walk's scan would
make. ``scale`` is chosen so that 95 % of those errors fall inside the 95 % circle of a 2-D
Gaussian, ``r95 = sqrt(-2 ln 0.05) sigma = 2.448 sigma``. A map of one walk has nothing to leave
out: no calibration (``None``).

Frames and units: the radio map's frame, metres.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, Mapping

import numpy as np
from numpy.typing import NDArray

from graphslam.core.radiomap.knn import WEIGHT_EPS_DB, KnnConfig, KnnLocator
from graphslam.core.radiomap.radiomap import RadioMap

R95 = math.sqrt(-2.0 * math.log(0.05))  # radius / sigma of a 2-D Gaussian's 95 % circle
DEFAULT_FLOOR_M = 2.0


@dataclass(frozen=True)
class KnnUncertainty:
    """``sigma = scale * sqrt(spread^2 + floor_m^2)`` for answers of the kNN it was measured with."""

    metric: str
    k: int
    weighted: bool
    scale: float
    floor_m: float
    n: int  # map fingerprints it was measured on
    coverage: float = 0.95  # share of those errors inside the 95 % circle (by construction ~0.95)

    def matches(self, config: KnnConfig) -> bool:
        """Measured with this kNN (metric, k, weights)?"""
        return (self.metric, self.k, self.weighted) == (config.metric, config.k, config.weighted)

    def sigma(self, spread: NDArray[np.float64]) -> NDArray[np.float64]:
        """Per answer: sigma (m, per axis) from its neighbours' spread (NaN stays NaN)."""
        s = np.asarray(spread, float)
        return self.scale * np.sqrt(s * s + self.floor_m**2)

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "KnnUncertainty | None":
        """From a radio map's metadata; None when absent or not a valid record."""
        try:
            u = cls(str(d["metric"]), int(d["k"]), bool(d["weighted"]), float(d["scale"]), float(d["floor_m"]),
                    int(d["n"]), float(d.get("coverage", 0.95)))
        except (KeyError, TypeError, ValueError):
            return None
        ok = math.isfinite(u.scale) and u.scale > 0 and math.isfinite(u.floor_m) and u.floor_m > 0
        return u if ok else None


def leave_one_session_out(
    rm: RadioMap, rows: NDArray[np.int64] | None = None, *, config: KnnConfig | None = None, extra: int = 30
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """((len(rows), 2) error vectors (estimate - map position, m), (len(rows),) spreads) of the map's
    fingerprints ``rows`` (default all), each located among the other sessions' fingerprints: the
    ``k`` nearest of another session among its ``k + extra`` nearest overall, weighted as
    ``KnnLocator``. NaN rows: every candidate came from the fingerprint's own session."""
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
    nxy = rm.xy[np.maximum(idx[ok], 0)]
    est = (w[ok, :, None] * nxy).sum(axis=1) / wsum[ok, None]
    e[ok] = est - rm.xy[rows[ok]]
    spread[ok] = np.sqrt((w[ok] * ((nxy - est[:, None, :]) ** 2).sum(axis=2)).sum(axis=1) / wsum[ok])
    return e, spread


def calibrate_uncertainty(
    rm: RadioMap, config: KnnConfig | None = None, *, floor_m: float = DEFAULT_FLOOR_M, max_queries: int = 3000,
    max_sessions: int = 12, seed: int = 0,
) -> KnnUncertainty | None:
    """``KnnUncertainty`` of ``config`` on ``rm`` (module docstring): up to ``max_sessions`` walks
    (a seeded sample), each located on the map of the other walks (up to ``max_queries`` scans in
    all); None for a map of one walk, or when no scan can be located among the others."""
    cfg = KnnConfig(k=(config or KnnConfig()).k, weighted=(config or KnnConfig()).weighted,
                    metric=(config or KnnConfig()).metric, index="exact")
    sessions = np.unique(rm.session_ids)
    if len(rm) < 2 or len(sessions) < 2:
        return None
    rng = np.random.default_rng(seed)
    if len(sessions) > max_sessions:
        sessions = np.sort(rng.choice(sessions, max_sessions, replace=False))
    per = max(1, max_queries // len(sessions))
    err, spread = [], []
    for sid in sessions:
        own = rm.session_ids == sid
        rows = np.flatnonzero(own)
        if len(rows) > per:
            rows = np.sort(rng.choice(rows, per, replace=False))
        keep = np.flatnonzero(~own)
        others = RadioMap.from_fingerprints(
            rm.fingerprints.rows(keep), rm.xy[keep], session_ids=rm.session_ids[keep], t_ns=rm.t_ns[keep],
            frame=rm.frame, min_rssi_dbm=rm.min_rssi_dbm,
        )
        res = KnnLocator(others, cfg, threads=1).locate(others.reindex(rm.fingerprints.rows(rows)))
        ok = res.valid
        err.append(np.linalg.norm(res.xy[ok] - rm.xy[rows[ok]], axis=1))
        spread.append(res.spread[ok])
    e, sp = np.concatenate(err), np.concatenate(spread)
    if not len(e):
        return None
    base = np.sqrt(sp**2 + floor_m**2)
    scale = max(float(np.quantile(e / (R95 * base), 0.95)), 1e-3)
    coverage = float(np.mean(e <= R95 * scale * base))
    return KnnUncertainty(cfg.metric, cfg.k, cfg.weighted, scale, floor_m, len(e), coverage)


METADATA_KEY = "knn_uncertainty"  # the radio map's metadata: the calibration of the default kNN


def with_uncertainty(rm: RadioMap, config: KnnConfig | None = None) -> RadioMap:
    """``rm`` with the calibration of ``config`` (default: the default kNN) in its metadata (unchanged
    when none can be measured)."""
    u = calibrate_uncertainty(rm, config)
    return rm if u is None else rm.with_metadata(**{METADATA_KEY: u.as_dict()})


def map_uncertainty(rm: RadioMap, config: KnnConfig) -> KnnUncertainty | None:
    """The calibration of ``config`` on ``rm``: the one its metadata records when measured with the
    same kNN, else measured now (None for a map of one walk)."""
    stored = rm.metadata.get(METADATA_KEY)
    if isinstance(stored, Mapping):
        u = KnnUncertainty.from_dict(stored)
        if u is not None and u.matches(config):
            return u
    return calibrate_uncertainty(rm, config)


__all__ = [
    "KnnUncertainty", "METADATA_KEY", "R95", "calibrate_uncertainty", "leave_one_session_out", "map_uncertainty",
    "with_uncertainty",
]
