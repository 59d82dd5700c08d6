"""Fusing the default (Sørensen) kNN estimate with a signal-field likelihood, vs kNN alone, on a real
floor's oracle maps, with the folds of ``graphslam bench locate-real`` (held_out_folds: leave one
route out when the files name routes, else 5 seeded random folds), so the kNN rows match its numbers.
Truth builds the maps and scores only, as locate-real does; no estimator sees it.

Per held-out scan: eq.9 kNN and Sørensen kNN (KnnConfig defaults), the field posterior mean
(field_locate.py's field: log-distance law + Gaussian-kernel residual grid per AP, per-AP tau, a
per-query RSS offset profiled out with a 6 dB prior, unheard APs ignored), and fusions on the field's
1-m grid: posterior ∝ exp(loglik / T) * N(cell; knn_sorensen, s^2 I), posterior mean, with s fixed
(3, 5, 8 m) or s = max(c * spread, 2 m) (spread: the kNN answer's weighted RMS distance of its
neighbours to it), and convex blends w * knn + (1 - w) * field. Tn=K: the temperature T = max(1, n_heard / K) per
query (n_heard: the query's APs the map knows), one setting that tempers scans hearing many APs more.

python lab/radiomap/fusion.py FLOOR [FLOOR ...] [max_q=600] [T=1,2,4,8] [out=/tmp/fusion/x.json]
"""
from __future__ import annotations

import json
import sys
import time

import numpy as np
from scipy import sparse
from scipy.ndimage import gaussian_filter
from scipy.spatial import cKDTree

import graphslam as gs
from graphslam import ApFitConfig, ApModel, KnnConfig, KnnLocator, RadioMap, fit_ap, held_out_folds, oracle_radio_map

args = [a for a in sys.argv[1:] if "=" not in a]
kw = dict(a.split("=", 1) for a in sys.argv[1:] if "=" in a)
MAX_Q = int(kw.get("max_q", 600))  # held-out scans per floor scored for the field/fusion (seeded subsample); 0 = all
TS = [float(t) for t in kw.get("T", "1,2,4,8").split(",")]
SS = [float(s) for s in kw.get("s", "3,5,8").split(",")]
CS = [float(c) for c in kw.get("c", "1,1.5,2").split(",")]
WS = [float(w) for w in kw.get("w", "0.5,0.7").split(",")]
KS = [float(k) for k in kw.get("K", "4,8,16").split(",")]  # adaptive temperature T = max(1, n_heard / K)
OUT = kw.get("out")
H, SHR, S0, OFFSET = 3.0, 0.5, 5.0, 6.0  # field_locate.py's h, s, s0 and its best offset=6 (unheard=0)
FLOOR_DBM = -100.0
CELL = 1.0
SPREAD_FLOOR = 2.0

gs.limit_blas_threads(1)


