"""The PNG pictures (graphslam.viz.*_picture): real files read back with Pillow, drawn by the real
commands (survey, plot, track, locate) on simulated recordings."""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import numpy as np
import pytest
from conftest import run_cli
from PIL import Image

from graphslam.app.survey import run_survey
from graphslam.app.survey_inputs import SurveyInputs
from graphslam.config import GraphSlamConfig
from graphslam.io.mcap_reader import read_survey
from graphslam.io.mcap_writer import write_session
from graphslam.sim import simulate
from graphslam.viz import radiomap_picture, survey_picture, track_picture
from graphslam.viz.common import session_colours

NO_WIFI = 5  # the corridor walk recorded without WiFi: it cannot be aligned


def _rgb(path: Path) -> np.ndarray:
    with Image.open(path) as im:
        assert im.format == "PNG"
        return np.asarray(im.convert("RGB")).astype(int)


def _colours_present(img: np.ndarray, colours: dict[str, tuple[int, int, int]], min_px: int = 40) -> set[str]:
    """Ids whose colour covers at least ``min_px`` pixels (within 10 of each channel: antialiasing)."""
    return {sid for sid, c in colours.items() if int((np.abs(img - np.array(c)).max(axis=2) <= 10).sum()) >= min_px}


@pytest.fixture(scope="module")
def corridor_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, object]:
    """12 corridor walks (one without WiFi) and 2 held-out walks, surveyed into OUT (with survey.png)."""
    root = tmp_path_factory.mktemp("pictures")
    sim = simulate("corridor", seed=0, test_walks=2)
    sim.write(root / "rec")
    lonely = sim.survey.sessions[NO_WIFI]
    write_session(dataclasses.replace(lonely, scans=()), root / "rec" / f"{lonely.session_id}.mcap")
    result = run_survey(SurveyInputs(tuple(sorted((root / "rec").glob("*.mcap"))), root / "out"))
    # corridor APs lie on one line, so fit-aps rightly fits none: give `track` the simulator's APs,
    # moved into the map frame through the survey's landmark fit (a test shortcut, not the product)
    from graphslam.core.tracking.apmodel import ApModel, ApModels
    from graphslam.io.apmodel_io import write_ap_models
    from graphslam.viz.common import site_to_frame

    aps = sim.building.aps
    xy = site_to_frame(np.array(result.evaluation.site_from_aligned), aps.xy)
    cov = tuple(tuple(float(v) for v in row) for row in np.eye(4) * 0.1)
    fitted = tuple(ApModel(b, float(p[0]), float(p[1]), float(p0), float(g), 4.0, 50, cov)
                   for b, p, p0, g in zip(aps.bssids, xy, aps.p0_dbm, aps.gamma))
    from graphslam.io.radiomap_io import read_radio_map

    rm = read_radio_map(root / "out" / "radio_map.parquet")
    write_ap_models(ApModels(rm.frame, 1.0, fitted, ()), root / "aps.json", radio_map=rm)
    return root, root / "out", result


def test_survey_writes_survey_png_with_one_colour_per_aligned_walk(corridor_run: tuple) -> None:
    _, out, result = corridor_run
    al = result.alignment
    lonely = al.session_ids[NO_WIFI]
    # without WiFi the walk is not in the main map: unaligned, or a component of its own
    assert lonely not in al.main_tracks() and len(al.main_tracks()) == len(al.session_ids) - 1
    assert lonely in al.unaligned or al.component_of()[lonely] != 0
    png = out / "survey.png"
    assert result.files["picture"] == png
    with Image.open(png) as im:
        assert im.size == survey_picture.SIZE_PX
    present = _colours_present(_rgb(png), session_colours(al.session_ids))
    # every aligned walk in its own colour (another component's in the strip below), an unaligned one not drawn
    assert present == set(al.tracks)
    assert not list(out.glob(".*"))  # written atomically: no temporary file left over
    assert result.report["timings_s"]["picture"] > 0


