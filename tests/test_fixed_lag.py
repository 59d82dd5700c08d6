"""Fixed-lag smoother (graphslam.core.tracking.fixed_lag): known answers on linear-Gaussian runs.

With theta fixed, velocity readings and position fixes only, the model is linear-Gaussian, so
every estimate has a closed form computed by unrelated code: the Kalman filter (``run_epochs``)
and the RTS pass over the readings known at the report time.
"""

from __future__ import annotations

import numpy as np
import pytest

from graphslam.core.tracking.filters import Epochs, ExtendedKalmanFilter, FusionModel, run_epochs
from graphslam.core.tracking.fixed_lag import FixedLagConfig, fixed_lag_smooth, mixture_moments
from graphslam.core.tracking.smoother import MapProblem, map_smooth, rts_smooth
from graphslam.errors import EstimationError

X0 = np.array([1.0, 2.0, 0.1, -0.2, 0.0, 0.0])
P0 = np.diag([0.5, 0.5, 0.2, 0.2, 0.01, 0.01])
TIGHT = dict(huber_k=None, rel_tol=1e-20, stall_tol=None, max_iter=30, prune_cost=None, adaptive_rssi=False, report="best")  # exact solves, Gaussian loss


def _model() -> FusionModel:
    base = FusionModel.paper_ekf()
    return FusionModel(base.path_loss, base.q_diag * 1e3, np.full(2, 0.01), base.r_rssi, theta_rad=0.1)


def _epochs(seed: int = 4, n: int = 30) -> Epochs:
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.3, 2.0, n))
    vel_k = np.sort(rng.choice(n, size=n - 6, replace=False))  # some epochs hold no velocity
    fix_k = np.sort(rng.integers(0, n, 8))
    none = np.zeros(0, np.int64)
    return Epochs(
        t, vel_k, rng.normal(0.0, 0.3, (len(vel_k), 2)), none, none, np.zeros(0),
        fix_k, rng.normal(3.0, 2.0, (len(fix_k), 2)), rng.uniform(0.5, 3.0, len(fix_k)),
    )


def _known_at(e: Epochs, j: int, vel_avail: np.ndarray | None = None, now: float | None = None) -> Epochs:
    """The readings of epochs < j (velocity: also available by ``now``)."""
    v = e.vel_k < j
    if vel_avail is not None:
        v &= vel_avail <= now + 1e-12
    f = e.fix_k < j
    none = np.zeros(0, np.int64)
    return Epochs(e.t_s[:j], e.vel_k[v], e.vel_y[v], none, none, np.zeros(0), e.fix_k[f], e.fix_xy[f], e.fix_sigma[f])


def test_lag_zero_window_zero_is_the_kalman_filter():
    # Marginalising every epoch but the newest leaves the filter's recursion: same mean and covariance.
    m, e = _model(), _epochs()
    kf = run_epochs(ExtendedKalmanFilter(m), X0, P0, e)
    fl = fixed_lag_smooth(m, [X0], P0, e, FixedLagConfig(lag_s=0.0, window_s=0.0, **TIGHT))
    np.testing.assert_allclose(fl.x, kf.x, atol=1e-8)
    np.testing.assert_allclose(fl.P, kf.P, atol=1e-9)
    np.testing.assert_allclose(fl.reported_at_s, e.t_s)  # each epoch reported at its own time


def test_infinite_lag_is_the_whole_run_map():
    m, e = _model(), _epochs()
    kf = run_epochs(ExtendedKalmanFilter(m), X0, P0, e)
    rts = rts_smooth(m, kf, e)
    whole = map_smooth(MapProblem(m, X0, P0, e), [kf.x])
    fl = fixed_lag_smooth(m, [X0], P0, e, FixedLagConfig(lag_s=1e9, window_s=1e9, **TIGHT))
    np.testing.assert_allclose(fl.x, rts.x, atol=1e-6)
    np.testing.assert_allclose(fl.x, whole.x, atol=1e-4)  # whole-run LM stops at 1e-8 relative
    np.testing.assert_allclose(fl.P, rts.P, rtol=1e-6, atol=1e-10)
    assert (fl.reported_at_s == e.t_s[-1]).all()


