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


# --- the smooth 2-D bias structure (``field_adu`` over ``field_box_px``) ----------------------------------------

def test_the_field_is_the_2d_cosine_series_held_at_its_box():
    from detector.effects.readout import bias_field_adu

    ys, xs = np.arange(0.0, 60.0), np.arange(0.0, 90.0)
    coef = [[5.0, 0.0, 0.0], [0.0, 0.0, 2.0]]  # C_00 is the level's: left out
    got = bias_field_adu(ys, xs, 60, 90, coef, (10.0, 20.0, 70.0, 50.0))
    v = np.clip((ys - 20) / 30, 0, 1)[:, None]
    u = np.clip((xs - 10) / 60, 0, 1)[None, :]
    assert np.allclose(got, 2 * np.cos(np.pi * v) * np.cos(2 * np.pi * u), atol=1e-5)


def test_the_effect_adds_the_field():
    """A noiseless bias frame of the effect is the bias plus the field at every pixel (up to the ADU rounding)."""
    from detector.effects.readout import bias_field_adu

    s = make_sensor("ml11002", {"read_noise_e": 0.0, "dark_current_e_per_s": 0.0, "binning": 8})
    coef = [[0.0, 6.0], [4.0, -3.0]]
    det = Detector(s, build_effects({"bias_gradient": {"gradient_x_adu": 0.0, "field_adu": coef}}, s))
    f = det.expose(0.0, 0.0, 1).astype(float)
    h, w = f.shape
    # the binned pixels' sensor centres (a CCD bins in charge: the bias is added once per binned pixel)
    want = bias_field_adu(np.arange(h) * 8 + 3.5, np.arange(w) * 8 + 3.5, s.sensor_height_px, s.sensor_width_px, coef)
    d = f - f.mean() - (want - want.mean())
    assert np.abs(d).max() <= 1.0 and np.ptp(want) > 19


def _oblique_wave(ptp, cycles=2.2, angle=2.58):
    def field(ys, xs):
        t = (np.cos(angle) * xs[None, :] / xs.max() + np.sin(angle) * ys[:, None] / ys.max()) * cycles
        return 0.5 * ptp * np.sin(2 * np.pi * t + 0.4)
    return field


def _bias_frame_2d(field, seed=5, read_adu=10.0):
    rng = np.random.default_rng(seed)
    s = make_sensor("ml11002", {"binning": 8})
    h, w = s.output_shape
    ys, xs = np.arange(h) * 8 + 3.5, np.arange(w) * 8 + 3.5
    model = np.full((h, w), 1000.0)
    data = model + field(ys, xs) + rng.normal(0, read_adu, (h, w))
    z = np.zeros((h, w), np.float32)
    return Residuals(data.astype(np.float32), model.astype(np.float32), np.full((h, w), read_adu ** 2, np.float32),
                     np.ones((h, w), bool), z, z, ys, xs, s, 0.0, SpikeStats(0, 0, 0, 0, 0), SpikeStats(0, 0, 0, 0, 0))


def test_an_oblique_wave_of_the_bias_is_fitted_as_a_2d_field():
    """A fixed oblique wave of 2.2 cycles and 8 ADU peak to peak under 10 ADU of read noise (what a random form
    of the bias structure draws): the ramps and the column profile take little of it; the 2-D field keeps at
    least 90 % of its variance, and is plausible."""
    wave = _oblique_wave(8.0)
    res = _bias_frame_2d(wave)
    sig = registry()["bias_gradient"].signature
    fit = sig.fit(res, "bias_gradient")
    assert fit.params.get("field_adu") and fit.delta_bic < -1000
    truth = wave(res.ys, res.xs)
    kept = 1 - np.var(truth - np.asarray(fit.delta_adu)) / np.var(truth)
    assert kept > 0.9
    assert sig.plausible(fit, res) == ""


def test_white_noise_alone_takes_no_field():
    """A bias frame of read noise alone: no variant of the bias structure is significant (delta BIC >= -10)."""
    res = _bias_frame_2d(lambda ys, xs: np.zeros((ys.size, xs.size)), seed=11)
    fit = registry()["bias_gradient"].signature.fit(res, "bias_gradient")
    assert fit is None or fit.delta_bic > -10


def test_the_field_on_its_window_spans_the_window_edge_to_edge():
    """The grid on which a fitted field is bounded by the bias and described: the window the residuals cover,
    edge to edge; over the window's own box its corners are where the cosines are at 0 and pi (C_01 cos(k pi u)
    is +C_01 at x0, -C_01 at x1)."""
    from types import SimpleNamespace

    from detector.effects.readout import BIAS_FIELD_GRID, field_on_window, window_box

    coef = [[0.0, 3.0], [0.0, 0.0]]
    res = SimpleNamespace(sensor=SimpleNamespace(sensor_height_px=60, sensor_width_px=90),
                          ys=np.linspace(20.0, 50.0, 31), xs=np.linspace(10.0, 70.0, 61))
    got = field_on_window(coef, window_box(res), res)
    assert got.shape == (BIAS_FIELD_GRID, BIAS_FIELD_GRID)
    assert got[0, 0] == pytest.approx(3.0) and got[-1, -1] == pytest.approx(-3.0) and np.ptp(got) == pytest.approx(6.0)


def test_a_sensor_scale_field_is_as_smooth_through_a_window_as_its_share_of_the_sensor():
    """A read-out drift or a die's temperature field is sensor-scale: a window spanning a twentieth of the sensor
    sees a third of a half cycle of the sensor's 8-term series, so only ramps and their cross term are offered
    over it; the whole sensor keeps every order; half the sensor sees half the half-cycles."""
    from types import SimpleNamespace

    from detector.effects.readout import BIAS_FIELD_ORDERS, sensor_scale_orders

    s = SimpleNamespace(sensor_width_px=4008, sensor_height_px=2672)

    def res(w, h):
        return SimpleNamespace(sensor=s, xs=np.arange(w, dtype=float), ys=np.arange(h, dtype=float))

    assert sensor_scale_orders(res(200, 200)) == (2,)
    assert sensor_scale_orders(res(4008, 2672)) == tuple(BIAS_FIELD_ORDERS)
    assert sensor_scale_orders(res(2004, 1336)) == (2, 3, 5)  # ceil((N - 1) x 0.4999) + 1 for N = 3, 5, 8


@pytest.mark.parametrize("params, key", [("BiasGradientParams", "field_adu"), ("DarkGradientParams", "field_e_per_s")])
def test_both_smooth_fields_validate_their_coefficients_and_box_alike(params, key):
    """The bias structure [ADU] and the dark-rate field [e-/s] share one declaration of their basis: a ragged
    coefficient array or a box with x1 <= x0 is an error naming the key, in either unit."""
    from detector.effects import readout, thermal

    cls = getattr(readout, params, None) or getattr(thermal, params)
    ok = cls(**{key: [[0.0, 1.0], [2.0, 3.0]], "field_box_px": [0.0, 0.0, 10.0, 10.0]})
    assert getattr(ok, key) == [[0.0, 1.0], [2.0, 3.0]]
    with pytest.raises(ValueError, match=f"{key}[\\s\\S]*rectangular"):
        cls(**{key: [[0.0, 1.0], [2.0]]})
    with pytest.raises(ValueError, match="field_box_px[\\s\\S]*x1 > x0"):
        cls(field_box_px=[0.0, 0.0, -1.0, 10.0])
    unit = cls.model_json_schema()["properties"][key]["unit"]
    assert unit == ("ADU" if key == "field_adu" else "e-/s")
