"""A likelihood estimator over a signal field (law + kernel-smoothed residual, per AP) vs kNN, on a
real floor's oracle maps (folds of walks; truth builds the map and scores, as bench tracking-real).
python lab/radiomap/field_locate.py FLOOR [folds=5] [h=3] [s=0.5] [s0=5] [T=1,2,4,8]"""
from __future__ import annotations
import sys, time
import numpy as np
from scipy import sparse
from scipy.ndimage import gaussian_filter
from scipy.special import log_ndtr
from scipy.spatial import cKDTree
import graphslam as gs
from graphslam import oracle_radio_map
from graphslam import RadioMap
from graphslam import KnnConfig, KnnLocator
from graphslam import fit_ap, ApFitConfig, ApModel

folder = sys.argv[1]
kw = dict(a.split("=") for a in sys.argv[2:] if "=" in a)
FOLDS = int(kw.get("folds", 5)); H = float(kw.get("h", 3)); SHR = float(kw.get("s", 0.5)); S0 = float(kw.get("s0", 5))
TS = [float(t) for t in kw.get("T", "1,2,4,8").split(",")]
FLOOR_DBM = -100.0; CELL = 1.0
OFFSET = float(kw.get('offset', 0))
UNHEARD = kw.get('unheard', '1') == '1'


class Field:
    def __init__(self, rm: RadioMap):
        V = rm.fingerprints.values.tocsc()
        self.bssids = rm.bssids; A = len(rm.bssids)
        lo = rm.xy.min(0) - 5; hi = rm.xy.max(0) + 5
        self.lo = np.floor(lo); self.n = np.ceil((hi - self.lo) / CELL).astype(int) + 1
        gx, gy = np.meshgrid(self.lo[0] + np.arange(self.n[0]) * CELL, self.lo[1] + np.arange(self.n[1]) * CELL, indexing="ij")
        allc = np.column_stack([gx.ravel(), gy.ravel()])
        d, _ = cKDTree(rm.xy).query(allc)
        self.cells = allc[d <= 4.0]  # mapped area
        C = len(self.cells)
        self.cell_id = np.full(self.n[0] * self.n[1], -1); 
        ci = np.rint((self.cells - self.lo) / CELL).astype(int)
        self.cell_id[ci[:, 0] * self.n[1] + ci[:, 1]] = np.arange(C)
        self.law = np.full((A, 4), np.nan)  # x, y, p0, gamma
        self.const = np.full(A, FLOOR_DBM)
        self.tau = np.full(A, 8.0)
        rows, cols, mu, cnt = [], [], [], []
        cfg = ApFitConfig(min_readings=15)
        s = H / CELL; norm = 2 * np.pi * s * s
        for a in range(A):
            r_idx = V.indices[V.indptr[a]:V.indptr[a + 1]]
            r = V.data[V.indptr[a]:V.indptr[a + 1]] + rm.missing_dbm
            ok = r >= FLOOR_DBM; r_idx, r = r_idx[ok], r[ok]
            if len(r) == 0: continue
            p = rm.xy[r_idx]
            self.const[a] = r.mean()
            if len(r) >= 15:
                f = fit_ap("", p, r, cfg)
                if isinstance(f, ApModel):
                    self.law[a] = (f.x, f.y, f.p0_dbm, f.gamma)
            m = self.mean_fn(a, p)
            res = r - m
            self.tau[a] = max(np.std(res), 2.0) if len(r) > 3 else 8.0
            # grid of the AP: the global grid's cells within 3H of its readings
            c = np.rint((p - self.lo) / CELL).astype(int)
            c0 = np.maximum(c.min(0) - int(3 * s) - 1, 0); c1 = np.minimum(c.max(0) + int(3 * s) + 2, self.n)
            shp = c1 - c0
            lin = (c[:, 0] - c0[0]) * shp[1] + (c[:, 1] - c0[1])
            Sg = gaussian_filter(np.bincount(lin, weights=res, minlength=shp[0] * shp[1]).reshape(shp).astype(float), s, mode="constant") * norm
            Wg = gaussian_filter(np.bincount(lin, minlength=shp[0] * shp[1]).reshape(shp).astype(float), s, mode="constant") * norm
            ii, jj = np.nonzero(Wg > 1e-3)
            gid = self.cell_id[(ii + c0[0]) * self.n[1] + (jj + c0[1])]
            keep = gid >= 0
            ii, jj, gid = ii[keep], jj[keep], gid[keep]
            corr = Sg[ii, jj] / (Wg[ii, jj] + SHR)
            rows.append(gid); cols.append(np.full(len(gid), a)); mu.append(self.mean_fn(a, self.cells[gid]) + corr); cnt.append(Wg[ii, jj])
        rows, cols = np.concatenate(rows), np.concatenate(cols)
        self.MU = sparse.csc_matrix((np.concatenate(mu), (rows, cols)), shape=(C, A))
        self.N = sparse.csc_matrix((np.concatenate(cnt), (rows, cols)), shape=(C, A))
        self.index = {b: i for i, b in enumerate(self.bssids)}

    def mean_fn(self, a, z):
        L = self.law[a]
        if np.isfinite(L[0]):
            d2 = ((z - L[:2]) ** 2).sum(1) + 1.0
            return L[2] - 5 * L[3] * np.log10(d2)
        return np.full(len(z), self.const[a])

    def at(self, aps):
        """(C, k) mean and sigma of APs ``aps`` at every mapped cell."""
        mu_in = self.MU[:, aps].toarray(); n_in = self.N[:, aps].toarray()
        inside = n_in > 0
        base = np.column_stack([self.mean_fn(a, self.cells) if np.isfinite(self.law[a, 0]) else np.full(len(self.cells), FLOOR_DBM) for a in aps])
        mu = np.where(inside, mu_in, base)
        tau = self.tau[aps][None]
        sig = np.sqrt(S0**2 + tau**2 * SHR / (n_in + SHR))
        return mu, sig

    def loglik(self, reading: dict, extra_unheard: set):
        heard = [(self.index[b], v) for b, v in reading.items() if b in self.index and v >= FLOOR_DBM]
        if not heard: return None
        aps = np.array([a for a, _ in heard]); r = np.array([v for _, v in heard])
        mu, sig = self.at(aps)
        if OFFSET:
            w_ = 1 / sig**2
            o = (w_ * (r[None] - mu)).sum(1) / (w_.sum(1) + 1 / OFFSET**2)
            ll = (-0.5 * ((r[None] - mu - o[:, None]) / sig) ** 2 - np.log(sig)).sum(1) - 0.5 * (o / OFFSET) ** 2
        else:
            ll = (-0.5 * ((r[None] - mu) / sig) ** 2 - np.log(sig)).sum(1)
        un = np.array(sorted(extra_unheard - set(aps.tolist())), dtype=int)
        if len(un):
            mu2, sig2 = self.at(un)
            ll += log_ndtr((FLOOR_DBM - mu2) / sig2).sum(1)
        return ll


