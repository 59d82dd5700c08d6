"""UWB ranges in the survey graph: arrays in, native GTSAM factors out (no Python in the loop).

Ranges are attached to step poses with the stride model (``motion``): a range taken at time t
during the stride from step k to k+1 belongs to pose X(k), with the antenna at the body-frame
offset o = R(-h_k) (p(t) - p_k) that the dead reckoning measured for that fraction of the stride.

- **anchor range**: ``RangeFactorWithTransform2D(X(k), L(a), r_h, noise, Pose2(o, 0))``: the
  planar distance from X(k) (+) o to anchor a. The anchor is a ``Point2`` variable L(a) held at
  its surveyed position by a ``PriorFactorPoint2`` of ``anchor_prior_sigma_m`` (the anchors fix
  the site frame; no reference-pose prior). r_h = sqrt(r^2 - dz^2) with dz the anchor's height
  above the tag, sigma_h = sigma r / r_h.
- **peer range** (two walkers at the same instant): ``RangeFactorWithTransformPose2(X(k_a),
  X(k_b), r, noise, Pose2(o_a, 0))``: from walker A's antenna to walker B's pose. GTSAM's factor
  moves one end only, so B's end is a step pose: the walker that was nearer (by its own dead
  reckoning, within ``peer_max_offset_m``) to one of its step poses at t takes that end;
  the range noise adds the remaining offset in quadrature.
- **robust loss** (``loss``, ``loss_k`` in sigmas): Cauchy by default. An NLOS range is longer
  than the truth by 0.3-2 m, i.e. 3-20 sigma; GTSAM's error is h(x) - z, so such ranges give
  large negative errors. ``AsymmetricCauchy`` would fit the physics but is robust on the
  positive side (z too short), the wrong one for this factor's sign, so the loss is symmetric.

Keys: ``X(i)`` step poses (global numbering, as ``graphslam.core.survey.align``), ``L(a)`` anchors.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from graphslam.config import UwbConfig

if TYPE_CHECKING:  # gtsam is imported where a factor is built: a WiFi-only survey never loads it
    import gtsam


def X(j: int) -> int:
    """Key of pose ``x_j``: GTSAM's ``symbol_shorthand.X`` (character in the top 8 bits, index below)."""
    return (ord("x") << 56) | int(j)


def L(j: int) -> int:
    """Key of anchor ``l_j``: GTSAM's ``symbol_shorthand.L``."""
    return (ord("l") << 56) | int(j)


@dataclass(frozen=True, eq=False)
class SurveyRanges:
    """Ranges attached to step nodes (global node ids). Offsets are body-frame (m)."""

    anchor_ids: tuple[str, ...]
    anchor_xy: NDArray[np.float64]  # (A, 2) site frame
    a_node: NDArray[np.int64]  # (Ma,)
    a_anchor: NDArray[np.int64]  # (Ma,) index into anchor_ids
    a_range: NDArray[np.float64]  # (Ma,) planar range (m)
    a_sigma: NDArray[np.float64]  # (Ma,)
    a_offset: NDArray[np.float64]  # (Ma, 2)
    p_node: NDArray[np.int64]  # (Mp, 2): the transformed end first
    p_range: NDArray[np.float64]  # (Mp,)
    p_sigma: NDArray[np.float64]  # (Mp,)
    p_offset: NDArray[np.float64]  # (Mp, 2) offset at the first end
    dropped: dict[str, int] = field(default_factory=dict)

    @property
    def nodes(self) -> NDArray[np.int64]:
        return np.unique(np.concatenate([self.a_node, self.p_node.ravel()]))

    def select(self, keep_node: NDArray[np.bool_]) -> "SurveyRanges":
        """Only the ranges whose nodes are all in ``keep_node`` (N,) (walks in the graph)."""
        ka = keep_node[self.a_node]
        kp = keep_node[self.p_node].all(axis=1) if len(self.p_node) else np.zeros(0, bool)
        return self.subset(ka, kp)

    def subset(self, ka: NDArray[np.bool_], kp: NDArray[np.bool_]) -> "SurveyRanges":
        """The anchor ranges ``ka`` and peer ranges ``kp`` (boolean masks)."""
        return SurveyRanges(
            self.anchor_ids, self.anchor_xy, self.a_node[ka], self.a_anchor[ka], self.a_range[ka], self.a_sigma[ka],
            self.a_offset[ka], self.p_node[kp], self.p_range[kp], self.p_sigma[kp], self.p_offset[kp], dict(self.dropped),
        )


