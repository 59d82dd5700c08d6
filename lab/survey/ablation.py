#!/usr/bin/env python
"""Ablation of the alignment defaults on the simulator (accuracy and solve time per variant).

Usage: python lab/survey/ablation.py [--scenario paper] [--seeds 0,1,2]
Prints one JSON line per variant: mean over seeds of landmark mean/max error, heading
error, LM iterations and alignment time. Each variant changes the defaults as named.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from graphslam import align, evaluate, load_config, simulate

VARIANTS: dict[str, dict] = {
    "defaults": {},
    "paper literal (d_min 2, e_max 1, Omega_IMU diag(1,1,20), all edges)": {
        "wifi": {"d_min_m": 2.0, "e_max": 1.0},
        "imu": {"sigma_xy_m": 1.0, "sigma_heading_rad": 0.2236},
        "edges": {"max_per_fingerprint": 0},
    },
    "FINDINGS weights (d_min 2, e_max 0.3, sigma 0.05 m / 0.01 rad)": {
        "wifi": {"d_min_m": 2.0, "e_max": 0.3},
        "imu": {"sigma_heading_rad": 0.01},
    },
    "d_min 2 m (paper)": {"wifi": {"d_min_m": 2.0}},
    "e_max 0.3": {"wifi": {"e_max": 0.3}},
    "sigma_heading 0.01 rad": {"imu": {"sigma_heading_rad": 0.01}},
    "all edges below threshold (paper, no cap)": {"edges": {"max_per_fingerprint": 0}},
    "10 partners per fingerprint": {"edges": {"max_per_fingerprint": 10}},
    "origin start (paper eq. 2)": {"optimizer": {"initialization": "origin"}},
    "no chain compression": {"optimizer": {"compress_chains": False}},
    "one stage (no graduated saturation)": {"optimizer": {"outer_iterations": 1}},
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenario", default="paper")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--only", default=None, help="substring of the variant names to run")
    args = ap.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    surveys = {s: simulate(args.scenario, seed=s).survey for s in seeds}
    for name, override in VARIANTS.items():
        if args.only and args.only not in name:
            continue
        cfg = load_config(None, override)
        rows = []
        for s in seeds:
            t = time.perf_counter()
            al = align(surveys[s], cfg)
            dt = time.perf_counter() - t
            ev = evaluate(al.tracks, surveys[s])
            rows.append((ev.landmarks.mean_m, ev.landmarks.max_m, ev.heading_mean_deg, len(al.iterations), dt, len(al.edges)))
        r = np.array(rows)
        print(
            json.dumps(
                {
                    "variant": name,
                    "scenario": args.scenario,
                    "seeds": seeds,
                    "landmark_mean_m": round(float(r[:, 0].mean()), 3),
                    "landmark_max_m_worst": round(float(r[:, 1].max()), 3),
                    "heading_mean_deg": round(float(r[:, 2].mean()), 3),
                    "lm_iterations": round(float(r[:, 3].mean()), 1),
                    "align_s_median": round(float(np.median(r[:, 4])), 2),
                    "wifi_edges": int(r[:, 5].mean()),
                }
            ),
            flush=True,
        )


if __name__ == "__main__":
    main()
