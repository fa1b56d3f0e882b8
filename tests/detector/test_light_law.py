"""The law of a smooth light pattern: an added light A(x) and a response P(x) to the light L(x) are one image
where L is one level; the sources above that level tell them apart (detector.signatures.light_law_evidence)."""

from __future__ import annotations

import numpy as np

from detector.sensor import make_sensor
from detector.signatures import LIGHT_LAW_CHI2, Fit, Residuals, SpikeStats, light_law_evidence


def _frame(rng, stars: bool, added: bool):
    h = w = 96
    s = make_sensor("imx411", {"width": w, "height": h})
    sky = 200.0
    light = np.full((h, w), sky)
    if stars:
        for y, x in rng.integers(4, 92, size=(40, 2)):
            yy, xx = np.mgrid[:h, :w]
            light += 4000.0 * np.exp(-((yy - y) ** 2 + (xx - x) ** 2) / (2 * 1.5 ** 2))
    u = np.linspace(-1, 1, w)[None, :] * np.ones((h, 1))
    shape = 0.5 * (1 + u)  # a ramp across the columns
    delta = 0.05 * sky * shape if added else 0.05 * shape * light  # the same 5 % of the sky at the edge
    var = light + 25.0
    model = light + 100.0
    data = model + delta + rng.normal(0, np.sqrt(var))
    z = np.zeros((h, w), np.float32)
    res = Residuals(data.astype(np.float32), model.astype(np.float32), var.astype(np.float32), np.ones((h, w), bool),
                    light.astype(np.float32), z, np.arange(h, dtype=float), np.arange(w, dtype=float), s, 1.0,
                    SpikeStats(0, 0, 0, 0, 0), SpikeStats(0, 0, 0, 0, 0),
                    background_adu=np.full((h, w), sky + 100.0, np.float32))
    # the added-light candidate's fitted map: the ramp as an added light (its law is "added")
    return res, Fit("straylight", {}, 0.0, 1, h * w, "", delta_adu=(0.05 * sky * shape).astype(np.float32))


def test_the_sources_tell_an_added_light_from_a_response_and_one_level_does_not():
    rng = np.random.default_rng(23)
    res, fit = _frame(rng, stars=True, added=True)
    assert light_law_evidence(fit, res, multiplicative=False)[0] < -LIGHT_LAW_CHI2  # added: its own law wins
    res, fit = _frame(rng, stars=True, added=False)
    assert light_law_evidence(fit, res, multiplicative=False)[0] > LIGHT_LAW_CHI2  # a response: the other law
    res, fit = _frame(rng, stars=False, added=False)
    assert abs(light_law_evidence(fit, res, multiplicative=False)[0]) < LIGHT_LAW_CHI2  # one level: not told


def test_an_offset_of_the_read_out_ties_with_a_response_only_where_the_light_is_one_level_and_its_noise_is_silent():
    """A bias structure and a vignetting of the same shape are one image on a flat (one light level) when the
    shot noise such a change of charge would carry is below LIGHT_LAW_CHI2 (detector.signatures.
    offset_response_untold); the sources tell them (a response scales them), and so does the shot noise of a deep
    change on a bright flat; a frame without light has no response to be."""
    from dataclasses import replace

    from detector.signatures import offset_response_untold

    untold = offset_response_untold(("vignetting",))
    rng = np.random.default_rng(29)
    res, fit = _frame(rng, stars=False, added=True)
    bias = replace(fit, effect="bias_gradient")
    assert untold(bias, res) == ("vignetting",)  # 5 % of a 200 ADU sky on 96^2 pixels: its noise is silent
    res, fit = _frame(rng, stars=True, added=True)
    assert untold(replace(fit, effect="bias_gradient"), res) == ()  # the sources tell an offset from a response
    res, fit = _frame(rng, stars=False, added=True)
    deep = replace(fit, effect="bias_gradient", delta_adu=20 * fit.delta_adu)  # the ramp at the whole sky
    assert untold(deep, res) == ()  # a response that deep changes the shot noise measurably
    dark = replace(res, photo_adu=np.zeros_like(res.photo_adu), _flat={})
    assert untold(bias, dark) == ()


def test_dark_charge_ties_with_a_response_where_the_light_is_one_level():
    """A field of dark charge and a response of the same shape are one image on a flat (one light level), their
    shot noise alike (both change the charge by as much): named together (detector.signatures.
    dark_field_untold); the sources tell them apart."""
    from dataclasses import replace

    from detector.signatures import dark_field_untold

    untold = dark_field_untold((), ("vignetting",))
    rng = np.random.default_rng(31)
    res, fit = _frame(rng, stars=False, added=True)
    assert untold(replace(fit, effect="dark_gradient"), res) == ("vignetting",)
    res, fit = _frame(rng, stars=True, added=True)
    assert untold(replace(fit, effect="dark_gradient"), res) == ()
