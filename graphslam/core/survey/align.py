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
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Callable, Mapping

import numpy as np
from numpy.typing import NDArray

from graphslam.config import GraphSlamConfig
from graphslam.core.progress import Task
from graphslam.core.survey import factors as F
from graphslam.core.survey import solver as S
from graphslam.core.survey import incremental
from graphslam.core.survey.association import FingerprintNodes, associate
from graphslam.core.survey.chains import expand
from graphslam.core.survey.components import Component
from graphslam.core.survey.heading_split import ComponentSplit, split_by_heading, split_incremental, split_without_headings
from graphslam.core.survey.edges import WifiEdges, propose_edges, window_thresholds
from graphslam.core.survey.graph import (
    dead_reckoned_nodes,
    describe_solver,
    gtsam_linear_solver,
    gtsam_lm,
    native_graph,
    pose_graph,
    solved_wifi_pairs,
    solved_magnetic_pairs,
    use_vectorised_solver,
    values_to_xyh,
)
from graphslam.core.survey.initialise import Placement, connected_to, register_walks, se2_apply_poses
from graphslam.core.survey.magnetic import MagneticLinks, MagneticParams, factor_pairs
from graphslam.core.survey.reference import FieldTies, field_ties, reference_links_job
from graphslam.core.survey.problem import Problem
from graphslam.core.types import PoseTrack, Survey
from graphslam.errors import SolverError

if TYPE_CHECKING:
    from graphslam.core.radiomap.magnetic_map import MagneticMap
    from graphslam.core.uwb.survey import UwbSummary

log = logging.getLogger(__name__)


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
    uwb: UwbSummary | None = None  # UWB ranges used; frame "site" when anchors fixed it
    # the walks of ``tracks`` by component; empty: every aligned walk is in component 0
    component_list: tuple[Component, ...] = ()
    # "aligned": the reference walk's first pose; "earth": east/north (x east, y north) from the
    # phones' headings, origin at the reference walk's first pose; "site": control points, UWB anchors
    # or a reference map
    frame_name: str = "aligned"
    # rad: the site frame's rotation from east/north (the headings' frame), when control points or a
    # reference map placed the main map (None: another frame, or UWB anchors)
    site_from_earth: float | None = None
    control_digest: str = ""  # ``incremental.control_points_digest`` of the control points used
    # the control points given: landmark id -> site (x, y) (pictures draw them apart from landmarks)
    control_points: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    # (E,) per WiFi edge of ``edges``: it entered the optimiser (same walks' component, the placement's
    # gate); None: every edge between aligned walks did
    used_edges: NDArray[np.bool_] | None = None
    magnetic: MagneticLinks | None = None  # the magnetic links the placement used (their pairs: factors)
    magnetic_pairs: NDArray[np.int64] | None = None  # (P, 2) step nodes of the magnetic factors solved
    ties: ControlTies | None = None  # control-point marks tied to the site frame
    reference_map: RadioMap | None = None  # the surveyed map component 0 is placed on (site frame)
    anchor_pairs: NDArray[np.int64] | None = None  # (E, 2) its WiFi edges: (step node, reference fingerprint)
    field_ties: FieldTies | None = None  # the reference's field: its samples and the crowd's magnetic factors to them
    unused_reference: RadioMap | None = None  # a reference map given that no walk registers onto
    # WiFi and reference edges that joined after a solve brought them within the tight gate (``_regated``)
    regated_edges: tuple[int, int] = (0, 0)
    # the optimiser that solved it (the last LM call's way): the vectorised LM's {"solver": "cholmod",
    # "linear_solver": "cholesky", "ordering": "metis" | "amd"} or {..., "linear_solver": "pcg",
    # "preconditioner": "spanning tree"} (``FactorInfo.as_dict``),
    # {"solver": "gtsam", "linear_solver": "cholesky" | "pcg"} for GTSAM's; empty: nothing was optimised
    solver: dict[str, str] = field(default_factory=dict)

    def links_by_component(self) -> list[dict[str, int]]:
        """Per component (0 first): what links its walks, by kind — WiFi edges and magnetic links
        (walk pairs) in the optimiser, UWB ranges, control-point marks, WiFi edges to a reference map and
        magnetic factors to its field."""
        comp = self.component_of()
        ids = self.session_ids
        walk_comp = np.array([comp.get(sid, -1) for sid in ids], np.int64)
        n = len(self.components)
        out = [{"wifi": 0, "magnetic": 0, "uwb": 0, "control_points": 0, "reference": 0, "reference_magnetic": 0}
               for _ in range(n)]
        fp = self.fingerprints
        if len(self.edges):
            used = np.ones(len(self.edges), bool) if self.used_edges is None else self.used_edges
            ca, cb = walk_comp[fp.session[self.edges.i]], walk_comp[fp.session[self.edges.j]]
            for k, c in zip(*np.unique(ca[used & (ca == cb) & (ca >= 0)], return_counts=True)):
                out[int(k)]["wifi"] = int(c)
        if self.magnetic is not None and len(self.magnetic):
            ca, cb = walk_comp[self.magnetic.a], walk_comp[self.magnetic.b]
            for k, c in zip(*np.unique(ca[(ca == cb) & (ca >= 0)], return_counts=True)):
                out[int(k)]["magnetic"] = int(c)
        if self.ties is not None and len(self.ties):
            ct = walk_comp[self.ties.session]
            for k, c in zip(*np.unique(ct[ct >= 0], return_counts=True)):
                out[int(k)]["control_points"] = int(c)
        if self.anchor_pairs is not None and len(self.anchor_pairs) and n:  # the reference holds component 0
            out[0]["reference"] = int(len(self.anchor_pairs))
        if self.field_ties is not None and n:  # magnetic factors to the reference's field (component 0's)
            out[0]["reference_magnetic"] = int(len(self.field_ties))
        if self.uwb is not None and n:  # UWB surveys are one component
            out[0]["uwb"] = int(self.uwb.anchor_ranges + self.uwb.peer_ranges)
        return out

    @property
    def frame(self) -> str:
        """Frame of component 0: "site" (control points, UWB anchors or a reference map), "earth" (east/north, from
        the phones' headings) or "aligned" (the reference walk's first pose)."""
        if self.uwb is not None and self.uwb.frame == "site":
            return "site"
        return self.frame_name

    @property
    def components(self) -> tuple[Component, ...]:
        """Components in order (0 first); one component of every aligned walk when none were formed."""
        if self.component_list:
            return self.component_list
        return (Component(0, tuple(self.tracks)),) if self.tracks else ()

    def component_of(self) -> dict[str, int]:
        """session id -> component index, for every walk in ``tracks``."""
        return {sid: c.index for c in self.components for sid in c.walks}

    def main_tracks(self) -> dict[str, PoseTrack]:
        """The walks of component 0 (the radio map's)."""
        main = set(self.components[0].walks) if self.components else set()
        return {sid: t for sid, t in self.tracks.items() if sid in main}

    @property
    def n_nodes(self) -> int:
        return len(self.node_xyh)

    def fingerprint_xy(self) -> NDArray[np.float64]:
        """Optimised position of every fingerprint (NaN where its walk is unaligned)."""
        return self.node_xyh[self.fingerprints.node, :2]


