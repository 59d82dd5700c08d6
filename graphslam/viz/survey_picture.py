"""``survey.png``: the aligned survey at a glance (matplotlib, headless).

Every aligned walk in its own colour (the colours of the Rerun views), the reference walk
marked at its first pose (the origin of the output frame), the WiFi edges faint by their
final state, landmark truth / estimate / error when the recordings have marks, a scale bar,
and the floor plan underneath when one is given. Unaligned walks are listed in the legend,
grouped by their reason.

Frames: the picture is drawn in the output frame (trajectories.csv) unless a floor plan is
given and the landmarks gave a site-from-output fit: then everything is drawn in the plan's
site frame through that fit (display only; the subtitle says which).

Two sources, one ``SurveyScene``: ``scene_of_alignment`` (in memory, by ``graphslam survey``)
and ``scene_of_folder`` (a finished output folder, by ``graphslam plot``).
"""

from __future__ import annotations

import json
import textwrap
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from graphslam.config import GraphSlamConfig
from graphslam.core.radiomap.survey_maps import WifiEdgeRows, crowdsourced_edges
from graphslam.core.survey.align import Alignment
from graphslam.core.survey.evaluate import Evaluation
from graphslam.core.survey.initialise import se2_apply
from graphslam.core.types import Survey
from graphslam.errors import InputError, VisualizationError
from graphslam.viz.common import (
    FloorPlan, LandmarkMarks, fitted_site_from_aligned, landmark_marks, session_colours, site_to_frame,
)
from graphslam.viz.figure import draw_floor_plan, fit_limits, new_figure, rgb01, save_png, scale_bar, segments

if TYPE_CHECKING:
    from matplotlib.figure import Figure

SIZE_PX = (1600, 1000)
MAX_EDGES = 20_000  # drawn; more are subsampled (deterministically), the legend gives both counts
MAX_LEGEND_WALKS = 16  # more aligned walks: one legend line for all (the colours still differ)
MAX_REASONS = 6  # unaligned walks are grouped by reason; at most this many groups listed
EDGE_COLOURS = ((0.27, 0.67, 0.35), (1.0, 0.63, 0.0), (0.86, 0.16, 0.16))  # inactive, ramp, saturated (as Rerun)
EDGE_NAMES = ("inactive", "ramp", "saturated")


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


def scene_of_alignment(
    survey: Survey, al: Alignment, cfg: GraphSlamConfig, evaluation: Evaluation | None = None,
    *, max_edges: int = MAX_EDGES,
) -> SurveyScene:
    """The scene of a survey just aligned (``graphslam survey``)."""
    tracks = {sid: np.asarray(tr.xy) for sid, tr in al.tracks.items()}
    xy = al.fingerprint_xy()
    rows_xy = xy[np.isfinite(xy).all(axis=1)]
    marks = landmark_marks(al.tracks, survey)
    T = marks.site_from_output if marks is not None else None
    if T is None and evaluation is not None and evaluation.steps.n:  # fitted on true poses (simulations)
        T = np.asarray(evaluation.site_from_aligned, float)
    return _scene(
        tracks, al.session_ids, al.reference, dict(al.unaligned), rows_xy, crowdsourced_edges(al, cfg), marks, T,
        _landmark_text(marks.stats.as_dict() if marks is not None else None), survey.n_steps, max_edges, (),
    )


