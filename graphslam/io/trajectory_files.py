"""One walk's trajectory as a file other tools read (``graphslam export``): TUM, KITTI or CSV.

- TUM (``.tum``): ``timestamp tx ty tz qx qy qz qw`` per line, space-separated, the timestamp in
  seconds (nanoseconds exact: ``sec.nnnnnnnnn``), z = 0 and the heading as a unit quaternion about
  z; a ``#`` header line. What ``evo_traj tum`` / ``evo_ape tum`` read: 8 entries per row, no
  trailing space, ascending unique timestamps, unit quaternions.
- KITTI (``.kitti``): the first three rows of the 4x4 pose matrix, 12 numbers per line
  (``r11 r12 r13 tx r21 r22 r23 ty r31 r32 r33 tz``), no timestamps (``evo_traj kitti``).
- CSV (``.csv``): ``t_ns,x,y,heading`` with a header (m, rad), as trajectories.csv.

Steps with the same timestamp as the one before (evo refuses duplicates) keep the first.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from graphslam.core.types import PoseTrack
from graphslam.io.atomic import atomic_write_text

SUFFIX = {"tum": ".tum", "kitti": ".kitti", "csv": ".csv"}


def unique_times(track: PoseTrack) -> PoseTrack:
    """``track`` without the steps whose timestamp repeats the previous one's."""
    keep = np.concatenate([[True], np.diff(track.t_ns) > 0]) if len(track) else np.zeros(0, bool)
    if keep.all():
        return track
    return PoseTrack(track.t_ns[keep], track.xy[keep], track.heading[keep])


def _seconds(t_ns: int) -> str:
    sign, t = ("-", -t_ns) if t_ns < 0 else ("", t_ns)
    return f"{sign}{t // 1_000_000_000}.{t % 1_000_000_000:09d}"


def tum_text(track: PoseTrack) -> str:
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for t, (x, y), h in zip(track.t_ns.tolist(), track.xy.tolist(), track.heading.tolist()):
        lines.append(f"{_seconds(t)} {x:.6f} {y:.6f} 0.0 0.0 0.0 {math.sin(h / 2):.9f} {math.cos(h / 2):.9f}")
    return "\n".join(lines) + "\n"


def kitti_text(track: PoseTrack) -> str:
    lines = []
    for (x, y), h in zip(track.xy.tolist(), track.heading.tolist()):
        c, s = math.cos(h), math.sin(h)
        lines.append(f"{c:.9f} {-s:.9f} 0.0 {x:.6f} {s:.9f} {c:.9f} 0.0 {y:.6f} 0.0 0.0 1.0 0.0")
    return "\n".join(lines) + "\n"


def csv_text(track: PoseTrack) -> str:
    rows = [f"{t},{x:.6f},{y:.6f},{h:.6f}" for t, (x, y), h in zip(track.t_ns.tolist(), track.xy.tolist(), track.heading.tolist())]
    return "\n".join(["t_ns,x,y,heading", *rows]) + "\n"


def write_trajectory(track: PoseTrack, path: str | Path, fmt: str) -> Path:
    """``track`` (duplicate timestamps dropped) as ``fmt`` (tum, kitti, csv), written atomically."""
    text = {"tum": tum_text, "kitti": kitti_text, "csv": csv_text}[fmt](unique_times(track))
    atomic_write_text(path, text)
    return Path(path)
