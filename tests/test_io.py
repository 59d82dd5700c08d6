"""Ingest: round trip, the real ILC floor, and every bad-input case of the contract."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import (
    ILC,
    T0,
    good_messages,
    make_session,
    needs_data,
    pose_body,
    scan_body,
    write_raw_mcap,
)

from graphslam.cli import main
from graphslam.errors import InputError
from graphslam.io.mcap_reader import read_session, read_survey
from graphslam.io.mcap_writer import write_session


def test_round_trip_keeps_everything(tmp_path: Path) -> None:
    s = make_session("walk-1", 30)
    p = write_session(s, tmp_path / "w.mcap")
    r = read_session(p)
    assert r.session_id == "walk-1" and r.site == "test" and r.floor == "0"
    np.testing.assert_array_equal(r.steps.t_ns, s.steps.t_ns)
    np.testing.assert_allclose(r.steps.xy, s.steps.xy, atol=1e-12)
    np.testing.assert_allclose(np.cos(r.steps.heading - s.steps.heading), 1.0, atol=1e-12)
    assert [dict(x.readings) for x in r.scans] == [dict(x.readings) for x in s.scans]
    assert r.landmarks == s.landmarks
    assert r.ground_truth is not None
    np.testing.assert_allclose(r.ground_truth.xy, s.ground_truth.xy, atol=1e-12)
    assert not list(tmp_path.glob(".*.tmp")), "temp file left behind"


def test_missing_metadata_uses_file_stem(tmp_path: Path) -> None:
    p = write_raw_mcap(tmp_path / "my-walk.mcap", good_messages())
    assert read_session(p).session_id == "my-walk"


@needs_data("ilc20/site1/F1")
def test_reads_real_ilc_floor() -> None:
    survey = read_survey([ILC / "F1"])
    assert len(survey) == 105
    assert survey.n_scans == 1688
    assert sum(len(s.landmarks) for s in survey) == 740
    assert all(s.steps.xy[0].tolist() == [0.0, 0.0] for s in survey)


@needs_data("ilc20/site1")
def test_reads_every_ilc_file() -> None:
    floors = sorted(p for p in ILC.iterdir() if p.is_dir())
    assert [f.name for f in floors] == ["B1", "F1", "F2", "F3", "F4"]
    for floor in floors:
        survey = read_survey([floor])
        assert len(survey) == len(list(floor.glob("*.mcap"))) > 90
        assert all(s.floor == floor.name for s in survey)


def test_folder_means_its_own_files_not_subfolders(tmp_path: Path) -> None:
    write_session(make_session("top", 10), tmp_path / "top.mcap")
    write_session(make_session("held-out", 10), tmp_path / "test" / "held-out.mcap")
    assert [s.session_id for s in read_survey([tmp_path])] == ["top"]


def _err(path: Path | list[Path]) -> InputError:
    with pytest.raises(InputError) as e:
        read_survey(path if isinstance(path, list) else [path])
    return e.value


def test_not_mcap(tmp_path: Path) -> None:
    p = tmp_path / "notes.mcap"
    p.write_text("hello, not a recording")
    e = _err(p)
    assert e.path == str(p) and "not an MCAP file" in str(e)


def test_truncated(tmp_path: Path) -> None:
    good = write_raw_mcap(tmp_path / "good.mcap", good_messages(200, 50))
    data = good.read_bytes()
    for cut in (len(data) // 2, len(data) - 5):
        p = tmp_path / f"cut{cut}.mcap"
        p.write_bytes(data[:cut])
        e = _err(p)
        assert e.path == str(p) and "truncated" in str(e)


def test_missing_pose_topic(tmp_path: Path) -> None:
    msgs = [m for m in good_messages() if m[0] != "/fmip/pose"]
    e = _err(write_raw_mcap(tmp_path / "a.mcap", msgs))
    assert e.topic == "/fmip/pose" and "no step poses" in str(e)


def test_wrong_schema(tmp_path: Path) -> None:
    p = write_raw_mcap(tmp_path / "a.mcap", good_messages(), schema_names={"/wifi/scan": "foxglove.Log"})
    e = _err(p)
    assert e.topic == "/wifi/scan" and e.field == "schema" and "foxglove.Log" in str(e)


@pytest.mark.parametrize(
    "field",
    ["pose.position.x", "pose.orientation.w", "timestamp.nsec"],
)
def test_missing_pose_field(tmp_path: Path, field: str) -> None:
    msgs = good_messages()
    topic, body, t = msgs[3]
    assert topic == "/fmip/pose"
    node = body
    *parents, leaf = field.split(".")
    for k in parents:
        node = node[k]
    del node[leaf]
    e = _err(write_raw_mcap(tmp_path / "a.mcap", msgs))
    assert e.topic == "/fmip/pose" and e.field == field and "missing" in str(e)


def test_missing_scan_rssi(tmp_path: Path) -> None:
    msgs = good_messages()
    t = T0 + 10
    msgs.append(("/wifi/scan", {"timestamp": {"sec": t // 10**9, "nsec": t % 10**9}, "readings": [{"bssid": "x"}]}, t))
    msgs.sort(key=lambda m: m[2])
    e = _err(write_raw_mcap(tmp_path / "a.mcap", msgs))
    assert e.topic == "/wifi/scan" and e.field == "readings[0].rssi"


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_values(tmp_path: Path, bad: float) -> None:
    msgs = good_messages()
    msgs[2][1]["pose"]["position"]["y"] = bad  # json.dumps writes NaN / Infinity
    e = _err(write_raw_mcap(tmp_path / "a.mcap", msgs))
    assert e.field == "pose.position.y" and "non-finite" in str(e)
    msgs = good_messages()
    i = next(i for i, m in enumerate(msgs) if m[0] == "/wifi/scan")
    msgs[i][1]["readings"][0]["rssi"] = bad
    e = _err(write_raw_mcap(tmp_path / "b.mcap", msgs))
    assert e.topic == "/wifi/scan" and e.field == "readings[0].rssi"


def test_non_unit_quaternion(tmp_path: Path) -> None:
    msgs = good_messages()
    msgs[2][1]["pose"]["orientation"] = {"x": 0.0, "y": 0.0, "z": 0.5, "w": 0.5}
    e = _err(write_raw_mcap(tmp_path / "a.mcap", msgs))
    assert e.field == "pose.orientation" and "not unit" in str(e)


def test_times_going_backwards(tmp_path: Path) -> None:
    msgs = [m for m in good_messages() if m[0] == "/fmip/pose"]
    t_late = msgs[5][2]
    # step 6 claims an earlier time than step 5 (file order is what the walker recorded)
    msgs[6] = ("/fmip/pose", pose_body(t_late - 1, 1.0, 0.0, 0.0), t_late - 1)
    e = _err(write_raw_mcap(tmp_path / "a.mcap", msgs))
    assert e.topic == "/fmip/pose" and e.field == "timestamp" and "does not increase" in str(e)
    scans = [m for m in good_messages() if m[0] == "/fmip/pose"]
    scans += [("/wifi/scan", scan_body(T0 + 3 * 10**9, {"a": -50.0}), T0 + 3 * 10**9)]
    scans += [("/wifi/scan", scan_body(T0 + 1 * 10**9, {"a": -50.0}), T0 + 1 * 10**9)]
    e = _err(write_raw_mcap(tmp_path / "b.mcap", scans))
    assert e.topic == "/wifi/scan" and e.field == "timestamp" and "backwards" in str(e)


def test_invalid_json_message(tmp_path: Path) -> None:
    msgs = good_messages()
    msgs[0] = (msgs[0][0], b"{not json", msgs[0][2])
    e = _err(write_raw_mcap(tmp_path / "a.mcap", msgs))
    assert e.topic == "/fmip/pose" and "not valid JSON" in str(e)


def test_duplicate_session_ids(tmp_path: Path) -> None:
    meta = {"session_id": "same", "site": "s", "floor": "f"}
    a = write_raw_mcap(tmp_path / "a.mcap", good_messages(), metadata=meta)
    b = write_raw_mcap(tmp_path / "b.mcap", good_messages(), metadata=meta)
    e = _err([a, b])
    assert e.path == str(b) and "duplicate session id 'same'" in str(e) and str(a) in str(e)


def test_empty_folder(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    e = _err(tmp_path / "empty")
    assert "no .mcap" in str(e)


def test_cli_exits_nonzero_with_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    p = tmp_path / "bad.mcap"
    p.write_bytes(b"\x00" * 100)
    with pytest.raises(SystemExit) as e:
        main(["inspect", str(p)])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(p) in err[0] and "not an MCAP file" in err[0]


def test_cli_inspect_reports_counts(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    write_session(make_session("a", 21), tmp_path / "a.mcap")
    write_session(make_session("b", 9), tmp_path / "b.mcap")
    main(["inspect", "--json", str(tmp_path)])
    lines = [json.loads(x) for x in capsys.readouterr().out.strip().splitlines()]
    assert [x.get("session_id") for x in lines[:2]] == ["a", "b"]
    assert lines[0]["steps"] == 21 and lines[0]["scans"] == 6 and lines[0]["landmarks"] == 1
    assert lines[-1]["totals"]["sessions"] == 2 and lines[-1]["totals"]["steps"] == 30
    assert lines[0]["walked_m"] == pytest.approx(20 * 0.7, rel=1e-6)


def test_floor_folders_lists_floors_and_names_what_is_missing(tmp_path: Path) -> None:
    from graphslam.io.mcap_reader import floor_folders

    for name in ("F1", "B1"):
        (tmp_path / name).mkdir()
    (tmp_path / "floor_info.json").write_text("{}")
    assert [p.name for p in floor_folders(tmp_path)] == ["B1", "F1"]
    assert [p.name for p in floor_folders(tmp_path, ["F1"])] == ["F1"]
    with pytest.raises(InputError, match="F9.*no such floor folder"):
        floor_folders(tmp_path, ["F1", "F9"])
    with pytest.raises(InputError, match="no floor folders"):
        floor_folders(tmp_path / "B1")
    with pytest.raises(InputError, match="not a folder"):
        floor_folders(tmp_path / "floor_info.json")


def test_cli_inspect_table_shows_whole_session_ids(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # IPIN-like ids differ only after 28 characters: the table must not cut them
    ids = ["IPIN2023_T3_TrainingTrial21_repetition01", "IPIN2023_T3_TrainingTrial21_repetition02"]
    for sid in ids:
        write_session(make_session(sid, 5), tmp_path / f"{sid}.mcap")
    main(["inspect", str(tmp_path)])
    rows = capsys.readouterr().out.splitlines()[1:3]
    assert [r.split()[0] for r in rows] == ids


def _tracks(seed: int, walks: int, poses: int) -> dict:
    from graphslam.core.types import PoseTrack

    rng = np.random.default_rng(seed)
    out = {}
    for w in range(walks):
        n = int(rng.integers(0, poses)) if w == 0 else poses  # walk 0 may be empty
        # drawn from a small shared pool: walks often have poses at the same time (ordered by channel)
        t = np.sort(rng.choice(2 * poses + 2, n, replace=False)).astype(np.int64) * 10**8
        out[f"w{w:02d}"] = PoseTrack(t, rng.normal(0, 30, (n, 2)), rng.uniform(-np.pi, np.pi, n))
    return out


@pytest.mark.parametrize(("walks", "poses"), [(0, 0), (1, 1), (3, 40), (6, 9000)])  # 6 x 9000: several chunks
def test_aligned_mcap_is_the_writers_byte_for_byte(tmp_path: Path, walks: int, poses: int) -> None:
    """``write_aligned`` packs the messages itself (``io.mcap_bulk``): the file must be exactly
    what mcap's Writer makes of the same poses, and read back with every CRC checked."""
    from mcap.reader import make_reader

    from graphslam.io.mcap_writer import _write_aligned_by_writer, write_aligned

    tracks = _tracks(walks, walks, poses)
    fast, ref = write_aligned(tracks, tmp_path / "fast.mcap"), _write_aligned_by_writer(tracks, tmp_path / "ref.mcap")
    assert fast.read_bytes() == ref.read_bytes()
    with fast.open("rb") as f:
        reader = make_reader(f, validate_crcs=True)
        n = sum(1 for _ in reader.iter_messages())
        summary = reader.get_summary()
    assert n == sum(len(t.t_ns) for t in tracks.values())
    assert summary is not None and summary.statistics.message_count == n
    if walks == 6:
        assert summary.statistics.chunk_count > 1


