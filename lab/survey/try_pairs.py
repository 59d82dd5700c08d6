import sys, time
sys.path.insert(0, "lab/survey")
import numpy as np
from common import load, true_xy
from pairlik import calibrate2, calibrate, truth_calibrate, sim_bins, PairGrid
from graphslam import PowerCosine

fl = load(sys.argv[1])
mode = sys.argv[2] if len(sys.argv) > 2 else "self"
pc = PowerCosine.of(fl.fp.fingerprints, 10.0)
T = true_xy(fl)
t_s = fl.fp.t_ns / 1e9
rng = np.random.default_rng(0)
N = len(fl.xy)
ii = rng.integers(0, N, 100000); jj = rng.integers(0, N, 100000)
edges_s = sim_bins(pc.pairs(ii, jj), 12)
if mode == "truth":
    logp, H = truth_calibrate(T, fl.sess, pc, edges_s)
else:
    logp, H = calibrate2(fl.xy, fl.sess, t_s, pc, edges_s)
np.set_printoptions(precision=2, suppress=True, linewidth=200)
print((logp[:-1] - logp[-1]))
print(H.sum(1))
pg = PairGrid(logp, cell=1.0, half=64)
S = len(fl.psi)
t0 = time.time()
res = []
for a in range(S):
    ia = np.flatnonzero(fl.sess == a)
    for b in range(a + 1, S):
        ib = np.flatnonzero(fl.sess == b)
        I, J = np.meshgrid(ia, ib, indexing="ij"); I, J = I.ravel(), J.ravel()
        o = fl.xy[I] - fl.xy[J]
        sb = np.searchsorted(edges_s, pc.pairs(I, J))
        Sg = pg.score(o, sb)
        k = np.unravel_index(np.argmax(Sg), Sg.shape)
        t_hat = pg.t_of(*k)
        # runner-up: best at least 5 m away
        g = (np.arange(pg.n) - pg.n // 2) * pg.cell
        d2 = (g[:, None] - t_hat[0]) ** 2 + (g[None, :] - t_hat[1]) ** 2
        second = Sg[d2 > 25].max()
        t_true = fl.tau_true[a] - fl.tau_true[b]  # B at t: p^B + t = p^A  => t = tau_B - tau_A? check below
        # p_true^A = xy^A + tau_A ; for B placed at offset t relative to A: xy^B + t ~ xy^A at the same place
        # same place: xy^A + tau_A = xy^B + tau_B  => xy^A - xy^B = tau_B - tau_A = o ; t in S is o-centred
        t_true = fl.tau_true[b] - fl.tau_true[a]
        # truth overlap: share of A's points within 4 m of B's
        dd = np.linalg.norm(T[ia][:, None] - T[ib][None], axis=2)
        ov = min((dd.min(1) < 4).mean(), (dd.min(0) < 4).mean())
        res.append((a, b, Sg.max(), second, np.linalg.norm(t_hat - t_true), ov))
print("time", time.time() - t0)
res = np.array(res)
np.save(f"/tmp/pairs_{mode}.npy", res)
names = [s.session_id.replace("IPIN2023_T3_TrainingTrial", "")[:12] for s in fl.survey]
for lo, hi in [(0.3, 1.01), (0.05, 0.3), (0.0001, 0.05), (-1, 0.0001)]:
    m = (res[:, 5] > lo) & (res[:, 5] <= hi)
    if m.sum() == 0: continue
    e = res[m, 4]
    print(f"overlap {lo}-{hi}: n {m.sum()} err median {np.median(e):.1f} <3m {np.mean(e<3):.2f} peak med {np.median(res[m,2]):.1f} margin med {np.median(res[m,2]-res[m,3]):.1f}")
