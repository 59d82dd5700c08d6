"""`graphslam survey --update`: new walks joined to a solved floor (issue 18).

A simulated crowd floor: 11 walks surveyed first, a 12th walk arrives later.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from conftest import run_cli as _run

from graphslam.config import GraphSlamConfig
from graphslam.core.survey import incremental as inc
from graphslam.core.survey.align import build_problem, solve
from graphslam.core.types import HeadingTrack, Survey
from graphslam.io.csv_io import read_trajectories
from graphslam.io.mcap_writer import write_session
from graphslam.io.survey_state import STATE_FILE, read_survey_state
from graphslam.sim import simulate


@pytest.fixture(scope="module")
def floor(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """Recordings of 12 walks (old/ holds the first 11), and the 11-walk survey's output."""
    root = tmp_path_factory.mktemp("update")
    sim = simulate("crowd", seed=0, size=0.25)
    # these walks carry no headings: the registration-based update (with headings: the component
    # update, test_an_update_with_headings_keeps_the_components_apart)
    sim = replace(sim, survey=Survey(tuple(replace(s, heading=None) for s in sim.survey)))
    (root / "old").mkdir()
    (root / "all").mkdir()
    for k, s in enumerate(sim.survey):
        write_session(s, root / "all" / f"{s.session_id}.mcap")
        if k < len(sim.survey) - 1:
            shutil.copy(root / "all" / f"{s.session_id}.mcap", root / "old")
    assert _run(["survey", str(root / "old"), "--out", str(root / "prev"), "--no-progress"]) == 0
    return {"root": root, "sim": sim, "new": sim.survey.sessions[-1].session_id}


def test_update_edges_equal_a_full_recomputation(floor: dict) -> None:
    survey = floor["sim"].survey
    cfg = GraphSlamConfig()
    old = Survey(survey.sessions[:-1])
    al_old = solve(build_problem(old, cfg), cfg)
    fp = al_old.fingerprints
    prev = inc.PreviousSolution(
        tuple(s.session_id for s in old), tuple(inc.session_digest(s) for s in old),
        np.array([s.session_id in al_old.tracks for s in old]), fp.offsets, al_old.node_xyh,
        np.column_stack([fp.session[al_old.edges.i], fp.session[al_old.edges.j]]),
        np.column_stack([fp.scan[al_old.edges.i], fp.scan[al_old.edges.j]]), al_old.edges.candidates,
        al_old.reference, cfg.model_dump_json(), None,
    )
    full = build_problem(survey, cfg)
    warm = inc.warm_start(prev, survey, hops=1)
    upd = build_problem(survey, cfg, warm)
    # the same pairs, distances and candidate count as comparing every fingerprint with every other
    assert len(full.edges) > len(al_old.edges)
    np.testing.assert_array_equal(upd.edges.i, full.edges.i)
    np.testing.assert_array_equal(upd.edges.j, full.edges.j)
    np.testing.assert_allclose(upd.edges.rss_distance, full.edges.rss_distance, rtol=1e-9)
    np.testing.assert_array_equal(upd.edges.common_aps, full.edges.common_aps)
    assert upd.edges.candidates == full.edges.candidates
    # the new walk is free, and so is a neighbourhood, but not the whole floor
    n_new = len(survey.sessions[-1].steps)
    assert upd.free is not None and upd.free[-n_new:].all()
    assert n_new < upd.free.sum() < len(upd.free)
    # more hops, a larger part re-solved (monotone)
    bigger = build_problem(survey, cfg, inc.warm_start(prev, survey, hops=3))
    assert (bigger.free >= upd.free).all() and bigger.free.sum() > upd.free.sum()
    # solved walks start from their previous solution, exactly
    np.testing.assert_array_equal(upd.init_xyh[: len(al_old.node_xyh)][warm.solved[: len(al_old.node_xyh)]],
                                  al_old.node_xyh[warm.solved[: len(al_old.node_xyh)]])


