"""Levenberg-Marquardt for the paper's pose graph: vectorised factors, sparse linear algebra.

The same objective as the GTSAM graph of ``graphslam.core.survey.factors`` (IMU-between
factors with GTSAM's Pose2 Logmap error, the dead-zone WiFi range factors), solved by an
LM loop whose every step is a handful of numpy array operations over all factors plus one
sparse solve (a Cholesky factorisation, or conjugate gradients on large systems). Why not GTSAM's own LM: on the WiFi graph its multifrontal
elimination redoes the symbolic work at every try of lambda, where a sparse Cholesky with
the analysis reused (CHOLMOD: ``graphslam.core.common.cholesky``) refactorises only.

 * Variables: (x, y, theta) of every kept node except the reference node, which is held
   fixed (the paper's invariant reference pose; GTSAM's 1e-6 prior, exactly).
 * IMU-between: e = Log(U^-1 (X_a^-1 X_b)), whitened by an upper-triangular W with
   W^T W = Sigma^-1 (GTSAM's ``BetweenFactorPose2`` with a Gaussian noise model).
 * WiFi range: r = max(d - d_min, 0) / sigma, d = |p_a - p_b| (GTSAM's ``RangeFactorPose2``
   at range 0 under ``L2WithDeadZone``), with its exact Hessian (``range_hessian``) where
   GTSAM's robust wrapper reweights a Gauss-Newton one; the minimum is the same.
 * Linear algebra: the normal equations' pattern is fixed for one active edge set, so the
   sparse Cholesky's ordering (METIS; AMD for CHOLMOD on small systems) and symbolic analysis
   run once per stage and each lambda try or iteration is only a numeric refactorisation.
   Lambda follows Nielsen's rule, which rejects few steps (each rejection costs a
   factorisation).
 * Large systems (``linear_solver``: from ``pcg_above_variables`` unknowns on) are solved by
   conjugate gradients preconditioned by a spanning tree of the pose graph (``_TreeSystem``,
   ``graphslam.core.common.pcg``) to the same relative residual: no factor of the whole matrix,
   whose fill is what a large survey's time and memory went to (paper size 12: optimise 3.2 s and
   439 MiB peak, against 17.1 s and 917 MiB by CHOLMOD's factorisation; docs/benchmarks.md).
 * Convergence: the error's relative decrease, or (``shape_tol_m``) a step that barely changes
   the map's shape: held by one pose, a large map's last iterations only turn it about that pose.

Everything here is pure maths on arrays; nothing reads files.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Callable, Literal

import numpy as np
from numpy.typing import NDArray
from scipy import sparse

from graphslam.core.common.cholesky import (  # noqa: F401 (re-exported)
    block_nested_dissection, cholmod_available, nested_dissection, sparse_cholesky,
)
from graphslam.core.common.pcg import conjugate_gradients, spanning_tree_blocks
from graphslam.core.types import wrap_angle
from graphslam.errors import SolverError

log = logging.getLogger(__name__)

IterationHook = Callable[[int, float, float], None]  # (iteration, error before, error after)


@dataclass(frozen=True, eq=False)
class PoseGraph:
    """The factor graph as arrays; node ids are global step numbers (rows of ``xyh``)."""

    n_nodes: int
    variables: NDArray[np.int64]  # (K,) node ids optimised, ascending (reference excluded)
    reference: int  # node id held fixed (-1: none; nodes not in ``variables`` are all held at their given pose)
    between_pairs: NDArray[np.int64]  # (M, 2) node ids (a, b)
    between_measured: NDArray[np.float64]  # (M, 3) U = a^-1 b as (x, y, theta)
    between_sqrt_info: NDArray[np.float64]  # (M, 3, 3) W, upper triangular, W^T W = Sigma^-1
    range_pairs: NDArray[np.int64]  # (E, 2) node ids of WiFi edges (and magnetic pairs)
    range_sigma: float | NDArray[np.float64]  # one for all, or (E,) per edge
    range_dead_zone_m: float | NDArray[np.float64]
    # (E, 4) per range edge: the points it joins as offsets (x, y) in each end's body frame, a's then b's
    # (a magnetic pair between two steps chain compression left out, carried by the kept steps before
    # them); None: every edge joins the poses themselves
    range_offsets: NDArray[np.float64] | None = None
    # unary factors: a heading prior r = wrap(theta - target) / sigma (the phones' headings) and a
    # position prior r = (p - xy) / sigma (control points), each on one node
    heading_nodes: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    heading_target: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    heading_sigma: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    point_nodes: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    point_xy: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 2)))
    point_sigma: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    # Cauchy kernel of the heading priors, in sigmas (0: Gaussian): a walk whose WiFi disagrees with
    # its phone's heading by far (a turned phone, a bent field) is not held at the heading
    heading_cauchy: float = 0.0


@dataclass(frozen=True)
class LMSettings:
    max_iterations: int = 100
    relative_error_tol: float = 1e-4
    absolute_error_tol: float = 1e-5
    lambda_initial: float = 1e-5  # damping lambda * diag(J^T J): dimensionless
    lambda_upper: float = 1e8  # a stall beyond this: no step lowers the error
    # converged once a step moves the poses by less than this (rms, metres) beyond one rigid motion and
    # lowers the error by less than 10x relative_error_tol; 0: off
    shape_tol_m: float = 0.0
    # CHOLMOD's fill-reducing ordering: "metis" (nested dissection), "amd", or "auto": METIS from
    # ``metis_above_variables`` unknowns on, where its fill saves more than GTSAM's import costs
    ordering: Literal["auto", "metis", "amd"] = "auto"
    metis_above_variables: int = 20_000
    # how each damped system is solved: "cholesky" (a direct factorisation), "pcg" (conjugate gradients
    # preconditioned by a spanning tree of the pose graph, ``_TreeSystem``), or "auto": pcg from
    # ``pcg_above_variables`` unknowns on, where the factor's fill outweighs the iterations
    linear_solver: Literal["auto", "cholesky", "pcg"] = "auto"
    pcg_above_variables: int = 10_000


@dataclass(frozen=True)
class FactorInfo:
    """How an LM run solved its damped systems (the last one's way, after any switch from conjugate
    gradients to the direct factorisation): CHOLMOD, directly or as the preconditioner's factor."""

    ordering: str  # the direct factorisation's fill-reducing ordering: "metis" (nested dissection), "amd"; pcg: ""
    linear_solver: str = "cholesky"  # "cholesky" (direct) or "pcg" (spanning-tree preconditioned)

    def as_dict(self) -> dict[str, str]:
        """report.json's ``optimizer`` entries (``graph.describe_solver`` phrases them)."""
        if self.linear_solver == "pcg":
            return {"solver": "cholmod", "linear_solver": "pcg", "preconditioner": "spanning tree"}
        return {"solver": "cholmod", "linear_solver": "cholesky", "ordering": self.ordering}


