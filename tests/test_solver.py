"""The vectorised Levenberg-Marquardt (core/survey/solver.py) on CHOLMOD: factors against GTSAM, normal
equations, and the same minimum as GTSAM's optimiser."""

from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np
import pytest
from test_align import CFG, two_walks

from graphslam.core.survey import solver as S
from graphslam.core.survey.align import build_problem, pose_graph, solve
from graphslam.errors import SolverError

X = gtsam.symbol_shorthand.X
from graphslam.core.common import cholesky as C

needs_cholmod = pytest.mark.skipif(not C.cholmod_available(), reason="cvxopt (CHOLMOD) not installed")
BACKENDS = [pytest.param("cholmod", marks=needs_cholmod), pytest.param("auto", marks=needs_cholmod)]


def _poses(rng: np.random.Generator, m: int) -> tuple[np.ndarray, np.ndarray]:
    xa = rng.normal(size=(m, 3)) * [5.0, 5.0, 2.0]
    return xa, xa + rng.normal(size=(m, 3)) * [1.0, 1.0, 1.5]


def _numerical(fun, x: np.ndarray, h: float = 1e-6) -> np.ndarray:
    cols = []
    for i in range(3):
        dx = np.zeros(3)
        dx[i] = h
        cols.append((fun(x + dx) - fun(x - dx)) / (2 * h))
    return np.stack(cols, axis=-1)


def test_between_factor_equals_gtsam_and_its_jacobians_the_numerical_ones() -> None:
    rng = np.random.default_rng(1)
    xa, xb = _poses(rng, 40)
    u = rng.normal(size=(40, 3))
    cov = np.array([np.diag(rng.uniform(0.01, 0.1, 3)) for _ in range(40)])
    cov[:, 0, 1] = cov[:, 1, 0] = 0.003  # correlated, as a compressed chain's covariance
    W = S.sqrt_information(cov)
    r, Ja, Jb = S.between_residuals(xa, xb, u, W)
    for k in range(40):
        f = gtsam.BetweenFactorPose2(X(0), X(1), gtsam.Pose2(*u[k]), gtsam.noiseModel.Gaussian.Covariance(cov[k]))
        v = gtsam.Values()
        v.insert(X(0), gtsam.Pose2(*xa[k]))
        v.insert(X(1), gtsam.Pose2(*xb[k]))
        assert 0.5 * r[k] @ r[k] == pytest.approx(f.error(v), rel=1e-9)
    np.testing.assert_allclose(Ja, _numerical(lambda x: S.between_residuals(x, xb, u, W, jacobians=False)[0], xa), atol=1e-6)
    np.testing.assert_allclose(Jb, _numerical(lambda x: S.between_residuals(xa, x, u, W, jacobians=False)[0], xb), atol=1e-6)


def test_range_factor_equals_gtsam_dead_zone_and_its_hessian_the_numerical_one() -> None:
    rng = np.random.default_rng(2)
    xa, xb = _poses(rng, 30)
    sigma, d0 = 0.7, 1.0
    r, Ja, Jb = S.range_residuals(xa, xb, sigma, d0)
    noise = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.L2WithDeadZone(d0 / sigma), gtsam.noiseModel.Isotropic.Sigma(1, sigma)
    )
    for k in range(30):
        v = gtsam.Values()
        v.insert(X(0), gtsam.Pose2(*xa[k]))
        v.insert(X(1), gtsam.Pose2(*xb[k]))
        assert 0.5 * r[k] ** 2 == pytest.approx(gtsam.RangeFactorPose2(X(0), X(1), 0.0, noise).error(v), abs=1e-12)
    def grad_b(x: np.ndarray) -> np.ndarray:  # d(0.5 r^2)/d(pose b) = r J_b
        rr, _, jb = S.range_residuals(xa, x, sigma, d0)
        return rr[:, None] * jb

    np.testing.assert_allclose(S.range_hessian(xa, xb, r, Jb, sigma), _numerical(grad_b, xb), atol=1e-5)
    np.testing.assert_allclose(Ja, -Jb)


