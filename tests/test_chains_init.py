"""Chain compression (exact first-order marginal), RANSAC registration, forked logging failures."""

from __future__ import annotations

import os

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import X
from numpy.typing import NDArray

from graphslam.core.survey.chains import compress, expand, relative
from graphslam.core.survey.initialise import (
    _inverse,
    fit_se2,
    ransac_se2,
    register_walks,
    se2_apply,
)
from graphslam.core.types import wrap_angle
from graphslam.errors import GraphSlamError, VisualizationError
from graphslam.viz.background import BackgroundLog


def chain(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    xyh = np.zeros((n, 3))
    for k in range(1, n):
        h = xyh[k - 1, 2]
        step = np.array([0.7 + rng.normal(0, 0.05), rng.normal(0, 0.05)])
        c, s = np.cos(h), np.sin(h)
        xyh[k, :2] = xyh[k - 1, :2] + [c * step[0] - s * step[1], s * step[0] + c * step[1]]
        xyh[k, 2] = wrap_angle(h + rng.normal(0, 0.2))
    return xyh


def test_compressed_segment_equals_the_marginal_of_the_chain() -> None:
    xyh = chain(9, seed=1)
    step_cov = np.diag([0.05**2, 0.03**2, 0.02**2])
    keep = np.zeros(9, bool)
    keep[[0, 8]] = True
    cc = compress(xyh, np.array([0, 9]), keep, np.array([True]), step_cov)
    assert cc.pairs.tolist() == [[0, 8]]
    np.testing.assert_allclose(cc.measured[0], relative(xyh[:1], xyh[8:9])[0], atol=1e-12)
    # GTSAM's marginal of the last pose given the first, through all the steps
    g = gtsam.NonlinearFactorGraph()
    v = gtsam.Values()
    noise = gtsam.noiseModel.Gaussian.Covariance(step_cov)
    for k in range(9):
        v.insert(X(k), gtsam.Pose2(*xyh[k]))
    g.add(gtsam.PriorFactorPose2(X(0), gtsam.Pose2(*xyh[0]), gtsam.noiseModel.Isotropic.Sigma(3, 1e-9)))
    for k in range(1, 9):
        g.add(gtsam.BetweenFactorPose2(X(k - 1), X(k), gtsam.Pose2(*relative(xyh[k - 1 : k], xyh[k : k + 1])[0]), noise))
    marginal = gtsam.Marginals(g, v).marginalCovariance(X(8))
    np.testing.assert_allclose(cc.covariance[0], marginal, rtol=1e-6, atol=1e-12)


def test_expand_restores_dropped_steps() -> None:
    xyh = chain(12, seed=2)
    keep = np.zeros(12, bool)
    keep[[0, 5, 11]] = True
    cc = compress(xyh, np.array([0, 12]), keep, np.array([True]), np.eye(3) * 1e-4)
    # a rigidly moved solution: expand must reproduce the moved chain exactly
    T = np.array([3.0, -2.0, 0.7])
    moved = np.column_stack([se2_apply(T, xyh[:, :2]), wrap_angle(xyh[:, 2] + T[2])])
    opt = np.full_like(xyh, np.nan)
    opt[cc.kept] = moved[cc.kept]
    out = expand(opt, xyh, cc)
    np.testing.assert_allclose(out[:, :2], moved[:, :2], atol=1e-9)
    np.testing.assert_allclose(np.cos(out[:, 2] - moved[:, 2]), 1.0, atol=1e-12)


def test_ransac_recovers_transform_despite_outliers() -> None:
    rng = np.random.default_rng(3)
    q = rng.uniform(-20, 20, (40, 2))
    T = np.array([5.0, -3.0, 1.1])
    p = se2_apply(T, q) + rng.normal(0, 0.5, q.shape)
    p[:12] = rng.uniform(-30, 30, (12, 2))  # 30 % wrong matches
    est, inl = ransac_se2(p, q, inlier_m=2.0, rng=np.random.default_rng(0))
    np.testing.assert_allclose(est[:2], T[:2], atol=0.5)
    assert abs(wrap_angle(est[2] - T[2])) < np.radians(2)
    assert inl[12:].mean() > 0.9 and inl[:12].mean() < 0.3
    np.testing.assert_allclose(fit_se2(q[12:], se2_apply(T, q[12:])), T, atol=1e-9)


def test_register_walks_chains_pairwise_transforms() -> None:
    rng = np.random.default_rng(4)
    truth = [np.array([0.0, 0.0, 0.0]), np.array([10.0, 5.0, 0.8]), np.array([-7.0, 12.0, -2.0])]
    n = 30
    site = rng.uniform(-15, 15, (n, 2))  # shared places seen by all three walks
    own = [se2_apply(np.array([-(np.cos(t[2]) * t[0] + np.sin(t[2]) * t[1]),
                               np.sin(t[2]) * t[0] - np.cos(t[2]) * t[1], -t[2]]), site) for t in truth]
    node_xy = np.concatenate(own)
    node_session = np.repeat(np.arange(3), n)
    # walk 0 <-> 1 and 1 <-> 2 matched; walk 2 reaches the reference only through walk 1
    a = np.concatenate([np.arange(n), n + np.arange(n)])
    b = np.concatenate([n + np.arange(n), 2 * n + np.arange(n)])
    pl = register_walks(3, 0, node_session, node_xy, a, b, inlier_m=1.0)
    assert pl.placed.all() and pl.parent.tolist() == [-1, 0, 1]
    for s in (1, 2):
        np.testing.assert_allclose(pl.transforms[s][:2], truth[s][:2], atol=1e-6)
        assert abs(wrap_angle(pl.transforms[s][2] - truth[s][2])) < 1e-6
    lonely = register_walks(3, 0, node_session, node_xy, a[:n], b[:n], inlier_m=1.0)
    assert lonely.placed.tolist() == [True, True, False]
    assert pl.loops == 0 and pl.loop_consistency is None and pl.reliable is None


def _walk_frames(truth: list[NDArray], site: NDArray) -> NDArray:
    """Site points expressed in each walk's own frame (walk pose ``t`` in the site frame)."""
    return np.concatenate([se2_apply(_inverse(t), site) for t in truth])


def test_registration_loop_check_flags_contradicting_pairs() -> None:
    """Every pair of 5 walks matched: 6 loops beyond the tree's 4 edges. Right matches close
    them all; matches of one walk shifted by 20 m for half its partners break some."""
    rng = np.random.default_rng(7)
    truth = [np.array([rng.uniform(-20, 20), rng.uniform(-20, 20), rng.uniform(-3, 3)]) for _ in range(5)]
    truth[0] = np.zeros(3)
    n = 30
    site = rng.uniform(-15, 15, (n, 2))
    node_xy = _walk_frames(truth, site)
    node_session = np.repeat(np.arange(5), n)
    pairs = [(u, v) for u in range(5) for v in range(u + 1, 5)]
    a = np.concatenate([u * n + np.arange(n) for u, v in pairs])
    b = np.concatenate([v * n + np.arange(n) for u, v in pairs])
    good = register_walks(5, 0, node_session, node_xy, a, b, inlier_m=1.0)
    assert good.placed.all() and good.loops == 6 and good.loops_consistent == 6
    assert good.loop_consistency == 1.0 and good.reliable is None  # too few loops to judge
    # walks 2 and 3 match walk 4 at other nodes of walk 4, which in truth lie 20 m away from
    # the places they saw (a wrong but self-consistent match set): appended nodes of walk 4
    shifted = _walk_frames([truth[4] + np.array([20.0, 0, 0])], site)
    bad_xy = np.concatenate([node_xy, shifted])
    sess = np.concatenate([node_session, np.full(n, 4)])
    bad_b = b.copy()
    for i, (u, v) in enumerate(pairs):
        if v == 4 and u in (2, 3):
            bad_b[i * n:(i + 1) * n] = 5 * n + np.arange(n)
    bad = register_walks(5, 0, sess, bad_xy, a, bad_b, inlier_m=1.0)
    assert bad.placed.all() and bad.loops == 6
    assert bad.loops_consistent < 6


def _fails() -> float:
    raise GraphSlamError("bad floor plan")


def _dies() -> float:
    os._exit(3)


def _works() -> float:
    return 0.25


def test_background_logging_reports_failures_in_one_line() -> None:
    assert BackgroundLog(_works).wait() == 0.25
    with pytest.raises(VisualizationError, match="bad floor plan") as e:
        BackgroundLog(_fails).wait()
    assert "\n" not in str(e.value)
    with pytest.raises(VisualizationError, match="died"):
        BackgroundLog(_dies).wait()


@pytest.mark.parametrize("seed", range(20))
def test_spanning_tree_is_scipys_including_ties(seed: int) -> None:
    """The walk-placement tree without csgraph: the same edges as scipy's Kruskal, ties and all
    (weights are inlier counts: ties are the rule), and the same components."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components, minimum_spanning_tree

    from graphslam.core.survey.initialise import connected_to, spanning_tree

    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 40))
    pairs = sorted({(int(i), int(j)) for i, j in rng.integers(0, n, (int(rng.integers(1, 3 * n)), 2)) if i < j})
    if not pairs:
        pairs = [(0, 1)]
    wi, wj = [p[0] for p in pairs], [p[1] for p in pairs]
    cost = -rng.integers(4, 9, len(pairs)).astype(float)  # few distinct values: many ties
    tree = minimum_spanning_tree(coo_matrix((cost, (wi, wj)), shape=(n, n)).tocsr()).tocoo()
    kept = spanning_tree(n, wi, wj, cost)
    assert sorted(zip(tree.row.tolist(), tree.col.tolist())) == [pairs[k] for k in np.flatnonzero(kept)]
    _, label = connected_components(coo_matrix((np.ones(len(wi)), (wi, wj)), shape=(n, n)), directed=False)
    ref = int(rng.integers(0, n))
    assert np.array_equal(connected_to(n, np.array(wi), np.array(wj), ref), label == label[ref])
