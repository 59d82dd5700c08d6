"""``graphslam serve``'s settings as one object (the command's options are its fields). Each default
is written here once; the service's modules take theirs from here."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field, ValidationError

from graphslam.config import _Strict, problems
from graphslam.errors import ConfigError
from graphslam.names import DEFAULT_INDEX, DEFAULT_K, DEFAULT_METRIC, LOG_LEVELS  # noqa: F401 (LOG_LEVELS: API)

DEFAULT_HOST = "127.0.0.1"  # loopback unless the operator says otherwise
DEFAULT_PORT = 8077
DEFAULT_MAX_BATCH = 10_000
DEFAULT_MAX_BODY_BYTES = 32 * 1024 * 1024
DEFAULT_WATCH_S = 1.0  # serve --watch without --watch-interval


class ServeConfig(_Strict):
    """How the HTTP service serves one radio map. Invalid values are ``ConfigError``."""

    host: str = Field(DEFAULT_HOST, description="bind address (loopback by default)")
    port: int = Field(DEFAULT_PORT, ge=0, le=65535, description="TCP port")
    k: int = Field(DEFAULT_K, ge=1, description="neighbours")
    weighted: bool = Field(True, description="inverse-distance weights, else uniform")
    min_common: int = Field(1, ge=1, description="neighbours must share this many APs")
    metric: Literal["sorensen", "eq9"] = Field(DEFAULT_METRIC, description="fingerprint distance")
    max_batch: int = Field(DEFAULT_MAX_BATCH, ge=1, description="most fingerprints per request")
    max_body_bytes: int = Field(DEFAULT_MAX_BODY_BYTES, ge=1024, description="largest request body")
    index: Literal["auto", "exact", "ivf"] = Field(DEFAULT_INDEX, description="kNN search; auto: IVF from 5,000 references")
    ivf_clusters: int | None = Field(None, ge=1, description="IVF: k-means clusters (null: ~2 sqrt(N))")
    ivf_probes: int | None = Field(None, ge=1, description="IVF: clusters searched per query (null: 8)")
    workers: int = Field(1, ge=1, description="server processes (each loads the map)")
    search_processes: int | None = Field(
        None, ge=0, description="forked search workers sharing the map (null: min(2, cores), 0 with workers > 1)"
    )
    log_level: Literal["critical", "error", "warning", "info", "debug", "trace"] = Field(
        "info", description="uvicorn's; info logs one access line per request"
    )
    token: str | None = Field(None, description="bearer token required on /v1/ (null: none)")
    watch_s: float | None = Field(None, ge=0.05, description="reload the map when its file changes, checked this often (null: SIGHUP only)")

    def __init__(self, **data: Any) -> None:
        try:
            super().__init__(**data)
        except ValidationError as e:
            raise ConfigError(f"serve: {problems(e)}") from None

    def app_options(self) -> dict[str, Any]:
        """The options ``service.app.create_app`` takes (``search_processes`` as given: resolved by ``serve``)."""
        return dict(k=self.k, weighted=self.weighted, min_common=self.min_common, max_batch=self.max_batch,
                    max_body_bytes=self.max_body_bytes, index=self.index, ivf_clusters=self.ivf_clusters,
                    ivf_probes=self.ivf_probes, token=self.token or None, metric=self.metric)
