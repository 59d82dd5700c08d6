"""`python -m lab.bench scale`: growth exponent, the stage table, and its bad-input errors."""

from __future__ import annotations

from pathlib import Path

import pytest

from lab.bench.scale import growth_exponent, markdown_table
from lab.bench.__main__ import main


def test_growth_exponent_is_the_log_log_slope() -> None:
    sizes = [1, 2, 4, 8, 12]
    assert growth_exponent(sizes, [3.0 * s**1.25 for s in sizes]) == pytest.approx(1.25)
    assert growth_exponent(sizes, [5.0] * 5) == pytest.approx(0.0)


def _side(wall: float) -> dict:
    stages = {"read": 0.4, "align.edges": 0.2, "align.optimise": wall / 4, "write": 0.3, "total": wall - 1.0}
    return {"runs": 3, "wall_s": wall, "cpu_s": wall * 0.9, "startup_s": 1.0, "stages_s": stages, "peak_rss_mb": 200.0,
            "final_error": 27.79, "iterations": 7, "edges": 5392, "landmark_mean_m": 0.677}


def test_table_has_a_column_per_side_and_size_and_the_load() -> None:
    result = {"rows": [{"size": 1.0, "load_1min": [0.5, 0.7], "base": _side(4.0), "new": _side(2.0)},
                       {"size": 12.0, "load_1min": [1.0, 1.2], "new": _side(40.0)}], "growth_exponent_new": 1.2}
    table = markdown_table(result)
    assert table.splitlines()[0] == "| stage (wall s) | size 1 base | size 1 new | size 12 new |"
    assert "| optimise | 1.00 | 0.50 | 10.00 |" in table
    assert "| **wall** | **4.00** | **2.00** | **40.00** |" in table
    assert "size 1: 0.5-0.7" in table and "growth exponent (this checkout): 1.2 " in table


@pytest.mark.parametrize(
    "args, message",
    [(["--sizes", "1,2", "--runs", "3,2,1"], "--runs"), (["--sizes", "one"], "--sizes"), (["--runs", "0"], "--runs")],
)
def test_bad_sizes_or_runs_are_one_line_errors(args: list[str], message: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        main(["scale", "paper", *args])
    err = capsys.readouterr().err
    assert e.value.code == 2 and message in err and len(err.strip().splitlines()) == 1


def test_a_baseline_that_is_not_a_checkout_is_an_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        main(["scale", "paper", "--baseline", str(tmp_path)])
    assert e.value.code == 2 and "not a graphslam checkout" in capsys.readouterr().err


def test_the_baseline_runs_its_own_code_even_from_inside_this_checkout(tmp_path: Path, monkeypatch) -> None:
    # A fake baseline whose `python -m graphslam survey` writes a report with iterations = 4242.
    # Started from the repository root (where ./graphslam is this checkout), the run must still
    # import the baseline's package: before -P, `python -m` put the cwd first and timed this
    # checkout twice.
    import json

    from lab.bench.scale import _run_once

    pkg = tmp_path / "base" / "graphslam"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    report = {"timings_s": {"total": 0.0}, "edges": {"wifi": 0},
              "optimizer": {"final_error": 0.0, "iterations": 4242, "solver": "cholmod", "ordering": "metis",
                            "linear_solver": "cholesky"}}
    (pkg / "__main__.py").write_text(
        "import json, pathlib, sys\n"
        "out = pathlib.Path(sys.argv[sys.argv.index('--out') + 1]); out.mkdir(parents=True, exist_ok=True)\n"
        f"(out / 'report.json').write_text({json.dumps(json.dumps(report))})\n"
    )
    monkeypatch.chdir(Path(__file__).resolve().parents[3])
    run = _run_once(tmp_path / "data", tmp_path / "out", str(tmp_path / "base"), None)
    assert run["iterations"] == 4242 and run["backend"] == "cholmod metis cholesky"


def test_rounds_go_round_robin_over_the_sizes(tmp_path: Path, monkeypatch) -> None:
    """Round r of every size before round r + 1 of any: a host that slows down over minutes slows
    all sizes alike (the exponent is not tilted by which size ran last)."""
    import graphslam as gs
    from lab.bench import scale as bench_scale

    class _Fake:
        def write(self, path: Path) -> None:
            path.mkdir(parents=True)

    calls: list[tuple[str, str | None]] = []

    def fake_run(data: Path, out: Path, base: str | None, config: Path | None) -> dict:
        calls.append((data.name, base))
        wall = {"data-1": 1.0, "data-4": 4.0}[data.name]
        return {"wall": wall, "cpu": wall, "stages": {"total": wall - 0.1, "align.optimise": 0.5}, "rss_mb": 1.0,
                "final_error": 0.0, "iterations": 1, "edges": 0, "landmark_mean_m": None}

    monkeypatch.setattr(gs, "simulate", lambda *a, **k: _Fake())
    monkeypatch.setattr(bench_scale, "_run_once", fake_run)
    base = tmp_path / "base"
    (base / "graphslam").mkdir(parents=True)
    (base / "graphslam" / "__init__.py").write_text("")
    res = bench_scale.scale("paper", 0, [1, 4], [2, 3], baseline=base, baseline_max_size=1)
    sizes = [c[0] for c in calls]
    assert sizes == ["data-1", "data-1", "data-4", "data-1", "data-1", "data-4", "data-4"]
    assert [c[1] is None for c in calls[:2]] == [True, False] and [c[1] is None for c in calls[3:5]] == [False, True]
    assert res["rows"][0]["new"]["runs"] == 2 and res["rows"][1]["new"]["runs"] == 3
    assert res["growth_exponent_new"] == 1.0  # walls 1 and 4 at sizes 1 and 4


def test_solvers_take_turns_and_are_compared_with_cholmod(tmp_path: Path, monkeypatch) -> None:
    import graphslam as gs
    from lab.bench import scale as bench_scale

    class _Fake:
        def write(self, path: Path) -> None:
            path.mkdir(parents=True)

    calls: list[str] = []

    def fake_run(data: Path, out: Path, base: str | None, config: Path | None) -> dict:
        name = config.read_text().split("solver: ")[1].strip()
        calls.append(name)
        wall = {"gtsam": 9.0, "auto": 3.0, "cholmod": 2.0}[name]
        return {"wall": wall, "cpu": wall, "stages": {"total": wall, "align.optimise": wall / 2}, "rss_mb": 1.0,
                "final_error": 1.0, "iterations": 3, "edges": 0, "landmark_mean_m": 0.5}

    monkeypatch.setattr(gs, "simulate", lambda *a, **k: _Fake())
    monkeypatch.setattr(bench_scale, "_run_once", fake_run)
    row = bench_scale.solvers("paper", 0, 4.0, ["gtsam", "auto", "cholmod"], 2)
    assert calls == ["gtsam", "auto", "cholmod", "cholmod", "auto", "gtsam"]
    assert row["wall_vs_cholmod"] == {"gtsam": 4.5, "auto": 1.5, "cholmod": 1.0}
    assert row["optimise_vs_cholmod"]["auto"] == 1.5 and row["auto"]["runs"] == 2


def test_unknown_solvers_are_one_line_errors(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        main(["solvers", "--solvers", "gtsam,superlu"])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "--solvers" in err and len(err.strip().splitlines()) == 1
