"""The bias pattern along the serial direction (bias_gradient's ``column_profile_adu``, issue 10).

A fixed bias structure of any smooth shape along the columns is fitted on unlit frames as a cosine series
whose order is chosen by BIC. Checked against independent results: the Fourier series of a sawtooth (the
share of its power a truncated series keeps is analytic), a frame with ramps only keeps the ramps (BIC), and
a lit frame is not offered the profile (a light's pattern along the columns could take it).
"""

from __future__ import annotations

import numpy as np
import pytest

from detector import Detector
from detector.effects import registry
from detector.effects.base import build_effects
from detector.effects.readout import bias_profile_adu
from detector.sensor import make_sensor
from detector.signatures import Residuals, SpikeStats


def test_the_profile_is_the_cosine_series():
    xs = np.arange(101, dtype=float)
    got = bias_profile_adu(xs, 101, [0.0, 2.0, 0.0, -1.0])
    t = xs / 100
    assert np.allclose(got, 2 * np.cos(2 * np.pi * t) - np.cos(4 * np.pi * t), atol=1e-5)


def test_the_effect_adds_the_profile_along_the_columns():
    """A noiseless bias frame of the effect: every row is the cosine series of its columns (plus the bias)."""
    s = make_sensor("ml11002", {"read_noise_e": 0.0, "dark_current_e_per_s": 0.0, "height": 40})
    det = Detector(s, build_effects({"bias_gradient": {"gradient_x_adu": 0.0, "column_profile_adu": [6.0, 3.0]}}, s))
    f = det.expose(0.0, 0.0, 1).astype(float)
    want = bias_profile_adu(np.arange(s.sensor_width_px, dtype=float), s.sensor_width_px, [6.0, 3.0])
    col = f.mean(axis=0) - f.mean()
    assert np.abs(col - (want - want.mean())).max() < 0.6  # quantisation of single rows averaged over 40
    assert np.ptp(f, axis=0).max() <= 1  # the same in every row (up to the ADU rounding)


def _bias_frame(offset_row, seed=3, read_adu=10.0, lit=False):
    """A 334 x 501 bias frame of the whole ML11002 binned 8 (sensor columns at the binned pixels' centres) with
    ``offset_row`` [ADU] added along the columns, against a flat model."""
    rng = np.random.default_rng(seed)
    s = make_sensor("ml11002", {"binning": 8})
    h, w = s.output_shape
    ys = np.arange(h) * 8 + 3.5
    xs = np.arange(w) * 8 + 3.5
    model = np.full((h, w), 1000.0)
    photo = np.full((h, w), 500.0 if lit else 0.0)
    var = np.full((h, w), read_adu ** 2) + photo
    data = model + photo + offset_row(xs)[None, :] + rng.normal(0, 1, (h, w)) * np.sqrt(var)
    return Residuals(data.astype(np.float32), (model + photo).astype(np.float32), var.astype(np.float32),
                     np.ones((h, w), bool), photo.astype(np.float32), np.zeros((h, w), np.float32), ys, xs, s,
                     0.0, SpikeStats(0, 0, 0, 0, 0), SpikeStats(0, 0, 0, 0, 0))


def _sawtooth(cycles, ptp, width):
    return lambda xs: ptp * ((cycles * xs / (width - 1) + 0.3) % 1.0 - 0.5)


def test_a_sawtooth_bias_is_fitted_as_a_profile_keeping_what_its_fourier_series_predicts():
    """A 3-cycle sawtooth of 3 ADU peak to peak: the fitted profile's order is one that reaches its harmonics
    (3 cycles: cos(k pi t) with k = 6, 12, 18, ...), and the fit takes the share of the sawtooth's power that
    its harmonics up to that order carry (sum_{n <= N} 1/n^2 / (pi^2 / 6), Fourier series of a sawtooth),
    within the noise."""
    s = make_sensor("ml11002", {"binning": 8})
    saw = _sawtooth(3.0, 3.0, s.sensor_width_px)
    res = _bias_frame(saw)
    sig = registry()["bias_gradient"].signature
    fit = sig.fit(res, "bias_gradient")
    prof = fit.params.get("column_profile_adu") or []
    assert len(prof) >= 16 and fit.delta_bic < -100
    n_harm = len(prof) // 6
    share = sum(1 / n ** 2 for n in range(1, n_harm + 1)) / (np.pi ** 2 / 6)
    truth = saw(res.xs)
    delta = np.asarray(fit.delta_adu)[0]
    kept = 1 - np.var(truth - delta) / np.var(truth)
    assert kept == pytest.approx(share, abs=0.06)
    assert sig.plausible(fit, res) == ""


def test_ramps_alone_keep_the_simple_form():
    """A linear ramp only: the larger variants fit no better than their BIC cost, the ramps are kept."""
    s = make_sensor("ml11002", {"binning": 8})
    res = _bias_frame(lambda xs: 4.0 * (xs / (s.sensor_width_px - 1) - 0.5))
    fit = registry()["bias_gradient"].signature.fit(res, "bias_gradient")
    assert not fit.params.get("column_profile_adu")
    assert fit.params["gradient_x_adu"] == pytest.approx(4.0, abs=0.3)


def test_a_lit_frame_is_not_offered_the_profile():
    s = make_sensor("ml11002", {"binning": 8})
    res = _bias_frame(_sawtooth(3.0, 3.0, s.sensor_width_px), lit=True)
    fit = registry()["bias_gradient"].signature.fit(res, "bias_gradient")
    assert fit is None or not fit.params.get("column_profile_adu")
