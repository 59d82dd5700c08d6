#!/usr/bin/env python3
"""What a `graphslam` command's start-up cannot go below with its chosen libraries: CPU time
(user + sys, the child's own, ``os.wait4``) of the interpreter alone, typer and pydantic imported,
a minimal typer app with one option (run and ``--help``), graphslam's configuration module, and
the real commands, medians of ``--runs`` fresh processes each (installed graphslam).

    python lab/speed/startup_floor.py [--runs 9]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile

MINIMAL = "import typer\napp = typer.Typer()\n@app.command()\ndef f(x: str = typer.Option('a')): pass\n" \
          "@app.command()\ndef g(): pass\napp()"


def cpu(cmd: list[str], env: dict[str, str] | None = None) -> float:
    p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env, cwd=tempfile.gettempdir())
    _, _, ru = os.wait4(p.pid, 0)
    return ru.ru_utime + ru.ru_stime


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=9)
    a = ap.parse_args()
    py = sys.executable
    missing = os.path.join(tempfile.gettempdir(), "graphslam-startup-floor-missing")
    rows = {
        "python -c pass": [py, "-c", "pass"],
        "import typer": [py, "-c", "import typer"],
        "import typer, pydantic": [py, "-c", "import typer, pydantic"],
        "minimal typer app, one option, run": [py, "-c", MINIMAL, "f", "--x", "b"],
        "minimal typer app, one option, --help": [py, "-c", MINIMAL, "f", "--help"],
        "import graphslam.config (pydantic models)": [py, "-c", "import graphslam.config"],
        "graphslam --help": [py, "-m", "graphslam", "--help"],
        "graphslam survey --help": [py, "-m", "graphslam", "survey", "--help"],
        "graphslam survey MISSING -o OUT (exit 2)": [py, "-m", "graphslam", "survey", missing, "-o", missing + "-out"],
    }
    print(f"| command | CPU, median of {a.runs} |\n|---|---|")
    for name, cmd in rows.items():
        print(f"| `{name}` | {statistics.median(cpu(cmd) for _ in range(a.runs)):.3f} s |", flush=True)
    print(f"\nload average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
