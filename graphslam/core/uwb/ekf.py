"""The collaborative UWB EKF of Paper 003, section IV-C, for many tags at once.

State per tag: planar position and velocity x = (p_x, p_y, v_x, v_y) in the site frame (m,
m/s). The paper's filter has three translation axes; tags here live on one floor at a known
height, so the vertical axis is dropped (anchors keep their height in the range model).

- Transition (eq. 7): F = [[I, dt I], [0, I]], first order (constant velocity).
- Process noise (eq. 12): Q = dt * diag(q_p I, q_v I): confidence in the model decays in
  proportion to the time since the last update.
- Trilateration (eq. 13), when >= 3 anchors answer in one slot: z = the least-squares
  position of those ranges (``ranging.trilaterate``), H = [I 0], R = sigma_tri^2 I.
- Range to an anchor or a neighbour (eq. 14): h(x) = |(p, z_tag) - q|, H = [u^T, 0] with
  u = (p - q) / h the unit line of sight; residual z - h(x_pred).
- Range noise: for an anchor (hard-coded, surveyed position) R = sigma_r^2; the paper lets it
  grow with the time since the range was taken, which is nil here: every range is fused in the
  slot that measured it. For a neighbour
  (eq. 15) its position is an estimate: R = kappa(P_j) sigma_r^2 + u^T P_j u, kappa the
  condition number of the neighbour's position covariance (the paper's confidence indicator;
  the paper's exact expression did not survive in our copy). The second term, the
  neighbour's variance along the line of sight, is ours: without it a neighbour whose estimate
  is isotropically poor (kappa = 1) would count as much as an anchor.
- Residual bound: a range whose residual exceeds ``residual_bound_m`` (plus 3 sigma of the
  predicted range) is rejected (the paper "bounds the accepted readings"), as is a
  trilateration whose RMS exceeds its own bound. A trilateration that fits its ranges but lies
  outside the filter's 99 % ellipse restarts the filter there (a tag that drifted in a zone
  without anchors is found again when it sees three; ours, the paper does not say).
- No measurement: prediction only (the state drifts with its last velocity; its covariance grows
  with Q).

Decision flow per slot (the paper's Fig. 3): >= 3 anchors -> trilateration; else each anchor
range, then each neighbour range (neighbours only without trilateration: it is the least
precise input). The label of a slot is its best accepted input: trilateration > anchor >
neighbour > none. A tag's filter starts at its first trilateration (before it, its slots give
no estimate).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from graphslam.core.types import Session
from graphslam.core.uwb.ranging import trilaterate
from graphslam.errors import EstimationError

MEASUREMENT_TYPES = ("none", "neighbour", "anchor", "trilateration")
CHI2_2DOF_99 = 9.21  # 99 % quantile of chi-square with 2 degrees of freedom
NONE, NEIGHBOUR, ANCHOR, TRILATERATION = range(4)


@dataclass(frozen=True)
class UwbEkfConfig:
    """Noise and bounds (SI units; process noise per second). Defaults chosen on seeds 0-3 of the
    simulated seven-tag experiment (docs/uwb.md): walkers at 0.5-1 m/s who stop at goals."""

    q_position: float = 0.002  # m^2/s
    q_velocity: float = 0.1  # (m/s)^2/s: walkers turn and stop (zone A within 2 mm for 0.05-0.5)
    sigma_trilateration_m: float = 0.05  # eq. 13 (the paper measured its doPositioning standing still)
    sigma_range_m: float = 0.1  # eq. 14: the simulated LOS noise is 0.05; 0.1 did better in zones B-D
    residual_bound_m: float = 0.5  # range residuals beyond this (+ the prediction's 3 sigma) are rejected
    trilateration_max_rms_m: float = 0.25  # a trilateration fitting its ranges worse is not used
    init_velocity_sigma_mps: float = 1.0
    tag_height_m: float = 1.0  # every tag's antenna height (m, site frame)
    neighbour_los_variance: bool = True  # add u^T P_j u to a neighbour range's R (see module docstring)

    def __post_init__(self) -> None:
        vals = (self.q_position, self.q_velocity, self.sigma_trilateration_m, self.sigma_range_m,
                self.residual_bound_m, self.trilateration_max_rms_m, self.init_velocity_sigma_mps)
        if not all(np.isfinite(v) and v > 0 for v in vals):
            raise EstimationError("UWB EKF: noise levels and bounds must be finite and > 0")


@dataclass
class TagState:
    """One tag's Gaussian estimate at time ``t_ns``: x (4,), P (4, 4)."""

    t_ns: int
    x: NDArray[np.float64]
    P: NDArray[np.float64]


