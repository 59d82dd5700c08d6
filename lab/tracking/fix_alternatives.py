#!/usr/bin/env python3
"""Other ways to get a kNN fix out of the same radio map (diagnostics; none in the product).

The folds and oracle maps of ``bench tracking-real`` (5 seeded folds on ILC, leave one route out on
IPIN; ground truth places the map's scans and scores, nothing is chosen on it). Each held-out scan
is located with k = 3 under the Sørensen metric (the tracker's fixes); the fix track is scored at
the landmarks as ``bench tracking-real`` scores kNN. One mode per run:

- ``sequence``: a route-shape match instead of one scan: for scan i and every map fingerprint j,
  the mean fingerprint distance of the walk's scans of the last L metres walked (causal) to the
  fingerprints of j's own map walk at the same arc-length offsets, either sense; the fix is the
  mean position of the 3 best (j, sense). L = 3, 6, 10 m.
- ``cells``: the map's fingerprints averaged per square cell (1, 2, 3 m; every AP heard in the cell,
  or only those heard in at least half its scans) before the search.
- ``shift``: the fixes placed ``delta`` seconds before (after, if negative) their scan's timestamp
  (a scan's readings are gathered over the second or two before it completes).
- ``directions``: whether a scan's neighbours were walked the way the query walks (body
  shadowing): the angle between each neighbour's map walk direction and the query's true
  direction (ground truth, for this statistic only), histogrammed; and the forward/backward table
  the map itself gives (leave one session out, no ground truth) on the map of all walks.

    python lab/tracking/fix_alternatives.py FOLDER route|FOLDS sequence|cells|shift|directions
"""

from __future__ import annotations

import itertools
import math
import sys
from collections import defaultdict

import numpy as np

from graphslam import (
    fit_se2, held_out_folds, interpolate_xy, KnnConfig, KnnLocator, oracle_radio_map, PoseTrack, RadioMap,
    read_survey, se2_apply, walk_landmarks, WEIGHT_EPS_DB,
)


MODES = ("sequence", "cells", "shift", "directions")


def _arc(xy: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])


def _map_walks(rm: RadioMap) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Rows sorted by (session, time); per sorted row its arc length along its walk and the sorted
    index range [start, end) of its walk."""
    order = np.lexsort((rm.t_ns, rm.session_ids))
    sid = rm.session_ids[order]
    arc, start, end = np.zeros(len(rm)), np.zeros(len(rm), int), np.zeros(len(rm), int)
    bounds = np.flatnonzero(np.r_[True, sid[1:] != sid[:-1], True])
    for a, b in itertools.pairwise(bounds):
        arc[a:b], start[a:b], end[a:b] = _arc(rm.xy[order[a:b]]), a, b
    return order, arc, start, end


def _sequence_fixes(D: np.ndarray, c: np.ndarray, rm: RadioMap, walks, L: float, k: int = 3) -> np.ndarray:
    order, arc, start, end = walks  # all in sorted order
    D = np.where(np.isfinite(D), D, 1.0)[:, order]  # Sørensen's worst is 1
    key = start * 1e6 + arc  # increasing: walks in blocks, arc within
    out = np.full((len(c), 2), np.nan)
    for i in range(len(c)):
        ms = np.flatnonzero((c[i] - c <= L) & (np.arange(len(c)) <= i))
        costs = []
        for sense in (1.0, -1.0):
            cost = np.zeros(len(order))
            for m in ms:
                target = arc - sense * (c[i] - c[m])
                pos = np.clip(np.searchsorted(key, start * 1e6 + target), start, end - 1)
                prev = np.clip(pos - 1, start, end - 1)
                pick = np.where(np.abs(arc[prev] - target) < np.abs(arc[pos] - target), prev, pos)
                inside = (target >= arc[start] - 1.0) & (target <= arc[end - 1] + 1.0)
                cost += np.where(inside, D[m, pick], 1.0)
            costs.append(cost / len(ms))
        best = np.argsort(np.minimum(*costs))[:k]
        out[i] = rm.xy[order[best]].mean(axis=0)
    return out


def _cell_map(train, cell: float, min_share: float) -> RadioMap:
    rm = oracle_radio_map(train)
    scans = [dict(sc.readings) for w in train for sc in w.scans]
    groups = defaultdict(list)
    for i, key in enumerate(map(tuple, np.floor(rm.xy / cell).astype(int))):
        groups[key].append(i)
    fps, xy = [], []
    for rows in groups.values():
        heard = defaultdict(list)
        for i in rows:
            for b, r in scans[i].items():
                heard[b].append(r)
        fp = {b: float(np.mean(v)) for b, v in heard.items() if len(v) >= min_share * len(rows)}
        if fp:
            fps.append(fp)
            xy.append(rm.xy[rows].mean(axis=0))
    return RadioMap.from_scans(fps, np.array(xy), session_ids=[f"c{i}" for i in range(len(fps))],
                               t_ns=list(range(len(fps))), frame="site")


def _walk_dirs(rm: RadioMap) -> np.ndarray:
    """Map-frame walking direction per map row (central difference along its walk; NaN < 0.5 m)."""
    order = np.lexsort((rm.t_ns, rm.session_ids))
    sid, xy, n = rm.session_ids[order], rm.xy[order], len(order)
    i = np.arange(n)
    link = sid[1:] == sid[:-1]
    d = xy[np.where(np.r_[link, False], i + 1, i)] - xy[np.where(np.r_[False, link], i - 1, i)]
    out = np.full(n, np.nan)
    ok = np.hypot(d[:, 0], d[:, 1]) >= 0.5
    out[order[ok]] = np.arctan2(d[ok, 1], d[ok, 0])
    return out


def _wrap_abs(a: np.ndarray) -> np.ndarray:
    return np.abs(np.remainder(a + math.pi, 2 * math.pi) - math.pi)


def _direction_table(rm: RadioMap, bins: int = 12, k: int = 3) -> np.ndarray:
    """The map's own forward/backward log-ratio per bin of [0, pi] (leave one session out)."""
    phi = _walk_dirs(rm)
    rows = np.flatnonzero(np.isfinite(phi))
    rows = np.sort(np.random.default_rng(0).choice(rows, min(3000, len(rows)), replace=False))
    res = KnnLocator(rm, KnnConfig(k=k + 30, metric="sorensen")).locate(rm.fingerprints.rows(rows))
    idx, dist = res.neighbours, res.distances
    safe = np.maximum(idx, 0)
    other = (idx >= 0) & (rm.session_ids[safe] != rm.session_ids[rows][:, None])
    use = other & (np.cumsum(other, axis=1) <= k) & np.isfinite(phi[safe])
    w = np.where(use, 1.0 / (np.where(use, dist, 0.0) + WEIGHT_EPS_DB), 0.0)
    keep = w.sum(axis=1) > 0
    w = w[keep] / w[keep].sum(axis=1, keepdims=True)
    delta = np.nan_to_num(_wrap_abs(phi[safe[keep]] - phi[rows[keep]][:, None]))
    b = np.minimum((delta / math.pi * bins).astype(int), bins - 1)
    counts = np.bincount(b.ravel(), weights=w.ravel(), minlength=bins) + 20.0 / bins
    logp = np.log(counts / counts.sum())
    return 0.5 * (logp - logp[::-1])


