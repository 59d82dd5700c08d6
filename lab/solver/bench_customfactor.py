#!/usr/bin/env python
"""Speed and result of graphslam's native-factor solver vs the same graph built with
``gtsam.CustomFactor`` in Python, as a user following GTSAM's Python examples would.

Same survey (simulated, named scenario and seed), same nodes, same edges, same initial
placement, same LM settings. The CustomFactor build evaluates eq. 7 and eq. 10 (with
its flat saturation) in Python inside every linearisation; graphslam's build uses
GTSAM's C++ BetweenFactorPose2 / RangeFactorPose2 + L2WithDeadZone and handles the
saturation between LM runs.

Usage: python lab/solver/bench_customfactor.py [--scenario paper] [--seed 0] [--runs 3]
Prints one JSON line.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from functools import partial

import gtsam
import numpy as np
from gtsam.symbol_shorthand import X

from graphslam import (
    build_problem, evaluate, GraphSlamConfig, lm_params, PoseTrack, Problem, simulate,
    solve_problem as solve, survey_factors as F, values_to_xyh as _values_to_xyh,
)



def imu_error(u: np.ndarray, this: gtsam.CustomFactor, v: gtsam.Values, H: list | None) -> np.ndarray:
    """Eq. 7: u_nodes - u, u_nodes from eq. 6 inverted; analytic Jacobians."""
    k0, k1 = this.keys()
    p0, p1 = v.atPose2(k0), v.atPose2(k1)
    c, s = np.cos(p0.theta()), np.sin(p0.theta())
    dx, dy = p1.x() - p0.x(), p1.y() - p0.y()
    un = np.array([c * dx + s * dy, -s * dx + c * dy, p1.theta() - p0.theta()])
    e = un - u
    e[2] = np.arctan2(np.sin(e[2]), np.cos(e[2]))
    if H is not None:
        # derivatives w.r.t. each pose's local (body-frame) tangent coordinates
        R0 = np.array([[c, s], [-s, c]])
        J0 = np.zeros((3, 3))
        J0[:2, :2] = -np.eye(2)  # moving p0 in its own frame
        J0[:2, 2] = [un[1], -un[0]]
        J0[2, 2] = -1.0
        c1, s1 = np.cos(p1.theta()), np.sin(p1.theta())
        J1 = np.zeros((3, 3))
        J1[:2, :2] = R0 @ np.array([[c1, -s1], [s1, c1]])
        J1[2, 2] = 1.0
        H[0] = J0
        H[1] = J1
    return e


def wifi_error(cfg: object, this: gtsam.CustomFactor, v: gtsam.Values, H: list | None) -> np.ndarray:
    """Eq. 10 with its flat saturation; Jacobian through d = |p_k - p_q|."""
    k0, k1 = this.keys()
    p0, p1 = v.atPose2(k0), v.atPose2(k1)
    delta = np.array([p1.x() - p0.x(), p1.y() - p0.y()])
    d = float(np.hypot(*delta))
    e = float(F.fuzzy_error(d, cfg))
    if H is not None:
        on_ramp = cfg.d_min_m < d < cfg.d_max_m
        g = (cfg.e_max / (cfg.d_max_m - cfg.d_min_m)) * (delta / d) if on_ramp and d > 0 else np.zeros(2)
        c0, s0 = np.cos(p0.theta()), np.sin(p0.theta())
        c1, s1 = np.cos(p1.theta()), np.sin(p1.theta())
        H[0] = np.array([[*(-g @ np.array([[c0, -s0], [s0, c0]])), 0.0]])
        H[1] = np.array([[*(g @ np.array([[c1, -s1], [s1, c1]])), 0.0]])
    return np.array([e])


def custom_solve(problem: Problem, cfg: GraphSlamConfig, max_iterations: int) -> tuple[np.ndarray, int, float]:
    graph = gtsam.NonlinearFactorGraph()
    imu_nm = F.imu_noise(cfg.imu)
    for (i, j), u in zip(problem.imu_pairs.tolist(), problem.imu_u):
        graph.add(gtsam.CustomFactor(imu_nm, [X(i), X(j)], partial(imu_error, u)))
    wifi_nm = gtsam.noiseModel.Isotropic.Sigma(1, 1.0 / np.sqrt(cfg.wifi.omega))
    for i, j in problem.wifi_pairs.tolist():
        graph.add(gtsam.CustomFactor(wifi_nm, [X(i), X(j)], partial(wifi_error, cfg.wifi)))
    r0 = problem.reference_node
    graph.add(gtsam.PriorFactorPose2(X(r0), gtsam.Pose2(*problem.init_xyh[r0]), F.reference_prior_noise()))
    values = gtsam.Values()
    for n in np.flatnonzero(np.isfinite(problem.init_xyh[:, 0])).tolist():
        values.insert(X(n), gtsam.Pose2(*problem.init_xyh[n]))
    params = lm_params(cfg)
    params.setMaxIterations(max_iterations)
    t = time.perf_counter()
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    result = opt.optimize()
    return _values_to_xyh(result, problem.init_xyh), opt.iterations(), time.perf_counter() - t


def landmark_mean(problem: Problem, xyh: np.ndarray) -> float:
    fp = problem.fingerprints
    tracks = {}
    for s in np.flatnonzero(problem.included):
        sess = problem.survey.sessions[s]
        tracks[sess.session_id] = PoseTrack.from_xyh(sess.steps.t_ns, xyh[fp.offsets[s] : fp.offsets[s + 1]])
    return evaluate(tracks, problem.survey).landmarks.mean_m


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenario", default="paper")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--runs", type=int, default=3, help="native runs (median); the custom build runs once")
    ap.add_argument("--custom-max-iterations", type=int, default=100)
    args = ap.parse_args()
    cfg = GraphSlamConfig()
    survey = simulate(args.scenario, seed=args.seed).survey
    problem = build_problem(survey, cfg)
    # the same graph as the CustomFactor build: one IMU factor per step (no chain compression)
    same_graph = cfg.model_copy(update={"optimizer": cfg.optimizer.model_copy(update={"compress_chains": False})})
    native_times, native = [], None
    for _ in range(args.runs):
        t = time.perf_counter()
        native = solve(problem, same_graph)
        native_times.append(time.perf_counter() - t)
    assert native is not None
    compressed_times = []
    for _ in range(args.runs):
        t = time.perf_counter()
        compressed = solve(problem, cfg)
        compressed_times.append(time.perf_counter() - t)
    xyh_c, it_c, t_c = custom_solve(problem, cfg, args.custom_max_iterations)
    t_n = statistics.median(native_times)
    print(
        json.dumps(
            {
                "scenario": args.scenario,
                "seed": args.seed,
                "nodes": int(len(problem.init_xyh)),
                "wifi_edges": int(len(problem.wifi_pairs)),
                "native_solve_s_median": round(t_n, 3),
                "native_iterations": len(native.iterations),
                "native_landmark_mean_m": round(landmark_mean(problem, native.node_xyh), 3),
                "native_compressed_solve_s_median": round(statistics.median(compressed_times), 3),
                "native_compressed_landmark_mean_m": round(landmark_mean(problem, compressed.node_xyh), 3),
                "custom_solve_s": round(t_c, 3),
                "custom_iterations": it_c,
                "custom_landmark_mean_m": round(landmark_mean(problem, xyh_c), 3),
                "speedup": round(t_c / t_n, 1),
                "speedup_per_iteration": round((t_c / max(it_c, 1)) / (t_n / max(len(native.iterations), 1)), 1),
            }
        )
    )


if __name__ == "__main__":
    main()