def test_normal_equations_equal_the_dense_products() -> None:
    rng = np.random.default_rng(3)
    n_vars, m = 6, 15
    va = rng.integers(-1, n_vars, m)  # -1: the fixed reference
    vb = (va + 1 + rng.integers(0, n_vars - 1, m)) % n_vars
    Ja, Jb, res = rng.normal(size=(m, 3, 3)), rng.normal(size=(m, 3, 3)), rng.normal(size=(m, 3))
    ne = S._NormalEquations(n_vars, va, vb)
    tr = lambda a: np.transpose(a, (0, 2, 1))
    H, g = ne.assemble(tr(Ja) @ Ja, tr(Jb) @ Jb, tr(Ja) @ Jb, (tr(Ja) @ res[:, :, None])[..., 0], (tr(Jb) @ res[:, :, None])[..., 0])
    J = np.zeros((3 * m, 3 * n_vars))
    for k in range(m):
        for v, Jk in ((va[k], Ja[k]), (vb[k], Jb[k])):
            if v >= 0:
                J[3 * k : 3 * k + 3, 3 * v : 3 * v + 3] = Jk
    upper = np.zeros((3 * n_vars, 3 * n_vars))
    rows = np.repeat(np.arange(3 * n_vars), np.diff(ne.indptr))
    upper[rows, ne.indices] = H
    np.testing.assert_allclose(upper, np.triu(J.T @ J), atol=1e-12)
    np.testing.assert_allclose(g, J.T @ res.ravel(), atol=1e-12)
    x = rng.normal(size=3 * n_vars)
    np.testing.assert_allclose(S._sym_matvec(ne, H, x), J.T @ J @ x, atol=1e-10)


@pytest.mark.parametrize("backend", BACKENDS)
def test_reaches_gtsam_minimum_with_one_factorisation_per_iteration(backend: str) -> None:
    survey = two_walks()
    cfg_p = CFG.model_copy(update={"optimizer": CFG.optimizer.model_copy(update={"solver": backend})})
    cfg_g = CFG.model_copy(update={"optimizer": CFG.optimizer.model_copy(update={"solver": "gtsam"})})
    problem = build_problem(survey, cfg_p)
    p, g = solve(problem, cfg_p), solve(problem, cfg_g)
    assert p.converged and g.converged
    assert p.final_error <= g.final_error * (1 + 1e-3) + 1e-6
    # the valley is flat (total error 0.08): both stop within a few cm of each other
    np.testing.assert_allclose(p.node_xyh[:, :2], g.node_xyh[:, :2], atol=0.05)
    # the reference node is held exactly where the initialisation put it
    r0 = problem.reference_node
    np.testing.assert_array_equal(p.node_xyh[r0], problem.init_xyh[r0])
    # every LM run: one factorisation per iteration when no step is rejected
    graph, _ = pose_graph(problem, cfg_p)
    active = np.ones(len(problem.wifi_pairs), bool)
    res = S.levenberg_marquardt(graph, problem.init_xyh, active, S.LMSettings())
    assert res.converged and res.error < res.initial_error
    assert res.factorizations <= res.iterations + 2


@needs_cholmod
def test_cholmod_refuses_a_matrix_that_is_not_positive_definite() -> None:
    rng = np.random.default_rng(5)
    ne, H = _chain_system(rng, 50, 1.0)
    f = C.sparse_cholesky(ne.indptr, ne.indices)
    f.factor(H)
    b = rng.normal(size=ne.n)
    assert np.linalg.norm(S._sym_matvec(ne, H, f.solve(b)) - b) <= 1e-9 * np.linalg.norm(b)
    bad = H.copy()
    bad[ne.diag_pos[:3]] = -1.0
    with pytest.raises(np.linalg.LinAlgError):
        f.factor(bad)


def test_an_unfinite_start_is_an_error() -> None:
    problem = build_problem(two_walks(), CFG)
    graph, _ = pose_graph(problem, CFG)
    bad = problem.init_xyh.copy()
    bad[graph.variables[3]] = np.nan
    with pytest.raises(SolverError, match="not finite"):
        S.levenberg_marquardt(graph, bad, np.ones(len(problem.wifi_pairs), bool))


