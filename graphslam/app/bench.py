"""Benchmarks on simulated surveys: accuracy over seeds, end-to-end speed, scale.

Side effects (temporary files, subprocesses) live here, not in ``core``. Every
function returns plain dicts so the CLI prints them as JSON lines and
docs/benchmarks.md can quote the command that made them.
"""

from __future__ import annotations

import json
import logging
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

import numpy as np

from graphslam.config import GraphSlamConfig
from graphslam.core.progress import progress_over
from graphslam.core.survey.align import align
from graphslam.core.survey.evaluate import evaluate

log = logging.getLogger(__name__)


def accuracy(scenario: str, seeds: Sequence[int], cfg: GraphSlamConfig, *, size: float = 1.0) -> list[dict[str, Any]]:
    """Align simulated surveys in memory; landmark/heading/step errors per seed."""
    from graphslam.sim import simulate

    rows = []
    for seed in progress_over(seeds, "bench accuracy", unit="seeds"):
        survey = simulate(scenario, seed=seed, size=size).survey
        t = time.perf_counter()
        al = align(survey, cfg)
        dt = time.perf_counter() - t
        ev = evaluate(al.main_tracks(), survey)  # the main map: other components stand in frames of their own
        rows.append(
            {
                "scenario": scenario,
                "seed": seed,
                "walks": len(survey),
                "aligned": len(al.tracks),
                "main": len(al.main_tracks()),
                "frame": al.frame,
                "steps": survey.n_steps,
                "wifi_edges": len(al.edges),
                "landmark_n": ev.landmarks.n,
                "landmark_mean_m": round(ev.landmarks.mean_m, 3),
                "landmark_median_m": round(ev.landmarks.median_m, 3),
                "landmark_p90_m": round(ev.landmarks.p90_m, 3),
                "landmark_max_m": round(ev.landmarks.max_m, 3),
                "raw_landmark_mean_m": round(ev.landmarks_raw.mean_m, 3),
                "raw_landmark_max_m": round(ev.landmarks_raw.max_m, 3),
                "heading_mean_deg": round(ev.heading_mean_deg, 3),
                "steps_mean_m": round(ev.steps.mean_m, 3),
                "align_s": round(dt, 3),
                "lm_iterations": len(al.iterations),
            }
        )
    return rows


def survey_speed(
    scenario: str, seed: int, *, runs: int = 5, size: float = 1.0, config: Path | None = None
) -> dict[str, Any]:
    """End-to-end ``graphslam survey`` (read MCAP, align, write every output) in a fresh process per run.

    Median wall time over ``runs``; per-stage medians from report.json; peak RSS of the runs.
    """
    from graphslam.sim import simulate

    with tempfile.TemporaryDirectory(prefix="graphslam-bench-") as tmp:
        data = Path(tmp) / "data"
        sim = simulate(scenario, seed=seed, size=size)
        sim.write(data)
        totals, walls, stages = [], [], []
        peak_kb = 0
        for r in progress_over(range(runs), "bench survey", unit="runs"):
            out = Path(tmp) / f"out{r}"
            cmd = [sys.executable, "-m", "graphslam", "survey", str(data), "--out", str(out), "--no-progress"]
            if config:
                cmd += ["--config", str(config)]
            before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
            t = time.perf_counter()
            proc = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "RERUN": "off"})
            walls.append(time.perf_counter() - t)
            if proc.returncode != 0:
                from graphslam.errors import SolverError

                raise SolverError(f"benchmark survey run failed: {proc.stderr.strip()}")
            peak_kb = max(peak_kb, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, before)
            rep = json.loads((out / "report.json").read_text())
            totals.append(rep["timings_s"]["total"])
            stages.append(rep["timings_s"])
        keys = stages[0].keys()
        return {
            "scenario": scenario,
            "seed": seed,
            "size": size,
            "runs": runs,
            "steps": sim.survey.n_steps,
            "scans": sim.survey.n_scans,
            "wall_s_median": round(statistics.median(walls), 3),
            "pipeline_s_median": round(statistics.median(totals), 3),
            "stages_s_median": {k: round(statistics.median(s[k] for s in stages), 3) for k in keys},
            "peak_rss_mb": round(peak_kb / 1024, 1),
            "landmark_mean_m": rep.get("evaluation", {}).get("landmarks", {}).get("mean_m"),
        }


