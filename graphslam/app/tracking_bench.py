"""Tracking on real recordings: held-out walks tracked on a radio map of the other walks.

``graphslam bench tracking-real FOLDER`` (IPIN 2023 b100_f-2: leave one route out) and
``scripts/ilc_tracking.py`` (ILC 2.0 site1 floors: seeded folds) both call ``tracking_real``.
Per fold, the radio map is built from the training walks only, in one of two ways:

- ``oracle``: each training walk's foot-module/PDR track placed by a rigid fit to its own
  landmarks, its scans at those positions (ground truth builds the map, as a perfect survey
  would; it never reaches the tracker);
- ``crowdsourced``: the survey pipeline (``graphslam.app.survey.run_survey``) on the training
  walks' files, its radio map as ``graphslam survey`` writes it (the main map, component 0: the
  other components' walks are in frames of their own) put into the landmarks' frame by the
  evaluation's one SE(2) fit (for scoring only: a rigid motion of the map changes neither kNN nor
  the tracker).

AP models are fitted from that map (``ApModels.fit``, as ``graphslam fit-aps``). Each held-out
walk is then located scan by scan (``knn``: the fixes interpolated in time, as in every tracking
benchmark) and tracked by each variant (``graphslam.app.track``, positions interpolated
in time). Errors at the walk's landmark times against the landmarks (m): mean, median, p75 (the
IPIN competition's metric), p90. Calibration: the share of landmarks inside the tracker's
reported 95 % position ellipse (squared Mahalanobis distance <= 5.991, chi-square with 2 dof).
Coverage: the share of landmarks at steps the tracker flags outside the map's walks (``outside``:
the step's latest scan, ``core.tracking.tracker.with_outside``) and the errors and ellipse coverage
of the others (``not_outside``).
With a floor plan (``floor_plan_area``: ``floor_image.png`` beside the walks, as on the ILC floors)
the trackers on the oracle maps get its walkable area (``track --floor-plan``); kNN never does.
"""

from __future__ import annotations

import logging
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from numpy.typing import NDArray

from graphslam.core.tracking.tracker import Tracker

from graphslam.tracking_config import DEFAULTS, TrackConfig
from graphslam.config import GraphSlamConfig
from graphslam.core.radiomap.knn import KnnConfig, KnnLocator
from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.core.common.geometry import fit_se2, interpolate_xy, se2_apply
from graphslam.core.tracking.apmodel import ApModels
from graphslam.core.tracking.calibration import ellipse_coverage, mahalanobis_sq
from graphslam.core.tracking.walkable import WalkableArea
from graphslam.core.types import PoseTrack, Session
from graphslam.errors import GraphSlamError, InputError

log = logging.getLogger(__name__)

MAP_KINDS = ("oracle", "crowdsourced")
# kNN baselines reported beside the trackers: name -> KnnConfig.metric. ``knn`` (the paper's eq. 9)
# is the one ``vs_knn`` compares with; ``vs_knn_sorensen`` compares with the other.
KNN_BASELINES = {"knn": "eq9", "knn:sorensen": "sorensen"}
_ROUTE = re.compile(r"Trial(\d+)_repetition\d+")


@dataclass(frozen=True)
class Variant:
    """A named tracker configuration (``knn`` is always reported besides); ``floor_plan``: whether it
    gets the floor's walkable area, when the benchmark has one (oracle maps only)."""

    name: str
    cfg: TrackConfig
    floor_plan: bool = True


def standard_variants(lags: Sequence[float], filters: Sequence[str] = ("ekf",), smoothers: Sequence[str] = ()) -> list[Variant]:
    """``fixed-lag:LAG`` per lag (``graphslam track --lag LAG``'s defaults), each causal filter
    (``track --filter F``, defaults otherwise) and each filter + offline smoother."""
    out = [Variant(f"fixed-lag:{lag:g}", TrackConfig(fixed_lag={"lag_s": float(lag)})) for lag in lags]
    out += [Variant(f, TrackConfig(filter={"kind": f})) for f in filters]
    out += [Variant(f"{f}+{sm}", TrackConfig(filter={"kind": f, "smoother": sm})) for f in filters for sm in smoothers]
    return out


