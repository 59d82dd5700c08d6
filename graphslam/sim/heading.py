"""The phone's own azimuth per step (``/phone/heading``, ``Session.heading``).

Frames: the simulator's *site* frame is the building's own (metres; angles counter-clockwise
from site +x). The *Earth* frame is east/north (angles counter-clockwise from east). One
fixed rotation per site relates them:

    angle_earth = angle_site + earth_from_site

so a site direction at angle a points at Earth azimuth a + earth_from_site.

The phone's yaw at step k >= 1 (the step timestamps after the first, as the data contract
says), radians in [-pi, pi):

    yaw_k = wrap(h_k + earth_from_site + o + m(p_k) + n_k)

- h_k: the walker's true heading at step k (site frame; ``Session.ground_truth.heading``);
- o: the walk's offset, the phone's pointing relative to the walking direction:
  N(0, offset_sigma^2), or with probability ``turned_prob`` a large +-U(turned range) (the
  phone turned in the hand or in a pocket);
- m(p): the site's indoor magnetic distortion at the true position p_k, a smooth Gaussian
  field (std ``distortion_sigma``, correlation exp(-(r / distortion_corr)^2)) fixed per site:
  every walk sees the same distortion at the same place;
- n_k: white noise per step.

Every draw comes from generators of its own (``graphslam.sim.scenarios``), never from a
walk's own stream, so switching headings on or off changes no other simulated value.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from graphslam.core.types import HeadingTrack, PoseTrack
from graphslam.errors import ConfigError, SimulationError
from graphslam.sim.floorplan import FloorPlan
from graphslam.sim.radio import ShadowingField, gaussian_field

_GRID_M = 1.0  # distortion field grid spacing (bilinear in between)


@dataclass(frozen=True)
class HeadingModel:
    """The phone azimuth's error model (degrees, metres); see the module docstring.

    ``enabled=False``: no ``/phone/heading`` (``Session.heading`` is None), no field drawn.
    """

    enabled: bool = True
    earth_from_site_deg: float = 12.0  # Earth azimuth of site +x (deg CCW from east); non-zero on purpose
    offset_sigma_deg: float = 5.0  # per walk: phone pointing vs walking direction, Gaussian std
    turned_prob: float = 0.05  # per walk: probability that the offset is a large one instead ...
    turned_deg: tuple[float, float] = (30.0, 70.0)  # ... of magnitude uniform in this range, random sign
    distortion_sigma_deg: float = 7.0  # indoor magnetic distortion field, std
    distortion_corr_m: float = 7.0  # its correlation exp(-1) distance
    noise_sigma_deg: float = 2.5  # white, per step

    def __post_init__(self) -> None:
        values = (
            self.earth_from_site_deg, self.offset_sigma_deg, self.turned_prob, *self.turned_deg,
            self.distortion_sigma_deg, self.distortion_corr_m, self.noise_sigma_deg,
        )
        if not all(math.isfinite(v) for v in values):
            raise ConfigError("HeadingModel: every parameter must be finite")
        for name in ("offset_sigma_deg", "distortion_sigma_deg", "noise_sigma_deg"):
            if getattr(self, name) < 0:
                raise ConfigError(f"HeadingModel.{name} must be >= 0")
        if not 0 <= self.turned_prob <= 1:
            raise ConfigError("HeadingModel.turned_prob must be in [0, 1]")
        lo, hi = self.turned_deg
        if not 0 <= lo <= hi <= 180:
            raise ConfigError(f"HeadingModel.turned_deg: need 0 <= low <= high <= 180, got {self.turned_deg}")
        if self.distortion_corr_m <= 0:
            raise ConfigError("HeadingModel.distortion_corr_m must be > 0")

    @property
    def earth_from_site_rad(self) -> float:
        return math.radians(self.earth_from_site_deg)


def wrap_yaw(a: NDArray | float) -> NDArray[np.float64]:
    """Angles wrapped to [-pi, pi) (the contract's range for ``/phone/heading``)."""
    return np.asarray(np.mod(np.asarray(a, dtype=float) + math.pi, 2.0 * math.pi) - math.pi)


def distortion_field(plan: FloorPlan, model: HeadingModel, rng: np.random.Generator) -> ShadowingField:
    """The site's magnetic distortion of the azimuth (rad, one layer) on a 1 m grid over ``plan``.

    Padded by twice the correlation length, as the shadowing is: the FFT field is periodic
    over its grid, and the padding keeps opposite edges of the floor uncorrelated.
    """
    pad = 2.0 * model.distortion_corr_m
    nx = int(np.ceil((plan.width_m + 2 * pad) / _GRID_M)) + 1
    ny = int(np.ceil((plan.height_m + 2 * pad) / _GRID_M)) + 1
    sigma = math.radians(model.distortion_sigma_deg)
    if sigma > 0:
        values = gaussian_field(rng, (1, ny, nx), sigma, model.distortion_corr_m / _GRID_M)
    else:
        values = np.zeros((1, ny, nx))
    return ShadowingField((-pad, -pad), _GRID_M, values)


def walk_offset(model: HeadingModel, rng: np.random.Generator) -> float:
    """One walk's pointing offset (rad). Always four draws, so later draws do not depend on the branch."""
    turned = rng.random() < model.turned_prob
    gauss = rng.normal(0.0, math.radians(model.offset_sigma_deg))
    large = math.radians(rng.uniform(*model.turned_deg))
    sign = 1.0 if rng.random() < 0.5 else -1.0
    return float(sign * large if turned else gauss)


def phone_heading(
    truth: PoseTrack, model: HeadingModel, field: ShadowingField, rng: np.random.Generator
) -> HeadingTrack:
    """The phone's yaw (Earth frame, rad in [-pi, pi)) at ``truth``'s step timestamps after the first.

    Draws the walk's offset first (``walk_offset``), then one noise value per step.
    """
    if not model.enabled:
        raise SimulationError("phone_heading: the heading model is disabled")
    offset = walk_offset(model, rng)
    xy, h = truth.xy[1:], truth.heading[1:]
    noise = rng.normal(0.0, math.radians(model.noise_sigma_deg), len(h))
    distortion = field.at(xy)[:, 0]
    yaw = wrap_yaw(h + model.earth_from_site_rad + offset + distortion + noise)
    return HeadingTrack(truth.t_ns[1:], yaw)
