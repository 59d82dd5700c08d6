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

import orjson

from graphslam.core.radiomap.knn import KnnResult
from graphslam.core.radiomap.uncertainty import KnnUncertainty

# Every position object starts with its first key, and orjson escapes '"' inside strings: this
# separator occurs between two objects of a serialised list and nowhere else.
_ROW_START = b'{"x":'
_ROW_SEP = b"," + _ROW_START


def position_dicts(res: KnnResult, uncertainty: KnnUncertainty | None = None) -> list[dict[str, Any]]:
    """One ``Position`` object per row of ``res`` (finite values: callers locate with ``strict=True``);
    ``sigma_m`` from ``uncertainty`` (None: null)."""
    n = len(res)
    floor = res.floor.tolist() if res.floor is not None else [""] * n
    building = res.building.tolist() if res.building is not None else [""] * n
    sigma = uncertainty.sigma(res.spread, res.score).tolist() if uncertainty is not None else [None] * n
    return [
        {"x": p[0], "y": p[1], "score": s, "spread": sp, "sigma_m": sg, "n_neighbours": nn, "floor": f or None,
         "building": b or None}
        for p, s, sp, sg, nn, f, b in zip(
            res.xy.tolist(), res.score.tolist(), res.spread.tolist(), sigma, res.n_neighbours.tolist(), floor, building
        )
    ]


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
