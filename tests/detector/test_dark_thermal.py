"""The dark-current gradient in its physical form: a linear temperature field across the die with the dark current
doubling every ``T_2`` (Janesick 2001, Scientific CCDs, eq. 7.4; Widenhorn et al. 2002, J. Appl. Phys. 92, 7434).

Checked against independent results: the doubling interval against its closed form and the literature's ~6 K at
-20 C; the rendered dark against ``D0 (2^(T / T_2) - 1) t`` evaluated here; and the diagnosis on synthetic
residuals of a binned ML11002 dark, where the truth is known: a temperature gradient is fitted by the exponential
form (temperatures within 10 %) and beats a bias's ramps and bowl, and a bias ramp with a bowl is not taken for
a temperature gradient.
"""

from __future__ import annotations

import numpy as np
import pytest

from detector import registry
from detector.chain import Detector
from detector.effects import build_effects
from detector.effects.thermal import doubling_interval_k, gradient_rate, thermal_rate
from detector.sensor import make_sensor
from detector.signatures import Residuals, SpikeStats

K_B = 8.617333262e-5  # eV/K


def test_doubling_interval_is_the_mid_gap_law_and_the_literature_values():
    for tc in (-40.0, -20.0, 0.0, 25.0):
        t = tc + 273.15
        # independent: D(T) ~ T^3 exp(-Eg / 2kT) differentiated numerically, T_2 = ln 2 / (d ln D / dT)
        ln_d = lambda x: 3 * np.log(x) - 1.12 / (2 * K_B * x)  # noqa: E731
        h = 1e-3
        slope = (ln_d(t + h) - ln_d(t - h)) / (2 * h)
        assert doubling_interval_k(tc) == pytest.approx(np.log(2) / slope, rel=1e-6)
    # the literature: ~6 K at -20 C, 6-8 K between 0 C and room temperature (Janesick 2001 sect. 7.2)
    assert doubling_interval_k(-20.0) == pytest.approx(6.1, abs=0.2)
    assert 6.5 < doubling_interval_k(0.0) < 7.5 and 7.5 < doubling_interval_k(20.0) < 8.5
    # colder: doubles faster
    assert doubling_interval_k(-60.0) < doubling_interval_k(-20.0)


def test_thermal_rate_is_the_exponential_of_the_linear_field():
    ys, xs = np.array([0.0, 50.0, 100.0]), np.array([0.0, 100.0, 200.0])
    m = thermal_rate(ys, xs, 101, 201, 0.5, 4.0, -2.0, 6.0)
    assert m[1, 1] == pytest.approx(0.0, abs=1e-7)  # zero at the centre
    assert m[1, 2] == pytest.approx(0.5 * (2 ** (2.0 / 6.0) - 1), rel=1e-6)  # right edge: +2 K
    assert m[0, 0] == pytest.approx(0.5 * (2 ** ((-2.0 + 1.0) / 6.0) - 1), rel=1e-6)  # corner: -2 K + 1 K
    # small gradients: the linearised ramp D0 ln2 dT / T_2 (to second order: relative ln2 dT / 2T_2 ~ 3e-4)
    small = thermal_rate(ys, xs, 101, 201, 0.5, 0.01, 0.0, 6.0)
    ramp = gradient_rate(ys, xs, 101, 201, 0.5 * np.log(2) * 0.01 / 6.0, 0.0)
    np.testing.assert_allclose(small, ramp, rtol=1e-3, atol=1e-9)


def test_apply_adds_the_formula_to_a_noiseless_dark():
    s = make_sensor("ml11002", {"binning": 8})
    t = 600.0
    base = Detector(s, []).expose(0.0, t, 1, noiseless=True)
    p = {"temperature_x_k": 4.0, "temperature_y_k": -2.0, "gradient_x_e_per_s": 0.01, "gradient_y_e_per_s": 0.0}
    got = Detector(s, build_effects({"dark_gradient": p}, s)).expose(0.0, t, 1, noiseless=True)
    h, w = s.output_shape
    b = s.binning
    ys, xs = np.arange(h * b, dtype=float), np.arange(w * b, dtype=float)
    t2 = doubling_interval_k(s.temperature_c)
    tf = 4.0 * (xs / (s.sensor_width_px - 1) - 0.5)[None, :] - 2.0 * (ys / (s.sensor_height_px - 1) - 0.5)[:, None]
    rate = s.dark_current_e_per_s * (2.0 ** (tf / t2) - 1) + 0.01 * (xs / (s.sensor_width_px - 1) - 0.5)[None, :]
    expect = (rate * t).reshape(h, b, w, b).sum(axis=(1, 3))  # charge-binned: the b x b pixels' sum
    np.testing.assert_allclose(got - base, expect, rtol=2e-3, atol=2e-3 * np.abs(expect).max())


