#!/usr/bin/env python3
"""How wrong is the tracker's walking direction, and would fixes searched near its own estimate do
better than the global ones? (diagnostics; ground truth scores only)

ILC-style seeded folds of a real floor (oracle map of the other walks and the floor plan beside
the walks, as ``bench tracking-real``), the default tracker on each held-out walk. Two modes:

- ``heading``: the angle between the reported map-frame velocity and the true one (the walk's
  odometry turned by its rigid fit to its landmarks), by time since the first step, at steps
  where both move (> 0.3 / 0.2 m/s): the share under 30 deg, 30-60, 60-120 and over 120 (flips);
- ``local``: each scan's k = 3 Sørensen fix among only the map fingerprints within 5 / 10 / 15 m of
  the tracker's reported position at the scan (or inside the 99 % gate of its covariance plus a
  2-m fix), against the global fix and the tracker itself, scored at the landmarks.

    python lab/tracking/tracking_heading_errors.py FOLDER FOLD_IDS heading|local
    python lab/tracking/tracking_heading_errors.py ../shared/data/ilc20/site1/B1 0,1 heading
"""

from __future__ import annotations

import sys
from collections import defaultdict

import numpy as np

from graphslam import (
    ApModels, fit_se2, floor_plan_area, held_out_folds, interpolate_cov, interpolate_xy, KnnConfig,
    KnnLocator, limit_blas_threads, oracle_radio_map, PoseTrack, read_survey, TrackConfig, Tracker,
    walk_landmarks, WEIGHT_EPS_DB,
)


BINS_S = [(0, 2), (2, 4), (4, 8), (8, 15), (15, 40)]


def _local_fix(D: np.ndarray, xy: np.ndarray, mask: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    d = np.where(mask & np.isfinite(D), D, np.inf)
    nn = np.argsort(d)[:3]
    nn = nn[np.isfinite(d[nn])]
    if not len(nn):
        return fallback
    w = 1.0 / (d[nn] + WEIGHT_EPS_DB)
    return (w[:, None] * xy[nn]).sum(axis=0) / w.sum()


def main(argv: list[str]) -> int:
    if len(argv) != 3 or argv[2] not in ("heading", "local"):
        print(__doc__, file=sys.stderr)
        return 2
    folder, fold_ids, mode = argv[0], [int(x) for x in argv[1].split(",")], argv[2]
    limit_blas_threads(1)
    walks = [w for w in read_survey([folder]) if len(w.landmarks) >= 2 and len(w.scans) and len(w.steps) >= 2]
    area, split = floor_plan_area(folder), held_out_folds(walks, 5, 0)
    rows: list[tuple[float, float]] = []
    errs: dict[str, list[np.ndarray]] = defaultdict(list)
    for fi in fold_ids:
        test = split[fi][1]
        rm = oracle_radio_map([w for i, w in enumerate(walks) if i not in set(test)])
        trk = Tracker.on_map(rm, ApModels.fit(rm), TrackConfig(), area=area)
        loc = KnnLocator(rm, KnnConfig(k=3, metric="sorensen"))
        for i in test:
            w = walks[i]
            t, marks = walk_landmarks(w)
            tr = trk.track(w)
            if mode == "heading":
                th = float(fit_se2(interpolate_xy(w.steps, t), marks)[2])  # odometry -> site
                v_true = np.diff(w.steps.xy, axis=0) @ np.array([[np.cos(th), np.sin(th)], [-np.sin(th), np.cos(th)]])
                v = tr.x[:-1, 2:4]
                ok = (np.linalg.norm(v_true, axis=1) > 0.3) & (np.linalg.norm(v, axis=1) > 0.2)
                d = np.abs(np.angle(np.exp(1j * (np.arctan2(v[:, 1], v[:, 0]) - np.arctan2(v_true[:, 1], v_true[:, 0])))))
                ts = (w.steps.t_ns[:-1] - w.steps.t_ns[0]) / 1e9
                rows += list(zip(ts[ok], d[ok]))
                continue
            st = np.array([sc.t_ns for sc in w.scans])
            q = rm.encode([sc.readings for sc in w.scans])
            fx, D = loc.locate(q), loc.distances(q)
            p = interpolate_xy(PoseTrack(tr.t_ns, tr.xy, np.zeros(len(tr.t_ns))), st.astype(float))
            cov = interpolate_cov(tr.t_ns, tr.P, st.astype(float))
            tracks = {"tracker": (tr.t_ns, tr.xy), "global": (st[fx.valid], fx.xy[fx.valid])}
            for r in (5.0, 10.0, 15.0, "gate"):
                out = np.zeros((len(st), 2))
                for s in range(len(st)):
                    e = rm.xy - p[s]
                    if r == "gate":
                        m2 = np.einsum("ni,ij,nj->n", e, np.linalg.inv(cov[s, :2, :2] + 4.0 * np.eye(2)), e)
                        mask = m2 <= 9.21
                    else:
                        mask = (e * e).sum(axis=1) <= r * r
                    out[s] = _local_fix(D[s], rm.xy, mask, fx.xy[s])
                ok = np.isfinite(out[:, 0])
                tracks[f"local {r}"] = (st[ok], out[ok])
            for name, (tt, xy) in tracks.items():
                errs[name].append(np.linalg.norm(interpolate_xy(PoseTrack(tt, xy, np.zeros(len(tt))), t) - marks, axis=1))
    if mode == "local":
        print(folder, "folds", fold_ids, {k: round(float(np.concatenate(v).mean()), 3) for k, v in errs.items()})
        return 0
    r = np.array(rows)
    for a, b in BINS_S:
        m = (r[:, 0] >= a) & (r[:, 0] < b)
        d = np.degrees(r[m, 1])
        print(f"{folder} t {a}-{b} s: n {m.sum()}, median {np.median(d):.0f} deg; < 30: {np.mean(d < 30):.2f}, "
              f"30-60: {np.mean((d >= 30) & (d < 60)):.2f}, 60-120: {np.mean((d >= 60) & (d < 120)):.2f}, > 120: {np.mean(d >= 120):.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
