#!/usr/bin/env python3
"""What would averaging a walk's kNN fixes give with perfect odometry? (evaluation only)

The best case for a tracker: perfect odometry and a known heading, so that every kNN fix of a
walk measures one and the same unknown offset; the mean of the fixes so far then estimates it.
With the fix errors' real correlation along a walk, that average is far from the 1/sqrt(n) of
independent fixes. Measured on a real floor:

1. fix errors: every fingerprint of the map (each walk placed by its rigid fit to its own
   landmarks, ``tracking_bench.oracle_radio_map``) located among the OTHER walks' (leave one
   session out, k = 3, inverse-distance weights, as ``calibration.leave_one_session_out_errors``);
2. their correlation against the time between two fixes of one walk (pairs binned by seconds);
3. for every fix of every walk, the mean of the walk's fixes up to ``LAG`` s later: its RMS
   over the RMS of single fixes.

The ratio shows what a tracker's mean error against kNN's could be with ideal odometry (for
Gaussian-shaped errors mean and RMS scale alike); the gap to a tracker's figure is what its
odometry, the unknown heading and the start cost. (A generalised-least-squares average under
the binned correlation was tried: the binned estimate is not positive definite, and clipped it
gives unstable weights, e.g. +110 % on ILC F3; the plain mean is what is reported.)

    python lab/tracking/fix_average_bound.py FOLDER [LAG_S]
    python lab/tracking/fix_average_bound.py ../shared/data/ilc20/site1/B1 2
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from graphslam import leave_one_session_out_error_vectors, oracle_radio_map, read_survey

EDGES_S = np.array([0.0, 1.0, 3.0, 5.0, 7.0, 10.0, 15.0, 20.0, 30.0, 60.0, 120.0, 1e9])


def loso_errors(walks: list, k: int = 3, extra: int = 30) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N, 2) leave-one-session-out kNN error vectors (NaN where none), session ids, times (s)."""
    rm = oracle_radio_map(walks)
    return leave_one_session_out_error_vectors(rm, k=k, extra=extra), rm.session_ids, rm.t_ns / 1e9


def correlation_by_time(e: np.ndarray, sid: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per bin of EDGES_S: the fix errors' correlation (vector inner product over the variance)
    between fixes of one walk that far apart, and the pair count."""
    finite = np.isfinite(e).all(axis=1)
    mu = e[finite].mean(axis=0)
    var = ((e[finite] - mu) ** 2).sum(axis=1).mean()
    num = np.zeros(len(EDGES_S) - 1)
    cnt = np.zeros(len(EDGES_S) - 1)
    for s in np.unique(sid):
        i = np.flatnonzero((sid == s) & finite)
        if len(i) < 2:
            continue
        a, b = np.triu_indices(len(i), 1)
        dt = np.abs(t[i][a] - t[i][b])
        prod = ((e[i][a] - mu) * (e[i][b] - mu)).sum(axis=1)
        bins = np.searchsorted(EDGES_S, dt, side="right") - 1
        np.add.at(num, bins, prod)
        np.add.at(cnt, bins, 1)
    rho = np.where(cnt > 0, num / np.maximum(cnt, 1) / var, 0.0)
    return rho, cnt


def ideal_average(e: np.ndarray, sid: np.ndarray, t: np.ndarray, lag_s: float) -> float:
    """RMS of the mean of each walk's fixes up to ``lag_s`` s after each of its fixes, over the
    RMS of the single fixes."""
    finite = np.isfinite(e).all(axis=1)
    mu = e[finite].mean(axis=0)
    avg, one = [], []
    for s in np.unique(sid):
        i = np.flatnonzero((sid == s) & finite)
        i = i[np.argsort(t[i], kind="stable")]
        ts, es = t[i], e[i] - mu
        c = np.cumsum(es, axis=0)
        m = np.searchsorted(ts, ts + lag_s, side="right")  # fixes up to lag_s after each fix
        avg.append(c[m - 1] / m[:, None])
        one.append(es)
    rms = lambda v: float(np.sqrt((np.concatenate(v) ** 2).sum(axis=1).mean()))  # noqa: E731
    return rms(avg) / rms(one)


def main(argv: list[str]) -> int:
    if not argv:
        print(__doc__, file=sys.stderr)
        return 2
    folder, lag = Path(argv[0]), float(argv[1]) if len(argv) > 1 else 2.0
    walks = [w for w in read_survey([folder]) if len(w.landmarks) >= 2 and len(w.scans) and len(w.steps) >= 2]
    e, sid, t = loso_errors(walks)
    rho, cnt = correlation_by_time(e, sid, t)
    print(f"{folder.name}: {len(walks)} walks, {int(np.isfinite(e).all(axis=1).sum())} fixes")
    for a, b, r, c in zip(EDGES_S[:-1], EDGES_S[1:], rho, cnt):
        if c:
            print(f"  correlation of fix errors {a:g}-{b:g} s apart: {r:.3f} ({int(c)} pairs)")
    r = ideal_average(e, sid, t, lag)
    print(f"  mean of the walk's fixes up to {lag:g} s later (perfect odometry, known heading): "
          f"{100 * (r - 1):+.1f} % RMS vs single kNN fixes")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
