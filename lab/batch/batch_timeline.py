"""When each floor of a `survey-batch` ran: start and end of every floor (from its row's seconds and
the time its result arrived), the cluster's start-up before the first floor and the tail after the
last one. Shows whether the scheduler or the machine limits the batch.

    python lab/batch/batch_timeline.py SITES_ROOT [--workers 2]

SITES_ROOT as for `graphslam survey-batch`; outputs go to a temporary folder.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time

from graphslam import run_batch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sites_root")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    t0 = time.perf_counter()
    events: list[tuple[float, str, float]] = []
    with tempfile.TemporaryDirectory(prefix="graphslam-timeline-") as out:
        run_batch(args.sites_root, out, workers=args.workers,
                  on_floor=lambda row: events.append((time.perf_counter() - t0, row.floor, row.seconds)))
    total = time.perf_counter() - t0
    for end, floor, seconds in events:
        print(f"{end - seconds:6.2f} -> {end:6.2f}  {seconds:5.2f} s  {floor}")
    print(json.dumps({"wall_s": round(total, 2), "first_floor_start_s": round(min(e - s for e, _, s in events), 2),
                      "last_floor_end_s": round(max(e for e, _, _ in events), 2),
                      "floor_seconds_sum": round(sum(s for *_, s in events), 2)}))


if __name__ == "__main__":  # the local cluster's workers re-import this file
    main()
