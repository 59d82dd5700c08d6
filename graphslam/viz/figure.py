"""Matplotlib helpers shared by the PNG pictures: a figure of an exact pixel size (Agg, no
pyplot state), the floor plan underneath, a scale bar, atomic saving.

Pictures draw every walk / edge set as one vectorised collection, never one artist per item:
200 walks or 20,000 edges cost one ``draw`` call each.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np
from numpy.typing import NDArray

from graphslam.errors import InputError
from graphslam.io.atomic import atomic_open
from graphslam.viz.common import FloorPlan

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

DPI = 100


def new_figure(width_px: int, height_px: int) -> "Figure":
    """A figure of exactly ``width_px`` x ``height_px`` pixels, drawn by Agg (headless; no pyplot,
    so no global figure registry to leak into and nothing to close)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_px / DPI, height_px / DPI), dpi=DPI)
    FigureCanvasAgg(fig)
    return fig


def save_png(fig: "Figure", path: str | Path) -> Path:
    """Write ``fig`` as PNG atomically (complete or absent). The size is the figure's, exactly."""
    with atomic_open(path, "wb") as fh:
        fig.savefig(fh, format="png", dpi=DPI)
    return Path(path)


def rgb01(colours: Sequence[tuple[int, int, int]]) -> NDArray[np.float64]:
    return np.asarray(colours, float).reshape(-1, 3) / 255.0


def draw_floor_plan(ax: "Axes", plan: FloorPlan, out_from_site: NDArray | None = None) -> None:
    """The plan image under everything: it spans x in [0, W], y in [0, H] of the site frame (top
    row at y = H); ``out_from_site`` (x, y, theta) places it in the frame the axes draw."""
    from matplotlib.image import imread
    from matplotlib.transforms import Affine2D

    try:
        img = imread(str(plan.path))
    except Exception as e:  # PIL / matplotlib raise many types for a damaged image
        raise InputError(plan.path, f"cannot read the floor plan image ({e})") from None
    im = ax.imshow(img, extent=(0.0, plan.width_m, 0.0, plan.height_m), origin="upper", zorder=0, alpha=0.85,
                   interpolation="antialiased")
    if out_from_site is not None:
        x, y, th = (float(v) for v in out_from_site)
        im.set_transform(Affine2D().rotate(th).translate(x, y) + ax.transData)


def nice_length(span: float) -> float:
    """1, 2 or 5 times a power of ten, about a fifth of ``span``."""
    if not span > 0 or not math.isfinite(span):
        return 1.0
    target = span / 5.0
    p = 10.0 ** math.floor(math.log10(target))
    return max(m * p for m in (1.0, 2.0, 5.0) if m * p <= target)


def scale_bar(ax: "Axes", span_m: float) -> float:
    """A black bar of a round length in metres, lower left inside the axes; returns its length."""
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    length = nice_length(span_m)
    label = f"{length:g} m" if length >= 1 else f"{length * 100:g} cm"
    bar = AnchoredSizeBar(ax.transData, length, label, "lower left", pad=0.6, borderpad=0.8, sep=4,
                          frameon=True, size_vertical=0, fontproperties={"size": 10})
    bar.patch.set_alpha(0.8)
    ax.add_artist(bar)
    return length


def fit_limits(ax: "Axes", xy: NDArray, margin: float = 0.04) -> float:
    """Equal-aspect limits around the finite points ``xy``, widened to the axes box's own aspect
    (so nothing is re-fitted at draw time); returns the larger data span (m)."""
    xy = np.asarray(xy, float).reshape(-1, 2)
    xy = xy[np.isfinite(xy).all(axis=1)]
    lo, hi = (xy.min(axis=0), xy.max(axis=0)) if len(xy) else (np.array([-1.0, -1.0]), np.array([1.0, 1.0]))
    span = float(max(hi - lo)) or 1.0
    half = (hi - lo) / 2.0 + margin * span + 0.5
    centre = (lo + hi) / 2.0
    box = ax.get_position(original=True)  # the box as laid out, not as an earlier aspect shrank it
    w_px, h_px = box.width * ax.figure.get_figwidth(), box.height * ax.figure.get_figheight()
    ratio = h_px / w_px  # data height per data width that fills the box at equal scale
    if half[1] / half[0] < ratio:
        half[1] = half[0] * ratio
    else:
        half[0] = half[1] / ratio
    ax.set_xlim(centre[0] - half[0], centre[0] + half[0])
    ax.set_ylim(centre[1] - half[1], centre[1] + half[1])
    ax.set_aspect("equal", adjustable="box")
    return span


def segments(ax: "Axes", seg: NDArray, colour: Sequence[float], *, lw: float, alpha: float, zorder: float) -> None:
    """Line segments ``seg`` (E, 2, 2) as ONE path (move-to / line-to pairs): one draw call however
    many there are, unlike a collection with one path per segment."""
    from matplotlib.patches import PathPatch
    from matplotlib.path import Path as MplPath

    seg = np.asarray(seg, float).reshape(-1, 2, 2)
    if not len(seg):
        return
    codes = np.tile(np.array([MplPath.MOVETO, MplPath.LINETO], np.uint8), len(seg))
    path = MplPath(seg.reshape(-1, 2), codes)
    # add_artist, not add_patch: add_patch walks every segment in Python to update the data limits
    ax.add_artist(PathPatch(path, fill=False, edgecolor=colour, linewidth=lw, alpha=alpha, zorder=zorder))
