"""A kNN answer's calibrated uncertainty (graphslam.core.radiomap.uncertainty): measured on the map by
leaving its walks out, it must hold about 95 % of new walks' errors in its 95 % circle; it rides with
the survey's radio map and reaches locate's CSV and the service's JSON."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from graphslam.app.tracking_bench import oracle_radio_map
from graphslam.core.radiomap.knn import KnnConfig, KnnLocator
from graphslam.core.radiomap.uncertainty import (
    METADATA_KEY,
    R95,
    KnnUncertainty,
    calibrate_uncertainty,
    map_uncertainty,
    with_uncertainty,
)
from graphslam.sim import simulate


@pytest.fixture(scope="module")
def walks() -> list:
    return [w for w in simulate("corridor", seed=1).survey if len(w.landmarks) >= 2]


def test_the_95_percent_circle_holds_new_walks_errors(walks: list) -> None:
    # map of most walks, queries from the others (truth: their oracle positions); calibrated on the map only
    train, test = walks[:-3], walks[-3:]
    rm = oracle_radio_map(train)
    cfg = KnnConfig(k=3, metric="sorensen")
    u = calibrate_uncertainty(rm, cfg)
    assert u is not None and u.matches(cfg) and 0.9 <= u.coverage <= 0.99
    loc = KnnLocator(rm, cfg)
    res = loc.locate([dict(sc.readings) for w in test for sc in w.scans])
    truth = oracle_radio_map(test).xy
    ok = res.valid
    err = np.linalg.norm(res.xy[ok] - truth[ok], axis=1)
    inside = np.mean(err <= R95 * u.sigma(res.spread[ok]))
    assert 0.85 <= inside <= 0.99, inside
    # the spread matters: a constant sigma of the same median misses more of the far answers
    flat = np.median(u.sigma(res.spread[ok]))
    assert np.mean((err > R95 * flat) & (err <= R95 * u.sigma(res.spread[ok]))) > 0


def test_a_stored_calibration_is_used_only_for_the_same_knn(walks: list, monkeypatch: pytest.MonkeyPatch) -> None:
    import graphslam.core.radiomap.uncertainty as unc

    rm = with_uncertainty(oracle_radio_map(walks[:6]), KnnConfig())
    stored = KnnUncertainty.from_dict(rm.metadata[METADATA_KEY])
    assert stored is not None and stored.matches(KnnConfig())
    calls = []
    monkeypatch.setattr(unc, "calibrate_uncertainty", lambda *a, **k: calls.append(a) or None)
    assert map_uncertainty(rm, KnnConfig()) == stored and not calls  # read, not measured
    map_uncertainty(rm, KnnConfig(k=5))
    assert len(calls) == 1  # another k: measured again
    # a map of one walk has nothing to leave out
    monkeypatch.undo()
    assert calibrate_uncertainty(oracle_radio_map(walks[:1])) is None
    assert KnnUncertainty.from_dict({"metric": "sorensen", "k": 3}) is None


def test_locate_writes_sigma_and_the_service_answers_it(tmp_path: Path, walks: list) -> None:
    import httpx

    from graphslam.app.locate import POSITIONS_HEADER, locate_files
    from graphslam.io.mcap_writer import write_session
    from graphslam.io.radiomap_io import read_radio_map, write_radio_map
    from graphslam.service.server import reloading_app, start_background_server

    rm = with_uncertainty(oracle_radio_map(walks[:-2]))
    write_radio_map(rm, tmp_path / "map.parquet")
    rm = read_radio_map(tmp_path / "map.parquet")  # the calibration survives the file
    u = KnnUncertainty.from_dict(rm.metadata[METADATA_KEY])
    assert u is not None
    q = tmp_path / "q"
    q.mkdir()
    write_session(walks[-1], q / "w.mcap")
    run = locate_files(tmp_path / "map.parquet", [q], out=tmp_path / "pos.csv")
    assert "sigma_m" in POSITIONS_HEADER and run.as_dict()["uncertainty"]["scale"] == round(u.scale, 4)
    rows = list(csv.DictReader(open(tmp_path / "pos.csv")))
    ok = [r for r in rows if r["x"]]
    assert ok and all(abs(float(r["sigma_m"]) - float(u.sigma(np.array([float(r["spread"])]))[0])) < 2e-3 for r in ok)
    readings = dict(walks[-1].scans[3].readings)
    app = reloading_app(tmp_path / "map.parquet", None, k=3, search_processes=0)
    with start_background_server(app) as srv, httpx.Client(base_url=srv.url, timeout=30.0) as c:
        pos = c.post("/v1/locate", json={"readings": readings}).json()["positions"][0]
    assert pos["sigma_m"] == pytest.approx(float(u.sigma(np.array([pos["spread"]]))[0]))


def test_the_survey_radio_map_carries_the_calibration(tmp_path: Path) -> None:
    from conftest import run_cli

    from graphslam.io.mcap_writer import write_session
    from graphslam.io.radiomap_io import read_radio_map

    d = tmp_path / "walks"
    d.mkdir()
    for s in simulate("corridor", seed=0, size=0.5).survey:
        write_session(s, d / f"{s.session_id}.mcap")
    assert run_cli(["survey", str(d), "--out", str(tmp_path / "out"), "--no-progress"]) == 0
    meta = read_radio_map(tmp_path / "out" / "radio_map.parquet").metadata
    u = KnnUncertainty.from_dict(meta[METADATA_KEY])
    assert u is not None and u.matches(KnnConfig()) and u.n > 0
    json.dumps(dict(meta))  # JSON all the way