@pytest.mark.parametrize("window_s", [3.0, 8.0])
def test_a_lag_reports_the_smoothed_state_given_the_data_up_to_that_lag(window_s):
    # Epoch k is reported after the last epoch at or before t_k + lag: its estimate must be the
    # RTS-smoothed state of k over exactly the readings known then, whatever the window (>= lag)
    # since marginalisation is exact here.
    m, e, lag = _model(), _epochs(), 3.0
    fl = fixed_lag_smooth(m, [X0], P0, e, FixedLagConfig(lag_s=lag, window_s=window_s, **TIGHT))
    for k in range(len(e)):
        j = int(np.searchsorted(e.t_s, e.t_s[k] + lag, side="right"))
        sub = _known_at(e, j)
        ref = rts_smooth(m, run_epochs(ExtendedKalmanFilter(m), X0, P0, sub), sub)
        np.testing.assert_allclose(fl.x[k], ref.x[k], atol=1e-6)
        np.testing.assert_allclose(fl.P[k], ref.P[k], rtol=1e-6, atol=1e-10)
        assert fl.reported_at_s[k] == (e.t_s[j - 1] if j < len(e) else e.t_s[-1])


def test_late_velocity_readings_are_used_only_once_available():
    # A step's velocity known only at the next epoch (a walker's step interval): at lag 0 epoch k
    # is estimated without the velocity reading of its own epoch.
    m, e = _model(), _epochs()
    avail = e.t_s[np.minimum(e.vel_k + 1, len(e) - 1)]
    fl = fixed_lag_smooth(m, [X0], P0, e, FixedLagConfig(lag_s=0.0, window_s=5.0, **TIGHT), vel_available_s=avail)
    for k in (5, 17, len(e) - 2):
        sub = _known_at(e, k + 1, avail, e.t_s[k])
        ref = run_epochs(ExtendedKalmanFilter(m), X0, P0, sub)
        np.testing.assert_allclose(fl.x[k], ref.x[k], atol=1e-6)
    with pytest.raises(EstimationError, match="availability"):
        fixed_lag_smooth(m, [X0], P0, e, FixedLagConfig(), vel_available_s=avail - 1.0)


def test_the_bank_reports_the_start_that_explains_the_fixes():
    # Two starts 20 m apart with a tight prior: fixes near the second make the first's cost
    # grow; it is pruned, and every report after the first few fixes comes from the second.
    m, e = _model(), _epochs()
    far = X0 + np.r_[20.0, 0, 0, 0, 0, 0]
    tight = np.diag([0.01, 0.01, 0.2, 0.2, 0.01, 0.01])
    fl = fixed_lag_smooth(m, [far, X0], tight, e, FixedLagConfig(lag_s=0.0, window_s=5.0, huber_k=None, prune_cost=30.0, adaptive_rssi=False, report="best"))
    assert np.isinf(fl.cost[0]) and np.isfinite(fl.cost[1])
    assert (fl.hypothesis[e.fix_k[2]:] == 1).all()


def test_mixture_moments_match_the_raw_moment_formula_and_wrap_the_angle():
    rng = np.random.default_rng(3)
    X = rng.normal(0.0, 2.0, (3, 3))
    Ps = [(lambda A: A @ A.T + np.eye(3))(rng.normal(size=(3, 3))) for _ in range(3)]
    costs = np.array([4.0, 3.0, 6.5])
    w = np.exp(-costs / 2) / np.exp(-costs / 2).sum()
    mean = w @ X  # E[x] and E[x x^T] - E[x] E[x]^T, computed differently from the code
    cov = sum(wi * (P + np.outer(x, x)) for wi, x, P in zip(w, X, Ps)) - np.outer(mean, mean)
    for ref in range(3):  # the reference hypothesis changes nothing without an angle
        m, P = mixture_moments(list(zip(X, Ps)), costs, ref)
        np.testing.assert_allclose(m, mean, atol=1e-12)
        np.testing.assert_allclose(P, cov, atol=1e-12)
    # far more likely one: its own estimate; equal odds at theta = +-(pi - 0.1): pi, not 0
    m, P = mixture_moments(list(zip(X, Ps)), np.array([0.0, 200.0, 300.0]), 0)
    np.testing.assert_allclose(m, X[0], atol=1e-12)
    np.testing.assert_allclose(P, Ps[0], atol=1e-12)
    a = np.array([0.0, 0.0, np.pi - 0.1])
    b = np.array([2.0, 0.0, -np.pi + 0.1])
    m, P = mixture_moments([(a, np.eye(3)), (b, np.eye(3))], np.zeros(2), 0, angle_index=2)
    np.testing.assert_allclose(m[:2], [1.0, 0.0], atol=1e-12)
    assert -np.pi <= m[2] < np.pi and abs(abs(m[2]) - np.pi) < 1e-12
    np.testing.assert_allclose(np.diag(P), [2.0, 1.0, 1.01], atol=1e-12)
    # the mean across the cut: pi - 0.1 and -pi + 0.3 average to -pi + 0.1, inside [-pi, pi)
    c = np.array([0.0, 0.0, -np.pi + 0.3])
    for ref in (0, 1):
        m, _ = mixture_moments([(a, np.eye(3)), (c, np.eye(3))], np.zeros(2), ref, angle_index=2)
        assert abs(m[2] - (-np.pi + 0.1)) < 1e-12


