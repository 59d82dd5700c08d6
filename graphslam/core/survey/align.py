"""Multi-walk alignment: the paper's graph (section III), built and solved with GTSAM.

``align(survey, config)`` reads like the method:
 1. attach fingerprints to step nodes            (association)
 2. median-window thresholds and WiFi edges      (edges)
 3. initial placement of walks                   (initialise)
 4. IMU-between + fuzzy WiFi factors             (factors)
 5. Levenberg-Marquardt, reference pose fixed    (below)

Only ``steps`` and ``scans`` of the sessions are read here: landmarks and ground
truth never reach the solver, its initialisation or its parameters.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Callable

import gtsam
import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from graphslam.config import GraphSlamConfig
from graphslam.core.survey import factors as F
from graphslam.core.survey.association import FingerprintNodes, associate
from graphslam.core.survey.chains import CompressedChains, compress, expand
from graphslam.core.survey.edges import WifiEdges, propose_edges, window_thresholds
from graphslam.core.survey.initialise import Placement, register_walks, se2_apply
from graphslam.core.types import PoseTrack, Survey, wrap_angle
from graphslam.core.uwb import factors as uwb_factors
from graphslam.core.uwb.survey import UwbSummary, UwbTerms, uwb_terms
from graphslam.errors import SolverError

log = logging.getLogger(__name__)

X = gtsam.symbol_shorthand.X  # X(i): step pose i, numbered globally over all walks


@dataclass(frozen=True)
class IterationRecord:
    stage: int  # outer stage (one saturation radius / active edge set)
    iteration: int  # LM iteration within the stage
    error_before: float
    error_after: float
    active_edges: int


ProgressCallback = Callable[[IterationRecord], None]


@dataclass(frozen=True, eq=False)
class Alignment:
    """Result of ``align``: aligned walks in the reference walk's frame (metres, radians)."""

    session_ids: tuple[str, ...]
    reference: str
    tracks: dict[str, PoseTrack]  # aligned walks only
    unaligned: dict[str, str]  # session id -> reason
    fingerprints: FingerprintNodes
    edges: WifiEdges
    node_xyh: NDArray[np.float64]  # (N, 3) optimised pose of every step node (NaN: unaligned)
    initial_xyh: NDArray[np.float64]  # (N, 3) initial guess
    placement: Placement | None
    iterations: tuple[IterationRecord, ...]
    initial_error: float
    final_error: float
    converged: bool
    timings_s: dict[str, float] = field(default_factory=dict)
    edge_states: dict[str, int] = field(default_factory=dict)
    snapshots: tuple[tuple[int, NDArray[np.float64]], ...] = ()  # (stage, node_xyh) after each stage
    uwb: UwbSummary | None = None  # UWB ranges used (issue 15); frame "site" when anchors fixed it

    @property
    def frame(self) -> str:
        """"site" when UWB anchors fixed the frame, else "aligned" (the reference walk's)."""
        return self.uwb.frame if self.uwb is not None else "aligned"

    @property
    def n_nodes(self) -> int:
        return len(self.node_xyh)

    def fingerprint_xy(self) -> NDArray[np.float64]:
        """Optimised position of every fingerprint (NaN where its walk is unaligned)."""
        return self.node_xyh[self.fingerprints.node, :2]


def _dr_nodes(survey: Survey) -> tuple[NDArray, NDArray]:
    xyh = np.concatenate([s.steps.xyh for s in survey]) if len(survey) else np.zeros((0, 3))
    sess = np.concatenate([np.full(len(s.steps), i) for i, s in enumerate(survey)]).astype(np.int64)
    return xyh, sess


def _reference_index(survey: Survey, cfg: GraphSlamConfig) -> int:
    ref = cfg.optimizer.reference_session
    if ref is None:
        return 0
    ids = [s.session_id for s in survey]
    if ref not in ids:
        raise SolverError(f"reference session {ref!r} is not in the survey (have e.g. {ids[:3]})")
    return ids.index(ref)


