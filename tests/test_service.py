"""HTTP service against a REAL uvicorn server on 127.0.0.1 (free port), real HTTP with httpx."""

from __future__ import annotations

import json
import time
from typing import Iterator

import httpx
import numpy as np
import pytest

from graphslam.core.radiomap.knn import KnnConfig, KnnLocator
from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.service.app import create_app
from graphslam.service.server import BackgroundServer, start_background_server

MAX_BATCH = 5
MAX_BODY = 4096


def radio_map() -> RadioMap:
    rng = np.random.default_rng(7)
    scans = [{f"ap{j}": float(rng.integers(-95, -35)) for j in rng.choice(12, 5, replace=False)} for _ in range(40)]
    return RadioMap.from_scans(
        scans, rng.uniform(0, 30, (40, 2)), session_ids="s", t_ns=np.arange(40), frame="aligned",
        floors=["F1"] * 20 + ["F2"] * 20,
    )


RM = radio_map()


@pytest.fixture(scope="module")
def server() -> Iterator[BackgroundServer]:
    app = create_app(RM, k=3, max_batch=MAX_BATCH, max_body_bytes=MAX_BODY)
    with start_background_server(app, host="127.0.0.1", port=0) as srv:
        yield srv


@pytest.fixture()
def client(server: BackgroundServer) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=server.url, timeout=10.0) as c:
        yield c


def post_raw(c: httpx.Client, body: bytes | str, content_type: str = "application/json") -> httpx.Response:
    return c.post("/v1/locate", content=body, headers={"content-type": content_type})


def test_server_is_real_and_on_loopback(server: BackgroundServer, client: httpx.Client) -> None:
    assert server.host == "127.0.0.1" and server.port > 0
    r = client.get("/healthz")
    assert r.status_code == 200 and r.json() == {"status": "ok"}


