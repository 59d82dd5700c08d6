"""Coverage in every answer: a kNN answer (locate, serve) and a tracked step (track) from a place the
map's walks have not been is flagged outside, with a score, by a test measured on the map itself
(graphslam.core.radiomap.uncertainty: the map's own scans where other walks have been, against the
same scans located without the fingerprints around them), and its sigma says so too."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from graphslam.core.radiomap.knn import KnnConfig, KnnLocator
from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.core.radiomap.uncertainty import (
    METADATA_KEY,
    KnnUncertainty,
    OutsideTest,
    calibrate_uncertainty,
    map_uncertainty,
    with_uncertainty,
)
from graphslam.core.types import PoseTrack, Scan, Session

APS = np.arange(0.0, 201.0, 8.0)  # access points every 8 m along a 200 m corridor, 6 m off its axis
T0 = 1_700_000_000_000_000_000


def _scan(x: float, rng: np.random.Generator, y: float = 0.0) -> dict[str, float]:
    rss = -35.0 - 30.0 * np.log10(np.hypot(x - APS, 6.0 - y)) + rng.normal(0.0, 3.0, len(APS))
    return {f"02:00:00:00:00:{j:02x}": float(r) for j, r in enumerate(rss) if r > -85.0}


@pytest.fixture(scope="module")
def line() -> RadioMap:
    """Five walks over the first 80 m of the corridor: the rest of it is where the map has not walked."""
    rng = np.random.default_rng(0)
    scans, xy, sid, t = [], [], [], []
    for w in range(5):
        for i, x in enumerate(np.arange(0.0, 80.0, 1.0) + rng.uniform(0.0, 1.0)):
            y = (w - 2) * 1.5 + rng.normal(0.0, 0.5)  # across the corridor's width too (the AP models' fit)
            scans.append(_scan(x, rng, y))
            xy.append((x, y))
            sid.append(f"w{w}")
            t.append(T0 + i * 1_000_000_000)
    return RadioMap.from_scans(scans, np.array(xy), session_ids=sid, t_ns=t, frame="site")


def _queries(xs: np.ndarray, seed: int = 1) -> list[dict[str, float]]:
    rng = np.random.default_rng(seed)
    return [_scan(float(x), rng) for x in xs]


NEAR_X = np.arange(2.0, 78.0, 1.0)  # where the map's walks have been
FAR_X = np.arange(100.0, 200.0, 1.0)  # 20 m and more beyond them


def test_answers_from_where_the_map_has_not_walked_are_flagged_and_get_a_wide_sigma(line: RadioMap) -> None:
    u = calibrate_uncertainty(line)
    assert u is not None and isinstance(u.outside, OutsideTest)
    t = u.outside
    assert t.n_covered > 0 and t.n_outside > 0 and t.false_alarm == 0.05 and t.radius_m == 10.0
    assert list(t.covered_db) == sorted(t.covered_db)
    loc = KnnLocator(line)
    near, far = loc.locate(_queries(NEAR_X)), loc.locate(_queries(FAR_X))
    near_out, far_out = u.outside_of(near), u.outside_of(far)
    assert near_out is not None and far_out is not None
    assert near_out.mean() <= 0.1 and far_out.mean() >= 0.8, (near_out.mean(), far_out.mean())
    # the score says the same: outside exactly when above 1 - false_alarm
    for res, flags in ((near, near_out), (far, far_out)):
        s = u.outside_score_of(res)
        assert s is not None and np.all((s >= 0) & (s <= 1)) and np.array_equal(s > 0.95, flags)
    # an outside answer's sigma is at least the outside sigma, wider than the walked places' answers
    sig_far, sig_near = u.sigma_of(far), u.sigma_of(near)
    assert np.all(sig_far[far_out] >= t.sigma_m) and t.sigma_m > np.median(sig_near[~near_out])
    assert np.array_equal(sig_near[~near_out], u.sigma(near.spread, near.score)[~near_out])  # inside: as before
    # a map whose walks all left the same places has nothing to leave out: no test
    assert calibrate_uncertainty(line, outside_radius_m=0.0).outside is None


@pytest.mark.parametrize("dense_cells", [0, 1 << 16])  # the pairs by keys (many queries) / dense (a few)
def test_the_statistic_is_the_rss_difference_to_the_neighbours_on_every_search_path(
    line: RadioMap, dense_cells: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``rss_diff_db``: the mean eq. 9 distance (dB) from the query to its neighbours, whatever the
    metric and the search (the few-query path, blocks, the IVF index), unknown APs counted as eq. 9 does."""
    import graphslam.core.radiomap.neighbours as nb_mod

    monkeypatch.setattr(nb_mod, "PAIR_DENSE_MAX_CELLS", dense_cells)
    qs = _queries(np.arange(0.0, 120.0, 3.0))
    qs[0] = dict(qs[0], **{"0a:00:00:00:00:01": -50.0})  # an AP the map never heard
    full = KnnLocator(line, KnnConfig(metric="eq9", k=len(line), index="exact"))
    d = full.distances(line.reindex(line.encode(qs)))
    for cfg in (KnnConfig(), KnnConfig(metric="eq9", k=5), KnnConfig(index="ivf", ivf_clusters=8)):
        loc = KnnLocator(line, cfg)
        for res, part in ((loc.locate(qs), qs), (loc.locate(qs[:5]), qs[:5])):
            nb = res.neighbours
            want = np.array([d[i, nb[i][nb[i] >= 0]].mean() for i in range(len(part))])
            assert res.rss_diff_db is not None and np.allclose(res.rss_diff_db, want, rtol=1e-9, atol=1e-9)


