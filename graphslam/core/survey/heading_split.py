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
from graphslam.core.radiomap.similarity import Matches, PowerCosine
from graphslam.core.survey.association import FingerprintNodes
from graphslam.core.survey.components import Component, ComponentPlacement, place_components, place_units, se2_apply_rows
from graphslam.core.survey.control import ControlTies, control_ties, tie_walks
from graphslam.core.survey.heading import heading_residuals, walk_headings
from graphslam.core.survey.incremental import WarmStart
from graphslam.core.survey.magnetic import (
    LinkUnits, MagneticLinks, MagneticParams, link_units, magnetic_links, singleton_units,
)
from graphslam.core.survey.reference import ReferenceLinks, site_rotation
from graphslam.core.survey.initialise import Placement, se2_apply_poses, se2_compose
from graphslam.core.survey.placement import GrowthParams, grow_placement
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
    heading: HeadingTerms | None  # None: walks without the phones' headings (``split_without_headings``)
    ties: ControlTies | None
    frame_name: str
    magnetic: MagneticLinks | None = None  # the links the placement used (their node pairs: the graph's factors)
    anchors: ReferenceLinks | None = None  # the reference map component 0 is placed on
    unused_reference: bool = False  # a reference map was given and no walk registers onto it
    site_from_earth: float | None = None  # rad: the site frame's rotation from east/north (frame "site")


def split_by_heading(
    survey: Survey, fp: FingerprintNodes, dr_xyh: NDArray, node_sess: NDArray, cfg: GraphSlamConfig,
    control_points: Mapping[str, tuple[float, float]] | None,
    *,
    seed: int | None = None,
    reference: ReferenceLinks | None = None,
) -> ComponentSplit:
    """Heading placement: every walk rotated by its heading (east/north), map growth into components
    (``graphslam.core.survey.components``); with control points component 0 grows from the walks
    they tie, in the site frame; with a reference map (``graphslam.core.survey.reference``) from it."""
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
    ties = tied = tp = None
    phi = 0.0
    unused_reference = False
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
    units = _magnetic_units(survey, fp, dr_xyh, node_sess, cfg, matches, rotation, wh.sigma, params)
    tie_arrays = None
    if ties is not None:
        placed = np.isin(ties.session, list(tied))
        tie_arrays = (ties.session[placed], dr_xyh[ties.node[placed], :2], ties.xy[placed])
    cp = None
    if reference is not None:  # the surveyed map holds component 0 in the site frame
        on_ref = units if units is not None else singleton_units(rotation)
        turn = 0.0
        if ties is None or not tp.rotation_fixed:  # the site's rotation from the crowd's reference matches
            unit_xy = se2_apply_rows(on_ref.transforms[fp.session], dr_xyh[fp.node, :2])
            turn, _ = site_rotation(on_ref.unit[fp.session], unit_xy, reference, params)
            on_ref = on_ref.turned(turn)
        cp = place_units(
            len(survey), fp.session, dr_xyh[fp.node, :2], matches, params, on_ref, rotation_sigma=wh.sigma,
            ties=tie_arrays, seed=seed, reference=(reference.xy, Matches(reference.match_i, reference.match_j,
                                                                         reference.similarity)),
        )
        if (cp.component == 0).any():
            phi += turn
            rotation = wh.rotation + phi
            log.info("reference map: the site frame is turned %.1f deg from east/north (the crowd's matches)",
                     np.degrees(phi))
        else:  # no walk registers onto it: surveyed as without it, and said
            log.warning("reference map: no walk registers onto it unambiguously; the survey does not use it")
            reference, cp = None, None
            unused_reference = True
    if cp is None and units is not None and units.n_units < len(survey):  # walks the field holds together move as one
        cp = place_units(
            len(survey), fp.session, dr_xyh[fp.node, :2], matches, params, units,
            rotation_sigma=wh.sigma, ties=tie_arrays, seed=seed,
        )
    elif cp is None:
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
    main_walks = cp.walks_of(0)
    ref_walk = cp.seeds[0] if cp.seeds and cp.seeds[0] >= 0 else int(main_walks[0]) if len(main_walks) else 0
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
    frame = "site" if ties is not None or reference is not None else "earth"
    main = int((cp.component == 0).sum())
    log.info("heading placement: %d components, the main map holds %d of %d walks", cp.n_components, main, len(survey))
    return ComponentSplit(pl, cp.component, comps, ref_walk, fixed, heading, ties, frame,
                          magnetic=None if units is None else units.links, anchors=reference,
                          unused_reference=unused_reference, site_from_earth=phi if frame == "site" else None)


