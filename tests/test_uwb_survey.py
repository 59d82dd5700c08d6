"""UWB in the survey: native range factors (cost and Jacobians vs numerical derivatives), the
hook in align (site frame from anchors, walks joined by peer ranges), NLOS rejection, and the
survey job's outputs. Ground truth only scores."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import gtsam
import numpy as np
import pytest

from graphslam.config import GraphSlamConfig, MagneticConfig, UwbConfig
from graphslam.core.survey.align import align, build_problem
from graphslam.core.survey.evaluate import evaluate, trajectory_errors
from graphslam.core.types import PoseTrack, Survey
from graphslam.core.uwb.factors import L, X, SurveyRanges, anchor_range_factor, peer_range_factor, range_residuals

CFG = UwbConfig()


def _numerical_jacobian(f: gtsam.NonlinearFactor, v: gtsam.Values, key: int, dim: int) -> np.ndarray:
    J = np.zeros((1, dim))
    for i in range(dim):
        d = np.zeros(dim)
        d[i] = 1e-6
        vp, vm = gtsam.Values(v), gtsam.Values(v)
        if gtsam.Symbol(key).chr() == ord("x"):
            vp.update(key, v.atPose2(key).retract(d))
            vm.update(key, v.atPose2(key).retract(-d))
        else:
            vp.update(key, v.atPoint2(key) + d)
            vm.update(key, v.atPoint2(key) - d)
        J[0, i] = (f.unwhitenedError(vp)[0] - f.unwhitenedError(vm)[0]) / 2e-6
    return J


def test_range_factors_cost_and_jacobians() -> None:
    sigma = 0.1
    off = np.array([0.3, -0.1])
    v = gtsam.Values()
    v.insert(X(0), gtsam.Pose2(1.0, 2.0, 0.7))
    v.insert(X(1), gtsam.Pose2(4.0, -1.0, -2.0))
    v.insert(L(0), np.array([6.0, 5.0]))
    antenna = np.array([1.0, 2.0]) + np.array([[np.cos(0.7), -np.sin(0.7)], [np.sin(0.7), np.cos(0.7)]]) @ off
    for f, other in (
        (anchor_range_factor(0, 0, 6.0, sigma, off, CFG), np.array([6.0, 5.0])),
        (peer_range_factor(0, 1, 4.5, sigma, off, CFG), np.array([4.0, -1.0])),
    ):
        d = float(np.linalg.norm(antenna - other))
        z = 6.0 if other[0] == 6.0 else 4.5
        assert f.unwhitenedError(v)[0] == pytest.approx(d - z, abs=1e-9)  # GTSAM's error: h(x) - z
        # Cauchy cost, threshold k sigma: 0.5 k^2 log(1 + (e / (k sigma))^2)
        k = CFG.loss_k
        assert f.error(v) == pytest.approx(0.5 * k**2 * np.log1p(((d - z) / (k * sigma)) ** 2), rel=1e-9)
        lin = f.linearize(v)
        A, _ = lin.jacobian()
        w = 1.0 / (1.0 + ((d - z) / (k * sigma)) ** 2)  # IRLS weight of the robust loss
        keys = list(f.keys())
        dims = [3 if gtsam.Symbol(key).chr() == ord("x") else 2 for key in keys]
        num = np.hstack([_numerical_jacobian(f, v, key, dim) for key, dim in zip(keys, dims)])
        np.testing.assert_allclose(A, np.sqrt(w) * num / sigma, atol=1e-5)


def test_range_residuals_match_the_factors() -> None:
    rng = np.random.default_rng(0)
    xyh = np.column_stack([rng.uniform(0, 20, (6, 2)), rng.uniform(-3, 3, 6)])
    sr = SurveyRanges(
        ("A1",), np.array([[5.0, 5.0]]), np.array([0, 2]), np.array([0, 0]), np.array([4.0, 7.0]), np.array([0.1, 0.1]),
        rng.normal(0, 0.2, (2, 2)), np.array([[1, 3], [4, 5]]), np.array([3.0, 9.0]), np.array([0.1, 0.1]),
        rng.normal(0, 0.2, (2, 2)),
    )
    ea, ep = range_residuals(sr, xyh)
    v = gtsam.Values()
    for i, p in enumerate(xyh):
        v.insert(X(i), gtsam.Pose2(*p))
    v.insert(L(0), sr.anchor_xy[0])
    fa = [anchor_range_factor(n, 0, r, 0.1, o, CFG) for n, r, o in zip(sr.a_node, sr.a_range, sr.a_offset)]
    fp = [peer_range_factor(a, b, r, 0.1, o, CFG) for (a, b), r, o in zip(sr.p_node, sr.p_range, sr.p_offset)]
    np.testing.assert_allclose(ea, [-f.unwhitenedError(v)[0] for f in fa], atol=1e-12)
    np.testing.assert_allclose(ep, [-f.unwhitenedError(v)[0] for f in fp], atol=1e-12)


@pytest.fixture(scope="module")
def crowd():  # type: ignore[no-untyped-def]
    """4 walkers, 2-2.5 min, at once; 4 anchors; the last walker records no WiFi."""
    from graphslam.sim.uwb.scenarios import CrowdUwb, simulate_crowd

    return simulate_crowd(1, CrowdUwb(n_walkers=4, duration_min=(2.0, 2.5)))


def test_with_anchors_the_survey_comes_out_in_the_site_frame(crowd) -> None:  # type: ignore[no-untyped-def]
    survey = crowd.survey
    al = align(survey, GraphSlamConfig())
    assert al.frame == "site" and set(al.tracks) == {s.session_id for s in survey}
    site = trajectory_errors(al.tracks, survey, np.zeros(3)).mean_m  # no fit at all
    assert site < 0.35
    # WiFi alone (the simulated walks carry the magnetic field too: off here)
    wifi = align(survey, GraphSlamConfig(uwb=UwbConfig(enabled=False), magnetic=MagneticConfig(enabled=False)))
    # no WiFi, no WiFi edge: WiFi alone cannot place it in the main map (it stands apart, or unaligned)
    assert wifi.component_of().get(crowd.no_wifi[0], -1) != 0
    assert evaluate(wifi.main_tracks(), survey).steps.mean_m > 2 * site
    assert al.uwb is not None and al.uwb.anchor_ranges > 100 and al.uwb.peer_ranges > 0


def test_without_anchors_peer_ranges_join_a_walk_that_shares_no_wifi_edge(crowd) -> None:  # type: ignore[no-untyped-def]
    survey = Survey(tuple(replace(s, uwb_anchors={}, uwb_ranges=_peers_only(s.uwb_ranges)) for s in crowd.survey))
    lone = crowd.no_wifi[0]
    wifi = align(survey, GraphSlamConfig(uwb=UwbConfig(enabled=False)))
    assert wifi.component_of().get(lone, -1) != 0  # WiFi alone: not in the main map
    al = align(survey, GraphSlamConfig())
    assert al.frame == "aligned" and lone in al.tracks and al.uwb is not None and al.uwb.placed_by[lone] == "ranges"
    ev = evaluate(al.tracks, survey)
    T = np.array(ev.site_from_aligned)
    assert trajectory_errors({lone: al.tracks[lone]}, survey, T).mean_m < 1.5


def _peers_only(r):  # type: ignore[no-untyped-def]
    from graphslam.core.types import UwbRanges

    keep = ~r.is_anchor
    return UwbRanges(r.t_ns[keep], tuple(np.array(r.responder_id, dtype=object)[keep]), r.is_anchor[keep], r.range_m[keep])


def test_nlos_ranges_are_rejected_one_sided(crowd) -> None:  # type: ignore[no-untyped-def]
    """A quarter of the anchor ranges made 0.5-2 m too long: the UWB-only solve drops them (and
    almost nothing else), and the survey stays close to the clean one."""
    from graphslam.core.types import UwbRanges

    rng = np.random.default_rng(5)
    biased, sessions = {}, []
    for s in crowd.survey:
        r = s.uwb_ranges
        hit = r.is_anchor & (rng.random(len(r)) < 0.25)
        biased[s.session_id] = hit
        rr = r.range_m + np.where(hit, rng.uniform(0.5, 2.0, len(r)), 0.0)
        sessions.append(replace(s, uwb_ranges=UwbRanges(r.t_ns, r.responder_id, r.is_anchor, rr)))
    survey = Survey(tuple(sessions))
    cfg = GraphSlamConfig()
    pb = build_problem(survey, cfg)
    assert pb.uwb is not None
    n_hit = sum(int(h.sum()) for h in biased.values())
    dropped = pb.uwb.ranges.dropped["nlos_anchor"]
    assert 0.8 * n_hit <= dropped <= 1.3 * n_hit
    clean = trajectory_errors(align(crowd.survey, cfg).tracks, crowd.survey, np.zeros(3)).mean_m
    nlos = trajectory_errors(align(survey, cfg).tracks, survey, np.zeros(3)).mean_m
    assert nlos < 1.5 * clean + 0.05


def test_ground_truth_never_reaches_the_uwb_solver(crowd) -> None:  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(9)
    garbage = Survey(tuple(
        replace(s, ground_truth=PoseTrack(s.ground_truth.t_ns, rng.normal(0, 50, s.ground_truth.xy.shape), s.ground_truth.heading),
                landmarks=())
        for s in crowd.survey
    ))
    a = align(crowd.survey, GraphSlamConfig())
    b = align(garbage, GraphSlamConfig())
    np.testing.assert_array_equal(a.node_xyh, b.node_xyh)


def test_survey_job_writes_site_frame_outputs(crowd, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    from mcap.reader import make_reader

    from graphslam.cli import main

    crowd.write(tmp_path / "rec")
    main(["survey", str(tmp_path / "rec"), "--out", str(tmp_path / "out"), "--no-progress"])
    rep = json.loads((tmp_path / "out" / "report.json").read_text())
    assert rep["uwb"]["frame"] == "site" and rep["uwb"]["anchors"] == ["A1", "A2", "A3", "A4"]
    assert rep["evaluation"]["steps_site_frame"]["mean_m"] < 0.35
    with open(tmp_path / "out" / "aligned.mcap", "rb") as fh:
        _, _, msg = next(make_reader(fh).iter_messages())
    assert json.loads(msg.data)["frame_id"] == "site"


def test_uwb_ranges_and_a_reference_map_are_refused_together(crowd) -> None:  # type: ignore[no-untyped-def]
    """The ranges place the walks themselves (and with anchors fix the site frame): a reference map or
    control points as well are refused with their reason, not silently dropped; with UWB off the
    reference is used."""
    from graphslam.core.radiomap.radiomap import RadioMap
    from graphslam.errors import SolverError

    survey = crowd.survey
    s = survey.sessions[0]
    t = s.ground_truth.t_ns
    scans = [sc for sc in s.scans if sc.readings]
    xy = np.array([s.ground_truth.xy[int(np.argmin(np.abs(t - sc.t_ns)))] for sc in scans])
    ref = RadioMap.from_scans([dict(sc.readings) for sc in scans], xy, session_ids="reference",
                              t_ns=[sc.t_ns for sc in scans], frame="site")
    with pytest.raises(SolverError, match="a reference map and UWB ranges"):
        align(survey, GraphSlamConfig(), reference=ref)
    mark = s.landmarks[0]
    with pytest.raises(SolverError, match="control points and UWB ranges"):
        align(survey, GraphSlamConfig(), control_points={mark.landmark_id: (mark.x, mark.y)})
    assert align(survey, GraphSlamConfig(uwb=UwbConfig(enabled=False)), reference=ref).frame == "site"
