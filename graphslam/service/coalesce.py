"""Concurrent small requests answered by one search (on the event loop).

Why: a kNN search has a fixed cost per call (encoding, top-k, aggregation: most of one query's
~0.5 ms on a 2,000-fingerprint map) that a batch shares: 8 queries in one call cost less than 8
calls (~2-6x one query since ``knn``'s few-query path, docs/radio_map.md). With several clients sending single fingerprints, the
requests that reach the handler in the same event-loop pass are located together: the
first schedules a flush for the next pass (``call_soon``), the others join it. A lone
client's request waits one loop pass (~10 us); nothing waits for a timer.

Each request gets its own rows back (``KnnResult.rows``-like slicing), so a query that
cannot be located fails only its own request (422). Rows agree with a search of the
request alone up to floating-point summation order (~1e-13 m).
"""

from __future__ import annotations

import asyncio
from typing import Callable, Mapping, Sequence

from graphslam.core.radiomap.knn import KnnResult

Scan = Mapping[str, float]
# One flush locates at most this many rows (pending requests beyond it go in the next pass):
# bounds how long the event loop is held.
MAX_FLUSH_ROWS = 64
_ROW_FIELDS = ("xy", "score", "spread", "neighbours", "distances", "n_known_aps", "floor", "building", "rss_diff_db")


def result_rows(res: KnnResult, lo: int, hi: int) -> KnnResult:
    """Rows ``lo:hi`` of ``res`` as a result of their own."""
    cols = {f: (None if getattr(res, f) is None else getattr(res, f)[lo:hi]) for f in _ROW_FIELDS}
    return KnnResult(**cols, config=res.config)  # type: ignore[arg-type]


class Coalescer:
    """``await locate(scans)``: ``search(all pending scans)`` once per event-loop pass.

    ``search`` must not raise for an unlocatable query (``strict=False``): each caller checks
    its own rows. Any other exception of ``search`` is raised to every request of that flush."""

    def __init__(self, search: Callable[[list[Scan]], KnnResult], max_rows: int = MAX_FLUSH_ROWS) -> None:
        self.search = search
        self.max_rows = max(1, max_rows)
        self._pending: list[tuple[Sequence[Scan], asyncio.Future[KnnResult]]] = []
        self._scheduled = False

    async def locate(self, scans: Sequence[Scan]) -> KnnResult:
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[KnnResult] = loop.create_future()
        self._pending.append((scans, fut))
        if not self._scheduled:
            self._scheduled = True
            loop.call_soon(self._flush, loop)
        return await fut

    def _flush(self, loop: asyncio.AbstractEventLoop) -> None:
        take, rows = 0, 0
        while take < len(self._pending) and (take == 0 or rows + len(self._pending[take][0]) <= self.max_rows):
            rows += len(self._pending[take][0])
            take += 1
        batch, self._pending = self._pending[:take], self._pending[take:]
        self._scheduled = bool(self._pending)
        if self._scheduled:
            loop.call_soon(self._flush, loop)
        batch = [(s, f) for s, f in batch if not f.cancelled()]  # (a client that went away)
        if not batch:
            return
        scans = [scan for s, _ in batch for scan in s]
        try:
            res = self.search(scans)
        except Exception as e:  # noqa: BLE001 - handed to every waiting request, as its own error
            for _, f in batch:
                f.set_exception(e)
            return
        lo = 0
        for s, f in batch:
            f.set_result(res if len(batch) == 1 else result_rows(res, lo, lo + len(s)))
            lo += len(s)
