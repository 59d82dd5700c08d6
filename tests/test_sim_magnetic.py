"""The simulated magnetic field (``/phone/magnetic``, graphslam.sim.magnetic): the site's field (Earth +
a smooth anomaly), what the phone records (one message per step after the first, east ~ 0), the same
field at the same place on every walk, independence from every other simulated value, MCAP round
trip, the switch to turn it off."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from graphslam.cli import main
from graphslam.core.types import PoseTrack, Session
from graphslam.errors import ConfigError, SimulationError
from graphslam.io.mcap_reader import read_session, read_survey
from graphslam.io.mcap_writer import write_session
from graphslam.io.schemas import TOPIC_MAGNETIC
from graphslam.sim import (
    MagneticModel,
    SimulatedSurvey,
    anomaly_field,
    build_building,
    corridor_plan,
    office_plan,
    phone_magnetic,
    simulate,
    with_overrides,
)
from graphslam.sim.magnetic import walk_offset
from graphslam.sim.scenarios import _magnetic_rng

OFF = MagneticModel(enabled=False)
# Small versions of every scenario (walks of their own streams, so the same walks as the full ones).
CASES = {"paper": 0.4, "corridor": 0.5, "crowd": 0.1, "museum": 0.25}


def _small(name: str, field: bool = True) -> SimulatedSurvey:
    sc = with_overrides(name) if field else with_overrides(name, magnetic=OFF)
    return simulate(sc, seed=3, size=CASES[name], test_walks=1)


@pytest.fixture(scope="module")
def sims() -> dict[str, tuple[SimulatedSurvey, SimulatedSurvey]]:
    return {name: (_small(name), _small(name, field=False)) for name in CASES}


def _walks(sim: SimulatedSurvey) -> list[Session]:
    return list(sim.survey) + list(sim.test_sessions)


def test_one_field_per_step_after_the_first_east_near_zero(sims: dict) -> None:
    """Every walk of every scenario: one message per /phone/heading timestamp; the horizontal part points
    north up to the orientation's azimuth error (7 deg); north ~ 20 uT, up ~ -44 uT (the Earth's field)."""
    for name, (sim, _) in sims.items():
        az = []
        for s in _walks(sim):
            m = s.magnetic
            assert m is not None and s.heading is not None, (name, s.session_id)
            np.testing.assert_array_equal(m.t_ns, s.heading.t_ns)
            e, n, u = m.enu.T
            assert np.all(n > 0)
            az.append(np.degrees(np.arctan2(e, n)))
            # one walk's offset (2.5 uT per component; 5 % of walks 10-30 uT) moves the means
            assert 5.0 < np.median(np.hypot(e, n)) < 40.0 and -75.0 < np.median(u) < -15.0
        a = np.concatenate(az)
        # errors correlated over ~1 step: about half as many independent ones as steps
        assert abs(a.mean()) < 6 * 7.0 / math.sqrt(len(a)) and 6.3 < a.std() < 7.7, name
    # no azimuth error: east is exactly 0, north the horizontal magnitude
    sim = sims["corridor"][0]
    gt = sim.survey.sessions[0].ground_truth
    exact = phone_magnetic(gt, dataclasses.replace(MagneticModel(), azimuth_sigma_deg=0.0), sim.building.field_anomaly,
                           np.random.default_rng(0))
    np.testing.assert_array_equal(exact.enu[:, 0], 0.0)


def test_field_changes_no_other_value(sims: dict, tmp_path: Path) -> None:
    """The field comes from streams of its own: with or without it, every other value is bit-identical,
    down to every other topic's bytes in the MCAP files."""
    for name, (on, off) in sims.items():
        np.testing.assert_array_equal(on.building.radio.shadowing.values, off.building.radio.shadowing.values)
        np.testing.assert_array_equal(on.building.magnetic_field.values, off.building.magnetic_field.values)
        assert off.building.field_anomaly is None and off.building.field_model is None
        a, b = _walks(on), _walks(off)
        assert [s.session_id for s in a] == [s.session_id for s in b]
        for x, y in zip(a, b):
            assert y.magnetic is None and x.magnetic is not None
            for u, v in ((x.steps, y.steps), (x.ground_truth, y.ground_truth)):
                np.testing.assert_array_equal(u.xy, v.xy)
                np.testing.assert_array_equal(u.heading, v.heading)
            np.testing.assert_array_equal(x.heading.yaw, y.heading.yaw)
            assert [(c.t_ns, dict(c.readings)) for c in x.scans] == [(c.t_ns, dict(c.readings)) for c in y.scans]
            assert x.landmarks == y.landmarks

    def messages(path: Path) -> list[tuple[str, int, bytes]]:
        with path.open("rb") as f:
            return [(c.topic, m.log_time, m.data) for _, c, m in make_reader(f).iter_messages()]

    on, off = sims["museum"]
    for x, y in zip(on.survey, off.survey):
        mx = messages(write_session(x, tmp_path / "on.mcap"))
        my = messages(write_session(y, tmp_path / "off.mcap"))
        assert [m for m in mx if m[0] != TOPIC_MAGNETIC] == my
        assert sum(m[0] == TOPIC_MAGNETIC for m in mx) == len(x.steps) - 1


