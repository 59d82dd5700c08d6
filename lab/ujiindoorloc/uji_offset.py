"""UJIIndoorLoc validation: device-robust kNN formulations (per-query RSS offset, rank-based
fingerprints, per-phone normalisation of the training set, floor decision by a wider vote).

    python -m lab.ujiindoorloc.uji_offset

Training set = map, validation set = queries; validation positions/floors/buildings are used only
to score. Re-ranking variants re-rank the Sørensen (powed, exact) top-100 candidates of each query.

Default chosen BEFORE the run (principled, not tuned): "offset-Sørensen" (1a): per (query,
candidate) pair, the median RSS difference over the commonly heard APs (clipped to +-20 dB) is
added to the query, then the usual powed Sørensen distance over the union of heard APs (so APs
heard by only one side are penalised by what they weigh); k = 3 inverse-distance (the product's
k); floor by the 20-neighbour distance-weighted vote over that ranking, position = k = 3 among the
candidates on the voted building/floor (4c).
"""
from __future__ import annotations

import dataclasses
import sys
import time

import numpy as np

from graphslam import KnnConfig, KnnLocator
from lab.bench.uji import TEST_FILE, TRAIN_FILE, find_uji_file
from lab.bench.ujiindoorloc import read_ujiindoorloc

D = "../shared/data/ujiindoorloc"
NC = 100  # candidates per query
EPS = 1e-6
MISS = -110.0  # graphslam DEFAULT_MISSING_DBM: shifted value = rss - MISS
MINR = -100.0  # graphslam DEFAULT_MIN_RSSI_DBM: weaker readings are dropped
OFF_CLIP = 20.0
PEN_DB = 10.0

t00 = time.perf_counter()
tr = read_ujiindoorloc(find_uji_file(D, TRAIN_FILE))
te = read_ujiindoorloc(find_uji_file(D, TEST_FILE))
R = np.where(tr.rssi >= MINR, tr.rssi, np.nan)  # as the radio map sees it
Qr = np.where(te.rssi >= MINR, te.rssi, np.nan)
known = (~np.isnan(R)).any(0)  # APs the map ever heard
Qr[:, ~known] = np.nan  # Sørensen leaves unknown query APs out
xy, fl, bd = tr.xy, tr.floor, tr.building
fb = bd * 10 + fl  # building-floor code
txy, tfl, tbd = te.xy, te.floor, te.building
rows: list[tuple] = []


def powed(v_dbm: np.ndarray) -> np.ndarray:
    v = np.clip(v_dbm - MISS, 0.0, -MISS)
    return np.where(np.isnan(v_dbm), 0.0, (v / -MISS) ** np.e)


def vote(lab: np.ndarray, idx: np.ndarray, w: np.ndarray) -> np.ndarray:
    out = np.empty(len(idx), lab.dtype)
    for i in range(len(idx)):
        u, inv = np.unique(lab[idx[i]], return_inverse=True)
        out[i] = u[np.argmax(np.bincount(inv, weights=w[i]))]
    return out


def score(name: str, est: np.ndarray, floor: np.ndarray, bld: np.ndarray, secs: float, note: str = "") -> None:
    e = np.linalg.norm(est - txy, axis=1)
    r = (name, e.mean(), np.median(e), np.percentile(e, 90), 100 * np.mean(floor == tfl), 100 * np.mean(bld == tbd), secs, note)
    rows.append(r)
    print(f"{r[0]:<52s} mean {r[1]:6.3f}  med {r[2]:6.3f}  p90 {r[3]:6.2f}  floor {r[4]:5.1f}  bld {r[5]:5.1f}  {r[6]:6.1f}s {note}", flush=True)


