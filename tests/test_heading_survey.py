"""The phones' headings in the survey: walk rotations, heading and position priors, components,
control points (graphslam.core.survey.heading / components / control, solver unary factors)."""

from __future__ import annotations

import dataclasses

import gtsam
import numpy as np
import pytest
from test_align import CFG, loop, session

from graphslam.config import load_config
from graphslam.core.radiomap.similarity import Matches
from graphslam.core.survey import solver as S
from graphslam.core.survey.align import align, build_problem, initialization, solve
from graphslam.core.survey.components import place_components
from graphslam.core.survey.control import control_ties, tie_walks
from graphslam.core.survey.heading import robust_circular_mean, walk_headings
from graphslam.core.common.geometry import se2_apply
from graphslam.core.survey.placement import GrowthParams
from graphslam.core.types import HeadingTrack, LandmarkMark, Session, Survey, wrap_angle
from graphslam.errors import SolverError

X = gtsam.symbol_shorthand.X
EARTH = np.radians(25.0)  # Earth azimuth of site +x in these tests


def with_heading(s: Session, offset: float = 0.0, noise: float = 0.0, seed: int = 0) -> Session:
    """The session with a phone heading: true site heading + EARTH + offset (+ noise), steps after the first;
    landmark ids by place (walks marking the same point share its id, as surveyed landmarks do)."""
    rng = np.random.default_rng(seed)
    gt = s.ground_truth
    yaw = wrap_angle(gt.heading[1:] + EARTH + offset + rng.normal(0, noise, len(gt) - 1))
    marks = tuple(LandmarkMark(m.t_ns, f"{m.x:.0f},{m.y:.0f}", m.x, m.y) for m in s.landmarks)
    return Session(s.session_id, s.steps, s.scans, marks, s.ground_truth, heading=HeadingTrack(gt.t_ns[1:], yaw))


def survey_with_headings(n: int = 3) -> Survey:
    return Survey(tuple(with_heading(session(f"w{k}", loop(160, 20.0 * k), 10**18 + k * 10**12), seed=k)
                        for k in range(n)))


def test_walk_rotation_is_the_heading_offset_and_ignores_a_disturbed_stretch() -> None:
    s = session("a", loop(200, 5.0), 10**18)
    rng = np.random.default_rng(4)
    gt = s.ground_truth
    yaw = gt.heading[1:] + EARTH + rng.normal(0, np.radians(2.0), len(gt) - 1)
    yaw[50:70] += np.radians(60.0)  # steel: a stretch bent by 60 degrees
    h = Session("a", s.steps, s.scans, heading=HeadingTrack(gt.t_ns[1:], wrap_angle(yaw)))
    wh = walk_headings(Survey((h, session("b", loop(50, 0.0), 2 * 10**18))), sigma_floor_rad=np.radians(6))
    true_rot = wrap_angle(gt.heading[0] + EARTH)  # the walk's frame starts along its first true heading
    assert abs(wrap_angle(wh.rotation[0] - true_rot)) < np.radians(1.0)
    assert np.isnan(wh.rotation[1]) and not wh.complete  # the second walk has no heading
    assert wh.sigma[0] >= np.radians(6)  # never below the floor (the phone's pointing offset)
    # the plain circular mean is pulled by the bent stretch; the robust one is not
    plain = np.angle(np.exp(1j * (yaw - gt.heading[1:])).mean())
    assert abs(wrap_angle(plain - EARTH)) > np.radians(4.0)
    mu, spread = robust_circular_mean(wrap_angle(yaw - gt.heading[1:]), np.radians(10))
    assert abs(wrap_angle(mu - EARTH)) < np.radians(1.0) and spread < np.radians(4.0)


def test_auto_takes_the_heading_only_when_every_walk_has_one() -> None:
    sv = survey_with_headings(2)
    assert initialization(CFG, sv) == "heading"
    off = load_config(overrides={"heading": {"enabled": False}})
    assert initialization(off, sv) == "registration"
    mixed = Survey((sv.sessions[0], session("plain", loop(80, 0.0), 3 * 10**18)))
    assert initialization(CFG, mixed) == "registration"
    forced = load_config(overrides={"optimizer": {"initialization": "heading"}})
    with pytest.raises(SolverError, match="needs /phone/heading on every walk"):
        build_problem(mixed, forced)


