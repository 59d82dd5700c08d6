"""Seeded bit-flip fuzz of a small recording, radio map and AP models through the real readers
(and some through the CLI): never altered data, never a traceback. The full run (500+ flips
per type) is ``lab/files/fuzz_files.py``, recorded in docs/benchmarks.md; this is a subset with
another seed."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
from lab.conftest import REPO

sys.path.insert(0, str(REPO / "lab" / "files"))
import fuzz_files  # noqa: E402


@pytest.fixture(scope="module")
def targets(tmp_path_factory: pytest.TempPathFactory) -> dict[str, fuzz_files.Target]:
    tmp = tmp_path_factory.mktemp("fuzz")
    return {t.name: t for t in fuzz_files.make_targets(tmp, None)}


@pytest.mark.parametrize("kind,flips", [("mcap", 150), ("radio_map", 150), ("ap_models", 150)])
def test_bit_flips_are_detected_or_harmless(targets: dict, kind: str, flips: int, tmp_path: Path) -> None:
    row = fuzz_files.fuzz(targets[kind], flips, seed=11, cli=4, tmp=tmp_path)
    assert row.get("ALTERED", 0) == 0 and row.get("TRACEBACK", 0) == 0, row["findings"]
    assert set(row["cli_exit_codes"]) <= {"0", "2"}, row["findings"]
    assert row["error"] > flips // 2  # most flips hit checked bytes; the CRCs / hashes catch them


def test_the_fuzz_catches_an_unchecked_reader(targets: dict, tmp_path: Path) -> None:
    # The harness itself: a reader that skips the checks must show up as ALTERED or TRACEBACK.
    import pyarrow.parquet as pq

    t = targets["radio_map"]
    naive = fuzz_files.Target("naive", t.path, lambda p: pq.read_table(p).to_pylist(), lambda rows: rows, t.cli)
    row = fuzz_files.fuzz(naive, 60, seed=3, cli=0, tmp=tmp_path)
    assert row.get("ALTERED", 0) + row.get("TRACEBACK", 0) > 0


def test_damaged_mcap_names_the_byte(targets: dict, tmp_path: Path) -> None:
    from graphslam import InputError, read_session

    data = bytearray(targets["mcap"].path.read_bytes())
    meta = data.index(b"walk-0")  # the session id, in the metadata record (outside every chunk)
    data[meta] ^= 0x01
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(data)
    with pytest.raises(InputError, match=r"bad\.mcap: damaged or truncated MCAP file: data section CRC mismatch"):
        read_session(bad)