def _reference_index(survey: Survey, cfg: GraphSlamConfig) -> int:
    ref = cfg.optimizer.reference_session
    if ref is None:
        return 0
    ids = [s.session_id for s in survey]
    if ref not in ids:
        raise SolverError(f"reference session {ref!r} is not in the survey (have e.g. {ids[:3]})")
    return ids.index(ref)


def _transform_poses(xyh: NDArray, T: NDArray) -> NDArray:
    return se2_apply_poses(T, xyh)


def initialization(cfg: GraphSlamConfig, survey: Survey | None = None) -> str:
    """``optimizer.initialization`` resolved: auto takes ``heading`` when every walk has the phone's
    heading (and ``heading.enabled``) and none ranges by UWB, else ``registration``; --update (a warm
    start) keeps its own."""
    method = cfg.optimizer.initialization
    if method != "auto":
        return method
    if survey is None or not cfg.heading.enabled or not len(survey):
        return "registration"
    if cfg.uwb.enabled and any(s.uwb_ranges is not None and len(s.uwb_ranges) for s in survey):
        return "registration"  # UWB ranges place and link the walks themselves (graphslam.core.uwb.survey)
    if all(s.heading is not None and len(s.heading) >= 3 for s in survey):
        return "heading"
    return "registration"


def _saturation_radii(cfg: GraphSlamConfig, method: str = "registration") -> list[float]:
    """Graduated saturation: start wide (far-off starts still attract), end at d_max (the paper).

    From the origin start the first stage has no saturation at all; from a registration
    start the radius shrinks geometrically from 2 d_max to d_max.
    """
    n = cfg.optimizer.outer_iterations
    d_max = cfg.wifi.d_max_m
    if n == 1:
        return [d_max]
    if method == "origin":
        return [float("inf")] + [float(r) for r in np.geomspace(4.0 * d_max, d_max, n - 1)]
    return [float(r) for r in np.geomspace(2.0 * d_max, d_max, n)]


def edge_candidates(cfg: GraphSlamConfig, n_fingerprints: int) -> str:
    """``edges.candidates`` resolved: auto takes the IVF index above ``edges.ivf_above_fingerprints``."""
    c = cfg.edges.candidates
    if c == "auto":
        return "ivf" if n_fingerprints > cfg.edges.ivf_above_fingerprints else "exact"
    return c


