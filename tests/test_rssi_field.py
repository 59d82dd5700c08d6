"""The AP models' residual field (graphslam.core.tracking.rssi_field) and its use by the trackers."""

from __future__ import annotations

import numpy as np
import pytest

from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.core.tracking.apmodel import residual_field
from graphslam.core.tracking.filters import FilterError, PathLossModel
from graphslam.core.tracking.rssi_field import ResidualField, fit_residual_field
from graphslam.errors import EstimationError

APS = np.array([[0.0, 0.0], [30.0, 0.0]])
P0, GAMMA = np.array([-35.0, -40.0]), np.array([2.5, 2.0])
LAW = PathLossModel(APS, P0, GAMMA, 1.0, ("a", "b"))


def _wall(xy: np.ndarray) -> np.ndarray:
    """A wall's shadow: AP a's readings 8 dB weaker beyond x = 15 m (what the law cannot say)."""
    return np.where(xy[..., 0] > 15.0, -8.0, 0.0)


def test_bilinear_field_is_exact_at_cell_centres_linear_between_and_zero_off_its_grid():
    # AP 0: a 3 x 2 grid (ny = 2, nx = 3) of 2-m cells from (10, 20); AP 1: no grid
    vals = np.array([0.0, 2.0, 4.0, 1.0, 3.0, 5.0], np.float32)
    f = ResidualField(2.0, np.array([[10.0, 20.0], [0.0, 0.0]]), np.array([[2, 3], [0, 0]]), np.array([0, 6]), vals)
    xy = np.array([[10.0, 20.0], [14.0, 22.0], [11.0, 20.0], [12.0, 21.0], [9.9, 20.0], [16.5, 21.0], [12.0, 21.0]])
    out = f.at(xy, np.array([0, 0, 0, 0, 0, 0, 1]))
    np.testing.assert_allclose(out, [0.0, 5.0, 1.0, 2.5, 0.0, 0.0, 0.0])


def test_field_rejects_grids_that_run_past_their_values():
    with pytest.raises(EstimationError, match="past the stored values"):
        ResidualField(1.0, np.zeros((1, 2)), np.array([[3, 3]]), np.array([0]), np.zeros(8, np.float32))


def test_fit_recovers_a_wall_and_returns_to_the_law_far_from_the_readings():
    rng = np.random.default_rng(0)
    xy = rng.uniform([0, -10], [30, 10], (3000, 2))
    r = _wall(xy) + rng.normal(0, 1.0, len(xy))
    fit = fit_residual_field(xy, r, np.zeros(len(xy), np.int64), rng.integers(0, 10, len(xy)), 1, bandwidth_m=2.0)
    c = fit.field.at(np.array([[5.0, 0.0], [25.0, 0.0], [90.0, 90.0]]), np.zeros(3, np.int64))
    assert abs(c[0]) < 0.5 and abs(c[1] + 8.0) < 0.8 and c[2] == 0.0
    # the walls' readings, each walk left out, scatter about the noise around the field; around the law by the wall
    assert fit.sigma_db[0] < 1.5 and fit.sigma_law_db[0] > 3.0


def test_shrink_pulls_a_lone_reading_towards_the_law():
    # one reading of residual 10 dB: at its place the kernel sums to 1, so the correction is 10 / (1 + shrink)
    for shrink in (0.5, 2.0):
        fit = fit_residual_field(np.array([[5.0, 5.0]]), np.array([10.0]), np.array([0]), np.array([0]), 1,
                                 bandwidth_m=3.0, shrink=shrink, leave_out=False)
        assert fit.field.at(np.array([[5.0, 5.0]]), np.array([0]))[0] == pytest.approx(10.0 / (1.0 + shrink), rel=0.05)
        assert np.isnan(fit.sigma_db[0])


def test_noise_alone_is_not_mistaken_for_a_field():
    rng = np.random.default_rng(1)
    xy = rng.uniform(0, 30, (2000, 2))
    r = rng.normal(0, 4.0, len(xy))
    fit = fit_residual_field(xy, r, np.zeros(len(xy), np.int64), np.arange(len(xy)) % 8, 1, bandwidth_m=3.0)
    assert fit.sigma_db[0] >= 0.97 * fit.sigma_law_db[0]  # left-out readings gain nothing from a field of noise


