"""Domain objects: sessions, scans, landmarks. Pure data, checked on construction.

Conventions (used everywhere unless a docstring says otherwise):
- time: integer nanoseconds since the Unix epoch (``t_ns``);
- positions: metres; headings: radians, counter-clockwise about +z, wrapped to (-pi, pi];
- a session's ``steps`` are in the foot module's own frame (first pose (0, 0, 0) by
  contract); ``ground_truth`` and ``landmarks`` are in the site frame and are for
  evaluation only: nothing in ``graphslam.core`` that builds or solves a graph reads them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Iterator, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray


def frozen_array(a: object, dtype: object) -> NDArray:
    """A read-only copy: frozen dataclasses must not share writable arrays with callers."""
    arr: NDArray = np.array(a, dtype=dtype, copy=True)
    arr.setflags(write=False)
    return arr


def wrap_angle(a: NDArray | float) -> NDArray | float:
    """Wrap angles to (-pi, pi]."""
    return np.pi - np.mod(np.pi - np.asarray(a), 2.0 * np.pi)


@dataclass(frozen=True, eq=False)
class PoseTrack:
    """A time-stamped sequence of planar poses (x, y, heading)."""

    t_ns: NDArray[np.int64]
    xy: NDArray[np.float64]  # (N, 2)
    heading: NDArray[np.float64]  # (N,)

    def __post_init__(self) -> None:
        t = frozen_array(self.t_ns, np.int64)
        xy = frozen_array(np.reshape(self.xy, (-1, 2)), np.float64)
        h = frozen_array(self.heading, np.float64)
        if not (t.ndim == 1 and h.ndim == 1 and len(t) == len(xy) == len(h)):
            raise ValueError("PoseTrack: t_ns, xy and heading must have the same length")
        if not (np.isfinite(xy).all() and np.isfinite(h).all()):
            raise ValueError("PoseTrack: non-finite pose")
        if len(t) > 1 and np.any(np.diff(t) <= 0):
            raise ValueError("PoseTrack: timestamps must strictly increase")
        object.__setattr__(self, "t_ns", t)
        object.__setattr__(self, "xy", xy)
        object.__setattr__(self, "heading", h)

    def __len__(self) -> int:
        return len(self.t_ns)

    @property
    def xyh(self) -> NDArray[np.float64]:
        """(N, 3) array of x, y, heading."""
        return np.column_stack([self.xy, self.heading])

    @property
    def path_length(self) -> float:
        """Walked length in metres (sum of step lengths)."""
        if len(self) < 2:
            return 0.0
        return float(np.linalg.norm(np.diff(self.xy, axis=0), axis=1).sum())

    @classmethod
    def from_xyh(cls, t_ns: Sequence[int] | NDArray, xyh: NDArray) -> "PoseTrack":
        xyh = np.asarray(xyh, dtype=float).reshape(-1, 3)
        return cls(np.asarray(t_ns, dtype=np.int64), xyh[:, :2], xyh[:, 2])


@dataclass(frozen=True)
class Scan:
    """One completed WiFi scan: access point id (BSSID) -> RSS in dBm."""

    t_ns: int
    readings: Mapping[str, float]

    def __post_init__(self) -> None:
        r = {k: float(v) for k, v in dict(self.readings).items()}
        if not all(type(b) is str and b for b in r):
            raise ValueError("Scan: bssid must be a non-empty string")
        if r and not np.isfinite(np.fromiter(r.values(), float, len(r))).all():
            raise ValueError("Scan: non-finite rssi")
        object.__setattr__(self, "t_ns", int(self.t_ns))
        object.__setattr__(self, "readings", MappingProxyType(r))

    def __len__(self) -> int:
        return len(self.readings)

    @classmethod
    def _validated(cls, t_ns: int, readings: dict[str, float]) -> "Scan":
        """A scan whose readings a reader has already checked as ``__post_init__`` does (non-empty
        ``str`` BSSIDs, finite ``float`` dBm; ``t_ns`` an ``int``): no second pass over every reading.
        Why: a large survey holds hundreds of thousands of readings."""
        scan = object.__new__(cls)
        object.__setattr__(scan, "t_ns", t_ns)
        object.__setattr__(scan, "readings", MappingProxyType(readings))
        return scan


def shared_floats(values: np.ndarray) -> list[float]:
    """``values.tolist()`` with one float object per distinct value. Why: a survey keeps every reading
    as a Python float in its scans' dicts, and RSS values repeat (whole dBm mostly): 200 walks hold
    ~800k readings, ~19 MiB of float objects, of ~100 values. (BSSIDs are interned for the same reason.)"""
    if not len(values):
        return []
    uniq, inv = np.unique(values, return_inverse=True)
    u = uniq.tolist()
    return list(map(u.__getitem__, inv.ravel().tolist()))


@dataclass(frozen=True)
class LandmarkMark:
    """A walker pressed the button at surveyed landmark ``landmark_id`` (site frame)."""

    t_ns: int
    landmark_id: str
    x: float
    y: float

    def __post_init__(self) -> None:
        if not (np.isfinite(self.x) and np.isfinite(self.y)):
            raise ValueError("LandmarkMark: non-finite position")


@dataclass(frozen=True, eq=False)
class UwbRanges:
    """One tag's completed two-way rangings (its session's ``/uwb/range``), in time order.

    ``responder_id[i]`` is an anchor id (``is_anchor[i]``) or another session's ``uwb_id``;
    ``range_m`` is the measured distance (m, 3-D, as the radio reports it).
    """

    t_ns: NDArray[np.int64]
    responder_id: tuple[str, ...]
    is_anchor: NDArray[np.bool_]
    range_m: NDArray[np.float64]

    def __post_init__(self) -> None:
        t = frozen_array(self.t_ns, np.int64)
        a = frozen_array(self.is_anchor, np.bool_)
        r = frozen_array(self.range_m, np.float64)
        ids = tuple(self.responder_id)
        if not (t.ndim == 1 and len(t) == len(a) == len(r) == len(ids)):
            raise ValueError("UwbRanges: t_ns, responder_id, is_anchor and range_m must have the same length")
        if not (np.isfinite(r).all() and (r >= 0).all()):
            raise ValueError("UwbRanges: ranges must be finite and >= 0")
        if len(t) > 1 and np.any(np.diff(t) < 0):
            raise ValueError("UwbRanges: timestamps must not decrease")
        object.__setattr__(self, "t_ns", t)
        object.__setattr__(self, "responder_id", ids)
        object.__setattr__(self, "is_anchor", a)
        object.__setattr__(self, "range_m", r)

    def __len__(self) -> int:
        return len(self.t_ns)


@dataclass(frozen=True, eq=False)
class HeadingTrack:
    """The phone's own azimuth (``/phone/heading``): ``yaw[i]`` at ``t_ns[i]``, radians counter-clockwise
    from east, Earth-fixed (east/north). Not the walking direction in general (the phone's pointing
    relative to the body is a per-walk offset) and bent indoors by the building's magnetic field."""

    t_ns: NDArray[np.int64]
    yaw: NDArray[np.float64]

    def __post_init__(self) -> None:
        t = frozen_array(self.t_ns, np.int64)
        y = frozen_array(self.yaw, np.float64)
        if not (t.ndim == 1 and y.ndim == 1 and len(t) == len(y)):
            raise ValueError("HeadingTrack: t_ns and yaw must have the same length")
        if not np.isfinite(y).all():
            raise ValueError("HeadingTrack: non-finite yaw")
        if len(t) > 1 and np.any(np.diff(t) <= 0):
            raise ValueError("HeadingTrack: timestamps must strictly increase")
        object.__setattr__(self, "t_ns", t)
        object.__setattr__(self, "yaw", y)

    def __len__(self) -> int:
        return len(self.t_ns)