def test_cli_update_rewrites_a_consistent_set(floor: dict) -> None:
    root = floor["root"]
    out = root / "upd"
    assert _run(["survey", str(root / "all"), "--out", str(out), "--update", str(root / "prev"), "--no-progress"]) == 0
    rep = json.loads((out / "report.json").read_text())
    u = rep["update"]
    assert u["mode"] == "incremental" and u["reason"] is None
    assert u["new_walks"] == [floor["new"]]
    res = u["resolved"]
    assert 0 < res["nodes"] < res["of_nodes"] == rep["nodes"]
    assert res["edges_added"] > 0
    # every output describes the 12-walk floor
    state = read_survey_state(out / STATE_FILE)
    assert floor["new"] in state.session_ids and len(state.session_ids) == 12
    tracks = read_trajectories(out / "trajectories.csv")
    assert set(tracks) == {sid for sid, ok in zip(state.session_ids, state.aligned) if ok}
    from graphslam.io.radiomap_io import read_radio_map

    rm = read_radio_map(out / "radio_map.parquet")
    assert floor["new"] in set(rm.session_ids.tolist())
    # a walk the update did not touch keeps its previous trajectory
    prev_tracks = read_trajectories(root / "prev" / "trajectories.csv")
    untouched = [sid for sid in prev_tracks if sid not in res["walks"]]
    touched = [sid for sid in res["walks"] if sid in prev_tracks]
    assert touched
    for sid in untouched:
        np.testing.assert_array_equal(tracks[sid].xy, prev_tracks[sid].xy)
    # walks it touched moved only in part: some of their steps are exactly where they were
    same = [np.mean(np.all(tracks[s].xy == prev_tracks[s].xy, axis=1)) for s in touched]
    assert max(same) > 0
    # the frame is kept: the reference walk is the previous one's
    assert rep["reference_session"] == json.loads((root / "prev" / "report.json").read_text())["reference_session"]
    ev = rep["evaluation"]["landmarks"]
    assert np.isfinite(ev["mean_m"])


def test_update_with_a_changed_configuration_or_walk_is_a_full_resolve(floor: dict, tmp_path: Path) -> None:
    root = floor["root"]
    out = tmp_path / "cfg"
    assert _run(["survey", str(root / "all"), "--out", str(out), "--update", str(root / "prev"), "--no-progress",
                 "--set", "wifi.d_min_m=2"]) == 0
    u = json.loads((out / "report.json").read_text())["update"]
    assert u["mode"] == "full" and "wifi.d_min_m 1.0 -> 2.0" in u["reason"]
    # a walk whose scans changed since the previous survey
    changed = tmp_path / "changed"
    shutil.copytree(root / "all", changed)
    s0 = floor["sim"].survey.sessions[0]
    from graphslam.core.types import Scan, Session

    scans = tuple(Scan(sc.t_ns, {b: r - 1.0 for b, r in sc.readings.items()}) for sc in s0.scans)
    write_session(Session(s0.session_id, s0.steps, scans, s0.landmarks, s0.ground_truth, s0.site, s0.floor),
                  changed / f"{s0.session_id}.mcap")
    out = tmp_path / "walk"
    assert _run(["survey", str(changed), "--out", str(out), "--update", str(root / "prev"), "--no-progress"]) == 0
    u = json.loads((out / "report.json").read_text())["update"]
    assert u["mode"] == "full" and s0.session_id in u["reason"] and "changed" in u["reason"]
    # a walk of the previous survey that is gone
    (changed / f"{s0.session_id}.mcap").unlink()
    out = tmp_path / "gone"
    assert _run(["survey", str(changed), "--out", str(out), "--update", str(root / "prev"), "--no-progress"]) == 0
    u = json.loads((out / "report.json").read_text())["update"]
    assert u["mode"] == "full" and s0.session_id in u["reason"] and "not among" in u["reason"]


