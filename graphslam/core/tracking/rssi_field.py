"""What the log-distance law misses: each AP's residual RSS as a smooth field over the map.

Indoors the path-loss law (``graphslam.core.tracking.apmodel``) is a trend: walls, shelves and
corridors add offsets of several dB that stay put (shadowing is a function of place). The map's
own readings show them: per AP, the residuals ``r_i = rss_i - h(xy_i)`` of its fingerprints are
smoothed by a Gaussian kernel of std ``bandwidth_m`` and shrunk towards 0 where they are few::

    c(x) = sum_i K(x, xy_i) r_i / (sum_i K(x, xy_i) + shrink),   K = exp(-|x - xy_i|^2 / 2 bw^2)

(Nadaraya-Watson with a prior of ``shrink`` pseudo-readings of residual 0: far from the readings the
model is the law again). This is the mean of a Gaussian-process correction of the law (Ferris et
al. 2006 put a GP on WiFi signal strength with a path-loss mean), kept cheap: the sums are
accumulated on a grid of ``cell_m`` cells per AP (only around that AP's readings) and blurred, and
the field is read by bilinear interpolation.

The trackers' Jacobians keep the law's gradient alone (``PathLossModel.rss_pairs``): the field's own
gradient is the derivative of a kernel estimate at the bandwidth's scale, far noisier than its value,
and in H it made the fixed-lag tracker surer and worse on the real floors (docs/tracking.md). So
the field moves the readings' mean to where the map says it is, and the law says how it changes.

The readings' noise around the corrected law is measured leaving each map walk out (its readings'
correction from the other walks only): a walk's own readings would make the field look better than
it is on a new walk. It is reported, not used: the trackers keep the law's noise levels.

Frames and units: the radio map's frame (m), dBm and dB.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import gaussian_filter
from scipy.spatial import cKDTree

from graphslam.errors import EstimationError

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class ResidualField:
    """Per AP a grid of corrections (dB) added to the path-loss law; 0 outside an AP's grid.

    All grids are stored flat in ``values``; AP ``a``'s grid has ``shape[a]`` = (ny, nx) cells of
    ``cell_m`` with the centre of cell (0, 0) at ``origin[a]`` (m), from ``offset[a]`` on."""

    cell_m: float
    origin: NDArray[np.float64]  # (A, 2) m
    shape: NDArray[np.int64]  # (A, 2) ny, nx (0, 0: no correction for that AP)
    offset: NDArray[np.int64]  # (A,)
    values: NDArray[np.float32]  # (sum ny nx,) dB

    def __post_init__(self) -> None:
        a = len(self.origin)
        if self.origin.shape != (a, 2) or self.shape.shape != (a, 2) or self.offset.shape != (a,) or self.cell_m <= 0:
            raise EstimationError("RSSI field: one origin, shape and offset per AP and a positive cell size expected")
        if a and int((self.offset + self.shape[:, 0] * self.shape[:, 1]).max()) > self.values.size:
            raise EstimationError("RSSI field: a grid runs past the stored values")

    def __len__(self) -> int:
        return len(self.origin)

    @property
    def cells(self) -> int:
        return int(self.values.size)

    def at(self, xy: NDArray, idx: NDArray) -> NDArray[np.float64]:
        """Correction (m,) dB of AP ``idx[j]`` at ``xy[j]`` (m, 2): bilinear between cell centres,
        0 off the AP's grid. In the trackers' inner loop: a few array operations, no Python per pair."""
        xy = np.asarray(xy, float).reshape(-1, 2)
        return self.rows(np.asarray(idx, dtype=np.int64).ravel()).at(xy[:, 0], xy[:, 1])

    def rows(self, idx: NDArray) -> "FieldRows":
        """The grids of APs ``idx`` (m,) gathered once, for reading them at many positions."""
        g = self._table[np.asarray(idx, dtype=np.int64)]  # (m, 6)
        top = g[:, 2:4]  # last cell centre in cells (negative: no grid)
        full = (top >= 0.0).all(axis=1)
        hi = np.maximum(top - 1e-9, 0.0)
        # a reading without a grid is never inside: its cells are read at 0, 1 (in range, discarded)
        return FieldRows(1.0 / self.cell_m, g[:, 0], g[:, 1], top[:, 0], top[:, 1], hi[:, 0], hi[:, 1],
                         np.where(full, g[:, 4], 0).astype(np.int64), np.where(full, g[:, 5], 0).astype(np.int64),
                         self.values)

    @property
    def _table(self) -> NDArray[np.float64]:
        """(A, 6) per AP: origin x, y; last cell centre in cells (nx - 1, ny - 1; -1 for a grid of fewer
        than 2 x 2 cells, never inside); nx; offset. Built once."""
        t = self.__dict__.get("_table_cache")
        if t is None:
            full = (self.shape >= 2).all(axis=1)[:, None]
            t = np.column_stack([self.origin, np.where(full, self.shape[:, ::-1] - 1.0, -1.0), self.shape[:, 1], self.offset])
            object.__setattr__(self, "_table_cache", t)
        return t


@dataclass(frozen=True, eq=False)
class FieldRows:
    """The field of one AP per reading (``ResidualField.rows``): per reading its grid's origin (m), last
    cell centre (cells; negative: no grid, never inside), the clamp inside it, row length and offset."""

    inv_cell: float
    ox: NDArray[np.float64]
    oy: NDArray[np.float64]
    top_x: NDArray[np.float64]
    top_y: NDArray[np.float64]
    hi_x: NDArray[np.float64]
    hi_y: NDArray[np.float64]
    nx: NDArray[np.int64]
    offset: NDArray[np.int64]
    values: NDArray[np.float32]

    def at(self, x: NDArray, y: NDArray) -> NDArray[np.float64]:
        """Correction (dB) of each reading's AP at positions ``x``, ``y`` (m; shape (..., m))."""
        v = self.values
        if v.size < 2:  # no grid of 2 x 2 cells: never inside one
            return np.zeros(np.broadcast_shapes(np.shape(x), self.ox.shape))
        ux = (x - self.ox) * self.inv_cell  # in cells
        uy = (y - self.oy) * self.inv_cell
        inside = (ux >= 0.0) & (uy >= 0.0) & (ux <= self.top_x) & (uy <= self.top_y)
        ux = np.minimum(np.maximum(ux, 0.0), self.hi_x)
        uy = np.minimum(np.maximum(uy, 0.0), self.hi_y)
        ix, iy = ux.astype(np.int64), uy.astype(np.int64)  # floor: u >= 0; the cell and its neighbours are in the grid
        fx, fy = ux - ix, uy - iy
        gx = 1 - fx
        base = self.offset + iy * self.nx + ix
        up = base + self.nx
        val = (v[base] * gx + v[base + 1] * fx) * (1 - fy) + (v[up] * gx + v[up + 1] * fx) * fy
        return np.where(inside, val, 0.0)

    def take(self, rows: slice | NDArray) -> "FieldRows":
        """The field of these readings only."""
        return FieldRows(self.inv_cell, self.ox[rows], self.oy[rows], self.top_x[rows], self.top_y[rows], self.hi_x[rows],
                         self.hi_y[rows], self.nx[rows], self.offset[rows], self.values)


