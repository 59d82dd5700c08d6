"""A call run in a forked child (graphslam.io.forked): its value, its failures in one line, the thread or
inline fallback where no child can be forked; and the survey's radio map calibrated in one, or here when
the child fails."""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

import numpy as np
import pytest

from graphslam.io import forked
from graphslam.io.forked import ForkedCall, ForkedCallError

PARENT = os.getpid()


def _where(x: float) -> tuple[int, float]:
    return os.getpid(), 2.0 * x


def _fails() -> None:
    raise ValueError("no\nluck")


def _dies() -> None:
    os._exit(3)


def _sleeps() -> None:
    time.sleep(60)


@pytest.mark.skipif(not forked.can_fork(), reason="no fork on this platform")
def test_a_forked_call_returns_its_value_from_a_child_and_its_failures_in_one_line() -> None:
    call = ForkedCall(_where, 1.5)
    assert call.forked
    pid, value = call.result()
    assert value == 3.0 and pid != os.getpid()
    with pytest.raises(ForkedCallError, match="ValueError: no luck") as e:
        ForkedCall(_fails).result()
    assert "\n" not in str(e.value)
    with pytest.raises(ForkedCallError, match="died"):
        ForkedCall(_dies).result()
    with pytest.raises(ForkedCallError, match="no answer .* in 0 s"):
        ForkedCall(_sleeps).result(timeout_s=0.2)


@pytest.mark.skipif(not forked.can_fork(), reason="no fork on this platform")
def test_a_child_still_running_when_the_caller_fails_is_stopped() -> None:
    with pytest.raises(RuntimeError), ForkedCall(_sleeps) as call:
        proc = call._proc
        assert proc.is_alive()
        raise RuntimeError("the caller's own failure")
    assert not proc.is_alive() and call._proc is None


@pytest.mark.parametrize("fallback", ["thread", "inline"])
def test_where_no_child_can_be_forked_the_call_runs_here(fallback: str, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(forked, "can_fork", lambda: False)  # e.g. a Dask worker (daemonic: no children)
    call = ForkedCall(_where, 2.0, fallback=fallback)
    assert not call.forked and call._here is not None and call._here.threaded == (fallback == "thread")
    assert call.result() == (os.getpid(), 4.0)
    with pytest.raises(ValueError, match="no"):  # the call's own exception, not a child's report
        ForkedCall(_fails, fallback=fallback).result()


@pytest.mark.skipif(not forked.can_fork(), reason="no fork on this platform")
def test_the_survey_calibrates_its_radio_map_here_when_the_child_fails(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    from graphslam import SurveyInputs, load_config, run_survey
    from graphslam.core.radiomap import uncertainty
    from graphslam.io.radiomap_io import read_radio_map
    from graphslam.sim import simulate

    simulate("corridor", seed=1).write(tmp_path / "walks")
    walks = sorted((tmp_path / "walks").glob("*.mcap"))
    cfg = load_config(None)
    run_survey(SurveyInputs(walks, picture=False, out=tmp_path / "forked"), cfg)
    calibrate = uncertainty.calibrate_uncertainty
    here: list[int] = []

    def dies_in_the_child(rm, *a, **k):  # noqa: ANN001, ANN002, ANN003, ANN202
        if os.getpid() != PARENT:
            os._exit(3)
        here.append(1)
        return calibrate(rm, *a, **k)

    monkeypatch.setattr(uncertainty, "calibrate_uncertainty", dies_in_the_child)
    with caplog.at_level(logging.WARNING, logger="graphslam.app.survey"):
        run_survey(SurveyInputs(walks, picture=False, out=tmp_path / "here"), cfg)
    assert here == [1] and "the child process failed (the child process died); calibrating here" in caplog.text
    a, b = (read_radio_map(tmp_path / d / "radio_map.parquet") for d in ("forked", "here"))
    assert a.metadata[uncertainty.METADATA_KEY] == b.metadata[uncertainty.METADATA_KEY]
    assert np.array_equal(a.xy, b.xy)
