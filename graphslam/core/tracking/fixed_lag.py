"""Fixed-lag smoothing: online estimates with a latency, from a sliding window of recent epochs.

The state at time ``t`` is reported once the readings up to ``t + lag_s`` are in, as the maximum
a-posteriori estimate of the window of epochs in ``[t_now - window_s, t_now]`` under the filters'
own model (``graphslam.core.tracking.filters.FusionModel``: process eq. 3 with Q(dt), velocity
eq. 4, RSSI eq. 6, position fixes), solved by the whole-run MAP's sparse Levenberg-Marquardt
(``graphslam.core.tracking.smoother.MapProblem``) warm-started from the previous window.
Epochs that leave the window are marginalised: the rows that touch the oldest epoch (its prior,
its readings, the process step to the next epoch) are linearised at their current estimate
(IRLS weights when robust) and eliminated, leaving a Gaussian prior on the next epoch (the
Schur complement: exactly what a Kalman filter would carry forward from that linearisation).

- ``lag_s = 0``: the newest state of the window, i.e. a filter whose every update relinearises
  the whole window (moving-horizon estimation); it equals the EKF on a linear-Gaussian model.
- ``window_s, lag_s -> inf``: nothing is marginalised and the last solve is the whole-run MAP.

Readings can arrive after their epoch (``vel_available_s``): a walker's step velocity of the
interval ``[t_k, t_k+1]`` belongs to epoch ``k`` but is known only at ``t_k+1``; a reading is
used from the first solve at or after its availability time, and dropped (counted) if its epoch
was marginalised before then.

Several starts (e.g. heading hypotheses) run as a bank in lock-step; each output takes the
hypothesis with the lowest total cost (the marginalised parts' constants plus the window cost,
i.e. twice the negative log posterior up to a shared constant), or with ``report="mixture"`` the
moments of the bank's posterior mixture (weights exp(-cost / 2)); a hypothesis whose cost exceeds
the best by ``prune_cost`` is dropped (its posterior odds are below exp(-prune_cost / 2)). With
``temper`` T > 1 the costs are divided by T in both (weights exp(-cost / 2T), pruning at T
``prune_cost``): readings whose errors are correlated in time count T times too often in the costs,
so the bank would decide for one hypothesis too early; each hypothesis's own estimate is unchanged.

With ``axes`` every window also holds the walk-axes prior on its velocities
(``graphslam.core.tracking.axes``), with ``area`` the walkable-area prior on its step positions
(``graphslam.core.tracking.walkable``), each marginalised with its epoch like any other row.

Frames and units as the filters (m, m/s, rad, dBm, s).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from numpy.typing import NDArray

from graphslam.core.tracking.axes import WalkAxes
from graphslam.core.tracking.filters import Epochs, FusionModel
from graphslam.core.tracking.smoother import MapProblem, dead_reckoning_starts, levenberg_marquardt
from graphslam.core.tracking.walkable import WalkableArea
from graphslam.errors import EstimationError
from graphslam.tracking_config import DEFAULTS

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FixedLagConfig:
    """Latency and window of the fixed-lag smoother (s), robust loss, iteration budget.

    ``window_s`` >= ``lag_s``: the window must still hold an epoch when its estimate is reported.
    ``huber_k``: Huber loss (in std) on RSSI and fix rows (None: Gaussian). ``prune_cost``:
    hypotheses this far above the best are dropped (None: keep all)."""

    lag_s: float = DEFAULTS.fixed_lag.lag_s
    window_s: float = DEFAULTS.fixed_lag.window_s
    huber_k: float | None = DEFAULTS.filter.gate_sigma
    max_iter: int = 10
    restart_every: int = 0  # every this many epochs also solve from dead-reckoning starts (0: never)
    rel_tol: float = 1e-6  # LM stops when a step lowers the window cost by less than this share
    prune_cost: float | None = DEFAULTS.fixed_lag.prune_cost
    adaptive_rssi: bool = DEFAULTS.rssi.adaptive  # scale an epoch's RSSI std by its innovations' NIS per reading (> 1)
    prior_count: float = 4.0  # pseudo-fixes of NIS 2 in the variance factor
    report: str = DEFAULTS.fixed_lag.bank_report  # best: the lowest-cost hypothesis | mixture: the bank's posterior mixture
    angle_index: int | None = None  # state entry that is an angle (mixture differences wrapped)
    temper: float = 1.0  # the bank's costs are divided by this in its weights and pruning (correlated readings)

    def __post_init__(self) -> None:
        if not (self.lag_s >= 0 and self.window_s >= self.lag_s):
            raise EstimationError(f"fixed-lag: need 0 <= lag_s <= window_s, got lag {self.lag_s}, window {self.window_s}")
        if self.huber_k is not None and self.huber_k <= 0:
            raise EstimationError(f"fixed-lag: huber_k must be > 0, got {self.huber_k}")
        if self.max_iter < 1 or (self.prune_cost is not None and self.prune_cost <= 0):
            raise EstimationError("fixed-lag: max_iter >= 1 and prune_cost > 0 required")
        if not (math.isfinite(self.temper) and self.temper >= 1.0):
            raise EstimationError(f"fixed-lag: temper must be a finite number >= 1, got {self.temper}")
        if self.report not in ("best", "mixture"):
            raise EstimationError(f"fixed-lag: report must be 'best' or 'mixture', got {self.report!r}")


@dataclass(frozen=True, eq=False)
class FixedLagRun:
    """Per epoch: the estimate reported ``lag_s`` after it, ``x`` (N, n), marginal ``P`` (N, n, n),
    the hypothesis it came from and the stream time (s) at which it was reported."""

    x: NDArray[np.float64]
    P: NDArray[np.float64]
    hypothesis: NDArray[np.int64]
    reported_at_s: NDArray[np.float64]
    variance_factor: NDArray[np.float64]  # (N,) fix-innovation variance factor at report time (>= 1)
    cost: NDArray[np.float64]  # (H,) final total cost per hypothesis (inf: pruned)
    solves: int
    readings_dropped: int  # arrived after their epoch had been marginalised

    @property
    def trace_p(self) -> NDArray[np.float64]:
        return np.trace(self.P, axis1=1, axis2=2)


class _Window:
    """One hypothesis: the window ``[lo, hi]`` of the run's epochs, its prior and estimate."""

    def __init__(self, stream: "_Stream", x0: NDArray, P0: NDArray) -> None:
        self.s = stream
        self.lo = self.hi = 0
        self.prior_x, self.prior_P = np.asarray(x0, float).copy(), np.asarray(P0, float).copy()
        self.X = self.prior_x[None, :].copy()
        self.const = 0.0  # cost of what was marginalised, at its minimum
        self.problem: MapProblem | None = None
        self.window_cost = 0.0
        self.alive = True
        self.dropped = 0  # velocity readings of marginalised epochs that were not yet available
        self.rss_scale = stream.epochs.rss_scale.copy()  # as used: adaptive RSSI scales new epochs
        cfg = stream.cfg
        # innovation statistics of the position fixes (see ``innovate``), with prior pseudo-counts
        self.n_fix = cfg.prior_count
        self.sum_nis = 2.0 * cfg.prior_count  # E[NIS] = 2 (dof) when the model is right

    @property
    def total_cost(self) -> float:
        return self.const + self.window_cost

    @property
    def variance_factor(self) -> float:
        """Mean fix NIS / 2 so far (prior: 1): how much larger the innovations are than the model
        says. Scaling every covariance by it is the covariance-matching estimate of one common
        variance factor (the estimate does not change, its reported uncertainty does)."""
        return max(1.0, self.sum_nis / (2.0 * self.n_fix))

    def innovate(self, j: int) -> None:
        """Before epoch ``j``'s solve: the innovations of epoch ``j``'s fixes and RSSI readings
        against the prediction from the previous solve (mean, and covariance propagated by the
        process). Fix NIS feeds ``variance_factor``; with ``adaptive_rssi`` an epoch whose RSSI
        NIS per reading exceeds 1 has its RSSI std scaled by its square root (the filters'
        adaptive R, ``filters._inflate_rssi_noise``, kept for that epoch)."""
        e, cfg = self.s.epochs, self.s.cfg
        rows = np.flatnonzero(e.fix_k == j)
        rss = np.flatnonzero(e.rss_k == j) if cfg.adaptive_rssi else np.zeros(0, np.int64)
        if not (len(rows) or len(rss)) or self.problem is None or j != self.hi or j - 1 < self.lo:
            return
        m = self.s.model
        Pk = self.problem.marginal(self.X[: j - self.lo], j - 1 - self.lo)
        dt, dist = float(e.t_s[j] - e.t_s[j - 1]), e.interval_travel(j - 1)
        F = m.transition(dt, dist)
        Pp = F @ Pk @ F.T + m.process_noise(dt, dist)
        xp = self.X[-1, :2]
        for i in rows:
            nu = e.fix_xy[i] - xp
            S = Pp[:2, :2] + np.eye(2) * e.fix_sigma[i] ** 2
            self.sum_nis += float(nu @ np.linalg.solve(S, nu))
            self.n_fix += 1
        if len(rss):
            H = m.measurement_jacobian(self.X[-1], False, e.rss_ap[rss])
            nu = e.rss_y[rss] - m.measure(self.X[-1], False, e.rss_ap[rss])[0]
            S = H @ Pp @ H.T + np.diag(m.r_rssi[e.rss_ap[rss]] * self.rss_scale[rss] ** 2)
            ratio = float(nu @ np.linalg.solve(S, nu)) / len(rss)
            if ratio > 1.0:
                self.rss_scale[rss] *= np.sqrt(ratio)

    def solve(self, now: float, restart: bool = False) -> None:
        self.problem = self.s.problem(self.lo, self.hi, now, self.prior_x, self.prior_P, self.rss_scale)
        cfg = self.s.cfg
        X, cost, _ = levenberg_marquardt(self.problem, self.X, cfg.max_iter, rel_tol=cfg.rel_tol)
        if restart:
            for X0 in dead_reckoning_starts(self.problem):
                Xr, cr, _ = levenberg_marquardt(self.problem, X0, cfg.max_iter * 5, rel_tol=cfg.rel_tol)
                if cr < cost:
                    X, cost = Xr, cr
        self.X, self.window_cost = X, cost

    def extend(self, hi: int) -> None:
        """Add epochs up to ``hi``, started by the noise-free process from the newest estimate."""
        m, t = self.s.model, self.s.epochs.t_s
        rows = [self.X]
        x = self.X[-1]
        for k in range(self.hi + 1, hi + 1):
            x = m.propagate(x[None, :], float(t[k] - t[k - 1]), self.s.epochs.interval_travel(k - 1))[0]
            rows.append(x[None, :])
        self.X, self.hi = np.vstack(rows), hi

    def marginalise_first(self) -> None:
        """Eliminate epoch ``lo`` (linearised at the current estimate); prior on ``lo + 1``."""
        assert self.hi > self.lo
        p = self.s.problem(self.lo, self.hi, self.s.now, self.prior_x, self.prior_P, self.rss_scale)  # readings known now
        n = p.n
        x = self.X.ravel()
        r = p.residual(x)
        sw = p.weights(r)
        rows = p.rows_touching_first_epoch()
        J = (sp.diags(sw[rows]) @ p.jacobian(x)[rows])[:, : 2 * n].toarray()
        rr = sw[rows] * r[rows]
        H, g = J.T @ J, J.T @ rr
        c00 = sla.cho_factor(H[:n, :n])
        A = sla.cho_solve(c00, H[:n, n:])  # H00^-1 H01
        H1 = H[n:, n:] - H[n:, :n] @ A
        g1 = g[n:] - A.T @ g[:n]
        c11 = sla.cho_factor(0.5 * (H1 + H1.T))
        step = sla.cho_solve(c11, g1)
        head = p.cost(r) - p.cost(_without(r, rows))  # robust cost of the eliminated rows
        self.const += head - g[:n] @ sla.cho_solve(c00, g[:n]) - g1 @ step
        self.prior_x = self.X[1] - step
        self.prior_P = sla.cho_solve(c11, np.eye(n))
        self.prior_P = 0.5 * (self.prior_P + self.prior_P.T)
        e = self.s.epochs
        self.dropped += int(((e.vel_k == self.lo) & (self.s.vel_avail > self.s.now)).sum())
        self.X, self.lo = self.X[1:], self.lo + 1
        self.problem = None  # the next solve builds the shorter window

    def estimate(self, k: int) -> tuple[NDArray, NDArray]:
        """Mean and marginal covariance of epoch ``k`` (in the window) from the current solve."""
        n, i = self.s.model.n, k - self.lo
        if self.problem is None:
            return self.X[i].copy(), self.prior_P.copy()
        return self.X[i].copy(), self.problem.marginal(self.X, i)


