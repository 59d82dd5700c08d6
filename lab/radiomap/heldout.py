"""Held-out readings: how well does each model predict a new walk's RSS? Folds of walks (the map =
the other walks' scans at their oracle positions; truth builds the map, as bench tracking-real does).
python lab/radiomap/heldout.py FLOOR [folds=10] [h=3] [s=0.5]"""
from __future__ import annotations
import sys
import numpy as np
from scipy.spatial import cKDTree
import graphslam as gs
from graphslam import oracle_radio_map
from graphslam import fit_ap, ApFitConfig, ApModel

folder = sys.argv[1]
kw = dict(a.split("=") for a in sys.argv[2:] if "=" in a)
FOLDS = int(kw.get("folds", 10)); H = float(kw.get("h", 3)); SHR = float(kw.get("s", 0.5)); UNHEARD = -100.0
sv = gs.read_survey([folder])
walks = [w for w in sv if len(w.landmarks) >= 2]
rm = oracle_radio_map(walks)
V = rm.fingerprints.values.tocoo()
row, ap, rss = V.row, V.col, V.data + rm.missing_dbm
keep = rss >= -100
row, ap, rss = row[keep], ap[keep], rss[keep]
xy = rm.xy[row]; sid = rm.session_ids[row]
ids = np.array(sorted(set(rm.session_ids)))
rng = np.random.default_rng(0)
fold_of = dict(zip(ids, rng.permutation(len(ids)) % FOLDS))
f_read = np.array([fold_of[s] for s in sid]); f_scan = np.array([fold_of[s] for s in rm.session_ids])
pred = {k: np.full(len(rss), np.nan) for k in ("nearest_fp", "nearest_reading", "nw_const", "law_nw", "law")}
law_cfg = ApFitConfig(min_readings=15)
for f in range(FOLDS):
    tr, te = f_read != f, f_read == f
    # 1. nearest training scan (spatially), its reading of the AP (unheard -> UNHEARD)
    scans_tr = np.flatnonzero(f_scan != f)
    tree = cKDTree(rm.xy[scans_tr])
    _, nn = tree.query(xy[te])
    nn_scan = scans_tr[nn]
    lut = {}
    for r_, a_, v_ in zip(row[tr], ap[tr], rss[tr]):
        lut[(r_, a_)] = v_
    pred["nearest_fp"][te] = [lut.get((s_, a_), UNHEARD) for s_, a_ in zip(nn_scan, ap[te])]
    # per AP models
    order = np.argsort(ap[tr], kind="stable"); atr = ap[tr][order]
    xtr, rtr = xy[tr][order], rss[tr][order]
    bounds = np.searchsorted(atr, np.arange(rm.fingerprints.n_aps + 1))
    te_idx = np.flatnonzero(te)
    te_order = te_idx[np.argsort(ap[te_idx], kind="stable")]
    tb = np.searchsorted(ap[te_order], np.arange(rm.fingerprints.n_aps + 1))
    for a in range(rm.fingerprints.n_aps):
        q = te_order[tb[a]:tb[a + 1]]
        if len(q) == 0: continue
        p, r = xtr[bounds[a]:bounds[a + 1]], rtr[bounds[a]:bounds[a + 1]]
        if len(p) == 0: continue
        t = cKDTree(p)
        _, j = t.query(xy[q]); pred["nearest_reading"][q] = r[j]
        m0 = r.mean()
        # NW with shrink towards the constant mean
        D = t.sparse_distance_matrix(cKDTree(xy[q]), 3 * H, output_type="coo_matrix")
        k = np.exp(-0.5 * (D.data / H) ** 2)
        num = np.bincount(D.col, weights=k * (r[D.row] - m0), minlength=len(q)); den = np.bincount(D.col, weights=k, minlength=len(q))
        pred["nw_const"][q] = m0 + num / (den + SHR)
        fit = fit_ap("", p, r, law_cfg) if len(p) >= 15 else None
        if isinstance(fit, ApModel):
            def law(z):
                d2 = ((z - [fit.x, fit.y]) ** 2).sum(1) + 1.0
                return fit.p0_dbm - 5 * fit.gamma * np.log10(d2)
            res = r - law(p)
            num = np.bincount(D.col, weights=k * res[D.row], minlength=len(q))
            pred["law"][q] = law(xy[q])
            pred["law_nw"][q] = law(xy[q]) + num / (den + SHR)
        else:
            pred["law"][q] = pred["nw_const"][q]; pred["law_nw"][q] = pred["nw_const"][q]
ok = np.isfinite(pred["nearest_reading"])
out = {k: round(float(np.sqrt(np.nanmean((v[ok] - rss[ok]) ** 2))), 2) for k, v in pred.items()}
print(folder.split("/")[-1], f"readings {ok.sum()}", out)
