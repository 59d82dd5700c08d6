"""Faults other than a kill at a random moment (issue 42): a disk that fills up and a read-only
output (real tmpfs mounts: skipped where mounting is not permitted), a Dask worker killed while
it surveys a floor, a kill between the two renames of the swap used where there is no
``renameat2``."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path
from typing import Iterator

import pytest
from conftest import run_cli

from graphslam.io.mcap_writer import write_session
from graphslam.sim import simulate

BASE = ["--no-progress"]
NEW = ["--set", "wifi.d_max_m=25"]


@pytest.fixture(scope="module")
def sites(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three small floors F0, F1, F2 (5 corridor walks each)."""
    root = tmp_path_factory.mktemp("faults")
    for k in range(3):
        for s in simulate("corridor", seed=k, size=0.5).survey.sessions[:5]:
            write_session(replace(s, heading=None), root / f"F{k}" / f"{s.session_id}.mcap")
    return root


def raw(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def hidden(folder: Path) -> list[str]:
    """Anything staged (a name starting with '.') anywhere under ``folder``."""
    return sorted(str(p.relative_to(folder)) for p in folder.rglob(".*"))


def one_line_exit_2(capsys: pytest.CaptureFixture[str], args: list[object]) -> str:
    capsys.readouterr()
    assert run_cli([str(a) for a in args]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1, lines
    return lines[0]


class Mount:
    """A small tmpfs at ``path`` (unmounted at the end)."""

    def __init__(self, path: Path, size_kb: int) -> None:
        self.path = path
        path.mkdir(parents=True, exist_ok=True)
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size_kb}k,mode=0755", "tmpfs", str(path)],
                              capture_output=True, text=True)
        if done.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here ({done.stderr.strip() or done.returncode}): needs root")

    def read_only(self) -> None:
        subprocess.run(["mount", "-o", "remount,ro", str(self.path)], check=True, capture_output=True)

    def fill(self) -> None:
        """Fill the filesystem to the last block."""
        with open(self.path / "ballast", "wb", buffering=0) as fh:
            try:
                while True:
                    fh.write(b"\0" * 4096)
            except OSError:
                pass

    def umount(self) -> None:
        subprocess.run(["umount", "-l", str(self.path)], capture_output=True)


@pytest.fixture
def mount(tmp_path: Path) -> Iterator[type]:
    made: list[Mount] = []

    def make(path: Path, size_kb: int) -> Mount:
        m = Mount(path, size_kb)
        made.append(m)
        return m

    yield make  # type: ignore[misc]
    for m in made:
        m.umount()


