"""WiFi radio model of the simulator.

Mean received power of access point ``a`` at a phone at ``p`` (site frame, m):

    mean_a(p) = P0_a - 10 * gamma_a * log10(d_a(p)) - L_wall * n_walls_a(p) + S_a(p)

- the log-distance path loss of eq. 5 of Paper 000 (``P0`` = RSS at 1 m, dBm;
  ``gamma`` = path-loss exponent), with per-AP ``P0`` and ``gamma``;
- ``d`` is the 3-D distance with the AP ``ap_height_m`` above the phone, which
  keeps the model finite under the AP (a ceiling AP is never closer than that);
- ``n_walls`` = number of wall segments crossed by the straight line AP -> phone,
  each costing ``wall_loss_db``;
- ``S_a`` = shadowing: a zero-mean Gaussian random field per AP, fixed for the
  building (every walker sees the same field), std ``shadowing_sigma_db``, with
  correlation ``exp(-(r / shadowing_corr_m)^2)`` between points r metres apart.
- APs on another floor (``other_floor_fraction`` of them, none by default) are
  ``floor_height_m`` higher, with their own P0 (the slab's loss included) and gamma,
  and lose nothing to this floor's walls: they are heard widely, with a slowly
  varying RSS.

A scan reading adds independent Gaussian noise (``noise_sigma_db``), is rounded
to whole dBm (phones report integers), and is reported only when it is at least
``floor_dbm`` and not randomly missed (``miss_prob``, plus up to
``weak_miss_prob`` more for readings within ``weak_band_db`` of the floor:
phones drop weak beacons more often).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from graphslam.core.types import Scan, frozen_array
from graphslam.errors import ConfigError
from graphslam.sim.floorplan import FloorPlan

log = logging.getLogger(__name__)

# Cells (points x APs x walls) per block of the wall-crossing test: small enough to
# stay in cache (measured faster than 16M-cell blocks).
_MAX_CELLS = 2_000_000



@dataclass(frozen=True)
class RadioParams:
    """Parameters of the radio model (dB, dBm, metres). See the module docstring."""

    p0_dbm_range: tuple[float, float] = (-42.0, -32.0)  # per-AP P0, uniform in this range
    gamma_range: tuple[float, float] = (1.8, 2.8)  # per-AP path-loss exponent, uniform
    ap_height_m: float = 1.5  # AP (ceiling) above phone (hand)
    wall_loss_db: float = 3.5  # per wall crossed (plasterboard / glass: 2-5 dB)
    shadowing_sigma_db: float = 4.0
    shadowing_corr_m: float = 4.0  # correlation exp(-1) at this distance
    shadowing_grid_m: float = 1.0  # field sampled on this grid, bilinear in between
    noise_sigma_db: float = 3.0  # per reading, independent between scans
    floor_dbm: float = -95.0  # weaker readings are never reported
    miss_prob: float = 0.05  # any reading is dropped with this probability ...
    weak_miss_prob: float = 0.25  # ... plus up to this much more near the floor
    weak_band_db: float = 10.0  # width of the "near the floor" band
    ap_min_separation_m: float = 5.0  # APs are placed at least this far apart
    other_floor_fraction: float = 0.0  # share of the APs on the floor above (heard through the slab)
    other_floor_p0_dbm_range: tuple[float, float] = (-50.0, -40.0)  # their P0, the slab's loss included
    other_floor_gamma_range: tuple[float, float] = (1.8, 2.2)  # their path-loss exponent (open floor above)
    floor_height_m: float = 4.0  # height of a floor

    def __post_init__(self) -> None:
        lo, hi = self.p0_dbm_range
        glo, ghi = self.gamma_range
        olo, ohi = self.other_floor_gamma_range
        plo, phi = self.other_floor_p0_dbm_range
        if not (lo <= hi and 0 < glo <= ghi and 0 < olo <= ohi and plo <= phi):
            raise ConfigError(
                f"RadioParams: bad P0 range {self.p0_dbm_range} or gamma range {self.gamma_range} "
                f"(other floor: {self.other_floor_p0_dbm_range}, {self.other_floor_gamma_range})"
            )
        for name in (
            "ap_height_m", "wall_loss_db", "shadowing_sigma_db", "noise_sigma_db", "weak_band_db", "floor_height_m",
        ):
            if getattr(self, name) < 0:
                raise ConfigError(f"RadioParams: {name} must be >= 0")
        if self.shadowing_corr_m <= 0 or self.shadowing_grid_m <= 0:
            raise ConfigError("RadioParams: shadowing_corr_m and shadowing_grid_m must be > 0")
        if not (0 <= self.miss_prob <= 1 and 0 <= self.weak_miss_prob <= 1 - self.miss_prob):
            raise ConfigError("RadioParams: miss probabilities must be in [0, 1] and sum to <= 1")
        if not 0 <= self.other_floor_fraction <= 1:
            raise ConfigError("RadioParams: other_floor_fraction must be in [0, 1]")


@dataclass(frozen=True, eq=False)
class AccessPoints:
    """AP table: ``bssids[i]`` is at ``xy[i]`` (site frame, m) with ``p0_dbm[i]``, ``gamma[i]``,
    ``floor_offset[i]`` floors above this one (0: on this floor)."""

    bssids: tuple[str, ...]
    xy: NDArray[np.float64]  # (A, 2)
    p0_dbm: NDArray[np.float64]  # (A,)
    gamma: NDArray[np.float64]  # (A,)
    floor_offset: NDArray[np.int64] | None = None  # (A,), None: all on this floor

    def __post_init__(self) -> None:
        object.__setattr__(self, "bssids", tuple(self.bssids))
        object.__setattr__(self, "xy", frozen_array(np.reshape(self.xy, (-1, 2)), np.float64))
        object.__setattr__(self, "p0_dbm", frozen_array(self.p0_dbm, np.float64))
        object.__setattr__(self, "gamma", frozen_array(self.gamma, np.float64))
        n = len(self.bssids)
        off = np.zeros(n, np.int64) if self.floor_offset is None else self.floor_offset
        object.__setattr__(self, "floor_offset", frozen_array(off, np.int64))
        if not (len(self.xy) == len(self.p0_dbm) == len(self.gamma) == len(off) == n):
            raise ConfigError("AccessPoints: bssids, xy, p0_dbm, gamma and floor_offset must have the same length")
        if len(set(self.bssids)) != n:
            raise ConfigError("AccessPoints: duplicate BSSID")

    def __len__(self) -> int:
        return len(self.bssids)


@dataclass(frozen=True, eq=False)
class ShadowingField:
    """Per-AP shadowing (dB) on a regular grid; ``values[a, iy, ix]`` at ``origin + (ix, iy) * spacing``."""

    origin: tuple[float, float]
    spacing_m: float
    values: NDArray[np.float64]  # (A, ny, nx)

    def __post_init__(self) -> None:
        object.__setattr__(self, "values", frozen_array(self.values, np.float64))

    def at(self, xy: NDArray) -> NDArray[np.float64]:
        """(N, A) shadowing at points ``xy`` (N, 2), bilinear; clamped outside the grid."""
        xy = np.reshape(np.asarray(xy, dtype=float), (-1, 2))
        _, ny, nx = self.values.shape
        gx = np.clip((xy[:, 0] - self.origin[0]) / self.spacing_m, 0.0, nx - 1.000001)
        gy = np.clip((xy[:, 1] - self.origin[1]) / self.spacing_m, 0.0, ny - 1.000001)
        ix, iy = gx.astype(np.int64), gy.astype(np.int64)
        fx, fy = (gx - ix)[:, None], (gy - iy)[:, None]
        v = self.values
        return (
            v[:, iy, ix].T * (1 - fx) * (1 - fy)
            + v[:, iy, ix + 1].T * fx * (1 - fy)
            + v[:, iy + 1, ix].T * (1 - fx) * fy
            + v[:, iy + 1, ix + 1].T * fx * fy
        )


def gaussian_field(
    rng: np.random.Generator, shape: tuple[int, ...], sigma: float, corr_cells: float
) -> NDArray[np.float64]:
    """Zero-mean stationary Gaussian field(s), std ``sigma``, correlation exp(-(r/corr_cells)^2).

    White noise convolved (periodically, by FFT, over the last two axes) with a
    Gaussian kernel of std ``corr_cells / 2`` has exactly that correlation; the
    scale factor comes from the discrete kernel, so the marginal std is ``sigma``.
    """
    ny, nx = shape[-2:]
    k_sigma = corr_cells / 2.0

    def kernel(n: int) -> NDArray[np.float64]:
        i = np.arange(n)
        d = np.minimum(i, n - i)  # periodic distance to cell 0
        return np.exp(-0.5 * (d / k_sigma) ** 2)

    ky, kx = kernel(ny), kernel(nx)
    transfer = np.fft.rfft2(np.outer(ky, kx))
    smooth = np.fft.irfft2(np.fft.rfft2(rng.standard_normal(shape)) * transfer, s=(ny, nx))
    return smooth * (sigma / (np.sqrt(np.sum(ky**2)) * np.sqrt(np.sum(kx**2))))


def wall_crossings(points: NDArray, aps: NDArray, walls: NDArray) -> NDArray[np.int32]:
    """(N, A) number of wall segments properly crossed by each segment point -> AP.

    Vectorised orientation test: segments PA and W1W2 cross iff P, A are strictly
    on opposite sides of line W1W2 and W1, W2 strictly on opposite sides of line
    PA. Both tests are affine in P, so their coefficients are computed once per
    (AP, wall) and evaluated for blocks of points at once; the blocks keep the
    (block, A, W) temporaries cache-sized.
    """
    p = np.reshape(np.asarray(points, dtype=np.float64), (-1, 2))
    a = np.reshape(np.asarray(aps, dtype=np.float64), (-1, 2))
    w = np.reshape(np.asarray(walls, dtype=np.float64), (-1, 4))
    n, na, nw = len(p), len(a), len(w)
    out = np.zeros((n, na), dtype=np.int32)
    if n == 0 or na == 0 or nw == 0:
        return out
    w1, w2 = w[:, :2], w[:, 2:]
    d = w2 - w1
    # side of line W (sign of cross(d, q - w1)) = q . nrm + off; signs from float64, kept as float32
    nrm = np.column_stack([-d[:, 1], d[:, 0]])  # (W, 2)
    off = -np.sum(w1 * nrm, axis=1)  # (W,)
    side_a = (a[:, :1] * nrm[:, 0] + a[:, 1:] * nrm[:, 1] + off).astype(np.float32)  # (A, W)
    # side of line AP for wall end e: cross(p - a, e - a) = p . (e_y - a_y, a_x - e_x) - (a_x e_y - a_y e_x)
    coef = []
    for e in (w1, w2):
        ex = e[None, :, 0] - a[:, None, 0]  # (A, W)
        ey = e[None, :, 1] - a[:, None, 1]
        c0 = -(a[:, None, 0] * e[None, :, 1] - a[:, None, 1] * e[None, :, 0])
        coef.append((np.stack([ey, -ex]).reshape(2, -1).astype(np.float32), c0.reshape(-1).astype(np.float32)))
    block = max(1, _MAX_CELLS // (na * nw))
    for s in range(0, n, block):
        pb = p[s : s + block]
        # Explicit products, not matmul: with an inner dimension of 2, BLAS threading
        # costs more than it saves (measured slower on a busy machine).
        side_p = (pb[:, :1] * nrm[:, 0] + pb[:, 1:] * nrm[:, 1] + off).astype(np.float32)  # (B, W)
        opposite = (side_p[:, None, :] * side_a[None, :, :]) < 0  # (B, A, W)
        px, py = pb[:, :1].astype(np.float32), pb[:, 1:].astype(np.float32)
        t = px * coef[0][0][0] + py * coef[0][0][1] + coef[0][1]  # (B, A*W)
        t *= px * coef[1][0][0] + py * coef[1][0][1] + coef[1][1]
        cross = (t < 0).reshape(len(pb), na, nw)
        cross &= opposite
        out[s : s + block] = cross.view(np.uint8).sum(axis=2, dtype=np.int32)
    return out


@dataclass(frozen=True, eq=False)
class RadioEnvironment:
    """Access points, walls and shadowing of one building, with the RSS model."""

    params: RadioParams
    aps: AccessPoints
    walls: NDArray[np.float64]  # (W, 4) site frame
    shadowing: ShadowingField

    def __post_init__(self) -> None:
        object.__setattr__(self, "walls", frozen_array(np.reshape(self.walls, (-1, 4)), np.float64))

    @property
    def bssids(self) -> tuple[str, ...]:
        return self.aps.bssids

    def distances(self, xy: NDArray) -> NDArray[np.float64]:
        """(N, A) 3-D distance phone -> AP (m), the ``d`` of the path-loss model."""
        xy = np.reshape(np.asarray(xy, dtype=float), (-1, 2))
        d2 = np.sum((xy[:, None, :] - self.aps.xy[None, :, :]) ** 2, axis=2)
        height = self.params.ap_height_m + self.params.floor_height_m * np.abs(self._floor_offset())
        return np.sqrt(d2 + height[None, :] ** 2)

    def _floor_offset(self) -> NDArray[np.int64]:
        off = self.aps.floor_offset
        assert off is not None  # set by AccessPoints.__post_init__
        return off

    def mean_rss(self, xy: NDArray, *, walls: bool = True, shadowing: bool = True) -> NDArray[np.float64]:
        """(N, A) noiseless mean RSS (dBm) of every AP (columns in ``bssids`` order) at ``xy`` (N, 2).

        ``walls`` / ``shadowing`` switch those terms off (e.g. to test the pure
        path-loss law). No noise, no floor, no quantisation.
        """
        xy = np.reshape(np.asarray(xy, dtype=float), (-1, 2))
        rss = self.aps.p0_dbm[None, :] - 10.0 * self.aps.gamma[None, :] * np.log10(self.distances(xy))
        other = self._floor_offset() != 0
        if walls and self.params.wall_loss_db > 0:
            here = np.flatnonzero(~other)  # APs on another floor lose nothing to this floor's walls
            rss[:, here] -= self.params.wall_loss_db * wall_crossings(xy, self.aps.xy[here], self.walls)
        if shadowing:
            rss = rss + self.shadowing.at(xy)
        return rss

    def sample_rss(
        self, xy: NDArray, rng: np.random.Generator, offset_db: float | NDArray = 0.0
    ) -> NDArray[np.float64]:
        """(N, A) one scan's readings per row: integer dBm, NaN where not reported.

        ``offset_db`` (dB, broadcast to (N, A)) is added to the mean before the noise
        and the floor: e.g. a phone model's constant offset (a weaker radio reads lower
        and so also hears fewer APs).
        """
        p = self.params
        mean = self.mean_rss(xy) + offset_db
        r = np.round(mean + rng.normal(0.0, p.noise_sigma_db, mean.shape))
        u = rng.random(mean.shape)
        weak = np.clip((p.floor_dbm + p.weak_band_db - r) / max(p.weak_band_db, 1e-9), 0.0, 1.0)
        heard = (r >= p.floor_dbm) & (u >= p.miss_prob + p.weak_miss_prob * weak)
        return np.where(heard, r, np.nan)

    def scans(self, t_ns: NDArray, xy: NDArray, rng: np.random.Generator) -> tuple[Scan, ...]:
        """One ``Scan`` per (time, position); readings ordered strongest first."""
        return self.scans_from_rss(t_ns, self.sample_rss(xy, rng))

    def scans_from_rss(self, t_ns: NDArray, r: NDArray) -> tuple[Scan, ...]:
        """One ``Scan`` per row of ``r`` ((N, A) dBm, NaN = not heard, columns in ``bssids`` order)."""
        out = []
        for t, row in zip(np.asarray(t_ns).tolist(), r):
            idx = np.flatnonzero(~np.isnan(row))
            idx = idx[np.argsort(-row[idx], kind="stable")]
            out.append(Scan(int(t), {self.aps.bssids[i]: float(row[i]) for i in idx}))
        return tuple(out)


def bssid(i: int) -> str:
    """Deterministic locally administered MAC address of simulated AP ``i``."""
    return f"02:00:00:{(i >> 16) & 255:02x}:{(i >> 8) & 255:02x}:{i & 255:02x}"


def place_access_points(
    plan: FloorPlan, n_aps: int, params: RadioParams, rng: np.random.Generator
) -> AccessPoints:
    """``n_aps`` APs uniformly over the floor, at least ``ap_min_separation_m`` apart where possible."""
    if n_aps < 1:
        raise ConfigError(f"need at least one access point, got {n_aps}")
    margin = 1.0
    lo = np.array([margin, margin])
    hi = np.array([plan.width_m - margin, plan.height_m - margin])
    xy: list[NDArray] = []
    sep = params.ap_min_separation_m
    tries = 0
    while len(xy) < n_aps:
        cand = lo + rng.random(2) * (hi - lo)
        tries += 1
        if tries > 200 * n_aps:  # floor too small for the separation: relax it
            sep *= 0.8
            tries = 0
            log.debug("AP placement: relaxing separation to %.2f m", sep)
        if not xy or np.min(np.linalg.norm(np.array(xy) - cand, axis=1)) >= sep:
            xy.append(cand)
    p0 = rng.uniform(*params.p0_dbm_range, n_aps)
    gamma = rng.uniform(*params.gamma_range, n_aps)
    offset = np.zeros(n_aps, np.int64)
    if params.other_floor_fraction > 0:  # drawn last: the other scenarios' APs stay as they were
        up = rng.choice(n_aps, int(round(params.other_floor_fraction * n_aps)), replace=False)
        offset[up] = 1
        p0[up] = rng.uniform(*params.other_floor_p0_dbm_range, len(up))
        gamma[up] = rng.uniform(*params.other_floor_gamma_range, len(up))
    return AccessPoints(tuple(bssid(i) for i in range(n_aps)), np.array(xy), p0, gamma, offset)


def make_radio(plan: FloorPlan, n_aps: int, params: RadioParams, rng: np.random.Generator) -> RadioEnvironment:
    """APs, P0/gamma and shadowing fields for ``plan``, drawn from ``rng``."""
    aps = place_access_points(plan, n_aps, params, rng)
    g = params.shadowing_grid_m
    pad = 2.0 * params.shadowing_corr_m
    nx = int(np.ceil((plan.width_m + 2 * pad) / g)) + 1
    ny = int(np.ceil((plan.height_m + 2 * pad) / g)) + 1
    if params.shadowing_sigma_db > 0:
        values = gaussian_field(rng, (n_aps, ny, nx), params.shadowing_sigma_db, params.shadowing_corr_m / g)
    else:
        values = np.zeros((n_aps, ny, nx))
    field = ShadowingField((-pad, -pad), g, values)
    return RadioEnvironment(params, aps, plan.walls, field)
