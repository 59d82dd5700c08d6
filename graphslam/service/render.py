"""JSON of ``POST /v1/locate`` answers (``LocateResponse``), shared by the server process
and the search workers.

Why the workers render too: building and serialising the position objects costs ~1.5 ms
per 1,000 fingerprints; in the server process that is in series with every request, in
the workers it runs in parallel with the other share. The server then only splices the
rows into the response (``response_json``): the bytes are those of ``orjson.dumps`` of
the whole response (tested).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import orjson

from graphslam.core.radiomap.knn import KnnResult
from graphslam.core.radiomap.uncertainty import KnnUncertainty

# Every position object starts with its first key, and orjson escapes '"' inside strings: this
# separator occurs between two objects of a serialised list and nowhere else.
_ROW_START = b'{"x":'
_ROW_SEP = b"," + _ROW_START


# The reason the geolocation APIs users know (Google's, Mozilla's) give for a query no position is
# found for; ``status`` says why, in the words of locate's CSV (``KnnResult.status``).
NOT_FOUND = "notFound"


def not_found(status: str, min_common: int = 1, where: str = "the radio map") -> dict[str, str]:
    """The ``error`` of a fingerprint that cannot be located (``status``: ``no_known_ap`` or
    ``no_candidate``)."""
    if status == "no_known_ap":
        message = f"none of its access points is in {where}"
    else:
        message = f"no fingerprint of {where} shares {min_common} of its access points"
    return {"reason": NOT_FOUND, "status": status, "message": message}


def unlocated(error: dict[str, str]) -> dict[str, Any]:
    """The position object of a fingerprint that cannot be located: no position, and why."""
    return {"x": None, "y": None, "score": None, "spread": None, "sigma_m": None, "outside": None,
            "outside_score": None, "n_neighbours": 0, "floor": None, "building": None, "error": error}


def position_dicts(res: KnnResult, uncertainty: KnnUncertainty | None = None) -> list[dict[str, Any]]:
    """One ``Position`` object per row of ``res``; ``sigma_m``, ``outside`` and ``outside_score``
    from ``uncertainty`` (None: null). A row that could not be located has no position (nulls) and
    an ``error`` (``not_found``); the others have no ``error`` key."""
    n = len(res)
    floor = res.floor.tolist() if res.floor is not None else [""] * n
    building = res.building.tolist() if res.building is not None else [""] * n
    sigma = uncertainty.sigma_of(res).tolist() if uncertainty is not None else [None] * n
    flags = uncertainty.outside_of(res) if uncertainty is not None else None
    scores = uncertainty.outside_score_of(res) if uncertainty is not None else None
    outside = flags.tolist() if flags is not None else [None] * n
    outside_score = scores.tolist() if scores is not None else [None] * n
    rows = [
        {"x": p[0], "y": p[1], "score": s, "spread": sp, "sigma_m": sg, "outside": o, "outside_score": os_,
         "n_neighbours": nn, "floor": f or None, "building": b or None}
        for p, s, sp, sg, o, os_, nn, f, b in zip(
            res.xy.tolist(), res.score.tolist(), res.spread.tolist(), sigma, outside, outside_score,
            res.n_neighbours.tolist(), floor, building,
        )
    ]
    bad = np.flatnonzero(~res.valid)
    if len(bad):
        status = res.status
        for i in bad.tolist():
            rows[i] = unlocated(not_found(str(status[i]), res.config.min_common))
    return rows


def position_rows(res: KnnResult, uncertainty: KnnUncertainty | None = None) -> list[bytes]:
    """Each row's position object as JSON: one ``orjson.dumps`` of the list, cut between objects."""
    out = orjson.dumps(position_dicts(res, uncertainty))[1:-1]
    if not out:
        return []
    rows = out.split(_ROW_SEP)
    return [rows[0]] + [_ROW_START + r for r in rows[1:]]


def response_json(head: dict[str, Any], rows: list[bytes]) -> bytes:
    """``orjson.dumps({**head, "positions": [...]})`` from the positions' JSON ``rows``."""
    empty = orjson.dumps({**head, "positions": []})  # "positions" last: the bytes end with []}
    return b"".join((empty[:-2], b",".join(rows), b"]}"))
