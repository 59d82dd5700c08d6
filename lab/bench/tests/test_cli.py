"""``python -m lab.bench``: its option parsers and one-line errors (exit code 2), as ``graphslam``'s."""

from __future__ import annotations

from pathlib import Path

import pytest

from lab.bench.__main__ import main, seeds_of


def test_cli_seed_lists_take_ranges_and_reject_garbage(capsys) -> None:
    assert seeds_of("0-3,7") == [0, 1, 2, 3, 7]
    assert seeds_of("5") == [5]
    with pytest.raises(SystemExit) as e:
        main(["filters", "--seeds", "0-x"])
    assert e.value.code == 2 and "--seeds '0-x'" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main(["filters", "--seeds", "0", "--smoothers", "ks"])
    assert e.value.code == 2 and "unknown smoother 'ks'" in capsys.readouterr().err
    for bad in ("1.5,3", "0.5", "0.5,-1", "a,b"):
        with pytest.raises(SystemExit) as e:
            main(["filters", "--seeds", "0", "--shadowing", bad])
        err = capsys.readouterr().err
        assert e.value.code == 2 and f"--shadowing: {bad!r}" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("command", [["filters"], ["tracking", "paper"]])
@pytest.mark.parametrize("lags", ["abc", "-1", "1,nan"])
def test_bad_lags_are_one_line_usage_errors(command, lags, capsys):
    with pytest.raises(SystemExit) as e:
        main([*command, f"--lags={lags}"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "--lags" in err and len(err.strip().splitlines()) == 1


def test_an_unknown_metric_is_refused_before_any_file_is_read(capsys, tmp_path: Path) -> None:
    with pytest.raises(SystemExit) as e:
        main(["ujiindoorloc", str(tmp_path), "--metric", "cosine"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "--metric: 'cosine' is not one of sorensen, eq9" in err
    assert len(err.strip().splitlines()) == 1 and list(tmp_path.iterdir()) == []


def test_the_simulator_benchmarks_are_not_graphslam_commands(capsys) -> None:
    from graphslam import cli_main as graphslam_main

    with pytest.raises(SystemExit) as e:
        graphslam_main(["bench", "accuracy", "paper"])
    assert e.value.code == 2 and "No such command 'accuracy'" in capsys.readouterr().err
