"""Incremental surveys (``graphslam survey --update``): new walks joined to a solved floor.

A floor surveyed before gets new walks. Instead of solving everything again:

1. **Edges**: only the new walks' fingerprints are compared with every fingerprint
   (O(F_new x F) instead of O(F^2)). An old fingerprint's kept partners are its previous
   ones merged with the new candidates, so the edge set equals a full recomputation:
   a fingerprint's top-m partners all appear in the previous (symmetrised) edge set, so
   the m nearest previous edges that pass its own threshold *are* its previous top-m.
2. **Placement**: every walk solved before starts from its previous solution; the other
   walks (new, or unaligned before) are registered by the same 2-point RANSAC + spanning
   tree as a full survey, against the solved walks taken together as one rigid body.
3. **Neighbourhood**: the part re-solved is every node of a placed new walk, every node
   touched by an added or removed edge, and what lies within ``hops`` factors of them in
   the (chain-compressed) graph. The rest keeps its previous solution exactly; nodes of the
   neighbourhood's border are held by tight priors. LM then runs over that part only.

Everything here is pure array maths on the current survey's numbering; what a previous
output holds (``PreviousSolution``) is read and written by ``graphslam.io.survey_state``.
"""

from __future__ import annotations

import hashlib
import logging
from dataclasses import dataclass
from typing import Mapping

import numpy as np
from numpy.typing import NDArray
from scipy import sparse

from graphslam.config import EdgeConfig
from graphslam.core.common.arrays import nonzero_2d
from graphslam.core.radiomap.fingerprints import DistanceEngine
from graphslam.core.survey.association import FingerprintNodes
from graphslam.core.survey.edges import WifiEdges, _row_distances, nearest_per_row
from graphslam.core.survey.initialise import Placement, register_walks
from graphslam.core.types import Session, Survey
from graphslam.errors import SolverError

log = logging.getLogger(__name__)


def control_points_digest(control_points: Mapping[str, tuple[float, float]] | None) -> str:
    """SHA-256 of a control-points mapping (landmark id -> site x, y), "" for none: an update whose
    control points differ from the previous run's must place its walks again."""
    if not control_points:
        return ""
    h = hashlib.sha256()
    for lid in sorted(control_points):
        x, y = control_points[lid]
        h.update(f"{lid}\0{float(x)!r}\0{float(y)!r}\n".encode())
    return h.hexdigest()


def session_digest(session: Session) -> str:
    """SHA-256 of what the solver reads from a walk: equal digests, equal walk. Its id, steps and
    scans; when present (each hashed only then: a walk without them keeps the digest it had before
    they were), the phone's headings and magnetic field, the landmark marks' ids and times (the ids a user names as
    control points tie the walk to the site) and its UWB id, anchors and rangings. Left out: ground
    truth and the marks' surveyed positions, which never reach the solver."""
    h = hashlib.sha256()
    h.update(session.session_id.encode())
    st = session.steps
    for a in (st.t_ns, st.xy, st.heading):
        h.update(np.ascontiguousarray(a).tobytes())
    scans = session.scans
    h.update(np.array([sc.t_ns for sc in scans], np.int64).tobytes())
    h.update(np.array([len(sc.readings) for sc in scans], np.int64).tobytes())
    h.update("\n".join([b for sc in scans for b in sc.readings]).encode())
    h.update(np.array([r for sc in scans for r in sc.readings.values()], np.float64).tobytes())
    if session.heading is not None:
        h.update(b"\0heading")
        h.update(np.ascontiguousarray(session.heading.t_ns, np.int64).tobytes())
        h.update(np.ascontiguousarray(session.heading.yaw, np.float64).tobytes())
    if session.magnetic is not None:
        h.update(b"\0magnetic")
        h.update(np.ascontiguousarray(session.magnetic.t_ns, np.int64).tobytes())
        h.update(np.ascontiguousarray(session.magnetic.enu, np.float64).tobytes())
    if session.landmarks:
        h.update(b"\0landmarks")
        h.update(np.array([m.t_ns for m in session.landmarks], np.int64).tobytes())
        h.update("\n".join(m.landmark_id for m in session.landmarks).encode())
    if session.uwb_id or session.uwb_anchors or session.uwb_ranges is not None:
        h.update(b"\0uwb")
        h.update(session.uwb_id.encode())
        for aid in sorted(session.uwb_anchors):
            h.update(f"\n{aid}\0".encode() + np.array(session.uwb_anchors[aid], np.float64).tobytes())
        u = session.uwb_ranges
        if u is not None:
            h.update(np.ascontiguousarray(u.t_ns, np.int64).tobytes())
            h.update("\n".join(u.responder_id).encode())
            h.update(np.ascontiguousarray(u.is_anchor, np.bool_).tobytes())
            h.update(np.ascontiguousarray(u.range_m, np.float64).tobytes())
    return h.hexdigest()


