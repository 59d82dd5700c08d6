"""One access point's RSS field over a grid, with its standard error (radio_map.png's AP panels,
the service's ``GET /v1/heatmap/{bssid}.png``).

Every fingerprint counts: one that did not hear the AP as the map's ``min_rssi_dbm`` (the reading
floor: it was weaker than that). Each cell's value is a Gaussian kernel average (Nadaraya-Watson,
std ``bandwidth_m``) of the readings, with weights ``w_i = k(|x_i - cell|)``:

- ``mean = sum w r / W`` with ``W = sum w`` (the kernel weight, in fingerprints);
- ``n_eff = W^2 / sum w^2`` (Kish's effective number of readings);
- ``s^2 = sum w (r - mean)^2 / W`` (the kernel-weighted variance of the readings) and the standard
  error ``sqrt(s^2 / (n_eff - 1))`` (``s^2 n_eff / (n_eff - 1)`` is the unbiased variance with
  reliability weights; divided by ``n_eff``).

The sums are binned on the grid (fingerprint positions rounded to their cell) and filtered with the
separable kernel (``scipy.ndimage.correlate1d``; ``w^2`` with the squared kernel), so the cost is
that of the grid, not of fingerprints x cells. Cells with ``W < min_weight`` are outside the
surveyed area: mean and standard error NaN. Inside, the standard error is NaN where ``n_eff < 2``
(one reading says nothing of its spread).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.errors import ConfigError

MIN_WEIGHT = 0.05  # kernel weight (in fingerprints) below which a cell is "not surveyed"
TRUNCATE = 4.0  # kernel radius in standard deviations (scipy.ndimage.gaussian_filter's default)


def grid_cell_m(xy: NDArray) -> float:
    """A round cell size (0.5, 1, 2, 2.5, 5 m x 10^k) giving about 150 cells along the longer side,
    never finer than 0.5 m."""
    span = float(np.ptp(xy, axis=0).max()) if len(xy) else 0.0
    target = max(0.5, span / 150.0)
    p = 10.0 ** math.floor(math.log10(target))
    return min(m * p for m in (1.0, 2.0, 2.5, 5.0, 10.0) if m * p >= target - 1e-9)


class FieldGrid:
    """Square cells of ``cell`` m covering ``xy`` (N, 2) with a margin of 3 cells; cell (i, j) spans
    ``lo + (i, j) * cell`` to ``lo + (i + 1, j + 1) * cell``. Arrays on it are (nx, ny): x first."""

    def __init__(self, xy: NDArray, cell: float) -> None:
        xy = np.asarray(xy, float).reshape(-1, 2)
        if not (cell > 0 and math.isfinite(cell)):
            raise ConfigError(f"RSS field: cell size must be a positive number of metres, got {cell}")
        if not len(xy):
            raise ConfigError("RSS field: no fingerprint")
        lo, hi = xy.min(axis=0) - 3 * cell, xy.max(axis=0) + 3 * cell
        self.cell = float(cell)
        self.n = np.maximum(np.ceil((hi - lo) / cell).astype(int), 1)
        self.lo = lo
        self.extent = (float(lo[0]), float(lo[0] + self.n[0] * cell), float(lo[1]), float(lo[1] + self.n[1] * cell))
        self._ij = np.clip(((xy - lo) / cell).astype(int), 0, self.n - 1)

    def bin(self, w: NDArray) -> NDArray:
        """Sum of ``w`` (one value per point) per cell, shape (nx, ny)."""
        flat = np.bincount(self._ij[:, 0] * self.n[1] + self._ij[:, 1], weights=w, minlength=int(self.n.prod()))
        return flat.reshape(self.n[0], self.n[1])

    def kernel(self, bandwidth_m: float) -> NDArray:
        """The 1-D Gaussian kernel of std ``bandwidth_m`` in cells, summing to 1 (as gaussian_filter's)."""
        if not (bandwidth_m > 0 and math.isfinite(bandwidth_m)):
            raise ConfigError(f"RSS field: bandwidth must be a positive number of metres, got {bandwidth_m}")
        sd = bandwidth_m / self.cell
        r = int(TRUNCATE * sd + 0.5)
        k = np.exp(-0.5 * (np.arange(-r, r + 1) / sd) ** 2)
        return k / k.sum()

    def smooth(self, g: NDArray, bandwidth_m: float, *, squared: bool = False) -> NDArray:
        """``g`` (nx, ny) filtered with the Gaussian kernel (``squared``: with its square, for sums of
        squared weights); zero beyond the grid."""
        from scipy.ndimage import correlate1d

        k = self.kernel(bandwidth_m)
        if squared:
            k = k * k
        return correlate1d(correlate1d(g, k, axis=0, mode="constant"), k, axis=1, mode="constant")


@dataclass(frozen=True)
class RssField:
    """An AP's RSS field on a grid (module docstring); arrays (nx, ny), x along the first axis."""

    bssid: str
    origin: NDArray[np.float64]  # (2,) lower-left corner of cell (0, 0), metres
    cell_m: float
    bandwidth_m: float
    floor_dbm: float  # what a fingerprint that did not hear the AP counts as
    mean_dbm: NDArray[np.float64]  # NaN outside the surveyed area
    std_error_db: NDArray[np.float64]  # NaN outside, and where n_eff < 2
    weight: NDArray[np.float64]  # kernel weight W, in fingerprints
    n_eff: NDArray[np.float64]
    n_heard: int  # fingerprints that heard the AP

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(x0, x1, y0, y1) metres covered by the grid."""
        nx, ny = self.mean_dbm.shape
        x0, y0 = (float(v) for v in self.origin)
        return (x0, x0 + nx * self.cell_m, y0, y0 + ny * self.cell_m)

    @property
    def outside(self) -> NDArray[np.bool_]:
        """Cells outside the surveyed area (kernel weight below the threshold)."""
        return np.isnan(self.mean_dbm)


def ap_readings(rm: RadioMap, bssid: str) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
    """Every fingerprint's RSS of ``bssid`` (dBm; ``rm.min_rssi_dbm`` where it was not heard), and
    the rows that heard it."""
    col = rm.column(bssid)
    if col is None:
        raise ConfigError(f"RSS field: no fingerprint of the radio map heard access point {bssid}")
    values = rm.fingerprints.values.tocsc()
    lo, hi = values.indptr[col], values.indptr[col + 1]
    rss = np.full(len(rm), float(rm.min_rssi_dbm))
    rows = values.indices[lo:hi]
    rss[rows] = values.data[lo:hi] + rm.missing_dbm
    return rss, rows


def rss_field(
    rm: RadioMap,
    bssid: str,
    *,
    xy: NDArray | None = None,
    grid: FieldGrid | None = None,
    cell_m: float | None = None,
    bandwidth_m: float | None = None,
    min_weight: float = MIN_WEIGHT,
) -> RssField:
    """``bssid``'s RSS field over ``rm`` (module docstring). ``xy``: the fingerprints' positions to
    use (default ``rm.xy``; e.g. moved into a floor plan's frame); ``grid``: the grid, built on these
    positions (default one of ``cell_m``, else ``grid_cell_m``); ``bandwidth_m``: the kernel's std (default 2 cells)."""
    if not len(rm):
        raise ConfigError("RSS field: the radio map has no fingerprint")
    rss, heard = ap_readings(rm, bssid)
    return readings_field(rm.xy if xy is None else xy, rss, bssid, float(rm.min_rssi_dbm), n_heard=len(heard),
                          grid=grid, cell_m=cell_m, bandwidth_m=bandwidth_m, min_weight=min_weight)


def readings_field(
    xy: NDArray,
    rss: NDArray,
    bssid: str,
    floor_dbm: float,
    *,
    n_heard: int | None = None,
    grid: FieldGrid | None = None,
    cell_m: float | None = None,
    bandwidth_m: float | None = None,
    min_weight: float = MIN_WEIGHT,
) -> RssField:
    """The field of one reading per point: ``rss`` (N,) dBm at ``xy`` (N, 2), ``floor_dbm`` where the
    AP was not heard (``n_heard``: points that heard it; default: those above ``floor_dbm``); the
    other arguments as ``rss_field``'s."""
    rss = np.asarray(rss, float).ravel()
    xy = np.asarray(xy, float)
    if xy.shape != (len(rss), 2):
        raise ConfigError(f"RSS field: xy must be ({len(rss)}, 2), got {xy.shape}")
    if not len(rss):
        raise ConfigError("RSS field: no fingerprint")
    if not np.isfinite(rss).all() or not np.isfinite(xy).all():
        raise ConfigError("RSS field: positions and readings must be finite")
    if grid is None:
        grid = FieldGrid(xy, float(cell_m or grid_cell_m(xy)))
    h = float(bandwidth_m or 2.0 * grid.cell)
    ones = grid.bin(np.ones(len(xy)))
    W = grid.smooth(ones, h)
    W2 = grid.smooth(ones, h, squared=True)
    ref = float(np.mean(rss))  # centred: no cancellation in the variance
    d = rss - ref
    S1 = grid.smooth(grid.bin(d), h)
    S2 = grid.smooth(grid.bin(d * d), h)
    inside = W >= min_weight
    with np.errstate(invalid="ignore", divide="ignore"):
        m = np.where(inside, S1 / W, np.nan)
        var = np.maximum(S2 / W - m * m, 0.0)  # kernel-weighted variance of the readings
        n_eff = np.where(W2 > 0, W * W / W2, 0.0)
        se = np.where(inside & (n_eff >= 2.0), np.sqrt(var / (n_eff - 1.0)), np.nan)
    heard = int(np.count_nonzero(rss > floor_dbm)) if n_heard is None else int(n_heard)
    return RssField(bssid, np.asarray(grid.lo, float).copy(), grid.cell, h, float(floor_dbm), m + ref, se, W, n_eff,
                    heard)
