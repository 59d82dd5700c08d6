"""Survey speed side by side with a baseline checkout, over survey sizes: ``python -m lab.bench scale``.

Why: on a shared machine a single wall time says little. Here every size's survey is
simulated once, then ``graphslam survey`` runs in fresh processes, alternating between this
checkout and a ``--baseline`` one (a git worktree of an older commit, imported through
``PYTHONPATH``) so both see the same load; medians per stage from each run's report.json,
peak RSS per process (``wait4``), the load average before and after. The wall-time growth
exponent is the least-squares slope of log(wall) over log(size).
"""

from __future__ import annotations

import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Sequence

from graphslam import InputError, SolverError

# report.json stages shown, in pipeline order (align.* as written by app/survey.py)
STAGES = (
    ("read", "read MCAP"),
    ("align.edges", "edges"),
    ("align.initialise", "initialise"),
    ("align.build_graph", "build graph"),
    ("align.optimise", "optimise"),
    ("write", "write"),
    ("total", "pipeline total"),
)


def _run_once(data: Path, out: Path, pythonpath: str | None, config: Path | None) -> dict[str, Any]:
    # -P: no working directory on sys.path, or a run started inside a checkout would import that
    # checkout's graphslam ahead of the baseline's PYTHONPATH (and time the same code twice)
    cmd = [sys.executable, "-P", "-m", "graphslam", "survey", str(data), "--out", str(out), "--no-progress"]
    if config is not None:
        cmd += ["--config", str(config)]
    env = {**os.environ, "RERUN": "off"}
    if pythonpath is not None:
        env["PYTHONPATH"] = pythonpath
    log_path = out.with_suffix(".stderr")
    with open(log_path, "w") as log:
        t = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=log, env=env)
        _, status, usage = os.wait4(proc.pid, 0)  # this child's own peak RSS
        wall = time.perf_counter() - t
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        err = log_path.read_text().strip().splitlines()[-1:] or [""]
        raise SolverError(f"benchmark survey run failed ({'baseline' if pythonpath else 'this checkout'}): {err[0]}")
    rep = json.loads((out / "report.json").read_text())
    return {
        "wall": wall,
        "cpu": usage.ru_utime + usage.ru_stime,  # less sensitive to other jobs than wall time
        "rss_mb": usage.ru_maxrss / 1024,
        "stages": rep["timings_s"],
        "final_error": rep["optimizer"]["final_error"],
        "iterations": rep["optimizer"]["iterations"],
        "edges": rep["edges"]["wifi"],
        "landmark_mean_m": rep.get("evaluation", {}).get("landmarks", {}).get("mean_m"),
        # the optimiser report.json names, e.g. "cholmod metis cholesky" ("" before it named one)
        "backend": " ".join(str(rep["optimizer"][k]) for k in ("solver", "ordering", "factor_precision", "linear_solver")
                            if k in rep["optimizer"]),
    }


def _summary(runs: list[dict[str, Any]]) -> dict[str, Any]:
    keys = runs[0]["stages"].keys()
    return {
        "runs": len(runs),
        "wall_s": round(statistics.median(r["wall"] for r in runs), 3),
        "cpu_s": round(statistics.median(r["cpu"] for r in runs), 3),
        "startup_s": round(statistics.median(r["wall"] - r["stages"]["total"] for r in runs), 3),
        "stages_s": {k: round(statistics.median(r["stages"].get(k, 0.0) for r in runs), 3) for k in keys},
        "peak_rss_mb": round(max(r["rss_mb"] for r in runs), 1),
        "final_error": runs[-1]["final_error"],
        "iterations": runs[-1]["iterations"],
        "edges": runs[-1]["edges"],
        "landmark_mean_m": runs[-1]["landmark_mean_m"],
        "backend": runs[-1].get("backend", ""),
    }


def growth_exponent(sizes: Sequence[float], walls: Sequence[float]) -> float:
    """Least-squares slope of log(wall) against log(size)."""
    x = [math.log(s) for s in sizes]
    y = [math.log(w) for w in walls]
    mx, my = sum(x) / len(x), sum(y) / len(y)
    sxx = sum((a - mx) ** 2 for a in x)
    return sum((a - mx) * (b - my) for a, b in zip(x, y)) / sxx if sxx > 0 else float("nan")


def scale(
    scenario: str,
    seed: int,
    sizes: Sequence[float],
    runs: Sequence[int],
    *,
    baseline: Path | None = None,
    baseline_max_size: float = math.inf,
    config: Path | None = None,
    progress: Any = None,
) -> dict[str, Any]:
    """Per size: ``runs[i]`` rounds of (this checkout, baseline) in alternating order. The rounds
    go round robin over the sizes (round 1 of every size, then round 2, ...): a host whose speed
    drifts over minutes then slows every size alike instead of tilting the growth exponent."""
    from graphslam import simulate

    if baseline is not None and not (baseline / "graphslam" / "__init__.py").is_file():
        raise InputError(baseline, "not a graphslam checkout (no graphslam/__init__.py)")
    rows = []
    with tempfile.TemporaryDirectory(prefix="graphslam-scale-") as tmp:
        plan = []
        for size, n_runs in zip(sizes, runs):
            data = Path(tmp) / f"data-{size:g}"
            simulate(scenario, seed=seed, size=size).write(data)
            sides = {"new": None}
            if baseline is not None and size <= baseline_max_size:
                sides["base"] = str(baseline.resolve())
            plan.append((size, n_runs, data, sides, {k: [] for k in sides}, [os.getloadavg()[0]]))
        for r in range(max(runs, default=0)):
            for size, n_runs, data, sides, results, load in plan:
                if r >= n_runs:
                    continue
                order = list(sides) if r % 2 == 0 else list(reversed(sides))
                for side in order:
                    out = Path(tmp) / f"out-{size:g}-{side}-{r}"
                    results[side].append(_run_once(data, out, sides[side], config))
                    if progress is not None:
                        progress(f"size {size:g} {side} run {r + 1}/{n_runs}: {results[side][-1]['wall']:.2f} s")
                load.append(os.getloadavg()[0])
        for size, _, _, _, results, load in plan:
            row: dict[str, Any] = {"size": size, "load_1min": [round(min(load[1:] or load), 2), round(max(load[1:] or load), 2)]}
            for side, res in results.items():
                row[side] = _summary(res)
            if "base" in row:
                row["speedup_wall"] = round(row["base"]["wall_s"] / row["new"]["wall_s"], 2)
                row["speedup_cpu"] = round(row["base"]["cpu_s"] / row["new"]["cpu_s"], 2)
                row["speedup_optimise"] = round(
                    row["base"]["stages_s"]["align.optimise"] / max(row["new"]["stages_s"]["align.optimise"], 1e-9), 2
                )
            rows.append(row)
    out: dict[str, Any] = {"scenario": scenario, "seed": seed, "rows": rows}
    if len(rows) >= 2:
        sz = [r["size"] for r in rows]
        out["growth_exponent_new"] = round(growth_exponent(sz, [r["new"]["wall_s"] for r in rows]), 3)
        out["growth_exponent_new_cpu"] = round(growth_exponent(sz, [r["new"]["cpu_s"] for r in rows]), 3)
    return out


