#!/usr/bin/env python3
"""How far are held-out walks' RSSI readings from the AP models' law, and from the law plus the
map's residual field (``graphslam.core.tracking.rssi_field``)? Diagnostics for the tracker on real walks.

The folds and oracle maps of ``bench tracking-real`` (seeded folds on ILC, leave one route out on
IPIN); per fold, AP models and the field are fitted on the training map only; each held-out reading
of a fitted AP is compared with the model at the reading's true position (ground truth places the
held-out scans: evaluation only). Prints the readings' rms and robust std (1.4826 MAD) in dB.

    python lab/tracking/rssi_field_residuals.py FOLDER route|FOLDS [MAX_FOLDS] [BANDWIDTHS]

    python lab/tracking/rssi_field_residuals.py ../shared/data/ilc20/site1/B1 5 2 1.5,3,5
"""

from __future__ import annotations

import dataclasses
import sys

import numpy as np

from graphslam import (
    ApModels, fit_se2, held_out_folds, interpolate_xy, oracle_radio_map, read_survey, residual_field,
    se2_apply, walk_landmarks,
)



def main(argv: list[str]) -> int:
    if len(argv) < 2:
        print(__doc__, file=sys.stderr)
        return 2
    folder, folds = argv[0], argv[1]
    max_folds = int(argv[2]) if len(argv) > 2 else 1000
    bandwidths = [float(b) for b in argv[3].split(",")] if len(argv) > 3 else [3.0]
    walks = [w for w in read_survey([folder]) if len(w.landmarks) >= 2 and len(w.scans) and len(w.steps) >= 2]
    res: dict[str, list[np.ndarray]] = {}
    for _, test in held_out_folds(walks, None if folds == "route" else int(folds), 0)[:max_folds]:
        train = [w for i, w in enumerate(walks) if i not in set(test)]
        rm = oracle_radio_map(train)
        law = ApModels.fit(rm).path_loss()
        index = {b: a for a, b in enumerate(law.bssids)}
        xy, ap, y = [], [], []
        for i in test:
            w = walks[i]
            t, marks = walk_landmarks(w)
            pos = se2_apply(fit_se2(interpolate_xy(w.steps, t), marks),
                            interpolate_xy(w.steps, np.array([sc.t_ns for sc in w.scans], float)))
            for p, sc in zip(pos, w.scans):
                for b, r in sc.readings.items():
                    if b in index:
                        xy.append(p)
                        ap.append(index[b])
                        y.append(r)
        xy, ap, y = np.array(xy), np.array(ap, np.int64), np.array(y, float)
        res.setdefault("law", []).append(y - law.rss_pairs(xy, ap)[0])
        for bw in bandwidths:
            pl = dataclasses.replace(law, correction=residual_field(rm, law, bandwidth_m=bw, leave_out=False).field)
            res.setdefault(f"law + field {bw:g} m", []).append(y - pl.rss_pairs(xy, ap)[0])
    for name, parts in res.items():
        r = np.concatenate(parts)
        mad = 1.4826 * float(np.median(np.abs(r - np.median(r))))
        print(f"{folder} {name}: {len(r)} readings, rms {np.sqrt(np.mean(r ** 2)):.2f} dB, robust std {mad:.2f} dB")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
