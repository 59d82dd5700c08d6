"""magnetic_map.png: the main map's magnetic field, a heatmap per feature (Pillow, ``graphslam.io.canvas``).

Two panels: the field's magnitude |B| and its vertical component B_up (µT, each walk's offset removed),
kernel-smoothed on a grid over the samples (blank where no walk passed), with the samples as dots, a
colour bar, metre axes and a scale bar. The colour range is the 2nd-98th percentile of the map: what
matters is the variation from place to place, not the absolute level.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np
from numpy.typing import NDArray

from graphslam.core.radiomap.field import MIN_WEIGHT, FieldGrid, grid_cell_m
from graphslam.core.radiomap.magnetic_map import MagneticMap
from graphslam.core.common.geometry import se2_apply
from graphslam.errors import ConfigError
from graphslam.io.canvas import VIRIDIS, Picture, colour_map
from graphslam.viz.common import FloorPlan

MAGNETIC_PNG = "magnetic_map.png"
SIZE_PX = (1600, 760)
PANELS = ((0, "magnitude |B|"), (2, "vertical component B_up"))


def magnetic_map_picture(
    mm: MagneticMap, *, floor_plan: FloorPlan | None = None, site_from_map: NDArray | None = None,
    size_px: tuple[int, int] = SIZE_PX,
) -> Picture:
    """The picture (module docstring); ``site_from_map`` draws a map that is not in the site frame over a
    ``floor_plan`` that is."""
    if not len(mm):
        raise ConfigError("magnetic map picture: the magnetic map has no sample")
    T = None if site_from_map is None or floor_plan is None else np.asarray(site_from_map, float).reshape(3)
    xy = se2_apply(T, np.asarray(mm.xy, float)) if T is not None else np.asarray(mm.xy, float)
    frame = f"{mm.frame} frame"
    if floor_plan is not None:
        frame = "site frame of the floor plan" if T is not None or mm.frame == "site" else (
            f"{mm.frame} frame, floor plan NOT registered to it")
    cell = grid_cell_m(xy)
    h = 1.5 * cell
    grid = FieldGrid(xy, cell)
    weight = grid.smooth(grid.bin(np.ones(len(xy))), h)
    outside = weight < MIN_WEIGHT
    pic = Picture(size_px, title_lines=[
        f"magnetic map: {len(mm):,} samples of {mm.n_walks} walks; {frame}; {cell:g} m cells, Gaussian kernel "
        f"{h:g} m; each walk's device offset removed (µT)"
    ], frame="site" if T is not None else mm.frame)
    w, hgt = size_px
    half = w // 2
    x0, x1, y0, y1 = grid.extent
    for k, (col, name) in enumerate(PANELS):
        box = (k * half + 52, 76, (k + 1) * half - 95, hgt - 30)
        v = mm.features[:, col]
        lo, hi = (float(q) for q in np.percentile(v, [2, 98]))
        if hi <= lo:
            lo, hi = lo - 1.0, hi + 1.0
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = grid.smooth(grid.bin(v), h) / weight
        rgba = np.zeros(mean.shape + (4,), np.uint8)
        rgba[..., :3] = colour_map(np.nan_to_num(mean, nan=lo), lo, hi, VIRIDIS)
        rgba[..., 3] = np.where(outside, 0, 235)
        panel = pic.panel(box, (x0, y0, x1, y1))
        if floor_plan is not None:
            panel.floor_plan(floor_plan)
        panel.raster(np.transpose(rgba, (1, 0, 2))[::-1], grid.extent, smooth=True)
        panel.dots(xy, (30, 30, 30), size=1)
        panel.scale_bar()
        pic.colourbar((box[2] + 10, box[1], box[2] + 26, box[3]), VIRIDIS, lo, hi, f"{name.split()[-1]} (µT)")
        pic.caption((box[0], box[1] - 34), f"{name}: {np.percentile(v, 2):.1f} to {np.percentile(v, 98):.1f} µT "
                    f"(2nd-98th percentile)\nstandard deviation {v.std():.1f} µT over the map", 12)
    return pic


def draw_magnetic_map(
    mm: MagneticMap, path: str | Path, *, floor_plan: FloorPlan | None = None, site_from_map: NDArray | None = None,
    text: Mapping[str, str] | None = None,
) -> Path:
    """Render ``magnetic_map_picture`` to ``path`` (PNG, written atomically)."""
    return magnetic_map_picture(mm, floor_plan=floor_plan, site_from_map=site_from_map).save(path, text)
