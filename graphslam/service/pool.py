"""Search process pool: large batches searched in forked worker processes.

Why: the IVF search loop holds the GIL, so one server process searches on about one
core. ``SearchPool`` forks N worker processes once the locator (radio map + index) is
built; they inherit it copy-on-write (fork start method: nothing is pickled or rebuilt).

- ``locate(scans)``: a batch of ``min_batch`` scans or more is split into contiguous
  chunks, each located in a worker with ``KnnLocator.locate``; the per-row result arrays
  are concatenated in order.
- ``locate_body(body)`` (the service's path for big bodies): every worker gets the raw
  JSON body, parses and validates it (``parsing.flat_scans``), takes its share of the rows,
  encodes them from the parsed arrays (``batching.ScanEncoder``, cheaper than
  ``RadioMap.encode``) and locates them. Why: in the server process, parsing, encoding or pickling the scans is GIL-bound work in series with everything else;
  in the workers it runs in parallel, and the server only does HTTP. With an IVF index the
  shares are places, not row ranges (``batching.PlaceSplit``): each worker then probes
  fewer clusters (~18% less search time on UJIIndoorLoc).

One batch alone in flight is split over every worker (one client gets all the cores);
concurrent batches take fewer shares each, down to one worker per batch (a search call
has a fixed cost, the IVF loop over clusters, paid once per share).

The workers also render the rows' JSON position objects (``render``): the server then
only splices them into the response (~1.5 ms per 1,000 off its serial path).

Transport: two pipes per worker, framed pickles (a request body goes raw, not copied into
a pickle), written and read by the request's own thread: no executor threads, queues or
per-request pickling of the body (the server's CPU per 1,000-fingerprint request went
from ~6 ms to ~3.7 ms with the changes above). A worker serves one request at a time; a
request claims free workers all at once (``_Crew``: no deadlock, no wait while a worker
is free). The server never blocks on a pipe without also watching the deadline and the
exit of every worker of the request (process sentinels).

Results: the same neighbours and labels as in-process search; the same floats where a
row's search is computed on its own (exact search on sparse maps); where BLAS GEMMs are
involved (IVF, dense maps) ~1 ulp apart, as in-process search already is when the same
query arrives in another batch (tested). Workers use one BLAS thread, as
``graphslam serve``'s server process does (the thread count changes GEMM rounding).
Smaller requests stay in the server process: a round trip costs more than their search.

Failures: if a worker dies (OOM killer, a signal) or does not answer within ``timeout``,
the request(s) in flight get ``SearchUnavailableError`` (the service answers 503) and the
pool is retired (its workers stopped: a late answer could not be matched to its request);
later requests are searched in the server process (slower, still correct). Where ``fork``
is unavailable the pool is never started and everything is searched in-process.
"""

from __future__ import annotations

import gc
import logging
import math
import multiprocessing as mp
import os
import pickle
import select
import signal
import struct
import threading
import time
import weakref
from multiprocessing.process import BaseProcess
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from graphslam.core.radiomap.knn import KnnLocator, KnnResult, strict_error
from graphslam.errors import GraphSlamError
from graphslam.service.batching import PLACE_MAX_CLUSTERS, PlaceSplit, ScanEncoder
from graphslam.service.parsing import flat_scans
from graphslam.service.render import position_rows

log = logging.getLogger(__name__)

# Batches from this size go to the pool: below it the IPC round trip outweighs the search
# saved (measured with the IVF index on UJIIndoorLoc).
SEARCH_POOL_MIN_BATCH = 64
# A worker silent this long (far beyond any chunk's search) is stuck.
SEARCH_TIMEOUT_S = 120.0
# Grace period for workers to exit at shutdown before they are killed.
SHUTDOWN_TIMEOUT_S = 5.0
# Pipe buffer asked for (Linux; best effort): a 1,000-fingerprint body (~300 KB) or a reply
# then goes in one write, without waking the reader once per 64 KB.
PIPE_BYTES = 1 << 20

