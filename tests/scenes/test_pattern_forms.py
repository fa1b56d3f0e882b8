"""The forms of the pixel patterns (issue 23, random forms): a PRNU's low-frequency part is a smooth flat-field
map, predicted on pixels its fit did not see (the held-out folds compare it with the residual's own
empirical map); the added scatter's uniformity across the frame is measured on read codes dithered over their
code (a median of squares of integer values snaps between lattice points).

Physics asserted: a response map of coating and thickness variations multiplies the light at every scale
(Janesick 2007, Photon Transfer, ch. 8); a dithered quantizer's output is continuous (Widrow & Kollar 2008)."""

from __future__ import annotations

import numpy as np
from helpers import small_sensor

from detector.effects.pixel_response import _DSNU_SIGNATURE, _PRNU_SIGNATURE
from detector.signatures import Residuals, SpikeStats, heldout_delta
from scenes.app.compare.catch_all import catch_all_heldout
from scenes.app.compare.policy import DEFAULT_POLICY

SHAPE = (192, 192)


def _flat(sensor, truth_rel, rng, light_adu=8000.0):
    h, w = SHAPE
    photo = np.full(SHAPE, light_adu, np.float32)
    var = (photo / sensor.gain_e_per_adu + (4.0 / sensor.gain_e_per_adu) ** 2).astype(np.float32)
    data = (photo * (1 + truth_rel) + sensor.bias_adu + rng.normal(0, 1, SHAPE) * np.sqrt(var)).astype(np.float32)
    none = SpikeStats(0, 0, 0, 0, 0)
    return Residuals(data, (photo + sensor.bias_adu).astype(np.float32), var, np.ones(SHAPE, bool), photo,
                     np.zeros(SHAPE, np.float32), np.arange(h, dtype=float) + 0.5, np.arange(w, dtype=float) + 0.5,
                     sensor, 10.0, none, none, light_source="flat")


def test_a_prnu_low_frequency_map_is_predicted_on_unseen_pixels():
    """White PRNU 1 % and a smooth response map of 1 % rms with up to 2 cycles across the frame (the cosine
    basis holds 2.5): the PRNU's held-out score carries the map (at least the policy's share of what the
    residual's empirical map predicts on the same folds)."""
    s = small_sensor(width=SHAPE[1], height=SHAPE[0])
    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[0:SHAPE[0], 0:SHAPE[1]] / SHAPE[0]
    lf = sum(np.cos(2 * np.pi * (kx * xx + ky * yy) + ph) for kx, ky, ph in
             zip(rng.uniform(-2, 2, 12), rng.uniform(-2, 2, 12), rng.uniform(0, 2 * np.pi, 12)))
    lf = 0.01 * lf / lf.std()
    res = _flat(s, 0.01 * rng.standard_normal(SHAPE) + lf, rng)
    fit = _PRNU_SIGNATURE.fit(res, "prnu")
    assert fit is not None and fit.delta_adu is not None and "low-frequency" in fit.note
    # the map it predicts is the response map's (correlation with the truth's low-frequency part)
    assert np.corrcoef(fit.delta_adu.ravel(), lf.ravel())[0, 1] > 0.9
    held = heldout_delta(_PRNU_SIGNATURE, res, "prnu")
    ca = catch_all_heldout(res)
    assert ca is not None and ca < 0
    assert held <= DEFAULT_POLICY.min_catch_all_share * ca, (held, ca)


def test_a_uniform_extra_scatter_on_read_codes_is_uniform_across_the_frame():
    """A uniform dark (every pixel the same dark signal, 0.4 ADU off a code) with a DSNU of 1.5 x the dark on
    integer read codes whose noise spans a few codes (2.5 e- read noise at 1 e-/ADU): the cells' excess variances
    agree within their errors once the codes are dithered (undithered, the median of squares snaps between
    lattice points and the excess "varies across the frame", chi2 far above its dof)."""
    s = small_sensor(width=256, height=256, read_noise_e=2.5, gain_e_per_adu=1.0)
    shape = (256, 256)
    dark_e, v = 1.0, 2.5 ** 2
    extra = (1.5 * dark_e) ** 2
    model = np.full(shape, s.bias_adu + dark_e + 0.4, np.float32)
    none = SpikeStats(0, 0, 0, 0, 0)
    for seed in (0, 1):
        rng = np.random.default_rng(seed)
        data = np.round(model + rng.normal(0, np.sqrt(v + extra), shape)).astype(np.float32)
        res = Residuals(data, model, np.full(shape, v, np.float32), np.ones(shape, bool), np.zeros(shape, np.float32),
                        np.full(shape, dark_e, np.float32), np.arange(256.0) + 0.5, np.arange(256.0) + 0.5, s, 10.0,
                        none, none, light_source="none")
        fit = _DSNU_SIGNATURE.fit(res, "dsnu")
        assert fit is not None and fit.params["sigma"] > 1.0
        assert _DSNU_SIGNATURE.uniformity(fit, res) == ""
