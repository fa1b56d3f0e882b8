"""The shared robust statistics (detector.stats) against their reference implementations."""

import numpy as np
import pytest
from scipy import ndimage

from detector.stats import median3x3


@pytest.mark.parametrize("shape", [(1, 1), (1, 9), (9, 1), (2, 2), (5, 7), (64, 33), (301, 300)])
def test_the_3x3_median_network_is_scipys_median_filter(shape):
    """The same values as ``ndimage.median_filter(size=3, mode="nearest")``: normal noise (float32), values with
    many ties (a few integer codes, float64) and a frame with spikes and a dead column, edges included."""
    rng = np.random.default_rng(sum(shape))
    cases = [rng.normal(size=shape).astype(np.float32),
             rng.integers(0, 3, size=shape).astype(np.float64),
             np.round(2 * rng.normal(size=shape)).astype(np.float32)]
    spiky = rng.normal(size=shape)
    spiky.flat[rng.integers(0, spiky.size, size=max(1, spiky.size // 50))] = 1e4
    spiky[:, shape[1] // 2] = -50.0
    cases.append(spiky)
    for img in cases:
        want = ndimage.median_filter(img, size=3, mode="nearest")
        got = median3x3(img)
        assert got.dtype == want.dtype and got.shape == want.shape
        assert np.array_equal(got, want)
