"""`optimizer.blas_threads`: OpenBLAS's thread count within a survey, restored after it (issue 16)."""

from __future__ import annotations

from pathlib import Path

import pytest
from threadpoolctl import threadpool_info

from graphslam.app.survey import run_survey
from graphslam.config import config_from_dict
from graphslam.io.mcap_writer import write_session
from graphslam.sim import simulate


def _openblas_threads() -> list[int]:
    return [i["num_threads"] for i in threadpool_info() if i["internal_api"] == "openblas"]


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
    run_survey(recordings, None, cfg, progress=lambda rec: seen.append(_openblas_threads()))
    assert seen, "the optimiser reported no iteration"
    want = before if n == 0 else [n] * len(before)
    assert all(s == want for s in seen)
    assert _openblas_threads() == before
