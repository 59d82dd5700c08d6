"""The lab's benchmarks on simulated and public data: ``python -m lab.bench COMMAND`` (from the
repository root; ``--help`` lists them). Each prints JSON lines; docs/benchmarks.md quotes the
command behind every figure. What a user runs on their own recordings stays in ``graphslam
bench`` (``real``, ``tracking-real``).

Errors and usage errors are one line and exit code 2, as ``graphslam``'s (``gs.run_app``).
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path
from typing import List, Optional

import typer

import graphslam as gs

app = typer.Typer(add_completion=False, help="The lab's benchmarks on simulated and public data (JSON lines).")


@app.callback()
def _root(ctx: typer.Context, quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bars or lines.")) -> None:
    import logging

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    gs.show_progress("off" if quiet else "auto")
    ctx.call_on_close(lambda: gs.show_progress("off"))  # as graphslam's: nothing left behind for the next caller


def seeds_of(text: str) -> list[int]:
    """'0,1,2' or ranges '0-19' (mixed: '0-3,7')."""
    out: list[int] = []
    try:
        for part in (p.strip() for p in text.split(",")):
            if "-" in part[1:]:
                lo, hi = (int(v) for v in part.split("-", 1))
                out += list(range(lo, hi + 1))
            elif part:
                out.append(int(part))
    except ValueError:
        raise gs.ConfigError(f"--seeds {text!r}: expected comma-separated integers or ranges, e.g. 0,1,2 or 0-19") from None
    return out


def shadowing_of(text: str) -> tuple[float, float] | None:
    """'0.5,3': share of the RSSI variance in (0, 1) and correlation distance > 0 (m); '' for none."""
    if not text.strip():
        return None
    try:
        share, corr = (float(v) for v in text.split(","))
    except ValueError:
        share = corr = math.nan
    if not (0.0 < share < 1.0 and math.isfinite(corr) and corr > 0):
        raise gs.ConfigError(f"--shadowing: {text!r} is not SHARE,CORR_M with 0 < SHARE < 1 and CORR_M > 0, e.g. 0.5,3")
    return share, corr


def echo_rows(rows: list[dict], last: dict) -> None:
    """One JSON line per row, then the aggregate."""
    for r in rows:
        typer.echo(json.dumps(r))
    typer.echo(json.dumps(last))


@app.command("accuracy")
def bench_accuracy(
    scenario: str = typer.Argument(..., help="Simulator scenario: paper, corridor, crowd."),
    seeds: str = typer.Option("0,1,2", help="Comma-separated seeds."),
    size: float = typer.Option(1.0, help="Simulator size multiplier."),
    config: Optional[Path] = typer.Option(None, "--config", "-c"),
    set_: Optional[List[str]] = typer.Option(None, "--set", help="Override a config value."),
) -> None:
    """Align simulated surveys; print one JSON line of errors per seed, then the mean over seeds."""
    from lab.bench.simulated import accuracy

    rows = accuracy(scenario, seeds_of(seeds), gs.load_config(config, gs.parse_overrides(set_)), size=size)
    for r in rows:
        typer.echo(json.dumps(r))
    keys = ("main", "landmark_mean_m", "landmark_max_m", "heading_mean_deg", "steps_mean_m", "align_s")
    typer.echo(json.dumps({"mean_over_seeds": {k: round(sum(r[k] for r in rows) / len(rows), 3) for k in keys}}))


@app.command("survey")
def bench_survey(
    scenario: str = typer.Argument("paper"),
    seed: int = typer.Option(0),
    runs: int = typer.Option(5, help="End-to-end runs (median reported)."),
    size: float = typer.Option(1.0, help="Simulator size multiplier (scale tests)."),
    config: Optional[Path] = typer.Option(None, "--config", "-c"),
) -> None:
    """Time `graphslam survey` end to end on a simulated survey (fresh process per run); peak memory."""
    from lab.bench.simulated import survey_speed

    typer.echo(json.dumps(survey_speed(scenario, seed, runs=runs, size=size, config=config)))


@app.command("scale")
def bench_scale(
    scenario: str = typer.Argument("paper"),
    seed: int = typer.Option(0),
    sizes: str = typer.Option("1", help="Comma-separated simulator sizes, e.g. 1,2,4,8,12."),
    runs: str = typer.Option("5", help="Rounds per size: one number, or one per size (e.g. 7,5,3,1,1)."),
    baseline: Optional[Path] = typer.Option(
        None, "--baseline", help="A graphslam checkout (e.g. a git worktree of the previous main) run alternately."
    ),
    baseline_max_size: float = typer.Option(1e9, help="Run the baseline only up to this size (it may be slow)."),
    config: Optional[Path] = typer.Option(None, "--config", "-c"),
) -> None:
    """`graphslam survey` per size, alternating with --baseline in fresh processes: stage medians, peak RSS,
    growth exponent; JSON on stdout, then the markdown stage table."""
    from lab.bench.scale import markdown_table, scale
    try:
        size_list = [float(v) for v in sizes.split(",") if v.strip()]
        run_list = [int(v) for v in runs.split(",") if v.strip()]
    except ValueError:
        raise gs.ConfigError(f"--sizes / --runs: numbers separated by commas, got {sizes!r} / {runs!r}") from None
    if len(run_list) == 1:
        run_list *= len(size_list)
    if not size_list or len(run_list) != len(size_list) or min(run_list) < 1 or min(size_list) <= 0:
        raise gs.ConfigError("--runs: one count >= 1, or one per size; --sizes: positive numbers")
    result = scale(
        scenario, seed, size_list, run_list, baseline=baseline, baseline_max_size=baseline_max_size, config=config,
        progress=lambda msg: typer.echo(msg, err=True),
    )
    typer.echo(json.dumps(result))
    typer.echo(markdown_table(result))


@app.command("speed")
def bench_speed(
    baseline: Path = typer.Option(..., "--baseline", help="A graphslam checkout to compare with, e.g. a git worktree "
                                  "of an older commit (e.g. 6d0b028)."),
    sizes: str = typer.Option("1,12", help="`paper` survey sizes (the last one is the large-survey row)."),
    runs: str = typer.Option("3,3", help="Rounds per size."),
    startup_runs: int = typer.Option(7, min=1),
    update_runs: int = typer.Option(3, min=1),
    update_size: float = typer.Option(4.0, min=0.1, help="`crowd` floor size of the update row (10 new walks at 4)."),
    track_rounds: int = typer.Option(2, min=1),
    service_rounds: int = typer.Option(2, min=1),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Also write every figure to this file."),
) -> None:
    """Every speed row of docs/benchmarks.md (start-up, survey, solver, update, tracking, service) side by side with
    --baseline in one run: JSON on stdout, then the markdown table."""
    from lab.bench.speed import markdown_table, speed
    try:
        size_list = [float(v) for v in sizes.split(",") if v.strip()]
        run_list = [int(v) for v in runs.split(",") if v.strip()]
    except ValueError:
        raise gs.ConfigError(f"--sizes / --runs: numbers separated by commas, got {sizes!r} / {runs!r}") from None
    if not size_list or len(run_list) != len(size_list) or min(run_list) < 1 or min(size_list) <= 0:
        raise gs.ConfigError("--runs: one count >= 1 per size; --sizes: positive numbers")
    result = speed(baseline, sizes=size_list, runs=run_list, startup_runs=startup_runs, update_runs=update_runs, update_size=update_size,
                   track_rounds=track_rounds, service_rounds=service_rounds,
                   progress=lambda msg: typer.echo(f"speed: {msg}", err=True))
    if json_out is not None:
        json_out.write_text(json.dumps(result, indent=1))
    typer.echo(json.dumps(result))
    typer.echo(markdown_table(result))


@app.command("solvers")
def bench_solvers(
    scenario: str = typer.Argument("paper"),
    seed: int = typer.Option(0),
    size: float = typer.Option(4.0, help="Simulator size multiplier."),
    solvers: str = typer.Option("gtsam,cholmod", help="optimizer.solver values, taking turns run by run."),
    runs: int = typer.Option(3, min=1, help="Runs of each (medians reported)."),
) -> None:
    """`graphslam survey` per optimizer.solver side by side in fresh processes: stage medians, peak RSS,
    wall and optimise time over CHOLMOD's."""
    from lab.bench.scale import solvers as run_solvers

    names = [s.strip() for s in solvers.split(",") if s.strip()]
    bad = [s for s in names if s not in ("gtsam", "cholmod", "auto")]
    if bad or not names:
        raise gs.ConfigError(f"--solvers {solvers!r}: expected some of gtsam, cholmod, auto")
    typer.echo(json.dumps(run_solvers(scenario, seed, size, names, runs, progress=lambda m: typer.echo(m, err=True))))


