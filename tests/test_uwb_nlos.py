"""The NLOS pre-filter of ``core/uwb/nlos.py``: ranges the dead reckoning alone proves too long.
Tiny synthetic links with known truth: every flagged range is biased, and a bias larger than the
chord walked since a LOS range (plus the slack) is always flagged."""

from __future__ import annotations

import numpy as np

from graphslam.core.uwb.nlos import too_long_by_chords

SIGMA = 0.1
KW = dict(k=3.0, step_sigma_m=0.03, max_dt_s=30.0)


def _walk(n: int = 200, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A walker (steps of 0.6 m every 0.5 s, pausing for 10 steps every 40) and an anchor at the
    origin; the dead-reckoning frame is rotated and shifted against the true one (the test needs
    no placement), with 1 cm noise per step."""
    rng = np.random.default_rng(seed)
    moving = (np.arange(n) // 10) % 4 != 3
    heading = np.cumsum(rng.normal(0, 0.15, n))
    step = 0.6 * moving[:, None] * np.column_stack([np.cos(heading), np.sin(heading)])
    p = np.array([4.0, -3.0]) + np.cumsum(step, 0)
    c, s = np.cos(1.1), np.sin(1.1)
    dr = p + np.cumsum(rng.normal(0, 0.01, (n, 2)), 0)
    q = dr @ np.array([[c, -s], [s, c]]).T + np.array([50.0, -20.0])
    return 0.5 * np.arange(n), p, q


def test_chord_test_flags_only_ranges_longer_than_the_truth() -> None:
    rng = np.random.default_rng(1)
    t, p, q = _walk()
    n = len(t)
    truth = np.linalg.norm(p, axis=1)
    bias = np.where(rng.random(n) < 0.35, rng.uniform(0.3, 2.0, n), 0.0)
    r = truth + bias + rng.normal(0, 0.05, n)
    flag = too_long_by_chords(np.zeros(n, np.int64), t, q[:, None], np.arange(n)[:, None], r, np.full(n, SIGMA), **KW)
    assert not (flag & (bias == 0)).any()  # never a LOS range
    assert flag.sum() >= 0.2 * (bias > 0).sum()  # and a good share of the biased ones
    # a range biased by more than the chord to a LOS neighbour + the slack is always caught
    los = np.flatnonzero(bias == 0)
    chord = np.linalg.norm(q[:, None] - q[los][None], axis=-1)
    slack = 3.0 * np.sqrt(2 * SIGMA**2 + np.abs(np.arange(n)[:, None] - los[None]) * 0.03**2)
    margin = r[:, None] - r[los][None] - chord - slack
    sure = ((margin > 0.15) & (np.abs(t[:, None] - t[los][None]) <= 30.0)).any(axis=1)
    assert sure.any() and flag[sure].all()


def test_chord_test_groups_links_and_sums_both_walkers_chords() -> None:
    """Peer link: the distance between two walkers changes by at most the sum of their chords. A
    range too long for one walker's chord alone but not for both is not flagged; another link's
    ranges never bound this one's."""
    t = np.array([0.0, 5.0, 0.0, 5.0])
    group = np.array([0, 0, 1, 1])
    qa = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 0.0], [0.0, 0.0]])  # walker A moves 1 m in link 0
    qb = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 0.0], [0.0, 0.0]])  # and so does B
    q = np.stack([qa, qb], 1)
    node = np.array([[0, 0], [1, 1], [0, 0], [0, 0]])
    r = np.array([5.0, 6.5, 1.0, 5.0])  # link 0: +1.5 m after 1 + 1 m of chords: possible
    flag = too_long_by_chords(group, t, q, node, r, np.full(4, 0.05), k=3.0, step_sigma_m=0.0, max_dt_s=30.0)
    assert flag.tolist() == [False, False, False, True]  # link 1: +4 m, nobody moved
    one_end = too_long_by_chords(group, t, q[:, :1], node[:, :1], r, np.full(4, 0.05), k=3.0, step_sigma_m=0.0, max_dt_s=30.0)
    assert one_end.tolist() == [False, True, False, True]  # A's chord alone (1 m) cannot explain +1.5 m
    late = too_long_by_chords(group, t * 10, q, node, r, np.full(4, 0.05), k=3.0, step_sigma_m=0.0, max_dt_s=30.0)
    assert late.tolist() == [False, False, False, False]  # 50 s apart: not compared


def test_chord_test_under_a_persistent_bias_flags_nothing_unbiased() -> None:
    """A wall between walker and anchor for 20 s: every range of that stretch +1.2 m (one bias,
    not drawn per range). The test may catch the stretch's ranges near its ends (where little was
    walked since a LOS range), never a LOS one, and keeps most of the stretch's ranges for the
    solve-based rejection (no reliance on independent biases)."""
    rng = np.random.default_rng(2)
    t, p, q = _walk(seed=3)
    n = len(t)
    bias = np.where((t >= 40.0) & (t < 60.0), 1.2, 0.0)
    r = np.linalg.norm(p, axis=1) + bias + rng.normal(0, 0.05, n)
    flag = too_long_by_chords(np.zeros(n, np.int64), t, q[:, None], np.arange(n)[:, None], r, np.full(n, SIGMA), **KW)
    assert not (flag & (bias == 0)).any()
    assert flag[bias > 0].any()  # the first ranges behind the wall


def test_chord_prefilter_compares_only_within_the_time_window() -> None:
    """A range is judged only against ranges of its link within max_dt_s, also across the
    512-row blocks: the same flags as the direct pairwise rule on a long link."""
    rng = np.random.default_rng(5)
    m = 1500
    t = np.sort(rng.uniform(0, 600, m))
    q = np.cumsum(rng.normal(0, 0.05, (m, 1, 2)), axis=0)
    node = np.arange(m)[:, None]
    r = 5 + np.abs(rng.normal(0, 0.05, m)) + np.where(rng.random(m) < 0.3, rng.uniform(0.3, 2, m), 0.0)
    sigma = np.full(m, 0.05)
    group = np.zeros(m, np.int64)
    got = too_long_by_chords(group, t, q, node, r, sigma, k=3.0, step_sigma_m=0.03, max_dt_s=10.0)
    chord = np.linalg.norm(q[:, None, 0] - q[None, :, 0], axis=-1)
    steps = np.abs(node[:, None, 0] - node[None, :, 0])
    bound = r[None, :] + chord + 3.0 * np.sqrt(2 * 0.05**2 + steps * 0.03**2)
    want = ((r[:, None] > bound) & (np.abs(t[:, None] - t[None, :]) <= 10.0)).any(axis=1)
    np.testing.assert_array_equal(got, want)
    assert want.sum() > 10  # the rule fires on this link
