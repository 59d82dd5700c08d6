"""EKF / UKF (graphslam.core.tracking.filters) against known answers, and the papers' cart experiment."""

from __future__ import annotations

import numpy as np
import pytest

from graphslam.core.tracking.filters import (
    ExtendedKalmanFilter,
    FusionModel,
    GaussianState,
    PathLossModel,
    UnscentedKalmanFilter,
    run_fixed_rate,
    sigma_points,
    unscented_transform,
    velocity_matrix,
)
from graphslam.errors import EstimationError
from graphslam.sim.cart import PAPER_P0, PAPER_X0, CartNoise, simulate_cart


def _kf_reference(x, P, ys, A, Q, H, R):
    """Textbook linear Kalman filter: predict (k > 0) then update, returns the filtered states."""
    out = []
    for k, y in enumerate(ys):
        if k:
            x, P = A @ x, A @ P @ A.T + Q
        S = H @ P @ H.T + R
        K = P @ H.T @ np.linalg.inv(S)
        x, P = x + K @ (y - H @ x), (np.eye(len(x)) - K @ H) @ P
        out.append((x, P))
    return out


@pytest.mark.parametrize("kind", ["ekf", "ukf"])
def test_linear_gaussian_case_matches_kalman_reference(kind):
    # velocity-only updates with fixed theta: a linear-Gaussian system, both filters must be the KF
    m = FusionModel.paper_ekf()
    rng = np.random.default_rng(1)
    ys = rng.normal(0, 0.1, (15, 2))
    filt = ExtendedKalmanFilter(m) if kind == "ekf" else UnscentedKalmanFilter(m, 0.1)
    A, Q = m.transition(4.0), m.process_noise(4.0)
    H = np.zeros((2, 6))
    H[:, 2:4] = velocity_matrix(0.1)
    H[:, 4:6] = np.eye(2)
    x0 = np.array([1.0, 1.0, 0.0, 0.1, 0.0, 0.0])
    P0 = np.diag([1e-2, 1e-2, 1e-2, 1e-2, 1e-3, 1e-3])
    ref = _kf_reference(x0, P0, ys, A, Q, H, np.diag(m.r_velocity))
    s = GaussianState(x0, P0)
    for k, y in enumerate(ys):
        if k:
            s = filt.predict(s, 4.0)
        s, info = filt.update(s, y, use_velocity=True)
        assert info.n_used == 2
        np.testing.assert_allclose(s.x, ref[k][0], rtol=1e-7, atol=1e-10)
        np.testing.assert_allclose(s.P, ref[k][1], rtol=1e-6, atol=1e-12)


@pytest.mark.parametrize("w0", [0.0, 0.1, 0.5])
def test_sigma_points_weights_and_linear_map(w0):
    rng = np.random.default_rng(2)
    n = 6
    L = rng.normal(size=(n, n))
    P = L @ L.T + n * np.eye(n)
    x = rng.normal(size=n)
    X, w = sigma_points(x, P, w0)
    assert X.shape == (2 * n + 1, n)
    assert w.sum() == pytest.approx(1.0, abs=1e-12)
    assert w[0] == w0 and np.allclose(w[1:], (1 - w0) / (2 * n))
    M = rng.normal(size=(3, n))
    c = rng.normal(size=3)
    mu, C = unscented_transform(X @ M.T + c, w)
    np.testing.assert_allclose(mu, M @ x + c, atol=1e-10)
    np.testing.assert_allclose(C, M @ P @ M.T, rtol=1e-9, atol=1e-9)
    with pytest.raises(EstimationError):
        sigma_points(x, P, 1.0)


@pytest.mark.parametrize("theta_in_state", [False, True])
def test_ekf_jacobian_matches_numerical_differentiation(theta_in_state):
    pl = PathLossModel.paper_ekf()
    base = FusionModel.paper_ekf()
    q = np.append(base.q_diag, 1e-4) if theta_in_state else base.q_diag
    m = FusionModel(pl, q, base.r_velocity, base.r_rssi, theta_rad=None if theta_in_state else 0.1)
    x = np.array([2.3, 5.1, 0.3, -0.2, 0.01, -0.02, 0.7][: m.n])
    idx = np.array([0, 2, 3])
    H = m.measurement_jacobian(x, True, idx)
    num = np.zeros_like(H)
    for j in range(m.n):
        e = np.zeros(m.n)
        e[j] = 1e-6
        num[:, j] = (m.measure(x + e, True, idx)[0] - m.measure(x - e, True, idx)[0]) / 2e-6
    np.testing.assert_allclose(H, num, rtol=1e-5, atol=1e-6)


def test_updates_shrink_covariance_and_keep_it_symmetric():
    m = FusionModel.paper_ukf()
    s = GaussianState(PAPER_X0, 0.5 * np.eye(6))
    for filt in (ExtendedKalmanFilter(m), UnscentedKalmanFilter(m, 0.1)):
        s2, _ = filt.update(s, np.array([0.1, 0.0, -40.0, -50.0, -52.0, -45.0]), use_velocity=True, ap_idx=np.arange(4))
        assert np.trace(s2.P) < np.trace(s.P)  # Paper 002 eq. 10 prints "+": that would grow
        np.testing.assert_array_equal(s2.P, s2.P.T)
        assert np.linalg.eigvalsh(s2.P).min() > 0


