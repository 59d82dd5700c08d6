"""Radio maps from a survey: crowdsourced (optimised poses) or surveyed (ground truth, evaluation only),
and the magnetic map beside them."""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy import sparse

from graphslam.config import GraphSlamConfig
from graphslam.core.survey.align import Alignment
from graphslam.core.common.geometry import interpolate_xy, se2_apply
from graphslam.core.survey.factors import edge_state
from graphslam.core.radiomap.fingerprints import FingerprintMatrix
from graphslam.core.radiomap.magnetic_map import MagneticMap
from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.core.radiomap.uncertainty import with_uncertainty
from graphslam.core.types import Survey
from graphslam.errors import SolverError


def _kept_fingerprints(al: Alignment, keep: NDArray[np.bool_]) -> FingerprintMatrix:
    """The ``keep`` rows of the survey's fingerprint matrix (``associate``'s, encoded with the
    config's ``fingerprint`` settings) over the APs those rows heard: what encoding their scans
    again (``FingerprintMatrix.from_scans``) gives, without doing it."""
    m = al.fingerprints.fingerprints
    rows = np.flatnonzero(keep)
    sub = m.values[rows]
    used = np.unique(sub.indices)
    if len(used) < m.n_aps:  # APs only dropped walks heard: out of the index, as from_scans leaves them
        sub = sparse.csr_matrix((sub.data, np.searchsorted(used, sub.indices), sub.indptr), shape=(len(rows), len(used)))
    return FingerprintMatrix(tuple(m.bssids[i] for i in used.tolist()), sub, m.missing_dbm, m.extra_sq[rows], m.extra_n[rows])


def _build(survey: Survey, al: Alignment, xy: NDArray, frame: str, cfg: GraphSlamConfig, meta: dict[str, Any]) -> RadioMap:
    fp = al.fingerprints
    keep = np.isfinite(xy).all(axis=1)
    ids = np.array(al.session_ids, dtype=object)[fp.session]
    return RadioMap.from_fingerprints(
        _kept_fingerprints(al, keep),
        xy[keep],
        session_ids=[str(x) for x in ids[keep]],
        t_ns=fp.t_ns[keep],
        frame=frame,
        floors=[survey.sessions[s].floor for s in fp.session[keep]] if any(s.floor for s in survey) else None,
        metadata={"config": cfg.model_dump(mode="json"), "reference_session": al.reference, **meta},
        min_rssi_dbm=cfg.fingerprint.min_rssi_dbm,
    )


def crowdsourced_radio_map(
    survey: Survey, al: Alignment, cfg: GraphSlamConfig, *, site_from_aligned: NDArray | None = None,
    calibrate: bool = True,
) -> RadioMap:
    """Every fingerprint of an aligned walk at its optimised position, in the survey's frame
    (``Alignment.frame``: the name report.json gives it), or in the site frame when
    ``site_from_aligned`` is given (e.g. from an evaluation fit); with the default kNN's uncertainty
    calibrated on it unless ``calibrate`` is false (``graphslam.core.radiomap.uncertainty.with_calibration``)."""
    xy = al.fingerprint_xy()
    frame = al.frame  # the survey's own (report.json's): aligned, earth or site
    if site_from_aligned is not None:
        xy = se2_apply(np.asarray(site_from_aligned, float), xy)
        frame = "site"
    rm = _build(survey, al, xy, frame, cfg, {"kind": "crowdsourced"})
    if al.reference_map is not None:  # a survey on a reference map: its fingerprints join the crowd's
        rm = with_reference(rm, al.reference_map)
    # the default kNN's uncertainty, measured on the map (leave one walk out), rides along
    return with_uncertainty(rm) if calibrate else rm


def with_reference(crowd: RadioMap, ref: RadioMap) -> RadioMap:
    """The crowd's fingerprints and the reference's in one map (site frame), over the union of their access
    points; every fingerprint counts the same in a kNN answer (the reference's as surveyed, the crowd's at
    their optimised positions). ``metadata.reference``: where it came from and how many rows it gave."""
    from graphslam.core.survey.reference import on_index

    bssids = tuple(sorted(set(crowd.fingerprints.bssids) | set(ref.fingerprints.bssids)))
    a, b = on_index(crowd.fingerprints, bssids), on_index(ref.fingerprints, bssids)
    fm = FingerprintMatrix(bssids, sparse.vstack([a.values, b.values]).tocsr(), a.missing_dbm,
                           np.concatenate([a.extra_sq, b.extra_sq]), np.concatenate([a.extra_n, b.extra_n]))
    labels = None if crowd.floors is None else [*crowd.floors.tolist(), *([""] * len(ref))]
    meta = {**dict(crowd.metadata), "reference": {"source": ref.metadata.get("source"), "fingerprints": len(ref),
                                                  "rss_offset_db": ref.metadata.get("rss_offset_db")}}
    return RadioMap.from_fingerprints(
        fm, np.concatenate([crowd.xy, ref.xy]), session_ids=[*crowd.session_ids.tolist(), *ref.session_ids.tolist()],
        t_ns=np.concatenate([crowd.t_ns, ref.t_ns]), frame=crowd.frame, floors=labels, metadata=meta,
        min_rssi_dbm=crowd.min_rssi_dbm,
    )


def reference_label(source: object) -> str:
    """How outputs name a reference map: its file's name ("reference map" when it has none)."""
    return Path(str(source)).name if source else "reference map"


