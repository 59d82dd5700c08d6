"""Initial placement of walks whose start poses are unknown.

``origin``: the paper's default (eq. 2): every walk starts at (0, 0, 0) of the reference frame.

``registration``: WiFi edges between two walks are correspondences between their
dead-reckoned frames. A 2-point RANSAC finds, per pair of walks, the rigid
transform with most correspondences within ``inlier_m``; a maximum spanning tree
over walks (weight = inliers) chains these transforms out from the reference walk.
Walks the tree does not reach keep the origin start and are reported unplaced.
The fit is rigid, so long drifting walks are placed only roughly: LM does the rest.

Loop check: every pairwise transform the tree did not use closes a loop. Where the
placement is right, the tree predicts it (mean displacement of the walk's steps below
``inlier_m``); the fraction of such consistent loops is a self-check that needs no
ground truth. Simulated surveys: 0.64-1; real short phone walks (ILC): ~0.3, i.e. the
pairwise matches are not reliable enough to place walks (docs/method.md).
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from graphslam.core.common.geometry import fit_se2, ransac_se2, se2_apply, se2_apply_poses, se2_compose  # noqa: F401 (re-exported)

log = logging.getLogger(__name__)

# Loop self-check: with this many loops or more, a consistency below the threshold marks the
# placement unreliable. Simulated surveys close ~all loops, real short phone walks (ILC
# site1) ~0.3: the threshold sits between the two, not tuned further.
MIN_LOOPS_TO_JUDGE = 10
MIN_LOOP_CONSISTENCY = 0.5


@dataclass(frozen=True, eq=False)
class Placement:
    """Per-walk rigid transform (x, y, theta) from its dead-reckoning frame to the reference frame."""

    transforms: NDArray[np.float64]  # (S, 3)
    placed: NDArray[np.bool_]  # (S,) reached from the reference walk
    inliers: NDArray[np.int64]  # (S,) inliers of the tree edge that placed it (reference: -1)
    parent: NDArray[np.int64]  # (S,) tree parent (-1 for the reference / unplaced)
    loops: int = 0  # pairwise transforms between placed walks not used by the tree
    loops_consistent: int = 0  # ... of which the tree placement predicts within inlier_m
    method: str = "registration"  # or "growth" (graphslam.core.survey.placement)
    # growth only, per walk (NaN: unplaced): vote support per fingerprint, margin over the
    # runner-up placement, fraction of match weight consistent at the final placement
    support: NDArray[np.float64] | None = None
    margin: NDArray[np.float64] | None = None
    consistency: NDArray[np.float64] | None = None
    unplaced_reasons: dict[int, str] | None = None  # walk index -> why it was not placed

    @property
    def loop_consistency(self) -> float | None:
        """Fraction of loops the placement closes (None: no loop to check)."""
        return self.loops_consistent / self.loops if self.loops else None

    @property
    def reliable(self) -> bool | None:
        """False when the loops contradict the placement; None when there are too few to judge."""
        c = self.loop_consistency
        return None if c is None or self.loops < MIN_LOOPS_TO_JUDGE else c >= MIN_LOOP_CONSISTENCY


def register_walks(
    n_sessions: int,
    reference: int,
    node_session: NDArray[np.int64],
    node_xy: NDArray[np.float64],
    edge_a: NDArray[np.int64],
    edge_b: NDArray[np.int64],
    *,
    inlier_m: float = 6.0,
    min_inliers: int = 4,
    seed: int = 0,
) -> Placement:
    """Place walks by pairwise RANSAC + maximum spanning tree. ``edge_a/b`` are node indices."""
    rng = np.random.default_rng(seed)
    sa, sb = node_session[edge_a], node_session[edge_b]
    cross = sa != sb
    a, b, sa, sb = edge_a[cross], edge_b[cross], sa[cross], sb[cross]
    # orient every pair (lo, hi)
    swap = sa > sb
    a, b = np.where(swap, b, a), np.where(swap, a, b)
    sa, sb = np.minimum(sa, sb), np.maximum(sa, sb)
    pair_key = sa * n_sessions + sb
    order = np.argsort(pair_key, kind="stable")
    keys, starts = np.unique(pair_key[order], return_index=True)
    ends = np.append(starts[1:], len(order))
    rel: dict[tuple[int, int], NDArray] = {}
    wi, wj, ww = [], [], []
    for key, s0, s1 in zip(keys, starts, ends):
        idx = order[s0:s1]
        if len(idx) < min_inliers:
            continue
        lo, hi = int(key // n_sessions), int(key % n_sessions)
        T, inl = ransac_se2(node_xy[a[idx]], node_xy[b[idx]], inlier_m=inlier_m, rng=rng)
        k = int(inl.sum())
        if k >= min_inliers:
            rel[(lo, hi)] = T  # maps hi's frame into lo's frame
            wi.append(lo)
            wj.append(hi)
            ww.append(k)
    transforms = np.zeros((n_sessions, 3))
    placed = np.zeros(n_sessions, bool)
    inliers = np.zeros(n_sessions, np.int64)
    parent = np.full(n_sessions, -1, np.int64)
    placed[reference] = True
    inliers[reference] = -1
    if ww:
        # maximum spanning tree = minimum spanning tree of negated weights
        kept = spanning_tree(n_sessions, wi, wj, -np.asarray(ww, float))
        adj: dict[int, list[tuple[int, int]]] = {}
        for k in np.flatnonzero(kept).tolist():
            u, v, w = wi[k], wj[k], ww[k]
            adj.setdefault(int(u), []).append((int(v), int(w)))
            adj.setdefault(int(v), []).append((int(u), int(w)))
        queue = deque([reference])
        while queue:
            u = queue.popleft()
            for v, w in adj.get(u, []):
                if placed[v]:
                    continue
                T_uv = rel[(u, v)] if (u, v) in rel else _inverse(rel[(v, u)])
                transforms[v] = se2_compose(transforms[u], T_uv)
                placed[v] = True
                inliers[v] = w
                parent[v] = u
                queue.append(v)
    loops = consistent = 0
    # each walk's nodes once (not a mask over all nodes per loop: surveys have thousands of loops)
    by_walk = np.argsort(node_session, kind="stable")
    bounds = np.searchsorted(node_session[by_walk], np.arange(n_sessions + 1))
    for (u, v), T_uv in rel.items():
        if not (placed[u] and placed[v]) or parent[v] == u or parent[u] == v:
            continue
        xy = node_xy[by_walk[bounds[v] : bounds[v + 1]]]
        moved = se2_apply(se2_compose(transforms[u], T_uv), xy) - se2_apply(transforms[v], xy)
        loops += 1
        consistent += int(np.linalg.norm(moved, axis=1).mean() < inlier_m)
    log.info(
        "registration: %d of %d walks placed from %d walk pairs; %d of %d loops consistent",
        placed.sum(), n_sessions, len(ww), consistent, loops,
    )
    pl = Placement(transforms, placed, inliers, parent, loops, consistent)
    if pl.reliable is False:
        log.warning(
            "registration: only %d of %d loops between placed walks are consistent: the WiFi matches "
            "do not support a reliable placement (short or non-overlapping walks?)", consistent, loops,
        )
    return pl


def spanning_tree(n: int, a: Sequence[int], b: Sequence[int], cost: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Which edges ``(a[k], b[k])`` of an undirected graph on ``n`` nodes form its minimum spanning
    forest (Kruskal). Ties go to the edge listed first: with the edges in (row, column) order this is
    ``scipy.sparse.csgraph.minimum_spanning_tree``'s rule (a stable sort of its CSR data), so the same
    tree — without importing csgraph and scipy.linalg beneath it (a share of a survey's start-up;
    the graph here has one node per walk)."""
    parent = list(range(n))

    def root(x: int) -> int:
        while parent[x] != x:
            parent[x] = parent[parent[x]]  # path halving
            x = parent[x]
        return x

    kept = np.zeros(len(cost), bool)
    for k in np.argsort(cost, kind="stable").tolist():
        ra, rb = root(int(a[k])), root(int(b[k]))
        if ra != rb:
            parent[rb] = ra
            kept[k] = True
    return kept


def connected_to(n: int, a: NDArray[np.int64], b: NDArray[np.int64], node: int) -> NDArray[np.bool_]:
    """Nodes of the undirected graph (``n`` nodes, edges ``a[k]-b[k]``) with a path to ``node``."""
    pairs = np.unique(np.stack([np.asarray(a), np.asarray(b)], axis=1), axis=0)  # edges to the walk graph's
    adj: dict[int, list[int]] = {}
    for u, v in pairs.tolist():
        adj.setdefault(u, []).append(v)
        adj.setdefault(v, []).append(u)
    seen = np.zeros(n, bool)
    seen[node] = True
    queue = deque([node])
    while queue:
        for v in adj.get(queue.popleft(), []):
            if not seen[v]:
                seen[v] = True
                queue.append(v)
    return seen


def _inverse(T: NDArray) -> NDArray:
    c, s = np.cos(T[2]), np.sin(T[2])
    return np.array([-(c * T[0] + s * T[1]), -(-s * T[0] + c * T[1]), -T[2]])
