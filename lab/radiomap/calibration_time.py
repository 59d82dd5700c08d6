"""How long the radio map's calibration (``sigma_m`` by score bins and the outside test) takes on a
map ``graphslam survey`` wrote: the median of RUNS calls of ``calibrate_uncertainty`` with the
product's defaults (one warm-up call first), and what it found (the same on every run).

    graphslam simulate paper --size 12 -o /tmp/p12 && graphslam survey /tmp/p12 -o /tmp/s12
    python lab/radiomap/calibration_time.py /tmp/s12/radio_map.parquet 5
"""

from __future__ import annotations

import json
import statistics
import sys
import time

from graphslam import calibrate_uncertainty, read_radio_map


def main(path: str, runs: int = 5) -> None:
    rm = read_radio_map(path)
    calibrate_uncertainty(rm)
    times = []
    for _ in range(runs):
        t = time.perf_counter()
        u = calibrate_uncertainty(rm)
        times.append(time.perf_counter() - t)
    print(json.dumps({"fingerprints": len(rm), "runs": runs, "median_s": round(statistics.median(times), 3),
                      "scales": None if u is None else list(u.scales), "n": None if u is None else u.n}))


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 5)