def build_problem(
    survey: Survey,
    cfg: GraphSlamConfig,
    warm: incremental.WarmStart | None = None,
    *,
    control_points: Mapping[str, tuple[float, float]] | None = None,
    reference: RadioMap | None = None,
    reference_field: MagneticMap | None = None,
) -> Problem:
    """Steps 1-3 of the method: fingerprints on nodes, WiFi edges, initial placement.

    ``control_points``: landmark id -> site (x, y) of the landmarks a user names as control
    points (``graphslam survey --control-points``): the walks that mark them are tied there and
    component 0 is in the site frame (``graphslam.core.survey.control``; without the headings a walk is tied by
    two marks, ``split_without_headings``).
    ``reference``: a surveyed radio map in the site frame, held; component 0 is placed on it and tied to
    it by WiFi edges (``graphslam.core.survey.reference``; walks without the phones' headings are
    registered onto it over every rotation, ``split_without_headings``). ``reference_field``: the
    reference's magnetic field (a previous survey's magnetic map, site frame): component 0's walks are tied
    to it by magnetic factors once placed (``graphslam.core.survey.reference.field_ties``).

    ``warm`` (``graphslam survey --update``, see ``graphslam.core.survey.incremental``): walks
    solved before start from their previous solution, only the new walks' fingerprints are
    compared, the new walks are registered to the solved ones, and ``Problem.free`` marks the
    neighbourhood that ``solve`` re-solves."""
    if len(survey) == 0:
        raise SolverError("survey has no sessions")
    timings: dict[str, float] = {}
    t = time.perf_counter()
    task = Task("associate")
    fp = associate(
        survey,
        max_gap_s=cfg.fingerprint.max_scan_step_gap_s,
        missing_dbm=cfg.fingerprint.missing_rssi_dbm,
        min_rssi_dbm=cfg.fingerprint.min_rssi_dbm,
        standstill_max_s=cfg.fingerprint.standstill_max_s,
    )
    timings["associate"] = time.perf_counter() - t
    task.end()

    ranged = cfg.uwb.enabled and any(s.uwb_ranges is not None and len(s.uwb_ranges) for s in survey)
    if reference is not None and warm is not None:
        raise SolverError("a reference map needs a full survey (no --update): a survey on one is solved in full")
    if (reference is not None or (control_points and warm is None)) and ranged:
        raise SolverError(f"{'a reference map' if reference is not None else 'control points'} and UWB ranges do not "
                          "go together: the ranges place the walks themselves (set uwb.enabled false to use "
                          f"{'it' if reference is not None else 'them'})")

    t = time.perf_counter()
    thr = window_thresholds(fp, cfg.edges.window_steps)
    # the crowd's ties to a reference map: on a thread beside the crowd's own edges where its products are large
    links = None if reference is None else reference_links_job(
        fp.fingerprints, thr, reference, matches_per_fingerprint=cfg.placement.matches_per_fingerprint,
        scale_db=cfg.placement.similarity_scale_db, max_per_fingerprint=cfg.edges.max_per_fingerprint,
        min_common_aps=cfg.edges.min_common_aps,
    )
    if warm is not None:  # --update: the same edges, computed from the new walks' rows only
        edges = incremental.update_edges(fp, thr, warm, cfg.edges)
    else:
        edges = propose_edges(
            fp,
            thr,
            exclude_same_session_s=cfg.edges.exclude_same_session_s,
            exclude_same_session_m=cfg.edges.exclude_same_session_m,
            max_per_fingerprint=cfg.edges.max_per_fingerprint,
            min_common_aps=cfg.edges.min_common_aps,
            block_rows=cfg.edges.chunk_rows,
            candidates=edge_candidates(cfg, len(fp)),
            ivf_neighbours=cfg.edges.ivf_neighbours,
            ivf_probes=cfg.edges.ivf_probes,
        )
    timings["edges"] = time.perf_counter() - t
    log.info("%d fingerprints on %d steps, %d WiFi edges", len(fp), fp.offsets[-1], len(edges))

    t = time.perf_counter()
    task = Task("initialise")
    dr_xyh, node_sess = dead_reckoned_nodes(survey)
    ref = _reference_index(survey, cfg)
    n_s = len(survey)
    ea, eb = fp.node[edges.i], fp.node[edges.j]
    placement = None
    unaligned: dict[str, str] = {}
    method = initialization(cfg, survey)
    if warm is not None and (method != "heading" or warm.component is None):
        method = "registration"  # an update without headings: new walks registered to the solved ones
    split: ComponentSplit | None = None
    anchors = None
    unused: RadioMap | None = None  # a reference map given that no walk registers onto (walks without headings)
    if links is not None:
        anchors = links.result()
        # the offset found travels with the reference: report.json and the radio map say it
        reference = reference.with_metadata(rss_offset_db=round(anchors.rss_offset_db, 2))
    if warm is None and method != "heading" and (reference is not None or control_points):
        # no headings: walks tied rigidly by two marks, the others registered over every rotation
        split = split_without_headings(survey, fp, dr_xyh, node_sess, cfg, control_points, anchors)
        if split is None and control_points:
            raise SolverError(
                "control points without the phones' headings need a walk that marks two of them at least 5 m apart"
                + (" or registers onto the reference map" if reference is not None else "")
                + f" (this survey resolves to optimizer.initialization {method!r})"
            )
        if split is None:
            unused, reference, anchors = reference, None, None
        else:
            method = split.placement.method
    if split is not None:  # placed in the site frame without headings (above)
        placement, transforms = split.placement, split.placement.transforms
        included = np.ones(n_s, bool)
        ref = split.reference
    elif warm is not None and method == "registration":  # --update: new walks registered to the solved ones
        placement = incremental.place_new_walks(warm, n_s, node_sess, dr_xyh[:, :2], ea, eb)
        included = placement.placed.copy()
        transforms = placement.transforms
        for s in np.flatnonzero(~included):
            unaligned[survey.sessions[s].session_id] = "no rigid WiFi registration chain to the walks solved before"
        if placement.reliable is False and cfg.optimizer.unreliable_registration == "unalign":
            for s in np.flatnonzero(included & ~warm.solved_walks(node_sess, n_s)):
                unaligned[survey.sessions[s].session_id] = (
                    f"registration unreliable: {placement.loops_consistent} of {placement.loops} loops "
                    "between the walks placed anew are consistent"
                )
                included[s] = False
    elif method == "heading" and warm is not None:  # --update: new walks onto the previous components
        split = split_incremental(survey, fp, dr_xyh, node_sess, cfg, control_points, warm)
        placement, transforms = split.placement, split.placement.transforms
        included = np.ones(n_s, bool)
        ref = split.reference
    elif method == "heading":
        seed = _reference_index(survey, cfg) if cfg.optimizer.reference_session is not None else None
        split = split_by_heading(survey, fp, dr_xyh, node_sess, cfg, control_points, seed=seed, reference=anchors)
        placement, transforms = split.placement, split.placement.transforms
        included = np.ones(n_s, bool)
        ref = split.reference
    elif method == "registration":
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
    elif method == "growth":
        placement = _grow(survey, fp, dr_xyh, cfg)
        if cfg.optimizer.reference_session is None:
            ref = int(np.flatnonzero(placement.parent == -2)[0])  # the seed walk defines the frame
        included = placement.placed.copy()
        transforms = placement.transforms
        for s, why in placement_reasons(placement, survey).items():
            unaligned[s] = why
    else:
        transforms = np.zeros((n_s, 3))
        included = connected_to(n_s, node_sess[ea], node_sess[eb], ref)
        for s in np.flatnonzero(~included):
            unaligned[survey.sessions[s].session_id] = "no WiFi edge path to the reference walk"
    # --- UWB hook (graphslam.core.uwb.survey): range factors; with anchors the site
    # frame, the inclusion and the placement come from the ranges
    uwb = None
    if cfg.uwb.enabled and any(s.uwb_ranges is not None and len(s.uwb_ranges) for s in survey):
        from graphslam.core.uwb.survey import uwb_terms  # the UWB modules: for surveys with ranges only

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
    if warm is not None:  # --update: solved walks start from their solution; only their neighbourhood moves
        init_xyh = np.where(warm.solved[:, None], warm.xyh, init_xyh)
    use = included[node_sess[ea]] & included[node_sess[eb]]
    if split is not None:  # no WiFi edge between components: nothing the placement trusted links them
        use &= split.component[node_sess[ea]] == split.component[node_sess[eb]]
    wifi_pairs = np.column_stack([ea[use], eb[use]]).astype(np.int64)
    gated_wifi = np.zeros((0, 2), np.int64)  # see Problem.gated_wifi_pairs
    if split is not None:  # ... and within one, only edges the placement agrees with
        gap = np.linalg.norm(init_xyh[wifi_pairs[:, 0], :2] - init_xyh[wifi_pairs[:, 1], :2], axis=1)
        gate = np.full(len(gap), cfg.heading.wifi_gate_m)
        if split.ties is not None or split.anchors is not None:
            # the component the control points or the reference map place: tighter (they place its walks)
            tied = split.component[node_sess[wifi_pairs[:, 0]]] == 0
            gate[tied] = min(cfg.heading.wifi_gate_m, cfg.control_points.wifi_gate_m)
        keep = gap <= gate
        # only the tight gate dropped them (an update keeps the previous solve's choice: none)
        gated = ~keep & (gap <= cfg.heading.wifi_gate_m) & (warm is None)
        if warm is not None and warm.prev_edge_used is not None:
            # between walks solved before, the previous graph's choice (its gate saw the placement
            # then; the solution now would drop other edges and move the whole floor)
            old_walk = warm.solved_walks(node_sess, n_s)
            both_old = old_walk[node_sess[wifi_pairs[:, 0]]] & old_walk[node_sess[wifi_pairs[:, 1]]]
            prev = fp.node[incremental.previous_edge_rows(fp, warm)]
            keep[both_old] = incremental.pairs_in(wifi_pairs[both_old], prev[warm.prev_edge_used], len(init_xyh))
        gated_wifi = wifi_pairs[gated]  # empty unless the tight gate applied (ties or a reference)
        wifi_pairs = wifi_pairs[keep]
    anchor_xy, anchor_pairs = np.zeros((0, 2)), np.zeros((0, 2), np.int64)
    gated_anchor = np.zeros((0, 2), np.int64)
    if split is not None and split.anchors is not None:
        # the reference's WiFi edges to component 0's walks that the placement puts within the gate
        a = split.anchors
        node = fp.node[a.edge_i]
        on = split.component[node_sess[node]] == 0
        gap = np.linalg.norm(init_xyh[node, :2] - a.xy[a.edge_j], axis=1)
        keep = on & (gap <= min(cfg.heading.wifi_gate_m, cfg.control_points.wifi_gate_m))
        anchor_xy, anchor_pairs = a.xy, np.column_stack([node[keep], a.edge_j[keep]]).astype(np.int64)
        if warm is None:
            gated_a = on & ~keep & (gap <= cfg.heading.wifi_gate_m)
            gated_anchor = np.column_stack([node[gated_a], a.edge_j[gated_a]]).astype(np.int64)
    field_pairs, ties_to_field = np.zeros((0, 2), np.int64), None
    if split is not None and split.anchors is not None and reference_field is not None and cfg.magnetic.enabled:
        ties_to_field = field_ties(
            survey, fp.offsets, transforms, split.component == 0, reference_field, MagneticParams.from_config(cfg.magnetic),
            dr_xy=dr_xyh[:, :2], node_walk=node_sess, max_offset_m=cfg.magnetic.d_max_m,
            per_place=cfg.magnetic.partners_per_place,
        )
        # the field's samples are held nodes after the reference's fingerprints
        field_pairs = ties_to_field.pairs + np.array([0, len(anchor_xy)])
        anchor_xy = np.concatenate([anchor_xy, ties_to_field.xy])
    magnetic_pairs = np.zeros((0, 2), np.int64)
    if split is not None and split.magnetic is not None and len(split.magnetic):
        mag = split.magnetic
        pn = mag.pair_nodes
        keep = split.component[node_sess[pn[:, 0]]] == split.component[node_sess[pn[:, 1]]]
        keep &= factor_pairs(mag, dr_xyh[:, :2], node_sess, cfg.magnetic.pair_every_m, cfg.magnetic.partners_per_place)
        magnetic_pairs = pn[keep]
    free = None
    if warm is not None:
        free = incremental.free_nodes(
            warm, fp.offsets, included, wifi_pairs, incremental.previous_graph_pairs(fp, warm), int(fp.offsets[ref]),
            compressed=cfg.optimizer.compress_chains,
        )
    timings["initialise"] = time.perf_counter() - t
    task.end()
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
        wifi_pairs=wifi_pairs,
        timings_s=timings,
        magnetic_pairs=magnetic_pairs,
        magnetic=None if split is None else split.magnetic,
        anchor_xy=anchor_xy,
        anchor_pairs=anchor_pairs,
        field_pairs=field_pairs,
        field_ties=ties_to_field,
        gated_wifi_pairs=gated_wifi.reshape(-1, 2),
        gated_anchor_pairs=gated_anchor,
        reference_map=reference if split is not None and split.anchors is not None else None,
        unused_reference=unused if unused is not None else reference if split is not None and split.unused_reference else None,
        free=free,
        uwb=uwb,
        method=method,
        component=None if split is None else split.component,
        components=() if split is None else split.components,
        fixed_nodes=None if split is None else split.fixed_nodes,
        heading=None if split is None else split.heading,
        ties=None if split is None else split.ties,
        frame_name="aligned" if split is None else split.frame_name,
        site_from_earth=None if split is None else split.site_from_earth,
        control_digest=incremental.control_points_digest(control_points),
        control_points=dict(control_points or {}),
    )


