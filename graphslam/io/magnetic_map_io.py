"""Magnetic map files (``magnetic_map.parquet``): Parquet, one row per located field sample.

Schema (format version 1; ``graphslam.core.radiomap.magnetic_map``):

==============  ===========  ==================================================
column          Arrow type   meaning
==============  ===========  ==================================================
session_id      string       walk the sample came from
t_ns            int64        the step's time, ns since the Unix epoch
x, y            float64      position, metres, in the map's frame
magnitude_ut    float64      |B| (µT), the walk's offset removed
horizontal_ut   float64      |B_h| (µT), the walk's offset removed
vertical_ut     float64      B_up (µT, Earth frame), the walk's offset removed
==============  ===========  ==================================================

File key-value metadata ``graphslam.magnetic_map`` (JSON): ``format_version``, ``frame``,
``n_samples``, ``offsets`` (walk -> the three offsets removed, µT), ``metadata`` and
``content_sha256`` (SHA-256 of the decoded map, checked on read, as the radio map's is).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import numpy as np

from graphslam.core.radiomap.magnetic_map import FEATURES, MAGNETIC_MAP_FORMAT_VERSION, MagneticMap
from graphslam.errors import RadioMapError
from graphslam.io.atomic import atomic_open

METADATA_KEY = b"graphslam.magnetic_map"
HASH_KEY = "content_sha256"
COLUMNS = ("session_id", "t_ns", "x", "y", *FEATURES)


def content_hash(mm: MagneticMap) -> str:
    """SHA-256 (hex) of everything a magnetic map holds: what its file must decode to."""
    h = hashlib.sha256()

    def put(tag: str, data: bytes) -> None:
        h.update(tag.encode())
        h.update(len(data).to_bytes(8, "little"))
        h.update(data)

    put("format_version", str(mm.format_version).encode())
    put("frame", mm.frame.encode())
    put("session_ids", json.dumps([str(s) for s in mm.session_ids], ensure_ascii=False).encode())
    put("t_ns", np.ascontiguousarray(mm.t_ns, "<i8").tobytes())
    put("xy", np.ascontiguousarray(mm.xy, "<f8").tobytes())
    put("features", np.ascontiguousarray(mm.features, "<f8").tobytes())
    put("offsets", json.dumps({k: list(v) for k, v in mm.offsets.items()}, sort_keys=True).encode())
    put("metadata", json.dumps(dict(mm.metadata), sort_keys=True, ensure_ascii=False).encode())
    return h.hexdigest()


def write_magnetic_map(mm: MagneticMap, path: str | Path) -> Path:
    """Write ``mm`` to ``path`` as Parquet (zstd, page checksums), atomically."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    path = Path(path)
    cols = [
        pa.array(mm.session_ids.tolist(), type=pa.string()),
        pa.array(mm.t_ns, type=pa.int64()),
        pa.array(mm.xy[:, 0], type=pa.float64()),
        pa.array(mm.xy[:, 1], type=pa.float64()),
        *(pa.array(mm.features[:, k], type=pa.float64()) for k in range(3)),
    ]
    meta = {
        "format_version": mm.format_version, "frame": mm.frame, "n_samples": len(mm),
        "offsets": {k: list(v) for k, v in mm.offsets.items()}, "metadata": dict(mm.metadata),
        HASH_KEY: content_hash(mm),
    }
    schema = pa.schema([(c, a.type) for c, a in zip(COLUMNS, cols)]).with_metadata(
        {METADATA_KEY: json.dumps(meta, sort_keys=True).encode()})
    with atomic_open(path, "wb") as fh:
        pq.write_table(pa.Table.from_arrays(cols, schema=schema), fh, compression="zstd", write_page_checksum=True)
    return path


def _fail(path: Path, problem: str, field: str | None = None) -> RadioMapError:
    return RadioMapError(f"{path}" + (f" [field {field}]" if field else "") + f": {' '.join(problem.split())}")


def read_magnetic_map(path: str | Path) -> MagneticMap:
    """Read a magnetic map file; ``RadioMapError`` naming the file and field when it is not one, is of
    another format version, misses or mistypes a column, holds a non-finite value, or was changed."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    path = Path(path)
    if not path.is_file():
        raise _fail(path, "no such file" if not path.exists() else "not a file")
    try:
        table = pq.read_table(path, page_checksum_verification=True)
    except (pa.ArrowException, OSError, ValueError) as e:
        raise _fail(path, f"not a readable Parquet file ({e})") from None
    raw = (table.schema.metadata or {}).get(METADATA_KEY)
    if raw is None:
        raise _fail(path, "no graphslam.magnetic_map metadata: not a graphslam magnetic map", "metadata")
    try:
        meta: dict[str, Any] = json.loads(raw)
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise _fail(path, f"metadata is not JSON ({e})", "metadata") from None
    if not isinstance(meta, dict):
        raise _fail(path, "metadata is not a JSON object", "metadata")
    if meta.get("format_version") != MAGNETIC_MAP_FORMAT_VERSION:
        raise _fail(path, f"format version {meta.get('format_version')!r}, this graphslam reads version "
                    f"{MAGNETIC_MAP_FORMAT_VERSION}", "metadata.format_version")
    arrays: dict[str, np.ndarray] = {}
    for c in COLUMNS:
        if c not in table.column_names:
            raise _fail(path, "missing column", c)
        col = table.column(c)
        if col.null_count:
            raise _fail(path, f"{col.null_count} null values", c)
        kind = pa.types.is_string if c == "session_id" else pa.types.is_integer if c == "t_ns" else pa.types.is_floating
        if not kind(col.type):
            raise _fail(path, f"unexpected type {col.type}", c)
        arrays[c] = col.to_numpy()
    try:
        mm = MagneticMap(
            arrays["session_id"].astype(str), arrays["t_ns"].astype(np.int64),
            np.column_stack([arrays["x"], arrays["y"]]).astype(np.float64),
            np.column_stack([arrays[c] for c in FEATURES]).astype(np.float64),
            frame=str(meta.get("frame") or ""), offsets=meta.get("offsets") or {}, metadata=meta.get("metadata") or {},
        )
    except (RadioMapError, TypeError, ValueError) as e:
        raise _fail(path, str(e)) from None
    if meta.get(HASH_KEY) != content_hash(mm):
        raise _fail(path, "content does not match its SHA-256: the file is damaged or was changed after it was "
                    "written", f"metadata.{HASH_KEY}")
    return mm
