"""The survey's factor graph, two ways: GTSAM C++ factors (``native_graph``) or arrays for the
vectorised Levenberg-Marquardt (``pose_graph``, ``graphslam.core.survey.solver``), and GTSAM's own
LM for one saturation stage.

Both hold the same terms: IMU-between factors along each walk (one per step, or one per compressed
chain segment), the fuzzy WiFi factors, priors on the held poses, one heading prior per walk (or
per pose), control-point ties, and the UWB hook's range factors (GTSAM only). A factor type added
here needs its vectorised counterpart in ``solver.py`` or a case in ``use_vectorised_solver``.
Keys: ``X(i)``, step pose i numbered globally over all walks.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable

import numpy as np
from numpy.typing import NDArray

from graphslam.config import GraphSlamConfig
from graphslam.core.survey import factors as F
from graphslam.core.survey import solver as S
from graphslam.core.survey.chains import CompressedChains, compress
from graphslam.core.survey.problem import Problem
from graphslam.core.types import Survey
from graphslam.core.uwb import factors as uwb_factors

if TYPE_CHECKING:
    import gtsam


def X(i: int) -> int:
    """GTSAM key of step pose i, numbered globally over all walks (``symbol_shorthand.X``)."""
    import gtsam  # lazy: a slow import, needed only by the GTSAM back end (optimizer.solver: gtsam)

    return gtsam.symbol_shorthand.X(i)


def dead_reckoned_nodes(survey: Survey) -> tuple[NDArray, NDArray]:
    """Every step pose of every walk in its own dead-reckoning frame (x, y, heading), and its walk."""
    xyh = np.concatenate([s.steps.xyh for s in survey]) if len(survey) else np.zeros((0, 3))
    sess = np.concatenate([np.full(len(s.steps), i) for i, s in enumerate(survey)]).astype(np.int64)
    return xyh, sess


def native_graph(
    problem: Problem, cfg: GraphSlamConfig
) -> tuple[gtsam.NonlinearFactorGraph, list[gtsam.NonlinearFactor], gtsam.Values, CompressedChains | None]:
    """(IMU factors + reference prior, one WiFi factor per edge, initial values, chains): GTSAM C++ factors only.

    With ``optimizer.compress_chains`` the IMU chain between fingerprint poses becomes one
    between factor per segment (``graphslam.core.survey.chains``); otherwise one per step (eq. 6-8).
    The default back end solves ``pose_graph`` instead, except for --update and UWB surveys
    (``use_vectorised_solver``): a factor type added here needs its vectorised counterpart in ``solver.py``,
    or a case in ``use_vectorised_solver``.
    With ``problem.free`` (--update) only factors touching a free node are built; the other
    nodes they touch are held at their previous solution by priors as tight as the reference's.
    """
    import gtsam

    imu_graph = gtsam.NonlinearFactorGraph()
    chains = None
    free = problem.free
    if cfg.optimizer.compress_chains:
        keep = kept_nodes(problem)
        step_cov = np.diag([cfg.imu.sigma_xy_m**2, cfg.imu.sigma_xy_m**2, cfg.imu.sigma_heading_rad**2])
        # measured from the dead reckoning (rigid-invariant): init_xyh is not one with a warm start
        chains = compress(dead_reckoned_nodes(problem.survey)[0], problem.fingerprints.offsets, keep, problem.included, step_cov)
        pairs, measured, noises = chains.pairs, chains.measured, [gtsam.noiseModel.Gaussian.Covariance(c) for c in chains.covariance]
    else:
        pairs, measured = problem.imu_pairs, problem.imu_u
        noises = [F.imu_noise(cfg.imu)] * len(pairs)
    use = np.ones(len(pairs), bool) if free is None else free[pairs].any(axis=1)
    idx = np.flatnonzero(use)
    for k, (i, j) in zip(idx.tolist(), pairs[idx].tolist()):
        imu_graph.add(F.imu_factor(X(i), X(j), measured[k], noises[k]))
    wifi_pairs = solved_wifi_pairs(problem)
    if free is None:
        nodes = chains.kept if chains is not None else np.flatnonzero(np.isfinite(problem.init_xyh[:, 0]))
    else:
        nodes = np.unique(np.concatenate([pairs[use].ravel(), wifi_pairs.ravel(), solved_magnetic_pairs(problem).ravel()]))
        for n in nodes[~free[nodes]].tolist():  # the neighbourhood's border keeps its previous solution
            imu_graph.add(gtsam.PriorFactorPose2(X(n), gtsam.Pose2(*problem.init_xyh[n]), F.reference_prior_noise()))
    uwb = problem.uwb
    # with UWB anchors they fix the frame instead; --update: only when the reference is re-solved
    for r0 in problem.held_nodes.tolist():
        if (uwb is None or not uwb.site_frame) and (free is None or free[r0]):
            imu_graph.add(gtsam.PriorFactorPose2(X(r0), gtsam.Pose2(*problem.init_xyh[r0]), F.reference_prior_noise()))
    hn, ht, hs = heading_priors(problem, nodes)
    for n, th, sg in zip(hn.tolist(), ht.tolist(), hs.tolist()):
        nm = gtsam.noiseModel.Isotropic.Sigma(1, sg)
        if cfg.heading.cauchy_sigmas > 0:
            nm = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(cfg.heading.cauchy_sigmas), nm)
        imu_graph.add(gtsam.PoseRotationPrior2D(X(n), gtsam.Rot2(th), nm))
    pn, pxy, ps = point_priors(problem, cfg)
    local = np.isin(pn, nodes)  # --update: the ties of the re-solved part only
    for n, (px, py), sg in zip(pn[local].tolist(), pxy[local].tolist(), ps[local].tolist()):
        imu_graph.add(gtsam.PoseTranslationPrior2D(X(n), gtsam.Pose2(px, py, 0.0), gtsam.noiseModel.Isotropic.Sigma(2, sg)))
    values = gtsam.Values()
    for n in nodes.tolist():
        values.insert(X(n), gtsam.Pose2(*problem.init_xyh[n]))
    if uwb is not None:  # UWB hook: range factors (always active) and the anchors
        for f in uwb_factors.range_factors(uwb.ranges, cfg.uwb, with_anchors=uwb.site_frame):
            imu_graph.add(f)
        values.insert(uwb_factors.anchor_values(uwb.ranges))
    wifi_nm = F.wifi_noise(cfg.wifi)
    wifi = [F.wifi_factor(X(i), X(j), wifi_nm) for i, j in wifi_pairs.tolist()]
    if len(problem.magnetic_pairs):  # after the WiFi edges, in the order solve's active set has them
        mag_nm = F.magnetic_noise(cfg.magnetic)
        wifi += [F.wifi_factor(X(i), X(j), mag_nm) for i, j in solved_magnetic_pairs(problem).tolist()]
    return imu_graph, wifi, values, chains


def pose_graph(problem: Problem, cfg: GraphSlamConfig) -> tuple[S.PoseGraph, CompressedChains | None]:
    """The same graph as ``native_graph``, as arrays for ``solver.levenberg_marquardt`` (vectorised)."""
    step_cov = np.diag([cfg.imu.sigma_xy_m**2, cfg.imu.sigma_xy_m**2, cfg.imu.sigma_heading_rad**2])
    held = problem.held_nodes
    chains = None
    mag_pairs, mag_offsets = problem.magnetic_pairs, None
    if cfg.optimizer.compress_chains:
        # magnetic pairs ride on the kept steps before them (``carried_pairs``): a variable per pair end
        # would more than double a large survey's factorisation
        keep = kept_nodes(problem, magnetic=False)
        dr = dead_reckoned_nodes(problem.survey)[0]
        if len(mag_pairs):
            keep[problem.fingerprints.offsets[:-1][problem.included]] = True  # a kept step before every pair end
            mag_pairs, mag_offsets = carried_pairs(mag_pairs, keep, dr)
        chains = compress(dr, problem.fingerprints.offsets, keep, problem.included, step_cov)
        nodes, pairs, measured = chains.kept, chains.pairs, chains.measured
        sqrt_info = S.sqrt_information(chains.covariance)
    else:
        nodes = np.flatnonzero(np.isfinite(problem.init_xyh[:, 0]))
        pairs, measured = problem.imu_pairs, problem.imu_u
        sqrt_info = np.broadcast_to(S.sqrt_information(step_cov[None])[0], (len(pairs), 3, 3))
    hn, ht, hs = heading_priors(problem, nodes)
    pn, pxy, ps = point_priors(problem, cfg)
    n_w, n_m, n_r = len(problem.wifi_pairs), len(problem.magnetic_pairs), len(problem.anchor_pairs)
    n_f = len(problem.field_pairs)
    n_steps = len(problem.init_xyh)
    # WiFi edges, magnetic pairs, WiFi edges to a reference map's fingerprints and magnetic factors to its
    # field's samples (held nodes after the steps)
    anchor = np.concatenate([problem.anchor_pairs, problem.field_pairs]).reshape(-1, 2) + np.array([0, n_steps])
    sigma = np.repeat([F.wifi_sigma(cfg.wifi), cfg.magnetic.sigma_m, F.wifi_sigma(cfg.wifi), cfg.magnetic.sigma_m],
                      [n_w, n_m, n_r, n_f])
    dead = np.repeat([cfg.wifi.d_min_m, cfg.magnetic.d_min_m, cfg.wifi.d_min_m, cfg.magnetic.d_min_m], [n_w, n_m, n_r, n_f])
    graph = S.PoseGraph(
        n_nodes=n_steps + len(problem.anchor_xy),
        variables=nodes[~np.isin(nodes, held)].astype(np.int64),
        reference=int(held[0]) if len(held) else -1,
        between_pairs=pairs,
        between_measured=measured,
        between_sqrt_info=sqrt_info,
        # WiFi edges, then magnetic pairs (each kind its sigma and dead zone)
        range_pairs=np.concatenate([problem.wifi_pairs, mag_pairs, anchor]).astype(np.int64).reshape(-1, 2),
        range_sigma=F.wifi_sigma(cfg.wifi) if not (n_m or n_r or n_f) else sigma,
        range_dead_zone_m=cfg.wifi.d_min_m if not (n_m or n_r or n_f) else dead,
        range_offsets=None if mag_offsets is None else np.concatenate(
            [np.zeros((n_w, 4)), mag_offsets, np.zeros((n_r + n_f, 4))]),
        heading_nodes=hn,
        heading_target=ht,
        heading_sigma=hs,
        point_nodes=pn,
        point_xy=pxy,
        point_sigma=ps,
        heading_cauchy=cfg.heading.cauchy_sigmas,
    )
    return graph, chains


def kept_nodes(problem: Problem, *, magnetic: bool = True) -> NDArray[np.bool_]:
    """Nodes chain compression keeps as variables: WiFi edge ends, magnetic pair ends (``magnetic``; the
    vectorised graph carries them on the kept steps instead, ``carried_pairs``), held nodes, control-point
    ties, UWB ranges."""
    keep = np.zeros(len(problem.init_xyh), bool)
    keep[problem.wifi_pairs.ravel()] = True
    if magnetic:
        keep[problem.magnetic_pairs.ravel()] = True
    keep[problem.anchor_pairs[:, 0]] = True
    keep[problem.field_pairs[:, 0]] = True
    keep[problem.held_nodes] = True
    if problem.ties is not None:
        keep[problem.ties.node] = True
    if problem.uwb is not None:  # UWB hook: poses with a range stay variables
        keep[problem.uwb.nodes] = True
    if problem.heading is not None:  # every walk keeps one pose at least, for its heading prior
        keep[problem.fingerprints.offsets[:-1][problem.included]] = True
    return keep


def carried_pairs(pairs: NDArray[np.int64], keep: NDArray[np.bool_], dr_xyh: NDArray) -> tuple[NDArray, NDArray]:
    """Each pair end moved to the last kept step at or before it, with the end's dead-reckoned position in
    that step's body frame: (pairs of kept steps (P, 2), offsets (P, 4): a's x, y then b's). Between kept steps
    chain compression holds the walk rigid to first order, so a point at that offset from the kept pose is
    the skipped step (``keep`` must hold every walk's first step)."""
    kept = np.flatnonzero(keep)
    out, offs = [], []
    for side in (0, 1):
        n = pairs[:, side]
        k = kept[np.searchsorted(kept, n, side="right") - 1]
        c, s = np.cos(dr_xyh[k, 2]), np.sin(dr_xyh[k, 2])
        d = dr_xyh[n, :2] - dr_xyh[k, :2]
        out.append(k)
        offs.append(np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]]))
    return np.column_stack(out).astype(np.int64), np.concatenate(offs, axis=1)


