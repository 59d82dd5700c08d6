"""Rerun recordings (graphslam.viz.rerun_log): written files are read back with rerun's own reader."""

from __future__ import annotations

import dataclasses
import json
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest

RrdReader = pytest.importorskip("rerun.chunk", reason="the rerun extra is not installed").RrdReader
from conftest import run_cli

from graphslam.config import GraphSlamConfig
from graphslam.core.survey.align import Alignment, align
from graphslam.core.survey.factors import edge_state
from graphslam.core.types import Survey
from graphslam.errors import ConfigError, InputError, VisualizationError
from graphslam.io.csv_io import read_trajectories
from graphslam.sim import simulate
from graphslam.viz import rerun_log as rl  # noqa: E402

# ---- reading helpers -----------------------------------------------------------------


class Rrd:
    """Per entity: static and timed rows, with every column as Python lists (one per row)."""

    def __init__(self, path: Path) -> None:
        reader = RrdReader(path)
        self.recordings = reader.recordings()
        self.blueprints = reader.blueprints()
        self.static: dict[str, dict[str, list[Any]]] = defaultdict(lambda: defaultdict(list))
        self.timed: dict[str, dict[str, list[Any]]] = defaultdict(lambda: defaultdict(list))
        for ch in reader.stream():
            rb = ch.to_record_batch()
            target = self.static if ch.is_static else self.timed
            for name in rb.schema.names:
                if name != "rerun.controls.RowId":
                    target[ch.entity_path][name] += rb.column(name).to_pylist()
        self.entities = set(self.static) | set(self.timed)

    def under(self, prefix: str) -> list[str]:
        return sorted(e for e in self.entities if e.startswith(prefix + "/"))

    def n_static(self, entity: str, column: str) -> int:
        """Instances of ``column`` in the static row(s) of ``entity``."""
        return sum(len(v) for v in self.static[entity][column])


# ---- fixtures --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def corridor() -> tuple[Survey, Alignment, GraphSlamConfig]:
    """12 short walks on a line, with landmark marks: aligns in ~1 s."""
    sim = simulate("corridor", seed=0)
    cfg = GraphSlamConfig()
    return sim.survey, align(sim.survey, cfg), cfg


@pytest.fixture(scope="module")
def logged(corridor: tuple, tmp_path_factory: pytest.TempPathFactory) -> tuple[rl.RerunLogSummary, Rrd]:
    survey, al, cfg = corridor
    path = tmp_path_factory.mktemp("rrd") / "survey.rrd"
    summary = rl.log_survey(path, survey, al, cfg)
    return summary, Rrd(path)


def _png(path: Path, w: int = 40, h: int = 20) -> Path:
    from PIL import Image

    Image.new("RGB", (w, h), (200, 220, 255)).save(path)
    return path


def _aligned_marks(survey: Survey, al: Alignment) -> int:
    return sum(len(s.landmarks) for s in survey if s.session_id in al.tracks)


# ---- log_survey ------------------------------------------------------------------------


def test_file_is_complete_with_recording_and_blueprint(logged: tuple) -> None:
    summary, rrd = logged
    assert summary.path.exists() and summary.path.stat().st_size > 0
    assert [r.recording_id for r in rrd.recordings] == [summary.recording_id]
    assert len(rrd.blueprints) == 1  # default blueprint saved with the recording
    assert not list(summary.path.parent.glob(".*.tmp"))  # temporary file renamed away


def test_trajectories_raw_and_reference(corridor: tuple, logged: tuple) -> None:
    survey, al, _ = corridor
    _, rrd = logged
    aligned = rrd.under("/" + rl.TRAJECTORIES)
    assert len(aligned) == len(al.tracks) == 12
    for sid, tr in al.tracks.items():
        strips = rrd.static[f"/{rl.TRAJECTORIES}/{sid}"]["LineStrips2D:strips"]
        assert len(strips) == 1 and len(strips[0]) == 1  # one strip per walk, one log call
        np.testing.assert_allclose(np.array(strips[0][0]), tr.xy, atol=1e-3)  # float32 in the file
    raw = [e for e in rrd.under("/raw") if e.count("/") == 2]
    assert len(raw) == len(survey)
    assert all("Transform3D:translation" in rrd.static[e] for e in raw)  # laid out on a grid
    offsets = {tuple(rrd.static[e]["Transform3D:translation"][0][0]) for e in raw}
    assert len(offsets) == len(raw)  # side by side, not on top of each other
    ref = rrd.static["/" + rl.REFERENCE]
    assert rrd.n_static("/" + rl.REFERENCE, "Arrows2D:vectors") == 1
    assert al.reference in ref["Arrows2D:labels"][0][0]


