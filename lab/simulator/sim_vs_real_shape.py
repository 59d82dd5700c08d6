#!/usr/bin/env python3
"""Shape of the simulated ``museum`` survey next to the real IPIN 2023 floor -2 recordings.

Both are measured the same way (``graphslam.sim.shape``): positions are each walk's PDR
rigidly fitted to its own landmarks, since the real walks have no other ground truth.
Prints a Markdown table: one column for the real floor (when its folder exists), one
per simulator seed. Ground truth is used only to measure, as everywhere.

    python lab/simulator/sim_vs_real_shape.py [--data ../shared/data/ipin2023/b100_f-2] [--seeds 0,1,2] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from graphslam import GraphSlamError, read_survey, shape_walks, simulate, survey_shape

REPO = Path(__file__).resolve().parents[2]
DEFAULT_DATA = Path(os.environ.get("GRAPHSLAM_DATA", REPO.parent / "shared" / "data")) / "ipin2023" / "b100_f-2"


def _fmt(v: object) -> str:
    if isinstance(v, tuple):
        return ", ".join(_fmt(x) for x in v)
    if isinstance(v, float):
        return f"{v:g}" if abs(v) >= 100 or v == int(v) else f"{v:.2f}".rstrip("0").rstrip(".")
    return str(v)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="folder of the real floor -2 recordings")
    ap.add_argument("--seeds", default="0,1,2", help="comma-separated simulator seeds")
    ap.add_argument("--json", action="store_true", help="one JSON line per column instead of the table")
    args = ap.parse_args(argv)
    columns: list[tuple[str, dict]] = []
    try:
        if args.data.is_dir():
            t0 = time.perf_counter()
            real = read_survey([args.data])
            columns.append((f"real ({len(real)} walks)", survey_shape(real, shape_walks(real))))
            print(f"real: {args.data} ({time.perf_counter() - t0:.1f} s)", file=sys.stderr)
        else:
            print(f"real data not found at {args.data}: simulator columns only", file=sys.stderr)
        for seed in (int(s) for s in args.seeds.split(",") if s.strip()):
            t0 = time.perf_counter()
            sim = simulate("museum", seed=seed).survey
            columns.append((f"sim seed {seed}", survey_shape(sim, shape_walks(sim))))
            print(f"sim seed {seed} ({time.perf_counter() - t0:.1f} s)", file=sys.stderr)
    except (GraphSlamError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if args.json:
        for name, col in columns:
            print(json.dumps({"column": name, **{k.strip(): v for k, v in col.items()}}))
        return 0
    print("| statistic | " + " | ".join(name for name, _ in columns) + " |")
    print("|---|" + "---|" * len(columns))
    for key in columns[0][1]:
        print(f"| {key.strip() if not key.startswith(' ') else '... ' + key.strip()} | "
              + " | ".join(_fmt(col[key]) for _, col in columns) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
