"""UWB scenarios: the paper's seven-tag experiment (Fig. 5) and a crowd surveying together.

``zones``: Paper 003, section V. Four rooms in a row (10 m x 8 m each, castle stone walls that
pass almost nothing, doors 1.5 m wide on the rooms' centre line), zones A-D with 4, 3, 2 and 0
anchors (2.2 m high). Seven tags start together in zone A and walk, in two groups with their
own itineraries, from goal to goal (U(3, 10) s at each, 0.5-1 m/s): the groups split, meet
again and split, and a tag near a door hears tags two rooms apart that its own group does not
(hidden nodes).

``crowd``: the survey use: walkers of the simulator's office floor (``graphslam.sim``) all
surveying at the same time, with 2-4 anchors in the corridors; their tags range with the
anchors and with each other through the same network. Every ``no_wifi_every``-th walker's
phone records no WiFi (a tag and a foot module only): such a walk shares no WiFi edge with
anyone and can only be joined by ranges.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from graphslam.core.types import Session, Survey, UwbRanges
from graphslam.core.uwb.motion import stride_knots
from graphslam.errors import ConfigError
from graphslam.io.mcap_writer import write_session
from graphslam.sim.scenarios import Building, SimulatedSurvey, simulate, with_overrides
from graphslam.sim.uwb.network import Devices, NetworkParams, NetworkRun, simulate_network
from graphslam.sim.uwb.radio import UwbRadioParams

NS = 1_000_000_000
# 2026-06-01T09:00:00Z: the seven-tag runs' shared clock origin
ZONES_T0_NS = 1_780_304_400 * NS


def _rng(seed: int, stream: int, i: int = 0) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(10 + stream, i)))


# --------------------------------------------------------------------------- the seven-tag experiment


@dataclass(frozen=True)
class Zone:
    name: str
    x0: float
    x1: float
    anchors: tuple[tuple[float, float, float], ...]


@dataclass(frozen=True, eq=False)
class ZonesSite:
    """Walls (W, 4), zones along x, door centres between them, goal points per zone (site frame, m)."""

    walls: NDArray[np.float64]
    zones: tuple[Zone, ...]
    doors: NDArray[np.float64]  # (Z-1, 2)
    goals: tuple[NDArray[np.float64], ...]
    height_m: float

    @property
    def anchor_ids(self) -> tuple[str, ...]:
        return tuple(f"A{z.name}{k + 1}" for z in self.zones for k in range(len(z.anchors)))

    @property
    def anchor_xyz(self) -> NDArray[np.float64]:
        return np.array([a for z in self.zones for a in z.anchors], float).reshape(-1, 3)

    def zone_of(self, xy: NDArray) -> NDArray[np.int64]:
        edges = np.array([z.x1 for z in self.zones[:-1]])
        return np.searchsorted(edges, np.asarray(xy)[..., 0], side="right")


def zones_site(room_w: float = 10.0, room_h: float = 8.0, door_w: float = 1.5, anchor_z: float = 2.2) -> ZonesSite:
    """The paper's Fig. 5 layout, as we chose it (the paper gives no dimensions)."""
    n = 4
    w = n * room_w
    yc = room_h / 2
    walls = [(0, 0, w, 0), (w, 0, w, room_h), (w, room_h, 0, room_h), (0, room_h, 0, 0)]
    for k in range(1, n):
        x = k * room_w
        walls += [(x, 0, x, yc - door_w / 2), (x, yc + door_w / 2, x, room_h)]
    m = 0.5  # anchors 0.5 m from the walls
    names = "ABCD"
    layout = {
        0: [(m, m), (room_w - m, m), (room_w - m, room_h - m), (m, room_h - m)],
        1: [(m, m), (room_w - m, m), (room_w / 2, room_h - m)],
        2: [(m, m), (room_w - m, room_h - m)],
        3: [],
    }
    zones = tuple(
        Zone(names[k], k * room_w, (k + 1) * room_w, tuple((k * room_w + x, y, anchor_z) for x, y in layout[k]))
        for k in range(n)
    )
    gx = np.array([0.25, 0.75, 0.5, 0.25, 0.75]) * room_w
    gy = np.array([0.25, 0.25, 0.5, 0.75, 0.75]) * room_h
    goals = tuple(np.column_stack([k * room_w + gx, gy]) for k in range(n))
    doors = np.array([[k * room_w, yc] for k in range(1, n)], float)
    return ZonesSite(np.array(walls, float), zones, doors, goals, room_h)


