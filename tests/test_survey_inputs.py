"""A survey's inputs as one object (graphslam.app.survey_inputs.SurveyInputs): its named
constructors, the reserved reference map, and the earlier call form of run_survey."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import graphslam as gs
from graphslam.app.survey import run_survey
from graphslam.app.survey_inputs import CONTROL_POINTS_FILE, FLOOR_PLAN_FILE, REFERENCE_MAP_FILE, SurveyInputs
from graphslam.config import GraphSlamConfig
from graphslam.errors import InputError
from graphslam.io.mcap_writer import write_session
from graphslam.sim import simulate


@pytest.fixture(scope="module")
def floor(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, tuple[float, float]]]:
    """A folder of corridor walks (~1 s to survey) and two of its landmarks at their true positions."""
    d = tmp_path_factory.mktemp("inputs") / "floor"
    sim = simulate("corridor", seed=3)
    marks: dict[str, tuple[float, float]] = {}
    for s in sim.survey:
        write_session(s, d / f"{s.session_id}.mcap")
        for m in s.landmarks:
            marks.setdefault(m.landmark_id, (m.x, m.y))
    assert len(marks) >= 2
    return d, dict(list(marks.items())[:2])


def test_paths_are_held_as_path_objects(tmp_path: Path) -> None:
    inputs = SurveyInputs.from_paths(str(tmp_path / "a.mcap"), str(tmp_path / "out"), floor_size=[30, 20],
                                     control_points=str(tmp_path / "cp.csv"), previous=str(tmp_path / "old"))
    assert inputs.recordings == (tmp_path / "a.mcap",)
    assert inputs.out == tmp_path / "out" and inputs.previous == tmp_path / "old"
    assert inputs.control_points == tmp_path / "cp.csv" and inputs.floor_size == (30, 20)
    assert inputs.picture and not inputs.surveyed and inputs.rerun is None and inputs.reference_map is None
    many = SurveyInputs([tmp_path / "a.mcap", str(tmp_path / "b.mcap")])
    assert many.recordings == (tmp_path / "a.mcap", tmp_path / "b.mcap") and many.out is None
    points = {"L1": (1.0, 2.0)}
    held = SurveyInputs(tmp_path, control_points=points)
    points["L2"] = (3.0, 4.0)  # the caller's dict changing later does not change the inputs
    assert held.control_points == {"L1": (1.0, 2.0)}
    with pytest.raises(AttributeError):
        held.out = tmp_path  # type: ignore[misc]  # frozen


def test_a_floor_folder_brings_its_control_points_reference_map_and_previous_output(floor: tuple, tmp_path: Path) -> None:
    folder, _ = floor
    plain = SurveyInputs.for_floor(folder, tmp_path / "out", update=True)
    # no control_points.csv, no reference_map.csv, no previous output
    assert plain.control_points is None and plain.reference_map is None and plain.previous is None
    site = tmp_path / "site"
    site.mkdir()
    (site / CONTROL_POINTS_FILE).write_text("landmark_id,x,y\nL1,1,2\n")
    (site / REFERENCE_MAP_FILE).write_text("fingerprint_id,x,y,bssid,rssi_dbm\nfp0,1,2,aa:bb,-60\n")
    (tmp_path / "out" / "survey_state.npz").parent.mkdir()
    (tmp_path / "out" / "survey_state.npz").write_bytes(b"")
    inputs = SurveyInputs.for_floor(site, tmp_path / "out", update=True, picture=False)
    assert inputs.control_points == site / CONTROL_POINTS_FILE and inputs.previous == tmp_path / "out"
    assert inputs.reference_map == site / REFERENCE_MAP_FILE
    assert SurveyInputs.for_floor(site, reference_map=None).reference_map is None  # an option given wins
    assert inputs.floor_plan is None  # no floor_image.png
    assert not inputs.picture and inputs.recordings == (site,)
    assert SurveyInputs.for_floor(site, tmp_path / "out").previous is None  # no update asked for


def test_a_floor_folder_brings_its_floor_plan_when_its_size_is_beside_it(floor: tuple, tmp_path: Path) -> None:
    """survey-batch draws a floor's survey.png over the floor_image.png of its folder (the ILC layout: its
    size in floor_info.json beside it); an image without its size is left out, not a failed floor."""
    folder, _ = floor
    site = tmp_path / "site"
    site.mkdir()
    for f in folder.glob("*.mcap"):
        (site / f.name).write_bytes(f.read_bytes())
    Image.new("RGB", (300, 40), (255, 220, 120)).save(site / FLOOR_PLAN_FILE)  # a colour no walk has
    assert SurveyInputs.for_floor(site).floor_plan is None  # no floor_info.json yet
    (site / "floor_info.json").write_text(json.dumps({"map_info": {"width": 90.0, "height": 12.0}}))
    inputs = SurveyInputs.for_floor(site, tmp_path / "out")
    assert inputs.floor_plan == site / FLOOR_PLAN_FILE and inputs.floor_size is None
    run_survey(inputs)
    with Image.open(tmp_path / "out" / "survey.png") as im:
        img = np.asarray(im.convert("RGB")).astype(int)
    assert (np.abs(img - np.array([255, 225, 140])).max(axis=2) <= 12).sum() > 2_000  # the plan, at alpha 0.85


def test_a_missing_reference_map_fails_before_any_work(floor: tuple, tmp_path: Path) -> None:
    folder, _ = floor
    with pytest.raises(InputError, match="reference map not found") as e:
        run_survey(SurveyInputs((folder,), tmp_path / "out", reference_map=tmp_path / "ref.parquet"))
    assert e.value.path == str(tmp_path / "ref.parquet")
    assert not (tmp_path / "out").exists()  # nothing written


def test_the_earlier_call_form_runs_the_same_survey_with_a_warning(floor: tuple) -> None:
    folder, points = floor
    cfg = GraphSlamConfig()
    new = run_survey(SurveyInputs((folder,), control_points=points, picture=False), cfg)
    with pytest.warns(DeprecationWarning, match="SurveyInputs"):
        old = gs.run_survey([folder], None, cfg, picture=False, control_points=points)
    assert new.alignment.frame == old.alignment.frame == "site"
    assert np.array_equal(new.alignment.node_xyh, old.alignment.node_xyh, equal_nan=True)
    strip = lambda r: json.dumps({k: v for k, v in r.items() if k != "timings_s"}, sort_keys=True)  # noqa: E731
    assert strip(new.report) == strip(old.report)
    with pytest.raises(TypeError, match="fields of SurveyInputs"):
        run_survey(SurveyInputs((folder,)), cfg, picture=False)  # type: ignore[call-arg]


def test_the_earlier_call_forms_map_to_the_same_inputs(tmp_path: Path) -> None:
    from graphslam.app.survey import _legacy_inputs

    cfg = GraphSlamConfig()
    want = SurveyInputs((tmp_path,), tmp_path / "o", previous=tmp_path / "p", rerun=tmp_path / "r.rrd", picture=False)
    options = {"update": tmp_path / "p", "rerun_path": tmp_path / "r.rrd", "picture": False}
    forms = [  # run_survey(paths, out, cfg, ...), (paths, out_dir=out, config=cfg, ...), (paths, out, ...): no config
        ((tmp_path / "o", (cfg,), dict(options)), cfg),
        ((cfg, (), {"out_dir": tmp_path / "o", **options}), cfg),
        ((tmp_path / "o", (), dict(options)), None),
    ]
    for (second, args, kw), config in forms:
        with pytest.warns(DeprecationWarning):
            inputs, got = _legacy_inputs([tmp_path], second, args, kw)
        assert got is config and vars(inputs) == vars(want)
    with pytest.warns(DeprecationWarning), pytest.raises(TypeError, match="unexpected keyword arguments \\['out'\\]"):
        _legacy_inputs([tmp_path], None, (), {"out": tmp_path})
