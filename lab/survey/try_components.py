"""Components by repeated growth on heading-rotated walks; truth per component (scoring only)."""
import sys, time
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

folder = sys.argv[1]
kw = dict(a.split("=") for a in sys.argv[2:])
sv = gs.read_survey([folder])
fp = associate(sv, max_gap_s=1.5, missing_dbm=-110.0, min_rssi_dbm=-100.0, standstill_max_s=120.0)
wh = walk_headings(sv, sigma_floor_rad=np.radians(float(kw.get("floor", 6))))
dr = np.concatenate([s.steps.xy for s in sv])
sim = PowerCosine.of(fp.fingerprints, 10.0)
matches = sim.top_matches(fp.session, int(kw.get("k", 5)))
params = GrowthParams(rotation_window_deg=float(kw.get("win", 12)), min_margin=float(kw.get("margin", 0.25)),
                      rotation_step_deg=float(kw.get("step", 3)), weight_power=float(kw.get("pow", 4)), margin_per_fingerprint=kw.get("perfp", "0") == "1")
use_h = kw.get("heading", "1") == "1"
t0 = time.time()
cp = place_components(len(sv.sessions), fp.session, dr[fp.node], matches, params,
                      rotation=wh.rotation if use_h else None, rotation_sigma=wh.sigma if use_h else None)
print("time", round(time.time() - t0, 2), "components", cp.n_components)
ids = [s.session_id for s in sv]
nm = lambda s: s.replace("IPIN2023_T3_TrainingTrial", "")[:14]
over10 = 0; tot = []
for k in range(cp.n_components):
    walks = cp.walks_of(k)
    tracks = {}
    for s in walks:
        sess = sv.sessions[s]
        T = cp.transforms[s]
        tracks[ids[s]] = PoseTrack(sess.steps.t_ns, se2_apply(T, sess.steps.xy), sess.steps.heading + T[2])
    st, _, per = landmark_errors(tracks, sv)
    bad = sum(v > 10 for v in per.values()); over10 += bad
    if len(walks) > 1:
        print(f"comp {k}: {len(walks)} walks mean {st.mean_m:.2f} max {st.max_m:.1f} >10m {bad}  {[nm(ids[s]) for s in walks]}  {cp.reasons.get(k, '')[:80]}")
print("singletons", sum(len(cp.walks_of(k)) == 1 for k in range(cp.n_components)), "walks >10 m", over10)
