"""`python -m lab.bench speed`: the table from a run's figures, the JSON found in a tool's output, a
baseline that is not a checkout."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from graphslam import SolverError
from lab.bench.speed import _json_after, markdown_table, speed

RESULT = Path(__file__).with_name("speed_result.json")  # a smoke run's figures (sizes 0.5, 1 round each)


def test_table_puts_baseline_this_ratio_and_goal_side_by_side() -> None:
    table = markdown_table(json.loads(RESULT.read_text()))
    rows = {line.split(" | ")[0].lstrip("| "): line for line in table.splitlines() if line.startswith("| `")}
    assert rows["`graphslam survey MISSING` (exit 2), CPU"].endswith("| 1.40 s | **0.39 s** | ×3.6 | ≤ 0.3 s |")
    track = next(v for k, v in rows.items() if k.startswith("`graphslam track`"))
    assert "| 84.4 ms | **11.3 ms** | ×7.5 | ≤ 5 ms/step |" in track
    update = next(v for k, v in rows.items() if k.startswith("`survey --update`"))
    assert "1 new walks on 24" in update and "| 107% (2.6 s) | **68% (2.2 s)** |" in update
    assert "baseline /tmp/base40." in table.splitlines()[-1]


def test_json_is_found_between_log_lines_even_when_indented_over_lines() -> None:
    text = "round 0 this: ...\n{\n \"steps\": 3,\n \"median\": {\"a\": 1}\n}\n"
    assert _json_after(text) == {"steps": 3, "median": {"a": 1}}
    assert _json_after('log\n{"x": 1}\n| table |') == {"x": 1}
    with pytest.raises(SolverError, match="no JSON"):
        _json_after("only logs\n")


def test_a_baseline_without_the_package_is_refused(tmp_path: Path) -> None:
    with pytest.raises(SolverError, match="not a graphslam checkout"):
        speed(tmp_path)
