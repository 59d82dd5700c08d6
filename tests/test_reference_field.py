"""A reference's magnetic field (a previous survey's magnetic_map.parquet beside its radio map): the crowd's
placed walks tied to it by magnetic factors (``graphslam.core.survey.reference.field_ties``), read with the
reference, counted in the report."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from test_magnetic import corridor  # noqa: I001
from test_reference_map import reference_csv

from conftest import run_cli as cli_main
from graphslam.app.survey import run_survey
from graphslam.app.survey_inputs import SurveyInputs
from graphslam.config import load_config
from graphslam.core.common.geometry import fit_se2
from graphslam.core.radiomap.magnetic_map import MagneticMap
from graphslam.core.survey.magnetic import MagneticParams, step_features
from graphslam.core.survey.reference import field_sequences, field_ties
from graphslam.core.types import Survey
from graphslam.errors import InputError
from graphslam.io.magnetic_map_io import write_magnetic_map
from graphslam.io.mcap_writer import write_session
from graphslam.io.reference_map import read_reference_field, read_reference_map


def _field_of(survey: Survey, walks: list[int]) -> MagneticMap:
    """The walks' field at their true positions: a previous survey's magnetic map in the site frame."""
    feats = step_features(survey)
    ids, t, xy, f = [], [], [], []
    for w in walks:
        s = survey.sessions[w]
        ids += [s.session_id] * len(s.steps)
        t.append(s.steps.t_ns)
        xy.append(s.ground_truth.xy)
        f.append(feats[w])
    return MagneticMap(np.array(ids), np.concatenate(t), np.concatenate(xy), np.concatenate(f), frame="site")


def _nodes(survey: Survey) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    offsets = np.concatenate([[0], np.cumsum([len(s.steps) for s in survey])]).astype(np.int64)
    dr = np.concatenate([s.steps.xy for s in survey])
    return offsets, dr, np.repeat(np.arange(len(survey)), np.diff(offsets))


def test_the_reference_walks_are_resampled_along_their_path_and_number_held_nodes() -> None:
    survey = corridor()
    seq = field_sequences(_field_of(survey, [0, 1]), 0.5, first_node=1000)
    assert seq.n_walks == 2 and seq.node[0] == 1000 and np.all(np.diff(seq.node) == 1)
    for w in (0, 1):
        xy = seq.xy[seq.offsets[w]:seq.offsets[w + 1]]
        np.testing.assert_allclose(np.linalg.norm(np.diff(xy, axis=0), axis=1), 0.5, atol=0.02)
        np.testing.assert_allclose(xy[0], survey.sessions[w].ground_truth.xy[0])


def test_a_placed_walk_is_tied_to_where_the_field_says_not_where_it_was_placed() -> None:
    survey = corridor()
    ref = _field_of(survey, [0])  # walk 0 (0 -> 80 m) is the reference's field
    offsets, dr, walk = _nodes(survey)
    true_T = np.array([fit_se2(s.steps.xy, s.ground_truth.xy) for s in survey])
    placed = true_T.copy()
    placed[2, 0] += 3.0  # walk 2 placed 3 m along the corridor from where it is
    on = np.array([False, False, True, True, False])
    ties = field_ties(survey, offsets, placed, on, ref, MagneticParams(), dr_xy=dr, node_walk=walk,
                      max_offset_m=5.0, per_place=3)
    assert set(ties.walks.tolist()) == {2, 3} and ties.links >= 2 and len(ties) >= 10
    true = np.concatenate([s.ground_truth.xy for s in survey])
    gap = np.linalg.norm(true[ties.pairs[:, 0]] - ties.xy[ties.pairs[:, 1]], axis=1)
    assert np.median(gap) < 0.6 and gap.max() < 2.0  # each factor: a crowd step and the reference's sample there
    # a link the placement leaves further than max_offset_m from the field's place is dropped
    near = field_ties(survey, offsets, placed, on, ref, MagneticParams(), dr_xy=dr, node_walk=walk,
                      max_offset_m=2.0, per_place=3)
    assert set(near.walks.tolist()) == {3}
    # walks not placed are not searched
    none = field_ties(survey, offsets, placed, np.zeros(5, bool), ref, MagneticParams(), dr_xy=dr, node_walk=walk,
                      max_offset_m=5.0, per_place=3)
    assert len(none) == 0


@pytest.fixture(scope="module")
def previous(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[Path]]:
    """A previous survey in the site frame (two walks on a CSV reference: it writes a magnetic map) and the
    recordings of three more walks of the corridor."""
    d = tmp_path_factory.mktemp("field")
    survey = corridor()
    (d / "walks").mkdir()
    files = [write_session(s, d / "walks" / f"{s.session_id}.mcap") for s in survey]
    run_survey(SurveyInputs.from_paths(files[1:3], out=d / "prev", reference_map=reference_csv(d / "ref.csv", survey),
                                       picture=False), load_config())
    assert (d / "prev" / "magnetic_map.parquet").is_file()
    return d / "prev", files


def test_a_crowd_on_a_previous_survey_is_tied_to_its_field_and_the_report_says_so(previous: tuple) -> None:
    prev, files = previous
    r = run_survey(SurveyInputs.from_paths([files[0], *files[3:]], reference_map=prev / "radio_map.parquet",
                                           picture=False), load_config()).report
    assert r["frame"] == "site" and r["components"][0]["n_walks"] == 3
    field = r["reference_map"]["field"]
    assert field["walks"] == 2 and field["factors"] > 0 and field["crowd_walks"] >= 1
    assert r["components"][0]["links"]["reference_magnetic"] == field["factors"]
    assert field["factor_distance_m"]["median"] < 1.0  # the solve brings the factors' ends together
    # the field off: no factors, and the report says none
    off = run_survey(SurveyInputs.from_paths([files[0], *files[3:]], reference_map=prev / "radio_map.parquet",
                                             picture=False), load_config(None, {"magnetic": {"enabled": False}})).report
    assert off["reference_map"]["field"] is None and off["components"][0]["links"]["reference_magnetic"] == 0


def test_a_csv_reference_has_no_field_and_a_bad_field_file_is_one_line(previous: tuple, tmp_path: Path,
                                                                        capsys: pytest.CaptureFixture) -> None:
    prev, files = previous
    assert read_reference_field(prev.parent / "ref.csv") is None
    with pytest.raises(InputError, match="gone.parquet"):
        read_reference_field(tmp_path / "gone.parquet")
    copy = tmp_path / "copy"
    copy.mkdir()
    (copy / "radio_map.parquet").write_bytes((prev / "radio_map.parquet").read_bytes())
    assert read_reference_field(copy / "radio_map.parquet") is None  # no field beside it
    data = bytearray((prev / "magnetic_map.parquet").read_bytes())
    data[len(data) // 2] ^= 0xFF
    (copy / "magnetic_map.parquet").write_bytes(bytes(data))
    with pytest.raises(InputError, match="magnetic_map.parquet"):
        read_reference_field(copy / "radio_map.parquet")
    out = tmp_path / "out"
    assert cli_main(["survey", str(files[0]), "--out", str(out), "--reference-map", str(copy / "radio_map.parquet")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "magnetic_map.parquet" in err[0] and not out.exists()
    # a field in another frame than its radio map's is not one survey's
    mm = _field_of(corridor(), [0])
    write_magnetic_map(MagneticMap(mm.session_ids, mm.t_ns, mm.xy, mm.features, frame="earth"), copy / "magnetic_map.parquet")
    with pytest.raises(InputError, match="frame"):
        read_reference_field(copy / "radio_map.parquet")
    # another survey's field beside the radio map (a walk the radio map does not hold)
    write_magnetic_map(mm, copy / "magnetic_map.parquet")  # walk w0's: the previous survey surveyed w1 and w2
    with pytest.raises(InputError, match="'w0'.*not one survey's"):
        read_reference_field(copy / "radio_map.parquet", read_reference_map(copy / "radio_map.parquet"))
    assert read_reference_field(prev / "radio_map.parquet", read_reference_map(prev / "radio_map.parquet")) is not None


def test_rerun_shows_the_factors_to_the_reference_field(previous: tuple, tmp_path: Path) -> None:
    rerun = pytest.importorskip("rerun.chunk", reason="the rerun extra is not installed")
    prev, files = previous
    rrd = tmp_path / "survey.rrd"
    run_survey(SurveyInputs.from_paths([files[0], *files[3:]], reference_map=prev / "radio_map.parquet", rerun=rrd,
                                       picture=False), load_config())
    paths = {str(p) for p in rerun.RrdReader(rrd).store().schema().entity_paths()}
    assert {"/world/aligned/reference_field/factors", "/world/aligned/reference_field/samples"} <= paths


def test_the_field_factors_alone_hold_the_crowd_in_the_site_frame(previous: tuple) -> None:
    # the reference's WiFi edges taken out and the placement moved 3 m along the corridor: only the magnetic
    # factors to the held field samples place the walks in the site frame, and the solve brings them back
    from graphslam.core.survey.align import build_problem, solve

    prev, _ = previous
    survey = corridor()
    crowd = Survey(tuple(survey.sessions[k] for k in (0, 3, 4)))
    ref = read_reference_map(prev / "radio_map.parquet")
    cfg = load_config()
    pb = build_problem(crowd, cfg, reference=ref, reference_field=read_reference_field(prev / "radio_map.parquet", ref))
    assert len(pb.field_pairs) > 10
    none = np.zeros((0, 2), np.int64)
    moved = pb.init_xyh + np.array([3.0, 0.0, 0.0])
    al = solve(dataclasses.replace(pb, anchor_pairs=none, gated_anchor_pairs=none, init_xyh=moved), cfg)
    true = np.concatenate([s.ground_truth.xy for s in crowd])
    placed = np.isfinite(al.node_xyh[:, 0])
    err = np.linalg.norm(al.node_xyh[placed, :2] - true[placed], axis=1)
    assert np.median(err) < 1.0
