"""HTTP query service: kNN positioning against one radio map (FastAPI).

Endpoints (OpenAPI at ``/openapi.json``, docs at ``/docs``):

- ``POST /v1/locate``: one fingerprint ``{"readings": {bssid: dBm}}`` or a batch
  ``{"fingerprints": [{"readings": {...}}, ...]}`` -> ``{"frame": ..., "positions": [...]}``,
  one position per fingerprint, in order. As the geolocation APIs users know (Google's,
  Mozilla's) answer a query no position is found for: a single fingerprint that cannot be located
  (no access point known to the map) is a 404 with ``reason`` ``notFound``; in a batch such a
  fingerprint gets null values and an ``error`` (``reason`` ``notFound``, ``status``,
  ``message``) and the others their answers;
- ``GET /v1/radio-map``: summary of the loaded map;
- ``GET /v1/heatmap/{bssid}.png``: one access point's RSS heatmap over the map, cells faded where
  the standard error of the mean exceeds ``graphslam.io.heatmap.MAX_STD_ERROR_DB``
  (``graphslam.io.heatmap.heatmap_png``: its tEXt chunks say where it lies); 404 for an access
  point the map does not know. Rendered once per access point and map (a reload builds a new app,
  with an empty cache; at most ``HEATMAP_CACHE`` kept);
- ``GET /healthz``: liveness.

``/docs`` (Swagger UI) and ``/redoc`` are served from assets packaged with
``fastapi-offline`` (no CDN: they render on a site without internet). With a ``token``,
every ``/v1/`` request needs ``Authorization: Bearer <token>`` (401 otherwise);
``/healthz``, ``/openapi.json`` and the docs stay open (they say nothing about the map).

Every bad request is a 4xx with a ``detail`` message: malformed JSON (also: nested deeper
than ``parsing.MAX_JSON_DEPTH``), wrong types,
NaN/inf, RSS outside [-200, 0] dBm, empty readings, an empty or too large batch
(413), a too large body (413). The whole batch is refused if any fingerprint is malformed, so
positions always line up with the request. 503 if a search worker process (see
``graphslam.service.pool``) died while answering: retry.
"""

from __future__ import annotations

import hmac
import logging
import threading
from contextlib import asynccontextmanager
from typing import Any, AsyncIterator, Awaitable, Callable, MutableMapping

import orjson
from fastapi import FastAPI, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from fastapi_offline import FastAPIOffline

from graphslam.core.radiomap.knn import IndexKind, KnnConfig, KnnLocator, KnnResult
from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.errors import QueryError
from graphslam.io.heatmap import radio_map_heatmap_png
from graphslam.names import DEFAULT_INDEX, DEFAULT_METRIC
from graphslam.service.config import DEFAULT_MAX_BATCH, DEFAULT_MAX_BODY_BYTES
from graphslam.service.models import (  # re-exported: the service's public models
    BSSID_MAX_CHARS,
    MAX_READINGS,
    RSSI_MAX_DBM,
    RSSI_MIN_DBM,
    Fingerprint,
    Health,
    LocateRequest,
    LocateResponse,
    Position,
    RadioMapInfo,
)
from graphslam.service.coalesce import Coalescer
from graphslam.service.parsing import flat_scans, is_json_content_type, validated_request
from graphslam.service.pool import BatchTooLargeError, SearchPool, SearchUnavailableError
from graphslam.core.radiomap.uncertainty import map_uncertainty
from graphslam.service.render import not_found, position_dicts, response_json

log = logging.getLogger(__name__)

INLINE_MAX = 8  # batches up to this size are answered on the event loop (see locate())
PARSE_INLINE_MAX_BYTES = 64 * 1024  # bigger bodies (~100+ fingerprints) are parsed off the event loop
# With search processes, bodies from this size (~50+ fingerprints) are parsed and searched on them.
POOL_MIN_BODY_BYTES = 16 * 1024
HEATMAP_CACHE = 64  # heatmap PNGs kept per map (~10-100 kB each), the oldest dropped first
HEATMAP_RESPONSES: dict[int | str, dict[str, Any]] = {
    200: {"content": {"image/png": {}}, "description": "the access point's heatmap (PNG)"},
    404: {"description": "an access point the radio map does not know"},
}
__all__ = [
    "BSSID_MAX_CHARS", "MAX_READINGS", "RSSI_MAX_DBM", "RSSI_MIN_DBM", "Fingerprint", "Health",
    "LocateRequest", "LocateResponse", "Position", "RadioMapInfo", "create_app",
]


