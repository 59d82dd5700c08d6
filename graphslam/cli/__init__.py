"""Command-line interface, by command group: ``survey`` (survey, survey-batch, evaluate, export,
simulate, inspect, plot, view, demo), ``radiomap`` (locate, serve, fit-aps), ``tracking`` (track), ``uwb``
(simulate-uwb, track-uwb), ``bench`` (real, locate-real, tracking-real, soak), ``configs`` (config show). Each command parses its arguments,
calls one library function and prints its result; the modules import nothing heavy at start-up.

This is the only place that catches ``GraphSlamError`` (prints one line, exits 2).
"""

from __future__ import annotations

import sys
from typing import Optional

import typer

# each module registers its commands on ``app``, in this order (``--help`` lists them so)
from graphslam.cli import survey, radiomap, tracking, uwb, bench, configs  # noqa: F401, I001
from graphslam.cli.base import EXIT_ERROR, app  # noqa: F401 (app: typer's, for tests and tools)
from graphslam.cli.options import parse_lags, parse_metric, parse_smoothers  # noqa: F401 (public API)
from graphslam.cli.process import _defer_numpy_extras, _exit_now
from graphslam.errors import GraphSlamError

# root options users put after the command name: --quiet/-q (a flag) and --progress-interval (a value)
_ROOT_FLAGS = ("--quiet", "-q")
_ROOT_VALUED = ("--progress-interval",)


def _hoist_quiet(argv: list[str]) -> list[str]:
    """``graphslam survey ... --quiet --progress-interval 5`` means ``graphslam --quiet
    --progress-interval 5 survey ...``: progress is a root option (every command has it), but users
    put it after the command. ``--progress-interval=5`` is moved too; a value-less one at the end is
    left where it is, for click to name it."""
    end = argv.index("--") if "--" in argv else len(argv)
    hoisted: list[str] = []
    rest: list[str] = []
    i = 0
    while i < end:
        a = argv[i]
        if a in _ROOT_FLAGS or a.partition("=")[0] in _ROOT_VALUED and "=" in a:
            hoisted.append(a)
        elif a in _ROOT_VALUED and i + 1 < end:
            hoisted += argv[i : i + 2]
            i += 1
        else:
            rest.append(a)
        i += 1
    return hoisted + rest + argv[end:]


def _command_path(typer_app: typer.Typer, argv: list[str], prog_name: str) -> str:
    """The command an argument list names (``graphslam survey``, ``graphslam bench real``), for an
    error click raises without a context (an option's arity): its help is the one to read."""
    import typer.main

    group = typer.main.get_command(typer_app)
    path = [prog_name]
    args = iter(_hoist_quiet(argv))
    for a in args:
        if a in _ROOT_VALUED:
            next(args, None)
            continue
        if a.startswith("-"):
            continue
        sub = getattr(group, "commands", {}).get(a)
        if sub is None:
            break
        path.append(a)
        group = sub
        if not hasattr(group, "commands"):
            break
    return " ".join(path)


def _one_line(text: str) -> str:
    return " ".join(line.strip() for line in str(text).splitlines() if line.strip())


def _fail(message: str) -> None:
    typer.echo(f"error: {_one_line(message)}", err=True)
    sys.exit(EXIT_ERROR)


def _usage_message(e: Exception, typer_app: typer.Typer | None = None, argv: list[str] | None = None,
                   prog_name: str = "graphslam") -> str:
    """One line for a click usage error: where, what, and where to read more (the command's help)."""
    ctx = getattr(e, "ctx", None)
    where = ctx.command_path if ctx is not None else _command_path(typer_app or app, argv or [], prog_name)
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
        _fail(_usage_message(e, typer_app, argv, prog_name))
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
