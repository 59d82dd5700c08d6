"""The odometry chain every pose graph shares (survey and UWB): IMU-between factors (eq. 6-8),
built from GTSAM's native ``BetweenFactorPose2``, and the reference pose's prior.

GTSAM is imported where a factor is built: a graph solved by the vectorised solver never loads it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from graphslam.config import ImuConfig
from graphslam.core.types import PoseTrack, wrap_angle

if TYPE_CHECKING:
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