# ------------------------------------------------------------------------------------ the diagnosis
def _dark_residuals(extra_e: np.ndarray | None = None, extra_adu: np.ndarray | None = None, seed: int = 1,
                    t: float = 600.0) -> Residuals:
    """A binned (8x8) ML11002 dark of ``t`` seconds: model = bias + dark current; data = the model plus an extra
    dark charge [e-] (with its shot noise) or an extra bias [ADU] (without), Gaussian noise of the model's
    variance (dark shot noise + read noise once per binned read)."""
    s = make_sensor("ml11002", {"binning": 8})
    h, w = s.output_shape
    b, g = s.binning, s.gain_e_per_adu
    ys, xs = b * np.arange(h) + (b - 1) / 2.0, b * np.arange(w) + (b - 1) / 2.0
    dark = np.full((h, w), s.dark_current_e_per_s * t * b * b)
    charge = dark + (0 if extra_e is None else extra_e)
    rng = np.random.default_rng(seed)
    data = s.bias_adu + (charge + rng.normal(0, np.sqrt(charge + s.read_noise_e ** 2))) / g
    if extra_adu is not None:
        data = data + extra_adu
    model = s.bias_adu + dark / g
    var = (dark + s.read_noise_e ** 2) / g ** 2
    f32 = np.float32
    return Residuals(data.astype(f32), model.astype(f32), var.astype(f32), np.ones((h, w), bool),
                     np.zeros((h, w), f32), dark.astype(f32), ys, xs, s, t, SpikeStats(0, 0, 0, 0, 0),
                     SpikeStats(0, 0, 0, 0, 0))


def _fits(res):
    reg = registry()
    out = {}
    for name in ("dark_gradient", "bias_gradient"):
        sig = reg[name].signature
        fit = sig.fit(res, name)
        out[name] = (fit, sig.plausible(fit, res) if fit is not None else "no fit")
    return out


def test_temperature_gradient_is_fitted_by_the_exponential_form_and_beats_a_bias():
    s = make_sensor("ml11002", {"binning": 8})
    h, w = s.output_shape
    b, t = s.binning, 600.0
    ys, xs = b * np.arange(h) + (b - 1) / 2.0, b * np.arange(w) + (b - 1) / 2.0
    # the truth's own doubling interval (the sensor's at -25 C)
    extra = thermal_rate(ys, xs, s.sensor_height_px, s.sensor_width_px, s.dark_current_e_per_s, 4.0, -2.0,
                         doubling_interval_k(s.temperature_c)).astype(float) * t * b * b
    res = _dark_residuals(extra_e=extra)
    f = _fits(res)
    dark, why = f["dark_gradient"]
    assert why == "", why
    assert dark.params["temperature_x_k"] == pytest.approx(4.0, rel=0.1)
    assert dark.params["temperature_y_k"] == pytest.approx(-2.0, rel=0.1)
    assert dark.params["gradient_x_e_per_s"] == 0.0 and dark.k == 2
    assert "K warmer at the right edge" in dark.explanation and "cooler at the top" in dark.explanation
    # the fitted mean change is the exponential model at the fitted temperatures (the fixed part included)
    back = thermal_rate(ys, xs, s.sensor_height_px, s.sensor_width_px, s.dark_current_e_per_s,
                        dark.params["temperature_x_k"], dark.params["temperature_y_k"],
                        doubling_interval_k(s.temperature_c)) * t * b * b / s.gain_e_per_adu
    np.testing.assert_allclose(dark.delta_adu, back, atol=0.02 * np.abs(back).max())
    bias = f["bias_gradient"][0]
    assert dark.delta_bic < bias.delta_bic - 10, (dark.delta_bic, bias.delta_bic)


