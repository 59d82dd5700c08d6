"""Command-line interface. Parses arguments, calls one library function, prints its result.

This is the only place that catches ``GraphSlamError`` (prints one line, exits 2).
"""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path
from typing import List, Optional

import typer

from graphslam.errors import GraphSlamError

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="Factor-graph SLAM for crowdsourced indoor WiFi site survey (foot-mounted IMU + WiFi).",
)
bench_app = typer.Typer(no_args_is_help=True, help="Benchmarks on simulated and real data.")
app.add_typer(bench_app, name="bench")

EXIT_ERROR = 2


@app.callback()
def _root(verbose: bool = typer.Option(False, "--verbose", "-v", help="Log progress at INFO level.")) -> None:
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )


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
    header = f"{'session':<28} {'steps':>6} {'scans':>6} {'APs':>5} {'dur s':>8} {'walk m':>8} {'lmks':>5}"
    typer.echo(header)
    for s in summary.sessions:
        typer.echo(
            f"{s.session_id[:28]:<28} {s.steps:>6} {s.scans:>6} {s.access_points:>5} "
            f"{s.duration_s:>8.1f} {s.walked_m:>8.1f} {s.landmarks:>5}"
        )
    t = summary.totals
    typer.echo(
        f"{t['sessions']} sessions, {t['steps']:,} steps, {t['scans']:,} scans, "
        f"{t['access_points']:,} distinct APs, {t['duration_s'] / 60:.1f} min, "
        f"{t['walked_m'] / 1000:.2f} km walked, {t['landmarks']:,} landmarks"
    )


def main(argv: Optional[list[str]] = None) -> None:
    """Console entry point: run the app, turn ``GraphSlamError`` into one line and exit 2."""
    try:
        app(args=argv, standalone_mode=False)
    except GraphSlamError as e:
        typer.echo(f"error: {e}", err=True)
        sys.exit(EXIT_ERROR)
    except KeyboardInterrupt:
        typer.echo("interrupted", err=True)
        sys.exit(130)
    except Exception as e:  # click's usage errors
        import click

        if isinstance(e, click.exceptions.ClickException):
            e.show()
            sys.exit(e.exit_code)
        if isinstance(e, click.exceptions.Exit):
            sys.exit(e.exit_code)
        if isinstance(e, click.exceptions.Abort):
            sys.exit(1)
        raise


if __name__ == "__main__":
    main()