@dataclass(frozen=True)
class FieldFit:
    """A fitted field and the readings' noise around the corrected law per AP (dB, robust std of
    the leave-one-walk-out residuals; NaN where an AP has too few readings to say)."""

    field: ResidualField
    sigma_db: NDArray[np.float64]  # (A,)
    sigma_law_db: NDArray[np.float64]  # (A,) the same statistic around the law alone


def _mad(r: NDArray) -> float:
    return float(1.4826 * np.median(np.abs(r - np.median(r)))) if len(r) >= 5 else float("nan")


def _left_out_correction(p: NDArray, r: NDArray, g: NDArray, bandwidth_m: float, shrink: float) -> NDArray[np.float64]:
    """Each reading's correction from the readings of the other walks only: the kernel truncated at
    3 bandwidths (a sparse neighbour graph; never an n x n matrix for a much-heard AP)."""
    tree = cKDTree(p)
    D = tree.sparse_distance_matrix(tree, 3.0 * bandwidth_m, output_type="coo_matrix")
    i, j = D.row, D.col
    other = g[i] != g[j]
    i, j = i[other], j[other]
    k = np.exp(-0.5 * (D.data[other] / bandwidth_m) ** 2)
    num = np.bincount(i, weights=k * r[j], minlength=len(r))
    den = np.bincount(i, weights=k, minlength=len(r))
    return num / (den + shrink)