def _without(r: NDArray, rows: NDArray) -> NDArray:
    out = r.copy()
    out[rows] = 0.0
    return out


class _Stream:
    """The run's readings, sliced into window problems by epoch range and availability time."""

    def __init__(
        self, model: FusionModel, epochs: Epochs, cfg: FixedLagConfig, vel_available_s: NDArray | None,
        axes: WalkAxes | None = None, area: WalkableArea | None = None,
    ) -> None:
        self.model, self.epochs, self.cfg, self.axes, self.area = model, epochs, cfg, axes, area
        e = epochs
        va = e.t_s[e.vel_k] if vel_available_s is None else np.asarray(vel_available_s, float).ravel()
        if va.shape != e.vel_k.shape or (va < e.t_s[e.vel_k] - 1e-9).any():
            raise EstimationError("fixed-lag: one availability time per velocity reading, not before its epoch")
        self.vel_avail = va
        self.now = float(e.t_s[0])

    def problem(
        self, lo: int, hi: int, now: float, x0: NDArray, P0: NDArray, rss_scale: NDArray
    ) -> MapProblem:
        e = self.epochs
        v = (e.vel_k >= lo) & (e.vel_k <= hi) & (self.vel_avail <= now)
        r = (e.rss_k >= lo) & (e.rss_k <= hi)
        f = (e.fix_k >= lo) & (e.fix_k <= hi)
        win = Epochs(
            e.t_s[lo : hi + 1], e.vel_k[v] - lo, e.vel_y[v], e.rss_k[r] - lo, e.rss_ap[r], e.rss_y[r],
            e.fix_k[f] - lo, e.fix_xy[f], e.fix_sigma[f], rss_scale[r],
            None if e.travel_m is None else e.travel_m[lo:hi],
        )
        return MapProblem(self.model, x0, P0, win, huber_k=self.cfg.huber_k, axes=self.axes, area=self.area)


