"""`graphslam survey-batch` on a REAL local Dask cluster (issue 18): floors, failures, summary, exit codes."""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from dataclasses import replace
from pathlib import Path

import pytest
from conftest import run_cli as _run

pytest.importorskip("distributed", reason="the batch extra (Dask) is not installed")

from graphslam.io.mcap_writer import write_session
from graphslam.sim import simulate


@pytest.fixture(scope="module")
def sites(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three small floors in two buildings; b2/F1 has one truncated recording."""
    root = tmp_path_factory.mktemp("sites")
    for k, rel in enumerate(["b1/F1", "b1/F2", "b2/F1"]):
        for s in simulate("corridor", seed=k, size=0.5).survey:
            # without headings: the update below is the incremental one (with headings it is a full re-solve)
            write_session(replace(s, heading=None), root / rel / f"{s.session_id}.mcap")
    bad = sorted((root / "b2/F1").glob("*.mcap"))[1]
    bad.write_bytes(bad.read_bytes()[:300])
    (root / "b1" / "notes.txt").write_text("not a floor")
    return root


def test_batch_surveys_every_floor_and_reports_the_broken_one(
    sites: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "out"
    assert _run(["survey-batch", str(sites), "--out", str(out), "--workers", "2", "--no-progress"]) == 1
    rows = json.loads((out / "summary.json").read_text())
    assert [r["floor"] for r in rows] == ["b1/F1", "b1/F2", "b2/F1"]
    # the main map first, counted as `survey` counts it
    assert list(rows[0])[:9] == ["floor", "status", "error", "walks", "main", "other_walks", "other_components",
                                 "unaligned", "main_map"]
    assert set(rows[0]) == {*list(rows[0])[:9], "aligned", "frame", "seconds", "warning"}
    ok = [r for r in rows if r["status"] == "ok"]
    assert len(ok) == 2 and all(r["error"] is None and r["walks"] == 6 and r["aligned"] >= 1 for r in ok)
    assert all(r["warning"] is None and 2 * r["main"] >= r["walks"] for r in ok)
    for r in ok:
        assert r["main"] + r["other_walks"] + r["unaligned"] == r["walks"] and r["aligned"] == r["main"] + r["other_walks"]
        report = json.loads((out / r["floor"] / "report.json").read_text())
        assert r["main"] == report["components"][0]["n_walks"] and r["frame"] == report["frame"]
        assert r["main_map"] == (f"main map: {r['main']} of {r['walks']} walks; {r['other_walks']} in "
                                 f"{r['other_components']} other component{'' if r['other_components'] == 1 else 's'}; "
                                 f"{r['unaligned']} unaligned")
    bad = rows[2]
    bad_file = sorted((sites / "b2/F1").glob("*.mcap"))[1]
    assert bad["status"] == "failed" and str(bad_file) in bad["error"] and bad["walks"] == 0 and bad["frame"] is None
    # each floor's outputs at its relative path; none for the failed floor
    assert (out / "b1/F1/radio_map.parquet").is_file() and (out / "b1/F2/report.json").is_file()
    assert not (out / "b2/F1/report.json").exists()
    printed = capsys.readouterr().out
    assert f"failed: b2/F1: {bad_file}" in printed
    assert all(f"ok: {r['floor']}: {r['main_map']}; frame {r['frame']}\n" in printed for r in ok)
    # the next night: floors surveyed before are updated in place, the broken one is tried in full again
    assert _run(["survey-batch", str(sites), "--out", str(out), "--workers", "1", "--no-progress", "--update"]) == 1
    for rel in ("b1/F1", "b1/F2"):
        u = json.loads((out / rel / "report.json").read_text())["update"]
        assert u["mode"] == "incremental" and u["new_walks"] == [] and u["resolved"]["nodes"] == 0


def test_batch_bad_arguments_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert _run(["survey-batch", str(tmp_path / "nope"), "--out", str(tmp_path / "o")]) == 2
    assert "not a folder" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert _run(["survey-batch", str(tmp_path / "empty"), "--out", str(tmp_path / "o")]) == 2
    assert "no folder under it holds .mcap" in capsys.readouterr().err
    assert _run(["survey-batch", str(tmp_path / "empty"), "--out", str(tmp_path / "o"), "--workers", "0"]) == 2


@pytest.mark.parametrize("allowed_failures", [3, 0])
def test_batch_on_an_existing_cluster_survives_a_killed_worker(
    sites: Path, tmp_path: Path, allowed_failures: int
) -> None:
    """--address joins a running scheduler. A worker killed while it surveys a floor: the scheduler
    runs the floor again (default), or with no retries allowed that floor alone fails as 'worker lost'
    while the other worker's floor finishes."""
    import dask
    from distributed import Client, LocalCluster

    good = tmp_path / "sites"
    for rel in ("b1/F1", "b1/F2"):
        (good / rel).mkdir(parents=True)
        for f in (sites / rel).glob("*.mcap"):
            os.link(f, good / rel / f.name)
    out = tmp_path / "out"
    with dask.config.set({"distributed.scheduler.allowed-failures": allowed_failures}):
        with LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=None) as cluster, Client(cluster) as c:
            codes: list[int] = []
            args = ["survey-batch", str(good), "--out", str(out), "--address", cluster.scheduler_address,
                    "--no-progress"]
            t = threading.Thread(target=lambda: codes.append(_run(args)))
            t.start()
            deadline = time.monotonic() + 60
            while not any(c.processing().values()) and time.monotonic() < deadline:
                time.sleep(0.01)
            pids = c.run(os.getpid)
            busy = [a for a, keys in c.processing().items() if keys]
            assert busy, "no floor started"
            os.kill(pids[busy[0]], signal.SIGKILL)
            t.join(120)
    rows = {r["floor"]: r for r in json.loads((out / "summary.json").read_text())}
    assert set(rows) == {"b1/F1", "b1/F2"}
    if allowed_failures:
        assert codes == [0] and all(r["status"] == "ok" for r in rows.values())
    else:
        lost = [r for r in rows.values() if r["status"] == "failed"]
        assert codes == [1] and len(lost) == 1 and lost[0]["error"].startswith("worker lost after retries: ")
        assert [r["status"] for r in rows.values()].count("ok") == 1


