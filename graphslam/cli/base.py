"""The ``graphslam`` typer app, its ``bench`` group and the root options (-v, -q, --progress-interval,
--version). The command modules register their commands on ``app``."""

from __future__ import annotations

import logging

import typer

# no_args_is_help stays off: typer prints the whole help while raising that error; without it,
# `graphslam` / `graphslam bench` alone is a usage error ("Missing command"), one line like all others.
# rich_markup_mode=None: click's plain-text help; rich's rendering imports ~0.14 s of modules.
app = typer.Typer(
    add_completion=False,
    rich_markup_mode=None,
    help="Factor-graph SLAM for crowdsourced indoor WiFi site survey (foot-mounted IMU + WiFi).",
)


bench_app = typer.Typer(rich_markup_mode=None, help="Evaluate on your own recordings with ground truth (the simulator benchmarks: python -m lab.bench).")
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
