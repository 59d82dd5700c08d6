"""Map-growth placement: power-cosine similarity, standstill scans, Hough registration, growth."""

from __future__ import annotations

import numpy as np
import pytest

from graphslam.core.radiomap.fingerprints import FingerprintMatrix
from graphslam.core.radiomap.similarity import PowerCosine
from graphslam.core.survey.association import associate
from graphslam.core.common.geometry import se2_apply
from graphslam.core.survey.placement import GrowthParams, grow_placement, hough_se2, refine_rigid
from graphslam.core.types import PoseTrack, Scan, Session, Survey


def _field(xy: np.ndarray, aps: np.ndarray, offset_db: float = 0.0) -> np.ndarray:
    """Noise-free log-distance RSS of every AP at every position (dBm), phone offset added."""
    d = np.linalg.norm(xy[:, None] - aps[None], axis=2)
    return -35.0 - 25.0 * np.log10(np.maximum(d, 1.0)) + offset_db


def test_power_cosine_ignores_a_phone_offset_and_eq9_does_not() -> None:
    rng = np.random.default_rng(0)
    aps = rng.uniform(0, 60, (12, 2))
    xy = rng.uniform(0, 60, (30, 2))
    a = FingerprintMatrix.from_dense(_field(xy, aps), [f"ap{k}" for k in range(12)], min_rssi_dbm=-200)
    b = FingerprintMatrix.from_dense(_field(xy, aps, offset_db=-7.0), [f"ap{k}" for k in range(12)], min_rssi_dbm=-200)
    ua, ub = PowerCosine.of(a).unit, PowerCosine.of(b).unit
    # the same places heard by a phone 7 dB less sensitive: identical unit vectors, cosine 1
    assert np.allclose(ua.toarray(), ub.toarray())
    assert np.allclose(PowerCosine.of(a).pairs(np.arange(30), np.arange(30)), 1.0)
    assert not np.allclose(a.values.toarray(), b.values.toarray())


def test_top_matches_skip_the_own_walk_and_find_the_nearest_place() -> None:
    rng = np.random.default_rng(1)
    aps = rng.uniform(0, 80, (20, 2))
    xy = np.column_stack([np.linspace(0, 80, 40), np.full(40, 10.0)])
    walk = np.repeat([0, 1], 20)
    # walk 1 re-walks walk 0's positions 0.2 m aside
    xy[20:] = xy[:20] + [0.0, 0.2]
    fm = FingerprintMatrix.from_dense(_field(xy, aps), [f"ap{k}" for k in range(20)], min_rssi_dbm=-200)
    sim = PowerCosine.of(fm)
    m = sim.top_matches(walk, 1, block_rows=7)  # blocks smaller than a walk: same answer as one block
    assert (walk[m.i] != walk[m.j]).all()
    assert np.array_equal(np.sort(m.j[m.i < 20]), np.arange(20, 40))  # each scan's twin of the other walk
    m2 = sim.top_matches(walk, 3, block_rows=512)
    assert len(m2) == 120 and np.allclose(np.sort(sim.pairs(m2.i, m2.j)), np.sort(m2.similarity))


def _session(sid: str, t_steps_s: np.ndarray, xy: np.ndarray, t_scans_s: np.ndarray) -> Session:
    steps = PoseTrack((t_steps_s * 1e9).astype(np.int64), xy, np.zeros(len(xy)))
    scans = tuple(Scan(int(t * 1e9), {"ap": -60.0}) for t in t_scans_s)
    return Session(sid, steps, scans)


