"""The UWB part of the input contract: /uwb/range, uwb_id, graphslam.uwb_anchors; every bad value
is one InputError naming the file and the field, exit code 2 from the CLI."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import T0, make_session, pose_body
from mcap.writer import Writer

from graphslam.cli import main
from graphslam.core.types import UwbRanges
from graphslam.errors import InputError
from graphslam.io.mcap_reader import read_session, read_survey
from graphslam.io.mcap_writer import write_session
from graphslam.io.schemas import TOPIC_SCHEMAS, schema_bytes

ANCHORS = {"A1": "[0.0, 0.0, 2.5]", "A2": "[10, 0]"}


def _range(t: int, rid: str, kind: str, r: Any) -> dict:
    return {"timestamp": {"sec": t // 10**9, "nsec": t % 10**9}, "responder_id": rid, "responder_kind": kind, "range_m": r}


def _write(path: Path, ranges: list[dict | bytes], *, anchors: dict[str, str] | None = ANCHORS, uwb_id: str = "T1") -> Path:
    """Steps plus the given raw /uwb/range bodies, the session record with uwb_id, the anchor record."""
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start()
        w.add_metadata("graphslam.session", {"session_id": path.stem, "site": "s", "floor": "0", "uwb_id": uwb_id})
        if anchors is not None:
            w.add_metadata("graphslam.uwb_anchors", anchors)
        ch = {}
        for topic in ("/fmip/pose", "/uwb/range"):
            name, schema = TOPIC_SCHEMAS[topic]
            sid = w.register_schema(name=name, encoding="jsonschema", data=schema_bytes(schema))
            ch[topic] = w.register_channel(topic=topic, message_encoding="json", schema_id=sid)
        for i in range(5):
            t = T0 + i * 500_000_000
            w.add_message(ch["/fmip/pose"], log_time=t, publish_time=t, data=json.dumps(pose_body(t, 0.7 * i, 0, 0)).encode())
        for i, body in enumerate(ranges):
            t = T0 + i * 100_000_000
            data = body if isinstance(body, bytes) else json.dumps(body).encode()
            w.add_message(ch["/uwb/range"], log_time=t, publish_time=t, data=data)
        w.finish()
    return path


def test_round_trip_keeps_ranges_anchors_and_tag_id(tmp_path: Path) -> None:
    s = make_session("w1", 10)
    r = UwbRanges(s.steps.t_ns[:3] + 5, ("A1", "T2", "A1"), np.array([True, False, True]), np.array([3.25, 0.5, 7.0]))
    from dataclasses import replace

    s = replace(s, uwb_id="T1", uwb_ranges=r, uwb_anchors={"A1": (1.0, 2.0, 2.5), "A2": (3.0, 4.0)})
    back = read_session(write_session(s, tmp_path / "w1.mcap"))
    assert back.uwb_id == "T1"
    assert dict(back.uwb_anchors) == {"A1": (1.0, 2.0, 2.5), "A2": (3.0, 4.0)}
    assert back.uwb_ranges is not None
    np.testing.assert_array_equal(back.uwb_ranges.t_ns, r.t_ns)
    assert back.uwb_ranges.responder_id == r.responder_id
    np.testing.assert_array_equal(back.uwb_ranges.is_anchor, r.is_anchor)
    np.testing.assert_array_equal(back.uwb_ranges.range_m, r.range_m)
    # a recording without UWB keeps the defaults
    plain = read_session(write_session(make_session("w2", 5), tmp_path / "w2.mcap"))
    assert plain.uwb_ranges is None and plain.uwb_id == "" and not plain.uwb_anchors


BAD = [
    ([_range(T0, "A1", "anchor", -0.5)], "range_m", "negative range"),
    ([b'{"timestamp": {"sec": 1, "nsec": 0}, "responder_id": "A1", "responder_kind": "anchor", "range_m": NaN}'],
     "range_m", "non-finite"),
    ([_range(T0, "A1", "anchor", 5000.0)], "range_m", "absurd range"),
    ([_range(T0, "A1", "anchor", "3")], "range_m", "expected a number"),
    ([_range(T0, "A1", "beacon", 3.0)], "responder_kind", "'anchor' or 'tag'"),
    ([_range(T0, "", "tag", 3.0)], "responder_id", "non-empty string"),
    ([_range(T0, "A9", "anchor", 3.0)], "responder_id", "unknown anchor 'A9'"),
    ([_range(T0, "T1", "tag", 3.0)], "responder_id", "ranges itself"),
]


@pytest.mark.parametrize("ranges, field, problem", BAD, ids=[b[2] for b in BAD])
def test_bad_range_message(tmp_path: Path, ranges: list, field: str, problem: str) -> None:
    p = _write(tmp_path / "bad.mcap", ranges)
    with pytest.raises(InputError) as e:
        read_survey([p])
    msg = str(e.value)
    assert str(p) in msg and "/uwb/range" in msg and f"[field {field}]" in msg and problem in msg


def test_ranges_going_back_in_time(tmp_path: Path) -> None:
    bodies = [_range(T0 + 10**9, "A1", "anchor", 3.0), _range(T0, "A1", "anchor", 3.0)]
    p = _write(tmp_path / "back.mcap", bodies)
    with pytest.raises(InputError, match="time goes backwards") as e:
        read_survey([p])
    assert "[field timestamp]" in str(e.value)


@pytest.mark.parametrize("raw", ['[1, "a"]', "[1]", "1, 2", "[1, 2, 3, 4]", "[1e999, 0]"])
def test_bad_anchor_record(tmp_path: Path, raw: str) -> None:
    p = _write(tmp_path / "anc.mcap", [], anchors={"A1": raw})
    with pytest.raises(InputError) as e:
        read_survey([p])
    assert str(p) in str(e.value) and "[field graphslam.uwb_anchors.A1]" in str(e.value)


def test_anchors_must_agree_between_files_and_tag_ids_be_unique(tmp_path: Path) -> None:
    a = _write(tmp_path / "a.mcap", [], anchors={"A1": "[0, 0]"}, uwb_id="T1")
    b = _write(tmp_path / "b.mcap", [], anchors={"A1": "[0, 0.5]"}, uwb_id="T2")
    with pytest.raises(InputError) as e:
        read_survey([a, b])
    assert str(b) in str(e.value) and "graphslam.uwb_anchors.A1" in str(e.value) and str(a) in str(e.value)
    c = _write(tmp_path / "c.mcap", [], anchors={"A1": "[0, 0]"}, uwb_id="T1")
    with pytest.raises(InputError) as e:
        read_survey([a, c])
    assert str(c) in str(e.value) and "graphslam.session.uwb_id" in str(e.value) and "'T1'" in str(e.value)


def test_cli_reports_a_bad_range_in_one_line_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    p = _write(tmp_path / "bad.mcap", [_range(T0, "A1", "anchor", -1.0)])
    with pytest.raises(SystemExit) as e:
        main(["track-uwb", str(p), "--out", str(tmp_path / "out.csv")])
    err = capsys.readouterr().err.strip()
    assert e.value.code == 2 and len(err.splitlines()) == 1 and "range_m" in err and str(p) in err
    assert not (tmp_path / "out.csv").exists()
