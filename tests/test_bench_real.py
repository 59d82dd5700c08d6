"""``graphslam bench real`` (one JSON line per floor and variant, then one per variant) and the
per-component evaluation behind it (``graphslam.core.survey.evaluate.component_errors``, also
report.json's ``evaluation.components``)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import run_cli

from graphslam.app.survey import run_survey
from graphslam.app.survey_inputs import SurveyInputs
from graphslam.core.survey.align import Alignment, Component
from graphslam.core.survey.evaluate import component_errors
from graphslam.core.common.geometry import se2_apply
from graphslam.core.types import LandmarkMark, PoseTrack, Session, Survey
from graphslam.io.mcap_writer import write_session
from graphslam.sim import simulate

ROW_FIELDS = {
    "floor", "variant", "walks", "aligned", "aligned_fraction", "main", "main_fraction", "other_walks",
    "other_components", "unaligned", "main_map", "landmarks",
    "main_mean_m", "main_site_mean_m", "mean_m", "p90_m", "max_m", "components",
    "walks_in_components_of_5_or_more", "walks_in_components_of_5_or_more_fraction",
    "components_of_5_or_more_mean_m", "walks_in_components_of_4_or_more",
    "walks_in_components_of_4_or_more_fraction", "components_of_4_or_more_mean_m",
    "walks_over_6m", "walks_over_10m", "walks_over_15m", "frame", "control_points", "reference_map",
    "per_walk_rigid_fit_mean_m", "initialization", "placement", "loop_consistency", "reliable", "confidence",
    "time_s",
}
FRACTIONS = ("aligned_fraction", "main_fraction", "walks_in_components_of_5_or_more_fraction",
             "walks_in_components_of_4_or_more_fraction")


# ---------------------------------------------------------------- component_errors, by hand

T0 = 1_767_225_600_000_000_000
SECOND = 1_000_000_000


def _walk(sid: str, y: float, n_marks: int = 4) -> Session:
    """A straight walk along x at height ``y`` (site frame), one step a second, landmarks along it."""
    n = 41
    t = T0 + np.arange(n, dtype=np.int64) * SECOND
    xy = np.column_stack([np.arange(n) * 0.7, np.full(n, y)])
    marks = tuple(
        LandmarkMark(int(t[k]), f"L{sid}{k}", float(xy[k, 0]), float(xy[k, 1]))
        for k in np.linspace(2, n - 3, n_marks).astype(int)
    )
    truth = PoseTrack(t, xy, np.zeros(n))
    return Session(sid, truth, landmarks=marks)


def _moved(track: PoseTrack, T: tuple[float, float, float]) -> PoseTrack:
    return PoseTrack(track.t_ns, se2_apply(np.array(T), track.xy), track.heading + T[2])


def _alignment(tracks: dict[str, PoseTrack], groups: list[list[str]]) -> Alignment:
    """An ``Alignment`` holding only what the evaluation reads: tracks and components."""
    comps = tuple(Component(k, tuple(g), "" if k == 0 else "no WiFi edge to the main map") for k, g in enumerate(groups))
    return Alignment(
        session_ids=tuple(tracks), reference=groups[0][0], tracks=tracks, unaligned={}, fingerprints=None,  # type: ignore[arg-type]
        edges=None, node_xyh=np.zeros((0, 3)), initial_xyh=np.zeros((0, 3)), placement=None,  # type: ignore[arg-type]
        iterations=(), initial_error=0.0, final_error=0.0, converged=True, component_list=comps,
    )


@pytest.fixture
def hand_survey() -> Survey:
    # component 0: a, b; component 1: c, d, e (e marks fewer landmarks); component 2: f with one mark
    return Survey((
        _walk("a", 0.0), _walk("b", 5.0), _walk("c", 10.0), _walk("d", 15.0), _walk("e", 20.0, n_marks=2),
        _walk("f", 25.0, n_marks=1),
    ))


def test_each_component_gets_its_own_fit_and_one_in_a_frame_of_its_own_scores_zero(hand_survey: Survey) -> None:
    truth = {s.session_id: s.steps for s in hand_survey}
    shift = (20.0, -20.0, 0.7)  # component 1 in a frame of its own: 20 m off, turned
    tracks = {sid: truth[sid] for sid in "ab"} | {sid: _moved(truth[sid], shift) for sid in "cdef"}
    al = _alignment(tracks, [["a", "b"], ["c", "d", "e"], ["f"]])
    c0, c1, c2 = component_errors(al, hand_survey, site_frame=False)
    assert [c.index for c in (c0, c1, c2)] == [0, 1, 2]
    assert c0.walks == ("a", "b") and c1.walks == ("c", "d", "e")
    assert c0.landmarks.n == 8 and c1.landmarks.n == 10
    assert c0.landmarks.max_m < 1e-6 and c1.landmarks.max_m < 1e-6
    assert c0.walks_over_10m == 0 and c1.walks_over_10m == 0
    assert set(c1.per_walk_mean_m) == {"c", "d", "e"}
    # the fit undoes the shift: site from component 1 is its inverse
    fit = np.array(c1.site_from_component)
    assert np.allclose(se2_apply(fit, se2_apply(np.array(shift), np.array([[3.0, 4.0]]))), [[3.0, 4.0]], atol=1e-6)
    # one landmark mark: no fit, n = 0
    assert c2.landmarks.n == 0 and c2.per_walk_mean_m == {} and c2.walks_over_10m == 0
    assert c2.site_from_component is None
    d2 = c2.as_dict()
    assert d2["n"] == 0 and d2["mean_m"] is None and d2["walks"] == 1
    # not in the site frame: no unfitted figures
    assert c0.site is None and "site_mean_m" not in c0.as_dict()


def test_components_of_4_walks_count_in_the_4_or_more_figures_only(hand_survey: Survey) -> None:
    from graphslam.app.bench_real import big_component_figures

    truth = {s.session_id: s.steps for s in hand_survey}
    tracks = {sid: truth[sid] for sid in "ab"} | {sid: _moved(truth[sid], (0.0, 3.0 * (sid == "f"), 0.0)) for sid in "cdef"}
    al = _alignment(tracks, [["a", "b"], ["c", "d", "e", "f"]])  # component 1: four walks, f 3 m off the others
    comps = component_errors(al, hand_survey, site_frame=False)
    four, five = big_component_figures(comps, 6, 4), big_component_figures(comps, 6, 5)
    assert four["walks_in_components_of_4_or_more"] == 4 and four["walks_in_components_of_4_or_more_fraction"] == 0.667
    assert four["components_of_4_or_more_mean_m"] == round(comps[1].landmarks.mean_m, 2) > 0
    assert five == {"walks_in_components_of_5_or_more": 0, "walks_in_components_of_5_or_more_fraction": 0.0,
                    "components_of_5_or_more_mean_m": None}


def test_a_walk_displaced_inside_its_component_counts_over_10m(hand_survey: Survey) -> None:
    truth = {s.session_id: s.steps for s in hand_survey}
    tracks = dict(truth)
    tracks["e"] = _moved(truth["e"], (0.0, 40.0, 0.0))  # 40 m off the rest of component 1
    al = _alignment(tracks, [["a", "b"], ["c", "d", "e"], ["f"]])
    c0, c1, _ = component_errors(al, hand_survey, site_frame=False)
    assert c0.walks_over_10m == 0
    assert c1.walks_over_10m == 1
    assert c1.per_walk_mean_m["e"] > 10.0 > max(c1.per_walk_mean_m["c"], c1.per_walk_mean_m["d"])
    assert c1.landmarks.max_m > 10.0
    assert c1.as_dict()["walks_over_10m"] == 1


def test_site_frame_component_0_is_also_scored_with_no_fit(hand_survey: Survey) -> None:
    truth = {s.session_id: s.steps for s in hand_survey}
    # component 0 3 m off the site frame: 0 after the fit, 3 m without; b also 12 m off on its own
    tracks = {"a": _moved(truth["a"], (3.0, 0.0, 0.0)), "b": _moved(truth["b"], (0.0, 0.0, 0.0))}
    tracks |= {sid: _moved(truth[sid], (50.0, 0.0, 0.0)) for sid in "cd"}
    al = _alignment(tracks, [["a", "b"], ["c", "d"]])
    c0, c1 = component_errors(al, hand_survey, site_frame=True)
    assert c0.site is not None and c0.site.n == 8
    assert c0.site_per_walk_mean_m == pytest.approx({"a": 3.0, "b": 0.0})
    assert c0.site.mean_m == pytest.approx(1.5)
    assert c0.site_walks_over_10m == 0
    assert c0.landmarks.mean_m > 0.1  # one fit cannot undo a's offset alone
    d0 = c0.as_dict()
    assert d0["site_mean_m"] == pytest.approx(1.5) and d0["site_n"] == 8 and d0["index"] == 0 and d0["walks"] == 2
    # only component 0 is in the site frame: component 1 (50 m off) after its fit only
    assert c1.site is None and c1.landmarks.max_m < 1e-6
    tracks["b"] = _moved(truth["b"], (0.0, 12.0, 0.0))
    c0 = component_errors(_alignment(tracks, [["a", "b"], ["c", "d"]]), hand_survey, site_frame=True)[0]
    assert c0.site_walks_over_10m == 1 and c0.site_per_walk_mean_m["b"] == pytest.approx(12.0)


# ---------------------------------------------------------------- bench real on a simulated floor


@pytest.fixture(scope="module")
def floors(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A site of two simulated floors with landmarks and /phone/heading: ``cp`` holds a
    control_points.csv (four landmarks at their true positions), ``plain`` none."""
    site = tmp_path_factory.mktemp("bench_real") / "site"
    for name, seed in (("cp", 0), ("plain", 1)):
        d = site / name
        sim = simulate("crowd", seed=seed, size=0.25)
        ids: dict[str, tuple[float, float]] = {}
        for s in sim.survey:
            assert s.heading is not None
            write_session(s, d / f"{s.session_id}.mcap")
            for m in s.landmarks:
                ids.setdefault(m.landmark_id, (m.x, m.y))
        assert len(ids) >= 4
        if name == "cp":
            rows = "".join(f'"{k}",{x},{y}\n' for k, (x, y) in list(ids.items())[:4])
            (d / "control_points.csv").write_text("landmark_id,x,y\n" + rows)
    return site


