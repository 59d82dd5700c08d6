"""``track.png`` / ``positions.png``: walks tracked (``graphslam track``) or scans located
(``graphslam locate``) on a radio map, with the truth when the recordings carry it
(``graphslam.io.canvas``: Pillow, fast).

Everything is drawn in the radio map's frame: the estimates as they are, the truth moved
into it by the caller (``graphslam.app.pictures`` knows the frames). Each session has its
own colour (the survey picture's palette); its truth is the same colour, dashed, with thin
grey segments from each estimate to the truth at the same time. The radio map's
fingerprints are faint grey dots: where the map can answer at all.
"""

from __future__ import annotations

import textwrap
from pathlib import Path
from typing import Mapping

import numpy as np
from numpy.typing import NDArray

from graphslam.core.summary import plural
from graphslam.io.canvas import BLACK, LegendEntry, Picture, bounds_of
from graphslam.viz.common import session_colours

SIZE_PX = (1400, 1000)
MAX_LEGEND = 16
MAX_ERROR_SEGMENTS = 5_000
MAP_DOTS = (175, 175, 175)
ERROR = (110, 110, 110)
ANCHOR = (230, 110, 0)  # as survey.png's


def draw_tracks(
    estimates: Mapping[str, NDArray],
    path: str | Path,
    *,
    truth: Mapping[str, NDArray] | None = None,
    truth_at_estimates: Mapping[str, NDArray] | None = None,
    map_xy: NDArray | None = None,
    points: bool = False,
    title: str = "",
    frame: str = "radio map frame",
    frame_name: str = "",
    anchors: Mapping[str, tuple[float, float]] | None = None,
    size_px: tuple[int, int] = SIZE_PX,
) -> Path:
    """Render to the PNG ``path``. ``estimates``: session -> (N, 2) positions in time order (NaN rows:
    no answer, skipped). ``truth``: session -> (M, 2) true path; ``truth_at_estimates``: session ->
    (N, 2) true position at each estimate's time (error segments and the mean error). ``points``:
    draw each estimate as a dot (kNN answers) rather than only a line (a tracked walk). ``frame``: the
    subtitle saying which frame is drawn; ``frame_name``: that frame's name (the radio map's), the
    PNG's ``frame`` text chunk. ``anchors``: UWB anchors (id -> x, y in the drawn frame), marked."""
    ids = list(estimates)
    colours = session_colours(ids)
    lines = [_finite(estimates[s]) for s in ids]
    truths = [_finite(truth[s]) for s in ids if truth and s in truth]
    seg, n_err, err_sum = _errors(ids, estimates, truth_at_estimates)
    err = f"; error vs truth mean {err_sum / n_err:.2f} m over {n_err:,} {'answers' if points else 'steps'}" if n_err else ""
    w, h = size_px
    pic = Picture(size_px, title_lines=textwrap.wrap(title + err, 140) + textwrap.wrap(frame, 140),
                  legend_x=int(0.7 * w), frame=frame_name)
    top = 16 + 20 * len(pic.title_lines)
    anchor_xy = np.array(list((anchors or {}).values()), float).reshape(-1, 2)
    panel = pic.panel((62, top, int(0.68 * w), h - 30), bounds_of(map_xy, *lines, *truths, anchor_xy))
    legend = pic.legend
    if map_xy is not None and len(map_xy):
        panel.dots(map_xy, MAP_DOTS)
        legend.append(LegendEntry(f"radio map fingerprints ({len(map_xy):,})", MAP_DOTS, "point"))
    if len(seg):
        panel.faint_segments(seg[:: max(1, len(seg) // MAX_ERROR_SEGMENTS)], ERROR, alpha=0.45)
        legend.append(LegendEntry("error: estimate to truth at the same time", ERROR, width=1))
    if truth:
        for s in ids:
            if s in truth:
                panel.dashed(truth[s], colours[s], width=2)
        legend.append(LegendEntry("truth (dashed, the session's colour)", BLACK, "dashed", width=2))
    panel.polylines(lines, [colours[s] for s in ids], width=1 if points else 2)
    if points:
        for s, xy in zip(ids, lines):
            panel.dots(xy, colours[s], size=4)
    if len(ids) <= MAX_LEGEND:
        legend += [LegendEntry(s, colours[s], width=4) for s in ids]
    else:
        legend.append(LegendEntry(f"{plural(len(ids), 'session')}, one colour each", colours[ids[0]], width=4))
    if len(anchor_xy):
        panel.points(anchor_xy, ANCHOR, radius=7, kind="square", outline=BLACK)
        legend.append(LegendEntry(f"{plural(len(anchor_xy), 'UWB anchor')}", ANCHOR, "square"))
    starts = [xy[:1] for xy in lines if len(xy)]
    if starts:
        panel.points(np.concatenate(starts), BLACK, radius=6, kind="ring")
        legend.append(LegendEntry("start", BLACK, "ring"))
    panel.scale_bar()
    return pic.save(path)


def _errors(
    ids: list[str], estimates: Mapping[str, NDArray], truth_at: Mapping[str, NDArray] | None
) -> tuple[NDArray, int, float]:
    """(estimate-to-truth segments (E, 2, 2), their number, the sum of their lengths)."""
    if not truth_at:
        return np.zeros((0, 2, 2)), 0, 0.0
    pairs = [np.stack([estimates[s], truth_at[s]], axis=1) for s in ids if s in truth_at]
    seg = np.concatenate(pairs) if pairs else np.zeros((0, 2, 2))
    seg = seg[np.isfinite(seg).all(axis=(1, 2))]
    return seg, len(seg), float(np.linalg.norm(seg[:, 0] - seg[:, 1], axis=1).sum())


def _finite(xy: NDArray) -> NDArray:
    xy = np.asarray(xy, float).reshape(-1, 2)
    return xy[np.isfinite(xy).all(axis=1)]
