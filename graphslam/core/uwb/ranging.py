"""UWB range models (Paper 003, section IV-A/B): two-way ranging, trilateration, planar ranges.

Units: seconds, metres; positions in the site frame. A UWB radio measures the 3-D distance
between its antenna and the responder's; the survey and the filter work in the plane, with
every tag at one assumed height (``tag_height_m``) and anchors at their own height when the
anchor record gives one (a 2-D anchor is taken to be at tag height).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

SPEED_OF_LIGHT_MPS = 299_792_458.0


def ss_twr_tof(t_round: NDArray | float, t_reply: NDArray | float) -> NDArray:
    """Eq. 4, single-sided: time of flight = (round trip at the initiator - reply delay at the
    responder) / 2, each interval measured by its own device's clock (s).

    A clock-rate difference e between the two devices biases it by e * t_reply / 2: 20 ppm and a
    0.3 ms reply give 3 ns, i.e. 0.9 m. ``ds_twr_tof`` cancels that to first order.
    """
    return (np.asarray(t_round, float) - np.asarray(t_reply, float)) / 2.0


def ds_twr_tof(
    t_round1: NDArray | float, t_reply1: NDArray | float, t_round2: NDArray | float, t_reply2: NDArray | float
) -> NDArray:
    """Eq. 4 averaged over the two round trips of a double-sided exchange (poll, response, final),
    in the asymmetric form (R1 R2 - D1 D2) / (R1 + R2 + D1 + D2): independent of both clocks'
    rates to first order, whatever the two reply delays are (s)."""
    r1, d1, r2, d2 = (np.asarray(v, float) for v in (t_round1, t_reply1, t_round2, t_reply2))
    return (r1 * r2 - d1 * d2) / (r1 + r2 + d1 + d2)


def tof_to_range(tof: NDArray | float) -> NDArray:
    """Eq. 5: distance = c * time of flight (m)."""
    return SPEED_OF_LIGHT_MPS * np.asarray(tof, float)


def distance(p: NDArray, q: NDArray) -> NDArray:
    """Eq. 6: Euclidean distance between rows of ``p`` and ``q`` (2-D or 3-D)."""
    return np.linalg.norm(np.asarray(p, float) - np.asarray(q, float), axis=-1)


def anchor_height_offset(anchor: NDArray | tuple[float, ...], tag_height_m: float) -> float:
    """Vertical offset anchor - tag (m); 0 for a 2-D anchor (assumed at tag height)."""
    return float(anchor[2]) - tag_height_m if len(anchor) == 3 else 0.0


def horizontal_range(r: NDArray, dz: NDArray | float, sigma: NDArray | float) -> tuple[NDArray, NDArray]:
    """Planar distance sqrt(r^2 - dz^2) of measured 3-D ranges ``r`` with vertical offsets ``dz``,
    and its first-order std sigma * r / r_h. A range shorter than |dz| gives r_h = 0 (NaN std):
    the radio is right below the anchor, or the range is noise."""
    r = np.asarray(r, float)
    h2 = r**2 - np.asarray(dz, float) ** 2
    rh = np.sqrt(np.maximum(h2, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        sh = np.where(rh > 0, np.asarray(sigma, float) * r / rh, np.nan)
    return rh, sh


@dataclass(frozen=True)
class Trilateration:
    """A position from ranges to >= 3 anchors: ``xy`` (m), its first-order covariance (m^2),
    the RMS range residual (m) and the Gauss-Newton iterations used."""

    xy: NDArray[np.float64]
    cov: NDArray[np.float64]
    rms_m: float
    iterations: int
    ok: bool


def trilaterate(
    anchors: NDArray,
    ranges: NDArray,
    sigma_m: float,
    *,
    tag_height_m: float = 0.0,
    start: NDArray | None = None,
    iterations: int = 10,
) -> Trilateration:
    """Least-squares planar position from ranges to K >= 3 anchors ((K, 2) or (K, 3) positions).

    Start: the linear solution of |p - a_k|^2 = r_k^2 differenced against the first anchor
    (exact for exact ranges), or ``start``; then Gauss-Newton on the 3-D range model with
    the tag at ``tag_height_m``. ``ok`` is False with fewer than 3 anchors, collinear anchors or a
    diverged solve. This is the "doPositioning" of the paper's eq. 13.
    """
    a = np.asarray(anchors, float)
    r = np.asarray(ranges, float)
    k = len(a)
    dz = (a[:, 2] - tag_height_m) if a.shape[1] == 3 else np.zeros(k)
    axy = a[:, :2]
    bad = Trilateration(np.full(2, np.nan), np.full((2, 2), np.nan), float("nan"), 0, False)
    if k < 3:
        return bad
    rh2 = np.maximum(r**2 - dz**2, 0.0)
    if start is None:
        A = 2.0 * (axy[1:] - axy[0])
        b = rh2[0] - rh2[1:] + np.sum(axy[1:] ** 2, axis=1) - np.sum(axy[0] ** 2)
        if np.linalg.matrix_rank(A, tol=1e-6) < 2:
            return bad
        p = np.linalg.lstsq(A, b, rcond=None)[0]
    else:
        p = np.asarray(start, float).copy()
    J = np.zeros((k, 2))
    it = 0
    for it in range(1, iterations + 1):
        d = np.sqrt(np.sum((p - axy) ** 2, axis=1) + dz**2)
        J = (p - axy) / np.maximum(d, 1e-9)[:, None]
        res = r - d
        JtJ = J.T @ J
        if np.linalg.cond(JtJ) > 1e8:
            return bad
        step = np.linalg.solve(JtJ, J.T @ res)
        p = p + step
        if np.linalg.norm(step) < 1e-6:
            break
    d = np.sqrt(np.sum((p - axy) ** 2, axis=1) + dz**2)
    J = (p - axy) / np.maximum(d, 1e-9)[:, None]
    JtJ = J.T @ J
    if not np.isfinite(p).all() or np.linalg.cond(JtJ) > 1e8:
        return bad
    rms = float(np.sqrt(np.mean((r - d) ** 2)))
    return Trilateration(p, sigma_m**2 * np.linalg.inv(JtJ), rms, it, True)