def test_bias_ramp_and_bowl_is_not_taken_for_a_temperature_gradient():
    s = make_sensor("ml11002", {"binning": 8})
    h, w = s.output_shape
    u = (np.arange(w) / (w - 1) - 0.5)[None, :]
    v = (np.arange(h) / (h - 1) - 0.5)[:, None]
    # of the size of the 4 K gradient above (~600 ADU across the frame: 1920 e- of dark per binned pixel in
    # 600 s, 0.45 of it across 4 K), with a bowl
    bias = 400.0 * u - 200.0 * v + 150.0 * (u * u + v * v)
    res = _dark_residuals(extra_adu=bias, seed=2)
    f = _fits(res)
    bias_fit = f["bias_gradient"][0]
    dark, why = f["dark_gradient"]
    assert bias_fit.delta_bic < -100
    assert dark is None or why != "" or bias_fit.delta_bic < dark.delta_bic - 10, (bias_fit.delta_bic,
                                                                                 dark.delta_bic, why)


def test_a_variant_with_a_fixed_part_counts_its_chi2_from_the_residual_itself():
    """fit_variant's delta chi2 of a variant with a fixed part against the level-profiled chi2 computed
    directly: chi2(r - f - J c) - chi2(r)."""
    from detector.signatures import Variant, fit_variant, profiled_chi2

    rng = np.random.default_rng(5)
    s = make_sensor("ml11002", {"binning": 8})
    h, w = s.output_shape
    res = _dark_residuals(seed=3)
    idx, r, wt = res.flat_profiled()[0], res.flat()[1], res.flat_profiled()[2]
    tmpl = [rng.normal(0, 1, (h, w)).astype(np.float32), np.linspace(-1, 1, w, dtype=np.float32)[None, :]]
    fmap = (5.0 * np.outer(np.linspace(-1, 1, h), np.ones(w)) ** 2).astype(np.float32)
    v = Variant(tmpl, lambda c: {}, fixed=lambda i: fmap.ravel()[i].astype(np.float64))
    c, d = fit_variant(res, v, idx, r, wt)
    direct = profiled_chi2(res, idx, r - fmap.ravel()[idx] - c @ v.values(idx, (h, w)), wt) - profiled_chi2(
        res, idx, r, wt)
    assert d == pytest.approx(direct, rel=1e-6, abs=1e-3)
    np.testing.assert_allclose(v.fixed_map((h, w)), fmap)


# ------------------------------------------------------------------ smooth fields of any low-order shape
def _poly_field(s, scale: float) -> np.ndarray:
    """A smooth field on the binned ML11002 window that is neither a plane nor the doubling law's curvature
    (a cross term and a one-sided bowl: two heat sources), peak to peak ``scale``."""
    h, w = s.output_shape
    u = (np.arange(w) / (w - 1) - 0.5)[None, :]
    v = (np.arange(h) / (h - 1) - 0.5)[:, None]
    f = 0.6 * u - 0.3 * v + 1.5 * u * v + 1.2 * (v + 0.5) ** 2
    return scale * (f - f.min()) / np.ptp(f)


def test_a_smooth_dark_field_is_fitted_in_the_bias_basis_and_told_from_a_bias_by_its_shot_noise():
    """On a dark frame a dark-rate field and a bias structure get the same smooth basis (2-D cosines over the
    sensor): the forms do not decide, the dark charge's shot noise does; the fitted field is the truth's."""
    s = make_sensor("ml11002", {"binning": 8})
    extra = _poly_field(s, 1500.0)  # [e-] per binned pixel: ~0.04 e-/s per sensor pixel over 600 s
    res = _dark_residuals(extra_e=extra, seed=4)
    f = _fits(res)
    dark, why = f["dark_gradient"]
    bias = f["bias_gradient"][0]
    assert why == "", why
    assert dark.params.get("field_e_per_s") and "field_adu" in bias.params  # the same basis for both
    assert "smooth dark-rate field" in dark.explanation
    # the field's mean change is the truth's up to a constant (the level's)
    got = np.asarray(dark.delta_adu, float) * s.gain_e_per_adu
    diff = got - extra
    assert np.std(diff - diff.mean()) < 0.05 * np.ptp(extra)
    # the same fit of the mean; the dark charge's shot noise speaks for the dark
    assert dark.delta_bic < bias.delta_bic, (dark.delta_bic, bias.delta_bic)