def _transform_poses(xyh: NDArray, T: NDArray) -> NDArray:
    return np.column_stack([se2_apply(T, xyh[:, :2]), wrap_angle(xyh[:, 2] + T[2])])


def _saturation_radii(cfg: GraphSlamConfig) -> list[float]:
    """Graduated saturation: start wide (far-off starts still attract), end at d_max (the paper).

    From the origin start the first stage has no saturation at all; from a registration
    start the radius shrinks geometrically from 2 d_max to d_max.
    """
    n = cfg.optimizer.outer_iterations
    d_max = cfg.wifi.d_max_m
    if n == 1:
        return [d_max]
    if cfg.optimizer.initialization == "origin":
        return [float("inf")] + [float(r) for r in np.geomspace(4.0 * d_max, d_max, n - 1)]
    return [float(r) for r in np.geomspace(2.0 * d_max, d_max, n)]


@dataclass(frozen=True, eq=False)
class Problem:
    """Everything the optimiser needs, as arrays: built once, solvable by any back end.

    Node ``n`` is step ``n - offsets[s]`` of session ``s`` (global numbering).
    """

    survey: Survey
    fingerprints: FingerprintNodes
    edges: WifiEdges
    reference: int  # session index
    included: NDArray[np.bool_]  # (S,) walks in the graph
    unaligned: dict[str, str]
    placement: Placement | None
    init_xyh: NDArray[np.float64]  # (N, 3), NaN for walks not in the graph
    imu_pairs: NDArray[np.int64]  # (M, 2) consecutive nodes of included walks
    imu_u: NDArray[np.float64]  # (M, 3) measured body-frame step (eq. 6)
    wifi_pairs: NDArray[np.int64]  # (E, 2) nodes of WiFi edges between included walks
    timings_s: dict[str, float]
    uwb: UwbTerms | None = None  # UWB range factors and placement (issue 15)

    @property
    def reference_node(self) -> int:
        return int(self.fingerprints.offsets[self.reference])


