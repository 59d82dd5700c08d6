import numpy as np
import pytest

from graphslam.core.common.arrays import nonzero_2d


@pytest.mark.parametrize("shape", [(7, 13), (1, 40), (40, 1), (0, 5), (5, 0), (3, 3)])
def test_nonzero_2d_is_numpys_row_major_nonzero(shape: tuple[int, int]) -> None:
    rng = np.random.default_rng(sum(shape))
    for frac in (0.0, 0.2, 1.0):
        mask = rng.random(shape) < frac
        want = np.nonzero(mask)
        got = nonzero_2d(mask)
        for g, w in zip(got, want):
            np.testing.assert_array_equal(g, w)
            assert g.dtype == w.dtype
