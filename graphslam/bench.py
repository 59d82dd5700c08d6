"""Benchmarks on simulated surveys: accuracy over seeds, end-to-end speed, scale.

Side effects (temporary files, subprocesses) live here, not in ``core``. Every
function returns plain dicts so the CLI prints them as JSON lines and
docs/benchmarks.md can quote the command that made them.
"""

from __future__ import annotations

import json
import logging
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Sequence

from graphslam.config import GraphSlamConfig
from graphslam.core.align import align
from graphslam.core.evaluate import evaluate

log = logging.getLogger(__name__)


def accuracy(scenario: str, seeds: Sequence[int], cfg: GraphSlamConfig, *, size: float = 1.0) -> list[dict[str, Any]]:
    """Align simulated surveys in memory; landmark/heading/step errors per seed."""
    from graphslam.sim import simulate

    rows = []
    for seed in seeds:
        survey = simulate(scenario, seed=seed, size=size).survey
        t = time.perf_counter()
        al = align(survey, cfg)
        dt = time.perf_counter() - t
        ev = evaluate(al.tracks, survey)
        rows.append(
            {
                "scenario": scenario,
                "seed": seed,
                "walks": len(survey),
                "aligned": len(al.tracks),
                "steps": survey.n_steps,
                "wifi_edges": len(al.edges),
                "landmark_n": ev.landmarks.n,
                "landmark_mean_m": round(ev.landmarks.mean_m, 3),
                "landmark_median_m": round(ev.landmarks.median_m, 3),
                "landmark_p90_m": round(ev.landmarks.p90_m, 3),
                "landmark_max_m": round(ev.landmarks.max_m, 3),
                "raw_landmark_mean_m": round(ev.landmarks_raw.mean_m, 3),
                "raw_landmark_max_m": round(ev.landmarks_raw.max_m, 3),
                "heading_mean_deg": round(ev.heading_mean_deg, 3),
                "steps_mean_m": round(ev.steps.mean_m, 3),
                "align_s": round(dt, 3),
                "lm_iterations": len(al.iterations),
            }
        )
    return rows


def survey_speed(
    scenario: str, seed: int, *, runs: int = 5, size: float = 1.0, config: Path | None = None
) -> dict[str, Any]:
    """End-to-end ``graphslam survey`` (read MCAP, align, write every output) in a fresh process per run.

    Median wall time over ``runs``; per-stage medians from report.json; peak RSS of the runs.
    """
    from graphslam.sim import simulate

    with tempfile.TemporaryDirectory(prefix="graphslam-bench-") as tmp:
        data = Path(tmp) / "data"
        sim = simulate(scenario, seed=seed, size=size)
        sim.write(data)
        totals, walls, stages = [], [], []
        peak_kb = 0
        for r in range(runs):
            out = Path(tmp) / f"out{r}"
            cmd = [sys.executable, "-m", "graphslam", "survey", str(data), "--out", str(out), "--no-progress"]
            if config:
                cmd += ["--config", str(config)]
            before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
            t = time.perf_counter()
            proc = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "RERUN": "off"})
            walls.append(time.perf_counter() - t)
            if proc.returncode != 0:
                raise RuntimeError(f"survey failed: {proc.stderr.strip()}")
            peak_kb = max(peak_kb, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, before)
            rep = json.loads((out / "report.json").read_text())
            totals.append(rep["timings_s"]["total"])
            stages.append(rep["timings_s"])
        keys = stages[0].keys()
        return {
            "scenario": scenario,
            "seed": seed,
            "size": size,
            "runs": runs,
            "steps": sim.survey.n_steps,
            "scans": sim.survey.n_scans,
            "wall_s_median": round(statistics.median(walls), 3),
            "pipeline_s_median": round(statistics.median(totals), 3),
            "stages_s_median": {k: round(statistics.median(s[k] for s in stages), 3) for k in keys},
            "peak_rss_mb": round(peak_kb / 1024, 1),
            "landmark_mean_m": rep.get("evaluation", {}).get("landmarks", {}).get("mean_m"),
        }


