"""Fixed-lag smoothing: online estimates with a latency, from a sliding window of recent epochs.

The state at time ``t`` is reported once the readings up to ``t + lag_s`` are in, as the maximum
a-posteriori estimate of the window of epochs in ``[t_now - window_s, t_now]`` under the filters'
own model (``graphslam.core.tracking.filters.FusionModel``: process eq. 3 with Q(dt), velocity
eq. 4, RSSI eq. 6, position fixes), solved by Levenberg-Marquardt (``MapProblem``'s cost and steps,
``graphslam.core.tracking.smoother``) warm-started from the previous window; the bank's hypotheses
share their window's readings and are solved together (``graphslam.core.tracking.window``).
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
Starts that reach the same solution (window states within ``merge_tol`` in every entry) are
merged into the cheapest, which takes over their posterior mass (``_Bank.merge``): the bank solves
each distinct hypothesis once, its weights and odds as before.

With ``axes`` every window also holds the walk-axes prior on its velocities
(``graphslam.core.tracking.axes``), with ``area`` the walkable-area prior on its step positions
(``graphslam.core.tracking.walkable``), each marginalised with its epoch like any other row.

Frames and units as the filters (m, m/s, rad, dBm, s).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from graphslam.core.tracking.axes import WalkAxes
from graphslam.core.tracking.filters import Epochs, FusionModel
from graphslam.core.tracking.smoother import MapProblem, dead_reckoning_starts, levenberg_marquardt
from graphslam.core.tracking.walkable import WalkableArea
from graphslam.core.tracking.window import (
    RunReadings, WindowProblem, banded_cholesky, levenberg_marquardt_bank, marginal_covariances,
)
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
    rel_tol: float = 1e-5  # LM stops when a step lowers the window cost by less than this share
    max_damping: float = 1.0  # ... or when its damping would grow beyond this (steps that damped change nothing)
    stall_tol: float | None = 1e-3  # ... or when a step promising less than this share of the cost raises it (None: retry damped)
    prune_cost: float | None = DEFAULTS.fixed_lag.prune_cost
    adaptive_rssi: bool = DEFAULTS.rssi.adaptive  # scale an epoch's RSSI std by its innovations' NIS per reading (> 1)
    prior_count: float = 4.0  # pseudo-fixes of NIS 2 in the variance factor
    report: str = DEFAULTS.fixed_lag.bank_report  # best: the lowest-cost hypothesis | mixture: the bank's posterior mixture
    angle_index: int | None = None  # state entry that is an angle (mixture differences wrapped)
    temper: float = 1.0  # the bank's costs are divided by this in its weights and pruning (correlated readings)
    merge_tol: float | None = 0.05  # hypotheses whose window states agree to this (m, m/s, rad; every entry) become one (None: never)

    def __post_init__(self) -> None:
        if not (self.lag_s >= 0 and self.window_s >= self.lag_s):
            raise EstimationError(f"fixed-lag: need 0 <= lag_s <= window_s, got lag {self.lag_s}, window {self.window_s}")
        if self.huber_k is not None and self.huber_k <= 0:
            raise EstimationError(f"fixed-lag: huber_k must be > 0, got {self.huber_k}")
        if self.max_iter < 1 or (self.prune_cost is not None and self.prune_cost <= 0) or not self.max_damping > 0:
            raise EstimationError("fixed-lag: max_iter >= 1, prune_cost > 0 and max_damping > 0 required")
        if not (math.isfinite(self.rel_tol) and self.rel_tol >= 0) or (
                self.stall_tol is not None and not (math.isfinite(self.stall_tol) and self.stall_tol >= 0)):
            raise EstimationError(f"fixed-lag: rel_tol and stall_tol must be finite numbers >= 0, got {self.rel_tol}, {self.stall_tol}")
        if self.merge_tol is not None and not (math.isfinite(self.merge_tol) and self.merge_tol > 0):
            raise EstimationError(f"fixed-lag: merge_tol must be a finite number > 0 or None, got {self.merge_tol}")
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
    cost: NDArray[np.float64]  # (H,) final total cost per hypothesis (inf: pruned, or merged into another)
    solves: int
    readings_dropped: int  # arrived after their epoch had been marginalised

    @property
    def trace_p(self) -> NDArray[np.float64]:
        return np.trace(self.P, axis1=1, axis2=2)


class _Bank:
    """The bank's hypotheses in lock-step: one window ``[lo, hi]`` of the run's epochs; per hypothesis
    its prior, states, RSSI std scales, the cost of what it marginalised and its fix statistics.
    Each step's work is done for the live hypotheses together (``graphslam.core.tracking.window``)."""

    def __init__(self, stream: "_Stream", starts: Sequence[NDArray], P0: NDArray) -> None:
        self.s = stream
        H, n = len(starts), stream.model.n
        self.lo = self.hi = 0
        self.prior_x = np.array([np.asarray(x0, float).ravel() for x0 in starts]).reshape(H, n)
        try:
            info = np.linalg.inv(np.linalg.cholesky(np.asarray(P0, float).reshape(n, n)))
        except np.linalg.LinAlgError:
            raise EstimationError("fixed-lag: P0 is not positive definite") from None
        self.prior_info = np.repeat((info.T @ info)[None], H, axis=0)  # inverse covariance: what a window needs
        self.X = self.prior_x[:, None, :].copy()  # (H, window epochs, n)
        self.const = np.zeros(H)  # cost of what was marginalised, at its minimum
        self.window_cost = np.zeros(H)
        self.alive = np.ones(H, bool)
        self.dropped = np.zeros(H, np.int64)  # velocity readings of marginalised epochs that were not yet available
        self.rss_scale = np.repeat(stream.run.rss_scale[None, :], H, axis=0)  # as used: adaptive RSSI scales new epochs
        cfg = stream.cfg
        # innovation statistics of the position fixes (see ``innovate``), with prior pseudo-counts
        self.n_fix = np.full(H, cfg.prior_count)
        self.sum_nis = np.full(H, 2.0 * cfg.prior_count)  # E[NIS] = 2 (dof) when the model is right
        self._solved: _Solved | None = None
        self._factor: NDArray | None = None

    @property
    def prior_P(self) -> NDArray[np.float64]:
        """(H, n, n) prior covariances."""
        P = np.linalg.inv(self.prior_info)
        return 0.5 * (P + np.swapaxes(P, 1, 2))

    @property
    def live(self) -> NDArray[np.int64]:
        return np.flatnonzero(self.alive)

    @property
    def total_cost(self) -> NDArray[np.float64]:
        return self.const + self.window_cost

    def variance_factor(self, h: int) -> float:
        """Mean fix NIS / 2 so far (prior: 1): how much larger the innovations are than the model
        says. Scaling every covariance by it is the covariance-matching estimate of one common
        variance factor (the estimate does not change, its reported uncertainty does)."""
        return max(1.0, float(self.sum_nis[h]) / (2.0 * float(self.n_fix[h])))

    def extend(self, hi: int) -> None:
        """Add epochs up to ``hi``, started by the noise-free process from the newest estimate."""
        m, t = self.s.model, self.s.epochs.t_s
        rows = [self.X]
        x = self.X[:, -1]
        for k in range(self.hi + 1, hi + 1):
            x = m.propagate(x, float(t[k] - t[k - 1]), self.s.epochs.interval_travel(k - 1))
            rows.append(x[:, None, :])
        self.X, self.hi = np.concatenate(rows, axis=1), hi

    def innovate(self, j: int) -> None:
        """Before epoch ``j``'s solve: the innovations of epoch ``j``'s fixes and RSSI readings
        against the prediction from the previous solve (mean, and covariance propagated by the
        process). Fix NIS feeds ``variance_factor``; with ``adaptive_rssi`` an epoch whose RSSI
        NIS per reading exceeds 1 has its RSSI std scaled by its square root (the filters'
        adaptive R, ``filters._inflate_rssi_noise``, kept for that epoch)."""
        s, cfg = self.s, self.s.cfg
        e = s.epochs
        fixes = range(s.run.fix_at[j], s.run.fix_at[j + 1])
        rss = np.arange(s.run.rss_at[j], s.run.rss_at[j + 1]) if cfg.adaptive_rssi else np.zeros(0, np.int64)
        if not (len(fixes) or len(rss)) or self._solved is None or j != self.hi or j - 1 < self.lo:
            return
        m, hs = s.model, self.live
        dt, dist = float(e.t_s[j] - e.t_s[j - 1]), e.interval_travel(j - 1)
        F = m.transition(dt, dist)
        Pp = F @ self.marginals(j - 1 - self.lo, hs) @ F.T + m.process_noise(dt, dist)
        xl = self.X[hs, -1]
        for i in fixes:
            nu = e.fix_xy[i] - xl[:, :2]
            S = Pp[:, :2, :2] + np.eye(2) * e.fix_sigma[i] ** 2
            self.sum_nis[hs] += np.einsum("bi,bi->b", nu, np.linalg.solve(S, nu[..., None])[..., 0])
            self.n_fix[hs] += 1
        if len(rss):
            ap, B = e.rss_ap[rss], len(hs)
            law = s.run.law.take(rss)  # these readings' AP laws and field, gathered once per run
            x, y = xl[:, 0:1], xl[:, 1:2]  # (B, 1) against the readings' (R,)
            Hm = np.zeros((B, len(rss), m.n))
            Hm[..., 0], Hm[..., 1] = law.gradient(x, y)
            pred = law.mean(x, y)
            if m.shadowing is not None:
                Hm[:, np.arange(len(rss)), m.shadow_state(ap)] = 1.0
                pred = pred + xl[:, m.shadow_state(ap)]
            nu = e.rss_y[rss] - pred
            S = Hm @ Pp @ np.swapaxes(Hm, 1, 2)
            S[:, np.arange(len(rss)), np.arange(len(rss))] += m.r_rssi[ap] * self.rss_scale[hs][:, rss] ** 2
            ratio = np.einsum("bi,bi->b", nu, np.linalg.solve(S, nu[..., None])[..., 0]) / len(rss)
            up = ratio > 1.0
            self.rss_scale[np.ix_(hs[up], rss)] *= np.sqrt(ratio[up])[:, None]

    def solve(self, now: float, restart: bool = False) -> None:
        hs, cfg = self.live, self.s.cfg
        p = self.s.run.window(self.lo, self.hi, now, self.prior_x[hs], self.prior_info[hs], self.rss_scale[hs])
        X, cost, r, band, g, fresh = levenberg_marquardt_bank(
            p, self.X[hs], cfg.max_iter, rel_tol=cfg.rel_tol, max_damping=cfg.max_damping, stall_tol=cfg.stall_tol)
        if restart:
            prior_P = self.prior_P
            for b, h in enumerate(hs):
                mp = self.s.problem(self.lo, self.hi, now, self.prior_x[h], prior_P[h], self.rss_scale[h])
                for X0 in dead_reckoning_starts(mp):
                    Xr, cr, _ = levenberg_marquardt(mp, X0, cfg.max_iter * 5, rel_tol=cfg.rel_tol)
                    if cr < cost[b]:
                        X[b], cost[b], fresh[b] = Xr, cr, False
            r = p.residual(X)
        if not fresh.all():  # the information at the final states (marginals, marginalisation)
            k = np.flatnonzero(~fresh)
            band[k], g[k] = p.normal_equations(X[k], r[k], k)
        self.X[hs], self.window_cost[hs] = X, cost
        # what marginalising the first epoch needs, kept before the band becomes its factor
        self._solved = _Solved(p, hs, now, r, band, band[:, : p.n].copy(), g[:, : p.n].copy())
        self._factor = None

    def marginals(self, i: int, hs: NDArray) -> NDArray[np.float64]:
        """(len(hs), n, n) marginal covariances of window epoch ``i`` of the hypotheses ``hs`` at the
        last solve: one block column of the inverse information of each, by banded solves."""
        sv = self._solved
        if sv is None:
            return self.prior_P[hs]
        if self._factor is None:
            self._factor = banded_cholesky(sv.band, overwrite=True)
            if self._factor is None:
                raise EstimationError("fixed-lag: the information matrix is singular (unobservable state)")
        S = marginal_covariances(self._factor, len(sv.hs), sv.p.size, sv.p.n, i)
        return S[np.searchsorted(sv.hs, hs)]

    def marginalise_first(self) -> None:
        """Eliminate epoch ``lo`` (linearised at the current estimate); prior on ``lo + 1``."""
        assert self.hi > self.lo
        hs, n, s = self.live, self.s.model.n, self.s
        # the rows that touch epoch lo (its prior, its readings known now, the process step to lo + 1):
        # those of the last solve's window when it is this one's (its information and gradient at
        # the current states), else their own problem
        sv, run = self._solved, s.run
        v = slice(run.vel_at[self.lo], run.vel_at[self.lo + 1])
        at = None if sv is None else np.searchsorted(sv.hs, hs)  # live now among those solved (pruning only drops)
        if (sv is not None and sv.p.N > 1 and ((run.vel_avail[v] <= sv.now) == (run.vel_avail[v] <= s.now)).all()):
            H = np.zeros((len(hs), 2 * n, 2 * n))
            rows, cols, d = _first_block_maps(n)
            H[:, rows, cols] = H[:, cols, rows] = sv.block0[at][:, cols, d]
            H[:, np.arange(n, 2 * n), np.arange(n, 2 * n)] = sv.p.inv_sq[0] ** 2  # the process step alone
            r = sv.r[at]
            g = np.concatenate([sv.g0[at], r[:, n : 2 * n] * sv.p.inv_sq[0]], axis=1)
            head = sv.p.first_epoch_cost(r)
        else:
            p = run.window(self.lo, self.lo + 1, s.now, self.prior_x[hs], self.prior_info[hs], self.rss_scale[hs], upto=self.lo)
            X2 = self.X[hs, :2]
            r = p.residual(X2)
            band, g = p.normal_equations(X2, r)
            H, head = p.dense(band), p.cost(r)
        g0, g1 = g[:, :n], g[:, n:]
        try:
            A = np.linalg.solve(H[:, :n, :n], np.concatenate([H[:, :n, n:], g0[..., None]], axis=2))
            H1 = H[:, n:, n:] - H[:, n:, :n] @ A[..., :n]  # H00^-1 H01 in A's first columns, H00^-1 g0 in its last
            H1 = 0.5 * (H1 + np.swapaxes(H1, 1, 2))
            g1 = g1 - np.einsum("bij,bi->bj", A[..., :n], g0)
            step = np.linalg.solve(H1, g1[..., None])[..., 0]
        except np.linalg.LinAlgError:
            raise EstimationError("fixed-lag: the marginalised epoch's information is singular") from None
        self.const[hs] += head - np.einsum("bi,bi->b", g0, A[..., n]) - np.einsum("bi,bi->b", g1, step)
        self.prior_x[hs] = self.X[hs, 1] - step
        self.prior_info[hs] = H1
        self.dropped[hs] += int((run.vel_avail[v] > s.now).sum())
        self.X, self.lo = self.X[:, 1:], self.lo + 1
        self._solved = self._factor = None  # the next solve builds the shorter window

    def prune(self, prune_cost: float | None) -> None:
        if prune_cost is None:
            return
        tc = self.total_cost
        self.alive &= ~(tc > tc[self.alive].min() + prune_cost)

    def merge(self, tol: float | None, temper: float, angle_index: int | None) -> None:
        """Hypotheses whose window states agree to ``tol`` in every entry (the angle's difference
        wrapped) are one hypothesis reached from several starts: the cheapest is kept, its cost
        lowered by the others' posterior mass (``-2 T log sum exp(-cost / 2 T)`` over the group), so
        the bank's mixture weights and odds against the other hypotheses stay as they were."""
        hs = self.live
        if tol is None or len(hs) < 2:
            return
        X = self.X[hs]
        D = X[:, None] - X[None]
        if angle_index is not None:
            D[..., angle_index] = np.remainder(D[..., angle_index] + math.pi, 2 * math.pi) - math.pi
        close = np.abs(D).max(axis=(2, 3)) <= tol
        tc = self.total_cost[hs]
        order = np.argsort(tc, kind="stable")
        gone = np.zeros(len(hs), bool)
        for i in order:
            if gone[i]:
                continue
            group = np.flatnonzero(close[i] & ~gone)
            group = group[group != i]
            if not len(group):
                continue
            gone[group] = True
            u = (tc[group] - tc[i]) / (2.0 * temper)  # >= 0
            self.const[hs[i]] -= 2.0 * temper * np.log1p(np.exp(-u).sum())
        self.alive[hs[gone]] = False