def test_a_dark_field_whose_shot_noise_cannot_speak_is_untold_from_a_bias():
    """The dark charge's shot noise tells a dark-rate field from a bias structure of the same shape by its
    expected chi2, ``sum(q - ln(1 + q))``, ``q = dv / v`` (~ 1/2 sum q^2, Kullback & Leibler 1951): a field whose
    noise cannot reach LIGHT_LAW_CHI2 says the frame does not tell it from a bias (``untold``); a strong one
    does, and its delta BIC then beats the bias's."""
    from detector.signatures import LIGHT_LAW_CHI2, shot_noise_separation

    s = make_sensor("ml11002", {"binning": 8})
    sig = registry()["dark_gradient"].signature
    for scale, told in ((30.0, False), (100.0, False), (1500.0, True)):
        res = _dark_residuals(extra_e=_poly_field(s, scale), seed=4)
        f = _fits(res)
        dark, bias = f["dark_gradient"][0], f["bias_gradient"][0]
        v = res.var_adu2.astype(float)
        dv = np.asarray(dark.extra_var_adu2, float)
        assert dv.max() > 0
        # independent: the mean of -2 ln L(v) + 2 ln L(v + dv) over draws of noise of variance v + dv
        r = np.random.default_rng(7).normal(0.0, np.sqrt(v + dv), (200,) + v.shape)
        mc = float(np.mean(np.sum(np.log(v / (v + dv)) + r * r * (1 / v - 1 / (v + dv)), axis=(1, 2))))
        assert shot_noise_separation(dark, res) == pytest.approx(mc, rel=0.05, abs=0.5)
        if not told:  # small changes: 1/2 sum (dv / v)^2
            assert shot_noise_separation(dark, res) == pytest.approx(0.5 * np.sum((dv / v) ** 2), rel=0.05)
        assert (shot_noise_separation(dark, res) >= LIGHT_LAW_CHI2) == told
        assert sig.untold_from(dark, res) == (() if told else ("bias_gradient",))
        if told:
            assert dark.delta_bic < bias.delta_bic - LIGHT_LAW_CHI2


def test_a_smooth_bias_field_on_a_dark_is_not_taken_for_dark_charge():
    s = make_sensor("ml11002", {"binning": 8})
    res = _dark_residuals(extra_adu=_poly_field(s, 500.0), seed=6)
    f = _fits(res)
    bias, dark = f["bias_gradient"][0], f["dark_gradient"]
    assert "field_adu" in bias.params
    # the same smooth field in the same basis: the dark charge's shot noise, absent from the data, speaks against
    # the dark by more than 2 ln n (two parameters' BIC penalty)
    assert dark[0] is not None and dark[0].params.get("field_e_per_s"), dark
    assert bias.delta_bic < dark[0].delta_bic - 2 * np.log(dark[0].n), (bias.delta_bic, dark)


def test_a_smooth_dark_field_is_fitted_better_by_the_dark_field_than_by_a_dsnu():
    """A smooth dark field without any pixel-to-pixel scatter: the dark-rate field in the bias's basis fits it
    better than a DSNU's low-frequency part with its scatter. (The DSNU still finds a scatter: the shot noise of
    the field's mean charge, which on one dark the levels give to the bias offset without its shot noise.)"""
    s = make_sensor("ml11002", {"binning": 8})
    res = _dark_residuals(extra_e=_poly_field(s, 1500.0), seed=7)
    dsnu = registry()["dsnu"].signature.fit(res, "dsnu")
    dark = registry()["dark_gradient"].signature.fit(res, "dark_gradient")
    assert dsnu is None or dark.delta_bic < dsnu.delta_bic, (dark.delta_bic, dsnu.delta_bic)


