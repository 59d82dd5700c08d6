#!/usr/bin/env python3
"""What would the fixed-lag tracker gain if it knew its heading (or its start)? (evaluation only)

The target: the online tracker (lag <= 2 s) beating kNN by 15 % on ILC site1's 30-s walks. The
offline smoother shows that the whole walk holds more information than the first seconds; this
script measures which *unknown* the online tracker lacks, by telling it the answer from ground
truth (never done by the product): each held-out walk's rotation odometry -> site frame and its
start position come from the rigid fit of its foot-module/PDR track to its own landmarks, and
replace the tracker's start as

- ``heading``: one hypothesis at the true rotation (5 deg std) instead of the bank of 8;
- ``heading-mod-180``: two hypotheses, the true rotation and its opposite (what a prior from the
  map's corridor directions could tell at best: the axis of the walk, not its sense);
- ``heading-mod-90``: four hypotheses 90 deg apart (a Manhattan-world prior at best);
- ``heading+start``: the true rotation and the true start position (1 m std).

Everything else is ``graphslam track``'s default (fixed-lag 2 s, the bank's mixture report,
self-calibrated noise); the same folds, oracle maps and scoring as ``bench tracking-real``
(``tracking_bench.score_walks``). Mean landmark error per variant, also by seconds since the
walk's first step.

    python lab/tracking/tracking_oracle_bounds.py FOLDER FOLD_IDS [VARIANTS]
    python lab/tracking/tracking_oracle_bounds.py ../shared/data/ilc20/site1/B1 0,1,2,3,4 heading,heading-mod-180,heading+start
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

from graphslam import (
    ApModels, fit_se2, held_out_folds, interpolate_xy, limit_blas_threads, oracle_radio_map, read_survey,
    score_walks, se2_apply, show_progress, TrackConfig, tracking_pipeline as track_module, Variant,
    walk_landmarks,
)


BINS_S = [0, 5, 10, 15, 20, 30, np.inf]
ORACLES = {"heading": 1, "heading-mod-180": 2, "heading-mod-90": 4, "heading+start": 1}
_TRUTH: dict[str, tuple[np.ndarray, np.ndarray]] = {}  # held-out session id -> (SE(2) odometry -> site, start xy)
_product_fixed_lag = track_module._track_fixed_lag


def _oracle_fixed_lag(session_id, model, starts, P0, t, y_v, walked, meas, fixes, cfg, *rest):  # noqa: ANN001, ANN002, ANN202
    """The product's fixed-lag tracker with its start replaced by the oracle's (``cfg.oracle``)."""
    oracle = getattr(cfg, "oracle", None)
    if oracle is not None and session_id in _TRUTH:  # a held-out walk (not the self-calibration's replay)
        T, start = _TRUTH[session_id]
        P0 = P0.copy()
        P0[6, 6] = math.radians(5.0) ** 2
        x0 = starts[0].copy()
        if oracle == "heading+start":
            x0[:2] = start
            P0[0, 0] = P0[1, 1] = 1.0
        n = ORACLES[oracle]
        starts = [np.concatenate([x0[:6], [T[2] + 2.0 * math.pi * k / n]]) for k in range(n)]
    return _product_fixed_lag(session_id, model, starts, P0, t, y_v, walked, meas, fixes, cfg, *rest)  # axes, area, progress


class _OracleConfig(TrackConfig):
    oracle: str | None = None


def main(argv: list[str]) -> int:
    if len(argv) < 2:
        print(__doc__, file=sys.stderr)
        return 2
    folder, fold_ids = Path(argv[0]), [int(x) for x in argv[1].split(",")]
    names = argv[2].split(",") if len(argv) > 2 else list(ORACLES)
    unknown = [n for n in names if n not in ORACLES]
    if unknown:
        print(f"error: unknown variant {unknown[0]!r}; use {', '.join(ORACLES)}", file=sys.stderr)
        return 2
    show_progress()
    limit_blas_threads(1)
    track_module._track_fixed_lag = _oracle_fixed_lag
    walks = [w for w in read_survey([folder]) if len(w.landmarks) >= 2 and len(w.scans) and len(w.steps) >= 2]
    variants = [Variant("default", TrackConfig())] + [Variant(n, _OracleConfig(oracle=n)) for n in names]
    split = held_out_folds(walks, 5, 0)
    acc: dict[str, dict[str, list]] = {}
    for fi in fold_ids:
        _, test = split[fi]
        train = [w for i, w in enumerate(walks) if i not in set(test)]
        _TRUTH.clear()
        for i in test:
            t, marks = walk_landmarks(walks[i])
            T = fit_se2(interpolate_xy(walks[i].steps, t), marks)
            _TRUTH[walks[i].session_id] = (T, se2_apply(T, walks[i].steps.xy[:1])[0])
        rm = oracle_radio_map(train)
        res = score_walks(rm, ApModels.fit(rm), [walks[i] for i in test], variants)
        for v, d in res.items():
            for key in ("err", "t"):
                acc.setdefault(v, {}).setdefault(key, []).extend(d.get(key, []))
    knn = float(np.concatenate(acc["knn"]["err"]).mean())
    for v, d in acc.items():
        e, t = np.concatenate(d["err"]), np.concatenate(d["t"])
        cells = [f"{e[(t >= a) & (t < b)].mean():.2f}({((t >= a) & (t < b)).sum()})" for a, b in zip(BINS_S[:-1], BINS_S[1:])]
        print(f"{v:16s} mean {e.mean():.3f} ({e.mean() / knn - 1:+.1%} vs kNN)  by t [s] {BINS_S[:-1]}: {' '.join(cells)}",
              flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
