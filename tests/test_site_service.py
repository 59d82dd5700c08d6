"""A building served whole (issue 41): ``serve`` of a folder of floor maps, against a REAL uvicorn
server on 127.0.0.1: the floor and the position in its frame, the unlocatable query, a floor's reload,
a bad site folder on the command line."""

from __future__ import annotations

import dataclasses
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

import httpx
import numpy as np
import pytest

from graphslam.app.tracking_bench import oracle_radio_map
from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.io.radiomap_io import read_radio_map, write_radio_map
from graphslam.service.server import served_app, start_background_server
from graphslam.sim import simulate

SHIFT = 1000.0  # floor B's frame: its map is moved by this in x (each survey has its own frame)


def _renamed(scans: list[dict[str, float]], prefix: str) -> list[dict[str, float]]:
    return [{prefix + b: v for b, v in s.items()} for s in scans]


def _floor(seed: int, prefix: str, dx: float, frame: str) -> tuple[RadioMap, list[dict[str, float]], np.ndarray]:
    """A floor's map (its walks but the last; BSSIDs renamed with ``prefix``) and the last walk's scans
    with their true positions (in the floor's frame)."""
    walks = [w for w in simulate("corridor", seed=seed, size=0.5).survey if len(w.landmarks) >= 2]
    train, test = oracle_radio_map(walks[:-1]), oracle_radio_map(walks[-1:])
    rm = RadioMap.from_scans(
        _renamed(_scans(train), prefix), train.xy + [dx, 0.0], session_ids=train.session_ids, t_ns=train.t_ns, frame=frame,
    )
    return rm, _renamed(_scans(test), prefix), test.xy + [dx, 0.0]


def _scans(rm: RadioMap) -> list[dict[str, float]]:
    v = rm.fingerprints.values
    out = []
    for i in range(len(rm)):
        lo, hi = v.indptr[i], v.indptr[i + 1]
        out.append({rm.bssids[j]: float(x + rm.missing_dbm) for j, x in zip(v.indices[lo:hi], v.data[lo:hi])})
    return out


@pytest.fixture(scope="module")
def floors() -> dict[str, tuple[RadioMap, list[dict[str, float]], np.ndarray]]:
    return {"floor_0": _floor(0, "a-", 0.0, "site-a"), "floor_1": _floor(1, "b-", SHIFT, "site-b")}


def _site(root: Path, floors: dict) -> Path:
    for name, (rm, _, _) in floors.items():
        (root / name).mkdir(parents=True)
        write_radio_map(rm, root / name / "radio_map.parquet")
    (root / ".floor_0.stage-x").mkdir()  # a survey's stage: not a floor
    write_radio_map(floors["floor_0"][0], root / ".floor_0.stage-x" / "radio_map.parquet")
    (root / "summary.json").write_text("[]")
    return root


def test_each_floors_queries_are_answered_with_that_floor_in_its_frame(tmp_path: Path, floors: dict) -> None:
    site = _site(tmp_path / "site", floors)
    app = served_app(site, None, search_processes=0)
    with start_background_server(app) as srv, httpx.Client(base_url=srv.url, timeout=30.0) as c:
        info = c.get("/v1/radio-map").json()
        assert info["site"] == "site"
        assert [f["name"] for f in info["floors"]] == ["floor_0", "floor_1"]
        assert [f["n_fingerprints"] for f in info["floors"]] == [len(floors[n][0]) for n in ("floor_0", "floor_1")]
        assert [f["frame"] for f in info["floors"]] == ["site-a", "site-b"]
        for name, (_, queries, truth) in floors.items():
            r = c.post("/v1/locate", json={"fingerprints": [{"readings": q} for q in queries]})
            assert r.status_code == 200, r.text
            got = r.json()
            assert got["site"] == "site" and len(got["positions"]) == len(queries)
            ps = got["positions"]
            assert {p["floor"] for p in ps} == {name}
            assert {p["frame"] for p in ps} == {floors[name][0].frame}
            xy = np.array([[p["x"], p["y"]] for p in ps])
            assert np.median(np.linalg.norm(xy - truth, axis=1)) < 5.0  # in the floor's own frame
            other = "floor_1" if name == "floor_0" else "floor_0"
            assert all(p["floor_scores"][other] is None and 0 <= p["floor_scores"][name] <= 1 for p in ps)
            assert all(p["sigma_m"] is None or p["sigma_m"] > 0 for p in ps)
            one = c.post("/v1/locate", json={"readings": queries[0]}).json()["positions"]
            assert len(one) == 1 and one[0]["floor"] == name
        # a fingerprint both floors hear: the better match answers, both scores given
        mixed = {**floors["floor_0"][1][3], **dict(list(floors["floor_1"][1][3].items())[:1])}
        p = c.post("/v1/locate", json={"readings": mixed}).json()["positions"][0]
        assert p["floor"] == "floor_0" and p["floor_scores"]["floor_0"] < p["floor_scores"]["floor_1"]
        # no floor knows the access points: as a single map answers, null and its reason in a batch
        # (the other fingerprint answered), a 404 notFound alone
        r = c.post("/v1/locate", json={"fingerprints": [{"readings": floors["floor_0"][1][0]},
                                                        {"readings": {"zz:zz": -60.0}}]})
        assert r.status_code == 200, r.text
        ok, bad = r.json()["positions"]
        assert ok["floor"] == "floor_0" and ok["x"] is not None and "error" not in ok
        assert bad["x"] is None and bad["floor"] is None and bad["frame"] is None
        assert bad["error"] == {"reason": "notFound", "status": "no_known_ap",
                                "message": "none of its access points is in any floor's radio map"}
        assert bad["floor_scores"] == {"floor_0": None, "floor_1": None}
        r = c.post("/v1/locate", json={"readings": {"zz:zz": -60.0}})
        assert r.status_code == 404 and r.json()["reason"] == "notFound" and "any floor" in r.json()["detail"]
        r = c.post("/v1/locate", content=b"{", headers={"content-type": "application/json"})
        assert r.status_code == 422 and "malformed JSON" in r.json()["detail"]


