"""Read survey recordings (one MCAP file per session) into checked ``Session`` objects.

Every violation of DATA_CONTRACT.md raises ``InputError`` naming file, topic and field.
"""

from __future__ import annotations

import json
import logging
import math
import struct
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np
import orjson
from mcap.exceptions import McapError
from mcap.reader import make_reader

from graphslam.core.types import LandmarkMark, PoseTrack, Scan, Session, Survey
from graphslam.errors import InputError
from graphslam.io import uwb_io
from graphslam.io.schemas import (
    MCAP_MAGIC,
    SESSION_METADATA,
    TOPIC_GROUND_TRUTH,
    TOPIC_LANDMARKS,
    TOPIC_POSE,
    TOPIC_SCAN,
    TOPIC_SCHEMAS,
    TOPIC_UWB_RANGE,
    UWB_ANCHORS_METADATA,
)

log = logging.getLogger(__name__)

QUATERNION_NORM_TOL = 1e-3


def expand_paths(paths: Iterable[str | Path]) -> list[Path]:
    """Files as given; a folder means the ``*.mcap`` files directly in it (not its sub-folders:
    a simulator's held-out ``test/`` walks or another floor must not join a survey by accident).
    Sorted, de-duplicated."""
    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            found = sorted(p.glob("*.mcap"))
            if not found:
                raise InputError(p, "folder contains no .mcap recordings")
            out.extend(found)
        elif p.exists():
            out.append(p)
        else:
            raise InputError(p, "no such file or folder")
    seen: set[Path] = set()
    unique = []
    for p in out:
        r = p.resolve()
        if r not in seen:
            seen.add(r)
            unique.append(p)
    if not unique:
        raise InputError(", ".join(map(str, paths)) or "<none>", "no recordings given")
    return unique


def floor_folders(site_dir: str | Path, floors: Iterable[str] | None = None) -> list[Path]:
    """The floor folders of a multi-floor site (e.g. ILC ``site1/{B1,F1,...}``): ``floors`` if
    given (each must exist), else every sub-folder, sorted."""
    site = Path(site_dir)
    if not site.is_dir():
        raise InputError(site, "not a folder (a site with one folder per floor)")
    names = list(floors) if floors else sorted(p.name for p in site.iterdir() if p.is_dir())
    if not names:
        raise InputError(site, "no floor folders (e.g. B1, F1) in this site folder")
    missing = [n for n in names if not (site / n).is_dir()]
    if missing:
        raise InputError(site / missing[0], "no such floor folder")
    return [site / n for n in names]


def read_survey(paths: Iterable[str | Path]) -> Survey:
    """Read every session under ``paths`` (files or folders). Session ids must be unique."""
    files = expand_paths(paths)
    sessions = [read_session(f) for f in files]
    by_id: dict[str, Session] = {}
    for s in sessions:
        if s.session_id in by_id:
            raise InputError(
                s.source,
                f"duplicate session id {s.session_id!r} (also in {by_id[s.session_id].source})",
                field="graphslam.session.session_id",
            )
        by_id[s.session_id] = s
    uwb_io.check_survey(sessions)  # UWB (issue 15): anchors agree between files, uwb_id unique
    return Survey(tuple(sessions))


class _Parse:
    """Field access that raises ``InputError`` with the full field path."""

    def __init__(self, path: Path, topic: str, index: int) -> None:
        self.path, self.topic, self.index = path, topic, index

    def fail(self, field: str, problem: str) -> InputError:
        return InputError(self.path, f"message #{self.index}: {problem}", topic=self.topic, field=field)

    def get(self, obj: Any, field: str) -> Any:
        cur = obj
        for part in field.split("."):
            if not isinstance(cur, dict) or part not in cur:
                raise self.fail(field, "missing field")
            cur = cur[part]
        return cur

    def number(self, obj: Any, field: str) -> float:
        v = self.get(obj, field)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.fail(field, f"expected a number, got {type(v).__name__}")
        if not math.isfinite(v):
            raise self.fail(field, f"non-finite value {v}")
        return float(v)

    def string(self, obj: Any, field: str) -> str:
        v = self.get(obj, field)
        if not isinstance(v, str) or not v:
            raise self.fail(field, "expected a non-empty string")
        return v

    def stamp(self, obj: Any, log_time: int) -> int:
        sec = self.get(obj, "timestamp.sec")
        nsec = self.get(obj, "timestamp.nsec")
        for name, v in (("timestamp.sec", sec), ("timestamp.nsec", nsec)):
            if isinstance(v, bool) or not isinstance(v, int):
                raise self.fail(name, f"expected an integer, got {v!r}")
        t = sec * 1_000_000_000 + nsec
        if t != log_time:
            log.debug("%s %s: log_time %d != timestamp %d", self.path, self.topic, log_time, t)
        return t


