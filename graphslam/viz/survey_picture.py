"""``survey.png``: the aligned survey at a glance (``graphslam.io.canvas``: Pillow, fast).

Every aligned walk in its own colour (the colours of the Rerun views), the reference walk
marked at its first pose (the origin of the output frame), the WiFi edges faint by their
final state, landmark truth / estimate / error when the recordings have marks, a scale bar,
and the floor plan underneath when one is given. Unaligned walks are listed in the legend,
grouped by their reason.

Components: the big panel is the main map (component 0, the radio map's walks). Walks in
other components (each in a frame of its own, its placement relative to the main map
unknown) are drawn apart, in a strip of small panels under it, each at its own scale and
labelled "component k: n walks (own frame)": the ``MAX_INSETS`` largest; the legend counts the
rest (not drawn) and groups all of them by why they stand apart.

Frames: the picture is drawn in the output frame (trajectories.csv) unless a floor plan is
given and the landmarks gave a site-from-output fit: then everything is drawn in the plan's
site frame through that fit (display only; the subtitle says which). In the "earth" frame
(x east, y north from the phones' headings) a north arrow marks the main panel.

Two sources, one ``SurveyScene``: ``scene_of_alignment`` (in memory, by ``graphslam survey``)
and ``scene_of_folder`` (a finished output folder, by ``graphslam plot``).
"""

from __future__ import annotations

import json
import textwrap
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from graphslam.config import GraphSlamConfig
from graphslam.core.survey.radio_maps import WifiEdgeRows, crowdsourced_edges, held_reference, reference_label
from graphslam.core.survey.align import Alignment
from graphslam.core.survey.evaluate import Evaluation
from graphslam.core.common.geometry import se2_apply
from graphslam.core.summary import main_map_counts
from graphslam.core.types import Survey
from graphslam.errors import InputError
from graphslam.names import FRAMES
from graphslam.viz.common import (
    FloorPlan, LandmarkMarks, fitted_site_from_aligned, landmark_marks, session_colours, site_to_frame,
    survey_folder_trajectories,
)
from graphslam.io.canvas import BLACK, GREY, LegendEntry, Picture, bounds_of

SIZE_PX = (1600, 1000)
MAX_EDGES = 20_000  # drawn; more are subsampled (deterministically), the legend gives both counts
MAX_LEGEND_WALKS = 16  # more aligned walks: one legend line for all (the colours still differ)
MAX_REASONS = 6  # unaligned walks are grouped by reason; at most this many groups listed
MAX_INSETS = 6  # other components drawn in the strip under the main map (the largest first)
INSET_STRIP_PX = 200  # height of that strip, its labels included
EDGE_COLOURS = ((70, 170, 90), (255, 160, 0), (220, 40, 40))  # inactive, ramp, saturated (as in Rerun)
MAGENTA = (215, 0, 215)
CONTROL = (0, 90, 255)  # control points (given) and their marks: not the landmarks' black and magenta
ANCHOR = (230, 110, 0)  # UWB anchors
REFERENCE = (95, 95, 95)  # a reference map's places (held): under the walks, darker than the edges
EDGE_NAMES = ("inactive", "ramp", "saturated")
PICTURE = "survey.png"


