"""Cluster-to-cluster registration by a GP signal field (per AP) of cluster A predicting cluster B's
readings: log-likelihood ratio against the field's prior, over translations (FFT correlation).
Oracle layout (walks at their truth translation) -> the right offset is 0. Truth scores only.
python lab/survey/ap/gpreg.py [ell=3] [sn=4] [minrss=-90]"""
from __future__ import annotations
import re, sys
import numpy as np
from scipy.fft import rfft2, irfft2
sys.path.insert(0, "lab/survey"); sys.path.insert(0, "lab/survey/ap")
from common import load, true_xy

args = dict(a.split("=") for a in sys.argv[1:] if "=" in a)
ELL = float(args.get("ell", 3)); SN = float(args.get("sn", 4)); MINRSS = float(args.get("minrss", -90))
CELL = 1.0
fl = load("../shared/data/ipin2023/b100_f-2")
sv, fp = fl.survey, fl.fp
ids = [s.session_id for s in sv]
trial = np.array([int(re.search(r"Trial(\d+)", i).group(1)) for i in ids])
group = {21: "21", 51: "21", 22: "22", 23: "23", 53: "23", 24: "24", 25: "25", 26: "26", 27: "27", 52: "27"}
clus = np.array([group[t] for t in trial])[fl.sess]
from rigid import rigid_xy
P = rigid_xy(fl) if args.get("oracle") == "rigid" else true_xy(fl)
R = fp.fingerprints.values.toarray() - 110.0  # dBm; unheard -> -110
R[R <= -109.9] = np.nan
R[R < MINRSS] = np.nan


def field(Pa, Ra, lo, shape):
    """Per AP: images A0, A1, A2 (LLR = A0 + A1 r + A2 r^2 relative to the prior) on the grid."""
    gx = lo[0] + (np.arange(shape[0]) + 0.5) * CELL
    gy = lo[1] + (np.arange(shape[1]) + 0.5) * CELL
    G = np.stack(np.meshgrid(gx, gy, indexing="ij"), -1).reshape(-1, 2)
    out = {}
    for a in range(Ra.shape[1]):
        ok = np.isfinite(Ra[:, a])
        if ok.sum() < 8:
            continue
        p, r = Pa[ok], Ra[ok, a]
        c = np.floor((p - lo) / CELL).astype(int)
        key = c[:, 0] * shape[1] + c[:, 1]
        u, inv, n = np.unique(key, return_inverse=True, return_counts=True)
        mean = np.bincount(inv, r) / n
        cx = lo + (np.column_stack([u // shape[1], u % shape[1]]) + 0.5) * CELL
        m0 = r.mean(); sf2 = max(r.var(), 9.0)
        K = sf2 * np.exp(-((cx[:, None] - cx[None]) ** 2).sum(-1) / (2 * ELL**2))
        K[np.diag_indices_from(K)] += SN**2 / n
        L = np.linalg.cholesky(K)
        alpha = np.linalg.solve(L.T, np.linalg.solve(L, mean - m0))
        # only grid cells within 4 ell of data
        d2min = np.full(len(G), np.inf)
        Ks = sf2 * np.exp(-((G[:, None] - cx[None]) ** 2).sum(-1) / (2 * ELL**2))
        mu = m0 + Ks @ alpha
        W = np.linalg.solve(L, Ks.T)
        var = sf2 - (W * W).sum(0)
        V = var + SN**2; V0 = sf2 + SN**2
        A0 = -0.5 * np.log(V) - mu**2 / (2 * V) - (-0.5 * np.log(V0) - m0**2 / (2 * V0))
        A1 = mu / V - m0 / V0
        A2 = -1 / (2 * V) + 1 / (2 * V0)
        out[a] = np.stack([A0, A1, A2]).reshape(3, *shape)
    return out


def register(ca, cb, rots=(0.0,), margin=40.0):
    A = clus == ca; B = clus == cb
    Pa, Pb = P[A], P[B]
    lo = Pa.min(0) - margin; hi = Pa.max(0) + margin
    shape = np.ceil((hi - lo) / CELL).astype(int)
    F = field(Pa, R[A], lo, shape)
    best = []
    for rot in rots:
        c, s = np.cos(rot), np.sin(rot)
        cen = Pb.mean(0)
        q = (Pb - cen) @ np.array([[c, s], [-s, c]]) + cen
        # B's points relative to its own origin qlo
        qlo = q.min(0)
        qs = np.ceil((q.max(0) - qlo) / CELL).astype(int) + 1
        S = (shape[0] + qs[0], shape[1] + qs[1])
        tot = np.zeros(S)
        qc = np.floor((q - qlo) / CELL).astype(int)
        for a, img in F.items():
            ok = np.isfinite(R[B][:, a])
            if not ok.any():
                continue
            r = R[B][ok, a]; qq = qc[ok]
            for k, w in enumerate((np.ones_like(r), r, r * r)):
                im = np.zeros(qs)
                np.add.at(im, (qq[:, 0], qq[:, 1]), w)
                # correlation: out[t] = sum_j img[qq_j + t]
                tot += irfft2(rfft2(img[k], S) * np.conj(rfft2(im, S)), S)
        # index t (in cells) = grid cell of qlo's image; wrap: t in [-qs, shape)
        best.append((tot, rot, qlo))
    return best, lo, shape


names = ["22", "23", "24", "25", "26", "27"]
pairs = [("23", "22"), ("22", "23"), ("23", "24"), ("24", "23"), ("24", "25"), ("25", "24"), ("25", "26"), ("26", "25"), ("26", "27"), ("27", "26"), ("21", "22"), ("22", "21")]
for ca, cb in pairs:
    res, lo, shape = register(ca, cb)
    tot, rot, qlo = res[0]
    S = tot.shape
    # translation for index (i, j): B's qlo goes to lo + (i, j) * CELL (with wrap for negatives)
    ii = np.arange(S[0]); jj = np.arange(S[1])
    ii = np.where(ii >= shape[0], ii - S[0], ii); jj = np.where(jj >= shape[1], jj - S[1], jj)
    TX = lo[0] + ii * CELL - qlo[0]; TY = lo[1] + jj * CELL - qlo[1]
    k = np.unravel_index(np.argmax(tot), S)
    t = np.array([TX[k[0]], TY[k[1]]])
    # value at truth (t=0) and runner-up beyond 5 m
    d = np.sqrt(TX[:, None] ** 2 + TY[None] ** 2)
    at0 = tot[d < 1.0].max()
    far = np.sqrt((TX[:, None] - t[0]) ** 2 + (TY[None] - t[1]) ** 2) > 5
    second = tot[far].max()
    print(f"A={ca} B={cb}: peak at t=({t[0]:6.1f},{t[1]:6.1f}) |t|={np.linalg.norm(t):5.1f}  LLR peak {tot.max():8.1f} at-truth {at0:8.1f} runner-up(>5m) {second:8.1f}")
