"""Noise levels measured on the radio map, and the calibration figures (graphslam.core.tracking.calibration)."""

from __future__ import annotations

import numpy as np
import pytest

from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.core.tracking.apmodel import ApModel, ApModels
from graphslam.core.tracking.calibration import (
    CHI2_2DOF_95, ellipse_coverage, fix_noise, leave_one_session_out_errors, mahalanobis_sq, rssi_variance_factor,
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
    fn = fix_noise(rm, k=1)
    assert fn.median_m == pytest.approx(1.5) and fn.sigma_m == pytest.approx(1.5 / 1.1774, rel=1e-3)
    one = RadioMap.from_scans(scans, xy, session_ids="a", t_ns=list(range(40)), frame="site")
    with pytest.raises(Exception, match="2 sessions"):
        leave_one_session_out_errors(one)


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