def _grow(survey: Survey, fp: FingerprintNodes, dr_xyh: NDArray, cfg: GraphSlamConfig) -> Placement:
    """Map-growth placement (graphslam.core.survey.placement) as a ``Placement``; the seed walk
    (the configured reference, else the one with the most match weight) has ``parent == -2``."""
    # imported here: scipy.ndimage etc. only for surveys that use this placement
    from graphslam.core.radiomap.similarity import PowerCosine
    from graphslam.core.survey.placement import GrowthParams, grow_placement

    pc = cfg.placement
    sim = PowerCosine.of(fp.fingerprints, pc.similarity_scale_db)
    matches = sim.top_matches(fp.session, pc.matches_per_fingerprint)
    params = GrowthParams.from_config(cfg)
    seed = _reference_index(survey, cfg) if cfg.optimizer.reference_session is not None else None
    res = grow_placement(len(survey), fp.session, dr_xyh[fp.node, :2], matches, params, seed=seed)
    parent = np.full(len(survey), -1, np.int64)
    parent[res.seed] = -2
    return Placement(
        res.transforms, res.placed, np.full(len(survey), -1, np.int64), parent,
        method="growth", support=res.support, margin=res.margin, consistency=res.consistency,
        unplaced_reasons=res.reasons,
    )


