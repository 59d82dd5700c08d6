"""Offset-corrected Sørensen kNN (uji_offset.py's "offsor_med") vs plain Sørensen kNN on real floors,
with the folds and oracle maps of ``graphslam bench locate-real`` (held_out_folds(walks, None, 0);
the map = oracle_radio_map of the training walks, truth = oracle_radio_map of the held-out walks,
used to build maps and to score only).

Per held-out scan: eq.9 and Sørensen kNN with KnnConfig defaults (= locate-real's rows), the exact
Sørensen top-100 (KnnConfig(k=100, metric="sorensen", index="exact")) and, on those 100
candidates: per (query, candidate) pair the median of (candidate dBm - query dBm) over the APs both
heard (0 if none, clipped to +-20 dB) added to the query's readings (shifted values clipped to the
powed representation's range [0, -missing_dbm]), then the same powed Sørensen distance over the union
of heard APs (query APs the map does not know left out, as the product does). Re-ranked; estimate =
inverse-distance weighted mean (1 / (d + 1e-6), as KnnLocator) of the k nearest, k = 3 and 5.
Check: the same code with offset 0 reproduces KnnLocator's distances on the candidates.

python lab/radiomap/offset_real.py FLOOR [FLOOR ...] [max_q=0] [out=/tmp/offreal/x.json]
max_q: score the offset variants on a seeded subsample of this many held-out scans when a floor has
more than 2 * max_q (0 = all scans); the baselines are then reported on the same subsample too.
"""
from __future__ import annotations

import json
import sys
import time

import numpy as np

import graphslam as gs
from graphslam import KnnConfig, KnnLocator, held_out_folds, oracle_radio_map

args = [a for a in sys.argv[1:] if "=" not in a]
kw = dict(a.split("=", 1) for a in sys.argv[1:] if "=" in a)
MAX_Q = int(kw.get("max_q", 0))
OUT = kw.get("out")
NC = 100
OFF_CLIP = 20.0
EPS = 1e-6  # KnnLocator's WEIGHT_EPS_DB
KS = (3, 5)

gs.limit_blas_threads(1)


def offset_rerank(rm, qm, cand):
    """qm: the queries encoded by rm.encode (csr of shifted values over the map's APs); cand: (Q, NC)
    exact Sørensen candidates (-1 padded). Returns per query the plain (offset 0) and offset Sørensen
    distances on the candidates, and the raw (unclipped) median offsets (NaN: no common AP)."""
    V = rm.fingerprints.values.tocsr()
    scale = -rm.missing_dbm  # SorensenRefs.scale (missing_dbm < 0)
    Q = qm.shape[0]
    d0 = np.full((Q, NC), np.inf)
    d1 = np.full((Q, NC), np.inf)
    raw = np.full((Q, NC), np.nan)
    qi_ptr, qi_ind, qi_dat = qm.indptr, qm.indices, qm.data
    for i in range(Q):
        c = cand[i]
        c = c[c >= 0]
        if not len(c):
            continue
        qc, qv = qi_ind[qi_ptr[i]:qi_ptr[i + 1]], qi_dat[qi_ptr[i]:qi_ptr[i + 1]]
        R = V[c]
        cols = np.union1d(qc, R.indices)
        R = R[:, cols].toarray()  # (nc, nU) shifted values, 0 = not heard
        q = np.zeros(len(cols))
        q[np.searchsorted(cols, qc)] = qv
        hq, hr = q > 0, R > 0
        C = hq[None, :] & hr
        diff = np.where(C, R - q[None, :], np.nan)
        with np.errstate(all="ignore"):
            med = np.nanmedian(diff, 1)
        raw[i, :len(c)] = med
        o = np.clip(np.nan_to_num(med), -OFF_CLIP, OFF_CLIP)
        pr = (R / scale) ** np.e
        srs = pr.sum(1)
        for o_, out in ((np.zeros(len(c)), d0), (o, d1)):
            qs = np.clip(q[None, :] + o_[:, None], 0.0, scale)
            pq = np.where(hq[None, :], (qs / scale) ** np.e, 0.0)
            out[i, :len(c)] = np.maximum(1.0 - 2.0 * np.minimum(pq, pr).sum(1) / (pq.sum(1) + srs), 0.0)
    return d0, d1, raw


