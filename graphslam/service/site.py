"""A building served whole: ``graphslam serve --radio-map SITE_DIR``, one radio map per floor.

``SITE_DIR`` is a folder of survey outputs, as ``graphslam survey-batch --out`` writes them:
every folder under it (itself included, hidden ones skipped: they are a survey's stages) that
holds ``radio_map.parquet`` is one floor, named by its path relative to ``SITE_DIR``
(``summary.json``'s ``floor``; the folder's own name when ``SITE_DIR`` itself is the floor).

Every floor is served by its own service app (``create_app``: locator, uncertainty, search
pool) behind its own ``ReloadingApp``: a floor whose file changes (``--watch``) or every floor
(SIGHUP) is reloaded and swapped atomically as a single map is, a broken one refused while the
others go on. A query is located on every floor and answered by the floor whose kNN answer has
the lowest score over all the query's access points (``KnnLocator.scores_over_query``: a
floor's own Sørensen score ignores the access points it does not know). The
position is in that floor's frame (each survey has its own): ``floor`` and ``frame`` say which.
``floor_scores`` gives those scores (null where the floor could not locate the query). ``GET /v1/maps/{floor}/heatmap/{bssid}.png``: one access point's heatmap on one
floor (the single map's ``/v1/heatmap/{bssid}.png``; 404 for an unknown floor or access point).
A fingerprint that no floor can locate (none of its access points is known to any floor) is
answered as a single map answers it: a 404 (``notFound``) for a single fingerprint, null values and
an ``error`` in a batch (the others answered).
"""

from __future__ import annotations

import asyncio
import logging
import math
import signal
import threading
from contextlib import ExitStack, asynccontextmanager
from pathlib import Path
from typing import Any, AsyncIterator, Callable

import numpy as np
import orjson
from fastapi import FastAPI, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi_offline import FastAPIOffline
from pydantic import BaseModel, Field

from graphslam.errors import InputError
from graphslam.io.paths import walk_folders
from graphslam.service.app import (
    HEATMAP_RESPONSES,
    INLINE_MAX,
    LOCATE_REQUEST_BODY,
    PARSE_INLINE_MAX_BYTES,
    BearerToken,
    BodyLimit,
    _problem,
    not_found_response,
    with_problem_handlers,
    with_request_model,
)
from graphslam.service.config import DEFAULT_MAX_BATCH, DEFAULT_MAX_BODY_BYTES
from graphslam.service.models import Position, RadioMapInfo
from graphslam.service.parsing import validated_request
from graphslam.service.reload import ReloadingApp
from graphslam.service.render import not_found, position_dicts, unlocated

log = logging.getLogger(__name__)

FLOOR_MAP_FILE = "radio_map.parquet"  # a survey's radio map (graphslam.app.survey's output set)


class SitePosition(Position):
    frame: str | None = Field(description="the answering floor's frame: x, y are in it (null: not located)")
    floor_scores: dict[str, float | None] = Field(
        description="every floor's kNN score over all of this fingerprint's access points, the lowest answers "
        "(null: the floor could not locate it)"
    )


class SiteLocateResponse(BaseModel):
    site: str
    k: int
    weighted: bool
    positions: list[SitePosition]


class FloorInfo(RadioMapInfo):
    name: str
    path: str
    generation: int = Field(description="reloads of this floor's map since the start")


class SiteInfo(BaseModel):
    site: str
    floors: list[FloorInfo]


def is_site(path: str | Path) -> bool:
    """Whether ``serve`` is given a site (a folder), not one radio map file."""
    return Path(path).is_dir()