def test_the_mixture_report_spreads_over_undecided_starts_and_follows_a_decided_bank():
    m, e = _model(), _epochs()
    tight = np.diag([0.01, 0.01, 0.2, 0.2, 0.01, 0.01])
    cfg = dict(lag_s=0.0, window_s=5.0, huber_k=None, adaptive_rssi=False)
    # two identical starts: the mixture is the single run
    one = fixed_lag_smooth(m, [X0], tight, e, FixedLagConfig(**cfg, report="best"))
    two = fixed_lag_smooth(m, [X0, X0], tight, e, FixedLagConfig(**cfg, report="mixture"))
    np.testing.assert_allclose(two.x, one.x, atol=1e-9)
    np.testing.assert_allclose(two.P, one.P, atol=1e-9)
    # 20 m apart: at the first epoch (no fix yet) the report sits between the two with their
    # spread in its covariance; once the fixes decide, it is the best start's estimate
    far = X0 + np.r_[20.0, 0, 0, 0, 0, 0]
    best = fixed_lag_smooth(m, [far, X0], tight, e, FixedLagConfig(**cfg, prune_cost=30.0, report="best"))
    mix = fixed_lag_smooth(m, [far, X0], tight, e, FixedLagConfig(**cfg, prune_cost=30.0, report="mixture"))
    assert abs(mix.x[0, 0] - (X0[0] + 10.0)) < 1e-6 and mix.P[0, 0, 0] > 99.0
    assert best.P[0, 0, 0] < 0.1
    after = slice(e.fix_k[2], None)
    np.testing.assert_allclose(mix.x[after], best.x[after], atol=1e-9)
    np.testing.assert_allclose(mix.P[after], best.P[after], atol=1e-9)
    with pytest.raises(EstimationError, match="report"):
        FixedLagConfig(report="mean")


def test_a_tempered_bank_weighs_its_starts_as_if_the_costs_were_divided():
    # temper T: the mixture's weights exp(-cost / 2T) and pruning at T x prune_cost. A cost gap of
    # 2 T ln 3 makes the odds 3 : 1, whatever T; the tempered bank keeps a start the plain one prunes.
    m, e = _model(), _epochs()
    tight = np.diag([0.01, 0.01, 0.2, 0.2, 0.01, 0.01])
    far = X0 + np.r_[20.0, 0, 0, 0, 0, 0]
    cfg = dict(lag_s=0.0, window_s=5.0, huber_k=None, report="mixture", adaptive_rssi=False)
    plain = fixed_lag_smooth(m, [far, X0], tight, e, FixedLagConfig(**cfg, prune_cost=30.0))
    temp = fixed_lag_smooth(m, [far, X0], tight, e, FixedLagConfig(**cfg, prune_cost=30.0, temper=1e4))
    assert np.isinf(plain.cost[0]) and np.isfinite(temp.cost).all()
    k = len(e) - 1  # the last report: the plain bank's one start, the tempered bank's even mixture of both
    assert abs(plain.x[k, 0] - temp.x[k, 0]) > 1.0
    same = fixed_lag_smooth(m, [far, X0], tight, e, FixedLagConfig(**cfg, prune_cost=30.0, temper=1.0))
    np.testing.assert_array_equal(same.x, plain.x)  # temper 1: the bank's own costs
    for bad in (0.5, float("inf")):
        with pytest.raises(EstimationError, match="temper"):
            FixedLagConfig(temper=bad)
    costs = temp.cost
    w = np.exp(-0.5 * (costs - costs.min()) / 1e4)
    w /= w.sum()
    assert 0.4 < w[0] < 0.6  # nearly even odds after tempering