def main(argv: list[str]) -> int:
    if len(argv) != 3 or argv[2] not in MODES:
        print(__doc__, file=sys.stderr)
        return 2
    folder, folds, mode = argv
    walks = [w for w in read_survey([folder]) if len(w.landmarks) >= 2 and len(w.scans) and len(w.steps) >= 2]
    errs: dict[str, list[np.ndarray]] = defaultdict(list)
    angles: list[np.ndarray] = []
    for _, test in held_out_folds(walks, None if folds == "route" else int(folds), 0):
        train = [w for i, w in enumerate(walks) if i not in set(test)]
        rm = oracle_radio_map(train)
        maps = {"single": rm}
        if mode == "cells":
            maps.update({f"cell {c:g} m, share {s:g}": _cell_map(train, c, s) for c in (1.0, 2.0, 3.0) for s in (0.0, 0.5)})
        locs = {name: KnnLocator(m, KnnConfig(k=3, metric="sorensen")) for name, m in maps.items()}
        mw = _map_walks(rm) if mode == "sequence" else None
        md = _walk_dirs(rm) if mode == "directions" else None
        for i in test:
            w = walks[i]
            t, marks = walk_landmarks(w)
            st = np.array([sc.t_ns for sc in w.scans])
            q = rm.encode([sc.readings for sc in w.scans])
            single = locs["single"].locate(q)
            ok = single.valid
            tracks: dict[str, tuple[np.ndarray, np.ndarray]] = {"single": (st[ok], single.xy[ok])}
            for name, loc in locs.items():
                if name != "single":  # a cell map: its own AP index, so the raw readings
                    fx = loc.locate([sc.readings for sc in w.scans])
                    tracks[name] = (st[fx.valid], fx.xy[fx.valid])
            if mode == "sequence":
                D = locs["single"].distances(q)
                c = np.interp(st.astype(float), w.steps.t_ns.astype(float), _arc(w.steps.xy))
                for L in (3.0, 6.0, 10.0):
                    tracks[f"sequence {L:g} m"] = (st[ok], _sequence_fixes(D, c, rm, mw, L)[ok])
            if mode == "shift":
                for delta in (0.5, 1.0, 1.5, 2.0, 3.0, -0.5, -1.0):
                    tracks[f"shift {delta:g} s"] = (st[ok] - int(delta * 1e9), single.xy[ok])
            if mode == "directions":
                th = float(fit_se2(interpolate_xy(w.steps, t), marks)[2])  # ground truth: this statistic only
                v = se2_apply(np.array([0.0, 0.0, th]), interpolate_xy(w.steps, st + 0.7e9) - interpolate_xy(w.steps, st - 0.7e9))
                moving = ok & (np.linalg.norm(v, axis=1) > 0.8)
                nb = single.neighbours[moving]
                a = np.where(nb >= 0, md[np.maximum(nb, 0)], np.nan) - np.arctan2(v[moving, 1], v[moving, 0])[:, None]
                angles.append(_wrap_abs(a[np.isfinite(a)]))
            for name, (tt, xy) in tracks.items():
                if len(tt):
                    errs[name].append(np.linalg.norm(interpolate_xy(PoseTrack(tt, xy, np.zeros(len(tt))), t) - marks, axis=1))
    print(folder, mode, {k: round(float(np.concatenate(v).mean()), 3) for k, v in errs.items()})
    if mode == "directions":
        a = np.concatenate(angles)
        h = np.histogram(a, bins=6, range=(0, math.pi))[0]
        print(f"neighbour vs query direction, 30-deg bins from 0 to 180 deg: {np.round(h / h.sum(), 3).tolist()}; "
              f"same (< 45 deg) {np.mean(a < math.pi / 4):.3f}, opposite (> 135 deg) {np.mean(a > 3 * math.pi / 4):.3f}")
        print("map's forward/backward table g (nats, 15-deg bins):", np.round(_direction_table(oracle_radio_map(walks)), 2).tolist())
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
