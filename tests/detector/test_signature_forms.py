"""Signature forms that follow the laws real sensors have (issue 23, random forms): CTI trails in the serial
register as well as the parallel one, a soft-saturating (cubic) non-linearity, a smear's minor axis that the
transform cannot narrow, and defect counts judged on the window's count."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import small_sensor

from detector import registry
from detector.effects.cti import ML11002_PARALLEL_TRANSFER_S, CTIParams, cti_transfer
from detector.effects.image_plane import _jitter_params, _jitter_transform
from detector.effects.pixel_response import KNEE_FRACTIONS, knee_nonlinearity, quadratic_nonlinearity
from detector.signatures import Residuals, SpikeStats


def _stars(sensor, shape, seed, n_stars=40, peak=(5e3, 3e4)):
    """Gaussian stars (sigma 1.3 px) on a 200 ADU sky [ADU]."""
    rng = np.random.default_rng(seed)
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w]
    photo = np.full(shape, 200.0)
    for _ in range(n_stars):
        y0, x0 = rng.uniform(4, h - 4), rng.uniform(4, w - 4)
        photo += rng.uniform(*peak) * np.exp(-((yy - y0) ** 2 + (xx - x0) ** 2) / (2 * 1.3 ** 2))
    return photo, rng


#: the window's corner on the sensor [px]: its first row and column are 1001 transfers from the registers
CORNER = 1000


def _residuals(sensor, photo, truth, rng):
    """The measured frame: ``truth`` [ADU] plus the bias and Gaussian noise of the model's variance; the window
    at (CORNER, CORNER) of the sensor."""
    shape = photo.shape
    h, w = shape
    var = (photo / sensor.gain_e_per_adu + (4.0 / sensor.gain_e_per_adu) ** 2).astype(np.float32)
    data = (truth + sensor.bias_adu + rng.normal(0, 1, shape) * np.sqrt(var)).astype(np.float32)
    none = SpikeStats(0, 0, 0, 0, 0)
    return Residuals(data, (photo + sensor.bias_adu).astype(np.float32), var, np.ones(shape, bool),
                     photo.astype(np.float32), np.zeros(shape, np.float32), np.arange(h, dtype=float) + CORNER + 0.5,
                     np.arange(w, dtype=float) + CORNER + 0.5, sensor, 10.0, none, none,
                     background_adu=np.full(shape, 200.0 + sensor.bias_adu, np.float32), light_source="sky")


@pytest.mark.parametrize("direction", ["serial", "parallel"])
def test_cti_trails_are_fitted_in_their_register(direction):
    """ArCTIc's model (Massey et al. 2014) read out along the rows (serial register) or the columns: the
    signature names the register and the trap density within 30 % (the trail of 0.3 traps/pixel releasing
    in one transfer; the fitted release time is one of the three the search tries)."""
    shape = (96, 96)
    sensor = small_sensor(width=shape[1], height=shape[0], bias_adu=100.0)
    photo, rng = _stars(sensor, shape, 7)
    g = sensor.gain_e_per_adu
    q = photo * g
    well = sensor.full_well_e
    if direction == "serial":
        dwell = CTIParams.model_fields["serial_transfer_s"].default
        trailed = cti_transfer(q.T, [0.3], [0.74 * dwell], dwell, 0.478, well, CORNER + 1).T
    else:
        dwell = ML11002_PARALLEL_TRANSFER_S
        trailed = cti_transfer(q, [0.3], [0.74 * dwell], dwell, 0.478, well, CORNER + 1)
    res = _residuals(sensor, photo, trailed / g, rng)
    fit = registry()["cti"].signature.fit(res, "cti")
    assert fit is not None and fit.delta_bic < -100
    p = fit.params
    serial = any(p.get("serial_density_per_px") or [])
    assert serial == (direction == "serial")
    dens = (p["serial_density_per_px"] if serial else p["density_per_px"])[0]
    assert dens == pytest.approx(0.3, rel=0.3)
    # the fitted parameters are the plugin's own: they validate, and the parallel register of a serial fit is off
    CTIParams(**p)
    if serial:
        assert not any(p["density_per_px"])


def test_cti_is_not_found_where_there_is_none():
    shape = (96, 96)
    sensor = small_sensor(width=shape[1], height=shape[0], bias_adu=100.0)
    for seed in (3, 4):
        photo, rng = _stars(sensor, shape, seed)
        fit = registry()["cti"].signature.fit(_residuals(sensor, photo, photo, rng), "cti")
        assert fit is None or fit.delta_bic > -10


def test_soft_saturation_is_the_cubic_term():
    """``S' = S (1 - beta x - beta2 x^2)``, x = S / FW: a response ``a tanh(x / a)`` has the leading term
    ``beta2 = 1 / (3 a^2)`` and no linear one; the plugin's apply follows the law, and the signature fits a
    tanh compression of 6 % at full well as the cubic term (not the quadratic one), its size within 25 %."""
    s = np.array([0.0, 1e4, 4e4], np.float32)
    quadratic_nonlinearity(s, 0.01, 4e4, 0.05)
    assert s[1] == pytest.approx(1e4 * (1 - 0.01 * 0.25 - 0.05 * 0.0625), rel=1e-6)
    assert s[2] == pytest.approx(4e4 * 0.94, rel=1e-6)
    shape = (128, 128)
    sensor = small_sensor(width=shape[1], height=shape[0], bias_adu=100.0, full_well_e=60000.0)
    photo, rng = _stars(sensor, shape, 11, n_stars=60, peak=(5e3, 3.5e4))
    fw = sensor.full_well_e
    a = 2.3  # 1 - a tanh(1 / a) = 0.0598
    q = photo * sensor.gain_e_per_adu
    res = _residuals(sensor, photo, a * fw * np.tanh(q / fw / a) / sensor.gain_e_per_adu, rng)
    fit = registry()["nonlinearity"].signature.fit(res, "nonlinearity")
    assert fit is not None and fit.delta_bic < -50
    p = fit.params
    assert p["beta"] == 0.0 and p["beta2"] == pytest.approx(1 - a * np.tanh(1 / a), rel=0.25)


def test_a_knee_response_is_fitted_as_a_knee():
    """A response linear up to 0.45 of the full well whose slope then falls by 25 % (a piecewise-linear, knee
    response): the plugin's apply follows the law below and above the knee; the signature fits it as a knee
    (one of KNEE_FRACTIONS within 0.1 of the truth), its slope deficit within 30 %, and it beats the smooth laws
    (the quadratic, cubic and power-law fits leave the bend)."""
    from scenes.app.compare.floors import nonlinearity_floor, response_ratio
    from scenes.app.compare.policy import DEFAULT_POLICY

    s = np.array([1e4, 3e4, 4e4], np.float32)
    knee_nonlinearity(s, 0.25, 2e4)
    assert s[0] == 1e4 and s[1] == pytest.approx(3e4 - 0.25 * 1e4) and s[2] == pytest.approx(4e4 - 0.25 * 2e4)
    assert response_ratio({"knee": 0.5, "knee_deficit": 0.25}, 1.0) == pytest.approx(1 - 0.25 * 0.5)
    assert response_ratio({"knee": 0.5, "knee_deficit": 0.25}, 0.4) == pytest.approx(1.0)
    shape = (128, 128)
    sensor = small_sensor(width=shape[1], height=shape[0], bias_adu=100.0, full_well_e=60000.0)
    photo, rng = _stars(sensor, shape, 12, n_stars=80, peak=(1e4, 3.8e4))
    fw = sensor.full_well_e
    q = (photo * sensor.gain_e_per_adu).astype(np.float32)
    knee_nonlinearity(q, 0.25, 0.45 * fw)
    res = _residuals(sensor, photo, q / sensor.gain_e_per_adu, rng)
    sig = registry()["nonlinearity"].signature
    fit = sig.fit(res, "nonlinearity")
    assert fit is not None and fit.delta_bic < -50
    p = fit.params
    assert p["knee"] in KNEE_FRACTIONS and abs(p["knee"] - 0.45) <= 0.1
    assert p["knee_deficit"] == pytest.approx(0.25, rel=0.3)
    assert nonlinearity_floor(p, sensor, DEFAULT_POLICY) == ""  # 25 % x (1 - knee) at full well


def test_a_smear_cannot_narrow_so_its_minor_axis_is_zero():
    """The jitter transform renders a negative minor variance as 0 (a smear cannot narrow the sources): the fit's
    chi2 is flat there, so a fitted negative minor is no measurement and the form is a smear along one line."""
    from types import SimpleNamespace

    res = SimpleNamespace(sensor=SimpleNamespace(binning=1), photo_field_adu=None, data_adu=np.zeros((32, 32)))
    img = np.zeros((32, 32))
    img[16, 16] = 1000.0
    import detector.effects.image_plane as ip

    cap = ip._max_var
    ip._max_var = lambda r: 100.0
    try:
        a = _jitter_transform(res, img, np.array([0.5, -0.3, 0.0]))
        b = _jitter_transform(res, img, np.array([0.5, 0.0, 0.0]))
    finally:
        ip._max_var = cap
    np.testing.assert_allclose(a, b, atol=1e-9)
    p = _jitter_params(np.array([0.09, -0.05, 0.0]), res)
    assert p is not None and p["sigma_minor_px"] == 0.0 and p["sigma_major_px"] == pytest.approx(0.3)


def test_an_elliptical_fall_off_is_fitted_with_the_azimuthal_terms():
    """A fall-off on the window's scale whose rho^2 rate differs along the two diagonals (axis ratio ~0.75 at 45
    degrees): the vignetting's elliptical variant (a2_cos2, a2_sin2) is chosen over the circular one by the BIC,
    its sin 2phi term the truth's within 20 %."""
    from detector.effects.optical import radial_vignetting

    shape = (96, 96)
    s = small_sensor(width=shape[1], height=shape[0], bias_adu=100.0)
    rng = np.random.default_rng(11)
    photo = np.full(shape, 20000.0)  # a flat light: the fall-off measured everywhere
    pitch = s.pixel_pitch_um * 1e-3
    xs = np.arange(shape[1]) + s.roi_x0 + 0.5
    ys = np.arange(shape[0]) + s.roi_y0 + 0.5
    u = (xs - (s.sensor_width_px - 1) / 2.0) * pitch
    v = (ys - (s.sensor_height_px - 1) / 2.0) * pitch
    cx, cy = float(u.mean()), float(v.mean())
    radius = 2 * 0.5 * pitch * float(np.hypot(*shape))  # the window-scale variants' radius
    ri = radial_vignetting(u[None, :], v[:, None], radius, 0.3, 0.0, (cx, cy), 0.0, 0.12)
    var = (photo / s.gain_e_per_adu + (4.0 / s.gain_e_per_adu) ** 2).astype(np.float32)
    data = (photo * ri + s.bias_adu + rng.normal(0, 1, shape) * np.sqrt(var)).astype(np.float32)
    none = SpikeStats(0, 0, 0, 0, 0)
    res = Residuals(data, (photo + s.bias_adu).astype(np.float32), var, np.ones(shape, bool),
                    photo.astype(np.float32), np.zeros(shape, np.float32), ys, xs, s, 10.0, none, none)
    fit = registry()["vignetting"].signature.fit(res, "vignetting")
    assert fit is not None and fit.note.endswith("|elliptical"), None if fit is None else fit.note
    assert fit.params["a2_sin2"] == pytest.approx(0.12, rel=0.2)
    assert abs(fit.params["a2_cos2"]) < 0.03