def transition(dt: float) -> NDArray[np.float64]:
    """Eq. 7: [[I, dt I], [0, I]]."""
    F = np.eye(4)
    F[0, 2] = F[1, 3] = dt
    return F


def process_noise(dt: float, cfg: UwbEkfConfig) -> NDArray[np.float64]:
    """Eq. 12: Q grows in proportion to the elapsed time."""
    return dt * np.diag([cfg.q_position, cfg.q_position, cfg.q_velocity, cfg.q_velocity])


def predict(s: TagState, t_ns: int, cfg: UwbEkfConfig) -> TagState:
    """Eq. 8 (prediction to ``t_ns``; a time before the state's is not allowed)."""
    dt = (t_ns - s.t_ns) / 1e9
    if dt < 0:
        raise EstimationError(f"UWB EKF: prediction back in time ({dt:.3f} s)")
    F = transition(dt)
    return TagState(t_ns, F @ s.x, F @ s.P @ F.T + process_noise(dt, cfg))


def kalman_update(s: TagState, residual: NDArray, H: NDArray, R: NDArray) -> TagState:
    """Eq. 9-11 with the Joseph form (keeps P symmetric positive definite)."""
    S = H @ s.P @ H.T + R
    K = np.linalg.solve(S, H @ s.P).T
    IKH = np.eye(4) - K @ H
    P = IKH @ s.P @ IKH.T + K @ R @ K.T
    return TagState(s.t_ns, s.x + K @ residual, 0.5 * (P + P.T))


def position_update(s: TagState, xy: NDArray, sigma_m: float) -> TagState:
    """Eq. 13: a trilaterated position, H = [I 0], R = sigma^2 I."""
    H = np.zeros((2, 4))
    H[0, 0] = H[1, 1] = 1.0
    return kalman_update(s, np.asarray(xy, float) - s.x[:2], H, sigma_m**2 * np.eye(2))


def range_model(x: NDArray, ref_xy: NDArray, dz: float) -> tuple[float, NDArray[np.float64]]:
    """h(x) = |(p, 0) - (q, dz)| and its Jacobian row H = [u^T, 0, 0] (eq. 14)."""
    d = x[:2] - np.asarray(ref_xy, float)
    h = float(np.sqrt(d @ d + dz * dz))
    H = np.zeros(4)
    H[:2] = d / max(h, 1e-9)
    return h, H


def range_update(
    s: TagState, ref_xy: NDArray, dz: float, z: float, variance: float, bound_m: float
) -> tuple[TagState, bool]:
    """Eq. 14 update with range ``z`` to a point at ``ref_xy`` (``dz`` above the tag); rejected
    (state unchanged, False) when the residual exceeds ``bound_m`` plus three standard deviations
    of the predicted range (a filter that has drifted for a while must still accept ranges)."""
    h, H = range_model(s.x, ref_xy, dz)
    if abs(z - h) > bound_m + 3.0 * float(np.sqrt(H @ s.P @ H)):
        return s, False
    return kalman_update(s, np.array([z - h]), H[None, :], np.array([[variance]])), True


def condition_number(P2: NDArray) -> float:
    """kappa = lambda_max / lambda_min of a 2x2 covariance (eq. 15's confidence indicator)."""
    ev = np.linalg.eigvalsh(0.5 * (P2 + P2.T))
    return float(ev[-1] / max(ev[0], 1e-12))