def held_reference(rm: RadioMap) -> tuple[NDArray[np.float64], str] | None:
    """(site positions, label) of the reference map's rows in a survey's radio map (``with_reference``
    appends them last and counts them in ``metadata.reference``); None when it holds none."""
    held = rm.metadata.get("reference")
    n = int(held.get("fingerprints") or 0) if isinstance(held, dict) else 0
    if not 0 < n <= len(rm):
        return None
    return np.asarray(rm.xy, float)[len(rm) - n:], reference_label(held.get("source"))


def surveyed_radio_map(survey: Survey, al: Alignment, cfg: GraphSlamConfig) -> RadioMap:
    """The same fingerprints at their true positions (``/ground_truth/pose`` at scan time), site frame.

    For evaluation only (the paper's total-station radio map).
    """
    fp = al.fingerprints
    xy = np.full((len(fp), 2), np.nan)
    for s, sess in enumerate(survey):
        rows = np.flatnonzero(fp.session == s)
        if len(rows) and sess.ground_truth is not None:
            xy[rows] = interpolate_xy(sess.ground_truth, fp.t_ns[rows].astype(float))
    if not np.isfinite(xy).any():
        raise SolverError("--surveyed needs /ground_truth/pose in the recordings")
    return _build(survey, al, xy, "site", cfg, {"kind": "surveyed"})


class WifiEdgeRows(NamedTuple):
    """WiFi edges between aligned walks as rows of ``crowdsourced_radio_map`` (same order)."""

    a: NDArray[np.int64]
    b: NDArray[np.int64]
    distance_m: NDArray[np.float64]  # final distance between the two fingerprints (m)
    state: NDArray[np.int8]  # ``graphslam.core.survey.factors.edge_state`` at that distance


def crowdsourced_edges(al: Alignment, cfg: GraphSlamConfig) -> WifiEdgeRows:
    """The WiFi edges whose two fingerprints are both in ``crowdsourced_radio_map(survey, al, cfg)``."""
    xy = al.fingerprint_xy()
    keep = np.isfinite(xy).all(axis=1)
    row = np.cumsum(keep) - 1  # fingerprint -> radio map row (where kept)
    i, j = np.asarray(al.edges.i, np.int64), np.asarray(al.edges.j, np.int64)
    ok = keep[i] & keep[j]
    i, j = i[ok], j[ok]
    d = np.linalg.norm(xy[i] - xy[j], axis=1)
    return WifiEdgeRows(row[i], row[j], d, edge_state(d, cfg.wifi))


def crowdsourced_magnetic_map(survey: Survey, al: Alignment, cfg: GraphSlamConfig) -> MagneticMap | None:
    """The field of the main map's walks at their optimised step positions (``MagneticMap``), each
    walk's offset removed; None when no walk of the main map carries ``/phone/magnetic`` or
    ``magnetic.enabled`` is off.

    Offsets: per feature, least squares over the magnetic links of o_a - o_b = mean over the link's
    pairs of (F_a - F_b), with a small pull of every offset towards 0 (it fixes the common level and
    leaves a walk no link ties at 0)."""
    from graphslam.core.survey.magnetic import step_features

    if not cfg.magnetic.enabled:
        return None
    main = set(al.components[0].walks) if al.components else set()
    feats = step_features(survey)
    offsets = al.fingerprints.offsets
    ids = [s.session_id for s in survey]
    walks = [s for s in range(len(survey)) if ids[s] in main and feats[s] is not None]
    if not walks:
        return None
    node_feat = np.full((int(offsets[-1]), 3), np.nan)
    for s in walks:
        node_feat[offsets[s]:offsets[s + 1]] = feats[s]
    col = {s: k for k, s in enumerate(walks)}
    off = np.zeros((len(walks), 3))
    links = al.magnetic
    if links is not None and len(links):
        rows, diffs = [], []
        pa, pb = links.pair_nodes[:, 0], links.pair_nodes[:, 1]
        d = node_feat[pa] - node_feat[pb]
        ok = np.isfinite(d).all(axis=1)
        for k in range(len(links)):
            a, b = int(links.a[k]), int(links.b[k])
            sel = ok & (links.pair_link == k)
            if a in col and b in col and sel.any():
                rows.append((col[a], col[b]))
                diffs.append(d[sel].mean(axis=0))
        if rows:
            A = np.zeros((len(rows) + len(walks), len(walks)))
            for r, (ca, cb) in enumerate(rows):
                A[r, ca], A[r, cb] = 1.0, -1.0
            A[len(rows):] = 1e-3 * np.eye(len(walks))
            rhs = np.vstack([np.array(diffs), np.zeros((len(walks), 3))])
            off = np.linalg.lstsq(A, rhs, rcond=None)[0]
    parts_id, parts_t, parts_xy, parts_f = [], [], [], []
    for s in walks:
        a, b = int(offsets[s]), int(offsets[s + 1])
        xy = al.node_xyh[a:b, :2]
        ok = np.isfinite(xy).all(axis=1)
        parts_id.append(np.full(int(ok.sum()), ids[s], dtype=object))
        parts_t.append(survey.sessions[s].steps.t_ns[ok])
        parts_xy.append(xy[ok])
        parts_f.append(feats[s][ok] - off[col[s]])
    return MagneticMap(
        np.concatenate(parts_id), np.concatenate(parts_t), np.concatenate(parts_xy), np.concatenate(parts_f),
        frame=al.frame, offsets={ids[s]: tuple(off[col[s]].round(6)) for s in walks},
        metadata={"kind": "crowdsourced", "reference_session": al.reference,
                  "magnetic": cfg.magnetic.model_dump(mode="json")},
    )
