#!/usr/bin/env python3
"""Do the two kNN metrics' fixes err independently enough to average? (a diagnostic)

The folds and oracle maps of ``bench tracking-real`` (5 seeded folds on ILC, leave one route out
on IPIN; ground truth places the map's scans and scores, nothing is chosen on it): each held-out
scan located with k = 3 under the paper's eq. 9 and under Sørensen, and with the mean of the two
fixes (1 : 1, and 1 : 2 toward Sørensen); mean landmark error (m) of each fix track, interpolated
as ``bench tracking-real`` scores kNN.

    python lab/tracking/knn_fix_ensemble.py FOLDER [route|FOLDS]
"""

from __future__ import annotations

import sys

import numpy as np

from graphslam import (
    held_out_folds, interpolate_xy, KnnConfig, KnnLocator, oracle_radio_map, PoseTrack, read_survey,
    walk_landmarks,
)



def main(argv: list[str]) -> int:
    if not 1 <= len(argv) <= 2:
        print(__doc__, file=sys.stderr)
        return 2
    folder, folds = argv[0], argv[1] if len(argv) > 1 else "5"
    walks = [w for w in read_survey([folder]) if len(w.landmarks) >= 2 and len(w.scans) and len(w.steps) >= 2]
    errs: dict[str, list[np.ndarray]] = {}
    for _, test in held_out_folds(walks, None if folds == "route" else int(folds), 0):
        held = set(test)
        rm = oracle_radio_map([w for i, w in enumerate(walks) if i not in held])
        locators = {m: KnnLocator(rm, KnnConfig(k=3, metric=m)) for m in ("eq9", "sorensen")}
        for i in test:
            w = walks[i]
            t, marks = walk_landmarks(w)
            st = np.array([sc.t_ns for sc in w.scans])
            fix = {m: loc.locate([sc.readings for sc in w.scans]) for m, loc in locators.items()}
            ok = fix["eq9"].valid & fix["sorensen"].valid
            if not ok.any():
                continue
            e9, so = fix["eq9"].xy, fix["sorensen"].xy
            for name, xy in {"eq9": e9, "sorensen": so, "mean 1:1": 0.5 * (e9 + so), "mean 1:2": (e9 + 2 * so) / 3}.items():
                track = PoseTrack(st[ok], xy[ok], np.zeros(int(ok.sum())))
                errs.setdefault(name, []).append(np.linalg.norm(interpolate_xy(track, t) - marks, axis=1))
    print(folder, {k: round(float(np.concatenate(v).mean()), 3) for k, v in errs.items()})
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
