"""The reference map's time cost at scale, on the simulator: a scenario's walks split into a
"professional" survey (every ``--every``-th walk's scans at their true positions, the reference CSV a
site would have: truth builds the reference only) and the crowd (the other walks); ``graphslam
survey`` of the crowd with and without ``--reference-map``, whole processes alternating, medians of
wall time, and the main map and landmark mean of each.

    python lab/survey/reference_scale.py --scenario paper --size 4 --rounds 3 [--every 5] [--out DIR]
"""

from __future__ import annotations

import argparse
import csv
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from graphslam import simulate, write_session


def reference_csv(path: Path, sessions: list) -> int:
    """Every scan of ``sessions`` at its true position (the step nearest its time); returns the count."""
    n = 0
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["fingerprint_id", "x", "y", "bssid", "rssi_dbm"])
        for s in sessions:
            t = s.ground_truth.t_ns
            for k, sc in enumerate(s.scans):
                i = int(np.argmin(np.abs(t - sc.t_ns)))
                x, y = s.ground_truth.xy[i]
                for b, r in sc.readings.items():
                    w.writerow([f"{s.session_id}-{k}", f"{x:.3f}", f"{y:.3f}", b, r])
                n += 1
    return n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", default="paper")
    ap.add_argument("--size", type=float, default=4.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--every", type=int, default=5, help="every this-th walk makes the reference")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--out", type=Path, default=None, help="keep the data here (default: a temporary folder)")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = a.out or Path(tmp)
        sim = simulate(a.scenario, seed=a.seed, size=a.size)
        sessions = list(sim.survey)
        ref_walks = sessions[:: a.every]
        crowd = [s for k, s in enumerate(sessions) if k % a.every]
        (root / "crowd").mkdir(parents=True, exist_ok=True)
        files = [str(write_session(s, root / "crowd" / f"{s.session_id}.mcap")) for s in crowd]
        n_ref = reference_csv(root / "reference_map.csv", ref_walks)
        print(json.dumps({"scenario": a.scenario, "size": a.size, "seed": a.seed, "crowd_walks": len(crowd),
                          "reference_walks": len(ref_walks), "reference_fingerprints": n_ref}), flush=True)
        variants = {"crowd alone": [], "reference": ["--reference-map", str(root / "reference_map.csv")]}
        walls: dict[str, list[float]] = {k: [] for k in variants}
        for r in range(a.rounds):
            for name, extra in variants.items():
                out = root / f"out-{name.replace(' ', '_')}-{r}"
                t = time.perf_counter()
                subprocess.run([sys.executable, "-m", "graphslam", "-q", "survey", *files, "-o", str(out),
                                "--no-picture", *extra], check=True, stdout=subprocess.DEVNULL)
                walls[name].append(time.perf_counter() - t)
                if r == 0:
                    rep = json.loads((out / "report.json").read_text())
                    lm = (rep.get("evaluation") or {}).get("landmarks") or {}
                    print(json.dumps({"variant": name, "frame": rep.get("frame"),
                                      "main_map": rep["components"][0]["n_walks"] if rep.get("components") else 0,
                                      "landmark_mean_m": lm.get("mean_m"), "timings_s": {
                                          k: round(v, 2) for k, v in rep["timings_s"].items()
                                          if k in ("total", "align.initialise", "align.optimise", "write")}}), flush=True)
        med = {k: statistics.median(v) for k, v in walls.items()}
        print(json.dumps({"wall_s_median": {k: round(v, 2) for k, v in med.items()}, "rounds": a.rounds,
                          "reference_over_alone": round(med["reference"] / med["crowd alone"], 3)}), flush=True)


if __name__ == "__main__":
    main()
