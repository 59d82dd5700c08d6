#!/usr/bin/env python3
"""Tracking on REAL recordings (ILC 2.0 site1) given a radio map: kNN vs EKF vs EKF + smoother.

Issue #6 is blocked (our alignment cannot build these floors' map), so this measures the
tracking half on its own: the radio map is built from the OTHER walks' scans placed by
their waypoint-fitted rigid poses (an oracle survey: ground truth makes the map, as a
perfect survey would; it never reaches the tracker), APs fitted from it (``fit-aps``), and
every held-out walk tracked with its real foot-module steps and phone scans exactly as
``graphslam track`` does (start: kNN fix; heading unknown, 8 hypotheses). Walks are split
into 5 folds per floor (seeded).

Errors at the surveyor's waypoint times, against the waypoints:
- ``knn``: the held-out scans' kNN fixes (k = 3), linearly interpolated in time;
- ``ekf`` (causal) and ``ekf+map`` (offline whole-run MAP), each also with every scan's kNN
  fix fused as a position reading (``ekf+knn``, ``ekf+knn+map``; ``track --knn-fixes``): the
  tracker's step output interpolated in time;
- ``rigid_oracle``: the walk's own dead reckoning under ITS OWN waypoint fit: the best any
  rigid placement of the walk could do (its drift), and the map's own position error.

    python scripts/ilc_tracking.py [SITE_DIR] [--floors F1,F3] [--folds 5] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from graphslam.app.bench import variant_name
from graphslam.core.tracking.apmodel import ApModels
from graphslam.core.survey.evaluate import interpolate_xy
from graphslam.core.survey.initialise import fit_se2, se2_apply
from graphslam.core.radiomap.knn import KnnConfig, KnnLocator
from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.core.types import PoseTrack
from graphslam.errors import GraphSlamError
from graphslam.io.mcap_reader import floor_folders, read_survey
from graphslam.app.track import TrackConfig, track_sessions

REPO = Path(__file__).resolve().parents[1]
DEFAULT_SITE = Path(os.environ.get("GRAPHSLAM_DATA", REPO.parent / "shared" / "data")) / "ilc20" / "site1"
VARIANTS = (("ekf", "none", False), ("ekf", "map", False), ("ekf", "none", True), ("ekf", "map", True))


def _stats(e: NDArray) -> dict[str, float]:
    return {
        "n": int(e.size), "mean_m": round(float(e.mean()), 2), "median_m": round(float(np.median(e)), 2),
        "p90_m": round(float(np.percentile(e, 90)), 2),
    }


def floor(path: Path, folds: int, seed: int) -> dict:
    survey = read_survey([path])
    walks = [w for w in survey if len(w.landmarks) >= 2 and len(w.scans) and len(w.steps) >= 2]
    T, wp_t, wp_xy = [], [], []
    for w in walks:
        t = np.array([m.t_ns for m in w.landmarks], float)
        xy = np.array([[m.x, m.y] for m in w.landmarks])
        T.append(fit_se2(interpolate_xy(w.steps, t), xy))
        wp_t.append(t)
        wp_xy.append(xy)
    fold = np.random.default_rng(seed).permutation(len(walks)) % folds
    errs: dict[str, list[NDArray]] = {"knn": [], "rigid_oracle": [], **{variant_name(*v): [] for v in VARIANTS}}
    n_failed, t0 = 0, time.perf_counter()
    for f in range(folds):
        train = [i for i in range(len(walks)) if fold[i] != f]
        test = [i for i in range(len(walks)) if fold[i] == f]
        scans, xy, sid, ts = [], [], [], []
        for i in train:
            w = walks[i]
            t = np.array([sc.t_ns for sc in w.scans], float)
            xy.append(se2_apply(T[i], interpolate_xy(w.steps, t)))
            scans += [dict(sc.readings) for sc in w.scans]
            sid += [w.session_id] * len(w.scans)
            ts += [sc.t_ns for sc in w.scans]
        rm = RadioMap.from_scans(scans, np.concatenate(xy), session_ids=sid, t_ns=ts, frame="site")
        models = ApModels.fit(rm)
        locator = KnnLocator(rm, KnnConfig(k=3))
        for i in test:
            w = walks[i]
            errs["rigid_oracle"].append(np.linalg.norm(se2_apply(T[i], interpolate_xy(w.steps, wp_t[i])) - wp_xy[i], axis=1))
            fix = locator.locate([sc.readings for sc in w.scans])
            ok = fix.valid
            if ok.sum() >= 1:
                knn_track = PoseTrack(np.array([sc.t_ns for sc in w.scans])[ok], fix.xy[ok], np.zeros(int(ok.sum())))
                errs["knn"].append(np.linalg.norm(interpolate_xy(knn_track, wp_t[i]) - wp_xy[i], axis=1))
            for kind, sm, fx in VARIANTS:
                try:
                    (tr,) = track_sessions([w], rm, models, TrackConfig(filter=kind, smoother=sm, knn_fixes=fx))
                except GraphSlamError:
                    n_failed += 1
                    continue
                est = interpolate_xy(PoseTrack(tr.t_ns, tr.xy, np.zeros(len(tr.t_ns))), wp_t[i])
                errs[variant_name(kind, sm, fx)].append(np.linalg.norm(est - wp_xy[i], axis=1))
    out: dict = {"floor": path.name, "walks": len(walks), "walks_skipped": len(survey) - len(walks), "track_failures": n_failed}
    for name, v in errs.items():
        out[name] = _stats(np.concatenate(v)) if v else None
    out["time_s"] = round(time.perf_counter() - t0, 1)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("site", nargs="?", type=Path, default=DEFAULT_SITE)
    ap.add_argument("--floors", default=None, help="comma-separated, e.g. F1,F3 (default: every floor folder)")
    ap.add_argument("--folds", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    try:
        folders = floor_folders(args.site, args.floors.split(",") if args.floors else None)
    except GraphSlamError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    for folder in folders:
        print(json.dumps(floor(folder, args.folds, args.seed)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
