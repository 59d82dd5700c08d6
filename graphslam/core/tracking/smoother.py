"""Offline smoothing of a fusion run: Rauch-Tung-Striebel and whole-run MAP.

The causal filters (``graphslam.core.tracking.filters``) estimate each state from the past only. Offline
(a survey processed after the walk) every state can use the whole run:

- ``rts_smooth``: the RTS backward pass over a filter's output (the process, eq. 3, is linear);
- ``map_smooth``: the maximum a-posteriori trajectory under the filters' own model (prior
  N(x0, P0), process residuals with Q(dt), velocity (eq. 4) and RSSI (eq. 6) residuals with R)
  by sparse Levenberg-Marquardt from the given starts, lowest cost kept; marginal covariances
  from the block-tridiagonal information matrix at the optimum. Gauss-Newton on this cost is
  the iterated extended Kalman smoother; the LM damping keeps it from diverging where a
  linearisation is poor (e.g. an estimate outside the AP rectangle).

Why it matters (docs/tracking.md, the cart experiment): the EKF lets its bias state absorb the
first round's spatially correlated shadowing, and the position offset that integrates from it
never leaves; the whole-run MAP under the same model does not.

Same frame, units and state layout as the filters (m, m/s, rad, dBm; states in rows).
Residuals and Jacobians are vectorised over readings; the linear solves are sparse.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Literal, Sequence

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from numpy.typing import NDArray

from graphslam.core.tracking.axes import WalkAxes
from graphslam.core.tracking.filters import Epochs, FilterRun, FusionModel, velocity_matrix
from graphslam.core.tracking.walkable import WalkableArea
from graphslam.errors import EstimationError

log = logging.getLogger(__name__)

SmoothMethod = Literal["rts", "map"]
SMOOTH_METHODS: tuple[str, ...] = ("rts", "map")


@dataclass(frozen=True, eq=False)
class SmoothedRun:
    """Smoothed states ``x`` (N, n) and marginal covariances ``P`` (N, n, n) at every epoch.

    ``cost``: sum of squared whitened residuals of the whole run at ``x`` (Huber-weighted RSSI
    rows when robust), i.e. twice the negative log posterior up to a constant; lower is a more
    probable trajectory (NaN for RTS, which does not evaluate it). ``start``: index of the
    start the MAP kept (0 for RTS).
    """

    method: str
    x: NDArray[np.float64]
    P: NDArray[np.float64]
    cost: float
    iterations: int
    start: int = 0

    @property
    def trace_p(self) -> NDArray[np.float64]:
        return np.trace(self.P, axis1=1, axis2=2)


class MapProblem:
    """Whitened residuals of a whole run under ``model`` and their sparse Jacobian.

    Row blocks: prior (n), process ((N - 1) n), velocity (2 per reading), then the map rows:
    RSSI (1 per reading), position fixes (2 per fix), with ``axes`` the walk-axes prior on the
    velocity (1 per velocity reading; ``graphslam.core.tracking.axes``) and with ``area`` the
    walkable-area prior on the position (1 per velocity reading, i.e. per step;
    ``graphslam.core.tracking.walkable``). ``huber_k`` (in standard
    deviations) turns the map rows' squares into Huber's loss. With ``model.shadowing`` an RSSI row also
    holds its AP's offset state, and the process decays the offsets over ``epochs.travel_m``.
    """

    def __init__(
        self, model: FusionModel, x0: NDArray, P0: NDArray, epochs: Epochs, *, huber_k: float | None = None,
        axes: WalkAxes | None = None, area: WalkableArea | None = None,
    ) -> None:
        epochs.check_model(model)
        n, N = model.n, len(epochs)
        if (np.asarray(model.q_diag) <= 0).any():
            raise EstimationError("map smoothing needs every process-noise variance > 0")
        if huber_k is not None and huber_k <= 0:
            raise EstimationError(f"map smoothing: huber_k must be > 0, got {huber_k}")
        x0 = np.asarray(x0, float).ravel()
        if x0.shape != (n,) or np.shape(P0) != (n, n):
            raise EstimationError(f"map smoothing: prior of shape {x0.shape} / {np.shape(P0)} for a state of size {n}")
        try:
            C = np.linalg.cholesky(np.asarray(P0, float))
        except np.linalg.LinAlgError:
            raise EstimationError("map smoothing: P0 is not positive definite") from None
        self.model, self.epochs, self.n, self.N, self.huber_k, self.axes = model, epochs, n, N, huber_k, axes
        self.area = area
        self.x0, self.P0 = x0, np.asarray(P0, float)
        self._W0 = sla.solve_triangular(C, np.eye(n), lower=True)  # C^-1: whitens x - x0
        self._dt = epochs.dt
        self._sq = np.sqrt(np.outer(self._dt / model.period_s, model.q_diag))  # (N-1, n) process std
        self._rho = np.ones((N - 1, n))  # (N-1, n) diagonal of the transition (1; shadowing: its decay)
        self._shadow = model.shadowing is not None
        if model.shadowing is not None:
            if epochs.travel_m is None:
                raise EstimationError(
                    "map smoothing: a model with shadowing states needs the distance moved (Epochs.travel_m)")
            rho = model.shadowing.decay(epochs.travel_m)
            self._rho[:, model.n_base:] = rho[:, None]
            sd = np.sqrt(model.shadowing.noise_var(rho))
            self._sq = np.hstack([self._sq, np.repeat(sd[:, None], n - model.n_base, axis=1)])
            self._rss_col = model.shadow_state(epochs.rss_ap)  # state index of each reading's offset
        self._sv = np.sqrt(model.r_velocity)
        self._sr = np.sqrt(model.r_rssi[epochs.rss_ap]) * epochs.rss_scale
        n_axes = len(epochs.vel_k) if axes is not None else 0
        n_area = len(epochs.vel_k) if area is not None else 0
        self._rows = np.cumsum(
            [0, n, (N - 1) * n, 2 * len(epochs.vel_k), len(epochs.rss_k) + 2 * len(epochs.fix_k) + n_axes + n_area])
        self._pattern = self._structure()
        self._pairs: tuple[NDArray, NDArray, NDArray, NDArray] | None = None

    @property
    def size(self) -> int:
        return self.N * self.n

    def residual(self, X: NDArray) -> NDArray[np.float64]:
        """All whitened residuals (unweighted) at states ``X`` (N, n)."""
        m, e = self.model, self.epochs
        X = np.asarray(X, float).reshape(self.N, self.n)
        proc = X[1:] - self._rho * X[:-1]
        proc[:, 0:2] -= self._dt[:, None] * X[:-1, 2:4]
        xv = X[e.vel_k]
        th = xv[:, 6] if m.theta_rad is None else np.full(len(xv), m.theta_rad)
        vel = e.vel_y - np.einsum("mij,mj->mi", velocity_matrix(th), xv[:, 2:4]) - xv[:, 4:6]
        h = m.path_loss.rss_mean(X[e.rss_k, 0:2], e.rss_ap)
        if self._shadow:
            h = h + X[e.rss_k, self._rss_col]
        return np.concatenate([
            self._W0 @ (X[0] - self.x0), (proc / self._sq).ravel(), (vel / self._sv).ravel(), (e.rss_y - h) / self._sr,
            ((e.fix_xy - X[e.fix_k, 0:2]) / e.fix_sigma[:, None]).ravel(),
            self.axes.residual(xv[:, 2:4]) if self.axes is not None else np.zeros(0),
            self.area.residual(xv[:, 0:2]) if self.area is not None else np.zeros(0),
        ])

    def weights(self, r: NDArray) -> NDArray[np.float64]:
        """IRLS square-root weights: 1, except Huber's sqrt(k / |r|) on map rows beyond k."""
        sw = np.ones(len(r))
        if self.huber_k is not None:
            a = np.abs(r[self._rows[3]:])
            sw[self._rows[3]:] = np.sqrt(np.minimum(1.0, self.huber_k / np.maximum(a, 1e-300)))
        return sw

    def cost(self, r: NDArray) -> float:
        """Sum of squares; Huber 2 k |r| - k^2 beyond k on map rows (RSSI, fixes) when robust."""
        if self.huber_k is None:
            return float(r @ r)
        k, head, a = self.huber_k, r[: self._rows[3]], np.abs(r[self._rows[3]:])
        return float(head @ head + np.where(a <= k, a * a, 2.0 * k * a - k * k).sum())

    def _structure(self) -> tuple[NDArray, NDArray]:
        """Row and column of every Jacobian entry, in the order ``jacobian`` fills them."""
        n, N, e = self.n, self.N, self.epochs
        rows, cols = [], []
        r0 = np.repeat(np.arange(n), n)
        rows.append(r0)
        cols.append(np.tile(np.arange(n), n))
        k = np.arange(N - 1)
        base = self._rows[1] + k[:, None] * n + np.arange(n)  # (N-1, n) process rows
        rows += [base.ravel(), base.ravel(), base[:, 0:2].ravel()]
        cols += [((k[:, None] + 1) * n + np.arange(n)).ravel(), (k[:, None] * n + np.arange(n)).ravel(),
                 (k[:, None] * n + np.arange(2, 4)).ravel()]
        j = np.arange(len(e.vel_k))
        vr = self._rows[2] + 2 * j[:, None] + np.arange(2)  # (Mv, 2)
        vc = e.vel_k[:, None] * n
        per_row = [2, 3, 4, 5] + ([6] if self.model.theta_rad is None else [])  # vx vy bx by (theta)
        for c in per_row:
            rows.append(vr.ravel())
            cols.append((vc + np.array([c, c])).ravel())
        rr = self._rows[3] + np.arange(len(e.rss_k))
        rows += [rr, rr]
        cols += [e.rss_k * n, e.rss_k * n + 1]
        if self._shadow:
            rows.append(rr)
            cols.append(e.rss_k * n + self._rss_col)
        fr = self._rows[3] + len(e.rss_k) + np.arange(2 * len(e.fix_k))  # x, y row of each fix
        rows.append(fr)
        cols.append((e.fix_k[:, None] * n + np.arange(2)).ravel())
        n_axes = len(e.vel_k) if self.axes is not None else 0
        if self.axes is not None:  # one row per velocity reading, on that epoch's vx, vy
            ar = self._rows[3] + len(e.rss_k) + 2 * len(e.fix_k) + np.arange(len(e.vel_k))
            rows += [ar, ar]
            cols += [e.vel_k * n + 2, e.vel_k * n + 3]
        if self.area is not None:  # one row per velocity reading (a step), on that epoch's x, y
            wr = self._rows[3] + len(e.rss_k) + 2 * len(e.fix_k) + n_axes + np.arange(len(e.vel_k))
            rows += [wr, wr]
            cols += [e.vel_k * n, e.vel_k * n + 1]
        return np.concatenate(rows), np.concatenate(cols)

    def jacobian(self, X: NDArray) -> sp.csr_matrix:
        """d residual / d X (rows as ``residual``, columns state-major: epoch k, component i -> k n + i)."""
        r, c = self._pattern
        return sp.csr_matrix((self.jacobian_values(X), (r, c)), shape=(self._rows[-1], self.size))

    def jacobian_values(self, X: NDArray) -> NDArray[np.float64]:
        """The Jacobian's entries, in the order of ``_structure``'s (row, column) pattern."""
        m, e, n = self.model, self.epochs, self.n
        X = np.asarray(X, float).reshape(self.N, n)
        inv_sq = 1.0 / self._sq
        vals = [self._W0.ravel(), inv_sq.ravel(), (-self._rho * inv_sq).ravel(), (-self._dt[:, None] * inv_sq[:, 0:2]).ravel()]
        xv = X[e.vel_k]
        th = xv[:, 6] if m.theta_rad is None else np.full(len(xv), m.theta_rad)
        M = velocity_matrix(th)  # (Mv, 2, 2)
        inv_sv = 1.0 / self._sv
        vals += [(-M[:, :, 0] * inv_sv).ravel(), (-M[:, :, 1] * inv_sv).ravel()]
        vals += [np.tile([-inv_sv[0], 0.0], len(xv)), np.tile([0.0, -inv_sv[1]], len(xv))]
        if m.theta_rad is None:
            s, c = np.sin(th), np.cos(th)
            dM = np.stack([np.stack([-c, -s], -1), np.stack([-s, c], -1)], -2)  # d M / d theta
            vals.append((-np.einsum("mij,mj->mi", dM, xv[:, 2:4]) * inv_sv).ravel())
        g = m.path_loss.rss_gradient(X[e.rss_k, 0:2], e.rss_ap)
        vals += [-g[:, 0] / self._sr, -g[:, 1] / self._sr] + ([-1.0 / self._sr] if self._shadow else [])
        vals.append(-np.repeat(1.0 / e.fix_sigma, 2))
        if self.axes is not None:
            Ja = self.axes.jacobian(xv[:, 2:4])
            vals += [Ja[:, 0], Ja[:, 1]]
        if self.area is not None:
            Jw = self.area.jacobian(xv[:, 0:2])
            vals += [Jw[:, 0], Jw[:, 1]]
        return np.concatenate(vals)

    def _band_pairs(self) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
        """For ``normal_equations``: every pair (a, b) of Jacobian entries in one row with column
        a <= column b, their row, and the flat index of (col a, col b) in the upper band. Each row
        holds at most n entries, so there are O(rows n^2) pairs; computed once per problem."""
        if self._pairs is None:
            r, c = self._pattern
            order = np.argsort(r, kind="stable")
            rs = r[order]
            counts = np.bincount(rs, minlength=self._rows[-1])
            start = np.cumsum(counts) - counts
            m = counts[rs]  # partners of each entry (its row's size)
            a = np.repeat(order, m)
            offs = np.arange(m.sum()) - np.repeat(np.cumsum(m) - m, m)
            b = order[np.repeat(start[rs], m) + offs]
            keep = c[a] <= c[b]
            a, b = a[keep], b[keep]
            u = 2 * self.n - 1
            self._pairs = (a, b, r[a], (u + c[a] - c[b]) * self.size + c[b])
        return self._pairs

    def normal_equations(self, X: NDArray, r: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Gauss-Newton system at ``X`` with residuals ``r``: the upper band (``banded`` layout) of
        J^T W J and the gradient J^T W r (W: IRLS weights), assembled without a sparse matrix."""
        w = self.weights(r) ** 2
        v = self.jacobian_values(X)
        a, b, row, flat = self._band_pairs()
        band = np.bincount(flat, weights=v[a] * v[b] * w[row], minlength=2 * self.n * self.size)
        rr, cc = self._pattern
        g = np.bincount(cc, weights=v * (w * r)[rr], minlength=self.size)
        return band.reshape(2 * self.n, self.size), g

    def banded(self, A: sp.spmatrix) -> NDArray[np.float64]:
        """Upper band of the symmetric ``A`` (size x size) in ``scipy.linalg.solveh_banded`` layout.
        Epochs are ordered state-major and couple only their neighbours: bandwidth 2n - 1."""
        u = 2 * self.n - 1
        A = sp.coo_matrix(A)
        A.sum_duplicates()
        up = A.row <= A.col
        ab = np.zeros((u + 1, self.size))
        ab[u + A.row[up] - A.col[up], A.col[up]] = A.data[up]
        return ab

    def rows_touching_first_epoch(self) -> NDArray[np.int64]:
        """Rows whose Jacobian has an entry in epoch 0's columns: its prior, its readings and the
        process step to epoch 1 (they touch epochs 0 and 1 only): what marginalising it removes."""
        r, c = self._pattern
        return np.unique(r[c < self.n])

    def information(self, X: NDArray) -> sp.csr_matrix:
        """Gauss-Newton information ``J^T W J`` at ``X`` (IRLS weights when robust)."""
        J = sp.diags(self.weights(self.residual(X))) @ self.jacobian(X)
        return (J.T @ J).tocsr()

    def marginal(self, X: NDArray, k: int) -> NDArray[np.float64]:
        """(n, n) marginal covariance of epoch ``k`` at ``X``: one block column of the inverse
        information by a banded Cholesky solve (cheaper than ``marginals`` for one epoch)."""
        n = self.n
        E = np.zeros((self.size, n))
        E[k * n : (k + 1) * n] = np.eye(n)
        band, _ = self.normal_equations(X, self.residual(X))
        try:
            S = sla.solveh_banded(band, E, check_finite=False)[k * n : (k + 1) * n]
        except np.linalg.LinAlgError:
            raise EstimationError("map smoothing: the information matrix is singular (unobservable state)") from None
        return 0.5 * (S + S.T)

    def marginals(self, X: NDArray) -> NDArray[np.float64]:
        """(N, n, n) marginal covariances at ``X``: diagonal blocks of (J^T W J)^-1, by the block-
        tridiagonal recursion (the information matrix couples consecutive epochs only)."""
        n, N = self.n, self.N
        A = self.information(X).tocoo()
        bi, bj = A.row // n, A.col // n
        D, B = np.zeros((N, n, n)), np.zeros((max(N - 1, 0), n, n))
        on = bi == bj
        np.add.at(D, (bi[on], A.row[on] % n, A.col[on] % n), A.data[on])
        low = bi == bj + 1  # A[k+1, k]
        np.add.at(B, (bj[low], A.row[low] % n, A.col[low] % n), A.data[low])
        Sinv = np.empty((N, n, n))
        S = D[0]
        for k in range(N):
            if k:
                S = D[k] - B[k - 1] @ Sinv[k - 1] @ B[k - 1].T
            Sinv[k] = _spd_inverse(S)
        Sig = np.empty((N, n, n))
        Sig[-1] = Sinv[-1]
        for k in range(N - 2, -1, -1):
            G = Sinv[k] @ B[k].T
            Sig[k] = Sinv[k] + G @ Sig[k + 1] @ G.T
        return 0.5 * (Sig + np.transpose(Sig, (0, 2, 1)))


def _spd_inverse(S: NDArray) -> NDArray[np.float64]:
    try:
        c = sla.cho_factor(S)
    except np.linalg.LinAlgError:
        raise EstimationError("map smoothing: the information matrix is singular (unobservable state)") from None
    return sla.cho_solve(c, np.eye(len(S)))


def levenberg_marquardt(
    problem: MapProblem, X0: NDArray, max_iter: int, *, rel_tol: float = 1e-8
) -> tuple[NDArray, float, int]:
    """Damped Gauss-Newton (IRLS weights when robust); a step is kept only if the cost falls.
    Stops when a step lowers the cost by less than ``rel_tol`` of it."""
    x = np.asarray(X0, float).ravel().copy()
    if x.shape != (problem.size,) or not np.isfinite(x).all():
        raise EstimationError(f"map smoothing: start of {x.size} values for {problem.N} x {problem.n} states, or non-finite")
    r = problem.residual(x)
    cost, lam, it = problem.cost(r), 1e-3, 0
    for it in range(1, max_iter + 1):
        band, g = problem.normal_equations(x, r)
        diag = band[-1].copy()
        while True:
            band[-1] = diag * (1.0 + lam)
            try:
                dx = sla.solveh_banded(band, -g, check_finite=False)
            except np.linalg.LinAlgError:  # not positive definite at this damping
                dx = None
            r_new = problem.residual(x + dx) if dx is not None else None
            c_new = problem.cost(r_new) if r_new is not None and np.isfinite(r_new).all() else np.inf
            if c_new < cost:
                break
            lam *= 10.0
            if lam > 1e10:
                return x.reshape(problem.N, problem.n), cost, it
        x, r, drop = x + dx, r_new, cost - c_new
        cost, lam = c_new, max(lam / 10.0, 1e-12)
        if drop <= rel_tol * cost or np.abs(dx).max() < 1e-10:
            break
    return x.reshape(problem.N, problem.n), cost, it


def rts_smooth(model: FusionModel, filtered: FilterRun, epochs: Epochs) -> SmoothedRun:
    """Rauch-Tung-Striebel backward pass over ``filtered`` (one state per epoch of ``epochs``)."""
    N = len(epochs)
    if filtered.x.shape[0] != N:
        raise EstimationError(f"rts: {filtered.x.shape[0]} filtered states for {N} epochs")
    xs, Ps = filtered.x.copy(), filtered.P.copy()
    for k in range(N - 2, -1, -1):
        dt, dist = float(epochs.t_s[k + 1] - epochs.t_s[k]), epochs.interval_travel(k)
        F = model.transition(dt, dist)
        Pp = F @ filtered.P[k] @ F.T + model.process_noise(dt, dist)
        G = np.linalg.solve(Pp, F @ filtered.P[k]).T  # P_k F^T Pp^-1 (Pp symmetric)
        xs[k] = filtered.x[k] + G @ (xs[k + 1] - F @ filtered.x[k])
        Ps[k] = filtered.P[k] + G @ (Ps[k + 1] - Pp) @ G.T
    Ps = 0.5 * (Ps + np.transpose(Ps, (0, 2, 1)))
    return SmoothedRun("rts", xs, Ps, float("nan"), 1)


def dead_reckoning_starts(
    problem: MapProblem, *, grid: int = 9, span_sigma: float = 2.0, keep: int = 4
) -> list[NDArray[np.float64]]:
    """Start trajectories that do not inherit a filter's early mistakes: from the prior mean,
    integrate the velocity readings (eq. 4 inverted, last reading held between readings) with a
    constant bias on a ``grid`` x ``grid`` lattice over the prior's +- ``span_sigma`` std, and
    keep the ``keep`` paths of lowest cost. Uses only the model, the prior and the readings."""
    m, e, x0 = problem.model, problem.epochs, problem.x0
    if not len(e.vel_k) or keep < 1:
        return []
    order = np.argsort(e.vel_k, kind="stable")
    held = np.searchsorted(e.vel_k[order], np.arange(len(e)), side="right") - 1  # last reading at or before k
    y = np.where((held >= 0)[:, None], e.vel_y[order][np.maximum(held, 0)], 0.0)  # (N, 2); none yet: still
    theta = x0[6] if m.theta_rad is None else m.theta_rad
    Minv = np.linalg.inv(velocity_matrix(theta))
    sb = span_sigma * np.sqrt(np.diag(problem.P0)[4:6])
    out = []
    for bx in x0[4] + np.linspace(-sb[0], sb[0], grid):
        for by in x0[5] + np.linspace(-sb[1], sb[1], grid):
            b = np.array([bx, by])
            v = np.where((held >= 0)[:, None], (y - b) @ Minv.T, x0[2:4])
            p = x0[0:2] + np.vstack([np.zeros(2), np.cumsum(v[:-1] * e.dt[:, None], axis=0)])
            X = np.column_stack([p, v, np.tile(b, (len(p), 1))] + ([np.full(len(p), theta)] if m.theta_rad is None else [])
                                + [np.tile(x0[m.n_base:], (len(p), 1))])  # shadowing offsets (if any) held at the prior's
            out.append((problem.cost(problem.residual(X)), X))
    out.sort(key=lambda t: t[0])
    return [X for _, X in out[:keep]]


def map_smooth(problem: MapProblem, starts: Sequence[NDArray], *, max_iter: int = 100) -> SmoothedRun:
    """The whole run's MAP trajectory from each start (N, n); the lowest-cost result is kept."""
    if not starts:
        raise EstimationError("map smoothing: no start trajectory")
    results = [levenberg_marquardt(problem, s, max_iter) for s in starts]
    best = int(np.argmin([c for _, c, _ in results]))
    X, cost, it = results[best]
    log.debug("map smoothing: costs %s from %d starts, kept %d", [round(c, 1) for _, c, _ in results], len(starts), best)
    return SmoothedRun("map", X, problem.marginals(X), cost, it, best)


def smooth(
    model: FusionModel,
    x0: NDArray,
    P0: NDArray,
    epochs: Epochs,
    filtered: FilterRun,
    method: str = "map",
    *,
    huber_k: float | None = None,
    axes: WalkAxes | None = None,
    area: WalkableArea | None = None,
) -> SmoothedRun:
    """``"rts"``: RTS over ``filtered``; ``"map"``: whole-run MAP started from the filter's and the
    RTS trajectories and from ``dead_reckoning_starts`` (nothing else), lowest cost kept; ``axes``
    and ``area`` (MAP only): the walk-axes prior on the velocity, the walkable-area prior on the position."""
    if method not in SMOOTH_METHODS:
        raise EstimationError(f"unknown smoother {method!r}; use {' or '.join(SMOOTH_METHODS)}")
    rts = rts_smooth(model, filtered, epochs)
    if method == "rts":
        return rts
    problem = MapProblem(model, x0, P0, epochs, huber_k=huber_k, axes=axes, area=area)
    return map_smooth(problem, [filtered.x, rts.x, *dead_reckoning_starts(problem)])
