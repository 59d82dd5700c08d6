"""Fast parsing of ``POST /v1/locate`` bodies, with the pydantic models' exact semantics.

FastAPI's default path (stdlib ``json.loads``, then pydantic validation of every
reading) costs ~40 ms per 1,000 fingerprints, as much as the IVF search. Here:

1. ``flat_scans`` / ``fast_scans``: ``orjson`` parse plus a hand-written check that
   accepts a body only when it is certainly valid for ``LocateRequest`` (exactly one of
   ``readings`` / ``fingerprints``, no extra keys, 1..MAX_READINGS readings, BSSIDs of
   1..128 characters, RSS an int or float (not bool, not a string), finite, in [-200, 0]
   dBm). Type checks are one ``map(type, ...)`` over the flattened values, range checks one
   numpy pass. ``flat_scans`` also keeps the flattened readings (``FlatScans``): the search
   workers encode straight from them (``graphslam.service.batching``).
2. Anything it does not accept (malformed JSON, NaN literals that orjson refuses,
   wrong types, empty or oversized fields ...) goes through the *original* path:
   ``LocateRequest.model_validate`` of the parsed body (stdlib ``json.loads`` where orjson
   refused it), raising the same ``RequestValidationError`` FastAPI would. So every 4xx
   keeps its message by construction, and the fast path only ever says "valid" where
   pydantic would.

Depth: a body nested deeper than ``MAX_JSON_DEPTH`` is refused (422) before the stdlib
parser, which recurses once per level (a ``RecursionError`` and a 500 at ~1,000 levels).
A valid request is 4 levels deep.
"""

from __future__ import annotations

import email.message
import json
import re
from dataclasses import dataclass
from itertools import chain
from typing import Any, Mapping

import numpy as np
import orjson
from numpy.typing import NDArray
from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError

from graphslam.service.models import (
    BSSID_MAX_CHARS,
    MAX_READINGS,
    RSSI_MAX_DBM,
    RSSI_MIN_DBM,
    LocateRequest,
)

Scan = Mapping[str, float]
_NUMBER_TYPES = frozenset({float, int})
MAX_JSON_DEPTH = 32
_JSON_STRING = re.compile(rb'"(?:[^"\\]|\\.)*+"', re.DOTALL)


def json_depth(body: bytes | bytearray) -> int:
    """Deepest nesting of arrays/objects in ``body`` (brackets inside strings do not count;
    meant for bodies a parser refused or may recurse on: vectorised, no recursion)."""
    b = np.frombuffer(_JSON_STRING.sub(b'""', bytes(body)), np.uint8)
    step = ((b == ord("[")) | (b == ord("{"))).astype(np.int8) - ((b == ord("]")) | (b == ord("}"))).astype(np.int8)
    return int(np.cumsum(step, dtype=np.int64).max(initial=0))


def is_json_content_type(value: str | None) -> bool:
    """FastAPI's rule (strict content type): JSON iff ``application/json`` or ``application/*+json``."""
    if not value:
        return False
    message = email.message.Message()
    message["content-type"] = value
    if message.get_content_maintype() != "application":
        return False
    subtype = message.get_content_subtype()
    return subtype == "json" or subtype.endswith("+json")


def _readings_ok(r: Any) -> bool:
    return type(r) is dict and 1 <= len(r) <= MAX_READINGS


@dataclass(frozen=True, eq=False)
class FlatScans:
    """A valid body's scans, and their readings flattened scan after scan (the validation
    builds these lists anyway; the search workers encode from them without a Python loop)."""

    scans: list[Scan]
    keys: list[str]  # every reading's BSSID
    values: NDArray[np.float64]  # every reading's RSS (dBm)
    offsets: NDArray[np.int64]  # (len(scans) + 1,): scan i's readings are [offsets[i], offsets[i + 1])
    single: bool = False  # the one-fingerprint form ({"readings": ...}), not a batch of one

    def __len__(self) -> int:
        return len(self.scans)


def flat_scans(body: bytes | bytearray) -> FlatScans | None:
    """``body``'s scans, flattened, if it is certainly a valid ``LocateRequest``, else ``None``
    (then ``validated_scans`` decides, with pydantic's messages)."""
    try:
        obj = orjson.loads(body)
    except orjson.JSONDecodeError:
        return None
    return _flat(obj)