def test_the_test_rides_in_the_maps_metadata_and_an_older_record_is_measured_again(
    line: RadioMap, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import graphslam.core.radiomap.uncertainty as unc
    from graphslam.io.radiomap_io import read_radio_map, write_radio_map

    rm = with_uncertainty(line)
    write_radio_map(rm, tmp_path / "map.parquet")
    stored = read_radio_map(tmp_path / "map.parquet").metadata[METADATA_KEY]
    u = KnnUncertainty.from_dict(stored)
    assert u is not None and u.outside == calibrate_uncertainty(line).outside  # measured once, read back as is
    calls: list[object] = []
    real = unc.calibrate_uncertainty
    monkeypatch.setattr(unc, "calibrate_uncertainty", lambda *a, **k: calls.append(a) or real(*a, **k))
    assert map_uncertainty(rm, KnnConfig()) == u and not calls
    older = line.with_metadata(**{METADATA_KEY: {k: v for k, v in stored.items() if k != "outside"}})
    again = map_uncertainty(older, KnnConfig())  # written before the test: measured now, so answers carry it
    assert len(calls) == 1 and again is not None and again.outside == u.outside
    bad = {**stored, "outside": {**stored["outside"], "covered_db": stored["outside"]["covered_db"][::-1]}}
    assert KnnUncertainty.from_dict(bad) is None  # a damaged test is no test: measured again


def _walk(session_id: str, xs: np.ndarray, scan_every: int, seed: int) -> Session:
    """A walk along the corridor: a step every 0.7 m (0.5 s), a scan every ``scan_every`` steps."""
    rng = np.random.default_rng(seed)
    t = T0 + np.arange(len(xs), dtype=np.int64) * 500_000_000
    xy = np.column_stack([xs, np.zeros_like(xs)])
    scans = tuple(Scan(int(t[i]) + 1, _scan(float(xs[i]), rng)) for i in range(0, len(xs), scan_every))
    return Session(session_id, PoseTrack(t, xy, np.zeros(len(xs))), scans)


def test_locate_writes_the_flag_and_the_service_answers_it(line: RadioMap, tmp_path: Path) -> None:
    import httpx

    from graphslam.app.locate import POSITIONS_HEADER, locate_files
    from graphslam.io.mcap_writer import write_session
    from graphslam.io.radiomap_io import write_radio_map
    from graphslam.service.server import reloading_app, start_background_server

    write_radio_map(with_uncertainty(line), tmp_path / "map.parquet")
    u = calibrate_uncertainty(line)
    assert u is not None and u.outside is not None
    q = tmp_path / "q"
    q.mkdir()
    write_session(_walk("w", np.arange(10.0, 180.0, 0.7), 4, seed=3), q / "w.mcap")
    run = locate_files(tmp_path / "map.parquet", [q], out=tmp_path / "pos.csv")
    assert POSITIONS_HEADER.index("outside") == POSITIONS_HEADER.index("sigma_m") + 1
    rows = list(csv.DictReader(open(tmp_path / "pos.csv")))
    x = np.array([float(r["x"]) for r in rows])
    out = np.array([r["outside"] == "1" for r in rows])
    truth_x = np.arange(10.0, 180.0, 0.7)[::4]
    assert {r["outside"] for r in rows} == {"0", "1"} and all(r["outside_score"] for r in rows)
    assert out[truth_x < 70].mean() <= 0.1 and out[truth_x > 100].mean() >= 0.8
    assert all((float(r["outside_score"]) > 0.95) == (r["outside"] == "1") for r in rows)
    assert all(float(r["sigma_m"]) >= u.outside.sigma_m - 1e-3 for r in rows if r["outside"] == "1")
    assert np.all(x[out] < 90)  # the answers themselves stay on the map: only the flag can say where they are from
    summary = run.as_dict()
    assert summary["outside"] == int(out.sum()) and summary["uncertainty"]["outside"]["sigma_m"] == round(u.outside.sigma_m, 3)

    near, far = _queries(np.array([30.0]), 7)[0], _queries(np.array([150.0]), 8)[0]
    loc = KnnLocator(line)
    want = {k: (bool(u.outside_of(loc.locate([s]))[0]), float(u.outside_score_of(loc.locate([s]))[0]))
            for k, s in (("near", near), ("far", far))}
    assert want["near"][0] is False and want["far"][0] is True
    # a real HTTP server on a free port: the small-request path, and a batch the search process renders
    batch = _queries(np.arange(0.0, 200.0, 0.25), 9)
    for processes in (0, 1):
        app = reloading_app(tmp_path / "map.parquet", None, k=3, search_processes=processes)
        with start_background_server(app) as srv, httpx.Client(base_url=srv.url, timeout=60.0) as c:
            for key, scan in (("near", near), ("far", far)):
                r = c.post("/v1/locate", json={"readings": scan})
                assert r.status_code == 200, r.text
                pos = r.json()["positions"][0]
                assert (pos["outside"], pos["outside_score"]) == pytest.approx(want[key])
                assert pos["sigma_m"] >= (u.outside.sigma_m if key == "far" else 0.0)
            got = c.post("/v1/locate", json={"fingerprints": [{"readings": s} for s in batch]}).json()["positions"]
        res = loc.locate(batch)
        assert [p["outside"] for p in got] == u.outside_of(res).tolist()
        assert [p["outside_score"] for p in got] == pytest.approx(u.outside_score_of(res).tolist())
        assert [p["sigma_m"] for p in got] == pytest.approx(u.sigma_of(res).tolist())


def test_a_tracks_steps_beyond_the_map_are_flagged_with_a_wide_ellipse(line: RadioMap, tmp_path: Path) -> None:
    from graphslam.app.track import TRACK_HEADER, TrackRun, write_track_csv
    from graphslam.core.tracking.apmodel import ApModels
    from graphslam.core.tracking.tracker import Tracker
    from graphslam.tracking_config import TrackConfig

    xs = np.arange(20.0, 170.0, 0.7)
    walk = _walk("w", xs, 4, seed=5)
    cfg = TrackConfig(calibration={"enabled": False}, motion={"n_theta_hypotheses": 2})
    tracker = Tracker.on_map(line, ApModels.fit(line), cfg)
    u = tracker.locator.uncertainty
    assert u is not None and u.outside is not None  # measured on the map when it records none
    tr = tracker.track(walk)
    assert tr.outside is not None and tr.outside_score is not None and len(tr.outside) == len(xs)
    assert tr.outside[xs < 65].mean() <= 0.1 and tr.outside[xs > 110].mean() >= 0.8
    assert np.array_equal(tr.outside, tr.outside_score > 0.95)
    # an outside step claims no small ellipse: at least the map's outside sigma in every direction
    smallest = np.linalg.eigvalsh(tr.P[:, :2, :2])[:, 0]
    assert np.all(smallest[tr.outside] >= u.outside.sigma_m**2 * (1 - 1e-9))
    write_track_csv([tr], tmp_path / "t.csv")
    rows = list(csv.DictReader(open(tmp_path / "t.csv")))
    assert TRACK_HEADER[TRACK_HEADER.index("outside") + 1] == "outside_score"
    assert [r["outside"] == "1" for r in rows] == tr.outside.tolist()
    assert TrackRun((tr,), None, 0).as_dict()["outside_steps"] == int(tr.outside.sum())
    # a map without a test (one walk: nothing to leave out) leaves the columns empty
    one = RadioMap.from_fingerprints(line.fingerprints.rows(np.flatnonzero(line.session_ids == "w0")),
                                     line.xy[line.session_ids == "w0"], session_ids=["w0"] * int((line.session_ids == "w0").sum()),
                                     t_ns=line.t_ns[line.session_ids == "w0"], frame="site")
    bare = Tracker.on_map(one, ApModels.fit(line), cfg).track(walk)
    assert bare.outside is None and TrackRun((bare,), None, 0).as_dict()["outside_steps"] is None
    write_track_csv([bare], tmp_path / "bare.csv")
    assert {r["outside"] for r in csv.DictReader(open(tmp_path / "bare.csv"))} == {""}