def test_unary_factors_equal_gtsams_and_their_jacobians_the_numerical_ones() -> None:
    rng = np.random.default_rng(7)
    x = rng.normal(size=(20, 3)) * [5, 5, 2]
    target, sig = rng.uniform(-3, 3, 20), rng.uniform(0.05, 0.3, 20)
    xy, psig = rng.normal(size=(20, 2)) * 5, rng.uniform(0.2, 1.0, 20)
    rh = S.heading_residuals(x, target, sig)
    rp = S.point_residuals(x, xy, psig)
    for k in range(20):
        v = gtsam.Values()
        v.insert(X(0), gtsam.Pose2(*x[k]))
        fh = gtsam.PoseRotationPrior2D(X(0), gtsam.Rot2(target[k]), gtsam.noiseModel.Isotropic.Sigma(1, sig[k]))
        fp = gtsam.PoseTranslationPrior2D(X(0), gtsam.Pose2(*xy[k], 0.0), gtsam.noiseModel.Isotropic.Sigma(2, psig[k]))
        assert 0.5 * rh[k] ** 2 == pytest.approx(fh.error(v), rel=1e-9)
        assert 0.5 * rp[k] @ rp[k] == pytest.approx(fp.error(v), rel=1e-9)
    h = 1e-6
    for i in range(3):
        dx = np.zeros(3)
        dx[i] = h
        num_h = (S.heading_residuals(x + dx, target, sig) - S.heading_residuals(x - dx, target, sig)) / (2 * h)
        num_p = (S.point_residuals(x + dx, xy, psig) - S.point_residuals(x - dx, xy, psig)) / (2 * h)
        np.testing.assert_allclose(num_h, (1.0 / sig) * (i == 2), atol=1e-6)
        np.testing.assert_allclose(num_p, (np.eye(2)[:, i] if i < 2 else np.zeros(2))[None, :] / psig[:, None], atol=1e-6)


def test_both_back_ends_reach_the_same_minimum_with_heading_priors() -> None:
    sv = survey_with_headings(3)
    sols = []
    for solver in ("cholmod", "gtsam"):
        # converged tightly: with a loose heading prior the minimum is flat, and each back end stops elsewhere on it
        opt = CFG.optimizer.model_copy(update={"solver": solver, "relative_error_tol": 1e-9, "shape_tol_m": 0.0})
        cfg = CFG.model_copy(update={"optimizer": opt})
        sols.append(solve(build_problem(sv, cfg), cfg))
    assert sols[0].frame == "earth"
    assert abs(sols[0].final_error - sols[1].final_error) <= 1e-3 * max(1.0, sols[1].final_error)
    for sid in sols[0].tracks:
        np.testing.assert_allclose(sols[0].tracks[sid].xy, sols[1].tracks[sid].xy, atol=0.05)


def test_a_heading_survey_comes_out_north_up() -> None:
    sv = survey_with_headings(3)
    al = align(sv, CFG)
    assert al.frame == "earth" and len(al.components) == 1 and len(al.tracks) == 3
    for s in sv:
        # east/north: the aligned heading is the true site heading turned by EARTH (no fitted rotation)
        d = wrap_angle(al.tracks[s.session_id].heading - s.ground_truth.heading - EARTH)
        assert np.degrees(np.abs(np.angle(np.exp(1j * d).mean()))) < 2.0


def _two_clusters() -> tuple[np.ndarray, np.ndarray, Matches]:
    """Walks 0, 1 see the same places (walk 1 shifted by (5, -3) in its own frame); walk 2 matches nothing."""
    rng = np.random.default_rng(0)
    base = rng.uniform(0, 30, size=(40, 2))
    xy = np.concatenate([base, base - [5.0, -3.0], rng.uniform(0, 30, size=(40, 2))])
    sess = np.repeat([0, 1, 2], 40)
    i = np.arange(40)
    return sess, xy, Matches(i, i + 40, np.full(40, 0.95))


def test_components_keep_unlinked_walks_apart() -> None:
    sess, xy, m = _two_clusters()
    cp = place_components(3, sess, xy, m, GrowthParams(rotation_window_deg=9.0, min_margin=1.0),
                          rotation=np.zeros(3), rotation_sigma=np.full(3, 0.1))
    assert cp.n_components == 2
    assert cp.component[0] == cp.component[1] == 0 and cp.component[2] == 1
    # walk 1 lands on walk 0's places
    np.testing.assert_allclose(se2_apply(cp.transforms[1], xy[40:80]), se2_apply(cp.transforms[0], xy[:40]), atol=0.5)
    assert "no WiFi matches" in cp.reasons[1]


