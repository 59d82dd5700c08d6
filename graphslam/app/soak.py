"""``graphslam bench soak``: a long loopback load on a real ``graphslam serve --watch``.

Does a service that runs for hours stay flat (latency, memory) under steady traffic
and a map reload every minute? The steps:

1. A copy of ``--radio-map`` (A) and the same map moved by ``SHIFT`` metres in x (B) are written
   to a temporary folder; ``graphslam serve --watch`` (a subprocess, 127.0.0.1, a free port,
   ``--log-level warning``) serves ``radio_map.parquet`` there, a copy of A.
2. Capacity: a closed-loop burst (``CAPACITY_CLIENTS`` keep-alive connections, one request in
   flight each, ``capacity_s`` seconds after a short warm-up) measures the requests per second
   the server answers with this client on this machine.
3. Open loop at ``load`` (0.8) of that capacity for ``minutes``: requests are sent on a fixed
   schedule whatever the answers do, each on an idle keep-alive connection (a new one when none
   is idle, at most ``MAX_CONNECTIONS``); a request's latency runs from its *scheduled* time,
   so a server that falls behind shows as latency, not as a slower client (no coordinated
   omission). Every ``batch_every``-th request is a batch of ``batch_size`` fingerprints (it goes
   to the search processes); the rest are single fingerprints, the map's own with +-3 dB.
4. Every minute, half-way through it, the map file is replaced (written beside, renamed onto:
   what ``graphslam survey`` does), alternately by B and A; ``--watch`` reloads it. Every answer
   says which map gave it (x beyond ``SHIFT / 2``), so the row counts answers from each.

One row per minute (``MinuteRow``): requests scheduled in that minute, errors (non-200,
connection errors, no answer within ``REQUEST_TIMEOUT_S``), p50/p99 latency (ms), the server's
RSS at the minute's end (the server process, and with its search processes), reloads done so
far (from the server's log), the load average. The server and the load generator share the
machine: read latency with the load average. Bounded: the run stops by itself after
``minutes`` (+ capacity and drain time); the server is stopped at the end.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import logging
import os
import re
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from graphslam.errors import GraphSlamError

log = logging.getLogger(__name__)

LOOPBACK = "127.0.0.1"
SHIFT = 1000.0  # map B = map A moved by this in x: every answer says which map gave it
CAPACITY_CLIENTS = 16
MAX_CONNECTIONS = 64
REQUEST_TIMEOUT_S = 10.0
MINUTE_S = 60.0
_RELOADED = re.compile(rb"reloaded \(generation (\d+)")
_REFUSED = re.compile(rb"refused \(")


@dataclass(frozen=True)
class MinuteRow:
    minute: int  # 1-based
    requests: int  # scheduled in this minute
    errors: int
    error_kinds: dict[str, int]  # "timeout", a status code, an exception's name -> count
    p50_ms: float | None
    p99_ms: float | None
    from_a: int  # answers from map A / from map B
    from_b: int
    rss_mb: float  # server process at the minute's end
    rss_total_mb: float  # with its search processes
    reloads: int  # map swaps done so far (the server's log)
    refused: int  # maps refused so far
    load1: float


@dataclass
class SoakResult:
    capacity_rps: float
    rate_rps: float
    rows: list[MinuteRow]

    @property
    def summary(self) -> dict:
        rows = self.rows
        p99 = [r.p99_ms for r in rows if r.p99_ms is not None]
        base = rows[min(4, len(rows) - 1)].rss_mb if rows else 0.0  # minute 5 (or the last, if fewer)
        return {
            "capacity_rps": round(self.capacity_rps, 1), "rate_rps": round(self.rate_rps, 1),
            "minutes": len(rows), "requests": sum(r.requests for r in rows), "errors": sum(r.errors for r in rows),
            "reloads": rows[-1].reloads if rows else 0, "refused": rows[-1].refused if rows else 0,
            "p99_first_ms": p99[0] if p99 else None, "p99_max_ms": max(p99) if p99 else None,
            "p99_max_over_first": round(max(p99) / p99[0], 2) if p99 and p99[0] else None,
            "rss_min5_mb": base, "rss_end_mb": rows[-1].rss_mb if rows else None,
            "rss_end_over_min5": round(rows[-1].rss_mb / base, 3) if rows and base else None,
            "load1_max": max((r.load1 for r in rows), default=None),
        }


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM, socket.IPPROTO_TCP) as s:
        s.bind((LOOPBACK, 0))
        return int(s.getsockname()[1])


def query_bodies(radio_map: Path, n: int, seed: int) -> list[bytes]:
    """``n`` request bodies ``{"readings": ...}``: the map's own fingerprints, each RSS moved by a
    seeded +-3 dB (capped at 0 dBm)."""
    from graphslam.io.radiomap_io import read_radio_map

    rm = read_radio_map(radio_map)
    rng = np.random.default_rng(seed)
    v = rm.fingerprints.values.tocsr()
    rows = [i for i in range(len(rm)) if v.indptr[i + 1] > v.indptr[i]]
    if not rows:
        raise GraphSlamError(f"{radio_map}: no fingerprint hears an access point")
    out = []
    for i in rng.choice(rows, size=min(n, len(rows)), replace=len(rows) < n):
        lo, hi = v.indptr[i], v.indptr[i + 1]
        rss = v.data[lo:hi] + rm.missing_dbm + rng.uniform(-3, 3, hi - lo)
        readings = {rm.bssids[j]: round(float(min(r, 0.0)), 1) for j, r in zip(v.indices[lo:hi], rss)}
        out.append(json.dumps({"readings": readings}).encode())
    return out


def wait_for_port(proc: subprocess.Popen, port: int, timeout: float) -> None:
    """Until ``proc`` (a server) accepts connections on the loopback ``port``; ``GraphSlamError``
    if it exits first or does not within ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise GraphSlamError(f"the server exited at start (code {proc.returncode})")
        try:
            with socket.create_connection((LOOPBACK, port), timeout=1):
                return
        except OSError:
            time.sleep(0.2)
    raise GraphSlamError(f"the server did not start within {timeout:.0f} s")


