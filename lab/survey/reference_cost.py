"""What a surveyed reference map gives a crowd and what it costs: the crowd walks of a floor (those
the reference was not made from) surveyed alone, on the reference, on the reference with control
points, with control points alone, and the last three with the headings off (walks without them), scored
per component (ground truth only scores); then
``graphslam survey`` of the crowd with and without ``--reference-map`` as whole processes,
alternating, the median wall time of each.

    python lab/survey/reference_cost.py ../shared/data/ipin2023/b100_f-2 [ROUNDS]
"""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from graphslam import SurveyInputs, component_errors, crowd_walks, load_config, run_survey


def score(inputs: SurveyInputs, cfg) -> dict:
    """The main map's walks and landmark mean (site frame with no fit when it is in one, else its own SE(2)
    fit), and the walks of any component whose mean error is over 6 m."""
    res = run_survey(inputs, cfg)
    al = res.alignment
    site = al.frame == "site"
    comps = component_errors(al, res.survey, site_frame=site)
    per_walk: dict[str, float] = {}
    for c in comps:
        per_walk.update(c.site_per_walk_mean_m if c.site_per_walk_mean_m is not None else c.per_walk_mean_m)
    c0 = comps[0]
    mean = c0.site.mean_m if site and c0.site is not None else c0.landmarks.mean_m
    return {"walks": len(res.survey), "main": len(al.components[0].walks), "frame": al.frame,
            "main_mean_m": round(float(mean), 2), "walks_over_6m": int(sum(v > 6.0 for v in per_walk.values()))}


def main(folder: Path, rounds: int = 5) -> None:
    ref, cp = folder / "reference_map.csv", folder / "control_points.csv"
    crowd = crowd_walks(folder, ref)
    cfg = load_config(None)
    variants = {
        "crowd alone": SurveyInputs(crowd, picture=False),
        "reference": SurveyInputs(crowd, reference_map=ref, picture=False),
        "reference + control points": SurveyInputs(crowd, reference_map=ref, control_points=cp, picture=False),
        "control points": SurveyInputs(crowd, control_points=cp, picture=False),
    }
    for name, inputs in variants.items():
        print(json.dumps({"variant": name, **score(inputs, cfg)}), flush=True)
    # walks without the phones' headings (a foot-mounted module's): the headings switched off stand in
    no_headings = load_config(None, {"heading": {"enabled": False}})
    for name in ("reference", "reference + control points", "control points"):
        print(json.dumps({"variant": f"{name}, no headings", **score(variants[name], no_headings)}), flush=True)
    cli = [sys.executable, "-m", "graphslam", "-q", "survey", *map(str, crowd)]
    walls: dict[str, list[float]] = {"crowd alone": [], "reference": []}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(rounds):
            for name, extra in (("crowd alone", []), ("reference", ["--reference-map", str(ref)])):
                t = time.perf_counter()
                subprocess.run([*cli, "-o", f"{tmp}/{name}-{r}", *extra], check=True, stdout=subprocess.DEVNULL)
                walls[name].append(time.perf_counter() - t)
    med = {k: statistics.median(v) for k, v in walls.items()}
    print(json.dumps({"wall_s_median": {k: round(v, 3) for k, v in med.items()}, "rounds": rounds,
                      "reference_over_alone": round(med["reference"] / med["crowd alone"], 3)}))


if __name__ == "__main__":
    main(Path(sys.argv[1]), int(sys.argv[2]) if len(sys.argv) > 2 else 5)
