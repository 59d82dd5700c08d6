"""``wifi_edges.parquet``: the survey's WiFi-vicinity edges between aligned walks, after the solve.

One row per edge; ``a`` and ``b`` are rows of the ``radio_map.parquet`` beside it (the two
fingerprints the edge ties), ``distance_m`` their final distance (output frame) and ``state``
the fuzzy factor's state there (0 inactive, d < d_min; 1 on the ramp; 2 saturated, d > d_max;
``graphslam.core.survey.factors.edge_state``). ``graphslam plot`` draws them from this file.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from graphslam.core.survey.radio_maps import WifiEdgeRows
from graphslam.errors import InputError
from graphslam.io.atomic import atomic_open

COLUMNS = ("a", "b", "distance_m", "state")


def write_wifi_edges(edges: WifiEdgeRows, path: str | Path) -> Path:
    """Parquet, written atomically."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    table = pa.table(
        {
            "a": pa.array(np.asarray(edges.a, np.int64)),
            "b": pa.array(np.asarray(edges.b, np.int64)),
            "distance_m": pa.array(np.asarray(edges.distance_m, np.float32)),
            "state": pa.array(np.asarray(edges.state, np.int8)),
        }
    )
    with atomic_open(path, "wb") as fh:
        pq.write_table(table, fh)
    return Path(path)


def read_wifi_edges(path: str | Path, n_rows: int | None = None) -> WifiEdgeRows:
    """Read ``path``; ``n_rows`` (the radio map's length) checks that ``a`` and ``b`` are rows of it."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        table = pq.read_table(str(path))
    except (OSError, pa.ArrowException) as e:
        raise InputError(path, f"cannot read WiFi edges ({e})") from None
    missing = [c for c in COLUMNS if c not in table.column_names]
    if missing:
        raise InputError(path, "missing column", field=missing[0])
    cols = {c: table.column(c).to_numpy() for c in COLUMNS}
    a, b = cols["a"].astype(np.int64), cols["b"].astype(np.int64)
    state = cols["state"].astype(np.int8)
    if len(a) and (min(a.min(), b.min()) < 0 or (n_rows is not None and max(a.max(), b.max()) >= n_rows)):
        raise InputError(path, f"edge ends outside the radio map's {n_rows} rows", field="a/b")
    if len(state) and (state.min() < 0 or state.max() > 2):
        raise InputError(path, "state must be 0, 1 or 2", field="state")
    return WifiEdgeRows(a, b, cols["distance_m"].astype(np.float64), state)
