"""``radio_map.png``: is the survey good enough? What Anyplace users look at (``graphslam.io.canvas``).

Panel 1, coverage: fingerprints per m^2 on a grid of ``cell_m`` cells. Panel 2, expected accuracy
(``graphslam.core.radiomap.uncertainty.expected_accuracy``): per cell of ``ACCURACY_CELL_M`` (or the
grid's cell, if coarser), the median error of the map's fingerprints located among the other walks'
fingerprints with the default kNN (a seeded sample of ``ACCURACY_ROWS`` on big maps), on a fixed
``ACCURACY_RANGE_M`` scale; grey cells hold fingerprints that could not be located among other walks
(a map of one walk: all of them); cells without fingerprints are blank. Then one panel per
access point (``aps``, else the ``top`` most-heard, stronger mean RSS first on ties): its
RSS interpolated over the surveyed area, with the AP's fitted position (``fit-aps``'
ap_models.json) marked when there is one, and the fingerprints that heard it as dots.

Interpolation (``graphslam.core.radiomap.field.rss_field``): a Gaussian kernel average
(Nadaraya-Watson, std ``bandwidth_m``) of every fingerprint's reading, where a fingerprint that
did not hear the AP counts as the map's ``min_rssi_dbm`` (the reading floor: it was weaker than
that), with its standard error (the kernel-weighted spread of the readings over the effective
number of readings). Cells whose standard error exceeds ``MAX_STD_ERROR_DB`` (or is unknown:
fewer than 2 effective readings) are faded toward white (``graphslam.io.heatmap``). Binned on the
grid and filtered, so the cost is that of the grid, not of the fingerprints x cells. Cells where
the kernel weight of all fingerprints is below ``MIN_WEIGHT`` are outside the surveyed area and
left blank (the same mask in every panel).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from graphslam.core.radiomap.field import MIN_WEIGHT, FieldGrid, ap_readings, grid_cell_m, rss_field
from graphslam.core.radiomap.knn import KnnConfig
from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.core.radiomap.uncertainty import METADATA_KEY, AccuracyCells, KnnUncertainty, expected_accuracy
from graphslam.core.common.geometry import se2_apply
from graphslam.core.tracking.apmodel import ApModels
from graphslam.errors import ConfigError
from graphslam.io.heatmap import MAX_STD_ERROR_DB, RSS_RANGE_DBM, heatmap_rgba
from graphslam.io.canvas import MAGMA_R, RDYLGN_R, VIRIDIS, Panel, Picture, colour_map, font
from graphslam.viz.common import FloorPlan, top_access_points

SIZE_PX = (1600, 1000)
TOP_APS = 5
MAX_APS = 10  # 12 panels at most (coverage, accuracy, APs): beyond that nothing is readable
ACCURACY_CELL_M = 2.0
ACCURACY_RANGE_M = (0.0, 15.0)  # fixed colour scale: floors compare; beyond 15 m the map does not localise
ACCURACY_ROWS = 5000  # fingerprints located at most (a seeded sample, even over the cells) ...
ACCURACY_PAIRS = 20_000_000  # ... and fewer on big maps: at most ~this many distances (a few seconds)
NOT_LOCATED = (200, 200, 200)


def draw_radio_map(
    rm: RadioMap,
    path: str | Path,
    *,
    aps: Sequence[str] = (),
    top: int = TOP_APS,
    ap_models: ApModels | None = None,
    floor_plan: FloorPlan | None = None,
    site_from_map: NDArray | None = None,
    cell_m: float | None = None,
    bandwidth_m: float | None = None,
    size_px: tuple[int, int] = SIZE_PX,
    text: Mapping[str, str] | None = None,
) -> Path:
    """Render the radio map picture (``radio_map_picture``) to ``path`` (PNG of ``size_px``, written
    atomically; ``text``: PNG text chunks, e.g. the options it was drawn with)."""
    pic = radio_map_picture(rm, aps=aps, top=top, ap_models=ap_models, floor_plan=floor_plan,
                            site_from_map=site_from_map, cell_m=cell_m, bandwidth_m=bandwidth_m, size_px=size_px)
    return pic.save(path, text)


def radio_map_picture(
    rm: RadioMap,
    *,
    aps: Sequence[str] = (),
    top: int = TOP_APS,
    ap_models: ApModels | None = None,
    floor_plan: FloorPlan | None = None,
    site_from_map: NDArray | None = None,
    cell_m: float | None = None,
    bandwidth_m: float | None = None,
    size_px: tuple[int, int] = SIZE_PX,
) -> Picture:
    """The radio map picture: coverage, expected accuracy, then one panel per AP of ``aps`` (else the
    ``top`` most heard).

    ``site_from_map`` (x, y, theta) draws a map in the aligned frame over a ``floor_plan`` in
    the site frame (e.g. report.json's landmark fit); without it the plan is drawn as is.
    """
    if not len(rm):
        raise ConfigError("radio map picture: the radio map has no fingerprint")
    cols = ap_columns(rm, aps, top)
    T = None if site_from_map is None or floor_plan is None else np.asarray(site_from_map, float).reshape(3)
    registered = T is not None  # drawn in the plan's site frame

    def place(points: NDArray) -> NDArray:
        return se2_apply(T, points) if T is not None else points

    xy = place(np.asarray(rm.xy, float))
    cell = float(cell_m or grid_cell_m(xy))
    h = float(bandwidth_m or 2.0 * cell)
    grid = FieldGrid(xy, cell)
    weight = grid.smooth(grid.bin(np.ones(len(xy))), h)
    outside = weight < MIN_WEIGHT
    floor = rm.min_rssi_dbm

    frame = f"{rm.frame} frame"
    if floor_plan is not None:
        frame = "site frame of the floor plan" if registered else f"{rm.frame} frame, floor plan NOT registered to it"
    extent = grid.extent
    boxes, height = _layout(2 + len(cols), size_px, top=36, aspect=_shown_aspect(extent))
    pic = Picture((size_px[0], height), title_lines=[
        f"radio map: {len(rm):,} fingerprints, {rm.fingerprints.n_aps:,} APs, {len(set(rm.session_ids.tolist()))} walks; "
        f"{frame}; {cell:g} m cells, Gaussian kernel {h:g} m; an AP not heard counts as {floor:g} dBm"
    ], frame="site" if registered else rm.frame)

    density = weight / cell**2  # kernel density: fingerprints per m^2
    d_hi = float(np.percentile(density[~outside], 99)) if (~outside).any() else 1.0
    panel = _heat_panel(pic, boxes[0], extent, density, outside, 0.0, d_hi, MAGMA_R, floor_plan, "fingerprints / m²")
    area = float((~outside).sum()) * cell**2
    pic.caption((boxes[0][0], boxes[0][1] - 34), f"coverage: {len(rm):,} fingerprints over ~{area:,.0f} m²\n"
                f"median {np.median(density[~outside]) if (~outside).any() else 0:.2f} / m² where surveyed", 12)
    _accuracy_panel(pic, boxes[1], grid, rm, xy, floor_plan)

    fitted = {a.bssid: a for a in ap_models.fitted} if ap_models is not None else {}
    unfitted = {u.bssid: u.reason for u in ap_models.unfitted} if ap_models is not None else {}
    for box, c in zip(boxes[2:], cols):
        field = rss_field(rm, rm.bssids[c], xy=xy, grid=grid, bandwidth_m=h)
        _, rows = ap_readings(rm, rm.bssids[c])
        panel = _heat_panel(pic, box, extent, field.mean_dbm, outside, *RSS_RANGE_DBM, VIRIDIS, floor_plan, "RSS (dBm)",
                            rgba=heatmap_rgba(field))
        panel.dots(xy[rows], (30, 30, 30), size=1)
        bssid = rm.bssids[c]
        note = "no AP models (run fit-aps)" if ap_models is None else "no AP model"
        if bssid in fitted:
            a = fitted[bssid]
            p = place(np.array([[a.x, a.y]]))
            panel.points(p, (255, 0, 0), radius=12, kind="star")
            note = f"fitted AP (red star): P0 {a.p0_dbm:.0f} dBm, γ {a.gamma:.1f}, ±{a.position_std_m:.1f} m"
        elif bssid in unfitted:
            note = f"AP not fitted: {unfitted[bssid].split(' (')[0]}"
        head = f"{bssid}, heard by {len(rows):,}; faded: standard error > {MAX_STD_ERROR_DB:g} dB"
        if font(12).getlength(head) > box[2] - box[0] + 80:  # beyond the colour bar: abbreviated
            head = f"{bssid}, heard by {len(rows):,}; faded: s.e. > {MAX_STD_ERROR_DB:g} dB"
        pic.caption((box[0], box[1] - 34), f"{head}\n{note}", 12)
    return pic


def _accuracy_panel(
    pic: Picture, box: tuple[int, int, int, int], grid: FieldGrid, rm: RadioMap, xy: NDArray, plan: FloorPlan | None
) -> AccuracyCells:
    """Panel: the expected accuracy per cell (module docstring), on cells aligned with ``grid``."""
    stored = rm.metadata.get(METADATA_KEY)
    u = KnnUncertainty.from_dict(stored) if isinstance(stored, Mapping) else None
    if u is not None and not u.matches(KnnConfig()):
        u = None  # measured with another kNN than the one located with here
    cell = max(ACCURACY_CELL_M, grid.cell)
    rows = min(ACCURACY_ROWS, max(500, ACCURACY_PAIRS // len(rm)))
    acc = expected_accuracy(rm, cell_m=cell, xy=xy, origin=grid.lo, uncertainty=u, max_rows=rows)
    x0, x1, y0, y1 = grid.extent
    n = np.ceil(np.array([x1 - x0, y1 - y0]) / cell - 1e-9).astype(int)
    rgba = np.zeros((n[0], n[1], 4), np.uint8)  # (nx, ny): x along the first axis
    measured = np.isfinite(acc.error_m)
    sampled = acc.n_sampled > 0  # all cells but on maps of more cells than fingerprints located
    i, j = np.clip(acc.ij[:, 0], 0, n[0] - 1), np.clip(acc.ij[:, 1], 0, n[1] - 1)
    rgba[i, j, :3] = np.where(measured[:, None], colour_map(np.nan_to_num(acc.error_m), *ACCURACY_RANGE_M, RDYLGN_R),
                              np.array(NOT_LOCATED, np.uint8))
    rgba[i, j, 3] = np.where(sampled, 235, 0)
    panel = pic.panel(box, (x0, y0, x1, y1))
    if plan is not None:
        panel.floor_plan(plan)
    panel.raster(np.transpose(rgba, (1, 0, 2))[::-1], (x0, x0 + n[0] * cell, y0, y0 + n[1] * cell))
    panel.scale_bar()
    pic.colourbar((box[2] + 10, box[1], box[2] + 26, box[3]), RDYLGN_R, *ACCURACY_RANGE_M, "error (m)")
    if measured.any():
        r95 = f", 95 % radius {np.nanmedian(acc.r95_m):.1f} m" if np.isfinite(acc.r95_m).any() else ""
        grey = f"; grey: {int((sampled & ~measured).sum())} cells, 1 walk" if (sampled & ~measured).any() else ""
        text = (f"expected accuracy: located among other walks, {cell:g} m cells\n"
                f"median error {np.median(acc.error_m[measured]):.1f} m{r95}{grey}")
    else:
        text = "expected accuracy: one walk, nothing to compare (grey)\nsurvey more walks to measure it"
    pic.caption((box[0], box[1] - 34), text, 12)
    return acc


# room around each panel: left for the tick labels, right for the colour bar, above for a 2-line
# caption, below for the tick labels
_LEFT, _RIGHT, _ABOVE, _BELOW = 52, 95, 40, 24
MIN_HEIGHT_PX = 300


def _shown_aspect(extent: tuple[float, float, float, float]) -> float:
    """Width / height of what a panel shows of ``extent`` (x0, x1, y0, y1): the grid and the
    panel's margins (``Panel``: 4 % of the larger side and 0.5 m each way)."""
    x0, x1, y0, y1 = extent
    pad = 2 * (0.04 * max(x1 - x0, y1 - y0) + 0.5)
    return max(x1 - x0 + pad, 1e-6) / max(y1 - y0 + pad, 1e-6)


def _layout(
    n: int, size_px: tuple[int, int], top: int, aspect: float = 1.5
) -> tuple[list[tuple[int, int, int, int]], int]:
    """Panel boxes on a grid of the columns that fit a floor of ``aspect`` (width / height) best, and
    the picture's height (at most ``size_px``'s; less when the panels need less, so that a wide
    floor's picture is not mostly blank). Each box: room above for a 2-line caption, right for a
    colour bar, left and below for the ticks; its height is what the floor needs at the box's width.

    Best: the largest share of the picture the floor covers, plus a tenth of the panels' size
    relative to the largest possible (two layouts as good: the bigger panels)."""
    w, h = size_px
    options = []
    for ncols in range(1, n + 1):
        nrows = math.ceil(n / ncols)
        pw = w / ncols - _LEFT - _RIGHT
        ph = (h - top) / nrows - _ABOVE - _BELOW
        if pw < 60 or ph < 40:
            continue
        dw = min(pw, ph * aspect)  # the floor drawn at one scale in the box
        dh = dw / aspect
        height = max(MIN_HEIGHT_PX, min(h, int(math.ceil(top + nrows * (dh + _ABOVE + _BELOW)))))
        options.append((n * dw * dh / (w * height), dw * dh, ncols, nrows, min(ph, dh), height))
    if not options:  # a picture too small for any grid: one row, as it comes
        options = [(0.0, 0.0, n, 1, (h - top) - _ABOVE - _BELOW, h)]
    biggest = max(o[1] for o in options) or 1.0
    _, _, ncols, nrows, ph, height = max(options, key=lambda o: (o[0] + 0.1 * o[1] / biggest, o[1]))
    cw, ch = w / ncols, (height - top) / nrows
    boxes = [
        (int(c * cw + _LEFT), int(top + r * ch + _ABOVE), int((c + 1) * cw - _RIGHT),
         int(top + r * ch + _ABOVE + max(20.0, min(ph, ch - _ABOVE - _BELOW))))
        for r in range(nrows) for c in range(ncols)
    ][:n]
    return boxes, height


def _heat_panel(
    pic: Picture, box: tuple[int, int, int, int], extent: tuple[float, float, float, float], field: NDArray,
    outside: NDArray, lo: float, hi: float, table: NDArray, plan: FloorPlan | None, label: str,
    rgba: NDArray | None = None,
) -> Panel:
    """A panel of ``field`` (nx, ny) coloured on ``table`` from ``lo`` to ``hi``, blank ``outside``;
    ``rgba``: the cells' colours, already made (e.g. faded)."""
    x0, x1, y0, y1 = extent
    panel = pic.panel(box, (x0, y0, x1, y1))
    if plan is not None:
        panel.floor_plan(plan)
    if rgba is None:
        rgba = np.zeros(field.shape + (4,), np.uint8)  # (nx, ny): x along the first axis
        rgba[..., :3] = colour_map(field, lo, hi, table)
        rgba[..., 3] = np.where(outside, 0, 235)
    panel.raster(np.transpose(rgba, (1, 0, 2))[::-1], extent, smooth=True)  # rows from the top
    panel.scale_bar()
    pic.colourbar((box[2] + 10, box[1], box[2] + 26, box[3]), table, lo, hi, label)
    return panel


def ap_columns(rm: RadioMap, aps: Sequence[str], top: int) -> list[int]:
    """Columns of ``rm`` to draw: ``aps`` (each must be in the map), else the ``top`` most heard."""
    if aps:
        index = {b: i for i, b in enumerate(rm.bssids)}
        unknown = [a for a in aps if a not in index]
        if unknown:
            raise ConfigError(f"--ap {unknown[0]}: no fingerprint of the radio map heard this access point")
        cols = [index[a] for a in dict.fromkeys(aps)]
    else:
        cols = top_access_points(rm.fingerprints, np.arange(len(rm)), max(0, top))
    if len(cols) > MAX_APS:
        raise ConfigError(f"radio map picture: {len(cols)} access points asked for, at most {MAX_APS} fit")
    return cols
