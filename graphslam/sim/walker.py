"""Walkers: true trajectories, foot-module dead reckoning, WiFi scan times, landmark marks.

Frames and units:
- ground truth (``Session.ground_truth``) is in the site frame (m, rad);
- the dead-reckoned track (``Session.steps``) is in the foot module's own frame:
  its first pose is exactly (0, 0, 0), and it is the true start pose's frame
  (origin at the true start position, x along the true start heading) corrupted
  by the module's errors. The true start pose is random, so the relation of the
  DR frame to the site is unknown to a solver;
- times are integer ns since the Unix epoch.

True motion: the walker follows a route (a polyline of walkable-graph nodes,
or the marked line of the ``corridor`` experiment) with a smooth random lateral
offset; one pose per detected step. Pose 0 is the walker standing at the start,
facing a random direction (so the DR frame is rotated arbitrarily against the
site); pose k >= 1 faces along step k. Pauses (button presses at landmarks,
random stops) add time without steps, as a foot module detects no step while
the wearer stands.

Dead reckoning error model (per walker: step-length scale error and initial gyro
bias; per step: length noise, heading noise, bias random walk):

    L_dr_k  = |true step k| * (1 + scale) + n_L
    e_k     = e_{k-1} + b_k * dt_k + n_h          (heading error, e_0 = 0)
    b_k     = b_{k-1} + n_b * sqrt(dt_k)          (yaw-rate bias, rad/s)
    h_dr_k  = h_k - h_0 + e_k
    p_dr_k  = p_dr_{k-1} + L_dr_k * (cos h_dr_k, sin h_dr_k)

so raw drift grows with time (bias, random walk) and distance (scale).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from graphslam.core.types import LandmarkMark, PoseTrack, Session, wrap_angle
from graphslam.errors import ConfigError, SimulationError
from graphslam.sim.floorplan import FloorPlan
from graphslam.sim.radio import RadioEnvironment

log = logging.getLogger(__name__)

NS = 1_000_000_000


@dataclass(frozen=True)
class WalkerParams:
    """How people walk, scan and mark landmarks (s, m, rad)."""

    step_period_s: tuple[float, float] = (0.48, 0.56)  # per-walker mean time per step, uniform
    step_period_jitter: float = 0.04  # relative std, per step
    step_length_m: tuple[float, float] = (0.62, 0.72)  # per-walker mean step length, uniform
    step_length_sigma_m: float = 0.04  # per-step variation of the true step length
    min_step_m: float = 0.35
    max_step_m: float = 0.95
    lateral_sigma_m: float = 0.25  # std of the offset from the centre line
    lateral_corr_steps: float = 10.0  # correlation exp(-1) of that offset after this many steps
    room_weight: float = 0.15  # at a door, weight of entering the room (corridor ways weigh 1)
    stop_prob: float = 0.003  # per step: stop for a while (talk, look around)
    stop_s: tuple[float, float] = (3.0, 15.0)
    mark_radius_m: float = 0.7  # a landmark can be marked when passing this close
    mark_prob: float = 0.5  # ... and is, with this probability per pass
    mark_cooldown_s: float = 120.0  # not the same landmark again within this time
    mark_pause_s: tuple[float, float] = (2.0, 4.0)  # standing still to press the button
    scan_period_s: float = 2.0  # WiFi scan interval, independent of steps
    scan_jitter_s: float = 0.3  # std of each interval
    initial_heading_spread_rad: float = math.pi  # start heading = route direction + U(-s, s)

    def __post_init__(self) -> None:
        for name in ("step_period_s", "step_length_m", "stop_s", "mark_pause_s"):
            lo, hi = getattr(self, name)
            if not 0 < lo <= hi:
                raise ConfigError(f"WalkerParams.{name}: need 0 < low <= high, got {(lo, hi)}")
        if not 0 < self.min_step_m <= self.step_length_m[0] <= self.step_length_m[1] <= self.max_step_m:
            raise ConfigError("WalkerParams: need 0 < min_step_m <= step_length_m <= max_step_m")
        for name in ("room_weight", "stop_prob", "mark_prob"):
            if not 0 <= getattr(self, name) <= 1:
                raise ConfigError(f"WalkerParams.{name} must be in [0, 1]")
        if self.mark_pause_s[0] < 1.0:
            raise ConfigError("WalkerParams.mark_pause_s must be >= 1 s (the press happens while standing)")
        if self.scan_period_s <= 0 or self.scan_jitter_s < 0 or self.lateral_corr_steps < 1:
            raise ConfigError("WalkerParams: bad scan period/jitter or lateral_corr_steps")


@dataclass(frozen=True)
class ImuErrorParams:
    """Foot-module dead-reckoning errors (see the module docstring)."""

    scale_sigma: float = 0.01  # per-walker step-length scale error (relative)
    step_length_sigma_m: float = 0.02  # per-step length error
    heading_sigma_rad: float = 0.002  # per-step heading error (heading random walk)
    # Initial yaw-rate bias: magnitude uniform in this range, random sign. A range
    # rather than a Gaussian keeps every walker's drift of similar size.
    gyro_bias_rad_s: tuple[float, float] = (2.5e-4, 3.5e-4)  # 0.86-1.2 deg/min
    gyro_bias_walk: float = 3.0e-6  # bias random walk, rad/s per sqrt(s)

    def __post_init__(self) -> None:
        lo, hi = self.gyro_bias_rad_s
        if not 0 <= lo <= hi:
            raise ConfigError(f"ImuErrorParams.gyro_bias_rad_s: need 0 <= low <= high, got {(lo, hi)}")
        for name in ("scale_sigma", "step_length_sigma_m", "heading_sigma_rad", "gyro_bias_walk"):
            if getattr(self, name) < 0:
                raise ConfigError(f"ImuErrorParams.{name} must be >= 0")


@dataclass(frozen=True)
class WalkSpec:
    """One walk to simulate."""

    session_id: str
    start_t_ns: int
    route: Literal["graph", "line"]
    duration_s: float | None  # graph routes stop here; line routes at the end of the line


# --------------------------------------------------------------------------- routes


def graph_route(plan: FloorPlan, rng: np.random.Generator, length_m: float, room_weight: float) -> NDArray:
    """Random walk on the walkable graph (no U-turns except at dead ends), >= ``length_m`` long.

    Entering a room node adds a detour: to a random point of the room and back.
    """
    adj = plan.neighbours()
    is_room = (plan.node_room >= 0).tolist()
    nodes = plan.nodes.tolist()
    rooms = plan.rooms.tolist()
    starts = plan.corridor_nodes
    cur = int(starts[rng.integers(len(starts))])
    prev = -1
    pts: list[list[float]] = [nodes[cur]]
    total = 0.0
    while total < length_m:
        options = [n for n in adj[cur] if n != prev] or adj[cur]
        cum = np.cumsum([room_weight if is_room[n] else 1.0 for n in options])
        pick = int(np.searchsorted(cum, rng.random() * cum[-1], side="right")) if cum[-1] > 0 else 0
        nxt = options[min(pick, len(options) - 1)]
        new = [nodes[nxt]]
        if is_room[nxt]:
            x0, y0, x1, y1 = rooms[int(plan.node_room[nxt])]
            new += [[rng.uniform(x0, max(x0, x1)), rng.uniform(y0, max(y0, y1))], nodes[nxt]]
        for p in new:
            total += math.hypot(p[0] - pts[-1][0], p[1] - pts[-1][1])
            pts.append(p)
        prev, cur = cur, nxt
    return np.array(pts)


def along_polyline(route: NDArray, s: NDArray) -> tuple[NDArray, NDArray]:
    """Points at arc lengths ``s`` on polyline ``route``, and the unit direction there."""
    seg = np.diff(route, axis=0)
    ln = np.linalg.norm(seg, axis=1)
    keep = ln > 1e-9
    route = np.vstack([route[:1], route[1:][keep]])
    seg, ln = seg[keep], ln[keep]
    cum = np.concatenate([[0.0], np.cumsum(ln)])
    i = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(ln) - 1)
    u = seg[i] / ln[i, None]
    return route[i] + (s - cum[i])[:, None] * u, u


def smooth_noise(rng: np.random.Generator, n: int, sigma: float, corr_steps: float) -> NDArray:
    """Stationary Gaussian sequence, std ``sigma``, correlation exp(-(k / corr_steps)^2) at lag k.

    White noise convolved with a Gaussian kernel of std ``corr_steps / 2``.
    """
    if n == 0 or sigma == 0:
        return np.zeros(n)
    k_sigma = corr_steps / 2.0
    pad = int(4 * k_sigma) + 1
    kernel = np.exp(-0.5 * (np.arange(-pad, pad + 1) / k_sigma) ** 2)
    smooth = np.convolve(rng.standard_normal(n + 2 * pad), kernel, mode="valid")
    return smooth * (sigma / np.sqrt(np.sum(kernel**2)))


# --------------------------------------------------------------------------- walk


@dataclass(frozen=True, eq=False)
class TrueMotion:
    """A walker's true motion: one pose per step; pauses precede a step (``walk_s`` excludes them)."""

    t_ns: NDArray[np.int64]  # (N,)
    xy: NDArray[np.float64]  # (N, 2) true positions
    heading: NDArray[np.float64]  # (N,) true headings
    walk_s: NDArray[np.float64]  # (N,) walking time of step k (0 for k = 0)
    marks: tuple[LandmarkMark, ...]


