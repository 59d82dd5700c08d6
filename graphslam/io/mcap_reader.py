"""Read survey recordings (one MCAP file per session) into checked ``Session`` objects.

Every violation of DATA_CONTRACT.md, and every damaged or truncated file (CRCs checked,
``graphslam.io.mcap_container``), raises ``InputError`` naming file, topic and field.

Reading goes container -> per-topic message lists -> one decoder per topic (``DECODERS``).
Each decoder first tries a vectorised pass over all of the topic's messages that accepts
only certainly valid input; anything it refuses goes through the per-message checks, which
name the message and field at fault.
"""

from __future__ import annotations

import gc
import json
import logging
import math
import sys
from contextlib import contextmanager
from dataclasses import dataclass
from itertools import chain
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Mapping, Sequence

import numpy as np
import orjson

from graphslam.core.progress import progress_over
from graphslam.core.types import (
    HeadingTrack, LandmarkMark, MagneticTrack, PoseTrack, Scan, Session, Survey, shared_floats, wrap_angle,
)
from graphslam.errors import InputError
from graphslam.io.mcap_container import DamagedMcap, McapContents, TopicMessages, read_mcap
from graphslam.io import uwb_io
from graphslam.io.paths import expand_paths
from graphslam.io.recording_cache import RecordingCache, recording_key
from graphslam.io.schemas import (
    MCAP_MAGIC,
    SESSION_METADATA,
    TOPIC_GROUND_TRUTH,
    TOPIC_HEADING,
    TOPIC_LANDMARKS,
    TOPIC_MAGNETIC,
    TOPIC_POSE,
    TOPIC_SCAN,
    TOPIC_SCHEMAS,
    TOPIC_UWB_RANGE,
    UWB_ANCHORS_METADATA,
)

log = logging.getLogger(__name__)

QUATERNION_NORM_TOL = 1e-3
NSEC_PER_SEC = 1_000_000_000
MAX_SEC = (2**63 - 1) // NSEC_PER_SEC - 1  # sec * 1e9 + nsec must fit in int64


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
    return read_recordings(paths).survey


@dataclass(frozen=True, eq=False)
class Recordings:
    """A survey as read, with each walk's file key (``recording_cache.recording_key``, by session id)."""

    survey: Survey
    keys: Mapping[str, str]
    cached: int = 0  # walks taken from the cache


def read_recordings(paths: Iterable[str | Path], cache: RecordingCache | None = None) -> Recordings:
    """``read_survey``, keeping each file's key; a file whose key ``cache`` holds is taken from it,
    not parsed (``graphslam.io.recording_cache``)."""
    files = expand_paths(paths)
    sessions, keys, cached = [], [], 0
    for f in progress_over(files, "read", unit="files"):
        buf = _file_bytes(f)
        key = recording_key(buf)
        s = None
        if cache is not None:
            with _gc_paused():  # as the parser: thousands of readings' dicts, nothing to collect
                s = cache.session(key, f)
        cached += s is not None
        sessions.append(s if s is not None else _parse_session(f, buf))
        keys.append(key)
    if cache is not None:
        log.info("read %d recordings, %d of them from the cache", len(files), cached)
    survey = _checked_survey(sessions)
    return Recordings(survey, {s.session_id: k for s, k in zip(sessions, keys)}, cached)


def _checked_survey(sessions: list[Session]) -> Survey:
    by_id: dict[str, Session] = {}
    for s in sessions:
        if s.session_id in by_id:
            raise InputError(
                s.source,
                f"duplicate session id {s.session_id!r} (also in {by_id[s.session_id].source})",
                field="graphslam.session.session_id",
            )
        by_id[s.session_id] = s
    uwb_io.check_survey(sessions)  # UWB: anchors agree between files, uwb_id unique
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
        try:
            f = float(v)
        except OverflowError:  # an integer literal beyond float range
            raise self.fail(field, "number out of range") from None
        if not math.isfinite(f):
            raise self.fail(field, f"non-finite value {v}")
        return f

    def string(self, obj: Any, field: str) -> str:
        v = self.get(obj, field)
        if not isinstance(v, str) or not v:
            raise self.fail(field, "expected a non-empty string")
        return v

    def stamp(self, obj: Any) -> int:
        sec = self.get(obj, "timestamp.sec")
        nsec = self.get(obj, "timestamp.nsec")
        for name, v, hi in (("timestamp.sec", sec, MAX_SEC), ("timestamp.nsec", nsec, NSEC_PER_SEC - 1)):
            if isinstance(v, bool) or not isinstance(v, int):
                raise self.fail(name, f"expected an integer, got {v!r}")
            if not 0 <= v <= hi:
                raise self.fail(name, f"{v} outside [0, {hi}]")
        return sec * NSEC_PER_SEC + nsec


