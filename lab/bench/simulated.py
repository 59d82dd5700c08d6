"""Benchmarks on simulated surveys and walks: survey accuracy over seeds, end-to-end speed, the paper's
fig. 8, the filter papers' cart, tracking held-out walks; ILC floors (``graphslam bench real``'s rows).

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
from typing import Any, Sequence

from graphslam import GraphSlamConfig, align, evaluate, progress_over, real_floors

log = logging.getLogger(__name__)


def accuracy(scenario: str, seeds: Sequence[int], cfg: GraphSlamConfig, *, size: float = 1.0) -> list[dict[str, Any]]:
    """Align simulated surveys in memory; landmark/heading/step errors per seed."""
    from graphslam import simulate

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
    from graphslam import simulate

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
                from graphslam import SolverError

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

    from graphslam import (
        calibrate_uncertainty, crowdsourced_radio_map, interpolate_xy, KnnConfig, KnnLocator, simulate,
        surveyed_radio_map,
    )
    R95 = float(np.sqrt(-2.0 * np.log(0.05)))
    default_e: dict[str, list] = {"crowdsourced": [], "surveyed": []}
    inside: dict[str, list] = {"crowdsourced": [], "surveyed": []}


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
            res = KnnLocator(rm, KnnConfig(k=k, metric="eq9", index="exact")).locate([sc.readings for sc in scans])  # the paper's
            e = np.linalg.norm(res.xy - truth, axis=1)
            e = e[np.isfinite(e)]
            errs[name].append(e)
            row[f"{name}_p_lt_10m"] = round(float(np.mean(e < 10.0)), 4)
            row[f"{name}_median_m"] = round(float(np.median(e)), 3)
            # the product's default kNN (Sorensen) and its sigma_m, calibrated on the map without truth
            d = KnnLocator(rm, KnnConfig(k=k, index="exact")).locate([sc.readings for sc in scans])
            ed = np.linalg.norm(d.xy - truth, axis=1)
            ok = np.isfinite(ed)
            default_e[name].append(ed[ok])
            u = calibrate_uncertainty(rm, KnnConfig(k=k))
            if u is not None:
                inside[name].append(ed[ok] <= R95 * u.sigma_of(d)[ok])  # sigma_m as answered: outside ones widened
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
        out[f"{n}_default_knn_mean_m"] = round(float(np.mean(np.concatenate(default_e[n]))), 3)
        if inside[n]:
            out[f"{n}_default_inside_95_circle"] = round(float(np.mean(np.concatenate(inside[n]))), 3)
    if plot is not None:
        from graphslam import error_cdf

        error_cdf(all_e, plot, title=f"kNN (k={k}) on held-out walks, {scenario}, seeds {','.join(map(str, seeds))}")
    return out


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

    from graphslam import (
        CartNoise, Epochs, fixed_lag_smooth, FixedLagConfig, FusionModel, make_filter, PAPER_P0,
        PAPER_RMS_TARGETS_M, PAPER_X0, run_epochs, simulate_cart, smooth,
    )


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
                    restart_every=restart_every, adaptive_rssi=False, report="best",  # one hypothesis, the papers' R
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
                from graphslam import cart_figure

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
    fixes fused, the other settings ``TrackConfig``'s defaults updated by ``track_overrides``, ``{"section.key": value}``).
    Every tracker row also reports ``inside_95``: the share of scan-time errors inside its 95 %
    position ellipse.

    The crowdsourced map is put into the site frame with the landmark SE(2) fit (evaluation only,
    as ``fig8``); errors at scan times (the tracker's step output interpolated there).
    """
    import numpy as np

    from graphslam import (
        ap_position_errors, ApModels, crowdsourced_radio_map, interpolate_xy, KnnConfig, KnnLocator,
        PoseTrack, simulate, track_sessions, TrackConfig,
    )


    from graphslam import ellipse_coverage, interpolate_cov

    over = dict(track_overrides or {})
    configs = {
        variant_name(f, sm, fx): TrackConfig().updated({**over, "filter.kind": f, "filter.smoother": sm, "knn_fixes.enabled": fx})
        for fx in ((False, True) if knn_fixes else (False,)) for f in filters for sm in ("none", *smoothers)
    }
    for lag in lags:
        configs[f"fixed-lag:{lag:g}"] = TrackConfig().updated({**over, "filter.kind": "fixed-lag", "fixed_lag.lag_s": float(lag)})
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
        knn = KnnLocator(rm, KnnConfig(k=3, metric="eq9", index="exact")).locate([sc.readings for s in sessions for sc in s.scans])
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
