"""Factors: errors equal the paper's equations; Jacobians match numerical derivatives."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import X

from graphslam.config import ImuConfig, WifiFactorConfig
from graphslam.core.survey import factors as F
from graphslam.core.types import PoseTrack

CFG = WifiFactorConfig(d_min_m=2.0, d_max_m=30.0, e_max=0.3, omega=1.0)


def numerical_jacobian(factor: gtsam.NonlinearFactor, values: gtsam.Values, key: int, eps: float = 1e-6) -> np.ndarray:
    """d(whitened error)/d(local coordinates of key), central differences on the manifold."""
    base = values.atPose2(key)
    cols = []
    for i in range(3):
        dv = np.zeros(3)
        dv[i] = eps
        out = []
        for sgn in (+1, -1):
            v = gtsam.Values(values)
            v.update(key, base.retract(sgn * dv))
            out.append(factor.whitenedError(v) if hasattr(factor, "whitenedError") else factor.unwhitenedError(v))
        cols.append((out[0] - out[1]) / (2 * eps))
    return np.column_stack(cols)


def analytic_jacobians(factor: gtsam.NonlinearFactor, values: gtsam.Values) -> list[np.ndarray]:
    lin = factor.linearize(values)
    A, _ = lin.jacobian()
    return [A[:, 0:3], A[:, 3:6]]


def test_relative_steps_inverts_eq6() -> None:
    rng = np.random.default_rng(1)
    h = np.cumsum(rng.normal(0, 0.3, 20))
    xy = np.cumsum(rng.normal(0, 0.7, (20, 2)), axis=0)
    u = F.relative_steps(PoseTrack(np.arange(20), xy, h))
    # eq. 6: pos_k = pos_{k-1} + R(theta_{k-1}) (dx, dy), theta_k = theta_{k-1} + dtheta
    c, s = np.cos(h[:-1]), np.sin(h[:-1])
    x_next = xy[:-1, 0] + u[:, 0] * c - u[:, 1] * s
    y_next = xy[:-1, 1] + u[:, 0] * s + u[:, 1] * c
    np.testing.assert_allclose(np.column_stack([x_next, y_next]), xy[1:], atol=1e-12)
    np.testing.assert_allclose(np.cos(h[:-1] + u[:, 2] - h[1:]), 1.0, atol=1e-12)


def test_imu_factor_error_is_eq7_to_first_order() -> None:
    noise = F.imu_noise(ImuConfig(sigma_xy_m=1.0, sigma_heading_rad=1.0))
    u = np.array([0.7, 0.05, 0.1])
    f = F.imu_factor(X(0), X(1), u, noise)
    p0 = gtsam.Pose2(3.0, -2.0, 0.4)
    u_nodes = np.array([0.71, 0.048, 0.1015])  # the step the nodes imply
    p1 = p0.compose(gtsam.Pose2(*u_nodes))
    v = gtsam.Values()
    v.insert(X(0), p0)
    v.insert(X(1), p1)
    e = f.unwhitenedError(v)
    e7 = u_nodes - u  # eq. 7
    # GTSAM expresses the translation error in the frame of the later pose (eq. 7: the
    # earlier one): a rotation by dtheta, invisible to the isotropic Omega_IMU of eq. 8.
    assert e[2] == pytest.approx(e7[2], abs=1e-12)
    assert np.hypot(e[0], e[1]) == pytest.approx(np.hypot(e7[0], e7[1]), rel=1e-3)
    assert f.error(v) == pytest.approx(0.5 * e7 @ e7, rel=2e-3)


def test_imu_information_matches_eq8() -> None:
    cfg = ImuConfig(sigma_xy_m=0.05, sigma_heading_rad=0.01)
    R = F.imu_noise(cfg).R()
    np.testing.assert_allclose(R.T @ R, np.diag([400.0, 400.0, 1e4]), rtol=1e-12)


@pytest.mark.parametrize("seed", range(4))
def test_imu_jacobians_match_numerical(seed: int) -> None:
    rng = np.random.default_rng(seed)
    f = F.imu_factor(X(0), X(1), rng.normal(0, 0.5, 3), F.imu_noise(ImuConfig()))
    v = gtsam.Values()
    v.insert(X(0), gtsam.Pose2(*rng.normal(0, 3, 3)))
    v.insert(X(1), gtsam.Pose2(*rng.normal(0, 3, 3)))
    A = analytic_jacobians(f, v)
    for k, key in enumerate((X(0), X(1))):
        np.testing.assert_allclose(A[k], numerical_jacobian(f, v, key), atol=1e-5, rtol=1e-5)


def test_fuzzy_error_is_eq10() -> None:
    d = np.array([0.0, 1.9, 2.0, 9.0, 16.0, 30.0, 31.0, 300.0])
    expected = [0.0, 0.0, 0.0, 0.3 * 7 / 28, 0.3 * 14 / 28, 0.3, 0.3, 0.3]
    np.testing.assert_allclose(F.fuzzy_error(d, CFG), expected, atol=1e-12)
    np.testing.assert_array_equal(F.edge_state(d, CFG), [0, 0, 1, 1, 1, 1, 2, 2])


@pytest.mark.parametrize("d", [0.5, 1.99, 2.5, 10.0, 29.0])
def test_wifi_factor_cost_equals_eq10_on_ramp(d: float) -> None:
    cfg = WifiFactorConfig(d_min_m=2.0, d_max_m=30.0, e_max=0.3, omega=2.5)
    f = F.wifi_factor(X(0), X(1), F.wifi_noise(cfg))
    v = gtsam.Values()
    v.insert(X(0), gtsam.Pose2(1.0, 2.0, 0.3))
    ang = 0.7
    v.insert(X(1), gtsam.Pose2(1.0 + d * np.cos(ang), 2.0 + d * np.sin(ang), -1.0))
    assert f.error(v) == pytest.approx(float(F.fuzzy_cost(d, cfg)), rel=1e-9, abs=1e-15)


@pytest.mark.parametrize("seed", range(4))
def test_wifi_jacobians_match_numerical(seed: int) -> None:
    """Gradient of the robust factor's error vs central differences of its cost."""
    rng = np.random.default_rng(seed)
    f = F.wifi_factor(X(0), X(1), F.wifi_noise(CFG))
    v = gtsam.Values()
    p0 = gtsam.Pose2(*rng.normal(0, 3, 3))
    d = rng.uniform(3, 28)
    a = rng.uniform(-np.pi, np.pi)
    v.insert(X(0), p0)
    v.insert(X(1), gtsam.Pose2(p0.x() + d * np.cos(a), p0.y() + d * np.sin(a), rng.normal()))
    lin = f.linearize(v)
    A, b = lin.jacobian()
    grad = -(A.T @ b)  # gradient of 0.5|A dx - b|^2 at dx = 0 is -A^T b ... sign: error(dx) ~ 0.5|A dx + r|^2
    eps = 1e-6
    num = []
    for key in (X(0), X(1)):
        base = v.atPose2(key)
        for i in range(3):
            dv = np.zeros(3)
            dv[i] = eps
            vp, vm = gtsam.Values(v), gtsam.Values(v)
            vp.update(key, base.retract(dv))
            vm.update(key, base.retract(-dv))
            num.append((f.error(vp) - f.error(vm)) / (2 * eps))
    # GTSAM linearises to |A dx - b|^2 / 2 with b = -whitened error: gradient = -A^T b
    np.testing.assert_allclose(grad, num, rtol=1e-4, atol=1e-7)
    # and the plain range Jacobian (unwhitened) against differences of the distance
    rf = gtsam.RangeFactorPose2(X(0), X(1), 0.0, gtsam.noiseModel.Unit.Create(1))
    Ar = analytic_jacobians(rf, v)
    for k, key in enumerate((X(0), X(1))):
        np.testing.assert_allclose(Ar[k], numerical_jacobian(rf, v, key), atol=1e-6)


def test_wifi_factor_is_flat_inside_dead_zone() -> None:
    f = F.wifi_factor(X(0), X(1), F.wifi_noise(CFG))
    v = gtsam.Values()
    v.insert(X(0), gtsam.Pose2(0, 0, 0))
    v.insert(X(1), gtsam.Pose2(1.5, 0.5, 0))
    assert f.error(v) == 0.0
    A, b = f.linearize(v).jacobian()
    assert np.allclose(A, 0) and np.allclose(b, 0)
