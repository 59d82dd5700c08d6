#!/usr/bin/env python3
"""Single-query load on the HTTP service: 1, 8 and 32 concurrent keep-alive clients, this
checkout side by side with another one (e.g. the base commit), on one radio map.

Each variant is a real ``graphslam serve`` process on 127.0.0.1 (a free port) started from
its checkout. The load generator is a separate process (asyncio, raw HTTP/1.1 over
keep-alive connections, one request in flight per client: a closed loop, so the load is
bounded by the number of clients; each level is bounded by ``--requests`` and
``--seconds``). Queries are the map's own fingerprints, each with its RSS moved by a
seeded +-3 dB, one ``{"readings": ...}`` body per request. Variants alternate in ABBA order
over ``--rounds``; reported per variant and level: the median over rounds of throughput
(requests/s) and of p50 / p99 latency (client-measured round trip), the non-200 count, and
the load average around each block (the machine is shared: read the figures with it).

    python lab/service/bench_service_load.py --radio-map out/paper/radio_map.parquet --base /path/to/base-checkout \\
        [--rounds 3] [--clients 1,8,32] [--requests 3000] [--seconds 10] [--variant NAME=CHECKOUT:ARGS ...]

A variant is ``NAME=CHECKOUT`` or ``NAME=CHECKOUT:extra serve args`` (e.g.
``new-quiet=.:--log-level warning``); without ``--variant``: ``new`` (this checkout) and
``base`` (``--base``), both with their default serve options. ``--hide NAME=mod1,mod2``
makes those modules unimportable in that variant's server (e.g. the base commit did not
depend on ``httptools``/``uvloop``, which uvicorn uses whenever they are installed).
Prints one JSON line per variant and level, then a table (with the server's CPU time per
request, which the machine's other jobs change far less than latency).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import shlex
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from graphslam import GraphSlamError, free_port, http_exchange, query_bodies, wait_for_port
from graphslam import soak_loopback as LOOPBACK

REPO = Path(__file__).resolve().parents[2]


class Server:
    def __init__(self, name: str, checkout: Path, radio_map: Path, extra: list[str], log: Path,
                 hide: list[str]) -> None:
        self.name, self.port, self.log = name, free_port(), log
        path = [str(checkout)]
        if hide:  # modules that raise ImportError, found before the installed ones
            shadow = log.with_suffix(".hide")
            shadow.mkdir(exist_ok=True)
            for m in hide:
                (shadow / f"{m}.py").write_text(f"raise ImportError('{m} hidden by bench_service_load.py')\n")
            path.append(str(shadow))
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(path))
        cmd = [sys.executable, "-m", "graphslam", "serve", "--radio-map", str(radio_map), "--host", LOOPBACK,
               "--port", str(self.port), *extra]
        # cwd = the checkout: `python -m` puts the working folder first on sys.path
        # stderr to a file, not a pipe: a full pipe would block the server's access log
        with open(log, "wb") as err:
            self.proc = subprocess.Popen(cmd, cwd=checkout, env=env, stdout=subprocess.DEVNULL, stderr=err)
        try:
            wait_for_port(self.proc, self.port, 90.0)
        except GraphSlamError as e:
            raise RuntimeError(f"{name}: {e}: {log.read_text()[-2000:]}") from None

    def stop(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(15)
        except subprocess.TimeoutExpired:
            self.proc.kill()


# ---- the load generator (runs in its own process: --child) ----------------------------------


async def _client(port: int, reqs: list[bytes], first: int, n: int, deadline: float, lat: list[float],
                  status: dict[int, int]) -> None:
    reader, writer = await asyncio.open_connection(LOOPBACK, port)
    writer.get_extra_info("socket").setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    clock = time.perf_counter
    try:
        for i in range(n):
            if clock() > deadline:
                break
            t0 = clock()
            code, _ = await http_exchange((reader, writer), reqs[(first + i) % len(reqs)])
            lat.append(clock() - t0)
            status[code] = status.get(code, 0) + 1
    finally:
        writer.close()


async def _level(port: int, reqs: list[bytes], clients: int, total: int, seconds: float) -> dict:
    # warm-up: every connection's first request is not timed
    lat: list[float] = []
    status: dict[int, int] = {}
    await asyncio.gather(*(_client(port, reqs, c, 5, time.perf_counter() + 5, [], {}) for c in range(clients)))
    per_client = max(1, total // clients)
    t0 = time.perf_counter()
    await asyncio.gather(*(
        _client(port, reqs, c * per_client, per_client, t0 + seconds, lat, status) for c in range(clients)
    ))
    wall = time.perf_counter() - t0
    ms = np.array(lat) * 1e3
    return {"clients": clients, "requests": len(lat), "wall_s": round(wall, 3), "rps": round(len(lat) / wall, 1),
            "p50_ms": round(float(np.percentile(ms, 50)), 3), "p99_ms": round(float(np.percentile(ms, 99)), 3),
            "non_200": sum(v for k, v in status.items() if k != 200)}


def child(args: argparse.Namespace) -> None:
    bodies = Path(args.bodies).read_bytes().split(b"\n")
    reqs = [b"POST /v1/locate HTTP/1.1\r\nHost: bench\r\nContent-Type: application/json\r\n"
            b"Content-Length: %d\r\n\r\n%s" % (len(b), b) for b in bodies if b]
    out = [asyncio.run(_level(args.port, reqs, c, args.requests, args.seconds)) for c in args.clients]  # (one level)
    print(json.dumps(out))


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process and its (search worker) children still running."""
    import psutil

    p = psutil.Process(pid)
    total = sum(p.cpu_times()[:2])
    for c in p.children(recursive=True):
        try:
            total += sum(c.cpu_times()[:2])
        except psutil.NoSuchProcess:
            pass
    return total