def neighbour_range_variance(P_j: NDArray, u: NDArray, cfg: UwbEkfConfig) -> float:
    """Eq. 15 (see the module docstring): kappa(P_j) sigma_r^2 [+ u^T P_j u]."""
    Pj = np.asarray(P_j, float)[:2, :2]
    v = condition_number(Pj) * cfg.sigma_range_m**2
    if cfg.neighbour_los_variance:
        v += float(u @ Pj @ u)
    return v


@dataclass(frozen=True)
class UwbEpoch:
    """The ranges one tag completed in one TDMA slot (``t_ns``: when, on the shared clock)."""

    tag: str
    t_ns: int
    anchor_ids: tuple[str, ...] = ()
    anchor_ranges: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    peer_ids: tuple[str, ...] = ()
    peer_ranges: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))

    @property
    def empty(self) -> bool:
        return not self.anchor_ids and not self.peer_ids


@dataclass(frozen=True, eq=False)
class TagTrack:
    """A tag's estimate after every processed slot: x (N, 4), P (N, 4, 4), ``kind`` (N,) the
    slot's measurement type (index into ``MEASUREMENT_TYPES``)."""

    tag: str
    t_ns: NDArray[np.int64]
    x: NDArray[np.float64]
    P: NDArray[np.float64]
    kind: NDArray[np.int8]
    rejected: int  # ranges (or trilaterations) refused by the residual bounds
    skipped_before_start: int  # slots before the first trilateration
    restarts: int  # trilaterations that restarted a lost filter


def _trilateration_start(ep: UwbEpoch, anchors: Mapping[str, NDArray], cfg: UwbEkfConfig) -> NDArray | None:
    if len(ep.anchor_ids) < 3:
        return None
    tri = trilaterate(
        np.array([anchors[a] for a in ep.anchor_ids]), ep.anchor_ranges, cfg.sigma_range_m,
        tag_height_m=cfg.tag_height_m,
    )
    return tri.xy if tri.ok and tri.rms_m <= cfg.trilateration_max_rms_m else None


def _initial_cov(cfg: UwbEkfConfig) -> NDArray[np.float64]:
    return np.diag([cfg.sigma_trilateration_m**2] * 2 + [cfg.init_velocity_sigma_mps**2] * 2)


def _dz(anchor: NDArray, cfg: UwbEkfConfig) -> float:
    return float(anchor[2]) - cfg.tag_height_m if len(anchor) == 3 else 0.0


