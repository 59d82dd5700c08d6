"""`graphslam bench scale`: growth exponent, the stage table, and its bad-input errors."""

from __future__ import annotations

from pathlib import Path

import pytest

from graphslam.app.bench_scale import growth_exponent, markdown_table
from graphslam.cli import main


def test_growth_exponent_is_the_log_log_slope() -> None:
    sizes = [1, 2, 4, 8, 12]
    assert growth_exponent(sizes, [3.0 * s**1.25 for s in sizes]) == pytest.approx(1.25)
    assert growth_exponent(sizes, [5.0] * 5) == pytest.approx(0.0)


def _side(wall: float) -> dict:
    stages = {"read": 0.4, "align.edges": 0.2, "align.optimise": wall / 4, "write": 0.3, "total": wall - 1.0}
    return {"runs": 3, "wall_s": wall, "cpu_s": wall * 0.9, "startup_s": 1.0, "stages_s": stages, "peak_rss_mb": 200.0,
            "final_error": 27.79, "iterations": 7, "edges": 5392, "landmark_mean_m": 0.677}


def test_table_has_a_column_per_side_and_size_and_the_load() -> None:
    result = {"rows": [{"size": 1.0, "load_1min": [0.5, 0.7], "base": _side(4.0), "new": _side(2.0)},
                       {"size": 12.0, "load_1min": [1.0, 1.2], "new": _side(40.0)}], "growth_exponent_new": 1.2}
    table = markdown_table(result)
    assert table.splitlines()[0] == "| stage (wall s) | size 1 base | size 1 new | size 12 new |"
    assert "| optimise | 1.00 | 0.50 | 10.00 |" in table
    assert "| **wall** | **4.00** | **2.00** | **40.00** |" in table
    assert "size 1: 0.5-0.7" in table and "growth exponent (this checkout): 1.2 " in table


@pytest.mark.parametrize(
    "args, message",
    [(["--sizes", "1,2", "--runs", "3,2,1"], "--runs"), (["--sizes", "one"], "--sizes"), (["--runs", "0"], "--runs")],
)
def test_bad_sizes_or_runs_are_one_line_errors(args: list[str], message: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        main(["bench", "scale", "paper", *args])
    err = capsys.readouterr().err
    assert e.value.code == 2 and message in err and len(err.strip().splitlines()) == 1


def test_a_baseline_that_is_not_a_checkout_is_an_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        main(["bench", "scale", "paper", "--baseline", str(tmp_path)])
    assert e.value.code == 2 and "not a graphslam checkout" in capsys.readouterr().err
