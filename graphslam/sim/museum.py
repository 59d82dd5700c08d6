"""The ``museum`` scenario: out-and-back routes along a tree of corridors, each walked several times with a phone.

It reproduces the shape of the IPIN 2023 Track 3 training trials on floor -2 of the
Museum Industriekultur, Nuremberg (Torres-Sospedra et al., Zenodo
10.5281/zenodo.8362205; ``../shared/data/ipin2023/b100_f-2``), where the paper's
alignment fails; ``scripts/sim_vs_real_shape.py`` prints the shape statistics of both.

Layout (``museum_layout``): the routes of that floor, as a template measured from its
landmarks (building axes, metres): a ~105 m spine corridor with branches, seven routes
that each cover their own part of the tree, and three short stair/lift walks at
junctions. Six routes form a chain, each sharing a junction stretch with its neighbours;
the seventh (route1, trial 21) lies in a wing of its own at the spine's end, more than
4 m from every other route (``LayoutParams.lone_wing_gap_m``), as on the real floor.
Per seed the template is warped by a random monotone piecewise-linear map of x and of y
(lengths change by up to ~25 %, axis-parallel corridors stay axis-parallel, nothing
crosses that did not cross) and maybe mirrored, so every seed is a different floor of
the same kind. Walls:
the spine corridor's two sides plus hall partitions between the branches, with a door
wherever a route crosses a wall.

Walk (``simulate_museum_walk``), site frame, metres, seconds:

- out along the route with a smooth lateral offset (tapered to 0 at the ends), every
  landmark marked while passing it (no stop);
- at the far end the walker turns on the spot (2-4 slow steps) and stands for
  ``pause_s`` (split into 1-4 standing spells by 1-3 shuffling steps). A hand-held
  phone's step detector fires on those steps; while standing there are no steps, and
  the scans go on; the far landmark is marked on arrival and again before leaving;
- back along the same route (a new lateral offset).

Phone PDR (``PhonePdrParams``): step length = true length x (1 + scale) x (1 + noise),
scale per walk; the turning / shuffling steps are reported at a normal-looking length.
Heading = true heading + e_k with

    e_k = m(x_k) + o_leg(k) + w_k + n_k

m = a smooth heading-disturbance field fixed for the building (magnetic disturbances of
the rotation-vector heading: every walk sees the same distortion at the same place),
o_leg = a constant offset for the way back (the phone is held differently after the
turn), w = a slow random walk per step, n = white noise per step. The track is
re-expressed to start at (0, 0, 0): its frame is the phone's initial heading. (The
phone's absolute azimuth on ``/phone/heading`` is ``graphslam.sim.heading``'s, with a
distortion field of its own.)

Scans (``PhoneModel``, ``sweep_scans``): every 2 s or 4 s by phone model, small jitter,
an occasional skipped scan; each AP read at a random moment of the scan's 2 s sweep.
Added to the radio model's mean before its noise and floor: the model's constant RSS
offset, a small per-walk per-AP offset, fading correlated over seconds (AR(1) per AP)
and the walker's body (APs behind read lower). All defaults were calibrated on floor -2
(docs/simulator.md, "The museum scenario").
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from graphslam.core.types import LandmarkMark, PoseTrack, Scan, Session, wrap_angle
from graphslam.errors import ConfigError, SimulationError
from graphslam.sim.floorplan import FloorPlan, Landmark
from graphslam.sim.radio import RadioEnvironment, ShadowingField, gaussian_field
from graphslam.sim.walker import NS, TrueMotion, along_polyline, positions_at, smooth_noise

log = logging.getLogger(__name__)

# The template: IPIN 2023 floor -2 routes (trials 21-27) and stair/lift walks (51-53),
# vertices = the surveyed landmarks in the order walked out, in the building's own axes
# (east/north rotated by -20.65 deg, the floor's corridor direction), rounded to 0.1 m.
# The stair/lift walks' third field lists vertices that are not landmarks.
_TEMPLATE: tuple[tuple[str, tuple[tuple[float, float], ...], tuple[int, ...]], ...] = (
    ("route1", ((32.6, 4.6), (32.6, 1.2), (36.2, 1.2), (48.8, 0.2), (54.8, 0.2)), ()),
    ("route2", ((22.4, 7.1), (28.4, 7.1), (28.4, 1.4), (21.4, 1.4), (13.4, 1.5), (13.4, 7.1)), ()),
    ("route3", ((13.4, 1.5), (11.5, 1.4), (3.9, 1.4), (1.4, 1.4), (-3.5, 1.5), (-10.5, 1.5)), ()),
    (
        "route4",
        (
            (10.3, -6.0), (3.9, -6.1), (3.9, 1.4), (-10.5, 1.5), (-10.6, 7.1), (-10.6, 11.9), (-12.1, 15.5),
            (-17.8, 13.9),
        ),
        (),
    ),
    (
        "route5",
        (
            (-10.5, 1.5), (-18.5, 1.4), (-24.0, 1.4), (-24.0, 7.1), (-22.4, 13.8), (-30.0, 7.1), (-28.5, 1.5),
            (-27.5, -2.8), (-31.8, -8.4), (-27.4, -8.4), (-24.1, -8.4), (-24.0, -2.8), (-24.0, 1.4),
        ),
        (),
    ),
    (
        "route6",
        ((-24.0, 1.4), (-28.5, 1.5), (-33.5, 1.5), (-34.5, 7.1), (-34.5, 15.4), (-42.4, 15.4), (-42.4, 10.0)),
        (),
    ),
    ("route7", ((-33.5, 1.5), (-38.5, 1.4), (-43.5, 1.4), (-47.5, 1.4), (-47.5, -2.8), (-47.4, -11.8)), ()),
    ("stairs1", ((32.6, 4.6), (32.6, 6.1)), (1,)),
    ("stairs2", ((-52.7, -6.8), (-47.5, 1.4)), ()),
    ("stairs3", ((-14.4, 4.2), (-10.5, 1.5)), ()),
)
# The lone route's wing (trial 21 and the stairs at its start): on floor -2 no other route
# comes within 4 m of it; moved ``LayoutParams.lone_wing_gap_m`` further out along the spine.
_LONE_WING = ("route1", "stairs1")
# Template vertices within this band around the spine's y lie on the spine corridor.
_SPINE_Y, _SPINE_BAND = 1.45, 1.5
# Template points closer than this are the same landmark (a revisited point keeps its id).
_SAME_POINT_M = 0.6


# --------------------------------------------------------------------------- parameters


@dataclass(frozen=True)
class LayoutParams:
    """How the template becomes a floor (m)."""

    warp_slope: tuple[float, float] = (0.8, 1.25)  # local stretch of the template, uniform per knot interval
    warp_knot_x_m: float = 8.0
    warp_knot_y_m: float = 4.0
    mirror: bool = True  # mirror x and/or y, each with probability 1/2
    margin_m: float = 6.0  # outer wall this far beyond the outermost route vertex
    corridor_margin_m: float = 1.5  # spine corridor walls this far beyond the spine vertices' y range
    door_m: float = 2.4  # opening cut in a wall where a route crosses it
    hall_max_m: float = 14.0  # hall partitions at most this far apart along the spine
    # The lone route's wing moved this much further out along the spine (after the warp): the
    # template's 4.2 m gap, warped and walked with sideways offsets, shrinks to 2.6-4.4 m; with
    # 3 m more no other route's walk comes within 5.5 m of it (seeds 0-29).
    lone_wing_gap_m: float = 3.0

    def __post_init__(self) -> None:
        lo, hi = self.warp_slope
        if not 0 < lo <= hi:
            raise ConfigError(f"LayoutParams.warp_slope: need 0 < low <= high, got {self.warp_slope}")
        if not self.lone_wing_gap_m >= 0:
            raise ConfigError(f"LayoutParams.lone_wing_gap_m must be >= 0, got {self.lone_wing_gap_m}")
        for name in ("warp_knot_x_m", "warp_knot_y_m", "margin_m", "corridor_margin_m", "door_m", "hall_max_m"):
            if getattr(self, name) <= 0:
                raise ConfigError(f"LayoutParams.{name} must be > 0")


@dataclass(frozen=True)
class MuseumWalkerParams:
    """How the museum walkers walk (s, m, rad); defaults measured on IPIN 2023 floor -2 (module docstring)."""

    step_period_s: tuple[float, float] = (0.58, 0.68)  # per-walker mean, uniform (real: median 0.61 s)
    step_period_jitter: float = 0.06  # relative std per step
    step_length_m: tuple[float, float] = (0.54, 0.64)  # per-walker mean true step length, uniform
    step_length_sigma_m: float = 0.04
    lateral_sigma_m: float = 0.35  # offset from the route's centre line; a new one on every leg
    lateral_corr_steps: float = 12.0
    start_stand_s: tuple[float, float] = (0.5, 1.5)  # standing at the start, first landmark pressed then
    pause_s: tuple[float, float] = (20.0, 40.0)  # standing at the far end of a route ...
    stairs_pause_s: tuple[float, float] = (7.0, 24.0)  # ... of a stair/lift walk (waiting at the stairs/lift)
    pause_spells_p: tuple[float, ...] = (0.45, 0.3, 0.1, 0.15)  # P(1, 2, 3, 4 standing spells)
    shuffle_steps: tuple[int, int] = (1, 3)  # steps between two standing spells
    turn_steps: tuple[int, int] = (2, 4)  # steps to turn round at the far end
    spot_step_s: tuple[float, float] = (0.8, 1.6)  # duration of a turning / shuffling step
    spot_sigma_m: float = 0.08  # true displacement of those steps (on the spot)
    start_heading_spread_rad: float = math.radians(10)  # phone heading at the start vs the route direction

    def __post_init__(self) -> None:
        for name in ("step_period_s", "step_length_m", "start_stand_s", "pause_s", "stairs_pause_s", "spot_step_s"):
            lo, hi = getattr(self, name)
            if not 0 < lo <= hi:
                raise ConfigError(f"MuseumWalkerParams.{name}: need 0 < low <= high, got {(lo, hi)}")
        for name in ("shuffle_steps", "turn_steps"):
            lo, hi = getattr(self, name)
            if not 1 <= lo <= hi:
                raise ConfigError(f"MuseumWalkerParams.{name}: need 1 <= low <= high, got {(lo, hi)}")
        p = np.asarray(self.pause_spells_p)
        if len(p) == 0 or np.any(p < 0) or abs(p.sum() - 1.0) > 1e-9:
            raise ConfigError("MuseumWalkerParams.pause_spells_p must be probabilities summing to 1")


@dataclass(frozen=True)
class PhonePdrParams:
    """Hand-held phone PDR errors (relative, rad); see the module docstring."""

    scale_mean: float = -0.01  # per-walk step-length scale error ~ N(mean, sigma)
    scale_sigma: float = 0.08
    step_length_noise: float = 0.08  # relative std per step (Weinberg estimate)
    spot_step_m: tuple[float, float] = (0.40, 0.50)  # reported length of a turning / shuffling step
    heading_noise_rad: float = math.radians(4.0)  # white, per step (hand sway)
    heading_walk_rad: float = math.radians(0.8)  # random walk per step (slow drift)
    leg_offset_rad: float = math.radians(6.0)  # std of the constant offset of the way back
    field_sigma_rad: float = math.radians(12.0)  # heading-disturbance field, fixed per building
    field_corr_m: float = 6.0  # its correlation exp(-1) distance

    def __post_init__(self) -> None:
        for name in ("scale_sigma", "step_length_noise", "heading_noise_rad", "heading_walk_rad", "leg_offset_rad"):
            if getattr(self, name) < 0:
                raise ConfigError(f"PhonePdrParams.{name} must be >= 0")
        if self.field_sigma_rad < 0 or self.field_corr_m <= 0:
            raise ConfigError("PhonePdrParams: field_sigma_rad must be >= 0 and field_corr_m > 0")
        lo, hi = self.spot_step_m
        if not 0 < lo <= hi:
            raise ConfigError(f"PhonePdrParams.spot_step_m: need 0 < low <= high, got {self.spot_step_m}")


@dataclass(frozen=True)
class PhoneModel:
    """A phone model's WiFi scanning: interval (s), jitter, skipped scans, RSS offset (dB)."""

    name: str
    scan_period_s: float
    rss_offset_db: float = 0.0
    scan_jitter_s: float = 0.04
    scan_skip_prob: float = 0.02  # a scan slot is skipped (the interval doubles)
    # A scan sweeps the channels for a while before it completes: each AP's reading is
    # taken at a random moment of the last ``scan_span_s`` (the walker moves meanwhile).
    scan_span_s: float = 2.0

    def __post_init__(self) -> None:
        if self.scan_period_s <= 0 or self.scan_jitter_s < 0 or not 0 <= self.scan_skip_prob < 1:
            raise ConfigError(f"PhoneModel {self.name!r}: bad scan period, jitter or skip probability")
        if self.scan_span_s < 0:
            raise ConfigError(f"PhoneModel {self.name!r}: scan_span_s must be >= 0")


