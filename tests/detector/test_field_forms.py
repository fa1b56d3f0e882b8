"""General forms of the smooth fields and response laws the diagnosis fits (issue 23, random forms): a light
field of any low order (a Legendre series whose order the BIC picks), a response pattern with column gains
(a CMOS sensor's column amplifiers), and a power-law response referenced at the frame's own signal."""

from __future__ import annotations

import numpy as np
from helpers import small_sensor

from detector import registry
from detector.effects.base import Stage, Tile
from detector.effects.pixel_response import frame_reference_fraction, line_gain_vector, power_law_nonlinearity
from detector.effects.sky import legendre_field_rate, window_uv
from detector.signatures import Residuals, SpikeStats, heldout_delta


def _residuals(sensor, photo, truth, rng, exptime_s=10.0, light_source="sky"):
    """The measured frame: ``truth`` [ADU] plus the bias and Gaussian noise of the model's variance, on the
    sensor's read-out window (pixel centres in sensor coordinates)."""
    h, w = photo.shape
    var = (photo / sensor.gain_e_per_adu + (4.0 / sensor.gain_e_per_adu) ** 2).astype(np.float32)
    data = (truth + sensor.bias_adu + rng.normal(0, 1, photo.shape) * np.sqrt(var)).astype(np.float32)
    none = SpikeStats(0, 0, 0, 0, 0)
    return Residuals(data, (photo + sensor.bias_adu).astype(np.float32), var, np.ones(photo.shape, bool),
                     photo.astype(np.float32), np.zeros(photo.shape, np.float32),
                     sensor.roi_y0 + np.arange(h, dtype=float), sensor.roi_x0 + np.arange(w, dtype=float), sensor,
                     exptime_s, none, none, background_adu=np.full(photo.shape, 200.0 + sensor.bias_adu, np.float32),
                     light_source=light_source)


def test_straylight_fits_a_cubic_field_of_light_at_the_order_the_pixels_support():
    """A cubic field of light (about 5 e-/s per pixel from faintest to brightest over a 10 s exposure: twice the
    sky's shot noise per pixel, 8 % of the sky) is fitted by the straylight's Legendre series at order 3
    (BIC: order 2 misses it, order 4 pays for nothing), and the effect renders the fitted field within 3 % of
    its span."""
    sensor = small_sensor(width=128, height=96, bias_adu=100.0)
    rng = np.random.default_rng(5)
    g = sensor.gain_e_per_adu
    photo = np.full((96, 128), 400.0)  # ADU of sky
    ys, xs = sensor.roi_y0 + np.arange(96.0), sensor.roi_x0 + np.arange(128.0)
    v, u = window_uv(sensor, ys, xs)
    cubic = 1.2 * (u ** 3)[None, :] - 1.0 * (v[:, None] * u[None, :] ** 2) + 0.8 * (v ** 3)[:, None] \
        + 0.5 * u[None, :]  # [e-/s/pixel]
    field_adu = cubic * 10.0 / g
    res = _residuals(sensor, photo, photo + field_adu, rng)
    fit = registry()["straylight"].signature.fit(res, "straylight")
    assert fit is not None and fit.delta_bic < -100
    p = fit.params
    assert p["model"] == "legendre" and p["order"] == 3, fit.note
    rendered = legendre_field_rate(v, u, p["order"], p["coef"])
    span = float(cubic.max() - cubic.min())
    # the field less its mean (a constant is the sky's level, refitted with it)
    err = (rendered - rendered.mean()) - (cubic - cubic.mean())
    assert float(np.sqrt(np.mean(err ** 2))) < 0.03 * span
    # the effect with the fitted parameters adds that field of light [e-] on the window (a tile of it)
    cls = registry()["straylight"]
    eff = cls(cls.Params.model_validate(p), sensor)
    tile = Tile(sensor, 0, sensor.roi_y0, sensor.roi_y0 + 96, sensor.roi_x0, sensor.roi_x0 + 128, 10.0, 1)
    light = np.full((96, 128), 600.0, np.float32)
    eff.apply(Stage.FIELD, tile, light)
    assert np.allclose(light - 600.0, rendered * 10.0, atol=1e-3)


