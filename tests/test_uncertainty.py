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
from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.core.radiomap.uncertainty import (
    METADATA_KEY,
    R95,
    KnnUncertainty,
    calibrate_uncertainty,
    expected_accuracy,
    map_uncertainty,
    with_uncertainty,
)
from graphslam.errors import ConfigError
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
    def want(spread: float, score: float, outside: bool) -> float:  # an outside answer: at least the outside sigma
        base = float(u.sigma(np.array([spread]), np.array([score]))[0])
        return max(base, u.outside.sigma_m) if outside and u.outside is not None else base

    assert ok and all(abs(float(r["sigma_m"]) - want(float(r["spread"]), float(r["score"]), r["outside"] == "1")) < 2e-3
                      for r in ok)
    readings = dict(walks[-1].scans[3].readings)
    app = reloading_app(tmp_path / "map.parquet", None, k=3, search_processes=0)
    with start_background_server(app) as srv, httpx.Client(base_url=srv.url, timeout=30.0) as c:
        pos = c.post("/v1/locate", json={"readings": readings}).json()["positions"][0]
    assert pos["sigma_m"] == pytest.approx(want(pos["spread"], pos["score"], pos["outside"]))


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


def _line_map(only: str | None = None) -> RadioMap:
    """Walks along y = 0 under 11 APs every 10 m (log-distance RSS): on x 0..20 two walks agree; on
    x 60..80 two walks disagree (the second's scans placed mirrored, as a wrongly aligned walk)."""
    aps = np.arange(0.0, 101.0, 10.0)

    def scan(x: float) -> dict[str, float]:
        rss = -30.0 - 25.0 * np.log10(1.0 + np.abs(x - aps))
        return {f"ap{j:02d}": float(r) for j, r in enumerate(rss) if r > -90}

    xa, xb = np.arange(0.0, 20.5, 1.0), np.arange(60.0, 80.5, 1.0)
    walks = [("a1", xa, xa), ("a2", xa + 0.5, xa + 0.5), ("b1", xb, xb), ("b2", xb, 140.0 - xb)]
    walks = [w for w in walks if only in (None, w[0])]
    scans = [scan(x) for _, rss_x, _ in walks for x in rss_x]
    x = np.concatenate([at for *_, at in walks])
    sid = [w for w, rss_x, _ in walks for _ in rss_x]
    return RadioMap.from_scans(scans, np.column_stack([x, np.zeros_like(x)]), session_ids=sid,
                               t_ns=np.arange(len(scans)), frame="site")


def test_expected_accuracy_is_worse_where_walks_disagree_and_empty_where_none_walked() -> None:
    rm = _line_map()
    u = KnnUncertainty("sorensen", 3, True, 1.0, 2.0, 1)
    acc = expected_accuracy(rm, cell_m=2.0, uncertainty=u)
    cx = acc.centres[:, 0]
    agree, disagree = cx < 30, cx > 50
    # cells without fingerprints are not there: none between the two stretches
    assert agree.sum() + disagree.sum() == len(cx) and acc.n_fingerprints.sum() == len(rm) == acc.n_rows
    assert np.all(acc.n_located == acc.n_fingerprints) and np.all(acc.n_sampled == acc.n_fingerprints)
    assert np.isfinite(acc.error_m).all()
    assert np.median(acc.error_m[agree]) < 1.5
    assert np.median(acc.error_m[disagree]) > 3 * np.median(acc.error_m[agree]) + 3
    assert np.isfinite(acc.r95_m).all() and np.all(acc.r95_m >= R95 * 2.0 - 1e-9)  # sigma >= floor
    np.testing.assert_allclose(acc.centres, acc.origin + (acc.ij + 0.5) * 2.0)
    # a sample of the fingerprints is located; the coverage still counts them all
    few = expected_accuracy(rm, cell_m=2.0, max_rows=30)  # ~4 fingerprints per cell: one of each
    assert few.n_rows <= 30 and np.all(few.n_sampled == 1) and few.n_fingerprints.sum() == len(rm)
    assert np.median(few.error_m[disagree]) > 3 * np.median(few.error_m[agree]) + 3
    assert np.isnan(few.r95_m).all()  # no calibration given
    fewer = expected_accuracy(rm, cell_m=2.0, max_rows=5)  # fewer rows than cells: whole cells left out
    assert fewer.n_rows == 5 and np.sum(fewer.n_sampled) == 5 and set(fewer.n_sampled.tolist()) == {0, 1}
    more = expected_accuracy(rm, cell_m=2.0, max_rows=60)  # the same number q of every cell, all of a smaller one
    q = int(more.n_sampled.max())
    assert q >= 2 and more.n_rows <= 60 and np.array_equal(more.n_sampled, np.minimum(more.n_fingerprints, q))
    # one walk: covered, nothing to compare
    one = expected_accuracy(_line_map(only="a1"), cell_m=2.0)
    assert len(one.ij) > 0 and np.isnan(one.error_m).all() and not one.n_located.any()
    with pytest.raises(ConfigError, match="cell size"):
        expected_accuracy(rm, cell_m=0.0)
    with pytest.raises(ConfigError, match="xy must be"):
        expected_accuracy(rm, xy=np.zeros((3, 2)))


