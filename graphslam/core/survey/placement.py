"""Global placement of walks by map growth: ``optimizer.initialization: growth``.

Every walk is a rigid body (its dead reckoning is good over one walk: IPIN 2023 phone PDR
rigidly fitted to its own landmarks is at 1.4 m). Each fingerprint's ``k`` most similar
fingerprints of *other* walks (power-cosine similarity, ``graphslam.core.radiomap.similarity``)
are its matches. The map starts from the walk with the most match weight and grows one
walk at a time:

1. every unplaced walk with matches into the placed walks is registered onto them by
   Hough voting over SE(2): for each rotation (``rotation_step_deg``), each match votes
   for the translation that puts the two fingerprints together, weighted by
   similarity^``weight_power``; votes are blurred by ``blur_m`` (WiFi resolves a few
   metres) and the best cell is the walk's candidate placement. All rotations are voted
   in one vectorised pass (one ``bincount`` over rotation x cell);
2. the candidate with the largest *margin* is placed: support of its best placement minus
   that of the best placement that moves the walk by more than ``distinct_m`` on average
   (a walk that matches equally well in two places is not placed on either);
3. all placed walks are refined jointly (matched fingerprints pulled together, Cauchy loss
   of scale ``refine_scale_m``; Gauss-Newton on the 3W x 3W normal equations, analytic Jacobian).

Why matches come from the whole survey, not from the placed walks only: a walk whose true
partners are not placed yet then has few matches into the map and waits, instead of being
forced onto the most similar place among the placed walks (measured: forcing places whole
routes 10-40 m off on IPIN). A walk stops being a candidate when its margin is below
``min_margin``; it is reported unplaced with the reason.

Per-walk figures for the report (no ground truth): ``support`` (vote weight of the chosen
placement per fingerprint), ``margin`` (relative to the runner-up placement) and
``consistency`` (fraction of the walk's match weight into other placed walks whose partners
end within ``consistent_m``).

Cost: one Hough registration per (walk, round) where the walk's matches into the map
changed; vote grids are bounded by the map's extent / ``cell_m``.
"""

from __future__ import annotations

import logging
from contextlib import AbstractContextManager
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import gaussian_filter
from threadpoolctl import ThreadpoolController

from graphslam.config import GraphSlamConfig
from graphslam.core.progress import Task
from graphslam.core.radiomap.similarity import Matches
from graphslam.core.survey.initialise import se2_apply

log = logging.getLogger(__name__)

_POOLS: list[ThreadpoolController] = []  # the thread pools loaded, scanned once: a scan costs ~0.6 ms per join


def _one_thread() -> AbstractContextManager[object]:
    """A context holding every BLAS / OpenMP pool at one thread (the joins' 3W x 3W systems: threads only
    add overhead)."""
    if not _POOLS:
        _POOLS.append(ThreadpoolController())
    return _POOLS[0].limit(limits=1)


@dataclass(frozen=True)
class GrowthParams:
    """Map-growth settings (m, degrees). Defaults chosen on IPIN 2023 floor -2 and the simulator."""

    weight_power: float = 4.0  # vote weight = similarity ** weight_power (favours near-identical scans)
    rotation_step_deg: float = 3.0
    cell_m: float = 1.0
    blur_m: float = 1.5
    distinct_m: float = 5.0  # a runner-up placement must move the walk this much on average
    min_margin: float = 0.25  # vote weight; below this a walk is not placed
    refine_scale_m: float = 3.0
    refine_max_evaluations: int = 10  # Gauss-Newton iterations per refinement (each start is already close)
    consistent_m: float = 6.0
    max_grid_cells: int = 1_000_000  # rotations x cells of one vote grid (bounds memory and blur time)
    # beyond this many placed walks a join refines the new walk alone (the rest held), and every placed
    # walk together only when the map has grown by half since the last such refinement and at the
    # end: the joint refinement costs O(matches of the map) per join; and a walk the join matched
    # votes again only when its matches into the map grew by a quarter or it is the next to join
    full_refine_walks: int = 24
    # walks already rotated into a common frame (the phones' headings): rotations searched only
    # within +-rotation_window_deg of it, and the refinement holds each walk's rotation near 0
    # with its own sigma (``grow_placement(rotation_sigma=...)``); None: every rotation
    rotation_window_deg: float | None = None
    # margin per fingerprint of the joining walk (a long walk collects more votes, right or wrong:
    # its margin is compared per fingerprint, so one threshold fits short and long walks)
    margin_per_fingerprint: bool = False

    @classmethod
    def from_config(cls, cfg: "GraphSlamConfig", **override: object) -> "GrowthParams":
        """From the ``placement`` section (``override``: e.g. the heading placement's margin and window)."""
        pc = cfg.placement
        base = dict(
            weight_power=pc.weight_power, rotation_step_deg=pc.rotation_step_deg, blur_m=pc.blur_m,
            distinct_m=pc.distinct_m, min_margin=pc.min_margin, refine_scale_m=pc.refine_scale_m,
            consistent_m=pc.consistent_m,
        )
        return cls(**{**base, **override})  # type: ignore[arg-type]