@dataclass(frozen=True, eq=False)
class PreviousSolution:
    """What a finished survey leaves for the next ``--update`` (``survey_state.npz``).

    Poses are in the previous survey's aligned frame (its reference walk's first pose).
    Edges are named by (session index, scan index) into ``session_ids``.
    """

    session_ids: tuple[str, ...]
    digests: tuple[str, ...]
    aligned: NDArray[np.bool_]  # (S,)
    offsets: NDArray[np.int64]  # (S + 1,) step ranges into xyh
    xyh: NDArray[np.float64]  # (N, 3) solution of every step (NaN: walk not aligned)
    edge_session: NDArray[np.int64]  # (E, 2)
    edge_scan: NDArray[np.int64]  # (E, 2)
    candidates: int  # pairs below threshold before the per-fingerprint cap (report.json)
    reference: str
    config_json: str  # the effective configuration the solution was computed with
    registration_reliable: bool | None
    # per walk its component (0: the main map; -1: unaligned); None: a state written before components
    component: NDArray[np.int64] | None = None
    frame: str = "aligned"  # component 0's frame (``Alignment.frame``)
    control_digest: str = ""  # ``control_points_digest`` of the control points used ("" none)
    edge_used: NDArray[np.bool_] | None = None  # (E,) the edge entered the optimiser (None: all did)
    # the state's format (``graphslam.io.survey_state``): before 3 the digests covered ids, steps and scans only
    format_version: int = 4
    # the magnetic links used: (walks (K, 2), each pair's link (P,), each pair's steps (P, 2)); None: none kept
    magnetic: tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]] | None = None

    def walk_xyh(self, session_id: str) -> NDArray[np.float64]:
        s = self.session_ids.index(session_id)
        return self.xyh[self.offsets[s] : self.offsets[s + 1]]


@dataclass(frozen=True, eq=False)
class WarmStart:
    """A previous solution mapped onto the current survey's numbering (``build_problem(warm=...)``).

    ``old`` walks were in the previous survey unchanged (their fingerprints' edges are known);
    of those, the ones with finite ``xyh`` were aligned and start from it.
    """

    xyh: NDArray[np.float64]  # (N, 3) previous solution per node, NaN where the walk is placed anew
    old: NDArray[np.bool_]  # (S,) walk was in the previous survey, unchanged
    prev_edge_session: NDArray[np.int64]  # (E, 2) current session indices
    prev_edge_scan: NDArray[np.int64]  # (E, 2)
    prev_candidates: int
    hops: int
    # (S,) component of each old walk in the previous solution (-1: new, or not aligned before);
    # None: the previous state has none (written before components)
    component: NDArray[np.int64] | None = None
    prev_edge_used: NDArray[np.bool_] | None = None  # (E,) per previous edge: it entered the optimiser
    # the previous magnetic links between walks solved before: (walks (K, 2) current indices, each pair's
    # link (P,), each pair's nodes (P, 2) current numbering); None: none
    magnetic: tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]] | None = None

    @property
    def solved(self) -> NDArray[np.bool_]:
        """(N,) nodes that start from their previous solution."""
        return np.isfinite(self.xyh[:, 0])

    def solved_walks(self, node_session: NDArray[np.int64], n_sessions: int) -> NDArray[np.bool_]:
        """(S,) walks that start from their previous solution."""
        out = np.zeros(n_sessions, bool)
        out[node_session[self.solved]] = True
        return out