def run_load(srv: "Server", bodies_file: Path, clients: int, requests: int, seconds: float) -> dict:
    cmd = [sys.executable, __file__, "--child", "--port", str(srv.port), "--bodies", str(bodies_file),
           "--clients", str(clients), "--requests", str(requests), "--seconds", str(seconds)]
    cpu0 = cpu_seconds(srv.proc.pid)
    row = json.loads(subprocess.run(cmd, capture_output=True, text=True, check=True).stdout)[0]
    # server CPU per request: what a request costs, far less sensitive to other jobs than its latency
    # (includes the warm-up requests, 5 per client)
    row["server_cpu_us_per_req"] = round((cpu_seconds(srv.proc.pid) - cpu0) / (row["requests"] + 5 * clients) * 1e6)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--radio-map", type=Path)
    ap.add_argument("--base", type=Path, help="checkout to compare with (variant 'base')")
    ap.add_argument("--variant", action="append", default=[], help="NAME=CHECKOUT[:serve args] (repeatable)")
    ap.add_argument("--hide", action="append", default=[], help="NAME=mod1,mod2: unimportable in that variant")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--clients", default="1,8,32")
    ap.add_argument("--requests", type=int, default=3000, help="requests per level, at most")
    ap.add_argument("--seconds", type=float, default=10.0, help="seconds per level, at most")
    ap.add_argument("--queries", type=int, default=500)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--port", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--bodies", help=argparse.SUPPRESS)
    a = ap.parse_args()
    a.clients = [int(c) for c in str(a.clients).split(",")]
    if a.radio_map is not None:
        a.radio_map = a.radio_map.resolve()  # the servers run in their checkouts
    if a.child:
        child(a)
        return
    variants: list[tuple[str, Path, list[str]]] = []
    for v in a.variant:
        name, _, rest = v.partition("=")
        checkout, _, extra = rest.partition(":")
        variants.append((name, Path(checkout).resolve(), shlex.split(extra)))
    if not variants:
        variants = [("new", REPO, [])] + ([("base", a.base.resolve(), [])] if a.base else [])
    hide = {n: m.split(",") for n, _, m in (h.partition("=") for h in a.hide)}
    results: dict[str, dict[int, list[dict]]] = {n: {c: [] for c in a.clients} for n, _, _ in variants}
    with tempfile.TemporaryDirectory(prefix="graphslam-load-") as tmp:
        bodies_file = Path(tmp) / "bodies.ndjson"
        bodies_file.write_bytes(b"\n".join(query_bodies(a.radio_map, a.queries, a.seed)))
        for r in range(a.rounds):
            order = variants if r % 2 == 0 else variants[::-1]  # ABBA: both see the same drift in load
            for name, checkout, extra in order:
                srv = Server(name, checkout, a.radio_map, extra, Path(tmp) / f"{name}.log", hide.get(name, []))
                try:
                    for c in a.clients:
                        load0 = os.getloadavg()[0]
                        row = run_load(srv, bodies_file, c, a.requests, a.seconds)
                        row.update(variant=name, round=r, load1_before=round(load0, 2),
                                   load1_after=round(os.getloadavg()[0], 2))
                        results[name][c].append(row)
                        print(json.dumps(row), flush=True)
                finally:
                    srv.stop()
    print(f"\nmedians over {a.rounds} rounds (radio map {a.radio_map}):")
    print(f"{'variant':<14} {'clients':>7} {'req/s':>8} {'p50 ms':>8} {'p99 ms':>8} {'cpu us/req':>10} "
          f"{'non-200':>8} {'load1':>11}")
    for name, _, _ in variants:
        for c in a.clients:
            rows = results[name][c]
            keys = ("rps", "p50_ms", "p99_ms", "server_cpu_us_per_req")
            med = {k: statistics.median(x[k] for x in rows) for k in keys}
            loads = [x["load1_before"] for x in rows]
            print(f"{name:<14} {c:>7} {med['rps']:>8.0f} {med['p50_ms']:>8.2f} {med['p99_ms']:>8.2f} "
                  f"{med['server_cpu_us_per_req']:>10.0f} {sum(x['non_200'] for x in rows):>8} "
                  f"{min(loads):>5.1f}-{max(loads):<5.1f}")


if __name__ == "__main__":
    main()