def _true_motion(
    spec: WalkSpec, plan: FloorPlan, wp: WalkerParams, rng: np.random.Generator
) -> TrueMotion:
    period = rng.uniform(*wp.step_period_s)
    mean_len = rng.uniform(*wp.step_length_m)
    if spec.route == "line":
        if plan.line is None:
            raise SimulationError(f"{spec.session_id}: floor plan {plan.name!r} has no marked line")
        a, b = plan.line
        # The walker starts and stops within ~1 m of the marked ends.
        u = (b - a) / np.linalg.norm(b - a)
        route = np.array([a + u * rng.uniform(-1, 1), b + u * rng.uniform(-1, 1)])
        route_len = float(np.linalg.norm(route[1] - route[0]))
        n_max = int(route_len / wp.min_step_m) + 2
    else:
        if spec.duration_s is None or spec.duration_s <= 0:
            raise SimulationError(f"{spec.session_id}: graph walks need a positive duration")
        n_max = int(spec.duration_s / (period * (1 - 4 * wp.step_period_jitter))) + 2
        route = graph_route(plan, rng, n_max * wp.max_step_m + 10.0, wp.room_weight)
        route_len = float(np.sum(np.linalg.norm(np.diff(route, axis=0), axis=1)))
    lengths = np.clip(rng.normal(mean_len, wp.step_length_sigma_m, n_max), wp.min_step_m, wp.max_step_m)
    s = np.concatenate([[0.0], np.cumsum(lengths)])
    s = s[s <= route_len]
    centre, u = along_polyline(route, s)
    # Normals averaged over 5 steps: the sideways offset turns smoothly at corners
    # (and fades out at U-turns) instead of jumping with the route direction.
    normal = np.column_stack([-u[:, 1], u[:, 0]])
    kernel = np.ones(5) / 5.0
    normal = np.column_stack([np.convolve(np.pad(normal[:, i], 2, mode="edge"), kernel, "valid") for i in (0, 1)])
    xy = centre + smooth_noise(rng, len(s), wp.lateral_sigma_m, wp.lateral_corr_steps)[:, None] * normal
    n = len(xy)
    walk = period * np.clip(1 + rng.normal(0, wp.step_period_jitter, n), 0.5, 1.5)
    walk[0] = 0.0
    nominal_t = np.cumsum(walk)

    # Landmark marks: first step of each pass within the radius, cooldown, probability.
    pause = np.zeros(n)
    stops = rng.random(n) < wp.stop_prob
    pause[stops] = rng.uniform(*wp.stop_s, int(stops.sum()))
    events: list[tuple[int, int]] = []  # (step, landmark index)
    lm_xy = plan.landmark_xy
    if len(lm_xy):
        near = np.linalg.norm(xy[:, None, :] - lm_xy[None, :, :], axis=2) < wp.mark_radius_m
        enter = near & ~np.vstack([np.zeros((1, len(lm_xy)), bool), near[:-1]])
        events = sorted(zip(*map(list, np.nonzero(enter))))
    press = rng.random(len(events)) < wp.mark_prob
    last: dict[int, float] = {}
    marked: list[tuple[int, int, float]] = []
    for (k, j), ok in zip(events, press):
        if ok and nominal_t[k] - last.get(j, -np.inf) >= wp.mark_cooldown_s:
            last[j] = nominal_t[k]
            delay = rng.uniform(0.3, 1.0)
            pause[k] = max(pause[k], rng.uniform(*wp.mark_pause_s))
            marked.append((k, j, delay))
    # Step k happens walk[k] after the end of the pause that follows step k-1.
    dt = walk + np.concatenate([[0.0], pause[:-1]])
    t_rel = np.cumsum(dt)
    t_ns = spec.start_t_ns + np.round(t_rel * NS).astype(np.int64)
    if spec.route == "graph" and spec.duration_s is not None:
        n = int(np.searchsorted(t_rel, spec.duration_s, side="right"))
    if n < 2:
        raise SimulationError(f"{spec.session_id}: walk too short ({n} steps)")
    t_ns, xy, walk = t_ns[:n], xy[:n], walk[:n]
    step = np.diff(xy, axis=0)
    heading = np.empty(n)
    heading[1:] = np.arctan2(step[:, 1], step[:, 0])
    heading[0] = wrap_angle(heading[1] + rng.uniform(-1, 1) * wp.initial_heading_spread_rad)
    marks = tuple(
        LandmarkMark(
            int(t_ns[k] + round(d * NS)),
            plan.landmarks[j].landmark_id,
            plan.landmarks[j].x,
            plan.landmarks[j].y,
        )
        for k, j, d in marked
        if k < n - 1 or (k == n - 1 and spec.route == "line")
    )
    return TrueMotion(t_ns, xy, np.asarray(wrap_angle(heading)), walk, tuple(sorted(marks, key=lambda m: m.t_ns)))


