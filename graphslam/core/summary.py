"""Per-session statistics for ``graphslam inspect``; the counts of a survey's walks as every
output states them (``main_map_counts``)."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Mapping

from graphslam.core.types import Session, Survey


@dataclass(frozen=True)
class SessionSummary:
    session_id: str
    site: str
    floor: str
    steps: int
    scans: int
    access_points: int
    duration_s: float
    walked_m: float
    landmarks: int
    has_ground_truth: bool

    @classmethod
    def of(cls, s: Session) -> "SessionSummary":
        return cls(
            session_id=s.session_id,
            site=s.site,
            floor=s.floor,
            steps=len(s.steps),
            scans=len(s.scans),
            access_points=len(s.access_points),
            duration_s=round(s.duration_s, 3),
            walked_m=round(s.steps.path_length, 3),
            landmarks=len(s.landmarks),
            has_ground_truth=s.ground_truth is not None,
        )

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class SurveySummary:
    sessions: tuple[SessionSummary, ...]
    access_points: int  # distinct over the whole survey

    @classmethod
    def of(cls, survey: Survey) -> "SurveySummary":
        aps: set[str] = set()
        for s in survey:
            aps |= s.access_points
        return cls(tuple(SessionSummary.of(s) for s in survey), len(aps))

    @property
    def totals(self) -> dict:
        ss = self.sessions
        return {
            "sessions": len(ss),
            "steps": sum(s.steps for s in ss),
            "scans": sum(s.scans for s in ss),
            "access_points": self.access_points,
            "duration_s": round(sum(s.duration_s for s in ss), 3),
            "walked_m": round(sum(s.walked_m for s in ss), 3),
            "landmarks": sum(s.landmarks for s in ss),
        }


def plural(n: int, noun: str, many: str | None = None) -> str:
    """``1 session``, ``2 sessions``, ``1,204 steps`` (``many``: an irregular plural)."""
    return f"{n:,} {noun if n == 1 else many or noun + 's'}"


def main_map_counts(walks: int, main: int, other_walks: int, other_components: int, unaligned: int) -> str:
    """The walks of a survey, the main map first: ``main map: 8 of 40 walks; 32 in 12 other
    components; 0 unaligned`` (what ``survey`` prints first, survey.png's title, ``survey-batch`` and
    ``bench real`` say)."""
    return (f"main map: {main:,} of {plural(walks, 'walk')}; {other_walks:,} in {other_components:,} other "
            f"component{'' if other_components == 1 else 's'}; {unaligned:,} unaligned")


def report_main_map_counts(report: Mapping[str, Any]) -> str:
    """``main_map_counts`` of a survey's report.json (``components``, ``sessions``, ``unaligned``)."""
    comps = report.get("components") or []
    n_main = int(comps[0]["n_walks"]) if comps else 0
    return main_map_counts(int(report.get("sessions") or 0), n_main, sum(int(c["n_walks"]) for c in comps[1:]),
                           max(0, len(comps) - 1), len(report.get("unaligned") or []))
