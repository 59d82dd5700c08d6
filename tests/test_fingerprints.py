"""Eq. 9 distance engine against the definition, on random hand-made fingerprints."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import sparse

from graphslam.core.radiomap.fingerprints import DistanceEngine, FingerprintMatrix, rss_distance


def random_scans(n: int, n_aps: int, seed: int) -> list[dict[str, float]]:
    rng = np.random.default_rng(seed)
    aps = [f"ap{i}" for i in range(n_aps)]
    return [
        {a: float(rng.integers(-99, -35)) for a in rng.choice(aps, rng.integers(1, 15), replace=False)}
        for _ in range(n)
    ]


def test_rss_distance_by_hand() -> None:
    a = {"x": -50.0, "y": -70.0}
    b = {"x": -60.0, "z": -90.0}
    # union {x, y, z}: (10^2 + 40^2 + 20^2) / 3 with missing = -110
    assert rss_distance(a, b) == pytest.approx(np.sqrt((100 + 1600 + 400) / 3))
    assert rss_distance(a, a) == 0.0


@pytest.mark.parametrize("dense", [True, False])
def test_engine_matches_definition(dense: bool) -> None:
    scans = random_scans(60, 120, seed=3)
    fm = FingerprintMatrix.from_scans(scans)
    eng = DistanceEngine(fm, dense_threshold=0.0 if dense else 1.1)
    assert eng.dense is dense or fm.n_aps <= 64
    d, common = eng.block(fm, min_common=0)
    ref = np.array([[rss_distance(a, b) for b in scans] for a in scans])
    np.testing.assert_allclose(d, ref, atol=1e-6)
    inter = np.array([[len(set(a) & set(b)) for b in scans] for a in scans])
    np.testing.assert_array_equal(common, inter)


def test_queries_with_aps_unknown_to_the_reference() -> None:
    scans = random_scans(40, 80, seed=5)
    ref = FingerprintMatrix.from_scans(scans[10:])
    q = FingerprintMatrix.from_scans(scans[:10], bssids=ref.bssids)
    assert q.extra_n.sum() > 0, "the test needs query APs the reference lacks"
    d, _ = DistanceEngine(ref).block(q, min_common=0)
    expected = np.array([[rss_distance(a, b) for b in scans[10:]] for a in scans[:10]])
    np.testing.assert_allclose(d, expected, atol=1e-6)


def test_min_common_and_blocks() -> None:
    scans = random_scans(50, 40, seed=7)
    fm = FingerprintMatrix.from_scans(scans)
    eng = DistanceEngine(fm)
    d3, c = eng.block(fm, min_common=3)
    assert np.isinf(d3[c < 3]).all() and np.isfinite(d3[c >= 3]).all()
    blocks = list(eng.iter_blocks(fm, min_common=3, block_rows=7))
    assert [b[0] for b in blocks] == list(range(0, 50, 7))
    np.testing.assert_array_equal(np.vstack([b[1] for b in blocks]), d3)


@pytest.mark.parametrize("dense", [True, False])
def test_pairs_below_are_the_block_entries_below_each_rows_limit(dense: bool) -> None:
    scans = random_scans(70, 90, seed=11)
    fm = FingerprintMatrix.from_scans(scans)
    eng = DistanceEngine(fm, dense_threshold=0.0 if dense else 1.1)
    d, _ = eng.block(fm, min_common=2)
    limit = np.quantile(d[np.isfinite(d)], np.linspace(0.0, 0.3, len(fm)))
    limit[[3, 9]] = np.nan, np.inf  # NaN: no pair; inf: every pair sharing enough APs
    ri, ci, dv = eng.pairs_below(fm, limit, min_common=2)
    want_r, want_c = np.nonzero(d < np.where(np.isnan(limit), -np.inf, limit)[:, None])
    np.testing.assert_array_equal(ri, want_r)
    np.testing.assert_array_equal(ci, want_c)
    np.testing.assert_allclose(dv, d[want_r, want_c], rtol=1e-12)
    assert 3 not in ri and (ri == 9).sum() == np.isfinite(d[9]).sum()


def test_pairs_below_keep_the_pairs_a_hair_below_the_limit() -> None:
    """The dense set's one-product prefilter (float32) must pass every pair the element-wise test does,
    those within rounding of their limit too: limits a relative 1e-9 above and below chosen pairs."""
    scans = random_scans(60, 50, seed=13)
    fm = FingerprintMatrix.from_scans(scans)
    eng = DistanceEngine(fm, dense_threshold=0.0)
    sparse_eng = DistanceEngine(fm, dense_threshold=1.1)
    d, _ = eng.block(fm, min_common=1)
    rng = np.random.default_rng(0)
    pick = np.array([rng.choice(np.flatnonzero(np.isfinite(row) & (row > 0))) for row in d])
    at = d[np.arange(len(d)), pick]
    for factor, kept in ((1.0 + 1e-9, True), (1.0 - 1e-9, False)):
        limit = at * factor
        ri, ci, dv = eng.pairs_below(fm, limit, min_common=1)
        hit = set(zip(ri.tolist(), ci.tolist()))
        assert all(((i, int(j)) in hit) is kept for i, j in enumerate(pick))
        want = sparse_eng.pairs_below(fm, limit, min_common=1)
        np.testing.assert_array_equal(ri, want[0])
        np.testing.assert_array_equal(ci, want[1])
        np.testing.assert_allclose(dv, want[2], rtol=1e-12)


def test_readings_below_floor_are_dropped() -> None:
    fm = FingerprintMatrix.from_scans([{"a": -50.0, "b": -105.0}], min_rssi_dbm=-100.0)
    assert fm.bssids == ("a",) and fm.heard.tolist() == [1]
    np.testing.assert_allclose(fm.dense_rssi(), [[-50.0]])


def _encode_by_loop(scans, bssids, index, missing_dbm, min_rssi_dbm):
    """The reading-by-reading definition the vectorised ``FingerprintMatrix.encode`` must equal."""
    floor = max(min_rssi_dbm, missing_dbm + 1e-6)
    rows, cols, vals = [], [], []
    extra_sq, extra_n = np.zeros(len(scans)), np.zeros(len(scans), np.int64)
    for i, s in enumerate(scans):
        for b, r in s.items():
            if r < floor:
                continue
            j = index.get(b)
            if j is None:
                extra_sq[i] += (r - missing_dbm) ** 2
                extra_n[i] += 1
            else:
                rows.append(i)
                cols.append(j)
                vals.append(r - missing_dbm)
    return rows, cols, vals, extra_sq, extra_n


@pytest.mark.parametrize("seed", range(5))
def test_encode_equals_the_reading_by_reading_definition(seed: int) -> None:
    rng = np.random.default_rng(seed)
    aps = [f"02:00:00:00:{k // 256:02x}:{k % 256:02x}" for k in range(40)]
    known = tuple(sorted(aps[:25]))  # the other 15 are unknown to the index
    index = {b: j for j, b in enumerate(known)}
    scans = []
    for _ in range(300):
        heard = rng.choice(len(aps), size=int(rng.integers(0, 12)), replace=False)  # empty scans too
        scans.append({aps[k]: (int(rng.integers(-105, -30)) if rng.random() < 0.3 else float(rng.uniform(-105, -30)))
                      for k in heard})  # ints as JSON gives them, readings below the floor
    fm = FingerprintMatrix.encode(scans, known, index, -110.0, -100.0)
    rows, cols, vals, extra_sq, extra_n = _encode_by_loop(scans, known, index, -110.0, -100.0)
    want = sparse.csr_matrix((vals, (rows, cols)), shape=(len(scans), len(known)))
    assert (fm.values != want).nnz == 0 and fm.values.nnz == len(vals) > 0
    # squares: x * x here, the C library's pow() in the loop (an ulp apart at most, per term)
    np.testing.assert_allclose(fm.extra_sq, extra_sq, rtol=1e-15, atol=0)
    assert np.array_equal(fm.extra_n, extra_n) and extra_n.sum() > 0