@pytest.mark.parametrize("bad", [{"bandwidth_m": 0.0}, {"shrink": 0.0}, {"bandwidth_m": 0.5, "cell_m": 1.0}])
def test_fit_rejects_bad_settings(bad):
    with pytest.raises(EstimationError, match="RSSI field"):
        fit_residual_field(np.zeros((1, 2)), np.zeros(1), np.zeros(1, np.int64), np.zeros(1), 1, **bad)


def _wall_map(rng: np.random.Generator, n: int = 2000) -> RadioMap:
    xy = rng.uniform([0, -10], [30, 10], (n, 2))
    h = LAW.mean_rss(xy)  # (n, 2)
    h[:, 0] += _wall(xy)
    y = h + rng.normal(0, 1.0, h.shape)
    scans = [{"a": float(a), "b": float(b)} for a, b in y]
    return RadioMap.from_scans(scans, xy, session_ids=[f"w{i % 12}" for i in range(n)], t_ns=np.arange(n), frame="site")


def test_corrected_law_predicts_new_readings_and_keeps_the_laws_gradient():
    rng = np.random.default_rng(2)
    rm = _wall_map(rng)
    fit = residual_field(rm, LAW, bandwidth_m=2.0)
    pl = PathLossModel(APS, P0, GAMMA, 1.0, ("a", "b"), correction=fit.field)
    q = rng.uniform([1, -8], [29, 8], (400, 2))
    truth = LAW.mean_rss(q)
    truth[:, 0] += _wall(q)
    err_law, err_field = np.abs(LAW.mean_rss(q) - truth), np.abs(pl.mean_rss(q) - truth)
    keep = np.abs(q[:, 0] - 15.0) > 3.0  # away from the wall's edge, which a 2-m kernel blurs
    assert err_field[keep].mean() < 0.6 and err_law[keep, 0].mean() > 3.0  # the law: 8 dB off beyond the wall
    # rss_pairs agrees with mean_rss; its gradient and jacobian are the law's (the field's is noise)
    idx = rng.integers(0, 2, len(q))
    h, g = pl.rss_pairs(q, idx)
    np.testing.assert_allclose(h, pl.mean_rss(q)[np.arange(len(q)), idx])
    np.testing.assert_allclose(g, LAW.rss_pairs(q, idx)[1])
    np.testing.assert_allclose(pl.jacobian(q[0]), LAW.jacobian(q[0]))
    # only the APs asked for are corrected
    only_b = residual_field(rm, LAW, bandwidth_m=2.0, aps=np.array([1]), leave_out=False).field
    assert only_b.shape[0].tolist() == [0, 0] and np.abs(only_b.at(q, np.zeros(len(q), np.int64))).max() == 0.0


def test_path_loss_model_refuses_a_field_for_other_aps():
    with pytest.raises(FilterError, match="residual field"):
        PathLossModel(APS, P0, GAMMA, 1.0, correction=ResidualField(1.0, np.zeros((1, 2)), np.zeros((1, 2), np.int64),
                                                                    np.zeros(1, np.int64), np.zeros(0, np.float32)))


def test_trackers_take_the_field_from_their_map_unless_told_not_to():
    from graphslam.core.tracking.tracker import Tracker, fusion_model, with_residual_field
    from graphslam.core.tracking.apmodel import ApModels
    from graphslam.errors import ConfigError
    from graphslam.tracking_config import TrackConfig

    rm = _wall_map(np.random.default_rng(3))
    models = ApModels.fit(rm)
    base = fusion_model(models, TrackConfig())
    assert base.path_loss.correction is None
    on = with_residual_field(base, rm, TrackConfig())
    assert on.path_loss.correction is not None and on.path_loss.correction.cells > 0
    np.testing.assert_array_equal(on.r_rssi, base.r_rssi)  # the noise stays the law's
    assert with_residual_field(base, rm, TrackConfig(rssi={"field_m": 0.0})) is base
    with pytest.raises(ConfigError, match="field_m must be 0"):
        TrackConfig(rssi={"field_m": 0.5})
    quick = {"calibration": {"enabled": False}}
    assert Tracker.on_map(rm, models, TrackConfig(**quick)).model.path_loss.correction is not None
    assert Tracker.on_map(rm, models, TrackConfig(rssi={"enabled": False}, **quick)).model.path_loss.correction is None
    assert Tracker.on_map(rm, models, TrackConfig(rssi={"field_m": 0.0}, **quick)).model.path_loss.correction is None
