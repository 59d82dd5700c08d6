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
constant per window plus one small block per reading on the diagonal.

Frames and units as the filters (m, m/s, rad, dBm, s).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import scipy.linalg.lapack as lapack
from numpy.typing import NDArray

from graphslam.core.tracking.axes import WalkAxes
from graphslam.core.tracking.filters import FusionModel
from graphslam.core.tracking.walkable import WalkableArea
from graphslam.errors import EstimationError


@dataclass(frozen=True, eq=False)
class WindowReadings:
    """What a window holds, shared by every hypothesis: epoch times (N,) and the readings with
    their epoch as an index into the window (each kind sorted by epoch). ``travel_m`` (N - 1,):
    distances moved (models with shadowing states only)."""

    t_s: NDArray[np.float64]
    vel_k: NDArray[np.int64]
    vel_y: NDArray[np.float64]
    rss_k: NDArray[np.int64]
    rss_ap: NDArray[np.int64]
    rss_y: NDArray[np.float64]
    fix_k: NDArray[np.int64]
    fix_xy: NDArray[np.float64]
    fix_sigma: NDArray[np.float64]
    travel_m: NDArray[np.float64] | None = None


class WindowProblem:
    """The whitened residuals of one window for ``B`` hypotheses: prior ``N(x0[b], P0[b])`` on the
    first epoch and RSSI std ``sqrt(r_rssi) * rss_scale[b]`` per reading; rows as ``MapProblem``'s
    (prior, process, velocity, then the Huber-weighted map rows: RSSI, fixes, axes, area).

    States ``X`` are (B', N, n) or (B', N n) for the hypotheses ``hs`` (indices into the B; all by
    default); residuals (B', rows); costs (B',). Bands are (B', N n, kd + 1) with ``band[b, j, d] =
    A_b[j + d, j]``: each hypothesis's rows are LAPACK's lower band layout, column-major."""

    def __init__(
        self, model: FusionModel, w: WindowReadings, x0: NDArray, P0: NDArray, rss_scale: NDArray, *,
        huber_k: float | None = None, axes: WalkAxes | None = None, area: WalkableArea | None = None,
    ) -> None:
        n, N = model.n, len(w.t_s)
        self.model, self.w, self.n, self.N, self.size = model, w, n, N, N * n
        self.huber_k, self.axes, self.area = huber_k, axes, area
        # band: an epoch couples its neighbour only through the process, whose block (k + 1, k) is
        # diagonal but for (x, vx) and (y, vy) above it: bandwidth n, not 2n - 1
        self.kd = n if N > 1 else n - 1
        self.x0 = np.asarray(x0, float).reshape(-1, n)
        try:
            C = np.linalg.cholesky(np.asarray(P0, float).reshape(-1, n, n))
        except np.linalg.LinAlgError:
            raise EstimationError("fixed-lag: a window's prior covariance is not positive definite") from None
        self.W0 = np.linalg.inv(C)  # C^-1 whitens x - x0
        ii, jj = _tril(n)
        self._prior_vals = np.einsum("bki,bkj->bij", self.W0, self.W0)[:, ii, jj]  # P0^-1, lower triangle
        self._prior_pos = jj * (self.kd + 1) + ii - jj
        self._shadow = model.shadowing is not None
        self.dt = np.diff(w.t_s)
        self.sq = np.sqrt(np.outer(self.dt / model.period_s, np.asarray(model.q_diag, float)))  # (N-1, n) process std
        self.rho = np.ones((N - 1, n))
        if self._shadow:
            assert model.shadowing is not None and w.travel_m is not None
            rho = model.shadowing.decay(w.travel_m)
            self.rho[:, model.n_base:] = rho[:, None]
            sd = np.sqrt(model.shadowing.noise_var(rho))
            self.sq = np.hstack([self.sq, np.repeat(sd[:, None], n - model.n_base, axis=1)])
            self._rss_col = model.shadow_state(w.rss_ap)
        self.sv = np.sqrt(model.r_velocity)
        self.sr = np.sqrt(model.r_rssi[w.rss_ap]) * np.asarray(rss_scale, float).reshape(len(self.x0), -1)
        self._pl = model.path_loss.rows(w.rss_ap)
        self.theta = model.theta_rad is None
        Mv, Mr, Mf = len(w.vel_k), len(w.rss_k), len(w.fix_k)
        self.meas = n + (N - 1) * n  # first reading row
        self.head = self.meas + 2 * Mv  # rows before the (robust) map rows
        self.rows = self.head + Mr + 2 * Mf + (Mv if axes is not None else 0) + (Mv if area is not None else 0)
        self._band_const = self._process_band()
        self._reading_structure()

    # --- residuals and costs -------------------------------------------------------------------
    def residual(self, X: NDArray, hs: NDArray | None = None) -> NDArray[np.float64]:
        X = np.asarray(X, float).reshape(-1, self.N, self.n)
        h = slice(None) if hs is None else hs
        w, B = self.w, len(X)
        out = np.empty((B, self.rows))
        out[:, : self.n] = np.einsum("bij,bj->bi", self.W0[h], X[:, 0] - self.x0[h])
        if self.N > 1:
            proc = X[:, 1:] - self.rho * X[:, :-1]
            proc[..., 0:2] -= self.dt[:, None] * X[:, :-1, 2:4]
            out[:, self.n : self.meas] = (proc / self.sq).reshape(B, -1)
        xv = X[:, w.vel_k]
        if len(w.vel_k):
            s, c = self._sincos(xv)
            vx, vy = xv[..., 2], xv[..., 3]
            out[:, self.meas : self.head : 2] = (w.vel_y[:, 0] - (c * vy - s * vx) - xv[..., 4]) / self.sv[0]
            out[:, self.meas + 1 : self.head : 2] = (w.vel_y[:, 1] - (c * vx + s * vy) - xv[..., 5]) / self.sv[1]
        at = self.head
        if len(w.rss_k):
            xr = X[:, w.rss_k]
            hr = self._pl.mean(xr[..., 0], xr[..., 1])
            if self._shadow:
                hr = hr + xr[:, np.arange(len(w.rss_k)), self._rss_col]
            out[:, at : at + len(w.rss_k)] = (w.rss_y - hr) / self.sr[h]
            at += len(w.rss_k)
        if len(w.fix_k):
            out[:, at : at + 2 * len(w.fix_k)] = ((w.fix_xy - X[:, w.fix_k, 0:2]) / w.fix_sigma[:, None]).reshape(B, -1)
            at += 2 * len(w.fix_k)
        for prior, part in ((self.axes, 2), (self.area, 0)):
            if prior is not None:
                out[:, at : at + len(w.vel_k)] = prior.residual(xv[..., part : part + 2].reshape(-1, 2)).reshape(B, -1)
                at += len(w.vel_k)
        return out

    def _sincos(self, xv: NDArray) -> tuple[NDArray, NDArray]:
        th = xv[..., 6] if self.theta else np.full(xv.shape[:-1], self.model.theta_rad)
        return np.sin(th), np.cos(th)

    def cost(self, r: NDArray) -> NDArray[np.float64]:
        """Per hypothesis: sum of squares, Huber's 2 k |r| - k^2 beyond k on the map rows."""
        if self.huber_k is None:
            return np.einsum("br,br->b", r, r)
        k, hd, a = self.huber_k, r[:, : self.head], np.abs(r[:, self.head:])
        return np.einsum("br,br->b", hd, hd) + np.where(a <= k, a * a, 2.0 * k * a - k * k).sum(axis=1)

    def weights(self, r: NDArray) -> NDArray[np.float64]:
        """IRLS weights (squared) of the reading rows (``r``'s from the first velocity row on): 1,
        Huber's k / |r| on map rows beyond k."""
        w = np.ones((len(r), self.rows - self.meas))
        if self.huber_k is not None:
            w[:, self.head - self.meas:] = np.minimum(1.0, self.huber_k / np.maximum(np.abs(r[:, self.head:]), 1e-300))
        return w

    # --- normal equations -----------------------------------------------------------------------
    def _process_band(self) -> NDArray[np.float64]:
        """The process rows' J^T J (size, kd + 1) (constant: the process is linear)."""
        n, N = self.n, self.N
        band = np.zeros((self.size, self.kd + 1))
        if N == 1:
            return band
        inv = 1.0 / self.sq  # (N-1, n)
        Bk = np.zeros((N - 1, n, n))  # d p_k / d x_k (whitened)
        Bk[:, np.arange(n), np.arange(n)] = -self.rho * inv
        Bk[:, 0, 2] = -self.dt * inv[:, 0]
        Bk[:, 1, 3] = -self.dt * inv[:, 1]
        D = np.zeros((N, n, n))
        D[1:, np.arange(n), np.arange(n)] = inv * inv
        D[:-1] += np.einsum("kij,kil->kjl", Bk, Bk)
        O = inv[:, :, None] * Bk  # block (k + 1, k): A_k^T B_k, A_k = diag(inv)
        self._Bk = Bk
        posD, selD, posO, selO = _band_maps(N, n)
        band.reshape(-1)[posD] = D.reshape(-1)[selD]
        band.reshape(-1)[posO] = O.reshape(-1)[selO]
        return band

    def _reading_structure(self) -> None:
        """Every reading row as up to ``c`` Jacobian entries in its epoch's columns (unused ones in
        column 0 with value 0): their columns, the constant entries, and the band and gradient
        positions of their products, in the row order of ``residual``."""
        n, w, kd1 = self.n, self.w, self.kd + 1
        Mv, Mr, Mf = len(w.vel_k), len(w.rss_k), len(w.fix_k)
        c = 5 if self.theta else 4
        R = self.rows - self.meas
        cols, J0, k = np.zeros((R, c), np.int64), np.zeros((R, c)), np.zeros(R, np.int64)
        vc = np.arange(2, 2 + c)  # vx vy bx by (theta)
        cols[: 2 * Mv] = vc
        k[: 2 * Mv] = np.repeat(w.vel_k, 2)
        J0[0 : 2 * Mv : 2, 2] = -1.0 / self.sv[0]  # bias entries are constant
        J0[1 : 2 * Mv : 2, 3] = -1.0 / self.sv[1]
        at = 2 * Mv
        cols[at : at + Mr, 1] = 1
        if self._shadow:
            cols[at : at + Mr, 2] = self._rss_col
        k[at : at + Mr] = w.rss_k
        at += Mr
        cols[at : at + 2 * Mf : 2, 0], cols[at + 1 : at + 2 * Mf : 2, 0] = 0, 1
        J0[at : at + 2 * Mf, 0] = -np.repeat(1.0 / w.fix_sigma, 2)
        k[at : at + 2 * Mf] = np.repeat(w.fix_k, 2)
        at += 2 * Mf
        for prior, part in ((self.axes, 2), (self.area, 0)):
            if prior is not None:
                cols[at : at + Mv, 0], cols[at : at + Mv, 1] = part, part + 1
                k[at : at + Mv] = w.vel_k
                at += Mv
        # products of the entries (i >= j) each reading adds, per kind: (first row, rows, entries, rows per reading)
        seg = [(0, 2 * Mv, c, 2), (2 * Mv, Mr, 3 if self._shadow else 2, 1), (2 * Mv + Mr, 2 * Mf, 1, 1),
               (2 * Mv + Mr + 2 * Mf, R - 2 * Mv - Mr - 2 * Mf, 2, 1)]
        self._segments = [(a, a + m, e, per, _tril(e)) for a, m, e, per in seg if m]
        pos = []
        for a, b, e, per, (ii, jj) in self._segments:
            cs, ks = cols[a:b:per, :e], k[a:b:per]
            lo, hi = np.minimum(cs[:, ii], cs[:, jj]), np.maximum(cs[:, ii], cs[:, jj])
            pos.append(((ks[:, None] * n + lo) * kd1 + hi - lo).ravel())
        self._J0 = J0
        self._pos = np.concatenate(pos) if pos else np.zeros(0, np.int64)
        self._gpos = (k[:, None] * n + cols).ravel()

    def jacobian_rows(self, X: NDArray, hs: NDArray | None = None) -> NDArray[np.float64]:
        """(B', reading rows, c): the reading rows' Jacobian entries (columns as ``_reading_structure``)."""
        X = np.asarray(X, float).reshape(-1, self.N, self.n)
        h = slice(None) if hs is None else hs
        w, B = self.w, len(X)
        J = np.repeat(self._J0[None], B, axis=0)
        xv = X[:, w.vel_k]
        Mv = len(w.vel_k)
        if Mv:
            s, c = self._sincos(xv)
            a, b = 1.0 / self.sv[0], 1.0 / self.sv[1]
            J[:, 0 : 2 * Mv : 2, 0], J[:, 0 : 2 * Mv : 2, 1] = s * a, -c * a
            J[:, 1 : 2 * Mv : 2, 0], J[:, 1 : 2 * Mv : 2, 1] = -c * b, -s * b
            if self.theta:
                vx, vy = xv[..., 2], xv[..., 3]
                J[:, 0 : 2 * Mv : 2, 4] = (c * vx + s * vy) * a
                J[:, 1 : 2 * Mv : 2, 4] = (s * vx - c * vy) * b
        at = 2 * Mv
        if len(w.rss_k):
            xr = X[:, w.rss_k]
            gx, gy = self._pl.gradient(xr[..., 0], xr[..., 1])
            inv = -1.0 / self.sr[h]
            J[:, at : at + len(w.rss_k), 0], J[:, at : at + len(w.rss_k), 1] = gx * inv, gy * inv
            if self._shadow:
                J[:, at : at + len(w.rss_k), 2] = inv
            at += len(w.rss_k)
        at += 2 * len(w.fix_k)
        for prior, part in ((self.axes, 2), (self.area, 0)):
            if prior is not None:
                J[:, at : at + Mv, 0:2] = prior.jacobian(xv[..., part : part + 2].reshape(-1, 2)).reshape(B, Mv, 2)
                at += Mv
        return J

    def normal_equations(
        self, X: NDArray, r: NDArray, hs: NDArray | None = None
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Gauss-Newton system at ``X`` with residuals ``r`` for the hypotheses ``hs``: the band of
        J^T W J (B', size, kd + 1; see the class) and J^T W r (B', size), W the IRLS weights."""
        h = slice(None) if hs is None else hs
        n, B, kd1 = self.n, len(r), self.kd + 1
        J = self.jacobian_rows(X, hs)
        WJ = J * self.weights(r)[..., None]
        vals = []
        for a, b, e, per, (ii, jj) in self._segments:
            if per == 1:
                vals.append((WJ[:, a:b, ii] * J[:, a:b, jj]).reshape(B, -1))
            else:  # a velocity reading's two rows share their columns: their products summed
                Ws, Js = WJ[:, a:b, :e].reshape(B, -1, per, e), J[:, a:b, :e].reshape(B, -1, per, e)
                vals.append(np.einsum("bmrp,bmrp->bmp", Ws[..., ii], Js[..., jj]).reshape(B, -1))
        vals = np.concatenate(vals, axis=1) if vals else np.zeros((B, 0))
        nb = self.size * kd1
        band = _sums((np.arange(B)[:, None] * nb + self._pos).ravel(), vals.ravel(), B * nb)
        band = band.reshape(B, self.size, kd1) + self._band_const
        band.reshape(B, -1)[:, self._prior_pos] += self._prior_vals[h]
        gv = WJ * r[:, self.meas :, None]
        g = _sums((np.arange(B)[:, None] * self.size + self._gpos).ravel(), gv.ravel(), B * self.size)
        g = g.reshape(B, self.size)
        g[:, :n] += np.einsum("bki,bk->bi", self.W0[h], r[:, :n])
        if self.N > 1:
            p = r[:, n : self.meas].reshape(B, self.N - 1, n)
            g[:, n:] += (p / self.sq).reshape(B, -1)
            g[:, :-n] += np.einsum("kij,bki->bkj", self._Bk, p).reshape(B, -1)
        return band, g

    def dense(self, band: NDArray) -> NDArray[np.float64]:
        """(B', size, size) symmetric matrices of bands (B', size, kd + 1)."""
        A = np.zeros((len(band), self.size, self.size))
        i = np.arange(self.size)
        for d in range(self.kd + 1):
            A[:, i[d:], i[: self.size - d]] = band[:, : self.size - d, d]
            A[:, i[: self.size - d], i[d:]] = band[:, : self.size - d, d]
        return A


def _sums(idx: NDArray, vals: NDArray, length: int) -> NDArray[np.float64]:
    """Sums of ``vals`` by index ``idx`` (floats, also when there are none)."""
    return np.bincount(idx, vals, minlength=length) if len(vals) else np.zeros(length)


@lru_cache(maxsize=16)
def _tril(c: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    return np.tril_indices(c)


@lru_cache(maxsize=256)
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
    p: WindowProblem, X0: NDArray, max_iter: int, *, rel_tol: float = 1e-8, max_damping: float = 1e10
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """``smoother.levenberg_marquardt`` for every hypothesis of ``p`` at once, each with its own damping
    and stop; one more stop: after an iteration whose first step (damped at most as much as the
    first try) promises less than ``rel_tol`` of the cost, taken if it lowers the cost. At the
    optimum such a step often fails to lower the cost by rounding, and the damping would retry it
    ten times over before giving up, with nothing to gain. Returns the states
    (B, N, n), costs (B,), the final residuals, the last undamped bands and which of them are at
    the final states."""
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
    while not done.all():
        lin = np.flatnonzero(~done & ~fresh)
        if len(lin):
            it[lin] += 1
            band[lin], g[lin] = p.normal_equations(x[lin], r[lin], lin)
            fresh[lin] = True
        a = np.flatnonzero(~done)
        d0 = band[a, :, 0]
        dx, ok = banded_solve(band[a], -g[a], lam[a])
        # predicted decrease of the quadratic model: -2 g.dx - dx.H dx with (H + lam D) dx = -g
        pred = -np.einsum("bi,bi->b", g[a], dx) + lam[a] * np.einsum("bi,bi->b", d0, dx * dx)
        # the undamped step's decrease is at most pred (1 + lam)^2 (exact for a diagonal H)
        last = ok & (pred * (1.0 + lam[a]) ** 2 <= rel_tol * cost[a])
        c_new = np.full(len(a), np.inf)
        r_new = np.zeros((len(a), p.rows))
        if ok.any():
            r_new[ok] = p.residual(x[a[ok]] + dx[ok], a[ok])
            fin = np.isfinite(r_new[ok]).all(axis=1)
            c_new[ok] = np.where(fin, p.cost(np.where(fin[:, None], r_new[ok], 0.0)), np.inf)
        acc = c_new < cost[a]
        rej = a[~acc]
        lam[rej] *= 10.0
        done[rej[lam[rej] > max_damping]] = True
        ac = a[acc]
        if len(ac):
            drop = cost[ac] - c_new[acc]
            x[ac] += dx[acc]
            r[ac] = r_new[acc]
            cost[ac] = c_new[acc]
            lam[ac] = np.maximum(lam[ac] / 10.0, 1e-12)
            fresh[ac] = False
            stop = (drop <= rel_tol * cost[ac]) | (np.abs(dx[acc]).max(axis=1) < 1e-10) | (it[ac] >= max_iter)
            done[ac[stop]] = True
        done[a[last]] = True  # taken if it lowered the cost; nothing left to gain either way
    return x.reshape(B, p.N, p.n), cost, r, band, fresh
