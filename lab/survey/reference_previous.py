"""A previous graphslam survey as the reference map, against the floor's professional one: the walks
the floor's ``reference_map.csv`` was made from surveyed with the control points (a site-frame radio
map, as a site would have from an earlier survey), then the other walks (the crowd) placed on that
``radio_map.parquet`` and on the CSV; per variant the main map's walks and landmark mean in the site
frame with no fit, and the walks over 6 m (ground truth only scores).

    python lab/survey/reference_previous.py ../shared/data/ipin2023/b100_f-2
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

from graphslam import SurveyInputs, component_errors, crowd_walks, load_config, run_survey


def score(inputs: SurveyInputs, cfg) -> dict:
    res = run_survey(inputs, cfg)
    al = res.alignment
    comps = component_errors(al, res.survey, site_frame=al.frame == "site")
    c0 = comps[0]
    per_walk: dict[str, float] = {}
    for c in comps:
        per_walk.update(c.site_per_walk_mean_m if c.site_per_walk_mean_m is not None else c.per_walk_mean_m)
    mean = c0.site.mean_m if c0.site is not None else c0.landmarks.mean_m
    field = (res.report.get("reference_map") or {}).get("field")  # a previous survey's magnetic field, if used
    return {"walks": len(res.survey), "main": len(al.components[0].walks), "frame": al.frame,
            "main_mean_m": round(float(mean), 2), "walks_over_6m": int(sum(v > 6.0 for v in per_walk.values())),
            "field": None if field is None else {k: field[k] for k in ("walks", "links", "crowd_walks", "factors")}}


def main(folder: Path) -> None:
    csv_ref, cp = folder / "reference_map.csv", folder / "control_points.csv"
    crowd = crowd_walks(folder, csv_ref)
    own = tuple(sorted(set(folder.glob("*.mcap")) - {Path(p) for p in crowd}))
    cfg = load_config(None)
    with tempfile.TemporaryDirectory() as tmp:
        prev = Path(tmp) / "previous"
        print(json.dumps({"variant": "previous survey (its walks, control points)",
                          **score(SurveyInputs(own, prev, control_points=cp, picture=False), cfg)}), flush=True)
        for name, ref in (("crowd on the previous survey", prev / "radio_map.parquet"), ("crowd on the CSV", csv_ref)):
            print(json.dumps({"variant": name, **score(SurveyInputs(crowd, reference_map=ref, picture=False), cfg)}),
                  flush=True)


if __name__ == "__main__":
    main(Path(sys.argv[1]))
