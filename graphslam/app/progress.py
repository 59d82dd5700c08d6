"""What a user sees of the library's progress (``graphslam.core.progress`` tasks).

``show_progress(mode)`` installs one handler on the ``graphslam.progress`` logger:

- ``bar``: a tqdm bar per running task on stderr (nested tasks stack), gone when the task ends;
- ``log``: a line every ``interval_s`` seconds per running task, and one when a task that
  ran at least ``min(interval_s, 1 s)`` ends, so a nightly job's log shows where it is::

      2026-12-01 02:00:13,201 progress edges: 12/30 blocks (40 %), 10.0 s
      2026-12-01 02:00:21,950 progress edges: 30/30 blocks (100 %) done in 18.7 s

- ``off``: nothing; ``auto``: ``bar`` on a terminal, else ``log``.

The CLI calls it once per command (``--quiet`` means ``off``); library users may call it too.
"""

from __future__ import annotations

import logging
import sys
import threading
import time
from typing import IO, Any

from graphslam.core.progress import PROGRESS_LOGGER, Tick
from graphslam.errors import ConfigError

MODES = ("auto", "bar", "log", "off")
DEFAULT_INTERVAL_S = 10.0  # a nightly log gets a line per running stage every 10 s: enough to see a hang

_installed: logging.Handler | None = None


def show_progress(mode: str = "auto", *, interval_s: float = DEFAULT_INTERVAL_S, stream: IO[str] | None = None) -> str:
    """Show progress as ``mode`` from now on (replacing what an earlier call installed); returns
    the mode used (``auto`` resolved)."""
    global _installed
    if mode not in MODES:
        raise ConfigError(f"progress mode {mode!r}: use one of {', '.join(MODES)}")
    if not interval_s >= 0:
        raise ConfigError(f"progress interval must be >= 0 s, got {interval_s}")
    out = stream if stream is not None else sys.stderr
    if mode == "auto":
        mode = "bar" if _isatty(out) else "log"
    log = logging.getLogger(PROGRESS_LOGGER)
    if _installed is not None:
        log.removeHandler(_installed)
        _installed.close()
        _installed = None
    if mode == "off":
        log.setLevel(logging.NOTSET)  # the root level (WARNING) again: tasks skip their ticks
        return mode
    _installed = _BarHandler(out) if mode == "bar" else _LineHandler(out, interval_s)
    log.addHandler(_installed)
    log.setLevel(logging.INFO)
    return mode


def progress_shown() -> bool:
    """Whether progress is shown (``show_progress`` installed a bar or a line handler): what a
    command prints about its progress besides the ticks (e.g. ``track``'s expected cost) follows it."""
    return _installed is not None


def _isatty(stream: IO[str]) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


class _TickHandler(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self._guard = threading.Lock()

    def emit(self, record: logging.LogRecord) -> None:
        tick = getattr(record, "tick", None)
        if isinstance(tick, Tick):
            with self._guard:
                self.show(tick)

    def show(self, tick: Tick) -> None:  # pragma: no cover - abstract
        raise NotImplementedError


class _BarHandler(_TickHandler):
    def __init__(self, stream: IO[str]) -> None:
        super().__init__()
        self.stream = stream
        self.bars: dict[int, Any] = {}

    def show(self, tick: Tick) -> None:
        from tqdm import tqdm

        bar = self.bars.get(tick.task_id)
        if bar is None:
            if tick.event == "end":
                return
            counted = tick.total is not None or bool(tick.unit)
            bar = tqdm(
                desc=tick.name, total=tick.total, unit=f" {tick.unit}", leave=False, file=self.stream,
                position=len(self.bars), dynamic_ncols=True, mininterval=0,
                bar_format=None if counted else "{desc}: {elapsed}{postfix}",  # a stage without a count
            )
            self.bars[tick.task_id] = bar
        if tick.event == "end":
            bar.close()
            del self.bars[tick.task_id]
            return
        bar.n = tick.done
        bar.set_postfix_str(tick.info, refresh=False)
        bar.refresh()

    def close(self) -> None:
        for bar in self.bars.values():
            bar.close()
        self.bars.clear()
        super().close()


class _LineHandler(_TickHandler):
    def __init__(self, stream: IO[str], interval_s: float) -> None:
        super().__init__()
        self.stream = stream
        self.interval_s = interval_s
        self.last: dict[int, float] = {}  # task -> when its last line was written
        self.fmt = logging.Formatter("%(asctime)s progress %(message)s")

    def show(self, tick: Tick) -> None:
        now = time.monotonic()
        if tick.event == "start":
            self.last[tick.task_id] = now
            return
        last = self.last.get(tick.task_id, now)
        if tick.event == "end":
            self.last.pop(tick.task_id, None)
            if tick.elapsed_s < min(self.interval_s, 1.0):
                return  # a quick stage: its line would only be noise
        elif now - last < self.interval_s or (tick.total is not None and tick.done >= tick.total):
            return  # (a task's count complete: its end's "done" line says it, once)
        else:
            self.last[tick.task_id] = now
        record = logging.LogRecord(PROGRESS_LOGGER, logging.INFO, __file__, 0, tick.describe(), None, None)
        self.stream.write(self.fmt.format(record) + "\n")
        self.stream.flush()
