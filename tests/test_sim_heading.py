"""The simulated phone azimuth (``/phone/heading``, graphslam.sim.heading): timing, frames, error model,
independence from every other simulated value, MCAP round trip, the switch to turn it off."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest

from graphslam.cli import main
from graphslam.core.types import Session
from graphslam.errors import ConfigError, SimulationError
from graphslam.io.mcap_reader import read_session, read_survey
from graphslam.io.mcap_writer import write_session
from graphslam.sim import (
    HeadingModel,
    ShadowingField,
    SimulatedSurvey,
    build_building,
    phone_heading,
    simulate,
    walk_offset,
    with_overrides,
    wrap_yaw,
)
from graphslam.sim.scenarios import _heading_rng

OFF = HeadingModel(enabled=False)
# Small versions of every scenario (walks of their own streams, so the same walks as the full ones).
CASES = {"paper": 0.4, "corridor": 0.5, "crowd": 0.1, "museum": 0.25}


def _small(name: str, heading: bool = True) -> SimulatedSurvey:
    sc = with_overrides(name) if heading else with_overrides(name, heading=OFF)
    return simulate(sc, seed=3, size=CASES[name], test_walks=1)


@pytest.fixture(scope="module")
def sims() -> dict[str, tuple[SimulatedSurvey, SimulatedSurvey]]:
    return {name: (_small(name), _small(name, heading=False)) for name in CASES}


def _walks(sim: SimulatedSurvey) -> list[Session]:
    return list(sim.survey) + list(sim.test_sessions)


def _residual_deg(s: Session, model: HeadingModel = HeadingModel()) -> np.ndarray:
    """Yaw minus the true heading rotated into the Earth frame (deg, wrapped): offset + distortion + noise."""
    assert s.heading is not None and s.ground_truth is not None
    d = s.heading.yaw - s.ground_truth.heading[1:] - model.earth_from_site_rad
    return np.degrees(wrap_yaw(d))


def test_one_yaw_per_step_after_the_first_in_range(sims: dict) -> None:
    for name, (sim, _) in sims.items():
        assert sim.building.earth_from_site_deg == 12.0 and sim.building.magnetic_field is not None
        for s in _walks(sim):
            assert s.heading is not None, (name, s.session_id)
            np.testing.assert_array_equal(s.heading.t_ns, s.steps.t_ns[1:])
            assert np.all(s.heading.yaw >= -math.pi) and np.all(s.heading.yaw < math.pi)


def test_headings_change_no_other_value(sims: dict) -> None:
    """Headings come from streams of their own: with or without them, every other value is bit-identical."""
    for name, (on, off) in sims.items():
        np.testing.assert_array_equal(on.building.aps.xy, off.building.aps.xy)
        np.testing.assert_array_equal(on.building.radio.shadowing.values, off.building.radio.shadowing.values)
        np.testing.assert_array_equal(on.building.walls, off.building.walls)
        assert off.building.magnetic_field is None and off.building.earth_from_site_deg is None
        a, b = _walks(on), _walks(off)
        assert [s.session_id for s in a] == [s.session_id for s in b]
        for x, y in zip(a, b):
            assert y.heading is None
            assert x.ground_truth is not None and y.ground_truth is not None
            for u, v in ((x.steps, y.steps), (x.ground_truth, y.ground_truth)):
                np.testing.assert_array_equal(u.t_ns, v.t_ns)
                np.testing.assert_array_equal(u.xy, v.xy)
                np.testing.assert_array_equal(u.heading, v.heading)
            assert [(c.t_ns, dict(c.readings)) for c in x.scans] == [(c.t_ns, dict(c.readings)) for c in y.scans]
            assert x.landmarks == y.landmarks


def test_uwb_crowd_walks_carry_the_heading() -> None:
    from graphslam.sim.uwb.scenarios import CrowdUwb, simulate_crowd

    run = simulate_crowd(0, CrowdUwb(n_walkers=2, duration_min=(0.5, 0.5), n_anchors=2))
    for s in run.survey:
        assert s.heading is not None
        np.testing.assert_array_equal(s.heading.t_ns, s.steps.t_ns[1:])


def test_offsets_follow_the_model() -> None:
    """Per walk: N(0, 5 deg) or, 5 % of walks, a turned phone at +-U(30, 70) deg."""
    m = HeadingModel()
    off = np.degrees([walk_offset(m, np.random.default_rng([7, i])) for i in range(4000)])
    turned = np.abs(off) >= 25.0  # a Gaussian offset beyond 5 sigma: p ~ 6e-7 per walk
    assert 0.035 <= turned.mean() <= 0.065
    assert np.all((np.abs(off[turned]) >= 30.0) & (np.abs(off[turned]) <= 70.0))
    assert 0.3 <= (off[turned] > 0).mean() <= 0.7  # either way round
    assert 4.6 <= off[~turned].std() <= 5.4 and abs(off[~turned].mean()) < 0.3
    assert walk_offset(HeadingModel(turned_prob=1.0), np.random.default_rng(0)) != 0.0
    np.testing.assert_array_equal(walk_offset(HeadingModel(offset_sigma_deg=0.0, turned_prob=0.0),
                                              np.random.default_rng(0)), 0.0)


def test_error_is_offset_plus_distortion_plus_noise(sims: dict) -> None:
    """On every walk: mean error (distortion removed) = the walk's drawn offset, spread = the white noise;
    with the distortion left in, the spread is that of noise and distortion together."""
    m = HeadingModel()
    for name in ("paper", "crowd"):
        sim = sims[name][0]
        field = sim.building.magnetic_field
        for i, s in enumerate(sim.survey):
            assert s.ground_truth is not None
            drawn = math.degrees(walk_offset(m, _heading_rng(3, 1, i)))  # the walk's own stream (4, 1, i)
            r = _residual_deg(s)
            own = np.degrees(wrap_yaw(np.radians(r) - field.at(s.ground_truth.xy[1:])[:, 0]))
            n = len(own)
            assert abs(own.mean() - drawn) < 4 * 2.5 / math.sqrt(n), (name, s.session_id)
            assert 2.5 * 0.85 <= own.std() <= 2.5 * 1.15
            # the distortion seen along a long walk: more than the noise, at most noise + the field's 7 deg
            if n > 300:
                assert 3.5 <= r.std() <= math.hypot(2.5, 7.0) * 1.25, (name, s.session_id)


def test_distortion_is_smooth_and_shared_by_every_walk(sims: dict) -> None:
    """The field: ~7 deg std, correlated within a few metres, not beyond ~20 m; two walks at one place
    see the same distortion (the museum's repeated routes)."""
    field = build_building("paper", seed=5).magnetic_field
    assert field is not None
    rng = np.random.default_rng(1)
    p = rng.uniform([0, 0], [120, 60], (4000, 2))
    ang = rng.uniform(0, 2 * np.pi, 4000)

    def corr(r: float) -> float:
        q = p + r * np.column_stack([np.cos(ang), np.sin(ang)])
        return float(np.corrcoef(field.at(p)[:, 0], field.at(q)[:, 0])[0, 1])

    assert 4.5 <= np.degrees(field.at(p)[:, 0].std()) <= 9.5
    assert corr(1.0) > 0.9 and 0.15 < corr(7.0) < 0.6 and abs(corr(25.0)) < 0.2
    # two walks of one route (repetitions 1 and 2), each less its drawn offset (stream (4, 1, r, k)):
    # at steps within 0.7 m of each other they see the same distortion
    sim = simulate("museum", seed=4, size=0.5)
    pa, pb = [], []
    for r, route in enumerate(sim.building.routes):
        a, b = (sim.survey[f"museum-s4-{route.name}-rep0{k + 1}"] for k in (0, 1))
        ra, rb = (_residual_deg(s) - math.degrees(walk_offset(HeadingModel(), _heading_rng(4, 1, r, k)))
                  for k, s in enumerate((a, b)))
        xa, xb = a.ground_truth.xy[1:], b.ground_truth.xy[1:]  # type: ignore[union-attr]
        i, j = np.nonzero(np.linalg.norm(xa[:, None] - xb[None], axis=2) < 0.7)
        pa.append(ra[i])
        pb.append(rb[j])
    ra, rb = np.concatenate(pa), np.concatenate(pb)
    assert len(ra) > 500
    # the same field: corr ~ 7^2 / (7^2 + 2.5^2) = 0.89, differences ~ the two walks' noise (3.5 deg);
    # a field of its own per walk: corr ~ 0, differences ~ 10.5 deg
    assert np.corrcoef(ra, rb)[0, 1] > 0.75
    assert (ra - rb).std() < 4.5


def test_heading_round_trips_through_mcap(tmp_path: Path, sims: dict) -> None:
    s = sims["corridor"][0].survey.sessions[0]
    assert s.heading is not None
    back = read_session(write_session(s, tmp_path / "w.mcap"))
    assert back.heading is not None
    np.testing.assert_array_equal(back.heading.t_ns, s.heading.t_ns)
    np.testing.assert_allclose(wrap_yaw(back.heading.yaw - s.heading.yaw), 0.0, atol=1e-12)
    no = read_session(write_session(sims["corridor"][1].survey.sessions[0], tmp_path / "n.mcap"))
    assert no.heading is None


def test_cli_simulate_no_heading(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    main(["simulate", "corridor", "--out", str(tmp_path / "on"), "--size", "0.25"])
    main(["simulate", "corridor", "--out", str(tmp_path / "off"), "--size", "0.25", "--no-heading"])
    capsys.readouterr()
    on = read_survey(sorted((tmp_path / "on").glob("*.mcap")))
    off = read_survey(sorted((tmp_path / "off").glob("*.mcap")))
    assert len(on) == len(off) == 3
    for x, y in zip(on, off):
        assert x.heading is not None and len(x.heading) == len(x.steps) - 1 and y.heading is None
        np.testing.assert_array_equal(x.steps.xy, y.steps.xy)
    assert json.loads((tmp_path / "on" / "building.json").read_text())["building"]["earth_from_site_deg"] == 12.0
    assert json.loads((tmp_path / "off" / "building.json").read_text())["building"]["earth_from_site_deg"] is None
    main(["simulate", "--help"])
    assert "--no-heading" in capsys.readouterr().out


def test_bad_heading_models_raise() -> None:
    for bad in (
        {"offset_sigma_deg": -1.0}, {"noise_sigma_deg": -0.1}, {"distortion_sigma_deg": -2.0},
        {"turned_prob": 1.5}, {"turned_deg": (70.0, 30.0)}, {"turned_deg": (30.0, 200.0)},
        {"distortion_corr_m": 0.0}, {"earth_from_site_deg": math.nan},
    ):
        with pytest.raises(ConfigError):
            HeadingModel(**bad)  # type: ignore[arg-type]
    b = build_building("corridor", seed=0)
    sim = simulate("corridor", seed=0, size=0.1)
    with pytest.raises(SimulationError):
        phone_heading(sim.survey.sessions[0].ground_truth, OFF, b.magnetic_field, np.random.default_rng(0))  # type: ignore[arg-type]
    # no distortion, no noise, no offset: the yaw is the true heading turned by the site's rotation
    exact = dataclasses.replace(HeadingModel(), offset_sigma_deg=0.0, turned_prob=0.0, noise_sigma_deg=0.0,
                                distortion_sigma_deg=0.0, earth_from_site_deg=-30.0)
    gt = sim.survey.sessions[0].ground_truth
    assert gt is not None
    h = phone_heading(gt, exact, ShadowingField((0.0, 0.0), 1.0, np.zeros((1, 2, 2))), np.random.default_rng(0))
    np.testing.assert_allclose(wrap_yaw(h.yaw - gt.heading[1:] + math.radians(30.0)), 0.0, atol=1e-12)