def test_a_graph_of_the_reference_pose_alone_is_already_solved() -> None:
    problem = build_problem(two_walks(), CFG)
    graph, _ = pose_graph(problem, CFG)
    lonely = replace(graph, variables=graph.variables[:0], between_pairs=graph.between_pairs[:0],
                     between_measured=graph.between_measured[:0], between_sqrt_info=graph.between_sqrt_info[:0],
                     range_pairs=graph.range_pairs[:0])
    res = S.levenberg_marquardt(lonely, problem.init_xyh, np.zeros(0, bool))
    assert res.converged and res.iterations == 0 and res.error == 0.0
    np.testing.assert_array_equal(res.xyh, problem.init_xyh)



def test_nonrigid_rms_ignores_one_rigid_motion_and_measures_the_rest() -> None:
    rng = np.random.default_rng(3)
    x, y = rng.normal(size=(2, 200)) * 20.0
    a = 0.3
    xr, yr = np.cos(a) * x - np.sin(a) * y + 4.0, np.sin(a) * x + np.cos(a) * y - 7.0
    assert S.nonrigid_rms(x, y, xr, yr) < 1e-9
    # a deformation no rigid motion explains: one half of the points moved 1 m along x
    bump = np.where(np.arange(200) < 100, 1.0, 0.0)
    got = S.nonrigid_rms(x, y, x + bump, y)
    assert 0.4 < got < 0.55  # about 0.5 m (a shift of 0.5 explains the mean; rotation absorbs little)
    # the same deformation, then moved rigidly: the same value
    xb = x + bump
    moved = S.nonrigid_rms(x, y, np.cos(a) * xb - np.sin(a) * y + 4.0, np.sin(a) * xb + np.cos(a) * y - 7.0)
    assert abs(moved - got) < 1e-9
    assert S.nonrigid_rms(x[:1], y[:1], x[:1] + 5, y[:1]) == 0.0


def test_the_shape_tolerance_ends_lm_once_a_step_only_moves_the_map_rigidly() -> None:
    problem = build_problem(two_walks(), CFG)
    graph, _ = pose_graph(problem, CFG)
    active = np.ones(len(problem.wifi_pairs), bool)
    tight = S.levenberg_marquardt(graph, problem.init_xyh, active, S.LMSettings(shape_tol_m=0.0))
    loose = S.levenberg_marquardt(graph, problem.init_xyh, active, S.LMSettings(shape_tol_m=1e3))
    assert tight.iterations > 1
    # every step is "below" 1 km: LM ends at the first step whose decrease is within 10x the tolerance
    assert loose.converged and loose.iterations < tight.iterations
    mid = S.LMSettings(shape_tol_m=1e-4)
    assert S.levenberg_marquardt(graph, problem.init_xyh, active, mid).iterations <= tight.iterations


def _chain_system(
    rng: np.random.Generator, n_vars: int, scale_range: float, ridge: float = 1e-3, anchored: bool = True
) -> tuple[S._NormalEquations, np.ndarray]:
    """A chain of 3x3 blocks plus random extra edges (the survey's pattern) as upper-triangle CSR
    data on ``ne``'s pattern: variables scaled over ``scale_range`` (as metres vs radians, dense vs
    sparse areas), ``ridge`` on the diagonal; not ``anchored``: no edge to the fixed reference, so
    only the ridge makes it positive definite."""
    first = -1 if anchored else 0
    va = np.concatenate([np.arange(first, n_vars - 1), rng.integers(0, n_vars, n_vars)])
    vb = np.concatenate([np.arange(first + 1, n_vars), rng.integers(0, n_vars, n_vars)])
    keep = va != vb
    ne = S._NormalEquations(n_vars, va[keep], vb[keep])
    m = int(keep.sum())
    J = rng.normal(size=(m, 3, 3))
    tr = lambda a: np.transpose(a, (0, 2, 1))
    zero = np.zeros((m, 3))
    H, _ = ne.assemble(tr(J) @ J, tr(J) @ J, -(tr(J) @ J), zero, zero)
    # scale the variables over the condition range (as metres vs radians and dense vs sparse areas do)
    s = np.exp(np.linspace(0.0, 0.5 * np.log(scale_range), ne.n))
    rng.shuffle(s)
    rows = np.repeat(np.arange(ne.n), np.diff(ne.indptr))
    H = H * s[rows] * s[ne.indices]
    H[ne.diag_pos] += ridge * s**2
    return ne, H