def _flat(obj: Any) -> FlatScans | None:
    if type(obj) is not dict or len(obj) != 1:
        return None
    single = "readings" in obj
    if single:
        scans = [obj["readings"]]
    elif "fingerprints" in obj:
        fps = obj["fingerprints"]
        if type(fps) is not list or not fps:
            return None
        # A batch item is exactly {"readings": {...}}: one key, so len == 1 and the key matches.
        if not all(type(f) is dict and len(f) == 1 and "readings" in f for f in fps):
            return None
        scans = [f["readings"] for f in fps]
    else:
        return None
    if not all(map(_readings_ok, scans)):
        return None
    values = list(chain.from_iterable(map(dict.values, scans)))
    if not set(map(type, values)) <= _NUMBER_TYPES:  # bool, str, None, list, dict -> pydantic
        return None
    v = np.array(values, dtype=np.float64)
    # NaN fails both comparisons; big ints become big floats and fail the range.
    if not ((v >= RSSI_MIN_DBM) & (v <= RSSI_MAX_DBM)).all():
        return None
    keys = list(chain.from_iterable(scans))  # JSON keys are always str
    # Lengths of the distinct BSSIDs only: a batch repeats a few hundred of them (3x cheaper).
    lengths = list(map(len, set(keys)))
    if min(lengths) < 1 or max(lengths) > BSSID_MAX_CHARS:
        return None
    offsets = np.zeros(len(scans) + 1, np.int64)
    np.cumsum(np.fromiter(map(len, scans), np.int64, len(scans)), out=offsets[1:])
    return FlatScans(scans, keys, v, offsets, single)


def fast_scans(body: bytes) -> list[Scan] | None:
    """The request's scans if ``body`` is certainly a valid ``LocateRequest``, else ``None``
    (then ``validated_scans`` decides, with pydantic's messages)."""
    flat = flat_scans(body)
    return flat.scans if flat is not None else None


def _stdlib_json(body: bytes) -> Any:
    """What FastAPI's parser makes of a body orjson refused (NaN literals, bad JSON, not UTF-8)."""
    if json_depth(body) > MAX_JSON_DEPTH:
        raise RequestValidationError(
            [{"type": "json_invalid", "loc": ("body",), "msg": f"JSON nested deeper than {MAX_JSON_DEPTH} levels",
              "input": {}}]
        )
    try:
        return json.loads(body)
    except json.JSONDecodeError as e:
        raise RequestValidationError(
            [{"type": "json_invalid", "loc": ("body", e.pos), "msg": "JSON decode error", "input": {},
              "ctx": {"error": e.msg}}]
        ) from None
    except UnicodeDecodeError:
        return body  # FastAPI hands undecodable bytes to validation as they are
    except RecursionError:  # (cannot happen below MAX_JSON_DEPTH; a last guard against a 500)
        raise RequestValidationError(
            [{"type": "json_invalid", "loc": ("body",), "msg": "JSON nested too deeply", "input": {}}]
        ) from None


def _body_errors(errors: list[Any]) -> RequestValidationError:
    return RequestValidationError([{**e, "loc": ("body", *e.get("loc", ()))} for e in errors])


def validated_scans(body: bytes, content_type: str | None) -> list[Scan]:
    """Scans of a ``POST /v1/locate`` body, or ``RequestValidationError`` exactly as FastAPI
    with ``LocateRequest`` in the signature would raise it."""
    return validated_request(body, content_type)[0]


def validated_request(body: bytes, content_type: str | None) -> tuple[list[Scan], bool]:
    """``validated_scans`` and whether the body is the one-fingerprint form (``readings``; a batch
    answers per fingerprint, one fingerprint that cannot be located is a 404)."""
    if body and is_json_content_type(content_type):
        try:
            obj: Any = orjson.loads(body)  # parsed once: pydantic below validates this object
        except orjson.JSONDecodeError:
            obj = _stdlib_json(body)
        else:
            flat = _flat(obj)
            if flat is not None:
                return flat.scans, flat.single
    elif body:
        obj = body  # not JSON: FastAPI validates the raw bytes (and they fail)
    else:
        raise RequestValidationError([{"type": "missing", "loc": ("body",), "msg": "Field required", "input": None}])
    try:
        req = LocateRequest.model_validate(obj)
        return req.scans(), req.readings is not None
    except ValidationError as e:
        raise _body_errors(e.errors(include_url=False)) from None
