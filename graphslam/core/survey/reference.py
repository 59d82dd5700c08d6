"""A surveyed radio map as anchors: crowd walks join a site's existing survey.

A reference map (fingerprints at known site positions: a professional survey, last year's, another
tool's) is held fixed in the site frame. The crowd's walks are tied to it as they are to each other:

1. **Matches for placement**: each crowd fingerprint's ``k`` most similar reference fingerprints by
   the placement's power-cosine similarity (``graphslam.core.radiomap.similarity``: a constant RSS
   offset between phones cancels; the reference may come from another device).
2. **The site's rotation**: every walk is turned into east/north by its heading; the site frame's one
   rotation from east/north is the rotation under which the crowd's matches agree best: for each
   rotation of a grid, every unit's (walk's, or magnetic unit's) best translation vote onto the
   reference, summed over units (``site_rotation``).
3. **Placement**: the reference is a placed, held body; units join it by map growth on their reference
   matches alone (``graphslam.core.survey.components.place_units``) — the repetitions of a route,
   held together by the field, vote as one. Units that match no reference place stay apart.
4. **Factors**: a crowd fingerprint and a reference fingerprint whose eq.-9 distance is below the
   crowd fingerprint's own median-window threshold (the edge rule between walks, ``edges``) get the
   same fuzzy WiFi factor as two crowd fingerprints, with the reference end fixed
   (``reference_edges``); the ones the placement puts beyond the gate are left out, as between walks.
   The reference's device may hear every AP louder or weaker than the crowd's phones by about one
   constant: the power cosine of 1 cancels it, eq. 9 does not. It is estimated where the two are most
   alike (``rss_offset_db``: every crowd fingerprint's best match) and taken off the reference's
   readings for the edges.
5. **The reference's field** (a previous graphslam survey's ``magnetic_map.parquet``: its walks' field at
   their solved positions): each walk of the reference is a held sequence of the field along its path
   (``field_sequences``). Once the crowd is placed, every window of a placed crowd walk is compared with
   the reference's stretches near where the placement puts it, with the threshold from surrogates and
   the link rule between walks (``graphslam.core.survey.magnetic``); a link whose stretches lie within
   ``magnetic.d_max_m`` of each other gives magnetic factors from the crowd's steps to the reference's
   held samples (``field_ties``). The field corrects a placement by metres where WiFi leaves it loose;
   it places no walk (a walk the WiFi does not place has no place to search from).

Frames: site (the reference's, metres); the crowd's dead reckoning turned by the headings (east/north)
and by the site's rotation.
"""

from __future__ import annotations

import logging
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import sparse

from graphslam.core.common.deferred import Deferred
from graphslam.core.radiomap.fingerprints import DistanceEngine, FingerprintMatrix
from graphslam.core.radiomap.magnetic_map import MagneticMap
from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.core.radiomap.similarity import Matches, PowerCosine, top_matches_between
from graphslam.core.survey.edges import nearest_per_row
from graphslam.core.survey.magnetic import (
    MagneticParams, MagneticSequences, along, factor_pairs, null_threshold, walk_links, walk_sequences, window_matches,
    windows,
)
from graphslam.core.survey.placement import GrowthParams, hough_profile
from graphslam.core.types import Survey

log = logging.getLogger(__name__)


def on_index(fm: FingerprintMatrix, bssids: tuple[str, ...]) -> FingerprintMatrix:
    """``fm``'s rows over another AP index: readings of APs outside it count in ``extra_sq``/``extra_n``,
    as ``FingerprintMatrix.from_scans`` with a given index does (eq. 9 unchanged)."""
    col = {b: i for i, b in enumerate(bssids)}
    to = np.array([col.get(b, -1) for b in fm.bssids], np.int64)
    v = fm.values.tocoo()
    inside = to[v.col] >= 0
    vals = sparse.csr_matrix((v.data[inside], (v.row[inside], to[v.col[inside]])), shape=(len(fm), len(bssids)))
    extra_sq = fm.extra_sq + np.bincount(v.row[~inside], weights=v.data[~inside] ** 2, minlength=len(fm))
    extra_n = fm.extra_n + np.bincount(v.row[~inside], minlength=len(fm))
    return FingerprintMatrix(bssids, vals, fm.missing_dbm, extra_sq, extra_n)


