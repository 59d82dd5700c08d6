"""Access-point fits (graphslam.core.tracking.apmodel) and the track CLI end to end."""

from __future__ import annotations

import csv
import json
import logging

import numpy as np
import pytest

from graphslam.core.tracking.apmodel import ApFitConfig, ApModel, ApModels, UnfittedAp, fit_ap
from graphslam.io.apmodel_io import read_ap_models, write_ap_models
from graphslam.core.radiomap.radiomap import RadioMap

AP = np.array([7.0, 4.0])
P0, GAMMA = -38.0, 2.4


def _readings(rng, n=300, sigma=0.0, outliers=0.0):
    xy = rng.uniform([-5, -10], [25, 15], (n, 2))
    d = np.sqrt(((xy - AP) ** 2).sum(1) + 1.0)
    rss = P0 - 10 * GAMMA * np.log10(d) + rng.normal(0, sigma, n) if sigma else P0 - 10 * GAMMA * np.log10(d)
    bad = rng.random(n) < outliers
    rss = np.where(bad, rss + 15.0, rss)  # multipath: abnormally high readings (Paper 000 fig. 4)
    return xy, rss


def test_noiseless_readings_recover_the_ap_exactly():
    xy, rss = _readings(np.random.default_rng(0))
    a = fit_ap("ap", xy, rss)
    assert isinstance(a, ApModel)
    np.testing.assert_allclose([a.x, a.y, a.p0_dbm, a.gamma], [*AP, P0, GAMMA], atol=1e-4)


def test_noisy_readings_with_outliers_recover_the_ap_with_honest_uncertainty():
    xy, rss = _readings(np.random.default_rng(1), sigma=4.0, outliers=0.05)
    a = fit_ap("ap", xy, rss)
    assert isinstance(a, ApModel)
    assert np.hypot(a.x - AP[0], a.y - AP[1]) < 1.5
    assert abs(a.gamma - GAMMA) < 0.4 and abs(a.p0_dbm - P0) < 4.0
    assert 0.05 < a.position_std_m < 2.0
    assert 3.0 < a.sigma_db < 5.5
    assert np.all(np.linalg.eigvalsh(np.array(a.cov)) > 0)


def test_p0_is_bounded_by_what_a_physical_ap_gives_at_1_m():
    """Walls' losses grow with distance and read as a steep law with an unphysically strong AP (the
    simulator's floors fitted P0 of -1 to -3 dBm with gamma ~5): P0 stops at the ceiling, -10 dBm,
    and the fit is kept there (gamma and position adjusted); a fit at the floor (-90) is rejected."""
    rng = np.random.default_rng(3)
    xy = rng.uniform([-5, -10], [25, 15], (400, 2))
    d = np.sqrt(((xy - AP) ** 2).sum(1) + 1.0)
    steep = -1.0 - 10 * 5.5 * np.log10(d) + rng.normal(0, 2.0, len(d))
    a = fit_ap("steep", xy, steep)
    assert ApFitConfig().p0_bounds_dbm[1] == -10.0
    assert isinstance(a, ApModel) and a.p0_dbm == pytest.approx(-10.0, abs=1e-6), a
    assert 4.0 < a.gamma < 6.0 and np.hypot(a.x - AP[0], a.y - AP[1]) < 2.0
    unbounded = fit_ap("steep", xy, steep, ApFitConfig(p0_bounds_dbm=(-90.0, 0.0)))
    assert isinstance(unbounded, ApModel) and unbounded.p0_dbm > -5.0  # what it fitted before the ceiling
    weak = fit_ap("weak", xy, -120.0 - 10 * 1.2 * np.log10(d) + rng.normal(0, 2.0, len(d)))
    assert isinstance(weak, UnfittedAp) and "implausible P0" in weak.reason


def test_unfittable_aps_are_reported_with_a_reason():
    rng = np.random.default_rng(2)
    xy, rss = _readings(rng, n=10)
    u = fit_ap("few", xy, rss)
    assert isinstance(u, UnfittedAp) and "too few" in u.reason and u.n_readings == 10
    line = np.column_stack([np.linspace(0, 30, 80), np.full(80, 2.0) + rng.normal(0, 0.1, 80)])
    u = fit_ap("line", line, P0 - 24 * np.log10(np.hypot(*(line - AP).T) + 1))
    assert isinstance(u, UnfittedAp) and "degenerate" in u.reason
    # an AP far outside the readings: position at its search bound, not invented
    far = np.array([200.0, 200.0])
    xy = rng.uniform(0, 10, (100, 2))
    u = fit_ap("far", xy, -40 - 25 * np.log10(np.hypot(*(xy - far).T)) + rng.normal(0, 4, 100))
    assert isinstance(u, UnfittedAp), u