@dataclass(frozen=True, eq=False)
class LMResult:
    xyh: NDArray[np.float64]  # (n_nodes, 3): variables and the reference updated, other rows as given
    iterations: int
    factorizations: int
    initial_error: float
    error: float
    converged: bool  # a tolerance was met (not the iteration cap, not a lambda stall)
    factor: FactorInfo | None = None  # None: nothing was factorised


def sqrt_information(cov: NDArray[np.float64]) -> NDArray[np.float64]:
    """(M, 3, 3) upper-triangular W with W^T W = cov^-1 (GTSAM's sqrt-information convention)."""
    info = np.linalg.inv(cov)
    info = 0.5 * (info + np.transpose(info, (0, 2, 1)))
    return np.transpose(np.linalg.cholesky(info), (0, 2, 1))


# --- the two factor types, vectorised ---------------------------------------------------


def _log_coeffs(w: NDArray) -> tuple[NDArray, NDArray]:
    """Pose2 Logmap's V^-1 = [[a, w/2], [-w/2, a]], a = (w/2) cot(w/2), and da/dw."""
    small = np.abs(w) < 1e-4
    ws = np.where(small, 1.0, w)
    half = 0.5 * ws
    a = np.where(small, 1.0 - w * w / 12.0, half / np.tan(half))
    da = np.where(small, -w / 6.0, 0.5 / np.tan(half) - half / (2.0 * np.sin(half) ** 2))
    return a, da


def between_residuals(
    xa: NDArray, xb: NDArray, u: NDArray, W: NDArray, *, jacobians: bool = True
) -> tuple[NDArray, NDArray | None, NDArray | None]:
    """Whitened e = W Log(U^-1 a^-1 b) (M, 3) and its Jacobians (M, 3, 3) w.r.t. a's and b's (x, y, theta)."""
    d = xb[:, :2] - xa[:, :2]
    al = xa[:, 2] + u[:, 2]  # R(theta_a + phi)^T maps world offsets into U's frame
    c, s = np.cos(al), np.sin(al)
    cp, sp = np.cos(u[:, 2]), np.sin(u[:, 2])
    zx = c * d[:, 0] + s * d[:, 1] - (cp * u[:, 0] + sp * u[:, 1])
    zy = -s * d[:, 0] + c * d[:, 1] - (-sp * u[:, 0] + cp * u[:, 1])
    w = wrap_angle(xb[:, 2] - xa[:, 2] - u[:, 2])
    a, da = _log_coeffs(w)
    e = np.column_stack([a * zx + 0.5 * w * zy, -0.5 * w * zx + a * zy, w])
    r = np.einsum("mij,mj->mi", W, e)
    if not jacobians:
        return r, None, None
    m = len(xa)
    # z_t = R(al)^T d - R(phi)^T u_t; dz_t/dp_b = R(al)^T, dz_t/dtheta_a = dR(al)^T/dal d
    dzx_dth = -s * d[:, 0] + c * d[:, 1]
    dzy_dth = -c * d[:, 0] - s * d[:, 1]
    # e_t = V^-1(w) z_t; de_t/dw = [[da, 1/2], [-1/2, da]] z_t; dw/dtheta_b = 1 = -dw/dtheta_a
    dex_dw = da * zx + 0.5 * zy
    dey_dw = -0.5 * zx + da * zy
    Jb = np.zeros((m, 3, 3))
    Jb[:, 0, 0] = a * c - 0.5 * w * s
    Jb[:, 0, 1] = a * s + 0.5 * w * c
    Jb[:, 1, 0] = -0.5 * w * c - a * s
    Jb[:, 1, 1] = -0.5 * w * s + a * c
    Jb[:, 0, 2] = dex_dw
    Jb[:, 1, 2] = dey_dw
    Jb[:, 2, 2] = 1.0
    Ja = -Jb
    Ja[:, 0, 2] = a * dzx_dth + 0.5 * w * dzy_dth - dex_dw
    Ja[:, 1, 2] = -0.5 * w * dzx_dth + a * dzy_dth - dey_dw
    Ja[:, 2, 2] = -1.0
    return r, W @ Ja, W @ Jb


