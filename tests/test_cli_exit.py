"""The console entry (issue 16): a fast exit (what the interpreter's exit does, minus the teardown),
numpy's rarely used submodules deferred until used."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import graphslam
from graphslam import cli


def _python(code: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=120)


def test_exit_joins_threads_runs_handlers_and_flushes_buffered_output() -> None:
    p = _python("""
        import atexit, sys, threading, time
        from graphslam import cli
        atexit.register(lambda: print("handler ran"))
        def late():
            time.sleep(0.3)
            print("thread done")
        threading.Thread(target=late).start()
        sys.stdout.write("buffered, not flushed; ")
        sys.argv = ["graphslam", "--version"]
        cli.entry()
        print("never reached")
    """)
    assert p.returncode == 0, p.stderr
    assert p.stdout.startswith("buffered, not flushed; ") and graphslam.__version__ in p.stdout
    assert p.stdout.index("thread done") < p.stdout.index("handler ran")
    assert "never reached" not in p.stdout


@pytest.mark.parametrize(("code", "status", "stderr"), [(None, 0, ""), (2, 2, ""), ("boom", 1, "boom\n")])
def test_exit_status_is_the_interpreters(code: object, status: int, stderr: str) -> None:
    p = _python(f"from graphslam import cli; cli._exit_now({code!r})")
    assert (p.returncode, p.stderr) == (status, stderr)


def test_module_entry_keeps_the_exit_code_and_one_line_of_a_usage_error() -> None:
    p = subprocess.run([sys.executable, "-m", "graphslam", "survey", "--no-such-option"], capture_output=True,
                       text=True, timeout=120)
    assert p.returncode == 2 and p.stdout == ""
    assert len(p.stderr.strip().splitlines()) == 1 and "--no-such-option" in p.stderr


def test_under_a_tracer_the_exit_is_the_normal_one() -> None:
    """cProfile and coverage write their results at the normal exit: it must happen."""
    previous = sys.gettrace()
    sys.settrace(previous or (lambda *a: None))
    try:
        with pytest.raises(SystemExit) as e:
            cli._exit_now(3)
    finally:
        sys.settrace(previous)
    assert e.value.code == 3


def test_numpy_extras_load_on_first_use_not_at_start() -> None:
    p = _python("""
        import sys
        from graphslam import cli
        cli._defer_numpy_extras()
        import numpy, scipy.sparse  # scipy's array-API layer touches every numpy submodule
        eager = [m for m in ("numpy.f2py.crackfortran", "charset_normalizer", "numpy.polynomial.polynomial",
                             "numpy.testing._private") if m in sys.modules]
        print(eager)
        print(numpy.ma.masked_array([1.0, 2.0], mask=[False, True]).sum(), numpy.polynomial.Polynomial([1, 2])(2.0))
        from numpy.testing import assert_allclose
        assert_allclose(1.0, 1.0)
        lazy = type(numpy.f2py).__name__
        print(lazy, callable(numpy.f2py.run_main), type(numpy.f2py).__name__)  # loaded on that access
    """)
    assert p.returncode == 0, p.stderr
    assert p.stdout.splitlines() == ["[]", "1.0 5.0", "_LazyModule True module"]


def test_a_survey_through_the_console_entry(tmp_path: Path) -> None:
    """The whole command in its own process: deferred numpy modules and the fast exit together."""
    from graphslam.io.mcap_writer import write_session
    from graphslam.sim import simulate

    for s in simulate("paper", seed=0, size=0.25).survey:
        write_session(s, tmp_path / "rec" / f"{s.session_id}.mcap")
    p = subprocess.run([sys.executable, "-m", "graphslam", "survey", str(tmp_path / "rec"), "--out",
                        str(tmp_path / "out"), "--no-progress"], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    assert p.stdout.startswith("main map: ") and (tmp_path / "out" / "report.json").is_file()
    assert (tmp_path / "out" / "radio_map.parquet").is_file() and (tmp_path / "out" / "survey.png").is_file()
