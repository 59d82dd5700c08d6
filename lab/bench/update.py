"""Benchmarks of ``survey --update`` against a full re-solve, ``survey-batch`` against a loop.

Each run is a fresh ``graphslam`` process, as a user runs it; runs of the variants alternate so
that they share the (shared, loaded) machine alike. ``os.getloadavg()`` is recorded with every result.
"""

from __future__ import annotations

import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from graphslam import SolverError


CPU_S: list[float] = []  # user + system seconds of each `_graphslam` run, in order (core-seconds)


def _children_cpu() -> float:
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def _graphslam(*args: str) -> float:
    """Run ``graphslam ARGS`` in a fresh process; its wall time (s). Its CPU time goes to ``CPU_S``
    (what the run costs on a dedicated core, whatever else the shared machine runs)."""
    t, c = time.perf_counter(), _children_cpu()
    proc = subprocess.run([sys.executable, "-m", "graphslam", *args], capture_output=True, text=True,
                          env={**os.environ, "RERUN": "off"})
    if proc.returncode != 0:
        raise SolverError(f"benchmark run `graphslam {' '.join(args)}` failed: {proc.stderr.strip()[-500:]}")
    CPU_S.append(_children_cpu() - c)
    return time.perf_counter() - t


def _load() -> list[float]:
    return [round(v, 2) for v in os.getloadavg()]


def update_speed(
    scenario: str, seed: int, *, size: float, new_fraction: float, hops: Sequence[int], runs: int = 3
) -> dict[str, Any]:
    """A floor of ``size`` x the scenario's walks surveyed, then ``new_fraction`` more walks arrive:
    ``survey --update`` (per ``hops``) vs a full ``survey`` of every walk, end to end."""
    from graphslam import get_scenario, read_trajectories, simulate, write_session

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
        cpus: dict[str, list[float]] = {v: [] for v in variants}
        reports: dict[str, list[dict]] = {v: [] for v in variants}
        for r in range(runs):
            for v in variants if r % 2 == 0 else variants[::-1]:
                out = root / f"{v}_{r}"
                args = ["survey", str(root / "all"), "--out", str(out), "--no-progress"]
                if v != "full":
                    args += ["--update", str(root / "prevout"), "--set", f"update.hops={v.removeprefix('update_hops')}"]
                walls[v].append(_graphslam(*args))
                cpus[v].append(CPU_S[-1])
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
                "cpu_s_median": round(statistics.median(cpus[v]), 3),
                "pipeline_s_median": round(statistics.median(r["timings_s"]["total"] for r in reports[v]), 3),
                "optimise_s_median": round(statistics.median(r["timings_s"]["align.optimise"] for r in reports[v]), 3),
                # every stage's median (report.json's timings_s): what an update still pays, and where
                "stages_s": {k: round(statistics.median(r["timings_s"].get(k, 0.0) for r in reports[v]), 3)
                             for k in reports[v][-1]["timings_s"]},
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
                    "cpu_ratio_to_full": round(row["cpu_s_median"] / statistics.median(cpus["full"]), 3),
                    "pipeline_ratio_to_full": round(row["pipeline_s_median"] / full_total, 3),
                    "landmark_mean_minus_full_m": round(
                        row["landmark_mean_m"] - reports["full"][-1]["evaluation"]["landmarks"]["mean_m"], 3),
                    "step_distance_to_full_mean_m": round(float(d.mean()), 3),
                    "step_distance_to_full_max_m": round(float(d.max()), 3),
                })
            result[v] = row
        result["load_average"] = load
        return result


_SEQUENTIAL = """
import json, sys, time
from graphslam.app.batch import survey_floor
from graphslam.config import GraphSlamConfig
sites, out = sys.argv[1], sys.argv[2]
floors = json.loads(sys.argv[3])
cfg = GraphSlamConfig().model_dump_json()
t = time.perf_counter()
rows = [survey_floor(f"{sites}/{f}", f"{out}/{f}", cfg, f) for f in floors]
print(json.dumps({"seconds": time.perf_counter() - t, "ok": sum(r["status"] == "ok" for r in rows)}))
"""


