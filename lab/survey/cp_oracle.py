"""Walks tied at control points with rotation from the heading (+ common offset fitted): landmark errors."""
import sys, csv
sys.path.insert(0, "lab/survey")
import numpy as np
from common import load
from graphslam import interpolate_xy
from graphslam import se2_apply, fit_se2

fl = load(sys.argv[1])
cps = {r["landmark_id"]: (float(r["x"]), float(r["y"])) for r in csv.DictReader(open(sys.argv[2]))}
names = [s.session_id.replace("IPIN2023_T3_TrainingTrial", "") for s in fl.survey]
tot = []
for k, s in enumerate(fl.survey):
    marks = [m for m in s.landmarks if m.landmark_id in cps]
    if not marks:
        print(f"{names[k]:>22s} no control point"); continue
    ids = sorted({m.landmark_id for m in marks})
    tt = np.array([m.t_ns for m in marks], float)
    p = interpolate_xy(s.steps, tt)
    q = np.array([cps[m.landmark_id] for m in marks])
    # rotation: heading + common offset (phi0 from truth here: the product would fit it from the CPs)
    th = fl.psi[k] + fl.phi0
    R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    tr = (q - p @ R.T).mean(0)
    allt = np.array([m.t_ns for m in s.landmarks], float)
    est = interpolate_xy(s.steps, allt) @ R.T + tr
    true = np.array([[m.x, m.y] for m in s.landmarks])
    e = np.linalg.norm(est - true, axis=1)
    # with a free rotation when >=2 distinct points
    e2 = None
    if len(ids) >= 2:
        T = fit_se2(p, q)
        e2 = np.linalg.norm(se2_apply(T, interpolate_xy(s.steps, allt)) - true, axis=1).mean()
    tot.append(e)
    print(f"{names[k]:>22s} cps {len(ids)} marks {len(marks)} heading-rot err mean {e.mean():5.2f} max {e.max():5.2f}" + (f" free-rot {e2:5.2f}" if e2 is not None else ""))
tot = np.concatenate(tot)
print("all tied walks", len(tot), "marks, mean", tot.mean().round(2))