def test_radio_map_fit_and_json_round_trip(tmp_path):
    rng = np.random.default_rng(3)
    xy, rss = _readings(rng, sigma=2.0)
    scans = [{"ap": float(np.round(r)), "rare": -50.0} if i < 3 else {"ap": float(np.round(r))} for i, r in enumerate(rss)]
    rm = RadioMap.from_scans(scans, xy, session_ids="s", t_ns=np.arange(len(xy)), frame="site")
    models = ApModels.fit(rm, ApFitConfig(min_readings=20))
    assert [a.bssid for a in models.fitted] == ["ap"]
    assert [u.bssid for u in models.unfitted] == ["rare"]
    p = write_ap_models(models, tmp_path / "ap_models.json")
    back = read_ap_models(p)
    assert back.fitted == models.fitted and back.unfitted == models.unfitted and back.frame == "site"
    pl = back.path_loss()
    assert pl.bssids == ("ap",) and pl.min_distance_m == models.min_distance_m


@pytest.fixture(scope="module")
def tiny_case(tmp_path_factory):
    """A surveyed radio map of the simulator's paper building (2 walks at their true positions) and
    the first 80 steps of one held-out walk, as files."""
    from graphslam.core.common.geometry import interpolate_xy
    from graphslam.core.types import PoseTrack, Session
    from graphslam.io.mcap_writer import write_session
    from graphslam.io.radiomap_io import write_radio_map
    from graphslam.sim import simulate

    sim = simulate("paper", seed=0, test_walks=1)
    scans, xys = [], []
    for s in sim.survey.sessions[:2]:
        t = np.array([sc.t_ns for sc in s.scans], float)
        xys.append(interpolate_xy(s.ground_truth, t))
        scans += [dict(sc.readings) for sc in s.scans]
    rm = RadioMap.from_scans(scans, np.concatenate(xys), session_ids="m", t_ns=np.arange(len(scans)), frame="site")
    d = tmp_path_factory.mktemp("track")
    write_radio_map(rm, d / "radio_map.parquet")
    s = sim.test_sessions[0]
    n = 80
    st = PoseTrack(s.steps.t_ns[:n], s.steps.xy[:n], s.steps.heading[:n])
    gt = s.ground_truth
    keep = gt.t_ns <= st.t_ns[-1]
    short = Session(
        s.session_id, st, tuple(sc for sc in s.scans if sc.t_ns <= st.t_ns[-1]),
        ground_truth=PoseTrack(gt.t_ns[keep], gt.xy[keep], gt.heading[keep]),
    )
    write_session(short, d / "walk.mcap")
    return d, short


