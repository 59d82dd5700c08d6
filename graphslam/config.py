"""Typed configuration, mirrored by ``configs/default.yaml``.

Unknown keys are errors (``extra="forbid"``); the effective configuration is dumped
with every run's outputs (``config.yaml``).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Literal, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from graphslam.errors import ConfigError

log = logging.getLogger(__name__)


M = TypeVar("M", bound=BaseModel)


class _Strict(BaseModel):
    # allow_inf_nan=False: every float knob is finite (inf, .inf, 1e999, nan are errors): an
    # infinite distance or sigma only fails deep inside GTSAM, after the whole alignment.
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class FingerprintConfig(_Strict):
    """Eq. 9: RMS RSS difference over the union of a pair's access points."""

    missing_rssi_dbm: float = Field(-110.0, description="value of an access point not heard (paper: -110 dBm)")
    min_rssi_dbm: float = Field(-100.0, description="readings weaker than this are dropped as noise")
    max_scan_step_gap_s: float = Field(
        1.5, gt=0, description="a scan further than this in time from every step is not associated"
    )
    standstill_max_s: float = Field(
        120.0, ge=0,
        description="a scan in a pause between steps (or before the first / after the last) up to this long is "
        "attached to the pose where the walker stands; 0: drop such scans (IPIN: 309 of 310 dropped scans were in pauses)",
    )

    @model_validator(mode="after")
    def _floor_above_missing(self) -> "FingerprintConfig":
        if self.min_rssi_dbm <= self.missing_rssi_dbm:
            raise ValueError("min_rssi_dbm must be above missing_rssi_dbm")
        return self


class EdgeConfig(_Strict):
    """Which fingerprint pairs become WiFi-vicinity edges (paper section III-B.2)."""

    window_steps: int = Field(20, ge=2, description="L: the median-window length, in steps")
    exclude_same_session_s: float = Field(
        30.0, ge=0, description="no edge between scans of one session closer than this in time"
    )
    exclude_same_session_m: float = Field(
        10.0, ge=0, description="... or closer than this along the walked path (dead reckoning)"
    )
    max_per_fingerprint: int = Field(
        3, ge=0, description="keep at most this many most-similar partners per fingerprint (0 = paper: all)"
    )
    min_common_aps: int = Field(3, ge=1, description="pairs sharing fewer access points are not compared")
    chunk_rows: int = Field(1024, ge=16, description="at most this many fingerprints per block of the distance computation "
                            "(fewer against many references: a block holds at most 2M distances)")
    candidates: Literal["auto", "exact", "ivf"] = Field(
        "auto",
        description="pairs compared with the threshold. exact: all (O(F^2)); ivf: each fingerprint's ivf_neighbours "
        "nearest in an IVF index (recall 99.7-99.9 % of the exact edges on paper sizes 1-12); auto: ivf above "
        "ivf_above_fingerprints",
    )
    ivf_above_fingerprints: int = Field(
        5000, ge=0, description="auto takes ivf above this many fingerprints (the exact comparison grows as F^2)"
    )
    ivf_neighbours: int = Field(32, ge=1, description="ivf: candidates per fingerprint (the cap keeps 3 of them)")
    ivf_probes: int = Field(8, ge=1, description="ivf: clusters searched per fingerprint (4: recall 98 %, 8: 99.7-99.9 %)")


class ImuConfig(_Strict):
    """Eq. 8: information of the IMU-between factors, as standard deviations per step."""

    sigma_xy_m: float = Field(0.05, gt=0, description="per-step position sigma (Omega = 1/sigma^2)")
    sigma_heading_rad: float = Field(0.02, gt=0, description="per-step heading sigma (0.02 measured best on the simulator)")


