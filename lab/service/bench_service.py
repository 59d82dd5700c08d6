#!/usr/bin/env python3
"""Latency and throughput of the HTTP service against a real local server (loopback only).

Writes a UJIIndoorLoc-sized radio map (the 19,937 trainingData fingerprints) to a
temporary Parquet file (or takes --radio-map FILE), starts ``graphslam serve`` on it in
a separate process on 127.0.0.1 (a free port), waits for /healthz, then:

1. single-fingerprint requests, one at a time over a keep-alive connection, replaying
   validationData fingerprints: p50 / p99 / max latency (client-measured, full HTTP
   round trip);
2. batch requests of --batch fingerprints: fingerprints/s, with 1 and with 2
   concurrent clients.

Every loop is bounded in count (--single-requests, --batch-requests) and in time
(--time-budget seconds per phase); the server process (ours, by its pid) is stopped at
the end. Prints a summary and one JSON line.

The server's search is ``--index`` (default ``auto``: the IVF index on this map); it
runs ``--workers`` processes (default 1) and ``--search-processes`` search workers (default:
the server's, min(2, cores) with one server process; 0 = search in the server process).

    python lab/service/bench_service.py [DATA_DIR] [--k 7] [--batch 1000] [--index auto] [--workers 1]
                                    [--search-processes N]
"""

from __future__ import annotations

import argparse
import http.client
import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from graphslam import RadioMap

REPO = Path(__file__).resolve().parents[2]
DEFAULT_DATA = Path(os.environ.get("GRAPHSLAM_DATA", REPO.parent / "shared" / "data")) / "ujiindoorloc"
LOOPBACK = "127.0.0.1"
HEADERS = {"content-type": "application/json"}


class Client:
    """Minimal keep-alive HTTP/1.1 client (stdlib ``http.client``, TCP_NODELAY). Why not httpx:
    on this 2-core box httpx's own per-request cost (~1-6 ms under load) would dominate the
    latency being measured; http.client sends headers and a bytes body in one write."""

    def __init__(self, url: str, timeout: float) -> None:
        host, port = url.removeprefix("http://").split(":")
        self.conn = http.client.HTTPConnection(host, int(port), timeout=timeout)
        self.conn.connect()
        self.conn.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def request(self, method: str, path: str, body: bytes | None = None) -> tuple[int, bytes]:
        self.conn.request(method, path, body=body, headers=HEADERS if body is not None else {})
        r = self.conn.getresponse()
        data = r.read()
        if r.status != 200:
            raise RuntimeError(f"{method} {path}: HTTP {r.status}: {data[:300]!r}")
        return r.status, data

    def post(self, path: str, body: bytes) -> bytes:
        return self.request("POST", path, body)[1]

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc: object) -> None:
        self.conn.close()