def build_problem(survey: Survey, cfg: GraphSlamConfig) -> Problem:
    """Steps 1-3 of the method: fingerprints on nodes, WiFi edges, initial placement."""
    if len(survey) == 0:
        raise SolverError("survey has no sessions")
    timings: dict[str, float] = {}
    t = time.perf_counter()
    fp = associate(
        survey,
        max_gap_s=cfg.fingerprint.max_scan_step_gap_s,
        missing_dbm=cfg.fingerprint.missing_rssi_dbm,
        min_rssi_dbm=cfg.fingerprint.min_rssi_dbm,
    )
    timings["associate"] = time.perf_counter() - t

    t = time.perf_counter()
    thr = window_thresholds(fp, cfg.edges.window_steps)
    edges = propose_edges(
        fp,
        thr,
        exclude_same_session_s=cfg.edges.exclude_same_session_s,
        exclude_same_session_m=cfg.edges.exclude_same_session_m,
        max_per_fingerprint=cfg.edges.max_per_fingerprint,
        min_common_aps=cfg.edges.min_common_aps,
        block_rows=cfg.edges.chunk_rows,
    )
    timings["edges"] = time.perf_counter() - t
    log.info("%d fingerprints on %d steps, %d WiFi edges", len(fp), fp.offsets[-1], len(edges))

    t = time.perf_counter()
    dr_xyh, node_sess = _dr_nodes(survey)
    ref = _reference_index(survey, cfg)
    n_s = len(survey)
    ea, eb = fp.node[edges.i], fp.node[edges.j]
    placement = None
    unaligned: dict[str, str] = {}
    if cfg.optimizer.initialization == "registration":
        placement = register_walks(n_s, ref, node_sess, dr_xyh[:, :2], ea, eb)
        included = placement.placed.copy()
        transforms = placement.transforms
        for s in np.flatnonzero(~included):
            unaligned[survey.sessions[s].session_id] = "no rigid WiFi registration chain to the reference walk"
        if placement.reliable is False and cfg.optimizer.unreliable_registration == "unalign":
            # a placement its own loops contradict is mostly wrong (ILC: ~2 % of pairwise
            # transforms right): report the walks unaligned rather than place them wrong
            why = (
                f"registration unreliable: {placement.loops_consistent} of {placement.loops} loops between "
                "placed walks are consistent; the WiFi matches do not fix where this walk is"
            )
            for s in np.flatnonzero(included):
                if s != ref:
                    unaligned[survey.sessions[s].session_id] = why
            included[:] = False
            included[ref] = True
            log.warning(
                "registration unreliable: %d walks reported unaligned (optimizer.unreliable_registration=keep "
                "would output them anyway)", int(placement.placed.sum()) - 1,
            )
    else:
        transforms = np.zeros((n_s, 3))
        g = coo_matrix((np.ones(len(ea)), (node_sess[ea], node_sess[eb])), shape=(n_s, n_s))
        _, label = connected_components(g, directed=False)
        included = label == label[ref]
        for s in np.flatnonzero(~included):
            unaligned[survey.sessions[s].session_id] = "no WiFi edge path to the reference walk"
    # --- UWB hook (issue 15, graphslam.core.uwb.survey): range factors; with anchors the site
    # frame, the inclusion and the placement come from the ranges
    uwb = uwb_terms(survey, cfg, fp.offsets, ea, eb, included, transforms, unaligned)
    if uwb is not None:
        included, unaligned = uwb.included, dict(uwb.unaligned)
    # ---
    init_xyh = np.full_like(dr_xyh, np.nan)
    imu_pairs, imu_u = [], []
    for s in np.flatnonzero(included):
        a, b = int(fp.offsets[s]), int(fp.offsets[s + 1])
        init_xyh[a:b] = _transform_poses(dr_xyh[a:b], transforms[s])
        k = np.arange(a + 1, b)
        imu_pairs.append(np.column_stack([k - 1, k]))
        imu_u.append(F.relative_steps(survey.sessions[s].steps))
    if uwb is not None:  # UWB hook: the placement from the ranges
        placed = np.isfinite(uwb.init_xyh[:, 0])
        init_xyh[placed] = uwb.init_xyh[placed]
    use = included[node_sess[ea]] & included[node_sess[eb]]
    timings["initialise"] = time.perf_counter() - t
    return Problem(
        survey=survey,
        fingerprints=fp,
        edges=edges,
        reference=ref,
        included=included,
        unaligned=unaligned,
        placement=placement,
        init_xyh=init_xyh,
        imu_pairs=np.concatenate(imu_pairs).astype(np.int64),
        imu_u=np.concatenate(imu_u),
        wifi_pairs=np.column_stack([ea[use], eb[use]]).astype(np.int64),
        timings_s=timings,
        uwb=uwb,
    )