def warm_start(previous: PreviousSolution, survey: Survey, hops: int) -> WarmStart:
    """Map ``previous`` onto ``survey`` (whose walks the caller has checked: every previous walk
    is present with the same digest)."""
    ids = [s.session_id for s in survey]
    index = {sid: k for k, sid in enumerate(ids)}
    sizes = np.array([len(s.steps) for s in survey], np.int64)
    offsets = np.concatenate([[0], np.cumsum(sizes)])
    xyh = np.full((int(offsets[-1]), 3), np.nan)
    old = np.zeros(len(ids), bool)
    for p, sid in enumerate(previous.session_ids):
        s = index[sid]
        old[s] = True
        if previous.aligned[p]:
            xyh[offsets[s] : offsets[s + 1]] = previous.xyh[previous.offsets[p] : previous.offsets[p + 1]]
    remap = np.array([index[sid] for sid in previous.session_ids], np.int64)
    component = None
    if previous.component is not None:
        component = np.full(len(ids), -1, np.int64)
        component[remap] = np.where(previous.aligned, previous.component, -1)
    magnetic = None
    if previous.magnetic is not None and len(previous.magnetic[0]):
        mw, ml, ms = previous.magnetic
        walks = remap[mw]
        magnetic = (walks, ml.copy(), offsets[walks[ml]] + ms)
    return WarmStart(
        magnetic=magnetic,
        xyh=xyh,
        old=old,
        prev_edge_session=remap[previous.edge_session] if len(previous.edge_session) else np.zeros((0, 2), np.int64),
        prev_edge_scan=previous.edge_scan.copy(),
        prev_candidates=previous.candidates,
        hops=hops,
        component=component,
        prev_edge_used=None if previous.edge_used is None else previous.edge_used.copy(),
    )


def _rows_of(fp: FingerprintNodes, session: NDArray, scan: NDArray) -> NDArray[np.int64]:
    """Fingerprint rows of (session, scan) pairs (rows are ordered by session, then scan)."""
    key = fp.session * (int(fp.scan.max(initial=0)) + 1) + fp.scan
    want = session * (int(fp.scan.max(initial=0)) + 1) + scan
    rows = np.searchsorted(key, want)
    rows = np.minimum(rows, max(len(key) - 1, 0))
    if len(want) and not np.array_equal(key[rows], want):
        raise SolverError("the previous solution's WiFi edges name scans that are not fingerprints of this survey")
    return rows.astype(np.int64)


def previous_edge_rows(fp: FingerprintNodes, warm: WarmStart) -> NDArray[np.int64]:
    """(E, 2) fingerprint rows of the previous survey's edges."""
    if not len(warm.prev_edge_session):
        return np.zeros((0, 2), np.int64)
    return np.column_stack([
        _rows_of(fp, warm.prev_edge_session[:, 0], warm.prev_edge_scan[:, 0]),
        _rows_of(fp, warm.prev_edge_session[:, 1], warm.prev_edge_scan[:, 1]),
    ])


def previous_graph_pairs(fp: FingerprintNodes, warm: WarmStart) -> NDArray[np.int64]:
    """(E, 2) node pairs of the WiFi edges the previous optimiser had (every previous edge when the
    state does not say which)."""
    pairs = fp.node[previous_edge_rows(fp, warm)]
    return pairs if warm.prev_edge_used is None else pairs[warm.prev_edge_used]


