"""Coverage of a radio map: which answers come from where the map's walks have not been
(lab/journal/coverage.md). Truth places the held-out walks and scores, never a model.

Two studies, one per mode:

``statistic FOLDER...``: the outside test's statistic. ``graphslam bench locate-real``'s folds and
figures (the share of held-out scans flagged outside among those more than 10 m from every
fingerprint of the map, and among those within 3 m of one), with the product's statistic (the
mean eq. 9 distance from the query to its Sørensen neighbours, ``rss_diff_db``) and with the
Sørensen score instead (the same calibration, the statistic swapped). Seeds: the calibration's
sample of walks.

``crowd FOLDER``: the default tracker on the crowdsourced maps of ``bench tracking-real`` (the
main map of a survey of the other routes) against the same fingerprints at their oracle positions
(each walk's PDR fitted to its own landmarks): the same coverage, the survey's geometry or the
truth's. Per map kind: the share of landmarks at steps flagged outside, the others' mean error and
share inside the 95 % ellipse, and the self-calibration's covariance scale; for the crowdsourced maps also
that share with each covariance widened by the map's true displacement (what a placement covariance from
the survey could at best add: the rms displacement of the 10 map fingerprints nearest the estimate, or of
the whole map; once and twice that variance).

python lab/radiomap/outside.py statistic ../shared/data/ipin2023/b100_f-2 ../shared/data/ilc20/site1 [--seeds 0,1,2]
    [--statistics rss_diff_db] [--max-sessions 12 --max-queries 300]
python lab/radiomap/outside.py crowd ../shared/data/ipin2023/b100_f-2
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

import graphslam as gs


def _score_as_statistic(self, q, idx, dist):  # noqa: ANN001 - KnnLocator.rss_diff_db's signature
    """The Sørensen score (the neighbours' mean distance) in place of ``rss_diff_db``."""
    ok = idx >= 0
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(ok, dist, 0.0).sum(axis=1) / ok.sum(axis=1)
    out[~ok.any(axis=1)] = np.nan
    return out


def _floors(folders: list[str]) -> list[Path]:
    out: list[Path] = []
    for f in map(Path, folders):
        out += [f] if any(f.glob("*.mcap")) else sorted(p for p in f.iterdir() if p.is_dir())
    return out


def statistic(folders: list[str], seeds: list[int], sample: dict[str, int], statistics: list[str]) -> None:
    """``bench locate-real``'s outside figures (default kNN, its folds) per statistic and seed;
    ``sample``: the calibration's ``max_sessions`` / ``max_queries`` (default: the product's)."""
    original = gs.KnnLocator.rss_diff_db
    floors = {f: [w for w in gs.read_survey([f]) if len(w.landmarks) >= 2] for f in _floors(folders)}
    try:
        for name, method in (("rss_diff_db", original), ("sorensen_score", _score_as_statistic)):
            if name not in statistics:
                continue
            gs.KnnLocator.rss_diff_db = method
            for seed in seeds:
                total = np.zeros(4, int)
                for floor, walks in floors.items():
                    c = np.zeros(4, int)  # beyond 10 m, of them flagged; within 3 m, of them flagged
                    for _, test in gs.held_out_folds(walks, None, 0):
                        rm = gs.oracle_radio_map([w for i, w in enumerate(walks) if i not in set(test)])
                        truth = gs.oracle_radio_map([walks[i] for i in test]).xy
                        res = gs.KnnLocator(rm).locate([dict(sc.readings) for i in test for sc in walks[i].scans])
                        u = gs.calibrate_uncertainty(rm, gs.KnnConfig(), seed=seed, **sample)
                        flags = u.outside_of(res) if u is not None and u.outside is not None else np.zeros(len(res), bool)
                        gap = cKDTree(rm.xy).query(truth)[0]  # truth to the map's nearest fingerprint
                        ok = res.valid
                        far, near = ok & (gap > 10.0), ok & (gap <= 3.0)
                        c += [far.sum(), (far & flags).sum(), near.sum(), (near & flags).sum()]
                    total += c
                    print(json.dumps({"statistic": name, "seed": seed, **sample, "floor": floor.name, "beyond_10m": int(c[0]),
                                      "flagged_beyond_10m": round(c[1] / max(c[0], 1), 3), "within_3m": int(c[2]),
                                      "flagged_within_3m": round(c[3] / max(c[2], 1), 3)}), flush=True)
                print(json.dumps({"statistic": name, "seed": seed, **sample, "floor": "all", "beyond_10m": int(total[0]),
                                  "flagged_beyond_10m": round(total[1] / max(total[0], 1), 3), "within_3m": int(total[2]),
                                  "flagged_within_3m": round(total[3] / max(total[2], 1), 3)}), flush=True)
    finally:
        gs.KnnLocator.rss_diff_db = original


def _oracle_positions(crowd, oracle):
    """``crowd``'s fingerprints at their positions in ``oracle`` (the same scans: session and time)."""
    key = {(s, t): i for i, (s, t) in enumerate(zip(oracle.session_ids.tolist(), oracle.t_ns.tolist()))}
    idx = np.array([key[(s, t)] for s, t in zip(crowd.session_ids.tolist(), crowd.t_ns.tolist())])
    return gs.RadioMap.from_fingerprints(crowd.fingerprints, oracle.xy[idx], session_ids=crowd.session_ids.tolist(),
                                         t_ns=crowd.t_ns, frame="site", min_rssi_dbm=crowd.min_rssi_dbm)


def crowd(folder: str) -> None:
    walks = [w for w in gs.read_survey([folder]) if len(w.landmarks) >= 2 and len(w.scans) and len(w.steps) >= 2]
    cfg = gs.GraphSlamConfig()
    got: dict[str, dict[str, list]] = {"crowdsourced": {}, "same walks at oracle positions": {}}
    for fold, test in gs.held_out_folds(walks, None, 0):
        train = [w for i, w in enumerate(walks) if i not in set(test)]
        rm, info = gs.crowdsourced_map(train, cfg)
        maps = {"crowdsourced": rm, "same walks at oracle positions": _oracle_positions(rm, gs.oracle_radio_map(train))}
        disp = np.linalg.norm(rm.xy - maps["same walks at oracle positions"].xy, axis=1)  # truth: scores only
        near_map = cKDTree(rm.xy)
        for kind, m in maps.items():
            try:
                models = gs.ApModels.fit(m)
                tracker = gs.Tracker.on_map(m, models)
            except gs.GraphSlamError as e:
                print(json.dumps({"fold": fold, "map": kind, "error": str(e)}))
                continue
            d = got[kind]
            d.setdefault("scale", []).append(tracker.calibration.covariance_scale if tracker.calibration else None)
            for i in test:
                w = walks[i]
                tr = tracker.track(w)
                t, marks = gs.walk_landmarks(w)
                err = gs.interpolate_xy(gs.PoseTrack(tr.t_ns, tr.xy, np.zeros(len(tr.t_ns))), t) - marks
                cov = gs.interpolate_cov(tr.t_ns, tr.P, t)
                d.setdefault("err", []).append(np.linalg.norm(err, axis=1))
                d.setdefault("inside", []).append(gs.ellipse_coverage(err, cov))
                d.setdefault("outside", []).append(tr.outside[np.maximum(np.searchsorted(tr.t_ns, t, side="right") - 1, 0)])
                if kind == "crowdsourced":
                    _, nn = near_map.query(err + marks, k=min(10, len(rm.xy)))
                    d.setdefault("err_xy", []).append(err)
                    d.setdefault("cov", []).append(cov)
                    d.setdefault("disp_near", []).append(np.sqrt((disp[nn] ** 2).mean(axis=1)))
                    d.setdefault("disp_map", []).append(np.full(len(t), np.sqrt((disp**2).mean())))
            print(json.dumps({"fold": fold, "map": kind, "walks_in_map": info["main_map"],
                              "covariance_scale": round(d["scale"][-1], 2) if d["scale"][-1] else None}), flush=True)
    for kind, d in got.items():
        e, ins, out = (np.concatenate(d[k]) for k in ("err", "inside", "outside"))
        keep = ~out
        print(json.dumps({"map": kind, "landmarks": len(e), "mean_m": round(float(e.mean()), 2),
                          "inside_95": round(float(ins.mean()), 3), "outside": round(float(out.mean()), 3),
                          "not_outside": {"n": int(keep.sum()), "mean_m": round(float(e[keep].mean()), 2),
                                          "inside_95": round(float(ins[keep].mean()), 3)},
                          "covariance_scale_median": round(float(np.median([s for s in d["scale"] if s])), 2)}))
        if "disp_near" in d:  # the covariances widened by the map's true displacement (module docstring)
            exy, cov = np.concatenate(d["err_xy"]), np.concatenate(d["cov"])
            widened = {}
            for name in ("disp_near", "disp_map"):
                v = np.concatenate(d[name]) ** 2
                for f in (1, 2):
                    inside = gs.ellipse_coverage(exy, cov + (f * v)[:, None, None] * np.eye(2))
                    widened[f"{name}_x{f}"] = round(float(inside[keep].mean()), 3)
            print(json.dumps({"map": kind, "not_outside_inside_95_widened": widened,
                              "displacement_near_median_m": round(float(np.median(np.concatenate(d["disp_near"])[keep])), 2)}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("mode", choices=("statistic", "crowd"))
    ap.add_argument("folders", nargs="+")
    ap.add_argument("--seeds", default="0", help="statistic: the calibration's seeds, comma-separated")
    ap.add_argument("--statistics", default="rss_diff_db,sorensen_score", help="statistic: which, comma-separated")
    ap.add_argument("--max-sessions", type=int, help="statistic: walks in the calibration's sample (default: the product's)")
    ap.add_argument("--max-queries", type=int, help="statistic: scans in the calibration's sample (default: the product's)")
    a = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    gs.limit_blas_threads(1)
    if a.mode == "statistic":
        sample = {k: v for k, v in (("max_sessions", a.max_sessions), ("max_queries", a.max_queries)) if v is not None}
        statistic(a.folders, [int(s) for s in a.seeds.split(",")], sample, a.statistics.split(","))
    else:
        crowd(a.folders[0])


if __name__ == "__main__":
    main()