def _worker_state() -> tuple[bool, str | None, str | None, bool]:
    import os
    import sys

    import dask

    # nothing imported by this task itself: what the worker process was started with
    return ("graphslam.app.survey" in sys.modules, os.environ.get("OPENBLAS_NUM_THREADS"), os.environ.get("RERUN"),
            dask.config.get("distributed.worker.profile.enabled"))


def test_local_workers_start_with_the_survey_code_imported() -> None:
    """Local workers fork from a fork server that imported the survey code once (so no floor pays
    the imports), with one BLAS thread, no Rerun and no Dask profiler; the caller's environment is left as it was,
    and no process outlives the batch."""
    import multiprocessing
    import os

    from graphslam.app.batch import _client

    if "forkserver" not in multiprocessing.get_all_start_methods():
        pytest.skip("no fork server on this platform")
    import psutil  # a dependency of distributed

    before, children = dict(os.environ), {c.pid for c in psutil.Process().children(recursive=True)}
    with _client(None, 2) as client:
        states = client.gather([client.submit(_worker_state, pure=False, key=f"state-{k}") for k in range(4)])
        assert len(client.scheduler_info()["workers"]) == 2
    assert all(s == (True, "1", "off", False) for s in states), states
    assert dict(os.environ) == before
    # the fork server and its workers are gone with the batch
    assert {c.pid for c in psutil.Process().children(recursive=True) if c.status() != psutil.STATUS_ZOMBIE} <= children
    import dask

    assert dask.config.get("distributed.worker.multiprocessing-method") != "forkserver"  # config restored
    assert dask.config.get("distributed.worker.profile.enabled")


def test_batch_surveys_the_largest_floors_first(sites: Path, tmp_path: Path) -> None:
    """Largest floors (bytes of recordings) first, so that no worker is left with a big floor at
    the end while the others idle: with one worker the floors finish in that order."""
    from graphslam.app.batch import run_batch

    done: list[str] = []
    run_batch(sites, tmp_path / "out", workers=1, on_floor=lambda row: done.append(row.floor))
    size = {rel: sum(f.stat().st_size for f in (sites / rel).glob("*.mcap")) for rel in done}
    assert len(set(size.values())) == len(done)  # the fixture's floors differ in size
    assert done == sorted(done, key=lambda rel: -size[rel]) != sorted(done)  # not the folders' order


def test_linked_floor_folders_are_floors_each_real_folder_once(tmp_path: Path) -> None:
    """A site assembled of symbolic links to floors on another disk is surveyed; a link back up the tree,
    or a second link to a floor, does not make a floor twice (nor a walk without end)."""
    store, sites = tmp_path / "disk2", tmp_path / "sites"
    for name in ("F1", "F2"):
        (store / name).mkdir(parents=True)
        (store / name / "a.mcap").write_bytes(b"")
    (sites / "b1").mkdir(parents=True)
    (sites / "b1" / "F1").symlink_to(store / "F1", target_is_directory=True)
    (sites / "b1" / "F2").symlink_to(store / "F2", target_is_directory=True)
    (sites / "b1" / "again").symlink_to(store / "F1", target_is_directory=True)  # the same floor twice
    (store / "F2" / "up").symlink_to(sites, target_is_directory=True)  # a loop
    from graphslam.app.batch import find_floors

    floors = find_floors(sites, tmp_path / "out")
    assert [f.relative_to(sites).as_posix() for f in floors] == ["b1/F1", "b1/F2"]