# Per worker process, inherited from the server process (set by _worker_main).
_LOCATOR: KnnLocator | None = None
_ENCODER: ScanEncoder | None = None
_SPLIT: PlaceSplit | None = None

_Rows = tuple[NDArray, ...]
_FIELDS = ("xy", "score", "spread", "neighbours", "distances", "n_known_aps", "floor", "building", "rss_diff_db")
# A frame: the lengths of its two parts, a pickle ``(op, args)`` or ``(ok, result)``, then raw
# bytes (a request body: sent as is, not copied into a pickle). A 0-length pickle asks a worker to exit.
_HEADER = struct.Struct("!QQ")


class SearchUnavailableError(GraphSlamError):
    """The search worker processes cannot answer (one died, or they did not answer in time)."""


class BatchTooLargeError(GraphSlamError):
    """A request body holds more fingerprints than the service accepts."""

    def __init__(self, n: int, max_batch: int) -> None:
        self.n = n
        self.max_batch = max_batch
        super().__init__(f"batch of {n} fingerprints, at most {max_batch} per request")


class _WorkerDied(Exception):
    """Internal: a worker exited (or its pipe broke) during an exchange."""


class _WorkerTimeout(Exception):
    """Internal: a worker did not answer before the deadline."""


class _PoolClosed(Exception):
    """Internal: the pool was shut down while a request waited for a worker."""


def default_search_processes() -> int:
    """``min(2, cores)``: the machines this serves on have 2 cores; more processes than
    cores only add contention."""
    return min(2, os.cpu_count() or 1)


def fork_available() -> bool:
    return "fork" in mp.get_all_start_methods()


# --- worker process side -------------------------------------------------------------------


def _init_worker(parent_pid: int) -> None:
    # Ctrl-C reaches the whole process group: the server shuts the pool down itself, so a
    # worker must not die first (that would show as a crashed pool, with tracebacks).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    from graphslam.core.radiomap.ivf import limit_blas_threads

    limit_blas_threads(1)  # one search per process; BLAS threads only slow the IVF's small GEMMs
    # The inherited heap (map, index, every module) never becomes garbage: keep the collector
    # off it (full collections would walk it, and touching it un-shares copy-on-write pages).
    gc.freeze()
    # Pipes of pools created later in the server are inherited by their workers, so a worker
    # cannot count on EOF if the server is killed (SIGKILL): watch the parent, leave with it.
    threading.Thread(target=_exit_with_parent, args=(parent_pid,), daemon=True, name="parent-watch").start()


def _exit_with_parent(parent_pid: int) -> None:
    while os.getppid() == parent_pid:
        time.sleep(1.0)
    os._exit(0)


def _read_exact(fd: int, n: int) -> bytearray | None:
    """``n`` bytes from a blocking ``fd``; ``None`` at EOF."""
    buf = bytearray(n)
    view = memoryview(buf)
    got = 0
    while got < n:
        k = os.readv(fd, [view[got:]])
        if k == 0:
            return None
        got += k
    return buf


def _write_frame(fd: int, meta: bytes, blob: bytes, wait: Callable[[], None] | None = None) -> None:
    """Write one frame to ``fd``; on a non-blocking fd, ``wait()`` until it is writable again."""
    views = [memoryview(b) for b in (_HEADER.pack(len(meta), len(blob)), meta, blob) if len(b)]
    while views:
        try:
            k = os.writev(fd, views)
        except BlockingIOError:
            if wait is None:
                raise
            wait()
            continue
        while k:  # drop what was written: whole buffers, then part of the next
            if k >= len(views[0]):
                k -= len(views[0])
                views.pop(0)
            else:
                views[0] = views[0][k:]
                k = 0