class WifiFactorConfig(_Strict):
    """Eq. 10: fuzzy vicinity error, 0 below d_min, linear to e_max at d_max, flat beyond."""

    d_min_m: float = Field(1.0, ge=0, description="paper: 2 m; 1 m measured best on the simulator")
    d_max_m: float = Field(30.0, gt=0, description="beyond this the error is flat (edge treated as an outlier)")
    e_max: float = Field(1.0, gt=0, description="error at and beyond d_max (weight of an edge vs the IMU chain)")
    omega: float = Field(1.0, gt=0, description="Omega_Wifi, the scalar information of each edge")

    @model_validator(mode="after")
    def _order(self) -> "WifiFactorConfig":
        if self.d_max_m <= self.d_min_m:
            raise ValueError("d_max_m must be greater than d_min_m")
        return self


class OptimizerConfig(_Strict):
    """Levenberg-Marquardt, reference pose, initial placement of walks with unknown start."""

    reference_session: str | None = Field(None, description="session whose first pose is fixed (default: first)")
    initialization: Literal["auto", "origin", "registration", "growth", "heading"] = Field(
        "auto",
        description="origin: every walk starts at (0,0,0) as in the paper; registration: rigid WiFi-match fit "
        "(pairwise RANSAC + spanning tree); growth: map growth by Hough registration onto the placed walks "
        "(see the placement section); heading: each walk rotated by its phone heading, then map growth into "
        "components (north-up; walks nothing links stand apart); auto: heading when every walk has "
        "/phone/heading (and heading.enabled), else registration",
    )
    unreliable_registration: Literal["unalign", "keep"] = Field(
        "unalign",
        description="when the registration's loop check contradicts it: unalign: only the reference walk is aligned, "
        "the others are reported with the reason; keep: align them anyway (a warning)",
    )
    max_iterations: int = Field(100, ge=1)
    relative_error_tol: float = Field(1e-4, gt=0)
    absolute_error_tol: float = Field(1e-5, ge=0)
    shape_tol_m: float = Field(
        0.005, ge=0, description="the vectorised LM (solver auto / cholmod): converged once an LM step moves the poses "
        "by less than this (rms, metres) beyond one rigid motion of the whole map (which no output but the frame "
        "depends on) and lowers the error by less than 10x relative_error_tol; 0: off",
    )
    outer_iterations: int = Field(6, ge=1, description="re-evaluations of the saturated (d > d_max) edge set")
    solver: Literal["auto", "cholmod", "gtsam"] = Field(
        "auto",
        description="auto or cholmod: the vectorised LM (own factors; SuiteSparse CHOLMOD through cvxopt, the "
        "sparse Cholesky's analysis reused, or the spanning tree of linear_solver pcg); gtsam: GTSAM's "
        "LevenbergMarquardtOptimizer",
    )
    ordering: Literal["auto", "metis", "amd"] = Field(
        "auto",
        description="the vectorised LM's direct factorisation (linear_solver cholesky, or auto below "
        "pcg_above_variables): its fill-reducing ordering; metis: nested dissection "
        "(GTSAM's METIS) of the pose graph; amd: CHOLMOD's approximate minimum degree; auto: metis from "
        "metis_above_variables unknowns on, amd below",
    )
    metis_above_variables: int = Field(
        20_000, ge=0, description="ordering=auto: METIS from this many unknowns on (3 per solved pose; paper size 4: "
        "27k), where its smaller factor saves more than loading GTSAM costs",
    )
    blas_threads: int = Field(
        1, ge=0, description="OpenBLAS threads (numpy's and scipy's) during a survey; 0 = OpenBLAS's default: every "
        "core, or OPENBLAS_NUM_THREADS. 1: the survey's many small products do not pay for waking the other "
        "threads",
    )
    linear_solver: Literal["auto", "cholesky", "pcg"] = Field(
        "auto",
        description="how each damped system is solved. cholesky: a sparse Cholesky factorisation (solver=gtsam: "
        "multifrontal, METIS); pcg: preconditioned conjugate gradients (the vectorised LM: a spanning tree of the "
        "pose graph factorised as the preconditioner, no fill, each step to the direct step's accuracy; "
        "solver=gtsam: block-Jacobi); auto: pcg from pcg_above_variables unknowns on (solver=gtsam: above "
        "pcg_above_poses pose variables)",
    )
    pcg_above_variables: int = Field(
        10_000, ge=0, description="linear_solver=auto, the vectorised LM: pcg from this many unknowns on (3 per "
        "solved pose; paper size 1: 7k, size 4: 27k)",
    )
    pcg_above_poses: int = Field(6000, ge=0, description="solver=gtsam, linear_solver=auto: pcg above this many pose "
                                 "variables")
    compress_chains: bool = Field(
        True, description="solve only fingerprint poses (IMU chains between them composed exactly), restore the rest"
    )

    @model_validator(mode="before")
    @classmethod
    def _without_pardiso(cls, data: Any) -> Any:
        """A configuration written when MKL PARDISO was a solver (a previous survey's config.yaml): its own
        keys are ignored and ``solver: pardiso`` solves by CHOLMOD, each with a warning. PARDISO gave a
        survey nothing CHOLMOD does not (docs/benchmarks.md) for a ~1 GB dependency."""
        if not isinstance(data, dict):
            return data
        data = dict(data)
        for key in REMOVED_OPTIMIZER_KEYS:
            if key in data:
                del data[key]
                log.warning("optimizer.%s: MKL PARDISO is no longer a solver; the key is ignored", key)
        if data.get("solver") == "pardiso":
            data["solver"] = "cholmod"
            log.warning("optimizer.solver pardiso: MKL PARDISO is no longer a solver; CHOLMOD solves")
        return data