@dataclass(frozen=True, eq=False)
class GrowthResult:
    """Per-walk transforms (x, y, theta) from dead-reckoning frame to the seed walk's frame."""

    transforms: NDArray[np.float64]  # (S, 3)
    placed: NDArray[np.bool_]  # (S,)
    seed: int
    order: tuple[int, ...]  # walks in the order they were placed (seed first)
    support: NDArray[np.float64]  # (S,) vote weight per fingerprint of the chosen placement (NaN: unplaced)
    margin: NDArray[np.float64]  # (S,) support minus runner-up support, vote weight (seed: inf)
    consistency: NDArray[np.float64]  # (S,) see module docstring (NaN: unplaced or no match)
    reasons: dict[int, str]  # unplaced walk -> why


def hough_se2(
    src_xy: NDArray, dst_xy: NDArray, weight: NDArray, params: GrowthParams
) -> tuple[NDArray, float, float]:
    """Rigid T maximising the blurred vote of matched point pairs (src_i -> dst_i).

    Returns (T, support, runner-up support): ``T`` maps ``src`` onto ``dst``; the runner-up
    is the best placement per rotation whose mean displacement of the matched source points
    exceeds ``distinct_m``.
    """
    if params.rotation_window_deg is None:
        thetas = np.radians(np.arange(0.0, 360.0, params.rotation_step_deg))
    else:
        k = int(np.floor(params.rotation_window_deg / params.rotation_step_deg))
        thetas = np.radians(np.arange(-k, k + 1) * params.rotation_step_deg)
    votes, lo, cell, shape = _vote_grid(src_xy, thetas, dst_xy, weight, params)
    n_rot = len(thetas)
    per_rot = votes.reshape(n_rot, -1)
    best_cell = per_rot.argmax(axis=1)
    best_val = per_rot[np.arange(n_rot), best_cell]
    r0 = int(best_val.argmax())
    cand = np.column_stack([lo[0] + (best_cell // shape[1] + 0.5) * cell,
                            lo[1] + (best_cell % shape[1] + 0.5) * cell, thetas])
    T = cand[r0]
    # runner-up: best other rotation's peak that moves the walk, or the best cell of the same
    # rotation outside the distinct radius
    # x and y apart (contiguous (R, n) arrays; the same sums as a norm over a stacked last axis)
    sx, sy = src_xy[:, 0], src_xy[:, 1]
    c0, s0 = np.cos(thetas[r0:r0 + 1]), np.sin(thetas[r0:r0 + 1])
    bx, by = c0 * sx - s0 * sy + T[0], s0 * sx + c0 * sy + T[1]
    moved = np.empty(n_rot)
    for a, b in _chunks(n_rot, len(src_xy)):
        c, s = np.cos(thetas[a:b])[:, None], np.sin(thetas[a:b])[:, None]
        dx = c * sx - s * sy + cand[a:b, 0:1] - bx
        dy = s * sx + c * sy + cand[a:b, 1:2] - by
        moved[a:b] = np.sqrt(dx * dx + dy * dy).mean(1)
    others = best_val[moved > params.distinct_m]
    second = float(others.max()) if len(others) else 0.0
    grid = votes[r0].copy()
    cx, cy = best_cell[r0] // shape[1], best_cell[r0] % shape[1]
    rad = int(np.ceil(params.distinct_m / cell))
    grid[max(0, cx - rad): cx + rad + 1, max(0, cy - rad): cy + rad + 1] = 0.0
    second = max(second, float(grid.max()))
    return T, float(best_val[r0]), second


_CHUNK = 1 << 16  # rotated points per pass: temporaries stay in cache instead of fresh pages


def _chunks(n_rot: int, n_points: int) -> list[tuple[int, int]]:
    """Rotation ranges of at most ``_CHUNK`` rotated points (at least one rotation each)."""
    step = max(1, _CHUNK // max(n_points, 1))
    return [(a, min(n_rot, a + step)) for a in range(0, n_rot, step)]


def _vote_grid(
    src_xy: NDArray, thetas: NDArray, dst_xy: NDArray, weight: NDArray, params: GrowthParams
) -> tuple[NDArray, NDArray, float, NDArray]:
    """(votes (R, nx, ny) blurred, grid origin, cell, shape): each source point rotated by each of
    ``thetas`` votes, with its weight, for the translation that puts it on its destination; per
    cell_m^2 of translation. Rotations are taken a chunk at a time (same sums, bounded temporaries)."""
    n_rot = len(thetas)
    chunks = _chunks(n_rot, len(src_xy))
    c, s = np.cos(thetas)[:, None], np.sin(thetas)[:, None]
    sx, sy, dx, dy = src_xy[:, 0], src_xy[:, 1], dst_xy[:, 0], dst_xy[:, 1]

    def translations(a: int, b: int) -> tuple[NDArray, NDArray]:  # (b - a, M) each, x and y apart (contiguous)
        return dx - (c[a:b] * sx - s[a:b] * sy), dy - (s[a:b] * sx + c[a:b] * sy)

    lo, hi = np.full(2, np.inf), np.full(2, -np.inf)
    for a, b in chunks:  # the translations' extent
        tx, ty = translations(a, b)
        lo = np.minimum(lo, [tx.min(), ty.min()])
        hi = np.maximum(hi, [tx.max(), ty.max()])
    lo, hi = lo - 3.0 * params.blur_m, hi + 3.0 * params.blur_m
    shape = np.ceil((hi - lo) / params.cell_m).astype(int) + 1
    if n_rot * shape[0] * shape[1] > params.max_grid_cells:
        # very spread votes: coarser cells keep the grid bounded (resolution degrades, memory does not)
        cell = params.cell_m * np.sqrt(n_rot * shape[0] * shape[1] / params.max_grid_cells)
    else:
        cell = params.cell_m
    shape = np.ceil((hi - lo) / cell).astype(int) + 1
    per = int(shape[0] * shape[1])
    votes = np.empty((n_rot, per))
    for a, b in chunks:
        tx, ty = translations(a, b)
        gx = np.floor((tx - lo[0]) / cell).astype(np.int64)
        gy = np.floor((ty - lo[1]) / cell).astype(np.int64)
        flat = (np.arange(b - a)[:, None] * shape[0] + gx) * shape[1] + gy
        votes[a:b] = np.bincount(flat.ravel(), weights=np.broadcast_to(weight, flat.shape).ravel(),
                                 minlength=(b - a) * per).reshape(b - a, per)
    votes = votes.reshape(n_rot, shape[0], shape[1])
    votes = gaussian_filter(votes, sigma=(0.0, params.blur_m / cell, params.blur_m / cell), mode="constant", truncate=3.0)
    # per cell_m^2 of translation, so support and margins mean the same whatever cell a wide grid took
    votes *= (params.cell_m / cell) ** 2
    return votes, lo, float(cell), shape


def hough_profile(src_xy: NDArray, dst_xy: NDArray, weight: NDArray, thetas: NDArray, params: GrowthParams) -> NDArray:
    """Per rotation of ``thetas``: the best translation's blurred vote (``hough_se2``'s grid)."""
    votes, _, _, _ = _vote_grid(src_xy, thetas, dst_xy, weight, params)
    return votes.reshape(len(thetas), -1).max(axis=1)


def refine_rigid(
    transforms: NDArray, walks: NDArray, fixed: int | NDArray, scan_session: NDArray, scan_xy: NDArray,
    i: NDArray, j: NDArray, w: NDArray, params: GrowthParams, rotation_sigma: NDArray | None = None,
) -> NDArray:
    """Jointly refine the transforms of ``walks`` (``fixed`` held) so matched fingerprints coincide.

    Gauss-Newton with iteratively reweighted Cauchy weights on each match's 2-D gap (scale
    ``refine_scale_m``): residual r_m = p_i(T_a) - p_j(T_b), Jacobian d r / d(x, y, theta) of each
    walk analytic; the normal equations are 3W x 3W (W walks, small), so they are assembled
    from sparse per-match blocks and solved densely (Levenberg damping on failure).
    ``fixed``: the walk (or walks) held; ``rotation_sigma`` (S,): a Gaussian prior holding each
    walk's rotation near 0 (walks pre-rotated by their headings).
    """
    held = set(np.atleast_1d(fixed).tolist())
    free = np.array([s for s in walks if s not in held], dtype=np.int64)
    if len(free) == 0 or len(i) == 0:
        return transforms
    col = np.full(len(transforms), -1, np.int64)
    col[free] = np.arange(len(free))
    sa, sb = scan_session[i], scan_session[j]
    # x and y apart: contiguous 1-D arrays (reductions over a length-2 axis cost more than the maths)
    pax, pay, pbx, pby = scan_xy[i, 0], scan_xy[i, 1], scan_xy[j, 0], scan_xy[j, 1]
    c2 = params.refine_scale_m**2

    def place(T: NDArray, cw: NDArray, sw: NDArray, s: NDArray, px: NDArray, py: NDArray) -> tuple[NDArray, ...]:
        c, sn = cw[s], sw[s]  # the walks' cos / sin of rotation, per match
        return (c * px - sn * py + T[s, 0], sn * px + c * py + T[s, 1],  # position
                -sn * px - c * py, c * px - sn * py)  # d position / d theta

    # in the matches' units (w e^2, m^2, for gaps well inside the Cauchy scale): a walk's rotation
    # prior weighs as much as one full-weight match whose gap is c * theta / sigma
    prior_w = None if rotation_sigma is None else c2 / rotation_sigma[free] ** 2

    def cost(T: NDArray) -> tuple[float, tuple[NDArray, ...]]:
        cw, sw = np.cos(T[:, 2]), np.sin(T[:, 2])
        qax, qay, dax, day = place(T, cw, sw, sa, pax, pay)
        qbx, qby, dbx, dby = place(T, cw, sw, sb, pbx, pby)
        rx, ry = qax - qbx, qay - qby
        e2 = rx * rx + ry * ry
        f = float(np.dot(w, np.log1p(e2 / c2))) * c2
        if prior_w is not None:
            f += float((prior_w * T[free, 2] ** 2).sum())
        return f, (dax, day, dbx, dby, rx, ry, e2)

    T = transforms.copy()
    f, lin = cost(T)
    lam = 1e-6
    normal_equations = _NormalEquations(len(free), col[sa], col[sb])  # column block of each match's walks (-1: held)
    for _ in range(params.refine_max_evaluations):
        irls = w / (1.0 + lin[6] / c2)  # Cauchy weight of each match
        H, g = normal_equations(*lin[:6], irls)
        if prior_w is not None:  # the rotation prior (H, g in the same half-gradient units as the matches')
            H[3 * np.arange(len(free)) + 2, 3 * np.arange(len(free)) + 2] += prior_w
            g[3 * np.arange(len(free)) + 2] += prior_w * T[free, 2]
        while True:
            step = np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-9), -g)
            T_new = T.copy()
            T_new[free] += step.reshape(-1, 3)
            f_new, lin_new = cost(T_new)
            if f_new <= f:
                break
            lam *= 10.0
            if lam > 1e6:
                return T
        lam = max(lam / 10.0, 1e-9)
        converged = f - f_new <= 1e-9 * max(f, 1.0) or np.abs(step).max() < 1e-4
        T, f, lin = T_new, f_new, lin_new
        if converged:
            break
    return T


