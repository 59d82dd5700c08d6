"""Search process pool (graphslam.service.pool) behind a REAL uvicorn server on 127.0.0.1."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from typing import Any, Iterator

import httpx
import numpy as np
import psutil
import pytest
from threadpoolctl import threadpool_limits

from graphslam.core.radiomap.knn import KnnConfig, KnnLocator
from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.service import pool as pool_mod
from graphslam.service.app import create_app
from graphslam.service.pool import SEARCH_POOL_MIN_BATCH, SearchPool
from graphslam.service.server import start_background_server

pytestmark = pytest.mark.skipif(not pool_mod.fork_available(), reason="needs the fork start method")

IVF = dict(index="ivf", ivf_clusters=8, ivf_probes=3)


def scans(n: int, seed: int, n_aps: int) -> list[dict[str, float]]:
    rng = np.random.default_rng(seed)
    return [
        {f"ap{j}": float(rng.uniform(-95, -35)) for j in rng.choice(n_aps, int(rng.integers(3, 12)), replace=False)}
        for _ in range(n)
    ]


def radio_map(n_aps: int) -> RadioMap:
    rng = np.random.default_rng(3)
    n = 600
    return RadioMap.from_scans(
        scans(n, 1, n_aps), rng.uniform(0, 60, (n, 2)), session_ids="s", t_ns=np.arange(n), frame="aligned",
        floors=rng.choice(["F1", "F2", "F3"], n).tolist(),
    )


# 200 APs, ~3% heard: exact search on sparse products, where every row is computed on its own
# (like UJIIndoorLoc). 40 APs: dense BLAS (DistanceEngine), like the IVF index's GEMMs.
RM = radio_map(200)
RM_DENSE = radio_map(40)
QUERIES = scans(301, 2, 200)  # odd: chunks of unequal size
QUERIES_DENSE = scans(301, 2, 40)
FIELDS = ("xy", "score", "spread", "neighbours", "distances", "n_known_aps", "floor", "building")


@pytest.fixture(autouse=True)
def one_blas_thread() -> Iterator[None]:
    # As in `graphslam serve` and in the workers: the BLAS thread count changes GEMM rounding
    # (dense maps, IVF), so "identical" compares searches with the same setting.
    with threadpool_limits(limits=1, user_api="blas"):
        yield


def alive(pids: tuple[int, ...]) -> list[int]:
    """Those of ``pids`` still running (zombies count as gone: they are not ours to reap here)."""
    out = []
    for pid in pids:
        try:
            if psutil.Process(pid).status() != psutil.STATUS_ZOMBIE:
                out.append(pid)
        except psutil.NoSuchProcess:
            pass
    return out


def wait_gone(pids: tuple[int, ...], timeout: float = 10.0) -> list[int]:
    deadline = time.monotonic() + timeout
    while alive(pids) and time.monotonic() < deadline:
        time.sleep(0.05)
    return alive(pids)


def post(c: httpx.Client, qs: list[dict[str, float]]) -> httpx.Response:
    return c.post("/v1/locate", json={"fingerprints": [{"readings": q} for q in qs]})


def assert_same(expect: Any, got: Any, rtol: float = 0.0) -> None:
    for f in FIELDS:
        a, b = getattr(expect, f), getattr(got, f)
        if a is None:
            assert b is None
        elif a.dtype.kind == "f" and rtol:
            np.testing.assert_allclose(b, a, rtol=rtol, atol=0)
        elif a.dtype.kind == "f":
            np.testing.assert_array_equal(b, a)  # same floats, NaN where NaN
        else:
            assert np.array_equal(a, b), f
    assert got.config == expect.config


@pytest.mark.parametrize("processes", [1, 2, 3])
def test_pool_result_is_identical_to_in_process_sparse_exact(processes: int) -> None:
    loc = KnnLocator(RM, KnnConfig(k=4, index="exact"))
    assert not loc.engine.dense and loc.ivf is None
    expect = loc.locate(QUERIES)
    assert expect.valid.mean() > 0.9
    with SearchPool(loc, processes) as sp:
        assert sp.processes == processes and len(sp.pids) == processes
        assert_same(expect, sp.locate(QUERIES))
        assert_same(loc.locate(QUERIES[:5]), sp.locate(QUERIES[:5]))  # below min_batch: in-process


@pytest.mark.parametrize("processes", [1, 2, 3])
@pytest.mark.parametrize(
    "config,dense_map", [(IVF, False), (IVF, True), (dict(index="exact"), True)], ids=["ivf", "ivf-dense", "exact-dense"]
)
def test_pool_result_with_blas_is_the_in_process_one_up_to_rounding(
    config: dict[str, Any], dense_map: bool, processes: int
) -> None:
    # BLAS GEMMs (the IVF index's per-cluster products; exact search on a dense map) round a
    # row's distances differently depending on the other rows of the product: in-process too, a
    # query alone and the same query in a batch differ by ~1e-15. Chunks change the batches, so:
    # same neighbours and labels, floats equal to ~1 ulp.
    rm, qs = (RM_DENSE, QUERIES_DENSE) if dense_map else (RM, QUERIES)
    loc = KnnLocator(rm, KnnConfig(k=4, **config))
    expect = loc.locate(qs)
    with SearchPool(loc, processes) as sp:
        got = sp.locate(qs)
    assert_same(expect, got, rtol=1e-13)
    if processes == 1:  # one chunk = the same batch: bit for bit
        assert_same(expect, got)
    assert expect.valid.mean() > 0.9


def test_http_batch_identical_with_and_without_pool_and_no_leaked_processes() -> None:
    assert len(QUERIES) >= SEARCH_POOL_MIN_BATCH
    bodies = {}
    pids: tuple[int, ...] = ()
    for processes in (0, 2):
        app = create_app(RM, k=4, max_batch=1000, search_processes=processes, index="exact")
        assert not app.state.locator.engine.dense
        sp = app.state.search_pool
        assert sp.processes == processes
        if processes:
            pids = sp.pids
            assert len(alive(pids)) == 2
            assert set(pids) <= {p.pid for p in psutil.Process().children()}
        with start_background_server(app) as srv, httpx.Client(base_url=srv.url, timeout=30.0) as c:
            r = post(c, QUERIES)
            assert r.status_code == 200, r.text
            bodies[processes] = r.content
            one = c.post("/v1/locate", json={"readings": QUERIES[0]})
            assert one.status_code == 200 and one.json()["positions"][0] == r.json()["positions"][0]
    assert bodies[0] == bodies[2]  # byte for byte: same neighbours, same floats
    assert wait_gone(pids) == [], "search workers outlived the server"
    assert not set(pids) & {p.pid for p in psutil.Process().children()}


def test_a_big_batch_answers_its_unlocatable_fingerprints_per_item_as_in_process() -> None:
    bad = list(QUERIES)
    unknown = (3, 70, 71, 200, 250, 290, 300)
    for i in unknown:
        bad[i] = {"unknown-ap": -50.0}
    bodies = {}
    for processes in (0, 2):  # in the server process (thread pool) and on the search processes (the body path)
        app = create_app(RM, k=4, max_batch=1000, search_processes=processes, **IVF)  # type: ignore[arg-type]
        with start_background_server(app) as srv, httpx.Client(base_url=srv.url, timeout=30.0) as c:
            r = post(c, bad)
            good = post(c, QUERIES)
        assert r.status_code == 200, r.text
        bodies[processes] = r.content
        pos, expect = r.json()["positions"], good.json()["positions"]
        assert [i for i, p in enumerate(pos) if "error" in p] == list(unknown)
        assert all(pos[i]["x"] is None and pos[i]["error"]["status"] == "no_known_ap" for i in unknown)
        assert all(pos[i] == expect[i] for i in range(len(pos)) if i not in unknown)
    assert bodies[0] == bodies[2]  # byte for byte


def test_worker_crash_is_503_then_searches_in_process() -> None:
    app = create_app(RM, k=4, max_batch=1000, search_processes=2, **IVF)  # type: ignore[arg-type]
    expect = KnnLocator(RM, KnnConfig(k=4, **IVF)).locate(QUERIES)  # type: ignore[arg-type]
    pids = app.state.search_pool.pids
    with start_background_server(app) as srv, httpx.Client(base_url=srv.url, timeout=30.0) as c:
        assert post(c, QUERIES).status_code == 200
        os.kill(pids[0], signal.SIGKILL)
        assert c.post("/v1/locate", json={"readings": QUERIES[0]}).status_code == 200  # small: never on the pool
        r = post(c, QUERIES)
        assert r.status_code == 503, r.text
        assert "search worker process died" in r.json()["detail"]
        assert wait_gone(pids) == []  # the survivor is stopped too
        assert app.state.search_pool.processes == 0
        r = post(c, QUERIES)  # in-process from now on: same answer
        assert r.status_code == 200
        got = np.array([[p["x"], p["y"]] for p in r.json()["positions"]])
        np.testing.assert_array_equal(got, expect.xy)
        assert c.get("/healthz").status_code == 200


def test_no_fork_means_in_process(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(pool_mod, "fork_available", lambda: False)
    loc = KnnLocator(RM, KnnConfig(k=4))
    sp = SearchPool(loc, 2)
    assert sp.processes == 0 and sp.pids == ()
    np.testing.assert_array_equal(sp.locate(QUERIES).xy, loc.locate(QUERIES).xy)
    sp.close()


def test_close_is_idempotent_and_stops_workers() -> None:
    sp = SearchPool(KnnLocator(RM, KnnConfig(k=4)), 2)
    pids = sp.pids
    sp.close()
    sp.close()
    assert wait_gone(pids) == [] and sp.processes == 0
    assert len(sp.locate(QUERIES)) == len(QUERIES)  # in-process after close
    with pytest.raises(Exception, match="search processes must be an integer >= 0"):
        SearchPool(sp.locator, -1)


def test_cli_serve_has_the_option() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "graphslam.cli", "serve", "--help"], capture_output=True, text=True, timeout=60,
        env={**os.environ, "COLUMNS": "200"},
    )
    assert out.returncode == 0 and "--search-processes" in out.stdout


def test_pool_path_keeps_the_4xx_semantics() -> None:
    app = create_app(RM, k=4, max_batch=200, search_processes=2, **IVF)  # type: ignore[arg-type]
    big = [{"readings": q} for q in QUERIES]
    bad_value = [dict(f) for f in big]
    bad_value[250] = {"readings": {"ap1": "-50"}}  # the workers' fast parser declines: pydantic's message
    with start_background_server(app) as srv, httpx.Client(base_url=srv.url, timeout=30.0) as c:
        r = c.post("/v1/locate", json={"fingerprints": big})
        assert r.status_code == 413 and r.json()["detail"] == "batch of 301 fingerprints, at most 200 per request"
        r = c.post("/v1/locate", json={"fingerprints": bad_value[:200]})
        assert r.status_code == 200  # row 250 is not in the first 200
        r = c.post("/v1/locate", json={"fingerprints": bad_value[100:]})
        assert r.status_code == 422, r.text
        assert "fingerprints.150.readings.ap1: Input should be a valid number" in r.json()["detail"]
        body = b'{"fingerprints": [' + b" " * 20000 + b"]"
        r = c.post("/v1/locate", content=body, headers={"content-type": "application/json"})
        assert r.status_code == 422 and r.json()["detail"].startswith("malformed JSON body")
        r = c.post("/v1/locate", content=b"x" * 20000, headers={"content-type": "text/plain"})
        assert 400 <= r.status_code < 500
