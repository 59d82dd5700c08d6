"""A call run beside the caller's work in a forked child process: the second core for work that holds
the GIL (numpy on small arrays, Python loops), where a thread would only take turns with the caller.

The child is forked when the call is made, so it inherits its inputs without copying or pickling them;
only its result (picklable) comes back, through a pipe. Where no child can be forked (no ``fork`` start
method, or a daemonic process such as a Dask worker, which may not have children) the call runs in a
thread, or inline when its result is asked for (``fallback``): ``result()`` is the same either way.
"""

from __future__ import annotations

import multiprocessing as mp
from multiprocessing.connection import Connection
from typing import Any, Callable, Literal

from graphslam.core.common.deferred import Deferred
from graphslam.errors import GraphSlamError

WAIT_TIMEOUT_S = 600.0  # far above any call's time: a child forked from a threaded process could deadlock


class ForkedCallError(GraphSlamError):
    """The child failed (its exception in one line), died, or did not answer in time."""


def can_fork() -> bool:
    """Whether this process can fork a child for a call."""
    return "fork" in mp.get_all_start_methods() and not mp.current_process().daemon


def _child(conn: Connection, fn: Callable[..., Any], args: tuple, kwargs: dict) -> None:
    try:
        conn.send(("ok", fn(*args, **kwargs)))
    except GraphSlamError as e:
        conn.send(("error", " ".join(str(e).split())))
    except BaseException as e:  # report in one line, never hang the parent
        conn.send(("error", f"{type(e).__name__}: {' '.join(str(e).split())}"))
    finally:
        conn.close()


class ForkedCall:
    """``fn(*args, **kwargs)`` started now, in a forked child (else per ``fallback``); ``result()`` waits
    for its value. As a context manager: a child still running at the exit (the caller failed) is stopped."""

    def __init__(self, fn: Callable[..., Any], *args: Any, fallback: Literal["thread", "inline"] = "inline",
                 **kwargs: Any) -> None:
        self._proc: Any = None
        self._here: Deferred | None = None  # the call in this process, where no child can be forked
        if can_fork():
            ctx = mp.get_context("fork")
            self._recv, send = ctx.Pipe(duplex=False)
            self._proc = ctx.Process(target=_child, args=(send, fn, args, kwargs), daemon=True)
            self._proc.start()
            send.close()
        else:
            self._here = Deferred(fn, *args, thread=fallback == "thread", **kwargs)

    @property
    def forked(self) -> bool:
        return self._proc is not None

    def result(self, timeout_s: float = WAIT_TIMEOUT_S) -> Any:
        """The call's value; its exception where it ran in this process; ``ForkedCallError`` for a child
        that failed, died or did not answer within ``timeout_s``."""
        if self._here is not None:
            return self._here.result()
        if self._proc is None:
            raise ForkedCallError("the call's value was already taken")
        status, value = "error", f"no answer from the child process in {timeout_s:.0f} s"
        try:
            if self._recv.poll(timeout_s):
                status, value = self._recv.recv()
        except EOFError:
            status, value = "error", "the child process died"
        finally:
            self._close(stop=status != "ok")
        if status != "ok":
            raise ForkedCallError(value)
        return value

    def _close(self, stop: bool) -> None:
        """Wait for the thread or the child (``stop``: the child is stopped first), once."""
        if self._here is not None:
            self._here.close()
        if self._proc is not None:
            self._recv.close()
            if stop and self._proc.is_alive():
                self._proc.terminate()
            self._proc.join()
            self._proc = None

    def __enter__(self) -> "ForkedCall":
        return self

    def __exit__(self, *exc: object) -> None:
        self._close(stop=True)
