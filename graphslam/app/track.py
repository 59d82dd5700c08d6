"""``graphslam track``: online tracking of walks on a radio map (steps + WiFi RSSI + kNN fixes).

``filter``: ``fixed-lag`` (default; ``graphslam.core.tracking.fixed_lag``: each step reported
``lag_s`` after it from a sliding-window MAP of the last ``window_s``, Huber loss instead of the
gate, the heading bank ranked by total cost), or the causal ``ekf`` / ``ukf`` described below.
All share the model, readings and start. ``self_calibrate`` (default on): the kNN fix floor,
the RSSI variance, a covariance scale and the heading bank's temper (how much the correlated
fixes overstate the odds between headings) measured on the radio map itself (``Tracker.on_map``,
``graphslam.core.tracking.calibration``; docs/tracking.md).

Per session (positions in the radio map's frame, m):

- velocity (eq. 4): each foot-module step interval gives ``v_odo = (p_{k+1} - p_k) / dt`` in the
  session's odometry frame; it enters as ``y_v = S v_odo`` (``S`` = x/y swap) so that
  ``y_v = M(theta) v + b`` with ``theta`` the rotation odometry -> map, estimated in the state;
  an interval faster than ``max_step_speed_mps`` is not a walk but an odometry jump (e.g. the
  ILC converter's origin pose 1 ms before the first step: 0.7 m in 1 ms) and gives no reading;
- RSSI (eq. 6): each /wifi/scan reading of an AP with a fitted model (``ApModels``), at or
  above the map's ``min_rssi_dbm``; ``R_i = max(sigma_i, rssi_sigma_floor_db)^2`` from the fit;
  readings beyond ``gate_sigma`` innovation std are skipped (gated);
- kNN fix (``knn_fixes``, default on; not in the papers): the scan's kNN position on the radio
  map as a 2-D position reading, std ``max(neighbour spread, fix_sigma_floor_m)``, gated as one
  reading at ``gate_sigma`` (simulator: 1.20 -> 1.03 m, docs/tracking.md);
- adaptive RSSI noise (``adaptive_rssi``, default on; the papers' future work): when a scan's
  RSSI innovations are larger than their covariance says (NIS per reading > 1), that scan's R
  is scaled by the ratio (``filters._inflate_rssi_noise``); consistent scans are unchanged;
- walk axes (``walk_axes``, default on; fixed-lag and ``--smooth map``; not in the papers): the two
  perpendicular directions the map's own walks keep to (``graphslam.core.tracking.axes``, measured on
  the map; none where its walks keep to no axes) as a robust prior on the map-frame walking
  direction: corridors fix the heading the fixes find only slowly (docs/tracking.md);
- floor plan (only when given, ``track --floor-plan``; ``walkable_mode``): the plan's walkable area
  (``graphslam.core.tracking.walkable``) either moves each reported position that lies off it to the
  nearest walkable cell (``snap``, default; any filter; covariance unchanged), or is a robust prior
  row per step in the fixed-lag / ``--smooth map`` problem (``prior``), or both;
- start: position = kNN fix of the first locatable scan (the radio map itself); heading
  unknown, so a bank of ``n_theta_hypotheses`` filters with theta_0 spread over the circle runs
  in lock-step and each step reports the one with the highest cumulative innovation
  likelihood so far (online; gated readings count as a fixed penalty). Never ground truth.

``smoother`` (offline, whole session known): ``rts`` runs the RTS pass, ``map`` the whole-run MAP
(``graphslam.core.tracking.smoother``; Huber loss at ``gate_sigma`` on RSSI and fix rows instead of the gate)
over the hypothesis with the highest final likelihood; the output rows are then that
smoothed trajectory (``hypothesis`` column constant).
"""

from __future__ import annotations

import csv
import dataclasses
import logging
import math
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
from numpy.typing import NDArray

from graphslam.core.tracking.apmodel import ApModels
from graphslam.core.tracking.axes import WalkAxes
from graphslam.core.tracking.filters import (
    Epochs, FusionModel, GaussianState, KalmanFilter, make_filter, position_update, run_epochs,
)
from graphslam.core.radiomap.knn import METRICS as KNN_METRICS, KnnConfig, KnnLocator
from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.core.tracking.fixed_lag import FixedLagConfig, fixed_lag_smooth
from graphslam.core.tracking.particle import ParticleConfig, RssiReadings, run_particle_filter, scan_matches
from graphslam.core.tracking.smoother import SMOOTH_METHODS, smooth
from graphslam.core.tracking.walkable import WalkableArea
from graphslam.core.progress import Task
from graphslam.core.types import Session
from graphslam.errors import ConfigError, EstimationError
from graphslam.io.atomic import atomic_open

log = logging.getLogger(__name__)

TRACK_HEADER = (
    "session_id", "t_ns", "x", "y", "cov_xx", "cov_xy", "cov_yy", "vx", "vy", "theta", "theta_std", "hypothesis",
)
_SWAP = np.array([[0.0, 1.0], [1.0, 0.0]])
TRACKERS = ("fixed-lag", "ekf", "ukf", "particle")
# The particle filter's match temperature T per fingerprint distance (its units: eq. 9 dB; Sørensen, unitless
# in [0, 1]): each the maximum of the leave-one-session-out log-likelihood of the ILC B1 training maps' own
# fingerprint positions under the scan-match mixture (the map only; the surface is flat near it: docs/tracking.md)
PARTICLE_TEMPERATURE = {"eq9": 2.0, "sorensen": 0.05}
WALKABLE_MODES = ("snap", "prior", "both")  # how a floor plan's walkable area is used (TrackConfig.walkable_mode)
BANK_REPORTS = ("mixture", "best")  # fixed-lag: the heading bank's posterior mixture, or its best hypothesis


