"""Time ``read_survey`` of this checkout against another checkout, side by side.

Each measurement is a fresh process (so imports and caches do not carry over); old and new
runs alternate, and the medians of wall and CPU time are reported with the load average.

    python lab/speed/bench_read.py --base /path/to/base-checkout DATA [DATA ...] [--rounds 5]

``DATA``: a folder of .mcap recordings (or several, one survey each). Prints one JSON line per
data folder: {"data", "sessions", "messages", "new_wall_s", "old_wall_s", "new_cpu_s", "old_cpu_s", ...}.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]

_CHILD = r"""
import json, sys, time
import graphslam
from graphslam.io.mcap_reader import read_survey
paths = sys.argv[1:]
survey = read_survey(paths)  # warm-up: imports, file cache
best = []
for _ in range(3):
    w, c = time.perf_counter(), time.process_time()
    read_survey(paths)
    best.append((time.perf_counter() - w, time.process_time() - c))
best.sort()
n = sum(len(s.steps) + len(s.scans) + len(s.landmarks) + (len(s.ground_truth) if s.ground_truth else 0) for s in survey)
cpu = sorted(b[1] for b in best)[1]
row = {"module": graphslam.__file__, "wall": best[1][0], "cpu": cpu, "sessions": len(survey), "messages": n}
print(json.dumps(row))
"""


def run(checkout: Path, data: str) -> dict:
    env = dict(os.environ, PYTHONPATH=str(checkout))
    # cwd = the checkout: `python -c` puts the working folder first on sys.path
    out = subprocess.run(
        [sys.executable, "-c", _CHILD, str(Path(data).resolve())], env=env, cwd=checkout, capture_output=True,
        text=True, check=True,
    )
    return json.loads(out.stdout)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", nargs="+")
    ap.add_argument("--base", required=True, type=Path, help="checkout of the commit to compare with")
    ap.add_argument("--rounds", type=int, default=5)
    a = ap.parse_args()
    for data in a.data:
        new, old = [], []
        load0 = os.getloadavg()
        for _ in range(a.rounds):
            new.append(run(REPO, data))
            old.append(run(a.base, data))
        assert new[0]["module"] != old[0]["module"], "both runs imported the same graphslam"
        cols = (("new_wall_s", new, "wall"), ("old_wall_s", old, "wall"), ("new_cpu_s", new, "cpu"),
                ("old_cpu_s", old, "cpu"))
        med = {k: round(statistics.median(r[m] for r in rows), 4) for k, rows, m in cols}
        print(json.dumps({
            "data": data, "sessions": new[0]["sessions"], "messages": new[0]["messages"], **med,
            "speedup_wall": round(med["old_wall_s"] / med["new_wall_s"], 2),
            "speedup_cpu": round(med["old_cpu_s"] / med["new_cpu_s"], 2),
            "rounds": a.rounds, "load_avg_before": [round(x, 2) for x in load0],
            "load_avg_after": [round(x, 2) for x in os.getloadavg()],
        }))


if __name__ == "__main__":
    main()
