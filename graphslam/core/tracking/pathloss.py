"""The log-distance path-loss law of the RSSI measurement (Papers 000 and 002, eq. 5-6), per access
point, in the frame of the AP models / radio map (metres, dBm)::

    y_i = P0_i - 10 gamma_i log10(sqrt(|p - a_i|^2 + d0^2))

``d0`` (``min_distance_m``) keeps the model finite and smooth at the AP. A residual field
(``graphslam.core.tracking.rssi_field``) may add what the law misses to its mean.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from graphslam.core.tracking.rssi_field import FieldRows, ResidualField
from graphslam.errors import EstimationError as FilterError


def _ro(a: NDArray | Sequence[float], dtype: type = np.float64) -> NDArray:
    arr: NDArray = np.array(a, dtype=dtype, copy=True)
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class PathLossModel:
    """Log-distance path loss (eq. 5) of A access points, map frame (m, dBm)."""

    ap_xy: NDArray[np.float64]  # (A, 2) m
    p0_dbm: NDArray[np.float64]  # (A,) RSS at 1 m
    gamma: NDArray[np.float64]  # (A,) path-loss exponent
    min_distance_m: float = 0.1  # d0 in sqrt(d^2 + d0^2)
    bssids: tuple[str, ...] = ()
    # what the law misses, per AP, added to its mean RSS (``graphslam.core.tracking.rssi_field``; None: the
    # law alone). ``jacobian`` / ``rss_pairs``' gradient stay the law's: the field's own gradient is noise
    correction: ResidualField | None = None

    def __post_init__(self) -> None:
        xy = np.asarray(self.ap_xy, float).reshape(-1, 2)
        a = len(xy)
        p0, g = np.asarray(self.p0_dbm, float).ravel(), np.asarray(self.gamma, float).ravel()
        if p0.shape != (a,) or g.shape != (a,):
            raise FilterError(f"path-loss model: {a} APs but {p0.size} P0 and {g.size} gamma values")
        if not (np.isfinite(xy).all() and np.isfinite(p0).all() and np.isfinite(g).all()):
            raise FilterError("path-loss model: non-finite parameter")
        if self.min_distance_m <= 0:
            raise FilterError("path-loss model: min_distance_m must be > 0")
        if self.bssids and len(self.bssids) != a:
            raise FilterError("path-loss model: one BSSID per AP expected")
        if self.correction is not None and len(self.correction) != a:
            raise FilterError(f"path-loss model: {a} APs but a residual field of {len(self.correction)}")
        object.__setattr__(self, "ap_xy", _ro(xy))
        object.__setattr__(self, "p0_dbm", _ro(p0))
        object.__setattr__(self, "gamma", _ro(g))
        object.__setattr__(self, "bssids", tuple(self.bssids))

    @classmethod
    def paper_ekf(cls) -> "PathLossModel":
        """Paper 000, sec. IV: 4 APs at the corners of 8.2 m x 14.6 m; P0 = -24/-33 dBm, gamma = 2.5."""
        return cls(_PAPER_APS, np.array([-24.0, -33.0, -33.0, -24.0]), np.full(4, 2.5))

    @classmethod
    def paper_ukf(cls) -> "PathLossModel":
        """Paper 002, sec. IV: same APs, P0 = -25 dBm, gamma = 2.5 for all."""
        return cls(_PAPER_APS, np.full(4, -25.0), np.full(4, 2.5))

    def __len__(self) -> int:
        return len(self.ap_xy)

    def mean_rss(self, xy: NDArray, idx: NDArray | None = None) -> NDArray[np.float64]:
        """(..., a) mean RSS (dBm) at positions ``xy`` (..., 2) of the APs ``idx`` (default all)."""
        idx = np.arange(len(self)) if idx is None else np.asarray(idx, dtype=np.int64)
        d = np.asarray(xy, float)[..., None, :] - self.ap_xy[idx]
        d2 = np.einsum("...k,...k->...", d, d) + self.min_distance_m**2
        out = self.p0_dbm[idx] - 5.0 * self.gamma[idx] * np.log10(d2)  # 10 log10(sqrt(.)) = 5 log10(.)
        if self.correction is not None:
            p = np.broadcast_to(np.asarray(xy, float)[..., None, :], d.shape).reshape(-1, 2)
            out = out + self.correction.at(p, np.broadcast_to(idx, d.shape[:-1]).ravel()).reshape(out.shape)
        return out

    def jacobian(self, xy: NDArray, idx: NDArray | None = None) -> NDArray[np.float64]:
        """(a, 2) d mean_rss / d (x, y) at one position."""
        idx = np.arange(len(self)) if idx is None else np.asarray(idx, dtype=np.int64)
        d = np.asarray(xy, float).reshape(1, 2) - self.ap_xy[idx]
        d2 = np.einsum("ak,ak->a", d, d) + self.min_distance_m**2
        return -(10.0 / np.log(10.0)) * self.gamma[idx, None] * d / d2[:, None]  # the law's alone (``correction``)

    def rss_pairs(self, xy: NDArray, idx: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Mean RSS (m,) of AP ``idx[j]`` at position ``xy[j]`` (m, 2), and the law's (m, 2) gradient
        in (x, y): ``mean_rss`` / ``jacobian`` for many (position, AP) pairs at once."""
        return self.rss_mean(xy, idx), self.rss_gradient(xy, idx)

    def rss_mean(self, xy: NDArray, idx: NDArray) -> NDArray[np.float64]:
        """``rss_pairs``' mean alone (m,) dBm: what a residual needs, without the gradient."""
        xy = np.asarray(xy, float).reshape(-1, 2)
        return self.rows(idx).mean(xy[:, 0], xy[:, 1])

    def rss_gradient(self, xy: NDArray, idx: NDArray) -> NDArray[np.float64]:
        """``rss_pairs``' gradient alone (m, 2), dB/m: what a Jacobian needs, without the mean."""
        xy = np.asarray(xy, float).reshape(-1, 2)
        return np.stack(self.rows(idx).gradient(xy[:, 0], xy[:, 1]), axis=1)

    def rows(self, idx: NDArray) -> "PathLossRows":
        """The law (and field) of AP ``idx[j]`` per reading ``j``, gathered once for many positions."""
        idx = np.asarray(idx, dtype=np.int64).ravel()
        g = self.gamma[idx]
        return PathLossRows(
            self.ap_xy[idx, 0], self.ap_xy[idx, 1], self.p0_dbm[idx], (5.0 / np.log(10.0)) * g, -(10.0 / np.log(10.0)) * g,
            self.min_distance_m**2, None if self.correction is None else self.correction.rows(idx),
        )


