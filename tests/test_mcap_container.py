"""The MCAP reading path: every compression and layout the format allows reads the same
session; hostile message bodies are InputErrors naming the message and field."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from conftest import good_messages, make_session, write_raw_mcap
from mcap.writer import CompressionType, Writer

from graphslam.errors import InputError
from graphslam.io.mcap_reader import DECODERS, read_session
from graphslam.io.mcap_writer import write_session
from graphslam.io.schemas import TOPIC_SCHEMAS, schema_bytes


def rewrite(src: Path, dst: Path, **writer_options: object) -> Path:
    """``src``'s records again with other writer options (compression, chunking, CRCs)."""
    from mcap.reader import make_reader

    with open(src, "rb") as fh, open(dst, "wb") as out:
        reader = make_reader(fh)
        w = Writer(out, **writer_options)  # type: ignore[arg-type]
        w.start()
        for m in reader.iter_metadata():
            w.add_metadata(m.name, dict(m.metadata))
        schemas, channels = {}, {}
        for schema, channel, msg in reader.iter_messages(log_time_order=False):
            if schema.id not in schemas:
                schemas[schema.id] = w.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = w.register_channel(channel.topic, channel.message_encoding, schemas[schema.id])
            w.add_message(channels[channel.id], msg.log_time, msg.data, msg.publish_time)
        w.finish()
    return dst


@pytest.mark.parametrize("options", [
    {"compression": CompressionType.LZ4},
    {"compression": CompressionType.NONE},
    {"use_chunking": False},
    {"compression": CompressionType.ZSTD, "enable_crcs": False, "use_summary_offsets": False},
    {"compression": CompressionType.ZSTD, "chunk_size": 512},  # many chunks
], ids=["lz4", "uncompressed", "unchunked", "no-crcs", "small-chunks"])
def test_every_layout_reads_the_same_session(tmp_path: Path, options: dict) -> None:
    ref_path = write_session(make_session("w", 40), tmp_path / "ref.mcap")
    ref = read_session(ref_path)
    got = read_session(rewrite(ref_path, tmp_path / "other.mcap", **options))
    assert got.session_id == ref.session_id and got.site == ref.site
    assert got.steps.t_ns.tolist() == ref.steps.t_ns.tolist() and (got.steps.xy == ref.steps.xy).all()
    assert [(s.t_ns, dict(s.readings)) for s in got.scans] == [(s.t_ns, dict(s.readings)) for s in ref.scans]
    assert got.landmarks == ref.landmarks and got.ground_truth is not None


def test_every_contract_topic_has_a_decoder() -> None:
    assert set(DECODERS) == set(TOPIC_SCHEMAS)


def _with_pose(tmp_path: Path, raw: bytes) -> Path:
    msgs = good_messages()
    i = next(i for i, m in enumerate(msgs) if m[0] == "/fmip/pose" and i > 0)
    msgs[i] = (msgs[i][0], raw, msgs[i][2])
    return write_raw_mcap(tmp_path / "a.mcap", msgs)


@pytest.mark.parametrize("raw,field,problem", [
    (b'{"timestamp": {"sec": 1767225600, "nsec": 1000000000}, "pose": {}}', "timestamp.nsec", "outside"),
    (b'{"timestamp": {"sec": -1, "nsec": 0}, "pose": {}}', "timestamp.sec", "outside"),
    # beyond 64 bits: orjson reads a float (an integer error), the standard parser an int (out of range)
    (b'{"timestamp": {"sec": 99999999999999999999, "nsec": 0}}', "timestamp.sec", "outside|expected an integer"),
    (b'{"timestamp": {"sec": 1767225600, "nsec": 5}, "pose": {"position": {"x": 1' + b"0" * 400 + b', "y": 0}}}',
     "pose.position.x", "out of range"),
])
def test_hostile_values_name_the_field(tmp_path: Path, raw: bytes, field: str, problem: str) -> None:
    with pytest.raises(InputError) as e:
        read_session(_with_pose(tmp_path, raw))
    assert e.value.topic == "/fmip/pose" and e.value.field == field and re.search(problem, str(e.value))


@pytest.mark.parametrize("depth", [2000, 200_000])
def test_deep_json_message_is_an_input_error(tmp_path: Path, depth: int) -> None:
    body = b'{"timestamp": {"sec": 1, "nsec": 0}, "x": ' + b"[" * depth + b"]" * depth + b"}"
    with pytest.raises(InputError, match=r"message #\d+ is not valid JSON"):
        read_session(_with_pose(tmp_path, body))


def test_message_on_an_undefined_channel(tmp_path: Path) -> None:
    path = tmp_path / "a.mcap"
    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start()
        sid = w.register_schema("foxglove.PoseInFrame", "jsonschema", schema_bytes(TOPIC_SCHEMAS["/fmip/pose"][1]))
        w.register_channel("/fmip/pose", "json", sid)
        w.add_message(7, 1, json.dumps({}).encode(), 1)  # channel 7 was never registered
        w.finish()
    with pytest.raises(InputError, match="channel 7, which is not defined"):
        read_session(path)


def test_scans_read_are_what_a_validated_scan_holds(tmp_path: Path) -> None:
    """The reader builds scans without a second validation pass (``Scan._validated``): they must be
    what ``Scan(...)`` would hold, Python ints and floats in a read-only mapping, on both reading
    paths (a duplicate BSSID within a scan takes the slower one)."""
    from types import MappingProxyType

    from graphslam.core.types import Scan

    session = make_session("w", 40)
    scans = list(session.scans)
    scans[3] = Scan(scans[3].t_ns, {**scans[3].readings, "aa:bb:cc:dd:ee:ff": -61})  # an int RSS written
    import dataclasses

    got = read_session(write_session(dataclasses.replace(session, scans=tuple(scans)), tmp_path / "w.mcap"))
    assert got.scans and all(s == Scan(s.t_ns, dict(s.readings)) for s in got.scans)
    for s in got.scans:
        assert type(s.t_ns) is int and isinstance(s.readings, MappingProxyType)
        assert all(type(b) is str and b and type(v) is float for b, v in s.readings.items())
    assert got.scans[3].readings["aa:bb:cc:dd:ee:ff"] == -61.0