@dataclass(frozen=True)
class TrackConfig:
    """Filter settings for walking people (SI units; process noise per second)."""

    filter: str = "fixed-lag"  # fixed-lag (online, lag_s late) | ekf | ukf (causal)
    lag_s: float = 2.0  # fixed-lag: a step's position is reported once the data up to lag_s later are in
    window_s: float = 20.0  # fixed-lag: older epochs are marginalised into a prior
    prune_cost: float | None = 50.0  # fixed-lag: heading hypotheses this far above the best are dropped
    # fixed-lag: the heading bank's costs over this in its weights and pruning; None: measured on the map with
    # self-calibration (the fixes' error correlation along a walk, ``calibration.bank_temper``), else 1
    bank_temper: float | None = None
    calibrate_covariance: bool = True  # fixed-lag: covariances also scaled by the walk's own fix-innovation variance factor
    bank_report: str = "mixture"  # fixed-lag: mixture (posterior mixture of the heading bank) | best (lowest-cost hypothesis)
    w0: float = 0.1  # UKF weight of the central sigma point (Paper 002's value)
    velocity_sigma_mps: float = 0.15  # step-velocity noise per axis
    q_position: float = 0.01  # m^2/s
    q_velocity: float = 1.0  # (m/s)^2/s: walkers turn and stop
    q_bias: float = 1e-6  # (m/s)^2/s
    q_theta: float = 1e-4  # rad^2/s: foot-module heading drift
    init_position_sigma_m: float = 4.0
    init_velocity_sigma_mps: float = 1.0
    init_bias_sigma_mps: float = 0.05
    n_theta_hypotheses: int = 8
    rssi_sigma_floor_db: float = 4.0
    gate_sigma: float = 3.0
    knn_k: int = 3
    # kNN fixes' fingerprint distance (``KnnConfig.metric``). Sørensen on powed RSS since 2026-12-02:
    # better fixes, means and ellipses on IPIN b100_f-2 and all five ILC site1 floors (docs/tracking.md).
    # The particle filter's scan matches use it too (its temperature in this distance's units)
    knn_metric: str = "sorensen"
    max_step_speed_mps: float = 3.0  # faster step intervals are odometry jumps: no velocity reading
    # walk-axes prior (``graphslam.core.tracking.axes``; fixed-lag and --smooth map only): walkers keep to
    # the two perpendicular directions the map's own walks keep to, when they keep to them this much
    walk_axes: bool = True
    # std of a step's velocity across the nearest axis: a weak prior per step (one row per step, whose
    # directions are correlated along a leg); 1.0 of 0.25 / 0.5 / 1.0, the one better than none on all six
    # real floors (IPIN b100_f-2, ILC site1 B1-F4; docs/tracking.md)
    axis_sigma_mps: float = 1.0
    axis_min_concentration: float = 0.3  # the map's |m4| (0: no preferred direction, 1: all on the axes)
    # a floor plan's walkable area (``graphslam.core.tracking.walkable``; only with ``track --floor-plan``):
    # snap (each reported position off the area to its nearest walkable cell; any filter) | prior (one row per
    # step in the fixed-lag / --smooth map problem) | both. snap: the one better than none on every ILC site1
    # floor; the prior helps F2 / F3 more and hurts B1 (docs/tracking.md)
    walkable_mode: str = "snap"
    walkable_sigma_m: float = 2.0  # prior: std (m) of a step's distance to the walkable area
    knn_fixes: bool = True  # also fuse each scan's kNN fix on the radio map as a position reading
    fix_sigma_floor_m: float = 2.0  # a fix's std = max(kNN neighbour spread, this)
    adaptive_rssi: bool = True  # inflate a scan's RSSI noise when its innovations say so
    # what the AP models' law misses, as a field per AP measured on the map (``rssi_field``): its kernel std
    # (m; 0: the law alone) and its pull towards 0 where the map's readings are few (pseudo-readings)
    rssi_field_m: float = 3.0
    rssi_field_shrink: float = 0.5
    rssi: bool = True  # fuse the RSSI readings through the AP models (False: steps and kNN fixes only)
    replay_sessions: int = 20  # self-calibration: replay this many map walks to scale the covariance (0: off)
    replay_max_scans: int = 40  # self-calibration: replayed segments hold at most this many scans
    replay_seed: int = 0
    # self-calibration: also leave out walks covering half a replayed segment within this (m; 0: off). A new
    # walk need not follow a surveyed route; 1 m (a step) chosen among 0 / 1 / 2 m on IPIN b100_f-2 and
    # ILC site1's five floors, where it puts the 95 % ellipses at 85.7-99.6 % (docs/tracking.md)
    replay_route_radius_m: float = 1.0
    covariance_scale: float = 1.0  # reported covariances are multiplied by this (set by self-calibration)
    self_calibrate: bool = True  # RSSI variance and kNN fix floor measured on the map (self_calibrated)
    smoother: str = "none"  # none | rts | map (offline: uses the whole session)
    particles: int = 1000  # particle: particles per walk
    particle_top_k: int = 16  # particle: map fingerprints in a scan's likelihood mixture
    # particle: match weights exp(-(D_j - D_1) / T), T in knn_metric's units; None: PARTICLE_TEMPERATURE's
    particle_temperature: float | None = None
    particle_kernel_m: float = 4.0  # particle: each match's spatial spread (m)
    particle_outlier: float = 0.01  # particle: share of a uniform density in a scan's likelihood
    particle_seed: int = 0

    def __post_init__(self) -> None:
        if self.filter not in TRACKERS:
            raise EstimationError(f"track: unknown filter {self.filter!r}; use {', '.join(TRACKERS)}")
        if self.smoother != "none" and self.smoother not in SMOOTH_METHODS:
            raise EstimationError(f"track: unknown smoother {self.smoother!r}; use none, {', '.join(SMOOTH_METHODS)}")
        if self.n_theta_hypotheses < 1 or self.velocity_sigma_mps <= 0 or self.rssi_sigma_floor_db <= 0:
            raise EstimationError("track: n_theta_hypotheses >= 1 and positive noise levels required")
        if not (math.isfinite(self.lag_s) and self.lag_s >= 0 and math.isfinite(self.window_s) and self.window_s >= 0):
            raise EstimationError(f"track: lag_s and window_s must be finite and >= 0, got {self.lag_s}, {self.window_s}")
        if self.max_step_speed_mps <= 0 or self.fix_sigma_floor_m <= 0:
            raise EstimationError("track: max_step_speed_mps and fix_sigma_floor_m must be > 0")
        if self.bank_temper is not None and not (math.isfinite(self.bank_temper) and self.bank_temper >= 1):
            raise EstimationError(f"track: bank_temper must be >= 1 (or None), got {self.bank_temper}")
        if self.bank_report not in BANK_REPORTS:
            raise EstimationError(f"track: unknown bank report {self.bank_report!r}; use {', '.join(BANK_REPORTS)}")
        if self.filter == "particle" and self.smoother != "none":
            raise EstimationError("track: the particle filter has no offline smoother (its --lag is the smoothing)")
        if self.filter == "particle":
            self.particle_config()  # its own checks, before any file is read
        if self.knn_metric not in KNN_METRICS:
            raise EstimationError(f"track: unknown kNN metric {self.knn_metric!r}; use {', '.join(KNN_METRICS)}")
        if not (self.axis_sigma_mps > 0 and 0.0 <= self.axis_min_concentration <= 1.0):
            raise EstimationError(
                f"track: axis_sigma_mps must be > 0 and axis_min_concentration in [0, 1], got "
                f"{self.axis_sigma_mps}, {self.axis_min_concentration}")
        if self.walkable_mode not in WALKABLE_MODES:
            raise EstimationError(f"track: unknown walkable_mode {self.walkable_mode!r}; use {', '.join(WALKABLE_MODES)}")
        if not (math.isfinite(self.walkable_sigma_m) and self.walkable_sigma_m > 0):
            raise EstimationError(f"track: walkable_sigma_m must be finite and > 0, got {self.walkable_sigma_m}")
        if not (math.isfinite(self.rssi_field_m) and (self.rssi_field_m == 0 or self.rssi_field_m >= 1.0)
                and math.isfinite(self.rssi_field_shrink) and self.rssi_field_shrink > 0):
            raise EstimationError(f"track: rssi_field_m must be 0 (off) or >= 1 m and rssi_field_shrink > 0, got "
                                  f"{self.rssi_field_m}, {self.rssi_field_shrink}")
        if not (math.isfinite(self.replay_route_radius_m) and self.replay_route_radius_m >= 0):
            raise EstimationError(f"track: replay_route_radius_m must be finite and >= 0, got {self.replay_route_radius_m}")

    def walk_axes_of(self, rm: RadioMap) -> WalkAxes | None:
        """The walk-axes prior measured on ``rm``'s own walks (None: off, or no axes there)."""
        if not self.walk_axes:
            return None
        return WalkAxes.from_walks(rm.xy, rm.session_ids, rm.t_ns, sigma_mps=self.axis_sigma_mps,
                                   min_concentration=self.axis_min_concentration)

    def walkable_area(self, area: WalkableArea | None) -> WalkableArea | None:
        """``area`` with this configuration's std (None stays None)."""
        if area is None or area.sigma_m == self.walkable_sigma_m:
            return area
        return dataclasses.replace(area, sigma_m=self.walkable_sigma_m)

    def knn_config(self) -> KnnConfig:
        """The kNN fixes' search (and the particle filter's scan matches)."""
        return KnnConfig(k=self.knn_k, metric=self.knn_metric)  # type: ignore[arg-type]

    def particle_config(self, area_m2: float = 1.0, seed: int = 0) -> ParticleConfig:
        """The particle filter's settings (``EstimationError`` when invalid); ``seed`` is mixed with
        ``particle_seed``."""
        return ParticleConfig(
            n_particles=self.particles, top_k=self.particle_top_k,
            temperature=PARTICLE_TEMPERATURE[self.knn_metric] if self.particle_temperature is None else self.particle_temperature,
            kernel_m=self.particle_kernel_m, outlier=self.particle_outlier, area_m2=area_m2, lag_s=self.lag_s,
            huber_k=self.gate_sigma, seed=self.particle_seed ^ seed,
        )