@dataclass(eq=False)
class _Solved:
    """The last solve: its problem, hypotheses and time, final residuals and information (band, to
    be factored in place), and the first epoch's block column of that band and of the gradient."""

    p: WindowProblem
    hs: NDArray[np.int64]
    now: float
    r: NDArray[np.float64]
    band: NDArray[np.float64]
    block0: NDArray[np.float64]
    g0: NDArray[np.float64]


@lru_cache(maxsize=8)
def _first_block_maps(n: int) -> tuple[NDArray, NDArray, NDArray]:
    """Row, column (< n) and band offset of the lower entries of the first two epochs' information
    that a band (kd = n) holds in the first epoch's columns."""
    cols, d = np.divmod(np.arange(n * (n + 1)), n + 1)
    return cols + d, cols, d


class _Stream:
    """The run's readings, each kind sorted by epoch (``run``: sliced into the windows' problems)."""

    def __init__(
        self, model: FusionModel, epochs: Epochs, cfg: FixedLagConfig, vel_available_s: NDArray | None,
        axes: WalkAxes | None = None, area: WalkableArea | None = None,
    ) -> None:
        self.model, self.cfg, self.axes, self.area = model, cfg, axes, area
        e = epochs
        va = e.t_s[e.vel_k] if vel_available_s is None else np.asarray(vel_available_s, float).ravel()
        if va.shape != e.vel_k.shape or (va < e.t_s[e.vel_k] - 1e-9).any():
            raise EstimationError("fixed-lag: one availability time per velocity reading, not before its epoch")
        run = self.run = RunReadings(model, e, va, huber_k=cfg.huber_k, axes=axes, area=area)
        self.epochs = Epochs(
            e.t_s, run.vel_k, run.vel_y, run.rss_k, run.rss_ap, run.rss_y, run.fix_k, run.fix_xy, run.fix_sigma,
            run.rss_scale, e.travel_m,
        )
        self.now = float(e.t_s[0])

    def problem(
        self, lo: int, hi: int, now: float, x0: NDArray, P0: NDArray, rss_scale: NDArray
    ) -> MapProblem:
        """The window ``[lo, hi]`` at ``now`` for one hypothesis as a ``MapProblem`` (the dead-reckoning
        restarts): prior N(x0, P0), RSSI scales per reading of the run."""
        e, run = self.epochs, self.run
        v = (e.vel_k >= lo) & (e.vel_k <= hi) & (run.vel_avail <= now)
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
    bank = _Bank(stream, starts, P0)
    xs, Ps = np.zeros((N, n)), np.zeros((N, n, n))
    hyp, at, vf = np.zeros(N, np.int64), np.zeros(N), np.ones(N)
    out, solves = 0, 0

    def report(upto_time: float) -> None:  # every epoch not yet reported whose time + lag <= upto
        nonlocal out
        live = bank.live
        while out < N and out <= bank.hi and t[out] + cfg.lag_s <= upto_time + 1e-9:
            tc = bank.total_cost[live]
            b = int(live[np.argmin(tc)])
            i = out - bank.lo
            if cfg.report == "mixture" and len(live) > 1:
                xs[out], Ps[out] = mixture_moments(
                    list(zip(bank.X[live, i], bank.marginals(i, live))), tc / cfg.temper, int(np.argmin(tc)),
                    cfg.angle_index,
                )
            else:
                xs[out], Ps[out] = bank.X[b, i], bank.marginals(i, np.array([b]))[0]
            hyp[out], at[out], vf[out] = b, stream.now, bank.variance_factor(b)
            out += 1

    for j in range(N):
        now = float(t[j])
        if j:
            report(np.nextafter(now, -np.inf))  # the previous solve is the latest before ``now``
        stream.now = now
        bank.extend(j)
        bank.innovate(j)
        while bank.lo < j and t[bank.lo] < now - cfg.window_s - 1e-9 and bank.lo < out:
            bank.marginalise_first()
        bank.solve(now, restart=cfg.restart_every > 0 and j % cfg.restart_every == 0 and j > 0)
        solves += len(bank.live)
        bank.prune(None if cfg.prune_cost is None else cfg.prune_cost * cfg.temper)
        bank.merge(cfg.merge_tol, cfg.temper, cfg.angle_index)
        if progress is not None:
            progress(j + 1)
    report(math.inf)
    costs = np.where(bank.alive, bank.total_cost, np.inf)
    return FixedLagRun(xs, Ps, hyp, at, vf, costs, solves, int(bank.dropped[int(np.argmin(costs))]))


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
