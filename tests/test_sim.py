"""Simulator: scenario statistics, radio model, dead reckoning, determinism, MCAP round trip."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest

from graphslam.cli import main
from graphslam.core.types import wrap_angle
from graphslam.errors import ConfigError
from graphslam.io.mcap_reader import read_survey
from graphslam.sim import (
    RadioParams,
    SimulatedSurvey,
    SurveyStats,
    build_building,
    raw_drift,
    simulate,
    wall_crossings,
    with_overrides,
)
from graphslam.sim.radio import gaussian_field

EPOCH_2026_NS = 1_767_225_600 * 10**9

# Documented in docs/simulator.md ("Measured statistics").
PAPER_MAX_DRIFT_BAND_M = (12.0, 55.0)  # any one seed
PAPER_MEAN_MAX_DRIFT_M = (20.0, 40.0)  # mean over seeds 0-3
PAPER_TOTAL_KM = (5.2, 6.0)


@pytest.fixture(scope="module")
def paper() -> SimulatedSurvey:
    return simulate("paper", seed=0)


@pytest.fixture(scope="module")
def corridor() -> SimulatedSurvey:
    return simulate("corridor", seed=0, test_walks=2)


# --------------------------------------------------------------------------- scenarios


def test_paper_totals_match_the_paper(paper: SimulatedSurvey) -> None:
    st = SurveyStats.of(paper.survey)
    assert len(st.walks) == 5
    minutes = sorted(w.duration_s / 60 for w in st.walks)
    assert 8.9 <= minutes[0] <= 9.1 and 27.9 <= minutes[-1] <= 28.1
    assert all(9 - 0.1 <= m <= 28 + 0.1 for m in minutes)
    assert PAPER_TOTAL_KM[0] <= st.length_m / 1000 <= PAPER_TOTAL_KM[1]
    assert 40 <= len(paper.building.aps) <= 80 and st.access_points_heard >= 40
    assert 4 <= len(paper.building.landmarks) <= 10
    assert st.marks >= 20, "walkers must mark landmarks (paper: 43 marks)"
    # ~0.5 s per step, 0.6-0.75 m steps, a scan every ~2 s
    for s in paper.survey:
        gt = s.ground_truth
        assert gt is not None
        step = np.linalg.norm(np.diff(gt.xy, axis=0), axis=1)
        assert 0.6 <= np.median(step) <= 0.75
        assert 0.45 <= np.median(np.diff(gt.t_ns)) / 1e9 <= 0.6
        scan_dt = np.diff([x.t_ns for x in s.scans]) / 1e9
        assert 1.8 <= scan_dt.mean() <= 2.2 and scan_dt.std() > 0.1


def test_paper_raw_drift_in_documented_band(paper: SimulatedSurvey) -> None:
    """Max raw drift per survey (worst walk, DR aligned by the true start pose): ~30 m as in the paper."""
    worst = []
    for seed in range(4):
        sim = paper if seed == 0 else simulate("paper", seed=seed)
        drifts = [raw_drift(s) for s in sim.survey]
        worst.append(max(float(d.max()) for d in drifts))
        assert all(d[0] < 1e-9 for d in drifts), "aligned by the true start pose, the first error is zero"
        # drift grows with time: late errors larger than early ones on the long walks
        for d in drifts[2:]:
            n = len(d)
            assert d[-n // 4 :].mean() > d[: n // 4].mean()
    assert all(PAPER_MAX_DRIFT_BAND_M[0] <= w <= PAPER_MAX_DRIFT_BAND_M[1] for w in worst), worst
    assert PAPER_MEAN_MAX_DRIFT_M[0] <= float(np.mean(worst)) <= PAPER_MEAN_MAX_DRIFT_M[1], worst


def test_walks_revisit_the_same_areas(paper: SimulatedSurvey) -> None:
    """Alignment needs overlap: most of every walk passes within 2 m of another walk."""
    sessions = list(paper.survey)
    for i, s in enumerate(sessions):
        assert s.ground_truth is not None
        others = np.vstack([o.ground_truth.xy for j, o in enumerate(sessions) if j != i])  # type: ignore[union-attr]
        pts = s.ground_truth.xy[::10]
        d = np.min(np.linalg.norm(pts[:, None, :] - others[None, ::5, :], axis=2), axis=1)
        assert np.mean(d < 2.0) > 0.6


def test_dead_reckoning_starts_at_origin_and_true_start_is_random(paper: SimulatedSurvey) -> None:
    starts = []
    for s in list(paper.survey) + list(simulate("crowd", seed=0, size=0.25).survey):
        assert s.steps.xy[0].tolist() == [0.0, 0.0] and s.steps.heading[0] == 0.0
        assert s.ground_truth is not None
        starts.append(s.ground_truth.xyh[0])
    starts_a = np.array(starts)
    assert np.ptp(starts_a[:, 0]) > 20 and np.ptp(starts_a[:, 1]) > 10
    assert np.std(np.cos(starts_a[:, 2])) > 0.3 and np.std(np.sin(starts_a[:, 2])) > 0.3


def test_session_metadata_and_timestamps(paper: SimulatedSurvey) -> None:
    ids = [s.session_id for s in paper.survey]
    assert ids == [f"paper-s0-w{i:02d}" for i in range(5)]
    starts = [int(s.steps.t_ns[0]) for s in paper.survey]
    assert all(t >= EPOCH_2026_NS for t in starts) and len(set(starts)) == 5
    for s in paper.survey:
        assert s.site == "sim-paper" and s.floor == "F1"
        assert s.steps.t_ns.dtype == np.int64
        t = [x.t_ns for x in s.scans]
        assert s.steps.t_ns[0] <= t[0] and t[-1] <= s.steps.t_ns[-1]


def test_landmark_marks_are_surveyed_points_the_walker_is_at(paper: SimulatedSurvey) -> None:
    surveyed = {lm.landmark_id: (lm.x, lm.y) for lm in paper.building.landmarks}
    for s in paper.survey:
        gt = s.ground_truth
        assert gt is not None
        last: dict[str, int] = {}
        for m in s.landmarks:
            assert (m.x, m.y) == surveyed[m.landmark_id]
            k = int(np.searchsorted(gt.t_ns, m.t_ns)) - 1
            assert np.hypot(*(gt.xy[k] - [m.x, m.y])) <= 0.7 + 1e-9
            if m.landmark_id in last:  # cooldown
                assert m.t_ns - last[m.landmark_id] >= 100 * 10**9
            last[m.landmark_id] = m.t_ns


def test_corridor_walks_are_straight_with_random_headings(corridor: SimulatedSurvey) -> None:
    assert len(corridor.survey) == 12
    line = corridor.building.plan.line
    assert line is not None
    dr_dirs, true_h0 = [], []
    for s in corridor.survey:
        gt = s.ground_truth
        assert gt is not None
        # the true path stays on the marked line
        assert np.all(np.abs(gt.xy[:, 1] - line[0, 1]) < 0.5)
        assert np.ptp(gt.xy[:, 0]) > 70
        # the DR track is straight: small residual from its principal axis
        xy = s.steps.xy - s.steps.xy.mean(axis=0)
        sv = np.linalg.svd(xy, compute_uv=False)
        assert sv[1] / math.sqrt(len(xy)) < 1.5 and sv[0] / math.sqrt(len(xy)) > 15
        d = s.steps.xy[-1] - s.steps.xy[0]
        dr_dirs.append(math.atan2(d[1], d[0]))
        true_h0.append(gt.heading[0])
    # DR frames rotated arbitrarily against the site: directions in the DR frame differ
    dirs = np.array(dr_dirs)
    assert np.ptp(np.asarray(wrap_angle(dirs - dirs[0]))) > math.radians(40)
    # and equal the line direction minus the (random) true start heading, up to drift
    np.testing.assert_allclose(np.cos(dirs + np.array(true_h0)), 1.0, atol=0.01)


def test_crowd_has_many_short_walks() -> None:
    sim = simulate("crowd", seed=0)
    st = SurveyStats.of(sim.survey)
    assert len(st.walks) >= 40
    assert all(0.95 <= w.duration_s / 60 <= 4.05 for w in st.walks)


def test_size_and_test_walks(corridor: SimulatedSurvey, paper: SimulatedSurvey) -> None:
    small = simulate("corridor", seed=0, size=0.25)
    assert len(small.survey) == 3
    # walk i does not depend on how many walks are simulated
    np.testing.assert_array_equal(small.survey.sessions[2].steps.xy, corridor.survey.sessions[2].steps.xy)
    bigger = simulate("paper", seed=0, size=2.0)
    assert len(bigger.survey) == 10
    assert bigger.survey.n_steps > 1.8 * paper.survey.n_steps
    # test walks: own stream, same building, ids apart, later dates
    assert [s.session_id for s in corridor.test_sessions] == ["corridor-s0-t00", "corridor-s0-t01"]
    assert not {s.session_id for s in corridor.test_sessions} & {s.session_id for s in corridor.survey}
    assert corridor.test_sessions[0].steps.t_ns[0] > corridor.survey.sessions[-1].steps.t_ns[-1]
    assert corridor.test_sessions[0].access_points <= set(corridor.building.aps.bssids)


def test_bad_arguments_raise_config_error() -> None:
    with pytest.raises(ConfigError, match="unknown scenario"):
        simulate("nope")
    with pytest.raises(ConfigError):
        simulate("corridor", size=0)
    with pytest.raises(ConfigError):
        simulate("corridor", test_walks=-1)
    with pytest.raises(ConfigError):
        RadioParams(gamma_range=(3.0, 2.0))


# --------------------------------------------------------------------------- determinism


def _fingerprint(sim: SimulatedSurvey) -> list:
    out = []
    for s in list(sim.survey) + list(sim.test_sessions):
        assert s.ground_truth is not None
        out.append(
            (
                s.session_id,
                s.steps.t_ns.tolist(),
                s.steps.xy.tolist(),
                s.ground_truth.xy.tolist(),
                [(x.t_ns, dict(x.readings)) for x in s.scans],
                s.landmarks,
            )
        )
    return out


def test_deterministic_per_seed() -> None:
    a = simulate("corridor", seed=7, size=0.5, test_walks=1)
    b = simulate("corridor", seed=7, size=0.5, test_walks=1)
    c = simulate("corridor", seed=8, size=0.5, test_walks=1)
    assert _fingerprint(a) == _fingerprint(b)
    np.testing.assert_array_equal(a.building.aps.xy, b.building.aps.xy)
    assert _fingerprint(a) != _fingerprint(c)
    assert not np.array_equal(a.building.aps.xy, c.building.aps.xy)


# --------------------------------------------------------------------------- radio model


def _no_walls_no_shadow(noise: float = 3.0) -> RadioParams:
    return RadioParams(wall_loss_db=0.0, shadowing_sigma_db=0.0, noise_sigma_db=noise, miss_prob=0.0)


def test_rss_follows_configured_path_loss() -> None:
    b = build_building(with_overrides("paper", radio=_no_walls_no_shadow()), seed=3)
    rng = np.random.default_rng(0)
    xy = rng.uniform([0, 0], [120, 60], (4000, 2))
    d = b.radio.distances(xy)
    # noiseless: exactly eq. 5
    mean = b.mean_rss(xy)
    np.testing.assert_allclose(mean, b.aps.p0_dbm - 10 * b.aps.gamma * np.log10(d), atol=1e-9)
    # noisy, quantised, floored samples: a least-squares fit recovers P0 and gamma
    rss = b.radio.sample_rss(xy, rng)
    assert np.all(np.isnan(rss) | (rss == np.round(rss)))
    assert np.nanmin(rss) >= -95
    for a in range(0, len(b.aps), 7):
        ok = (mean[:, a] > -80) & ~np.isnan(rss[:, a])  # well above the floor: no truncation bias
        x = -10 * np.log10(d[ok, a])
        gamma, p0 = np.polyfit(x, rss[ok, a], 1)
        assert abs(gamma - b.aps.gamma[a]) < 0.12, (a, gamma, b.aps.gamma[a])
        assert abs(p0 - b.aps.p0_dbm[a]) < 1.5, (a, p0, b.aps.p0_dbm[a])


def test_walls_attenuate_per_wall_crossed() -> None:
    walls = np.array([[5.0, -10, 5, 10], [8.0, -10, 8, 10], [0.0, 20, 30, 20]])
    aps = np.array([[0.0, 0.0], [10.0, 5.0]])
    pts = np.array([[3.0, 0.0], [6.0, 0.0], [9.0, 1.0], [9.0, 25.0]])
    np.testing.assert_array_equal(wall_crossings(pts, aps, walls), [[0, 2], [1, 1], [2, 0], [1, 1]])
    # against a plain loop on random geometry
    rng = np.random.default_rng(1)
    walls = rng.uniform(0, 50, (40, 4))
    aps = rng.uniform(0, 50, (7, 2))
    pts = rng.uniform(0, 50, (60, 2))

    def crosses(p: np.ndarray, q: np.ndarray, w: np.ndarray) -> bool:
        def orient(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> float:
            return float((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]))

        w1, w2 = w[:2], w[2:]
        return orient(w1, w2, p) * orient(w1, w2, q) < 0 and orient(p, q, w1) * orient(p, q, w2) < 0

    expected = [[sum(crosses(p, a, w) for w in walls) for a in aps] for p in pts]
    np.testing.assert_array_equal(wall_crossings(pts, aps, walls), expected)
    # the model charges wall_loss_db per wall
    b = build_building("paper", seed=0)
    xy = rng.uniform([0, 0], [120, 60], (300, 2))
    diff = b.mean_rss(xy, shadowing=False) - b.mean_rss(xy, walls=False, shadowing=False)
    n = wall_crossings(xy, b.aps.xy, b.walls)
    np.testing.assert_allclose(diff, -b.radio.params.wall_loss_db * n, atol=1e-9)
    assert n.max() >= 3


def test_shadowing_is_spatially_correlated() -> None:
    b = build_building("paper", seed=0)
    sigma = b.radio.params.shadowing_sigma_db
    rng = np.random.default_rng(2)
    p = rng.uniform([10, 10], [110, 50], (3000, 2))
    ang = rng.uniform(0, 2 * np.pi, (3000, 1))
    u = np.hstack([np.cos(ang), np.sin(ang)])
    s0 = b.radio.shadowing.at(p).ravel()
    near = b.radio.shadowing.at(p + 0.5 * u).ravel()
    far = b.radio.shadowing.at(p + 20.0 * u).ravel()
    assert 0.8 * sigma < s0.std() < 1.2 * sigma
    assert np.corrcoef(s0, near)[0, 1] > 0.85
    assert abs(np.corrcoef(s0, far)[0, 1]) < 0.1
    # the generator itself: std and correlation exp(-(r/l)^2) on the grid
    f = gaussian_field(np.random.default_rng(3), (40, 64, 64), 4.0, 5.0)
    assert abs(f.std() - 4.0) < 0.2
    rho = np.mean(f * np.roll(f, 5, axis=2)) / f.var()
    assert abs(rho - math.exp(-1.0)) < 0.06


def test_scans_see_nearby_aps_strongest(paper: SimulatedSurvey) -> None:
    s = paper.survey.sessions[0]
    gt = s.ground_truth
    assert gt is not None
    aps = dict(zip(paper.building.aps.bssids, paper.building.aps.xy))
    hits = 0
    for scan in s.scans[::10]:
        k = int(np.searchsorted(gt.t_ns, scan.t_ns))
        pos = gt.xy[min(k, len(gt) - 1)]
        strongest = max(scan.readings, key=scan.readings.__getitem__)
        dists = sorted(np.linalg.norm(xy - pos) for xy in aps.values())
        hits += np.linalg.norm(aps[strongest] - pos) <= dists[4]
        assert all(-95 <= r <= -20 and r == int(r) for r in scan.readings.values())
    assert hits >= 0.7 * len(s.scans[::10])


# --------------------------------------------------------------------------- files and CLI


def test_written_files_read_back_equal(tmp_path: Path, corridor: SimulatedSurvey) -> None:
    corridor.write(tmp_path)
    back = read_survey(sorted(tmp_path.glob("*.mcap")))
    tests = read_survey([tmp_path / "test"])
    assert (tmp_path / "building.json").exists()
    for sims, reads in ((list(corridor.survey), list(back)), (list(corridor.test_sessions), list(tests))):
        assert [s.session_id for s in reads] == [s.session_id for s in sims]
        for a, b in zip(sims, reads):
            assert (b.site, b.floor) == (a.site, a.floor)
            np.testing.assert_array_equal(b.steps.t_ns, a.steps.t_ns)
            np.testing.assert_allclose(b.steps.xy, a.steps.xy, atol=1e-12)
            np.testing.assert_allclose(np.cos(b.steps.heading - a.steps.heading), 1.0, atol=1e-12)
            assert a.ground_truth is not None and b.ground_truth is not None
            np.testing.assert_allclose(b.ground_truth.xy, a.ground_truth.xy, atol=1e-12)
            assert [(x.t_ns, dict(x.readings)) for x in b.scans] == [(x.t_ns, dict(x.readings)) for x in a.scans]
            assert b.landmarks == a.landmarks


def test_cli_simulate(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    main(["simulate", "corridor", "--out", str(tmp_path), "--size", "0.25", "--test-walks", "1", "--seed", "4"])
    out = capsys.readouterr().out
    assert "3 sessions" in out and "max raw drift" in out and "km" in out
    assert sorted(p.name for p in tmp_path.glob("*.mcap")) == [f"corridor-s4-w{i:02d}.mcap" for i in range(3)]
    assert [p.name for p in (tmp_path / "test").glob("*.mcap")] == ["corridor-s4-t00.mcap"]
    # the km it reports are those inspect reads back from the recordings (the true path's beside them)
    walked = re.search(r"([\d.]+) km walked \(true path ([\d.]+) km\)", out)
    assert walked, out
    main(["inspect", *map(str, sorted(tmp_path.glob("*.mcap")))])
    assert f"{walked.group(1)} km walked" in capsys.readouterr().out
    with pytest.raises(SystemExit) as e:
        main(["simulate", "nope", "--out", str(tmp_path)])
    assert e.value.code == 2