def dead_reckon(
    t_ns: NDArray[np.int64], xy: NDArray, heading: NDArray, imu: ImuErrorParams, rng: np.random.Generator
) -> NDArray[np.float64]:
    """(N, 3) foot-module DR poses (x, y, heading) in its own frame; pose 0 is (0, 0, 0)."""
    n = len(t_ns)
    step = np.diff(xy, axis=0)
    length = np.linalg.norm(step, axis=1)
    dt = np.diff(t_ns).astype(float) / NS
    scale = rng.normal(0.0, imu.scale_sigma)
    b0 = rng.choice([-1.0, 1.0]) * rng.uniform(*imu.gyro_bias_rad_s)
    bias = b0 + np.cumsum(rng.normal(0.0, 1.0, n - 1) * imu.gyro_bias_walk * np.sqrt(dt))
    err = np.concatenate([[0.0], np.cumsum(bias * dt + rng.normal(0.0, imu.heading_sigma_rad, n - 1))])
    l_dr = np.maximum(length * (1.0 + scale) + rng.normal(0.0, imu.step_length_sigma_m, n - 1), 0.0)
    h_dr = np.asarray(wrap_angle(heading - heading[0] + err))
    h_dr[0] = 0.0
    d = l_dr[:, None] * np.column_stack([np.cos(h_dr[1:]), np.sin(h_dr[1:])])
    p = np.vstack([np.zeros((1, 2)), np.cumsum(d, axis=0)])
    return np.column_stack([p, h_dr])


