"""EKF and UKF for RSSI / velocity fusion (Papers 000 and 002 in ../shared/papers).

State (frame of the AP models / radio map, metres, m/s)::

    x = [p_x, p_y, v_x, v_y, b_x, b_y]            (papers' eq. 3)
    x = [p_x, p_y, v_x, v_y, b_x, b_y, theta]     (optional: alignment angle estimated)

Process (eq. 1-3): p += T v; v, b, theta constant; additive noise ``Q(T)``.
Velocity measurement (eq. 4)::

    y_v = M(theta) v + b,   M(theta) = [[-sin theta, cos theta], [cos theta, sin theta]]

``M(theta) = S @ Rot(-theta)`` with ``S`` the x/y swap: the velocity sensor reports
(east, north)-swapped components of the velocity rotated by ``-theta``. A foot
module's odometry velocity ``v_odo`` therefore enters as ``y_v = S v_odo`` with
``theta`` = rotation from the odometry frame to the map frame (see ``graphslam.app.track``).
RSSI measurement (eq. 5-6), one row per access point ``i``::

    y_i = P0_i - 10 gamma_i log10(sqrt(|p - a_i|^2 + d0^2))

``d0`` (``min_distance_m``) keeps the model finite and smooth at the AP.

Optional (``FusionModel.shadowing``, not in the papers): the RSSI error of AP ``i`` is a
shadowing offset ``s_i`` in the state plus white noise, ``y_i = h_i(p) + s_i + n_i``. The
shadowing is spatially correlated (Gudmundson: ``exp(-d / corr_m)`` over a distance ``d``
moved), so between epochs it is an Ornstein-Uhlenbeck process in the distance walked:
``s_i <- rho s_i + w``, ``rho = exp(-d / corr_m)``, ``var w = sigma^2 (1 - rho^2)``, with ``d``
from the epochs' velocity readings (``Epochs.travel_m``). States ``[base..., s_0 .. s_A-1]``.

EKF: eq. 8 of Paper 000, covariance update in Joseph form. UKF: eq. 8-10 of
Paper 002 (sigma points ``x +- columns of chol(n / (1 - w0) P)``, weights
``w0`` and ``(1 - w0) / 2n``), two deliberate departures, both documented in
docs/tracking.md: the covariance update is ``P - K Psi K^T`` (eq. 10 prints ``+``,
a typo: with ``+`` the covariance grows with every measurement), and the sigma points
of the update are redrawn from the predicted ``(x, P)`` so that ``Q`` is part of
the measurement statistics (the textbook additive-noise UKF).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from graphslam.core.tracking.pathloss import PathLossModel, PathLossRows, _ro  # noqa: F401 (PathLossRows: re-exported)
from graphslam.errors import EstimationError

log = logging.getLogger(__name__)

FilterKind = Literal["ekf", "ukf"]
STATE_NAMES = ("px", "py", "vx", "vy", "bx", "by", "theta")
_EMPTY_IDX = np.zeros(0, dtype=np.int64)


FilterError = EstimationError  # local name: every filter failure is an EstimationError


def velocity_matrix(theta: float | NDArray) -> NDArray[np.float64]:
    """``M(theta)`` of eq. 4 (shape (..., 2, 2) for an array of angles)."""
    t = np.asarray(theta, dtype=float)
    s, c = np.sin(t), np.cos(t)
    return np.stack([np.stack([-s, c], -1), np.stack([c, s], -1)], -2)


# 1 - rho^2 of a shadowing state is floored here: a walker standing still (rho = 1) keeps a
# tiny process noise, so the whitened process rows stay finite.
_MIN_DECORRELATION = 1e-6


@dataclass(frozen=True)
class Shadowing:
    """Spatially correlated RSSI error, one state per AP (module docstring): stationary std
    ``sigma_db`` (dB) and correlation distance ``corr_m`` (m, exp(-d / corr_m))."""

    sigma_db: float
    corr_m: float

    def __post_init__(self) -> None:
        if not (np.isfinite(self.sigma_db) and self.sigma_db > 0 and np.isfinite(self.corr_m) and self.corr_m > 0):
            raise FilterError(f"shadowing: sigma_db and corr_m must be finite and > 0, got {self.sigma_db}, {self.corr_m}")

    def decay(self, travel_m: NDArray | float) -> NDArray[np.float64]:
        """``rho = exp(-d / corr_m)`` for distances ``d`` (m) moved."""
        return np.exp(-np.abs(np.asarray(travel_m, float)) / self.corr_m)

    def noise_var(self, rho: NDArray | float) -> NDArray[np.float64]:
        """Variance of the OU step with decay ``rho`` (keeps the stationary variance sigma^2)."""
        return self.sigma_db**2 * np.maximum(1.0 - np.asarray(rho, float) ** 2, _MIN_DECORRELATION)


@dataclass(frozen=True, eq=False)
class FusionModel:
    """Process and measurement models of the papers, with their noise covariances.

    ``q_diag`` is the process-noise variance per nominal period ``period_s`` (the papers'
    ``Q`` with T = 4 s); for another ``dt`` it scales by ``dt / period_s`` (white-noise
    rates), so irregular step times keep the same noise per second. ``theta_rad`` fixes the
    alignment angle (the papers); ``None`` puts it in the state (index 6). ``shadowing``: one
    correlated RSSI offset per AP appended to the state (module docstring); ``r_rssi`` is then
    the white part only, and the process needs the distance moved (``dist_m``) per interval.
    """

    path_loss: PathLossModel
    q_diag: NDArray[np.float64]  # (n_base,) per period_s
    r_velocity: NDArray[np.float64]  # (2,) variance of y_v, (m/s)^2
    r_rssi: NDArray[np.float64]  # (A,) variance per AP, dB^2 (white part when shadowing is set)
    period_s: float = 4.0
    theta_rad: float | None = 0.1
    shadowing: Shadowing | None = None

    def __post_init__(self) -> None:
        q = np.asarray(self.q_diag, float).ravel()
        if q.shape != (self.n_base,):
            raise FilterError(f"fusion model: q_diag has {q.size} entries, state has {self.n_base}")
        rv = np.broadcast_to(np.asarray(self.r_velocity, float), (2,))
        rr = np.broadcast_to(np.asarray(self.r_rssi, float), (len(self.path_loss),))
        if (q < 0).any() or (rv <= 0).any() or (rr <= 0).any() or self.period_s <= 0:
            raise FilterError("fusion model: noise variances must be >= 0 (Q) / > 0 (R) and period_s > 0")
        object.__setattr__(self, "q_diag", _ro(q))
        object.__setattr__(self, "r_velocity", _ro(rv))
        object.__setattr__(self, "r_rssi", _ro(rr))

    @classmethod
    def paper_ekf(cls) -> "FusionModel":
        """Paper 000 sec. IV: T = 4 s, theta = 0.1 rad, Q, R as printed (Q_55 = 1e9 read as 1e-9)."""
        return cls(
            PathLossModel.paper_ekf(),
            q_diag=np.array([1e-3, 1e-3, 1e-4, 1e-4, 1e-9, 1e-9]),
            r_velocity=np.array([1e-4, 1e-4]),
            r_rssi=np.full(4, 40.0),
        )

    @classmethod
    def paper_ukf(cls) -> "FusionModel":
        """Paper 002 sec. IV: Q = diag(1, 1, 1, 1, 1e-5, 1e-5) 1e-4, R = diag(2e-3, 2e-3, 10, 10, 10, 10)."""
        return cls(
            PathLossModel.paper_ukf(),
            q_diag=np.array([1, 1, 1, 1, 1e-5, 1e-5]) * 1e-4,
            r_velocity=np.array([2e-3, 2e-3]),
            r_rssi=np.full(4, 10.0),
        )

    @property
    def n_base(self) -> int:
        """The papers' state (6), or 7 with theta."""
        return 6 if self.theta_rad is not None else 7

    @property
    def n(self) -> int:
        return self.n_base + (len(self.path_loss) if self.shadowing is not None else 0)

    def shadow_state(self, ap_idx: NDArray | int) -> NDArray[np.int64]:
        """State index of AP ``ap_idx``'s shadowing offset (only with ``shadowing``)."""
        return self.n_base + np.asarray(ap_idx, np.int64)

    def _rho(self, dist_m: float | None) -> float:
        if self.shadowing is None:
            return 1.0
        if dist_m is None:
            raise FilterError("fusion model: the shadowing states need the distance moved in each interval")
        return float(self.shadowing.decay(dist_m))

    def transition(self, dt: float, dist_m: float | None = None) -> NDArray[np.float64]:
        """``A`` of eq. 3 for a period ``dt`` (s); shadowing states decay over ``dist_m`` (m)."""
        F = np.eye(self.n)
        F[0, 2] = F[1, 3] = dt
        if self.shadowing is not None:
            F[self.n_base:, self.n_base:] *= self._rho(dist_m)
        return F

    def process_noise(self, dt: float, dist_m: float | None = None) -> NDArray[np.float64]:
        q = self.q_diag * (dt / self.period_s)
        if self.shadowing is not None:
            q = np.concatenate([q, np.full(len(self.path_loss), float(self.shadowing.noise_var(self._rho(dist_m))))])
        return np.diag(q)

    def propagate(self, X: NDArray, dt: float, dist_m: float | None = None) -> NDArray[np.float64]:
        """Eq. 3 without noise, for states in rows (m, n)."""
        out = np.array(X, dtype=float, copy=True)
        out[..., 0:2] += dt * out[..., 2:4]
        if self.shadowing is not None:
            out[..., self.n_base:] *= self._rho(dist_m)
        return out

    def with_shadowing(self, share: float, corr_m: float) -> "FusionModel":
        """This model with its RSSI variance split: ``share`` of it (of the mean over APs) becomes
        correlated shadowing states (``corr_m``), the rest stays white noise. Same total variance
        per reading; what changes is that errors at nearby places are no longer independent."""
        if not 0.0 < share < 1.0:
            raise FilterError(f"shadowing: the correlated share must be in (0, 1), got {share}")
        if self.shadowing is not None:
            raise FilterError("shadowing: the model has shadowing states already")
        sigma = float(np.sqrt(share * float(np.mean(self.r_rssi))))
        return dataclasses.replace(self, r_rssi=self.r_rssi * (1.0 - share), shadowing=Shadowing(sigma, corr_m))

    def prior(self, x0: NDArray, P0: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """A prior on the base state extended to the model's: shadowing states at 0 with their
        stationary variance (unchanged without shadowing)."""
        x0, P0 = np.asarray(x0, float).ravel(), np.asarray(P0, float)
        if len(x0) == self.n:
            return x0, P0
        if len(x0) != self.n_base or P0.shape != (self.n_base, self.n_base):
            raise FilterError(f"fusion model: a prior of size {len(x0)} / {P0.shape} for a base state of {self.n_base}")
        P = np.zeros((self.n, self.n))
        P[: self.n_base, : self.n_base] = P0
        P[self.n_base:, self.n_base:] = np.eye(self.n - self.n_base) * self.shadowing.sigma_db**2
        return np.concatenate([x0, np.zeros(self.n - self.n_base)]), P

    def measure(self, X: NDArray, use_velocity: bool, ap_idx: NDArray) -> NDArray[np.float64]:
        """Predicted measurements (m, p) of states (m, n): [y_v (2) if used; RSSI of ``ap_idx``]."""
        X = np.atleast_2d(np.asarray(X, float))
        parts = []
        if use_velocity:
            th = X[:, 6] if self.theta_rad is None else np.full(len(X), self.theta_rad)
            M = velocity_matrix(th)  # (m, 2, 2)
            parts.append(np.einsum("mij,mj->mi", M, X[:, 2:4]) + X[:, 4:6])
        if len(ap_idx):
            rss = self.path_loss.mean_rss(X[:, 0:2], ap_idx)
            if self.shadowing is not None:
                rss = rss + X[:, self.shadow_state(ap_idx)]
            parts.append(rss)
        return np.concatenate(parts, axis=1) if parts else np.zeros((len(X), 0))

    def measurement_jacobian(self, x: NDArray, use_velocity: bool, ap_idx: NDArray) -> NDArray[np.float64]:
        """Analytic ``H`` (p, n) of ``measure`` at one state (eq. 8's H_k)."""
        x = np.asarray(x, float)
        rows = []
        if use_velocity:
            Hv = np.zeros((2, self.n))
            th = float(x[6]) if self.theta_rad is None else self.theta_rad
            Hv[:, 2:4] = velocity_matrix(th)
            Hv[:, 4:6] = np.eye(2)
            if self.theta_rad is None:
                s, c = np.sin(th), np.cos(th)
                Hv[:, 6] = np.array([[-c, -s], [-s, c]]) @ x[2:4]  # dM/dtheta v
            rows.append(Hv)
        if len(ap_idx):
            Hr = np.zeros((len(ap_idx), self.n))
            Hr[:, 0:2] = self.path_loss.jacobian(x[0:2], ap_idx)
            if self.shadowing is not None:
                Hr[np.arange(len(ap_idx)), self.shadow_state(ap_idx)] = 1.0
            rows.append(Hr)
        return np.vstack(rows) if rows else np.zeros((0, self.n))

    def measurement_noise(self, use_velocity: bool, ap_idx: NDArray) -> NDArray[np.float64]:
        r = np.concatenate([self.r_velocity if use_velocity else np.zeros(0), self.r_rssi[np.asarray(ap_idx, np.int64)]])
        return np.diag(r)


@dataclass(frozen=True, eq=False)
class GaussianState:
    """Mean ``x`` (n,) and covariance ``P`` (n, n); read-only."""

    x: NDArray[np.float64]
    P: NDArray[np.float64]

    def __post_init__(self) -> None:
        x = np.asarray(self.x, float).ravel()
        P = np.asarray(self.P, float)
        if P.shape != (len(x), len(x)) or not (np.isfinite(x).all() and np.isfinite(P).all()):
            raise FilterError(f"state: P has shape {P.shape} for a state of size {len(x)}, or non-finite values")
        object.__setattr__(self, "x", _ro(x))
        object.__setattr__(self, "P", _ro(0.5 * (P + P.T)))  # why: keep P exactly symmetric


@dataclass(frozen=True)
class UpdateInfo:
    """What one measurement update saw: innovation log-likelihood, NIS, rows used / gated out."""

    loglik: float
    nis: float
    n_used: int
    n_gated: int


def _kalman_gain(C: NDArray, S: NDArray) -> NDArray:
    """K = C S^-1 via a solve (S symmetric positive definite)."""
    try:
        cf = np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        raise FilterError("innovation covariance is not positive definite") from None
    return np.linalg.solve(cf.T, np.linalg.solve(cf, C.T)).T


def _gate(nu: NDArray, S: NDArray, n_fixed: int, gate_sigma: float | None) -> NDArray[np.bool_]:
    """Rows kept: the first ``n_fixed`` (velocity) always; RSSI rows within ``gate_sigma`` std."""
    keep = np.ones(len(nu), dtype=bool)
    if gate_sigma is not None and len(nu) > n_fixed:
        z = np.abs(nu[n_fixed:]) / np.sqrt(np.diag(S)[n_fixed:])
        keep[n_fixed:] = z <= gate_sigma
    return keep


def _inflate_rssi_noise(nu: NDArray, S: NDArray, R: NDArray, n_fixed: int) -> tuple[NDArray, NDArray]:
    """Innovation-based adaptive R (Papers 000/002's future work): when the RSSI rows' NIS per
    row exceeds 1, their R is scaled by that ratio, so one scan whose readings disagree with the
    path-loss models together (correlated model error, a wrong position) cannot make the state
    more certain than the readings' spread supports. Consistent innovations change nothing."""
    r = slice(n_fixed, None)
    m = len(nu) - n_fixed
    if m <= 0:
        return S, R
    ratio = float(nu[r] @ np.linalg.solve(S[r, r], nu[r])) / m
    if ratio <= 1.0:
        return S, R
    dR = np.zeros_like(R)
    dR[r, r] = (ratio - 1.0) * R[r, r]
    return S + dR, R + dR


def _loglik(nu: NDArray, S: NDArray) -> tuple[float, float]:
    if len(nu) == 0:
        return 0.0, 0.0
    nis = float(nu @ np.linalg.solve(S, nu))
    _, logdet = np.linalg.slogdet(2.0 * np.pi * S)
    return -0.5 * (nis + logdet), nis


@dataclass(frozen=True, eq=False)
class ExtendedKalmanFilter:
    """Eq. 8 of Paper 000 (analytic Jacobians; Joseph-form covariance update)."""

    model: FusionModel
    kind: FilterKind = field(default="ekf", init=False)

    def predict(self, s: GaussianState, dt: float, dist_m: float | None = None) -> GaussianState:
        F = self.model.transition(dt, dist_m)
        return GaussianState(F @ s.x, F @ s.P @ F.T + self.model.process_noise(dt, dist_m))

    def update(
        self, s: GaussianState, y: NDArray, *, use_velocity: bool, ap_idx: NDArray = _EMPTY_IDX,
        gate_sigma: float | None = None, adaptive_rssi: bool = False,
    ) -> tuple[GaussianState, UpdateInfo]:
        m = self.model
        ap_idx = np.asarray(ap_idx, np.int64)
        H = m.measurement_jacobian(s.x, use_velocity, ap_idx)
        R = m.measurement_noise(use_velocity, ap_idx)
        nu = np.asarray(y, float) - m.measure(s.x, use_velocity, ap_idx)[0]
        S = H @ s.P @ H.T + R
        keep = _gate(nu, S, 2 if use_velocity else 0, gate_sigma)
        H, R, nu, S = H[keep], R[np.ix_(keep, keep)], nu[keep], S[np.ix_(keep, keep)]
        if adaptive_rssi:
            S, R = _inflate_rssi_noise(nu, S, R, 2 if use_velocity else 0)
        if not len(nu):
            return s, UpdateInfo(0.0, 0.0, 0, int((~keep).sum()))
        K = _kalman_gain(s.P @ H.T, S)
        IKH = np.eye(m.n) - K @ H
        P = IKH @ s.P @ IKH.T + K @ R @ K.T  # Joseph form: stays PSD with rounding
        ll, nis = _loglik(nu, S)
        return GaussianState(s.x + K @ nu, P), UpdateInfo(ll, nis, len(nu), int((~keep).sum()))


def sigma_points(x: NDArray, P: NDArray, w0: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Eq. 8 of Paper 002: (2n+1, n) sigma points and their weights (sum to one)."""
    n = len(x)
    if not 0.0 <= w0 < 1.0:
        raise FilterError(f"UKF weight w0 must be in [0, 1), got {w0}")
    try:
        L = np.linalg.cholesky((n / (1.0 - w0)) * np.asarray(P, float))
    except np.linalg.LinAlgError:
        raise FilterError("state covariance is not positive definite (sigma points)") from None
    X = np.empty((2 * n + 1, n))
    X[0] = x
    X[1::2] = x - L.T  # i odd: (-1)^i = -1; column ceil(i/2) of L
    X[2::2] = x + L.T
    w = np.full(2 * n + 1, (1.0 - w0) / (2 * n))
    w[0] = w0
    return X, w


def unscented_transform(X: NDArray, w: NDArray) -> tuple[NDArray, NDArray]:
    """Weighted mean and covariance of rows ``X`` (eq. 9 without Q)."""
    mu = w @ X
    D = X - mu
    return mu, (D * w[:, None]).T @ D


@dataclass(frozen=True, eq=False)
class UnscentedKalmanFilter:
    """Eq. 8-10 of Paper 002 with weight ``w0`` (their experiment: 0.1)."""

    model: FusionModel
    w0: float = 0.1
    kind: FilterKind = field(default="ukf", init=False)

    def predict(self, s: GaussianState, dt: float, dist_m: float | None = None) -> GaussianState:
        X, w = sigma_points(s.x, s.P, self.w0)
        mu, P = unscented_transform(self.model.propagate(X, dt, dist_m), w)
        return GaussianState(mu, P + self.model.process_noise(dt, dist_m))

    def update(
        self, s: GaussianState, y: NDArray, *, use_velocity: bool, ap_idx: NDArray = _EMPTY_IDX,
        gate_sigma: float | None = None, adaptive_rssi: bool = False,
    ) -> tuple[GaussianState, UpdateInfo]:
        m = self.model
        ap_idx = np.asarray(ap_idx, np.int64)
        X, w = sigma_points(s.x, s.P, self.w0)  # redrawn from the predicted (x, P): includes Q
        Y = m.measure(X, use_velocity, ap_idx)  # (2n+1, p), vectorised over sigma points
        y_hat, Psi = unscented_transform(Y, w)
        R = m.measurement_noise(use_velocity, ap_idx)
        Psi = Psi + R
        Phi = ((X - w @ X) * w[:, None]).T @ (Y - y_hat)  # cross covariance (n, p)
        nu = np.asarray(y, float) - y_hat
        keep = _gate(nu, Psi, 2 if use_velocity else 0, gate_sigma)
        nu, Psi, Phi, R = nu[keep], Psi[np.ix_(keep, keep)], Phi[:, keep], R[np.ix_(keep, keep)]
        if adaptive_rssi:
            Psi, R = _inflate_rssi_noise(nu, Psi, R, 2 if use_velocity else 0)
        if not len(nu):
            return s, UpdateInfo(0.0, 0.0, 0, int((~keep).sum()))
        K = _kalman_gain(Phi, Psi)
        P = s.P - K @ Psi @ K.T  # eq. 10 prints "+": a typo (see module docstring)
        ll, nis = _loglik(nu, Psi)
        return GaussianState(s.x + K @ nu, P), UpdateInfo(ll, nis, len(nu), int((~keep).sum()))


KalmanFilter = ExtendedKalmanFilter | UnscentedKalmanFilter


def position_update(
    s: GaussianState, xy: NDArray, sigma_m: float, *, gate_sigma: float | None = None
) -> tuple[GaussianState, UpdateInfo]:
    """Update with a position fix ``xy`` (m) of isotropic std ``sigma_m``: linear (H = [I 0]),
    so the EKF and the UKF update are the same Kalman update. Gated as one 2-D reading: dropped
    when its Mahalanobis distance exceeds ``gate_sigma``."""
    n = len(s.x)
    H = np.zeros((2, n))
    H[0, 0] = H[1, 1] = 1.0
    R = np.eye(2) * sigma_m**2
    nu = np.asarray(xy, float) - s.x[0:2]
    S = s.P[0:2, 0:2] + R
    ll, nis = _loglik(nu, S)
    if gate_sigma is not None and nis > gate_sigma**2:
        return s, UpdateInfo(0.0, nis, 0, 1)
    K = _kalman_gain(s.P @ H.T, S)
    IKH = np.eye(n) - K @ H
    return GaussianState(s.x + K @ nu, IKH @ s.P @ IKH.T + K @ R @ K.T), UpdateInfo(ll, nis, 1, 0)


def make_filter(kind: str, model: FusionModel, *, w0: float = 0.1) -> KalmanFilter:
    """``"ekf"`` or ``"ukf"`` (``FilterError`` otherwise)."""
    if kind == "ekf":
        return ExtendedKalmanFilter(model)
    if kind == "ukf":
        return UnscentedKalmanFilter(model, w0)
    raise FilterError(f"unknown filter {kind!r}; use ekf or ukf")


@dataclass(frozen=True, eq=False)
class Epochs:
    """The measurements of one run grouped by epoch: state ``k`` lives at time ``t_s[k]``.

    Velocity readings ``vel_y[i]`` (eq. 4) belong to epoch ``vel_k[i]``; RSSI readings
    ``rss_y[j]`` (dBm) of access point ``rss_ap[j]`` (a row of the path-loss model) to epoch
    ``rss_k[j]`` (its std is the model's times ``rss_scale[j]``, default 1: the whole-run and
    fixed-lag MAP use it, the causal filters do not); optional position fixes ``fix_xy[l]`` (m, e.g. a kNN fix on the radio map)
    with isotropic std ``fix_sigma[l]`` (m) to epoch ``fix_k[l]``. ``travel_m`` (N - 1,): the
    distance moved between consecutive epochs (m), which a model with shadowing states needs.
    Times strictly increase (readings at one time share an epoch); an epoch may hold no
    reading. Read-only arrays.
    """

    t_s: NDArray[np.float64]
    vel_k: NDArray[np.int64]
    vel_y: NDArray[np.float64]
    rss_k: NDArray[np.int64]
    rss_ap: NDArray[np.int64]
    rss_y: NDArray[np.float64]
    fix_k: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    fix_xy: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 2)))
    fix_sigma: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    rss_scale: NDArray[np.float64] | None = None  # per RSSI reading: std multiplier (>= 1; None: all 1)
    travel_m: NDArray[np.float64] | None = None  # (N - 1,) distance moved per interval, m (None: not known)

    def __post_init__(self) -> None:
        t = np.asarray(self.t_s, float).ravel()
        vk, rk, ra = (np.asarray(a, np.int64).ravel() for a in (self.vel_k, self.rss_k, self.rss_ap))
        vy = np.asarray(self.vel_y, float).reshape(-1, 2)
        ry = np.asarray(self.rss_y, float).ravel()
        fk = np.asarray(self.fix_k, np.int64).ravel()
        fxy = np.asarray(self.fix_xy, float).reshape(-1, 2)
        fs = np.asarray(self.fix_sigma, float).ravel()
        if not (len(fk) == len(fxy) == len(fs)):
            raise FilterError(f"epochs: {len(fk)}/{len(fxy)}/{len(fs)} fix epochs/positions/sigmas")
        if ((fk < 0) | (fk >= len(t))).any() or not (np.isfinite(fxy).all() and np.isfinite(fs).all() and (fs > 0).all()):
            raise FilterError("epochs: a position fix is out of range, non-finite or has sigma <= 0")
        if not len(t):
            raise FilterError("epochs: no epoch")
        if not np.isfinite(t).all() or (np.diff(t) <= 0).any():
            raise FilterError("epochs: t_s must be finite and strictly increasing")
        if len(vk) != len(vy) or not (len(rk) == len(ra) == len(ry)):
            raise FilterError(f"epochs: {len(vk)} velocity epochs for {len(vy)} readings, "
                              f"{len(rk)}/{len(ra)}/{len(ry)} RSSI epochs/APs/readings")
        if ((vk < 0) | (vk >= len(t))).any() or ((rk < 0) | (rk >= len(t))).any() or (ra < 0).any():
            raise FilterError("epochs: an epoch or AP index is out of range")
        if not (np.isfinite(vy).all() and np.isfinite(ry).all()):
            raise FilterError("epochs: non-finite reading")
        rs = np.ones(len(ry)) if self.rss_scale is None else np.asarray(self.rss_scale, float).ravel()
        if rs.shape != ry.shape or not (np.isfinite(rs).all() and (rs > 0).all()):
            raise FilterError("epochs: rss_scale needs one positive finite value per RSSI reading")
        object.__setattr__(self, "rss_scale", _ro(rs))
        if self.travel_m is not None:
            tr = np.asarray(self.travel_m, float).ravel()
            if tr.shape != (len(t) - 1,) or not (np.isfinite(tr).all() and (tr >= 0).all()):
                raise FilterError(f"epochs: travel_m needs {len(t) - 1} finite distances >= 0, got {tr.shape[0]}")
            object.__setattr__(self, "travel_m", _ro(tr))
        if len(np.unique(vk)) != len(vk):
            raise FilterError("epochs: more than one velocity reading in an epoch")
        for name, a in (("t_s", t), ("vel_k", vk), ("vel_y", vy), ("rss_k", rk), ("rss_ap", ra), ("rss_y", ry),
                        ("fix_k", fk), ("fix_xy", fxy), ("fix_sigma", fs)):
            object.__setattr__(self, name, _ro(a, a.dtype.type))

    @classmethod
    def fixed_rate(cls, y_velocity: NDArray, y_rssi: NDArray, dt: float) -> "Epochs":
        """The papers' loop: epoch ``k`` at ``k dt`` holds ``y_velocity[k]`` and the finite entries
        of ``y_rssi[k]`` (NaN = AP not heard). Distance moved from epoch ``k`` to ``k + 1``:
        ``|y_velocity[k]| dt`` (eq. 4's ``M`` keeps lengths, so this is the speed up to the bias)."""
        yv, yr = np.asarray(y_velocity, float), np.asarray(y_rssi, float)
        if yv.ndim != 2 or yv.shape[1] != 2 or yr.ndim != 2 or len(yr) != len(yv) or dt <= 0:
            raise FilterError(f"epochs: y_velocity {yv.shape} / y_rssi {yr.shape} / dt {dt} do not fit together")
        k, a = np.nonzero(np.isfinite(yr))
        travel = np.linalg.norm(yv[:-1], axis=1) * float(dt)
        return cls(np.arange(len(yv)) * float(dt), np.arange(len(yv)), yv, k, a, yr[k, a], travel_m=travel)

    def interval_travel(self, k: int) -> float | None:
        """Distance moved from epoch ``k`` to ``k + 1`` (m), None when not known."""
        return None if self.travel_m is None else float(self.travel_m[k])

    def __len__(self) -> int:
        return len(self.t_s)

    @property
    def dt(self) -> NDArray[np.float64]:
        """(N - 1,) seconds between consecutive epochs."""
        return np.diff(self.t_s)

    def check_model(self, model: "FusionModel") -> None:
        if len(self.rss_ap) and int(self.rss_ap.max()) >= len(model.path_loss):
            raise FilterError(f"epochs: AP index {int(self.rss_ap.max())} but the model has {len(model.path_loss)} APs")


@dataclass(frozen=True, eq=False)
class FilterRun:
    """Filtered states after each epoch's update: ``x`` (N, n), ``P`` (N, n, n)."""

    kind: str
    x: NDArray[np.float64]
    P: NDArray[np.float64]
    loglik: float
    n_rssi_used: int = 0
    n_rssi_gated: int = 0

    @property
    def trace_p(self) -> NDArray[np.float64]:
        return np.trace(self.P, axis1=1, axis2=2)


def run_epochs(
    filt: KalmanFilter, x0: NDArray, P0: NDArray, epochs: Epochs, *, gate_sigma: float | None = None
) -> FilterRun:
    """Causal filtering: at every epoch predict from the previous one (k > 0), then one joint
    update with ``[y_v if any; RSSI of that epoch]``; RSSI rows beyond ``gate_sigma`` dropped."""
    epochs.check_model(filt.model)
    n_ep = len(epochs)
    vel_at = np.full(n_ep, -1, np.int64)
    vel_at[epochs.vel_k] = np.arange(len(epochs.vel_k))
    order = np.argsort(epochs.rss_k, kind="stable")
    bounds = np.searchsorted(epochs.rss_k[order], np.arange(n_ep + 1))
    f_order = np.argsort(epochs.fix_k, kind="stable")
    f_bounds = np.searchsorted(epochs.fix_k[f_order], np.arange(n_ep + 1))
    dts = epochs.dt
    s = GaussianState(x0, P0)
    xs, Ps = np.empty((n_ep, len(s.x))), np.empty((n_ep, len(s.x), len(s.x)))
    ll, used, gated = 0.0, 0, 0
    for k in range(n_ep):
        if k:
            s = filt.predict(s, float(dts[k - 1]), epochs.interval_travel(k - 1))
        rows = order[bounds[k]:bounds[k + 1]]
        use_v = vel_at[k] >= 0
        if use_v or len(rows):
            y = np.concatenate([epochs.vel_y[vel_at[k]] if use_v else np.zeros(0), epochs.rss_y[rows]])
            s, info = filt.update(s, y, use_velocity=bool(use_v), ap_idx=epochs.rss_ap[rows], gate_sigma=gate_sigma)
            ll += info.loglik
            used += info.n_used - (2 if use_v else 0)
            gated += info.n_gated
        for j in f_order[f_bounds[k]:f_bounds[k + 1]]:
            s, info = position_update(s, epochs.fix_xy[j], float(epochs.fix_sigma[j]), gate_sigma=gate_sigma)
            ll += info.loglik
        xs[k], Ps[k] = s.x, s.P
    return FilterRun(filt.kind, xs, Ps, ll, used, gated)


def run_fixed_rate(
    filt: KalmanFilter, x0: NDArray, P0: NDArray, y_velocity: NDArray, y_rssi: NDArray, dt: float
) -> FilterRun:
    """The papers' loop: at every epoch k (period ``dt``) predict (k > 0), then one joint update
    with ``[y_v; RSSI]``. ``y_rssi`` (N, A) may hold NaN for an AP not heard at that epoch."""
    yr = np.asarray(y_rssi, float)
    if yr.ndim != 2 or yr.shape[1] != len(filt.model.path_loss):
        raise FilterError(f"run: y_rssi {yr.shape} does not match the model's {len(filt.model.path_loss)} APs")
    return run_epochs(filt, x0, P0, Epochs.fixed_rate(y_velocity, yr, dt))
