"""The optional dependencies (pyproject's extras): a feature used without its extra stops before any
work with one line naming the extra to install, exit code 2; the rest runs without them."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from conftest import make_session
from graphslam.errors import MissingExtraError, require_extra
from graphslam.io.mcap_writer import write_session


def _absent(monkeypatch: pytest.MonkeyPatch, *modules: str) -> None:
    """Import of each of ``modules`` fails as if not installed (None in sys.modules)."""
    for m in modules:
        monkeypatch.setitem(sys.modules, m, None)


def _fails(capsys: pytest.CaptureFixture[str], *args: object) -> str:
    from graphslam.cli import main

    with pytest.raises(SystemExit) as e:
        main([str(a) for a in args])
    err = capsys.readouterr().err
    assert e.value.code == 2, err
    assert len(err.strip().splitlines()) == 1, err
    return err


@pytest.fixture()
def walks(tmp_path: Path) -> Path:
    d = tmp_path / "walks"
    d.mkdir()
    for i in range(2):
        write_session(make_session(f"s{i}", seed=i), d / f"s{i}.mcap")
    return d


def test_require_extra_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    assert require_extra("json", "anything").dumps({}) == "{}"
    _absent(monkeypatch, "matplotlib", "distributed")
    with pytest.raises(MissingExtraError, match=r'plots needs matplotlib.*pip install "graphslam\[plots\]"'):
        require_extra("matplotlib.pyplot", "plots")
    with pytest.raises(MissingExtraError, match=r'graphslam\[batch\]'):
        require_extra("distributed", "survey-batch")


def test_rerun_without_rerun_sdk_is_one_line_before_any_output(monkeypatch, capsys, walks: Path, tmp_path: Path) -> None:
    _absent(monkeypatch, "rerun")
    out = tmp_path / "out"
    err = _fails(capsys, "survey", walks, "--out", out, "--rerun", tmp_path / "s.rrd")
    assert 'pip install "graphslam[rerun]"' in err and not out.exists()
    err = _fails(capsys, "view", out, "--save", tmp_path / "v.rrd")
    assert 'pip install "graphslam[rerun]"' in err
    err = _fails(capsys, "locate", walks, "--radio-map", tmp_path / "none.parquet", "--out", tmp_path / "l.csv",
                 "--rerun", tmp_path / "l.rrd")
    assert 'graphslam[rerun]' in err and "none.parquet" not in err  # checked before the map is read


def test_survey_batch_without_dask_is_one_line(monkeypatch, capsys, tmp_path: Path) -> None:
    _absent(monkeypatch, "distributed", "dask")
    err = _fails(capsys, "survey-batch", tmp_path, "--out", tmp_path / "out", "--no-progress")
    assert 'pip install "graphslam[batch]"' in err and not (tmp_path / "out").exists()


def test_a_plot_without_matplotlib_is_one_line(monkeypatch, capsys, walks: Path, tmp_path: Path) -> None:
    _absent(monkeypatch, "matplotlib")
    err = _fails(capsys, "evaluate", tmp_path / "trajectories.csv", walks, "--plot", tmp_path / "h.png")
    assert 'pip install "graphslam[plots]"' in err and "trajectories.csv" not in err


def test_survey_locate_and_track_need_no_extra(monkeypatch, capsys, walks: Path, tmp_path: Path) -> None:
    # the core commands with rerun, Dask and matplotlib absent (and the survey on its default solver)
    _absent(monkeypatch, "rerun", "distributed", "dask", "matplotlib")
    from graphslam.cli import main

    out = tmp_path / "out"
    main(["-q", "survey", str(walks), "--out", str(out)])
    main(["-q", "locate", str(walks), "--radio-map", str(out / "radio_map.parquet"), "--out", str(tmp_path / "l.csv")])
    capsys.readouterr()
    assert (out / "radio_map.parquet").is_file() and (tmp_path / "l.csv").is_file() and (tmp_path / "l.png").is_file()
