"""``graphslam bench locate-real``: held-out walks' scans located on the map of the other walks of
their floor, per metric, with the share of errors inside the answers' 95 % circles."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import run_cli

from graphslam.app.locate_bench import locate_real_rows
from graphslam.errors import ConfigError, InputError
from graphslam.io.mcap_writer import write_session
from graphslam.sim import simulate


@pytest.fixture(scope="module")
def floor(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("floor")
    for s in simulate("corridor", seed=1).survey:
        write_session(s, d / f"{s.session_id}.mcap")
    return d


def test_rows_score_each_metric_and_the_sigma(floor: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert run_cli(["bench", "locate-real", str(floor), "--folds", "3"]) == 0
    row = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert row["folds"] == 3 and row["walks"] >= 6 and row["scans"] > 50
    for m in ("sorensen", "eq9"):
        r = row[m]
        assert r["located"] > 0.9 * row["scans"] and 0 < r["median_m"] <= r["p90_m"]
        assert r["mean_m"] < 10.0  # the corridor's oracle maps locate to a few metres
    assert 0.5 <= row["sorensen"]["inside_95_circle"] <= 1.0 and "inside_95_circle" not in row["eq9"]
    # the circles' width is reported with their coverage: wider than the typical error, not absurd
    assert row["sorensen"]["median_m"] < row["sorensen"]["median_r95_m"] < 20 * row["sorensen"]["p90_m"]
    # the first metric is the one scored for sigma_m
    only = next(locate_real_rows([floor], metrics=["eq9"], folds=3))
    assert set(only) == {"floor", "walks", "folds", "scans", "eq9"} and "inside_95_circle" in only["eq9"]
    assert only["eq9"]["mean_m"] == row["eq9"]["mean_m"]  # the same folds (seeded)


def test_bad_input_is_refused(floor: Path, tmp_path: Path) -> None:
    with pytest.raises(ConfigError):
        next(locate_real_rows([floor], metrics=["cosine"]))
    one = tmp_path / "one"
    one.mkdir()
    write_session(next(iter(simulate("corridor", seed=1).survey)), one / "w.mcap")
    with pytest.raises(InputError, match="fewer than 2 walks"):
        next(locate_real_rows([one]))
    assert run_cli(["bench", "locate-real", str(one)]) == 2
    assert run_cli(["bench", "locate-real", str(floor), "--metrics", "cosine"]) == 2