def test_apply_renders_the_smooth_dark_field():
    from detector.effects.readout import bias_field_adu

    s = make_sensor("ml11002", {"binning": 8})
    t = 300.0
    coef = [[0.0, 0.01, -0.004], [0.005, 0.002, 0.0], [-0.003, 0.0, 0.001]]
    base = Detector(s, []).expose(0.0, t, 1, noiseless=True)
    got = Detector(s, build_effects({"dark_gradient": {"gradient_x_e_per_s": 0.0, "field_e_per_s": coef}}, s)
                   ).expose(0.0, t, 1, noiseless=True)
    h, w = s.output_shape
    b = s.binning
    ys, xs = np.arange(h * b, dtype=float), np.arange(w * b, dtype=float)
    rate = bias_field_adu(ys, xs, s.sensor_height_px, s.sensor_width_px, coef).astype(float)
    expect = (np.maximum(rate + s.dark_current_e_per_s, 0) - s.dark_current_e_per_s) * t
    expect = expect.reshape(h, b, w, b).sum(axis=(1, 3))
    np.testing.assert_allclose(got - base, expect, rtol=2e-3, atol=2e-3 * np.abs(expect).max())


def test_a_windowed_dark_field_round_trips_fit_params_apply():
    """On a window of a dark (a region of interest a fifth of the sensor a side) the smooth dark-rate field is
    fitted over the window's box (cosines over the whole sensor seen through the window are nearly collinear):
    the fitted parameters, applied by the effect on that window, give back the fitted mean change, and that is
    the truth's up to the level."""
    from detector.effects.base import Stage, Tile
    from detector.effects.thermal import DarkGradient

    s = make_sensor("ml11002", {"binning": 8})
    b, t = s.binning, 600.0
    y0, x0, hh, ww = 40, 60, 40, 56  # binned pixels: the window [y0*b, (y0+hh)*b) x [x0*b, (x0+ww)*b)
    ys, xs = b * (y0 + np.arange(hh)) + (b - 1) / 2.0, b * (x0 + np.arange(ww)) + (b - 1) / 2.0
    u = ((xs - xs[0]) / np.ptp(xs))[None, :]
    v = ((ys - ys[0]) / np.ptp(ys))[:, None]
    extra = 1500.0 * (0.6 * u - 0.3 * v + 1.5 * u * v) / 2.0  # [e-] per binned pixel: a sensor-scale field's part
    dark = np.full((hh, ww), s.dark_current_e_per_s * t * b * b)
    g = s.gain_e_per_adu
    rng = np.random.default_rng(11)
    charge = dark + extra
    f32 = np.float32
    res = Residuals(f32(s.bias_adu + (charge + rng.normal(0, np.sqrt(charge + s.read_noise_e ** 2))) / g),
                    f32(s.bias_adu + dark / g), f32((dark + s.read_noise_e ** 2) / g ** 2), np.ones((hh, ww), bool),
                    np.zeros((hh, ww), f32), f32(dark), ys, xs, s, t, SpikeStats(0, 0, 0, 0, 0),
                    SpikeStats(0, 0, 0, 0, 0))
    fit = registry()["dark_gradient"].signature.fit(res, "dark_gradient")
    p = fit.params
    assert p.get("field_e_per_s"), p
    assert p["field_box_px"] == [xs[0], ys[0], xs[-1], ys[-1]]  # the window's box
    assert max(abs(c) for row in p["field_e_per_s"] for c in row) < 1.0  # well-conditioned: e-/s, not 1e3
    eff = DarkGradient(DarkGradient.Params(**p), s)
    back = np.full((hh * b, ww * b), s.dark_current_e_per_s * t, np.float32)  # the dark charge it adds to
    eff.apply(Stage.DARK, Tile(s, 0, y0 * b, (y0 + hh) * b, x0 * b, (x0 + ww) * b, t, 0), back)
    back = back.reshape(hh, b, ww, b).sum(axis=(1, 3)) / g  # [ADU] per binned pixel
    fitted = np.asarray(fit.delta_adu, float)
    np.testing.assert_allclose(back - back.mean(), fitted - fitted.mean(), atol=0.01 * np.ptp(fitted))
    truth = extra / g
    assert np.std((fitted - truth) - (fitted - truth).mean()) < 0.05 * np.ptp(truth)


