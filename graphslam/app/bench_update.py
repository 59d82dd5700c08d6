"""Benchmarks of issue 18: ``survey --update`` against a full re-solve, ``survey-batch`` against a loop.

Each run is a fresh ``graphslam`` process, as a user runs it; runs of the variants alternate so
that they share the (shared, loaded) machine alike. ``os.getloadavg()`` is recorded with every result.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from graphslam.errors import SolverError


def _graphslam(*args: str) -> float:
    """Run ``graphslam ARGS`` in a fresh process; its wall time (s)."""
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "graphslam", *args], capture_output=True, text=True,
                          env={**os.environ, "RERUN": "off"})
    if proc.returncode != 0:
        raise SolverError(f"benchmark run `graphslam {' '.join(args)}` failed: {proc.stderr.strip()[-500:]}")
    return time.perf_counter() - t


def _load() -> list[float]:
    return [round(v, 2) for v in os.getloadavg()]


def update_speed(
    scenario: str, seed: int, *, size: float, new_fraction: float, hops: Sequence[int], runs: int = 3
) -> dict[str, Any]:
    """A floor of ``size`` x the scenario's walks surveyed, then ``new_fraction`` more walks arrive:
    ``survey --update`` (per ``hops``) vs a full ``survey`` of every walk, end to end."""
    from graphslam.io.csv_io import read_trajectories
    from graphslam.io.mcap_writer import write_session
    from graphslam.sim import simulate
    from graphslam.sim.scenarios import get_scenario

    sc = get_scenario(scenario)
    n_prev = max(1, int(round(sc.n_walks * size)))
    n_new = max(1, int(round(n_prev * new_fraction)))
    sim = simulate(scenario, seed=seed, size=(n_prev + n_new) / sc.n_walks)
    load = [_load()]
    with tempfile.TemporaryDirectory(prefix="graphslam-bench-update-") as tmp:
        root = Path(tmp)
        for k, s in enumerate(sim.survey):
            write_session(s, root / "all" / f"{s.session_id}.mcap")
            if k < n_prev:
                (root / "prev").mkdir(exist_ok=True)
                os.link(root / "all" / f"{s.session_id}.mcap", root / "prev" / f"{s.session_id}.mcap")
        prev_wall = _graphslam("survey", str(root / "prev"), "--out", str(root / "prevout"), "--no-progress")
        variants = ["full"] + [f"update_hops{h}" for h in hops]
        walls: dict[str, list[float]] = {v: [] for v in variants}
        reports: dict[str, list[dict]] = {v: [] for v in variants}
        for r in range(runs):
            for v in variants if r % 2 == 0 else variants[::-1]:
                out = root / f"{v}_{r}"
                args = ["survey", str(root / "all"), "--out", str(out), "--no-progress"]
                if v != "full":
                    args += ["--update", str(root / "prevout"), "--set", f"update.hops={v.removeprefix('update_hops')}"]
                walls[v].append(_graphslam(*args))
                reports[v].append(json.loads((out / "report.json").read_text()))
            load.append(_load())
        full_tracks = read_trajectories(root / f"full_{runs - 1}" / "trajectories.csv")
        result: dict[str, Any] = {
            "scenario": scenario, "seed": seed, "walks_before": n_prev, "walks_new": n_new,
            "steps": sim.survey.n_steps, "runs": runs, "previous_survey_wall_s": round(prev_wall, 2),
        }
        full_wall = statistics.median(walls["full"])
        full_total = statistics.median(r["timings_s"]["total"] for r in reports["full"])
        for v in variants:
            rep = reports[v][-1]
            row: dict[str, Any] = {
                "wall_s_median": round(statistics.median(walls[v]), 3),
                "pipeline_s_median": round(statistics.median(r["timings_s"]["total"] for r in reports[v]), 3),
                "optimise_s_median": round(statistics.median(r["timings_s"]["align.optimise"] for r in reports[v]), 3),
                "lm_iterations": rep["optimizer"]["iterations"],
                "landmark_mean_m": round(rep["evaluation"]["landmarks"]["mean_m"], 3),
                "landmark_max_m": round(rep["evaluation"]["landmarks"]["max_m"], 3),
                "aligned": rep["aligned_sessions"],
            }
            if v != "full":
                u = rep["update"]
                tracks = read_trajectories(root / f"{v}_{runs - 1}" / "trajectories.csv")
                d = np.concatenate([np.linalg.norm(tracks[s].xy - full_tracks[s].xy, axis=1)
                                    for s in full_tracks if s in tracks])
                row.update({
                    "mode": u["mode"],
                    "resolved_nodes": u["resolved"]["nodes"],
                    "of_nodes": u["resolved"]["of_nodes"],
                    "wall_ratio_to_full": round(row["wall_s_median"] / full_wall, 3),
                    "pipeline_ratio_to_full": round(row["pipeline_s_median"] / full_total, 3),
                    "landmark_mean_minus_full_m": round(
                        row["landmark_mean_m"] - reports["full"][-1]["evaluation"]["landmarks"]["mean_m"], 3),
                    "step_distance_to_full_mean_m": round(float(d.mean()), 3),
                    "step_distance_to_full_max_m": round(float(d.max()), 3),
                })
            result[v] = row
        result["load_average"] = load
        return result
