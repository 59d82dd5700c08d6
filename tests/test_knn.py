"""kNN positioning on eq. 9: hand-made maps with known answers, and agreement with DistanceEngine."""

from __future__ import annotations

import numpy as np
import pytest

from graphslam.core.radiomap.fingerprints import DistanceEngine, FingerprintMatrix, rss_distance
from graphslam.core.radiomap.knn import KnnConfig, KnnLocator
from graphslam.core.radiomap.neighbours import candidate_block, gather_block, nearest
from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.errors import ConfigError, QueryError, RadioMapError

# Four reference fingerprints at the corners of a 10 m square; AP "a" loud at (0,0), "b" at (10,0), ...
CORNERS = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0]])
SCANS = [
    {"a": -40.0, "b": -70.0, "c": -70.0, "d": -90.0},
    {"a": -70.0, "b": -40.0, "c": -90.0, "d": -70.0},
    {"a": -70.0, "b": -90.0, "c": -40.0, "d": -70.0},
    {"a": -90.0, "b": -70.0, "c": -70.0, "d": -40.0},
]


def corner_map(**kw: object) -> RadioMap:
    return RadioMap.from_scans(
        SCANS, CORNERS, session_ids="walk", t_ns=[1, 2, 3, 4], frame="site",
        floors=["F1", "F1", "F2", "F2"], buildings=["B", "B", "B", "B"], **kw,  # type: ignore[arg-type]
    )


def test_k1_returns_the_nearest_fingerprint_position_and_its_distance() -> None:
    rm = corner_map()
    q = {"a": -42.0, "b": -71.0, "c": -69.0, "d": -88.0}
    res = KnnLocator(rm, KnnConfig(metric="eq9", k=1)).locate([q])
    assert res.neighbours[0].tolist() == [0]
    assert res.xy[0].tolist() == [0.0, 0.0]
    assert res.score[0] == pytest.approx(rss_distance(q, SCANS[0]))
    assert res.spread[0] == 0.0
    assert res.floor is not None and res.floor[0] == "F1"
    assert res.valid.all() and res.status.tolist() == ["ok"]


def test_unweighted_k2_is_the_midpoint_and_weighted_leans_to_the_closer_match() -> None:
    rm = corner_map()
    # Closer to corner 0 than to corner 1 (in RSS), far from 2 and 3.
    q = {"a": -50.0, "b": -52.0, "c": -80.0, "d": -80.0}
    d0, d1 = rss_distance(q, SCANS[0]), rss_distance(q, SCANS[1])
    assert d0 < d1 < min(rss_distance(q, SCANS[2]), rss_distance(q, SCANS[3]))
    plain = KnnLocator(rm, KnnConfig(metric="eq9", k=2, weighted=False)).locate([q])
    assert plain.neighbours[0].tolist() == [0, 1]
    assert plain.xy[0] == pytest.approx([5.0, 0.0])
    assert plain.spread[0] == pytest.approx(5.0)
    assert plain.score[0] == pytest.approx((d0 + d1) / 2)
    weighted = KnnLocator(rm, KnnConfig(metric="eq9", k=2, weighted=True)).locate([q])
    w0, w1 = 1 / d0, 1 / d1
    assert weighted.xy[0] == pytest.approx([10.0 * w1 / (w0 + w1), 0.0], rel=1e-5)
    assert weighted.xy[0, 0] < 5.0


def test_floor_vote_is_weighted() -> None:
    rm = corner_map()
    # Nearest is corner 2 (F2); corners 0 and 1 (F1) are further: uniform vote of k=3 says F1,
    # inverse-distance vote says F2 when corner 2 is much closer.
    q = {"a": -70.0, "b": -90.0, "c": -41.0, "d": -70.0}
    uni = KnnLocator(rm, KnnConfig(metric="eq9", k=3, weighted=False)).locate([q])
    wtd = KnnLocator(rm, KnnConfig(metric="eq9", k=3, weighted=True)).locate([q])
    assert uni.neighbours[0, 0] == 2 and set(uni.neighbours[0, 1:].tolist()) <= {0, 3}
    nb_floors = rm.floors[uni.neighbours[0]]  # type: ignore[index]
    majority = max(set(nb_floors.tolist()), key=nb_floors.tolist().count)
    assert uni.floor is not None and wtd.floor is not None
    assert uni.floor[0] == majority
    assert wtd.floor[0] == "F2"


