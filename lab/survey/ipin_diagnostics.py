#!/usr/bin/env python3
"""What the WiFi of one IPIN 2023 floor can and cannot tell about walk placement.

Ground truth is used only to *measure*: nothing here feeds a solver. Truth per walk: the rigid
SE(2) fit of its dead reckoning (PDR) to its own landmarks (``fit_se2`` of the PDR position at
each landmark time onto the landmark, as ``graphslam.core.survey.evaluate`` does); a scan's true
position is its PDR position under that fit. Every scan is kept: one taken while the walker
stands still is attached to the nearest step, where the walker stands.

Walks are grouped into *routes* by the trial number in the file name (``...Trial21_...``; a name
without one is a route of its own). The grouping is for these diagnostics only -- no solver gets
it: the competition's trials 21-27 are seven routes walked four times each, and the question is
how well routes can be stitched together. The phone model is told by the scan interval (the two
models scan every 2 s and 4 s; ../shared/DATA_CONTRACT.md).

Similarity of two scans: the cosine of their exp(rssi / 10 dB) vectors (0 for an AP not heard),
chosen by experiment 1. One JSON line per experiment on stdout, nothing written anywhere else:

0. ``floor``: walks, scans, routes, phones.
1. ``similarity``: candidate similarities (eq. 9 distance; Torres-Sospedra's powed RSS, cosine;
   exp(rssi / 5, 10, 20 dB), cosine). Among pairs of scans of different walks: AUC of near pairs
   (< 4 m apart in truth) against far pairs (> 15 m), for same-phone pairs, different-phone pairs
   and pairs of different routes; each scan's most similar scan of another walk, its true distance.
2. ``calibration``: similarity per distance band for pairs *within* walks more than 10 s (30 s)
   apart, at their PDR distance -- no ground truth -- and for pairs across walks at their true
   distance (same / different phone). Where they match, a walk's own PDR calibrates the
   similarity -> distance relation for free.
3. ``walk_to_perfect_map``: leave-one-walk-out. Every other walk at its true pose (a perfect map);
   the walk placed by Hough voting of its scans' 10 most similar map scans (each vote weighted by
   max(0, L(s, d < 2 m)) of the ``intra`` table below; rotations every 4 deg, 1 m cells, Gaussian
   1.5 m), then the best 8 rotations re-scored by the ``intra`` composite likelihood. Mean error
   over the walk's scans: fraction of walks within 3 / 5 m.
4. ``route_overlap``: per pair of routes, the scans of each within 3 m of the other (the junction),
   the similarity of those pairs, and how often a junction scan's most similar scan of the other
   route lies within 5 m. Neighbours: >= 3 junction scans on each side.
5. ``route_registration``: a route (its walks at their true relative poses, in its first walk's
   PDR frame) registered (a) onto one neighbouring route, (b) leave-route-out, onto all the other
   routes at their true poses. Rotation searched every 5 deg; error: mean over the route's scans.
   Methods, each an exhaustive grid search:
   ``hough``: votes of each scan's 5 most similar scans of other routes, weight s^4, Gaussian 1.5 m.
   ``composite_<table>``: the sum over EVERY pair (route scan, map scan) of a log-likelihood ratio
   L(s, d) = log p(s | d) - log p_ref(s) (``likelihood_tables``: ``intra`` and ``intra_10`` from
   pairs within walks at PDR distance, no ground truth; ``intra_background`` the same against a
   mismatched reference; ``oracle`` from pairs across walks at true distance), on a 1 m
   translation grid by FFT: every pair is a vote, one kernel per similarity bin.
   ``ap``: path-loss access points fitted to the map scans at their true positions (``fit_ap``);
   the route placed by the robust likelihood of every second scan's readings (Huber, 6 dB; fitted
   APs not heard penalised above -92 dBm), 3 m translation grid, 10 deg rotations.
6. ``manhattan``: each walk's dominant direction modulo 90 deg (``axis_vector``: length-weighted
   circular mean of 4 x step direction), in the site frame through its true rotation. If the
   corridors were one orthogonal grid, every walk would give the same angle.
7. ``rotation``: the searches of 5 with the rotation unknown (5 deg grid), known modulo 90 deg
   from the walks' PDR axes (align the route's axis with the map's, + k 90 deg: a Manhattan prior
   from the data), known modulo 90 deg exactly (true + k 90 deg) and known; ``fails_by`` says
   whether a wrong unknown-rotation answer is the rotation's fault or wrong even at the true one.

    python lab/survey/ipin_diagnostics.py [FLOOR_DIR]    # default ../shared/data/ipin2023/b100_f-2

About two minutes on a 2-core machine under load (most of it experiment 5).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from itertools import combinations, pairwise
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy import sparse
from scipy.fft import irfft2, next_fast_len, rfft2

from graphslam import (
    ApModel, associate, DistanceEngine, FingerprintMatrix, fit_ap, fit_se2, GraphSlamError, InputError,
    interpolate_xy, read_survey, se2_apply, Survey, wrap_angle,
)


REPO = Path(__file__).resolve().parents[2]
DEFAULT_FLOOR = Path(os.environ.get("GRAPHSLAM_DATA", REPO.parent / "shared" / "data")) / "ipin2023" / "b100_f-2"

BLOCK_CELLS = 4_000_000  # pair blocks: rows x all scans, ~32 MB of float64 per array
KEEP_ALL_GAP_S = 3600.0  # associate every scan, standing still included
NEAR_M, FAR_M = 4.0, 15.0  # exp. 1: AUC of near against far pairs
SCALE_DB = 10.0  # exp(rssi / 10): the representation used from exp. 2 on (best of exp. 1)
MIN_DT_S = 10.0  # intra-walk pairs closer in time share the same moment's noise
S_FINE = 200  # similarity bins of the accumulated histograms (cosine in [0, 1])
D_FINE_M = 1.0  # distance bins of the accumulated histograms
D_MAX_M = 200.0
S_BINS = 25  # similarity bins of the likelihood tables (every 8 fine bins)
D_BIN_M = 2.0  # likelihood-table distance bins (reach and reference: ``likelihood_tables``)
KERNEL_REACH_M = 60.0  # the longest table reach: all kernels share one size (and the FFT histograms)
CELL_M = 1.0  # translation grid of the searches
HOUGH_SIGMA_M = 1.5
ROT_STEP_DEG = 5.0
CAL_BANDS = (0, 2, 4, 7, 10, 15, 20, 30, 50, np.inf)


# ---------------------------------------------------------------------------------------- data


@dataclass(frozen=True, eq=False)
class Floor:
    name: str
    walks: tuple[str, ...]
    route: NDArray  # (W,) route label per walk
    phone: NDArray  # (W,) scan interval class per walk ("2s" / "4s")
    truth: NDArray  # (W, 3) walk frame -> site frame
    steps: tuple[NDArray, ...]  # per walk (n, 2) PDR step positions
    walk: NDArray  # (N,) walk index per scan
    t_s: NDArray  # (N,) scan time
    pdr: NDArray  # (N, 2) scan position in its walk's PDR frame
    xy: NDArray  # (N, 2) scan position in the site frame (truth)
    fp: FingerprintMatrix
    E: sparse.csr_matrix  # (N, A) exp(rssi / SCALE_DB), unit rows
    axes: NDArray  # (W,) complex: ``axis_vector`` of each walk's PDR, own frame

    @property
    def n(self) -> int:
        return len(self.walk)

    @property
    def scan_route(self) -> NDArray:
        return self.route[self.walk]

    @property
    def routes(self) -> list[str]:
        return list(dict.fromkeys(self.route))


def _route_of(name: str) -> str:
    m = re.search(r"Trial(\d+)", name)
    return m.group(1) if m else name


def exp_rows(fp: FingerprintMatrix, scale_db: float) -> sparse.csr_matrix:
    """exp(rssi / scale) of the heard readings (0 where not heard), each row of unit norm."""
    v = fp.values.copy().astype(np.float64)
    v.data = np.exp((v.data + fp.missing_dbm) / scale_db)
    norm = np.sqrt(np.asarray(v.multiply(v).sum(axis=1)).ravel())
    return sparse.diags(1.0 / np.maximum(norm, 1e-300)) @ v


def load(folder: Path) -> Floor:
    survey = read_survey([folder])
    keep = [s for s in survey if len(s.landmarks) >= 2 and s.scans]
    if len(keep) < 2:
        raise InputError(
            folder, "fewer than two walks with WiFi scans and >= 2 landmarks (needed as truth)", field="/landmarks"
        )
    fp = associate(Survey(tuple(keep)), max_gap_s=KEEP_ALL_GAP_S)
    truth = []
    for s in keep:
        est = interpolate_xy(s.steps, np.array([m.t_ns for m in s.landmarks], float))
        truth.append(fit_se2(est, np.array([[m.x, m.y] for m in s.landmarks])))
    T = np.array(truth)
    steps = tuple(s.steps.xy for s in keep)
    pdr = np.concatenate(steps)[fp.node]
    xy = np.empty_like(pdr)
    for w in range(len(keep)):
        m = fp.session == w
        xy[m] = se2_apply(T[w], pdr[m])
    interval = np.array(
        [np.median(np.diff(np.sort([sc.t_ns for sc in s.scans]))) / 1e9 if len(s.scans) > 1 else np.nan for s in keep]
    )
    return Floor(
        name=folder.name,
        walks=tuple(s.session_id for s in keep),
        route=np.array([_route_of(Path(s.source).name if s.source else s.session_id) for s in keep]),
        phone=np.where(interval < 3.0, "2s", "4s"),
        truth=T,
        steps=steps,
        walk=fp.session,
        t_s=fp.t_ns / 1e9,
        pdr=pdr,
        xy=xy,
        fp=fp.fingerprints,
        E=exp_rows(fp.fingerprints, SCALE_DB),
        axes=np.array([axis_vector(st) for st in steps]),
    )


def row_blocks(n: int, width: int) -> Iterator[slice]:
    rows = max(16, BLOCK_CELLS // max(width, 1))
    for a in range(0, n, rows):
        yield slice(a, min(n, a + rows))


def cross_dist(a: NDArray, b: NDArray) -> NDArray:
    return np.sqrt(np.maximum((a * a).sum(1)[:, None] + (b * b).sum(1)[None] - 2 * a @ b.T, 0.0))


def sim_block(E: sparse.csr_matrix, rows: NDArray | slice, cols: NDArray | slice | None = None) -> NDArray:
    """Cosine similarities of unit rows ``rows`` against ``cols`` (all scans by default), dense."""
    other = E if cols is None else E[cols]
    return np.asarray((E[rows] @ other.T).todense())


def _r(x: float, nd: int = 2) -> float | None:
    return None if not np.isfinite(x) else round(float(x), nd)


# --------------------------------------------------------------------------- 1. similarity


def _similarities(f: Floor) -> dict[str, tuple[Callable[[slice], NDArray], tuple[float, float]]]:
    """name -> (row block -> similarity to all scans (higher = more alike), score range)."""
    eng = DistanceEngine(f.fp)
    powed = f.fp.values.copy()
    powed.data = (powed.data / -f.fp.missing_dbm) ** np.e  # ((rss - min) / -min) ** e
    powed = sparse.diags(1.0 / np.maximum(np.sqrt(np.asarray(powed.multiply(powed).sum(1)).ravel()), 1e-300)) @ powed
    reps: dict[str, tuple[Callable[[slice], NDArray], tuple[float, float]]] = {
        "eq9": (lambda b: -eng.block(f.fp.rows(b), min_common=1)[0], (f.fp.missing_dbm, 0.0)),
        "powed_cosine": (lambda b: sim_block(powed, b), (0.0, 1.0)),
    }
    for scale in (5.0, 10.0, 20.0):
        E = f.E if scale == SCALE_DB else exp_rows(f.fp, scale)
        reps[f"exp{scale:g}_cosine"] = (lambda b, E=E: sim_block(E, b), (0.0, 1.0))
    return reps


def _auc(h_near: NDArray, h_far: NDArray) -> float | None:
    """P(score of a near pair > score of a far pair), ties half, from histograms over score bins."""
    n, m = h_near.sum(), h_far.sum()
    if n == 0 or m == 0:
        return None
    below = np.cumsum(h_far) - h_far
    return round(float((h_near * (below + 0.5 * h_far)).sum() / (n * m)), 3)


def similarity(f: Floor) -> dict:
    nbins = 4000
    phone, route = f.phone[f.walk], f.scan_route
    groups = {  # row block -> which of its pairs belong to the group
        "same_phone": lambda b: phone[b][:, None] == phone[None],
        "diff_phone": lambda b: phone[b][:, None] != phone[None],
        "diff_route": lambda b: route[b][:, None] != route[None],
    }
    out = {}
    for name, (block, (lo, hi)) in _similarities(f).items():
        h = {g: np.zeros((2, nbins)) for g in groups}
        nn_d = np.empty(f.n)
        for b in row_blocks(f.n, f.n):
            S = block(b)
            other = f.walk[b][:, None] != f.walk[None]
            upper = np.arange(f.n)[None] > np.arange(f.n)[b][:, None]
            d = cross_dist(f.xy[b], f.xy)
            k = np.clip(((np.clip(S, lo, hi) - lo) / (hi - lo) * nbins).astype(int), 0, nbins - 1)
            for g, sel in groups.items():
                m = other & upper & sel(b)
                h[g][0] += np.bincount(k[m & (d < NEAR_M)], minlength=nbins)
                h[g][1] += np.bincount(k[m & (d > FAR_M)], minlength=nbins)
            S = np.where(other, S, -np.inf)
            nn_d[b] = d[np.arange(len(d)), np.argmax(S, axis=1)]
        out[name] = {
            **{f"auc_{g}": _auc(*h[g]) for g in groups},
            "nearest_other_walk_median_m": _r(np.median(nn_d)),
            "nearest_other_walk_p90_m": _r(np.percentile(nn_d, 90)),
            "nearest_other_walk_within_5m": _r(np.mean(nn_d < 5), 3),
        }
    return {"near_m": NEAR_M, "far_m": FAR_M, "representations": out}


# ----------------------------------------------------------- 2. calibration, likelihood tables


def pair_histograms(f: Floor) -> dict[str, NDArray]:
    """(distance bin, similarity bin) counts of exp(rssi/10) cosine, per pair category, each pair
    once. Within walks: PDR distance (no truth); across walks: true distance."""
    nd = int(D_MAX_M / D_FINE_M) + 1
    H = {c: np.zeros((nd, S_FINE)) for c in ("intra_dt10", "intra_dt30", "cross_same_phone", "cross_diff_phone")}
    phone = f.phone[f.walk]
    for b in row_blocks(f.n, f.n):
        S = sim_block(f.E, b)
        si = np.clip((S * S_FINE).astype(int), 0, S_FINE - 1)
        upper = np.arange(f.n)[None] > np.arange(f.n)[b][:, None]
        same = f.walk[b][:, None] == f.walk[None]
        dt = np.abs(f.t_s[b][:, None] - f.t_s[None])
        d_pdr = np.minimum(cross_dist(f.pdr[b], f.pdr) / D_FINE_M, nd - 1).astype(int)
        d_true = np.minimum(cross_dist(f.xy[b], f.xy) / D_FINE_M, nd - 1).astype(int)
        same_ph = phone[b][:, None] == phone[None]
        masks = {
            "intra_dt10": (same & (dt > MIN_DT_S), d_pdr),
            "intra_dt30": (same & (dt > 30.0), d_pdr),
            "cross_same_phone": (~same & same_ph, d_true),
            "cross_diff_phone": (~same & ~same_ph, d_true),
        }
        for c, (m, di) in masks.items():
            m = m & upper
            H[c] += np.bincount(di[m] * S_FINE + si[m], minlength=nd * S_FINE).reshape(nd, S_FINE)
    return H


def _quantiles(h: NDArray, qs: tuple[float, ...] = (0.25, 0.5, 0.75)) -> list[float | None]:
    if h.sum() == 0:
        return [None] * len(qs)
    c = np.cumsum(h) / h.sum()
    return [round((int(np.searchsorted(c, q)) + 0.5) / S_FINE, 3) for q in qs]


def calibration(H: dict[str, NDArray]) -> dict:
    d = np.arange(H["intra_dt10"].shape[0]) * D_FINE_M
    bands = []
    for lo, hi in pairwise(CAL_BANDS):
        sel = (d >= lo) & (d < hi)
        row = {"band_m": [lo, hi if np.isfinite(hi) else None]}
        for c, h in H.items():
            hh = h[sel].sum(0)
            row[c] = {"q25_median_q75": _quantiles(hh), "pairs": int(hh.sum())}
        bands.append(row)
    gap = {}
    for c in ("cross_same_phone", "cross_diff_phone"):
        diffs = [
            abs(b["intra_dt10"]["q25_median_q75"][1] - b[c]["q25_median_q75"][1])
            for b in bands
            if b["band_m"][1] is not None and b["band_m"][1] <= 20 and b[c]["pairs"] and b["intra_dt10"]["pairs"]
        ]
        gap[c] = round(max(diffs), 3) if diffs else None
    return {"similarity": f"exp{SCALE_DB:g}_cosine", "bands": bands, "max_median_gap_to_20m_intra_vs": gap}


def llr_table(h: NDArray, reference: NDArray, cut_m: float) -> NDArray:
    """(distance bin, similarity bin) log p(s | d) - log p_ref(s) for d < ``cut_m`` (beyond: 0),
    from fine counts ``h`` (distance x similarity) and the reference's similarity counts."""
    per_d, n_near = int(D_BIN_M / D_FINE_M), int(cut_m / D_BIN_M)

    def coarse(x: NDArray) -> NDArray:
        return x.reshape(*x.shape[:-1], S_BINS, S_FINE // S_BINS).sum(-1)

    P = np.array([coarse(h[i * per_d : (i + 1) * per_d].sum(0)) for i in range(n_near)]) + 0.5
    ref = coarse(reference) + 0.5
    return np.log(P / P.sum(1, keepdims=True)) - np.log(ref / ref.sum())[None]


def likelihood_tables(H: dict[str, NDArray]) -> dict[str, NDArray]:
    """The similarity -> distance log-likelihood ratio tables L(s, d) of the composite likelihood.

    Summed over pairs, a table is the log-likelihood ratio of a placement against one where every
    pair is beyond the cut. For that the reference must be the similarity of pairs just beyond
    the cut: against any other, a pair coming into reach adds log p(s | cut) / p_ref(s) != 0, and
    pulling a route into the crowd of map scans pays by itself.

    - ``intra``: pairs within walks (> 10 s apart) at their PDR distance, no truth: up to 16 m,
      against 16-30 m. Within a walk, pairs run out beyond ~25 m (out-and-back routes: 12,440 /
      10,136 / 1,559 / 46 pairs in 0-10 / 10-20 / 20-30 / 30-40 m on b100_f-2); 16 m keeps
      > 1,000 pairs in every 2 m bin.
    - ``intra_10``: the same up to 10 m against 10-20 m (the reach of the first experiments).
    - ``intra_background``: the same up to 24 m against all pairs of different walks wherever they
      are (still no truth): the reference is NOT the distribution beyond the cut; kept to show
      what that costs.
    - ``oracle``: pairs across walks at TRUE distance, up to 60 m against >= 60 m.
    """
    intra = H["intra_dt10"]
    cross = H["cross_same_phone"] + H["cross_diff_phone"]

    def band(h: NDArray, lo: float, hi: float) -> NDArray:
        return h[int(lo / D_FINE_M) : int(hi / D_FINE_M)].sum(0)

    return {
        "intra": llr_table(intra, band(intra, 16, 30), 16.0),
        "intra_10": llr_table(intra, band(intra, 10, 20), 10.0),
        "intra_background": llr_table(intra, cross.sum(0), 24.0),
        "oracle": llr_table(cross, band(cross, 60, D_MAX_M + 1), 60.0),
    }


def s_bin(S: NDArray) -> NDArray:
    return np.clip((S * S_BINS).astype(int), 0, S_BINS - 1)


def table_value(L: NDArray, sb: NDArray, d: NDArray) -> NDArray:
    """L at similarity bin ``sb`` and distance ``d``: linear in d between the bin centres, falling
    to 0 half a bin past the cut and 0 beyond, so that a placement's score changes smoothly (a
    1 m search grid then loses < 0.2 % of the best score, measured on b100_f-2)."""
    n = L.shape[0]
    Lz = np.vstack([L, np.zeros((2, L.shape[1]))])
    x = np.clip(d / D_BIN_M - 0.5, 0.0, float(n))
    k = x.astype(np.int64)
    frac = x - k
    return Lz[k, sb] * (1.0 - frac) + Lz[k + 1, sb] * frac


def composite(L: NDArray, S: NDArray, d: NDArray) -> float:
    """Sum over pairs (similarity S, distance d) of L(s, d)."""
    return float(table_value(L, s_bin(S), d).sum())


def table_kernels(L: NDArray) -> NDArray:
    """(similarity bin, 2R+1, 2R+1): L(s, |r|) for every grid offset r of the translation grid."""
    R = int(np.ceil(KERNEL_REACH_M / CELL_M)) + 2
    g = np.arange(-R, R + 1) * CELL_M
    r = np.hypot(g[:, None], g[None])
    return np.stack([table_value(L, np.full(r.shape, b), r) for b in range(L.shape[1])])


def gaussian_kernel(sigma_m: float) -> NDArray:
    R = int(np.ceil(4 * sigma_m / CELL_M))
    g = np.arange(-R, R + 1) * CELL_M
    return np.exp(-(g[:, None] ** 2 + g[None] ** 2) / (2 * sigma_m**2))[None]


# ------------------------------------------------------------------------------ SE(2) search


def se2_search(
    P: NDArray,
    Q: NDArray,
    i: NDArray,
    j: NDArray,
    chan: NDArray,
    w: NDArray | None,
    kernels: list[NDArray],
    thetas: NDArray,
) -> list[tuple[NDArray, NDArray]]:
    """Rigid placement of points ``P`` (own frame) onto ``Q`` (map frame), exhaustive on a grid.

    For rotation theta and translation t: score = sum over votes v of
    K_chan[v](R P[i_v] + t - Q[j_v]) (weighted by ``w``), i.e. every vote's kernel centred on the
    translation that would put its two points together. Per rotation: one histogram of the votes
    per channel, convolved with its kernel by FFT, summed, maximised over t. Each kernel set in
    ``kernels`` (channels x (2R+1)^2, same R) shares the histograms. Returns, per kernel set,
    (best score per theta, best T = (x, y, theta) per theta)."""
    c = P.mean(0)
    Pc = P - c
    r = np.sqrt((Pc**2).sum(1).max())
    R = kernels[0].shape[-1] // 2
    lo = Q.min(0) - r - 2 * CELL_M
    nx, ny = np.ceil((Q.max(0) + r + 2 * CELL_M - lo) / CELL_M).astype(int)
    C = kernels[0].shape[0]
    shape = (next_fast_len(nx + 2 * R), next_fast_len(ny + 2 * R))
    Kf = [rfft2(K, s=shape, workers=1) for K in kernels]
    w = np.ones(len(i)) if w is None else w
    out = [(np.empty(len(thetas)), np.empty((len(thetas), 3))) for _ in kernels]
    for k, th in enumerate(thetas):
        ct, st = np.cos(th), np.sin(th)
        tv = Q[j] - np.column_stack([ct * Pc[i, 0] - st * Pc[i, 1], st * Pc[i, 0] + ct * Pc[i, 1]])
        # each vote shared bilinearly by the 4 cells around it (cell a's centre: lo + (a + 0.5) cell)
        u = (tv - lo) / CELL_M - 0.5
        g = np.floor(u).astype(np.int64)
        fx, fy = (u - g).T
        H = np.zeros(C * nx * ny)
        for dx, dy, wc in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
            H += np.bincount((chan * nx + g[:, 0] + dx) * ny + g[:, 1] + dy, weights=w * wc, minlength=C * nx * ny)
        Hf = rfft2(H.reshape(C, nx, ny), s=shape, workers=1)
        for (score, T), kf in zip(out, Kf):
            A = irfft2(np.einsum("cxy,cxy->xy", Hf, kf), s=shape, workers=1)[R : R + nx, R : R + ny]
            a = np.unravel_index(int(np.argmax(A)), A.shape)
            t = lo + (np.array(a) + 0.5) * CELL_M
            score[k] = A[a]
            T[k] = [t[0] - (ct * c[0] - st * c[1]), t[1] - (st * c[0] + ct * c[1]), th]
    return out


def axis_vector(steps: NDArray) -> complex:
    """Sum over steps of length x exp(4i heading of the step's displacement): its angle / 4 is the
    walk's dominant direction modulo 90 deg (own frame), its modulus / length the concentration."""
    d = np.diff(steps, axis=0)
    return complex((np.linalg.norm(d, axis=1) * np.exp(4j * np.arctan2(d[:, 1], d[:, 0]))).sum())


def rotation_set(
    theta_true: float, theta_axes: float, step_deg: float | None = None
) -> tuple[NDArray, dict[str, slice]]:
    """Rotations to search and, per rotation prior, which of them it may pick: ``unknown`` a grid
    (in the route's own frame, so the truth is not on it); ``mod90`` the true rotation + k 90 deg
    (a perfect Manhattan prior); ``known`` the true rotation; ``mod90_pdr_axes`` the rotation that
    aligns the route's PDR dominant direction with the map's, + k 90 deg (a Manhattan prior from
    the data)."""
    grid = np.radians(np.arange(0.0, 360.0, step_deg or ROT_STEP_DEG))
    quarter = np.radians([0.0, 90.0, 180.0, 270.0])
    n = len(grid)
    groups = {
        "unknown": slice(0, n),
        "mod90": slice(n, n + 4),
        "known": slice(n, n + 1),
        "mod90_pdr_axes": slice(n + 4, n + 8),
    }
    return np.concatenate([grid, theta_true + quarter, theta_axes + quarter]), groups


def summarise(
    score: NDArray, T: NDArray, groups: dict[str, slice], P: NDArray, truth_xy: NDArray, theta_true: float
) -> dict:
    """Per rotation prior: error (mean over the points), rotation error and score of the best placement."""
    out = {}
    for name, g in groups.items():
        k = g.start + int(np.argmax(score[g]))
        out[name] = {
            "err_m": _r(np.linalg.norm(se2_apply(T[k], P) - truth_xy, axis=1).mean(), 1),
            "rot_err_deg": _r(np.degrees(abs(wrap_angle(T[k, 2] - theta_true))), 0),
            "score": _r(score[k], 1),
        }
    return out


# ------------------------------------------------------------------ 3. walk to a perfect map


def top_matches(f: Floor, key: NDArray, k: int) -> tuple[NDArray, NDArray, NDArray]:
    """Each scan's ``k`` most similar scans with a different ``key`` (walk or route): (i, j, s)."""
    I, J, V = [], [], []
    for b in row_blocks(f.n, f.n):
        S = sim_block(f.E, b)
        S[key[b][:, None] == key[None]] = -np.inf
        j = np.argpartition(-S, k - 1, axis=1)[:, :k]
        I.append(np.repeat(np.arange(f.n)[b], k))
        J.append(j.ravel())
        V.append(np.take_along_axis(S, j, 1).ravel())
    I_, J_, V_ = np.concatenate(I), np.concatenate(J), np.concatenate(V)
    ok = np.isfinite(V_)
    return I_[ok], J_[ok], V_[ok]


def walk_to_perfect_map(f: Floor, L: NDArray, k: int = 10, keep: int = 8) -> dict:
    i, j, s = top_matches(f, f.walk, k)
    w = np.maximum(L[0, s_bin(s)], 0.0)  # log-likelihood ratio of "same place" (d < 2 m), if positive
    G = [gaussian_kernel(HOUGH_SIGMA_M)]
    thetas = np.radians(np.arange(0.0, 360.0, 4.0))
    errs = {"hough": [], "hough_rescored": []}
    for wk in range(len(f.walks)):
        mine = np.flatnonzero(f.walk == wk)
        if len(mine) < 2:
            continue
        loc = np.full(f.n, -1)
        loc[mine] = np.arange(len(mine))
        sel = f.walk[i] == wk
        ((score, T),) = se2_search(
            f.pdr[mine], f.xy, loc[i[sel]], j[sel], np.zeros(sel.sum(), np.int64), w[sel], G, thetas
        )
        order = np.argsort(-score)[:keep]
        ref = np.flatnonzero(f.walk != wk)
        S = sim_block(f.E, mine, ref)
        ll = [composite(L, S, cross_dist(se2_apply(T[o], f.pdr[mine]), f.xy[ref])) for o in order]
        for name, o in (("hough", order[0]), ("hough_rescored", order[int(np.argmax(ll))])):
            errs[name].append(np.linalg.norm(se2_apply(T[o], f.pdr[mine]) - f.xy[mine], axis=1).mean())
    out = {"k": k, "walks": len(errs["hough"])}
    for name, e in errs.items():
        e = np.array(e)
        out[name] = {
            "within_3m": _r(np.mean(e < 3), 3),
            "within_5m": _r(np.mean(e < 5), 3),
            "median_m": _r(np.median(e)),
            "max_m": _r(e.max(), 1),
        }
    return out


# ------------------------------------------------------------------------- 4. route overlaps


def route_overlap(f: Floor, near_m: float = 3.0) -> tuple[dict, list[tuple[str, str]]]:
    rows, neighbours = [], []
    sr = f.scan_route
    for ra, rb in combinations(f.routes, 2):
        A, B = np.flatnonzero(sr == ra), np.flatnonzero(sr == rb)
        d = cross_dist(f.xy[A], f.xy[B])
        close = d < near_m
        ja, jb = close.any(1), close.any(0)
        if not (ja.any() or jb.any()):
            continue
        S = sim_block(f.E, A, B)
        # a junction scan's most similar scan of the other route: within 5 m of it?
        hit_a = d[np.arange(len(A)), np.argmax(S, 1)][ja] < 5.0
        hit_b = d[np.argmax(S, 0), np.arange(len(B))][jb] < 5.0
        rows.append(
            {
                "routes": [ra, rb],
                "scans": [len(A), len(B)],
                "junction_scans": [int(ja.sum()), int(jb.sum())],
                "pairs_within_3m": int(close.sum()),
                "median_s_of_those": _r(np.median(S[close]), 3) if close.any() else None,
                "junction_best_match_within_5m": [
                    _r(hit_a.mean(), 2) if len(hit_a) else None,
                    _r(hit_b.mean(), 2) if len(hit_b) else None,
                ],
            }
        )
        if ja.sum() >= 3 and jb.sum() >= 3:
            neighbours.append((ra, rb))
    return {"near_m": near_m, "pairs": rows, "neighbours": [list(p) for p in neighbours]}, neighbours


# ------------------------------------------------------------------ 5. route registration


@dataclass(frozen=True)
class ApMap:
    """Path-loss APs fitted to map scans: column index, position, P0, gamma; the not-heard map."""

    col: NDArray
    a: NDArray
    p0: NDArray
    gamma: NDArray


AP_SIGMA_DB, AP_FLOOR_DBM, AP_D0_M = 6.0, -92.0, 1.0
AP_CELL_M, AP_ROT_STEP_DEG, AP_SCAN_STRIDE = 3.0, 10.0, 2  # coarser than the FFT search: evaluated directly


def fit_ap_map(f: Floor, idx: NDArray) -> ApMap:
    V = f.fp.values[idx].tocsc()
    cols, rows = [], []
    for k in range(V.shape[1]):
        r = V.indices[V.indptr[k] : V.indptr[k + 1]]
        m = fit_ap(str(k), f.xy[idx[r]], V.data[V.indptr[k] : V.indptr[k + 1]] + f.fp.missing_dbm)
        if isinstance(m, ApModel):
            cols.append(k)
            rows.append((m.x, m.y, m.p0_dbm, m.gamma))
    A = np.array(rows).reshape(-1, 4)
    return ApMap(np.array(cols, np.int64), A[:, :2], A[:, 2], A[:, 3])


def _huber(z: NDArray) -> NDArray:
    a = np.abs(z)
    return np.where(a < 2.0, 0.5 * z * z, 2.0 * a - 2.0)


def ap_search(f: Floor, aps: ApMap, P: NDArray, scans: NDArray, Q: NDArray, thetas: NDArray) -> tuple[NDArray, NDArray]:
    """Best score (minus robust NLL) and T per rotation, translation on an AP_CELL_M grid.

    NLL of a scan at x: Huber((rss - pred_k(x)) / 6 dB) over its heard fitted APs plus
    Huber(max(pred_k(x) - floor, 0) / 6 dB) over the fitted APs it did not hear. The second sum is
    (over all fitted APs, a precomputed 1 m map) - (over the heard ones): the rest is sparse."""
    if len(aps.col) == 0:
        return np.full(len(thetas), -np.inf), np.zeros((len(thetas), 3))
    pos = np.full(f.fp.n_aps, -1)
    pos[aps.col] = np.arange(len(aps.col))
    sub = f.fp.values[scans].tocoo()
    keep = pos[sub.col] >= 0
    r_i, a_i = sub.row[keep], pos[sub.col[keep]]
    rss = (sub.data[keep] + f.fp.missing_dbm).astype(np.float32)
    p0, g5 = aps.p0[a_i].astype(np.float32), (5.0 * aps.gamma[a_i]).astype(np.float32)

    def hinge(p: NDArray) -> NDArray:
        return _huber(np.maximum(p - AP_FLOOR_DBM, 0.0) / AP_SIGMA_DB)

    c = P.mean(0)
    Pc = P - c
    r = np.sqrt((Pc**2).sum(1).max())
    lo, hi = Q.min(0) - r, Q.max(0) + r
    gx, gy = np.arange(lo[0], hi[0] + AP_CELL_M, AP_CELL_M), np.arange(lo[1], hi[1] + AP_CELL_M, AP_CELL_M)
    tx, ty = (v.ravel().astype(np.float32) for v in np.meshgrid(gx, gy, indexing="ij"))
    # not-heard penalty summed over every fitted AP, on a 1 m map covering every candidate position
    mlo = lo - r - 1.0
    mx, my = np.arange(mlo[0], hi[0] + r + 2.0), np.arange(mlo[1], hi[1] + r + 2.0)
    U = sum(
        hinge(
            aps.p0[a]
            - 5.0
            * aps.gamma[a]
            * np.log10((mx[:, None] - aps.a[a, 0]) ** 2 + (my[None] - aps.a[a, 1]) ** 2 + AP_D0_M**2)
        )
        for a in range(len(aps.col))
    )
    score, T = np.empty(len(thetas)), np.empty((len(thetas), 3))
    for k, th in enumerate(thetas):
        ct, st = np.cos(th), np.sin(th)
        RP = np.column_stack([ct * Pc[:, 0] - st * Pc[:, 1], st * Pc[:, 0] + ct * Pc[:, 1]]).astype(np.float32)
        ix = np.clip(np.rint(tx[:, None] + (RP[:, 0] - mlo[0])[None]).astype(np.int64), 0, len(mx) - 1)
        iy = np.clip(np.rint(ty[:, None] + (RP[:, 1] - mlo[1])[None]).astype(np.int64), 0, len(my) - 1)
        nll = U[ix, iy].sum(1)
        dx = tx[:, None] + (RP[r_i, 0] - aps.a[a_i, 0]).astype(np.float32)[None]  # (G, readings)
        dy = ty[:, None] + (RP[r_i, 1] - aps.a[a_i, 1]).astype(np.float32)[None]
        p = p0 - g5 * np.log10(dx * dx + dy * dy + np.float32(AP_D0_M**2))
        nll += (_huber((rss - p) / np.float32(AP_SIGMA_DB)) - hinge(p)).sum(1)
        g = int(np.argmin(nll))
        score[k] = -nll[g]
        T[k] = [tx[g] - (ct * c[0] - st * c[1]), ty[g] - (st * c[0] + ct * c[1]), th]
    return score, T


def register_routes(
    f: Floor,
    B: NDArray,
    A: NDArray,
    tables: dict[str, NDArray],
    kernels: dict[str, NDArray],
    matches: tuple[NDArray, NDArray, NDArray],
    with_ap: bool,
) -> dict:
    """Scans ``B`` (one route, true internal geometry, in its first walk's PDR frame) onto map scans
    ``A`` at their true positions, by every method; errors per rotation prior."""
    w0 = f.walk[B[0]]
    T0 = f.truth[w0]
    c0, s0 = np.cos(T0[2]), np.sin(T0[2])
    rel = f.xy[B] - T0[:2]
    P = np.column_stack([c0 * rel[:, 0] + s0 * rel[:, 1], -s0 * rel[:, 0] + c0 * rel[:, 1]])  # T0^-1(xy)
    # Manhattan prior from the data: route axis in its frame, map axis in the site frame
    z_route = sum(f.axes[w] * np.exp(4j * (f.truth[w, 2] - T0[2])) for w in np.unique(f.walk[B]))
    z_map = sum(f.axes[w] * np.exp(4j * f.truth[w, 2]) for w in np.unique(f.walk[A]))
    theta_axes = (np.angle(z_map) - np.angle(z_route)) / 4
    thetas, groups = rotation_set(T0[2], theta_axes)
    Q = f.xy[A]
    out: dict = {"pdr_axes_rot_err_deg": _r(np.degrees(abs(wrap_angle(4 * (theta_axes - T0[2])) / 4)), 1)}
    # top-k Hough: votes of the matches with one end in B and the other in A
    i, j, s = matches
    locB, locA = np.full(f.n, -1), np.full(f.n, -1)
    locB[B], locA[A] = np.arange(len(B)), np.arange(len(A))
    fw, bw = (locB[i] >= 0) & (locA[j] >= 0), (locA[i] >= 0) & (locB[j] >= 0)
    vi = np.concatenate([locB[i[fw]], locB[j[bw]]])
    vj = np.concatenate([locA[j[fw]], locA[i[bw]]])
    vw = np.concatenate([s[fw], s[bw]]) ** 4
    out["hough_votes"] = len(vi)
    if len(vi) >= 2:
        ((score, T),) = se2_search(
            P, Q, vi, vj, np.zeros(len(vi), np.int64), vw, [gaussian_kernel(HOUGH_SIGMA_M)], thetas
        )
        out["hough"] = summarise(score, T, groups, P, f.xy[B], T0[2])
    # composite likelihood: every pair a vote in the channel of its similarity bin
    sb = s_bin(sim_block(f.E, B, A))
    ii, jj = np.divmod(np.arange(sb.size), len(A))
    names = list(tables)
    res = se2_search(P, Q, ii, jj, sb.ravel(), None, [kernels[n] for n in names], thetas)
    for n, (score, T) in zip(names, res):
        out[f"composite_{n}"] = summarise(score, T, groups, P, f.xy[B], T0[2])
    if with_ap:
        aps = fit_ap_map(f, A)
        sub = np.arange(0, len(B), AP_SCAN_STRIDE)
        th_ap, g_ap = rotation_set(T0[2], theta_axes, AP_ROT_STEP_DEG)
        score, T = ap_search(f, aps, P[sub], B[sub], Q, th_ap)
        out["ap"] = summarise(score, T, g_ap, P, f.xy[B], T0[2])
        out["ap_fitted_aps"] = len(aps.col)
    return out


# ------------------------------------------------------------------------------ 6. Manhattan


def manhattan(f: Floor) -> dict:
    """Each walk's dominant direction modulo 90 deg in the site frame (its PDR axis turned by its
    true rotation); the floor's: all walks' axis vectors summed (so weighted by length)."""
    z_site = np.array([f.axes[w] * np.exp(4j * f.truth[w, 2]) for w in range(len(f.walks))])
    site = np.degrees(np.angle(z_site) / 4)  # (-45, 45]
    floor_axis = np.degrees(np.angle(z_site.sum()) / 4)
    dev = np.degrees(wrap_angle(4 * np.radians(site - floor_axis)) / 4)
    length = np.array([np.linalg.norm(np.diff(st, axis=0), axis=1).sum() for st in f.steps])
    routes = {}
    for r in f.routes:
        m = f.route == r
        routes[r] = {
            "axis_site_deg": [_r(x, 1) for x in site[m]],
            "deviation_from_floor_deg": [_r(x, 1) for x in dev[m]],
            "spread_deg": _r(np.ptp(dev[m]), 1),
            "length_m": [_r(x, 0) for x in length[m]],
            "r4": [_r(abs(z) / max(n, 1e-9), 2) for z, n in zip(z_site[m], length[m])],
        }
    return {
        "floor_axis_deg": _r(floor_axis, 1),
        "deviation_abs_median_deg": _r(np.median(np.abs(dev)), 1),
        "deviation_abs_max_deg": _r(np.abs(dev).max(), 1),
        "routes": routes,
    }


# ------------------------------------------------------------------------------------ main


def _emit(name: str, t0: float, payload: dict) -> None:
    print(json.dumps({"experiment": name, **payload, "time_s": round(time.perf_counter() - t0, 1)}), flush=True)


def run(folder: Path) -> None:
    t = time.perf_counter()
    f = load(folder)
    _emit(
        "0_floor",
        t,
        {
            "floor": f.name,
            "walks": len(f.walks),
            "scans": f.n,
            "aps": f.fp.n_aps,
            "routes": {r: int((f.route == r).sum()) for r in f.routes},
            "phones": {p: int((f.phone == p).sum()) for p in np.unique(f.phone)},
        },
    )
    t = time.perf_counter()
    _emit("1_similarity", t, similarity(f))
    t = time.perf_counter()
    H = pair_histograms(f)
    _emit("2_calibration", t, calibration(H))
    tables = likelihood_tables(H)
    kernels = {n: table_kernels(L) for n, L in tables.items()}
    t = time.perf_counter()
    _emit("3_walk_to_perfect_map", t, walk_to_perfect_map(f, tables["intra"]))
    t = time.perf_counter()
    ov, neighbours = route_overlap(f)
    _emit("4_route_overlap", t, ov)
    t = time.perf_counter()
    sr = f.scan_route
    matches = top_matches(f, sr, 5)
    pairwise = {}
    for ra, rb in neighbours:
        A, B = np.flatnonzero(sr == ra), np.flatnonzero(sr == rb)
        pairwise[f"{ra}-{rb}"] = register_routes(f, B, A, tables, kernels, matches, with_ap=False)
    lro = {}
    for r in f.routes:
        B, A = np.flatnonzero(sr == r), np.flatnonzero(sr != r)
        lro[r] = register_routes(f, B, A, tables, kernels, matches, with_ap=True)
    _emit(
        "5_route_registration", t, {"pairwise": _prior(pairwise, "unknown"), "leave_route_out": _prior(lro, "unknown")}
    )
    t = time.perf_counter()
    _emit("6_manhattan", t, manhattan(f))
    t = time.perf_counter()
    _emit("7_rotation", t, {"pairwise": _rotation_table(pairwise), "leave_route_out": _rotation_table(lro)})


def _prior(results: dict[str, dict], prior: str) -> dict:
    return {k: {m: v[prior] if isinstance(v, dict) else v for m, v in res.items()} for k, res in results.items()}


def _rotation_table(results: dict[str, dict], right_m: float = 5.0) -> dict:
    """Per case and method: error per rotation prior, and why the unknown-rotation answer is wrong
    (> 5 m): ``rotation`` (right at the true rotation, but the objective scores a wrong rotation
    higher), ``grid`` (right at the true rotation, which outscores every grid rotation: only the
    5 deg grid missed it), ``translation`` (wrong even at the true rotation)."""
    out = {}
    for k, res in results.items():
        row: dict = {"pdr_axes_rot_err_deg": res["pdr_axes_rot_err_deg"]}
        for m, v in res.items():
            if not isinstance(v, dict):
                continue
            u, kn = v["unknown"], v["known"]
            why = None
            if u["err_m"] > right_m:
                why = "translation" if kn["err_m"] > right_m else "rotation" if u["score"] > kn["score"] else "grid"
            row[m] = {p: v[p]["err_m"] for p in ("unknown", "mod90_pdr_axes", "mod90", "known")} | {"fails_by": why}
        out[k] = row
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("floor", nargs="?", type=Path, default=DEFAULT_FLOOR, help="folder of one floor's MCAP walks")
    args = ap.parse_args()
    try:
        run(args.floor)
    except GraphSlamError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
