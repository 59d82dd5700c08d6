"""Typed tracking configuration (``graphslam track``), mirrored by ``configs/track.yaml``.

As the survey's (``graphslam.config``): sections of strict models, unknown keys and invalid
values are ``ConfigError``, a partial file is merged over the defaults, ``--set section.key=value``
overrides one value, and the effective configuration is written beside every run's output.
Each default is written here once: the core's fixed-lag and particle-filter settings take theirs
from ``DEFAULTS`` (``graphslam.core.tracking``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import Field, ValidationError, model_validator

from graphslam.config import _Strict, commented_yaml, load_model, problems, validated
from graphslam.errors import ConfigError

from graphslam.names import BANK_REPORTS, DEFAULT_METRIC, METRICS, SMOOTHERS, TRACKERS, WALKABLE_MODES  # noqa: F401


class _Section(_Strict):
    pass


class FilterSection(_Section):
    """Which tracker: the online fixed-lag MAP, the causal EKF / UKF or the particle filter; offline smoothers."""

    kind: Literal["fixed-lag", "ekf", "ukf", "particle"] = Field(
        "fixed-lag", description="fixed-lag: online, each step reported fixed_lag.lag_s late; ekf / ukf: causal; "
        "particle: map-matching particle filter, fixed_lag.lag_s late (docs/tracking.md)",
    )
    smoother: Literal["none", "rts", "map"] = Field(
        "none", description="offline, the whole session known: rts or map (whole-run MAP) over the most probable "
        "heading hypothesis; none: the online tracker",
    )
    gate_sigma: float = Field(
        3.0, gt=0, description="readings beyond this many innovation std are gated (the MAP problems: Huber loss at it)"
    )
    ukf_w0: float = Field(0.1, description="UKF weight of the central sigma point (Paper 002's value)")


class FixedLagSection(_Section):
    """The fixed-lag smoother (filter.kind fixed-lag) and its bank of heading hypotheses."""

    lag_s: float = Field(2.0, ge=0, description="a step is reported once the data up to lag_s later are in (also the particle filter's)")
    window_s: float = Field(20.0, ge=0, description="older epochs are marginalised into a prior")
    prune_cost: float | None = Field(50.0, gt=0, description="heading hypotheses this far above the best are dropped (null: keep all)")
    merge_tol: float | None = Field(
        0.05, gt=0, description="heading hypotheses whose window states agree to this in every entry (m, m/s, rad) become one, "
        "their odds kept (null: never)",
    )
    bank_temper: float | None = Field(
        None, ge=1, description="the bank's costs are divided by this in its weights and pruning; null: measured on the "
        "map by self-calibration (its fixes' error correlation along a walk), 1 without it",
    )
    bank_report: Literal["mixture", "best"] = Field(
        "mixture", description="mixture: the heading hypotheses' posterior mixture; best: the most probable one only"
    )
    calibrate_covariance: bool = Field(True, description="covariances also scaled by the walk's own fix-innovation variance factor")


class MotionSection(_Section):
    """Walking people: step-velocity noise, process noise per second, the start's uncertainty, heading hypotheses."""

    velocity_sigma_mps: float = Field(0.15, gt=0, description="step-velocity noise per axis")
    q_position: float = Field(0.01, ge=0, description="m^2/s")
    q_velocity: float = Field(1.0, ge=0, description="(m/s)^2/s: walkers turn and stop")
    q_bias: float = Field(1e-6, ge=0, description="(m/s)^2/s")
    q_theta: float = Field(1e-4, ge=0, description="rad^2/s: foot-module heading drift")
    init_position_sigma_m: float = Field(4.0, gt=0)
    init_velocity_sigma_mps: float = Field(1.0, gt=0)
    init_bias_sigma_mps: float = Field(0.05, gt=0)
    n_theta_hypotheses: int = Field(8, ge=1, description="heading hypotheses spread over the circle at the start")
    max_step_speed_mps: float = Field(3.0, gt=0, description="faster step intervals are odometry jumps: no velocity reading")


class RssiSection(_Section):
    """The RSSI readings through the access points' path-loss models (fitted on the map) and their residual field."""

    enabled: bool = Field(True, description="fuse the RSSI readings (false: steps and kNN fixes only)")
    sigma_floor_db: float = Field(4.0, gt=0, description="least RSSI std of an AP model")
    adaptive: bool = Field(True, description="inflate a scan's RSSI noise when its innovations disagree (NIS per reading > 1)")
    field_m: float = Field(
        3.0, ge=0, description="kernel std (m) of each AP's residual field measured on the map: what the log-distance law "
        "misses (walls, shelves), added to it; 0: the law alone; else at least 1",
    )
    field_shrink: float = Field(0.5, gt=0, description="the field's pull towards 0 where the map's readings are few (pseudo-readings)")

    @model_validator(mode="after")
    def _field(self) -> "RssiSection":
        if 0 < self.field_m < 1.0:
            raise ValueError("field_m must be 0 (off) or >= 1 m")
        return self


class KnnFixSection(_Section):
    """Each scan's kNN position on the radio map as a position reading (not in the papers)."""

    enabled: bool = Field(True, description="fuse the kNN fixes (false: the papers' RSSI-only model)")
    k: int = Field(3, ge=1, description="neighbours")
    metric: Literal["sorensen", "eq9"] = Field(
        DEFAULT_METRIC, description="fingerprint distance of the fixes (and of the particle filter's scan matches): "
        "sorensen (on powed RSS) or eq9 (the paper's RMS dB difference)",
    )
    sigma_floor_m: float = Field(2.0, gt=0, description="a fix's std = max(kNN neighbour spread, this)")