def estimate(xy, idx, d, k):
    """KnnLocator._aggregate's weighted estimate over the first k of (idx, d) (sorted ascending)."""
    i, dd = idx[:, :k], d[:, :k]
    ok = (i >= 0) & np.isfinite(dd)
    w = np.where(ok, 1.0 / (np.where(ok, dd, 0.0) + EPS), 0.0)
    ws = w.sum(1)
    with np.errstate(invalid="ignore", divide="ignore"):
        est = (w[..., None] * xy[np.where(ok, i, 0)]).sum(1) / ws[:, None]
    est[ws <= 0] = np.nan
    return est


def stats(e):
    e = np.asarray(e, float)
    ok = np.isfinite(e)
    return {"n": int(len(e)), "located": int(ok.sum()), "mean": float(e[ok].mean()), "median": float(np.median(e[ok])),
            "p90": float(np.percentile(e[ok], 90))}


def run_floor(folder: str) -> dict:
    t_floor = time.time()
    walks = [w for w in gs.read_survey([folder]) if len(w.landmarks) >= 2]
    split = held_out_folds(walks, None, 0)  # locate-real's default
    t_read = time.time() - t_floor
    names = ["eq9 (default cfg)", "sorensen (default cfg)", "sorensen exact k=3"] + [f"offsor k={k}" for k in KS] + ["sorensen exact k=5"]
    err = {n: [] for n in names}
    err_all = {"eq9": [], "sorensen": []}  # every held-out scan: locate-real's numbers
    offs_all, offs_nb, clipped_all, clipped_nb = [], [], [], []
    t_search, t_rerank, n_rr = 0.0, 0.0, 0
    max_chk = 0.0
    n_top_diff = 0
    n_refs, n_scans = [], 0
    total = 0
    fold_data = []
    for _, test_idx in split:
        held = set(test_idx)
        train = [w for i, w in enumerate(walks) if i not in held]
        test = [walks[i] for i in test_idx]
        if not train or not any(w.scans for w in test):
            continue
        fold_data.append((train, test))
        total += sum(len(w.scans) for w in test)
    rng = np.random.default_rng(0)
    sub = np.sort(rng.choice(total, MAX_Q, replace=False)) if MAX_Q and total > 2 * MAX_Q else np.arange(total)
    start = 0
    index_kinds = set()
    walk_of = []
    for train, test in fold_data:
        rm = oracle_radio_map(train)
        truth = oracle_radio_map(test).xy
        queries = [dict(sc.readings) for w in test for sc in w.scans]
        qwalk = np.array([w.session_id for w in test for sc in w.scans])
        sel = sub[(sub >= start) & (sub < start + len(queries))] - start
        start += len(queries)
        n_refs.append(len(rm))
        n_scans += len(queries)
        for m in ("eq9", "sorensen"):
            loc = KnnLocator(rm, KnnConfig(metric=m), threads=1)
            index_kinds.add(f"{m}:{loc.index_kind}")
            res = loc.locate(queries)
            e_all = np.linalg.norm(res.xy - truth, axis=1)
            err_all[m].append(e_all)
            err[f"{m} (default cfg)"].append(e_all[sel])
        qsel = [queries[j] for j in sel]
        walk_of.append(qwalk[sel])
        tr = truth[sel]
        t0 = time.perf_counter()
        res = KnnLocator(rm, KnnConfig(k=NC, metric="sorensen", index="exact"), threads=1).locate(qsel)
        t_search += time.perf_counter() - t0
        cand, dk = res.neighbours, res.distances
        qm = rm.encode(qsel).values.tocsr()
        t0 = time.perf_counter()
        d0, d1, raw = offset_rerank(rm, qm, cand)
        # re-rank (stable: ties keep the Sørensen order) and the estimates; timed with the distances
        order = np.argsort(d1, axis=1, kind="stable")
        idx1 = np.take_along_axis(cand, order, 1)
        dd1 = np.take_along_axis(d1, order, 1)
        idx1[~np.isfinite(dd1)] = -1
        ests = {k: estimate(rm.xy, idx1, dd1, k) for k in KS}
        t_rerank += time.perf_counter() - t0
        n_rr += len(sel)
        fin = np.isfinite(dk)
        if fin.any():
            max_chk = max(max_chk, float(np.abs(d0[fin] - dk[fin]).max()))
        for k in KS:
            err[f"offsor k={k}"].append(np.linalg.norm(ests[k] - tr, axis=1))
            err[f"sorensen exact k={k}"].append(np.linalg.norm(estimate(rm.xy, cand, dk, k) - tr, axis=1))
        n_top_diff += int((idx1[:, 0] != cand[:, 0]).sum())
        ok = np.isfinite(raw)
        offs_all.append(np.clip(raw[ok], -OFF_CLIP, OFF_CLIP))
        clipped_all.append(np.abs(raw[ok]) > OFF_CLIP)
        # the offsets of the k=3 neighbours chosen by the re-ranking
        raw_sorted = np.take_along_axis(raw, order, 1)[:, :3]
        okn = np.isfinite(raw_sorted)
        offs_nb.append(np.clip(raw_sorted[okn], -OFF_CLIP, OFF_CLIP))
        clipped_nb.append(np.abs(raw_sorted[okn]) > OFF_CLIP)
        print(f"  fold: {len(rm)} refs, {len(queries)} scans, {len(sel)} scored, {time.time() - t_floor:.0f}s", flush=True)
    oa, on = np.concatenate(offs_all), np.concatenate(offs_nb)
    row = {"floor": folder, "walks": len(walks), "folds": len(split), "scans": n_scans, "scored": int(len(sub)),
           "subsample": bool(len(sub) < total), "map_refs_mean": int(np.mean(n_refs)), "index": sorted(index_kinds),
           "check_max_abs_diff_sorensen": max_chk, "top1_changed_share": n_top_diff / max(n_rr, 1),
           "ms_per_query_exact_top100": 1e3 * t_search / max(n_rr, 1), "ms_per_query_rerank": 1e3 * t_rerank / max(n_rr, 1),
           "offset_pairs": {"median_abs": float(np.median(np.abs(oa))), "median": float(np.median(oa)),
                            "share_clipped": float(np.concatenate(clipped_all).mean())},
           "offset_k3_neighbours": {"median_abs": float(np.median(np.abs(on))), "median": float(np.median(on)),
                                    "share_clipped": float(np.concatenate(clipped_nb).mean())},
           "seconds": round(time.time() - t_floor, 1), "read_seconds": round(t_read, 1), "err": {}}
    if OUT:  # per-scan errors and walks, for paired walk-bootstrap intervals
        np.savez_compressed(OUT.replace(".json", "") + "_" + folder.rstrip("/").split("/")[-1] + ".npz", walk=np.concatenate(walk_of),
                            names=np.array(names), err=np.array([np.concatenate(err[n]) for n in names], float))
    for m, v in err_all.items():
        row["err"][f"ALL {m} (default cfg)"] = stats(np.concatenate(v))
    for n in names:
        row["err"][n] = stats(np.concatenate(err[n]))
    return row


