"""``track.png`` / ``positions.png``: walks tracked (``graphslam track``) or scans located
(``graphslam locate``) on a radio map, with the truth when the recordings carry it
(matplotlib, headless).

Everything is drawn in the radio map's frame: the estimates as they are, the truth moved
into it by the caller (``graphslam.app.pictures`` knows the frames). Each session has its
own colour (the survey picture's palette); its truth is the same colour, dashed, with thin
grey segments from each estimate to the truth at the same time. The radio map's
fingerprints are faint grey dots: where the map can answer at all.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np
from numpy.typing import NDArray

from graphslam.viz.common import session_colours
from graphslam.viz.figure import fit_limits, new_figure, rgb01, save_png, scale_bar, segments

SIZE_PX = (1400, 1000)
MAX_LEGEND = 16
MAX_ERROR_SEGMENTS = 5_000


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
    size_px: tuple[int, int] = SIZE_PX,
) -> Path:
    """Render to the PNG ``path``. ``estimates``: session -> (N, 2) positions in time order (NaN rows:
    no answer, skipped). ``truth``: session -> (M, 2) true path; ``truth_at_estimates``: session ->
    (N, 2) true position at each estimate's time (error segments and the mean error). ``points``:
    draw each estimate as a dot (kNN answers) rather than only a line (a tracked walk)."""
    from matplotlib.collections import LineCollection
    from matplotlib.lines import Line2D

    ids = list(estimates)
    colours = session_colours(ids)
    rgb = rgb01([colours[s] for s in ids])
    fig = new_figure(*size_px)
    ax = fig.add_axes((0.06, 0.07, 0.62, 0.83))
    handles = []
    extent = []
    if map_xy is not None and len(map_xy):
        ax.scatter(map_xy[:, 0], map_xy[:, 1], s=2, c=[(0.6, 0.6, 0.6)], alpha=0.35, linewidths=0, zorder=1)
        handles.append(Line2D([], [], ls="none", marker="o", ms=3, color=(0.6, 0.6, 0.6),
                              label=f"radio map fingerprints ({len(map_xy):,})"))
        extent.append(map_xy)
    lines = [_finite(estimates[s]) for s in ids]
    ax.add_collection(LineCollection(lines, colors=rgb, linewidths=0.8 if points else 1.6, zorder=3,
                                     alpha=0.6 if points else 1.0))
    if points:
        xy = np.concatenate(lines) if lines else np.zeros((0, 2))
        c = np.repeat(rgb, [len(v) for v in lines], axis=0)
        ax.scatter(xy[:, 0], xy[:, 1], s=9, c=c, linewidths=0, zorder=4)
    extent += lines
    n_err, err_sum = 0, 0.0
    if truth:
        tl = [_finite(truth[s]) for s in ids if s in truth]
        tc = rgb[[k for k, s in enumerate(ids) if s in truth]]
        ax.add_collection(LineCollection(tl, colors=tc, linewidths=1.0, linestyles=(0, (4, 3)), zorder=2))
        handles.append(Line2D([], [], color="black", lw=1.0, ls=(0, (4, 3)), label="truth (dashed, same colour)"))
        extent += tl
    if truth_at_estimates:
        seg = []
        for s in ids:
            if s in truth_at_estimates:
                pair = np.stack([estimates[s], truth_at_estimates[s]], axis=1)
                pair = pair[np.isfinite(pair).all(axis=(1, 2))]
                seg.append(pair)
                n_err += len(pair)
                err_sum += float(np.linalg.norm(pair[:, 0] - pair[:, 1], axis=1).sum())
        seg_all = np.concatenate(seg) if seg else np.zeros((0, 2, 2))
        step = max(1, len(seg_all) // MAX_ERROR_SEGMENTS)
        segments(ax, seg_all[::step], (0.35, 0.35, 0.35), lw=0.5, alpha=0.5, zorder=2.5)
        if n_err:
            handles.append(Line2D([], [], color=(0.35, 0.35, 0.35), lw=0.8, label="error: estimate to truth"))
    if len(ids) <= MAX_LEGEND:
        handles += [Line2D([], [], color=c, lw=2.5, marker="o" if points else None, ms=4, label=s) for s, c in zip(ids, rgb)]
    else:
        handles.append(Line2D([], [], color=rgb[0], lw=2.5, label=f"{len(ids)} sessions, one colour each"))
    starts = np.array([v[0] for v in lines if len(v)])
    if len(starts):
        ax.scatter(starts[:, 0], starts[:, 1], marker="o", s=40, facecolors="none", edgecolors="black", zorder=5)
        handles.append(Line2D([], [], ls="none", marker="o", mfc="none", mec="black", label="start"))
    span = fit_limits(ax, np.concatenate(extent) if extent else np.zeros((0, 2)))
    scale_bar(ax, span)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(alpha=0.2)
    err = f"; error vs truth mean {err_sum / n_err:.2f} m over {n_err:,} {'answers' if points else 'steps'}" if n_err else ""
    ax.set_title((title + err) + f"\n{frame}", fontsize=11, loc="left")
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8.5, frameon=False,
              borderaxespad=0.0)
    return save_png(fig, path)


def _finite(xy: NDArray) -> NDArray:
    xy = np.asarray(xy, float).reshape(-1, 2)
    return xy[np.isfinite(xy).all(axis=1)]
