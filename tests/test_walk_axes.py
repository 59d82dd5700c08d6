"""Walk-axes prior (graphslam.core.tracking.axes): the residual's shape and derivative, the axes
found on walks, and what the prior does for a tracker whose heading the fixes leave wrong."""

from __future__ import annotations

import math

import numpy as np
import pytest

from graphslam.core.tracking.axes import WalkAxes, axis_statistics
from graphslam.core.tracking.fixed_lag import FixedLagConfig, fixed_lag_smooth
from graphslam.errors import EstimationError

from conftest import walk_epochs, walking_model


def _unit(deg: float) -> np.ndarray:
    return np.array([math.cos(math.radians(deg)), math.sin(math.radians(deg))])


def test_residual_vanishes_on_every_axis_is_odd_across_it_and_fades_at_standstill():
    ax = WalkAxes(math.radians(20.0), sigma_mps=0.2)
    on = np.array([1.2 * _unit(20.0 + 90.0 * k) for k in range(4)])
    np.testing.assert_allclose(ax.residual(on), 0.0, atol=1e-12)
    plus, minus = ax.residual(np.array([1.2 * _unit(26.0), 1.2 * _unit(14.0)]))
    assert plus > 0 and minus == pytest.approx(-plus)
    # near an axis it is the cross-axis velocity over sigma (times |u| / sqrt(|u|^2 + v0^2))
    assert plus == pytest.approx(1.2 * math.sin(math.radians(6.0)) / 0.2, rel=0.05)
    sweep = ax.residual(np.array([1.2 * _unit(20.0 + d) for d in range(0, 91)]))
    assert np.argmax(np.abs(sweep)) == 45  # largest half-way between axes, where no side pulls
    assert abs(ax.residual(np.array([0.01 * _unit(60.0)]))[0]) < 0.01 * abs(ax.residual(np.array([1.2 * _unit(60.0)]))[0])


def test_jacobian_matches_numerical_differentiation():
    rng = np.random.default_rng(2)
    ax = WalkAxes(-0.4, sigma_mps=0.3, v0_mps=0.25)
    v = np.vstack([rng.normal(0.0, 1.0, (20, 2)), [[0.0, 0.0], [1e-3, -2e-3]]])
    J = ax.jacobian(v)
    num = np.zeros_like(J)
    for i in range(2):
        e = np.zeros(2)
        e[i] = 1e-6
        num[:, i] = (ax.residual(v + e) - ax.residual(v - e)) / 2e-6
    np.testing.assert_allclose(J, num, rtol=1e-6, atol=1e-8)


def _grid_walks(angle_deg: float, rng: np.random.Generator, n_sessions: int = 6, scatter_deg: float = 5.0):
    """Walks of 3-m legs along a grid turned by ``angle_deg``, a position every 1.5 s."""
    xy, sid, t = [], [], []
    for s in range(n_sessions):
        p = rng.normal(0.0, 20.0, 2)
        for i in range(40):
            if i % 5 == 0:
                leg = angle_deg + 90.0 * rng.integers(0, 4) + rng.normal(0.0, scatter_deg)
            p = p + 3.0 * _unit(leg + rng.normal(0.0, scatter_deg))
            xy.append(p)
            sid.append(f"s{s}")
            t.append(int((1000 + 1.5 * i) * 1e9))
    return np.array(xy), np.array(sid), np.array(t, np.int64)


@pytest.mark.parametrize("angle", [25.0, -40.0, 0.0])
def test_the_axes_of_walks_on_a_turned_grid_are_found(angle):
    xy, sid, t = _grid_walks(angle, np.random.default_rng(int(angle) + 100))
    order = np.random.default_rng(0).permutation(len(t))  # the map's row order does not matter
    a, conc, used = axis_statistics(xy[order], sid[order], t[order])
    assert math.degrees(a) == pytest.approx(angle, abs=2.5)
    assert conc > 0.8 and used == 6 * 39  # no segment across two sessions
    ax = WalkAxes.from_walks(xy, sid, t, sigma_mps=0.3)
    assert ax is not None and ax.sigma_mps == 0.3 and ax.concentration == pytest.approx(conc)