def test_legend_lists_unaligned_walks_with_reason_and_the_reference(corridor_run: tuple) -> None:
    _, out, result = corridor_run
    al = result.alignment
    scene = survey_picture.scene_of_alignment(result.survey, al, GraphSlamConfig(), result.evaluation)
    texts = [e.text for e in survey_picture.survey_picture(scene).legend]
    lonely = al.session_ids[NO_WIFI]
    if lonely in al.unaligned:  # listed under its reason
        reason = al.unaligned[lonely]
        hit = [t for t in texts if lonely in t]
        assert len(hit) == 1 and reason in hit[0]
    else:  # a component of its own: listed with its component, the component's reason in the legend
        k = al.component_of()[lonely]
        reason = next(c.reason for c in al.components if c.index == k)
        assert f"{lonely} (component {k})" in texts and reason
        assert any(reason in t and f"component {k})" in t for t in texts)
    assert any(t.startswith(f"reference {al.reference}") for t in texts)
    assert scene.marks is not None and scene.marks.stats.n >= 2  # landmark truth / estimate / error drawn
    # every edge between aligned walks is counted, by state, as in report.json
    assert len(scene.edge_xy) == sum(scene.edge_counts) <= survey_picture.MAX_EDGES  # small: none subsampled
    states = result.report["edges"]["wifi_states"]
    assert list(scene.edge_counts) == [states["inactive"], states["ramp"], states["saturated"]]


