"""Magnetic links between walks: sequences of the building's field matched along the walked path.

Indoors the building's steel makes the magnetic field vary from metre to metre, and every phone
records it (``/phone/magnetic``: east/north/up in µT, per step). Where the phone's orientation is
referenced to the magnetometer (every real recording here) the horizontal direction points north by
construction, so the features are the direction-free ones: the magnitude |B|, the horizontal
magnitude |B_h| and the vertical component B_up. A stretch of them along a walk is a signature of
the corridor walked, in whichever direction it is walked.

1. **Sequences** (``walk_sequences``): each walk's features resampled every ``sample_m`` of its
   dead-reckoned path, so that two walks of one corridor line up sample by sample (standstills
   collapse to one place).
2. **Window matches** (``window_matches``): windows of ``window_m`` every ``stride_m`` of each walk,
   mean-removed (a per-walk device or calibration offset of a few µT, 10-30 µT on some phones, is
   the data's: it cancels), compared with every window of another walk, forwards and reversed, by
   ``r = 2 <x, y> / (|x|^2 + |y|^2)`` (1: identical; it punishes a different amplitude as well as a
   different shape). Only where WiFi suggests it: each fingerprint's most similar fingerprints of
   other walks (the placement's matches) are anchors, and the window centred on each is compared with
   the other walk's stretches within ``search_m`` of the anchored place: a cost that grows with the
   survey, not its square (on IPIN 2023 floor -2 it finds 39 % of the right matches an all-pairs search
   finds, and every pair of a route's repetitions still links: ``lab/survey/magnetic.py recall``).
   Each window keeps its best match per other walk.
3. **Threshold from the data** (``null_threshold``): the same search against phase-randomised
   surrogates of the walks' sequences (same spectrum, so the same smoothness, but no place in
   common) gives the best score a window reaches by chance; a match counts when it beats the
   ``null_quantile`` of that. No ground truth, no per-floor tuning.
4. **Links** (``walk_links``): a single match is no link (the best match between routes that never
   meet still passes any fixed threshold now and then). With every walk turned into east/north by
   its heading, each match says where the other walk lies (a translation) and which way the two
   windows run (parallel for a forward match, anti-parallel for a reversed one: else it is dropped);
   a link is at least ``min_windows`` matches, disjoint on both walks, agreeing on one translation
   within ``agree_m``. Its correspondences (sample pairs every ``pair_every_m`` along every agreeing
   match, as step nodes) become the graph's magnetic factors, at most ``partners_per_place`` a place
   (``factor_pairs``).
5. **Units** (``link_units``): walks the links connect are placed relative to each other as rigid
   bodies; a link the placement leaves more than ``agree_m`` apart is dropped.

Frames: each walk's dead reckoning; translations in east/north (after each walk's rotation from its
heading), metres. Field in µT.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from graphslam.core.types import Survey

if TYPE_CHECKING:
    from graphslam.config import MagneticConfig
    from graphslam.core.survey.placement import GrowthParams

log = logging.getLogger(__name__)

N_FEATURES = 3  # |B|, |B_h|, B_up


@dataclass(frozen=True)
class MagneticParams:
    """Matching settings (metres, µT): ``graphslam.config.MagneticConfig``'s (``from_config``)."""

    sample_m: float = 0.5
    window_m: float = 10.0
    stride_m: float = 2.0
    search_m: float = 10.0
    null_quantile: float = 0.99
    min_windows: int = 2
    agree_m: float = 2.0
    direction_cos: float = 0.7
    pair_every_m: float = 4.0
    min_std_ut: float = 0.3  # a window flatter than this (rms, every feature) is no signature
    sharp_m: float = 2.0
    min_sharpness: float = 0.0
    seed: int = 0  # of the surrogates

    @classmethod
    def from_config(cls, cfg: "MagneticConfig") -> "MagneticParams":
        return cls(
            sample_m=cfg.sample_m, window_m=cfg.window_m, stride_m=cfg.stride_m, search_m=cfg.search_m,
            null_quantile=cfg.null_quantile, min_windows=cfg.min_windows, agree_m=cfg.agree_m,
            direction_cos=cfg.direction_cos, pair_every_m=cfg.pair_every_m,
        )

    @property
    def window(self) -> int:
        """Window length in samples."""
        return max(2, int(round(self.window_m / self.sample_m)))

    @property
    def stride(self) -> int:
        return max(1, int(round(self.stride_m / self.sample_m)))

    @property
    def search(self) -> int:
        return max(0, int(round(self.search_m / self.sample_m)))