def placement_reasons(placement: Placement, survey: Survey) -> dict[str, str]:
    """session id -> why the placement left the walk out."""
    reasons = placement.unplaced_reasons or {}
    return {survey.sessions[s].session_id: reasons.get(int(s), "not placed") for s in np.flatnonzero(~placement.placed)}


def align(
    survey: Survey,
    config: GraphSlamConfig | None = None,
    progress: ProgressCallback | None = None,
    warm: incremental.WarmStart | None = None,
    *,
    control_points: Mapping[str, tuple[float, float]] | None = None,
    reference: RadioMap | None = None,
    reference_field: MagneticMap | None = None,
) -> Alignment:
    """Align all walks of ``survey`` into the frame of the reference walk's first pose
    (``warm``: re-solve only around the walks new since a previous solution, see ``build_problem``;
    ``control_points``: landmark id -> site (x, y); ``reference``: a surveyed radio map in the site
    frame, ``reference_field`` its magnetic field; passed on to ``build_problem``)."""
    cfg = config or GraphSlamConfig()
    t0 = time.perf_counter()
    problem = build_problem(survey, cfg, warm, control_points=control_points, reference=reference,
                            reference_field=reference_field)
    return solve(problem, cfg, progress, t0=t0)


# passes of re-gating after the first solve (``solve``); on the simulator and IPIN the second adds little
_REGATE_ROUNDS = 2
# LM iterations of a re-gating pass that another pass follows: its solution only chooses which gated edges
# join next (metres against a 3-m gate), the last pass converges (paper size 12: the first pass's 3rd and
# 4th iterations moved the error by 4e-4 and 6e-6 of itself)
_REGATE_PASS_ITERATIONS = 2