def _lines(capsys: pytest.CaptureFixture[str], args: list[str]) -> list[dict[str, Any]]:
    capsys.readouterr()
    assert run_cli(["-q", "bench", "real", *args]) == 0
    out = capsys.readouterr().out.splitlines()
    return [json.loads(line) for line in out]


def test_one_line_per_floor_and_variant_then_a_summary_per_variant(floors: Path, capsys: pytest.CaptureFixture[str]) -> None:
    lines = _lines(capsys, [str(floors)])
    rows = [r for r in lines if "variant" in r]
    summaries = [r for r in lines if "summary" in r]
    assert len(rows) + len(summaries) == len(lines)
    # the control_points variant only on the floor with the file
    assert [(r["floor"], r["variant"]) for r in rows] == [
        ("cp", "headings"), ("cp", "no_magnetic"), ("cp", "no_headings"), ("cp", "control_points"), ("plain", "headings"),
        ("plain", "no_magnetic"), ("plain", "no_headings"),
    ]
    for r in rows:
        assert set(r) == ROW_FIELDS
        assert r["walks"] == 12
        # the main map counted first, as `graphslam survey` counts it
        assert list(r)[:5] == ["floor", "variant", "walks", "main", "main_fraction"]
        assert r["main"] + r["other_walks"] + r["unaligned"] == r["walks"] and r["aligned"] == r["main"] + r["other_walks"]
        assert r["main_map"].startswith(f"main map: {r['main']} of 12 walks; {r['other_walks']} in ")
        assert 0 < r["main"] <= r["aligned"] <= r["walks"]
        assert 1 <= r["components"] <= r["aligned"]
        assert r["walks_in_components_of_5_or_more"] <= r["walks_in_components_of_4_or_more"] <= r["aligned"]
        if r["walks_in_components_of_4_or_more"] == r["walks_in_components_of_5_or_more"]:  # the same components
            assert r["components_of_4_or_more_mean_m"] == r["components_of_5_or_more_mean_m"]
        for f in FRACTIONS:
            assert 0.0 <= r[f] <= 1.0
        assert r["main_fraction"] == round(r["main"] / r["walks"], 3)
        assert 0 <= r["walks_over_15m"] <= r["walks_over_10m"] <= r["walks_over_6m"] <= r["aligned"]
        assert r["main_mean_m"] == r["mean_m"] and r["main_mean_m"] < 5.0  # the simulator's walks align
        assert r["landmarks"] > 0 and r["p90_m"] <= r["max_m"]
        assert r["time_s"] > 0
        assert set(r["confidence"]) >= {"right", "wrong"}
        assert 0 < r["confidence"]["right"] + r["confidence"]["wrong"] <= r["aligned"]  # walks with marks
    by = {(r["floor"], r["variant"]): r for r in rows}
    assert by["cp", "headings"]["frame"] == "earth" and by["cp", "headings"]["placement"] == "heading"
    assert by["cp", "no_headings"]["frame"] == "aligned" and by["cp", "no_headings"]["placement"] != "heading"
    cp = by["cp", "control_points"]
    assert cp["frame"] == "site" and cp["control_points"].endswith("control_points.csv")
    assert cp["main_site_mean_m"] is not None and cp["main_site_mean_m"] < 5.0
    assert all(r["main_site_mean_m"] is None for k, r in by.items() if k[1] != "control_points")
    # the summary: one per variant, sums over its floors
    assert [s["summary"] for s in summaries] == ["headings", "no_magnetic", "no_headings", "control_points"]
    for s in summaries:
        mine = [r for r in rows if r["variant"] == s["summary"]]
        assert s["floors"] == len(mine) and s["walks"] == sum(r["walks"] for r in mine)
        assert s["main"] == sum(r["main"] for r in mine)
        assert s["walks_in_components_of_4_or_more"] == sum(r["walks_in_components_of_4_or_more"] for r in mine)
        assert s["main_map"].startswith(f"main maps: {s['main']} of {s['walks']} walks; ")
        assert s["walks_over_10m"] == sum(r["walks_over_10m"] for r in mine)
        assert 0.0 <= s["main_fraction"] <= 1.0
    assert summaries[3]["main_mean_m"] == cp["main_mean_m"]


