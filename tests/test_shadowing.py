"""Correlated RSSI shadowing as states (FusionModel.shadowing): the OU process in distance walked,
the measurement and its derivatives, the whole-run and fixed-lag MAP with it, and the cart run
whose first-round shadowing the white-noise model mistakes for a velocity bias."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from threadpoolctl import threadpool_limits

from graphslam.core.tracking.filters import Epochs, ExtendedKalmanFilter, FusionModel, GaussianState, Shadowing
from graphslam.core.tracking.fixed_lag import FixedLagConfig, fixed_lag_smooth
from graphslam.core.tracking.smoother import MapProblem
from graphslam.errors import EstimationError
from graphslam.sim.cart import PAPER_P0, PAPER_X0, CartNoise, simulate_cart


def _model(theta_in_state: bool = False, sigma_db: float = 4.0, corr_m: float = 3.0) -> FusionModel:
    base = FusionModel.paper_ekf()
    q = np.append(base.q_diag * 1e3, 1e-3) if theta_in_state else base.q_diag * 1e3
    return FusionModel(base.path_loss, q, np.full(2, 0.01), np.full(4, 9.0), theta_rad=None if theta_in_state else 0.1,
                       shadowing=Shadowing(sigma_db, corr_m))


def _epochs(rng, n: int = 12, n_aps: int = 4) -> Epochs:
    t = np.cumsum(rng.uniform(0.3, 2.0, n))
    vel_k = np.sort(rng.choice(n, size=n - 3, replace=False))
    rss_k = rng.integers(0, n, 3 * n)
    return Epochs(t, vel_k, rng.normal(0.0, 0.3, (len(vel_k), 2)), rss_k, rng.integers(0, n_aps, len(rss_k)),
                  rng.normal(-55.0, 6.0, len(rss_k)), travel_m=rng.uniform(0.0, 2.5, n - 1))


def test_the_offsets_follow_gudmundsons_correlation_over_the_distance_walked():
    # Prior and process only (no reading): the shadowing states' joint covariance over the epochs,
    # from the MAP problem's information matrix, must be sigma^2 exp(-|D_i - D_j| / corr) with D
    # the distance walked -- the exponential model, by a route unrelated to the OU recursion.
    rng = np.random.default_rng(1)
    m = _model()
    n, N = m.n, 9
    travel = rng.uniform(0.0, 4.0, N - 1)
    travel[3] = 0.0  # standing still: the offset does not change
    e = Epochs(np.arange(N, dtype=float), np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0, np.int64),
               np.zeros(0, np.int64), np.zeros(0), travel_m=travel)
    x0, P0 = m.prior(PAPER_X0, np.eye(6))
    pr = MapProblem(m, x0, P0, e)
    cov = np.linalg.inv(pr.information(np.zeros((N, n))).toarray())
    D = np.concatenate([[0.0], np.cumsum(travel)])
    want = 16.0 * np.exp(-np.abs(D[:, None] - D[None]) / 3.0)
    for a in range(4):
        idx = np.arange(N) * n + m.shadow_state(a)
        np.testing.assert_allclose(cov[np.ix_(idx, idx)], want, rtol=2e-5, atol=1e-4)
    other = np.arange(N) * n + m.shadow_state(1)
    assert np.abs(cov[np.ix_(np.arange(N) * n + m.shadow_state(0), other)]).max() < 1e-8  # APs independent


def test_transition_and_noise_keep_the_stationary_variance_and_need_the_distance():
    m = _model()
    rho = np.exp(-1.5 / 3.0)
    F, Q = m.transition(2.0, 1.5), m.process_noise(2.0, 1.5)
    s = slice(m.n_base, m.n)
    np.testing.assert_allclose(np.diag(F)[s], rho)
    np.testing.assert_allclose(np.diag(F @ (16.0 * np.eye(m.n)) @ F.T + Q)[s], 16.0)  # sigma^2 kept
    plain = dataclasses.replace(m, shadowing=None)
    np.testing.assert_array_equal(F[: m.n_base, : m.n_base], plain.transition(2.0))
    np.testing.assert_array_equal(Q[: m.n_base, : m.n_base], plain.process_noise(2.0))
    assert np.isfinite(1.0 / np.diag(m.process_noise(1.0, 0.0))[s]).all()  # standing still: tiny, not zero
    with pytest.raises(EstimationError, match="distance"):
        m.transition(2.0)
    with pytest.raises(EstimationError, match="distance"):
        ExtendedKalmanFilter(m).predict(GaussianState(*m.prior(PAPER_X0, PAPER_P0)), 4.0)


def test_rssi_measurement_adds_its_aps_offset_and_the_jacobian_matches_numerics():
    m = _model(theta_in_state=True)
    x = np.r_[3.0, 5.0, 0.1, 0.2, 0.01, -0.02, 0.3, 2.0, -1.0, 0.5, 4.0]
    ap = np.array([3, 1, 1])
    plain = dataclasses.replace(m, shadowing=None)
    np.testing.assert_allclose(m.measure(x, False, ap)[0], plain.measure(x[:7], False, ap)[0] + x[7 + ap])
    H = m.measurement_jacobian(x, True, ap)
    num = np.array([(m.measure(x + d, True, ap)[0] - m.measure(x - d, True, ap)[0]) / 2e-6 for d in np.eye(len(x)) * 1e-6]).T
    np.testing.assert_allclose(H, num, rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("theta_in_state", [False, True])
def test_map_jacobian_with_shadowing_matches_numerical_differentiation(theta_in_state):
    rng = np.random.default_rng(5)
    m = _model(theta_in_state)
    e = _epochs(rng)
    x0, P0 = m.prior(np.r_[1.0, 1.0, 0.0, 0.1, 0.0, 0.0, 0.3][: m.n_base], np.eye(m.n_base) * 0.3)
    pr = MapProblem(m, x0, P0, e)
    X = rng.normal(0.0, 1.0, (12, m.n)) + np.r_[4.0, 7.0, np.zeros(m.n - 2)]
    J = pr.jacobian(X).toarray()
    flat = X.ravel()
    num = np.array([(pr.residual(flat + d) - pr.residual(flat - d)) / 2e-6 for d in np.eye(flat.size) * 1e-6]).T
    np.testing.assert_allclose(J, num, rtol=1e-5, atol=1e-6)


def test_epochs_carry_the_distance_walked_and_a_shadowing_model_needs_it():
    yv = np.array([[0.3, 0.4], [0.0, 0.1], [1.0, 0.0]])
    e = Epochs.fixed_rate(yv, np.full((3, 4), -50.0), 4.0)
    np.testing.assert_allclose(e.travel_m, [2.0, 0.4])  # |y_v| T: eq. 4's M keeps lengths
    with pytest.raises(EstimationError, match="travel_m"):
        Epochs(e.t_s, e.vel_k, e.vel_y, e.rss_k, e.rss_ap, e.rss_y, travel_m=[1.0])
    with pytest.raises(EstimationError, match="travel_m"):
        Epochs(e.t_s, e.vel_k, e.vel_y, e.rss_k, e.rss_ap, e.rss_y, travel_m=[1.0, -0.5])
    m = _model()
    no_travel = Epochs(e.t_s, e.vel_k, e.vel_y, e.rss_k, e.rss_ap, e.rss_y)
    with pytest.raises(EstimationError, match="distance moved"):
        MapProblem(m, *m.prior(PAPER_X0, PAPER_P0), no_travel)
    with pytest.raises(EstimationError, match="prior of size 5"):
        m.prior(PAPER_X0[:5], PAPER_P0[:5, :5])
    with pytest.raises(EstimationError, match="share"):
        FusionModel.paper_ekf().with_shadowing(1.0, 3.0)
    with pytest.raises(EstimationError, match="already"):
        m.with_shadowing(0.5, 3.0)
    with pytest.raises(EstimationError, match="corr_m"):
        Shadowing(4.0, 0.0)


def test_fixed_lag_with_shadowing_holds_a_cart_run_the_white_model_loses():
    # Seed 11 of `bench filters`, its first two rounds: with the papers' white RSSI noise (R = 40
    # dB^2) the fixed-lag smoother mistakes the first round's spatially correlated shadowing for a
    # velocity bias and stays ~2.4 m off in x; the same total variance split into a correlated
    # half (3 m) and a white half lets it explain the shadowing as shadowing (~1.2 m).
    white = FusionModel.paper_ekf()
    corr = white.with_shadowing(0.5, 3.0)
    assert corr.shadowing.sigma_db**2 + corr.r_rssi[0] == pytest.approx(40.0)  # the papers' total variance
    run = simulate_cart(11, path_loss=white.path_loss, noise=CartNoise())
    k = 188  # two rounds of the rectangle
    e = Epochs.fixed_rate(run.y_velocity[:k], run.y_rssi[:k], run.period_s)
    cfg = FixedLagConfig(lag_s=2.0, window_s=480.0, huber_k=None, prune_cost=None, restart_every=10,
                         adaptive_rssi=False, report="best")
    rms = {}
    with threadpool_limits(limits=1, user_api="blas"):  # thousands of tiny solves, as `bench filters`
        for name, m in (("white", white), ("shadowing", corr)):
            x0, P0 = m.prior(PAPER_X0, PAPER_P0)
            X = fixed_lag_smooth(m, [x0], P0, e, cfg).x
            rms[name] = np.sqrt(np.mean((X[:, :2] - run.xy[:k]) ** 2, axis=0))
    assert rms["white"][0] > 2.0
    assert rms["shadowing"][0] < 1.4 and rms["shadowing"][1] < 0.8
