"""Noise levels measured on the radio map, and the calibration figures (graphslam.core.tracking.calibration)."""

from __future__ import annotations


import numpy as np
import pytest

from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.core.tracking.apmodel import ApModel, ApModels
from graphslam.core.tracking.calibration import (
    CHI2_2DOF_95, bank_temper, ellipse_coverage, fix_error_correlation, fix_noise, leave_one_session_out_error_vectors,
    leave_one_session_out_errors, mahalanobis_sq, rssi_variance_factor,
)

APS = np.array([[0.0, 0.0], [30.0, 0.0], [0.0, 30.0], [30.0, 30.0], [15.0, -5.0], [-5.0, 15.0]])
P0, GAMMA = -35.0, 2.5


def _rss(xy: np.ndarray) -> np.ndarray:
    d2 = ((xy[:, None, :] - APS[None]) ** 2).sum(2) + 1.0
    return P0 - 5.0 * GAMMA * np.log10(d2)


def _models(bssids: list[str], aps: np.ndarray) -> ApModels:
    fitted = tuple(ApModel(b, float(x), float(y), P0, GAMMA, 4.0, 100, tuple(tuple(0.0 for _ in range(4)) for _ in range(4)))
                   for b, (x, y) in zip(bssids, aps))
    return ApModels("site", 1.0, fitted, ())


def test_mahalanobis_and_coverage_of_gaussian_errors():
    C = np.array([[4.0, 1.5], [1.5, 2.0]])
    e = np.array([[1.0, -2.0]])
    assert mahalanobis_sq(e, C[None])[0] == pytest.approx(float(e[0] @ np.linalg.solve(C, e[0])))
    rng = np.random.default_rng(0)
    errs = rng.multivariate_normal([0, 0], C, 40_000)
    inside = ellipse_coverage(errs, np.broadcast_to(C, (len(errs), 2, 2))).mean()
    assert inside == pytest.approx(0.95, abs=0.005)
    assert ellipse_coverage(errs, np.broadcast_to(C / 4, (len(errs), 2, 2))).mean() < 0.6  # over-confident: misses
    # a singular covariance holds only a zero error
    np.testing.assert_array_equal(ellipse_coverage(np.array([[0.0, 0.0], [0.1, 0.0]]), np.zeros((2, 2, 2))), [True, False])
    assert CHI2_2DOF_95 == pytest.approx(5.991, abs=1e-3)


def test_leave_one_session_out_errors_measure_the_gap_to_the_other_sessions():
    # Two sessions with identical fingerprints, one laid 1.5 m east of the other: every
    # fingerprint's nearest fingerprints of the other session are 1.5 m away.
    rng = np.random.default_rng(1)
    xy = np.column_stack([np.linspace(0, 30, 40), np.full(40, 10.0)])
    rss = _rss(xy) + rng.normal(0, 0.5, (40, len(APS)))
    scans = [{f"ap{j}": float(r[j]) for j in range(len(APS))} for r in rss]
    rm = RadioMap.from_scans(
        scans + scans, np.vstack([xy, xy + [1.5, 0.0]]), session_ids=["a"] * 40 + ["b"] * 40,
        t_ns=list(range(80)), frame="site",
    )
    e = leave_one_session_out_errors(rm, k=1)
    np.testing.assert_allclose(e, 1.5, atol=1e-9)
    # the vectors point from each session to the other: b's fingerprints found 1.5 m west in a
    v = leave_one_session_out_error_vectors(rm, np.array([0, 45]), k=1)
    np.testing.assert_allclose(v, [[1.5, 0.0], [-1.5, 0.0]], atol=1e-9)
    fn = fix_noise(rm, k=1)
    assert fn.median_m == pytest.approx(1.5) and fn.sigma_m == pytest.approx(1.5 / 1.1774, rel=1e-3)
    one = RadioMap.from_scans(scans, xy, session_ids="a", t_ns=list(range(40)), frame="site")
    with pytest.raises(Exception, match="2 sessions"):
        leave_one_session_out_errors(one)


def test_fix_error_correlation_tells_slow_map_errors_from_white_ones_and_tempers_the_bank():
    # Session b repeats a's fingerprints, laid off its true path: by a slowly varying shift (the
    # errors of neighbouring fixes agree: correlation near 1) or by an independent shift per
    # fingerprint (near 0). Sessions are stored out of time order: the pairs follow t_ns.
    rng = np.random.default_rng(2)
    n = 60
    xy = np.column_stack([np.linspace(0, 59, n), np.full(n, 10.0)])
    rss = _rss(xy) + rng.normal(0, 0.3, (n, len(APS)))
    scans = [{f"ap{j}": float(r[j]) for j in range(len(APS))} for r in rss]
    order = rng.permutation(n)

    def two_sessions(shift: np.ndarray) -> RadioMap:
        return RadioMap.from_scans(
            [scans[i] for i in order] + scans, np.vstack([xy[order], xy + shift]), session_ids=["a"] * n + ["b"] * n,
            t_ns=list(order) + list(range(n)), frame="site",
        )

    slow = np.column_stack([np.zeros(n), 4.0 * np.sin(np.arange(n) / 8.0)])
    white = rng.normal(0.0, 3.0, (n, 2))
    rho_slow = fix_error_correlation(two_sessions(slow), k=1)
    rho_white = fix_error_correlation(two_sessions(white), k=1)
    assert rho_slow > 0.9 and abs(rho_white) < 0.3
    assert bank_temper(0.0) == 1.0 and bank_temper(-0.4) == 1.0 and bank_temper(0.5) == pytest.approx(3.0)
    assert bank_temper(0.99) == pytest.approx(19.0)  # clipped at rho 0.9
    assert bank_temper(rho_slow) > 10.0
    with pytest.raises(Exception, match="2 sessions"):
        fix_error_correlation(RadioMap.from_scans(scans, xy, session_ids="a", t_ns=list(range(n)), frame="site"))