def track_tags(
    epochs: Sequence[UwbEpoch], anchors: Mapping[str, Sequence[float]], cfg: UwbEkfConfig = UwbEkfConfig()
) -> dict[str, TagTrack]:
    """Run every tag's filter over ``epochs`` in time order (the order a live network would see
    them). A neighbour range uses the neighbour's estimate predicted to that instant, as the
    neighbour would broadcast it; a neighbour not yet started is not used."""
    anc = {k: np.asarray(v, float) for k, v in anchors.items()}
    states: dict[str, TagState] = {}
    rows: dict[str, list[tuple[int, NDArray, NDArray, int]]] = {}
    rejected: dict[str, int] = {}
    skipped: dict[str, int] = {}
    restarts: dict[str, int] = {}
    for ep in sorted(epochs, key=lambda e: (e.t_ns, e.tag)):
        rows.setdefault(ep.tag, [])
        rejected.setdefault(ep.tag, 0)
        skipped.setdefault(ep.tag, 0)
        restarts.setdefault(ep.tag, 0)
        s = states.get(ep.tag)
        if s is None:
            p0 = _trilateration_start(ep, anc, cfg)
            if p0 is None:
                skipped[ep.tag] += 1
                continue
            s = TagState(ep.t_ns, np.array([p0[0], p0[1], 0.0, 0.0]), _initial_cov(cfg))
            states[ep.tag] = s
            rows[ep.tag].append((ep.t_ns, s.x.copy(), s.P.copy(), TRILATERATION))
            continue
        s = predict(s, ep.t_ns, cfg)
        kind = NONE
        if len(ep.anchor_ids) >= 3:
            tri = trilaterate(
                np.array([anc[a] for a in ep.anchor_ids]), ep.anchor_ranges, cfg.sigma_range_m,
                tag_height_m=cfg.tag_height_m, start=s.x[:2],
            )
            if tri.ok and tri.rms_m <= cfg.trilateration_max_rms_m:
                nu = tri.xy - s.x[:2]
                S = s.P[:2, :2] + cfg.sigma_trilateration_m**2 * np.eye(2)
                if float(nu @ np.linalg.solve(S, nu)) <= CHI2_2DOF_99:
                    s = position_update(s, tri.xy, cfg.sigma_trilateration_m)
                else:  # the filter lost itself: start again from the trilateration
                    s = TagState(ep.t_ns, np.array([tri.xy[0], tri.xy[1], 0.0, 0.0]), _initial_cov(cfg))
                    restarts[ep.tag] += 1
                kind = TRILATERATION
            else:
                rejected[ep.tag] += 1
        if kind != TRILATERATION:
            for aid, z in zip(ep.anchor_ids, ep.anchor_ranges.tolist()):
                a = anc[aid]
                s, ok = range_update(s, a[:2], _dz(a, cfg), z, cfg.sigma_range_m**2, cfg.residual_bound_m)
                kind = max(kind, ANCHOR) if ok else kind
                rejected[ep.tag] += int(not ok)
            for pid, z in zip(ep.peer_ids, ep.peer_ranges.tolist()):
                n = states.get(pid)
                if n is None or pid == ep.tag:
                    continue
                n_now = predict(n, ep.t_ns, cfg) if ep.t_ns >= n.t_ns else n
                _, H = range_model(s.x, n_now.x[:2], 0.0)
                var = neighbour_range_variance(n_now.P, H[:2], cfg)
                s, ok = range_update(s, n_now.x[:2], 0.0, z, var, cfg.residual_bound_m)
                kind = max(kind, NEIGHBOUR) if ok else kind
                rejected[ep.tag] += int(not ok)
        states[ep.tag] = s
        rows[ep.tag].append((ep.t_ns, s.x.copy(), s.P.copy(), kind))
    out = {}
    for tag, r in rows.items():
        out[tag] = TagTrack(
            tag,
            np.array([v[0] for v in r], np.int64),
            np.array([v[1] for v in r]).reshape(-1, 4),
            np.array([v[2] for v in r]).reshape(-1, 4, 4),
            np.array([v[3] for v in r], np.int8),
            rejected[tag],
            skipped[tag],
            restarts[tag],
        )
    return out


def session_epochs(
    sessions: Sequence[Session], *, slot_gap_s: float = 0.02, extra_times: Mapping[str, NDArray] | None = None
) -> list[UwbEpoch]:
    """Group each session's ``/uwb/range`` messages into slots (ranges less than ``slot_gap_s``
    apart belong to one TDMA slot) as ``UwbEpoch`` of tag = the session's ``uwb_id`` (else its
    session id). ``extra_times[tag]`` adds empty epochs (prediction only), e.g. at step times."""
    out: list[UwbEpoch] = []
    for s in sessions:
        tag = s.uwb_id or s.session_id
        r = s.uwb_ranges
        if r is not None and len(r):
            t = r.t_ns
            cut = np.flatnonzero(np.diff(t) > slot_gap_s * 1e9) + 1
            for idx in np.split(np.arange(len(t)), cut):
                a = idx[r.is_anchor[idx]]
                p = idx[~r.is_anchor[idx]]
                out.append(UwbEpoch(
                    tag, int(t[idx[-1]]),
                    tuple(r.responder_id[i] for i in a), r.range_m[a].copy(),
                    tuple(r.responder_id[i] for i in p), r.range_m[p].copy(),
                ))
        for t_extra in (extra_times or {}).get(tag, np.zeros(0, np.int64)).tolist():
            out.append(UwbEpoch(tag, int(t_extra)))
    return out
