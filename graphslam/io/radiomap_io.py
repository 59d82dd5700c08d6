"""Radio map files: Parquet, one row per fingerprint, readings as list columns.

Schema (format version 1; see docs/radio_map.md):

=============  ======================  ==========================================
column         Arrow type              meaning
=============  ======================  ==========================================
session_id     string                  session the fingerprint came from
t_ns           int64                   scan time, ns since the Unix epoch
x, y           float64                 position, metres, in the map's frame
floor          string (nullable)       floor label (column absent: no labels)
building       string (nullable)       building label (column absent: no labels)
bssid          list<string>            APs heard (no duplicates within a row)
rssi_dbm       list<float64>           their RSS, dBm, same order as ``bssid``
=============  ======================  ==========================================

File key-value metadata ``graphslam.radio_map`` (JSON): ``format_version``,
``frame``, ``missing_dbm``, ``min_rssi_dbm``, ``n_fingerprints``,
``n_access_points``, ``metadata`` (provenance/config) and ``content_sha256``. The AP
index is not stored: it is the sorted set of BSSIDs in ``bssid`` (``RadioMap`` is canonical).

Integrity: data pages carry Parquet page CRCs (checked on read), and ``content_sha256``
(``content_hash``: SHA-256 of the decoded map) is checked after decoding, so a changed
byte anywhere (data, footer, metadata) is an error, never a silently different map. A
file without ``content_sha256`` (written by another tool) is read with a warning.
"""

from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
from scipy import sparse

from graphslam.core.radiomap.fingerprints import FingerprintMatrix
from graphslam.core.radiomap.radiomap import RADIO_MAP_FORMAT_VERSION, RadioMap
from graphslam.errors import RadioMapError
from graphslam.io.atomic import atomic_open

log = logging.getLogger(__name__)

METADATA_KEY = b"graphslam.radio_map"
REQUIRED_COLUMNS = ("session_id", "t_ns", "x", "y", "bssid", "rssi_dbm")
LABEL_COLUMNS = ("floor", "building")
REQUIRED_META = ("format_version", "frame", "missing_dbm", "min_rssi_dbm")
HASH_KEY = "content_sha256"


def content_hash(rm: RadioMap) -> str:
    """SHA-256 (hex) of everything a radio map holds, in its canonical form: what the file must
    decode to. Also what AP models record of the map they were fitted from."""
    h = hashlib.sha256()

    def put(tag: str, data: bytes) -> None:  # length-prefixed: no two contents hash alike by concatenation
        h.update(tag.encode())
        h.update(len(data).to_bytes(8, "little"))
        h.update(data)

    def strings(a: Any) -> bytes:
        return b"" if a is None else json.dumps([str(v) for v in a], ensure_ascii=False).encode()

    fm = rm.fingerprints
    v = fm.values.copy()
    v.sort_indices()
    put("format_version", str(rm.format_version).encode())
    put("frame", rm.frame.encode())
    put("missing_min", np.array([fm.missing_dbm, rm.min_rssi_dbm], "<f8").tobytes())
    put("bssids", strings(fm.bssids))
    put("indptr", v.indptr.astype("<i8").tobytes())
    put("indices", v.indices.astype("<i8").tobytes())
    put("values", v.data.astype("<f8").tobytes())
    put("xy", np.ascontiguousarray(rm.xy, "<f8").tobytes())
    put("t_ns", np.ascontiguousarray(rm.t_ns, "<i8").tobytes())
    put("session_ids", strings(rm.session_ids))
    put("floors", strings(rm.floors) if rm.floors is not None else b"\0none")
    put("buildings", strings(rm.buildings) if rm.buildings is not None else b"\0none")
    put("metadata", json.dumps(dict(rm.metadata), sort_keys=True, ensure_ascii=False).encode())
    return h.hexdigest()