def fit_residual_field(
    xy: NDArray, residual: NDArray, ap: NDArray, group: NDArray, n_aps: int, *, bandwidth_m: float = 3.0,
    shrink: float = 0.5, cell_m: float = 1.0, leave_out: bool = True,
) -> FieldFit:
    """The field from readings of AP ``ap[i]`` at ``xy[i]`` (m) whose residual around the law is
    ``residual[i]`` (dB); ``group[i]``: the map walk of the reading (left out together when the
    noise is measured; ``leave_out`` False: neither noise is measured, NaN). ``shrink``: pseudo-readings of residual 0
    at every place (module docstring)."""
    if not (bandwidth_m > 0 and shrink > 0 and cell_m > 0 and bandwidth_m >= cell_m):
        raise EstimationError(f"RSSI field: need bandwidth_m >= cell_m > 0 and shrink > 0, got {bandwidth_m}, {cell_m}, {shrink}")
    xy = np.asarray(xy, float).reshape(-1, 2)
    residual, ap = np.asarray(residual, float).ravel(), np.asarray(ap, np.int64).ravel()
    group = np.asarray(group).ravel()
    if not (len(xy) == len(residual) == len(ap) == len(group)):
        raise EstimationError("RSSI field: one position, residual, AP and walk per reading expected")
    margin = 3.0 * bandwidth_m
    s = bandwidth_m / cell_m
    norm = 2.0 * np.pi * s * s  # gaussian_filter's kernel sums to 1; the readings' kernel peaks at 1
    origin, shape = np.zeros((n_aps, 2)), np.zeros((n_aps, 2), np.int64)
    grids: list[NDArray] = []
    sigma, sigma_law = np.full(n_aps, np.nan), np.full(n_aps, np.nan)
    order = np.argsort(ap, kind="stable")
    bounds = np.searchsorted(ap[order], np.arange(n_aps + 1))
    for a in range(n_aps):
        rows = order[bounds[a] : bounds[a + 1]]
        if len(rows) == 0:
            continue
        p, r, g = xy[rows], residual[rows], group[rows]
        lo = np.floor((p.min(axis=0) - margin) / cell_m) * cell_m
        n = (np.ceil((p.max(axis=0) + margin - lo) / cell_m).astype(np.int64) + 1)  # nx, ny
        c = np.rint((p - lo) / cell_m).astype(np.int64)
        lin = c[:, 1] * n[0] + c[:, 0]
        m = n[0] * n[1]
        sums = np.bincount(np.r_[lin, lin + m], weights=np.r_[r, np.ones(len(r))], minlength=2 * m)
        S, W = gaussian_filter(sums.reshape(2, n[1], n[0]), (0.0, s, s), mode="constant")  # both at once
        grids.append((S * norm / (W * norm + shrink)).ravel())
        origin[a], shape[a] = lo, (n[1], n[0])
        if leave_out:
            sigma_law[a] = _mad(r)
            sigma[a] = _mad(r - _left_out_correction(p, r, g, bandwidth_m, shrink))
    offset = np.concatenate([[0], np.cumsum([len(v) for v in grids])])[:-1] if grids else np.zeros(0, np.int64)
    off = np.zeros(n_aps, np.int64)
    off[[a for a in range(n_aps) if shape[a, 0] > 0]] = offset
    values = np.concatenate(grids).astype(np.float32) if grids else np.zeros(0, np.float32)  # dB: float32 is plenty
    field = ResidualField(cell_m, origin, shape, off, values)
    log.info("RSSI field: %d APs, %.1f M cells, bandwidth %.1f m", n_aps, field.values.size / 1e6, bandwidth_m)
    return FieldFit(field, sigma, sigma_law)
