"""``survey_state.npz``: what a survey output keeps for a later ``graphslam survey --update``.

A NumPy ``.npz`` archive (no pickles), format version 4. Older states are still read: version 1,
without the last four arrays, has no components (a survey with headings re-solves in full);
versions 1 and 2 digested each walk's id, steps and scans only (an update whose walks carry
headings, landmark marks or UWB re-solves in full, once); before 4 there are no magnetic links (an
update keeps none between the walks solved before):

==================  ===========  ==================================================
array               dtype        meaning
==================  ===========  ==================================================
format_version      int64 ()     3
session_ids         str (S,)     every walk of the survey, in survey order
digests             str (S,)     SHA-256 of each walk's solver inputs (``incremental.session_digest``)
aligned             bool (S,)    walk was aligned
offsets             int64 (S+1)  step ranges of each walk into ``xyh``
xyh                 float64 (N,3) solution of every step: x, y (m), heading (rad), aligned frame; NaN if unaligned
edge_session        int64 (E,2)  the WiFi edges' walks (indices into ``session_ids``)
edge_scan           int64 (E,2)  ... and scans (index into the walk's ``/wifi/scan`` messages)
candidates          int64 ()     pairs below threshold before the per-fingerprint cap
reference           str ()       the reference walk (its first pose is the frame's origin)
config_json         str ()       the effective configuration, JSON
registration_reliable int64 ()   1 / 0, or -1 when the loop check had too few loops to judge
component           int64 (S,)   each walk's component (0: the main map), -1 if unaligned
frame               str ()       component 0's frame: aligned, earth or site
control_digest      str ()       SHA-256 of the control points used ("" none)
edge_used           bool (E,)    the edge entered the optimiser (its walks' component, the placement's gate)
mag_walks           int64 (K,2)  the magnetic links' walks (indices into ``session_ids``)
mag_link            int64 (P,)   each magnetic pair's link
mag_step            int64 (P,2)  each magnetic pair's steps (index into each walk's steps)
==================  ===========  ==================================================
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from graphslam.config import GraphSlamConfig
from graphslam.core.survey.align import Alignment
from graphslam.core.survey.incremental import PreviousSolution, session_digest
from graphslam.core.types import Survey
from graphslam.errors import InputError
from graphslam.io.atomic import atomic_open

STATE_FILE = "survey_state.npz"
STATE_FORMAT_VERSION = 4
READABLE_VERSIONS = (1, 2, 3, 4)


def write_survey_state(path: str | Path, survey: Survey, al: Alignment, cfg: GraphSlamConfig) -> Path:
    path = Path(path)
    fp = al.fingerprints
    reliable = None if al.placement is None else al.placement.reliable
    comp = al.component_of()
    arrays = {
        "format_version": np.int64(STATE_FORMAT_VERSION),
        "session_ids": np.array([s.session_id for s in survey], dtype=str),
        "digests": np.array([session_digest(s) for s in survey], dtype=str),
        "aligned": np.array([s.session_id in al.tracks for s in survey], bool),
        "offsets": np.asarray(fp.offsets, np.int64),
        "xyh": np.asarray(al.node_xyh, np.float64),
        "edge_session": np.column_stack([fp.session[al.edges.i], fp.session[al.edges.j]]).astype(np.int64),
        "edge_scan": np.column_stack([fp.scan[al.edges.i], fp.scan[al.edges.j]]).astype(np.int64),
        "candidates": np.int64(al.edges.candidates),
        "reference": np.array(al.reference),
        "config_json": np.array(cfg.model_dump_json()),
        "registration_reliable": np.int64(-1 if reliable is None else int(reliable)),
        "component": np.array([comp.get(s.session_id, -1) for s in survey], np.int64),
        "frame": np.array(al.frame),
        "control_digest": np.array(al.control_digest),
        "edge_used": np.ones(len(al.edges.i), bool) if al.used_edges is None else np.asarray(al.used_edges, bool),
        **_magnetic_arrays(al),
    }
    with atomic_open(path, "wb") as fh:
        np.savez(fh, **arrays)
    return path


def _magnetic_arrays(al: Alignment) -> dict[str, np.ndarray]:
    """The magnetic links the solution used, by walk and step (none: empty arrays)."""
    links = al.magnetic
    if links is None or not len(links):
        return {"mag_walks": np.zeros((0, 2), np.int64), "mag_link": np.zeros(0, np.int64),
                "mag_step": np.zeros((0, 2), np.int64)}
    offsets = al.fingerprints.offsets
    walk = np.searchsorted(offsets, links.pair_nodes, side="right") - 1
    return {"mag_walks": np.column_stack([links.a, links.b]).astype(np.int64),
            "mag_link": links.pair_link.astype(np.int64),
            "mag_step": (links.pair_nodes - offsets[walk]).astype(np.int64)}


def read_survey_state(path: str | Path) -> PreviousSolution:
    """Read and check a state file; every problem is an ``InputError`` naming the file and array."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no survey state: not the output folder of a `graphslam survey` run (or one from before "
                         "--update existed; re-run the survey once)")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as e:
        raise InputError(path, f"unreadable survey state ({type(e).__name__}: {e})") from None
    need = ("format_version", "session_ids", "digests", "aligned", "offsets", "xyh", "edge_session", "edge_scan",
            "candidates", "reference", "config_json", "registration_reliable")
    for k in need:
        if k not in data:
            raise InputError(path, "missing array", field=k)
    version = int(data["format_version"])
    if version not in READABLE_VERSIONS:
        raise InputError(path, f"format version {version}, expected one of {READABLE_VERSIONS}", field="format_version")
    if version >= 2:
        for k in ("component", "frame", "control_digest", "edge_used"):
            if k not in data:
                raise InputError(path, "missing array", field=k)
    ids = tuple(str(x) for x in data["session_ids"].reshape(-1))
    n_s = len(ids)
    offsets = data["offsets"].astype(np.int64).reshape(-1)
    xyh = data["xyh"].astype(np.float64)
    checks = [
        ("digests", data["digests"].shape == (n_s,)),
        ("aligned", data["aligned"].shape == (n_s,)),
        ("offsets", offsets.shape == (n_s + 1,) and offsets[0] == 0 and bool(np.all(np.diff(offsets) >= 0))),
        ("xyh", xyh.ndim == 2 and xyh.shape[1:] == (3,) and len(offsets) > 0 and xyh.shape[0] == offsets[-1]),
        ("edge_session", data["edge_session"].ndim == 2 and data["edge_session"].shape[1:] == (2,)),
        ("edge_scan", data["edge_scan"].shape == data["edge_session"].shape),
    ]
    for name, ok in checks:
        if not ok:
            raise InputError(path, "array has the wrong shape or values", field=name)
    es = data["edge_session"].astype(np.int64)
    if len(es) and (es.min() < 0 or es.max() >= n_s or data["edge_scan"].min() < 0):
        raise InputError(path, "edge index out of range", field="edge_session")
    aligned = data["aligned"].astype(bool)
    for s in np.flatnonzero(aligned):
        if not np.isfinite(xyh[offsets[s] : offsets[s + 1]]).all():
            raise InputError(path, f"walk {ids[s]!r} is marked aligned but has non-finite poses", field="xyh")
    reference = str(data["reference"])
    if reference not in ids:
        raise InputError(path, f"reference walk {reference!r} is not one of its walks", field="reference")
    rel = int(data["registration_reliable"])
    component = None
    if version >= 2:
        component = data["component"].astype(np.int64).reshape(-1)
        if component.shape != (n_s,) or bool(np.any(component[aligned] < 0)):
            raise InputError(path, "array has the wrong shape or values", field="component")
        if data["edge_used"].shape != (len(es),):
            raise InputError(path, "array has the wrong shape or values", field="edge_used")
    mag = None
    if version >= 4:
        for k in ("mag_walks", "mag_link", "mag_step"):
            if k not in data:
                raise InputError(path, "missing array", field=k)
        mw, ml, ms = (data[k].astype(np.int64) for k in ("mag_walks", "mag_link", "mag_step"))
        ok = (mw.ndim == 2 and mw.shape[1:] == (2,) and ms.shape == (len(ml), 2) and (not len(mw) or
              (mw.min() >= 0 and mw.max() < n_s)) and (not len(ml) or (ml.min() >= 0 and ml.max() < len(mw))))
        if ok and len(ml):
            steps = np.diff(offsets)[mw[ml]]
            ok = bool((ms >= 0).all() and (ms < steps).all())
        if not ok:
            raise InputError(path, "array has the wrong shape or values", field="mag_step")
        mag = (mw, ml, ms)
    return PreviousSolution(
        session_ids=ids,
        digests=tuple(str(x) for x in data["digests"]),
        aligned=aligned,
        offsets=offsets,
        xyh=xyh,
        edge_session=es,
        edge_scan=data["edge_scan"].astype(np.int64),
        candidates=int(data["candidates"]),
        reference=reference,
        config_json=str(data["config_json"]),
        registration_reliable=None if rel < 0 else bool(rel),
        component=component,
        frame=str(data["frame"]) if version >= 2 else "aligned",
        control_digest=str(data["control_digest"]) if version >= 2 else "",
        edge_used=data["edge_used"].astype(bool) if version >= 2 else None,
        format_version=version,
        magnetic=mag,
    )
