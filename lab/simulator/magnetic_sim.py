#!/usr/bin/env python3
"""The survey on simulated surveys with and without the magnetic field: components and the magnetic links.

Per scenario and seed (the simulated walks carry ``/phone/magnetic``), the survey twice: as
configured and with ``magnetic.enabled=false``. One JSON line each: walks in the main map and its
landmark error (one SE(2) fit), walks in components of >= 4 and >= 5 walks with their mean landmark
error (each component its own fit, weighted by walks), walks over 10 m; with the field, the
magnetic links the survey keeps (the graph's factors) scored against the simulator's ground truth:
a link is right when its node pairs' median true distance is under 3 m (ground truth only to score).
Museum links are split by route (repetitions of one route vs different routes).

    python lab/simulator/magnetic_sim.py museum --seeds 0,1,2 [--set KEY=VALUE ...]
"""

from __future__ import annotations

import argparse
import json
import logging
import re

import numpy as np

from graphslam import align, build_problem, component_errors, evaluate, load_config, parse_overrides, simulate

_LINK_LOG = re.compile(r"magnetic: (\d+) links, (\d+) consistent with their units' placement")


class _Capture(logging.Handler):
    """The survey's log line counting its magnetic links (found, kept: consistent with the placement)."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.counts: tuple[int, int] | None = None

    def emit(self, record: logging.LogRecord) -> None:
        m = _LINK_LOG.match(record.getMessage())
        if m:
            self.counts = tuple(int(v) for v in m.groups())  # type: ignore[assignment]


def _route(session_id: str) -> str:
    m = re.search(r"-(route\d+|stairs\d+)-rep", session_id)
    return m.group(1) if m else session_id


def link_scores(survey, problem) -> dict:  # type: ignore[no-untyped-def]
    """The kept links (``problem.magnetic``) against the truth: per link its pairs' median distance."""
    links = problem.magnetic
    if links is None or not len(links):
        return {"kept": 0}
    truth = np.concatenate([s.ground_truth.xy for s in survey.sessions])
    pn = links.pair_nodes
    d = np.linalg.norm(truth[pn[:, 0]] - truth[pn[:, 1]], axis=1)
    ids = [s.session_id for s in survey.sessions]
    med = np.array([np.median(d[links.pair_link == k]) for k in range(len(links))])
    same = np.array([_route(ids[a]) == _route(ids[b]) for a, b in zip(links.a, links.b)])
    out = {
        "kept": len(links),
        "kept_right": int((med < 3.0).sum()),
        "precision": round(float((med < 3.0).mean()), 3),
        "pairs": len(d),
        "pair_median_m": round(float(np.median(d)), 2),
        "pair_within_1p5m": round(float((d < 1.5).mean()), 3),
        "walks_linked": len(set(links.a.tolist()) | set(links.b.tolist())),
    }
    if survey.sessions[0].session_id.startswith("museum"):
        out |= {
            "same_route": int(same.sum()), "same_route_right": int((med[same] < 3.0).sum()),
            "other_route": int((~same).sum()), "other_route_right": int((med[~same] < 3.0).sum()),
            "route_pairs_linked": sorted({tuple(sorted((_route(ids[a]), _route(ids[b]))))
                                          for a, b, s in zip(links.a, links.b, same) if not s}),
        }
    return out


def survey_row(scenario: str, seed: int, survey, cfg, field: bool) -> dict:  # type: ignore[no-untyped-def]
    al = align(survey, cfg)
    ev = evaluate(al.main_tracks(), survey)
    comps = component_errors(al, survey, site_frame=False)
    per_walk = {sid: e for c in comps for sid, e in c.per_walk_mean_m.items()}
    row = {
        "scenario": scenario, "seed": seed, "magnetic": field, "walks": len(survey),
        "main": len(al.main_tracks()), "main_mean_m": round(ev.landmarks.mean_m, 3),
    }
    for n in (4, 5):
        big = [c for c in comps if len(c.walks) >= n and c.landmarks.n > 0]
        w = sum(len(c.walks) for c in big)
        row[f"walks_in_components_of_{n}_or_more"] = w
        row[f"components_of_{n}_or_more_mean_m"] = (
            round(sum(len(c.walks) * c.landmarks.mean_m for c in big) / w, 3) if w else None
        )
    row["walks_over_10m"] = int(sum(v > 10.0 for v in per_walk.values()))
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scenario")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--size", type=float, default=1.0)
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    args = ap.parse_args()
    cfg = load_config(None, parse_overrides(args.overrides))
    off = load_config(None, parse_overrides(args.overrides + ["magnetic.enabled=false"]))
    cap = _Capture()
    logging.getLogger("graphslam").addHandler(cap)
    logging.getLogger("graphslam").setLevel(logging.INFO)
    for seed in (int(s) for s in args.seeds.split(",")):
        survey = simulate(args.scenario, seed=seed, size=args.size).survey
        cap.counts = None
        problem = build_problem(survey, cfg)
        links = link_scores(survey, problem)
        if cap.counts is not None:
            links |= dict(zip(("found", "kept_logged"), cap.counts))
        print(json.dumps(survey_row(args.scenario, seed, survey, cfg, True) | {"links": links}), flush=True)
        print(json.dumps(survey_row(args.scenario, seed, survey, off, False)), flush=True)


if __name__ == "__main__":
    main()