class _NormalEquations:
    """J^T W J (3F x 3F) and J^T W r of the matches' 2-D gaps, summed per pair of walks.

    Match m's gap r = p_a - p_b has d r / d(x, y, theta) = s [I | d] with s = +1, d = d_a for walk a
    and s = -1, d = d_b for walk b (``d``: d p / d theta); a held walk (column -1) has no block.
    J_1^T J_2 = s_1 s_2 [[1, 0, d_2x], [0, 1, d_2y], [d_1x, d_1y, d_1 . d_2]]: six sums per pair of
    walks. The matches' walks are fixed over a refinement, so every (side, side) term of every match
    is indexed once here and each evaluation is one ``bincount`` per sum (O(matches), no sparse matrix)."""

    def __init__(self, n_free: int, ka: NDArray, kb: NDArray) -> None:
        m = len(ka)
        self.n_free = n_free
        k = np.concatenate([ka, kb])  # side rows: a-sides then b-sides
        sign = np.concatenate([np.ones(m), -np.ones(m)])
        match = np.concatenate([np.arange(m), np.arange(m)])
        free = np.flatnonzero(k >= 0)
        self.g_k, self.g_row, self.g_sign, self.g_match = k[free], free, sign[free], match[free]
        # a match's side with itself adds to its walk's diagonal block: those terms are the free side rows
        # above (e_1 = e_2, s_1 s_2 = 1); the two sides together add to the off-diagonal blocks of their
        # walks, or to a diagonal one for a match inside one walk (then every term is summed generically,
        # to keep each block's sum in one order)
        both = np.flatnonzero((ka >= 0) & (kb >= 0))
        self.split = not bool((ka[both] == kb[both]).any())
        row1, row2 = [], []
        for s1 in (0, m):
            for s2 in (0, m):
                if self.split and s1 == s2:
                    continue
                pick = both if s1 != s2 else np.flatnonzero(k[s1:s1 + m] >= 0)
                row1.append(pick + s1)
                row2.append(pick + s2)
        self.row1, self.row2 = np.concatenate(row1), np.concatenate(row2)
        self.h_sign, self.h_match = sign[self.row1] * sign[self.row2], match[self.row1]
        self.pair = k[self.row1] * n_free + k[self.row2]

    def __call__(self, dax: NDArray, day: NDArray, dbx: NDArray, dby: NDArray, rx: NDArray, ry: NDArray,
                 wt: NDArray) -> tuple[NDArray, NDArray]:
        """(H, g) at one linearisation: ``d*``: d p / d theta of each match's ends, ``r*``: its gap."""
        nf = self.n_free
        dx, dy = np.concatenate([dax, dbx]), np.concatenate([day, dby])

        def acc(index: NDArray, v: NDArray, n: int) -> NDArray:
            return np.bincount(index, weights=v, minlength=n)

        ww = self.h_sign * wt[self.h_match]
        e1x, e1y, e2x, e2y = dx[self.row1], dy[self.row1], dx[self.row2], dy[self.row2]
        H = np.zeros((nf, nf, 3, 3))
        one = acc(self.pair, ww, nf * nf).reshape(nf, nf)
        H[:, :, 0, 0] = one
        H[:, :, 1, 1] = one
        H[:, :, 0, 2] = acc(self.pair, ww * e2x, nf * nf).reshape(nf, nf)
        H[:, :, 1, 2] = acc(self.pair, ww * e2y, nf * nf).reshape(nf, nf)
        H[:, :, 2, 0] = acc(self.pair, ww * e1x, nf * nf).reshape(nf, nf)
        H[:, :, 2, 1] = acc(self.pair, ww * e1y, nf * nf).reshape(nf, nf)
        H[:, :, 2, 2] = acc(self.pair, ww * (e1x * e2x + e1y * e2y), nf * nf).reshape(nf, nf)
        ws = wt[self.g_match]
        ex, ey = dx[self.g_row], dy[self.g_row]
        if self.split:  # the diagonal blocks' side-with-itself terms (the off-diagonal sums add nothing there)
            d = np.arange(nf)
            one = acc(self.g_k, ws, nf)
            H[d, d, 0, 0] += one
            H[d, d, 1, 1] += one
            t0, t1 = acc(self.g_k, ws * ex, nf), acc(self.g_k, ws * ey, nf)
            H[d, d, 0, 2] += t0
            H[d, d, 2, 0] += t0
            H[d, d, 1, 2] += t1
            H[d, d, 2, 1] += t1
            H[d, d, 2, 2] += acc(self.g_k, ws * (ex * ex + ey * ey), nf)
        w = self.g_sign * ws
        wrx, wry = w * rx[self.g_match], w * ry[self.g_match]
        g = np.column_stack([acc(self.g_k, wrx, nf), acc(self.g_k, wry, nf),
                             acc(self.g_k, wrx * ex + wry * ey, nf)])
        return H.transpose(0, 2, 1, 3).reshape(3 * nf, 3 * nf), g.reshape(3 * nf)


