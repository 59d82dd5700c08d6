"""Tracking walks on a radio map (steps + WiFi RSSI + kNN fixes): ``Tracker`` and its self-calibration.

No file I/O (``graphslam.app.track`` reads the map and the walks and writes the tracks). The
configuration is ``graphslam.tracking_config.TrackConfig`` (sections named below).

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

import dataclasses
import logging
import math
import zlib
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from graphslam.core.progress import Task
from graphslam.core.radiomap.knn import KnnConfig, KnnLocator
from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.core.radiomap.uncertainty import map_uncertainty
from graphslam.core.tracking.apmodel import ApModels
from graphslam.core.tracking.axes import WalkAxes
from graphslam.core.tracking.filters import (
    Epochs, FusionModel, GaussianState, KalmanFilter, make_filter, position_update, run_epochs,
)
from graphslam.core.tracking.fixed_lag import FixedLagConfig, fixed_lag_smooth
from graphslam.core.tracking.particle import (
    PARTICLE_TEMPERATURE, ParticleConfig, RssiReadings, run_particle_filter, scan_matches,
)
from graphslam.core.tracking.smoother import smooth
from graphslam.core.tracking.walkable import WalkableArea
from graphslam.core.types import Session
from graphslam.errors import EstimationError
from graphslam.tracking_config import DEFAULTS, TrackConfig

log = logging.getLogger(__name__)


def walk_axes_of(cfg: TrackConfig, rm: RadioMap) -> WalkAxes | None:
    """The walk-axes prior measured on ``rm``'s own walks (None: off, or no axes there)."""
    if not cfg.walk_axes.enabled:
        return None
    return WalkAxes.from_walks(rm.xy, rm.session_ids, rm.t_ns, sigma_mps=cfg.walk_axes.sigma_mps,
                               min_concentration=cfg.walk_axes.min_concentration)


def walkable_area(cfg: TrackConfig, area: WalkableArea | None) -> WalkableArea | None:
    """``area`` with the configuration's std (None stays None)."""
    if area is None or area.sigma_m == cfg.floor_plan.sigma_m:
        return area
    return dataclasses.replace(area, sigma_m=cfg.floor_plan.sigma_m)


def knn_config(cfg: TrackConfig) -> KnnConfig:
    """The kNN fixes' search (and the particle filter's scan matches). Exact: a walk's scans are a
    small batch, and the self-calibration builds a locator per replayed walk (an IVF index each)."""
    return KnnConfig(k=cfg.knn_fixes.k, metric=cfg.knn_fixes.metric, index="exact")


def particle_config(cfg: TrackConfig, area_m2: float = 1.0, seed: int = 0) -> ParticleConfig:
    """The particle filter's settings; ``seed`` is mixed with ``particle.seed``."""
    p = cfg.particle
    return ParticleConfig(
        n_particles=p.count, top_k=p.top_k,
        temperature=PARTICLE_TEMPERATURE[cfg.knn_fixes.metric] if p.temperature is None else p.temperature,
        kernel_m=p.kernel_m, outlier=p.outlier, area_m2=area_m2, lag_s=cfg.fixed_lag.lag_s,
        huber_k=cfg.filter.gate_sigma, seed=p.seed ^ seed,
    )