def range_residuals(
    xa: NDArray, xb: NDArray, sigma: float | NDArray, dead_zone_m: float | NDArray, *, jacobians: bool = True
) -> tuple[NDArray, NDArray | None, NDArray | None]:
    """r = max(|p_b - p_a| - d0, 0) / sigma (E,) and its Jacobians (E, 3) w.r.t. a's and b's (x, y, theta);
    ``sigma``, ``dead_zone_m``: one for all edges or (E,)."""
    sigma = np.asarray(sigma, float)
    d = xb[:, :2] - xa[:, :2]
    n = np.hypot(d[:, 0], d[:, 1])
    on = n > dead_zone_m
    r = np.where(on, n - dead_zone_m, 0.0) / sigma
    if not jacobians:
        return r, None, None
    unit = np.where(on[:, None], d / np.where(on, n, 1.0)[:, None], 0.0) / (sigma[:, None] if sigma.ndim else sigma)
    Jb = np.zeros((len(xa), 3))
    Jb[:, :2] = unit
    return r, -Jb, Jb


def offset_range_residuals(
    xa: NDArray, xb: NDArray, offsets: NDArray, sigma: NDArray, dead_zone_m: NDArray, *, jacobians: bool = True
) -> tuple[NDArray, NDArray | None, NDArray | None, NDArray | None]:
    """``range_residuals`` between points carried by the poses: p = t + R(theta) o, ``offsets`` (E, 4) the
    o of a and of b. Returns r and its Jacobians (E, 3) w.r.t. a's and b's (x, y, theta), and the
    curvature of the distance on the translations, r / (sigma d) (I - u u^T) (E, 2, 2) (``range_hessian``)."""
    def carried(x: NDArray, o: NDArray) -> tuple[NDArray, NDArray]:
        c, s = np.cos(x[:, 2]), np.sin(x[:, 2])
        p = x[:, :2] + np.column_stack([c * o[:, 0] - s * o[:, 1], s * o[:, 0] + c * o[:, 1]])
        dp = np.column_stack([-s * o[:, 0] - c * o[:, 1], c * o[:, 0] - s * o[:, 1]])  # dp / dtheta
        return p, dp

    sigma = np.asarray(sigma, float)
    pa, dpa = carried(xa, offsets[:, :2])
    pb, dpb = carried(xb, offsets[:, 2:])
    d = pb - pa
    n = np.hypot(d[:, 0], d[:, 1])
    on = n > dead_zone_m
    r = np.where(on, n - dead_zone_m, 0.0) / sigma
    if not jacobians:
        return r, None, None, None
    u = np.where(on[:, None], d / np.where(on, n, 1.0)[:, None], 0.0)
    g = u / sigma[:, None]
    Jb = np.column_stack([g, (g * dpb).sum(1)])
    Ja = -np.column_stack([g, (g * dpa).sum(1)])
    k = np.where(r > 0, r / (sigma * np.where(n > 0, n, 1.0)), 0.0)
    curv = k[:, None, None] * (np.eye(2) - u[:, :, None] * u[:, None, :])
    return r, Ja, Jb, curv


def heading_residuals(x: NDArray, target: NDArray, sigma: NDArray) -> NDArray:
    """r = wrap(theta - target) / sigma (H,); its Jacobian w.r.t. (x, y, theta) is (0, 0, 1 / sigma)."""
    return np.asarray(wrap_angle(x[:, 2] - target)) / sigma


def point_residuals(x: NDArray, xy: NDArray, sigma: NDArray) -> NDArray:
    """r = (p - xy) / sigma (P, 2); its Jacobian w.r.t. (x, y, theta) is [I 0] / sigma."""
    return (x[:, :2] - xy) / sigma[:, None]


def cauchy(r: NDArray, c: float) -> tuple[NDArray, NDArray]:
    """(2 rho(r), IRLS weight) of the Cauchy kernel rho = c^2 / 2 log(1 + r^2 / c^2) (GTSAM's); c = 0: Gaussian."""
    if c <= 0:
        return r * r, np.ones_like(r)
    q = 1.0 + (r / c) ** 2
    return c * c * np.log(q), 1.0 / q


def unary_error(graph: PoseGraph, xyh: NDArray) -> float:
    """Error of the heading (robust) and position priors at poses ``xyh`` (n_nodes, 3)."""
    rh = heading_residuals(xyh[graph.heading_nodes], graph.heading_target, graph.heading_sigma)
    rp = point_residuals(xyh[graph.point_nodes], graph.point_xy, graph.point_sigma)
    return 0.5 * float(np.sum(cauchy(rh, graph.heading_cauchy)[0]) + np.sum(rp * rp))