class Field:
    """field_locate.py's Field (copied; unheard-AP term dropped: unheard=0 was its best option)."""

    def __init__(self, rm: RadioMap):
        V = rm.fingerprints.values.tocsc()
        self.bssids = rm.bssids
        A = len(rm.bssids)
        lo = rm.xy.min(0) - 5
        hi = rm.xy.max(0) + 5
        self.lo = np.floor(lo)
        self.n = np.ceil((hi - self.lo) / CELL).astype(int) + 1
        gx, gy = np.meshgrid(self.lo[0] + np.arange(self.n[0]) * CELL, self.lo[1] + np.arange(self.n[1]) * CELL, indexing="ij")
        allc = np.column_stack([gx.ravel(), gy.ravel()])
        d, _ = cKDTree(rm.xy).query(allc)
        self.cells = allc[d <= 4.0]  # mapped area
        C = len(self.cells)
        self.cell_id = np.full(self.n[0] * self.n[1], -1)
        ci = np.rint((self.cells - self.lo) / CELL).astype(int)
        self.cell_id[ci[:, 0] * self.n[1] + ci[:, 1]] = np.arange(C)
        self.law = np.full((A, 4), np.nan)  # x, y, p0, gamma
        self.const = np.full(A, FLOOR_DBM)
        self.tau = np.full(A, 8.0)
        rows, cols, mu, cnt = [], [], [], []
        cfg = ApFitConfig(min_readings=15)
        s = H / CELL
        norm = 2 * np.pi * s * s
        for a in range(A):
            r_idx = V.indices[V.indptr[a]:V.indptr[a + 1]]
            r = V.data[V.indptr[a]:V.indptr[a + 1]] + rm.missing_dbm
            ok = r >= FLOOR_DBM
            r_idx, r = r_idx[ok], r[ok]
            if len(r) == 0:
                continue
            p = rm.xy[r_idx]
            self.const[a] = r.mean()
            if len(r) >= 15:
                f = fit_ap("", p, r, cfg)
                if isinstance(f, ApModel):
                    self.law[a] = (f.x, f.y, f.p0_dbm, f.gamma)
            m = self.mean_fn(a, p)
            res = r - m
            self.tau[a] = max(np.std(res), 2.0) if len(r) > 3 else 8.0
            c = np.rint((p - self.lo) / CELL).astype(int)
            c0 = np.maximum(c.min(0) - int(3 * s) - 1, 0)
            c1 = np.minimum(c.max(0) + int(3 * s) + 2, self.n)
            shp = c1 - c0
            lin = (c[:, 0] - c0[0]) * shp[1] + (c[:, 1] - c0[1])
            Sg = gaussian_filter(np.bincount(lin, weights=res, minlength=shp[0] * shp[1]).reshape(shp).astype(float), s, mode="constant") * norm
            Wg = gaussian_filter(np.bincount(lin, minlength=shp[0] * shp[1]).reshape(shp).astype(float), s, mode="constant") * norm
            ii, jj = np.nonzero(Wg > 1e-3)
            gid = self.cell_id[(ii + c0[0]) * self.n[1] + (jj + c0[1])]
            keep = gid >= 0
            ii, jj, gid = ii[keep], jj[keep], gid[keep]
            corr = Sg[ii, jj] / (Wg[ii, jj] + SHR)
            rows.append(gid)
            cols.append(np.full(len(gid), a))
            mu.append(self.mean_fn(a, self.cells[gid]) + corr)
            cnt.append(Wg[ii, jj])
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
        """(C, k) mean and sigma of APs ``aps`` at every mapped cell, cached per AP (same values as
        field_locate.py's, computed once per AP and fold)."""
        if not hasattr(self, "_cache"):
            self._cache = {}
        miss = [a for a in aps if a not in self._cache]
        if miss:
            mu, sig = self._at(np.array(miss))
            for j, a in enumerate(miss):
                self._cache[a] = (mu[:, j], sig[:, j])
        return (np.column_stack([self._cache[a][0] for a in aps]), np.column_stack([self._cache[a][1] for a in aps]))

    def _at(self, aps):
        mu_in = self.MU[:, aps].toarray()
        n_in = self.N[:, aps].toarray()
        inside = n_in > 0
        base = np.column_stack([self.mean_fn(a, self.cells) if np.isfinite(self.law[a, 0]) else np.full(len(self.cells), FLOOR_DBM) for a in aps])
        mu = np.where(inside, mu_in, base)
        tau = self.tau[aps][None]
        sig = np.sqrt(S0**2 + tau**2 * SHR / (n_in + SHR))
        return mu, sig

    def loglik(self, reading: dict):
        heard = [(self.index[b], v) for b, v in reading.items() if b in self.index and v >= FLOOR_DBM]
        if not heard:
            return None
        aps = np.array([a for a, _ in heard])
        r = np.array([v for _, v in heard])
        mu, sig = self.at(aps)
        w_ = 1 / sig**2
        o = (w_ * (r[None] - mu)).sum(1) / (w_.sum(1) + 1 / OFFSET**2)
        ll = (-0.5 * ((r[None] - mu - o[:, None]) / sig) ** 2 - np.log(sig)).sum(1) - 0.5 * (o / OFFSET) ** 2
        return ll, len(aps)


