"""Survey commands: inspect, survey, survey-batch, evaluate, export, simulate, plot, view, demo."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import List, Optional

import typer

from graphslam import names
from graphslam.cli.base import app
from graphslam.cli.options import choices, config_from_options, plain, require_plots, require_rerun
from graphslam.io.paths import expand_paths

Scenario = choices("Scenario", names.SCENARIOS)
ExportFormat = choices("ExportFormat", names.EXPORT_FORMATS)
ExportFrame = choices("ExportFrame", names.EXPORT_FRAMES)


@app.command()
def inspect(
    paths: List[Path] = typer.Argument(..., help="Recordings (.mcap) or folders of them."),
    as_json: bool = typer.Option(False, "--json", help="One JSON object per session, then the totals."),
) -> None:
    """Print per-session statistics: steps, scans, distinct APs, duration, walked length, landmarks."""
    expand_paths(paths)  # a missing input: one line before numpy & co. are imported
    from graphslam.core.summary import SurveySummary, plural
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
        f"{plural(t['sessions'], 'session')}, {plural(t['steps'], 'step')}, {plural(t['scans'], 'scan')}, "
        f"{plural(t['access_points'], 'distinct AP')}, {t['duration_s'] / 60:.1f} min, "
        f"{t['walked_m'] / 1000:.2f} km walked, {plural(t['landmarks'], 'landmark')}"
    )


@app.command()
def survey(
    paths: List[Path] = typer.Argument(..., help="Recordings (.mcap) or folders of them."),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder (created)."),
    config: Optional[Path] = typer.Option(None, "--config", "-c", help="YAML config (`graphslam config show` prints the defaults)."),
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
    reference_map: Optional[Path] = typer.Option(
        None, "--reference-map", help="A surveyed radio map of the floor in the site frame (CSV fingerprint_id,x,y,"
        "bssid,rssi_dbm, or a radio_map.parquet in the site frame): held fixed, the walks that match it are placed "
        "on it and the main map is in the site frame.",
    ),
) -> None:
    """Align every walk into one frame; write trajectories.csv, aligned.mcap, radio_map.parquet,
    wifi_edges.parquet, report.json, survey_state.npz, the effective config.yaml and survey.png into OUT.
    Walks the data does not link to the main map form components of their own (report.json)."""
    require_rerun(rerun)
    cfg = config_from_options(config, set_)
    expand_paths(paths)  # a missing input: one line before the survey's libraries are imported
    from graphslam.app.survey import run_survey
    from graphslam.app.survey_inputs import SurveyInputs

    if not progress:
        from graphslam.app.progress import show_progress

        show_progress("off")
    inputs = SurveyInputs(
        tuple(paths), out, control_points=control_points, reference_map=reference_map, floor_plan=floor_plan,
        floor_size=floor_size, previous=update, rerun=rerun, picture=picture, surveyed=surveyed,
    )
    result = run_survey(inputs, cfg)
    r = result.report
    from graphslam.core.summary import report_main_map_counts

    typer.echo(
        f"{report_main_map_counts(r)}; frame {r['frame']}; {r['nodes']:,} poses, "
        # the edges in the graph (every state) of the edges proposed: the gates and components leave some out
        f"{sum(r['edges']['wifi_states'].values()):,} of {r['edges']['wifi']:,} WiFi edges in the graph; "
        f"LM {r['optimizer']['iterations']} iterations "
        f"(converged: {r['optimizer']['converged']}){_solver_phrase(r['optimizer'])}, error {r['optimizer']['initial_error']:.4g} -> "
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


def _solver_phrase(opt: dict) -> str:
    """" with cholmod (metis ordering, double precision)": the optimiser report.json names, as the log does."""
    if "solver" not in opt:
        return ""
    from graphslam.core.survey.graph import describe_solver

    return f" with {describe_solver(opt)}"


def _echo_update(u: Optional[dict]) -> None:
    """One line on what `survey --update` did."""
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
    A floor folder holding control_points.csv is surveyed with it (survey --control-points), one holding
    reference_map.csv on that map (survey --reference-map), floor_image.png with floor_info.json under its
    survey.png (survey --floor-plan); each row says its main map's frame. A floor
    whose main map holds under half of its walks is "partial". Exit code 0: no floor failed (ok or
    partial); 1: some failed (their error in summary.json); 2: bad arguments."""
    from tqdm import tqdm

    from graphslam.app.batch import check_sites_root, run_batch  # app.batch: no numpy, no Dask at import
    from graphslam.errors import require_extra

    check_sites_root(sites_root)  # a missing input: one line before Dask (half a second) is imported
    require_extra("distributed", "survey-batch (Dask)")
    from graphslam.core.summary import plural

    cfg = config_from_options(config, set_)
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
    typer.echo(f"{plural(len(res.rows), 'floor')}: {res.ok} ok, {res.partial} partial, {res.failed} failed in "
               f"{res.seconds:.1f} s; summary in {res.summary}")
    for row in res.rows:  # each floor's walks counted as `survey` counts them: the main map first
        if row.status == "failed":
            typer.echo(f"failed: {row.floor}: {row.error}")
        else:
            typer.echo(f"{row.status}: {row.floor}: {row.main_map}; frame {row.frame}"  # as `survey`'s first line
                       + (" (under half of the walks in the main map: its report.json, components and unaligned)"
                          if row.status == "partial" else ""))
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
    require_plots(plot)
    from graphslam.core.summary import plural
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
    recorded = [s.session_id for s in survey_]
    if not set(tracks) & set(recorded):
        raise InputError(
            trajectories, f"none of its {plural(len(tracks), 'walk')} of component {component} (e.g. {next(iter(tracks))!r}) is "
            f"among the {len(recorded)} recorded sessions (e.g. {recorded[0]!r}): evaluate a survey's trajectories "
            "against that survey's recordings")
    ev = run_evaluation(tracks, survey_)
    if not (ev.landmarks.n or ev.steps.n):
        raise InputError(", ".join(map(str, paths)), f"the {plural(len(set(tracks) & set(recorded)), 'walk')} of "
                         f"component {component} found there carry no /landmarks or /ground_truth/pose to evaluate against")
    if out:
        atomic_write_json(out, ev.as_dict())
    if plot:
        from graphslam.viz.plots import landmark_histogram

        landmark_histogram(ev, plot)
    lm, raw = ev.landmarks, ev.landmarks_raw

    def mm(v: float) -> float:  # printed to the millimetre (and the millidegree), as locate's and track's figures
        return round(float(v), 3)

    summary = {
        "component": component,
        "walks": len(tracks),
        "landmarks": {k: getattr(lm, k) if k == "n" else mm(getattr(lm, k)) for k in ("n", "mean_m", "median_m", "p90_m", "max_m")},
        "raw_landmarks_mean_m": mm(raw.mean_m),
        "heading_mean_deg": mm(ev.heading_mean_deg),
        "steps_mean_m": mm(ev.steps.mean_m),
    }
    typer.echo(json.dumps(json_safe(summary)))


