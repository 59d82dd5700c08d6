"""Request / response models of the HTTP service (pydantic; they define the OpenAPI schema).

``POST /v1/locate`` bodies are parsed by ``graphslam.service.parsing``, which accepts
exactly what ``LocateRequest`` accepts and falls back to it for every error message.
"""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, StringConstraints, model_validator

MAX_READINGS = 4096  # per fingerprint; real scans hear a few hundred APs at most
RSSI_MIN_DBM, RSSI_MAX_DBM = -200.0, 0.0

BSSID_MAX_CHARS = 128

Bssid = Annotated[str, StringConstraints(min_length=1, max_length=BSSID_MAX_CHARS)]
# strict: "-60" (a string) or true are refused; ints are accepted as numbers.
Rssi = Annotated[float, Field(strict=True, allow_inf_nan=False, ge=RSSI_MIN_DBM, le=RSSI_MAX_DBM)]


class Fingerprint(BaseModel):
    """One WiFi scan: BSSID -> RSS in dBm (APs not listed were not heard)."""

    model_config = ConfigDict(extra="forbid")
    readings: dict[Bssid, Rssi] = Field(min_length=1, max_length=MAX_READINGS)


class LocateRequest(BaseModel):
    """Either ``readings`` (one fingerprint) or ``fingerprints`` (a batch), not both."""

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "examples": [
                {"readings": {"00:11:22:33:44:55": -61, "00:11:22:33:44:66": -78.5}},
                {"fingerprints": [{"readings": {"00:11:22:33:44:55": -61}}, {"readings": {"aa:bb:cc:dd:ee:ff": -70}}]},
            ]
        },
    )
    readings: dict[Bssid, Rssi] | None = Field(default=None, min_length=1, max_length=MAX_READINGS)
    fingerprints: list[Fingerprint] | None = Field(default=None, min_length=1)

    @model_validator(mode="after")
    def _one_form(self) -> "LocateRequest":
        if (self.readings is None) == (self.fingerprints is None):
            raise ValueError("give exactly one of 'readings' (one fingerprint) or 'fingerprints' (a batch)")
        return self

    def scans(self) -> list[dict[str, float]]:
        if self.readings is not None:
            return [self.readings]
        assert self.fingerprints is not None
        return [f.readings for f in self.fingerprints]


class NotFound(BaseModel):
    """Why a fingerprint of a batch has no position (the geolocation APIs' ``notFound``)."""

    reason: str = Field(description="'notFound', as Google's and Mozilla's geolocation APIs say it")
    status: str = Field(description="'no_known_ap': none of its access points is in the map; 'no_candidate': no "
                        "fingerprint of the map shares min_common of them (locate's CSV says the same)")
    message: str


class Position(BaseModel):
    """One fingerprint's answer. In a batch, a fingerprint that cannot be located has null values
    and an ``error``; the others are answered as usual (a single ``readings`` query that cannot be
    located is a 404 instead)."""

    x: float | None = Field(description="metres, in the radio map's frame (the answer's 'frame')")
    y: float | None
    score: float | None = Field(
        description="mean fingerprint distance of the neighbours used (metric eq9: dB; sorensen: 0-1; see GET /v1/radio-map); lower = closer match"
    )
    spread: float | None = Field(description="weighted RMS distance (m) of the neighbours' positions to the estimate")
    sigma_m: float | None = Field(
        None, description="the answer's uncertainty: sigma (m) of an isotropic 2-D Gaussian, calibrated on the map "
        "(its walks left out one at a time); the 95 % circle has radius 2.448 sigma_m; at least the map's "
        "outside sigma when outside is true; null for a map of one walk",
    )
    outside: bool | None = Field(
        None, description="true when the fingerprint comes from a place the map's walks have not been: its readings "
        "differ from the neighbours' more than those of 95 % of the map's own scans where other walks have been "
        "(measured on the map, without ground truth); null without that measurement (a map of one walk) and for a "
        "fingerprint that cannot be located",
    )
    outside_score: float | None = Field(
        None, description="0-1: the share of the map's own covered scans whose readings matched their neighbours "
        "closer than this fingerprint's; outside is true above 0.95",
    )
    n_neighbours: int
    floor: str | None = None
    building: str | None = None
    error: NotFound | None = Field(None, description="only on a fingerprint that cannot be located")


class LocateResponse(BaseModel):
    frame: str = Field(description="the radio map's frame (its report.json's 'frame': aligned, earth or site)")
    k: int
    weighted: bool
    positions: list[Position]


class RadioMapInfo(BaseModel):
    format_version: int
    frame: str
    n_fingerprints: int
    n_access_points: int
    n_sessions: int
    mean_aps_per_fingerprint: float
    bbox: dict[str, float] | None
    floors: dict[str, int] | None
    buildings: dict[str, int] | None
    missing_dbm: float
    min_rssi_dbm: float
    t_ns_range: list[int] | None
    metadata: dict[str, Any]
    k: int
    weighted: bool
    min_common: int
    index: str = Field(description="kNN search in use: 'exact' or 'ivf' (approximate inverted file)")
    metric: str = Field(description="fingerprint distance: 'eq9' (the paper's, dB) or 'sorensen' (powed RSS, 0-1)")


class Health(BaseModel):
    status: str