@dataclass(frozen=True, eq=False)
class ReferenceLinks:
    """How the crowd's fingerprints (rows of ``FingerprintNodes``) relate to the reference's."""

    xy: NDArray[np.float64]  # (R, 2) the reference fingerprints' site positions
    match_i: NDArray[np.int64]  # (M,) crowd fingerprint
    match_j: NDArray[np.int64]  # (M,) its similar reference fingerprint
    similarity: NDArray[np.float64]  # (M,) power cosine
    edge_i: NDArray[np.int64]  # (E,) crowd fingerprint of a reference edge
    edge_j: NDArray[np.int64]  # (E,) its reference fingerprint
    edge_d: NDArray[np.float64]  # (E,) eq.-9 distance (dB)
    rss_offset_db: float = 0.0  # the reference's readings minus the crowd's at one place (taken off for the edges)

    def __len__(self) -> int:
        return len(self.xy)


def reference_links(
    crowd: FingerprintMatrix, thresholds: NDArray[np.float64], ref: RadioMap, *, matches_per_fingerprint: int,
    scale_db: float, max_per_fingerprint: int, min_common_aps: int, block_rows: int = 2048,
) -> ReferenceLinks:
    """Matches (placement) and edges (factors) between the crowd's fingerprints and the reference's
    (module docstring, 1 and 4). ``thresholds``: each crowd fingerprint's median-window threshold."""
    bssids = tuple(sorted(set(crowd.bssids) | set(ref.fingerprints.bssids)))
    c, r = on_index(crowd, bssids), on_index(ref.fingerprints, bssids)
    # placement matches: power cosine of crowd rows against reference rows, top k per crowd row
    pc = PowerCosine.of(FingerprintMatrix(bssids, sparse.vstack([c.values, r.values]).tocsr(), c.missing_dbm), scale_db)
    top = top_matches_between(PowerCosine(pc.unit[: len(c)], scale_db), PowerCosine(pc.unit[len(c):], scale_db),
                              matches_per_fingerprint)
    offset = rss_offset_db(c, r, top)
    ei, ej, ed = [], [], []
    engine = DistanceEngine(louder(r, -offset))  # the reference at the crowd's level (module docstring, 4)
    limit = np.where(np.isfinite(thresholds), thresholds, np.nan)  # no threshold (NaN or inf): no edge
    for a in range(0, len(c), block_rows):
        b = min(len(c), a + block_rows)
        # edges: below the crowd row's own threshold, the nearest few (ties to the lower reference row)
        ri, ci, d = engine.pairs_below(c.rows(slice(a, b)), limit[a:b], min_common=min_common_aps)
        ri, ci, d = nearest_per_row(ri, ci, d, max(1, max_per_fingerprint))
        ei.append(ri + a)
        ej.append(ci)
        ed.append(d)

    def cat(parts: list, dtype: object) -> NDArray:
        return np.concatenate(parts).astype(dtype) if parts else np.zeros(0, dtype)

    out = ReferenceLinks(np.asarray(ref.xy, float), top.i, top.j, top.similarity,
                         cat(ei, np.int64), cat(ej, np.int64), cat(ed, np.float64), offset)
    log.info("reference map: %d fingerprints; %d placement matches and %d edges from the crowd's %d fingerprints; "
             "its readings %+.1f dB from the crowd's", len(out), len(out.match_i), len(out.edge_i), len(c), offset)
    return out


# crowd x reference fingerprint pairs from which ``reference_links_job`` runs on a thread: the links' products
# (power cosine, eq. 9) release the GIL and overlap the crowd's own edge search (paper size 4, ~9M pairs:
# 4.48 -> 4.31 s; size 12, ~80M: 14.3 -> 13.2 s); IPIN 2023 floor -2's 0.55M pairs: slower on a thread
LINKS_THREAD_MIN_PAIRS = 4_000_000


