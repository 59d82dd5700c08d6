"""``graphslam track``: the files around ``graphslam.core.tracking.tracker.Tracker`` (which tracks):
read the radio map, its AP models and the walks, keep the self-calibration beside the map, write
the tracks (CSV) and, beside them, the effective configuration (``<out>.config.yaml``).
"""

from __future__ import annotations

import csv
import dataclasses
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

from graphslam.core.progress import Task
from graphslam.core.tracking.apmodel import ApModels
from graphslam.core.tracking.tracker import SelfCalibration, SessionTrack, Tracker
from graphslam.errors import ConfigError
from graphslam.io.atomic import atomic_open, atomic_write_text
from graphslam.tracking_config import DEFAULTS, TrackConfig

log = logging.getLogger(__name__)


def config_path(out: str | Path) -> Path:
    """Where the effective configuration of a run writing ``out`` goes: ``track.csv`` -> ``track.config.yaml``."""
    return Path(out).with_suffix(".config.yaml")


TRACK_HEADER = (
    "session_id", "t_ns", "x", "y", "cov_xx", "cov_xy", "cov_yy", "vx", "vy", "theta", "theta_std", "hypothesis",
)


@dataclass(frozen=True, eq=False)
class TrackRun:
    tracks: tuple[SessionTrack, ...]
    out: Path | None
    n_aps_modelled: int
    config: Path | None = None  # the effective configuration written beside ``out``

    def as_dict(self) -> dict[str, object]:
        return {
            "out": None if self.out is None else str(self.out),
            "config": None if self.config is None else str(self.config),
            "sessions": len(self.tracks),
            "steps": int(sum(len(t.t_ns) for t in self.tracks)),
            "aps_modelled": self.n_aps_modelled,
            "rssi_used": int(sum(t.n_rssi_used for t in self.tracks)),
            "rssi_gated": int(sum(t.n_rssi_gated for t in self.tracks)),
        }


def write_track_csv(tracks: Iterable[SessionTrack], path: str | Path) -> Path:
    """CSV (``TRACK_HEADER``), one row per step, written atomically. Units: m, m^2, m/s, rad."""
    path = Path(path)
    with atomic_open(path, "w", encoding="utf-8", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(TRACK_HEADER)
        for tr in tracks:
            for t, x, P, h in zip(tr.t_ns.tolist(), tr.x, tr.P, tr.hypothesis.tolist()):
                w.writerow((
                    tr.session_id, t, f"{x[0]:.4f}", f"{x[1]:.4f}", f"{P[0, 0]:.5f}", f"{P[0, 1]:.5f}",
                    f"{P[1, 1]:.5f}", f"{x[2]:.4f}", f"{x[3]:.4f}", f"{math.remainder(x[6], 2 * math.pi):.5f}",
                    f"{math.sqrt(max(P[6, 6], 0.0)):.5f}", h,
                ))
    return path


def track_files(
    radio_map_path: str | Path,
    session_paths: Iterable[str | Path],
    *,
    ap_models_path: str | Path | None = None,
    out: str | Path | None = None,
    cfg: TrackConfig = DEFAULTS,
    calibration_cache: bool = True,
    floor_plan: str | Path | None = None,
    floor_size: tuple[float, float] | None = None,
) -> TrackRun:
    """Read the radio map, its AP models (``ap_models_path``, else ``ap_models.json`` beside the map,
    else fitted now), the sessions (MCAP); track; write ``out`` (CSV). ``calibration_cache``: keep
    the self-calibration in ``track_calibration.json`` beside the map and reuse it while the map,
    AP models and configuration are the same. ``floor_plan`` (image; ``floor_size`` W H in metres,
    else ``floor_info.json`` beside it): its walkable area constrains the positions
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
        except StaleApModelsError as e:  # e.g. left by an earlier survey into the same folder
            log.warning("%s; fitting them now", e)
            models = ApModels.fit(rm)
    else:
        log.info("no AP models beside %s: fitting them now", radio_map_path)
        models = ApModels.fit(rm)
    survey = read_survey(list(session_paths))
    cache = key = cached = None
    if cfg.calibration.enabled and calibration_cache:
        cache = Path(radio_map_path).with_name(CALIBRATION_FILE)
        models_source = Path(ap_models_path) if ap_models_path is not None else beside if beside.exists() else None
        key = _calibration_key(Path(radio_map_path), models_source, models, cfg, plan.path if plan is not None else None)
        cached = _read_calibration(cache, key)
    tracker = Tracker.on_map(rm, models, cfg, calibration=cached, area=area)
    if cache is not None and cached is None and tracker.calibration is not None:
        _write_calibration(cache, key, tracker.calibration)
    with Task("track", total=sum(len(s.steps) for s in survey.sessions), unit="steps") as task:
        tracks = tuple(tracker.track(s, task) for s in survey.sessions)
    written = config = None
    if out is not None:
        written = write_track_csv(tracks, out)
        config = config_path(out)
        atomic_write_text(config, cfg.to_yaml())  # the effective configuration, beside the tracks
    return TrackRun(tracks, written, len(models.fitted), config)


# Self-calibration kept beside the radio map: measuring it replays the map's walks (the longest
# step of a track run), the same for every call with the same map, AP models and configuration.
CALIBRATION_FILE = "track_calibration.json"


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
    from graphslam.errors import OutputError
    from graphslam.io.atomic import atomic_write_json

    try:
        atomic_write_json(path, {"format": _CALIBRATION_FORMAT, "key": key, **dataclasses.asdict(cal)})
    except (OSError, OutputError) as e:  # a read-only or full map folder: track anyway, measure again next time
        log.warning("%s: cannot keep the self-calibration (%s)", path, e)