def fig8(
    scenario: str,
    seeds: Sequence[int],
    cfg: GraphSlamConfig,
    *,
    test_walks: int = 5,
    k: int = 3,
    plot: Path | None = None,
) -> dict[str, Any]:
    """The paper's fig. 8: kNN errors of held-out test walks on the crowdsourced vs the surveyed map.

    The crowdsourced map lives in the aligned frame; it is put into the site frame with the
    SE(2) fit of the landmark evaluation (evaluation only, like the paper's manual rotation).
    The surveyed map holds the same fingerprints at their ground-truth positions.
    """
    import numpy as np

    from graphslam.core.common.geometry import interpolate_xy
    from graphslam.core.radiomap.knn import KnnConfig, KnnLocator
    from graphslam.core.survey.radio_maps import crowdsourced_radio_map, surveyed_radio_map
    from graphslam.sim import simulate

    errs: dict[str, list] = {"crowdsourced": [], "surveyed": []}
    per_seed = []
    for seed in progress_over(seeds, "bench fig8", unit="seeds"):
        sim = simulate(scenario, seed=seed, test_walks=test_walks)
        al = align(sim.survey, cfg)
        ev = evaluate(al.tracks, sim.survey)
        maps = {
            "crowdsourced": crowdsourced_radio_map(sim.survey, al, cfg, site_from_aligned=np.array(ev.site_from_aligned)),
            "surveyed": surveyed_radio_map(sim.survey, al, cfg),
        }
        scans = [sc for s in sim.test_sessions for sc in s.scans]
        truth = np.concatenate(
            [interpolate_xy(s.ground_truth, np.array([sc.t_ns for sc in s.scans], float)) for s in sim.test_sessions]
        )
        row: dict[str, Any] = {"seed": seed, "queries": len(scans)}
        for name, rm in maps.items():
            res = KnnLocator(rm, KnnConfig(k=k)).locate([sc.readings for sc in scans])
            e = np.linalg.norm(res.xy - truth, axis=1)
            e = e[np.isfinite(e)]
            errs[name].append(e)
            row[f"{name}_p_lt_10m"] = round(float(np.mean(e < 10.0)), 4)
            row[f"{name}_median_m"] = round(float(np.median(e)), 3)
        per_seed.append(row)
    all_e = {n: np.concatenate(v) for n, v in errs.items()}
    out: dict[str, Any] = {
        "scenario": scenario,
        "seeds": list(seeds),
        "k": k,
        "test_walks_per_seed": test_walks,
        "queries": int(len(all_e["surveyed"])),
        "per_seed": per_seed,
    }
    for n, e in all_e.items():
        out[f"{n}_p_lt_10m"] = round(float(np.mean(e < 10.0)), 4)
        out[f"{n}_mean_m"] = round(float(np.mean(e)), 3)
        out[f"{n}_median_m"] = round(float(np.median(e)), 3)
        out[f"{n}_p90_m"] = round(float(np.percentile(e, 90)), 3)
    if plot is not None:
        from graphslam.viz.plots import error_cdf

        error_cdf(all_e, plot, title=f"kNN (k={k}) on held-out walks, {scenario}, seeds {','.join(map(str, seeds))}")
    return out


REAL_VARIANTS = ("headings", "no_headings", "control_points")
BIG_COMPONENT_WALKS = 5  # walks_in_components_of_5_or_more
RIGHT_WALK_M = 5.0  # a walk whose mean landmark error (after its component's SE(2) fit) is at most this is right


