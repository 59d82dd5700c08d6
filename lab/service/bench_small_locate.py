"""CPU per ``KnnLocator.locate`` call for 1 and 8 queries, two checkouts side by side.

    python lab/service/bench_small_locate.py --base /tmp/sq_base --rounds 7

One worker process per checkout (maps built once), rounds alternate base / this checkout;
each round times ``calls`` locate calls with ``time.process_time``; medians over rounds.
Maps: UJIIndoorLoc training (19,937 refs: index auto = IVF, and exact), and the simulator's
``paper`` survey (oracle radio map, exact). Queries: scans of the validation set / the map's own
scans with readings jittered.
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

UJI = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "ujiindoorloc"


def _worker() -> None:  # pragma: no cover - benchmark
    import numpy as np

    from graphslam import KnnConfig, KnnLocator, limit_blas_threads
    from lab.bench.ujiindoorloc import read_ujiindoorloc

    limit_blas_threads(1)
    rng = np.random.default_rng(0)
    maps = {}
    tr = read_ujiindoorloc(UJI / "trainingData.csv.gz")
    va = read_ujiindoorloc(UJI / "validationData.csv.gz")
    uji = tr.to_radio_map()
    names = list(va.bssids)
    vscans = [{names[j]: float(r[j]) for j in np.flatnonzero(np.isfinite(r))} for r in va.rssi]
    maps["uji"] = (uji, vscans)
    import graphslam
    from graphslam import simulate

    walks = simulate("paper", seed=0).survey
    sim = graphslam.oracle_radio_map(list(walks))
    sscans = [{b: v + float(rng.normal(0, 3)) for b, v in s.items()} for w in walks for s in (sc.readings for sc in w.scans)]
    maps["sim"] = (sim, sscans)
    locs = {}
    for mname, (rm, scans) in maps.items():
        for metric in ("sorensen", "eq9"):
            for index in ("auto", "exact"):
                if mname == "sim" and index == "auto" and len(rm) < 5000:
                    continue
                locs[(mname, metric, index)] = KnnLocator(rm, KnnConfig(metric=metric, index=index))
    print(json.dumps({"ready": True, "sim_refs": len(sim), "uji_refs": len(uji)}), flush=True)
    for line in sys.stdin:
        calls = int(line)
        out = {}
        for (mname, metric, index), loc in locs.items():
            scans = maps[mname][1]
            for nq in (1, 8):
                sets = [[scans[int(i)] for i in rng.integers(len(scans), size=nq)] for _ in range(64)]
                loc.locate(sets[0])
                t0 = time.process_time()
                for c in range(calls):
                    loc.locate(sets[c % 64])
                out[f"{mname} {metric} {loc.index_kind} q={nq}"] = (time.process_time() - t0) / calls * 1e6
        print(json.dumps(out), flush=True)


def main() -> None:  # pragma: no cover - benchmark
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--base", required=True, help="checkout to compare with (e.g. a copy of main)")
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--calls", type=int, default=300)
    a = ap.parse_args()
    here = Path(__file__).resolve().parents[2]
    procs = {}
    for name, root in (("base", Path(a.base).resolve()), ("new", here)):
        env = dict(os.environ, PYTHONPATH=str(root), OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
        # the worker is this file's (a base checkout may file the lab otherwise), graphslam the root's
        procs[name] = subprocess.Popen([sys.executable, "-c", f"import sys, runpy; sys.path.insert(0, {str(root)!r}); "
                                        f"runpy.run_path({str(Path(__file__).resolve())!r})['_worker']()"],
                                       cwd=root, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    for p in procs.values():
        print(p.stdout.readline().strip(), file=sys.stderr)
    res: dict[str, dict[str, list[float]]] = {"base": {}, "new": {}}
    for r in range(a.rounds):
        for name in (("base", "new") if r % 2 == 0 else ("new", "base")):
            procs[name].stdin.write(f"{a.calls}\n")
            procs[name].stdin.flush()
            for k, v in json.loads(procs[name].stdout.readline()).items():
                res[name].setdefault(k, []).append(v)
    for p in procs.values():
        p.stdin.close()
        p.wait()
    print(f"{'case':<34} {'base µs':>9} {'new µs':>9} {'ratio':>6}")
    for k in res["base"]:
        b, n = statistics.median(res["base"][k]), statistics.median(res["new"][k])
        print(f"{k:<34} {b:9.0f} {n:9.0f} {b / n:6.2f}")


if __name__ == "__main__":
    main()
