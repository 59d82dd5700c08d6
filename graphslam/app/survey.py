"""The survey job: read recordings, align, export. Side effects live here, maths in ``core``.

``run_survey`` reads like a table of contents; each step is one library call.
"""

from __future__ import annotations

import contextlib
import logging
import shutil
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from graphslam.config import GraphSlamConfig
from graphslam.core.survey.align import Alignment, ProgressCallback, align
from graphslam.core.survey.evaluate import Evaluation, evaluate
from graphslam.core.types import Survey
from graphslam.errors import InputError, OutputError
from graphslam.io.atomic import atomic_write_json, atomic_write_text
from graphslam.io.csv_io import write_trajectories
from graphslam.io.mcap_reader import read_survey
from graphslam.io.mcap_writer import write_aligned

log = logging.getLogger(__name__)

REPORT_VERSION = 1


@dataclass(frozen=True, eq=False)
class SurveyResult:
    survey: Survey
    alignment: Alignment
    evaluation: Evaluation | None
    report: dict[str, Any]
    out_dir: Path | None
    files: dict[str, Path] = field(default_factory=dict)


def build_report(survey: Survey, al: Alignment, ev: Evaluation | None, cfg: GraphSlamConfig, timings: dict) -> dict:
    fp = al.fingerprints
    report: dict[str, Any] = {
        "version": REPORT_VERSION,
        "sessions": len(survey),
        "aligned_sessions": len(al.tracks),
        "reference_session": al.reference,
        "unaligned": [{"session_id": k, "reason": v} for k, v in al.unaligned.items()],
        "nodes": al.n_nodes,
        "fingerprints": len(fp),
        "scans_dropped": fp.dropped,
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
        },
        "timings_s": {k: round(v, 4) for k, v in timings.items()},
    }
    if al.placement is not None:
        ids = al.session_ids
        pl = al.placement
        c = pl.loop_consistency
        report["registration"] = {
            "placed": int(pl.placed.sum()),
            "loops": pl.loops,
            "loops_consistent": pl.loops_consistent,
            "loop_consistency": None if c is None else round(c, 3),
            "reliable": pl.reliable,
        }
        report["walks"] = [
            {
                "session_id": ids[s],
                "aligned": ids[s] in al.tracks,
                "registration_inliers": int(al.placement.inliers[s]),
                "registered_to": ids[int(al.placement.parent[s])] if al.placement.parent[s] >= 0 else None,
            }
            for s in range(len(ids))
        ]
    if ev is not None:
        report["evaluation"] = ev.as_dict()
    if al.uwb is not None:  # UWB ranges (issue 15); in the site frame the error needs no fit
        report["uwb"] = al.uwb.as_dict()
        if ev is not None and al.frame == "site":
            from graphslam.core.survey.evaluate import trajectory_errors

            report["evaluation"]["steps_site_frame"] = trajectory_errors(al.tracks, survey, np.zeros(3)).as_dict()
    return report


