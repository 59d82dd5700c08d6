"""What a survey process loads and runs with (issue 16): OpenBLAS's thread count within a survey
(`optimizer.blas_threads`), restored after it; no GTSAM for a survey the vectorised solver solves."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from threadpoolctl import threadpool_info

from graphslam.app.survey import run_survey
from graphslam.app.survey_inputs import SurveyInputs
from graphslam.config import config_from_dict
from graphslam.io.mcap_writer import write_session
from graphslam.sim import simulate


def _openblas_threads() -> list[int]:
    # numpy's and scipy's; cvxopt's bundled copy (CHOLMOD's, loaded by an earlier test) follows optimizer.threads
    return [i["num_threads"] for i in threadpool_info()
            if i["internal_api"] == "openblas" and "cvxopt" not in i["filepath"]]


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    root = tmp_path_factory.mktemp("threads")
    paths = []
    for s in simulate("paper", seed=0, size=0.25).survey:
        paths.append(root / f"{s.session_id}.mcap")
        write_session(s, paths[-1])
    return paths


@pytest.mark.parametrize("n", [1, 2, 0])
def test_survey_runs_openblas_at_the_configured_count_and_restores_it(recordings: list[Path], n: int) -> None:
    before = _openblas_threads()
    if not before:
        pytest.skip("numpy is not built on OpenBLAS here")
    seen: list[list[int]] = []
    cfg = config_from_dict({"optimizer": {"blas_threads": n}})
    run_survey(SurveyInputs(recordings), cfg, progress=lambda rec: seen.append(_openblas_threads()))
    assert seen, "the optimiser reported no iteration"
    want = before if n == 0 else [n] * len(before)
    assert all(s == want for s in seen)
    assert _openblas_threads() == before


def test_a_wifi_only_survey_never_loads_gtsam(recordings: list[Path], tmp_path: Path) -> None:
    """GTSAM (~0.1 s to import) is loaded where a GTSAM factor is built: not for the default solver."""
    code = textwrap.dedent(f"""
        import sys
        from graphslam.app.survey import run_survey
        from graphslam.app.survey_inputs import SurveyInputs
        r = run_survey(SurveyInputs({[str(p) for p in recordings]!r}, {str(tmp_path / "out")!r}))
        assert not r.alignment.unaligned and r.alignment.tracks, r.alignment.unaligned
        print(sorted(m for m in sys.modules if m.split(".")[0] == "gtsam"))
    """)
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip() == "[]"


def test_uwb_keys_are_gtsams_symbols() -> None:
    import gtsam

    from graphslam.core.uwb.factors import L, X

    for j in (0, 1, 7, 123_456, 2**40):
        assert X(j) == gtsam.symbol_shorthand.X(j) and L(j) == gtsam.symbol_shorthand.L(j)
        assert gtsam.Symbol(X(j)).chr() == ord("x") and gtsam.Symbol(L(j)).index() == j