sv = gs.read_survey([folder])
walks = [w for w in sv if len(w.landmarks) >= 2]
rm_all = oracle_radio_map(walks)
ids = np.array(sorted({w.session_id for w in walks}))
rng = np.random.default_rng(0); fold_of = dict(zip(ids, rng.permutation(len(ids)) % FOLDS))
res = {"knn_eq9": [], "knn_sorensen": [], "field": {T: [] for T in TS}, "cov95": {T: [] for T in TS}, "hpd95": {T: [] for T in TS}}
t0 = time.time()
def scans_of(ws):
    rd = []
    for w in ws:
        rd += [dict(sc.readings) for sc in w.scans]
    return rd
for f in range(FOLDS):
    trw = [w for w in walks if fold_of[w.session_id] != f]; tew = [w for w in walks if fold_of[w.session_id] == f]
    rm = oracle_radio_map(trw)
    field = Field(rm)
    readings = scans_of(tew)
    truth = oracle_radio_map(tew).xy
    for metric in ("eq9", "sorensen"):
        loc = KnnLocator(rm, KnnConfig(k=3, metric=metric))
        out = loc.locate(readings)
        e = np.linalg.norm(out.xy - truth, axis=1); e[~out.valid] = np.nan
        res[f"knn_{metric}"].append(e)
        if metric == "sorensen":
            nb = out.neighbours
    Vm = rm.fingerprints.values.tocsr()
    for qi, rd in enumerate(readings):
        near_aps = set(np.unique(Vm[nb[qi][nb[qi] >= 0]].indices).tolist())
        ll = field.loglik(rd, near_aps if UNHEARD else set())
        for T in TS:
            if ll is None:
                res["field"][T].append(np.nan); res["cov95"][T].append(np.nan); res["hpd95"][T].append(np.nan); continue
            w = np.exp((ll - ll.max()) / T); w /= w.sum()
            mu = w @ field.cells
            d = field.cells - mu
            Cv = (w[:, None, None] * d[:, :, None] * d[:, None, :]).sum(0) + np.eye(2) / 12
            et = truth[qi] - mu
            res["field"][T].append(np.linalg.norm(et))
            res["cov95"][T].append(float(et @ np.linalg.solve(Cv, et) <= 5.991))
            # HPD: truth's nearest cell inside the 95 % mass?
            o = np.argsort(-w); cum = np.cumsum(w[o]); inside = o[: np.searchsorted(cum, 0.95) + 1]
            tc = np.argmin(((field.cells - truth[qi]) ** 2).sum(1))
            res["hpd95"][T].append(float(tc in set(inside.tolist())))
    print(f"fold {f} done {time.time()-t0:.0f}s", flush=True)
for k in ("knn_eq9", "knn_sorensen"):
    e = np.concatenate(res[k]); print(f"{k:14s} mean {np.nanmean(e):5.2f} median {np.nanmedian(e):5.2f}")
for T in TS:
    e = np.array(res["field"][T])
    print(f"field T={T:<4g}  mean {np.nanmean(e):5.2f} median {np.nanmedian(e):5.2f}  inside 95% ellipse {np.nanmean(res['cov95'][T]):.3f} HPD {np.nanmean(res['hpd95'][T]):.3f}")
