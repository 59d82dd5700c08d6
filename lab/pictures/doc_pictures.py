"""Regenerate every picture of docs/pictures.md with today's graphslam, by the commands its captions give.

    python -m lab.pictures.doc_pictures                 # all of them (a few minutes on 2 cores; real data: ../shared/data)
    python -m lab.pictures.doc_pictures paper crowd200  # some of them (the groups below)
    python -m lab.pictures.doc_pictures --into /tmp/img # somewhere else than docs/img

Each group runs real `graphslam` commands (this interpreter's) in a temporary folder and copies the
pictures they wrote into docs/img under the names docs/pictures.md shows. A group whose real data
is absent (GRAPHSLAM_DATA, else ../shared/data) is skipped with a message; nothing else is.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Callable

REPO = Path(__file__).resolve().parents[2]
DATA = Path(os.environ.get("GRAPHSLAM_DATA", REPO.parent / "shared" / "data"))


def gs(work: Path, *args: str) -> None:
    """One `graphslam` command in ``work``, echoed; a failure stops the script."""
    print("+ graphslam " + " ".join(args), flush=True)
    subprocess.run([sys.executable, "-m", "graphslam", "-q", *args], cwd=work, check=True, stdout=subprocess.DEVNULL)


def paper(work: Path) -> dict[str, Path]:
    gs(work, "simulate", "paper", "--out", "data/paper", "--seed", "0", "--test-walks", "3")
    gs(work, "survey", "data/paper", "--out", "out/paper")
    print("+ python lab/pictures/sim_floor_plan_png.py data/paper/building.json plan.png", flush=True)
    subprocess.run([sys.executable, str(REPO / "lab" / "pictures" / "sim_floor_plan_png.py"), "data/paper/building.json",
                    "plan.png"], cwd=work, check=True, stdout=subprocess.DEVNULL)
    gs(work, "fit-aps", "--radio-map", "out/paper/radio_map.parquet")
    gs(work, "plot", "out/paper", "--floor-plan", "plan.png", "--floor-size", "120", "60", "--recordings", "data/paper")
    gs(work, "track", "data/paper/test", "--radio-map", "out/paper/radio_map.parquet", "--filter", "ekf", "-o", "out/track.csv")
    gs(work, "locate", "--radio-map", "out/paper/radio_map.parquet", "data/paper/test", "-o", "out/positions.csv")
    return {"survey_paper.png": work / "out/paper/survey.png", "radio_map_paper.png": work / "out/paper/radio_map.png",
            "track_paper.png": work / "out/track.png", "positions_paper.png": work / "out/positions.png"}


def crowd200(work: Path) -> dict[str, Path]:
    gs(work, "simulate", "crowd", "--out", "data/crowd", "--seed", "0", "--size", "4.17")
    gs(work, "survey", "data/crowd", "--out", "out/crowd")
    return {"survey_crowd200.png": work / "out/crowd/survey.png"}


def ipin(work: Path) -> dict[str, Path]:
    floor = DATA / "ipin2023" / "b100_f-2"
    gs(work, "survey", str(floor), "--out", "out/ipin")
    gs(work, "fit-aps", "--radio-map", "out/ipin/radio_map.parquet")
    gs(work, "plot", "out/ipin", "--recordings", str(floor))
    return {"survey_ipin_b100_f-2.png": work / "out/ipin/survey.png",
            "radio_map_ipin_b100_f-2.png": work / "out/ipin/radio_map.png"}


def ipin_accuracy(work: Path) -> dict[str, Path]:
    """radio_map.png's coverage and expected-accuracy panels on the IPIN floor's oracle radio map: the
    walks with >= 2 landmarks, each placed by a rigid fit to its own landmarks (truth places the map,
    for the picture only; the accuracy itself is measured without it)."""
    import graphslam
    from graphslam import draw_radio_map, with_uncertainty

    floor = DATA / "ipin2023" / "b100_f-2"
    print(f"+ python: draw_radio_map(with_uncertainty(oracle_radio_map(walks of {floor} with >= 2 landmarks)), "
          "top=0, size_px=(1400, 600))", flush=True)
    walks = [w for w in graphslam.read_survey([floor]) if len(w.landmarks) >= 2]
    rm = with_uncertainty(graphslam.oracle_radio_map(walks))
    draw_radio_map(rm, work / "accuracy.png", top=0, size_px=(1400, 600))
    return {"accuracy_ipin_b100_f-2.png": work / "accuracy.png"}


def ilc_f1(work: Path) -> dict[str, Path]:
    floor = DATA / "ilc20" / "site1" / "F1"
    gs(work, "survey", str(floor), "--out", "out/ilc_f1", "--floor-plan", str(floor / "floor_image.png"))
    gs(work, "fit-aps", "--radio-map", "out/ilc_f1/radio_map.parquet")
    gs(work, "plot", "out/ilc_f1", "--floor-plan", str(floor / "floor_image.png"), "--recordings", str(floor))
    return {"survey_ilc_f1.png": work / "out/ilc_f1/survey.png", "radio_map_ilc_f1.png": work / "out/ilc_f1/radio_map.png"}


# group -> (the real data it needs, or None; what it writes)
GROUPS: dict[str, tuple[Path | None, Callable[[Path], dict[str, Path]]]] = {
    "paper": (None, paper),
    "crowd200": (None, crowd200),
    "ipin": (DATA / "ipin2023" / "b100_f-2", ipin),
    "ipin_accuracy": (DATA / "ipin2023" / "b100_f-2", ipin_accuracy),
    "ilc_f1": (DATA / "ilc20" / "site1" / "F1", ilc_f1),
}
# what each group writes into docs/img (docs/pictures.md shows exactly these; lab/pictures/tests check it)
PICTURES = {
    "paper": ("survey_paper.png", "radio_map_paper.png", "track_paper.png", "positions_paper.png"),
    "crowd200": ("survey_crowd200.png",),
    "ipin": ("survey_ipin_b100_f-2.png", "radio_map_ipin_b100_f-2.png"),
    "ipin_accuracy": ("accuracy_ipin_b100_f-2.png",),
    "ilc_f1": ("survey_ilc_f1.png", "radio_map_ilc_f1.png"),
}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("groups", nargs="*", help=f"groups to redraw: {', '.join(GROUPS)} (default: all)")
    ap.add_argument("--into", type=Path, default=REPO / "docs" / "img", help="where the pictures go (default: docs/img)")
    args = ap.parse_args(argv)
    unknown = [g for g in args.groups if g not in GROUPS]
    if unknown:
        ap.error(f"unknown group {unknown[0]!r}; groups: {', '.join(GROUPS)}")
    for name in args.groups or list(GROUPS):
        needs, run = GROUPS[name]
        if needs is not None and not needs.exists():
            print(f"skipped {name}: needs the real data in {needs}", flush=True)
            continue
        with tempfile.TemporaryDirectory(prefix=f"doc-pictures-{name}-") as tmp:
            written = run(Path(tmp))
            assert set(written) == set(PICTURES[name]), (name, sorted(written))
            args.into.mkdir(parents=True, exist_ok=True)
            for target, source in written.items():
                shutil.copyfile(source, args.into / target)
                print(f"wrote {args.into / target}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