def heading_priors(problem: Problem, nodes: NDArray[np.int64]) -> tuple[NDArray, NDArray, NDArray]:
    """(nodes, target heading, sigma) of the heading priors on ``nodes`` (the solved poses)."""
    h = problem.heading
    if h is None or h.mode == "none":
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
    nodes = nodes[np.isfinite(h.target[nodes])]
    sess = dead_reckoned_nodes(problem.survey)[1]
    if h.mode == "walk":  # one rotation prior per walk, on its first solved pose
        _, first = np.unique(sess[nodes], return_index=True)
        nodes = nodes[first]
        return nodes.astype(np.int64), h.target[nodes], h.walk_sigma[sess[nodes]]
    return nodes.astype(np.int64), h.target[nodes], h.node_sigma(nodes, sess)


def point_priors(problem: Problem, cfg: GraphSlamConfig) -> tuple[NDArray, NDArray, NDArray]:
    """(nodes, site xy, sigma) of the control-point ties."""
    t = problem.ties
    if t is None or len(t) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0)
    return t.node, t.xy, np.full(len(t), cfg.control_points.sigma_m)


def use_vectorised_solver(cfg: GraphSlamConfig, problem: Problem | None = None) -> bool:
    """``optimizer.solver``: the vectorised LM (``solver.py``) unless gtsam is asked for; its sparse
    Cholesky is CHOLMOD (``core.common.cholesky``). A local re-solve
    (--update: ``problem.free``) and a survey with UWB range factors always take GTSAM's: only
    ``native_graph`` builds those factors."""
    if problem is not None and (problem.free is not None or problem.uwb is not None):
        return False
    return cfg.optimizer.solver != "gtsam"


