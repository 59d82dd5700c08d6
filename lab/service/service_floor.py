#!/usr/bin/env python3
"""What bounds the service's single-query throughput on this machine: the same load (8 keep-alive
clients, ``bench_service_load.py``'s generator, on the same cores) against three servers, layer by
layer:

- ``raw``: uvicorn (uvloop + httptools, as ``graphslam serve`` runs) with a bare ASGI app that reads
  the body and returns a constant answer: the HTTP stack and the load generator alone;
- ``raw+locate``: the same bare app answering each body with ``KnnLocator.locate`` on the map
  (orjson in and out, no FastAPI, no validation): the stack plus the search;
- ``serve``: ``graphslam serve`` itself.

Rounds alternate the three; medians of requests/s, p99 and the server's CPU per request.

    python lab/service/service_floor.py --radio-map out/paper/radio_map.parquet [--rounds 3] [--clients 8]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from graphslam import free_port, query_bodies, wait_for_port
from graphslam import soak_loopback as LOOPBACK

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]

APP = r'''
import os
import orjson

LOCATOR = None
if os.environ.get("FLOOR_MAP"):
    from graphslam import KnnLocator, read_radio_map
    LOCATOR = KnnLocator(read_radio_map(os.environ["FLOOR_MAP"]))

CONSTANT = orjson.dumps({"positions": [{"x": 0.0, "y": 0.0}]})
HEADERS = [(b"content-type", b"application/json")]


async def app(scope, receive, send):
    if scope["type"] != "http":
        return
    body, more = b"", True
    while more:
        msg = await receive()
        body += msg.get("body", b"")
        more = msg.get("more_body", False)
    if LOCATOR is None:
        out = CONSTANT
    else:
        res = LOCATOR.locate([orjson.loads(body)["readings"]])
        out = orjson.dumps({"positions": [{"x": float(res.xy[0, 0]), "y": float(res.xy[0, 1])}]})
    await send({"type": "http.response.start", "status": 200, "headers": HEADERS + [(b"content-length", str(len(out)).encode())]})
    await send({"type": "http.response.body", "body": out})
'''


def _cpu(pid: int) -> float:
    import psutil

    p = psutil.Process(pid)
    return sum(p.cpu_times()[:2]) + sum(sum(c.cpu_times()[:2]) for c in p.children(recursive=True))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--radio-map", type=Path, required=True)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--clients", type=int, default=8)
    ap.add_argument("--requests", type=int, default=6000)
    ap.add_argument("--seconds", type=float, default=8.0)
    a = ap.parse_args()
    radio_map = a.radio_map.resolve()
    rows: dict[str, list[dict]] = {"raw": [], "raw+locate": [], "serve": []}
    with tempfile.TemporaryDirectory(prefix="graphslam-floor-") as tmp:
        (Path(tmp) / "floorapp.py").write_text(APP)
        bodies = Path(tmp) / "bodies.ndjson"
        bodies.write_bytes(b"\n".join(query_bodies(radio_map, 500, 0)))
        for r in range(a.rounds):
            order = list(rows) if r % 2 == 0 else list(rows)[::-1]
            for name in order:
                port = free_port()
                env = {**os.environ, "RERUN": "off"}
                if name == "serve":
                    cmd = [sys.executable, "-m", "graphslam", "serve", "--radio-map", str(radio_map), "--host", LOOPBACK,
                           "--port", str(port), "--log-level", "warning"]
                    cwd = REPO
                else:
                    if name == "raw+locate":
                        env["FLOOR_MAP"] = str(radio_map)
                    cmd = [sys.executable, "-m", "uvicorn", "floorapp:app", "--host", LOOPBACK, "--port", str(port),
                           "--log-level", "warning", "--no-access-log"]
                    cwd = Path(tmp)
                with open(Path(tmp) / f"{name}.log", "wb") as err:
                    proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.DEVNULL, stderr=err)
                try:
                    wait_for_port(proc, port, 90.0)
                    cpu0 = _cpu(proc.pid)
                    out = subprocess.run([sys.executable, str(HERE / "bench_service_load.py"), "--child", "--port", str(port),
                                          "--bodies", str(bodies), "--clients", str(a.clients), "--requests",
                                          str(a.requests), "--seconds", str(a.seconds)],
                                         capture_output=True, text=True, check=True).stdout
                    row = json.loads(out)[0]
                    row["server_cpu_us_per_req"] = round((_cpu(proc.pid) - cpu0) / (row["requests"] + 5 * a.clients) * 1e6)
                    row.update(variant=name, round=r, load1=round(os.getloadavg()[0], 2))
                    rows[name].append(row)
                    print(json.dumps(row), flush=True)
                finally:
                    proc.terminate()
                    proc.wait(15)
    print(f"\nmedians over {a.rounds} rounds, {a.clients} clients:")
    print("| server | req/s | p99 ms | server CPU per request |\n|---|---|---|---|")
    for name, rs in rows.items():
        print(f"| {name} | {statistics.median(x['rps'] for x in rs):,.0f} | {statistics.median(x['p99_ms'] for x in rs):.1f} | "
              f"{statistics.median(x['server_cpu_us_per_req'] for x in rs):,.0f} µs |")


if __name__ == "__main__":
    main()
