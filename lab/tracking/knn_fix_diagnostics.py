#!/usr/bin/env python3
"""Two diagnostics of kNN fixes on a real floor (evaluation only; nothing here reaches a tracker).

1. How slowly do kNN fix errors change along a walk? The map (every walk placed by its rigid
   fit to its own landmarks, ``tracking_bench.oracle_radio_map``) locates each fingerprint among
   the OTHER walks' (leave one session out, k = 3, as ``calibration.leave_one_session_out_errors``);
   the autocorrelation of the error vectors between fingerprints 1, 2, 3, 5 scans apart in the
   same walk, and their median time apart.
2. How much would knowing roughly where the walker is help kNN? For the held-out walks of seeded
   fold 0 (map of the other walks), the k = 3 best matches among the 40 best *within R m of the
   true position* (the truth is the condition: an upper bound, not a method), R = 5, 10, 15 m, vs
   plain kNN at the scan times.

    python lab/tracking/knn_fix_diagnostics.py FOLDER [FOLDER ...]
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from graphslam import (
    fit_se2, held_out_folds, interpolate_xy, KnnConfig, KnnLocator, leave_one_session_out_error_vectors,
    oracle_radio_map, read_survey, se2_apply, walk_landmarks, WEIGHT_EPS_DB,
)



def _weighted(xy: np.ndarray, d: np.ndarray) -> np.ndarray:
    w = 1.0 / (d + WEIGHT_EPS_DB)
    return (w[:, None] * xy).sum(axis=0) / w.sum()


def autocorrelation(walks: list, k: int = 3, extra: int = 30) -> None:
    rm = oracle_radio_map(walks)
    e = leave_one_session_out_error_vectors(rm, k=k, extra=extra)
    order = np.lexsort((rm.t_ns, rm.session_ids))
    e, sid, t = e[order], rm.session_ids[order], rm.t_ns[order]
    finite = np.isfinite(e).all(axis=1)
    mu = e[finite].mean(axis=0)
    var = ((e[finite] - mu) ** 2).sum(axis=1).mean()
    for lag in (1, 2, 3, 5):
        g = (sid[lag:] == sid[:-lag]) & finite[lag:] & finite[:-lag]
        rho = float((((e[:-lag] - mu) * (e[lag:] - mu)).sum(axis=1))[g].mean() / var)
        dt = float(np.median((t[lag:] - t[:-lag])[g]) / 1e9)
        print(f"  fix-error autocorrelation, {lag} scan(s) apart (median {dt:.1f} s): {rho:.3f}")


def conditioned_knn(walks: list) -> None:
    _, test = held_out_folds(walks, 5, 0)[0]
    rm = oracle_radio_map([w for i, w in enumerate(walks) if i not in set(test)])
    loc = KnnLocator(rm, KnnConfig(k=40, metric="eq9", index="exact"))
    rows = []  # (candidate positions, distances, truth) per scan
    for i in test:
        w = walks[i]
        t, marks = walk_landmarks(w)
        truth = se2_apply(fit_se2(interpolate_xy(w.steps, t), marks),
                          interpolate_xy(w.steps, np.array([sc.t_ns for sc in w.scans], float)))
        res = loc.locate([sc.readings for sc in w.scans])
        for q in range(len(truth)):
            ok = res.neighbours[q] >= 0
            if ok.any():
                rows.append((rm.xy[res.neighbours[q][ok]], res.distances[q][ok], truth[q]))
    plain = np.mean([np.linalg.norm(_weighted(p[:3], d[:3]) - x) for p, d, x in rows])
    print(f"  fold 0, {len(rows)} scans: plain kNN {plain:.2f} m")
    for R in (5.0, 10.0, 15.0):
        errs = []
        for p, d, x in rows:
            near = np.flatnonzero(np.linalg.norm(p - x, axis=1) <= R)[:3]
            sel = near if len(near) else np.arange(min(3, len(p)))
            errs.append(np.linalg.norm(_weighted(p[sel], d[sel]) - x))
        print(f"  kNN among matches within {R:g} m of the truth: {np.mean(errs):.2f} m")


def main(argv: list[str]) -> int:
    if not argv:
        print(__doc__, file=sys.stderr)
        return 2
    for folder in map(Path, argv):
        walks = [w for w in read_survey([folder]) if len(w.landmarks) >= 2 and len(w.scans) and len(w.steps) >= 2]
        print(folder.name)
        autocorrelation(walks)
        conditioned_knn(walks)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
