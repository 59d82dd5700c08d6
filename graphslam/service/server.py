"""Run the service: blocking (``serve``) or in a background thread (tests, benchmarks)."""

from __future__ import annotations

import errno
import gc
import ipaddress
import json
import logging
import os
import signal
import socket
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import uvicorn
from fastapi import FastAPI

from graphslam.errors import GraphSlamError, ServiceError
from graphslam.service.config import DEFAULT_HOST, ServeConfig

if TYPE_CHECKING:
    from graphslam.service.reload import ReloadingApp

log = logging.getLogger(__name__)

# `serve --workers N`: the worker processes rebuild the app from this (JSON) environment variable.
_WORKER_CONFIG_ENV = "GRAPHSLAM_SERVE_WORKER_CONFIG"


def _build_app(radio_map_path: str | Path, **app_kwargs: object) -> FastAPI:
    from graphslam.core.radiomap.ivf import limit_blas_threads
    from graphslam.io.radiomap_io import read_radio_map
    from graphslam.service.app import create_app

    # A server process: parallelism comes from concurrent requests (and worker processes);
    # multi-threaded BLAS only slows the IVF index's many small GEMMs.
    limit_blas_threads(1)
    rm = read_radio_map(radio_map_path)
    app = create_app(rm, **app_kwargs)  # type: ignore[arg-type]
    # The map, index and modules live as long as the process: a full collection walking them is a
    # long pause any request could hit. Frozen, collections skip them.
    gc.freeze()
    log.info(
        "loaded %s (%d fingerprints, %s search, %d search processes)", radio_map_path, len(rm),
        app.state.locator.index_kind, app.state.search_pool.processes,
    )
    return app


def reloading_app(radio_map_path: str | Path, watch: float | None, **app_kwargs: object) -> "ReloadingApp":
    """The service behind a ``ReloadingApp``: SIGHUP (and ``watch``: polling the file every so many
    seconds) swaps in a new map without failing a request (``graphslam.service.reload``)."""
    from graphslam.service.reload import ReloadingApp

    def build() -> FastAPI:
        return _build_app(radio_map_path, **app_kwargs)

    return ReloadingApp(build(), build, radio_map_path, watch_interval=watch)


def served_app(radio_map_path: str | Path, watch: float | None, **app_kwargs: object) -> "ReloadingApp | FastAPI":
    """What ``serve`` serves: ``reloading_app`` of a radio map file, or the site app of a folder of
    floor maps (``graphslam.service.site``: every floor reloads on its own)."""
    from graphslam.service.site import is_site, site_app

    if not is_site(radio_map_path):
        return reloading_app(radio_map_path, watch, **app_kwargs)
    return site_app(radio_map_path, lambda path: _build_app(path, **app_kwargs), watch, **app_kwargs)


def worker_app() -> "ReloadingApp | FastAPI":
    """App factory for uvicorn worker processes (``serve(workers=N)``)."""
    cfg = json.loads(os.environ[_WORKER_CONFIG_ENV])
    return served_app(cfg.pop("radio_map_path"), cfg.pop("watch"), **cfg)




def is_loopback(host: str) -> bool:
    """Whether binding ``host`` keeps the service on this machine (``0.0.0.0`` / ``::`` do not)."""
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:  # a host name: it may resolve anywhere
        return False


def serve(radio_map_path: str | Path, cfg: ServeConfig | None = None) -> None:
    """Load the radio map and serve it until interrupted (``cfg``: ``ServeConfig``, its defaults when
    None). Why processes: a search holds the GIL most of the time, so one process searches on about
    one core.

    ``search_processes``: forked search workers that share the server's map and index
    (``graphslam.service.pool``); large batches are split over them, whatever the number of
    client connections. ``None``: ``min(2, cores)`` with one server process, 0 with
    ``workers`` > 1 (which already runs a process per worker). 0: search in the server process.
    ``workers`` > 1: that many server processes on one socket (uvicorn), each with its own copy
    of the map and index; connections, not requests, are spread over them. ``log_level``: one
    of ``LOG_LEVELS`` (``warning`` drops the access line per request). ``token``: bearer token
    required on ``/v1/`` (a warning when ``host`` is not loopback and there is none).
    SIGHUP reloads the map (in every worker); ``watch_s``: also poll the file every so many seconds.
    ``radio_map_path`` a folder: a site, one map per floor (``graphslam.service.site``; search in
    the server process unless ``search_processes`` is given, then that many per floor).
    The socket is bound first: an address that cannot be (taken, not this machine's) is a
    ``ServiceError``, before the map is read."""
    cfg = cfg or ServeConfig()
    log_level = cfg.log_level
    # the service's own lines (map loaded, reloaded, refused) at uvicorn's level: info by default
    service_log = logging.getLogger("graphslam.service")
    level = service_log.level
    service_log.setLevel(logging.DEBUG if log_level == "trace" else log_level.upper())
    try:
        _serve(radio_map_path, cfg)
    finally:
        service_log.setLevel(level)


