"""``graphslam bench locate-real``: kNN positioning on real recordings with landmarks, scored
against the truth (what a user evaluating ``locate`` / ``serve`` on their own floors runs).

Per floor (a folder of ``.mcap`` files; a folder without any, e.g. an ILC site, stands for its floor
sub-folders): the walks are split into folds (leave one route out when every file names its route,
else seeded random folds: ``tracking_bench.held_out_folds``); each fold's scans are located on the
oracle radio map of the other walks (``tracking_bench.oracle_radio_map``: each walk placed by a
rigid fit to its own landmarks, so the map is in the site frame; ground truth builds the map and
scores, as ``bench tracking-real`` does), with each metric asked for. Per metric: mean / median /
p90 error (m) at the scans' true positions (the same fits) and, for the default kNN, the share of
errors inside the answers' 95 % circles (``sigma_m`` calibrated on each fold's map without truth,
``core.radiomap.uncertainty``) and how its outside test does (``outside``): of the scans whose
truth is more than ``OUTSIDE_RADIUS_M`` from every fingerprint of the map, the share flagged
outside; of those within ``NEAR_M`` of one, the share flagged (the test's own distances). One plain
dict per floor, for JSON lines, and ``locate_real_summary`` over them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np
from scipy.spatial import cKDTree

from graphslam.core.progress import progress_over
from graphslam.core.radiomap.knn import KnnConfig, KnnLocator
from graphslam.core.radiomap.uncertainty import NEAR_M, OUTSIDE_RADIUS_M, R95, calibrate_uncertainty
from graphslam.errors import ConfigError, InputError
from graphslam.names import DEFAULT_METRIC, METRICS

# the counts behind ``outside``'s shares (``locate_real_summary`` pools them over floors)
_OUTSIDE_COUNTS = ("beyond", "beyond_flagged", "near", "near_flagged", "located", "flagged", "flagged_inside")


def locate_real_rows(
    folders: Sequence[Path], *, metrics: Sequence[str] = (DEFAULT_METRIC, "eq9"), folds: int | None = None,
    seed: int = 0,
) -> Iterator[dict[str, Any]]:
    """One row per floor folder (module docstring), yielded as each is done."""
    from graphslam.app.tracking_bench import held_out_folds, oracle_radio_map
    from graphslam.io.mcap_reader import floor_folders, read_survey

    bad = [m for m in metrics if m not in METRICS]
    if bad or not metrics:
        raise ConfigError(f"bench locate-real metrics {list(metrics)!r}: expected some of {', '.join(METRICS)}")
    expanded: list[Path] = []
    for f in map(Path, folders):
        expanded += [f] if not f.is_dir() or any(f.glob("*.mcap")) else floor_folders(f)
    for folder in progress_over(expanded, "bench locate-real", unit="floors"):
        walks = [w for w in read_survey([folder]) if len(w.landmarks) >= 2]
        if len(walks) < 2:
            raise InputError(folder, "fewer than 2 walks with 2 or more /landmarks: nothing to hold out")
        err: dict[str, list[np.ndarray]] = {m: [] for m in metrics}
        inside: list[np.ndarray] = []
        radius: list[np.ndarray] = []  # the answers' 95 % radii (m): how wide the circles are
        counts = dict.fromkeys(_OUTSIDE_COUNTS, 0)
        measured = False  # an outside test was measured on some fold's map
        n_scans = 0
        split = held_out_folds(walks, folds, seed)
        for _, test_idx in split:
            held = set(test_idx)
            train = [w for i, w in enumerate(walks) if i not in held]
            test = [walks[i] for i in test_idx]
            if not train or not any(w.scans for w in test):
                continue
            rm = oracle_radio_map(train)
            truth = oracle_radio_map(test).xy
            queries = [dict(sc.readings) for w in test for sc in w.scans]
            n_scans += len(queries)
            for m in metrics:
                cfg = KnnConfig(metric=m)  # type: ignore[arg-type]
                res = KnnLocator(rm, cfg).locate(queries)
                e = np.linalg.norm(res.xy - truth, axis=1)  # NaN: unlocated
                err[m].append(e)
                if m == metrics[0]:
                    u = calibrate_uncertainty(rm, cfg)
                    if u is not None:
                        ok = res.valid
                        r95 = R95 * u.sigma_of(res)[ok]
                        inside.append(e[ok] <= r95)
                        radius.append(r95)
                        flags = u.outside_of(res)
                        if flags is not None:
                            measured = True
                            flags = flags[ok]
                            gap = cKDTree(rm.xy).query(truth[ok])[0]  # truth to the map's nearest fingerprint
                            beyond, near = gap > OUTSIDE_RADIUS_M, gap <= NEAR_M
                            for key, v in (("beyond", beyond.sum()), ("beyond_flagged", (beyond & flags).sum()),
                                           ("near", near.sum()), ("near_flagged", (near & flags).sum()),
                                           ("located", len(flags)), ("flagged", flags.sum()),
                                           ("flagged_inside", (flags & (e[ok] <= r95)).sum())):
                                counts[key] += int(v)
        row: dict[str, Any] = {"floor": str(folder), "walks": len(walks), "folds": len(split), "scans": n_scans}
        for m in metrics:
            e = np.concatenate(err[m]) if err[m] else np.zeros(0)
            ok = np.isfinite(e)
            row[m] = {
                "located": int(ok.sum()),
                "mean_m": round(float(e[ok].mean()), 3) if ok.any() else None,
                "median_m": round(float(np.median(e[ok])), 3) if ok.any() else None,
                "p90_m": round(float(np.percentile(e[ok], 90)), 3) if ok.any() else None,
            }
        got = np.concatenate(inside) if inside else np.zeros(0, bool)
        row[metrics[0]]["inside_95_circle"] = round(float(got.mean()), 3) if len(got) else None
        row[metrics[0]]["median_r95_m"] = round(float(np.median(np.concatenate(radius))), 2) if radius else None
        row[metrics[0]]["outside"] = outside_figures(counts) if measured else None
        yield row


def outside_figures(c: dict[str, int]) -> dict[str, Any]:
    """The outside test's shares from its counts (``_OUTSIDE_COUNTS``), the counts kept beside them."""

    def share(a: str, b: str) -> float | None:
        return round(c[a] / c[b], 3) if c[b] else None

    return {
        f"flagged_beyond_{OUTSIDE_RADIUS_M:g}m": share("beyond_flagged", "beyond"),
        f"flagged_within_{NEAR_M:g}m": share("near_flagged", "near"),
        "flagged": share("flagged", "located"),
        "flagged_inside_95_circle": share("flagged_inside", "flagged"),
        "counts": dict(c),
    }


def locate_real_summary(rows: Sequence[dict[str, Any]], metric: str = DEFAULT_METRIC) -> dict[str, Any]:
    """The outside test's figures over every floor's scans (``metric``'s rows, as ``locate_real_rows`` gives)."""
    c = dict.fromkeys(_OUTSIDE_COUNTS, 0)
    floors = 0
    for r in rows:
        out = (r.get(metric) or {}).get("outside")
        if out:
            floors += 1
            for k in c:
                c[k] += int(out["counts"][k])
    return {"summary": {"floors": len(rows), "metric": metric, "outside": outside_figures(c) if floors else None}}


__all__ = ["locate_real_rows", "locate_real_summary"]