def _default_phones() -> tuple[PhoneModel, ...]:
    # Real floor -2: one model scans every 4 s, the other every 2 s and reads ~7 dB lower
    # (mean difference over common APs of scans within 2 m: scripts/sim_vs_real_shape.py).
    return (PhoneModel("phone-a", 4.0, 0.0), PhoneModel("phone-b", 2.0, -7.0))


@dataclass(frozen=True)
class MuseumParams:
    """Everything of the museum scenario that the other scenarios do not have."""

    repetitions: int = 4  # walks per route and per stair/lift spot (x ``size``)
    layout: LayoutParams = field(default_factory=LayoutParams)
    walker: MuseumWalkerParams = field(default_factory=MuseumWalkerParams)
    pdr: PhonePdrParams = field(default_factory=PhonePdrParams)
    phones: tuple[PhoneModel, ...] = field(default_factory=_default_phones)
    # Per walk and AP, a constant RSS offset (people, doors, another day); kept small: the
    # fading and the body below already give floor -2's difference between two walks.
    walk_rss_sigma_db: float = 0.5
    # The walker's body: an AP straight behind reads this much lower (on floor -2, co-located
    # scans of two walks differ by 4.56 dB going opposite ways, 3.96 dB going the same way).
    body_loss_db: float = 5.0
    # Fading correlated over seconds (per walk and AP, correlation exp(-dt / fading_corr_s)),
    # on top of the radio model's white noise: one AP's squared difference on floor -2 is
    # 11.2 dB^2 between consecutive scans of a standstill, 28.2 dB^2 between two walks' scans
    # at one place (scripts/sim_vs_real_shape.py).
    fading_sigma_db: float = 2.4
    fading_corr_s: float = 15.0

    def __post_init__(self) -> None:
        if self.repetitions < 1 or not self.phones:
            raise ConfigError("MuseumParams: need repetitions >= 1 and at least one phone model")
        if min(self.walk_rss_sigma_db, self.body_loss_db, self.fading_sigma_db) < 0 or self.fading_corr_s <= 0:
            raise ConfigError("MuseumParams: RSS offsets and fading must be >= 0, fading_corr_s > 0")

    def phone_for(self, route_index: int, repetition: int) -> PhoneModel:
        """Repetitions 1-2 with one model, 3-4 with the next (as on floor -2), alternating by route."""
        return self.phones[(repetition // 2 + route_index) % len(self.phones)]


# --------------------------------------------------------------------------- layout


@dataclass(frozen=True, eq=False)
class Route:
    """A designed walk, walked out and back: vertices from the start to the far end (site frame, m)."""

    name: str
    kind: Literal["route", "stairs"]
    xy: NDArray[np.float64]  # (K, 2)
    landmark_ids: tuple[str | None, ...]  # per vertex: the landmark marked there, or None

    @property
    def length_m(self) -> float:
        return float(np.linalg.norm(np.diff(self.xy, axis=0), axis=1).sum())


@dataclass(frozen=True, eq=False)
class MuseumLayout:
    plan: FloorPlan
    routes: tuple[Route, ...]


def _monotone_warp(v: NDArray, knot_m: float, slope: tuple[float, float], rng: np.random.Generator) -> NDArray:
    """A random increasing piecewise-linear map of ``v`` (slopes uniform in ``slope`` per knot interval)."""
    knots = np.arange(v.min() - knot_m, v.max() + 2 * knot_m, knot_m)
    mapped = np.concatenate([[0.0], np.cumsum(rng.uniform(*slope, len(knots) - 1) * knot_m)])
    return np.interp(v, knots, mapped)


def _cut_doors(a: NDArray, b: NDArray, routes: list[NDArray], door_m: float) -> list[tuple[float, float, float, float]]:
    """Wall a-b as segments, with an opening of ``door_m`` wherever a route segment crosses it."""
    d = b - a
    length = float(np.hypot(*d))
    cuts: list[float] = []
    for r in routes:
        p, q = r[:-1], r[1:]
        e = q - p
        den = d[0] * e[:, 1] - d[1] * e[:, 0]
        ok = np.abs(den) > 1e-12
        w = p - a
        safe = np.where(ok, den, 1.0)
        on_wall = np.where(ok, (w[:, 0] * e[:, 1] - w[:, 1] * e[:, 0]) / safe, -1.0)
        on_route = np.where(ok, (w[:, 0] * d[1] - w[:, 1] * d[0]) / safe, -1.0)
        hit = ok & (on_wall >= 0) & (on_wall <= 1) & (on_route >= 0) & (on_route <= 1)
        cuts += (on_wall[hit] * length).tolist()
    out, pos = [], 0.0
    for c in sorted(cuts):
        if c - door_m / 2 > pos:
            out.append((pos, c - door_m / 2))
        pos = max(pos, c + door_m / 2)
    if pos < length:
        out.append((pos, length))
    u = d / length
    return [
        (float(a[0] + s0 * u[0]), float(a[1] + s0 * u[1]), float(a[0] + s1 * u[0]), float(a[1] + s1 * u[1]))
        for s0, s1 in out
        if s1 - s0 > 0.05
    ]


def _free_midpoints(
    occupied: list[tuple[float, float]], lo: float, hi: float, min_gap: float, max_gap: float
) -> list[float]:
    """Wall positions in the gaps between occupied intervals: one per gap >= min_gap, more if a gap > max_gap."""
    iv = sorted(occupied)
    merged: list[list[float]] = []
    for a, b in iv:
        if merged and a <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], b)
        else:
            merged.append([a, b])
    out: list[float] = []
    for (_, e), (s, _) in zip(merged[:-1], merged[1:]):
        gap = s - e
        if gap >= min_gap:
            n = max(1, int(math.ceil(gap / max_gap)))  # n walls, halls no wider than max_gap
            out += [e + gap * (i + 1) / (n + 1) for i in range(n)]
    return [x for x in out if lo < x < hi]