@dataclass(frozen=True, eq=False)
class SessionTrack:
    """State at every step: x (N, 7), P (N, 7, 7). Filtered (after the step's velocity update), or
    smoothed over the whole session when ``TrackConfig.smoother`` is set."""

    session_id: str
    t_ns: NDArray[np.int64]
    x: NDArray[np.float64]
    P: NDArray[np.float64]
    hypothesis: NDArray[np.int64]  # theta hypothesis reported at each step
    n_rssi_used: int  # of the hypothesis reported at the last step
    n_rssi_gated: int

    @property
    def xy(self) -> NDArray[np.float64]:
        return self.x[:, :2]


@dataclass(frozen=True, eq=False)
class TrackRun:
    tracks: tuple[SessionTrack, ...]
    out: Path | None
    n_aps_modelled: int

    def as_dict(self) -> dict[str, object]:
        return {
            "out": None if self.out is None else str(self.out),
            "sessions": len(self.tracks),
            "steps": int(sum(len(t.t_ns) for t in self.tracks)),
            "aps_modelled": self.n_aps_modelled,
            "rssi_used": int(sum(t.n_rssi_used for t in self.tracks)),
            "rssi_gated": int(sum(t.n_rssi_gated for t in self.tracks)),
        }


def fusion_model(models: ApModels, cfg: TrackConfig) -> FusionModel:
    """The papers' model with theta in the state, noise per second (``period_s`` = 1)."""
    pl = models.path_loss()
    sig = np.array([max(a.sigma_db, cfg.rssi_sigma_floor_db) for a in models.fitted])
    return FusionModel(
        pl,
        q_diag=np.array([cfg.q_position] * 2 + [cfg.q_velocity] * 2 + [cfg.q_bias] * 2 + [cfg.q_theta]),
        r_velocity=np.full(2, cfg.velocity_sigma_mps**2),
        r_rssi=sig**2,
        period_s=1.0,
        theta_rad=None,
    )


def _scan_measurements(
    session: Session, bssids: Sequence[str], min_rssi_dbm: float, use_rssi: bool = True
) -> list[tuple[int, NDArray, NDArray]]:
    """Per scan, in time order: (t_ns, AP rows, dBm) of its readings of modelled APs (empty arrays
    when none, or when ``use_rssi`` is off): every scan is an epoch, for its kNN fix if nothing else."""
    index = {b: i for i, b in enumerate(bssids)}
    out = []
    for sc in sorted(session.scans, key=lambda s: s.t_ns):
        pairs = sorted((index[b], r) for b, r in sc.readings.items() if b in index and r >= min_rssi_dbm) if use_rssi else []
        out.append((sc.t_ns, np.array([p[0] for p in pairs], np.int64), np.array([p[1] for p in pairs], float)))
    return out


