"""How sparse a surveyed reference can be: the floor's ``reference_map.csv`` thinned (every 2nd and 4th
fingerprint in file order; at least 2, 4 and 8 m apart, chosen greedily in file order, as a professional
survey's grid would be), the crowd walks (those the reference was not made from; or, in a folder
``lab/survey/reference_scale.py --out`` wrote, its ``crowd/``) surveyed on each, scored in the site frame
with no fit (ground truth only scores): the main map's walks, their landmark mean, those over 6 m (and
the other components' walks over 6 m after each component's own fit), the
reference's ``spacing_m`` and the site frame's rotation from east/north the crowd's matches gave.

    python lab/survey/reference_density.py ../shared/data/ipin2023/b100_f-2
    python lab/survey/reference_scale.py --scenario paper --size 4 --rounds 1 --out /tmp/rs4 && \
        python lab/survey/reference_density.py /tmp/rs4
"""

from __future__ import annotations

import csv
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from graphslam import SurveyInputs, component_errors, crowd_walks, load_config, run_survey


def _spaced(ids: list[str], pos: dict[str, tuple[float, float]], min_m: float) -> set[str]:
    kept: list[str] = []
    for i in ids:
        if all(np.hypot(pos[i][0] - pos[k][0], pos[i][1] - pos[k][1]) >= min_m for k in kept):
            kept.append(i)
    return set(kept)


def main(folder: Path) -> None:
    src = folder / "reference_map.csv"
    with open(src, newline="", encoding="utf-8-sig") as fh:
        rows = list(csv.DictReader(fh))
    ids = list(dict.fromkeys(r["fingerprint_id"] for r in rows))
    pos = {r["fingerprint_id"]: (float(r["x"]), float(r["y"])) for r in rows}
    variants = {"all": set(ids), "every 2nd": set(ids[::2]), "every 4th": set(ids[::4]),
                "at least 2 m apart": _spaced(ids, pos, 2.0), "at least 4 m apart": _spaced(ids, pos, 4.0),
                "at least 8 m apart": _spaced(ids, pos, 8.0)}
    crowd = tuple(sorted((folder / "crowd").glob("*.mcap"))) if (folder / "crowd").is_dir() else crowd_walks(folder, src)
    cfg = load_config(None)
    with tempfile.TemporaryDirectory() as tmp:
        for name, keep in variants.items():
            ref = Path(tmp) / f"{len(keep)}.csv"
            with open(ref, "w", newline="") as fh:
                w = csv.DictWriter(fh, fieldnames=list(rows[0]))
                w.writeheader()
                w.writerows(r for r in rows if r["fingerprint_id"] in keep)
            res = run_survey(SurveyInputs(crowd, reference_map=ref, picture=False), cfg)
            al = res.alignment
            comps = component_errors(al, res.survey, site_frame=al.frame == "site")
            # the main map's walks in the site frame, no fit (the "more than 6 m off"); the other
            # components' walks after each component's own fit (a component wrong inside itself)
            c0 = comps[0]
            main_walks = c0.site_per_walk_mean_m if c0.site_per_walk_mean_m is not None else c0.per_walk_mean_m
            others = [v for c in comps[1:] for v in c.per_walk_mean_m.values()]
            mean = c0.site.mean_m if c0.site is not None else c0.landmarks.mean_m
            print(json.dumps({"reference": name, "fingerprints": len(keep),
                              "spacing_m": (res.report.get("reference_map") or {}).get("spacing_m"),
                              "walks": len(res.survey),
                              "main": len(al.components[0].walks), "frame": al.frame,
                              "main_mean_m": round(float(mean), 2),
                              "main_over_6m": int(sum(v > 6.0 for v in main_walks.values())),
                              "others_over_6m": int(sum(v > 6.0 for v in others)),
                              "site_from_earth_deg": res.report.get("site_from_earth_deg")}), flush=True)


if __name__ == "__main__":
    main(Path(sys.argv[1]))
