"""Where a walker is between two steps: the motion model UWB ranges are attached with.

A range is taken at any instant, a foot module reports a pose per step. Between steps
k-1 and k the walker moves during the last ``move_s`` of the interval (one stride) and stands
still before that: a long interval is a pause, not a slow step. ``move_s`` defaults to the
walk's median step interval. The same model places the simulator's radios (so the sim's
"truth" between steps and the solver's assumption agree up to the stride-time jitter, ~4 %)
and attaches ranges to the dead-reckoned steps in the survey.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def median_step_s(t_ns: NDArray[np.int64]) -> float:
    """The walk's median step interval (s); 0.5 s for fewer than two steps."""
    dt = np.diff(np.asarray(t_ns, np.int64)) / 1e9
    return float(np.median(dt)) if len(dt) else 0.5


def stride_knots(t_ns: NDArray[np.int64], xy: NDArray, move_s: float | None = None) -> tuple[NDArray, NDArray]:
    """Knots (t_s, xy) of the piecewise-linear path: each step, plus the instant the stride
    towards it starts (the end of a pause) where the interval is longer than ``move_s``.
    Times in s relative to ``t_ns[0]``."""
    t = (np.asarray(t_ns, np.int64) - int(t_ns[0])) / 1e9
    xy = np.asarray(xy, float)
    move = median_step_s(t_ns) if move_s is None else move_s
    if len(t) < 2:
        return t, xy
    pause = np.flatnonzero(np.diff(t) > move * 1.0001) + 1  # steps preceded by a pause
    kt = np.concatenate([t, t[pause] - move])
    kxy = np.concatenate([xy, xy[pause - 1]])
    order = np.argsort(kt, kind="stable")
    return kt[order], kxy[order]


def position_at(t_ns: NDArray[np.int64], xy: NDArray, t_query_ns: NDArray, move_s: float | None = None) -> NDArray:
    """(Q, 2) positions at ``t_query_ns`` by the stride model (clamped to the first/last step)."""
    kt, kxy = stride_knots(t_ns, xy, move_s)
    q = (np.asarray(t_query_ns, np.int64) - int(t_ns[0])) / 1e9
    return np.column_stack([np.interp(q, kt, kxy[:, 0]), np.interp(q, kt, kxy[:, 1])])


def stride_fraction(t_ns: NDArray[np.int64], t_query_ns: NDArray, move_s: float | None = None) -> tuple[NDArray, NDArray]:
    """For each query time: the step k with t_k <= t < t_{k+1} (clamped to [0, N-2]) and the
    fraction f in [0, 1] of stride k -> k+1 done at t (0 while standing at k)."""
    t = np.asarray(t_ns, np.int64)
    q = np.asarray(t_query_ns, np.int64)
    move = median_step_s(t) if move_s is None else move_s
    k = np.clip(np.searchsorted(t, q, side="right") - 1, 0, max(len(t) - 2, 0))
    if len(t) < 2:
        return k, np.zeros(len(q))
    t_end = t[k + 1]
    dur = np.minimum((t_end - t[k]) / 1e9, move)
    f = 1.0 - (t_end - q) / 1e9 / np.maximum(dur, 1e-9)
    return k, np.clip(f, 0.0, 1.0)
