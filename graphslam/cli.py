"""Command-line interface. Parses arguments, calls one library function, prints its result.

This is the only place that catches ``GraphSlamError`` (prints one line, exits 2).
"""

from __future__ import annotations

import json
import logging
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING, List, Optional

import typer

from graphslam.errors import GraphSlamError

if TYPE_CHECKING:
    from graphslam.config import GraphSlamConfig

# no_args_is_help stays off: typer prints the whole help while raising that error; without it,
# `graphslam` / `graphslam bench` alone is a usage error ("Missing command"), one line like all others.
app = typer.Typer(
    add_completion=False,
    help="Factor-graph SLAM for crowdsourced indoor WiFi site survey (foot-mounted IMU + WiFi).",
)
bench_app = typer.Typer(help="Benchmarks on simulated and real data.")
app.add_typer(bench_app, name="bench")

EXIT_ERROR = 2


def _show_version(value: bool) -> None:
    if value:
        from graphslam import __version__

        typer.echo(f"graphslam {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    ctx: typer.Context,
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Log details at INFO level."),
    quiet: bool = typer.Option(
        False, "--quiet", "-q", help="No progress: neither bars (terminal) nor progress log lines (batch). "
        "Also accepted after the command name."
    ),
    progress_interval: float = typer.Option(
        10.0, "--progress-interval", min=0.0, help="Seconds between progress log lines when stderr is not a terminal."
    ),
    version: bool = typer.Option(
        False, "--version", callback=_show_version, is_eager=True, help="Print the version and exit."
    ),
) -> None:
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    from graphslam.app.progress import show_progress

    # bars on a terminal, periodic lines in a batch job's log (graphslam.app.progress)
    if show_progress("off" if quiet else "auto", interval_s=progress_interval) == "bar":
        from tqdm.contrib.logging import logging_redirect_tqdm

        ctx.with_resource(logging_redirect_tqdm())  # warnings printed above the bars, not through them
    ctx.call_on_close(lambda: show_progress("off"))


@app.command()
def inspect(
    paths: List[Path] = typer.Argument(..., help="Recordings (.mcap) or folders of them."),
    as_json: bool = typer.Option(False, "--json", help="One JSON object per session, then the totals."),
) -> None:
    """Print per-session statistics: steps, scans, distinct APs, duration, walked length, landmarks."""
    from graphslam.core.summary import SurveySummary
    from graphslam.io.mcap_reader import read_survey

    summary = SurveySummary.of(read_survey(paths))
    if as_json:
        for s in summary.sessions:
            typer.echo(json.dumps(s.as_dict()))
        typer.echo(json.dumps({"totals": summary.totals}))
        return
    # the id column is as wide as the longest id: truncated ids (IPIN's differ only at the end) are ambiguous
    w = max([7] + [len(s.session_id) for s in summary.sessions])
    header = f"{'session':<{w}} {'steps':>6} {'scans':>6} {'APs':>5} {'dur s':>8} {'walk m':>8} {'lmks':>5}"
    typer.echo(header)
    for s in summary.sessions:
        typer.echo(
            f"{s.session_id:<{w}} {s.steps:>6} {s.scans:>6} {s.access_points:>5} "
            f"{s.duration_s:>8.1f} {s.walked_m:>8.1f} {s.landmarks:>5}"
        )
    t = summary.totals
    typer.echo(
        f"{t['sessions']} sessions, {t['steps']:,} steps, {t['scans']:,} scans, "
        f"{t['access_points']:,} distinct APs, {t['duration_s'] / 60:.1f} min, "
        f"{t['walked_m'] / 1000:.2f} km walked, {t['landmarks']:,} landmarks"
    )


def _seeds(text: str) -> list[int]:
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
        from graphslam.errors import ConfigError

        raise ConfigError(f"--seeds {text!r}: expected comma-separated integers or ranges, e.g. 0,1,2 or 0-19") from None
    return out


def _config(config: Optional[Path], set_: Optional[List[str]]) -> "GraphSlamConfig":
    """Config file (partial files merge over the defaults) plus ``--set a.b=value`` overrides."""
    import yaml

    from graphslam.config import load_config
    from graphslam.errors import ConfigError

    overrides: dict = {}
    for item in set_ or []:
        key, sep, raw = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE, e.g. wifi.d_min_m=3")
        try:
            value = yaml.safe_load(raw)
        except yaml.YAMLError:
            raise ConfigError(f"--set {item!r}: the value is not valid YAML") from None
        node = overrides
        *parents, leaf = key.split(".")
        for part in parents:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"--set {item!r}: {part} is set to a value, not a section, by another --set")
        node[leaf] = value
    return load_config(config, overrides)