def solved_wifi_pairs(problem: Problem) -> NDArray[np.int64]:
    """The WiFi edges in the graph ``solve`` optimises: all, or those touching a free node (--update)."""
    if problem.free is None:
        return problem.wifi_pairs
    return problem.wifi_pairs[problem.free[problem.wifi_pairs].any(axis=1)]


def solved_magnetic_pairs(problem: Problem) -> NDArray[np.int64]:
    """The magnetic pairs in the graph ``solve`` optimises: all, or those touching a free node (--update)."""
    if problem.free is None:
        return problem.magnetic_pairs
    return problem.magnetic_pairs[problem.free[problem.magnetic_pairs].any(axis=1)]


def describe_solver(solver: dict[str, str]) -> str:
    """One phrase for ``Alignment.solver``, the same in the log and the command's summary, e.g.
    "cholmod (metis ordering)" or "gtsam (pcg)"."""
    if solver.get("solver") == "gtsam":
        return f"gtsam ({solver.get('linear_solver', '?')})"
    if solver.get("linear_solver") == "pcg":
        return f"{solver['solver']} (conjugate gradients, spanning-tree preconditioner)"
    return f"{solver['solver']} ({solver['ordering']} ordering)"


def gtsam_linear_solver(cfg: GraphSlamConfig, n_poses: int) -> str:
    """``optimizer.linear_solver`` resolved for GTSAM's LM over ``n_poses`` poses: "cholesky" or "pcg"."""
    solver = cfg.optimizer.linear_solver
    return "pcg" if solver == "pcg" or (solver == "auto" and n_poses > cfg.optimizer.pcg_above_poses) else "cholesky"


