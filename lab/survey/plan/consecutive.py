"""Consecutive walks: does the next walk start where the last one ended? Time gap, WiFi similarity of
the last scans of walk k and the first scans of walk k+1, and (truth, scoring only) the distance.
python lab/survey/plan/consecutive.py FLOOR"""
import sys
import numpy as np
import graphslam as gs
from graphslam import PowerCosine, associate, fit_se2, se2_apply, interpolate_xy

folder = sys.argv[1]
sv = gs.read_survey([folder])
fp = associate(sv, max_gap_s=1.5, missing_dbm=-110.0, min_rssi_dbm=-100.0, standstill_max_s=120.0)
pc = PowerCosine.of(fp.fingerprints, 10.0)
order = np.argsort([s.steps.t_ns[0] for s in sv])
rows = []
for a, b in zip(order[:-1], order[1:]):
    A, B = sv.sessions[a], sv.sessions[b]
    gap = (B.steps.t_ns[0] - A.steps.t_ns[-1]) / 1e9
    fa = np.flatnonzero(fp.session == a); fb = np.flatnonzero(fp.session == b)
    if len(fa) == 0 or len(fb) == 0 or len(A.landmarks) < 2 or len(B.landmarks) < 2:
        continue
    ia = fa[np.argsort(fp.t_ns[fa])][-2:]; ib = fb[np.argsort(fp.t_ns[fb])][:2]
    sim = pc.pairs(np.repeat(ia, len(ib)), np.tile(ib, len(ia))).max()
    # truth: each walk's rigid fit to its own landmarks
    def pose(S, first):
        tt = np.array([m.t_ns for m in S.landmarks], float)
        T = fit_se2(interpolate_xy(S.steps, tt), np.array([[m.x, m.y] for m in S.landmarks]))
        return se2_apply(T, S.steps.xy[[0 if first else -1]])[0]
    d = np.linalg.norm(pose(A, False) - pose(B, True))
    # a null: similarity of walk k's last scans to a random other walk's first scans
    rows.append((gap, sim, d))
r = np.array(rows)
print(f"{folder.split('/')[-1]}: {len(r)} consecutive pairs; gap median {np.median(r[:,0]):.0f} s; end-start within 3 m: {np.mean(r[:,2]<3):.2f}")
for th in (0.9, 0.95, 0.97, 0.98, 0.99):
    m = r[:, 1] >= th
    if m.any():
        print(f"  similarity >= {th}: {m.sum():3d} pairs, within 3 m {np.mean(r[m,2]<3):.2f}, within 5 m {np.mean(r[m,2]<5):.2f}, median {np.median(r[m,2]):.1f} m")
m = r[:, 0] < 60
print(f"  gap < 60 s: {m.sum()} pairs, within 3 m {np.mean(r[m,2]<3):.2f}")
