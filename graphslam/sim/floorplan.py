"""Floor plans for the simulator: walls (line segments) and a walkable graph.

Frame and units: the *site* frame of the building, metres, x along the building's axis,
y 90 deg counter-clockwise from it, origin at the corner of the outer wall with the least
x and y; the building spans x in [0, width_m], y in [0, height_m]. Landmarks and ground
truth use this frame. It is not east/north: the Earth frame of the phone's azimuth is
this frame rotated by ``HeadingModel.earth_from_site_deg`` (``graphslam.sim.heading``).

A plan is a set of corridors (straight, ``2 * half_width`` wide, walls on both
sides with openings at junctions and doors) and rows of rooms along them (one
door per room, facing its corridor). Walkers move along the *walkable graph*:
corridor centre lines (nodes at corridor ends, junctions and in front of every
door) plus one node per room, just inside its door. A room node is a dead end;
a walker entering it wanders to a random point of the room and comes back.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from graphslam.core.types import frozen_array
from graphslam.errors import SimulationError

Side = Literal["S", "N", "W", "E"]

# A room node sits this far inside the door, so the walker crosses the door line.
_THRESHOLD_M = 0.6
# Random waypoints in a room keep this clearance from its walls.
_ROOM_MARGIN_M = 1.0
# Corridor centre-line nodes closer than this are merged into one.
_MERGE_M = 0.5



@dataclass(frozen=True)
class Landmark:
    """A surveyed point (site frame, m) that walkers mark with a button press."""

    landmark_id: str
    x: float
    y: float

    @property
    def xy(self) -> NDArray[np.float64]:
        return np.array([self.x, self.y])


@dataclass(frozen=True, eq=False)
class FloorPlan:
    """Walls and walkable graph of one floor (site frame, metres).

    ``walls``: (W, 4) segments ``x1, y1, x2, y2``.
    ``nodes``: (K, 2) walkable-graph node positions; ``edges``: (E, 2) node indices.
    ``node_room``: (K,) index into ``rooms`` for room nodes, -1 for corridor nodes.
    ``rooms``: (R, 4) ``xmin, ymin, xmax, ymax`` of the area a walker may wander to
    inside each room (room interior minus a clearance).
    ``line``: (2, 2) start and end of the marked straight line walked in the
    ``corridor`` experiment, or ``None``.
    """

    name: str
    width_m: float
    height_m: float
    walls: NDArray[np.float64]
    nodes: NDArray[np.float64]
    edges: NDArray[np.int64]
    node_room: NDArray[np.int64]
    rooms: NDArray[np.float64]
    landmarks: tuple[Landmark, ...]
    line: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "walls", frozen_array(np.reshape(self.walls, (-1, 4)), np.float64))
        object.__setattr__(self, "nodes", frozen_array(np.reshape(self.nodes, (-1, 2)), np.float64))
        object.__setattr__(self, "edges", frozen_array(np.reshape(self.edges, (-1, 2)), np.int64))
        object.__setattr__(self, "node_room", frozen_array(self.node_room, np.int64))
        object.__setattr__(self, "rooms", frozen_array(np.reshape(self.rooms, (-1, 4)), np.float64))
        object.__setattr__(self, "landmarks", tuple(self.landmarks))
        if self.line is not None:
            object.__setattr__(self, "line", frozen_array(np.reshape(self.line, (2, 2)), np.float64))
        k = len(self.nodes)
        if k == 0 or len(self.edges) == 0:
            raise SimulationError(f"floor plan {self.name!r}: empty walkable graph")
        if self.edges.min() < 0 or self.edges.max() >= k or len(self.node_room) != k:
            raise SimulationError(f"floor plan {self.name!r}: graph edges reference unknown nodes")
        ids = [lm.landmark_id for lm in self.landmarks]
        if len(set(ids)) != len(ids):
            raise SimulationError(f"floor plan {self.name!r}: duplicate landmark ids")

    def neighbours(self) -> list[list[int]]:
        """Adjacency lists of the walkable graph."""
        adj: list[list[int]] = [[] for _ in range(len(self.nodes))]
        for a, b in self.edges.tolist():
            adj[a].append(b)
            adj[b].append(a)
        return adj

    @property
    def corridor_nodes(self) -> NDArray[np.int64]:
        return np.flatnonzero(self.node_room < 0)

    @property
    def landmark_xy(self) -> NDArray[np.float64]:
        return np.array([[lm.x, lm.y] for lm in self.landmarks], dtype=float).reshape(-1, 2)


# --------------------------------------------------------------------------- builder


@dataclass
class _Line:
    """An axis-parallel wall line with openings: x = c (axis 'v') or y = c (axis 'h')."""

    axis: Literal["h", "v"]
    c: float
    a0: float
    a1: float
    gaps: list[tuple[float, float]] = field(default_factory=list)

    def segments(self) -> list[tuple[float, float, float, float]]:
        out = []
        pos = self.a0
        for g0, g1 in sorted(self.gaps):
            if g0 > pos:
                out.append((pos, min(g0, self.a1)))
            pos = max(pos, g1)
        if pos < self.a1:
            out.append((pos, self.a1))
        if self.axis == "h":
            return [(s, self.c, e, self.c) for s, e in out if e - s > 1e-6]
        return [(self.c, s, self.c, e) for s, e in out if e - s > 1e-6]


@dataclass
class _Builder:
    width: float
    height: float
    hw: float  # corridor half width
    lines: dict[str, _Line] = field(default_factory=dict)
    walls: list[tuple[float, float, float, float]] = field(default_factory=list)
    # corridor id -> (axis, centre coordinate, set of node positions along it)
    corridors: dict[str, tuple[str, float, float, float, set[float]]] = field(default_factory=dict)
    doors: list[tuple[str, float, NDArray, tuple[float, float, float, float]]] = field(default_factory=list)

    def corridor(self, cid: str, axis: Literal["h", "v"], c: float, a0: float, a1: float) -> None:
        """A corridor along ``axis`` at centre ``c``, walls from a0 to a1; nodes 2 m from the ends."""
        self.lines[f"{cid}-"] = _Line(axis, c - self.hw, a0, a1)
        self.lines[f"{cid}+"] = _Line(axis, c + self.hw, a0, a1)
        self.corridors[cid] = (axis, c, a0, a1, set())

    def room_row(
        self, rect: tuple[float, float, float, float], facing: Side, cid: str, room_w: float, door_w: float
    ) -> None:
        """Rooms filling ``rect`` (xmin, ymin, xmax, ymax), doors on the ``facing`` edge onto corridor ``cid``."""
        x0, y0, x1, y1 = rect
        along_x = facing in ("S", "N")
        a0, a1 = (x0, x1) if along_x else (y0, y1)
        n = max(1, int(round((a1 - a0) / room_w)))
        cuts = np.linspace(a0, a1, n + 1)
        axis, c, _, _, _ = self.corridors[cid]
        line_key = f"{cid}+" if facing in ("S", "W") else f"{cid}-"
        for i in range(n):
            lo, hi = float(cuts[i]), float(cuts[i + 1])
            if i > 0:  # partition wall between room i-1 and room i
                self.walls.append((lo, y0, lo, y1) if along_x else (x0, lo, x1, lo))
            mid = 0.5 * (lo + hi)
            self.lines[line_key].gaps.append((mid - door_w / 2, mid + door_w / 2))
            self.corridors[cid][4].add(mid)
            if along_x:
                wall_y = y0 if facing == "S" else y1
                inside = wall_y + (_THRESHOLD_M if facing == "S" else -_THRESHOLD_M)
                node = np.array([mid, inside])
                box = (lo + _ROOM_MARGIN_M, y0 + _ROOM_MARGIN_M, hi - _ROOM_MARGIN_M, y1 - _ROOM_MARGIN_M)
            else:
                wall_x = x0 if facing == "W" else x1
                inside = wall_x + (_THRESHOLD_M if facing == "W" else -_THRESHOLD_M)
                node = np.array([inside, mid])
                box = (x0 + _ROOM_MARGIN_M, lo + _ROOM_MARGIN_M, x1 - _ROOM_MARGIN_M, hi - _ROOM_MARGIN_M)
            self.doors.append((cid, mid, node, box))

    def junction(self, h_cid: str, v_cid: str, north: bool, south: bool) -> None:
        """Open the walls of horizontal corridor ``h_cid`` where vertical ``v_cid`` joins it."""
        _, yc, _, _, hset = self.corridors[h_cid]
        _, xc, _, _, vset = self.corridors[v_cid]
        if north:
            self.lines[f"{h_cid}+"].gaps.append((xc - self.hw, xc + self.hw))
        if south:
            self.lines[f"{h_cid}-"].gaps.append((xc - self.hw, xc + self.hw))
        hset.add(xc)
        vset.add(yc)

    def build(self, name: str, landmarks: list[tuple[str, float, float]], line: NDArray | None) -> FloorPlan:
        w, h = self.width, self.height
        walls = [(0.0, 0.0, w, 0.0), (w, 0.0, w, h), (w, h, 0.0, h), (0.0, h, 0.0, 0.0)]
        walls += self.walls
        for ln in self.lines.values():
            walls += ln.segments()
        # Corridor centre-line nodes, keyed by rounded position so junctions are shared.
        key_to_idx: dict[tuple[int, int], int] = {}
        nodes: list[tuple[float, float]] = []

        def node(x: float, y: float) -> int:
            k = (int(round(x / _MERGE_M)), int(round(y / _MERGE_M)))
            if k not in key_to_idx:
                key_to_idx[k] = len(nodes)
                nodes.append((x, y))
            return key_to_idx[k]

        edges: list[tuple[int, int]] = []
        door_node: dict[tuple[str, float], int] = {}
        for cid, (axis, c, a0, a1, pos) in self.corridors.items():
            along = sorted(pos | {a0 + 2.0, a1 - 2.0})
            merged: list[float] = []
            for a in along:
                if not merged or a - merged[-1] > _MERGE_M:
                    merged.append(a)
            idx = [node(a, c) if axis == "h" else node(c, a) for a in merged]
            edges += [(i, j) for i, j in zip(idx[:-1], idx[1:]) if i != j]
            for a in pos:
                j = int(np.argmin(np.abs(np.array(merged) - a)))
                door_node[(cid, a)] = idx[j]
        node_room = [-1] * len(nodes)
        rooms: list[tuple[float, float, float, float]] = []
        for cid, mid, pt, box in self.doors:
            r = len(nodes)
            nodes.append((float(pt[0]), float(pt[1])))
            node_room.append(len(rooms))
            rooms.append(box)
            edges.append((door_node[(cid, mid)], r))
        nodes_a = np.array(nodes)
        lms = []
        for lid, x, y in landmarks:
            # Landmarks sit on graph nodes so that walkers pass over them.
            j = int(np.argmin(np.linalg.norm(nodes_a - [x, y], axis=1)))
            lms.append(Landmark(lid, float(nodes_a[j, 0]), float(nodes_a[j, 1])))
        return FloorPlan(
            name=name,
            width_m=w,
            height_m=h,
            walls=np.array(walls),
            nodes=nodes_a,
            edges=np.array(edges),
            node_room=np.array(node_room),
            rooms=np.array(rooms),
            landmarks=tuple(lms),
            line=line,
        )


def office_plan(
    width_m: float = 120.0,
    height_m: float = 60.0,
    h_corridors: tuple[float, float] = (15.0, 45.0),
    v_corridors: tuple[float, ...] = (10.0, 60.0, 110.0),
    half_width_m: float = 1.25,
    room_width_m: float = 8.0,
    door_width_m: float = 1.0,
) -> FloorPlan:
    """An office floor: two long east-west corridors joined by north-south ones.

    With the defaults: 120 m x 60 m, corridors at y = 15 and y = 45 (full width)
    and x = 10, 60, 110 (between them), i.e. two corridor loops; rooms of ~8 m
    along every corridor wall; 8 landmarks (6 junctions, 2 doors).
    """
    yl, yh = h_corridors
    hw = half_width_m
    if not (0 < yl - hw and yl + hw < yh - hw and yh + hw < height_m):
        raise SimulationError("office_plan: corridors do not fit in the building")
    b = _Builder(width_m, height_m, hw)
    b.corridor("H0", "h", yl, 0.0, width_m)
    b.corridor("H1", "h", yh, 0.0, width_m)
    for i, xv in enumerate(v_corridors):
        b.corridor(f"V{i}", "v", xv, yl + hw, yh - hw)
        b.junction("H0", f"V{i}", north=True, south=False)
        b.junction("H1", f"V{i}", north=False, south=True)
    # Rooms south of H0 and north of H1 (full width, back wall = outer wall).
    b.room_row((0.0, 0.0, width_m, yl - hw), "N", "H0", room_width_m, door_width_m)
    b.room_row((0.0, yh + hw, width_m, height_m), "S", "H1", room_width_m, door_width_m)
    # Between the corridors: end blocks face the outer vertical corridors;
    # middle blocks hold two rows back to back (a wall at mid-height).
    xs = list(v_corridors)
    b.room_row((0.0, yl + hw, xs[0] - hw, yh - hw), "E", "V0", room_width_m, door_width_m)
    b.room_row((xs[-1] + hw, yl + hw, width_m, yh - hw), "W", f"V{len(xs) - 1}", room_width_m, door_width_m)
    ym = 0.5 * (yl + yh)
    for xa, xb in zip(xs[:-1], xs[1:]):
        b.walls.append((xa + hw, ym, xb - hw, ym))
        b.room_row((xa + hw, yl + hw, xb - hw, ym), "S", "H0", room_width_m, door_width_m)
        b.room_row((xa + hw, ym, xb - hw, yh - hw), "N", "H1", room_width_m, door_width_m)
    landmarks = [(f"L{i + 1}", xv, yc) for i, (yc, xv) in enumerate((y, x) for y in h_corridors for x in xs)]
    landmarks += [(f"L{len(landmarks) + 1}", 0.3 * width_m, yl), (f"L{len(landmarks) + 2}", 0.7 * width_m, yh)]
    return b.build("office", landmarks, None)


def corridor_plan(
    width_m: float = 100.0,
    height_m: float = 20.0,
    half_width_m: float = 1.25,
    room_width_m: float = 6.0,
    door_width_m: float = 1.0,
    line_m: tuple[float, float] = (10.0, 90.0),
) -> FloorPlan:
    """One long east-west corridor (y = height/2) with rooms on both sides.

    The marked line of the alignment experiment runs along the corridor centre
    from x = line_m[0] to x = line_m[1]; landmarks at both ends and the middle.
    """
    yc = 0.5 * height_m
    hw = half_width_m
    b = _Builder(width_m, height_m, hw)
    b.corridor("H0", "h", yc, 0.0, width_m)
    b.room_row((0.0, 0.0, width_m, yc - hw), "N", "H0", room_width_m, door_width_m)
    b.room_row((0.0, yc + hw, width_m, height_m), "S", "H0", room_width_m, door_width_m)
    x0, x1 = line_m
    b.corridors["H0"][4].update({x0, 0.5 * (x0 + x1), x1})
    landmarks = [("L1", x0, yc), ("L2", 0.5 * (x0 + x1), yc), ("L3", x1, yc)]
    return b.build("corridor", landmarks, np.array([[x0, yc], [x1, yc]]))