def test_range_factors_between_carried_points_have_the_numerical_jacobians() -> None:
    rng = np.random.default_rng(7)
    xa, xb = _poses(rng, 25)
    offsets = rng.normal(size=(25, 4)) * 1.5
    sigma, d0 = rng.uniform(0.5, 2.5, 25), rng.uniform(0.0, 1.0, 25)
    r, Ja, Jb, curv = S.offset_range_residuals(xa, xb, offsets, sigma, d0)
    np.testing.assert_allclose(Ja, _numerical(lambda x: S.offset_range_residuals(x, xb, offsets, sigma, d0,
                                                                                 jacobians=False)[0], xa), atol=1e-6)
    np.testing.assert_allclose(Jb, _numerical(lambda x: S.offset_range_residuals(xa, x, offsets, sigma, d0,
                                                                                 jacobians=False)[0], xb), atol=1e-6)
    # the point itself: the distance between the carried points
    c, s = np.cos(xa[:, 2]), np.sin(xa[:, 2])
    pa = xa[:, :2] + np.column_stack([c * offsets[:, 0] - s * offsets[:, 1], s * offsets[:, 0] + c * offsets[:, 1]])
    c, s = np.cos(xb[:, 2]), np.sin(xb[:, 2])
    pb = xb[:, :2] + np.column_stack([c * offsets[:, 2] - s * offsets[:, 3], s * offsets[:, 2] + c * offsets[:, 3]])
    np.testing.assert_allclose(r, np.maximum(np.linalg.norm(pb - pa, axis=1) - d0, 0) / sigma)
    # with no offsets: the plain range factor, curvature included
    r0, Ja0, Jb0, curv0 = S.offset_range_residuals(xa, xb, np.zeros((25, 4)), sigma, d0)
    rr, _, jb = S.range_residuals(xa, xb, sigma, d0)
    np.testing.assert_allclose(r0, rr)
    np.testing.assert_allclose(Jb0, jb, atol=1e-12)
    H = S.range_hessian(xa, xb, rr, jb, sigma)
    np.testing.assert_allclose(Jb0[:, :, None] * Jb0[:, None, :] + np.pad(curv0, ((0, 0), (0, 1), (0, 1))), H, atol=1e-12)


def test_a_magnetic_pair_between_skipped_steps_rides_on_the_kept_ones() -> None:
    from graphslam.core.survey.graph import carried_pairs

    rng = np.random.default_rng(3)
    dr = np.column_stack([np.cumsum(rng.normal(0.7, 0.05, 40)), np.cumsum(rng.normal(0, 0.1, 40)),
                          rng.normal(0, 0.3, 40)])
    keep = np.zeros(40, bool)
    keep[[0, 7, 15, 20, 30]] = True
    pairs = np.array([[3, 25], [7, 33], [16, 39]])
    kp, off = carried_pairs(pairs, keep, dr)
    np.testing.assert_array_equal(kp, [[0, 20], [7, 30], [15, 30]])
    # carried from the kept step's pose, the offset lands on the skipped step
    for side in (0, 1):
        k, n, o = kp[:, side], pairs[:, side], off[:, 2 * side:2 * side + 2]
        c, s = np.cos(dr[k, 2]), np.sin(dr[k, 2])
        np.testing.assert_allclose(dr[k, :2] + np.column_stack([c * o[:, 0] - s * o[:, 1], s * o[:, 0] + c * o[:, 1]]),
                                   dr[n, :2], atol=1e-12)