def test_components_respect_the_margin() -> None:
    sess, xy, m = _two_clusters()
    weak = Matches(m.i[:4], m.j[:4], m.similarity[:4])  # four matches: a margin below 1 vote
    cp = place_components(3, sess, xy, weak, GrowthParams(rotation_window_deg=9.0, min_margin=3.0),
                          rotation=np.zeros(3), rotation_sigma=np.full(3, 0.1))
    assert cp.n_components == 3  # nothing is forced together
    assert "ambiguous" in " ".join(cp.reasons.values())


def test_control_points_tie_walks_in_the_site_frame() -> None:
    sv = survey_with_headings(3)
    # two landmark ids of walk 0 and one of walk 1 are named control points
    marks = {m.landmark_id: (m.x, m.y) for m in sv.sessions[0].landmarks[:2]}
    marks[sv.sessions[1].landmarks[1].landmark_id] = (sv.sessions[1].landmarks[1].x, sv.sessions[1].landmarks[1].y)
    al = align(sv, CFG, control_points=marks)
    assert al.frame == "site"
    for s in sv:
        if s.session_id in al.components[0].walks:
            err = np.linalg.norm(al.tracks[s.session_id].xy - s.ground_truth.xy, axis=1)
            assert err.mean() < 1.0, s.session_id  # the site frame itself: no fit
    assert {"w0", "w1"} <= set(al.components[0].walks)


def test_tie_walks_finds_the_site_rotation_from_a_walk_with_two_points() -> None:
    sv = survey_with_headings(2)
    offsets = np.concatenate([[0], np.cumsum([len(s.steps) for s in sv])])
    lm0 = sv.sessions[0].landmarks
    cps = {lm0[0].landmark_id: (lm0[0].x, lm0[0].y), lm0[3].landmark_id: (lm0[3].x, lm0[3].y)}
    ties = control_ties(sv, cps, offsets)
    assert len(ties) >= 2 and 0 in ties.session
    dr = np.concatenate([s.steps.xyh for s in sv])
    node_sess = np.repeat(np.arange(2), [len(s.steps) for s in sv])
    wh = walk_headings(sv, sigma_floor_rad=0.1)
    tp = tie_walks(ties, dr, node_sess, wh.rotation)
    assert tp.rotation_fixed and set(tp.transforms) == set(ties.session.tolist())
    assert abs(wrap_angle(tp.site_from_earth + EARTH)) < np.radians(1.0)  # site = earth - EARTH
    placed = se2_apply(tp.transforms[0], sv.sessions[0].steps.xy)
    assert np.linalg.norm(placed - sv.sessions[0].ground_truth.xy, axis=1).max() < 0.5


def test_control_points_without_headings_tie_a_walk_by_two_marks(caplog: pytest.LogCaptureFixture) -> None:
    """Walks without headings (a foot-mounted module's): a walk marking two control points apart is tied
    rigidly in the site frame, the others join by WiFi over every rotation; one mark alone cannot place a
    walk (its rotation is unknown), and the survey says so."""
    sv = survey_with_headings(3)
    plain = Survey(tuple(dataclasses.replace(s, heading=None) for s in sv.sessions))
    lm0 = plain.sessions[0].landmarks
    one = {lm0[0].landmark_id: (lm0[0].x, lm0[0].y)}
    with pytest.raises(SolverError, match="marks two of them at least 5 m apart"):
        align(plain, CFG, control_points=one)
    two = {**one, lm0[3].landmark_id: (lm0[3].x, lm0[3].y)}
    caplog.clear()
    al = align(plain, CFG, control_points=two)
    assert "east/north" not in caplog.text  # no heading, so no rotation is taken from one
    assert al.frame == "site" and al.placement is not None and al.placement.method == "control_points"
    assert al.site_from_earth is None and "w0" in al.components[0].walks
    for s in plain:
        if s.session_id in al.components[0].walks:  # the site frame itself: no fit
            err = np.linalg.norm(al.tracks[s.session_id].xy - s.ground_truth.xy, axis=1)
            assert err.mean() < 1.5, s.session_id


def test_the_report_says_how_the_heading_placement_placed_each_walk() -> None:
    from graphslam.app.survey import build_report

    sv = survey_with_headings(3)
    al = align(sv, CFG)
    rep = build_report(sv, al, None, CFG, {})
    assert rep["registration"]["method"] == "heading"
    assert all({"support", "margin", "consistency", "component"} <= set(w) for w in rep["walks"])
    assert sum(w["margin"] is None for w in rep["walks"]) == 1  # the seed: no runner-up
