"""``python -m lab.bench uwb``: Paper 003's experiment (Fig. 5) in simulation, and the UWB survey.

``zones``: per seed, the seven-tag run of ``graphslam.sim.uwb.scenarios.simulate_zones`` through
the network simulation, then the paper's EKF over the ranges each tag completed (in the order
a live network would see them). Reported: collisions during ranging (frames of a TWR exchange
lost to a collision at their intended receiver), slots per tag per cycle, the clock offset of
every tag to its neighbours' average after sync (each cycle's worst tag), and the tracking
error per zone and per measurement type (truth = the tag's true position at the slot).

``survey``: the crowd of ``simulate_crowd`` aligned three ways: WiFi only (UWB ignored),
UWB clean, UWB with NLOS (the same walkers); mean step error in the site frame without any
fit (UWB) and after one SE(2) fit (all).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from numpy.typing import NDArray

from graphslam import MEASUREMENT_TYPES, track_tags, UwbEkfConfig

log = logging.getLogger(__name__)

ZONE_NAMES = ("A (4 anchors)", "B (3 anchors)", "C (2 anchors)", "D (0 anchors)")


def _stats(e: NDArray) -> dict[str, float | int]:
    e = np.asarray(e, float)
    if not len(e):
        return {"n": 0}
    return {"n": int(len(e)), "mean_m": round(float(e.mean()), 4), "median_m": round(float(np.median(e)), 4),
            "p90_m": round(float(np.percentile(e, 90)), 4)}


def zones_seed(seed: int, ekf: UwbEkfConfig = UwbEkfConfig()) -> tuple[dict[str, Any], dict[str, Any]]:
    """One run: (JSON row, raw arrays for the aggregate and the plots)."""
    from graphslam import simulate_zones

    t = time.perf_counter()
    run = simulate_zones(seed)
    t_sim = time.perf_counter() - t
    net = run.network
    cyc = [c for c in net.cycles if c.active_tags]
    offsets = np.array([max(c.offset_to_neighbours_s.values()) for c in cyc if c.offset_to_neighbours_s])
    slots = np.array([len(c.slots.get(tg, ())) for c in cyc for tg in c.active_tags])
    anchors = dict(zip(net.devices.anchor_ids, run.site.anchor_xyz))
    t = time.perf_counter()
    tracks = track_tags(net.epochs(), anchors, ekf)
    t_ekf = time.perf_counter() - t
    err, zone, kind, tag_of, t_of = [], [], [], [], []
    for ti, tid in enumerate(run.tag_ids):
        tr = tracks[tid]
        truth = run.paths.at(ti, tr.t_ns / 1e9)
        err.append(np.linalg.norm(tr.x[:, :2] - truth, axis=1))
        zone.append(run.site.zone_of(truth))
        kind.append(tr.kind)
        tag_of.append(np.full(len(tr.t_ns), ti))
        t_of.append(tr.t_ns / 1e9)
    raw = {k: np.concatenate(v) for k, v in (("err", err), ("zone", zone), ("kind", kind), ("tag", tag_of), ("t", t_of))}
    r = net.ranges
    los_err = (r.range_m - r.true_m)[~r.nlos]
    row = {
        "seed": seed,
        "duration_s": round(net.t1_s - net.t0_s, 1),
        "cycles": len(cyc),
        "ranging_collisions": int(sum(c.ranging_collisions for c in cyc)),
        "ranging_frames": int(sum(c.ranging_frames for c in cyc)),
        "schedule_conflicts": int(sum(c.schedule_conflicts for c in cyc)),
        "tag_cycles": int(len(slots)),
        "tag_cycles_without_slot": int((slots == 0).sum()),
        "tag_cycles_silenced_new_link": int(sum(len(c.suspended_tags) for c in cyc)),
        "slots_per_tag_per_cycle": {"min": int(slots.min()), "mean": round(float(slots.mean()), 3), "max": int(slots.max())},
        "sync_offset_us": {
            "median": round(float(np.median(offsets)) * 1e6, 2),
            "p95": round(float(np.percentile(offsets, 95)) * 1e6, 2),
            "max": round(float(offsets.max()) * 1e6, 2),
        },
        "sync_collisions": int(sum(c.sync_collisions for c in cyc)),
        "tdma_collisions": int(sum(c.tdma_collisions for c in cyc)),
        "ranges": int(len(r.t_s)),
        "range_error_los_m": {"mean": round(float(los_err.mean()), 4), "std": round(float(los_err.std()), 4)},
        "nlos_fraction": round(float(r.nlos.mean()), 4),
        "ekf_restarts": int(sum(tr.restarts for tr in tracks.values())),
        "ekf_rejected": int(sum(tr.rejected for tr in tracks.values())),
        "zone_error": {ZONE_NAMES[z]: _stats(raw["err"][raw["zone"] == z]) for z in range(4)},
        "time_s": {"simulate": round(t_sim, 2), "ekf": round(t_ekf, 2)},
    }
    return row, {"raw": raw, "run": run, "tracks": tracks}


def zones_benchmark(
    seeds: Sequence[int], ekf: UwbEkfConfig = UwbEkfConfig(), plot_dir: Path | None = None
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Rows per seed and the aggregate over ``seeds`` (the issue's criteria included)."""
    rows, raws = [], []
    for i, seed in enumerate(seeds):
        row, extra = zones_seed(seed, ekf)
        rows.append(row)
        raws.append(extra["raw"])
        log.info("uwb zones seed %d: %d collisions, zone A %.3f m", seed, row["ranging_collisions"],
                 row["zone_error"][ZONE_NAMES[0]].get("mean_m", float("nan")))
        if plot_dir is not None and i == 0:
            from graphslam import error_over_time, zones_map

            run = extra["run"]
            tracks = extra["tracks"]
            zones_map(
                run.site.walls, [(z.x0, z.x1) for z in run.site.zones], ZONE_NAMES, run.site.anchor_xyz,
                [run.paths.xy[k] for k in range(len(run.tag_ids))],
                [tracks[t].x[:, :2] for t in run.tag_ids], Path(plot_dir) / "uwb_zones.png",
                title=f"seven tags, seed {seed}: true paths (grey) and EKF estimates",
            )
            raw = extra["raw"]
            error_over_time(
                raw["t"], raw["err"], raw["kind"], raw["tag"], MEASUREMENT_TYPES, list(run.tag_ids),
                Path(plot_dir) / "uwb_fig8.png", title=f"EKF error per slot by measurement type (seed {seed})",
            )
    err = np.concatenate([r["err"] for r in raws])
    zone = np.concatenate([r["zone"] for r in raws])
    kind = np.concatenate([r["kind"] for r in raws])
    agg = {
        "seeds": len(rows),
        "ranging_collisions": sum(r["ranging_collisions"] for r in rows),
        "runs_with_ranging_collisions": sum(r["ranging_collisions"] > 0 for r in rows),
        "schedule_conflicts": sum(r["schedule_conflicts"] for r in rows),
        "tag_cycles": sum(r["tag_cycles"] for r in rows),
        "tag_cycles_without_slot": sum(r["tag_cycles_without_slot"] for r in rows),
        "min_slots_per_tag_per_cycle": min(r["slots_per_tag_per_cycle"]["min"] for r in rows),
        "mean_slots_per_tag_per_cycle": round(float(np.mean([r["slots_per_tag_per_cycle"]["mean"] for r in rows])), 3),
        "sync_offset_us_median_of_cycle_max": round(float(np.median([r["sync_offset_us"]["median"] for r in rows])), 2),
        "sync_offset_us_max": max(r["sync_offset_us"]["max"] for r in rows),
        "range_error_los_std_m": round(float(np.mean([r["range_error_los_m"]["std"] for r in rows])), 4),
        "zone_error": {
            ZONE_NAMES[z]: {
                "all": _stats(err[zone == z]),
                **{MEASUREMENT_TYPES[k]: _stats(err[(zone == z) & (kind == k)]) for k in range(len(MEASUREMENT_TYPES))
                   if ((zone == z) & (kind == k)).any()},
            }
            for z in range(4)
        },
        "type_error": {MEASUREMENT_TYPES[k]: _stats(err[kind == k]) for k in range(len(MEASUREMENT_TYPES))},
    }
    za = agg["zone_error"][ZONE_NAMES[0]]["all"]
    agg["criteria"] = {
        "zero_ranging_collisions": agg["ranging_collisions"] == 0,
        "every_tag_a_slot_every_cycle": agg["tag_cycles_without_slot"] == 0,
        "zone_A_mean_le_0.10_m": bool(za.get("mean_m", np.inf) <= 0.10),
    }
    return rows, agg