def _walls(routes: list[NDArray], spine: tuple[float, float], w: float, h: float, lp: LayoutParams) -> NDArray:
    """Outer walls, the spine corridor's sides, hall partitions; doors where routes cross."""
    y_lo, y_hi = spine
    lines = [((0.0, y_lo), (w, y_lo)), ((0.0, y_hi), (w, y_hi))]
    segs = np.vstack([np.column_stack([r[:-1], r[1:]]) for r in routes])
    dx, dy = np.abs(segs[:, 2] - segs[:, 0]), np.abs(segs[:, 3] - segs[:, 1])
    # Partitions between the branches (x), and between branch levels on each side (y).
    vert = [(min(s[0], s[2]) - 0.5, max(s[0], s[2]) + 0.5) for s, a, b in zip(segs, dx, dy) if a < 0.3 * b]
    for x in _free_midpoints(vert + [(-1.0, 0.0), (w, w + 1.0)], 0.0, w, 4.0, lp.hall_max_m):
        lines += [((x, 0.0), (x, y_lo)), ((x, y_hi), (x, h))]
    horiz = [(min(s[1], s[3]) - 0.5, max(s[1], s[3]) + 0.5) for s, a, b in zip(segs, dx, dy) if b < 0.3 * a]
    north = [iv for iv in horiz if iv[0] > y_hi]
    south = [iv for iv in horiz if iv[1] < y_lo]
    for y in _free_midpoints(north, y_hi, h, 4.0, 1e9) + _free_midpoints(south, 0.0, y_lo, 4.0, 1e9):
        lines.append(((0.0, y), (w, y)))
    walls = [(0.0, 0.0, w, 0.0), (w, 0.0, w, h), (w, h, 0.0, h), (0.0, h, 0.0, 0.0)]
    for a, b in lines:
        walls += _cut_doors(np.array(a), np.array(b), routes, lp.door_m)
    return np.array(walls)


