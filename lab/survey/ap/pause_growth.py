"""Placement with standstill links: each pause (no step for > MIN_S s, >= 2 scans) gets its averaged
fingerprint; pauses of different walks with power-cosine >= THR become heavy matches (weight = W
per pair, between the pauses' middle scans). Placement only; truth scores.
python lab/survey/ap/pause_growth.py FLOOR [thr=0.95] [w=10] [margin=1.0]"""
import sys
import numpy as np
import graphslam as gs
from graphslam import associate
from graphslam import walk_headings
from graphslam import place_components
from graphslam import GrowthParams
from graphslam import PowerCosine, Matches
from graphslam import landmark_errors
from graphslam import PoseTrack
from graphslam import se2_apply

folder = sys.argv[1]
kw = dict(a.split("=") for a in sys.argv[2:])
THR = float(kw.get("thr", 0.95)); W = int(kw.get("w", 10)); MIN_S = 4.0
sv = gs.read_survey([folder])
fp = associate(sv, max_gap_s=1.5, missing_dbm=-110.0, min_rssi_dbm=-100.0, standstill_max_s=120.0)
wh = walk_headings(sv, sigma_floor_rad=np.radians(25))
dr = np.concatenate([s.steps.xy for s in sv])
matches = PowerCosine.of(fp.fingerprints, 10.0).top_matches(fp.session, 5)
R = fp.fingerprints.values.toarray() - 110.0
R[R < -100] = np.nan
pauses = []
for k, s in enumerate(sv):
    t = s.steps.t_ns / 1e9
    f = np.flatnonzero(fp.session == k); ft = fp.t_ns[f] / 1e9
    for i in np.flatnonzero(np.diff(t) > MIN_S):
        inside = f[(ft > t[i] + 0.5) & (ft < t[i + 1] - 0.5)]
        if len(inside) >= 2:
            pauses.append((k, inside[len(inside) // 2], np.nanmean(R[inside], 0)))
M = np.array([p[2] for p in pauses]); M = np.where(np.isfinite(M), np.exp(M / 10.0), 0.0)
M /= np.linalg.norm(M, axis=1, keepdims=True) + 1e-12
S = M @ M.T
Wk = np.array([p[0] for p in pauses]); mid = np.array([p[1] for p in pauses])
ii, jj = np.nonzero((S >= THR) & (Wk[:, None] != Wk[None]) & (np.arange(len(S))[:, None] < np.arange(len(S))[None]))
print(f"{len(pauses)} pauses, {len(ii)} pause links")
if W > 0 and len(ii):
    mi = np.concatenate([matches.i, np.repeat(mid[ii], W)]); mj = np.concatenate([matches.j, np.repeat(mid[jj], W)])
    ms = np.concatenate([matches.similarity, np.ones(len(ii) * W)])
    matches = Matches(mi, mj, ms)
ids = [s.session_id for s in sv]
cp = place_components(len(sv.sessions), fp.session, dr[fp.node], matches,
                      GrowthParams(rotation_window_deg=12, min_margin=float(kw.get("margin", 1.0))),
                      rotation=wh.rotation, rotation_sigma=wh.sigma)
n5 = 0; e5 = 0; o10 = 0
for k in range(cp.n_components):
    walks = cp.walks_of(k)
    tracks = {ids[s]: PoseTrack(sv.sessions[s].steps.t_ns, se2_apply(cp.transforms[s], sv.sessions[s].steps.xy), sv.sessions[s].steps.heading) for s in walks}
    st, _, per = landmark_errors(tracks, sv)
    o10 += sum(v > 10 for v in per.values())
    if len(walks) >= 5: n5 += len(walks); e5 += st.mean_m * len(walks)
    if len(walks) >= 2:
        print(f"  comp {k}: {len(walks)} walks {st.mean_m:.2f} m  " + " ".join(sorted(ids[s].replace('IPIN2023_T3_TrainingTrial','')[:5] for s in walks)))
print(f"comps>=5 {n5} at {e5/max(n5,1):.2f} m; >10 m {o10}")