def real_floor_rows(
    folders: Sequence[Path],
    cfg: GraphSlamConfig,
    floors: Sequence[str] | None = None,
    *,
    variants: Sequence[str] = REAL_VARIANTS,
    control_points: str = "auto",
) -> Iterator[dict[str, Any]]:
    """Survey each floor of real recordings with landmarks once per variant; one row per floor and
    variant, yielded as each is done.

    A folder holding ``.mcap`` files is one floor; a folder without (an ILC site) stands for its
    floor sub-folders (``floors`` picks some). Variants: ``headings`` (``cfg`` as given: with the
    phones' headings where every walk has them), ``no_headings`` (``cfg`` with
    ``heading.enabled=false``: the registration path) and ``control_points`` (``cfg`` with the
    floor folder's ``control_points.csv``, component 0 in the site frame; only where the file is
    there and ``control_points`` is ``"auto"``; ``"none"``: never). Ground truth only scores
    (``graphslam.core.survey.evaluate.component_errors``): each component after its own SE(2) fit,
    component 0 of a survey in the site frame also with no fit. See ``_real_row`` for the fields.
    """
    from graphslam.app.batch import CONTROL_POINTS_FILE  # a floor folder's control points, as survey-batch
    from graphslam.errors import ConfigError
    from graphslam.io.mcap_reader import floor_folders

    unknown = [v for v in variants if v not in REAL_VARIANTS]
    if unknown or not variants:
        raise ConfigError(f"bench real variants {list(variants)!r}: expected some of {', '.join(REAL_VARIANTS)}")
    if control_points not in ("auto", "none"):
        raise ConfigError(f"--control-points {control_points!r}: expected auto or none")
    expanded: list[Path] = []
    for f in map(Path, folders):
        expanded += [f] if any(f.glob("*.mcap")) else floor_folders(f, floors)
    plan = []
    for folder in expanded:
        cp_file = folder / CONTROL_POINTS_FILE
        for v in variants:
            if v == "control_points" and (control_points == "none" or not cp_file.is_file()):
                continue
            plan.append((folder, v, cp_file if v == "control_points" else None))
    configs = {v: _variant_config(cfg, v) for v in variants}
    for folder, variant, cp_file in progress_over(plan, "bench real", unit="surveys"):
        yield _real_row(folder, variant, configs[variant], cp_file)


def real_floors(
    folders: Sequence[Path],
    cfg: GraphSlamConfig,
    floors: Sequence[str] | None = None,
    *,
    variants: Sequence[str] = REAL_VARIANTS,
    control_points: str = "auto",
) -> list[dict[str, Any]]:
    """``real_floor_rows`` as a list."""
    return list(real_floor_rows(folders, cfg, floors, variants=variants, control_points=control_points))


def _variant_config(cfg: GraphSlamConfig, variant: str) -> GraphSlamConfig:
    if variant != "no_headings":
        return cfg
    from graphslam.config import config_from_dict

    data = cfg.model_dump()
    data["heading"]["enabled"] = False
    return config_from_dict(data, "bench real no_headings")


