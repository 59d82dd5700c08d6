"""Map-matching particle filter: steps of the foot module moved on the radio map, every scan
weighed by its fingerprint matches as a multimodal likelihood, reported with a fixed lag.

Why besides the Gaussian trackers: a kNN fix is unimodal; when a scan's best matches lie in two
places (a repeated corridor, a hall heard from both ends) its mean lies between them and a
Gaussian tracker has to choose one. Here a scan's likelihood at a position ``x`` is the mixture
over its ``top_k`` nearest map fingerprints ``j`` (distances ``D_j``: eq. 9 dB or Sørensen, unitless):

    p(x) = (1 - eps) sum_j w_j N(x; m_j, h^2 I) + eps / A,   w_j ~ exp(-(D_j - D_1) / T)

with ``m_j`` the fingerprint's map position, ``h`` the kernel width (m), ``T`` the match
temperature (the distance's units) and a uniform share ``eps`` over the map's area ``A``; the walker's steps move
every particle, so only the modes that the walk's geometry connects survive.

State per particle: position (m, map frame), the rotation ``phi`` (rad) from the foot module's
own frame to the map frame, and a step-length scale. A step interval moves a particle by
``scale R(phi) d`` (``d``: the module's displacement, its frame) plus noise. Scans between two
steps are weighed at the position interpolated in time. Output at each step: the weighted mean
and covariance of the particles' positions once the data up to ``lag_s`` later are in (the
particles' ancestry is kept for the steps not yet reported, so a resampling carries it along:
the fixed-lag particle smoother of Kitagawa).

Pure numpy; frames and units as above (m, rad, dB, s).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from graphslam.core.tracking.filters import PathLossModel
from graphslam.errors import EstimationError
from graphslam.tracking_config import DEFAULTS

# The match temperature T per fingerprint distance (its units: eq. 9 dB; Sørensen, unitless in [0, 1]): each
# the maximum of the leave-one-session-out log-likelihood of the ILC B1 training maps' own fingerprint
# positions under the scan-match mixture (the map only; the surface is flat near it: docs/tracking.md)
PARTICLE_TEMPERATURE = {"eq9": 2.0, "sorensen": 0.05}


@dataclass(frozen=True)
class ParticleConfig:
    n_particles: int = DEFAULTS.particle.count
    top_k: int = DEFAULTS.particle.top_k  # map fingerprints in a scan's likelihood mixture
    temperature: float = PARTICLE_TEMPERATURE["eq9"]  # T: match weights exp(-(D_j - D_1) / T), the distances' units
    kernel_m: float = DEFAULTS.particle.kernel_m  # h: each match's spatial spread (m)
    outlier: float = DEFAULTS.particle.outlier  # eps: share of a uniform density in a scan's likelihood
    area_m2: float = 10000.0  # the uniform density's area (the map's bounding box)
    step_sigma_m: float = 0.05  # position noise per step, per axis (m)
    step_sigma_rel: float = 0.05  # and per metre walked (fraction)
    scale_sigma: float = 0.05  # the walk's step-length scale: N(1, this) at the start
    heading_sigma_rad: float = 0.01  # random walk of phi per step (rad)
    init_spread_m: float = 3.0  # start positions: the first scan's matches, each spread by this
    lag_s: float = DEFAULTS.fixed_lag.lag_s
    resample_ess: float = 0.5  # systematic resampling once the effective sample size < this x n
    huber_k: float = DEFAULTS.filter.gate_sigma  # RSSI readings (when given): Huber loss beyond this many std
    seed: int = DEFAULTS.particle.seed

    def __post_init__(self) -> None:
        if self.n_particles < 2 or self.top_k < 1:
            raise EstimationError("particle filter: n_particles >= 2 and top_k >= 1 required")
        vals = (self.temperature, self.kernel_m, self.init_spread_m)
        if not all(math.isfinite(v) and v > 0 for v in vals):
            raise EstimationError("particle filter: temperature, kernel_m and init_spread_m must be > 0")
        if not (0 < self.resample_ess <= 1) or self.lag_s < 0 or not (0 < self.outlier < 1) or not self.area_m2 > 0:
            raise EstimationError("particle filter: 0 < resample_ess <= 1, lag_s >= 0, 0 < outlier < 1 and area_m2 > 0 required")


@dataclass(frozen=True, eq=False)
class RssiReadings:
    """Per scan the readings of modelled APs (rows of ``path_loss``, dBm), std ``sigma_db`` per AP."""

    path_loss: PathLossModel
    sigma_db: NDArray[np.float64]  # (A,)
    ap_idx: Sequence[NDArray[np.int64]]  # per scan
    rss_dbm: Sequence[NDArray[np.float64]]  # per scan

    def log_likelihood(self, xy: NDArray, scan: int, huber_k: float) -> NDArray[np.float64]:
        """(N,) minus the Huber cost of scan ``scan``'s readings at positions ``xy`` (N, 2)."""
        idx = self.ap_idx[scan]
        z = (self.rss_dbm[scan] - self.path_loss.mean_rss(xy, idx)) / self.sigma_db[idx]
        a = np.abs(z)
        return -np.where(a <= huber_k, 0.5 * z * z, huber_k * a - 0.5 * huber_k**2).sum(axis=1)


