"""The phone's heading (``/phone/heading``) as each walk's rotation into the Earth frame.

A walk's dead reckoning is in its own frame; the phone's yaw is Earth-fixed (radians CCW from
east). Per step k, ``yaw_k - h_k`` (``h_k``: the dead-reckoned heading at the same instant) is the
rotation that takes the walk's frame to east/north, up to what is real about a phone indoors:

- a per-walk offset between where the phone points and where the walker goes (held in the
  hand: small; turned or pocketed: any) — one rotation per walk, which the heading cannot
  tell apart from the walk's own rotation;
- stretches bent by the building's steel (spatially correlated, metres to tens of metres);
- outliers and noise per step;
- with a foot module, the dead reckoning's own heading drift, which ``yaw_k - h_k`` then follows.

``walk_headings`` estimates one rotation per walk: the circular mean of ``yaw_k - h_k`` with
Cauchy weights (disturbed stretches and outliers down-weighted), and its uncertainty: the
residuals' robust spread over the effective number of independent stretches, never below
``sigma_floor_rad`` (the per-walk offset, which no single walk reveals). The survey uses it
as the walk's rotation in the placement and as a prior on its heading in the optimiser
(``graphslam.core.survey.align``).

Frames: dead reckoning (each walk's own) -> Earth (x east, y north). Angles in radians.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from graphslam.core.types import Session, Survey, wrap_angle


@dataclass(frozen=True, eq=False)
class WalkHeadings:
    """Per walk: rotation from its dead-reckoning frame to the Earth frame (rad) and its sigma."""

    rotation: NDArray[np.float64]  # (S,) NaN where the walk has no heading
    sigma: NDArray[np.float64]  # (S,) rad; NaN where the walk has no heading
    spread: NDArray[np.float64]  # (S,) robust spread of yaw - h along the walk (rad)

    @property
    def available(self) -> NDArray[np.bool_]:
        return np.isfinite(self.rotation)

    @property
    def complete(self) -> bool:
        """Every walk has a heading (the survey can be solved north-up)."""
        return bool(len(self.rotation)) and bool(self.available.all())


def heading_residuals(session: Session) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """(step index, yaw - dead-reckoned heading) per heading message that falls on a step
    (the contract: one message per step after the first; others are matched to the nearest
    step no more than half a step away)."""
    h = session.heading
    if h is None or len(h) == 0 or len(session.steps) == 0:
        return np.zeros(0, np.int64), np.zeros(0)
    t = session.steps.t_ns
    k = np.clip(np.searchsorted(t, h.t_ns), 1, len(t) - 1) if len(t) > 1 else np.zeros(len(h), np.int64)
    if len(t) > 1:
        prev = k - 1
        k = np.where(np.abs(t[prev] - h.t_ns) < np.abs(t[k] - h.t_ns), prev, k)
        step_ns = float(np.median(np.diff(t)))
        ok = np.abs(t[k] - h.t_ns) <= 0.5 * step_ns
    else:
        ok = np.abs(t[k] - h.t_ns) <= 0
    k = k[ok]
    return k.astype(np.int64), np.asarray(wrap_angle(h.yaw[ok] - session.steps.heading[k]), float)


def robust_circular_mean(d: NDArray[np.float64], scale_rad: float, iterations: int = 10) -> tuple[float, float]:
    """(mean, robust spread) of angles ``d``: Cauchy-weighted circular mean, MAD-based spread."""
    mu = float(np.angle(np.exp(1j * d).mean()))
    for _ in range(iterations):
        r = np.asarray(wrap_angle(d - mu))
        w = 1.0 / (1.0 + (r / scale_rad) ** 2)
        mu = float(np.angle((w * np.exp(1j * d)).sum()))
    r = np.asarray(wrap_angle(d - mu))
    return mu, float(1.4826 * np.median(np.abs(r)))


def walk_headings(
    survey: Survey,
    *,
    sigma_floor_rad: float,
    cauchy_scale_rad: float = np.radians(10.0),
    correlation_steps: int = 20,
    min_steps: int = 3,
) -> WalkHeadings:
    """One rotation (dead reckoning -> Earth) per walk from its heading (module docstring).

    ``correlation_steps``: steps over which the residual is treated as one draw (indoor
    distortion is spatially correlated): the spread counts ``n / correlation_steps`` draws.
    A walk with fewer than ``min_steps`` heading samples has none (NaN)."""
    n = len(survey.sessions)
    rot, sig, spread = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
    for s, sess in enumerate(survey):
        _, d = heading_residuals(sess)
        if len(d) < min_steps:
            continue
        mu, sp = robust_circular_mean(d, cauchy_scale_rad)
        n_eff = max(1.0, len(d) / correlation_steps)
        rot[s], spread[s] = mu, sp
        sig[s] = float(np.hypot(sigma_floor_rad, sp / np.sqrt(n_eff)))
    return WalkHeadings(rot, sig, spread)