def test_a_floor_replaced_on_disk_is_reloaded_alone(tmp_path: Path, floors: dict) -> None:
    site = _site(tmp_path / "site", floors)
    app = served_app(site, 0.05, search_processes=0)
    rm1, queries, _ = floors["floor_1"]
    moved = dataclasses.replace(rm1, xy=rm1.xy + [SHIFT, 0.0])
    with start_background_server(app) as srv, httpx.Client(base_url=srv.url, timeout=30.0) as c:
        x0 = c.post("/v1/locate", json={"readings": queries[0]}).json()["positions"][0]["x"]
        new = site / "floor_1" / "radio_map.parquet.new"
        write_radio_map(moved, new)
        os.replace(new, site / "floor_1" / "radio_map.parquet")
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            gens = {f["name"]: f["generation"] for f in c.get("/v1/radio-map").json()["floors"]}
            if gens["floor_1"] == 1:
                break
            time.sleep(0.05)
        assert gens == {"floor_0": 0, "floor_1": 1}
        x1 = c.post("/v1/locate", json={"readings": queries[0]}).json()["positions"][0]["x"]
        assert x1 == pytest.approx(x0 + SHIFT)
        # a broken file is refused: the floor keeps its map, the other floor is untouched
        (site / "floor_1" / "radio_map.parquet").write_bytes(b"not parquet")
        time.sleep(1.0)
        assert c.post("/v1/locate", json={"readings": queries[0]}).json()["positions"][0]["x"] == pytest.approx(x1)
    assert read_radio_map(site / "floor_0" / "radio_map.parquet").frame == "site-a"


@pytest.mark.parametrize("case", ["empty", "unreadable"])
def test_a_bad_site_folder_is_one_line_and_exit_2(tmp_path: Path, floors: dict, case: str) -> None:
    site = tmp_path / "site"
    site.mkdir()
    if case == "unreadable":
        _site(tmp_path / "ok", floors)
        site = tmp_path / "ok"
        (site / "floor_1" / "radio_map.parquet").write_bytes(b"not parquet")
    p = subprocess.run([sys.executable, "-m", "graphslam", "serve", "--radio-map", str(site), "--port", "0",
                        "--log-level", "warning"],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 2, p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), p.stderr
    want = site / "floor_1" / "radio_map.parquet" if case == "unreadable" else site
    assert str(want) in lines[0]