def reference_links_job(crowd: FingerprintMatrix, thresholds: NDArray[np.float64], ref: RadioMap,
                        **kwargs: Any) -> Deferred[ReferenceLinks]:
    """``reference_links(crowd, thresholds, ref, **kwargs)``, started on a thread now when the crowd and the
    reference are large (``LINKS_THREAD_MIN_PAIRS``), else computed when its ``result()`` is asked for."""
    return Deferred(reference_links, crowd, thresholds, ref, thread=len(crowd) * len(ref) >= LINKS_THREAD_MIN_PAIRS,
                    name="reference-links", **kwargs)


def rss_offset_db(crowd: FingerprintMatrix, ref: FingerprintMatrix, top: Matches, min_common: int = 3) -> float:
    """How much louder (dB) the reference hears an AP than the crowd at one place: over every crowd
    fingerprint's most similar reference fingerprint (``top``: the placement's matches, one AP index)
    sharing at least ``min_common`` APs, the median of their mean reading difference over the APs both
    heard. 0 when no pair qualifies. On IPIN 2023 floor -2: +5.3 dB (its reference made of repetition
    1's scans), and +5 dB more for every 5 dB added to the reference's readings."""
    if not len(top.i):
        return 0.0
    order = np.lexsort((-top.similarity, top.i))
    first = order[np.concatenate([[True], top.i[order][1:] != top.i[order][:-1]])]
    a, b = crowd.values[top.i[first]], ref.values[top.j[first]]
    both = a.multiply(b) > 0  # APs both heard
    n = np.asarray(both.sum(axis=1)).ravel()
    diff = np.asarray(b.multiply(both).sum(axis=1)).ravel() - np.asarray(a.multiply(both).sum(axis=1)).ravel()
    ok = n >= max(1, min_common)
    return float(np.median(diff[ok] / n[ok])) if ok.any() else 0.0


def louder(fm: FingerprintMatrix, db: float) -> FingerprintMatrix:
    """``fm`` with every reading ``db`` louder (negative: weaker); a reading that falls to the missing
    level or below is no reading. APs outside the index (``extra_*``) are left as they are."""
    if db == 0.0:
        return fm
    v = fm.values.copy()
    v.data = v.data + db
    v.data[v.data <= 0.0] = 0.0
    v.eliminate_zeros()
    return FingerprintMatrix(fm.bssids, v, fm.missing_dbm, fm.extra_sq, fm.extra_n)


def place_spacing(xy: NDArray[np.float64]) -> float | None:
    """The median distance (m) from each place a reference measured (its distinct positions: several
    fingerprints at one point are one place) to the nearest other place; None for fewer than two places.
    What it does to a survey on it (IPIN 2023 floor -2's reference thinned): walks join as well up to
    2.2 m with several passes' scans near each place, far fewer at 2.9-4.6 m with one, and at 8.6 m
    wrongly (``lab/survey/reference_density.py``; the simulator's richer WiFi places every walk at 8.5 m)."""
    from scipy.spatial import cKDTree

    places = np.unique(np.asarray(xy, float).reshape(-1, 2), axis=0)
    if len(places) < 2:
        return None
    d, _ = cKDTree(places).query(places, k=2)
    return float(np.median(d[:, 1]))


