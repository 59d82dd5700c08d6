"""UWB maths: two-way ranging (eq. 4-6), trilateration, the stride model, and the paper's EKF
(eq. 7, 12-15) checked against a linear-Gaussian batch solution and numerical derivatives."""

from __future__ import annotations

import numpy as np
import pytest

from graphslam.core.uwb.ekf import (
    ANCHOR, NEIGHBOUR, TRILATERATION, TagState, UwbEkfConfig, UwbEpoch, condition_number, kalman_update,
    neighbour_range_variance, position_update, predict, process_noise, range_model, range_update, track_tags,
    transition,
)
from graphslam.core.uwb.motion import position_at, stride_fraction
from graphslam.core.uwb.ranging import (
    SPEED_OF_LIGHT_MPS, ds_twr_tof, horizontal_range, ss_twr_tof, tof_to_range, trilaterate,
)

C = SPEED_OF_LIGHT_MPS


def test_ds_twr_cancels_clock_rates_ss_twr_does_not() -> None:
    tof, reply = 20.0 / C, 300e-6
    ri, rj = 1 + 15e-6, 1 - 10e-6  # initiator / responder clock rates
    # single-sided: the initiator times the round trip on its clock, the responder its reply on its own
    t_round = ri * (2 * tof + reply / rj)
    ss = tof_to_range(ss_twr_tof(t_round, reply))
    assert ss - 20.0 == pytest.approx(C * (ri - rj) / rj * reply / 2, rel=1e-3)  # ~1.1 m: the known SS-TWR drift
    # double-sided, asymmetric replies: first-order clock independent
    d1, d2 = 300e-6, 450e-6
    r1 = ri * (2 * tof + d1 / rj)
    r2 = rj * (2 * tof + d2 / ri)
    ds = tof_to_range(ds_twr_tof(r1, d1, r2, d2))
    assert abs(ds - 20.0) < 1e-3


def test_trilateration_recovers_the_position_and_its_covariance() -> None:
    anchors = np.array([[0, 0, 2.2], [10, 0, 2.2], [10, 8, 2.2], [0, 8, 2.2]])
    p = np.array([3.0, 5.0])
    r = np.sqrt(np.sum((anchors[:, :2] - p) ** 2, axis=1) + (2.2 - 1.0) ** 2)
    tri = trilaterate(anchors, r, 0.05, tag_height_m=1.0)
    assert tri.ok and np.allclose(tri.xy, p, atol=1e-6) and tri.rms_m < 1e-6
    # covariance sigma^2 (J^T J)^-1 matches the spread of noisy solutions
    rng = np.random.default_rng(1)
    sols = np.array([trilaterate(anchors, r + rng.normal(0, 0.05, 4), 0.05, tag_height_m=1.0).xy for _ in range(4000)])
    # sampling error of a covariance entry ~ sigma^2 sqrt(2 / n) ~ 3e-5 here
    np.testing.assert_allclose(np.cov(sols.T), tri.cov, rtol=0.1, atol=1e-4)
    assert not trilaterate(anchors[:2], r[:2], 0.05).ok
    assert not trilaterate(np.array([[0, 0], [1, 1], [2, 2]]), np.array([1.0, 1.0, 1.0]), 0.05).ok  # collinear


def test_horizontal_range() -> None:
    rh, sh = horizontal_range(np.array([5.0, 1.0]), np.array([3.0, 2.0]), 0.1)
    assert rh[0] == pytest.approx(4.0) and sh[0] == pytest.approx(0.1 * 5 / 4)
    assert rh[1] == 0.0 and np.isnan(sh[1])


def test_stride_model_stands_during_a_pause() -> None:
    t = np.array([0, 500, 1000, 6000, 6500], np.int64) * 1_000_000  # a 5 s pause before step 3
    xy = np.array([[0, 0], [0.7, 0], [1.4, 0], [2.1, 0], [2.8, 0]], float)
    q = np.array([250, 3000, 5750], np.int64) * 1_000_000
    np.testing.assert_allclose(position_at(t, xy, q), [[0.35, 0], [1.4, 0], [1.75, 0]])
    k, f = stride_fraction(t, q)
    np.testing.assert_array_equal(k, [0, 2, 2])
    np.testing.assert_allclose(f, [0.5, 0.0, 0.5])