class WalkAxesSection(_Section):
    """Walkers keep to the two perpendicular directions the map's own walks keep to (fixed-lag and smoother map)."""

    enabled: bool = Field(True, description="the walk-axes prior (off by itself where the map's walks keep to none)")
    sigma_mps: float = Field(1.0, gt=0, description="std of a step's velocity across the nearest axis")
    min_concentration: float = Field(0.3, ge=0, le=1, description="the map's |m4| below which it has no axes")


class FloorPlanSection(_Section):
    """A floor plan's walkable area (track --floor-plan only)."""

    mode: Literal["snap", "prior", "both"] = Field(
        "snap", description="snap: each reported position off the area to its nearest walkable cell (any filter); "
        "prior: a row per step in the fixed-lag / smoother map problem; both",
    )
    sigma_m: float = Field(2.0, gt=0, description="prior: std of a step's distance to the walkable area")


class CalibrationSection(_Section):
    """Self-calibration: the kNN fix noise, RSSI variance, covariance scale and bank temper measured on the map."""

    enabled: bool = Field(True, description="measure them on the radio map itself (docs/tracking.md)")
    replay_sessions: int = Field(20, ge=0, description="replay this many map walks to scale the covariance (0: off)")
    replay_max_scans: int = Field(40, ge=1, description="replayed segments hold at most this many scans")
    replay_seed: int = Field(0)
    replay_route_radius_m: float = Field(
        1.0, ge=0, description="also leave out walks covering half a replayed segment within this (0: off): a new walk "
        "need not follow a surveyed route",
    )
    covariance_scale: float = Field(1.0, gt=0, description="reported covariances are multiplied by this (self-calibration sets it)")


class ParticleSection(_Section):
    """The map-matching particle filter (filter.kind particle)."""

    count: int = Field(1000, ge=2, description="particles per walk")
    top_k: int = Field(16, ge=1, description="map fingerprints in a scan's likelihood mixture")
    temperature: float | None = Field(
        None, gt=0, description="match weights exp(-(D_j - D_1) / T), T in knn_fixes.metric's units; null: the value "
        "measured for that metric (eq9: 2.0, sorensen: 0.05)",
    )
    kernel_m: float = Field(4.0, gt=0, description="each match's spatial spread")
    outlier: float = Field(0.01, gt=0, lt=1, description="share of a uniform density in a scan's likelihood")
    seed: int = Field(0)


class TrackConfig(_Strict):
    """Everything ``graphslam track`` (and ``Tracker``) is configured by, in sections. Built in code
    (``TrackConfig(fixed_lag={"lag_s": 1.0})``) an invalid value is a ``ConfigError`` too."""

    filter: FilterSection = FilterSection()
    fixed_lag: FixedLagSection = FixedLagSection()
    motion: MotionSection = MotionSection()
    rssi: RssiSection = RssiSection()
    knn_fixes: KnnFixSection = KnnFixSection()
    walk_axes: WalkAxesSection = WalkAxesSection()
    floor_plan: FloorPlanSection = FloorPlanSection()
    calibration: CalibrationSection = CalibrationSection()
    particle: ParticleSection = ParticleSection()

    def __init__(self, **data: Any) -> None:
        try:
            super().__init__(**data)
        except ValidationError as e:
            raise ConfigError(f"invalid tracking configuration: {problems(e)}") from None

    @model_validator(mode="after")
    def _consistent(self) -> "TrackConfig":
        if self.filter.kind == "particle" and self.filter.smoother != "none":
            raise ValueError("the particle filter has no offline smoother (its fixed_lag.lag_s is the smoothing)")
        return self

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.model_dump(mode="json"), sort_keys=False)

    def updated(self, changes: dict[str, Any]) -> "TrackConfig":
        """A copy with ``{"section.key": value}`` changed, validated (``ConfigError``)."""
        data = self.model_dump()
        for key, value in changes.items():
            section, _, name = key.partition(".")
            if section not in data or not isinstance(data[section], dict) or name not in data[section]:
                raise ConfigError(f"track: unknown configuration key {key!r}")
            data[section][name] = value
        return validated(type(self), data, "track")  # a subclass (a lab study's) stays itself

    def flat(self) -> dict[str, Any]:
        """``{"section.key": value}`` of every setting."""
        return {f"{s}.{k}": v for s, sec in self.model_dump().items() for k, v in sec.items()}


DEFAULTS = TrackConfig()


def track_config_from_dict(data: dict[str, Any] | None, source: str = "<dict>") -> TrackConfig:
    return validated(TrackConfig, data, source)


def load_track_config(path: str | Path | None = None, overrides: dict[str, Any] | None = None) -> TrackConfig:
    """A YAML tracking config (a partial file is merged over the defaults) and ``--set`` overrides."""
    return load_model(TrackConfig, path, overrides)


def commented_track_yaml(cfg: TrackConfig | None = None) -> str:
    """``configs/track.yaml``: the configuration with each field's description as a comment."""
    return commented_yaml(cfg or TrackConfig(), "graphslam track configuration (mirrors graphslam/tracking_config.py; unknown keys are errors).")
