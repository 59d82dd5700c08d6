"""``graphslam demo``: the whole job on the embedded simulator, headline figures at the end.

simulate (paper scenario + held-out walks) -> survey (align, export) -> locate held-out walks
on the crowdsourced radio map -> evaluate against the simulator's ground truth.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from graphslam.config import GraphSlamConfig
from graphslam.core.summary import report_main_map_counts


@dataclass(frozen=True)
class DemoResult:
    out_dir: Path
    figures: dict[str, Any]


def run_demo(out_dir: str | Path, *, scenario: str = "paper", seed: int = 0, test_walks: int = 3,
             config: GraphSlamConfig | None = None, rerun: str | Path | None = None) -> DemoResult:
    """Simulate, survey into OUT/survey, locate the held-out walks; ``rerun``: also the survey's
    Rerun recording there, and the located scans' beside it (``NAME.locate.rrd``)."""
    from graphslam.core.common.geometry import interpolate_xy
    from graphslam.core.common.geometry import se2_apply
    from graphslam.core.radiomap.knn import KnnLocator, locate_survey
    from graphslam.io.mcap_reader import read_survey
    from graphslam.io.radiomap_io import read_radio_map
    from graphslam.app.survey import run_survey
    from graphslam.app.survey_inputs import SurveyInputs
    from graphslam.sim import simulate

    out = Path(out_dir)
    t0 = time.perf_counter()
    sim = simulate(scenario, seed=seed, test_walks=test_walks)
    sim.write(out / "recordings")
    t_sim = time.perf_counter() - t0

    recordings = tuple(sorted((out / "recordings").glob("*.mcap")))
    result = run_survey(SurveyInputs(recordings, out / "survey", rerun=rerun), config)
    ev = result.evaluation

    t = time.perf_counter()
    rm = read_radio_map(out / "survey" / "radio_map.parquet")
    test = read_survey([out / "recordings" / "test"])
    located = locate_survey(KnnLocator(rm), test)
    t_locate = time.perf_counter() - t
    # held-out truth (site frame) vs answers (aligned frame, mapped by the evaluation's SE(2) fit)
    truth = np.concatenate(
        [interpolate_xy(s.ground_truth, np.array([sc.t_ns for sc in s.scans], float)) for s in test if s.ground_truth is not None]
    )
    est = se2_apply(np.array(ev.site_from_aligned), located.result.xy) if ev is not None else located.result.xy
    if rerun is not None:
        from graphslam.viz.rerun_log import log_locate_results

        log_locate_results(
            locate_recording(rerun),
            located.result.xy,
            truth,
            site_from_map=ev.site_from_aligned if ev is not None else None,
        )
    err = np.linalg.norm(est - truth, axis=1)
    err = err[np.isfinite(err)]
    figures = {
        "walks": len(sim.survey),
        "steps": sim.survey.n_steps,
        "km_walked": round(sum(s.steps.path_length for s in sim.survey) / 1000, 2),
        "main_map": report_main_map_counts(result.report),
        "aligned": f"{len(result.alignment.tracks)}/{len(sim.survey)}",
        "landmark_mean_m": round(ev.landmarks.mean_m, 2) if ev else None,
        "landmark_max_m": round(ev.landmarks.max_m, 2) if ev else None,
        "raw_dead_reckoning_landmark_mean_m": round(ev.landmarks_raw.mean_m, 2) if ev else None,
        "knn_queries": int(len(err)),
        "knn_median_m": round(float(np.median(err)), 2) if len(err) else None,
        "knn_p_lt_10m": round(float(np.mean(err < 10)), 3) if len(err) else None,
        "time_simulate_s": round(t_sim, 2),
        "time_survey_s": round(result.report["timings_s"]["total"], 2),
        "time_locate_s": round(t_locate, 3),
        "total_s": round(time.perf_counter() - t0, 2),
    }
    return DemoResult(out, figures)


def locate_recording(rerun: str | Path) -> Path:
    """Where ``demo --rerun NAME.rrd`` logs the located held-out scans: ``NAME.locate.rrd``."""
    return Path(rerun).with_suffix(".locate.rrd")