def scene_of_folder(
    out_dir: str | Path, recordings: Sequence[str | Path] = (), *, max_edges: int = MAX_EDGES
) -> SurveyScene:
    """The scene of a finished ``graphslam survey --out`` folder (``graphslam plot``).

    Needs ``trajectories.csv``; uses ``report.json`` (reference, unaligned walks and reasons,
    the landmark fit), ``radio_map.parquet`` + ``wifi_edges.parquet`` (edges) when present.
    ``recordings`` add the landmark marks and the walks that were not aligned.
    """
    from graphslam.io.csv_io import read_trajectories

    d = Path(out_dir)
    if not d.is_dir():
        raise InputError(d, "not a folder (expected a `graphslam survey --out` folder)")
    if not (d / "trajectories.csv").exists():
        raise InputError(d, "no trajectories.csv: not a finished survey output folder")
    pose_tracks = read_trajectories(d / "trajectories.csv")
    if not pose_tracks:
        raise InputError(d / "trajectories.csv", "no aligned walk in the file")
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
    rows_xy, edges = np.zeros((0, 2)), None
    if (d / "wifi_edges.parquet").exists() and (d / "radio_map.parquet").exists():
        from graphslam.io.edges_io import read_wifi_edges
        from graphslam.io.radiomap_io import read_radio_map

        rows_xy = np.asarray(read_radio_map(d / "radio_map.parquet").xy)
        edges = read_wifi_edges(d / "wifi_edges.parquet", len(rows_xy))
    else:
        notes.append("WiFi edges not shown: no wifi_edges.parquet + radio_map.parquet in the folder")
    marks = landmark_marks(pose_tracks, survey)
    ev = report.get("evaluation") if isinstance(report.get("evaluation"), dict) else {}
    T = marks.site_from_output if marks is not None else None
    if T is None:
        T = fitted_site_from_aligned(ev)
    lm = marks.stats.as_dict() if marks is not None else ev.get("landmarks")
    n_poses = int(report.get("nodes") or sum(len(t) for t in pose_tracks.values()))
    return _scene(
        {sid: np.asarray(t.xy) for sid, t in pose_tracks.items()}, ids, reference, unaligned, rows_xy, edges,
        marks, T, _landmark_text(lm), n_poses, max_edges, tuple(notes),
    )


