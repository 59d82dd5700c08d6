"""Offline smoothers (graphslam.core.tracking.smoother): known answers, derivatives, the cart run."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from graphslam.core.tracking.axes import WalkAxes
from graphslam.core.tracking.walkable import WalkableArea
from graphslam.core.tracking.filters import Epochs, ExtendedKalmanFilter, FusionModel, PathLossModel, make_filter, run_epochs
from graphslam.core.tracking.smoother import MapProblem, map_smooth, rts_smooth, smooth
from graphslam.errors import EstimationError
from graphslam.sim.cart import PAPER_P0, PAPER_X0, simulate_cart


def _irregular_epochs(rng, n_aps: int = 0, n: int = 25, n_fix: int = 6) -> Epochs:
    t = np.cumsum(rng.uniform(0.3, 2.0, n))
    vel_k = np.sort(rng.choice(n, size=max(n - 6, 1), replace=False))  # some epochs hold no velocity
    rss_k = rng.integers(0, n, 3 * n) if n_aps else np.zeros(0, np.int64)
    rss_ap = rng.integers(0, n_aps, len(rss_k)) if n_aps else np.zeros(0, np.int64)
    fix_k = rng.integers(0, n, n_fix)  # position fixes, two at one epoch allowed
    return Epochs(
        t, vel_k, rng.normal(0.0, 0.3, (len(vel_k), 2)), rss_k, rss_ap, rng.normal(-55.0, 6.0, len(rss_k)),
        fix_k, rng.normal(3.0, 2.0, (n_fix, 2)), rng.uniform(0.5, 3.0, n_fix),
    )


def _model(theta_in_state: bool) -> FusionModel:
    base = FusionModel.paper_ekf()
    q = np.append(base.q_diag * 1e3, 1e-3) if theta_in_state else base.q_diag * 1e3
    return FusionModel(base.path_loss, q, np.full(2, 0.01), base.r_rssi, theta_rad=None if theta_in_state else 0.1)


def test_linear_gaussian_map_equals_rts_in_mean_and_covariance():
    # Velocity readings and position fixes, theta fixed: a linear-Gaussian smoothing problem whose
    # answer the Kalman filter + RTS pass and the whole-run least squares must both reach, by
    # unrelated code.
    rng = np.random.default_rng(4)
    m = _model(False)
    epochs = _irregular_epochs(rng)
    x0 = np.array([1.0, 2.0, 0.1, -0.2, 0.0, 0.0])
    P0 = np.diag([0.5, 0.5, 0.2, 0.2, 0.01, 0.01])
    filtered = run_epochs(ExtendedKalmanFilter(m), x0, P0, epochs)
    rts = rts_smooth(m, filtered, epochs)
    mp = map_smooth(MapProblem(m, x0, P0, epochs), [np.zeros((len(epochs), 6))])
    np.testing.assert_allclose(mp.x, rts.x, atol=1e-5)  # LM stops at a relative cost change of 1e-8
    np.testing.assert_allclose(mp.P, rts.P, rtol=1e-6, atol=1e-10)
    np.testing.assert_allclose(rts.x[-1], filtered.x[-1])  # the last state has no future to use
    assert not np.allclose(rts.x[0], filtered.x[0], atol=1e-3)  # earlier ones do


# a walkable area whose distance field is non-zero around the test states (x ~ 4, y ~ 7): a band at y 0-5 m
_AREA = WalkableArea(np.r_[np.zeros((40, 50), bool), np.ones((10, 50), bool)], 25.0, 25.0, sigma_m=1.5)


@pytest.mark.parametrize("theta_in_state,axes,area", [
    (False, None, None), (True, None, None), (True, WalkAxes(0.3, 0.2), None), (True, WalkAxes(0.3, 0.2), _AREA),
])
def test_map_jacobian_matches_numerical_differentiation(theta_in_state, axes, area):
    rng = np.random.default_rng(5)
    m = _model(theta_in_state)
    epochs = _irregular_epochs(rng, n_aps=4, n=12)
    pr = MapProblem(m, np.r_[1.0, 1.0, 0.0, 0.1, 0.0, 0.0, 0.3][: m.n], np.eye(m.n) * 0.3, epochs, axes=axes, area=area)
    X = rng.normal(0.0, 1.0, (12, m.n)) + np.r_[4.0, 7.0, 0, 0, 0, 0, 0][: m.n]
    J = pr.jacobian(X).toarray()
    num = np.zeros_like(J)
    flat = X.ravel()
    for j in range(flat.size):
        e = np.zeros(flat.size)
        e[j] = 1e-6
        num[:, j] = (pr.residual(flat + e) - pr.residual(flat - e)) / 2e-6
    np.testing.assert_allclose(J, num, rtol=1e-5, atol=1e-6)
    # the banded normal equations the solver uses hold the same J^T W J and J^T W r
    pr2 = MapProblem(m, np.r_[1.0, 1.0, 0.0, 0.1, 0.0, 0.0, 0.3][: m.n], np.eye(m.n) * 0.3, epochs, huber_k=1.0, axes=axes,
                     area=area)
    r = pr2.residual(X)
    band, g = pr2.normal_equations(X, r)
    W = pr2.weights(r) ** 2
    np.testing.assert_allclose(band, pr2.banded(sp.csr_matrix(J.T @ (W[:, None] * J))), atol=1e-8)
    np.testing.assert_allclose(g, J.T @ (W * r), atol=1e-8)
    if axes is not None:  # one prior row per velocity reading (each prior), after the fixes
        assert len(r) == len(MapProblem(m, X[0], np.eye(m.n), epochs).residual(X)) + len(epochs.vel_k) * (1 + (area is not None))
    if area is not None:  # the area's rows are not all zero here: the test exercises them
        assert (area.residual(X[epochs.vel_k, :2]) > 0).all()


def test_marginals_are_the_diagonal_blocks_of_the_inverse_information():
    rng = np.random.default_rng(6)
    m = _model(True)
    epochs = _irregular_epochs(rng, n_aps=4, n=15)
    pr = MapProblem(m, np.r_[1.0, 1.0, 0.0, 0.1, 0.0, 0.0, 0.3], np.eye(7) * 0.3, epochs, huber_k=2.0)
    X = rng.normal(0.0, 1.0, (15, 7)) + np.r_[4.0, 7.0, 0, 0, 0, 0, 0]
    J = np.diag(pr.weights(pr.residual(X))) @ pr.jacobian(X).toarray()
    full = np.linalg.inv(J.T @ J)
    blocks = np.array([full[7 * k : 7 * k + 7, 7 * k : 7 * k + 7] for k in range(15)])
    np.testing.assert_allclose(pr.marginals(X), blocks, rtol=1e-6, atol=1e-10)


def test_huber_cost_is_quadratic_inside_and_linear_outside():
    rng = np.random.default_rng(7)
    m = _model(False)
    pr = MapProblem(m, np.zeros(6), np.eye(6), _irregular_epochs(rng, n_aps=4, n=5, n_fix=0), huber_k=2.0)
    r = np.zeros(pr._rows[-1])
    r[0], r[-1], r[-2] = 3.0, 1.0, -5.0  # a prior row (always quadratic), two map rows
    assert pr.cost(r) == pytest.approx(9.0 + 1.0 + (2 * 2.0 * 5.0 - 4.0))
    w = pr.weights(r)
    assert w[0] == 1.0 and w[-1] == 1.0 and w[-2] == pytest.approx(np.sqrt(2.0 / 5.0))


def test_map_smoother_recovers_the_cart_run_the_ekf_loses():
    # Seed 12 of `graphslam bench filters`: the EKF locks onto a shifted path (RMS ~2.3 / 2.4 m);
    # the whole-run MAP under the same model, started without the truth, meets the paper's figures.
    m = FusionModel.paper_ekf()
    run = simulate_cart(12, path_loss=m.path_loss)
    epochs = Epochs.fixed_rate(run.y_velocity, run.y_rssi, run.period_s)
    filtered = run_epochs(make_filter("ekf", m), PAPER_X0, PAPER_P0, epochs)
    rms = lambda X: np.sqrt(((X[:, :2] - run.xy) ** 2).mean(0))
    assert (rms(filtered.x) > 2.0).all()
    sm = smooth(m, PAPER_X0, PAPER_P0, epochs, filtered, "map")
    assert (rms(sm.x) <= [0.86, 1.15]).all(), rms(sm.x)
    pr = MapProblem(m, PAPER_X0, PAPER_P0, epochs)
    assert sm.cost < pr.cost(pr.residual(filtered.x))  # a more probable trajectory, not a luckier one
    assert np.all(np.linalg.eigvalsh(sm.P) > 0)


def test_epochs_and_smoother_reject_bad_input():
    with pytest.raises(EstimationError, match="strictly increasing"):
        Epochs(np.array([0.0, 1.0, 1.0]), [0], [[0.0, 0.1]], [], [], [])
    with pytest.raises(EstimationError, match="non-finite"):
        Epochs(np.array([0.0, 1.0]), [0], [[np.nan, 0.1]], [], [], [])
    with pytest.raises(EstimationError, match="out of range"):
        Epochs(np.array([0.0, 1.0]), [2], [[0.0, 0.1]], [], [], [])
    base = FusionModel.paper_ekf()
    epochs = Epochs.fixed_rate(np.zeros((3, 2)), np.full((3, 4), -50.0), 4.0)
    zero_q = FusionModel(base.path_loss, np.r_[base.q_diag[:5], 0.0], base.r_velocity, base.r_rssi)
    with pytest.raises(EstimationError, match="process-noise"):
        MapProblem(zero_q, PAPER_X0, PAPER_P0, epochs)
    filtered = run_epochs(ExtendedKalmanFilter(base), PAPER_X0, PAPER_P0, epochs)
    with pytest.raises(EstimationError, match="unknown smoother"):
        smooth(base, PAPER_X0, PAPER_P0, epochs, filtered, "ukf")
    five_aps = Epochs(np.array([0.0, 1.0]), [0], [[0.0, 0.1]], [1], [4], [-50.0])
    with pytest.raises(EstimationError, match="AP index 4"):
        MapProblem(FusionModel(PathLossModel.paper_ekf(), base.q_diag, base.r_velocity, base.r_rssi), PAPER_X0, PAPER_P0, five_aps)
