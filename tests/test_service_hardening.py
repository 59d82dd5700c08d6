"""The service against hostile or careless use, on a REAL uvicorn server on 127.0.0.1:
deep JSON, offline /docs, bearer token, log level, a warning for a non-loopback bind,
concurrent single requests answered together (each with its own answer and its own 4xx)."""

from __future__ import annotations

import asyncio
import logging
import re
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Iterator

import httpx
import numpy as np
import pytest
from test_service import RM

from graphslam.core.radiomap.knn import KnnConfig, KnnLocator
from graphslam.service.app import create_app
from graphslam.service.coalesce import Coalescer
from graphslam.service.parsing import MAX_JSON_DEPTH, json_depth
from graphslam.service.server import BackgroundServer, is_loopback, start_background_server

TOKEN = "s3cret-token"


@pytest.fixture(scope="module")
def server() -> Iterator[BackgroundServer]:
    with start_background_server(create_app(RM, k=3, max_body_bytes=1 << 22)) as srv:
        yield srv


@pytest.fixture(scope="module")
def guarded() -> Iterator[BackgroundServer]:
    with start_background_server(create_app(RM, k=3, token=TOKEN)) as srv:
        yield srv


def post(url: str, body: bytes, **headers: str) -> httpx.Response:
    return httpx.post(f"{url}/v1/locate", content=body, headers={"content-type": "application/json", **headers},
                      timeout=30)


@pytest.mark.parametrize("depth", [40, 1000, 1100, 100_000])
@pytest.mark.parametrize("shape", ["arrays", "objects", "nan first"])
def test_deep_json_is_422_never_500(server: BackgroundServer, depth: int, shape: str) -> None:
    # 1000+: the standard parser's recursion limit (a 500 and a RecursionError per request before);
    # 1100: orjson refuses it too (its own limit is 1024); "nan first": orjson refuses at once.
    inner = b"[" * depth + b"]" * depth if shape != "objects" else b'{"a":' * depth + b"1" + b"}" * depth
    head = b'{"readings": {"ap1": NaN, "x": ' if shape == "nan first" else b'{"readings": {"x": '
    r = post(server.url, head + inner + b"}}")
    assert r.status_code == 422, r.text[:300]
    detail = r.json()["detail"]
    assert detail.startswith("malformed JSON body") or "readings" in detail
    if depth > MAX_JSON_DEPTH and shape == "nan first":
        assert f"nested deeper than {MAX_JSON_DEPTH} levels" in detail
    assert httpx.get(f"{server.url}/healthz").status_code == 200


def test_json_depth_ignores_brackets_in_strings() -> None:
    assert json_depth(b'{"a": [1, {"b": "[[[{{"}], "c\\"[": 2}') == 3
    assert json_depth(b"[" * 50) == 50 and json_depth(b"") == 0


def test_docs_render_from_packaged_assets(server: BackgroundServer) -> None:
    for page in ("/docs", "/redoc"):
        html = httpx.get(server.url + page).text
        assets = re.findall(r'(?:src|href)="([^"]+)"', html)
        assert assets and all(a.startswith("/") for a in assets), assets  # nothing from a CDN
        for a in assets:
            r = httpx.get(server.url + a)
            assert r.status_code == 200 and len(r.content) > 1000, a
    assert "openapi.json" in httpx.get(server.url + "/docs").text


def test_bearer_token(guarded: BackgroundServer) -> None:
    body = b'{"readings": {"ap1": -50}}'
    for headers in ({}, {"authorization": "Bearer wrong"}, {"authorization": TOKEN}):
        r = post(guarded.url, body, **headers)
        assert r.status_code == 401 and r.headers["www-authenticate"] == "Bearer", headers
        assert "bearer token" in r.json()["detail"]
    assert post(guarded.url, body, authorization=f"Bearer {TOKEN}").status_code == 200
    assert httpx.get(f"{guarded.url}/v1/radio-map").status_code == 401
    assert httpx.get(f"{guarded.url}/healthz").status_code == 200
    spec = httpx.get(f"{guarded.url}/openapi.json").json()
    assert spec["components"]["securitySchemes"]["bearer"]["scheme"] == "bearer"
    assert spec["paths"]["/v1/locate"]["post"]["security"] == [{"bearer": []}]
    assert httpx.get(f"{guarded.url}/docs").status_code == 200