def update_edges(fp: FingerprintNodes, thresholds: NDArray[np.float64], warm: WarmStart, cfg: EdgeConfig) -> WifiEdges:
    """The WiFi edges of the whole survey, computing distances only from the new walks' rows.

    Same rule as ``edges.propose_edges`` (threshold, same-walk exclusions, per-fingerprint cap,
    ties broken by column), hence the same edge set (see the module docstring).
    """
    n = len(fp)
    m = cfg.max_per_fingerprint if cfg.max_per_fingerprint > 0 else n
    new_row = ~warm.old[fp.session]
    rows_new = np.flatnonzero(new_row)
    t_s = (fp.t_ns - (fp.t_ns.min() if n else 0)) / 1e9
    di, dj, dd = [], [], []  # directed candidates (row -> partner) of old rows
    ki, kj, kd = [], [], []  # kept directed partners of new rows
    candidates = warm.prev_candidates
    if len(rows_new):
        engine = DistanceEngine(fp.fingerprints)
        q = fp.fingerprints.rows(rows_new)
        for start, d, _ in engine.iter_blocks(q, min_common=cfg.min_common_aps, block_rows=cfg.chunk_rows):
            rows = rows_new[start : start + len(d)]
            # new row -> any column: the full rule (new walks' own columns are new rows too)
            ok = d < thresholds[rows][:, None]
            ok[np.arange(len(rows)), rows] = False
            _exclude_same_walk(ok, rows, fp, t_s, cfg)
            ri, ci = nonzero_2d(ok)
            candidates += len(ri)
            ki.append(rows[ri])
            kj.append(ci)
            kd.append(d[ri, ci])
            # old row -> new column: the transposed block (eq. 9 is symmetric); other walks, no exclusion
            back = (d < thresholds[None, :]) & ~new_row[None, :]
            ri, ci = nonzero_2d(back)
            candidates += len(ri)
            di.append(ci)
            dj.append(rows[ri])
            dd.append(d[ri, ci])
    prev = previous_edge_rows(fp, warm)
    if len(prev):
        d_prev = _row_distances(fp, prev[:, 0], prev[:, 1])
        for a, b in ((0, 1), (1, 0)):
            ok = d_prev < thresholds[prev[:, a]]  # a previous edge is a candidate of each end it passes
            di.append(prev[ok, a])
            dj.append(prev[ok, b])
            dd.append(d_prev[ok])
    cat = lambda parts, dt: np.concatenate(parts).astype(dt) if parts else np.zeros(0, dt)  # noqa: E731
    i = np.concatenate([_top(cat(ki, np.int64), cat(kj, np.int64), cat(kd, float), m),
                        _top(cat(di, np.int64), cat(dj, np.int64), cat(dd, float), m)], axis=1)
    a, b, dist = np.minimum(i[0], i[1]).astype(np.int64), np.maximum(i[0], i[1]).astype(np.int64), i[2]
    key = a * n + b
    _, first = np.unique(key, return_index=True)
    a, b, dist = a[first], b[first], dist[first]
    common = _common_aps(fp, a, b)
    log.info("WiFi edges (update): %d new fingerprints compared, %d edges", len(rows_new), len(a))
    return WifiEdges(a, b, dist, common, int(candidates))


def _exclude_same_walk(ok: NDArray[np.bool_], rows: NDArray[np.int64], fp: FingerprintNodes, t_s: NDArray,
                       cfg: EdgeConfig) -> None:
    """Clear ``ok[i, j]`` (rows ``rows``, every column) where fingerprints ``rows[i]`` and ``j`` are of
    one walk and near in time or along the walk (``propose_edges``' exclusion). Fingerprints are
    grouped by walk (``associate``), so only each row's own walk's columns are looked at, not all."""
    walk = fp.session
    if len(walk) > 1 and bool(np.any(np.diff(walk) < 0)):  # not grouped: the whole block
        same = walk[rows][:, None] == walk[None, :]
        near = (np.abs(t_s[rows][:, None] - t_s[None, :]) < cfg.exclude_same_session_s) | (
            np.abs(fp.path_m[rows][:, None] - fp.path_m[None, :]) < cfg.exclude_same_session_m)
        ok &= ~(same & near)
        return
    for w in np.unique(walk[rows]).tolist():
        r = np.flatnonzero(walk[rows] == w)
        c0, c1 = int(np.searchsorted(walk, w, side="left")), int(np.searchsorted(walk, w, side="right"))
        rr = rows[r]
        near = (np.abs(t_s[rr][:, None] - t_s[None, c0:c1]) < cfg.exclude_same_session_s) | (
            np.abs(fp.path_m[rr][:, None] - fp.path_m[None, c0:c1]) < cfg.exclude_same_session_m)
        ok[r, c0:c1] &= ~near