def _walk_errors(tracks: dict, survey: Any, T: NDArray) -> dict[str, float]:
    from graphslam import trajectory_errors

    return {sid: trajectory_errors({sid: tr}, survey, T).mean_m for sid, tr in tracks.items()}


def _mean_over(errors: dict[str, float], survey: Any, walks: Sequence[str]) -> float:
    """Mean step error over the steps of ``walks`` (weighted by steps, as the survey-wide mean)."""
    n = {s.session_id: len(s.steps) for s in survey}
    w = [n[s] for s in walks]
    return float(np.average([errors[s] for s in walks], weights=w)) if walks else float("nan")


def survey_seed(seed: int, n_anchors: int, cfg: Any) -> dict[str, Any]:
    """One crowd survey (clean and NLOS ranges, same walkers) aligned WiFi-only, with UWB, with
    UWB + NLOS. Errors: mean over steps vs ground truth; "site" = no fit, "fit" = one SE(2) fit."""
    from graphslam import align, CrowdUwb, evaluate, nlos_fraction, simulate_crowd

    out: dict[str, Any] = {"seed": seed, "anchors": n_anchors}
    runs = {"clean": simulate_crowd(seed, CrowdUwb(n_anchors=n_anchors)),
            "nlos": simulate_crowd(seed, CrowdUwb(n_anchors=n_anchors, nlos=True))}
    survey = runs["clean"].survey
    out["walks"] = len(survey)
    out["walks_without_wifi"] = list(runs["clean"].no_wifi)
    out["steps"] = survey.n_steps
    t = time.perf_counter()
    wifi = align(survey, cfg.model_copy(update={"uwb": cfg.uwb.model_copy(update={"enabled": False})}))
    t_wifi = time.perf_counter() - t
    ev = evaluate(wifi.tracks, survey)
    wifi_err = _walk_errors(wifi.tracks, survey, np.array(ev.site_from_aligned))
    out["wifi_only"] = {"aligned": len(wifi.tracks), "fit_mean_m": round(ev.steps.mean_m, 4), "align_s": round(t_wifi, 2)}
    for name, run in runs.items():
        t = time.perf_counter()
        al = align(run.survey, cfg)
        dt = time.perf_counter() - t
        ev_u = evaluate(al.tracks, run.survey)
        site = _walk_errors(al.tracks, run.survey, np.zeros(3))
        fit = _walk_errors(al.tracks, run.survey, np.array(ev_u.site_from_aligned))
        both = [s for s in wifi.tracks if s in al.tracks]
        no_wifi = [s for s in run.no_wifi if s in al.tracks]
        r = run.network.ranges
        out[f"uwb_{name}"] = {
            "frame": al.frame,
            "aligned": len(al.tracks),
            "site_mean_m": round(_mean_over(site, run.survey, list(al.tracks)), 4) if al.frame == "site" else None,
            "fit_mean_m": round(ev_u.steps.mean_m, 4),
            "same_walkers_as_wifi": {
                "walks": len(both),
                "uwb_m": round(_mean_over(site if al.frame == "site" else fit, run.survey, both), 4),
                "wifi_only_fit_m": round(_mean_over(wifi_err, survey, both), 4),
            },
            "walks_without_wifi_aligned": len(no_wifi),
            "walks_without_wifi_m": round(_mean_over(site if al.frame == "site" else fit, run.survey, no_wifi), 4),
            "ranges": int(len(r.t_s)),
            "nlos_fraction": round(nlos_fraction(run.network), 4),
            "ranging_collisions": int(sum(c.ranging_collisions for c in run.network.cycles)),
            "uwb": al.uwb.as_dict() if al.uwb is not None else None,
            "align_s": round(dt, 2),
        }
    c, n = out["uwb_clean"], out["uwb_nlos"]
    key = "site_mean_m" if c["frame"] == "site" else "fit_mean_m"
    if c[key] is not None and n[key] is not None:
        out["nlos_over_clean"] = round(n[key] / c[key], 3)
    return out