def test_an_elliptical_saddle_is_refused_and_its_loss_counts_the_major_axis():
    """An elliptical fall-off loses light in every direction: a saddle (a2 = 0.05 with an azimuthal amplitude 0.3,
    light rising by 0.25 rho^2 along one axis) gets no parameters; a fall-off's loss at the corner counts its
    rho^2 rate along the axis that loses most, a2 + hypot(a2_cos2, a2_sin2)."""
    from detector.effects.optical import _loss_at_edge, _vignetting_variant

    shape = (32, 32)
    s = small_sensor(width=shape[1], height=shape[0], bias_adu=100.0)
    ones = np.ones(shape, np.float32)
    none = SpikeStats(0, 0, 0, 0, 0)
    res = Residuals(ones, ones, ones, np.ones(shape, bool), ones, 0 * ones, np.arange(shape[0]) + 0.5,
                    np.arange(shape[1]) + 0.5, s, 10.0, none, none)
    v = _vignetting_variant(res, 0.0, 0.0, elliptical=True)
    assert v.to_params(np.array([0.05, 0.0, 0.3, 0.0])) is None
    assert v.to_params(np.array([-0.05, 0.0, 0.0, 0.2])) is None  # along one diagonal it gains light too
    p = v.to_params(np.array([0.2, 0.01, 0.06, 0.08]))
    assert p is not None
    assert _loss_at_edge(p, res) == pytest.approx(0.2 + 0.1 + 0.01)


