"""Oracle layout with a free rigid fit per walk (DR -> site by its own landmarks), in the Earth frame
of common.load (site = R(phi0) earth). Scoring/oracle only."""
import numpy as np
from graphslam import interpolate_xy
from graphslam import se2_apply, fit_se2


def rigid_xy(fl):
    sv, fp = fl.survey, fl.fp
    dr = np.concatenate([s.steps.xy for s in sv])[fp.node]
    out = np.full_like(dr, np.nan)
    c, s_ = np.cos(-fl.phi0), np.sin(-fl.phi0)
    Rinv = np.array([[c, -s_], [s_, c]])
    for k, s in enumerate(sv):
        if not s.landmarks or len(s.landmarks) < 2:
            continue
        tt = np.array([m.t_ns for m in s.landmarks], float)
        p = interpolate_xy(s.steps, tt)
        q = np.array([[m.x, m.y] for m in s.landmarks]) @ Rinv.T  # earth frame
        T = fit_se2(p, q)
        m = fp.session == k
        out[m] = se2_apply(T, dr[m])
    return out
