"""The phone's magnetic field per step (``/phone/magnetic``, ``Session.magnetic``).

Frames: the field's components are Earth-frame east/north/up (µT), as ``/phone/magnetic``'s;
``north`` is magnetic north (the direction the phone's azimuth is referenced to); the field is a
function of the site-frame position (``graphslam.sim.heading`` relates the two frames' angles).

The site's field at a site-frame position p (one per site, the same for every walk):

    B(p) = (0, H, V) + a(p)

- (0, H, V): the Earth's field, horizontal ``horizontal_ut`` to the north and vertical
  ``vertical_ut`` (negative: pointing down, a northern-hemisphere inclination);
- a(p) = g(p) exp(s(p) - s2): the building's anomaly. g: three independent smooth Gaussian fields
  (east, north, up) of correlation exp(-(r / anomaly_corr_m)^2); s: one smooth Gaussian field of
  std ``envelope_sigma`` (natural log of the amplitude) and correlation exp(-(r / envelope_corr_m)^2)
  shared by the three, so that the field is strong in places (steel) and calm in others, as real
  floors are (on IPIN 2023 floor -2 and ILC site1 F1 the rms of 10 m stretches spans a factor 4.2-4.3
  between its 10th and 90th percentiles: lab/scripts/magnetic_field_shape.py); s2 =
  ``envelope_sigma``^2, which makes the std of each component ``anomaly_sigma_ut``. On a
  ``grid_m`` grid over the plan, bilinear in between.

What the phone records at step k >= 1 (the ``/phone/heading`` timestamps: the step timestamps
after the first, one message each), µT:

    b_k = mean of B over the true path from step k-1 to step k (``samples_per_step`` points)
          + o + n_k
    east_k, north_k = |b_k,horizontal| * (sin e_k, cos e_k),  up_k = b_k,up

- o: the walk's device/calibration offset, N(0, offset_sigma^2) per component, or with
  probability ``large_offset_prob`` one of magnitude U(``large_offset_ut``) in a random
  direction (the 10-30 µT jumps of some phones);
- n_k: white noise per step and component (the magnetometer's, the hand's motion);
- e_k: the orientation's azimuth error per step, std ``azimuth_sigma_deg``, correlation
  exp(-(lag / ``azimuth_corr_steps``)^2). The phone's orientation is referenced to the
  magnetometer, so the recorded horizontal part points to magnetic north by construction: ``east``
  is 0 up to this error, ``north`` is the local horizontal magnitude, ``up`` the vertical component.

Simplifications: the anomaly is a random vector field, not a potential field (no physics ties its
components); an offset is constant in the Earth frame (a residual hard-iron offset lives in the
phone's frame and turns with it); standing still within a step's interval is not weighted. The
phone's azimuth (``graphslam.sim.heading``) keeps a distortion field of its own (7 deg over 7 m),
drawn independently of this one. Physically both are one field: the azimuth's error is the local
horizontal field's direction, atan2(a_east, H + a_north) (~0.2 rad over ~2.5 m with the
defaults), smoothed by the rotation vector's gyroscope; the heading simulation is kept as it was so that every figure
measured on it stays.

Every draw comes from generators of its own (``graphslam.sim.scenarios``), never from a walk's own
stream or the heading's, so switching the field on or off changes no other simulated value.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from graphslam.core.types import MagneticTrack, PoseTrack
from graphslam.errors import ConfigError, SimulationError
from graphslam.sim.floorplan import FloorPlan
from graphslam.sim.radio import ShadowingField, gaussian_field
from graphslam.sim.walker import smooth_noise


@dataclass(frozen=True)
class MagneticModel:
    """The site's magnetic field and the phone's recording of it (µT, metres, degrees); see the module docstring.

    ``enabled=False``: no ``/phone/magnetic`` (``Session.magnetic`` is None), no field drawn. Defaults:
    the Earth's field at a central European site (Nuremberg: ~20 µT horizontal, ~44 µT down); anomaly,
    offsets and noise of the size IPIN 2023 floor -2 shows (docs/simulator.md).
    """

    enabled: bool = True
    horizontal_ut: float = 20.0  # the Earth's field, horizontal (to magnetic north)
    vertical_ut: float = -44.0  # ... and vertical (up; < 0: pointing down)
    anomaly_sigma_ut: float = 4.5  # the building's anomaly, std per component (calm places much less)
    anomaly_corr_m: float = 2.5  # its correlation exp(-1) distance
    envelope_sigma: float = 0.5  # the anomaly's amplitude varies over the floor: log-amplitude std ...
    envelope_corr_m: float = 6.0  # ... correlation exp(-1) distance
    grid_m: float = 0.5  # the anomaly's grid spacing (bilinear in between)
    offset_sigma_ut: float = 2.5  # per walk: device/calibration offset, Gaussian std per component ...
    large_offset_prob: float = 0.05  # ... or with this probability a large one ...
    large_offset_ut: tuple[float, float] = (10.0, 30.0)  # ... of magnitude uniform in this range, random direction
    noise_sigma_ut: float = 0.4  # white, per step and component
    azimuth_sigma_deg: float = 7.0  # the orientation's azimuth error per step (east = |B_h| sin of it) ...
    azimuth_corr_steps: float = 1.0  # ... correlation exp(-1) lag in steps
    samples_per_step: int = 4  # points of the path from the previous step averaged per step

    def __post_init__(self) -> None:
        values = (
            self.horizontal_ut, self.vertical_ut, self.anomaly_sigma_ut, self.anomaly_corr_m, self.grid_m,
            self.envelope_sigma, self.envelope_corr_m,
            self.offset_sigma_ut, self.large_offset_prob, *self.large_offset_ut, self.noise_sigma_ut,
            self.azimuth_sigma_deg, self.azimuth_corr_steps,
        )
        if not all(math.isfinite(v) for v in values):
            raise ConfigError("MagneticModel: every parameter must be finite")
        for name in ("anomaly_sigma_ut", "envelope_sigma", "offset_sigma_ut", "noise_sigma_ut", "azimuth_sigma_deg"):
            if getattr(self, name) < 0:
                raise ConfigError(f"MagneticModel.{name} must be >= 0")
        if min(self.anomaly_corr_m, self.envelope_corr_m, self.grid_m, self.azimuth_corr_steps) <= 0:
            raise ConfigError(
                "MagneticModel.anomaly_corr_m, envelope_corr_m, grid_m and azimuth_corr_steps must be > 0"
            )
        if not 0 <= self.large_offset_prob <= 1:
            raise ConfigError("MagneticModel.large_offset_prob must be in [0, 1]")
        lo, hi = self.large_offset_ut
        if not 0 <= lo <= hi:
            raise ConfigError(f"MagneticModel.large_offset_ut: need 0 <= low <= high, got {self.large_offset_ut}")
        if self.samples_per_step < 1:
            raise ConfigError("MagneticModel.samples_per_step must be >= 1")

    @property
    def earth_ut(self) -> NDArray[np.float64]:
        """The Earth's field (east, north, up), µT."""
        return np.array([0.0, self.horizontal_ut, self.vertical_ut])


