"""Statistics of simulated sessions: raw dead-reckoning drift, lengths, durations."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

import numpy as np
from numpy.typing import NDArray

from graphslam.core.types import Session
from graphslam.errors import SimulationError


def align_by_start(session: Session) -> NDArray[np.float64]:
    """(N, 2) DR positions moved into the site frame by the *true* start pose.

    This is the best a solver could do with perfect knowledge of the start only;
    what is left is the module's drift.
    """
    gt = session.ground_truth
    if gt is None:
        raise SimulationError(f"{session.session_id}: no ground truth to align with")
    h0 = float(gt.heading[0])
    c, s = np.cos(h0), np.sin(h0)
    rot = np.array([[c, -s], [s, c]])
    return gt.xy[0] + session.steps.xy @ rot.T


def raw_drift(session: Session) -> NDArray[np.float64]:
    """(N,) position error (m) of the DR track aligned by the true start pose, per step."""
    gt = session.ground_truth
    if gt is None:
        raise SimulationError(f"{session.session_id}: no ground truth to measure drift")
    return np.linalg.norm(align_by_start(session) - gt.xy, axis=1)


@dataclass(frozen=True)
class WalkStats:
    session_id: str
    steps: int
    scans: int
    marks: int
    duration_s: float
    length_m: float  # true walked length
    max_drift_m: float
    final_drift_m: float
    mean_readings_per_scan: float
    walked_m: float = 0.0  # the recorded (dead-reckoned) steps' length: what `inspect` reads back

    @classmethod
    def of(cls, s: Session) -> "WalkStats":
        gt = s.ground_truth
        drift = raw_drift(s)
        return cls(
            session_id=s.session_id,
            steps=len(s.steps),
            scans=len(s.scans),
            marks=len(s.landmarks),
            duration_s=s.duration_s,
            length_m=gt.path_length if gt is not None else s.steps.path_length,
            max_drift_m=float(drift.max()),
            final_drift_m=float(drift[-1]),
            mean_readings_per_scan=float(np.mean([len(x) for x in s.scans])) if s.scans else 0.0,
            walked_m=s.steps.path_length,
        )


@dataclass(frozen=True)
class SurveyStats:
    walks: tuple[WalkStats, ...]
    access_points_heard: int

    @classmethod
    def of(cls, sessions: Iterable[Session]) -> "SurveyStats":
        sessions = list(sessions)
        aps: set[str] = set()
        for s in sessions:
            aps |= s.access_points
        return cls(tuple(WalkStats.of(s) for s in sessions), len(aps))

    @property
    def steps(self) -> int:
        return sum(w.steps for w in self.walks)

    @property
    def scans(self) -> int:
        return sum(w.scans for w in self.walks)

    @property
    def marks(self) -> int:
        return sum(w.marks for w in self.walks)

    @property
    def length_m(self) -> float:
        return sum(w.length_m for w in self.walks)

    @property
    def walked_m(self) -> float:
        return sum(w.walked_m for w in self.walks)

    @property
    def duration_s(self) -> float:
        return sum(w.duration_s for w in self.walks)

    @property
    def max_drift_m(self) -> float:
        return max((w.max_drift_m for w in self.walks), default=0.0)