@dataclass(frozen=True, eq=False)
class MagneticSequences:
    """Every walk's field features resampled along its dead-reckoned path.

    Walk ``s`` owns samples ``offsets[s]:offsets[s + 1]`` (none when it has no ``/phone/magnetic``)."""

    offsets: NDArray[np.int64]  # (S + 1,)
    features: NDArray[np.float64]  # (Q, 3) |B|, |B_h|, B_up (µT)
    xy: NDArray[np.float64]  # (Q, 2) dead-reckoned position, the walk's own frame (m)
    node: NDArray[np.int64]  # (Q,) global step node nearest each sample (``FingerprintNodes`` numbering)
    path_m: NDArray[np.float64]  # (Q,) distance walked at each sample

    @property
    def n_walks(self) -> int:
        return len(self.offsets) - 1

    def walk_of(self) -> NDArray[np.int64]:
        return np.repeat(np.arange(self.n_walks), np.diff(self.offsets))

    def has_field(self) -> NDArray[np.bool_]:
        return np.diff(self.offsets) > 0

    @classmethod
    def of_walks(cls, walks: list[tuple[NDArray, NDArray, NDArray, NDArray] | None]) -> "MagneticSequences":
        """Walk by walk: (features (n, 3), xy (n, 2), node (n,), path_m (n,)); None: a walk without samples."""
        parts = [w for w in walks if w is not None]
        sizes = [0 if w is None else len(w[3]) for w in walks]

        def cat(k: int, shape: tuple[int, ...], dtype: object) -> NDArray:
            return np.concatenate([w[k] for w in parts]).astype(dtype) if parts else np.zeros((0, *shape), dtype)

        return cls(np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64), cat(0, (N_FEATURES,), np.float64),
                   cat(1, (2,), np.float64), cat(2, (), np.int64), cat(3, (), np.float64))


def along(q: NDArray[np.float64], d: NDArray[np.float64], values: NDArray[np.float64]) -> NDArray[np.float64]:
    """``values`` (n, C), given at the increasing path distances ``d``, interpolated at the distances ``q``."""
    return np.column_stack([np.interp(q, d, values[:, c]) for c in range(values.shape[1])])


def step_features(survey: Survey) -> list[NDArray[np.float64] | None]:
    """Per walk: (n_steps, 3) features at every step (None: no ``/phone/magnetic``). A step without a
    message (the first; one whose interval held no magnetometer sample) takes the nearest message's."""
    out: list[NDArray[np.float64] | None] = []
    for sess in survey:
        m = sess.magnetic
        n = len(sess.steps)
        if m is None or len(m) == 0 or n == 0:
            out.append(None)
            continue
        t = sess.steps.t_ns
        k = np.clip(np.searchsorted(t, m.t_ns), 0, n - 1)
        if n > 1:  # the nearest step in time
            prev = np.maximum(k - 1, 0)
            k = np.where(np.abs(t[prev] - m.t_ns) < np.abs(t[k] - m.t_ns), prev, k)
        b = m.enu
        f = np.column_stack([np.linalg.norm(b, axis=1), np.hypot(b[:, 0], b[:, 1]), b[:, 2]])
        have, first = np.unique(k, return_index=True)  # one message per step: the first
        idx = np.arange(n)
        near = np.clip(np.searchsorted(have, idx), 0, len(have) - 1)
        lower = np.maximum(near - 1, 0)
        near = np.where(np.abs(have[lower] - idx) < np.abs(have[near] - idx), lower, near)
        out.append(f[first][near])
    return out


def walk_sequences(survey: Survey, node_offsets: NDArray[np.int64], sample_m: float) -> MagneticSequences:
    """Every walk's features every ``sample_m`` of its dead-reckoned path (module docstring, 1)."""
    feats = step_features(survey)
    walks: list[tuple[NDArray, NDArray, NDArray, NDArray] | None] = []
    for s, (sess, f) in enumerate(zip(survey, feats)):
        xy = np.asarray(sess.steps.xy)
        if f is None or len(xy) < 2:
            walks.append(None)
            continue
        d_all = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
        # a step's message is the field averaged since the previous step: it belongs mid-way between them
        # (at the step itself, walks matched in opposite directions would be half a step each off the other)
        mid = np.concatenate([[0.0], 0.5 * (d_all[:-1] + d_all[1:])])
        on = np.concatenate([[True], np.diff(mid) > 1e-6])
        # standing still (steps on the spot) is one place: the first step there stands for it
        keep = np.concatenate([[True], np.diff(d_all) > 1e-6])
        d, xy_k, k = d_all[keep], xy[keep], np.flatnonzero(keep)
        if len(d) < 2:
            walks.append(None)
            continue
        q = np.arange(0.0, d[-1] + 1e-9, sample_m)
        step = np.rint(np.interp(q, d, k.astype(float))).astype(np.int64)
        walks.append((along(q, mid[on], f[on]), along(q, d, xy_k), node_offsets[s] + step, q))
    return MagneticSequences.of_walks(walks)


@dataclass(frozen=True, eq=False)
class Windows:
    """Window starts of every walk (global sample index) and their mean-removed descriptors."""

    start: NDArray[np.int64]  # (W,) global sample index of each window's first sample
    walk: NDArray[np.int64]  # (W,)
    x: NDArray[np.float32]  # (W, L, 3) mean-removed features
    energy: NDArray[np.float64]  # (W,) |x|^2


def windows(seq: MagneticSequences, p: MagneticParams) -> Windows:
    L, st = p.window, p.stride
    starts, walks = [], []
    for s in range(seq.n_walks):
        a, b = int(seq.offsets[s]), int(seq.offsets[s + 1])
        if b - a >= L:
            i = np.arange(a, b - L + 1, st)
            starts.append(i)
            walks.append(np.full(len(i), s))
    if not starts:
        z = np.zeros(0, np.int64)
        return Windows(z, z, np.zeros((0, L, N_FEATURES), np.float32), np.zeros(0))
    start, walk = np.concatenate(starts), np.concatenate(walks)
    x = seq.features[start[:, None] + np.arange(L)]  # (W, L, 3)
    x = x - x.mean(axis=1, keepdims=True)
    energy = (x * x).sum(axis=(1, 2))
    return Windows(start, walk, x.astype(np.float32), energy)