def test_the_site_keeps_the_service_options(tmp_path: Path, floors: dict) -> None:
    site = _site(tmp_path / "site", floors)
    app = served_app(site, None, search_processes=0, token="s3cret", max_batch=2)
    with start_background_server(app) as srv, httpx.Client(base_url=srv.url, timeout=30.0) as c:
        q = {"readings": floors["floor_0"][1][0]}
        assert c.post("/v1/locate", json=q).status_code == 401
        assert c.get("/v1/radio-map").status_code == 401
        auth = {"authorization": "Bearer s3cret"}
        assert c.post("/v1/locate", json=q, headers=auth).json()["positions"][0]["floor"] == "floor_0"
        assert c.post("/v1/locate", json={"fingerprints": [q] * 3}, headers=auth).status_code == 413
        assert c.get("/healthz").status_code == 200
        schema = c.get("/openapi.json").json()
        body = schema["paths"]["/v1/locate"]["post"]["requestBody"]["content"]["application/json"]["schema"]
        assert body == {"$ref": "#/components/schemas/LocateRequest"} and "LocateRequest" in schema["components"]["schemas"]
        assert "SiteLocateResponse" in schema["components"]["schemas"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_serve_of_a_site_reloads_every_floor_on_sighup(tmp_path: Path, floors: dict) -> None:
    site = _site(tmp_path / "site", floors)
    port = _free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "graphslam", "serve", "--radio-map", str(site), "--port", str(port)],
        stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True,
    )
    url = f"http://127.0.0.1:{port}"
    rm1, queries, _ = floors["floor_1"]

    def x() -> float:
        return httpx.post(url + "/v1/locate", json={"readings": queries[0]}, timeout=10).json()["positions"][0]["x"]

    def wait_for(cond: Callable[[], bool], what: str) -> None:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            try:
                if cond():
                    return
            except httpx.HTTPError:
                pass
            time.sleep(0.05)
        raise AssertionError(what)

    try:
        wait_for(lambda: x() < 2 * SHIFT, "server did not start")
        new = site / "floor_1" / "radio_map.parquet.new"
        write_radio_map(dataclasses.replace(rm1, xy=rm1.xy + [SHIFT, 0.0]), new)
        os.replace(new, site / "floor_1" / "radio_map.parquet")
        proc.send_signal(signal.SIGHUP)
        wait_for(lambda: x() >= 2 * SHIFT, "SIGHUP did not swap in floor_1's new map")
        gens = {f["name"]: f["generation"] for f in httpx.get(url + "/v1/radio-map", timeout=10).json()["floors"]}
        assert gens["floor_1"] == 1 and proc.poll() is None
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=30)
    assert f"radio map {site / 'floor_1' / 'radio_map.parquet'} reloaded (generation 1" in err
    assert "Traceback" not in err


def test_a_floor_that_knows_one_weak_access_point_of_the_query_does_not_answer(tmp_path: Path, floors: dict) -> None:
    """Scores over all the query's access points: a floor whose fingerprints hear only one weak AP of
    the query would win on its own Sørensen score (that AP alone matches perfectly)."""
    rm0, queries, _ = floors["floor_0"]
    q = dict(queries[3])
    weak = min(q, key=q.get)
    leak = RadioMap.from_scans([{weak: q[weak]}] * 4, np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]),
                               session_ids=np.array(["x", "x", "y", "y"]), t_ns=np.arange(4), frame="leak")
    site = _site(tmp_path / "site", {"floor_0": floors["floor_0"], "leak": (leak, [], np.zeros((0, 2)))})
    from graphslam.core.radiomap.knn import KnnConfig, KnnLocator

    own = [KnnLocator(m, KnnConfig()).locate([q]).score[0] for m in (rm0, leak)]
    assert own[1] < own[0]  # on their own scores the leak floor would answer
    app = served_app(site, None, search_processes=0)
    with start_background_server(app) as srv, httpx.Client(base_url=srv.url, timeout=30.0) as c:
        p = c.post("/v1/locate", json={"readings": q}).json()["positions"][0]
    assert p["floor"] == "floor_0" and p["floor_scores"]["leak"] > p["floor_scores"]["floor_0"]
    assert p["floor_scores"]["floor_0"] == pytest.approx(own[0])  # a floor that knows every AP: unchanged


def test_linked_floor_folders_are_served_each_real_folder_once(tmp_path: Path, floors: dict) -> None:
    """A site whose floors are symbolic links (to survey-batch's outputs elsewhere) is served; a link back
    up the tree or a survey's hidden stage is not a floor."""
    from graphslam.service.site import find_floor_maps

    store = _site(tmp_path / "outputs", floors)
    site = tmp_path / "site"
    site.mkdir()
    for name in floors:
        (site / name).symlink_to(store / name, target_is_directory=True)
    (store / "floor_1" / "up").symlink_to(site, target_is_directory=True)  # a loop
    found = find_floor_maps(site)
    assert list(found) == ["floor_0", "floor_1"] and found["floor_1"] == site / "floor_1" / "radio_map.parquet"