def _schema() -> Any:
    import pyarrow as pa

    return pa.schema(
        [
            ("session_id", pa.string()),
            ("t_ns", pa.int64()),
            ("x", pa.float64()),
            ("y", pa.float64()),
            ("floor", pa.string()),
            ("building", pa.string()),
            ("bssid", pa.list_(pa.string())),
            ("rssi_dbm", pa.list_(pa.float64())),
        ]
    )


def radio_map_table(rm: RadioMap) -> Any:
    """The radio map as a ``pyarrow.Table`` in the file schema (with its metadata)."""
    import pyarrow as pa

    fm = rm.fingerprints
    v = fm.values.copy()
    v.sort_indices()
    offsets = pa.array(v.indptr.astype(np.int32))
    # Each reading's BSSID materialised (parquet dictionary-encodes them back); indexed in numpy, not
    # with pyarrow's `take`, which imports pyarrow.compute (a slow import)
    flat_bssid = pa.array(np.asarray(fm.bssids, dtype=object)[v.indices], type=pa.string())
    # rssi = v + missing: exact inverse of v = rssi - missing for RSS values (see docs/radio_map.md).
    flat_rssi = pa.array(v.data + fm.missing_dbm, type=pa.float64())
    cols: dict[str, Any] = {
        "session_id": pa.array(rm.session_ids.tolist(), type=pa.string()),
        "t_ns": pa.array(rm.t_ns, type=pa.int64()),
        "x": pa.array(rm.xy[:, 0], type=pa.float64()),
        "y": pa.array(rm.xy[:, 1], type=pa.float64()),
    }
    schema = _schema()
    for name, labels in (("floor", rm.floors), ("building", rm.buildings)):
        if labels is None:
            schema = schema.remove(schema.get_field_index(name))
        else:
            cols[name] = pa.array([s if s else None for s in labels.tolist()], type=pa.string())
    cols["bssid"] = pa.ListArray.from_arrays(offsets, flat_bssid)
    cols["rssi_dbm"] = pa.ListArray.from_arrays(offsets, flat_rssi)
    meta = {
        "format_version": rm.format_version,
        "frame": rm.frame,
        "missing_dbm": rm.missing_dbm,
        "min_rssi_dbm": rm.min_rssi_dbm,
        "n_fingerprints": len(rm),
        "n_access_points": fm.n_aps,
        "metadata": dict(rm.metadata),
        HASH_KEY: content_hash(rm),
    }
    schema = schema.with_metadata({METADATA_KEY: json.dumps(meta, sort_keys=True).encode()})
    return pa.Table.from_arrays([cols[f.name] for f in schema], schema=schema)


def write_radio_map(rm: RadioMap, path: str | Path) -> Path:
    """Write ``rm`` to ``path`` as Parquet (zstd), atomically: complete or absent."""
    import pyarrow.parquet as pq

    path = Path(path)
    table = radio_map_table(rm)
    with atomic_open(path, "wb") as fh:
        pq.write_table(table, fh, compression="zstd", write_page_checksum=True)
    log.info("wrote radio map %s: %d fingerprints, %d APs", path, len(rm), rm.fingerprints.n_aps)
    return path


def _fail(path: Path, problem: str, field: str | None = None) -> RadioMapError:
    where = f"{path}" + (f" [field {field}]" if field else "")
    return RadioMapError(f"{where}: {' '.join(problem.split())}")  # Arrow's messages span lines


def _values(path: Path, table: Any, name: str, kind: str) -> np.ndarray:
    """A column as numpy, checked for type (``kind``: 'string', 'int', 'float') and nulls."""
    import pyarrow as pa

    col = table.column(name)
    t = col.type
    ok = {
        "string": pa.types.is_string(t) or pa.types.is_large_string(t),
        "int": pa.types.is_integer(t),
        "float": pa.types.is_floating(t) or pa.types.is_integer(t),
    }[kind]
    if not ok:
        raise _fail(path, f"expected {kind} values, got {t}", name)
    if col.null_count:
        raise _fail(path, f"{col.null_count} null values", name)
    return col.to_numpy()