def wait_ready(url: str, proc: subprocess.Popen, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            err = proc.stderr.read().decode() if proc.stderr else ""
            raise RuntimeError(f"server exited with {proc.returncode}: {err[-2000:]}")
        try:
            with Client(url, 2.0) as c:
                c.request("GET", "/healthz")
                return
        except OSError:
            time.sleep(0.2)
    raise RuntimeError("server did not become ready")


def single_latency(url: str, bodies: list[bytes], n: int, budget: float) -> dict[str, float]:
    with Client(url, 60.0) as c:
        for b in bodies[:20]:  # warm-up
            c.post("/v1/locate", b)
        lat = []
        deadline = time.monotonic() + budget
        for i in range(n):
            if time.monotonic() > deadline:
                break
            t0 = time.perf_counter()
            c.post("/v1/locate", bodies[i % len(bodies)])
            lat.append(time.perf_counter() - t0)
    ms = np.array(lat) * 1e3
    return {"single_requests": len(lat), "p50_ms": float(np.percentile(ms, 50)),
            "p99_ms": float(np.percentile(ms, 99)), "max_ms": float(ms.max())}


def batch_throughput(url: str, bodies: list[bytes], batch: int, clients: int, n: int, budget: float) -> float:
    done = [0] * clients
    per_client = max(1, n // clients)
    deadline = time.monotonic() + budget

    def worker(w: int) -> None:
        with Client(url, 120.0) as c:
            for i in range(per_client):
                if time.monotonic() > deadline:
                    break
                c.post("/v1/locate", bodies[(w + i) % len(bodies)])
                done[w] += batch

    with Client(url, 120.0) as c:  # warm-up
        c.post("/v1/locate", bodies[0])
    t0 = time.perf_counter()
    threads = [threading.Thread(target=worker, args=(w,)) for w in range(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return sum(done) / (time.perf_counter() - t0)


def load_workload(
    data_dir: Path, radio_map: Path | None, min_rssi: float, missing_dbm: float
) -> tuple["RadioMap", list[dict[str, float]]]:
    """The radio map (``radio_map``, or UJIIndoorLoc trainingData) and the validationData
    fingerprints that hear at least one AP above the map's RSS floor, as scans."""
    from lab.bench.uji import TEST_FILE, TRAIN_FILE, find_uji_file
    from graphslam import read_radio_map
    from lab.bench.ujiindoorloc import read_ujiindoorloc

    test = read_ujiindoorloc(find_uji_file(data_dir, TEST_FILE))
    if radio_map:
        rm = read_radio_map(radio_map)
    else:
        train = read_ujiindoorloc(find_uji_file(data_dir, TRAIN_FILE))
        rm = train.to_radio_map(missing_dbm=missing_dbm, min_rssi_dbm=min_rssi)
    heard = ~np.isnan(test.rssi)
    queries = [{test.bssids[j]: float(test.rssi[i, j]) for j in np.flatnonzero(heard[i])} for i in range(len(test))]
    return rm, [q for q in queries if any(r >= rm.min_rssi_dbm for r in q.values())]


def batch_body(queries: list[dict[str, float]], start: int, batch: int) -> bytes:
    """A ``{"fingerprints": [...]}`` body of ``batch`` queries from ``start`` (wrapping around)."""
    fps = [{"readings": queries[(start + i) % len(queries)]} for i in range(batch)]
    return json.dumps({"fingerprints": fps}).encode()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data_dir", nargs="?", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--radio-map", type=Path, help="serve this .parquet instead of trainingData")
    ap.add_argument("--k", type=int, default=7)
    ap.add_argument("--min-rssi", type=float, default=-95.0)
    ap.add_argument("--missing-dbm", type=float, default=-100.0)
    ap.add_argument("--single-requests", type=int, default=1000)
    ap.add_argument("--batch", type=int, default=1000)
    ap.add_argument("--batch-requests", type=int, default=12)
    ap.add_argument("--time-budget", type=float, default=60.0, help="seconds per phase, at most")
    ap.add_argument("--index", default="auto", help="kNN search of the server: exact, ivf or auto")
    ap.add_argument("--workers", type=int, default=1, help="server processes (graphslam serve --workers)")
    ap.add_argument("--search-processes", type=int, default=None,
                    help="search workers per server process (graphslam serve --search-processes; "
                    "default: the server's)")
    args = ap.parse_args()

    try:
        rm, queries = load_workload(args.data_dir, args.radio_map, args.min_rssi, args.missing_dbm)
    except Exception as e:  # noqa: BLE001 - a script: one line and exit
        print(f"error: {e}", file=sys.stderr)
        return 2
    single_bodies = [json.dumps({"readings": q}).encode() for q in queries]
    batch_bodies = [batch_body(queries, i * args.batch, args.batch) for i in range(4)]

    out: dict[str, object] = {"n_fingerprints_map": len(rm), "n_aps_map": rm.fingerprints.n_aps, "k": args.k,
                              "batch": args.batch, "index": args.index, "workers": args.workers,
                              "search_processes": args.search_processes}
    with tempfile.TemporaryDirectory(prefix="graphslam-bench-") as tmp:
        from graphslam import write_radio_map

        map_path = args.radio_map or write_radio_map(rm, Path(tmp) / "uji.parquet")
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM, socket.IPPROTO_TCP) as probe:
            probe.bind((LOOPBACK, 0))
            port = probe.getsockname()[1]
        cmd = [sys.executable, "-m", "graphslam.cli", "serve", "--radio-map", str(map_path), "--host", LOOPBACK,
               "--port", str(port), "--k", str(args.k), "--max-batch", str(max(args.batch, 1)),
               "--index", args.index, "--workers", str(args.workers)]
        if args.search_processes is not None:
            cmd += ["--search-processes", str(args.search_processes)]
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        url = f"http://{LOOPBACK}:{port}"
        try:
            wait_ready(url, proc)
            out.update(single_latency(url, single_bodies, args.single_requests, args.time_budget))
            for clients in (1, 2):
                out[f"batch_fps_{clients}_client"] = batch_throughput(
                    url, batch_bodies, args.batch, clients, args.batch_requests, args.time_budget
                )
        finally:
            proc.terminate()
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
    print(f"radio map: {len(rm)} fingerprints, {rm.fingerprints.n_aps} APs; k={args.k}; index={args.index}; "
          f"{args.workers} server process(es); search processes "
          f"{'default' if args.search_processes is None else args.search_processes}; server pid {proc.pid}")
    print(f"single fingerprint: p50 {out['p50_ms']:.2f} ms, p99 {out['p99_ms']:.2f} ms, "
          f"max {out['max_ms']:.2f} ms over {out['single_requests']} requests")
    for clients in (1, 2):
        print(f"batch of {args.batch}, {clients} client(s): {out[f'batch_fps_{clients}_client']:.0f} fingerprints/s")
    print(json.dumps({k: (round(v, 3) if isinstance(v, float) else v) for k, v in out.items()}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