def test_ekf_equals_the_batch_linear_gaussian_solution() -> None:
    """Prediction (eq. 7, 12) + position updates (eq. 13) are linear-Gaussian: the filter's last
    state must equal the last state of the batch least-squares solution over all states."""
    cfg = UwbEkfConfig(q_position=0.003, q_velocity=0.2, sigma_trilateration_m=0.05)
    rng = np.random.default_rng(0)
    times = np.cumsum(rng.uniform(0.2, 1.5, 12))
    x0, P0 = np.array([1.0, 2.0, 0.3, -0.2]), np.diag([0.04, 0.04, 1.0, 1.0])
    z = np.array([[1.0 + 0.3 * t, 2.0 - 0.2 * t] for t in times]) + rng.normal(0, 0.05, (12, 2))
    s = TagState(0, x0, P0)
    for t, zk in zip(times, z):
        s = position_update(predict(s, int(t * 1e9), cfg), zk, cfg.sigma_trilateration_m)
    # batch: states x_0..x_n, prior on x_0, dynamics x_k = F x_{k-1} + w (Q), measurements on x_1..x_n
    n = len(times)
    dim = 4 * (n + 1)
    H_rows, rhs, W = [], [], []
    e = np.zeros((4, dim))
    e[:, :4] = np.eye(4)
    H_rows.append(e)
    rhs.append(x0)
    W.append(np.linalg.inv(P0))
    prev = 0.0
    for k, t in enumerate(times, start=1):
        F, Q = transition(t - prev), process_noise(t - prev, cfg)
        row = np.zeros((4, dim))
        row[:, 4 * k : 4 * k + 4] = np.eye(4)
        row[:, 4 * (k - 1) : 4 * k] = -F
        H_rows.append(row)
        rhs.append(np.zeros(4))
        W.append(np.linalg.inv(Q))
        m = np.zeros((2, dim))
        m[:, 4 * k : 4 * k + 2] = np.eye(2)
        H_rows.append(m)
        rhs.append(z[k - 1])
        W.append(np.eye(2) / cfg.sigma_trilateration_m**2)
        prev = t
    A = np.zeros((dim, dim))
    b = np.zeros(dim)
    for Hk, rk, Wk in zip(H_rows, rhs, W):
        A += Hk.T @ Wk @ Hk
        b += Hk.T @ Wk @ rk
    sol = np.linalg.solve(A, b)
    cov = np.linalg.inv(A)
    np.testing.assert_allclose(s.x, sol[-4:], atol=1e-9)
    np.testing.assert_allclose(s.P, cov[-4:, -4:], atol=1e-9)


def test_range_model_jacobian_matches_central_differences() -> None:
    x = np.array([2.0, -1.0, 0.5, 0.1])
    ref, dz = np.array([5.0, 3.0]), 1.2
    h, H = range_model(x, ref, dz)
    num = np.array([(range_model(x + d, ref, dz)[0] - range_model(x - d, ref, dz)[0]) / 2e-6 for d in np.eye(4) * 1e-6])
    np.testing.assert_allclose(H, num, atol=1e-8)
    assert h == pytest.approx(np.sqrt(3**2 + 4**2 + 1.2**2))


