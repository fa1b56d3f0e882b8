"""The shot noise of a change tells charge from an offset of the read-out (detector.noise_law)."""

import numpy as np
import pytest

from detector.noise_law import noise_share
from detector.significance import law_verdict


def _frame(rng, charge: bool, misfit: float = 1.0, shape=(256, 256), gain=1.5, read_adu2=64.0, cosmics=0):
    """A dark frame of model variance ``read + dark / g`` [ADU^2] and a smooth change of 0-150 ADU (a gradient
    and a bump) that is charge (its Poisson variance added) or an offset (none); the residual holds
    ``misfit`` x the change (a form that fits it badly leaves a smooth structure in the residual)."""
    h, w = shape
    y, x = np.mgrid[0:h, 0:w] / np.array([h, w])[:, None, None]
    change = 100.0 * x + 50.0 * np.exp(-((x - 0.3) ** 2 + (y - 0.6) ** 2) / 0.02)
    dark = 40.0  # ADU of dark charge everywhere, in the model
    var = np.full(shape, read_adu2 + dark / gain)
    extra = change / gain if charge else 0.0
    data = rng.normal(0.0, np.sqrt(var + extra)) + misfit * change
    if cosmics:
        iy, ix = rng.integers(0, h, cosmics), rng.integers(0, w, cosmics)
        data[iy, ix] += 5000.0
    return data, var, change, 1.0 / gain


@pytest.mark.parametrize("charge", [True, False])
def test_the_share_is_one_for_charge_and_zero_for_an_offset(charge):
    rng = np.random.default_rng(3)
    r, v, d, p = _frame(rng, charge)
    s = noise_share(r, v, np.ones(r.shape, bool), d, p)
    assert abs(s.share - (1.0 if charge else 0.0)) < 4 * s.error
    assert s.error < 0.1 and s.pairs >= 0.999 * (r.size // 2)  # a few 5-sigma pairs left out as outliers
    # the verdict: an offset candidate on charge is refused, a charge candidate on an offset too
    assert law_verdict(s.share, s.error, own=0.0 if charge else 1.0, other=1.0 if charge else 0.0) is True


def test_a_smooth_misfit_and_outliers_do_not_move_it():
    """A fit that takes half of the change leaves it half in the residual: the pair differences cancel it. Cosmic
    rays (one pixel of 5000 ADU in 0.5 % of the pairs) are left out as outliers."""
    rng = np.random.default_rng(4)
    r, v, d, p = _frame(rng, charge=True, misfit=0.5, cosmics=300)
    s = noise_share(r, v, np.ones(r.shape, bool), d, p)
    assert abs(s.share - 1.0) < 4 * s.error and s.error < 0.1


def test_a_uniform_change_or_too_few_pixels_say_nothing():
    """A level changes the variance by a constant that a read noise off by as much would also give: not measured
    apart from the nuisances (None); nor on fewer than MIN_TEST_PIXELS pairs."""
    rng = np.random.default_rng(5)
    r, v, _, p = _frame(rng, charge=True)
    assert noise_share(r, v, np.ones(r.shape, bool), np.full(r.shape, 80.0), p) is None
    small = np.zeros(r.shape, bool)
    small[:4, :40] = True
    assert noise_share(r, v, small, r * 0 + np.arange(r.shape[1]), p) is None


def test_a_gain_or_read_noise_off_is_taken_by_the_nuisances():
    """The model's variance 20 % low everywhere and 30 ADU^2 of read noise short: the share of an offset stays 0."""
    rng = np.random.default_rng(6)
    r, v, d, p = _frame(rng, charge=False)
    s = noise_share(r, 0.8 * v - 30.0, np.ones(r.shape, bool), d, p)
    assert abs(s.share) < 4 * s.error


def test_law_verdict():
    assert law_verdict(0.9, 0.1, own=0.0, other=1.0) is True
    assert law_verdict(0.1, 0.1, own=0.0, other=1.0) is False  # 9 errors from 1: the offset's law
    assert law_verdict(0.5, 0.2, own=0.0, other=1.0) is None  # 2.5 errors from both: cannot tell
    assert law_verdict(float("nan"), 0.1, own=0.0, other=1.0) is None