@app.command()
def survey(
    paths: List[Path] = typer.Argument(..., help="Recordings (.mcap) or folders of them."),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder (created)."),
    config: Optional[Path] = typer.Option(None, "--config", "-c", help="YAML config (see configs/default.yaml)."),
    set_: Optional[List[str]] = typer.Option(None, "--set", help="Override a config value, e.g. wifi.d_min_m=3."),
    rerun: Optional[Path] = typer.Option(None, "--rerun", help="Also log the survey to this .rrd file."),
    floor_plan: Optional[Path] = typer.Option(None, "--floor-plan", help="Image drawn under survey.png and in Rerun."),
    floor_size: Optional[tuple[float, float]] = typer.Option(
        None, "--floor-size", help="W H of the floor plan (m); default: floor_info.json beside the image."
    ),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show progress (--no-progress: as --quiet)."),
    surveyed: bool = typer.Option(
        False, "--surveyed", help="Also write radio_map_surveyed.parquet: fingerprints at ground-truth poses (evaluation)."
    ),
    picture: bool = typer.Option(True, "--picture/--no-picture", help="Write OUT/survey.png (over --floor-plan)."),
    update: Optional[Path] = typer.Option(
        None, "--update", help="A previous survey's OUT folder of this floor: walks solved there start from their "
        "solution and only the new walks' neighbourhood is re-solved (a full re-solve, said in report.json, if "
        "the configuration or a walk changed). OUT may be the same folder.",
    ),
    control_points: Optional[Path] = typer.Option(
        None, "--control-points", help="CSV landmark_id,x,y (site metres): the landmarks of these ids, where a walk "
        "marks them on /landmarks, tie the map to the site frame.",
    ),
) -> None:
    """Align every walk into one frame; write trajectories.csv, aligned.mcap, radio_map.parquet,
    wifi_edges.parquet, report.json, survey_state.npz, the effective config.yaml and survey.png into OUT.
    Walks the data does not link to the main map form components of their own (report.json)."""
    from graphslam.app.survey import run_survey

    cfg = _config(config, set_)
    if not progress:
        from graphslam.app.progress import show_progress

        show_progress("off")
    result = run_survey(
        paths, out, cfg, rerun_path=rerun, floor_plan=floor_plan, floor_size=floor_size, surveyed=surveyed,
        picture=picture, update=update, control_points=control_points,
    )
    r = result.report
    typer.echo(
        f"aligned {r['aligned_sessions']}/{r['sessions']} walks, {r['nodes']:,} poses, "
        f"{r['edges']['wifi']:,} WiFi edges; LM {r['optimizer']['iterations']} iterations "
        f"(converged: {r['optimizer']['converged']}), error {r['optimizer']['initial_error']:.4g} -> "
        f"{r['optimizer']['final_error']:.4g}; {r['timings_s']['total']:.2f} s"
    )
    ev = r.get("evaluation")
    if ev and ev["landmarks"]["n"]:
        lm, raw = ev["landmarks"], ev["landmarks_raw"]
        typer.echo(
            f"landmark error (SE(2) fit, n={lm['n']}): mean {lm['mean_m']:.2f} m, median {lm['median_m']:.2f} m, "
            f"p90 {lm['p90_m']:.2f} m, max {lm['max_m']:.2f} m"
            + (f"; raw dead reckoning mean {raw['mean_m']:.2f} m" if raw["n"] else "")
        )
    _echo_update(r.get("update"))
    typer.echo(f"outputs in {out}")


def _echo_update(u: Optional[dict]) -> None:
    """One line on what `survey --update` did (issue 18)."""
    if not u:
        return
    res = u["resolved"]
    if u["mode"] == "full":
        typer.echo(f"update: full re-solve ({u['reason']})")
        return
    typer.echo(
        f"update: {len(u['new_walks'])} new walks (+{len(u['placed_again'])} placed again); re-solved "
        f"{res['nodes']:,} of {res['of_nodes']:,} poses in {len(res['walks'])} walks ({res['hops']} hops)"
    )


@app.command("survey-batch")
def survey_batch(
    sites_root: Path = typer.Argument(..., help="Folder whose sub-folders of .mcap recordings are floors."),
    out: Path = typer.Option(..., "--out", "-o", help="OUT_ROOT: each floor's outputs go to its relative path here."),
    address: Optional[str] = typer.Option(
        None, "--address", help="Join a running Dask scheduler (e.g. tcp://host:8786) instead of starting a local "
        "cluster; its workers must see SITES_ROOT and OUT_ROOT at the same paths.",
    ),
    workers: Optional[int] = typer.Option(None, "--workers", min=1, help="Local cluster: worker processes (default: cores)."),
    update: bool = typer.Option(
        False, "--update", help="Floors with a previous output in OUT_ROOT are updated in place (survey --update); "
        "the others are surveyed in full.",
    ),
    config: Optional[Path] = typer.Option(None, "--config", "-c", help="YAML config for every floor."),
    set_: Optional[List[str]] = typer.Option(None, "--set", help="Override a config value, e.g. wifi.d_min_m=3."),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Progress bar over floors."),
) -> None:
    """Survey every floor under SITES_ROOT as one task each on Dask; OUT_ROOT/summary.json lists them.
    A floor folder holding control_points.csv is surveyed with it (survey --control-points). A floor
    whose main map holds under half of its walks is "partial". Exit code 0: no floor failed (ok or
    partial); 1: some failed (their error in summary.json); 2: bad arguments."""
    from tqdm import tqdm

    from graphslam.app.batch import run_batch

    cfg = _config(config, set_)
    bar = tqdm(desc="floors", unit="floor", disable=not (progress and sys.stderr.isatty()), file=sys.stderr)
    failed = [0]

    def on_floor(row: object) -> None:
        failed[0] += getattr(row, "status") == "failed"
        bar.update(1)
        bar.set_postfix(failed=failed[0])

    try:
        res = run_batch(sites_root, out, cfg, address=address, workers=workers, update=update, on_floor=on_floor,
                        on_start=lambda n: bar.reset(total=n))
    finally:
        bar.close()
    typer.echo(f"{len(res.rows)} floors: {res.ok} ok, {res.partial} partial, {res.failed} failed in "
               f"{res.seconds:.1f} s; summary in {res.summary}")
    for row in res.rows:
        if row.status == "partial":
            typer.echo(f"partial: {row.floor}: {row.warning}")
        elif row.status != "ok":
            typer.echo(f"failed: {row.floor}: {row.error}")
    if res.failed:
        sys.exit(1)  # not typer.Exit: main() runs click with standalone_mode=False, which returns its code