# optimizer keys of MKL PARDISO, accepted and ignored (``OptimizerConfig._without_pardiso``)
REMOVED_OPTIMIZER_KEYS = ("threads", "factor_precision", "single_above_variables")


class PlacementConfig(_Strict):
    """Map-growth placement (optimizer.initialization: growth): power-cosine matches, Hough votes, rigid refine."""

    similarity_scale_db: float = Field(
        10.0, gt=0, description="readings enter as exp(rssi / scale): device-invariant cosine (10-15 dB equal on IPIN)"
    )
    matches_per_fingerprint: int = Field(5, ge=1, description="most similar fingerprints of other walks kept per fingerprint")
    weight_power: float = Field(4.0, gt=0, description="a match votes with similarity ** weight_power")
    rotation_step_deg: float = Field(3.0, gt=0, le=30, description="rotation grid of the Hough registration")
    blur_m: float = Field(1.5, gt=0, description="vote blur: WiFi resolves a few metres")
    distinct_m: float = Field(5.0, gt=0, description="a runner-up placement moves the walk at least this much")
    min_margin: float = Field(
        0.25, ge=0, description="vote weight by which the best placement must beat the runner-up, else the walk is unplaced"
    )
    refine_scale_m: float = Field(3.0, gt=0, description="Cauchy scale of the joint rigid refinement")
    consistent_m: float = Field(6.0, gt=0, description="a match is consistent when its partners end this close")


