"""Search pool over raw pipes: body path results, concurrency, and every failure path ends in
an error (503 over HTTP), never a hang."""

from __future__ import annotations

import gc
import json
import os
import signal
import threading
import time
from pathlib import Path
from typing import Any, Callable, Iterator

import httpx
import numpy as np
import orjson
import pytest
from threadpoolctl import threadpool_limits

from graphslam.core.radiomap.knn import KnnConfig, KnnLocator
from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.errors import QueryError
from graphslam.service import pool as pool_mod
from graphslam.service.app import create_app
from graphslam.service.pool import SearchPool, SearchUnavailableError
from graphslam.service.render import position_rows
from graphslam.service.server import start_background_server
from test_service_pool import alive

pytestmark = pytest.mark.skipif(not pool_mod.fork_available(), reason="needs the fork start method")

IVF = dict(index="ivf", ivf_clusters=8, ivf_probes=3)
FIELDS = ("xy", "score", "spread", "neighbours", "distances", "n_known_aps", "floor", "building")


def scans(n: int, seed: int, n_aps: int) -> list[dict[str, float]]:
    rng = np.random.default_rng(seed)
    return [
        {f"ap{j}": float(rng.uniform(-95, -35)) for j in rng.choice(n_aps, int(rng.integers(3, 12)), replace=False)}
        for _ in range(n)
    ]


def radio_map() -> RadioMap:
    rng = np.random.default_rng(3)
    n = 600
    return RadioMap.from_scans(
        scans(n, 1, 200), rng.uniform(0, 60, (n, 2)), session_ids="s", t_ns=np.arange(n), frame="aligned",
        floors=rng.choice(["F1", "F2", "F3"], n).tolist(),
    )


RM = radio_map()
QUERIES = scans(301, 2, 200)


def body(qs: list[dict[str, float]]) -> bytes:
    return json.dumps({"fingerprints": [{"readings": q} for q in qs]}).encode()


@pytest.fixture(autouse=True)
def one_blas_thread() -> Iterator[None]:
    with threadpool_limits(limits=1, user_api="blas"):  # as in the workers (see test_service_pool)
        yield


def wait_gone(pids: tuple[int, ...], timeout: float = 10.0) -> list[int]:
    deadline = time.monotonic() + timeout
    while alive(pids) and time.monotonic() < deadline:
        time.sleep(0.05)
    return alive(pids)


def stalling(marker_dir: Path, then: Callable[..., Any] | None = None) -> Callable[..., Any]:
    """A worker op that says it started (a file named after its pid), then hangs (or calls ``then``
    once the test removes the file)."""

    def op(*args: Any) -> Any:
        mark = marker_dir / str(os.getpid())
        mark.touch()
        while mark.exists():
            time.sleep(0.01)
        return then(*args) if then is not None else None

    return op


def wait_for_marks(marker_dir: Path, n: int = 1, timeout: float = 60.0) -> list[int]:
    deadline = time.monotonic() + timeout
    while len(list(marker_dir.iterdir())) < n:
        assert time.monotonic() < deadline, "the worker op never started"
        time.sleep(0.01)
    return [int(p.name) for p in marker_dir.iterdir()]


def in_thread(fn: Callable[[], Any]) -> tuple[threading.Thread, dict[str, Any]]:
    out: dict[str, Any] = {}

    def run() -> None:
        try:
            out["value"] = fn()
        except BaseException as e:  # noqa: BLE001 - handed to the test
            out["error"] = e

    t = threading.Thread(target=run, daemon=True)
    t.start()
    return t, out


@pytest.mark.parametrize("processes", [1, 2, 3])
def test_body_path_is_the_in_process_search(processes: int) -> None:
    loc = KnnLocator(RM, KnnConfig(k=4, **IVF))  # type: ignore[arg-type]
    qs = QUERIES + [{"unknown-ap": -50.0}, {"ap1": -99.0, "zz": -40.0}]  # an invalid row; a strongest AP unknown
    expect = loc.locate(qs)
    with SearchPool(loc, processes) as sp:
        got = sp.locate_body(body(qs), max_batch=1000)
        assert got is not None
        for f in FIELDS:  # same neighbours and labels; floats up to the GEMMs' rounding (test_service_pool)
            a, b = getattr(expect, f), getattr(got, f)
            if a is None:
                assert b is None
            elif a.dtype.kind == "f":
                np.testing.assert_allclose(b, a, rtol=1e-13, atol=0)
            else:
                assert np.array_equal(a, b), f
        with pytest.raises(QueryError, match="1 of 303 queries cannot be located"):
            sp.locate_body(body(qs), max_batch=1000, strict=True)
        res, rows = sp.locate_body_json(body(QUERIES), max_batch=1000, strict=True)  # type: ignore[misc]
        assert [orjson.loads(r) for r in rows] == [orjson.loads(r) for r in position_rows(res)]
        res, rows = sp.locate_body_json(body(qs), max_batch=1000)  # type: ignore[misc]
        assert len(rows) == len(qs) and orjson.loads(rows[-2])["x"] is None  # NaN -> null, as in-process


def test_concurrent_requests_share_the_workers() -> None:
    loc = KnnLocator(RM, KnnConfig(k=4, **IVF))  # type: ignore[arg-type]
    batches = [scans(80 + 17 * i, 10 + i, 200) for i in range(6)]
    expect = [loc.locate(b).neighbours for b in batches]
    with SearchPool(loc, 2) as sp:
        runs = [in_thread(lambda i=i: [sp.locate_body(body(batches[i]), max_batch=1000) for _ in range(3)])
                for i in range(6)]
        for t, out in runs:
            t.join(120)
            assert not t.is_alive() and "error" not in out, out.get("error")
        for (_, out), want in zip(runs, expect):
            assert all(np.array_equal(r.neighbours, want) for r in out["value"])