def test_a_fall_off_steeper_than_rho4_is_fitted_on_the_bound_of_its_rho2_rate():
    """A power-law fall-off (rho^6, 15 % deep at the window's farthest pixel) about a centre inside the window:
    the unbounded least squares of (a2, a4) puts a2 < 0 (light rising from the centre), which the bound a2 >= 0
    refuses at every centre; the least squares on that bound (a4 alone) is the fit, not nothing."""
    from detector.effects.optical import _offsets_mm, _vignetting_variant

    shape = (96, 96)
    s = small_sensor(width=shape[1], height=shape[0], bias_adu=100.0)
    rng = np.random.default_rng(12)
    photo = np.full(shape, 20000.0)
    xs = np.arange(shape[1]) + s.roi_x0 + 0.5
    ys = np.arange(shape[0]) + s.roi_y0 + 0.5
    none = SpikeStats(0, 0, 0, 0, 0)
    probe = Residuals(photo.astype(np.float32), photo.astype(np.float32), photo.astype(np.float32),
                      np.ones(shape, bool), photo.astype(np.float32), np.zeros(shape, np.float32), ys, xs, s, 10.0,
                      none, none)
    u, v = _offsets_mm(probe, 0.0, 0.0)
    cu, cv = float(u[30]), float(v[60])  # off the window's centre, inside it
    rho2 = ((u[None, :] - cu) ** 2 + (v[:, None] - cv) ** 2)
    ri = 1.0 - 0.15 * (rho2 / rho2.max()) ** 3
    var = (photo / s.gain_e_per_adu + (4.0 / s.gain_e_per_adu) ** 2).astype(np.float32)
    data = (photo * ri + s.bias_adu + rng.normal(0, 1, shape) * np.sqrt(var)).astype(np.float32)
    res = Residuals(data, (photo + s.bias_adu).astype(np.float32), var, np.ones(shape, bool),
                    photo.astype(np.float32), np.zeros(shape, np.float32), ys, xs, s, 10.0, none, none)
    from detector.signatures import fit_variant, search_sample

    ctx = search_sample(res)
    unbounded = _vignetting_variant(res, cu, cv, 2 * 0.5 * s.pixel_pitch_um * 1e-3 * float(np.hypot(*shape)))
    c, _ = fit_variant(res, unbounded, ctx["idx"], ctx["r"], ctx["w"])
    assert c[0] < 0 and unbounded.to_params(c) is None  # the bound refuses the unbounded fit
    fit = registry()["vignetting"].signature.fit(res, "vignetting")
    assert fit is not None and fit.note.endswith("|quartic"), None if fit is None else fit.note
    assert fit.params["a2"] == 0.0 and fit.params["a4"] > 0
    assert fit.delta_m2lnl < -1000
    # on the bound the loss is the rho^4 term's: a negative one would brighten the field everywhere
    quartic = _vignetting_variant(res, cu, cv, 2 * 0.5 * s.pixel_pitch_um * 1e-3 * float(np.hypot(*shape)),
                                  quartic=True)
    assert quartic.to_params(np.array([0.05])) is not None and quartic.to_params(np.array([-0.05])) is None