def _problem(status: int, detail: str, **extra: Any) -> JSONResponse:
    return JSONResponse({"detail": detail, **extra}, status_code=status)


def not_found_response(error: dict[str, str]) -> JSONResponse:
    """404 for a single fingerprint no position is found for (the geolocation APIs' ``notFound``)."""
    return JSONResponse({"detail": f"the fingerprint cannot be located: {error['message']}", **error}, status_code=404)


class HeatmapCache:
    """The heatmap PNGs of one radio map, rendered on first request (``radio_map_heatmap_png``)."""

    def __init__(self, radio_map: RadioMap, size: int = HEATMAP_CACHE) -> None:
        self.radio_map, self.size = radio_map, size
        self.known = frozenset(radio_map.bssids)
        self._pngs: dict[str, bytes] = {}
        self._lock = threading.Lock()

    def png(self, bssid: str) -> bytes | None:
        """``bssid``'s heatmap PNG; None for an access point the map does not know."""
        if bssid not in self.known:
            return None
        with self._lock:
            got = self._pngs.get(bssid)
        if got is None:
            got = radio_map_heatmap_png(self.radio_map, bssid)
            with self._lock:
                self._pngs[bssid] = got
                while len(self._pngs) > self.size:
                    self._pngs.pop(next(iter(self._pngs)))
        return got

    async def response(self, bssid: str, where: str = "the radio map") -> Response:
        """The route's answer: the PNG, or 404 with a problem JSON."""
        data = await run_in_threadpool(self.png, bssid)
        if data is None:
            return _problem(404, f"access point {bssid!r} is not in {where} (no fingerprint heard it)")
        return Response(data, media_type="image/png")


class BodyLimit:
    """ASGI middleware: refuse bodies above ``max_bytes`` (declared or streamed) with 413,
    before anything is parsed."""

    def __init__(self, app: Callable[..., Awaitable[None]], max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: MutableMapping[str, Any], receive: Callable, send: Callable) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        too_big = _problem(413, f"request body larger than {self.max_bytes} bytes")
        for name, value in scope.get("headers", []):
            if name == b"content-length":
                try:
                    declared = int(value)
                except ValueError:
                    await _problem(400, "invalid Content-Length header")(scope, receive, send)
                    return
                if declared > self.max_bytes:
                    await too_big(scope, receive, send)
                    return
        # Read the whole body here (FastAPI would anyway), counting: a chunked body has no
        # Content-Length to check, and an exception raised inside receive() would turn into a 400.
        chunks: list[bytes] = []
        seen = 0
        while True:
            message = await receive()
            if message["type"] == "http.disconnect":
                return
            body = message.get("body", b"")
            seen += len(body)
            if seen > self.max_bytes:
                await too_big(scope, receive, send)
                return
            chunks.append(body)
            if not message.get("more_body", False):
                break
        replay = [{"type": "http.request", "body": b"".join(chunks), "more_body": False}]

        async def buffered_receive() -> MutableMapping[str, Any]:
            if replay:
                return replay.pop()
            return await receive()

        await self.app(scope, buffered_receive, send)


class BearerToken:
    """ASGI middleware: ``/v1/`` requests need ``Authorization: Bearer <token>`` (compared in
    constant time), else 401 before the body is read."""

    def __init__(self, app: Callable[..., Awaitable[None]], token: str) -> None:
        self.app = app
        self.expected = f"Bearer {token}".encode()

    async def __call__(self, scope: MutableMapping[str, Any], receive: Callable, send: Callable) -> None:
        if scope["type"] == "http" and scope.get("path", "").startswith("/v1/"):
            got = next((v for k, v in scope.get("headers", []) if k == b"authorization"), b"")
            if not hmac.compare_digest(got, self.expected):
                detail = "missing or wrong bearer token (Authorization: Bearer <token>)"
                r = JSONResponse({"detail": detail}, status_code=401, headers={"WWW-Authenticate": "Bearer"})
                await r(scope, receive, send)
                return
        await self.app(scope, receive, send)


