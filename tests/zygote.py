"""A process that has imported graphslam once and forks one `graphslam` command per request, for
the kill tests (issue 42): a command starts at once (no 1-3 s of imports per kill), and the fork
is killed, with every process it started (its own session), at a chosen moment.

Run as a script by ``Zygote`` (never imported by pytest's process: forking a process with
threads is unsafe). Protocol: one JSON request per stdin line ``{"argv": [...], "env": {...},
"kill_after": seconds or null}``, one JSON answer per stdout line ``{"killed": bool, "code":
exit code or null, "elapsed": seconds}``: ``killed`` when the command was still running at
``kill_after`` and was SIGKILLed (its whole process group).
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any


def _child(req: dict) -> None:
    os.setsid()  # its own process group: a kill takes the Dask cluster it starts too
    os.environ.update(req.get("env") or {})
    if req.get("cwd"):
        os.chdir(req["cwd"])
    fd = os.open(req.get("log") or os.devnull, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    code = 0
    try:
        from graphslam.cli import main

        main(req["argv"])
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    except BaseException:  # noqa: BLE001 - shown in the log, exit 99
        import traceback

        traceback.print_exc()
        code = 99
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def _gone(pgid: int, timeout: float = 20.0) -> None:
    """Kill what is left of process group ``pgid`` and wait until it is empty (its orphans are this
    process's children, a subreaper: reaped here, whatever init does)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            os.killpg(pgid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            return
        try:
            while os.waitpid(-1, os.WNOHANG)[0]:
                pass
        except ChildProcessError:
            pass
        time.sleep(0.01)


def _subreaper() -> None:
    """Orphans of the commands become this process's children (Linux PR_SET_CHILD_SUBREAPER)."""
    import ctypes

    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(36, 1, 0, 0, 0)


def _serve() -> None:
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    import graphslam.app.batch  # noqa: F401 - what the commands import, imported once
    import graphslam.app.survey  # noqa: F401
    import graphslam.app.update  # noqa: F401
    import graphslam.cli  # noqa: F401
    import graphslam.io.radiomap_io  # noqa: F401

    _subreaper()
    print(json.dumps({"ready": True}), flush=True)
    for line in sys.stdin:
        req = json.loads(line)
        t0 = time.perf_counter()
        pid = os.fork()
        if pid == 0:
            _child(req)
        kill_after = req.get("kill_after")
        killed, status = False, None
        while True:
            done, st = os.waitpid(pid, os.WNOHANG)
            if done:
                status = st
                break
            if kill_after is not None and time.perf_counter() - t0 >= kill_after:
                os.killpg(pid, signal.SIGKILL)
                killed = True
                _, status = os.waitpid(pid, 0)
                break
            time.sleep(0.002)
        elapsed = time.perf_counter() - t0
        _gone(pid)  # the cluster's processes too, killed or not
        code = os.waitstatus_to_exitcode(status)
        print(json.dumps({"killed": killed or code == -signal.SIGKILL, "code": code, "elapsed": elapsed}),
              flush=True)


class Zygote:
    """The zygote as a subprocess of the tests (its environment: this process's, so PYTHONPATH too)."""

    def __init__(self) -> None:
        self.proc = subprocess.Popen([sys.executable, __file__], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     text=True, env=dict(os.environ))
        assert self.proc.stdout is not None
        first = self.proc.stdout.readline()
        if not first:
            raise RuntimeError("the zygote did not start")

    def run(self, argv: list[str], *, kill_after: float | None = None, env: dict[str, str] | None = None,
            log: Path | None = None) -> dict[str, Any]:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(json.dumps({"argv": [str(a) for a in argv], "kill_after": kill_after,
                                          "env": env or {}, "log": str(log) if log else None}) + "\n")
        self.proc.stdin.flush()
        answer = self.proc.stdout.readline()
        if not answer:
            raise RuntimeError("the zygote died")
        return json.loads(answer)

    def close(self) -> None:
        if self.proc.stdin is not None:
            self.proc.stdin.close()
        try:
            self.proc.wait(20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


if __name__ == "__main__":
    _serve()