@dataclass(frozen=True, eq=False)
class SurveyScene:
    """What ``survey.png`` shows. Positions in the output frame (metres) except ``marks.truth_xy``."""

    tracks: dict[str, NDArray[np.float64]]  # aligned walks: (N, 2) each
    colours: dict[str, tuple[int, int, int]]  # every session (aligned or not), as in Rerun
    reference: str
    unaligned: dict[str, str]  # session id -> reason
    edge_xy: NDArray[np.float64]  # (E, 2, 2) the edges drawn (a sample when there are many)
    edge_state: NDArray[np.int8]  # (E,)
    edge_counts: tuple[int, int, int]  # every edge between aligned walks, by state
    marks: LandmarkMarks | None  # from the recordings
    site_from_output: NDArray[np.float64] | None  # landmark fit (marks or report.json)
    landmark_text: str  # "43 marks: mean 0.67 m ..." or ""
    n_sessions: int
    n_poses: int
    notes: tuple[str, ...] = ()  # what could not be shown, and why
    # (index, walks, reason) of every component, 0 first; empty: every walk of ``tracks`` in component 0
    components: tuple[tuple[int, tuple[str, ...], str], ...] = ()
    frame: str = "aligned"  # of component 0: "aligned" | "earth" | "site"
    # the control points given (landmark id -> site x, y): drawn apart from the landmarks
    control_points: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    # the UWB anchors whose ranges placed the main map in the site frame (id -> site x, y)
    anchors: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    reference_map: str = ""  # the file name of the reference map the main map is placed on ("": none)
    # its fingerprints' site positions (drawn under the walks)
    reference_xy: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 2)))

    def main_ids(self) -> list[str]:
        """The walks of the main map (component 0), in ``tracks`` order."""
        if not self.components:
            return list(self.tracks)
        main = set(self.components[0][1])
        return [s for s in self.tracks if s in main]

    def other_components(self) -> list[tuple[int, tuple[str, ...], str]]:
        """Components >= 1 with their walks that are in ``tracks``; empty ones left out."""
        out = []
        for k, walks, why in self.components[1:]:
            w = tuple(s for s in walks if s in self.tracks)
            if w:
                out.append((k, w, why))
        return out


def scene_of_alignment(
    survey: Survey, al: Alignment, cfg: GraphSlamConfig, evaluation: Evaluation | None = None,
    *, max_edges: int = MAX_EDGES,
) -> SurveyScene:
    """The scene of a survey just aligned (``graphslam survey``)."""
    tracks = {sid: np.asarray(tr.xy) for sid, tr in al.tracks.items()}
    xy = al.fingerprint_xy()
    finite = np.isfinite(xy).all(axis=1)
    rows_xy = xy[finite]
    edges = crowdsourced_edges(al, cfg)
    comps = tuple((c.index, tuple(c.walks), c.reason) for c in al.components)
    if len(comps) > 1:  # the main map's edges only: an edge to another component joins two frames
        main = np.isin(np.asarray(al.session_ids, dtype=object)[al.fingerprints.session[finite]],
                       list(comps[0][1]))
        ok = main[edges.a] & main[edges.b]
        edges = WifiEdgeRows(edges.a[ok], edges.b[ok], edges.distance_m[ok], edges.state[ok])
    marks = landmark_marks(al.main_tracks(), survey)  # one fit: the main map's walks
    T = marks.site_from_output if marks is not None else None
    if T is None and evaluation is not None and evaluation.steps.n:  # fitted on true poses (simulations)
        T = np.asarray(evaluation.site_from_aligned, float)
    anchors = _anchors(survey, al.uwb.anchors) if al.uwb is not None and al.frame == "site" else {}
    return _scene(
        tracks, al.session_ids, al.reference, dict(al.unaligned), rows_xy, edges, marks, T,
        _landmark_text(marks.stats.as_dict() if marks is not None else None), survey.n_steps, max_edges, (),
        comps, al.frame, dict(al.control_points), anchors,
        reference_label(al.reference_map.metadata.get("source")) if al.reference_map is not None else "",
        np.asarray(al.reference_map.xy, float) if al.reference_map is not None else None,
    )


def _anchors(survey: Survey | None, ids: Sequence[str]) -> dict[str, tuple[float, float]]:
    """The site (x, y) of the anchors ``ids`` as the walks' recordings give them."""
    if survey is None:
        return {}
    out: dict[str, tuple[float, float]] = {}
    for s in survey:
        for a, p in s.uwb_anchors.items():
            if a in ids:
                out.setdefault(a, (float(p[0]), float(p[1])))
    return out


