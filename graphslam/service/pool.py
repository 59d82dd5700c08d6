"""Search process pool: large batches searched in forked worker processes.

Why: the IVF search loop holds the GIL, so one server process searches on about one
core. ``SearchPool`` forks N worker processes once the locator (radio map + index) is
built; they inherit it copy-on-write (fork start method: nothing is pickled or rebuilt).

- ``locate(scans)``: a batch of ``min_batch`` scans or more is split into contiguous
  chunks, each located in a worker with ``KnnLocator.locate``; the per-row result arrays
  are concatenated in order.
- ``locate_body(body)`` (the service's path for big bodies): every worker gets the raw
  JSON body, parses it with the service's fast parser and locates its share of the rows.
  Why: in the server process, parsing (~5 ms per 1,000), encoding (~10 ms) or pickling
  the scans (~3 ms) is GIL-bound work in series with everything else; in the workers it
  runs in parallel, and the server only does HTTP.

One batch alone in flight is split over every worker (one client gets all the cores);
concurrent batches take fewer chunks each, down to one worker per batch (a search call
has a fixed cost, the IVF loop over clusters, paid once per chunk).

Results: the same neighbours and labels as in-process search; the same floats where a
row's search is computed on its own (exact search on sparse maps); where BLAS GEMMs are
involved (IVF, dense maps) ~1 ulp apart, as in-process search already is when the same
query arrives in another batch (tested). Workers use one BLAS thread, as
``graphslam serve``'s server process does (the thread count changes GEMM rounding).
Smaller requests stay in the server process: a round trip costs more than their search.

Failures: if a worker dies (OOM killer, a signal), the request(s) in flight get
``SearchUnavailableError`` (the service answers 503) and the pool is retired; later
requests are searched in the server process (slower, still correct). Where ``fork`` is
unavailable the pool is never started and everything is searched in-process.
"""

from __future__ import annotations

import gc
import logging
import multiprocessing as mp
import os
import signal
import threading
import time
import weakref
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from graphslam.core.knn import KnnLocator, KnnResult, strict_error
from graphslam.errors import GraphSlamError
from graphslam.service.parsing import fast_scans

log = logging.getLogger(__name__)

# Batches from this size go to the pool: below it the IPC round trip (~1 ms) outweighs
# the search saved (~35 us per fingerprint with the IVF index on UJIIndoorLoc).
SEARCH_POOL_MIN_BATCH = 64
# A chunk of 5,000 fingerprints takes ~0.2 s; a worker silent this long is stuck.
SEARCH_TIMEOUT_S = 120.0
# Grace period for workers to exit at shutdown before they are killed.
SHUTDOWN_TIMEOUT_S = 5.0

# Per worker process: the locator inherited from the server process (set by _init_worker).
_LOCATOR: KnnLocator | None = None

_Rows = tuple[NDArray, ...]
_FIELDS = ("xy", "score", "spread", "neighbours", "distances", "n_known_aps", "floor", "building")


class SearchUnavailableError(GraphSlamError):
    """The search worker processes cannot answer (one died, or they did not answer in time)."""


class BatchTooLargeError(GraphSlamError):
    """A request body holds more fingerprints than the service accepts."""

    def __init__(self, n: int, max_batch: int) -> None:
        self.n = n
        self.max_batch = max_batch
        super().__init__(f"batch of {n} fingerprints, at most {max_batch} per request")


def default_search_processes() -> int:
    """``min(2, cores)``: the machines this serves on have 2 cores; more processes than
    cores only add contention."""
    return min(2, os.cpu_count() or 1)


def fork_available() -> bool:
    return "fork" in mp.get_all_start_methods()


def _init_worker(locator: KnnLocator, parent_pid: int) -> None:
    global _LOCATOR
    _LOCATOR = locator
    # Ctrl-C reaches the whole process group: the server shuts the pool down itself, so a
    # worker must not die first (that would show as a crashed pool, with tracebacks).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    from graphslam.core.ivf import limit_blas_threads

    limit_blas_threads(1)  # one search per process; BLAS threads only slow the IVF's small GEMMs
    # The inherited heap (map, index, every module) never becomes garbage: keep the collector
    # off it (full collections would walk it, and touching it un-shares copy-on-write pages).
    gc.freeze()
    # A worker inherits the write ends of the pool's pipes, so it would never see EOF if the
    # server were killed (SIGKILL): watch the parent instead, and leave with it.
    threading.Thread(target=_exit_with_parent, args=(parent_pid,), daemon=True, name="parent-watch").start()


