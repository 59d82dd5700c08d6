"""The pictures behind commands, where files are read: ``graphslam plot OUT`` (survey.png and
radio_map.png of a finished survey folder) and the pictures ``track`` and ``locate`` write
beside their CSV. Drawing is ``graphslam.viz``'s; this module finds the inputs and the frames.

Frames: estimates stay in the radio map's frame. Truth (site frame) is moved into it with the
site-from-map transform: ``--site-from-map`` when given, identity for a map in the site
frame, else the landmark fit in the ``report.json`` beside the map (display and evaluation
only, like everywhere else); without any of them the truth is not drawn, and the picture
says so.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from graphslam.app.locate import LocateRun
from graphslam.app.track import TrackRun
from graphslam.core.progress import Task
from graphslam.core.summary import plural
from graphslam.core.common.geometry import interpolate_xy
from graphslam.core.tracking.apmodel import ApModels
from graphslam.core.types import Survey
from graphslam.errors import InputError
from graphslam.viz.common import fitted_site_from_aligned, site_to_frame

SURVEY_PNG = "survey.png"
RADIO_MAP_PNG = "radio_map.png"


def plot_survey_folder(
    out_dir: str | Path,
    *,
    floor_plan: str | Path | None = None,
    floor_size: tuple[float, float] | None = None,
    recordings: Sequence[str | Path] = (),
    aps: Sequence[str] = (),
    top_aps: int = 5,
    radio_map: bool = True,
) -> dict[str, Path]:
    """(Re)draw OUT/survey.png and, when OUT has radio_map.parquet, OUT/radio_map.png (with the
    fitted APs of OUT/ap_models.json when ``fit-aps`` has run). Returns the files written."""
    from graphslam.viz.common import load_floor_plan
    from graphslam.viz.survey_picture import draw_survey, scene_of_folder

    d = Path(out_dir)
    plan = load_floor_plan(floor_plan, floor_size)  # bad input fails before anything is drawn
    rm_path = d / "radio_map.parquet"
    rm = None
    if radio_map and rm_path.exists():
        from graphslam.io.radiomap_io import read_radio_map
        from graphslam.viz.radiomap_picture import ap_columns, draw_radio_map

        rm = read_radio_map(rm_path)
        ap_columns(rm, aps, top_aps)
    elif aps:
        raise InputError(rm_path, "no radio map to draw --ap from")
    with Task("plot", total=1 + (rm is not None), unit="pictures") as task:
        scene = scene_of_folder(d, recordings)
        files = {"survey": draw_survey(scene, d / SURVEY_PNG, floor_plan=plan)}
        task.advance()
        if rm is not None:
            T = np.zeros(3) if rm.frame == "site" else scene.site_from_output
            files["radio_map"] = draw_radio_map(
                rm, d / RADIO_MAP_PNG, aps=aps, top=top_aps, ap_models=_ap_models_beside(rm_path), floor_plan=plan,
                site_from_map=T,
            )
            task.advance()
    return files


def write_track_picture(
    run: TrackRun, radio_map_path: str | Path, session_paths: Sequence[str | Path], path: str | Path, label: str = ""
) -> Path:
    """The tracked walks (and the truth when the sessions carry it) on the radio map, as PNG ``path``."""
    from graphslam.io.mcap_reader import read_survey
    from graphslam.io.radiomap_io import read_radio_map
    from graphslam.viz.track_picture import draw_tracks

    with Task("picture"):
        rm = read_radio_map(radio_map_path)
        survey = read_survey(list(session_paths))
        T, why = site_from_map(radio_map_path, rm.frame)
        estimates = {t.session_id: np.asarray(t.xy) for t in run.tracks}
        truth, at = {}, {}
        if T is not None:
            for s in survey:
                if s.ground_truth is not None and s.session_id in estimates:
                    tr = next(t for t in run.tracks if t.session_id == s.session_id)
                    truth[s.session_id] = site_to_frame(T, s.ground_truth.xy)
                    at[s.session_id] = site_to_frame(T, interpolate_xy(s.ground_truth, tr.t_ns.astype(float)))
        steps = sum(len(t.t_ns) for t in run.tracks)
        title = f"track{' ' + label if label else ''}: {plural(len(run.tracks), 'session')}, {plural(steps, 'step')}"
        return draw_tracks(estimates, path, truth=truth or None, truth_at_estimates=at or None, map_xy=np.asarray(rm.xy),
                           title=title, frame=_frame_note(rm.frame, truth, why, survey))


def write_locate_picture(
    run: LocateRun, radio_map_path: str | Path, query_paths: Sequence[str | Path], path: str | Path,
    site_from_map_xyt: Sequence[float] | None = None,
) -> Path:
    """The kNN answers per session (and the truth at scan time when the queries carry it) as PNG ``path``."""
    from graphslam.io.mcap_reader import read_survey
    from graphslam.io.radiomap_io import read_radio_map
    from graphslam.viz.track_picture import draw_tracks

    with Task("picture"):
        rm = read_radio_map(radio_map_path)
        pos = run.positions
        T, why = site_from_map(radio_map_path, rm.frame, site_from_map_xyt)
        estimates, truth, at = {}, {}, {}
        survey = read_survey(list(query_paths))
        for s in survey:
            rows = np.flatnonzero(pos.session_ids == s.session_id)
            if not len(rows):
                continue
            estimates[s.session_id] = pos.result.xy[rows]
            if T is not None and s.ground_truth is not None:
                truth[s.session_id] = site_to_frame(T, s.ground_truth.xy)
                at[s.session_id] = site_to_frame(T, interpolate_xy(s.ground_truth, pos.t_ns[rows].astype(float)))
        title = f"locate (kNN): {run.n_located:,} of {plural(run.n_scans, 'scan')} located, {plural(run.n_sessions, 'session')}"
        return draw_tracks(estimates, path, truth=truth or None, truth_at_estimates=at or None, map_xy=np.asarray(rm.xy),
                           points=True, title=title, frame=_frame_note(rm.frame, truth, why, survey))


def site_from_map(
    radio_map_path: str | Path, frame: str, given: Sequence[float] | None = None
) -> tuple[NDArray[np.float64] | None, str]:
    """(site-from-map (x, y, theta) or None, where it came from / why there is none)."""
    if given is not None:
        return np.asarray(given, float).reshape(3), "--site-from-map"
    if frame == "site":
        return np.zeros(3), "the map is in the site frame"
    rep_path = Path(radio_map_path).with_name("report.json")
    try:
        report = json.loads(rep_path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None, f"no usable {rep_path.name} beside the radio map (its landmark fit places the truth)"
    T = fitted_site_from_aligned(report.get("evaluation") if isinstance(report, dict) else None)
    if T is None:
        return None, f"{rep_path.name} beside the radio map has no landmark fit"
    return T, f"the landmark fit in {rep_path}"


def _frame_note(frame: str, truth: dict, why: str, survey: Survey) -> str:
    has_truth = any(s.ground_truth is not None for s in survey)
    note = f"radio map's {frame} frame"
    if truth:
        return note + f"; truth placed by {why} (display only)"
    if has_truth:
        return note + f"; truth not drawn: {why}"
    return note + "; the recordings carry no ground truth"


def _ap_models_beside(rm_path: Path) -> ApModels | None:
    p = rm_path.with_name("ap_models.json")
    if not p.exists():
        return None
    from graphslam.io.apmodel_io import read_ap_models

    return read_ap_models(p)
