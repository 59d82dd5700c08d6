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

from graphslam.core.types import Session, Survey
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
    errors: dict[str, object] | None = None  # against the recordings' truth and marks (site frame); None: neither
    picture: Path | None = None

    def as_dict(self) -> dict[str, object]:
        kinds = np.concatenate([t.kind for t in self.tracks.values()]) if self.tracks else np.zeros(0, int)
        extra: dict[str, object] = {} if self.errors is None else {"errors": self.errors}
        if self.picture is not None:
            extra["picture"] = str(self.picture)
        return {
            "out": None if self.out is None else str(self.out),
            "frame": "site",
            "sessions": len(self.tracks),
            "rows": int(sum(len(t.t_ns) for t in self.tracks.values())),
            "updates": {name: int((kinds == k).sum()) for k, name in enumerate(MEASUREMENT_TYPES)},
            "rejected": int(sum(t.rejected for t in self.tracks.values())),
            "restarts": int(sum(t.restarts for t in self.tracks.values())),
            "not_started": sorted(self.session_of[t] for t, tr in self.tracks.items() if not len(tr.t_ns)),
        } | extra

    def answers(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """session id -> (t_ns, (N, 2) positions in the anchors' site frame) of every tag that started."""
        return {self.session_of.get(tag, tag): (tr.t_ns, np.asarray(tr.x)[:, :2])
                for tag, tr in self.tracks.items() if len(tr.t_ns)}


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
    slot_gap_s: float = 0.02, at_steps: bool = True, picture: bool = True,
) -> UwbTrackRun:
    """Read the recordings (MCAP), filter them together, write ``out`` (CSV) and, with ``picture``,
    ``out`` with ``.png`` (the tracks, the truth when the recordings carry it, the anchors). When the
    recordings carry ground truth or landmark marks, ``errors`` scores the tracks against them (the
    anchors' site frame is the truth's: no fit)."""
    from dataclasses import replace

    from graphslam.app.scoring import errors_in_site_frame
    from graphslam.io.mcap_reader import read_survey

    survey = read_survey(list(session_paths))
    run = track_uwb_sessions(survey.sessions, cfg, slot_gap_s=slot_gap_s, at_steps=at_steps)
    errors = errors_in_site_frame(run.answers(), survey, np.zeros(3), "site",
                                  "identity: the tracks are in the anchors' site frame")
    run = replace(run, errors=errors)
    if out is not None:
        run = replace(run, out=write_uwb_track_csv(run, out))
        if picture:
            run = replace(run, picture=write_uwb_track_picture(run, survey, Path(out).with_suffix(".png")))
    return run


def write_uwb_track_picture(run: UwbTrackRun, survey: "Survey", path: str | Path) -> Path:
    """The tags' tracks, the truth where the recordings carry it, and the anchors, as PNG ``path``
    (all in the anchors' site frame)."""
    from graphslam.core.common.geometry import interpolate_xy
    from graphslam.core.summary import plural
    from graphslam.viz.track_picture import draw_tracks

    answers = run.answers()
    truth, at = {}, {}
    for s in survey:
        if s.ground_truth is not None and s.session_id in answers:
            truth[s.session_id] = np.asarray(s.ground_truth.xy)
            at[s.session_id] = interpolate_xy(s.ground_truth, answers[s.session_id][0].astype(float))
    anchors: dict[str, tuple[float, float]] = {}
    for s in survey:
        for a, p in s.uwb_anchors.items():
            anchors.setdefault(a, (float(p[0]), float(p[1])))
    rows = sum(len(t) for t, _ in answers.values())
    note = "site frame of the anchors (metres)" + ("; truth as recorded (the same frame)" if truth else
                                                   "; the recordings carry no ground truth")
    return draw_tracks({sid: xy for sid, (_, xy) in answers.items()}, path, truth=truth or None,
                       truth_at_estimates=at or None, title=f"track-uwb (collaborative EKF): "
                       f"{plural(len(answers), 'session')}, {plural(rows, 'row')}", frame=note, frame_name="site",
                       anchors=anchors)
