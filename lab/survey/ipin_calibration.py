#!/usr/bin/env python3
"""Can the similarity -> distance table be calibrated from a placement instead of the truth?

A diagnostic of the IPIN floor; ground truth used only to perturb and to score. Every route of the floor
is moved rigidly about its centroid by a random SE(2) (``--perturb-m``, ``--perturb-deg``: the
standard deviations) -- a stand-in for a placement that is that far off. Tables built from that
placement:

- ``rough``: cross-walk pairs at the placement's distances, 0-60 m against >= 60 m;
- ``hybrid``: the same far rows, near rows (< 16 m) from pairs within walks at their PDR
  distance (no truth at all), against the placement's >= 60 m reference;
- ``oracle``: cross-walk pairs at true distance (the bound).

Each route is then registered onto all other routes at their TRUE positions (leave-route-out,
``lab/survey/ipin_diagnostics.py`` experiment 5) with the Manhattan prior from the PDR axes; one JSON
line per perturbation seed with every route's error and the mean.

    python lab/survey/ipin_calibration.py ../shared/data/ipin2023/b100_f-2 --perturb-m 5 --perturb-deg 5 --seeds 0
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import ipin_diagnostics as D  # noqa: E402  (the diagnostics' loading, tables and SE(2) search)


def perturbed_positions(f: D.Floor, sigma_m: float, sigma_deg: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    xy = f.xy.copy()
    sr = f.scan_route
    for r in f.routes:
        m = sr == r
        c = xy[m].mean(0)
        th = rng.normal(0.0, np.radians(sigma_deg))
        R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
        xy[m] = (xy[m] - c) @ R.T + c + rng.normal(0.0, sigma_m, 2)
    return xy


def cross_histogram(f: D.Floor, xy: np.ndarray) -> np.ndarray:
    """(distance bin, similarity bin) counts of pairs of different walks at distances in ``xy``."""
    nd = int(D.D_MAX_M / D.D_FINE_M) + 1
    H = np.zeros((nd, D.S_FINE))
    for b in D.row_blocks(f.n, f.n):
        S = D.sim_block(f.E, b)
        si = np.clip((S * D.S_FINE).astype(int), 0, D.S_FINE - 1)
        upper = np.arange(f.n)[None] > np.arange(f.n)[b][:, None]
        m = (f.walk[b][:, None] != f.walk[None]) & upper
        di = np.minimum(D.cross_dist(xy[b], xy) / D.D_FINE_M, nd - 1).astype(int)
        H += np.bincount(di[m] * D.S_FINE + si[m], minlength=nd * D.S_FINE).reshape(nd, D.S_FINE)
    return H


def band(h: np.ndarray, lo: float, hi: float) -> np.ndarray:
    return h[int(lo / D.D_FINE_M): int(hi / D.D_FINE_M)].sum(0)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("floor", nargs="?", default="../shared/data/ipin2023/b100_f-2", type=Path)
    ap.add_argument("--perturb-m", type=float, default=5.0)
    ap.add_argument("--perturb-deg", type=float, default=5.0)
    ap.add_argument("--seeds", default="0", help="comma-separated perturbation seeds")
    a = ap.parse_args()
    try:
        seeds = [int(s) for s in a.seeds.split(",") if s.strip()]
        f = D.load(a.floor)
    except (ValueError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    intra = D.pair_histograms(f)["intra_dt10"]
    oracle = D.likelihood_tables(D.pair_histograms(f))["oracle"]
    sr = f.scan_route
    matches = D.top_matches(f, sr, 5)
    # the seven walked routes; the stair/lift parts (3-25 m walks) have no PDR axis to speak of
    length = np.array([np.linalg.norm(np.diff(s, axis=0), axis=1).sum() for s in f.steps])
    routes = [r for r in f.routes if np.median(length[f.route == r]) > 30.0]
    for seed in seeds:
        t = time.perf_counter()
        H = cross_histogram(f, perturbed_positions(f, a.perturb_m, a.perturb_deg, seed))
        ref = band(H, 60, D.D_MAX_M + 1)
        rough = D.llr_table(H, ref, 60.0)
        hybrid = rough.copy()
        near = D.llr_table(intra, ref, 16.0)
        hybrid[: near.shape[0]] = near
        tables = {"oracle": oracle, "rough": rough, "hybrid": hybrid}
        kernels = {n: D.table_kernels(L) for n, L in tables.items()}
        errs: dict[str, dict[str, float]] = {n: {} for n in tables}
        for r in routes:
            B, A = np.flatnonzero(sr == r), np.flatnonzero(sr != r)
            out = D.register_routes(f, B, A, tables, kernels, matches, with_ap=False)
            for n in tables:
                errs[n][str(r)] = out[f"composite_{n}"]["mod90_pdr_axes"]["err_m"]
        print(json.dumps({
            "perturb_m": a.perturb_m, "perturb_deg": a.perturb_deg, "seed": seed,
            "route_err_m": errs, "mean_err_m": {n: round(float(np.mean(list(v.values()))), 2) for n, v in errs.items()},
            "routes_within_5m": {n: int(sum(e <= 5 for e in v.values())) for n, v in errs.items()},
            "seconds": round(time.perf_counter() - t, 1),
        }), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