def scene_of_folder(
    out_dir: str | Path, recordings: Sequence[str | Path] = (), *, max_edges: int = MAX_EDGES
) -> SurveyScene:
    """The scene of a finished ``graphslam survey --out`` folder (``graphslam plot``).

    Needs ``trajectories.csv``; uses ``report.json`` (reference, unaligned walks and reasons,
    the landmark fit), ``radio_map.parquet`` + ``wifi_edges.parquet`` (edges) when present.
    ``recordings`` add the landmark marks and the walks that were not aligned.
    """
    d = Path(out_dir)
    traj = survey_folder_trajectories(d)
    pose_tracks = traj.tracks
    report = _read_json(d / "report.json")
    notes: list[str] = []
    survey = None
    if recordings:
        from graphslam.io.mcap_reader import read_survey

        survey = read_survey(recordings)
    # the survey's own order gives each walk the colour it had in survey.png and in Rerun
    ids = [w.get("session_id") for w in report.get("walks") or [] if isinstance(w, dict)]
    unaligned = {
        str(u.get("session_id")): str(u.get("reason")) for u in report.get("unaligned") or [] if isinstance(u, dict)
    }
    if survey is not None and not ids:
        ids = [s.session_id for s in survey]
    ids = list(dict.fromkeys([str(i) for i in ids] + list(pose_tracks) + list(unaligned)))
    reference = str(report.get("reference_session") or next(iter(pose_tracks)))
    rows_xy, edges, ref_xy = np.zeros((0, 2)), None, None
    if (d / "wifi_edges.parquet").exists() and (d / "radio_map.parquet").exists():
        from graphslam.io.edges_io import read_wifi_edges
        from graphslam.io.radiomap_io import read_radio_map

        rm = read_radio_map(d / "radio_map.parquet")
        rows_xy = np.asarray(rm.xy)
        edges = read_wifi_edges(d / "wifi_edges.parquet", len(rows_xy))
        held = held_reference(rm)
        ref_xy = None if held is None else held[0]
    else:
        notes.append("WiFi edges not shown: no wifi_edges.parquet + radio_map.parquet in the folder")
    marks = landmark_marks(traj.of_component(0), survey)
    ev = report.get("evaluation") if isinstance(report.get("evaluation"), dict) else {}
    T = marks.site_from_output if marks is not None else None
    if T is None:
        T = fitted_site_from_aligned(ev)
    lm = marks.stats.as_dict() if marks is not None else ev.get("landmarks")
    n_poses = int(report.get("nodes") or sum(len(t) for t in pose_tracks.values()))
    reasons = {
        c.get("index"): str(c.get("reason") or "") for c in report.get("components") or [] if isinstance(c, dict)
    }
    by_index: dict[int, list[str]] = {}
    for sid in pose_tracks:
        by_index.setdefault(traj.components.get(sid, 0), []).append(sid)
    comps = tuple((k, tuple(by_index[k]), reasons.get(k, "")) for k in sorted(by_index))
    if comps and comps[0][0] != 0:  # no walk in the main map: an empty component 0 first
        comps = ((0, (), ""),) + comps
    frame = report.get("frame") if report.get("frame") in FRAMES else "aligned"
    cps = report.get("control_points") if isinstance(report.get("control_points"), dict) else {}
    control = {str(k): (float(v[0]), float(v[1])) for k, v in cps.items()}
    uwb = report.get("uwb") if isinstance(report.get("uwb"), dict) else {}
    anchors = _anchors(survey, [str(a) for a in uwb.get("anchors") or []]) if frame == "site" else {}
    ref = report.get("reference_map") if isinstance(report.get("reference_map"), dict) else {}
    return _scene(
        {sid: np.asarray(t.xy) for sid, t in pose_tracks.items()}, ids, reference, unaligned, rows_xy, edges,
        marks, T, _landmark_text(lm), n_poses, max_edges, tuple(notes), comps if len(comps) > 1 else (), frame,
        control, anchors, reference_label(ref.get("source")) if frame == "site" and ref.get("used") is True else "",
        ref_xy,
    )