def _magnetic_units(
    survey: Survey, fp: FingerprintNodes, dr_xyh: NDArray, node_sess: NDArray, cfg: GraphSlamConfig, matches: Matches,
    rotation: NDArray, sigma: NDArray, params: GrowthParams,
) -> LinkUnits | None:
    """The walks the magnetic field links (``graphslam.core.survey.magnetic``), as units; None when it
    is off or fewer than two walks carry it."""
    if not cfg.magnetic.enabled or sum(s.magnetic is not None and len(s.magnetic) > 0 for s in survey) < 2:
        return None
    mp = MagneticParams.from_config(cfg.magnetic)
    links = magnetic_links(survey, fp.offsets, rotation, fp.node[matches.i], fp.node[matches.j], mp)
    units = link_units(links, len(survey), rotation, sigma, dr_xyh[:, :2], node_sess, mp.agree_m, params)
    log.info("magnetic: %d links, %d consistent with their units' placement; %d walks in %d units of two or more",
             len(links), len(units.links), int((np.bincount(units.unit)[units.unit] > 1).sum()),
             int((np.bincount(units.unit) > 1).sum()))
    return units


def split_without_headings(
    survey: Survey, fp: FingerprintNodes, dr_xyh: NDArray, node_sess: NDArray, cfg: GraphSlamConfig,
    control_points: Mapping[str, tuple[float, float]] | None = None, reference: ReferenceLinks | None = None,
) -> ComponentSplit | None:
    """Walks without the phones' headings (a foot-mounted module's, or a phone's without its azimuth) in
    the site frame of control points and/or a reference map: each walk a rigid body in its own dead
    reckoning. A walk marking two control points at least ``min_baseline_m`` apart is tied rigidly by its
    marks (``tie_walks``); the others join by map growth over every rotation (``heading.min_margin``: a
    search of every rotation finds runner-ups that one near a heading would not) — onto the held
    reference by their reference matches, onto placed walks by their WiFi matches. No heading prior, no
    magnetic units (the field's links need each walk's rotation into east/north); a walk with one mark is
    tied by it once it is placed (its mark's prior in the solve). The walks left form components among
    themselves, each in a frame of its own. None when nothing ties a walk to the site frame (no walk
    marks two points apart and none registers onto the reference). Frames: site (component 0)."""
    n = len(survey)
    pc = cfg.placement
    ties = tie_arrays = None
    if control_points:
        ties = control_ties(survey, control_points, fp.offsets)
        rigid = tie_walks(ties, dr_xyh, node_sess, None).transforms  # the walks two marks place (no heading)
        sel = np.isin(ties.session, list(rigid))
        if sel.any():
            tie_arrays = (ties.session[sel], dr_xyh[ties.node[sel], :2], ties.xy[sel])
    if tie_arrays is None and reference is None:
        return None
    matches = PowerCosine.of(fp.fingerprints, pc.similarity_scale_db).top_matches(fp.session, pc.matches_per_fingerprint)
    params = GrowthParams.from_config(cfg, min_margin=cfg.heading.min_margin)  # rotation_window_deg None: all
    cp = place_units(
        n, fp.session, dr_xyh[fp.node, :2], matches, params, singleton_units(np.zeros(n)),
        rotation_sigma=np.full(n, np.inf), ties=tie_arrays,  # no rotation prior
        reference=None if reference is None else (
            reference.xy, Matches(reference.match_i, reference.match_j, reference.similarity)),
    )
    if not (cp.component == 0).any():
        return None  # no walk registers onto the reference (and none is tied)
    if ties is not None:  # the marks of the main map's walks tie them in the solve (the others stand apart)
        on = cp.component[ties.session] == 0
        ties = ControlTies(ties.session[on], ties.node[on], ties.xy[on],
                           tuple(t for t, k in zip(ties.landmark_id, on.tolist()) if k))
    ids = [s_.session_id for s_ in survey]
    comps = tuple(
        Component(k, tuple(ids[w] for w in cp.walks_of(k)), cp.reasons.get(k, "")) for k in range(cp.n_components)
    )
    # held: component 0 by the ties or the reference; every other component by its seed walk's first pose
    fixed = np.array([int(fp.offsets[sd]) for sd in cp.seeds if sd >= 0], np.int64)
    pl = Placement(
        cp.transforms, np.ones(n, bool), np.full(n, -1, np.int64), np.full(n, -1, np.int64),
        method="reference" if reference is not None else "control_points", support=cp.support, margin=cp.margin,
        consistency=cp.consistency,
    )
    log.info("site frame without headings: %d components, the main map holds %d of %d walks", cp.n_components,
             int((cp.component == 0).sum()), n)
    return ComponentSplit(pl, cp.component, comps, int(cp.walks_of(0)[0]), fixed, None, ties, "site",
                          anchors=reference)


