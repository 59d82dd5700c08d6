"""Start-up (issue 40): help, the version and argument errors answer without importing the libraries
the work needs (numpy, scipy, GTSAM, pyarrow, the web service's, the pictures')."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

# rich: the help is click's plain text (the app's rich_markup_mode=None); rendering it with rich
# imported ~0.14 s of modules.
HEAVY = ("numpy", "scipy", "gtsam", "pyarrow", "fastapi", "uvicorn", "PIL", "matplotlib", "sklearn", "rerun", "rich")


def _modules_at_exit(argv: list[str]) -> subprocess.CompletedProcess[str]:
    """Run the console entry on ``argv``; stdout's last line: the heavy modules imported by its exit."""
    code = f"""
        import atexit, sys
        atexit.register(lambda: print(sorted(m for m in {HEAVY!r} if m in sys.modules)))
        sys.argv = ["graphslam", *{argv!r}]
        from graphslam.cli import entry
        entry()
    """
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("argv", [
    ["--help"], ["--version"], ["survey", "--help"], ["locate", "--help"], ["serve", "--help"], ["track", "--help"],
])
def test_help_imports_nothing_heavy(argv: list[str]) -> None:
    p = _modules_at_exit(argv)
    assert p.returncode == 0, p.stderr
    assert p.stdout.splitlines()[-1] == "[]"


@pytest.mark.parametrize("argv", [
    ["survey", "{missing}", "--out", "{out}"],
    ["inspect", "{missing}"],
    ["survey", "{missing}"],  # --out missing: click's error
    ["survey", "{missing}", "--out", "{out}", "--set", "wifi.no_such_key=1"],
    ["no-such-command"],
    ["serve", "--radio-map", "{missing}"],
    ["view", "{missing}"],  # none of --save, --serve, --spawn
    ["survey-batch", "{missing}", "--out", "{out}"],
])
def test_argument_errors_import_nothing_heavy(tmp_path: Path, argv: list[str]) -> None:
    args = [a.format(missing=tmp_path / "missing", out=tmp_path / "out") for a in argv]
    p = _modules_at_exit(args)
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1, p.stderr
    assert p.stderr.startswith("error: ")
    assert p.stdout.splitlines() == ["[]"]
    assert not (tmp_path / "out").exists()


def test_a_survey_imports_only_what_it_uses(tmp_path: Path) -> None:
    """A WiFi survey (no UWB, no --rerun, default solver): no GTSAM, web service, Rerun, scikit-learn or
    matplotlib; numpy's extras (f2py, testing, polynomial) registered but never executed."""
    from graphslam.io.mcap_writer import write_session
    from graphslam.sim import simulate

    sim = simulate("paper", seed=0, size=0.5)
    assert len(sim.survey) >= 2  # walks placed against each other: the whole survey path
    for s in sim.survey:
        write_session(s, tmp_path / "rec" / f"{s.session_id}.mcap")
    code = f"""
        import atexit, sys
        unused = ("gtsam", "fastapi", "uvicorn", "rerun", "sklearn", "matplotlib", "graphslam.core.uwb.survey",
                  "numpy.f2py.crackfortran", "charset_normalizer", "numpy.testing._private", "numpy.polynomial.polynomial")
        atexit.register(lambda: print(sorted(m for m in unused if m in sys.modules)))
        sys.argv = ["graphslam", "survey", {str(tmp_path / "rec")!r}, "--out", {str(tmp_path / "out")!r}, "--no-progress"]
        from graphslam.cli import entry
        entry()
    """
    p = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    assert p.stdout.startswith("main map: ") and (tmp_path / "out" / "survey.png").is_file()
    assert p.stdout.splitlines()[-1] == "[]"
