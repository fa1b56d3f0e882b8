"""psf_elongation's lopsided form (a one-sided exponential tail of the PSF: coma): the rendered profile against
the analytic exponentially modified Gaussian, its cumulants against the mixture's, the linearised start and
the plausibility bounds."""

from types import SimpleNamespace

import numpy as np
import pytest
from scipy import special

from detector.effects import image_plane as ip
from detector.signatures import Fit


def _gauss(n, c, sigma):
    yy, xx = np.mgrid[0:n, 0:n].astype(float)
    return np.exp(-0.5 * ((xx - c) ** 2 + (yy - c) ** 2) / sigma ** 2) / (2 * np.pi * sigma ** 2), xx - c, yy - c


@pytest.mark.parametrize("length,frac,angle", [(1.5, 0.4, 20.0), (3.0, 0.2, -130.0), (0.7, 0.6, 90.0)])
def test_the_tail_adds_the_cumulants_of_a_point_plus_an_exponential(length, frac, angle):
    """Cumulants of a convolution add: a Gaussian (sigma 2 px, band-limited on the grid to 3e-9) gains along
    the tail k1 = f L, k2 = f L^2 (2 - f), k3 = 2 f L^3 (3 - 3 f + f^2) (raw moments of the mixture f L,
    2 f L^2, 6 f L^3), and nothing across; the flux is kept."""
    sigma = 2.0
    g, x, y = _gauss(129, 64.0, sigma)
    out = ip.one_sided_tail(g, length, frac, angle)
    u = np.radians(angle)
    s, t = x * np.cos(u) + y * np.sin(u), -x * np.sin(u) + y * np.cos(u)
    flux = out.sum()
    m1 = (out * s).sum() / flux
    k2 = (out * (s - m1) ** 2).sum() / flux - sigma ** 2
    k3 = (out * (s - m1) ** 3).sum() / flux
    e1, e2, e3 = ip.tail_cumulants(length, frac)
    assert flux == pytest.approx(1.0, abs=1e-8)
    assert (m1, k2, k3) == pytest.approx((e1, e2, e3), rel=1e-5)
    # by hand, the same analytic values (the function is not tested against itself)
    assert e1 == pytest.approx(frac * length) and e3 == pytest.approx(
        6 * frac * length ** 3 - 3 * (2 * frac * length ** 2) * (frac * length) + 2 * (frac * length) ** 3)
    mt = (out * t).sum() / flux
    assert abs(mt) < 1e-8 and abs((out * (t - mt) ** 3).sum() / flux) < 1e-5
    assert (out * (t - mt) ** 2).sum() / flux == pytest.approx(sigma ** 2, rel=1e-6)


@pytest.mark.parametrize("angle", [0.0, 33.0])
def test_the_tail_profile_is_the_exponentially_modified_gaussian(angle):
    """A Gaussian star with a one-sided exponential tail is, along the tail, ``(1 - f) N(s; sigma) + f
    EMG(s; sigma, L)``, the exponentially modified Gaussian ``EMG = 1 / (2 L) exp(sigma^2 / (2 L^2) - s / L)
    erfc((sigma^2 / L - s) / (sqrt(2) sigma))`` (Grushka 1972, Anal. Chem. 44, 1733), and the Gaussian across
    it: evaluated in closed form at the pixel centres, no Fourier transform."""
    sigma, length, frac = 2.0, 2.5, 0.35
    g, x, y = _gauss(129, 64.0, sigma)
    out = ip.one_sided_tail(g, length, frac, angle)
    u = np.radians(angle)
    s, t = x * np.cos(u) + y * np.sin(u), -x * np.sin(u) + y * np.cos(u)
    across = np.exp(-0.5 * t ** 2 / sigma ** 2) / (np.sqrt(2 * np.pi) * sigma)
    core = np.exp(-0.5 * s ** 2 / sigma ** 2) / (np.sqrt(2 * np.pi) * sigma)
    emg = (0.5 / length * np.exp(sigma ** 2 / (2 * length ** 2) - s / length)
           * special.erfc((sigma ** 2 / length - s) / (np.sqrt(2) * sigma)))
    ref = across * ((1 - frac) * core + frac * emg)
    assert np.max(np.abs(out - ref)) < 1e-6 * ref.max()
    # lopsided: the peak stays on the source (the apex), the light goes one way
    assert np.unravel_index(np.argmax(out), out.shape) == (64, 64)


def _res_of(photo, binning=1):
    """The parts of a Residuals the PSF width and the check read."""
    return SimpleNamespace(photo_adu=photo.astype(np.float32), _flat={}, sensor=SimpleNamespace(binning=binning))


def test_the_psf_width_from_the_derivatives_is_the_fwhm_of_a_sampled_gaussian():
    """sum |grad I|^2 / sum (lap I)^2 = sigma^2 / 2 for a Gaussian: a well sampled star field's FWHM within
    10 % (pixel differences err wide), whatever the stars' brightness."""
    img = np.zeros((200, 200))
    rng = np.random.default_rng(1)
    for _ in range(12):
        g, _, _ = _gauss(200, 100.0, 2.5)
        img += rng.uniform(1e3, 1e5) * np.roll(g, rng.integers(-80, 80, 2), axis=(0, 1))
    fwhm = ip.psf_fwhm_px(_res_of(img + 300.0))
    assert fwhm == pytest.approx(2.3548 * 2.5, rel=0.1)


