"""Progress of long work, reported without printing.

Library code marks each stage that can take more than a second (read, edges, optimise,
write, track, fit-aps, benchmark loops, ...) with a ``Task``::

    with Task("read", total=len(files), unit="file") as task:
        for f in files:
            ...
            task.advance()

    for seed in progress_over(seeds, "bench accuracy", unit="seed"):  # the same, for a loop
        ...

A task reports ``Tick`` records to the ``graphslam.progress`` logger (``extra={"tick": tick}``)
and never prints: what a user sees is decided by whoever runs the code
(``graphslam.app.progress.show_progress``: tqdm bars on a terminal, periodic log lines in a
batch job's log, nothing with ``--quiet``). The logger does not propagate, so ticks never
reach the root logger's handlers. Nobody listening costs one ``isEnabledFor`` per task and
per throttled update: tasks may advance once per step of a Python loop.
"""

from __future__ import annotations

import itertools
import logging
import time
from dataclasses import dataclass
from typing import Iterable, Iterator, TypeVar

PROGRESS_LOGGER = "graphslam.progress"
_log = logging.getLogger(PROGRESS_LOGGER)
_log.propagate = False
_log.addHandler(logging.NullHandler())
_ids = itertools.count(1)

# a running task reports at most this often (plus its start and its end): a listener sees
# a live count, and a per-step loop does not pay for a log record per step
MIN_INTERVAL_S = 0.1

T = TypeVar("T")


@dataclass(frozen=True)
class Tick:
    """One report of a task: ``done`` of ``total`` (None: unknown) ``unit``s after ``elapsed_s``."""

    task_id: int  # unique per Task in this process (two tasks may share a name)
    name: str  # what is running: "read", "edges", "optimise", "bench accuracy", ...
    done: int
    total: int | None
    unit: str
    elapsed_s: float
    info: str = ""  # the latest detail, e.g. "stage 1, error 27.8"
    event: str = "update"  # "start", "update" or "end"

    def describe(self) -> str:
        """One line: ``edges: 12/30 blocks (40 %), 1.2 s; info`` or ``write: done in 0.4 s``."""
        unit = f" {self.unit}" if self.unit else ""
        if self.total:
            count = f" {self.done:,}/{self.total:,}{unit} ({100.0 * self.done / self.total:.0f} %)"
        else:
            count = f" {self.done:,}{unit}" if self.done else ""  # a stage without a count
        when = f" done in {self.elapsed_s:.1f} s" if self.event == "end" else f", {self.elapsed_s:.1f} s"
        return f"{self.name}:{count}{when}" + (f"; {self.info}" if self.info else "")


class Task:
    """A stage of work in progress; starts when made, ends at ``end()`` or when its ``with`` exits."""

    def __init__(self, name: str, total: int | None = None, unit: str = "", info: str = "") -> None:
        self.name, self.total, self.unit = name, total, unit
        self.done = 0
        self.info = info  # the first detail, shown from the start
        self._id = next(_ids)
        self._t0 = time.perf_counter()
        self._last = self._t0
        self._ended = False
        self._emit("start")

    def advance(self, n: int = 1, info: str | None = None) -> None:
        """``n`` more units done; ``info`` replaces the detail shown beside the count."""
        self.done += n
        if info is not None:
            self.info = info
        now = time.perf_counter()
        if now - self._last >= MIN_INTERVAL_S:
            self._last = now
            self._emit("update")

    def end(self, info: str | None = None) -> None:
        """The task is over (idempotent)."""
        if self._ended:
            return
        self._ended = True
        if info is not None:
            self.info = info
        self._emit("end")

    def __enter__(self) -> "Task":
        return self

    def __exit__(self, exc_type: type[BaseException] | None, *_: object) -> None:
        # a loop left early (GeneratorExit from ``progress_over``) is not a failure
        failed = exc_type is not None and not issubclass(exc_type, GeneratorExit)
        self.end("failed" if failed else None)

    def _emit(self, event: str) -> None:
        if _log.isEnabledFor(logging.INFO):
            tick = Tick(
                self._id, self.name, self.done, self.total, self.unit, time.perf_counter() - self._t0, self.info, event
            )
            _log.info("%s", tick.describe(), extra={"tick": tick})


def progress_over(items: Iterable[T], name: str, *, total: int | None = None, unit: str = "it") -> Iterator[T]:
    """Yield ``items`` as a ``Task`` named ``name``: one unit done per item."""
    if total is None and hasattr(items, "__len__"):
        total = len(items)  # type: ignore[arg-type]
    with Task(name, total, unit) as task:
        for item in items:
            yield item
            task.advance()