def _request(body: bytes) -> bytes:
    return (b"POST /v1/locate HTTP/1.1\r\nHost: soak\r\nContent-Type: application/json\r\n"
            b"Content-Length: %d\r\n\r\n%s" % (len(body), body))


# ---- the server ---------------------------------------------------------------------------------


class _Server:
    """``graphslam serve --watch`` on a free loopback port, its stderr in ``log``."""

    def __init__(self, radio_map: Path, log_path: Path, extra: list[str]) -> None:
        self.port, self.log_path = free_port(), log_path
        cmd = [sys.executable, "-m", "graphslam", "serve", "--radio-map", str(radio_map), "--host", LOOPBACK,
               "--port", str(self.port), "--watch", "--log-level", "warning", *extra]
        with open(log_path, "wb") as err:  # a file, not a pipe: a full pipe would block the server
            self.proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err, start_new_session=True)
        try:
            wait_for_port(self.proc, self.port, 120.0)
        except GraphSlamError as e:
            self.stop()
            raise GraphSlamError(f"soak: {e}: {self.tail()}") from None

    def tail(self) -> str:
        return self.log_path.read_bytes()[-1500:].decode(errors="replace")

    def reloads(self) -> tuple[int, int]:
        text = self.log_path.read_bytes()
        gens = [int(g) for g in _RELOADED.findall(text)]
        return (max(gens) if gens else 0), len(_REFUSED.findall(text))

    def rss_mb(self) -> tuple[float, float]:
        import psutil

        try:
            p = psutil.Process(self.proc.pid)
            own = p.memory_info().rss
            total = own
            for c in p.children(recursive=True):
                with contextlib.suppress(psutil.Error):
                    total += c.memory_info().rss
        except psutil.Error:
            return 0.0, 0.0
        return round(own / 2**20, 1), round(total / 2**20, 1)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


# ---- the load generator -------------------------------------------------------------------------