def _exit_with_parent(parent_pid: int) -> None:
    while os.getppid() == parent_pid:
        time.sleep(1.0)
    os._exit(0)


def _ping() -> int:
    return os.getpid()


def _locate_chunk(scans: Sequence[Mapping[str, float]]) -> _Rows:
    """In a worker: locate a chunk of scans (non-strict: the batch-wide check is the caller's)."""
    loc = _LOCATOR
    if loc is None:  # pragma: no cover - only if called outside a pool worker
        raise SearchUnavailableError("search worker process has no locator")
    res = loc.locate(scans)
    return tuple(getattr(res, f) for f in _FIELDS)


def _locate_body(body: bytes, part: int, parts: int, max_batch: int) -> _Rows | int | None:
    """In a worker: parse a request body with the fast parser and locate rows ``part`` of
    ``parts``. ``None``: not certainly valid (the server takes the full path); an int: the
    batch size, above ``max_batch`` (nothing searched)."""
    scans = fast_scans(body)
    if scans is None:
        return None
    if len(scans) > max_batch:
        return len(scans)
    bounds = _bounds(len(scans), parts)
    return _locate_chunk(scans[bounds[part] : bounds[part + 1]])


def _bounds(n: int, parts: int) -> list[int]:
    """Contiguous, near-equal chunks of ``n`` rows: chunk i is rows [b[i], b[i + 1])."""
    return [n * i // parts for i in range(parts + 1)]


def _stop_executor(ex: ProcessPoolExecutor, timeout: float = SHUTDOWN_TIMEOUT_S) -> None:
    """Shut ``ex`` down without ever blocking on a stuck worker: ask politely, wait up to
    ``timeout``, then kill what is left. Every worker is reaped before this returns."""
    procs = list((getattr(ex, "_processes", None) or {}).values())  # before shutdown() drops it
    manager = getattr(ex, "_executor_manager_thread", None)
    ex.shutdown(wait=False, cancel_futures=True)
    if manager is not None:
        manager.join(timeout)
    for p in procs:
        if p.is_alive():
            p.kill()
    if manager is not None:
        manager.join(timeout)
    for p in procs:
        p.join(timeout)


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
        self._executor: ProcessPoolExecutor | None = None
        self._pids: tuple[int, ...] = ()
        self._inflight = 0  # batches on the workers now (see _parts)
        if processes == 0 or len(locator.radio_map) == 0:
            return
        if not fork_available():
            log.warning("no 'fork' start method on this platform: searching in the server process")
            return
        ex = ProcessPoolExecutor(
            processes, mp_context=mp.get_context("fork"), initializer=_init_worker,
            initargs=(locator, os.getpid()),
        )
        try:
            # With the fork context the first submit forks every worker, here and now: from a
            # complete locator, and before the server starts its threads.
            ex.submit(_ping).result(timeout)
        except BaseException:
            _stop_executor(ex)
            raise
        self._executor = ex
        self._pids = tuple(getattr(ex, "_processes", None) or ())
        self._finalizer = weakref.finalize(self, _stop_executor, ex)
        log.info("search pool: %d worker processes (pids %s)", processes, ", ".join(map(str, self._pids)))

    @property
    def processes(self) -> int:
        """Worker processes in use (0: searching in-process)."""
        return len(self._pids) if self._executor is not None else 0

    @property
    def pids(self) -> tuple[int, ...]:
        return self._pids if self._executor is not None else ()

    def _parts(self) -> int:
        """Chunks for the next batch: every worker when it is the only batch in flight (one
        client: all cores on it); fewer when others are in flight, down to one worker per batch
        (several clients: whole batches in parallel, without paying a search's per-call cost
        -- the IVF loop over clusters -- once per chunk)."""
        return max(1, self.processes // max(1, self._inflight))

    def _run(self, fn: Callable[..., Any], args: list[tuple[Any, ...]]) -> list[Any]:
        """``fn(*a)`` for every ``a`` on the workers, results in order; worker failures ->
        ``SearchUnavailableError``, never a hang."""
        ex = self._executor
        futures: list[Future[Any]] = []
        try:
            if ex is None:
                raise RuntimeError("closed")
            futures = [ex.submit(fn, *a) for a in args]
            deadline = time.monotonic() + self.timeout
            return [f.result(max(0.0, deadline - time.monotonic())) for f in futures]
        except BrokenProcessPool:
            self._retire("a search worker process died")
            raise SearchUnavailableError(
                "a search worker process died while answering; the server now searches in-process: retry the request"
            ) from None
        except RuntimeError as e:  # submit() after close(): the server is shutting down
            raise SearchUnavailableError(f"search pool is shut down ({e})") from None
        except TimeoutError:
            for f in futures:
                f.cancel()
            raise SearchUnavailableError(f"search worker processes did not answer within {self.timeout:g} s") from None

    def _result(self, parts: list[_Rows], strict: bool) -> KnnResult:
        cols = [np.concatenate([p[i] for p in parts]) if parts[0][i] is not None else None for i in range(len(_FIELDS))]
        res = KnnResult(**dict(zip(_FIELDS, cols)), config=self.locator.config)  # type: ignore[arg-type]
        err = strict_error(res, self.locator.config.min_common) if strict else None
        if err is not None:
            raise err
        return res

    def locate(self, scans: Sequence[Mapping[str, float]], *, strict: bool = False) -> KnnResult:
        """``self.locator.locate(scans, strict=strict)``, the same result; batches of
        ``min_batch`` or more on the workers. ``SearchUnavailableError`` if a worker died or
        stalled meanwhile."""
        if self._executor is None or len(scans) < self.min_batch:
            return self.locator.locate(scans, strict=strict)
        with self._lock:
            self._inflight += 1
            parts = self._parts()
        try:
            n = len(scans)
            bounds = _bounds(n, parts)
            chunks = [(list(scans[lo:hi]),) for lo, hi in zip(bounds[:-1], bounds[1:]) if hi > lo]
            return self._result(self._run(_locate_chunk, chunks), strict)
        finally:
            with self._lock:
                self._inflight -= 1

    def locate_body(self, body: bytes, *, max_batch: int, strict: bool = False) -> KnnResult | None:
        """Locate the scans of a ``POST /v1/locate`` JSON body without parsing it here: each
        worker parses it (``parsing.fast_scans``) and locates its share of the rows. ``None``
        if the body is not certainly valid for the fast parser (the caller then takes the full
        path, with pydantic's messages) or if there is no pool. ``BatchTooLargeError`` above
        ``max_batch`` fingerprints (checked before any search).

        Why: parsing is ~7 ms per 1,000 fingerprints of GIL-bound work; in the workers it runs
        in parallel with the other chunk, and the server process (which does all the HTTP
        work) never serialises the scans (pickling them cost ~3 ms per 1,000 each way)."""
        if self._executor is None:
            return None
        with self._lock:
            self._inflight += 1
            parts = self._parts()
        try:
            out = self._run(_locate_body, [(body, i, parts, max_batch) for i in range(parts)])
        finally:
            with self._lock:
                self._inflight -= 1
        if out[0] is None:  # every worker ran the same deterministic parser
            return None
        if isinstance(out[0], int):
            raise BatchTooLargeError(out[0], max_batch)
        return self._result(out, strict)

    def _retire(self, why: str) -> None:
        with self._lock:
            ex, self._executor = self._executor, None
        if ex is not None:
            log.error("search pool: %s; searching in the server process from now on", why)
            _stop_executor(ex)

    def close(self) -> None:
        """Stop the workers (idempotent). Later ``locate`` calls search in-process."""
        with self._lock:
            ex, self._executor = self._executor, None
        if ex is not None:
            _stop_executor(ex)
            self._finalizer.detach()

    def __enter__(self) -> "SearchPool":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