def error_stats(e: NDArray) -> dict[str, float]:
    """n, mean, median, p75, p90 of errors (m)."""
    if not e.size:
        return {"n": 0}
    return {
        "n": int(e.size), "mean_m": round(float(e.mean()), 3), "median_m": round(float(np.median(e)), 3),
        "p75_m": round(float(np.percentile(e, 75)), 3), "p90_m": round(float(np.percentile(e, 90)), 3),
    }


def interpolate_cov(t_ns: NDArray, P: NDArray, t: NDArray) -> NDArray[np.float64]:
    """(len(t), 2, 2) position covariance of a track (steps at ``t_ns``, states' ``P``) at times
    ``t``, each entry linearly interpolated (clamped at the ends, as ``interpolate_xy``)."""
    tf = np.asarray(t_ns, float)
    return np.stack([np.stack([np.interp(t, tf, P[:, i, j]) for j in (0, 1)], -1) for i in (0, 1)], -2)


def route_of(session: Session) -> str:
    """The IPIN route (trial number) from the file name or id, '' when there is none."""
    m = _ROUTE.search(Path(session.source).name if session.source else session.session_id) or _ROUTE.search(
        session.session_id
    )
    return m.group(1) if m else ""


def walk_landmarks(w: Session) -> tuple[NDArray, NDArray]:
    return np.array([m.t_ns for m in w.landmarks], float), np.array([[m.x, m.y] for m in w.landmarks])


def oracle_radio_map(walks: Sequence[Session]) -> RadioMap:
    """Scans of ``walks`` at their PDR positions under each walk's rigid fit to its own landmarks
    (site frame). Ground truth builds this map; evaluation only."""
    scans, xy, sid, ts = [], [], [], []
    for w in walks:
        t, marks = walk_landmarks(w)
        T = fit_se2(interpolate_xy(w.steps, t), marks)
        st = np.array([sc.t_ns for sc in w.scans], float)
        xy.append(se2_apply(T, interpolate_xy(w.steps, st)))
        scans += [dict(sc.readings) for sc in w.scans]
        sid += [w.session_id] * len(w.scans)
        ts += [sc.t_ns for sc in w.scans]
    return RadioMap.from_scans(scans, np.concatenate(xy), session_ids=sid, t_ns=ts, frame="site")


def crowdsourced_map(walks: Sequence[Session], cfg: GraphSlamConfig) -> tuple[RadioMap, dict[str, Any]]:
    """The survey pipeline on the walks' files; the map in the landmark frame by one SE(2) fit."""
    from graphslam.app.survey import main_alignment, run_survey
    from graphslam.app.survey_inputs import SurveyInputs
    from graphslam.core.survey.radio_maps import crowdsourced_radio_map

    res = run_survey(SurveyInputs(tuple(w.source for w in walks)), cfg)
    ev = res.evaluation
    if ev is None or ev.landmarks.n < 2:
        raise GraphSlamError("crowdsourced map: the survey placed fewer than 2 landmarks")
    main = main_alignment(res.alignment)  # what radio_map.parquet holds: the evaluation's fit is of it too
    rm = crowdsourced_radio_map(res.survey, main, cfg, site_from_aligned=np.array(ev.site_from_aligned))
    info = {"aligned": len(res.alignment.tracks), "main_map": len(main.tracks), "walks": len(walks),
            "survey_landmark_mean_m": round(ev.landmarks.mean_m, 2)}
    return rm, info


