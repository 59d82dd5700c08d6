"""Run ``log_survey`` in a forked child process, overlapping Rerun's import with the survey's output writing.

Importing ``rerun`` costs a fixed ~0.3-0.5 s, a sizeable share of a few-second survey.
The child is forked *after* alignment, so it inherits the survey and alignment without
copying or pickling them, and imports and logs on the second core while the parent
writes its outputs. Where ``fork`` is unavailable the logging runs inline.
"""

from __future__ import annotations

import multiprocessing as mp
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any, Callable

from graphslam.errors import GraphSlamError, VisualizationError


WAIT_TIMEOUT_S = 600.0  # far above any survey's logging time


def _child(conn: Connection, fn: Callable[..., Any], args: tuple, kwargs: dict) -> None:
    try:
        seconds = fn(*args, **kwargs)
        conn.send(("ok", float(seconds), ""))
    except GraphSlamError as e:
        conn.send(("error", 0.0, str(e)))
    except BaseException as e:  # report in one line, never hang the parent
        conn.send(("error", 0.0, f"{type(e).__name__}: {e}"))
    finally:
        conn.close()


class BackgroundLog:
    """A started logging job. ``fn`` returns the seconds it spent logging; ``wait()`` returns them
    or raises ``VisualizationError``."""

    def __init__(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> None:
        self._inline: tuple | None = None
        if "fork" in mp.get_all_start_methods():
            ctx = mp.get_context("fork")
            self._recv, send = ctx.Pipe(duplex=False)
            self._proc = ctx.Process(target=_child, args=(send, fn, args, kwargs), daemon=True)
            self._proc.start()
            send.close()
        else:
            self._inline = (fn, args, kwargs)

    def wait(self) -> float:
        if self._inline is not None:
            fn, args, kwargs = self._inline
            return float(fn(*args, **kwargs))
        try:
            if self._recv.poll(WAIT_TIMEOUT_S):
                status, seconds, message = self._recv.recv()
            else:  # a child forked from a threaded process could deadlock: do not wait forever
                self._proc.terminate()
                status, seconds, message = "error", 0.0, f"no answer from the logging process in {WAIT_TIMEOUT_S:.0f} s"
        except EOFError:
            status, seconds, message = "error", 0.0, "the logging process died"
        finally:
            self._recv.close()
        self._proc.join()
        if status != "ok":
            raise VisualizationError(f"rerun logging failed: {message}")
        return float(seconds)


def start_log_survey(rerun_path: str | Path, *args: Any, **kwargs: Any) -> BackgroundLog:
    """``graphslam.viz.rerun_log.log_survey(rerun_path, *args, **kwargs)`` in the background."""
    return BackgroundLog(_log_survey, rerun_path, *args, **kwargs)


def _log_survey(*args: Any, **kwargs: Any) -> float:
    from graphslam.viz.rerun_log import log_survey

    return log_survey(*args, **kwargs).seconds
