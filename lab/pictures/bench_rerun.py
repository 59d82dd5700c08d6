"""Time `graphslam survey` with and without `--rerun` (fresh process per run); medians.

    graphslam simulate paper --out /tmp/paper
    python lab/pictures/bench_rerun.py /tmp/paper --runs 5

Prints one JSON object: median end-to-end wall time with/without --rerun, the median
`rerun` step of report.json (log_survey alone), the survey total it reports, and the
.rrd size.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def run(rec: str, out: Path, rrd: Path | None, extra: list[str]) -> tuple[float, dict]:
    cmd = [sys.executable, "-m", "graphslam", "survey", rec, "--out", str(out), "--no-progress", *extra]
    if rrd is not None:
        cmd += ["--rerun", str(rrd)]
    t = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t
    return wall, json.loads((out / "report.json").read_text())["timings_s"]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("recordings")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("extra", nargs="*", help="extra survey options, e.g. --floor-plan P --floor-size W H")
    a = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench-rerun-"))
    rrd = tmp / "survey.rrd"
    walls_on, walls_off, rerun_s, total_on, total_off = [], [], [], [], []
    for k in range(a.runs):  # interleaved: load changes on a shared machine hit both alike
        w, t = run(a.recordings, tmp / f"on{k}", rrd, a.extra)
        walls_on.append(w), rerun_s.append(t["rerun"]), total_on.append(t["total"])
        w, t = run(a.recordings, tmp / f"off{k}", None, [])
        walls_off.append(w), total_off.append(t["total"])
    med = statistics.median
    print(json.dumps({
        "runs": a.runs,
        "wall_s_with_rerun": round(med(walls_on), 3),
        "wall_s_without_rerun": round(med(walls_off), 3),
        "report_total_s_with_rerun": round(med(total_on), 3),
        "report_total_s_without_rerun": round(med(total_off), 3),
        "log_survey_s": round(med(rerun_s), 3),
        "log_survey_share_of_survey": round(med(rerun_s) / med(total_off), 4),
        "rrd_bytes": rrd.stat().st_size,
    }))


if __name__ == "__main__":
    main()