def score_walks(
    rm: RadioMap, models: ApModels, walks: Sequence[Session], variants: Sequence[Variant], *, knn_k: int = 3,
    area: WalkableArea | None = None,
) -> dict[str, dict[str, list]]:
    """Per variant and per kNN baseline (``KNN_BASELINES``: the paper's eq. 9 as ``knn``, the
    Sørensen metric as ``knn:sorensen``): landmark errors (m), and for trackers whether each
    landmark lies in the reported 95 % ellipse, plus seconds spent. ``area``: the floor plan's
    walkable area in ``rm``'s frame, for the variants that take it."""
    out: dict[str, dict[str, list]] = {v: {"err": [], "inside": [], "s": []} for v in (*KNN_BASELINES, *(v.name for v in variants))}
    locators = {name: KnnLocator(rm, KnnConfig(k=knn_k, metric=metric)) for name, metric in KNN_BASELINES.items()}  # type: ignore[arg-type]
    trackers = {v.name: Tracker.on_map(rm, models, v.cfg, area=area if v.floor_plan else None)
                for v in variants}  # self-calibration once per map
    for w in walks:
        t, marks = walk_landmarks(w)
        for name, locator in locators.items():
            t0 = time.perf_counter()
            fix = locator.locate([sc.readings for sc in w.scans])
            ok = fix.valid
            if ok.any():
                knn = PoseTrack(np.array([sc.t_ns for sc in w.scans])[ok], fix.xy[ok], np.zeros(int(ok.sum())))
                out[name]["err"].append(np.linalg.norm(interpolate_xy(knn, t) - marks, axis=1))
                out[name].setdefault("t", []).append((t - w.steps.t_ns[0]) / 1e9)
            out[name]["s"].append(time.perf_counter() - t0)
        for v in variants:
            t0 = time.perf_counter()
            try:
                tr = trackers[v.name].track(w)
            except GraphSlamError as e:
                log.warning("tracking-real: %s not tracked by %s: %s", w.session_id, v.name, e)
                continue
            out[v.name]["s"].append(time.perf_counter() - t0)
            track = PoseTrack(tr.t_ns, tr.xy, np.zeros(len(tr.t_ns)))
            err = interpolate_xy(track, t) - marks
            cov = interpolate_cov(tr.t_ns, tr.P, t)
            out[v.name]["err"].append(np.linalg.norm(err, axis=1))
            out[v.name]["inside"].append(ellipse_coverage(err, cov))
            if tr.outside is not None:  # each landmark: the flag of the step at or before it
                out[v.name].setdefault("outside", []).append(
                    tr.outside[np.maximum(np.searchsorted(tr.t_ns, t, side="right") - 1, 0)])
            out[v.name].setdefault("d2", []).append(mahalanobis_sq(err, cov))
            out[v.name].setdefault("sd", []).append(np.sqrt(0.5 * (cov[:, 0, 0] + cov[:, 1, 1])))
            out[v.name].setdefault("t", []).append((t - w.steps.t_ns[0]) / 1e9)
    return out


def floor_plan_area(folder: Path | str, spec: str = "auto", sigma_m: float = DEFAULTS.floor_plan.sigma_m) -> WalkableArea | None:
    """The walkable area for ``tracking_real``: ``auto``: from ``floor_image.png`` beside the walks
    (with its ``floor_info.json``, as the ILC floors) when there is one; ``none``; or a plan image."""
    from graphslam.io.floor_plan import load_floor_plan, read_walkable_area

    if spec == "none":
        return None
    path = Path(folder) / "floor_image.png" if spec == "auto" else Path(spec)
    if spec == "auto" and not path.is_file():
        return None
    return read_walkable_area(load_floor_plan(path, None), sigma_m)


def held_out_folds(walks: Sequence[Session], folds: int | None, seed: int) -> list[tuple[str, list[int]]]:
    """Leave one route out when every walk names its route, else ``folds`` seeded random folds."""
    routes = [route_of(w) for w in walks]
    if folds is None and all(routes):
        return [(f"route {r}", [i for i, x in enumerate(routes) if x == r]) for r in sorted(set(routes), key=int)]
    k = folds or 5
    fold = np.random.default_rng(seed).permutation(len(walks)) % k
    return [(f"fold {f}", [i for i in range(len(walks)) if fold[i] == f]) for f in range(k)]