def museum_layout(lp: LayoutParams, rng: np.random.Generator) -> MuseumLayout:
    """The template warped (and maybe mirrored) by ``rng``: routes, landmarks, walls, walkable graph."""
    pts = np.vstack([np.array(v, dtype=float) for _, v, _ in _TEMPLATE])
    on_spine = np.abs(pts[:, 1] - _SPINE_Y) < _SPINE_BAND
    x = _monotone_warp(pts[:, 0], lp.warp_knot_x_m, lp.warp_slope, rng)
    y = _monotone_warp(pts[:, 1], lp.warp_knot_y_m, lp.warp_slope, rng)
    # After the warp, so that the draws (and the rest of the floor) do not change with the gap;
    # the wing is the template's east end, so a shift east keeps the order along the spine.
    lone = np.concatenate([np.full(len(v), name in _LONE_WING) for name, v, _ in _TEMPLATE])
    x = x + np.where(lone, lp.lone_wing_gap_m, 0.0)
    if lp.mirror:
        x = -x if rng.random() < 0.5 else x
        y = -y if rng.random() < 0.5 else y
    xy = np.column_stack([x, y])
    xy -= xy.min(axis=0) - lp.margin_m
    w, h = (xy.max(axis=0) + lp.margin_m).tolist()
    spine = (float(xy[on_spine, 1].min()) - lp.corridor_margin_m, float(xy[on_spine, 1].max()) + lp.corridor_margin_m)
    # Landmark ids by template position, so that a point shared by routes keeps its id.
    ids: list[tuple[NDArray, str]] = []
    routes: list[Route] = []
    i = 0
    for name, verts, not_landmarks in _TEMPLATE:
        k = len(verts)
        vt, vs = pts[i : i + k], xy[i : i + k]
        i += k
        lids: list[str | None] = []
        for j, p in enumerate(vt):
            if j in not_landmarks:
                lids.append(None)
                continue
            hit = next((lid for q, lid in ids if np.hypot(*(q - p)) < _SAME_POINT_M), None)
            if hit is None:
                hit = f"M{len(ids) + 1:02d}"
                ids.append((p, hit))
            lids.append(hit)
        routes.append(Route(name, "stairs" if name.startswith("stairs") else "route", vs, tuple(lids)))
    # A landmark sits where it first occurs; every route passing it goes exactly there.
    site_of: dict[str, NDArray] = {}
    for r in routes:
        for lid, p in zip(r.landmark_ids, r.xy):
            if lid is not None:
                site_of.setdefault(lid, p)
    snapped = [np.array([p if i is None else site_of[i] for i, p in zip(r.landmark_ids, r.xy)]) for r in routes]
    routes = [Route(r.name, r.kind, xy_r, r.landmark_ids) for r, xy_r in zip(routes, snapped)]
    landmarks = tuple(Landmark(lid, float(p[0]), float(p[1])) for lid, p in site_of.items())
    nodes: list[NDArray] = []
    edges: list[tuple[int, int]] = []

    def node(p: NDArray) -> int:
        for n, q in enumerate(nodes):
            if np.hypot(*(q - p)) < _SAME_POINT_M:
                return n
        nodes.append(p)
        return len(nodes) - 1

    for r in routes:
        idx = [node(p) for p in r.xy]
        edges += [(a, b) for a, b in zip(idx[:-1], idx[1:]) if a != b]
    plan = FloorPlan(
        name="museum",
        width_m=w,
        height_m=h,
        walls=_walls([r.xy for r in routes], spine, w, h, lp),
        nodes=np.array(nodes),
        edges=np.array(edges),
        node_room=np.full(len(nodes), -1),
        rooms=np.zeros((0, 4)),
        landmarks=landmarks,
    )
    return MuseumLayout(plan, tuple(routes))