def test_gating_drops_outlier_rssi_only():
    m = FusionModel.paper_ekf()
    s = GaussianState(PAPER_X0, PAPER_P0)
    good = m.measure(PAPER_X0, True, np.arange(4))[0]
    y = good.copy()
    y[3] += 60.0  # one AP 60 dB off: ~9 sigma
    _, info = ExtendedKalmanFilter(m).update(s, y, use_velocity=True, ap_idx=np.arange(4), gate_sigma=3.0)
    assert (info.n_used, info.n_gated) == (5, 1)


@pytest.mark.parametrize("kind", ["ekf", "ukf"])
def test_cart_experiment_without_shadowing_tracks_well(kind):
    # The papers' loop on the simulated cart with fading + bias only: sub-metre RMS, while
    # dead reckoning of the biased velocities drifts by metres.
    m = FusionModel.paper_ekf() if kind == "ekf" else FusionModel.paper_ukf()
    run = simulate_cart(3, path_loss=m.path_loss, noise=CartNoise(shadowing_sigma_db=1e-6))
    filt = ExtendedKalmanFilter(m) if kind == "ekf" else UnscentedKalmanFilter(m, 0.1)
    res = run_fixed_rate(filt, PAPER_X0, PAPER_P0, run.y_velocity, run.y_rssi, run.period_s)
    rms = np.sqrt(np.mean((res.x[:, :2] - run.xy) ** 2, axis=0))
    assert (rms < 0.8).all(), rms
    assert np.abs(res.x[-1, 4:6] - run.bias).max() < 0.005  # bias recovered
    dr = run.xy[0] + np.cumsum(run.y_velocity @ np.linalg.inv(velocity_matrix(0.1)).T * run.period_s, axis=0)
    assert np.abs(dr[-1] - run.xy[-1]).max() > 5 * rms.max()
    assert res.trace_p[-1] < 1.0


def test_position_fix_update_is_the_kalman_update_and_gates_outliers():
    from graphslam.core.tracking.filters import position_update

    rng = np.random.default_rng(8)
    L = rng.normal(size=(6, 6))
    s = GaussianState(rng.normal(size=6), L @ L.T + np.eye(6))
    s2, info = position_update(s, s.x[:2] + [1.0, -2.0], 1.5)
    H = np.eye(6)[:2]
    K = s.P @ H.T @ np.linalg.inv(H @ s.P @ H.T + 1.5**2 * np.eye(2))
    np.testing.assert_allclose(s2.x, s.x + K @ [1.0, -2.0], rtol=1e-10)
    np.testing.assert_allclose(s2.P, (np.eye(6) - K @ H) @ s.P, rtol=1e-8, atol=1e-10)
    assert (info.n_used, info.n_gated) == (1, 0)
    far, info = position_update(s, s.x[:2] + [60.0, 0.0], 1.5, gate_sigma=3.0)
    assert (info.n_used, info.n_gated) == (0, 1) and far is s


@pytest.mark.parametrize("kind", ["ekf", "ukf"])
def test_adaptive_rssi_noise_changes_nothing_when_consistent_and_distrusts_a_disagreeing_scan(kind):
    m = FusionModel.paper_ekf()
    filt = ExtendedKalmanFilter(m) if kind == "ekf" else UnscentedKalmanFilter(m, 0.1)
    s = GaussianState(np.array([3.0, 5.0, 0.0, 0.1, 0.0, 0.0]), np.diag([4.0, 4.0, 0.1, 0.1, 1e-3, 1e-3]))
    idx = np.arange(4)
    y = m.measure(s.x, False, idx)[0] + np.array([2.0, -3.0, 1.0, -2.0])  # well within R = 40 dB^2
    a, _ = filt.update(s, y, use_velocity=False, ap_idx=idx, adaptive_rssi=True)
    b, _ = filt.update(s, y, use_velocity=False, ap_idx=idx)
    np.testing.assert_array_equal(a.P, b.P)
    np.testing.assert_array_equal(a.x, b.x)
    y_bad = m.measure(s.x, False, idx)[0] + np.array([25.0, -30.0, 28.0, -26.0])  # ~4 sigma each, all off
    a, ia = filt.update(s, y_bad, use_velocity=False, ap_idx=idx, adaptive_rssi=True)
    b, ib = filt.update(s, y_bad, use_velocity=False, ap_idx=idx)
    assert np.trace(a.P[:2, :2]) > np.trace(b.P[:2, :2])  # less certain than the plain update
    assert np.linalg.norm(a.x[:2] - s.x[:2]) < np.linalg.norm(b.x[:2] - s.x[:2])  # and moved less
    assert ia.nis == pytest.approx(4.0, rel=0.35) and ib.nis > 8.0  # ~1 per row after adaptation