class _Connections:
    """Idle keep-alive connections to the server; a new one when none is idle (at most ``limit``).
    A connection idle for ``IDLE_S`` or more is closed instead of reused: the server closes its
    idle connections after 5 s (uvicorn's keep-alive timeout), and a request sent just as it does
    would fail for the client's sake, not the server's (a browser's or httpx's pool does the same)."""

    IDLE_S = 2.0

    def __init__(self, port: int, limit: int) -> None:
        self.port, self.limit, self.open = port, limit, 0
        self.idle: list[tuple[float, asyncio.StreamReader, asyncio.StreamWriter]] = []
        self.freed = asyncio.Condition()

    async def take(self) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
        async with self.freed:
            while not self.idle and self.open >= self.limit:
                await self.freed.wait()
            while self.idle:
                since, reader, writer = self.idle.pop()  # the most recently used first
                if time.perf_counter() - since < self.IDLE_S:
                    return reader, writer
                writer.close()
                self.open -= 1
            self.open += 1
        try:
            reader, writer = await asyncio.open_connection(LOOPBACK, self.port)
        except BaseException:
            await self.give(None)
            raise
        writer.get_extra_info("socket").setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return reader, writer

    async def give(self, conn: tuple[asyncio.StreamReader, asyncio.StreamWriter] | None) -> None:
        """Return ``conn`` as idle, or (None) give up its place (closed after an error)."""
        async with self.freed:
            if conn is None:
                self.open -= 1
            else:
                self.idle.append((time.perf_counter(), *conn))
            self.freed.notify()

    def close(self) -> None:
        for _, _, w in self.idle:
            w.close()


async def http_exchange(conn: tuple[asyncio.StreamReader, asyncio.StreamWriter], req: bytes) -> tuple[int, bytes]:
    """Send one raw HTTP/1.1 request on a keep-alive connection; (status, body) of its answer."""
    reader, writer = conn
    writer.write(req)
    head = await reader.readuntil(b"\r\n\r\n")
    code = int(head[9:12])
    length = 0
    for line in head.split(b"\r\n")[1:]:
        if line[:15].lower() == b"content-length:":
            length = int(line[15:])
    return code, await reader.readexactly(length)


@dataclass
class _Bucket:
    """What the requests scheduled in one minute got."""

    latency_s: list[float] = dataclasses.field(default_factory=list)
    sent: int = 0
    errors: int = 0
    kinds: dict[str, int] = dataclasses.field(default_factory=dict)  # error kind -> count
    from_a: int = 0
    from_b: int = 0
    pending: int = 0


async def _one(conns: _Connections, req: bytes, t_sched: float, bucket: _Bucket) -> None:
    bucket.pending += 1
    bucket.sent += 1
    conn = None
    try:
        conn = await asyncio.wait_for(conns.take(), REQUEST_TIMEOUT_S)
        code, body = await asyncio.wait_for(http_exchange(conn, req), REQUEST_TIMEOUT_S)
    except (OSError, asyncio.TimeoutError, asyncio.IncompleteReadError, asyncio.LimitOverrunError, ValueError) as e:
        bucket.errors += 1
        kind = "timeout" if isinstance(e, asyncio.TimeoutError) else type(e).__name__
        bucket.kinds[kind] = bucket.kinds.get(kind, 0) + 1
        if conn is not None:
            conn[1].close()
            await conns.give(None)
        bucket.pending -= 1
        return
    bucket.latency_s.append(time.perf_counter() - t_sched)
    await conns.give(conn)
    if code != 200:
        bucket.errors += 1
        bucket.kinds[str(code)] = bucket.kinds.get(str(code), 0) + 1
    else:
        # the first position's x says which map answered
        m = re.search(rb'"x":\s*(-?[0-9.eE+-]+)', body)
        if m is not None and float(m.group(1)) >= SHIFT / 2:
            bucket.from_b += 1
        else:
            bucket.from_a += 1
    bucket.pending -= 1