@dataclass(frozen=True, eq=False)
class ParticleRun:
    xy: NDArray[np.float64]  # (n_steps, 2) reported positions, map frame (m)
    cov: NDArray[np.float64]  # (n_steps, 2, 2) their covariances (m^2)
    phi: NDArray[np.float64]  # (n_steps,) circular mean of the frame rotation (rad)
    phi_var: NDArray[np.float64]  # (n_steps,) its circular variance proxy (rad^2)
    resamplings: int
    rssi_used: int = 0  # RSSI readings weighed (Huber: none is gated out)


def scan_matches(distances: NDArray, k: int) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """(S, k) map rows of each scan's ``k`` nearest fingerprints (``-1`` padded) and their distances
    (``inf`` padded), nearest first, from the (S, M) distance matrix."""
    s, m = distances.shape
    k = min(k, m)
    if k == 0:
        return np.full((s, 0), -1, np.int64), np.zeros((s, 0))
    part = np.argpartition(distances, k - 1, axis=1)[:, :k] if k < m else np.tile(np.arange(m), (s, 1))
    d = np.take_along_axis(distances, part, axis=1)
    order = np.argsort(d, axis=1, kind="stable")
    idx, d = np.take_along_axis(part, order, axis=1), np.take_along_axis(d, order, axis=1)
    return np.where(np.isfinite(d), idx, -1), d


def _mixture(d: NDArray, cfg: ParticleConfig) -> NDArray[np.float64]:
    """Match weights of one scan's distances (inf = no match), summing to 1 (all zero if none)."""
    ok = np.isfinite(d)
    if not ok.any():
        return np.zeros_like(d)
    w = np.where(ok, np.exp(-(np.where(ok, d, 0.0) - d[ok].min()) / cfg.temperature), 0.0)
    return w / w.sum()


def log_likelihood(xy: NDArray, centres: NDArray, w: NDArray, cfg: ParticleConfig) -> NDArray[np.float64]:
    """log of the scan's position density at particle positions ``xy`` (N, 2) for matches at
    ``centres`` (K, 2) weighted ``w`` (K,): (1 - eps) Gaussian mixture + eps uniform (per m^2,
    over ``area_m2``)."""
    d2 = ((xy[:, None, :] - centres[None, :, :]) ** 2).sum(-1)
    h2 = cfg.kernel_m**2
    mix = np.exp(-0.5 * d2 / h2) @ w / (2 * math.pi * h2)
    return np.log((1 - cfg.outlier) * mix + cfg.outlier / cfg.area_m2)


def _systematic(w: NDArray, rng: np.random.Generator) -> NDArray[np.int64]:
    n = len(w)
    c = np.cumsum(w)
    c[-1] = 1.0
    return np.minimum(np.searchsorted(c, (rng.random() + np.arange(n)) / n), n - 1)