class HeadingConfig(_Strict):
    """The phone's heading (/phone/heading): each walk's rotation into east/north, and its prior in the optimiser."""

    enabled: bool = Field(True, description="use /phone/heading when every walk has it (false: as without headings)")
    sigma_floor_deg: float = Field(
        25.0, gt=0, le=90, description="least uncertainty of a walk's rotation from its heading (the phone's pointing "
        "relative to the walk, which one walk cannot reveal)",
    )
    cauchy_scale_deg: float = Field(10.0, gt=0, description="yaw - dead-reckoned heading residuals beyond this are down-weighted (disturbed stretches)")
    correlation_steps: int = Field(20, ge=1, description="steps over which the indoor distortion counts as one draw")
    rotation_window_deg: float = Field(
        12.0, gt=0, le=180, description="the placement searches rotations this far either side of the heading"
    )
    min_margin: float = Field(
        1.0, ge=0, description="with headings (and onto a reference map without them), the placement's min_margin: a "
        "walk joins a component only when its best placement beats the runner-up by this vote weight (else it stands apart)",
    )
    wifi_gate_m: float = Field(
        30.0, ge=0, description="with headings, a WiFi edge enters the optimiser only when the placement puts its two "
        "fingerprints this close (at wifi.d_max_m or more: every edge within a component; 0: none)",
    )
    cauchy_sigmas: float = Field(
        1.0, ge=0, description="Cauchy kernel of the heading priors, in sigmas: a walk its WiFi turns far from its "
        "heading (a turned phone, a bent field) is let go; 0: Gaussian",
    )
    prior: Literal["walk", "step", "none"] = Field(
        "walk", description="in the optimiser: walk: one rotation prior per walk (on its first solved pose); step: a "
        "heading factor at every solved pose (the phone's yaw turned by the walk's offset as placed); none: the "
        "heading places the walks only",
    )


class MagneticConfig(_Strict):
    """The magnetic field (/phone/magnetic): sequences of it along the walks link walks that share a corridor."""

    enabled: bool = Field(True, description="use /phone/magnetic where walks have it, with the headings (false: WiFi only)")
    sample_m: float = Field(0.5, gt=0, description="the field is resampled every this much walked (dead-reckoned) distance")
    window_m: float = Field(10.0, gt=0, description="length of a matched stretch")
    stride_m: float = Field(2.0, gt=0, description="a window starts every this much along each walk")
    search_m: float = Field(
        10.0, ge=0, description="a window is compared with the other walk's stretches this far either side of where "
        "a WiFi match (the placement's) anchors it",
    )
    null_quantile: float = Field(
        0.99, gt=0, lt=1, description="a window match counts when its score beats this quantile of the best scores "
        "the same search reaches against phase-randomised surrogates of the walks (the threshold comes from the data)",
    )
    min_windows: int = Field(
        2, ge=1, description="a link between two walks: at least this many window matches, disjoint on both walks, "
        "agreeing on one translation",
    )
    agree_m: float = Field(2.0, gt=0, description="window matches of one link agree on its translation this closely")
    direction_cos: float = Field(
        0.7, ge=0, le=1, description="matched stretches must run parallel (forward) or anti-parallel (reversed) "
        "within this cosine, with each walk turned by its heading",
    )
    pair_every_m: float = Field(
        4.0, gt=0, description="one magnetic factor every this much along a matched stretch (paper --size 12: every 2 m "
        "costs the factorisation a third more than every 4 m, for about the same accuracy)",
    )
    partners_per_place: int = Field(
        3, ge=1, description="each place (pair_every_m of a walk's path) keeps the magnetic factors of this many "
        "best-scoring links (a pair stays when either end keeps it): a route walked n times would tie each place to "
        "n - 1 others, factors growing with the square of the walks",
    )
    window_sigma_m: float = Field(
        1.0, gt=0, description="precision of one matched window's alignment (IPIN 2023 floor -2: its node pairs lie "
        "0.45-0.55 m apart in truth, median, p90 1.2 m); a window's window_m / pair_every_m factors are one "
        "measurement, so each factor's sigma is this times the square root of their number",
    )
    d_min_m: float = Field(0.5, ge=0, description="dead zone of a magnetic factor (the match's own precision)")
    d_max_m: float = Field(5.0, gt=0, description="a magnetic factor saturates beyond this (an outlier)")

    @property
    def sigma_m(self) -> float:
        """Sigma of one magnetic factor on the ramp beyond its dead zone (``window_sigma_m``)."""
        return self.window_sigma_m * max(1.0, self.window_m / self.pair_every_m) ** 0.5

    @model_validator(mode="after")
    def _order(self) -> "MagneticConfig":
        if self.d_max_m <= self.d_min_m:
            raise ValueError("d_max_m must be greater than d_min_m")
        if self.window_m < 4 * self.sample_m:
            raise ValueError("window_m must hold at least 4 samples (sample_m)")
        return self


