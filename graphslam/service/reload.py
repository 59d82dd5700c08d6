"""Hot reload of the radio map: ``graphslam serve --watch`` and SIGHUP.

``ReloadingApp`` is an ASGI app in front of the service app (``create_app``). Every request
goes to the *current* service app, taken once when the request starts, so a request is
answered wholly by one map. A reload builds a complete new service app (map read and checked,
locator and index built, search processes forked) on a background thread while the old one
keeps answering, self-tests it with one of its own fingerprints, then swaps the reference on
the event loop: the swap itself is one assignment, nothing is refused or queued. The old app
is closed (its search processes stopped) when its last request has finished.

A new map that does not load (unreadable, wrong schema, failed checksum, no fingerprint, a
self-test that does not answer) is refused: the error is logged and the old map stays. A
failed file is not retried until it changes again (``--watch`` compares its ``stat``).

Why a whole app and not just the locator: ``create_app`` binds the locator, its search pool
and the map summary together; swapping the app keeps them consistent without touching it.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import signal
import threading
from pathlib import Path
from typing import Any, Callable, Iterator, MutableMapping

from fastapi import FastAPI

log = logging.getLogger(__name__)

Builder = Callable[[], FastAPI]
_Signature = tuple[int, int, int, int]  # st_dev, st_ino, st_size, st_mtime_ns


def _signature(path: Path) -> _Signature | None:
    try:
        st = path.stat()
    except OSError:
        return None
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)


def self_test(app: FastAPI) -> None:
    """Locate one fingerprint of the app's own map: it must answer with a finite position."""
    import numpy as np

    locator = app.state.locator
    rm = locator.radio_map
    heard = np.flatnonzero(np.diff(rm.fingerprints.values.indptr) > 0)
    if len(heard) == 0:
        raise ValueError("the radio map has no fingerprint that hears an access point")
    res = locator.locate(rm.fingerprints.rows(slice(int(heard[0]), int(heard[0]) + 1)))
    if not (bool(res.valid[0]) and np.isfinite(res.xy[0]).all()):
        raise ValueError("self-test: one of the map's own fingerprints got no position")


def _forget_fastapi_caches() -> None:
    """Empty FastAPI's module-level caches of endpoint functions, so that a retired app is freed.
    FastAPI (``fastapi.dependencies.models``, 0.12x+) remembers per endpoint function whether it
    is a coroutine or a generator in LRU caches of 4,096 entries keyed by the function itself;
    our endpoints are closures over their app's map, index and search pool, so every retired
    app stayed alive until thousands of reloads later (measured: +3 MB RSS per reload).
    The caches refill on the next requests (one check per endpoint)."""
    import functools

    try:
        from fastapi.dependencies import models
    except ImportError:
        return
    for value in vars(models).values():
        if isinstance(value, functools._lru_cache_wrapper):
            value.cache_clear()


