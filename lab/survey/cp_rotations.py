"""After the control-points survey of a floor: each component-0 walk's mean landmark error in the site
frame, its error after its own rigid fit, and the rotation that fit needs (ground truth only scores).

    python lab/survey/cp_rotations.py ../shared/data/ipin2023/b100_f-2
"""
import sys
from pathlib import Path
import numpy as np
from graphslam import SurveyInputs, load_config, run_survey, fit_se2, interpolate_xy
folder = Path(sys.argv[1]); cp = folder / "control_points.csv"
res = run_survey(SurveyInputs((folder,), control_points=cp, picture=False), load_config())
al = res.alignment
c0 = set(al.components[0].walks)
for s in res.survey:
    if s.session_id not in c0: continue
    tr = al.tracks[s.session_id]
    lm = s.landmarks
    t = np.array([m.t_ns for m in lm]); truth = np.array([[m.x, m.y] for m in lm])
    est = np.column_stack([np.interp(t, tr.t_ns, tr.xy[:, 0]), np.interp(t, tr.t_ns, tr.xy[:, 1])])
    err = np.linalg.norm(est - truth, axis=1).mean()
    T = fit_se2(est, truth)
    rig = np.linalg.norm((est @ np.array([[np.cos(T[2]), np.sin(T[2])], [-np.sin(T[2]), np.cos(T[2])]]) + T[:2]) - truth, axis=1).mean()
    print(f"{Path(s.source).stem[-22:]:24s} err {err:5.2f} rigid-after {rig:5.2f} rot {np.degrees(T[2]):6.1f} deg  n {len(lm)}")