def test_survey_into_a_disk_that_fills_up(
    sites: Path, tmp_path: Path, mount: type, capsys: pytest.CaptureFixture[str]
) -> None:
    """Room for one set and a half: the first survey fits, the second fills the disk while its
    stage is written: one line, exit 2, the first set intact, nothing staged left."""
    ref = tmp_path / "ref"
    assert run_cli(["survey", str(sites / "F0"), "--out", str(ref), *BASE]) == 0
    size = sum(len(b) for b in raw(ref).values())
    disk = mount(tmp_path / "disk", (size * 3 // 2) // 1024 + 16)
    out = disk.path / "out"
    assert run_cli(["survey", str(sites / "F0"), "--out", str(out), *BASE]) == 0
    before = raw(out)
    msg = one_line_exit_2(capsys, ["survey", sites / "F0", "--out", out, *BASE, *NEW])
    assert "No space left on device" in msg and str(out) in msg, msg
    assert raw(out) == before and hidden(disk.path) == []
    # disk full from the start: the same
    disk.fill()
    msg = one_line_exit_2(capsys, ["survey", sites / "F0", "--out", out, *BASE, *NEW])
    assert "No space left on device" in msg
    assert raw(out) == before and hidden(disk.path) == []


def test_survey_and_batch_into_a_read_only_folder(
    sites: Path, tmp_path: Path, mount: type, capsys: pytest.CaptureFixture[str]
) -> None:
    disk = mount(tmp_path / "disk", 8192)
    out = disk.path / "out"
    assert run_cli(["survey", str(sites / "F0"), "--out", str(out), *BASE]) == 0
    before = raw(out)
    disk.read_only()
    msg = one_line_exit_2(capsys, ["survey", sites / "F0", "--out", out, *BASE, *NEW])
    assert "cannot write" in msg and str(out) in msg, msg
    assert raw(out) == before
    # survey-batch: refused before a cluster is started
    msg = one_line_exit_2(capsys, ["survey-batch", sites, "--out", disk.path / "outs", "--workers", "1", *BASE])
    assert "cannot write" in msg, msg
    assert sorted(p.name for p in disk.path.iterdir()) == ["out"] and raw(out) == before


def test_batch_into_a_full_disk_keeps_the_previous_outputs(
    sites: Path, tmp_path: Path, mount: type, capsys: pytest.CaptureFixture[str]
) -> None:
    """The floors fail to write (their previous sets stay), then so does summary.json: one line,
    exit 2, the previous summary and floors intact, nothing staged left."""
    two = tmp_path / "two"
    for f in ("F0", "F1"):
        (two / f).mkdir(parents=True)
        for m in (sites / f).glob("*.mcap"):
            os.link(m, two / f / m.name)
    disk = mount(tmp_path / "disk", 16384)
    outs = disk.path / "outs"
    assert run_cli(["survey-batch", str(two), "--out", str(outs), "--workers", "1", *BASE]) == 0
    before = raw(outs)
    disk.fill()
    msg = one_line_exit_2(capsys, ["survey-batch", two, "--out", outs, "--workers", "1", *BASE, *NEW])
    assert "summary.json" in msg and "No space left on device" in msg, msg
    assert raw(outs) == before and hidden(outs) == []


def test_a_floor_whose_worker_is_killed_is_retried_and_fails_alone_when_it_always_is(
    sites: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A real local cluster. F0's worker is killed on its first try only: F0 is surveyed again
    and is ok. F1's is killed on every try: after the allowed retries F1 is a failed row naming
    the cause. F2 is untouched and ok. summary.json lists all three."""
    import dask

    from graphslam.app.batch import run_batch

    counts = tmp_path / "tries"
    counts.mkdir()
    monkeypatch.setenv("GRAPHSLAM_TEST_KILL_AT", "floor:F0@1,floor:F1")
    monkeypatch.setenv("GRAPHSLAM_TEST_KILL_DIR", str(counts))
    out = tmp_path / "outs"
    with dask.config.set({"distributed.scheduler.allowed-failures": 1}):
        res = run_batch(sites, out, workers=2)
    rows = {r["floor"]: r for r in json.loads((out / "summary.json").read_text())}
    assert rows["F0"]["status"] == "ok" and rows["F2"]["status"] == "ok", rows
    assert sorted(p.name for p in counts.iterdir()) == ["floor_F0.0"]  # F0 was killed once, then ran
    assert rows["F1"]["status"] == "failed" and rows["F1"]["error"].startswith(
        "worker lost after retries: the process surveying this floor died on each of 2 tries"), rows["F1"]
    assert res.failed == 1 and (out / "F0" / "report.json").is_file() and not (out / "F1").exists()
    assert hidden(out) == []


def test_killed_between_the_two_renames_the_next_run_puts_the_previous_set_back(
    sites: Path, tmp_path: Path
) -> None:
    """Where there is no renameat2 (GRAPHSLAM_NO_EXCHANGE here), the swap is two renames; a run
    killed between them leaves --out missing and the previous set beside it: the next run, an
    --update of that very folder, finds it back in place first."""
    parent = tmp_path / "o"
    out = parent / "out"
    assert run_cli(["survey", str(sites / "F0"), "--out", str(out), *BASE]) == 0
    before = raw(out)
    env = dict(os.environ, GRAPHSLAM_NO_EXCHANGE="1", GRAPHSLAM_TEST_KILL_AT="publish.aside")
    done = subprocess.run([sys.executable, "-m", "graphslam", "survey", str(sites / "F0"), "--out", str(out),
                           *BASE, *NEW], env=env, capture_output=True)
    assert done.returncode == -9, done.stderr[-2000:]
    assert not out.exists() and [p for p in parent.iterdir() if p.name.startswith(".out.old-")]
    assert run_cli(["survey", str(sites / "F0"), "--update", str(out), "--out", str(out), *BASE]) == 0
    assert json.loads((out / "report.json").read_text())["update"]["mode"] == "incremental"
    assert sorted(p.name for p in parent.iterdir()) == ["out"] and set(raw(out)) == set(before)


def test_killed_before_its_lock_file_is_marked_the_next_run_removes_it(sites: Path, tmp_path: Path) -> None:
    """A run killed between creating its stage's lock file and writing our marker into it leaves an
    empty lock file and nothing else: the next run into that folder removes it (and an empty lock
    file beside a stage folder, which is not how we leave them, is left alone)."""
    parent = tmp_path / "o"
    out = parent / "out"
    env = dict(os.environ, GRAPHSLAM_TEST_KILL_AT="stage.unmarked")
    done = subprocess.run([sys.executable, "-m", "graphslam", "survey", str(sites / "F0"), "--out", str(out), *BASE],
                          env=env, capture_output=True)
    assert done.returncode == -9, done.stderr[-2000:]
    left = [p for p in parent.iterdir()]
    assert len(left) == 1 and left[0].name.startswith(".out.stage-") and left[0].stat().st_size == 0
    (parent / ".out.stage-foreign").mkdir()
    (parent / ".out.stage-foreign.lock").write_bytes(b"")
    assert run_cli(["survey", str(sites / "F0"), "--out", str(out), *BASE]) == 0
    assert sorted(p.name for p in parent.iterdir()) == [".out.stage-foreign", ".out.stage-foreign.lock", "out"]