@pytest.mark.parametrize("victim", [0, 1])
def test_worker_killed_mid_request_is_503_not_a_hang(
    victim: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Either share's worker: the request must not wait for the other share (stuck here) first.
    monkeypatch.setitem(pool_mod._OPS, "body", stalling(tmp_path))  # inherited by the workers at fork
    app = create_app(RM, k=4, max_batch=1000, search_processes=2, **IVF)  # type: ignore[arg-type]
    pids = app.state.search_pool.pids
    with start_background_server(app) as srv, httpx.Client(base_url=srv.url, timeout=60.0) as c:
        headers = {"content-type": "application/json"}
        t, out = in_thread(lambda: c.post("/v1/locate", content=body(QUERIES), headers=headers))
        assert sorted(wait_for_marks(tmp_path, n=2)) == sorted(pids)
        os.kill(pids[victim], signal.SIGKILL)
        t.join(60)
        assert not t.is_alive() and "error" not in out
        r = out["value"]
        assert r.status_code == 503 and "search worker process died" in r.json()["detail"]
        assert wait_gone(pids) == [] and app.state.search_pool.processes == 0
        r = c.post("/v1/locate", content=body(QUERIES), headers={"content-type": "application/json"})
        assert r.status_code == 200 and len(r.json()["positions"]) == len(QUERIES)  # in-process now


def test_timeout_is_an_error_and_retires_the_pool(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(pool_mod._OPS, "body", stalling(tmp_path))
    sp = SearchPool(KnnLocator(RM, KnnConfig(k=4, **IVF)), 2, timeout=0.5)  # type: ignore[arg-type]
    pids = sp.pids
    with pytest.raises(SearchUnavailableError, match="did not answer within 0.5 s"):
        sp.locate_body(body(QUERIES), max_batch=1000)
    assert sp.processes == 0 and wait_gone(pids) == []
    assert sp.locate_body(body(QUERIES), max_batch=1000) is None  # no pool: the caller searches in-process
    assert len(sp.locate(QUERIES)) == len(QUERIES)
    sp.close()


def test_close_during_a_request_fails_it_without_hanging(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(pool_mod._OPS, "body", stalling(tmp_path))
    monkeypatch.setattr(pool_mod, "SHUTDOWN_TIMEOUT_S", 0.5)  # the grace period before kill
    sp = SearchPool(KnnLocator(RM, KnnConfig(k=4, **IVF)), 2)  # type: ignore[arg-type]
    pids = sp.pids
    t, out = in_thread(lambda: sp.locate_body(body(QUERIES), max_batch=1000))
    wait_for_marks(tmp_path)
    sp.close()
    t.join(60)
    assert not t.is_alive() and isinstance(out.get("error"), SearchUnavailableError)
    assert wait_gone(pids) == [] and sp.processes == 0


def test_graceful_close_lets_the_request_in_flight_finish(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(pool_mod._OPS, "body", stalling(tmp_path, then=pool_mod._locate_body))
    loc = KnnLocator(RM, KnnConfig(k=4, **IVF))  # type: ignore[arg-type]
    sp = SearchPool(loc, 2)
    pids = sp.pids
    t, out = in_thread(lambda: sp.locate_body(body(QUERIES), max_batch=1000))
    wait_for_marks(tmp_path, n=2)
    closer, _ = in_thread(sp.close)
    for mark in tmp_path.iterdir():  # let the workers go on: close() waits for them
        mark.unlink()
    t.join(60)
    closer.join(60)
    assert "error" not in out and np.array_equal(out["value"].neighbours, loc.locate(QUERIES).neighbours)
    assert wait_gone(pids) == []


def test_worker_exception_reaches_the_caller_and_the_pool_goes_on(monkeypatch: pytest.MonkeyPatch) -> None:
    real = pool_mod._locate_chunk

    def picky(chunk: list[dict[str, float]]) -> Any:
        if len(chunk) == 65:
            raise QueryError("65 is not a size I search")
        return real(chunk)

    monkeypatch.setitem(pool_mod._OPS, "chunk", picky)
    loc = KnnLocator(RM, KnnConfig(k=4, **IVF))  # type: ignore[arg-type]
    with SearchPool(loc, 2) as sp:
        with pytest.raises(QueryError, match="65 is not a size"):
            sp.locate(QUERIES[:130])  # two chunks of 65
        assert sp.processes == 2
        np.testing.assert_allclose(sp.locate(QUERIES).xy, loc.locate(QUERIES).xy, rtol=1e-13)  # no answer left over


@pytest.mark.skipif(not Path("/proc/self/fd").exists(), reason="needs /proc")
def test_no_file_descriptor_outlives_the_pool() -> None:
    gc.collect()  # earlier tests' garbage (sockets, pools) must not close fds during this one
    before = set(os.listdir("/proc/self/fd"))
    sp = SearchPool(KnnLocator(RM, KnnConfig(k=4, **IVF)), 2)  # type: ignore[arg-type]
    assert sp.locate_body(body(QUERIES), max_batch=1000) is not None
    pids = sp.pids
    os.kill(pids[1], signal.SIGKILL)  # retired on the next request
    with pytest.raises(SearchUnavailableError):
        sp.locate_body(body(QUERIES), max_batch=1000)
    sp.close()
    assert wait_gone(pids) == []
    assert set(os.listdir("/proc/self/fd")) - before == set()