def heading_field(plan: FloorPlan, pdr: PhonePdrParams, rng: np.random.Generator) -> ShadowingField:
    """The building's heading-disturbance field (rad) on a 1 m grid, same for every walk."""
    pad = 2.0 * pdr.field_corr_m
    nx = int(np.ceil(plan.width_m + 2 * pad)) + 1
    ny = int(np.ceil(plan.height_m + 2 * pad)) + 1
    if pdr.field_sigma_rad > 0:
        values = gaussian_field(rng, (1, ny, nx), pdr.field_sigma_rad, pdr.field_corr_m)
    else:
        values = np.zeros((1, ny, nx))
    return ShadowingField((-pad, -pad), 1.0, values)


# --------------------------------------------------------------------------- one walk


@dataclass
class _Steps:
    """Steps in the making (pose 0 first): true position and body heading, timing, PDR kind, leg."""

    xy: list[NDArray] = field(default_factory=list)
    heading: list[float] = field(default_factory=list)
    walk_s: list[float] = field(default_factory=list)  # movement time of the step
    pause_s: list[float] = field(default_factory=list)  # standing before the step starts
    on_spot: list[bool] = field(default_factory=list)  # turning / shuffling (PDR reports a normal-looking step)
    back: list[bool] = field(default_factory=list)  # after the turn (the way back's heading offset)

    def add(self, xy: NDArray, heading: float, walk: float, pause: float, on_spot: bool, back: bool) -> None:
        self.xy.append(xy)
        self.heading.append(heading)
        self.walk_s.append(walk)
        self.pause_s.append(pause)
        self.on_spot.append(on_spot)
        self.back.append(back)