def _objects(path: Path, topic: str, data: list[bytes]) -> list[dict]:
    """Every message of a topic as a JSON object."""
    try:
        objs = list(map(orjson.loads, data))
    except orjson.JSONDecodeError:
        objs = [_decode(path, topic, i, d) for i, d in enumerate(data)]
    if not all(type(o) is dict for o in objs):
        i = next(i for i, o in enumerate(objs) if type(o) is not dict)
        raise InputError(path, f"message #{i} is not a JSON object", topic=topic)
    return objs


def _decode(path: Path, topic: str, index: int, data: bytes) -> Any:
    try:
        return orjson.loads(data)
    except orjson.JSONDecodeError:
        pass
    # orjson rejects NaN/Infinity literals; the standard parser reads them, so the field
    # check can name the non-finite field instead of calling the message invalid.
    try:
        return json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(path, f"message #{index} is not valid JSON ({e})", topic=topic) from None
    except RecursionError:
        raise InputError(path, f"message #{index} is not valid JSON (nested too deeply)", topic=topic) from None


_NUMBERS = frozenset({int, float})
_INTS = frozenset({int})


def _stamps_fast(objs: list[dict]) -> np.ndarray | None:
    """int64 ns of every message's ``timestamp``, or None unless all are certainly valid."""
    ts = [m["timestamp"] for m in objs]
    sec = [t["sec"] for t in ts]
    nsec = [t["nsec"] for t in ts]
    if not (set(map(type, sec)) | set(map(type, nsec))) <= _INTS:
        return None
    try:
        s, ns = np.array(sec, np.int64), np.array(nsec, np.int64)
    except OverflowError:
        return None
    if s.size and (s.min() < 0 or s.max() > MAX_SEC or ns.min() < 0 or ns.max() >= NSEC_PER_SEC):
        return None
    return s * NSEC_PER_SEC + ns


def _finite(values: list[Any]) -> np.ndarray | None:
    if not set(map(type, values)) <= _NUMBERS:
        return None  # bool, str, None, ... -> the per-message path names it
    try:
        a = np.array(values, np.float64)
    except OverflowError:
        return None
    return a if np.isfinite(a).all() else None


def _heading(q: np.ndarray) -> np.ndarray:
    """Heading (rad) of unit quaternions, rows (x, y, z, w)."""
    qx, qy, qz, qw = q.T
    return np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))


def _poses_fast(objs: list[dict]) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    try:
        t = _stamps_fast(objs)
        poses = [m["pose"] for m in objs]
        pos = [p["position"] for p in poses]
        ori = [p["orientation"] for p in poses]
        xy = [p["x"] for p in pos] + [p["y"] for p in pos]
        q = [o["x"] for o in ori] + [o["y"] for o in ori] + [o["z"] for o in ori] + [o["w"] for o in ori]
    except (KeyError, TypeError):
        return None
    a, b = _finite(xy), _finite(q)
    if t is None or a is None or b is None:
        return None
    n = len(objs)
    quat = b.reshape(4, n).T
    norm = np.sqrt((quat * quat).sum(axis=1))
    if (np.abs(norm - 1.0) > QUATERNION_NORM_TOL).any():
        return None
    return t, a.reshape(2, n).T, _heading(quat / norm[:, None])


def _pose(p: _Parse, msg: dict) -> tuple[int, float, float, float]:
    t = p.stamp(msg)
    x = p.number(msg, "pose.position.x")
    y = p.number(msg, "pose.position.y")
    q = np.array([p.number(msg, f"pose.orientation.{k}") for k in "xyzw"])
    n = float(np.sqrt((q * q).sum()))
    if abs(n - 1.0) > QUATERNION_NORM_TOL:
        raise p.fail("pose.orientation", f"quaternion is not unit (norm {n:.6f})")
    return t, x, y, float(_heading((q / n)[None, :])[0])


def _poses(path: Path, topic: str, msgs: TopicMessages) -> PoseTrack:
    objs = _objects(path, topic, msgs.data)
    fast = _poses_fast(objs)
    if fast is None:  # some message is not certainly valid: check one by one (raises at the bad one)
        rows = [_pose(_Parse(path, topic, i), m) for i, m in enumerate(objs)]
        fast = (
            np.array([r[0] for r in rows], np.int64),
            np.array([r[1:3] for r in rows], np.float64).reshape(-1, 2),
            np.array([r[3] for r in rows], np.float64),
        )
    t, xy, h = fast
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        problem = f"message #{i}: time does not increase ({t[i]} ns after {t[i - 1]} ns)"
        raise InputError(path, problem, topic=topic, field="timestamp")
    _log_time_mismatch(path, topic, t, msgs)
    return PoseTrack(t, xy, h)


