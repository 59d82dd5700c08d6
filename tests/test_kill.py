"""SIGKILL at any moment (issue 42): `survey`, `survey --update` (in place and into a new folder)
and `survey-batch`, each killed at >= 20 seeded moments spread over every stage of a measured
uncontaminated run (stratified: one random moment in each twentieth of it, a little past its
end too), plus the named write points (``graphslam.io.atomic.kill_point``) that no timer hits:
after an output file is complete but before its rename, before the swap, after it, before the
lock file goes.

After every kill the output is the previous set or the new one, whole (every file equal to the
uncontaminated run's, report.json but its timings), never a mix and never missing. Then one
clean run removes what the killed runs left beside it (stages, lock files), and only that: a
folder named like a stage that is not ours and a concurrent run's live stage stay.

Commands run in ``zygote.Zygote``: forked from a process that imported graphslam once, each in
its own process group, killed whole (the batch's Dask processes too).
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path
from typing import Callable, Iterator

import numpy as np
import pytest
from zygote import Zygote

from graphslam.io.mcap_writer import write_session
from graphslam.sim import simulate

MOMENTS = 20
SEED = 42
BASE = ["--no-progress"]
NEW = ["--set", "wifi.d_max_m=25"]  # the new run's set differs from the previous one in every data file
SURVEY_POINTS = [
    "atomic:trajectories.csv", "atomic:survey_state.npz", "atomic:report.json",
    "publish.start", "publish.exchanged", "publish.cleaned",
]
Snapshot = dict[str, object]


@pytest.fixture(scope="module")
def zygote() -> Iterator[Zygote]:
    z = Zygote()
    yield z
    z.close()


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """old/: 5 walks of a corridor floor; all/: the same and a 6th (what --update joins);
    sites/F0, sites/F1: two such floors (survey-batch)."""
    root = tmp_path_factory.mktemp("kill")
    for k in range(2):
        walks = [replace(s, heading=None) for s in simulate("corridor", seed=k, size=0.5).survey]
        for i, s in enumerate(walks):
            write_session(s, root / "sites" / f"F{k}" / f"{s.session_id}.mcap")
            if k == 0:
                write_session(s, root / "all" / f"{s.session_id}.mcap")
                if i < len(walks) - 1:
                    write_session(s, root / "old" / f"{s.session_id}.mcap")
    return root


def _comparable(name: str, data: bytes) -> object:
    if name == "report.json":
        rep = json.loads(data)  # parses
        rep.pop("timings_s", None)
        return rep
    if name == "summary.json":
        return [{k: v for k, v in row.items() if k != "seconds"} for row in json.loads(data)]
    return data


def _files(folder: Path) -> list[Path]:
    """The files of ``folder`` (recursively), not what is staged in it (names starting with '.')."""
    return [p for p in sorted(folder.rglob("*"))
            if p.is_file() and not any(part.startswith(".") for part in p.relative_to(folder).parts)]


def snapshot(folder: Path) -> Snapshot:
    """Every file of ``folder``, comparable: report.json without its timings (and parsed)."""
    return {str(p.relative_to(folder)): _comparable(p.name, p.read_bytes()) for p in _files(folder)}


def raw(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in _files(folder)}


def restore(folder: Path, snap: dict[str, bytes]) -> None:
    """``folder`` as ``snap`` again; what is staged in it (hidden names) stays for the next run."""
    folder.mkdir(parents=True, exist_ok=True)
    for p in folder.iterdir():
        if not p.name.startswith("."):
            shutil.rmtree(p) if p.is_dir() else p.unlink()
    for rel, data in snap.items():
        (folder / rel).parent.mkdir(parents=True, exist_ok=True)
        (folder / rel).write_bytes(data)


def moments(duration: float, n: int = MOMENTS, seed: int = SEED) -> list[float]:
    """One seeded random moment in each n-th of 1.1 x ``duration``: every stage gets some."""
    u = np.random.default_rng(seed).uniform(size=n)
    return [1.1 * duration * (i + u[i]) / n for i in range(n)]


def leftovers(parent: Path, keep: set[str]) -> list[str]:
    return sorted(p.name for p in parent.iterdir() if p.name not in keep)


def kill_series(
    zygote: Zygote, argv: list[str], before: Callable[[], None], check: Callable[[], str], duration: float,
    points: list[str], env: dict[str, str] | None = None,
) -> dict[str, int]:
    """Run ``argv`` killed at each moment and at each named point, ``before()`` first each time;
    ``check()`` says which set is there ("previous" / "new") or fails. Returns the counts."""
    seen = {"previous": 0, "new": 0, "killed": 0}
    runs = [(t, {}) for t in moments(duration)] + [(None, {"GRAPHSLAM_TEST_KILL_AT": p}) for p in points]
    for t, hook in runs:
        before()
        res = zygote.run(argv, kill_after=t, env={**(env or {}), **hook})
        assert res["killed"] or res["code"] == 0, (t, hook, res)
        seen["killed"] += res["killed"]
        seen[check()] += 1
    assert seen["killed"] >= MOMENTS * 0.6, seen  # most moments fall inside the run
    return seen


def which(got: Snapshot, previous: Snapshot, new: Snapshot, what: str) -> str:
    if got == previous:
        return "previous"
    if got == new:
        return "new"
    mixed = sorted(k for k in set(got) | set(previous) | set(new) if got.get(k) not in (previous.get(k), new.get(k)))
    raise AssertionError(f"{what} is neither the previous set nor the new one: {mixed}")


def foreign_and_live(parent: Path, name: str) -> tuple[set[str], subprocess.Popen]:
    """Beside ``parent/name``: a folder named like a stage that is not ours (no lock file), one
    whose lock file is not ours, and a live stage held by another process."""
    (parent / f".{name}.stage-notours").mkdir()
    (parent / f".{name}.stage-notours" / "x").write_text("someone else's")
    (parent / f".{name}.stage-alsonot").mkdir()
    (parent / f".{name}.stage-alsonot.lock").write_text("another program's lock\n")
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys; from graphslam.io.atomic import FolderStage; "
         "from graphslam.app.survey import OWNED_FILES; "
         "s = FolderStage.create(sys.argv[1], OWNED_FILES); print(s.path.name, flush=True); sys.stdin.read()",
         str(parent / name)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert holder.stdout is not None
    live = holder.stdout.readline().strip()
    assert live.startswith(f".{name}.stage-")
    return {f".{name}.stage-notours", f".{name}.stage-alsonot", f".{name}.stage-alsonot.lock", live,
            live + ".lock"}, holder


def end_clean(zygote: Zygote, argv: list[str], parent: Path, name: str, keep: set[str]) -> None:
    """One clean run: nothing of ours is left beside ``parent/name``; what is not ours, and the
    live stage, are; once the live stage's process is killed, the next run removes it too."""
    others, holder = foreign_and_live(parent, name)
    try:
        assert zygote.run(argv)["code"] == 0
        assert leftovers(parent, keep | {name}) == sorted(others)
    finally:
        holder.kill()
        holder.wait()
    assert zygote.run(argv)["code"] == 0
    assert leftovers(parent, keep | {name}) == sorted(others - {o for o in others if "notours" not in o
                                                                and "alsonot" not in o})