_SWAP = np.array([[0.0, 1.0], [1.0, 0.0]])




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
    # per step: from a place the map's walks have not been (``with_outside``); None: the map has no outside test
    outside: NDArray[np.bool_] | None = None
    outside_score: NDArray[np.float64] | None = None  # per step: 0-1 (``OutsideTest``)

    @property
    def xy(self) -> NDArray[np.float64]:
        return self.x[:, :2]


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
        cls, rm: RadioMap, models: ApModels, cfg: TrackConfig = DEFAULTS, calibration: SelfCalibration | None = None,
        area: WalkableArea | None = None,
    ) -> "Tracker":
        """``calibration``: one measured on this map with this ``cfg`` before (else measured now);
        ``area``: the floor's walkable area in the map's frame (``TrackConfig.walkable_mode``)."""
        if models.frame != rm.frame:
            raise EstimationError(f"track: AP models are in frame {models.frame!r}, radio map in {rm.frame!r}")
        model = fusion_model(models, cfg)
        if cfg.rssi.enabled and cfg.rssi.field_m > 0:
            with Task("track: RSSI field"):
                # the readings' leave-one-walk-out noise is only logged (~0.7 s on a small map): at INFO only
                model = with_residual_field(model, rm, cfg, leave_out=log.isEnabledFor(logging.INFO))
        area = walkable_area(cfg, area)  # once: its distance field is rebuilt for another std
        if not cfg.calibration.enabled:
            calibration = None
        elif calibration is None:
            calibration = SelfCalibration.measure(rm, models, model, cfg, area)
        if calibration is not None:
            model, cfg = calibration.apply(model, cfg)
        if cfg.walk_axes.enabled and (cfg.filter.kind == "fixed-lag" or cfg.filter.smoother == "map"):
            axes = walk_axes_of(cfg, rm)
            if axes is None:
                log.info("track: walk axes: none on this map (concentration below %.2f)", cfg.walk_axes.min_concentration)
            else:
                log.info("track: walk axes at %.1f deg + k 90 deg (concentration %.2f)", math.degrees(axes.angle_rad), axes.concentration)
        if area is not None:
            log.info("track: walkable area from the floor plan: %.0f %% of %.0f x %.0f m (%s)",
                     100 * area.fraction_walkable(), area.width_m, area.height_m, cfg.floor_plan.mode)
        locator = KnnLocator(rm, knn_config(cfg))
        # the outside test of the fixes' kNN (``with_outside``): the map's stored calibration, else measured now
        locator.uncertainty = map_uncertainty(rm, locator.config)
        return cls(model, locator, cfg, calibration, area)

    def track(self, session: Session, progress: Task | None = None) -> SessionTrack:
        return track_session(session, self.model, self.locator, self.cfg, progress, self.area)

    def track_all(self, sessions: Sequence[Session]) -> tuple[SessionTrack, ...]:
        """Every session in turn, as one ``track`` task over their steps (its detail: which session)."""
        out = []
        with Task("track", total=sum(len(s.steps) for s in sessions), unit="steps") as task:
            for i, s in enumerate(sessions):
                task.advance(0, info=f"session {i + 1}/{len(sessions)}: {s.session_id}")
                out.append(self.track(s, task))
        return tuple(out)


def fusion_model(models: ApModels, cfg: TrackConfig) -> FusionModel:
    """The papers' model with theta in the state, noise per second (``period_s`` = 1)."""
    pl = models.path_loss()
    sig = np.array([max(a.sigma_db, cfg.rssi.sigma_floor_db) for a in models.fitted])
    return FusionModel(
        pl,
        q_diag=np.array([cfg.motion.q_position] * 2 + [cfg.motion.q_velocity] * 2 + [cfg.motion.q_bias] * 2 + [cfg.motion.q_theta]),
        r_velocity=np.full(2, cfg.motion.velocity_sigma_mps**2),
        r_rssi=sig**2,
        period_s=1.0,
        theta_rad=None,
    )


def with_residual_field(model: FusionModel, rm: RadioMap, cfg: TrackConfig, *, aps: NDArray | None = None,
                        leave_out: bool = False) -> FusionModel:
    """``model`` with its AP models' residual field measured on ``rm`` (``cfg.rssi.field_m``; the
    model as it is when 0). The RSSI noise stays the law's (``rssi_field``). ``aps``: only these APs
    corrected; ``leave_out``: also log the readings' leave-one-walk-out noise around the field."""
    if cfg.rssi.field_m <= 0 or not len(model.path_loss):
        return model
    from graphslam.core.tracking.apmodel import residual_field

    fit = residual_field(rm, model.path_loss, bandwidth_m=cfg.rssi.field_m, shrink=cfg.rssi.field_shrink,
                         leave_out=leave_out, aps=aps)
    if leave_out:
        ok = np.isfinite(fit.sigma_db)
        if ok.any():
            log.info("track: RSSI field (%.1f m): the map's readings scatter %.1f dB around it, %.1f dB around the law "
                     "(median over %d APs, each map walk left out)", cfg.rssi.field_m, float(np.median(fit.sigma_db[ok])),
                     float(np.median(fit.sigma_law_db[ok])), int(ok.sum()))
    return dataclasses.replace(model, path_loss=dataclasses.replace(model.path_loss, correction=fit.field))