def test_wifi_edges_by_state(corridor: tuple, logged: tuple) -> None:
    _, al, cfg = corridor
    summary, rrd = logged
    fp = al.fingerprints
    a, b = al.node_xyh[fp.node[al.edges.i], :2], al.node_xyh[fp.node[al.edges.j], :2]
    d = np.linalg.norm(a - b, axis=1)
    of = al.component_of()  # edges within one component: across two, they would join unrelated frames
    comp = np.array([of.get(s, -1) for s in al.session_ids])[fp.session]
    d = d[np.isfinite(d) & (comp[al.edges.i] == comp[al.edges.j])]
    assert len(d) <= rl.MAX_EDGES  # small survey: nothing subsampled
    expected = np.bincount(edge_state(d, cfg.wifi), minlength=3)
    for k, name in enumerate(rl.EDGE_STATES):
        entity = f"/{rl.EDGES}/{name}"
        assert rrd.n_static(entity, "LineStrips2D:strips") == expected[k] == summary.counts[entity[1:]]
    assert sum(rrd.n_static(e, "LineStrips2D:strips") for e in rrd.under("/" + rl.EDGES)) == len(d)
    assert {name: rrd.n_static(f"/{rl.EDGES}/{name}", "LineStrips2D:strips") for name in rl.EDGE_STATES} == al.edge_states


def test_wifi_edges_are_subsampled(corridor: tuple, tmp_path: Path) -> None:
    survey, al, cfg = corridor
    s = rl.log_survey(tmp_path / "s.rrd", survey, al, cfg, max_edges=100)
    rrd = Rrd(s.path)
    assert sum(rrd.n_static(e, "LineStrips2D:strips") for e in rrd.under("/" + rl.EDGES)) == 100
    assert "100 of" in s.notes


def test_landmarks(corridor: tuple, logged: tuple) -> None:
    survey, al, _ = corridor
    summary, rrd = logged
    n = _aligned_marks(survey, al)
    assert n >= 2
    for part, col in (("truth", "Points2D:positions"), ("estimate", "Points2D:positions"), ("error", "LineStrips2D:strips")):
        assert rrd.n_static(f"/{rl.LANDMARKS}/{part}", col) == n
    truth = np.array(rrd.static[f"/{rl.LANDMARKS}/truth"]["Points2D:positions"][0])
    marks = np.array([[m.x, m.y] for s in survey for m in s.landmarks if s.session_id in al.tracks])
    np.testing.assert_allclose(truth, marks, atol=1e-3)
    # the aligned frame is displayed in the site frame through the fit, and the notes say so
    assert "Transform3D:translation" in rrd.static["/" + rl.ALIGNED]
    assert f"site-from-{al.frame}" in summary.notes and f"the {al.frame} frame" in summary.notes
    assert f"site-from-{al.frame}" in rrd.static["/" + rl.NOTES]["TextDocument:text"][0][0]