def _decode(path: Path, topic: str, index: int, data: bytes) -> dict:
    try:
        msg = orjson.loads(data)
    except orjson.JSONDecodeError:
        # orjson rejects NaN/Infinity literals; the standard parser reads them, so the
        # field check can name the non-finite field instead of calling the message invalid
        msg = _decode_std(path, topic, index, data)
    if not isinstance(msg, dict):
        raise InputError(path, f"message #{index} is not a JSON object", topic=topic)
    return msg


def _decode_std(path: Path, topic: str, index: int, data: bytes) -> Any:
    try:
        msg = json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(path, f"message #{index} is not valid JSON ({e})", topic=topic) from None
    return msg


_NUM = (int, float)


def _pose_fast(msg: dict) -> tuple[int, float, float, float] | None:
    """The common, valid case without per-field bookkeeping; None sends the message to ``_pose``,
    which names the exact problem."""
    try:
        ts, pose = msg["timestamp"], msg["pose"]
        sec, nsec = ts["sec"], ts["nsec"]
        pos, q = pose["position"], pose["orientation"]
        x, y, qx, qy, qz, qw = pos["x"], pos["y"], q["x"], q["y"], q["z"], q["w"]
    except (KeyError, TypeError):
        return None
    if type(sec) is not int or type(nsec) is not int:
        return None
    for v in (x, y, qx, qy, qz, qw):
        if type(v) not in _NUM or not math.isfinite(v):
            return None
    n = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    if abs(n - 1.0) > QUATERNION_NORM_TOL:
        return None
    qx, qy, qz, qw = qx / n, qy / n, qz / n, qw / n
    return sec * 1_000_000_000 + nsec, float(x), float(y), math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))


def _readings_fast(msg: dict) -> tuple[int, dict[str, float]] | None:
    try:
        ts = msg["timestamp"]
        sec, nsec = ts["sec"], ts["nsec"]
        items = msg["readings"]
        r: dict[str, float] = {}
        for item in items:
            b, v = item["bssid"], item["rssi"]
            if type(b) is not str or not b or type(v) not in _NUM or not math.isfinite(v):
                return None
            if v > r.get(b, -math.inf):  # a BSSID twice in one scan: keep the stronger reading
                r[b] = float(v)
    except (KeyError, TypeError):
        return None
    if type(sec) is not int or type(nsec) is not int:
        return None
    return sec * 1_000_000_000 + nsec, r


def _pose(p: _Parse, msg: dict, log_time: int) -> tuple[int, float, float, float]:
    fast = _pose_fast(msg)
    if fast is not None:
        return fast
    t = p.stamp(msg, log_time)
    x = p.number(msg, "pose.position.x")
    y = p.number(msg, "pose.position.y")
    q = [p.number(msg, f"pose.orientation.{k}") for k in "xyzw"]
    n = math.sqrt(sum(c * c for c in q))
    if abs(n - 1.0) > QUATERNION_NORM_TOL:
        raise p.fail("pose.orientation", f"quaternion is not unit (norm {n:.6f})")
    qx, qy, qz, qw = (c / n for c in q)
    h = math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
    return t, x, y, h


def _scan_slow(p: _Parse, msg: dict, log_time: int) -> tuple[int, dict[str, float]]:
    t = p.stamp(msg, log_time)
    readings = p.get(msg, "readings")
    if not isinstance(readings, list):
        raise p.fail("readings", "expected an array")
    r: dict[str, float] = {}
    for j, item in enumerate(readings):
        if not isinstance(item, dict):
            raise p.fail(f"readings[{j}]", "expected an object")
        bssid = item.get("bssid")
        if not isinstance(bssid, str) or not bssid:
            raise p.fail(f"readings[{j}].bssid", f"expected a non-empty string, got {bssid!r}")
        value = item.get("rssi")
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise p.fail(f"readings[{j}].rssi", f"missing or non-finite rssi: {value!r}")
        r[bssid] = max(float(value), r.get(bssid, -math.inf))
    return t, r


def _track(path: Path, topic: str, rows: list[tuple[int, float, float, float]]) -> PoseTrack:
    a = np.array(rows, dtype=float).reshape(-1, 4)
    t = np.array([r[0] for r in rows], dtype=np.int64)
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise InputError(
            path,
            f"message #{i}: time does not increase ({t[i]} ns after {t[i - 1]} ns)",
            topic=topic,
            field="timestamp",
        )
    return PoseTrack(t, a[:, 1:3], a[:, 3])