def track_sessions(
    sessions: Sequence[Session], rm: RadioMap, models: ApModels, cfg: TrackConfig = DEFAULTS
) -> tuple[SessionTrack, ...]:
    """Track every session on ``rm`` with the AP models ``models`` (same frame as ``rm``)."""
    return Tracker.on_map(rm, models, cfg).track_all(sessions)


def track_session(
    session: Session, model: FusionModel, locator: KnnLocator, cfg: TrackConfig = DEFAULTS,
    progress: Task | None = None, area: WalkableArea | None = None,
) -> SessionTrack:
    """Track one session (see module docstring). ``EstimationError`` if it has < 2 steps or no scan
    the radio map can locate. Covariances come out multiplied by ``cfg.calibration.covariance_scale``;
    ``progress`` advances by one per step. ``area``: the floor's walkable area in the radio map's
    frame, used as ``cfg.floor_plan.mode`` says (the prior: fixed-lag and ``--smooth map`` only)."""
    tr = _track_session(session, model, locator, cfg, progress, area if cfg.floor_plan.mode in ("prior", "both") else None)
    if cfg.calibration.covariance_scale != 1.0:
        tr = dataclasses.replace(tr, P=tr.P * cfg.calibration.covariance_scale)
    if area is not None and cfg.floor_plan.mode in ("snap", "both"):
        x = tr.x.copy()
        x[:, :2] = area.snap(x[:, :2])  # covariance kept: the snap does not make the estimate surer
        tr = dataclasses.replace(tr, x=x)
    return with_outside(tr, session, locator)


def with_outside(tr: SessionTrack, session: Session, locator: KnnLocator) -> SessionTrack:
    """``tr`` with each step's outside flag and score: those of the walk's latest scan at or before
    the step (its first scan for the steps before it), by the outside test of ``locator.uncertainty``
    (``graphslam.core.radiomap.knn_types.OutsideTest``); a scan the map cannot locate at all is
    outside (score 1). An outside step's position covariance is widened to at least the test's
    ``sigma_m`` squared in every direction: a step where the map has not walked does not claim a
    small ellipse. ``tr`` as it is when the map has no outside test or the walk no scan."""
    u = locator.uncertainty
    if u is None or u.outside is None or not session.scans:
        return tr
    scans = sorted(session.scans, key=lambda sc: sc.t_ns)
    res = locator.locate([sc.readings for sc in scans])
    flags = np.where(res.valid, u.outside.flags(res.rss_diff_db), True)
    scores = np.where(res.valid, u.outside.scores(res.rss_diff_db), 1.0)
    j = np.maximum(np.searchsorted(np.array([sc.t_ns for sc in scans], np.int64), tr.t_ns, side="right") - 1, 0)
    out, score = flags[j], scores[j]
    P = tr.P
    if out.any():
        P = P.copy()
        w, V = np.linalg.eigh(P[out, :2, :2])
        w = np.maximum(w, u.outside.sigma_m**2)
        P[out, :2, :2] = np.einsum("nij,nj,nkj->nik", V, w, V)
    return dataclasses.replace(tr, P=P, outside=out, outside_score=score)