def knn(idx: np.ndarray, d: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """idx, d sorted ascending per row; inverse-distance weights over the first k."""
    i, w = idx[:, :k], 1.0 / (d[:, :k] + EPS)
    est = (w[:, :, None] * xy[i]).sum(1) / w.sum(1)[:, None]
    return est, vote(fl, i, w), vote(bd, i, w)


def rerank(idx: np.ndarray, D_: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    o = np.argsort(D_, axis=1, kind="stable")
    return np.take_along_axis(idx, o, 1), np.take_along_axis(D_, o, 1)


def floor_then_knn(idx, d, kf, k=3, mode="vote", m=5):
    """Decide building+floor from the ranking, then kNN (k) among the candidates on it."""
    Q = len(idx)
    est, f_out, b_out = np.zeros((Q, 2)), np.zeros(Q, int), np.zeros(Q, int)
    for i in range(Q):
        lab = fb[idx[i]]
        if mode == "vote":
            w = 1.0 / (d[i, :kf] + EPS)
            u, inv = np.unique(lab[:kf], return_inverse=True)
            win = u[np.argmax(np.bincount(inv, weights=w))]
        else:  # summed similarity of each floor's m best candidates
            best, win = -1.0, lab[0]
            for f in np.unique(lab):
                s = (1.0 - d[i][lab == f][:m]).sum()
                if s > best:
                    best, win = s, f
        sel = np.flatnonzero(lab == win)[:k]
        w = 1.0 / (d[i, sel] + EPS)
        est[i] = (w[:, None] * xy[idx[i, sel]]).sum(0) / w.sum()
        f_out[i], b_out[i] = win % 10, win // 10
    return est, f_out, b_out


def sorensen_top(map_rssi: np.ndarray | None, q_rssi: np.ndarray | None, k: int = NC):
    trx = tr if map_rssi is None else dataclasses.replace(tr, rssi=map_rssi)
    tex = te if q_rssi is None else dataclasses.replace(te, rssi=q_rssi)
    loc = KnnLocator(trx.to_radio_map(), KnnConfig(k=k, metric="sorensen", index="exact"), threads=1)
    res = loc.locate(tex.fingerprints())
    return res.neighbours, res.distances


# ---------------------------------------------------------------- baseline
t0 = time.perf_counter()
rm = tr.to_radio_map()
assert np.array_equal(rm.xy, xy)
idx0, d0 = sorensen_top(None, None)
t_base = time.perf_counter() - t0
for k in (3,):
    e, f, b = knn(idx0, d0, k)
    score(f"B0 Sørensen k={k} (default)", e, f, b, t_base)

# ---------------------------------------------------------------- pairwise distances on candidates
t0 = time.perf_counter()
Q = len(Qr)
names = ["sor_chk", "offsor_med", "offsor_mean", "offL1_pen", "offL1_lvl", "rank_foot", "rank_kendall"]
Dm = {n: np.full((Q, NC), np.inf) for n in names}
tsec = {n: 0.0 for n in names}
pair_off = np.zeros((Q, NC))
for i in range(Q):
    c = idx0[i]
    cols = np.flatnonzero(~np.isnan(Qr[i]) | (~np.isnan(R[c])).any(0))
    qv, rv = Qr[i, cols], R[c][:, cols]  # (n,), (NC, n)
    hq, hr = ~np.isnan(qv), ~np.isnan(rv)
    C = hq[None, :] & hr
    U = hq[None, :] | hr
    nC, nU = C.sum(1), U.sum(1)
    diff = np.where(C, rv - qv[None, :], np.nan)
    with np.errstate(all="ignore"):
        o_med = np.clip(np.nan_to_num(np.nanmedian(diff, 1)), -OFF_CLIP, OFF_CLIP)
        o_mean = np.clip(np.nan_to_num(np.nanmean(diff, 1)), -OFF_CLIP, OFF_CLIP)
    pair_off[i] = o_med
    pr = powed(rv)
    for nm, o in (("sor_chk", np.zeros(NC)), ("offsor_med", o_med), ("offsor_mean", o_mean)):
        s = time.perf_counter()
        pq = powed(qv[None, :] + o[:, None])
        pq = np.where(hq[None, :], pq, 0.0)
        Dm[nm][i] = np.maximum(1.0 - 2.0 * np.minimum(pq, pr).sum(1) / (pq.sum(1) + pr.sum(1)), 0.0)
        tsec[nm] += time.perf_counter() - s
    s = time.perf_counter()
    qs = qv[None, :] + o_med[:, None]  # query in the candidate's device units
    l1 = np.where(C, np.abs(qs - rv), 0.0).sum(1)
    nX = (U & ~C).sum(1)
    Dm["offL1_pen"][i] = (l1 + PEN_DB * nX) / np.maximum(nU, 1)
    gap = np.where(hq[None, :] & ~hr, np.maximum(qs - MINR, 0.0), 0.0) + np.where(hr & ~hq[None, :], np.maximum(rv - MINR, 0.0), 0.0)
    Dm["offL1_lvl"][i] = (l1 + gap.sum(1)) / np.maximum(nU, 1)
    tsec["offL1_pen"] += (time.perf_counter() - s) / 2
    tsec["offL1_lvl"] += (time.perf_counter() - s) / 2
    # rank-based: ranks within the common set, Jaccard on the heard sets
    s = time.perf_counter()
    jac = 1.0 - nC / np.maximum(nU, 1)
    hcol = np.flatnonzero(hq)  # the common set lies within the query's heard APs
    Cq = C[:, hcol]
    qm = np.where(Cq, qv[hcol][None, :], np.nan)
    rmm = np.where(Cq, rv[:, hcol], np.nan)
    sq = np.sign(qm[:, :, None] - qm[:, None, :])  # (NC, n, n), nan outside C x C
    sr = np.sign(rmm[:, :, None] - rmm[:, None, :])
    valid = Cq[:, :, None] & Cq[:, None, :]
    # average ranks within C (ties half)
    rq = np.where(valid, (sq > 0) + 0.5 * (sq == 0), 0.0).sum(2) + 0.5  # self counted as half tie -> +0.5 -> rank from 1
    rr = np.where(valid, (sr > 0) + 0.5 * (sr == 0), 0.0).sum(2) + 0.5
    foot = np.where(Cq, np.abs(rq - rr), 0.0).sum(1) / np.maximum(np.floor(nC**2 / 2.0), 1)
    foot = np.where(nC >= 2, foot, 1.0)
    Dm["rank_foot"][i] = 0.5 * foot + 0.5 * jac
    tsec["rank_foot"] += time.perf_counter() - s
    s = time.perf_counter()
    prod = np.where(valid, sq * sr, 0.0).sum((1, 2))
    npairs = nC * (nC - 1)
    ken = np.where(npairs > 0, (1.0 - prod / np.maximum(npairs, 1)) / 2.0, 1.0)
    Dm["rank_kendall"][i] = 0.5 * ken + 0.5 * jac
    tsec["rank_kendall"] += time.perf_counter() - s
t_pairs = time.perf_counter() - t0
chk = np.abs(Dm["sor_chk"] - d0)
print(f"check: my Sørensen vs graphslam's on candidates: max |diff| {chk.max():.2e}  (pair loop {t_pairs:.1f}s)", flush=True)

rr_ = {}
for nm, ks in (("offsor_med", (3, 5, 7, 10)), ("offsor_mean", (3,)), ("offL1_pen", (3, 5)), ("offL1_lvl", (3, 5)),
               ("rank_foot", (3, 5)), ("rank_kendall", (3, 5))):
    ii, dd = rerank(idx0, Dm[nm])
    rr_[nm] = (ii, dd)
    for k in ks:
        e, f, b = knn(ii, dd, k)
        score(f"1/2 {nm} k={k}", e, f, b, t_base + tsec[nm])
# a rank/offset blend: mean of the two normalised rankings' distances (offset-Sørensen + footrule)
ii, dd = rerank(idx0, 0.5 * Dm["offsor_med"] + 0.5 * Dm["rank_foot"])
e, f, b = knn(ii, dd, 3)
score("1+2 0.5 offsor_med + 0.5 rank_foot k=3", e, f, b, t_base + tsec["offsor_med"] + tsec["rank_foot"])

# ---------------------------------------------------------------- 3: per-phone offsets (training only)
t0 = time.perf_counter()
phone = np.array([s.split("-p")[1] for s in tr.session_ids])
ph_u, ph_i = np.unique(phone, return_inverse=True)
P = len(ph_u)
# reference points: identical coordinates and floor; per phone the mean RSS per AP there
key = np.unique(np.column_stack([np.round(xy, 2), fl, bd]), axis=0, return_inverse=True)[1].ravel()
obs_a, obs_b, obs_v, obs_w = [], [], [], []
order = np.lexsort((ph_i, key))
bounds = np.flatnonzero(np.diff(key[order])) + 1
for grp in np.split(order, bounds):
    phs = np.unique(ph_i[grp])
    if len(phs) < 2:
        continue
    with np.errstate(all="ignore"):
        means = {p: np.nanmean(R[grp[ph_i[grp] == p]], 0) for p in phs}
    for a_ in range(len(phs)):
        for b_ in range(a_ + 1, len(phs)):
            dv = means[phs[a_]] - means[phs[b_]]
            dv = dv[~np.isnan(dv)]
            if len(dv) >= 3:
                obs_a.append(phs[a_]); obs_b.append(phs[b_]); obs_v.append(np.median(dv)); obs_w.append(np.sqrt(len(dv)))
A = np.zeros((len(obs_v) + 1, P))
A[np.arange(len(obs_v)), obs_a] = 1.0
A[np.arange(len(obs_v)), obs_b] = -1.0
A[-1, :] = 1.0  # sum of offsets = 0
w_ = np.append(obs_w, 10.0)
off = np.linalg.lstsq(A * w_[:, None], np.append(obs_v, 0.0) * w_, rcond=None)[0]
print("training phone offsets (dB, level - common):", {ph_u[p]: round(off[p], 1) for p in range(P)},
      f"from {len(obs_v)} co-located phone pairs", flush=True)
Rn = np.clip(R - off[ph_i][:, None], MINR, 0.0)  # NaN stays NaN
t_phone = time.perf_counter() - t0
t0 = time.perf_counter()
idxN, dN = sorensen_top(Rn, None)
tN = time.perf_counter() - t0 + t_phone
e, f, b = knn(idxN, dN, 3)
score("3a phone-normalised map, Sørensen k=3", e, f, b, tN)


def blind_offsets(map_R, idx, kk=10):
    """Per query: median over its kk nearest of the pair median (map - query) difference."""
    o = np.zeros(Q)
    for i in range(Q):
        diff = map_R[idx[i, :kk]] - Qr[i][None, :]
        with np.errstate(all="ignore"):
            pm = np.nanmedian(diff, 1)
        pm = pm[~np.isnan(pm)]
        o[i] = np.clip(np.median(pm), -OFF_CLIP, OFF_CLIP) if len(pm) else 0.0
    return o


def shifted_queries(o):
    return np.clip(Qr + o[:, None], MINR, 0.0)


for label, mapR, idxS, dS, tS in (("raw map", None, idx0, d0, t_base), ("phone-normalised map", Rn, idxN, dN, tN)):
    base_R = R if mapR is None else mapR
    t0 = time.perf_counter()
    o1 = blind_offsets(base_R, idxS)
    i1, d1 = sorensen_top(mapR, shifted_queries(o1))
    t1 = time.perf_counter() - t0
    e, f, b = knn(i1, d1, 3)
    score(f"3b {label} + blind query offset (1 pass) k=3", e, f, b, tS + t1, f"offset med {np.median(o1):+.1f} dB")
    t0 = time.perf_counter()
    # second pass: re-estimate the offset against the new neighbours, from the unshifted query
    o2 = blind_offsets(base_R, i1)
    i2, d2 = sorensen_top(mapR, shifted_queries(o2))
    t2 = time.perf_counter() - t0
    e, f, b = knn(i2, d2, 3)
    score(f"3c {label} + blind query offset (iterated) k=3", e, f, b, tS + t1 + t2, f"offset med {np.median(o2):+.1f} dB")
    # transductive, no labels: pool the blind offsets of each validation phone (PHONEID is a device attribute)
    vph = np.array([s.split("-p")[1] for s in te.session_ids])
    op = o2.copy()
    for p in np.unique(vph):
        op[vph == p] = np.median(o2[vph == p])
    i3, d3 = sorensen_top(mapR, shifted_queries(op))
    e, f, b = knn(i3, d3, 3)
    score(f"3d {label} + per-validation-phone pooled offset k=3", e, f, b, tS + t1 + t2,
          "phones " + " ".join(f"{p}:{op[vph == p][0]:+.1f}" for p in np.unique(vph)))

# ---------------------------------------------------------------- 4: floor decisions
for nm, (ii, dd), tt in (("Sørensen", (idx0, d0), t_base), ("offsor_med", rr_["offsor_med"], t_base + tsec["offsor_med"])):
    for kf in (10, 20, 30):
        s = time.perf_counter()
        e, f, b = floor_then_knn(ii, dd, kf)
        score(f"4 {nm}: floor vote k={kf} (1/d), then k=3 on it", e, f, b, tt + time.perf_counter() - s)
    s = time.perf_counter()
    e, f, b = floor_then_knn(ii, dd, 0, mode="sum", m=5)
    score(f"4 {nm}: floor by summed sim of best 5, then k=3", e, f, b, tt + time.perf_counter() - s)

# diagnostic (labels used for scoring only): the best single candidate among the top-N of a ranking
for nm, (ii, dd) in (("Sørensen", (idx0, d0)), ("offsor_med", rr_["offsor_med"])):
    ce = np.linalg.norm(xy[ii] - txy[:, None, :], axis=2)
    print(f"oracle nearest-to-truth candidate in {nm} top-N:", {n: round(float(ce[:, :n].min(1).mean()), 2) for n in (1, 3, 10, 100)})
print(f"\ntotal {time.perf_counter() - t00:.0f}s\n")
print("| variant | mean m | median m | p90 m | floor % | building % | runtime s |")
print("|---|---|---|---|---|---|---|")
for r in rows:
    print(f"| {r[0]} | {r[1]:.3f} | {r[2]:.2f} | {r[3]:.2f} | {r[4]:.1f} | {r[5]:.1f} | {r[6]:.1f} |")
sys.stdout.flush()
