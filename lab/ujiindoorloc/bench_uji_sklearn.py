#!/usr/bin/env python3
"""graphslam kNN (eq. 9) vs scikit-learn KNeighborsRegressor on UJIIndoorLoc, side by side.

Both train on trainingData and answer all 1,111 validationData fingerprints at the same k.
scikit-learn: brute force, Euclidean, on the dense 520-column matrix with "not heard"
(100) replaced by --sk-missing dBm (default -110), weights "distance" or "uniform" to
match ours. Our eq. 9 metric as a scikit-learn callable is not feasible (a Python call
per pair: 22 M calls per run), so the comparison is "our metric + our engine" vs
"Euclidean + scikit-learn's engine".

Timing: the query phase only (sklearn ``predict`` vs our ``locate``, which also encodes
the queries over the map's AP index and votes floor and building), alternated, median of
--repeats runs (>= 5). The two engines use the machine's cores (OpenMP/BLAS threads vs
our 2 search threads). Prints a table, then one JSON line.

    python lab/ujiindoorloc/bench_uji_sklearn.py [DATA_DIR] [--k 7] [--repeats 7]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
DEFAULT_DATA = Path(os.environ.get("GRAPHSLAM_DATA", REPO.parent / "shared" / "data")) / "ujiindoorloc"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data_dir", nargs="?", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--k", type=int, default=7)
    ap.add_argument("--weighted", action=argparse.BooleanOptionalAction, default=True)
    ap.add_argument("--min-rssi", type=float, default=-95.0, help="ours: drop readings below (dBm)")
    ap.add_argument("--missing-dbm", type=float, default=-100.0, help="ours: eq. 9 value of an unheard AP")
    ap.add_argument("--sk-missing", type=float, default=-110.0, help="sklearn: fill value for 'not heard'")
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()
    if args.repeats < 5:
        ap.error("--repeats must be >= 5 (the ratio is a median)")

    from sklearn.neighbors import KNeighborsClassifier, KNeighborsRegressor

    from graphslam import KnnConfig, KnnLocator
    from lab.bench.uji import TEST_FILE, TRAIN_FILE, find_uji_file
    from lab.bench.ujiindoorloc import read_ujiindoorloc

    try:
        train = read_ujiindoorloc(find_uji_file(args.data_dir, TRAIN_FILE))
        test = read_ujiindoorloc(find_uji_file(args.data_dir, TEST_FILE))
    except Exception as e:  # noqa: BLE001 - a script: one line and exit
        print(f"error: {e}", file=sys.stderr)
        return 2

    rm = train.to_radio_map(missing_dbm=args.missing_dbm, min_rssi_dbm=args.min_rssi)
    loc = KnnLocator(rm, KnnConfig(k=args.k, weighted=args.weighted, metric="eq9", index="exact"))
    queries = test.fingerprints(missing_dbm=args.missing_dbm, min_rssi_dbm=args.min_rssi)

    weights = "distance" if args.weighted else "uniform"
    x_train = np.nan_to_num(train.rssi, nan=args.sk_missing)
    x_test = np.nan_to_num(test.rssi, nan=args.sk_missing)
    sk = KNeighborsRegressor(n_neighbors=args.k, algorithm="brute", metric="euclidean", weights=weights)
    sk.fit(x_train, train.xy)

    ours_t, sk_t = [], []
    res = sk_xy = None
    for _ in range(args.repeats):  # alternate, so load from other processes hits both alike
        t0 = time.perf_counter()
        res = loc.locate(queries)
        ours_t.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        sk_xy = sk.predict(x_test)
        sk_t.append(time.perf_counter() - t0)
    assert res is not None and sk_xy is not None

    # sklearn floor/building (not timed): the same neighbours searched twice more.
    fb = KNeighborsClassifier(n_neighbors=args.k, algorithm="brute", weights=weights)
    fb.fit(x_train, np.column_stack([train.floor, train.building]))
    sk_fb = fb.predict(x_test)

    def stats(xy: np.ndarray) -> dict[str, float]:
        e = np.linalg.norm(xy - test.xy, axis=1)
        return {"mean_error_m": float(e.mean()), "median_error_m": float(np.median(e)),
                "p75_error_m": float(np.percentile(e, 75))}

    ours = {
        **stats(res.xy),
        "building_hit": float(np.mean(res.building == test.building.astype(str))),
        "floor_hit": float(np.mean(res.floor == test.floor.astype(str))),
        "query_time_s": float(np.median(ours_t)),
    }
    theirs = {
        **stats(sk_xy),
        "building_hit": float(np.mean(sk_fb[:, 1] == test.building)),
        "floor_hit": float(np.mean(sk_fb[:, 0] == test.floor)),
        "query_time_s": float(np.median(sk_t)),
    }
    for d in (ours, theirs):
        d["queries_per_s"] = len(test) / d["query_time_s"]
    ratio = theirs["query_time_s"] / ours["query_time_s"]
    print(f"{'':24}{'graphslam eq.9':>16}{'sklearn eucl.':>16}")
    for key in ("mean_error_m", "median_error_m", "p75_error_m", "building_hit", "floor_hit", "query_time_s",
                "queries_per_s"):
        print(f"{key:24}{ours[key]:>16.4f}{theirs[key]:>16.4f}")
    print(f"speed ratio (sklearn time / ours, median of {args.repeats}): {ratio:.2f}")
    out = {
        "k": args.k, "weighted": args.weighted, "min_rssi_dbm": args.min_rssi, "missing_dbm": args.missing_dbm,
        "sk_missing_dbm": args.sk_missing, "repeats": args.repeats, "n_train": len(train), "n_test": len(test),
        "ours": {k: round(v, 4) for k, v in ours.items()},
        "sklearn": {k: round(v, 4) for k, v in theirs.items()},
        "speed_ratio_sklearn_over_ours": round(ratio, 3),
        "ours_times_s": [round(t, 4) for t in ours_t], "sklearn_times_s": [round(t, 4) for t in sk_t],
    }
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