def _regated(problem: Problem, xyh: NDArray, cfg: GraphSlamConfig) -> Problem | None:
    """``problem`` with the gated edges that ``xyh`` (a solution) puts within the tight gate joined to its
    WiFi and reference edges, from ``xyh``; None when none does. The placement of a walk tied at one place
    is rigid and its dead reckoning drifts: far from the tie, right edges can lie beyond the gate until a
    solve bends the walk; wrong ones stay beyond it."""
    gate = min(cfg.heading.wifi_gate_m, cfg.control_points.wifi_gate_m)
    gw, ga = problem.gated_wifi_pairs, problem.gated_anchor_pairs
    near_w = np.linalg.norm(xyh[gw[:, 0], :2] - xyh[gw[:, 1], :2], axis=1) <= gate
    near_a = np.linalg.norm(xyh[ga[:, 0], :2] - problem.anchor_xy[ga[:, 1]], axis=1) <= gate
    if not (near_w.any() or near_a.any()):
        return None
    log.info("re-gating: %d WiFi and %d reference edges join after the solve", int(near_w.sum()), int(near_a.sum()))
    return replace(
        problem,
        init_xyh=xyh,
        wifi_pairs=np.concatenate([problem.wifi_pairs, gw[near_w]]),
        anchor_pairs=np.concatenate([problem.anchor_pairs, ga[near_a]]),
        gated_wifi_pairs=gw[~near_w],
        gated_anchor_pairs=ga[~near_a],
    )