def test_scans_while_standing_still_attach_to_the_pose_where_the_walker_stands() -> None:
    # steps every 0.5 s for 5 s, a 20 s pause, 5 s more steps; scans every 2 s from -6 s to 36 s
    t = np.concatenate([np.arange(0, 5, 0.5), np.arange(25, 30, 0.5)])
    xy = np.column_stack([np.arange(len(t)) * 0.7, np.zeros(len(t))])
    scans = np.arange(-6.0, 36.0, 2.0)
    s = Survey((_session("w", t, xy, scans),))
    strict = associate(s, max_gap_s=1.5)
    still = associate(s, max_gap_s=1.5, standstill_max_s=30.0)
    # dropped by the nearest-step rule: 3 before the first step, 8 in the pause, 2 after the last
    assert strict.standstill == 0 and strict.dropped == 13 and len(strict) + strict.dropped == len(scans)
    assert still.standstill == 13 and still.dropped == 0
    pause = (scans > 7.0) & (scans < 23.0)  # more than 1.5 s from every step
    before = scans < -1.5
    at = dict(zip(still.t_ns.tolist(), still.step.tolist()))
    for ts in scans[pause]:
        assert at[int(ts * 1e9)] == 9  # the last step before the pause: where the walker stands
    for ts in scans[before]:
        assert at[int(ts * 1e9)] == 0
    # scans beyond the standstill limit are still dropped
    short = associate(s, max_gap_s=1.5, standstill_max_s=3.0)
    assert short.standstill == 2 and short.dropped == 11  # -2 s and 32 s only; the 20.5 s pause is too long


def test_hough_recovers_a_rigid_transform_and_reports_no_margin_for_a_symmetric_walk() -> None:
    rng = np.random.default_rng(2)
    src = rng.uniform(-20, 20, (60, 2))
    T = np.array([12.0, -7.0, np.radians(48.0)])
    dst = se2_apply(T, src)
    est, best, second = hough_se2(src, dst, np.ones(60), GrowthParams())
    assert np.linalg.norm(se2_apply(est, src) - dst, axis=1).mean() < 1.0
    assert best > 2 * second
    # a straight walk matched to a straight corridor: sliding along it is as good: no margin
    line = np.column_stack([np.linspace(0, 30, 31), np.zeros(31)])
    j = np.arange(31)
    w = np.ones(31 * 31)
    _, b2, s2 = hough_se2(line[np.repeat(j, 31)], line[np.tile(j, 31)], w, GrowthParams())
    assert b2 - s2 < 0.1 * b2


def test_rigid_refinement_closes_matched_points_from_a_perturbed_start() -> None:
    rng = np.random.default_rng(3)
    truth = np.array([[0.0, 0.0, 0.0], [5.0, 3.0, 0.4], [-4.0, 8.0, -1.0]])
    walk = np.repeat([0, 1, 2], 30)
    world = rng.uniform(0, 30, (90, 2))
    world[30:60] = world[:30] + rng.normal(0, 0.1, (30, 2))  # walks 1 and 2 revisit walk 0's places
    world[60:] = world[:30] + rng.normal(0, 0.1, (30, 2))
    local = np.concatenate([se2_apply(_inv(truth[w]), world[walk == w]) for w in range(3)])
    i = np.concatenate([np.arange(30), np.arange(30), np.arange(30, 60)])
    j = np.concatenate([np.arange(30, 60), np.arange(60, 90), np.arange(60, 90)])
    start = truth + [[0, 0, 0], [2.0, -1.5, 0.1], [-1.0, 2.0, -0.08]]
    out = refine_rigid(start, np.arange(3), 0, walk, local, i, j, np.ones(len(i)), GrowthParams())
    assert np.abs(out - truth).max() < 0.05
    assert np.array_equal(out[0], start[0])  # the fixed walk stays


def _inv(T: np.ndarray) -> np.ndarray:
    c, s = np.cos(T[2]), np.sin(T[2])
    return np.array([-(c * T[0] + s * T[1]), -(-s * T[0] + c * T[1]), -T[2]])