@app.command("update")
def bench_update(
    scenario: str = typer.Argument("paper"),
    seed: int = typer.Option(0),
    size: float = typer.Option(4.0, help="Walks surveyed first, as the simulator's size multiplier."),
    new_fraction: float = typer.Option(0.05, "--new-fraction", help="Then this many more walks arrive (>= 1)."),
    hops: str = typer.Option("0,1,2", help="update.hops values to measure (comma-separated)."),
    runs: int = typer.Option(3, min=1, help="Runs of each variant, alternated (medians reported)."),
) -> None:
    """`survey --update` vs a full re-solve of every walk, end to end in fresh processes."""
    from lab.bench.update import update_speed

    typer.echo(json.dumps(update_speed(scenario, seed, size=size, new_fraction=new_fraction, hops=seeds_of(hops), runs=runs)))


@app.command("batch")
def bench_batch(
    scenario: str = typer.Argument("crowd"),
    floors: int = typer.Option(16, min=1, help="Simulated floors (seeds 0..N-1)."),
    size: float = typer.Option(0.5, help="Simulator size multiplier of each floor."),
    workers: int = typer.Option(2, min=1, help="survey-batch --workers."),
    runs: int = typer.Option(1, min=1, help="Runs of each variant (medians reported)."),
) -> None:
    """`survey-batch` on a local Dask cluster vs the same floors one after another."""
    from lab.bench.update import batch_speed

    typer.echo(json.dumps(batch_speed(scenario, floors=floors, size=size, workers=workers, runs=runs)))


