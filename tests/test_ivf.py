"""IVF approximate kNN index: exactness when every cluster is probed, determinism, recall."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

import graphslam.core.radiomap.knn as knn
from graphslam.core.radiomap.fingerprints import FingerprintMatrix
from graphslam.core.radiomap.ivf import IvfIndex, default_clusters, kmeans
from graphslam.core.radiomap.knn import KnnConfig, KnnLocator
from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.errors import ConfigError, QueryError


def building(n_ref: int, n_q: int, *, seed: int = 0, integer: bool = False) -> tuple[RadioMap, list[dict[str, float]]]:
    """A 100 x 60 m floor with 40 APs, log-distance path loss + noise; heard above -90 dBm."""
    rng = np.random.default_rng(seed)
    aps = rng.uniform([0, 0], [100, 60], (40, 2))

    def scans(xy: np.ndarray) -> list[dict[str, float]]:
        d = np.linalg.norm(xy[:, None, :] - aps[None, :, :], axis=2)
        rss = -35.0 - 25.0 * np.log10(np.maximum(d, 1.0)) + rng.normal(0, 3.0, d.shape)
        if integer:
            rss = np.round(rss)
        return [{f"ap{j}": float(r[j]) for j in np.flatnonzero(r > -90)} for r in rss]

    ref_xy = rng.uniform([0, 0], [100, 60], (n_ref, 2))
    q_xy = rng.uniform([0, 0], [100, 60], (n_q, 2))
    rm = RadioMap.from_scans(
        scans(ref_xy), ref_xy, session_ids="s", t_ns=np.arange(n_ref), frame="f",
        floors=np.where(ref_xy[:, 0] < 50, "F1", "F2"), missing_dbm=-100, min_rssi_dbm=-95,
    )
    return rm, scans(q_xy)


def test_all_clusters_probed_is_the_exact_search() -> None:
    rm, q = building(600, 200)
    exact = KnnLocator(rm, KnnConfig(metric="eq9", k=5)).locate(q)
    ivf = KnnLocator(rm, KnnConfig(metric="eq9", k=5, index="ivf", ivf_clusters=12, ivf_probes=12)).locate(q)
    assert ivf.valid.all()
    np.testing.assert_array_equal(ivf.neighbours, exact.neighbours)
    np.testing.assert_allclose(ivf.distances, exact.distances, rtol=1e-12)
    np.testing.assert_allclose(ivf.xy, exact.xy, rtol=1e-12)
    assert ivf.floor.tolist() == exact.floor.tolist()  # type: ignore[union-attr]


@pytest.mark.parametrize("min_common", [1, 3])
def test_sorensen_with_all_clusters_probed_is_the_exact_sorensen_search(min_common: int, monkeypatch: pytest.MonkeyPatch) -> None:
    import graphslam.core.radiomap.ivf as ivf_module

    rm, q = building(600, 200, seed=5)
    exact = KnnLocator(rm, KnnConfig(k=5, metric="sorensen", index="exact", min_common=min_common)).locate(q)
    monkeypatch.setattr(ivf_module, "SORENSEN_CHUNK_CELLS", 5_000)  # several chunks of queries per cluster
    ivf = KnnLocator(rm, KnnConfig(k=5, metric="sorensen", index="ivf", ivf_clusters=12, ivf_probes=12,
                                   min_common=min_common)).locate(q)
    assert ivf.valid.all()
    np.testing.assert_array_equal(ivf.neighbours, exact.neighbours)
    np.testing.assert_allclose(ivf.distances, exact.distances, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(ivf.score, exact.score, rtol=1e-9)
    # fewer probes: approximate, yet nearly always the same neighbours on this floor
    few = KnnLocator(rm, KnnConfig(k=5, metric="sorensen", index="ivf", ivf_clusters=12, ivf_probes=4,
                                   min_common=min_common)).locate(q)
    assert np.mean((np.sort(few.neighbours, 1) == np.sort(exact.neighbours, 1)).all(1)) > 0.8


def test_integer_rss_with_ties_is_bit_identical_to_exact() -> None:
    # Whole-dBm readings and repeated fingerprints: many tied distances, which must be ordered
    # by map row as the exact path does; integer arithmetic makes the distances bit-identical.
    rm, q = building(300, 150, seed=3, integer=True)
    dup = [dict(s) for s in q[:20]]
    rm2 = RadioMap.from_scans(
        [*q[:20], *dup, *[dict(s) for s in q[20:60]]], np.random.default_rng(1).uniform(0, 50, (80, 2)),
        session_ids="s", t_ns=np.arange(80), frame="f", missing_dbm=-100, min_rssi_dbm=-95,
    )
    for m in (rm, rm2):
        for k in (1, 3, 8):
            exact = KnnLocator(m, KnnConfig(metric="eq9", k=k)).locate(q)
            ivf = KnnLocator(m, KnnConfig(metric="eq9", k=k, index="ivf", ivf_clusters=9, ivf_probes=9)).locate(q)
            np.testing.assert_array_equal(ivf.neighbours, exact.neighbours)
            np.testing.assert_array_equal(ivf.distances, exact.distances)


def test_clustering_is_deterministic_per_seed() -> None:
    rm, _ = building(500, 1)
    a = IvfIndex(rm.fingerprints, clusters=16, seed=4)
    b = IvfIndex(rm.fingerprints, clusters=16, seed=4)
    c = IvfIndex(rm.fingerprints, clusters=16, seed=5)
    np.testing.assert_array_equal(a.labels, b.labels)
    np.testing.assert_array_equal(a.centroids, b.centroids)
    assert not np.array_equal(a.labels, c.labels)
    assert a.sizes.sum() == len(rm) and sorted(a.members_flat.tolist()) == list(range(len(rm)))


def test_default_settings_recall_on_a_clustered_map() -> None:
    rm, q = building(3000, 300, seed=1)
    exact = KnnLocator(rm, KnnConfig(metric="eq9", k=7)).locate(q)
    ivf = KnnLocator(rm, KnnConfig(metric="eq9", k=7, index="ivf")).locate(q)
    assert ivf.config.ivf_probes == knn.DEFAULT_IVF_PROBES
    assert ivf is not None and default_clusters(3000) == 110
    same = (np.sort(ivf.neighbours, axis=1) == np.sort(exact.neighbours, axis=1)).all(axis=1)
    assert same.mean() >= 0.9
    assert np.median(np.linalg.norm(ivf.xy - exact.xy, axis=1)) < 1e-9


def test_empty_clusters_are_dropped() -> None:
    # 5 distinct fingerprints, 20 clusters asked for: k-means cannot fill them all.
    rng = np.random.default_rng(2)
    base = [{f"ap{j}": float(rng.uniform(-90, -40)) for j in range(6)} for _ in range(5)]
    scans = [dict(base[i % 5]) for i in range(60)]
    rm = RadioMap.from_scans(scans, rng.uniform(0, 10, (60, 2)), session_ids="s", t_ns=np.arange(60), frame="f")
    loc = KnnLocator(rm, KnnConfig(metric="eq9", k=4, index="ivf", ivf_clusters=20, ivf_probes=20))
    assert loc.ivf is not None and 1 <= loc.ivf.n_clusters <= 5 and (loc.ivf.sizes > 0).all()
    q = [{"ap0": -50.0, "ap3": -70.0}, base[2]]
    exact = KnnLocator(rm, KnnConfig(metric="eq9", k=4)).locate(q)
    got = loc.locate(q)
    np.testing.assert_array_equal(got.neighbours, exact.neighbours)
    np.testing.assert_allclose(got.distances, exact.distances, rtol=1e-12)
    cent, labels = kmeans(np.zeros((7, 3), np.float32), 4)
    assert len(cent) == 1 and (labels == 0).all()


def test_unanswerable_queries_are_flagged_as_in_the_exact_path() -> None:
    rm, q = building(400, 3)
    queries = [q[0], {"unknown": -50.0}, {"ap1": -99.0}]  # ok, unknown AP only, below min_rssi only
    for index in ("exact", "ivf"):
        loc = KnnLocator(rm, KnnConfig(metric="eq9", k=3, index=index, ivf_clusters=10, ivf_probes=2))  # type: ignore[arg-type]
        res = loc.locate(queries)
        assert res.status.tolist() == ["ok", "no_known_ap", "no_known_ap"]
        assert np.isnan(res.xy[1:]).all() and (res.neighbours[1:] == -1).all()
        with pytest.raises(QueryError, match="#1: no_known_ap"):
            loc.locate(queries, strict=True)


def test_too_few_candidates_in_the_probed_clusters_fall_back_to_exact() -> None:
    # One probe, and a query hearing one AP that only a far-away corner of the map hears:
    # whatever cluster is probed, the k answers must be the exact ones.
    rm, q = building(400, 50, seed=6)
    exact = KnnLocator(rm, KnnConfig(metric="eq9", k=6)).locate(q)
    ivf = KnnLocator(rm, KnnConfig(metric="eq9", k=6, index="ivf", ivf_clusters=40, ivf_probes=1)).locate(q)
    np.testing.assert_array_equal(ivf.n_neighbours, exact.n_neighbours)
    assert ivf.valid.all()


def test_index_config_and_auto(monkeypatch: pytest.MonkeyPatch) -> None:
    for bad in ({"index": "hnsw"}, {"ivf_probes": 0}, {"ivf_clusters": 0}, {"ivf_probes": True}):
        with pytest.raises(ConfigError):
            KnnConfig(metric="eq9", **bad)  # type: ignore[arg-type]
    rm, _ = building(300, 1)
    assert KnnLocator(rm, KnnConfig(metric="eq9", index="auto")).index_kind == "exact"
    monkeypatch.setattr(knn, "IVF_AUTO_MIN_REFS", 200)
    assert KnnLocator(rm, KnnConfig(metric="eq9", index="auto")).index_kind == "ivf"
    assert KnnLocator(rm, KnnConfig(metric="eq9", index="exact")).index_kind == "exact"
    assert KnnConfig().index == "auto" and KnnLocator(rm).index_kind == "ivf"  # auto is the default, for either metric


def test_fingerprints_outside_the_index_count_as_extra_aps() -> None:
    # Query APs unknown to the map add to eq. 9's numerator and |U| in the IVF path too.
    rm, q = building(300, 40, seed=8)
    q2 = [{**s, "zz:1": -60.0, "zz:2": -80.0} for s in q]
    exact = KnnLocator(rm, KnnConfig(metric="eq9", k=3)).locate(q2)
    ivf = KnnLocator(rm, KnnConfig(metric="eq9", k=3, index="ivf", ivf_clusters=8, ivf_probes=8)).locate(q2)
    np.testing.assert_allclose(ivf.distances, exact.distances, rtol=1e-12)
    fm = rm.encode(q2)
    assert isinstance(fm, FingerprintMatrix) and (fm.extra_n == 2).all()


def test_blas_limit_reaches_the_openblas_that_scipy_linalg_loads_later() -> None:
    # A fresh interpreter: numpy's OpenBLAS is loaded, scipy.linalg's (its own copy in the wheels)
    # not yet -- as in a command that limits threads before importing the trackers lazily.
    code = (
        "from graphslam.core.radiomap.ivf import limit_blas_threads\n"
        "limit_blas_threads(1)\n"
        "import scipy.linalg\n"
        "from threadpoolctl import threadpool_info\n"
        "print(max(i['num_threads'] for i in threadpool_info() if i['user_api'] == 'blas'))\n"
    )
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert out.stdout.strip() == "1"
