import sys
sys.path.insert(0, "lab/issue37")
import numpy as np
from common import load, true_xy
from graphslam import PowerCosine
fl = load(sys.argv[1]); scale = float(sys.argv[2]) if len(sys.argv) > 2 else 10.0
pc = PowerCosine.of(fl.fp.fingerprints, scale)
T = true_xy(fl); t = fl.fp.t_ns / 1e9
S = len(fl.psi)
period = np.array([np.median(np.diff(np.sort(t[fl.sess == k]))) if (fl.sess == k).sum() > 2 else np.nan for k in range(S)])
dev = (period > 3).astype(int)
print("scan period per walk", np.round(period, 1))
# within-walk
wi, wj = [], []
for k in range(S):
    idx = np.flatnonzero(fl.sess == k)
    i, j = np.triu_indices(len(idx), 1)
    wi.append(idx[i]); wj.append(idx[j])
wi, wj = np.concatenate(wi), np.concatenate(wj)
ok = np.abs(t[wi] - t[wj]) >= 20
wi, wj = wi[ok], wj[ok]
dw = np.linalg.norm(fl.xy[wi] - fl.xy[wj], axis=1); sw = pc.pairs(wi, wj)
rng = np.random.default_rng(0); N = len(T)
ci = rng.integers(0, N, 300000); cj = rng.integers(0, N, 300000)
ok = (fl.sess[ci] != fl.sess[cj]) & np.isfinite(T[ci, 0]) & np.isfinite(T[cj, 0])
ci, cj = ci[ok], cj[ok]
dc = np.linalg.norm(T[ci] - T[cj], axis=1); sc = pc.pairs(ci, cj)
same_dev = dev[fl.sess[ci]] == dev[fl.sess[cj]]
print(f"{'d':>8s} {'within':>14s} {'cross same':>14s} {'cross diff':>14s}")
for lo, hi in [(0, 2), (2, 4), (4, 6), (6, 10), (10, 15), (15, 20), (20, 30), (30, 50), (50, 200)]:
    m1 = (dw >= lo) & (dw < hi); m2 = (dc >= lo) & (dc < hi) & same_dev; m3 = (dc >= lo) & (dc < hi) & ~same_dev
    f = lambda s, m: f"{np.median(s[m]):.3f}({m.sum():5d})" if m.sum() else "      -      "
    print(f"{lo:3d}-{hi:3d} {f(sw, m1):>14s} {f(sc, m2):>14s} {f(sc, m3):>14s}")