def _scene(
    tracks: dict[str, NDArray], ids: Sequence[str], reference: str, unaligned: dict[str, str], rows_xy: NDArray,
    edges: WifiEdgeRows | None, marks: LandmarkMarks | None, T: NDArray | None, landmark_text: str, n_poses: int,
    max_edges: int, notes: tuple[str, ...], components: tuple[tuple[int, tuple[str, ...], str], ...] = (),
    frame: str = "aligned", control_points: Mapping[str, tuple[float, float]] | None = None,
    anchors: Mapping[str, tuple[float, float]] | None = None, reference_map: str = "",
    reference_xy: NDArray | None = None,
) -> SurveyScene:
    if edges is None or not len(edges.a):
        seg, state, counts = np.zeros((0, 2, 2)), np.zeros(0, np.int8), (0, 0, 0)
    else:
        c = np.bincount(edges.state, minlength=3)
        counts = (int(c[0]), int(c[1]), int(c[2]))
        pick = np.arange(len(edges.a))
        if len(pick) > max_edges:  # same sample every time: the picture of a survey does not flicker
            pick = np.sort(np.random.default_rng(0).choice(len(pick), max_edges, replace=False))
        seg = np.stack([rows_xy[edges.a[pick]], rows_xy[edges.b[pick]]], axis=1)
        state = edges.state[pick]
    return SurveyScene(
        tracks, session_colours(ids), reference, unaligned, seg, state, counts, marks, T, landmark_text,
        len(ids), n_poses, notes, components if len(components) > 1 else (), frame, dict(control_points or {}),
        dict(anchors or {}), reference_map,
        np.zeros((0, 2)) if reference_xy is None or not reference_map else np.asarray(reference_xy, float).reshape(-1, 2),
    )


def _read_json(path: Path) -> dict[str, Any]:
    if not path.exists():
        return {}
    try:
        rep = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise InputError(path, f"not readable JSON ({e})") from None
    if not isinstance(rep, dict):
        raise InputError(path, "not a JSON object")
    return rep


def _landmark_text(lm: Mapping[str, Any] | None) -> str:
    if not lm or not lm.get("n"):
        return ""
    return (
        f"landmark error (SE(2) fit, {lm['n']} marks): mean {lm['mean_m']:.2f} m, median {lm['median_m']:.2f} m, "
        f"max {lm['max_m']:.2f} m"
    )


# ---- drawing -------------------------------------------------------------------------------


def draw_survey(
    scene: SurveyScene, path: str | Path, *, floor_plan: FloorPlan | None = None, size_px: tuple[int, int] = SIZE_PX
) -> Path:
    """Render ``scene`` to the PNG ``path`` (``size_px`` pixels exactly, written atomically)."""
    return survey_picture(scene, floor_plan=floor_plan, size_px=size_px).save(path)