@dataclass(frozen=True, eq=False)
class WindowMatches:
    """Each searched (window, other walk): its best match there."""

    window: NDArray[np.int64]  # (M,) index into ``Windows``
    other: NDArray[np.int64]  # (M,) the other walk
    start: NDArray[np.int64]  # (M,) global sample index where the other walk's matched stretch starts
    reverse: NDArray[np.bool_]  # (M,) the window matched the other walk run backwards
    score: NDArray[np.float64]  # (M,) r in [-1, 1]
    sharpness: NDArray[np.float64]  # (M,) score minus the best score of alignments sharp_m or more away

    def __len__(self) -> int:
        return len(self.window)


def _prefix(f: NDArray[np.float64]) -> tuple[NDArray, NDArray]:
    """Prefix sums of the features and of their squares (Q + 1 rows)."""
    z = np.zeros((1, f.shape[1]))
    return np.concatenate([z, np.cumsum(f, axis=0)]), np.concatenate([z[:, 0], np.cumsum((f * f).sum(axis=1))])


def anchored_windows(
    seq: MagneticSequences, win: Windows, p: MagneticParams, anchor_a: NDArray[np.int64], anchor_b: NDArray[np.int64]
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """(window, other walk, forward start) per distinct anchored comparison.

    ``anchor_a``, ``anchor_b``: global sample indices of anchored pairs (a WiFi match: the two places
    may be one). The window of a's walk centred nearest the anchor is compared with the other walk
    around the start ``j0 = anchor_b - (anchor_a - i)`` that keeps the anchor's offset (forward; the
    reversed alignment is derived from it in ``window_matches``). Anchors that ask for the same window
    near the same place are one comparison."""
    L, st, R = p.window, p.stride, p.search
    if len(anchor_a) == 0 or len(win.start) == 0:
        z = np.zeros(0, np.int64)
        return z, z, z
    walk = seq.walk_of()
    wa, wb = walk[anchor_a], walk[anchor_b]
    first_win = np.searchsorted(win.start, seq.offsets[:-1])
    n_win = np.bincount(win.walk, minlength=seq.n_walks)
    ok = n_win[wa] > 0
    anchor_a, anchor_b, wa, wb = anchor_a[ok], anchor_b[ok], wa[ok], wb[ok]
    k = np.clip(np.rint((anchor_a - seq.offsets[wa] - (L - 1) / 2) / st).astype(np.int64), 0, n_win[wa] - 1)
    w = first_win[wa] + k
    j0 = anchor_b - (anchor_a - win.start[w])
    # reversed: a(i + t) ~ b(j + L - 1 - t) with the anchor kept: j = anchor_b - (L - 1 - (anchor_a - i))
    jr = anchor_b - (L - 1 - (anchor_a - win.start[w]))
    q = max(1, R // 2)  # anchors within half the search radius of each other ask for the same comparison
    key = (w * (seq.n_walks + 1) + wb) * (len(seq.features) // q + 3) + (j0 + jr) // (2 * q) + 1
    _, u = np.unique(key, return_index=True)
    return w[u], wb[u], j0[u]


def window_matches(
    seq: MagneticSequences, win: Windows, p: MagneticParams, anchor_a: NDArray[np.int64], anchor_b: NDArray[np.int64],
    features: NDArray[np.float64] | None = None, block: int = 20_000,
) -> WindowMatches:
    """Every anchored (window, other walk)'s best match (module docstring, 2); ``features``: the
    sequences the windows are compared with (default the walks' own; surrogates for the null).

    Each comparison scores the window against the other walk's stretches starting within ``search``
    samples of its anchored start, forwards and reversed: one gather of a segment of ``L + 2 search``
    samples per comparison and one contraction over the window's samples and features against a strided
    view of every alignment (no per-cell copy; 9x faster than ``L`` multiply-adds of one sample each)."""
    L, R = p.window, p.search
    f = seq.features if features is None else features
    w, ob, j0 = anchored_windows(seq, win, p, anchor_a, anchor_b)
    if len(w) == 0:
        z = np.zeros(0, np.int64)
        return WindowMatches(z, z, z, np.zeros(0, bool), np.zeros(0), np.zeros(0))
    S1, S2 = _prefix(f)
    f32 = f.astype(np.float32)
    lags = np.arange(-R, R + 1)
    span = np.arange(L + 2 * R)
    best_s, best_j, best_r = np.empty(len(w)), np.empty(len(w), np.int64), np.empty(len(w), bool)
    best_h = np.empty(len(w))
    gap = max(1, int(round(p.sharp_m / p.sample_m)))
    lo_all, hi_all = seq.offsets[ob], seq.offsets[ob + 1] - L  # valid starts in the other walk
    for a in range(0, len(w), block):
        b = min(len(w), a + block)
        ww, lo, hi = w[a:b], lo_all[a:b], hi_all[a:b]
        x = win.x[ww]  # (n, L, 3)
        out = []
        j_base = j0[a:b]
        start = j_base - R
        idx = np.clip(start[:, None] + span[None, :], 0, len(f) - 1)
        seg = f32[idx]  # (n, L + 2R, 3)
        # every alignment's stretch of the other walk, a view (n, lags, 3, L): one contraction over (t, f)
        stretch = np.lib.stride_tricks.sliding_window_view(seg, L, axis=1)
        for rev in (False, True):
            # reversed: the same stretch (the window, centred on its anchor, read backwards covers
            # the same samples to within a stride), scored against x reversed
            xx = x[:, ::-1] if rev else x
            dot = np.einsum("ntf,nkft->nk", xx, stretch)
            j = j_base[:, None] + lags[None, :]
            valid = (j >= lo[:, None]) & (j <= hi[:, None])
            jc = np.clip(j, 0, len(f) - L)
            s1 = S1[jc + L] - S1[jc]
            ey = (S2[jc + L] - S2[jc]) - (s1 * s1).sum(axis=2) / L
            den = win.energy[ww][:, None] + ey
            r = np.where(valid & (den > 0), 2.0 * dot / np.where(den > 0, den, 1.0), -np.inf)
            k = r.argmax(axis=1)
            # sharpness: how far the best beats every alignment ``gap`` samples or more away from it
            far = np.abs(np.arange(len(lags))[None, :] - k[:, None]) >= gap
            side = np.where(far, r, -np.inf).max(axis=1)
            rk = r[np.arange(b - a), k]
            with np.errstate(invalid="ignore"):
                sharp = np.where(np.isfinite(side), rk - side, 1.0)
            out.append((rk, jc[np.arange(b - a), k], sharp))
        (rf, jf, hf), (rr, jr, hr) = out
        use_r = rr > rf
        best_h[a:b] = np.where(use_r, hr, hf)
        best_s[a:b] = np.where(use_r, rr, rf)
        best_j[a:b] = np.where(use_r, jr, jf)
        best_r[a:b] = use_r
    keep = np.isfinite(best_s)
    w, ob, best_j, best_r, best_s, best_h = w[keep], ob[keep], best_j[keep], best_r[keep], best_s[keep], best_h[keep]
    # several comparisons of one (window, other walk): the best
    key = w * (seq.n_walks + 1) + ob
    order = np.lexsort((-best_s, key))
    first = np.concatenate([[True], key[order][1:] != key[order][:-1]])
    k = order[first]
    return WindowMatches(w[k], ob[k], best_j[k], best_r[k], best_s[k], best_h[k])


def surrogates(seq: MagneticSequences, rng: np.random.Generator) -> NDArray[np.float64]:
    """Phase-randomised copies of every walk's sequence: the same power spectrum (smoothness) per
    feature and the same phase shift for all three (their cross-spectra kept), no place in common."""
    out = seq.features.copy()
    for s in range(seq.n_walks):
        a, b = int(seq.offsets[s]), int(seq.offsets[s + 1])
        if b - a < 4:
            continue
        f = seq.features[a:b]
        mean = f.mean(axis=0)
        z = np.fft.rfft(f - mean, axis=0)
        ph = np.exp(2j * np.pi * rng.random(len(z)))
        ph[0] = 1.0
        if (b - a) % 2 == 0:
            ph[-1] = 1.0  # the Nyquist term stays real
        out[a:b] = np.fft.irfft(z * ph[:, None], n=b - a, axis=0) + mean
    return out


def null_threshold(
    seq: MagneticSequences, win: Windows, p: MagneticParams, anchor_a: NDArray[np.int64], anchor_b: NDArray[np.int64],
    max_anchors: int = 20_000,
) -> float:
    """The ``null_quantile`` of the best score a window reaches against surrogates (module docstring, 3),
    searched exactly as the real matches are (the same anchors, at most ``max_anchors`` of them)."""
    rng = np.random.default_rng(p.seed)
    if len(anchor_a) > max_anchors:
        pick = rng.choice(len(anchor_a), max_anchors, replace=False)
        anchor_a, anchor_b = anchor_a[pick], anchor_b[pick]
    m = window_matches(seq, win, p, anchor_a, anchor_b, features=surrogates(seq, rng))
    if len(m) == 0:
        return 1.0
    return float(np.quantile(m.score, p.null_quantile))


def fingerprint_anchors(
    seq: MagneticSequences, node_i: NDArray[np.int64], node_j: NDArray[np.int64]
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Anchors (global sample pairs) of fingerprint matches given as their step nodes, both
    directions, between walks that both have samples."""
    if len(seq.node) == 0:
        z = np.zeros(0, np.int64)
        return z, z
    walk = seq.walk_of()

    def sample_of(nodes: NDArray[np.int64]) -> NDArray[np.int64]:
        # samples are in node order (walks in order, nodes increasing along each walk)
        k = np.clip(np.searchsorted(seq.node, nodes), 0, len(seq.node) - 1)
        lower = np.maximum(k - 1, 0)
        return np.where(np.abs(seq.node[lower] - nodes) < np.abs(seq.node[k] - nodes), lower, k)

    a, b = sample_of(node_i), sample_of(node_j)
    ok = (np.abs(seq.node[a] - node_i) <= 2) & (np.abs(seq.node[b] - node_j) <= 2) & (walk[a] != walk[b])
    a, b = a[ok], b[ok]
    return np.concatenate([a, b]), np.concatenate([b, a])


@dataclass(frozen=True, eq=False)
class MagneticLinks:
    """Walk pairs the field links, and the step-node pairs behind each (the graph's factors).

    ``translation[k]``: where walk ``b[k]``'s dead reckoning, turned by its rotation, lies relative to
    walk ``a[k]``'s turned by its own: p_world = R_w xy + T_w gives T_b - T_a = ``translation[k]``."""

    a: NDArray[np.int64]  # (K,) walk
    b: NDArray[np.int64]  # (K,) walk, > a
    translation: NDArray[np.float64]  # (K, 2) m, east/north
    windows: NDArray[np.int64]  # (K,) agreeing non-overlapping window matches
    candidates: NDArray[np.int64]  # (K,) the pair's window matches above the threshold, in any translation
    score: NDArray[np.float64]  # (K,) mean score of the agreeing matches
    pair_link: NDArray[np.int64]  # (P,) link of each node pair
    pair_nodes: NDArray[np.int64]  # (P, 2) step nodes (of walk a, of walk b)
    threshold: float = 1.0  # the score a window match needed (``null_threshold``)
    matches: int = 0  # window matches above it

    def __len__(self) -> int:
        return len(self.a)

    @classmethod
    def empty(cls, threshold: float = 1.0) -> "MagneticLinks":
        z = np.zeros(0, np.int64)
        return cls(z, z, np.zeros((0, 2)), z, z, np.zeros(0), z, np.zeros((0, 2), np.int64), threshold, 0)

    @classmethod
    def of_pairs(cls, walks: NDArray[np.int64], pair_link: NDArray[np.int64], pair_nodes: NDArray[np.int64]) -> "MagneticLinks":
        """Links known by their walks and node pairs alone (a previous survey's: ``survey --update``)."""
        k = len(walks)
        z = np.zeros(k, np.int64)
        return cls(walks[:, 0].astype(np.int64), walks[:, 1].astype(np.int64), np.zeros((k, 2)), z, z, np.zeros(k),
                   pair_link.astype(np.int64), pair_nodes.astype(np.int64))

    def __add__(self, other: "MagneticLinks") -> "MagneticLinks":
        """Both sets of links (``other``'s numbered after these)."""
        return MagneticLinks(
            np.concatenate([self.a, other.a]), np.concatenate([self.b, other.b]),
            np.concatenate([self.translation, other.translation]), np.concatenate([self.windows, other.windows]),
            np.concatenate([self.candidates, other.candidates]), np.concatenate([self.score, other.score]),
            np.concatenate([self.pair_link, other.pair_link + len(self)]),
            np.concatenate([self.pair_nodes, other.pair_nodes]), other.threshold, self.matches + other.matches,
        )

    def subset(self, keep: NDArray[np.bool_]) -> "MagneticLinks":
        """The links ``keep`` marks (their node pairs with them)."""
        new = np.cumsum(keep) - 1
        pk = keep[self.pair_link]
        return MagneticLinks(self.a[keep], self.b[keep], self.translation[keep], self.windows[keep],
                             self.candidates[keep], self.score[keep], new[self.pair_link[pk]], self.pair_nodes[pk], self.threshold, self.matches)


def walk_links(
    seq: MagneticSequences, win: Windows, m: WindowMatches, rotation: NDArray[np.float64], threshold: float,
    p: MagneticParams,
) -> MagneticLinks:
    """Links from window matches above ``threshold`` (module docstring, 4); ``rotation`` (S,): each
    walk's rotation from its dead reckoning into east/north (its heading)."""
    L = p.window
    keep = (m.score >= threshold) & (win.energy[m.window] >= L * N_FEATURES * p.min_std_ut**2)
    keep &= m.sharpness >= p.min_sharpness
    w, ob, jb, rev, sc = m.window[keep], m.other[keep], m.start[keep], m.reverse[keep], m.score[keep]
    if len(w) == 0:
        return MagneticLinks.empty(threshold)
    wa = win.walk[w]
    ia = win.start[w]
    # each sample in east/north (translation unknown): its walk's rotation
    walk = seq.walk_of()
    rot = np.where(np.isfinite(rotation), rotation, 0.0)[walk]
    c, s = np.cos(rot), np.sin(rot)
    xy = seq.xy
    xe = np.column_stack([c * xy[:, 0] - s * xy[:, 1], s * xy[:, 0] + c * xy[:, 1]])
    P = np.concatenate([np.zeros((1, 2)), np.cumsum(xe, axis=0)])
    centroid_a = (P[ia + L] - P[ia]) / L
    centroid_b = (P[jb + L] - P[jb]) / L
    # one place: R_a xy_a + T_a = R_b xy_b + T_b, so T_b - T_a = (turned) centroid_a - centroid_b
    t = centroid_a - centroid_b
    # the two stretches must run the same way (forward) or opposite ways (reversed)
    va = xe[ia + L - 1] - xe[ia]
    vb = xe[jb + L - 1] - xe[jb]
    cos = (va * vb).sum(1) / np.maximum(np.linalg.norm(va, axis=1) * np.linalg.norm(vb, axis=1), 1e-9)
    ok = np.where(rev, cos <= -p.direction_cos, cos >= p.direction_cos)
    wa, ob, ia, jb, rev, sc, t = wa[ok], ob[ok], ia[ok], jb[ok], rev[ok], sc[ok], t[ok]
    # one orientation per pair: (lo, hi), translation hi - lo; the window of each side
    flip = wa > ob
    lo, hi = np.where(flip, ob, wa), np.where(flip, wa, ob)
    t = np.where(flip[:, None], -t, t)
    s_lo, s_hi = np.where(flip, jb, ia), np.where(flip, ia, jb)
    pair = lo * seq.n_walks + hi
    order = np.lexsort((-sc, pair))
    bounds = np.flatnonzero(np.concatenate([[True], pair[order][1:] != pair[order][:-1], [True]]))
    links_a, links_b, links_t, links_n, links_c, links_s = [], [], [], [], [], []
    pairs_k, pairs_lo, pairs_hi = [], [], []
    step_pairs = max(1, int(round(p.pair_every_m / p.sample_m)))
    for g0, g1 in zip(bounds[:-1], bounds[1:]):
        idx = order[g0:g1]  # by score, best first
        if len(idx) < p.min_windows:
            continue
        tt = t[idx]
        near = np.linalg.norm(tt[:, None] - tt[None], axis=2) <= p.agree_m
        size = near.sum(axis=1)
        best: list[int] = []
        members = np.zeros(0, np.int64)
        # a match holds a stretch of both walks: two matches are independent when they overlap on neither
        # (``_independent``); a pair of many matches has each match's overlaps as one bit set
        ga, gb = s_lo[idx], s_hi[idx]
        bits = _overlap_bits(ga, gb, L) if len(idx) > GREEDY_BITS_ABOVE else None
        ga_l, gb_l = ga.tolist(), gb.tolist()
        seen: set[bytes] = set()  # agreeing sets already chosen from: the same set, the same choice
        for c0 in np.argsort(-size, kind="stable").tolist():  # the largest agreeing sets first
            if size[c0] <= len(best):
                break  # no smaller set can hold more disjoint matches
            key = near[c0].tobytes()
            if key in seen:
                continue
            seen.add(key)
            agree = np.flatnonzero(near[c0])  # ascending index = descending score
            chosen = _independent(agree.tolist(), ga_l, gb_l, L, bits)
            if len(chosen) > len(best):
                best, members = chosen, agree
        if len(best) < p.min_windows:
            continue
        k = len(links_a)
        sel = idx[best]
        links_a.append(int(lo[sel[0]]))
        links_b.append(int(hi[sel[0]]))
        links_t.append(t[sel].mean(axis=0))
        links_n.append(len(sel))
        links_c.append(len(idx))
        links_s.append(float(sc[sel].mean()))
        # node pairs from every agreeing match (overlapping ones too: they cover the shared stretch), one
        # every ``pair_every_m`` along the first walk, from the best-scoring match there (idx is by score):
        # overlapping matches say the same thing and must not count twice
        tk = np.arange(L)
        us, vs = [], []
        for e in idx[members]:
            us.append(s_lo[e] + tk)
            vs.append(s_hi[e] + (L - 1 - tk if rev[e] else tk))
        u_all, v_all = np.concatenate(us), np.concatenate(vs)
        _, first = np.unique(u_all // step_pairs, return_index=True)
        pairs_k.append(np.full(len(first), k))
        pairs_lo.append(seq.node[u_all[first]])
        pairs_hi.append(seq.node[v_all[first]])
    if not links_a:
        return MagneticLinks.empty(threshold)
    nodes = np.column_stack([np.concatenate(pairs_lo), np.concatenate(pairs_hi)])
    link = np.concatenate(pairs_k)
    _, u = np.unique(nodes[:, 0] * (int(nodes.max()) + 1) + nodes[:, 1], return_index=True)
    u = np.sort(u)
    return MagneticLinks(np.array(links_a, np.int64), np.array(links_b, np.int64), np.array(links_t),
                         np.array(links_n, np.int64), np.array(links_c, np.int64), np.array(links_s), link[u], nodes[u],
                         threshold, int(len(w)))


# matches of one pair of walks above which the greedy choice runs on bit sets (``_overlap_bits``): their
# construction costs more than it saves on the many pairs of a few matches (a crowd of 200: 11.7k pairs;
# 8, 16, 32, 64 measured there and at paper size 12)
GREEDY_BITS_ABOVE = 16


def _overlap_bits(ga: NDArray[np.int64], gb: NDArray[np.int64], L: int) -> list[int]:
    """Per match, the matches it overlaps (on either walk: window starts less than ``L`` apart) as the
    bits of one Python int (bit x: match x; itself included)."""
    conflict = (np.abs(ga[:, None] - ga[None]) < L) | (np.abs(gb[:, None] - gb[None]) < L)
    packed = np.packbits(conflict, axis=1, bitorder="little")
    return [int.from_bytes(row.tobytes(), "little") for row in packed]


def _independent(agree: list[int], ga: list[int], gb: list[int], L: int, bits: list[int] | None) -> list[int]:
    """Greedily, in ``agree``'s order (best score first), the matches overlapping none chosen before
    (window starts ``ga``, ``gb`` on the two walks, ``L`` long); ``bits``: ``_overlap_bits``, or None to
    compare the starts (the same choice)."""
    chosen: list[int] = []
    if bits is not None:
        blocked = 0  # matches overlapping a chosen one
        for q in agree:
            if not (blocked >> q) & 1:
                chosen.append(q)
                blocked |= bits[q]
        return chosen
    for q in agree:
        a, b = ga[q], gb[q]
        if all(abs(ga[x] - a) >= L and abs(gb[x] - b) >= L for x in chosen):
            chosen.append(q)
    return chosen


def factor_pairs(
    links: MagneticLinks, dr_xy: NDArray[np.float64], node_walk: NDArray[np.int64], place_m: float, per_place: int,
) -> NDArray[np.bool_]:
    """Which of ``links``' node pairs become factors: each place (``place_m`` of a walk's dead-reckoned
    path; ``dr_xy``, ``node_walk``: every step node's) keeps the ``per_place`` pair ends there of the
    best-scoring links, and a pair stays when either end's place keeps it. A route walked n times would otherwise tie each of its places to the
    n - 1 others: factors growing with the square of the walks over one corridor (a crowd of 200
    walks: as many magnetic factors as WiFi edges), where a few partners per place hold it as well."""
    pn = links.pair_nodes
    keep = np.zeros(len(pn), bool)
    if not len(pn):
        return keep
    step = np.linalg.norm(np.diff(dr_xy, axis=0), axis=1) * (np.diff(node_walk) == 0)
    path = np.concatenate([[0.0], np.cumsum(step)])
    path -= np.maximum.accumulate(np.where(np.concatenate([[True], np.diff(node_walk) != 0]), path, -np.inf))  # per walk
    bin_ = (path // place_m).astype(np.int64)
    # both ends of every pair, ranked together at their place: best link first
    end = pn.T.ravel()
    pair = np.tile(np.arange(len(pn)), 2)
    place = node_walk[end].astype(np.int64) * (int(bin_.max()) + 1) + bin_[end]
    order = np.lexsort((links.pair_link[pair], -links.score[links.pair_link[pair]], place))
    p = place[order]
    first = np.concatenate([[True], p[1:] != p[:-1]])
    rank = np.arange(len(p)) - np.maximum.accumulate(np.where(first, np.arange(len(p)), 0))
    keep[pair[order[rank < per_place]]] = True
    return keep


def magnetic_links(
    survey: Survey, node_offsets: NDArray[np.int64], rotation: NDArray[np.float64],
    match_node_i: NDArray[np.int64], match_node_j: NDArray[np.int64], p: MagneticParams,
) -> MagneticLinks:
    """The survey's magnetic links (module docstring): sequences, anchored window matches, the
    threshold from surrogates, links. ``match_node_i/j``: step nodes of fingerprint matches (WiFi)."""
    seq = walk_sequences(survey, node_offsets, p.sample_m)
    if seq.has_field().sum() < 2:
        return MagneticLinks.empty()
    win = windows(seq, p)
    aa, ab = fingerprint_anchors(seq, match_node_i, match_node_j)
    threshold = null_threshold(seq, win, p, aa, ab)
    m = window_matches(seq, win, p, aa, ab)
    links = walk_links(seq, win, m, rotation, threshold, p)
    log.info("magnetic: %d walks with the field, %d window matches above %.3f (the surrogates' %g quantile), "
             "%d links", int(seq.has_field().sum()), links.matches, threshold, p.null_quantile, len(links))
    return links


@dataclass(frozen=True, eq=False)
class LinkUnits:
    """Walks the magnetic links hold together as rigid bodies ("units"), placed relative to each other.

    Every walk is in one unit (a walk no link holds is a unit of its own). ``transforms[s]`` takes walk
    ``s``'s dead reckoning into its unit's frame: east/north (the walks' headings), origin where the
    unit's seed walk's turned dead reckoning has it."""

    unit: NDArray[np.int64]  # (S,)
    transforms: NDArray[np.float64]  # (S, 3) x, y, theta
    seed: NDArray[np.int64]  # (U,) each unit's seed walk
    links: MagneticLinks  # the links the units are made of (verified, consistent with the placement)

    @property
    def n_units(self) -> int:
        return len(self.seed)

    def walks_of(self, u: int) -> NDArray[np.int64]:
        return np.flatnonzero(self.unit == u)

    def turned(self, angle: float) -> "LinkUnits":
        """The same units with every unit frame turned by ``angle`` (rad) about its origin."""
        c, s = np.cos(angle), np.sin(angle)
        T = self.transforms
        out = np.column_stack([c * T[:, 0] - s * T[:, 1], s * T[:, 0] + c * T[:, 1],
                               np.arctan2(np.sin(T[:, 2] + angle), np.cos(T[:, 2] + angle))])
        return LinkUnits(self.unit, out, self.seed, self.links)


def singleton_units(rotation: NDArray[np.float64]) -> LinkUnits:
    """Every walk a unit of its own, turned by its ``rotation`` (no magnetic links)."""
    n = len(rotation)
    rot = np.where(np.isfinite(rotation), rotation, 0.0)
    return LinkUnits(np.arange(n, dtype=np.int64), np.column_stack([np.zeros(n), np.zeros(n), rot]),
                     np.arange(n, dtype=np.int64), MagneticLinks.empty())


def link_units(
    links: MagneticLinks, n_walks: int, rotation: NDArray[np.float64], rotation_sigma: NDArray[np.float64],
    node_xy: NDArray[np.float64], node_walk: NDArray[np.int64], agree_m: float, refine: "GrowthParams",
    max_pairs: int = 12,
) -> LinkUnits:
    """Units from verified links: translations by least squares over each connected set of walks (one
    walk held), then every walk's rotation and translation refined on the links' node pairs (a rigid
    refinement, rotations held near the headings); a link whose pairs the result leaves more than
    ``agree_m`` apart on average is dropped and the units are formed again."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from graphslam.core.survey.placement import refine_rigid

    rot = np.where(np.isfinite(rotation), rotation, 0.0)
    # work on the dead reckoning turned by the headings: the refinement holds rotations near 0 there
    c, s_ = np.cos(rot[node_walk]), np.sin(rot[node_walk])
    turned = np.column_stack([c * node_xy[:, 0] - s_ * node_xy[:, 1], s_ * node_xy[:, 0] + c * node_xy[:, 1]])
    while True:
        g = coo_matrix((np.ones(len(links)), (links.a, links.b)), shape=(n_walks, n_walks))
        n_units, unit = connected_components(g, directed=False)
        degree = np.bincount(np.concatenate([links.a, links.b]), minlength=n_walks)
        T = np.zeros((n_walks, 3))  # turned dead reckoning -> unit frame
        seeds = np.zeros(n_units, np.int64)
        for u in range(n_units):
            walks = np.flatnonzero(unit == u)
            seeds[u] = walks[np.argmax(degree[walks])]
            if len(walks) == 1:
                continue
            col = np.full(n_walks, -1, np.int64)
            free = walks[walks != seeds[u]]
            col[free] = np.arange(len(free))
            inside = np.flatnonzero(unit[links.a] == u)
            A = np.zeros((len(inside), len(free)))
            r = np.arange(len(inside))
            ca, cb = col[links.a[inside]], col[links.b[inside]]
            A[r[cb >= 0], cb[cb >= 0]] += 1.0
            A[r[ca >= 0], ca[ca >= 0]] -= 1.0
            sol = np.linalg.lstsq(A, links.translation[inside], rcond=None)[0]  # T_b - T_a = translation
            T[free, :2] = sol
        if len(links):
            # the refinement on at most ``max_pairs`` pairs of each link, spread along it (a rigid body's
            # pose needs few; a large survey has tens of thousands)
            rank = np.arange(len(links.pair_link)) - np.searchsorted(np.sort(links.pair_link), links.pair_link)
            count = np.bincount(links.pair_link, minlength=len(links))[links.pair_link]
            spread = (rank * max_pairs) // np.maximum(count, 1)
            use = np.concatenate([[True], (spread[1:] != spread[:-1]) | (links.pair_link[1:] != links.pair_link[:-1])])
            pa, pb = links.pair_nodes[use, 0], links.pair_nodes[use, 1]
            pts = np.concatenate([turned[pa], turned[pb]])
            sess = np.concatenate([node_walk[pa], node_walk[pb]])
            i = np.arange(len(pa))
            multi = np.flatnonzero(np.bincount(unit, minlength=n_units)[unit] > 1)
            T = refine_rigid(T, multi, seeds, sess, pts, i, i + len(pa), np.ones(len(pa)), refine, rotation_sigma)
            pa, pb = links.pair_nodes[:, 0], links.pair_nodes[:, 1]
            gap = np.linalg.norm(_apply(T, node_walk[pa], turned[pa]) - _apply(T, node_walk[pb], turned[pb]), axis=1)
            per_link = np.bincount(links.pair_link, weights=gap, minlength=len(links)) / np.maximum(
                np.bincount(links.pair_link, minlength=len(links)), 1)
            bad = per_link > agree_m
            if bad.any():
                log.info("magnetic: %d links disagree with their units' placement, dropped", int(bad.sum()))
                links = links.subset(~bad)
                continue
        # dead reckoning -> unit frame: the turn by the heading, then T
        out = np.column_stack([T[:, 0], T[:, 1], np.arctan2(np.sin(rot + T[:, 2]), np.cos(rot + T[:, 2]))])
        return LinkUnits(unit.astype(np.int64), out, seeds, links)


def _apply(T: NDArray, walk: NDArray[np.int64], xy: NDArray) -> NDArray:
    c, s = np.cos(T[walk, 2]), np.sin(T[walk, 2])
    return np.column_stack([c * xy[:, 0] - s * xy[:, 1] + T[walk, 0], s * xy[:, 0] + c * xy[:, 1] + T[walk, 1]])
