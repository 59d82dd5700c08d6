"""Error figures of ``track`` and ``locate`` answers, when their recordings carry ground truth
(``/ground_truth/pose``) or landmark marks (``/landmarks``): what the commands print.

The answers are in the radio map's frame, the truth in the site frame: the map is placed in the
site frame as the pictures place it (``app.pictures.site_from_map``: ``--site-from-map``, the
identity for a map in the site frame, else the landmark fit in the report.json beside the map);
without any of them nothing is scored and the figures say why. Evaluation only: nothing here
feeds the estimates.

- ``truth``: every answer against the true position at its time (interpolated);
- ``landmarks``: at every landmark mark, the answers interpolated at the mark's time against the
  landmark's surveyed position; a mark more than ``MARK_GAP_S`` from the nearest answer of its
  walk is left out (kNN answers come only at scans).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from graphslam.core.common.geometry import interpolate_xy, se2_apply
from graphslam.core.survey.evaluate import ErrorStats
from graphslam.core.types import PoseTrack, Survey

MARK_GAP_S = 5.0
FIGURES = ("n", "mean_m", "median_m", "p90_m", "max_m")


def figures(e: NDArray[np.float64]) -> dict[str, Any]:
    """n, mean, median, p90 and max of errors ``e`` (m, 3 decimals)."""
    st = ErrorStats.of(e).as_dict()
    return {k: st[k] if k == "n" else round(float(st[k]), 3) for k in FIGURES}


def answer_errors(
    answers: Mapping[str, tuple[NDArray[np.int64], NDArray[np.float64]]],
    survey: Survey,
    radio_map_path: str | Path,
    frame: str,
    site_from_map_xyt: Sequence[float] | None = None,
) -> dict[str, Any] | None:
    """The error figures of ``answers`` (session id -> (t_ns, (N, 2) xy in the map's frame)) against
    ``survey``'s ground truth and landmarks; None when the recordings carry neither."""
    from graphslam.app.pictures import site_from_map

    has_truth = any(s.ground_truth is not None for s in survey if s.session_id in answers)
    has_marks = any(s.landmarks for s in survey if s.session_id in answers)
    if not (has_truth or has_marks):
        return None
    T, why = site_from_map(radio_map_path, frame, site_from_map_xyt)
    if T is None:
        return {"evaluated": False, "frame": frame, "reason": why}
    return errors_in_site_frame(answers, survey, T, frame, why)


def errors_in_site_frame(
    answers: Mapping[str, tuple[NDArray[np.int64], NDArray[np.float64]]],
    survey: Survey,
    T: NDArray[np.float64],
    frame: str,
    why: str,
) -> dict[str, Any] | None:
    """``answer_errors`` with the answers (in ``frame``) placed in the truth's site frame by ``T``
    (x, y, theta; ``why``: what placed them); None when the recordings carry no truth and no marks."""
    has_truth = any(s.ground_truth is not None for s in survey if s.session_id in answers)
    has_marks = any(s.landmarks for s in survey if s.session_id in answers)
    if not (has_truth or has_marks):
        return None
    truth_e, mark_e = [], []
    for s in survey:
        if s.session_id not in answers:
            continue
        t, xy = answers[s.session_id]
        ok = np.isfinite(xy).all(axis=1)
        t, xy = np.asarray(t)[ok], se2_apply(T, np.asarray(xy)[ok])  # site frame
        if not len(t):
            continue
        if s.ground_truth is not None:
            truth_e.append(np.linalg.norm(xy - interpolate_xy(s.ground_truth, t.astype(float)), axis=1))
        if s.landmarks:
            tm = np.array([m.t_ns for m in s.landmarks], np.int64)
            near = np.abs(t[np.clip(np.searchsorted(t, tm), 0, len(t) - 1)] - tm)
            near = np.minimum(near, np.abs(t[np.clip(np.searchsorted(t, tm) - 1, 0, len(t) - 1)] - tm))
            use = near <= MARK_GAP_S * 1e9
            est = interpolate_xy(PoseTrack(t, xy, np.zeros(len(t))), tm[use].astype(float))
            true = np.array([[m.x, m.y] for m in s.landmarks])[use]
            mark_e.append(np.linalg.norm(est - true, axis=1))
    # the errors are distances in the truth's site frame; the answers are in the map's ``frame``,
    # placed there by ``site_from_map`` (what placed them is said: the frame keeps its one name)
    out: dict[str, Any] = {"evaluated": True, "frame": frame, "site_from_map": why}
    if has_truth:
        out["truth"] = figures(np.concatenate(truth_e) if truth_e else np.zeros(0))
    if has_marks:
        out["landmarks"] = figures(np.concatenate(mark_e) if mark_e else np.zeros(0))
    return out