def positions_at(t_query: NDArray[np.int64], m: TrueMotion) -> NDArray[np.float64]:
    """True positions at arbitrary times: still during pauses, linear while stepping."""
    t = m.t_ns
    k = np.clip(np.searchsorted(t, t_query, side="left"), 1, len(t) - 1)
    move_start = t[k] - np.round(m.walk_s[k] * NS)
    frac = np.clip((t_query - move_start) / np.maximum(m.walk_s[k] * NS, 1.0), 0.0, 1.0)
    return m.xy[k - 1] + frac[:, None] * (m.xy[k] - m.xy[k - 1])


def scan_times(start_ns: int, end_ns: int, wp: WalkerParams, rng: np.random.Generator) -> NDArray[np.int64]:
    """Scan completion times in [start, end]: a random phase, then ~``scan_period_s`` apart."""
    span = (end_ns - start_ns) / NS
    n = int(span / (0.5 * wp.scan_period_s)) + 2
    gaps = np.clip(
        rng.normal(wp.scan_period_s, wp.scan_jitter_s, n), 0.5 * wp.scan_period_s, 2.0 * wp.scan_period_s
    )
    t = rng.uniform(0, wp.scan_period_s) + np.concatenate([[0.0], np.cumsum(gaps[:-1])])
    t = t[t <= span]
    return start_ns + np.round(t * NS).astype(np.int64)


def simulate_walk(
    spec: WalkSpec,
    plan: FloorPlan,
    radio: RadioEnvironment,
    walker: WalkerParams,
    imu: ImuErrorParams,
    rng: np.random.Generator,
    *,
    site: str,
    floor: str,
) -> Session:
    """One walker's recording: DR steps, scans, landmark marks and ground truth."""
    m = _true_motion(spec, plan, walker, rng)
    dr = dead_reckon(m.t_ns, m.xy, m.heading, imu, rng)
    ts = scan_times(int(m.t_ns[0]), int(m.t_ns[-1]), walker, rng)
    scans = radio.scans(ts, positions_at(ts, m), rng)
    log.debug("%s: %d steps, %d scans, %d marks", spec.session_id, len(m.t_ns), len(scans), len(m.marks))
    return Session(
        session_id=spec.session_id,
        steps=PoseTrack(m.t_ns, dr[:, :2], dr[:, 2]),
        scans=scans,
        landmarks=m.marks,
        ground_truth=PoseTrack(m.t_ns, m.xy, m.heading),
        site=site,
        floor=floor,
    )
