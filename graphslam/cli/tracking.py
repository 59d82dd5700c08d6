"""Tracking command: track walks on a radio map.

Configured as the survey is: ``--config FILE`` (configs/track.yaml mirrors every key) and ``--set
section.key=value``; the options below are shortcuts for the most used keys (each names its key).
Defaults live in ``graphslam.tracking_config`` only: an option not given leaves its key as the
file (or the default) has it.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, List, Optional

import typer

from graphslam import names
from graphslam.cli.base import app
from graphslam.cli.options import METRIC_HELP, Metric, choices, plain

Tracker = choices("Tracker", names.TRACKERS)
Smoother = choices("Smoother", names.SMOOTHERS)
BankReport = choices("BankReport", names.BANK_REPORTS)
WalkableMode = choices("WalkableMode", names.WALKABLE_MODES)

# option -> configuration key it sets (shortcuts of --set KEY=VALUE)
SHORTCUTS = {
    "--filter": "filter.kind", "--smooth": "filter.smoother", "--lag": "fixed_lag.lag_s",
    "--bank-report": "fixed_lag.bank_report", "--bank-temper": "fixed_lag.bank_temper",
    "--knn-fixes": "knn_fixes.enabled", "--metric": "knn_fixes.metric", "--adaptive-rssi": "rssi.adaptive",
    "--rssi-field": "rssi.field_m", "--self-calibrate": "calibration.enabled", "--walk-axes": "walk_axes.enabled",
    "--floor-plan-use": "floor_plan.mode", "--walkable-sigma": "floor_plan.sigma_m",
}


def _key(option: str) -> str:
    return f"(config {SHORTCUTS[option]})."


@app.command()
def track(
    sessions: List[Path] = typer.Argument(..., help="Session recordings (.mcap) or folders of them."),
    radio_map: Path = typer.Option(..., "--radio-map", help="Radio map (.parquet); positions come out in its frame."),
    out: Path = typer.Option(..., "--out", "-o", help="Output CSV: one row per step (t_ns, x, y, covariance, ...); the "
                             "effective configuration is written beside it (OUT with .config.yaml)."),
    config: Optional[Path] = typer.Option(None, "--config", "-c", help="YAML tracking config (`graphslam config show --track` prints the defaults)."),
    set_: Optional[List[str]] = typer.Option(None, "--set", help="Override a config value, e.g. fixed_lag.lag_s=1."),
    filter_: Optional[Tracker] = typer.Option(
        None, "--filter", help="fixed-lag (online, reports each step --lag s late), the causal ekf / ukf, or particle "
        "(map-matching particle filter, --lag s late; docs/tracking.md) " + _key("--filter"),
    ),
    lag: Optional[float] = typer.Option(
        None, "--lag", min=0.0, help="fixed-lag / particle: latency in s (a step is reported once the data up to lag s "
        "later are in) " + _key("--lag"),
    ),
    bank_report: Optional[BankReport] = typer.Option(
        None, "--bank-report", help="fixed-lag: mixture (the heading hypotheses' posterior mixture) or best (the most "
        "probable one only) " + _key("--bank-report"),
    ),
    bank_temper: Optional[float] = typer.Option(
        None, "--bank-temper", help="fixed-lag: divide the heading hypotheses' costs by this (>= 1) before weighing "
        "them; unset: measured on the map by self-calibration " + _key("--bank-temper"),
    ),
    ap_models: Optional[Path] = typer.Option(
        None, "--ap-models", help="AP models JSON (default: ap_models.json beside the map, else fitted now)."
    ),
    smooth: Optional[Smoother] = typer.Option(
        None, "--smooth", help="Offline, whole session: none (the online tracker), rts, or map (whole-run MAP) "
        + _key("--smooth"),
    ),
    knn_fixes: Optional[bool] = typer.Option(
        None, "--knn-fixes/--no-knn-fixes", help="Fuse each scan's kNN fix on the radio map (--no-knn-fixes: the "
        "papers' RSSI-only model) " + _key("--knn-fixes"),
    ),
    adaptive_rssi: Optional[bool] = typer.Option(
        None, "--adaptive-rssi/--no-adaptive-rssi", help="Inflate a scan's RSSI noise when its innovations disagree "
        + _key("--adaptive-rssi"),
    ),
    self_calibrate: Optional[bool] = typer.Option(
        None, "--self-calibrate/--no-self-calibrate", help="Measure the kNN fix noise, RSSI variance and covariance "
        "scale on the radio map itself (docs/tracking.md) " + _key("--self-calibrate"),
    ),
    calibration_cache: bool = typer.Option(
        True, "--calibration-cache/--no-calibration-cache",
        help="Keep the self-calibration in the cache folder (--cache-dir) and reuse it for the same map, AP models and "
        "options (the survey's folder is never written).",
    ),
    cache_dir: Optional[Path] = typer.Option(
        None, "--cache-dir", help="Cache folder (default: $XDG_CACHE_HOME/graphslam, else ~/.cache/graphslam).",
    ),
    metric: Optional[Metric] = typer.Option(
        None, "--metric", help=METRIC_HELP.replace("Fingerprint distance", "Fingerprint distance of the kNN fixes (and "
                                                   "the particle filter's scan matches)") + " " + _key("--metric"),
    ),
    walk_axes: Optional[bool] = typer.Option(
        None, "--walk-axes/--no-walk-axes", help="fixed-lag / --smooth map: walkers keep to the two perpendicular "
        "directions the map's own walks keep to (docs/tracking.md) " + _key("--walk-axes"),
    ),
    rssi_field: Optional[float] = typer.Option(
        None, "--rssi-field", help="Kernel std (m) of each AP's residual field measured on the map; 0: the "
        "log-distance law alone (docs/tracking.md) " + _key("--rssi-field"),
    ),
    floor_plan: Optional[Path] = typer.Option(
        None, "--floor-plan", help="A floor plan image (site frame, as the radio map): its blank area inside the outline "
        "is walkable; positions off it are moved to it (docs/tracking.md).",
    ),
    floor_size: Optional[tuple[float, float]] = typer.Option(
        None, "--floor-size", help="W H of the floor plan (m); default: floor_info.json beside the image."
    ),
    floor_plan_use: Optional[WalkableMode] = typer.Option(
        None, "--floor-plan-use", help="snap (each position off the walkable area to its nearest cell), prior (a row "
        "per step in the fixed-lag / --smooth map problem, std --walkable-sigma) or both " + _key("--floor-plan-use"),
    ),
    walkable_sigma: Optional[float] = typer.Option(
        None, "--walkable-sigma", help="--floor-plan-use prior / both: std (m) of a step's distance to the walkable "
        "area " + _key("--walkable-sigma"),
    ),
    picture: bool = typer.Option(True, "--picture/--no-picture", help="Also write OUT with .png: the tracks (and truth)."),
) -> None:
    """Track walks on a radio map: fusion of step velocity, WiFi RSSI and kNN fixes (fixed-lag MAP, or EKF/UKF).
    The default fixed-lag tracker takes ~4 ms a step (the EKF ~5 ms), plus a self-calibration
    on a map the first time (~5 s on a small map, kept in --cache-dir): a long run is announced before it starts."""
    from graphslam.app.progress import progress_shown
    from graphslam.app.track import prepare_track
    from graphslam.core.radiomap.ivf import limit_blas_threads

    limit_blas_threads(1)  # thousands of tiny solves: OpenBLAS threads only slow them down
    given = {
        "--filter": filter_, "--smooth": smooth, "--lag": lag, "--bank-report": bank_report, "--bank-temper": bank_temper,
        "--knn-fixes": knn_fixes, "--metric": metric, "--adaptive-rssi": adaptive_rssi, "--rssi-field": rssi_field,
        "--self-calibrate": self_calibrate, "--walk-axes": walk_axes, "--floor-plan-use": floor_plan_use,
        "--walkable-sigma": walkable_sigma,
    }
    cfg = track_config_from_options(config, set_, {k: plain(v) for k, v in given.items() if v is not None})
    job = prepare_track(radio_map, sessions, ap_models_path=ap_models, out=out, cfg=cfg, calibration_cache=calibration_cache,
                        cache_dir=cache_dir, floor_plan=floor_plan, floor_size=floor_size)
    notice = job.notice()
    if notice and progress_shown():  # as progress: not with --quiet
        typer.echo(notice, err=True)
    run = job.run()
    from graphslam.app.scoring import answer_errors

    errors = answer_errors({t.session_id: (t.t_ns, t.xy) for t in run.tracks}, job.survey, radio_map, job.radio_map.frame)
    shown: dict[str, object] = {} if errors is None else {"errors": errors}
    if picture:
        from graphslam.app.pictures import write_track_picture

        kind, smoother = cfg.filter.kind, cfg.filter.smoother
        label = (f"fixed-lag {cfg.fixed_lag.lag_s:g} s" if kind == "fixed-lag" else kind) if smoother == "none" else f"{kind} + {smoother} smoother"
        shown["picture"] = str(write_track_picture(run, radio_map, sessions, out.with_suffix(".png"), label))
    typer.echo(json.dumps(run.as_dict() | shown))


def track_config_from_options(config: Optional[Path], set_: Optional[List[str]], shortcuts: dict[str, Any]) -> Any:
    """The tracking configuration: ``config`` (merged over the defaults), ``--set`` overrides, then the
    shortcut options; a shortcut's invalid value is an error naming the option."""
    from graphslam.config import parse_overrides
    from graphslam.errors import ConfigError
    from graphslam.tracking_config import DEFAULTS, load_track_config

    overrides = parse_overrides(set_, example="fixed_lag.lag_s=1")
    for option, value in shortcuts.items():
        section, _, key = SHORTCUTS[option].partition(".")
        try:
            DEFAULTS.updated({SHORTCUTS[option]: value})
        except ConfigError as e:
            raise ConfigError(f"{option} {value!r}: {e}") from None
        overrides.setdefault(section, {})[key] = value
    return load_track_config(config, overrides)
