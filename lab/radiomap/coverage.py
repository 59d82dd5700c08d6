"""The product's calibrated kNN uncertainty (graphslam.core.radiomap.uncertainty) on real floors'
oracle maps: 5 folds of walks; the map of the other folds is calibrated without truth
(calibrate_uncertainty: its walks left out one at a time), the held-out fold's scans are located and
scored against the truth (evaluation only). Prints mean error and the share of errors inside the
answers' 95 % circles (2.448 sigma_m).
python -m lab.radiomap.coverage FLOOR [FLOOR ...] [folds=5]"""
from __future__ import annotations

import math
import sys

import numpy as np

import graphslam as gs
from graphslam import KnnConfig, KnnLocator, calibrate_uncertainty, oracle_radio_map

R95 = math.sqrt(-2.0 * math.log(0.05))  # the 95 % circle's radius / sigma

kw = dict(a.split("=") for a in sys.argv[1:] if "=" in a)
FOLDS = int(kw.get("folds", 5))
for folder in [a for a in sys.argv[1:] if "=" not in a]:
    walks = [w for w in gs.read_survey([folder]) if len(w.landmarks) >= 2]
    ids = np.array(sorted({w.session_id for w in walks}))
    fold_of = dict(zip(ids, np.random.default_rng(0).permutation(len(ids)) % FOLDS))
    cfg = KnnConfig()
    err, inside, scales = [], [], []
    for f in range(FOLDS):
        train = [w for w in walks if fold_of[w.session_id] != f]
        test = [w for w in walks if fold_of[w.session_id] == f]
        rm = oracle_radio_map(train)
        u = calibrate_uncertainty(rm, cfg)
        res = KnnLocator(rm, cfg).locate([dict(sc.readings) for w in test for sc in w.scans])
        truth = oracle_radio_map(test).xy
        ok = res.valid
        e = np.linalg.norm(res.xy[ok] - truth[ok], axis=1)
        err.append(e)
        inside.append(e <= R95 * u.sigma(res.spread[ok]))
        scales.append(u.scale)
    e, i = np.concatenate(err), np.concatenate(inside)
    print(f"{folder}: walks {len(walks)} scans {len(e)} mean {e.mean():.2f} m median {np.median(e):.2f} m "
          f"coverage95 {i.mean():.3f} scale {np.mean(scales):.2f}", flush=True)