def survey_picture(scene: SurveyScene, *, floor_plan: FloorPlan | None = None, size_px: tuple[int, int] = SIZE_PX) -> Picture:
    """The picture, not yet rendered: the main map's panel (a strip of small panels under it for the
    other components), the legend in a column on its right."""
    # a main map in the site frame is drawn over the plan as it is; another through the landmark fit
    T = np.zeros(3) if scene.frame == "site" else scene.site_from_output
    in_site = floor_plan is not None and T is not None
    move = (lambda xy: se2_apply(T, xy)) if in_site else (lambda xy: xy)  # noqa: E731
    ids = scene.main_ids()
    others = scene.other_components()
    lines = [move(scene.tracks[s]) for s in ids]
    colours = [scene.colours[s] for s in ids]
    est = truth = None
    site_drawn = in_site or scene.frame == "site"  # the panel's metres are the site frame's
    if scene.marks is not None:
        m = scene.marks
        if scene.frame == "site":  # estimates and truth in one frame: the error with no fit
            est, truth = m.estimate_xy, m.truth_xy
        else:
            est = se2_apply(m.site_from_output, m.estimate_xy) if in_site else m.estimate_xy
            truth = m.truth_xy if in_site else site_to_frame(m.site_from_output, m.truth_xy)
    # control points and anchors are site positions: drawn where the panel's frame has them
    to_panel = None if site_drawn else scene.site_from_output
    control = _site_points(scene.control_points, site_drawn, to_panel)
    anchors = _site_points(scene.anchors, site_drawn, to_panel)
    # a reference map's places (site positions; a survey placed on one is in the site frame)
    ref_places = np.unique(scene.reference_xy, axis=0) if len(scene.reference_xy) and site_drawn else None
    plan_box = np.array([[0.0, 0.0], [floor_plan.width_m, floor_plan.height_m]]) if floor_plan is not None else None
    w, h = size_px
    pic = Picture(size_px, title_lines=_title(scene, floor_plan, in_site), legend_x=int(0.685 * w),
                  frame="site" if in_site else scene.frame)
    top = 16 + 20 * len(pic.title_lines)
    right = int(0.665 * w)
    bottom = h - 30 - (INSET_STRIP_PX if others else 0)
    panel = pic.panel((62, top, right, bottom), bounds_of(*lines, truth, plan_box, control[1], anchors[1], ref_places))
    legend = pic.legend

    if floor_plan is not None:
        panel.floor_plan(floor_plan)
        legend.append(LegendEntry(
            f"floor plan {floor_plan.path.name} ({floor_plan.width_m:.0f} x {floor_plan.height_m:.0f} m)",
            (235, 235, 235), "box"))
    n_drawn, n_edges = len(scene.edge_xy), sum(scene.edge_counts)
    if n_drawn:
        seg = move(scene.edge_xy.reshape(-1, 2)).reshape(-1, 2, 2)
        for k in range(3):
            panel.faint_segments(seg[scene.edge_state == k], EDGE_COLOURS[k], alpha=0.18)
    for k, name in enumerate(EDGE_NAMES):
        if scene.edge_counts[k]:
            legend.append(LegendEntry(f"WiFi edges {name}: {scene.edge_counts[k]:,}", _faint(EDGE_COLOURS[k]), width=2))
    if n_edges:
        shown = "all drawn" if n_drawn == n_edges else f"{n_drawn:,} drawn"
        legend[-1].text += f" (of {n_edges:,}; {shown})"

    if ref_places is not None:  # under the walks that were placed on them
        panel.points(ref_places, REFERENCE, radius=2, kind="square", outline=REFERENCE)
        legend.append(LegendEntry(f"reference map {scene.reference_map}: {len(scene.reference_xy):,} fingerprints at "
                                  f"{len(ref_places):,} places (held)", REFERENCE, "square"))
    if est is not None and truth is not None:  # under the walks: big errors must not hide them
        panel.faint_segments(np.stack([est, truth], axis=1), MAGENTA, alpha=0.45)
    n_walks = len(scene.tracks)
    width = 2 if n_walks <= 40 else 1
    panel.polylines(lines, colours, width=width)
    component = {sid: k for k, walks, _ in others for sid in walks}
    if n_walks <= MAX_LEGEND_WALKS:
        legend += [LegendEntry(s + (" (reference)" if s == scene.reference else "")
                               + (f" (component {component[s]})" if s in component else ""), scene.colours[s], width=4)
                   for s in scene.tracks]
    else:
        legend.append(LegendEntry(
            f"{len(ids)} walks of the main map, one colour each" + (" (the other components' in the strip below)"
                                                                    if others else ""),
            colours[0] if colours else GREY, width=4))

    if scene.reference in ids and len(scene.tracks[scene.reference]):
        ref = lines[ids.index(scene.reference)]
        panel.polylines([ref], [BLACK], width=1)  # thin, on top: marks the walk without hiding others
        panel.points(ref[:1], BLACK, radius=11, kind="star")
        where = "" if in_site or scene.frame == "site" else ", starts at the origin"
        legend.append(LegendEntry(f"reference {scene.reference} (thin black line{where})", BLACK, "star"))

    if scene.marks is not None and est is not None and truth is not None:
        tie = np.isin(np.asarray(scene.marks.ids, dtype=object), list(scene.control_points)) \
            if scene.marks.ids and scene.control_points else np.zeros(len(est), bool)
        if (~tie).any():  # the landmarks (evaluation only); a control point's marks are drawn with it below
            panel.points(truth[~tie], BLACK, radius=4, kind="cross")
            panel.points(est[~tie], MAGENTA, radius=2)
            legend.append(LegendEntry("landmark truth (evaluation only)", BLACK, "cross"))
            mean = (f"{float(np.linalg.norm(est[~tie] - truth[~tie], axis=1).mean()):.2f} m mean, site frame, no fit"
                    if scene.frame == "site" else f"{scene.marks.stats.mean_m:.2f} m mean")
            legend.append(LegendEntry(f"landmark estimate and error line ({mean})", MAGENTA, "point"))
        if tie.any():
            panel.points(est[tie], CONTROL, radius=3)
    if len(control[0]):
        panel.points(control[1], CONTROL, radius=8, kind="diamond", outline=BLACK)
        legend.append(LegendEntry(
            f"{len(control[0])} control point{'s' if len(control[0]) != 1 else ''} (given, site frame: the walks "
            "marking one are tied there); the dots: its marks", CONTROL, "diamond"))
    if len(anchors[0]):
        panel.points(anchors[1], ANCHOR, radius=7, kind="square", outline=BLACK)
        _labels(panel, anchors)
        legend.append(LegendEntry(
            f"{len(anchors[0])} UWB anchor{'s' if len(anchors[0]) != 1 else ''} (site frame: their ranges place "
            "the main map)", ANCHOR, "square"))
    if scene.frame == "earth":
        north = se2_apply(np.array([0.0, 0.0, T[2]]), np.array([[0.0, 1.0]]))[0] if in_site and T is not None \
            else np.array([0.0, 1.0])
        _north_arrow(panel, north)
        legend.append(LegendEntry(
            "north arrow: the main map is east/north (x east, y north, from the phones' headings)"
            + ("; turned here by the landmark fit" if in_site else ": north-up"), kind="text"))
    legend += _component_entries(scene, others, len(ids))
    legend += _unaligned_entries(scene.unaligned)
    panel.scale_bar()
    if others:
        _component_strip(pic, scene, others, (62, bottom + 42, right, h - 12))
    return pic


