"""iSAM2 against the warm-started local LM of `survey --update` (which of the two to build `--update` on).

Same survey, same edges, same start (walks solved before at their previous solution, the new
walks registered to them by `build_problem(warm=...)`), same factors (chain-compressed IMU,
reference prior, the WiFi edges active at the start):

- iSAM2: `ISAM2.update(old factors, old values)` (a process that starts from files must load the
  previous solution into a Bayes tree: one full elimination), then `update(new factors, new values)`
  and `RELIN_UPDATES` more updates to relinearise;
- local LM: what `graphslam survey --update` does (`update.hops` = HOPS).

    python lab/solver/bench_update_isam2.py RECORDINGS PREVIOUS_OUT [--hops 1]

Prints one JSON line: seconds of each part and the landmark errors after an SE(2) fit.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time

import gtsam
import numpy as np

from graphslam import (
    build_problem, dead_reckoned_nodes as _dr_nodes, evaluate, expand_chains as expand, GraphSlamConfig,
    load_previous, native_graph, PoseTrack, read_survey, solve_problem as solve,
    values_to_xyh as _values_to_xyh, warm_start,
)


RELIN_UPDATES = 3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recordings")
    ap.add_argument("previous_out")
    ap.add_argument("--hops", type=int, default=1)
    args = ap.parse_args()
    previous = load_previous(args.previous_out)
    survey = read_survey([args.recordings])
    base = GraphSlamConfig()
    ref = {"reference_session": previous.reference}
    cfg = base.model_copy(update={"optimizer": base.optimizer.model_copy(update=ref)})
    out: dict = {"load_average": [round(v, 2) for v in os.getloadavg()]}

    t = time.perf_counter()
    problem = build_problem(survey, cfg, warm_start(previous, survey, args.hops))
    al = solve(problem, cfg)
    out["local_lm"] = {"seconds": round(time.perf_counter() - t, 3), "optimise_s": round(al.timings_s["optimise"], 3),
                       "landmark_mean_m": round(evaluate(al.tracks, survey).landmarks.mean_m, 3)}

    # iSAM2 over the same start and factors
    full = dataclasses.replace(problem, free=None)
    imu_graph, wifi, values, chains = native_graph(full, cfg)
    xyh0 = problem.init_xyh
    ea, eb = problem.wifi_pairs[:, 0], problem.wifi_pairs[:, 1]
    active = np.linalg.norm(xyh0[ea, :2] - xyh0[eb, :2], axis=1) <= cfg.wifi.d_max_m
    walk_of = np.repeat(np.arange(len(survey)), np.diff(problem.fingerprints.offsets))
    was = {sid for sid, ok in zip(previous.session_ids, previous.aligned.tolist()) if ok}
    old_node = np.isin(walk_of, [k for k, s in enumerate(survey) if s.session_id in was])  # walks solved before
    g_old, g_new = gtsam.NonlinearFactorGraph(), gtsam.NonlinearFactorGraph()
    factors = [imu_graph.at(k) for k in range(imu_graph.size())] + [wifi[k] for k in np.flatnonzero(active)]
    for f in factors:
        keys = [gtsam.Symbol(k).index() for k in f.keys()]
        (g_old if old_node[keys].all() else g_new).add(f)
    v_old, v_new = gtsam.Values(), gtsam.Values()
    for k in values.keys():
        (v_old if old_node[gtsam.Symbol(k).index()] else v_new).insert(k, values.atPose2(k))
    params = gtsam.ISAM2Params()
    isam = gtsam.ISAM2(params)
    t = time.perf_counter()
    isam.update(g_old, v_old)
    t_load = time.perf_counter() - t
    t = time.perf_counter()
    isam.update(g_new, v_new)
    for _ in range(RELIN_UPDATES):
        isam.update()
    est = isam.calculateEstimate()
    t_new = time.perf_counter() - t
    xyh = _values_to_xyh(est, xyh0)
    if chains is not None:
        xyh = expand(xyh, _dr_nodes(survey)[0], chains)
    tracks = {survey.sessions[s].session_id: PoseTrack.from_xyh(survey.sessions[s].steps.t_ns,
              xyh[problem.fingerprints.offsets[s]:problem.fingerprints.offsets[s + 1]])
              for s in np.flatnonzero(problem.included)}
    out["isam2"] = {"load_previous_s": round(t_load, 3), "new_walks_s": round(t_new, 3),
                    "seconds": round(t_load + t_new, 3), "factors_old": g_old.size(), "factors_new": g_new.size(),
                    "landmark_mean_m": round(evaluate(tracks, survey).landmarks.mean_m, 3)}
    out["load_average_end"] = [round(v, 2) for v in os.getloadavg()]
    print(json.dumps(out))


if __name__ == "__main__":
    main()
