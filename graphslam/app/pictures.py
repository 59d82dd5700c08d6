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
from typing import TYPE_CHECKING, Sequence

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

if TYPE_CHECKING:
    from graphslam.core.radiomap.radiomap import RadioMap
    from graphslam.viz.common import FloorPlan

SURVEY_PNG = "survey.png"
RADIO_MAP_PNG = "radio_map.png"
MAGNETIC_MAP = "magnetic_map.parquet"


# radio_map.png's text chunk holding the options `plot` drew it with, so that `survey` redraws it
# the same way when it replaces the folder (graphslam.app.derived)
PLOT_OPTIONS_KEY = "graphslam-plot"


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
    fitted APs of OUT/ap_models.json when ``fit-aps`` has run). Returns the files written.
    radio_map.png records these options (``PLOT_OPTIONS_KEY``): a later survey into OUT redraws it."""
    from graphslam.viz.common import load_floor_plan
    from graphslam.viz.survey_picture import draw_survey, scene_of_folder

    d = Path(out_dir)
    plan = load_floor_plan(floor_plan, floor_size)  # bad input fails before anything is drawn
    rm_path = d / "radio_map.parquet"
    rm = None
    if radio_map and rm_path.exists():
        from graphslam.io.radiomap_io import read_radio_map
        from graphslam.viz.radiomap_picture import ap_columns

        rm = read_radio_map(rm_path)
        ap_columns(rm, aps, top_aps)
    elif aps:
        raise InputError(rm_path, "no radio map to draw --ap from")
    with Task("plot", total=1 + (rm is not None), unit="pictures") as task:
        scene = scene_of_folder(d, recordings)
        files = {"survey": draw_survey(scene, d / SURVEY_PNG, floor_plan=plan)}
        task.advance()
        if rm is not None:
            options = {
                "floor_plan": str(Path(floor_plan).resolve()) if floor_plan is not None else None,
                "floor_size": list(floor_size) if floor_size is not None else None,
                "recordings": [str(Path(r).resolve()) for r in recordings], "aps": list(aps), "top_aps": top_aps,
            }
            files["radio_map"] = _draw_radio_map(d, rm, plan, scene.site_from_output, options)
            task.advance()
            if (d / MAGNETIC_MAP).exists():
                files["magnetic_map"] = _draw_magnetic_map(d, plan, scene.site_from_output, options)
    return files


def _draw_magnetic_map(
    d: Path, plan: "FloorPlan | None", site_from_output: NDArray[np.float64] | None, options: dict
) -> Path:
    """OUT/magnetic_map.png from OUT/magnetic_map.parquet, recording ``options`` in it."""
    from graphslam.io.magnetic_map_io import read_magnetic_map
    from graphslam.viz.magnetic_picture import MAGNETIC_PNG, draw_magnetic_map

    mm = read_magnetic_map(d / MAGNETIC_MAP)
    T = np.zeros(3) if mm.frame == "site" else site_from_output
    return draw_magnetic_map(mm, d / MAGNETIC_PNG, floor_plan=plan, site_from_map=T,
                             text={PLOT_OPTIONS_KEY: json.dumps(options)})


def redraw_magnetic_map(folder: str | Path, options: dict) -> Path:
    """magnetic_map.png of ``folder`` drawn again with the options ``plot`` recorded in it (a floor plan
    that is gone is left out)."""
    from graphslam.viz.common import load_floor_plan
    from graphslam.viz.survey_picture import scene_of_folder

    d = Path(folder)
    plan_path = options.get("floor_plan")
    if plan_path is not None and not Path(plan_path).is_file():
        plan_path = None
    size = tuple(options["floor_size"]) if plan_path is not None and options.get("floor_size") else None
    plan = load_floor_plan(plan_path, size)
    recordings = [r for r in options.get("recordings") or [] if Path(r).exists()]
    return _draw_magnetic_map(d, plan, scene_of_folder(d, recordings).site_from_output, options)


def _draw_radio_map(
    d: Path, rm: "RadioMap", plan: "FloorPlan | None", site_from_output: NDArray[np.float64] | None, options: dict
) -> Path:
    """OUT/radio_map.png, recording ``options`` in it (``PLOT_OPTIONS_KEY``)."""
    from graphslam.viz.radiomap_picture import draw_radio_map

    T = np.zeros(3) if rm.frame == "site" else site_from_output
    return draw_radio_map(
        rm, d / RADIO_MAP_PNG, aps=options["aps"], top=options["top_aps"], ap_models=_ap_models_beside(d / "radio_map.parquet"),
        floor_plan=plan, site_from_map=T, text={PLOT_OPTIONS_KEY: json.dumps(options)},
    )


def plot_options(picture: str | Path) -> dict | None:
    """The options a radio_map.png was drawn with (``plot_survey_folder``), None when it does not say."""
    from PIL import Image

    try:
        with Image.open(picture) as im:
            text = getattr(im, "text", {}).get(PLOT_OPTIONS_KEY)
        options = json.loads(text) if text else None
    except (OSError, ValueError):
        return None
    return options if isinstance(options, dict) else None


def redraw_radio_map(folder: str | Path, options: dict) -> Path:
    """radio_map.png of ``folder`` (a survey set: radio_map.parquet, report.json, trajectories.csv,
    maybe ap_models.json) drawn with ``options`` (``plot_options``); a recorded floor plan or
    recording that is gone is left out (logged)."""
    import logging

    from graphslam.io.radiomap_io import read_radio_map
    from graphslam.viz.common import load_floor_plan
    from graphslam.viz.survey_picture import scene_of_folder

    log = logging.getLogger(__name__)
    d = Path(folder)
    options = {"floor_plan": None, "floor_size": None, "recordings": [], "aps": [], "top_aps": 5} | options
    plan_path = options["floor_plan"]
    if plan_path is not None and not Path(plan_path).is_file():
        log.warning("%s: the floor plan it was drawn over, %s, is gone: drawn without it", d / RADIO_MAP_PNG, plan_path)
        options |= {"floor_plan": None, "floor_size": None}
    recordings = [r for r in options["recordings"] if Path(r).exists()]
    size = tuple(options["floor_size"]) if options["floor_size"] else None
    plan = load_floor_plan(options["floor_plan"], size)
    rm = read_radio_map(d / "radio_map.parquet")
    from graphslam.viz.radiomap_picture import ap_columns

    aps = [a for a in options["aps"] if a in set(rm.bssids)]  # an AP the new map does not hear: left out
    ap_columns(rm, aps, int(options["top_aps"]))
    scene = scene_of_folder(d, recordings)
    return _draw_radio_map(d, rm, plan, scene.site_from_output, options | {"aps": aps, "recordings": recordings})


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
                           title=title, frame=_frame_note(rm.frame, truth, why, survey), frame_name=rm.frame)


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
                           points=True, title=title, frame=_frame_note(rm.frame, truth, why, survey), frame_name=rm.frame)


def site_from_map(
    radio_map_path: str | Path, frame: str, given: Sequence[float] | None = None
) -> tuple[NDArray[np.float64] | None, str]:
    """(site-from-map (x, y, theta) or None, where it came from / why there is none)."""
    if given is not None:
        return np.asarray(given, float).reshape(3), "--site-from-map"
    if frame == "site":
        return np.zeros(3), "identity: the map is in the site frame"
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
        if frame == "site":
            return note + "; truth as recorded (the same frame)"
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
