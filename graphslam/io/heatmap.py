"""An access point's RSS heatmap as colours and as a PNG (``graphslam.core.radiomap.field.RssField``):
the same cells in radio_map.png's AP panels and in the service's ``GET /v1/heatmap/{bssid}.png``.

Cells are coloured by their mean RSS on ``RSS_RANGE_DBM`` (viridis). Cells whose standard error
exceeds ``MAX_STD_ERROR_DB`` (or is unknown: fewer than 2 effective readings) are faded: blended
``FADE`` of the way toward white. Cells outside the surveyed area are blank.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from graphslam.core.radiomap.field import RssField, rss_field
from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.io.png import VIRIDIS, colour_map, png_bytes

RSS_RANGE_DBM = (-100.0, -30.0)  # fixed colour scale, the same in every panel (and as Rerun's)
MAX_STD_ERROR_DB = 3.0  # cells less certain than this are faded
FADE = 0.65  # share of the way toward white a faded cell is blended
HEATMAP_PX = 600  # the PNG's longer side, about (whole pixels per cell)


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
    """The field as a PNG: one square block of whole pixels per cell, north (+y) up, white outside
    the surveyed area; tEXt chunks say what it shows and where it lies (``extent_m``: x0 x1 y0 y1)."""
    rgba = heatmap_rgba(field, max_std_error_db=max_std_error_db, alpha=255)
    rgb = np.where(rgba[..., 3:] > 0, rgba[..., :3], np.uint8(255))
    scale = max(1, size_px // max(rgb.shape[:2]))
    img = np.transpose(rgb, (1, 0, 2))[::-1]  # rows from the top: y decreasing
    img = np.repeat(np.repeat(img, scale, axis=0), scale, axis=1)
    x0, x1, y0, y1 = field.extent
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
    }
    return png_bytes(np.ascontiguousarray(img), text=text)


def radio_map_heatmap_png(rm: RadioMap, bssid: str, *, max_std_error_db: float = MAX_STD_ERROR_DB) -> bytes:
    """``bssid``'s heatmap over ``rm`` (default grid and kernel, as radio_map.png's) as a PNG
    (``heatmap_png``); ``ConfigError`` for an access point the map does not know."""
    return heatmap_png(rss_field(rm, bssid), frame=rm.frame, max_std_error_db=max_std_error_db)