def _worker_main(
    rx: int, tx: int, foreign: list[int], locator: KnnLocator, encoder: ScanEncoder, split: PlaceSplit | None,
    parent_pid: int,
) -> None:
    """A worker's life: answer framed requests ``(op, args)`` with ``(True, result)`` or
    ``(False, exception)`` until an empty frame, EOF or the parent's exit."""
    global _LOCATOR, _ENCODER, _SPLIT
    for fd in foreign:  # the server's ends and the other workers' pipes: not ours to hold open
        try:
            os.close(fd)
        except OSError:
            pass
    _LOCATOR, _ENCODER, _SPLIT = locator, encoder, split
    _init_worker(parent_pid)
    while True:
        header = _read_exact(rx, _HEADER.size)
        if header is None:
            return
        n_meta, n_blob = _HEADER.unpack(header)
        meta = _read_exact(rx, n_meta) if n_meta else None
        blob = _read_exact(rx, n_blob) if n_blob else b""
        if meta is None or blob is None:
            return
        op, args = pickle.loads(meta)
        if n_blob:
            args = (blob, *args)
        try:
            reply: tuple[bool, Any] = (True, _OPS[op](*args))
        except Exception as e:  # noqa: BLE001 - handed to the caller, as an executor would
            reply = (False, e)
        try:
            data = pickle.dumps(reply, protocol=pickle.HIGHEST_PROTOCOL)
        except Exception as e:  # noqa: BLE001 - an unpicklable exception: send its text
            data = pickle.dumps((False, SearchUnavailableError(f"search worker failed: {reply[1]!r} ({e})")))
        _write_frame(tx, data, b"")


def _ping() -> int:
    return os.getpid()


def _locate_chunk(scans: Sequence[Mapping[str, float]]) -> _Rows:
    """In a worker: locate a chunk of scans (non-strict: the batch-wide check is the caller's)."""
    loc = _LOCATOR
    if loc is None:  # pragma: no cover - only if called outside a pool worker
        raise SearchUnavailableError("search worker process has no locator")
    res = loc.locate(scans)
    return tuple(getattr(res, f) for f in _FIELDS)


def _locate_body(
    body: bytes | bytearray, part: int, parts: int, max_batch: int, render: bool
) -> tuple[NDArray[np.int64], _Rows, list[bytes] | None] | int | None:
    """In a worker: parse and validate a request body, locate share ``part`` of ``parts``:
    (its row indices, its result rows, with ``render`` their JSON position objects). ``None``: not
    certainly valid (the server takes the full path); an int: the batch size, above ``max_batch``
    (nothing searched)."""
    loc, enc = _LOCATOR, _ENCODER
    if loc is None or enc is None:  # pragma: no cover - only if called outside a pool worker
        raise SearchUnavailableError("search worker process has no locator")
    flat = flat_scans(body)
    if flat is None:
        return None
    n = len(flat)
    if n > max_batch:
        return n
    if _SPLIT is not None and parts > 1:
        rows = _SPLIT.split(flat, parts)[part]
    else:
        b = _bounds(n, parts)
        rows = np.arange(b[part], b[part + 1], dtype=np.int64)
    res = loc.locate(enc.encode(flat, rows))
    # every row rendered, one not located too (nulls and its error: a batch answers per fingerprint)
    json_rows = position_rows(res, loc.uncertainty) if render else None
    return rows, tuple(getattr(res, f) for f in _FIELDS), json_rows


_OPS: dict[str, Callable[..., Any]] = {"ping": _ping, "chunk": _locate_chunk, "body": _locate_body}