def test_control_points_none_and_variants_and_floors(floors: Path, capsys: pytest.CaptureFixture[str]) -> None:
    lines = _lines(capsys, [str(floors), "--floors", "cp", "--control-points", "none", "--variants", "headings",
                            "--set", "heading.enabled=false"])
    assert [(r.get("floor"), r.get("variant"), r.get("summary")) for r in lines] == [
        ("cp", "headings", None), (None, None, "headings"),
    ]
    assert lines[0]["frame"] == "aligned"  # --set reached the variant's config


def test_bad_variant_or_control_points_is_one_line_exit_2(floors: Path, capsys: pytest.CaptureFixture[str]) -> None:
    for args in (["--variants", "nope"], ["--control-points", "file.csv"]):
        capsys.readouterr()
        assert run_cli(["-q", "bench", "real", str(floors / "cp"), *args]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and ("variants" in err[0] or "control-points" in err[0])


def test_report_json_evaluation_has_the_components(floors: Path) -> None:
    res = run_survey(SurveyInputs.for_floor(floors / "cp", picture=False))  # with its control_points.csv
    ev = res.report["evaluation"]
    assert ev["component"] == 0
    comps = ev["components"]
    assert [c["index"] for c in comps] == [c.index for c in res.alignment.components]
    assert sum(c["walks"] for c in comps) == len(res.alignment.tracks)
    c0 = comps[0]
    assert c0["mean_m"] == pytest.approx(ev["landmarks"]["mean_m"]) and c0["n"] == ev["landmarks"]["n"]
    assert {"p90_m", "max_m", "walks_over_10m", "site_mean_m"} <= set(c0)
    assert res.alignment.frame == "site" and math.isfinite(c0["site_mean_m"])
    json.dumps(res.report, allow_nan=False)  # strict JSON
