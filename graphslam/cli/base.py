"""The ``graphslam`` typer app, its ``bench`` group and the root options (-v, -q, --progress-interval,
--version). The command modules register their commands on ``app``."""

from __future__ import annotations

import logging
from typing import Any

import typer
from typer.core import TyperCommand


def usage_name(p: Any) -> str:
    """An argument as click names it in a usage line: ``PATHS...`` (required), ``[OUT]`` (optional)."""
    name = (p.metavar or p.name or "").upper()
    return (name if p.required else f"[{name}]") + ("..." if p.nargs != 1 else "")


class Command(TyperCommand):
    """A command whose usage line and errors name its arguments as click does, ``PATHS...``
    (required) or ``[OUT]`` (optional), instead of typer's ``{paths}...`` and ``'paths'``."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        for p in self.params:
            if getattr(p, "param_type_name", "") == "argument":
                p.get_error_hint = lambda *_, p=p: f"'{usage_name(p)}'"  # "Missing argument 'PATHS...'"

    def collect_usage_pieces(self, ctx: Any) -> list[str]:
        pieces = [self.options_metavar] if self.options_metavar else []
        for p in self.get_params(ctx):
            if getattr(p, "param_type_name", "") == "argument":
                pieces.append(usage_name(p))
            else:
                pieces += p.get_usage_pieces(ctx)  # options: none (they are [OPTIONS])
        return pieces


class Typer(typer.Typer):
    """``typer.Typer`` whose commands are ``Command``s (their usage lines as click writes them)."""

    def command(self, name: str | None = None, *, cls: type[TyperCommand] | None = None, **kwargs: Any) -> Any:
        return super().command(name, cls=cls or Command, **kwargs)

# no_args_is_help stays off: typer prints the whole help while raising that error; without it,
# `graphslam` / `graphslam bench` alone is a usage error ("Missing command"), one line like all others.
# rich_markup_mode=None: click's plain-text help; rich's rendering imports ~0.14 s of modules.
app = Typer(
    add_completion=False,
    rich_markup_mode=None,
    help="Factor-graph SLAM for crowdsourced indoor WiFi site survey (foot-mounted IMU + WiFi).",
)


bench_app = Typer(rich_markup_mode=None, help="Evaluate on your own recordings with ground truth (the simulator benchmarks: python -m lab.bench).")
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
