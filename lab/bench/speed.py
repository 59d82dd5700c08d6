"""Every speed row of docs/benchmarks.md's speed table side by side with a baseline checkout, in one run:
``python -m lab.bench speed --baseline CHECKOUT``.

Why one command: on a shared 2-core machine an absolute time says little unless the baseline ran
beside it. Each row runs the benchmark that owns it, this checkout and the baseline alternating in
fresh processes (the baseline imported through ``PYTHONPATH`` with ``python -P``, or from its own
folder), and the table puts the medians side by side with the goal:

- start-up: CPU of ``graphslam --help``, ``survey --help``, ``survey MISSING`` (exit 2), median of
  ``startup_runs`` alternating runs (``os.wait4``: the child's own CPU);
- survey: ``lab.bench scale`` on the simulator's ``paper`` at each size (wall, CPU, peak RSS);
- the native solver against the same graph in ``gtsam.CustomFactor`` (``lab/solver/bench_customfactor.py``,
  this checkout only: it is a ratio within one run already);
- update: ``lab.bench update crowd`` (10 new walks on a size-4 floor), CPU of ``--update`` over a
  full survey, per side;
- tracking: ``lab/tracking/tracking_speed_ab.py`` on the ``paper`` map (seed 0) and its held-out walks;
- service: ``lab/service/bench_service_load.py``, single queries from 8 keep-alive clients.

Stdout: one JSON object (every figure, the load averages), then the markdown table. The baseline is
any checkout of graphslam with this layout (``lab/``, ``graphslam/``), e.g.
``git worktree add --detach /tmp/base 6d0b028``.
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
from typing import Any, Callable, Sequence

from graphslam import SolverError

HERE = Path(__file__).resolve().parents[2]  # this checkout (holds lab/ and graphslam/)

# The goals, one per row (None: reported, no goal of its own).
GOALS = {
    "startup_help": "≤ 0.3 s", "startup_survey_help": "≤ 0.3 s", "startup_survey_missing": "≤ 0.3 s",
    "survey_small": None, "survey_large": "≤ 15 s, ≤ 1 GB",
    "customfactor": "≥ 10×", "update": "≤ 15 % of a full survey",
    "track": "≤ 5 ms/step", "calibration": "≤ 5 s", "service": "≥ 3,000 req/s, p99 ≤ 5 ms",
}


def _env(pythonpath: Path | None) -> dict[str, str]:
    env = {**os.environ, "RERUN": "off"}
    env.pop("PYTHONPATH", None)
    if pythonpath is not None:
        env["PYTHONPATH"] = str(pythonpath)
    return env


def _python() -> list[str]:
    # -P: the working directory is not put on sys.path, so PYTHONPATH (the side's checkout) decides,
    # not an installed graphslam
    return [sys.executable, "-P"]


def _json_after(text: str, first: str = "{") -> Any:
    """The first JSON value in ``text`` that starts a line with ``first`` (tools print logs around it)."""
    lines = text.splitlines()
    for k, line in enumerate(lines):
        if line.startswith(first):
            for end in range(k + 1, len(lines) + 1):
                try:
                    return json.loads("\n".join(lines[k:end]))
                except json.JSONDecodeError:
                    continue
    raise SolverError(f"benchmark output holds no JSON value: {text.strip()[-300:]!r}")


def _run(cmd: Sequence[str], *, cwd: Path, env: dict[str, str], what: str) -> str:
    proc = subprocess.run(list(cmd), cwd=cwd, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SolverError(f"speed benchmark {what} failed (exit {proc.returncode}): {proc.stderr.strip()[-500:]}")
    return proc.stdout


def startup_cpu(tree: Path, args: Sequence[str], missing_ok: bool) -> float:
    """CPU seconds (user + sys) of one ``python -m graphslam ARGS`` process of ``tree``."""
    cmd = [*_python(), "-m", "graphslam", *args]
    proc = subprocess.Popen(cmd, cwd=tempfile.gettempdir(), env=_env(tree),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    _, status, usage = os.wait4(proc.pid, 0)
    code = os.waitstatus_to_exitcode(status)
    if code != 0 and not (missing_ok and code == 2):
        raise SolverError(f"speed benchmark: `graphslam {' '.join(args)}` exited {code}")
    return usage.ru_utime + usage.ru_stime


def startup_rows(baseline: Path, runs: int, tmp: Path) -> dict[str, dict[str, float]]:
    commands = {
        "startup_help": (["--help"], False),
        "startup_survey_help": (["survey", "--help"], False),
        "startup_survey_missing": (["survey", str(tmp / "MISSING"), "-o", str(tmp / "never")], True),
    }
    out: dict[str, dict[str, float]] = {}
    for name, (args, missing_ok) in commands.items():
        cpu: dict[str, list[float]] = {"this": [], "base": []}
        for r in range(runs):
            for side in ("this", "base") if r % 2 == 0 else ("base", "this"):
                tree = HERE if side == "this" else baseline
                cpu[side].append(startup_cpu(tree, args, missing_ok))
        out[name] = {side: round(statistics.median(v), 3) for side, v in cpu.items()}
    return out


def speed(
    baseline: Path,
    *,
    sizes: Sequence[float] = (1.0, 12.0),
    runs: Sequence[int] = (3, 3),
    startup_runs: int = 7,
    update_runs: int = 3,
    update_size: float = 4.0,
    track_rounds: int = 2,
    service_rounds: int = 2,
    progress: Callable[[str], None] = lambda msg: None,
) -> dict[str, Any]:
    """Every row; see the module's docstring."""
    baseline = Path(baseline).resolve()
    if not (baseline / "graphslam").is_dir():
        raise SolverError(f"--baseline {baseline}: not a graphslam checkout (no graphslam/ folder)")
    result: dict[str, Any] = {"baseline": str(baseline), "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                              "load_before": [round(v, 2) for v in os.getloadavg()]}
    env_this, env_base = _env(HERE), _env(baseline)
    with tempfile.TemporaryDirectory(prefix="graphslam-speed-") as tmp_s:
        tmp = Path(tmp_s)
        progress("start-up")
        result["startup"] = startup_rows(baseline, startup_runs, tmp)

        progress(f"survey at sizes {', '.join(f'{s:g}' for s in sizes)} (lab.bench scale)")
        text = _run([*_python(), "-m", "lab.bench", "-q", "scale", "paper", "--sizes", ",".join(f"{s:g}" for s in sizes),
                     "--runs", ",".join(str(r) for r in runs), "--baseline", str(baseline)],
                    cwd=HERE, env=env_this, what="scale")
        result["survey"] = _json_after(text)

        progress("native solver vs gtsam.CustomFactor (paper seed 0)")
        text = _run([sys.executable, str(HERE / "lab" / "solver" / "bench_customfactor.py"), "--runs", "3"],
                    cwd=HERE, env=env_this, what="bench_customfactor")
        result["customfactor"] = _json_after(text)

        result["update"] = {}
        for side, tree, env in (("this", HERE, env_this), ("base", baseline, env_base)):
            progress(f"update ({side})")
            # the baseline's own lab.bench and graphslam: run from its folder (its sub-processes too)
            text = _run([*_python(), "-m", "lab.bench", "-q", "update", "crowd", "--size", f"{update_size:g}",
                         "--new-fraction", "0.05", "--hops", "0", "--runs", str(update_runs)],
                        cwd=tree, env=env, what=f"update ({side})")
            result["update"][side] = _json_after(text)

        progress("tracking map: simulate paper seed 0 with 5 held-out walks, survey it")
        data, out = tmp / "paper", tmp / "paper-out"
        _run([*_python(), "-m", "graphslam", "simulate", "paper", "--out", str(data), "--seed", "0",
              "--test-walks", "5"], cwd=HERE, env=env_this, what="simulate")
        _run([*_python(), "-m", "graphslam", "survey", str(data), "--out", str(out), "--no-progress"],
             cwd=HERE, env=env_this, what="survey of the tracking map")
        radio_map = out / "radio_map.parquet"
        progress("tracking (tracking_speed_ab.py)")
        text = _run([sys.executable, str(HERE / "lab" / "tracking" / "tracking_speed_ab.py"), "--baseline", str(baseline),
                     str(radio_map), str(data / "test"), "--rounds", str(track_rounds)],
                    cwd=HERE, env=env_this, what="tracking_speed_ab")
        result["track"] = _json_after(text)

        progress("service (bench_service_load.py, 8 clients)")
        text = _run([sys.executable, str(HERE / "lab" / "service" / "bench_service_load.py"), "--radio-map", str(radio_map),
                     "--variant", f"this={HERE}:--log-level warning", "--variant", f"base={baseline}:--log-level warning",
                     "--rounds", str(service_rounds), "--clients", "8"],
                    cwd=HERE, env=env_this, what="bench_service_load")
        rows = [json.loads(line) for line in text.splitlines() if line.startswith("{")]
        result["service"] = {
            side: {key: statistics.median(r[key] for r in rows if r["variant"] == side)
                   for key in ("rps", "p50_ms", "p99_ms", "server_cpu_us_per_req")}
            for side in ("this", "base")
        }
    result["load_after"] = [round(v, 2) for v in os.getloadavg()]
    return result


def _ratio(base: float, this: float) -> str:
    return f"×{base / this:.1f}" if this > 0 else "—"


def markdown_table(r: dict[str, Any]) -> str:
    """One row per workload: baseline, this checkout, baseline / this, the goal."""
    lines = ["| workload | baseline | this checkout | baseline / this | goal |", "|---|---|---|---|---|"]

    def row(name: str, label: str, base: str, this: str, ratio: str) -> None:
        lines.append(f"| {label} | {base} | **{this}** | {ratio} | {GOALS.get(name) or ''} |")

    labels = {"startup_help": "`graphslam --help`, CPU", "startup_survey_help": "`graphslam survey --help`, CPU",
              "startup_survey_missing": "`graphslam survey MISSING` (exit 2), CPU"}
    for name, label in labels.items():
        s = r["startup"][name]
        row(name, label, f"{s['base']:.2f} s", f"{s['this']:.2f} s", _ratio(s["base"], s["this"]))
    rows = r["survey"]["rows"]
    for k, sr in enumerate(rows):
        name = "survey_large" if k == len(rows) - 1 and len(rows) > 1 else "survey_small"
        new, base = sr["new"], sr.get("base")
        label = f"`paper --size {sr['size']:g}` survey ({new['edges']:,} WiFi edges), wall / CPU / peak RSS, median of {new['runs']}"
        this_s = f"{new['wall_s']:.1f} / {new['cpu_s']:.1f} s / {new['peak_rss_mb']:.0f} MB"
        base_s = f"{base['wall_s']:.1f} / {base['cpu_s']:.1f} s / {base['peak_rss_mb']:.0f} MB" if base else "—"
        row(name, label, base_s, this_s, _ratio(base["wall_s"], new["wall_s"]) if base else "—")
    cf = r["customfactor"]
    row("customfactor", f"solve of the `paper` graph ({cf['nodes']:,} poses): gtsam.CustomFactor vs native",
        f"{cf['custom_solve_s']:.1f} s", f"{cf['native_solve_s_median']:.2f} s", f"×{cf['speedup']:.1f}")
    up = {side: v["update_hops0"] for side, v in r["update"].items()}
    u = r["update"]["this"]
    row("update", f"`survey --update`, {u['walks_new']} new walks on {u['walks_before']} (`crowd`, {u['steps']:,} steps): "
        "CPU over a full survey",
        f"{up['base']['cpu_ratio_to_full']:.0%} ({up['base']['cpu_s_median']:.1f} s)",
        f"{up['this']['cpu_ratio_to_full']:.0%} ({up['this']['cpu_s_median']:.1f} s)",
        _ratio(up["base"]["cpu_s_median"], up["this"]["cpu_s_median"]))
    t = r["track"]["median"]
    row("track", f"`graphslam track` default, `paper` seed 0, {r['track']['steps']:,} steps: CPU per step",
        f"{t['baseline']['track_cpu_ms_per_step']:.1f} ms", f"{t['this']['track_cpu_ms_per_step']:.1f} ms",
        _ratio(t["baseline"]["track_cpu_ms_per_step"], t["this"]["track_cpu_ms_per_step"]))
    row("calibration", "its self-calibration, CPU", f"{t['baseline']['calibration_cpu_s']:.1f} s",
        f"{t['this']['calibration_cpu_s']:.1f} s", _ratio(t["baseline"]["calibration_cpu_s"], t["this"]["calibration_cpu_s"]))
    sv = r["service"]
    row("service", "`serve`, single fingerprints, 8 keep-alive clients: req/s, p99, server CPU per request",
        f"{sv['base']['rps']:,.0f} /s, {sv['base']['p99_ms']:.1f} ms, {sv['base']['server_cpu_us_per_req']:,.0f} µs",
        f"{sv['this']['rps']:,.0f} /s, {sv['this']['p99_ms']:.1f} ms, {sv['this']['server_cpu_us_per_req']:,.0f} µs",
        f"×{sv['this']['rps'] / sv['base']['rps']:.1f} req/s")
    lines.append("")
    lines.append(f"{r['date']}; load average before {r['load_before']}, after {r['load_after']}; baseline {r['baseline']}.")
    return "\n".join(lines)