def fixed_lag_smooth(
    model: FusionModel,
    starts: Sequence[NDArray],
    P0: NDArray,
    epochs: Epochs,
    cfg: FixedLagConfig = FixedLagConfig(),
    *,
    vel_available_s: NDArray | None = None,
    axes: WalkAxes | None = None,
    area: WalkableArea | None = None,
    progress: Callable[[int], None] | None = None,
) -> FixedLagRun:
    """Stream ``epochs`` through a bank of fixed-lag smoothers, one per start state ``x0`` (prior
    N(x0, P0) on the first epoch); report every epoch ``lag_s`` after its time (see module
    docstring). RSSI and fixes are available at their epoch; velocity readings at their epoch or
    at ``vel_available_s`` (one per reading, s, same clock as ``epochs.t_s``). ``axes``: the walk-axes
    prior on the velocity (``graphslam.core.tracking.axes``), ``area``: the walkable-area prior on the
    position (``graphslam.core.tracking.walkable``); map rows of every window. ``progress``: called
    with the number of epochs streamed so far, after each."""
    if not len(starts):
        raise EstimationError("fixed-lag: no start state")
    epochs.check_model(model)
    stream = _Stream(model, epochs, cfg, vel_available_s, axes, area)
    t = epochs.t_s
    N, n = len(epochs), model.n
    bank = [_Window(stream, x0, P0) for x0 in starts]
    xs, Ps = np.zeros((N, n)), np.zeros((N, n, n))
    hyp, at, vf = np.zeros(N, np.int64), np.zeros(N), np.ones(N)
    out, solves = 0, 0

    def report(upto_time: float) -> None:  # every epoch not yet reported whose time + lag <= upto
        nonlocal out
        live = [h for h, w in enumerate(bank) if w.alive]
        while out < N and out <= bank[live[0]].hi and t[out] + cfg.lag_s <= upto_time + 1e-9:
            b = min(live, key=lambda h: bank[h].total_cost)
            if cfg.report == "mixture" and len(live) > 1:
                costs = np.array([bank[h].total_cost for h in live])
                xs[out], Ps[out] = mixture_moments(
                    [bank[h].estimate(out) for h in live], costs / cfg.temper, live.index(b), cfg.angle_index
                )
            else:
                xs[out], Ps[out] = bank[b].estimate(out)
            hyp[out], at[out], vf[out] = b, stream.now, bank[b].variance_factor
            out += 1

    for j in range(N):
        now = float(t[j])
        if j:
            report(np.nextafter(now, -np.inf))  # the previous solve is the latest before ``now``
        stream.now = now
        for w in bank:
            if not w.alive:
                continue
            w.extend(j)
            w.innovate(j)
            while w.lo < j and t[w.lo] < now - cfg.window_s - 1e-9 and w.lo < out:
                w.marginalise_first()
            w.solve(now, restart=cfg.restart_every > 0 and j % cfg.restart_every == 0 and j > 0)
            solves += 1
        _prune(bank, None if cfg.prune_cost is None else cfg.prune_cost * cfg.temper)
        if progress is not None:
            progress(j + 1)
    report(math.inf)
    costs = np.array([w.total_cost if w.alive else np.inf for w in bank])
    return FixedLagRun(xs, Ps, hyp, at, vf, costs, solves, bank[int(np.argmin(costs))].dropped)


