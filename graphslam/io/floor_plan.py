"""Floor plans: the image and the site-frame rectangle it covers (``floor_info.json`` beside it, as in
the ILC data, or a size given in metres)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from graphslam.core.tracking.walkable import WalkableArea
from graphslam.errors import ConfigError, InputError


@dataclass(frozen=True)
class FloorPlan:
    """A floor plan image and the site-frame rectangle it covers: x in [0, width], y in [0, height]."""

    path: Path
    width_m: float
    height_m: float
    pixels: tuple[int, int]  # (columns, rows)


FLOOR_INFO_FILE = "floor_info.json"  # beside a floor plan image: its size in metres (the ILC layout)


def load_floor_plan(path: str | Path | None, size: tuple[float, float] | None) -> FloorPlan | None:
    """The floor plan image and its size in metres.

    Without ``size``, a ``floor_info.json`` beside the image (``{"map_info": {"width": W,
    "height": H}}``, as in the ILC data) gives it.
    """
    if path is None:
        if size is not None:
            raise ConfigError("--floor-size given without --floor-plan")
        return None
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "floor plan image not found")
    if size is None:
        info = p.parent / FLOOR_INFO_FILE
        try:
            mi = json.loads(info.read_text(encoding="utf-8"))["map_info"]
            size = (float(mi["width"]), float(mi["height"]))
        except (OSError, ValueError, KeyError, TypeError):
            raise ConfigError(f"floor plan {p}: give --floor-size W H (metres); no usable {info.name} beside it") from None
    w, h = float(size[0]), float(size[1])
    if not (np.isfinite(w) and np.isfinite(h) and w > 0 and h > 0):
        raise ConfigError(f"floor size must be two positive numbers of metres, got {size}")
    try:
        from PIL import Image  # reads the header only

        with Image.open(p) as im:
            px = (int(im.size[0]), int(im.size[1]))
    except Exception as e:  # PIL raises many types for bad images
        raise InputError(p, f"cannot read the floor plan image ({e})") from None
    return FloorPlan(p, w, h, px)


# A plan pixel is background (not drawn) when transparent or this near white (0-255, every channel).
BACKGROUND_MIN_RGB = 240


def read_walkable_area(plan: FloorPlan, sigma_m: float = 2.0) -> WalkableArea:
    """The walkable area of a floor plan image: its background pixels (transparent, or white within
    ``BACKGROUND_MIN_RGB``) that the drawing encloses. Plans draw walls, rooms and shops and leave the
    corridors and open floor blank (the ILC plans: corridors transparent inside the building's
    outline, shops filled); the blank outside the outline is not walkable. ``InputError`` naming the
    file when the image cannot be read or encloses no blank area (e.g. an outline with a gap)."""
    from PIL import Image
    from scipy import ndimage

    try:
        with Image.open(plan.path) as im:
            px = np.asarray(im.convert("RGBA"))
    except Exception as e:  # PIL raises many types for bad images
        raise InputError(plan.path, f"cannot read the floor plan image ({e})") from None
    background = (px[..., 3] == 0) | (px[..., :3].min(axis=-1) >= BACKGROUND_MIN_RGB)
    walkable = ndimage.binary_fill_holes(~background) & background
    if not walkable.any():
        raise InputError(plan.path, "the floor plan encloses no blank (walkable) area: no closed outline around the corridors")
    return WalkableArea(walkable, plan.width_m, plan.height_m, sigma_m=sigma_m)
