"""The magnetic map: the building's field at located places, beside the radio map.

One row per step of the main map's walks that carries ``/phone/magnetic``: the step's position (the
map's frame, metres) and the direction-free features of the field there (µT): its magnitude |B|, its
horizontal magnitude |B_h| and its vertical component B_up (Earth frame; negative where the field
points down). Each walk's device and calibration offset, estimated where the magnetic links say two
walks stood at one place, is removed (``offsets``), so that walks agree where they overlap; a walk no
link ties keeps its own level (offset 0). What a positioning on the field would search: a sequence
of a query walk's features along its path, matched against the map's sequences (not built yet).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Mapping

import numpy as np
from numpy.typing import NDArray

from graphslam.core.types import frozen_array
from graphslam.errors import RadioMapError

MAGNETIC_MAP_FORMAT_VERSION = 1
FEATURES = ("magnitude_ut", "horizontal_ut", "vertical_ut")


@dataclass(frozen=True, eq=False)
class MagneticMap:
    """N located field samples (see the module docstring)."""

    session_ids: NDArray[np.str_]  # (N,)
    t_ns: NDArray[np.int64]  # (N,) the step's time
    xy: NDArray[np.float64]  # (N, 2) metres, in ``frame``
    features: NDArray[np.float64]  # (N, 3) |B|, |B_h|, B_up (µT), each walk's offset removed
    frame: str
    offsets: Mapping[str, tuple[float, float, float]] = field(default_factory=dict)  # walk -> removed (µT)
    metadata: Mapping[str, Any] = field(default_factory=dict)
    format_version: int = MAGNETIC_MAP_FORMAT_VERSION

    def __post_init__(self) -> None:
        n = len(np.asarray(self.t_ns))
        ids = np.array([str(s) for s in np.asarray(self.session_ids, dtype=object).ravel()], dtype=str)
        if n == 0:
            ids = np.zeros(0, dtype="<U1")
        xy = frozen_array(np.reshape(self.xy, (-1, 2)), np.float64)
        f = frozen_array(np.reshape(self.features, (-1, 3)), np.float64)
        if not (len(ids) == n == len(xy) == len(f)):
            raise RadioMapError(f"magnetic map: {len(ids)} ids, {n} times, {len(xy)} positions, {len(f)} features")
        if not (np.isfinite(xy).all() and np.isfinite(f).all()):
            raise RadioMapError("magnetic map: non-finite position or field")
        if not self.frame:
            raise RadioMapError("magnetic map: no frame name")
        ids.setflags(write=False)
        object.__setattr__(self, "session_ids", ids)
        object.__setattr__(self, "t_ns", frozen_array(self.t_ns, np.int64))
        object.__setattr__(self, "xy", xy)
        object.__setattr__(self, "features", f)
        offsets = {str(k): tuple(float(x) for x in v) for k, v in dict(self.offsets).items()}
        if not all(len(v) == 3 and np.isfinite(v).all() for v in offsets.values()):
            raise RadioMapError("magnetic map: an offset must be three finite numbers")
        object.__setattr__(self, "offsets", MappingProxyType(offsets))
        try:
            meta = json.loads(json.dumps(dict(self.metadata), sort_keys=True, allow_nan=False))
        except (TypeError, ValueError) as e:
            raise RadioMapError(f"magnetic map: metadata is not JSON-serialisable ({e})") from None
        object.__setattr__(self, "metadata", MappingProxyType(meta))

    def __len__(self) -> int:
        return len(self.t_ns)

    @property
    def n_walks(self) -> int:
        return len(np.unique(self.session_ids))