ZONES_RADIO = UwbRadioParams(wall_range_factor=0.1)  # stone walls: 30 m -> 3 m through one
# the two groups' itineraries (zone indices), the paper's "groups splitting and merging"
ZONE_ITINERARIES = ((0, 1, 2, 3, 2, 1, 0), (0, 1, 0, 1, 2, 3, 2))
ZONE_GROUPS = (0, 0, 0, 0, 1, 1, 1)


@dataclass(frozen=True, eq=False)
class TagPaths:
    """Piecewise-linear true paths: per tag knot times (s from t0) and positions (m)."""

    t_s: tuple[NDArray[np.float64], ...]
    xy: tuple[NDArray[np.float64], ...]

    def positions(self, t: float) -> NDArray:
        return np.array([[np.interp(t, ts, p[:, 0]), np.interp(t, ts, p[:, 1])] for ts, p in zip(self.t_s, self.xy)])

    def at(self, tag: int, t: NDArray) -> NDArray:
        ts, p = self.t_s[tag], self.xy[tag]
        return np.column_stack([np.interp(t, ts, p[:, 0]), np.interp(t, ts, p[:, 1])])

    @property
    def end_s(self) -> float:
        return float(min(ts[-1] for ts in self.t_s))


def zone_paths(site: ZonesSite, seed: int, dwell_s: tuple[float, float] = (20.0, 35.0)) -> TagPaths:
    """Seven tags walking the two itineraries from a common start in zone A."""
    group_rng = [_rng(seed, 0, g) for g in range(len(ZONE_ITINERARIES))]
    # each group leaves a zone at the same instants (its members then walk at their own pace)
    leave = [np.cumsum(r.uniform(*dwell_s, len(it))) for r, it in zip(group_rng, ZONE_ITINERARIES)]
    ts_all, xy_all = [], []
    for tag, g in enumerate(ZONE_GROUPS):
        rng = _rng(seed, 1, tag)
        speed = rng.uniform(0.5, 1.0)
        goals0 = site.goals[0]
        p = goals0[rng.integers(len(goals0))] + rng.uniform(-0.5, 0.5, 2)
        t = 0.0
        ts, pts = [t], [p]
        zone = 0

        def walk_to(q: NDArray, t: float, p: NDArray) -> tuple[float, NDArray]:
            d = float(np.linalg.norm(q - p))
            t += d / speed
            ts.append(t)
            pts.append(q)
            return t, q

        for stop, (z, t_leave) in enumerate(zip(ZONE_ITINERARIES[g], leave[g])):
            if z != zone:  # through the doors between the zones
                step = 1 if z > zone else -1
                for dz in range(zone, z, step):
                    door = site.doors[dz if step > 0 else dz - 1] + rng.uniform(-0.3, 0.3, 2) * [0, 1]
                    t, p = walk_to(door, t, p)
                zone = z
            while True:  # goal to goal in the zone until the group leaves
                goal = site.goals[z][rng.integers(len(site.goals[z]))] + rng.uniform(-0.4, 0.4, 2)
                t_arrive = t + float(np.linalg.norm(goal - p)) / speed
                if t_arrive > t_leave and stop < len(leave[g]) - 1:
                    break
                t, p = walk_to(goal, t, p)
                t += rng.uniform(3.0, 10.0)
                ts.append(t)
                pts.append(p)
                if t > t_leave:
                    break
            if t < t_leave:
                t = t_leave
                ts.append(t)
                pts.append(p)
        ts_all.append(np.array(ts))
        xy_all.append(np.array(pts))
    return TagPaths(tuple(ts_all), tuple(xy_all))


@dataclass(frozen=True, eq=False)
class ZonesRun:
    site: ZonesSite
    paths: TagPaths
    network: NetworkRun
    seed: int

    @property
    def tag_ids(self) -> tuple[str, ...]:
        return self.network.devices.tag_ids

    def sessions(self) -> tuple[Session, ...]:
        """The run as recordings: one session per tag with its ``/uwb/range`` stream (and the
        anchors), ground truth along its whole true path (the path's knots up to the network's end:
        the path is piecewise linear between them; evaluation only). No steps are recorded (no foot
        module in this experiment): ``steps`` holds the first true position only, as the contract
        needs one."""
        net = self.network
        anchors = dict(zip(net.devices.anchor_ids, self.site.anchor_xyz.tolist()))
        out = []
        for tag, tid in enumerate(self.tag_ids):
            ts = self.paths.t_s[tag]
            end = float(net.t1_s)
            t = np.unique(np.concatenate([[0.0], ts[(ts > 0.0) & (ts < end)], [min(end, float(ts[-1]))]]))
            out.append(_tag_session(net, tag, tid, ZONES_T0_NS, anchors, t, self.paths.at(tag, t)))
        return tuple(out)

    def write(self, out_dir: str | Path) -> list[Path]:
        """``OUT/<session_id>.mcap`` per tag (the ``/uwb/range`` stream and the anchors)."""
        return [write_session(s, Path(out_dir) / f"{s.session_id}.mcap") for s in self.sessions()]