def test_radio_map(corridor: tuple, logged: tuple) -> None:
    _, al, _ = corridor
    _, rrd = logged
    xy = al.fingerprint_xy()
    assert rrd.n_static("/" + rl.FINGERPRINTS, "Points2D:positions") == int(np.isfinite(xy).all(axis=1).sum())
    aps = rrd.under("/" + rl.APS)
    assert len(aps) == min(rl.TOP_APS, al.fingerprints.fingerprints.n_aps) == 10
    heard = np.diff(al.fingerprints.fingerprints.values.tocsc().indptr)
    counts = [rrd.n_static(e, "Points2D:positions") for e in aps]
    assert counts == sorted(heard, reverse=True)[: len(aps)]  # most-heard first, one point per hearing
    for e in aps:  # colour per point, RSSI values alongside
        assert rrd.n_static(e, "Points2D:colors") == rrd.n_static(e, "Points2D:positions") == rrd.n_static(e, "rssi_dbm")
        rssi = np.array(rrd.static[e]["rssi_dbm"][0])
        assert (rssi < 0).all() and (rssi > -120).all()
    # one heatmap image per AP, same rank and name, placed in metres by its transform
    heat = rrd.under("/" + rl.HEATMAPS)
    assert [e.rsplit("/", 1)[1] for e in heat] == [e.rsplit("/", 1)[1] for e in aps]
    for e in heat:
        cols = rrd.static[e]
        assert any(c.startswith("Image:buffer") for c in cols) and any(c.startswith("Transform3D:scale") for c in cols)


def test_optimiser_timeline_and_convergence(corridor: tuple, logged: tuple) -> None:
    _, al, _ = corridor
    _, rrd = logged
    err = rrd.timed["/optimizer/error"]
    assert len(err["lm_iteration"]) == len(al.iterations) > 0
    assert err["lm_iteration"] == list(range(1, len(al.iterations) + 1))
    np.testing.assert_allclose([v[0] for v in err["Scalars:scalars"]], [r.error_after for r in al.iterations])
    conv = rrd.under("/" + rl.CONVERGENCE)
    assert len(conv) == len(al.tracks)
    for e in conv:  # initial guess + one per stage snapshot, on both LM timelines
        assert len(rrd.timed[e]["lm_iteration"]) == len(al.snapshots) + 1
        assert rrd.timed[e]["lm_stage"] == list(range(len(al.snapshots) + 1))
    # everything else is static
    assert set(rrd.timed) == {f"/optimizer/{n}" for n, _ in rl._OPT_PLOTS} | set(conv)


# ---- floor plan ------------------------------------------------------------------------


def test_floor_plan_entity(corridor: tuple, tmp_path: Path, logged: tuple) -> None:
    survey, al, cfg = corridor
    _, without = logged
    assert "/" + rl.FLOOR_PLAN not in without.entities
    png = _png(tmp_path / "plan.png", 40, 20)
    s = rl.log_survey(tmp_path / "p.rrd", survey, al, cfg, floor_plan=png, floor_size=(80.0, 30.0))
    rrd = Rrd(s.path)
    plan = rrd.static["/" + rl.FLOOR_PLAN]
    assert bytes(plan["EncodedImage:blob"][0][0]) == png.read_bytes()
    # pixel (u, v) -> site (2 u, 30 - 1.5 v): spans x in [0, 80], y in [0, 30], top edge at y = 30
    np.testing.assert_allclose(plan["Transform3D:scale"][0][0], [2.0, -1.5, 1.0])
    np.testing.assert_allclose(plan["Transform3D:translation"][0][0], [0.0, 30.0, 0.0])
    assert "floor plan" in s.notes


def test_floor_plan_size_from_floor_info(tmp_path: Path) -> None:
    png = _png(tmp_path / "floor_image.png")
    (tmp_path / "floor_info.json").write_text(json.dumps({"map_info": {"width": 12.5, "height": 7.0}}))
    plan = rl.load_floor_plan(png, None)
    assert plan is not None and (plan.width_m, plan.height_m, plan.pixels) == (12.5, 7.0, (40, 20))


def test_floor_plan_errors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError):
        rl.load_floor_plan(None, (10.0, 10.0))
    with pytest.raises(InputError):
        rl.load_floor_plan(tmp_path / "missing.png", (10.0, 10.0))
    with pytest.raises(ConfigError):
        rl.load_floor_plan(_png(tmp_path / "a.png"), None)  # no size, no floor_info.json
    with pytest.raises(ConfigError):
        rl.load_floor_plan(_png(tmp_path / "b.png"), (0.0, 5.0))
    (tmp_path / "bad.png").write_bytes(b"not an image")
    with pytest.raises(InputError):
        rl.load_floor_plan(tmp_path / "bad.png", (10.0, 10.0))


# ---- failures leave no file ------------------------------------------------------------