def test_the_calibration_equals_locating_each_walk_on_a_map_of_the_others(walks: list) -> None:
    """One locator with the walk masked out (and the APs only it heard moved outside the index) is
    what a map built of the other walks answers: the same scale, both metrics."""
    from graphslam.core.radiomap.radiomap import RadioMap

    rm = oracle_radio_map(walks)
    rm = RadioMap.from_scans(  # an AP only the first walk hears, loud: counted against it on eq. 9
        [dict(r, **({"solo": -40.0} if s == rm.session_ids[0] else {})) for r, s in
         zip(_readings(rm), rm.session_ids)], rm.xy, session_ids=rm.session_ids, t_ns=rm.t_ns, frame=rm.frame,
    )
    for cfg in (KnnConfig(), KnnConfig(metric="eq9", k=5, weighted=False)):
        e, sp = [], []
        for sid in np.unique(rm.session_ids):
            keep = rm.session_ids != sid
            others = RadioMap.from_scans([r for r, k in zip(_readings(rm), keep) if k], rm.xy[keep],
                                         session_ids=rm.session_ids[keep], t_ns=rm.t_ns[keep], frame=rm.frame)
            res = KnnLocator(others, cfg).locate([r for r, k in zip(_readings(rm), keep) if not k])
            e.append(np.linalg.norm(res.xy - rm.xy[~keep], axis=1))
            sp.append(res.spread)
        base = np.sqrt(np.concatenate(sp) ** 2 + 2.0**2)
        want = np.quantile(np.concatenate(e) / (R95 * base), 0.95)
        u = calibrate_uncertainty(rm, cfg, max_queries=10**6, max_sessions=10**6)
        assert u is not None and u.n == len(rm) and u.scale == pytest.approx(want, rel=1e-9)


def test_walks_located_a_batch_at_a_time_or_alone_give_the_same_calibration(walks: list, monkeypatch: pytest.MonkeyPatch) -> None:
    # each row's answer is its own: the walks of one batch located together (the default on a small map)
    # give the calibration of every walk located alone, bit for bit, its three sets and the outside test
    import graphslam.core.radiomap.uncertainty as U

    rm = oracle_radio_map(walks)
    assert U.BATCH_CELLS // len(rm) >= len(rm)  # one batch holds every walk's scans
    together = calibrate_uncertainty(rm)
    monkeypatch.setattr(U, "BATCH_CELLS", 1)  # a batch of one walk
    alone = calibrate_uncertainty(rm)
    assert together is not None and together.outside is not None and len(together.score_edges) > 0
    assert together.outside.detection > 0.1  # the outside scans' own RSS distances (not zeros: none flagged)
    assert together == alone


def _readings(rm) -> list[dict[str, float]]:
    v = rm.fingerprints.values
    return [{rm.bssids[j]: float(x + rm.missing_dbm) for j, x in zip(v.indices[v.indptr[i]:v.indptr[i + 1]],
                                                                    v.data[v.indptr[i]:v.indptr[i + 1]])}
            for i in range(len(rm))]


def test_a_walks_own_aps_leave_the_index_as_on_a_map_without_it() -> None:
    from graphslam.core.radiomap.radiomap import RadioMap
    from graphslam.core.radiomap.uncertainty import _heard_only_by, _without_columns

    scans = [{"a": -50.0, "solo": -40.0}, {"a": -60.0, "b": -70.0}, {"b": -65.0}, {"a": -55.0, "b": -75.0}]
    rm = RadioMap.from_scans(scans, np.zeros((4, 2)), session_ids=["w1", "w1", "w2", "w2"], t_ns=np.arange(4),
                             frame="f")
    values = rm.fingerprints.values
    heard = np.bincount(values.indices, minlength=rm.fingerprints.n_aps)
    alone = _heard_only_by(values, heard, np.array([True, True, False, False]))
    assert {rm.bssids[j]: bool(o) for j, o in enumerate(alone)} == {"a": False, "b": False, "solo": True}
    # the second walk and the first walk's second scan removed: "b" is heard by nobody left, "solo" still is
    gone = np.array([False, True, True, True])
    assert {rm.bssids[j] for j in np.flatnonzero(_heard_only_by(values, heard, gone))} == {"b"}
    owner = alone
    q = _without_columns(rm.fingerprints.rows(np.array([0, 1])), owner)
    others = RadioMap.from_scans(scans[2:], np.zeros((2, 2)), session_ids=["w2", "w2"], t_ns=np.arange(2), frame="f")
    want = others.reindex(rm.fingerprints.rows(np.array([0, 1])))
    assert np.allclose(q.extra_sq, want.extra_sq) and np.array_equal(q.extra_n, want.extra_n) and q.extra_n[0] == 1
    assert np.array_equal(q.values.toarray()[:, [rm.column("a"), rm.column("b")]], want.values.toarray())
    # a query that hears none of the columns dropped is itself (no copy)
    third = rm.fingerprints.rows(np.array([2, 3]))
    assert _without_columns(third, owner) is third


