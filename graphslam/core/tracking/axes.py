"""Walk axes: the two perpendicular directions a building's walkers keep to, as a prior on the
tracker's walking direction.

Most buildings are laid out on two perpendicular axes (corridors, aisles, shop fronts); foot-mounted
inertial navigation has long used them to remove heading drift (heuristic drift elimination,
Borenstein, Ojeda and Kwanmuang 2009). Here they are measured on the radio map's own walks, with no
floor plan: consecutive fingerprints of one session give a walking direction ``phi`` per segment, and
the fourth circular moment ``m4 = sum w exp(4 i phi) / sum w`` (``w``: segment length) gives the
axis angle ``arg(m4) / 4`` (the axes are that angle plus multiples of 90 deg) and its concentration
``|m4|`` (1: every segment along an axis; 0: no preferred direction, e.g. a round hall).

The prior is one residual per velocity reading on the state's map-frame velocity ``v`` (m/s):
with ``u = R(-angle) v`` (the velocity in the axes' frame),

    r(v) = u_x u_y / sqrt(u_x^2 + u_y^2 + v0^2) / sigma

which is the velocity component across the nearest axis (``u_y`` along x, ``u_x`` along y) for a
walker (|u| >> v0), zero on every axis, largest at 45 deg (where its gradient vanishes: a diagonal
walk is not pulled either way), and fades smoothly to 0 at standstill (``v0``). In the smoothers it
is a map row (Huber-weighted like the RSSI and fix rows), so a turn or a walk across a hall costs a
bounded amount. Frames: map frame in, m/s; angles in rad.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from graphslam.errors import EstimationError


@dataclass(frozen=True)
class WalkAxes:
    """Axes at ``angle_rad`` + k pi / 2 in the map frame; ``sigma_mps``: std of the velocity
    component across the nearest axis; ``v0_mps``: speed below which the prior fades;
    ``concentration``: the map's |m4| they were measured with (NaN when given by hand)."""

    angle_rad: float
    sigma_mps: float = 1.0  # per step: weak, since a walker's steps along a leg share one direction
    v0_mps: float = 0.3
    concentration: float = math.nan

    def __post_init__(self) -> None:
        if not math.isfinite(self.angle_rad):
            raise EstimationError(f"walk axes: angle must be finite, got {self.angle_rad}")
        if not (self.sigma_mps > 0 and self.v0_mps > 0):
            raise EstimationError(f"walk axes: sigma and v0 must be > 0, got {self.sigma_mps}, {self.v0_mps}")

    @classmethod
    def from_walks(
        cls,
        xy: NDArray,
        session_ids: NDArray,
        t_ns: NDArray,
        *,
        sigma_mps: float = 1.0,
        min_concentration: float = 0.3,
        min_segments: int = 50,
        max_gap_s: float = 15.0,
        min_segment_m: float = 0.5,
    ) -> "WalkAxes | None":
        """The axes of the walks through positions ``xy`` (N, 2; m) of sessions ``session_ids`` at
        ``t_ns``: segments between consecutive positions of one session at most ``max_gap_s``
        apart and at least ``min_segment_m`` long. None when fewer than ``min_segments`` qualify
        (a map of static fingerprints, e.g. UJIIndoorLoc's floors hold 6-48: a concentration from
        so few says nothing) or the concentration is below ``min_concentration``."""
        s = axis_statistics(xy, session_ids, t_ns, max_gap_s=max_gap_s, min_segment_m=min_segment_m)
        if s is None or s[2] < min_segments or s[1] < min_concentration:
            return None
        return cls(s[0], sigma_mps=sigma_mps, concentration=s[1])

    def residual(self, v: NDArray) -> NDArray[np.float64]:
        """(M,) whitened residuals of map-frame velocities ``v`` (M, 2)."""
        v = np.asarray(v, float).reshape(-1, 2)
        return self.residual_xy(v[:, 0], v[:, 1])

    def jacobian(self, v: NDArray) -> NDArray[np.float64]:
        """(M, 2) d residual / d v at ``v`` (M, 2)."""
        v = np.asarray(v, float).reshape(-1, 2)
        return np.stack(self.jacobian_xy(v[:, 0], v[:, 1]), 1)

    def residual_xy(self, vx: NDArray, vy: NDArray) -> NDArray[np.float64]:
        """``residual`` of velocities given by their components (arrays of one shape)."""
        ux, uy = self._rotate(vx, vy)
        return ux * uy / np.sqrt(ux * ux + uy * uy + self.v0_mps**2) / self.sigma_mps

    def jacobian_xy(self, vx: NDArray, vy: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """``jacobian`` of velocities given by their components: d residual / d vx, d residual / d vy."""
        ux, uy = self._rotate(vx, vy)
        v0 = self.v0_mps**2
        s2 = ux * ux + uy * uy + v0
        q = 1.0 / (s2 * np.sqrt(s2) * self.sigma_mps)
        dx, dy = uy * (uy * uy + v0) * q, ux * (ux * ux + v0) * q
        c, sn = math.cos(self.angle_rad), math.sin(self.angle_rad)
        # u = R(-a) v, so d r / d v = R(-a)^T d r / d u = R(a) d r / d u
        return c * dx - sn * dy, sn * dx + c * dy

    def _rotate(self, vx: NDArray, vy: NDArray) -> tuple[NDArray, NDArray]:
        c, s = math.cos(self.angle_rad), math.sin(self.angle_rad)
        return c * vx + s * vy, c * vy - s * vx


def axis_statistics(
    xy: NDArray, session_ids: NDArray, t_ns: NDArray, *, max_gap_s: float = 15.0, min_segment_m: float = 0.5
) -> tuple[float, float, int] | None:
    """(axis angle in (-pi/4, pi/4] rad, concentration |m4| in [0, 1], segments used) of the walks
    (see ``WalkAxes.from_walks``); None when no segment qualifies."""
    xy = np.asarray(xy, float).reshape(-1, 2)
    sid, t = np.asarray(session_ids), np.asarray(t_ns, np.int64)
    if not (len(sid) == len(t) == len(xy)):
        raise EstimationError(f"walk axes: {len(xy)} positions, {len(sid)} session ids, {len(t)} times")
    if len(xy) < 2:
        return None
    o = np.lexsort((t, sid))
    d = np.diff(xy[o], axis=0)
    length = np.hypot(d[:, 0], d[:, 1])
    ok = (sid[o][1:] == sid[o][:-1]) & (np.diff(t[o]) <= max_gap_s * 1e9) & (length >= min_segment_m)
    if not ok.any():
        return None
    phi = np.arctan2(d[ok, 1], d[ok, 0])
    m4 = (length[ok] * np.exp(4j * phi)).sum() / length[ok].sum()
    return float(np.angle(m4) / 4.0), float(abs(m4)), int(ok.sum())
