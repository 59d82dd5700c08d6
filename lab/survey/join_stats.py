"""Per joined walk: margin, support, scans vs its truth error (permissive growth)."""
import sys
sys.path.insert(0, "lab/survey")
import numpy as np
import graphslam as gs
from graphslam import associate
from graphslam import walk_headings
from graphslam import place_components
from graphslam import GrowthParams
from graphslam import PowerCosine
from graphslam import landmark_errors
from graphslam import PoseTrack
from graphslam import se2_apply

out = []
for folder in sys.argv[2:]:
    sv = gs.read_survey([folder])
    fp = associate(sv, max_gap_s=1.5, missing_dbm=-110.0, min_rssi_dbm=-100.0, standstill_max_s=120.0)
    wh = walk_headings(sv, sigma_floor_rad=np.radians(6))
    dr = np.concatenate([s.steps.xy for s in sv])
    matches = PowerCosine.of(fp.fingerprints, 10.0).top_matches(fp.session, 5)
    cp = place_components(len(sv.sessions), fp.session, dr[fp.node], matches,
                          GrowthParams(rotation_window_deg=12, min_margin=float(sys.argv[1])),
                          rotation=wh.rotation, rotation_sigma=wh.sigma)
    ids = [s.session_id for s in sv]
    nsc = np.bincount(fp.session, minlength=len(ids))
    for k in range(cp.n_components):
        walks = cp.walks_of(k)
        if len(walks) < 2: continue
        tracks = {ids[s]: PoseTrack(sv.sessions[s].steps.t_ns, se2_apply(cp.transforms[s], sv.sessions[s].steps.xy), sv.sessions[s].steps.heading + cp.transforms[s][2]) for s in walks}
        st, _, per = landmark_errors(tracks, sv)
        for s in walks:
            if np.isfinite(cp.margin[s]) and not np.isinf(cp.margin[s]) and ids[s] in per:
                best = cp.support[s] * nsc[s]
                out.append((cp.margin[s], best, nsc[s], per[ids[s]], len(walks), folder[-4:]))
o = np.array([r[:5] for r in out], float)
wrong = o[:, 3] > 6
for name, v in [("margin", o[:, 0]), ("rel", o[:, 0] / o[:, 1]), ("per scan", o[:, 0] / o[:, 2]), ("best/scan", o[:, 1] / o[:, 2])]:
    qs = np.quantile(v, [0.1, 0.25, 0.5, 0.75, 0.9])
    print(f"{name:10s} right med {np.median(v[~wrong]):.3f} wrong med {np.median(v[wrong]) if wrong.any() else np.nan:.3f}")
    for t in qs:
        m = v >= t
        print(f"    >= {t:.3f}: joins {m.sum():3d} wrong {np.sum(m & wrong):3d}")