def _top(i: NDArray, j: NDArray, d: NDArray, m: int) -> NDArray:
    """(3, K) the ``m`` nearest partners of every row (ties: lower column first), as propose_edges."""
    return np.vstack(nearest_per_row(i, j, d, m))


def _common_aps(fp: FingerprintNodes, a: NDArray, b: NDArray) -> NDArray[np.int64]:
    heard = fp.fingerprints.values.copy()
    heard.data[:] = 1.0
    return np.asarray(heard[a].multiply(heard[b]).sum(axis=1)).ravel().astype(np.int64)


def place_new_walks(
    warm: WarmStart, n_sessions: int, node_session: NDArray[np.int64], dr_xy: NDArray, edge_a: NDArray, edge_b: NDArray
) -> Placement:
    """Register the walks without a previous solution to the solved ones (one rigid body, in the
    previous frame) and to each other: ``initialise.register_walks`` over walk 0 = all solved walks.

    The returned ``Placement`` is per walk of the survey: solved walks are placed with a zero
    transform (they start from ``warm.xyh``, not from a transform), new walks carry theirs;
    ``parent`` of a walk registered to the solved body is the solved walk it shares most edges with.
    """
    solved_walk = warm.solved_walks(node_session, n_sessions)
    new = np.flatnonzero(~solved_walk)
    label = np.zeros(n_sessions, np.int64)
    label[new] = 1 + np.arange(len(new))
    xy = np.where(warm.solved[:, None], warm.xyh[:, :2], dr_xy)
    sub = register_walks(1 + len(new), 0, label[node_session], xy, edge_a, edge_b)
    transforms = np.zeros((n_sessions, 3))
    placed = solved_walk.copy()
    inliers = np.where(solved_walk, -1, 0).astype(np.int64)
    parent = np.full(n_sessions, -1, np.int64)
    sa, sb = node_session[edge_a], node_session[edge_b]
    for r, s in enumerate(new.tolist()):
        k = 1 + r
        if not sub.placed[k]:
            continue
        transforms[s] = sub.transforms[k]
        placed[s] = True
        inliers[s] = sub.inliers[k]
        if sub.parent[k] > 0:
            parent[s] = new[sub.parent[k] - 1]
        else:  # registered to the solved body: name the solved walk it shares most edges with
            other = np.concatenate([sb[sa == s], sa[sb == s]])
            other = other[solved_walk[other]]
            parent[s] = int(np.bincount(other).argmax()) if len(other) else -1
    return Placement(transforms, placed, inliers, parent, sub.loops, sub.loops_consistent)


def kept_nodes(
    n_nodes: int, offsets: NDArray, included: NDArray, wifi_pairs: NDArray, reference_node: int
) -> NDArray[np.bool_]:
    """The nodes chain compression keeps as variables (``chains.compress``): WiFi edge ends, the
    reference pose, first and last step of every included walk."""
    keep = np.zeros(n_nodes, bool)
    keep[wifi_pairs.ravel()] = True
    keep[reference_node] = True
    sizes = np.diff(offsets)
    keep[offsets[:-1][sizes > 0]] = True
    keep[offsets[1:][sizes > 0] - 1] = True
    walk_of = np.repeat(np.arange(len(offsets) - 1), sizes)
    return keep & included[walk_of]


