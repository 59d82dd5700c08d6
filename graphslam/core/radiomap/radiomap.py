"""The radio map: located WiFi fingerprints, what kNN positioning searches.

A ``RadioMap`` is N fingerprints (a ``FingerprintMatrix`` over an AP index of
BSSIDs) with, per row, a position ``xy`` (metres, in the frame named ``frame``),
the session it came from, its time, and optional floor / building labels.

The AP index is canonical: the BSSIDs heard by at least one fingerprint, sorted.
Why: an AP no reference heard contributes exactly the same to eq. 9 whether it is
a (zero) column or an "extra" query AP, so dropping such columns changes no
distance, makes files smaller, gives one on-disk form per map (exact round trip)
and makes "AP unknown to the map" mean "no reference fingerprint heard it".
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy import sparse

from graphslam.core.radiomap.fingerprints import (
    DEFAULT_MIN_RSSI_DBM,
    DEFAULT_MISSING_DBM,
    FingerprintMatrix,
    heard_floor,
    scan_arrays,
)
from graphslam.core.types import frozen_array
from graphslam.errors import QueryError, RadioMapError

log = logging.getLogger(__name__)

RADIO_MAP_FORMAT_VERSION = 1



def _labels(name: str, labels: Sequence[Any] | NDArray | None, n: int) -> NDArray[np.str_] | None:
    """Per-row labels as a read-only str array; ``None`` or ``""`` entries mean unknown."""
    if labels is None:
        return None
    out = np.array(["" if v is None else str(v) for v in np.asarray(labels, dtype=object).ravel()], dtype=str)
    if len(out) != n:
        raise RadioMapError(f"radio map: {name} has {len(out)} labels for {n} fingerprints")
    if n == 0:
        out = np.zeros(0, dtype="<U1")
    out.setflags(write=False)
    return out


def _json_metadata(metadata: Mapping[str, Any] | None) -> Mapping[str, Any]:
    """Deep copy through JSON: the metadata must survive the file format unchanged."""
    try:
        text = json.dumps(dict(metadata or {}), sort_keys=True, allow_nan=False)
    except (TypeError, ValueError) as e:
        raise RadioMapError(f"radio map: metadata is not JSON-serialisable ({e})") from None
    return MappingProxyType(json.loads(text))


def _check_finite(values: NDArray[np.float64], extra_sq: NDArray[np.float64]) -> None:
    if not (np.isfinite(values).all() and np.isfinite(extra_sq).all()):
        raise QueryError("query scans hold a non-finite RSS value")


def canonical_fingerprints(fm: FingerprintMatrix) -> FingerprintMatrix:
    """Same fingerprints over the canonical AP index (heard APs, sorted). No-op when already canonical."""
    if fm.extra_n is not None and np.any(fm.extra_n):
        raise RadioMapError("radio map: fingerprints have readings outside their AP index (extra APs)")
    heard = np.bincount(fm.values.indices, minlength=fm.n_aps) > 0
    names = np.array(fm.bssids, dtype=object)
    keep = np.flatnonzero(heard)
    order = keep[np.argsort(names[keep].astype(str), kind="stable")]
    if len(order) == fm.n_aps and np.array_equal(order, np.arange(fm.n_aps)):
        return fm
    if len(set(names[order].tolist())) != len(order):
        raise RadioMapError("radio map: duplicate BSSID in the AP index")
    values = sparse.csr_matrix(fm.values[:, order])
    values.sort_indices()
    return FingerprintMatrix(tuple(names[order].tolist()), values, fm.missing_dbm)


@dataclass(frozen=True)
class RadioMapSummary:
    """What ``GET /v1/radio-map`` returns: counts, bounding box, labels, provenance."""

    format_version: int
    frame: str
    n_fingerprints: int
    n_access_points: int
    n_sessions: int
    mean_aps_per_fingerprint: float
    bbox: tuple[float, float, float, float] | None  # (min_x, min_y, max_x, max_y), metres
    floors: Mapping[str, int] | None  # label -> fingerprints
    buildings: Mapping[str, int] | None
    missing_dbm: float
    min_rssi_dbm: float
    t_ns_range: tuple[int, int] | None
    metadata: Mapping[str, Any]

    def as_dict(self) -> dict[str, Any]:
        bbox = None
        if self.bbox is not None:
            bbox = dict(zip(("min_x", "min_y", "max_x", "max_y"), self.bbox))
        return {
            "format_version": self.format_version,
            "frame": self.frame,
            "n_fingerprints": self.n_fingerprints,
            "n_access_points": self.n_access_points,
            "n_sessions": self.n_sessions,
            "mean_aps_per_fingerprint": self.mean_aps_per_fingerprint,
            "bbox": bbox,
            "floors": None if self.floors is None else dict(self.floors),
            "buildings": None if self.buildings is None else dict(self.buildings),
            "missing_dbm": self.missing_dbm,
            "min_rssi_dbm": self.min_rssi_dbm,
            "t_ns_range": None if self.t_ns_range is None else list(self.t_ns_range),
            "metadata": json.loads(json.dumps(dict(self.metadata))),
        }


@dataclass(frozen=True, eq=False)
class RadioMap:
    """Located fingerprints. Build with ``from_scans`` / ``from_fingerprints``; read/write with
    ``graphslam.io.radiomap_io``. Arrays are read-only; rows are fingerprints."""

    fingerprints: FingerprintMatrix
    xy: NDArray[np.float64]  # (N, 2) metres, in ``frame``
    session_ids: NDArray[np.str_]  # (N,)
    t_ns: NDArray[np.int64]  # (N,)
    frame: str
    floors: NDArray[np.str_] | None = None  # (N,), "" = unknown
    buildings: NDArray[np.str_] | None = None
    metadata: Mapping[str, Any] = field(default_factory=dict)  # JSON-serialisable provenance/config
    min_rssi_dbm: float = DEFAULT_MIN_RSSI_DBM  # readings below this were dropped; queries get the same
    format_version: int = RADIO_MAP_FORMAT_VERSION
    # BSSID -> column, built once: queries are encoded against it many times.
    _index: dict[str, int] = field(init=False, repr=False, compare=False, default_factory=dict)

    def __post_init__(self) -> None:
        fm = canonical_fingerprints(self.fingerprints)
        n = len(fm)  # an empty map is valid (a degenerate survey); it answers no query
        xy = np.asarray(self.xy, dtype=np.float64).reshape(-1, 2) if n == 0 else np.asarray(self.xy, np.float64)
        if xy.shape != (n, 2):
            raise RadioMapError(f"radio map: xy has shape {xy.shape}, expected ({n}, 2)")
        if not np.isfinite(xy).all():
            raise RadioMapError(f"radio map: non-finite position at row {int(np.flatnonzero(~np.isfinite(xy).all(1))[0])}")
        sids = np.asarray(self.session_ids, dtype=str).ravel()
        if len(sids) != n:
            raise RadioMapError(f"radio map: {len(sids)} session ids for {n} fingerprints")
        t = np.asarray(self.t_ns)
        if t.shape != (n,) or not np.issubdtype(t.dtype, np.integer):
            raise RadioMapError(f"radio map: t_ns must be {n} integers (ns), got shape {t.shape} dtype {t.dtype}")
        if not self.frame or not isinstance(self.frame, str):
            raise RadioMapError("radio map: frame must be a non-empty string")
        if not np.isfinite(self.min_rssi_dbm) or not np.isfinite(fm.missing_dbm):
            raise RadioMapError("radio map: missing_dbm and min_rssi_dbm must be finite")
        if self.format_version != RADIO_MAP_FORMAT_VERSION:
            raise RadioMapError(
                f"radio map: format version {self.format_version} not supported (expected {RADIO_MAP_FORMAT_VERSION})"
            )
        object.__setattr__(self, "fingerprints", fm)
        object.__setattr__(self, "xy", frozen_array(xy, np.float64))
        object.__setattr__(self, "session_ids", frozen_array(sids, str))
        object.__setattr__(self, "t_ns", frozen_array(t, np.int64))
        object.__setattr__(self, "floors", _labels("floors", self.floors, n))
        object.__setattr__(self, "buildings", _labels("buildings", self.buildings, n))
        object.__setattr__(self, "metadata", _json_metadata(self.metadata))
        object.__setattr__(self, "min_rssi_dbm", float(self.min_rssi_dbm))
        object.__setattr__(self, "_index", {b: i for i, b in enumerate(fm.bssids)})
        empty = int(np.sum(np.diff(fm.values.indptr) == 0))
        if empty:
            log.info("radio map: %d of %d fingerprints hear no access point", empty, n)

    def with_metadata(self, **extra: Any) -> "RadioMap":
        """The same map with ``extra`` keys added to (or replacing those of) its metadata."""
        import dataclasses

        return dataclasses.replace(self, metadata={**dict(self.metadata), **extra})

    # ---- constructors -------------------------------------------------------------

    @classmethod
    def from_scans(
        cls,
        scans: Sequence[Mapping[str, float]],
        xy: NDArray | Sequence[Sequence[float]],
        *,
        session_ids: Sequence[str] | str,
        t_ns: Sequence[int] | NDArray,
        frame: str,
        floors: Sequence[Any] | None = None,
        buildings: Sequence[Any] | None = None,
        metadata: Mapping[str, Any] | None = None,
        missing_dbm: float = DEFAULT_MISSING_DBM,
        min_rssi_dbm: float = DEFAULT_MIN_RSSI_DBM,
    ) -> "RadioMap":
        """One fingerprint per scan (``bssid -> dBm``) located at ``xy[i]``.

        ``session_ids`` is one id per scan, or one string for all of them.
        Readings below ``min_rssi_dbm`` are dropped (the map remembers the threshold and
        applies it to queries too).
        """
        fm = FingerprintMatrix.from_scans(scans, missing_dbm=missing_dbm, min_rssi_dbm=min_rssi_dbm)
        return cls.from_fingerprints(
            fm,
            np.asarray(xy, dtype=np.float64).reshape(-1, 2) if len(scans) else np.zeros((0, 2)),
            session_ids=session_ids,
            t_ns=t_ns,
            frame=frame,
            floors=floors,
            buildings=buildings,
            metadata=metadata,
            min_rssi_dbm=min_rssi_dbm,
        )

    @classmethod
    def from_fingerprints(
        cls,
        fingerprints: FingerprintMatrix,
        xy: NDArray,
        *,
        session_ids: Sequence[str] | str,
        t_ns: Sequence[int] | NDArray,
        frame: str,
        floors: Sequence[Any] | None = None,
        buildings: Sequence[Any] | None = None,
        metadata: Mapping[str, Any] | None = None,
        min_rssi_dbm: float = DEFAULT_MIN_RSSI_DBM,
    ) -> "RadioMap":
        """From an existing ``FingerprintMatrix`` (e.g. a benchmark's dense RSS table)."""
        if isinstance(session_ids, str):
            session_ids = [session_ids] * len(fingerprints)
        return cls(
            fingerprints, np.asarray(xy, dtype=np.float64), np.asarray(list(session_ids), dtype=str),
            np.asarray(t_ns, dtype=np.int64), frame, floors, buildings, metadata or {}, min_rssi_dbm,
        )

    # ---- access -------------------------------------------------------------------

    def __len__(self) -> int:
        return len(self.fingerprints)

    @property
    def bssids(self) -> tuple[str, ...]:
        return self.fingerprints.bssids

    @property
    def missing_dbm(self) -> float:
        return self.fingerprints.missing_dbm

    def column(self, bssid: str) -> int | None:
        """``bssid``'s column in ``fingerprints`` (None: no fingerprint heard it)."""
        return self._index.get(bssid)

    def encode(self, scans: Sequence[Mapping[str, float]]) -> FingerprintMatrix:
        """Query scans as fingerprints over this map's AP index (unknown APs go to ``extra_*``),
        with the map's ``missing_dbm`` and ``min_rssi_dbm``. Same result as
        ``FingerprintMatrix.from_scans(scans, bssids=self.bssids, ...)`` without rebuilding the
        BSSID index per call (it dominates single-query latency on large maps)."""
        fm = FingerprintMatrix.encode(scans, self.bssids, self._index, self.missing_dbm, self.min_rssi_dbm)
        _check_finite(fm.values.data, fm.extra_sq)
        return fm

    def scan_arrays(
        self, scans: Sequence[Mapping[str, float]]
    ) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
        """``encode``'s content as arrays (``fingerprints.scan_arrays``: rows, cols, shifted values in
        scan order; ``extra_sq``, ``extra_n``), same checks, no sparse matrix."""
        a = scan_arrays(scans, self._index, self.missing_dbm, self.min_rssi_dbm)
        _check_finite(a[2], a[3])
        return a

    def reindex(self, fm: FingerprintMatrix) -> FingerprintMatrix:
        """``fm`` (any AP index, same ``missing_dbm``) re-expressed over this map's AP index,
        vectorised. Readings below the map's ``min_rssi_dbm`` are dropped, as in ``encode``."""
        if fm.missing_dbm != self.missing_dbm:
            raise RadioMapError(
                f"radio map: query missing_dbm {fm.missing_dbm} differs from the map's {self.missing_dbm}"
            )
        index = self._index
        col_map = np.array([index.get(b, -1) for b in fm.bssids], dtype=np.int64)
        coo = fm.values.tocoo()
        keep = coo.data >= heard_floor(self.min_rssi_dbm, self.missing_dbm) - self.missing_dbm
        rows, cols, data = coo.row[keep], col_map[coo.col[keep]], coo.data[keep]
        known = cols >= 0
        n = len(fm)
        extra_sq = np.bincount(rows[~known], weights=data[~known] ** 2, minlength=n) + fm.extra_sq
        extra_n = np.bincount(rows[~known], minlength=n).astype(np.int64) + fm.extra_n
        v = sparse.csr_matrix((data[known], (rows[known], cols[known])), shape=(n, len(index)))
        return FingerprintMatrix(self.bssids, v, self.missing_dbm, extra_sq, extra_n)

    def summary(self) -> RadioMapSummary:
        def counts(labels: NDArray | None) -> dict[str, int] | None:
            if labels is None:
                return None
            u, c = np.unique(labels, return_counts=True)
            return {str(k): int(v) for k, v in zip(u, c)}

        n = len(self)
        bbox = None
        if n:
            lo, hi = self.xy.min(axis=0), self.xy.max(axis=0)
            bbox = (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))
        return RadioMapSummary(
            format_version=self.format_version,
            frame=self.frame,
            n_fingerprints=n,
            n_access_points=self.fingerprints.n_aps,
            n_sessions=int(len(np.unique(self.session_ids))),
            mean_aps_per_fingerprint=float(self.fingerprints.values.nnz / n) if n else 0.0,
            bbox=bbox,
            floors=counts(self.floors),
            buildings=counts(self.buildings),
            missing_dbm=float(self.missing_dbm),
            min_rssi_dbm=self.min_rssi_dbm,
            t_ns_range=(int(self.t_ns.min()), int(self.t_ns.max())) if n else None,
            metadata=self.metadata,
        )
