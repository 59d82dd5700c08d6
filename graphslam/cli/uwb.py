"""UWB commands (Paper 003): simulate-uwb, track-uwb."""

from __future__ import annotations

import json
from pathlib import Path
from typing import List

import typer

from graphslam import names
from graphslam.cli.base import app
from graphslam.cli.options import choices, plain

UwbScenario = choices("UwbScenario", names.UWB_SCENARIOS)


@app.command("simulate-uwb")
def simulate_uwb(
    scenario: UwbScenario = typer.Argument(
        ..., help="zones (the paper's seven tags in rooms of 4, 3, 2 and 0 anchors: for track-uwb) or crowd (walkers "
        "surveying together, anchors along the corridors: for survey; docs/uwb.md).",
    ),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder (created); one .mcap per tag / walker."),
    seed: int = typer.Option(0, "--seed", min=0, help="Random seed; same seed, same recordings."),
    anchors: int = typer.Option(4, "--anchors", min=0, max=4, help="crowd: anchors in the corridors (0-4)."),
    walkers: int = typer.Option(12, "--walkers", min=2, help="crowd: walkers (the network's time grows with them)."),
    nlos: bool = typer.Option(False, "--nlos", help="crowd: a third of the ranges NLOS-biased (+0.3-2 m)."),
) -> None:
    """Simulate the UWB network (sync, TDMA, ranging) and write recordings with the /uwb/range stream."""
    from graphslam.errors import ConfigError

    scenario = plain(scenario)
    if scenario == "zones":
        from graphslam.sim.uwb.scenarios import simulate_zones

        run = simulate_zones(seed)
        paths, net = run.write(out), run.network
    elif scenario == "crowd":
        from graphslam.sim.uwb.scenarios import CrowdUwb, simulate_crowd

        crowd = simulate_crowd(seed, CrowdUwb(n_walkers=walkers, n_anchors=anchors, nlos=nlos))
        paths, net = crowd.write(out), crowd.network
    else:
        raise ConfigError(f"unknown UWB scenario {scenario!r}; known: crowd, zones")
    typer.echo(json.dumps({"out": str(out), "files": len(paths), "ranges": int(len(net.ranges.t_s)),
                           "cycles": len(net.cycles), "nlos_fraction": round(float(net.ranges.nlos.mean()), 4)}))


@app.command("track-uwb")
def track_uwb(
    sessions: List[Path] = typer.Argument(..., help="Recordings with /uwb/range (.mcap) or folders of them."),
    out: Path = typer.Option(..., "--out", "-o", help="Output CSV: one row per slot and step (t_ns, x, y, covariance, update)."),
    slot_gap_s: float = typer.Option(0.02, "--slot-gap", min=0.0, help="Ranges closer than this form one slot (s)."),
    at_steps: bool = typer.Option(True, "--at-steps/--slots-only", help="Also report at every step time."),
    picture: bool = typer.Option(True, "--picture/--no-picture", help="Also write OUT with .png: the tracks, the truth and the anchors."),
) -> None:
    """Track UWB tags with the paper's collaborative EKF (Paper 003, IV-C): trilateration, anchor and neighbour ranges.
    Prints the error figures when the recordings carry ground truth or landmark marks."""
    from graphslam.app.uwb_track import track_uwb_files

    run = track_uwb_files(sessions, out=out, slot_gap_s=slot_gap_s, at_steps=at_steps, picture=picture)
    typer.echo(json.dumps(run.as_dict()))
