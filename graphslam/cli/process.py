"""The console process's start and end: numpy's unused submodules deferred, and an exit that skips
tearing down every module."""

from __future__ import annotations

import sys

# numpy submodules that numpy itself loads on first use and no survey uses (numpy.ma is not among
# them: pyarrow loads it anyway, so deferring it would only move its import into a request thread).
_DEFERRED_NUMPY_MODULES = ("numpy.f2py", "numpy.ctypeslib", "numpy.polynomial", "numpy.testing")


class _LazyNumpyExtras:
    """A ``sys.meta_path`` finder: the deferred numpy submodules, found as usual (``PathFinder``) but
    loaded through the standard library's ``importlib.util.LazyLoader``, i.e. executed on first
    attribute access."""

    @staticmethod
    def find_spec(name: str, path: object = None, target: object = None) -> object:
        if name not in _DEFERRED_NUMPY_MODULES:
            return None
        import importlib.machinery
        import importlib.util

        spec = importlib.machinery.PathFinder.find_spec(name, path)  # type: ignore[arg-type]
        if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
            return None  # the usual import, then
        spec.loader = importlib.util.LazyLoader(spec.loader)
        return spec


def _defer_numpy_extras() -> None:
    """scipy's array-API layer (``scipy._lib.array_api_compat.numpy``, imported with scipy.sparse)
    clones numpy's namespace: ``hasattr(numpy, n)`` for every name of ``dir(numpy)``, which lists the
    submodules numpy keeps lazy, so it imports them all — f2py (and, through it, charset_normalizer),
    ctypeslib, polynomial, testing: a fifth of a survey's start-up. No scipy setting avoids it
    (``SCIPY_ARRAY_API`` does not). A finder put first on ``sys.meta_path`` loads them lazily instead:
    executed on first attribute access, which no survey makes. numpy itself is not imported here
    (``--help`` and argument errors need none of it). Console process only (library users and tests
    are untouched), and only for modules not yet imported."""
    if not any(isinstance(f, _LazyNumpyExtras) for f in sys.meta_path):
        sys.meta_path.insert(0, _LazyNumpyExtras())


def _exit_now(code: object) -> None:
    """Exit as the interpreter would — non-daemon threads joined, exit handlers run (logging,
    multiprocessing, temporary folders, Rerun), stdout and stderr flushed — but without tearing
    down every module (numpy, scipy, GTSAM, pyarrow, ...), a tenth of a small survey's time.
    Under a profiler or tracer (cProfile, coverage) the normal exit,
    so that they write their results."""
    status = 0 if code is None else code if isinstance(code, int) else 1
    if not isinstance(code, (int, type(None))):
        print(code, file=sys.stderr)  # sys.exit("message"), as the interpreter prints it
    if sys.getprofile() is not None or sys.gettrace() is not None:
        sys.exit(status)
    import atexit
    import os
    import threading

    for t in threading.enumerate():
        if t is not threading.main_thread() and not t.daemon:
            t.join()
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe (`| head`) or stream: nothing more to say
            pass
    os._exit(status & 0xFF)
