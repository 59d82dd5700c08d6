"""The fixed-lag smoother's batched window (graphslam.core.tracking.window) against the reference
algebra: ``MapProblem``'s rows and sparse Jacobian, its Levenberg-Marquardt, dense inverses and
the dense Schur complement of the marginalised epoch, on small nonlinear windows (RSSI rows,
the heading in the state, Huber weights, walk axes, a walkable area, shadowing states)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg as sla
import scipy.sparse as sp

from graphslam.core.tracking.axes import WalkAxes
from graphslam.core.tracking.filters import Epochs, FusionModel
from graphslam.core.tracking.fixed_lag import FixedLagConfig, _Bank, _Stream, fixed_lag_smooth
from graphslam.core.tracking.smoother import MapProblem, levenberg_marquardt, map_smooth
from graphslam.core.tracking.walkable import WalkableArea
from graphslam.core.tracking.window import (
    RunReadings, banded_cholesky, banded_solve, levenberg_marquardt_bank, marginal_covariances,
)


def _model(theta: bool, shadowing: bool = False) -> FusionModel:
    base = FusionModel.paper_ekf()
    q = np.r_[base.q_diag * 1e3, 1e-4] if theta else base.q_diag * 1e3
    m = FusionModel(base.path_loss, q, np.full(2, 0.01), base.r_rssi, theta_rad=None if theta else 0.1)
    return m.with_shadowing(0.5, 3.0) if shadowing else m


def _epochs(n: int = 25, seed: int = 5) -> Epochs:
    """Readings of a walk across the paper's AP rectangle under the model's own noise (theta 0.4,
    bias (0.02, -0.01)); velocity readings at most epochs, RSSI at every other, seven fixes."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.3, 1.5, n))
    v = np.column_stack([0.3 + 0.2 * np.sin(t / 3.0), 0.6 + 0.1 * np.cos(t / 2.0)])
    xy = np.array([2.0, 1.0]) + np.vstack([np.zeros(2), np.cumsum(v[:-1] * np.diff(t)[:, None], axis=0)])
    vel_k = np.sort(rng.choice(n, size=n - 5, replace=False))
    s, c = np.sin(0.4), np.cos(0.4)
    yv = np.column_stack([-s * v[vel_k, 0] + c * v[vel_k, 1], c * v[vel_k, 0] + s * v[vel_k, 1]]) + [0.02, -0.01]
    rss_k = np.repeat(np.arange(0, n, 2), 3)
    ap = rng.integers(0, 4, len(rss_k))
    pl = FusionModel.paper_ekf().path_loss
    rss = pl.rss_mean(xy[rss_k], ap) + rng.normal(0.0, 3.0, len(rss_k))
    fix_k = np.sort(rng.choice(n, size=7, replace=False))
    return Epochs(
        t, vel_k, yv + rng.normal(0.0, 0.05, yv.shape), rss_k, ap, rss, fix_k, xy[fix_k] + rng.normal(0.0, 1.0, (7, 2)),
        rng.uniform(0.5, 2.0, 7), travel_m=np.linalg.norm(np.diff(xy, axis=0), axis=1),
    )