def test_failure_leaves_no_file(corridor: tuple, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    survey, al, cfg = corridor
    target = tmp_path / "out.rrd"
    target.write_bytes(b"previous")

    def boom(*args: Any, **kwargs: Any) -> None:
        raise RuntimeError("disk on fire")

    # fails in the middle of writing (the optimiser series are sent after the static layers)
    monkeypatch.setattr(rl.rr.Scalars, "columns", boom)
    with pytest.raises(RuntimeError, match="disk on fire"):
        rl.log_survey(target, survey, al, cfg)
    assert target.read_bytes() == b"previous"  # old output untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.rrd"]  # no temporary file left

    fresh = tmp_path / "fresh.rrd"
    with pytest.raises(RuntimeError):
        rl.log_survey(fresh, survey, al, cfg)
    assert not fresh.exists()


def test_rerun_disabled_is_an_error(corridor: tuple, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    survey, al, cfg = corridor
    monkeypatch.setenv("RERUN", "off")
    with pytest.raises(VisualizationError, match="RERUN=off"):
        rl.log_survey(tmp_path / "x.rrd", survey, al, cfg)
    assert list(tmp_path.iterdir()) == []


# ---- locate ----------------------------------------------------------------------------


def test_log_locate_results(tmp_path: Path) -> None:
    est = np.array([[1.0, 2.0], [np.nan, np.nan], [5.0, 5.0]])
    truth = np.array([[1.0, 3.0], [2.0, 2.0], [5.0, 8.0]])
    s = rl.log_locate_results(tmp_path / "q.rrd", est, truth, query_ids=["a", "b", "c"], recording_id="rec-1")
    rrd = Rrd(s.path)
    assert [r.recording_id for r in rrd.recordings] == ["rec-1"]  # overlays a survey recording with this id
    assert rrd.n_static("/" + rl.LOCATE_ESTIMATE, "Points2D:positions") == 2  # invalid answer skipped
    assert rrd.n_static(f"/{rl.LOCATE}/truth", "Points2D:positions") == 2
    assert rrd.n_static(f"/{rl.LOCATE}/error", "LineStrips2D:strips") == 2
    assert rrd.static["/" + rl.LOCATE_ESTIMATE]["Points2D:labels"][0] == ["a", "c"]
    assert "mean 2.00 m" in s.notes
    # a site-from-map transform moves the estimates before the error is measured
    s2 = rl.log_locate_results(tmp_path / "q2.rrd", est[[0]], np.array([[11.0, 2.0]]), site_from_map=(10.0, 0.0, 0.0))
    assert "mean 0.00 m" in s2.notes
    with pytest.raises(ConfigError):
        rl.log_locate_results(tmp_path / "q3.rrd", est, truth[:2])


# ---- pipeline and `graphslam view` -----------------------------------------------------


def test_survey_and_view_commands(tmp_path: Path) -> None:
    sim = simulate("corridor", seed=1)
    rec_dir = tmp_path / "rec"
    sim.write(rec_dir)
    out = tmp_path / "out"
    survey_rrd = tmp_path / "survey.rrd"
    # the pipeline imports and calls log_survey lazily
    assert run_cli(["survey", str(rec_dir), "--out", str(out), "--rerun", str(survey_rrd), "--no-progress"]) == 0
    report = json.loads((out / "report.json").read_text())
    rrd = Rrd(survey_rrd)
    assert len(rrd.under("/" + rl.TRAJECTORIES)) == report["aligned_sessions"]
    assert "rerun" in report["timings_s"]

    # view: only the output folder
    bare = tmp_path / "bare.rrd"
    summary = rl.write_survey_view(out, bare)
    rrd = Rrd(bare)
    assert len(rrd.under("/" + rl.TRAJECTORIES)) == report["aligned_sessions"]
    assert "/" + rl.REFERENCE in rrd.entities
    assert rrd.under("/" + rl.APS) and "/" + rl.FINGERPRINTS in rrd.entities  # from radio_map.parquet
    assert not rrd.under("/raw") and "/" + rl.LANDMARKS + "/truth" not in rrd.entities
    assert "/info/config" in rrd.entities
    assert "--recordings" in summary.notes

    # view through the CLI, with the recordings: raw walks and landmarks too
    full = tmp_path / "full.rrd"
    assert run_cli(["view", str(out), "--recordings", str(rec_dir), "--save", str(full)]) == 0
    rrd = Rrd(full)
    assert len([p for p in rrd.under("/raw") if p.count("/") == 2]) == len(sim.survey)
    aligned = set(read_trajectories(out / "trajectories.csv"))
    n_marks = sum(len(s.landmarks) for s in sim.survey if s.session_id in aligned)
    assert n_marks > 0
    for part in ("truth", "estimate"):
        assert rrd.n_static(f"/{rl.LANDMARKS}/{part}", "Points2D:positions") == n_marks


def test_view_errors(tmp_path: Path) -> None:
    with pytest.raises(InputError):
        rl.write_survey_view(tmp_path / "missing", tmp_path / "x.rrd")
    with pytest.raises(InputError, match="trajectories.csv"):
        rl.write_survey_view(tmp_path, tmp_path / "x.rrd")
    assert run_cli(["view", str(tmp_path)]) == 2  # no --save/--serve/--spawn: one-line error
    assert not (tmp_path / "x.rrd").exists()


# ---- helpers ---------------------------------------------------------------------------


def test_top_access_points_and_colours() -> None:
    from graphslam.core.radiomap.fingerprints import FingerprintMatrix

    scans = [{"a": -50.0, "b": -80.0}, {"a": -60.0, "c": -40.0}, {"b": -70.0, "c": -45.0}, {"c": -90.0}]
    fm = FingerprintMatrix.from_scans(scans)
    cols = rl.top_access_points(fm, np.arange(4), 2)
    assert [fm.bssids[c] for c in cols] == ["c", "a"]  # c heard 3x; a and b 2x, a stronger
    assert [fm.bssids[c] for c in rl.top_access_points(fm, np.array([3]), 5)] == ["c"]
    col = rl.rssi_colours(np.array([-200.0, -100.0, -30.0, 0.0]))
    assert col.shape == (4, 3) and (col[0] == col[1]).all() and (col[2] == col[3]).all()
    c = rl.session_colours(["a", "b", "c"])
    assert len(set(c.values())) == 3


def test_a_reference_map_is_its_own_layer(tmp_path: Path) -> None:
    """A survey on a reference map logs the reference's fingerprints (held, site frame) apart from the
    crowd's, from the alignment and again from the output folder (the radio map's last rows)."""
    from graphslam.app.survey import run_survey
    from graphslam.app.survey_inputs import SurveyInputs
    from graphslam.config import load_config
    from graphslam.io.mcap_writer import write_session
    from graphslam.io.reference_map import read_reference_map
    from test_magnetic import corridor as magnetic_corridor
    from test_reference_map import reference_csv

    survey = magnetic_corridor()
    (tmp_path / "walks").mkdir()
    files = [write_session(s, tmp_path / "walks" / f"{s.session_id}.mcap") for s in survey]
    ref = reference_csv(tmp_path / "reference_map.csv", survey)
    res = run_survey(SurveyInputs.from_paths(files[1:], out=tmp_path / "out", reference_map=ref, picture=False),
                     load_config())
    want = np.asarray(read_reference_map(ref).xy)
    rl.log_survey(tmp_path / "a.rrd", res.survey, res.alignment, load_config())
    rl.write_survey_view(tmp_path / "out", tmp_path / "b.rrd")
    for rrd in (Rrd(tmp_path / "a.rrd"), Rrd(tmp_path / "b.rrd")):
        got = np.array(rrd.static["/" + rl.REFERENCE_MAP]["Points2D:positions"][0])
        np.testing.assert_allclose(got, want, atol=1e-4)
        assert set(rrd.static["/" + rl.REFERENCE_MAP]["Points2D:labels"][0]) == {"reference_map.csv"}
    plain = Rrd(tmp_path / "c.rrd") if rl.log_survey(tmp_path / "c.rrd", res.survey,
                                                      dataclasses.replace(res.alignment, reference_map=None)) else None
    assert "/" + rl.REFERENCE_MAP not in plain.entities