def _track_session(
    session: Session, model: FusionModel, locator: KnnLocator, cfg: TrackConfig, progress: Task | None,
    area: WalkableArea | None = None,
) -> SessionTrack:
    steps = session.steps
    if len(steps) < 2:
        raise EstimationError(f"track: session {session.session_id} has {len(steps)} steps (need 2)")
    if cfg.filter.kind == "particle":
        tr = _track_particles(session, model, locator, cfg)
        if progress is not None:
            progress.advance(len(steps))
        return tr
    filt: KalmanFilter = make_filter("ekf" if cfg.filter.kind == "fixed-lag" else cfg.filter.kind, model, w0=cfg.filter.ukf_w0)
    bssids = model.path_loss.bssids
    meas = _scan_measurements(session, bssids, locator.radio_map.min_rssi_dbm, cfg.rssi.enabled)
    fix = locator.locate([sc.readings for sc in session.scans]) if session.scans else None
    ok = np.flatnonzero(fix.valid) if fix is not None else np.zeros(0, int)
    if not len(ok):
        raise EstimationError(f"track: session {session.session_id}: no scan could be located on the radio map")
    p0 = fix.xy[ok[0]]
    fixes: dict[int, tuple[NDArray, float]] = {}  # scan time -> (kNN position, std)
    if cfg.knn_fixes.enabled:
        for i in ok[1:]:  # the first fix is the start position already
            sigma = float(np.nan_to_num(fix.spread[i], nan=0.0))
            fixes[session.scans[i].t_ns] = (fix.xy[i], max(sigma, cfg.knn_fixes.sigma_floor_m))
    t = steps.t_ns
    v_odo = np.diff(steps.xy, axis=0) / (np.diff(t)[:, None] / 1e9)
    y_v = v_odo @ _SWAP.T
    walked = np.linalg.norm(v_odo, axis=1) <= cfg.motion.max_step_speed_mps
    if not walked.all():
        log.info("track: session %s: %d step interval(s) faster than %.1f m/s skipped (odometry jumps)",
                 session.session_id, int((~walked).sum()), cfg.motion.max_step_speed_mps)
    H = cfg.motion.n_theta_hypotheses
    P0 = np.diag(
        [cfg.motion.init_position_sigma_m**2] * 2 + [cfg.motion.init_velocity_sigma_mps**2] * 2
        + [cfg.motion.init_bias_sigma_mps**2] * 2 + [(math.pi / H) ** 2]
    )
    starts = [np.array([p0[0], p0[1], 0, 0, 0, 0, 2 * math.pi * h / H]) for h in range(H)]
    windowed = cfg.filter.kind == "fixed-lag" or cfg.filter.smoother == "map"  # the MAP problems that hold priors
    axes = walk_axes_of(cfg, locator.radio_map) if windowed else None
    area = walkable_area(cfg, area) if windowed else None
    if cfg.filter.kind == "fixed-lag" and cfg.filter.smoother == "none":
        return _track_fixed_lag(session.session_id, model, starts, P0, t, y_v, walked, meas, fixes, cfg, axes, area,
                                progress)
    states = [GaussianState(x0, P0) for x0 in starts]
    ll = np.zeros(H)
    penalty = 0.5 * cfg.filter.gate_sigma**2  # a gated reading costs at least what a 'gate_sigma' one would
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
                    s, rss, use_velocity=False, ap_idx=idx, gate_sigma=cfg.filter.gate_sigma, adaptive_rssi=cfg.rssi.adaptive
                )
                ll[h] += info.loglik - penalty * info.n_gated
                used[h] += info.n_used
                gated[h] += info.n_gated
                if ts in fixes:
                    states[h], info = position_update(states[h], *fixes[ts], gate_sigma=cfg.filter.gate_sigma)
                    ll[h] += info.loglik - penalty * info.n_gated
            t_now = ts
            j += 1
        dt = (t[k + 1] - t_now) / 1e9
        states = [filt.predict(s, dt) for s in states]
    if cfg.filter.smoother == "none":
        return SessionTrack(
            session.session_id, t.copy(), np.array(xs), np.array(Ps), np.array(best, np.int64),
            int(used[best[-1]]), int(gated[best[-1]]),
        )
    h = best[-1]
    x0 = np.array([p0[0], p0[1], 0, 0, 0, 0, 2 * math.pi * h / H])
    epochs, step_epoch = _session_epochs(t, y_v, walked, meas, fixes)
    filtered = run_epochs(filt, x0, P0, epochs, gate_sigma=cfg.filter.gate_sigma)
    sm = smooth(model, x0, P0, epochs, filtered, cfg.filter.smoother, huber_k=cfg.filter.gate_sigma, axes=axes, area=area)
    return SessionTrack(
        session.session_id, t.copy(), sm.x[step_epoch], sm.P[step_epoch], np.full(len(t), h, np.int64),
        filtered.n_rssi_used, filtered.n_rssi_gated,
    )