@app.command("ujiindoorloc")
def bench_ujiindoorloc(
    data_dir: Path = typer.Argument(..., help="Folder with trainingData.csv[.gz] and validationData.csv[.gz]."),
    k: int = typer.Option(7, "--k", min=1, help="Neighbours."),
    weighted: bool = typer.Option(True, "--weighted/--no-weighted", help="Inverse-distance weights, else uniform."),
    min_rssi: float = typer.Option(-95.0, "--min-rssi", help="Drop readings below this (dBm)."),
    missing_dbm: float = typer.Option(-100.0, "--missing-dbm", help="RSS of an AP not heard, in eq. 9 (dBm)."),
    min_common: int = typer.Option(1, "--min-common", min=1, help="Neighbours must share this many APs."),
    repeats: int = typer.Option(5, "--repeats", min=1, help="Timed runs (the median is reported)."),
    index: str = typer.Option("exact", "--index", help="kNN search: exact, ivf (approximate inverted file) or auto. Default: exact."),
    ivf_clusters: Optional[int] = typer.Option(None, "--ivf-clusters", min=1, help="IVF: k-means clusters (default ~2 sqrt(N))."),
    ivf_probes: Optional[int] = typer.Option(None, "--ivf-probes", min=1, help="IVF: clusters searched per query (default 8)."),
    metric: str = typer.Option("eq9", "--metric", help="Fingerprint distance: eq9 or sorensen."),
) -> None:
    """kNN on UJIIndoorLoc (train: trainingData, test: validationData); prints one JSON line."""
    metric = gs.parse_metric(metric)
    from lab.bench.uji import run_ujiindoorloc_benchmark

    if index != "exact":

        gs.limit_blas_threads(1)  # the IVF search's small GEMMs (see limit_blas_threads)

    r = run_ujiindoorloc_benchmark(
        data_dir, k=k, weighted=weighted, min_rssi_dbm=min_rssi, missing_dbm=missing_dbm,
        min_common=min_common, repeats=repeats, index=index, ivf_clusters=ivf_clusters, ivf_probes=ivf_probes,
        metric=metric,
    )
    typer.echo(json.dumps(r.as_dict()))


@app.command("fig8")
def bench_fig8(
    scenario: str = typer.Argument("paper"),
    seeds: str = typer.Option("0,1,2", help="Comma-separated seeds."),
    test_walks: int = typer.Option(5, help="Held-out test walks per seed."),
    k: int = typer.Option(3, help="kNN neighbours."),
    plot: Optional[Path] = typer.Option(None, help="Write the CDF plot (PNG) here."),
    config: Optional[Path] = typer.Option(None, "--config", "-c"),
) -> None:
    """The paper's fig. 8: kNN error CDF of held-out walks, crowdsourced vs surveyed radio map."""
    from lab.bench.simulated import fig8

    typer.echo(json.dumps(fig8(scenario, seeds_of(seeds), gs.load_config(config), test_walks=test_walks, k=k, plot=plot)))


@app.command("ilc")
def bench_ilc(
    site_dir: Path = typer.Argument(..., help="An ILC 2.0 site folder with one sub-folder per floor."),
    floors: Optional[str] = typer.Option(None, help="Comma-separated floors (default: all)."),
    config: Optional[Path] = typer.Option(None, "--config", "-c"),
    set_: Optional[List[str]] = typer.Option(None, "--set", help="Override a config value."),
) -> None:
    """Align each real ILC floor; one JSON line per floor with waypoint errors (SE(2) fit) and time."""
    from lab.bench.simulated import ilc_floors

    for row in ilc_floors(site_dir, gs.load_config(config, gs.parse_overrides(set_)), floors.split(",") if floors else None):
        typer.echo(json.dumps(row))


