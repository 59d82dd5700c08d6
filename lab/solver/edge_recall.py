#!/usr/bin/env python3
"""Recall of the IVF edge candidates against the exact edge set, on simulated ``paper`` surveys.

Both edge sets come from ``propose_edges`` with the default thresholds, exclusions and cap;
only the candidate source differs. Recall = |ivf & exact| / |exact|, precision = |ivf &
exact| / |ivf|; seconds are wall time of ``propose_edges`` (window thresholds excluded).

    python lab/solver/edge_recall.py --sizes 1,4,12 [--seed 0] [--neighbours 32] [--probes 8]
"""

from __future__ import annotations

import argparse
import json
import os
import time

from graphslam import associate, GraphSlamConfig, propose_edges, simulate, window_thresholds


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", default="1,4")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--neighbours", type=int, default=32)
    ap.add_argument("--probes", type=int, default=8)
    args = ap.parse_args()
    cfg = GraphSlamConfig()
    e, f = cfg.edges, cfg.fingerprint
    for size in (float(s) for s in args.sizes.split(",")):
        survey = simulate("paper", seed=args.seed, size=size).survey
        fp = associate(survey, max_gap_s=f.max_scan_step_gap_s, missing_dbm=f.missing_rssi_dbm, min_rssi_dbm=f.min_rssi_dbm)
        thr = window_thresholds(fp, e.window_steps)
        common = dict(
            exclude_same_session_s=e.exclude_same_session_s, exclude_same_session_m=e.exclude_same_session_m,
            max_per_fingerprint=e.max_per_fingerprint, min_common_aps=e.min_common_aps, block_rows=e.chunk_rows,
            ivf_neighbours=args.neighbours, ivf_probes=args.probes,
        )
        sets, secs = {}, {}
        for source in ("exact", "ivf"):
            t = time.perf_counter()
            edges = propose_edges(fp, thr, candidates=source, **common)
            secs[source] = round(time.perf_counter() - t, 3)
            sets[source] = set(zip(edges.i.tolist(), edges.j.tolist()))
        both = len(sets["ivf"] & sets["exact"])
        print(json.dumps({
            "size": size, "fingerprints": len(fp), "exact_edges": len(sets["exact"]), "ivf_edges": len(sets["ivf"]),
            "recall": round(both / max(1, len(sets["exact"])), 4), "precision": round(both / max(1, len(sets["ivf"])), 4),
            "exact_s": secs["exact"], "ivf_s": secs["ivf"], "load_1min": round(os.getloadavg()[0], 2),
        }), flush=True)


if __name__ == "__main__":
    main()
