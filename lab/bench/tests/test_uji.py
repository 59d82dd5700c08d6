"""UJIIndoorLoc importer and benchmark (lab/bench/ujiindoorloc.py, uji.py): tiny synthetic CSVs written here, real data when present."""

from __future__ import annotations

import gzip
import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from graphslam import InputError
from lab.bench.__main__ import app
from lab.bench.uji import run_ujiindoorloc_benchmark
from lab.bench.ujiindoorloc import read_ujiindoorloc
from lab.conftest import DATA, needs_data

HEADER = ["WAP001", "WAP002", "WAP003", "LONGITUDE", "LATITUDE", "FLOOR", "BUILDINGID", "SPACEID",
          "RELATIVEPOSITION", "USERID", "PHONEID", "TIMESTAMP"]


def write_csv(path: Path, rows: list[list[object]], header: list[str] = HEADER) -> Path:
    text = ",".join(header) + "\n" + "".join(",".join(map(str, r)) + "\n" for r in rows)
    if path.suffix == ".gz":
        path.write_bytes(gzip.compress(text.encode()))
    else:
        path.write_text(text)
    return path


# Two "rooms" per floor, AP1 loud in building 0, AP3 loud in building 1.
TRAIN = [
    [-40, -80, 100, -7600.5, 4864900.25, 0, 0, 1, 1, 1, 1, 1371713733],
    [-45, -75, 100, -7600.5, 4864900.25, 0, 0, 1, 1, 1, 1, 1371713734],
    [-80, -40, 100, -7580.0, 4864920.0, 1, 0, 2, 1, 2, 3, 1371713735],
    [-82, -42, 100, -7580.0, 4864920.0, 1, 0, 2, 1, 2, 3, 1371713736],
    [100, -90, -40, -7400.0, 4864800.0, 2, 1, 3, 2, 3, 3, 1371713737],
    [100, -88, -45, -7400.0, 4864800.0, 2, 1, 3, 2, 3, 3, 1371713738],
]
TEST = [
    [-42, -78, 100, -7601.0, 4864901.0, 0, 0, 0, 0, 0, 0, 1380872703],
    [-81, -41, 100, -7579.0, 4864921.0, 1, 0, 0, 0, 0, 0, 1380872704],
    [100, -89, -43, -7401.0, 4864801.0, 2, 1, 0, 0, 0, 0, 1380872705],
]


def test_importer_reads_values_labels_and_ids(tmp_path: Path) -> None:
    d = read_ujiindoorloc(write_csv(tmp_path / "trainingData.csv.gz", TRAIN))
    assert d.bssids == ("WAP001", "WAP002", "WAP003") and len(d) == 6
    assert np.isnan(d.rssi[0, 2]) and d.rssi[0, 0] == -40.0 and d.rssi[4, 2] == -40.0
    assert d.xy[0].tolist() == [-7600.5, 4864900.25]
    assert d.floor.tolist() == [0, 0, 1, 1, 2, 2] and d.building.tolist() == [0, 0, 0, 0, 1, 1]
    assert d.session_ids[2] == "u2-p3" and d.t_ns[0] == 1371713733 * 10**9
    rm = d.to_radio_map()
    assert rm.frame == "EPSG:3857" and rm.floors.tolist()[2] == "1"  # type: ignore[union-attr]
    assert rm.bssids == ("WAP001", "WAP002", "WAP003")
    assert rm.fingerprints.values[0].toarray().tolist() == [[70.0, 30.0, 0.0]]  # rssi + 110


def test_importer_errors_name_file_and_column(tmp_path: Path) -> None:
    no_floor = [c for c in HEADER if c != "FLOOR"]
    rows = [[v for c, v in zip(HEADER, r) if c != "FLOOR"] for r in TRAIN]
    with pytest.raises(InputError, match=r"x\.csv \[field FLOOR\]: missing column"):
        read_ujiindoorloc(write_csv(tmp_path / "x.csv", rows, no_floor))
    bad = [r[:] for r in TRAIN]
    bad[3][1] = 55
    with pytest.raises(InputError, match=r"\[field WAP002\]: row 5: RSSI 55"):
        read_ujiindoorloc(write_csv(tmp_path / "y.csv", bad))
    (tmp_path / "z.csv.gz").write_bytes(b"not gzip at all")
    with pytest.raises(InputError, match=r"z\.csv\.gz: not a readable UJIIndoorLoc CSV"):
        read_ujiindoorloc(tmp_path / "z.csv.gz")
    with pytest.raises(InputError, match="no such file"):
        read_ujiindoorloc(tmp_path / "absent.csv")


def test_benchmark_on_synthetic_data(tmp_path: Path) -> None:
    write_csv(tmp_path / "trainingData.csv", TRAIN)
    write_csv(tmp_path / "validationData.csv.gz", TEST)
    r = run_ujiindoorloc_benchmark(tmp_path, k=2, weighted=False, repeats=1)
    assert r.n_train == 6 and r.n_test == 3
    assert r.building_hit == 1.0 and r.floor_hit == 1.0
    # k=2 uniform: the estimate is the (shared) position of the two same-room references
    assert r.mean_error_m == pytest.approx(np.mean([np.hypot(0.5, 0.75), np.hypot(1, 1), np.hypot(1, 1)]))
    out = CliRunner().invoke(app, ["ujiindoorloc", str(tmp_path), "--k", "2", "--no-weighted", "--repeats", "1"])
    assert out.exit_code == 0, out.output
    line = json.loads(out.output.strip().splitlines()[-1])
    assert line["floor_hit"] == 1.0 and line["k"] == 2 and line["weighted"] is False and line["queries_per_s"] > 0


@needs_data("ujiindoorloc")
def test_real_ujiindoorloc_meets_targets() -> None:
    r = run_ujiindoorloc_benchmark(DATA / "ujiindoorloc", k=7, min_rssi_dbm=-95.0, missing_dbm=-100.0, repeats=1)
    assert r.n_train == 19937 and r.n_test == 1111 and r.n_unlocated == 0
    assert r.mean_error_m <= 7.9
    assert r.building_hit >= 0.99
    assert r.floor_hit >= 0.90
