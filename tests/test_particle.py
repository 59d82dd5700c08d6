"""The map-matching particle filter (core/tracking/particle.py) on synthetic walks."""

from __future__ import annotations

import math

import numpy as np
import pytest

from graphslam.core.tracking.particle import ParticleConfig, log_likelihood, run_particle_filter, scan_matches
from graphslam.errors import EstimationError


def test_scan_matches_are_the_nearest_first_and_padded() -> None:
    d = np.array([[5.0, 1.0, np.inf, 3.0], [np.inf, np.inf, np.inf, 2.0]])
    idx, dist = scan_matches(d, 3)
    np.testing.assert_array_equal(idx, [[1, 3, 0], [3, -1, -1]])
    np.testing.assert_array_equal(dist[0], [1.0, 3.0, 5.0])
    assert np.isinf(dist[1, 1:]).all()
    idx, _ = scan_matches(d, 10)  # k beyond the map: every row, sorted
    assert idx.shape == (2, 4) and idx[0, 0] == 1


def test_the_likelihood_peaks_at_the_best_match() -> None:
    cfg = ParticleConfig(kernel_m=1.0, temperature=1.0, area_m2=2500.0)
    centres = np.array([[0.0, 0.0], [10.0, 0.0]])
    w = np.array([0.8, 0.2])
    ll = log_likelihood(np.array([[0.0, 0.0], [10.0, 0.0], [5.0, 0.0], [50.0, 50.0]]), centres, w, cfg)
    assert ll[0] > ll[1] > ll[2] and ll[2] >= ll[3]
    assert np.isfinite(ll).all()  # the floor: far away is unlikely, not impossible


def _walk(rng: np.random.Generator, rot: float):
    """An L-shaped walk (map frame), its odometry turned by ``rot``, and scans every 2 s whose
    matches are the truth (+ 1 m noise) and, for the first 4 scans, an equally good decoy 15 m away."""
    t = np.arange(0.0, 60.0, 0.5)
    path = np.where(t[:, None] < 30, np.column_stack([t, 0 * t]), np.column_stack([30 + 0 * t, t - 30]))
    c, s = math.cos(rot), math.sin(rot)
    odo = path @ np.array([[c, -s], [s, c]])  # module frame = map frame turned by -rot
    scan_t = np.arange(1.0, 59.0, 2.0)
    truth = np.array([np.interp(scan_t, t, path[:, i]) for i in range(2)]).T
    mx = np.stack([truth + rng.normal(scale=1.0, size=truth.shape), truth + [0.0, 15.0]], axis=1)
    md = np.column_stack([np.full(len(scan_t), 3.0), np.where(np.arange(len(scan_t)) < 4, 3.0, np.inf)])
    return t, path, odo, scan_t, mx, md


def test_the_walk_resolves_an_ambiguous_start_and_an_unknown_heading() -> None:
    rng = np.random.default_rng(0)
    t, path, odo, scan_t, mx, md = _walk(rng, rot=1.0)
    run = run_particle_filter(t, odo, np.ones(len(t) - 1, bool), scan_t, mx, md, ParticleConfig(lag_s=0.0, seed=1))
    err = np.linalg.norm(run.xy - path, axis=1)
    assert err[t > 20].mean() < 1.5  # on the route once the turn and the scans have spoken
    # the module-to-map rotation found: module frame turned by -1 rad
    assert abs(math.remainder(run.phi[-1] - 1.0, 2 * math.pi)) < 0.15
    assert run.cov.shape == (len(t), 2, 2) and (np.linalg.eigvalsh(run.cov) >= -1e-12).all()


def test_a_lag_uses_later_scans_for_earlier_steps() -> None:
    rng = np.random.default_rng(1)
    t, path, odo, scan_t, mx, md = _walk(rng, rot=-2.0)
    errs = []
    for lag in (0.0, 6.0):
        run = run_particle_filter(t, odo, np.ones(len(t) - 1, bool), scan_t, mx, md, ParticleConfig(lag_s=lag, seed=2))
        errs.append(np.linalg.norm(run.xy - path, axis=1)[t < 12].mean())
    assert errs[1] < 0.8 * errs[0]


def test_no_matching_scan_is_an_error() -> None:
    t = np.arange(5.0)
    with pytest.raises(EstimationError, match="no scan"):
        run_particle_filter(t, np.zeros((5, 2)), np.ones(4, bool), np.array([1.0]), np.zeros((1, 2, 2)),
                            np.full((1, 2), np.inf))
    with pytest.raises(EstimationError):
        ParticleConfig(n_particles=1)


def test_rssi_readings_weigh_positions_by_the_path_loss_models_with_a_huber_tail() -> None:
    from graphslam.core.tracking.filters import PathLossModel
    from graphslam.core.tracking.particle import RssiReadings

    pl = PathLossModel(np.array([[0.0, 0.0], [20.0, 0.0], [0.0, 20.0]]), np.full(3, -30.0), np.full(3, 2.5))
    truth = np.array([[6.0, 4.0]])
    rss = pl.mean_rss(truth)[0]
    r = RssiReadings(pl, np.full(3, 4.0), [np.arange(3)], [rss])
    grid = np.array([[6.0, 4.0], [8.0, 4.0], [15.0, 15.0]])
    ll = r.log_likelihood(grid, 0, huber_k=3.0)
    assert ll[0] == pytest.approx(0.0) and ll[0] > ll[1] > ll[2]
    # one reading 40 dB off costs k |z| - k^2 / 2 (linear), not z^2 / 2
    off = RssiReadings(pl, np.full(3, 4.0), [np.arange(1)], [rss[:1] + 40.0])
    assert off.log_likelihood(truth, 0, huber_k=3.0)[0] == pytest.approx(-(3.0 * 10.0 - 4.5))


def test_the_start_is_the_earliest_matching_scan_whatever_the_order() -> None:
    rng = np.random.default_rng(4)
    t, path, odo, scan_t, mx, md = _walk(rng, rot=0.5)
    perm = rng.permutation(len(scan_t))
    a = run_particle_filter(t, odo, np.ones(len(t) - 1, bool), scan_t, mx, md, ParticleConfig(lag_s=0.0, seed=3))
    b = run_particle_filter(t, odo, np.ones(len(t) - 1, bool), scan_t[perm], mx[perm], md[perm],
                            ParticleConfig(lag_s=0.0, seed=3))
    np.testing.assert_allclose(b.xy, a.xy)


def test_track_config_checks_the_particle_settings_up_front() -> None:
    from graphslam.core.tracking.tracker import particle_config
    from graphslam.errors import ConfigError
    from graphslam.tracking_config import TrackConfig

    for bad in (dict(count=1), dict(outlier=1.5), dict(kernel_m=0.0), dict(top_k=0)):
        with pytest.raises(ConfigError, match="particle."):
            TrackConfig(filter={"kind": "particle"}, particle=bad)
    cfg = particle_config(TrackConfig(filter={"kind": "particle"}, particle={"seed": 5}), area_m2=20.0, seed=3)
    assert cfg.seed == 5 ^ 3 and cfg.area_m2 == 20.0 and cfg.kernel_m == 4.0 and cfg.lag_s == 2.0
