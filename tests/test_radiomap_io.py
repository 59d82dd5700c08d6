"""Radio map Parquet files: exact round trip, and every kind of bad file named with its field."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.errors import OutputError, RadioMapError
from graphslam.io.radiomap_io import METADATA_KEY, radio_map_table, read_radio_map, write_radio_map


def sample_map(labels: bool = True) -> RadioMap:
    rng = np.random.default_rng(3)
    scans = []
    for i in range(50):
        aps = rng.choice(30, size=rng.integers(1, 8), replace=False)
        # non-integer dBm on purpose: the round trip must be exact anyway
        scans.append({f"{j:02x}:aa:bb:cc:dd:ee": float(rng.uniform(-99.9, -20.0)) for j in aps})
    scans.append({})  # a fingerprint that heard nothing is kept
    n = len(scans)
    return RadioMap.from_scans(
        scans,
        rng.normal(0, 30, (n, 2)),
        session_ids=[f"walk{i % 3}" for i in range(n)],
        t_ns=1_767_225_600_000_000_000 + np.arange(n) * 2_000_000_000,
        frame="aligned",
        floors=[("F1" if i % 2 else "B1") if i != 7 else None for i in range(n)] if labels else None,
        buildings=["main"] * n if labels else None,
        metadata={"config": {"k": 3, "nested": [1, 2.5, "x"]}, "reference_session": "walk0"},
        missing_dbm=-110.0,
        min_rssi_dbm=-100.0,
    )


def assert_same(a: RadioMap, b: RadioMap) -> None:
    assert a.bssids == b.bssids
    va, vb = a.fingerprints.values, b.fingerprints.values
    assert np.array_equal(va.indptr, vb.indptr) and np.array_equal(va.indices, vb.indices)
    assert np.array_equal(va.data, vb.data)  # exact, not approx
    assert np.array_equal(a.xy, b.xy)
    assert a.session_ids.tolist() == b.session_ids.tolist()
    assert np.array_equal(a.t_ns, b.t_ns)
    for name in ("floors", "buildings"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None and y is None) or x.tolist() == y.tolist()
    assert a.frame == b.frame and a.missing_dbm == b.missing_dbm and a.min_rssi_dbm == b.min_rssi_dbm
    assert dict(a.metadata) == dict(b.metadata) and a.format_version == b.format_version


@pytest.mark.parametrize("labels", [True, False])
def test_round_trip_is_exact(tmp_path: Path, labels: bool) -> None:
    rm = sample_map(labels)
    path = write_radio_map(rm, tmp_path / "map.parquet")
    back = read_radio_map(path)
    assert_same(rm, back)
    assert back.floors is None if not labels else back.floors[7] == ""  # type: ignore[index]
    assert [p.name for p in tmp_path.iterdir()] == ["map.parquet"]  # no temp file left


def test_file_is_plain_typed_parquet(tmp_path: Path) -> None:
    path = write_radio_map(sample_map(), tmp_path / "map.parquet")
    t = pq.read_table(path)
    assert t.schema.field("bssid").type == pa.list_(pa.string())
    assert t.schema.field("rssi_dbm").type == pa.list_(pa.float64())
    assert t.schema.field("t_ns").type == pa.int64()
    meta = json.loads(t.schema.metadata[METADATA_KEY])
    assert meta["format_version"] == 1 and meta["frame"] == "aligned" and meta["n_fingerprints"] == 51
    row = t.slice(0, 1).to_pylist()[0]
    assert len(row["bssid"]) == len(row["rssi_dbm"]) >= 1 and all(-100 <= r < -20 for r in row["rssi_dbm"])


def test_failed_write_keeps_the_old_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = write_radio_map(sample_map(), tmp_path / "map.parquet")
    before = path.read_bytes()

    def boom(*a: object, **k: object) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(pq, "write_table", boom)
    with pytest.raises(OutputError, match=r"map\.parquet: cannot write \(disk full\)"):  # one line for the CLI
        write_radio_map(sample_map(False), path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["map.parquet"]


def _rewrite(tmp_path: Path, table: pa.Table) -> Path:
    p = tmp_path / "bad.parquet"
    pq.write_table(table, p)
    return p


def test_not_parquet_and_missing_file(tmp_path: Path) -> None:
    p = tmp_path / "map.parquet"
    p.write_text("session_id,x,y\n")
    with pytest.raises(RadioMapError, match=r"map\.parquet.*not a readable Parquet file"):
        read_radio_map(p)
    with pytest.raises(RadioMapError, match="no such file"):
        read_radio_map(tmp_path / "absent.parquet")
    plain = _rewrite(tmp_path, pa.table({"a": [1, 2]}))
    with pytest.raises(RadioMapError, match=r"bad\.parquet \[field metadata\]: no graphslam.radio_map"):
        read_radio_map(plain)


def _with_meta(table: pa.Table, **changes: object) -> pa.Table:
    meta = json.loads(table.schema.metadata[METADATA_KEY])
    meta.update(changes)
    for k, v in list(meta.items()):
        if v is None:
            del meta[k]
    return table.replace_schema_metadata({METADATA_KEY: json.dumps(meta).encode()})


def test_wrong_version_and_bad_metadata(tmp_path: Path) -> None:
    t = radio_map_table(sample_map())
    with pytest.raises(RadioMapError, match=r"\[field metadata.format_version\]: format version 2"):
        read_radio_map(_rewrite(tmp_path, _with_meta(t, format_version=2)))
    with pytest.raises(RadioMapError, match=r"\[field metadata.frame\]: missing"):
        read_radio_map(_rewrite(tmp_path, _with_meta(t, frame=None)))
    with pytest.raises(RadioMapError, match=r"\[field metadata.missing_dbm\]"):
        read_radio_map(_rewrite(tmp_path, _with_meta(t, missing_dbm="low")))


@pytest.mark.parametrize("column", ["session_id", "t_ns", "x", "y", "bssid", "rssi_dbm"])
def test_missing_column(tmp_path: Path, column: str) -> None:
    t = radio_map_table(sample_map())
    t = t.drop_columns([column])
    with pytest.raises(RadioMapError, match=rf"bad\.parquet \[field {column}\]: missing column"):
        read_radio_map(_rewrite(tmp_path, t))


def test_wrong_types_and_values(tmp_path: Path) -> None:
    t = radio_map_table(sample_map())
    i = t.schema.get_field_index("x")
    bad_x = t.set_column(i, "x", pa.array([str(v) for v in t.column("x").to_pylist()]))
    with pytest.raises(RadioMapError, match=r"\[field x\]: expected float"):
        read_radio_map(_rewrite(tmp_path, bad_x))
    j = t.schema.get_field_index("rssi_dbm")
    rssi = t.column("rssi_dbm").to_pylist()
    short = [r[:-1] if len(r) > 1 else r for r in rssi]
    with pytest.raises(RadioMapError, match=r"\[field rssi_dbm\]: row 0: \d+ BSSIDs but \d+ RSS values"):
        read_radio_map(_rewrite(tmp_path, t.set_column(j, "rssi_dbm", pa.array(short, pa.list_(pa.float64())))))
    nan = [[float("nan")] + r[1:] if r else r for r in rssi]
    with pytest.raises(RadioMapError, match=r"\[field rssi_dbm\]: row 0: RSS nan"):
        read_radio_map(_rewrite(tmp_path, t.set_column(j, "rssi_dbm", pa.array(nan, pa.list_(pa.float64())))))
    b = t.schema.get_field_index("bssid")
    dup = [[r[0]] + r[:-1] if len(r) > 1 else r for r in t.column("bssid").to_pylist()]
    with pytest.raises(RadioMapError, match=r"\[field bssid\]: a BSSID appears twice"):
        read_radio_map(_rewrite(tmp_path, t.set_column(b, "bssid", pa.array(dup, pa.list_(pa.string())))))
    n = t.schema.get_field_index("session_id")
    nulls = t.set_column(n, "session_id", pa.array([None] * t.num_rows, pa.string()))
    with pytest.raises(RadioMapError, match=r"\[field session_id\]: \d+ null values"):
        read_radio_map(_rewrite(tmp_path, nulls))