@pytest.mark.parametrize("params,bad", [
    ({"tail_px": 2.0, "tail_frac": 0.4, "tail_angle_deg": 20.0}, ""),
    ({"tail_px": 2.0, "tail_frac": 0.75, "tail_angle_deg": 20.0}, "more tail than core"),
    ({"tail_px": 25.0, "tail_frac": 0.3, "tail_angle_deg": 20.0}, "times the PSF's FWHM"),
])
def test_a_tail_that_no_psf_has_is_not_plausible(params, bad, monkeypatch):
    g, _, _ = _gauss(101, 50.0, 1.5)  # FWHM 3.5 px: a tail of 2 px is a coma, 25 px a trail
    fit = Fit("psf_elongation", {"dcxx_px2": 0.0, "dcyy_px2": 0.0, "dcxy_px2": 0.0, **params}, -1e4, 3, 10000, "")
    why = ip._elongation_check(fit, _res_of(1e5 * g))
    assert (bad in why) if bad else why == ""
    # the symmetric form is not judged by the tail's bounds, but by the nested test against the smear (the
    # jitter's Gaussian form, its minor eigenvalue held at 0): one parameter freed, bar 1 + 8 sqrt(2) = 12.3
    sym = Fit("psf_elongation", {"dcxx_px2": 1.0, "dcyy_px2": -0.5, "dcxy_px2": 0.0}, -1e4, 3, 10000, "")
    for smear_m2lnl, refused in ((-9000.0, False), (-1e4 + 10.0, True)):
        smear = Fit("jitter", {}, smear_m2lnl, 3, 10000, "")
        monkeypatch.setattr(ip.Jitter.signature, "form_fit", lambda res, name, sub, smear=smear: smear)
        assert ("narrowing across is within the noise" in ip._elongation_check(sym, _res_of(1e5 * g))) == refused


def test_the_effect_renders_the_tail_and_zero_share_is_identity():
    """The registered adapter applies the tail (first cumulant moves by f L along the angle); tail_frac 0 with
    the covariance 0 leaves the image untouched."""
    from detector.effects.base import registry

    cls = registry()["psf_elongation"]
    g, x, y = _gauss(101, 50.0, 2.0)
    data = (1e4 * g).astype(np.float32)
    eff = cls.__new__(cls)
    eff.params = cls.Params(tail_px=1.5, tail_frac=0.4, tail_angle_deg=-60.0)
    out = data.copy()
    eff.apply(None, None, out)
    mx, my = (out * x).sum() / out.sum(), (out * y).sum() / out.sum()
    assert (mx, my) == pytest.approx((0.6 * np.cos(np.radians(-60)), 0.6 * np.sin(np.radians(-60))), abs=1e-4)
    eff.params = cls.Params(tail_px=1.5, tail_frac=0.0)
    same = data.copy()
    eff.apply(None, None, same)
    assert np.array_equal(same, data)


@pytest.mark.parametrize("frac,sigma_h,dx,dy", [(0.2, 3.0, 1.5, 2.5), (0.5, 1.0, -3.0, 0.0)])
def test_the_displaced_halo_moves_the_moments_of_a_point_plus_a_gaussian(frac, sigma_h, dx, dy):
    """psf_elongation's displaced halo (the flare of a fast lens off its axis): a Gaussian source (sigma 2 px)
    keeps its flux; its centroid moves by f d and its variance along each axis grows by f sigma_h^2 +
    f (1 - f) d^2 (the mixture of a point of weight 1 - f and a Gaussian of mean d, variance sigma_h^2), as the
    effect renders it."""
    sigma = 2.0
    g, x, y = _gauss(129, 64.0, sigma)
    eff = ip.PSFElongation(ip.ElongationParams(halo_frac=frac, halo_sigma_px=sigma_h, halo_dx_px=dx, halo_dy_px=dy), None)
    transfer, pad = ip.displaced_halo_transfer(frac, sigma_h, dx, dy)
    out = ip.fourier_filter(g, pad, transfer)
    flux = out.sum()
    mx, my = (out * x).sum() / flux, (out * y).sum() / flux
    vx = (out * (x - mx) ** 2).sum() / flux - sigma ** 2
    vy = (out * (y - my) ** 2).sum() / flux - sigma ** 2
    assert flux == pytest.approx(1.0, abs=1e-8)
    assert (mx, my) == pytest.approx((frac * dx, frac * dy), abs=1e-6)
    assert vx == pytest.approx(frac * sigma_h ** 2 + frac * (1 - frac) * dx ** 2, abs=1e-5)
    assert vy == pytest.approx(frac * sigma_h ** 2 + frac * (1 - frac) * dy ** 2, abs=1e-5)
    # the effect applies the same filter
    data = g.astype(np.float64).copy()
    eff.apply(None, None, data)
    assert np.allclose(data, out, atol=1e-12)