def tracking_real(
    folder: Path | str,
    cfg: GraphSlamConfig,
    variants: Sequence[Variant],
    *,
    maps: Sequence[str] = MAP_KINDS,
    folds: int | None = None,
    seed: int = 0,
    area: WalkableArea | None = None,
) -> dict[str, Any]:
    """Held-out walks of ``folder`` tracked on maps of the other walks (module docstring). ``area``:
    the floor plan's walkable area (site frame), given to the variants that take it on the oracle
    maps only (a crowdsourced map reaches the site frame only through the landmarks)."""
    from graphslam.io.mcap_reader import read_survey

    bad = [m for m in maps if m not in MAP_KINDS]
    if bad:
        raise InputError(str(folder), f"unknown map kind {bad[0]!r}; use {', '.join(MAP_KINDS)}")
    survey = read_survey([folder])
    walks = [w for w in survey if len(w.landmarks) >= 2 and len(w.scans) and len(w.steps) >= 2]
    if len(walks) < 2:
        raise InputError(str(folder), f"need at least 2 walks with >= 2 landmarks, scans and steps; found {len(walks)}")
    split = held_out_folds(walks, folds, seed)
    t_start = time.perf_counter()
    result: dict[str, Any] = {
        "folder": str(folder), "walks": len(walks), "walks_skipped": len(survey) - len(walks),
        "folds": [name for name, _ in split], "variants": {v.name: _describe(v.cfg) for v in variants},
        "floor_plan": {v.name: area is not None and v.floor_plan for v in variants},
    }
    for kind in maps:
        acc: dict[str, dict[str, list]] = {}
        per_fold = []
        for name, test in split:
            train = [w for i, w in enumerate(walks) if i not in set(test)]
            info: dict[str, Any] = {"fold": name, "test_walks": len(test)}
            try:
                if kind == "oracle":
                    rm = oracle_radio_map(train)
                else:
                    rm, survey_info = crowdsourced_map(train, cfg)
                    info.update(survey_info)
                models = ApModels.fit(rm)
                models.path_loss()  # EstimationError when no AP could be fitted
            except GraphSlamError as e:  # the fold is left out for every variant, kNN included
                log.warning("tracking-real: %s map of %s: %s", kind, name, e)
                info["error"] = str(e)
                per_fold.append(info)
                continue
            res = score_walks(rm, models, [walks[i] for i in test], variants, area=area if kind == "oracle" else None)
            for v, d in res.items():
                for key, vals in d.items():
                    acc.setdefault(v, {}).setdefault(key, []).extend(vals)
                if d["err"]:
                    info[f"{v}_mean_m"] = round(float(np.concatenate(d["err"]).mean()), 3)
            per_fold.append(info)
        summary: dict[str, Any] = {}
        for v, d in acc.items():
            e = np.concatenate(d["err"]) if d["err"] else np.zeros(0)
            row: dict[str, Any] = error_stats(e)
            if d["inside"]:
                row["inside_95"] = round(float(np.concatenate(d["inside"]).mean()), 3)
            if d.get("outside") and len(d["outside"]) == len(d["inside"]):
                row.update(_coverage_figures(e, np.concatenate(d["inside"]), np.concatenate(d["outside"])))
            row["s_per_walk"] = round(float(np.mean(d["s"])), 3) if d["s"] else None
            summary[v] = row
        for base in KNN_BASELINES:
            base_mean = summary.get(base, {}).get("mean_m")
            for v, row in summary.items():
                if v != base and base_mean and "mean_m" in row:
                    row["vs_" + base.replace(":", "_")] = round(row["mean_m"] / base_mean - 1.0, 3)
        result[kind] = {"summary": summary, "per_fold": per_fold}
    result["time_s"] = round(time.perf_counter() - t_start, 1)
    return result


def _coverage_figures(err: NDArray, inside: NDArray, outside: NDArray) -> dict[str, Any]:
    """``outside``: the share of landmarks at steps flagged outside; ``not_outside``: the others' errors
    and the share of them inside the 95 % ellipse."""
    keep = ~outside.astype(bool)
    rest: dict[str, Any] = error_stats(err[keep])
    if keep.any():
        rest["inside_95"] = round(float(inside[keep].mean()), 3)
    return {"outside": round(float(outside.mean()), 3) if len(outside) else None, "not_outside": rest}


def _describe(cfg: TrackConfig) -> str:
    """The variant's kind, and every other setting (``section.key``) that is not the default."""
    flat = cfg.flat()
    keys = ["filter.kind", "filter.smoother", "knn_fixes.enabled"]
    if cfg.filter.kind == "fixed-lag" and cfg.filter.smoother == "none":
        keys += ["fixed_lag.lag_s", "fixed_lag.window_s", "fixed_lag.bank_report"]
    default = DEFAULTS.flat()
    keys += [k for k, v in flat.items() if k not in keys and v != default[k]]
    return ", ".join(f"{k}={flat[k]}" for k in keys)
