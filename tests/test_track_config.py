"""One tracking configuration (graphslam/tracking_config.py, configs/track.yaml): sections, strict
values, --config/--set, the effective configuration beside every run; and the service's one object."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from conftest import REPO
from test_apmodel import tiny_case  # noqa: F401 (the fixture)

from graphslam.errors import ConfigError
from graphslam.tracking_config import DEFAULTS, TrackConfig, commented_track_yaml, load_track_config


def test_track_yaml_mirrors_the_models() -> None:
    # regenerate with: python -c "from graphslam.tracking_config import commented_track_yaml as c; print(c(), end='')"
    assert (REPO / "configs" / "track.yaml").read_text() == commented_track_yaml()
    assert load_track_config(REPO / "configs" / "track.yaml") == DEFAULTS


def test_partial_files_merge_and_bad_values_are_config_errors(tmp_path: Path) -> None:
    p = tmp_path / "t.yaml"
    p.write_text("fixed_lag:\n  lag_s: 1.5\nfilter:\n  kind: ekf\n")
    cfg = load_track_config(p, {"rssi": {"adaptive": False}})
    assert (cfg.fixed_lag.lag_s, cfg.filter.kind, cfg.rssi.adaptive) == (1.5, "ekf", False)
    assert cfg.fixed_lag.window_s == DEFAULTS.fixed_lag.window_s  # the rest: defaults
    for data, where in (({"fixed_lag": {"lag_s": -1}}, "fixed_lag.lag_s"), ({"motion": {"typo": 1}}, "motion.typo"),
                        ({"knn_fixes": {"metric": "cosine"}}, "knn_fixes.metric"),
                        ({"filter": {"kind": "particle", "smoother": "rts"}}, "no offline smoother")):
        with pytest.raises(ConfigError, match=where):
            load_track_config(None, data)
        with pytest.raises(ConfigError, match=where):
            TrackConfig(**data)  # built in code: the same error type
    with pytest.raises(ConfigError, match="unknown configuration key 'motion.nope'"):
        DEFAULTS.updated({"motion.nope": 1})


def test_the_core_takes_its_defaults_from_the_one_configuration() -> None:
    from graphslam.core.tracking.fixed_lag import FixedLagConfig
    from graphslam.core.tracking.particle import ParticleConfig

    fl, pc = FixedLagConfig(), ParticleConfig()
    assert (fl.lag_s, fl.window_s, fl.prune_cost) == (DEFAULTS.fixed_lag.lag_s, DEFAULTS.fixed_lag.window_s, DEFAULTS.fixed_lag.prune_cost)
    # these two disagreed before: the fixed-lag smoother's own defaults are the tracker's
    assert fl.report == DEFAULTS.fixed_lag.bank_report == "mixture" and fl.adaptive_rssi is DEFAULTS.rssi.adaptive is True
    assert fl.huber_k == pc.huber_k == DEFAULTS.filter.gate_sigma
    assert (pc.n_particles, pc.top_k, pc.kernel_m, pc.lag_s) == (
        DEFAULTS.particle.count, DEFAULTS.particle.top_k, DEFAULTS.particle.kernel_m, DEFAULTS.fixed_lag.lag_s)


def test_track_takes_config_and_set_and_writes_the_effective_config_beside_its_output(tiny_case, tmp_path) -> None:  # noqa: F811
    from graphslam.cli import main

    d, _ = tiny_case
    cfg_file = tmp_path / "track.yaml"
    cfg_file.write_text("filter:\n  kind: ekf\nmotion:\n  n_theta_hypotheses: 2\n")
    out = tmp_path / "pos.csv"
    main(["-q", "track", str(d / "walk.mcap"), "--radio-map", str(d / "radio_map.parquet"), "--out", str(out),
          "--config", str(cfg_file), "--set", "motion.velocity_sigma_mps=0.2", "--no-self-calibrate", "--no-picture"])
    written = yaml.safe_load((tmp_path / "pos.config.yaml").read_text())
    effective = load_track_config(None, written)
    assert effective.filter.kind == "ekf" and effective.motion.n_theta_hypotheses == 2
    assert effective.motion.velocity_sigma_mps == 0.2 and effective.calibration.enabled is False
    assert effective.fixed_lag == DEFAULTS.fixed_lag  # untouched sections: the defaults


def test_track_set_errors_are_one_line(tiny_case, tmp_path, capsys) -> None:  # noqa: F811
    from graphslam.cli import main

    d, _ = tiny_case
    out = tmp_path / "bad.csv"
    for args, message in ((["--set", "motion.n_theta_hypotheses=0"], "motion.n_theta_hypotheses"),
                          (["--set", "nope"], "expected KEY=VALUE"), (["--config", str(tmp_path / "absent.yaml")], "absent.yaml")):
        with pytest.raises(SystemExit) as e:
            main(["track", str(d / "walk.mcap"), "--radio-map", str(d / "radio_map.parquet"), "--out", str(out), *args])
        err = capsys.readouterr().err
        assert e.value.code == 2 and message in err and len(err.strip().splitlines()) == 1, err
        assert not out.exists()


def test_serve_builds_one_config_object_from_the_options_given(monkeypatch, capsys, tmp_path) -> None:
    from graphslam.cli import main
    from graphslam.service import server
    from graphslam.service.config import DEFAULT_WATCH_S, ServeConfig

    seen: list = []
    monkeypatch.setattr(server, "serve", lambda path, cfg: seen.append((path, cfg)))
    (tmp_path / "m.parquet").write_bytes(b"")  # serve refuses a missing map before anything else
    main(["serve", "--radio-map", str(tmp_path / "m.parquet"), "--port", "9001", "--watch", "--log-level", "WARNING"])
    (path, cfg), = seen
    assert path == tmp_path / "m.parquet"
    assert cfg == ServeConfig(port=9001, watch_s=DEFAULT_WATCH_S, log_level="warning")  # the rest: its defaults
    with pytest.raises(SystemExit) as e:
        main(["serve", "--radio-map", str(tmp_path / "m.parquet"), "--index", "kdtree"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "Invalid value for '--index'" in err and len(err.strip().splitlines()) == 1
    with pytest.raises(ConfigError, match="port"):
        ServeConfig(port=70000)