def test_walks_with_no_preferred_direction_give_no_prior_and_gaps_break_segments():
    rng = np.random.default_rng(5)
    xy = np.cumsum(rng.normal(0.0, 2.0, (400, 2)), axis=0)
    sid, t = np.array(["a"] * 400), (np.arange(400) * 1.5e9).astype(np.int64)
    assert axis_statistics(xy, sid, t)[1] < 0.15
    assert WalkAxes.from_walks(xy, sid, t) is None
    t_gappy = t.copy()
    t_gappy[200:] += int(60e9)  # a minute's gap: the segment over it is no walk
    assert axis_statistics(xy, sid, t_gappy)[2] == axis_statistics(xy, sid, t)[2] - 1
    assert axis_statistics(xy[:1], sid[:1], t[:1]) is None
    # a few segments on a grid are concentrated, but too few to trust (a static-fingerprint map)
    gx, gs, gt = _grid_walks(10.0, np.random.default_rng(1), n_sessions=1)
    _, conc, used = axis_statistics(gx[:31], gs[:31], gt[:31])
    assert conc > 0.8 and used == 30
    assert WalkAxes.from_walks(gx[:31], gs[:31], gt[:31]) is None
    assert WalkAxes.from_walks(gx[:31], gs[:31], gt[:31], min_segments=30) is not None
    with pytest.raises(EstimationError, match="positions"):
        axis_statistics(xy, sid[:-1], t)
    with pytest.raises(EstimationError, match="sigma"):
        WalkAxes(0.0, sigma_mps=0.0)


def _l_walk(theta: float, rng: np.random.Generator):
    """An L-shaped walk on axes at 0 deg (map frame): 1.2 m/s along +x for 20 s, then along +y
    for 20 s, a step every 0.5 s; odometry turned by ``theta`` (eq. 4: y_v = M(theta) v);
    a noisy fix (std 4 m) every 2 s. Returns the epochs and the true positions."""
    t = np.arange(0.0, 40.0, 0.5)
    v = np.where((t < 20.0)[:, None], [1.2, 0.0], [0.0, 1.2])
    p = np.vstack([[0.0, 0.0], np.cumsum(v[:-1] * 0.5, axis=0)])
    return walk_epochs(t, v, p, theta, np.arange(4, len(t), 4), rng), p


def test_the_prior_corrects_a_heading_the_fixes_leave_wrong():
    # One start whose heading is 14 deg off: the sparse, noisy fixes hardly move it in 40 s; the
    # walker's legs along the axes do (both turned by the same odometry rotation).
    m = walking_model()
    theta = 0.7
    errs: dict[str, list[float]] = {"off": [], "on": []}
    for seed in range(4):
        e, p = _l_walk(theta, np.random.default_rng(seed))
        x0 = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, theta + 0.25])
        P0 = np.diag([1.0, 1.0, 1.0, 1.0, 0.0025, 0.0025, 0.3**2])
        cfg = FixedLagConfig(lag_s=2.0, window_s=20.0, huber_k=3.0, adaptive_rssi=False, report="best")
        for name, axes in (("off", None), ("on", WalkAxes(0.0, sigma_mps=0.25))):
            run = fixed_lag_smooth(m, [x0], P0, e, cfg, axes=axes)
            errs[name].append(abs(math.remainder(run.x[-1, 6] - theta, 2 * math.pi)))
            errs[name].append(float(np.linalg.norm(run.x[:, :2] - p, axis=1).mean()))
    th_off, th_on = np.mean(errs["off"][0::2]), np.mean(errs["on"][0::2])
    pos_off, pos_on = np.mean(errs["off"][1::2]), np.mean(errs["on"][1::2])
    assert th_on < 0.05 and th_on < 0.5 * th_off
    assert pos_on < 0.8 * pos_off


def test_track_config_measures_the_axes_on_the_map_and_validates_its_settings():
    from graphslam.core.tracking.tracker import walk_axes_of
    from graphslam.errors import ConfigError
    from graphslam.tracking_config import TrackConfig
    from graphslam.core.radiomap.radiomap import RadioMap

    xy, sid, t = _grid_walks(-12.0, np.random.default_rng(9))
    scans = [{"aa:bb:cc:dd:ee:0" + str(i % 3): -60.0 - i % 7} for i in range(len(t))]
    rm = RadioMap.from_scans(scans, xy, session_ids=list(sid), t_ns=list(t), frame="site")
    ax = walk_axes_of(TrackConfig(walk_axes={"sigma_mps": 0.4}), rm)
    assert ax is not None and math.degrees(ax.angle_rad) == pytest.approx(-12.0, abs=2.5) and ax.sigma_mps == 0.4
    assert walk_axes_of(TrackConfig(walk_axes={"enabled": False}), rm) is None
    assert walk_axes_of(TrackConfig(walk_axes={"min_concentration": 1.0}), rm) is None  # no real floor is that regular
    for bad in (dict(sigma_mps=0.0), dict(min_concentration=1.5), dict(min_concentration=-0.1)):
        with pytest.raises(ConfigError, match="walk_axes."):
            TrackConfig(walk_axes=bad)