def test_anomaly_statistics_on_the_grid() -> None:
    """Each component: std ~ anomaly_sigma_ut, correlation exp(-(r / anomaly_corr_m)^2) along the grid
    (no envelope: exactly; with the default envelope the correlation is that times exp(s2 (rho_s - 1)))."""
    for model in (MagneticModel(envelope_sigma=0.0),
                  MagneticModel(anomaly_sigma_ut=5.0, anomaly_corr_m=1.0, grid_m=0.25, envelope_sigma=0.0),
                  MagneticModel()):
        f = anomaly_field(office_plan(), model, np.random.default_rng(11))
        v = f.values
        assert v.shape[0] == 3 and f.spacing_m == model.grid_m
        s2, tol = model.envelope_sigma**2, 0.1 if model.envelope_sigma else 0.06
        for c in range(3):
            assert abs(v[c].mean()) < 0.1 * model.anomaly_sigma_ut
            assert 1 - 2 * tol < v[c].std() / model.anomaly_sigma_ut < 1 + 2 * tol
            for r in (0.5 * model.anomaly_corr_m, model.anomaly_corr_m, 2.0 * model.anomaly_corr_m):
                k = int(round(r / model.grid_m))
                rho = np.mean([np.corrcoef(v[c][:, :-k].ravel(), v[c][:, k:].ravel())[0, 1],
                               np.corrcoef(v[c][:-k].ravel(), v[c][k:].ravel())[0, 1]])
                d = k * model.grid_m
                rho_s = math.exp(-((d / model.envelope_corr_m) ** 2))
                want = math.exp(-((d / model.anomaly_corr_m) ** 2) + s2 * (rho_s - 1))
                assert abs(rho - want) < tol, (c, r, rho, want)
        assert abs(np.corrcoef(v[0].ravel(), v[2].ravel())[0, 1]) < 0.06  # components independent
        # the envelope: strong in places, calm in others (heavy tails); none: Gaussian (kurtosis 3)
        kurt = float(np.mean(v[2] ** 4) / np.mean(v[2] ** 2) ** 2)
        assert (kurt > 4.0) if model.envelope_sigma else (2.7 < kurt < 3.3), kurt
    # the site's field = the Earth's + the anomaly, in every scenario's building
    b = build_building("paper", seed=2)
    p = np.random.default_rng(0).uniform([0, 0], [120, 60], (3000, 2))
    np.testing.assert_allclose(b.field_ut(p) - b.field_anomaly.at(p), np.tile([0.0, 20.0, -44.0], (3000, 1)))
    assert 19.0 < np.median(np.hypot(*b.field_ut(p)[:, :2].T)) < 21.5


def test_same_field_at_the_same_place_on_every_walk() -> None:
    """Two repetitions of one museum route: at steps within 0.3 m of each other the recorded field, each
    walk less its drawn offset, agrees to the noise; without removing the offsets, to the offsets."""
    sim = simulate("museum", seed=4, size=0.5)
    ua, ub, ha, hb = [], [], [], []
    for r, route in enumerate(sim.building.routes):
        a, b = (sim.survey[f"museum-s4-{route.name}-rep0{k + 1}"] for k in (0, 1))
        oa, ob = (walk_offset(MagneticModel(), _magnetic_rng(4, 1, r, k)) for k in (0, 1))
        xa, xb = a.ground_truth.xy[1:], b.ground_truth.xy[1:]
        i, j = np.nonzero(np.linalg.norm(xa[:, None] - xb[None], axis=2) < 0.3)
        ua.append(a.magnetic.enu[i, 2] - oa[2])
        ub.append(b.magnetic.enu[j, 2] - ob[2])
        # the horizontal magnitude, each walk's mean removed (what the survey's windows compare)
        ha.append(np.hypot(*a.magnetic.enu[i, :2].T) - np.hypot(*a.magnetic.enu[i, :2].T).mean())
        hb.append(np.hypot(*b.magnetic.enu[j, :2].T) - np.hypot(*b.magnetic.enu[j, :2].T).mean())
    ua, ub = np.concatenate(ua), np.concatenate(ub)
    assert len(ua) > 300
    # the same field: differences ~ two walks' noise (0.4 uT each) and the steps' own paths;
    # a field of its own per walk would differ by ~6 uT
    assert np.corrcoef(ua, ub)[0, 1] > 0.9
    assert (ua - ub).std() < 1.6
    assert np.corrcoef(np.concatenate(ha), np.concatenate(hb))[0, 1] > 0.75