def test_rssi_variance_factor_is_one_for_independent_readings_and_grows_with_duplicated_bssids():
    # Readings with the stated 4 dB independent noise: the map positions sit where the readings
    # put them, chi-square distributed (factor ~1). The same physical APs announced under 8
    # BSSIDs each (identical readings) claim 8x the information they have: factor ~8.
    rng = np.random.default_rng(2)
    xy = rng.uniform(2, 28, (400, 2))
    noise = rng.normal(0, 4.0, (400, len(APS)))
    rss = _rss(xy) + noise
    names = [f"ap{j}" for j in range(len(APS))]
    rm = RadioMap.from_scans([dict(zip(names, r.tolist())) for r in rss], xy, session_ids="s", t_ns=list(range(400)), frame="site")
    sig = np.full(len(APS), 4.0)
    assert rssi_variance_factor(rm, _models(names, APS), sig) == pytest.approx(1.0, abs=0.25)
    dup = [f"ap{j}-{c}" for j in range(len(APS)) for c in range(8)]
    rm8 = RadioMap.from_scans(
        [{f"ap{j}-{c}": float(r[j]) for j in range(len(APS)) for c in range(8)} for r in rss], xy,
        session_ids="s", t_ns=list(range(400)), frame="site",
    )
    f8 = rssi_variance_factor(rm8, _models(dup, np.repeat(APS, 8, axis=0)), np.full(len(dup), 4.0))
    assert 6.0 < f8 < 10.0, f8


def _corridor_map(offset_m: float, seed: int = 3) -> RadioMap:
    """Two walks along y = 10 with the same fingerprints, the second laid ``offset_m`` east."""
    rng = np.random.default_rng(seed)
    xy = np.column_stack([np.linspace(0, 30, 40), np.full(40, 10.0)])
    scans = [{f"ap{j}": float(r[j]) for j in range(len(APS))} for r in _rss(xy) + rng.normal(0, 1.0, (40, len(APS)))]
    t = [int(2e9 * i) for i in range(40)]
    return RadioMap.from_scans(
        scans + scans, np.vstack([xy, xy + [offset_m, 0.0]]), session_ids=["a"] * 40 + ["b"] * 40, t_ns=t + t, frame="site",
    )


def test_self_calibration_takes_the_fix_noise_from_the_map_and_keeps_the_configured_floor_otherwise():
    from graphslam.core.tracking.tracker import Tracker
    from graphslam.tracking_config import TrackConfig

    names = [f"ap{j}" for j in range(len(APS))]
    cfg = TrackConfig(calibration={"replay_sessions": 0})
    far = Tracker.on_map(_corridor_map(6.0), _models(names, APS), cfg)
    assert far.cfg.knn_fixes.sigma_floor_m == pytest.approx(6.0 / 1.1774, rel=0.05)  # the maps' sessions disagree by 6 m
    near = Tracker.on_map(_corridor_map(0.5), _models(names, APS), cfg)
    assert near.cfg.knn_fixes.sigma_floor_m == cfg.knn_fixes.sigma_floor_m  # never below the configured floor
    off = Tracker.on_map(_corridor_map(6.0), _models(names, APS), TrackConfig(calibration={"enabled": False}))
    assert off.cfg.knn_fixes.sigma_floor_m == cfg.knn_fixes.sigma_floor_m and off.cfg.calibration.covariance_scale == 1.0
    assert off.cfg.fixed_lag.bank_temper is None and far.cfg.fixed_lag.bank_temper > 1.0  # measured on the map (None: the bank's own costs)
    assert far.calibration.bank_temper == far.cfg.fixed_lag.bank_temper
    fixed = Tracker.on_map(_corridor_map(6.0), _models(names, APS), cfg.updated({"fixed_lag.bank_temper": 2.5}))
    assert fixed.cfg.fixed_lag.bank_temper == 2.5 and fixed.calibration.bank_temper == 1.0  # configured: not measured
    ekf = Tracker.on_map(_corridor_map(6.0), _models(names, APS), cfg.updated({"filter.kind": "ekf"}))
    assert ekf.calibration.bank_temper == 1.0  # no weighted bank to temper: not measured
    assert (far.model.r_rssi >= off.model.r_rssi - 1e-12).all()  # RSSI variance only ever inflated