@pytest.mark.parametrize("lonely", [False, True])
def test_growth_places_repeated_walks_and_leaves_an_unmatched_one_out(lonely: bool) -> None:
    rng = np.random.default_rng(4)
    aps = rng.uniform(-10, 70, (25, 2))
    path = np.column_stack([np.linspace(0, 60, 50), 8 * np.sin(np.linspace(0, 6, 50))])
    truth = [np.array([0.0, 0.0, 0.0]), np.array([3.0, -2.0, 2.0]), np.array([-6.0, 4.0, -1.2])]
    locals_, rss, walk = [], [], []
    for w, T in enumerate(truth):
        world = path + rng.normal(0, 0.3, path.shape)
        locals_.append(se2_apply(_inv(T), world))
        rss.append(_field(world, aps, offset_db=-4.0 * w) + rng.normal(0, 2.0, (50, 25)))
        walk.append(np.full(50, w))
    if lonely:  # a fourth walk in a place no other walk has been, hearing other APs
        far = path + [500.0, 500.0]
        locals_.append(far)
        rss.append(_field(far, aps + [500.0, 500.0]) + rng.normal(0, 2.0, (50, 25)))
        walk.append(np.full(50, 3))
    xy, walk = np.concatenate(locals_), np.concatenate(walk)
    names = [f"ap{k}" for k in range(25)]
    fm = FingerprintMatrix.from_dense(np.concatenate(rss), names, min_rssi_dbm=-95)
    if lonely:  # its APs are its own
        dense = fm.dense_rssi()
        dense = np.concatenate([np.where(walk[:, None] == 3, -110.0, dense), np.where(walk[:, None] == 3, dense, -110.0)], 1)
        fm = FingerprintMatrix.from_dense(dense, names + [f"far{k}" for k in range(25)], min_rssi_dbm=-95)
    m = PowerCosine.of(fm).top_matches(walk, 5)
    res = grow_placement(int(walk.max()) + 1, walk, xy, m, GrowthParams(), seed=0)
    for w in (1, 2):
        assert res.placed[w]
        placed = se2_apply(res.transforms[w], xy[walk == w])
        true = se2_apply(truth[w], xy[walk == w])
        assert np.linalg.norm(placed - true, axis=1).mean() < 1.0
        assert res.consistency[w] > 0.8
    assert res.order[0] == 0 and res.seed == 0
    if lonely:
        assert not res.placed[3] and "no WiFi matches" in res.reasons[3]


@pytest.mark.parametrize("inside", [True, False])  # matches inside one walk (summed generically), or none
def test_normal_equations_equal_an_explicit_jacobian(inside: bool) -> None:
    # J^T W J and J^T W r accumulated per walk pair must equal the dense products of the stacked
    # Jacobian: gap r = p_a - p_b, d r / d(x, y, theta) = +[I | d_a] (walk a), -[I | d_b] (walk b)
    from graphslam.core.survey.placement import _normal_equations

    rng = np.random.default_rng(3)
    F, m = 4, 60
    ka, kb = rng.integers(-1, F, m), rng.integers(-1, F, m)
    if not inside:  # the diagonal blocks' terms apart from the others' (each match's sides in two walks)
        kb = np.where((kb == ka) & (ka >= 0), (ka + 1) % F, kb)
    assert ((ka == kb) & (ka >= 0)).any() == inside
    da, db, r = rng.normal(size=(m, 2)), rng.normal(size=(m, 2)), rng.normal(size=(m, 2))
    w = rng.uniform(0.1, 2.0, m)
    J = np.zeros((2 * m, 3 * F))
    for k in range(m):
        for walk, d, sign in ((ka[k], da[k], 1.0), (kb[k], db[k], -1.0)):
            if walk < 0:
                continue
            J[2 * k: 2 * k + 2, 3 * walk: 3 * walk + 2] += sign * np.eye(2)
            J[2 * k: 2 * k + 2, 3 * walk + 2] += sign * d
    W = np.repeat(w, 2)
    H, g = _normal_equations(F, ka, kb, da, db, r, w)
    np.testing.assert_allclose(H, J.T @ (W[:, None] * J), atol=1e-12)
    np.testing.assert_allclose(g, J.T @ (W * r.ravel()), atol=1e-12)


