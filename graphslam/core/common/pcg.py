"""Preconditioned conjugate gradients, and a spanning tree of a block matrix's graph as the preconditioner.

The survey's damped normal equations ``A x = b`` (3x3 blocks, one block row per solved pose) are a
sum of per-factor terms: an IMU chain or a WiFi, magnetic or reference pair adds
``[[A_aa, A_ab], [A_ba, A_bb]]`` at its two poses. A direct Cholesky of a large survey's ``A`` fills:
the WiFi edges tie walks together, and the factor of a 200-walk survey holds 80 M entries (608 MiB)
however it is ordered. The preconditioner here keeps every diagonal block and the off-diagonal
blocks of a maximum spanning tree of the block graph (each pair of poses weighted by the Frobenius
norm of its block): a tree's matrix factorises with no fill, in time and memory linear in the
poses. The subgraph preconditioner of Dellaert, Carlson, Ila, Ni and Thorpe (IROS 2010) in its
simplest form.

Why it is safe: every factor's term is positive semi-definite (Gauss-Newton's ``J^T J``, the range
factors' exact Hessian ``[[H, -H], [-H, H]]`` with ``H >= 0``; the damping sits on the diagonal blocks,
all kept). ``P`` is ``A`` with each left-out pair's summed term ``S = [[S_aa, S_ab], [S_ba, S_bb]]``
replaced by ``[[S_aa, 0], [0, S_bb]]``, which is at least half of it (their difference, ``[[S_aa, -S_ab],
[-S_ba, S_bb]]``, is ``S`` with one pose's sign flipped: positive semi-definite). So ``P >= A / 2`` and
``P`` is positive definite wherever ``A`` is; conjugate gradients in ``P``'s norm converge as
``A``'s condition number relative to ``P`` allows (80-100 iterations to a relative residual of 1e-10
with the magnetic pairs, ~25 without, on every survey measured, 27k to 168k unknowns:
docs/benchmarks.md).
"""

from __future__ import annotations

from typing import Callable

import numpy as np
from numpy.typing import NDArray
from scipy import sparse
from scipy.sparse.csgraph import minimum_spanning_tree

LinearMap = Callable[[NDArray[np.float64]], NDArray[np.float64]]


def conjugate_gradients(
    matvec: LinearMap, b: NDArray[np.float64], precondition: LinearMap, *, tol: float, max_iterations: int,
    x0: NDArray[np.float64] | None = None,
) -> tuple[NDArray[np.float64], int, bool]:
    """(x, iterations, converged): preconditioned conjugate gradients for ``matvec(x) = b`` from ``x0``
    (default 0) until the residual's norm is at most ``tol`` (absolute). Not converged: the iteration
    cap, or a direction of non-positive curvature (the matrix, or the preconditioner's view of it, not
    positive definite): ``x`` is then the last iterate."""
    if x0 is None:
        x, r = np.zeros_like(b), np.array(b, np.float64)
    else:
        x = x0
        r = b - matvec(x)
    if float(np.linalg.norm(r)) <= tol:
        return x, 0, True
    z = precondition(r)
    p, rz = z, float(r @ z)
    for it in range(1, max_iterations + 1):
        Ap = matvec(p)
        pAp = float(p @ Ap)
        if not pAp > 0:
            return x, it, False
        alpha = rz / pAp
        x = x + alpha * p
        r = r - alpha * Ap
        if float(np.linalg.norm(r)) <= tol:
            return x, it, True
        z = precondition(r)
        rz, rz_prev = float(r @ z), rz
        p = z + (rz / rz_prev) * p
    return x, max_iterations, False


def spanning_tree_blocks(
    n_vars: int, block_lo: NDArray[np.int64], block_hi: NDArray[np.int64], block_weight: NDArray[np.float64],
) -> NDArray[np.bool_]:
    """Per block (``block_lo[i] <= block_hi[i]``, block rows, each pair once; diagonal blocks have
    ``lo == hi``): kept in the preconditioner. Every diagonal block, and the off-diagonal blocks of a
    maximum spanning tree (a forest, on a disconnected graph) of the graph whose edges they are,
    weighted by ``block_weight`` (a block of weight 0 or NaN joins no tree)."""
    keep = block_lo == block_hi
    off = np.flatnonzero(~keep & (block_weight > 0))
    if not len(off):
        return keep
    # a spanning tree depends only on the weights' order: minimum_spanning_tree over their ranks,
    # heaviest first (1, 2, ...: no overflow of 1 / weight, no zero that scipy would take for no edge);
    # each edge's block found again by the order of its (lo, hi) key among the sorted keys
    rank = np.empty(len(off))
    rank[np.argsort(-block_weight[off], kind="stable")] = np.arange(1, len(off) + 1)
    g = sparse.csr_matrix((rank, (block_lo[off], block_hi[off])), shape=(n_vars, n_vars))
    t = minimum_spanning_tree(g).tocoo()
    lo, hi = np.minimum(t.row, t.col).astype(np.int64), np.maximum(t.row, t.col).astype(np.int64)
    keys = block_lo[off] * n_vars + block_hi[off]
    order = np.argsort(keys, kind="stable")
    at = np.searchsorted(keys[order], lo * n_vars + hi)
    keep[off[order[at]]] = True
    return keep


__all__ = ["LinearMap", "conjugate_gradients", "spanning_tree_blocks"]
