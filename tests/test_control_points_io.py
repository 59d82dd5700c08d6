"""``graphslam survey --control-points FILE``: the reader (graphslam.io.control_points), its bad
files (one line naming the file, line and field, exit code 2, nothing written), the check that a
walk marks at least one id, and the wiring down to ``align`` (also with --update)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from conftest import DATA, needs_data, run_cli

import graphslam.app.survey as app_survey
import graphslam.app.update as app_update
from graphslam.errors import InputError
from graphslam.io.control_points import read_control_points
from graphslam.io.mcap_writer import write_session
from graphslam.sim import simulate


@pytest.fixture(scope="module")
def floor(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("cp") / "floor"
    for s in simulate("corridor", seed=0, size=0.5).survey:
        write_session(s, d / f"{s.session_id}.mcap")
    return d


def marked_ids(floor: Path) -> list[str]:
    from graphslam.io.mcap_reader import read_survey

    return sorted({m.landmark_id for s in read_survey([floor]) for m in s.landmarks})


def test_reads_quoted_ids_with_commas_a_bom_and_blank_lines(tmp_path: Path) -> None:
    f = tmp_path / "cp.csv"
    f.write_text('\ufefflandmark_id,x,y\n"49.461132,11.111006",-10.341,-2.250\n\nL2, 3.5 ,1e1\n', encoding="utf-8")
    assert read_control_points(f) == {"49.461132,11.111006": (-10.341, -2.25), "L2": (3.5, 10.0)}


BAD = {
    "wrong header": ("id,x,y\nL1,1,2\n", "header", None),
    "empty file": ("", "empty file", None),
    "header only": ("landmark_id,x,y\n", "no control point", None),
    "duplicate id": ("landmark_id,x,y\nL1,1,2\nL1,3,4\n", "line 3: duplicate landmark id 'L1'", "landmark_id"),
    "not finite": ("landmark_id,x,y\nL1,inf,2\n", "line 2: 'inf' is not a finite number", "x"),
    "nan": ("landmark_id,x,y\nL1,1,nan\n", "line 2: 'nan' is not a finite number", "y"),
    "not numeric": ("landmark_id,x,y\nL1,1,north\n", "line 2: 'north' is not a number", "y"),
    "empty id": ("landmark_id,x,y\n,1,2\n", "line 2: empty landmark id", "landmark_id"),
    "extra column": ("landmark_id,x,y\nL1,1,2,3\n", "line 2: 4 columns", None),
    "unquoted comma": ("landmark_id,x,y\n49.46,11.11,1,2\n", "line 2: 4 columns", None),
    "missing column": ("landmark_id,x,y\nL1,1\n", "line 2: 2 columns", None),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_a_bad_file_is_one_line_naming_it_and_exit_2_with_nothing_written(
    case: str, floor: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text, problem, field = BAD[case]
    cp = tmp_path / "cp.csv"
    cp.write_text(text, encoding="utf-8")
    with pytest.raises(InputError) as e:
        read_control_points(cp)
    assert e.value.path == str(cp) and e.value.field == field and problem in e.value.problem
    out = tmp_path / "out"
    assert run_cli(["survey", str(floor), "--out", str(out), "--no-progress", "--control-points", str(cp)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {cp}") and problem in err[0], err
    if field:
        assert f"[field {field}]" in err[0]
    assert not out.exists() and [p.name for p in tmp_path.iterdir()] == ["cp.csv"]


def test_a_missing_file_and_ids_no_walk_marks_are_refused(
    floor: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    missing = tmp_path / "nope.csv"
    assert run_cli(["survey", str(floor), "--out", str(out), "--control-points", str(missing)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(missing) in err[0] and "not found" in err[0]
    other = tmp_path / "other_floor.csv"
    other.write_text("landmark_id,x,y\nZ9,1,2\nZ8,3,4\n")
    assert run_cli(["survey", str(floor), "--out", str(out), "--control-points", str(other)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(other) in err[0]
    assert "none of the 2 ids ('Z9', 'Z8') is marked by any walk's /landmarks" in err[0]
    assert not out.exists()


def test_control_points_reach_align_also_with_update(
    floor: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    ids = marked_ids(floor)
    cp = tmp_path / "cp.csv"
    cp.write_text("landmark_id,x,y\n" + "".join(f"{i},{k}.5,-{k}\n" for k, i in enumerate(ids)) + "ZZ,0,0\n")
    want = {i: (k + 0.5, -float(k)) for k, i in enumerate(ids)} | {"ZZ": (0.0, 0.0)}  # an unmarked id is fine
    seen: list[Any] = []

    def spy(real: Any) -> Any:
        def f(*a: Any, **kw: Any) -> Any:
            seen.append(kw.get("control_points"))
            return real(*a, **kw)
        return f

    monkeypatch.setattr(app_survey, "align", spy(app_survey.align))
    out = tmp_path / "out"
    assert run_cli(["survey", str(floor), "--out", str(out), "--no-progress", "--control-points", str(cp)]) == 0
    assert seen == [want]
    monkeypatch.setattr(app_update, "build_problem", spy(app_update.build_problem))
    monkeypatch.setattr(app_update, "align", spy(app_update.align))
    seen.clear()
    assert run_cli(["survey", str(floor), "--out", str(out), "--no-progress", "--update", str(out),
                    "--control-points", str(cp)]) == 0
    assert seen == [want]  # the incremental path's build_problem (or a full re-solve's align) got them


@needs_data("ipin2023/b100_f-2/control_points.csv")
def test_ipins_control_points_read_and_every_id_is_marked_by_a_walk() -> None:
    from graphslam.app.survey import check_control_points_marked
    from graphslam.io.mcap_reader import read_survey

    folder = DATA / "ipin2023" / "b100_f-2"
    cp = read_control_points(folder / "control_points.csv")
    assert len(cp) == 3 and all("," in k for k in cp)  # ids are "lat,lon": quoted in the file
    survey = read_survey([folder])
    check_control_points_marked(cp, survey)
    assert set(cp) <= {m.landmark_id for s in survey for m in s.landmarks}