def track_session(
    session: Session, model: FusionModel, locator: KnnLocator, cfg: TrackConfig = TrackConfig(),
    progress: Task | None = None, area: WalkableArea | None = None,
) -> SessionTrack:
    """Track one session (see module docstring). ``EstimationError`` if it has < 2 steps or no scan
    the radio map can locate. Covariances come out multiplied by ``cfg.covariance_scale``;
    ``progress`` advances by one per step. ``area``: the floor's walkable area in the radio map's
    frame, used as ``cfg.walkable_mode`` says (the prior: fixed-lag and ``--smooth map`` only)."""
    tr = _track_session(session, model, locator, cfg, progress, area if cfg.walkable_mode in ("prior", "both") else None)
    if cfg.covariance_scale != 1.0:
        tr = dataclasses.replace(tr, P=tr.P * cfg.covariance_scale)
    if area is not None and cfg.walkable_mode in ("snap", "both"):
        x = tr.x.copy()
        x[:, :2] = area.snap(x[:, :2])  # covariance kept: the snap does not make the estimate surer
        tr = dataclasses.replace(tr, x=x)
    return tr


def _track_session(
    session: Session, model: FusionModel, locator: KnnLocator, cfg: TrackConfig, progress: Task | None,
    area: WalkableArea | None = None,
) -> SessionTrack:
    steps = session.steps
    if len(steps) < 2:
        raise EstimationError(f"track: session {session.session_id} has {len(steps)} steps (need 2)")
    if cfg.filter == "particle":
        tr = _track_particles(session, model, locator, cfg)
        if progress is not None:
            progress.advance(len(steps))
        return tr
    filt: KalmanFilter = make_filter("ekf" if cfg.filter == "fixed-lag" else cfg.filter, model, w0=cfg.w0)
    bssids = model.path_loss.bssids
    meas = _scan_measurements(session, bssids, locator.radio_map.min_rssi_dbm, cfg.rssi)
    fix = locator.locate([sc.readings for sc in session.scans]) if session.scans else None
    ok = np.flatnonzero(fix.valid) if fix is not None else np.zeros(0, int)
    if not len(ok):
        raise EstimationError(f"track: session {session.session_id}: no scan could be located on the radio map")
    p0 = fix.xy[ok[0]]
    fixes: dict[int, tuple[NDArray, float]] = {}  # scan time -> (kNN position, std)
    if cfg.knn_fixes:
        for i in ok[1:]:  # the first fix is the start position already
            sigma = float(np.nan_to_num(fix.spread[i], nan=0.0))
            fixes[session.scans[i].t_ns] = (fix.xy[i], max(sigma, cfg.fix_sigma_floor_m))
    t = steps.t_ns
    v_odo = np.diff(steps.xy, axis=0) / (np.diff(t)[:, None] / 1e9)
    y_v = v_odo @ _SWAP.T
    walked = np.linalg.norm(v_odo, axis=1) <= cfg.max_step_speed_mps
    if not walked.all():
        log.info("track: session %s: %d step interval(s) faster than %.1f m/s skipped (odometry jumps)",
                 session.session_id, int((~walked).sum()), cfg.max_step_speed_mps)
    H = cfg.n_theta_hypotheses
    P0 = np.diag(
        [cfg.init_position_sigma_m**2] * 2 + [cfg.init_velocity_sigma_mps**2] * 2
        + [cfg.init_bias_sigma_mps**2] * 2 + [(math.pi / H) ** 2]
    )
    starts = [np.array([p0[0], p0[1], 0, 0, 0, 0, 2 * math.pi * h / H]) for h in range(H)]
    windowed = cfg.filter == "fixed-lag" or cfg.smoother == "map"  # the MAP problems that hold priors
    axes = cfg.walk_axes_of(locator.radio_map) if windowed else None
    area = cfg.walkable_area(area) if windowed else None
    if cfg.filter == "fixed-lag" and cfg.smoother == "none":
        tr = _track_fixed_lag(session.session_id, model, starts, P0, t, y_v, walked, meas, fixes, cfg, axes, area)
        if progress is not None:
            progress.advance(len(t))
        return tr
    states = [GaussianState(x0, P0) for x0 in starts]
    ll = np.zeros(H)
    penalty = 0.5 * cfg.gate_sigma**2  # a gated reading costs at least what a 'gate_sigma' one would
    xs, Ps, best = [], [], []
    used = np.zeros(H, np.int64)  # per hypothesis: RSSI readings used / gated
    gated = np.zeros(H, np.int64)
    j = 0
    while j < len(meas) and meas[j][0] <= t[0]:
        j += 1  # scans before the first step: the kNN start already used them
    for k in range(len(t)):
        if k < len(t) - 1 and walked[k]:
            for h in range(H):
                states[h], info = filt.update(states[h], y_v[k], use_velocity=True)
                ll[h] += info.loglik
        b = int(np.argmax(ll))
        xs.append(states[b].x)
        Ps.append(states[b].P)
        best.append(b)
        if progress is not None:
            progress.advance()
        if k == len(t) - 1:
            break
        t_now = t[k]
        while j < len(meas) and meas[j][0] <= t[k + 1]:
            ts, idx, rss = meas[j]
            for h in range(H):
                s = filt.predict(states[h], (ts - t_now) / 1e9)
                states[h], info = filt.update(
                    s, rss, use_velocity=False, ap_idx=idx, gate_sigma=cfg.gate_sigma, adaptive_rssi=cfg.adaptive_rssi
                )
                ll[h] += info.loglik - penalty * info.n_gated
                used[h] += info.n_used
                gated[h] += info.n_gated
                if ts in fixes:
                    states[h], info = position_update(states[h], *fixes[ts], gate_sigma=cfg.gate_sigma)
                    ll[h] += info.loglik - penalty * info.n_gated
            t_now = ts
            j += 1
        dt = (t[k + 1] - t_now) / 1e9
        states = [filt.predict(s, dt) for s in states]
    if cfg.smoother == "none":
        return SessionTrack(
            session.session_id, t.copy(), np.array(xs), np.array(Ps), np.array(best, np.int64),
            int(used[best[-1]]), int(gated[best[-1]]),
        )
    h = best[-1]
    x0 = np.array([p0[0], p0[1], 0, 0, 0, 0, 2 * math.pi * h / H])
    epochs, step_epoch = _session_epochs(t, y_v, walked, meas, fixes)
    filtered = run_epochs(filt, x0, P0, epochs, gate_sigma=cfg.gate_sigma)
    sm = smooth(model, x0, P0, epochs, filtered, cfg.smoother, huber_k=cfg.gate_sigma, axes=axes, area=area)
    return SessionTrack(
        session.session_id, t.copy(), sm.x[step_epoch], sm.P[step_epoch], np.full(len(t), h, np.int64),
        filtered.n_rssi_used, filtered.n_rssi_gated,
    )


