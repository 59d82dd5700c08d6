"""``graphslam export``: a survey's walks as trajectory files other tools read (one file per walk,
``graphslam.io.trajectory_files``), in the map's frame or the site frame, optionally with each
walk's ground truth beside it, so that ``evo_traj`` / ``evo_ape`` run on our output."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from graphslam.core.common.geometry import se2_apply
from graphslam.core.types import PoseTrack
from graphslam.errors import ConfigError, InputError
from graphslam.io.trajectory_files import SUFFIX, write_trajectory
from graphslam.names import EXPORT_FORMATS, EXPORT_FRAMES


@dataclass(frozen=True)
class ExportRun:
    out: Path
    files: tuple[Path, ...]
    walks: int
    frame: str  # what the coordinates are: "aligned", "earth", "site" or "component_<k>"
    truth_files: int

    def as_dict(self) -> dict[str, object]:
        return {"out": str(self.out), "walks": self.walks, "files": len(self.files), "truth_files": self.truth_files,
                "frame": self.frame}


def file_stem(session_id: str) -> str:
    """A walk's file name: its session id with anything but letters, digits, ``.``, ``_`` and ``-`` as ``_``."""
    return re.sub(r"[^A-Za-z0-9._-]", "_", session_id) or "walk"


def export_survey(
    survey_dir: str | Path, out: str | Path, *, fmt: str = "tum", frame: str = "map", component: int = 0,
    recordings: Sequence[str | Path] = (),
) -> ExportRun:
    """Write every walk of ``component`` of the survey folder ``survey_dir`` into ``out`` as ``fmt``.
    ``frame``: ``map`` (as trajectories.csv: component 0 in report.json's frame, another component in
    its own) or ``site`` (component 0 placed by report.json's landmark fit, or as is when the map is
    in the site frame). ``recordings``: also each walk's ``/ground_truth/pose`` (site frame; with
    ``frame`` map, moved into the map's frame by the same fit) as ``<walk>.truth<suffix>``."""
    import json

    from graphslam.viz.common import fitted_site_from_aligned, survey_folder_trajectories

    if fmt not in EXPORT_FORMATS or frame not in EXPORT_FRAMES:
        raise ConfigError(f"export: format must be one of {', '.join(EXPORT_FORMATS)} and frame one of {', '.join(EXPORT_FRAMES)}")
    d = Path(survey_dir)
    traj = survey_folder_trajectories(d)
    tracks = traj.of_component(component)
    if not tracks:
        raise InputError(d / "trajectories.csv", f"no walk in component {component} (components: "
                         f"{sorted(set(traj.components.values()))})", field="component")
    try:
        report = json.loads((d / "report.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        report = {}
    map_frame = str(report.get("frame") or "aligned") if component == 0 else f"component_{component}"
    fit = fitted_site_from_aligned(report.get("evaluation")) if component == 0 else None
    site_from_map = np.zeros(3) if map_frame == "site" else fit
    if frame == "site" and site_from_map is None:
        raise InputError(d / "report.json", f"no site frame for component {component}: the map is in the {map_frame!r} "
                         "frame and report.json has no landmark fit for it (use --frame map)")
    move = site_from_map if frame == "site" and map_frame != "site" else None
    # the truth is in the site frame: as recorded there, moved into the map's frame by the fit
    in_site = frame == "site" or map_frame == "site"
    if recordings and not in_site and site_from_map is None:
        raise InputError(d / "report.json", f"no landmark fit places the ground truth in the {map_frame!r} frame")
    truths = _truths(recordings, tracks, None if in_site else site_from_map)
    o = Path(out)
    files = []
    for sid, tr in tracks.items():
        if move is not None:
            tr = PoseTrack(tr.t_ns, se2_apply(move, tr.xy), tr.heading + move[2])
        files.append(write_trajectory(tr, o / f"{file_stem(sid)}{SUFFIX[fmt]}", fmt))
    for sid, tr in truths.items():
        files.append(write_trajectory(tr, o / f"{file_stem(sid)}.truth{SUFFIX[fmt]}", fmt))
    return ExportRun(o, tuple(files), len(tracks), "site" if frame == "site" else map_frame, len(truths))


def _truths(
    recordings: Sequence[str | Path], tracks: dict[str, PoseTrack], site_from_map: np.ndarray | None
) -> dict[str, PoseTrack]:
    """The recordings' ground truth of the exported walks, in the exported frame (``site_from_map``:
    the fit placing the map in the site frame, undone; None: the site frame as recorded)."""
    if not recordings:
        return {}
    from graphslam.io.mcap_reader import read_survey
    from graphslam.viz.common import site_to_frame

    survey = read_survey(list(recordings))
    out = {}
    for s in survey:
        g = s.ground_truth
        if g is None or s.session_id not in tracks:
            continue
        if site_from_map is not None:
            g = PoseTrack(g.t_ns, site_to_frame(site_from_map, g.xy), g.heading - site_from_map[2])
        out[s.session_id] = g
    if not out:
        raise InputError(", ".join(map(str, recordings)), "no /ground_truth/pose for any exported walk")
    return out