def post_mean(logp, cells):
    w = np.exp(logp - logp.max())
    return (w / w.sum()) @ cells


def variant_names():
    names = ["knn_eq9", "knn_sorensen"] + [f"field T={T:g}" for T in TS]
    names += [f"fuse T={T:g} s={s:g}" for T in TS for s in SS]
    names += [f"fuse T={T:g} s={c:g}*spread" for T in TS for c in CS]
    names += [f"blend w={w:g} T={T:g}" for w in WS for T in TS]
    names += [f"field Tn={K:g}" for K in KS]
    names += [f"fuse Tn={K:g} s={s:g}" for K in KS for s in SS]
    names += [f"fuse Tn={K:g} s={c:g}*spread" for K in KS for c in CS]
    return names


def run_floor(folder: str) -> dict:
    t_floor = time.time()
    walks = [w for w in gs.read_survey([folder]) if len(w.landmarks) >= 2]
    split = held_out_folds(walks, None, 0)  # locate-real's default
    names = variant_names()
    err = {n: [] for n in names}
    allknn = {"knn_eq9": [], "knn_sorensen": []}  # on every held-out scan (checks against locate-real)
    t_field, t_fuse, n_q = 0.0, 0.0, 0
    n_heard = []
    rng = np.random.default_rng(0)
    chunks = []  # (fold, rm, truth, queries, res_eq9, res_sor)
    for _, test_idx in split:
        held = set(test_idx)
        train = [w for i, w in enumerate(walks) if i not in held]
        test = [walks[i] for i in test_idx]
        if not train or not any(w.scans for w in test):
            continue
        rm = oracle_radio_map(train)
        truth = oracle_radio_map(test).xy
        queries = [dict(sc.readings) for w in test for sc in w.scans]
        qwalk = [w.session_id for w in test for sc in w.scans]
        outs = {}
        for m in ("eq9", "sorensen"):
            outs[m] = KnnLocator(rm, KnnConfig(metric=m)).locate(queries)
            allknn[f"knn_{m}"].append(np.linalg.norm(outs[m].xy - truth, axis=1))
        chunks.append((rm, truth, queries, outs, qwalk))
    total = sum(len(c[2]) for c in chunks)
    # seeded subsample of the held-out scans, spread over the folds in proportion
    if MAX_Q and total > MAX_Q:
        pick = np.sort(rng.choice(total, MAX_Q, replace=False))
    else:
        pick = np.arange(total)
    start = 0
    walk_of = []
    for rm, truth, queries, outs, qwalk in chunks:
        sel = pick[(pick >= start) & (pick < start + len(queries))] - start
        start += len(queries)
        if not len(sel):
            continue
        t0 = time.time()
        field = Field(rm)
        t_build = time.time() - t0
        cells = field.cells
        for qi in sel:
            e = {}
            for m in ("eq9", "sorensen"):
                e[f"knn_{m}"] = np.linalg.norm(outs[m].xy[qi] - truth[qi])  # NaN when unlocated
            knn = outs["sorensen"].xy[qi]
            kv = bool(np.all(np.isfinite(knn)))
            spread = float(outs["sorensen"].spread[qi]) if kv else np.nan
            t1 = time.time()
            got = field.loglik(queries[qi])
            ll, nh = got if got is not None else (None, 0)
            n_heard.append(nh)
            t2 = time.time()
            if ll is None:  # no AP of the map heard: the field has nothing; fusion falls back to kNN
                for n in names[2:]:
                    e[n] = e["knn_sorensen"] if n.startswith(("fuse", "blend")) else np.nan
            else:
                d2 = ((cells - knn) ** 2).sum(1) if kv else None
                def score(label: str, T: float) -> None:  # every variant at temperature T, named by label
                    fmean = post_mean(ll / T, cells)
                    e[f"field {label}"] = np.linalg.norm(fmean - truth[qi])
                    for s in SS:
                        est = post_mean(ll / T - 0.5 * d2 / s**2, cells) if kv else fmean
                        e[f"fuse {label} s={s:g}"] = np.linalg.norm(est - truth[qi])
                    for c in CS:
                        s = max(c * spread, SPREAD_FLOOR) if kv else np.nan
                        est = post_mean(ll / T - 0.5 * d2 / s**2, cells) if kv else fmean
                        e[f"fuse {label} s={c:g}*spread"] = np.linalg.norm(est - truth[qi])
                    if label.startswith("T="):
                        for w in WS:
                            est = w * knn + (1 - w) * fmean if kv else fmean
                            e[f"blend w={w:g} {label}"] = np.linalg.norm(est - truth[qi])

                for T in TS:
                    score(f"T={T:g}", T)
                for K in KS:
                    score(f"Tn={K:g}", max(1.0, nh / K))
            t3 = time.time()
            t_field += t2 - t1
            t_fuse += (t3 - t2) / ((len(TS) + len(KS)) * (len(SS) + len(CS) + 1))  # one posterior's share
            n_q += 1
            for n in names:
                err[n].append(e[n])
            walk_of.append(qwalk[qi])
        print(f"  fold done: {len(sel)} queries, field build {t_build:.1f}s, {time.time()-t_floor:.0f}s so far", flush=True)
    row = {"floor": folder, "walks": len(walks), "folds": len(split), "scans": total, "queries": n_q,
           "ms_per_query_loglik": round(1e3 * t_field / max(n_q, 1), 2),
           "ms_per_query_one_fusion_posterior": round(1e3 * t_fuse / max(n_q, 1), 3),
           "seconds": round(time.time() - t_floor, 1), "mean_heard_aps": round(float(np.mean(n_heard)), 1), "all_scans": {}, "subsample": {}}
    if OUT:  # per-query errors and walks, for paired walk-bootstrap intervals
        np.savez_compressed(OUT.replace(".json", "") + "_" + folder.rstrip("/").split("/")[-1] + ".npz",
                            walk=np.array(walk_of), names=np.array(names), err=np.array([err[n] for n in names], float))
    for k, v in allknn.items():
        a = np.concatenate(v)
        row["all_scans"][k] = {"located": int(np.isfinite(a).sum()), "mean": round(float(np.nanmean(a)), 3), "median": round(float(np.nanmedian(a)), 3)}
    for n in names:
        a = np.array(err[n], float)
        row["subsample"][n] = {"located": int(np.isfinite(a).sum()), "mean": round(float(np.nanmean(a)), 3), "median": round(float(np.nanmedian(a)), 3)}
    return row


rows = []
for folder in args:
    print(f"== {folder}", flush=True)
    row = run_floor(folder)
    rows.append(row)
    print(f"{row['floor']}: walks {row['walks']} folds {row['folds']} scans {row['scans']} queries {row['queries']} "
          f"heard APs {row['mean_heard_aps']}, loglik {row['ms_per_query_loglik']} ms/q, one fusion {row['ms_per_query_one_fusion_posterior']} ms/q, {row['seconds']} s")
    for k, v in row["all_scans"].items():
        print(f"  ALL  {k:28s} mean {v['mean']:6.2f} median {v['median']:6.2f} located {v['located']}")
    for k, v in row["subsample"].items():
        print(f"  SUB  {k:28s} mean {v['mean']:6.2f} median {v['median']:6.2f} located {v['located']}")
    if OUT:
        with open(OUT, "w") as fh:
            json.dump(rows, fh, indent=1)
