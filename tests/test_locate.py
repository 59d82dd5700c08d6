"""``graphslam locate`` end to end: MCAP query sessions + Parquet radio map -> positions CSV."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from conftest import T0
from graphslam.cli import app
from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.core.types import PoseTrack, Scan, Session
from graphslam.io.mcap_writer import write_session
from graphslam.io.radiomap_io import write_radio_map
from graphslam.app.locate import POSITIONS_HEADER, locate_files

# A corridor: reference fingerprint every 5 m along x, AP i strongest at x = 10 i.
XS = np.arange(0.0, 45.0, 5.0)


def readings_at(x: float) -> dict[str, float]:
    return {f"ap{i}": float(round(-35.0 - 1.2 * abs(x - 10.0 * i))) for i in range(5) if abs(x - 10.0 * i) < 40}


def make_map(tmp_path: Path) -> Path:
    rm = RadioMap.from_scans(
        [readings_at(x) for x in XS], np.column_stack([XS, np.zeros_like(XS)]), session_ids="survey",
        t_ns=T0 + np.arange(len(XS)), frame="aligned", floors=["F1"] * len(XS),
    )
    return write_radio_map(rm, tmp_path / "map.parquet")


def query_session(sid: str, xs: list[float], unknown_last: bool = False) -> Session:
    t = T0 + np.arange(len(xs) + 1, dtype=np.int64) * 1_000_000_000
    steps = PoseTrack(t, np.zeros((len(t), 2)), np.zeros(len(t)))
    scans = [Scan(int(t[i]) + 10, readings_at(x)) for i, x in enumerate(xs)]
    if unknown_last:
        scans.append(Scan(int(t[-1]) + 10, {"not-in-map": -50.0}))
    return Session(sid, steps, tuple(scans))


def test_locate_cli_writes_positions_csv(tmp_path: Path) -> None:
    rm_path = make_map(tmp_path)
    write_session(query_session("q1", [10.0, 20.0]), tmp_path / "q" / "q1.mcap")
    write_session(query_session("q2", [35.0], unknown_last=True), tmp_path / "q" / "q2.mcap")
    out = tmp_path / "out" / "positions.csv"
    res = CliRunner().invoke(
        app, ["locate", "--radio-map", str(rm_path), str(tmp_path / "q"), "--out", str(out), "-k", "1"]
    )
    assert res.exit_code == 0, res.output
    summary = json.loads(res.output.strip().splitlines()[-1])
    picture = str(out.with_suffix(".png"))  # the answers drawn beside the CSV (graphslam.app.pictures)
    assert summary == {"out": str(out), "frame": "aligned", "sessions": 2, "scans": 4, "located": 3, "unlocated": 1,
                       "outside": None, "picture": picture,
                       "uncertainty": None}  # a map of one walk: nothing to calibrate sigma_m on
    with out.open() as fh:
        rows = list(csv.DictReader(fh))
    assert tuple(rows[0].keys()) == POSITIONS_HEADER
    assert list(POSITIONS_HEADER[:4]) == ["session_id", "t_ns", "x", "y"]
    assert [(r["session_id"], float(r["x"]) if r["x"] else None) for r in rows] == [
        ("q1", 10.0), ("q1", 20.0), ("q2", 35.0), ("q2", None),
    ]
    assert rows[0]["t_ns"] == str(T0 + 10) and rows[0]["score"] == "0.0000" and rows[0]["floor"] == "F1"
    assert rows[3]["status"] == "no_known_ap" and rows[3]["y"] == ""
    assert sorted(p.name for p in out.parent.iterdir()) == ["positions.csv", "positions.png"]  # atomic: no temp left


def test_locate_library_k2_interpolates(tmp_path: Path) -> None:
    rm_path = make_map(tmp_path)
    q = write_session(query_session("q", [12.0]), tmp_path / "q.mcap")
    run = locate_files(rm_path, [q], k=2, weighted=False)
    assert run.out is None and run.n_located == 1
    assert run.positions.result.xy[0].tolist() == pytest.approx([12.5, 0.0])  # midpoint of 10 and 15


def test_locate_cli_metric_sorensen_answers_as_the_library(tmp_path: Path) -> None:
    from graphslam.core.radiomap.knn import KnnConfig, KnnLocator
    from graphslam.io.radiomap_io import read_radio_map

    rm_path = make_map(tmp_path)
    queries = [{**readings_at(12.0), "ap0": -60.0}, readings_at(31.0), readings_at(3.0)]
    t = T0 + np.arange(4, dtype=np.int64) * 1_000_000_000
    session = Session("q", PoseTrack(t, np.zeros((4, 2)), np.zeros(4)), tuple(Scan(int(t[i]) + 10, r) for i, r in enumerate(queries)))
    write_session(session, tmp_path / "q.mcap")
    expect = {m: KnnLocator(read_radio_map(rm_path), KnnConfig(k=2, metric=m)).locate(queries) for m in ("eq9", "sorensen")}
    assert not np.allclose(expect["eq9"].xy, expect["sorensen"].xy)  # the metric matters for these queries
    out = tmp_path / "positions.csv"
    res = CliRunner().invoke(app, ["locate", "--radio-map", str(rm_path), str(tmp_path / "q.mcap"), "--out", str(out),
                                   "-k", "2", "--metric", "sorensen", "--no-picture"])
    assert res.exit_code == 0, res.output
    rows = list(csv.DictReader(out.open()))
    got = np.array([[float(r["x"]), float(r["y"])] for r in rows])
    np.testing.assert_allclose(got, expect["sorensen"].xy, atol=1e-3)  # the CSV's 4 decimals
    assert [float(r["score"]) for r in rows] == pytest.approx(expect["sorensen"].score.tolist(), abs=1e-4)


def test_locate_cli_bad_radio_map_is_one_line_error(tmp_path: Path) -> None:
    bad = tmp_path / "map.parquet"
    bad.write_text("nope")
    q = write_session(query_session("q", [10.0]), tmp_path / "q.mcap")
    from graphslam.cli import main

    with pytest.raises(SystemExit) as e:
        main(["locate", "--radio-map", str(bad), str(q), "--out", str(tmp_path / "o.csv")])
    assert e.value.code == 2
    assert not (tmp_path / "o.csv").exists()


def test_locate_rerun_logs_answers_and_truth(tmp_path: Path) -> None:
    from dataclasses import replace

    RrdReader = pytest.importorskip("rerun.chunk", reason="the rerun extra is not installed").RrdReader

    rm_path = make_map(tmp_path)
    q = query_session("q1", [10.0, 20.0, 30.0])
    truth = PoseTrack(q.steps.t_ns, np.column_stack([np.arange(len(q.steps)) * 10.0 + 10.0, np.zeros(len(q.steps))]), q.steps.heading)
    write_session(replace(q, ground_truth=truth), tmp_path / "q" / "q1.mcap")
    rrd = tmp_path / "loc.rrd"
    res = CliRunner().invoke(
        app,
        ["locate", "--radio-map", str(rm_path), str(tmp_path / "q"), "--out", str(tmp_path / "p.csv"), "-k", "1",
         "--rerun", str(rrd)],
    )
    assert res.exit_code == 0, res.output
    paths = set(RrdReader(rrd).store().schema().entity_paths())
    assert {"/world/aligned/locate/estimate", "/world/locate/truth", "/world/locate/error"} <= {str(p) for p in paths}
