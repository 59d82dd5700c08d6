"""Median-window thresholds and edge rules on hand-made fingerprints."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import T0

from graphslam.core.survey.association import associate
from graphslam.core.survey.edges import nearest_per_row, propose_edges, window_thresholds
from graphslam.core.radiomap.fingerprints import rss_distance
from graphslam.core.types import PoseTrack, Scan, Session, Survey

STEP_NS = 500_000_000


def walk(sid: str, fingerprints: list[dict[str, float]], every: int = 4, t0: int = T0) -> Session:
    """A straight walk, 0.7 m steps, one scan at every ``every``-th step."""
    n = every * len(fingerprints) + 1
    t = t0 + np.arange(n, dtype=np.int64) * STEP_NS
    xy = np.column_stack([0.7 * np.arange(n), np.zeros(n)])
    scans = tuple(Scan(int(t[every * i]) + 10, f) for i, f in enumerate(fingerprints))
    return Session(sid, PoseTrack(t, xy, np.zeros(n)), scans)


A_FPS = [
    {"a": -40.0, "b": -60.0},
    {"a": -45.0, "b": -58.0},
    {"a": -50.0, "b": -56.0, "c": -80.0},
    {"a": -55.0, "b": -54.0, "c": -75.0},
    {"a": -60.0, "b": -52.0, "c": -70.0},
]


def test_association_nearest_step_and_gap() -> None:
    s = walk("a", A_FPS)
    late = Scan(int(s.steps.t_ns[-1]) + 5 * 10**9, {"a": -50.0})  # 5 s after the last step
    s = Session("a", s.steps, s.scans + (late,))
    fp = associate(Survey((s,)), max_gap_s=1.5)
    np.testing.assert_array_equal(fp.step, [0, 4, 8, 12, 16])
    assert fp.dropped == 1
    np.testing.assert_allclose(fp.path_m, 0.7 * fp.step)


def test_window_threshold_is_median_of_neighbours_in_window() -> None:
    fp = associate(Survey((walk("a", A_FPS),)))
    thr = window_thresholds(fp, window_steps=8)  # +-4 steps: the adjacent scans only
    d = lambda i, j: rss_distance(A_FPS[i], A_FPS[j])  # noqa: E731
    assert thr[0] == pytest.approx(d(0, 1))
    assert thr[2] == pytest.approx(np.median([d(2, 1), d(2, 3)]))
    assert thr[4] == pytest.approx(d(4, 3))
    thr16 = window_thresholds(fp, window_steps=16)  # +-8 steps: two on each side
    assert thr16[2] == pytest.approx(np.median([d(2, 0), d(2, 1), d(2, 3), d(2, 4)]))
    lonely = window_thresholds(fp, window_steps=2)  # nothing else within +-1 step
    assert np.isnan(lonely).all()


def _edges(sessions: list[Session], **kw: float) -> tuple[set[tuple[int, int]], object]:
    fp = associate(Survey(tuple(sessions)))
    thr = window_thresholds(fp, window_steps=8)
    args = dict(exclude_same_session_s=30.0, exclude_same_session_m=10.0, max_per_fingerprint=10, min_common_aps=1)
    args.update(kw)
    e = propose_edges(fp, thr, **args)
    return {(int(i), int(j)) for i, j in zip(e.i, e.j)}, fp


def brute_force_pairs(fps: list[dict[str, float]], thr: np.ndarray, allowed: np.ndarray) -> set[tuple[int, int]]:
    """The paper's rule straight from its definition: d(k, q) < d_med(k) for either end."""
    out = set()
    for k in range(len(fps)):
        for q in range(len(fps)):
            if k != q and allowed[k, q] and rss_distance(fps[k], fps[q]) < thr[k]:
                out.add((min(k, q), max(k, q)))
    return out


def test_edges_follow_the_threshold_rule_between_walks() -> None:
    b_fps = [{"x": -40.0, "y": -60.0}, {"x": -45.0}, dict(A_FPS[3]), {"x": -55.0, "y": -50.0}]
    pairs, fp = _edges([walk("a", A_FPS), walk("b", b_fps, t0=T0 + 10**12)])
    thr = window_thresholds(fp, window_steps=8)
    cross = fp.session[:, None] != fp.session[None, :]
    assert pairs == brute_force_pairs(A_FPS + b_fps, thr, cross)
    # b's third scan (global index 5 + 2 = 7) equals a's fourth (index 3); b's other scans share no AP with a
    assert (3, 7) in pairs and all(j == 7 for _, j in pairs)