def test_a_dark_field_below_zero_rate_is_refused_and_its_span_is_the_doubling_laws_ratio():
    """A smooth dark-rate field that takes the rate below zero within the window is no temperature field; one that
    does not needs ``T_2 log2((D + F_max) / (D + F_min))`` across the window; a ragged field is refused."""
    from types import SimpleNamespace

    from detector.effects.readout import field_on_window, sensor_box
    from detector.effects.thermal import DarkGradientParams, _check, base_rate, field_span_k

    res = _dark_residuals(seed=8)
    d = base_rate(res)
    zero = {"gradient_x_e_per_s": 0.0, "gradient_y_e_per_s": 0.0, "temperature_x_k": 0.0, "temperature_y_k": 0.0}
    deep = [[0.0, 2.0 * d], [0.0, 0.0]]  # cos(pi u) of amplitude 2 D: the rate at one edge -D
    assert field_span_k(deep, res) is None
    assert "below zero" in _check(SimpleNamespace(params=dict(zero, field_e_per_s=deep)), res)
    mild = [[0.0, 0.2 * d], [0.0, 0.0]]
    f = field_on_window(mild, sensor_box(res.sensor), res)
    t2 = doubling_interval_k(res.sensor.temperature_c)
    assert field_span_k(mild, res) == pytest.approx(t2 * np.log2((d + f.max()) / (d + f.min())), rel=1e-6)
    assert _check(SimpleNamespace(params=dict(zero, field_e_per_s=mild)), res) == ""
    with pytest.raises(ValueError, match="rectangular"):
        DarkGradientParams(field_e_per_s=[[0.0, 1.0], [0.0]])


def test_a_dark_ramp_is_tested_on_the_window_at_the_frames_dark_rate():
    """The linear ramp is a first-order form of the doubling law: it is refused when it takes the dark rate below
    zero within the window the frame sees (not at the sensor's corners, where it is no longer the law), at the
    frame's own mean dark rate (which a dark-rate field the model lacks raises), and its span there is the doubling
    law's ratio."""
    from types import SimpleNamespace

    from detector.effects.thermal import _check, base_rate, frame_dark_rate, ramp_span_k

    res = _dark_residuals(seed=8)
    d = base_rate(res)
    assert frame_dark_rate(res) == pytest.approx(res.sensor.dark_current_e_per_s, rel=0.05)  # a null dark
    zero = {"gradient_x_e_per_s": 0.0, "gradient_y_e_per_s": 0.0, "temperature_x_k": 0.0, "temperature_y_k": 0.0}
    frac = (res.xs.max() - res.xs.min()) / max(res.sensor.sensor_width_px - 1, 1)  # the window's share of the width
    mild = 0.5 * d / frac  # across the sensor: +-0.25 d across the window
    span = ramp_span_k(mild, 0.0, res)
    t2 = doubling_interval_k(res.sensor.temperature_c)
    assert span == pytest.approx(t2 * np.log2(1.25 / 0.75), rel=1e-3)
    assert _check(SimpleNamespace(params=dict(zero, gradient_x_e_per_s=mild)), res) == ""
    deep = 3.0 * d / frac  # +-1.5 d across the window: the rate below zero at one side
    assert ramp_span_k(deep, 0.0, res) is None
    assert "below zero within the window" in _check(SimpleNamespace(params=dict(zero, gradient_x_e_per_s=deep)), res)
    # the same ramp on a frame whose measured dark rate is four times the model's is a physical field
    lifted = SimpleNamespace(**{k: getattr(res, k) for k in ("exptime_s", "dark_e", "photo_adu", "fit", "pixel_sum",
                                                           "gain", "model_adu", "xs", "ys", "sensor")})
    lifted.data_adu = res.data_adu + np.float32(3.0 * d * res.exptime_s * res.pixel_sum / res.gain)
    assert frame_dark_rate(lifted) == pytest.approx(frame_dark_rate(res) + 3.0 * d, rel=1e-2)
    assert ramp_span_k(deep, 0.0, lifted) is not None