@dataclass(frozen=True, eq=False)
class MagneticTrack:
    """The phone's magnetic field per step (``/phone/magnetic``): ``enu[i]`` = (east, north, up) in µT at
    ``t_ns[i]``, the calibrated magnetometer rotated into the Earth frame with the phone's own orientation
    and averaged since the previous step. Indoors it varies from metre to metre (the building's steel):
    a sequence of it along a walk is a signature of the corridor walked. Per-walk device and calibration
    offsets of a few µT (10-30 µT on some phones) are the data's, not an error."""

    t_ns: NDArray[np.int64]
    enu: NDArray[np.float64]  # (N, 3) east, north, up (µT)

    def __post_init__(self) -> None:
        t = frozen_array(self.t_ns, np.int64)
        b = frozen_array(np.reshape(self.enu, (-1, 3)), np.float64)
        if not (t.ndim == 1 and len(t) == len(b)):
            raise ValueError("MagneticTrack: t_ns and enu must have the same length")
        if not np.isfinite(b).all():
            raise ValueError("MagneticTrack: non-finite field")
        if len(t) > 1 and np.any(np.diff(t) <= 0):
            raise ValueError("MagneticTrack: timestamps must strictly increase")
        object.__setattr__(self, "t_ns", t)
        object.__setattr__(self, "enu", b)

    def __len__(self) -> int:
        return len(self.t_ns)


