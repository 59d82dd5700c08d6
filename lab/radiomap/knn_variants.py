"""kNN variants and a calibrated uncertainty on real floors' oracle maps (folds of walks; truth builds
the map and scores, as bench tracking-real does). The uncertainty's scale is calibrated without
truth: each map walk located on the map of the other walks (its own positions in the map are the
reference there).
python lab/radiomap/knn_variants.py FLOOR [folds=5]"""
from __future__ import annotations
import sys
import numpy as np
import graphslam as gs
from graphslam import KnnConfig, KnnLocator, oracle_radio_map

folder = sys.argv[1]
kw = dict(a.split("=") for a in sys.argv[2:] if "=" in a)
FOLDS = int(kw.get("folds", 5))
sv = gs.read_survey([folder])
walks = [w for w in sv if len(w.landmarks) >= 2]
ids = np.array(sorted({w.session_id for w in walks}))
rng = np.random.default_rng(0)
fold_of = dict(zip(ids, rng.permutation(len(ids)) % FOLDS))
VARIANTS = {
    "eq9_k3": KnnConfig(k=3, metric="eq9"),
    "sor_k3": KnnConfig(k=3, metric="sorensen"),
    "sor_k5": KnnConfig(k=5, metric="sorensen"),
    "sor_k8": KnnConfig(k=8, metric="sorensen"),
}


def scans_of(ws):
    return [dict(sc.readings) for w in ws for sc in w.scans]


def sq_dist(res, truth):
    return ((res.xy - truth) ** 2).sum(1)


out = {k: {"e": [], "spread": [], "cal": []} for k in VARIANTS}
for f in range(FOLDS):
    trw = [w for w in walks if fold_of[w.session_id] != f]
    tew = [w for w in walks if fold_of[w.session_id] == f]
    rm = oracle_radio_map(trw)
    q = scans_of(tew)
    truth = oracle_radio_map(tew).xy
    for name, cfg in VARIANTS.items():
        res = KnnLocator(rm, cfg).locate(q)
        ok = res.valid
        out[name]["e"].append(np.where(ok, np.sqrt(sq_dist(res, truth)), np.nan))
        out[name]["spread"].append(np.where(ok, res.spread, np.nan))
        # calibration without truth: each training walk against the others (its map positions as reference)
        e2, s2 = [], []
        for w in trw[:: max(1, len(trw) // 12)]:
            others = [x for x in trw if x.session_id != w.session_id]
            r2 = KnnLocator(oracle_radio_map(others), cfg).locate(scans_of([w]))
            ref = oracle_radio_map([w]).xy
            ok2 = r2.valid
            e2.append(np.sqrt(sq_dist(r2, ref))[ok2]); s2.append(r2.spread[ok2])
        e2, s2 = np.concatenate(e2), np.concatenate(s2)
        out[name]["cal"].append((e2, s2))
for name in VARIANTS:
    e = np.concatenate(out[name]["e"]); sp = np.concatenate(out[name]["spread"])
    # sigma model: sigma^2 = a^2 (spread^2 + b^2), 2-D Gaussian: P(|err| <= r) = 1 - exp(-r^2 / 2 sigma^2);
    # a from the calibration set so that 95 % of calibration errors fall inside r95 = sqrt(5.991) sigma
    covs = []
    for f, (e2, s2) in enumerate(out[name]["cal"]):
        b = 2.0
        base = np.sqrt(s2**2 + b**2)
        a = np.quantile(e2 / (np.sqrt(5.991) * base), 0.95)
        ef, sf = out[name]["e"][f], out[name]["spread"][f]
        sig = a * np.sqrt(sf**2 + b**2)
        covs.append(ef <= np.sqrt(5.991) * sig)
    cov = np.nanmean(np.concatenate(covs).astype(float)[np.isfinite(e)])
    print(f"{folder.split('/')[-1]:9s} {name:7s} mean {np.nanmean(e):5.2f} median {np.nanmedian(e):5.2f}  inside calibrated 95 %: {cov:.3f}", flush=True)
