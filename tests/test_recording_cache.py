"""``recordings_cache.npz``: the walks a survey read, taken back by their files' contents."""

from __future__ import annotations

import json
import logging
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import graphslam
from conftest import run_cli as _run

from graphslam.core.survey.incremental import session_digest
from graphslam.core.types import Session, UwbRanges
from graphslam.io.csv_io import read_trajectories
from graphslam.io.mcap_reader import read_recordings
from graphslam.io.mcap_writer import write_session
from graphslam.io.recording_cache import CACHE_FILE, read_recording_cache, write_recording_cache
from graphslam.sim import simulate


def _same_session(a: Session, b: Session) -> None:
    assert (a.session_id, a.site, a.floor, a.source, a.uwb_id) == (b.session_id, b.site, b.floor, b.source, b.uwb_id)
    for x, y in ((a.steps, b.steps), (a.ground_truth, b.ground_truth)):
        assert (x is None) == (y is None)
        if x is not None:
            for f in ("t_ns", "xy", "heading"):
                np.testing.assert_array_equal(getattr(x, f), getattr(y, f))
    assert (a.heading is None) == (b.heading is None)
    if a.heading is not None:
        np.testing.assert_array_equal(a.heading.t_ns, b.heading.t_ns)
        np.testing.assert_array_equal(a.heading.yaw, b.heading.yaw)
    assert a.landmarks == b.landmarks
    assert [(s.t_ns, list(s.readings.items())) for s in a.scans] == [(s.t_ns, list(s.readings.items())) for s in b.scans]
    assert dict(a.uwb_anchors) == dict(b.uwb_anchors)
    assert (a.uwb_ranges is None) == (b.uwb_ranges is None)
    if a.uwb_ranges is not None:
        assert a.uwb_ranges.responder_id == b.uwb_ranges.responder_id
        for f in ("t_ns", "is_anchor", "range_m"):
            np.testing.assert_array_equal(getattr(a.uwb_ranges, f), getattr(b.uwb_ranges, f))
    assert session_digest(a) == session_digest(b)


