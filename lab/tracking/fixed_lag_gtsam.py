#!/usr/bin/env python3
"""GTSAM's fixed-lag smoothers vs graphslam's own, on the filter papers' cart (same model, same data).

The question: build the online tracker on ``gtsam.BatchFixedLagSmoother`` /
``gtsam.IncrementalFixedLagSmoother`` or on our own sliding-window MAP
(``graphslam.core.tracking.fixed_lag``)? Both are run here on the cart experiment of
``python -m lab.bench filters`` (Paper 000's EKF model: Q, R, x0, P0, path loss; seeds as given),
reporting each epoch's estimate right after its update (lag 0) with a window of ``--window`` s,
Gaussian losses on both sides. GTSAM has no native factor for the papers' RSSI (eq. 6) and
velocity (eq. 4) readings nor for the process x' = F x, so they are ``gtsam.CustomFactor``s:
Python callbacks inside the optimiser (docs/benchmarks.md measures what that costs).

    python lab/tracking/fixed_lag_gtsam.py [--seeds 0-4] [--window 40]

One JSON line per smoother: RMS x / y (m) mean over seeds, seconds per run (median), and the
largest difference of its estimates from ours (m).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from functools import partial

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from graphslam import (
    CartNoise, Epochs, fixed_lag_smooth, FixedLagConfig, FusionModel, limit_blas_threads, PAPER_P0, PAPER_X0,
    simulate_cart, velocity_matrix,
)



def _process(F: np.ndarray, this: gtsam.CustomFactor, v: gtsam.Values, H: list | None) -> np.ndarray:
    k0, k1 = this.keys()
    a, b = v.atVector(k0), v.atVector(k1)
    if H is not None:
        H[0], H[1] = -F, np.eye(len(a))
    return b - F @ a


def _velocity(y: np.ndarray, M: np.ndarray, this: gtsam.CustomFactor, v: gtsam.Values, H: list | None) -> np.ndarray:
    x = v.atVector(this.keys()[0])
    if H is not None:
        J = np.zeros((2, len(x)))
        J[:, 2:4], J[:, 4:6] = M, np.eye(2)
        H[0] = J
    return M @ x[2:4] + x[4:6] - y


def _rssi(y: float, ap: int, model: FusionModel, this: gtsam.CustomFactor, v: gtsam.Values, H: list | None) -> np.ndarray:
    x = v.atVector(this.keys()[0])
    h, g = model.path_loss.rss_pairs(x[None, 0:2], np.array([ap]))
    if H is not None:
        J = np.zeros((1, len(x)))
        J[0, 0:2] = g[0]
        H[0] = J
    return np.array([h[0] - y])


def run_gtsam(kind: str, model: FusionModel, epochs: Epochs, window_s: float) -> np.ndarray:
    """Epoch k's estimate right after its update (lag 0), window ``window_s`` s."""
    smoother = gtsam.BatchFixedLagSmoother(window_s) if kind == "batch" else gtsam.IncrementalFixedLagSmoother(window_s)
    M = velocity_matrix(model.theta_rad)
    sv = gtsam.noiseModel.Diagonal.Sigmas(np.sqrt(model.r_velocity))
    sr = [gtsam.noiseModel.Isotropic.Sigma(1, float(np.sqrt(r))) for r in model.r_rssi]
    out = np.zeros((len(epochs), model.n))
    x = np.asarray(PAPER_X0, float)
    for k in range(len(epochs)):
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if k == 0:
            graph.add(gtsam.PriorFactorVector(X(0), x, gtsam.noiseModel.Gaussian.Covariance(PAPER_P0)))
        else:
            dt = float(epochs.t_s[k] - epochs.t_s[k - 1])
            F = model.transition(dt)
            sq = gtsam.noiseModel.Diagonal.Sigmas(np.sqrt(model.q_diag * dt / model.period_s))
            graph.add(gtsam.CustomFactor(sq, [X(k - 1), X(k)], partial(_process, F)))
            x = F @ x
        values.insert(X(k), x)
        for i in np.flatnonzero(epochs.vel_k == k):
            graph.add(gtsam.CustomFactor(sv, [X(k)], partial(_velocity, epochs.vel_y[i], M)))
        for i in np.flatnonzero(epochs.rss_k == k):
            a = int(epochs.rss_ap[i])
            graph.add(gtsam.CustomFactor(sr[a], [X(k)], partial(_rssi, float(epochs.rss_y[i]), a, model)))
        smoother.update(graph, values, {X(k): float(epochs.t_s[k])})
        x = smoother.calculateEstimateVector(X(k))
        out[k] = x
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0-4", help="e.g. 0-4 or 0,3,7")
    ap.add_argument("--window", type=float, default=40.0, help="window (GTSAM: smoother lag), s")
    args = ap.parse_args()
    a, _, b = args.seeds.partition("-")
    seeds = list(range(int(a), int(b) + 1)) if b else [int(s) for s in args.seeds.split(",")]
    limit_blas_threads(1)
    model = FusionModel.paper_ekf()
    rows: dict[str, dict[str, list]] = {n: {"rx": [], "ry": [], "s": [], "diff": []} for n in ("graphslam", "batch", "incremental")}
    for seed in seeds:
        run = simulate_cart(seed, path_loss=model.path_loss, noise=CartNoise())
        epochs = Epochs.fixed_rate(run.y_velocity, run.y_rssi, run.period_s)
        t0 = time.perf_counter()
        ours = fixed_lag_smooth(
            model, [PAPER_X0], PAPER_P0, epochs, FixedLagConfig(lag_s=0.0, window_s=args.window, huber_k=None, prune_cost=None, adaptive_rssi=False, report="best")
        ).x
        ests = {"graphslam": (ours, time.perf_counter() - t0)}
        for kind in ("batch", "incremental"):
            t0 = time.perf_counter()
            ests[kind] = (run_gtsam(kind, model, epochs, args.window), time.perf_counter() - t0)
        for name, (est, secs) in ests.items():
            e = est[:, :2] - run.xy
            r = rows[name]
            r["rx"].append(float(np.sqrt(np.mean(e[:, 0] ** 2))))
            r["ry"].append(float(np.sqrt(np.mean(e[:, 1] ** 2))))
            r["s"].append(secs)
            r["diff"].append(float(np.abs(est[:, :2] - ours[:, :2]).max()))
    for name, r in rows.items():
        print(json.dumps({
            "smoother": name, "seeds": seeds, "window_s": args.window,
            "rms_x_mean_m": round(float(np.mean(r["rx"])), 3), "rms_y_mean_m": round(float(np.mean(r["ry"])), 3),
            "seconds_per_run_median": round(statistics.median(r["s"]), 2),
            "max_diff_from_graphslam_m": round(max(r["diff"]), 4),
        }))
    return 0


if __name__ == "__main__":
    sys.exit(main())
