"""How much do two processes slow each other on this machine? A compute-bound kernel (a Python loop)
and a memory-bound one (streaming a 512 MB array), each alone and then as two processes side by
side: the ratio bounds what any two-worker scheduler can reach (`survey-batch`).

    python lab/speed/core_contention.py [--rounds 2]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

_COMPUTE = "import time\nt=time.perf_counter()\nx=0\nfor i in range(30_000_000): x += i * i % 7\nprint(time.perf_counter()-t)"
_MEMORY = ("import time, numpy as np\na=np.random.rand(64_000_000)\nt=time.perf_counter()\n"
           "for _ in range(20): a *= 1.0000001\nprint(time.perf_counter()-t)")


def _run(code: str, n: int) -> list[float]:
    procs = [subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True) for _ in range(n)]
    return [float(p.communicate()[0]) for p in procs]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=2)
    args = ap.parse_args()
    for name, code in (("compute", _COMPUTE), ("memory", _MEMORY)):
        for _ in range(args.rounds):
            alone, pair = _run(code, 1), _run(code, 2)
            print(json.dumps({"kernel": name, "alone_s": round(alone[0], 2), "pair_s": [round(x, 2) for x in pair],
                              "slowdown": round(max(pair) / alone[0], 2)}), flush=True)


if __name__ == "__main__":
    main()