def test_small_requests_are_not_delayed_by_nagle(client: httpx.Client) -> None:
    # Regression: without TCP_NODELAY on accepted sockets every response took ~40 ms (delayed ACK).
    times = []
    for _ in range(15):
        t0 = time.perf_counter()
        assert client.post("/v1/locate", json={"readings": {"ap1": -50}}).status_code == 200
        times.append(time.perf_counter() - t0)
    assert sorted(times)[len(times) // 2] < 0.025


def test_single_and_batch_match_the_library(client: httpx.Client) -> None:
    q = [{"ap1": -50.0, "ap2": -70.0, "unknown": -40.0}, {"ap5": -60, "ap7": -80.5}]
    expect = KnnLocator(RM, KnnConfig(k=3)).locate(q)
    one = client.post("/v1/locate", json={"readings": q[0]})
    assert one.status_code == 200
    p = one.json()["positions"]
    assert len(p) == 1 and [p[0]["x"], p[0]["y"]] == pytest.approx(expect.xy[0].tolist())
    batch = client.post("/v1/locate", json={"fingerprints": [{"readings": r} for r in q]})
    assert batch.status_code == 200
    body = batch.json()
    assert body["frame"] == "aligned" and body["k"] == 3 and body["weighted"] is True
    got = np.array([[d["x"], d["y"]] for d in body["positions"]])
    np.testing.assert_allclose(got, expect.xy, rtol=1e-12)
    assert [d["score"] for d in body["positions"]] == pytest.approx(expect.score.tolist())
    assert [d["floor"] for d in body["positions"]] == expect.floor.tolist()  # type: ignore[union-attr]
    assert all(d["n_neighbours"] == 3 and d["spread"] >= 0 and d["building"] is None for d in body["positions"])


def test_radio_map_summary_and_openapi(client: httpx.Client) -> None:
    s = client.get("/v1/radio-map").json()
    assert s["n_fingerprints"] == 40 and s["n_access_points"] == 12 and s["frame"] == "aligned"
    assert s["floors"] == {"F1": 20, "F2": 20} and set(s["bbox"]) == {"min_x", "min_y", "max_x", "max_y"}
    assert s["k"] == 3 and s["metric"] == "sorensen"
    spec = client.get("/openapi.json").json()
    assert {"/v1/locate", "/v1/radio-map", "/healthz"} <= set(spec["paths"])
    assert "LocateRequest" in spec["components"]["schemas"]


BAD_422 = [
    ("malformed JSON", b'{"readings": {"ap1": -50', "malformed JSON body"),
    ("not an object", b"[1, 2, 3]", "valid dictionary"),
    ("string rssi", b'{"readings": {"ap1": "-50"}}', "readings.ap1: Input should be a valid number"),
    ("bool rssi", b'{"readings": {"ap1": true}}', "readings.ap1: Input should be a valid number"),
    ("NaN", b'{"readings": {"ap1": NaN}}', "readings.ap1: Input should be a finite number"),
    ("Infinity", b'{"readings": {"ap1": -Infinity}}', "finite number"),
    ("rssi 100 (UJI not-heard)", b'{"readings": {"ap1": 100}}', "less than or equal to 0"),
    ("empty readings", b'{"readings": {}}', "readings: Dictionary should have at least 1 item"),
    ("empty batch", b'{"fingerprints": []}', "fingerprints: List should have at least 1 item"),
    ("empty bssid", b'{"readings": {"": -50}}', "at least 1 character"),
    ("readings not a map", b'{"readings": [["ap1", -50]]}', "readings: Input should be a valid dictionary"),
    ("batch item not an object", b'{"fingerprints": [3]}', "fingerprints.0"),
    ("no body fields", b"{}", "give exactly one of 'readings'"),
    ("both forms", b'{"readings": {"ap1": -50}, "fingerprints": [{"readings": {"ap1": -50}}]}', "exactly one"),
    ("extra field", b'{"readings": {"ap1": -50}, "k": 9}', "k: Extra inputs are not permitted"),
]


@pytest.mark.parametrize("name,body,message", BAD_422, ids=[b[0] for b in BAD_422])
def test_bad_requests_are_422_with_a_message(client: httpx.Client, name: str, body: bytes, message: str) -> None:
    r = post_raw(client, body)
    assert r.status_code == 422, (name, r.text)
    assert message in r.json()["detail"], r.text


@pytest.mark.parametrize("name,body", [
    ("unknown APs only", b'{"readings": {"zz:zz": -50}}'),
    ("below min_rssi only", b'{"readings": {"ap1": -105}}'),
])
def test_one_fingerprint_that_cannot_be_located_is_404_not_found(client: httpx.Client, name: str, body: bytes) -> None:
    # as Google's and Mozilla's geolocation APIs answer a query no position is found for
    r = post_raw(client, body)
    assert r.status_code == 404, (name, r.text)
    got = r.json()
    assert got["reason"] == "notFound" and got["status"] == "no_known_ap", got
    assert got["detail"] == "the fingerprint cannot be located: none of its access points is in the radio map"


def test_a_batch_answers_each_fingerprint_one_not_located_with_null_and_its_reason(client: httpx.Client) -> None:
    good = {"ap1": -50.0, "ap2": -70.0}
    for n in (2, MAX_BATCH):  # (big batches, on the thread pool and the search processes: test_service_pool)
        batch = [{"readings": good}] * n
        batch[1] = {"readings": {"nope": -50.0}}
        r = client.post("/v1/locate", json={"fingerprints": batch})
        assert r.status_code == 200, r.text
        pos = r.json()["positions"]
        assert len(pos) == n
        bad = pos[1]
        assert bad["x"] is None and bad["y"] is None and bad["sigma_m"] is None and bad["n_neighbours"] == 0
        assert bad["error"] == {"reason": "notFound", "status": "no_known_ap",
                                "message": "none of its access points is in the radio map"}
        one = client.post("/v1/locate", json={"readings": good}).json()["positions"][0]
        assert all(p == one for k, p in enumerate(pos) if k != 1)  # the others: their own answers, no error key
    # a batch of one is a batch: answered per fingerprint, not a 404
    r = client.post("/v1/locate", json={"fingerprints": [{"readings": {"nope": -50.0}}]})
    assert r.status_code == 200 and r.json()["positions"][0]["error"]["reason"] == "notFound"


def test_wrong_content_type_is_4xx(client: httpx.Client) -> None:
    r = post_raw(client, "readings=1", content_type="text/plain")
    assert 400 <= r.status_code < 500 and r.json()["detail"]


def test_oversized_batch_is_413(client: httpx.Client) -> None:
    body = {"fingerprints": [{"readings": {"ap1": -50}}] * (MAX_BATCH + 1)}
    r = client.post("/v1/locate", json=body)
    assert r.status_code == 413 and f"at most {MAX_BATCH}" in r.json()["detail"]


def test_oversized_body_is_413_declared_or_chunked(client: httpx.Client) -> None:
    big = json.dumps({"readings": {f"ap{i}": -50 for i in range(600)}}).encode()
    assert len(big) > MAX_BODY
    r = post_raw(client, big)
    assert r.status_code == 413 and f"larger than {MAX_BODY} bytes" in r.json()["detail"]

    def chunks() -> Iterator[bytes]:  # no Content-Length: chunked transfer encoding
        for i in range(0, len(big), 500):
            yield big[i : i + 500]

    r = client.post("/v1/locate", content=chunks(), headers={"content-type": "application/json"})
    assert r.status_code == 413 and "larger than" in r.json()["detail"]


def test_wrong_method_and_path_are_4xx_and_server_survives(client: httpx.Client) -> None:
    assert client.get("/v1/locate").status_code == 405
    assert client.get("/v2/nothing").status_code == 404
    assert client.get("/healthz").status_code == 200
    assert client.post("/v1/locate", json={"readings": {"ap1": -50}}).status_code == 200


def test_openapi_describes_the_locate_request_and_response(client: httpx.Client) -> None:
    spec = client.get("/openapi.json").json()
    post = spec["paths"]["/v1/locate"]["post"]
    body_schema = post["requestBody"]["content"]["application/json"]["schema"]
    assert body_schema == {"$ref": "#/components/schemas/LocateRequest"} and post["requestBody"]["required"]
    schemas = spec["components"]["schemas"]
    assert {"LocateRequest", "Fingerprint", "LocateResponse", "Position"} <= set(schemas)
    assert set(schemas["LocateRequest"]["properties"]) == {"readings", "fingerprints"}
    ok = post["responses"]["200"]["content"]["application/json"]["schema"]
    assert ok == {"$ref": "#/components/schemas/LocateResponse"}


def test_ivf_service_matches_the_ivf_library() -> None:
    app = create_app(RM, k=3, index="ivf", ivf_clusters=4, ivf_probes=2)
    q = [{"ap1": -50.0, "ap2": -70.0}, {"ap5": -60, "ap7": -80.5}, {"ap3": -41.5}]
    expect = KnnLocator(RM, KnnConfig(k=3, index="ivf", ivf_clusters=4, ivf_probes=2)).locate(q)
    with start_background_server(app) as srv, httpx.Client(base_url=srv.url, timeout=10.0) as c:
        assert c.get("/v1/radio-map").json()["index"] == "ivf"
        r = c.post("/v1/locate", json={"fingerprints": [{"readings": s} for s in q]})
    assert r.status_code == 200
    got = np.array([[d["x"], d["y"]] for d in r.json()["positions"]])
    np.testing.assert_allclose(got, expect.xy, rtol=1e-12)


def test_sorensen_service_matches_the_sorensen_library() -> None:
    app = create_app(RM, k=3, metric="sorensen")
    q = [{"ap1": -50.0, "ap2": -70.0, "unknown": -40.0}, {"ap5": -60, "ap7": -80.5}, {"ap3": -41.5, "ap9": -90.0}]
    expect = KnnLocator(RM, KnnConfig(k=3, metric="sorensen")).locate(q)
    eq9 = KnnLocator(RM, KnnConfig(k=3, metric="eq9")).locate(q)
    assert not np.allclose(expect.xy, eq9.xy)  # the two metrics answer differently here
    with start_background_server(app) as srv, httpx.Client(base_url=srv.url, timeout=10.0) as c:
        assert c.get("/v1/radio-map").json()["metric"] == "sorensen"
        r = c.post("/v1/locate", json={"fingerprints": [{"readings": s} for s in q]})
    assert r.status_code == 200
    body = r.json()["positions"]
    np.testing.assert_allclose([[d["x"], d["y"]] for d in body], expect.xy, rtol=1e-12)
    assert [d["score"] for d in body] == pytest.approx(expect.score.tolist())
