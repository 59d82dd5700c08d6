#!/usr/bin/env python3
"""How well could any ONLINE estimator do on the simulated cart? The posterior given the data so far.

The target: the fixed-lag smoother (lag <= 2 s) meeting Paper 000's RMS (x <= 0.86 m) on the
simulated cart. The cart's epochs are T = 4 s apart, so a 2-s lag holds no later epoch: the
estimate of epoch k can use the readings of epochs 0..k only. This script computes, for each
seed of ``python -m lab.bench filters`` (same simulation, the papers' EKF model, x0, P0, Q, R), at
every ``--every``-th epoch k:

- ``online_map``: the maximum a-posteriori trajectory of epochs 0..k (the whole history, nothing
  marginalised) by sparse Levenberg-Marquardt from the EKF's and the RTS trajectories of that
  data and the four best dead-reckoning paths (``smoother.smooth(..., "map")``'s starts: no
  truth), lowest cost kept; its epoch-k state is scored;
- ``online_mmse``: the mean of the distinct local minima found, weighted by exp(-cost / 2)
  (a Gaussian-sum posterior mean: what reporting the bank's mixture would give);
- ``whole_run_map``: the same MAP given the whole run (offline), at the same epochs.

If ``online_map`` misses the target where ``whole_run_map`` meets it, the information that fixes
the error arrives later than the lag allows: no estimator reporting the posterior of the data so
far can meet it under this model. ~7 s per seed at ``--every 10``.

    python lab/tracking/cart_online_bound.py [--seeds 0-19] [--every 10] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from graphslam import (
    CartNoise, dead_reckoning_starts, Epochs, FusionModel, make_filter,
    map_levenberg_marquardt as levenberg_marquardt, MapProblem, PAPER_P0, PAPER_RMS_TARGETS_M, PAPER_X0,
    rts_smooth, run_epochs, simulate_cart,
)



def _upto(e: Epochs, j: int) -> Epochs:
    """The readings of epochs 0..j-1."""
    v, r, f = e.vel_k < j, e.rss_k < j, e.fix_k < j
    return Epochs(e.t_s[:j], e.vel_k[v], e.vel_y[v], e.rss_k[r], e.rss_ap[r], e.rss_y[r], e.fix_k[f], e.fix_xy[f],
                  e.fix_sigma[f], e.rss_scale[r])


def _minima(model: FusionModel, e: Epochs) -> tuple[list[np.ndarray], np.ndarray]:
    """Local minima of the MAP cost of ``e`` from the product's starts (duplicates merged)."""
    problem = MapProblem(model, PAPER_X0, PAPER_P0, e)
    filt = run_epochs(make_filter("ekf", model), PAPER_X0, PAPER_P0, e)
    xs, cs = [], []
    for start in (filt.x, rts_smooth(model, filt, e).x, *dead_reckoning_starts(problem)):
        X, c, _ = levenberg_marquardt(problem, start, 100)
        if not any(np.abs(X - Y).max() < 1e-3 for Y in xs):
            xs.append(X)
            cs.append(c)
    return xs, np.array(cs)


def _seeds(text: str) -> list[int]:
    if "-" in text and "," not in text:
        a, b = text.split("-")
        return list(range(int(a), int(b) + 1))
    return [int(x) for x in text.split(",")]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0-19")
    ap.add_argument("--every", type=int, default=10, help="score every this many epochs")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    model = FusionModel.paper_ekf()
    tx, ty = PAPER_RMS_TARGETS_M["ekf"]
    rows = []
    for seed in _seeds(args.seeds):
        run = simulate_cart(seed, path_loss=model.path_loss, noise=CartNoise())
        E = Epochs.fixed_rate(run.y_velocity, run.y_rssi, run.period_s)
        ks = np.arange(args.every, len(E) + 1, args.every) - 1
        whole_x, whole_c = _minima(model, E)
        whole = whole_x[int(np.argmin(whole_c))]
        err = {"online_map": [], "online_mmse": [], "whole_run_map": []}
        for k in ks:
            xs, cs = _minima(model, _upto(E, k + 1))
            w = np.exp(-0.5 * (cs - cs.min()))
            w /= w.sum()
            err["online_map"].append(xs[int(np.argmin(cs))][k, :2] - run.xy[k])
            err["online_mmse"].append(sum(wi * X[k, :2] for wi, X in zip(w, xs)) - run.xy[k])
            err["whole_run_map"].append(whole[k, :2] - run.xy[k])
        row = {"seed": seed, **{name: np.sqrt(np.mean(np.square(v), axis=0)).round(3).tolist() for name, v in err.items()}}
        rows.append(row)
        print(json.dumps(row), flush=True)
    out = {"seeds": [r["seed"] for r in rows], "every": args.every, "target_m": [tx, ty]}
    for name in ("online_map", "online_mmse", "whole_run_map"):
        a = np.array([r[name] for r in rows])
        out[name] = {"mean_x_y_m": a.mean(axis=0).round(3).tolist(), "median_x_y_m": np.median(a, axis=0).round(3).tolist(),
                     "seeds_meeting": int(((a[:, 0] <= tx) & (a[:, 1] <= ty)).sum())}
    print(json.dumps(out))
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump({"summary": out, "per_seed": rows}, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
