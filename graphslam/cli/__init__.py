"""Command-line interface, by command group: ``survey`` (survey, survey-batch, evaluate, simulate,
inspect, plot, view, demo), ``radiomap`` (locate, serve, fit-aps), ``tracking`` (track), ``uwb``
(simulate-uwb, track-uwb), ``bench`` (real, tracking-real). Each command parses its arguments,
calls one library function and prints its result; the modules import nothing heavy at start-up.

This is the only place that catches ``GraphSlamError`` (prints one line, exits 2).
"""

from __future__ import annotations

import sys
from typing import Optional

import typer

# each module registers its commands on ``app``, in this order (``--help`` lists them so)
from graphslam.cli import survey, radiomap, tracking, uwb, bench  # noqa: F401, I001
from graphslam.cli.base import EXIT_ERROR, app  # noqa: F401 (app: typer's, for tests and tools)
from graphslam.cli.options import parse_lags, parse_metric, parse_smoothers  # noqa: F401 (public API)
from graphslam.cli.process import _defer_numpy_extras, _exit_now
from graphslam.errors import GraphSlamError

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
    run_app(app, sys.argv[1:] if argv is None else argv, "graphslam")


def run_app(typer_app: typer.Typer, argv: list[str], prog_name: str) -> None:
    """Run ``typer_app`` on ``argv`` as the ``graphslam`` command runs (``--quiet`` hoisted, one-line
    errors, exit code 2): also the lab's commands (``python -m lab.bench``)."""
    try:
        code = typer_app(args=_hoist_quiet(argv), prog_name=prog_name, standalone_mode=False)
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
