"""The filter papers' experiment in simulation: a cart pushed 5 times round a rectangle.

Papers 000 / 002, sec. IV: 4 APs at (0, 0), (0, 14.6), (8.2, 14.6), (8.2, 0) m; a velocity
sensor and a WiFi receiver sampled every T = 4 s; alignment angle theta = 0.1 rad.
What the papers do not give is chosen here, once, and documented in docs/tracking.md:

- path: the rectangle (1, 1) -> (1, 13.6) -> (7.2, 13.6) -> (7.2, 1) m (1 m inside the
  APs, starting at the papers' x0 = (1, 1) heading +y), walked at 0.1 m/s (x0's v_y);
- velocity sensor (eq. 4): ``M(theta) v + b + n`` with a constant bias ``b`` drawn per run,
  N(0, 0.015^2) (m/s) per axis, and white noise ``n`` of std 0.01 m/s (sqrt of the EKF's R);
- RSSI (eq. 5-6 with the paper's P0 / gamma): + shadowing, a Gaussian field per AP with
  std 4 dB and exponential (Gudmundson) correlation exp(-r / 3 m), fixed over the 5
  rounds (the same place always shadows the same way) + fast fading, white, std 3 dB,
  then rounded to whole dB (1 dB quantisation).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from graphslam.core.tracking.filters import PathLossModel, velocity_matrix
from graphslam.errors import SimulationError

PAPER_PERIOD_S = 4.0
PAPER_THETA_RAD = 0.1
PAPER_X0 = np.array([1.0, 1.0, 0.0, 0.1, 0.0, 0.0])
PAPER_P0 = 1e-3 * np.eye(6)
PAPER_RMS_TARGETS_M = {"ekf": (0.86, 1.15), "ukf": (0.75, 1.04)}  # the papers' RMS x / y (000 / 002)


@dataclass(frozen=True)
class CartNoise:
    """Sensor errors of the simulated cart (see module docstring). Units: m/s, dB, m."""

    bias_sigma_mps: float = 0.015
    velocity_sigma_mps: float = 0.01
    shadowing_sigma_db: float = 4.0
    shadowing_corr_m: float = 3.0
    fading_sigma_db: float = 3.0
    quantum_db: float = 1.0


@dataclass(frozen=True)
class CartPath:
    """Rectangle walked ``rounds`` times at ``speed_mps``, sampled every ``period_s``."""

    corners: tuple[tuple[float, float], ...] = ((1.0, 1.0), (1.0, 13.6), (7.2, 13.6), (7.2, 1.0))
    rounds: int = 5
    speed_mps: float = 0.1
    period_s: float = PAPER_PERIOD_S

    def positions(self) -> NDArray[np.float64]:
        """(N + 1, 2) positions at t = 0, T, ..., N T (m), N = rounds x perimeter / (speed T)."""
        c = np.asarray(self.corners, float)
        loop = np.vstack([c, c[:1]])
        seg = np.linalg.norm(np.diff(loop, axis=0), axis=1)
        perim = float(seg.sum())
        if self.rounds < 1 or self.speed_mps <= 0 or self.period_s <= 0 or perim <= 0:
            raise SimulationError("cart path: rounds, speed, period and perimeter must be > 0")
        n = int(round(self.rounds * perim / (self.speed_mps * self.period_s)))
        s = np.mod(np.arange(n + 1) * self.speed_mps * self.period_s, perim)  # arc length
        cum = np.concatenate([[0.0], np.cumsum(seg)])
        i = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
        f = (s - cum[i]) / seg[i]
        return loop[i] + f[:, None] * (loop[i + 1] - loop[i])


@dataclass(frozen=True, eq=False)
class CartRun:
    """One simulated experiment: truth and what the sensors reported, per epoch k (t = k T)."""

    t_s: NDArray[np.float64]  # (N,)
    xy: NDArray[np.float64]  # (N, 2) true position, m
    v: NDArray[np.float64]  # (N, 2) true velocity over [k T, (k+1) T], m/s
    bias: NDArray[np.float64]  # (2,) true velocity-sensor bias, m/s
    y_velocity: NDArray[np.float64]  # (N, 2) eq. 4 readings
    y_rssi: NDArray[np.float64]  # (N, 4) eq. 6 readings, dBm (whole dB)
    path_loss: PathLossModel
    theta_rad: float
    period_s: float


def _shadowing(xy: NDArray, n_aps: int, sigma: float, corr_m: float, rng: np.random.Generator) -> NDArray:
    """(N, A) Gaussian field values at ``xy``, exp(-r / corr) correlation, independent per AP."""
    # why: positions repeat every round; identical points must get identical shadowing
    u, inv = np.unique(np.round(xy, 6), axis=0, return_inverse=True)
    r = np.linalg.norm(u[:, None] - u[None], axis=2)
    L = np.linalg.cholesky(np.exp(-r / corr_m) + 1e-9 * np.eye(len(u)))
    return sigma * (L @ rng.standard_normal((len(u), n_aps)))[inv.ravel()]


def simulate_cart(
    seed: int,
    *,
    path_loss: PathLossModel | None = None,
    noise: CartNoise = CartNoise(),
    path: CartPath = CartPath(),
    theta_rad: float = PAPER_THETA_RAD,
) -> CartRun:
    """Simulate the papers' experiment; same seed, same run. ``path_loss`` defaults to Paper 000's."""
    pl = path_loss or PathLossModel.paper_ekf()
    rng = np.random.default_rng(seed)
    pts = path.positions()
    xy, v = pts[:-1], np.diff(pts, axis=0) / path.period_s  # p_{k+1} = p_k + T v_k (eq. 1)
    n = len(xy)
    bias = rng.normal(0.0, noise.bias_sigma_mps, 2)
    yv = v @ velocity_matrix(theta_rad).T + bias + rng.normal(0.0, noise.velocity_sigma_mps, (n, 2))
    shadow = _shadowing(xy, len(pl), noise.shadowing_sigma_db, noise.shadowing_corr_m, rng)
    rss = pl.mean_rss(xy) + shadow + rng.normal(0.0, noise.fading_sigma_db, (n, len(pl)))
    rss = noise.quantum_db * np.round(rss / noise.quantum_db)
    return CartRun(np.arange(n) * path.period_s, xy, v, bias, yv, rss, pl, theta_rad, path.period_s)