def _track_fixed_lag(
    session_id: str, model: FusionModel, starts: list[NDArray], P0: NDArray, t: NDArray[np.int64], y_v: NDArray,
    walked: NDArray[np.bool_], meas: Sequence[tuple[int, NDArray, NDArray]], fixes: dict[int, tuple[NDArray, float]],
    cfg: TrackConfig, axes: WalkAxes | None = None, area: WalkableArea | None = None,
) -> SessionTrack:
    """The fixed-lag smoother over the session's epochs; a step interval's velocity is known at its
    end step (``vel_available_s``), so a lag of 0 reports each step from the data up to it."""
    epochs, step_epoch = _session_epochs(t, y_v, walked, meas, fixes)
    avail = epochs.t_s[step_epoch[1:][walked]]
    run = fixed_lag_smooth(
        model, starts, P0, epochs,
        FixedLagConfig(
            lag_s=cfg.lag_s, window_s=max(cfg.window_s, cfg.lag_s), huber_k=cfg.gate_sigma, prune_cost=cfg.prune_cost,
            adaptive_rssi=cfg.adaptive_rssi, report=cfg.bank_report, angle_index=None if model.theta_rad is not None else 6,
            temper=1.0 if cfg.bank_temper is None else cfg.bank_temper,
        ),
        vel_available_s=avail, axes=axes, area=area,
    )
    P = run.P * (run.variance_factor[:, None, None] if cfg.calibrate_covariance else 1.0)
    return SessionTrack(
        session_id, t.copy(), run.x[step_epoch], P[step_epoch], run.hypothesis[step_epoch],
        len(epochs.rss_k), 0,  # every RSSI reading is used (Huber-weighted, never gated)
    )


def _track_particles(session: Session, model: FusionModel, locator: KnnLocator, cfg: TrackConfig) -> SessionTrack:
    """The map-matching particle filter (``graphslam.core.tracking.particle``): state columns x, y
    and theta (the module-to-map rotation); velocity and bias columns 0."""
    steps = session.steps
    t0 = steps.t_ns[0]
    scans = sorted(session.scans, key=lambda s: s.t_ns)
    rm = locator.radio_map
    if scans and len(rm):
        idx, dist = scan_matches(locator.distances(rm.encode([sc.readings for sc in scans])), cfg.particle_top_k)
    else:
        idx, dist = np.full((len(scans), 0), -1, np.int64), np.zeros((len(scans), 0))
    t_s = (steps.t_ns - t0) / 1e9
    walked = np.linalg.norm(np.diff(steps.xy, axis=0), axis=1) / np.maximum(np.diff(t_s), 1e-9) <= cfg.max_step_speed_mps
    rssi = None
    if cfg.rssi and len(model.path_loss):
        meas = _scan_measurements(session, model.path_loss.bssids, rm.min_rssi_dbm)  # time order, as ``scans``
        rssi = RssiReadings(model.path_loss, np.sqrt(model.r_rssi), [m[1] for m in meas], [m[2] for m in meas])
    pcfg = cfg.particle_config(_area_m2(rm), zlib.crc32(session.session_id.encode()))
    try:
        run = run_particle_filter(
            t_s, steps.xy, walked, np.array([(sc.t_ns - t0) / 1e9 for sc in scans]), rm.xy[np.maximum(idx, 0)], dist, pcfg,
            rssi,
        )
    except EstimationError as e:
        raise EstimationError(f"track: session {session.session_id}: {e}") from None
    n = len(t_s)
    x = np.zeros((n, 7))
    x[:, :2], x[:, 6] = run.xy, run.phi
    P = np.zeros((n, 7, 7))
    P[:, :2, :2] = run.cov
    P[:, 6, 6] = run.phi_var
    return SessionTrack(session.session_id, steps.t_ns.copy(), x, P, np.zeros(n, np.int64), 0, 0)


def _area_m2(rm: RadioMap) -> float:
    """The radio map's bounding box, 5 m around its fingerprints (m^2)."""
    if not len(rm):
        return 1.0
    return float(np.prod(rm.xy.max(axis=0) - rm.xy.min(axis=0) + 10.0))


def _session_epochs(
    t_ns: NDArray[np.int64],
    y_v: NDArray,
    walked: NDArray[np.bool_],
    meas: Sequence[tuple[int, NDArray, NDArray]],
    fixes: dict[int, tuple[NDArray, float]],
) -> tuple[Epochs, NDArray[np.int64]]:
    """The filter loop's readings as ``Epochs``: step times (velocity of the interval that starts
    there if ``walked``, none at the last step) and scan times in (first step, last step] with
    their RSSI and kNN fix; returns the epoch of every step too. Times in s from the first step."""
    scans = [m for m in meas if t_ns[0] < m[0] <= t_ns[-1]]
    times, inv = np.unique(np.concatenate([t_ns, np.array([m[0] for m in scans], np.int64)]), return_inverse=True)
    step_epoch = inv[: len(t_ns)]
    scan_epoch = inv[len(t_ns):]
    n_each = np.array([len(m[1]) for m in scans], np.int64)
    cat = (lambda parts, dt: np.concatenate(parts) if parts else np.zeros(0, dt))
    fixed = [j for j, m in enumerate(scans) if m[0] in fixes]
    epochs = Epochs(
        (times - t_ns[0]) / 1e9, step_epoch[:-1][walked], y_v[walked],
        np.repeat(scan_epoch, n_each), cat([m[1] for m in scans], np.int64), cat([m[2] for m in scans], float),
        scan_epoch[fixed], np.array([fixes[scans[j][0]][0] for j in fixed]).reshape(-1, 2),
        np.array([fixes[scans[j][0]][1] for j in fixed]),
    )
    return epochs, step_epoch