def _leg(
    route: NDArray,
    st: _Steps,
    mean_len: float,
    period: float,
    wp: MuseumWalkerParams,
    rng: np.random.Generator,
    back: bool,
) -> NDArray:
    """Walk ``route`` (polyline) from its start; appends the steps; returns their centre-line arc lengths."""
    length = float(np.linalg.norm(np.diff(route, axis=0), axis=1).sum())
    n_max = int(length / (0.5 * mean_len)) + 3
    s = np.cumsum(np.clip(rng.normal(mean_len, wp.step_length_sigma_m, n_max), 0.5 * mean_len, 1.5 * mean_len))
    s = s[s < length - 0.3 * mean_len]
    s = np.append(s, length)  # the last step ends at the vertex
    centre, u = along_polyline(route, s)
    normal = np.column_stack([-u[:, 1], u[:, 0]])
    kernel = np.ones(5) / 5.0
    normal = np.column_stack([np.convolve(np.pad(normal[:, i], 2, mode="edge"), kernel, "valid") for i in (0, 1)])
    n = len(s)
    k = np.arange(n)
    taper = np.clip(np.minimum(k + 1, n - 1 - k) / 4.0, 0.0, 1.0)  # starts and ends at the vertex
    xy = centre + (smooth_noise(rng, n, wp.lateral_sigma_m, wp.lateral_corr_steps) * taper)[:, None] * normal
    walk = period * np.clip(1 + rng.normal(0, wp.step_period_jitter, n), 0.5, 1.5)
    prev = st.xy[-1]
    for p, t in zip(xy, walk):
        d = p - prev
        st.add(p, math.atan2(d[1], d[0]), float(t), 0.0, False, back)
        prev = p
    return s


