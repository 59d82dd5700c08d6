"""``graphslam bench real``: real recordings with landmarks surveyed per variant and scored per
component (what a user evaluating a survey of their own floors runs).

Every function returns plain dicts so the CLI prints them as JSON lines.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

import numpy as np

from graphslam.app.survey_inputs import CONTROL_POINTS_FILE, REFERENCE_MAP_FILE, SurveyInputs
from graphslam.config import GraphSlamConfig
from graphslam.core.progress import progress_over
from graphslam.core.summary import main_map_counts

log = logging.getLogger(__name__)


REAL_VARIANTS = ("headings", "no_magnetic", "no_headings", "control_points", "reference_map")
BIG_COMPONENT_WALKS = 5  # walks_in_components_of_5_or_more
# ... and of 4 or more: the size the survey's targets are stated for
COMPONENT_SIZES = (4, BIG_COMPONENT_WALKS)
RIGHT_WALK_M = 5.0  # a walk whose mean landmark error (after its component's SE(2) fit) is at most this is right


def real_floor_rows(
    folders: Sequence[Path],
    cfg: GraphSlamConfig,
    floors: Sequence[str] | None = None,
    *,
    variants: Sequence[str] = REAL_VARIANTS,
    control_points: str = "auto",
    reference_map: str = "auto",
) -> Iterator[dict[str, Any]]:
    """Survey each floor of real recordings with landmarks once per variant; one row per floor and
    variant, yielded as each is done.

    A folder holding ``.mcap`` files is one floor; a folder without (an ILC site) stands for its
    floor sub-folders (``floors`` picks some). Variants: ``headings`` (``cfg`` as given: with the
    phones' headings where every walk has them, and the magnetic field where walks carry it),
    ``no_magnetic`` (``cfg`` with ``magnetic.enabled=false``: WiFi and headings only), ``no_headings`` (``cfg`` with
    ``heading.enabled=false``: the registration path) and ``control_points`` (``cfg`` with the
    floor folder's ``control_points.csv``, component 0 in the site frame; only where the file is
    there and ``control_points`` is ``"auto"``; ``"none"``: never) and ``reference_map`` (the floor
    folder's ``reference_map.csv`` held fixed in the site frame, the crowd placed on it: every walk but
    the reference's own — those whose scans it holds verbatim, ``crowd_walks``; only where the file is
    there and ``reference_map`` is ``"auto"``). Ground truth only scores
    (``graphslam.core.survey.evaluate.component_errors``): each component after its own SE(2) fit,
    component 0 of a survey in the site frame also with no fit. See ``_real_row`` for the fields.
    """
    from graphslam.errors import ConfigError
    from graphslam.io.mcap_reader import floor_folders

    unknown = [v for v in variants if v not in REAL_VARIANTS]
    if unknown or not variants:
        raise ConfigError(f"bench real variants {list(variants)!r}: expected some of {', '.join(REAL_VARIANTS)}")
    if control_points not in ("auto", "none"):
        raise ConfigError(f"--control-points {control_points!r}: expected auto or none")
    if reference_map not in ("auto", "none"):
        raise ConfigError(f"--reference-map {reference_map!r}: expected auto or none")
    expanded: list[Path] = []
    for f in map(Path, folders):
        expanded += [f] if any(f.glob("*.mcap")) else floor_folders(f, floors)
    plan = []
    for folder in expanded:
        cp_file = folder / CONTROL_POINTS_FILE
        ref_file = folder / REFERENCE_MAP_FILE
        for v in variants:
            if v == "control_points" and (control_points == "none" or not cp_file.is_file()):
                continue
            if v == "reference_map":
                if reference_map == "none" or not ref_file.is_file():
                    continue
                inputs = SurveyInputs(crowd_walks(folder, ref_file), reference_map=ref_file, picture=False)
                plan.append((folder, v, inputs))
                continue
            cp = cp_file if v == "control_points" else None
            plan.append((folder, v, SurveyInputs((folder,), control_points=cp, picture=False)))
    configs = {v: _variant_config(cfg, v) for v in variants}
    for folder, variant, inputs in progress_over(plan, "bench real", unit="surveys"):
        yield _real_row(folder, inputs, variant, configs[variant])


def real_floors(
    folders: Sequence[Path],
    cfg: GraphSlamConfig,
    floors: Sequence[str] | None = None,
    *,
    variants: Sequence[str] = REAL_VARIANTS,
    control_points: str = "auto",
    reference_map: str = "auto",
) -> list[dict[str, Any]]:
    """``real_floor_rows`` as a list."""
    return list(real_floor_rows(folders, cfg, floors, variants=variants, control_points=control_points,
                                reference_map=reference_map))


def crowd_walks(folder: Path, reference: Path) -> tuple[Path, ...]:
    """The recordings of ``folder`` that are not the reference map's own: a walk at least half of whose
    scans the reference holds verbatim (the same readings) is one of the walks it was made from."""
    from graphslam.io.mcap_reader import read_recordings
    from graphslam.io.reference_map import read_reference_map

    ref = read_reference_map(reference)
    fm = ref.fingerprints
    v = fm.values
    held = {frozenset((fm.bssids[j], round(float(x) + fm.missing_dbm, 3)) for j, x in
                      zip(v.indices[v.indptr[r]:v.indptr[r + 1]], v.data[v.indptr[r]:v.indptr[r + 1]]))
            for r in range(len(fm))}
    floor = ref.min_rssi_dbm
    out = []
    for s in read_recordings([folder]).survey:
        scans = [frozenset((b, round(r, 3)) for b, r in sc.readings.items() if r >= floor) for sc in s.scans]
        if not scans or sum(sc in held for sc in scans) < 0.5 * len(scans):
            out.append(Path(s.source))
    return tuple(out)


def _variant_config(cfg: GraphSlamConfig, variant: str) -> GraphSlamConfig:
    if variant not in ("no_headings", "no_magnetic"):
        return cfg
    from graphslam.config import config_from_dict

    data = cfg.model_dump()
    data["heading" if variant == "no_headings" else "magnetic"]["enabled"] = False
    return config_from_dict(data, f"bench real {variant}")


def _real_row(folder: Path, inputs: SurveyInputs, variant: str, cfg: GraphSlamConfig) -> dict[str, Any]:
    """One floor (``folder``; ``inputs``: its recordings, no files written) surveyed under one variant, scored
    per component.

    ``main``: walks in component 0, first, with ``other_walks`` in ``other_components`` and
    ``unaligned`` (``main_map``: the same as ``graphslam survey``'s first line); ``main_mean_m``
    (= ``mean_m``) / ``p90_m`` / ``max_m`` its landmark errors after one SE(2) fit, ``main_site_mean_m`` with no fit when it is in the site
    frame (control points; else None); ``walks_in_components_of_5_or_more``, its fraction of the
    walks read and ``components_of_5_or_more_mean_m`` (each such component's mean error after its own
    fit, weighted by its walks; components without 2 marks left out), the same for components of 4
    or more (``..._4_or_more``); ``walks_over_10m`` /
    ``walks_over_15m``: walks of any component whose mean error is over 10 / 15 m (each component
    after its own fit; component 0 in the site frame without fit); ``time_s``: the whole survey.
    """
    from graphslam.app.survey import run_survey
    from graphslam.core.survey.evaluate import component_errors

    log.info("bench real: %s, %s", folder, variant)
    t = time.perf_counter()
    res = run_survey(inputs, cfg)
    dt = time.perf_counter() - t
    al, ev, n = res.alignment, res.evaluation, len(res.survey)
    site = al.frame == "site"
    comps = component_errors(al, res.survey, site_frame=site) if ev is not None else []
    lm = ev.landmarks if ev is not None else None
    main = len(al.components[0].walks) if al.components else 0
    # per walk, in the frame the variant delivers: component 0 in the site frame unfitted
    per_walk: dict[str, float] = {}
    for c in comps:
        per_walk.update(c.site_per_walk_mean_m if c.site_per_walk_mean_m is not None else c.per_walk_mean_m)
    c0 = comps[0] if comps else None
    pl = al.placement

    def r2(v: float | None) -> float | None:
        return None if v is None or not np.isfinite(v) else round(float(v), 2)

    by_size = {k: v for size in COMPONENT_SIZES for k, v in big_component_figures(comps, n, size).items()}
    n_other = sum(len(c.walks) for c in al.components[1:])
    return {
        "floor": folder.name,
        "variant": variant,
        "walks": n,
        # the main map first, counted as `graphslam survey`'s first line counts it
        "main": main,
        "main_fraction": round(main / max(1, n), 3),
        "other_walks": n_other,
        "other_components": max(0, len(al.components) - 1),
        "unaligned": len(al.unaligned),
        "main_map": main_map_counts(n, main, n_other, max(0, len(al.components) - 1), len(al.unaligned)),
        "aligned": len(al.tracks),
        "aligned_fraction": round(len(al.tracks) / max(1, n), 3),
        "landmarks": lm.n if lm else 0,
        "main_mean_m": r2(lm.mean_m) if lm and lm.n else None,
        "main_site_mean_m": r2(c0.site.mean_m) if c0 is not None and c0.site is not None and c0.site.n else None,
        "mean_m": r2(lm.mean_m) if lm and lm.n else None,
        "p90_m": r2(lm.p90_m) if lm and lm.n else None,
        "max_m": r2(lm.max_m) if lm and lm.n else None,
        "components": len(al.components),
        **by_size,
        "walks_over_6m": int(sum(v > 6.0 for v in per_walk.values())),
        "walks_over_10m": int(sum(v > 10.0 for v in per_walk.values())),
        "walks_over_15m": int(sum(v > 15.0 for v in per_walk.values())),
        "frame": al.frame,
        "control_points": None if inputs.control_points is None else str(inputs.control_points),
        "reference_map": None if inputs.reference_map is None else str(inputs.reference_map),
        "per_walk_rigid_fit_mean_m": r2(ev.landmarks_per_walk_fit.mean_m) if ev else None,
        "initialization": cfg.optimizer.initialization,
        "placement": None if pl is None else pl.method,
        "loop_consistency": None if pl is None or pl.loop_consistency is None else round(pl.loop_consistency, 3),
        "reliable": None if pl is None else pl.reliable,
        "confidence": _confidence_separation(al, _per_walk_fit(comps)) if comps else None,
        "time_s": round(dt, 2),
    }


def big_component_figures(comps: Sequence[Any], walks: int, size: int) -> dict[str, Any]:
    """The walks in components of ``size`` walks or more (``ComponentErrors``), their fraction of
    ``walks`` and those components' mean landmark error, each after its own fit, weighted by its
    walks (components without 2 marks left out; None when none is left)."""
    big = [c for c in comps if len(c.walks) >= size]
    n_big = sum(len(c.walks) for c in big)
    scored = [c for c in big if c.landmarks.n > 0]
    w = sum(len(c.walks) for c in scored)
    mean = sum(len(c.walks) * c.landmarks.mean_m for c in scored) / w if w else None
    return {
        f"walks_in_components_of_{size}_or_more": n_big,
        f"walks_in_components_of_{size}_or_more_fraction": round(n_big / max(1, walks), 3),
        f"components_of_{size}_or_more_mean_m": None if mean is None or not np.isfinite(mean) else round(float(mean), 2),
    }


def _per_walk_fit(comps: Sequence[Any]) -> dict[str, float]:
    """session id -> mean landmark error after its component's SE(2) fit (``ComponentErrors``)."""
    return {sid: e for c in comps for sid, e in c.per_walk_mean_m.items()}


def real_summary(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """One line per variant over ``real_floor_rows``' rows: floors, walks, their sums and
    walk-weighted means (``main_mean_m`` weighted by ``main``, ``components_of_5_or_more_mean_m`` and
    ``components_of_4_or_more_mean_m`` by their walks)."""
    out = []
    for variant in dict.fromkeys(r["variant"] for r in rows):
        rs = [r for r in rows if r["variant"] == variant]
        walks = sum(r["walks"] for r in rs)

        def wmean(key: str, weight: str) -> float | None:
            pairs = [(r[weight], r[key]) for r in rs if r[key] is not None and r[weight]]
            tot = sum(p[0] for p in pairs)
            return round(sum(a * b for a, b in pairs) / tot, 2) if tot else None

        main = sum(r["main"] for r in rs)
        by_size = {}
        for size in COMPONENT_SIZES:
            key = f"walks_in_components_of_{size}_or_more"
            big = sum(r[key] for r in rs)
            by_size.update({key: big, f"{key}_fraction": round(big / max(1, walks), 3),
                            f"components_of_{size}_or_more_mean_m": wmean(f"components_of_{size}_or_more_mean_m", key)})
        other = sum(r["other_walks"] for r in rs)
        n_comps = sum(r["other_components"] for r in rs)
        unaligned = sum(r["unaligned"] for r in rs)
        out.append({
            "summary": variant,
            "floors": len(rs),
            "walks": walks,
            "main": main,
            "main_fraction": round(main / max(1, walks), 3),
            "other_walks": other,
            "other_components": n_comps,
            "unaligned": unaligned,
            "main_map": main_map_counts(walks, main, other, n_comps, unaligned).replace("main map:", "main maps:", 1),
            "main_mean_m": wmean("main_mean_m", "main"),
            "main_site_mean_m": wmean("main_site_mean_m", "main"),
            **by_size,
            "walks_over_6m": sum(r["walks_over_6m"] for r in rs),
            "walks_over_10m": sum(r["walks_over_10m"] for r in rs),
            "walks_over_15m": sum(r["walks_over_15m"] for r in rs),
            "time_s": round(sum(r["time_s"] for r in rs), 2),
        })
    return out


def _confidence_separation(al: Any, per_walk: Mapping[str, float]) -> dict[str, Any]:
    """Right / wrong aligned walks (``per_walk``: mean landmark error after its component's fit),
    and the AUC of each per-walk placement figure (P(a right walk scores higher than a wrong one);
    0.5: no separation; None: only one class)."""
    ids = list(al.session_ids)
    pl = al.placement
    right = {sid: e <= RIGHT_WALK_M for sid, e in per_walk.items() if sid in al.tracks}
    out: dict[str, Any] = {"right": int(sum(right.values())), "wrong": int(sum(not r for r in right.values()))}
    figures = {}
    if pl is not None and pl.method in ("growth", "heading", "reference", "control_points"):
        figures = {"support": pl.support, "margin": pl.margin, "consistency": pl.consistency}
    elif pl is not None:
        figures = {"registration_inliers": pl.inliers.astype(float)}
    for name, values in figures.items():
        if values is None:
            continue
        pairs = [(float(values[ids.index(sid)]), ok) for sid, ok in right.items()]
        pairs = [(v if np.isfinite(v) else np.inf, ok) for v, ok in pairs]
        out[f"auc_{name}"] = _auc([v for v, ok in pairs if ok], [v for v, ok in pairs if not ok])
    return out


def _auc(pos: Sequence[float], neg: Sequence[float]) -> float | None:
    if not pos or not neg:
        return None
    p, n = np.asarray(pos)[:, None], np.asarray(neg)[None, :]
    return round(float((p > n).mean() + 0.5 * (p == n).mean()), 3)
