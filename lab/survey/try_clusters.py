import sys
sys.path.insert(0, "lab/survey")
import numpy as np
from common import load, true_xy
from pairlik import calibrate2, calibrate, truth_calibrate, sim_bins, PairGrid
from graphslam import PowerCosine

fl = load(sys.argv[1]); mode = sys.argv[2]
pc = PowerCosine.of(fl.fp.fingerprints, 10.0)
T = true_xy(fl)
rng = np.random.default_rng(0); N = len(fl.xy)
ii = rng.integers(0, N, 100000); jj = rng.integers(0, N, 100000)
edges_s = sim_bins(pc.pairs(ii, jj), 12)
from pairlik import truncate, cross_ref
if mode == "truth":
    logp, H = truth_calibrate(T, fl.sess, pc, edges_s)
elif mode == "truthnear":
    logp, H = truth_calibrate(T, fl.sess, pc, edges_s)
    logp = truncate(logp, cross_ref(fl.sess, pc, edges_s), float(sys.argv[3]))
elif mode == "extrap":
    from pairlik import calibrate_extrap
    logp, H = calibrate_extrap(fl.xy, fl.sess, fl.fp.t_ns / 1e9, pc, edges_s, d_to=float(sys.argv[3]))
else:
    logp, H = calibrate2(fl.xy, fl.sess, fl.fp.t_ns / 1e9, pc, edges_s)
pg = PairGrid(logp, cell=1.0, half=64)
names = [s.session_id.replace("IPIN2023_T3_TrainingTrial", "") for s in fl.survey]
route = np.array([int(n[:2]) for n in names])
R = sorted(set(route))
# cluster points: walk points shifted to truth within-cluster offsets (relative to the cluster's first walk)
cl = {}
for r in R:
    ws = np.flatnonzero(route == r)
    idx = np.flatnonzero(np.isin(fl.sess, ws))
    base = fl.tau_true[ws[0]]
    pts = fl.xy[idx] + fl.tau_true[fl.sess[idx]] - base
    cl[r] = (idx, pts, base)
for x in range(len(R)):
    for y in range(x + 1, len(R)):
        ia, pa, ba = cl[R[x]]; ib, pb, bb = cl[R[y]]
        I, J = np.meshgrid(np.arange(len(ia)), np.arange(len(ib)), indexing="ij"); I, J = I.ravel(), J.ravel()
        o = pa[I] - pb[J]
        sb = np.searchsorted(edges_s, pc.pairs(ia[I], ib[J]))
        Sg = pg.score(o, sb)
        k = np.unravel_index(np.argmax(Sg), Sg.shape)
        t_hat = pg.t_of(*k)
        t_true = bb - ba
        g = (np.arange(pg.n) - pg.n // 2) * pg.cell
        d2 = (g[:, None] - t_hat[0]) ** 2 + (g[None, :] - t_hat[1]) ** 2
        second = Sg[d2 > 25].max()
        dd = np.linalg.norm(T[ia][:, None] - T[ib][None], axis=2)
        ov = min((dd.min(1) < 4).mean(), (dd.min(0) < 4).mean())
        # score at the true offset
        kt = np.round(t_true / pg.cell).astype(int) + pg.n // 2
        st = Sg[kt[0], kt[1]] if (0 <= kt).all() and (kt < pg.n).all() else np.nan
        print(f"{R[x]}-{R[y]} ov {ov:.2f} err {np.linalg.norm(t_hat - t_true):5.1f} peak {Sg.max():8.1f} second {second:8.1f} at-truth {st:8.1f}")
