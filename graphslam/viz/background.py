"""Run ``log_survey`` in a forked child process, overlapping Rerun's import with the survey's output writing.

Importing ``rerun`` costs a fixed ~0.3-0.5 s, a sizeable share of a few-second survey.
The child is forked *after* alignment, so it inherits the survey and alignment without
copying or pickling them, and imports and logs on the second core while the parent
writes its outputs (``graphslam.io.forked``). Where ``fork`` is unavailable the logging runs inline.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

from graphslam.errors import VisualizationError
from graphslam.io.forked import WAIT_TIMEOUT_S, ForkedCall, ForkedCallError


class BackgroundLog:
    """A started logging job. ``fn`` returns the seconds it spent logging; ``wait()`` returns them
    or raises ``VisualizationError``."""

    def __init__(self, fn: Callable[..., Any], *args: Any, **kwargs: Any) -> None:
        self._call = ForkedCall(fn, *args, **kwargs)

    def wait(self) -> float:
        try:
            return float(self._call.result(WAIT_TIMEOUT_S))
        except ForkedCallError as e:
            raise VisualizationError(f"rerun logging failed: {e}") from None


def start_log_survey(rerun_path: str | Path, *args: Any, **kwargs: Any) -> BackgroundLog:
    """``graphslam.viz.rerun_log.log_survey(rerun_path, *args, **kwargs)`` in the background."""
    return BackgroundLog(_log_survey, rerun_path, *args, **kwargs)


def _log_survey(*args: Any, **kwargs: Any) -> float:
    from graphslam.viz.rerun_log import log_survey

    return log_survey(*args, **kwargs).seconds