def test_a_wider_removal_searches_again_exactly_the_scans_it_changes() -> None:
    """Distances after dropping other AP columns, from the ones before, equal a search from scratch,
    whichever way the dropped set changes; a row hearing no changed column is not searched again."""
    from graphslam.core.radiomap.uncertainty import _distances_again, _without_columns

    scans = [{"a": -50.0, "b": -60.0}, {"a": -55.0, "c": -45.0}, {"b": -65.0, "c": -70.0, "d": -52.0},
             {"a": -58.0, "b": -62.0, "c": -75.0}, {"b": -61.0, "d": -66.0}, {"a": -49.0, "c": -71.0}]
    rm = RadioMap.from_scans(scans, np.arange(12.0).reshape(6, 2), session_ids=list("wwwxxx"), t_ns=np.arange(6),
                             frame="f")
    loc = KnnLocator(rm, KnnConfig(metric="eq9", k=2))
    q = rm.fingerprints.rows(np.arange(3))
    col = {b: rm.column(b) for b in "abcd"}
    none, only_c, c_and_d = (np.zeros(rm.fingerprints.n_aps, bool) for _ in range(3))
    only_c[col["c"]] = c_and_d[col["c"]] = c_and_d[col["d"]] = True
    assert not np.array_equal(loc.distances(_without_columns(q, c_and_d)), loc.distances(_without_columns(q, only_c)))
    for before, after in ((none, only_c), (only_c, c_and_d), (c_and_d, only_c), (c_and_d, none)):
        d0 = loc.distances(_without_columns(q, before))
        searched: list[int] = []
        real = loc.distances
        loc.distances = lambda m: searched.append(len(m)) or real(m)  # type: ignore[method-assign]
        try:
            out, d = _distances_again(loc, q, d0, before, after)
        finally:
            del loc.distances
        assert np.array_equal(d, loc.distances(_without_columns(q, after)))
        assert np.array_equal(out.extra_n, _without_columns(q, after).extra_n)
        changed = before != after
        assert searched == [sum(any(changed[col[b]] for b in s) for s in scans[:3])]


def test_a_worse_score_never_gets_a_narrower_circle_and_old_records_still_read(walks: list) -> None:
    u = calibrate_uncertainty(oracle_radio_map(walks))
    assert u is not None and len(u.scales) == len(u.score_edges) + 1 >= 2
    assert list(u.scales) == sorted(u.scales) and list(u.score_edges) == sorted(set(u.score_edges))
    spread = np.full(4, 1.5)
    score = np.array([u.score_edges[0] - 0.01, u.score_edges[-1] + 0.01, np.nan, u.score_edges[0]])
    sig = u.sigma(spread, score)
    assert sig[0] == pytest.approx(u.scales[0] * np.sqrt(1.5**2 + u.floor_m**2))
    assert sig[1] == pytest.approx(u.scales[-1] * np.sqrt(1.5**2 + u.floor_m**2)) and sig[1] >= sig[0]
    assert sig[2] == pytest.approx(u.scale * np.sqrt(1.5**2 + u.floor_m**2))  # no score: the covered scale
    assert sig[3] == pytest.approx(u.scales[1] * np.sqrt(1.5**2 + u.floor_m**2))  # an edge opens the next bin
    assert KnnUncertainty.from_dict(u.as_dict()) == u
    old = {k: v for k, v in u.as_dict().items() if k not in ("score_edges", "scales")}
    assert KnnUncertainty.from_dict(old).sigma(spread, score)[1] == pytest.approx(sig[2])  # one scale for all
    assert KnnUncertainty.from_dict({**u.as_dict(), "scales": list(u.scales)[:-1]}) is None
    assert KnnUncertainty.from_dict({**u.as_dict(), "score_edges": list(u.score_edges)[::-1]}) is None or len(u.score_edges) == 1
    assert calibrate_uncertainty(oracle_radio_map(walks), bins=1).scales == ()