def test_range_update_bound_and_neighbour_noise() -> None:
    s = TagState(0, np.array([0.0, 0.0, 0, 0]), np.diag([1e-4, 1e-4, 1, 1]))
    kept, ok = range_update(s, np.array([3.0, 4.0]), 0.0, 5.05, 0.01, 0.5)
    assert ok and kept.P[0, 0] < s.P[0, 0]
    same, ok = range_update(s, np.array([3.0, 4.0]), 0.0, 6.0, 0.01, 0.5)  # 1 m residual: NLOS, rejected
    assert not ok and same is s
    # eq. 15: condition number of the neighbour's covariance scales sigma^2; + its variance along u
    Pj = np.diag([0.09, 0.01, 1, 1])
    assert condition_number(Pj[:2, :2]) == pytest.approx(9.0)
    cfg = UwbEkfConfig(sigma_range_m=0.1)
    assert neighbour_range_variance(Pj, np.array([1.0, 0.0]), cfg) == pytest.approx(9 * 0.01 + 0.09)
    assert neighbour_range_variance(Pj, np.array([0.0, 1.0]), UwbEkfConfig(sigma_range_m=0.1, neighbour_los_variance=False)) == pytest.approx(0.09)


def test_kalman_update_keeps_covariance_symmetric_positive() -> None:
    s = TagState(0, np.zeros(4), np.eye(4))
    H = np.array([[1.0, 0, 0, 0]])
    out = kalman_update(s, np.array([1.0]), H, np.array([[1e-6]]))
    assert np.allclose(out.P, out.P.T) and np.all(np.linalg.eigvalsh(out.P) > 0)


def _anchor_epoch(tag: str, t: float, p: np.ndarray, anchors: dict, ids: tuple[str, ...], rng: np.random.Generator,
                  peers: tuple = ()) -> UwbEpoch:
    r = np.array([np.sqrt(np.sum((np.asarray(anchors[a][:2]) - p) ** 2) + (anchors[a][2] - 1.0) ** 2) for a in ids])
    return UwbEpoch(tag, int(t * 1e9), ids, r + rng.normal(0, 0.05, len(ids)),
                    tuple(pid for pid, _ in peers), np.array([d for _, d in peers], float))


def test_track_tags_decision_flow_restart_and_neighbours() -> None:
    """Trilateration with >= 3 anchors; a lost filter restarts at a trilateration; a tag seeing one
    anchor plus a well-placed neighbour uses both (labelled anchor)."""
    rng = np.random.default_rng(3)
    anchors = {"A": (0.0, 0.0, 2.2), "B": (10.0, 0.0, 2.2), "C": (10.0, 8.0, 2.2), "D": (0.0, 8.0, 2.2)}
    epochs = []
    for k in range(40):  # T1 walks along y = 4 at 0.5 m/s, sees all four anchors
        t = 0.5 * k
        p1 = np.array([1.0 + 0.25 * t, 4.0])
        epochs.append(_anchor_epoch("T1", t, p1, anchors, ("A", "B", "C", "D"), rng))
        p2 = np.array([2.0, 2.0])  # T2 stands, sees anchor A only after its start, and ranges to T1
        ids = ("A", "B", "C") if k < 3 else ("A",)
        epochs.append(_anchor_epoch("T2", t + 0.01, p2, anchors, ids, rng, peers=(("T1", float(np.linalg.norm(p1 - p2))),)))
    # T1 jumps 5 m (a lost filter would reject it): a trilateration far outside the ellipse restarts it
    epochs.append(_anchor_epoch("T1", 20.5, np.array([9.0, 7.0]), anchors, ("A", "B", "C", "D"), rng))
    tr = track_tags(epochs, anchors)
    t1, t2 = tr["T1"], tr["T2"]
    assert (t1.kind == TRILATERATION).all() and t1.restarts == 1
    assert np.linalg.norm(t1.x[-1, :2] - [9.0, 7.0]) < 0.15
    assert (t2.kind[3:] == ANCHOR).all()  # one anchor + a neighbour: best input is the anchor range
    assert np.linalg.norm(t2.x[-1, :2] - [2.0, 2.0]) < 0.2
    # without the neighbour ranges T2's single anchor leaves it free to drift along the circle
    lone = track_tags([e if e.tag == "T1" else UwbEpoch(e.tag, e.t_ns, e.anchor_ids, e.anchor_ranges) for e in epochs], anchors)
    assert np.trace(lone["T2"].P[-1, :2, :2]) > np.trace(t2.P[-1, :2, :2])
    assert NEIGHBOUR not in t1.kind