def lm_params(cfg: GraphSlamConfig, n_poses: int = 0) -> gtsam.LevenbergMarquardtParams:
    """LM settings. Direct multifrontal Cholesky is fastest on surveys of a few thousand fingerprint
    poses; beyond that the WiFi edges, which tie every revisited place together, make elimination
    cliques grow large and block-Jacobi PCG wins."""
    import gtsam

    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(cfg.optimizer.max_iterations)
    params.setRelativeErrorTol(cfg.optimizer.relative_error_tol)
    params.setAbsoluteErrorTol(cfg.optimizer.absolute_error_tol)
    params.setOrderingType("METIS")
    if gtsam_linear_solver(cfg, n_poses) == "pcg":
        params.setLinearSolverType("ITERATIVE")
        pcg = gtsam.PCGSolverParameters()
        pcg.preconditioner = gtsam.BlockJacobiPreconditionerParameters()
        params.setIterativeParams(pcg)
    return params


def gtsam_lm(
    imu_graph: gtsam.NonlinearFactorGraph,
    wifi_factors: list[gtsam.NonlinearFactor],
    values: gtsam.Values,
    active: NDArray[np.bool_],
    cfg: GraphSlamConfig,
    hook: Callable[[int, float, float], None],
) -> tuple[gtsam.Values, bool]:
    """One stage with GTSAM's own LM (``optimizer.solver: gtsam``)."""
    import gtsam

    graph = gtsam.NonlinearFactorGraph(imu_graph)
    for k in np.flatnonzero(active).tolist():
        graph.add(wifi_factors[k])
    params = lm_params(cfg, values.size())
    params.iterationHook = hook
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    values = optimizer.optimize()
    # LM also stops when it can find no step that lowers the error (lambda at its upper
    # bound): that is a stall, not convergence
    converged = (
        optimizer.iterations() < cfg.optimizer.max_iterations
        and optimizer.lambda_() < params.getlambdaUpperBound()
    )
    return values, converged


def values_to_xyh(values: gtsam.Values, template: NDArray) -> NDArray:
    import gtsam

    out = np.full_like(template, np.nan)
    # gtsam.utilities.extractPose2 returns the poses in key order (UWB anchors are Point2s)
    keys = [k for k in values.keys() if gtsam.Symbol(k).chr() == ord("x")]
    poses = gtsam.utilities.extractPose2(values)
    idx = np.array([gtsam.Symbol(k).index() for k in keys], dtype=np.int64)
    out[idx] = poses
    return out
