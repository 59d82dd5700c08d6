"""The kNN's value types, shared by the locator (``graphslam.core.radiomap.knn``) and the
calibration of its uncertainty (``graphslam.core.radiomap.uncertainty``): its configuration, its
answers and the calibrated uncertainty of its answers, with the test that tells an answer from a
place the map has not walked (``OutsideTest``).

Frames and units: the radio map's frame, metres; distances in the metric's unit (eq. 9: dB;
Sørensen: 0-1).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, Literal, Mapping

import numpy as np
from numpy.typing import NDArray

from graphslam.errors import ConfigError
from graphslam.names import DEFAULT_INDEX, DEFAULT_K, DEFAULT_METRIC, INDEXES, METRICS

# Inverse-distance weights 1 / (d + eps): an exact match (d = 0) dominates without dividing by zero.
WEIGHT_EPS_DB = 1e-6
# IVF clusters probed per query (``KnnConfig.ivf_probes``)
DEFAULT_IVF_PROBES = 8

IndexKind = Literal["auto", "exact", "ivf"]
Metric = Literal["sorensen", "eq9"]

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
    ``knn.IVF_AUTO_MIN_REFS`` references, exact below. ``ivf_clusters``: ``None`` = ~2 sqrt(N);
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
    # (Q,) mean eq. 9 distance (RMS dB difference) from the query to the neighbours used, whatever the
    # metric: what ``OutsideTest`` tests (None: not measured)
    rss_diff_db: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        for name in ("xy", "score", "spread", "neighbours", "distances", "n_known_aps", "floor", "building", "rss_diff_db"):
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


# ``OutsideTest.covered_db``: the covered scans' statistic at these quantile levels
OUTSIDE_LEVELS = tuple(i / 20 for i in range(21))


@dataclass(frozen=True)
class OutsideTest:
    """Whether a kNN answer comes from a place the map has not walked, from how far its query's
    readings are from those of the fingerprints it rests on (``KnnResult.rss_diff_db``: the mean
    eq. 9 distance, dB), measured on the map by ``graphslam.core.radiomap.uncertainty`` (its
    docstring): the map's own scans where other walks have been (*covered*: within ``near_m`` of
    another walk's fingerprint, located on the map without their walk) against the same scans
    located without every fingerprint within ``radius_m`` of their walk (*outside*).

    An answer is outside when its ``rss_diff_db`` is above all but ``false_alarm`` of the covered
    scans' (``flags``); its outside score is the share of the covered scans that matched closer
    (0-1, interpolated between ``OUTSIDE_LEVELS``): outside means a score above ``1 - false_alarm``.
    An outside answer's sigma is at least ``sigma_m``: 95 % of the outside scans' errors lie within
    2.448 ``sigma_m`` of their answers."""

    covered_db: tuple[float, ...]  # the covered scans' rss_diff_db at ``OUTSIDE_LEVELS``, non-decreasing
    sigma_m: float  # the least sigma of an outside answer (m)
    detection: float  # share of the outside scans flagged (the map's own figure)
    n_covered: int
    n_outside: int
    false_alarm: float = 0.05  # share of the covered scans flagged
    radius_m: float = 10.0
    near_m: float = 3.0

    @property
    def threshold_db(self) -> float:
        """The ``rss_diff_db`` above which an answer is outside."""
        return float(np.interp(1.0 - self.false_alarm, OUTSIDE_LEVELS, self.covered_db))

    def flags(self, rss_diff_db: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Per answer: outside? (False for NaN: no answer)."""
        with np.errstate(invalid="ignore"):
            return np.asarray(rss_diff_db, float) > self.threshold_db

    def scores(self, rss_diff_db: NDArray[np.float64]) -> NDArray[np.float64]:
        """Per answer: its outside score, 0-1 (NaN for NaN)."""
        d = np.asarray(rss_diff_db, float)
        return np.where(np.isfinite(d), np.interp(np.nan_to_num(d), self.covered_db, OUTSIDE_LEVELS), np.nan)

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["covered_db"] = list(self.covered_db)
        return d

    @classmethod
    def from_dict(cls, d: Any) -> "OutsideTest | None":
        """From a radio map's metadata (``KnnUncertainty.as_dict``'s ``outside``); None when not a valid record."""
        try:
            t = cls(tuple(float(v) for v in d["covered_db"]), float(d["sigma_m"]), float(d["detection"]),
                    int(d["n_covered"]), int(d["n_outside"]), float(d["false_alarm"]), float(d["radius_m"]),
                    float(d["near_m"]))
        except (KeyError, TypeError, ValueError):
            return None
        c = t.covered_db
        ok = len(c) == len(OUTSIDE_LEVELS) and all(math.isfinite(v) for v in c) and all(a <= b for a, b in zip(c, c[1:]))
        ok = ok and math.isfinite(t.sigma_m) and t.sigma_m > 0 and 0.0 < t.false_alarm < 1.0
        return t if ok else None


