"""The console process's start and end: numpy's unused submodules deferred, and an exit that skips
tearing down every module."""

from __future__ import annotations

import sys

# numpy submodules that numpy itself loads on first use and no survey uses (numpy.ma is not among
# them: pyarrow loads it anyway, so deferring it would only move its import into a request thread).
_DEFERRED_NUMPY_MODULES = ("numpy.f2py", "numpy.ctypeslib", "numpy.polynomial", "numpy.testing")


def _defer_numpy_extras() -> None:
    """scipy's array-API layer (``scipy._lib.array_api_compat.numpy``, imported with scipy.sparse)
    does ``from numpy import *``, which imports every submodule numpy keeps lazy — f2py (and,
    through it, charset_normalizer), ctypeslib, polynomial, testing: a fifth of a survey's
    start-up. Registered first as lazy modules (the
    standard library's ``importlib.util.LazyLoader``) they are executed on first attribute access
    instead, which no survey makes. Console process only (library users and tests are untouched),
    and only for modules not yet imported."""
    import importlib.util

    import numpy

    for name in _DEFERRED_NUMPY_MODULES:
        if name in sys.modules:
            continue
        spec = importlib.util.find_spec(name)
        if spec is None or spec.loader is None:
            continue
        spec.loader = importlib.util.LazyLoader(spec.loader)
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
        setattr(numpy, name.rpartition(".")[2], module)  # else numpy's __getattr__ imports it again


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
