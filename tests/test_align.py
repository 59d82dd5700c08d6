"""Alignment end to end: recovered poses, unaligned walks, ground truth isolation, outputs."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import T0
from mcap.reader import make_reader

from graphslam.cli import main
from graphslam.config import load_config
from graphslam.core.survey.align import align
from graphslam.core.common.geometry import fit_se2, se2_apply
from graphslam.core.types import LandmarkMark, PoseTrack, Scan, Session, Survey
from graphslam.io.mcap_writer import write_session

APS = np.array([[x, y] for x in (-5.0, 15.0, 35.0, 55.0) for y in (-12.0, 8.0, 28.0)])


def rss(xy: np.ndarray) -> list[dict[str, float]]:
    """Noiseless log-distance path loss (P0 = -35 dBm, gamma = 2.2), 12 APs on a grid."""
    d = np.linalg.norm(xy[:, None, :] - APS[None, :, :], axis=2)
    r = -35.0 - 22.0 * np.log10(np.maximum(d, 0.5))
    return [{f"ap{j}": float(v) for j, v in enumerate(row) if v > -95} for row in r]


def loop(n: int, phase: float) -> np.ndarray:
    """True poses on a 50 m x 20 m rectangle loop, 0.7 m steps, starting ``phase`` metres in."""
    perim = np.array([[0, 0], [50, 0], [50, 20], [0, 20], [0, 0]], float)
    seg = np.linalg.norm(np.diff(perim, axis=0), axis=1)
    s = (phase + 0.7 * np.arange(n)) % seg.sum()
    k = np.searchsorted(np.cumsum(seg), s, side="right")
    start = np.concatenate([[0], np.cumsum(seg)])[k]
    dirn = np.diff(perim, axis=0)[k] / seg[k, None]
    xy = perim[k] + dirn * (s - start)[:, None]
    h = np.arctan2(dirn[:, 1], dirn[:, 0])
    return np.column_stack([xy, h])


def to_own_frame(true: np.ndarray) -> np.ndarray:
    """Dead reckoning without noise: the true path expressed in the frame of its first pose."""
    x0, y0, h0 = true[0]
    c, s = np.cos(-h0), np.sin(-h0)
    d = true[:, :2] - [x0, y0]
    return np.column_stack([c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1], true[:, 2] - h0])


def session(sid: str, true: np.ndarray, t0: int, marks: bool = True) -> Session:
    n = len(true)
    t = t0 + np.arange(n, dtype=np.int64) * 500_000_000
    dr = to_own_frame(true)
    scans = tuple(Scan(int(t[i]) + 1, r) for i, r in zip(range(0, n, 2), rss(true[::2, :2])))
    lm = tuple(LandmarkMark(int(t[i]), f"L{i}", float(true[i, 0]), float(true[i, 1])) for i in range(0, n, 25)) if marks else ()
    return Session(sid, PoseTrack.from_xyh(t, dr), scans, lm, PoseTrack.from_xyh(t, true))


def two_walks() -> Survey:
    return Survey((session("a", loop(300, 0.0), T0), session("b", loop(260, 37.0), T0 + 10**12)))


CFG = load_config(None, {"wifi": {"d_min_m": 0.5}})


def test_noiseless_two_walk_survey_recovers_true_relative_pose() -> None:
    survey = two_walks()
    al = align(survey, CFG)
    assert set(al.tracks) == {"a", "b"} and not al.unaligned
    # a's first pose is the reference: fixed at its own origin
    np.testing.assert_allclose(al.tracks["a"].xyh[0], [0, 0, 0], atol=1e-6)
    # true pose of b's start in a's frame
    a_true, b_true = survey["a"].ground_truth, survey["b"].ground_truth
    T_site_from_a = np.array([a_true.xy[0, 0], a_true.xy[0, 1], a_true.heading[0]])
    expected = se2_apply(np.array([0, 0, -T_site_from_a[2]]), (b_true.xy[:1] - a_true.xy[:1]))[0]
    got = al.tracks["b"].xy[0]
    assert np.linalg.norm(got - expected) < 0.5, (got, expected)
    dh = np.angle(np.exp(1j * (al.tracks["b"].heading[0] - (b_true.heading[0] - a_true.heading[0]))))
    assert abs(np.degrees(dh)) < 1.0
    # every step of both walks, after the one rigid site fit
    est = np.concatenate([al.tracks["a"].xy, al.tracks["b"].xy])
    true = np.concatenate([a_true.xy, b_true.xy])
    T = fit_se2(est, true)
    assert np.linalg.norm(se2_apply(T, est) - true, axis=1).max() < 0.6


def test_origin_start_also_converges_on_overlapping_loops() -> None:
    cfg = load_config(None, {"wifi": {"d_min_m": 0.5}, "optimizer": {"initialization": "origin"}})
    survey = two_walks()
    al = align(survey, cfg)
    est = np.concatenate([al.tracks["a"].xy, al.tracks["b"].xy])
    true = np.concatenate([survey["a"].ground_truth.xy, survey["b"].ground_truth.xy])
    T = fit_se2(est, true)
    assert np.median(np.linalg.norm(se2_apply(T, est) - true, axis=1)) < 1.0


def test_walk_without_common_aps_is_reported_unaligned() -> None:
    a, b = two_walks().sessions
    t = b.steps.t_ns
    alien = Session("c", b.steps, tuple(Scan(int(t[i]) + 1, {"zz:1": -50.0, "zz:2": -60.0}) for i in range(0, len(t), 2)))
    al = align(Survey((a, b, alien)), CFG)
    assert "c" not in al.tracks and "c" in al.unaligned and "registration" in al.unaligned["c"]
    assert np.isnan(al.node_xyh[al.fingerprints.offsets[2] :]).all()


def test_registration_its_loops_contradict_leaves_walks_unaligned(monkeypatch: pytest.MonkeyPatch) -> None:
    import graphslam.core.survey.align as align_mod
    from graphslam.core.survey.initialise import MIN_LOOPS_TO_JUDGE, Placement

    def contradicted(n_sessions: int, reference: int, *args: object, **kwargs: object) -> Placement:
        # every walk placed (at the origin), but only 1 of the loops agrees with the tree
        return Placement(
            np.zeros((n_sessions, 3)), np.ones(n_sessions, bool), np.full(n_sessions, 5, np.int64),
            np.where(np.arange(n_sessions) == reference, -1, reference), loops=MIN_LOOPS_TO_JUDGE, loops_consistent=1,
        )

    monkeypatch.setattr(align_mod, "register_walks", contradicted)
    al = align(two_walks(), CFG)
    assert set(al.tracks) == {"a"}  # the reference walk only
    assert "registration unreliable: 1 of 10 loops" in al.unaligned["b"]
    assert np.isnan(al.node_xyh[al.fingerprints.offsets[1] :]).all()
    kept = align(two_walks(), load_config(None, {"wifi": {"d_min_m": 0.5}, "optimizer": {"unreliable_registration": "keep"}}))
    assert set(kept.tracks) == {"a", "b"} and not kept.unaligned


def test_ground_truth_never_reaches_the_solver() -> None:
    survey = two_walks()
    garbage = Survey(
        tuple(
            replace(
                s,
                landmarks=(LandmarkMark(int(s.steps.t_ns[0]), "X", 1e6, -1e6),),
                ground_truth=PoseTrack(s.steps.t_ns, s.steps.xy * 0 + 123.0, s.steps.heading * 0),
            )
            for s in survey
        )
    )
    a1, a2 = align(survey, CFG), align(garbage, CFG)
    np.testing.assert_array_equal(a1.node_xyh, a2.node_xyh)


def test_reference_session_is_configurable() -> None:
    cfg = load_config(None, {"wifi": {"d_min_m": 0.5}, "optimizer": {"reference_session": "b"}})
    al = align(two_walks(), cfg)
    assert al.reference == "b"
    np.testing.assert_allclose(al.tracks["b"].xyh[0], [0, 0, 0], atol=1e-6)
    bad = load_config(None, {"optimizer": {"reference_session": "nope"}})
    with pytest.raises(Exception, match="reference session 'nope'"):
        align(two_walks(), bad)


def test_survey_cli_writes_every_output(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    for s in two_walks():
        write_session(s, tmp_path / "in" / f"{s.session_id}.mcap")
    cfg_file = tmp_path / "c.yaml"
    cfg_file.write_text("wifi:\n  d_min_m: 0.5\n")
    out = tmp_path / "out"
    main(["survey", str(tmp_path / "in"), "--out", str(out), "--config", str(cfg_file), "--no-progress"])
    printed = capsys.readouterr().out
    assert printed.startswith("main map: 2 of 2 walks; 0 in 0 other components; 0 unaligned; frame aligned")
    lines = (out / "trajectories.csv").read_text().splitlines()
    assert lines[0] == "session_id,t_ns,x,y,heading,component,frame" and len(lines) == 1 + 300 + 260
    report = json.loads((out / "report.json").read_text())
    # the summary's edge counts are the report's: those in the graph, of those proposed
    in_graph = sum(report["edges"]["wifi_states"].values())
    assert f"{in_graph:,} of {report['edges']['wifi']:,} WiFi edges in the graph" in printed
    assert report["aligned_sessions"] == 2 and report["edges"]["wifi"] > 0
    assert report["optimizer"]["final_error"] < report["optimizer"]["initial_error"]
    assert report["evaluation"]["landmarks"]["mean_m"] < 0.5
    # two walks: one tree edge, no loop to check the registration with
    assert report["registration"] == {
        "method": "registration", "placed": 2, "loops": 0, "loops_consistent": 0, "loop_consistency": None,
        "reliable": None,
    }
    assert {"associate", "edges", "optimise"} <= {k.split(".")[-1] for k in report["timings_s"]}
    assert load_config(out / "config.yaml").wifi.d_min_m == 0.5
    assert yaml.safe_load((out / "config.yaml").read_text()) == load_config(cfg_file).model_dump(mode="json")
    with open(out / "aligned.mcap", "rb") as fh:
        topics = {c.topic for c in make_reader(fh).get_summary().channels.values()}
    assert topics == {"/aligned/a", "/aligned/b"}
    assert not [p for p in out.iterdir() if p.name.startswith(".")], "staging files left behind"


def test_survey_bad_input_writes_nothing(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    write_session(two_walks().sessions[0], tmp_path / "in" / "a.mcap")
    (tmp_path / "in" / "b.mcap").write_bytes(b"\x89MCAP0\r\n" + b"\x00" * 50)  # magic, then garbage
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as e:
        main(["survey", str(tmp_path / "in"), "--out", str(out), "--no-progress"])
    assert e.value.code == 2
    assert "b.mcap" in capsys.readouterr().err
    assert not out.exists() or not any(out.iterdir())


def test_unknown_config_key_fails_before_any_output(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    for s in two_walks():
        write_session(s, tmp_path / "in" / f"{s.session_id}.mcap")
    bad = tmp_path / "c.yaml"
    bad.write_text("optimiser:\n  max_iterations: 3\n")  # British spelling: not a key
    with pytest.raises(SystemExit) as e:
        main(["survey", str(tmp_path / "in"), "--out", str(tmp_path / "out"), "--config", str(bad)])
    assert e.value.code == 2 and "optimiser" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()



def test_evaluation_with_ground_truth_at_its_own_rate() -> None:
    survey = two_walks()
    al = align(survey, CFG)
    full = evaluate_all(al, survey)
    half = Survey(
        tuple(
            replace(s, ground_truth=PoseTrack(s.ground_truth.t_ns[::2], s.ground_truth.xy[::2], s.ground_truth.heading[::2]))
            for s in survey
        )
    )
    ev = evaluate_all(al, half)
    # straight segments interpolate exactly; only the corners differ
    assert abs(ev.steps.mean_m - full.steps.mean_m) < 0.05
    assert abs(ev.heading_mean_deg - full.heading_mean_deg) < 1.0


def evaluate_all(al, survey):  # type: ignore[no-untyped-def]
    from graphslam.core.survey.evaluate import evaluate

    return evaluate(al.tracks, survey)