def _flat(sensor, shape, level_adu=20000.0):
    return np.full(shape, level_adu)


def test_prnu_measures_column_gains_that_predict_held_out_pixels():
    """A flat (20 000 ADU) whose response has 0.3 % column gains (one per column, a CMOS sensor's column
    amplifiers) and 0.2 % white PRNU: the prnu signature measures both within 20 %, and its column gains,
    fitted on one half of a checkerboard, improve the other half (held-out delta far below zero). A step of the
    response between two halves of the frame (amplifier regions) is not column gains: neighbouring columns
    follow each other, and no column part is claimed."""
    shape = (128, 192)
    sensor = small_sensor(width=shape[1], height=shape[0], bias_adu=100.0)
    rng = np.random.default_rng(11)
    photo = _flat(sensor, shape)
    cols = 1.0 + 0.003 * rng.standard_normal(shape[1])
    white = 1.0 + 0.002 * rng.standard_normal(shape)
    res = _residuals(sensor, photo, photo * cols[None, :] * white, rng, light_source="flat")
    sig = registry()["prnu"].signature
    fit = sig.fit(res, "prnu")
    assert fit is not None and fit.delta_bic < -1000
    assert abs(fit.params["column_sigma"] / 0.003 - 1) < 0.2, fit.params
    assert abs(fit.params["sigma"] / 0.002 - 1) < 0.2, fit.params
    assert "row_sigma" not in fit.params
    assert heldout_delta(sig, res, "prnu", fit) < -500

    step = np.where(np.arange(shape[1]) < shape[1] // 2, 1.0, 1.004)
    res2 = _residuals(sensor, photo, photo * step[None, :] * white, rng, light_source="flat")
    fit2 = sig.fit(res2, "prnu")
    assert fit2 is None or "column_sigma" not in fit2.params


def test_prnu_column_gains_are_one_per_sensor_column():
    """The rendered column gains are drawn once per sensor column from the hardware seed: the same for any
    window, tile or row, of the requested rms."""
    g = line_gain_vector(7, "prnu_columns", 4000, 0.01)
    assert np.array_equal(g, line_gain_vector(7, "prnu_columns", 4000, 0.01))
    assert abs(float(np.std(g)) / 0.01 - 1) < 0.05 and abs(float(np.mean(g)) - 1) < 1e-3


def test_a_power_law_response_is_referenced_at_the_frames_median_signal():
    """Stars on a sky (3.6 % of an 80 000 e- well at their peaks) read through a power law of gamma 0.98: the
    nonlinearity signature recovers gamma within 0.003, referenced at the frame's median signal, where the
    rendered law leaves the signal as it is (no level change extrapolated from half the well)."""
    shape = (128, 128)
    sensor = small_sensor(width=shape[1], height=shape[0], bias_adu=100.0, full_well_e=80_000.0)
    rng = np.random.default_rng(3)
    g = sensor.gain_e_per_adu
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
    photo = np.full(shape, 100.0 / g)
    for _ in range(80):
        y0, x0 = rng.uniform(4, shape[0] - 4), rng.uniform(4, shape[1] - 4)
        photo += rng.uniform(300, 2800) / g * np.exp(-((yy - y0) ** 2 + (xx - x0) ** 2) / (2 * 1.5 ** 2))
    q = (photo * g).astype(np.float32)
    ref_e = float(np.median(q))
    out = q.copy()
    power_law_nonlinearity(out, 0.98, ref_e)
    res = _residuals(sensor, photo, out / g, rng)
    fit = registry()["nonlinearity"].signature.fit(res, "nonlinearity")
    assert fit is not None and fit.delta_bic < -30
    p = fit.params
    assert abs(p["gamma"] - 0.98) < 0.003, p
    assert abs(p["gamma_reference"] / frame_reference_fraction(res) - 1) < 1e-5
    assert abs(p["gamma_reference"] * sensor.full_well_e - ref_e) < 0.05 * ref_e
    at_ref = np.full(4, p["gamma_reference"] * sensor.full_well_e, np.float32)
    kept = at_ref.copy()
    power_law_nonlinearity(kept, p["gamma"], p["gamma_reference"] * sensor.full_well_e)
    assert np.allclose(kept, at_ref, rtol=1e-5)
