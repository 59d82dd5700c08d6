#!/usr/bin/env python3
"""Seeded bit-flip fuzz of the files graphslam reads: a small recording (MCAP), a small radio
map (Parquet) and its AP models (JSON), each written by the graphslam on the path, then read
back through the real readers after flipping one bit.

Every outcome must be one of:

- ``identical``: read, and the content equals the original's (the bit was in something the
  reader does not use, e.g. an index or a statistics field);
- ``error``: a ``GraphSlamError`` with one line that names the file (the CLI prints it and
  exits 2).

Anything else is a finding: ``ALTERED`` (read without complaint but the content changed) or
``TRACEBACK`` (another exception, or an error message that is not one line naming the file).
Flips are uniform over the file's bits (``--flips`` per type), plus, for the MCAP file, as
many again over its bytes outside compressed chunk data (headers, metadata, indexes,
summary: where a CRC is least likely to help). ``--cli N``: N of the flipped files per type
also go through the CLI entry point (``graphslam.cli.main``: ``inspect``, ``fit-aps``,
``track``), which must exit 0 or 2 with one line on stderr.

    python lab/files/fuzz_files.py [--flips 500] [--seed 0] [--cli 20] [--types mcap,radio_map,ap_models]
        [--mcap FILE]    # fuzz this recording too (e.g. a real one, which may lack a data CRC)

Prints one JSON line per file type with the counts (and the first findings), exit 1 if any.
"""

from __future__ import annotations

import argparse
import contextlib
import inspect
import io
import json
import random
import struct
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

T0 = 1_767_225_600_000_000_000  # 2026-01-01 in ns


def small_session() -> Any:
    """60 steps, 15 scans, 3 landmarks, ground truth: every topic of the contract."""
    from graphslam import LandmarkMark, PoseTrack, Scan, Session

    rng = np.random.default_rng(0)
    n = 60
    t = T0 + np.arange(n, dtype=np.int64) * 500_000_000
    h = np.cumsum(rng.normal(0, 0.05, n))
    h[0] = 0.0
    xy = np.cumsum(np.column_stack([np.cos(h), np.sin(h)]) * 0.7, axis=0)
    xy -= xy[0]
    scans = tuple(
        Scan(int(t[i]) + 1000, {f"02:00:00:00:00:{k:02x}": float(-40 - 3 * k - rng.integers(0, 5)) for k in range(6)})
        for i in range(0, n, 4)
    )
    marks = tuple(LandmarkMark(int(t[i]), f"L{i}", float(xy[i, 0]) + 10, float(xy[i, 1]) + 5) for i in (3, 30, 57))
    return Session("walk-0", PoseTrack(t, xy, h), scans, marks, PoseTrack(t, xy + [10.0, 5.0], h), site="s", floor="1")


def small_radio_map() -> Any:
    """80 fingerprints over 6 APs that follow a path-loss law (so that AP models fit)."""
    from graphslam import RadioMap

    rng = np.random.default_rng(1)
    xy = rng.uniform(0, 40, (80, 2))
    aps = rng.uniform(0, 40, (6, 2))
    d = np.linalg.norm(xy[:, None] - aps[None], axis=2)
    rss = -40 - 25 * np.log10(np.maximum(d, 1)) + rng.normal(0, 2, d.shape)
    scans = [{f"02:00:00:00:01:{j:02x}": round(float(r[j]), 1) for j in range(6) if r[j] > -95} for r in rss]
    return RadioMap.from_scans(
        scans, xy, session_ids=[f"w{i % 4}" for i in range(80)], t_ns=T0 + np.arange(80) * 2_000_000_000,
        frame="aligned", floors=["F1"] * 80, metadata={"source": "fuzz_files.py"},
    )


def session_key(s: Any) -> tuple:
    track = lambda p: None if p is None else (p.t_ns.tobytes(), p.xy.tobytes(), p.heading.tobytes())  # noqa: E731
    return (s.session_id, s.site, s.floor, track(s.steps), track(s.ground_truth),
            tuple((x.t_ns, tuple(sorted(x.readings.items()))) for x in s.scans),
            tuple((m.t_ns, m.landmark_id, m.x, m.y) for m in s.landmarks))