def test_fit_aps_and_track_cli_end_to_end(tiny_case):
    from graphslam.cli import main
    from graphslam.core.common.geometry import interpolate_xy

    d, session = tiny_case
    main(["fit-aps", "--radio-map", str(d / "radio_map.parquet")])
    assert (d / "ap_models.json").exists()
    out = d / "positions.csv"
    main(["track", str(d / "walk.mcap"), "--radio-map", str(d / "radio_map.parquet"), "--filter", "ekf", "--out", str(out)])
    rows = list(csv.DictReader(out.open()))
    assert len(rows) == len(session.steps)
    assert [int(r["t_ns"]) for r in rows] == session.steps.t_ns.tolist()
    xy = np.array([[float(r["x"]), float(r["y"])] for r in rows])
    cov = np.array([[float(r["cov_xx"]), float(r["cov_yy"])] for r in rows])
    assert (cov > 0).all()
    err = np.linalg.norm(xy - interpolate_xy(session.ground_truth, session.steps.t_ns.astype(float)), axis=1)
    assert err[len(err) // 2 :].mean() < 4.0, err.mean()  # after the start-up (heading unknown at first)


@pytest.mark.parametrize(
    ("option", "value", "message"),
    [("--filter", "pf", "Invalid value for '--filter': Value error, 'pf' is not one of 'fixed-lag', 'ekf', 'ukf', 'particle'"),
     ("--smooth", "ks", "Invalid value for '--smooth': Value error, 'ks' is not one of 'none', 'rts', 'map'"),
     ("--bank-report", "mean", "Invalid value for '--bank-report': Value error, 'mean' is not one of 'mixture', 'best'"),
     ("--bank-temper", "0.5", "fixed_lag.bank_temper: Input should be greater than or equal to 1"),
     ("--rssi-field", "0.5", "field_m must be 0 (off) or >= 1")],
)
def test_track_cli_rejects_unknown_filter_or_smoother(tiny_case, capsys, option, value, message):
    from graphslam.cli import main

    d, _ = tiny_case
    out = d / f"rejected{option}.csv"
    with pytest.raises(SystemExit) as e:
        main(["track", str(d / "walk.mcap"), "--radio-map", str(d / "radio_map.parquet"), option, value, "--out", str(out)])
    assert e.value.code == 2 and message in capsys.readouterr().err
    assert not out.exists()


def _track_cli(d, session, name: str, *args: str) -> tuple[list[dict], np.ndarray]:
    """``graphslam track`` on the tiny case's walk: the CSV rows and each step's error (m)."""
    from graphslam.cli import main
    from graphslam.core.common.geometry import interpolate_xy

    out = d / f"positions_{name}.csv"
    main(["track", str(d / "walk.mcap"), "--radio-map", str(d / "radio_map.parquet"), "--out", str(out), *args])
    rows = list(csv.DictReader(out.open()))
    assert [int(r["t_ns"]) for r in rows] == session.steps.t_ns.tolist()
    xy = np.array([[float(r["x"]), float(r["y"])] for r in rows])
    return rows, np.linalg.norm(xy - interpolate_xy(session.ground_truth, session.steps.t_ns.astype(float)), axis=1)


def test_track_cli_smoothed_output_uses_the_whole_walk(tiny_case):
    # --smooth map: one hypothesis for the whole walk, the start-up no longer lost (the filter
    # needs ~half the walk to find the heading; the smoother sees it all at once).
    d, session = tiny_case
    errs = {}
    for smooth in ("none", "map"):
        # without the walk axes, which close most of this gap online (next test)
        rows, errs[smooth] = _track_cli(d, session, smooth, "--smooth", smooth, "--no-walk-axes")
        if smooth == "map":
            assert len({r["hypothesis"] for r in rows}) == 1
            assert all(float(r["cov_xx"]) > 0 and float(r["cov_yy"]) > 0 for r in rows)
    # measured: 0.97 vs 1.19 m with the default Sørensen fixes (0.77 of it with eq. 9's: 1.08 vs 1.39 m);
    # a smoother that did not use the whole walk would be level with the online tracker
    assert errs["map"].mean() < 0.85 * errs["none"].mean(), (errs["map"].mean(), errs["none"].mean())


def test_track_cli_walk_axes_prior_helps_on_a_corridor_floor(tiny_case):
    # The simulated floor's walks keep to its corridors; the map's walks say so, and the prior on the
    # walking direction fixes the heading the online tracker otherwise finds only slowly (measured:
    # 1.13 vs 1.19 m at the default sigma 1.0 m/s, 0.96 m at 0.25; --no-walk-axes is the tracker before
    # the prior, and a flag that did not reach the tracker would make the two equal).
    d, session = tiny_case
    on = _track_cli(d, session, "axes", "--walk-axes", "--no-picture")[1].mean()
    off = _track_cli(d, session, "no_axes", "--no-walk-axes", "--no-picture")[1].mean()
    assert on < 0.98 * off, (on, off)


def _path_plan(d, session, half_width_m: float = 1.5):
    """A floor plan PNG (0.25 m pixels) whose walkable (transparent) area is the band within
    ``half_width_m`` of the walk's true path; everything else drawn (opaque)."""
    from PIL import Image
    from scipy import ndimage

    cell, gt = 0.25, session.ground_truth.xy
    w, h = float(gt[:, 0].max() + 10.0), float(gt[:, 1].max() + 10.0)
    cols, rows = int(round(w / cell)), int(round(h / cell))
    on_path = np.zeros((rows, cols), bool)
    dense = np.vstack([np.linspace(a, b, 20) for a, b in zip(gt[:-1], gt[1:])])
    on_path[(rows - 1 - (dense[:, 1] / cell).astype(int)).clip(0, rows - 1), (dense[:, 0] / cell).astype(int).clip(0, cols - 1)] = True
    band = ndimage.distance_transform_edt(~on_path) * cell <= half_width_m
    px = np.zeros((rows, cols, 4), np.uint8)
    px[~band] = (195, 235, 245, 255)
    Image.fromarray(px, "RGBA").save(d / "plan.png")
    return d / "plan.png", (cols * cell, rows * cell)


def test_track_cli_floor_plan_keeps_the_track_on_the_walkable_area(tiny_case, capsys, caplog):
    # The plan's walkable area is a 1.5-m band along the walk: snapped reports (the default) and the
    # prior in the window both keep the track closer to the truth than without the plan.
    from graphslam.cli import main

    d, session = tiny_case
    plan, (w, h) = _path_plan(d, session, 0.75)
    caplog.set_level(logging.INFO, logger="graphslam")
    given = ["--floor-plan", str(plan), "--floor-size", f"{w}", f"{h}", "--no-picture"]
    snap = _track_cli(d, session, "snap", *given)[1]
    assert "walkable area from the floor plan" in caplog.text
    prior = _track_cli(d, session, "prior", *given, "--floor-plan-use", "prior", "--walkable-sigma", "1")[1].mean()
    off = _track_cli(d, session, "no_plan", "--no-picture")[1].mean()
    assert snap.mean() < 0.95 * off and prior < 0.95 * off, (snap.mean(), prior, off)  # measured: 0.91 and 0.92 of it
    capsys.readouterr()
    # bad input: one line naming the file, exit 2, nothing written
    out = d / "bad_plan.csv"
    (d / "not_a_plan.png").write_bytes(b"\x89PNG not really")
    for args, message in (
        (["--floor-plan", str(d / "not_a_plan.png"), "--floor-size", "10", "10"], "not_a_plan.png"),
        (["--floor-plan", str(d / "missing.png"), "--floor-size", "10", "10"], "missing.png"),
        (["--floor-size", "10", "10"], "--floor-size given without --floor-plan"),
        (["--floor-plan", str(plan), "--floor-size", f"{w}", f"{h}", "--walkable-sigma", "0"], "floor_plan.sigma_m"),
        (["--floor-plan", str(plan), "--floor-size", f"{w}", f"{h}", "--floor-plan-use", "teleport"], "Invalid value for '--floor-plan-use'"),
    ):
        with pytest.raises(SystemExit) as e:
            main(["-q", "track", str(d / "walk.mcap"), "--radio-map", str(d / "radio_map.parquet"), "--out", str(out), *args])
        assert e.value.code == 2
        err = capsys.readouterr().err.strip()
        assert message in err and len(err.splitlines()) == 1, err
        assert not out.exists()


def test_track_cli_refuses_a_floor_plan_for_a_map_in_another_frame(tiny_case, tmp_path, capsys):
    # A survey's own (aligned) frame is not the plan's site frame: snapping to it would be wrong.
    from graphslam.cli import main
    from graphslam.io.radiomap_io import read_radio_map, write_radio_map

    d, session = tiny_case
    plan, (w, h) = _path_plan(d, session)
    rm = read_radio_map(d / "radio_map.parquet")
    aligned = RadioMap.from_fingerprints(rm.fingerprints, rm.xy, session_ids=rm.session_ids.tolist(), t_ns=rm.t_ns,
                                         frame="aligned", min_rssi_dbm=rm.min_rssi_dbm)
    write_radio_map(aligned, tmp_path / "radio_map.parquet")
    out = tmp_path / "t.csv"
    with pytest.raises(SystemExit) as e:
        main(["-q", "track", str(d / "walk.mcap"), "--radio-map", str(tmp_path / "radio_map.parquet"), "--out", str(out),
              "--floor-plan", str(plan), "--floor-size", f"{w}", f"{h}"])
    err = capsys.readouterr().err.strip()
    assert e.value.code == 2 and "'aligned' frame" in err and len(err.splitlines()) == 1, err
    assert not out.exists()


def test_track_skips_an_odometry_jump_instead_of_flying_off(tiny_case):
    # ILC's converter puts the origin pose 1 ms before the first step (0.7 m in 1 ms = 700 m/s).
    # As a velocity reading that throws the estimate hundreds of metres; it must be skipped.
    from graphslam.core.common.geometry import interpolate_xy
    from graphslam.core.types import PoseTrack, Session
    from graphslam.io.apmodel_io import read_ap_models
    from graphslam.io.radiomap_io import read_radio_map
    from graphslam.core.tracking.tracker import track_sessions
    from graphslam.tracking_config import TrackConfig

    d, s = tiny_case
    rm = read_radio_map(d / "radio_map.parquet")
    models = read_ap_models(d / "ap_models.json") if (d / "ap_models.json").exists() else ApModels.fit(rm)
    st = s.steps
    jumped = Session(s.session_id, PoseTrack(
        np.r_[st.t_ns[0] - 1_000_000, st.t_ns], np.vstack([st.xy[:1] - [0.7, 0.0], st.xy]), np.r_[st.heading[:1], st.heading],
    ), s.scans)
    truth = interpolate_xy(s.ground_truth, st.t_ns.astype(float))
    err = {}
    for limit in (3.0, 1e9):
        (tr,) = track_sessions([jumped], rm, models, TrackConfig(motion={"max_step_speed_mps": limit}))
        err[limit] = np.linalg.norm(tr.xy[1:] - truth, axis=1)[len(truth) // 2 :].mean()
    assert err[3.0] < 4.0, err
    assert err[1e9] > 3 * err[3.0], err  # the guard is what keeps it on the map


def _track_rows_and_errors(tiny_case, name: str, *args: str) -> tuple[list[dict], np.ndarray]:
    """``graphslam track`` on the tiny case's walk with ``args``: the CSV's rows (one per step, in
    step order: asserted) and each step's error against the walk's ground truth (scoring only)."""
    from graphslam.cli import main
    from graphslam.core.common.geometry import interpolate_xy

    d, session = tiny_case
    out = d / name
    main(["track", str(d / "walk.mcap"), "--radio-map", str(d / "radio_map.parquet"), *args, "--out", str(out)])
    rows = list(csv.DictReader(out.open()))
    assert [int(r["t_ns"]) for r in rows] == session.steps.t_ns.tolist()
    xy = np.array([[float(r["x"]), float(r["y"])] for r in rows])
    return rows, np.linalg.norm(xy - interpolate_xy(session.ground_truth, session.steps.t_ns.astype(float)), axis=1)


def test_track_cli_default_is_the_fixed_lag_tracker_and_rejects_a_negative_lag(tiny_case, capsys):
    from graphslam.cli import main

    d, _ = tiny_case
    _, err = _track_rows_and_errors(tiny_case, "positions_lag.csv", "--lag", "1")
    assert err[len(err) // 2 :].mean() < 4.0, err.mean()
    bad = d / "positions_neg.csv"
    with pytest.raises(SystemExit) as e:
        main(["track", str(d / "walk.mcap"), "--radio-map", str(d / "radio_map.parquet"), "--lag", "-1", "--out", str(bad)])
    assert e.value.code == 2 and "--lag" in capsys.readouterr().err and not bad.exists()
    with pytest.raises(SystemExit) as e:
        main(["track", str(d / "walk.mcap"), "--radio-map", str(d / "radio_map.parquet"), "--lag", "nan", "--out", str(bad)])
    assert e.value.code == 2 and "--lag" in capsys.readouterr().err and not bad.exists()
    from graphslam.errors import ConfigError
    from graphslam.tracking_config import TrackConfig

    with pytest.raises(ConfigError, match="fixed_lag.lag_s"):  # library callers get the same check
        TrackConfig(fixed_lag={"lag_s": float("nan")})


def test_track_keeps_its_self_calibration_in_the_cache_folder(tiny_case, tmp_path, monkeypatch, caplog):
    """The self-calibration is measured once per (map, AP models, configuration), kept in the cache
    folder ($XDG_CACHE_HOME/graphslam, one file per key; never beside the map: the survey's folder
    is the survey's) and reused (same tracks); another configuration, a damaged or tampered file
    mean measuring again (logged, never an error)."""
    import json
    import logging
    import shutil

    from graphslam.app import track as T

    d, _ = tiny_case
    shutil.copy(d / "radio_map.parquet", tmp_path / "radio_map.parquet")
    shutil.copy(d / "walk.mcap", tmp_path / "walk.mcap")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    rm_path, walk = tmp_path / "radio_map.parquet", [tmp_path / "walk.mcap"]
    measured = []
    real = T.SelfCalibration.measure.__func__
    monkeypatch.setattr(T.SelfCalibration, "measure", classmethod(lambda cls, *a: measured.append(1) or real(cls, *a)))
    cfg = T.TrackConfig(filter={"kind": "ekf"})
    first = T.track_files(rm_path, walk, cfg=cfg)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["radio_map.parquet", "walk.mcap", "xdg"]  # nothing beside the map
    cache, = (tmp_path / "xdg" / "graphslam" / T.CALIBRATION_FOLDER).iterdir()
    assert len(measured) == 1 and json.loads(cache.read_text())["covariance_scale"] >= 1
    again = T.track_files(rm_path, walk, cfg=cfg)
    assert len(measured) == 1  # reused
    np.testing.assert_array_equal(again.tracks[0].x, first.tracks[0].x)
    np.testing.assert_array_equal(again.tracks[0].P, first.tracks[0].P)
    # an offline smoother post-processes its filter's run: `--filter ekf --smooth map|rts` reuses the
    # EKF's kept calibration, and smooths what the calibrated EKF would track
    for smoother in ("map", "rts"):
        smoothed = T.track_files(rm_path, walk, cfg=cfg.updated({"filter.smoother": smoother}))
        assert len(measured) == 1 and len(list(cache.parent.iterdir())) == 1, smoother
        fresh = T.track_files(rm_path, walk, cfg=cfg.updated({"filter.smoother": smoother}), calibration_cache=False)
        assert len(measured) == 2, smoother  # measured anew: the same calibration as the one kept
        measured.pop()
        np.testing.assert_array_equal(smoothed.tracks[0].P, fresh.tracks[0].P)
    T.track_files(rm_path, walk, cfg=cfg.updated({"knn_fixes.k": 5}))
    assert len(measured) == 2  # another configuration: another calibration, kept beside the first
    assert len(list(cache.parent.iterdir())) == 2
    T.track_files(rm_path, walk, cfg=cfg, cache_dir=tmp_path / "elsewhere")  # --cache-dir
    assert len(measured) == 3 and (tmp_path / "elsewhere" / T.CALIBRATION_FOLDER / cache.name).is_file()
    measured.pop()
    caplog.set_level(logging.INFO, logger="graphslam.app.track")
    cache.write_text("{not json")
    T.track_files(rm_path, walk, cfg=cfg)
    assert len(measured) == 3 and "unreadable" in caplog.text
    kept = json.loads(cache.read_text())
    cache.write_text(json.dumps(kept | {"covariance_scale": 0.5}))  # right key, impossible value
    T.track_files(rm_path, walk, cfg=cfg)
    assert len(measured) == 4 and "out of range" in caplog.text
    cache.unlink()
    T.track_files(rm_path, walk, cfg=cfg, calibration_cache=False)
    assert len(measured) == 5 and not cache.exists()


def test_track_cli_particle_filter_follows_the_walk_and_has_no_offline_smoother(tiny_case, capsys):
    import json

    from graphslam.cli import main

    d, session = tiny_case
    capsys.readouterr()
    rows, err = _track_rows_and_errors(tiny_case, "positions_pf.csv", "--filter", "particle")
    # it weighs every scan's readings of modelled APs (Huber, none gated): it says how many
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    from graphslam.io.radiomap_io import read_radio_map

    modelled = {a.bssid for a in ApModels.fit(read_radio_map(d / "radio_map.parquet")).fitted}
    heard = sum(len(set(sc.readings) & modelled) for sc in session.scans)
    assert 0 < printed["rssi_used"] <= heard and printed["rssi_gated"] == 0, (printed, heard)
    assert all(float(r["cov_xx"]) > 0 and float(r["cov_yy"]) > 0 for r in rows)
    assert err[len(err) // 2 :].mean() < 4.0, err.mean()
    bad = d / "positions_pf_map.csv"
    with pytest.raises(SystemExit) as e:
        main(["track", str(d / "walk.mcap"), "--radio-map", str(d / "radio_map.parquet"), "--filter", "particle",
              "--smooth", "map", "--out", str(bad)])
    assert e.value.code == 2 and "no offline smoother" in capsys.readouterr().err and not bad.exists()


def test_tracking_reports_its_sessions_and_self_calibration_as_it_goes(tiny_case, monkeypatch):
    """The default (fixed-lag) tracker is slow: its progress moves within a walk, names the walk,
    and the self-calibration (and the RSSI field before it) report their parts."""
    import dataclasses
    import logging

    import graphslam.core.progress as progress
    from graphslam.core.tracking.tracker import Tracker
    from graphslam.io.radiomap_io import read_radio_map
    from graphslam.tracking_config import TrackConfig

    d, session = tiny_case
    rm = read_radio_map(d / "radio_map.parquet")
    models = ApModels.fit(rm)
    ticks: list = []

    class Grab(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            ticks.append(record.tick)  # type: ignore[attr-defined]

    log = logging.getLogger(progress.PROGRESS_LOGGER)
    monkeypatch.setattr(progress, "MIN_INTERVAL_S", 0.0)  # every advance reported
    h = Grab()
    log.addHandler(h)
    log.setLevel(logging.INFO)
    try:
        tracker = Tracker.on_map(rm, models, TrackConfig())
        tracker.track_all([session, dataclasses.replace(session, session_id="second")])
    finally:
        log.removeHandler(h)
        log.setLevel(logging.NOTSET)
    by = lambda name: [t for t in ticks if t.name == name]  # noqa: E731
    assert [t.event for t in by("track: RSSI field")] == ["start", "end"]
    cal = by("track: self-calibration")
    assert cal[-1].event == "end" and cal[-1].done == cal[-1].total == 4
    assert {"RSSI variance", "kNN fix noise", "heading bank temper", "replaying the map's walks"} <= {t.info for t in cal}
    track = by("track")
    n = len(session.steps)
    assert track[-1].event == "end" and track[-1].done == track[-1].total == 2 * n
    assert {f"session 1/2: {session.session_id}", "session 2/2: second"} <= {t.info for t in track}
    # the fixed-lag stream advances step by step within the first walk, not once at its end
    assert any(0 < t.done < n and t.info == f"session 1/2: {session.session_id}" for t in track)


def test_track_announces_a_long_run_before_it_starts(tiny_case, monkeypatch, capsys, tmp_path):
    from graphslam.app import track as T
    from graphslam.cli import main

    d, session = tiny_case
    job = T.prepare_track(d / "radio_map.parquet", [d / "walk.mcap"], cache_dir=tmp_path / "cache")
    n = len(session.steps)
    assert (job.expected.steps, job.expected.walks, job.expected.filter) == (n, 1, "fixed-lag")
    assert job.expected.tracking_s == pytest.approx(n * T.SECONDS_PER_STEP["fixed-lag"])
    assert job.expected.calibration_s > 0  # nothing kept for this map yet
    assert job.notice() is None  # 80 steps: not worth a line
    text = job.notice(above_s=0.0)
    assert text is not None and text.startswith(f"track: 1 walk, {n} steps with the fixed-lag tracker: expect about ")
    assert "of self-calibration on this map, kept in" in text and "(--filter ekf: about" in text
    monkeypatch.setattr(T, "NOTICE_ABOVE_S", 0.0)
    args = ["track", str(d / "walk.mcap"), "--radio-map", str(d / "radio_map.parquet"), "--filter", "ekf", "--no-picture",
            "--cache-dir", str(tmp_path / "cache"), "-o", str(tmp_path / "t.csv")]
    main(args)
    err = capsys.readouterr().err
    assert f"track: 1 walk, {n} steps with the ekf tracker: expect about" in err and "self-calibration" in err
    main(args)  # the calibration is kept now: only the tracking is announced
    err = capsys.readouterr().err
    assert "expect about" in err and "self-calibration" not in err
    main([*args, "-q"])  # --quiet: no progress, no announcement
    assert "expect about" not in capsys.readouterr().err


def test_track_prints_its_errors_against_the_truth(tiny_case, capsys, tmp_path):
    from graphslam.cli import main
    from graphslam.core.common.geometry import interpolate_xy

    d, session = tiny_case
    out = tmp_path / "t.csv"
    main(["-q", "track", str(d / "walk.mcap"), "--radio-map", str(d / "radio_map.parquet"), "--filter", "ekf",
          "--no-picture", "-o", str(out)])
    ev = json.loads(capsys.readouterr().out)["errors"]
    assert ev["evaluated"] and ev["frame"] == "site" and ev["site_from_map"] == "identity: the map is in the site frame"
    rows = list(csv.DictReader(out.open()))
    xy = np.array([[float(r["x"]), float(r["y"])] for r in rows])
    e = np.linalg.norm(xy - interpolate_xy(session.ground_truth, np.array([float(r["t_ns"]) for r in rows])), axis=1)
    assert ev["truth"]["n"] == len(session.steps) == len(rows)
    assert ev["truth"]["mean_m"] == pytest.approx(float(e.mean()), abs=2e-3)
    assert "landmarks" not in ev  # the walk marks none
