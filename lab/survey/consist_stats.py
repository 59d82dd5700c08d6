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
rows = []
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
    for k in range(cp.n_components):
        walks = cp.walks_of(k)
        if len(walks) < 3: continue
        tracks = {ids[s]: PoseTrack(sv.sessions[s].steps.t_ns, se2_apply(cp.transforms[s], sv.sessions[s].steps.xy), sv.sessions[s].steps.heading + cp.transforms[s][2]) for s in walks}
        st, _, per = landmark_errors(tracks, sv)
        for s in walks:
            if ids[s] in per:
                rows.append((cp.consistency[s], per[ids[s]], cp.margin[s]))
r = np.array(rows); wrong = r[:, 1] > 6
print("n", len(r), "wrong", wrong.sum())
for t in [0.3, 0.4, 0.5, 0.6, 0.7]:
    m = r[:, 0] >= t
    print(f"consistency >= {t}: keep {m.sum()} wrong kept {np.sum(m & wrong)} right dropped {np.sum(~m & ~wrong)}")