def find_floor_maps(site: str | Path) -> dict[str, Path]:
    """Floor name -> its ``radio_map.parquet``, sorted by name; ``InputError`` when there is none."""
    root = Path(site)
    if not root.is_dir():
        raise InputError(root, "not a folder (expected a site: one folder per floor, each holding radio_map.parquet)")
    floors: dict[str, Path] = {}
    found = []
    for here, dirs, files in walk_folders(root):  # linked floor folders too, each once
        dirs[:] = [d for d in dirs if not d.startswith(".")]  # a survey's stage or old set (graphslam.io.atomic.FolderStage)
        if FLOOR_MAP_FILE in files and (here / FLOOR_MAP_FILE).is_file():
            found.append(here / FLOOR_MAP_FILE)
    for f in sorted(found):
        rel = f.parent.relative_to(root)
        name = rel.as_posix() if rel.parts else root.resolve().name
        if name in floors:  # the folder's own map and a sub-folder of its name
            raise InputError(f, f"a second floor named {name!r} (rename one of the two folders)")
        floors[name] = f
    if not floors:
        raise InputError(root, f"no floor folder under it holds {FLOOR_MAP_FILE} (expected survey-batch --out's layout)")
    return dict(sorted(floors.items()))


def _choose(scores: np.ndarray) -> np.ndarray:
    """Per row of the (floors, rows) score matrix (NaN where a floor did not locate the row): the
    index of the floor with the lowest score (-1: none located it)."""
    located = np.isfinite(scores).any(axis=0)
    return np.where(located, np.argmin(np.where(np.isfinite(scores), scores, np.inf), axis=0), -1)