@app.command("filters")
def bench_filters(
    seeds: str = typer.Option(",".join(map(str, range(20))), help="Comma-separated seeds."),
    shadowing_db: Optional[float] = typer.Option(None, help="Override the 4 dB shadowing std (sensitivity)."),
    plot_dir: Optional[Path] = typer.Option(None, help="Write tracking_cart_{ekf,ukf}.png here (first seed)."),
    smoothers: str = typer.Option("rts,map", help="Offline smoothers also reported (comma-separated; '' for none)."),
    lags: str = typer.Option("2", help="Fixed-lag smoother latencies also reported (s, comma-separated; '' for none)."),
    window: float = typer.Option(480.0, min=0.0, help="Fixed-lag window (s): older epochs are marginalised."),
    restart_every: int = typer.Option(10, min=0, help="Fixed-lag: also solve from dead-reckoning starts every N epochs (0: never)."),
    shadowing: str = typer.Option(
        "0.5,3", help="Fixed-lag also with this share of the RSSI variance as shadowing correlated over this "
        "distance (SHARE,CORR_M; '' for none).",
    ),
) -> None:
    """The filter papers' experiment simulated: RMS error in x and y of EKF and UKF (and smoothed) over seeds."""
    from lab.bench.simulated import filters_cart

    gs.limit_blas_threads(1)

    res = filters_cart(
        seeds_of(seeds), shadowing_db=shadowing_db, plot_dir=plot_dir, smoothers=gs.parse_smoothers(smoothers),
        lags=gs.parse_lags(lags), window_s=window, restart_every=restart_every, shadowing=shadowing_of(shadowing),
    )
    typer.echo(json.dumps(res))


@app.command("tracking")
def bench_tracking(
    scenario: str = typer.Argument("paper"),
    seeds: str = typer.Option("0,1,2", help="Comma-separated seeds."),
    test_walks: int = typer.Option(3, help="Held-out test walks per seed."),
    config: Optional[Path] = typer.Option(None, "--config", "-c"),
    smoothers: str = typer.Option("", help="Offline smoothers also reported, e.g. 'rts,map' (default none)."),
    knn_fixes: bool = typer.Option(False, "--knn-fixes", help="Also report every variant with kNN fixes fused."),
    lags: str = typer.Option("", help="Also report the fixed-lag tracker at these latencies (s, comma-separated)."),
) -> None:
    """Held-out walks: EKF/UKF tracking vs kNN (mean error); AP position error vs the simulator."""
    from lab.bench.simulated import tracking_paper

    gs.limit_blas_threads(1)
    res = tracking_paper(
        scenario, seeds_of(seeds), gs.load_config(config), test_walks=test_walks, smoothers=gs.parse_smoothers(smoothers),
        knn_fixes=knn_fixes, lags=gs.parse_lags(lags),
    )
    typer.echo(json.dumps(res))


@app.command("uwb")
def bench_uwb(
    seeds: str = typer.Option("0-99", help="Seeds of the seven-tag runs (e.g. 0-99)."),
    plot_dir: Optional[Path] = typer.Option(None, help="Write uwb_fig8.png and uwb_zones.png (first seed) here."),
    per_seed: bool = typer.Option(False, "--per-seed", help="Also print one JSON line per seed."),
) -> None:
    """Paper 003's experiment simulated: collisions, slots per tag per cycle, clock offsets, EKF error per zone/type."""
    from lab.bench.uwb import zones_benchmark

    rows, agg = zones_benchmark(seeds_of(seeds), plot_dir=plot_dir)
    echo_rows(rows if per_seed else [], agg)


@app.command("uwb-survey")
def bench_uwb_survey(
    seeds: str = typer.Option("0-4", help="Seeds of the simulated crowd (12 walkers, 5-8 min, all at once)."),
    anchors: str = typer.Option("2,3,4", help="Anchor counts to run (0: peer ranges only, reference-walk frame)."),
    config: Optional[Path] = typer.Option(None, "--config", "-c"),
    set_: Optional[List[str]] = typer.Option(None, "--set", help="Override a config value."),
    per_seed: bool = typer.Option(False, "--per-seed", help="Also print one JSON line per (anchors, seed)."),
) -> None:
    """A crowd surveying together with UWB: site-frame error, vs WiFi only, with NLOS ranges."""
    from lab.bench.uwb import survey_benchmark

    rows, agg = survey_benchmark(seeds_of(seeds), seeds_of(anchors), gs.load_config(config, gs.parse_overrides(set_)))
    echo_rows(rows if per_seed else [], agg)


def main(argv: Optional[list[str]] = None) -> None:
    gs.run_app(app, sys.argv[1:] if argv is None else argv, "python -m lab.bench")


if __name__ == "__main__":
    main()
