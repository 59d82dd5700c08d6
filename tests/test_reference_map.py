"""A surveyed radio map as the survey's anchors (survey --reference-map): reading it, placing the crowd on
it in the site frame, its fingerprints in the output map, bad files."""

from __future__ import annotations

import csv
import dataclasses
import importlib.util
import json
import math
from pathlib import Path

import numpy as np
import pytest
from test_magnetic import EARTH, corridor  # noqa: I001

from graphslam.app.survey import run_survey
from graphslam.app.survey_inputs import SurveyInputs
from conftest import run_cli as cli_main
from graphslam.config import load_config
from graphslam.core.types import Survey
from graphslam.errors import InputError
from graphslam.io.mcap_writer import write_session
from graphslam.io.radiomap_io import read_radio_map
from graphslam.core.radiomap.fingerprints import FingerprintMatrix
from graphslam.io.reference_map import _parsed_checked, _parsed_fast, read_reference_map


def reference_csv(path: Path, survey: Survey, walk: int = 0) -> Path:
    """One walk's scans at their true positions (the synthetic site frame), as a site would have them."""
    s = survey.sessions[walk]
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["fingerprint_id", "x", "y", "bssid", "rssi_dbm"])
        t = s.ground_truth.t_ns
        for k, sc in enumerate(s.scans):
            i = int(np.argmin(np.abs(t - sc.t_ns)))
            x, y = s.ground_truth.xy[i]
            for b, r in sc.readings.items():
                w.writerow([f"fp{k}", f"{x:.3f}", f"{y:.3f}", b, r])
    return path


def _write(folder: Path, survey: Survey) -> list[Path]:
    folder.mkdir()
    return [write_session(s, folder / f"{s.session_id}.mcap") for s in survey]


@pytest.fixture(scope="module")
def floor(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[Path], Path, Survey]:
    d = tmp_path_factory.mktemp("reference")
    survey = corridor()
    files = _write(d / "walks", survey)
    return d, files, reference_csv(d / "reference_map.csv", survey), survey


def test_the_reference_csv_is_read_as_a_site_map(floor: tuple) -> None:
    _, _, ref, survey = floor
    rm = read_reference_map(ref)
    assert rm.frame == "site" and len(rm) == len(survey.sessions[0].scans)
    assert set(rm.session_ids.tolist()) == {"reference"} and rm.metadata["fingerprint_ids"][:2] == ["fp0", "fp1"]
    np.testing.assert_allclose(rm.xy[0], survey.sessions[0].ground_truth.xy[0], atol=0.5)


