"""Control points (``graphslam survey --control-points FILE``): landmarks of known site position.

The file is a CSV with the header ``landmark_id,x,y`` and one row per control point: the
``landmark_id`` exactly as the walks mark it on ``/landmarks`` (standard CSV quoting: an id
holding a comma is quoted, ``"49.461132,11.111006",-10.341,-2.250``), and its site position
in metres. A UTF-8 byte-order mark and blank lines are accepted; anything else that is not one
control point per row (another header, a missing or extra column, an empty or duplicate id,
a coordinate that is not a finite number) is an ``InputError`` naming the file, the line and
the field.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

from graphslam.errors import InputError

HEADER = ("landmark_id", "x", "y")


def read_control_points(path: str | Path) -> dict[str, tuple[float, float]]:
    """landmark id -> (x, y) site metres, in the file's order."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "control points file not found")
    out: dict[str, tuple[float, float]] = {}
    first_line: dict[str, int] = {}
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            reader = csv.reader(fh, strict=True)
            header = next(reader, None)
            if header is None:
                raise InputError(path, "empty file: expected the header landmark_id,x,y and one row per control point")
            if tuple(c.strip() for c in header) != HEADER:
                raise InputError(path, f"line 1: header {','.join(header)!r}, expected {','.join(HEADER)}")
            for row in reader:
                n = reader.line_num
                if not row:
                    continue  # a blank line
                if len(row) != len(HEADER):
                    raise InputError(path, f"line {n}: {len(row)} columns, expected 3 (landmark_id,x,y; quote an "
                                           "id that holds a comma)")
                lid = row[0]
                if not lid.strip():
                    raise InputError(path, f"line {n}: empty landmark id", field="landmark_id")
                if lid in first_line:
                    raise InputError(path, f"line {n}: duplicate landmark id {lid!r} (first on line {first_line[lid]})",
                                     field="landmark_id")
                xy = tuple(_coordinate(path, n, name, text) for name, text in zip(HEADER[1:], row[1:]))
                first_line[lid] = n
                out[lid] = (xy[0], xy[1])
    except OSError as e:
        raise InputError(path, f"cannot read: {e.strerror or e}") from None
    except (UnicodeDecodeError, csv.Error) as e:
        raise InputError(path, f"not a readable CSV file ({type(e).__name__}: {e})") from None
    if not out:
        raise InputError(path, "no control point: the file has a header and no rows")
    return out


def _coordinate(path: Path, line: int, name: str, text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise InputError(path, f"line {line}: {text!r} is not a number (site metres)", field=name) from None
    if not math.isfinite(v):
        raise InputError(path, f"line {line}: {text!r} is not a finite number (site metres)", field=name)
    return v