def solve(
    problem: Problem, cfg: GraphSlamConfig, progress: ProgressCallback | None = None, *, t0: float | None = None
) -> Alignment:
    """Step 5: LM over a shrinking set of unsaturated WiFi edges (graduated saturation); then, where control
    points or a reference map place component 0, the edges its placement had put beyond the tight gate
    join once a solve brings them within it (``_regated``), and LM runs again on the wider graph (the
    first solve then stops before the final radius: at it, the narrower graph's solution would be
    replaced at once; paper size 12 with a reference, 13 -> 10 iterations)."""
    t0 = time.perf_counter() if t0 is None else t0
    timings = dict(problem.timings_s)
    t = time.perf_counter()
    placed_xyh = problem.init_xyh  # the placement (the output's initial poses, whatever the passes)
    dr_xyh = dead_reckoned_nodes(problem.survey)[0]
    n_steps = len(problem.init_xyh)
    vectorised = use_vectorised_solver(cfg, problem)
    settings = S.LMSettings(
        max_iterations=cfg.optimizer.max_iterations,
        relative_error_tol=cfg.optimizer.relative_error_tol,
        absolute_error_tol=cfg.optimizer.absolute_error_tol,
        shape_tol_m=cfg.optimizer.shape_tol_m,
        ordering=cfg.optimizer.ordering,
        metis_above_variables=cfg.optimizer.metis_above_variables,
        linear_solver=cfg.optimizer.linear_solver,
        pcg_above_variables=cfg.optimizer.pcg_above_variables,
    )

    def build(pb: Problem) -> tuple:
        """The graph of ``pb`` and its range factors' end nodes: WiFi (ea, eb), magnetic (ma, mb), reference (ra, rb)."""
        with Task("build graph"):
            if vectorised:
                pg, chains = pose_graph(pb, cfg)
                native = None
            else:
                if len(pb.anchor_pairs) or len(pb.field_pairs):
                    raise SolverError("a reference map is solved by graphslam's own LM (optimizer.solver auto "
                                      "or cholmod), not optimizer.solver gtsam")
                pg = None
                imu_graph, wifi_factors, values, chains = native_graph(pb, cfg)
                native = (imu_graph, wifi_factors, values)
        wp = pb.wifi_pairs if vectorised else solved_wifi_pairs(pb)
        mp = pb.magnetic_pairs if vectorised else solved_magnetic_pairs(pb)
        # a reference map's fingerprints and its field's samples: held nodes after the steps (node N + r), WiFi
        # edges and magnetic factors to them
        return (pg, chains, native, wp[:, 0], wp[:, 1], mp[:, 0], mp[:, 1],
                pb.anchor_pairs[:, 0], n_steps + pb.anchor_pairs[:, 1], pb.field_pairs[:, 0], n_steps + pb.field_pairs[:, 1])

    pg, chains, native, ea, eb, ma, mb, ra, rb, fa, fb = build(problem)
    perm = S.graph_ordering(pg, settings) if vectorised else None  # CHOLMOD's, one per graph
    anchors = np.column_stack([problem.anchor_xy, np.zeros(len(problem.anchor_xy))])
    timings["build_graph"] = time.perf_counter() - t

    t = time.perf_counter()
    task = Task("optimise", unit="iterations")
    records: list[IterationRecord] = []
    snapshots: list[tuple[int, NDArray]] = []

    def objective(xyh: NDArray) -> float:
        d = np.linalg.norm(xyh[ea, :2] - xyh[eb, :2], axis=1)
        imu = S.between_error(pg, xyh) + S.unary_error(pg, xyh) if vectorised else native[0].error(values)
        dm = np.linalg.norm(xyh[ma, :2] - xyh[mb, :2], axis=1)
        dr = np.linalg.norm(xyh[ra, :2] - anchors[rb - n_steps, :2], axis=1)
        df = np.linalg.norm(xyh[fa, :2] - anchors[fb - n_steps, :2], axis=1)
        return float(imu + F.fuzzy_cost(d, cfg.wifi).sum() + F.magnetic_cost(dm, cfg.magnetic).sum()
                     + F.fuzzy_cost(dr, cfg.wifi).sum() + F.magnetic_cost(df, cfg.magnetic).sum())

    xyh = problem.init_xyh.copy()
    values = native[2] if native is not None else None
    initial_error = objective(xyh)
    converged = False
    solver: dict[str, str] = {}
    prev_active: NDArray | None = None
    all_radii = _saturation_radii(cfg, problem.method)
    # edges a placement put beyond the gate: the first round stops before the final radius, which the
    # re-gated graph's passes run (a converged final stage on the narrower graph would be re-solved at once)
    final_pending = len(all_radii) > 1 and bool(len(problem.gated_wifi_pairs) or len(problem.gated_anchor_pairs))
    radii = all_radii[:-1] if final_pending else all_radii
    stage = 0
    regated = (0, 0)
    capped = False  # the last LM call stopped at _REGATE_PASS_ITERATIONS
    for regate_round in range(1 + _REGATE_ROUNDS + 1):  # the last: only to finish a capped pass
        lm = settings
        if regate_round:  # the edges this solution brings within the gate join; LM again at the final radius
            wider = _regated(problem, xyh, cfg) if regate_round <= _REGATE_ROUNDS else None
            if wider is None and not capped and not final_pending:
                break
            if wider is not None:
                regated = (regated[0] + len(wider.wifi_pairs) - len(problem.wifi_pairs),
                           regated[1] + len(wider.anchor_pairs) - len(problem.anchor_pairs))
                problem = wider
                pg, chains, native, ea, eb, ma, mb, ra, rb, fa, fb = build(problem)
                perm = S.graph_ordering(pg, settings) if vectorised else None
                values = native[2] if native is not None else None
                if regate_round < _REGATE_ROUNDS:  # another pass follows: a few iterations choose its edges
                    lm = replace(settings, max_iterations=min(settings.max_iterations, _REGATE_PASS_ITERATIONS))
            # else: nothing more joins the capped pass's graph (or the final radius is still to run): LM finishes it
            radii, prev_active, final_pending = all_radii[-1:], None, False
        for radius in radii:
            this_stage, stage = stage, stage + 1  # a skipped stage keeps its number
            d = np.linalg.norm(xyh[ea, :2] - xyh[eb, :2], axis=1)
            dm = np.linalg.norm(xyh[ma, :2] - xyh[mb, :2], axis=1)
            dr = np.linalg.norm(xyh[ra, :2] - anchors[rb - n_steps, :2], axis=1)
            df = np.linalg.norm(xyh[fa, :2] - anchors[fb - n_steps, :2], axis=1)
            # magnetic pairs saturate at their own d_max, shrinking in step with the WiFi edges' radius
            mag_radius = radius * cfg.magnetic.d_max_m / cfg.wifi.d_max_m
            active = np.concatenate([d <= radius, dm <= mag_radius, dr <= radius, df <= mag_radius])
            if prev_active is not None and np.array_equal(active, prev_active) and converged:
                continue  # LM already converged on exactly this graph
            n_active = int(active[:len(d)].sum())  # WiFi edges (the records' and the progress line's count)

            def hook(it: int, before: float, after: float, _s: int = this_stage, _n: int = n_active) -> None:
                rec = IterationRecord(_s, int(it), float(before), float(after), _n)
                records.append(rec)
                task.advance(info=f"stage {_s}, error {after:.4g}, {_n:,} WiFi edges")
                if progress is not None:
                    progress(rec)

            if vectorised:
                res = S.levenberg_marquardt(pg, np.concatenate([xyh, anchors]), active, lm, hook, perm=perm)
                converged = res.converged
                capped = lm is not settings and not converged and res.iterations >= lm.max_iterations
                xyh = res.xyh[:n_steps]
                if res.factor is not None:
                    solver = res.factor.as_dict()
            else:
                values, converged = gtsam_lm(native[0], native[1], values, active, cfg, hook)
                xyh = values_to_xyh(values, problem.init_xyh)
                solver = {"solver": "gtsam", "linear_solver": gtsam_linear_solver(cfg, values.size())}
            if chains is not None:
                xyh = expand(xyh, dr_xyh, chains)
            if problem.free is not None:  # --update: outside the neighbourhood, the previous solution
                xyh = np.where(problem.free[:, None], xyh, problem.init_xyh)
            snapshots.append((this_stage, xyh.copy()))
            prev_active = active
    timings["optimise"] = time.perf_counter() - t
    task.end()
    if solver:
        log.info("optimised with %s", describe_solver(solver))
    init_xyh = placed_xyh
    if vectorised and problem.init_xyh is not placed_xyh:  # the wider graph's error at the placement, comparable
        initial_error = objective(placed_xyh)
    final_error = objective(xyh)

    d = np.linalg.norm(xyh[problem.wifi_pairs[:, 0], :2] - xyh[problem.wifi_pairs[:, 1], :2], axis=1)
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
        component_list=problem.components,
        frame_name=problem.frame_name,
        site_from_earth=problem.site_from_earth,
        control_digest=problem.control_digest,
        control_points=problem.control_points,
        solver=solver,
        used_edges=incremental.pairs_in(
            np.column_stack([fp.node[problem.edges.i], fp.node[problem.edges.j]]), problem.wifi_pairs, len(xyh)
        ),
        magnetic=problem.magnetic,
        magnetic_pairs=problem.magnetic_pairs,
        ties=problem.ties,
        reference_map=problem.reference_map,
        anchor_pairs=problem.anchor_pairs if problem.reference_map is not None else None,
        field_ties=problem.field_ties if problem.reference_map is not None else None,
        unused_reference=problem.unused_reference,
        regated_edges=regated,
    )
