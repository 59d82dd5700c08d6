#!/usr/bin/env python3
"""What limits walk placement on real crowdsourced phone walks (ILC 2.0 site1): three measurements.

Uses the ground truth (the surveyor's labelled waypoints) to *measure* the information in
the data; nothing here feeds the solver. Per floor:

1. **Fingerprint resolution**: for every scan, its most similar scan of another walk
   (eq. 9, and two alternatives from the literature: cosine and Euclidean on "powed"
   RSS, Torres-Sospedra et al.); the true distance between the two (median, p90).
2. **Pairwise walk registration**: for every pair of walks, nearest-fingerprint matches
   both ways, 2-point RANSAC (inliers within 5 m) as ``registration`` does; fraction of
   pairs whose transform is right (walk displaced < 5 m mean), overall and for the pairs
   with the best matches (lowest mean RSS distance).
3. **Walk-to-map bound**: every other walk placed at its TRUE pose (a perfect map); each
   walk registered to it from its k = 3 nearest fingerprints per scan (RANSAC, Cauchy
   score). Fraction of walks then within 5 m / 10 m: an upper bound for any method that
   places a walk by registering it to the others' fingerprints.

4. **Soft walk-to-map, the issue's metric**: the same perfect map; each walk placed by a soft
   likelihood (its scans against their k = 10 most similar map scans, Gaussian 4 m kernel,
   hypotheses from 2-point matches, EM refinement); per-walk mean WAYPOINT error: fraction
   within 5 m, mean over the best 80 % of walks chosen by an oracle and by the likelihood.
5. **Is the truth a fixed point?** Start every walk at its TRUE pose and re-register each to
   all the others (local EM of 4., six sweeps); waypoint error after one global SE(2) fit,
   per sweep. Any method that places walks by "similar fingerprints are close" optimises
   this objective: if the error grows from the truth, its optimum is not the truth.
6. **Same for access points as landmarks**: fit every AP's position, P0 and gamma (the
   ``fit-aps`` model) to the TRUE layout, re-localise each walk by its path-loss likelihood
   (soft-L1, 6 dB), refit, repeat (two sweeps).

Truth per walk: the rigid SE(2) fit of its dead reckoning to its own waypoints (itself
~1.5-1.9 m off, the drift within a walk).

    python lab/survey/ilc_diagnostics.py [SITE_DIR] [--floors B1,F1] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from graphslam import (
    associate, DistanceEngine, fit_se2, floor_folders, GraphSlamError, interpolate_xy, ransac_se2,
    read_survey, se2_apply, se2_compose,
)


REPO = Path(__file__).resolve().parents[2]
DEFAULT_SITE = Path(os.environ.get("GRAPHSLAM_DATA", REPO.parent / "shared" / "data")) / "ilc20" / "site1"
INLIER_M = 5.0


def _inverse(T: NDArray) -> NDArray:
    c, s = np.cos(T[2]), np.sin(T[2])
    return np.array([-(c * T[0] + s * T[1]), s * T[0] - c * T[1], -T[2]])


def _true_transforms(survey) -> NDArray:  # noqa: ANN001 - a Survey
    out = []
    for w in survey:
        est = interpolate_xy(w.steps, np.array([m.t_ns for m in w.landmarks], float))
        out.append(fit_se2(est, np.array([[m.x, m.y] for m in w.landmarks])))
    return np.array(out)


def _pct(x: NDArray) -> dict[str, float]:
    return {"median_m": round(float(np.median(x)), 2), "p90_m": round(float(np.percentile(x, 90)), 2)}


def resolution(D_by_name: dict[str, NDArray], true_d: NDArray) -> dict[str, dict[str, float]]:
    n = len(true_d)
    return {name: _pct(true_d[np.arange(n), np.argmin(D, axis=1)]) for name, D in D_by_name.items()}


def pairwise(D: NDArray, P: NDArray, ws: NDArray, T: NDArray, rng: np.random.Generator) -> dict[str, float]:
    W = len(T)
    idx = [np.flatnonzero(ws == w) for w in range(W)]
    right, quality = [], []
    for a in range(W):
        for b in range(a + 1, W):
            Dab = D[np.ix_(idx[a], idx[b])]
            if Dab.size == 0:  # a walk without associated scans
                continue
            j, i = np.argmin(Dab, 1), np.argmin(Dab, 0)
            da, db = Dab[np.arange(len(j)), j], Dab[i, np.arange(Dab.shape[1])]
            ia, ib = np.flatnonzero(np.isfinite(da)), np.flatnonzero(np.isfinite(db))
            pa = np.concatenate([idx[a][ia], idx[a][i[ib]]])
            pb = np.concatenate([idx[b][j[ia]], idx[b][ib]])
            if len(pa) < 4:
                continue
            Tr, inl = ransac_se2(P[pa], P[pb], inlier_m=INLIER_M, rng=rng)
            if inl.sum() < 4:
                continue
            Tt = se2_compose(_inverse(T[a]), T[b])
            xy = P[idx[b]]
            right.append(np.linalg.norm(se2_apply(Tr, xy) - se2_apply(Tt, xy), axis=1).mean() < INLIER_M)
            quality.append(float(np.concatenate([da[ia], db[ib]]).mean()))
    right_a, q = np.array(right), np.array(quality)
    out = {"pairs_registered": int(len(right_a)), "right_fraction": round(float(right_a.mean()), 3)}
    order = np.argsort(q)
    for top in (25, 100):
        sel = order[:top]
        out[f"right_fraction_best_{top}"] = round(float(right_a[sel].mean()), 3)
    return out


def walk_to_map(D: NDArray, P: NDArray, ws: NDArray, T: NDArray, rng: np.random.Generator, k: int = 3) -> dict[str, float]:
    W = len(T)
    pt = _placed(P, ws, T)
    errs = []
    for w in np.unique(ws):
        mine, ref = np.flatnonzero(ws == w), np.flatnonzero(ws != w)
        Dw = D[np.ix_(mine, ref)]
        o = np.argsort(Dw, axis=1)[:, :k]
        fin = np.isfinite(np.take_along_axis(Dw, o, 1)).ravel()
        q = np.repeat(P[mine], k, axis=0)[fin]
        p = pt[ref[o.ravel()][fin]]
        if len(q) < 2:
            errs.append(np.inf)
            continue
        n = len(q)
        a, b = rng.integers(0, n, 2000), rng.integers(0, n, 2000)
        dp, dq = p[b] - p[a], q[b] - q[a]
        g = (a != b) & (np.linalg.norm(dq, axis=1) > 3)
        if not g.any():
            errs.append(np.inf)
            continue
        a, b, dp, dq = a[g], b[g], dp[g], dq[g]
        th = np.arctan2(dp[:, 1], dp[:, 0]) - np.arctan2(dq[:, 1], dq[:, 0])
        c, s = np.cos(th), np.sin(th)
        mq, mp = (q[a] + q[b]) / 2, (p[a] + p[b]) / 2
        tx, ty = mp[:, 0] - (c * mq[:, 0] - s * mq[:, 1]), mp[:, 1] - (s * mq[:, 0] + c * mq[:, 1])
        px = c[:, None] * q[None, :, 0] - s[:, None] * q[None, :, 1] + tx[:, None]
        py = s[:, None] * q[None, :, 0] + c[:, None] * q[None, :, 1] + ty[:, None]
        score = (1.0 / (1.0 + (np.hypot(px - p[None, :, 0], py - p[None, :, 1]) / INLIER_M) ** 2)).sum(1)
        best = int(np.argmax(score))
        Tb = np.array([tx[best], ty[best], th[best]])
        errs.append(float(np.linalg.norm(se2_apply(Tb, P[mine]) - se2_apply(T[w], P[mine]), axis=1).mean()))
    e = np.array(errs)
    # walks without scans cannot be registered: they count as misses
    e = np.concatenate([e, np.full(W - len(np.unique(ws)), np.inf)])
    return {"walks_without_scans": int(W - len(np.unique(ws))), "within_5m": round(float(np.mean(e < 5)), 3), "within_10m": round(float(np.mean(e < 10)), 3)}


def _waypoint_errors(survey, Tw: NDArray, global_fit: bool) -> tuple[NDArray, NDArray]:  # noqa: ANN001
    """Per-waypoint errors of walks placed by ``Tw`` (optionally after one SE(2) fit) and walk index."""
    est, tru, wid = [], [], []
    for w, sess in enumerate(survey):
        if not sess.landmarks or not np.isfinite(Tw[w]).all():
            continue
        e = interpolate_xy(sess.steps, np.array([m.t_ns for m in sess.landmarks], float))
        est.append(se2_apply(Tw[w], e))
        tru.append(np.array([[m.x, m.y] for m in sess.landmarks]))
        wid += [w] * len(sess.landmarks)
    e_xy, t_xy = np.concatenate(est), np.concatenate(tru)
    if global_fit:
        e_xy = se2_apply(fit_se2(e_xy, t_xy), e_xy)
    return np.linalg.norm(e_xy - t_xy, axis=1), np.array(wid)


def _soft_neighbours(Dq: NDArray, k: int, tau_db: float) -> tuple[NDArray, NDArray]:
    o = np.argsort(Dq, axis=1)[:, :k]
    dk = np.take_along_axis(Dq, o, 1)
    return o, np.exp(-(dk - dk[:, :1]) / tau_db)


def _em_refine(q: NDArray, Pk: NDArray, w: NDArray, T: NDArray, sigma_m: float, iters: int = 10) -> NDArray:
    """EM over soft correspondences: each scan to its k candidates, Gaussian kernel + outlier mass."""
    k = Pk.shape[1]
    for _ in range(iters):
        d2 = ((se2_apply(T, q)[:, None, :] - Pk) ** 2).sum(2)
        r = w * np.exp(-d2 / (2 * sigma_m**2))
        r = r / (r.sum(1, keepdims=True) + 0.05 * w.sum(1, keepdims=True))
        if r.sum() < 1e-6:
            break
        T = fit_se2(np.repeat(q, k, 0), Pk.reshape(-1, 2), r.ravel() + 1e-12)
    return T


def soft_register(
    q: NDArray, P: NDArray, Dq: NDArray, rng: np.random.Generator, *, k: int = 10, tau_db: float = 3.0,
    sigma_m: float = 4.0, hypotheses: int = 3000,
) -> tuple[NDArray | None, float]:
    """Place a walk (scan positions ``q`` in its own frame) on map positions ``P`` from RSS distances
    ``Dq``: best of 2-point hypotheses by soft likelihood, then EM. (T, log-likelihood per scan)."""
    o, w = _soft_neighbours(Dq, k, tau_db)
    n = len(q)
    ia, ib = rng.integers(0, n, hypotheses), rng.integers(0, n, hypotheses)
    pa, pb = P[o[ia, rng.integers(0, 3, hypotheses)]], P[o[ib, rng.integers(0, 3, hypotheses)]]
    dq, dp = q[ib] - q[ia], pb - pa
    lq = np.linalg.norm(dq, axis=1)
    g = (ia != ib) & (lq > 3) & (np.abs(lq - np.linalg.norm(dp, axis=1)) < 8)
    if not g.any():
        return None, -np.inf
    ia, ib, pa, pb, dq, dp = ia[g], ib[g], pa[g], pb[g], dq[g], dp[g]
    th = np.arctan2(dp[:, 1], dp[:, 0]) - np.arctan2(dq[:, 1], dq[:, 0])
    c, s = np.cos(th), np.sin(th)
    mq, mp = (q[ia] + q[ib]) / 2, (pa + pb) / 2
    tx, ty = mp[:, 0] - (c * mq[:, 0] - s * mq[:, 1]), mp[:, 1] - (s * mq[:, 0] + c * mq[:, 1])
    Pk, wn = P[o], w / w.sum(1, keepdims=True)
    score = np.empty(len(th))
    for a in range(0, len(th), 500):  # (H, n, k) in blocks
        b = slice(a, a + 500)
        X = c[b, None] * q[None, :, 0] - s[b, None] * q[None, :, 1] + tx[b, None]
        Y = s[b, None] * q[None, :, 0] + c[b, None] * q[None, :, 1] + ty[b, None]
        d2 = (X[:, :, None] - Pk[None, :, :, 0]) ** 2 + (Y[:, :, None] - Pk[None, :, :, 1]) ** 2
        score[b] = np.log(0.05 + (wn[None] * np.exp(-d2 / (2 * sigma_m**2))).sum(2)).sum(1)
    best = int(np.argmax(score))
    T = _em_refine(q, Pk, w, np.array([tx[best], ty[best], th[best]]), sigma_m)
    return T, float(score[best]) / n


def soft_walk_to_map(survey, D: NDArray, P: NDArray, ws: NDArray, T: NDArray, rng: np.random.Generator) -> dict:  # noqa: ANN001
    pt = _placed(P, ws, T)
    W = len(T)
    Te, score = np.full((W, 3), np.nan), np.full(W, -np.inf)
    for w in range(W):
        mine, ref = np.flatnonzero(ws == w), np.flatnonzero(ws != w)
        if len(mine) >= 2:
            t, sc = soft_register(P[mine], pt[ref], D[np.ix_(mine, ref)], rng)
            if t is not None:
                Te[w], score[w] = t, sc
    err, wid = _waypoint_errors(survey, Te, global_fit=False)
    per = np.full(W, np.inf)
    for w in np.unique(wid):
        per[w] = err[wid == w].mean()
    has_marks = np.array([bool(s.landmarks) for s in survey])
    per, score = per[has_marks], score[has_marks]
    k80 = int(np.ceil(0.8 * len(per)))
    return {
        "within_5m": round(float(np.mean(per < 5)), 3),
        "best_80pct_mean_m_oracle": round(float(np.sort(per)[:k80].mean()), 2),
        "best_80pct_mean_m_by_likelihood": round(float(per[np.argsort(-score)][:k80].mean()), 2),
    }


def _placed(P: NDArray, ws: NDArray, T: NDArray) -> NDArray:
    c, s = np.cos(T[ws, 2]), np.sin(T[ws, 2])
    return np.column_stack([c * P[:, 0] - s * P[:, 1] + T[ws, 0], s * P[:, 0] + c * P[:, 1] + T[ws, 1]])


def truth_fixed_point(survey, D: NDArray, P: NDArray, ws: NDArray, T: NDArray, sweeps: int = 6) -> list[float]:  # noqa: ANN001
    """Waypoint mean error (one SE(2) fit) after each sweep of local re-registration from the truth."""
    Tw = T.copy()
    out = [round(float(_waypoint_errors(survey, Tw, True)[0].mean()), 2)]
    rng = np.random.default_rng(0)
    for _ in range(sweeps):
        for w in rng.permutation(len(T)):
            mine, ref = np.flatnonzero(ws == w), np.flatnonzero(ws != w)
            if len(mine) < 3:
                continue
            o, wt = _soft_neighbours(D[np.ix_(mine, ref)], 10, 3.0)
            Tw[w] = _em_refine(P[mine], _placed(P, ws, Tw)[ref][o], wt, Tw[w].copy(), 4.0)
        out.append(round(float(_waypoint_errors(survey, Tw, True)[0].mean()), 2))
    return out


def ap_fixed_point(survey, fp, P: NDArray, ws: NDArray, T: NDArray, sweeps: int = 2) -> list[float]:  # noqa: ANN001
    """As ``truth_fixed_point`` with access points as landmarks (fit-aps model, path-loss likelihood)."""
    from scipy.optimize import least_squares

    from graphslam import ApModel, fit_ap

    V = fp.fingerprints.values
    miss = fp.fingerprints.missing_dbm
    Vc, Vr = V.tocsc(), V.tocsr()
    Tw = T.copy()
    out = [round(float(_waypoint_errors(survey, Tw, True)[0].mean()), 2)]
    for _ in range(sweeps):
        pos = _placed(P, ws, Tw)
        models = {}
        for j in range(Vc.shape[1]):
            rows = Vc.indices[Vc.indptr[j] : Vc.indptr[j + 1]]
            if len(rows) >= 20:
                m = fit_ap(str(j), pos[rows], Vc.data[Vc.indptr[j] : Vc.indptr[j + 1]] + miss)
                if isinstance(m, ApModel):
                    models[j] = (m.x, m.y, m.p0_dbm, m.gamma)
        A = np.array(list(models.values()))
        col = np.full(Vc.shape[1], -1)
        col[list(models)] = np.arange(len(models))
        for w in range(len(T)):
            mine = np.flatnonzero(ws == w)
            sub = Vr[mine].tocoo()
            keep = col[sub.col] >= 0
            r_i, a_i, rss = sub.row[keep], col[sub.col[keep]], sub.data[keep] + miss
            if len(rss) < 10:
                continue
            q = P[mine]

            def residual(t: NDArray, q: NDArray = q, r_i: NDArray = r_i, a_i: NDArray = a_i, rss: NDArray = rss) -> NDArray:
                d = se2_apply(t, q)[r_i] - A[a_i, :2]
                return A[a_i, 2] - 5 * A[a_i, 3] * np.log10((d * d).sum(1) + 1.0) - rss

            Tw[w] = least_squares(residual, Tw[w], loss="soft_l1", f_scale=6.0).x
        out.append(round(float(_waypoint_errors(survey, Tw, True)[0].mean()), 2))
    return out


def floor(path: Path, seed: int) -> dict:
    t0 = time.perf_counter()
    survey = read_survey([path])
    fp = associate(survey)
    dr = np.concatenate([w.steps.xyh for w in survey])
    P, ws = dr[fp.node, :2], fp.session
    T = _true_transforms(survey)
    pt = _placed(P, ws, T)
    true_d = np.linalg.norm(pt[:, None] - pt[None], axis=2)
    same = ws[:, None] == ws[None, :]
    D, _ = DistanceEngine(fp.fingerprints).block(fp.fingerprints, min_common=3)
    D[same] = np.inf
    V = fp.fingerprints.values.toarray()
    X = (V / -fp.fingerprints.missing_dbm) ** np.e  # powed: ((rss - min) / -min) ** e
    heard = (V > 0).astype(float)
    few = heard @ heard.T < 3
    sq = (X**2).sum(1)
    eucl = np.sqrt(np.maximum(sq[:, None] + sq[None] - 2 * X @ X.T, 0))
    nrm = np.linalg.norm(X, axis=1)
    cos = 1 - (X @ X.T) / np.maximum(np.outer(nrm, nrm), 1e-12)
    for M in (eucl, cos):
        M[same | few] = np.inf
    Dfin = np.where(np.isfinite(D), D, 1e3)  # never-comparable pairs: least similar
    rng = np.random.default_rng(seed)
    return {
        "floor": path.name,
        "walks": len(survey),
        "scans": len(fp),
        "nearest_other_walk_scan": resolution({"eq9": D, "powed_euclidean": eucl, "powed_cosine": cos}, true_d),
        "pairwise_registration": pairwise(D, P, ws, T, rng),
        "walk_to_true_map": walk_to_map(D, P, ws, T, rng),
        "soft_walk_to_true_map": soft_walk_to_map(survey, Dfin, P, ws, T, rng),
        "fingerprint_fixed_point_mean_m_per_sweep": truth_fixed_point(survey, Dfin, P, ws, T),
        "ap_fixed_point_mean_m_per_sweep": ap_fixed_point(survey, fp, P, ws, T),
        "time_s": round(time.perf_counter() - t0, 1),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("site", nargs="?", type=Path, default=DEFAULT_SITE)
    ap.add_argument("--floors", default=None, help="comma-separated (default: every floor folder)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    try:
        folders = floor_folders(args.site, args.floors.split(",") if args.floors else None)
    except GraphSlamError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    for folder in folders:
        print(json.dumps(floor(folder, args.seed)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