def _site_points(
    points: Mapping[str, tuple[float, float]], site_drawn: bool, site_from_panel: NDArray | None
) -> tuple[list[str], NDArray[np.float64]]:
    """(ids, (N, 2) panel metres) of site positions: as they are when the panel is drawn in the site
    frame, else through the landmark fit; none without it."""
    ids = list(points)
    xy = np.array([points[k] for k in ids], float).reshape(-1, 2)
    if site_drawn:
        return ids, xy
    if site_from_panel is None:
        return [], np.zeros((0, 2))
    return ids, site_to_frame(np.asarray(site_from_panel, float), xy)


def _labels(panel: Any, points: tuple[list[str], NDArray], max_labels: int = 24) -> None:
    """Each point's id beside it (none when there are more than ``max_labels``)."""
    from graphslam.io.canvas import font

    ids, xy = points
    if len(ids) > max_labels:
        return
    f = font(11)
    for k, (x, y) in zip(ids, panel.px(xy).tolist()):
        panel.draw.text((x + 9, y - 7), k, fill=BLACK, font=f)


def _north_arrow(panel: Any, north: NDArray) -> None:
    """An arrow pointing north (unit vector ``north`` in the panel's metres), top right, with an N."""
    from graphslam.io.canvas import font

    w, _ = panel.image.size
    c = np.array([w - 34.0, 52.0])  # pixel centre (y down)
    d = np.array([north[0], -north[1]]) / max(float(np.hypot(*north)), 1e-9)
    tip, tail = c + 22 * d, c - 22 * d
    n = np.array([-d[1], d[0]])
    panel.draw.ellipse([c[0] - 30, c[1] - 30, c[0] + 30, c[1] + 30], fill=(255, 255, 255), outline=GREY)
    panel.draw.line([tuple(tail), tuple(tip)], fill=BLACK, width=3)
    panel.draw.polygon([tuple(tip), tuple(tip - 10 * d + 6 * n), tuple(tip - 10 * d - 6 * n)], fill=BLACK)
    f = font(13)
    label = c - 13 * d  # the N beside the shaft, on the tail's half
    panel.draw.text((label[0] + 8 * n[0] - 4, label[1] + 8 * n[1] - 8), "N", fill=BLACK, font=f)


