#!/usr/bin/env python3
"""Does pinning each of two plain survey processes to its own core help? (a control for `survey-batch`)

16 simulated `crowd --size 2` floors (generated once into OUT/sites); per round, alternating:
the floors one after another in one process (the sequential baseline of `python -m lab.bench batch`),
two plain processes on one thread each (the benchmark's control), and the same two pinned with
`taskset -c 0|1`. Prints each run and the medians' throughput ratios.

    python lab/batch/batch_pinning.py OUT --rounds 3
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

from lab.bench.update import _ONE_THREAD, _SEQUENTIAL
from graphslam import simulate, write_session


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out")
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    root = Path(args.out)
    sites = root / "sites"
    names = [f"site{k // 4}/F{k % 4}" for k in range(16)]
    if not sites.exists():
        for k, name in enumerate(names):
            for s in simulate("crowd", seed=k, size=2).survey:
                write_session(s, sites / name / f"{s.session_id}.mcap")
    env = {**os.environ, "RERUN": "off"}
    walls: dict[str, list[float]] = {"sequential": [], "plain": [], "pinned": []}

    def survey(names_: list[str], out: str, extra_env: dict, pin: int | None) -> subprocess.Popen:
        pre = ["taskset", "-c", str(pin)] if pin is not None else []
        cmd = pre + [sys.executable, "-c", _SEQUENTIAL, str(sites), str(root / out), json.dumps(names_)]
        return subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env={**env, **extra_env})

    for r in range(args.rounds):
        for kind in walls:
            t = time.perf_counter()
            if kind == "sequential":
                procs = [survey(names, f"seq{r}", {}, None)]
            else:
                procs = [survey(names[k::2], f"{kind}{r}", _ONE_THREAD, k if kind == "pinned" else None) for k in (0, 1)]
            if any(p.wait() != 0 for p in procs):
                raise SystemExit(f"{kind} run failed")
            walls[kind].append(time.perf_counter() - t)
            print(f"{kind} round {r + 1}: {walls[kind][-1]:.2f} s", flush=True)
    med = {k: statistics.median(v) for k, v in walls.items()}
    print(json.dumps({**{f"{k}_wall_s": round(v, 2) for k, v in med.items()},
                      "plain_vs_sequential": round(med["sequential"] / med["plain"], 3),
                      "pinned_vs_sequential": round(med["sequential"] / med["pinned"], 3)}))


if __name__ == "__main__":
    main()
