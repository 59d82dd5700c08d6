import sys
import numpy as np
sys.path.insert(0, "lab/issue37")
from common import load, true_xy
from graphslam import PowerCosine

fl = load(sys.argv[1])
print("F", len(fl.xy), "S", len(fl.psi), "phi0 deg", np.degrees(fl.phi0))
pc = PowerCosine.of(fl.fp.fingerprints, 10.0)
T = true_xy(fl)
rng = np.random.default_rng(0)
n = len(T)
i = rng.integers(0, n, 400000); j = rng.integers(0, n, 400000)
cross = fl.sess[i] != fl.sess[j]
ok = cross & np.isfinite(T[i, 0]) & np.isfinite(T[j, 0])
i, j = i[ok], j[ok]
d = np.linalg.norm(T[i] - T[j], axis=1)
s = pc.pairs(i, j)
for lo, hi in [(0, 2), (2, 4), (4, 8), (8, 15), (15, 30), (30, 1e9)]:
    m = (d >= lo) & (d < hi)
    print(f"truth d {lo}-{hi} m: n {m.sum():6d} sim median {np.median(s[m]):.3f} p10 {np.percentile(s[m],10):.3f} p90 {np.percentile(s[m],90):.3f}")