def _tag_ranges(net: NetworkRun, tag: int, t0_ns: int) -> UwbRanges | None:
    r = net.ranges
    sel = np.flatnonzero(r.tag == tag)
    if not len(sel):
        return None
    order = sel[np.argsort(r.t_s[sel], kind="stable")]
    nt = net.devices.n_tags
    return UwbRanges(
        t0_ns + np.round(r.t_s[order] * NS).astype(np.int64),
        tuple(net.responder_name(int(j)) for j in r.responder[order]),
        r.responder[order] >= nt,
        np.maximum(r.range_m[order], 0.0),
    )


def _tag_session(net: NetworkRun, tag: int, tid: str, t0_ns: int, anchors: dict, t_s: NDArray, xy: NDArray) -> Session:
    """A tag's recording: its ranges, and its true path ``xy`` at ``t_s`` (s from ``t0_ns``; heading:
    the direction to the next point, the last one's kept)."""
    from graphslam.core.types import PoseTrack

    steps = PoseTrack(np.array([t0_ns], np.int64), np.zeros((1, 2)), np.zeros(1))
    d = np.diff(xy, axis=0)
    heading = np.arctan2(d[:, 1], d[:, 0]) if len(d) else np.zeros(0)
    heading = np.concatenate([heading, heading[-1:] if len(heading) else [0.0]])
    truth = PoseTrack(t0_ns + np.round(np.asarray(t_s) * NS).astype(np.int64), np.asarray(xy, float), heading)
    return Session(
        session_id=f"zones-{tid}", steps=steps, ground_truth=truth, site="sim-zones", floor="F1",
        uwb_id=tid, uwb_ranges=_tag_ranges(net, tag, t0_ns), uwb_anchors=anchors,
    )


def simulate_zones(seed: int, params: NetworkParams | None = None, end_s: float | None = None) -> ZonesRun:
    """One run of the seven-tag experiment (``end_s``: stop the network earlier, e.g. in tests)."""
    site = zones_site()
    paths = zone_paths(site, seed)
    p = params or NetworkParams(radio=ZONES_RADIO)
    devices = Devices(
        tag_ids=tuple(f"Tag{101 + i}" for i in range(len(ZONE_GROUPS))),
        anchor_ids=site.anchor_ids,
        anchor_xyz=site.anchor_xyz,
        positions=paths.positions,
        active=lambda t: np.ones(len(ZONE_GROUPS), bool),
        walls=site.walls,
    )
    net = simulate_network(devices, 0.0, paths.end_s if end_s is None else min(end_s, paths.end_s), p, _rng(seed, 2))
    return ZonesRun(site, paths, net, seed)


# --------------------------------------------------------------------------- a crowd surveying together


@dataclass(frozen=True)
class CrowdUwb:
    """The crowd survey with UWB (site frame m; durations in min)."""

    n_walkers: int = 12
    duration_min: tuple[float, float] = (5.0, 8.0)
    n_anchors: int = 4
    no_wifi_every: int = 4  # every k-th walker records no WiFi (0: all do)
    nlos: bool = False  # bias a third of the ranges (bodies and walls); else no range is biased (walls only limit the reach)
    anchor_z: float = 2.5
    radio: UwbRadioParams = field(default_factory=UwbRadioParams)

    def __post_init__(self) -> None:
        if not 0 <= self.n_anchors <= len(CROWD_ANCHORS):
            raise ConfigError(f"crowd UWB: n_anchors must be in [0, {len(CROWD_ANCHORS)}]")
        if self.n_walkers < 2 or self.no_wifi_every < 0:
            raise ConfigError("crowd UWB: need at least 2 walkers and no_wifi_every >= 0")


