"""Every command of the README runs as written, in order, in a fresh folder (as a new user would
from a fresh clone): its ``bash`` blocks command by command (``[...]``: optional, left out;
``# ...``: a comment), then its ``python`` block. Skipped, with the reason: what needs the real
data in ``../shared/data`` (none today: those are in the prose), and the set-up block, which CI
runs itself (``.ci/run``: ``pip install ".[test]"``, then this very test suite). ``serve`` runs
until it answers ``/healthz`` on a free port, then is stopped. Afterwards nothing the commands
wrote is left untracked by git, given the repository's ``.gitignore``.

One test per command, in the README's order (they share the folder): a failing command names
itself."""

from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
SETUP = ('pip install ".[test]"', "python -m pytest -q")  # the set-up block: CI runs it (.ci/run)


def _blocks(text: str) -> list[tuple[str, str]]:
    """(language, code) of every fenced block."""
    return [(m.group(1), m.group(2)) for m in re.finditer(r"^```(\w*)\n(.*?)^```", text, re.S | re.M)]


def _command(line: str) -> str:
    """A README command line as bash runs it: the comment and the optional ``[--option ...]`` parts
    left out (``".[test]"`` is no option)."""
    line = re.sub(r"\s+#\s.*$", "", line)  # a trailing comment (commands hold no ' # ')
    return re.sub(r"\s+\[-[^\[\]]*\]", "", line).strip()


def readme_commands() -> list[tuple[str, str]]:
    """(kind, command) in the README's order: kind is ``bash`` or ``python`` (a whole block)."""
    out = []
    for lang, code in _blocks(README.read_text(encoding="utf-8")):
        if lang == "bash":
            out += [("bash", _command(ln)) for ln in code.replace("\\\n", " ").splitlines() if _command(ln)]
        elif lang == "python":
            out.append(("python", code))
    return out


COMMANDS = readme_commands()


def _skip_reason(kind: str, cmd: str) -> str | None:
    if "../shared/data" in cmd:
        return f"needs the real data in ../shared/data: {cmd}"
    if kind == "bash" and cmd in SETUP:
        return f"the set-up command, which CI itself runs (.ci/run): {cmd}"
    return None


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The user's folder: a git work tree with the repository's .gitignore (nothing else)."""
    d = tmp_path_factory.mktemp("readme")
    shutil.copy(REPO / ".gitignore", d / ".gitignore")
    (d / "bin").mkdir()
    # `graphslam` and `python` are this interpreter's (the installed package, or PYTHONPATH's)
    for name, run in (("graphslam", f'"{sys.executable}" -m graphslam'), ("python", f'"{sys.executable}"')):
        script = d / "bin" / name
        script.write_text(f'#!/bin/sh\nexec {run} "$@"\n')
        script.chmod(0o755)
    with open(d / ".gitignore", "a") as fh:
        fh.write("/bin/\n")  # the test's own shims
    return d


def _env(folder: Path) -> dict[str, str]:
    return {**os.environ, "PATH": f"{folder / 'bin'}{os.pathsep}{os.environ['PATH']}",
            "XDG_CACHE_HOME": str(folder.parent / f"{folder.name}-cache")}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _serve(cmd: str, folder: Path) -> None:
    """A `graphslam serve ...` line: up until /healthz answers (on a free port), then stopped."""
    port = _free_port()
    proc = subprocess.Popen(["bash", "-c", f"exec {cmd} --port {port} --log-level warning"], cwd=folder, env=_env(folder),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while True:
            assert proc.poll() is None, f"{cmd}: exited {proc.returncode}: {proc.communicate()[1][-2000:]}"
            try:
                if httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            assert time.monotonic() < deadline, f"{cmd}: no answer on /healthz"
            time.sleep(0.2)
    finally:
        proc.send_signal(signal.SIGINT)  # Ctrl-C, as the README says
        try:
            proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()


@pytest.mark.parametrize("kind, cmd", COMMANDS, ids=[f"{i:02d}" for i in range(len(COMMANDS))])
def test_readme_command_runs_as_written(folder: Path, kind: str, cmd: str) -> None:
    reason = _skip_reason(kind, cmd)
    if reason:
        pytest.skip(reason)
    if kind == "bash" and re.match(r"graphslam serve\b", cmd):
        _serve(cmd, folder)
        return
    argv = ["bash", "-eo", "pipefail", "-c", cmd] if kind == "bash" else [sys.executable, "-c", cmd]
    p = subprocess.run(argv, cwd=folder, env=_env(folder), capture_output=True, text=True, timeout=900)
    assert p.returncode == 0, f"{cmd}\nexit {p.returncode}\n{p.stderr[-3000:]}"
    assert "Traceback" not in p.stderr, p.stderr[-3000:]


def test_the_readme_has_what_a_new_user_runs() -> None:
    cmds = [c for k, c in COMMANDS if k == "bash"]
    assert any(c.startswith("graphslam demo") for c in cmds) and any(c.startswith("graphslam track-uwb") or
                                                                     "&& graphslam track-uwb" in c for c in cmds)
    # the UWB tracker runs on the scenario it can start on; the crowd's anchors are for the survey
    uwb = [c for c in cmds if "track-uwb" in c]
    assert uwb and all("zones" in c for c in uwb)
    assert _command("graphslam plot out/x [--a b] [-r c] [--e]   # note") == "graphslam plot out/x"
    assert _command('pip install ".[test]"') == 'pip install ".[test]"'


def test_nothing_the_commands_wrote_is_left_untracked(folder: Path) -> None:
    """Run last (file order): with the repository's .gitignore, git sees nothing new but .gitignore."""
    if shutil.which("git") is None:
        pytest.skip("git is not installed")
    if not (folder / "out" / "paper" / "report.json").exists():
        pytest.skip("runs after the README's commands (the whole file)")
    env = {**os.environ, "GIT_CONFIG_GLOBAL": os.devnull, "GIT_CONFIG_NOSYSTEM": "1"}
    subprocess.run(["git", "init", "-q"], cwd=folder, check=True, env=env)
    p = subprocess.run(["git", "status", "--porcelain", "--untracked-files=all"], cwd=folder, capture_output=True,
                       text=True, check=True, env=env)
    assert p.stdout.splitlines() == ["?? .gitignore"], p.stdout[:2000]
