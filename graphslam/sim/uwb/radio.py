"""UWB radio of the network simulation: who hears whom, frames on the air, two-way ranging.

Frames: positions in the site frame (m); times are *true* times in seconds since the start
of the simulation; each device stamps with its own hardware clock (``clock.Clocks``).

- **Links**: nodes a, b hear each other when their planar distance is at most
  ``los_range_m * wall_range_factor ** n_walls`` (each wall crossed by the straight line
  shortens the reach; a castle's stone walls pass almost nothing, an office's plasterboard
  half). Links are symmetric and re-evaluated per phase / per slot (walkers move < 5 cm in a
  slot).
- **Medium**: a frame lasts ``airtime_s``. A node receives a frame of a node it hears unless
  it transmits itself at any time during it (half duplex), another node it hears transmits
  during it (a collision), or the frame is lost (``loss_prob``, independent).
- **Ranging** (eq. 4-6): double-sided TWR (poll, response, final) between two devices with
  their own clock rates; every receive timestamp has ``sigma_timestamp_s`` of jitter. The flight
  time is that of the 3-D distance plus an NLOS excess path: a link through a wall, or a line
  of sight blocked by a body (probability ``los_nlos_prob``), adds U(nlos_bias_m) metres. An
  NLOS range is never shorter than the truth beyond noise.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from graphslam.core.uwb.ranging import SPEED_OF_LIGHT_MPS, ds_twr_tof
from graphslam.errors import ConfigError
from graphslam.sim.radio import wall_crossings


@dataclass(frozen=True)
class UwbRadioParams:
    """Link, medium and ranging model (m, s). Defaults: an office floor (plasterboard)."""

    los_range_m: float = 30.0  # DW1000-class radios at 6.8 Mb/s indoors
    wall_range_factor: float = 0.5  # reach multiplied by this per wall crossed
    airtime_s: float = 150e-6  # one short frame
    loss_prob: float = 0.02  # a frame lost for no visible reason
    sigma_timestamp_s: float = 0.27e-9  # receive-timestamp jitter: 5 cm range std after DS-TWR (tests/test_uwb_network.py)
    nlos_bias_m: tuple[float, float] = (0.3, 2.0)  # excess path of an NLOS range, uniform
    nlos_through_walls: bool = True  # a link through a wall is NLOS
    los_nlos_prob: float = 0.0  # a line-of-sight range is NLOS anyway (bodies, furniture)

    def __post_init__(self) -> None:
        lo, hi = self.nlos_bias_m
        if not (self.los_range_m > 0 and 0 <= self.wall_range_factor <= 1 and self.airtime_s > 0):
            raise ConfigError("UwbRadioParams: los_range_m and airtime_s must be > 0, wall_range_factor in [0, 1]")
        if not (0 <= self.loss_prob < 1 and 0 <= self.los_nlos_prob <= 1 and 0 <= lo <= hi and self.sigma_timestamp_s >= 0):
            raise ConfigError("UwbRadioParams: bad loss/NLOS probability, NLOS bias range or timestamp jitter")


def link_matrix(xy: NDArray, walls: NDArray, params: UwbRadioParams, active: NDArray | None = None) -> tuple[NDArray, NDArray]:
    """(N, N) bool "a hears b" and (N, N) int walls crossed, for nodes at ``xy`` (N, 2).
    Inactive nodes (a walker not yet started or gone home) hear nobody."""
    xy = np.asarray(xy, float)
    n = len(xy)
    walls_ab = wall_crossings(xy, xy, walls) if len(walls) and n else np.zeros((n, n), np.int32)
    d = np.linalg.norm(xy[:, None, :] - xy[None, :, :], axis=2)
    reach = params.los_range_m * params.wall_range_factor ** walls_ab.astype(float)
    linked = (d <= reach) & ~np.eye(n, dtype=bool)
    if active is not None:
        linked &= np.asarray(active)[:, None] & np.asarray(active)[None, :]
    return linked, walls_ab


@dataclass
class Frame:
    start: float  # true time (s)
    sender: int
    payload: Any
    end: float = 0.0


class Medium:
    """Frames on the air during one phase; ``resolve`` decides who received which frame.

    Frames are added in any order of their start; ``resolve(until)`` settles every frame that
    ended by ``until`` (all frames that could overlap it must have been added by then)."""

    def __init__(self, linked: NDArray, params: UwbRadioParams, rng: np.random.Generator) -> None:
        self.linked = linked
        self.params = params
        self.rng = rng
        self.frames: list[Frame] = []
        self.starts: list[float] = []
        self.by_sender: dict[int, list[Frame]] = {}
        self.pending: list[Frame] = []
        self.collisions = 0  # (frame, receiver) pairs lost to a collision
        self.losses = 0

    def send(self, start: float, sender: int, payload: Any) -> Frame:
        f = Frame(start, sender, payload, start + self.params.airtime_s)
        i = bisect.bisect(self.starts, start)
        self.starts.insert(i, start)
        self.frames.insert(i, f)
        self.by_sender.setdefault(sender, []).append(f)
        self.pending.append(f)
        return f

    def _overlapping(self, f: Frame) -> list[Frame]:
        lo = bisect.bisect_left(self.starts, f.start - self.params.airtime_s)
        hi = bisect.bisect_left(self.starts, f.end)
        return [g for g in self.frames[lo:hi] if g is not f and g.start < f.end and g.end > f.start]

    def status(self, f: Frame, r: int, others: list[Frame] | None = None) -> str:
        """What receiver ``r`` got of ``f``: "ok", "collision", "loss" or "unlinked" (counted)."""
        if not self.linked[f.sender, r]:
            return "unlinked"
        others = self._overlapping(f) if others is None else others
        if any(g.sender == r or self.linked[g.sender, r] for g in others):
            self.collisions += 1
            return "collision"
        if self.rng.random() < self.params.loss_prob:
            self.losses += 1
            return "loss"
        return "ok"

    def receivers(self, f: Frame) -> list[int]:
        """Every node that received broadcast ``f``."""
        others = self._overlapping(f)
        return [r for r in np.flatnonzero(self.linked[f.sender]).tolist() if self.status(f, r, others) == "ok"]

    def resolve(self, until: float) -> list[tuple[Frame, list[int]]]:
        """Frames that ended by ``until``, in start order, with their receivers."""
        done = [f for f in self.pending if f.end <= until]
        if not done:
            return []
        self.pending = [f for f in self.pending if f.end > until]
        done.sort(key=lambda f: f.start)
        return [(f, self.receivers(f)) for f in done]


def nlos_excess(n_walls: NDArray, params: UwbRadioParams, rng: np.random.Generator) -> tuple[NDArray, NDArray]:
    """(excess path m, NLOS flag) for ranges over links crossing ``n_walls`` walls."""
    n_walls = np.asarray(n_walls)
    nlos = (n_walls > 0) & params.nlos_through_walls
    nlos |= rng.random(n_walls.shape) < params.los_nlos_prob
    excess = np.where(nlos, rng.uniform(*params.nlos_bias_m, n_walls.shape), 0.0)
    return excess, nlos


def ds_twr_range(
    distance_m: NDArray,
    excess_m: NDArray,
    rate_i: NDArray,
    rate_j: NDArray,
    reply_s: float,
    params: UwbRadioParams,
    rng: np.random.Generator,
) -> NDArray:
    """Measured ranges of double-sided TWR exchanges (initiator i, responder j), eq. 4-6.

    Both reply delays are ``reply_s`` on the replying device's own clock; rates are the
    hardware clock rates (1 + drift). The devices' offsets do not enter: only intervals do.
    """
    tof = (np.asarray(distance_m, float) + np.asarray(excess_m, float)) / SPEED_OF_LIGHT_MPS
    n = np.shape(tof)
    jit = rng.normal(0.0, params.sigma_timestamp_s, (3,) + tuple(n))
    # true instants (poll sent at 0); an "rx" is the receiver's timestamp (arrival + jitter),
    # a reply is scheduled reply_s after it on the replying device's clock
    poll_rx = tof + jit[0]
    resp_tx = poll_rx + reply_s / rate_j
    resp_rx = resp_tx + tof + jit[1]
    final_tx = resp_rx + reply_s / rate_i
    final_rx = final_tx + tof + jit[2]
    r1 = rate_i * resp_rx  # initiator: poll tx -> response rx
    d1 = rate_j * (resp_tx - poll_rx)  # responder: poll rx -> response tx
    d2 = rate_i * (final_tx - resp_rx)  # initiator: response rx -> final tx
    r2 = rate_j * (final_rx - resp_tx)  # responder: response tx -> final rx
    return SPEED_OF_LIGHT_MPS * ds_twr_tof(r1, d1, r2, d2)