def test_a_well_formed_reference_is_read_in_bulk_as_line_by_line(floor: tuple, tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    # Arrow's reading (a large survey) must give what the checked line-by-line reading gives: ids in order
    # of first appearance, positions, every fingerprint's readings in file order, BSSIDs stripped
    _, _, ref, _ = floor
    tricky = tmp_path / "tricky.csv"
    tricky.write_bytes(b'\xef\xbb\xbffingerprint_id,x,y,bssid,rssi_dbm\r\nb 1,1.5,2e1,aa:bb ,-50\r\n\r\n'
                       b'z,0,-0.0,aa:bb,-70\r\nb 1,1.5,20,cc,-6.25E1\r\n')
    def readings(parsed: tuple) -> list[dict]:  # each fingerprint's readings, in the order the columns give
        ids, _, row, code, names, rssi = parsed
        out: list[dict] = [{} for _ in ids]
        for r, c, v in zip(row.tolist(), code.tolist(), rssi.tolist()):
            out[r][names[c]] = v
        return out

    for path in (ref, tricky):
        fast, checked = _parsed_fast(path), _parsed_checked(path)
        assert fast is not None
        assert fast[0] == checked[0] and readings(fast) == readings(checked)
        assert [list(d) for d in readings(fast)] == [list(d) for d in readings(checked)]  # file order within one
        np.testing.assert_array_equal(fast[1], checked[1])
        # the columns give the matrix the readings' mappings give
        by_columns, by_mappings = read_reference_map(path).fingerprints, FingerprintMatrix.from_scans(readings(fast))
        assert by_columns.bssids == by_mappings.bssids and (by_columns.values != by_mappings.values).nnz == 0
        np.testing.assert_array_equal(by_columns.values.indptr, by_mappings.values.indptr)
    assert fast[0] == ["b 1", "z"] and readings(fast)[0] == {"aa:bb": -50.0, "cc": -62.5}
    # quoting is left to the strict line parser (Arrow reads '"ab"x' as abx, the line parser refuses it)
    quoted = tmp_path / "quoted.csv"
    quoted.write_text('fingerprint_id,x,y,bssid,rssi_dbm\n"b 1",1.5,2,"aa",-50\n')
    assert _parsed_fast(quoted) is None and read_reference_map(quoted).metadata["fingerprint_ids"] == ["b 1"]
    # what Arrow does not take but Python's float() does (digits grouped by "_") is read line by line
    grouped = tmp_path / "grouped.csv"
    grouped.write_text("fingerprint_id,x,y,bssid,rssi_dbm\n0,1_5,2,aa,-50\n")
    assert _parsed_fast(grouped) is None and read_reference_map(grouped).xy.tolist() == [[15.0, 2.0]]
    # a well-formed file takes the bulk reading alone, threaded from THREADED_MIN_BYTES or not
    import graphslam.io.reference_map as reference_map

    monkeypatch.setattr(reference_map, "_parsed_checked", None)
    assert read_reference_map(tricky).metadata["fingerprint_ids"] == ["b 1", "z"]
    monkeypatch.setattr(reference_map, "THREADED_MIN_BYTES", 0)
    assert read_reference_map(tricky).metadata["fingerprint_ids"] == ["b 1", "z"]


def test_the_crowd_is_placed_on_the_reference_in_the_site_frame(floor: tuple, tmp_path: Path) -> None:
    _, files, ref, survey = floor
    out = tmp_path / "out"
    res = run_survey(SurveyInputs.from_paths(files[1:], out=out, reference_map=ref, picture=False), load_config())
    r = res.report
    assert r["frame"] == "site" and r["components"][0]["n_walks"] == 4
    assert r["components"][0]["links"]["reference"] > 0 and r["reference_map"]["walks_placed_on_it"] == 4
    assert r["reference_map"]["fingerprints"] == len(survey.sessions[0].scans) and r["reference_map"]["edges"] > 0
    # no fit: the crowd's steps land where the truth has them, in the reference's frame
    for s in survey.sessions[1:]:
        est = res.alignment.tracks[s.session_id].xy
        assert np.linalg.norm(est - s.ground_truth.xy, axis=1).mean() < 1.0, s.session_id
    # the output map: the crowd's fingerprints and the reference's, in the site frame, one truth with the report
    rm = read_radio_map(out / "radio_map.parquet")
    assert rm.frame == "site" and len(rm) == r["radio_map"]["fingerprints"]
    assert (rm.session_ids == "reference").sum() == r["radio_map"]["reference_fingerprints"] == len(survey.sessions[0].scans)
    assert rm.metadata["reference"]["fingerprints"] == len(survey.sessions[0].scans)


def test_a_large_crowd_and_reference_are_linked_on_a_thread_as_in_turn(floor: tuple, monkeypatch: pytest.MonkeyPatch) -> None:
    # the links run beside the crowd's own edges from LINKS_THREAD_MIN_PAIRS crowd x reference pairs: the
    # same links, the same survey, bit for bit
    import threading

    from graphslam.core.survey import reference as R

    _, files, ref, _ = floor
    where: list[str] = []
    links = R.reference_links
    monkeypatch.setattr(R, "reference_links", lambda *a, **k: where.append(threading.current_thread().name) or links(*a, **k))
    inputs = SurveyInputs.from_paths(files[1:], reference_map=ref, picture=False)
    in_turn = run_survey(inputs, load_config()).alignment
    monkeypatch.setattr(R, "LINKS_THREAD_MIN_PAIRS", 0)
    beside = run_survey(inputs, load_config()).alignment
    assert where[0] == threading.main_thread().name and where[1].startswith("reference-links")
    assert np.array_equal(in_turn.anchor_pairs, beside.anchor_pairs) and np.array_equal(in_turn.node_xyh, beside.node_xyh)


def test_a_walk_that_matches_no_reference_place_stays_apart(floor: tuple, tmp_path: Path) -> None:
    d, files, _, survey = floor
    # a reference of the corridor's first 40 m only; a walk of a corridor 25 m away shares nothing with it
    rows = list(csv.reader(open(d / "reference_map.csv")))
    near = [rows[0]] + [row for row in rows[1:] if float(row[1]) < 40.0]
    small = tmp_path / "small.csv"
    with open(small, "w", newline="") as fh:
        csv.writer(fh).writerows(near)
    from test_magnetic import Field, walk

    far = walk("far", 60.0, 95.0, Field(0), t0=survey.sessions[-1].steps.t_ns[-1] + 10**12, dr_turn=0.4,
               rng=np.random.default_rng(9), y0=25.0)
    paths = files[1:] + [write_session(far, tmp_path / "far.mcap")]
    r = run_survey(SurveyInputs.from_paths(paths, reference_map=small, picture=False), load_config()).report
    main = set(r["components"][0]["walks"])
    assert "far" not in main and len(main) >= 1
    assert any("far" in c["walks"] and c["reason"] for c in r["components"][1:])
    # a reference no walk registers onto is not used, and the report says so
    tiny = tmp_path / "tiny.csv"
    with open(tiny, "w", newline="") as fh:
        csv.writer(fh).writerows([rows[0]] + [row for row in rows[1:] if float(row[1]) < 6.0])
    r = run_survey(SurveyInputs.from_paths(paths, reference_map=tiny, picture=False), load_config()).report
    assert r["frame"] == "earth" and r["reference_map"]["used"] is False and r["components"][0]["n_walks"] > 0


@pytest.mark.parametrize("body, field", [
    ("fingerprint_id,x,y,bssid\n0,1,2,aa\n", "header"),
    ("fingerprint_id,x,y,bssid,rssi_dbm\n0,1,nan,aa,-50\n", "y"),
    ("fingerprint_id,x,y,bssid,rssi_dbm\n0,1,2,aa,loud\n", "rssi_dbm"),
    ("fingerprint_id,x,y,bssid,rssi_dbm\n", "no fingerprint"),
    ("fingerprint_id,x,y,bssid,rssi_dbm\n0,1,2,aa,-50\n0,1,2,aa,-60\n", "bssid"),
    ("fingerprint_id,x,y,bssid,rssi_dbm\n0,1,2,aa,-50\n0,1,3,bb,-60\n", "x"),
    ("fingerprint_id,x,y,bssid,rssi_dbm\n,1,2,aa,-50\n", "fingerprint_id"),
    ("fingerprint_id,x,y,bssid,rssi_dbm\n0,1,2,aa,-50,7\n", "columns"),
])
def test_a_bad_reference_file_is_one_line_and_exit_2(floor: tuple, tmp_path: Path, body: str, field: str,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    _, files, _, _ = floor
    bad = tmp_path / "bad.csv"
    bad.write_text(body)
    assert _parsed_fast(bad) is None  # the line-by-line reading names the line and field
    with pytest.raises(InputError, match=field):
        read_reference_map(bad)
    out = tmp_path / "out"
    assert cli_main(["survey", str(files[1]), "--out", str(out), "--reference-map", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(bad) in err[0] and not out.exists()


def test_a_radio_map_in_another_frame_is_no_reference(floor: tuple, tmp_path: Path) -> None:
    _, files, _, _ = floor
    out = tmp_path / "earth"
    run_survey(SurveyInputs.from_paths(files, out=out, picture=False), load_config())  # frame earth
    with pytest.raises(InputError, match="frame"):
        read_reference_map(out / "radio_map.parquet")


def test_a_site_radio_map_a_survey_wrote_is_a_reference(floor: tuple, tmp_path: Path) -> None:
    _, files, ref, _ = floor
    first = tmp_path / "first"
    run_survey(SurveyInputs.from_paths(files[1:3], out=first, reference_map=ref, picture=False), load_config())
    again = run_survey(SurveyInputs.from_paths(files[3:], reference_map=first / "radio_map.parquet", picture=False),
                       load_config()).report
    assert again["frame"] == "site" and again["components"][0]["n_walks"] == 2


def test_an_update_on_a_reference_is_solved_in_full(floor: tuple, tmp_path: Path) -> None:
    _, files, ref, _ = floor
    out = tmp_path / "out"
    run_survey(SurveyInputs.from_paths(files[1:4], out=out, reference_map=ref, picture=False), load_config())
    r = run_survey(SurveyInputs.from_paths(files[1:], out=out, reference_map=ref, previous=out, picture=False),
                   load_config()).report
    assert r["update"]["mode"] == "full" and "reference" in r["update"]["reason"]
    assert r["components"][0]["n_walks"] == 4
    # without the reference this time: the state holds neither it nor the site's rotation from east/north, so
    # the floor is solved in full without it and says its frame as it is (not the site frame the walks had)
    r = run_survey(SurveyInputs.from_paths(files[1:], out=tmp_path / "again", previous=out, picture=False),
                   load_config()).report
    assert r["update"]["mode"] == "full" and "placed on a reference map" in r["update"]["reason"]
    assert r["frame"] == "earth" and "reference_map" not in r


def test_walks_without_headings_are_registered_onto_the_reference_over_every_rotation(
    floor: tuple, tmp_path: Path
) -> None:
    """A foot-mounted module's walks (no /phone/heading: each dead reckoning in a frame of its own, here
    turned by its own angle) are placed on the reference all the same, in its site frame."""
    _, _, ref, survey = floor
    paths = []
    for k, s in enumerate(survey.sessions[1:]):
        a = 0.7 + 1.1 * k  # each walk's dead reckoning turned its own way: no common frame to start from
        c, sn = math.cos(a), math.sin(a)
        xy = np.asarray(s.steps.xy) @ np.array([[c, sn], [-sn, c]])
        steps = dataclasses.replace(s.steps, xy=xy, heading=np.asarray(s.steps.heading) + a)
        paths.append(write_session(dataclasses.replace(s, steps=steps, heading=None), tmp_path / f"{s.session_id}.mcap"))
    res = run_survey(SurveyInputs.from_paths(paths, out=tmp_path / "out", reference_map=ref, picture=False),
                     load_config())
    r = res.report
    assert r["frame"] == "site" and r["registration"]["method"] == "reference" and r.get("site_from_earth_deg") is None
    assert r["components"][0]["n_walks"] == 4 and r["reference_map"]["walks_placed_on_it"] == 4
    assert r["components"][0]["links"]["reference"] > 0
    for s in survey.sessions[1:]:  # no fit: where the truth has them
        est = res.alignment.tracks[s.session_id].xy
        assert np.linalg.norm(est - s.ground_truth.xy, axis=1).mean() < 1.5, s.session_id
    assert read_radio_map(tmp_path / "out" / "radio_map.parquet").frame == "site"
    # the same walks without the reference: no site frame (and no error)
    alone = run_survey(SurveyInputs.from_paths(paths, picture=False), load_config()).report
    assert alone["frame"] != "site" and "reference_map" not in alone
    # a reference no walk registers onto (its first 6 m) is not used, and the report says so
    rows = list(csv.reader(open(ref)))
    tiny = tmp_path / "tiny.csv"
    with open(tiny, "w", newline="") as fh:
        csv.writer(fh).writerows([rows[0]] + [row for row in rows[1:] if float(row[1]) < 6.0])
    r = run_survey(SurveyInputs.from_paths(paths, reference_map=tiny, picture=False), load_config()).report
    assert r["frame"] != "site" and r["reference_map"]["used"] is False and r["registration"]["method"] != "reference"


def test_the_site_rotation_comes_from_the_crowds_matches(floor: tuple, tmp_path: Path) -> None:
    _, files, ref, survey = floor
    res = run_survey(SurveyInputs.from_paths(files[1:], reference_map=ref, picture=False), load_config())
    # the walks' headings are east/north; the site frame is turned EARTH from it: the placed headings show it
    s = survey.sessions[1]
    est = res.alignment.tracks[s.session_id]
    dh = np.angle(np.exp(1j * (est.heading - s.ground_truth.heading))).mean()
    assert abs(math.degrees(dh)) < 3.0
    assert json.dumps(res.report["reference_map"])  # JSON-ready
    assert EARTH != 0.0


def test_bench_real_surveys_the_crowd_on_the_floors_reference(floor: tuple, tmp_path: Path,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    d, files, ref, _ = floor
    folder = tmp_path / "floor"
    folder.mkdir()
    for f in files:
        (folder / f.name).write_bytes(f.read_bytes())
    (folder / "reference_map.csv").write_bytes(ref.read_bytes())
    capsys.readouterr()
    assert cli_main(["-q", "bench", "real", str(folder), "--variants", "reference_map"]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    row = next(r for r in rows if r.get("variant") == "reference_map")
    # the crowd: every walk but the one whose scans the reference holds verbatim
    assert row["floor"] == "floor" and row["walks"] == 4 and row["main"] == 4 and row["frame"] == "site"
    assert row["reference_map"].endswith("reference_map.csv") and row["walks_over_6m"] == 0
    assert cli_main(["-q", "bench", "real", str(folder), "--variants", "reference_map", "--reference-map", "none"]) == 0
    assert not [r for r in map(json.loads, capsys.readouterr().out.splitlines()) if r.get("variant")]


def test_edges_beyond_the_tight_gate_join_when_a_solve_brings_them_within_it(floor: tuple) -> None:
    from dataclasses import replace

    from graphslam.core.survey.align import _regated, build_problem
    from graphslam.io.mcap_reader import read_recordings

    _, files, ref, _ = floor
    cfg = load_config()
    problem = build_problem(read_recordings(files[1:]).survey, cfg, reference=read_reference_map(ref))
    a, b, c, e = problem.fingerprints.node[[0, 1, 2, 3]]
    xyh = problem.init_xyh.copy()
    xyh[b, :2] = xyh[a, :2] + [1.0, 0.0]  # within the 6 m gate
    xyh[e, :2] = xyh[c, :2] + [20.0, 0.0]  # beyond it
    gated = replace(problem, gated_wifi_pairs=np.array([[a, b], [c, e]]), gated_anchor_pairs=np.zeros((0, 2), np.int64))
    wider = _regated(gated, xyh, cfg)
    assert wider is not None and wider.init_xyh is xyh
    assert len(wider.wifi_pairs) == len(problem.wifi_pairs) + 1 and wider.wifi_pairs[-1].tolist() == [a, b]
    assert wider.gated_wifi_pairs.tolist() == [[c, e]]  # a wrong edge stays out
    # a reference edge likewise: node a within the gate of the reference fingerprint it names
    r = int(np.argmin(np.linalg.norm(problem.anchor_xy - xyh[a, :2], axis=1)))
    near = replace(gated, gated_wifi_pairs=np.zeros((0, 2), np.int64), gated_anchor_pairs=np.array([[a, r]]))
    assert _regated(near, xyh, cfg).anchor_pairs[-1].tolist() == [a, r]
    assert _regated(replace(gated, gated_wifi_pairs=np.array([[c, e]])), xyh, cfg) is None  # nothing joins: no pass


def _paper_walks_and_reference(tmp_path: Path) -> tuple[list[Path], Path]:
    """``paper`` seed 1's walks 1-4 as recordings and walk 0's scans at their true places as the reference."""
    from graphslam.sim import simulate

    survey = simulate("paper", seed=1, size=1).survey
    ref = reference_csv(tmp_path / "reference_map.csv", survey, walk=0)
    return [write_session(s, tmp_path / f"{s.session_id}.mcap") for s in survey.sessions[1:]], ref


def test_walks_that_drift_far_from_where_the_reference_places_them_are_bent_onto_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # the simulator's long office walks: placed rigidly on the reference, their far ends lie beyond the
    # tight gate until a solve bends them; without the second pass the map is twice as far off
    import graphslam.core.survey.align as align_mod

    files, ref = _paper_walks_and_reference(tmp_path)

    def landmark_mean() -> tuple[float, int, dict]:
        res = run_survey(SurveyInputs.from_paths(files, reference_map=ref, picture=False), load_config())
        opt = res.report["optimizer"]
        return res.evaluation.landmarks.mean_m, opt["stages"], opt["regated_edges"]

    with_passes, stages, regated = landmark_mean()
    monkeypatch.setattr(align_mod, "_REGATE_ROUNDS", 0)
    without, stages0, regated0 = landmark_mean()
    assert stages > stages0 and regated0 == {"wifi": 0, "reference": 0}
    assert regated["wifi"] > 0 and regated["reference"] > 0  # the report says what joined
    assert with_passes < 0.8 and with_passes < 0.6 * without


def test_a_regating_pass_another_follows_stops_early_and_the_last_converges(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # a pass whose solution only chooses the next pass's edges stops at _REGATE_PASS_ITERATIONS; when
    # nothing more joins after it, LM finishes on its graph: the output is converged either way
    import graphslam.core.survey.align as align_mod

    files, ref = _paper_walks_and_reference(tmp_path)
    monkeypatch.setattr(align_mod, "_REGATE_PASS_ITERATIONS", 1)

    def passes() -> tuple[list[int], bool]:
        al = run_survey(SurveyInputs.from_paths(files, reference_map=ref, picture=False), load_config()).alignment
        stages = [r.stage for r in al.iterations]
        return [stages.count(s) for s in sorted(set(stages))], al.converged

    counts, converged = passes()
    assert converged and counts[-2] == 1 and counts[-1] >= 1  # the first pass capped, the second to the end
    real = align_mod._regated
    calls = []

    def once(*args: object) -> object:  # the second re-gating finds nothing: the capped pass is finished
        calls.append(1)
        return real(*args) if len(calls) == 1 else None

    monkeypatch.setattr(align_mod, "_regated", once)
    counts_once, converged_once = passes()
    assert converged_once and len(calls) == 2 and counts_once[-2] == 1 and len(counts_once) == len(counts)


def test_with_gated_edges_the_final_radius_runs_on_the_regated_graph(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # the first round stops before the final saturation radius when a placement left edges beyond the
    # gate: its stage on the narrower graph would be solved again at once; when nothing joins, the
    # final radius still runs, on the graph as it is
    import graphslam.core.survey.align as align_mod

    files, ref = _paper_walks_and_reference(tmp_path)

    def stages() -> tuple[list[int], list[int], bool]:
        al = run_survey(SurveyInputs.from_paths(files, reference_map=ref, picture=False), load_config()).alignment
        first = {}
        for r in al.iterations:
            first.setdefault(r.stage, r.active_edges)
        return sorted(first), [first[s] for s in sorted(first)], al.converged

    order, active, converged = stages()
    assert converged and len(order) >= 2
    assert active[1] > active[0]  # the second LM call already holds the joined edges
    monkeypatch.setattr(align_mod, "_regated", lambda *args: None)
    order_none, active_none, converged_none = stages()
    assert converged_none and len(order_none) == 2 and active_none[1] <= active_none[0]


def test_every_output_says_the_reference_map_placed_the_site_frame(floor: tuple, tmp_path: Path) -> None:
    """report.json's frame description, its site rotation and survey.png's title (drawn now and again from
    the folder) name what placed the main map: the reference map, by its file."""
    from PIL import Image

    from graphslam.viz import survey_picture

    _, files, ref, _ = floor
    out = tmp_path / "out"
    r = run_survey(SurveyInputs.from_paths(files[1:], out=out, reference_map=ref), load_config()).report
    assert r["frame"] == "site" and "reference map" in r["frame_description"]
    # the walks' headings are east/north, turned EARTH from the synthetic site frame: the site is -EARTH from them
    assert abs(r["site_from_earth_deg"] + math.degrees(EARTH)) < 3.0
    with Image.open(out / "survey.png") as im:
        assert "placed by the reference map reference_map.csv" in im.text["Title"]
    img = np.asarray(Image.open(out / "survey.png").convert("RGB")).astype(int)
    grey = (np.abs(img - np.array(survey_picture.REFERENCE)).max(axis=2) <= 3).sum()
    assert grey > len(read_reference_map(ref)) * 4  # its places drawn, a few pixels each
    # drawn again from the folder: the same reference, its rows the radio map's last ones
    again = survey_picture.scene_of_folder(out)
    assert again.reference_map == "reference_map.csv"
    np.testing.assert_allclose(np.sort(again.reference_xy, axis=0), np.sort(read_reference_map(ref).xy, axis=0), atol=1e-9)
    texts = [e.text for e in survey_picture.survey_picture(again).legend]
    assert any(t.startswith("reference map reference_map.csv: ") for t in texts)
    # without a reference (headings alone): no site rotation, and the title says nothing of one
    plain = run_survey(SurveyInputs.from_paths(files, out=tmp_path / "plain"), load_config()).report
    assert plain["frame"] == "earth" and "site_from_earth_deg" not in plain
    with Image.open(tmp_path / "plain" / "survey.png") as im:
        assert "reference map" not in im.text["Title"]
    assert not len(survey_picture.scene_of_folder(tmp_path / "plain").reference_xy)


def test_the_report_says_how_far_apart_the_reference_measured_its_places(floor: tuple, tmp_path: Path) -> None:
    from graphslam.core.survey.reference import place_spacing

    grid = np.array([(x, y) for x in (0.0, 4.0, 8.0) for y in (0.0, 4.0, 8.0)])
    assert place_spacing(np.repeat(grid, 3, axis=0)) == 4.0  # three scans at each point: one place
    assert place_spacing(np.zeros((5, 2))) is None
    _, files, ref, _ = floor
    r = run_survey(SurveyInputs.from_paths(files[1:], reference_map=ref, picture=False), load_config()).report
    assert r["reference_map"]["spacing_m"] == round(place_spacing(read_reference_map(ref).xy), 2) > 0


def test_a_reference_from_a_louder_device_gives_the_same_survey(floor: tuple, tmp_path: Path) -> None:
    """The reference's device hears every AP a constant louder or weaker than the crowd's phones: the
    offset is estimated from the best matches and taken off for the WiFi edges (the placement's power
    cosine cancels it by itself), so the survey is the one a same-device reference gives."""
    from graphslam.core.radiomap.fingerprints import FingerprintMatrix as FM
    from graphslam.core.radiomap.similarity import Matches
    from graphslam.core.survey.reference import louder, rss_offset_db

    crowd = FM.from_scans([{"a": -60.0, "b": -70.0, "c": -80.0}, {"a": -50.0, "d": -75.0}])
    ref = FM.from_scans([{"a": -53.0, "b": -63.0, "c": -73.0, "e": -40.0}, {"a": -43.0, "d": -68.0, "e": -30.0}],
                        bssids=crowd.bssids + ("e",))
    crowd = FM(ref.bssids, sparse_hstack(crowd.values, 1), crowd.missing_dbm, crowd.extra_sq, crowd.extra_n)
    top = Matches(np.array([0, 0, 1]), np.array([1, 0, 1]), np.array([0.5, 0.9, 0.8]))  # best: 0 -> 0, 1 -> 1
    assert rss_offset_db(crowd, ref, top, min_common=2) == pytest.approx(7.0)
    assert rss_offset_db(crowd, ref, top, min_common=4) == 0.0  # no pair shares four APs
    quiet = louder(ref, -45.0)  # readings at or below the missing level (-110 dBm) are no readings
    assert quiet.values[0].nnz == 3 and quiet.values[1].nnz == 2
    # a survey on the reference read 8 dB louder: the same walks where they were, its offset 8 dB more
    _, files, ref_csv, _ = floor
    loud = tmp_path / "loud.csv"
    with open(ref_csv, newline="") as src, open(loud, "w", newline="") as dst:
        rows = list(csv.reader(src))
        csv.writer(dst).writerows([rows[0]] + [r[:4] + [f"{float(r[4]) + 8.0:g}"] for r in rows[1:]])
    same, louder_run = (run_survey(SurveyInputs.from_paths(files[1:], reference_map=r, picture=False), load_config())
                        for r in (ref_csv, loud))
    a, b = same.report["reference_map"], louder_run.report["reference_map"]
    assert b["rss_offset_db"] == pytest.approx(a["rss_offset_db"] + 8.0, abs=0.02) and b["edges"] == a["edges"]
    for sid, tr in same.alignment.tracks.items():
        np.testing.assert_allclose(louder_run.alignment.tracks[sid].xy, tr.xy, atol=1e-6)


def sparse_hstack(m, extra_columns: int):  # noqa: ANN001, ANN201 - a test helper: columns of zeros on the right
    from scipy import sparse

    return sparse.hstack([m, sparse.csr_matrix((m.shape[0], extra_columns))]).tocsr()


@pytest.mark.skipif(importlib.util.find_spec("distributed") is None, reason="the batch extra (Dask) is not installed")
def test_survey_batch_surveys_a_floor_on_the_reference_map_its_folder_holds(floor: tuple, tmp_path: Path) -> None:
    """A real local Dask cluster: a floor folder holding reference_map.csv is surveyed on it (site frame,
    its report names the file), the same walks without one by their headings (earth frame), and a broken
    reference_map.csv fails its floor alone, the file and field named."""
    _, files, ref, _ = floor
    sites = tmp_path / "sites"
    for name in ("surveyed", "plain", "broken"):
        (sites / name).mkdir(parents=True)
        for f in files:
            (sites / name / f.name).write_bytes(f.read_bytes())
    (sites / "surveyed" / "reference_map.csv").write_bytes(ref.read_bytes())
    (sites / "broken" / "reference_map.csv").write_text("fingerprint_id,x,y,bssid,rssi_dbm\nfp0,1.0,north,aa:bb,-60\n")
    out = tmp_path / "out"
    assert cli_main(["survey-batch", str(sites), "--out", str(out), "--workers", "2", "--no-progress"]) == 1
    rows = {r["floor"]: r for r in json.loads((out / "summary.json").read_text())}
    assert {k: (r["status"], r["frame"]) for k, r in rows.items()} == {
        "surveyed": ("ok", "site"), "plain": ("ok", "earth"), "broken": ("failed", None)}
    report = json.loads((out / "surveyed" / "report.json").read_text())
    assert report["frame"] == "site" and report["reference_map"]["source"].endswith("reference_map.csv")
    assert "reference_map" not in json.loads((out / "plain" / "report.json").read_text())
    assert str(sites / "broken" / "reference_map.csv") in rows["broken"]["error"] and "[field y]" in rows["broken"]["error"]
    assert not (out / "broken").exists()  # nothing written for the failed floor