def markdown_table(result: dict[str, Any]) -> str:
    """The stage table (wall seconds, medians) as in docs/benchmarks.md."""
    cols = []
    for row in result["rows"]:
        for side in ("base", "new"):
            if side in row:
                cols.append((f"size {row['size']:g} {side}", row[side]))
    lines = ["| stage (wall s) | " + " | ".join(c for c, _ in cols) + " |", "|---" * (len(cols) + 1) + "|"]
    lines.append("| runs | " + " | ".join(str(s["runs"]) for _, s in cols) + " |")
    lines.append("| WiFi edges | " + " | ".join(f"{s['edges']:,}" for _, s in cols) + " |")
    lines.append("| interpreter, imports, exit | " + " | ".join(f"{s['startup_s']:.2f}" for _, s in cols) + " |")
    for key, name in STAGES:
        lines.append(f"| {name} | " + " | ".join(f"{s['stages_s'].get(key, 0.0):.2f}" for _, s in cols) + " |")
    lines.append("| **wall** | " + " | ".join(f"**{s['wall_s']:.2f}**" for _, s in cols) + " |")
    lines.append("| CPU (user + sys) | " + " | ".join(f"{s['cpu_s']:.2f}" for _, s in cols) + " |")
    lines.append("| peak RSS (MB) | " + " | ".join(f"{s['peak_rss_mb']:.0f}" for _, s in cols) + " |")
    lines.append("| LM iterations / final error | " + " | ".join(f"{s['iterations']} / {s['final_error']:.2f}" for _, s in cols) + " |")
    lm = " | ".join("-" if s["landmark_mean_m"] is None else f"{s['landmark_mean_m']:.3f}" for _, s in cols)
    lines.append(f"| landmark error mean (m) | {lm} |")
    loads = ", ".join(f"size {r['size']:g}: {r['load_1min'][0]}-{r['load_1min'][1]}" for r in result["rows"])
    lines.append("")
    lines.append(f"Load average (1 min, lowest-highest after its rounds): {loads}.")
    if "growth_exponent_new" in result:
        lines.append(
            f"Wall-time growth exponent (this checkout): {result['growth_exponent_new']} "
            f"(CPU time: {result.get('growth_exponent_new_cpu')})."
        )
    return "\n".join(lines)


def solvers(
    scenario: str, seed: int, size: float, names: Sequence[str], runs: int, *, progress: Any = None
) -> dict[str, Any]:
    """``graphslam survey`` of one simulated survey per ``optimizer.solver`` in ``names`` (gtsam,
    cholmod, auto), in fresh processes, the solvers taking turns run by run (in reversed order
    every other round: a host that drifts slows all alike). Per solver the medians (``_summary``)
    and, when ``cholmod`` ran, each solver's wall and optimise time over CHOLMOD's."""
    from graphslam import simulate

    with tempfile.TemporaryDirectory(prefix="graphslam-solvers-") as tmp:
        data = Path(tmp) / "data"
        simulate(scenario, seed=seed, size=size).write(data)
        configs = {}
        for name in names:
            configs[name] = Path(tmp) / f"{name}.yaml"
            configs[name].write_text(f"optimizer:\n  solver: {name}\n")
        results: dict[str, list[dict[str, Any]]] = {n: [] for n in names}
        load = [os.getloadavg()[0]]
        for r in range(runs):
            for name in (names if r % 2 == 0 else list(reversed(names))):
                results[name].append(_run_once(data, Path(tmp) / f"out-{name}-{r}", None, configs[name]))
                if progress is not None:
                    progress(f"{name} run {r + 1}/{runs}: {results[name][-1]['wall']:.2f} s")
            load.append(os.getloadavg()[0])
    row: dict[str, Any] = {"scenario": scenario, "seed": seed, "size": size, "load_1min": [min(load), max(load)]}
    for name, res in results.items():
        row[name] = _summary(res)
    if "cholmod" in row:
        row["wall_vs_cholmod"] = {n: round(row[n]["wall_s"] / row["cholmod"]["wall_s"], 2) for n in names}
        row["optimise_vs_cholmod"] = {
            n: round(row[n]["stages_s"].get("align.optimise", 0.0) / max(row["cholmod"]["stages_s"].get("align.optimise", 0.0), 1e-9), 2)
            for n in names
        }
    return row