def site_rotation(
    unit_of_row: NDArray[np.int64], unit_xy: NDArray[np.float64], links: ReferenceLinks, params: GrowthParams,
) -> tuple[float, float]:
    """(rotation of the site frame from east/north, its vote support): the rotation under which the
    units' reference matches agree best (module docstring, 2): every 3 degrees around the circle, then
    every half degree within 4 degrees of the best. ``unit_xy``: each crowd fingerprint in its unit's
    frame (east/north); ``unit_of_row``: its unit."""
    if not len(links.match_i):
        return 0.0, 0.0
    w = np.power(np.clip(links.similarity, 0.0, 1.0), params.weight_power)
    u = unit_of_row[links.match_i]
    order = np.argsort(u, kind="stable")
    bounds = np.flatnonzero(np.concatenate([[True], np.diff(u[order]) != 0, [True]]))
    groups = [order[g0:g1] for g0, g1 in zip(bounds[:-1], bounds[1:]) if g1 - g0 >= 3]

    def profile(thetas: NDArray, p: GrowthParams) -> NDArray:
        def one(sel: NDArray) -> NDArray:
            return hough_profile(unit_xy[links.match_i[sel]], links.xy[links.match_j[sel]], w[sel], thetas, p)

        # units on two threads: the grids' blur, most of the cost, releases the GIL (summed in unit order)
        with ThreadPoolExecutor(max_workers=min(2, os.cpu_count() or 1, max(len(groups), 1))) as pool:
            total = np.zeros(len(thetas))
            for part in pool.map(one, groups):
                total += part
        return total

    coarse = np.radians(np.arange(0.0, 360.0, 3.0))
    # the coarse pass only picks the fine pass's window: a quarter of the cells (twice as coarse), as
    # the 3-degree step already smears a unit's far fingerprints by metres; the blur is most of its cost
    c0 = coarse[int(np.argmax(profile(coarse, replace(params, max_grid_cells=params.max_grid_cells // 4))))]
    fine = c0 + np.radians(np.arange(-4.0, 4.01, 0.5))
    total = profile(fine, params)
    best = int(np.argmax(total))
    return float(np.arctan2(np.sin(fine[best]), np.cos(fine[best]))), float(total[best])


def field_sequences(field: MagneticMap, sample_m: float, first_node: int) -> MagneticSequences:
    """The reference's walks (``field``'s samples of one ``session_id``, in time order) resampled every
    ``sample_m`` of their path (site frame), as ``walk_sequences`` does a crowd walk's dead reckoning;
    sample ``q``'s node is ``first_node + q`` (held nodes: ``field_ties``)."""
    ids = np.asarray(field.session_ids)
    walks: list[tuple[NDArray, NDArray, NDArray, NDArray] | None] = []
    n = 0
    for sid in dict.fromkeys(ids.tolist()):
        rows = np.flatnonzero(ids == sid)
        rows = rows[np.argsort(np.asarray(field.t_ns)[rows], kind="stable")]
        xy, f = np.asarray(field.xy)[rows], np.asarray(field.features)[rows]
        d = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
        on = np.concatenate([[True], np.diff(d) > 1e-6])  # standing still is one place
        d, xy, f = d[on], xy[on], f[on]
        if len(d) < 2:
            continue
        q = np.arange(0.0, d[-1] + 1e-9, sample_m)
        walks.append((along(q, d, f), along(q, d, xy), first_node + n + np.arange(len(q), dtype=np.int64), q))
        n += len(q)
    return MagneticSequences.of_walks(walks)


@dataclass(frozen=True, eq=False)
class FieldTies:
    """Magnetic factors from placed crowd walks to a reference's field (module docstring, 5)."""

    xy: NDArray[np.float64]  # (Q, 2) the reference's field samples (site frame), held
    pairs: NDArray[np.int64]  # (P, 2) (crowd step node, row of ``xy``)
    links: int  # crowd walk - reference walk links kept
    walks: NDArray[np.int64]  # crowd walks with a factor
    reference_walks: int  # the reference's walks with a sequence
    threshold: float  # the score a window match needed

    def __len__(self) -> int:
        return len(self.pairs)


def field_ties(
    survey: Survey, node_offsets: NDArray[np.int64], transforms: NDArray[np.float64], placed: NDArray[np.bool_],
    field: MagneticMap, p: MagneticParams, *, dr_xy: NDArray[np.float64], node_walk: NDArray[np.int64],
    max_offset_m: float, per_place: int,
) -> FieldTies:
    """Magnetic factors of the walks ``placed`` marks (``transforms``: dead reckoning -> site) to the
    reference's field (module docstring, 5). Every window of a placed walk is compared with the stretches
    of each reference walk that pass within ``p.search_m`` of it (the nearest sample anchors the search);
    a link (the window-match rule between walks) whose stretches lie within ``max_offset_m`` of each other
    gives its node pairs, thinned as between walks (``factor_pairs``: ``per_place`` partners a place).
    ``dr_xy``, ``node_walk``: every step node's dead-reckoned position and walk."""
    from scipy.spatial import cKDTree

    n_nodes, n_walks = int(node_offsets[-1]), len(survey)
    crowd = walk_sequences(survey, node_offsets, p.sample_m)
    ref = field_sequences(field, p.sample_m, first_node=n_nodes)
    empty = FieldTies(ref.xy, np.zeros((0, 2), np.int64), 0, np.zeros(0, np.int64), ref.n_walks, 1.0)
    if not len(crowd.features) or not len(ref.features) or not placed.any():
        return empty
    walk = crowd.walk_of()
    T = transforms[walk]
    c, s = np.cos(T[:, 2]), np.sin(T[:, 2])
    site = np.column_stack([c * crowd.xy[:, 0] - s * crowd.xy[:, 1] + T[:, 0],
                            s * crowd.xy[:, 0] + c * crowd.xy[:, 1] + T[:, 1]])
    seq = MagneticSequences(
        np.concatenate([crowd.offsets, crowd.offsets[-1] + ref.offsets[1:]]),
        np.concatenate([crowd.features, ref.features]), np.concatenate([site, ref.xy]),
        np.concatenate([crowd.node, ref.node]), np.concatenate([crowd.path_m, ref.path_m]),
    )
    win = windows(seq, p)
    # anchors: each placed crowd window's centre and, per reference walk, its nearest sample within search_m
    on = (win.walk < n_walks) & placed[np.minimum(win.walk, n_walks - 1)]
    centre = win.start[on] + (p.window - 1) // 2
    ref_walk = np.repeat(np.arange(ref.n_walks), np.diff(ref.offsets))
    k = int(min(len(ref.xy), 32))
    d, j = cKDTree(ref.xy).query(seq.xy[centre], k=k, distance_upper_bound=p.search_m)
    d, j = np.reshape(d, (len(centre), k)), np.reshape(j, (len(centre), k))
    a, b = np.repeat(centre, k), j.ravel()
    ok = np.isfinite(d.ravel())
    a, b = a[ok], b[ok]
    key = a * (ref.n_walks + 1) + ref_walk[b]
    _, first = np.unique(key, return_index=True)  # query order: the nearest per (window, reference walk)
    aa, ab = a[first], b[first] + int(crowd.offsets[-1])
    if not len(aa):
        return empty
    threshold = null_threshold(seq, win, p, aa, ab)
    links = walk_links(seq, win, window_matches(seq, win, p, aa, ab), np.zeros(seq.n_walks), threshold, p)
    links = links.subset(np.linalg.norm(links.translation, axis=1) <= max_offset_m)
    if not len(links):
        return replace(empty, threshold=threshold)
    # thinned as between walks: the reference's samples are nodes of walks of their own after the steps
    xy_all = np.concatenate([dr_xy, ref.xy])
    walk_all = np.concatenate([node_walk, n_walks + ref_walk])
    pn = links.pair_nodes[factor_pairs(links, xy_all, walk_all, p.pair_every_m, per_place)]
    pairs = np.column_stack([pn[:, 0], pn[:, 1] - n_nodes]).astype(np.int64)
    out = FieldTies(ref.xy, pairs, int(len(links)), np.unique(node_walk[pairs[:, 0]]), ref.n_walks, threshold)
    log.info("reference field: %d walks of it; %d links to %d crowd walks (window matches above %.3f), %d factors",
             ref.n_walks, out.links, len(out.walks), threshold, len(out))
    return out
