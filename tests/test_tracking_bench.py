"""Held-out walks tracked on a map of the others (graphslam.app.tracking_bench, bench tracking-real)."""

from __future__ import annotations

import numpy as np
import pytest

from graphslam.app.tracking_bench import held_out_folds, route_of
from graphslam.core.types import PoseTrack, Session


def _stub(name: str) -> Session:
    return Session(name, PoseTrack(np.array([0, 1]), np.zeros((2, 2)), np.zeros(2)), source=f"/data/{name}.mcap")


def test_folds_leave_one_route_out_when_names_say_routes_else_seeded_random():
    walks = [_stub(f"Trial2{r}_repetition{k}") for r in (1, 2, 3) for k in (1, 2)]
    assert [route_of(w) for w in walks[:3]] == ["21", "21", "22"]
    folds = held_out_folds(walks, None, 0)
    assert [name for name, _ in folds] == ["route 21", "route 22", "route 23"]
    assert [test for _, test in folds] == [[0, 1], [2, 3], [4, 5]]
    other = [_stub(f"walk{i}") for i in range(7)]
    a, b = held_out_folds(other, None, 0), held_out_folds(other, None, 1)
    assert len(a) == 5 and sorted(i for _, t in a for i in t) == list(range(7))  # a partition
    assert a != b and a == held_out_folds(other, None, 0)  # seeded


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    from graphslam.io.mcap_writer import write_session
    from graphslam.sim import simulate

    d = tmp_path_factory.mktemp("tracking_real")
    for s in simulate("paper", seed=1).survey.sessions[:4]:
        t_end = s.landmarks[1].t_ns + 5_000_000_000  # two landmarks: 35-100 s of walking
        n = int(np.searchsorted(s.steps.t_ns, t_end, side="right"))
        write_session(
            Session(s.session_id, PoseTrack(s.steps.t_ns[:n], s.steps.xy[:n], s.steps.heading[:n]),
                    tuple(sc for sc in s.scans if sc.t_ns <= t_end), tuple(m for m in s.landmarks if m.t_ns <= t_end),
                    site=s.site, floor=s.floor),
            d / f"{s.session_id}.mcap",
        )
    return d


def test_tracking_real_scores_knn_and_the_tracker_on_the_same_landmarks(folder):
    # What `graphslam bench tracking-real` runs, with a light tracker (2 heading hypotheses, no
    # self-calibration) to keep the test short.
    from graphslam.tracking_config import TrackConfig
    from graphslam.app.tracking_bench import Variant, tracking_real
    from graphslam.config import GraphSlamConfig

    light = Variant("fixed-lag:1", TrackConfig(fixed_lag={"lag_s": 1.0}, motion={"n_theta_hypotheses": 2}, calibration={"enabled": False}))
    res = tracking_real(folder, GraphSlamConfig(), [light], maps=["oracle"], folds=2)
    assert res["walks"] == 4 and res["folds"] == ["fold 0", "fold 1"]
    s = res["oracle"]["summary"]
    assert set(s) == {"knn", "knn:sorensen", "fixed-lag:1"}
    assert s["knn"]["n"] == s["knn:sorensen"]["n"] == s["fixed-lag:1"]["n"] > 0  # the same landmarks scored for all
    assert s["knn"]["mean_m"] != s["knn:sorensen"]["mean_m"]  # two kNN metrics, two answers
    row = s["fixed-lag:1"]
    assert row["median_m"] <= row["p75_m"] <= row["p90_m"] and 0.0 <= row["inside_95"] <= 1.0
    assert row["vs_knn"] == pytest.approx(row["mean_m"] / s["knn"]["mean_m"] - 1.0, abs=2e-3)
    assert row["vs_knn_sorensen"] == pytest.approx(row["mean_m"] / s["knn:sorensen"]["mean_m"] - 1.0, abs=2e-3)
    folds = res["oracle"]["per_fold"]
    assert [f["test_walks"] for f in folds] == [2, 2] and all("fixed-lag:1_mean_m" in f for f in folds)
    # coverage: the share of landmarks at steps flagged outside the map's walks, the others scored apart
    assert 0.0 <= row["outside"] <= 1.0 and "outside" not in s["knn"]
    rest = row["not_outside"]
    assert rest["n"] == round((1.0 - row["outside"]) * row["n"]) and 0.0 <= rest.get("inside_95", 0.0) <= 1.0


def test_the_crowdsourced_map_is_the_main_map_the_survey_writes(tmp_path):
    """``radio_map.parquet`` holds component 0 only; the benchmark's crowdsourced map must too (the
    other components' walks lie in frames of their own)."""
    from graphslam.app.tracking_bench import crowdsourced_map
    from graphslam.config import GraphSlamConfig
    from graphslam.io.mcap_reader import read_survey
    from graphslam.io.mcap_writer import write_session
    from graphslam.sim import simulate

    for s in simulate("museum", seed=1, size=0.3).survey.sessions:  # its survey leaves walks in other components
        write_session(s, tmp_path / f"{s.session_id}.mcap")
    rm, info = crowdsourced_map(read_survey([tmp_path]), GraphSlamConfig())
    assert info["main_map"] < info["aligned"]
    assert len(set(rm.session_ids.tolist())) == info["main_map"]


def test_bench_tracking_real_rejects_an_unknown_map_kind(folder, capsys):
    from graphslam.cli import main

    with pytest.raises(SystemExit) as e:
        main(["bench", "tracking-real", str(folder), "--maps", "floorplan"])
    assert e.value.code == 2 and "floorplan" in capsys.readouterr().err


@pytest.mark.parametrize("lags", ["abc", "-1", "1,nan"])
def test_bad_lags_are_one_line_usage_errors(lags, capsys):
    from graphslam.cli import main

    with pytest.raises(SystemExit) as e:
        main(["bench", "tracking-real", ".", f"--lags={lags}"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "--lags" in err and len(err.strip().splitlines()) == 1


def test_variant_descriptions_name_every_setting_that_differs_from_the_default():
    from graphslam.tracking_config import TrackConfig
    from graphslam.app.tracking_bench import _describe

    a, b = _describe(TrackConfig()), _describe(TrackConfig(fixed_lag={"bank_report": "best"}, calibration={"replay_route_radius_m": 2.0}))
    assert "bank_report=mixture" in a and "replay_route_radius_m" not in a
    assert "bank_report=best" in b and "replay_route_radius_m=2.0" in b