def _list_column(path: Path, table: Any, name: str, kind: str) -> tuple[np.ndarray, Any]:
    """(offsets, flat values) of a list column."""
    import pyarrow as pa

    col = table.column(name)
    if not (pa.types.is_list(col.type) or pa.types.is_large_list(col.type)):
        raise _fail(path, f"expected a list column, got {col.type}", name)
    col = col.combine_chunks() if col.num_chunks != 1 else col.chunk(0)
    if col.null_count:
        raise _fail(path, f"{col.null_count} null lists", name)
    flat = col.flatten()  # respects slicing, unlike .values
    offsets = col.offsets.to_numpy().astype(np.int64)
    offsets = offsets - offsets[0]
    vt = flat.type
    ok = (pa.types.is_string(vt) or pa.types.is_large_string(vt)) if kind == "string" else pa.types.is_floating(vt) or pa.types.is_integer(vt)
    if not ok:
        raise _fail(path, f"expected list<{kind}>, got {col.type}", name)
    if flat.null_count:
        raise _fail(path, f"{flat.null_count} null list items", name)
    return offsets, flat


def read_radio_map(path: str | Path) -> RadioMap:
    """Read a radio map file. ``RadioMapError`` (naming the file and field) if it is not a
    Parquet file, has another format version, misses or mistypes a column, or is damaged
    (a page CRC or the content hash does not match)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    path = Path(path)
    if not path.is_file():
        raise _fail(path, "no such file" if not path.exists() else "not a file")
    try:
        table = pq.read_table(path, page_checksum_verification=True)
    except (pa.ArrowException, OSError, ValueError, MemoryError) as e:
        raise _fail(path, f"not a readable Parquet file ({e})") from None
    try:
        rm, meta = _decode(path, table)
    except (pa.ArrowException, UnicodeError, ValueError, KeyError, IndexError, OverflowError) as e:
        # Damage the checks below do not name (e.g. a column name that is no longer UTF-8).
        raise _fail(path, f"damaged radio map file ({type(e).__name__}: {e})") from None
    _verify_hash(path, meta.get(HASH_KEY), rm)
    return rm


def _decode(path: Path, table: Any) -> tuple[RadioMap, dict[str, Any]]:
    import pyarrow as pa
    import pyarrow.compute as pc

    raw = (table.schema.metadata or {}).get(METADATA_KEY)
    if raw is None:
        raise _fail(path, "no graphslam.radio_map metadata: not a graphslam radio map", "metadata")
    try:
        meta = json.loads(raw)
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise _fail(path, f"metadata is not JSON ({e})", "metadata") from None
    if not isinstance(meta, dict):
        raise _fail(path, "metadata is not a JSON object", "metadata")
    for k in REQUIRED_META:
        if k not in meta:
            raise _fail(path, "missing", f"metadata.{k}")
    if meta["format_version"] != RADIO_MAP_FORMAT_VERSION:
        raise _fail(
            path,
            f"format version {meta['format_version']!r}, this graphslam reads version {RADIO_MAP_FORMAT_VERSION}",
            "metadata.format_version",
        )
    for k in ("missing_dbm", "min_rssi_dbm"):
        if isinstance(meta[k], bool) or not isinstance(meta[k], (int, float)) or not np.isfinite(meta[k]):
            raise _fail(path, f"expected a finite number, got {meta[k]!r}", f"metadata.{k}")
    if not isinstance(meta["frame"], str) or not meta["frame"]:
        raise _fail(path, "expected a non-empty string", "metadata.frame")
    extra_meta = meta.get("metadata", {})
    if not isinstance(extra_meta, dict):
        raise _fail(path, "expected a JSON object", "metadata.metadata")
    for c in REQUIRED_COLUMNS:
        if c not in table.column_names:
            raise _fail(path, "missing column", c)
    n = table.num_rows
    sids = _values(path, table, "session_id", "string").astype(str)
    t_ns = _values(path, table, "t_ns", "int").astype(np.int64)
    xy = np.column_stack([_values(path, table, c, "float").astype(np.float64) for c in ("x", "y")])
    if not np.isfinite(xy).all():
        raise _fail(path, f"non-finite position at row {int(np.flatnonzero(~np.isfinite(xy).all(1))[0])}", "x/y")
    labels: dict[str, np.ndarray | None] = {}
    for c in LABEL_COLUMNS:
        if c not in table.column_names:
            labels[c] = None
            continue
        col = table.column(c)
        if not (pa.types.is_string(col.type) or pa.types.is_large_string(col.type)):
            raise _fail(path, f"expected string labels, got {col.type}", c)
        labels[c] = np.array(["" if v is None else v for v in col.to_pylist()], dtype=str)
    off_b, flat_b = _list_column(path, table, "bssid", "string")
    off_r, flat_r = _list_column(path, table, "rssi_dbm", "float")
    if not np.array_equal(off_b, off_r):
        i = int(np.flatnonzero(np.diff(off_b) != np.diff(off_r))[0])
        raise _fail(path, f"row {i}: {off_b[i + 1] - off_b[i]} BSSIDs but {off_r[i + 1] - off_r[i]} RSS values", "rssi_dbm")
    rssi = flat_r.to_numpy(zero_copy_only=False).astype(np.float64)
    missing = float(meta["missing_dbm"])
    bad = ~np.isfinite(rssi) | (rssi <= missing)
    if bad.any():
        j = int(np.flatnonzero(bad)[0])
        row = int(np.searchsorted(off_r, j, side="right") - 1)
        raise _fail(path, f"row {row}: RSS {rssi[j]} is not a finite value above missing_dbm {missing}", "rssi_dbm")
    enc = pc.dictionary_encode(flat_b)
    names = np.array(enc.dictionary.to_pylist(), dtype=object)
    if (names == "").any():
        raise _fail(path, "empty BSSID", "bssid")
    order = np.argsort(names.astype(str), kind="stable")
    rank = np.empty(len(names), np.int64)
    rank[order] = np.arange(len(names))
    cols = rank[enc.indices.to_numpy(zero_copy_only=False).astype(np.int64)] if len(names) else np.zeros(0, np.int64)
    rows = np.repeat(np.arange(n), np.diff(off_b))
    # A BSSID twice in one row would be summed by the sparse constructor: refuse instead.
    key = rows * max(1, len(names)) + cols
    if len(np.unique(key)) != len(key):
        raise _fail(path, "a BSSID appears twice in one fingerprint", "bssid")
    v = sparse.csr_matrix((rssi - missing, (rows, cols)), shape=(n, len(names)))
    v.sort_indices()
    fm = FingerprintMatrix(tuple(names[order].astype(str).tolist()), v, missing)
    if "n_access_points" in meta and meta["n_access_points"] != fm.n_aps:
        raise _fail(path, f"says {meta['n_access_points']} APs, rows hold {fm.n_aps}", "metadata.n_access_points")
    if "n_fingerprints" in meta and meta["n_fingerprints"] != n:
        raise _fail(path, f"says {meta['n_fingerprints']} fingerprints, the file holds {n}", "metadata.n_fingerprints")
    try:
        rm = RadioMap(
            fingerprints=fm,
            xy=xy if n else np.zeros((0, 2)),
            session_ids=sids,
            t_ns=t_ns,
            frame=meta["frame"],
            floors=labels["floor"],
            buildings=labels["building"],
            metadata=extra_meta,
            min_rssi_dbm=float(meta["min_rssi_dbm"]),
        )
    except RadioMapError as e:
        raise _fail(path, str(e)) from None
    return rm, meta


def _verify_hash(path: Path, stored: Any, rm: RadioMap) -> None:
    """Last, so that a file with a precise problem (a missing column, a NaN) says that."""
    if stored is None:
        log.warning("%s: no %s in its metadata (not written by graphslam?): integrity not verified", path, HASH_KEY)
        return
    if stored != content_hash(rm):
        raise _fail(
            path, "content does not match its SHA-256: the file is damaged or was changed after it was written",
            f"metadata.{HASH_KEY}",
        )