def test_top_matches_dense_and_sparse_products_agree(monkeypatch: pytest.MonkeyPatch) -> None:
    # the dense float32 path (many fingerprints over few APs) must pick the sparse path's partners
    import graphslam.core.radiomap.similarity as sim

    rng = np.random.default_rng(5)
    n, a = 300, 12
    rssi = np.where(rng.random((n, a)) < 0.6, rng.uniform(-95, -40, (n, a)), np.nan)
    fm = FingerprintMatrix.from_dense(rssi, tuple(f"ap{i}" for i in range(a)))
    group = np.repeat(np.arange(10), 30)
    pc = PowerCosine.of(fm, 10.0)
    dense = pc.top_matches(group, 4, block_rows=64)
    monkeypatch.setattr(sim, "DENSE_MAX_CELLS", 0)
    sparse_ = pc.top_matches(group, 4, block_rows=64)
    assert set(zip(dense.i.tolist(), dense.j.tolist())) == set(zip(sparse_.i.tolist(), sparse_.j.tolist()))
    assert not (group[dense.i] == group[dense.j]).any()
    np.testing.assert_allclose(np.sort(dense.similarity), np.sort(sparse_.similarity), atol=1e-12)
    # interleaved labels (not contiguous runs) take the boolean mask: no own-walk partner either
    mixed = np.arange(n) % 10
    monkeypatch.setattr(sim, "DENSE_MAX_CELLS", 10**9)
    m = pc.top_matches(mixed, 4, block_rows=64)
    assert len(m) == 4 * n and not (mixed[m.i] == mixed[m.j]).any()


@pytest.mark.parametrize("cells", [10**9, 0])  # the dense float32 product, the sparse one
def test_matches_between_two_sets_are_each_rows_most_similar_of_the_other(
    monkeypatch: pytest.MonkeyPatch, cells: int
) -> None:
    # a crowd's fingerprints against a reference's: each crowd row's k most similar reference rows that
    # share an access point, largest first, ties to the lower row, with their float64 similarity
    import graphslam.core.radiomap.similarity as sim

    rng = np.random.default_rng(9)
    na, nb, a = 150, 70, 12
    rssi = np.where(rng.random((na + nb, a)) < 0.5, rng.uniform(-95, -40, (na + nb, a)), np.nan)
    rssi[na + 5] = rssi[na + 6]  # two identical reference rows: a tie, to the lower one
    rssi[3] = np.nan
    rssi[3, 0] = -50.0
    rssi[na:, 0] = np.nan  # crowd row 3 shares no access point with the reference: no match
    pc = PowerCosine.of(FingerprintMatrix.from_dense(rssi, tuple(f"ap{i}" for i in range(a))), 10.0)
    monkeypatch.setattr(sim, "DENSE_MAX_CELLS", cells)
    k = 4
    m = sim.top_matches_between(PowerCosine(pc.unit[:na], 10.0), PowerCosine(pc.unit[na:], 10.0), k, block_rows=32)
    full = (pc.unit[:na] @ pc.unit[na:].T).toarray()
    for i in range(na):
        want = [j for j in np.lexsort((np.arange(nb), -full[i])) if full[i, j] > 0][:k]
        got = m.j[m.i == i]
        assert list(got) == want if cells == 0 else set(got) == set(want), i
        np.testing.assert_allclose(m.similarity[m.i == i], full[i, got], atol=1e-12)
    assert 3 not in m.i