class ReloadingApp:
    """ASGI app that serves ``current`` and swaps in a new one built by ``builder``.

    ``watch_interval``: poll ``path`` every so many seconds and reload when it changes
    (None: no polling). ``sighup``: reload on SIGHUP (only where the event loop runs in the
    main thread, as in ``graphslam serve``). ``reload_now()`` asks for a reload from any thread.
    """

    def __init__(
        self, current: FastAPI, builder: Builder, path: str | Path, *, watch_interval: float | None = None,
        sighup: bool = True,
    ) -> None:
        self.current = current
        self.builder = builder
        self.path = Path(path)
        self.watch_interval = watch_interval
        self.sighup = sighup
        self.generation = 0  # swaps done
        self.refused = 0  # new maps refused
        self._seen = _signature(self.path)  # the file the current app was built from
        self._inflight: dict[int, int] = {}
        self._retired: dict[int, FastAPI] = {}
        self._loop: asyncio.AbstractEventLoop | None = None
        self._busy = threading.Lock()  # one reload at a time
        self._tasks: list[asyncio.Task] = []
        self.state = current.state  # `app.state.locator` etc. of the app being served

    # --- ASGI -------------------------------------------------------------------------------

    async def __call__(self, scope: MutableMapping[str, Any], receive: Callable, send: Callable) -> None:
        if scope["type"] == "lifespan":
            await self._lifespan(receive, send)
            return
        with self.hold() as app:  # taken once: the whole request is answered by this map
            await app(scope, receive, send)

    @contextlib.contextmanager
    def hold(self) -> Iterator[FastAPI]:
        """The current app, kept open (not closed by a swap) until the block ends. On the event loop."""
        app = self.current
        key = id(app)
        self._inflight[key] = self._inflight.get(key, 0) + 1
        try:
            yield app
        finally:
            self._inflight[key] -= 1
            if self._inflight[key] == 0 and key in self._retired:
                self._close_later(self._retired.pop(key))

    def start(self) -> None:
        """Start watching (and SIGHUP) on the running event loop: the lifespan's startup."""
        self._loop = asyncio.get_running_loop()
        if self.watch_interval is not None:
            self._tasks.append(asyncio.create_task(self._watch()))
        if self.sighup and threading.current_thread() is threading.main_thread():
            self._loop.add_signal_handler(signal.SIGHUP, self.reload_now)

    def stop(self) -> None:
        """Stop watching and close every app (their search processes): the lifespan's shutdown."""
        for t in self._tasks:
            t.cancel()
        if self.sighup and threading.current_thread() is threading.main_thread() and self._loop:
            self._loop.remove_signal_handler(signal.SIGHUP)
        for app in [self.current, *self._retired.values()]:
            app.state.search_pool.close()
        self._retired.clear()

    async def _lifespan(self, receive: Callable, send: Callable) -> None:
        while True:
            message = await receive()
            if message["type"] == "lifespan.startup":
                self.start()
                await send({"type": "lifespan.startup.complete"})
            elif message["type"] == "lifespan.shutdown":
                self.stop()
                await send({"type": "lifespan.shutdown.complete"})
                return

    # --- reload -----------------------------------------------------------------------------

    def reload_now(self) -> None:
        """Reload the map from ``path`` in the background (thread-safe; ignored while one runs)."""
        if self._loop is None:
            raise RuntimeError("the app is not being served")
        self._loop.call_soon_threadsafe(self._start_reload, _signature(self.path))

    def _start_reload(self, sig: _Signature | None) -> None:
        if not self._busy.acquire(blocking=False):
            log.info("radio map reload already running; %s will be checked again after it", self.path)
            return
        threading.Thread(target=self._build, args=(sig,), name="graphslam-reload", daemon=True).start()

    def _build(self, sig: _Signature | None) -> None:
        try:
            app = self.builder()
            try:
                self_test(app)
            except Exception:
                app.state.search_pool.close()
                raise
        except Exception as e:  # noqa: BLE001 - any failure keeps the old map
            self._seen = sig  # do not retry this file until it changes again
            if _signature(self.path) != sig:  # replaced while being read: the next check loads the new one
                log.info("radio map %s changed while being read; loading it again", self.path)
            else:
                self.refused += 1
                log.error("radio map %s refused (%s: %s); still serving the previous map", self.path,
                          type(e).__name__, e)
            self._busy.release()
            return
        assert self._loop is not None
        self._loop.call_soon_threadsafe(self._swap, app, sig)

    def _swap(self, app: FastAPI, sig: _Signature | None) -> None:
        old = self.current
        self.current = app
        self.state = app.state
        self._seen = sig
        self.generation += 1
        self._busy.release()
        # INFO: a plain `graphslam serve` shows it (serve's --log-level, info by default, is the
        # service loggers' level too: ``server.serve``); a reload is news, not a problem
        log.info(
            "radio map %s reloaded (generation %d: %d fingerprints, %s search)", self.path, self.generation,
            len(app.state.locator.radio_map), app.state.locator.index_kind,
        )
        if self._inflight.get(id(old), 0) == 0:
            self._close_later(old)
        else:
            self._retired[id(old)] = old

    def _close_later(self, app: FastAPI) -> None:
        self._inflight.pop(id(app), None)

        def close() -> None:
            app.state.search_pool.close()
            _forget_fastapi_caches()
            # the old map was frozen out of the collector at start-up (server._build_app): let
            # the collector see it again, or its reference cycles would never be freed
            gc.unfreeze()
            gc.collect()
            gc.freeze()

        threading.Thread(target=close, name="graphslam-retire", daemon=True).start()

    async def _watch(self) -> None:
        assert self.watch_interval is not None
        while True:
            await asyncio.sleep(self.watch_interval)
            sig = _signature(self.path)
            if sig is not None and sig != self._seen and not self._busy.locked():
                log.info("radio map %s changed on disk: reloading", self.path)
                self._start_reload(sig)