def test_survey_killed_at_any_moment(zygote: Zygote, data: Path, tmp_path: Path) -> None:
    parent = tmp_path / "o"
    out = parent / "out"
    argv = ["survey", data / "old", "--out", out, *BASE]
    assert zygote.run(argv)["code"] == 0
    previous_raw = raw(out)
    res = zygote.run(["survey", data / "old", "--out", tmp_path / "new", *BASE, *NEW])
    previous, new = snapshot(out), snapshot(tmp_path / "new")
    # (the recordings cache is the same: the same recordings were read)
    same = {"survey.png", "recordings_cache.npz"}
    assert previous.keys() == new.keys() and all(previous[k] != new[k] for k in previous if k not in same)
    seen = kill_series(zygote, [*argv, *NEW], lambda: restore(out, previous_raw),
                       lambda: which(snapshot(out), previous, new, "--out"), res["elapsed"], SURVEY_POINTS)
    assert seen["previous"] and seen["new"], seen
    end_clean(zygote, argv, parent, "out", set())


@pytest.mark.parametrize("into", ["in place", "a new folder"])
def test_survey_update_killed_at_any_moment(zygote: Zygote, data: Path, tmp_path: Path, into: str) -> None:
    parent = tmp_path / "o"
    prev = parent / "prev"
    assert zygote.run(["survey", data / "old", "--out", prev, *BASE])["code"] == 0
    previous_raw = raw(prev)
    previous = snapshot(prev)
    out = prev if into == "in place" else parent / "new"
    argv = ["survey", data / "all", "--update", prev, "--out", out, *BASE]

    def before() -> None:
        restore(prev, previous_raw)
        if out != prev and out.exists():
            shutil.rmtree(out)

    def check() -> str:
        if out != prev:
            assert raw(prev) == previous_raw  # the folder updated from is never touched
            if not out.exists():
                return "previous"  # nothing published: as before the run
        return which(snapshot(out), previous, new, "--out")

    before()
    res = zygote.run(argv)  # uncontaminated: the new set, and how long it takes
    assert res["code"] == 0
    new = snapshot(out)
    assert new["report.json"]["update"]["new_walks"]  # type: ignore[index]
    seen = kill_series(zygote, argv, before, check, res["elapsed"], SURVEY_POINTS)
    assert seen["previous"] and seen["new"], seen
    before()
    end_clean(zygote, argv, parent, out.name, {"prev"})


def test_survey_batch_killed_at_any_moment(zygote: Zygote, data: Path, tmp_path: Path) -> None:
    """Each floor's folder is its previous set or its new one (never a mix, never missing);
    summary.json is the previous or the new one (equal but for the seconds: the two runs'
    floors have the same counts)."""
    parent = tmp_path / "o"
    out = parent / "outs"
    argv = ["survey-batch", data / "sites", "--out", out, "--workers", "1", *BASE]
    assert zygote.run(argv)["code"] == 0
    previous_raw = raw(out)
    res = zygote.run(["survey-batch", data / "sites", "--out", tmp_path / "new", "--workers", "1", *BASE, *NEW])
    assert res["code"] == 0
    previous, new = snapshot(out), snapshot(tmp_path / "new")
    floors = ("F0", "F1")

    def part(snap: Snapshot, prefix: str) -> Snapshot:
        return {k: v for k, v in snap.items() if k.startswith(prefix + "/")}

    def check() -> str:
        got = snapshot(out)
        sets = [which(part(got, f), part(previous, f), part(new, f), f) for f in floors]
        which({"s": got["summary.json"]}, {"s": previous["summary.json"]}, {"s": new["summary.json"]}, "summary.json")
        return "new" if sets == ["new", "new"] else "previous"

    seen = kill_series(zygote, [*argv, *NEW], lambda: restore(out, previous_raw), check, res["elapsed"],
                       ["atomic:summary.json"])
    assert seen["previous"] and seen["new"], seen
    # one more run: nothing staged is left, neither the floors' stages nor a summary.json temp
    assert zygote.run(argv)["code"] == 0
    assert leftovers(out, {"summary.json", *floors}) == []
    assert not [p for f in floors for p in (out / f).iterdir() if p.name.startswith(".")]
