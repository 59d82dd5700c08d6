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


WAIT_TIMEOUT_S = 600.0  # far above any survey's logging time (0.2 s for 100k poses)


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


class WarmWorker:
    """A forked child that runs ``warm()`` at once, then one job sent later.

    For work whose fixed cost can start before its data exist: ``graphslam survey`` forks
    one at its start to import matplotlib while the survey reads and aligns, then sends it
    the (small) picture scene and lets it draw while the outputs are written. Forked before
    the solver runs, so no solver thread exists to be lost in the fork. ``submit(fn, *args)``
    pickles the job (``fn`` must be a module-level function); ``wait()`` returns what
    ``fn`` returned (a float: its seconds) or raises ``VisualizationError``. A worker
    dropped without ``wait()`` (the survey failed) sees its pipe close and exits. Where
    ``fork`` is unavailable the job runs inline in ``wait()``.
    """

    def __init__(self, warm: Callable[[], Any]) -> None:
        self._job: tuple | None = None
        self._submitted = False
        self._proc = None
        if "fork" in mp.get_all_start_methods():
            ctx = mp.get_context("fork")
            self._send, child_recv = ctx.Pipe(duplex=True)
            self._proc = ctx.Process(target=_warm_child, args=(child_recv, self._send, warm), daemon=True)
            self._proc.start()
            child_recv.close()

    def submit(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> None:
        if self._proc is None:
            self._job = (fn, args, kwargs)
            return
        try:
            self._send.send((fn, args, kwargs))
        except (OSError, EOFError):  # the child is gone: wait() says so
            pass
        self._submitted = True

    def wait(self) -> float:
        if self._proc is None:
            if self._job is None:
                raise VisualizationError("no job submitted")
            fn, args, kwargs = self._job
            return float(fn(*args, **kwargs))
        try:
            if self._send.poll(WAIT_TIMEOUT_S):
                status, seconds, message = self._send.recv()
            else:
                self._proc.terminate()
                status, seconds, message = "error", 0.0, f"no answer from the drawing process in {WAIT_TIMEOUT_S:.0f} s"
        except (EOFError, OSError):
            status, seconds, message = "error", 0.0, "the drawing process died"
        finally:
            self.close()
        if status != "ok":
            raise VisualizationError(message)
        return float(seconds)

    def close(self) -> None:
        """Stop the child (a running job first finishes); idempotent."""
        if self._proc is not None:
            self._release()
            self._proc.join(timeout=WAIT_TIMEOUT_S)
            self._proc = None

    def _release(self) -> None:
        # an explicit stop: a process forked later (the Rerun logger) may hold a copy of this
        # pipe, so the child cannot count on seeing EOF when we close our end
        try:
            if not self._submitted:
                self._send.send(None)
            self._send.close()
        except (OSError, EOFError):
            pass

    def __del__(self) -> None:
        try:
            if self._proc is not None:
                self._release()
        except Exception:  # noqa: BLE001 - interpreter shutdown
            pass


def _warm_child(conn: Connection, parent_end: Connection, warm: Callable[[], Any]) -> None:
    parent_end.close()  # else the child holds the parent's end open and never sees EOF
    try:
        warm()
    except BaseException:  # noqa: BLE001 - the job itself will report what is missing
        pass
    try:
        job = conn.recv()
    except (EOFError, OSError):
        return  # the parent is gone
    if job is None:
        return  # dropped without a job
    fn, args, kwargs = job
    _child(conn, fn, args, kwargs)
