"""sigma_m per score bin (Mondrian-style split calibration) from two truth-free calibration sets:
A = leave one walk out (the map has walked where the query is), B = the same walks located with
every map fingerprint within R m of their path removed (it has not). Per bin of the answer's score
(quantiles of A and B together), scale_b = the 95 % quantile of error / sqrt(spread^2 + 2^2);
sigma = scale_b * sqrt(spread^2 + 2^2). Compared with today's single scale (A only) and with the
score term of uncovered_calibration.py. Truth only scores the held-out walks.

python lab/radiomap/score_bins.py FLOOR route|FOLDS [R=5] [BINS=5] [WEIGHT_B=1]"""
import math
import sys

import numpy as np
from scipy.spatial import cKDTree

import graphslam as gs
from graphslam import KnnConfig, KnnLocator, RadioMap, held_out_folds, oracle_radio_map

R95 = math.sqrt(-2 * math.log(0.05))
FLOOR = 2.0


def sample(rm, seed=0, max_sessions=12, per=25):
    rng = np.random.default_rng(seed)
    ses = np.unique(rm.session_ids)
    if len(ses) > max_sessions:
        ses = np.sort(rng.choice(ses, max_sessions, replace=False))
    out = []
    for s in ses:
        own = rm.session_ids == s
        rows = np.flatnonzero(own)
        if len(rows) > per:
            rows = np.sort(rng.choice(rows, per, replace=False))
        out.append((own, rows))
    return out


def run(rm, rows, keep):
    others = RadioMap.from_fingerprints(rm.fingerprints.rows(keep), rm.xy[keep], session_ids=rm.session_ids[keep],
                                        t_ns=rm.t_ns[keep], frame=rm.frame, min_rssi_dbm=rm.min_rssi_dbm)
    res = KnnLocator(others, KnnConfig(index="exact"), threads=1).locate(others.reindex(rm.fingerprints.rows(rows)))
    ok = res.valid
    return np.linalg.norm(res.xy[ok] - rm.xy[rows[ok]], axis=1), res.spread[ok], res.score[ok]


def calibration_sets(rm, R):
    A, B = [], []
    for own, rows in sample(rm):
        keep = np.flatnonzero(~own)
        if len(keep) == 0:
            continue
        A.append(run(rm, rows, keep))
        d, _ = cKDTree(rm.xy[own]).query(rm.xy[keep])
        if (d > R).any():
            B.append(run(rm, rows, keep[d > R]))
    cat = lambda L: [np.concatenate(x) for x in zip(*L)]
    return cat(A), cat(B)


def bins_model(A, B, n_bins, weight_b):
    e = np.concatenate([A[0], B[0]])
    base = np.sqrt(np.concatenate([A[1], B[1]]) ** 2 + FLOOR ** 2)
    sc = np.concatenate([A[2], B[2]])
    w = np.concatenate([np.ones(len(A[0])), np.full(len(B[0]), weight_b)])
    edges = np.quantile(sc, np.linspace(0, 1, n_bins + 1)[1:-1])
    b = np.searchsorted(edges, sc)
    scales = []
    for k in range(n_bins):
        m = b == k
        r = e[m] / base[m]
        o = np.argsort(r)
        cw = np.cumsum(w[m][o]) / w[m].sum()
        scales.append(r[o][np.searchsorted(cw, 0.95)] / R95)
    return edges, np.maximum.accumulate(np.array(scales))  # not smaller for a worse score


folder = sys.argv[1]
folds = None if sys.argv[2] == "route" else int(sys.argv[2])
R = float(sys.argv[3]) if len(sys.argv) > 3 else 5.0
NB = int(sys.argv[4]) if len(sys.argv) > 4 else 5
WB = float(sys.argv[5]) if len(sys.argv) > 5 else 1.0
walks = [w for w in gs.read_survey([folder]) if len(w.landmarks) >= 2]
ins0, ins1, r0, r1, errs = [], [], [], [], []
for _, ti in held_out_folds(walks, folds, 0):
    tr = [w for i, w in enumerate(walks) if i not in set(ti)]
    te = [walks[i] for i in ti]
    rm = oracle_radio_map(tr)
    truth = oracle_radio_map(te).xy
    u = gs.calibrate_uncertainty(rm)
    A, B = calibration_sets(rm, R)
    edges, scales = bins_model(A, B, NB, WB)
    res = KnnLocator(rm, KnnConfig()).locate([dict(s.readings) for w in te for s in w.scans])
    ok = res.valid
    e = np.linalg.norm(res.xy[ok] - truth[ok], axis=1)
    base = np.sqrt(res.spread[ok] ** 2 + FLOOR ** 2)
    s0 = R95 * u.sigma(res.spread[ok])
    s1 = R95 * scales[np.searchsorted(edges, res.score[ok])] * base
    ins0.append(e <= s0); ins1.append(e <= s1); r0.append(s0); r1.append(s1); errs.append(e)
    print(f"  fold scales {np.round(scales, 2)} edges {np.round(edges, 3)}", flush=True)
c = np.concatenate
print(folder, sys.argv[2], f"R {R} bins {NB} wB {WB}: mean error {c(errs).mean():.2f} m; today coverage {c(ins0).mean():.3f} "
      f"median r95 {np.median(c(r0)):.2f} m; bins coverage {c(ins1).mean():.3f} median r95 {np.median(c(r1)):.2f} m")
