"""The survey's problem: everything the optimiser needs, as arrays (``Problem``), built by
``graphslam.core.survey.align.build_problem`` and turned into a factor graph by
``graphslam.core.survey.graph``.

Frames and units: poses ``(x, y, heading)`` in metres and radians, in the frame of the walk placed
first (or the site frame of the control points / UWB anchors).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Mapping

import numpy as np
from numpy.typing import NDArray

from graphslam.core.survey.association import FingerprintNodes
from graphslam.core.survey.components import Component
from graphslam.core.survey.control import ControlTies
from graphslam.core.survey.edges import WifiEdges
from graphslam.core.survey.heading_split import HeadingTerms
from graphslam.core.survey.initialise import Placement
from graphslam.core.survey.magnetic import MagneticLinks
from graphslam.core.types import Survey

if TYPE_CHECKING:
    from graphslam.core.radiomap.radiomap import RadioMap
    from graphslam.core.survey.reference import FieldTies
    from graphslam.core.uwb.survey import UwbTerms


@dataclass(frozen=True, eq=False)
class Problem:
    """Everything the optimiser needs, as arrays: built once, solvable by any back end.

    Node ``n`` is step ``n - offsets[s]`` of session ``s`` (global numbering).
    """

    survey: Survey
    fingerprints: FingerprintNodes
    edges: WifiEdges
    reference: int  # session index
    included: NDArray[np.bool_]  # (S,) walks in the graph
    unaligned: dict[str, str]
    placement: Placement | None
    init_xyh: NDArray[np.float64]  # (N, 3), NaN for walks not in the graph
    imu_pairs: NDArray[np.int64]  # (M, 2) consecutive nodes of included walks
    imu_u: NDArray[np.float64]  # (M, 3) measured body-frame step (eq. 6)
    wifi_pairs: NDArray[np.int64]  # (E, 2) nodes of WiFi edges between included walks
    timings_s: dict[str, float]
    # (P, 2) step nodes a magnetic link says are one place (graphslam.core.survey.magnetic), within a component
    magnetic_pairs: NDArray[np.int64] = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    magnetic: MagneticLinks | None = None  # the links behind them
    # a reference map (graphslam.core.survey.reference): its fingerprints' site positions, held, and the
    # WiFi edges (crowd node, reference fingerprint) of component 0's walks
    anchor_xy: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 2)))
    anchor_pairs: NDArray[np.int64] = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    reference_map: RadioMap | None = None  # the reference map itself (its fingerprints join the output map)
    # the reference's field (graphslam.core.survey.reference.field_ties): magnetic factors (crowd step node,
    # row of anchor_xy: the field's samples follow the reference's fingerprints there)
    field_pairs: NDArray[np.int64] = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    field_ties: FieldTies | None = None
    # the tied component's WiFi edges (and reference edges) the placement put beyond the tight gate
    # (``control_points.wifi_gate_m``) but within the headings' one: they join when a solve brings them within it
    gated_wifi_pairs: NDArray[np.int64] = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    gated_anchor_pairs: NDArray[np.int64] = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    unused_reference: RadioMap | None = None  # a reference map given that no walk registers onto (not used)
    # --update: nodes re-solved; the others keep init_xyh (their previous solution).
    # None: every node of an included walk is a variable (a full solve).
    free: NDArray[np.bool_] | None = None
    uwb: UwbTerms | None = None  # UWB range factors and placement
    method: str = "registration"  # the initialization used (``initialization``)
    component: NDArray[np.int64] | None = None  # (S,) component of each included walk (None: all in 0)
    components: tuple[Component, ...] = ()
    fixed_nodes: NDArray[np.int64] | None = None  # nodes held (one per component); None: the reference node
    heading: HeadingTerms | None = None
    ties: ControlTies | None = None  # control points: position priors (component 0 in the site frame)
    frame_name: str = "aligned"
    site_from_earth: float | None = None  # rad: the site frame's rotation from east/north (headings + ties/reference)
    control_digest: str = ""  # of the control points given (``incremental.control_points_digest``)
    control_points: Mapping[str, tuple[float, float]] = field(default_factory=dict)

    @property
    def reference_node(self) -> int:
        return int(self.fingerprints.offsets[self.reference])

    @property
    def held_nodes(self) -> NDArray[np.int64]:
        """Nodes held at their initial pose: one per component (the reference node by default)."""
        if self.fixed_nodes is not None:
            return self.fixed_nodes
        return np.array([self.reference_node], np.int64)