# On the office floor's east-west corridors (y = 15, 45): each covers ~30 m of corridor either way.
CROWD_ANCHORS = ((35.0, 15.0), (85.0, 45.0), (85.0, 15.0), (35.0, 45.0))
# With los_nlos_prob = 0.2, 31-35 % of the ranges come out NLOS (through-wall links add the rest;
# measured by `python -m lab.bench uwb-survey`): about a third, the share the NLOS experiment asks for.
CROWD_NLOS_LOS_PROB = 0.2


@dataclass(frozen=True, eq=False)
class CrowdRun:
    survey: Survey  # sessions with steps, scans (some without), ground truth, UWB ranges + anchors
    building: Building
    network: NetworkRun
    anchors: dict[str, tuple[float, float, float]]
    no_wifi: tuple[str, ...]  # session ids of the walkers without WiFi
    sim: SimulatedSurvey

    def write(self, out_dir: str | Path) -> list[Path]:
        """``OUT/<session_id>.mcap`` per walker: steps, scans, ground truth, marks, UWB ranges, anchors."""
        return [write_session(s, Path(out_dir) / f"{s.session_id}.mcap") for s in self.survey]


def simulate_crowd(seed: int, spec: CrowdUwb = CrowdUwb(), params: NetworkParams | None = None) -> CrowdRun:
    """Walkers of the office floor surveying at once (start within ~2 min), ranging over UWB."""
    sc = with_overrides(
        "crowd", name="uwbcrowd", n_walks=spec.n_walkers, duration_range_min=spec.duration_min, walk_spacing_s=5.0,
        description="walkers surveying at the same time, with UWB tags",
    )
    sim = simulate(sc, seed=seed)
    sessions = list(sim.survey.sessions)
    t0_ns = min(int(s.steps.t_ns[0]) for s in sessions)
    t1_ns = max(int(s.steps.t_ns[-1]) for s in sessions)
    truths = [s.ground_truth for s in sessions]
    assert all(g is not None for g in truths)
    spans = np.array([[g.t_ns[0], g.t_ns[-1]] for g in truths], np.int64)  # type: ignore[union-attr]

    # each walker's stride knots once (position_at's, which the network asks for thousands of times)
    knots = [(int(g.t_ns[0]), *stride_knots(g.t_ns, g.xy)) for g in truths]  # type: ignore[union-attr]

    def positions(t: float) -> NDArray:
        q = t0_ns + int(round(t * NS))
        return np.array([[np.interp((q - t0) / 1e9, kt, kxy[:, 0]), np.interp((q - t0) / 1e9, kt, kxy[:, 1])]
                         for t0, kt, kxy in knots])

    def active(t: float) -> NDArray:
        tn = t0_ns + t * NS
        return (spans[:, 0] <= tn) & (tn <= spans[:, 1])

    anchor_xy = CROWD_ANCHORS[: spec.n_anchors]
    anchor_ids = tuple(f"A{k + 1}" for k in range(spec.n_anchors))
    anchor_xyz = np.array([[x, y, spec.anchor_z] for x, y in anchor_xy]).reshape(-1, 3)
    if spec.nlos:
        radio = replace(spec.radio, los_nlos_prob=CROWD_NLOS_LOS_PROB, nlos_through_walls=True)
    else:
        radio = replace(spec.radio, los_nlos_prob=0.0, nlos_through_walls=False)
    p = params or NetworkParams(radio=radio)
    devices = Devices(
        tag_ids=tuple(f"T{101 + i}" for i in range(len(sessions))),
        anchor_ids=anchor_ids, anchor_xyz=anchor_xyz, positions=positions, active=active,
        walls=sim.building.walls,
    )
    net = simulate_network(devices, 0.0, (t1_ns - t0_ns) / NS, p, _rng(seed, 3))
    anchors = {a: tuple(map(float, xyz)) for a, xyz in zip(anchor_ids, anchor_xyz)}
    out, no_wifi = [], []
    for i, s in enumerate(sessions):
        drop_wifi = spec.no_wifi_every > 0 and i % spec.no_wifi_every == spec.no_wifi_every - 1
        if drop_wifi:
            no_wifi.append(s.session_id)
        out.append(replace(
            s, scans=() if drop_wifi else s.scans, uwb_id=devices.tag_ids[i],
            uwb_ranges=_tag_ranges(net, i, t0_ns), uwb_anchors=anchors,  # every session knows the anchors
        ))
    return CrowdRun(Survey(tuple(out)), sim.building, net, anchors, tuple(no_wifi), sim)


def nlos_fraction(net: NetworkRun) -> float:
    return float(net.ranges.nlos.mean()) if len(net.ranges.nlos) else math.nan