class SmallLocateFastPath:
    """ASGI middleware: a ``POST /v1/locate`` of at most ``INLINE_MAX`` fingerprints that the fast
    parser accepts and that locates in full is answered here, without FastAPI's routing and
    dependency machinery (~100 us of a ~350 us request). Everything else -- another route,
    another content type, a body the fast parser declines, a single fingerprint that cannot be
    located (a 404) -- goes to the app unchanged (with the body replayed), which answers exactly as
    it always does."""

    def __init__(self, app: Callable[..., Awaitable[None]], answer: Callable[[bytes], Awaitable[bytes | None]]) -> None:
        self.app, self.answer = app, answer

    async def __call__(self, scope: MutableMapping[str, Any], receive: Callable, send: Callable) -> None:
        if not (scope["type"] == "http" and scope["method"] == "POST" and scope["path"] == "/v1/locate"):
            await self.app(scope, receive, send)
            return
        content_type = next((v for k, v in scope.get("headers", []) if k == b"content-type"), b"")
        if not is_json_content_type(content_type.decode("latin-1")):
            await self.app(scope, receive, send)
            return
        message = await receive()  # BodyLimit (outside) hands the whole body in one message
        body = message.get("body", b"") if message["type"] == "http.request" else b""
        done = None
        if message["type"] == "http.request" and not message.get("more_body"):
            done = await self.answer(body)
        if done is None:
            replay = [message]

            async def replayed() -> MutableMapping[str, Any]:
                return replay.pop() if replay else await receive()

            await self.app(scope, replayed, send)
            return
        headers = [(b"content-length", str(len(done)).encode()), (b"content-type", b"application/json")]
        await send({"type": "http.response.start", "status": 200, "headers": headers})
        await send({"type": "http.response.body", "body": done})


def _validation_message(exc: RequestValidationError) -> tuple[str, list[dict[str, Any]]]:
    errors = []
    for e in exc.errors():
        loc = [str(p) for p in e.get("loc", ()) if p != "body"]
        errors.append({"loc": loc, "msg": e.get("msg", ""), "type": e.get("type", "")})
    bad_json = [e for e in errors if e["type"] == "json_invalid"]
    if bad_json:
        at = next((e["loc"][0] for e in bad_json if e["loc"]), None)
        why = next((e["msg"] for e in bad_json if e["msg"] != "JSON decode error"), None)  # e.g. too deep
        return "malformed JSON body" + (f" (at character {at})" if at is not None else "") + (
            f": {why}" if why else ""), errors
    parts = [f"{'.'.join(e['loc']) or 'body'}: {e['msg']}" for e in errors[:5]]
    more = f" (+{len(errors) - 5} more)" if len(errors) > 5 else ""
    return "invalid request: " + "; ".join(parts) + more, errors


# POST /v1/locate's body in OpenAPI (see with_request_model)
LOCATE_REQUEST_BODY = {
    "requestBody": {
        "required": True,
        "content": {"application/json": {"schema": {"$ref": "#/components/schemas/LocateRequest"}}},
    }
}


def with_request_model(app: FastAPI, token: str | None) -> None:
    """``app``'s OpenAPI description with ``LocateRequest`` as ``POST /v1/locate``'s body (the route
    reads its body itself, so FastAPI does not see it) and, with a ``token``, the bearer scheme."""
    default_openapi = app.openapi

    def openapi_with_request_model() -> dict[str, Any]:
        # /v1/locate reads its body itself (fast path), so FastAPI does not see LocateRequest:
        # add it (and its nested models) to the components the route's requestBody refers to.
        if app.openapi_schema:
            return app.openapi_schema
        schema = default_openapi()
        comps = schema.setdefault("components", {}).setdefault("schemas", {})
        req = LocateRequest.model_json_schema(ref_template="#/components/schemas/{model}")
        for name, definition in req.pop("$defs", {}).items():
            comps.setdefault(name, definition)
        comps["LocateRequest"] = req
        if token:  # Swagger UI's "Authorize" button, and the requirement on /v1/ operations
            schema["components"].setdefault("securitySchemes", {})["bearer"] = {"type": "http", "scheme": "bearer"}
            for path, ops in schema.get("paths", {}).items():
                if path.startswith("/v1/"):
                    for op in ops.values():
                        op["security"] = [{"bearer": []}]
        return schema

    app.openapi = openapi_with_request_model  # type: ignore[method-assign]