def test_no_edge_within_a_walk_when_near_in_time_or_distance() -> None:
    # the same fingerprint again 12 steps (6 s, 8.4 m) later: near in time -> no edge
    fps = A_FPS[:3] + [dict(A_FPS[0])] + A_FPS[3:]
    pairs, _ = _edges([walk("a", fps)])
    assert pairs == set()
    # ... far in time, but near along the path: still no edge
    pairs, _ = _edges([walk("a", fps)], exclude_same_session_s=1.0, exclude_same_session_m=10.0)
    assert pairs == set()
    # far in both (> 1 s and > 5 m apart): every pair below threshold is a loop closure
    pairs, fp = _edges([walk("a", fps)], exclude_same_session_s=1.0, exclude_same_session_m=5.0)
    far = np.abs(fp.path_m[:, None] - fp.path_m[None, :]) >= 5.0
    assert pairs == brute_force_pairs(fps, window_thresholds(fp, window_steps=8), far)
    assert (0, 3) in pairs  # the repeated fingerprint, 8.4 m along the path


def test_cap_keeps_most_similar_partners() -> None:
    base = {"a": -50.0, "b": -60.0, "c": -70.0}
    others = [
        walk(f"w{k}", [{"a": -50.0 - k * 0.5, "b": -60.0, "c": -70.0}, {"q": -40.0}, {"q": -41.0}], t0=T0 + k * 10**12)
        for k in range(1, 6)
    ]
    src = walk("src", [base, {"z": -40.0}, {"z": -41.0}])
    pairs, fp = _edges([src] + others, max_per_fingerprint=2)
    partners = {j for i, j in pairs if i == 0}
    # fingerprint 0 keeps its two most similar partners (w1 and w2 first scans: indices 3 and 6);
    # others may still link to it from their own side, but never more than 2 each
    assert {3, 6} <= partners
    counts = np.bincount(np.array([p for pr in pairs for p in pr]), minlength=len(fp))
    assert counts[3] <= 2 + 1 and counts[6] <= 2 + 1


def test_min_common_aps() -> None:
    a = walk("a", [{"a": -50.0, "b": -50.0}, {"c": -40.0}, {"c": -45.0}])
    b = walk("b", [{"a": -50.0, "d": -90.0}, {"e": -40.0}, {"e": -41.0}], t0=T0 + 10**12)
    pairs_1, _ = _edges([a, b], min_common_aps=1)
    pairs_2, _ = _edges([a, b], min_common_aps=2)
    assert (0, 3) in pairs_1 and (0, 3) not in pairs_2


def _sim_edges(candidates: str, **kw: int) -> tuple[set[tuple[int, int]], object]:
    from graphslam.sim import simulate

    fp = associate(simulate("paper", seed=3, size=0.3).survey)  # 2 walks, 563 fingerprints
    thr = window_thresholds(fp, window_steps=20)
    e = propose_edges(
        fp, thr, exclude_same_session_s=30.0, exclude_same_session_m=10.0, max_per_fingerprint=3, min_common_aps=3,
        candidates=candidates, **kw,
    )
    assert np.all(e.common_aps >= 3)
    return {(int(i), int(j)) for i, j in zip(e.i, e.j)}, e


def test_ivf_candidates_find_the_exact_edges() -> None:
    exact, ex = _sim_edges("exact")
    assert len(exact) > 300
    # every cluster probed and every fingerprint a neighbour: the exact edge set, the same distances
    everything, ev = _sim_edges("ivf", ivf_neighbours=600, ivf_probes=1000)
    assert everything == exact
    np.testing.assert_allclose(np.sort(ev.rss_distance), np.sort(ex.rss_distance), rtol=1e-9)
    # the defaults (32 neighbours, 8 probes) miss almost none of them
    approx, _ = _sim_edges("ivf")
    assert len(approx & exact) >= 0.97 * len(exact)
    with pytest.raises(ValueError, match="candidates"):
        _sim_edges("all")


def test_auto_candidates_switch_to_ivf_above_the_configured_size() -> None:
    from graphslam.config import load_config
    from graphslam.core.survey.align import edge_candidates

    cfg = load_config(None, {"edges": {"ivf_above_fingerprints": 1000}})
    assert edge_candidates(cfg, 1000) == "exact" and edge_candidates(cfg, 1001) == "ivf"
    assert edge_candidates(load_config(None, {"edges": {"candidates": "exact"}}), 10**6) == "exact"


@pytest.mark.parametrize("m", [1, 2, 3, 5])
def test_nearest_per_row_is_the_sort_rule(m: int) -> None:
    """Each row's m nearest partners, ties to the lower column, in (row, distance, column) order: the
    same pairs as sorting every pair, also with many equal distances and repeated pairs."""
    rng = np.random.default_rng(m)
    for _ in range(50):
        n_pairs = int(rng.integers(0, 300))
        i = rng.integers(0, 20, n_pairs)
        j = rng.integers(0, 20, n_pairs)
        d = rng.integers(0, 4, n_pairs).astype(float)  # few values: ties everywhere
        order = np.lexsort((j, d, i))
        si, sj, sd = i[order], j[order], d[order]
        keep = (np.arange(n_pairs) - np.searchsorted(si, si, side="left")) < m
        got = nearest_per_row(i, j, d, m)
        for a, b in zip(got, (si[keep], sj[keep], sd[keep])):
            np.testing.assert_array_equal(a, b)