def test_non_loopback_without_token_warns(monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture,
                                          tmp_path: Path) -> None:
    import uvicorn

    from graphslam.errors import GraphSlamError
    from graphslam.io.radiomap_io import write_radio_map
    from graphslam.service import server as srv
    from graphslam.service.config import ServeConfig

    assert is_loopback("127.0.0.1") and is_loopback("::1") and is_loopback("localhost")
    assert not is_loopback("0.0.0.0") and not is_loopback("::") and not is_loopback("192.168.1.4")
    path = write_radio_map(RM, tmp_path / "m.parquet")
    runs: list[dict] = []
    # the socket is bound (a free port) and closed: nothing is served
    monkeypatch.setattr(uvicorn.Server, "run", lambda self, sockets: (runs.append({"log_level": self.config.log_level}),
                                                                      [s.close() for s in sockets]))
    with caplog.at_level(logging.WARNING, logger="graphslam.service.server"):
        srv.serve(path, ServeConfig(host="0.0.0.0", port=0, search_processes=0, log_level="warning"))
        assert "without a bearer token" in caplog.text
        caplog.clear()
        srv.serve(path, ServeConfig(host="0.0.0.0", port=0, search_processes=0, token=TOKEN))
        srv.serve(path, ServeConfig(host="127.0.0.1", port=0, search_processes=0))
        assert "without a bearer token" not in caplog.text
    assert [r["log_level"] for r in runs] == ["warning", "info", "info"]
    with pytest.raises(GraphSlamError, match="serve: log_level: Input should be 'critical'"):
        srv.serve(path, ServeConfig(log_level="loud", search_processes=0))


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_serve_log_level_drops_the_access_line(tmp_path: Path) -> None:
    from graphslam.io.radiomap_io import write_radio_map

    path = write_radio_map(RM, tmp_path / "m.parquet")
    procs = {}
    for level in ("info", "warning"):  # both at once: each start is ~1 s of imports
        port = free_port()
        with open(tmp_path / f"{level}.log", "wb") as fh:
            procs[level] = port, subprocess.Popen(
                [sys.executable, "-m", "graphslam", "serve", "--radio-map", str(path), "--port", str(port),
                 "--search-processes", "0", "--log-level", level], stdout=fh, stderr=fh,  # (access lines: stdout)
            )
    try:
        for level, (port, proc) in procs.items():
            deadline = time.monotonic() + 60
            while True:
                try:
                    assert post(f"http://127.0.0.1:{port}", b'{"readings": {"ap1": -50}}').status_code == 200
                    break
                except httpx.TransportError:
                    assert time.monotonic() < deadline and proc.poll() is None, (tmp_path / f"{level}.log").read_text()
                    time.sleep(0.2)
    finally:
        for _, proc in procs.values():
            proc.terminate()
            proc.wait(20)
    logs = {level: (tmp_path / f"{level}.log").read_text() for level in procs}
    assert '"POST /v1/locate HTTP/1.1" 200' in logs["info"]
    assert "POST /v1/locate" not in logs["warning"] and "Traceback" not in logs["warning"]


@pytest.mark.parametrize("workers", ["1", "2"])
def test_serve_a_bad_map_is_one_line_and_exit_2(tmp_path: Path, workers: str) -> None:
    bad = tmp_path / "bad.parquet"
    bad.write_bytes(b"not a parquet file")
    p = subprocess.run([sys.executable, "-m", "graphslam", "serve", "--radio-map", str(bad), "--port", "0",
                        "--workers", workers], capture_output=True, text=True, timeout=120)
    lines = (p.stdout + p.stderr).strip().splitlines()
    # the map's error alone: no "serving ... on http://..." line before it
    assert p.returncode == 2 and len(lines) == 1, lines
    assert lines[0].startswith(f"error: {bad}: not a readable Parquet file"), lines


