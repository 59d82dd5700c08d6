"""``graphslam track``: the files around ``graphslam.core.tracking.tracker.Tracker`` (which tracks):
read the radio map, its AP models and the walks, keep the self-calibration in a cache folder
(``cache_dir``: ``$XDG_CACHE_HOME/graphslam``, else ``~/.cache/graphslam``; never the survey's
folder, which ``graphslam survey`` owns), write the tracks (CSV) and, beside them, the effective
configuration (``<out>.config.yaml``).

``prepare_track`` reads everything and says what the work will cost (``TrackJob.expected``: the
default fixed-lag tracker takes ~4 ms a step), ``TrackJob.run`` tracks; ``track_files`` is both.
"""

from __future__ import annotations

import csv
import dataclasses
import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable

from graphslam.core.tracking.apmodel import ApModels
from graphslam.core.tracking.tracker import SelfCalibration, SessionTrack, Tracker, calibration_config
from graphslam.errors import ConfigError, OutputError
from graphslam.io.atomic import atomic_open, atomic_write_text
from graphslam.tracking_config import DEFAULTS, TrackConfig

if TYPE_CHECKING:
    from graphslam.core.radiomap.radiomap import RadioMap
    from graphslam.core.tracking.walkable import WalkableArea
    from graphslam.core.types import Survey

log = logging.getLogger(__name__)


def config_path(out: str | Path) -> Path:
    """Where the effective configuration of a run writing ``out`` goes: ``track.csv`` -> ``track.config.yaml``."""
    return Path(out).with_suffix(".config.yaml")


TRACK_HEADER = (
    "session_id", "t_ns", "x", "y", "cov_xx", "cov_xy", "cov_yy", "vx", "vy", "theta", "theta_std", "hypothesis",
    "outside", "outside_score", "frame",
)


@dataclass(frozen=True, eq=False)
class TrackRun:
    tracks: tuple[SessionTrack, ...]
    out: Path | None
    n_aps_modelled: int
    config: Path | None = None  # the effective configuration written beside ``out``
    frame: str = ""  # the radio map's frame: the positions' (report.json's name)

    def as_dict(self) -> dict[str, object]:
        return {
            "out": None if self.out is None else str(self.out),
            "config": None if self.config is None else str(self.config),
            "frame": self.frame,
            "sessions": len(self.tracks),
            "steps": int(sum(len(t.t_ns) for t in self.tracks)),
            "aps_modelled": self.n_aps_modelled,
            "rssi_used": int(sum(t.n_rssi_used for t in self.tracks)),
            "rssi_gated": int(sum(t.n_rssi_gated for t in self.tracks)),
            # steps where the map's walks have not been (None: the map has no outside test)
            "outside_steps": None if any(t.outside is None for t in self.tracks) else int(sum(t.outside.sum() for t in self.tracks)),
        }


