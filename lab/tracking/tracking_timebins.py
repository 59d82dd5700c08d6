#!/usr/bin/env python3
"""Where along a walk does the tracker gain over kNN? Errors by time since the walk's start.

ILC-style seeded folds of a real floor (oracle map of the other walks, as ``bench tracking-real``);
per variant the mean landmark error in bins of seconds since the first step, and the share inside
the 95 % ellipse.

    python lab/tracking/tracking_timebins.py FOLDER FOLD_IDS NAMES [NAME=EXPR ...]
    python lab/tracking/tracking_timebins.py ../shared/data/ilc20/site1/B1 0,1 mixture,map 'g=TrackConfig(motion={"velocity_sigma_mps": 0.3})'

Built-in names: ``best``, ``mixture`` (default), ``map`` (``--filter ekf --smooth map``, offline),
``norssi`` (steps and kNN fixes only).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from graphslam import (
    ApModels, held_out_folds, limit_blas_threads, oracle_radio_map, read_survey, score_walks, show_progress,
    TrackConfig, Variant,
)


BINS_S = [0, 5, 10, 15, 20, 30, np.inf]


def main(argv: list[str]) -> int:
    if len(argv) < 3:
        print(__doc__, file=sys.stderr)
        return 2
    folder, fold_ids = Path(argv[0]), [int(x) for x in argv[1].split(",")]
    V = {"best": TrackConfig(fixed_lag={"bank_report": "best"}), "mixture": TrackConfig(), "map": TrackConfig(filter={"kind": "ekf", "smoother": "map"}),
         "norssi": TrackConfig(rssi={"enabled": False})}
    for extra in argv[3:]:
        name, expr = extra.split("=", 1)
        V[name] = eval(expr, {"TrackConfig": TrackConfig})  # a benchmark script's own argument
    variants = [Variant(n, V[n]) for n in argv[2].split(",")]
    show_progress()  # folds, walks and the self-calibration replay on stderr (bar on a terminal)
    limit_blas_threads(1)
    walks = [w for w in read_survey([folder]) if len(w.landmarks) >= 2 and len(w.scans) and len(w.steps) >= 2]
    split = held_out_folds(walks, 5, 0)
    acc: dict[str, dict[str, list]] = {}
    for fi in fold_ids:
        _, test = split[fi]
        train = [w for i, w in enumerate(walks) if i not in set(test)]
        rm = oracle_radio_map(train)
        res = score_walks(rm, ApModels.fit(rm), [walks[i] for i in test], variants)
        for v, d in res.items():
            for k in ("err", "t", "inside"):
                acc.setdefault(v, {}).setdefault(k, []).extend(d.get(k, []))
    for v, d in acc.items():
        e, t = np.concatenate(d["err"]), np.concatenate(d["t"])
        cells = [f"{e[(t >= a) & (t < b)].mean():.2f}({((t >= a) & (t < b)).sum()})" for a, b in zip(BINS_S[:-1], BINS_S[1:])]
        inside = f" in95 {np.concatenate(d['inside']).mean():.3f}" if d["inside"] else ""
        print(f"{v:10s} mean {e.mean():.3f}  by t [s] {BINS_S[:-1]}: {' '.join(cells)}{inside}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
