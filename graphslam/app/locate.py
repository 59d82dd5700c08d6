"""``graphslam locate``: answer every WiFi scan of query recordings against a radio map."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator, Sequence

import numpy as np
from numpy.typing import NDArray

from graphslam.core.progress import Task
from graphslam.core.radiomap.knn import KnnConfig, KnnLocator, SurveyPositions, locate_survey
from graphslam.core.radiomap.uncertainty import KnnUncertainty, map_uncertainty
from graphslam.io.atomic import atomic_open
from graphslam.names import DEFAULT_INDEX, DEFAULT_K, DEFAULT_METRIC

log = logging.getLogger(__name__)

POSITIONS_HEADER = (
    "session_id", "t_ns", "x", "y", "score", "spread", "sigma_m", "outside", "outside_score", "n_neighbours",
    "n_known_aps", "floor", "building", "status", "frame",
)


@dataclass(frozen=True)
class LocateRun:
    """What ``locate_files`` did: counts and the positions (also written to ``out``)."""

    positions: SurveyPositions
    out: Path | None
    n_sessions: int
    n_scans: int
    n_located: int
    radio_map_frame: str = ""  # the frame of the answers
    uncertainty: KnnUncertainty | None = None  # of the answers' sigma_m (None: a map of one walk)

    def as_dict(self) -> dict[str, object]:
        u = self.uncertainty
        flags = u.outside_of(self.positions.result) if u is not None else None
        return {
            "out": None if self.out is None else str(self.out),
            "frame": self.radio_map_frame,
            "sessions": self.n_sessions,
            "scans": self.n_scans,
            "located": self.n_located,
            "unlocated": self.n_scans - self.n_located,
            "outside": None if flags is None else int(flags.sum()),  # located, but where the map's walks have not been
            "uncertainty": None if u is None else {
                "scale": round(u.scale, 4), "floor_m": u.floor_m,
                "map_coverage_95": round(u.coverage, 4), "measured_on": u.n,
                "outside": None if u.outside is None else {
                    "above_db": round(u.outside.threshold_db, 3), "sigma_m": round(u.outside.sigma_m, 3),
                    "map_detection": round(u.outside.detection, 4),
                },
            },
        }


def _fmt(v: float, digits: int) -> str:
    return "" if not math.isfinite(v) else f"{v:.{digits}f}"


def position_rows(
    p: SurveyPositions, uncertainty: KnnUncertainty | None = None, frame: str = ""
) -> Iterator[tuple[object, ...]]:
    r = p.result
    floor = r.floor.tolist() if r.floor is not None else [""] * len(p)
    building = r.building.tolist() if r.building is not None else [""] * len(p)
    sigma = uncertainty.sigma_of(r).tolist() if uncertainty is not None else [math.nan] * len(p)
    flags = uncertainty.outside_of(r) if uncertainty is not None else None
    scores = uncertainty.outside_score_of(r) if uncertainty is not None else None
    # outside: 1 / 0, empty for an unlocated scan or without an outside test
    outside = [("" if not ok else int(f)) for f, ok in zip(flags.tolist(), r.valid.tolist())] if flags is not None else [""] * len(p)
    score = scores.tolist() if scores is not None else [math.nan] * len(p)
    for sid, t, (x, y), s, sp, sg, o, os_, nn, nk, f, b, st in zip(
        p.session_ids.tolist(), p.t_ns.tolist(), r.xy.tolist(), r.score.tolist(), r.spread.tolist(), sigma, outside,
        score, r.n_neighbours.tolist(), r.n_known_aps.tolist(), floor, building, r.status.tolist(),
    ):
        yield (sid, t, _fmt(x, 4), _fmt(y, 4), _fmt(s, 4), _fmt(sp, 4), _fmt(sg, 3), o, _fmt(os_, 3), nn, nk, f, b, st, frame)


def write_positions_csv(
    p: SurveyPositions, path: str | Path, uncertainty: KnnUncertainty | None = None, frame: str = ""
) -> Path:
    """CSV ``POSITIONS_HEADER``, written atomically. ``sigma_m``: the answer's calibrated uncertainty
    (``uncertainty``; the 95 % circle has radius 2.448 sigma_m), empty without one; ``outside``: 1 when
    the scan comes from a place the map's walks have not been (``OutsideTest``), else 0;
    ``outside_score``: 0-1, the share of the map's own covered scans that matched closer (outside:
    above 0.95); both empty without the test. Unlocated scans keep their row with empty
    x/y/score/spread/sigma_m/outside/outside_score. ``frame``: the radio map's frame name (the
    answers'), on every row."""
    import csv

    path = Path(path)
    with atomic_open(path, "w", encoding="utf-8", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(POSITIONS_HEADER)
        w.writerows(position_rows(p, uncertainty, frame))
    return path


def locate_files(
    radio_map_path: str | Path,
    query_paths: Iterable[str | Path],
    *,
    out: str | Path | None = None,
    k: int = DEFAULT_K,
    weighted: bool = True,
    min_common: int = 1,
    index: str = DEFAULT_INDEX,
    metric: str = DEFAULT_METRIC,
) -> LocateRun:
    """Read the radio map and the query sessions (MCAP), locate every scan, write ``out`` (CSV).
    ``index``: kNN search (``KnnConfig.index``); ``metric``: ``KnnConfig.metric`` (defaults: ``graphslam.names``)."""
    from graphslam.io.mcap_reader import read_survey
    from graphslam.io.radiomap_io import read_radio_map

    rm = read_radio_map(radio_map_path)
    survey = read_survey(list(query_paths))
    config = KnnConfig(k=k, weighted=weighted, min_common=min_common, index=index, metric=metric)  # type: ignore[arg-type]
    locator = KnnLocator(rm, config)
    locator.uncertainty = map_uncertainty(rm, config)
    with Task("locate", total=survey.n_scans, unit="scans") as task:
        positions = locate_survey(locator, survey)
        task.advance(len(positions))
    written = write_positions_csv(positions, out, locator.uncertainty, rm.frame) if out is not None else None
    n_ok = int(positions.result.valid.sum())
    log.info("located %d of %d scans from %d sessions", n_ok, len(positions), len(survey))
    return LocateRun(positions, written, len(survey), len(positions), n_ok, rm.frame, locator.uncertainty)


def answers_by_session(p: SurveyPositions) -> dict[str, tuple[NDArray[np.int64], NDArray[np.float64]]]:
    """session id -> (scan times, answers (N, 2) in the map's frame; NaN where unlocated)."""
    return {sid: (p.t_ns[p.session_ids == sid], p.result.xy[p.session_ids == sid]) for sid in dict.fromkeys(p.session_ids.tolist())}


__all__: Sequence[str] = ("LocateRun", "locate_files", "write_positions_csv", "POSITIONS_HEADER")


def query_truth(query_paths: Iterable[str | Path], positions: SurveyPositions) -> "NDArray[np.float64] | None":
    """True position (site frame) of every located scan from the queries' ``/ground_truth/pose``,
    interpolated at scan time; None when the queries carry no ground truth. Display/evaluation only."""
    from graphslam.core.common.geometry import interpolate_xy
    from graphslam.io.mcap_reader import read_survey

    survey = read_survey(query_paths)
    if not any(s.ground_truth is not None for s in survey):
        return None
    out = np.full((len(positions), 2), np.nan)
    for s in survey:
        rows = np.flatnonzero(positions.session_ids == s.session_id)
        if len(rows) and s.ground_truth is not None:
            out[rows] = interpolate_xy(s.ground_truth, positions.t_ns[rows].astype(float))
    return out