def _real_row(folder: Path, variant: str, cfg: GraphSlamConfig, cp_file: Path | None) -> dict[str, Any]:
    """One floor surveyed (``run_survey``, no files) under one variant, scored per component.

    ``main``: walks in component 0; ``main_mean_m`` (= ``mean_m``) / ``p90_m`` / ``max_m`` its
    landmark errors after one SE(2) fit, ``main_site_mean_m`` with no fit when it is in the site
    frame (control points; else None); ``walks_in_components_of_5_or_more``, its fraction of the
    walks read and ``components_of_5_or_more_mean_m`` (each such component's mean error after its own
    fit, weighted by its walks; components without 2 marks left out); ``walks_over_10m`` /
    ``walks_over_15m``: walks of any component whose mean error is over 10 / 15 m (each component
    after its own fit; component 0 in the site frame without fit); ``time_s``: the whole survey.
    """
    from graphslam.app.survey import run_survey
    from graphslam.core.survey.evaluate import component_errors

    log.info("bench real: %s, %s", folder, variant)
    t = time.perf_counter()
    res = run_survey([folder], None, cfg, picture=False, control_points=cp_file)
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
    big = [c for c in comps if len(c.walks) >= BIG_COMPONENT_WALKS]
    n_big = sum(len(c.walks) for c in big)
    scored = [c for c in big if c.landmarks.n > 0]
    w = sum(len(c.walks) for c in scored)
    big_mean = sum(len(c.walks) * c.landmarks.mean_m for c in scored) / w if w else None
    c0 = comps[0] if comps else None
    pl = al.placement

    def r2(v: float | None) -> float | None:
        return None if v is None or not np.isfinite(v) else round(float(v), 2)

    return {
        "floor": folder.name,
        "variant": variant,
        "walks": n,
        "aligned": len(al.tracks),
        "aligned_fraction": round(len(al.tracks) / max(1, n), 3),
        "main": main,
        "main_fraction": round(main / max(1, n), 3),
        "landmarks": lm.n if lm else 0,
        "main_mean_m": r2(lm.mean_m) if lm and lm.n else None,
        "main_site_mean_m": r2(c0.site.mean_m) if c0 is not None and c0.site is not None and c0.site.n else None,
        "mean_m": r2(lm.mean_m) if lm and lm.n else None,
        "p90_m": r2(lm.p90_m) if lm and lm.n else None,
        "max_m": r2(lm.max_m) if lm and lm.n else None,
        "components": len(al.components),
        "walks_in_components_of_5_or_more": n_big,
        "walks_in_components_of_5_or_more_fraction": round(n_big / max(1, n), 3),
        "components_of_5_or_more_mean_m": r2(big_mean),
        "walks_over_10m": int(sum(v > 10.0 for v in per_walk.values())),
        "walks_over_15m": int(sum(v > 15.0 for v in per_walk.values())),
        "frame": al.frame,
        "control_points": None if cp_file is None else str(cp_file),
        "per_walk_rigid_fit_mean_m": r2(ev.landmarks_per_walk_fit.mean_m) if ev else None,
        "initialization": cfg.optimizer.initialization,
        "placement": None if pl is None else pl.method,
        "loop_consistency": None if pl is None or pl.loop_consistency is None else round(pl.loop_consistency, 3),
        "reliable": None if pl is None else pl.reliable,
        "confidence": _confidence_separation(al, _per_walk_fit(comps)) if comps else None,
        "time_s": round(dt, 2),
    }


def _per_walk_fit(comps: Sequence[Any]) -> dict[str, float]:
    """session id -> mean landmark error after its component's SE(2) fit (``ComponentErrors``)."""
    return {sid: e for c in comps for sid, e in c.per_walk_mean_m.items()}


