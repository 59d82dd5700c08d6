"""Access-point models from a radio map: position, P0 and gamma of the log-distance law.

For each AP heard by at least ``min_readings`` fingerprints of a radio map (positions in
the map's frame, m; RSS in dBm), fit::

    rss_i = P0 - 10 gamma log10(sqrt(|xy_i - a|^2 + d0^2))      (Paper 000 eq. 5)

over theta = (a_x, a_y, P0, gamma) by robust nonlinear least squares
(``scipy.optimize.least_squares``, soft-L1 loss, scale ``loss_scale_db``; analytic,
vectorised residuals and Jacobian). ``d0`` (``min_distance_m``) keeps the model finite at
the AP (a ceiling AP is never closer than ~1 m to a phone). Start: the weighted centroid
of the strongest readings, P0/gamma by linear regression from there. Uncertainty:
``s^2 (J^T J)^-1`` at the solution, with ``s^2`` the residual variance (n - 4 dof).

An AP is *not* fitted, with a reason, when: too few readings; the readings lie nearly on
a line (mirror ambiguity across it); the solver did not converge; the position ends on
its search bound (AP outside the surveyed area, unobservable); gamma at a bound or P0 at its
lower bound (implausible); or the position standard deviation is too large. P0 is bounded above
by what a phone 1 m from a physical AP can hear (``p0_bounds_dbm``: -10 dBm, above the ~-20 dBm of
a 20 dBm transmitter after 1 m of free space at 2.4 GHz): a fit there is kept, the law's P0
traded against gamma (walls' losses read as a steep law with an unphysically strong AP, e.g.
-1 dBm with gamma 5.5 on the simulator's floors). Weak readings are censored by the phone's
floor, which biases gamma slightly low: documented, not corrected.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, replace
from typing import Any, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from graphslam.core.progress import progress_over
from graphslam.core.tracking.filters import PathLossModel
from graphslam.core.tracking.rssi_field import FieldFit, fit_residual_field
from graphslam.core.radiomap.radiomap import RadioMap
from graphslam.errors import EstimationError

log = logging.getLogger(__name__)

AP_MODELS_FORMAT_VERSION = 1
_K = 10.0 / np.log(10.0)  # d(10 log10 u)/du * u


@dataclass(frozen=True)
class ApFitConfig:
    """Fit settings (m, dB)."""

    min_readings: int = 20
    min_spread_m: float = 1.5  # smallest std of the reading positions across their main axis
    min_distance_m: float = 1.0  # d0
    gamma_bounds: tuple[float, float] = (1.0, 6.0)
    # P0 (dBm at 1 m): a fit at the lower bound is rejected (implausible), one at the upper kept
    # there (no physical AP is heard stronger at 1 m; module docstring)
    p0_bounds_dbm: tuple[float, float] = (-90.0, -10.0)
    margin_m: float = 15.0  # the AP may lie this far outside the readings' bounding box
    loss_scale_db: float = 4.0  # soft-L1 scale: residuals beyond ~this are down-weighted
    strongest: int = 10  # readings in the starting centroid
    max_position_std_m: float = 10.0

    def __post_init__(self) -> None:
        if self.min_readings < 5 or self.min_distance_m <= 0 or self.loss_scale_db <= 0:
            raise EstimationError("AP fit: min_readings >= 5, min_distance_m > 0 and loss_scale_db > 0 required")
        if not (0 < self.gamma_bounds[0] < self.gamma_bounds[1] and self.p0_bounds_dbm[0] < self.p0_bounds_dbm[1]):
            raise EstimationError("AP fit: empty gamma or P0 bounds")


@dataclass(frozen=True)
class ApModel:
    """One fitted AP: position (map frame, m), P0 (dBm at 1 m), gamma, with 1-sigma errors."""

    bssid: str
    x: float
    y: float
    p0_dbm: float
    gamma: float
    sigma_db: float  # residual std (robust: 1.4826 MAD) of the readings around the model
    n_readings: int
    cov: tuple[tuple[float, ...], ...]  # 4x4 over (x, y, P0, gamma)

    @property
    def position_std_m(self) -> float:
        """sqrt of the larger eigenvalue of the position covariance."""
        return float(np.sqrt(max(np.linalg.eigvalsh(np.array(self.cov)[:2, :2]).max(), 0.0)))


@dataclass(frozen=True)
class UnfittedAp:
    bssid: str
    n_readings: int
    reason: str


@dataclass(frozen=True, eq=False)
class ApModels:
    """Fitted and unfitted APs of one radio map (same frame as the map)."""

    frame: str
    min_distance_m: float
    fitted: tuple[ApModel, ...]
    unfitted: tuple[UnfittedAp, ...]
    format_version: int = AP_MODELS_FORMAT_VERSION

    @classmethod
    def fit(cls, rm: RadioMap, cfg: ApFitConfig = ApFitConfig()) -> "ApModels":
        """Fit every AP of ``rm`` (see module docstring)."""
        v = rm.fingerprints.values.tocsc()
        fitted: list[ApModel] = []
        unfitted: list[UnfittedAp] = []
        for j, bssid in enumerate(progress_over(rm.bssids, "fit-aps", unit="APs")):
            rows = v.indices[v.indptr[j] : v.indptr[j + 1]]
            rss = v.data[v.indptr[j] : v.indptr[j + 1]] + rm.missing_dbm
            res = fit_ap(bssid, rm.xy[rows], rss, cfg)
            (fitted if isinstance(res, ApModel) else unfitted).append(res)
        log.info("AP models: %d fitted, %d not fitted", len(fitted), len(unfitted))
        return cls(rm.frame, cfg.min_distance_m, tuple(fitted), tuple(unfitted))

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "ApModels":
        if d.get("format_version") != AP_MODELS_FORMAT_VERSION:
            raise EstimationError(f"AP models: format version {d.get('format_version')!r} not supported")
        fitted = tuple(
            ApModel(**{**a, "cov": tuple(tuple(float(x) for x in r) for r in a["cov"])}) for a in d["fitted"]
        )
        return cls(str(d["frame"]), float(d["min_distance_m"]), fitted, tuple(UnfittedAp(**u) for u in d["unfitted"]))

    def as_dict(self) -> dict[str, Any]:
        return {
            "format_version": self.format_version,
            "model": "rss = p0_dbm - 10 gamma log10(sqrt(d^2 + min_distance_m^2))",
            "frame": self.frame,
            "min_distance_m": self.min_distance_m,
            "fitted": [asdict(a) for a in self.fitted],
            "unfitted": [asdict(u) for u in self.unfitted],
        }

    def path_loss(self) -> PathLossModel:
        """The fitted APs as the filters' measurement model."""
        if not self.fitted:
            raise EstimationError("AP models: no fitted access point")
        return PathLossModel(
            np.array([[a.x, a.y] for a in self.fitted]),
            np.array([a.p0_dbm for a in self.fitted]),
            np.array([a.gamma for a in self.fitted]),
            self.min_distance_m,
            tuple(a.bssid for a in self.fitted),
        )


