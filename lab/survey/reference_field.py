"""A previous survey's magnetic field as part of the reference: the crowd placed on a previous graphslam
survey's ``radio_map.parquet`` with its ``magnetic_map.parquet`` beside it (the field ties the placed
walks) and without (the radio map alone, copied apart); per variant the main map's walks, their landmark
mean in the site frame with no fit, the walks over 6 m and the field's links and factors (ground truth
only scores).

The previous survey: on a real floor, the walks its ``reference_map.csv`` was made from, surveyed with
its control points; on the simulator (``--scenario``), every ``--every``-th walk surveyed on the CSV of
its own scans at their true places (truth builds that reference only, as ``reference_scale.py``'s).

    python lab/survey/reference_field.py ../shared/data/ipin2023/b100_f-2
    python lab/survey/reference_field.py --scenario museum --seed 0
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path

from graphslam import SurveyInputs, crowd_walks, load_config, simulate, write_session

from lab.survey.reference_previous import score
from lab.survey.reference_scale import reference_csv


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folder", nargs="?", type=Path, help="a real floor: reference_map.csv and control_points.csv")
    ap.add_argument("--scenario", help="the simulator instead (museum: IPIN-like, with the field)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--size", type=float, default=1.0)
    ap.add_argument("--every", type=int, default=5)
    a = ap.parse_args()
    cfg = load_config(None)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        prev = root / "previous"
        if a.scenario:
            sessions = list(simulate(a.scenario, seed=a.seed, size=a.size).survey)
            (root / "own").mkdir()
            (root / "crowd").mkdir()
            own = [write_session(s, root / "own" / f"{s.session_id}.mcap") for s in sessions[:: a.every]]
            crowd = tuple(write_session(s, root / "crowd" / f"{s.session_id}.mcap")
                          for k, s in enumerate(sessions) if k % a.every)
            reference_csv(root / "reference_map.csv", sessions[:: a.every])
            previous = SurveyInputs(tuple(own), prev, reference_map=root / "reference_map.csv", picture=False)
        else:
            csv_ref = a.folder / "reference_map.csv"
            crowd = crowd_walks(a.folder, csv_ref)
            own = sorted(set(a.folder.glob("*.mcap")) - {Path(p) for p in crowd})
            previous = SurveyInputs(tuple(own), prev, control_points=a.folder / "control_points.csv", picture=False)
        print(json.dumps({"variant": "previous survey", **score(previous, cfg)}), flush=True)
        alone = root / "radio_map_alone"
        alone.mkdir()
        shutil.copy(prev / "radio_map.parquet", alone / "radio_map.parquet")
        for name, ref in (("with its field", prev / "radio_map.parquet"), ("radio map alone", alone / "radio_map.parquet")):
            print(json.dumps({"variant": f"crowd on it, {name}",
                              **score(SurveyInputs(tuple(crowd), reference_map=ref, picture=False), cfg)}), flush=True)


if __name__ == "__main__":
    main()