def survey_benchmark(seeds: Sequence[int], anchors: Sequence[int], cfg: Any) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Rows per (anchors, seed) and, per anchor count, the means and the issue's criteria."""
    rows = [survey_seed(seed, na, cfg) for na in anchors for seed in seeds]
    agg: dict[str, Any] = {}
    for na in anchors:
        rs = [r for r in rows if r["anchors"] == na]
        m = lambda f: round(float(np.mean([f(r) for r in rs])), 4)  # noqa: E731
        site = na > 0
        clean_key = "site_mean_m" if site else "fit_mean_m"
        a = {
            "seeds": len(rs),
            "wifi_only_fit_m": m(lambda r: r["wifi_only"]["fit_mean_m"]),
            "uwb_clean_m": m(lambda r: r["uwb_clean"][clean_key]),
            "uwb_nlos_m": m(lambda r: r["uwb_nlos"][clean_key]),
            "same_walkers_uwb_m": m(lambda r: r["uwb_clean"]["same_walkers_as_wifi"]["uwb_m"]),
            "same_walkers_wifi_only_fit_m": m(lambda r: r["uwb_clean"]["same_walkers_as_wifi"]["wifi_only_fit_m"]),
            "walks_without_wifi": sum(len(r["walks_without_wifi"]) for r in rs),
            "walks_without_wifi_aligned": sum(r["uwb_clean"]["walks_without_wifi_aligned"] for r in rs),
            "walks_without_wifi_m": m(lambda r: r["uwb_clean"]["walks_without_wifi_m"]),
            "nlos_fraction": m(lambda r: r["uwb_nlos"]["nlos_fraction"]),
            "nlos_over_clean": m(lambda r: r["uwb_nlos"][clean_key] / r["uwb_clean"][clean_key]),
        }
        a["criteria"] = {
            "site_frame_le_0.3_m": bool(site and a["uwb_clean_m"] <= 0.3),
            "le_half_wifi_only": bool(a["same_walkers_uwb_m"] <= 0.5 * a["same_walkers_wifi_only_fit_m"]),
            "walks_without_wifi_joined": a["walks_without_wifi_aligned"] == a["walks_without_wifi"],
            "nlos_within_1.5x_clean": bool(a["uwb_nlos_m"] <= 1.5 * a["uwb_clean_m"]),
        }
        agg[f"anchors_{na}"] = a
    return rows, agg
