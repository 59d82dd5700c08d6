#!/usr/bin/env python3
"""The survey optimiser's linear system solved by each candidate sparse solver, side by side.

The system: the damped normal equations of the first LM step of stage 0 on a simulated
``paper`` survey (``core/survey/solver.py`` builds them; the same sparsity as GTSAM's).
Per solver, single-threaded, the fastest of ``--repeats`` runs, wall and process CPU seconds
(on a busy machine CPU time is the fairer comparison; both only grow with load):

- ``product``: the survey's own CHOLMOD (cvxopt, ``graphslam.core.common.cholesky``), METIS; analysis
  once, then numeric refactorisation + solve (what every LM iteration after the first costs);
- ``gtsam``: GTSAM's multifrontal Cholesky with METIS ordering on the GTSAM graph linearised at
  the same point (what GTSAM's LM pays per lambda try: elimination includes the symbolic work);
- ``cholmod``: CHOLMOD via the ``sksparse-minimal`` wheel (bundled reference BLAS; no API to
  reuse the analysis), if installed;
- ``qdldl``: QDLDL (AMD ordering, simplicial LDL^T), refactorisation + solve, if installed.

    python lab/solver/bench_linear_solvers.py --sizes 1,4,12 [--skip qdldl] [--repeats 3]

Prints one JSON line per size: seconds per solver and the residual |Ax - b| / |b|.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np
from scipy import sparse
from threadpoolctl import threadpool_limits

from graphslam import build_problem, GraphSlamConfig, native_graph, pose_graph, simulate, survey_solver as S

CPU: dict[str, float] = {}  # process CPU seconds of the last ``best`` call's fastest run


def best(fun, repeats: int, name: str) -> tuple[float, object]:
    """(fastest wall time, result); its CPU time (less sensitive to other jobs) goes to CPU[name]."""
    out, ts = None, []
    for _ in range(repeats):
        c = time.process_time()
        t = time.perf_counter()
        out = fun()
        ts.append((time.perf_counter() - t, time.process_time() - c))
    wall, cpu = min(ts)
    CPU[name] = round(cpu, 4)
    return wall, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", default="1,4")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--skip", default="", help="comma-separated solvers to leave out")
    args = ap.parse_args()
    skip = set(filter(None, args.skip.split(",")))
    cfg = GraphSlamConfig()
    for size in (float(s) for s in args.sizes.split(",")):
        print(json.dumps(measure(size, args.seed, args.repeats, skip, cfg)), flush=True)


def measure(size: float, seed: int, repeats: int, skip: set[str], cfg: GraphSlamConfig) -> dict:
    """One JSON row: every solver on the stage-0 system of ``paper`` at ``size``."""
    problem = build_problem(simulate("paper", seed=seed, size=size).survey, cfg)
    graph, _ = pose_graph(problem, cfg)
    active = np.ones(len(problem.wifi_pairs), bool)
    obj = S._Objective(graph, active, problem.init_xyh)
    v = problem.init_xyh[graph.variables].ravel()
    H, g, _ = obj.linearise(v)
    ne = obj.normal
    H[ne.diag_pos] += 1e-5 * np.clip(H[ne.diag_pos], 1e-9, None)  # LM's damping
    upper = sparse.csr_matrix((H, ne.indices, ne.indptr), shape=(ne.n, ne.n))
    full = (upper + upper.T - sparse.diags(H[ne.diag_pos])).tocsc()
    row: dict = {"size": size, "variables": ne.n, "nnz_upper": len(H), "load_1min": round(os.getloadavg()[0], 2)}

    def residual(x: np.ndarray) -> float:
        return float(np.linalg.norm(full @ x + g) / np.linalg.norm(g))

    with threadpool_limits(1):
        if "product" not in skip:
            t = time.perf_counter()
            p = S.sparse_cholesky(ne.indptr, ne.indices, perm=S.nested_dissection(ne.indptr, ne.indices))
            row["product_analyse_s"] = round(time.perf_counter() - t, 4)
            dt, x = best(lambda: (p.factor(H), p.solve(-g))[1], repeats, "product_refactor_solve_cpu_s")
            row["product_refactor_solve_s"] = round(dt, 4)
            row["product_residual"] = residual(x)
            p.free()
        if "gtsam" not in skip:
            import gtsam

            imu, wifi, values, _ = native_graph(problem, cfg)
            full_graph = gtsam.NonlinearFactorGraph(imu)
            for f in wifi:
                full_graph.add(f)
            lin = full_graph.linearize(values)
            dt, _ = best(lambda: lin.optimize(gtsam.Ordering.MetisGaussianFactorGraph(lin)), repeats, "gtsam_cpu_s")
            row["gtsam_multifrontal_metis_s"] = round(dt, 4)
        if "cholmod" not in skip:
            try:
                from sksparse_minimal import SparseCholesky
            except ImportError:
                row["cholmod_s"] = "not installed (pip install sksparse-minimal)"
            else:
                dt, x = best(lambda: SparseCholesky(full).solve_A(-g), repeats, "cholmod_cpu_s")
                row["cholmod_analyse_factor_solve_s"] = round(dt, 4)
                row["cholmod_residual"] = residual(x)
        if "qdldl" not in skip:
            try:
                import qdldl
            except ImportError:
                row["qdldl_s"] = "not installed (pip install qdldl)"
            else:
                t = time.perf_counter()
                q = qdldl.Solver(full)
                row["qdldl_first_s"] = round(time.perf_counter() - t, 4)
                dt, x = best(lambda: (q.update(full), q.solve(-g))[1], repeats, "qdldl_refactor_solve_cpu_s")
                row["qdldl_refactor_solve_s"] = round(dt, 4)
                row["qdldl_residual"] = residual(x)
    row.update(CPU)
    return row


if __name__ == "__main__":
    main()
