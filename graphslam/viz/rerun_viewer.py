"""The Rerun viewer for a written .rrd file (``graphslam view --serve / --spawn``): the viewer binary
that ships inside rerun-sdk, run as a subprocess. Logging is ``graphslam.viz.rerun_log``."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import quote

from graphslam.errors import InputError, VisualizationError


@dataclass
class ViewerServer:
    """A Rerun web viewer serving one .rrd file on the loopback interface."""

    url: str
    path: Path
    process: subprocess.Popen[bytes]

    def wait(self) -> int:
        """Block until the server stops (Ctrl-C stops it)."""
        try:
            return self.process.wait()
        except KeyboardInterrupt:
            self.stop()
            raise

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()


def _rerun_cli() -> list[str]:
    # the viewer binary ships inside rerun-sdk; `python -m rerun` finds it whatever PATH is
    return [sys.executable, "-m", "rerun"]


def serve_rrd(path: str | Path, *, web_port: int = 9090, grpc_port: int = 9876, bind: str = "127.0.0.1") -> ViewerServer:
    """Serve ``path`` in Rerun's web viewer on ``bind`` (loopback by default); returns at once."""
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "no such .rrd file")
    cmd = _rerun_cli() + [str(p), "--web-viewer", "--bind", bind, "--web-viewer-port", str(web_port),
                          "--port", str(grpc_port)]
    env = dict(os.environ, BROWSER="true")  # never try to open a browser from a server
    proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, env=env)  # noqa: S603 (fixed argv)
    time.sleep(1.0)
    if proc.poll() is not None:
        raise VisualizationError(f"rerun web viewer exited at once (code {proc.returncode}); ports {web_port}/{grpc_port} busy?")
    data = quote(f"rerun+http://{bind}:{grpc_port}/proxy", safe="")
    return ViewerServer(f"http://{bind}:{web_port}/?url={data}", p, proc)


def require_display() -> None:
    """Raise ``VisualizationError`` where a native viewer cannot show anything (headless Linux)."""
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        # a headless spawn does not fail, it hangs about and shows nothing: say so instead
        raise VisualizationError("no display (DISPLAY/WAYLAND_DISPLAY unset): use --save FILE.rrd or --serve")


def spawn_viewer(path: str | Path) -> None:
    """Open ``path`` in the native Rerun viewer (detached). Needs a display."""
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "no such .rrd file")
    require_display()
    subprocess.Popen(  # noqa: S603 (fixed argv)
        _rerun_cli() + [str(p)],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