@pytest.mark.parametrize("frame", ["aligned", 'a "quoted" \\ frame'])
def test_pose_messages_are_orjson_of_the_pose_dicts(frame: str) -> None:
    """``_pose_msgs`` formats the messages from the arrays: each must be, byte for byte, orjson of the
    pose's dict with ``heading_to_quaternion``'s quaternion (the files written before stay equal)."""
    import orjson

    from graphslam.core.types import PoseTrack, heading_to_quaternion
    from graphslam.io.mcap_writer import _pose_msgs, _stamp

    tracks = list(_tracks(5, 2, 300).values())
    t = np.arange(7, dtype=np.int64) * 1_000_000_007 + 1_600_000_000_123_456_789
    xy = np.array([[0.0, -0.0], [1e-7, 1e22], [-3.5, 2.0**-40], [123456.789, -1e-300], [5e-324, 0.1], [1.0, 2.0], [-0.0, 7.0]])
    tracks.append(PoseTrack(t, xy, np.array([0.0, -0.0, np.pi, -np.pi, 1e-9, 3.0, -2.5])))
    for track in tracks:
        expected = [
            orjson.dumps({"timestamp": _stamp(ti), "frame_id": frame, "pose": {
                "position": {"x": x, "y": y, "z": 0.0}, "orientation": dict(zip("xyzw", heading_to_quaternion(h)))}})
            for ti, (x, y), h in zip(track.t_ns.tolist(), track.xy.tolist(), track.heading.tolist())
        ]
        got = _pose_msgs(track, frame)
        assert [m for _, m in got] == expected
        assert [ti for ti, _ in got] == track.t_ns.tolist()