def test_a_linear_fit_whose_winner_leaves_its_bound_once_the_light_is_rescaled_falls_back_to_the_next():
    """A fall-off of the light (12 % deep along the columns) on a frame 30 % short of the model's light: the
    joint fit finds the loss as ``c = 0.12 x 0.7 = 0.084`` beside the light level, within the best variant's
    bound (0.1) on the search, and 0.12 once divided by the light level, beyond it. The fit falls back to the
    next variant in BIC order (a worse form within its bound) instead of returning nothing."""
    from detector.signatures import LinearSignature, Variant

    shape = (64, 64)
    s = small_sensor(width=shape[1], height=shape[0], bias_adu=100.0)
    rng = np.random.default_rng(3)
    photo = np.full(shape, 20000.0)
    x = (np.arange(shape[1]) / (shape[1] - 1))[None, :] * np.ones(shape)
    light, depth = -0.3, 0.12
    var = (photo / s.gain_e_per_adu + (4.0 / s.gain_e_per_adu) ** 2).astype(np.float32)
    data = (photo * (1 + light) * (1 - depth * x ** 2) + s.bias_adu
            + rng.normal(0, 1, shape) * np.sqrt(var)).astype(np.float32)
    xs = np.arange(shape[1]) + s.roi_x0 + 0.5
    ys = np.arange(shape[0]) + s.roi_y0 + 0.5
    none = SpikeStats(0, 0, 0, 0, 0)
    res = Residuals(data, (photo + s.bias_adu).astype(np.float32), var, np.ones(shape, bool),
                    photo.astype(np.float32), np.zeros(shape, np.float32), ys, xs, s, 10.0, none, none)

    def variant(shape_map, bound, label):
        return Variant([(-photo * shape_map).astype(np.float32)],
                       lambda c: {"depth": float(c[0])} if 0 < c[0] <= bound else None, label)

    def variants(res):
        yield variant(x ** 2, 0.1, "true form, bounded at 0.1")
        yield variant(x ** 3, 1.0, "cubic")

    sig = LinearSignature(variants, lambda p, res: "", of_light=True)
    fit = sig.fit(res, "fall-off")
    assert fit is not None and fit.note == "cubic", None if fit is None else fit.note
    assert fit.params["depth"] > 0.1
    # alone, the bounded true form leaves its bound once rescaled: nothing
    alone = LinearSignature(lambda res: [variant(x ** 2, 0.1, "true form, bounded at 0.1")], lambda p, res: "",
                            of_light=True)
    assert alone.fit(res, "fall-off") is None
