#!/usr/bin/env python3
"""Tracker variants side by side on a real floor: same folds, maps and self-calibration, one run.

``graphslam.app.tracking_bench.tracking_real`` with named ``TrackConfig`` variants (kNN is always
reported). Folds: ``route`` (leave one route out; IPIN) or a number of seeded random folds (ILC).

    python lab/tracking/tracking_variants.py FOLDER MAPS FOLDS NAMES [NAME=EXPR ...]

    python lab/tracking/tracking_variants.py ../shared/data/ilc20/site1/B1 oracle 5 best,mixture
    python lab/tracking/tracking_variants.py ../shared/data/ipin2023/b100_f-2 oracle,crowdsourced route best,mixture
    python lab/tracking/tracking_variants.py ../shared/data/ipin2023/b100_f-2 oracle route mixroute \\
        'mixroute=TrackConfig(calibration={"replay_route_radius_m": 2.0})'

Built-in names: ``best`` (the lowest-cost heading hypothesis), ``mixture`` (the default), ``ekf``,
``noplan`` (the default without the floor plan). Every other variant gets the floor's walkable area
when ``floor_image.png`` lies beside the walks (the ILC floors; oracle maps only).
``NAME=EXPR`` adds a variant whose ``TrackConfig(...)`` expression is evaluated here. One JSON
line (the floor's result) on stdout.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from graphslam import (
    floor_plan_area, GraphSlamConfig, GraphSlamError, limit_blas_threads, show_progress, TrackConfig,
    tracking_real, Variant,
)


VARIANTS = {
    "best": Variant("best", TrackConfig(fixed_lag={"bank_report": "best"})),
    "mixture": Variant("mixture", TrackConfig(fixed_lag={"bank_report": "mixture"})),
    "ekf": Variant("ekf", TrackConfig(filter={"kind": "ekf"})),
    "noplan": Variant("noplan", TrackConfig(), floor_plan=False),
}


def main(argv: list[str]) -> int:
    if len(argv) < 4:
        print(__doc__, file=sys.stderr)
        return 2
    folder, maps, folds, names = Path(argv[0]), tuple(argv[1].split(",")), argv[2], argv[3].split(",")
    variants = dict(VARIANTS)
    for extra in argv[4:]:
        name, expr = extra.split("=", 1)
        cfg = eval(expr, {"TrackConfig": TrackConfig})  # a benchmark script's own argument
        variants[name] = Variant(name, cfg)
    unknown = [n for n in names if n not in variants]
    if unknown:
        print(f"error: unknown variant {unknown[0]!r}", file=sys.stderr)
        return 2
    show_progress()  # folds, walks and the self-calibration replay on stderr (bar on a terminal)
    limit_blas_threads(1)  # thousands of tiny solves: OpenBLAS threads only slow them down
    t = time.perf_counter()
    try:
        area = floor_plan_area(folder)  # floor_image.png beside the walks (ILC), else none
        res = tracking_real(folder, GraphSlamConfig(), [variants[n] for n in names], maps=maps,
                            folds=None if folds == "route" else int(folds), seed=0, area=area)
    except GraphSlamError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(json.dumps({"floor": folder.name, "seconds": round(time.perf_counter() - t, 1), **res}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