class ControlPointConfig(_Strict):
    """Control points (survey --control-points): walks whose /landmarks mark a listed id are tied there."""

    sigma_m: float = Field(0.5, gt=0, description="position sigma of a walk at a control point it marks (the button press)")
    wifi_gate_m: float = Field(
        6.0, ge=0, description="in the component the control points tie, a WiFi edge enters the optimiser only when "
        "the placement puts its fingerprints this close (the surveyed points place the walks; WiFi refines them)",
    )


class UpdateConfig(_Strict):
    """graphslam survey --update: how much of a solved floor is re-solved around new walks."""

    hops: int = Field(
        0, ge=0, description="re-solve the new walks, the ends of changed edges and nodes this many factors "
        "from them (paper --size 4 + 1 walk: 0, 1, 2 hops re-solve 23, 48, 56 % of the poses, landmark mean "
        "+0.02, +0.02, -0.01 m vs a full re-solve; 0 is the fastest)",
    )


class UwbConfig(_Strict):
    """UWB ranges in the survey (Paper 003): anchor and peer range factors; values chosen on the simulated crowd (docs/uwb.md)."""

    enabled: bool = Field(True, description="use /uwb/range when the recordings have it (false: WiFi only)")
    range_sigma_m: float = Field(0.1, gt=0, description="range std (the simulated radios: 0.05 m LOS; the rest is timing and height)")
    loss: Literal["cauchy", "huber"] = Field("cauchy", description="robust loss of range factors (NLOS ranges are metres long)")
    loss_k: float = Field(3.0, gt=0, description="loss threshold, in range sigmas")
    tag_height_m: float = Field(1.0, description="antenna height of every tag (m); 2-D anchors are taken at this height")
    anchor_prior_sigma_m: float = Field(1e-3, gt=0, description="surveyed anchor positions: held by a prior this tight")
    peer_max_offset_m: float = Field(
        0.1, gt=0, description="a peer range is used when one walker is within this of a step pose at that instant"
    )
    min_horizontal_m: float = Field(0.5, ge=0, description="anchor ranges shorter than this in the plane are dropped")
    window_s: float = Field(180.0, gt=0, description="initial placement: one rigid fit of dead reckoning per window")
    nlos_reject_sigmas: float = Field(
        1.0, gt=0, description="a range longer than the UWB-only solution by this many sigmas is dropped as NLOS"
    )
    nlos_chord_prefilter: bool = Field(True, description="drop ranges the dead reckoning proves too long before the NLOS solve")
    nlos_chord_sigmas: float = Field(
        3.0, ge=0, description="pre-filter: a range longer than another of the same link plus the chord walked "
        "between them by this many sigmas is NLOS"
    )
    nlos_chord_max_dt_s: float = Field(30.0, gt=0, description="pre-filter: only ranges this close in time are compared")
    presolve_sigma_xy_m: float = Field(
        0.03, gt=0, description="per-step sigma of the UWB-only NLOS solve (no WiFi edges there to bend the chain)"
    )
    presolve_sigma_heading_rad: float = Field(
        0.005, gt=0, description="... and its heading sigma (the simulated foot module: 0.002 + bias)"
    )


class GraphSlamConfig(_Strict):
    fingerprint: FingerprintConfig = FingerprintConfig()
    edges: EdgeConfig = EdgeConfig()
    imu: ImuConfig = ImuConfig()
    wifi: WifiFactorConfig = WifiFactorConfig()
    optimizer: OptimizerConfig = OptimizerConfig()
    placement: PlacementConfig = PlacementConfig()
    heading: HeadingConfig = HeadingConfig()
    magnetic: MagneticConfig = MagneticConfig()
    control_points: ControlPointConfig = ControlPointConfig()
    update: UpdateConfig = UpdateConfig()  # not part of a solution's identity (app/update.py)
    uwb: UwbConfig = UwbConfig()

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.model_dump(mode="json"), sort_keys=False)