@dataclass(frozen=True, eq=False)
class PathLossRows:
    """``PathLossModel.rows``: per reading its AP's position (m), P0, 5 gamma / ln 10 and -10 gamma / ln 10
    (the law's factors), the field; positions ``x``, ``y`` of shape (..., m) give (..., m) means and gradients."""

    ap_x: NDArray[np.float64]
    ap_y: NDArray[np.float64]
    p0_dbm: NDArray[np.float64]
    gamma5_ln: NDArray[np.float64]
    slope: NDArray[np.float64]
    d0_sq: float
    field: "FieldRows | None"

    def mean(self, x: NDArray, y: NDArray) -> NDArray[np.float64]:
        """Mean RSS (dBm): the law plus the field."""
        dx, dy = x - self.ap_x, y - self.ap_y
        h = self.p0_dbm - self.gamma5_ln * np.log(dx * dx + dy * dy + self.d0_sq)  # 10 log10(sqrt(.)) = 5 ln(.) / ln 10
        return h + self.field.at(x, y) if self.field is not None else h

    def gradient(self, x: NDArray, y: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The law's d mean / d x and d mean / d y (dB/m; the field's gradient is noise, ``correction``)."""
        dx, dy = x - self.ap_x, y - self.ap_y
        f = self.slope / (dx * dx + dy * dy + self.d0_sq)
        return f * dx, f * dy

    def take(self, rows: slice | NDArray) -> "PathLossRows":
        """The law (and field) of these readings only."""
        return PathLossRows(self.ap_x[rows], self.ap_y[rows], self.p0_dbm[rows], self.gamma5_ln[rows], self.slope[rows],
                            self.d0_sq, None if self.field is None else self.field.take(rows))


_PAPER_APS = np.array([[0.0, 0.0], [0.0, 14.6], [8.2, 14.6], [8.2, 0.0]])


__all__ = ["PathLossModel", "PathLossRows"]
