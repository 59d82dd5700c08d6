#!/usr/bin/env python3
"""Fingerprint distances for kNN side by side on real floors (why ``KnnConfig.metric="sorensen"``).

Every scan of the held-out walks located among the training walks' scans (the folds of
``bench tracking-real``: leave one route out on IPIN, 5 seeded folds on ILC), the map built from
the training walks' PDR tracks placed by a rigid fit to their own landmarks (as the oracle map;
ground truth builds the map and scores, nothing is tuned on it here). Mean scan error (m), k = 1 / 3 / 5,
inverse-distance weights. Representations (Torres-Sospedra et al. 2015): ``shifted`` (RSS + 110,
the paper's eq. 9), ``positive`` (RSS - min + 1), ``powed`` (positive / its range) ** e; distances:
eq. 9, Euclidean, Sørensen, cosine. Dense over the floor's APs (a floor, not a survey: ~2,400 x 2,400).

    python lab/radiomap/knn_metrics.py FOLDER [route|FOLDS]
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from graphslam import fit_se2, held_out_folds, interpolate_xy, read_survey, se2_apply, walk_landmarks

MIN_DBM = -100.0  # readings below are dropped (the radio map's min_rssi_dbm)


def _eq9(q, d, hq, hd):
    sq = (q**2).sum(1)[:, None] + (d**2).sum(1)[None] - 2 * q @ d.T
    n = hq.sum(1)[:, None] + hd.sum(1)[None] - hq.astype(float) @ hd.T.astype(float)
    return np.sqrt(np.maximum(sq, 0) / np.maximum(n, 1))


def _euclid(q, d, hq, hd):
    return np.sqrt(np.maximum((q**2).sum(1)[:, None] + (d**2).sum(1)[None] - 2 * q @ d.T, 0))


def _sorensen(q, d, hq, hd):
    return np.abs(q[:, None, :] - d[None]).sum(-1) / (q.sum(1)[:, None] + d.sum(1)[None])


def _cosine(q, d, hq, hd):
    return 1 - (q @ d.T) / (np.linalg.norm(q, axis=1)[:, None] * np.linalg.norm(d, axis=1)[None] + 1e-12)


def main(argv: list[str]) -> int:
    if not argv:
        print(__doc__, file=sys.stderr)
        return 2
    folder, folds = Path(argv[0]), (argv[1] if len(argv) > 1 else "5")
    walks = [w for w in read_survey([folder]) if len(w.landmarks) >= 2 and len(w.scans) and len(w.steps) >= 2]
    bss = sorted({b for w in walks for sc in w.scans for b in sc.readings})
    col = {b: i for i, b in enumerate(bss)}
    rssi, xy, walk = [], [], []
    for wi, w in enumerate(walks):
        t, marks = walk_landmarks(w)
        xy.append(se2_apply(fit_se2(interpolate_xy(w.steps, t), marks),
                            interpolate_xy(w.steps, np.array([sc.t_ns for sc in w.scans], float))))
        for sc in w.scans:
            r = np.full(len(bss), np.nan)
            for b, v in sc.readings.items():
                if v >= MIN_DBM:
                    r[col[b]] = v
            rssi.append(r)
        walk += [wi] * len(w.scans)
    R, XY, W = np.array(rssi), np.concatenate(xy), np.array(walk)
    heard = np.isfinite(R)
    positive = np.where(heard, R - MIN_DBM + 1, 0.0)
    variants = {
        "eq9 on shifted (the paper)": (np.where(heard, R + 110.0, 0.0), _eq9),
        "Euclidean on positive": (positive, _euclid),
        "Euclidean on powed": ((positive / (-MIN_DBM + 1)) ** np.e, _euclid),
        "Sorensen on positive": (positive, _sorensen),
        "Sorensen on powed": ((positive / (-MIN_DBM + 1)) ** np.e, _sorensen),
        "cosine on powed": ((positive / (-MIN_DBM + 1)) ** np.e, _cosine),
    }
    ks = (1, 3, 5)
    errs: dict[str, dict[int, list]] = {v: {k: [] for k in ks} for v in variants}
    for _, test in held_out_folds(walks, None if folds == "route" else int(folds), 0):
        te = np.isin(W, test)
        tr = ~te
        for name, (X, dist) in variants.items():
            D = np.concatenate([dist(X[te][i:i + 200], X[tr], heard[te][i:i + 200], heard[tr])
                                for i in range(0, int(te.sum()), 200)])
            order = np.argsort(D, axis=1, kind="stable")
            for k in ks:
                idx = order[:, :k]
                w = 1 / (np.take_along_axis(D, idx, 1) + 1e-6)
                est = (w[..., None] * XY[tr][idx]).sum(1) / w.sum(1)[:, None]
                errs[name][k].append(np.linalg.norm(est - XY[te], axis=1))
    print(f"{folder.name}: {len(R)} scans, {len(bss)} APs; mean scan error (m)")
    for name in variants:
        print(f"  {name:28s} " + "  ".join(f"k={k}: {np.concatenate(errs[name][k]).mean():.3f}" for k in ks))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
