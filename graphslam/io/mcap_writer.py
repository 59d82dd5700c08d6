"""Write sessions (and aligned trajectories) as MCAP in the survey recording format."""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np
import orjson
from mcap.records import Channel, Schema
from mcap.writer import CompressionType, Writer

from graphslam.core.types import PoseTrack, Session
from graphslam.io.atomic import atomic_open
from graphslam.io.mcap_bulk import write_bulk
from graphslam.io.schemas import (
    SESSION_METADATA,
    TOPIC_GROUND_TRUTH,
    TOPIC_HEADING,
    TOPIC_MAGNETIC,
    TOPIC_LANDMARKS,
    TOPIC_POSE,
    TOPIC_SCAN,
    TOPIC_SCHEMAS,
    TOPIC_UWB_RANGE,
    UWB_ANCHORS_METADATA,
    schema_bytes,
)
from graphslam.io.uwb_io import anchors_metadata, range_messages


NSEC = 1_000_000_000


def _stamp(t_ns: int) -> dict:
    return {"sec": int(t_ns // 1_000_000_000), "nsec": int(t_ns % 1_000_000_000)}


# One pose message as orjson writes {"timestamp": _stamp(t), "frame_id": ..., "pose": {"position":
# {x, y, z: 0.0}, "orientation": heading_to_quaternion(heading)}} (keys in this order, no spaces).
_POSE_JSON = (b'{"timestamp":{"sec":%d,"nsec":%d},"frame_id":%s,"pose":{"position":{"x":%s,"y":%s,"z":0.0},'
              b'"orientation":{"x":0.0,"y":0.0,"z":%s,"w":%s}}}')


def _float_texts(a: np.ndarray) -> list[bytes]:
    """Each value as ``orjson.dumps`` writes it alone: one call for all of them, split at the commas."""
    return orjson.dumps(a.tolist())[1:-1].split(b",") if len(a) else []


def _pose_msgs(track: PoseTrack, frame_id: str) -> list[tuple[int, bytes]]:
    """Every pose's message, the bytes of ``orjson.dumps`` of its dict: formatted from the arrays'
    float texts (why: one dict and one dumps per pose cost 0.85 s of CPU for 103k poses; this, 0.2 s).
    The quaternion is ``heading_to_quaternion``'s, element-wise (numpy's sin and cos of an array
    equal those of its elements)."""
    half = track.heading / 2.0
    frame = orjson.dumps(frame_id)
    texts = zip(track.t_ns.tolist(), _float_texts(track.xy[:, 0]), _float_texts(track.xy[:, 1]),
                _float_texts(np.sin(half)), _float_texts(np.cos(half)))
    return [(t, _POSE_JSON % (t // NSEC, t % NSEC, frame, x, y, z, w)) for t, x, y, z, w in texts]


class _Channels:
    def __init__(self, writer: Writer) -> None:
        self.writer = writer
        self.schemas: dict[str, int] = {}
        self.channels: dict[str, int] = {}

    def channel(self, topic: str, schema_name: str | None = None, schema: dict | None = None) -> int:
        if topic not in self.channels:
            if schema_name is None:
                schema_name, schema = TOPIC_SCHEMAS[topic]
            if schema_name not in self.schemas:
                self.schemas[schema_name] = self.writer.register_schema(
                    name=schema_name, encoding="jsonschema", data=schema_bytes(schema or {})
                )
            self.channels[topic] = self.writer.register_channel(
                topic=topic, message_encoding="json", schema_id=self.schemas[schema_name]
            )
        return self.channels[topic]

    def add(self, channel_id: int, t_ns: int, data: bytes) -> None:
        self.writer.add_message(channel_id=channel_id, log_time=int(t_ns), publish_time=int(t_ns), data=data)


def write_session(session: Session, path: str | Path) -> Path:
    """Write ``session`` to ``path`` (atomically), including landmarks and ground truth if present."""
    path = Path(path)
    with atomic_open(path, "wb") as fh:
        writer = Writer(fh, compression=CompressionType.ZSTD, enable_data_crcs=True)
        writer.start(profile="", library="graphslam")
        ch = _Channels(writer)
        meta = {"session_id": session.session_id, "site": session.site, "floor": session.floor}
        if session.uwb_id:
            meta["uwb_id"] = session.uwb_id
        writer.add_metadata(SESSION_METADATA, meta)
        if session.uwb_anchors:
            writer.add_metadata(UWB_ANCHORS_METADATA, anchors_metadata(session))
        events: list[tuple[int, int, bytes]] = []
        pose_ch = ch.channel(TOPIC_POSE)
        events += [(t, pose_ch, d) for t, d in _pose_msgs(session.steps, "fmip")]
        scan_ch = ch.channel(TOPIC_SCAN)
        for s in session.scans:
            body = {
                "timestamp": _stamp(s.t_ns),
                "readings": [{"bssid": b, "rssi": r} for b, r in s.readings.items()],
            }
            events.append((s.t_ns, scan_ch, orjson.dumps(body)))
        if session.landmarks:
            lm_ch = ch.channel(TOPIC_LANDMARKS)
            for m in session.landmarks:
                body = {"timestamp": _stamp(m.t_ns), "landmark_id": m.landmark_id, "x": m.x, "y": m.y}
                events.append((m.t_ns, lm_ch, orjson.dumps(body)))
        if session.ground_truth is not None:
            gt_ch = ch.channel(TOPIC_GROUND_TRUTH)
            events += [(t, gt_ch, d) for t, d in _pose_msgs(session.ground_truth, "site")]
        if session.heading is not None:
            hd_ch = ch.channel(TOPIC_HEADING)
            for t, yaw in zip(session.heading.t_ns.tolist(), session.heading.yaw.tolist()):
                events.append((t, hd_ch, orjson.dumps({"timestamp": _stamp(t), "yaw": yaw})))
        if session.magnetic is not None:
            mg_ch = ch.channel(TOPIC_MAGNETIC)
            for t, (e, n, u) in zip(session.magnetic.t_ns.tolist(), session.magnetic.enu.tolist()):
                events.append((t, mg_ch, orjson.dumps({"timestamp": _stamp(t), "east": e, "north": n, "up": u})))
        if session.uwb_ranges is not None:
            uwb_ch = ch.channel(TOPIC_UWB_RANGE)
            events += [(t, uwb_ch, orjson.dumps(body)) for t, body in range_messages(session)]
        for t, c, d in sorted(events, key=lambda e: (e[0], e[1])):
            ch.add(c, t, d)
        writer.finish()
    return path


def write_aligned(
    tracks: dict[str, PoseTrack], path: str | Path, frame_id: str = "aligned",
    frame_ids: Mapping[str, str] | None = None,
) -> Path:
    """One ``foxglove.PoseInFrame`` topic per session (``/aligned/<session_id>``), viewable in Foxglove;
    every pose's ``frame_id`` is ``frame_ids[session_id]`` where given, else ``frame_id``.
    The messages are serialised in bulk (``graphslam.io.mcap_bulk``): the same bytes as mcap's Writer."""
    frames = {sid: (frame_ids or {}).get(sid, frame_id) for sid in tracks}
    if not tracks:  # no channel, hence no schema either: the Writer's file
        return _write_aligned_by_writer(tracks, path, frame_id)
    name, schema = TOPIC_SCHEMAS[TOPIC_POSE]
    channels, times, ids, data = [], [], [], []
    for k, (sid, track) in enumerate(tracks.items(), start=1):
        channels.append(Channel(id=k, topic=f"/aligned/{sid}", message_encoding="json", schema_id=1, metadata={}))
        times.append(np.asarray(track.t_ns, np.int64))
        ids.append(np.full(len(track.t_ns), k, np.int64))
        data += [d for _, d in _pose_msgs(track, frames[sid])]
    t, c = np.concatenate(times), np.concatenate(ids)
    order = np.lexsort((c, t))  # by time, then channel; stable, as the Writer's sorted events
    path = Path(path)
    with atomic_open(path, "wb") as fh:
        write_bulk(fh, Schema(id=1, name=name, encoding="jsonschema", data=schema_bytes(schema)), channels,
                   c[order], t[order], [data[i] for i in order.tolist()], library="graphslam")
    return path


def _write_aligned_by_writer(
    tracks: dict[str, PoseTrack], path: str | Path, frame_id: str = "aligned",
    frame_ids: Mapping[str, str] | None = None,
) -> Path:
    """``write_aligned`` through mcap's Writer, one call per pose (the reference ``write_bulk`` matches)."""
    path = Path(path)
    with atomic_open(path, "wb") as fh:
        writer = Writer(fh, compression=CompressionType.ZSTD, enable_data_crcs=True)
        writer.start(profile="", library="graphslam")
        ch = _Channels(writer)
        name, schema = TOPIC_SCHEMAS[TOPIC_POSE]
        events = []
        for sid, track in tracks.items():
            c = ch.channel(f"/aligned/{sid}", name, schema)
            events += [(t, c, d) for t, d in _pose_msgs(track, (frame_ids or {}).get(sid, frame_id))]
        for t, c, d in sorted(events, key=lambda e: (e[0], e[1])):
            ch.add(c, t, d)
        writer.finish()
    return path


