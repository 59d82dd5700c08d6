from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from conftest import REPO

from graphslam.config import GraphSlamConfig, commented_yaml, load_config
from graphslam.errors import ConfigError


def test_default_yaml_mirrors_models() -> None:
    assert load_config(REPO / "configs" / "default.yaml") == GraphSlamConfig()
    # regenerate with: python -c "from graphslam.config import commented_yaml; print(commented_yaml(), end='')"
    assert (REPO / "configs" / "default.yaml").read_text() == commented_yaml()
    data = yaml.safe_load((REPO / "configs" / "default.yaml").read_text())
    assert data == GraphSlamConfig().model_dump(mode="json")


def test_unknown_key_is_an_error(tmp_path: Path) -> None:
    p = tmp_path / "c.yaml"
    p.write_text("wifi:\n  d_min_m: 3\n  dmax: 20\n")
    with pytest.raises(ConfigError) as e:
        load_config(p)
    assert str(p) in str(e.value) and "wifi.dmax" in str(e.value)


def test_a_configuration_naming_mkl_pardiso_loads_with_a_warning_per_key(tmp_path: Path, caplog) -> None:
    # a previous survey's config.yaml from when PARDISO was a solver: its keys ignored, solver pardiso is CHOLMOD
    p = tmp_path / "c.yaml"
    p.write_text("optimizer:\n  solver: pardiso\n  threads: 2\n  factor_precision: single\n"
                 "  single_above_variables: 1000\n  max_iterations: 7\n")
    c = load_config(p)
    assert c.optimizer.solver == "cholmod" and c.optimizer.max_iterations == 7
    assert c.optimizer == GraphSlamConfig().optimizer.model_copy(update={"solver": "cholmod", "max_iterations": 7})
    for key in ("threads", "factor_precision", "single_above_variables", "solver pardiso"):
        assert f"optimizer.{key}" in caplog.text
    p.write_text("optimizer:\n  solver: mkl\n")
    with pytest.raises(ConfigError, match="optimizer.solver"):  # anything else stays an error
        load_config(p)


def test_partial_file_merges_over_defaults(tmp_path: Path) -> None:
    p = tmp_path / "c.yaml"
    p.write_text("wifi:\n  d_min_m: 3\n")
    c = load_config(p)
    assert c.wifi.d_min_m == 3 and c.wifi.d_max_m == GraphSlamConfig().wifi.d_max_m


def test_bad_values_rejected(tmp_path: Path) -> None:
    p = tmp_path / "c.yaml"
    p.write_text("wifi:\n  d_min_m: 40\n  d_max_m: 30\n")
    with pytest.raises(ConfigError, match="d_max_m must be greater"):
        load_config(p)
    p.write_text("- a list\n")
    with pytest.raises(ConfigError, match="mapping"):
        load_config(p)


def test_cli_metric_options_reject_unknown_metrics_before_reading_files(capsys, tmp_path: Path) -> None:
    from graphslam.cli import main

    missing = str(tmp_path / "no_map.parquet")  # the metric is checked first: no "no such file" here
    for argv, option in (
        (["locate", str(tmp_path), "--radio-map", missing, "--out", str(tmp_path / "o.csv"), "--metric", "cosine"], "--metric"),
        (["serve", "--radio-map", missing, "--metric", "cosine"], "--metric"),
        (["track", str(tmp_path), "--radio-map", missing, "--out", str(tmp_path / "o.csv"), "--metric", "cosine"], "--metric"),
    ):
        with pytest.raises(SystemExit) as e:
            main(argv)
        err = capsys.readouterr().err
        assert e.value.code == 2 and f"Invalid value for '{option}': Value error, 'cosine' is not one of 'sorensen', 'eq9'" in err, argv
        assert len(err.strip().splitlines()) == 1
    assert list(tmp_path.iterdir()) == []


def test_track_config_knn_metric() -> None:
    from graphslam.core.tracking.tracker import knn_config, particle_config
    from graphslam.tracking_config import TrackConfig

    assert knn_config(TrackConfig(knn_fixes={"metric": "sorensen"})).metric == "sorensen"
    # the particle filter matches on the same distance, its temperature in that distance's units
    from graphslam.core.tracking.particle import PARTICLE_TEMPERATURE

    pf = TrackConfig(filter={"kind": "particle"})
    assert knn_config(pf).metric == "sorensen" and particle_config(pf).temperature == PARTICLE_TEMPERATURE["sorensen"]
    assert PARTICLE_TEMPERATURE["sorensen"] < 1.0 < PARTICLE_TEMPERATURE["eq9"]  # unitless in [0, 1] / dB
    eq9 = TrackConfig(filter={"kind": "particle"}, knn_fixes={"metric": "eq9"})
    assert knn_config(eq9).metric == "eq9" and particle_config(eq9).temperature == PARTICLE_TEMPERATURE["eq9"]
    assert particle_config(TrackConfig(filter={"kind": "particle"}, particle={"temperature": 0.1})).temperature == 0.1
    with pytest.raises(ConfigError, match="particle.temperature"):
        TrackConfig(filter={"kind": "particle"}, particle={"temperature": 0.0})
    with pytest.raises(ConfigError, match="knn_fixes.metric: Input should be 'sorensen' or 'eq9'"):
        TrackConfig(knn_fixes={"metric": "cosine"})
    with pytest.raises(ConfigError, match="fixed_lag.bank_temper"):
        TrackConfig(fixed_lag={"bank_temper": 0.5})  # below 1 would sharpen the bank's odds beyond its own likelihood
