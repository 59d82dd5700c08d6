"""Each walk alone on the floor plan, rotation from its heading (+ one site rotation per floor):
how many places does it fit, is the truth among them? Truth scores only.
python lab/survey/plan/place_plan.py FLOOR_DIR [cell=0.5]"""
from __future__ import annotations
import sys, time
import numpy as np
from scipy.fft import rfft2, irfft2
from scipy import ndimage
sys.path.insert(0, "lab/survey")
import graphslam as gs
from graphslam import walk_headings
from graphslam import interpolate_xy
from graphslam import load_floor_plan, read_walkable_area

folder = sys.argv[1]
args = dict(a.split("=") for a in sys.argv[2:] if "=" in a)
CELL = float(args.get("cell", 0.5)); CAP = float(args.get("cap", 3.0))
t0 = time.time()
sv = gs.read_survey([folder])
wh = walk_headings(sv, sigma_floor_rad=np.radians(25))
plan = load_floor_plan(folder + "/floor_image.png", None)
wa = read_walkable_area(plan)
print(f"{len(sv.sessions)} walks, read {time.time()-t0:.1f}s; plan {plan.width_m:.0f}x{plan.height_m:.0f} m, walkable {wa.fraction_walkable():.2f}")
# penalty image on a CELL grid, x right, y up (index [ix, iy])
nx, ny = int(np.ceil(plan.width_m / CELL)), int(np.ceil(plan.height_m / CELL))
gx = (np.arange(nx) + 0.5) * CELL; gy = (np.arange(ny) + 0.5) * CELL
G = np.stack(np.meshgrid(gx, gy, indexing="ij"), -1).reshape(-1, 2)
d, _ = wa.distance(G)
pen = np.minimum(d, CAP).reshape(nx, ny) ** 2
PAD = 200  # cells of margin around the plan (walk extent)
penp = np.pad(pen, PAD, constant_values=CAP**2)
from scipy.fft import next_fast_len
SFFT = (next_fast_len(penp.shape[0] + PAD), next_fast_len(penp.shape[1] + PAD))
FPEN = rfft2(penp, SFFT)

def truth_T(s, rot):
    """site translation for the walk rotated by rot (least squares on its landmarks)."""
    tt = np.array([m.t_ns for m in s.landmarks], float)
    p = interpolate_xy(s.steps, tt)
    c, sn = np.cos(rot), np.sin(rot)
    q = p @ np.array([[c, sn], [-sn, c]])
    true = np.array([[m.x, m.y] for m in s.landmarks])
    return (true - q).mean(0), np.linalg.norm(true - q - (true - q).mean(0), axis=1).mean()

# site rotation phi: truth (for the oracle check) = circular mean over walks of the rigid rotation - psi
from graphslam import fit_se2
rots = []
for k, s in enumerate(sv):
    if len(s.landmarks) >= 3 and np.isfinite(wh.rotation[k]):
        tt = np.array([m.t_ns for m in s.landmarks], float)
        T = fit_se2(interpolate_xy(s.steps, tt), np.array([[m.x, m.y] for m in s.landmarks]))
        rots.append(T[2] - wh.rotation[k])
phi_true = float(np.angle(np.exp(1j * np.array(rots)).mean()))
print(f"site rotation (truth, for checking): {np.degrees(phi_true):.1f} deg")

def score_walk(s, rot, return_img=False):
    xy = s.steps.xy
    c, sn = np.cos(rot), np.sin(rot)
    q = xy @ np.array([[c, sn], [-sn, c]])
    lo = q.min(0)
    qi = np.floor((q - lo) / CELL).astype(int)
    qi = np.minimum(qi, PAD - 1)
    w = np.zeros((PAD, PAD))
    np.add.at(w, (qi[:, 0], qi[:, 1]), 1.0)
    ex = qi.max(0) + 1
    corr = irfft2(FPEN * np.conj(rfft2(w, SFFT)), SFFT)[: penp.shape[0] - ex[0] + 1, : penp.shape[1] - ex[1] + 1] / len(xy)
    # corr[i, j]: mean penalty with walk cell 0 at padded cell (i, j): site translation of walk's lo
    return corr, lo

def site_tr(i, j, lo):
    return np.array([(i - PAD) * CELL - lo[0], (j - PAD) * CELL - lo[1]])

# 1) site rotation from the plan alone: sum over walks of the best mean penalty per phi
if args.get("phi") != "truth":
    t1 = time.time()
    phis = np.radians(np.arange(0, 360, 4.0))
    tot = np.zeros(len(phis))
    sample = [k for k in range(len(sv.sessions)) if np.isfinite(wh.rotation[k])][:: max(1, len(sv.sessions) // 20)]
    for a, phi in enumerate(phis):
        for k in sample:
            corr, lo = score_walk(sv.sessions[k], wh.rotation[k] + phi)
            tot[a] += corr.min()
    a = tot.argmin()
    print(f"site rotation from the plan: {np.degrees(phis[a]):.0f} deg (score {tot[a]:.2f}; next best >10 deg away "
          f"{tot[np.abs(np.angle(np.exp(1j*(phis-phis[a]))))>np.radians(10)].min():.2f}) [{time.time()-t1:.0f}s]")
    phi = phis[a]
else:
    phi = phi_true

# 2) per walk: modes (local minima of penalty below thr, non-max suppression 5 m), truth among them?
res = []
for k, s in enumerate(sv.sessions):
    if not np.isfinite(wh.rotation[k]) or len(s.landmarks) < 2:
        continue
    best_modes = []
    for dr in np.radians([-6, -3, 0, 3, 6]):
        rot = wh.rotation[k] + phi + dr
        corr, lo = score_walk(s, rot)
        mn = ndimage.minimum_filter(corr, size=int(5 / CELL))
        ii, jj = np.nonzero((corr == mn) & (corr < float(args.get("thr", 0.25))))
        for i, j in zip(ii, jj):
            best_modes.append((corr[i, j], site_tr(i, j, lo), rot))
    ttrue, fit = truth_T(s, wh.rotation[k] + phi)
    best_modes.sort(key=lambda m: m[0])
    # merge modes across rotations within 5 m
    merged = []
    for m in best_modes:
        if all(np.linalg.norm(m[1] - o[1]) > 5 for o in merged):
            merged.append(m)
    dist = [np.linalg.norm(m[1] - ttrue) for m in merged]
    hit = [i for i, dd in enumerate(dist) if dd < 4]
    L = np.linalg.norm(np.diff(s.steps.xy, axis=0), axis=1).sum()
    res.append((len(merged), hit[0] if hit else -1, L, fit))
res = np.array(res)
n = res[:, 0]; rank = res[:, 1]
print(f"walks {len(res)}: modes median {np.median(n):.0f} p10 {np.percentile(n,10):.0f} p90 {np.percentile(n,90):.0f}; "
      f"truth among modes {np.mean(rank>=0):.2f}; truth is best mode {np.mean(rank==0):.2f}; unique & right {np.mean((n==1)&(rank==0)):.2f}")
for lo_, hi_ in ((0, 25), (25, 50), (50, 1e9)):
    m = (res[:, 2] >= lo_) & (res[:, 2] < hi_)
    if m.any():
        print(f"  length {lo_}-{hi_} m: {m.sum()} walks, modes median {np.median(n[m]):.0f}, truth among {np.mean(rank[m]>=0):.2f}, best {np.mean(rank[m]==0):.2f}")