def _priors(m: FusionModel, B: int, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    x0 = np.zeros((B, m.n))
    x0[:, :6] = [2.0, 1.0, 0.3, 0.6, 0.02, -0.01]
    x0 += rng.normal(0.0, 0.3, x0.shape)
    if m.theta_rad is None:
        x0[:, 6] = np.linspace(0.0, 0.8, B)
    A = rng.normal(0.0, 0.3, (B, m.n, m.n))
    P0 = np.einsum("bij,bkj->bik", A, A) + np.eye(m.n) * 0.5
    return x0, P0


def _window(m: FusionModel, e: Epochs, x0: np.ndarray, P0: np.ndarray, scale: np.ndarray, **kw):
    """The whole run as one window (every reading known)."""
    return RunReadings(m, e, **kw).window(0, len(e) - 1, np.inf, x0, np.linalg.inv(P0), scale)


CASES = [
    dict(theta=True), dict(theta=False), dict(theta=True, axes=True), dict(theta=True, area=True),
    dict(theta=False, shadowing=True), dict(theta=True, huber=None),
]


def _case(theta: bool, shadowing: bool = False, axes: bool = False, area: bool = False, huber: float | None = 1.0):
    m, e = _model(theta, shadowing), _epochs()
    walk = np.zeros((20, 20), bool)
    walk[5:15, :] = True
    return (m, e, WalkAxes(0.3) if axes else None, WalkableArea(walk, 20.0, 20.0, 1.5) if area else None, huber)


@pytest.mark.parametrize("case", CASES, ids=lambda c: "-".join(f"{k}={v}" for k, v in c.items()))
def test_rows_cost_and_normal_equations_are_the_map_problems(case):
    m, e, axes, area, huber = _case(**case)
    B = 3
    x0, P0 = _priors(m, B)
    rng = np.random.default_rng(2)
    scale = rng.uniform(1.0, 2.0, (B, len(e.rss_k)))
    p = _window(m, e, x0, P0, scale, huber_k=huber, axes=axes, area=area)
    X = x0[:, None, :] + rng.normal(0.0, 0.7, (B, len(e), m.n))
    r = p.residual(X)
    band, g = p.normal_equations(X, r)
    H = p.dense(band)
    for b in range(B):
        eb = Epochs(e.t_s, e.vel_k, e.vel_y, e.rss_k, e.rss_ap, e.rss_y, e.fix_k, e.fix_xy, e.fix_sigma, scale[b], e.travel_m)
        ref = MapProblem(m, x0[b], P0[b], eb, huber_k=huber, axes=axes, area=area)
        rr = ref.residual(X[b].ravel())
        # prior rows: whitened by another square root of the same information, so only their norm is the same
        assert np.linalg.norm(r[b, : m.n]) == pytest.approx(np.linalg.norm(rr[: m.n]), rel=1e-9)
        np.testing.assert_allclose(r[b, m.n:], rr[m.n:], rtol=1e-12, atol=1e-12)
        assert p.cost(r)[b] == pytest.approx(ref.cost(rr), rel=1e-12)
        sw = ref.weights(rr)
        J = sp.diags(sw) @ ref.jacobian(X[b].ravel())
        np.testing.assert_allclose(H[b], (J.T @ J).toarray(), rtol=1e-10, atol=1e-9)
        np.testing.assert_allclose(g[b], J.T @ (sw * rr), rtol=1e-10, atol=1e-9)
    sub = np.array([2, 0])  # a subset of the hypotheses gives their rows
    np.testing.assert_allclose(p.residual(X[sub], sub), r[sub], rtol=0, atol=0)
    np.testing.assert_allclose(p.normal_equations(X[sub], r[sub], sub)[0], band[sub], rtol=1e-14, atol=1e-12)


@pytest.mark.parametrize("case", CASES[:3], ids=lambda c: "-".join(f"{k}={v}" for k, v in c.items()))
def test_the_banks_levenberg_marquardt_reaches_the_reference_solutions(case):
    # Each hypothesis from its own start: with tight tolerances both reach the same minimum.
    m, e, axes, area, huber = _case(**case)
    B = 3
    x0, P0 = _priors(m, B)
    scale = np.ones((B, len(e.rss_k)))
    p = _window(m, e, x0, P0, scale, huber_k=huber, axes=axes, area=area)
    X0 = x0[:, None, :] + np.random.default_rng(4).normal(0.0, 0.3, (B, len(e), m.n))
    X, cost, r, _, _, _ = levenberg_marquardt_bank(p, X0, 60, rel_tol=1e-13)
    for b in range(B):
        ref = MapProblem(m, x0[b], P0[b], e, huber_k=huber, axes=axes, area=area)
        Xr, cr, _ = levenberg_marquardt(ref, X0[b], 60, rel_tol=1e-13)
        assert cost[b] == pytest.approx(cr, rel=1e-9)
        np.testing.assert_allclose(X[b], Xr, atol=1e-5)
    np.testing.assert_allclose(r, p.residual(X), atol=0)


@pytest.mark.parametrize("stall_tol", [None, 1e-3])
def test_the_banks_levenberg_marquardt_returns_the_system_at_its_final_states(stall_tol):
    # The tracker's tolerances: the LM stops without taking a step that promises too little (or,
    # with stall_tol, after one that failed); residuals, costs and the normal equations flagged
    # fresh are those of the returned states (the marginals and the marginalisation use them).
    m, e, axes, area, huber = _case(theta=True, axes=True)
    B = 4
    x0, P0 = _priors(m, B)
    p = _window(m, e, x0, P0, np.ones((B, len(e.rss_k))), huber_k=huber, axes=axes, area=area)
    X0 = x0[:, None, :] + np.random.default_rng(5).normal(0.0, 0.3, (B, len(e), m.n))
    X, cost, r, band, g, fresh = levenberg_marquardt_bank(p, X0, 10, rel_tol=1e-5, max_damping=1.0, stall_tol=stall_tol)
    np.testing.assert_array_equal(r, p.residual(X))
    np.testing.assert_array_equal(cost, p.cost(r))
    assert fresh.any()
    k = np.flatnonzero(fresh)
    b2, g2 = p.normal_equations(X[k], r[k], k)
    np.testing.assert_allclose(band[k], b2, rtol=1e-13, atol=1e-12)
    np.testing.assert_allclose(g[k], g2, rtol=1e-13, atol=1e-12)
    assert (cost <= p.cost(p.residual(X0))).all()
    tight, tc, _, _, _, _ = levenberg_marquardt_bank(p, X0, 60, rel_tol=1e-20, max_damping=1e10)
    assert (cost <= tc * (1 + 1e-3)).all()  # what the stops leave is below 0.1 % of the cost


def test_marginal_covariances_of_the_stacked_factor_are_blocks_of_the_inverses():
    m, e, axes, area, huber = _case(theta=True, axes=True)
    B = 3
    x0, P0 = _priors(m, B)
    p = _window(m, e, x0, P0, np.ones((B, len(e.rss_k))), huber_k=huber, axes=axes)
    X = x0[:, None, :] + np.random.default_rng(6).normal(0.0, 0.5, (B, len(e), m.n))
    band, _ = p.normal_equations(X, p.residual(X))
    inv = np.linalg.inv(p.dense(band))
    c = banded_cholesky(band.copy())
    n = m.n
    for i in (0, 7, len(e) - 3, len(e) - 1):
        S = marginal_covariances(c, B, p.size, n, i)
        np.testing.assert_allclose(S, inv[:, i * n : (i + 1) * n, i * n : (i + 1) * n], rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("reuse", [True, False], ids=["from the last solve", "own problem"])
def test_marginalising_the_first_epoch_is_the_dense_schur_complement_of_its_rows(reuse):
    # The reference: the rows of the window problem that touch its first epoch, linearised at the
    # current states (IRLS weights), dense, and that epoch eliminated. The bank takes them from the
    # last solve's information when that window is this one's, else builds them.
    m, e, axes, area, huber = _case(theta=True, axes=True)
    cfg = FixedLagConfig(huber_k=huber, adaptive_rssi=False)
    stream = _Stream(m, e, cfg, None, axes)
    x0, P0 = _priors(m, 1)
    starts = [x0[0], x0[0] + np.r_[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.5]]
    bank = _Bank(stream, starts, P0[0])
    for j in range(6):
        stream.now = float(e.t_s[j])
        bank.extend(j)
        bank.solve(stream.now)
    n, refs = m.n, []
    for h in range(2):
        p = stream.problem(bank.lo, bank.hi, stream.now, bank.prior_x[h], bank.prior_P[h], bank.rss_scale[h])
        x = bank.X[h].ravel()
        r = p.residual(x)
        sw = p.weights(r)
        rows = p.rows_touching_first_epoch()
        J = (sp.diags(sw[rows]) @ p.jacobian(x)[rows])[:, : 2 * n].toarray()
        H, g = J.T @ J, J.T @ (sw[rows] * r[rows])
        A = np.linalg.solve(H[:n, :n], H[:n, n:])
        H1 = H[n:, n:] - H[n:, :n] @ A
        g1 = g[n:] - A.T @ g[:n]
        step = np.linalg.solve(H1, g1)
        kept = r.copy()
        kept[rows] = 0.0
        head = p.cost(r) - p.cost(kept)
        refs.append((bank.X[h, 1] - step, np.linalg.inv(H1),
                     bank.const[h] + head - g[:n] @ np.linalg.solve(H[:n, :n], g[:n]) - g1 @ step))
    if not reuse:
        bank._solved = None
    bank.marginalise_first()
    for h, (x1, P1, const) in enumerate(refs):
        np.testing.assert_allclose(bank.prior_x[h], x1, rtol=1e-9, atol=1e-10)
        np.testing.assert_allclose(bank.prior_P[h], P1, rtol=1e-8, atol=1e-12)
        assert bank.const[h] == pytest.approx(const, rel=1e-9, abs=1e-9)


def test_a_window_that_keeps_every_epoch_ends_at_the_whole_run_map():
    # Nothing marginalised (window and lag beyond the run): the last solve of the incrementally
    # grown, warm-started window is the whole-run MAP solved from scratch (nonlinear, robust).
    m, e = _model(theta=True), _epochs()
    x0, P0 = _priors(m, 1)
    cfg = FixedLagConfig(lag_s=1e9, window_s=1e9, huber_k=1.0, rel_tol=1e-20, stall_tol=None, max_iter=60, prune_cost=None,
                         adaptive_rssi=False, report="best")
    fl = fixed_lag_smooth(m, [x0[0]], P0[0], e, cfg)
    whole = map_smooth(MapProblem(m, x0[0], P0[0], e, huber_k=1.0), [fl.x], max_iter=100)
    np.testing.assert_allclose(fl.x, whole.x, atol=1e-6)
    np.testing.assert_allclose(fl.P, whole.P, rtol=1e-6, atol=1e-9)
    assert fl.cost[0] == pytest.approx(whole.cost, rel=1e-9)


def test_an_indefinite_damped_system_fails_alone():
    m, e, axes, area, huber = _case(theta=True)
    B = 3
    x0, P0 = _priors(m, B)
    p = _window(m, e, x0, P0, np.ones((B, len(e.rss_k))), huber_k=huber)
    X = np.repeat(x0[:, None, :], len(e), axis=1)
    band, g = p.normal_equations(X, p.residual(X))
    band[1, 3, 0] = -1.0  # hypothesis 1's matrix is no longer positive definite
    dx, ok = banded_solve(band, -g, np.zeros(B))
    assert ok.tolist() == [True, False, True] and np.isnan(dx[1]).all()
    for b in (0, 2):
        np.testing.assert_allclose(dx[b], sla.solve(p.dense(band[b : b + 1])[0], -g[b]), rtol=1e-8, atol=1e-10)


def test_dead_reckoning_restarts_go_through_the_reference_lm_and_back_into_the_bank():
    # Every few epochs each hypothesis's window is also solved (by the reference LM on its
    # MapProblem) from dead-reckoning starts, the lower cost kept: the bank takes those states on.
    m, e = _model(theta=True), _epochs()
    x0, P0 = _priors(m, 2)
    cfg = dict(lag_s=2.0, window_s=6.0, huber_k=1.0, prune_cost=None, adaptive_rssi=False, report="best")
    plain = fixed_lag_smooth(m, list(x0), P0[0], e, FixedLagConfig(**cfg))
    again = fixed_lag_smooth(m, list(x0), P0[0], e, FixedLagConfig(**cfg, restart_every=4))
    assert np.isfinite(again.x).all() and np.isfinite(again.P).all() and np.isfinite(again.cost).all()
    assert again.solves == plain.solves
