"""Progress (graphslam.core.progress + graphslam.app.progress): what a real `graphslam` process shows
on a terminal (a pseudo-terminal) and in a batch job's log (a pipe), and that --quiet silences both."""

from __future__ import annotations

import io
import logging
import os
import pty
import re
import subprocess
import sys
from pathlib import Path
from typing import Iterator

import pytest

from graphslam.app.progress import show_progress
from graphslam.core.progress import PROGRESS_LOGGER, Task, Tick, progress_over
from graphslam.errors import ConfigError
from graphslam.sim import simulate

SURVEY_STAGES = ("read", "associate", "edges", "initialise", "build graph", "optimise", "write", "picture")


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("progress") / "rec"
    simulate("corridor", seed=1).write(d)
    return d


def _run(args: list[str], python_flags: tuple[str, ...] | list[str] = ()) -> subprocess.CompletedProcess:
    env = {**os.environ, "RERUN": "off"}
    return subprocess.run([sys.executable, *python_flags, "-m", "graphslam", *args], capture_output=True, text=True,
                          env=env, timeout=300)


def test_batch_log_has_a_line_per_stage(recordings: Path, tmp_path: Path) -> None:
    # stderr is a pipe: periodic log lines; interval 0 = every report (the default 10 s is for nightly jobs)
    p = _run(["--progress-interval", "0", "survey", str(recordings), "--out", str(tmp_path / "out")],
             python_flags=["-X", "importtime"])
    assert p.returncode == 0, p.stderr
    assert "matplotlib" not in p.stderr  # survey.png is drawn without matplotlib's ~0.4 s import
    lines = [ln for ln in p.stderr.splitlines() if " progress " in ln]
    done = {m.group(1) for ln in lines if (m := re.search(r" progress (.+?):.* done in [0-9.]+ s", ln))}
    assert set(SURVEY_STAGES) <= done
    assert re.search(r"progress read: 12/12 files \(100 %\) done in", p.stderr)
    assert re.search(r"progress optimise: \d+ iterations done in .*; stage \d+, error", p.stderr)
    assert "\r" not in p.stderr  # no bar drawing into a log file
    assert re.match(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d", lines[0])  # timestamped, for a nightly log


@pytest.mark.parametrize("args", [["inspect"], ["-q", "inspect"], ["inspect", "--quiet"], ["survey", "--no-progress"]])
def test_quiet_silences_progress(recordings: Path, tmp_path: Path, args: list[str]) -> None:
    out = ["--out", str(tmp_path / "out")] if "survey" in args else []
    p = _run(["--progress-interval", "0", *args, str(recordings), *out])
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip()  # the result itself is still printed
    if args == ["inspect"]:  # the control: without --quiet the same command reports
        assert "progress read: 12/12 files (100 %) done in" in p.stderr
    else:
        assert "progress" not in p.stderr and "\r" not in p.stderr


@pytest.mark.parametrize("after", [["--progress-interval", "0"], ["--progress-interval=0"]])
def test_progress_interval_is_accepted_after_the_command_name(recordings: Path, after: list[str]) -> None:
    p = _run(["inspect", str(recordings), *after])  # as -q is: a root option users put after the command
    assert p.returncode == 0, p.stderr
    assert "progress read: 12/12 files (100 %) done in" in p.stderr


def test_terminal_shows_tqdm_bars(recordings: Path, tmp_path: Path) -> None:
    import fcntl
    import struct
    import termios

    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 30, 120, 0, 0))  # a 120-column terminal
    env = {**os.environ, "RERUN": "off"}
    proc = subprocess.Popen([sys.executable, "-m", "graphslam", "survey", str(recordings), "--out", str(tmp_path / "o")],
                            stdin=slave, stdout=subprocess.DEVNULL, stderr=slave, env=env)
    os.close(slave)
    chunks = []
    while True:
        try:
            data = os.read(master, 65536)
        except OSError:  # EIO: the child closed the terminal
            break
        if not data:
            break
        chunks.append(data)
    assert proc.wait(timeout=300) == 0
    os.close(master)
    out = b"".join(chunks).decode(errors="replace")
    assert "\r" in out  # bars redraw in place
    assert re.search(r"read: +\d+%\|", out) and re.search(r"edges: +\d+%\|", out)
    assert re.search(r"optimise: \d+ iterations", out)
    assert " progress " not in out  # no log lines on a terminal


