"""``graphslam bench``: what a user runs on their own recordings with ground truth: ``real`` (the
survey per variant, scored per component), ``locate-real`` (held-out walks' scans located on a map of
the others) and ``tracking-real`` (held-out walks tracked on a map of the others); and ``soak``, the HTTP service on a user's own map under load for a set time. The
simulator and public-data benchmarks are the lab's (``python -m lab.bench``)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import List, Optional

import typer

from graphslam.cli.base import bench_app
from graphslam.cli.options import choices, config_from_options, parse_lags, parse_smoothers, plain

ControlPoints = choices("ControlPoints", ("auto", "none"))


@bench_app.command("real")
def bench_real(
    folders: List[Path] = typer.Argument(..., help="Floor folders of recordings with /landmarks, or site folders of floors."),
    floors: Optional[str] = typer.Option(None, help="Comma-separated floor sub-folders of a site (default: all)."),
    config: Optional[Path] = typer.Option(None, "--config", "-c", help="Survey configuration (YAML)."),
    set_: Optional[List[str]] = typer.Option(None, "--set", help="Override a config value."),
    control_points: ControlPoints = typer.Option(
        "auto", "--control-points",
        help="auto: also the control_points variant on floors whose folder holds control_points.csv; none: never.",
    ),
    reference_map: ControlPoints = typer.Option(
        "auto", "--reference-map",
        help="auto: also the reference_map variant on floors whose folder holds reference_map.csv (the crowd: every "
        "walk whose scans it does not hold); none: never.",
    ),
    variants: str = typer.Option(
        "headings,no_magnetic,no_headings,control_points,reference_map", "--variants",
        help="Comma-separated variants to run.",
    ),
) -> None:
    """Survey each floor of real recordings per variant (headings: the config as given; no_magnetic:
    magnetic.enabled=false; no_headings: heading.enabled=false; control_points: the floor's
    control_points.csv, site frame; reference_map: the floor's reference_map.csv held fixed, the other
    walks placed on it, site frame); one JSON line per floor and variant (walks in the main map and in
    components of 5 or more, landmark errors after each component's own SE(2) fit, walks over 6 / 10 /
    15 m, frame, time), then one summary line per variant."""
    from graphslam.app.bench_real import real_floor_rows, real_summary

    rows = []
    for row in real_floor_rows(
        folders, config_from_options(config, set_), floors.split(",") if floors else None,
        variants=[v.strip() for v in variants.split(",") if v.strip()], control_points=plain(control_points),
        reference_map=plain(reference_map),
    ):
        rows.append(row)
        typer.echo(json.dumps(row))
    for line in real_summary(rows):
        typer.echo(json.dumps(line))


@bench_app.command("locate-real")
def bench_locate_real(
    folders: List[Path] = typer.Argument(..., help="Floor folders of real recordings with /landmarks, or site folders of floors."),
    metrics: str = typer.Option("sorensen,eq9", help="kNN distances to compare, the first one scored for sigma_m too (sorensen, eq9)."),
    folds: Optional[int] = typer.Option(None, help="Seeded random folds (default: leave one route out when file names name routes, else 5)."),
    seed: int = typer.Option(0, help="Seed of the random folds."),
) -> None:
    """kNN positioning of held-out walks on the radio map of the other walks of their floor (placed
    by their landmarks: ground truth builds the map and scores): per metric mean / median / p90
    error, the share of errors inside the answers' 95 % circles (sigma_m), and the share of answers
    flagged outside among those far from / near the map's fingerprints. One JSON line per floor, then
    a summary line over them."""
    from graphslam.app.locate_bench import locate_real_rows, locate_real_summary

    names = [m.strip() for m in metrics.split(",") if m.strip()]
    rows = []
    for row in locate_real_rows(folders, metrics=names, folds=folds, seed=seed):
        rows.append(row)
        typer.echo(json.dumps(row))
    typer.echo(json.dumps(locate_real_summary(rows, names[0])))


@bench_app.command("tracking-real")
def bench_tracking_real(
    folder: Path = typer.Argument(..., help="Folder of real recordings with /landmarks (e.g. ../shared/data/ipin2023/b100_f-2)."),
    maps: str = typer.Option("oracle,crowdsourced", help="Radio maps to build per fold: oracle, crowdsourced."),
    lags: str = typer.Option("0,1,2", help="Fixed-lag tracker latencies to report (s, comma-separated)."),
    filters: str = typer.Option("ekf", help="Causal filters also reported (ekf, ukf; '' for none)."),
    smoothers: str = typer.Option("", help="Offline whole-session smoothers also reported (rts, map)."),
    folds: Optional[int] = typer.Option(None, help="Seeded random folds (default: leave one route out when file names name routes, else 5)."),
    seed: int = typer.Option(0, help="Seed of the random folds."),
    config: Optional[Path] = typer.Option(None, "--config", "-c", help="Survey configuration (crowdsourced map)."),
    set_: Optional[List[str]] = typer.Option(None, "--set", help="Override a survey config value."),
    floor_plan: str = typer.Option(
        "auto", "--floor-plan", help="Walkable-area prior for the trackers on the oracle maps: auto (floor_image.png "
        "beside the walks, when there is one), none, or a plan image (floor_info.json beside it).",
    ),
) -> None:
    """Held-out real walks tracked on a map of the other walks vs kNN: mean/median/p75/p90, 95 % ellipse coverage."""
    from graphslam.app.tracking_bench import floor_plan_area, standard_variants, tracking_real
    from graphslam.core.radiomap.ivf import limit_blas_threads

    limit_blas_threads(1)
    variants = standard_variants(
        parse_lags(lags), [f for f in filters.split(",") if f.strip()], parse_smoothers(smoothers)
    )
    area = floor_plan_area(folder, floor_plan)
    res = tracking_real(
        folder, config_from_options(config, set_), variants, maps=[m for m in maps.split(",") if m.strip()], folds=folds, seed=seed,
        area=area,
    )
    typer.echo(json.dumps(res))


@bench_app.command("soak")
def bench_soak(
    radio_map: Path = typer.Option(..., "--radio-map", help="Radio map (.parquet) to serve (a copy is served)."),
    minutes: int = typer.Option(60, "--minutes", min=1, help="Minutes of open-loop load (one row each)."),
    load: float = typer.Option(0.8, "--load", help="Fraction of the measured capacity to send."),
    rate: Optional[float] = typer.Option(None, "--rate", min=1.0, help="Requests/s instead of --load x capacity."),
    capacity_s: float = typer.Option(10.0, "--capacity-seconds", min=1.0, help="Closed-loop capacity burst (s)."),
    seed: int = typer.Option(0, "--seed", min=0, help="Seed of the query fingerprints."),
) -> None:
    """Soak `graphslam serve --watch` on 127.0.0.1: its capacity, then --load of it for --minutes with a
    map reload every minute; JSON lines: the capacity, one row per minute (requests, errors, p50/p99 ms,
    server RSS), a summary."""
    from graphslam.app.soak import run_soak

    result = run_soak(radio_map, minutes=minutes, load=load, rate=rate, capacity_s=capacity_s, seed=seed,
                      on_row=lambda row: typer.echo(json.dumps(row)))
    typer.echo(json.dumps({"summary": result.summary}))
