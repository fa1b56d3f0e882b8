"""RTS on one frame: a sparse, symmetric mixture of steps +-A on the Gaussian read noise (Kirton & Uren 1989;
Wang et al. 2006), and the variance laws that tell a DSNU from an extra read noise (Janesick 2007, ch. 7).

The mixture likelihood must recover a planted fraction and amplitude, claim nothing on pure noise, and not be
credited with a population of steps up alone (hot pixels) nor with a white excess of every pixel.
"""

from __future__ import annotations

import numpy as np
import pytest

from detector.effects.rts import RTSNoise, rts_frame_fit, rts_population, rts_tail_sample
from detector.sensor import make_sensor
from tests.helpers import residuals_of

N_PX = 200_000


def _planted(rng, f, a_sigma, s_ln, signs=(-1, 1)):
    r = rng.standard_normal(N_PX)
    hit = rng.random(N_PX) < f
    amp = a_sigma * np.exp(s_ln * rng.standard_normal(hit.sum()))
    r[hit] += amp * rng.choice(signs, hit.sum())
    return rts_tail_sample(r, np.ones(N_PX))


def test_mixture_recovers_a_planted_fraction_and_amplitude():
    """0.2 % of the pixels stepped by +-8 sigma (log-normal spread 0.4): f and the median amplitude come back
    within their sampling errors and the grid's steps (400 steps: f to 5 %; amplitudes 1.37 apart; the steps
    of a few sigma are lost in the noise)."""
    r, v, wt = _planted(np.random.default_rng(1), 2e-3, 8.0, 0.4)
    out = rts_frame_fit(r, v, wt)
    assert abs(out["f"] / 2e-3 - 1) < 0.15
    assert abs(np.log(out["a_adu"] / 8.0)) < np.log(1.4)
    assert out["delta"] + 3 * np.log(N_PX) < -1000  # 400 steps of ~8 sigma: far beyond the Schwarz price


def test_mixture_claims_nothing_on_gaussian_noise():
    """Pure N(0, v): the gain of the three RTS parameters stays below their Schwarz price."""
    r, v, wt = _planted(np.random.default_rng(2), 0.0, 8.0, 0.4)
    out = rts_frame_fit(r, v, wt)
    assert out["delta"] + 3 * np.log(N_PX) > 10


def test_steps_up_alone_are_not_rts():
    """Hot pixels (0.2 % of the pixels, +8 sigma only): the pixels below the model hold nothing, so RTS is credited
    with nothing (its steps up are not credited beyond their mirror below)."""
    r, v, wt = _planted(np.random.default_rng(3), 2e-3, 8.0, 0.4, signs=(1,))
    out = rts_frame_fit(r, v, wt)
    assert out["delta"] + 3 * np.log(N_PX) > 10


def test_white_excess_is_not_rts_on_a_frame():
    """A read noise 30 % above the model's on every pixel widens the core; the frame likelihood measures that
    width robustly, so the RTS candidate is not significant -- while planted steps on top of it still are."""
    s = make_sensor("ml11002", {"width": 256, "height": 256})
    rng = np.random.default_rng(4)
    shape = (256, 256)
    model = np.full(shape, 1000.0)
    var = np.full(shape, 50.0)
    data = model + 1.3 * np.sqrt(var) * rng.standard_normal(shape)
    res = residuals_of(data, model, var, np.zeros(shape), s)
    fit = RTSNoise.signature.fit(res, "rts_noise")
    assert fit is None or fit.delta_bic > 0
    hit = rng.random(shape) < 1e-3
    data2 = data + np.where(hit, 30 * np.sqrt(50.0) * rng.choice([-1, 1], shape), 0.0)
    fit2 = RTSNoise.signature.fit(residuals_of(data2, model, var, np.zeros(shape), s), "rts_noise")
    assert fit2 is not None and fit2.delta_bic < -100


def test_one_frame_measures_fraction_times_step_probability_per_sensor_pixel():
    """The same per-frame step fraction on a frame binned b x b (b^2 sensor pixels per output pixel) is a b^2 times
    smaller trap fraction; a fraction beyond the default time constants' reach is given with fast traps instead."""
    f1, f2 = rts_population(1e-4, 1)["fraction"], rts_population(1e-4, 2)["fraction"]
    assert abs(f2 / f1 - 0.25) < 0.01
    fast = rts_population(3e-3, 1)
    assert fast["fraction"] <= 0.1 and fast["tau_max_s"] < 1e-3


