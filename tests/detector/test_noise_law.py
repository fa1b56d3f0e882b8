"""The shot noise of a change tells charge from an offset of the read-out (detector.noise_law)."""

import numpy as np
import pytest

from detector.noise_law import NoiseShare, noise_law, noise_share
from detector.significance import law_verdict

GAIN = 1.5  # e-/ADU


def _change(shape, amplitude=100.0):
    """A smooth change [ADU]: a gradient across the columns and a bump."""
    h, w = shape
    y, x = np.mgrid[0:h, 0:w] / np.array([h, w])[:, None, None]
    return amplitude * (x + 0.5 * np.exp(-((x - 0.3) ** 2 + (y - 0.6) ** 2) / 0.02))


def _frame(rng, change, charge: bool, left=0.0, read_adu2=64.0, cosmics=0, column_sigma=0.0):
    """(residual once the candidate's change is taken off, model variance) of a dark frame of model variance
    ``read + dark / g`` [ADU^2] holding ``change`` as charge (its Poisson variance added) or as an offset (none);
    ``left``: the share of the change a form that fits it badly leaves in the residual; ``cosmics``: hits of 5000
    ADU; ``column_sigma``: a fixed column pattern the model lacks [ADU]."""
    dark = 40.0  # ADU of dark charge everywhere, in the model
    var = np.full(change.shape, read_adu2 + dark / GAIN)
    extra = change / GAIN if charge else 0.0
    r = rng.normal(0.0, np.sqrt(var + extra)) + left * change
    if column_sigma:
        r += rng.normal(0.0, column_sigma, change.shape[1])[None, :]
    if cosmics:
        iy, ix = rng.integers(0, change.shape[0], cosmics), rng.integers(0, change.shape[1], cosmics)
        r[iy, ix] += 5000.0
    return r, var


@pytest.mark.parametrize("charge", [True, False])
@pytest.mark.parametrize("amplitude", [100.0, 3000.0, 1e4])
def test_the_share_is_one_for_charge_and_zero_for_an_offset(charge, amplitude):
    """Also where the change's shot noise is many times the model's (a 1e4 ADU glow on a 90 ADU^2 dark): its pairs
    are judged against the noise the charge reading gives them, not cut as outliers of the model's."""
    rng = np.random.default_rng(3)
    d = _change((256, 256), amplitude)
    r, v = _frame(rng, d, charge)
    s = noise_share(r, v, np.ones(r.shape, bool), d, 1.0 / GAIN)
    assert abs(s.share - (1.0 if charge else 0.0)) < 4 * s.error
    assert s.error < 0.1 and s.pairs >= 0.999 * (r.size // 2)  # a few 5-sigma pairs left out as outliers
    # the verdict: an offset candidate on charge is refused, a charge candidate on an offset too
    assert noise_law(s, own=0.0 if charge else 1.0, other=1.0 if charge else 0.0) is True


def test_a_smooth_misfit_and_outliers_do_not_move_it():
    """A fit that takes half of the change leaves the other half in the residual: the pair differences cancel it.
    Cosmic rays (one pixel of 5000 ADU in 0.9 % of the pairs) are left out as outliers."""
    rng = np.random.default_rng(4)
    d = _change((256, 256))
    r, v = _frame(rng, d, charge=True, left=0.5, cosmics=300)
    s = noise_share(r, v, np.ones(r.shape, bool), d, 1.0 / GAIN)
    assert abs(s.share - 1.0) < 4 * s.error and s.error < 0.1


@pytest.mark.parametrize("pattern", ["parity", "cosine8"])
def test_an_offset_with_pixel_scale_structure_is_an_offset(pattern):
    """An offset whose pixel-to-pixel steps follow its own amplitude (even and odd columns apart by a growing
    amount; a cosine of 8 px period): its steps would read as its shot noise in the pair differences of the data;
    taken off with the fitted change, the offset carries none."""
    rng = np.random.default_rng(7)
    h, w = 256, 256
    xx = np.broadcast_to(np.arange(w, dtype=float), (h, w))
    d = (40.0 * xx / w * (xx % 2)) if pattern == "parity" else 20.0 * (1 + np.cos(2 * np.pi * xx / 8.0))
    r, v = _frame(rng, d, charge=False)
    s = noise_share(r, v, np.ones(r.shape, bool), d, 1.0 / GAIN)
    assert noise_law(s, own=0.0, other=1.0) is not True


def test_a_column_pattern_the_model_lacks_gives_no_verdict():
    """A fixed column pattern of 10 ADU (the pixel noise 9.5 ADU) repeats down the rows: the pairs of a column are
    not independent, and the jackknife over blocks of columns widens the error so that no law is claimed."""
    claimed = 0
    for seed in range(6):
        rng = np.random.default_rng(100 + seed)
        d = _change((256, 256), 30.0)
        r, v = _frame(rng, d, charge=False, column_sigma=10.0)
        s = noise_share(r, v, np.ones(r.shape, bool), d, 1.0 / GAIN)
        claimed += noise_law(s, own=0.0, other=1.0) is True
    assert claimed == 0


def test_a_uniform_change_or_too_few_pixels_say_nothing():
    """A level changes the variance by a constant that a read noise off by as much would also give: not measured
    apart from the nuisances (None); nor on fewer than MIN_TEST_PIXELS pairs."""
    rng = np.random.default_rng(5)
    d = _change((256, 256))
    r, v = _frame(rng, d, charge=True)
    assert noise_share(r, v, np.ones(r.shape, bool), np.full(r.shape, 80.0), 1.0 / GAIN) is None
    small = np.zeros(r.shape, bool)
    small[:4, :40] = True
    assert noise_share(r, v, small, d, 1.0 / GAIN) is None


def test_a_gain_or_read_noise_off_is_taken_by_the_nuisances():
    """The model's variance 20 % low everywhere and 30 ADU^2 of read noise short: the share of an offset stays 0."""
    rng = np.random.default_rng(6)
    d = _change((256, 256))
    r, v = _frame(rng, d, charge=False)
    s = noise_share(r, 0.8 * v - 30.0, np.ones(r.shape, bool), d, 1.0 / GAIN)
    assert abs(s.share) < 4 * s.error


def test_the_laws():
    assert law_verdict(0.9, 0.1, own=0.0, other=1.0) is True
    assert law_verdict(0.1, 0.1, own=0.0, other=1.0) is False  # 9 errors from 1: the offset's law
    assert law_verdict(0.5, 0.2, own=0.0, other=1.0) is None  # 2.5 errors from both: cannot tell
    assert law_verdict(float("nan"), 0.1, own=0.0, other=1.0) is None
    # the noise law also asks the share to agree with the law it names: 2.6 +- 0.1 is neither charge nor offset
    assert noise_law(NoiseShare(0.88, 0.09, 1000), own=0.0, other=1.0) is True
    assert noise_law(NoiseShare(2.6, 0.1, 1000), own=0.0, other=1.0) is None
    assert noise_law(NoiseShare(0.21, 0.006, 1000), own=1.0, other=0.0) is None
    assert noise_law(None, own=1.0, other=0.0) is None
