"""The service's fast body parser accepts exactly what the pydantic models accept, with their messages."""

from __future__ import annotations

import json
from typing import Any

import pytest
from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError

from graphslam.service.models import MAX_READINGS, LocateRequest
from graphslam.service.parsing import fast_scans, is_json_content_type, validated_scans

JSON = "application/json"


def reference(body: bytes) -> tuple[str, Any]:
    """What FastAPI with ``LocateRequest`` in the signature does: stdlib JSON, pydantic (python mode)."""
    try:
        obj = json.loads(body)
    except json.JSONDecodeError as e:
        return "error", [("json_invalid", ("body", e.pos))]
    try:
        return "ok", LocateRequest.model_validate(obj).scans()
    except ValidationError as e:
        return "error", [(x["type"], ("body", *x["loc"]), x["msg"]) for x in e.errors()]


def ours(body: bytes) -> tuple[str, Any]:
    try:
        return "ok", validated_scans(body, JSON)
    except RequestValidationError as e:
        errs = e.errors()
        if errs and errs[0]["type"] == "json_invalid":
            return "error", [("json_invalid", tuple(errs[0]["loc"]))]
        return "error", [(x["type"], tuple(x["loc"]), x["msg"]) for x in errs]


BODIES: list[bytes] = [
    b'{"readings": {"ap1": -50}}',
    b'{"readings": {"ap1": -50.5, "ap2": -200, "ap3": 0, "ap4": -0.0}}',
    b'{"fingerprints": [{"readings": {"ap1": -50}}, {"readings": {"x": -60.25}}]}',
    b'{"readings": {"ap1": -50, "ap1": -70}}',  # duplicate key: last wins in both parsers
    '{"readings": {"\u00e9t\u00e9-\u00fc": -50}}'.encode(),
    b'{"readings": {"ap1": -50',
    b"[1, 2, 3]",
    b"3",
    b"null",
    b'"readings"',
    b'{"readings": {"ap1": "-50"}}',
    b'{"readings": {"ap1": true}}',
    b'{"readings": {"ap1": null}}',
    b'{"readings": {"ap1": [1]}}',
    b'{"readings": {"ap1": {"v": 1}}}',
    b'{"readings": {"ap1": NaN}}',
    b'{"readings": {"ap1": -Infinity}}',
    b'{"readings": {"ap1": -1e400}}',
    b'{"readings": {"ap1": -200.0001}}',
    b'{"readings": {"ap1": 0.0001}}',
    b'{"readings": {"ap1": 100}}',
    b'{"readings": {"ap1": -100000000000000000000000}}',
    b'{"readings": {}}',
    b'{"fingerprints": []}',
    b'{"fingerprints": {}}',
    b'{"fingerprints": [3]}',
    b'{"fingerprints": [{}]}',
    b'{"fingerprints": [{"readings": {"a": -1}, "extra": 1}]}',
    b'{"fingerprints": [{"readings": {"a": -1}}, {"readings": {"b": "x"}}]}',
    b'{"fingerprints": [{"reading": {"a": -1}}]}',
    b'{"readings": {"": -50}}',
    b'{"readings": [["ap1", -50]]}',
    b"{}",
    b'{"readings": {"ap1": -50}, "fingerprints": [{"readings": {"ap1": -50}}]}',
    b'{"readings": null, "fingerprints": [{"readings": {"ap1": -50}}]}',
    b'{"readings": {"ap1": -50}, "k": 9}',
    b'{"readings": null}',
    b'  {"readings": {"ap1": -50}}  ',
    b"",
    b"\xff\xfe",
    json.dumps({"readings": {"a" * 128: -50}}).encode(),
    json.dumps({"readings": {"a" * 129: -50}}).encode(),
    json.dumps({"readings": {f"ap{i}": -50 for i in range(MAX_READINGS)}}).encode(),
    json.dumps({"readings": {f"ap{i}": -50 for i in range(MAX_READINGS + 1)}}).encode(),
]


@pytest.mark.parametrize("body", BODIES, ids=[repr(b[:40]) for b in BODIES])
def test_same_verdict_and_messages_as_pydantic(body: bytes) -> None:
    if not body or body == b"\xff\xfe":
        with pytest.raises(RequestValidationError):
            validated_scans(body, JSON)
        return
    want, got = reference(body), ours(body)
    assert got[0] == want[0], (got, want)
    if want[0] == "ok":
        assert got[1] == want[1]  # same scans (ints compare equal to the floats pydantic returns)
    else:
        assert got[1] == want[1]


def test_fast_path_takes_valid_bodies_and_declines_the_rest() -> None:
    assert fast_scans(b'{"fingerprints": [{"readings": {"a": -1}}, {"readings": {"b": -2.5}}]}') == [
        {"a": -1}, {"b": -2.5}
    ]
    for body in (b'{"readings": {"ap1": true}}', b'{"readings": {"ap1": NaN}}', b'{"readings": {}}', b"[]"):
        assert fast_scans(body) is None


def test_content_types() -> None:
    assert is_json_content_type("application/json")
    assert is_json_content_type("application/json; charset=utf-8")
    assert is_json_content_type("application/vnd.api+json")
    assert not is_json_content_type("text/plain")
    assert not is_json_content_type(None)
    with pytest.raises(RequestValidationError):
        validated_scans(b'{"readings": {"ap1": -50}}', "text/plain")  # as FastAPI: only JSON is parsed
    with pytest.raises(RequestValidationError):
        validated_scans(b'{"readings": {"ap1": -50}}', None)
