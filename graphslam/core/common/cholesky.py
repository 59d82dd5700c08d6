"""Sparse Cholesky of a symmetric positive-definite matrix given by its upper triangle (CSR), for the
vectorised Levenberg-Marquardt's damped normal equations: the fill-reducing ordering and the
symbolic factorisation once per pattern, then numeric refactorisations and solves
(``factor(data)``, ``solve(b)``, ``free()``).

SuiteSparse CHOLMOD (supernodal, or simplicial for a pattern that barely fills; double precision, one
thread: cvxopt's BLAS is a single-threaded build) through ``cvxopt``, a dependency: its wheels cover
every platform GTSAM's do (Linux x86-64 and ARM, macOS). Its ordering: ``nested_dissection`` (GTSAM's
METIS) where given, else CHOLMOD's AMD. Pure maths on arrays.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


class _Cholmod:
    """CHOLMOD (cvxopt's SuiteSparse, supernodal) for the same matrices: the ordering and symbolic
    factorisation once, then numeric refactorisations. Double precision only.

    ``perm``: the fill-reducing ordering to use (``nested_dissection``), else CHOLMOD's AMD. A given
    ordering is used as it is (``nmethods`` 1): by default CHOLMOD would also try AMD and keep
    whichever fills less, an analysis that costs time and leaves the choice to CHOLMOD."""

    def __init__(self, indptr: NDArray[np.int32], indices: NDArray[np.int32],
                 perm: NDArray[np.int64] | None = None, simplicial: bool = False) -> None:
        import cvxopt
        from cvxopt import cholmod

        self._cvxopt, self._cholmod = cvxopt, cholmod
        self._n = len(indptr) - 1
        # the upper triangle in CSR is the lower triangle in CSC: the same arrays, rows <-> columns;
        # its entries already in CSC order, so a refactorisation only replaces the values (``V``)
        rows = cvxopt.matrix(np.asarray(indices, np.int64))
        cols = cvxopt.matrix(np.repeat(np.arange(self._n, dtype=np.int64), np.diff(indptr)))
        self._a = cvxopt.spmatrix(cvxopt.matrix(np.ones(len(indices))), rows, cols, (self._n, self._n))
        self._simplicial = simplicial
        # cholmod.options is the module's, read by every call: each factorisation sets its own
        self._options = {"supernodal": 0 if simplicial else 2, "postorder": _POSTORDER}
        if perm is not None:
            self._options["nmethods"] = 1  # this ordering, no other tried
        self._set_options()
        if perm is None:
            self._factor = cholmod.symbolic(self._a, uplo="L")
        else:
            self._factor = cholmod.symbolic(self._a, p=cvxopt.matrix(np.asarray(perm, np.int64)), uplo="L")

    def _set_options(self) -> None:
        # supernodal 2: BLAS-3 on the dense fronts; 0: LDL' column by column, for a factor with no fill
        # (a tree's), where a supernode's fixed cost would outweigh its few entries
        self._cholmod.options.clear()
        self._cholmod.options.update(self._options)

    def factor(self, data: NDArray) -> None:
        self._a.V = self._cvxopt.matrix(np.ascontiguousarray(data, np.float64))
        self._set_options()
        try:
            self._cholmod.numeric(self._a, self._factor)
        except ArithmeticError as e:  # not positive definite
            raise np.linalg.LinAlgError(f"CHOLMOD: {e}") from None
        if self._simplicial:
            # LDL' goes through a matrix that is not positive definite where no pivot is zero: refused as
            # LL' is, by D's pivots (1 / D: solve D x = 1)
            inv_d = self._cvxopt.matrix(np.ones(self._n))
            self._cholmod.solve(self._factor, inv_d, sys=6)
            if not (np.array(inv_d) > 0).all():
                raise np.linalg.LinAlgError("CHOLMOD: not positive definite (a non-positive pivot of D)")

    def solve(self, b: NDArray) -> NDArray[np.float64]:
        x = self._cvxopt.matrix(np.ascontiguousarray(b, np.float64))
        self._cholmod.solve(self._factor, x)
        return np.array(x, np.float64).ravel()

    def permutation(self) -> NDArray[np.int64]:
        """The row order CHOLMOD factorises in (its P in P A P^T = L L^T): the ordering given or
        AMD's, then CHOLMOD's postorder of the elimination tree (the same fill)."""
        x = self._cvxopt.matrix(np.arange(self._n, dtype=np.float64))
        self._cholmod.solve(self._factor, x, sys=7)  # x = P b
        return np.array(x, np.float64).ravel().astype(np.int64)

    def free(self) -> None:
        self._factor = None


# CHOLMOD follows the ordering with a postorder of its elimination tree (the same fill, larger
# supernodes: paper size 12's factorisation 1.6-2.0 s against 2.1-3.4 s without)
_POSTORDER = True

def cholmod_available() -> bool:
    """cvxopt's CHOLMOD imports (a dependency; absent only from a broken install)."""
    try:
        import cvxopt.cholmod  # noqa: F401
    except ImportError:
        return False
    return True


def nested_dissection(indptr: NDArray[np.int32], indices: NDArray[np.int32], block: int = 3) -> NDArray[np.int64]:
    """A fill-reducing permutation of the symmetric pattern whose upper triangle is the CSR
    (``indptr``, ``indices``): METIS nested dissection (GTSAM's, in every gtsam wheel) of the graph
    of its ``block`` x ``block`` blocks (a pose's unknowns stay together: fewer, larger supernodes).

    Why not AMD: WiFi edges tie every walk to many others, and a minimum-degree ordering of such a
    graph fills the factor far more than dissecting it (paper size 12: 1.8x the non-zeros).
    Connected components are ordered one after the other, METIS on each of at least
    ``_METIS_MIN_BLOCKS`` blocks, the smaller ones (single poses, short chains: no fill to save) as
    they come; GTSAM's METIS crashes the process on a pose without neighbours."""
    n = len(indptr) - 1
    if n % block:
        raise ValueError(f"nested_dissection: order {n} is not a multiple of the block size {block}")
    rows = np.repeat(np.arange(n, dtype=np.int64), np.diff(indptr)) // block
    return block_nested_dissection(n // block, rows, np.asarray(indices, np.int64) // block, block)


def block_nested_dissection(
    m: int, a: NDArray[np.int64], b: NDArray[np.int64], block: int = 3
) -> NDArray[np.int64]:
    """``nested_dissection`` of the graph of ``m`` blocks whose edges are (``a``, ``b``) (either order,
    repeats and self-loops allowed): the permutation of the ``block * m`` scalar unknowns."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    lo, hi = np.minimum(a, b), np.maximum(a, b)
    off = lo != hi
    keys = np.unique(lo[off] * m + hi[off])  # block edges (i < j), once each
    bi, bj = keys // m, keys % m
    n_comp, label = connected_components(coo_matrix((np.ones(len(bi)), (bi, bj)), shape=(m, m)), directed=False)
    by_comp = np.argsort(label, kind="stable")
    starts = np.searchsorted(label[by_comp], np.arange(n_comp + 1))
    edge_comp = label[bi]
    edge_order = np.argsort(edge_comp, kind="stable")
    edge_starts = np.searchsorted(edge_comp[edge_order], np.arange(n_comp + 1))
    local = np.empty(m, np.int64)
    order = []
    for c in range(n_comp):
        verts = by_comp[starts[c]:starts[c + 1]]
        if len(verts) < _METIS_MIN_BLOCKS:
            order.append(verts)
            continue
        local[verts] = np.arange(len(verts))
        e = edge_order[edge_starts[c]:edge_starts[c + 1]]
        order.append(verts[_metis(len(verts), local[bi[e]], local[bj[e]])])
    blocks = np.concatenate(order) if order else np.zeros(0, np.int64)
    return (block * blocks[:, None] + np.arange(block)).ravel()


_METIS_MIN_BLOCKS = 16


def _metis(m: int, a: NDArray[np.int64], b: NDArray[np.int64]) -> NDArray[np.int64]:
    """METIS_NodeND (through GTSAM) of the connected graph of ``m`` vertices and edges (a, b)."""
    import gtsam

    graph = gtsam.SymbolicFactorGraph()
    for i, j in zip(a.tolist(), b.tolist()):
        graph.push_factor(i, j)
    ordering = gtsam.Ordering.MetisSymbolicFactorGraph(graph)
    perm = np.fromiter((ordering.at(k) for k in range(ordering.size())), np.int64, count=ordering.size())
    if len(perm) != m or not np.array_equal(np.sort(perm), np.arange(m)):
        raise ValueError(f"METIS returned no permutation of the {m} vertices")
    return perm


def sparse_cholesky(
    indptr: NDArray[np.int32], indices: NDArray[np.int32], perm: NDArray[np.int64] | None = None,
    simplicial: bool = False,
) -> _Cholmod:
    """A CHOLMOD factorisation of the upper-triangle CSR pattern (``indptr``, ``indices``): ``perm`` the
    fill-reducing ordering, else its AMD; ``simplicial``: LDL' column by column instead of supernodes, for
    a pattern that barely fills."""
    return _Cholmod(indptr, indices, perm=perm, simplicial=simplicial)