@dataclass(frozen=True)
class KnnUncertainty:
    """``sigma = scale_b * sqrt(spread^2 + floor_m^2)`` for answers of the kNN it was measured with,
    ``scale_b`` by the answer's score; measured by ``graphslam.core.radiomap.uncertainty`` (its docstring)."""

    metric: str
    k: int
    weighted: bool
    scale: float  # the covered scans' single scale (no score bins, or a score that is NaN)
    floor_m: float
    n: int  # scans located in the calibration (both sets)
    coverage: float = 0.95  # share of the covered scans' errors inside their 95 % circle
    score_edges: tuple[float, ...] = ()  # inner edges of the score bins, ascending
    scales: tuple[float, ...] = ()  # per bin (len(score_edges) + 1), non-decreasing; () = ``scale`` for all
    outside: OutsideTest | None = None  # answers from places the map has not walked (None: not measured)

    def matches(self, config: KnnConfig) -> bool:
        """Measured with this kNN (metric, k, weights)? (Not ``min_common``: the calibration uses 1,
        and a larger one, which only excludes weakly overlapping references, reuses it.)"""
        return (self.metric, self.k, self.weighted) == (config.metric, config.k, config.weighted)

    def scale_for(self, score: NDArray[np.float64] | None) -> NDArray[np.float64] | float:
        """The scale per answer score (``scale`` without bins, without scores, or for a NaN score)."""
        if not self.scales or score is None:
            return self.scale
        sc = np.asarray(score, float)
        edges = np.asarray(self.score_edges, float)
        out = np.asarray(self.scales, float)[np.searchsorted(edges, np.nan_to_num(sc), side="right")]
        return np.where(np.isfinite(sc), out, self.scale)

    def sigma(
        self, spread: NDArray[np.float64], score: NDArray[np.float64] | None = None,
        rss_diff_db: NDArray[np.float64] | None = None,
    ) -> NDArray[np.float64]:
        """Per answer: sigma (m, per axis) from its neighbours' spread and its score (``KnnResult``'s;
        without scores, the covered scale); with ``rss_diff_db``, at least ``outside.sigma_m`` for an
        answer from outside the map's walks. NaN spread stays NaN."""
        s = np.asarray(spread, float)
        out = self.scale_for(score) * np.sqrt(s * s + self.floor_m**2)
        if self.outside is not None and rss_diff_db is not None:
            out = np.where(self.outside.flags(rss_diff_db), np.maximum(out, self.outside.sigma_m), out)
        return out

    def sigma_of(self, res: "KnnResult") -> NDArray[np.float64]:
        """``sigma`` of every answer of ``res``."""
        return np.asarray(self.sigma(res.spread, res.score, res.rss_diff_db), float) * np.ones(len(res))

    def outside_of(self, res: "KnnResult") -> NDArray[np.bool_] | None:
        """Per answer of ``res``: from outside the map's walks? None when not measured (no test, or
        answers without ``rss_diff_db``)."""
        return None if self.outside is None or res.rss_diff_db is None else self.outside.flags(res.rss_diff_db)

    def outside_score_of(self, res: "KnnResult") -> NDArray[np.float64] | None:
        """Per answer of ``res``: its outside score (0-1; NaN: no answer); None as ``outside_of``."""
        return None if self.outside is None or res.rss_diff_db is None else self.outside.scores(res.rss_diff_db)

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["score_edges"], d["scales"] = list(self.score_edges), list(self.scales)
        d["outside"] = None if self.outside is None else self.outside.as_dict()
        return d

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "KnnUncertainty | None":
        """From a radio map's metadata; None when absent or not a valid record (a record without
        score bins, as written before them, gives one scale for every answer; one without
        ``outside``, no outside test)."""
        try:
            edges = tuple(float(v) for v in d.get("score_edges", ()))
            scales = tuple(float(v) for v in d.get("scales", ()))
            outside = None
            if d.get("outside") is not None:
                outside = OutsideTest.from_dict(d["outside"])
                if outside is None:
                    return None
            u = cls(str(d["metric"]), int(d["k"]), bool(d["weighted"]), float(d["scale"]), float(d["floor_m"]),
                    int(d["n"]), float(d.get("coverage", 0.95)), edges, scales, outside)
        except (KeyError, TypeError, ValueError):
            return None
        ok = math.isfinite(u.scale) and u.scale > 0 and math.isfinite(u.floor_m) and u.floor_m > 0
        if scales:
            ok = ok and len(scales) == len(edges) + 1 and all(math.isfinite(v) for v in edges)
            ok = ok and all(math.isfinite(v) and v > 0 for v in scales)
            ok = ok and all(a < b for a, b in zip(edges, edges[1:]))
        elif edges:
            ok = False
        return u if ok else None