def test_dsnu_and_read_noise_follow_their_variance_laws():
    """DSNU is a spread of the dark rate: its variance grows as (dark signal)^2 (Janesick 2007, ch. 7; EMVA 1288),
    a reset or read noise is the same at any dark signal. Where the dark signal varies over the frame (here x1 to
    x4 across the columns) each fit prefers its own law; where it is uniform the two are the same model and their
    likelihoods agree (the data cannot tell them apart)."""
    from detector.effects import registry

    s = make_sensor("ml11002", {"width": 256, "height": 256})
    g = s.gain_e_per_adu
    rng = np.random.default_rng(5)
    shape = (256, 256)
    dsnu, ktc = registry()["dsnu"].signature, registry()["reset_noise"].signature

    def deltas(dark_e, extra_sd_adu):
        model = np.full(shape, 1000.0) + dark_e / g
        var = np.full(shape, 30.0) + dark_e / g ** 2
        data = model + np.sqrt(var) * rng.standard_normal(shape) + extra_sd_adu * rng.standard_normal(shape)
        res = residuals_of(data, model, var, np.zeros(shape), s)
        res.dark_e = dark_e.astype(np.float32)
        return dsnu.fit(res, "dsnu").delta_bic, ktc.fit(res, "reset_noise").delta_bic

    ramp = np.broadcast_to(np.linspace(50.0, 200.0, shape[1]), shape)
    d, k = deltas(ramp, 0.3 * ramp / g)  # DSNU of 30 %: its scatter follows the dark map
    assert d < k - 10
    d, k = deltas(ramp, np.full(shape, 0.3 * 125.0 / g))  # the same mean excess, uniform: a read noise
    assert k < d - 10
    flat = np.full(shape, 125.0)
    d, k = deltas(flat, np.full(shape, 0.3 * 125.0 / g))
    assert abs(d - k) < 2 * np.log(res_n := shape[0] * shape[1]) and res_n > 0


def test_isolated_steps_are_rts_of_a_cmos_pixel_not_of_a_ccd():
    """RTS pixels are the in-pixel source followers of a CMOS sensor (Wang et al. 2006); a CCD reads every pixel
    through one amplifier, so the same steps on a CCD frame are not named RTS."""
    rng = np.random.default_rng(6)
    shape = (256, 256)
    model, var = np.full(shape, 1000.0), np.full(shape, 20.0)
    hit = rng.random(shape) < 2e-3
    data = model + np.sqrt(var) * rng.standard_normal(shape) + np.where(hit, 40.0 * rng.choice([-1, 1], shape), 0.0)
    for camera, ok in (("imx411", True), ("ml11002", False)):
        res = residuals_of(data, model, var, np.zeros(shape), make_sensor(camera, {"width": 256, "height": 256}))
        fit = RTSNoise.signature.fit(res, "rts_noise")
        assert fit.delta_bic < -100
        assert (RTSNoise.signature.plausible(fit, res) == "") == ok


@pytest.mark.parametrize("offset", [0.0, 0.3, 0.5])
def test_read_codes_below_the_noise_of_a_code_are_not_steps(offset):
    """A 16 x 16 average-binned dark: the noise (0.2 ADU) is below one ADC code and the read values sit on integer
    codes about a model mean ``offset`` above a code (the same everywhere on a uniform dark). A density takes the lattice of codes for +-1 ADU steps in a few per
    cent of the pixels; the likelihood of each code does not (nothing significant), and still finds steps of
    8 codes in 0.2 % of the pixels."""
    s = make_sensor("imx411", {"width": 256, "height": 256})
    rng = np.random.default_rng(7)
    shape = (256, 256)
    model = np.full(shape, 500.0 + offset)
    var = np.full(shape, 0.04)
    data = np.round(model + np.sqrt(var) * rng.standard_normal(shape))
    fit = RTSNoise.signature.fit(residuals_of(data, model, var, np.zeros(shape), s), "rts_noise")
    assert fit is None or fit.delta_bic > 0
    hit = rng.random(shape) < 2e-3
    stepped = data + np.where(hit, 8.0 * rng.choice([-1, 1], shape), 0.0)
    fit = RTSNoise.signature.fit(residuals_of(stepped, model, var, np.zeros(shape), s), "rts_noise")
    assert fit is not None and fit.delta_bic < -100

