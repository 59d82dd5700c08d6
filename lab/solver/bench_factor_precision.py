#!/usr/bin/env python3
"""The survey's LM with the factorisation in double vs single precision (refined in double), side by side.

For each folder of recordings: ``align`` once per precision and round (alternating, so a drifting
machine hits both), with PARDISO's phases and the refinement's products timed inside the run.
Prints one JSON line per folder and precision: optimise wall (median of the rounds), numeric
factorisation and triangular-solve seconds, solves per LM step, final error, landmark error, and
how often single precision fell back to double. Ground truth only scores.

    python lab/solver/bench_factor_precision.py /tmp/p4 /tmp/p8 /tmp/p12 --rounds 3

(folders: ``graphslam simulate paper --seed 0 --size N --out /tmp/pN``)
"""

from __future__ import annotations

import argparse
import collections
import glob
import json
import statistics
import time

from graphslam import evaluate, GraphSlamConfig, read_survey, survey_align as A, survey_solver as S

PHASES = {11: "analysis_s", 22: "factor_s", 33: "solve_s"}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folders", nargs="+")
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()

    clock: collections.Counter = collections.Counter()
    calls: collections.Counter = collections.Counter()
    fallbacks: list[int] = []
    call, free = S._Pardiso._call, S._DampedSystem.free

    def timed_call(self: S._Pardiso, phase: int, b, x) -> None:
        t = time.perf_counter()
        call(self, phase, b, x)
        clock[phase] += time.perf_counter() - t
        calls[phase] += 1

    def counted_free(self: S._DampedSystem) -> None:
        fallbacks.append(self.fallbacks)
        free(self)

    S._Pardiso._call = timed_call  # type: ignore[method-assign]
    S._DampedSystem.free = counted_free  # type: ignore[method-assign]
    for folder in args.folders:
        survey = read_survey(sorted(glob.glob(f"{folder}/*.mcap")))
        rows: dict[str, list[dict]] = {"double": [], "single": []}
        for _ in range(args.rounds):
            for precision in rows:
                cfg = GraphSlamConfig.model_validate({"optimizer": {"factor_precision": precision}})
                clock.clear(), calls.clear(), fallbacks.clear()
                al = A.align(survey, cfg)
                rows[precision].append({
                    "optimise_s": al.timings_s["optimise"],
                    **{name: clock[p] for p, name in PHASES.items()},
                    "factorisations": calls[22], "solves": calls[33],
                    "final_error": al.final_error, "fallbacks": sum(fallbacks),
                    "landmark_mean_m": evaluate(al.tracks, survey).landmarks.mean_m,
                })
        for precision, rs in rows.items():
            med = {k: round(statistics.median(r[k] for r in rs), 3) for k in ("optimise_s", "analysis_s", "factor_s", "solve_s")}
            last = rs[-1]
            print(json.dumps({
                "folder": folder, "precision": precision, "rounds": len(rs), **med,
                "factorisations": last["factorisations"],
                "solves_per_factorisation": round(last["solves"] / max(1, last["factorisations"]), 2),
                "final_error": round(last["final_error"], 6), "landmark_mean_m": round(last["landmark_mean_m"], 4),
                "fallbacks": last["fallbacks"],
            }), flush=True)


if __name__ == "__main__":
    main()