@dataclass(frozen=True, eq=False)
class Session:
    """One walker's recording.

    ``steps``, ``scans``, ``heading``, ``magnetic`` and ``uwb_ranges`` are what the solver sees. ``landmarks``
    and ``ground_truth`` are kept apart: evaluation only (landmark ids a user names as control
    points are the one exception, ``graphslam.core.survey.control``).
    """

    session_id: str
    steps: PoseTrack
    scans: tuple[Scan, ...] = ()
    landmarks: tuple[LandmarkMark, ...] = ()
    ground_truth: PoseTrack | None = None
    site: str = ""
    floor: str = ""
    source: str = ""  # file it came from, for messages
    # UWB (optional, Paper 003): this tag's id, its rangings, and the anchors it knows
    # (anchor id -> (x, y) or (x, y, z), site frame, m)
    uwb_id: str = ""
    uwb_ranges: UwbRanges | None = None
    uwb_anchors: Mapping[str, tuple[float, ...]] = field(default_factory=dict)
    heading: HeadingTrack | None = None  # the phone's azimuth per step (optional ``/phone/heading``)
    magnetic: MagneticTrack | None = None  # the phone's magnetic field per step (optional ``/phone/magnetic``)

    def __post_init__(self) -> None:
        if not self.session_id:
            raise ValueError("Session: empty session_id")
        object.__setattr__(self, "scans", tuple(self.scans))
        object.__setattr__(self, "landmarks", tuple(self.landmarks))
        anchors = {str(k): tuple(float(c) for c in v) for k, v in dict(self.uwb_anchors).items()}
        if not all(len(v) in (2, 3) and np.isfinite(v).all() for v in anchors.values()):
            raise ValueError("Session: an anchor position must be 2 or 3 finite numbers")
        object.__setattr__(self, "uwb_anchors", MappingProxyType(anchors))

    @property
    def duration_s(self) -> float:
        ts = [self.steps.t_ns[0], self.steps.t_ns[-1]] if len(self.steps) else []
        ts += [s.t_ns for s in self.scans[:1]] + [s.t_ns for s in self.scans[-1:]]
        return (max(ts) - min(ts)) / 1e9 if ts else 0.0

    @property
    def access_points(self) -> frozenset[str]:
        return frozenset(b for s in self.scans for b in s.readings)


@dataclass(frozen=True, eq=False)
class Survey:
    """A set of sessions with unique ids (what one survey job reads)."""

    sessions: tuple[Session, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "sessions", tuple(self.sessions))
        ids = [s.session_id for s in self.sessions]
        if len(set(ids)) != len(ids):
            dup = sorted({i for i in ids if ids.count(i) > 1})
            raise ValueError(f"duplicate session ids: {dup}")

    def __iter__(self) -> Iterator[Session]:
        return iter(self.sessions)

    def __len__(self) -> int:
        return len(self.sessions)

    def __getitem__(self, session_id: str) -> Session:
        for s in self.sessions:
            if s.session_id == session_id:
                return s
        raise KeyError(session_id)

    @property
    def n_steps(self) -> int:
        return sum(len(s.steps) for s in self.sessions)

    @property
    def n_scans(self) -> int:
        return sum(len(s.scans) for s in self.sessions)

    @property
    def has_ground_truth(self) -> bool:
        return any(s.ground_truth is not None or s.landmarks for s in self.sessions)


def heading_to_quaternion(h: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation by ``h`` about +z."""
    return (0.0, 0.0, float(np.sin(h / 2.0)), float(np.cos(h / 2.0)))


def quaternion_to_heading(x: float, y: float, z: float, w: float) -> float:
    """Yaw of a unit quaternion (rotation about +z)."""
    return float(np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z)))