def _model(theta: NDArray, xy: NDArray, d0: float) -> tuple[NDArray, NDArray]:
    """Mean RSS (n,) and Jacobian (n, 4) w.r.t. (a_x, a_y, P0, gamma)."""
    d = xy - theta[:2]
    u = np.einsum("nk,nk->n", d, d) + d0 * d0
    lg = np.log10(u)
    J = np.empty((len(xy), 4))
    J[:, :2] = (_K * theta[3] / u)[:, None] * d  # d/da of -5 gamma log10(u): +10 gamma d / (u ln10)
    J[:, 2] = 1.0
    J[:, 3] = -5.0 * lg
    return theta[2] - 5.0 * theta[3] * lg, J


def fit_ap(bssid: str, xy: NDArray, rss: NDArray, cfg: ApFitConfig = ApFitConfig()) -> ApModel | UnfittedAp:
    """Fit one AP from readings ``rss`` (n,) dBm at ``xy`` (n, 2) m; an ``UnfittedAp`` with a reason
    when it cannot be fitted (never raises for bad data)."""
    xy = np.asarray(xy, float).reshape(-1, 2)
    rss = np.asarray(rss, float).ravel()
    n = len(rss)
    if n < cfg.min_readings:
        return UnfittedAp(bssid, n, f"too few readings ({n} < {cfg.min_readings})")
    ev = np.linalg.eigvalsh(np.cov(xy.T))
    if np.sqrt(max(ev[0], 0.0)) < cfg.min_spread_m:
        return UnfittedAp(
            bssid, n, f"degenerate geometry: readings within {np.sqrt(max(ev[0], 0.0)):.2f} m of a line"
        )
    top = np.argsort(rss)[::-1][: cfg.strongest]
    w = 10.0 ** ((rss[top] - rss[top].max()) / 10.0)  # linear power: the strongest dominate
    a0 = (w[:, None] * xy[top]).sum(0) / w.sum()
    lo_xy, hi_xy = xy.min(0) - cfg.margin_m, xy.max(0) + cfg.margin_m
    g_lo, g_hi = cfg.gamma_bounds
    p_lo, p_hi = cfg.p0_bounds_dbm
    lg = np.log10(np.einsum("nk,nk->n", xy - a0, xy - a0) + cfg.min_distance_m**2)
    A = np.column_stack([np.ones(n), -5.0 * lg])
    p0, g = np.linalg.lstsq(A, rss, rcond=None)[0]
    theta0 = np.array([a0[0], a0[1], np.clip(p0, p_lo + 1, p_hi - 1), np.clip(g, g_lo + 0.1, g_hi - 0.1)])
    lo = np.array([lo_xy[0], lo_xy[1], p_lo, g_lo])
    hi = np.array([hi_xy[0], hi_xy[1], p_hi, g_hi])
    d0 = cfg.min_distance_m
    try:
        sol = least_squares(
            lambda t: _model(t, xy, d0)[0] - rss,
            theta0,
            jac=lambda t: _model(t, xy, d0)[1],
            bounds=(lo, hi),
            loss="soft_l1",
            f_scale=cfg.loss_scale_db,
            x_scale=np.array([5.0, 5.0, 5.0, 0.5]),
        )
    except (ValueError, np.linalg.LinAlgError) as e:  # pragma: no cover - scipy numerical failure
        return UnfittedAp(bssid, n, f"solver failed ({e})")
    if not sol.success:
        return UnfittedAp(bssid, n, f"not converged ({sol.message})")
    t = sol.x
    span = hi - lo
    at_bound = (np.abs(t - lo) < 1e-3 * span) | (np.abs(hi - t) < 1e-3 * span)
    if at_bound[:2].any():
        return UnfittedAp(bssid, n, "position at the search bound (AP outside the surveyed area?)")
    if at_bound[3]:
        return UnfittedAp(bssid, n, f"implausible gamma (at bound {t[3]:.2f})")
    if np.abs(t[2] - lo[2]) < 1e-3 * span[2]:
        return UnfittedAp(bssid, n, f"implausible P0 (at bound {t[2]:.1f} dBm)")
    r, J = _model(t, xy, d0)
    r = r - rss
    s2 = float(r @ r) / max(n - 4, 1)
    try:
        cov = s2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return UnfittedAp(bssid, n, "degenerate geometry: singular normal matrix")
    pos_std = float(np.sqrt(max(np.linalg.eigvalsh(cov[:2, :2]).max(), 0.0)))
    if not np.isfinite(pos_std) or pos_std > cfg.max_position_std_m:
        return UnfittedAp(bssid, n, f"position not identifiable (std {pos_std:.1f} m)")
    mad = 1.4826 * float(np.median(np.abs(r - np.median(r))))
    return ApModel(
        bssid, float(t[0]), float(t[1]), float(t[2]), float(t[3]), mad, n,
        tuple(tuple(float(x) for x in row) for row in cov),
    )