def _scans_fast(objs: list[dict]) -> tuple[np.ndarray, list[dict[str, float]]] | None:
    try:
        t = _stamps_fast(objs)
        readings = [m["readings"] for m in objs]
        if not set(map(type, readings)) <= {list}:
            return None
        items = list(chain.from_iterable(readings))
        bssids = [r["bssid"] for r in items]
        rssi = [r["rssi"] for r in items]
    except (KeyError, TypeError):
        return None
    values = _finite(rssi)
    if t is None or values is None or not set(map(type, bssids)) <= {str} or "" in bssids:
        return None
    bssids = list(map(sys.intern, bssids))
    out: list[dict[str, float]] = []
    vals = shared_floats(values)
    i = 0
    for r in readings:
        j = i + len(r)
        d = dict(zip(bssids[i:j], vals[i:j]))
        if len(d) != j - i:  # a BSSID twice in one scan: keep the stronger reading
            d = {}
            for b, v in zip(bssids[i:j], vals[i:j]):
                if v > d.get(b, -math.inf):
                    d[b] = v
        out.append(d)
        i = j
    return t, out


def _scan(p: _Parse, msg: dict) -> tuple[int, dict[str, float]]:
    t = p.stamp(msg)
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
        try:
            v = math.nan if isinstance(value, bool) or not isinstance(value, (int, float)) else float(value)
        except OverflowError:  # an integer literal beyond float range
            v = math.nan
        if not math.isfinite(v):
            raise p.fail(f"readings[{j}].rssi", f"missing or non-finite rssi: {value!r}")
        r[sys.intern(bssid)] = max(v, r.get(bssid, -math.inf))
    return t, r


def _scans(path: Path, topic: str, msgs: TopicMessages) -> tuple[Scan, ...]:
    objs = _objects(path, topic, msgs.data)
    fast = _scans_fast(objs)
    if fast is None:
        rows = [_scan(_Parse(path, topic, i), m) for i, m in enumerate(objs)]
        fast = np.array([r[0] for r in rows], np.int64), [r[1] for r in rows]
    t, readings = fast
    back = np.flatnonzero(np.diff(t) < 0)  # equal times are allowed (two scanners, one instant)
    if back.size:
        i = int(back[0]) + 1
        raise _Parse(path, topic, i).fail("timestamp", f"time goes backwards ({t[i]} ns after {t[i - 1]} ns)")
    _log_time_mismatch(path, topic, t, msgs)
    # both paths above checked every BSSID (non-empty str) and RSS (finite float)
    return tuple(map(Scan._validated, t.tolist(), readings))


def _landmarks(path: Path, topic: str, msgs: TopicMessages) -> tuple[LandmarkMark, ...]:
    marks = []
    for i, m in enumerate(_objects(path, topic, msgs.data)):
        p = _Parse(path, topic, i)
        marks.append(LandmarkMark(p.stamp(m), p.string(m, "landmark_id"), p.number(m, "x"), p.number(m, "y")))
    return tuple(sorted(marks, key=lambda m: m.t_ns))


def _headings(path: Path, topic: str, msgs: TopicMessages) -> HeadingTrack:
    """``/phone/heading``: one yaw (rad, CCW from east) per message, time strictly increasing."""
    objs = _objects(path, topic, msgs.data)
    try:
        t, yaw = _stamps_fast(objs), _finite([m["yaw"] for m in objs])
    except (KeyError, TypeError):
        t = yaw = None
    if t is None or yaw is None:  # some message is not certainly valid: check one by one
        rows = [(p.stamp(m), p.number(m, "yaw")) for p, m in ((_Parse(path, topic, i), m) for i, m in enumerate(objs))]
        t = np.array([r[0] for r in rows], np.int64)
        yaw = np.array([r[1] for r in rows], np.float64)
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise _Parse(path, topic, i).fail("timestamp", f"time does not increase ({t[i]} ns after {t[i - 1]} ns)")
    _log_time_mismatch(path, topic, t, msgs)
    return HeadingTrack(t, wrap_angle(yaw))


def _magnetic(path: Path, topic: str, msgs: TopicMessages) -> MagneticTrack:
    """``/phone/magnetic``: the field (east, north, up; µT) per message, time strictly increasing."""
    objs = _objects(path, topic, msgs.data)
    try:
        t = _stamps_fast(objs)
        enu = _finite([m["east"] for m in objs] + [m["north"] for m in objs] + [m["up"] for m in objs])
    except (KeyError, TypeError):
        t = enu = None
    if t is None or enu is None:  # some message is not certainly valid: check one by one
        rows = [(p.stamp(m), p.number(m, "east"), p.number(m, "north"), p.number(m, "up"))
                for p, m in ((_Parse(path, topic, i), m) for i, m in enumerate(objs))]
        t = np.array([r[0] for r in rows], np.int64)
        b = np.array([r[1:] for r in rows], np.float64).reshape(-1, 3)
    else:
        b = enu.reshape(3, len(objs)).T
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise _Parse(path, topic, i).fail("timestamp", f"time does not increase ({t[i]} ns after {t[i - 1]} ns)")
    _log_time_mismatch(path, topic, t, msgs)
    return MagneticTrack(t, b)