def pairs_in(pairs: NDArray[np.int64], of: NDArray[np.int64], n: int) -> NDArray[np.bool_]:
    """(K,) whether each node pair of ``pairs`` (either order) is one of ``of``; ``n``: node count."""
    key = lambda p: np.sort(p.reshape(-1, 2), axis=1) @ np.array([n, 1], np.int64)  # noqa: E731
    return np.isin(key(pairs), key(of))


def changed_edges(
    wifi_pairs: NDArray[np.int64], prev_pairs: NDArray[np.int64], solved: NDArray[np.bool_]
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """(added, removed): (K, 2) node pairs of the edges in the graph now and not before, and of the
    edges the previous graph had between solved walks that it has no more."""
    n = len(solved)
    prev_pairs = prev_pairs.reshape(-1, 2)
    prev_pairs = prev_pairs[solved[prev_pairs].all(axis=1)]
    cur = np.sort(wifi_pairs.reshape(-1, 2), axis=1) @ np.array([n, 1])
    old = np.sort(prev_pairs, axis=1) @ np.array([n, 1])
    unpack = lambda k: np.column_stack([k // n, k % n]).astype(np.int64)  # noqa: E731
    return unpack(np.setdiff1d(cur, old)), unpack(np.setdiff1d(old, cur))


def free_nodes(
    warm: WarmStart,
    offsets: NDArray[np.int64],
    included: NDArray[np.bool_],
    wifi_pairs: NDArray[np.int64],
    prev_pairs: NDArray[np.int64],
    reference_node: int,
    *,
    compressed: bool,
) -> NDArray[np.bool_]:
    """(N,) nodes the update re-solves: walks placed anew, ends of added or removed edges, and
    every node within ``warm.hops`` factors of them (hops over chain segments when ``compressed``)."""
    n = int(offsets[-1])
    walk_of = np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))
    inc = included[walk_of]
    keep = kept_nodes(n, offsets, included, wifi_pairs, reference_node) if compressed else inc.copy()
    seed = inc & ~warm.solved
    added, removed = changed_edges(wifi_pairs, prev_pairs, warm.solved)
    seed[added.ravel()] = True
    seed[removed.ravel()] = True
    seed &= inc
    # a seed that is not a variable (a removed edge's end inside a chain) seeds both ends of its segment
    kept_idx = np.flatnonzero(keep)
    if len(kept_idx) == 0:
        return seed
    pos = np.searchsorted(kept_idx, np.flatnonzero(seed & ~keep))
    for p in (pos - 1, pos):
        p = p[(p >= 0) & (p < len(kept_idx))]
        seed[kept_idx[p]] = True
    # graph over kept nodes: consecutive kept nodes of one walk, and WiFi edges
    same = walk_of[kept_idx[:-1]] == walk_of[kept_idx[1:]]
    ea = np.concatenate([kept_idx[:-1][same], wifi_pairs[:, 0]])
    eb = np.concatenate([kept_idx[1:][same], wifi_pairs[:, 1]])
    adj = sparse.coo_matrix((np.ones(len(ea)), (ea, eb)), shape=(n, n)).tocsr()
    adj = adj + adj.T
    free = seed & keep
    for _ in range(warm.hops):
        grown = free | (adj @ free.astype(float) > 0)
        if np.array_equal(grown, free):
            break
        free = grown
    # steps between kept nodes move with them: a segment with a free end is free
    seg = np.searchsorted(kept_idx, np.arange(n), side="left")  # first kept node at or after each step
    nxt = kept_idx[np.minimum(seg, len(kept_idx) - 1)]
    prv = kept_idx[np.maximum(np.minimum(seg, len(kept_idx)) - 1, 0)]
    inner = ~keep & inc
    free[inner] = (free[nxt] & (walk_of[nxt] == walk_of))[inner] | (free[prv] & (walk_of[prv] == walk_of))[inner]
    return free | (seed & inc)
