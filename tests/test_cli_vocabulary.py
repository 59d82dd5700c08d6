"""One vocabulary across the commands: the same option name and default for the same concept,
choices listed in --help, -o beside every --out, a path after every --rerun, help on every option."""

from __future__ import annotations

import os
import subprocess
import sys
import typing
from typing import Any, Iterator

import pytest
import typer.main

from graphslam import names
from graphslam.cli import app
from graphslam.cli.options import plain


def _commands(group: Any = None, path: tuple[str, ...] = ("graphslam",)) -> Iterator[tuple[str, Any]]:
    group = group or typer.main.get_command(app)
    for name, cmd in group.commands.items():
        if hasattr(cmd, "commands"):
            yield from _commands(cmd, (*path, name))
        else:
            yield " ".join((*path, name)), cmd


def _options(cmd: Any) -> dict[str, Any]:
    return {o: p for p in cmd.params for o in p.opts if o.startswith("--")}


COMMANDS = dict(_commands())


def test_every_option_has_help_and_out_has_o() -> None:
    assert {"graphslam locate", "graphslam serve", "graphslam track", "graphslam export", "graphslam bench real"} <= set(COMMANDS)
    for where, cmd in COMMANDS.items():
        for p in cmd.params:
            assert (getattr(p, "help", None) or "").strip(), (where, p.opts)  # e.g. simulate-uwb --seed had none
        opts = _options(cmd)
        if "--out" in opts:
            assert "-o" in opts["--out"].opts, where
        if "--rerun" in opts:  # a .rrd path everywhere (demo's was a flag)
            assert not opts["--rerun"].is_flag, where
        assert "--k" not in opts and "--knn-metric" not in opts, where
        if "--neighbours" in opts:
            assert "-k" in opts["--neighbours"].opts, where


def test_one_default_per_concept() -> None:
    from graphslam.app.locate import locate_files
    from graphslam.core.radiomap.knn import KnnConfig
    from graphslam.service.config import ServeConfig
    from graphslam.tracking_config import TrackConfig

    # Sørensen, the better distance on every data set measured, everywhere (docs/radio_map.md)
    assert names.DEFAULT_METRIC == "sorensen" and names.DEFAULT_INDEX == "auto"
    locate = _options(COMMANDS["graphslam locate"])
    assert plain(locate["--metric"].default) == "sorensen" and plain(locate["--index"].default) == "auto"
    assert KnnConfig().metric == ServeConfig().metric == TrackConfig().knn_fixes.metric == "sorensen"
    assert KnnConfig().index == ServeConfig().index == "auto"
    defaults = locate_files.__kwdefaults__
    assert defaults["metric"] == "sorensen" and defaults["index"] == "auto" and defaults["k"] == KnnConfig().k
    # serve's and track's options default to None: the configuration's value (the ones above)
    for where in ("graphslam serve", "graphslam track"):
        assert _options(COMMANDS[where])["--metric"].default is None
    # the names the light module lists are the ones the typed models accept
    assert set(typing.get_args(TrackConfig.model_fields["knn_fixes"].annotation.model_fields["metric"].annotation)) == set(names.METRICS)
    assert set(typing.get_args(ServeConfig.model_fields["index"].annotation)) == set(names.INDEXES)
    from graphslam.sim import SCENARIOS

    assert set(SCENARIOS) == set(names.SCENARIOS)


@pytest.mark.parametrize("command, shown", [
    (["locate"], ["<sorensen|eq9>", "<auto|exact|ivf>", "[default: sorensen]", "[default: auto]", "-k"]),
    (["serve"], ["<sorensen|eq9>", "<auto|exact|ivf>", "<critical|error|warning|info|debug|trace>"]),
    (["track"], ["<sorensen|eq9>", "<fixed-lag|ekf|ukf|particle>", "<none|rts|map>", "<mixture|best>", "<snap|prior|both>"]),
    (["simulate"], ["<paper|corridor|crowd|museum>"]),
    (["simulate-uwb"], ["<zones|crowd>"]),
    (["export"], ["<tum|kitti|csv>", "<map|site>"]),
])
def test_help_lists_the_choices(command: list[str], shown: list[str]) -> None:
    env = {**os.environ, "COLUMNS": "250", "NO_COLOR": "1", "TERM": "dumb"}
    p = subprocess.run([sys.executable, "-m", "graphslam", *command, "--help"], capture_output=True, text=True, env=env,
                       timeout=120)
    assert p.returncode == 0, p.stderr
    for text in shown:
        assert text in p.stdout, (command, text, p.stdout)


def test_usage_lines_name_arguments_as_metavariables() -> None:
    """``Usage: graphslam survey [OPTIONS] PATHS...``, not typer's ``{paths}...``; the errors say the same."""
    from typer.testing import CliRunner

    runner = CliRunner()
    for where, cmd in COMMANDS.items():
        res = runner.invoke(app, [*where.split()[1:], "--help"], env={"COLUMNS": "250"}, prog_name="graphslam")
        assert res.exit_code == 0, (where, res.output)
        usage = res.output.splitlines()[0]
        assert usage.startswith(f"Usage: {where} [OPTIONS]") and "{" not in usage and "}" not in usage, usage
        for p in cmd.params:
            if p.param_type_name == "argument":
                assert p.name.upper() in usage, (where, usage)
    assert runner.invoke(app, ["survey", "--help"], prog_name="graphslam").output.startswith("Usage: graphslam survey [OPTIONS] PATHS...\n")
    assert "evaluate [OPTIONS] TRAJECTORIES PATHS..." in runner.invoke(app, ["evaluate", "--help"], prog_name="graphslam").output
    p = subprocess.run([sys.executable, "-m", "graphslam", "survey"], capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and "Missing argument 'PATHS...'" in p.stderr, p.stderr


def test_config_show_prints_the_default_configurations(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """What the README passes to --config, wherever graphslam is installed (configs/ is in the clone only)."""
    from graphslam.config import GraphSlamConfig, load_config
    from graphslam.tracking_config import TrackConfig, load_track_config

    repo = __import__("pathlib").Path(__file__).resolve().parents[1]
    for args, file, load, default in ((["config", "show"], "default.yaml", load_config, GraphSlamConfig()),
                                      (["config", "show", "--track"], "track.yaml", load_track_config, TrackConfig())):
        p = subprocess.run([sys.executable, "-m", "graphslam", *args], capture_output=True, text=True, timeout=120,
                           cwd=tmp_path)
        assert p.returncode == 0, p.stderr
        assert p.stdout == (repo / "configs" / file).read_text()
        (tmp_path / file).write_text(p.stdout)
        assert load(tmp_path / file) == default