def _far_end(
    st: _Steps, h_in: float, h_out: float, pause: float, wp: MuseumWalkerParams, rng: np.random.Generator
) -> None:
    """Turn round on the spot and stand ``pause`` seconds in 1-4 spells separated by shuffling steps.

    The turning steps are split around the spells, at least one after the last spell
    (a spell is the standing time before the step that ends it).
    """
    n_turn = int(rng.integers(wp.turn_steps[0], wp.turn_steps[1] + 1))
    n_spells = 1 + int(rng.choice(len(wp.pause_spells_p), p=wp.pause_spells_p))
    spells = pause * rng.dirichlet(np.ones(n_spells))
    before = int(rng.integers(0, n_turn))
    steps: list[tuple[float, bool]] = [(0.0, True)] * before  # (standing before the step, turning?)
    for j, spell in enumerate(spells):
        last = j == n_spells - 1
        n = n_turn - before if last else int(rng.integers(wp.shuffle_steps[0], wp.shuffle_steps[1] + 1))
        steps += [(float(spell), last)] + [(0.0, last)] * (n - 1)
    centre = st.xy[-1].copy()
    turn = float(wrap_angle(h_out - h_in))
    done = 0
    for pause_before, turning in steps:
        done += turning
        h = h_in + turn * done / n_turn + (0.0 if turning else rng.normal(0.0, math.radians(10)))
        xy = centre + rng.normal(0.0, wp.spot_sigma_m, 2)
        st.add(xy, float(wrap_angle(h)), float(rng.uniform(*wp.spot_step_s)), pause_before, True, done > 0)


def _pdr(
    st: _Steps, field_: ShadowingField, pdr: PhonePdrParams, rng: np.random.Generator
) -> NDArray[np.float64]:
    """(N, 3) phone PDR poses in the phone's start frame: pose 0 is (0, 0, 0)."""
    xy = np.array(st.xy)
    h = np.array(st.heading)
    n = len(xy)
    on_spot = np.array(st.on_spot)[1:]
    scale = 1.0 + rng.normal(pdr.scale_mean, pdr.scale_sigma)
    true_len = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    length = true_len * (1.0 + rng.normal(0.0, pdr.step_length_noise, n - 1))
    length = np.where(on_spot, rng.uniform(*pdr.spot_step_m, n - 1), length) * scale
    err = (
        field_.at(xy)[:, 0]
        + np.where(np.array(st.back), rng.normal(0.0, pdr.leg_offset_rad), 0.0)
        + np.concatenate([[0.0], np.cumsum(rng.normal(0.0, pdr.heading_walk_rad, n - 1))])
        + rng.normal(0.0, pdr.heading_noise_rad, n)
    )
    h_dr = np.asarray(wrap_angle(h + err - (h[0] + err[0])))
    d = np.maximum(length, 0.0)[:, None] * np.column_stack([np.cos(h_dr[1:]), np.sin(h_dr[1:])])
    return np.column_stack([np.vstack([np.zeros((1, 2)), np.cumsum(d, axis=0)]), h_dr])


def phone_scan_times(start_ns: int, end_ns: int, phone: PhoneModel, rng: np.random.Generator) -> NDArray[np.int64]:
    """Scan completion times in [start, end]: a random phase, then every period (+ jitter, skipped slots)."""
    span = (end_ns - start_ns) / NS
    n = int(span / phone.scan_period_s) + 2
    gaps = phone.scan_period_s * (1 + (rng.random(n) < phone.scan_skip_prob))
    gaps = np.maximum(gaps + rng.normal(0.0, phone.scan_jitter_s, n), 0.25 * phone.scan_period_s)
    t = rng.uniform(0, phone.scan_period_s) + np.concatenate([[0.0], np.cumsum(gaps[:-1])])
    return start_ns + np.round(t[t <= span] * NS).astype(np.int64)


# A scan's sweep is sampled at this many moments (each AP's reading comes from one of them).
_SWEEP_SAMPLES = 4


def sweep_scans(
    radio: RadioEnvironment,
    ts: NDArray[np.int64],
    motion: TrueMotion,
    phone: PhoneModel,
    params: MuseumParams,
    rng: np.random.Generator,
) -> tuple[Scan, ...]:
    """Scans completing at ``ts``: every AP read at a random moment of the last ``scan_span_s``.

    Offsets added to the mean: the phone model's, this walk's per-AP one, the fading
    (an AR(1) process per AP over the scan times), the body's (``body_loss_db`` x
    (1 - cos(angle between the walker's heading and the AP))) / 2).
    """
    lags = phone.scan_span_s * (np.arange(_SWEEP_SAMPLES) + 0.5) / _SWEEP_SAMPLES
    t0 = int(motion.t_ns[0])
    n_ap = len(radio.aps)
    fading = np.zeros((len(ts), n_ap))
    if len(ts):
        rho = np.exp(-np.diff(ts, prepend=ts[0]) / NS / params.fading_corr_s)
        innov = rng.normal(0.0, params.fading_sigma_db, (len(ts), n_ap))
        fading[0] = innov[0]
        for i in range(1, len(ts)):
            fading[i] = rho[i] * fading[i - 1] + np.sqrt(1.0 - rho[i] ** 2) * innov[i]
    walk_offset = phone.rss_offset_db + rng.normal(0.0, params.walk_rss_sigma_db, n_ap)[None, :] + fading
    layers = []
    for lag in lags:
        t = np.maximum(ts - int(lag * NS), t0)
        xy = positions_at(t, motion)
        k = np.clip(np.searchsorted(motion.t_ns, t, side="left"), 0, len(motion.t_ns) - 1)  # the step under way
        to_ap = radio.aps.xy[None, :, :] - xy[:, None, :]
        cos = np.cos(np.arctan2(to_ap[..., 1], to_ap[..., 0]) - motion.heading[k][:, None])
        layers.append(radio.sample_rss(xy, rng, walk_offset - 0.5 * params.body_loss_db * (1.0 - cos)))
    rss = np.stack(layers)  # (moments, scans, APs)
    pick = rng.integers(0, _SWEEP_SAMPLES, rss.shape[1:])
    return radio.scans_from_rss(ts, np.take_along_axis(rss, pick[None], axis=0)[0])