def fig8(
    scenario: str,
    seeds: Sequence[int],
    cfg: GraphSlamConfig,
    *,
    test_walks: int = 5,
    k: int = 3,
    plot: Path | None = None,
) -> dict[str, Any]:
    """The paper's fig. 8: kNN errors of held-out test walks on the crowdsourced vs the surveyed map.

    The crowdsourced map lives in the aligned frame; it is put into the site frame with the
    SE(2) fit of the landmark evaluation (evaluation only, like the paper's manual rotation).
    The surveyed map holds the same fingerprints at their ground-truth positions.
    """
    import numpy as np

    from graphslam.core.evaluate import interpolate_xy
    from graphslam.core.knn import KnnConfig, KnnLocator
    from graphslam.core.survey_maps import crowdsourced_radio_map, surveyed_radio_map
    from graphslam.sim import simulate

    errs: dict[str, list] = {"crowdsourced": [], "surveyed": []}
    per_seed = []
    for seed in seeds:
        sim = simulate(scenario, seed=seed, test_walks=test_walks)
        al = align(sim.survey, cfg)
        ev = evaluate(al.tracks, sim.survey)
        maps = {
            "crowdsourced": crowdsourced_radio_map(sim.survey, al, cfg, site_from_aligned=np.array(ev.site_from_aligned)),
            "surveyed": surveyed_radio_map(sim.survey, al, cfg),
        }
        scans = [sc for s in sim.test_sessions for sc in s.scans]
        truth = np.concatenate(
            [interpolate_xy(s.ground_truth, np.array([sc.t_ns for sc in s.scans], float)) for s in sim.test_sessions]
        )
        row: dict[str, Any] = {"seed": seed, "queries": len(scans)}
        for name, rm in maps.items():
            res = KnnLocator(rm, KnnConfig(k=k)).locate([sc.readings for sc in scans])
            e = np.linalg.norm(res.xy - truth, axis=1)
            e = e[np.isfinite(e)]
            errs[name].append(e)
            row[f"{name}_p_lt_10m"] = round(float(np.mean(e < 10.0)), 4)
            row[f"{name}_median_m"] = round(float(np.median(e)), 3)
        per_seed.append(row)
    all_e = {n: np.concatenate(v) for n, v in errs.items()}
    out: dict[str, Any] = {
        "scenario": scenario,
        "seeds": list(seeds),
        "k": k,
        "test_walks_per_seed": test_walks,
        "queries": int(len(all_e["surveyed"])),
        "per_seed": per_seed,
    }
    for n, e in all_e.items():
        out[f"{n}_p_lt_10m"] = round(float(np.mean(e < 10.0)), 4)
        out[f"{n}_mean_m"] = round(float(np.mean(e)), 3)
        out[f"{n}_median_m"] = round(float(np.median(e)), 3)
        out[f"{n}_p90_m"] = round(float(np.percentile(e, 90)), 3)
    if plot is not None:
        from graphslam.viz.plots import error_cdf

        error_cdf(all_e, plot, title=f"kNN (k={k}) on held-out walks, {scenario}, seeds {','.join(map(str, seeds))}")
    return out


def ilc_floors(site_dir: Path, cfg: GraphSlamConfig, floors: Sequence[str] | None = None) -> list[dict[str, Any]]:
    """Align every floor of an ILC 2.0 site (real recordings); waypoint errors after one SE(2) fit."""
    from graphslam.errors import InputError
    from graphslam.pipeline import run_survey

    site_dir = Path(site_dir)
    names = list(floors) if floors else sorted(p.name for p in site_dir.iterdir() if p.is_dir())
    if not names:
        raise InputError(site_dir, "no floor folders (e.g. B1, F1) in this site folder")
    rows = []
    for name in names:
        t = time.perf_counter()
        res = run_survey([site_dir / name], None, cfg)
        dt = time.perf_counter() - t
        ev = res.evaluation
        lm = ev.landmarks if ev is not None else None
        rows.append(
            {
                "floor": name,
                "walks": len(res.survey),
                "aligned": len(res.alignment.tracks),
                "aligned_fraction": round(len(res.alignment.tracks) / max(1, len(res.survey)), 3),
                "waypoints": lm.n if lm else 0,
                "mean_m": round(lm.mean_m, 2) if lm else None,
                "p90_m": round(lm.p90_m, 2) if lm else None,
                "max_m": round(lm.max_m, 2) if lm else None,
                "per_walk_rigid_fit_mean_m": round(ev.landmarks_per_walk_fit.mean_m, 2) if ev else None,
                "time_s": round(dt, 2),
            }
        )
    return rows