rows = []
for folder in args:
    print(f"== {folder}", flush=True)
    row = run_floor(folder)
    rows.append(row)
    print(f"{row['floor']}: walks {row['walks']} folds {row['folds']} scans {row['scans']} scored {row['scored']} "
          f"refs~{row['map_refs_mean']} index {row['index']} {row['seconds']}s (read {row['read_seconds']}s)")
    print(f"  check max|my sorensen - KnnLocator| = {row['check_max_abs_diff_sorensen']:.2e}; top-1 changed by re-rank "
          f"{100 * row['top1_changed_share']:.1f}%; exact top-100 {row['ms_per_query_exact_top100']:.2f} ms/q, "
          f"re-rank {row['ms_per_query_rerank']:.2f} ms/q")
    print(f"  offsets all pairs: median|o| {row['offset_pairs']['median_abs']:.1f} dB, median {row['offset_pairs']['median']:+.1f}, "
          f"clipped {100 * row['offset_pairs']['share_clipped']:.1f}%; chosen k=3 neighbours: median|o| "
          f"{row['offset_k3_neighbours']['median_abs']:.1f}, median {row['offset_k3_neighbours']['median']:+.1f}, "
          f"clipped {100 * row['offset_k3_neighbours']['share_clipped']:.1f}%")
    for n, s in row["err"].items():
        print(f"  {n:26s} n {s['n']:6d} located {s['located']:6d} mean {s['mean']:6.2f} median {s['median']:6.2f} p90 {s['p90']:6.2f}")
    sys.stdout.flush()
    if OUT:
        with open(OUT, "w") as fh:
            json.dump(rows, fh, indent=1)