def test_unknown_aps_are_flagged_or_raise() -> None:
    rm = corner_map()
    loc = KnnLocator(rm, KnnConfig(metric="eq9", k=2))
    res = loc.locate([{"zz": -50.0}, {"a": -40.0}, {"a": -101.0}])  # the last is below min_rssi
    assert res.valid.tolist() == [False, True, False]
    assert res.status.tolist() == ["no_known_ap", "ok", "no_known_ap"]
    assert np.isnan(res.xy[0]).all() and res.neighbours[0].tolist() == [-1, -1]
    with pytest.raises(QueryError, match="#0: no_known_ap"):
        loc.locate([{"zz": -50.0}], strict=True)


def test_min_common_excludes_neighbours_sharing_too_few_aps() -> None:
    rm = RadioMap.from_scans(
        [{"a": -50.0}, {"a": -60.0, "b": -60.0, "c": -60.0}], [[0, 0], [5, 5]], session_ids="s", t_ns=[0, 1],
        frame="f",
    )
    q = {"a": -50.0, "b": -95.0, "c": -95.0}
    assert KnnLocator(rm, KnnConfig(metric="eq9", k=1)).locate([q]).neighbours[0, 0] == 0
    assert KnnLocator(rm, KnnConfig(metric="eq9", k=1, min_common=3)).locate([q]).neighbours[0, 0] == 1
    only_a = KnnLocator(rm, KnnConfig(metric="eq9", k=1, min_common=2)).locate([{"a": -50.0}])
    assert only_a.status.tolist() == ["no_candidate"]


def test_k_larger_than_map_pads() -> None:
    res = KnnLocator(corner_map(), KnnConfig(metric="eq9", k=6)).locate([SCANS[0]])
    assert res.n_neighbours[0] == 4
    assert res.neighbours[0, 4:].tolist() == [-1, -1]
    assert np.isinf(res.distances[0, 4:]).all()


def test_bad_config() -> None:
    with pytest.raises(ConfigError, match="k must be"):
        KnnConfig(metric="eq9", k=0)
    with pytest.raises(ConfigError, match="min_common"):
        KnnConfig(metric="eq9", min_common=0)


def _random_scans(rng: np.random.Generator, n: int, n_aps: int, per_scan: int) -> list[dict[str, float]]:
    out = []
    for _ in range(n):
        aps = rng.choice(n_aps, size=rng.integers(1, per_scan + 1), replace=False)
        out.append({f"ap{j:03d}": float(rng.integers(-99, -30)) for j in aps})
    return out