_ONE_THREAD = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def batch_speed(
    scenario: str, *, floors: int, size: float, workers: int, runs: int = 1, corrupt: bool = True
) -> dict[str, Any]:
    """``survey-batch --workers N`` vs two sequential baselines, and vs ``--workers 1``. The
    sequential baselines: the shell loop the issue starts from (``graphslam survey FLOOR --out
    OUT`` once per floor, a fresh process each, as floors run without ``survey-batch``), and the
    same floors one after another in one process (no cluster, no per-floor start-up: a loop no
    command offers, the stricter baseline). The control: N plain processes side by side, each
    surveying every N-th floor (no Dask), shows what parallelism the (shared) machine gives at
    that moment. Floors: the
    scenario with seeds 0..floors-1; with ``corrupt`` one more floor whose one recording is
    truncated must come out as one failed row naming the file."""
    from graphslam import simulate, write_session

    with tempfile.TemporaryDirectory(prefix="graphslam-bench-batch-") as tmp:
        root = Path(tmp)
        sites = root / "sites"
        names = [f"site{k // 4}/F{k % 4}" for k in range(floors)]
        for k, name in enumerate(names):
            for s in simulate(scenario, seed=k, size=size).survey:
                write_session(s, sites / name / f"{s.session_id}.mcap")
        load = [_load()]
        seq, shell, w1, wn, plain, cpu_seq, cpu_wn = [], [], [], [], [], [], []
        env = {**os.environ, "RERUN": "off"}
        for r in range(runs):
            t = time.perf_counter()
            for name in names:
                _graphslam("-q", "survey", str(sites / name), "--out", str(root / f"shell{r}" / name))
            shell.append(time.perf_counter() - t)
            t, c = time.perf_counter(), _children_cpu()
            proc = subprocess.run(
                [sys.executable, "-c", _SEQUENTIAL, str(sites), str(root / f"seq{r}"), json.dumps(names)],
                capture_output=True, text=True, env=env,
            )
            if proc.returncode != 0:
                raise SolverError(f"sequential run failed: {proc.stderr.strip()[-500:]}")
            seq.append(time.perf_counter() - t)
            cpu_seq.append(_children_cpu() - c)
            t = time.perf_counter()
            procs = [subprocess.Popen([sys.executable, "-c", _SEQUENTIAL, str(sites), str(root / f"plain{r}"),
                                       json.dumps(names[k::workers])], stdout=subprocess.DEVNULL,
                                      env={**env, **_ONE_THREAD}) for k in range(workers)]
            if any(p.wait() != 0 for p in procs):
                raise SolverError("plain parallel run failed")
            plain.append(time.perf_counter() - t)
            wn.append(_graphslam("survey-batch", str(sites), "--out", str(root / f"w{workers}_{r}"), "--workers",
                                 str(workers), "--no-progress"))
            cpu_wn.append(CPU_S[-1])
            w1.append(_graphslam("survey-batch", str(sites), "--out", str(root / f"w1_{r}"), "--workers", "1",
                                 "--no-progress"))
            load.append(_load())
        rows = json.loads((root / f"w{workers}_{runs - 1}" / "summary.json").read_text())
        res: dict[str, Any] = {
            "scenario": scenario, "size": size, "floors": floors, "workers": workers, "runs": runs,
            "walks_per_floor": rows[0]["walks"],
            "floor_seconds_median": round(statistics.median(r["seconds"] for r in rows), 3),
            "sequential_shell_loop_wall_s": round(statistics.median(shell), 2),
            "sequential_one_process_wall_s": round(statistics.median(seq), 2),
            "sequential_cpu_s_per_floor": round(statistics.median(cpu_seq) / floors, 3),
            f"batch_workers{workers}_cpu_s_per_floor": round(statistics.median(cpu_wn) / floors, 3),
            f"batch_workers{workers}_wall_s": round(statistics.median(wn), 2),
            "batch_workers1_wall_s": round(statistics.median(w1), 2),
            "throughput_ratio_vs_shell_loop": round(statistics.median(shell) / statistics.median(wn), 3),
            "throughput_ratio_vs_sequential": round(statistics.median(seq) / statistics.median(wn), 3),
            "throughput_ratio_vs_workers1": round(statistics.median(w1) / statistics.median(wn), 3),
            f"control_{workers}_plain_processes_wall_s": round(statistics.median(plain), 2),
            "control_ratio_vs_sequential": round(statistics.median(seq) / statistics.median(plain), 3),
            "all_ok": all(r["status"] == "ok" for r in rows),
        }
        if corrupt:
            bad_dir = sites / "broken" / "F0"
            for s in simulate(scenario, seed=floors, size=size).survey:
                write_session(s, bad_dir / f"{s.session_id}.mcap")
            bad = sorted(bad_dir.glob("*.mcap"))[0]
            bad.write_bytes(bad.read_bytes()[: bad.stat().st_size // 2])
            proc = subprocess.run([sys.executable, "-m", "graphslam", "survey-batch", str(sites), "--out",
                                   str(root / "with_broken"), "--workers", str(workers), "--no-progress"],
                                  capture_output=True, text=True)
            rows = json.loads((root / "with_broken" / "summary.json").read_text())
            failed = [r for r in rows if r["status"] != "ok"]
            res["corrupt_floor"] = {"exit_code": proc.returncode, "rows": len(rows), "failed_rows": failed,
                                    "names_the_file": len(failed) == 1 and str(bad) in (failed[0]["error"] or "")}
        res["load_average"] = load
        return res