def _serve(radio_map_path: str | Path, cfg: ServeConfig) -> None:
    from graphslam.service.pool import default_search_processes

    host, port, workers, log_level, watch = cfg.host, cfg.port, cfg.workers, cfg.log_level, cfg.watch_s
    if not cfg.token and not is_loopback(host):
        log.warning(
            "serving on %s without a bearer token: anyone who can reach this address can query the radio map "
            "(set --token or GRAPHSLAM_SERVE_TOKEN)", host,
        )
    from graphslam.service.site import is_site

    site = is_site(radio_map_path)
    if site:
        from graphslam.service.site import find_floor_maps

        find_floor_maps(radio_map_path)  # a folder without floor maps: one line, before the socket
    search_processes = cfg.search_processes
    if search_processes is None:  # a site's floors: each would fork its own
        search_processes = default_search_processes() if workers <= 1 and not site else 0
    kwargs: dict[str, object] = {**cfg.app_options(), "search_processes": search_processes}
    sock = listen(host, port)  # before the map loads: a taken port is one line, not uvicorn's start-up failure

    def serving() -> None:  # said once the map has loaded: a map that does not is its one error line alone
        log.info(
            "serving %s on http://%s:%d (%d worker process(es), %d search process(es) each)", radio_map_path, host,
            sock.getsockname()[1], workers, search_processes,
        )

    if workers <= 1:
        try:
            app = served_app(radio_map_path, watch, **kwargs)
        except BaseException:
            sock.close()
            raise
        serving()
        uvicorn.Server(uvicorn.Config(app, host=host, port=port, log_level=log_level)).run(sockets=[sock])
        return
    try:  # each worker process loads the maps: read them here first, so that a bad one is one line
        _check_maps(radio_map_path, site)
    except BaseException:
        sock.close()
        raise
    serving()
    from uvicorn.supervisors import Multiprocess

    class Supervisor(Multiprocess):
        def handle_hup(self) -> None:
            # every worker reloads in place (and refuses a broken map), instead of uvicorn's restart
            for process in self.processes:
                if process.pid is not None:
                    os.kill(process.pid, signal.SIGHUP)

    os.environ[_WORKER_CONFIG_ENV] = json.dumps({"radio_map_path": str(radio_map_path), "watch": watch, **kwargs})
    config = uvicorn.Config(
        "graphslam.service.server:worker_app", factory=True, host=host, port=port, workers=workers,
        log_level=log_level,
    )
    # What uvicorn.run does for workers > 1, but with our own listening socket: uvicorn's
    # bind_socket() omits IPPROTO_TCP, so asyncio skips TCP_NODELAY and every small response
    # waits for a delayed ACK.
    Supervisor(config, sockets=[sock]).run()


def _check_maps(radio_map_path: str | Path, site: bool) -> None:
    """Read the radio map (or every floor's): a ``RadioMapError`` naming a file that does not load."""
    from graphslam.io.radiomap_io import read_radio_map

    if site:
        from graphslam.service.site import find_floor_maps

        for path in find_floor_maps(radio_map_path).values():
            read_radio_map(path)
    else:
        read_radio_map(radio_map_path)


@dataclass
class BackgroundServer:
    """A real uvicorn server on a loopback socket, in a daemon thread. ``stop()`` runs the app's
    lifespan shutdown (stops its search worker processes)."""

    server: uvicorn.Server
    thread: threading.Thread
    host: str
    port: int

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    def stop(self, timeout: float = 10.0) -> None:
        self.server.should_exit = True
        self.thread.join(timeout)

    def __enter__(self) -> "BackgroundServer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _tcp_listener(host: str, port: int) -> socket.socket:
    """A bound listening-ready TCP socket. proto=IPPROTO_TCP matters: asyncio sets TCP_NODELAY on
    accepted sockets only when the listening socket says TCP; with proto 0, Nagle + delayed ACK
    delay every response."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM, socket.IPPROTO_TCP)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host.strip("[]"), port))
    except BaseException:
        sock.close()
        raise
    sock.set_inheritable(True)  # handed to the worker processes
    return sock


def listen(host: str, port: int) -> socket.socket:
    """``_tcp_listener``; an address that cannot be bound (taken, not this machine's) is a
    ``ServiceError`` naming it."""
    try:
        return _tcp_listener(host, port)
    except OSError as e:
        hint = " (another server listens there: stop it or choose another --port)" if e.errno == errno.EADDRINUSE else ""
        raise ServiceError(f"serve: cannot listen on {host}:{port}: {e.strerror or e}{hint}") from None


def start_background_server(
    app: FastAPI, *, host: str = DEFAULT_HOST, port: int = 0, startup_timeout: float = 20.0, log_level: str = "warning"
) -> BackgroundServer:
    """Bind ``host:port`` (0 = a free port) now, serve ``app`` in a thread, return once it accepts."""
    sock = _tcp_listener(host, port)  # IPPROTO_TCP: see _tcp_listener
    bound_port = sock.getsockname()[1]
    # lifespan on: the app's shutdown stops its search worker processes (see create_app).
    config = uvicorn.Config(app, log_level=log_level, lifespan="on")
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True, name="graphslam-http")
    thread.start()
    deadline = time.monotonic() + startup_timeout
    while not server.started:
        if not thread.is_alive() or time.monotonic() > deadline:
            server.should_exit = True
            raise GraphSlamError(f"HTTP server on {host}:{bound_port} did not start")
        time.sleep(0.01)
    return BackgroundServer(server, thread, host, bound_port)