@app.command()
def export(
    out_dir: Path = typer.Argument(..., help="A finished `graphslam survey --out` folder."),
    fmt: ExportFormat = typer.Option(
        "tum", "--format", help="tum (timestamp tx ty tz qx qy qz qw, s), kitti (a 3x4 pose matrix per line) or csv "
        "(t_ns,x,y,heading): as evo_traj / evo_ape read them.",
    ),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder (created): one file per walk, <walk>.<format>."),
    frame: ExportFrame = typer.Option(
        "map", "--frame", help="map: as trajectories.csv (report.json's frame); site: the main map placed in the site "
        "frame by report.json's landmark fit (needs ground truth or control points).",
    ),
    component: int = typer.Option(0, "--component", min=0, help="The walks of this component (0: the main map)."),
    recordings: Optional[List[Path]] = typer.Option(
        None, "--recordings", "-r", help="The survey's recordings (repeat): also each walk's /ground_truth/pose, as "
        "<walk>.truth.<format> in the same frame (the reference for evo_ape).",
    ),
) -> None:
    """Write a survey's walks as trajectory files other tools read (evo: TUM, KITTI), one per walk."""
    from graphslam.app.export import export_survey

    run = export_survey(out_dir, out, fmt=plain(fmt), frame=plain(frame), component=component, recordings=recordings or ())
    typer.echo(json.dumps(run.as_dict()))


