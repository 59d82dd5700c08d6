#!/usr/bin/env python3
"""A/B benchmark of the HTTP service: a baseline copy of ``graphslam/service`` vs the installed one.

Why: on this 2-core machine wall-clock figures of ``bench_service.py`` swing by +-20%
between runs with other jobs. Here two servers run side by side on the same UJIIndoorLoc
radio map (as ``bench_service.py`` builds it): A with the service package in ``--baseline
DIR`` (a copy of an older ``graphslam/service/``, e.g. ``git archive REV graphslam/service |
tar -x -C /tmp/base`` -> ``/tmp/base/graphslam/service``), B with the installed one; both
with the installed core (map, index, search). The client alternates short blocks between
them (ABBA...), so both see the same load. Per block, one client:

- batch throughput (``--block`` requests of ``--batch`` fingerprints, after one untimed: steady
  state, as in ``bench_service.py``, not the first request after idle workers);
- CPU time per batch request of the server process and of its search workers (schedstat):
  what a request consumes, which other jobs change far less than its wall time;
- ``--single`` single-fingerprint latencies (pooled over blocks for p50 / p99).

Prints, per metric, the median and range over blocks for A and B, and the median and range
of the paired ratio B / A (a ratio < 1 = B cheaper or faster). ``--baseline current``
runs the installed service on both sides (an A/A run: the noise floor).

    python lab/service/bench_service_ab.py --baseline /tmp/base/graphslam/service [DATA_DIR] [--rounds 12]
        [--block 4] [--single 100] [--batch 1000] [--search-processes 2]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import psutil

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_service import DEFAULT_DATA, LOOPBACK, Client, batch_body, load_workload, wait_ready  # noqa: E402


def serve_from(args: argparse.Namespace) -> None:
    """Child mode: ``graphslam serve``, with the ``graphslam.service`` package loaded from
    ``--service-dir`` if given (before anything imports it)."""
    if args.service_dir:
        import graphslam

        init = Path(args.service_dir) / "__init__.py"
        spec = importlib.util.spec_from_file_location(
            "graphslam.service", init, submodule_search_locations=[str(Path(args.service_dir))]
        )
        assert spec is not None and spec.loader is not None
        mod = importlib.util.module_from_spec(spec)
        sys.modules["graphslam.service"] = mod  # its submodules now load from that directory
        graphslam.service = mod  # type: ignore[attr-defined]
        spec.loader.exec_module(mod)
    from graphslam import serve

    options = dict(host=LOOPBACK, port=args.port, k=args.k, max_batch=args.batch, search_processes=args.search_processes,
                   log_level="warning")
    try:  # a service that takes one config object (ServeConfig), or an older copy that takes keywords
        from graphslam import ServeConfig
    except (ImportError, AttributeError):
        serve(args.serve, **options)
    else:
        serve(args.serve, ServeConfig(**options))


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM, socket.IPPROTO_TCP) as s:
        s.bind((LOOPBACK, 0))
        return s.getsockname()[1]


def _task_cpu_s(pid: int) -> float:
    """CPU seconds of every thread of ``pid``: /proc/PID/task/*/schedstat counts nanoseconds (psutil's
    cpu_times count clock ticks, 10 ms: too coarse per request); psutil where there is no /proc."""
    total = 0
    try:
        tasks = list(Path(f"/proc/{pid}/task").iterdir())
    except OSError:
        return sum(psutil.Process(pid).cpu_times()[:2])
    for t in tasks:
        try:
            total += int((t / "schedstat").read_text().split()[0])
        except (OSError, ValueError, IndexError):
            pass  # a thread that ended meanwhile
    return total / 1e9


def cpu_s(proc: psutil.Process) -> tuple[float, float]:
    """CPU seconds of the server process and of its children (the search workers)."""
    kids = 0.0
    for c in proc.children():
        try:
            kids += _task_cpu_s(c.pid)
        except psutil.NoSuchProcess:
            pass
    return _task_cpu_s(proc.pid), kids


def summary(values: list[float]) -> str:
    a = np.asarray(values)
    return f"{np.median(a):8.2f} [{a.min():.2f}-{a.max():.2f}]"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data_dir", nargs="?", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--baseline", help="graphslam/service directory for server A, or 'current'")
    ap.add_argument("--rounds", type=int, default=12, help="blocks per server")
    ap.add_argument("--block", type=int, default=4, help="batch requests per block")
    ap.add_argument("--single", type=int, default=100, help="single-fingerprint requests per block")
    ap.add_argument("--batch", type=int, default=1000)
    ap.add_argument("--k", type=int, default=7)
    ap.add_argument("--search-processes", type=int, default=2)
    ap.add_argument("--serve", help=argparse.SUPPRESS)  # child mode: the radio map to serve
    ap.add_argument("--port", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--service-dir", default="", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.serve:
        serve_from(args)
        return 0
    if not args.baseline:
        ap.error("--baseline FILE (or 'current') is required")
    baseline = "" if args.baseline == "current" else str(Path(args.baseline).resolve())

    rm, queries = load_workload(args.data_dir, None, -95.0, -100.0)
    batches = [batch_body(queries, i * args.batch, args.batch) for i in range(4)]
    singles = [json.dumps({"readings": q}).encode() for q in queries]
    metrics: dict[str, dict[str, list[float]]] = {s: {"fps": [], "server_ms": [], "workers_ms": []} for s in "AB"}
    latency: dict[str, list[float]] = {"A": [], "B": []}
    procs: dict[str, subprocess.Popen] = {}
    with tempfile.TemporaryDirectory(prefix="graphslam-ab-") as tmp:
        from graphslam import write_radio_map

        map_path = write_radio_map(rm, Path(tmp) / "uji.parquet")
        urls = {}
        try:
            for side, module in (("A", baseline), ("B", "")):
                port = free_port()
                cmd = [sys.executable, __file__, "--serve", str(map_path), "--port", str(port), "--service-dir", module,
                       "--k", str(args.k), "--batch", str(args.batch), "--search-processes", str(args.search_processes)]
                procs[side] = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
                urls[side] = f"http://{LOOPBACK}:{port}"
            for side in "AB":
                wait_ready(urls[side], procs[side], timeout=120.0)
            ps = {side: psutil.Process(procs[side].pid) for side in "AB"}
            clients = {side: Client(urls[side], 120.0) for side in "AB"}
            for side in "AB":  # warm-up: every body once, a few singles
                for b in batches:
                    clients[side].post("/v1/locate", b)
                for b in singles[:20]:
                    clients[side].post("/v1/locate", b)
            n_single = 0
            for r in range(args.rounds):
                for side in ("AB" if r % 2 == 0 else "BA"):
                    c = clients[side]
                    c.post("/v1/locate", batches[r % len(batches)])  # untimed: the singles left the workers idle
                    own0, kids0 = cpu_s(ps[side])
                    t0 = time.perf_counter()
                    for i in range(args.block):
                        c.post("/v1/locate", batches[(r + i) % len(batches)])
                    wall = time.perf_counter() - t0
                    own1, kids1 = cpu_s(ps[side])
                    m = metrics[side]
                    m["fps"].append(args.block * args.batch / wall)
                    m["server_ms"].append((own1 - own0) * 1e3 / args.block)
                    m["workers_ms"].append((kids1 - kids0) * 1e3 / args.block)
                    for i in range(args.single):
                        t0 = time.perf_counter()
                        c.post("/v1/locate", singles[(n_single + i) % len(singles)])
                        latency[side].append((time.perf_counter() - t0) * 1e3)
                n_single += args.single
            for c in clients.values():
                c.conn.close()
        finally:
            for p in procs.values():
                p.terminate()
            for p in procs.values():
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()

    load = psutil.getloadavg()
    print(f"A: {baseline or 'installed service'}; B: installed service; {args.rounds} rounds x {args.block} "
          f"batches of {args.batch} + {args.single} singles; load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}")
    heads = ("A median [range]", "B median [range]", "B/A median [range]")
    print(f"{'metric (per batch request)':28s} " + " ".join(f"{h:>24s}" for h in heads))
    out: dict[str, object] = {"baseline": args.baseline, "rounds": args.rounds, "block": args.block, "load1": load[0]}
    labels = {"fps": "batch fingerprints/s", "server_ms": "server CPU ms", "workers_ms": "workers CPU ms"}
    for key, label in labels.items():
        a, b = metrics["A"][key], metrics["B"][key]
        ratio = list(np.asarray(b) / np.asarray(a))
        print(f"{label:28s} {summary(a):>24s} {summary(b):>24s} {summary(ratio):>24s}")
        out[key] = {"A": float(np.median(a)), "B": float(np.median(b)), "ratio": float(np.median(ratio))}
    for side in "AB":
        lat = np.asarray(latency[side])
        per_round = [np.percentile(lat[i : i + args.single], 99) for i in range(0, len(lat), args.single)]
        print(f"single, {side}: p50 {np.percentile(lat, 50):.2f} ms, p99 {np.percentile(lat, 99):.2f} ms "
              f"(per-block p99 median {np.median(per_round):.2f}, range {min(per_round):.2f}-{max(per_round):.2f})")
        out[f"single_p99_{side}"] = float(np.percentile(lat, 99))
    print(json.dumps({k: (round(v, 3) if isinstance(v, float) else v) for k, v in out.items()}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