@pytest.fixture(scope="module")
def walks(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Four crowd walks (headings, ground truth, landmark marks), one of them with UWB rangings and
    anchors (2-D and 3-D), as MCAP files."""
    root = tmp_path_factory.mktemp("cache")
    sim = simulate("crowd", seed=3, size=0.34)
    sessions = list(sim.survey)[:4]
    s = sessions[1]
    t = s.steps.t_ns[::40][:5]
    sessions[1] = replace(s, uwb_id="T1", uwb_anchors={"A1": (1.0, 2.0, 2.5), "A2": (3.0, 4.0)},
                          uwb_ranges=UwbRanges(t, ("A1", "A2", "A1", sessions[2].session_id, "A2"),
                                               np.array([True, True, True, False, True]), np.arange(5.0) + 1.5))
    sessions[2] = replace(sessions[2], uwb_id="T2")
    assert any(w.landmarks for w in sessions) and all(w.heading is not None for w in sessions)
    for w in sessions:
        write_session(w, root / "walks" / f"{w.session_id}.mcap")
    return root


def test_cached_walks_are_the_parsed_walks(walks: Path, tmp_path: Path) -> None:
    parsed = read_recordings([walks / "walks"])
    assert parsed.cached == 0 and len(parsed.keys) == 4
    write_recording_cache(tmp_path / CACHE_FILE, parsed.survey, parsed.keys)
    cache = read_recording_cache(tmp_path / CACHE_FILE)
    assert cache is not None and len(cache) == 4
    again = read_recordings([walks / "walks"], cache)
    assert again.cached == 4 and again.keys == parsed.keys
    for a, b in zip(again.survey, parsed.survey):
        _same_session(a, b)
    assert again.survey.sessions[1].uwb_ranges is not None


def test_both_reads_keep_one_object_per_bssid_and_per_rss_value(walks: Path, tmp_path: Path) -> None:
    """A large survey holds every reading in its scans' dicts: a BSSID string and an RSS float per
    reading would be ~90 MiB at 200 walks. Parsed and cached walks both share them."""
    parsed = read_recordings([walks / "walks"])
    write_recording_cache(tmp_path / CACHE_FILE, parsed.survey, parsed.keys)
    again = read_recordings([walks / "walks"], read_recording_cache(tmp_path / CACHE_FILE))
    assert again.cached == 4
    for survey in (parsed.survey, again.survey):
        items = [kv for w in survey for s in w.scans for kv in s.readings.items()]
        assert len(items) > 10 * len({b for b, _ in items})  # APs heard again and again
        assert len({id(b) for b, _ in items}) == len({b for b, _ in items})  # interned: one per survey
        for w in survey:  # values: one object per value and walk
            values = [v for s in w.scans for v in s.readings.values()]
            assert len({id(v) for v in values}) == len(set(values)) < len(values) / 10


def test_a_changed_or_renamed_file_is_parsed(walks: Path, tmp_path: Path) -> None:
    parsed = read_recordings([walks / "walks"])
    write_recording_cache(tmp_path / CACHE_FILE, parsed.survey, parsed.keys)
    cache = read_recording_cache(tmp_path / CACHE_FILE)
    folder = tmp_path / "walks"
    shutil.copytree(walks / "walks", folder)
    # one walk re-recorded: a step moved
    w = parsed.survey.sessions[0]
    xy = w.steps.xy.copy()
    xy[5] += 0.25
    changed = replace(w, steps=replace(w.steps, xy=xy))
    write_session(changed, folder / f"{w.session_id}.mcap")
    got = read_recordings([folder], cache)
    assert got.cached == 3
    np.testing.assert_array_equal(got.survey[w.session_id].steps.xy, xy)
    assert got.keys[w.session_id] != parsed.keys[w.session_id]
    # a file whose id is its name, renamed: the id may have come from the name, so it is parsed
    v = parsed.survey.sessions[3]
    named = replace(v, session_id="stem-id")
    write_session(named, tmp_path / "stem-id.mcap")
    one = read_recordings([tmp_path / "stem-id.mcap"])
    write_recording_cache(tmp_path / "c2.npz", one.survey, one.keys)
    shutil.move(tmp_path / "stem-id.mcap", tmp_path / "renamed.mcap")
    moved = read_recordings([tmp_path / "renamed.mcap"], read_recording_cache(tmp_path / "c2.npz"))
    assert moved.cached == 0 and moved.survey.sessions[0].session_id == "stem-id"
    # ... while a walk whose id is not its file's name is taken from the cache under any name
    write_session(v, tmp_path / "recorded-as.mcap")
    one = read_recordings([tmp_path / "recorded-as.mcap"])
    write_recording_cache(tmp_path / "c3.npz", one.survey, one.keys)
    shutil.move(tmp_path / "recorded-as.mcap", tmp_path / "moved.mcap")
    moved = read_recordings([tmp_path / "moved.mcap"], read_recording_cache(tmp_path / "c3.npz"))
    assert moved.cached == 1 and moved.survey.sessions[0].session_id == v.session_id
    assert moved.survey.sessions[0].source == str(tmp_path / "moved.mcap")


def test_an_unusable_cache_is_a_log_line_and_a_full_read(walks: Path, tmp_path: Path,
                                                          caplog: pytest.LogCaptureFixture) -> None:
    parsed = read_recordings([walks / "walks"])
    path = write_recording_cache(tmp_path / CACHE_FILE, parsed.survey, parsed.keys)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])  # truncated
    with caplog.at_level(logging.WARNING):
        assert read_recording_cache(path) is None
    assert "unusable recordings cache" in caplog.text
    fresh = write_recording_cache(tmp_path / "fresh.npz", parsed.survey, parsed.keys)
    with np.load(fresh) as z:  # another version's cache
        arrays = {k: z[k] for k in z.files}
    arrays["graphslam"] = np.array("0.0.0-other")
    np.savez(tmp_path / "other.npz", **arrays)
    assert read_recording_cache(tmp_path / "other.npz") is None
    short = {**arrays, "graphslam": np.array(graphslam.__version__), "rssi": arrays["rssi"][:-1]}
    np.savez(tmp_path / "short.npz", **short)  # readings' arrays that disagree
    assert read_recording_cache(tmp_path / "short.npz") is None
    arrays = {k: v for k, v in arrays.items() if k != "graphslam"}
    np.savez(tmp_path / "missing.npz", **arrays)
    assert read_recording_cache(tmp_path / "missing.npz") is None
    assert read_recording_cache(tmp_path / "absent.npz") is None


def test_an_update_parses_only_the_new_walks_and_answers_as_a_full_read(tmp_path: Path) -> None:
    sim = simulate("crowd", seed=0, size=0.25)
    for k, s in enumerate(sim.survey):
        write_session(s, tmp_path / "all" / f"{s.session_id}.mcap")
        if k < len(sim.survey) - 1:
            write_session(s, tmp_path / "old" / f"{s.session_id}.mcap")
    assert _run(["survey", str(tmp_path / "old"), "--out", str(tmp_path / "prev"), "--no-progress"]) == 0
    assert (tmp_path / "prev" / CACHE_FILE).is_file()
    shutil.copytree(tmp_path / "prev", tmp_path / "prev_nocache")
    (tmp_path / "prev_nocache" / CACHE_FILE).unlink()
    outs = {}
    for name in ("prev", "prev_nocache"):
        out = tmp_path / f"upd_{name}"
        assert _run(["survey", str(tmp_path / "all"), "--out", str(out), "--update", str(tmp_path / name),
                     "--no-progress"]) == 0
        outs[name] = out
    rep = json.loads((outs["prev"] / "report.json").read_text())
    assert rep["update"]["mode"] == "incremental"
    assert rep["update"]["walks_from_cache"] == len(sim.survey) - 1
    assert json.loads((outs["prev_nocache"] / "report.json").read_text())["update"]["walks_from_cache"] == 0
    a, b = (read_trajectories(o / "trajectories.csv") for o in outs.values())
    assert a.keys() == b.keys()
    for sid in a:
        np.testing.assert_array_equal(a[sid].xy, b[sid].xy)
    assert (outs["prev"] / "wifi_edges.parquet").read_bytes() == (outs["prev_nocache"] / "wifi_edges.parquet").read_bytes()
    # the update's own output carries the cache of every walk, for the next update
    cache = read_recording_cache(outs["prev"] / CACHE_FILE)
    assert cache is not None and len(cache) == len(sim.survey)
