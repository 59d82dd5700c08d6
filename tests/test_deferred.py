"""A call whose value is taken later (graphslam.core.common.deferred): on its own thread or in turn, the
same value and the call's own exception."""

from __future__ import annotations

import threading

import pytest

from graphslam.core.common.deferred import Deferred
from graphslam.errors import GraphSlamError


def _where(x: float) -> tuple[str, float]:
    return threading.current_thread().name, 2.0 * x


def _fails() -> None:
    raise ValueError("no such thing")


@pytest.mark.parametrize("thread", [True, False])
def test_a_deferred_call_gives_its_value_and_its_own_exception(thread: bool) -> None:
    here = threading.current_thread().name
    call = Deferred(_where, 2.0, thread=thread, name="beside")
    assert call.threaded == thread
    where, value = call.result()
    assert value == 4.0 and (where.startswith("beside") if thread else where == here)
    with pytest.raises(ValueError, match="no such thing"):
        Deferred(_fails, thread=thread).result()


def test_a_call_in_turn_runs_once_and_a_thread_not_taken_is_waited_for() -> None:
    runs: list[int] = []
    call = Deferred(runs.append, 1)
    assert runs == []  # in turn: nothing runs before its value is asked for
    call.result()
    with pytest.raises(GraphSlamError, match="already taken"):
        call.result()
    assert runs == [1]
    started, release = threading.Event(), threading.Event()

    def slow() -> None:
        started.set()
        release.wait(5.0)
        runs.append(2)

    call = Deferred(slow, thread=True)
    started.wait(5.0)
    threading.Timer(0.05, release.set).start()
    call.close()  # the caller failed: the thread is waited for, not abandoned
    assert runs == [1, 2]