def run_survey(
    paths: Sequence[str | Path],
    out_dir: str | Path | None,
    config: GraphSlamConfig | None = None,
    *,
    progress: ProgressCallback | None = None,
    rerun_path: str | Path | None = None,
    floor_plan: str | Path | None = None,
    floor_size: tuple[float, float] | None = None,
    surveyed: bool = False,
) -> SurveyResult:
    """Read ``paths``, align every walk, write the outputs into ``out_dir`` (None: no files)."""
    cfg = config or GraphSlamConfig()
    _check_outputs(out_dir, rerun_path, floor_plan)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    survey = read_survey(paths)
    timings["read"] = time.perf_counter() - t0

    alignment = align(survey, cfg, progress=progress)
    timings.update({f"align.{k}": v for k, v in alignment.timings_s.items()})

    t = time.perf_counter()
    evaluation = evaluate(alignment.tracks, survey) if survey.has_ground_truth else None
    timings["evaluate"] = time.perf_counter() - t

    viz = None
    if rerun_path is not None:
        from graphslam.viz.background import start_log_survey

        # forked now: imports rerun and logs on the other core while the outputs are written
        viz = start_log_survey(rerun_path, survey, alignment, cfg, floor_plan=floor_plan, floor_size=floor_size)
    files: dict[str, Path] = {}
    report = build_report(survey, alignment, evaluation, cfg, timings)
    if out_dir is not None:
        t = time.perf_counter()
        try:
            files = write_outputs(Path(out_dir), survey, alignment, report, cfg, surveyed=surveyed)
        except BaseException:
            if viz is not None:  # let the child finish (and clean up its temp file) before failing
                with contextlib.suppress(Exception):
                    viz.wait()
            raise
        timings["write"] = time.perf_counter() - t
    if viz is not None:
        t = time.perf_counter()
        timings["rerun"] = viz.wait()  # log_survey itself, in the child
        timings["rerun_wait"] = time.perf_counter() - t  # what the parent still waited for it
    timings["total"] = time.perf_counter() - t0
    report["timings_s"] = {k: round(v, 4) for k, v in timings.items()}
    if out_dir is not None:
        atomic_write_json(Path(out_dir) / "report.json", report)
    return SurveyResult(survey, alignment, evaluation, report, Path(out_dir) if out_dir else None, files)


def _check_outputs(out_dir: str | Path | None, rerun_path: str | Path | None, floor_plan: str | Path | None) -> None:
    """Fail before the work, not after it, on outputs that cannot be written or a missing floor plan."""
    if out_dir is not None and Path(out_dir).exists() and not Path(out_dir).is_dir():
        raise OutputError(f"{out_dir}: exists and is not a folder")
    if rerun_path is not None and Path(rerun_path).is_dir():
        raise OutputError(f"{rerun_path}: is a folder, expected an .rrd file path")
    if floor_plan is not None and not Path(floor_plan).is_file():
        raise InputError(floor_plan, "floor plan image not found")


def write_outputs(
    out_dir: Path, survey: Survey, al: Alignment, report: dict, cfg: GraphSlamConfig, *, surveyed: bool = False
) -> dict[str, Path]:
    """Stage every output in a temporary folder, then move them in: no half-written file.

    Files are moved one by one (each rename is atomic); a crash between two renames can
    leave a previous run's files beside new ones in a re-used folder.
    """
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        stage = Path(tempfile.mkdtemp(prefix=".graphslam-", dir=out_dir))
    except OSError as e:
        raise OutputError(f"{out_dir}: cannot create the output folder ({e.strerror or e})") from None
    try:
        names = {
            "trajectories": "trajectories.csv",
            "aligned": "aligned.mcap",
            "radio_map": "radio_map.parquet",
            "config": "config.yaml",
            "report": "report.json",
        }
        write_trajectories(al.tracks, stage / names["trajectories"])
        write_aligned(al.tracks, stage / names["aligned"], frame_id=al.frame)
        _write_radio_map(survey, al, cfg, stage / names["radio_map"])
        if surveyed:  # evaluation: the same fingerprints at their ground-truth positions
            from graphslam.core.radiomap.survey_maps import surveyed_radio_map
            from graphslam.io.radiomap_io import write_radio_map

            names["radio_map_surveyed"] = "radio_map_surveyed.parquet"
            write_radio_map(surveyed_radio_map(survey, al, cfg), stage / names["radio_map_surveyed"])
        atomic_write_text(stage / names["config"], cfg.to_yaml())
        atomic_write_json(stage / names["report"], report)
        files = {}
        for key, name in names.items():
            if (stage / name).exists():
                (stage / name).replace(out_dir / name)
                files[key] = out_dir / name
        return files
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def _write_radio_map(survey: Survey, al: Alignment, cfg: GraphSlamConfig, path: Path) -> None:
    from graphslam.core.radiomap.survey_maps import crowdsourced_radio_map
    from graphslam.io.radiomap_io import write_radio_map

    write_radio_map(crowdsourced_radio_map(survey, al, cfg), path)