def ap_position_errors(models: ApModels, true_bssids: Sequence[str], true_xy: NDArray) -> NDArray[np.float64]:
    """Distances (m) between fitted and true AP positions, same frame (evaluation only)."""
    idx = {b: i for i, b in enumerate(true_bssids)}
    pairs = [(a, idx[a.bssid]) for a in models.fitted if a.bssid in idx]
    if not pairs:
        return np.zeros(0)
    est = np.array([[a.x, a.y] for a, _ in pairs])
    return np.linalg.norm(est - np.asarray(true_xy, float)[[i for _, i in pairs]], axis=1)


def residual_field(
    rm: RadioMap, pl: PathLossModel, *, bandwidth_m: float = 3.0, shrink: float = 0.5, cell_m: float = 1.0,
    leave_out: bool = True, aps: NDArray | None = None,
) -> FieldFit:
    """The residual field of ``pl``'s APs (``graphslam.core.tracking.rssi_field``) from ``rm``'s
    fingerprints, each map walk left out when the noise around it is measured (``leave_out``).
    ``aps``: only these AP indices get a correction (the others none)."""
    pl = replace(pl, correction=None)  # residuals around the law itself
    index = {b: i for i, b in enumerate(pl.bssids)}
    cols = np.array([index.get(b, -1) for b in rm.bssids], dtype=np.int64)
    v = rm.fingerprints.values.tocoo()
    a = cols[v.col]
    keep = a >= 0
    if aps is not None:
        keep &= np.isin(a, np.asarray(aps, np.int64))
    rows, a = v.row[keep], a[keep]
    rss = v.data[keep] + rm.missing_dbm
    h = pl.rss_mean(rm.xy[rows], a)
    return fit_residual_field(rm.xy[rows], rss - h, a, rm.session_ids[rows], len(pl), bandwidth_m=bandwidth_m,
                              shrink=shrink, cell_m=cell_m, leave_out=leave_out)
