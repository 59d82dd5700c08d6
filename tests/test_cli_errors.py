"""The real console entry point (a subprocess): every usage error and every bad input is one
line on stderr and exit code 2, never a traceback; --version; inf in a config."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import make_session

from graphslam import __version__
from graphslam.io.mcap_writer import write_session


def _entry_point() -> list[str]:
    """The installed console script (what a user runs), else ``python -m graphslam`` (same ``main``)."""
    script = Path(sys.executable).with_name("graphslam")
    return [str(script)] if script.exists() else [sys.executable, "-m", "graphslam"]


def _run_all(cases: dict[str, list[str]], cwd: Path) -> dict[str, subprocess.CompletedProcess]:
    """Run every case at once (each is a fresh interpreter: ~0.5 s of imports)."""
    env = {**os.environ, "COLUMNS": "80"}
    procs = {
        name: subprocess.Popen(
            _entry_point() + args, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        for name, args in cases.items()
    }
    out = {}
    for name, p in procs.items():
        stdout, stderr = p.communicate(timeout=120)
        out[name] = subprocess.CompletedProcess(p.args, p.returncode, stdout, stderr)
    return out


USAGE_ERRORS = {
    "no arguments": ([], "Missing command"),
    "unknown command": (["surveyy", "x"], "No such command 'surveyy'"),
    "misspelt option": (["inspect", "--jsonn", "x.mcap"], "No such option: --jsonn"),
    "missing argument": (["inspect"], "Missing argument"),
    "missing option value": (["survey", "x.mcap", "--out"], "requires an argument"),
    "not an integer": (["simulate", "paper", "--out", "sim", "--seed", "abc"], "Invalid value for '--seed'"),
    "out of range": (["simulate", "paper", "--out", "sim", "--seed", "-1"], "Invalid value for '--seed'"),
    "group without command": (["bench"], "Missing command"),
    # an option's arity: click names no command; the line points to the command's own help
    "option arity": (["survey", "x.mcap", "--out", "o", "--floor-size", "1"],
                     "graphslam survey: Option '--floor-size' requires 2 arguments. (see 'graphslam survey --help')"),
    "option arity in a group": (["-q", "bench", "real", "x", "--floors"], "(see 'graphslam bench real --help')"),
}


def test_usage_errors_and_bad_input_are_one_line_and_exit_2(tmp_path: Path) -> None:
    write_session(make_session("w", 12), tmp_path / "w.mcap")
    (tmp_path / "bad.mcap").write_bytes((tmp_path / "w.mcap").read_bytes()[:-40])  # truncated
    cases = {name: args for name, (args, _) in USAGE_ERRORS.items()}
    cases["truncated recording"] = ["inspect", "bad.mcap"]
    cases["inf in --set"] = ["survey", "w.mcap", "--out", "out", "--set", "wifi.d_max_m=inf", "--no-progress"]
    cases["version"] = ["--version"]
    cases["help"] = ["--help"]
    res = _run_all(cases, tmp_path)
    expected = {name: text for name, (_, text) in USAGE_ERRORS.items()}
    expected["truncated recording"] = "bad.mcap: damaged or truncated MCAP file"
    expected["inf in --set"] = "wifi.d_max_m: Input should be a finite number"
    for name, text in expected.items():
        r = res[name]
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2, (name, r.returncode, r.stderr[-2000:])
        assert len(lines) == 1 and lines[0].startswith("error: ") and text in lines[0], (name, r.stderr[-2000:])
        assert "Traceback" not in r.stderr and r.stdout == "", name
    assert not (tmp_path / "out").exists()  # the config is refused before any work or output
    assert not (tmp_path / "sim").exists()
    assert res["version"].returncode == 0 and res["version"].stdout.strip() == f"graphslam {__version__}"
    assert res["help"].returncode == 0 and "survey" in res["help"].stdout


@pytest.mark.parametrize("value", ["inf", "-inf", ".inf", "1e999", "nan"])
def test_non_finite_config_values_are_refused(tmp_path: Path, value: str, capsys: pytest.CaptureFixture[str]) -> None:
    from graphslam.cli import main

    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"imu:\n  sigma_xy_m: {value}\n")
    with pytest.raises(SystemExit) as e:
        main(["survey", str(tmp_path), "--out", str(tmp_path / "out"), "--config", str(cfg), "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and "imu.sigma_xy_m" in err[0] and "finite" in err[0]
    with pytest.raises(SystemExit) as e:
        main(["survey", str(tmp_path), "--out", str(tmp_path / "out"), "--set", f"wifi.e_max={value}"])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and "wifi.e_max" in err[0]
    assert not (tmp_path / "out").exists()


def test_a_count_of_one_is_singular(tmp_path: Path) -> None:
    write_session(make_session("w", 12), tmp_path / "w.mcap")
    p = subprocess.run(_entry_point() + ["inspect", "w.mcap"], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    totals = p.stdout.strip().splitlines()[-1]
    assert totals.startswith("1 session, 12 steps, "), totals
    assert "1 sessions" not in p.stdout