def config_from_dict(data: dict[str, Any] | None, source: str = "<dict>") -> GraphSlamConfig:
    return validated(GraphSlamConfig, data, source)


def validated(model: type[M], data: dict[str, Any] | None, source: str) -> M:
    """``model`` from ``data``; ``ConfigError`` naming ``source`` and every invalid key."""
    try:
        return model.model_validate(data or {})
    except ValidationError as e:
        raise ConfigError(f"{source}: invalid configuration: {problems(e)}") from None
    except ConfigError as e:  # a model that converts its own errors (graphslam.tracking_config)
        raise ConfigError(f"{source}: {e}") from None


def problems(e: ValidationError) -> str:
    """A pydantic error as one line: ``section.key: message; ...``."""
    return "; ".join(f"{'.'.join(str(p) for p in err['loc']) or '<root>'}: {err['msg']}" for err in e.errors())


def parse_overrides(items: list[str] | tuple[str, ...] | None, example: str = "wifi.d_min_m=3") -> dict[str, Any]:
    """``--set section.key=value`` options as a nested dict (each value parsed as YAML), to be
    merged over a configuration file (``load_config``'s ``overrides``)."""
    overrides: dict[str, Any] = {}
    for item in items or []:
        key, sep, raw = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE, e.g. {example}")
        try:
            value = yaml.safe_load(raw)
        except yaml.YAMLError:
            raise ConfigError(f"--set {item!r}: the value is not valid YAML") from None
        node = overrides
        *parents, leaf = key.split(".")
        for part in parents:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"--set {item!r}: {part} is set to a value, not a section, by another --set")
        node[leaf] = value
    return overrides


def load_config(path: str | Path | None = None, overrides: dict[str, Any] | None = None) -> GraphSlamConfig:
    """Load a YAML config (a partial file is merged over the defaults)."""
    return load_model(GraphSlamConfig, path, overrides)


def load_model(model: type[M], path: str | Path | None = None, overrides: dict[str, Any] | None = None) -> M:
    """``model`` from a YAML file (a partial file is merged over the defaults) and ``--set`` overrides."""
    data: dict[str, Any] = {}
    source = "--set" if overrides else "<defaults>"
    if path is not None:
        source = str(path)
        try:
            text = Path(path).read_text(encoding="utf-8")
        except OSError as e:
            raise ConfigError(f"{path}: cannot read config ({e.strerror or e})") from None
        try:
            loaded = yaml.safe_load(text)
        except yaml.YAMLError as e:
            raise ConfigError(f"{path}: not valid YAML ({e})") from None
        if loaded is not None and not isinstance(loaded, dict):
            raise ConfigError(f"{path}: top level must be a mapping")
        data = loaded or {}
        if overrides:
            source += " with --set"
    if overrides:
        data = _merge(data, overrides)
    return validated(model, data, source)


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def commented_yaml(cfg: BaseModel | None = None, header: str = "graphslam configuration (mirrors graphslam/config.py; unknown keys are errors).") -> str:
    """The configuration as YAML with each field's description as a comment (configs/default.yaml,
    configs/track.yaml)."""
    cfg = cfg or GraphSlamConfig()
    lines = [f"# {header}"]
    for section, model in cfg:
        lines.append(f"{section}:")
        doc = (type(model).__doc__ or "").strip().splitlines()
        if doc:
            lines[-1] += f"  # {doc[0]}"
        for name, field in type(model).model_fields.items():
            value = yaml.safe_dump({name: getattr(model, name)}, default_flow_style=True).strip()[1:-1]
            comment = f"  # {field.description}" if field.description else ""
            lines.append(f"  {value}{comment}")
    return "\n".join(lines) + "\n"
