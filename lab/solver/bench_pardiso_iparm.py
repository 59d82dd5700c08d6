"""PARDISO options on a survey's own normal equations: analysis and numeric factorisation time,
factor non-zeros, for the default parameters and the two-level factorisation (iparm[23] = 1).

    python lab/solver/bench_pardiso_iparm.py RECORDINGS_FOLDER [--repeat 3]

The system is the first LM step's damped J^T J of ``graphslam survey RECORDINGS_FOLDER`` (default
configuration), captured from the solver; each variant analyses it once and factorises it
``--repeat`` times (median). ``MKL_NUM_THREADS`` sets the threads. Output: one JSON line per variant.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np

from graphslam import align, config_from_dict, read_survey, survey_solver as S


class _Captured(Exception):
    pass


def first_system(folder: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    cap: dict = {}
    init, factor = S._Pardiso.__init__, S._Pardiso.factor

    def capture_init(self, indptr, indices, threads=0):  # type: ignore[no-untyped-def]
        cap["pattern"] = (indptr.copy(), indices.copy())
        init(self, indptr, indices, threads)

    def capture_factor(self, data):  # type: ignore[no-untyped-def]
        cap["data"] = data.copy()
        raise _Captured

    S._Pardiso.__init__, S._Pardiso.factor = capture_init, capture_factor
    try:
        align(read_survey(sorted(folder.glob("*.mcap"))), config_from_dict({"optimizer": {"solver": "pardiso"}}))
    except _Captured:
        pass
    finally:
        S._Pardiso.__init__, S._Pardiso.factor = init, factor
    return cap["pattern"][0], cap["pattern"][1], cap["data"]


def measure(indptr: np.ndarray, indices: np.ndarray, data: np.ndarray, iparm: dict[int, int], repeat: int) -> dict:
    p = S._Pardiso.__new__(S._Pardiso)  # the product's wrapper, its iparm replaced before the analysis
    p._lib, p._n, p._threads, p._live = S._mkl_runtime(), len(indptr) - 1, 0, False
    p._ia, p._ja = (indptr + 1).astype(np.int32), (indices + 1).astype(np.int32)
    p._a, p._pt = np.zeros(len(indices)), np.zeros(64, np.int64)
    p._iparm = np.zeros(64, np.int32)
    p._iparm[[0, 1, 9, 17]] = [1, 2, 8, -1]
    for k, v in iparm.items():
        p._iparm[k] = v
    t = time.perf_counter()
    p._call(11, np.zeros(1), np.zeros(1))
    analyse = time.perf_counter() - t
    p._live = True
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        p.factor(data)
        times.append(time.perf_counter() - t)
    x = p.solve(np.ones(p._n))
    nnz = int(p._iparm[17])
    p.free()
    return {"analyse_s": round(analyse, 3), "factor_s_median": round(statistics.median(times), 3),
            "factor_nnz": nnz, "x_checksum": float(np.round(x.sum(), 6))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    indptr, indices, data = first_system(args.folder)
    for name, iparm in (("default", {}), ("two-level (iparm[23]=1)", {23: 1})) * 2:
        row = {"variant": name, "variables": len(indptr) - 1, **measure(indptr, indices, data, iparm, args.repeat)}
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
