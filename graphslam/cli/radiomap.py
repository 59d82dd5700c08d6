"""Radio-map commands: locate (kNN), serve (HTTP), fit-aps (access-point models)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import List, Optional

import typer

from graphslam.cli.base import app
from graphslam import names
from graphslam.cli.options import (
    INDEX_HELP, IVF_CLUSTERS_HELP, IVF_PROBES_HELP, K_HELP, METRIC_HELP, Index, Metric, choices, plain, require_rerun,
)

LogLevel = choices("LogLevel", names.LOG_LEVELS)


@app.command()
def locate(
    query_paths: List[Path] = typer.Argument(..., help="Query recordings (.mcap) or folders of them."),
    radio_map: Path = typer.Option(..., "--radio-map", help="Radio map (.parquet)."),
    out: Path = typer.Option(..., "--out", "-o", help="Output CSV: session_id,t_ns,x,y,score,spread,..."),
    k: int = typer.Option(names.DEFAULT_K, "--neighbours", "-k", min=1, help=K_HELP),
    weighted: bool = typer.Option(True, "--weighted/--no-weighted", help="Inverse-distance weights, else uniform."),
    min_common: int = typer.Option(1, "--min-common", min=1, help="Neighbours must share this many APs."),
    rerun: Optional[Path] = typer.Option(
        None, "--rerun", help="Also log the answers (and the truth, if the queries carry /ground_truth/pose) to this .rrd."
    ),
    site_from_map: Optional[tuple[float, float, float]] = typer.Option(
        None, "--site-from-map", help="X Y THETA placing the map frame in the site frame (e.g. report.json's "
        "evaluation.site_from_aligned), for the truth overlay."
    ),
    index: Index = typer.Option(names.DEFAULT_INDEX, "--index", help=INDEX_HELP),
    metric: Metric = typer.Option(names.DEFAULT_METRIC, "--metric", help=METRIC_HELP),
    picture: bool = typer.Option(True, "--picture/--no-picture", help="Also write OUT with .png: answers (and truth)."),
) -> None:
    """Locate every /wifi/scan of the query sessions by kNN against a radio map."""
    from graphslam.app.locate import locate_files

    require_rerun(rerun)

    run = locate_files(
        radio_map, query_paths, out=out, k=k, weighted=weighted, min_common=min_common, index=plain(index),
        metric=plain(metric),
    )
    if rerun is not None:
        from graphslam.app.locate import query_truth
        from graphslam.viz.rerun_log import log_locate_results

        pos = run.positions
        log_locate_results(
            rerun,
            pos.result.xy,
            query_truth(query_paths, pos),
            query_ids=[f"{s}@{t}" for s, t in zip(pos.session_ids.tolist(), pos.t_ns.tolist())],
            site_from_map=site_from_map,
        )
    from graphslam.app.locate import answers_by_session
    from graphslam.app.scoring import answer_errors
    from graphslam.io.mcap_reader import read_survey

    errors = answer_errors(answers_by_session(run.positions), read_survey(query_paths), radio_map,
                           run.radio_map_frame, site_from_map)
    shown: dict[str, object] = {} if errors is None else {"errors": errors}
    if picture:
        from graphslam.app.pictures import write_locate_picture

        shown["picture"] = str(write_locate_picture(run, radio_map, query_paths, out.with_suffix(".png"), site_from_map))
    typer.echo(json.dumps(run.as_dict() | shown))


@app.command()
def serve(
    radio_map: Path = typer.Option(
        ..., "--radio-map", help="Radio map (.parquet), or a site: a folder of floor folders each holding "
        "radio_map.parquet (survey-batch --out); then every answer names its floor.",
    ),
    host: Optional[str] = typer.Option(None, "--host", help="Bind address (default: loopback, 127.0.0.1)."),
    port: Optional[int] = typer.Option(None, "--port", min=0, max=65535, help="TCP port (default 8077)."),
    k: Optional[int] = typer.Option(None, "--neighbours", "-k", min=1, help=f"{K_HELP} Default: {names.DEFAULT_K}."),
    weighted: Optional[bool] = typer.Option(None, "--weighted/--no-weighted", help="Inverse-distance weights (default), else uniform."),
    min_common: Optional[int] = typer.Option(None, "--min-common", min=1, help="Neighbours must share this many APs (default 1)."),
    max_batch: Optional[int] = typer.Option(None, "--max-batch", min=1, help="Most fingerprints per request (default 10,000)."),
    max_body_bytes: Optional[int] = typer.Option(None, "--max-body-bytes", min=1024, help="Largest request body (default 32 MiB)."),
    index: Optional[Index] = typer.Option(None, "--index", help=f"{INDEX_HELP} Default: {names.DEFAULT_INDEX}."),
    ivf_clusters: Optional[int] = typer.Option(None, "--ivf-clusters", min=1, help=IVF_CLUSTERS_HELP),
    ivf_probes: Optional[int] = typer.Option(None, "--ivf-probes", min=1, help=IVF_PROBES_HELP),
    workers: Optional[int] = typer.Option(None, "--workers", min=1, help="Server processes (each loads the map; ~1 core each; default 1)."),
    search_processes: Optional[int] = typer.Option(
        None, "--search-processes", min=0,
        help="Forked search workers sharing the map; batches of 64+ fingerprints are split over them. "
        "0 = search in the server process. Default: min(2, cores), 0 with --workers > 1.",
    ),
    log_level: Optional[LogLevel] = typer.Option(
        None, "--log-level", case_sensitive=False, help="uvicorn's and the service's log lines; info (the default) logs one access line per "
        "request and every map reload, warning neither.",
    ),
    token: Optional[str] = typer.Option(
        None, "--token", envvar="GRAPHSLAM_SERVE_TOKEN", show_envvar=True,
        help="Require 'Authorization: Bearer TOKEN' on /v1/ (prefer the environment variable: "
        "a command line is visible to other users).",
    ),
    watch: bool = typer.Option(
        False, "--watch", help="Reload the radio map when its file changes (SIGHUP always reloads); a map that "
        "does not load is refused and the old one kept. No request fails during a swap.",
    ),
    watch_interval: Optional[float] = typer.Option(None, "--watch-interval", min=0.05, help="--watch: seconds between checks (default 1)."),
    metric: Optional[Metric] = typer.Option(None, "--metric", help=f"{METRIC_HELP} Default: {names.DEFAULT_METRIC}."),
) -> None:
    """Serve kNN positioning over HTTP (POST /v1/locate, GET /v1/radio-map, GET /healthz, /openapi.json, /docs).
    A site (a folder of floor maps) is answered floor by floor: the best-matching floor gives the position.
    A port already in use, or a site folder without a readable floor map, is one line and exit code 2."""
    if not radio_map.exists():  # one line before the web service's libraries are imported
        from graphslam.errors import RadioMapError

        raise RadioMapError(f"{radio_map}: no such file")
    from graphslam.service.config import DEFAULT_WATCH_S, ServeConfig
    from graphslam.service.server import serve as serve_map

    given = dict(
        host=host, port=port, k=k, weighted=weighted, min_common=min_common, max_batch=max_batch,
        max_body_bytes=max_body_bytes, index=plain(index), ivf_clusters=ivf_clusters, ivf_probes=ivf_probes,
        workers=workers, search_processes=search_processes, log_level=plain(log_level), token=token, metric=plain(metric),
        watch_s=(watch_interval or DEFAULT_WATCH_S) if watch else None,
    )
    serve_map(radio_map, ServeConfig(**{k_: v for k_, v in given.items() if v is not None}))


@app.command("fit-aps")
def fit_aps(
    radio_map: Path = typer.Option(..., "--radio-map", help="Radio map (.parquet)."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="AP models JSON (default: ap_models.json beside the map)."),
    min_readings: int = typer.Option(20, "--min-readings", min=5, help="Fit only APs heard this often."),
) -> None:
    """Fit position, P0 and gamma of every often-heard AP of a radio map (robust least squares)."""
    from graphslam.core.tracking.apmodel import ApFitConfig, ApModels
    from graphslam.io.apmodel_io import write_ap_models
    from graphslam.io.radiomap_io import read_radio_map

    rm = read_radio_map(radio_map)
    fit = ApFitConfig(min_readings=min_readings)
    models = ApModels.fit(rm, fit)
    path = write_ap_models(models, out or radio_map.with_name("ap_models.json"), radio_map=rm, fit=fit)
    reasons: dict[str, int] = {}
    for u in models.unfitted:
        key = u.reason.split(" (")[0]
        reasons[key] = reasons.get(key, 0) + 1
    typer.echo(json.dumps({"out": str(path), "fitted": len(models.fitted), "unfitted": len(models.unfitted), "reasons": reasons}))