@app.command()
def evaluate(
    trajectories: Path = typer.Argument(..., help="trajectories.csv written by `graphslam survey`."),
    paths: List[Path] = typer.Argument(..., help="The recordings, with /landmarks or /ground_truth/pose."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Write the evaluation as JSON here."),
    plot: Optional[Path] = typer.Option(None, "--plot", help="Landmark error histogram (PNG, as the paper's fig. 7)."),
    component: int = typer.Option(
        0, "--component", min=0, help="The walks of this component of trajectories.csv (0: the main map); "
        "each component is in a frame of its own, so one fit covers one component.",
    ),
) -> None:
    """Landmark errors after an SE(2) fit, heading alignment and raw-vs-aligned comparison."""
    from graphslam.core.survey.evaluate import evaluate as run_evaluation
    from graphslam.errors import InputError
    from graphslam.io.atomic import atomic_write_json, json_safe
    from graphslam.io.csv_io import read_trajectory_file
    from graphslam.io.mcap_reader import read_survey

    traj = read_trajectory_file(trajectories)
    tracks = traj.of_component(component)
    if not tracks:
        found = sorted(set(traj.components.values()))
        raise InputError(trajectories, f"no walk in component {component} (components in the file: {found})",
                         field="component")
    survey_ = read_survey(paths)
    if not survey_.has_ground_truth:
        raise InputError(", ".join(map(str, paths)), "no /landmarks or /ground_truth/pose to evaluate against")
    ev = run_evaluation(tracks, survey_)
    if out:
        atomic_write_json(out, ev.as_dict())
    if plot:
        from graphslam.viz.plots import landmark_histogram

        landmark_histogram(ev, plot)
    lm, raw = ev.landmarks, ev.landmarks_raw
    summary = {
        "component": component,
        "walks": len(tracks),
        "landmarks": {k: getattr(lm, k) for k in ("n", "mean_m", "median_m", "p90_m", "max_m")},
        "raw_landmarks_mean_m": raw.mean_m,
        "heading_mean_deg": ev.heading_mean_deg,
        "steps_mean_m": ev.steps.mean_m,
    }
    typer.echo(json.dumps(json_safe(summary)))


@app.command()
def simulate(
    scenario: str = typer.Argument(..., help="Scenario: paper, corridor, crowd or museum (see docs/simulator.md)."),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder (created); existing files are replaced."),
    seed: int = typer.Option(0, "--seed", min=0, help="Random seed; same seed, same recordings."),
    size: float = typer.Option(1.0, "--size", help="Multiplies the number of walks (paper --size 12: ~100k steps)."),
    test_walks: int = typer.Option(0, "--test-walks", min=0, help="Extra held-out walks, written to OUT/test/."),
    no_heading: bool = typer.Option(
        False, "--no-heading",
        help="Record no /phone/heading (the phone's azimuth per step); every other value stays the same.",
    ),
) -> None:
    """Simulate a survey and write it as MCAP recordings (one per walk) plus OUT/building.json.

    Walks carry the phone's azimuth on /phone/heading (unless --no-heading), ground truth and
    landmark marks (evaluation only).
    Reading OUT as a folder also finds OUT/test/: pass OUT/*.mcap to keep test walks held out.
    """
    import time

    from graphslam.sim import HeadingModel, SurveyStats, with_overrides
    from graphslam.sim import simulate as run_simulation

    t0 = time.perf_counter()
    chosen = with_overrides(scenario, heading=HeadingModel(enabled=False)) if no_heading else scenario
    sim = run_simulation(chosen, seed=seed, size=size, test_walks=test_walks)
    t_sim = time.perf_counter() - t0
    sim.write(out)
    st = SurveyStats.of(sim.survey)
    typer.echo(
        f"{scenario} seed={seed} size={size:g}: {len(st.walks)} sessions, {st.steps:,} steps, "
        f"{st.scans:,} scans, {len(sim.building.aps)} APs ({st.access_points_heard} heard), "
        f"{st.length_m / 1000:.2f} km, {st.duration_s / 60:.1f} min, {st.marks} landmark marks"
    )
    drifts = ", ".join(f"{w.max_drift_m:.1f}" for w in st.walks[:12]) + (", ..." if len(st.walks) > 12 else "")
    typer.echo(f"max raw drift {st.max_drift_m:.1f} m (per walk: {drifts})")
    if sim.test_sessions:
        tst = SurveyStats.of(sim.test_sessions)
        typer.echo(f"test: {len(tst.walks)} sessions, {tst.steps:,} steps, {tst.scans:,} scans -> {out / 'test'}")
    typer.echo(f"wrote {out} (simulated in {t_sim:.1f} s, total {time.perf_counter() - t0:.1f} s)")


@bench_app.command("accuracy")
def bench_accuracy(
    scenario: str = typer.Argument(..., help="Simulator scenario: paper, corridor, crowd."),
    seeds: str = typer.Option("0,1,2", help="Comma-separated seeds."),
    size: float = typer.Option(1.0, help="Simulator size multiplier."),
    config: Optional[Path] = typer.Option(None, "--config", "-c"),
    set_: Optional[List[str]] = typer.Option(None, "--set", help="Override a config value."),
) -> None:
    """Align simulated surveys; print one JSON line of errors per seed, then the mean over seeds."""
    from graphslam.app.bench import accuracy

    rows = accuracy(scenario, _seeds(seeds), _config(config, set_), size=size)
    for r in rows:
        typer.echo(json.dumps(r))
    keys = ("main", "landmark_mean_m", "landmark_max_m", "heading_mean_deg", "steps_mean_m", "align_s")
    typer.echo(json.dumps({"mean_over_seeds": {k: round(sum(r[k] for r in rows) / len(rows), 3) for k in keys}}))


@bench_app.command("survey")
def bench_survey(
    scenario: str = typer.Argument("paper"),
    seed: int = typer.Option(0),
    runs: int = typer.Option(5, help="End-to-end runs (median reported)."),
    size: float = typer.Option(1.0, help="Simulator size multiplier (scale tests)."),
    config: Optional[Path] = typer.Option(None, "--config", "-c"),
) -> None:
    """Time `graphslam survey` end to end on a simulated survey (fresh process per run); peak memory."""
    from graphslam.app.bench import survey_speed

    typer.echo(json.dumps(survey_speed(scenario, seed, runs=runs, size=size, config=config)))


@bench_app.command("scale")
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
    from graphslam.app.bench_scale import markdown_table, scale
    from graphslam.errors import ConfigError

    try:
        size_list = [float(v) for v in sizes.split(",") if v.strip()]
        run_list = [int(v) for v in runs.split(",") if v.strip()]
    except ValueError:
        raise ConfigError(f"--sizes / --runs: numbers separated by commas, got {sizes!r} / {runs!r}") from None
    if len(run_list) == 1:
        run_list *= len(size_list)
    if not size_list or len(run_list) != len(size_list) or min(run_list) < 1 or min(size_list) <= 0:
        raise ConfigError("--runs: one count >= 1, or one per size; --sizes: positive numbers")
    result = scale(
        scenario, seed, size_list, run_list, baseline=baseline, baseline_max_size=baseline_max_size, config=config,
        progress=lambda msg: typer.echo(msg, err=True),
    )
    typer.echo(json.dumps(result))
    typer.echo(markdown_table(result))


@bench_app.command("update")
def bench_update(
    scenario: str = typer.Argument("paper"),
    seed: int = typer.Option(0),
    size: float = typer.Option(4.0, help="Walks surveyed first, as the simulator's size multiplier."),
    new_fraction: float = typer.Option(0.05, "--new-fraction", help="Then this many more walks arrive (>= 1)."),
    hops: str = typer.Option("0,1,2", help="update.hops values to measure (comma-separated)."),
    runs: int = typer.Option(3, min=1, help="Runs of each variant, alternated (medians reported)."),
) -> None:
    """`survey --update` vs a full re-solve of every walk, end to end in fresh processes (issue 18)."""
    from graphslam.app.bench_update import update_speed

    typer.echo(json.dumps(update_speed(scenario, seed, size=size, new_fraction=new_fraction, hops=_seeds(hops), runs=runs)))


@bench_app.command("batch")
def bench_batch(
    scenario: str = typer.Argument("crowd"),
    floors: int = typer.Option(16, min=1, help="Simulated floors (seeds 0..N-1)."),
    size: float = typer.Option(0.5, help="Simulator size multiplier of each floor."),
    workers: int = typer.Option(2, min=1, help="survey-batch --workers."),
    runs: int = typer.Option(1, min=1, help="Runs of each variant (medians reported)."),
) -> None:
    """`survey-batch` on a local Dask cluster vs the same floors one after another (issue 18)."""
    from graphslam.app.bench_update import batch_speed

    typer.echo(json.dumps(batch_speed(scenario, floors=floors, size=size, workers=workers, runs=runs)))


@bench_app.command("soak")
def bench_soak(
    radio_map: Path = typer.Option(..., "--radio-map", help="Radio map (.parquet) to serve (a copy is served)."),
    minutes: int = typer.Option(60, "--minutes", min=1, help="Minutes of open-loop load (one row each)."),
    load: float = typer.Option(0.8, "--load", help="Fraction of the measured capacity to send."),
    rate: Optional[float] = typer.Option(None, "--rate", min=1.0, help="Requests/s instead of --load x capacity."),
    capacity_s: float = typer.Option(10.0, "--capacity-seconds", min=1.0, help="Closed-loop capacity burst."),
    seed: int = typer.Option(0, "--seed", min=0, help="Seed of the query fingerprints."),
) -> None:
    """Soak `graphslam serve --watch` on 127.0.0.1 (issue 42): capacity, then --load of it for --minutes with a
    map reload every minute; JSON lines: the capacity, one row per minute (requests, errors, p50/p99 ms, server
    RSS), a summary."""
    from graphslam.app.soak import run_soak

    result = run_soak(radio_map, minutes=minutes, load=load, rate=rate, capacity_s=capacity_s, seed=seed,
                      on_row=lambda row: typer.echo(json.dumps(row)))
    typer.echo(json.dumps({"summary": result.summary}))


INDEX_HELP = "kNN search: exact, ivf (approximate inverted file) or auto."
IVF_CLUSTERS_HELP = "IVF: k-means clusters (default ~2 sqrt(N))."
IVF_PROBES_HELP = "IVF: clusters searched per query (default 8)."
METRIC_HELP = (
    "Fingerprint distance: eq9 (the paper's RMS dB difference) or sorensen (Sørensen on powed RSS, "
    "Torres-Sospedra 2015; exact search only)."
)


@bench_app.command("ujiindoorloc")
def bench_ujiindoorloc(
    data_dir: Path = typer.Argument(..., help="Folder with trainingData.csv[.gz] and validationData.csv[.gz]."),
    k: int = typer.Option(7, "--k", min=1, help="Neighbours."),
    weighted: bool = typer.Option(True, "--weighted/--no-weighted", help="Inverse-distance weights, else uniform."),
    min_rssi: float = typer.Option(-95.0, "--min-rssi", help="Drop readings below this (dBm)."),
    missing_dbm: float = typer.Option(-100.0, "--missing-dbm", help="RSS of an AP not heard, in eq. 9 (dBm)."),
    min_common: int = typer.Option(1, "--min-common", min=1, help="Neighbours must share this many APs."),
    repeats: int = typer.Option(5, "--repeats", min=1, help="Timed runs (the median is reported)."),
    index: str = typer.Option("exact", "--index", help=INDEX_HELP + " Default: exact."),
    ivf_clusters: Optional[int] = typer.Option(None, "--ivf-clusters", min=1, help=IVF_CLUSTERS_HELP),
    ivf_probes: Optional[int] = typer.Option(None, "--ivf-probes", min=1, help=IVF_PROBES_HELP),
    metric: str = typer.Option("eq9", "--metric", help=METRIC_HELP),
) -> None:
    """kNN on UJIIndoorLoc (train: trainingData, test: validationData); prints one JSON line."""
    metric = _metric(metric)
    from graphslam.app.uji_bench import run_ujiindoorloc_benchmark

    if index != "exact":
        from graphslam.core.radiomap.ivf import limit_blas_threads

        limit_blas_threads(1)  # the IVF search's small GEMMs (see limit_blas_threads)

    r = run_ujiindoorloc_benchmark(
        data_dir, k=k, weighted=weighted, min_rssi_dbm=min_rssi, missing_dbm=missing_dbm,
        min_common=min_common, repeats=repeats, index=index, ivf_clusters=ivf_clusters, ivf_probes=ivf_probes,
        metric=metric,
    )
    typer.echo(json.dumps(r.as_dict()))


@app.command()
def locate(
    query_paths: List[Path] = typer.Argument(..., help="Query recordings (.mcap) or folders of them."),
    radio_map: Path = typer.Option(..., "--radio-map", help="Radio map (.parquet)."),
    out: Path = typer.Option(..., "--out", help="Output CSV: session_id,t_ns,x,y,score,spread,..."),
    k: int = typer.Option(3, "--k", min=1, help="Neighbours."),
    weighted: bool = typer.Option(True, "--weighted/--no-weighted", help="Inverse-distance weights, else uniform."),
    min_common: int = typer.Option(1, "--min-common", min=1, help="Neighbours must share this many APs."),
    rerun: Optional[Path] = typer.Option(
        None, "--rerun", help="Also log the answers (and the truth, if the queries carry /ground_truth/pose) to this .rrd."
    ),
    site_from_map: Optional[tuple[float, float, float]] = typer.Option(
        None, "--site-from-map", help="X Y THETA placing the map frame in the site frame (e.g. report.json's "
        "evaluation.site_from_aligned), for the truth overlay."
    ),
    index: str = typer.Option("exact", "--index", help=INDEX_HELP + " Default: exact."),
    metric: str = typer.Option("eq9", "--metric", help=METRIC_HELP),
    picture: bool = typer.Option(True, "--picture/--no-picture", help="Also write OUT with .png: answers (and truth)."),
) -> None:
    """Locate every /wifi/scan of the query sessions by kNN against a radio map."""
    metric = _metric(metric)
    from graphslam.app.locate import locate_files

    run = locate_files(
        radio_map, query_paths, out=out, k=k, weighted=weighted, min_common=min_common, index=index, metric=metric
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
    shown = {}
    if picture:
        from graphslam.app.pictures import write_locate_picture

        shown["picture"] = str(write_locate_picture(run, radio_map, query_paths, out.with_suffix(".png"), site_from_map))
    typer.echo(json.dumps(run.as_dict() | shown))


@app.command()
def serve(
    radio_map: Path = typer.Option(..., "--radio-map", help="Radio map (.parquet)."),
    host: str = typer.Option("127.0.0.1", "--host", help="Bind address (loopback by default)."),
    port: int = typer.Option(8077, "--port", min=0, max=65535, help="TCP port."),
    k: int = typer.Option(3, "--k", min=1, help="Neighbours."),
    weighted: bool = typer.Option(True, "--weighted/--no-weighted", help="Inverse-distance weights, else uniform."),
    min_common: int = typer.Option(1, "--min-common", min=1, help="Neighbours must share this many APs."),
    max_batch: int = typer.Option(10_000, "--max-batch", min=1, help="Most fingerprints per request."),
    max_body_bytes: int = typer.Option(32 * 1024 * 1024, "--max-body-bytes", min=1024, help="Largest request body."),
    index: str = typer.Option("auto", "--index", help=INDEX_HELP + " Default: auto (IVF from 5,000 references)."),
    ivf_clusters: Optional[int] = typer.Option(None, "--ivf-clusters", min=1, help=IVF_CLUSTERS_HELP),
    ivf_probes: Optional[int] = typer.Option(None, "--ivf-probes", min=1, help=IVF_PROBES_HELP),
    workers: int = typer.Option(1, "--workers", min=1, help="Server processes (each loads the map; ~1 core each)."),
    search_processes: Optional[int] = typer.Option(
        None, "--search-processes", min=0,
        help="Forked search workers sharing the map; batches of 64+ fingerprints are split over them. "
        "0 = search in the server process. Default: min(2, cores), 0 with --workers > 1.",
    ),
    log_level: str = typer.Option(
        "info", "--log-level", help="critical, error, warning, info (one access line per request), debug, trace."
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
    watch_interval: float = typer.Option(1.0, "--watch-interval", min=0.05, help="--watch: seconds between checks."),
    metric: str = typer.Option("eq9", "--metric", help=METRIC_HELP),
) -> None:
    """Serve kNN positioning over HTTP (POST /v1/locate, GET /v1/radio-map, GET /healthz, /openapi.json, /docs)."""
    metric = _metric(metric)
    from graphslam.service.server import serve as serve_map

    serve_map(
        radio_map, host=host, port=port, k=k, weighted=weighted, min_common=min_common,
        max_batch=max_batch, max_body_bytes=max_body_bytes, index=index, ivf_clusters=ivf_clusters,
        ivf_probes=ivf_probes, workers=workers, search_processes=search_processes, log_level=log_level.lower(),
        token=token, metric=metric,
        watch=watch_interval if watch else None,
    )


@app.command()
def view(
    out_dir: Path = typer.Argument(..., help="A finished `graphslam survey --out` folder."),
    recordings: Optional[List[Path]] = typer.Option(
        None, "--recordings", "-r", help="The survey's .mcap files or folders (repeat): adds raw walks and landmarks."
    ),
    save: Optional[Path] = typer.Option(None, "--save", help="Write the Rerun recording to this .rrd file."),
    serve: bool = typer.Option(False, "--serve", help="Serve it in Rerun's web viewer on 127.0.0.1 (Ctrl-C stops)."),
    spawn: bool = typer.Option(False, "--spawn", help="Open it in the native Rerun viewer (needs a display)."),
    floor_plan: Optional[Path] = typer.Option(None, "--floor-plan", help="PNG shown under everything."),
    floor_size: Optional[tuple[float, float]] = typer.Option(None, "--floor-size", help="W H of the floor plan (m)."),
    web_port: int = typer.Option(9090, "--web-port", help="HTTP port of the web viewer (--serve)."),
    grpc_port: int = typer.Option(9876, "--grpc-port", help="gRPC port of the web viewer's data server (--serve)."),
) -> None:
    """Show a finished survey in Rerun: save an .rrd, serve it on the web viewer, or open the native viewer."""
    import tempfile

    from graphslam.errors import ConfigError
    from graphslam.viz.rerun_log import require_display, serve_rrd, spawn_viewer, write_survey_view

    if not (save or serve or spawn):
        raise ConfigError("choose at least one of --save FILE.rrd, --serve, --spawn")
    if spawn:
        require_display()
    target = save or Path(tempfile.mkdtemp(prefix="graphslam-view-")) / "survey.rrd"
    result = write_survey_view(
        out_dir, target, recordings=recordings or (), floor_plan=floor_plan, floor_size=floor_size
    )
    typer.echo(f"wrote {result.path} ({result.path.stat().st_size / 1e6:.1f} MB, {len(result.counts)} entities)")
    if spawn:
        spawn_viewer(result.path)
        typer.echo("opened the Rerun viewer")
    if serve:
        server = serve_rrd(result.path, web_port=web_port, grpc_port=grpc_port)
        typer.echo(f"serving {result.path} at {server.url} (Ctrl-C stops)")
        server.wait()


@app.command()
def plot(
    out_dir: Path = typer.Argument(..., help="A finished `graphslam survey --out` folder."),
    floor_plan: Optional[Path] = typer.Option(None, "--floor-plan", help="Image drawn under everything (site frame)."),
    floor_size: Optional[tuple[float, float]] = typer.Option(
        None, "--floor-size", help="W H of the floor plan (m); default: floor_info.json beside the image."
    ),
    recordings: Optional[List[Path]] = typer.Option(
        None, "--recordings", "-r", help="The survey's .mcap files or folders (repeat): adds the landmark marks."
    ),
    ap: Optional[List[str]] = typer.Option(None, "--ap", help="BSSID to map in radio_map.png (repeat); default: --top-aps."),
    top_aps: int = typer.Option(5, "--top-aps", min=0, help="Map the N most-heard access points."),
    radio_map: bool = typer.Option(True, "--radio-map/--no-radio-map", help="Also draw OUT/radio_map.png."),
) -> None:
    """Redraw OUT/survey.png and draw OUT/radio_map.png (coverage, RSS per access point, fitted APs of
    OUT/ap_models.json when `fit-aps` has run); prints the files written."""
    from graphslam.app.pictures import plot_survey_folder

    files = plot_survey_folder(
        out_dir, floor_plan=floor_plan, floor_size=floor_size, recordings=recordings or (), aps=ap or (),
        top_aps=top_aps, radio_map=radio_map,
    )
    typer.echo(json.dumps({k: str(v) for k, v in files.items()}))


@bench_app.command("fig8")
def bench_fig8(
    scenario: str = typer.Argument("paper"),
    seeds: str = typer.Option("0,1,2", help="Comma-separated seeds."),
    test_walks: int = typer.Option(5, help="Held-out test walks per seed."),
    k: int = typer.Option(3, help="kNN neighbours."),
    plot: Optional[Path] = typer.Option(None, help="Write the CDF plot (PNG) here."),
    config: Optional[Path] = typer.Option(None, "--config", "-c"),
) -> None:
    """The paper's fig. 8: kNN error CDF of held-out walks, crowdsourced vs surveyed radio map."""
    from graphslam.app.bench import fig8

    typer.echo(json.dumps(fig8(scenario, _seeds(seeds), _config(config, None), test_walks=test_walks, k=k, plot=plot)))


@app.command()
def demo(
    out: Path = typer.Option(Path("graphslam-demo"), "--out", "-o", help="Working folder (created)."),
    seed: int = typer.Option(0, help="Simulator seed."),
    rerun: bool = typer.Option(False, "--rerun", help="Also write OUT/survey.rrd."),
) -> None:
    """Simulate the paper's survey, align it, locate held-out walks; print the headline figures."""
    from graphslam.app.demo import run_demo

    r = run_demo(out, seed=seed, rerun=rerun)
    f = r.figures
    typer.echo(f"simulated {f['walks']} walks, {f['steps']:,} steps, {f['km_walked']} km ({f['time_simulate_s']} s)")
    typer.echo(
        f"survey: aligned {f['aligned']} walks in {f['time_survey_s']} s; landmark error mean "
        f"{f['landmark_mean_m']} m, max {f['landmark_max_m']} m (raw dead reckoning: {f['raw_dead_reckoning_landmark_mean_m']} m)"
    )
    typer.echo(
        f"locate: {f['knn_queries']} held-out scans, median error {f['knn_median_m']} m, "
        f"P(error < 10 m) = {f['knn_p_lt_10m']} ({f['time_locate_s']} s)"
    )
    typer.echo(f"outputs in {r.out_dir} (total {f['total_s']} s)")
    typer.echo(json.dumps(f))


@bench_app.command("real")
def bench_real(
    folders: List[Path] = typer.Argument(..., help="Floor folders of recordings with /landmarks, or site folders of floors."),
    floors: Optional[str] = typer.Option(None, help="Comma-separated floor sub-folders of a site (default: all)."),
    config: Optional[Path] = typer.Option(None, "--config", "-c"),
    set_: Optional[List[str]] = typer.Option(None, "--set", help="Override a config value."),
    control_points: str = typer.Option(
        "auto", "--control-points",
        help="auto: also the control_points variant on floors whose folder holds control_points.csv; none: never.",
    ),
    variants: str = typer.Option(
        "headings,no_headings,control_points", "--variants", help="Comma-separated variants to run."
    ),
) -> None:
    """Survey each floor of real recordings per variant (headings: the config as given; no_headings:
    heading.enabled=false; control_points: the floor's control_points.csv, site frame); one JSON line
    per floor and variant (walks in the main map and in components of 5 or more, landmark errors
    after each component's own SE(2) fit, walks over 10 / 15 m, frame, time), then one summary line
    per variant."""
    from graphslam.app.bench import real_floor_rows, real_summary

    rows = []
    for row in real_floor_rows(
        folders, _config(config, set_), floors.split(",") if floors else None,
        variants=[v.strip() for v in variants.split(",") if v.strip()], control_points=control_points,
    ):
        rows.append(row)
        typer.echo(json.dumps(row))
    for line in real_summary(rows):
        typer.echo(json.dumps(line))


@bench_app.command("ilc")
def bench_ilc(
    site_dir: Path = typer.Argument(..., help="An ILC 2.0 site folder with one sub-folder per floor."),
    floors: Optional[str] = typer.Option(None, help="Comma-separated floors (default: all)."),
    config: Optional[Path] = typer.Option(None, "--config", "-c"),
    set_: Optional[List[str]] = typer.Option(None, "--set", help="Override a config value."),
) -> None:
    """Align each real ILC floor; one JSON line per floor with waypoint errors (SE(2) fit) and time."""
    from graphslam.app.bench import ilc_floors

    for row in ilc_floors(site_dir, _config(config, set_), floors.split(",") if floors else None):
        typer.echo(json.dumps(row))


@app.command("fit-aps")
def fit_aps(
    radio_map: Path = typer.Option(..., "--radio-map", help="Radio map (.parquet)."),
    out: Optional[Path] = typer.Option(None, "--out", help="AP models JSON (default: ap_models.json beside the map)."),
    min_readings: int = typer.Option(20, "--min-readings", min=5, help="Fit only APs heard this often."),
) -> None:
    """Fit position, P0 and gamma of every often-heard AP of a radio map (robust least squares)."""
    from graphslam.core.tracking.apmodel import ApFitConfig, ApModels
    from graphslam.io.apmodel_io import write_ap_models
    from graphslam.io.radiomap_io import read_radio_map

    rm = read_radio_map(radio_map)
    models = ApModels.fit(rm, ApFitConfig(min_readings=min_readings))
    path = write_ap_models(models, out or radio_map.with_name("ap_models.json"), radio_map=rm)
    reasons: dict[str, int] = {}
    for u in models.unfitted:
        key = u.reason.split(" (")[0]
        reasons[key] = reasons.get(key, 0) + 1
    typer.echo(json.dumps({"out": str(path), "fitted": len(models.fitted), "unfitted": len(models.unfitted), "reasons": reasons}))


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
    knn_metric = _metric(knn_metric, "--knn-metric")
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


@bench_app.command("filters")
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
    from graphslam.app.bench import filters_cart
    from graphslam.core.radiomap.ivf import limit_blas_threads

    limit_blas_threads(1)

    res = filters_cart(
        _seeds(seeds), shadowing_db=shadowing_db, plot_dir=plot_dir, smoothers=_smoothers(smoothers),
        lags=_lags(lags), window_s=window, restart_every=restart_every, shadowing=_shadowing(shadowing),
    )
    typer.echo(json.dumps(res))


@bench_app.command("tracking")
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
    from graphslam.app.bench import tracking_paper
    from graphslam.core.radiomap.ivf import limit_blas_threads

    limit_blas_threads(1)
    res = tracking_paper(
        scenario, _seeds(seeds), _config(config, None), test_walks=test_walks, smoothers=_smoothers(smoothers),
        knn_fixes=knn_fixes, lags=_lags(lags),
    )
    typer.echo(json.dumps(res))


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
        _lags(lags), [f for f in filters.split(",") if f.strip()], _smoothers(smoothers)
    )
    area = floor_plan_area(folder, floor_plan)
    res = tracking_real(
        folder, _config(config, set_), variants, maps=[m for m in maps.split(",") if m.strip()], folds=folds, seed=seed,
        area=area,
    )
    typer.echo(json.dumps(res))


# --- UWB (Paper 003, issue 15): the seven-tag experiment, the survey with ranges, tracking ---


@bench_app.command("uwb")
def bench_uwb(
    seeds: str = typer.Option("0-99", help="Seeds of the seven-tag runs (e.g. 0-99)."),
    plot_dir: Optional[Path] = typer.Option(None, help="Write uwb_fig8.png and uwb_zones.png (first seed) here."),
    per_seed: bool = typer.Option(False, "--per-seed", help="Also print one JSON line per seed."),
) -> None:
    """Paper 003's experiment simulated: collisions, slots per tag per cycle, clock offsets, EKF error per zone/type."""
    from graphslam.app.uwb_bench import zones_benchmark

    rows, agg = zones_benchmark(_seeds(seeds), plot_dir=plot_dir)
    _echo_rows(rows if per_seed else [], agg)


@bench_app.command("uwb-survey")
def bench_uwb_survey(
    seeds: str = typer.Option("0-4", help="Seeds of the simulated crowd (12 walkers, 5-8 min, all at once)."),
    anchors: str = typer.Option("2,3,4", help="Anchor counts to run (0: peer ranges only, reference-walk frame)."),
    config: Optional[Path] = typer.Option(None, "--config", "-c"),
    set_: Optional[List[str]] = typer.Option(None, "--set", help="Override a config value."),
    per_seed: bool = typer.Option(False, "--per-seed", help="Also print one JSON line per (anchors, seed)."),
) -> None:
    """A crowd surveying together with UWB: site-frame error, vs WiFi only, with NLOS ranges."""
    from graphslam.app.uwb_bench import survey_benchmark

    rows, agg = survey_benchmark(_seeds(seeds), _seeds(anchors), _config(config, set_))
    _echo_rows(rows if per_seed else [], agg)


@app.command("simulate-uwb")
def simulate_uwb(
    scenario: str = typer.Argument(..., help="zones (the paper's seven tags) or crowd (walkers surveying together)."),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder (created); one .mcap per tag / walker."),
    seed: int = typer.Option(0, "--seed", min=0),
    anchors: int = typer.Option(4, "--anchors", min=0, max=4, help="crowd: anchors in the corridors (0-4)."),
    nlos: bool = typer.Option(False, "--nlos", help="crowd: a third of the ranges NLOS-biased (+0.3-2 m)."),
) -> None:
    """Simulate the UWB network (sync, TDMA, ranging) and write recordings with the /uwb/range stream."""
    from graphslam.errors import ConfigError

    if scenario == "zones":
        from graphslam.sim.uwb.scenarios import simulate_zones

        run = simulate_zones(seed)
        paths, net = run.write(out), run.network
    elif scenario == "crowd":
        from graphslam.sim.uwb.scenarios import CrowdUwb, simulate_crowd

        crowd = simulate_crowd(seed, CrowdUwb(n_anchors=anchors, nlos=nlos))
        paths, net = crowd.write(out), crowd.network
    else:
        raise ConfigError(f"unknown UWB scenario {scenario!r}; known: crowd, zones")
    typer.echo(json.dumps({"out": str(out), "files": len(paths), "ranges": int(len(net.ranges.t_s)),
                           "cycles": len(net.cycles), "nlos_fraction": round(float(net.ranges.nlos.mean()), 4)}))


@app.command("track-uwb")
def track_uwb(
    sessions: List[Path] = typer.Argument(..., help="Recordings with /uwb/range (.mcap) or folders of them."),
    out: Path = typer.Option(..., "--out", help="Output CSV: one row per slot and step (t_ns, x, y, covariance, update)."),
    slot_gap_s: float = typer.Option(0.02, "--slot-gap", min=0.0, help="Ranges closer than this form one slot (s)."),
    at_steps: bool = typer.Option(True, "--at-steps/--slots-only", help="Also report at every step time."),
) -> None:
    """Track UWB tags with the paper's collaborative EKF (Paper 003, IV-C): trilateration, anchor and neighbour ranges."""
    from graphslam.app.uwb_track import track_uwb_files

    run = track_uwb_files(sessions, out=out, slot_gap_s=slot_gap_s, at_steps=at_steps)
    typer.echo(json.dumps(run.as_dict()))


def _echo_rows(rows: list[dict], last: dict) -> None:
    """One JSON line per row, then the aggregate."""
    for r in rows:
        typer.echo(json.dumps(r))
    typer.echo(json.dumps(last))


def _lags(text: str) -> list[float]:
    """'0,1,2': fixed-lag latencies in s (finite, >= 0)."""
    try:
        lags = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        lags = [math.nan]
    if not all(math.isfinite(v) and v >= 0 for v in lags):
        from graphslam.errors import ConfigError

        raise ConfigError(f"--lags: {text!r} is not a comma-separated list of latencies >= 0 (s), e.g. 0,1,2")
    return lags


def _metric(text: str, option: str = "--metric") -> str:
    """A kNN fingerprint distance (``KnnConfig.metric``), checked before any file is read."""
    from graphslam.core.radiomap.knn import METRICS
    from graphslam.errors import ConfigError

    if text not in METRICS:
        raise ConfigError(f"{option}: {text!r} is not one of {', '.join(METRICS)}")
    return text


def _shadowing(text: str) -> tuple[float, float] | None:
    """'0.5,3': share of the RSSI variance in (0, 1) and correlation distance > 0 (m); '' for none."""
    if not text.strip():
        return None
    try:
        share, corr = (float(v) for v in text.split(","))
    except ValueError:
        share = corr = math.nan
    if not (0.0 < share < 1.0 and math.isfinite(corr) and corr > 0):
        from graphslam.errors import ConfigError

        raise ConfigError(f"--shadowing: {text!r} is not SHARE,CORR_M with 0 < SHARE < 1 and CORR_M > 0, e.g. 0.5,3")
    return share, corr


def _smoothers(text: str) -> list[str]:
    from graphslam.core.tracking.smoother import SMOOTH_METHODS

    names = [v.strip() for v in text.split(",") if v.strip()]
    bad = [v for v in names if v not in SMOOTH_METHODS]
    if bad:
        from graphslam.errors import ConfigError

        raise ConfigError(f"--smoothers: unknown smoother {bad[0]!r}; use {', '.join(SMOOTH_METHODS)}")
    return names


def _hoist_quiet(argv: list[str]) -> list[str]:
    """``graphslam survey ... --quiet`` means ``graphslam --quiet survey ...``: --quiet/-q is a
    root option (every command has progress), but users put it after the command."""
    end = argv.index("--") if "--" in argv else len(argv)
    flags = [a for a in argv[:end] if a in ("--quiet", "-q")]
    return flags + [a for a in argv[:end] if a not in ("--quiet", "-q")] + argv[end:]


def _one_line(text: str) -> str:
    return " ".join(line.strip() for line in str(text).splitlines() if line.strip())


def _fail(message: str) -> None:
    typer.echo(f"error: {_one_line(message)}", err=True)
    sys.exit(EXIT_ERROR)


def _usage_message(e: Exception) -> str:
    """One line for a click usage error: where, what, and where to read more."""
    ctx = getattr(e, "ctx", None)
    where = ctx.command_path if ctx is not None else "graphslam"
    return f"{where}: {e.format_message()} (see '{where} --help')"  # type: ignore[attr-defined]


# typer >= 0.2x bundles its own click (typer._click), older typer uses click itself: the base class of
# typer.BadParameter is the ClickException in use either way (catching click's would miss typer's).
_CLICK_EXCEPTION: type[Exception] = next(c for c in typer.BadParameter.__mro__ if c.__name__ == "ClickException")


def main(argv: Optional[list[str]] = None) -> None:
    """Console entry point: run the app; a ``GraphSlamError`` or a usage error (unknown command or
    option, missing or malformed argument, no arguments) becomes one line on stderr and exit 2."""
    try:
        code = app(args=_hoist_quiet(sys.argv[1:] if argv is None else argv), prog_name="graphslam", standalone_mode=False)
    except GraphSlamError as e:
        _fail(str(e))
    except _CLICK_EXCEPTION as e:
        _fail(_usage_message(e))
    except typer.Abort:
        typer.echo("aborted", err=True)
        sys.exit(1)
    except KeyboardInterrupt:
        typer.echo("interrupted", err=True)
        sys.exit(130)
    if isinstance(code, int) and code:  # typer.Exit(code) returns its code without standalone mode
        sys.exit(code)


def entry() -> None:
    """The ``graphslam`` script and ``python -m graphslam``: :func:`main`, then :func:`_exit_now`."""
    code: object = 0
    _defer_numpy_extras()
    try:
        main()
    except SystemExit as e:
        code = e.code
    _exit_now(code)


# numpy submodules that numpy itself loads on first use and no survey uses (numpy.ma is not among
# them: pyarrow loads it anyway, so deferring it would only move its import into a request thread).
_DEFERRED_NUMPY_MODULES = ("numpy.f2py", "numpy.ctypeslib", "numpy.polynomial", "numpy.testing")


def _defer_numpy_extras() -> None:
    """scipy's array-API layer (``scipy._lib.array_api_compat.numpy``, imported with scipy.sparse)
    does ``from numpy import *``, which imports every submodule numpy keeps lazy — f2py (and,
    through it, charset_normalizer), ctypeslib, polynomial, testing: ~0.1 s, a fifth of a
    survey's start-up (docs/benchmarks.md, issue 16). Registered first as lazy modules (the
    standard library's ``importlib.util.LazyLoader``) they are executed on first attribute access
    instead, which no survey makes. Console process only (library users and tests are untouched),
    and only for modules not yet imported."""
    import importlib.util

    import numpy

    for name in _DEFERRED_NUMPY_MODULES:
        if name in sys.modules:
            continue
        spec = importlib.util.find_spec(name)
        if spec is None or spec.loader is None:
            continue
        spec.loader = importlib.util.LazyLoader(spec.loader)
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
        setattr(numpy, name.rpartition(".")[2], module)  # else numpy's __getattr__ imports it again


def _exit_now(code: object) -> None:
    """Exit as the interpreter would — non-daemon threads joined, exit handlers run (logging,
    multiprocessing, temporary folders, Rerun), stdout and stderr flushed — but without tearing
    down every module (numpy, scipy, GTSAM, pyarrow, ...): that took ~0.2 s of a 1.7-s survey
    (docs/benchmarks.md, issue 16). Under a profiler or tracer (cProfile, coverage) the normal exit,
    so that they write their results."""
    status = 0 if code is None else code if isinstance(code, int) else 1
    if not isinstance(code, (int, type(None))):
        print(code, file=sys.stderr)  # sys.exit("message"), as the interpreter prints it
    if sys.getprofile() is not None or sys.gettrace() is not None:
        sys.exit(status)
    import atexit
    import os
    import threading

    for t in threading.enumerate():
        if t is not threading.main_thread() and not t.daemon:
            t.join()
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe (`| head`) or stream: nothing more to say
            pass
    os._exit(status & 0xFF)


if __name__ == "__main__":
    entry()
