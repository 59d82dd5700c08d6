"""The UWB part of the recording format (docs/data_format.md): ``/uwb/range`` messages, the
``uwb_id`` of ``graphslam.session`` and the ``graphslam.uwb_anchors`` metadata record.

Self-contained so the MCAP reader calls it through a few lines: one decoder per message,
one parser per metadata record, one check over the survey. Every problem is an
``InputError`` naming the file and the field.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from graphslam.core.types import Session, UwbRanges
from graphslam.errors import InputError
from graphslam.io.schemas import SESSION_METADATA, TOPIC_UWB_RANGE, UWB_ANCHORS_METADATA

log = logging.getLogger(__name__)

# Beyond this a "range" is not a UWB measurement (indoor links reach tens of metres, the
# best outdoor ones a few hundred): a unit or encoding error in the recording.
MAX_RANGE_M = 1000.0
# Two files placing one anchor further apart than this disagree (survey-grade anchor positions).
ANCHOR_AGREEMENT_M = 1e-3
RESPONDER_KINDS = ("anchor", "tag")

UwbRow = tuple[int, str, bool, float]


def decode_range(path: Path, index: int, msg: dict) -> UwbRow:
    """(t_ns, responder_id, is_anchor, range_m) of one ``/uwb/range`` message."""

    def fail(field: str, problem: str) -> InputError:
        return InputError(path, f"message #{index}: {problem}", topic=TOPIC_UWB_RANGE, field=field)

    ts = msg.get("timestamp")
    if not isinstance(ts, dict):
        raise fail("timestamp", "missing field")
    for name in ("sec", "nsec"):
        v = ts.get(name)
        if isinstance(v, bool) or not isinstance(v, int):
            raise fail(f"timestamp.{name}", f"expected an integer, got {v!r}")
    rid = msg.get("responder_id")
    if not isinstance(rid, str) or not rid:
        raise fail("responder_id", f"expected a non-empty string, got {rid!r}")
    kind = msg.get("responder_kind")
    if kind not in RESPONDER_KINDS:
        raise fail("responder_kind", f"expected 'anchor' or 'tag', got {kind!r}")
    r = msg.get("range_m")
    if isinstance(r, bool) or not isinstance(r, (int, float)):
        raise fail("range_m", f"expected a number, got {type(r).__name__}")
    if not math.isfinite(r):
        raise fail("range_m", f"non-finite value {r}")
    if r < 0:
        raise fail("range_m", f"negative range {r} m")
    if r > MAX_RANGE_M:
        raise fail("range_m", f"absurd range {r} m (more than {MAX_RANGE_M:g} m)")
    return ts["sec"] * 1_000_000_000 + ts["nsec"], rid, kind == "anchor", float(r)


def parse_anchors(path: Path, metadata: Mapping[str, str]) -> dict[str, tuple[float, ...]]:
    """The ``graphslam.uwb_anchors`` record: anchor id -> (x, y) or (x, y, z), site metres."""
    out: dict[str, tuple[float, ...]] = {}
    for aid, raw in metadata.items():
        field = f"{UWB_ANCHORS_METADATA}.{aid}"
        try:
            v: Any = json.loads(raw)
        except (TypeError, json.JSONDecodeError):
            raise InputError(path, f"anchor position {raw!r} is not JSON (expected [x, y] or [x, y, z])", field=field) from None
        ok = isinstance(v, list) and len(v) in (2, 3) and all(
            isinstance(c, (int, float)) and not isinstance(c, bool) and math.isfinite(c) for c in v
        )
        if not ok:
            raise InputError(path, f"anchor position {raw!r}: expected [x, y] or [x, y, z] of finite numbers", field=field)
        if not aid:
            raise InputError(path, "empty anchor id", field=UWB_ANCHORS_METADATA)
        out[aid] = tuple(float(c) for c in v)
    return out


def uwb_id(path: Path, session_meta: Mapping[str, str]) -> str:
    v = session_meta.get("uwb_id", "")
    if not isinstance(v, str):
        raise InputError(path, f"expected a string, got {v!r}", field=f"{SESSION_METADATA}.uwb_id")
    return v


def ranges(path: Path, rows: Sequence[UwbRow], anchors: Mapping[str, tuple[float, ...]], own_id: str) -> UwbRanges | None:
    """Checked ``UwbRanges`` of one file (None without messages): time never decreases, every
    anchor range names an anchor of this file's record, no tag ranges itself."""
    if not rows:
        return None
    t = np.array([r[0] for r in rows], np.int64)
    back = np.flatnonzero(np.diff(t) < 0)
    if back.size:
        i = int(back[0]) + 1
        raise InputError(
            path, f"message #{i}: time goes backwards ({t[i]} ns after {t[i - 1]} ns)", topic=TOPIC_UWB_RANGE,
            field="timestamp",
        )
    for i, (_, rid, is_anchor, _) in enumerate(rows):
        if is_anchor and rid not in anchors:
            known = ", ".join(sorted(anchors)) or f"none: no {UWB_ANCHORS_METADATA} record"
            raise InputError(
                path, f"message #{i}: unknown anchor {rid!r} (anchors known: {known})", topic=TOPIC_UWB_RANGE,
                field="responder_id",
            )
        if not is_anchor and own_id and rid == own_id:
            raise InputError(path, f"message #{i}: tag {rid!r} ranges itself", topic=TOPIC_UWB_RANGE, field="responder_id")
    return UwbRanges(t, tuple(r[1] for r in rows), np.array([r[2] for r in rows]), np.array([r[3] for r in rows]))