def test_tasks_report_only_when_someone_listens() -> None:
    records: list[Tick] = []

    class Grab(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            records.append(record.tick)  # type: ignore[attr-defined]

    log = logging.getLogger(PROGRESS_LOGGER)
    h = Grab()
    with Task("nobody", total=3):  # not enabled: no record is even made
        pass
    log.addHandler(h)
    log.setLevel(logging.INFO)
    try:
        for _ in progress_over(range(1000), "loop", unit="items"):
            pass
        with pytest.raises(RuntimeError), Task("fails", unit="files") as t:
            t.advance(2)
            raise RuntimeError("boom")
    finally:
        log.removeHandler(h)
        log.setLevel(logging.NOTSET)
    loop = [r for r in records if r.name == "loop"]
    assert [loop[0].event, loop[-1].event] == ["start", "end"]
    assert len(loop) < 10  # a fast loop of 1,000 items is throttled to a few reports
    assert (loop[-1].done, loop[-1].total) == (1000, 1000)
    assert loop[-1].describe().startswith("loop: 1,000/1,000 items (100 %) done in ")
    fails = [r for r in records if r.name == "fails"]
    assert fails[-1].event == "end" and fails[-1].info == "failed" and fails[-1].done == 2
    assert not [r for r in records if r.name == "nobody"]


def test_line_handler_throttles_to_its_interval_and_skips_quick_stages() -> None:
    buf = io.StringIO()
    assert show_progress("auto", interval_s=3600.0, stream=buf) == "log"  # a StringIO is no terminal
    try:
        with Task("quick", total=2) as t:
            t.advance(2)
        task = Task("slow", total=5)
        task._t0 -= 7200.0  # an hour-long stage: its end line is written
        task.end()
    finally:
        show_progress("off")
    text = buf.getvalue()
    assert "quick" not in text  # under a second: no line
    assert re.search(r"progress slow: 0/5 \(0 %\) done in 7200\.0 s", text)
    with pytest.raises(ConfigError):
        show_progress("sometimes")


def test_a_tasks_last_count_is_one_line_its_done_line(monkeypatch: pytest.MonkeyPatch) -> None:
    """The update that completes a task's count and its end come together (the self-calibration's
    replay: its last segment, then done): the log shows the count once, in the "done" line."""
    import graphslam.core.progress as core_progress

    monkeypatch.setattr(core_progress, "MIN_INTERVAL_S", 0.0)  # every advance reports
    buf = io.StringIO()
    show_progress("log", interval_s=0.0, stream=buf)
    try:
        with Task("track: self-calibration replay", total=3, unit="segments") as task:
            for _ in range(3):
                task.advance()
    finally:
        show_progress("off")
    lines = [ln.split(" progress ", 1)[1] for ln in buf.getvalue().splitlines()]
    assert [ln.split(",")[0].split(" done")[0] for ln in lines] == [
        "track: self-calibration replay: 1/3 segments (33 %)", "track: self-calibration replay: 2/3 segments (67 %)",
        "track: self-calibration replay: 3/3 segments (100 %)"]
    assert "done in" in lines[-1] and sum("3/3" in ln for ln in lines) == 1


class _Grab(logging.Handler):
    """Every tick of every task, while installed (``_grabbing``)."""

    def __init__(self) -> None:
        super().__init__()
        self.ticks: list[Tick] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.ticks.append(record.tick)  # type: ignore[attr-defined]

    def ended(self) -> set[str]:
        started = {t.task_id for t in self.ticks if t.event == "start"}
        return {t.name for t in self.ticks if t.event == "end" and t.task_id in started}


@pytest.fixture
def grab() -> Iterator[_Grab]:
    log = logging.getLogger(PROGRESS_LOGGER)
    h = _Grab()
    log.addHandler(h)
    log.setLevel(logging.INFO)
    try:
        yield h
    finally:
        log.removeHandler(h)
        log.setLevel(logging.NOTSET)


# What ran >= 1 s at `paper --size 12` (2026-12-03, 2 busy cores): simulate 7.9 s, write 8.5 s; survey:
# read 4.5 s, edges (the IVF index: 100k steps) 5.5 s, initialise 25.8 s (of which place walks 13.2 s),
# optimise 87 s, write 3.4 s. The tests below check, on small inputs, that every stage a survey times
# (report.json's timings_s: what could run long on a big floor) reports, with either edge search.
@pytest.mark.parametrize("candidates", ["exact", "ivf"])
def test_every_timed_survey_stage_reports_progress(recordings: Path, tmp_path: Path, grab: _Grab, candidates: str) -> None:
    from graphslam.app.survey import run_survey
    from graphslam.app.survey_inputs import SurveyInputs
    from graphslam.config import load_config

    cfg = load_config(None, {"edges": {"candidates": candidates}})
    result = run_survey(SurveyInputs((recordings,), tmp_path / "out"), cfg)
    stages = {k.removeprefix("align.").replace("_", " ") for k in result.report["timings_s"]} - {"total"}
    assert {"read", "edges", "initialise", "optimise", "write", "evaluate"} <= stages
    assert stages <= grab.ended(), stages - grab.ended()
    edges = [t for t in grab.ticks if t.name == "edges"]
    assert edges[-1].done == edges[-1].total == result.report["fingerprints"]
    if candidates == "ivf":  # the IVF stage was silent: its index build and its search now report
        assert {"IVF index", "IVF search"} <= {t.info for t in edges}


def test_simulators_report_progress(tmp_path: Path, grab: _Grab) -> None:
    from graphslam.sim.uwb.scenarios import CrowdUwb, simulate_crowd

    simulate("paper", seed=0).write(tmp_path / "paper")
    assert {"simulate", "write"} <= grab.ended()
    crowd = simulate_crowd(0, CrowdUwb(n_walkers=2, duration_min=(0.5, 0.6)))  # `simulate-uwb crowd`: 38 s, was silent
    net = [t for t in grab.ticks if t.name == "simulate UWB network"]
    assert net[0].event == "start" and net[-1].event == "end" and net[-1].unit == "cycles"
    assert net[-1].done == len(crowd.network.cycles) and net[-1].total == pytest.approx(net[-1].done, abs=2)
    assert net[-1].info == f"{len(crowd.network.ranges.t_s):,} ranges"