def radio_map_key(rm: Any) -> tuple:
    v = rm.fingerprints.values.copy()
    v.sort_indices()
    labels = lambda a: None if a is None else tuple(a.tolist())  # noqa: E731
    return (rm.bssids, v.indptr.tobytes(), v.indices.tobytes(), v.data.tobytes(), rm.xy.tobytes(),
            rm.t_ns.tobytes(), tuple(rm.session_ids.tolist()), labels(rm.floors), labels(rm.buildings), rm.frame,
            rm.missing_dbm, rm.min_rssi_dbm, json.dumps(dict(rm.metadata), sort_keys=True), rm.format_version)


def ap_models_key(m: Any) -> str:
    return json.dumps(m.as_dict(), sort_keys=True)


def _accepts(fn: Callable, name: str) -> bool:
    return name in inspect.signature(fn).parameters  # (the base commit's readers lack some options)


@dataclass
class Target:
    name: str
    path: Path
    read: Callable[[Path], Any]
    key: Callable[[Any], Any]
    cli: Callable[[Path, Path], list[str]]
    regions: list[tuple[int, int]] = field(default_factory=list)  # extra flips only inside these byte ranges


def outside_chunk_payloads(data: bytes) -> list[tuple[int, int]]:
    """Byte ranges of an MCAP file that are not compressed chunk data."""
    ranges, pos, start = [], 8, 0
    while pos + 9 <= len(data) - 8:
        op, length = struct.unpack_from("<BQ", data, pos)
        if op == 0x06:  # chunk: times, size, crc, compression string, records length, then the payload
            clen = struct.unpack_from("<I", data, pos + 9 + 28)[0]
            payload = pos + 9 + 28 + 4 + clen + 8
            ranges.append((start, payload))
            start = pos + 9 + length
        pos += 9 + length
    ranges.append((start, len(data)))
    return [(a, b) for a, b in ranges if b > a]


def make_targets(tmp: Path, extra_mcap: Path | None) -> list[Target]:
    from graphslam import (
        ApFitConfig, ApModels, read_ap_models, read_radio_map, read_session, write_ap_models, write_radio_map,
        write_session,
    )


    walk = write_session(small_session(), tmp / "walk.mcap")
    rm = small_radio_map()
    rm_path = write_radio_map(rm, tmp / "radio_map.parquet")
    models = ApModels.fit(rm, ApFitConfig(min_readings=20))
    bound = {"radio_map": rm} if _accepts(write_ap_models, "radio_map") else {}
    ap_path = write_ap_models(models, tmp / "ap_models.json", **bound)
    read_bound = {"radio_map": rm} if _accepts(read_ap_models, "radio_map") else {}
    targets = [
        Target("mcap", walk, read_session, session_key, lambda f, o: ["inspect", str(f)],
               outside_chunk_payloads(walk.read_bytes())),
        Target("radio_map", rm_path, read_radio_map, radio_map_key,
               lambda f, o: ["fit-aps", "--radio-map", str(f), "--out", str(o / "ap.json")]),
        Target("ap_models", ap_path, lambda p: read_ap_models(p, **read_bound), ap_models_key,
               lambda f, o: ["track", str(walk), "--radio-map", str(rm_path), "--ap-models", str(f),
                             "--out", str(o / "t.csv"), "--no-knn-fixes"]),
    ]
    if extra_mcap is not None:
        data = extra_mcap.read_bytes()
        copy = tmp / f"given-{extra_mcap.name}"
        copy.write_bytes(data)
        targets.append(Target(f"mcap:{extra_mcap.name}", copy, read_session, session_key,
                              lambda f, o: ["inspect", str(f)], outside_chunk_payloads(data)))
    return targets


