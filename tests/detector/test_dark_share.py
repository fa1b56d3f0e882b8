"""A dark frame's one level (bias offset and uniform dark, indistinguishable in the mean) shared between them for
the shot noise its dark part carries (detector.signatures.Residuals.dark_share)."""

from dataclasses import replace

import numpy as np
import pytest

from detector import make_sensor
from detector.signatures import Residuals, SpikeStats


def _dark_frame(dark_adu: float, offset_adu: float, level_sd=None, shape=(64, 64)) -> Residuals:
    """A uniform dark of ``dark_adu`` in the model, the data ``offset_adu`` away from it (noise-free)."""
    sensor = make_sensor("ml11002", {"width": shape[1], "height": shape[0]})
    g = sensor.gain_e_per_adu
    model = np.full(shape, 1000.0 + dark_adu, np.float32)
    var = np.full(shape, (sensor.read_noise_e ** 2 + dark_adu * g) / g ** 2, np.float32)
    return Residuals(model + np.float32(offset_adu), model, var, np.ones(shape, bool), np.zeros(shape, np.float32),
                     np.full(shape, dark_adu * g, np.float32), np.arange(shape[0], dtype=float),
                     np.arange(shape[1], dtype=float), sensor, 300.0, SpikeStats(0, 0, 0, 0, 0),
                     SpikeStats(0, 0, 0, 0, 0), level_sd=level_sd)


def test_a_large_dark_takes_the_offset_and_its_shot_noise():
    """A binned 300 s dark (686 ADU) 14 ADU low: with a bias known to 2 ADU and a dark to 10 %, the offset is
    dark charge (share 0.998) and the model's variance drops by its shot noise; without the priors it stays."""
    res = _dark_frame(686.0, -14.0, level_sd=(2.0, 0.1))
    lv = res.levels()
    assert lv["names"] == ["offset_adu"]  # the dark level is degenerate with the offset on a uniform dark
    sd2 = (0.1 * 686.0) ** 2
    assert lv["dark_share"] == pytest.approx(sd2 / (sd2 + 4.0))
    v0 = float(res.var_adu2[0, 0])
    expected = v0 + lv["dark_share"] * lv["coef"][0] * res.poisson_adu
    assert 1.0 / lv["w"] == pytest.approx(expected, rel=1e-6)
    plain = replace(res, level_sd=None, _flat={})
    assert plain.levels()["dark_share"] == 0.0
    assert 1.0 / plain.levels()["w"] == pytest.approx(v0, rel=1e-6)


def test_a_faint_dark_or_a_bias_frame_leaves_the_offset_a_bias():
    """A dark of 0.3 ADU (a short CMOS dark) gives the offset almost wholly to the bias; a bias frame wholly."""
    assert _dark_frame(0.3, -1.0, level_sd=(2.0, 0.1)).levels()["dark_share"] < 1e-3
    assert _dark_frame(0.0, -1.0, level_sd=(2.0, 0.1)).levels()["dark_share"] == 0.0


def test_a_choice_of_law_costs_its_prior_not_a_parameter():
    """Two laws cost 2 ln 2 of -2 ln L whatever the pixels (law_choice_k in units of ln n); one law nothing."""
    from detector.signatures import law_choice_k

    for n in (1_000, 65_536, 4_000_000):
        assert law_choice_k(2, n) * np.log(n) == pytest.approx(2 * np.log(2))
    assert law_choice_k(1, 65_536) == 0.0