def between_error(graph: PoseGraph, xyh: NDArray) -> float:
    """0.5 sum |W e|^2 of the IMU-between factors at poses ``xyh`` (n_nodes, 3)."""
    p = graph.between_pairs
    r, _, _ = between_residuals(
        xyh[p[:, 0]], xyh[p[:, 1]], graph.between_measured, graph.between_sqrt_info, jacobians=False
    )
    return 0.5 * float(np.sum(r * r))


def range_hessian(xa: NDArray, xb: NDArray, r: NDArray, Jb: NDArray, sigma: float | NDArray) -> NDArray:
    """(E, 3, 3) exact Hessian of 0.5 r^2 w.r.t. b's pose (w.r.t. a's: the same; cross term: minus it).

    J^T J = u u^T / sigma^2 plus the curvature of the distance, r / (sigma d) (I - u u^T), which is
    positive semi-definite (r >= 0): Newton's model stays convex and converges where Gauss-Newton
    crawls along the edges' tangential directions (measured: paper seed 1 stalled 0.11 above GTSAM's
    minimum with Gauss-Newton alone)."""
    d = np.hypot(*(xb[:, :2] - xa[:, :2]).T)
    H = np.zeros((len(r), 3, 3))
    sigma = np.asarray(sigma, float)
    u = Jb[:, :2] * (sigma[:, None] if sigma.ndim else sigma)  # unit vector where r > 0, else 0
    H[:, :2, :2] = Jb[:, :2, None] * Jb[:, None, :2]
    k = np.where(r > 0, r / (sigma * np.where(d > 0, d, 1.0)), 0.0)
    H[:, :2, :2] += k[:, None, None] * (np.eye(2) - u[:, :, None] * u[:, None, :])
    return H


# --- normal equations with a fixed pattern ------------------------------------------------


class _NormalEquations:
    """Assembles J^T J (upper triangle, CSR) and J^T r for one set of factors.

    Every factor adds 3x3 blocks at (a, a), (b, b) and (min, max); the block slots and the
    CSR position of each of their entries are computed once, so an assembly is a few
    ``bincount`` calls."""

    def __init__(self, n_vars: int, va: NDArray[np.int64], vb: NDArray[np.int64]) -> None:
        # va, vb: variable index of each factor's endpoints, -1 for the fixed reference
        self.n = 3 * n_vars
        self.va, self.vb = va, vb
        both = (va >= 0) & (vb >= 0)
        lo, hi = np.minimum(va, vb), np.maximum(va, vb)
        keys = np.concatenate([np.arange(n_vars) * (n_vars + 1), (lo * n_vars + hi)[both]])
        blocks, inv = np.unique(keys, return_inverse=True)
        self.n_blocks = len(blocks)
        slot_aa = _slot(blocks, va * (n_vars + 1), va >= 0)
        slot_bb = _slot(blocks, vb * (n_vars + 1), vb >= 0)
        slot_ab = np.full(len(va), -1, np.int64)
        slot_ab[both] = inv[n_vars:]
        # entry index (slot * 9 + row * 3 + col) in the blocks of each entry of each factor's block;
        # the (min, max) block is J_b^T J_a, i.e. J_a^T J_b transposed, when a is the larger index;
        # entries of a held end (slot -1) go to a bin past the end that the assembly drops. Kept
        # from one assembly to the next: an assembly is then three bincounts over the factors'
        # blocks as they come (no index arithmetic, no concatenated copy of every block)
        e9 = np.arange(9)
        e9t = (3 * e9) % 9 + e9 // 3  # (r, c) -> (c, r)
        self._trash = self.n_blocks * 9
        self._idx = []
        for slot, swap in ((slot_aa, None), (slot_bb, None), (slot_ab, va > vb)):
            idx = slot[:, None] * 9 + (e9 if swap is None else np.where(swap[:, None], e9t, e9))
            idx[slot < 0] = self._trash + e9
            self._idx.append(idx.ravel())
        self._gidx = []
        for v in (va, vb):
            gi = 3 * v[:, None] + np.arange(3)
            gi[v < 0] = self.n + np.arange(3)
            self._gidx.append(gi.ravel())
        bi, bj = blocks // n_vars, blocks % n_vars
        self.block_lo, self.block_hi = bi, bj  # block rows of each 3x3 block (lo <= hi)
        r, c = np.divmod(np.arange(9), 3)
        rows = (3 * bi[:, None] + r[None, :]).ravel()
        cols = (3 * bj[:, None] + c[None, :]).ravel()
        keep = rows <= cols  # upper triangle (only diagonal blocks have entries below)
        order = np.lexsort((cols[keep], rows[keep]))
        self.gather = np.flatnonzero(keep)[order]  # block-entry index of each CSR entry
        rr, cc = rows[keep][order], cols[keep][order]
        self.rows = rr.astype(np.int64)  # row of each CSR entry
        self.indptr = np.searchsorted(rr, np.arange(self.n + 1)).astype(np.int32)
        self.indices = cc.astype(np.int32)
        self.diag_pos = self.indptr[:-1].astype(np.int64)  # first entry of each row is its diagonal

    def assemble(self, aa: NDArray, bb: NDArray, ab: NDArray, ga: NDArray, gb: NDArray) -> tuple[NDArray, NDArray]:
        """(CSR data of J^T J's upper triangle, J^T r) from per-factor blocks J_a^T J_a, J_b^T J_b,
        J_a^T J_b (F, 3, 3) and gradients J_a^T r, J_b^T r (F, 3)."""
        size = self._trash + 9
        blocks = np.bincount(self._idx[0], np.ascontiguousarray(aa).reshape(-1), minlength=size)
        for idx, blk in zip(self._idx[1:], (bb, ab)):
            blocks += np.bincount(idx, np.ascontiguousarray(blk).reshape(-1), minlength=size)
        g = np.bincount(self._gidx[0], np.ascontiguousarray(ga).reshape(-1), minlength=self.n + 3)
        g += np.bincount(self._gidx[1], np.ascontiguousarray(gb).reshape(-1), minlength=self.n + 3)
        return blocks[self.gather], g[: self.n]


