"""The survey job: read recordings, align, export. Side effects live here, maths in ``core``.

``run_survey`` reads like a table of contents; each step is one library call.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, Sequence

import numpy as np

from graphslam import names
from graphslam.app.derived import DERIVED_FILES, KEPT_FILES, rebuild_derived
from graphslam.app.survey_inputs import SurveyInputs
from graphslam.config import GraphSlamConfig
from graphslam.core.progress import Task
from graphslam.core.survey.align import Alignment, ProgressCallback, align
from graphslam.core.survey.evaluate import Evaluation, evaluate
from graphslam.core.types import Survey
from graphslam.errors import InputError, OutputError
from graphslam.io.atomic import FolderStage, atomic_write_json, atomic_write_text, check_replaceable_folder, clean_stale
from graphslam.io.csv_io import component_frame, write_trajectories
from graphslam.io.mcap_reader import read_recordings
from graphslam.io.recording_cache import CACHE_FILE, read_recording_cache, write_recording_cache
from graphslam.io.mcap_writer import write_aligned
from graphslam.io.survey_state import STATE_FILE, write_survey_state

log = logging.getLogger(__name__)

REPORT_VERSION = 1
# What a survey writes into --out (and survey.png after them); what other commands add there is
# declared in graphslam.app.derived (rebuilt or kept when the folder is replaced). --out may hold
# only these: it is replaced as a whole.
OUTPUT_FILES = {
    "trajectories": "trajectories.csv",
    "aligned": "aligned.mcap",
    "radio_map": "radio_map.parquet",
    "radio_map_surveyed": "radio_map_surveyed.parquet",
    "magnetic_map": "magnetic_map.parquet",  # when the main map's walks carry /phone/magnetic
    "wifi_edges": "wifi_edges.parquet",
    "state": STATE_FILE,  # what a later `survey --update` starts from
    "recordings_cache": CACHE_FILE,  # ... and the walks it need not parse again
    "config": "config.yaml",
    "report": "report.json",
}
# survey.png: written into --out after the set is in place (a picture that fails is a warning)
OWNED_FILES = {*OUTPUT_FILES.values(), "survey.png", *DERIVED_FILES, *KEPT_FILES}

# report.json's ``frame_description``: what the coordinates of component 0 mean
FRAME_DESCRIPTIONS = names.FRAME_DESCRIPTIONS


@dataclass(frozen=True, eq=False)
class SurveyResult:
    survey: Survey
    alignment: Alignment
    evaluation: Evaluation | None
    report: dict[str, Any]
    out_dir: Path | None
    files: dict[str, Path] = field(default_factory=dict)


def build_report(
    survey: Survey, al: Alignment, ev: Evaluation | None, cfg: GraphSlamConfig, timings: dict, *, floor: str = ""
) -> dict:
    fp = al.fingerprints
    main = main_alignment(al)
    n_main_rows = int(np.isfinite(main.fingerprint_xy()).all(axis=1).sum())
    n_main = len(main.tracks)
    report: dict[str, Any] = {
        "version": REPORT_VERSION,
        "floor": floor or floor_name((), survey),
        "sessions": len(survey),
        "aligned_sessions": len(al.tracks),
        "reference_session": al.reference,
        "unaligned": [{"session_id": k, "reason": v} for k, v in al.unaligned.items()],
        "frame": al.frame,
        "frame_description": FRAME_DESCRIPTIONS.get(al.frame, al.frame)
        + ("; every other component in a frame of its own (its placement relative to component 0 unknown)"
           if len(al.components) > 1 else ""),
        # the site frame's rotation from east/north the control points or the reference map gave (degrees)
        **({"site_from_earth_deg": round(math.degrees(al.site_from_earth), 2)} if al.site_from_earth is not None else {}),
        # the control points given (landmark id -> site x, y): survey.png draws them apart from landmarks
        **({"control_points": {k: [float(v[0]), float(v[1])] for k, v in al.control_points.items()}}
           if al.control_points else {}),
        "components": [
            {"index": c.index, "walks": list(c.walks), "n_walks": len(c.walks), "reason": c.reason, "links": links}
            for c, links in zip(al.components, al.links_by_component())
        ],
        "radio_map": {
            "component": 0,
            "walks": n_main,
            # the file's rows: the main map's fingerprints and, on a reference map, the reference's
            "fingerprints": n_main_rows + (len(al.reference_map) if al.reference_map is not None else 0),
            "walks_in_other_components": len(al.tracks) - n_main,
            **({"reference_fingerprints": len(al.reference_map)} if al.reference_map is not None else {}),
        },
        "nodes": al.n_nodes,
        "fingerprints": len(fp),
        "scans_dropped": fp.dropped,
        "scans_standstill": fp.standstill,
        "access_points": fp.fingerprints.n_aps,
        "edges": {
            "imu": int(sum(len(t) - 1 for t in al.tracks.values())),
            "wifi": len(al.edges),
            "wifi_candidates": al.edges.candidates,
            "wifi_states": al.edge_states,
        },
        "optimizer": {
            "initialization": cfg.optimizer.initialization,
            "iterations": len(al.iterations),
            "stages": len({r.stage for r in al.iterations}),
            "initial_error": al.initial_error,
            "final_error": al.final_error,
            "converged": al.converged,
            # edges of the tied component that joined once a solve brought them within the gate
            "regated_edges": {"wifi": al.regated_edges[0], "reference": al.regated_edges[1]},
            **al.solver,
        },
        "timings_s": {k: round(v, 4) for k, v in timings.items()},
    }
    if al.magnetic is not None:
        report["magnetic"] = magnetic_report(survey, al, cfg)
    if al.reference_map is not None:
        report["reference_map"] = reference_report(al)
    elif al.unused_reference is not None:
        report["reference_map"] = {
            "source": al.unused_reference.metadata.get("source"), "fingerprints": len(al.unused_reference),
            "spacing_m": _spacing(al.unused_reference), "walks_placed_on_it": 0, "used": False,
            "reason": "no walk registers onto it unambiguously: the survey is in a frame of its own",
        }
    if al.placement is not None:
        report.update(_placement_report(al))
    if ev is not None:
        from graphslam.core.survey.evaluate import component_errors

        # the figures above are component 0's; "components": each component after its own SE(2)
        # fit, and component 0 in the site frame with no fit (site_mean_m) when it is in it
        report["evaluation"] = {
            **ev.as_dict(), "component": 0,
            "components": [c.as_dict() for c in component_errors(al, survey, site_frame=al.frame == "site")],
        }
    if al.uwb is not None:  # UWB ranges; in the site frame the error needs no fit
        report["uwb"] = al.uwb.as_dict()
        if ev is not None and al.frame == "site":
            from graphslam.core.survey.evaluate import trajectory_errors

            report["evaluation"]["steps_site_frame"] = trajectory_errors(al.main_tracks(), survey, np.zeros(3)).as_dict()
    return report


def magnetic_report(survey: Survey, al: Alignment, cfg: GraphSlamConfig) -> dict[str, Any]:
    """report.json's ``magnetic``: the walks with the field, the window-match threshold the surrogates
    gave, the links kept, and how far apart the solution leaves the magnetic pairs (no ground truth)."""
    links = al.magnetic
    assert links is not None
    pairs = al.magnetic_pairs if al.magnetic_pairs is not None else np.zeros((0, 2), np.int64)
    d = np.linalg.norm(al.node_xyh[pairs[:, 0], :2] - al.node_xyh[pairs[:, 1], :2], axis=1)
    d = d[np.isfinite(d)]
    return {
        "walks_with_field": int(sum(s.magnetic is not None and len(s.magnetic) > 0 for s in survey)),
        "threshold": round(float(links.threshold), 4),
        "window_matches": int(links.matches),
        "links": len(links),
        "pairs": int(len(pairs)),
        "pair_distance_m": None if not len(d) else {
            "median": round(float(np.median(d)), 3), "p90": round(float(np.percentile(d, 90)), 3),
            "saturated": int((d > cfg.magnetic.d_max_m).sum()),
        },
    }


def reference_report(al: Alignment) -> dict[str, Any]:
    """report.json's ``reference_map``: the surveyed map the main map is placed on, and how the crowd joined
    it: the walks placed on it, its WiFi edges in the optimiser and how far apart the solution leaves them."""
    ref = al.reference_map
    assert ref is not None
    pairs = al.anchor_pairs if al.anchor_pairs is not None else np.zeros((0, 2), np.int64)
    d = np.linalg.norm(al.node_xyh[pairs[:, 0], :2] - np.asarray(ref.xy)[pairs[:, 1]], axis=1)
    return {
        "source": ref.metadata.get("source"),
        "fingerprints": len(ref),
        "spacing_m": _spacing(ref),
        # its readings minus the crowd's at one place (dB), taken off for its WiFi edges
        "rss_offset_db": ref.metadata.get("rss_offset_db"),
        "used": True,
        "walks_placed_on_it": len(al.components[0].walks) if al.components else 0,
        "edges": int(len(pairs)),
        "edge_distance_m": None if not len(d) else {
            "median": round(float(np.median(d)), 3), "p90": round(float(np.percentile(d, 90)), 3),
        },
        "field": _field_report(al),
    }


def _field_report(al: Alignment) -> dict[str, Any] | None:
    """report.json's ``reference_map.field``: the reference's magnetic field (a previous survey's magnetic map)
    and the crowd's magnetic factors to it; None when the reference has none or the field is off."""
    ties = al.field_ties
    if ties is None:
        return None
    d = np.linalg.norm(al.node_xyh[ties.pairs[:, 0], :2] - ties.xy[ties.pairs[:, 1]], axis=1)
    return {
        "walks": int(ties.reference_walks),
        "links": int(ties.links),
        "crowd_walks": len(ties.walks),
        "factors": len(ties),
        "threshold": round(float(ties.threshold), 3),  # the score a window match needed (from surrogates)
        "factor_distance_m": None if not len(d) else {
            "median": round(float(np.median(d)), 3), "p90": round(float(np.percentile(d, 90)), 3),
        },
    }


def _spacing(ref: Any) -> float | None:
    """report.json's ``reference_map.spacing_m``: how far apart the places it measured are (median, m)."""
    from graphslam.core.survey.reference import place_spacing

    s = place_spacing(np.asarray(ref.xy))
    return None if s is None else round(s, 2)


def main_alignment(al: Alignment) -> Alignment:
    """``al`` restricted to component 0, the main map: the other components' walks leave ``tracks``
    and their step nodes become NaN (as unaligned walks' are), so that the radio map and the WiFi
    edges built from it hold component 0 only. ``al`` itself when it has one component."""
    comps = al.components
    if len(comps) <= 1:
        return al
    main = set(comps[0].walks)
    offsets = al.fingerprints.offsets
    xyh = al.node_xyh.copy()
    for s, sid in enumerate(al.session_ids):
        if sid in al.tracks and sid not in main:
            xyh[int(offsets[s]):int(offsets[s + 1])] = np.nan
    return dataclasses.replace(al, tracks=al.main_tracks(), node_xyh=xyh, component_list=(comps[0],))


def floor_name(paths: Sequence[str | Path], survey: Survey) -> str:
    """The floor a survey is of, for messages: the input folder's name (the folder of the files),
    with the sessions' ``site/floor`` metadata when they all share one."""
    folders = {(Path(p) if Path(p).is_dir() else Path(p).parent).resolve() for p in paths}
    folder = next(iter(folders)).name if len(folders) == 1 else ""
    meta = {(s.site, s.floor) for s in survey}
    site, fl = next(iter(meta)) if len(meta) == 1 else ("", "")
    tag = f"{site}/{fl}" if site and fl else ""
    if not folder:
        return tag or "survey"
    if not tag or folder == fl:
        return tag or folder
    return f"{folder} ({tag})"


def main_map_warning(report: Mapping[str, Any]) -> str | None:
    """The warning of a survey whose main map (component 0) holds under half of the walks read
    (unaligned walks counted), else None. ``graphslam survey`` logs it; ``survey-batch`` marks
    the floor ``partial`` by it."""
    n = int(report.get("sessions") or 0)
    comps = report.get("components") or []
    n_main = int(comps[0]["n_walks"]) if comps else 0
    if not n or 2 * n_main >= n:
        return None
    others = comps[1:]
    n_other = sum(int(c["n_walks"]) for c in others)
    n_unaligned = len(report.get("unaligned") or [])
    parts = []
    if others:
        parts.append(f"{n_other} in {len(others)} other component{'s' if len(others) != 1 else ''}")
    if n_unaligned or not others:
        parts.append(f"{n_unaligned} unaligned")
    return (f"{report.get('floor') or 'survey'}: the main map holds {n_main} of {n} walks; "
            f"{n - n_main} are not in it: {', '.join(parts)} (report.json: components, unaligned)")


def _placement_report(al: Alignment) -> dict[str, Any]:
    """report.json's ``registration`` block and per-walk rows (how each walk was placed)."""
    ids = al.session_ids
    pl = al.placement
    assert pl is not None
    c = pl.loop_consistency
    out: dict[str, Any] = {
        "registration": {
            "method": pl.method,
            "placed": int(pl.placed.sum()),
            "loops": pl.loops,
            "loops_consistent": pl.loops_consistent,
            "loop_consistency": None if c is None else round(c, 3),
            "reliable": pl.reliable,
        }
    }

    def num(a: Any, s: int) -> float | None:
        return None if a is None or not np.isfinite(a[s]) else round(float(a[s]), 4)

    walks = []
    component = al.component_of()
    for s in range(len(ids)):
        row: dict[str, Any] = {"session_id": ids[s], "aligned": ids[s] in al.tracks, "component": component.get(ids[s])}
        if pl.method in ("growth", "heading", "reference", "control_points"):
            # support: vote weight per fingerprint; margin: over the runner-up placement (seed: null);
            # consistency: share of the walk's match weight whose partners end within placement.consistent_m
            row.update(support=num(pl.support, s), margin=num(pl.margin, s), consistency=num(pl.consistency, s))
        else:
            row["registration_inliers"] = int(pl.inliers[s])
            row["registered_to"] = ids[int(pl.parent[s])] if pl.parent[s] >= 0 else None
        walks.append(row)
    out["walks"] = walks
    return out


def run_survey(
    inputs: SurveyInputs,
    config: GraphSlamConfig | None = None,
    *legacy_args: Any,
    progress: ProgressCallback | None = None,
    **legacy_options: Any,
) -> SurveyResult:
    """Read ``inputs`` (``SurveyInputs``: the recordings, control points, floor plan, previous
    output ...), align every walk with ``config``, write the outputs into ``inputs.out`` (None: no
    files) and survey.png there when ``inputs.picture``.

    The earlier form ``run_survey(paths, out_dir, config, rerun_path=, floor_plan=, floor_size=,
    surveyed=, picture=, update=, control_points=)`` still runs, with a ``DeprecationWarning``."""
    if not isinstance(inputs, SurveyInputs):
        inputs, config = _legacy_inputs(inputs, config, legacy_args, legacy_options)
    elif legacy_args or legacy_options:
        raise TypeError(f"run_survey(inputs, config, *, progress): unexpected arguments "
                        f"{list(legacy_args) + sorted(legacy_options)!r} (they are fields of SurveyInputs)")
    cfg = config or GraphSlamConfig()
    with _openblas_threads(cfg.optimizer.blas_threads):
        return _run_survey(inputs, cfg, progress)


_LEGACY_OPTIONS = {"rerun_path": "rerun", "floor_plan": "floor_plan", "floor_size": "floor_size", "surveyed": "surveyed",
                   "picture": "picture", "update": "previous", "control_points": "control_points"}


def _legacy_inputs(
    paths: Any, second: Any, args: tuple[Any, ...], options: dict[str, Any]
) -> tuple[SurveyInputs, GraphSlamConfig | None]:
    """(inputs, config) of a call in the earlier form ``run_survey(paths, out_dir, config, **options)``
    (``second``: what came as ``config``, the output folder unless it was named ``out_dir=``)."""
    warnings.warn("run_survey(paths, out_dir, config, **options) is deprecated: pass "
                  "run_survey(SurveyInputs(paths, out_dir, ...), config)", DeprecationWarning, stacklevel=3)
    named = isinstance(second, GraphSlamConfig) or "out_dir" in options  # run_survey(paths, [out_dir=...,] config=...)
    if len(args) > (0 if named else 1):
        raise TypeError("run_survey(paths, out_dir, config): too many positional arguments")
    out_dir, config = (options.pop("out_dir", None), second) if named else (second, args[0] if args else None)
    unknown = sorted(set(options) - set(_LEGACY_OPTIONS))
    if unknown:
        raise TypeError(f"run_survey: unexpected keyword arguments {unknown!r}")
    return SurveyInputs(paths, out_dir, **{_LEGACY_OPTIONS[k]: v for k, v in options.items()}), config


@contextlib.contextmanager
def _openblas_threads(n: int) -> Iterator[None]:
    """Within: OpenBLAS (numpy's and scipy's, whatever their build's prefix) at ``n`` threads;
    ``n`` = 0 leaves it."""
    if n <= 0:
        yield
        return
    from threadpoolctl import ThreadpoolController

    with ThreadpoolController().select(internal_api="openblas").limit(limits=n):
        yield


def _run_survey(inputs: SurveyInputs, cfg: GraphSlamConfig, progress: ProgressCallback | None) -> SurveyResult:
    out_dir, update = inputs.out, inputs.previous
    for folder in {Path(f).absolute() for f in (out_dir, update) if f is not None}:
        # what runs into these folders that were killed left (only theirs): a previous set is put
        # back before --update reads it
        clean_stale(folder)
    _check_outputs(inputs)
    plan = _picture_plan(inputs.floor_plan, inputs.floor_size) if inputs.picture and out_dir is not None else None
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    cp_source, cp = _read_control_points(inputs.control_points)  # a bad file fails before the work
    reference = reference_field = None
    if inputs.reference_map is not None:  # a bad file fails before the work
        from graphslam.io.reference_map import read_reference_field, read_reference_map

        reference = read_reference_map(inputs.reference_map, min_rssi_dbm=cfg.fingerprint.min_rssi_dbm,
                                       missing_dbm=cfg.fingerprint.missing_rssi_dbm)
        reference_field = read_reference_field(inputs.reference_map, reference)
    previous = None
    if update is not None:  # read first: a bad previous output fails before the work
        from graphslam.app.update import align_update, load_previous

        previous = load_previous(update)
    cache = None
    if update is not None:  # the walks read last time, by their files' contents: not parsed again
        cache = read_recording_cache(Path(update) / CACHE_FILE)
    recordings = read_recordings(inputs.recordings, cache)
    survey = recordings.survey
    if cp is not None:
        check_control_points_marked(cp, survey, cp_source)
    timings["read"] = time.perf_counter() - t0

    update_info = None
    if previous is not None:
        alignment, cfg, update_info = align_update(survey, cfg, previous, previous_dir=update, progress=progress,
                                                   control_points=cp, reference=reference,
                                                   reference_field=reference_field)
    else:
        alignment = align(survey, cfg, progress=progress, control_points=cp, reference=reference,
                          reference_field=reference_field)
    timings.update({f"align.{k}": v for k, v in alignment.timings_s.items()})

    t = time.perf_counter()
    # component 0 only: one site fit over walks in unrelated frames would measure nothing
    with Task("evaluate"):
        evaluation = evaluate(alignment.main_tracks(), survey) if survey.has_ground_truth else None
    timings["evaluate"] = time.perf_counter() - t

    viz = None
    if inputs.rerun is not None:
        from graphslam.viz.background import start_log_survey

        # forked now: imports rerun and logs on the other core while the outputs are written
        viz = start_log_survey(inputs.rerun, survey, alignment, cfg, floor_plan=inputs.floor_plan,
                               floor_size=inputs.floor_size)
    files: dict[str, Path] = {}
    report = build_report(survey, alignment, evaluation, cfg, timings, floor=floor_name(inputs.recordings, survey))
    if update_info is not None:
        report["update"] = {**update_info, "walks_from_cache": recordings.cached}

    def picture(folder: Path) -> None:
        """survey.png into the stage (drawn while the radio map is calibrated: a forked child, or a thread)."""
        if inputs.picture:
            _write_picture(folder, survey, alignment, cfg, evaluation, plan, files, timings)
            if "picture" in files:
                files["picture"] = Path(out_dir) / files["picture"].name  # where it is once published

    def finish() -> None:
        """The last of the run, before its set is published: the Rerun child waited for,
        report.json's timings (written last, with the set)."""
        if viz is not None:
            t_wait = time.perf_counter()
            timings["rerun"] = viz.wait()  # log_survey itself, in the child
            timings["rerun_wait"] = time.perf_counter() - t_wait  # what the parent still waited for it
        timings["total"] = time.perf_counter() - t0
        report["timings_s"] = {k: round(v, 4) for k, v in timings.items()}

    if out_dir is not None:
        t = time.perf_counter()

        def before_publish(stage: Path) -> None:
            # the writing's own time: the picture, drawn meanwhile, has its own figure
            timings["write"] = time.perf_counter() - t - timings.get("picture", 0.0)
            finish()

        try:
            with Task("write"):
                files |= write_outputs(Path(out_dir), survey, alignment, report, cfg, surveyed=inputs.surveyed,
                                       before_publish=before_publish, recording_keys=recordings.keys, beside=picture)
        except BaseException:
            if viz is not None:  # let the child finish (and clean up its temp file) before failing
                with contextlib.suppress(Exception):
                    viz.wait()
            raise
    else:
        finish()
    warning = main_map_warning(report)
    if warning is not None:
        log.warning("%s", warning)
    return SurveyResult(survey, alignment, evaluation, report, Path(out_dir) if out_dir else None, files)


def _read_control_points(
    source: str | Path | Mapping[str, tuple[float, float]] | None,
) -> tuple[str, dict[str, tuple[float, float]] | None]:
    """(what to name in a message, landmark id -> site (x, y)) of ``run_survey``'s ``control_points``."""
    if source is None:
        return "", None
    if isinstance(source, (str, Path)):
        from graphslam.io.control_points import read_control_points

        return str(source), read_control_points(source)
    return "control points", {str(k): (float(v[0]), float(v[1])) for k, v in source.items()}


def check_control_points_marked(cp: Mapping[str, Any], survey: Survey, source: str | Path = "control points") -> None:
    """An ``InputError`` when no walk of ``survey`` marks any of the control points' ids on
    /landmarks (a file of another floor, or ids spelt otherwise than the walks mark them)."""
    marked = {m.landmark_id for s in survey for m in s.landmarks}
    if marked & set(cp):
        return
    ids = list(cp)
    seen = sorted(marked)
    raise InputError(
        source,
        f"none of the {len(ids)} ids ({', '.join(map(repr, ids[:3]))}{', ...' if len(ids) > 3 else ''}) is marked "
        "by any walk's /landmarks" + (f" (the walks mark e.g. {', '.join(map(repr, seen[:3]))})" if seen
                                      else " (no walk has /landmarks)"),
        field="landmark_id",
    )


def _picture_plan(floor_plan: str | Path | None, floor_size: tuple[float, float] | None) -> Any:
    """The floor plan survey.png is drawn over; a bad one fails here, before the work."""
    from graphslam.viz.common import load_floor_plan

    return load_floor_plan(floor_plan, floor_size)


def _write_picture(
    out_dir: Path, survey: Survey, al: Alignment, cfg: GraphSlamConfig, ev: Evaluation | None, plan: Any,
    files: dict[str, Path], timings: dict[str, float],
) -> None:
    """survey.png in ``out_dir`` (the stage folder: it is published with the set); a picture that
    fails is a warning, not a failed survey (``graphslam.viz.survey_picture``: Pillow, a small share of the survey)."""
    from graphslam.errors import GraphSlamError
    from graphslam.viz.survey_picture import PICTURE, draw_survey, scene_of_alignment

    t = time.perf_counter()
    try:
        with Task("picture"):
            files["picture"] = draw_survey(scene_of_alignment(survey, al, cfg, ev), out_dir / PICTURE, floor_plan=plan)
    except (GraphSlamError, OSError, ValueError) as e:
        log.warning("%s not written: %s", PICTURE, e)
    timings["picture"] = time.perf_counter() - t


def _check_outputs(inputs: SurveyInputs) -> None:
    """Fail before the work, not after it: an --out that cannot be replaced as one set (see
    ``write_outputs``), or that is (inside) an input folder, a --rerun file inside --out, a
    missing floor plan."""
    paths, out_dir, rerun_path, floor_plan = inputs.recordings, inputs.out, inputs.rerun, inputs.floor_plan
    if out_dir is not None:
        out = Path(out_dir).resolve()
        for p in map(Path, paths):
            folder = p.resolve() if p.is_dir() else p.resolve().parent
            # aligned.mcap in a folder of recordings would join the next survey of that folder
            if out == folder or (p.is_dir() and folder in out.parents):
                raise OutputError(f"{out_dir}: is {'inside ' if out != folder else ''}the input folder {folder}")
            if out in p.resolve().parents:
                raise OutputError(f"{out_dir}: holds the input {p}, and is replaced as a whole")
        check_replaceable_folder(out, OWNED_FILES)
        if rerun_path is not None and out in Path(rerun_path).resolve().parents:
            raise OutputError(f"{rerun_path}: inside --out {out_dir}, which is replaced as a whole: put it beside")
    if rerun_path is not None and Path(rerun_path).is_dir():
        raise OutputError(f"{rerun_path}: is a folder, expected an .rrd file path")
    if floor_plan is not None and not Path(floor_plan).is_file():
        raise InputError(floor_plan, "floor plan image not found")


def write_outputs(
    out_dir: Path, survey: Survey, al: Alignment, report: dict, cfg: GraphSlamConfig, *, surveyed: bool = False,
    before_publish: Callable[[Path], None] | None = None, recording_keys: Mapping[str, str] | None = None,
    beside: Callable[[Path], None] | None = None,
) -> dict[str, Path]:
    """Write every output into a staging folder beside ``out_dir``, then swap it in as a whole
    (``FolderStage``): ``out_dir`` holds this run's files (no ``radio_map_surveyed.parquet`` left
    from an earlier run) and the other commands' files it held, rebuilt for the new map
    (``graphslam.app.derived``, listed in report.json's ``derived_files``), or, if anything fails or
    the process is killed, exactly what it held before. ``beside(stage folder)`` runs on this thread
    once the other data files are written, while the radio map is still being built (a file of its
    own into the stage: the picture); ``before_publish(stage folder)`` runs after the data files and
    before report.json (which it may still change) is written, the last file.
    ``recording_keys`` (session id -> file key, ``read_recordings``): the recordings cache is written
    for them, else none."""
    stage = FolderStage.create(out_dir, OWNED_FILES)
    try:
        names = {k: v for k, v in OUTPUT_FILES.items()
                 if (k != "radio_map_surveyed" or surveyed) and (k != "recordings_cache" or recording_keys is not None)}
        from graphslam.core.radiomap.uncertainty import calibrate_uncertainty, with_calibration
        from graphslam.core.survey.radio_maps import crowdsourced_radio_map
        from graphslam.io.forked import ForkedCall, ForkedCallError
        from graphslam.io.radiomap_io import write_radio_map

        main = main_alignment(al)  # the radio map and its edges: component 0 only
        radio_map = crowdsourced_radio_map(survey, main, cfg, calibrate=False)
        # the radio map's self-calibration, most of a large survey's writing, runs beside the other files and
        # the picture, on the other core (a forked child; a thread where there is none); an error in either
        # stops it, then discards the stage
        with ForkedCall(calibrate_uncertainty, radio_map, fallback="thread") as calibration:
            component = al.component_of()
            write_trajectories(al.tracks, stage.path / names["trajectories"], component, al.frame)
            write_aligned(al.tracks, stage.path / names["aligned"], frame_id=al.frame,
                          frame_ids={sid: component_frame_id(al, k) for sid, k in component.items()})
            _write_wifi_edges(main, cfg, stage.path / names["wifi_edges"])
            if not _write_magnetic_map(survey, al, cfg, stage.path / names["magnetic_map"]):
                names.pop("magnetic_map")
            if surveyed:  # evaluation: the same fingerprints at their ground-truth positions
                from graphslam.core.survey.radio_maps import surveyed_radio_map

                write_radio_map(surveyed_radio_map(_without_other_components(survey, al), al, cfg),
                                stage.path / names["radio_map_surveyed"])
            atomic_write_text(stage.path / names["config"], cfg.to_yaml())
            write_survey_state(stage.path / names["state"], survey, al, cfg)
            if recording_keys is not None:
                write_recording_cache(stage.path / names["recordings_cache"], survey, recording_keys)
            if beside is not None:
                beside(stage.path)
            try:
                uncertainty = calibration.result()
            except ForkedCallError as e:  # the child failed (a fork's hazard): measured here instead
                log.warning("radio map calibration: the child process failed (%s); calibrating here", e)
                uncertainty = calibrate_uncertainty(radio_map)
            write_radio_map(with_calibration(radio_map, uncertainty), stage.path / names["radio_map"])
        if before_publish is not None:
            before_publish(stage.path)
        atomic_write_json(stage.path / names["report"], report)
        report["derived_files"] = rebuild_derived(out_dir, stage.path)  # from the complete new set
        atomic_write_json(stage.path / names["report"], report)
    except BaseException as e:
        stage.discard()
        if isinstance(e, OSError):  # e.g. disk full in the middle of a file
            raise OutputError(f"{out_dir}: cannot write the outputs ({e.strerror or e})") from None
        if isinstance(e, OutputError) and hasattr(e, "reason"):  # a file of the stage: name --out
            raise OutputError(f"{out_dir}: cannot write the outputs ({e.reason})") from None
        raise
    stage.publish()
    return {key: out_dir / name for key, name in names.items()}


def component_frame_id(al: Alignment, index: int) -> str:
    """aligned.mcap's ``frame_id`` of a walk in component ``index``: the frame's name for the
    main map ("aligned", "earth", "site"), ``component_<index>`` for the others (a frame each)."""
    return component_frame(al.frame, index)


def _without_other_components(survey: Survey, al: Alignment) -> Survey:
    """``survey`` with no ground truth on the walks of components >= 1 (the surveyed map leaves
    them out, as the crowdsourced one does)."""
    comps = al.components
    other = {sid for c in comps[1:] for sid in c.walks}
    if not other:
        return survey
    return Survey(tuple(dataclasses.replace(s, ground_truth=None) if s.session_id in other else s for s in survey))


def _write_wifi_edges(al: Alignment, cfg: GraphSlamConfig, path: Path) -> None:
    from graphslam.core.survey.radio_maps import crowdsourced_edges
    from graphslam.io.edges_io import write_wifi_edges

    write_wifi_edges(crowdsourced_edges(al, cfg), path)


def _write_magnetic_map(survey: Survey, al: Alignment, cfg: GraphSlamConfig, path: Path) -> bool:
    """magnetic_map.parquet of the main map; False (no file) when none of its walks carries the field."""
    from graphslam.core.survey.radio_maps import crowdsourced_magnetic_map
    from graphslam.io.magnetic_map_io import write_magnetic_map

    mm = crowdsourced_magnetic_map(survey, al, cfg)
    if mm is None:
        return False
    write_magnetic_map(mm, path)
    return True