def _log_time_mismatch(path: Path, topic: str, t: np.ndarray, msgs: TopicMessages) -> None:
    if not log.isEnabledFor(logging.DEBUG):
        return
    n = int((t != np.array(msgs.log_times, np.uint64).astype(np.int64)).sum()) if len(t) else 0
    if n:
        log.debug("%s %s: %d messages whose log_time differs from their timestamp", path, topic, n)


def _uwb_ranges(path: Path, topic: str, msgs: TopicMessages) -> list[uwb_io.UwbRow]:
    """Every ``/uwb/range`` message (file order), checked field by field (graphslam.io.uwb_io)."""
    return [uwb_io.decode_range(path, i, m) for i, m in enumerate(_objects(path, topic, msgs.data))]


# topic -> decoder of all its messages (file order). A new topic: its schema in
# graphslam.io.schemas.TOPIC_SCHEMAS, its decoder here, its field in Session (read_session).
DECODERS: dict[str, Callable[[Path, str, TopicMessages], Any]] = {
    TOPIC_POSE: _poses,
    TOPIC_SCAN: _scans,
    TOPIC_LANDMARKS: _landmarks,
    TOPIC_GROUND_TRUTH: _poses,
    TOPIC_UWB_RANGE: _uwb_ranges,
    TOPIC_HEADING: _headings,
    TOPIC_MAGNETIC: _magnetic,
}


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
    """Read one recording. Raises ``InputError`` on anything that breaks the contract or
    a damaged file (every CRC it carries is checked)."""
    path = Path(path)
    return _parse_session(path, _file_bytes(path))


def _file_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except IsADirectoryError:
        raise InputError(path, "is a folder, expected an .mcap file") from None
    except OSError as e:
        raise InputError(path, f"cannot read: {e.strerror or e}") from None


def _parse_session(path: Path, buf: bytes) -> Session:
    if buf[: len(MCAP_MAGIC)] != MCAP_MAGIC:
        raise InputError(path, "not an MCAP file (bad magic bytes)")
    with _gc_paused():
        try:
            contents = read_mcap(buf, DECODERS)
        except DamagedMcap as e:
            raise InputError(path, f"damaged or truncated MCAP file: {e}") from None
        return _session(path, contents)


@contextmanager
def _gc_paused() -> Iterator[None]:
    """Decoding creates ~10 dicts per message and keeps them all alive; the cyclic GC's
    collections find nothing to free and cost about half the decoding time (paper --size 4).
    Reference counting still frees everything; the GC's previous state is restored."""
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


def _session(path: Path, contents: McapContents) -> Session:
    decoded: dict[str, Any] = {}
    for topic, msgs in contents.topics.items():
        for ch in msgs.channels:
            _check_schema(path, topic, contents.schemas.get(ch.schema_id), ch)
        decoded[topic] = DECODERS[topic](path, topic, msgs)
    if TOPIC_POSE not in decoded:
        raise InputError(path, "no step poses: topic missing or empty", topic=TOPIC_POSE)
    meta = contents.metadata.get(SESSION_METADATA, {})
    anchors = uwb_io.parse_anchors(path, contents.metadata.get(UWB_ANCHORS_METADATA, {}))
    tag_id = uwb_io.uwb_id(path, meta)
    return Session(
        session_id=str(meta.get("session_id") or path.stem),
        steps=decoded[TOPIC_POSE],
        scans=decoded.get(TOPIC_SCAN, ()),
        landmarks=decoded.get(TOPIC_LANDMARKS, ()),
        ground_truth=decoded.get(TOPIC_GROUND_TRUTH),
        site=str(meta.get("site", "")),
        floor=str(meta.get("floor", "")),
        source=str(path),
        uwb_id=tag_id,
        uwb_ranges=uwb_io.ranges(path, decoded.get(TOPIC_UWB_RANGE, []), anchors, tag_id),
        uwb_anchors=anchors,
        heading=decoded.get(TOPIC_HEADING),
        magnetic=decoded.get(TOPIC_MAGNETIC),
    )


def read_sessions(paths: Sequence[str | Path]) -> list[Session]:
    return list(read_survey(paths).sessions)
