"""Array helpers the hot paths share."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def nonzero_2d(mask: NDArray[np.bool_]) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """``np.nonzero`` of a 2-D mask (row-major: rows ascending, columns ascending within a row), from
    the flat indices. Why: numpy's 2-D ``nonzero`` costs 7-14x as much (a 600 x 24k block with 0.1 %
    set: 24 ms against 1.8 ms), and the survey's top-k and threshold passes call it per block."""
    flat = np.flatnonzero(mask)
    return np.divmod(flat, mask.shape[1]) if mask.shape[1] else (flat, flat)