def write_track_csv(tracks: Iterable[SessionTrack], path: str | Path) -> Path:
    """CSV (``TRACK_HEADER``), one row per step, written atomically. Units: m, m^2, m/s, rad."""
    path = Path(path)
    with atomic_open(path, "w", encoding="utf-8", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(TRACK_HEADER)
        for tr in tracks:
            for t, x, P, h in zip(tr.t_ns.tolist(), tr.x, tr.P, tr.hypothesis.tolist()):
                w.writerow((
                    tr.session_id, t, f"{x[0]:.4f}", f"{x[1]:.4f}", f"{P[0, 0]:.5f}", f"{P[0, 1]:.5f}",
                    f"{P[1, 1]:.5f}", f"{x[2]:.4f}", f"{x[3]:.4f}", f"{math.remainder(x[6], 2 * math.pi):.5f}",
                    f"{math.sqrt(max(P[6, 6], 0.0)):.5f}", h,
                ))
    return path


@dataclass(frozen=True, eq=False)
class Tracker:
    """A radio map made ready for tracking: the fusion model from its AP models, its kNN locator and
    the configuration, self-calibrated on the map once (``TrackConfig.self_calibrate``)."""

    model: FusionModel
    locator: KnnLocator
    cfg: TrackConfig
    calibration: SelfCalibration | None = None  # what self-calibration applied (None: off)
    area: WalkableArea | None = None  # the floor plan's walkable area in the map's frame (None: no plan)

    @classmethod
    def on_map(
        cls, rm: RadioMap, models: ApModels, cfg: TrackConfig = TrackConfig(), calibration: SelfCalibration | None = None,
        area: WalkableArea | None = None,
    ) -> "Tracker":
        """``calibration``: one measured on this map with this ``cfg`` before (else measured now);
        ``area``: the floor's walkable area in the map's frame (``TrackConfig.walkable_mode``)."""
        if models.frame != rm.frame:
            raise EstimationError(f"track: AP models are in frame {models.frame!r}, radio map in {rm.frame!r}")
        model = fusion_model(models, cfg)
        if cfg.rssi:
            model = with_residual_field(model, rm, cfg, leave_out=True)
        area = cfg.walkable_area(area)  # once: its distance field is rebuilt for another std
        if not cfg.self_calibrate:
            calibration = None
        elif calibration is None:
            calibration = SelfCalibration.measure(rm, models, model, cfg, area)
        if calibration is not None:
            model, cfg = calibration.apply(model, cfg)
        if cfg.walk_axes and (cfg.filter == "fixed-lag" or cfg.smoother == "map"):
            axes = cfg.walk_axes_of(rm)
            if axes is None:
                log.info("track: walk axes: none on this map (concentration below %.2f)", cfg.axis_min_concentration)
            else:
                log.info("track: walk axes at %.1f deg + k 90 deg (concentration %.2f)", math.degrees(axes.angle_rad), axes.concentration)
        if area is not None:
            log.info("track: walkable area from the floor plan: %.0f %% of %.0f x %.0f m (%s)",
                     100 * area.fraction_walkable(), area.width_m, area.height_m, cfg.walkable_mode)
        return cls(model, KnnLocator(rm, cfg.knn_config()), cfg, calibration, area)

    def track(self, session: Session, progress: Task | None = None) -> SessionTrack:
        return track_session(session, self.model, self.locator, self.cfg, progress, self.area)


def with_residual_field(model: FusionModel, rm: RadioMap, cfg: TrackConfig, *, aps: NDArray | None = None,
                        leave_out: bool = False) -> FusionModel:
    """``model`` with its AP models' residual field measured on ``rm`` (``cfg.rssi_field_m``; the
    model as it is when 0). The RSSI noise stays the law's (``rssi_field``). ``aps``: only these APs
    corrected; ``leave_out``: also log the readings' leave-one-walk-out noise around the field."""
    if cfg.rssi_field_m <= 0 or not len(model.path_loss):
        return model
    from graphslam.core.tracking.apmodel import residual_field

    fit = residual_field(rm, model.path_loss, bandwidth_m=cfg.rssi_field_m, shrink=cfg.rssi_field_shrink,
                         leave_out=leave_out, aps=aps)
    if leave_out:
        ok = np.isfinite(fit.sigma_db)
        if ok.any():
            log.info("track: RSSI field (%.1f m): the map's readings scatter %.1f dB around it, %.1f dB around the law "
                     "(median over %d APs, each map walk left out)", cfg.rssi_field_m, float(np.median(fit.sigma_db[ok])),
                     float(np.median(fit.sigma_law_db[ok])), int(ok.sum()))
    return dataclasses.replace(model, path_loss=dataclasses.replace(model.path_loss, correction=fit.field))


def track_sessions(
    sessions: Sequence[Session], rm: RadioMap, models: ApModels, cfg: TrackConfig = TrackConfig()
) -> tuple[SessionTrack, ...]:
    """Track every session on ``rm`` with the AP models ``models`` (same frame as ``rm``)."""
    tracker = Tracker.on_map(rm, models, cfg)
    with Task("track", total=sum(len(s.steps) for s in sessions), unit="steps") as task:
        return tuple(tracker.track(s, task) for s in sessions)


@dataclass(frozen=True)
class SelfCalibration:
    """What self-calibration measured on one radio map for one ``TrackConfig``: four numbers,
    so that they can be kept beside the map (``track_files``) instead of measured per call."""

    rssi_variance_factor: float  # RSSI variances x this
    fix_sigma_floor_m: float  # kNN fix std floor (m)
    covariance_scale: float  # reported covariances x this (>= 1)
    bank_temper: float = 1.0  # the heading bank's costs / this (>= 1; only where TrackConfig.bank_temper is None)

    @classmethod
    def measure(
        cls, rm: RadioMap, models: ApModels, model: FusionModel, cfg: TrackConfig, area: WalkableArea | None = None
    ) -> "SelfCalibration":
        """The map's own RSSI variance factor, its leave-one-session-out kNN error as the fix floor
        (``graphslam.core.tracking.calibration``), and the covariance scale from replaying its walks
        under those two (and the walkable ``area`` the tracker will use): noise levels measured on the
        map, not chosen per building. With ``cfg.bank_temper`` None also the heading bank's temper from
        the correlation of consecutive fix errors along the map's walks (``calibration.bank_temper``)."""
        from graphslam.core.tracking.calibration import bank_temper, fix_error_correlation, fix_noise, rssi_variance_factor

        kappa = rssi_variance_factor(rm, models, np.sqrt(model.r_rssi)) if len(models.fitted) else 1.0
        try:
            floor = max(cfg.fix_sigma_floor_m, fix_noise(rm, k=cfg.knn_k, metric=cfg.knn_config().metric).sigma_m)
        except EstimationError as e:  # a one-session map: keep the configured floor
            log.info("track: no leave-one-session-out fix noise (%s)", e)
            floor = cfg.fix_sigma_floor_m
        temper = 1.0
        if cfg.bank_temper is None and cfg.filter == "fixed-lag":  # only the fixed-lag tracker runs a weighted bank
            try:
                temper = bank_temper(fix_error_correlation(rm, k=cfg.knn_k, metric=cfg.knn_config().metric))
            except EstimationError as e:  # a one-session map: the bank's costs as they are
                log.info("track: no fix error correlation (%s)", e)
        half = cls(float(kappa), float(floor), 1.0, temper)
        scale = replay_covariance_scale(rm, *half.apply(model, cfg), area=area) if cfg.replay_sessions > 0 else 1.0
        log.info("track: self-calibration: RSSI variance x %.2f, kNN fix std floor %.2f m, covariance x %.2f, "
                 "heading bank temper %.2f", kappa, floor, scale, temper)
        return cls(float(kappa), float(floor), float(scale), float(temper))

    def apply(self, model: FusionModel, cfg: TrackConfig) -> tuple[FusionModel, TrackConfig]:
        model = dataclasses.replace(model, r_rssi=model.r_rssi * self.rssi_variance_factor)
        cfg = dataclasses.replace(cfg, fix_sigma_floor_m=self.fix_sigma_floor_m, self_calibrate=False,
                                  covariance_scale=cfg.covariance_scale * self.covariance_scale,
                                  bank_temper=self.bank_temper if cfg.bank_temper is None else cfg.bank_temper)
        return model, cfg


def self_calibrated(rm: RadioMap, models: ApModels, model: FusionModel, cfg: TrackConfig) -> tuple[FusionModel, TrackConfig]:
    """``model`` and ``cfg`` with the noise levels measured on the map (``SelfCalibration``)."""
    return SelfCalibration.measure(rm, models, model, cfg).apply(model, cfg)


def replay_covariance_scale(rm: RadioMap, model: FusionModel, cfg: TrackConfig, area: WalkableArea | None = None) -> float:
    """How over-confident is the tracker on this map? Replay (a seeded sample of) the map's own
    walks through it: each walk's fingerprints, at their map positions, become steps (in an
    odometry frame turned by a random angle) and scans; it is tracked on the map without its own
    fingerprints; the 95th percentile of the squared Mahalanobis distances of the map positions
    from the reported ellipses, over chi-square's (5.991), is the factor (>= 1) that makes the
    reported 95 % ellipses hold 95 % of them (a split-conformal calibration on the map, no
    ground truth). The replayed walks have near-perfect odometry, so the factor is a lower bound."""
    from graphslam.core.tracking.calibration import CHI2_2DOF_95, mahalanobis_sq
    from graphslam.core.types import PoseTrack, Scan

    rng = np.random.default_rng(cfg.replay_seed)
    ids, counts = np.unique(rm.session_ids, return_counts=True)
    ids = ids[counts >= 5]
    if len(ids) < 2:
        return 1.0
    ids = rng.permutation(ids)
    bssids, missing = rm.bssids, rm.missing_dbm
    d2 = []
    task = Task("track: self-calibration replay", total=cfg.replay_sessions, unit="segments")
    for n in range(cfg.replay_sessions):  # round robin over the walks: long walks give several segments
        if n:
            task.advance()
        sid = ids[n % len(ids)]
        own = np.flatnonzero(rm.session_ids == sid)
        own = own[np.argsort(rm.t_ns[own], kind="stable")]
        own = own[np.concatenate([[True], np.diff(rm.t_ns[own]) > 0])]
        if len(own) > cfg.replay_max_scans:  # a segment of a tracked walk's length
            start = int(rng.integers(0, len(own) - cfg.replay_max_scans + 1))
            own = own[start : start + cfg.replay_max_scans]
        rest = np.flatnonzero(rm.session_ids != sid)
        if cfg.replay_route_radius_m > 0:
            rest = rest[~np.isin(rm.session_ids[rest], _repeats(rm, own, rest, cfg.replay_route_radius_m))]
        others = RadioMap.from_fingerprints(
            rm.fingerprints.rows(rest), rm.xy[rest], session_ids=rm.session_ids[rest].tolist(), t_ns=rm.t_ns[rest],
            frame=rm.frame, min_rssi_dbm=rm.min_rssi_dbm,
        )
        a = rng.uniform(-math.pi, math.pi)
        R = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        xy = rm.xy[own]
        v = rm.fingerprints.values[own].tocsr()
        scans = tuple(
            Scan(int(rm.t_ns[r]), {bssids[c]: float(x) + missing for c, x in zip(v.indices[v.indptr[i]:v.indptr[i + 1]],
                                                                           v.data[v.indptr[i]:v.indptr[i + 1]])})
            for i, r in enumerate(own.tolist())
        )
        walk = Session(str(sid), PoseTrack(rm.t_ns[own], (xy - xy[0]) @ R.T, np.zeros(len(own))), scans)
        replayed = model
        if model.path_loss.correction is not None:  # the field without the replayed walk's readings, as a new walk's
            index = {b: i for i, b in enumerate(model.path_loss.bssids)}
            heard = np.unique([index[b] for sc in scans for b in sc.readings if b in index]).astype(np.int64)
            replayed = with_residual_field(
                dataclasses.replace(model, path_loss=dataclasses.replace(model.path_loss, correction=None)), others, cfg,
                aps=heard)
        try:
            tr = track_session(walk, replayed, KnnLocator(others, cfg.knn_config()), cfg, area=area)
        except EstimationError:
            continue
        d2.append(mahalanobis_sq(tr.xy - xy, tr.P[:, :2, :2]))
    task.advance()
    task.end()
    if not d2:
        return 1.0
    return max(1.0, float(np.percentile(np.concatenate(d2), 95)) / CHI2_2DOF_95)


def _repeats(rm: RadioMap, own: NDArray[np.int64], rest: NDArray[np.int64], radius_m: float) -> NDArray:
    """Sessions among ``rest`` that walk the path of fingerprints ``own`` again: a fingerprint
    within ``radius_m`` of at least half of its positions (map frame, m). A new walk need not
    follow a surveyed route, so the replay leaves the route's repetitions out too."""
    from scipy.spatial import cKDTree

    pts = cKDTree(rm.xy[own])
    hits = pts.query_ball_point(rm.xy[rest], r=radius_m)
    sid = rm.session_ids[rest]
    covered: dict[str, set[int]] = {}
    for s_, h in zip(sid.tolist(), hits):
        if h:
            covered.setdefault(s_, set()).update(h)
    return np.array([s_ for s_, c in covered.items() if len(c) >= 0.5 * len(own)], dtype=sid.dtype)


def track_files(
    radio_map_path: str | Path,
    session_paths: Iterable[str | Path],
    *,
    ap_models_path: str | Path | None = None,
    out: str | Path | None = None,
    cfg: TrackConfig = TrackConfig(),
    calibration_cache: bool = True,
    floor_plan: str | Path | None = None,
    floor_size: tuple[float, float] | None = None,
) -> TrackRun:
    """Read the radio map, its AP models (``ap_models_path``, else ``ap_models.json`` beside the map,
    else fitted now), the sessions (MCAP); track; write ``out`` (CSV). ``calibration_cache``: keep
    the self-calibration in ``track_calibration.json`` beside the map and reuse it while the map,
    AP models and configuration are the same. ``floor_plan`` (image; ``floor_size`` W H in metres,
    else ``floor_info.json`` beside it): its walkable area constrains the positions
    (``TrackConfig.walkable_mode``); the radio map must be in the plan's site frame."""
    from graphslam.io.apmodel_io import StaleApModelsError, read_ap_models
    from graphslam.io.floor_plan import load_floor_plan, read_walkable_area
    from graphslam.io.mcap_reader import read_survey
    from graphslam.io.radiomap_io import read_radio_map

    plan = load_floor_plan(floor_plan, floor_size)  # bad input fails before any work
    rm = read_radio_map(radio_map_path)
    area = None
    if plan is not None:
        if rm.frame != "site":
            raise ConfigError(
                f"--floor-plan: the radio map {radio_map_path} is in the {rm.frame!r} frame; a floor plan's walkable "
                "area needs a map in the plan's site frame")
        area = read_walkable_area(plan, cfg.walkable_sigma_m)
    beside = Path(radio_map_path).with_name("ap_models.json")
    if ap_models_path is not None:
        models = read_ap_models(ap_models_path, radio_map=rm)  # another map's models: an error
    elif beside.exists():
        try:
            models = read_ap_models(beside, radio_map=rm)
        except StaleApModelsError as e:  # e.g. left by an earlier survey into the same folder
            log.warning("%s; fitting them now", e)
            models = ApModels.fit(rm)
    else:
        log.info("no AP models beside %s: fitting them now", radio_map_path)
        models = ApModels.fit(rm)
    survey = read_survey(list(session_paths))
    cache = key = cached = None
    if cfg.self_calibrate and calibration_cache:
        cache = Path(radio_map_path).with_name(CALIBRATION_FILE)
        models_source = Path(ap_models_path) if ap_models_path is not None else beside if beside.exists() else None
        key = _calibration_key(Path(radio_map_path), models_source, models, cfg, plan.path if plan is not None else None)
        cached = _read_calibration(cache, key)
    tracker = Tracker.on_map(rm, models, cfg, calibration=cached, area=area)
    if cache is not None and cached is None and tracker.calibration is not None:
        _write_calibration(cache, key, tracker.calibration)
    with Task("track", total=sum(len(s.steps) for s in survey.sessions), unit="steps") as task:
        tracks = tuple(tracker.track(s, task) for s in survey.sessions)
    written = write_track_csv(tracks, out) if out is not None else None
    return TrackRun(tracks, written, len(models.fitted))


# Self-calibration kept beside the radio map: measuring it replays the map's walks (~46 s on the
# IPIN floor), the same for every call with the same map, AP models and configuration.
CALIBRATION_FILE = "track_calibration.json"
_CALIBRATION_FORMAT = 2  # 2: with the heading bank's temper


def _calibration_key(
    radio_map: Path, models_source: Path | None, models: ApModels, cfg: TrackConfig, floor_plan: Path | None = None
) -> str:
    """sha256 over what the calibration depends on: the map's bytes, the AP models' (or that they
    were fitted now, from the map), the floor plan's (its walkable area is replayed too), the tracking
    configuration and this graphslam's version."""
    import hashlib
    import json

    from graphslam import __version__

    h = hashlib.sha256()
    h.update(radio_map.read_bytes())
    h.update(models_source.read_bytes() if models_source is not None else f"fitted:{len(models.fitted)}".encode())
    if floor_plan is not None:
        h.update(b"plan:" + floor_plan.read_bytes())
    h.update(json.dumps(dataclasses.asdict(cfg), sort_keys=True, default=str).encode())
    h.update(f"{__version__}/{_CALIBRATION_FORMAT}".encode())
    return h.hexdigest()


def _read_calibration(path: Path, key: str) -> SelfCalibration | None:
    """The calibration kept in ``path`` for ``key``; None (measure it again) when there is none, it
    is for another map or configuration, or the file is damaged (a cache: logged, never an error)."""
    import json

    if not path.is_file():
        return None
    try:
        d = json.loads(path.read_text())
        if d.get("format") != _CALIBRATION_FORMAT or d.get("key") != key:
            log.info("%s: for another map, AP models or configuration: measuring again", path)
            return None
        cal = SelfCalibration(*(float(d[k]) for k in ("rssi_variance_factor", "fix_sigma_floor_m", "covariance_scale",
                                                       "bank_temper")))
    except (OSError, ValueError, TypeError, KeyError, AttributeError) as e:
        log.warning("%s: unreadable (%s): measuring the self-calibration again", path, e)
        return None
    if not all(math.isfinite(v) and v > 0 for v in dataclasses.astuple(cal)) or min(cal.covariance_scale, cal.bank_temper) < 1:
        log.warning("%s: values out of range: measuring the self-calibration again", path)
        return None
    log.info("track: self-calibration from %s", path)
    return cal


def _write_calibration(path: Path, key: str, cal: SelfCalibration) -> None:
    from graphslam.errors import OutputError
    from graphslam.io.atomic import atomic_write_json

    try:
        atomic_write_json(path, {"format": _CALIBRATION_FORMAT, "key": key, **dataclasses.asdict(cal)})
    except (OSError, OutputError) as e:  # a read-only or full map folder: track anyway, measure again next time
        log.warning("%s: cannot keep the self-calibration (%s)", path, e)