def test_an_updates_rows_get_the_partners_of_the_whole_survey(monkeypatch: pytest.MonkeyPatch) -> None:
    # ``top_matches(rows=...)`` (an update's new walks against every fingerprint) takes the same
    # products and the same own-walk mask as the whole survey's: the same partners for those rows,
    # on the dense and on the sparse path, with walks in runs and interleaved
    import graphslam.core.radiomap.similarity as sim

    rng = np.random.default_rng(7)
    n, a = 300, 12
    rssi = np.where(rng.random((n, a)) < 0.6, rng.uniform(-95, -40, (n, a)), np.nan)
    fm = FingerprintMatrix.from_dense(rssi, tuple(f"ap{i}" for i in range(a)))
    pc = PowerCosine.of(fm, 10.0)
    rows = np.r_[30:60, 200:215, 290:300]
    for group in (np.repeat(np.arange(10), 30), np.arange(n) % 10):
        for cells in (10**9, 0):  # dense, sparse
            monkeypatch.setattr(sim, "DENSE_MAX_CELLS", cells)
            whole = pc.top_matches(group, 4, block_rows=64)
            part = pc.top_matches(group, 4, block_rows=16, rows=rows)
            mine = np.isin(whole.i, rows)
            assert set(zip(part.i.tolist(), part.j.tolist())) == set(zip(whole.i[mine].tolist(), whole.j[mine].tolist()))
            assert len(part) == 4 * len(rows) and not (group[part.i] == group[part.j]).any()


@pytest.mark.parametrize("k", [1, 3, 5, 9])
def test_each_rows_best_matches_are_its_k_largest_positive_similarities(k: int) -> None:
    """``row_top_k`` (a bound from column groups' maxima, then a sort of the few values above it)
    against the definition: each row's k largest positive values, largest first, ties to the lower
    column; rows narrower or sparser than k, all ties, and zero or masked (-1) rows included."""
    from graphslam.core.radiomap.similarity import TOP_K_GROUP, row_top_k

    rng = np.random.default_rng(k)
    for trial in range(60):
        rows, cols = int(rng.integers(1, 6)), int(rng.integers(1, 6 * TOP_K_GROUP))
        if trial % 2:
            block = (rng.integers(-1, 5, (rows, cols)) / 4).astype(np.float32)  # few values: ties
        else:
            block = (rng.random((rows, cols)) ** 6).astype(np.float32)
        block[0, : cols // 2] = -1.0
        if rows > 1:
            block[1] = 0.0
        ri, ci = row_top_k(block, k)
        for r in range(rows):
            want = sorted((-float(block[r, j]), j) for j in range(cols) if block[r, j] > 0)[:k]
            assert ci[ri == r].tolist() == [j for _, j in want]


def test_votes_taken_a_chunk_of_rotations_at_a_time_equal_one_pass(monkeypatch: pytest.MonkeyPatch) -> None:
    # the vote grid is built a few rotations at a time (bounded temporaries): the sums, the grid's extent
    # and so the placement and its runner-up must be exactly those of one pass over every rotation
    import graphslam.core.survey.placement as placement

    rng = np.random.default_rng(11)
    src = rng.uniform(-30, 30, (200, 2))
    theta, t = 0.7, np.array([12.0, -5.0])
    c, s = np.cos(theta), np.sin(theta)
    dst = src @ np.array([[c, s], [-s, c]]) + t + rng.normal(0, 0.5, (200, 2))
    dst[:40] = rng.uniform(-60, 60, (40, 2))  # wrong matches spread the grid
    w = rng.uniform(0.2, 1.0, 200)
    params = GrowthParams()
    thetas = np.radians(np.arange(0.0, 360.0, 3.0))
    one_pass = placement.hough_se2(src, dst, w, params), placement.hough_profile(src, dst, w, thetas, params)
    monkeypatch.setattr(placement, "_CHUNK", 450)  # two rotations per chunk, the last one short
    chunked = placement.hough_se2(src, dst, w, params), placement.hough_profile(src, dst, w, thetas, params)
    np.testing.assert_array_equal(chunked[0][0], one_pass[0][0])
    assert chunked[0][1:] == one_pass[0][1:]
    np.testing.assert_array_equal(chunked[1], one_pass[1])
    np.testing.assert_allclose(one_pass[0][0], [*t, theta], atol=1.0)