def simulate_museum_walk(
    session_id: str,
    start_t_ns: int,
    route: Route,
    plan: FloorPlan,
    radio: RadioEnvironment,
    field_: ShadowingField,
    params: MuseumParams,
    phone: PhoneModel,
    rng: np.random.Generator,
    *,
    site: str,
    floor: str,
) -> Session:
    """One out-and-back walk of ``route`` with ``phone``: PDR steps, scans, landmark marks, ground truth."""
    wp = params.walker
    if len(route.xy) < 2 or route.length_m < 1.0:
        raise SimulationError(f"{session_id}: route {route.name!r} is too short to walk")
    period = rng.uniform(*wp.step_period_s)
    mean_len = rng.uniform(*wp.step_length_m)
    out, back = route.xy, route.xy[::-1]
    d0, d1 = out[1] - out[0], back[1] - back[0]
    st = _Steps()
    h0 = math.atan2(d0[1], d0[0]) + rng.uniform(-1, 1) * wp.start_heading_spread_rad
    st.add(out[0].copy(), float(wrap_angle(h0)), 0.0, 0.0, False, False)
    stand = rng.uniform(*wp.start_stand_s)
    s_out = _leg(out, st, mean_len, period, wp, rng, back=False)
    st.pause_s[1] = stand
    n_out = len(st.xy)  # poses 0 .. n_out-1: start and the way out
    h_in = st.heading[-1]
    pause = rng.uniform(*(wp.stairs_pause_s if route.kind == "stairs" else wp.pause_s))
    _far_end(st, h_in, math.atan2(d1[1], d1[0]), pause, wp, rng)
    n_spot = len(st.xy)
    s_back = _leg(back, st, mean_len, period, wp, rng, back=True)
    walk = np.array(st.walk_s)
    t_rel = np.cumsum(walk + np.array(st.pause_s))
    t_ns = start_t_ns + np.round(t_rel * NS).astype(np.int64)
    xy = np.array(st.xy)
    motion = TrueMotion(t_ns, xy, np.array(st.heading), walk, ())
    # Marks: every landmark vertex as the walker passes it; the far one on arrival and before leaving.
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(out, axis=0), axis=1))])
    total = float(arc[-1])
    t_out = t_rel[:n_out]
    t_back = t_rel[n_spot - 1 :]
    marks: list[tuple[float, str]] = []
    for j, lid in enumerate(route.landmark_ids):
        if lid is None:
            continue
        delay = rng.uniform(0.1, 0.4)
        if j == 0:
            marks.append((rng.uniform(0.3, 0.9) * stand, lid))
            marks.append((float(t_rel[-1]) + rng.uniform(0.2, 0.8), lid))
        elif j == len(arc) - 1:
            marks.append((float(t_out[-1]) + delay, lid))
            leave = float(t_rel[n_spot] - walk[n_spot])
            marks.append((leave - rng.uniform(0.1, 0.5), lid))
        else:
            marks.append((float(np.interp(arc[j], np.concatenate([[0.0], s_out]), t_out)) + delay, lid))
            tb = float(np.interp(total - arc[j], np.concatenate([[0.0], s_back]), t_back))
            marks.append((tb + rng.uniform(0.1, 0.4), lid))
    lm = {m.landmark_id: m for m in plan.landmarks}
    landmarks = tuple(
        LandmarkMark(start_t_ns + int(round(t * NS)), lid, lm[lid].x, lm[lid].y) for t, lid in sorted(marks)
    )
    dr = _pdr(st, field_, params.pdr, rng)
    ts = phone_scan_times(int(t_ns[0]), int(t_ns[-1]), phone, rng)
    scans = sweep_scans(radio, ts, motion, phone, params, rng)
    log.debug(
        "%s: %s with %s, %d steps, %d scans, %d marks", session_id, route.name, phone.name, len(xy), len(scans),
        len(landmarks),
    )
    return Session(
        session_id=session_id,
        steps=PoseTrack(t_ns, dr[:, :2], dr[:, 2]),
        scans=scans,
        landmarks=landmarks,
        ground_truth=PoseTrack(t_ns, xy, np.asarray(wrap_angle(motion.heading))),
        site=site,
        floor=floor,
    )
