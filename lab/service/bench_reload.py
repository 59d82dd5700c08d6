"""Loopback load test of `graphslam serve --watch` across radio map swaps.

A real server (uvicorn, 127.0.0.1, free port) serves map A; client threads post single
fingerprints and batches without pause while the map file is replaced (write + rename, as a
survey run does) SWAPS times, alternating A and B = A moved by 1,000 m in x, so every answer
says which map gave it. Bounded: stops after the swaps (or MAX_SECONDS). Prints one JSON line:
requests, failed requests, answers mixing two maps, per-swap latency from rename to the first
answer from the new map, request latency percentiles.

    python lab/service/bench_reload.py RADIO_MAP.parquet [--swaps 10] [--clients 4] [--search-processes 1]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np

from graphslam import RadioMap, read_radio_map, reloading_app, start_background_server, write_radio_map

SHIFT = 1000.0
MAX_SECONDS = 600.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("radio_map", type=Path)
    ap.add_argument("--swaps", type=int, default=10)
    ap.add_argument("--clients", type=int, default=4)
    ap.add_argument("--batch", type=int, default=100, help="every 4th request is a batch of this many")
    ap.add_argument("--search-processes", type=int, default=1)
    ap.add_argument("--dwell", type=float, default=1.0, help="seconds of load between swaps")
    args = ap.parse_args()
    rm = read_radio_map(args.radio_map)
    fm = rm.fingerprints
    queries = [
        {fm.bssids[j]: float(v + fm.missing_dbm) for j, v in zip(fm.values[i].indices, fm.values[i].data)}
        for i in range(0, len(rm), max(1, len(rm) // 500))
    ]
    with tempfile.TemporaryDirectory(prefix="graphslam-reload-") as tmp:
        a = Path(tmp) / "a.parquet"
        b = Path(tmp) / "b.parquet"
        write_radio_map(rm, a)
        write_radio_map(RadioMap(rm.fingerprints, rm.xy + [SHIFT, 0.0], rm.session_ids, rm.t_ns, rm.frame,
                                 rm.floors, rm.buildings, rm.metadata, rm.min_rssi_dbm), b)
        live = Path(tmp) / "radio_map.parquet"

        def install(src: Path) -> None:
            new = live.with_name("new.parquet")
            new.write_bytes(src.read_bytes())
            os.replace(new, live)

        install(a)
        app = reloading_app(live, 0.2, k=3, search_processes=args.search_processes)
        stop = threading.Event()
        lock = threading.Lock()
        lat: list[tuple[float, float]] = []  # (start time, seconds)
        failures: list[str] = []
        mixed = 0
        last_b: list[tuple[float, bool]] = []  # (request start, answer from map B)

        def client(k: int) -> None:
            nonlocal mixed
            rng = np.random.default_rng(k)
            with httpx.Client(base_url=srv.url, timeout=60.0) as c:
                n = 0
                while not stop.is_set():
                    if n % 4 == 3:
                        pick = rng.integers(0, len(queries), args.batch)
                        body = {"fingerprints": [{"readings": queries[i]} for i in pick]}
                    else:
                        body = {"readings": queries[int(rng.integers(0, len(queries)))]}
                    n += 1
                    t = time.perf_counter()
                    try:
                        r = c.post("/v1/locate", json=body)
                    except httpx.HTTPError as e:
                        with lock:
                            failures.append(f"{type(e).__name__}: {e}")
                        continue
                    dt = time.perf_counter() - t
                    with lock:
                        lat.append((t, dt))
                        if r.status_code != 200:
                            failures.append(f"{r.status_code}: {r.text[:200]}")
                            continue
                        flags = {p["x"] >= SHIFT / 2 for p in r.json()["positions"]}
                        mixed += len(flags) > 1
                        last_b.append((t, flags.pop()))

        t_start = time.perf_counter()
        switch_s = []
        with start_background_server(app) as srv:
            threads = [threading.Thread(target=client, args=(k,), daemon=True) for k in range(args.clients)]
            for th in threads:
                th.start()
            time.sleep(args.dwell)
            for swap in range(args.swaps):
                want_b = swap % 2 == 0
                t_swap = time.perf_counter()
                install(b if want_b else a)
                while time.perf_counter() - t_start < MAX_SECONDS:
                    with lock:  # a request that started after the rename got the new map
                        done = any(t0 > t_swap and is_b == want_b for t0, is_b in last_b[-50:])
                    if done:
                        break
                    time.sleep(0.005)
                switch_s.append(time.perf_counter() - t_swap)
                time.sleep(args.dwell)
            stop.set()
            for th in threads:
                th.join()
        d = np.array([x for _, x in lat]) * 1000
        print(json.dumps({
            "radio_map": str(args.radio_map), "fingerprints": len(rm), "index": app.state.locator.index_kind,
            "clients": args.clients, "search_processes": args.search_processes, "swaps": args.swaps,
            "swaps_done": app.generation, "requests": len(lat) + len(failures), "failed_requests": len(failures),
            "answers_mixing_maps": mixed, "failures": failures[:5],
            "rename_to_new_answers_s": {"median": round(float(np.median(switch_s)), 3), "max": round(max(switch_s), 3)},
            "latency_ms": {"p50": round(float(np.percentile(d, 50)), 2), "p99": round(float(np.percentile(d, 99)), 2),
                           "max": round(float(d.max()), 2)},
            "seconds": round(time.perf_counter() - t_start, 1), "load_average": [round(v, 2) for v in os.getloadavg()],
        }))


if __name__ == "__main__":
    main()
