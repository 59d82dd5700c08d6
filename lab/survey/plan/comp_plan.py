"""Components from growth at a low margin, each registered on the floor plan (rotation searched,
translation by FFT): is the truth placement the best plan fit, and do the off-plan walks at the best
fit coincide with the wrong walks? Truth scores only.
python lab/survey/plan/comp_plan.py FLOOR_DIR [margin=0.25] [minw=5]"""
from __future__ import annotations
import sys, time
import numpy as np
from scipy.fft import rfft2, irfft2, next_fast_len
import graphslam as gs
from graphslam import component_errors
from graphslam import se2_apply
from graphslam import load_floor_plan, read_walkable_area

folder = sys.argv[1]
args = dict(a.split("=") for a in sys.argv[2:] if "=" in a)
CELL = 0.5; CAP = 3.0; MINW = int(args.get("minw", 5))
sv = gs.read_survey([folder])
cfg = gs.load_config(overrides={"heading": {"min_margin": float(args.get("margin", 0.25))}})
al = gs.align(sv, cfg)
plan = load_floor_plan(folder + "/floor_image.png", None)
wa = read_walkable_area(plan)
nx, ny = int(np.ceil(plan.width_m / CELL)), int(np.ceil(plan.height_m / CELL))
G = np.stack(np.meshgrid((np.arange(nx) + 0.5) * CELL, (np.arange(ny) + 0.5) * CELL, indexing="ij"), -1).reshape(-1, 2)
pen = np.minimum(wa.distance(G)[0], CAP).reshape(nx, ny) ** 2
PAD = 300
penp = np.pad(pen, PAD, constant_values=CAP**2)
SFFT = (next_fast_len(penp.shape[0] + PAD), next_fast_len(penp.shape[1] + PAD))
FPEN = rfft2(penp, SFFT)


def plan_fit(xy, rot):
    c, s = np.cos(rot), np.sin(rot)
    q = xy @ np.array([[c, s], [-s, c]])
    lo = q.min(0)
    qi = np.minimum(np.floor((q - lo) / CELL).astype(int), PAD - 1)
    w = np.zeros((PAD, PAD)); np.add.at(w, (qi[:, 0], qi[:, 1]), 1.0)
    ex = qi.max(0) + 1
    corr = irfft2(FPEN * np.conj(rfft2(w, SFFT)), SFFT)[: penp.shape[0] - ex[0] + 1, : penp.shape[1] - ex[1] + 1] / len(xy)
    k = np.unravel_index(corr.argmin(), corr.shape)
    t = np.array([(k[0] - PAD) * CELL - lo[0], (k[1] - PAD) * CELL - lo[1]])
    return corr[k], t, corr


errs = component_errors(al, sv, site_frame=False)
for c, ce in zip(al.components, errs):
    if len(c.walks) < MINW:
        continue
    xy = np.concatenate([al.tracks[w].xy for w in c.walks])
    owner = np.concatenate([[w] * len(al.tracks[w].xy) for w in c.walks])
    # truth placement: the component's own SE(2) fit to the landmarks
    T = np.array(ce.site_from_component)
    pt = se2_apply(T, xy)
    d_truth = wa.distance(pt)[0]
    pen_truth = np.mean(np.minimum(d_truth, CAP) ** 2)
    # search
    t0 = time.time()
    best = []
    for rot in np.radians(np.arange(0, 360, 2.0)):
        v, t, _ = plan_fit(xy, rot)
        best.append((v, rot, t))
    best.sort(key=lambda b: b[0])
    v, rot, t = best[0]
    # runner-up: another rotation > 10 deg away or translation > 10 m away
    ru = next(b for b in best[1:] if abs(np.angle(np.exp(1j * (b[1] - rot)))) > np.radians(10) or np.linalg.norm(b[2] - t) > 10)
    Tb = np.array([t[0], t[1], rot])
    pb = se2_apply(Tb, xy)
    dist_from_truth = np.linalg.norm(pb - pt, axis=1).mean()
    print(f"comp {c.index} n={len(c.walks)} own-fit mean {ce.landmarks.mean_m:.2f} m; plan penalty truth {pen_truth:.2f} best {v:.2f} (runner-up {ru[0]:.2f}); "
          f"best fit {dist_from_truth:.1f} m from truth, rot {np.degrees(rot):.0f} vs truth {np.degrees(T[2]):.0f} [{time.time()-t0:.0f}s]")
    db = wa.distance(pb)[0]
    for w in c.walks:
        m = owner == w
        e = ce.per_walk_mean_m.get(w, np.nan)
        print(f"    walk {w[-6:]} err {e:5.1f}  off-plan(>2m) at truth {np.mean(d_truth[m] > 2):.2f} at best {np.mean(db[m] > 2):.2f}")