def mixture_moments(
    estimates: Sequence[tuple[NDArray, NDArray]], costs: NDArray, ref: int, angle_index: int | None = None
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Mean and covariance of the Gaussian mixture of the hypotheses' estimates ``(x_h, P_h)``,
    weighted by their posterior odds ``exp(-cost_h / 2)`` (``cost``: twice the negative log
    posterior). The minimum-mean-square-error estimate when the bank is unsure, the best
    hypothesis when it is not; the covariance holds the spread between hypotheses. Differences
    are taken from hypothesis ``ref``; entry ``angle_index`` (differences and the mean) is wrapped
    to [-pi, pi)."""
    w = np.exp(-0.5 * (np.asarray(costs, float) - np.min(costs)))
    w /= w.sum()
    X = np.array([x for x, _ in estimates])
    d = X - X[ref]
    if angle_index is not None:
        d[:, angle_index] = np.remainder(d[:, angle_index] + math.pi, 2 * math.pi) - math.pi
    mean_d = w @ d
    e = d - mean_d
    Ps = np.array([Ph for _, Ph in estimates])
    P = np.einsum("h,hij->ij", w, Ps) + (e * w[:, None]).T @ e  # within + between hypotheses
    mean = X[ref] + mean_d
    if angle_index is not None:  # the reference's angle plus a wrapped difference can leave [-pi, pi)
        mean[angle_index] = np.remainder(mean[angle_index] + math.pi, 2 * math.pi) - math.pi
    return mean, 0.5 * (P + P.T)


def _prune(bank: list[_Window], prune_cost: float | None) -> None:
    if prune_cost is None:
        return
    best = min(w.total_cost for w in bank if w.alive)
    for w in bank:
        if w.alive and w.total_cost > best + prune_cost:
            w.alive = False

