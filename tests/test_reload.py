"""Hot reload of the served radio map (issue 18): real servers on 127.0.0.1, real files, real signals."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.io.radiomap_io import write_radio_map
from graphslam.service.server import reloading_app, start_background_server

SHIFT = 1000.0  # map B is map A moved by this in x: every answer says which map gave it


def _maps(tmp: Path) -> tuple[Path, Path]:
    rng = np.random.default_rng(3)
    scans = [{f"ap{j}": float(rng.integers(-95, -35)) for j in rng.choice(12, 5, replace=False)} for _ in range(120)]
    xy = rng.uniform(0, 30, (120, 2))
    paths = []
    for name, dx in (("a", 0.0), ("b", SHIFT)):
        rm = RadioMap.from_scans(scans, xy + [dx, 0.0], session_ids="s", t_ns=np.arange(120), frame="aligned")
        paths.append(write_radio_map(rm, tmp / f"{name}.parquet"))
    return paths[0], paths[1]


def _install(src: Path, dst: Path) -> None:
    """What a survey run does: write beside, rename onto (atomic)."""
    tmp = dst.with_name(dst.name + ".new")
    tmp.write_bytes(src.read_bytes())
    os.replace(tmp, dst)


def test_watch_swaps_ten_maps_under_load_without_a_failed_request(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    a, b = _maps(tmp_path)
    live = tmp_path / "radio_map.parquet"
    _install(a, live)
    app = reloading_app(live, 0.05, k=3, search_processes=1)  # one forked search process: big batches go there
    one = {"readings": {"ap1": -50.0, "ap2": -70.0, "ap3": -60.0}}
    batch = {"fingerprints": [one] * 80}
    stop = threading.Event()
    failures: list[str] = []
    seen: list[tuple[float, float]] = []  # (request start, x of the answer)
    counts = [0, 0]

    def client(k: int) -> None:
        with httpx.Client(base_url=srv.url, timeout=30.0) as c:
            deadline = time.monotonic() + 120  # bounded: stops by itself
            while not stop.is_set() and time.monotonic() < deadline and counts[k] < 20_000:
                body = batch if counts[k] % 5 == 4 else one
                t0 = time.monotonic()
                try:
                    r = c.post("/v1/locate", json=body)
                except httpx.HTTPError as e:
                    failures.append(f"{type(e).__name__}: {e}")
                    continue
                counts[k] += 1
                if r.status_code != 200:
                    failures.append(f"{r.status_code}: {r.text[:200]}")
                    continue
                xs = {p["x"] for p in r.json()["positions"]}
                if len({x >= SHIFT / 2 for x in xs}) != 1:
                    failures.append("one answer mixed two maps")
                seen.append((t0, next(iter(xs))))

    with start_background_server(app) as srv:
        threads = [threading.Thread(target=client, args=(k,)) for k in range(2)]
        for t in threads:
            t.start()
        try:
            def switched(since: float, want_b: bool) -> bool:
                # a request that started after the rename got the new map (requests already running
                # when a map is swapped out finish on it: their answers do not count)
                return any(t0 > since and (x >= SHIFT / 2) == want_b for t0, x in seen[-50:])

            for swap in range(10):
                want_b = swap % 2 == 0
                t_install = time.monotonic()
                _install(b if want_b else a, live)
                deadline = time.monotonic() + 30
                while time.monotonic() < deadline and not switched(t_install, want_b):
                    time.sleep(0.02)
                assert switched(t_install, want_b), f"answers did not switch at swap {swap}"
            # a broken map is refused and the old one kept
            refused_before = app.refused
            live.with_name("broken.new").write_bytes(b"PAR1 not a parquet file")
            os.replace(live.with_name("broken.new"), live)
            deadline = time.monotonic() + 30
            while app.refused == refused_before and time.monotonic() < deadline:
                time.sleep(0.02)
            n = len(seen)
            time.sleep(0.3)
        finally:
            stop.set()
            for t in threads:
                t.join()
    assert failures == []
    assert app.generation == 10 and app.refused == refused_before + 1
    assert all(x < SHIFT / 2 for _, x in seen[n:]), "answers after the refused map still come from the old one"
    assert sum(counts) > 100
    assert any("refused" in r.getMessage() and str(live) in r.getMessage() for r in caplog.records)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_serve_reloads_on_sighup_and_refuses_a_broken_map(tmp_path: Path) -> None:
    a, b = _maps(tmp_path)
    live = tmp_path / "radio_map.parquet"
    _install(a, live)
    port = _free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "graphslam", "serve", "--radio-map", str(live), "--port", str(port),
         "--search-processes", "0"],
        stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True,
    )
    url = f"http://127.0.0.1:{port}"
    one = {"readings": {"ap1": -50.0, "ap2": -70.0, "ap3": -60.0}}

    def x() -> float:
        return httpx.post(url + "/v1/locate", json=one, timeout=10).json()["positions"][0]["x"]

    def wait_for(cond: object, what: str) -> None:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            try:
                if cond():  # type: ignore[operator]
                    return
            except httpx.HTTPError:
                pass
            time.sleep(0.05)
        raise AssertionError(what)

    try:
        wait_for(lambda: x() < SHIFT / 2, "server did not start")
        _install(b, live)
        proc.send_signal(signal.SIGHUP)
        wait_for(lambda: x() >= SHIFT / 2, "SIGHUP did not swap in the new map")
        live.write_bytes(b"garbage")
        proc.send_signal(signal.SIGHUP)
        time.sleep(1.0)
        assert x() >= SHIFT / 2  # still the last good map
        assert proc.poll() is None  # and still serving
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=20)
    assert "refused" in err and str(live) in err
    # a reload is logged at INFO (not a warning), and a plain serve (--log-level info) shows it
    assert f"INFO graphslam.service.reload: radio map {live} reloaded (generation 1" in err
    assert "WARNING" not in err


def test_serve_on_a_port_in_use_is_one_line_and_exit_2(tmp_path: Path) -> None:
    a, _ = _maps(tmp_path)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        runs = [
            subprocess.run([sys.executable, "-m", "graphslam", "serve", "--radio-map", str(a), "--port", str(port), *extra],
                           capture_output=True, text=True, timeout=120)
            for extra in ([], ["--workers", "2"])
        ]
    for p in runs:
        assert p.returncode == 2, p.stderr
        assert p.stderr.splitlines() == [
            f"error: serve: cannot listen on 127.0.0.1:{port}: Address already in use (another server listens there: "
            "stop it or choose another --port)"
        ]


def test_a_retired_map_is_freed(tmp_path: Path) -> None:
    """Issue 42's soak: every reload kept the retired app (map, index, search pool) alive, ~3 MB
    each, through FastAPI's module-level caches of endpoint functions. After a few swaps the
    first app's locator must be garbage collected."""
    import gc
    import weakref

    a, b = _maps(tmp_path)
    live = tmp_path / "radio_map.parquet"
    _install(a, live)
    app = reloading_app(live, None, k=3, search_processes=0)
    first = weakref.ref(app.current.state.locator)
    with start_background_server(app) as srv, httpx.Client(base_url=srv.url, timeout=30.0) as c:
        assert c.post("/v1/locate", json={"readings": {"ap1": -50.0}}).status_code == 200
        for k in range(3):
            _install(b if k % 2 == 0 else a, live)
            app.reload_now()
            deadline = time.monotonic() + 60
            while app.generation < k + 1 and time.monotonic() < deadline:
                time.sleep(0.02)
            assert app.generation == k + 1
            assert c.post("/v1/locate", json={"readings": {"ap1": -50.0}}).status_code == 200
        deadline = time.monotonic() + 30  # the retired apps are closed on a thread of their own
        while first() is not None and time.monotonic() < deadline:
            time.sleep(0.05)
            gc.unfreeze()  # (the server froze the maps out of the collector)
            gc.collect()
            gc.freeze()
        assert first() is None, "the first map's locator is still referenced after 3 reloads"