def native_graph(
    problem: Problem, cfg: GraphSlamConfig
) -> tuple[gtsam.NonlinearFactorGraph, list[gtsam.NonlinearFactor], gtsam.Values, CompressedChains | None]:
    """(IMU factors + reference prior, one WiFi factor per edge, initial values, chains): GTSAM C++ factors only.

    With ``optimizer.compress_chains`` the IMU chain between fingerprint poses becomes one
    between factor per segment (``graphslam.core.survey.chains``); otherwise one per step (eq. 6-8).
    """
    imu_graph = gtsam.NonlinearFactorGraph()
    chains = None
    if cfg.optimizer.compress_chains:
        keep = np.zeros(len(problem.init_xyh), bool)
        keep[problem.wifi_pairs.ravel()] = True
        keep[problem.reference_node] = True
        if problem.uwb is not None:  # UWB hook: poses with a range stay variables
            keep[problem.uwb.nodes] = True
        step_cov = np.diag([cfg.imu.sigma_xy_m**2, cfg.imu.sigma_xy_m**2, cfg.imu.sigma_heading_rad**2])
        chains = compress(_dr_nodes(problem.survey)[0], problem.fingerprints.offsets, keep, problem.included, step_cov)
        for (i, j), u, cov in zip(chains.pairs.tolist(), chains.measured, chains.covariance):
            imu_graph.add(F.imu_factor(X(i), X(j), u, gtsam.noiseModel.Gaussian.Covariance(cov)))
        nodes = chains.kept
    else:
        imu_nm = F.imu_noise(cfg.imu)
        for (i, j), u in zip(problem.imu_pairs.tolist(), problem.imu_u):
            imu_graph.add(F.imu_factor(X(i), X(j), u, imu_nm))
        nodes = np.flatnonzero(np.isfinite(problem.init_xyh[:, 0]))
    r0 = problem.reference_node
    uwb = problem.uwb
    if uwb is None or not uwb.site_frame:  # with UWB anchors they fix the frame instead
        imu_graph.add(gtsam.PriorFactorPose2(X(r0), gtsam.Pose2(*problem.init_xyh[r0]), F.reference_prior_noise()))
    values = gtsam.Values()
    for n in nodes.tolist():
        values.insert(X(n), gtsam.Pose2(*problem.init_xyh[n]))
    if uwb is not None:  # UWB hook: range factors (always active) and the anchors
        for f in uwb_factors.range_factors(uwb.ranges, cfg.uwb, with_anchors=uwb.site_frame):
            imu_graph.add(f)
        values.insert(uwb_factors.anchor_values(uwb.ranges))
    wifi_nm = F.wifi_noise(cfg.wifi)
    wifi = [F.wifi_factor(X(i), X(j), wifi_nm) for i, j in problem.wifi_pairs.tolist()]
    return imu_graph, wifi, values, chains


def lm_params(cfg: GraphSlamConfig, n_poses: int = 0) -> gtsam.LevenbergMarquardtParams:
    """LM settings. Direct multifrontal Cholesky is fastest on surveys of a few thousand fingerprint
    poses; beyond that the WiFi edges, which tie every revisited place together, make elimination
    cliques grow large and block-Jacobi PCG wins (docs/benchmarks.md)."""
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(cfg.optimizer.max_iterations)
    params.setRelativeErrorTol(cfg.optimizer.relative_error_tol)
    params.setAbsoluteErrorTol(cfg.optimizer.absolute_error_tol)
    params.setOrderingType("METIS")
    solver = cfg.optimizer.linear_solver
    if solver == "pcg" or (solver == "auto" and n_poses > cfg.optimizer.pcg_above_poses):
        params.setLinearSolverType("ITERATIVE")
        pcg = gtsam.PCGSolverParameters()
        pcg.preconditioner = gtsam.BlockJacobiPreconditionerParameters()
        params.setIterativeParams(pcg)
    return params


def align(survey: Survey, config: GraphSlamConfig | None = None, progress: ProgressCallback | None = None) -> Alignment:
    """Align all walks of ``survey`` into the frame of the reference walk's first pose."""
    cfg = config or GraphSlamConfig()
    t0 = time.perf_counter()
    problem = build_problem(survey, cfg)
    return solve(problem, cfg, progress, t0=t0)


