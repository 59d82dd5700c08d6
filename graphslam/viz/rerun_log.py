"""Rerun recordings of surveys, for visual inspection. The only module that imports ``rerun``.

``log_survey`` writes one ``.rrd`` file (atomically: a temporary file beside the target,
renamed once the footer is written) with a default blueprint. Entity tree (see
docs/rerun.md for what each shows)::

    /world                                   display root: y flipped (Rerun's 2D views draw y down)
    /world/floor_plan                        floor plan image, spans x in [0, W], y in [0, H] (site frame)
    /world/landmarks/{truth,estimate,error}  landmark marks (site frame), estimate after the SE(2) fit
    /world/aligned                           the aligned (reference-walk) frame; its transform is the
                                             fitted site-from-aligned SE(2) when landmarks allow one
    /world/aligned/trajectories/<session>    aligned walks, one colour per session
    /world/aligned/reference_pose            the fixed reference pose (first pose of the reference walk)
    /world/aligned/wifi_edges/{inactive,ramp,saturated}   WiFi-vicinity edges by final state
    /world/aligned/radio_map/fingerprints    fingerprint positions
    /world/aligned/radio_map/ap/<rank>_<bssid>            RSSI of the most-heard APs (colour-mapped)
    /world/aligned/radio_map/heatmap/<rank>_<bssid>       their RSS heatmaps (image), uncertain cells faded
    /world/aligned/magnetic_map/{magnitude,vertical}      the main map's field per step (colour-mapped, µT)
    /world/aligned/magnetic_pairs            the magnetic factors: step pairs a magnetic link says are one place
    /world/aligned/reference_field           a reference's field: its samples the crowd is tied to, and the factors
    /world/aligned/convergence/<session>     walks at the initial guess and after each LM stage (timed)
    /world/aligned/locate/estimate, /world/locate/{truth,error}   kNN answers (``log_locate_results``)
    /raw/<session>                           each walk in its own dead-reckoning frame, laid on a grid
    /optimizer/{error,log10_error,active_edges,stage}     one row per LM iteration (timeline lm_iteration)
    /info/notes                              text: counts, frames used, colour legends

Static data is logged once as static; every entity is one ``log`` (or one ``send_columns``)
with all its points, never one call per point.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Mapping, Sequence
from uuid import uuid4

import numpy as np
from numpy.typing import NDArray

from graphslam.config import GraphSlamConfig
from graphslam.core.survey.align import Alignment, IterationRecord
from graphslam.core.survey.factors import edge_state
from graphslam.core.radiomap.field import readings_field
from graphslam.core.radiomap.magnetic_map import MagneticMap
from graphslam.core.survey.radio_maps import held_reference, reference_label
from graphslam.core.radiomap.fingerprints import DEFAULT_MIN_RSSI_DBM, FingerprintMatrix
from graphslam.core.common.geometry import se2_apply
from graphslam.core.types import PoseTrack, Survey
from graphslam.errors import ConfigError, GraphSlamError, VisualizationError, require_extra
from graphslam.names import FRAME_DESCRIPTIONS
from graphslam.io.heatmap import MAX_STD_ERROR_DB, heatmap_rgba
from graphslam.viz.common import (
    FloorPlan, landmark_marks, load_floor_plan, session_colours, survey_folder_tracks, top_access_points,
)

rr = require_extra("rerun", "Rerun recordings (--rerun, graphslam view)")
import rerun.blueprint as rrb  # noqa: E402 (rerun is there: the line above)

log = logging.getLogger(__name__)

APP_ID = "graphslam"
TIMELINE_ITERATION = "lm_iteration"  # 0 = initial guess, k = after the k-th LM iteration (all stages)
TIMELINE_STAGE = "lm_stage"  # 0 = initial guess, s + 1 = after LM stage s
MAX_EDGES = 20_000  # more WiFi edges than this are subsampled (deterministically) for display
TOP_APS = 10
MAX_RAW_LABELS = 24  # more walks than this: raw-walk labels on hover only (they would overlap)
RSSI_RANGE_DBM = (-100.0, -30.0)  # fixed colour scale: APs are comparable across entities

WORLD = "world"
FLOOR_PLAN = "world/floor_plan"
LANDMARKS = "world/landmarks"
ALIGNED = "world/aligned"
TRAJECTORIES = "world/aligned/trajectories"
REFERENCE = "world/aligned/reference_pose"
EDGES = "world/aligned/wifi_edges"
FINGERPRINTS = "world/aligned/radio_map/fingerprints"
REFERENCE_MAP = "world/aligned/reference_map"  # a reference map's fingerprints, held (site frame)
APS = "world/aligned/radio_map/ap"
HEATMAPS = "world/aligned/radio_map/heatmap"
MAGNETIC = "world/aligned/magnetic_map"
MAGNETIC_PAIRS = "world/aligned/magnetic_pairs"
REFERENCE_FIELD = "world/aligned/reference_field"
CONVERGENCE = "world/aligned/convergence"
LOCATE_ESTIMATE = "world/aligned/locate/estimate"
LOCATE = "world/locate"
RAW = "raw"
OPTIMIZER = "optimizer"
NOTES = "info/notes"
CONFIG_TEXT = "info/config"

EDGE_STATES = ("inactive", "ramp", "saturated")  # index = graphslam.core.survey.factors.edge_state value
EDGE_COLOURS = np.array([[70, 170, 90, 110], [255, 160, 0, 160], [220, 40, 40, 200]], np.uint8)

# draw order: larger is drawn on top; the floor plan stays under everything
_Z_PLAN, _Z_EDGES, _Z_FP, _Z_TRACK, _Z_AP, _Z_LMK, _Z_REF = -100.0, 5.0, 8.0, 10.0, 12.0, 20.0, 30.0
_Z_HEAT = 1.0  # AP heatmaps: over the floor plan, under everything else

# viridis at 0, .25, .5, .75, 1 (enough for a readable RSSI ramp; avoids importing matplotlib)
_VIRIDIS = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]], float)
_FLIP_Y = np.diag([1.0, -1.0, 1.0])
_OPT_PLOTS = (("error", "LM total error"), ("log10_error", "log10 error"), ("active_edges", "active WiFi edges"),
              ("stage", "stage"))


# ---- results ---------------------------------------------------------------------------


@dataclass(frozen=True)
class RerunLogSummary:
    """What a call wrote: the file, its recording id, instances per entity, and the notes."""

    path: Path
    recording_id: str
    counts: dict[str, int]  # entity path -> points / segments / strips / rows logged
    notes: str
    seconds: float


@dataclass
class _Log:
    """Everything logged, as (entity, callable) steps plus counts and notes; written in one go."""

    steps: list[tuple[str, Callable[[rr.RecordingStream], None]]] = field(default_factory=list)
    counts: dict[str, int] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    views: dict[str, list[str]] = field(default_factory=dict)  # extra blueprint facts

    parts: dict[str, str] = field(default_factory=dict)  # id -> entity-path part (unique)

    def add(self, entity: str, count: int, fn: Callable[[rr.RecordingStream], None]) -> None:
        self.steps.append((entity, fn))
        self.counts[entity] = self.counts.get(entity, 0) + count

    def static(self, entity: str, count: int, *archetypes: rr.AsComponents) -> None:
        """One static ``log`` of all ``archetypes`` (each holding every instance) at ``entity``."""
        self.add(entity, count, lambda rec: rec.log(entity, *archetypes, static=True))

    def part(self, name: str) -> str:
        """An entity-path part for an id (session, BSSID): safe characters only, unique."""
        if name not in self.parts:
            base = re.sub(r"[^A-Za-z0-9_.-]", "_", name) or "_"
            used = set(self.parts.values())
            cand, k = base, 1
            while cand in used:
                k += 1
                cand = f"{base}~{k}"
            self.parts[name] = cand
        return self.parts[name]


# ---- public API ------------------------------------------------------------------------


def log_survey(
    rerun_path: str | Path,
    survey: Survey,
    alignment: Alignment,
    cfg: GraphSlamConfig | None = None,
    *,
    floor_plan: str | Path | None = None,
    floor_size: tuple[float, float] | None = None,
    max_edges: int = MAX_EDGES,
    top_aps: int = TOP_APS,
) -> RerunLogSummary:
    """Write ``survey`` and its ``alignment`` to the ``.rrd`` file ``rerun_path`` (with a blueprint).

    Landmarks (when the survey has them) are shown against the aligned walks after the
    SE(2) fit of ``graphslam.core.survey.evaluate.landmark_errors``: display and evaluation only.
    """
    t0 = time.perf_counter()
    cfg = cfg or GraphSlamConfig()
    plan = load_floor_plan(floor_plan, floor_size)
    lg = _Log()
    colours = session_colours(alignment.session_ids)
    T = _landmark_layers(lg, alignment.tracks, survey)
    _frame_layers(lg, T, plan, what=f"{alignment.frame} frame")
    _raw_layers(lg, survey, colours, set(alignment.tracks))
    _track_layers(lg, alignment.tracks, colours, alignment.reference)
    ref = alignment.session_ids.index(alignment.reference)
    ref_xyh = alignment.node_xyh[int(alignment.fingerprints.offsets[ref])]
    if np.isfinite(ref_xyh).all():
        _reference_layer(lg, ref_xyh, alignment.reference)
    _edge_layers(lg, alignment, cfg, max_edges)
    fm = alignment.fingerprints.fingerprints
    _radio_layers(lg, alignment.fingerprint_xy(), fm, top_aps, cfg.fingerprint.min_rssi_dbm)
    if alignment.reference_map is not None:
        _reference_map_layer(lg, np.asarray(alignment.reference_map.xy),
                             reference_label(alignment.reference_map.metadata.get("source")))
    if alignment.magnetic is not None:
        from graphslam.core.survey.radio_maps import crowdsourced_magnetic_map

        mm = crowdsourced_magnetic_map(survey, alignment, cfg)
        if mm is not None:
            _magnetic_layers(lg, mm)
        _magnetic_pair_layers(lg, alignment)
    _reference_field_layers(lg, alignment)
    _optimiser_layers(lg, alignment.iterations)
    _convergence_layers(lg, alignment, colours)
    lg.notes[:0] = _survey_summary(survey, alignment)
    return _write(Path(rerun_path), lg, _blueprint(lg), t0)


def log_locate_results(
    rerun_path: str | Path,
    estimate_xy: NDArray[np.float64],
    truth_xy: NDArray[np.float64] | None = None,
    *,
    query_ids: Sequence[str] | None = None,
    site_from_map: Sequence[float] | None = None,
    floor_plan: str | Path | None = None,
    floor_size: tuple[float, float] | None = None,
    recording_id: str | None = None,
) -> RerunLogSummary:
    """kNN answers (map frame) vs truth (site frame) as their own ``.rrd``.

    ``site_from_map`` (x, y, theta) places the map frame in the site frame (e.g. the
    survey report's ``evaluation.site_from_aligned``); without it both are taken to be the
    same frame. Invalid answers (NaN) are skipped. Pass the survey recording's
    ``recording_id`` to have the viewer overlay both files when opened together.
    """
    t0 = time.perf_counter()
    est = np.asarray(estimate_xy, dtype=float).reshape(-1, 2)
    truth = None if truth_xy is None else np.asarray(truth_xy, dtype=float).reshape(-1, 2)
    if truth is not None and len(truth) != len(est):
        raise ConfigError(f"locate: {len(est)} estimates but {len(truth)} truth positions")
    if query_ids is not None and len(query_ids) != len(est):
        raise ConfigError(f"locate: {len(est)} estimates but {len(query_ids)} query ids")
    ids = [str(q) for q in query_ids] if query_ids is not None else [f"q{i}" for i in range(len(est))]
    T = None if site_from_map is None else np.asarray(site_from_map, dtype=float).reshape(3)
    plan = load_floor_plan(floor_plan, floor_size)
    lg = _Log()
    _frame_layers(lg, T, plan, what="map frame")
    ok = np.isfinite(est).all(axis=1)
    lg.static(LOCATE_ESTIMATE, int(ok.sum()), _points(est[ok], [40, 120, 255], 4.0, _Z_LMK + 1, _pick(ids, ok)))
    lg.notes.append(f"- kNN answers: {int(ok.sum())} valid of {len(est)} queries (blue, map frame).")
    if truth is not None:
        both = ok & np.isfinite(truth).all(axis=1)
        est_site = se2_apply(T, est[both]) if T is not None else est[both]
        seg = np.stack([est_site, truth[both]], axis=1)
        err = np.linalg.norm(seg[:, 0] - seg[:, 1], axis=1)
        lg.static(f"{LOCATE}/truth", int(both.sum()), _points(truth[both], [0, 0, 0], 4.0, _Z_LMK, _pick(ids, both)))
        lg.static(f"{LOCATE}/error", len(seg), _segments(seg, [200, 0, 200, 220], 1.0, _Z_LMK - 1))
        if len(err):
            lg.notes.append(
                f"- error vs truth: mean {err.mean():.2f} m, median {np.median(err):.2f} m, "
                f"max {err.max():.2f} m (n={len(err)}; magenta segments)."
            )
    return _write(Path(rerun_path), lg, _blueprint(lg), t0, recording_id=recording_id)


def write_survey_view(
    out_dir: str | Path,
    rerun_path: str | Path,
    *,
    recordings: Sequence[str | Path] = (),
    floor_plan: str | Path | None = None,
    floor_size: tuple[float, float] | None = None,
    top_aps: int = TOP_APS,
) -> RerunLogSummary:
    """Log a finished survey output folder (``graphslam survey --out DIR``) to ``rerun_path``.

    Uses what DIR has: trajectories.csv (required), report.json, radio_map.parquet,
    config.yaml. ``recordings`` (the survey's .mcap files or folders) add the raw walks
    and the landmarks. WiFi edges and optimiser iterations are not stored in DIR: log them
    with ``graphslam survey --rerun`` instead.
    """
    t0 = time.perf_counter()
    d = Path(out_dir)
    tracks = survey_folder_tracks(d)
    plan = load_floor_plan(floor_plan, floor_size)
    report, problems = _read_report(d / "report.json")
    survey = None
    if recordings:
        from graphslam.io.mcap_reader import read_survey

        survey = read_survey(recordings)
    ids = tuple(dict.fromkeys(list(tracks) + ([s.session_id for s in survey] if survey else [])))
    colours = session_colours(ids)
    lg = _Log()
    T = _landmark_layers(lg, tracks, survey) if survey is not None else None
    _frame_layers(lg, T, plan, what=f"{report.get('frame') or 'aligned'} frame")
    if survey is not None:
        _raw_layers(lg, survey, colours, set(tracks))
    reference = str(report.get("reference_session") or next(iter(tracks)))
    _track_layers(lg, tracks, colours, reference)
    if reference in tracks:
        _reference_layer(lg, tracks[reference].xyh[0], reference)
    rm_path = d / "radio_map.parquet"
    if rm_path.exists():
        from graphslam.io.radiomap_io import read_radio_map

        try:
            rm = read_radio_map(rm_path)
            _radio_layers(lg, np.asarray(rm.xy), rm.fingerprints, top_aps, rm.min_rssi_dbm)
            held = held_reference(rm)
            if held is not None:
                _reference_map_layer(lg, *held)
        except GraphSlamError as e:  # optional file: show the rest, say why the map is missing
            problems.append(f"radio_map.parquet not shown: {e}")
    mm_path = d / "magnetic_map.parquet"
    if mm_path.exists():
        from graphslam.io.magnetic_map_io import read_magnetic_map

        try:
            _magnetic_layers(lg, read_magnetic_map(mm_path))
        except GraphSlamError as e:
            problems.append(f"magnetic_map.parquet not shown: {e}")
    cfg_path = d / "config.yaml"
    if cfg_path.exists():
        text = cfg_path.read_text(encoding="utf-8", errors="replace")
        lg.static(CONFIG_TEXT, 1, rr.TextDocument(text))
    lg.notes[:0] = _report_summary(d, tracks, report, survey) + [f"- {p}" for p in problems]
    return _write(Path(rerun_path), lg, _blueprint(lg), t0)


def rssi_colours(rssi_dbm: NDArray[np.float64], lo: float = RSSI_RANGE_DBM[0], hi: float = RSSI_RANGE_DBM[1]) -> NDArray[np.uint8]:
    """Viridis-like RGB for RSSI in dBm (``lo`` dark blue ... ``hi`` yellow)."""
    u = np.clip((np.asarray(rssi_dbm, float) - lo) / (hi - lo), 0.0, 1.0) * (len(_VIRIDIS) - 1)
    k = np.minimum(u.astype(int), len(_VIRIDIS) - 2)
    f = (u - k)[:, None]
    return np.round(_VIRIDIS[k] * (1 - f) + _VIRIDIS[k + 1] * f).astype(np.uint8)


# ---- layers: turn survey data into logging steps ---------------------------------------


def _landmark_layers(lg: _Log, tracks: Mapping[str, PoseTrack], survey: Survey | None) -> NDArray | None:
    """Truth, estimate and error of every landmark mark of an aligned walk; returns site_from_aligned."""
    if survey is None or not any(s.landmarks for s in survey):
        return None
    marks = landmark_marks(tracks, survey)
    if marks is None:
        lg.notes.append("- landmarks: fewer than 2 marks on aligned walks, no site-frame fit; not shown.")
        return None
    T, stats, labels = marks.site_from_output, marks.stats, list(marks.labels)
    e, tr = se2_apply(T, marks.estimate_xy), marks.truth_xy
    lg.static(f"{LANDMARKS}/truth", len(tr), _points(tr, [0, 0, 0], 3.5, _Z_LMK, labels))
    lg.static(f"{LANDMARKS}/estimate", len(e), _points(e, [230, 0, 230], 3.0, _Z_LMK + 1, labels))
    lg.static(f"{LANDMARKS}/error", len(e), _segments(np.stack([e, tr], axis=1), [230, 0, 230, 200], 1.0, _Z_LMK))
    lg.notes.append(
        f"- landmarks: {stats.n} marks; error after the SE(2) fit mean {stats.mean_m:.2f} m, "
        f"median {stats.median_m:.2f} m, max {stats.max_m:.2f} m (black = truth, magenta = estimate)."
    )
    return T


def _frame_layers(lg: _Log, T: NDArray | None, plan: FloorPlan | None, what: str = "aligned frame") -> None:
    """Root transforms (y flip for display, site-from-aligned) and the floor plan; states the frames."""
    lg.static(WORLD, 1, rr.Transform3D(mat3x3=_FLIP_Y))
    if T is not None:
        c, s = float(np.cos(T[2])), float(np.sin(T[2]))
        tf = rr.Transform3D(translation=[float(T[0]), float(T[1]), 0.0], mat3x3=[[c, -s, 0], [s, c, 0], [0, 0, 1]])
        lg.static(ALIGNED, 1, tf)
        lg.notes.append(
            f"- frames: the {what} (entities under /{ALIGNED}) is drawn in the site frame through the fitted "
            f"SE(2) site-from-{what.split()[0]} transform x={T[0]:.2f} m, y={T[1]:.2f} m, "
            f"theta={np.degrees(T[2]):.2f} deg (least-squares fit of the landmark marks; display and evaluation "
            "only, never used by the solver). Data keep their own coordinates."
        )
    else:
        described = FRAME_DESCRIPTIONS.get(what.split()[0])
        lg.notes.append(
            f"- frames: the {what} is drawn as is" + (f" ({described.split(': ', 1)[1]})" if described else "")
            + ("; it is NOT registered to the floor plan (no landmark fit)."
               if plan is not None and not what.startswith("site") else ".")
        )
    if plan is not None:
        w_px, h_px = plan.pixels
        # pixel (u, v), v down -> site (u W / w, H - v H / h); under the y flip of /world that is
        # a positive scale, so the image is not mirrored
        tf_plan = rr.Transform3D(translation=[0.0, plan.height_m, 0.0], scale=[plan.width_m / w_px, -plan.height_m / h_px, 1.0])
        img = rr.EncodedImage(contents=plan.path.read_bytes(), media_type=_media_type(plan.path), draw_order=_Z_PLAN)
        lg.static(FLOOR_PLAN, 1, tf_plan, img)
        lg.notes.append(
            f"- floor plan: {plan.path.name} ({w_px}x{h_px} px) spans x in [0, {plan.width_m:.2f}] m, "
            f"y in [0, {plan.height_m:.2f}] m of the site frame."
        )


def _raw_layers(lg: _Log, survey: Survey, colours: Mapping[str, tuple[int, int, int]], aligned: set[str]) -> None:
    """Every walk's dead reckoning in its own frame, laid side by side on a grid."""
    walks = [s for s in survey if len(s.steps)]
    if not walks:
        return
    lo = np.array([s.steps.xy.min(axis=0) for s in walks])
    hi = np.array([s.steps.xy.max(axis=0) for s in walks])
    cell = (hi - lo).max(axis=0) * 1.15 + 5.0  # one cell fits the largest walk, plus a margin
    cols = int(np.ceil(np.sqrt(len(walks))))
    lg.static(RAW, 1, rr.Transform3D(mat3x3=_FLIP_Y))
    for k, s in enumerate(walks):
        r, c = divmod(k, cols)
        offset = np.array([c * cell[0], -r * cell[1]]) - lo[k]
        path = f"{RAW}/{lg.part(s.session_id)}"
        label = s.session_id + ("" if s.session_id in aligned else " (unaligned)")
        strip = rr.LineStrips2D([s.steps.xy], colors=[colours.get(s.session_id, (128, 128, 128))],
                                radii=rr.components.Radius.ui_points(1.0), labels=[label],
                                show_labels=len(walks) <= MAX_RAW_LABELS, draw_order=_Z_TRACK)
        lg.static(path, 1, rr.Transform3D(translation=[float(offset[0]), float(offset[1]), 0.0]), strip)


def _track_layers(lg: _Log, tracks: Mapping[str, PoseTrack], colours: Mapping[str, tuple[int, int, int]], reference: str) -> None:
    for sid, tr in tracks.items():
        path = f"{TRAJECTORIES}/{lg.part(sid)}"
        strip = rr.LineStrips2D([tr.xy], colors=[colours.get(sid, (128, 128, 128))],
                                radii=rr.components.Radius.ui_points(2.0 if sid == reference else 1.25),
                                labels=[sid], show_labels=False, draw_order=_Z_TRACK)
        lg.static(path, 1, strip)


def _reference_layer(lg: _Log, xyh: NDArray, session_id: str) -> None:
    x, y, h = (float(v) for v in xyh)
    arrow = rr.Arrows2D(vectors=[[3.0 * np.cos(h), 3.0 * np.sin(h)]], origins=[[x, y]], colors=[[0, 0, 0]],
                        radii=rr.components.Radius.ui_points(2.5), labels=[f"reference: {session_id}"],
                        draw_order=_Z_REF)
    lg.static(REFERENCE, 1, arrow)


def _reference_map_layer(lg: _Log, xy: NDArray, name: str) -> None:
    """The reference map the main map is placed on: its fingerprints' site positions, dark grey."""
    lg.static(REFERENCE_MAP, len(xy), _points(xy, (70, 70, 70), 2.5, _Z_FP + 0.5, [name] * len(xy)))
    lg.notes.append(f"- reference map {name}: {len(xy):,} fingerprints, held (dark grey, /{REFERENCE_MAP})")


def _edge_layers(lg: _Log, al: Alignment, cfg: GraphSlamConfig, max_edges: int) -> None:
    """WiFi-vicinity edges between aligned walks of one component, one entity per final state (toggle
    each in the viewer); an edge between two components would join two unrelated frames."""
    fp = al.fingerprints
    a = al.node_xyh[fp.node[al.edges.i], :2]
    b = al.node_xyh[fp.node[al.edges.j], :2]
    ok = np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1)
    if len(al.components) > 1:
        of = al.component_of()
        comp = np.array([of.get(sid, -1) for sid in al.session_ids], np.int64)[fp.session]
        ok &= comp[al.edges.i] == comp[al.edges.j]
    idx = np.flatnonzero(ok)
    n_ok = len(idx)
    if n_ok > max_edges:
        # deterministic, uniform subsample: the share of each state is kept on average
        idx = np.sort(np.random.default_rng(0).choice(idx, size=max_edges, replace=False))
    seg = np.stack([a[idx], b[idx]], axis=1)
    d = np.linalg.norm(seg[:, 0] - seg[:, 1], axis=1)
    st = edge_state(d, cfg.wifi)
    for k, name in enumerate(EDGE_STATES):
        m = st == k
        lg.static(f"{EDGES}/{name}", int(m.sum()), _segments(seg[m], EDGE_COLOURS[k], 0.5, _Z_EDGES))
    shown = f"all {n_ok:,}" if n_ok == len(idx) else f"{len(idx):,} of {n_ok:,} (uniform random subsample, seed 0)"
    lg.notes.append(
        f"- WiFi edges: {len(al.edges):,} proposed, {n_ok:,} between aligned walks of one component; shown {shown}. "
        f"Colour = state at the final poses (d_min {cfg.wifi.d_min_m:g} m, d_max {cfg.wifi.d_max_m:g} m): "
        "green inactive (d < d_min), orange fuzzy ramp, red saturated (d > d_max)."
    )


def _radio_layers(lg: _Log, xy: NDArray, fm: FingerprintMatrix, top_aps: int,
                  min_rssi_dbm: float = DEFAULT_MIN_RSSI_DBM) -> None:
    """Fingerprint positions and, per most-heard AP, its RSSI at every fingerprint that heard it and
    its heatmap (``graphslam.core.radiomap.field``: an image in metres, uncertain cells faded)."""
    rows = np.flatnonzero(np.isfinite(xy).all(axis=1))
    lg.static(FINGERPRINTS, len(rows), _points(xy[rows], [90, 90, 90], 1.5, _Z_FP, None))
    if not len(rows) or fm.n_aps == 0:
        return
    cols = top_access_points(fm, rows, top_aps)
    sub = fm.values[rows].tocsc()
    names = []
    for rank, c in enumerate(cols, start=1):
        sl = slice(sub.indptr[c], sub.indptr[c + 1])
        heard_rows, rssi = sub.indices[sl], sub.data[sl] + fm.missing_dbm
        bssid = fm.bssids[c]
        part = f"{rank:02d}_{lg.part(bssid)}"
        path = f"{APS}/{part}"
        pts = rr.Points2D(xy[rows][heard_rows], colors=rssi_colours(rssi), radii=rr.components.Radius.ui_points(3.0),
                          draw_order=_Z_AP)
        lg.static(path, len(heard_rows), pts, rr.AnyValues(rssi_dbm=rssi.astype(np.float64)))
        full = np.full(len(rows), float(min_rssi_dbm))
        full[heard_rows] = rssi
        heat = readings_field(xy[rows], full, bssid, float(min_rssi_dbm), n_heard=len(heard_rows))
        rgba = heatmap_rgba(heat)
        img = np.ascontiguousarray(np.transpose(rgba, (1, 0, 2))[::-1])  # rows from the top: y decreasing
        x0, _, _, y1 = heat.extent
        # pixel (u, v), v down -> (x0 + u cell, y1 - v cell) of the aligned frame
        tf = rr.Transform3D(translation=[x0, y1, 0.0], scale=[heat.cell_m, -heat.cell_m, 1.0])
        lg.static(f"{HEATMAPS}/{part}", 1, tf, rr.Image(img, color_model="RGBA", draw_order=_Z_HEAT))
        names.append((path, f"{HEATMAPS}/{part}", bssid, len(heard_rows), float(np.median(rssi)), heat.cell_m))
    lg.views["aps"] = [p for p, *_ in names]
    lg.views["heatmaps"] = [h for _, h, *_ in names]
    lg.views["ap_titles"] = [f"AP {r}: {b}" for r, (_, _, b, *_) in enumerate(names, start=1)]
    listing = "; ".join(f"{b} heard {n}x, median {m:.0f} dBm" for _, _, b, n, m, _ in names)
    lg.notes.append(
        f"- radio map: {len(rows):,} fingerprints (grey), {fm.n_aps:,} APs. Top {len(names)} most-heard APs under "
        f"/{APS}: colour = RSSI, viridis from {RSSI_RANGE_DBM[0]:g} dBm (dark blue) to {RSSI_RANGE_DBM[1]:g} dBm "
        f"(yellow); values in the selection panel (rssi_dbm). Their heatmaps under /{HEATMAPS} (one tab per AP): "
        f"a Gaussian kernel average of every fingerprint's reading (not heard = {min_rssi_dbm:g} dBm) on "
        f"{names[0][5] if names else 0:g} m cells, faded toward white where its standard error exceeds "
        f"{MAX_STD_ERROR_DB:g} dB (docs/pictures.md). {listing}."
    )


def _magnetic_layers(lg: _Log, mm: MagneticMap) -> None:
    """The magnetic map's samples, coloured by |B| and by B_up (viridis over the map's 2nd-98th percentile)."""
    if not len(mm):
        return
    ranges = []
    for name, col in (("magnitude", 0), ("vertical", 2)):
        v = mm.features[:, col]
        lo, hi = (float(q) for q in np.percentile(v, [2, 98]))
        pts = rr.Points2D(mm.xy, colors=rssi_colours(v, lo, max(hi, lo + 1e-6)),
                          radii=rr.components.Radius.ui_points(2.5), draw_order=_Z_AP)
        lg.static(f"{MAGNETIC}/{name}", len(mm), pts, rr.AnyValues(field_ut=v.astype(np.float64)))
        ranges.append(f"{name} {lo:.1f} to {hi:.1f} µT")
    lg.notes.append(
        f"- magnetic map: {len(mm):,} samples of {mm.n_walks} walks under /{MAGNETIC} (one entity per feature: "
        f"|B| and B_up, each walk's device offset removed); colour viridis over the 2nd-98th percentile "
        f"({'; '.join(ranges)}); values in the selection panel (field_ut)."
    )


def _magnetic_pair_layers(lg: _Log, al: Alignment) -> None:
    """The magnetic factors as segments between the two poses they say are one place."""
    pairs = al.magnetic_pairs
    if pairs is None or not len(pairs):
        return
    seg = np.stack([al.node_xyh[pairs[:, 0], :2], al.node_xyh[pairs[:, 1], :2]], axis=1)
    seg = seg[np.isfinite(seg).all(axis=(1, 2))]
    lg.static(MAGNETIC_PAIRS, len(seg), _segments(seg, (140, 60, 200), 0.5, _Z_EDGES))
    n_links = len(al.magnetic) if al.magnetic is not None else 0
    lg.notes.append(f"- magnetic factors: {len(seg):,} step pairs of {n_links} magnetic links (purple) under "
                    f"/{MAGNETIC_PAIRS}.")


def _reference_field_layers(lg: _Log, al: Alignment) -> None:
    """A reference's field (a previous survey's magnetic map): the magnetic factors from crowd poses to its
    held samples, as segments, and those samples."""
    ties = al.field_ties
    if ties is None or not len(ties):
        return
    seg = np.stack([al.node_xyh[ties.pairs[:, 0], :2], ties.xy[ties.pairs[:, 1]]], axis=1)
    seg = seg[np.isfinite(seg).all(axis=(1, 2))]
    lg.static(f"{REFERENCE_FIELD}/factors", len(seg), _segments(seg, (140, 60, 200), 0.5, _Z_EDGES))
    held = np.unique(ties.pairs[:, 1])
    lg.static(f"{REFERENCE_FIELD}/samples", len(held),
              rr.Points2D(ties.xy[held], colors=[(90, 90, 90)], radii=rr.components.Radius.ui_points(2.0), draw_order=_Z_AP))
    lg.notes.append(f"- the reference's field: {len(seg):,} magnetic factors (purple) of {ties.links} links from "
                    f"{len(ties.walks)} crowd walks to {len(held):,} of its samples (grey), held, under /{REFERENCE_FIELD}.")


def _optimiser_layers(lg: _Log, iterations: Sequence[IterationRecord]) -> None:
    """Total error etc. per LM iteration on the ``lm_iteration`` timeline (1 = after the first)."""
    if not iterations:
        return
    n = len(iterations)
    t = [rr.TimeColumn(TIMELINE_ITERATION, sequence=np.arange(1, n + 1))]
    err = np.array([r.error_after for r in iterations], float)
    series = {
        "error": err,
        "log10_error": np.log10(np.maximum(err, 1e-300)),
        "active_edges": np.array([r.active_edges for r in iterations], float),
        "stage": np.array([r.stage for r in iterations], float),
    }
    for name, values in series.items():
        path = f"{OPTIMIZER}/{name}"

        def log_series(rec: rr.RecordingStream, path: str = path, name: str = name, values: NDArray = values) -> None:
            rec.log(path, rr.SeriesLines(names=name), static=True)
            rec.send_columns(path, indexes=t, columns=rr.Scalars.columns(scalars=values))

        lg.add(path, n, log_series)


def _convergence_layers(lg: _Log, al: Alignment, colours: Mapping[str, tuple[int, int, int]]) -> None:
    """Each aligned walk at the initial guess and after each LM stage, on both LM timelines."""
    iters = al.iterations
    it_times, st_times, frames = [0], [0], [al.initial_xyh]
    for stage, xyh in al.snapshots:
        done = [k + 1 for k, r in enumerate(iters) if r.stage <= stage]
        it_times.append(max(done) if done else it_times[-1])  # a stage without iterations: same time
        st_times.append(stage + 1)
        frames.append(xyh)
    fp = al.fingerprints
    idx = {sid: k for k, sid in enumerate(al.session_ids)}
    for sid in al.tracks:
        a, b = int(fp.offsets[idx[sid]]), int(fp.offsets[idx[sid] + 1])
        strips = [f[a:b, :2] for f in frames]
        path = f"{CONVERGENCE}/{lg.part(sid)}"
        colour = colours.get(sid, (128, 128, 128))
        times = [rr.TimeColumn(TIMELINE_ITERATION, sequence=it_times), rr.TimeColumn(TIMELINE_STAGE, sequence=st_times)]

        def log_conv(rec: rr.RecordingStream, path: str = path, strips: list = strips, colour: tuple = colour, times: list = times) -> None:
            rec.log(path, rr.LineStrips2D.from_fields(colors=[colour], radii=rr.components.Radius.ui_points(1.25),
                                                      draw_order=_Z_TRACK), static=True)
            rec.send_columns(path, indexes=times, columns=rr.LineStrips2D.columns(strips=strips).partition([1] * len(strips)))

        lg.add(path, len(strips), log_conv)


# ---- notes -----------------------------------------------------------------------------


def _survey_summary(survey: Survey, al: Alignment) -> list[str]:
    lines = [
        "# graphslam survey",
        f"- {len(survey)} walks, {len(al.tracks)} aligned; reference walk **{al.reference}** "
        f"(its first pose is fixed: black arrow at /{REFERENCE}).",
        f"- {al.n_nodes:,} step poses, {len(al.fingerprints):,} fingerprints.",
        f"- optimiser: {len(al.iterations)} LM iterations in {len({r.stage for r in al.iterations})} stages, "
        f"error {al.initial_error:.6g} -> {al.final_error:.6g} (converged: {al.converged}). Timeline "
        f"`{TIMELINE_ITERATION}` scrubs /{CONVERGENCE} (0 = initial guess) and the /{OPTIMIZER} plots; "
        f"`{TIMELINE_STAGE}` k = after k stages.",
    ]
    lines += _unaligned_lines(list(al.unaligned.items()))
    return lines


def _unaligned_lines(items: list[tuple[str, str]], limit: int = 10) -> list[str]:
    """One line per unaligned walk, the first ``limit`` of them (real surveys can have 100s)."""
    out = [f"- unaligned: {sid}: {why} (shown under /{RAW} only)." for sid, why in items[:limit]]
    if len(items) > limit:
        out.append(f"- ... and {len(items) - limit} more unaligned walks (see report.json).")
    return out


def _report_summary(d: Path, tracks: Mapping[str, PoseTrack], report: Mapping, survey: Survey | None) -> list[str]:
    lines = [f"# graphslam survey output: {d}", f"- {len(tracks)} aligned walks from trajectories.csv."]
    if report:
        opt = report.get("optimizer") if isinstance(report.get("optimizer"), dict) else {}
        edges = report.get("edges") if isinstance(report.get("edges"), dict) else {}
        lines.append(
            f"- report.json: {report.get('sessions', '?')} walks, {report.get('aligned_sessions', '?')} aligned, "
            f"reference {report.get('reference_session', '?')}; {edges.get('wifi', '?')} WiFi edges "
            f"{edges.get('wifi_states', '')}; LM {opt.get('iterations', '?')} iterations, "
            f"error {opt.get('initial_error', '?')} -> {opt.get('final_error', '?')}."
        )
        un = [u for u in report.get("unaligned", []) or [] if isinstance(u, dict)]
        lines += _unaligned_lines([(str(u.get("session_id")), str(u.get("reason"))) for u in un])
    lines.append(
        "- WiFi edges and optimiser iterations are not stored in the output folder: "
        "use `graphslam survey --rerun FILE.rrd` to see them."
        + ("" if survey is not None else " Raw walks and landmarks need `--recordings`.")
    )
    return lines


def _read_report(path: Path) -> tuple[dict, list[str]]:
    if not path.exists():
        return {}, ["report.json missing"]
    try:
        rep = json.loads(path.read_text(encoding="utf-8"))
        if not isinstance(rep, dict):
            raise ValueError("not a JSON object")
        return rep, []
    except (OSError, ValueError) as e:
        return {}, [f"report.json not read ({e})"]


# ---- blueprint and file ----------------------------------------------------------------


def _blueprint(lg: _Log) -> rrb.Blueprint:
    has = lambda prefix: any(e == prefix or e.startswith(prefix + "/") for e in lg.counts)  # noqa: E731
    main_contents = ["+ /world/**", f"- /{CONVERGENCE}/**", f"- /{APS}/**", f"- /{HEATMAPS}/**"]
    main = rrb.Spatial2DView(name="Aligned survey", origin="/", contents=main_contents)
    side: list[rrb.Container | rrb.View] = []
    if has(RAW):
        side.append(rrb.Spatial2DView(name="Raw walks (own frames)", origin="/", contents=[f"+ /{RAW}/**"]))
    if has(OPTIMIZER):
        # one plot per series: their scales differ by orders of magnitude
        side.append(
            rrb.Tabs(
                *[rrb.TimeSeriesView(name=title, origin=f"/{OPTIMIZER}/{name}") for name, title in _OPT_PLOTS],
                name="Optimiser",
            )
        )
    side.append(rrb.TextDocumentView(name="Notes", origin="/info"))
    tabs: list[rrb.Container | rrb.View] = [
        rrb.Horizontal(main, rrb.Vertical(*side), column_shares=[3, 2], name="Survey")
    ]
    if has(CONVERGENCE):
        tabs.append(
            rrb.Spatial2DView(
                name="Convergence (scrub lm_iteration)",
                origin="/",
                contents=[f"+ /{FLOOR_PLAN}", f"+ /{CONVERGENCE}/**", f"+ /{REFERENCE}", f"+ /{LANDMARKS}/truth"],
            )
        )
    aps = lg.views.get("aps", [])
    if aps:
        views = [
            rrb.Spatial2DView(name=title, origin="/",
                              contents=[f"+ /{FLOOR_PLAN}", f"+ /{h}", f"+ /{FINGERPRINTS}", f"+ /{p}"])
            for p, h, title in zip(aps, lg.views["heatmaps"], lg.views["ap_titles"])
        ]
        tabs.append(rrb.Tabs(*views, name="Radio map (per AP)"))
    time_panel = rrb.TimePanel(timeline=TIMELINE_ITERATION, state="collapsed") if has(OPTIMIZER) else rrb.TimePanel(state="collapsed")
    return rrb.Blueprint(rrb.Tabs(*tabs), time_panel, collapse_panels=False)


def _write(path: Path, lg: _Log, blueprint: rrb.Blueprint, t0: float, *, recording_id: str | None = None) -> RerunLogSummary:
    """Run the logging steps into a temporary file beside ``path``; rename it once complete."""
    if os.environ.get("RERUN", "").strip().lower() in ("off", "0", "false", "no"):
        raise VisualizationError(f"RERUN={os.environ['RERUN']} in the environment disables Rerun: cannot write {path}")
    notes = "\n".join(lg.notes)
    lg.static(NOTES, 1, rr.TextDocument(notes, media_type=rr.MediaType.MARKDOWN))
    rid = recording_id or str(uuid4())
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        os.close(fd)
        mask = os.umask(0)
        os.umask(mask)
        os.chmod(tmp_name, 0o666 & ~mask)  # mkstemp's 0600 would make the .rrd private
    except OSError as e:
        raise VisualizationError(f"cannot write {path}: {e.strerror or e}") from None
    tmp = Path(tmp_name)
    rec = rr.RecordingStream(APP_ID, recording_id=rid)
    try:
        if not rec.is_enabled():  # Rerun would silently drop everything
            raise VisualizationError(f"Rerun recording is disabled in this process: cannot write {path}")
        rec.save(tmp, default_blueprint=blueprint)
        for _entity, step in lg.steps:  # timed data go through send_columns: no sticky set_time
            step(rec)
        rec.flush()
        rec.disconnect()  # writes the footer: the file is complete from here on
        if tmp.stat().st_size == 0:
            raise VisualizationError(f"Rerun wrote nothing to {path} (recording disabled?)")
        os.replace(tmp, path)
    except BaseException as e:
        with contextlib.suppress(Exception):
            rec.disconnect()
        tmp.unlink(missing_ok=True)  # no half-written output, whatever failed
        if isinstance(e, OSError):
            raise VisualizationError(f"cannot write {path}: {e.strerror or e}") from e
        raise
    secs = time.perf_counter() - t0
    log.info("rerun: wrote %s (%.1f MB) in %.2f s", path, path.stat().st_size / 1e6, secs)
    return RerunLogSummary(path, rid, dict(lg.counts), notes, secs)


# ---- small helpers ---------------------------------------------------------------------


def _points(xy: NDArray, colour: Sequence[int], ui_radius: float, z: float, labels: Sequence[str] | None) -> rr.Points2D:
    return rr.Points2D(
        np.asarray(xy, float).reshape(-1, 2),
        colors=[[int(c) for c in colour]],
        radii=rr.components.Radius.ui_points(ui_radius),
        labels=list(labels) if labels is not None else None,
        show_labels=False if labels is not None else None,  # hover/selection shows them; 1000s would clutter
        draw_order=z,
    )


def _segments(seg: NDArray, colour: Sequence[int], ui_radius: float, z: float) -> rr.LineStrips2D:
    """Many 2-point strips in one archetype (one log call for all segments)."""
    return rr.LineStrips2D(
        np.asarray(seg, float).reshape(-1, 2, 2),
        colors=[[int(c) for c in colour]],
        radii=rr.components.Radius.ui_points(ui_radius),
        draw_order=z,
    )


def _pick(items: Sequence[str], mask: NDArray[np.bool_]) -> list[str]:
    return [s for s, m in zip(items, mask.tolist()) if m]


def _media_type(p: Path) -> str:
    return {".png": "image/png", ".jpg": "image/jpeg", ".jpeg": "image/jpeg"}.get(p.suffix.lower(), "image/png")