@pytest.mark.parametrize("min_common", [1, 2])
def test_sparse_candidate_distances_equal_the_engine(min_common: int) -> None:
    rng = np.random.default_rng(1)
    refs = _random_scans(rng, 300, 400, 8)  # sparse enough for the sparse path
    rm = RadioMap.from_scans(refs, rng.uniform(0, 50, (300, 2)), session_ids="s", t_ns=np.arange(300), frame="f")
    queries = _random_scans(rng, 40, 450, 10)  # includes APs unknown to the map
    q = rm.encode(queries)
    eng = DistanceEngine(rm.fingerprints)
    assert not eng.dense
    full, _ = eng.block(q, min_common=min_common)
    mine = candidate_block(eng, q, min_common)
    assert np.array_equal(np.isfinite(full), np.isfinite(mine))
    assert np.array_equal(full[np.isfinite(full)], mine[np.isfinite(mine)])  # bit-identical
    gathered = gather_block(eng, q, min_common)  # the few-queries path: same up to summation order
    assert np.array_equal(np.isfinite(full), np.isfinite(gathered))
    np.testing.assert_allclose(gathered[np.isfinite(gathered)], full[np.isfinite(full)], rtol=1e-12)
    # and eq. 9 from its definition, for a few pairs
    pairs = np.argwhere(np.isfinite(mine))
    assert len(pairs) >= 10
    for i, j in pairs[:: max(1, len(pairs) // 20)]:
        assert mine[i, j] == pytest.approx(rss_distance(queries[i], refs[j]))
    # kNN = brute force argsort of the same distances, on both paths (small blocks: gather; big: products)
    for cells in (2000, 10**6):
        res = KnnLocator(rm, KnnConfig(metric="eq9", k=5, min_common=min_common), block_cells=cells, threads=2).locate(q)
        for i in range(len(queries)):
            order = np.lexsort((np.arange(full.shape[1]), full[i]))[:5]
            expect = [int(j) if np.isfinite(full[i, j]) else -1 for j in order]
            assert res.neighbours[i].tolist() == expect


def test_scans_fingerprints_and_foreign_index_give_the_same_answer() -> None:
    rng = np.random.default_rng(2)
    refs = _random_scans(rng, 120, 60, 10)
    rm = RadioMap.from_scans(refs, rng.uniform(0, 50, (120, 2)), session_ids="s", t_ns=np.arange(120), frame="f")
    queries = _random_scans(rng, 30, 70, 10)
    loc = KnnLocator(rm, KnnConfig(metric="eq9", k=4))
    a = loc.locate(queries)
    foreign = FingerprintMatrix.from_scans(queries)  # its own AP index
    b = loc.locate(foreign)
    assert np.array_equal(a.neighbours, b.neighbours)
    np.testing.assert_allclose(a.xy, b.xy, rtol=1e-12)


def test_dense_engine_path_agrees() -> None:
    # <= 64 APs: DistanceEngine goes dense; the locator must use it and agree with brute force.
    rm = corner_map()
    loc = KnnLocator(rm, KnnConfig(metric="eq9", k=4, weighted=False))
    assert loc.engine.dense
    q = {"a": -60.0, "b": -60.0, "e": -50.0}
    res = loc.locate([q])
    d = [rss_distance(q, s) for s in SCANS]
    assert res.distances[0] == pytest.approx(sorted(d))


def test_radio_map_checks_and_canonical_index() -> None:
    fm = FingerprintMatrix.from_dense(np.array([[-50.0, np.nan, -60.0]]), ["z", "unused", "a"])
    rm = RadioMap.from_fingerprints(fm, np.array([[1.0, 2.0]]), session_ids="s", t_ns=[0], frame="f")
    assert rm.bssids == ("a", "z")  # sorted, never-heard AP dropped
    assert rm.fingerprints.values.toarray().tolist() == [[50.0, 60.0]]
    with pytest.raises(RadioMapError, match="xy"):
        RadioMap.from_scans([{"a": -50.0}], [[0.0, 0.0], [1.0, 1.0]], session_ids="s", t_ns=[0], frame="f")
    with pytest.raises(RadioMapError, match="non-finite"):
        RadioMap.from_scans([{"a": -50.0}], [[np.nan, 0.0]], session_ids="s", t_ns=[0], frame="f")
    with pytest.raises(RadioMapError, match="metadata"):
        RadioMap.from_scans([{"a": -50.0}], [[0.0, 0.0]], session_ids="s", t_ns=[0], frame="f", metadata={"x": {1}})
    s = corner_map().summary().as_dict()
    assert s["n_fingerprints"] == 4 and s["n_access_points"] == 4
    assert s["bbox"] == {"min_x": 0.0, "min_y": 0.0, "max_x": 10.0, "max_y": 10.0}
    assert s["floors"] == {"F1": 2, "F2": 2}


def test_empty_map_answers_nothing() -> None:
    rm = RadioMap.from_scans([], np.zeros((0, 2)), session_ids=[], t_ns=[], frame="f")
    assert len(rm) == 0 and rm.summary().bbox is None
    res = KnnLocator(rm, KnnConfig(metric="eq9")).locate([{"a": -50.0}])
    assert res.status.tolist() == ["no_known_ap"]


def test_ties_at_the_kth_distance_take_the_lowest_rows() -> None:
    # Rows 0, 7, 14, ... match the query better; all others are identical and tie. k=40 needs
    # 11 of the tied ones: the lowest rows, whatever argpartition picks, so answers do not
    # depend on k, block size or threads.
    n = 200
    scans = [{"a": -50.0, "b": -60.0} if i % 7 == 0 else {"a": -50.0, "b": -70.0} for i in range(n)]
    rm = RadioMap.from_scans(scans, np.zeros((n, 2)), session_ids="s", t_ns=np.arange(n), frame="f")
    res = KnnLocator(rm, KnnConfig(metric="eq9", k=40)).locate([{"a": -50.0, "b": -60.0}] * 2)
    better = list(range(0, n, 7))
    tied = [i for i in range(n) if i % 7][:11]
    assert res.neighbours.tolist() == [better + tied] * 2


def test_empty_query_batch_and_non_finite_rssi() -> None:
    loc = KnnLocator(corner_map())
    res = loc.locate([])
    assert len(res) == 0 and res.xy.shape == (0, 2) and res.floor is not None and len(res.floor) == 0
    with pytest.raises(QueryError, match="non-finite"):
        loc.locate([{"a": float("nan")}])


def _sorensen_brute(rm: RadioMap, queries: list[dict[str, float]], min_common: int) -> np.ndarray:
    """The Sørensen distance on powed RSS from its definition, over the map's APs only."""
    known = set(rm.bssids)
    m = -rm.missing_dbm

    def powed(s: dict[str, float]) -> dict[str, float]:
        return {b: ((r + m) / m) ** np.e for b, r in s.items() if b in known and r >= rm.min_rssi_dbm}

    refs = [powed(dict(zip(rm.bssids, row))) for row in rm.fingerprints.dense_rssi()]
    refs = [{b: v for b, v in r.items() if v > 0 and b in known} for r in refs]
    out = np.full((len(queries), len(refs)), np.inf)
    for i, q in enumerate(map(powed, queries)):
        for j, r in enumerate(refs):
            union = set(q) | set(r)
            if len(set(q) & set(r)) >= max(1, min_common):
                num = sum(abs(q.get(b, 0.0) - r.get(b, 0.0)) for b in union)
                out[i, j] = num / (sum(q.values()) + sum(r.values()))
    return out


@pytest.mark.parametrize("min_common", [1, 2])
def test_sorensen_distances_and_neighbours_equal_their_definition(min_common: int) -> None:
    rng = np.random.default_rng(5)
    refs = _random_scans(rng, 150, 80, 8)
    rm = RadioMap.from_scans(refs, rng.uniform(0, 50, (150, 2)), session_ids="s", t_ns=np.arange(150), frame="f")
    queries = _random_scans(rng, 25, 95, 10)  # includes APs unknown to the map: left out
    expect = _sorensen_brute(rm, queries, min_common)
    assert np.isfinite(expect).sum() >= 50 and (~np.isfinite(expect)).any()
    for cells in (600, 10**6):  # several query blocks, one block
        loc = KnnLocator(rm, KnnConfig(k=4, min_common=min_common, metric="sorensen"), block_cells=cells, threads=2)
        got = loc.distances(rm.encode(queries))
        assert np.array_equal(np.isfinite(got), np.isfinite(expect))
        np.testing.assert_allclose(got[np.isfinite(got)], expect[np.isfinite(expect)], rtol=1e-12, atol=1e-15)
        res = loc.locate(queries)
        for i in range(len(queries)):
            order = np.lexsort((np.arange(expect.shape[1]), expect[i]))[:4]
            assert res.neighbours[i].tolist() == [int(j) if np.isfinite(expect[i, j]) else -1 for j in order]


@pytest.mark.parametrize("min_common", [1, 3])
def test_sorensen_dense_blocks_equal_the_postings_bit_for_bit(min_common: int, monkeypatch: pytest.MonkeyPatch) -> None:
    # A block is summed dense, AP by AP, or from its postings (neighbours.SORENSEN_DENSE_MIN_FILL): the
    # same sums in the same order, so the same distances, neighbours and ties, bit for bit.
    from graphslam.core.radiomap import neighbours

    rng = np.random.default_rng(8)
    n = 300
    refs = _random_scans(rng, n, 30, 12)
    refs[::7] = [refs[2]] * len(refs[::7])  # ties at the k-th distance
    rm = RadioMap.from_scans(refs, rng.uniform(0, 50, (n, 2)), session_ids="s", t_ns=np.arange(n), frame="f",
                             floors=rng.choice(["F1", "F2"], n))
    queries = rm.encode(_random_scans(rng, 60, 40, 9) + [dict(refs[2]), {}])
    loc = KnnLocator(rm, KnnConfig(k=5, index="exact", min_common=min_common), block_cells=20 * n, threads=1)
    calls: list[int] = []
    dense = neighbours._sorensen_dense_sums
    monkeypatch.setattr(neighbours, "_sorensen_dense_sums", lambda *a: calls.append(1) or dense(*a))
    monkeypatch.setattr(neighbours, "SORENSEN_DENSE_MIN_FILL", 0.0)
    a = loc.locate(queries)
    assert len(calls) == 4  # every block of 20 queries (the last one's 2)
    monkeypatch.setattr(neighbours, "SORENSEN_DENSE_MIN_FILL", float("inf"))
    b = loc.locate(queries)
    assert len(calls) == 4
    assert np.array_equal(loc.distances(queries), neighbours.sorensen_block(loc._sorensen, queries, min_common))
    _assert_same_answers(a, b)
    # the dense path with the reference rows densified per block, not from the kept dense copy
    assert loc._sorensen._dense is not None
    monkeypatch.setattr(neighbours, "SORENSEN_DENSE_MIN_FILL", 0.0)
    monkeypatch.setattr(neighbours, "DENSE_REFS_MAX_CELLS", 0)
    fresh = KnnLocator(rm, KnnConfig(k=5, index="exact", min_common=min_common), block_cells=20 * n, threads=1)
    _assert_same_answers(a, fresh.locate(queries))
    assert fresh._sorensen._dense is None and len(calls) == 8


def test_sorensen_weighs_a_reading_by_its_strength_where_eq9_charges_a_fixed_gap() -> None:
    # The query matches A on its one strong AP and misses two weak readings A lacks; B hears the weak
    # ones exactly but the strong AP 15 dB lower. Eq. 9 charges each missing reading as -110 dBm
    # (20 dB each) and picks B; on powed RSS a -90 dBm reading weighs ~4 % of a -45 dBm one: A.
    rm = RadioMap.from_scans(
        [{"a": -45.0}, {"a": -60.0, "b": -90.0, "c": -90.0}], np.array([[0.0, 0.0], [20.0, 0.0]]),
        session_ids="s", t_ns=[1, 2], frame="f",
    )
    q = [{"a": -45.0, "b": -90.0, "c": -90.0}]
    assert KnnLocator(rm, KnnConfig(metric="eq9", k=1)).locate(q).neighbours[0, 0] == 1
    res = KnnLocator(rm, KnnConfig(k=1, metric="sorensen")).locate(q)
    assert res.neighbours[0, 0] == 0 and res.xy[0].tolist() == [0.0, 0.0]
    assert 0.0 < res.score[0] < 0.1  # a unitless distance in [0, 1]


def test_sorensen_config_and_index() -> None:
    with pytest.raises(ConfigError, match="metric must be one of"):
        KnnConfig(metric="cosine")  # type: ignore[arg-type]
    rng = np.random.default_rng(6)
    n = 5000  # IVF_AUTO_MIN_REFS: "auto" would pick the IVF index for eq. 9
    rm = RadioMap.from_scans(_random_scans(rng, n, 300, 6), rng.uniform(0, 50, (n, 2)), session_ids="s",
                             t_ns=np.arange(n), frame="f")
    assert KnnLocator(rm, KnnConfig(metric="eq9", index="auto")).index_kind == "ivf"
    # the IVF index searches Sørensen too: "auto" (the default) picks it for either metric
    assert KnnLocator(rm, KnnConfig(index="auto", metric="sorensen")).index_kind == "ivf"
    assert KnnLocator(rm).index_kind == "ivf" and KnnLocator(rm).config.metric == "sorensen"
    assert KnnLocator(rm, KnnConfig(index="exact")).index_kind == "exact"


def _assert_same_answers(a, b) -> None:  # type: ignore[no-untyped-def]
    assert np.array_equal(a.neighbours, b.neighbours)
    assert np.array_equal(a.distances, b.distances)  # bit-identical: same sums in the same order
    assert np.array_equal(a.xy, b.xy, equal_nan=True)
    assert np.array_equal(a.score, b.score, equal_nan=True)
    assert np.array_equal(a.spread, b.spread, equal_nan=True)
    assert a.status.tolist() == b.status.tolist() and a.n_known_aps.tolist() == b.n_known_aps.tolist()
    assert a.floor is not None and b.floor is not None and a.floor.tolist() == b.floor.tolist()


@pytest.mark.parametrize("metric", ["sorensen", "eq9"])
@pytest.mark.parametrize("index", ["exact", "ivf"])
@pytest.mark.parametrize("n_aps", [400, 40])  # sparse engine; dense engine (eq. 9's matrix path)
def test_few_query_path_equals_the_batch_path(metric: str, index: str, n_aps: int) -> None:
    # locate(scans) of <= FEW_MAX_QUERIES scans takes the few-query path; locate(rm.encode(scans))
    # the general one. Same neighbours, distances, positions, statuses, bit for bit.
    rng = np.random.default_rng(5)
    n = 400
    refs = _random_scans(rng, n, n_aps, 8)
    refs[::9] = [refs[1]] * len(refs[::9])  # exact duplicates: ties at the k-th distance
    rm = RadioMap.from_scans(refs, rng.uniform(0, 50, (n, 2)), session_ids="s", t_ns=np.arange(n), frame="f",
                             floors=rng.choice(["F1", "F2", ""], n))
    for min_common, weighted in ((1, True), (2, False), (3, True)):
        cfg = KnnConfig(metric=metric, k=5, index=index, min_common=min_common, weighted=weighted, ivf_clusters=12,
                        ivf_probes=3)
        loc = KnnLocator(rm, cfg)
        assert (loc.ivf is None) == (index == "exact") and loc.engine.dense == (n_aps == 40)
        for nq in (1, 2, 8, 16):
            queries = _random_scans(rng, nq, n_aps + 30, 10)  # APs unknown to the map too
            queries[0] = dict(refs[1])  # a query tied with many references
            if nq > 1:
                queries[1] = {"zz:unknown": -50.0}  # no known AP
            if nq > 2:
                queries[2] = {}
            _assert_same_answers(loc.locate(queries), loc.locate(rm.encode(queries)))
    bad = [queries[0], {"zz:unknown": -50.0}]
    with pytest.raises(QueryError) as few:
        loc.locate(bad, strict=True)
    with pytest.raises(QueryError) as batch:
        loc.locate(rm.encode(bad), strict=True)
    assert str(few.value) == str(batch.value)
    with pytest.raises(QueryError, match="non-finite"):
        loc.locate([{refs[0].popitem()[0]: float("inf")}])


def test_nearest_is_each_rows_k_smallest_finite_entries_ties_to_the_lower_column() -> None:
    """``nearest`` against its definition: per row the k smallest finite entries by (value, column),
    then -1 / inf; on blocks of many ties (few distinct values), infinite and NaN entries, rows with
    no finite entry, and k above the number of columns."""
    rng = np.random.default_rng(0)
    for trial in range(600):
        b, n, k = int(rng.integers(1, 6)), int(rng.integers(1, 400)), int(rng.integers(1, 12))
        d = rng.integers(0, int(rng.integers(1, 20)), (b, n)).astype(float)
        d[rng.random((b, n)) < rng.random() * 0.8] = np.inf
        d[rng.random((b, n)) < (0.05 if trial % 3 == 0 else 0.0)] = np.nan
        if trial % 5 == 0:
            d[int(rng.integers(0, b))] = np.inf
        idx, dist = nearest(d, k)
        assert idx.shape == dist.shape == (b, k) and idx.dtype == np.int64
        for r in range(b):
            cols = np.flatnonzero(np.isfinite(d[r]))
            cols = cols[np.lexsort((cols, d[r, cols]))][:k]
            want = np.full(k, -1)
            want[: len(cols)] = cols
            np.testing.assert_array_equal(idx[r], want)
            np.testing.assert_array_equal(dist[r], np.where(want >= 0, d[r, np.maximum(want, 0)], np.inf))