def test_thread_settings_do_not_force_a_full_resolve(floor: dict, tmp_path: Path) -> None:
    """Thread counts only reorder sums: a previous output made with others is still updated."""
    root = floor["root"]
    out = tmp_path / "threads"
    assert _run(["survey", str(root / "all"), "--out", str(out), "--update", str(root / "prev"), "--no-progress",
                 "--set", "optimizer.threads=1", "--set", "optimizer.blas_threads=0"]) == 0
    u = json.loads((out / "report.json").read_text())["update"]
    assert u["mode"] == "incremental" and u["reason"] is None


def test_update_from_a_bad_previous_output_is_one_line_exit_2(
    floor: dict, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = floor["root"]
    args = ["survey", str(root / "all"), "--no-progress", "--update"]
    # not a survey output
    empty = tmp_path / "empty"
    empty.mkdir()
    assert _run(args + [str(empty), "--out", str(tmp_path / "o1")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and STATE_FILE in err and "not the output folder" in err
    # a truncated state file
    broken = tmp_path / "broken"
    shutil.copytree(root / "prev", broken)
    data = (broken / STATE_FILE).read_bytes()
    (broken / STATE_FILE).write_bytes(data[: len(data) // 2])
    assert _run(args + [str(broken), "--out", str(tmp_path / "o2")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and str(broken / STATE_FILE) in err and "unreadable" in err
    assert not (tmp_path / "o1").exists() and not (tmp_path / "o2").exists()


def test_an_update_with_headings_keeps_the_components_apart(tmp_path: Path) -> None:
    # museum: route 1 lies in a wing no other route reaches, so a survey keeps it apart; an update with
    # two new walks must place only those, keep every previous component as it was (never merge two of
    # them into one frame, as registering onto one solved body would) and re-solve locally
    sim = simulate("museum", seed=0, size=0.5)
    (tmp_path / "old").mkdir()
    (tmp_path / "all").mkdir()
    for k, s in enumerate(sim.survey):
        write_session(s, tmp_path / "all" / f"{s.session_id}.mcap")
        if k < len(sim.survey) - 2:
            shutil.copy(tmp_path / "all" / f"{s.session_id}.mcap", tmp_path / "old")
    assert _run(["survey", str(tmp_path / "old"), "--out", str(tmp_path / "prev"), "--no-progress"]) == 0
    assert _run(["survey", str(tmp_path / "all"), "--out", str(tmp_path / "new"), "--update", str(tmp_path / "prev"),
                 "--no-progress"]) == 0
    prev = json.loads((tmp_path / "prev" / "report.json").read_text())
    upd = json.loads((tmp_path / "new" / "report.json").read_text())
    assert upd["update"]["mode"] == "incremental", upd["update"]
    assert upd["frame"] == prev["frame"] == "earth"
    comp_prev = {w: c["index"] for c in prev["components"] for w in c["walks"]}
    comp_upd = {w: c["index"] for c in upd["components"] for w in c["walks"]}
    old = sorted(comp_prev)
    assert len(prev["components"]) > 1
    # the previous partition of the old walks, exactly (same groups, same indices)
    assert all(comp_upd[w] == comp_prev[w] for w in old)
    new = [w for w in comp_upd if w not in comp_prev]
    assert sorted(new) == sorted(s.session_id for s in list(sim.survey)[-2:])
    # the lone wing's walks share a component with no other route's
    wing = {comp_upd[w] for w in comp_upd if "route1-" in w}
    assert not any(comp_upd[w] in wing for w in comp_upd if "route1-" not in w)
    # walks whose solution did not move keep it exactly
    t_prev = {r[0]: r for r in _rows(tmp_path / "prev" / "trajectories.csv")}
    t_upd = {r[0]: r for r in _rows(tmp_path / "new" / "trajectories.csv")}
    assert upd["update"]["resolved"]["nodes"] < upd["update"]["resolved"]["of_nodes"]
    assert sum(t_prev[k] == t_upd[k] for k in t_prev) > 0

    # an old walk whose phone headings changed (its steps and scans did not) is solved again, in full
    s0 = sim.survey.sessions[0]
    shutil.copytree(tmp_path / "all", tmp_path / "turned")
    write_session(replace(s0, heading=HeadingTrack(s0.heading.t_ns, s0.heading.yaw + 0.5)),
                  tmp_path / "turned" / f"{s0.session_id}.mcap")
    assert _run(["survey", str(tmp_path / "turned"), "--out", str(tmp_path / "t"), "--update", str(tmp_path / "prev"),
                 "--no-progress"]) == 0
    u = json.loads((tmp_path / "t" / "report.json").read_text())["update"]
    assert u["mode"] == "full" and s0.session_id in u["reason"] and "changed" in u["reason"], u
    # a state of format 2 digested steps and scans only: its walks' headings are unknown, so in full
    old_state = tmp_path / "prev2"
    shutil.copytree(tmp_path / "prev", old_state)
    with np.load(old_state / STATE_FILE) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["format_version"] = np.int64(2)
    np.savez(old_state / STATE_FILE, **arrays)
    assert _run(["survey", str(tmp_path / "all"), "--out", str(tmp_path / "f2"), "--update", str(old_state),
                 "--no-progress"]) == 0
    u = json.loads((tmp_path / "f2" / "report.json").read_text())["update"]
    assert u["mode"] == "full" and "format 2" in u["reason"], u


def test_session_digest_covers_every_solver_input() -> None:
    s = simulate("museum", seed=0, size=0.25).survey.sessions[0]
    assert s.heading is not None and s.landmarks
    d = inc.session_digest(s)
    m0 = s.landmarks[0]
    changed = [
        replace(s, heading=HeadingTrack(s.heading.t_ns, s.heading.yaw + 1e-6)),
        replace(s, heading=None),
        replace(s, landmarks=(replace(m0, t_ns=m0.t_ns + 1), *s.landmarks[1:])),
        replace(s, landmarks=(replace(m0, landmark_id=m0.landmark_id + "x"), *s.landmarks[1:])),
        replace(s, uwb_id="tag7"),
        replace(s, magnetic=None),
    ]
    assert all(inc.session_digest(c) != d for c in changed)
    # what never reaches the solver: the marks' surveyed positions, the ground truth
    same = [replace(s, landmarks=(replace(m0, x=m0.x + 1.0), *s.landmarks[1:])), replace(s, ground_truth=None)]
    assert all(inc.session_digest(c) == d for c in same)
    # a walk with none of the optional inputs keeps the digest earlier states recorded (id, steps, scans)
    bare = replace(s, heading=None, landmarks=(), magnetic=None)
    h = hashlib.sha256()
    h.update(bare.session_id.encode())
    for a in (bare.steps.t_ns, bare.steps.xy, bare.steps.heading):
        h.update(np.ascontiguousarray(a).tobytes())
    h.update(np.array([sc.t_ns for sc in bare.scans], np.int64).tobytes())
    h.update(np.array([len(sc.readings) for sc in bare.scans], np.int64).tobytes())
    h.update("\n".join([b for sc in bare.scans for b in sc.readings]).encode())
    h.update(np.array([r for sc in bare.scans for r in sc.readings.values()], np.float64).tobytes())
    assert inc.session_digest(bare) == h.hexdigest()


def _rows(path: Path) -> list[tuple[str, ...]]:
    """trajectories.csv rows as (session, t, x, y, ...) text tuples, keyed by session and time."""
    lines = path.read_text().splitlines()[1:]
    return [tuple([f"{ln.split(',')[0]}/{ln.split(',')[1]}"] + ln.split(",")[2:]) for ln in lines]


def test_a_state_without_components_or_with_other_control_points_means_a_full_resolve(tmp_path: Path) -> None:
    # a survey with headings whose state predates components (format 1) cannot say which component a
    # walk is in; and control points other than the previous run's place the walks differently
    from graphslam.app.update import mismatch

    sim = simulate("paper", seed=0, size=0.5)
    d = tmp_path / "walks"
    d.mkdir()
    for s in sim.survey:
        write_session(s, d / f"{s.session_id}.mcap")
    assert _run(["survey", str(d), "--out", str(tmp_path / "prev"), "--no-progress"]) == 0
    state = tmp_path / "prev" / STATE_FILE
    previous = read_survey_state(state)
    from graphslam.io.mcap_reader import read_survey

    survey = read_survey([d])
    cfg = GraphSlamConfig()
    assert previous.frame == "earth" and previous.component is not None and previous.edge_used is not None
    assert mismatch(previous, survey, cfg) is None
    # a state written when MKL PARDISO was a solver: its keys, and solver pardiso, are no difference
    prev_cfg = json.loads(previous.config_json)
    prev_cfg["optimizer"].update(threads=2, factor_precision="single", single_above_variables=40000)
    assert mismatch(replace(previous, config_json=json.dumps(prev_cfg)), survey, cfg) is None
    prev_cfg["optimizer"]["solver"] = "pardiso"
    cholmod = cfg.model_copy(update={"optimizer": cfg.optimizer.model_copy(update={"solver": "cholmod"})})
    assert mismatch(replace(previous, config_json=json.dumps(prev_cfg)), survey, cholmod) is None
    assert "optimizer.solver 'pardiso' -> 'gtsam'" in mismatch(
        replace(previous, config_json=json.dumps(prev_cfg)), survey,
        cfg.model_copy(update={"optimizer": cfg.optimizer.model_copy(update={"solver": "gtsam"})}))
    assert "control points differ" in mismatch(previous, survey, cfg, {"a": (0.0, 0.0)})
    with np.load(state) as z:
        old = {k: z[k] for k in z.files if k not in ("component", "frame", "control_digest", "edge_used")}
    old["format_version"] = np.int64(1)
    v1 = tmp_path / "v1.npz"
    np.savez(v1, **old)
    # (its digests also predate the walks' headings: that is said first)
    assert "format 1" in mismatch(read_survey_state(v1), survey, cfg)
    # a format-2 state missing one of its arrays is refused, naming it
    bad = {**old, "format_version": np.int64(2)}
    np.savez(tmp_path / "v2bad.npz", **bad)
    with pytest.raises(Exception, match="component"):
        read_survey_state(tmp_path / "v2bad.npz")


def test_the_same_walk_exclusion_looks_at_the_rows_own_walk_only() -> None:
    # update_edges clears near pairs of one walk from its own walk's columns only (fingerprints are
    # grouped by walk): the same mask as the whole-block rule, and that rule when they are not grouped
    from types import SimpleNamespace

    rng = np.random.default_rng(0)
    n = 400
    t_s, path = rng.random(n) * 100.0, rng.random(n) * 50.0
    cfg = SimpleNamespace(exclude_same_session_s=20.0, exclude_same_session_m=10.0)
    rows = np.sort(rng.choice(n, 60, replace=False))
    ok0 = rng.random((len(rows), n)) < 0.5
    for walk in (np.sort(rng.integers(0, 7, n)), rng.integers(0, 7, n)):
        fp = SimpleNamespace(session=walk, path_m=path)
        ok = ok0.copy()
        inc._exclude_same_walk(ok, rows, fp, t_s, cfg)
        same = walk[rows][:, None] == walk[None, :]
        near = (np.abs(t_s[rows][:, None] - t_s[None, :]) < 20.0) | (np.abs(path[rows][:, None] - path[None, :]) < 10.0)
        assert np.array_equal(ok, ok0 & ~(same & near))
        assert (ok != ok0).any()