def _bounds(n: int, parts: int) -> list[int]:
    """Contiguous, near-equal chunks of ``n`` rows: chunk i is rows [b[i], b[i + 1])."""
    return [n * i // parts for i in range(parts + 1)]


# --- server process side -------------------------------------------------------------------


class _Worker:
    """The server's handle on one worker: its process and the server ends of its pipes
    (non-blocking). Used by one request at a time (see ``_Crew``)."""

    def __init__(self, proc: BaseProcess, tx: int, rx: int) -> None:
        self.proc = proc
        self.tx = tx
        self.rx = rx
        self.busy = False  # claimed by a request (guarded by the crew's condition)
        self.orphaned = False  # shut down while busy: the request using it closes its pipes

    @property
    def pid(self) -> int:
        return self.proc.pid or 0

    def _wait(self, fd: int, event: int, sentinels: Sequence[int], deadline: float) -> None:
        """Until ``fd`` is ready for ``event``: ``_WorkerDied`` if one of the processes of
        ``sentinels`` exits first (this worker's and those of the request's other shares: any
        death fails the request at once), ``_WorkerTimeout`` at the deadline. Why poll, not
        select: the server may hold fds above 1024."""
        poll = select.poll()
        poll.register(fd, event)
        for s in sentinels:
            poll.register(s, select.POLLIN)
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise _WorkerTimeout()
            events = dict(poll.poll(math.ceil(left * 1000)))
            if fd in events:
                return
            if events:  # only sentinels: a worker has exited
                raise _WorkerDied()

    def send(self, meta: bytes, deadline: float, blob: bytes = b"") -> None:
        """One frame: ``meta`` (a pickle; empty: exit) and ``blob`` (raw bytes, the first argument of the op)."""
        try:
            _write_frame(
                self.tx, meta, blob, lambda: self._wait(self.tx, select.POLLOUT, [self.proc.sentinel], deadline)
            )
        except OSError as e:  # EPIPE: the worker is gone
            raise _WorkerDied() from e

    def _recv_exact(self, n: int, deadline: float, sentinels: Sequence[int]) -> bytearray:
        buf = bytearray(n)
        view = memoryview(buf)
        got = 0
        while got < n:
            try:
                k = os.readv(self.rx, [view[got:]])
            except BlockingIOError:
                self._wait(self.rx, select.POLLIN, sentinels, deadline)
                continue
            except OSError as e:
                raise _WorkerDied() from e
            if k == 0:
                raise _WorkerDied()
            got += k
        return buf

    def recv(self, deadline: float, others: Sequence["_Worker"] = ()) -> bytearray:
        """A reply's pickle (replies have no raw part). ``_WorkerDied`` also if one of ``others``
        dies meanwhile."""
        sentinels = [self.proc.sentinel] + [w.proc.sentinel for w in others if w is not self]
        n_meta, _ = _HEADER.unpack(self._recv_exact(_HEADER.size, deadline, sentinels))
        return self._recv_exact(n_meta, deadline, sentinels)

    def close_fds(self) -> None:
        for fd in (self.tx, self.rx):
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self.tx = self.rx = -1


class _Crew:
    """The pool's workers and who is using them. A request claims free workers all at once
    (never holds one while waiting for another: no deadlock) and never waits while one is free
    (an executor's queue would not either)."""

    def __init__(self, workers: list[_Worker]) -> None:
        self.workers = workers
        self.cond = threading.Condition()
        self.closed = False

    def claim(self, want: Callable[[int], int], deadline: float) -> list[_Worker]:
        """``want(free)`` of the free workers (at least one), once one is free."""
        with self.cond:
            free: list[_Worker] = []

            def ready() -> bool:
                free[:] = [w for w in self.workers if not w.busy]
                return self.closed or bool(free)

            if not self.cond.wait_for(ready, max(0.0, deadline - time.monotonic())):
                raise _WorkerTimeout()
            if self.closed:
                raise _PoolClosed()
            chosen = free[: max(1, min(len(free), want(len(free))))]
            for w in chosen:
                w.busy = True
            return chosen

    def release(self, chosen: list[_Worker]) -> None:
        with self.cond:
            for w in chosen:
                w.busy = False
                if w.orphaned:  # shut down meanwhile: the last user closes the pipes
                    w.close_fds()
            self.cond.notify_all()

    def shutdown(self, graceful: bool = True, timeout: float | None = None) -> None:
        """Stop the workers without ever blocking on a stuck one: ``graceful``: let requests in
        flight finish (up to ``timeout``, default ``SHUTDOWN_TIMEOUT_S``), ask the workers to exit
        and wait for them; then kill what is left. Every worker is reaped before this returns;
        pipes are closed here, or by the request still using them when it fails."""
        timeout = SHUTDOWN_TIMEOUT_S if timeout is None else timeout
        deadline = time.monotonic() + timeout
        with self.cond:
            self.closed = True
            self.cond.notify_all()  # requests waiting for a worker: the pool is gone
            if graceful:
                self.cond.wait_for(lambda: not any(w.busy for w in self.workers), timeout)
            idle = [w for w in self.workers if not w.busy]
            for w in idle:
                w.busy = True  # ours now, for good
        if graceful:
            for w in idle:
                try:
                    w.send(b"", min(deadline, time.monotonic() + 1.0))  # an empty pickle: exit
                except (_WorkerDied, _WorkerTimeout):
                    pass
            for w in self.workers:
                w.proc.join(max(0.0, deadline - time.monotonic()))
        for w in self.workers:
            if w.proc.is_alive():
                w.proc.kill()  # a request still on it fails on the sentinel, then releases it
        for w in self.workers:
            w.proc.join(timeout)
        with self.cond:
            for w in self.workers:
                if w in idle or not w.busy:
                    w.close_fds()
                else:
                    w.orphaned = True


def _set_pipe_size(fd: int) -> None:
    try:
        import fcntl

        fcntl.fcntl(fd, fcntl.F_SETPIPE_SZ, PIPE_BYTES)
    except (ImportError, AttributeError, OSError):  # not Linux, or above /proc/sys/fs/pipe-max-size
        pass


def _start_workers(processes: int, locator: KnnLocator, encoder: ScanEncoder, split: PlaceSplit | None) -> _Crew:
    ctx = mp.get_context("fork")
    pipes = []
    for _ in range(processes):
        req_r, req_w = os.pipe()  # server -> worker
        rep_r, rep_w = os.pipe()  # worker -> server
        for fd in (req_w, rep_w):
            _set_pipe_size(fd)
        pipes.append((req_r, req_w, rep_r, rep_w))
    # Fds of ours open in the server at each fork: a worker closes all but its own two ends. Only
    # these: an fd closed here earlier may already be reused (e.g. by the next fork's sentinel).
    open_fds = {fd for p in pipes for fd in p}
    workers: list[_Worker] = []
    try:
        for i, (req_r, req_w, rep_r, rep_w) in enumerate(pipes):
            proc = ctx.Process(
                target=_worker_main, name=f"graphslam-search-{i}", daemon=True,
                args=(req_r, rep_w, sorted(open_fds - {req_r, rep_w}), locator, encoder, split, os.getpid()),
            )
            proc.start()
            os.close(req_r)
            os.close(rep_w)
            open_fds -= {req_r, rep_w}
            os.set_blocking(req_w, False)
            os.set_blocking(rep_r, False)
            workers.append(_Worker(proc, req_w, rep_r))
    except BaseException:
        for fd in open_fds - {fd for w in workers for fd in (w.tx, w.rx)}:
            os.close(fd)
        _Crew(workers).shutdown(graceful=False)
        raise
    return _Crew(workers)


class SearchPool:
    """``locator.locate`` with large batches spread over ``processes`` forked workers.
    ``processes`` 0 (or no ``fork`` on this platform, or an empty map): in-process only.
    Thread-safe. Create it after the locator is complete (the workers fork a snapshot);
    ``close()`` stops the workers (also at garbage collection / interpreter exit)."""

    def __init__(
        self, locator: KnnLocator, processes: int, *, min_batch: int = SEARCH_POOL_MIN_BATCH,
        timeout: float = SEARCH_TIMEOUT_S,
    ) -> None:
        if isinstance(processes, bool) or not isinstance(processes, int) or processes < 0:
            raise GraphSlamError(f"search processes must be an integer >= 0, got {processes!r}")
        self.locator = locator
        self.min_batch = max(1, min_batch)
        self.timeout = timeout
        self._lock = threading.Lock()
        self._crew: _Crew | None = None
        self._inflight = 0  # batches on the workers now, or waiting for them (see _parts)
        if processes == 0 or len(locator.radio_map) == 0:
            return
        if not fork_available():
            log.warning("no 'fork' start method on this platform: searching in the server process")
            return
        ivf = locator.ivf
        split = None
        if processes > 1 and ivf is not None and 2 <= ivf.n_clusters <= PLACE_MAX_CLUSTERS:
            try:
                split = PlaceSplit(locator)
            except np.linalg.LinAlgError as e:  # only a speed-up: split batches in order instead
                log.warning("search pool: no split by place (%s)", e)
        # Forked here and now: from a complete locator, and before the server starts its threads.
        crew = _start_workers(processes, locator, ScanEncoder(locator.radio_map), split)
        try:
            deadline = time.monotonic() + timeout
            for w in crew.workers:
                w.send(pickle.dumps(("ping", ())), deadline)
            for w in crew.workers:
                ok, pid = pickle.loads(w.recv(deadline))
                if not ok or pid != w.pid:
                    raise _WorkerDied()
        except (_WorkerDied, _WorkerTimeout):
            crew.shutdown(graceful=False)
            raise SearchUnavailableError("search worker processes did not start") from None
        self._crew = crew
        self._finalizer = weakref.finalize(self, crew.shutdown)
        log.info(
            "search pool: %d worker processes (pids %s), batches split %s", processes,
            ", ".join(str(w.pid) for w in crew.workers), "by place" if split is not None else "in order",
        )

    @property
    def processes(self) -> int:
        """Worker processes in use (0: searching in-process)."""
        crew = self._crew
        return len(crew.workers) if crew is not None else 0

    @property
    def pids(self) -> tuple[int, ...]:
        crew = self._crew
        return tuple(w.pid for w in crew.workers) if crew is not None else ()

    def _parts(self, free: int) -> int:
        """Shares for a batch: every worker when it is the only batch in flight (one client: all
        cores on it); fewer when others are in flight, down to one worker per batch (several
        clients: whole batches in parallel, without paying a search's per-call cost -- the IVF
        loop over clusters -- once per share)."""
        return max(1, min(free, self.processes // max(1, self._inflight)))

    def _run(self, op: str, args_of: Callable[[int], list[tuple[Any, ...]]], blob: bytes = b"") -> list[Any]:
        """``op(*a)`` on the workers for every ``a`` in ``args_of(shares)`` (``op(blob, *a)`` with a
        ``blob``), results in order; worker failures -> ``SearchUnavailableError``, never a hang."""
        crew = self._crew
        if crew is None:
            raise SearchUnavailableError("search pool is shut down")
        with self._lock:
            self._inflight += 1
        deadline = time.monotonic() + self.timeout
        chosen: list[_Worker] = []
        try:
            chosen = crew.claim(self._parts, deadline)
            payloads = [pickle.dumps((op, a), protocol=pickle.HIGHEST_PROTOCOL) for a in args_of(len(chosen))]
            for w, payload in zip(chosen, payloads):
                w.send(payload, deadline, blob)
            # Every answer read before any is unpickled: whatever fails next, no answer is left in
            # a pipe for the next request to take as its own.
            raw = [w.recv(deadline, chosen) for w in chosen]
        except _WorkerDied:
            self._retire("a search worker process died", crew)
            raise SearchUnavailableError(
                "a search worker process died while answering; the server now searches in-process: retry the request"
            ) from None
        except _WorkerTimeout:
            self._retire(f"search worker processes did not answer within {self.timeout:g} s", crew)
            raise SearchUnavailableError(f"search worker processes did not answer within {self.timeout:g} s") from None
        except _PoolClosed:
            raise SearchUnavailableError("search pool is shut down") from None
        finally:
            crew.release(chosen)
            with self._lock:
                self._inflight -= 1
        out = []
        for ok, value in map(pickle.loads, raw):
            if not ok:
                raise value  # the worker's own exception, as an executor would re-raise it
            out.append(value)
        return out

    def _result(self, parts: list[_Rows], strict: bool, take: NDArray[np.int64] | None = None) -> KnnResult:
        """The shares' rows joined, in order, or reordered: row i is joined row ``take[i]``."""
        cols = [np.concatenate([p[i] for p in parts]) if parts[0][i] is not None else None for i in range(len(_FIELDS))]
        if take is not None:
            cols = [c[take] if c is not None else None for c in cols]
        res = KnnResult(**dict(zip(_FIELDS, cols)), config=self.locator.config)  # type: ignore[arg-type]
        err = strict_error(res, self.locator.config.min_common) if strict else None
        if err is not None:
            raise err
        return res

    def locate(self, scans: Sequence[Mapping[str, float]], *, strict: bool = False) -> KnnResult:
        """``self.locator.locate(scans, strict=strict)``, the same result; batches of
        ``min_batch`` or more on the workers. ``SearchUnavailableError`` if a worker died or
        stalled meanwhile."""
        if self._crew is None or len(scans) < self.min_batch:
            return self.locator.locate(scans, strict=strict)

        def chunks(parts: int) -> list[tuple[Any, ...]]:
            b = _bounds(len(scans), parts)
            return [(list(scans[lo:hi]),) for lo, hi in zip(b[:-1], b[1:])]

        return self._result(self._run("chunk", chunks), strict)

    def locate_body(self, body: bytes, *, max_batch: int, strict: bool = False) -> KnnResult | None:
        """Locate the scans of a ``POST /v1/locate`` JSON body without parsing it here: each
        worker parses it (``parsing.flat_scans``) and locates its share of the rows. ``None``
        if the body is not certainly valid for the fast parser (the caller then takes the full
        path, with pydantic's messages) or if there is no pool. ``BatchTooLargeError`` above
        ``max_batch`` fingerprints (checked before any search).

        Why: parsing and encoding are GIL-bound work; in the
        workers it runs in parallel with the other share, and the server process (which does
        all the HTTP work) never serialises the scans."""
        got = self._body(body, max_batch, strict, render=False)
        return got[0] if got is not None else None

    def locate_body_json(
        self, body: bytes, *, max_batch: int, strict: bool = False
    ) -> tuple[KnnResult, list[bytes]] | None:
        """``locate_body``, and each row's JSON position object rendered by the workers
        (``render.position_rows``, in request order; for ``render.response_json``)."""
        got = self._body(body, max_batch, strict, render=True)
        if got is None or got[1] is None:  # the latter only if a share had invalid rows, and strict is off
            return None if got is None else (got[0], position_rows(got[0], self.locator.uncertainty))
        return got[0], got[1]

    def _body(
        self, body: bytes, max_batch: int, strict: bool, render: bool
    ) -> tuple[KnnResult, list[bytes] | None] | None:
        if self._crew is None or not body:
            return None
        out = self._run("body", lambda parts: [(i, parts, max_batch, render) for i in range(parts)], blob=body)
        if out[0] is None:  # every worker ran the same deterministic parser
            return None
        if isinstance(out[0], int):
            raise BatchTooLargeError(out[0], max_batch)
        # Shares are sets of rows (places): request row i is row take[i] of the shares joined.
        take = np.argsort(np.concatenate([rows for rows, _, _ in out]), kind="stable") if len(out) > 1 else None
        res = self._result([fields for _, fields, _ in out], strict, take)
        shares_json = [j for _, _, j in out]
        if not render or any(j is None for j in shares_json):
            return res, None
        joined = [row for j in shares_json for row in j]
        return res, joined if take is None else [joined[i] for i in take.tolist()]

    def _retire(self, why: str, crew: _Crew) -> None:
        with self._lock:
            if self._crew is not crew:  # already retired or closed
                return
            self._crew = None
        log.error("search pool: %s; searching in the server process from now on", why)
        self._finalizer.detach()
        crew.shutdown(graceful=False)

    def close(self) -> None:
        """Stop the workers (idempotent). Later ``locate`` calls search in-process."""
        with self._lock:
            crew, self._crew = self._crew, None
        if crew is not None:
            self._finalizer.detach()
            crew.shutdown()

    def __enter__(self) -> "SearchPool":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