def solve(
    problem: Problem, cfg: GraphSlamConfig, progress: ProgressCallback | None = None, *, t0: float | None = None
) -> Alignment:
    """Step 5: LM over a shrinking set of unsaturated WiFi edges (graduated saturation)."""
    t0 = time.perf_counter() if t0 is None else t0
    timings = dict(problem.timings_s)
    t = time.perf_counter()
    imu_graph, wifi_factors, values, chains = native_graph(problem, cfg)
    ea, eb = problem.wifi_pairs[:, 0], problem.wifi_pairs[:, 1]
    timings["build_graph"] = time.perf_counter() - t

    t = time.perf_counter()
    records: list[IterationRecord] = []
    snapshots: list[tuple[int, NDArray]] = []

    def objective(xyh: NDArray, vals: gtsam.Values) -> float:
        d = np.linalg.norm(xyh[ea, :2] - xyh[eb, :2], axis=1)
        return float(imu_graph.error(vals) + F.fuzzy_cost(d, cfg.wifi).sum())

    init_xyh = problem.init_xyh
    dr_xyh = _dr_nodes(problem.survey)[0]
    xyh = init_xyh.copy()
    initial_error = objective(xyh, values)
    converged = False
    prev_active: NDArray | None = None
    for stage, radius in enumerate(_saturation_radii(cfg)):
        d = np.linalg.norm(xyh[ea, :2] - xyh[eb, :2], axis=1)
        active = d <= radius
        if prev_active is not None and np.array_equal(active, prev_active) and converged:
            continue  # LM already converged on exactly this graph
        graph = gtsam.NonlinearFactorGraph(imu_graph)
        for k in np.flatnonzero(active).tolist():
            graph.add(wifi_factors[k])
        params = lm_params(cfg, values.size())
        n_active = int(active.sum())

        def hook(it: int, before: float, after: float, _s: int = stage, _n: int = n_active) -> None:
            rec = IterationRecord(_s, int(it), float(before), float(after), _n)
            records.append(rec)
            if progress is not None:
                progress(rec)

        params.iterationHook = hook
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        values = optimizer.optimize()
        # LM also stops when it can find no step that lowers the error (lambda at its upper
        # bound): that is a stall, not convergence
        converged = (
            optimizer.iterations() < cfg.optimizer.max_iterations
            and optimizer.lambda_() < params.getlambdaUpperBound()
        )
        xyh = _values_to_xyh(values, init_xyh)
        if chains is not None:
            xyh = expand(xyh, dr_xyh, chains)
        snapshots.append((stage, xyh.copy()))
        prev_active = active
    timings["optimise"] = time.perf_counter() - t
    final_error = objective(xyh, values)

    d = np.linalg.norm(xyh[ea, :2] - xyh[eb, :2], axis=1)
    st = F.edge_state(d, cfg.wifi)
    survey = problem.survey
    fp = problem.fingerprints
    tracks = {}
    for s in np.flatnonzero(problem.included):
        sess = survey.sessions[s]
        a, b = fp.offsets[s], fp.offsets[s + 1]
        tracks[sess.session_id] = PoseTrack.from_xyh(sess.steps.t_ns, xyh[a:b])
    timings["total"] = time.perf_counter() - t0
    return Alignment(
        session_ids=tuple(s.session_id for s in survey),
        reference=survey.sessions[problem.reference].session_id,
        tracks=tracks,
        unaligned=dict(problem.unaligned),
        fingerprints=fp,
        edges=problem.edges,
        node_xyh=xyh,
        initial_xyh=init_xyh,
        placement=problem.placement,
        iterations=tuple(records),
        initial_error=initial_error,
        final_error=final_error,
        converged=converged,
        timings_s=timings,
        edge_states={
            "inactive": int((st == 0).sum()),
            "ramp": int((st == 1).sum()),
            "saturated": int((st == 2).sum()),
        },
        snapshots=tuple(snapshots),
        uwb=problem.uwb.summary() if problem.uwb is not None else None,
    )


def _values_to_xyh(values: gtsam.Values, template: NDArray) -> NDArray:
    out = np.full_like(template, np.nan)
    # gtsam.utilities.extractPose2 returns the poses in key order (UWB anchors are Point2s)
    keys = [k for k in values.keys() if gtsam.Symbol(k).chr() == ord("x")]
    poses = gtsam.utilities.extractPose2(values)
    idx = np.array([gtsam.Symbol(k).index() for k in keys], dtype=np.int64)
    out[idx] = poses
    return out
