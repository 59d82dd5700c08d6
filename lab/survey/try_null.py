"""Rotation null: a walk (cluster) rotated by a wrong angle keeps its similarity statistics but loses
its geometry; its best score is the null for the correct rotation's peak."""
import sys
sys.path.insert(0, "lab/survey")
import numpy as np
from common import load, true_xy
from pairlik import calibrate2, truth_calibrate, sim_bins, PairGrid
from graphslam import PowerCosine

fl = load(sys.argv[1]); mode = sys.argv[2]; level = sys.argv[3]
pc = PowerCosine.of(fl.fp.fingerprints, 10.0)
T = true_xy(fl)
rng = np.random.default_rng(0); N = len(fl.xy)
ii = rng.integers(0, N, 100000); jj = rng.integers(0, N, 100000)
edges_s = sim_bins(pc.pairs(ii, jj), 12)
logp, H = (truth_calibrate(T, fl.sess, pc, edges_s) if mode == "truth" else calibrate2(fl.xy, fl.sess, fl.fp.t_ns / 1e9, pc, edges_s))
pg = PairGrid(logp, cell=1.0, half=64)
names = [s.session_id.replace("IPIN2023_T3_TrainingTrial", "") for s in fl.survey]
route = np.array([int(n[:2]) for n in names])
groups = {}
if level == "cluster":
    for r in sorted(set(route)):
        ws = np.flatnonzero(route == r)
        idx = np.flatnonzero(np.isin(fl.sess, ws))
        base = fl.tau_true[ws[0]]
        groups[r] = (idx, fl.xy[idx] + fl.tau_true[fl.sess[idx]] - base, base)
else:
    for k in range(len(names)):
        idx = np.flatnonzero(fl.sess == k)
        groups[k] = (idx, fl.xy[idx], fl.tau_true[k])
keys = sorted(groups)
g = (np.arange(pg.n) - pg.n // 2) * pg.cell


def peak(pa, pb, sb):
    I, J = np.meshgrid(np.arange(len(pa)), np.arange(len(pb)), indexing="ij"); I, J = I.ravel(), J.ravel()
    S = pg.score(pa[I] - pb[J], sb)
    k = np.unravel_index(np.argmax(S), S.shape)
    return S.max(), pg.t_of(*k)


rows = []
for x in range(len(keys)):
    for y in range(x + 1, len(keys)):
        ia, pa, ba = groups[keys[x]]; ib, pb, bb = groups[keys[y]]
        I, J = np.meshgrid(np.arange(len(ia)), np.arange(len(ib)), indexing="ij")
        sb = np.searchsorted(edges_s, pc.pairs(ia[I.ravel()], ib[J.ravel()]))
        best, t_hat = peak(pa, pb, sb)
        cb = pb.mean(0)
        nulls = []
        for ang in np.radians([float(a) for a in sys.argv[4].split(",")]):
            R = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
            nulls.append(peak(pa, (pb - cb) @ R.T + cb, sb)[0])
        dd = np.linalg.norm(T[ia][:, None] - T[ib][None], axis=2)
        ov = min((dd.min(1) < 4).mean(), (dd.min(0) < 4).mean())
        err = np.linalg.norm(t_hat - (bb - ba))
        rows.append((keys[x], keys[y], ov, err, best, max(nulls), np.mean(nulls)))
rows = np.array(rows)
np.save(f"/tmp/null_{mode}_{level}.npy", rows)
ratio = (rows[:, 4] - rows[:, 5])
order = np.argsort(-ratio)
for r in rows[order][:40]:
    print(f"{int(r[0]):3d}-{int(r[1]):3d} ov {r[2]:.2f} err {r[3]:5.1f} peak {r[4]:8.1f} null max {r[5]:8.1f} excess {r[4]-r[5]:8.1f} rel {(r[4]-r[5])/max(abs(r[5]),1):.2f}")
