"""The survey with the phones' headings: components, heading priors, control-point ties.

``split_by_heading`` is the ``heading`` initialisation of ``graphslam.core.survey.align``:
every walk turned by its heading (``graphslam.core.survey.heading``), map growth into
components (``graphslam.core.survey.components``), with control points component 0 grown from
the walks they tie (``graphslam.core.survey.control``); ``HeadingTerms`` are the priors the
optimiser puts on the walks' headings.

Frames: dead reckoning -> each component's (east/north; site with control points). Radians, metres.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Mapping

import numpy as np
from numpy.typing import NDArray

from graphslam.config import GraphSlamConfig
from graphslam.core.radiomap.similarity import PowerCosine
from graphslam.core.survey.association import FingerprintNodes
from graphslam.core.survey.components import Component, place_components
from graphslam.core.survey.control import ControlTies, control_ties, tie_walks
from graphslam.core.survey.heading import heading_residuals, walk_headings
from graphslam.core.survey.initialise import Placement, se2_apply_poses
from graphslam.core.survey.placement import GrowthParams
from graphslam.core.types import Survey, wrap_angle
from graphslam.errors import SolverError

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class HeadingTerms:
    """Heading priors per node: target heading (rad, in the node's component frame) and sigma.

    ``walk``: one prior per walk, on its first solved pose: its dead-reckoned heading turned by the
    walk's rotation from the phone's heading, sigma the walk's (the dead reckoning's own drift along
    the walk stays free for the WiFi edges to correct); ``step``: the target is the phone's yaw at
    that step turned by the walk's offset as placed (the yaw's shape corrects the dead reckoning's
    heading drift; the walk's rotation stays the placement's), sigma = the yaw's spread along the
    walk, counted once per ``correlation_steps``."""

    target: NDArray[np.float64]  # (N,) NaN: no prior
    walk_sigma: NDArray[np.float64]  # (S,) the walk's rotation sigma (rad)
    spread: NDArray[np.float64]  # (S,) robust spread of yaw - dead-reckoned heading along the walk
    mode: str  # "walk" | "step" | "none"
    correlation_steps: int = 20
    step_floor_rad: float = float(np.radians(2.0))

    def node_sigma(self, nodes: NDArray[np.int64], node_session: NDArray[np.int64]) -> NDArray[np.float64]:
        """Sigma of each ``step`` prior on ``nodes``: the yaw's spread, counted once per ``correlation_steps``."""
        s = node_session[nodes]
        n = np.bincount(s, minlength=len(self.walk_sigma)).astype(float)
        steps = np.bincount(node_session, minlength=len(self.walk_sigma)).astype(float)
        per_draw = np.maximum(1.0, self.correlation_steps * n[s] / np.maximum(steps[s], 1.0))
        return np.hypot(self.spread[s], self.step_floor_rad) * np.sqrt(per_draw)


def _step_targets(survey: Survey, offsets: NDArray, init_xyh: NDArray, phi: float) -> NDArray[np.float64]:
    """Per node: the phone's yaw at that step (+ the site offset), turned by the walk's mean offset
    between the placed heading and the yaw (NaN where the walk has no heading)."""
    out = np.full(len(init_xyh), np.nan)
    for s, sess in enumerate(survey):
        k, _ = heading_residuals(sess)
        if len(k) == 0:
            continue
        a = int(offsets[s])
        n = len(sess.steps)
        yaw = np.full(n, np.nan)
        kk = np.clip(np.searchsorted(sess.steps.t_ns, sess.heading.t_ns), 0, n - 1)
        yaw[kk] = sess.heading.yaw + phi
        idx = np.arange(n)
        have = np.isfinite(yaw)
        near = idx[have][np.clip(np.searchsorted(idx[have], idx), 0, have.sum() - 1)]
        yaw = yaw[near]  # steps without a message take the next one's (the first step)
        off = np.angle(np.exp(1j * (init_xyh[a:a + n, 2] - yaw)).mean())
        out[a:a + n] = np.asarray(wrap_angle(yaw + off), float)
    return out


@dataclass(frozen=True, eq=False)
class ComponentSplit:
    """The heading placement's outcome: components, their held nodes, heading priors, control ties."""

    placement: Placement
    component: NDArray[np.int64]
    components: tuple[Component, ...]
    reference: int  # session index of component 0's seed (its first pose: the frame's origin without ties)
    fixed_nodes: NDArray[np.int64]
    heading: HeadingTerms
    ties: ControlTies | None
    frame_name: str