def _track_fixed_lag(
    session_id: str, model: FusionModel, starts: list[NDArray], P0: NDArray, t: NDArray[np.int64], y_v: NDArray,
    walked: NDArray[np.bool_], meas: Sequence[tuple[int, NDArray, NDArray]], fixes: dict[int, tuple[NDArray, float]],
    cfg: TrackConfig, axes: WalkAxes | None = None, area: WalkableArea | None = None, progress: Task | None = None,
) -> SessionTrack:
    """The fixed-lag smoother over the session's epochs; a step interval's velocity is known at its
    end step (``vel_available_s``), so a lag of 0 reports each step from the data up to it.
    ``progress`` advances by one per step as the stream passes it."""
    epochs, step_epoch = _session_epochs(t, y_v, walked, meas, fixes)
    avail = epochs.t_s[step_epoch[1:][walked]]
    passed = [0]  # steps reported to ``progress`` so far

    def streamed(n_epochs: int) -> None:
        steps = int(np.searchsorted(step_epoch, n_epochs - 1, side="right"))
        if progress is not None and steps > passed[0]:
            progress.advance(steps - passed[0])
            passed[0] = steps

    run = fixed_lag_smooth(
        model, starts, P0, epochs,
        FixedLagConfig(
            lag_s=cfg.fixed_lag.lag_s, window_s=max(cfg.fixed_lag.window_s, cfg.fixed_lag.lag_s), huber_k=cfg.filter.gate_sigma, prune_cost=cfg.fixed_lag.prune_cost,
            merge_tol=cfg.fixed_lag.merge_tol,
            adaptive_rssi=cfg.rssi.adaptive, report=cfg.fixed_lag.bank_report, angle_index=None if model.theta_rad is not None else 6,
            temper=1.0 if cfg.fixed_lag.bank_temper is None else cfg.fixed_lag.bank_temper,
        ),
        vel_available_s=avail, axes=axes, area=area, progress=streamed if progress is not None else None,
    )
    if progress is not None and passed[0] < len(t):
        progress.advance(len(t) - passed[0])
    P = run.P * (run.variance_factor[:, None, None] if cfg.fixed_lag.calibrate_covariance else 1.0)
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
        idx, dist = scan_matches(locator.distances(rm.encode([sc.readings for sc in scans])), cfg.particle.top_k)
    else:
        idx, dist = np.full((len(scans), 0), -1, np.int64), np.zeros((len(scans), 0))
    t_s = (steps.t_ns - t0) / 1e9
    walked = np.linalg.norm(np.diff(steps.xy, axis=0), axis=1) / np.maximum(np.diff(t_s), 1e-9) <= cfg.motion.max_step_speed_mps
    rssi = None
    if cfg.rssi.enabled and len(model.path_loss):
        meas = _scan_measurements(session, model.path_loss.bssids, rm.min_rssi_dbm)  # time order, as ``scans``
        rssi = RssiReadings(model.path_loss, np.sqrt(model.r_rssi), [m[1] for m in meas], [m[2] for m in meas])
    pcfg = particle_config(cfg, _area_m2(rm), zlib.crc32(session.session_id.encode()))
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
    return SessionTrack(session.session_id, steps.t_ns.copy(), x, P, np.zeros(n, np.int64), run.rssi_used, 0)


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
        map, not chosen per building. With ``cfg.fixed_lag.bank_temper`` None also the heading bank's temper from
        the correlation of consecutive fix errors along the map's walks (``calibration.bank_temper``)."""
        from graphslam.core.tracking.calibration import (
            bank_temper, fix_error_correlation, fix_noise, leave_one_session_out_error_vectors, rssi_variance_factor,
        )

        # four parts; the replay (the longest) reports its own segments
        with Task("track: self-calibration", total=4, unit="parts", info="RSSI variance") as task:
            kappa = rssi_variance_factor(rm, models, np.sqrt(model.r_rssi)) if len(models.fitted) else 1.0
            task.advance(info="kNN fix noise")
            knn = dict(k=cfg.knn_fixes.k, metric=knn_config(cfg).metric)
            vectors = None
            if len(rm) <= 3000 and len(set(rm.session_ids.tolist())) >= 2:  # both statistics below locate every fingerprint: once
                vectors = leave_one_session_out_error_vectors(rm, **knn)
            try:
                floor = max(cfg.knn_fixes.sigma_floor_m, fix_noise(rm, **knn, vectors=vectors).sigma_m)
            except EstimationError as e:  # a one-session map: keep the configured floor
                log.info("track: no leave-one-session-out fix noise (%s)", e)
                floor = cfg.knn_fixes.sigma_floor_m
            task.advance(info="heading bank temper")
            temper = 1.0
            if cfg.fixed_lag.bank_temper is None and cfg.filter.kind == "fixed-lag":  # only the fixed-lag tracker runs a weighted bank
                try:
                    temper = bank_temper(fix_error_correlation(rm, **knn, vectors=vectors))
                except EstimationError as e:  # a one-session map: the bank's costs as they are
                    log.info("track: no fix error correlation (%s)", e)
            task.advance(info="replaying the map's walks")
            half = cls(float(kappa), float(floor), 1.0, temper)
            # the online tracker's replay: an offline smoother takes its filter's calibration (one
            # calibration kept per map and filter, ``calibration_config``), not a replay of its own
            online = calibration_config(cfg)
            scale = replay_covariance_scale(rm, *half.apply(model, online), area=area) if cfg.calibration.replay_sessions > 0 else 1.0
            task.advance(info="")  # done: the replay's own line said it
        log.info("track: self-calibration: RSSI variance x %.2f, kNN fix std floor %.2f m, covariance x %.2f, "
                 "heading bank temper %.2f", kappa, floor, scale, temper)
        return cls(float(kappa), float(floor), float(scale), float(temper))

    def apply(self, model: FusionModel, cfg: TrackConfig) -> tuple[FusionModel, TrackConfig]:
        model = dataclasses.replace(model, r_rssi=model.r_rssi * self.rssi_variance_factor)
        cfg = cfg.updated({
            "knn_fixes.sigma_floor_m": self.fix_sigma_floor_m, "calibration.enabled": False,
            "calibration.covariance_scale": cfg.calibration.covariance_scale * self.covariance_scale,
            "fixed_lag.bank_temper": self.bank_temper if cfg.fixed_lag.bank_temper is None else cfg.fixed_lag.bank_temper,
        })
        return model, cfg