def write_track_csv(tracks: Iterable[SessionTrack], path: str | Path, frame: str = "") -> Path:
    """CSV (``TRACK_HEADER``), one row per step, written atomically. Units: m, m^2, m/s, rad.
    ``outside``: 1 at a step from a place the map's walks have not been (its covariance then at least
    the map's outside sigma squared), else 0; ``outside_score``: 0-1 (outside above 0.95); both
    empty when the map has no outside test (``core.tracking.tracker.with_outside``). ``frame``: the
    radio map's frame name, on every row."""
    path = Path(path)
    with atomic_open(path, "w", encoding="utf-8", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(TRACK_HEADER)
        for tr in tracks:
            n = len(tr.t_ns)
            out = tr.outside.astype(int).tolist() if tr.outside is not None else [""] * n
            score = [f"{v:.3f}" for v in tr.outside_score.tolist()] if tr.outside_score is not None else [""] * n
            for t, x, P, h, o, sc in zip(tr.t_ns.tolist(), tr.x, tr.P, tr.hypothesis.tolist(), out, score):
                w.writerow((
                    tr.session_id, t, f"{x[0]:.4f}", f"{x[1]:.4f}", f"{P[0, 0]:.5f}", f"{P[0, 1]:.5f}",
                    f"{P[1, 1]:.5f}", f"{x[2]:.4f}", f"{x[3]:.4f}", f"{math.remainder(x[6], 2 * math.pi):.5f}",
                    f"{math.sqrt(max(P[6, 6], 0.0)):.5f}", h, o, sc, frame,
                ))
    return path


# Seconds per tracked step on one core (default settings, measured 2026-12-04 on `paper`'s held-out
# walks, docs/tracking.md "Speed"): what ``TrackJob.expected`` says before the work. Rough by design.
SECONDS_PER_STEP = {"fixed-lag": 0.005, "ekf": 0.005, "ukf": 0.012, "particle": 0.01}
# the self-calibration's kNN passes over the map (leave-one-walk-out fixes, their correlation): ~N^2
SECONDS_PER_MAP_PAIR = 6e-7
# a run expected to take this long is announced (``TrackJob.notice``)
NOTICE_ABOVE_S = 30.0


@dataclass(frozen=True)
class TrackCost:
    """What a track run is expected to cost (s, one core): tracking the walks, and self-calibrating
    on the map first when no calibration is kept for it (0 when one is)."""

    steps: int
    walks: int
    filter: str
    tracking_s: float
    calibration_s: float

    @property
    def total_s(self) -> float:
        return self.tracking_s + self.calibration_s


def expected_cost(survey: "Survey", rm: "RadioMap", cfg: TrackConfig, calibrate: bool) -> TrackCost:
    """``TrackCost`` from ``SECONDS_PER_STEP``: the walks' steps, plus (``calibrate``) the replay of
    ``calibration.replay_sessions`` map segments as steps and the kNN passes over the map."""
    import numpy as np

    per_step = SECONDS_PER_STEP.get(cfg.filter.kind, SECONDS_PER_STEP["fixed-lag"])
    steps = sum(len(s.steps) for s in survey.sessions)
    cal = 0.0
    if calibrate:
        _, per_walk = np.unique(rm.session_ids, return_counts=True)
        per_walk = per_walk[per_walk >= 5]  # what the replay replays (none with fewer than two such walks)
        segment = min(cfg.calibration.replay_max_scans, float(np.mean(per_walk))) if len(per_walk) >= 2 else 0.0
        cal = cfg.calibration.replay_sessions * segment * per_step + SECONDS_PER_MAP_PAIR * len(rm) ** 2
    return TrackCost(steps, len(survey.sessions), cfg.filter.kind, steps * per_step, cal)


def _duration(seconds: float) -> str:
    return f"{seconds / 60:.0f} min" if seconds >= 90 else f"{seconds:.0f} s"


@dataclass(frozen=True, eq=False)
class TrackJob:
    """Everything read, nothing tracked yet (``prepare_track``): ``expected`` says what ``run`` costs."""

    radio_map: "RadioMap"
    models: ApModels
    survey: "Survey"
    cfg: TrackConfig
    expected: TrackCost
    out: Path | None = None
    cached: SelfCalibration | None = None  # the calibration kept for this map and configuration
    area: "WalkableArea | None" = None
    cache: Path | None = None  # where the calibration is kept (None: not kept)
    key: str | None = None

    def notice(self, above_s: float | None = None) -> str | None:
        """One line announcing a long run (None below ``above_s``, default ``NOTICE_ABOVE_S``), for a
        person waiting on it."""
        c = self.expected
        if c.total_s < (NOTICE_ABOVE_S if above_s is None else above_s):
            return None
        from graphslam.core.summary import plural

        text = (f"track: {plural(c.walks, 'walk')}, {plural(c.steps, 'step')} with the {c.filter} tracker: expect about "
                f"{_duration(c.tracking_s)}")
        if c.calibration_s:
            where = f", kept in {self.cache.parent} for the next run" if self.cache is not None else ""
            text += f", after about {_duration(c.calibration_s)} of self-calibration on this map{where}"
        if c.filter == "fixed-lag":
            text += f" (--filter ekf: about {_duration(c.steps * SECONDS_PER_STEP['ekf'])})"
        return text

    def run(self) -> TrackRun:
        tracker = Tracker.on_map(self.radio_map, self.models, self.cfg, calibration=self.cached, area=self.area)
        if self.cache is not None and self.cached is None and tracker.calibration is not None:
            _write_calibration(self.cache, self.key or "", tracker.calibration)
        tracks = tracker.track_all(self.survey.sessions)
        written = config = None
        if self.out is not None:
            written = write_track_csv(tracks, self.out, self.radio_map.frame)
            config = config_path(self.out)
            atomic_write_text(config, self.cfg.to_yaml())  # the effective configuration, beside the tracks
        return TrackRun(tracks, written, len(self.models.fitted), config, self.radio_map.frame)


def default_cache_dir() -> Path:
    """Where commands keep what they measured and may reuse: ``$XDG_CACHE_HOME/graphslam``, else
    ``~/.cache/graphslam``."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "graphslam"


def track_files(radio_map_path: str | Path, session_paths: Iterable[str | Path], **options: Any) -> TrackRun:
    """``prepare_track`` (same arguments) then ``TrackJob.run``: read, track, write ``out`` (CSV)."""
    return prepare_track(radio_map_path, session_paths, **options).run()


def prepare_track(
    radio_map_path: str | Path,
    session_paths: Iterable[str | Path],
    *,
    ap_models_path: str | Path | None = None,
    out: str | Path | None = None,
    cfg: TrackConfig = DEFAULTS,
    calibration_cache: bool = True,
    cache_dir: str | Path | None = None,
    floor_plan: str | Path | None = None,
    floor_size: tuple[float, float] | None = None,
) -> TrackJob:
    """Read the radio map, its AP models (``ap_models_path``, else ``ap_models.json`` beside the map,
    else fitted now), the sessions (MCAP). ``calibration_cache``: keep the self-calibration in
    ``cache_dir`` (``default_cache_dir()``), one file per (map, AP models, configuration, floor
    plan), and reuse it. ``floor_plan`` (image; ``floor_size`` W H in metres, else
    ``floor_info.json`` beside it): its walkable area constrains the positions
    (``TrackConfig.walkable_mode``); the radio map must be in the plan's site frame."""
    from graphslam.io.apmodel_io import StaleApModelsError, read_ap_models
    from graphslam.io.floor_plan import load_floor_plan, read_walkable_area
    from graphslam.io.mcap_reader import read_survey
    from graphslam.io.radiomap_io import read_radio_map

    plan = load_floor_plan(floor_plan, floor_size)  # bad input fails before any work
    rm = read_radio_map(radio_map_path)
    area = None
    if plan is not None:
        if rm.frame != "site":
            raise ConfigError(
                f"--floor-plan: the radio map {radio_map_path} is in the {rm.frame!r} frame; a floor plan's walkable "
                "area needs a map in the plan's site frame")
        area = read_walkable_area(plan, cfg.floor_plan.sigma_m)
    beside = Path(radio_map_path).with_name("ap_models.json")
    if ap_models_path is not None:
        models = read_ap_models(ap_models_path, radio_map=rm)  # another map's models: an error
    elif beside.exists():
        try:
            models = read_ap_models(beside, radio_map=rm)
        except StaleApModelsError as e:  # e.g. written by hand for an earlier map
            log.warning("%s; fitting them now", e)
            models = ApModels.fit(rm)
    else:
        log.info("no AP models beside %s: fitting them now", radio_map_path)
        models = ApModels.fit(rm)
    survey = read_survey(list(session_paths))
    cache = key = cached = None
    if cfg.calibration.enabled and calibration_cache:
        models_source = Path(ap_models_path) if ap_models_path is not None else beside if beside.exists() else None
        # the smoother left out: `--smooth` reuses its filter's kept calibration (core.tracking.tracker)
        key = _calibration_key(Path(radio_map_path), models_source, models, calibration_config(cfg),
                               plan.path if plan is not None else None)
        cache = calibration_path(cache_dir, key)
        cached = _read_calibration(cache, key)
    calibrate = cfg.calibration.enabled and cached is None
    return TrackJob(rm, models, survey, cfg, expected_cost(survey, rm, cfg, calibrate),
                    Path(out) if out is not None else None, cached, area, cache, key)


# Self-calibration kept in the cache folder: measuring it replays the map's walks (the longest
# step of a track run), the same for every call with the same map, AP models and configuration.
# One file per key (a content hash), so that several maps and configurations are kept at once.
CALIBRATION_FOLDER = "track-calibration"


def calibration_path(cache_dir: str | Path | None, key: str) -> Path:
    """The file the self-calibration of ``key`` is kept in: ``CACHE/track-calibration/<key>.json``."""
    return Path(cache_dir or default_cache_dir()) / CALIBRATION_FOLDER / f"{key}.json"


_CALIBRATION_FORMAT = 2  # 2: with the heading bank's temper


def _calibration_key(
    radio_map: Path, models_source: Path | None, models: ApModels, cfg: TrackConfig, floor_plan: Path | None = None
) -> str:
    """sha256 over what the calibration depends on: the map's bytes, the AP models' (or that they
    were fitted now, from the map), the floor plan's (its walkable area is replayed too), the tracking
    configuration and this graphslam's version."""
    import hashlib
    import json

    from graphslam import __version__

    h = hashlib.sha256()
    h.update(radio_map.read_bytes())
    h.update(models_source.read_bytes() if models_source is not None else f"fitted:{len(models.fitted)}".encode())
    if floor_plan is not None:
        h.update(b"plan:" + floor_plan.read_bytes())
    h.update(json.dumps(cfg.model_dump(mode="json"), sort_keys=True).encode())
    h.update(f"{__version__}/{_CALIBRATION_FORMAT}".encode())
    return h.hexdigest()


def _read_calibration(path: Path, key: str) -> SelfCalibration | None:
    """The calibration kept in ``path`` for ``key``; None (measure it again) when there is none, it
    is for another map or configuration, or the file is damaged (a cache: logged, never an error)."""
    import json

    if not path.is_file():
        return None
    try:
        d = json.loads(path.read_text())
        if d.get("format") != _CALIBRATION_FORMAT or d.get("key") != key:
            log.info("%s: for another map, AP models or configuration: measuring again", path)
            return None
        cal = SelfCalibration(*(float(d[k]) for k in ("rssi_variance_factor", "fix_sigma_floor_m", "covariance_scale",
                                                       "bank_temper")))
    except (OSError, ValueError, TypeError, KeyError, AttributeError) as e:
        log.warning("%s: unreadable (%s): measuring the self-calibration again", path, e)
        return None
    if not all(math.isfinite(v) and v > 0 for v in dataclasses.astuple(cal)) or min(cal.covariance_scale, cal.bank_temper) < 1:
        log.warning("%s: values out of range: measuring the self-calibration again", path)
        return None
    log.info("track: self-calibration from %s", path)
    return cal


def _write_calibration(path: Path, key: str, cal: SelfCalibration) -> None:
    from graphslam.io.atomic import atomic_write_json

    try:
        atomic_write_json(path, {"format": _CALIBRATION_FORMAT, "key": key, **dataclasses.asdict(cal)})
    except (OSError, OutputError) as e:  # a read-only cache folder: track anyway, measure again next time
        log.warning("%s: cannot keep the self-calibration (%s)", path, e)