def _component_strip(pic: Picture, scene: SurveyScene, others: list[tuple[int, tuple[str, ...], str]],
                     box: tuple[int, int, int, int]) -> None:
    """The largest other components, a small panel each (own frame, own scale), side by side in ``box``."""
    from graphslam.io.canvas import font

    x0, y0, x1, y1 = box
    shown = sorted(others, key=lambda c: (-len(c[1]), -sum(len(scene.tracks[s]) for s in c[1]), c[0]))[:MAX_INSETS]
    n_rest = len(others) - len(shown)
    head = ("other components, each in a frame of its own (placement relative to the main map unknown; "
            "not in the radio map)" + (f"; the {len(shown)} largest drawn" if n_rest else ""))
    pic.caption((x0, y0 - 20), head, size=12)
    gap = 12
    width = min(330, (x1 - x0 - gap * (len(shown) - 1)) // max(len(shown), 1))
    f = font(12)
    for n, (k, walks, _) in enumerate(shown):
        left = x0 + n * (width + gap)
        lines = [scene.tracks[s] for s in walks]
        inset = pic.panel((left, y0, left + width, y1), bounds_of(*lines), tick_labels=False)
        inset.polylines(lines, [scene.colours[s] for s in walks], width=2)
        label = f"component {k}: {len(walks)} walk{'s' if len(walks) != 1 else ''} (own frame)"
        while f.getlength(label) > width - 10 and " " in label:
            label = label.rsplit(" ", 1)[0]  # a narrow panel: "component k: n walks"
        inset.draw.rectangle([2, 2, 8 + f.getlength(label), 20], fill=(255, 255, 255))
        inset.draw.text((5, 4), label, fill=BLACK, font=f)
        inset.scale_bar()


def _component_entries(
    scene: SurveyScene, others: list[tuple[int, tuple[str, ...], str]], n_main: int
) -> list[LegendEntry]:
    """Which walks stand apart from the main map and why: one entry per reason (components, walks)."""
    if not others:
        return []
    n_other = sum(len(w) for _, w, _ in others)
    out = [LegendEntry(f"main map (component 0, the radio map's walks): {n_main} walks; {n_other} walks in "
                       f"{len(others)} other component{'s' if len(others) != 1 else ''} stand apart, each in its "
                       "own frame (the strip below):", kind="text")]
    groups: dict[str, list[tuple[int, tuple[str, ...], str]]] = {}
    for c in others:  # by the reason's words: its figures in brackets differ per component (report.json)
        groups.setdefault(c[2].split(" (")[0].strip() or "not linked to the main map", []).append(c)
    drawn = {c[0] for c in sorted(others, key=lambda c: (-len(c[1]), -sum(len(scene.tracks[s]) for s in c[1]),
                                                         c[0]))[:MAX_INSETS]}
    for j, (why, cs) in enumerate(sorted(groups.items(), key=lambda kv: -sum(len(c[1]) for c in kv[1]))):
        if j == MAX_REASONS:
            out.append(LegendEntry(f"... {len(groups) - j} more reasons (report.json: components)", kind="text"))
            break
        walks = sum(len(c[1]) for c in cs)
        singles = sum(len(c[1]) == 1 for c in cs)
        listed = ", ".join(str(c[0]) for c in cs[:5]) + (f" +{len(cs) - 5} more" if len(cs) > 5 else "")
        out.append(LegendEntry(
            f"{len(cs)} component{'s' if len(cs) != 1 else ''}, {walks} walk{'s' if walks != 1 else ''}"
            + (f" ({singles} of one walk)" if singles and len(cs) > 1 else "")
            + f": {why} (component{'s' if len(cs) != 1 else ''} {listed}"
            + ("; details in report.json)" if any(c[2] != cs[0][2] or " (" in c[2] for c in cs) else ")"),
            GREY, "line", width=2))
    rest = [c for c in others if c[0] not in drawn]
    if rest:
        out.append(LegendEntry(
            f"{len(rest)} smaller components ({sum(len(c[1]) for c in rest)} walks) not drawn "
            "(report.json: components, trajectories.csv)", kind="text"))
    return out


def _faint(c: tuple[int, int, int], a: float = 0.55) -> tuple[int, int, int]:
    r, g, b = (int(255 - (255 - v) * a) for v in c)
    return (r, g, b)


def _site_placers(scene: SurveyScene) -> str:
    """What placed the main map in the site frame, as the title says it."""
    given = ((f"reference map {scene.reference_map}", scene.reference_map), ("control points", scene.control_points),
             ("UWB anchors", scene.anchors))
    placers = [name for name, there in given if there]
    return " and the ".join(placers) if placers else "control points, UWB anchors or a reference map"


def _title(scene: SurveyScene, plan: FloorPlan | None, in_site: bool) -> list[str]:
    others = scene.other_components()
    counts = main_map_counts(scene.n_sessions, len(scene.main_ids()), sum(len(w) for _, w, _ in others), len(others),
                             len(scene.unaligned))
    head = (f"{counts}; {scene.n_poses:,} poses, {sum(scene.edge_counts):,} WiFi edges in the main map"
            + (f"; {scene.landmark_text}" if scene.landmark_text else ""))
    if in_site and scene.site_from_output is not None:
        x, y, th = (float(v) for v in scene.site_from_output)
        frame = (f"site frame of the floor plan: walks placed by the landmark SE(2) fit (x {x:.1f} m, y {y:.1f} m, "
                 f"{np.degrees(th):.1f} deg; display only)")
    else:
        frame = f"{scene.frame} frame (trajectories.csv, metres): " + {
            "earth": "north-up (x east, y north, from the phones' headings), origin = first pose of the reference walk",
            "site": "placed by the " + _site_placers(scene),
        }.get(scene.frame, "origin = first pose of the reference walk, x along its first heading")
        if plan is not None:
            frame += "; the floor plan is NOT registered to it (no landmark fit)"
    return [line for s in [head, frame, *scene.notes] for line in textwrap.wrap(s, 150)]


def _unaligned_entries(unaligned: Mapping[str, str]) -> list[LegendEntry]:
    """One legend entry per reason: how many walks, their ids (the first few)."""
    if not unaligned:
        return []
    groups: dict[str, list[str]] = {}
    for sid, why in unaligned.items():
        groups.setdefault(why, []).append(sid)
    out = [LegendEntry(f"{len(unaligned)} walks not aligned (not drawn):", kind="text")]
    for k, (why, sids) in enumerate(sorted(groups.items(), key=lambda kv: -len(kv[1]))):
        if k == MAX_REASONS:
            out.append(LegendEntry(f"... {len(groups) - k} more reasons (report.json)", kind="text"))
            break
        listed = ", ".join(sids[:4]) + (f" +{len(sids) - 4} more" if len(sids) > 4 else "")
        out.append(LegendEntry(f"{len(sids)}: {why} ({listed})", GREY, "cross"))
    return out
