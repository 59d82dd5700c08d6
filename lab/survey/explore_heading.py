"""Per-walk heading offset (phone yaw - dead-reckoned heading) vs the truth's rigid-fit rotation."""
import sys
import numpy as np
import graphslam as gs
from graphslam import fit_se2
from graphslam import interpolate_xy

folder = sys.argv[1]
sv = gs.read_survey([folder])
rows = []
for s in sv:
    if s.heading is None or len(s.landmarks) < 2:
        continue
    t = s.steps.t_ns
    idx = np.searchsorted(t, s.heading.t_ns)
    ok = (idx < len(t)) & (t[np.minimum(idx, len(t) - 1)] == s.heading.t_ns)
    d = np.angle(np.exp(1j * (s.heading.yaw[ok] - s.steps.heading[idx[ok]])))
    psi = np.angle(np.exp(1j * d).mean())
    spread = np.degrees(np.abs(np.angle(np.exp(1j * (d - psi)))))
    est = interpolate_xy(s.steps, np.array([m.t_ns for m in s.landmarks], float))
    true = np.array([[m.x, m.y] for m in s.landmarks])
    T = fit_se2(est, true)
    rows.append((s.session_id[-22:], psi, T[2], np.median(spread), np.percentile(spread, 90), len(d)))
psi = np.array([r[1] for r in rows]); th = np.array([r[2] for r in rows])
off = np.angle(np.exp(1j * (th - psi)).mean())
dev = np.degrees(np.angle(np.exp(1j * (th - psi - off))))
print(f"common offset {np.degrees(off):.1f} deg; |dev| median {np.median(np.abs(dev)):.1f} p90 {np.percentile(np.abs(dev),90):.1f} max {np.abs(dev).max():.1f}")
for r, d in zip(rows, dev):
    print(f"{r[0]:>24s} psi {np.degrees(r[1]):7.1f} truth {np.degrees(r[2]):7.1f} dev {d:6.1f} within-walk spread med {r[3]:5.1f} p90 {r[4]:5.1f} n {r[5]}")
