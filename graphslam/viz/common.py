"""What every picture shares, whichever library draws it (Rerun or Pillow): the floor plan,
one colour per walk, the landmark marks. Imports neither library, so a PNG never pays for
Rerun's import."""

from __future__ import annotations

import colorsys
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Mapping

import numpy as np
from numpy.typing import NDArray

from graphslam.core.radiomap.fingerprints import FingerprintMatrix
from graphslam.core.survey.evaluate import ErrorStats, landmark_errors
from graphslam.core.common.geometry import interpolate_xy
from graphslam.core.types import PoseTrack, Survey
from graphslam.errors import InputError
from graphslam.io.csv_io import TrajectoryFile
from graphslam.io.floor_plan import FloorPlan, load_floor_plan  # noqa: F401 (re-exported: the pictures' API)


def session_colours(session_ids: Iterable[str]) -> dict[str, tuple[int, int, int]]:
    """A distinct colour per session (golden-angle hues): the same in every view."""
    out = {}
    for k, sid in enumerate(session_ids):
        r, g, b = colorsys.hsv_to_rgb((0.61803398875 * k) % 1.0, 0.75 if k % 2 else 0.95, 0.95 if k % 3 else 0.8)
        out[sid] = (int(r * 255), int(g * 255), int(b * 255))
    return out


@dataclass(frozen=True, eq=False)
class LandmarkMarks:
    """Landmark marks of aligned walks: the estimate (output frame, interpolated at the mark's
    time), the surveyed truth (site frame) and the SE(2) site-from-output fit between them
    (``graphslam.core.survey.evaluate.landmark_errors``: display and evaluation only)."""

    stats: ErrorStats
    site_from_output: NDArray[np.float64]  # (x, y, theta)
    estimate_xy: NDArray[np.float64]  # (M, 2) output frame
    truth_xy: NDArray[np.float64]  # (M, 2) site frame
    labels: tuple[str, ...]  # "<landmark id> (<session>)"
    ids: tuple[str, ...] = ()  # each mark's landmark id


def landmark_marks(tracks: Mapping[str, PoseTrack], survey: Survey | None) -> LandmarkMarks | None:
    """The marks of ``survey`` on the walks in ``tracks``; None with fewer than 2 (no fit)."""
    if survey is None or not any(s.landmarks for s in survey):
        return None
    stats, T, _ = landmark_errors(tracks, survey)
    if stats.n < 2:
        return None
    est, truth, labels, ids = [], [], [], []
    for s in survey:
        if s.session_id in tracks and s.landmarks:
            t = np.array([m.t_ns for m in s.landmarks], dtype=float)
            est.append(interpolate_xy(tracks[s.session_id], t))
            truth.append(np.array([[m.x, m.y] for m in s.landmarks]))
            labels += [f"{m.landmark_id} ({s.session_id})" for m in s.landmarks]
            ids += [m.landmark_id for m in s.landmarks]
    return LandmarkMarks(stats, np.asarray(T, float), np.concatenate(est), np.concatenate(truth), tuple(labels),
                         tuple(ids))


def top_access_points(fm: FingerprintMatrix, rows: NDArray[np.int64], k: int) -> list[int]:
    """Column indices of the ``k`` APs heard by most of ``rows``; ties: stronger mean RSSI first."""
    sub = fm.values[rows].tocsc()
    heard = np.diff(sub.indptr)
    mean = np.asarray(sub.sum(axis=0)).ravel() / np.maximum(heard, 1)
    order = np.lexsort((-mean, -heard))
    return [int(c) for c in order[:k] if heard[c] > 0]


def fitted_site_from_aligned(evaluation: Mapping | None) -> NDArray[np.float64] | None:
    """A report's ``evaluation.site_from_aligned`` when it is a fit (>= 2 landmark marks, or true
    poses in a simulation), else None: without ground truth the field is a placeholder."""
    ev = evaluation if isinstance(evaluation, Mapping) else {}
    fitted = (ev.get("landmarks") or {}).get("n", 0) >= 2 or (ev.get("steps") or {}).get("n", 0) > 0
    if not fitted or ev.get("site_from_aligned") is None:
        return None
    return np.asarray(ev["site_from_aligned"], float).reshape(3)


def site_to_frame(site_from_frame: NDArray, xy: NDArray) -> NDArray[np.float64]:
    """Site-frame points ``xy`` in the frame that ``site_from_frame`` (x, y, theta) places in the
    site frame: R(theta)^T (xy - t)."""
    T = np.asarray(site_from_frame, float)
    c, s = np.cos(T[2]), np.sin(T[2])
    return (np.asarray(xy, float).reshape(-1, 2) - T[:2]) @ np.array([[c, -s], [s, c]])


def survey_folder_tracks(out_dir: str | Path) -> dict[str, PoseTrack]:
    """The aligned walks of a finished ``graphslam survey --out`` folder (its trajectories.csv);
    ``InputError`` when it is not one."""
    return survey_folder_trajectories(out_dir).tracks


def survey_folder_trajectories(out_dir: str | Path) -> TrajectoryFile:
    """trajectories.csv of a finished ``graphslam survey --out`` folder: the aligned walks and
    their components; ``InputError`` when it is not one."""
    from graphslam.io.csv_io import read_trajectory_file

    d = Path(out_dir)
    if not d.is_dir():
        raise InputError(d, "not a folder (expected a `graphslam survey --out` folder)")
    if not (d / "trajectories.csv").exists():
        raise InputError(d, "no trajectories.csv: not a finished survey output folder")
    traj = read_trajectory_file(d / "trajectories.csv")
    if not traj.tracks:
        raise InputError(d / "trajectories.csv", "no aligned walk in the file")
    return traj