def real_summary(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """One line per variant over ``real_floor_rows``' rows: floors, walks, their sums and
    walk-weighted means (``main_mean_m`` weighted by ``main``, ``components_of_5_or_more_mean_m`` by
    its walks)."""
    out = []
    for variant in dict.fromkeys(r["variant"] for r in rows):
        rs = [r for r in rows if r["variant"] == variant]
        walks = sum(r["walks"] for r in rs)

        def wmean(key: str, weight: str) -> float | None:
            pairs = [(r[weight], r[key]) for r in rs if r[key] is not None and r[weight]]
            tot = sum(p[0] for p in pairs)
            return round(sum(a * b for a, b in pairs) / tot, 2) if tot else None

        main = sum(r["main"] for r in rs)
        big = sum(r["walks_in_components_of_5_or_more"] for r in rs)
        out.append({
            "summary": variant,
            "floors": len(rs),
            "walks": walks,
            "main": main,
            "main_fraction": round(main / max(1, walks), 3),
            "main_mean_m": wmean("main_mean_m", "main"),
            "main_site_mean_m": wmean("main_site_mean_m", "main"),
            "walks_in_components_of_5_or_more": big,
            "walks_in_components_of_5_or_more_fraction": round(big / max(1, walks), 3),
            "components_of_5_or_more_mean_m": wmean("components_of_5_or_more_mean_m", "walks_in_components_of_5_or_more"),
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
    if pl is not None and pl.method in ("growth", "heading"):
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


def ilc_floors(site_dir: Path, cfg: GraphSlamConfig, floors: Sequence[str] | None = None) -> list[dict[str, Any]]:
    """Every floor of an ILC 2.0 site (``real_floors`` over the site's floor folders), ``cfg`` as
    given only (the ``headings`` variant): one row per floor."""
    return real_floors([site_dir], cfg, floors, variants=("headings",))


def filters_cart(
    seeds: Sequence[int],
    *,
    shadowing_db: float | None = None,
    plot_dir: Path | None = None,
    smoothers: Sequence[str] = ("rts", "map"),
    lags: Sequence[float] = (),
    window_s: float = 480.0,
    restart_every: int = 10,
    shadowing: tuple[float, float] | None = (0.5, 3.0),
) -> dict[str, Any]:
    """The filter papers' experiment (cart, 5 rounds, 4 APs) simulated per seed; EKF with Paper 000's
    constants, UKF with Paper 002's (each paper's P0/gamma for truth and filter, their Q, R, x0, P0).

    RMS error in x and y per seed and estimator: the causal filter (``ekf``, ``ukf``) and, per
    name in ``smoothers``, the same run smoothed offline under the same model (``ekf+rts``,
    ``ekf+map``, ...; ``graphslam.core.tracking.smoother``); mean / median / p90 over seeds and the
    number of seeds meeting the papers' figures. Per lag in ``lags`` (s), the fixed-lag smoother
    under the same model (``{kind}+fixed-lag:LAG``: each epoch reported LAG s after it, from a
    window of ``max(window_s, LAG)`` s, Gaussian losses, also solved from dead-reckoning starts
    every ``restart_every`` epochs). With ``shadowing = (share, corr_m)`` the fixed-lag smoother
    (``{kind}+fixed-lag:LAG+shadowing``) and the causal filter (``{kind}+shadowing``) also run under
    the same model with ``share`` of its RSSI variance as correlated shadowing states (``FusionModel.with_shadowing``: same total R, errors
    correlated over ``corr_m`` of the distance moved). ``shadowing_db`` overrides the documented
    default (4 dB) for a sensitivity sweep. ``plot_dir``: one PNG per filter (path, |error|,
    trace P) for the first seed.
    """
    import dataclasses

    import numpy as np

    from graphslam.core.tracking.filters import Epochs, FusionModel, make_filter, run_epochs
    from graphslam.core.tracking.fixed_lag import FixedLagConfig, fixed_lag_smooth
    from graphslam.core.tracking.smoother import smooth
    from graphslam.sim.cart import PAPER_P0, PAPER_RMS_TARGETS_M, PAPER_X0, CartNoise, simulate_cart

    noise = CartNoise() if shadowing_db is None else dataclasses.replace(CartNoise(), shadowing_sigma_db=shadowing_db)
    out: dict[str, Any] = {"seeds": list(seeds), "noise": dataclasses.asdict(noise)}
    for kind, model in (("ekf", FusionModel.paper_ekf()), ("ukf", FusionModel.paper_ukf())):
        fl_models = {"": model}
        if shadowing is not None:
            fl_models["+shadowing"] = model.with_shadowing(*shadowing)
        rms: dict[str, list[tuple[float, float]]] = {
            kind: [], **({f"{kind}+shadowing": []} if shadowing is not None else {}),
            **{f"{kind}+{sm}": [] for sm in smoothers},
            **{f"{kind}+fixed-lag:{lag:g}{tag}": [] for lag in lags for tag in fl_models},
        }
        tp, secs = [], {name: 0.0 for name in rms}
        for i, seed in enumerate(progress_over(seeds, f"bench filters {kind}", unit="seeds")):
            run = simulate_cart(seed, path_loss=model.path_loss, noise=noise)
            epochs = Epochs.fixed_rate(run.y_velocity, run.y_rssi, run.period_s)
            t0 = time.perf_counter()
            res = run_epochs(make_filter(kind, model), PAPER_X0, PAPER_P0, epochs)
            secs[kind] += time.perf_counter() - t0
            ests = {kind: res.x}
            if shadowing is not None:
                t0 = time.perf_counter()
                ests[f"{kind}+shadowing"] = run_epochs(make_filter(kind, fl_models["+shadowing"]),
                                                       *fl_models["+shadowing"].prior(PAPER_X0, PAPER_P0), epochs).x
                secs[f"{kind}+shadowing"] += time.perf_counter() - t0
            for sm in smoothers:
                t0 = time.perf_counter()
                ests[f"{kind}+{sm}"] = smooth(model, PAPER_X0, PAPER_P0, epochs, res, sm).x
                secs[f"{kind}+{sm}"] += time.perf_counter() - t0
            for lag in lags:
                flc = FixedLagConfig(
                    lag_s=float(lag), window_s=max(window_s, float(lag)), huber_k=None, prune_cost=None,
                    restart_every=restart_every,
                )
                for tag, fl_model in fl_models.items():
                    t0 = time.perf_counter()
                    x0, P0 = fl_model.prior(PAPER_X0, PAPER_P0)
                    ests[f"{kind}+fixed-lag:{lag:g}{tag}"] = fixed_lag_smooth(fl_model, [x0], P0, epochs, flc).x
                    secs[f"{kind}+fixed-lag:{lag:g}{tag}"] += time.perf_counter() - t0
            for name, X in ests.items():
                e = X[:, :2] - run.xy
                rms[name].append((float(np.sqrt(np.mean(e[:, 0] ** 2))), float(np.sqrt(np.mean(e[:, 1] ** 2)))))
            tp.append(float(res.trace_p[-1]))
            if plot_dir is not None and i == 0:
                from graphslam.viz.tracking_plots import cart_figure

                cart_figure(
                    run.t_s, run.xy, res.x[:, :2], res.trace_p, Path(plot_dir) / f"tracking_cart_{kind}.png",
                    f"{kind.upper()}, simulated cart (seed {seed}, shadowing {noise.shadowing_sigma_db:g} dB)",
                )
        tx, ty = PAPER_RMS_TARGETS_M[kind]
        for name, r in rms.items():
            a = np.array(r)
            for j, axis in enumerate("xy"):
                v = a[:, j]
                out[f"{name}_rms_{axis}_m"] = {
                    "mean": round(float(v.mean()), 3), "median": round(float(np.median(v)), 3),
                    "p90": round(float(np.percentile(v, 90)), 3), "min": round(float(v.min()), 3),
                    "max": round(float(v.max()), 3), "per_seed": [round(float(x), 3) for x in v],
                }
            out[f"{name}_seeds_meeting_target"] = int(((a[:, 0] <= tx) & (a[:, 1] <= ty)).sum())
            out[f"{name}_seconds_per_run"] = round(secs[name] / max(len(seeds), 1), 3)
        out[f"{kind}_final_trace_p_median"] = round(float(np.median(tp)), 4)
    return out


def tracking_paper(
    scenario: str,
    seeds: Sequence[int],
    cfg: GraphSlamConfig,
    *,
    test_walks: int = 3,
    filters: Sequence[str] = ("ekf", "ukf"),
    smoothers: Sequence[str] = (),
    knn_fixes: bool = False,
    lags: Sequence[float] = (),
    track_overrides: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Held-out walks tracked (EKF / UKF, AP models fitted from the crowdsourced radio map) vs kNN
    positioning of the same scans on the same map; AP position errors vs the simulator's APs.
    ``smoothers`` adds offline-smoothed variants, ``knn_fixes`` variants that also fuse each
    scan's kNN fix, ``lags`` the fixed-lag tracker at each lag (s; named ``fixed-lag:LAG``, kNN
    fixes fused, the other settings ``TrackConfig``'s defaults updated by ``track_overrides``).
    Every tracker row also reports ``inside_95``: the share of scan-time errors inside its 95 %
    position ellipse.

    The crowdsourced map is put into the site frame with the landmark SE(2) fit (evaluation only,
    as ``fig8``); errors at scan times (the tracker's step output interpolated there).
    """
    import numpy as np

    from graphslam.core.tracking.apmodel import ApModels, ap_position_errors
    from graphslam.core.common.geometry import interpolate_xy
    from graphslam.core.radiomap.knn import KnnConfig, KnnLocator
    from graphslam.core.survey.radio_maps import crowdsourced_radio_map
    from graphslam.core.types import PoseTrack
    from graphslam.sim import simulate
    from graphslam.app.track import TrackConfig, track_sessions

    from graphslam.app.tracking_bench import interpolate_cov
    from graphslam.core.tracking.calibration import ellipse_coverage

    over = dict(track_overrides or {})
    configs = {
        variant_name(f, sm, fx): TrackConfig(**{**over, "filter": f, "smoother": sm, "knn_fixes": fx})
        for fx in ((False, True) if knn_fixes else (False,)) for f in filters for sm in ("none", *smoothers)
    }
    for lag in lags:
        configs[f"fixed-lag:{lag:g}"] = TrackConfig(**{**over, "filter": "fixed-lag", "lag_s": float(lag)})
    errs: dict[str, list] = {"knn": [], **{name: [] for name in configs}}
    inside: dict[str, list] = {name: [] for name in configs}
    ap_err, per_seed = [], []
    n_unfitted = 0
    for seed in progress_over(seeds, "bench tracking", unit="seeds"):
        sim = simulate(scenario, seed=seed, test_walks=test_walks)
        al = align(sim.survey, cfg)
        ev = evaluate(al.tracks, sim.survey)
        rm = crowdsourced_radio_map(sim.survey, al, cfg, site_from_aligned=np.array(ev.site_from_aligned))
        models = ApModels.fit(rm)
        n_unfitted += len(models.unfitted)
        e_ap = ap_position_errors(models, sim.building.aps.bssids, sim.building.aps.xy)
        ap_err.append(e_ap)
        row: dict[str, Any] = {"seed": seed, "aps_fitted": len(models.fitted), "aps_unfitted": len(models.unfitted)}
        sessions = sim.test_sessions
        t_scan = [np.array([sc.t_ns for sc in s.scans], float) for s in sessions]
        truth = np.concatenate([interpolate_xy(s.ground_truth, t) for s, t in zip(sessions, t_scan)])
        knn = KnnLocator(rm, KnnConfig(k=3)).locate([sc.readings for s in sessions for sc in s.scans])
        e = np.linalg.norm(knn.xy - truth, axis=1)
        errs["knn"].append(e[np.isfinite(e)])
        row["knn_mean_m"] = round(float(np.nanmean(e)), 3)
        for name, tcfg in configs.items():
            t0 = time.perf_counter()
            tracks = track_sessions(sessions, rm, models, tcfg)
            est = np.concatenate(
                [interpolate_xy(PoseTrack(tr.t_ns, tr.xy, np.zeros(len(tr.t_ns))), t) for tr, t in zip(tracks, t_scan)]
            )
            cov = np.concatenate([interpolate_cov(tr.t_ns, tr.P, t) for tr, t in zip(tracks, t_scan)])
            e = np.linalg.norm(est - truth, axis=1)
            errs[name].append(e)
            inside[name].append(ellipse_coverage(est - truth, cov))
            row[f"{name}_mean_m"] = round(float(e.mean()), 3)
            row[f"{name}_s"] = round(time.perf_counter() - t0, 2)
        per_seed.append(row)
    out: dict[str, Any] = {"scenario": scenario, "seeds": list(seeds), "test_walks_per_seed": test_walks}
    for name, v in errs.items():
        a = np.concatenate(v)
        out[name] = {
            "n": int(a.size), "mean_m": round(float(a.mean()), 3), "median_m": round(float(np.median(a)), 3),
            "p90_m": round(float(np.percentile(a, 90)), 3),
        }
        if name in inside:
            out[name]["inside_95"] = round(float(np.concatenate(inside[name]).mean()), 3)
    a = np.concatenate(ap_err)
    out["ap_position_error"] = {
        "n_fitted": int(a.size), "n_unfitted": n_unfitted, "median_m": round(float(np.median(a)), 3),
        "p90_m": round(float(np.percentile(a, 90)), 3),
    }
    out["per_seed"] = per_seed
    return out


def variant_name(filter_kind: str, smoother: str, knn_fixes: bool = False) -> str:
    """'ekf', 'ekf+map', 'ekf+knn', 'ekf+knn+map', ..."""
    return "+".join([filter_kind] + (["knn"] if knn_fixes else []) + ([smoother] if smoother != "none" else []))