def test_replay_scale_grows_when_the_tracker_claims_too_much_and_scales_the_reported_covariance():
    # Replaying the map's own walks: a tracker told its fixes are good to 5 cm (and its RSSI to
    # 0.1 dB) reports ellipses far too small for where the map says the walk was, so the factor is
    # large; one told 20 m needs none (>= 1 by construction).
    from graphslam.core.tracking.tracker import fusion_model, replay_covariance_scale, track_session
    from graphslam.tracking_config import TrackConfig
    from graphslam.core.radiomap.knn import KnnConfig, KnnLocator

    names = [f"ap{j}" for j in range(len(APS))]
    rm, models = _corridor_map(1.0), _models(names, APS)
    # leave-one-walk-out replay: the two walks repeat each other 1 m apart, so the default route
    # radius (1 m) would leave nothing to replay on
    small = dict(calibration={"replay_sessions": 2, "replay_max_scans": 12, "enabled": False, "replay_route_radius_m": 0.0},
                 motion={"n_theta_hypotheses": 2})
    tight = TrackConfig(knn_fixes={"sigma_floor_m": 0.05}, rssi={"sigma_floor_db": 0.1}, **small)
    loose = TrackConfig(knn_fixes={"sigma_floor_m": 20.0}, rssi={"sigma_floor_db": 30.0}, **small)
    s_tight = replay_covariance_scale(rm, fusion_model(_models(names, APS), tight), tight)
    s_loose = replay_covariance_scale(rm, fusion_model(models, loose), loose)
    assert s_tight > 5.0 and s_loose == pytest.approx(1.0), (s_tight, s_loose)
    # covariance_scale multiplies the reported covariance and nothing else
    from graphslam.core.types import PoseTrack, Scan, Session

    v = rm.fingerprints.values.tocsr()
    scans = tuple(Scan(int(rm.t_ns[i]), {rm.bssids[c]: float(x) + rm.missing_dbm for c, x in zip(v[i].indices, v[i].data)})
                  for i in range(12))
    walk = Session("w", PoseTrack(rm.t_ns[:12], rm.xy[:12] - rm.xy[0], np.zeros(12)), scans)
    loc = KnnLocator(rm, KnnConfig(k=3))
    a = track_session(walk, fusion_model(models, tight), loc, tight)
    b = track_session(walk, fusion_model(models, tight), loc, tight.updated({"calibration.covariance_scale": 3.0}))
    np.testing.assert_allclose(b.x, a.x)
    np.testing.assert_allclose(b.P, 3.0 * a.P)


def test_replay_leaves_out_the_walks_that_repeat_the_replayed_path():
    from graphslam.core.tracking.tracker import _repeats

    x = np.linspace(0.0, 20.0, 21)
    paths = {
        "a": np.column_stack([x, np.zeros_like(x)]),  # the replayed walk
        "b": np.column_stack([x, np.full_like(x, 0.8)]),  # the same corridor again
        "c": np.column_stack([x[:3], np.full_like(x[:3], 0.8)]),  # its first 2 m only
        "d": np.column_stack([x, np.full_like(x, 6.0)]),  # a parallel corridor
    }
    sid = [s for s, p in paths.items() for _ in p]
    xy = np.vstack(list(paths.values()))
    rm = RadioMap.from_scans([{"ap": -50.0}] * len(xy), xy, session_ids=sid, t_ns=np.arange(len(xy)), frame="site")
    own = np.flatnonzero(rm.session_ids == "a")
    rest = np.flatnonzero(rm.session_ids != "a")
    assert sorted(_repeats(rm, own, rest, 2.0).tolist()) == ["b"]
    assert sorted(_repeats(rm, own, rest, 7.0).tolist()) == ["b", "d"]
    assert _repeats(rm, own, rest, 0.5).tolist() == []


def test_the_tracker_locates_and_self_calibrates_its_fixes_with_the_configured_metric(monkeypatch):
    import graphslam.core.tracking.calibration as calibration
    from graphslam.core.tracking.tracker import Tracker
    from graphslam.tracking_config import TrackConfig

    seen: list[str] = []
    real = calibration.fix_noise

    def spy(rm, *, k=3, metric="eq9", **kw):
        seen.append(metric)
        return real(rm, k=k, metric=metric, **kw)

    monkeypatch.setattr(calibration, "fix_noise", spy)
    names = [f"ap{j}" for j in range(len(APS))]
    for asked, used in (("sorensen", "sorensen"), ("eq9", "eq9")):
        tr = Tracker.on_map(_corridor_map(6.0), _models(names, APS), TrackConfig(calibration={"replay_sessions": 0}, knn_fixes={"metric": asked}))
        assert tr.locator.config.metric == used and seen[-1] == used
    assert TrackConfig().knn_fixes.metric == "sorensen"  # the default (docs/tracking.md)
