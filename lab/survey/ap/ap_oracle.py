"""Oracle information test: AP positions fitted per route cluster (walks at their truth translation,
rotations from the heading) -- do two clusters agree on a shared AP's position? Truth places walks
here only to measure how much a per-cluster AP fit could link clusters."""
from __future__ import annotations
import re, sys
import numpy as np
sys.path.insert(0, "lab/survey")
from common import load, true_xy
from graphslam import fit_ap, ApFitConfig, ApModel

folder = sys.argv[1] if len(sys.argv) > 1 else "../shared/data/ipin2023/b100_f-2"
fl = load(folder)
sv, fp = fl.survey, fl.fp
ids = [s.session_id for s in sv]
trial = np.array([int(re.search(r"Trial(\d+)", i).group(1)) for i in ids])
group = {21: "21", 51: "21", 22: "22", 23: "23", 53: "23", 24: "24", 25: "25", 26: "26", 27: "27", 52: "27"}
clus = np.array([group[t] for t in trial])[fl.sess]
P = true_xy(fl)
V = fp.fingerprints.values.tocsc()
rss_all = V.copy(); 
bss = fp.fingerprints.bssids
cfg = ApFitConfig(min_readings=15)
names = sorted(set(clus))
fits = {}
for c in names:
    m = np.flatnonzero(clus == c)
    sub = V[m]
    for a in range(sub.shape[1]):
        col = sub[:, a]
        rows = col.nonzero()[0]
        if len(rows) < 15: continue
        r = col.data - 110.0
        if r.max() < -75: continue
        f = fit_ap(bss[a], P[m][rows], r, cfg)
        if isinstance(f, ApModel):
            fits[(c, a)] = (np.array([f.x, f.y]), f.position_std_m, r.max(), len(rows))
print("fits per cluster:", {c: sum(1 for k in fits if k[0] == c) for c in names})
# same AP in two clusters
diffs = []
for i, c1 in enumerate(names):
    for c2 in names[i+1:]:
        d = []
        for (c, a), (p, s, mx, n) in fits.items():
            if c != c1 or (c2, a) not in fits: continue
            p2, s2, mx2, n2 = fits[(c2, a)]
            d.append((np.linalg.norm(p - p2), p - p2, s, s2, mx, mx2))
        if not d: continue
        e = np.array([x[0] for x in d])
        vec = np.array([x[1] for x in d])
        strong = np.array([min(x[4], x[5]) > -60 for x in d])
        med = np.median(vec, axis=0)
        print(f"{c1}-{c2}: shared {len(d):3d}  |dp| median {np.median(e):5.1f}  strong {strong.sum():3d} med {np.median(e[strong]) if strong.any() else np.nan:5.1f}  median vector offset {np.linalg.norm(med):5.1f}")