def check_survey(sessions: Sequence[Session]) -> None:
    """Across files: one position per anchor, one session per ``uwb_id``."""
    where: dict[str, tuple[tuple[float, ...], str]] = {}
    ids: dict[str, str] = {}
    for s in sessions:
        for aid, pos in s.uwb_anchors.items():
            if aid in where:
                other, src = where[aid]
                if len(other) != len(pos) or max(abs(a - b) for a, b in zip(other, pos)) > ANCHOR_AGREEMENT_M:
                    raise InputError(
                        s.source, f"anchor {aid!r} at {list(pos)} here but at {list(other)} in {src}",
                        field=f"{UWB_ANCHORS_METADATA}.{aid}",
                    )
            else:
                where[aid] = (pos, s.source)
        if s.uwb_id:
            if s.uwb_id in ids:
                raise InputError(
                    s.source, f"uwb_id {s.uwb_id!r} also used by session {ids[s.uwb_id]!r}", field=f"{SESSION_METADATA}.uwb_id"
                )
            ids[s.uwb_id] = s.session_id
    unknown = {
        rid for s in sessions if s.uwb_ranges is not None
        for rid, a in zip(s.uwb_ranges.responder_id, s.uwb_ranges.is_anchor.tolist()) if not a and rid not in ids
    }
    if unknown:
        # a walker outside this survey (or without a recording): its ranges have no second pose
        log.info("UWB: ranges to %d tag(s) not in this survey are not used: %s", len(unknown), sorted(unknown)[:5])


def range_messages(session: Session) -> list[tuple[int, dict]]:
    """``(t_ns, body)`` of every ``/uwb/range`` message of ``session`` (for the writer)."""
    r = session.uwb_ranges
    if r is None:
        return []
    out = []
    for t, rid, a, d in zip(r.t_ns.tolist(), r.responder_id, r.is_anchor.tolist(), r.range_m.tolist()):
        body = {
            "timestamp": {"sec": t // 1_000_000_000, "nsec": t % 1_000_000_000},
            "responder_id": rid,
            "responder_kind": "anchor" if a else "tag",
            "range_m": d,
        }
        out.append((t, body))
    return out


def anchors_metadata(session: Session) -> dict[str, str]:
    return {aid: json.dumps(list(pos)) for aid, pos in session.uwb_anchors.items()}
