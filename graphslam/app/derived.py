"""Who owns which file of a survey's folder, and what ``graphslam survey`` does with the files
other commands added there when it replaces the folder.

A survey folder is one consistent set: ``survey`` writes its outputs (``app.survey.OUTPUT_FILES``
and survey.png) and replaces the folder as a whole. Two other commands write into it by default,
and their files are declared parts of the set (``DERIVED_FILES``): ``fit-aps`` (ap_models.json,
beside the map it was fitted to) and ``plot`` (radio_map.png, magnetic_map.png). When the folder being replaced
holds them, the new set gets them rebuilt from the new map (the AP models refitted with the
settings recorded in them, the picture redrawn with the options recorded in it), so that they
never describe an earlier map; one that cannot be rebuilt is kept as it was, with a warning.
``KEPT_FILES`` (written by an earlier graphslam, read by nothing now) are carried over
unchanged. Nothing in the folder is deleted that ``survey`` did not write, and nothing another
command wrote there blocks an update. report.json's ``derived_files`` says what happened to each.
``track`` writes nothing there (its self-calibration lives in a cache folder, ``app.track``).
"""

from __future__ import annotations

import logging
import shutil
from pathlib import Path
from typing import Any, Callable

from graphslam.errors import GraphSlamError

log = logging.getLogger(__name__)

# file -> the command that writes it into a survey's folder (rebuilt by `survey`)
DERIVED_FILES = {"ap_models.json": "fit-aps", "radio_map.png": "plot", "magnetic_map.png": "plot"}
# file -> who wrote it (carried over unchanged)
KEPT_FILES = {"track_calibration.json": "track (graphslam before 2026-12-03; now in the cache folder)"}


def rebuild_derived(previous: Path, new: Path) -> dict[str, dict[str, Any]]:
    """For each derived or kept file in ``previous`` (the folder ``new`` will replace; absent: none),
    its counterpart in ``new`` (a complete survey set): rebuilt, or kept as it was. Returns
    report.json's ``derived_files``: file -> {written_by, status, reason?}."""
    if not previous.is_dir():
        return {}
    rebuild: dict[str, Callable[[Path, Path], None]] = {
        "ap_models.json": _refit_ap_models, "radio_map.png": _redraw, "magnetic_map.png": _redraw_magnetic,
    }
    out: dict[str, dict[str, Any]] = {}
    for name, by in DERIVED_FILES.items():
        old = previous / name
        if not old.is_file():
            continue
        try:
            rebuild[name](old, new / name)
            out[name] = {"written_by": by, "status": "rebuilt"}
        except (GraphSlamError, OSError, ValueError) as e:
            shutil.copy2(old, new / name)
            reason = " ".join(str(e).split())
            log.warning("%s: not rebuilt for the new map (%s); kept as it was", name, reason)
            out[name] = {"written_by": by, "status": "kept", "reason": f"not rebuilt: {reason}"}
    for name, by in KEPT_FILES.items():
        if (previous / name).is_file():
            shutil.copy2(previous / name, new / name)
            out[name] = {"written_by": by, "status": "kept"}
    return out


def _refit_ap_models(old: Path, target: Path) -> None:
    """``fit-aps`` again on the new radio map beside ``target``, with the settings ``old`` records."""
    from graphslam.core.tracking.apmodel import ApModels
    from graphslam.io.apmodel_io import read_fit_config, write_ap_models
    from graphslam.io.radiomap_io import read_radio_map

    rm = read_radio_map(target.with_name("radio_map.parquet"))
    cfg = read_fit_config(old)
    write_ap_models(ApModels.fit(rm, cfg), target, radio_map=rm, fit=cfg)


def _redraw_magnetic(old: Path, target: Path) -> None:
    """``plot``'s magnetic_map.png again from the new set (absent when the new map has no field)."""
    from graphslam.app.pictures import plot_options, redraw_magnetic_map
    from graphslam.errors import InputError

    if not target.with_name("magnetic_map.parquet").is_file():
        raise InputError(target.with_name("magnetic_map.parquet"), "the new survey has no magnetic map")
    redraw_magnetic_map(target.parent, plot_options(old) or {})


def _redraw(old: Path, target: Path) -> None:
    """``plot``'s radio_map.png again, from the new set, with the options ``old`` records."""
    from graphslam.app.pictures import plot_options, redraw_radio_map

    redraw_radio_map(target.parent, plot_options(old) or {})