def with_problem_handlers(app: FastAPI) -> None:
    """The errors every graphslam service answers as problem JSON (invalid request, unlocatable
    query: 422; a search worker lost: 503), and ``GET /healthz``."""

    @app.exception_handler(RequestValidationError)
    async def _on_invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        detail, errors = _validation_message(exc)
        return _problem(422, detail, errors=errors)

    @app.exception_handler(QueryError)
    async def _on_query_error(request: Request, exc: QueryError) -> JSONResponse:
        return _problem(422, str(exc))

    @app.exception_handler(SearchUnavailableError)
    async def _on_search_unavailable(request: Request, exc: SearchUnavailableError) -> JSONResponse:
        return _problem(503, str(exc))

    @app.get("/healthz", response_model=Health)
    def healthz() -> dict[str, str]:
        return {"status": "ok"}


def create_app(
    radio_map: RadioMap,
    *,
    k: int = 3,
    weighted: bool = True,
    min_common: int = 1,
    max_batch: int = DEFAULT_MAX_BATCH,
    max_body_bytes: int = DEFAULT_MAX_BODY_BYTES,
    threads: int | None = None,
    index: IndexKind = DEFAULT_INDEX,  # type: ignore[assignment]
    ivf_clusters: int | None = None,
    ivf_probes: int | None = None,
    search_processes: int = 0,
    token: str | None = None,
    metric: str = DEFAULT_METRIC,
) -> FastAPI:
    """The service for ``radio_map``. ``threads``: search threads per large request (default:
    up to 2, the machine's cores; small requests use one). ``index``: kNN search (see
    ``KnnConfig``); ``"auto"`` uses the approximate IVF index on maps of
    ``IVF_AUTO_MIN_REFS`` references or more, exact search below. ``search_processes``: forked
    search workers for large batches (``graphslam.service.pool``; 0 = search in this process).
    The workers are started here and stopped at the app's lifespan shutdown (or by
    ``app.state.search_pool.close()``), so an app with workers is served once. ``token``:
    bearer token required on ``/v1/`` (None: no authentication). ``metric``: ``KnnConfig.metric``."""
    ivf = {"ivf_clusters": ivf_clusters} | ({"ivf_probes": ivf_probes} if ivf_probes is not None else {})
    config = KnnConfig(k=k, weighted=weighted, min_common=min_common, index=index, metric=metric, **ivf)  # type: ignore[arg-type]
    locator = KnnLocator(radio_map, config, threads=threads)
    # every answer's sigma_m: the calibration the map records for this kNN, else measured now
    locator.uncertainty = map_uncertainty(radio_map, config)
    # After the locator: the workers fork a complete copy of it (copy-on-write).
    pool = SearchPool(locator, search_processes)
    summary = radio_map.summary().as_dict()
    head = {"frame": radio_map.frame, "k": k, "weighted": weighted}  # every answer's fields but "positions"

    @asynccontextmanager
    async def lifespan(_: FastAPI) -> AsyncIterator[None]:
        try:
            yield
        finally:
            pool.close()

    app = FastAPIOffline(  # a FastAPI app whose /docs and /redoc use packaged assets, not a CDN
        title="graphslam radio map service",
        version="1",
        summary="kNN WiFi fingerprint positioning (Sørensen or eq. 9 RSS distance) against one radio map",
        lifespan=lifespan,
    )
    app.state.locator = locator
    app.state.search_pool = pool
    # Concurrent small requests share one search (service/coalesce.py); unlocatable rows are
    # checked per request below.
    coalescer = Coalescer(lambda scans: locator.locate(scans))
    with_request_model(app, token)

    with_problem_handlers(app)

    @app.get("/v1/radio-map", response_model=RadioMapInfo)
    def radio_map_info() -> dict[str, Any]:
        return {**summary, "k": k, "weighted": weighted, "min_common": min_common, "index": locator.index_kind,
                "metric": config.metric}

    heatmaps = HeatmapCache(radio_map)
    app.state.heatmaps = heatmaps

    @app.get("/v1/heatmap/{bssid}.png", response_class=Response, responses=HEATMAP_RESPONSES)
    async def heatmap(bssid: str) -> Response:
        return await heatmaps.response(bssid)

    def answer(scans: list[Any], single: bool) -> Response:
        return respond(pool.locate(scans), single)

    def answer_body(body: bytes) -> Response | None:
        # Parsed, searched and rendered on the search processes; None: not for the fast path (or no pool).
        got = pool.locate_body_json(body, max_batch=max_batch)
        if got is None or (len(got[0]) == 1 and not got[0].valid.all()):
            return None  # one fingerprint not located: the route tells a 404 (one fingerprint) from a batch of one
        return Response(response_json(head, got[1]), media_type="application/json")

    async def answer_small(body: bytes) -> bytes | None:
        # The fast path's answer: the JSON the route would send, or None (the route decides).
        if len(body) >= (POOL_MIN_BODY_BYTES if pool.processes else PARSE_INLINE_MAX_BYTES):
            return None  # the route's pool / thread-pool paths
        flat = flat_scans(body)
        if flat is None or len(flat) > min(INLINE_MAX, max_batch):
            return None
        res = await coalescer.locate(flat.scans)
        if flat.single and not res.valid.all():
            return None  # the route answers the 404
        return orjson.dumps({**head, "positions": position_dicts(res, locator.uncertainty)})

    def respond(res: KnnResult, single: bool) -> Response:
        # Serialised here (the shape is LocateResponse, documented in OpenAPI): FastAPI's
        # response-model validation would add a second pass over every position. A row not
        # located is rendered with explicit nulls (position_dicts), so orjson's NaN -> null never applies.
        if single and not res.valid.all():
            return not_found_response(not_found(str(res.status[0]), min_common))
        return Response(orjson.dumps({**head, "positions": position_dicts(res, locator.uncertainty)}), media_type="application/json")

    @app.post(
        "/v1/locate",
        response_model=LocateResponse,
        responses={
            413: {"description": "body or batch too large"},
            404: {"description": "a single fingerprint ('readings') that cannot be located: reason 'notFound' "
                  "(in a batch, such a fingerprint gets null values and an 'error' instead)"},
            422: {"description": "malformed request"},
            503: {"description": "a search worker process died while answering (retry)"},
        },
        openapi_extra=LOCATE_REQUEST_BODY,
    )
    async def locate(request: Request) -> Any:
        # Parsed here, not by FastAPI: orjson + a vectorised check, with LocateRequest's exact
        # semantics and messages (graphslam.service.parsing); ~10x cheaper on big batches.
        body = await request.body()
        content_type = request.headers.get("content-type")
        if pool.processes and len(body) >= POOL_MIN_BODY_BYTES and is_json_content_type(content_type):
            try:
                done = await run_in_threadpool(answer_body, body)
            except BatchTooLargeError as e:
                return _problem(413, str(e))
            if done is not None:
                return done
        if len(body) > PARSE_INLINE_MAX_BYTES:
            scans, single = await run_in_threadpool(validated_request, body, content_type)
        else:
            scans, single = validated_request(body, content_type)
        if len(scans) > max_batch:
            return _problem(413, f"batch of {len(scans)} fingerprints, at most {max_batch} per request")
        if len(scans) <= INLINE_MAX:  # ~0.5 ms of search: on the event loop, shared with concurrent requests
            return respond(await coalescer.locate(scans), single)
        return await run_in_threadpool(answer, scans, single)  # big batches must not block the event loop

    # Middleware added later runs first: BearerToken (before the body is read), BodyLimit, then
    # the small-request fast path.
    app.add_middleware(SmallLocateFastPath, answer=answer_small)
    app.add_middleware(BodyLimit, max_bytes=max_body_bytes)
    if token:
        app.add_middleware(BearerToken, token=token)
    return app