def _scene(
    tracks: dict[str, NDArray], ids: Sequence[str], reference: str, unaligned: dict[str, str], rows_xy: NDArray,
    edges: WifiEdgeRows | None, marks: LandmarkMarks | None, T: NDArray | None, landmark_text: str, n_poses: int,
    max_edges: int, notes: tuple[str, ...],
) -> SurveyScene:
    if edges is None or not len(edges.a):
        seg, state, counts = np.zeros((0, 2, 2)), np.zeros(0, np.int8), (0, 0, 0)
    else:
        counts = tuple(int(c) for c in np.bincount(edges.state, minlength=3)[:3])
        pick = np.arange(len(edges.a))
        if len(pick) > max_edges:  # same sample every time: the picture of a survey does not flicker
            pick = np.sort(np.random.default_rng(0).choice(len(pick), max_edges, replace=False))
        seg = np.stack([rows_xy[edges.a[pick]], rows_xy[edges.b[pick]]], axis=1)
        state = edges.state[pick]
    return SurveyScene(
        tracks, session_colours(ids), reference, unaligned, seg, state, counts, marks, T, landmark_text,  # type: ignore[arg-type]
        len(ids), n_poses, notes,
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
    return save_png(survey_figure(scene, floor_plan=floor_plan, size_px=size_px), path)


def survey_figure(scene: SurveyScene, *, floor_plan: FloorPlan | None = None, size_px: tuple[int, int] = SIZE_PX) -> "Figure":
    """The picture as a matplotlib ``Figure`` (Agg canvas): one axes, its legend outside on the right."""
    from matplotlib.collections import LineCollection
    from matplotlib.lines import Line2D

    T = scene.site_from_output
    in_site = floor_plan is not None and T is not None
    move = (lambda xy: se2_apply(T, xy)) if in_site else (lambda xy: xy)  # noqa: E731
    fig = new_figure(*size_px)
    ax = fig.add_axes((0.05, 0.06, 0.62, 0.84))
    handles: list[Any] = []

    if floor_plan is not None:
        draw_floor_plan(ax, floor_plan)
        handles.append(Line2D([], [], ls="none", marker="s", ms=9, mfc=(0.9, 0.9, 0.9), mec="grey",
                              label=f"floor plan {floor_plan.path.name} ({floor_plan.width_m:.0f} x {floor_plan.height_m:.0f} m)"))

    n_drawn = len(scene.edge_xy)
    if n_drawn:
        seg = move(scene.edge_xy.reshape(-1, 2)).reshape(-1, 2, 2)
        for k in range(3):  # one compound path per state: 20,000 segments are one draw call
            segments(ax, seg[scene.edge_state == k], EDGE_COLOURS[k], lw=0.4, alpha=0.22, zorder=1)
    n_edges = sum(scene.edge_counts)
    if n_edges:
        shown = "" if n_drawn == n_edges else f", {n_drawn:,} drawn"
        for k, name in enumerate(EDGE_NAMES):
            if scene.edge_counts[k]:
                handles.append(Line2D([], [], color=EDGE_COLOURS[k], lw=1.5, alpha=0.6,
                                      label=f"WiFi edges {name}: {scene.edge_counts[k]:,}"))
        handles[-1].set_label(handles[-1].get_label() + f" (of {n_edges:,}{shown})")

    ids = list(scene.tracks)
    lines = [move(scene.tracks[s]) for s in ids]
    rgb = rgb01([scene.colours[s] for s in ids])
    lw = 1.6 if len(ids) <= 40 else 1.0
    ax.add_collection(LineCollection(lines, colors=rgb, linewidths=lw, zorder=3, capstyle="round", joinstyle="round"))
    if len(ids) <= MAX_LEGEND_WALKS:
        handles += [Line2D([], [], color=c, lw=2.5, label=s + (" (reference)" if s == scene.reference else ""))
                    for s, c in zip(ids, rgb)]
    else:
        handles.append(Line2D([], [], color=rgb[0], lw=2.5, label=f"{len(ids)} aligned walks, one colour each"))

    if scene.reference in scene.tracks and len(scene.tracks[scene.reference]):
        ref = lines[ids.index(scene.reference)]
        # a thin line on top: marks the reference without hiding the walks under it
        ax.plot(ref[:, 0], ref[:, 1], color="black", lw=0.6, zorder=3.5)
        ax.plot([ref[0, 0]], [ref[0, 1]], marker="*", ms=18, color="black", mec="white", mew=1.2, zorder=6, ls="none")
        where = "" if in_site else ", starts at the origin"
        handles.append(Line2D([], [], marker="*", ms=13, color="black", mec="white", lw=0.6,
                              label=f"reference {scene.reference} (black line{where})"))

    extent = [np.concatenate(lines)] if lines else []
    if scene.marks is not None:
        m = scene.marks
        est = se2_apply(m.site_from_output, m.estimate_xy) if in_site else m.estimate_xy
        truth = m.truth_xy if in_site else site_to_frame(m.site_from_output, m.truth_xy)
        segments(ax, np.stack([est, truth], axis=1), (0.85, 0.0, 0.85), lw=0.9, alpha=1.0, zorder=4)
        ax.scatter(truth[:, 0], truth[:, 1], s=28, marker="x", c="black", linewidths=1.2, zorder=5)
        ax.scatter(est[:, 0], est[:, 1], s=12, c=[(0.85, 0.0, 0.85)], zorder=5)
        handles.append(Line2D([], [], ls="none", marker="x", color="black", label="landmark truth"))
        handles.append(Line2D([], [], color=(0.85, 0.0, 0.85), marker="o", ms=4, lw=0.9,
                              label=f"landmark estimate, error line ({m.stats.mean_m:.2f} m mean)"))
        extent.append(truth)

    handles += _unaligned_handles(scene.unaligned)
    if floor_plan is not None:
        extent.append(np.array([[0.0, 0.0], [floor_plan.width_m, floor_plan.height_m]]))
    span = fit_limits(ax, np.concatenate(extent) if extent else np.zeros((0, 2)))
    scale_bar(ax, span)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(alpha=0.2, zorder=0)
    ax.set_title(_title(scene, floor_plan, in_site), fontsize=11, loc="left")
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8.5, frameon=False,
              borderaxespad=0.0, handlelength=2.2)
    return fig


def _title(scene: SurveyScene, plan: FloorPlan | None, in_site: bool) -> str:
    n_al = len(scene.tracks)
    head = (f"{n_al}/{scene.n_sessions} walks aligned, {scene.n_poses:,} poses, {sum(scene.edge_counts):,} WiFi edges"
            + (f"; {scene.landmark_text}" if scene.landmark_text else ""))
    if in_site:
        x, y, th = scene.site_from_output  # type: ignore[misc]
        frame = (f"site frame of the floor plan: walks placed by the landmark SE(2) fit (x {x:.1f} m, y {y:.1f} m, "
                 f"{np.degrees(th):.1f} deg; display only)")
    else:
        frame = "output frame (trajectories.csv): origin = first pose of the reference walk"
        if plan is not None:
            frame += "; the floor plan is NOT registered to it (no landmark fit)"
    lines = [head, frame] + list(scene.notes)
    return "\n".join(textwrap.fill(s, 130) for s in lines)