def create_site_app(
    floors: dict[str, ReloadingApp],
    *,
    site: str,
    k: int = 3,
    weighted: bool = True,
    min_common: int = 1,
    max_batch: int = DEFAULT_MAX_BATCH,
    max_body_bytes: int = DEFAULT_MAX_BODY_BYTES,
    token: str | None = None,
    sighup: bool = True,
) -> FastAPI:
    """The service of a site: ``floors`` (name -> that floor's reloading service app, made with
    ``sighup=False``) behind one ``POST /v1/locate`` / ``GET /v1/radio-map``. Its lifespan starts
    and stops the floors' reloaders; ``sighup``: SIGHUP reloads every floor (main thread only)."""
    names = list(floors)
    reloaders = [floors[n] for n in names]

    @asynccontextmanager
    async def lifespan(_: FastAPI) -> AsyncIterator[None]:
        for r in reloaders:
            r.start()
        main = sighup and threading.current_thread() is threading.main_thread()
        loop = asyncio.get_running_loop()
        if main:
            loop.add_signal_handler(signal.SIGHUP, lambda: [r.reload_now() for r in reloaders])
        try:
            yield
        finally:
            if main:
                loop.remove_signal_handler(signal.SIGHUP)
            for r in reloaders:
                r.stop()

    app = FastAPIOffline(
        title="graphslam site service",
        version="1",
        summary="kNN WiFi fingerprint positioning against one radio map per floor: floor and position",
        lifespan=lifespan,
    )
    app.state.floors = floors

    with_problem_handlers(app)

    @app.get("/v1/radio-map", response_model=SiteInfo)
    def site_info() -> dict[str, Any]:
        out = []
        for name, r in zip(names, reloaders):
            locator = r.current.state.locator
            info = {**locator.radio_map.summary().as_dict(), "k": k, "weighted": weighted, "min_common": min_common,
                    "index": locator.index_kind, "metric": locator.config.metric}
            out.append({**info, "name": name, "path": str(r.path), "generation": r.generation})
        return {"site": site, "floors": out}

    @app.get("/v1/maps/{floor:path}/heatmap/{bssid}.png", response_class=Response, responses=HEATMAP_RESPONSES)
    async def floor_heatmap(floor: str, bssid: str) -> Response:
        r = floors.get(floor)
        if r is None:
            return _problem(404, f"no floor {floor!r} in site {site} (floors: {', '.join(names)})")
        with r.hold() as current:  # this floor's map, cached per map generation
            return await current.state.heatmaps.response(bssid, f"floor {floor!r}")

    def answer(apps: list[FastAPI], scans: list[Any], single: bool) -> Response:
        results = [a.state.search_pool.locate(scans) for a in apps]
        # over every AP of the query: a floor's own score ignores the APs it does not know
        scores = np.vstack([a.state.locator.scores_over_query(scans, r) for r, a in zip(results, apps)])
        best = _choose(scores)
        rows = [position_dicts(r, a.state.locator.uncertainty) for r, a in zip(results, apps)]
        frames = [a.state.locator.radio_map.frame for a in apps]
        statuses = [r.status for r in results]
        positions = []
        for i, f in enumerate(best.tolist()):
            if f < 0:  # no floor located it: no position, and why
                unknown = all(st[i] == "no_known_ap" for st in statuses)
                error = not_found("no_known_ap" if unknown else "no_candidate", min_common, "any floor's radio map")
                if single:
                    return not_found_response(error)
                p = unlocated(error) | {"frame": None}
            else:
                p = rows[f][i] | {"floor": names[f], "frame": frames[f]}
            p["floor_scores"] = {n: (None if math.isnan(s) else s) for n, s in zip(names, scores[:, i].tolist())}
            positions.append(p)
        return Response(orjson.dumps({"site": site, "k": k, "weighted": weighted, "positions": positions}),
                        media_type="application/json")

    @app.post(
        "/v1/locate",
        response_model=SiteLocateResponse,
        responses={
            413: {"description": "body or batch too large"},
            404: {"description": "a single fingerprint ('readings') no floor can locate: reason 'notFound' (in a "
                  "batch, such a fingerprint gets null values and an 'error' instead)"},
            422: {"description": "malformed request"},
            503: {"description": "a search worker process died while answering (retry)"},
        },
        openapi_extra=LOCATE_REQUEST_BODY,
    )
    async def locate(request: Request) -> Any:
        body = await request.body()
        content_type = request.headers.get("content-type")
        if len(body) > PARSE_INLINE_MAX_BYTES:
            scans, single = await run_in_threadpool(validated_request, body, content_type)
        else:
            scans, single = validated_request(body, content_type)
        if len(scans) > max_batch:
            return _problem(413, f"batch of {len(scans)} fingerprints, at most {max_batch} per request")
        with ExitStack() as held:  # every floor's current app, kept open until answered
            apps = [held.enter_context(r.hold()) for r in reloaders]
            if len(scans) <= INLINE_MAX:
                return answer(apps, scans, single)
            return await run_in_threadpool(answer, apps, scans, single)

    with_request_model(app, token)
    app.add_middleware(BodyLimit, max_bytes=max_body_bytes)
    if token:
        app.add_middleware(BearerToken, token=token)
    return app


def site_app(
    site: str | Path, build_floor: Callable[[Path], FastAPI], watch: float | None, **app_kwargs: Any
) -> FastAPI:
    """``create_site_app`` over every floor of ``site``; ``build_floor(path)``: a floor's service app.
    A floor that does not load is an error naming its file (the others' search pools are closed)."""
    maps = find_floor_maps(site)
    floors: dict[str, ReloadingApp] = {}
    one_at_a_time = threading.Lock()  # reloads (SIGHUP: every floor) build one floor after another

    def rebuild(path: Path) -> FastAPI:
        with one_at_a_time:  # peak memory: the served floors plus one new one
            return build_floor(path)

    try:
        for name, path in maps.items():
            floors[name] = ReloadingApp(build_floor(path), lambda p=path: rebuild(p), path,
                                        watch_interval=watch, sighup=False)
    except BaseException:
        for r in floors.values():
            r.current.state.search_pool.close()
        raise
    site_kwargs = {k: app_kwargs[k] for k in ("k", "weighted", "min_common", "max_batch", "max_body_bytes", "token")
                   if k in app_kwargs}
    return create_site_app(floors, site=Path(site).resolve().name, **site_kwargs)
