"""Tracking command: track walks on a radio map."""

from __future__ import annotations

import json
from pathlib import Path
from typing import List, Optional

import typer

from graphslam.cli.base import app
from graphslam.cli.options import METRIC_HELP, parse_metric


@app.command()
def track(
    sessions: List[Path] = typer.Argument(..., help="Session recordings (.mcap) or folders of them."),
    radio_map: Path = typer.Option(..., "--radio-map", help="Radio map (.parquet); positions come out in its frame."),
    filter_: str = typer.Option(
        "fixed-lag", "--filter", help="fixed-lag (online, reports each step --lag s late), the causal ekf / ukf, or "
        "particle (map-matching particle filter, --lag s late; docs/tracking.md)."
    ),
    lag: float = typer.Option(2.0, "--lag", min=0.0, help="fixed-lag: latency in s (a step is reported once the data up to lag s later are in)."),
    bank_report: str = typer.Option(
        "mixture", "--bank-report",
        help="fixed-lag: mixture (the heading hypotheses' posterior mixture) or best (the most probable one only).",
    ),
    bank_temper: Optional[float] = typer.Option(
        None, "--bank-temper",
        help="fixed-lag: divide the heading hypotheses' costs by this (>= 1) before weighing them; default: measured on "
        "the map by self-calibration (its fixes' error correlation along a walk), 1 without it.",
    ),
    out: Path = typer.Option(..., "--out", help="Output CSV: one row per step (t_ns, x, y, covariance, ...)."),
    ap_models: Optional[Path] = typer.Option(
        None, "--ap-models", help="AP models JSON (default: ap_models.json beside the map, else fitted now)."
    ),
    smooth: str = typer.Option(
        "none", "--smooth", help="Offline, whole session: none (the online tracker), rts, or map (whole-run MAP)."
    ),
    knn_fixes: bool = typer.Option(
        True, "--knn-fixes/--no-knn-fixes", help="Also fuse each scan's kNN fix on the radio map (--no-knn-fixes: the papers' RSSI-only model)."
    ),
    adaptive_rssi: bool = typer.Option(
        True, "--adaptive-rssi/--no-adaptive-rssi", help="Inflate a scan's RSSI noise when its innovations disagree."
    ),
    self_calibrate: bool = typer.Option(
        True, "--self-calibrate/--no-self-calibrate",
        help="Measure the kNN fix noise, RSSI variance and covariance scale on the radio map itself (docs/tracking.md).",
    ),
    calibration_cache: bool = typer.Option(
        True, "--calibration-cache/--no-calibration-cache",
        help="Keep the self-calibration in track_calibration.json beside the map; reuse it for the same map, AP models and options.",
    ),
    knn_metric: str = typer.Option(
        "sorensen", "--knn-metric",
        help="kNN fixes' (and the particle filter's scan matches') " + METRIC_HELP[0].lower() + METRIC_HELP[1:]),
    walk_axes: bool = typer.Option(
        True, "--walk-axes/--no-walk-axes",
        help="fixed-lag / --smooth map: walkers keep to the two perpendicular directions the map's own walks keep to "
        "(measured on the map; off by itself where they keep to none; docs/tracking.md).",
    ),
    rssi_field: float = typer.Option(
        3.0, "--rssi-field", help="Kernel std (m) of each AP's residual field, measured on the map: what the AP models' "
        "log-distance law misses (walls, shelves), added to it; 0: the law alone (docs/tracking.md).",
    ),
    floor_plan: Optional[Path] = typer.Option(
        None, "--floor-plan", help="A floor plan image (site frame, as the radio map): its blank area inside the outline "
        "is walkable; positions off it are moved to it (docs/tracking.md).",
    ),
    floor_size: Optional[tuple[float, float]] = typer.Option(
        None, "--floor-size", help="W H of the floor plan (m); default: floor_info.json beside the image."
    ),
    floor_plan_use: str = typer.Option(
        "snap", "--floor-plan-use", help="snap (each position off the walkable area to its nearest cell), prior (a "
        "row per step in the fixed-lag / --smooth map problem, std --walkable-sigma) or both.",
    ),
    walkable_sigma: float = typer.Option(2.0, "--walkable-sigma", help="--floor-plan-use prior / both: std (m) of a step's distance to the walkable area."),
    picture: bool = typer.Option(True, "--picture/--no-picture", help="Also write OUT with .png: the tracks (and truth)."),
) -> None:
    """Track walks on a radio map: fusion of step velocity, WiFi RSSI and kNN fixes (fixed-lag MAP, or EKF/UKF)."""
    from graphslam.app.track import TrackConfig, track_files
    from graphslam.core.radiomap.ivf import limit_blas_threads

    limit_blas_threads(1)  # thousands of tiny solves: OpenBLAS threads only slow them down
    knn_metric = parse_metric(knn_metric, "--knn-metric")
    cfg = TrackConfig(
        filter=filter_, lag_s=lag, smoother=smooth, knn_fixes=knn_fixes, adaptive_rssi=adaptive_rssi,
        self_calibrate=self_calibrate, bank_report=bank_report, bank_temper=bank_temper, knn_metric=knn_metric, walk_axes=walk_axes,
        walkable_sigma_m=walkable_sigma, walkable_mode=floor_plan_use, rssi_field_m=rssi_field,
    )
    run = track_files(radio_map, sessions, ap_models_path=ap_models, out=out, cfg=cfg, calibration_cache=calibration_cache,
                      floor_plan=floor_plan, floor_size=floor_size)
    shown = {}
    if picture:
        from graphslam.app.pictures import write_track_picture

        label = (f"fixed-lag {lag:g} s" if filter_ == "fixed-lag" else filter_) if smooth == "none" else f"{filter_} + {smooth} smoother"
        shown["picture"] = str(write_track_picture(run, radio_map, sessions, out.with_suffix(".png"), label))
    typer.echo(json.dumps(run.as_dict() | shown))