async def _closed_loop(port: int, reqs: list[bytes], clients: int, seconds: float) -> float:
    """Requests per second answered by ``clients`` connections, one request in flight each."""
    done = [0]

    async def client(c: int, deadline: float, count: bool) -> None:
        reader, writer = await asyncio.open_connection(LOOPBACK, port)
        writer.get_extra_info("socket").setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        i = c
        try:
            while time.perf_counter() < deadline:
                code, _ = await http_exchange((reader, writer), reqs[i % len(reqs)])
                if code != 200:
                    raise GraphSlamError(f"soak: the server answered {code} while measuring capacity")
                i += clients
                done[0] += count
        finally:
            writer.close()

    await asyncio.gather(*(client(c, time.perf_counter() + 2.0, False) for c in range(clients)))  # warm-up
    t0 = time.perf_counter()
    await asyncio.gather(*(client(c, t0 + seconds, True) for c in range(clients)))
    return done[0] / (time.perf_counter() - t0)


async def _open_loop(
    port: int, reqs: list[bytes], rate: float, minutes: int, on_minute_end: Callable[[int], None],
    report: Callable[[int, _Bucket], None],
) -> None:
    """``rate`` requests per second for ``minutes``; ``on_minute_end(m)`` as minute m (1-based)
    ends (RSS sampled there), ``report(m, bucket)`` once all of minute m's requests are answered
    or timed out; the map reload is driven from ``on_minute_end``'s half-minute twin below."""
    conns = _Connections(port, MAX_CONNECTIONS)
    buckets = [_Bucket() for _ in range(minutes)]
    tasks: set[asyncio.Task] = set()
    t0 = time.perf_counter()
    n_total = int(round(rate * MINUTE_S * minutes))
    minute_done = 0

    async def reporter(m: int) -> None:
        # every request of minute m was scheduled before its end: wait for the last ones
        deadline = time.perf_counter() + 2 * REQUEST_TIMEOUT_S + 5
        while buckets[m - 1].pending and time.perf_counter() < deadline:
            await asyncio.sleep(0.05)
        report(m, buckets[m - 1])
        buckets[m - 1].latency_s = []  # a long run keeps no more than a minute's latencies

    n = 0
    while n < n_total:
        now = time.perf_counter()
        due = min(n_total, int((now - t0) * rate) + 1)  # every request scheduled by now
        for n in range(n, due):
            t_sched = t0 + n / rate
            minute = min(int((t_sched - t0) // MINUTE_S), minutes - 1)
            while minute_done < minute:  # a minute boundary passed
                minute_done += 1
                on_minute_end(minute_done)
                tasks.add(asyncio.ensure_future(reporter(minute_done)))
            task = asyncio.ensure_future(_one(conns, reqs[n % len(reqs)], t_sched, buckets[minute]))
            tasks.add(task)
            task.add_done_callback(tasks.discard)
        n = due
        # until the next one is due (0: let the requests run when behind the schedule)
        await asyncio.sleep(max(0.0, t0 + n / rate - time.perf_counter()))
    end = t0 + MINUTE_S * minutes
    now = time.perf_counter()
    if end > now:
        await asyncio.sleep(end - now)
    while minute_done < minutes:
        minute_done += 1
        on_minute_end(minute_done)
        tasks.add(asyncio.ensure_future(reporter(minute_done)))
    await asyncio.gather(*list(tasks))
    conns.close()


def _percentile_ms(latency_s: list[float], q: float) -> float | None:
    return round(float(np.percentile(np.asarray(latency_s) * 1e3, q)), 3) if latency_s else None


@contextlib.contextmanager
def _maps(radio_map: Path) -> Iterator[tuple[Path, Path, Path]]:
    """(live file, A, B) in a temporary folder; live starts as a copy of A."""
    from graphslam.core.radiomap.radiomap import RadioMap
    from graphslam.io.radiomap_io import read_radio_map, write_radio_map

    rm = read_radio_map(radio_map)
    with tempfile.TemporaryDirectory(prefix="graphslam-soak-") as tmp:
        a, b, live = Path(tmp) / "a.parquet", Path(tmp) / "b.parquet", Path(tmp) / "radio_map.parquet"
        write_radio_map(rm, a)
        write_radio_map(RadioMap(rm.fingerprints, rm.xy + [SHIFT, 0.0], rm.session_ids, rm.t_ns, rm.frame,
                                 rm.floors, rm.buildings, rm.metadata, rm.min_rssi_dbm), b)
        _install(a, live)
        yield live, a, b


def _install(src: Path, dst: Path) -> None:
    """Replace ``dst`` by a copy of ``src`` as a survey does: written beside, renamed onto."""
    tmp = dst.with_name(f".{dst.name}.new")
    tmp.write_bytes(src.read_bytes())
    os.replace(tmp, dst)


def run_soak(
    radio_map: str | Path,
    *,
    minutes: int,
    load: float = 0.8,
    rate: float | None = None,
    capacity_s: float = 10.0,
    batch_every: int = 50,
    batch_size: int = 100,
    seed: int = 0,
    serve_args: list[str] | None = None,
    on_row: Callable[[dict], None] | None = None,
) -> SoakResult:
    """Run the soak (module docstring); ``on_row`` gets the capacity line, then each minute's row
    (as dicts) as they are known. ``rate``: requests per second instead of ``load`` x capacity."""
    if minutes < 1:
        raise GraphSlamError("soak: --minutes must be at least 1")
    if not 0 < load <= 1.5:
        raise GraphSlamError("soak: --load must be in (0, 1.5]")
    radio_map = Path(radio_map)
    if not radio_map.is_file():
        raise GraphSlamError(f"{radio_map}: radio map not found")
    emit = on_row or (lambda row: None)
    singles = query_bodies(radio_map, 500, seed)
    reqs = []
    for i, body in enumerate(singles):
        if batch_every and i % batch_every == batch_every - 1:
            k = [singles[(i + j) % len(singles)] for j in range(batch_size)]
            body = b'{"fingerprints": [' + b", ".join(k) + b"]}"
        reqs.append(_request(body))
    with _maps(radio_map) as (live, a, b), tempfile.TemporaryDirectory(prefix="graphslam-soak-log-") as logs:
        server = _Server(live, Path(logs) / "serve.log", serve_args or [])
        try:
            capacity = asyncio.run(_closed_loop(server.port, reqs, CAPACITY_CLIENTS, capacity_s))
            target = rate if rate is not None else load * capacity
            emit({"capacity_rps": round(capacity, 1), "rate_rps": round(target, 1), "load": load,
                  "clients": CAPACITY_CLIENTS, "capacity_s": capacity_s, "port": server.port})
            rows: list[MinuteRow] = []
            rss: dict[int, tuple[float, float]] = {}
            reloads: dict[int, tuple[int, int]] = {}

            def minute_end(m: int) -> None:
                rss[m] = server.rss_mb()
                reloads[m] = server.reloads()

            def report(m: int, bucket: _Bucket) -> None:
                row = MinuteRow(
                    m, bucket.sent, bucket.errors, dict(bucket.kinds), _percentile_ms(bucket.latency_s, 50), _percentile_ms(bucket.latency_s, 99),
                    bucket.from_a, bucket.from_b, rss[m][0], rss[m][1], reloads[m][0], reloads[m][1],
                    round(os.getloadavg()[0], 2),
                )
                rows.append(row)
                emit(dataclasses.asdict(row))

            async def main() -> None:
                async def reload_every_minute() -> None:
                    for m in range(minutes):
                        await asyncio.sleep(MINUTE_S / 2 if m == 0 else MINUTE_S)
                        await asyncio.to_thread(_install, b if m % 2 == 0 else a, live)

                reloader = asyncio.ensure_future(reload_every_minute())
                try:
                    await _open_loop(server.port, reqs, target, minutes, minute_end, report)
                finally:
                    reloader.cancel()
                    with contextlib.suppress(asyncio.CancelledError):
                        await reloader

            asyncio.run(main())
            if server.proc.poll() is not None:
                raise GraphSlamError(f"soak: the server died: {server.tail()}")
        finally:
            server.stop()
    return SoakResult(capacity, target, sorted(rows, key=lambda r: r.minute))

