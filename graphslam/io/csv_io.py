"""CSV outputs (atomic)."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Iterable, Mapping, Sequence

from graphslam.core.types import PoseTrack
from graphslam.io.atomic import atomic_open

TRAJECTORY_HEADER = ("session_id", "t_ns", "x", "y", "heading")


def write_trajectories(tracks: Mapping[str, PoseTrack], path: str | Path) -> Path:
    """``session_id,t_ns,x,y,heading``: every step of every aligned walk (metres, radians)."""
    path = Path(path)
    with atomic_open(path, "w", encoding="utf-8", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(TRAJECTORY_HEADER)
        for sid, tr in tracks.items():
            for t, (x, y), h in zip(tr.t_ns.tolist(), tr.xy.tolist(), tr.heading.tolist()):
                w.writerow((sid, t, f"{x:.4f}", f"{y:.4f}", f"{h:.6f}"))
    return path


def write_rows(path: str | Path, header: Sequence[str], rows: Iterable[Sequence[object]]) -> Path:
    path = Path(path)
    with atomic_open(path, "w", encoding="utf-8", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        w.writerows(rows)
    return path


def read_trajectories(path: str | Path) -> dict[str, PoseTrack]:
    import numpy as np

    from graphslam.errors import InputError

    rows: dict[str, list[tuple[int, float, float, float]]] = {}
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            r = csv.reader(fh)
            header = next(r, None)
            if tuple(header or ()) != TRAJECTORY_HEADER:
                raise InputError(path, f"header {header!r}, expected {','.join(TRAJECTORY_HEADER)}")
            for n, row in enumerate(r, start=2):
                try:
                    rows.setdefault(row[0], []).append((int(row[1]), float(row[2]), float(row[3]), float(row[4])))
                except (ValueError, IndexError):
                    raise InputError(path, f"line {n}: malformed row {row!r}") from None
    except OSError as e:
        raise InputError(path, f"cannot read: {e.strerror or e}") from None
    except (UnicodeDecodeError, csv.Error) as e:
        raise InputError(path, f"not a readable CSV file ({type(e).__name__})") from None
    out = {}
    for sid, rr in rows.items():
        a = np.array(rr, dtype=float)
        try:
            out[sid] = PoseTrack(np.array([x[0] for x in rr], np.int64), a[:, 1:3], a[:, 3])
        except ValueError as e:
            raise InputError(path, f"session {sid}: {e}") from None
    return out
