"""Walkable area: where a floor plan lets people walk, used on the tracker's positions.

A floor plan says where walkers can be: corridors and open floor, not inside walls, shops drawn as
closed rooms or outside the building. Map matching against it is the classic companion of pedestrian
dead reckoning indoors. Two uses (``TrackConfig.walkable_mode``):

- ``snap``: a reported position off the walkable area is moved to the nearest walkable cell — the
  estimate constrained to the plan under an isotropic error. It changes the answer, not the tracker's
  state, so a plan that misses a doorway costs one report, not the track;
- ``prior``: one robust row per step in the fixed-lag (and whole-run MAP) problem on the state's
  map-frame position ``p`` (m), ``r(p) = d(p) / sigma`` with ``d`` the distance (m) from ``p`` to the
  nearest walkable cell (0 on the area; bilinear between cell centres; beyond the plan's rectangle the
  distance to it is added). Zero on the area; outside, a pull towards the nearest walkable place that
  Huber's loss bounds; it enters the heading hypotheses' costs too.

The area is a boolean grid in the radio map's frame: row 0 at the top (largest y), as images are
stored, x in [0, width_m] and y in [0, height_m]. Building it from an image is
``graphslam.io.floor_plan.read_walkable_area``; it only makes sense when the radio map is in the
plan's (site) frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from graphslam.errors import EstimationError


@dataclass(frozen=True, eq=False)
class WalkableArea:
    """A walkable-cell grid covering x in [0, ``width_m``], y in [0, ``height_m``] of the map frame
    (``walkable[0]`` is the top row, y = height); ``sigma_m``: std of the distance to it per step."""

    walkable: NDArray[np.bool_]  # (rows, cols), image order: row 0 at the top
    width_m: float
    height_m: float
    sigma_m: float = 2.0
    _dist: NDArray[np.float64] = field(init=False, repr=False)  # (rows, cols) bottom-up, m
    _nearest: NDArray[np.int64] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        w = np.asarray(self.walkable, bool)
        if w.ndim != 2 or min(w.shape) < 2:
            raise EstimationError(f"walkable area: need a 2-D grid of at least 2 x 2 cells, got shape {w.shape}")
        if not w.any():
            raise EstimationError("walkable area: no walkable cell")
        for name in ("width_m", "height_m", "sigma_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise EstimationError(f"walkable area: {name} must be finite and > 0, got {v}")
        w = w.copy()
        w.setflags(write=False)
        object.__setattr__(self, "walkable", w)
        # the field bottom-up: row i at y = (i + 0.5) cy
        dist, nearest = ndimage.distance_transform_edt(~w[::-1], sampling=(self.cell_m[1], self.cell_m[0]), return_indices=True)
        dist.setflags(write=False)
        nearest.setflags(write=False)
        object.__setattr__(self, "_dist", dist)
        object.__setattr__(self, "_nearest", nearest)  # (2, rows, cols): row, column of the nearest walkable cell

    @property
    def cell_m(self) -> tuple[float, float]:
        """Cell size (x, y) in metres."""
        rows, cols = self.walkable.shape
        return self.width_m / cols, self.height_m / rows

    def fraction_walkable(self) -> float:
        return float(self.walkable.mean())

    def distance(self, p: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Distance (m) of map-frame positions ``p`` (M, 2) to the walkable area and its gradient (M, 2)."""
        p = np.asarray(p, float).reshape(-1, 2)
        rows, cols = self._dist.shape
        cx, cy = self.cell_m
        # continuous cell coordinates of p (cell centres at integers), clamped to the grid
        u, v = p[:, 0] / cx - 0.5, p[:, 1] / cy - 0.5
        uc, vc = np.clip(u, 0.0, cols - 1.0), np.clip(v, 0.0, rows - 1.0)
        j0 = np.minimum(np.floor(uc).astype(np.int64), cols - 2)
        i0 = np.minimum(np.floor(vc).astype(np.int64), rows - 2)
        a, b = uc - j0, vc - i0
        D = self._dist
        d00, d01, d10, d11 = D[i0, j0], D[i0, j0 + 1], D[i0 + 1, j0], D[i0 + 1, j0 + 1]
        d = (1 - a) * (1 - b) * d00 + a * (1 - b) * d01 + (1 - a) * b * d10 + a * b * d11
        g = np.stack([((1 - b) * (d01 - d00) + b * (d11 - d10)) / cx, ((1 - a) * (d10 - d00) + a * (d11 - d01)) / cy], 1)
        # beyond the grid: the distance to it is added, and the clamped direction has that gradient
        ox, oy = (u - uc) * cx, (v - vc) * cy
        out = np.hypot(ox, oy)
        far = out > 0
        d = d + out
        g[far & (ox != 0), 0] = ox[far & (ox != 0)] / out[far & (ox != 0)]
        g[far & (oy != 0), 1] = oy[far & (oy != 0)] / out[far & (oy != 0)]
        return d, g

    def residual(self, p: NDArray) -> NDArray[np.float64]:
        """(M,) whitened residuals of map-frame positions ``p`` (M, 2)."""
        return self.distance(p)[0] / self.sigma_m

    def jacobian(self, p: NDArray) -> NDArray[np.float64]:
        """(M, 2) d residual / d (x, y)."""
        return self.distance(p)[1] / self.sigma_m

    def snap(self, p: NDArray) -> NDArray[np.float64]:
        """Map-frame positions ``p`` (M, 2) moved to the centre of the nearest walkable cell when off
        the area (those on it unchanged): the estimate constrained to the plan, under an isotropic
        error (the constrained least-squares point)."""
        p = np.array(p, float).reshape(-1, 2)
        rows, cols = self._dist.shape
        cx, cy = self.cell_m
        j = np.clip((p[:, 0] / cx).astype(np.int64), 0, cols - 1)
        i = np.clip((p[:, 1] / cy).astype(np.int64), 0, rows - 1)
        inside = (p[:, 0] >= 0) & (p[:, 0] <= self.width_m) & (p[:, 1] >= 0) & (p[:, 1] <= self.height_m)
        off = ~(inside & (self._dist[i, j] == 0.0))
        ni, nj = self._nearest[0][i[off], j[off]], self._nearest[1][i[off], j[off]]
        p[off] = np.stack([(nj + 0.5) * cx, (ni + 0.5) * cy], axis=1)
        return p