def test_concurrent_single_requests_each_get_their_own_answer(server: BackgroundServer) -> None:
    rng = np.random.default_rng(5)
    scans = [{f"ap{j}": float(rng.integers(-90, -40)) for j in rng.choice(12, 4, replace=False)} for _ in range(64)]
    scans[17] = {"nobody-heard-me": -50.0}  # unlocatable: 404 for its own request only
    expect = KnnLocator(RM, KnnConfig(k=3)).locate(scans)
    got: dict[int, httpx.Response] = {}
    barrier = threading.Barrier(8)

    def client(w: int) -> None:
        with httpx.Client(base_url=server.url, timeout=30) as c:
            barrier.wait()
            for i in range(w, len(scans), 8):
                got[i] = c.post("/v1/locate", json={"readings": scans[i]})

    threads = [threading.Thread(target=client, args=(w,)) for w in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert got[17].status_code == 404 and got[17].json()["status"] == "no_known_ap"
    for i, r in got.items():
        if i != 17:
            assert r.status_code == 200, r.text
            p = r.json()["positions"][0]
            np.testing.assert_allclose([p["x"], p["y"]], expect.xy[i], rtol=0, atol=1e-9)
            assert p["floor"] == expect.floor[i]  # type: ignore[index]


def test_small_request_fast_path_answers_what_the_route_would(server: BackgroundServer) -> None:
    import orjson

    from graphslam.service.render import position_dicts

    q = [{"ap1": -50.0, "ap2": -70.0, "unknown": -40.0}, {"ap5": -60, "ap7": -80.5}]
    expect = orjson.dumps({"frame": "aligned", "k": 3, "weighted": True,
                           "positions": position_dicts(KnnLocator(RM, KnnConfig(k=3)).locate(q))})
    r = post(server.url, orjson.dumps({"fingerprints": [{"readings": s} for s in q]}))
    assert r.status_code == 200 and r.content == expect  # the route's bytes: Response(orjson.dumps(...))
    assert r.headers["content-type"] == "application/json" and int(r.headers["content-length"]) == len(expect)
    # declined by the fast path (pydantic's message), or answered by the route (no known AP: a 404)
    assert post(server.url, b'{"readings": {"ap1": "-50"}}').status_code == 422
    assert post(server.url, b'{"readings": {"zz": -50}}').json()["reason"] == "notFound"
    # a small batch with a fingerprint not located: answered on the fast path, as the route renders it
    q2 = [q[0], {"zz": -50.0}]
    expect = orjson.dumps({"frame": "aligned", "k": 3, "weighted": True,
                           "positions": position_dicts(KnnLocator(RM, KnnConfig(k=3)).locate(q2))})
    r = post(server.url, orjson.dumps({"fingerprints": [{"readings": s} for s in q2]}))
    assert r.status_code == 200 and r.content == expect and r.json()["positions"][1]["error"]["reason"] == "notFound"


def test_coalescer_searches_once_per_loop_pass() -> None:
    calls: list[int] = []
    loc = KnnLocator(RM, KnnConfig(k=3))

    def search(scans: list) -> object:
        calls.append(len(scans))
        return loc.locate(scans)

    scans = [{"ap1": -50.0}, {"ap2": -60.0, "ap3": -70.0}, {"ap4": -55.0}]

    async def main() -> list:
        co = Coalescer(search, max_rows=3)
        first = await asyncio.gather(co.locate(scans[:1]), co.locate(scans[1:]), co.locate(scans[:1]))
        alone = await co.locate(scans[2:])
        return [*first, alone]

    a, b, c, alone = asyncio.run(main())
    assert calls == [3, 1, 1]  # rows 1+2 in one pass, the third request did not fit (max_rows 3)
    expect = loc.locate(scans)
    assert np.allclose(a.xy, expect.xy[:1]) and np.allclose(b.xy, expect.xy[1:]) and np.allclose(c.xy, expect.xy[:1])
    assert np.allclose(alone.xy, expect.xy[2:]) and len(b) == 2

    def broken(scans: list) -> object:
        raise RuntimeError("worker died")

    async def failing() -> list:
        co = Coalescer(broken)
        return await asyncio.gather(co.locate(scans[:1]), co.locate(scans[1:]), return_exceptions=True)

    assert all(isinstance(e, RuntimeError) for e in asyncio.run(failing()))
