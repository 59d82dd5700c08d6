"""Topic names and JSON schemas of the survey recording format (DATA_CONTRACT.md)."""

from __future__ import annotations

import json

MCAP_MAGIC = b"\x89MCAP0\r\n"
SESSION_METADATA = "graphslam.session"
UWB_ANCHORS_METADATA = "graphslam.uwb_anchors"  # anchor id -> JSON "[x, y]" or "[x, y, z]" (site frame, m)

TOPIC_POSE = "/fmip/pose"
TOPIC_SCAN = "/wifi/scan"
TOPIC_LANDMARKS = "/landmarks"
TOPIC_GROUND_TRUTH = "/ground_truth/pose"
TOPIC_UWB_RANGE = "/uwb/range"
TOPIC_HEADING = "/phone/heading"
TOPIC_MAGNETIC = "/phone/magnetic"

_TIME = {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}}
_XYZ = {"type": "object", "properties": {k: {"type": "number"} for k in "xyz"}}
_XYZW = {"type": "object", "properties": {k: {"type": "number"} for k in "xyzw"}}

POSE_IN_FRAME = {
    "title": "foxglove.PoseInFrame",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "frame_id": {"type": "string"},
        "pose": {"type": "object", "properties": {"position": _XYZ, "orientation": _XYZW}},
    },
}
WIFI_SCAN = {
    "title": "graphslam.WifiScan",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "readings": {
            "type": "array",
            "items": {
                "type": "object",
                "properties": {
                    "bssid": {"type": "string"},
                    "rssi": {"type": "number"},
                    "ssid": {"type": "string"},
                    "frequency_mhz": {"type": "integer"},
                },
                "required": ["bssid", "rssi"],
            },
        },
    },
    "required": ["timestamp", "readings"],
}
LANDMARK_MARK = {
    "title": "graphslam.LandmarkMark",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "landmark_id": {"type": "string"},
        "x": {"type": "number"},
        "y": {"type": "number"},
    },
    "required": ["timestamp", "landmark_id", "x", "y"],
}

UWB_RANGE = {
    "title": "graphslam.UwbRange",
    "type": "object",
    "properties": {
        "timestamp": _TIME,
        "responder_id": {"type": "string"},
        "responder_kind": {"type": "string", "enum": ["anchor", "tag"]},
        "range_m": {"type": "number", "minimum": 0},
    },
    "required": ["timestamp", "responder_id", "responder_kind", "range_m"],
}

HEADING = {
    "title": "graphslam.Heading",
    "type": "object",
    "properties": {"timestamp": _TIME, "yaw": {"type": "number"}},
    "required": ["timestamp", "yaw"],
}

MAGNETIC_FIELD = {
    "title": "graphslam.MagneticField",
    "type": "object",
    "properties": {"timestamp": _TIME, "east": {"type": "number"}, "north": {"type": "number"}, "up": {"type": "number"}},
    "required": ["timestamp", "east", "north", "up"],
}

# topic -> (schema name, schema)
TOPIC_SCHEMAS: dict[str, tuple[str, dict]] = {
    TOPIC_POSE: ("foxglove.PoseInFrame", POSE_IN_FRAME),
    TOPIC_SCAN: ("graphslam.WifiScan", WIFI_SCAN),
    TOPIC_LANDMARKS: ("graphslam.LandmarkMark", LANDMARK_MARK),
    TOPIC_GROUND_TRUTH: ("foxglove.PoseInFrame", POSE_IN_FRAME),
    TOPIC_UWB_RANGE: ("graphslam.UwbRange", UWB_RANGE),
    TOPIC_HEADING: ("graphslam.Heading", HEADING),
    TOPIC_MAGNETIC: ("graphslam.MagneticField", MAGNETIC_FIELD),
}


def schema_bytes(schema: dict) -> bytes:
    return json.dumps(schema).encode()
