"""Importer for the UJIIndoorLoc WiFi fingerprint benchmark (Torres-Sospedra et al., IPIN 2014).

CSV (optionally gzip-compressed, by the ``.gz`` suffix): one row per fingerprint,
columns ``WAP001..WAP520`` (RSSI in dBm, ``100`` = not heard), ``LONGITUDE`` and
``LATITUDE`` (despite the names: EPSG:3857 web-Mercator metres), ``FLOOR``,
``BUILDINGID``; optional ``USERID``, ``PHONEID``, ``TIMESTAMP`` (Unix seconds) and
others, which are ignored.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from graphslam import DEFAULT_MIN_RSSI_DBM, DEFAULT_MISSING_DBM, FingerprintMatrix, InputError, RadioMap

log = logging.getLogger(__name__)

UJI_NOT_HEARD = 100
UJI_FRAME = "EPSG:3857"
REQUIRED_COLUMNS = ("LONGITUDE", "LATITUDE", "FLOOR", "BUILDINGID")
# The dataset's documented RSSI range is [-104, 0] dBm; anything else (but 100) is a broken file.
RSSI_RANGE = (-150.0, 0.0)


@dataclass(frozen=True, eq=False)
class UjiIndoorLoc:
    """One UJIIndoorLoc CSV: dense RSS table (NaN = not heard) plus labels."""

    path: str
    bssids: tuple[str, ...]  # WAP column names, file order
    rssi: NDArray[np.float64]  # (N, A) dBm, NaN where not heard
    xy: NDArray[np.float64]  # (N, 2) EPSG:3857 metres (LONGITUDE, LATITUDE columns)
    floor: NDArray[np.int64]  # (N,)
    building: NDArray[np.int64]  # (N,)
    session_ids: NDArray[np.str_]  # (N,) "u<USERID>-p<PHONEID>" (or the file stem)
    t_ns: NDArray[np.int64]  # (N,) TIMESTAMP in ns (or 0)

    def __post_init__(self) -> None:
        for name in ("rssi", "xy", "floor", "building", "session_ids", "t_ns"):
            getattr(self, name).setflags(write=False)

    def __len__(self) -> int:
        return len(self.xy)

    def fingerprints(
        self, *, missing_dbm: float = DEFAULT_MISSING_DBM, min_rssi_dbm: float = DEFAULT_MIN_RSSI_DBM
    ) -> FingerprintMatrix:
        return FingerprintMatrix.from_dense(self.rssi, self.bssids, missing_dbm=missing_dbm, min_rssi_dbm=min_rssi_dbm)

    def to_radio_map(
        self, *, missing_dbm: float = DEFAULT_MISSING_DBM, min_rssi_dbm: float = DEFAULT_MIN_RSSI_DBM
    ) -> RadioMap:
        """Every row as a located fingerprint, frame ``EPSG:3857``, floor and building labels."""
        return RadioMap.from_fingerprints(
            self.fingerprints(missing_dbm=missing_dbm, min_rssi_dbm=min_rssi_dbm),
            self.xy,
            session_ids=self.session_ids,
            t_ns=self.t_ns,
            frame=UJI_FRAME,
            floors=self.floor.astype(str),
            buildings=self.building.astype(str),
            metadata={"source": "UJIIndoorLoc", "file": Path(self.path).name},
            min_rssi_dbm=min_rssi_dbm,
        )


def _column(path: Path, table: object, name: str) -> NDArray:
    col = table.column(name)  # type: ignore[attr-defined]
    if col.null_count:
        raise InputError(path, f"{col.null_count} empty cells", field=name)
    try:
        return col.to_numpy()
    except Exception as e:  # pyarrow raises several types for odd columns
        raise InputError(path, f"cannot read column ({e})", field=name) from None


def read_ujiindoorloc(path: str | Path) -> UjiIndoorLoc:
    """Read one UJIIndoorLoc CSV(.gz). Raises ``InputError`` naming the file and column."""
    import pyarrow as pa
    import pyarrow.csv as pacsv

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such file")
    try:
        table = pacsv.read_csv(path)
    except (pa.ArrowInvalid, OSError, EOFError) as e:
        raise InputError(path, f"not a readable UJIIndoorLoc CSV ({e})") from None
    names = table.column_names
    waps = [c for c in names if c.startswith("WAP")]
    if not waps:
        raise InputError(path, "no WAP columns (expected WAP001..WAP520)", field="WAP*")
    for c in REQUIRED_COLUMNS:
        if c not in names:
            raise InputError(path, "missing column", field=c)
    n = table.num_rows
    rssi = np.empty((n, len(waps)), dtype=np.float64)
    for j, c in enumerate(waps):
        v = _column(path, table, c)
        if not np.issubdtype(v.dtype, np.number):
            raise InputError(path, f"expected numbers, got {v.dtype}", field=c)
        v = v.astype(np.float64)
        heard = v != UJI_NOT_HEARD
        bad = heard & ~((v >= RSSI_RANGE[0]) & (v <= RSSI_RANGE[1]))
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise InputError(path, f"row {i + 2}: RSSI {v[i]} outside {RSSI_RANGE} and not {UJI_NOT_HEARD}", field=c)
        rssi[:, j] = np.where(heard, v, np.nan)
    num = {}
    for c in REQUIRED_COLUMNS:
        v = _column(path, table, c)
        if not np.issubdtype(v.dtype, np.number) or not np.isfinite(v.astype(float)).all():
            raise InputError(path, "expected finite numbers", field=c)
        num[c] = v
    if "USERID" in names and "PHONEID" in names:
        u, p = _column(path, table, "USERID"), _column(path, table, "PHONEID")
        sids = np.char.add(np.char.add("u", u.astype(str)), np.char.add("-p", p.astype(str)))
    else:
        sids = np.full(n, path.name.split(".")[0])
    t_ns = np.zeros(n, np.int64)
    if "TIMESTAMP" in names:
        t_ns = _column(path, table, "TIMESTAMP").astype(np.int64) * 1_000_000_000
    log.info("%s: %d fingerprints, %d WAP columns", path, n, len(waps))
    return UjiIndoorLoc(
        path=str(path),
        bssids=tuple(waps),
        rssi=rssi,
        xy=np.column_stack([num["LONGITUDE"], num["LATITUDE"]]).astype(np.float64),
        floor=num["FLOOR"].astype(np.int64),
        building=num["BUILDINGID"].astype(np.int64),
        session_ids=np.asarray(sids, dtype=str),
        t_ns=t_ns,
    )