def test_hypotheses_that_became_one_are_merged_with_their_posterior_mass():
    # Two starts that are the same hypothesis and a third 20 m away, with a temper that keeps all
    # three weighted (undecided): merged, the pair is one live hypothesis whose cost carries the
    # other's mass (c - 2 T ln 2), so the mixture and its odds against the far start are the
    # unmerged bank's; without merging both copies stay alive to the end.
    m, e = _model(), _epochs()
    tight = np.diag([0.01, 0.01, 0.2, 0.2, 0.01, 0.01])
    far = X0 + np.r_[20.0, 0, 0, 0, 0, 0]
    cfg = dict(lag_s=0.0, window_s=5.0, huber_k=None, report="mixture", adaptive_rssi=False, prune_cost=None, temper=1e4)
    kept = fixed_lag_smooth(m, [X0, X0, far], tight, e, FixedLagConfig(**cfg, merge_tol=None))
    merged = fixed_lag_smooth(m, [X0, X0, far], tight, e, FixedLagConfig(**cfg, merge_tol=1e-9))
    assert np.isfinite(kept.cost).all()
    assert np.isinf(merged.cost[1]) and np.isfinite(merged.cost[[0, 2]]).all()
    assert merged.cost[0] == pytest.approx(kept.cost[0] - 2e4 * np.log(2.0), rel=1e-12)
    np.testing.assert_allclose(merged.x, kept.x, atol=1e-8)
    np.testing.assert_allclose(merged.P, kept.P, atol=1e-8)
    # starts 20 m apart never agree: nothing merged, the same run as without merging
    apart = fixed_lag_smooth(m, [X0, far], tight, e, FixedLagConfig(**cfg, merge_tol=0.05))
    np.testing.assert_array_equal(apart.x, fixed_lag_smooth(m, [X0, far], tight, e, FixedLagConfig(**cfg, merge_tol=None)).x)
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(EstimationError, match="merge_tol"):
            FixedLagConfig(merge_tol=bad)


def test_config_rejects_a_window_shorter_than_the_lag():
    with pytest.raises(EstimationError, match="lag"):
        FixedLagConfig(lag_s=3.0, window_s=1.0)


@pytest.mark.parametrize("field, bad", [("rel_tol", -1e-5), ("rel_tol", float("nan")), ("stall_tol", -1.0),
                                        ("stall_tol", float("inf"))])
def test_config_rejects_bad_lm_tolerances(field: str, bad: float):
    with pytest.raises(EstimationError, match=field):
        FixedLagConfig(**{field: bad})
    FixedLagConfig(stall_tol=None)  # None: a failed step is retried damped, as the reference LM does


def test_normal_equations_and_one_epoch_marginal_match_the_sparse_algebra():
    # The fixed-lag path assembles J^T W J without a sparse matrix and takes one epoch's marginal
    # by a banded solve: both must equal the plain sparse products (robust weights on, RSSI rows in).
    base = FusionModel.paper_ekf()
    m = FusionModel(base.path_loss, base.q_diag * 1e3, np.full(2, 0.01), base.r_rssi, theta_rad=0.1)
    rng = np.random.default_rng(7)
    e0 = _epochs()
    rss_k = np.repeat(np.arange(0, len(e0), 3), 2)
    e = Epochs(
        e0.t_s, e0.vel_k, e0.vel_y, rss_k, rng.integers(0, 4, len(rss_k)), rng.normal(-60.0, 8.0, len(rss_k)),
        e0.fix_k, e0.fix_xy, e0.fix_sigma, rng.uniform(1.0, 2.0, len(rss_k)),
    )
    p = MapProblem(m, X0, P0, e, huber_k=1.0)
    X = X0 + rng.normal(0.0, 0.5, (len(e), len(X0)))
    r = p.residual(X.ravel())
    assert (p.weights(r) < 1.0).any()  # some rows are down-weighted: the test covers IRLS
    band, g = p.normal_equations(X, r)
    sw = p.weights(r)
    import scipy.sparse as sp

    J = sp.diags(sw) @ p.jacobian(X)
    np.testing.assert_allclose(band, p.banded(J.T @ J), rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(g, J.T @ (sw * r), rtol=1e-10, atol=1e-10)
    full = p.marginals(X)
    for k in (0, 11, len(e) - 1):
        np.testing.assert_allclose(p.marginal(X, k), full[k], rtol=1e-8, atol=1e-12)
