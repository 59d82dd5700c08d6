"""The paper's two factor types, built from GTSAM's native (C++) factors, and the magnetic pairs.

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

Magnetic pair (``graphslam.core.survey.magnetic``)
    Two step poses a magnetic link says are one place: the same dead-zone range factor with its own
    sigma and dead zone (``MagneticConfig.sigma_m``, from ``window_sigma_m``: the match's own precision, each
    window's factors counted once together; ``d_min_m``), saturated
    beyond ``magnetic.d_max_m`` as the WiFi factor is beyond d_max.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from graphslam.config import MagneticConfig, WifiFactorConfig
from graphslam.core.common.factors import (  # noqa: F401 (re-exported: the survey's IMU chain)
    REFERENCE_PRIOR_SIGMAS, imu_factor, imu_noise, reference_prior_noise, relative_steps,
)

if TYPE_CHECKING:  # gtsam is imported where a factor is built: a survey solved by solver.py never loads it
    import gtsam

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


def magnetic_noise(cfg: MagneticConfig) -> gtsam.noiseModel.Base:
    """A magnetic pair's noise: the dead-zone range loss of the WiFi factor with the magnetic sigma and dead zone."""
    import gtsam

    loss = gtsam.noiseModel.mEstimator.L2WithDeadZone(cfg.d_min_m / cfg.sigma_m)
    return gtsam.noiseModel.Robust.Create(loss, gtsam.noiseModel.Isotropic.Sigma(1, cfg.sigma_m))


def magnetic_cost(d: NDArray | float, cfg: MagneticConfig) -> NDArray:
    """0.5 ((d - d_min) / sigma)^2 per magnetic pair between d_min and d_max, flat beyond (saturated)."""
    e = (np.clip(np.asarray(d, dtype=float), cfg.d_min_m, cfg.d_max_m) - cfg.d_min_m) / cfg.sigma_m
    return 0.5 * e * e
