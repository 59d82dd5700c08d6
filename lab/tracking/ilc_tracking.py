#!/usr/bin/env python3
"""Tracking on REAL recordings (ILC 2.0 site1 floors) given a radio map: kNN vs the trackers.

Per floor, ``graphslam bench tracking-real`` on the floor's folder with the oracle map only
(alignment cannot build these floors' map): walks split into seeded folds; for each
fold the radio map is the OTHER walks' scans placed by their waypoint-fitted rigid poses (ground
truth builds the map as a perfect survey would and never reaches the tracker), AP models fitted
from it; every held-out walk is tracked from its real phone PDR steps and scans exactly as
``graphslam track`` does (kNN start, heading unknown). Errors at the surveyor's waypoints
(mean / median / p75 / p90) for ``knn`` (the scans' kNN fixes interpolated in time) and each
tracker; ``inside_95``: the share of waypoints inside the tracker's 95 % ellipse.

    python lab/tracking/ilc_tracking.py [SITE_DIR] [--floors F1,F3] [--folds 5] [--seed 0]
        [--lags 2] [--filters ekf] [--smoothers map]

One JSON line per floor (``graphslam.app.tracking_bench.tracking_real``'s result).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from graphslam import (
    floor_folders, GraphSlamConfig, GraphSlamError, limit_blas_threads, standard_variants, tracking_real,
)


REPO = Path(__file__).resolve().parents[2]
DEFAULT_SITE = Path(os.environ.get("GRAPHSLAM_DATA", REPO.parent / "shared" / "data")) / "ilc20" / "site1"


def _list(text: str) -> list[str]:
    return [x.strip() for x in text.split(",") if x.strip()]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("site", nargs="?", type=Path, default=DEFAULT_SITE)
    ap.add_argument("--floors", default=None, help="comma-separated, e.g. F1,F3 (default: every floor folder)")
    ap.add_argument("--folds", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--lags", default="2", help="fixed-lag latencies, s")
    ap.add_argument("--filters", default="ekf", help="causal filters also reported ('' for none)")
    ap.add_argument("--smoothers", default="", help="offline smoothers also reported (rts, map)")
    args = ap.parse_args()
    limit_blas_threads(1)  # thousands of tiny solves: OpenBLAS threads only slow them down
    try:
        folders = floor_folders(args.site, args.floors.split(",") if args.floors else None)
        variants = standard_variants([float(x) for x in _list(args.lags)], _list(args.filters), _list(args.smoothers))
        for folder in folders:
            res = tracking_real(folder, GraphSlamConfig(), variants, maps=("oracle",), folds=args.folds, seed=args.seed)
            print(json.dumps({"floor": folder.name, **res}), flush=True)
    except GraphSlamError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
