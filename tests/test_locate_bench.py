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
    lines = [json.loads(x) for x in capsys.readouterr().out.strip().splitlines()]
    row, summary = lines[-2], lines[-1]["summary"]
    assert summary["floors"] == 1 and summary["metric"] == "sorensen"
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


def _route_floor(d: Path) -> Path:
    """Three routes of a 200 m corridor, two repetitions each, named as IPIN's files are (leave one
    route out): routes 21 and 22 walk its first 70 m, route 23 its far end, 50 m and more from them."""
    import numpy as np

    from graphslam.core.types import LandmarkMark, PoseTrack, Scan, Session

    aps = np.arange(0.0, 201.0, 8.0)
    rng = np.random.default_rng(0)
    t0 = 1_700_000_000_000_000_000
    for route, (a, b) in {21: (0.0, 70.0), 22: (5.0, 70.0), 23: (120.0, 190.0)}.items():
        for rep in (1, 2):
            xs = np.arange(a, b, 0.7) + rng.uniform(0.0, 0.5)
            y = rng.uniform(-2.0, 2.0)
            t = t0 + np.arange(len(xs), dtype=np.int64) * 500_000_000
            scans = []
            for i in range(0, len(xs), 2):
                rss = -35.0 - 30.0 * np.log10(np.hypot(xs[i] - aps, 6.0 - y)) + rng.normal(0.0, 3.0, len(aps))
                scans.append(Scan(int(t[i]) + 1, {f"02:00:00:00:00:{j:02x}": float(r) for j, r in enumerate(rss) if r > -85}))
            marks = tuple(LandmarkMark(int(t[i]), f"m{i}", float(xs[i]), y) for i in (0, len(xs) // 2, len(xs) - 1))
            s = Session(f"Trial{route}_repetition0{rep}", PoseTrack(t, np.column_stack([xs, np.full(len(xs), y)]),
                        np.zeros(len(xs))), tuple(scans), marks)
            write_session(s, d / f"IPIN2023_T3_TrainingTrial{route}_repetition0{rep}.mcap")
    return d


def test_outside_figures_count_the_scans_far_from_and_near_the_map(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    site = tmp_path / "site"
    (site / "F1").mkdir(parents=True)
    _route_floor(site / "F1")
    # a site folder stands for its floor folders
    assert run_cli(["bench", "locate-real", str(site), "--metrics", "sorensen"]) == 0
    lines = [json.loads(x) for x in capsys.readouterr().out.strip().splitlines()]
    row, summary = lines[0], lines[-1]["summary"]
    assert row["floor"] == str(site / "F1") and row["folds"] == 3  # leave one route out
    out = row["sorensen"]["outside"]
    c = out["counts"]
    # route 23 held out: every scan is far from the map of routes 21-22; routes 21 and 22 cover each other
    assert c["beyond"] > 0 and c["near"] > 0 and c["beyond"] + c["near"] <= c["located"] == row["sorensen"]["located"]
    assert out["flagged_beyond_10m"] >= 0.8 and out["flagged_within_3m"] <= 0.1
    assert out["flagged_beyond_10m"] == round(c["beyond_flagged"] / c["beyond"], 3)
    assert 0.0 <= out["flagged_inside_95_circle"] <= 1.0
    assert summary["outside"]["counts"] == c and summary["floors"] == 1
