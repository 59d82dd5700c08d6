"""Register a route's walks onto a map of other walks held at the truth (the control-point case)."""
import sys
sys.path.insert(0, "lab/survey")
import numpy as np
from common import load, true_xy
from pairlik import calibrate2, truth_calibrate, sim_bins, PairGrid, truncate, cross_ref
from graphslam import PowerCosine

fl = load(sys.argv[1]); mode = sys.argv[2]
pc = PowerCosine.of(fl.fp.fingerprints, 10.0)
T = true_xy(fl)
rng = np.random.default_rng(0); N = len(fl.xy)
ii = rng.integers(0, N, 100000); jj = rng.integers(0, N, 100000)
edges_s = sim_bins(pc.pairs(ii, jj), 12)
if mode == "truth30":
    logp, H = truth_calibrate(T, fl.sess, pc, edges_s); logp = truncate(logp, cross_ref(fl.sess, pc, edges_s), 30)
else:
    logp, H = calibrate2(fl.xy, fl.sess, fl.fp.t_ns / 1e9, pc, edges_s)
pg = PairGrid(logp, cell=1.0, half=100)
names = [s.session_id.replace("IPIN2023_T3_TrainingTrial", "") for s in fl.survey]
route = np.array([int(n[:2]) for n in names])
mapw = np.flatnonzero(np.isin(route, [23, 24, 25, 26, 27, 52, 53]))
mi = np.flatnonzero(np.isin(fl.sess, mapw)); mp = T[mi]
g = (np.arange(pg.n) - pg.n // 2) * pg.cell
for w in np.flatnonzero(~np.isin(route, [23, 24, 25, 26, 27, 52, 53])):
    wi = np.flatnonzero(fl.sess == w); wp = fl.xy[wi]
    I, J = np.meshgrid(np.arange(len(mi)), np.arange(len(wi)), indexing="ij"); I, J = I.ravel(), J.ravel()
    sb = np.searchsorted(edges_s, pc.pairs(mi[I], wi[J]))
    S = pg.score(mp[I] - wp[J], sb)
    k = np.unravel_index(np.argmax(S), S.shape); t = pg.t_of(*k)
    d2 = (g[:, None] - t[0]) ** 2 + (g[None, :] - t[1]) ** 2
    second = S[d2 > 25].max()
    print(f"{names[w]:>20s} err {np.linalg.norm(t - fl.tau_true[w]):5.1f} peak {S.max():7.1f} second {second:7.1f}")