def test_per_step_value_is_the_path_mean_plus_offset_and_noise() -> None:
    """No noise, no azimuth error: (north, up) = the horizontal magnitude and vertical component of the
    field averaged over the step's path, plus the walk's offset."""
    b = build_building("corridor", seed=1)
    xy = np.column_stack([np.linspace(3.0, 40.0, 61), np.full(61, 2.0)])
    truth = PoseTrack(np.arange(61, dtype=np.int64) * 500_000_000, xy, np.zeros(61))
    model = dataclasses.replace(MagneticModel(), noise_sigma_ut=0.0, azimuth_sigma_deg=0.0, samples_per_step=64)
    m = phone_magnetic(truth, model, b.field_anomaly, np.random.default_rng(5))
    o = walk_offset(model, np.random.default_rng(5))
    fine = np.column_stack([np.linspace(3.0, 40.0, 60 * 400 + 1), np.full(60 * 400 + 1, 2.0)])
    f = b.field_ut(fine)
    mean = np.array([f[k * 400 : (k + 1) * 400 + 1].mean(axis=0) for k in range(60)]) + o
    np.testing.assert_allclose(m.enu[:, 1], np.hypot(mean[:, 0], mean[:, 1]), atol=0.02)
    np.testing.assert_allclose(m.enu[:, 2], mean[:, 2], atol=0.02)
    np.testing.assert_array_equal(m.t_ns, truth.t_ns[1:])


def test_offsets_follow_the_model() -> None:
    """Per walk: N(0, 2.5 uT) per component or, 5 % of walks, 10-30 uT in a random direction."""
    m = MagneticModel()
    off = np.array([walk_offset(m, np.random.default_rng([7, i])) for i in range(4000)])
    size = np.linalg.norm(off, axis=1)
    large = size >= 10.0  # a Gaussian offset beyond 10 uT: chi(3) at 4 sigma, p ~ 1e-3 per walk
    assert 0.035 <= large.mean() <= 0.07
    assert np.all(size[large] <= 30.0)
    small = off[size < 9.0]
    assert np.all(np.abs(small.mean(axis=0)) < 0.15) and np.all(np.abs(small.std(axis=0) - 2.5) < 0.15)
    np.testing.assert_array_equal(
        walk_offset(MagneticModel(offset_sigma_ut=0.0, large_offset_prob=0.0), np.random.default_rng(0)), 0.0
    )


def test_field_round_trips_through_mcap(tmp_path: Path, sims: dict) -> None:
    s = sims["corridor"][0].survey.sessions[0]
    back = read_session(write_session(s, tmp_path / "w.mcap"))
    assert back.magnetic is not None
    np.testing.assert_array_equal(back.magnetic.t_ns, s.magnetic.t_ns)
    np.testing.assert_array_equal(back.magnetic.enu, s.magnetic.enu)
    assert read_session(write_session(sims["corridor"][1].survey.sessions[0], tmp_path / "n.mcap")).magnetic is None


def test_cli_simulate_no_magnetic(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    main(["simulate", "corridor", "--out", str(tmp_path / "on"), "--size", "0.25"])
    main(["simulate", "corridor", "--out", str(tmp_path / "off"), "--size", "0.25", "--no-magnetic"])
    capsys.readouterr()
    on = read_survey(sorted((tmp_path / "on").glob("*.mcap")))
    off = read_survey(sorted((tmp_path / "off").glob("*.mcap")))
    assert len(on) == len(off) == 3
    for x, y in zip(on, off):
        assert x.magnetic is not None and len(x.magnetic) == len(x.steps) - 1 and y.magnetic is None
        np.testing.assert_array_equal(x.heading.yaw, y.heading.yaw)
    b_on = json.loads((tmp_path / "on" / "building.json").read_text())["building"]
    assert b_on["magnetic"]["earth_ut"] == {"east": 0.0, "north": 20.0, "up": -44.0}
    assert json.loads((tmp_path / "off" / "building.json").read_text())["building"]["magnetic"] is None
    main(["simulate", "--help"])
    assert "--no-magnetic" in capsys.readouterr().out


def test_bad_magnetic_models_raise() -> None:
    for bad in (
        {"anomaly_sigma_ut": -1.0}, {"noise_sigma_ut": -0.1}, {"offset_sigma_ut": -2.0}, {"azimuth_sigma_deg": -1.0},
        {"large_offset_prob": 1.5}, {"large_offset_ut": (30.0, 10.0)}, {"anomaly_corr_m": 0.0}, {"grid_m": 0.0},
        {"horizontal_ut": math.nan}, {"samples_per_step": 0}, {"envelope_sigma": -0.1}, {"envelope_corr_m": 0.0},
        {"azimuth_corr_steps": 0.0},
    ):
        with pytest.raises(ConfigError):
            MagneticModel(**bad)  # type: ignore[arg-type]
    sim = simulate("corridor", seed=0, size=0.1)
    with pytest.raises(SimulationError):
        phone_magnetic(sim.survey.sessions[0].ground_truth, OFF, sim.building.field_anomaly, np.random.default_rng(0))
    with pytest.raises(SimulationError):
        anomaly_field(corridor_plan(), OFF, np.random.default_rng(0))
    with pytest.raises(SimulationError):
        simulate(with_overrides("corridor", magnetic=OFF), seed=0, size=0.1).building.field_ut(np.zeros((1, 2)))
