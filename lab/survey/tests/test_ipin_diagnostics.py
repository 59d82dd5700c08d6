"""The search and statistics helpers of lab/survey/ipin_diagnostics.py (the script itself runs on real
data for minutes; its figures are only as good as these pieces)."""

from __future__ import annotations

import importlib.util
import sys
from types import ModuleType

import numpy as np
import pytest
from lab.conftest import REPO

from graphslam import se2_apply


@pytest.fixture(scope="module")
def diag() -> ModuleType:
    spec = importlib.util.spec_from_file_location("ipin_diagnostics", REPO / "lab" / "survey" / "ipin_diagnostics.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["ipin_diagnostics"] = mod
    spec.loader.exec_module(mod)
    return mod


def _scene(rng: np.random.Generator, T: np.ndarray, n: int = 60) -> tuple[np.ndarray, np.ndarray]:
    """Map points Q and the same places seen in a walk's own frame P (Q = T(P))."""
    Q = rng.uniform([0, 0], [40, 20], (n, 2))
    c, s = np.cos(T[2]), np.sin(T[2])
    rel = Q - T[:2]
    return np.column_stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1]]), Q


def test_se2_search_finds_the_transform_that_puts_matches_together(diag: ModuleType) -> None:
    rng = np.random.default_rng(1)
    T_true = np.array([5.3, -2.7, 0.7])
    P, Q = _scene(rng, T_true)
    # true correspondences plus as many random (wrong) ones
    i = np.concatenate([np.arange(len(P)), rng.integers(0, len(P), len(P))])
    j = np.concatenate([np.arange(len(Q)), rng.integers(0, len(Q), len(Q))])
    thetas = np.array([0.0, 0.7, 1.5, np.pi])
    ((score, T),) = diag.se2_search(P, Q, i, j, np.zeros(len(i), np.int64), None, [diag.gaussian_kernel(1.5)], thetas)
    assert int(np.argmax(score)) == 1
    assert np.linalg.norm(se2_apply(T[1], P) - Q, axis=1).max() < 0.8  # one 1 m grid cell


def test_se2_search_score_is_the_composite_likelihood(diag: ModuleType) -> None:
    """The FFT score at the returned placement equals the direct sum over all pairs."""
    rng = np.random.default_rng(2)
    T_true = np.array([1.0, 2.0, -0.4])
    P, Q = _scene(rng, T_true, 40)
    S = np.clip(np.exp(-diag.cross_dist(se2_apply(T_true, P), Q) / 8) + rng.normal(0, 0.1, (40, 40)), 0, 1)
    # the true log-likelihood ratio of s at d against s uniform, in 8 bins of 2 m (reach 16 m)
    d_mid, s_mid = (np.arange(8) + 0.5) * 2.0, (np.arange(diag.S_BINS) + 0.5) / diag.S_BINS
    L = -((s_mid[None] - np.exp(-d_mid[:, None] / 8)) ** 2) / (2 * 0.15**2) - np.log(0.15 * np.sqrt(2 * np.pi))
    sb = diag.s_bin(S)
    ii, jj = np.divmod(np.arange(sb.size), len(Q))
    thetas = np.array([-0.4, 0.3, 2.0])
    ((score, T),) = diag.se2_search(P, Q, ii, jj, sb.ravel(), None, [diag.table_kernels(L)], thetas)
    assert int(np.argmax(score)) == 0
    for k in range(len(thetas)):
        d = diag.cross_dist(se2_apply(T[k], P), Q)
        scale = np.abs(diag.table_value(L, sb, d)).sum()
        assert score[k] == pytest.approx(diag.composite(L, S, d), abs=0.01 * scale)


def test_auc_from_histograms_matches_the_rank_statistic(diag: ModuleType) -> None:
    rng = np.random.default_rng(3)
    near, far = rng.integers(0, 50, 300), rng.integers(0, 50, 500)  # many ties
    h_near, h_far = np.bincount(near, minlength=50), np.bincount(far, minlength=50)
    wins = (near[:, None] > far[None]).sum() + 0.5 * (near[:, None] == far[None]).sum()
    assert diag._auc(h_near, h_far) == pytest.approx(wins / (300 * 500), abs=1e-3)


def test_calibration_perturbation_moves_each_route_rigidly(diag: ModuleType) -> None:
    """ipin_calibration's stand-in placement: every route moved as a rigid body (distances within a
    route kept, between routes changed), reproducibly per seed."""
    import types

    spec = importlib.util.spec_from_file_location("ipin_calibration", REPO / "lab" / "survey" / "ipin_calibration.py")
    C = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(C)

    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 50, (40, 2))
    route = np.repeat(np.array(["a", "b"]), 20)
    f = types.SimpleNamespace(xy=xy, scan_route=route, routes=["a", "b"])
    out = C.perturbed_positions(f, 5.0, 5.0, seed=3)
    for r in ("a", "b"):
        m = route == r
        d0 = np.linalg.norm(xy[m][:, None] - xy[m][None], axis=2)
        d1 = np.linalg.norm(out[m][:, None] - out[m][None], axis=2)
        assert np.allclose(d0, d1)
    assert not np.allclose(np.linalg.norm(xy[:20, None] - xy[None, 20:], axis=2),
                           np.linalg.norm(out[:20, None] - out[None, 20:], axis=2))
    assert np.array_equal(out, C.perturbed_positions(f, 5.0, 5.0, seed=3))
