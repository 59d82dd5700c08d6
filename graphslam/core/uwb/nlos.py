"""NLOS ranges out, before the survey's LM: a UWB-only solve that rejects ranges too long.

Indoors NLOS is the rule: a range through a wall or a body is longer than the truth by
0.3-2 m and never shorter beyond noise. A symmetric robust loss still lets a third of such
ranges push walkers away from the anchors (simulated crowd, seed 0: 0.13 m clean, 0.86 m with
Cauchy on 35 % NLOS ranges, Huber 3.5 m). GTSAM's asymmetric losses do not help here: through a
``Robust`` model the cost sees only the size of the whitened error, and ``RangeFactor``'s error
h(x) - z puts NLOS ranges on the side they treat as quadratic. So the physics is used directly:

0. **pre-filter, no solve** (``too_long_by_chords``, ``uwb.nlos_chord_*``): between two ranges
   of one link (a walker and an anchor, or two walkers) the true distance changes by at most the
   chord each end walked, which the dead reckoning measures in its own frame (no placement). A
   range longer than another of its link within 30 s by more than that chord plus 3 sigma of
   the two ranges and the steps between is dropped for good (the other range may itself be too
   long: that only loosens the bound). It catches through-wall ranges where a walker hardly
   moved since a LOS one; under a persistent bias only the first ranges behind the wall;
1. the walks' dead-reckoning chains (one ``BetweenFactorPose2`` per step, with the tighter
   ``uwb.presolve_sigma_*`` of a chain that only ranges pull on: WiFi edges, which can be wrong
   by metres, are not in this solve), from the UWB placement, with the anchor ranges only: an
   anchor cannot move to hide a range that is too long;
2. every range measured longer than the solution by more than ``uwb.nlos_reject_sigmas`` of its
   own sigma is dropped as NLOS (one-sided: a range shorter than the solution is never dropped),
   and the solve repeats until the set has settled (fewer than 0.5 % of the ranges change sides;
   a dropped range the solution later fits, or whose upper bound it violates, comes back);
3. the peer ranges are judged against that solution (which they did not shape), join, and
   step 2 repeats over both kinds.

The survey then uses the kept ranges only, and starts from this solution. All factors are
native GTSAM; the gauge is the anchors' priors (site frame) or a prior on the first pose of a
walk the WiFi placement fixed (reference frame, peer ranges only).

Measured (lab/journal/benchmarks-history.md): with 2 anchors and a third of the ranges
NLOS, steps 1-3 alone leave 1.55x the clean error (5 seeds); the true NLOS flags (an oracle)
give 1.30x. By the truth, steps 1-3 already drop 97-99 % of the biased ranges; what costs is
the 2-3 % they keep (dropping those too: 1.43x) and the LOS ranges they drop (re-admitting
those: 1.49x). The pre-filter changes both a little; with it the same runs give 1.49x.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from graphslam.config import GraphSlamConfig, UwbConfig
from graphslam.core.common.factors import imu_factor, imu_noise, reference_prior_noise, relative_steps
from graphslam.core.types import Survey
from graphslam.core.uwb.factors import X, SurveyRanges, anchor_values, range_factors, range_residuals

log = logging.getLogger(__name__)

MAX_ROUNDS = 30
SETTLED_FRACTION = 0.005  # the set is settled when fewer ranges than this change sides in a round


def too_long_by_chords(
    group: NDArray[np.int64],
    t: NDArray[np.float64],
    q: NDArray[np.float64],
    node: NDArray[np.int64],
    r: NDArray[np.float64],
    sigma: NDArray[np.float64],
    *,
    k: float,
    step_sigma_m: float,
    max_dt_s: float,
) -> NDArray[np.bool_]:
    """Ranges that are provably too long, from the ranges and the dead reckoning alone (no solve).

    Ranges of one ``group`` measure one distance between the same two bodies (a walker and an
    anchor, or two walkers). Between two of them, at times i and j, that distance changes by at
    most the chord |q_i - q_j| each moving end travelled (``q`` (M, E, 2): the E = 1 or 2 ends'
    antennas, each in its own walk's dead-reckoning frame, so no placement is needed). Hence
    r_i > r_j + sum of the chords + k * sqrt(sigma_i^2 + sigma_j^2 + steps * step_sigma^2) says
    r_i is longer than the truth beyond noise, whatever r_j is (a too-long r_j only weakens the
    bound). ``node`` (M, E): the step nodes the antennas belong to (their difference counts the
    dead-reckoning steps between i and j, whose error the slack covers); only pairs within
    ``max_dt_s`` are compared. A LOS range is flagged only when its noise beats that slack.
    """
    out = np.zeros(len(r), bool)
    if not len(r):
        return out
    order = np.lexsort((t, group))
    g = group[order]
    cuts = np.flatnonzero(np.diff(g)) + 1
    for idx in np.split(order, cuts):
        if len(idx) < 2:
            continue
        tg = t[idx]  # sorted
        for lo in range(0, len(idx), 512):  # rows in blocks of 512 ...
            i = idx[lo:lo + 512]
            # ... against the ranges of the link within max_dt_s of them only: memory stays
            # O(512 x ranges per window), however long the walks
            t_first, t_last = tg[lo], tg[min(lo + 511, len(idx) - 1)]
            j = idx[np.searchsorted(tg, t_first - max_dt_s, "left"):np.searchsorted(tg, t_last + max_dt_s, "right")]
            dt = np.abs(t[i][:, None] - t[j][None, :])
            chord = np.linalg.norm(q[i][:, None] - q[j][None, :], axis=-1).sum(-1)
            steps = np.abs(node[i][:, None] - node[j][None, :]).sum(-1)
            slack = k * np.sqrt(sigma[i][:, None] ** 2 + sigma[j][None, :] ** 2 + steps * step_sigma_m**2)
            bound = r[j][None, :] + chord + slack
            out[i] = ((r[i][:, None] > bound) & (dt <= max_dt_s)).any(axis=1)
    return out


def chord_flags(
    sr: SurveyRanges, walk_a: NDArray[np.int64], t_a: NDArray, q_a: NDArray,
    walk_p: NDArray[np.int64], t_p: NDArray, qa_p: NDArray, qb_p: NDArray,
    node_walk: NDArray[np.int64], cfg: UwbConfig,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """``too_long_by_chords`` over the anchor ranges (one group per walker and anchor) and the peer
    ranges (one per pair of walkers, whichever of the two measured) of ``sr``; the other arrays
    (as ``RangeObservations``) in the order of ``sr``. (Ma,) and (Mp,) flags: provably too long."""
    kw = dict(k=cfg.nlos_chord_sigmas, step_sigma_m=cfg.presolve_sigma_xy_m, max_dt_s=cfg.nlos_chord_max_dt_s)
    n_a = len(sr.anchor_ids)
    fa = too_long_by_chords(walk_a * n_a + sr.a_anchor, t_a, q_a[:, None], sr.a_node[:, None], sr.a_range, sr.a_sigma, **kw)
    if not len(sr.p_node):
        return fa, np.zeros(0, bool)
    swap = walk_p[:, 0] > walk_p[:, 1]  # canonical order: the lower walk first
    lo, hi = np.where(swap, walk_p[:, 1], walk_p[:, 0]), np.where(swap, walk_p[:, 0], walk_p[:, 1])
    q = np.where(swap[:, None, None], np.stack([qb_p, qa_p], 1), np.stack([qa_p, qb_p], 1))
    first_is_lo = node_walk[sr.p_node[:, 0]] == lo
    node = np.where(first_is_lo[:, None], sr.p_node, sr.p_node[:, ::-1])
    n_w = int(max(walk_p.max(), walk_a.max(initial=0))) + 1
    fp = too_long_by_chords(lo * n_w + hi, t_p, q, node, sr.p_range, sr.p_sigma, **kw)
    return fa, fp


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
    too_long: tuple[NDArray[np.bool_], NDArray[np.bool_]] | None = None,
) -> NlosResult:
    """Steps 1-3 of the module docstring for the walks ``included``; ``gauge_node``: the pose held
    fixed when not ``site_frame``."""
    import gtsam  # here: a survey without UWB ranges never loads it

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
        return (ea <= k * sr.a_sigma) & ~bad_a, (ep <= k * sr.p_sigma) & ~bad_p

    bad_a, bad_p = too_long if too_long is not None else (np.zeros(len(sr.a_node), bool), np.zeros(len(sr.p_node), bool))

    keep_a = np.full(len(sr.a_node), site_frame) & ~bad_a
    keep_p = np.zeros(len(sr.p_node), bool)
    rounds = 0
    # 1. anchors only (fixed points: an NLOS anchor range cannot hide by moving its anchor);
    # 2. the peer ranges join, judged first by a solution they did not shape
    for stage, peers in enumerate((False, True)):
        if peers:
            if not site_frame:
                keep_p = ~bad_p
            elif len(keep_p):
                keep_p = (range_residuals(sr, xyh)[1] <= k * sr.p_sigma) & ~bad_p
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