def run_particle_filter(
    t_s: NDArray[np.float64],
    odo_xy: NDArray[np.float64],
    walked: NDArray[np.bool_],
    scan_t_s: NDArray[np.float64],
    match_xy: NDArray[np.float64],
    match_d: NDArray[np.float64],
    cfg: ParticleConfig = ParticleConfig(),
    rssi: RssiReadings | None = None,
) -> ParticleRun:
    """Track one walk.

    ``t_s`` (n,) step times (s, ascending); ``odo_xy`` (n, 2) the foot module's positions (its own
    frame, m); ``walked`` (n - 1,) whether a step interval is a usable displacement (else only
    noise moves the particles); ``scan_t_s`` (S,) scan times; ``match_xy`` (S, K, 2) and
    ``match_d`` (S, K) each scan's nearest map fingerprints (positions, distances in the metric's units; ``inf``
    for none). ``rssi``: each scan's readings under path-loss models, weighed too (Huber). The
    first scan with a match places the particles; ``EstimationError`` if none has.
    """
    n = len(t_s)
    rng = np.random.default_rng(cfg.seed)
    N = cfg.n_particles
    has = np.isfinite(match_d).any(axis=1) if match_d.size else np.zeros(len(scan_t_s), bool)
    if not has.any():
        raise EstimationError("particle filter: no scan matches the radio map")
    cand = np.flatnonzero(has)
    first = int(cand[np.argmin(scan_t_s[cand])])  # the earliest scan with a match
    w0 = _mixture(match_d[first], cfg)
    pick = rng.choice(len(w0), size=N, p=w0)
    pos = match_xy[first, pick] + rng.normal(scale=cfg.init_spread_m, size=(N, 2))
    phi = rng.uniform(-math.pi, math.pi, N)
    scale = 1.0 + cfg.scale_sigma * rng.standard_normal(N)
    logw = np.zeros(N)
    order = np.argsort(scan_t_s, kind="stable")
    scans = [int(j) for j in order if has[j] and j != first]
    si = 0
    hist: list[NDArray] = [pos.copy()]  # positions of the steps not yet reported, ancestry-aligned
    base = 0  # step index of hist[0]
    xy_out = np.zeros((n, 2))
    cov_out = np.zeros((n, 2, 2))
    phi_out = np.zeros(n)
    phi_var = np.zeros(n)
    resamplings = 0
    rssi_used = 0

    def weights() -> NDArray:
        w = np.exp(logw - logw.max())
        return w / w.sum()

    def report(k: int, p: NDArray, w: NDArray) -> None:
        m = w @ p
        dp = p - m
        cov_out[k] = (w[:, None] * dp).T @ dp
        xy_out[k] = m
        c, s = w @ np.cos(phi), w @ np.sin(phi)  # the particles' rotation now (it drifts ~0.01 rad a step)
        phi_out[k] = math.atan2(s, c)
        phi_var[k] = -2.0 * math.log(max(math.hypot(c, s), 1e-12))

    for k in range(n - 1):
        # this interval's displacement of every particle (module frame -> map frame)
        d = odo_xy[k + 1] - odo_xy[k]
        step = float(np.hypot(*d)) if walked[k] else 0.0
        if walked[k]:
            c, s = np.cos(phi), np.sin(phi)
            move = scale[:, None] * np.column_stack([c * d[0] - s * d[1], s * d[0] + c * d[1]])
        else:
            move = np.zeros((N, 2))
        move += rng.normal(scale=cfg.step_sigma_m + cfg.step_sigma_rel * step, size=(N, 2))
        t0, t1 = t_s[k], t_s[k + 1]
        while si < len(scans) and scan_t_s[scans[si]] <= t1:
            j = scans[si]
            si += 1
            if scan_t_s[j] < t0:
                continue  # before the first step: the start already used the first match
            a = (scan_t_s[j] - t0) / (t1 - t0) if t1 > t0 else 1.0
            ok = np.isfinite(match_d[j])
            at = pos + a * move
            logw += log_likelihood(at, match_xy[j, ok], _mixture(match_d[j, ok], cfg), cfg)
            if rssi is not None and len(rssi.ap_idx[j]):
                logw += rssi.log_likelihood(at, j, cfg.huber_k)
                rssi_used += len(rssi.ap_idx[j])
            logw -= logw.max()
        pos = pos + move
        phi = phi + cfg.heading_sigma_rad * rng.standard_normal(N)
        hist.append(pos)
        w = weights()
        if 1.0 / float(w @ w) < cfg.resample_ess * N:
            idx = _systematic(w, rng)
            pos, phi, scale = pos[idx], phi[idx], scale[idx]
            hist = [h[idx] for h in hist]
            logw = np.zeros(N)
            resamplings += 1
            w = weights()
        # the steps whose lag has passed, from the particles' ancestry
        while hist and t_s[base] <= t1 - cfg.lag_s:
            report(base, hist.pop(0), w)
            base += 1
    w = weights()
    for i, p in enumerate(hist):
        report(base + i, p, w)
    return ParticleRun(xy_out, cov_out, phi_out, phi_var, resamplings, rssi_used)