def split_by_heading(
    survey: Survey, fp: FingerprintNodes, dr_xyh: NDArray, node_sess: NDArray, cfg: GraphSlamConfig,
    control_points: Mapping[str, tuple[float, float]] | None,
    *,
    seed: int | None = None,
) -> ComponentSplit:
    """Heading placement: every walk rotated by its heading (east/north), map growth into components
    (``graphslam.core.survey.components``); with control points component 0 grows from the walks
    they tie, in the site frame."""
    hc, pc = cfg.heading, cfg.placement
    wh = walk_headings(
        survey, sigma_floor_rad=np.radians(hc.sigma_floor_deg), cauchy_scale_rad=np.radians(hc.cauchy_scale_deg),
        correlation_steps=hc.correlation_steps,
    )
    if not wh.complete:
        missing = [survey.sessions[s].session_id for s in np.flatnonzero(~wh.available)]
        raise SolverError(
            f"optimizer.initialization heading needs /phone/heading on every walk; {len(missing)} have none "
            f"(e.g. {missing[0]!r}): use auto or registration"
        )
    ties = tied = None
    phi = 0.0
    if control_points:
        ties = control_ties(survey, control_points, fp.offsets)
        tp = tie_walks(ties, dr_xyh, node_sess, wh.rotation)
        tied, phi = tp.transforms, tp.site_from_earth
        if not tied:
            raise SolverError("no walk can be tied to the control points (none marks one and has a heading)")
    sim = PowerCosine.of(fp.fingerprints, pc.similarity_scale_db)
    matches = sim.top_matches(fp.session, pc.matches_per_fingerprint)
    params = GrowthParams.from_config(cfg, min_margin=hc.min_margin, rotation_window_deg=hc.rotation_window_deg)
    # with ties, every walk's rotation is site-from-dead-reckoning: heading + the site frame's offset
    rotation = wh.rotation + phi
    cp = place_components(
        len(survey), fp.session, dr_xyh[fp.node, :2], matches, params,
        rotation=rotation, rotation_sigma=wh.sigma, tied=tied, seed=seed,
    )
    ids = [s.session_id for s in survey]
    comps = tuple(
        Component(k, tuple(ids[s] for s in cp.walks_of(k)), cp.reasons.get(k, "")) for k in range(cp.n_components)
    )
    offsets = fp.offsets
    # held nodes: the first pose of each component's seed walk (component 0 with ties: none, the ties hold it)
    fixed = np.array([int(offsets[sd]) for sd in cp.seeds if sd >= 0], np.int64)
    reference = cp.seeds[0] if cp.seeds and cp.seeds[0] >= 0 else int(ties.walks[0]) if ties is not None else 0
    # the prior's target: the dead-reckoned heading turned by the rotation the phone's heading gives
    # (not the placed one, which would only restate the placement); with ties every component was
    # placed turned by the site offset, so every frame is site-aligned
    walk_rot = wh.rotation + phi
    target = np.asarray(wrap_angle(dr_xyh[:, 2] + walk_rot[node_sess]), float)
    target[~np.isfinite(target)] = np.nan
    if hc.prior == "step":
        init = np.full_like(dr_xyh, np.nan)
        for w in range(len(survey)):
            a, b = int(offsets[w]), int(offsets[w + 1])
            init[a:b] = se2_apply_poses(cp.transforms[w], dr_xyh[a:b])
        target = _step_targets(survey, offsets, init, phi)
    heading = HeadingTerms(target, wh.sigma, wh.spread, hc.prior, hc.correlation_steps)
    pl = Placement(
        cp.transforms, np.ones(len(survey), bool), np.full(len(survey), -1, np.int64), np.full(len(survey), -1, np.int64),
        method="heading", support=cp.support, margin=cp.margin, consistency=cp.consistency,
    )
    frame = "site" if ties is not None else "earth"
    main = int((cp.component == 0).sum())
    log.info("heading placement: %d components, the main map holds %d of %d walks", cp.n_components, main, len(survey))
    return ComponentSplit(pl, cp.component, comps, reference, fixed, heading, ties, frame)