def split_incremental(
    survey: Survey, fp: FingerprintNodes, dr_xyh: NDArray, node_sess: NDArray, cfg: GraphSlamConfig,
    control_points: Mapping[str, tuple[float, float]] | None, warm: WarmStart,
) -> ComponentSplit:
    """The heading placement of an update (``graphslam survey --update``): the walks solved before
    keep their solution and their component; each new walk is grown onto the previous components in
    order (0 first), those solved walks held as rigid bodies at their solved fingerprint positions;
    the new walks no component takes form components of their own among themselves. Only the new
    walks' fingerprints are matched (against every fingerprint), so the cost grows with what was
    added. Two previous components that a new walk would link stay apart until a full survey."""
    assert warm.component is not None
    hc, pc = cfg.heading, cfg.placement
    n_s = len(survey)
    wh = walk_headings(
        survey, sigma_floor_rad=np.radians(hc.sigma_floor_deg), cauchy_scale_rad=np.radians(hc.cauchy_scale_deg),
        correlation_steps=hc.correlation_steps,
    )
    if not wh.complete:
        missing = [survey.sessions[s].session_id for s in np.flatnonzero(~wh.available)]
        raise SolverError(f"--update with headings needs /phone/heading on every walk; {missing[0]!r} has none")
    old = warm.solved_walks(node_sess, n_s) & (warm.component >= 0)
    new = ~old
    component = np.where(old, warm.component, -1).astype(np.int64)
    # the site (or Earth) frame's rotation from east/north, as the previous solution has it: the
    # solved walks' headings against their dead reckoning turned by the phone's heading
    solved = warm.solved & old[node_sess]
    d = np.angle(np.exp(1j * (warm.xyh[solved, 2] - dr_xyh[solved, 2] - wh.rotation[node_sess[solved]])))
    phi = float(np.angle(np.exp(1j * d).mean())) if len(d) else 0.0
    rotation = wh.rotation + phi
    ties = control_ties(survey, control_points, fp.offsets) if control_points else None
    # growth positions: solved walks at their solution (transform 0), new walks turned by their heading
    pre = np.zeros((n_s, 3))
    pre[new, 2] = rotation[new]
    xy = np.where(old[fp.session][:, None], warm.xyh[fp.node, :2], se2_apply_rows(pre[fp.session], dr_xyh[fp.node, :2]))
    sim = PowerCosine.of(fp.fingerprints, pc.similarity_scale_db)
    matches = sim.top_matches(fp.session, pc.matches_per_fingerprint, rows=np.flatnonzero(new[fp.session]))
    params = GrowthParams.from_config(cfg, min_margin=hc.min_margin, rotation_window_deg=hc.rotation_window_deg)
    T_pre = np.zeros((n_s, 3))
    support, margin, consistency = (np.full(n_s, np.nan) for _ in range(3))
    margin[old] = np.inf
    n_old = int(component.max()) + 1 if old.any() else 0
    # the magnetic field: the previous links between walks solved before are kept; the new walks' links
    # are sought (anchored by their matches only), and a new walk the field links to solved walks is
    # placed by those links before WiFi is asked
    links = None
    if warm.magnetic is not None:
        links = MagneticLinks.of_pairs(*warm.magnetic)
    if cfg.magnetic.enabled and new.any() and sum(x.magnetic is not None and len(x.magnetic) > 0 for x in survey) >= 2:
        mp = MagneticParams.from_config(cfg.magnetic)
        fresh = magnetic_links(survey, fp.offsets, rotation, fp.node[matches.i], fp.node[matches.j], mp)
        fresh = fresh.subset(new[fresh.a] | new[fresh.b])
        links = fresh if links is None else links + fresh
        placed_by_field = _place_by_links(fresh, new, old, warm, dr_xyh, node_sess, rotation, component, mp.agree_m)
        for w, (T, k) in placed_by_field.items():
            component[w], T_pre[w], margin[w] = k, T, np.inf
        log.info("update: the magnetic field places %d of %d new walks", len(placed_by_field), int(new.sum()))
    for k in range(n_old):
        left = new & (component < 0)
        members = np.flatnonzero(old & (component == k))
        if not left.any() or not len(members):
            continue
        res = grow_placement(n_s, fp.session, xy, matches, params, initial={int(m): np.zeros(3) for m in members},
                             candidates=left, rotation_sigma=wh.sigma)
        got = res.placed & left
        component[got] = k
        T_pre[got] = res.transforms[got]
        support[got], margin[got], consistency[got] = res.support[got], res.margin[got], res.consistency[got]
    transforms = np.zeros((n_s, 3))
    for s in np.flatnonzero(new & (component >= 0)):
        transforms[s] = se2_compose(T_pre[s], pre[s])
    reasons: dict[int, str] = {
        k: "apart from the main map in the previous survey; no walk added since links it" for k in range(1, n_old)
    }
    seeds: dict[int, int] = {}
    left = np.flatnonzero(new & (component < 0))
    if len(left):  # the rest: components of their own, among themselves
        sub = _sub_placement(left, fp, dr_xyh, matches, params, rotation, wh.sigma)
        for c in range(sub.n_components):
            walks = left[sub.walks_of(c)]
            component[walks] = n_old + c
            transforms[walks] = sub.transforms[sub.walks_of(c)]
            seeds[n_old + c] = int(left[sub.seeds[c]]) if sub.seeds[c] >= 0 else int(walks[0])
            reasons[n_old + c] = "new walks that do not register onto a component of the previous survey"
        sel = sub.component >= 0
        support[left[sel]], margin[left[sel]], consistency[left[sel]] = sub.support[sel], sub.margin[sel], sub.consistency[sel]
    ids = [s.session_id for s in survey]
    n_comp = int(component.max()) + 1 if n_s else 0
    comps = tuple(
        Component(k, tuple(ids[s] for s in np.flatnonzero(component == k)), reasons.get(k, ""))
        for k in range(n_comp) if (component == k).any()
    )
    offsets = fp.offsets
    # one held pose per component: the first walk of an old one (its neighbourhood's border holds the
    # rest), the seed of a new one
    fixed = []
    for k in range(n_comp):
        walks = np.flatnonzero(component == k)
        if len(walks):
            fixed.append(int(offsets[seeds.get(k, int(walks[0]))]))
    target = np.asarray(wrap_angle(dr_xyh[:, 2] + rotation[node_sess]), float)
    target[~np.isfinite(target)] = np.nan
    if hc.prior == "step":
        init = np.where(warm.solved[:, None], warm.xyh, np.nan)
        for w in np.flatnonzero(new):
            a, b = int(offsets[w]), int(offsets[w + 1])
            init[a:b] = se2_apply_poses(transforms[w], dr_xyh[a:b])
        target = _step_targets(survey, offsets, init, phi)
    heading = HeadingTerms(target, wh.sigma, wh.spread, hc.prior, hc.correlation_steps)
    pl = Placement(
        transforms, np.ones(n_s, bool), np.full(n_s, -1, np.int64), np.full(n_s, -1, np.int64),
        method="heading", support=support, margin=margin, consistency=consistency,
    )
    log.info("update: %d new walks, %d joined the previous components, %d in new ones", int(new.sum()),
             int((new & (component < n_old)).sum()), len(left))
    reference = int(np.flatnonzero(component == 0)[0]) if (component == 0).any() else 0
    frame = "earth" if ties is None else "site"  # the previous survey's (its control points are these)
    return ComponentSplit(pl, component, comps, reference, np.array(fixed, np.int64), heading, ties, frame,
                          magnetic=links, site_from_earth=phi if frame == "site" else None)