def _star_and_scraps(rng: np.random.Generator) -> tuple[S._NormalEquations, np.ndarray]:
    """Normal equations of 3x3 blocks: a 40-pose chain with a hub tied to every pose (one component),
    a 3-pose chain, and a pose with no factor to another (a prior only): the shapes a survey's
    components take, down to a walk that nothing links."""
    chain = np.arange(1, 40)
    va = np.concatenate([chain - 1, np.zeros(39, np.int64), [41, 42], [43]])
    vb = np.concatenate([chain, chain, [42, 43], [-1]])
    va[40:78] = 0
    ne = S._NormalEquations(44, va, vb)
    m = len(va)
    J = rng.normal(size=(m, 3, 3))
    tr = lambda a: np.transpose(a, (0, 2, 1))
    zero = np.zeros((m, 3))
    H, _ = ne.assemble(tr(J) @ J, tr(J) @ J, -(tr(J) @ J), zero, zero)
    H[ne.diag_pos] += 1.0
    return ne, H


def test_nested_dissection_orders_every_unknown_with_each_pose_kept_whole() -> None:
    ne, _ = _star_and_scraps(np.random.default_rng(7))
    perm = C.nested_dissection(ne.indptr, ne.indices)  # GTSAM's METIS crashes on the lonely pose if handed it
    assert np.array_equal(np.sort(perm), np.arange(ne.n))
    blocks = perm.reshape(-1, 3)
    assert np.all(blocks % 3 == [0, 1, 2]) and np.all(np.diff(blocks, axis=1) == 1)
    assert np.array_equal(perm, C.nested_dissection(ne.indptr, ne.indices))  # deterministic (METIS seed)
    with pytest.raises(ValueError, match="multiple of the block size"):
        C.nested_dissection(ne.indptr[:-1], ne.indices[: ne.indptr[-2]])


@needs_cholmod
def test_cholmod_factorises_in_the_given_ordering_even_where_amd_would_fill_less(monkeypatch: pytest.MonkeyPatch) -> None:
    """CHOLMOD left to itself compares a given ordering with its AMD and keeps the one that fills
    less; the back end must factorise in the ordering it is given. Here the hub first (a dense
    factor, where AMD puts it last), and CHOLMOD's postorder off so that its permutation is
    exactly the one factorised in."""
    monkeypatch.setattr(C, "_POSTORDER", False)
    ne, H = _star_and_scraps(np.random.default_rng(8))
    hub_first = np.arange(ne.n)
    f = C.sparse_cholesky(ne.indptr, ne.indices, perm=hub_first)
    f.factor(H)
    assert np.array_equal(f.permutation(), hub_first)
    amd = C.sparse_cholesky(ne.indptr, ne.indices)
    amd.factor(H)
    assert not np.array_equal(amd.permutation(), hub_first)  # AMD would not have kept it
    b = np.random.default_rng(9).normal(size=ne.n)
    np.testing.assert_allclose(f.solve(b), amd.solve(b), rtol=1e-9, atol=1e-12)


@needs_cholmod
def test_the_default_back_end_factorises_in_the_nested_dissection_order(monkeypatch: pytest.MonkeyPatch) -> None:
    """The LM's direct factorisation (CHOLMOD) in GTSAM's METIS order from ``metis_above_variables``
    unknowns on (the default config's 20,000: paper size 4 and up), in AMD's below; the result says
    which, and the answer is the same."""
    monkeypatch.setattr(C, "_POSTORDER", False)
    opt = CFG.optimizer
    assert (opt.solver, opt.ordering, opt.metis_above_variables) == ("auto", "auto", 20_000)
    problem = build_problem(two_walks(), CFG)
    graph, _ = pose_graph(problem, CFG)
    active = np.ones(len(problem.wifi_pairs), bool)
    made: list = []

    class Spy(C._Cholmod):
        def free(self) -> None:
            made.append(self.permutation())  # CHOLMOD's, read before the LM frees the factor
            super().free()

    monkeypatch.setattr(C, "_Cholmod", Spy)
    n = 3 * len(graph.variables)
    runs = {}
    for above in (n, n + 1):
        made.clear()
        settings = S.LMSettings(metis_above_variables=above, linear_solver="cholesky")
        runs[above] = S.levenberg_marquardt(graph, problem.init_xyh, active, settings)
        ne = S._Objective(graph, active, problem.init_xyh).normal
        if above == n:
            assert np.array_equal(made[0], C.nested_dissection(ne.indptr, ne.indices))
    assert runs[n].factor == S.FactorInfo("metis")
    assert runs[n + 1].factor == S.FactorInfo("amd")
    assert runs[n].iterations == runs[n + 1].iterations
    assert abs(runs[n].error - runs[n + 1].error) <= 1e-9 * runs[n].error
    np.testing.assert_allclose(runs[n].xyh, runs[n + 1].xyh, atol=1e-7)


