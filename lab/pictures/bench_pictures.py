"""What the pictures cost: `graphslam survey` with and without survey.png, side by side,
and the drawing time of survey.png for a small and a large survey.

    python lab/pictures/bench_pictures.py [--runs 7] [--big-walks 200] [--skip-big | --skip-paper]

1. Side by side on the simulator's `paper` survey (seed 0, 5 walks): fresh `graphslam survey`
   processes, alternating --picture / --no-picture (so load changes hit both alike); median
   wall time and CPU time (user + sys of the process) of each, their ratios, and the median of
   report.json's `picture` (seconds the survey spent drawing survey.png). On a shared machine
   the CPU time is the steadier figure: the wall time moves with the other users' load.
2. Drawing alone, in this process after one warm-up: median of 3 `draw_survey` calls, for
   `paper` (5 walks) and `crowd` scaled to --big-walks walks (aligned once, in memory).

Prints one JSON line per part; the load average before and after.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def side_by_side(data: Path, tmp: Path, runs: int) -> dict:
    walls: dict[str, list[float]] = {"picture": [], "no_picture": []}
    cpus: dict[str, list[float]] = {"picture": [], "no_picture": []}
    drawn = []
    for r in range(runs):
        for mode in ("picture", "no_picture") if r % 2 == 0 else ("no_picture", "picture"):
            out = tmp / f"{mode}{r}"
            cmd = [sys.executable, "-m", "graphslam", "survey", str(data), "--out", str(out), "--no-progress",
                   "--picture" if mode == "picture" else "--no-picture"]
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            t = time.perf_counter()
            proc = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "RERUN": "off"})
            if proc.returncode != 0:
                raise SystemExit(f"survey failed: {proc.stderr.strip()}")
            walls[mode].append(time.perf_counter() - t)
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            cpus[mode].append(after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime)
            if mode == "picture":
                rep = json.loads((out / "report.json").read_text())
                drawn.append(rep["timings_s"]["picture"])
    med = {k: statistics.median(v) for k, v in walls.items()}
    cpu = {k: statistics.median(v) for k, v in cpus.items()}
    return {
        "part": "survey paper seed 0, side by side",
        "runs_each": runs,
        "wall_s_median_picture": round(med["picture"], 3),
        "wall_s_median_no_picture": round(med["no_picture"], 3),
        "ratio": round(med["picture"] / med["no_picture"], 4),
        "cpu_s_median_picture": round(cpu["picture"], 3),
        "cpu_s_median_no_picture": round(cpu["no_picture"], 3),
        "cpu_ratio": round(cpu["picture"] / cpu["no_picture"], 4),
        "picture_s_median": round(statistics.median(drawn), 3),
        "walls": {k: [round(x, 3) for x in v] for k, v in walls.items()},
    }


def draw_time(scenario: str, size: float) -> dict:
    from graphslam import align, draw_survey, evaluate, GraphSlamConfig, scene_of_alignment, simulate

    sim = simulate(scenario, seed=0, size=size)
    cfg = GraphSlamConfig()
    t = time.perf_counter()
    al = align(sim.survey, cfg)
    align_s = time.perf_counter() - t
    ev = evaluate(al.tracks, sim.survey)
    with tempfile.TemporaryDirectory() as tmp:
        scene = scene_of_alignment(sim.survey, al, cfg, ev)
        draw_survey(scene, Path(tmp) / "warm.png")
        times, scene_times = [], []
        for k in range(3):
            t = time.perf_counter()
            scene = scene_of_alignment(sim.survey, al, cfg, ev)
            t1 = time.perf_counter()
            draw_survey(scene, Path(tmp) / f"s{k}.png")
            scene_times.append(t1 - t)
            times.append(time.perf_counter() - t1)
    return {
        "part": f"draw survey.png, {scenario} size {size:g}",
        "walks": len(sim.survey),
        "aligned": len(al.tracks),
        "steps": sim.survey.n_steps,
        "wifi_edges": len(al.edges),
        "edges_drawn": len(scene.edge_xy),
        "align_s": round(align_s, 2),
        "scene_s_median": round(statistics.median(scene_times), 3),
        "draw_s_median": round(statistics.median(times), 3),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--big-walks", type=int, default=200)
    ap.add_argument("--skip-big", action="store_true", help="only the paper survey")
    ap.add_argument("--skip-paper", action="store_true", help="only the big survey's drawing time")
    a = ap.parse_args()
    print(json.dumps({"load_average_before": os.getloadavg()}))
    if not a.skip_paper:
        with tempfile.TemporaryDirectory(prefix="graphslam-pictures-") as tmp:
            from graphslam import simulate

            data = Path(tmp) / "paper"
            simulate("paper", seed=0).write(data)
            print(json.dumps(side_by_side(data, Path(tmp), a.runs)), flush=True)
        print(json.dumps(draw_time("paper", 1.0)), flush=True)
    if not a.skip_big:
        print(json.dumps(draw_time("crowd", a.big_walks / 48.0)), flush=True)
    print(json.dumps({"load_average_after": os.getloadavg()}))


if __name__ == "__main__":
    main()