def calibration_config(cfg: TrackConfig) -> TrackConfig:
    """What the self-calibration depends on of ``cfg``: all of it but the offline smoother (the
    smoothers post-process their filter's run, so ``--smooth`` reuses the filter's calibration)."""
    return cfg if cfg.filter.smoother == "none" else cfg.updated({"filter.smoother": "none"})


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

    rng = np.random.default_rng(cfg.calibration.replay_seed)
    ids, counts = np.unique(rm.session_ids, return_counts=True)
    ids = ids[counts >= 5]
    if len(ids) < 2:
        return 1.0
    ids = rng.permutation(ids)
    bssids, missing = rm.bssids, rm.missing_dbm
    d2 = []
    task = Task("track: self-calibration replay", total=cfg.calibration.replay_sessions, unit="segments")
    for n in range(cfg.calibration.replay_sessions):  # round robin over the walks: long walks give several segments
        if n:
            task.advance()
        sid = ids[n % len(ids)]
        own = np.flatnonzero(rm.session_ids == sid)
        own = own[np.argsort(rm.t_ns[own], kind="stable")]
        own = own[np.concatenate([[True], np.diff(rm.t_ns[own]) > 0])]
        if len(own) > cfg.calibration.replay_max_scans:  # a segment of a tracked walk's length
            start = int(rng.integers(0, len(own) - cfg.calibration.replay_max_scans + 1))
            own = own[start : start + cfg.calibration.replay_max_scans]
        rest = np.flatnonzero(rm.session_ids != sid)
        if cfg.calibration.replay_route_radius_m > 0:
            rest = rest[~np.isin(rm.session_ids[rest], _repeats(rm, own, rest, cfg.calibration.replay_route_radius_m))]
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
            tr = track_session(walk, replayed, KnnLocator(others, knn_config(cfg)), cfg, area=area)
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