def _unaligned_handles(unaligned: Mapping[str, str]) -> list[Any]:
    """One legend entry per reason: how many walks, their ids (the first few)."""
    from matplotlib.lines import Line2D

    if not unaligned:
        return []
    groups: dict[str, list[str]] = {}
    for sid, why in unaligned.items():
        groups.setdefault(why, []).append(sid)
    out = [Line2D([], [], ls="none", label=f"{len(unaligned)} walks not aligned (not drawn):")]
    for k, (why, sids) in enumerate(sorted(groups.items(), key=lambda kv: -len(kv[1]))):
        if k == MAX_REASONS:
            out.append(Line2D([], [], ls="none", label=f"  ... {len(groups) - k} more reasons (report.json)"))
            break
        listed = ", ".join(sids[:4]) + (f" +{len(sids) - 4} more" if len(sids) > 4 else "")
        text = textwrap.fill(f"{len(sids)}: {why} ({listed})", 60, subsequent_indent="   ")
        out.append(Line2D([], [], ls="none", marker="x", color="grey", label=text))
    return out


# ---- survey.png beside the survey's outputs --------------------------------------------------

PICTURE = "survey.png"


def warm_matplotlib() -> None:
    """Import what ``draw_survey`` uses and load its font: the fixed ~0.5 s a first picture costs."""
    import matplotlib.backends.backend_agg  # noqa: F401
    import matplotlib.collections  # noqa: F401
    import matplotlib.image  # noqa: F401
    import matplotlib.lines  # noqa: F401
    import matplotlib.patches  # noqa: F401
    import mpl_toolkits.axes_grid1.anchored_artists  # noqa: F401

    fig = new_figure(40, 20)
    fig.text(0.1, 0.1, "m")
    fig.canvas.draw()


class SurveyPictureJob:
    """``survey.png`` for ``graphslam survey``, drawn so that it does not slow the survey down.

    Made at the survey's start, it forks a worker that imports matplotlib while the survey
    reads and aligns (``WarmWorker``); ``draw`` sends it the scene (a few MB for 200 walks)
    and it draws into a hidden file while the outputs are written; ``finish`` renames that
    file to ``survey.png`` once the other outputs are in place (``discard`` removes it when
    they could not be written: a failed survey leaves no picture).
    """

    def __init__(self, out_dir: str | Path, floor_plan: FloorPlan | None = None) -> None:
        import os

        from graphslam.viz.background import WarmWorker

        self.path = Path(out_dir) / PICTURE
        self._tmp = self.path.with_name(f".{PICTURE}.{os.getpid()}.{id(self):x}.part")
        self._plan = floor_plan
        self._worker = WarmWorker(warm_matplotlib)

    def draw(self, survey: Survey, al: Alignment, cfg: GraphSlamConfig, evaluation: Evaluation | None) -> None:
        self._worker.submit(_draw_timed, scene_of_alignment(survey, al, cfg, evaluation), self._tmp, self._plan)

    def finish(self) -> tuple[Path, float]:
        """(survey.png, seconds the worker spent drawing); ``VisualizationError`` if it failed."""
        try:
            seconds = self._worker.wait()
            self._tmp.replace(self.path)
        except OSError as e:
            self.discard()
            raise VisualizationError(f"{self.path}: cannot write ({e.strerror or e})") from None
        except BaseException:
            self.discard()
            raise
        return self.path, seconds

    def discard(self) -> None:
        self._worker.close()
        self._tmp.unlink(missing_ok=True)


def _draw_timed(scene: SurveyScene, path: Path, plan: FloorPlan | None) -> float:
    import time

    t = time.perf_counter()
    draw_survey(scene, path, floor_plan=plan)
    return time.perf_counter() - t
