"""The paper's two factor types, built from GTSAM's native (C++) factors.

IMU-between factor (eq. 6-8)
    u_{k-1,k} = pos_{k-1}^{-1} * pos_k, the step in the body frame of pose k-1, is
    measured by the foot module. GTSAM's ``BetweenFactorPose2`` uses the error
    Log(u^{-1} * u_nodes), which equals eq. 7's u_nodes - u to first order (the
    per-step errors here are centimetres and milliradians). Omega_IMU (eq. 8) is
    written as standard deviations: Omega = diag(1/sx^2, 1/sx^2, 1/sh^2).

Fuzzy WiFi-vicinity factor (eq. 10)
    e(d) = 0 for d < d_min, e_max (d - d_min)/(d_max - d_min) on the ramp, e_max
    beyond d_max, d = |p_k - p_q|; cost Omega_W e^2 (GTSAM's 0.5 factor in both).
    On the ramp this is exactly a ``RangeFactorPose2`` with measured range 0 and
    sigma = (d_max - d_min) / (e_max sqrt(Omega_W)) under GTSAM's
    ``L2WithDeadZone(k = d_min / sigma)`` loss: 0.5 (|d|/sigma - k)^2. Beyond d_max
    the paper's error is flat (zero gradient): the optimiser drops such edges from
    the active set between LM runs (``graphslam.core.survey.align.solve``), so no Python code
    runs inside GTSAM's inner loop.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from graphslam.config import ImuConfig, WifiFactorConfig
from graphslam.core.types import PoseTrack, wrap_angle

if TYPE_CHECKING:  # gtsam is imported where a factor is built: a survey solved by solver.py never loads it
    import gtsam

# The reference pose is "invariant during optimisation" (paper III-A): a prior this
# tight fixes it to numerical precision without a hard constraint, which LM handles badly.
REFERENCE_PRIOR_SIGMAS = np.array([1e-6, 1e-6, 1e-6])


def reference_prior_noise() -> gtsam.noiseModel.Base:
    import gtsam

    return gtsam.noiseModel.Diagonal.Sigmas(REFERENCE_PRIOR_SIGMAS)


def imu_noise(cfg: ImuConfig) -> gtsam.noiseModel.Base:
    """Omega_IMU of eq. 8 as a diagonal Gaussian."""
    import gtsam

    return gtsam.noiseModel.Diagonal.Sigmas(np.array([cfg.sigma_xy_m, cfg.sigma_xy_m, cfg.sigma_heading_rad]))


def relative_steps(track: PoseTrack) -> NDArray[np.float64]:
    """(N-1, 3) step increments (dx, dy, dtheta) in the body frame of the earlier pose (eq. 6 inverted)."""
    xy, h = track.xy, track.heading
    d = np.diff(xy, axis=0)
    c, s = np.cos(h[:-1]), np.sin(h[:-1])
    return np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], wrap_angle(np.diff(h))])


def imu_factor(k_prev: int, k: int, u: NDArray | tuple[float, float, float], noise: gtsam.noiseModel.Base) -> gtsam.NonlinearFactor:
    import gtsam

    return gtsam.BetweenFactorPose2(k_prev, k, gtsam.Pose2(float(u[0]), float(u[1]), float(u[2])), noise)


def wifi_sigma(cfg: WifiFactorConfig) -> float:
    """Range sigma that makes the dead-zone loss equal Omega_W * e(d)^2 on the ramp."""
    return (cfg.d_max_m - cfg.d_min_m) / (cfg.e_max * float(np.sqrt(cfg.omega)))


def wifi_noise(cfg: WifiFactorConfig) -> gtsam.noiseModel.Base:
    import gtsam

    sigma = wifi_sigma(cfg)
    loss = gtsam.noiseModel.mEstimator.L2WithDeadZone(cfg.d_min_m / sigma)
    return gtsam.noiseModel.Robust.Create(loss, gtsam.noiseModel.Isotropic.Sigma(1, sigma))


def wifi_factor(k: int, q: int, noise: gtsam.noiseModel.Base) -> gtsam.NonlinearFactor:
    import gtsam

    return gtsam.RangeFactorPose2(k, q, 0.0, noise)


def fuzzy_error(d: NDArray | float, cfg: WifiFactorConfig) -> NDArray:
    """Eq. 10, vectorised: e_Wifi as a function of metric distance d."""
    r = (np.asarray(d, dtype=float) - cfg.d_min_m) / (cfg.d_max_m - cfg.d_min_m)
    return cfg.e_max * np.clip(r, 0.0, 1.0)


def fuzzy_cost(d: NDArray | float, cfg: WifiFactorConfig) -> NDArray:
    """0.5 * Omega_W * e(d)^2 per edge (GTSAM's error convention), saturated beyond d_max."""
    return 0.5 * cfg.omega * fuzzy_error(d, cfg) ** 2


def edge_state(d: NDArray, cfg: WifiFactorConfig) -> NDArray[np.int8]:
    """0 = inactive (d < d_min), 1 = on the fuzzy ramp, 2 = saturated (d > d_max)."""
    d = np.asarray(d)
    return np.where(d < cfg.d_min_m, 0, np.where(d > cfg.d_max_m, 2, 1)).astype(np.int8)
