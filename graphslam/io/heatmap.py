"""An access point's RSS heatmap as colours and as a PNG (``graphslam.core.radiomap.field.RssField``):
the same cells in radio_map.png's AP panels and in the service's ``GET /v1/heatmap/{bssid}.png``.

Cells are coloured by their mean RSS on ``RSS_RANGE_DBM`` (viridis). Cells whose standard error
exceeds ``MAX_STD_ERROR_DB`` (or is unknown: fewer than 2 effective readings) are faded: blended
``FADE`` of the way toward white. Cells outside the surveyed area are blank.

The PNG (``heatmap_png``) reads on its own: a title (the access point, the frame, what is faded),
metre axes, a colour bar in dBm and a scale bar around the cells, drawn with ``graphslam.io.canvas``.
Its text chunks locate the cells (``extent_m`` in the map's frame, drawn at ``panel_px`` of the
image, ``px_per_cell`` pixels a cell), so the cells can still be laid over a map.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from graphslam.core.radiomap.field import RssField, rss_field
from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.io.png import VIRIDIS, colour_map

RSS_RANGE_DBM = (-100.0, -30.0)  # fixed colour scale, the same in every panel (and as Rerun's)
MAX_STD_ERROR_DB = 3.0  # cells less certain than this are faded
FADE = 0.65  # share of the way toward white a faded cell is blended
HEATMAP_PX = 600  # the cells' longer side in the PNG, about (whole pixels per cell)
# margins around the cells: tick labels left and below, the colour bar right (the title above)
_LEFT, _BOTTOM, _RIGHT = 64, 48, 110


def faded(field: RssField, max_std_error_db: float = MAX_STD_ERROR_DB) -> NDArray[np.bool_]:
    """Cells inside the surveyed area whose standard error exceeds ``max_std_error_db`` or is unknown."""
    se = field.std_error_db
    with np.errstate(invalid="ignore"):
        return ~field.outside & ~(se <= max_std_error_db)


def heatmap_rgba(
    field: RssField, *, max_std_error_db: float = MAX_STD_ERROR_DB, alpha: int = 235,
    lo: float = RSS_RANGE_DBM[0], hi: float = RSS_RANGE_DBM[1],
) -> NDArray[np.uint8]:
    """RGBA (nx, ny, 4), x along the first axis: mean RSS colours, faded cells blended toward white,
    cells outside the surveyed area transparent."""
    rgb = colour_map(np.nan_to_num(field.mean_dbm, nan=lo), lo, hi, VIRIDIS).astype(float)
    f = faded(field, max_std_error_db)
    rgb[f] += (255.0 - rgb[f]) * FADE
    rgba = np.zeros(field.mean_dbm.shape + (4,), np.uint8)
    rgba[..., :3] = np.round(rgb).astype(np.uint8)
    rgba[..., 3] = np.where(field.outside, 0, alpha)
    return rgba


def heatmap_png(field: RssField, *, frame: str = "", max_std_error_db: float = MAX_STD_ERROR_DB,
                size_px: int = HEATMAP_PX) -> bytes:
    """The field as a PNG picture: the cells (one square block of whole pixels each, north (+y) up,
    blank outside the surveyed area) with metre axes, a colour bar (dBm), a scale bar and a title;
    text chunks say what it shows and where the cells lie (``extent_m``: x0 x1 y0 y1 in the map's
    frame, drawn at ``panel_px``: left top right bottom pixels of the image)."""
    import textwrap

    from graphslam.io.canvas import Picture

    rgba = heatmap_rgba(field, max_std_error_db=max_std_error_db, alpha=255)
    nx, ny = rgba.shape[:2]
    scale = max(1, size_px // max(nx, ny))
    x0, x1, y0, y1 = field.extent
    w, h = nx * scale, ny * scale
    width = max(_LEFT + w + _RIGHT, 640)  # room for the title over a narrow map
    lo, hi = RSS_RANGE_DBM
    where = f"{frame} frame" if frame else "the radio map's frame"
    title = (f"RSS of {field.bssid} over the radio map ({where}, metres): kernel average of {field.n_heard:,} "
             f"fingerprints hearing it, {field.cell_m:g} m cells, Gaussian kernel {field.bandwidth_m:g} m; "
             f"faded: standard error > {max_std_error_db:g} dB; blank: not surveyed")
    lines = textwrap.wrap(title, max(40, (width - 32) // 8))
    top = 22 + 20 * len(lines)
    box = (_LEFT, top, _LEFT + w, top + h)
    pic = Picture((width, top + h + _BOTTOM), title_lines=lines, frame=frame)
    panel = pic.panel(box, (x0, y0, x1, y1), tight=True)
    panel.raster(np.transpose(rgba, (1, 0, 2))[::-1], (x0, x1, y0, y1))  # rows from the top: y decreasing
    pic.scale_bar(panel, (_LEFT, top + h + 36))  # under the axis, hiding no cell
    pic.colourbar((box[2] + 14, box[1], box[2] + 30, box[3]), VIRIDIS, lo, hi, "RSS (dBm)")
    text = {
        "bssid": field.bssid,
        "frame": frame,
        "extent_m": f"{x0:.3f} {x1:.3f} {y0:.3f} {y1:.3f}",
        "cell_m": f"{field.cell_m:g}",
        "px_per_cell": str(scale),
        "bandwidth_m": f"{field.bandwidth_m:g}",
        "rss_range_dbm": f"{RSS_RANGE_DBM[0]:g} {RSS_RANGE_DBM[1]:g} (viridis)",
        "faded": f"standard error > {max_std_error_db:g} dB",
        "not_heard_dbm": f"{field.floor_dbm:g}",
        "panel_px": " ".join(map(str, box)),
    }
    return pic.png(text)


def radio_map_heatmap_png(rm: RadioMap, bssid: str, *, max_std_error_db: float = MAX_STD_ERROR_DB) -> bytes:
    """``bssid``'s heatmap over ``rm`` (default grid and kernel, as radio_map.png's) as a PNG
    (``heatmap_png``); ``ConfigError`` for an access point the map does not know."""
    return heatmap_png(rss_field(rm, bssid), frame=rm.frame, max_std_error_db=max_std_error_db)