def _slot(blocks: NDArray, keys: NDArray, ok: NDArray) -> NDArray:
    return np.where(ok, np.searchsorted(blocks, np.where(ok, keys, 0)), -1)


class _DampedSystem:
    """Solves the damped normal equations (upper triangle ``data`` on the pattern of ``ne``) by a CHOLMOD
    factorisation (``perm``: its fill-reducing ordering, else AMD)."""

    def __init__(self, ne: _NormalEquations, perm: NDArray[np.int64] | None = None) -> None:
        self._factor = sparse_cholesky(ne.indptr, ne.indices, perm=perm)

    def factor(self, data: NDArray[np.float64]) -> None:
        self._factor.factor(data)

    def solve(self, b: NDArray[np.float64]) -> NDArray[np.float64]:
        return self._factor.solve(b)

    def free(self) -> None:
        self._factor.free()


class _TreeSystem:
    """Solves the damped normal equations by conjugate gradients preconditioned by a spanning tree of
    the pose graph (``graphslam.core.common.pcg``), the tree's matrix factorised by CHOLMOD, simplicial
    (no fill: a large survey's memory is then the matrix's, not a factor's). Each solve runs to a relative
    residual of ``TOL`` (the direct solve's step, to rounding: the same answers). A matrix the
    iterations do not resolve within ``MAX_ITERATIONS`` is handed to the direct factorisation
    (``direct`` builds it): not positive definite, it raises as the direct solver would (LM damps
    more); otherwise the direct factorisation solves this stage from then on."""

    TOL = 1e-10  # relative residual |b - A x| / |b| a solve stops at
    MAX_ITERATIONS = 400

    def __init__(self, ne: _NormalEquations, direct: Callable[[], _DampedSystem]) -> None:
        self._ne = ne
        self._make_direct = direct
        self._direct: _DampedSystem | None = None
        self._entry_block = ne.gather // 9  # the 3x3 block of each CSR entry
        self._mask: NDArray[np.bool_] | None = None
        self._pre = None  # the tree's factorisation
        self._data: NDArray = np.zeros(0)
        self.iterations = 0  # conjugate-gradient iterations, all solves (diagnostics, the log)
        self.fallbacks = 0  # switches to the direct factorisation

    @property
    def iterative(self) -> bool:
        """Solving by conjugate gradients (else the direct factorisation took over)."""
        return self._direct is None

    def factor(self, data: NDArray[np.float64]) -> None:
        if self._direct is not None:
            self._direct.factor(data)
            return
        ne = self._ne
        self._data = data
        weight = np.sqrt(np.bincount(self._entry_block, data * data, minlength=len(ne.block_lo)))
        keep = spanning_tree_blocks(ne.n // 3, ne.block_lo, ne.block_hi, weight)[self._entry_block]
        if self._mask is None or not np.array_equal(keep, self._mask):  # a new tree: a new analysis
            if self._pre is not None:
                self._pre.free()
            indptr = np.concatenate([[0], np.cumsum(np.bincount(ne.rows[keep], minlength=ne.n))]).astype(np.int32)
            self._pre = sparse_cholesky(indptr, ne.indices[keep], simplicial=True)
            self._mask = keep
        self._pre.factor(data[keep])  # P >= A / 2: positive definite wherever A is
        # the whole symmetric matrix, once: each iteration's product is then one pass over it
        U = sparse.csr_matrix((data, ne.indices, ne.indptr), shape=(ne.n, ne.n))
        full = (U + sparse.triu(U, 1, format="csr").T).tocsr()
        self._matvec = full.__matmul__

    def solve(self, b: NDArray[np.float64]) -> NDArray[np.float64]:
        if self._direct is not None:
            return self._direct.solve(b)
        x, it, ok = conjugate_gradients(self._matvec, b, self._pre.solve, tol=self.TOL * float(np.linalg.norm(b)),
                                        max_iterations=self.MAX_ITERATIONS)
        self.iterations += it
        if ok:
            return x
        direct = self._make_direct()
        try:
            direct.factor(self._data)
        except np.linalg.LinAlgError:
            direct.free()
            raise  # not positive definite: LM damps more, and the tree goes on
        log.debug("conjugate gradients did not resolve this matrix in %d iterations: the direct factorisation "
                  "from now on", it)
        self._pre.free()
        self._direct, self._pre = direct, None
        self.fallbacks += 1
        return direct.solve(b)

    def free(self) -> None:
        if self._pre is not None:
            self._pre.free()
        if self._direct is not None:
            self._direct.free()


# --- Levenberg-Marquardt ------------------------------------------------------------------


class _Objective:
    """Residuals and Jacobians of one active factor set at flattened variables ``v`` (3K,)."""

    def __init__(self, g: PoseGraph, active: NDArray[np.bool_], xyh: NDArray) -> None:
        self.g = g
        var_of = np.full(g.n_nodes, -1, np.int64)
        var_of[g.variables] = np.arange(len(g.variables))
        self.held = xyh.copy()  # poses of the nodes that are not variables (the reference among them)
        self.bp = g.between_pairs
        self.rp = g.range_pairs[active]
        # per active edge: its sigma and dead zone (WiFi edges and magnetic pairs differ)
        self.rs = np.broadcast_to(np.asarray(g.range_sigma, float), (len(g.range_pairs),))[active]
        self.rd = np.broadcast_to(np.asarray(g.range_dead_zone_m, float), (len(g.range_pairs),))[active]
        self.ro = None if g.range_offsets is None else g.range_offsets[active]
        # the edges that join carried points (the others take the plain, cheaper path)
        self.carried = None if self.ro is None else np.flatnonzero(np.any(self.ro != 0.0, axis=1))
        # unary factors enter as factors whose second end is held (no off-diagonal block)
        hv, pv = var_of[g.heading_nodes], var_of[g.point_nodes]
        self.hk, self.pk = hv >= 0, pv >= 0  # priors on held nodes are constants
        va = np.concatenate([var_of[self.bp[:, 0]], var_of[self.rp[:, 0]], hv[self.hk], pv[self.pk]])
        vb = np.concatenate([var_of[self.bp[:, 1]], var_of[self.rp[:, 1]],
                             np.full(int(self.hk.sum() + self.pk.sum()), -1, np.int64)])
        self.var_of = var_of
        self.normal = _NormalEquations(len(g.variables), va, vb)
        # each factor end's pose: one gather from the variables, the held ends' constant poses put back
        self._bp = (self._gather(self.bp[:, 0]), self._gather(self.bp[:, 1]))
        self._rp = (self._gather(self.rp[:, 0]), self._gather(self.rp[:, 1]))
        self._hp = (self._gather(g.heading_nodes), self._gather(g.point_nodes))

    def _gather(self, nodes: NDArray) -> tuple[NDArray, NDArray, NDArray]:
        """(variable of each node, 0 where held; the held ones' rows; their poses) for ``_poses``."""
        k = self.var_of[nodes]
        held = np.flatnonzero(k < 0)
        return np.maximum(k, 0), held, self.held[nodes[held]]

    @staticmethod
    def _poses(v: NDArray, gather: tuple[NDArray, NDArray, NDArray]) -> NDArray:
        k, held, at = gather
        x = v.reshape(-1, 3)[k]
        x[held] = at
        return x

    def _unary(self, v: NDArray) -> tuple[NDArray, NDArray]:
        g = self.g
        rh = heading_residuals(self._poses(v, self._hp[0]), g.heading_target, g.heading_sigma)
        rp = point_residuals(self._poses(v, self._hp[1]), g.point_xy, g.point_sigma)
        return rh, rp

    def error(self, v: NDArray) -> float:
        g = self.g
        rb, _, _ = between_residuals(
            self._poses(v, self._bp[0]), self._poses(v, self._bp[1]), g.between_measured, g.between_sqrt_info,
            jacobians=False,
        )
        xa, xb = self._poses(v, self._rp[0]), self._poses(v, self._rp[1])
        rr, _, _ = range_residuals(xa, xb, self.rs, self.rd, jacobians=False)
        if self.carried is not None and len(self.carried):
            c = self.carried
            rr[c] = offset_range_residuals(xa[c], xb[c], self.ro[c], self.rs[c], self.rd[c], jacobians=False)[0]
        rh, rp = self._unary(v)
        rho = cauchy(rh, g.heading_cauchy)[0]
        return 0.5 * float(np.sum(rb * rb) + np.sum(rr * rr) + np.sum(rho) + np.sum(rp * rp))

    def linearise(self, v: NDArray) -> tuple[NDArray, NDArray, float]:
        g = self.g
        rb, Jba, Jbb = between_residuals(
            self._poses(v, self._bp[0]), self._poses(v, self._bp[1]), g.between_measured, g.between_sqrt_info
        )
        xa, xb = self._poses(v, self._rp[0]), self._poses(v, self._rp[1])
        JbaT, JbbT = np.transpose(Jba, (0, 2, 1)), np.transpose(Jbb, (0, 2, 1))
        rr, Jra, Jrb = range_residuals(xa, xb, self.rs, self.rd)
        Hr = range_hessian(xa, xb, rr, Jrb, self.rs)
        Hra, Hrb, Hrab = Hr, Hr, -Hr
        if self.carried is not None and len(self.carried):
            # edges between carried points: the blocks of each end differ (their theta columns)
            c = self.carried
            rc, Ja, Jb, curv = offset_range_residuals(xa[c], xb[c], self.ro[c], self.rs[c], self.rd[c])
            K = np.zeros((len(c), 3, 3))
            K[:, :2, :2] = curv
            Hra, Hrb, Hrab = Hr.copy(), Hr.copy(), -Hr
            rr[c], Jra[c], Jrb[c] = rc, Ja, Jb
            Hra[c] = Ja[:, :, None] * Ja[:, None, :] + K
            Hrb[c] = Jb[:, :, None] * Jb[:, None, :] + K
            Hrab[c] = Ja[:, :, None] * Jb[:, None, :] - K
        rh, rp = self._unary(v)
        rho, wgt = cauchy(rh, g.heading_cauchy)  # IRLS: the kernel's weight on a Gauss-Newton block
        sh, sp = g.heading_sigma[self.hk], g.point_sigma[self.pk]
        Hh = np.zeros((len(sh), 3, 3))
        Hh[:, 2, 2] = wgt[self.hk] / sh**2
        gh = np.zeros((len(sh), 3))
        gh[:, 2] = wgt[self.hk] * rh[self.hk] / sh
        Hp = np.zeros((len(sp), 3, 3))
        Hp[:, 0, 0] = Hp[:, 1, 1] = 1.0 / sp**2
        gp = np.zeros((len(sp), 3))
        gp[:, :2] = rp[self.pk] / sp[:, None]
        n_u = len(sh) + len(sp)
        H, grad = self.normal.assemble(
            np.concatenate([JbaT @ Jba, Hra, Hh, Hp]),
            np.concatenate([JbbT @ Jbb, Hrb, np.zeros((n_u, 3, 3))]),
            np.concatenate([JbaT @ Jbb, Hrab, np.zeros((n_u, 3, 3))]),
            np.concatenate([(JbaT @ rb[:, :, None])[:, :, 0], Jra * rr[:, None], gh, gp]),
            np.concatenate([(JbbT @ rb[:, :, None])[:, :, 0], Jrb * rr[:, None], np.zeros((n_u, 3))]),
        )
        err = np.sum(rb * rb) + np.sum(rr * rr) + np.sum(rho) + np.sum(rp * rp)
        return H, grad, 0.5 * float(err)


def _cholmod_ordering(settings: LMSettings, n: int) -> str:
    """The fill-reducing ordering CHOLMOD takes for ``n`` unknowns: ``settings.ordering``, ``auto`` by size."""
    if settings.ordering != "auto":
        return settings.ordering
    return "metis" if n >= settings.metis_above_variables else "amd"


def _iterative(settings: LMSettings, n: int) -> bool:
    """Whether ``n`` unknowns are solved by conjugate gradients (``settings.linear_solver``, ``auto`` by size)."""
    if settings.linear_solver != "auto":
        return settings.linear_solver == "pcg"
    return n >= settings.pcg_above_variables


def graph_ordering(graph: PoseGraph, settings: LMSettings) -> NDArray[np.int64] | None:
    """One METIS ordering for every LM call on ``graph`` (``levenberg_marquardt``'s ``perm``), of the
    pattern of all its factors, every range edge active; None unless CHOLMOD orders by METIS here (or
    METIS is unavailable: each call then orders for itself). Why: the calls differ only in which range
    edges are active; any ordering gives the exact factor, and a call's pattern, a subset of this one,
    fills no more under it. METIS cost 0.6 s a call on a 200-walk survey (89k unknowns), four calls."""
    n_vars = len(graph.variables)
    if _cholmod_ordering(settings, 3 * n_vars) != "metis" or _iterative(settings, 3 * n_vars):
        return None  # (conjugate gradients factorise no such matrix)
    var_of = np.full(graph.n_nodes, -1, np.int64)
    var_of[graph.variables] = np.arange(n_vars)
    pairs = np.concatenate([graph.between_pairs, graph.range_pairs]).reshape(-1, 2)
    a, b = var_of[pairs[:, 0]], var_of[pairs[:, 1]]
    both = (a >= 0) & (b >= 0)
    try:
        return block_nested_dissection(n_vars, a[both], b[both])
    except (RuntimeError, ValueError, ImportError):  # levenberg_marquardt says why and orders by AMD
        return None


def levenberg_marquardt(
    graph: PoseGraph,
    xyh: NDArray[np.float64],
    active: NDArray[np.bool_],
    settings: LMSettings = LMSettings(),
    hook: IterationHook | None = None,
    *,
    perm: NDArray[np.int64] | None = None,
) -> LMResult:
    """Minimise the graph's error over its variables, WiFi edges restricted to ``active``.

    ``xyh``: (n_nodes, 3) initial poses (rows of non-variables are returned unchanged).
    Damping lambda * diag(J^T J) (Marquardt; scale-free across metres and radians).
    ``perm``: CHOLMOD's METIS ordering of the unknowns (``graph_ordering``), else one of the active pattern.
    """
    obj = _Objective(graph, active, xyh)
    v = np.ascontiguousarray(xyh[graph.variables]).ravel()
    if not np.all(np.isfinite(v)):
        raise SolverError("initial poses of the optimised nodes are not finite")
    if not len(v):  # only the fixed reference pose: nothing to optimise
        err = obj.error(v)
        return LMResult(xyh.copy(), 0, 0, err, err, True)
    ne = obj.normal
    iterative = _iterative(settings, ne.n)
    ordering = _cholmod_ordering(settings, ne.n)

    def direct(perm: NDArray[np.int64] | None = perm) -> _DampedSystem:
        nonlocal ordering
        if ordering != "metis" or (perm is not None and len(perm) != ne.n):
            perm = None
        elif perm is None:
            try:
                perm = nested_dissection(ne.indptr, ne.indices)
            except (RuntimeError, ValueError, ImportError) as e:  # a GTSAM built without METIS: slower, not wrong
                log.warning("METIS ordering unavailable (%s): CHOLMOD orders by AMD", e)
                ordering = "amd"
        return _DampedSystem(ne, perm)

    solver: _DampedSystem | _TreeSystem = _TreeSystem(ne, direct) if iterative else \
        direct()
    if iterative:
        log.debug("LM over %d unknowns: conjugate gradients, spanning-tree preconditioner (CHOLMOD)", ne.n)
    else:
        log.debug("LM over %d unknowns: CHOLMOD, %s ordering", ne.n, ordering)
    H, grad, err = obj.linearise(v)
    initial = err
    lam = settings.lambda_initial
    nu = 2.0
    it = factorizations = 0
    converged = False
    try:
        while it < settings.max_iterations:
            diag = np.clip(H[ne.diag_pos], 1e-9, None)
            accepted = False
            while lam <= settings.lambda_upper:
                Hd = H.copy()
                Hd[ne.diag_pos] += lam * diag
                factorizations += 1
                try:
                    solver.factor(Hd)
                    step = -solver.solve(grad)
                except np.linalg.LinAlgError:  # not positive definite: damp more
                    lam, nu = lam * nu, nu * 2.0
                    continue
                # predicted decrease of the Gauss-Newton model, 0.5 |r + J s|^2
                pred = -(grad @ step) - 0.5 * (step @ _sym_matvec(ne, H, step))
                v_new = v + step
                v_new[2::3] = wrap_angle(v_new[2::3])
                err_new = obj.error(v_new)
                rho = (err - err_new) / pred if pred > 0 else -1.0
                if rho > 0:
                    accepted = True
                    lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                    nu = 2.0
                    break
                lam, nu = lam * nu, nu * 2.0
            if not accepted:
                break  # stall: no lambda gives a lower error
            it += 1
            log.debug("LM %d: error %.6g -> %.6g, rho %.3f, lambda %.3g, factorisations %d", it, err, err_new, rho, lam,
                      factorizations)
            if hook is not None:
                hook(it, err, err_new)
            decrease = err - err_new
            # a step that only turns the map, while the error barely moves (within 10x the tolerance)
            shape = (settings.shape_tol_m > 0 and decrease <= 10 * settings.relative_error_tol * err
                     and nonrigid_rms(v[0::3], v[1::3], v_new[0::3], v_new[1::3]) < settings.shape_tol_m)
            v = v_new
            if shape or decrease <= settings.absolute_error_tol or decrease <= settings.relative_error_tol * err:
                err = err_new
                converged = True
                break
            H, grad, err = obj.linearise(v)
    finally:
        solver.free()
    out = xyh.copy()
    out[graph.variables] = v.reshape(-1, 3)
    if isinstance(solver, _TreeSystem):
        log.debug("conjugate gradients: %d iterations in %d factorisations%s", solver.iterations, factorizations,
                  "" if solver.iterative else ", then the direct factorisation")
    if isinstance(solver, _TreeSystem) and solver.iterative:
        info = FactorInfo("", "pcg")
    else:
        info = FactorInfo(ordering)
    return LMResult(out, it, factorizations, initial, err, converged, info)


def nonrigid_rms(x0: NDArray, y0: NDArray, x1: NDArray, y1: NDArray) -> float:
    """RMS distance (metres) from points (x1, y1) to the best rigid motion (rotation + translation,
    least squares: Kabsch) of points (x0, y0).

    Why the solver asks: with one pose held fixed, LM's last iterations on a large survey turn the
    whole map about it by ~0.4 deg an iteration at almost no change of the error (paper size 8:
    7 of 15 iterations, non-rigid part 2 mm rms). No distance, and no
    output up to the frame, depends on that motion."""
    if len(x0) < 2:
        return 0.0
    p = np.column_stack([x0 - x0.mean(), y0 - y0.mean()])
    q = np.column_stack([x1 - x1.mean(), y1 - y1.mean()])
    c = p.T @ q  # cross-covariance; the optimal rotation angle in closed form (2-D)
    ang = np.arctan2(c[0, 1] - c[1, 0], c[0, 0] + c[1, 1])
    co, si = np.cos(ang), np.sin(ang)
    rot = p @ np.array([[co, si], [-si, co]])
    return float(np.sqrt(np.mean(np.sum((q - rot) ** 2, axis=1))))


def _sym_matvec(ne: _NormalEquations, upper_data: NDArray, x: NDArray) -> NDArray:
    """(J^T J) x from its upper triangle."""
    U = sparse.csr_matrix((upper_data, ne.indices, ne.indptr), shape=(ne.n, ne.n))
    return U @ x + U.T @ x - upper_data[ne.diag_pos] * x