def _place_by_links(
    links: MagneticLinks, new: NDArray[np.bool_], old: NDArray[np.bool_], warm: WarmStart, dr_xyh: NDArray,
    node_sess: NDArray, rotation: NDArray, component: NDArray[np.int64], agree_m: float,
) -> dict[int, tuple[NDArray, int]]:
    """New walk -> (transform in the frame of the previous solution's pre-rotation, i.e. a translation
    applied after the walk is turned by ``rotation``; component): each new walk whose magnetic pairs with
    solved walks agree on one translation within ``agree_m`` (mean), into those walks' component."""
    out: dict[int, tuple[NDArray, int]] = {}
    pn = links.pair_nodes
    for w in np.flatnonzero(new):
        mine = np.where(node_sess[pn[:, 0]] == w, 0, np.where(node_sess[pn[:, 1]] == w, 1, -1))
        sel = np.flatnonzero(mine >= 0)
        if not len(sel):
            continue
        own = pn[sel, mine[sel]]
        partner = pn[sel, 1 - mine[sel]]
        solved = old[node_sess[partner]] & warm.solved[partner]
        if solved.sum() < 3:
            continue
        own, partner = own[solved], partner[solved]
        c, s_ = np.cos(rotation[w]), np.sin(rotation[w])
        src = dr_xyh[own, :2] @ np.array([[c, s_], [-s_, c]])
        dst = warm.xyh[partner, :2]
        t = (dst - src).mean(axis=0)
        if np.linalg.norm(src + t - dst, axis=1).mean() > agree_m:
            continue
        comps, counts = np.unique(component[node_sess[partner]], return_counts=True)
        out[int(w)] = (np.array([t[0], t[1], 0.0]), int(comps[np.argmax(counts)]))
    return out


def _sub_placement(
    walks: NDArray[np.int64], fp: FingerprintNodes, dr_xyh: NDArray, matches: Matches, params: GrowthParams,
    rotation: NDArray, sigma: NDArray,
) -> ComponentPlacement:
    """``place_components`` over the given walks only (their fingerprints and the matches among them)."""
    local = np.full(int(fp.session.max()) + 1, -1, np.int64)
    local[walks] = np.arange(len(walks))
    rows = np.flatnonzero(local[fp.session] >= 0)
    row_of = np.full(len(fp), -1, np.int64)
    row_of[rows] = np.arange(len(rows))
    keep = (row_of[matches.i] >= 0) & (row_of[matches.j] >= 0)
    m = Matches(row_of[matches.i[keep]], row_of[matches.j[keep]], matches.similarity[keep])
    return place_components(len(walks), local[fp.session[rows]], dr_xyh[fp.node[rows], :2], m, params,
                            rotation=rotation[walks], rotation_sigma=sigma[walks])
