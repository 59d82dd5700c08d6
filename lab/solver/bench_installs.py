#!/usr/bin/env python3
"""`graphslam survey` of one simulated survey by several installs (Python interpreters of different
environments, e.g. two trees, or `pip install .` against an install with another back end), alternating
run by run.

Why: on a shared machine only a side-by-side run, each install taking turns (in reversed order every
other round), compares them. Per install: medians of wall, CPU (user + sys) and the
optimise stage, peak RSS (the survey process's own, ``wait4``), the back end report.json names,
LM iterations, final error, landmark mean; the ratios to the first install; the load average.

    python lab/solver/bench_installs.py --python new=/tmp/venv-new/bin/python \\
        --python old=/tmp/venv-old/bin/python --scenario paper --size 12 --runs 3
    python lab/solver/bench_installs.py ... --scenario crowd --walks 200 --minutes 2,8 --seed 5

The survey is simulated once, by the interpreter running this script (`graphslam.sim`), into a
temporary folder; `--data DIR` takes a folder instead. Prints one JSON line per run, then one with
the medians.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path


def simulate_into(folder: Path, scenario: str, seed: int, size: float, walks: int, minutes: str) -> None:
    from graphslam import get_scenario, simulate

    sc = get_scenario(scenario)
    if walks:
        lo, hi = (float(m) for m in minutes.split(","))
        sc = replace(sc, name=f"{scenario}{walks}", n_walks=walks, duration_range_min=(lo, hi))
    simulate(sc, seed=seed, size=size).write(folder)


def run_once(python: str, data: Path, out: Path, extra: list[str]) -> dict:
    cmd = [python, "-P", "-m", "graphslam", "survey", str(data), "--out", str(out), "--no-progress", "--no-picture", *extra]
    load = os.getloadavg()[0]
    with open(out.with_suffix(".stderr"), "w") as err:
        t = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err, env={**os.environ, "RERUN": "off"})
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t
    if os.waitstatus_to_exitcode(status) != 0:
        sys.exit(f"{' '.join(cmd)} failed: {out.with_suffix('.stderr').read_text()[-500:]}")
    rep = json.loads((out / "report.json").read_text())
    opt = rep["optimizer"]
    return {
        "wall_s": wall,
        "cpu_s": usage.ru_utime + usage.ru_stime,
        "peak_rss_mb": usage.ru_maxrss / 1024,
        "optimise_s": rep["timings_s"].get("align.optimise"),
        "solver": " ".join(str(opt.get(k)) for k in ("solver", "linear_solver", "ordering", "factor_precision") if k in opt),
        "iterations": opt["iterations"],
        "final_error": opt["final_error"],
        "landmark_mean_m": rep.get("evaluation", {}).get("landmarks", {}).get("mean_m"),
        "poses": rep["nodes"],
        "wifi_edges": rep["edges"]["wifi"],
        "load_1min": load,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--python", action="append", required=True, help="NAME=INTERPRETER, two or more")
    ap.add_argument("--data", type=Path, help="a folder of recordings instead of a simulation")
    ap.add_argument("--scenario", default="paper")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--size", type=float, default=1.0)
    ap.add_argument("--walks", type=int, default=0, help="the scenario with this many walks (0: as it is, times --size)")
    ap.add_argument("--minutes", default="2,8", help="with --walks: walk durations, min,max minutes")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--set", dest="sets", action="append", default=[], help="passed on to every survey")
    args = ap.parse_args()
    installs = [p.split("=", 1) for p in args.python]
    extra = [a for s in args.sets for a in ("--set", s)]
    with tempfile.TemporaryDirectory(prefix="graphslam-installs-") as tmp:
        data = args.data
        if data is None:
            data = Path(tmp) / "data"
            simulate_into(data, args.scenario, args.seed, args.size, args.walks, args.minutes)
        results: dict[str, list[dict]] = {name: [] for name, _ in installs}
        for r in range(args.runs):
            for name, python in installs if r % 2 == 0 else installs[::-1]:
                row = run_once(python, data, Path(tmp) / f"out-{name}-{r}", extra)
                results[name].append(row)
                print(json.dumps({"install": name, "run": r + 1, **{k: round(v, 4) if isinstance(v, float) else v
                                                                     for k, v in row.items()}}), flush=True)
    summary: dict = {"runs": args.runs, "load_1min": [round(min(r["load_1min"] for rs in results.values() for r in rs), 2),
                                                     round(max(r["load_1min"] for rs in results.values() for r in rs), 2)]}
    first = installs[0][0]
    for name, rows in results.items():
        med = {k: statistics.median(r[k] for r in rows) for k in ("wall_s", "cpu_s", "optimise_s")}
        summary[name] = {**{k: round(v, 2) for k, v in med.items()}, "peak_rss_mb": round(max(r["peak_rss_mb"] for r in rows)),
                         **{k: rows[-1][k] for k in ("solver", "iterations", "final_error", "landmark_mean_m", "poses",
                                                     "wifi_edges")}}
    for name, _ in installs[1:]:
        summary[f"{first}_over_{name}"] = {
            k: round(summary[first][k] / summary[name][k], 3) for k in ("wall_s", "cpu_s", "optimise_s", "peak_rss_mb")
        }
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
