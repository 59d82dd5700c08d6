"""Shared loading for the headings / components / control-point experiments: heading-rotated walks, fingerprints, truth (scoring only)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import graphslam as gs
from graphslam import associate
from graphslam import interpolate_xy
from graphslam import se2_apply


def heading_offset(s) -> float:
    """Circular mean of phone yaw - dead-reckoned heading over the walk's steps."""
    t = s.steps.t_ns
    idx = np.clip(np.searchsorted(t, s.heading.t_ns), 0, len(t) - 1)
    d = s.heading.yaw - s.steps.heading[idx]
    return float(np.angle(np.exp(1j * d).mean()))


@dataclass
class Floor:
    survey: object
    fp: object
    psi: np.ndarray  # (S,) rotation DR -> Earth
    xy: np.ndarray  # (F, 2) fingerprint positions, walk rotated by psi, walk origin at 0
    sess: np.ndarray  # (F,)
    tau_true: np.ndarray  # (S, 2) truth translation of each rotated walk (NaN: no landmarks); scoring only
    phi0: float  # common offset site - earth (scoring only)


def load(folder: str) -> Floor:
    sv = gs.read_survey([folder])
    fp = associate(sv, max_gap_s=1.5, missing_dbm=-110.0, min_rssi_dbm=-100.0, standstill_max_s=120.0)
    S = len(sv.sessions)
    psi = np.array([heading_offset(s) if s.heading is not None else 0.0 for s in sv])
    dr = np.concatenate([s.steps.xy for s in sv])
    nodes_xy = dr[fp.node]
    xy = np.zeros_like(nodes_xy)
    for k in range(S):
        m = fp.session == k
        xy[m] = se2_apply(np.array([0, 0, psi[k]]), nodes_xy[m])
    # truth: common rotation then translation per walk (landmarks; scoring only)
    est, true, own = [], [], []
    for k, s in enumerate(sv):
        if not s.landmarks:
            continue
        tt = np.array([m.t_ns for m in s.landmarks], float)
        p = se2_apply(np.array([0, 0, psi[k]]), interpolate_xy(s.steps, tt))
        est.append(p); true.append(np.array([[m.x, m.y] for m in s.landmarks])); own += [k] * len(tt)
    est, true, own = np.concatenate(est), np.concatenate(true), np.array(own)
    # phi0 by grid: translation per walk free
    best = None
    for phi in np.radians(np.arange(-180, 180, 0.5)):
        R = np.array([[np.cos(phi), -np.sin(phi)], [np.sin(phi), np.cos(phi)]])
        q = est @ R.T
        r = 0.0
        for k in np.unique(own):
            m = own == k
            r += ((q[m] - q[m].mean(0) - (true[m] - true[m].mean(0))) ** 2).sum()
        if best is None or r < best[0]:
            best = (r, phi)
    phi0 = best[1]
    R = np.array([[np.cos(phi0), -np.sin(phi0)], [np.sin(phi0), np.cos(phi0)]])
    tau = np.full((S, 2), np.nan)
    for k in np.unique(own):
        m = own == k
        # tau in the Earth frame: site = R (p + tau)  ->  tau = R^T site - p
        tau[k] = (true[m] @ R - est[m]).mean(0)
    return Floor(sv, fp, psi, xy, fp.session.copy(), tau, phi0)


def true_xy(fl: Floor) -> np.ndarray:
    """Fingerprint positions in the Earth frame with each walk at its truth translation (scoring only)."""
    return fl.xy + fl.tau_true[fl.sess]