@needs_cholmod
def test_one_metis_ordering_per_graph_serves_every_active_set(monkeypatch: pytest.MonkeyPatch) -> None:
    """LM's calls on one graph differ only in their active range edges: the graph's ordering (of every
    factor, all edges active) is computed once and CHOLMOD factorises each call in it, with the answer
    of the call's own ordering; ``solve`` orders once per graph, never per call."""
    monkeypatch.setattr(C, "_POSTORDER", False)
    problem = build_problem(two_walks(), CFG)
    graph, _ = pose_graph(problem, CFG)
    metis = S.LMSettings(ordering="metis")
    perm = S.graph_ordering(graph, metis)
    every = np.ones(len(graph.range_pairs), bool)
    ne = S._Objective(graph, every, problem.init_xyh).normal
    assert np.array_equal(perm, C.nested_dissection(ne.indptr, ne.indices))
    assert S.graph_ordering(graph, replace(metis, ordering="amd")) is None
    made: list = []

    class Spy(C._Cholmod):
        def free(self) -> None:
            made.append(self.permutation())
            super().free()

    monkeypatch.setattr(C, "_Cholmod", Spy)
    half = np.arange(len(every)) % 2 == 0
    given = S.levenberg_marquardt(graph, problem.init_xyh, half, metis, perm=perm)
    assert np.array_equal(made[0], perm)
    own = S.levenberg_marquardt(graph, problem.init_xyh, half, metis)
    assert not np.array_equal(made[-1], perm)  # the half graph's own ordering differs: the test can tell
    assert abs(given.error - own.error) <= 1e-9 * own.error
    np.testing.assert_allclose(given.xyh, own.xyh, atol=1e-7)
    calls = {"graph": 0, "call": 0}
    real_graph, real_call = S.graph_ordering, S.nested_dissection

    def count(key: str, f):  # noqa: ANN202
        def wrapped(*a, **k):  # noqa: ANN002, ANN003, ANN202
            calls[key] += 1
            return f(*a, **k)
        return wrapped

    monkeypatch.setattr(S, "graph_ordering", count("graph", real_graph))
    monkeypatch.setattr(S, "nested_dissection", count("call", real_call))
    cfg = CFG.model_copy(update={"optimizer": CFG.optimizer.model_copy(
        update={"solver": "cholmod", "ordering": "metis"})})
    al = solve(build_problem(two_walks(), cfg), cfg)
    assert al.iterations and calls == {"graph": 1, "call": 0}


@needs_cholmod
def test_without_metis_cholmod_orders_by_amd_and_says_so(monkeypatch: pytest.MonkeyPatch, caplog) -> None:
    def no_metis(*_args, **_kwargs):
        raise RuntimeError("GTSAM built without METIS")

    monkeypatch.setattr(S, "nested_dissection", no_metis)
    problem = build_problem(two_walks(), CFG)
    graph, _ = pose_graph(problem, CFG)
    active = np.ones(len(problem.wifi_pairs), bool)
    res = S.levenberg_marquardt(graph, problem.init_xyh, active, S.LMSettings(ordering="metis"))
    assert res.converged and res.factor == S.FactorInfo("amd")
    assert "METIS ordering unavailable (GTSAM built without METIS): CHOLMOD orders by AMD" in caplog.text
