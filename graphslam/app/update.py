"""``graphslam survey --update PREVIOUS_OUT``: join new walks to a floor solved before.

``align_update`` decides between the incremental path (walks solved before start from their
previous solution, only their neighbourhood of the new walks is re-solved:
``graphslam.core.survey.incremental``) and a full re-solve, and says which and why in the
report's ``update`` section. A previous output that does not match — other configuration, a
walk changed or missing — is never mixed in: the floor is solved again from scratch.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping

import numpy as np

from graphslam.config import REMOVED_OPTIMIZER_KEYS, GraphSlamConfig

if TYPE_CHECKING:
    from graphslam.core.radiomap.magnetic_map import MagneticMap
    from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.core.survey.align import Alignment, ProgressCallback, align, build_problem, initialization, solve
from graphslam.core.survey.incremental import (
    control_points_digest,
    PreviousSolution,
    changed_edges,
    previous_graph_pairs,
    session_digest,
    warm_start,
)
from graphslam.core.types import Survey
from graphslam.errors import InputError
from graphslam.io.survey_state import STATE_FILE, read_survey_state

log = logging.getLogger(__name__)

# Config sections and settings that do not change the solution a previous output holds.
_NOT_COMPARED = ("update",)
# summation order only; and MKL PARDISO's keys, which a previous state may carry (its solution is CHOLMOD's to rounding)
_NOT_COMPARED_KEYS = {("optimizer", "blas_threads")} | {("optimizer", k) for k in REMOVED_OPTIMIZER_KEYS}


def load_previous(previous_dir: str | Path) -> PreviousSolution:
    """The state of a previous survey output folder (an ``InputError`` if it is not one)."""
    d = Path(previous_dir)
    if not d.is_dir():
        raise InputError(d, "--update: not a folder (expected a previous `graphslam survey --out` folder)")
    return read_survey_state(d / STATE_FILE)


def mismatch(
    previous: PreviousSolution, survey: Survey, cfg: GraphSlamConfig,
    control_points: Mapping[str, tuple[float, float]] | None = None,
) -> str | None:
    """Why ``previous`` cannot seed this survey (None: it can)."""
    diff = _config_diff(json.loads(previous.config_json), cfg)
    if diff:
        return "configuration differs from the previous run's: " + "; ".join(diff[:3]) + (
            f" (+{len(diff) - 3} more)" if len(diff) > 3 else "")
    current = {s.session_id: s for s in survey}
    if previous.format_version < 3 and any(
        s.heading is not None or s.landmarks or s.uwb_id or s.uwb_anchors or s.uwb_ranges is not None
        for s in (current.get(sid) for sid in previous.session_ids) if s is not None
    ):
        return (f"the previous survey state (format {previous.format_version}) does not record its walks' headings, "
                "landmark marks or UWB rangings, which this survey's walks carry")
    for sid, digest in zip(previous.session_ids, previous.digests):
        if sid not in current:
            return f"walk {sid!r} of the previous survey is not among the recordings"
        if session_digest(current[sid]) != digest:
            return f"walk {sid!r} changed since the previous survey (its steps, scans, headings, marks or UWB differ)"
    if previous.registration_reliable is False and cfg.optimizer.unreliable_registration == "unalign":
        return "the previous survey's registration was unreliable: which walks it aligns depends on all of them"
    if control_points_digest(control_points) != previous.control_digest:
        return "the control points differ from the previous run's"
    if previous.frame == "site" and not control_points and not any(s.uwb_anchors for s in survey):
        # a site frame without control points or UWB anchors: a reference map placed it, and the state holds
        # neither the reference nor its rotation from east/north; new walks would be placed without them
        # (given again, the floor is solved in full on it: align_update)
        return "the previous survey was placed on a reference map, which this run does not give (--reference-map)"
    if initialization(cfg, survey) == "heading":
        if previous.component is None:
            return "the previous survey state holds no components (written by an older version)"
        if previous.frame == "aligned":
            return "the previous survey was solved without the phones' headings"
    return None


def _config_diff(prev: dict[str, Any], cfg: GraphSlamConfig) -> list[str]:
    cur = cfg.model_dump(mode="json")
    out = []
    for section in sorted(set(prev) | set(cur)):
        if section in _NOT_COMPARED:
            continue
        a, b = prev.get(section, {}), cur.get(section, {})
        for key in sorted(set(a) | set(b)):
            if (section, key) in _NOT_COMPARED_KEYS:
                continue
            if section == "optimizer" and key == "reference_session" and b.get(key) is None:
                continue  # not set now: the previous reference walk is kept (same frame)
            was = "cholmod" if (section, key, a.get(key)) == ("optimizer", "solver", "pardiso") else a.get(key)
            if was != b.get(key):
                out.append(f"{section}.{key} {a.get(key)!r} -> {b.get(key)!r}")
    return out


def align_update(
    survey: Survey,
    cfg: GraphSlamConfig,
    previous: PreviousSolution,
    *,
    previous_dir: str | Path,
    progress: ProgressCallback | None = None,
    control_points: Mapping[str, tuple[float, float]] | None = None,
    reference: RadioMap | None = None,
    reference_field: MagneticMap | None = None,
) -> tuple[Alignment, GraphSlamConfig, dict[str, Any]]:
    """(alignment, effective config, the report's ``update`` section); ``control_points`` (landmark
    id -> site x, y) are passed on to the solver either way; with a ``reference`` map (and its
    ``reference_field``) the floor is solved in full (the reference places every walk: a new walk's
    placement can move old ones)."""
    prev_ids = set(previous.session_ids)
    prev_aligned = {sid for sid, ok in zip(previous.session_ids, previous.aligned.tolist()) if ok}
    info: dict[str, Any] = {
        "previous": str(previous_dir),
        "new_walks": [s.session_id for s in survey if s.session_id not in prev_ids],
        "placed_again": [s.session_id for s in survey if s.session_id in prev_ids - prev_aligned],
    }
    reason = mismatch(previous, survey, cfg, control_points)
    if reference is not None:
        reason = "a survey on a reference map is solved in full (the reference places every walk)"
    if reason is not None:
        log.warning("--update: full re-solve: %s", reason)
        al = align(survey, cfg, progress=progress, control_points=control_points, reference=reference,
                   reference_field=reference_field)
        info.update(mode="full", reason=reason, resolved={"nodes": al.n_nodes, "of_nodes": al.n_nodes})
        return al, cfg, info
    # the previous reference walk stays the reference: the solution keeps its frame
    eff = cfg.model_copy(
        update={"optimizer": cfg.optimizer.model_copy(update={"reference_session": previous.reference})}
    )
    t0 = time.perf_counter()
    warm = warm_start(previous, survey, cfg.update.hops)
    problem = build_problem(survey, eff, warm, control_points=control_points)
    al = solve(problem, eff, progress, t0=t0)
    free = problem.free if problem.free is not None else np.zeros(al.n_nodes, bool)
    walk_of = np.repeat(np.arange(len(survey)), np.diff(problem.fingerprints.offsets))
    ids = [s.session_id for s in survey]
    prev_pairs = previous_graph_pairs(problem.fingerprints, warm)
    added, removed = changed_edges(problem.wifi_pairs, prev_pairs, warm.solved)
    info.update(
        mode="incremental",
        reason=None,
        resolved={
            "hops": cfg.update.hops,
            "nodes": int(free.sum()),
            "of_nodes": al.n_nodes,
            "walks": sorted({ids[s] for s in np.unique(walk_of[free]).tolist()}),
            "edges_added": len(added),
            "edges_removed": len(removed),
        },
    )
    log.info("--update: %d new walks, re-solved %d of %d poses", len(info["new_walks"]), free.sum(), al.n_nodes)
    return al, eff, info
