"""Search-worker helpers: vectorised encoding (same matrix as RadioMap.encode), split by place,
JSON rendering (same bytes as orjson.dumps of the whole answer)."""

from __future__ import annotations

import json

import numpy as np
import orjson
import pytest

from graphslam.core.radiomap.knn import KnnConfig, KnnLocator, KnnResult
from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.service.batching import PlaceSplit, ScanEncoder
from graphslam.service.parsing import flat_scans
from graphslam.service.render import position_dicts, position_rows, response_json


def body_of(scans: list[dict[str, float]]) -> bytes:
    return json.dumps({"fingerprints": [{"readings": s} for s in scans]}).encode()


def random_scans(n: int, seed: int, n_aps: int, unknown: int = 0) -> list[dict[str, float]]:
    """Scans over ap0..ap{n_aps-1} and, with ``unknown``, APs the map never heard; RSS ints and floats."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        s: dict[str, float] = {}
        for j in rng.choice(n_aps, int(rng.integers(1, 12)), replace=False):
            r = float(rng.uniform(-110, -20))
            s[f"ap{j}"] = round(r) if rng.random() < 0.3 else r  # ints as JSON ints
        for j in range(int(rng.integers(0, unknown + 1))):
            s[f"new{seed}-{j}"] = float(rng.uniform(-99, -30))
        out.append(s)
    return out


def map_of(scans: list[dict[str, float]], xy: np.ndarray, **kw: object) -> RadioMap:
    n = len(scans)
    return RadioMap.from_scans(scans, xy, session_ids="s", t_ns=np.arange(n), frame="aligned", **kw)  # type: ignore[arg-type]


RM = map_of(random_scans(300, 1, 60), np.random.default_rng(2).uniform(0, 50, (300, 2)))


@pytest.mark.parametrize("rows", [None, [0], [], [5, 3, 1], [7, 7]], ids=["all", "one", "none", "reordered", "repeat"])
def test_encoder_is_radio_map_encode_bit_for_bit(rows: list[int] | None) -> None:
    scans = random_scans(40, 7, 80, unknown=3)  # APs 60..79 and new*: unknown to the map
    scans.append({"ap1": -105.0, "nowhere": -50})  # below the map's floor, and only an unknown AP
    flat = flat_scans(body_of(scans))
    assert flat is not None
    idx = np.arange(len(scans)) if rows is None else np.array(rows, np.int64)
    got = ScanEncoder(RM).encode(flat, idx)
    want = RM.encode([scans[i] for i in idx])
    assert got.bssids is RM.bssids and len(got) == len(idx)
    for a, b in [(got.values.data, want.values.data), (got.values.indices, want.values.indices),
                 (got.values.indptr, want.values.indptr), (got.extra_sq, want.extra_sq), (got.extra_n, want.extra_n)]:
        assert a.dtype == b.dtype and np.array_equal(a, b)
    assert got.values.shape == want.values.shape


def clustered_map() -> tuple[RadioMap, list[dict[str, float]]]:
    """Two 'buildings' with disjoint APs, each with its own clusters, and queries alternating between them."""
    rng = np.random.default_rng(5)
    scans, xy = [], []
    for b in range(2):
        for _ in range(200):
            p = rng.uniform(0, 40, 2)
            ap_xy = [(10 * (j % 5), 10 * (j // 5)) for j in range(25)]
            aps = {f"b{b}-ap{j}": -40.0 - 1.5 * float(np.hypot(*(p - a))) for j, a in enumerate(ap_xy)}
            scans.append({k: v for k, v in aps.items() if v > -90})
            xy.append(p + [100 * b, 0])
    rm = map_of(scans, np.array(xy))
    queries = [scans[i] if i % 2 else scans[200 + i] for i in range(0, 200)]
    return rm, queries


def test_split_by_place_covers_every_row_once_and_keeps_places_apart() -> None:
    rm, queries = clustered_map()
    loc = KnnLocator(rm, KnnConfig(k=3, index="ivf", ivf_clusters=10, ivf_probes=3))
    split = PlaceSplit(loc)
    flat = flat_scans(body_of(queries))
    assert flat is not None
    for parts in (1, 2, 3, 5):
        groups = split.split(flat, parts)
        assert len(groups) == parts
        assert np.array_equal(np.sort(np.concatenate(groups)), np.arange(len(queries)))
        assert all(np.array_equal(g, np.sort(g)) for g in groups)
        assert [g.tolist() for g in groups] == [g.tolist() for g in split.split(flat, parts)]  # deterministic
    halves = split.split(flat, 2)
    building = np.array([next(iter(q)).split("-")[0] for q in queries])
    for g in halves:  # a half is (almost) one building: each searches its own clusters only
        assert np.unique(building[g], return_counts=True)[1].max() >= 0.9 * len(g)
    assert min(map(len, halves)) >= 0.4 * len(queries)  # and the halves are balanced


def test_split_small_batches_and_unknown_aps() -> None:
    loc = KnnLocator(RM, KnnConfig(k=3, index="ivf", ivf_clusters=6, ivf_probes=2))
    split = PlaceSplit(loc)
    for scans in ([{"ap1": -50.0}], [{"zz": -40.0}, {"ap2": -60.0}], [{"zz": -40.0}] * 3):
        flat = flat_scans(body_of(scans))
        assert flat is not None
        groups = split.split(flat, 3)
        assert np.array_equal(np.sort(np.concatenate(groups)), np.arange(len(scans)))


def result(labels: list[str] | None, n: int = 4) -> KnnResult:
    rng = np.random.default_rng(0)
    lab = np.array(labels, dtype=str) if labels is not None else None
    return KnnResult(
        xy=rng.uniform(-1e3, 1e3, (n, 2)), score=rng.uniform(0, 30, n), spread=rng.uniform(0, 5, n),
        neighbours=rng.integers(-1, 9, (n, 3)), distances=rng.uniform(0, 9, (n, 3)),
        n_known_aps=np.ones(n, np.int64), floor=lab, building=lab, config=KnnConfig(),
    )


@pytest.mark.parametrize(
    "labels", [None, ["F1", "", "2", "B"], ['a "q"', ',{"x":1}', "\\", "é\n"]], ids=["none", "plain", "tricky"]
)
def test_rendered_rows_splice_into_the_same_bytes(labels: list[str] | None) -> None:
    res = result(labels)
    head = {"frame": "aligned", "k": 3, "weighted": True}
    rows = position_rows(res)
    assert len(rows) == len(res)
    assert [orjson.loads(r) for r in rows] == position_dicts(res)
    assert response_json(head, rows) == orjson.dumps({**head, "positions": position_dicts(res)})
    # A permutation of the rows (as the pool reorders shares) is the permuted answer.
    order = [2, 0, 3, 1]
    assert response_json(head, [rows[i] for i in order]) == orjson.dumps(
        {**head, "positions": [position_dicts(res)[i] for i in order]}
    )
    empty = result(labels, n=0) if labels is None else result([], n=0)
    assert position_rows(empty) == [] and response_json(head, []) == orjson.dumps({**head, "positions": []})
