"""Standstills (gaps between steps) and their averaged fingerprints: how precisely do pauses match
across walks? Truth scores only."""
from __future__ import annotations
import re, sys
import numpy as np
sys.path.insert(0, "lab/survey")
from common import load, true_xy

folder = sys.argv[1] if len(sys.argv) > 1 else "../shared/data/ipin2023/b100_f-2"
MIN_S = float(sys.argv[2]) if len(sys.argv) > 2 else 4.0
fl = load(folder)
sv, fp = fl.survey, fl.fp
P = true_xy(fl)
R = fp.fingerprints.values.toarray() - 110.0
R[R < -100] = np.nan
ids = [s.session_id for s in sv]
def lab(sid):
    m = re.search(r"Trial(\d+)_repetition(\d+)", sid)
    return f"{m.group(1)}.{int(m.group(2))}" if m else sid[-6:]
pauses = []  # (walk, step, n_scans, mean fp, truth pos)
for k, s in enumerate(sv):
    t = s.steps.t_ns / 1e9
    gaps = np.diff(t)
    idx = np.flatnonzero(gaps > MIN_S)
    f = np.flatnonzero(fp.session == k)
    ft = fp.t_ns[f] / 1e9
    for i in idx:
        inside = f[(ft > t[i] + 0.5) & (ft < t[i + 1] - 0.5)]
        if len(inside) < 2: continue
        pauses.append((k, i, len(inside), np.nanmean(R[inside], 0), P[inside].mean(0), gaps[i]))
print(len(pauses), "pauses of >", MIN_S, "s with >= 2 scans; per walk:", np.bincount([p[0] for p in pauses], minlength=len(sv)))
print("durations:", np.round(np.percentile([p[5] for p in pauses], [10, 50, 90]), 1), "scans:", np.percentile([p[2] for p in pauses], [10, 50, 90]))
# pairwise: power-cosine similarity of averaged fingerprints across walks
M = np.array([p[3] for p in pauses]); M = np.where(np.isfinite(M), np.exp(M / 10.0), 0.0)
M /= np.linalg.norm(M, axis=1, keepdims=True) + 1e-12
S = M @ M.T
W = np.array([p[0] for p in pauses]); X = np.array([p[4] for p in pauses])
D = np.linalg.norm(X[:, None] - X[None], axis=-1)
cross = W[:, None] != W[None]
for th in (0.98, 0.95, 0.9, 0.8):
    m = cross & (S > th)
    print(f"sim > {th}: {m.sum()//2} pairs, truth dist median {np.median(D[m]):.1f} p90 {np.percentile(D[m],90):.1f} >5m {np.mean(D[m]>5):.2f}")
# best match per pause among other walks
bd = []
for i in range(len(pauses)):
    s = np.where(cross[i], S[i], -1); j = s.argmax()
    bd.append((s[j], D[i, j]))
bd = np.array(bd)
print("best cross-walk match: truth dist median", np.median(bd[:, 1]).round(1), "p90", np.percentile(bd[:, 1], 90).round(1), "within 3 m", np.mean(bd[:, 1] < 3).round(2))
# same for single scans for comparison
F = np.where(np.isfinite(R), np.exp(R / 10.0), 0.0); F /= np.linalg.norm(F, axis=1, keepdims=True) + 1e-12
rng = np.random.default_rng(0); sel = rng.choice(len(F), 400, replace=False)
SS = F[sel] @ F.T
ws = fp.session
d1 = []
for a, i in enumerate(sel):
    s = np.where(ws != ws[i], SS[a], -1); j = s.argmax(); d1.append(np.linalg.norm(P[i] - P[j]))
print("single scans best cross-walk match: median", np.median(d1).round(1), "p90", np.percentile(d1, 90).round(1), "within 3 m", np.mean(np.array(d1) < 3).round(2))
print()
route = np.array([lab(ids[p[0]]).split(".")[0] for p in pauses])
# cluster pauses by truth position (for display), and list which routes pause there
from scipy.cluster.hierarchy import fcluster, linkage
Z = linkage(X, "single"); cl = fcluster(Z, 3.0, "distance")
for c in np.unique(cl):
    m = cl == c
    print(f"place {c:2d} at ({X[m,0].mean():6.1f},{X[m,1].mean():6.1f}): " + " ".join(sorted(lab(ids[pauses[i][0]]) for i in np.flatnonzero(m))))
# cross-route best matches
print("cross-route pairs sim>0.95:")
for i in range(len(pauses)):
    for j in range(i + 1, len(pauses)):
        if route[i] != route[j] and S[i, j] > 0.95:
            print(f"  {lab(ids[pauses[i][0]])} - {lab(ids[pauses[j][0]])} sim {S[i,j]:.3f} dist {D[i,j]:.1f}")
