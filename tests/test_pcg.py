"""Conjugate gradients with a spanning-tree preconditioner (core/common/pcg.py) and the LM that solves
its damped systems by them (``optimizer.linear_solver``): the same steps, the same minimum as the
direct factorisation, and the direct factorisation where the iterations do not resolve a matrix."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import sparse
from test_align import CFG, two_walks
from test_solver import _chain_system, needs_cholmod

from graphslam.core.common.pcg import conjugate_gradients, spanning_tree_blocks
from graphslam.core.survey import solver as S
from graphslam.core.survey.align import build_problem, pose_graph, solve


def _dense(ne: S._NormalEquations, data: np.ndarray) -> np.ndarray:
    U = sparse.csr_matrix((data, ne.indices, ne.indptr), shape=(ne.n, ne.n)).toarray()
    return U + U.T - np.diag(np.diag(U))


def test_conjugate_gradients_reach_the_tolerance_and_say_when_they_cannot() -> None:
    rng = np.random.default_rng(3)
    Q = rng.normal(size=(40, 40))
    A = Q @ Q.T + 0.1 * np.eye(40)
    b = rng.normal(size=40)
    jacobi = lambda r: r / np.diag(A)  # noqa: E731
    x, it, ok = conjugate_gradients(lambda v: A @ v, b, jacobi, tol=1e-10 * np.linalg.norm(b), max_iterations=500)
    assert ok and 0 < it <= 500
    assert np.linalg.norm(A @ x - b) <= 1e-10 * np.linalg.norm(b)
    np.testing.assert_allclose(x, np.linalg.solve(A, b), rtol=1e-6)
    # from a start that already solves it: no iteration
    assert conjugate_gradients(lambda v: A @ v, b, jacobi, tol=1e-8, max_iterations=5, x0=x)[1:] == (0, True)
    # the cap, and a direction of negative curvature (an indefinite matrix), are no convergence
    assert conjugate_gradients(lambda v: A @ v, b, jacobi, tol=1e-14, max_iterations=3)[1:] == (3, False)
    indefinite = np.diag(np.r_[np.ones(20), -np.ones(20)])
    assert not conjugate_gradients(lambda v: indefinite @ v, b, lambda r: r, tol=1e-12, max_iterations=50)[2]


def test_the_tree_is_the_heaviest_spanning_forest_with_every_diagonal_block() -> None:
    # blocks (lo, hi): 4 diagonal ones, a square 0-1-2-3 with its diagonal 0-2, and pair 4-5 apart
    lo = np.array([0, 1, 2, 3, 0, 1, 2, 0, 4, 4, 5, 3])
    hi = np.array([0, 1, 2, 3, 1, 2, 3, 2, 4, 5, 5, 3])
    w = np.array([1, 1, 1, 1, 5.0, 1.0, 4.0, 3.0, 1, 2.0, 1, 9])  # the last: a second copy of (3, 3)
    keep = spanning_tree_blocks(6, lo, hi, w)
    assert keep[lo == hi].all()
    off = {(int(a), int(b)) for a, b, k in zip(lo, hi, keep) if k and a != b}
    # Kruskal by weight: 0-1 (5), 2-3 (4), 0-2 (3); 1-2 (1) closes a cycle; 4-5 its own tree
    assert off == {(0, 1), (2, 3), (0, 2), (4, 5)}
    # a block of weight 0 joins no tree
    assert not spanning_tree_blocks(6, lo, hi, np.where((lo == 4) & (hi == 5), 0.0, w))[(lo == 4) & (hi == 5)].any()


def test_the_tree_preconditioner_is_at_least_half_the_matrix_and_preconditions_it() -> None:
    """P (every diagonal block, a spanning tree's off-diagonal ones) >= A / 2 (module docstring): positive
    definite wherever A is; and far fewer iterations than the diagonal alone needs."""
    rng = np.random.default_rng(7)
    ne, H = _chain_system(rng, 60, 1e4)
    weight = np.sqrt(np.bincount(ne.gather // 9, H * H, minlength=len(ne.block_lo)))
    keep = spanning_tree_blocks(ne.n // 3, ne.block_lo, ne.block_hi, weight)[ne.gather // 9]
    A, P = _dense(ne, H), _dense(ne, np.where(keep, H, 0.0))
    assert np.linalg.eigvalsh(P - A / 2).min() >= -1e-9 * np.abs(A).max()
    assert (~keep).any()  # the extra edges left out: the test can tell P from A
    b = rng.normal(size=ne.n)
    tol = 1e-10 * np.linalg.norm(b)
    _, tree_it, ok = conjugate_gradients(lambda v: A @ v, b, lambda r: np.linalg.solve(P, r), tol=tol,
                                         max_iterations=2000)
    _, diag_it, _ = conjugate_gradients(lambda v: A @ v, b, lambda r: r / np.diag(A), tol=tol, max_iterations=2000)
    assert ok and tree_it < diag_it


@needs_cholmod
def test_lm_by_conjugate_gradients_reaches_the_direct_minimum() -> None:
    problem = build_problem(two_walks(), CFG)
    graph, _ = pose_graph(problem, CFG)
    active = np.ones(len(problem.wifi_pairs), bool)
    direct, pcg = (S.levenberg_marquardt(graph, problem.init_xyh, active, S.LMSettings(linear_solver=ls))
                   for ls in ("cholesky", "pcg"))
    assert direct.converged and pcg.converged and pcg.iterations == direct.iterations
    assert abs(pcg.error - direct.error) <= 1e-9 * max(1.0, direct.error)
    np.testing.assert_allclose(pcg.xyh, direct.xyh, atol=1e-7)
    assert pcg.factor == S.FactorInfo("", "pcg")
    assert pcg.factor.as_dict() == {"solver": "cholmod", "linear_solver": "pcg", "preconditioner": "spanning tree"}
    assert direct.factor.linear_solver == "cholesky"


@needs_cholmod
def test_a_matrix_the_iterations_do_not_resolve_goes_to_the_direct_factorisation(monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(5)
    ne, H = _chain_system(rng, 80, 1e6)
    b = rng.normal(size=ne.n)
    exact = S._DampedSystem(ne)
    exact.factor(H)
    want = exact.solve(b)
    made = []

    def direct() -> S._DampedSystem:
        made.append(S._DampedSystem(ne))
        return made[-1]

    tree = S._TreeSystem(ne, direct)
    tree.factor(H)
    got = tree.solve(b)
    assert tree.iterative and tree.iterations > 0 and not made  # resolved by the iterations
    assert np.linalg.norm(S._sym_matvec(ne, H, got) - b) <= 1e-10 * np.linalg.norm(b) * 1.0001
    monkeypatch.setattr(S._TreeSystem, "MAX_ITERATIONS", 2)
    tree = S._TreeSystem(ne, direct)
    tree.factor(H)
    np.testing.assert_array_equal(tree.solve(b), want)  # the very same direct solve
    assert not tree.iterative and tree.fallbacks == 1 and len(made) == 1
    tree.factor(H)  # ...and direct for the rest of the stage
    np.testing.assert_array_equal(tree.solve(b), want)
    # a tree that is not positive definite: refused as the direct factorisation refuses its matrix
    bad = H.copy()
    bad[ne.diag_pos[:3]] = -1.0
    tree = S._TreeSystem(ne, direct)
    with pytest.raises(np.linalg.LinAlgError):
        tree.factor(bad)
    for f in (exact, tree, *made):
        f.free()


@needs_cholmod
def test_a_matrix_that_is_not_positive_definite_raises_from_the_solve_and_the_iterations_go_on() -> None:
    """Three poses, every pair tied: the tree (the two heavier pairs) is positive definite, the matrix
    is not. Conjugate gradients meet its negative curvature, the direct factorisation refuses it, and
    the solve raises (the LM's signal to damp more) with the tree kept for the next matrix."""
    ne = S._NormalEquations(3, np.array([0, 1, 0]), np.array([1, 2, 2]))
    eye = np.broadcast_to(np.eye(3), (3, 3, 3))
    zero = np.zeros((3, 3))
    A, _ = ne.assemble(0.5 * eye, 0.5 * eye, np.array([0.6, -0.5, 0.6])[:, None, None] * eye, zero, zero)
    dense = _dense(ne, A)
    lam, vec = np.linalg.eigh(dense)
    assert lam[0] < 0  # the matrix is indefinite...
    made = []

    def direct() -> S._DampedSystem:
        made.append(S._DampedSystem(ne))
        return made[-1]

    tree = S._TreeSystem(ne, direct)
    tree.factor(A)  # ...its tree is not
    P = _dense(ne, np.where(tree._mask, A, 0.0))
    assert np.linalg.eigvalsh(P).min() > 0
    with pytest.raises(np.linalg.LinAlgError):
        tree.solve(P @ vec[:, 0])  # the first direction is the negative eigenvector
    assert tree.iterative and tree.fallbacks == 0 and len(made) == 1
    tree.free()


@needs_cholmod
def test_auto_solves_by_conjugate_gradients_from_the_variable_count_on() -> None:
    """``linear_solver`` auto: the direct factorisation below ``pcg_above_variables`` unknowns, conjugate
    gradients from it on (no METIS ordering of the graph then: nothing factorises the whole matrix)."""
    problem = build_problem(two_walks(), CFG)
    graph, _ = pose_graph(problem, CFG)
    active = np.ones(len(problem.wifi_pairs), bool)
    n = 3 * len(graph.variables)
    seen = []
    for ls, above in (("auto", n), ("auto", n + 1), ("cholesky", 0), ("pcg", 10 * n)):
        settings = S.LMSettings(ordering="metis", linear_solver=ls, pcg_above_variables=above)
        seen.append((S.levenberg_marquardt(graph, problem.init_xyh, active, settings).factor.linear_solver,
                     S.graph_ordering(graph, settings) is None))
    assert seen == [("pcg", True), ("cholesky", False), ("cholesky", False), ("pcg", True)]
    # the survey reports it, in report.json's words
    cfg = CFG.model_copy(update={"optimizer": CFG.optimizer.model_copy(
        update={"solver": "cholmod", "linear_solver": "pcg"})})
    al = solve(build_problem(two_walks(), cfg), cfg)
    assert al.solver == {"solver": "cholmod", "linear_solver": "pcg", "preconditioner": "spanning tree"}


def test_where_the_iterations_give_up_lm_goes_on_with_the_direct_factorisation(monkeypatch: pytest.MonkeyPatch) -> None:
    problem = build_problem(two_walks(), CFG)
    graph, _ = pose_graph(problem, CFG)
    active = np.ones(len(problem.wifi_pairs), bool)
    want = S.levenberg_marquardt(graph, problem.init_xyh, active, S.LMSettings(linear_solver="cholesky"))
    monkeypatch.setattr(S._TreeSystem, "MAX_ITERATIONS", 1)
    got = S.levenberg_marquardt(graph, problem.init_xyh, active, S.LMSettings(linear_solver="pcg"))
    assert got.factor.linear_solver == "cholesky"
    assert got.factor == want.factor and abs(got.error - want.error) <= 1e-9 * max(1.0, want.error)
