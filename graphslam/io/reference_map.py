"""A site's surveyed radio map as the survey's anchors (``graphslam survey --reference-map FILE``).

Two forms, both fingerprints at known site positions (metres):

- a CSV with the header ``fingerprint_id,x,y,bssid,rssi_dbm`` and one row per reading (standard CSV
  quoting): every row of one ``fingerprint_id`` gives the same ``x, y``; ``rssi_dbm`` in dBm;
- a radio map graphslam wrote (``radio_map.parquet`` of a previous survey) whose frame is ``site``
  (control points, UWB anchors or a reference map): a map in an ``aligned`` or ``earth`` frame has no
  known place in the site and is refused. The survey's ``magnetic_map.parquet`` beside it, when there is
  one, is the reference's magnetic field (``read_reference_field``).

A UTF-8 byte-order mark and blank lines are accepted. Anything else (another header, a missing or
extra column, an empty id or BSSID, a coordinate or RSS that is not a finite number, two positions
for one fingerprint, a BSSID twice in one fingerprint, no fingerprint at all) is an ``InputError``
naming the file, the line and the field.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from graphslam.core.radiomap.fingerprints import FingerprintMatrix
from graphslam.core.radiomap.magnetic_map import MagneticMap
from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.errors import GraphSlamError, InputError

HEADER = ("fingerprint_id", "x", "y", "bssid", "rssi_dbm")
REFERENCE_SESSION = "reference"  # the session id of the reference's rows in the survey's radio map
FIELD_FILE = "magnetic_map.parquet"  # a previous survey's field, beside its radio map
# from this size Arrow parses on its threads (a smaller file is parsed sooner than they start)
THREADED_MIN_BYTES = 1 << 20


def read_reference_map(path: str | Path, *, min_rssi_dbm: float = -100.0, missing_dbm: float = -110.0) -> RadioMap:
    """The reference map at ``path`` (CSV or graphslam Parquet), frame ``site``; its rows' session id is
    ``reference`` for a CSV (one survey; the map's own ids for a Parquet file)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "reference map not found" if not path.exists() else "not a file")
    with open(path, "rb") as fh:
        magic = fh.read(4)
    if magic == b"PAR1":
        return _from_radio_map(path)
    return _from_csv(path, min_rssi_dbm, missing_dbm)


def read_reference_field(path: str | Path, reference: RadioMap | None = None) -> MagneticMap | None:
    """The magnetic field of the reference map at ``path``: for a radio map graphslam wrote, the same
    survey's ``magnetic_map.parquet`` beside it (site frame), None when it has none (or for a CSV). An
    ``InputError`` naming that file when it is not a magnetic map, was changed, is in another frame, or
    holds a walk ``reference`` (the radio map read from ``path``) does not: another survey's."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            if fh.read(4) != b"PAR1":
                return None
    except OSError as e:
        raise InputError(path, f"cannot read: {e.strerror or e}") from None
    field_path = path.with_name(FIELD_FILE)
    if not field_path.is_file():
        return None
    from graphslam.io.magnetic_map_io import read_magnetic_map

    try:
        field = read_magnetic_map(field_path)
    except GraphSlamError as e:
        raise InputError(field_path, f"the reference map's field: not a readable magnetic map "
                         f"({' '.join(str(e).split())})") from None
    if field.frame != "site":
        raise InputError(field_path, f"the reference map's field is in the {field.frame!r} frame, its radio map in the "
                         "site frame: not one survey's", field="metadata.frame")
    if reference is not None:
        foreign = sorted(set(np.asarray(field.session_ids).tolist()) - set(np.asarray(reference.session_ids).tolist()))
        if foreign:
            raise InputError(field_path, f"the reference map's field holds walk {foreign[0]!r}, which {path.name} does "
                             f"not ({len(foreign)} such): not one survey's", field="session_id")
    return field


def _from_radio_map(path: Path) -> RadioMap:
    from graphslam.io.radiomap_io import read_radio_map

    try:
        rm = read_radio_map(path)
    except GraphSlamError as e:
        raise InputError(path, f"not a readable radio map ({' '.join(str(e).split())})") from None
    if rm.frame != "site":
        raise InputError(path, f"a radio map in the {rm.frame!r} frame: a reference must be in the site frame (a survey "
                         "with control points, UWB anchors or a reference map)", field="metadata.frame")
    if not len(rm):
        raise InputError(path, "no fingerprint: the reference map is empty")
    return rm


def _from_csv(path: Path, min_rssi_dbm: float, missing_dbm: float) -> RadioMap:
    # a well-formed file parsed by Arrow (a professional survey can hold millions of readings: ~4x the
    # line parser's speed; IPIN's 150 kB 3 against 10 ms, and the survey imports Arrow for its outputs
    # anyway); anything it does not take, or the checks below find, is read again line by line for the
    # error (or accepted there: Python's float() takes a little more than Arrow's)
    parsed = _parsed_fast(path)
    order, xy, row, code, names, rssi = parsed if parsed is not None else _parsed_checked(path)
    fm = FingerprintMatrix.from_readings(row, code, names, rssi, len(order), missing_dbm=missing_dbm,
                                         min_rssi_dbm=min_rssi_dbm)
    return RadioMap.from_fingerprints(
        fm, xy, session_ids=REFERENCE_SESSION, t_ns=np.zeros(len(order), np.int64), frame="site",
        metadata={"kind": "reference", "source": str(path), "fingerprint_ids": order}, min_rssi_dbm=min_rssi_dbm,
    )


# (fingerprint ids in order of first appearance, their positions (F, 2), and one entry per reading, grouped
# by fingerprint in that order, in file order within one: its fingerprint, its BSSID as names[code], its dBm)
Parsed = tuple[list[str], np.ndarray, np.ndarray, np.ndarray, list[str], np.ndarray]


def _parsed_fast(path: Path) -> Parsed | None:
    """``Parsed`` of a well-formed file, the same as ``_parsed_checked`` gives; None for anything else."""
    import pyarrow as pa
    from pyarrow import csv as pacsv

    types = {"fingerprint_id": pa.string(), "x": pa.float64(), "y": pa.float64(), "bssid": pa.string(),
             "rssi_dbm": pa.float64()}
    try:
        data = path.read_bytes()
    except OSError:
        return None
    if b'"' in data or b"\x00" in data:  # quoting (Arrow takes some the strict line parser refuses), NUL
        return None
    try:
        table = pacsv.read_csv(
            pa.BufferReader(data), read_options=pacsv.ReadOptions(encoding="utf8",
                                                                  use_threads=len(data) >= THREADED_MIN_BYTES),
            convert_options=pacsv.ConvertOptions(column_types=types, strings_can_be_null=False,
                                                 quoted_strings_can_be_null=False),
        )
    except (pa.ArrowException, OSError, ValueError):
        return None
    if tuple(table.column_names) != HEADER or table.num_rows == 0:
        return None
    x, y, rssi = (table.column(c).to_numpy(zero_copy_only=False) for c in ("x", "y", "rssi_dbm"))
    if not (np.isfinite(x).all() and np.isfinite(y).all() and np.isfinite(rssi).all()):
        return None

    def codes(name: str) -> tuple[list[str], np.ndarray]:  # (values in order of first appearance, each row's)
        # a dict, not Arrow's dictionary_encode: its first call initialises Arrow's compute kernels (~25 ms)
        values = table.column(name).to_pylist()
        index = {v: k for k, v in enumerate(dict.fromkeys(values))}
        return list(index), np.fromiter(map(index.__getitem__, values), np.int64, len(values))

    ids, fid = codes("fingerprint_id")
    names, bcode = codes("bssid")
    stripped = [b.strip() for b in names]
    if not all(f.strip() for f in ids) or not all(stripped):
        return None
    # a BSSID twice in one fingerprint (after stripping, as the line parser does)
    key = {b: k for k, b in enumerate(dict.fromkeys(stripped))}
    bkey = np.array([key[b] for b in stripped], np.int64)[bcode]
    pair = fid * len(key) + bkey
    if len(np.unique(pair)) != len(pair):
        return None
    first = np.full(len(ids), len(fid), np.int64)
    np.minimum.at(first, fid, np.arange(len(fid)))
    if not (np.array_equal(x, x[first][fid]) and np.array_equal(y, y[first][fid])):
        return None  # two positions for one fingerprint
    rows = np.argsort(fid, kind="stable")  # readings grouped by fingerprint (first appearance), in file order
    return ids, np.column_stack([x[first], y[first]]), fid[rows], bkey[rows], list(key), rssi[rows]


def _parsed_checked(path: Path) -> Parsed:
    """``Parsed``, line by line: an ``InputError`` naming the line and field of the first thing wrong."""
    order: list[str] = []
    where: dict[str, tuple[float, float, int]] = {}  # id -> (x, y, first line)
    readings: dict[str, dict[str, float]] = {}
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            reader = csv.reader(fh, strict=True)
            header = next(reader, None)
            if header is None:
                raise InputError(path, f"empty file: expected the header {','.join(HEADER)} and one row per reading")
            if tuple(c.strip() for c in header) != HEADER:
                raise InputError(path, f"line 1: header {','.join(header)!r}, expected {','.join(HEADER)}")
            for row in reader:
                n = reader.line_num
                if not row:
                    continue
                if len(row) != len(HEADER):
                    raise InputError(path, f"line {n}: {len(row)} columns, expected {len(HEADER)} ({','.join(HEADER)})")
                fid, bssid = row[0], row[3].strip()
                if not fid.strip():
                    raise InputError(path, f"line {n}: empty fingerprint id", field="fingerprint_id")
                if not bssid:
                    raise InputError(path, f"line {n}: empty BSSID", field="bssid")
                x, y, rssi = (_number(path, n, name, text) for name, text in (("x", row[1]), ("y", row[2]),
                                                                                ("rssi_dbm", row[4])))
                if fid not in where:
                    where[fid] = (x, y, n)
                    order.append(fid)
                    readings[fid] = {}
                elif (x, y) != where[fid][:2]:
                    raise InputError(path, f"line {n}: fingerprint {fid!r} at ({x:g}, {y:g}), on line {where[fid][2]} at "
                                     f"({where[fid][0]:g}, {where[fid][1]:g})", field="x")
                if bssid in readings[fid]:
                    raise InputError(path, f"line {n}: BSSID {bssid} twice in fingerprint {fid!r}", field="bssid")
                readings[fid][bssid] = rssi
    except OSError as e:
        raise InputError(path, f"cannot read: {e.strerror or e}") from None
    except (UnicodeDecodeError, csv.Error) as e:
        raise InputError(path, f"not a readable CSV file ({type(e).__name__}: {e})") from None
    if not order:
        raise InputError(path, "no fingerprint: the file has a header and no rows")
    code_of: dict[str, int] = {}
    row, code, rssi = [], [], []
    for k, f in enumerate(order):
        for b, v in readings[f].items():
            row.append(k)
            code.append(code_of.setdefault(b, len(code_of)))
            rssi.append(v)
    return (order, np.array([where[f][:2] for f in order], float), np.array(row, np.int64), np.array(code, np.int64),
            list(code_of), np.array(rssi, np.float64))


def _number(path: Path, line: int, name: str, text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise InputError(path, f"line {line}: {text!r} is not a number", field=name) from None
    if not math.isfinite(v):
        raise InputError(path, f"line {line}: {text!r} is not a finite number", field=name)
    return v