def _check_schema(path: Path, topic: str, schema: Any, channel: Any) -> None:
    expected_name = TOPIC_SCHEMAS[topic][0]
    if schema is None or schema.name != expected_name:
        got = None if schema is None else schema.name
        raise InputError(path, f"schema is {got!r}, expected {expected_name!r}", topic=topic, field="schema")
    if channel.message_encoding != "json":
        raise InputError(
            path, f"message encoding {channel.message_encoding!r}, expected 'json'", topic=topic, field="encoding"
        )


def read_session(path: str | Path) -> Session:
    """Read one recording. Raises ``InputError`` on anything that breaks the contract."""
    path = Path(path)
    try:
        with path.open("rb") as fh:
            if fh.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
                raise InputError(path, "not an MCAP file (bad magic bytes)")
            fh.seek(0)
            return _read(path, fh)
    except InputError:
        raise
    except IsADirectoryError:
        raise InputError(path, "is a folder, expected an .mcap file") from None
    except OSError as e:
        raise InputError(path, f"cannot read: {e.strerror or e}") from None
    except (McapError, struct.error, ValueError, EOFError) as e:
        # The mcap library reports truncation as e.g. RecordLengthLimitExceeded with
        # a meaningless length; name the real cause instead.
        raise InputError(path, f"damaged or truncated MCAP file ({type(e).__name__}: {e})") from None


def _read(path: Path, fh: Any) -> Session:
    reader = make_reader(fh)
    meta: dict[str, str] = {}
    anchor_meta: dict[str, str] = {}
    for m in reader.iter_metadata():
        if m.name == SESSION_METADATA:
            meta = dict(m.metadata)
        elif m.name == UWB_ANCHORS_METADATA:
            anchor_meta = dict(m.metadata)
    uwb_rows: list[uwb_io.UwbRow] = []
    steps: list[tuple[int, float, float, float]] = []
    truth: list[tuple[int, float, float, float]] = []
    scans: list[Scan] = []
    marks: list[LandmarkMark] = []
    counts = {t: 0 for t in TOPIC_SCHEMAS}
    checked: set[int] = set()
    last_scan_t = -1
    for schema, channel, message in reader.iter_messages(log_time_order=False):
        topic = channel.topic
        if topic not in TOPIC_SCHEMAS:
            continue  # the contract allows extra topics
        if channel.id not in checked:
            _check_schema(path, topic, schema, channel)
            checked.add(channel.id)
        i = counts[topic]
        counts[topic] += 1
        p = _Parse(path, topic, i)
        msg = _decode(path, topic, i, message.data)
        if topic == TOPIC_POSE:
            steps.append(_pose(p, msg, message.log_time))
        elif topic == TOPIC_GROUND_TRUTH:
            truth.append(_pose(p, msg, message.log_time))
        elif topic == TOPIC_SCAN:
            fast = _readings_fast(msg)
            t, r = fast if fast is not None else _scan_slow(p, msg, message.log_time)
            if t < last_scan_t:
                raise p.fail("timestamp", f"time goes backwards ({t} ns after {last_scan_t} ns)")
            last_scan_t = t
            scans.append(Scan(t, r))
        elif topic == TOPIC_LANDMARKS:
            t = p.stamp(msg, message.log_time)
            marks.append(LandmarkMark(t, p.string(msg, "landmark_id"), p.number(msg, "x"), p.number(msg, "y")))
        elif topic == TOPIC_UWB_RANGE:
            uwb_rows.append(uwb_io.decode_range(path, i, msg))
    if not steps:
        raise InputError(path, "no step poses: topic missing or empty", topic=TOPIC_POSE)
    session_id = str(meta.get("session_id") or path.stem)
    anchors = uwb_io.parse_anchors(path, anchor_meta)
    tag_id = uwb_io.uwb_id(path, meta)
    return Session(
        session_id=session_id,
        steps=_track(path, TOPIC_POSE, steps),
        scans=tuple(scans),
        landmarks=tuple(sorted(marks, key=lambda m: m.t_ns)),
        ground_truth=_track(path, TOPIC_GROUND_TRUTH, truth) if truth else None,
        site=str(meta.get("site", "")),
        floor=str(meta.get("floor", "")),
        source=str(path),
        uwb_id=tag_id,
        uwb_ranges=uwb_io.ranges(path, uwb_rows, anchors, tag_id),
        uwb_anchors=anchors,
    )


def read_sessions(paths: Sequence[str | Path]) -> list[Session]:
    return list(read_survey(paths).sessions)
