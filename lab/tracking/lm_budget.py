#!/usr/bin/env python3
"""The fixed-lag tracker's LM budget per window and the bank's merging: ms per step and the tracks'
departure from the first variant's (give the unmerged 1e-6:10 first), on the same map and walks, one run.

    python lab/tracking/lm_budget.py RADIO_MAP WALKS... [--variants 1e-6:10,1e-4:10,1e-6:3,1e-6:10:0.001]

(a third field: ``fixed_lag.merge_tol``; without it, no merging)

Self-calibration is off (the same model for every variant); each variant tracks every walk; the
figures: CPU ms per step and per variant the mean / max distance (m) of its positions from the
first variant's.
"""

from __future__ import annotations

import argparse
import functools
import json
import time

import numpy as np

from graphslam import ApModels, TrackConfig, Tracker, limit_blas_threads, read_radio_map, read_survey
from graphslam import tracking_pipeline as tracker_mod  # the tracker's module: its FixedLagConfig patched per variant


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("radio_map")
    ap.add_argument("walks", nargs="+")
    ap.add_argument("--variants", default="1e-6:10,1e-5:10,1e-4:10,1e-3:10,1e-6:4,1e-6:2")
    ap.add_argument("--rounds", type=int, default=1)
    a = ap.parse_args()
    limit_blas_threads(1)
    rm = read_radio_map(a.radio_map)
    models = ApModels.fit(rm)
    survey = read_survey(a.walks)
    cfg = TrackConfig().updated({"calibration.enabled": False})
    original = tracker_mod.FixedLagConfig
    ref: dict[str, np.ndarray] | None = None
    try:
        for spec in a.variants.split(","):
            tol, it, *merge = spec.split(":")
            extra = {"merge_tol": float(merge[0])} if merge else {}
            tracker_mod.FixedLagConfig = functools.partial(original, rel_tol=float(tol), max_iter=int(it))
            tracker = Tracker.on_map(rm, models, cfg.updated({"fixed_lag.merge_tol": extra.get("merge_tol")}))
            cpu, tracks = [], {}
            for _ in range(a.rounds):
                c0 = time.process_time()
                for s in survey.sessions:
                    tr = tracker.track(s)
                    tracks[s.session_id] = tr.xy
                cpu.append(time.process_time() - c0)
            steps = sum(len(v) for v in tracks.values())
            if ref is None:
                ref = tracks
            d = np.concatenate([np.linalg.norm(tracks[k] - ref[k], axis=1) for k in ref])
            print(json.dumps({"rel_tol": float(tol), "max_iter": int(it), **extra, "cpu_ms_per_step": round(min(cpu) / steps * 1e3, 2),
                              "diff_mean_m": round(float(d.mean()), 4), "diff_max_m": round(float(d.max()), 4)}), flush=True)
    finally:
        tracker_mod.FixedLagConfig = original


if __name__ == "__main__":
    main()
