"""What a survey writes when its walks form several components (the main map, component 0, and
walks in frames of their own): trajectories.csv's ``component``, report.json's ``frame`` and
``components``, a radio map of component 0 only, aligned.mcap's frame ids, survey.png, the
under-half warning of ``graphslam survey`` and the ``partial`` floors of ``survey-batch``.

The components are made by hand (the real alignment, its walks regrouped), so these tests
check the outputs around the solver, whatever the solver forms."""

from __future__ import annotations

import importlib.util
import dataclasses
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import run_cli
from mcap.reader import make_reader
from PIL import Image

import graphslam.app.survey as app_survey
from graphslam.app.batch import survey_floor
from graphslam.app.survey import main_map_warning, run_survey
from graphslam.app.survey_inputs import SurveyInputs
from graphslam.config import GraphSlamConfig
from graphslam.core.survey.align import Component, align
from graphslam.errors import InputError
from graphslam.io.csv_io import read_trajectories, read_trajectory_file, write_trajectories
from graphslam.io.mcap_writer import write_session
from graphslam.io.radiomap_io import read_radio_map
from graphslam.sim import simulate
from graphslam.viz import survey_picture

REASON = "no WiFi edge to the main map"


@pytest.fixture(scope="module")
def floor(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Six corridor walks (with landmarks) in a folder named like a floor."""
    d = tmp_path_factory.mktemp("sites") / "b7_f2"
    for s in simulate("corridor", seed=0, size=0.5).survey:
        write_session(s, d / f"{s.session_id}.mcap")
    return d


def split_align(groups: tuple[int, ...], frame: str = "aligned") -> Any:
    """``align`` whose aligned walks are regrouped into components of ``groups`` walks (0 first)."""

    def fake(survey: Any, cfg: Any = None, progress: Any = None, warm: Any = None, **kw: Any) -> Any:
        al = align(survey, cfg, progress, warm, **kw)
        ids, comps, i = list(al.tracks), [], 0
        assert sum(groups) == len(ids)
        for k, n in enumerate(groups):
            comps.append(Component(k, tuple(ids[i:i + n]), "" if k == 0 else REASON))
            i += n
        return dataclasses.replace(al, component_list=tuple(comps), frame_name=frame)

    return fake


@pytest.fixture(scope="module")
def split_run(floor: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Any]:
    """The floor surveyed (real CLI) with its six walks in components of 2, 3 and 1 walks."""
    out = tmp_path_factory.mktemp("split") / "out"
    mp = pytest.MonkeyPatch()
    mp.setattr(app_survey, "align", split_align((2, 3, 1)))
    try:
        assert run_cli(["survey", str(floor), "--out", str(out), "--no-progress"]) == 0
    finally:
        mp.undo()
    return out, json.loads((out / "report.json").read_text())


def test_trajectories_csv_has_the_component_of_every_walk_and_round_trips(split_run: tuple, tmp_path: Path) -> None:
    out, report = split_run
    lines = (out / "trajectories.csv").read_text().splitlines()
    assert lines[0] == "session_id,t_ns,x,y,heading,component,frame"
    # each walk's frame: the report's for the main map, one of its own for every other component
    frames = {row.split(",")[0]: (int(row.split(",")[5]), row.split(",")[6]) for row in lines[1:]}
    assert {f for c, f in frames.values() if c == 0} == {report["frame"]}
    assert all(f == f"component_{c}" for c, f in frames.values() if c)
    expected = {sid: c["index"] for c in report["components"] for sid in c["walks"]}
    f = read_trajectory_file(out / "trajectories.csv")
    assert f.components == expected and sorted(set(expected.values())) == [0, 1, 2]
    assert set(read_trajectories(out / "trajectories.csv", component=0)) == set(report["components"][0]["walks"])
    # written again from what was read: the same file
    assert f.frame == report["frame"]
    again = write_trajectories(f.tracks, tmp_path / "again.csv", f.components, f.frame)
    assert again.read_text() == (out / "trajectories.csv").read_text()
    # a file written before the frame column reads as it did; one before components as the main map
    before_frame = tmp_path / "v2.csv"
    before_frame.write_text("\n".join(line.rsplit(",", 1)[0] for line in lines) + "\n")
    f_v2 = read_trajectory_file(before_frame)
    assert f_v2.components == f.components and f_v2.frame == ""
    old = tmp_path / "old.csv"
    old.write_text("\n".join(line.rsplit(",", 2)[0] for line in lines) + "\n")
    f_old = read_trajectory_file(old)
    assert set(f_old.components.values()) == {0} and set(f_old.tracks) == set(f.tracks)
    np.testing.assert_allclose(f_old.tracks[lines[1].split(",")[0]].xy, f.tracks[lines[1].split(",")[0]].xy)
    # one walk in two components, or a negative component: the file is refused
    bad = tmp_path / "bad.csv"
    bad.write_text("\n".join(lines[:3] + [lines[3].rsplit(",", 2)[0] + ",5,component_5"]) + "\n")
    with pytest.raises(InputError, match="component"):
        read_trajectory_file(bad)
    bad.write_text("\n".join(lines[:2] + [lines[2].rsplit(",", 2)[0] + ",-1,component_-1"]) + "\n")
    with pytest.raises(InputError, match="line 3"):
        read_trajectory_file(bad)


def test_report_has_the_frame_and_every_component(split_run: tuple) -> None:
    out, report = split_run
    assert report["frame"] == "aligned" and "reference walk's first pose" in report["frame_description"]
    assert "own" in report["frame_description"]  # the other components' frames are said
    comps = report["components"]
    assert [c["index"] for c in comps] == [0, 1, 2] and [c["n_walks"] for c in comps] == [2, 3, 1]
    assert all(set(c) == {"index", "walks", "n_walks", "reason", "links"} for c in comps)
    assert all(set(c["links"]) == {"wifi", "magnetic", "uwb", "control_points", "reference", "reference_magnetic"}
               for c in comps)
    assert comps[0]["reason"] == "" and comps[1]["reason"] == REASON
    walks = [w for c in comps for w in c["walks"]]
    assert sorted(walks) == sorted(read_trajectories(out / "trajectories.csv"))  # each aligned walk once
    if "walks" in report:  # per-walk rows (when the placement reports them) name the component too
        assert {w["session_id"]: w["component"] for w in report["walks"]} == {
            sid: c["index"] for c in comps for sid in c["walks"]}
    assert report["radio_map"]["component"] == 0 and report["radio_map"]["walks"] == 2
    assert report["radio_map"]["walks_in_other_components"] == 4
    assert report["floor"] == "b7_f2 (sim-corridor/F1)"
    for key in ("sessions", "aligned_sessions", "reference_session", "unaligned", "nodes", "fingerprints", "edges",
                "optimizer", "timings_s", "evaluation"):
        assert key in report
    assert report["evaluation"]["component"] == 0


def test_radio_map_and_wifi_edges_hold_component_0_only(split_run: tuple, floor: Path, tmp_path: Path) -> None:
    out, report = split_run
    main = set(report["components"][0]["walks"])
    rm = read_radio_map(out / "radio_map.parquet")
    assert set(rm.session_ids) == main and len(rm) == report["radio_map"]["fingerprints"]
    # the same survey in one component: the map holds more, and component 0's rows are the same
    full = run_survey(SurveyInputs((floor,), picture=False), GraphSlamConfig())
    assert full.report["radio_map"]["fingerprints"] > len(rm)
    from graphslam.core.survey.radio_maps import crowdsourced_radio_map

    all_rows = crowdsourced_radio_map(full.survey, full.alignment, GraphSlamConfig())
    assert sum(s in main for s in all_rows.session_ids) == len(rm)
    import pyarrow.parquet as pq

    edges = pq.read_table(out / "wifi_edges.parquet").to_pydict()
    a, b = np.array(edges["a"]), np.array(edges["b"])
    assert len(a) and a.max() < len(rm) and b.max() < len(rm)
    # aligned.mcap: every aligned walk, its poses in its component's frame
    frames: dict[str, set[str]] = {}
    with open(out / "aligned.mcap", "rb") as fh:
        for _, ch, msg in make_reader(fh).iter_messages():
            frames.setdefault(ch.topic.removeprefix("/aligned/"), set()).add(json.loads(msg.data)["frame_id"])
    want = {sid: {"aligned" if c["index"] == 0 else f"component_{c['index']}"} for c in report["components"]
            for sid in c["walks"]}
    assert frames == want


def test_survey_png_draws_the_other_components_apart(split_run: tuple) -> None:
    out, report = split_run
    png = out / "survey.png"
    with Image.open(png) as im:
        assert im.size == survey_picture.SIZE_PX
        img = np.asarray(im.convert("RGB")).astype(int)
    assert (img < 250).any()  # not blank
    scene = survey_picture.scene_of_folder(out)  # `graphslam plot`: components from trajectories.csv
    assert [(k, set(w)) for k, w, _ in scene.components] == [
        (c["index"], set(c["walks"])) for c in report["components"]]
    assert scene.other_components()[0][2] == REASON
    # the strip under the main panel: other components' walks there, the main map's not
    w, h = survey_picture.SIZE_PX
    strip = img[h - survey_picture.INSET_STRIP_PX + 30:h - 12, 62:int(0.665 * w)]
    near = lambda c: int((np.abs(strip - np.array(c)).max(axis=2) <= 10).sum())  # noqa: E731
    others = [s for c in report["components"][1:] for s in c["walks"]]
    assert all(near(scene.colours[s]) >= 20 for s in others)
    assert all(near(scene.colours[s]) < 5 for s in report["components"][0]["walks"])
    legend = " ".join(e.text for e in survey_picture.survey_picture(scene).legend)
    assert "4 walks in 2 other components" in legend and REASON in legend
    # the title counts the main map first, as `survey`'s first line does (not "6/6 walks aligned")
    counts = "main map: 2 of 6 walks; 4 in 2 other components; 0 unaligned"
    with Image.open(png) as im:
        assert im.text["Title"].startswith(counts), im.text["Title"]
    assert run_cli(["plot", str(out)]) == 0  # redrawn from the folder
    with Image.open(png) as im:
        assert im.text["Title"].startswith(counts), im.text["Title"]


def test_earth_frame_has_a_north_note_and_many_singletons_are_counted_not_drawn() -> None:
    rng = np.random.default_rng(0)
    ids = [f"w{k:03d}" for k in range(120)]
    tracks = {s: np.cumsum(rng.normal(0, 0.7, (40, 2)), axis=0) for s in ids}
    comps = ((0, tuple(ids[:50]), ""), (1, tuple(ids[50:60]), "linked among themselves only"),
             *((2 + k, (s,), "no WiFi match") for k, s in enumerate(ids[60:])))
    scene = survey_picture.SurveyScene(
        tracks, survey_picture.session_colours(ids), ids[0], {}, np.zeros((0, 2, 2)), np.zeros(0, np.int8), (0, 0, 0),
        None, None, "", 120, 4800, (), comps, "earth")
    pic = survey_picture.survey_picture(scene)
    assert any("north-up (x east, y north" in t for t in pic.title_lines)
    legend = [e.text for e in pic.legend]
    assert any(t.startswith("north arrow") for t in legend)
    assert any("61 components" not in t and "60 components, 60 walks" in t for t in legend)
    assert any("smaller components (55 walks) not drawn" in t for t in legend)
    # the walks' colours: those of the main map's 50 (not "120 aligned walks"), the others in the strip
    assert any(t.startswith("50 walks of the main map, one colour each") for t in legend)
    assert pic.title_lines[0].startswith("main map: 50 of 120 walks; 70 in 61 other components; 0 unaligned")
    assert len(pic.panels) == 1 + survey_picture.MAX_INSETS
    assert pic.render().size == survey_picture.SIZE_PX


def test_main_map_warning_rule() -> None:
    def rep(n: int, comps: list[int], unaligned: int) -> dict:
        return {"floor": "F", "sessions": n, "unaligned": [{}] * unaligned,
                "components": [{"n_walks": k} for k in comps]}

    assert main_map_warning(rep(6, [3, 3], 0)) is None  # half is not under half
    assert main_map_warning(rep(6, [6], 0)) is None
    w = main_map_warning(rep(40, [14, 10, 6, 4, 1, 1, 1, 1, 1, 1], 0))
    assert w == ("F: the main map holds 14 of 40 walks; 26 are not in it: 26 in 9 other components "
                 "(report.json: components, unaligned)")
    assert "2 in 1 other component, 3 unaligned" in main_map_warning(rep(7, [2, 2], 3))
    assert "0 of 2 walks" in main_map_warning(rep(2, [], 2))


def test_survey_warns_once_naming_the_floor_when_the_main_map_holds_under_half(
    floor: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(app_survey, "align", split_align((2, 3, 1)))
    caplog.set_level("WARNING")
    r = run_survey(SurveyInputs((floor,), tmp_path / "o1", picture=False), GraphSlamConfig())
    lines = [m for m in caplog.messages if "main map holds" in m]
    assert lines == [main_map_warning(r.report)]
    assert lines[0].startswith("b7_f2 (sim-corridor/F1): the main map holds 2 of 6 walks; 4 are not in it: "
                               "4 in 2 other components")
    caplog.clear()
    monkeypatch.setattr(app_survey, "align", split_align((3, 3)))  # half: no warning
    run_survey(SurveyInputs((floor,), tmp_path / "o2", picture=False), GraphSlamConfig())
    assert not [m for m in caplog.messages if "main map holds" in m]


def _floor_without_wifi(root: Path, name: str, keep: int) -> Path:
    """Six corridor walks, all but ``keep`` of them without WiFi (unaligned)."""
    d = root / name
    for k, s in enumerate(simulate("corridor", seed=1, size=0.5).survey):
        write_session(s if k < keep else dataclasses.replace(s, scans=()), d / f"{s.session_id}.mcap")
    return d


def test_the_cli_prints_one_warning_line_on_stderr_and_exits_0(tmp_path: Path) -> None:
    """The real command in its own process, the real solver: walks without WiFi count against the
    main map."""
    sparse = _floor_without_wifi(tmp_path, "b9_f1", keep=2)

    def survey(folder: Path, out: Path) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "graphslam", "survey", str(folder), "--out", str(out), "-q",
                               "--no-picture"], capture_output=True, text=True, timeout=120)

    res = survey(sparse, tmp_path / "o1")
    assert res.returncode == 0, res.stderr
    err = res.stderr.strip().splitlines()
    # the four walks without WiFi: unaligned, or components of their own, as the solver decides
    assert len(err) == 1 and "b9_f1" in err[0] and "the main map holds 2 of 6 walks; 4 are not in it" in err[0], err
    # the first line printed says the same as the warning: the main map first
    assert res.stdout.startswith("main map: 2 of 6 walks; "), res.stdout
    good = _floor_without_wifi(tmp_path, "b9_f2", keep=6)
    res = survey(good, tmp_path / "o2")
    assert res.returncode == 0 and "main map" not in res.stderr, res.stderr


def test_survey_floor_marks_a_floor_partial(floor: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(app_survey, "align", split_align((2, 3, 1)))
    row = survey_floor(str(floor), str(tmp_path / "o"), GraphSlamConfig().model_dump_json(), "b7_f2")
    assert row["status"] == "partial" and row["error"] is None and row["main"] == 2 and row["walks"] == 6
    assert row["warning"].startswith("b7_f2 (sim-corridor/F1): the main map holds 2 of 6 walks")


@pytest.mark.skipif(importlib.util.find_spec("distributed") is None, reason="the batch extra (Dask) is not installed")
def test_batch_counts_partial_floors_and_takes_each_floors_control_points(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A real local Dask cluster: an ok floor (with a control_points.csv it uses), a partial floor,
    and a floor whose control_points.csv is broken (failed, the file named)."""
    sites = tmp_path / "sites"
    good = _floor_without_wifi(sites, "good", keep=6)
    (good / "control_points.csv").write_text("landmark_id,x,y\nL1,1.0,2.0\n")
    _floor_without_wifi(sites, "sparse", keep=2)
    broken = _floor_without_wifi(sites, "broken", keep=6)
    (broken / "control_points.csv").write_text("landmark_id,x,y\nL1,1.0,north\n")
    out = tmp_path / "out"
    assert run_cli(["survey-batch", str(sites), "--out", str(out), "--workers", "2", "--no-progress"]) == 1
    rows = {r["floor"]: r for r in json.loads((out / "summary.json").read_text())}
    assert {k: r["status"] for k, r in rows.items()} == {"good": "ok", "sparse": "partial", "broken": "failed"}
    assert rows["sparse"]["main"] == 2 and "the main map holds 2 of 6 walks" in rows["sparse"]["warning"]
    assert str(broken / "control_points.csv") in rows["broken"]["error"] and "[field y]" in rows["broken"]["error"]
    stdout = capsys.readouterr().out
    assert "3 floors: 1 ok, 1 partial, 1 failed" in stdout
    assert f"partial: sparse: {rows['sparse']['main_map']}; frame {rows['sparse']['frame']} (under half of the walks in the main map" in stdout
    assert rows["sparse"]["main_map"].startswith("main map: 2 of 6 walks; ")
    # partial floors alone: exit code 0
    (broken / "control_points.csv").unlink()
    assert run_cli(["survey-batch", str(sites), "--out", str(out), "--workers", "2", "--no-progress"]) == 0
    assert "3 floors: 2 ok, 1 partial, 0 failed" in capsys.readouterr().out


def test_evaluate_fits_one_component(split_run: tuple, floor: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out, report = split_run
    traj = str(out / "trajectories.csv")
    capsys.readouterr()
    for k, comp in enumerate(report["components"]):
        assert run_cli(["evaluate", traj, str(floor), "--component", str(k)]) == 0
        row = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        assert row["component"] == k and row["walks"] == comp["n_walks"]
    assert run_cli(["evaluate", traj, str(floor), "--component", "7"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and traj in err[0] and "no walk in component 7" in err[0]


def test_the_radio_map_reuses_the_surveys_encoding_of_its_scans() -> None:
    # the crowdsourced map takes its rows of the matrix the survey encoded (associate's) instead of
    # encoding the kept scans again: the same matrix as from_scans, also when the dropped rows alone
    # heard an AP (it leaves the index) and with readings below the threshold
    from types import SimpleNamespace

    from graphslam.core.radiomap.fingerprints import FingerprintMatrix
    from graphslam.core.survey.radio_maps import _kept_fingerprints

    rng = np.random.default_rng(3)
    aps = [f"ap{i:02d}" for i in range(30)]
    scans = [{a: float(rng.integers(-105, -35)) for a in rng.choice(aps[:25], rng.integers(1, 12), replace=False)}
             for _ in range(60)]
    scans[7]["ap29"] = -50.0  # heard by a dropped row only
    keep = rng.random(60) < 0.7
    keep[7] = False
    full = FingerprintMatrix.from_scans(scans, missing_dbm=-110.0, min_rssi_dbm=-100.0)
    got = _kept_fingerprints(SimpleNamespace(fingerprints=SimpleNamespace(fingerprints=full)), keep)
    want = FingerprintMatrix.from_scans([s for s, k in zip(scans, keep) if k], missing_dbm=-110.0, min_rssi_dbm=-100.0)
    assert got.bssids == want.bssids and "ap29" not in got.bssids and len(got.bssids) < len(full.bssids)
    for a in ("indptr", "indices", "data"):
        assert np.array_equal(getattr(got.values, a), getattr(want.values, a)), a
    assert np.array_equal(got.extra_sq, want.extra_sq) and np.array_equal(got.extra_n, want.extra_n)
    assert got.missing_dbm == want.missing_dbm