def test_plot_redraws_the_folder_over_a_floor_plan_with_floor_info(corridor_run: tuple, tmp_path: Path) -> None:
    root, out, result = corridor_run
    plan = tmp_path / "floor_image.png"
    Image.new("RGB", (300, 40), (255, 220, 120)).save(plan)  # a plan colour no walk has
    (tmp_path / "floor_info.json").write_text(json.dumps({"map_info": {"width": 90.0, "height": 12.0}}))
    before = (out / "survey.png").stat().st_mtime_ns
    assert run_cli(["-q", "plot", str(out), "--floor-plan", str(plan), "--recordings", str(root / "rec")]) == 0
    img = _rgb(out / "survey.png")
    assert (out / "survey.png").stat().st_mtime_ns != before
    assert img.shape[:2] == survey_picture.SIZE_PX[::-1]
    assert _colours_present(img, session_colours(result.alignment.session_ids)) == set(result.alignment.tracks)
    # the plan is underneath (drawn at alpha 0.85 over white)
    assert (np.abs(img - np.array([255, 225, 140])).max(axis=2) <= 12).sum() > 2_000
    with Image.open(out / "radio_map.png") as im:  # as wide as ever; no taller than the floor needs
        assert im.size[0] == radiomap_picture.SIZE_PX[0] and im.size[1] <= radiomap_picture.SIZE_PX[1]


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--floor-plan", "{tmp}/missing.png", "--floor-size", "10", "10"], "floor plan image not found"),
        (["--floor-plan", "{tmp}/not_an_image.png", "--floor-size", "10", "10"], "cannot read the floor plan image"),
        (["--floor-plan", "{tmp}/plain.png"], "give --floor-size W H"),
        (["--floor-plan", "{tmp}/plain.png", "--floor-size", "0", "5"], "floor size must be two positive numbers"),
        (["--floor-size", "10", "10"], "--floor-size given without --floor-plan"),
        (["--ap", "ff:ff:ff:ff:ff:ff"], "--ap ff:ff:ff:ff:ff:ff: no fingerprint"),
    ],
)
def test_plot_errors_are_one_line_and_exit_2(
    corridor_run: tuple, tmp_path: Path, capsys: pytest.CaptureFixture, extra: list[str], message: str
) -> None:
    _, out, _ = corridor_run
    (tmp_path / "not_an_image.png").write_bytes(b"not a png at all")
    Image.new("RGB", (20, 10)).save(tmp_path / "plain.png")
    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    assert run_cli(["-q", "plot", str(out)] + [a.format(tmp=tmp_path) for a in extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and message in err[0]
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == before  # nothing (re)written


def test_plot_needs_a_survey_folder(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert run_cli(["-q", "plot", str(tmp_path)]) == 2
    assert "no trajectories.csv" in capsys.readouterr().err


def test_radio_map_picture_marks_fitted_aps(corridor_run: tuple, tmp_path: Path) -> None:
    _, out, _ = corridor_run
    from graphslam.core.tracking.apmodel import ApModel, ApModels
    from graphslam.io.radiomap_io import read_radio_map

    rm = read_radio_map(out / "radio_map.parquet")
    # corridor APs lie on one line: fit-aps rightly fits none of them, so place one by hand
    bssid = rm.bssids[0]
    x, y = np.asarray(rm.xy).mean(axis=0)
    cov = tuple(tuple(float(v) for v in row) for row in np.eye(4) * 0.1)
    models = ApModels(rm.frame, 1.0, (ApModel(bssid, float(x), float(y), -40.0, 2.5, 4.0, 50, cov),), ())
    plain, starred = tmp_path / "plain.png", tmp_path / "starred.png"
    radiomap_picture.draw_radio_map(rm, plain, aps=[bssid])
    radiomap_picture.draw_radio_map(rm, starred, aps=[bssid], ap_models=models)
    red = lambda p: int((np.abs(_rgb(p) - np.array([255, 0, 0])).max(axis=2) <= 30).sum())  # noqa: E731
    assert red(plain) == 0 and red(starred) > 30  # the fitted AP position: a red star
    h, w = _rgb(plain).shape[:2]
    assert w == radiomap_picture.SIZE_PX[0] and radiomap_picture.MIN_HEIGHT_PX <= h <= radiomap_picture.SIZE_PX[1]


def _radio_map(width_m: float, height_m: float, n: int = 600) -> object:
    from graphslam.core.radiomap.radiomap import RadioMap

    rng = np.random.default_rng(0)
    xy = np.column_stack([rng.uniform(0, width_m, n), rng.uniform(0, height_m, n)])
    aps = [(width_m * (j + 0.5) / 10, height_m / 2) for j in range(10)]
    scans = [{f"ap{j}": float(-40 - 0.3 * np.hypot(p[0] - a[0], p[1] - a[1])) for j, a in enumerate(aps)} for p in xy]
    return RadioMap.from_scans(scans, xy, session_ids=[f"s{i % 4}" for i in range(n)], t_ns=np.arange(n), frame="site")


def test_radio_map_picture_fits_a_wide_floor() -> None:
    """A 200 m x 20 m floor: the panels run wide, two a row, and the picture is no taller than they
    need; the floor covers far more of it than on a grid of panels shaped for a square floor."""
    def covered(pic: object, w: float, h: float) -> float:
        return sum(p.scale ** 2 * w * h for p in pic.panels) / (pic.size[0] * pic.size[1])  # type: ignore[attr-defined]

    wide = radiomap_picture.radio_map_picture(_radio_map(200.0, 20.0))
    assert len(wide.panels) == 7 and wide.size[0] == radiomap_picture.SIZE_PX[0] and wide.size[1] < 900
    boxes = [p.box for p in wide.panels]
    assert all((b[2] - b[0]) > 4 * (b[3] - b[1]) for b in boxes)  # wide panels for a wide floor
    assert len({b[0] for b in boxes}) == 2  # two columns
    assert covered(wide, 200.0, 20.0) > 0.12  # ~0.05 with the square floor's 3 x 3 grid
    # a floor about as wide as it is tall keeps three panels a row
    square = radiomap_picture.radio_map_picture(_radio_map(120.0, 80.0))
    assert len({p.box[0] for p in square.panels}) == 3 and covered(square, 120.0, 80.0) > 0.25


def test_track_and_locate_draw_one_colour_per_session(corridor_run: tuple, capsys: pytest.CaptureFixture) -> None:
    root, out, _ = corridor_run
    test_dir = root / "rec" / "test"
    ids = sorted(p.stem for p in test_dir.glob("*.mcap"))
    rm = str(out / "radio_map.parquet")
    log = ["--progress-interval", "0"]  # stderr is not a terminal here: progress as log lines
    track = [*log, "track", str(test_dir), "--radio-map", rm, "--ap-models", str(root / "aps.json"), "--out"]
    assert run_cli(track + [str(out / "track.csv")]) == 0
    assert run_cli([*log, "locate", str(test_dir), "--radio-map", rm, "--out", str(out / "positions.csv")]) == 0
    assert run_cli([*log, "fit-aps", "--radio-map", rm, "--out", str(out / "fitted.json")]) == 0
    err = capsys.readouterr().err
    n_steps = sum(len(read_survey([test_dir]).sessions[k].steps) for k in range(len(ids)))
    assert f"progress track: {n_steps:,}/{n_steps:,} steps (100 %) done in" in err
    assert re.search(r"progress locate: (\d+)/\1 scans \(100 %\) done in", err)
    assert re.search(r"progress fit-aps: (\d+)/\1 APs \(100 %\) done in", err)
    assert err.count("progress picture: done in") == 2
    for name in ("track.png", "positions.png"):
        img = _rgb(out / name)
        assert img.shape[:2] == track_picture.SIZE_PX[::-1]
        assert _colours_present(img, session_colours(ids)) == set(ids)


def test_wifi_edges_file_ties_radio_map_rows(corridor_run: tuple, tmp_path: Path) -> None:
    from graphslam.errors import InputError
    from graphslam.io.edges_io import read_wifi_edges
    from graphslam.io.radiomap_io import read_radio_map

    _, out, result = corridor_run
    xy = np.asarray(read_radio_map(out / "radio_map.parquet").xy)
    e = read_wifi_edges(out / "wifi_edges.parquet", len(xy))
    assert len(e.a) > 0
    np.testing.assert_allclose(np.linalg.norm(xy[e.a] - xy[e.b], axis=1), e.distance_m, atol=1e-4)
    states = result.report["edges"]["wifi_states"]
    assert np.bincount(e.state, minlength=3).tolist() == [states["inactive"], states["ramp"], states["saturated"]]
    with pytest.raises(InputError, match="outside the radio map"):
        read_wifi_edges(out / "wifi_edges.parquet", int(max(e.a.max(), e.b.max())))
    (tmp_path / "bad.parquet").write_bytes(b"PAR1 not really")
    with pytest.raises(InputError, match="cannot read WiFi edges"):
        read_wifi_edges(tmp_path / "bad.parquet")


def test_radio_map_picture_has_the_expected_accuracy_panel(corridor_run: tuple, tmp_path: Path) -> None:
    from graphslam.core.radiomap.radiomap import RadioMap
    from graphslam.io.radiomap_io import read_radio_map

    _, out, _ = corridor_run
    rm = read_radio_map(out / "radio_map.parquet")
    one = np.flatnonzero(rm.session_ids == rm.session_ids[0])
    lone = RadioMap.from_fingerprints(rm.fingerprints.rows(one), rm.xy[one], session_ids=rm.session_ids[one],
                                      t_ns=rm.t_ns[one], frame=rm.frame, min_rssi_dbm=rm.min_rssi_dbm)

    def accuracy_panel(m: RadioMap, name: str) -> np.ndarray:
        pic = radiomap_picture.radio_map_picture(m, aps=[m.bssids[0]])
        # coverage, expected accuracy, the AP: each with its colour bar
        assert len(pic.panels) == 3 and [c[4] for c in pic.colourbars] == ["fingerprints / m²", "error (m)", "RSS (dBm)"]
        pic.save(tmp_path / name)
        x0, y0, x1, y1 = pic.panels[1].box
        return _rgb(tmp_path / name)[y0:y1, x0:x1]

    colourful = lambda img: int((img.max(axis=2) - img.min(axis=2) > 60).sum())  # noqa: E731
    grey = lambda img: int((np.abs(img - radiomap_picture.NOT_LOCATED[0] - 4) <= 3).all(axis=2).sum())  # noqa: E731
    walks = accuracy_panel(rm, "walks.png")  # cells coloured by their error, none grey: every walk has others
    assert colourful(walks) > 200 and grey(walks) < 20
    alone = accuracy_panel(lone, "alone.png")  # one walk: its cells grey, nothing to compare
    assert colourful(alone) == 0 and grey(alone) > 200


def test_survey_png_draws_control_points_apart_from_landmarks(tmp_path: Path) -> None:
    """Control points (given: they tie the walks that mark them) in their own marker and colour, at
    their site positions; the other landmarks (evaluation only) as crosses; plot redraws them from
    report.json."""
    sim = simulate("crowd", seed=0, size=0.25)
    marks: dict[str, tuple[float, float]] = {}
    for s in sim.survey:
        write_session(s, tmp_path / "rec" / f"{s.session_id}.mcap")
        for m in s.landmarks:
            marks.setdefault(m.landmark_id, (m.x, m.y))
    cps = dict(list(marks.items())[:4])
    res = run_survey(SurveyInputs((tmp_path / "rec",), tmp_path / "out", control_points=cps))
    assert res.report["frame"] == "site" and res.report["control_points"] == {k: list(v) for k, v in cps.items()}
    for scene in (survey_picture.scene_of_alignment(res.survey, res.alignment, GraphSlamConfig(), res.evaluation),
                  survey_picture.scene_of_folder(tmp_path / "out", [tmp_path / "rec"])):
        assert dict(scene.control_points) == cps
        pic = survey_picture.survey_picture(scene)
        texts = [e.text for e in pic.legend]
        assert any(t.startswith("4 control points (given, site frame") for t in texts), texts
        assert "landmark truth (evaluation only)" in texts
        kinds = {e.kind for e in pic.legend if e.text.startswith("4 control points")}
        assert kinds == {"diamond"}
        # each control point drawn at its site position: the diamond's colour there, in the panel
        panel = pic.panels[0]
        img = np.asarray(panel.image).astype(int)
        for x, y in cps.values():
            i, j = (int(round(v)) for v in panel.px(np.array([[x, y]]))[0])
            near = img[max(0, j - 3):j + 4, max(0, i - 3):i + 4]
            assert (np.abs(near - np.array(survey_picture.CONTROL)).max(axis=2) <= 10).any(), (x, y)
    # a survey without control points draws none
    plain = survey_picture.scene_of_alignment(res.survey, dataclasses.replace(res.alignment, control_points={}),
                                              GraphSlamConfig(), res.evaluation)
    assert not any("control point" in e.text for e in survey_picture.survey_picture(plain).legend)


def test_the_uwb_surveys_picture_shows_its_anchors(tmp_path: Path) -> None:
    from graphslam.sim.uwb.scenarios import CROWD_ANCHORS, CrowdUwb, simulate_crowd

    crowd = simulate_crowd(1, CrowdUwb(n_walkers=4, duration_min=(2.0, 2.5)))
    crowd.write(tmp_path / "rec")
    res = run_survey(SurveyInputs((tmp_path / "rec",), tmp_path / "out"))
    assert res.alignment.frame == "site"
    scene = survey_picture.scene_of_alignment(res.survey, res.alignment, GraphSlamConfig(), res.evaluation)
    assert sorted(scene.anchors.values()) == sorted(CROWD_ANCHORS)
    img = _rgb(tmp_path / "out" / "survey.png")
    orange = (np.abs(img - np.array(survey_picture.ANCHOR)).max(axis=2) <= 10).sum()
    assert orange > 4 * 100  # four anchors, ~15 x 15 px each
    with Image.open(tmp_path / "out" / "survey.png") as im:
        assert "placed by the UWB anchors" in im.text["Title"]
    texts = [e.text for e in survey_picture.survey_picture(scene).legend]
    assert any(t.startswith("4 UWB anchors") for t in texts)
    # plot with the recordings draws them too (their positions are the recordings')
    assert sorted(survey_picture.scene_of_folder(tmp_path / "out", [tmp_path / "rec"]).anchors.values()) == sorted(CROWD_ANCHORS)
