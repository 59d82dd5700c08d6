"""A call whose value is taken later: started now on a thread beside the caller's work (worth it where the
call's work releases the GIL: large numpy products, the blur), or run when its value is asked for."""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, Callable, Generic, TypeVar

from graphslam.errors import GraphSlamError

T = TypeVar("T")


class Deferred(Generic[T]):
    """``fn(*args, **kwargs)``: on a thread started now when ``thread``, else in ``result()``. ``result()``
    gives the value (the call's own exception raised there) and waits for the thread; ``close()`` waits
    for a thread whose value is not taken (the caller failed)."""

    def __init__(self, fn: Callable[..., T], *args: Any, thread: bool = False, name: str | None = None,
                 **kwargs: Any) -> None:
        self._call: tuple[Callable[..., T], tuple, dict] | None = (fn, args, kwargs)
        self._pool: ThreadPoolExecutor | None = None
        self._future: Future | None = None
        if thread:
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix=name or getattr(fn, "__name__", "call"))
            self._future = self._pool.submit(fn, *args, **kwargs)

    @property
    def threaded(self) -> bool:
        """Whether the call runs on its own thread."""
        return self._future is not None

    def result(self) -> T:
        if self._future is not None:
            try:
                return self._future.result()
            finally:
                self.close()
        if self._call is None:
            raise GraphSlamError("the call's value was already taken")
        fn, args, kwargs = self._call
        self._call = None
        return fn(*args, **kwargs)

    def close(self) -> None:
        """Wait for the thread, if any (once)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
