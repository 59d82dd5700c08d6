"""Pairwise translation likelihood of two heading-rotated walks from all cross-walk similarities.

S_AB(t) = sum_ij h_{b(ij)}(|o_ij - t|), o_ij = p_i^A - p_j^B, h_b(d) = log p(b | d) - log p(b | far),
p(b | d) calibrated on within-walk pairs (dead-reckoning distances)."""
from __future__ import annotations

import numpy as np
from scipy.fft import rfft2, irfft2

D_EDGES = np.arange(0, 42, 2.0)  # distance bins (m); beyond: "far"


def sim_bins(sim_all: np.ndarray, nb: int) -> np.ndarray:
    return np.quantile(sim_all, np.linspace(0, 1, nb + 1)[1:-1])


def calibrate2(xy, sess, t_s, pc, edges_s, min_dt_s=20.0, d_cal=20.0, n_ref=200000, seed=0):
    """Near bins (< d_cal) from within-walk pairs; the reference ("far" row) = random cross-walk pairs."""
    logp, H = calibrate(xy, sess, t_s, pc, edges_s, min_dt_s)
    rng = np.random.default_rng(seed)
    N = len(xy)
    i = rng.integers(0, N, n_ref); j = rng.integers(0, N, n_ref)
    ok = sess[i] != sess[j]
    sb = np.searchsorted(edges_s, pc.pairs(i[ok], j[ok]))
    ref = np.bincount(sb, minlength=len(edges_s) + 1) + 0.5
    ref = np.log(ref / ref.sum())
    nd = len(D_EDGES)
    far = D_EDGES[:-1] >= d_cal
    logp = logp.copy()
    logp[:-1][far] = ref  # beyond the calibrated range: no information
    logp[-1] = ref
    return logp, H


def calibrate(xy, sess, t_s, pc, edges_s, min_dt_s=20.0, rng=None):
    """log p(b | d-bin) from within-walk pairs at least min_dt_s apart; last row = far (> D_EDGES[-1])."""
    nb = len(edges_s) + 1
    nd = len(D_EDGES)  # bins 0..nd-2 near, nd-1 = far
    H = np.ones((nd, nb)) * 0.5
    for k in np.unique(sess):
        idx = np.flatnonzero(sess == k)
        if len(idx) < 2:
            continue
        i, j = np.triu_indices(len(idx), 1)
        i, j = idx[i], idx[j]
        ok = np.abs(t_s[i] - t_s[j]) >= min_dt_s
        i, j = i[ok], j[ok]
        d = np.linalg.norm(xy[i] - xy[j], axis=1)
        db = np.minimum(np.searchsorted(D_EDGES, d, side="right") - 1, nd - 1)
        sb = np.searchsorted(edges_s, pc.pairs(i, j))
        np.add.at(H, (db, sb), 1.0)
    P = H / H.sum(1, keepdims=True)
    return np.log(P), H


def truth_calibrate(T, sess, pc, edges_s, n=300000, seed=0):
    rng = np.random.default_rng(seed)
    N = len(T)
    i = rng.integers(0, N, n); j = rng.integers(0, N, n)
    ok = (sess[i] != sess[j]) & np.isfinite(T[i, 0]) & np.isfinite(T[j, 0])
    i, j = i[ok], j[ok]
    nb = len(edges_s) + 1; nd = len(D_EDGES)
    H = np.ones((nd, nb)) * 0.5
    d = np.linalg.norm(T[i] - T[j], axis=1)
    db = np.minimum(np.searchsorted(D_EDGES, d, side="right") - 1, nd - 1)
    sb = np.searchsorted(edges_s, pc.pairs(i, j))
    np.add.at(H, (db, sb), 1.0)
    P = H / H.sum(1, keepdims=True)
    return np.log(P), H


class PairGrid:
    def __init__(self, logp, cell=1.0, half=64.0):
        self.cell, self.half = cell, half
        n = int(2 * half / cell)
        self.n = n
        # kernels: h_b on an (n, n) grid centred, radius up to D_EDGES[-1]
        h = logp[:-1] - logp[-1][None, :]  # (nd-1, nb): near bins minus far
        g = (np.arange(n) - n // 2) * cell
        R = np.hypot(g[:, None], g[None, :])
        db = np.searchsorted(D_EDGES, R, side="right") - 1
        K = np.zeros((h.shape[1], n, n))
        near = db < len(D_EDGES) - 1
        for b in range(h.shape[1]):
            K[b][near] = h[db[near], b]
        self.K = K
        self.Kf = rfft2(np.fft.ifftshift(K, axes=(1, 2)), s=(n, n))

    def score(self, o, b):
        """S on the grid of offsets t (index (ix, iy) -> t = (ix - n/2, iy - n/2) * cell)."""
        n, c = self.n, self.cell
        ix = np.round(o[:, 0] / c).astype(int) + n // 2
        iy = np.round(o[:, 1] / c).astype(int) + n // 2
        ok = (ix >= 0) & (ix < n) & (iy >= 0) & (iy < n)
        Hb = np.zeros((self.K.shape[0], n, n))
        np.add.at(Hb, (b[ok], ix[ok], iy[ok]), 1.0)
        S = irfft2(rfft2(Hb, s=(n, n)) * self.Kf, s=(n, n)).sum(0)
        return S

    def t_of(self, ix, iy):
        return np.array([(ix - self.n // 2) * self.cell, (iy - self.n // 2) * self.cell])


def truncate(logp, ref, d_cal=20.0):
    logp = logp.copy()
    far = D_EDGES[:-1] >= d_cal
    logp[:-1][far] = ref
    logp[-1] = ref
    return logp


def cross_ref(sess, pc, edges_s, n_ref=200000, seed=0):
    rng = np.random.default_rng(seed)
    N = len(sess)
    i = rng.integers(0, N, n_ref); j = rng.integers(0, N, n_ref)
    ok = sess[i] != sess[j]
    sb = np.searchsorted(edges_s, pc.pairs(i[ok], j[ok]))
    ref = np.bincount(sb, minlength=len(edges_s) + 1) + 0.5
    return np.log(ref / ref.sum())


def calibrate_extrap(xy, sess, t_s, pc, edges_s, d_fit=(8.0, 20.0), d_to=30.0, min_dt_s=20.0):
    """Within-walk calibration below d_fit[1]; per similarity bin, h extrapolated linearly in d
    (least squares over d_fit, weighted by counts) up to d_to; beyond: 0 (the cross-walk reference)."""
    logp, H = calibrate(xy, sess, t_s, pc, edges_s, min_dt_s)
    ref = cross_ref(sess, pc, edges_s)
    h = logp[:-1] - ref[None, :]
    dc = D_EDGES[:-1] + 1.0
    fit = (dc >= d_fit[0]) & (dc < d_fit[1])
    w = H[:-1][fit].sum(1)
    out = h.copy()
    for b in range(h.shape[1]):
        A = np.column_stack([np.ones(fit.sum()), dc[fit]])
        coef = np.linalg.lstsq(A * np.sqrt(w)[:, None], h[fit, b] * np.sqrt(w), rcond=None)[0]
        ext = (dc >= d_fit[1]) & (dc < d_to)
        out[ext, b] = coef[0] + coef[1] * dc[ext]
        # fade to 0 at d_to
        out[ext, b] *= np.clip((d_to - dc[ext]) / (d_to - d_fit[1]), 0, 1) ** 0.5
        out[dc >= d_to, b] = 0.0
    new = np.vstack([out + ref[None, :], ref[None, :]])
    return new, H
