"""How a change of the stars' images grows with their flux (detector.flux_law): a PSF's widening is the same at
every flux, brighter-fatter's grows with it (Antilogus et al. 2014)."""

import numpy as np
import pytest
from helpers import gaussian_stars as _stars

from detector.flux_law import Slope, flux_law, flux_slope, source_amplitudes


FLUXES = np.geomspace(2e4, 4e5, 12)


def _amplitudes(residual, change, noise=3.0, seed=1):
    src = _stars(1.5, FLUXES)
    rng = np.random.default_rng(seed)
    r = residual + rng.normal(0, noise, residual.shape)
    return source_amplitudes(src, np.full(src.shape, noise), np.ones(src.shape, bool), r, change)


def test_a_wider_psf_keeps_one_amplitude_at_every_flux():
    change = _stars(1.8, FLUXES) - _stars(1.5, FLUXES)  # the scene's PSF widened by 20 %
    flux, amp, err = _amplitudes(change, change)
    assert flux.size == FLUXES.size
    np.testing.assert_allclose(np.sort(flux) / FLUXES, 1, atol=0.02)  # the footprints hold the stars' light
    s = flux_slope(flux, amp, err)
    assert abs(s.power) < 3 * s.error + 0.02
    assert flux_law(s, own=0.0, other=1.0) is False  # the PSF's own law


def test_a_widening_that_grows_with_flux_follows_the_other_law():
    # the same widening in proportion to each star's flux (brighter-fatter to first order: F^2 x a shape)
    psf_change = _stars(1.8, FLUXES) - _stars(1.5, FLUXES)
    truth = np.zeros((120, 160))
    for i, f in enumerate(FLUXES):
        solo = np.zeros(FLUXES.size)
        solo[i] = f
        truth += (_stars(1.8, solo) - _stars(1.5, solo)) * (f / FLUXES[0])
    flux, amp, err = _amplitudes(truth, psf_change)
    s = flux_slope(flux, amp, err)
    assert s.power == pytest.approx(1.0, abs=0.05)
    assert flux_law(s, own=0.0, other=1.0) is True


def test_too_few_sources_or_too_narrow_a_flux_range_cannot_tell():
    # two sources: a line through them has no degree of freedom left to measure their scatter about it
    assert flux_slope(np.array([1e4, 5e4]), np.ones(2), np.full(2, 0.01)) is None
    # three sources have one: with 1 % amplitudes over a factor 5 in flux they tell the laws 0 and 1 apart, and
    # a scatter about the line beyond their errors inflates the slope's error until they cannot
    three = flux_slope(np.array([1e4, 2e4, 5e4]), np.ones(3), np.full(3, 0.01))
    assert three.n == 3 and flux_law(three, 0.0, 1.0) is False
    scattered = flux_slope(np.array([1e4, 2e4, 5e4]), np.array([1.0, 1.6, 1.0]), np.full(3, 0.01))
    assert flux_law(scattered, 0.0, 1.0) is None
    # a narrow range of fluxes (a factor 2) is no bar of its own: the slope's standard error, 1 / sqrt(sum w
    # (ln F - mean)^2), says whether it tells the laws 0 and 1 apart (amplitude ratios 1 and 2 across it)
    narrow = np.linspace(1e4, 2e4, 8)
    precise = flux_slope(narrow, np.ones(8), np.full(8, 0.01))  # 1 % amplitudes: 0.016 on the slope
    assert precise.error == pytest.approx(0.01 / np.sqrt(np.sum((np.log(narrow) - np.log(narrow).mean()) ** 2)))
    assert flux_law(precise, 0.0, 1.0) is False
    rough = flux_slope(narrow, np.ones(8), np.full(8, 0.15))  # 15 % amplitudes: 0.24 on the slope
    assert rough.error > 0.2 and flux_law(rough, 0.0, 1.0) is None  # 1 lies within 5 errors of the power 0
    assert flux_law(Slope(0.9, 0.3, 8, 10.0), 0.0, 1.0) is None  # 0.9 excludes 0 by 3 errors only
    assert flux_law(Slope(0.9, 0.05, 8, 10.0), 0.0, 1.0) is True


def test_a_power_far_from_both_laws_excludes_the_one_it_is_five_errors_from():
    """The test is of a law, not of the two laws' distance: 2.1 +- 0.4 (a few sources over a narrow range of
    flux) cannot tell 0 from 1 by their gap (2.5 errors) yet excludes 0 at 5.3 errors and lies nearer 1."""
    assert flux_law(Slope(2.1, 0.4, 12, 3.5), own=0.0, other=1.0) is True
    assert flux_law(Slope(-1.1, 0.2, 12, 3.5), own=0.0, other=1.0) is False  # excludes 1 (10.5 errors), nearer 0
    assert flux_law(Slope(-0.9, 0.4, 12, 3.5), own=0.0, other=1.0) is None  # 1 only 4.75 errors away
    assert flux_law(Slope(float("nan"), 0.1, 12, 3.5), 0.0, 1.0) is None
    assert flux_law(Slope(0.9, float("inf"), 12, 3.5), 0.0, 1.0) is None
    assert flux_law(None, 0.0, 1.0) is None


def test_a_saturated_source_is_left_out():
    src = _stars(1.5, FLUXES)
    sat = np.zeros(src.shape, bool)
    sat[20, 20] = True  # the first star's peak
    flux, _, _ = source_amplitudes(src, np.full(src.shape, 3.0), np.ones(src.shape, bool), src * 0, src, sat)
    assert flux.size == FLUXES.size - 1 and not np.any(np.isclose(flux, FLUXES[0], rtol=0.05))



def test_a_brightness_error_is_no_part_of_the_amplitude_with_the_sources_own_scale():
    # brighter-fatter (F^2 x a shape) on every star, under a light level 5 % too high on all of them (what one
    # bright star's own brighter-fatter did to the fitted global level): F x PSF left on each star as well
    psf = _stars(1.5, FLUXES)
    bf = np.zeros(psf.shape)
    for i, f in enumerate(FLUXES):
        solo = np.zeros(FLUXES.size)
        solo[i] = f
        bf += (_stars(1.8, solo) - _stars(1.5, solo)) * (f / FLUXES[0])
    noise = np.full(psf.shape, 3.0)
    r = 0.05 * bf - 0.05 * psf + np.random.default_rng(2).normal(0, 3.0, psf.shape)
    use = np.ones(psf.shape, bool)
    # the brighter-fatter template's own law is power 0; the level's share pulls it towards the PSF's (-1)
    pulled = flux_slope(*source_amplitudes(psf, noise, use, r, bf))
    own = flux_slope(*source_amplitudes(psf, noise, use, r, bf, own_scale=True))
    assert pulled.power < -5 * pulled.error
    assert abs(own.power) < 3 * own.error + 0.02
