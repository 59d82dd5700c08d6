"""NLOS ranges out, before the survey's LM: a UWB-only solve that rejects ranges too long.

Indoors NLOS is the rule: a range through a wall or a body is longer than the truth by
0.3-2 m and never shorter beyond noise. A symmetric robust loss still lets a third of such
ranges push walkers away from the anchors (simulated crowd, seed 0: 0.13 m clean, 0.86 m with
Cauchy on 35 % NLOS ranges, Huber 3.5 m). GTSAM's asymmetric losses do not help here: through a
``Robust`` model the cost sees only the size of the whitened error, and ``RangeFactor``'s error
h(x) - z puts NLOS ranges on the side they treat as quadratic. So the physics is used directly:

1. the walks' dead-reckoning chains (one ``BetweenFactorPose2`` per step, with the tighter
   ``uwb.presolve_sigma_*`` of a chain that only ranges pull on: WiFi edges, which can be wrong
   by metres, are not in this solve), from the UWB placement, with the anchor ranges only: an
   anchor cannot move to hide a range that is too long;
2. every range measured longer than the solution by more than ``uwb.nlos_reject_sigmas`` of its
   own sigma is dropped as NLOS (one-sided: a range shorter than the solution is never dropped),
   and the solve repeats until the set has settled (fewer than 0.5 % of the ranges change sides);
3. the peer ranges are judged against that solution (which they did not shape), join, and
   step 2 repeats over both kinds.

The survey then uses the kept ranges only, and starts from this solution. All factors are
native GTSAM; the gauge is the anchors' priors (site frame) or a prior on the first pose of a
walk the WiFi placement fixed (reference frame, peer ranges only).

Measured (docs/benchmarks.md, issue 15): this leaves ~2x the clean error where a third of the
ranges are NLOS; with the true NLOS flags (an oracle) the same graph reaches ~1.4x.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import gtsam
import numpy as np
from numpy.typing import NDArray

from graphslam.config import GraphSlamConfig
from graphslam.core.survey.factors import imu_factor, imu_noise, reference_prior_noise, relative_steps
from graphslam.core.types import Survey
from graphslam.core.uwb.factors import X, SurveyRanges, anchor_values, range_factors, range_residuals

log = logging.getLogger(__name__)

MAX_ROUNDS = 30
SETTLED_FRACTION = 0.005  # the set is settled when fewer ranges than this change sides in a round


@dataclass(frozen=True, eq=False)
class NlosResult:
    xyh: NDArray[np.float64]  # (N, 3) solution with the kept ranges (NaN: walks not solved)
    keep_anchor: NDArray[np.bool_]  # not NLOS
    keep_peer: NDArray[np.bool_]
    rounds: int


def reject_nlos(
    survey: Survey,
    offsets: NDArray[np.int64],
    included: NDArray[np.bool_],
    init_xyh: NDArray[np.float64],
    sr: SurveyRanges,
    cfg: GraphSlamConfig,
    *,
    site_frame: bool,
    gauge_node: int | None = None,
) -> NlosResult:
    """Steps 1-3 of the module docstring for the walks ``included``; ``gauge_node``: the pose held
    fixed when not ``site_frame``."""
    base = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    nm = imu_noise(cfg.imu.model_copy(update={
        "sigma_xy_m": cfg.uwb.presolve_sigma_xy_m, "sigma_heading_rad": cfg.uwb.presolve_sigma_heading_rad,
    }))
    for s in np.flatnonzero(included).tolist():
        a, b = int(offsets[s]), int(offsets[s + 1])
        for k, u in zip(range(a + 1, b), relative_steps(survey.sessions[s].steps)):
            base.add(imu_factor(X(k - 1), X(k), u, nm))
        for k in range(a, b):
            values.insert(X(k), gtsam.Pose2(*init_xyh[k]))
    if site_frame:
        values.insert(anchor_values(sr))
    elif gauge_node is not None:
        base.add(gtsam.PriorFactorPose2(X(gauge_node), gtsam.Pose2(*init_xyh[gauge_node]), reference_prior_noise()))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(cfg.optimizer.max_iterations)
    params.setRelativeErrorTol(cfg.optimizer.relative_error_tol)
    params.setOrderingType("METIS")
    k = cfg.uwb.nlos_reject_sigmas
    xyh = init_xyh.copy()

    def solve(use_a: NDArray, use_p: NDArray) -> tuple[NDArray, NDArray]:
        nonlocal values
        graph = gtsam.NonlinearFactorGraph(base)
        for f in range_factors(sr.subset(use_a, use_p), cfg.uwb, with_anchors=site_frame):
            graph.add(f)
        values = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
        keys = [key for key in values.keys() if gtsam.Symbol(key).chr() == ord("x")]
        xyh[[gtsam.Symbol(key).index() for key in keys]] = gtsam.utilities.extractPose2(values)
        ea, ep = range_residuals(sr, xyh)
        return ea <= k * sr.a_sigma, ep <= k * sr.p_sigma

    keep_a = np.full(len(sr.a_node), site_frame)
    keep_p = np.zeros(len(sr.p_node), bool)
    rounds = 0
    # 1. anchors only (fixed points: an NLOS anchor range cannot hide by moving its anchor);
    # 2. the peer ranges join, judged first by a solution they did not shape
    for stage, peers in enumerate((False, True)):
        if peers:
            if not site_frame:
                keep_p[:] = True
            elif len(keep_p):
                keep_p = range_residuals(sr, xyh)[1] <= k * sr.p_sigma
        elif not site_frame:
            continue
        for _ in range(MAX_ROUNDS):
            rounds += 1
            new_a, new_p = solve(keep_a, keep_p)
            new_a &= site_frame
            if not peers:
                new_p = keep_p
            flips = int((new_a != keep_a).sum() + (new_p != keep_p).sum())
            changed = flips > SETTLED_FRACTION * (len(new_a) + len(new_p))
            keep_a, keep_p = new_a, new_p
            log.info("UWB NLOS stage %d round %d: kept %d of %d anchor, %d of %d peer ranges", stage + 1, rounds,
                     keep_a.sum(), len(keep_a), keep_p.sum(), len(keep_p))
            if not changed:
                break
    return NlosResult(xyh, keep_a, keep_p, rounds)