def _normal_equations(
    n_free: int, ka: NDArray, kb: NDArray, da: NDArray, db: NDArray, r: NDArray, wt: NDArray
) -> tuple[NDArray, NDArray]:
    """``_NormalEquations(n_free, ka, kb)``, evaluated once (``d*``, ``r``: (M, 2))."""
    return _NormalEquations(n_free, ka, kb)(da[:, 0], da[:, 1], db[:, 0], db[:, 1], r[:, 0], r[:, 1], wt)


def grow_placement(
    n_sessions: int,
    scan_session: NDArray[np.int64],
    scan_xy: NDArray[np.float64],
    matches: Matches,
    params: GrowthParams = GrowthParams(),
    seed: int | None = None,
    *,
    initial: dict[int, NDArray] | None = None,
    candidates: NDArray[np.bool_] | None = None,
    rotation_sigma: NDArray | None = None,
) -> GrowthResult:
    """Place walks by map growth (module docstring). ``scan_xy``: fingerprint positions in
    their walk's dead-reckoning frame; ``matches`` index fingerprints.

    ``initial``: walks already placed (walk -> transform), held fixed — e.g. tied to control
    points; the map grows from them instead of from one seed. ``candidates``: only these
    walks take part (the others' matches are ignored). ``rotation_sigma``: see ``refine_rigid``."""
    use = np.ones(n_sessions, bool) if candidates is None else np.asarray(candidates, bool).copy()
    if initial:
        use[list(initial)] = True
    keep = use[scan_session[matches.i]] & use[scan_session[matches.j]]
    mi, mj = matches.i[keep], matches.j[keep]
    mw = np.power(np.clip(matches.similarity[keep], 0.0, 1.0), params.weight_power)
    si, sj = scan_session[mi], scan_session[mj]
    mass = np.bincount(si, weights=mw, minlength=n_sessions) + np.bincount(sj, weights=mw, minlength=n_sessions)
    if initial:
        seed = int(next(iter(initial)))
    elif seed is None:
        seed = int(np.where(use, mass, -1.0).argmax())
    held = np.array(sorted(initial), np.int64) if initial else np.array([seed], np.int64)
    n_scans = np.bincount(scan_session, minlength=n_sessions).astype(float)
    T = np.zeros((n_sessions, 3))
    placed = np.zeros(n_sessions, bool)
    placed[held] = True
    for k, Tk in (initial or {}).items():
        T[k] = Tk
    support = np.full(n_sessions, np.nan)
    margin = np.full(n_sessions, np.nan)
    margin[held] = np.inf
    order = held.tolist()
    world = np.full_like(scan_xy, np.nan)  # fingerprint positions of placed walks, seed frame
    by_walk = [np.flatnonzero(scan_session == s) for s in range(n_sessions)]
    for k in held.tolist():
        world[by_walk[k]] = se2_apply(T[k], scan_xy[by_walk[k]])
    # both directions of every match: (fingerprint of walk b, partner elsewhere, weight)
    ab_src = np.concatenate([mi, mj])
    ab_dst = np.concatenate([mj, mi])
    ab_w = np.concatenate([mw, mw])
    ab_walk = scan_session[ab_src]
    ab_other = scan_session[ab_dst]
    order_src = np.argsort(ab_walk, kind="stable")
    bounds = np.searchsorted(ab_walk[order_src], np.arange(n_sessions + 1))
    cache: dict[int, tuple[float, float, NDArray, float]] = {}  # walk -> (margin, support, T, n votes)
    stale = set(np.flatnonzero(use).tolist())
    last_full = len(held)  # placed walks at the last joint refinement
    dirty: set[int] = set()  # walks whose cached vote predates joins that matched them

    def _vote(b: int, sel: NDArray) -> tuple[float, float, NDArray, float]:
        Tb, best, second = hough_se2(scan_xy[ab_src[sel]], world[ab_dst[sel]], ab_w[sel], params)
        mg = (best - second) / max(n_scans[b], 1.0) if params.margin_per_fingerprint else best - second
        return mg, best, Tb, float(len(sel))
    with Task("place walks", total=int(use.sum()) - len(held), unit="walks") as task:
        while True:
            for b in list(stale):
                stale.discard(b)
                if placed[b]:
                    continue
                sel = order_src[bounds[b]:bounds[b + 1]]
                sel = sel[placed[ab_other[sel]]]
                if len(sel) < 3:
                    cache.pop(b, None)
                    dirty.discard(b)
                    continue
                if placed.sum() > params.full_refine_walks and b in cache and len(sel) < 1.25 * cache[b][3]:
                    dirty.add(b)  # a large map: votes again when it could be chosen, or its matches grew by a quarter
                    continue
                cache[b] = _vote(b, sel)
                dirty.discard(b)
            if not cache:
                break
            while True:  # the walk chosen is voted on the current map
                b = max(cache, key=lambda s: cache[s][0])
                if b not in dirty:
                    break
                dirty.discard(b)
                sel = order_src[bounds[b]:bounds[b + 1]]
                cache[b] = _vote(b, sel[placed[ab_other[sel]]])
            mg, best, Tb, _ = cache[b]
            if mg < params.min_margin:
                break  # b stays in the cache: its reason is the ambiguity
            del cache[b]
            placed[b] = True
            T[b] = Tb
            support[b] = best / max(n_scans[b], 1.0)
            margin[b] = mg
            order.append(b)
            walks = np.flatnonzero(placed)
            inside = placed[si] & placed[sj]
            if len(walks) <= params.full_refine_walks or len(walks) >= 1.5 * last_full:
                moved, last_full = walks, len(walks)
            else:  # the new walk alone on the map (its matches; the others held)
                moved = np.array([b])
                inside &= (si == b) | (sj == b)
            with _one_thread():
                T = refine_rigid(T, moved, held, scan_session, scan_xy, mi[inside], mj[inside], mw[inside], params,
                                 rotation_sigma)
            for s in moved:
                world[by_walk[s]] = se2_apply(T[s], scan_xy[by_walk[s]])
            # walks matched to the new one see a changed map; others keep their (slightly stale) vote
            stale |= set(np.unique(ab_walk[ab_other == b]).tolist())
            task.advance()
    if placed.sum() > last_full:  # local refinements since the last joint one
        walks = np.flatnonzero(placed)
        inside = placed[si] & placed[sj]
        with _one_thread():
            T = refine_rigid(T, walks, held, scan_session, scan_xy, mi[inside], mj[inside], mw[inside], params,
                             rotation_sigma)
        for s in walks:
            world[by_walk[s]] = se2_apply(T[s], scan_xy[by_walk[s]])
    consistency = np.full(n_sessions, np.nan)
    both = placed[ab_walk] & placed[ab_other]
    if both.any():
        d = np.linalg.norm(world[ab_src[both]] - world[ab_dst[both]], axis=1)
        w_all = np.bincount(ab_walk[both], weights=ab_w[both], minlength=n_sessions)
        w_ok = np.bincount(ab_walk[both], weights=ab_w[both] * (d < params.consistent_m), minlength=n_sessions)
        has = w_all > 0
        consistency[has] = w_ok[has] / w_all[has]
    reasons = {}
    for s in np.flatnonzero(~placed & use):
        if s in cache:
            reasons[int(s)] = (
                f"WiFi registration ambiguous: best placement beats the runner-up by {cache[s][0]:.2f} "
                f"(placement.min_margin {params.min_margin})"
            )
        else:
            reasons[int(s)] = "no WiFi matches to the placed walks"
    log.info("map growth: %d of %d walks placed from seed walk %d", placed.sum(), n_sessions, seed)
    return GrowthResult(T, placed, int(seed), tuple(order), support, margin, consistency, reasons)
