"""The fixed-lag smoother's window for the whole heading bank at once.

Every hypothesis of the bank (``graphslam.core.tracking.fixed_lag``) holds the same epochs and
readings in its window; only its states, its prior and its RSSI std scales differ. So the window's
residuals, Gauss-Newton normal equations and Levenberg-Marquardt steps are computed for all of them
together: arrays with a leading hypothesis axis, no Python loop per reading, epoch or hypothesis,
and one banded Cholesky (LAPACK ``dpbtrf``) of the block-diagonal system of all hypotheses.

The cost is ``MapProblem``'s (``graphslam.core.tracking.smoother``) on the same window, row for row
in the same order (the tests compare the two). The normal equations are assembled per epoch rather
than from a sparse Jacobian: every reading touches the state of one epoch only, and the process rows
(the only ones linking two epochs) do not depend on the states, so ``J^T W J`` is a band that is
constant per window plus one small block per reading on the diagonal. What does not depend on the
states (the process band, the readings' Jacobian constants and band positions, their APs' law and
field) is computed once per run (``RunReadings``) and sliced per window.

Frames and units as the filters (m, m/s, rad, dBm, s).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import scipy.linalg.lapack as lapack
from numpy.typing import NDArray

from graphslam.core.tracking.axes import WalkAxes
from graphslam.core.tracking.filters import Epochs, FusionModel
from graphslam.core.tracking.walkable import WalkableArea
from graphslam.errors import EstimationError


class RunReadings:
    """A run's readings, each kind sorted by epoch, with what about them does not depend on the
    states; ``window`` cuts the problem of one window out of them. Velocity readings are available
    from ``vel_available_s`` (one per reading; default: their epoch's time)."""

    def __init__(
        self, model: FusionModel, epochs: Epochs, vel_available_s: NDArray | None = None, *,
        huber_k: float | None = None, axes: WalkAxes | None = None, area: WalkableArea | None = None,
    ) -> None:
        e = epochs
        e.check_model(model)
        n, N = model.n, len(e)
        self.model, self.n, self.kd, self.huber_k, self.axes, self.area = model, n, n, huber_k, axes, area
        kd1 = n + 1
        va = e.t_s[e.vel_k] if vel_available_s is None else np.asarray(vel_available_s, float).ravel()
        ov, orr, of = (np.argsort(k, kind="stable") for k in (e.vel_k, e.rss_k, e.fix_k))
        self.t_s = e.t_s
        self.vel_k, self.vel_y, self.vel_avail = e.vel_k[ov], e.vel_y[ov], va[ov]
        self.rss_k, self.rss_ap, self.rss_y, self.rss_scale = e.rss_k[orr], e.rss_ap[orr], e.rss_y[orr], e.rss_scale[orr]
        self.fix_k, self.fix_xy, self.fix_sigma = e.fix_k[of], e.fix_xy[of], e.fix_sigma[of]
        self.travel_m = e.travel_m
        every = np.arange(N + 1)
        self.vel_at, self.rss_at, self.fix_at = (np.searchsorted(k, every) for k in (self.vel_k, self.rss_k, self.fix_k))
        self.shadow = model.shadowing is not None
        self.theta = model.theta_rad is None
        # the process: whitened rows p_k = (x_k+1 - rho x_k - dt (v_k, 0)) / sq per interval
        self.dt = np.diff(e.t_s)
        sq = np.sqrt(np.outer(self.dt / model.period_s, np.asarray(model.q_diag, float)))  # (N-1, n_base)
        self.rho = np.ones((N - 1, n))
        if model.shadowing is not None:
            if e.travel_m is None:
                raise EstimationError("fixed-lag: a model with shadowing states needs the distance moved (Epochs.travel_m)")
            rho = model.shadowing.decay(e.travel_m)
            self.rho[:, model.n_base:] = rho[:, None]
            sq = np.hstack([sq, np.repeat(np.sqrt(model.shadowing.noise_var(rho))[:, None], n - model.n_base, axis=1)])
        self.inv_sq = 1.0 / sq
        Bk = np.zeros((N - 1, n, n))  # d p_k / d x_k; d p_k / d x_k+1 = diag(inv_sq)
        Bk[:, np.arange(n), np.arange(n)] = -self.rho * self.inv_sq
        Bk[:, 0, 2] = -self.dt * self.inv_sq[:, 0]
        Bk[:, 1, 3] = -self.dt * self.inv_sq[:, 1]
        self.Bk = Bk
        # their J^T J by band column: interval k's own block (B^T B) and the block below it
        # (A^T B) in block k's columns, its diag(inv_sq^2) in block k + 1's
        posD, selD, posO, selO = _band_maps(N, n)
        m = N * n * (n + 1) // 2 - n * (n + 1) // 2  # the first N - 1 blocks' lower triangles
        self._next, self._prev = np.zeros((N * n, kd1)), np.zeros((N * n, kd1))
        if N > 1:
            self._next.reshape(-1)[posD[:m]] = np.einsum("kij,kil->kjl", Bk, Bk).reshape(-1)[selD[:m]]
            self._next.reshape(-1)[posO] = (self.inv_sq[:, :, None] * Bk).reshape(-1)[selO]
            self._prev[n:, 0] = (self.inv_sq * self.inv_sq).ravel()
        # reading rows: Jacobian constants, columns, band and gradient positions (epochs of the run)
        c = 5 if self.theta else 4
        self.c = c
        sv = np.sqrt(model.r_velocity)
        self.inv_sv = 1.0 / sv
        vc = np.arange(2, 2 + c)  # vx vy bx by (theta)
        self._J0v = np.zeros((2, c))
        self._J0v[0, 2], self._J0v[1, 3] = -self.inv_sv[0], -self.inv_sv[1]  # bias entries are constant
        self._pos_v, gv = _positions(self.vel_k, np.broadcast_to(vc, (len(self.vel_k), c)), n)
        self._gpos_v = np.repeat(gv[:, None, :], 2, axis=1)  # both rows of a reading
        rc = np.broadcast_to(np.arange(2), (len(self.rss_k), 2))
        if self.shadow:
            rc = np.column_stack([rc, model.shadow_state(self.rss_ap)])
        self._pos_r, self._gpos_r = _positions(self.rss_k, rc, n)
        self._pos_f, self._gpos_f = _positions(np.repeat(self.fix_k, 2), np.tile([[0], [1]], (len(self.fix_k), 1)), n)
        self.inv_fs = 1.0 / self.fix_sigma
        self._pos_a, self._gpos_a = _positions(self.vel_k, np.broadcast_to([2, 3], (len(self.vel_k), 2)), n)
        self._pos_w, self._gpos_w = _positions(self.vel_k, np.broadcast_to([0, 1], (len(self.vel_k), 2)), n)
        self.law = model.path_loss.rows(self.rss_ap)
        self.sr0 = np.sqrt(model.r_rssi[self.rss_ap])
        self._rss_col = model.shadow_state(self.rss_ap) if self.shadow else None

    def __len__(self) -> int:
        return len(self.t_s)

    def window(
        self, lo: int, hi: int, now: float, x0: NDArray, info: NDArray, rss_scale: NDArray, upto: int | None = None
    ) -> "WindowProblem":
        """The window of epochs ``lo`` .. ``hi`` at time ``now`` (velocity readings available by then),
        for hypotheses with prior means ``x0`` (B, n), prior informations (inverse covariances) ``info``
        (B, n, n) and RSSI std scales ``rss_scale`` (B, the run's readings); with ``upto``, only the
        readings of epochs up to it (the rows a marginalisation of epoch ``lo`` removes)."""
        return WindowProblem(self, lo, hi, now, x0, info, rss_scale, upto)


class WindowProblem:
    """The whitened residuals of one window for ``B`` hypotheses: prior ``N(x0[b], info[b]^-1)`` on the
    first epoch and RSSI std ``sqrt(r_rssi) * rss_scale[b]`` per reading; rows as ``MapProblem``'s
    (prior, process, velocity, then the Huber-weighted map rows: RSSI, fixes, axes, area), the prior
    rows whitened by the Cholesky factor of ``info`` (the same cost as ``MapProblem``'s).

    States ``X`` are (B', N, n) or (B', N n) for the hypotheses ``hs`` (indices into the B; all by
    default); residuals (B', rows); costs (B',). Bands are (B', N n, kd + 1) with ``band[b, j, d] =
    A_b[j + d, j]``: each hypothesis's rows are LAPACK's lower band layout, column-major."""

    def __init__(
        self, run: RunReadings, lo: int, hi: int, now: float, x0: NDArray, info: NDArray, rss_scale: NDArray,
        upto: int | None = None,
    ) -> None:
        n, N = run.n, hi - lo + 1
        self.run, self.model, self.n, self.N, self.size = run, run.model, n, N, N * n
        self.huber_k, self.axes, self.area, self.theta, self.kd = run.huber_k, run.axes, run.area, run.theta, run.kd
        kd1, last = self.kd + 1, hi if upto is None else upto
        v = np.arange(run.vel_at[lo], run.vel_at[last + 1])
        v = v[run.vel_avail[v] <= now]
        r = slice(run.rss_at[lo], run.rss_at[last + 1])
        f = slice(run.fix_at[lo], run.fix_at[last + 1])
        self.vel_k, self.vel_y = run.vel_k[v] - lo, run.vel_y[v]
        self.rss_k, self.rss_y, self.law = run.rss_k[r] - lo, run.rss_y[r], run.law.take(r)
        self.fix_k, self.fix_xy, self.inv_fs = run.fix_k[f] - lo, run.fix_xy[f], run.inv_fs[f]
        self.x0 = np.asarray(x0, float).reshape(-1, n)
        B = len(self.x0)
        self.sr = run.sr0[r] * np.asarray(rss_scale, float).reshape(B, -1)[:, r]
        self._rss_col = None if run._rss_col is None else run._rss_col[r]
        try:
            L = np.linalg.cholesky(np.asarray(info, float).reshape(B, n, n))
        except np.linalg.LinAlgError:
            raise EstimationError("fixed-lag: a window's prior information is not positive definite") from None
        self.W0 = np.swapaxes(L, 1, 2)  # W0^T W0 = info
        self.dt, self.rho, self.inv_sq, self._Bk = run.dt[lo:hi], run.rho[lo:hi], run.inv_sq[lo:hi], run.Bk[lo:hi]
        self._band_const = np.zeros((self.size, kd1))
        if N > 1:
            self._band_const[: (N - 1) * n] += run._next[lo * n : hi * n]
            self._band_const[n:] += run._prev[(lo + 1) * n : (hi + 1) * n]
        Mv, Mr, Mf = len(v), r.stop - r.start, f.stop - f.start
        self.meas = n + (N - 1) * n  # first reading row
        self.head = self.meas + 2 * Mv  # rows before the (robust) map rows
        self.rows = self.head + Mr + 2 * Mf + (Mv if run.axes is not None else 0) + (Mv if run.area is not None else 0)
        # the reading rows' Jacobian as (rows, c) entries in their epoch's columns (``jacobian_rows``),
        # the band positions of the products each reading adds (lower triangle of its entries) and
        # the gradient positions of its entries, the prior's first
        c, ii, jj = run.c, *_tril(n)
        ps, gs = [jj * kd1 + ii - jj], [np.arange(n)]
        shift, gshift = lo * n * kd1, lo * n
        f2 = slice(2 * f.start, 2 * f.stop)
        parts = [(Mv, run._pos_v[v], run._gpos_v[v]), (Mr, run._pos_r[r], run._gpos_r[r]), (Mf, run._pos_f[f2], run._gpos_f[f2])]
        if run.axes is not None:
            parts.append((Mv, run._pos_a[v], run._gpos_a[v]))
        if run.area is not None:
            parts.append((Mv, run._pos_w[v], run._gpos_w[v]))
        for m, pp, gp in parts:
            if m:
                ps.append(pp.ravel() - shift)
                gs.append(gp.ravel() - gshift)
        self._pos, self._gpos = np.concatenate(ps), np.concatenate(gs)
        self._prior_vals = np.asarray(info, float).reshape(B, n, n)[:, ii, jj]
        J0 = np.zeros((self.rows - self.meas, c))
        J0[: 2 * Mv] = np.tile(run._J0v, (Mv, 1))
        J0[2 * Mv + Mr : 2 * Mv + Mr + 2 * Mf, 0] = -np.repeat(self.inv_fs, 2)
        self._J0 = J0
        # reading kinds as (first row, rows, entries, rows per reading) of the reading rows
        seg = [(0, 2 * Mv, c, 2), (2 * Mv, Mr, 3 if run.shadow else 2, 1), (2 * Mv + Mr, 2 * Mf, 1, 1),
               (2 * Mv + Mr + 2 * Mf, self.rows - self.head - Mr - 2 * Mf, 2, 1)]
        self._segments = [(a, a + m, e, per, _tril(e)) for a, m, e, per in seg if m]
        self._gsegments = [(a, a + m, e) for a, m, e, _ in seg if m]
        self._cache: dict = {}

    # --- residuals and costs -------------------------------------------------------------------
    def residual(self, X: NDArray, hs: NDArray | None = None) -> NDArray[np.float64]:
        X = np.asarray(X, float).reshape(-1, self.N, self.n)
        h = slice(None) if hs is None else hs
        n, B, run = self.n, len(X), self.run
        out = np.empty((B, self.rows))
        out[:, :n] = np.matmul(self.W0[h], (X[:, 0] - self.x0[h])[..., None])[..., 0]
        if self.N > 1:
            proc = X[:, 1:] - self.rho * X[:, :-1] if run.shadow else X[:, 1:] - X[:, :-1]
            proc[..., 0:2] -= self.dt[:, None] * X[:, :-1, 2:4]
            out[:, n : self.meas] = (proc * self.inv_sq).reshape(B, -1)
        xv = X[:, self.vel_k]
        if len(self.vel_k):
            s, c = self._sincos(xv)
            vx, vy = xv[..., 2], xv[..., 3]
            out[:, self.meas : self.head : 2] = (self.vel_y[:, 0] - (c * vy - s * vx) - xv[..., 4]) * run.inv_sv[0]
            out[:, self.meas + 1 : self.head : 2] = (self.vel_y[:, 1] - (c * vx + s * vy) - xv[..., 5]) * run.inv_sv[1]
        at = self.head
        if len(self.rss_k):
            xr = X[:, self.rss_k]
            hr = self.law.mean(xr[..., 0], xr[..., 1])
            if run.shadow:
                hr = hr + xr[:, np.arange(len(self.rss_k)), self._rss_col]
            out[:, at : at + len(self.rss_k)] = (self.rss_y - hr) / self.sr[h]
            at += len(self.rss_k)
        if len(self.fix_k):
            out[:, at : at + 2 * len(self.fix_k)] = ((self.fix_xy - X[:, self.fix_k, 0:2]) * self.inv_fs[:, None]).reshape(B, -1)
            at += 2 * len(self.fix_k)
        if self.axes is not None:
            out[:, at : at + len(self.vel_k)] = self.axes.residual_xy(xv[..., 2], xv[..., 3])
            at += len(self.vel_k)
        if self.area is not None:
            out[:, at:] = self.area.residual(xv[..., 0:2].reshape(-1, 2)).reshape(B, -1)
        return out

    def _sincos(self, xv: NDArray) -> tuple[NDArray, NDArray]:
        th = xv[..., 6] if self.theta else np.full(xv.shape[:-1], self.model.theta_rad)
        return np.sin(th), np.cos(th)

    def cost(self, r: NDArray) -> NDArray[np.float64]:
        """Per hypothesis: sum of squares, Huber's 2 k |r| - k^2 beyond k on the map rows."""
        if self.huber_k is None:
            return np.einsum("br,br->b", r, r)
        hd, a = r[:, : self.head], np.abs(r[:, self.head:])
        m = np.minimum(a, self.huber_k)
        return np.einsum("br,br->b", hd, hd) + np.einsum("br,br->b", m, a + a - m)  # a^2 up to k, 2 k a - k^2 beyond

    def first_epoch_cost(self, r: NDArray) -> NDArray[np.float64]:
        """Per hypothesis: the cost of the rows that touch the first epoch (its prior, the process
        step to the second, its readings): what marginalising it takes out of the window."""
        n, m = self.n, [np.searchsorted(k, 1) for k in (self.vel_k, self.rss_k, self.fix_k)]
        Mv, Mr, Mf = len(self.vel_k), len(self.rss_k), len(self.fix_k)
        head = np.r_[0 : n * min(2, self.N), self.meas : self.meas + 2 * m[0]]
        at = self.head + np.r_[0 : m[1], Mr : Mr + 2 * m[2]]
        extra = Mr + 2 * Mf
        for prior in (self.axes, self.area):
            if prior is not None:
                at = np.r_[at, self.head + extra + np.arange(m[0])]
                extra += Mv
        rh, a = r[:, head], np.abs(r[:, at])
        if self.huber_k is None:
            return np.einsum("br,br->b", rh, rh) + np.einsum("br,br->b", a, a)
        k = self.huber_k
        return np.einsum("br,br->b", rh, rh) + np.where(a <= k, a * a, 2.0 * k * a - k * k).sum(axis=1)

    def weights(self, r: NDArray) -> NDArray[np.float64]:
        """IRLS weights (squared) of the reading rows (``r``'s from the first velocity row on): 1,
        Huber's k / |r| on map rows beyond k."""
        w = np.ones((len(r), self.rows - self.meas))
        if self.huber_k is not None:
            w[:, self.head - self.meas:] = np.minimum(1.0, self.huber_k / np.maximum(np.abs(r[:, self.head:]), 1e-300))
        return w

    # --- normal equations -----------------------------------------------------------------------
    def jacobian_rows(self, X: NDArray, hs: NDArray | None = None) -> NDArray[np.float64]:
        """(B', reading rows, c): the reading rows' Jacobian entries, in their epoch's columns vx vy bx
        by (theta) for a velocity row, x y (shadowing offset) for RSSI, x or y for a fix, vx vy for
        the axes, x y for the area."""
        X = np.asarray(X, float).reshape(-1, self.N, self.n)
        h = slice(None) if hs is None else hs
        B, run = len(X), self.run
        J = np.repeat(self._J0[None], B, axis=0)
        xv = X[:, self.vel_k]
        Mv = len(self.vel_k)
        if Mv:
            s, c = self._sincos(xv)
            a, b = run.inv_sv
            J[:, 0 : 2 * Mv : 2, 0], J[:, 0 : 2 * Mv : 2, 1] = s * a, -c * a
            J[:, 1 : 2 * Mv : 2, 0], J[:, 1 : 2 * Mv : 2, 1] = -c * b, -s * b
            if self.theta:
                vx, vy = xv[..., 2], xv[..., 3]
                J[:, 0 : 2 * Mv : 2, 4] = (c * vx + s * vy) * a
                J[:, 1 : 2 * Mv : 2, 4] = (s * vx - c * vy) * b
        at, Mr = 2 * Mv, len(self.rss_k)
        if Mr:
            xr = X[:, self.rss_k]
            gx, gy = self.law.gradient(xr[..., 0], xr[..., 1])
            inv = -1.0 / self.sr[h]
            J[:, at : at + Mr, 0], J[:, at : at + Mr, 1] = gx * inv, gy * inv
            if run.shadow:
                J[:, at : at + Mr, 2] = inv
        at += Mr + 2 * len(self.fix_k)
        if self.axes is not None:
            J[:, at : at + Mv, 0], J[:, at : at + Mv, 1] = self.axes.jacobian_xy(xv[..., 2], xv[..., 3])
            at += Mv
        if self.area is not None:
            J[:, at:, 0:2] = self.area.jacobian(xv[..., 0:2].reshape(-1, 2)).reshape(B, Mv, 2)
        return J

    def normal_equations(
        self, X: NDArray, r: NDArray, hs: NDArray | None = None
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Gauss-Newton system at ``X`` with residuals ``r`` for the hypotheses ``hs``: the band of
        J^T W J (B', size, kd + 1; see the class) and J^T W r (B', size), W the IRLS weights."""
        h = slice(None) if hs is None else hs
        n, B, kd1 = self.n, len(r), self.kd + 1
        J = self.jacobian_rows(X, hs)
        WJ = J.copy()
        if self.huber_k is not None:
            WJ[:, self.head - self.meas :] *= self.weights(r)[:, self.head - self.meas :, None]
        vals = [self._prior_vals[h]]
        for a, b, e, per, (ii, jj) in self._segments:
            if per == 1:
                vals.append((WJ[:, a:b, ii] * J[:, a:b, jj]).reshape(B, -1))
            else:  # a velocity reading's two rows share their columns: their products summed
                Ws, Js = WJ[:, a:b, :e].reshape(B, -1, per, e), J[:, a:b, :e].reshape(B, -1, per, e)
                vals.append(np.einsum("bmrp,bmrp->bmp", Ws[..., ii], Js[..., jj]).reshape(B, -1))
        nb = self.size * kd1
        band = np.bincount(self._offsets(B, nb, self._pos), np.concatenate(vals, axis=1).ravel(), minlength=B * nb)
        band = band.reshape(B, self.size, kd1) + self._band_const
        gr = WJ * r[:, self.meas :, None]
        gv = [np.matmul(r[:, None, :n], self.W0[h])[:, 0]]  # W0^T r of the prior rows
        gv += [gr[:, a:b, :e].reshape(B, -1) for a, b, e in self._gsegments]
        g = np.bincount(self._offsets(B, self.size, self._gpos), np.concatenate(gv, axis=1).ravel(),
                        minlength=B * self.size).reshape(B, self.size)
        if self.N > 1:
            p = r[:, n : self.meas].reshape(B, self.N - 1, n)
            g[:, n:] += (p * self.inv_sq).reshape(B, -1)
            g[:, :-n] += np.einsum("kij,bki->bkj", self._Bk, p).reshape(B, -1)
        return band, g

    def _offsets(self, B: int, stride: int, pos: NDArray) -> NDArray[np.int64]:
        """``pos`` for each of B hypotheses, hypothesis b's shifted by b stride (flat)."""
        key = (B, stride, id(pos))
        out = self._cache.get(key)
        if out is None:
            out = self._cache[key] = (np.arange(B)[:, None] * stride + pos).ravel()
        return out

    def dense(self, band: NDArray) -> NDArray[np.float64]:
        """(B', size, size) symmetric matrices of bands (B', size, kd + 1)."""
        A = np.zeros((len(band), self.size, self.size))
        i = np.arange(self.size)
        for d in range(min(self.kd + 1, self.size)):
            A[:, i[d:], i[: self.size - d]] = band[:, : self.size - d, d]
            A[:, i[: self.size - d], i[d:]] = band[:, : self.size - d, d]
        return A


def _positions(k: NDArray, cols: NDArray, n: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """For rows at epochs ``k`` (m,) with Jacobian entries in columns ``cols`` (m, c) of their epoch
    (ascending): the band positions (m, c (c + 1) / 2; layout of ``WindowProblem``, kd = n) of the
    products of entries i >= j, and the gradient positions (m, c) of the entries."""
    ii, jj = _tril(cols.shape[1])
    ci, cj = cols[:, ii], cols[:, jj]
    return (k[:, None] * n + cj) * (n + 1) + ci - cj, k[:, None] * n + cols


@lru_cache(maxsize=16)
def _tril(c: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    return np.tril_indices(c)


def _band_maps(N: int, n: int) -> tuple[NDArray, NDArray, NDArray, NDArray]:
    """Flat band positions (layout of ``WindowProblem``, kd = n) of the lower triangles of N diagonal
    blocks (and their flat indices in a (N, n, n) array), and of the nonzero entries of the N - 1
    process blocks below them: the diagonal and (x, vx), (y, vy) (and their flat indices)."""
    kd1 = n + 1
    ii, jj = _tril(n)
    k = np.arange(N)[:, None]
    posD = ((k * n + jj) * kd1 + ii - jj).ravel()
    selD = (k * n * n + ii * n + jj).ravel()
    a = np.r_[np.arange(n), 0, 1]  # row, column inside a block
    b = np.r_[np.arange(n), 2, 3]
    kk = np.arange(N - 1)[:, None]
    posO = ((kk * n + b) * kd1 + n + a - b).ravel()
    selO = (kk * n * n + a * n + b).ravel()
    return posD, selD, posO, selO


def banded_cholesky(band: NDArray, *, overwrite: bool = False) -> NDArray[np.float64] | None:
    """LAPACK's factor of the block-diagonal system of the bands (B, size, kd + 1) at once (None
    unless every block is positive definite). ``overwrite``: ``band`` may become the factor."""
    B, size, kd1 = band.shape
    c, info = lapack.dpbtrf(band.reshape(B * size, kd1).T, lower=1, overwrite_ab=int(overwrite))
    return c if info == 0 else None


def banded_solve(band: NDArray, rhs: NDArray, damping: NDArray) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Solve each block's damped system ``(A_b + damping_b diag(A_b)) x_b = rhs_b`` (rhs (B, size));
    blocks that are not positive definite come back as NaN, flagged False."""
    B, size, kd1 = band.shape
    A = band.copy()
    A[..., 0] *= 1.0 + damping[:, None]
    c = banded_cholesky(A, overwrite=True)
    if c is not None:
        return lapack.dpbtrs(c, rhs.reshape(B * size, 1), lower=1, overwrite_b=1)[0].reshape(rhs.shape), np.ones(B, bool)
    x, ok = np.full(rhs.shape, np.nan), np.zeros(B, bool)
    for b in range(B):  # rare: a damped step tried on an indefinite system; the others one by one
        A = band[b : b + 1].copy()
        A[..., 0] *= 1.0 + damping[b]
        c = banded_cholesky(A, overwrite=True)
        if c is not None:
            x[b], ok[b] = lapack.dpbtrs(c, rhs[b].reshape(size, 1), lower=1)[0][:, 0], True
    return x, ok


def marginal_covariances(c: NDArray, B: int, size: int, n: int, i: int) -> NDArray[np.float64]:
    """(B, n, n) marginal covariances of block ``i`` (rows i n .. i n + n) of the inverses of B systems of
    ``size`` whose stacked factor is ``c`` (``banded_cholesky``). With A = L L^T the block is
    Y^T Y for Y = L^-1 E_i, and Y is zero above block i: only the factor's trailing part below
    block i enters (a forward solve of a few blocks for the recent epochs)."""
    t = size - i * n
    cols = (np.arange(B)[:, None] * size + i * n + np.arange(t)).ravel()
    E = np.zeros((B, t, n))
    E[:, np.arange(n), np.arange(n)] = 1.0
    Y = lapack.dtbtrs(np.asfortranarray(c[:, cols]), E.reshape(B * t, n), uplo="L", overwrite_b=1)[0].reshape(B, t, n)
    S = np.einsum("bti,btj->bij", Y, Y)
    return 0.5 * (S + np.swapaxes(S, 1, 2))


def levenberg_marquardt_bank(
    p: WindowProblem, X0: NDArray, max_iter: int, *, rel_tol: float = 1e-8, max_damping: float = 1e10,
    stall_tol: float | None = None,
) -> tuple[NDArray, NDArray, NDArray, NDArray, NDArray, NDArray[np.bool_]]:
    """``smoother.levenberg_marquardt`` for every hypothesis of ``p`` at once, each with its own damping
    and stop; two more stops, both where the quadratic model has nothing left to give. A step that
    promises less than ``rel_tol`` of the cost (undamped, at most ``(1 + lambda)^2`` times the damped
    step's promise) is not taken: at the optimum it often fails to lower the cost by rounding, and
    the damping would retry it ten times over; stopping at the linearisation point also leaves the
    normal equations at the final states (the marginals need no further linearisation). With
    ``stall_tol``: a step promising less than ``stall_tol`` of the cost that raises it ends the
    iterations too. The RSSI rows' Jacobian leaves out the residual field's gradient (noise at the
    cell scale), so near the optimum the model and the cost part at that level and damped retries
    gain nothing. Returns the states (B, N, n), costs (B,), the final residuals, the last normal
    equations (bands and gradients) and which of them are at the final states."""
    B = len(p.x0)
    x = np.asarray(X0, float).reshape(B, p.size).copy()
    if not np.isfinite(x).all():
        raise EstimationError("fixed-lag: a window's start is not finite")
    r = p.residual(x)
    cost = p.cost(r)
    lam = np.full(B, 1e-3)
    it = np.zeros(B, np.int64)
    done = np.zeros(B, bool)
    fresh = np.zeros(B, bool)  # the band and gradient are at the current x
    band = np.zeros((B, p.size, p.kd + 1))
    g = np.zeros((B, p.size))
    while True:
        a = np.flatnonzero(~done)
        if not len(a):
            break
        lin = a[~fresh[a]]
        if len(lin):
            it[lin] += 1
            band[lin], g[lin] = p.normal_equations(x[lin], r[lin], None if len(lin) == B else lin)
            fresh[lin] = True
        every = len(a) == B
        hs = None if every else a
        ba, ga, la = (band, g, lam) if every else (band[a], g[a], lam[a])
        dx, ok = banded_solve(ba, -ga, la)
        # predicted decrease of the quadratic model: -2 g.dx - dx.H dx with (H + lam D) dx = -g
        pred = la * np.einsum("bi,bi->b", ba[..., 0], dx * dx) - np.einsum("bi,bi->b", ga, dx)
        ca = cost[a]
        # the undamped step's decrease is at most pred (1 + lam)^2 (exact for a diagonal H)
        last = ok & (pred * (1.0 + la) ** 2 <= rel_tol * ca)
        if last.any():
            done[a[last]] = True
            keep = ~last
            a, dx, ok, pred, ca = a[keep], dx[keep], ok[keep], pred[keep], ca[keep]
            if not len(a):
                continue
            every, hs = False, a
        xa = (x if every else x[a]) + dx
        if ok.all():
            r_new = p.residual(xa, hs)
            c_new = p.cost(r_new)  # NaN (a non-finite residual) is never accepted
        else:  # not positive definite even when damped: a failed try
            r_new, c_new = np.zeros((len(a), p.rows)), np.full(len(a), np.inf)
            if ok.any():
                r_new[ok] = p.residual(xa[ok], a[ok])
                c_new[ok] = p.cost(r_new[ok])
        acc = c_new < ca
        rej = a[~acc]
        lam[rej] *= 10.0
        done[rej[lam[rej] > max_damping]] = True
        if stall_tol is not None:
            done[rej[pred[~acc] <= stall_tol * ca[~acc]]] = True
        if acc.any():
            ac = a[acc]
            drop = ca[acc] - c_new[acc]
            x[ac] = xa[acc]
            r[ac] = r_new[acc]
            cost[ac] = c_new[acc]
            lam[ac] = np.maximum(lam[ac] / 10.0, 1e-12)
            fresh[ac] = False
            stop = (drop <= rel_tol * cost[ac]) | (np.abs(dx[acc]).max(axis=1) < 1e-10) | (it[ac] >= max_iter)
            done[ac[stop]] = True
    return x.reshape(B, p.N, p.n), cost, r, band, g, fresh
