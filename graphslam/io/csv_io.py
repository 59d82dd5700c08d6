"""CSV outputs (atomic) and trajectories.csv read back."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Iterable, Mapping, NamedTuple, Sequence

from graphslam.core.types import PoseTrack
from graphslam.io.atomic import atomic_open

TRAJECTORY_HEADER = ("session_id", "t_ns", "x", "y", "heading", "component", "frame")
# trajectories.csv before the frame column, and before components (every walk in component 0)
TRAJECTORY_HEADER_V2 = TRAJECTORY_HEADER[:6]
TRAJECTORY_HEADER_V1 = TRAJECTORY_HEADER[:5]


def component_frame(main_frame: str, component: int) -> str:
    """The frame a walk of ``component`` is in: the main map's (``main_frame``, report.json's
    ``frame``) for component 0, ``component_<k>`` (a frame of its own) for the others."""
    return main_frame if component == 0 else f"component_{component}"


def write_trajectories(
    tracks: Mapping[str, PoseTrack], path: str | Path, components: Mapping[str, int] | None = None,
    frame: str = "aligned",
) -> Path:
    """``session_id,t_ns,x,y,heading,component,frame``: every step of every aligned walk (metres,
    radians); ``component``: 0 for the main map (the radio map's frame), k >= 1 for a walk in a
    component of its own frame (``components``: session id -> index; None or missing: 0);
    ``frame``: the main map's frame name (report.json's) for component 0, ``component_<k>`` else."""
    path = Path(path)
    comp = components or {}
    with atomic_open(path, "w", encoding="utf-8", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(TRAJECTORY_HEADER)
        for sid, tr in tracks.items():
            c = int(comp.get(sid, 0))
            f = component_frame(frame, c)
            for t, (x, y), h in zip(tr.t_ns.tolist(), tr.xy.tolist(), tr.heading.tolist()):
                w.writerow((sid, t, f"{x:.4f}", f"{y:.4f}", f"{h:.6f}", c, f))
    return path


def write_rows(path: str | Path, header: Sequence[str], rows: Iterable[Sequence[object]]) -> Path:
    path = Path(path)
    with atomic_open(path, "w", encoding="utf-8", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        w.writerows(rows)
    return path


class TrajectoryFile(NamedTuple):
    """trajectories.csv read back: the walks and the component each belongs to."""

    tracks: dict[str, PoseTrack]
    components: dict[str, int]  # session id -> component (0: the main map)
    frame: str = ""  # the main map's frame name ("" in a file written before the frame column)

    def of_component(self, index: int) -> dict[str, PoseTrack]:
        return {sid: t for sid, t in self.tracks.items() if self.components.get(sid, 0) == index}


def read_trajectories(path: str | Path, component: int | None = None) -> dict[str, PoseTrack]:
    """The walks of trajectories.csv (``component``: only those of that component)."""
    f = read_trajectory_file(path)
    return f.tracks if component is None else f.of_component(component)


def read_trajectory_file(path: str | Path) -> TrajectoryFile:
    """trajectories.csv with or without its ``frame`` and ``component`` columns (a file written
    before components: every walk in component 0)."""
    import numpy as np

    from graphslam.errors import InputError

    rows: dict[str, list[tuple[int, float, float, float]]] = {}
    comp: dict[str, int] = {}
    main_frame = ""
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            r = csv.reader(fh)
            header = tuple(next(r, None) or ())
            if header not in (TRAJECTORY_HEADER, TRAJECTORY_HEADER_V2, TRAJECTORY_HEADER_V1):
                raise InputError(path, f"header {list(header)!r}, expected {','.join(TRAJECTORY_HEADER)}")
            width = len(header)
            for n, row in enumerate(r, start=2):
                try:
                    if len(row) != width:
                        raise IndexError
                    c = int(row[5]) if width >= 6 else 0
                    if c < 0:
                        raise ValueError
                    if width == 7 and c == 0:
                        main_frame = main_frame or row[6]
                    rows.setdefault(row[0], []).append((int(row[1]), float(row[2]), float(row[3]), float(row[4])))
                except (ValueError, IndexError):
                    raise InputError(path, f"line {n}: malformed row {row!r}") from None
                if comp.setdefault(row[0], c) != c:
                    raise InputError(path, f"line {n}: session {row[0]} in component {c}, "
                                           f"earlier rows in {comp[row[0]]}", field="component")
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
    return TrajectoryFile(out, comp, main_frame)