def range_noise(sigma: float, cfg: UwbConfig) -> gtsam.noiseModel.Base:
    """Isotropic 1-D noise of std ``sigma`` under the configured robust loss (threshold k sigma)."""
    import gtsam

    est = gtsam.noiseModel.mEstimator
    loss = est.Cauchy.Create(cfg.loss_k) if cfg.loss == "cauchy" else est.Huber.Create(cfg.loss_k)
    return gtsam.noiseModel.Robust.Create(loss, gtsam.noiseModel.Isotropic.Sigma(1, float(sigma)))


def anchor_prior_noise(cfg: UwbConfig) -> gtsam.noiseModel.Base:
    import gtsam

    return gtsam.noiseModel.Isotropic.Sigma(2, cfg.anchor_prior_sigma_m)


def anchor_range_factor(node: int, anchor: int, r: float, sigma: float, offset: NDArray, cfg: UwbConfig) -> gtsam.NonlinearFactor:
    import gtsam

    return gtsam.RangeFactorWithTransform2D(
        X(node), L(anchor), float(r), range_noise(sigma, cfg), gtsam.Pose2(float(offset[0]), float(offset[1]), 0.0)
    )


def peer_range_factor(node_a: int, node_b: int, r: float, sigma: float, offset_a: NDArray, cfg: UwbConfig) -> gtsam.NonlinearFactor:
    import gtsam

    return gtsam.RangeFactorWithTransformPose2(
        X(node_a), X(node_b), float(r), range_noise(sigma, cfg),
        gtsam.Pose2(float(offset_a[0]), float(offset_a[1]), 0.0),
    )


def range_factors(sr: SurveyRanges, cfg: UwbConfig, *, with_anchors: bool = True) -> list[gtsam.NonlinearFactor]:
    """Every range factor of ``sr`` (anchor ones only ``with_anchors``) plus one prior per used anchor."""
    import gtsam

    out: list[gtsam.NonlinearFactor] = []
    if with_anchors:
        for a in np.unique(sr.a_anchor).tolist():
            out.append(gtsam.PriorFactorPoint2(L(a), sr.anchor_xy[a], anchor_prior_noise(cfg)))
        for n, a, r, s, o in zip(sr.a_node.tolist(), sr.a_anchor.tolist(), sr.a_range, sr.a_sigma, sr.a_offset):
            out.append(anchor_range_factor(n, a, r, s, o, cfg))
    for (na, nb), r, s, o in zip(sr.p_node.tolist(), sr.p_range, sr.p_sigma, sr.p_offset):
        out.append(peer_range_factor(na, nb, r, s, o, cfg))
    return out


def anchor_values(sr: SurveyRanges) -> gtsam.Values:
    """Initial values of the anchors that have ranges (their surveyed positions)."""
    import gtsam

    v = gtsam.Values()
    for a in np.unique(sr.a_anchor).tolist():
        v.insert(L(a), np.asarray(sr.anchor_xy[a], float))
    return v


def range_residuals(sr: SurveyRanges, xyh: NDArray) -> tuple[NDArray, NDArray]:
    """z - h(x) of every anchor and peer range at node poses ``xyh`` (N, 3), vectorised: positive
    means measured longer than the poses say (what an NLOS range does)."""

    def antenna(node: NDArray, off: NDArray) -> NDArray:
        th = xyh[node, 2]
        c, s = np.cos(th), np.sin(th)
        return xyh[node, :2] + np.column_stack([c * off[:, 0] - s * off[:, 1], s * off[:, 0] + c * off[:, 1]])

    ea = sr.a_range - np.linalg.norm(antenna(sr.a_node, sr.a_offset) - sr.anchor_xy[sr.a_anchor], axis=1)
    ep = sr.p_range - np.linalg.norm(antenna(sr.p_node[:, 0], sr.p_offset) - xyh[sr.p_node[:, 1], :2], axis=1)
    return ea, ep
