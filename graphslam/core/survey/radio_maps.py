"""Radio maps from a survey: crowdsourced (optimised poses) or surveyed (ground truth, evaluation only)."""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy import sparse

from graphslam.config import GraphSlamConfig
from graphslam.core.survey.align import Alignment
from graphslam.core.common.geometry import interpolate_xy, se2_apply
from graphslam.core.survey.factors import edge_state
from graphslam.core.radiomap.fingerprints import FingerprintMatrix
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
    survey: Survey, al: Alignment, cfg: GraphSlamConfig, *, site_from_aligned: NDArray | None = None
) -> RadioMap:
    """Every fingerprint of an aligned walk at its optimised position, in the survey's frame
    (``Alignment.frame``: the name report.json gives it), or in the site frame when
    ``site_from_aligned`` is given (e.g. from an evaluation fit)."""
    xy = al.fingerprint_xy()
    frame = al.frame
    if site_from_aligned is not None:
        xy = se2_apply(np.asarray(site_from_aligned, float), xy)
        frame = "site"
    # the default kNN's uncertainty, measured on the map (leave one walk out), rides along
    return with_uncertainty(_build(survey, al, xy, frame, cfg, {"kind": "crowdsourced"}))


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
