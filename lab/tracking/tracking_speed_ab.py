#!/usr/bin/env python3
"""A/B of the tracker's speed: a baseline copy of the package vs this one, alternately, in one run.

Why: on this 2-core machine, shared with other jobs, wall-clock figures swing by tens of percent
from one run to the next. Here both versions track the same walks on the same radio map, one
after the other, ``--rounds`` times (ABAB...), each side in its own process (so the baseline can
be any version: ``git archive REV | tar -x -C /tmp/base``), and the paired ratios are reported
with the CPU time (which other jobs change far less than the wall time).

Per side and round: the self-calibration (``Tracker.on_map`` with it, minus without it), then
every walk tracked with ``graphslam track``'s defaults (the fixed-lag tracker) under that
calibration; ms per step (CPU and wall, all walks) and the calibration's seconds. At the end the
medians, the per-round ratios baseline / this, and the largest position difference between the
two sides' tracks and calibrations.

    git archive HEAD~3 | tar -x -C /tmp/base
    python lab/tracking/tracking_speed_ab.py --baseline /tmp/base RADIO_MAP WALK_OR_FOLDER... [--rounds 3]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

# What each side runs (its own package first on the path); public API only.
CHILD = r"""
import json, sys, time
import numpy as np
from graphslam import ApModels, TrackConfig, Tracker, limit_blas_threads, read_radio_map, read_survey

limit_blas_threads(1)  # as graphslam track does
radio_map, out, walks = sys.argv[1], sys.argv[2], sys.argv[3:]
rm = read_radio_map(radio_map)
models = ApModels.fit(rm)
survey = read_survey(walks)
cfg = TrackConfig()
t0, c0 = time.perf_counter(), time.process_time()
tracker = Tracker.on_map(rm, models, cfg)
t1, c1 = time.perf_counter(), time.process_time()
Tracker.on_map(rm, models, cfg.updated({"calibration.enabled": False}))
t2, c2 = time.perf_counter(), time.process_time()
steps, tracks = 0, {}
t3, c3 = time.perf_counter(), time.process_time()
for s in survey.sessions:
    tr = tracker.track(s)
    tracks[s.session_id] = tr.xy
    steps += len(tr.t_ns)
t4, c4 = time.perf_counter(), time.process_time()
np.savez(out, **tracks)
cal = tracker.calibration
print(json.dumps({
    "steps": steps, "track_cpu_ms_per_step": (c4 - c3) / steps * 1e3, "track_wall_ms_per_step": (t4 - t3) / steps * 1e3,
    "calibration_cpu_s": (c1 - c0) - (c2 - c1), "calibration_wall_s": (t1 - t0) - (t2 - t1),
    "calibration": None if cal is None else [
        cal.rssi_variance_factor, cal.fix_sigma_floor_m, cal.covariance_scale, cal.bank_temper],
}))
"""


def run_side(package: Path, radio_map: str, walks: list[str], out: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=str(package), OPENBLAS_NUM_THREADS="1")
    res = subprocess.run([sys.executable, "-c", CHILD, radio_map, str(out), *walks], env=env, capture_output=True,
                         text=True, check=True, cwd=tempfile.gettempdir())
    return json.loads(res.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--baseline", required=True, help="directory holding a baseline copy of the package (graphslam/)")
    ap.add_argument("radio_map")
    ap.add_argument("walks", nargs="+", help="MCAP walks or folders of them")
    ap.add_argument("--rounds", type=int, default=3)
    a = ap.parse_args()
    this = Path(__file__).resolve().parents[2]
    sides = {"baseline": Path(a.baseline).resolve(), "this": this}
    rows: dict[str, list[dict]] = {k: [] for k in sides}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(a.rounds):
            for name, pkg in sides.items():
                res = run_side(pkg, a.radio_map, a.walks, Path(tmp) / f"{name}.npz")
                res["load"] = os.getloadavg()[0]
                rows[name].append(res)
                print(f"round {r} {name}: track {res['track_cpu_ms_per_step']:.2f} ms/step cpu "
                      f"({res['track_wall_ms_per_step']:.2f} wall), calibration {res['calibration_cpu_s']:.2f} s cpu "
                      f"({res['calibration_wall_s']:.2f} wall), load {res['load']:.1f}", flush=True)
        tracks = {k: np.load(Path(tmp) / f"{k}.npz") for k in sides}
        d = np.concatenate([np.linalg.norm(tracks["baseline"][s] - tracks["this"][s], axis=1) for s in tracks["this"].files])
    med = {k: {m: float(np.median([x[m] for x in v])) for m in
               ("track_cpu_ms_per_step", "track_wall_ms_per_step", "calibration_cpu_s", "calibration_wall_s")}
           for k, v in rows.items()}
    ratio = {m: [round(b[m] / t[m], 2) for b, t in zip(rows["baseline"], rows["this"])]
             for m in ("track_cpu_ms_per_step", "calibration_cpu_s")}
    print(json.dumps({
        "steps": rows["this"][0]["steps"], "median": med, "ratio_baseline_over_this": ratio,
        "position_difference_m": {"max": round(float(d.max()), 4), "mean": round(float(d.mean()), 5)},
        "calibration": {k: v[0]["calibration"] for k, v in rows.items()},
        "load": [round(x["load"], 1) for v in rows.values() for x in v],
    }, indent=1))


if __name__ == "__main__":
    main()
