"""``graphslam track-uwb``: the paper's collaborative EKF (Paper 003, IV-C) over UWB recordings.

All sessions are filtered together, in time order, on their shared clock: a neighbour range
of session A to tag B uses B's estimate at that instant. Ranges less than ``slot_gap_s``
apart form one slot (trilateration when >= 3 anchors answered). With ``at_steps`` the filter
also reports (prediction only) at every step time of a session's foot module, so the output
has a row per step as ``graphslam track`` does, plus one per slot. Positions are in the site
frame of the anchors (m); covariances m^2.
"""

from __future__ import annotations

import csv
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from graphslam.core.types import Session
from graphslam.core.uwb.ekf import MEASUREMENT_TYPES, TagTrack, UwbEkfConfig, session_epochs, track_tags
from graphslam.errors import EstimationError
from graphslam.io.atomic import atomic_open

log = logging.getLogger(__name__)

UWB_TRACK_HEADER = ("session_id", "uwb_id", "t_ns", "x", "y", "cov_xx", "cov_xy", "cov_yy", "vx", "vy", "update")


@dataclass(frozen=True, eq=False)
class UwbTrackRun:
    tracks: dict[str, TagTrack]  # by tag id
    session_of: dict[str, str]  # tag id -> session id
    out: Path | None

    def as_dict(self) -> dict[str, object]:
        kinds = np.concatenate([t.kind for t in self.tracks.values()]) if self.tracks else np.zeros(0, int)
        return {
            "out": None if self.out is None else str(self.out),
            "sessions": len(self.tracks),
            "rows": int(sum(len(t.t_ns) for t in self.tracks.values())),
            "updates": {name: int((kinds == k).sum()) for k, name in enumerate(MEASUREMENT_TYPES)},
            "rejected": int(sum(t.rejected for t in self.tracks.values())),
            "restarts": int(sum(t.restarts for t in self.tracks.values())),
            "not_started": sorted(self.session_of[t] for t, tr in self.tracks.items() if not len(tr.t_ns)),
        }


def track_uwb_sessions(
    sessions: Sequence[Session], cfg: UwbEkfConfig = UwbEkfConfig(), *, slot_gap_s: float = 0.02, at_steps: bool = True
) -> UwbTrackRun:
    """Filter every session (see module docstring). ``EstimationError`` without anchors or ranges."""
    anchors: dict[str, tuple[float, ...]] = {}
    for s in sessions:
        anchors.update(s.uwb_anchors)
    if not any(s.uwb_ranges is not None and len(s.uwb_ranges) for s in sessions):
        raise EstimationError("track-uwb: no /uwb/range message in these recordings")
    if not anchors:
        raise EstimationError("track-uwb: no anchor positions (graphslam.uwb_anchors) in these recordings")
    extra = {(s.uwb_id or s.session_id): s.steps.t_ns for s in sessions if at_steps and len(s.steps) > 1}
    epochs = session_epochs(sessions, slot_gap_s=slot_gap_s, extra_times=extra)
    tracks = track_tags(epochs, anchors, cfg)
    session_of = {(s.uwb_id or s.session_id): s.session_id for s in sessions}
    started = [t for t, tr in tracks.items() if len(tr.t_ns)]
    if not started:
        raise EstimationError(
            "track-uwb: no session ever ranged to 3 anchors at once: the filter starts a tag at its first "
            "trilateration (anchors placed along corridors for a survey, as simulate-uwb crowd's, are for "
            "`graphslam survey`; simulate-uwb zones has rooms with 3 and 4 anchors; docs/uwb.md)")
    for t, tr in tracks.items():
        if not len(tr.t_ns):
            log.warning("track-uwb: %s never ranged to 3 anchors at once: no estimate", session_of.get(t, t))
    return UwbTrackRun(tracks, session_of, None)


def write_uwb_track_csv(run: UwbTrackRun, path: str | Path) -> Path:
    """CSV (``UWB_TRACK_HEADER``), one row per processed slot or step, written atomically."""
    path = Path(path)
    with atomic_open(path, "w", encoding="utf-8", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(UWB_TRACK_HEADER)
        for tag, tr in sorted(run.tracks.items(), key=lambda kv: run.session_of.get(kv[0], kv[0])):
            sid = run.session_of.get(tag, tag)
            for t, x, P, k in zip(tr.t_ns.tolist(), tr.x, tr.P, tr.kind.tolist()):
                w.writerow((
                    sid, tag, t, f"{x[0]:.4f}", f"{x[1]:.4f}", f"{P[0, 0]:.6f}", f"{P[0, 1]:.6f}", f"{P[1, 1]:.6f}",
                    f"{x[2]:.4f}", f"{x[3]:.4f}", MEASUREMENT_TYPES[k],
                ))
    return path


def track_uwb_files(
    session_paths: Iterable[str | Path], *, out: str | Path | None = None, cfg: UwbEkfConfig = UwbEkfConfig(),
    slot_gap_s: float = 0.02, at_steps: bool = True,
) -> UwbTrackRun:
    """Read the recordings (MCAP), filter them together, write ``out`` (CSV)."""
    from graphslam.io.mcap_reader import read_survey

    survey = read_survey(list(session_paths))
    run = track_uwb_sessions(survey.sessions, cfg, slot_gap_s=slot_gap_s, at_steps=at_steps)
    if out is not None:
        run = UwbTrackRun(run.tracks, run.session_of, write_uwb_track_csv(run, out))
    return run