def anomaly_field(plan: FloorPlan, model: MagneticModel, rng: np.random.Generator) -> ShadowingField:
    """The building's anomaly (µT; layers east, north, up) on a ``grid_m`` grid over ``plan``.

    Padded by twice the correlation length, as the shadowing is: the FFT field is periodic over its
    grid, and the padding keeps opposite edges of the floor uncorrelated.
    """
    if not model.enabled:
        raise SimulationError("anomaly_field: the magnetic model is disabled")
    pad = 2.0 * max(model.anomaly_corr_m, model.envelope_corr_m)
    nx = int(np.ceil((plan.width_m + 2 * pad) / model.grid_m)) + 1
    ny = int(np.ceil((plan.height_m + 2 * pad) / model.grid_m)) + 1
    if model.anomaly_sigma_ut == 0:
        return ShadowingField((-pad, -pad), model.grid_m, np.zeros((3, ny, nx)))
    s2 = model.envelope_sigma**2
    g = gaussian_field(rng, (3, ny, nx), model.anomaly_sigma_ut * math.exp(-s2), model.anomaly_corr_m / model.grid_m)
    if model.envelope_sigma > 0:
        # E[exp(2 s)] = exp(2 s2): the std of g exp(s) is sigma_g exp(s2) = anomaly_sigma_ut
        g = g * np.exp(gaussian_field(rng, (1, ny, nx), model.envelope_sigma, model.envelope_corr_m / model.grid_m))
    else:
        g = g * math.exp(s2)
    return ShadowingField((-pad, -pad), model.grid_m, g)


def field_at(xy: NDArray, model: MagneticModel, anomaly: ShadowingField) -> NDArray[np.float64]:
    """(N, 3) the site's field (east, north, up; µT) at site-frame points ``xy`` (N, 2): Earth + anomaly."""
    return anomaly.at(xy) + model.earth_ut


def walk_offset(model: MagneticModel, rng: np.random.Generator) -> NDArray[np.float64]:
    """One walk's device/calibration offset (east, north, up; µT). Always eight draws, whichever branch."""
    gauss = rng.normal(0.0, model.offset_sigma_ut, 3)
    large = rng.random() < model.large_offset_prob
    size = rng.uniform(*model.large_offset_ut)
    direction = rng.normal(0.0, 1.0, 3)
    norm = float(np.linalg.norm(direction))
    return size * direction / norm if large and norm > 0 else gauss


def phone_magnetic(
    truth: PoseTrack, model: MagneticModel, anomaly: ShadowingField, rng: np.random.Generator
) -> MagneticTrack:
    """The phone's field (east, north, up; µT) at ``truth``'s step timestamps after the first.

    Draws the walk's offset first (``walk_offset``), then the noise (steps x 3), then the azimuth errors.
    """
    if not model.enabled:
        raise SimulationError("phone_magnetic: the magnetic model is disabled")
    offset = walk_offset(model, rng)
    xy = np.asarray(truth.xy, dtype=float)
    n = len(xy) - 1
    noise = rng.normal(0.0, model.noise_sigma_ut, (n, 3))
    azimuth = smooth_noise(rng, n, math.radians(model.azimuth_sigma_deg), model.azimuth_corr_steps)
    # The mean over each step's path (the magnetometer runs at tens of Hz; the phone averages since
    # the previous step): points at the centres of equal parts of the segment.
    f = (np.arange(model.samples_per_step) + 0.5) / model.samples_per_step
    pts = xy[:-1, None, :] + f[None, :, None] * (xy[1:] - xy[:-1])[:, None, :]
    b = field_at(pts.reshape(-1, 2), model, anomaly).reshape(n, model.samples_per_step, 3).mean(axis=1)
    b = b + offset + noise
    horizontal = np.hypot(b[:, 0], b[:, 1])
    enu = np.column_stack([horizontal * np.sin(azimuth), horizontal * np.cos(azimuth), b[:, 2]])
    return MagneticTrack(truth.t_ns[1:], enu)