@app.command()
def simulate(
    scenario: Scenario = typer.Argument(..., help="Scenario (docs/simulator.md)."),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder (created); existing files are replaced."),
    seed: int = typer.Option(0, "--seed", min=0, help="Random seed; same seed, same recordings."),
    size: float = typer.Option(1.0, "--size", help="Multiplies the number of walks (paper --size 12: ~100k steps)."),
    test_walks: int = typer.Option(0, "--test-walks", min=0, help="Extra held-out walks, written to OUT/test/."),
    no_heading: bool = typer.Option(
        False, "--no-heading",
        help="Record no /phone/heading (the phone's azimuth per step); every other value stays the same.",
    ),
    no_magnetic: bool = typer.Option(
        False, "--no-magnetic",
        help="Record no /phone/magnetic (the phone's magnetic field per step); every other value stays the same.",
    ),
) -> None:
    """Simulate a survey and write it as MCAP recordings (one per walk) plus OUT/building.json.

    Walks carry the phone's azimuth on /phone/heading (unless --no-heading), its magnetic field on
    /phone/magnetic (unless --no-magnetic), ground truth and landmark marks (evaluation only).
    Reading OUT as a folder also finds OUT/test/: pass OUT/*.mcap to keep test walks held out.
    """
    import time

    from graphslam.core.summary import plural
    from graphslam.sim import HeadingModel, MagneticModel, SurveyStats, with_overrides
    from graphslam.sim import simulate as run_simulation

    t0 = time.perf_counter()
    scenario = plain(scenario)
    off: dict = {}
    if no_heading:
        off["heading"] = HeadingModel(enabled=False)
    if no_magnetic:
        off["magnetic"] = MagneticModel(enabled=False)
    chosen = with_overrides(scenario, **off) if off else scenario
    sim = run_simulation(chosen, seed=seed, size=size, test_walks=test_walks)
    t_sim = time.perf_counter() - t0
    sim.write(out)
    st = SurveyStats.of(sim.survey)
    typer.echo(
        f"{scenario} seed={seed} size={size:g}: {plural(len(st.walks), 'session')}, {plural(st.steps, 'step')}, "
        f"{plural(st.scans, 'scan')}, {plural(len(sim.building.aps), 'AP')} ({st.access_points_heard} heard), "
        # the recorded steps' length, as `inspect` and `demo` read it back; the true path's beside it
        f"{st.walked_m / 1000:.2f} km walked (true path {st.length_m / 1000:.2f} km), {st.duration_s / 60:.1f} min, "
        f"{st.marks} landmark marks"
    )
    drifts = ", ".join(f"{w.max_drift_m:.1f}" for w in st.walks[:12]) + (", ..." if len(st.walks) > 12 else "")
    typer.echo(f"max raw drift {st.max_drift_m:.1f} m (per walk: {drifts})")
    if sim.test_sessions:
        tst = SurveyStats.of(sim.test_sessions)
        typer.echo(f"test: {plural(len(tst.walks), 'session')}, {plural(tst.steps, 'step')}, {plural(tst.scans, 'scan')} "
                   f"-> {out / 'test'}")
    typer.echo(f"wrote {out} (simulated in {t_sim:.1f} s, total {time.perf_counter() - t0:.1f} s)")


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
    if not (save or serve or spawn):  # before Rerun's and the pictures' imports
        raise ConfigError("choose at least one of --save FILE.rrd, --serve, --spawn")
    require_rerun()
    from graphslam.viz.rerun_log import write_survey_view
    from graphslam.viz.rerun_viewer import require_display, serve_rrd, spawn_viewer

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
def demo(
    out: Path = typer.Option(Path("out/demo"), "--out", "-o", help="Working folder (created)."),
    seed: int = typer.Option(0, "--seed", min=0, help="Random seed of the simulation; same seed, same figures."),
    rerun: Optional[Path] = typer.Option(
        None, "--rerun", help="Also log the survey to this .rrd file, and the located held-out scans beside it "
        "(NAME.locate.rrd).",
    ),
) -> None:
    """Simulate the paper's survey, align it, locate held-out walks; print the headline figures."""
    from graphslam.app.demo import run_demo

    require_rerun(rerun)

    r = run_demo(out, seed=seed, rerun=rerun)
    f = r.figures
    typer.echo(f"simulated {f['walks']} walks, {f['steps']:,} steps, {f['km_walked']} km ({f['time_simulate_s']} s)")
    typer.echo(
        f"survey: {f['main_map']} ({f['time_survey_s']} s); landmark error mean "
        f"{f['landmark_mean_m']} m, max {f['landmark_max_m']} m (raw dead reckoning: {f['raw_dead_reckoning_landmark_mean_m']} m)"
    )
    typer.echo(
        f"locate: {f['knn_queries']} held-out scans, median error {f['knn_median_m']} m, "
        f"P(error < 10 m) = {f['knn_p_lt_10m']} ({f['time_locate_s']} s)"
    )
    typer.echo(f"outputs in {r.out_dir} (total {f['total_s']} s)")
    typer.echo(json.dumps(f))