def classify(read: Callable[[Path], Any], key: Callable[[Any], Any], ref: Any, path: Path) -> tuple[str, str]:
    from graphslam import GraphSlamError

    try:
        got = read(path)
    except GraphSlamError as e:
        msg = str(e)
        if "\n" in msg or str(path) not in msg:
            return "TRACEBACK", f"error message not one line naming the file: {msg[:300]!r}"
        return "error", msg
    except Exception as e:  # noqa: BLE001 - that is the finding
        return "TRACEBACK", f"{type(e).__name__}: {str(e)[:300]}"
    return ("identical", "") if key(got) == ref else ("ALTERED", "read without error, content changed")


def run_cli(args: list[str]) -> tuple[int, str]:
    from graphslam import cli_main as main

    err = io.StringIO()
    code: Any = 0
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            main(args)
        except SystemExit as e:
            code = e.code
        except Exception as e:  # noqa: BLE001
            return -1, f"{type(e).__name__}: {e}"
    return int(code or 0), err.getvalue()


def fuzz(target: Target, flips: int, seed: int, cli: int, tmp: Path) -> dict[str, Any]:
    data = target.path.read_bytes()
    ref = target.key(target.read(target.path))
    rng = random.Random(f"{seed}:{target.name}")
    positions = [rng.randrange(len(data) * 8) for _ in range(flips)]
    if target.regions:  # as many again, outside chunk payloads
        spans = [(a * 8, b * 8) for a, b in target.regions]
        weights = [b - a for a, b in spans]
        positions += [rng.randrange(*rng.choices(spans, weights)[0]) for _ in range(flips)]
    counts: dict[str, int] = {}
    findings: list[dict[str, Any]] = []
    cli_codes: dict[str, int] = {}
    bad = tmp / f"flipped-{target.path.name}"
    for n, bit in enumerate(positions):
        b = bytearray(data)
        b[bit // 8] ^= 1 << (bit % 8)
        bad.write_bytes(b)
        outcome, why = classify(target.read, target.key, ref, bad)
        counts[outcome] = counts.get(outcome, 0) + 1
        if outcome in ("ALTERED", "TRACEBACK") and len(findings) < 10:
            findings.append({"byte": bit // 8, "bit": bit % 8, "outcome": outcome, "detail": why})
        if n < cli:
            code, err = run_cli(target.cli(bad, tmp))
            lines = err.strip().splitlines()
            ok = code == 0 or (code == 2 and len(lines) == 1 and lines[0].startswith("error: "))
            label = str(code) if ok else "BAD"
            cli_codes[label] = cli_codes.get(label, 0) + 1
            if not ok and len(findings) < 10:
                findings.append(
                    {"byte": bit // 8, "bit": bit % 8, "outcome": "CLI", "detail": f"exit {code}: {err[-300:]}"}
                )
    return {"type": target.name, "file_bytes": len(data), "flips": len(positions), **counts,
            "cli_exit_codes": cli_codes, "findings": findings}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--flips", type=int, default=500, help="uniform flips per file type")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cli", type=int, default=20, help="flipped files per type also run through the CLI")
    ap.add_argument("--types", default="mcap,radio_map,ap_models")
    ap.add_argument("--mcap", type=Path, help="also fuzz this recording")
    a = ap.parse_args(argv)
    import logging

    logging.disable(logging.WARNING)  # the readers' warnings (e.g. "integrity not verified") are not findings
    wanted = set(a.types.split(",")) | ({f"mcap:{a.mcap.name}"} if a.mcap else set())
    findings = 0
    with tempfile.TemporaryDirectory(prefix="graphslam-fuzz-") as tmp:
        for target in make_targets(Path(tmp), a.mcap):
            if target.name in wanted:
                row = fuzz(target, a.flips, a.seed, a.cli, Path(tmp))
                findings += row.get("ALTERED", 0) + row.get("TRACEBACK", 0) + row["cli_exit_codes"].get("BAD", 0)
                print(json.dumps(row), flush=True)
    return 1 if findings else 0


if __name__ == "__main__":
    sys.exit(main())
