"""UJIIndoorLoc: neighbours' spatial consistency on cached Sørensen distances (/tmp/uji_soren.npy)."""
import sys
import numpy as np
sys.path.insert(0, str(__import__('pathlib').Path(__file__).resolve().parents[2]))  # the repository root: lab.bench
from lab.bench.ujiindoorloc import read_ujiindoorloc
D = "../shared/data/ujiindoorloc/"
tr = read_ujiindoorloc(D + "trainingData.csv.gz"); te = read_ujiindoorloc(D + "validationData.csv.gz")
Dm = np.load("/tmp/uji_soren.npy")
order = np.argsort(Dm, axis=1)[:, :60]
dd = np.take_along_axis(Dm, order, 1)
def est(K, radius, p, kin):
    pos = np.zeros((len(te), 2))
    for q in range(len(te)):
        idx = order[q, :K]; d = dd[q, :K]; w = (1 / (d + 1e-6)) ** p
        xy = tr.xy[idx]
        # densest cluster: the neighbour whose radius-ball holds most weight
        D2 = np.linalg.norm(xy[:, None] - xy[None], axis=-1)
        s = (D2 < radius) @ w
        c = s.argmax()
        m = D2[c] < radius
        # within that cluster, the kin best
        sel = np.flatnonzero(m)[:kin]
        pos[q] = (xy[sel] * w[sel, None]).sum(0) / w[sel].sum()
    e = np.linalg.norm(pos - te.xy, axis=1)
    return e
for K, radius, p, kin in [(10, 1e9, 1, 10), (10, 10, 1, 10), (20, 10, 1, 20), (20, 15, 1, 20), (20, 10, 2, 20), (30, 10, 2, 30), (20, 10, 4, 20), (30, 15, 4, 30), (30, 8, 3, 30), (40, 10, 3, 10), (40, 10, 3, 5)]:
    e = est(K, radius, p, kin)
    print(f"K={K:2d} radius={radius:5g} p={p} kin={kin:2d}: mean {e.mean():5.2f} median {np.median(e):5.2f} p90 {np.percentile(e,90):5.2f}")
