"""Crosstalk in the forms real read-out electronics give it (issue 10): a delayed echo with a tail, of either
sign, rendered by the plugin and recovered by its signature; the templates against an independent
computation; no crosstalk in a frame without it."""

from __future__ import annotations

import numpy as np
import pytest

from detector.effects.readout import (
    CROSSTALK_DELAYS,
    CROSSTALK_TAILS,
    CrosstalkLayout,
    _crosstalk_check,
    channel_crosstalk,
    crosstalk_kernel,
    crosstalk_signal,
    crosstalk_variant,
)
from detector.signatures import Residuals, SpikeStats


def test_kernel_is_a_normalised_delayed_exponential():
    assert np.array_equal(crosstalk_kernel(0, 0.0), [1.0])
    assert np.array_equal(crosstalk_kernel(2, 0.0), [0.0, 0.0, 1.0])
    k = crosstalk_kernel(1, 0.8)
    assert k[0] == 0.0 and np.isclose(k.sum(), 1.0)
    # successive lags fall by exp(-1 / tail) (a single-pole response), over 5 e-folding lengths
    assert np.allclose(k[2:] / k[1:-1], np.exp(-1 / 0.8))
    assert k.size == 1 + int(np.ceil(5 * 0.8)) + 1
    with pytest.raises(ValueError):
        crosstalk_kernel(-1, 0.0)


def _echo_by_hand(shape, n, mirrored, src, alpha, kern):
    """The echo of point sources ``src`` [(row, col, value)], written pixel by pixel from the definition: the
    victim pixel read ``m`` places after the source's read-out position gets ``alpha kern[m] value``."""
    wc = shape[1] // n
    out = np.zeros(shape)
    for y, x, val in src:
        j0 = x // wc
        q0 = x - j0 * wc
        p0 = wc - 1 - q0 if mirrored and j0 % 2 else q0  # read-out position of the source
        for j in range(n):
            if j == j0:
                continue
            for m, km in enumerate(kern):
                p = p0 + m
                if p >= wc:
                    continue
                q = wc - 1 - p if mirrored and j % 2 else p
                out[y, j * wc + q] += alpha * km * val
    return out


@pytest.mark.parametrize("n,mirrored,delay,tail,alpha", [(4, True, 0, 0.0, 0.01), (3, False, 2, 0.7, 2.5e-3),
                                                         (2, True, 1, 0.0, -6e-4), (5, True, 3, 1.5, -1e-3)])
def test_delayed_echo_matches_the_definition(n, mirrored, delay, tail, alpha):
    shape = (3, 5 * n + 3)  # columns left over beyond the last whole channel do not couple
    a = np.zeros(shape, np.float32)
    src = [(0, 1, 1000.0), (1, 5 + 2, 500.0), (2, shape[1] - 4, 800.0)]
    for y, x, v in src:
        a[y, x] += v
    before = a.copy()
    channel_crosstalk(a, n, alpha, mirrored, delay, tail)
    used = (shape[1] // n) * n
    expected = _echo_by_hand(shape, n, mirrored, [s for s in src if s[1] < used], alpha,
                             crosstalk_kernel(delay, tail))
    np.testing.assert_allclose(a - before, expected, atol=1e-4)


def test_defaults_are_the_instantaneous_coupling():
    rng = np.random.default_rng(0)
    a = rng.uniform(0, 1000, (8, 64)).astype(np.float32)
    b = a.copy()
    channel_crosstalk(a, 4, 1e-3, True)
    channel_crosstalk(b, 4, 1e-3, True, 0, 0.0)
    assert np.array_equal(a, b)


def _stars_residuals(alpha=0.0, n=3, mirrored=False, delay=0, tail=0.0, seed=1, shape=(256, 240)):
    """A star field (Gaussian stars on a sky, bias 100 ADU, gain 1.5 e-/ADU, read noise 4 e-), the measured
    frame being the model with the crosstalk of the plugin added and Gaussian noise of the model's variance."""
    from helpers import small_sensor

    h, w = shape
    sensor = small_sensor(width=w, height=h, bias_adu=100.0)
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    photo = np.full(shape, 200.0)
    for _ in range(60):
        y0, x0 = rng.uniform(4, h - 4), rng.uniform(4, w - 4)
        photo += rng.uniform(2e3, 4e4) * np.exp(-((yy - y0) ** 2 + (xx - x0) ** 2) / (2 * 1.3 ** 2))
    photo = photo.astype(np.float32)
    model = photo + np.float32(sensor.bias_adu)
    var = (photo / sensor.gain_e_per_adu + (4.0 / sensor.gain_e_per_adu) ** 2).astype(np.float32)
    truth = photo.copy()
    if alpha:
        channel_crosstalk(truth, n, alpha, mirrored, delay, tail)
    data = (truth + np.float32(sensor.bias_adu) + rng.normal(0, 1, shape) * np.sqrt(var)).astype(np.float32)
    none = SpikeStats(0, 0, 0, 0, 0)
    res = Residuals(data, model.astype(np.float32), var, np.ones(shape, bool), photo, np.zeros(shape, np.float32),
                    np.arange(h, dtype=float), np.arange(w, dtype=float), sensor, 10.0, none, none,
                    background_adu=np.full(shape, 200.0 + sensor.bias_adu, np.float32), light_source="sky")
    return res


@pytest.mark.parametrize("n,mirrored", [(3, False), (4, True), (2, True)])
def test_layout_taps_reproduce_the_plugin_template(n, mirrored):
    res = _stars_residuals(shape=(64, 4 * 17 + 3))
    sig = crosstalk_signal(res)
    lay = CrosstalkLayout(sig, n, mirrored)
    idx = np.arange(sig.size)
    for delay, tail in ((0, 0.0), (2, 0.0), (1, 0.9)):
        kern = crosstalk_kernel(delay, tail)
        t = sig.copy()
        channel_crosstalk(t, n, 1.0, mirrored, delay, tail)
        direct = (t.astype(np.float64) - sig).ravel()
        via_taps = kern @ lay.taps(idx, kern.size)
        np.testing.assert_allclose(via_taps, direct, atol=2e-3 * np.abs(direct).max())
        v = crosstalk_variant(res, n, mirrored, delay, tail, layout=lay)
        np.testing.assert_allclose(v.values(idx[::7], sig.shape)[0], via_taps[::7], rtol=1e-5, atol=1e-3)


@pytest.mark.parametrize("n,mirrored,delay,tail,alpha", [(3, False, 2, 0.7, 2.5e-3), (2, True, 1, 0.0, -1.5e-3),
                                                         (4, True, 0, 0.0, 1e-3), (2, False, 5, 0.0, 2e-3),
                                                         (3, False, 0, 2.5, 2e-3)])
def test_signature_recovers_a_delayed_echo_rendered_by_the_plugin(n, mirrored, delay, tail, alpha):
    from detector import registry

    res = _stars_residuals(alpha, n, mirrored, delay, tail)
    sig = registry()["crosstalk"].signature
    fit = sig.fit(res, "crosstalk")
    p = fit.params
    assert (p["n_channels"], p["mirrored"], p.get("delay_px", 0)) == (n, mirrored, delay)
    # the coefficient within 4 of its standard errors: sigma_alpha = |alpha| / sqrt(-delta chi2) for one template
    err = abs(p["alpha"]) / np.sqrt(-fit.delta_m2lnl)
    assert abs(p["alpha"] - alpha) < 4 * err + 0.05 * abs(alpha)
    if tail:
        assert abs(p["tail_px"] - tail) < 0.35
    else:
        assert "tail_px" not in p
    # parameters: alpha + the layout choice + one each for a delay and a tail
    assert fit.k == 2 + int(bool(delay)) + int("tail_px" in p)
    assert fit.delta_bic < -100 and _crosstalk_check(fit, res) == ""
    # the fitted template is the plugin's own: the model plus the fitted crosstalk leaves white residuals
    r1 = (res.data_adu - res.model_adu - fit.delta_adu).astype(np.float64)
    assert abs(np.mean(r1 ** 2 / res.var_adu2) - 1.0) < 0.02


@pytest.mark.parametrize("seed", [3, 4, 5])
def test_no_crosstalk_gives_no_significant_fit(seed):
    from detector import registry

    res = _stars_residuals(0.0, seed=seed)
    fit = registry()["crosstalk"].signature.fit(res, "crosstalk")
    assert fit is None or fit.delta_bic > -10


def test_a_delay_or_tail_at_the_search_bound_is_flagged():
    from detector.signatures import Fit

    res = _stars_residuals()
    base = {"n_channels": 2, "alpha": 1e-3, "mirrored": True}
    ok = Fit("crosstalk", {**base, "delay_px": 1, "tail_px": 0.5}, -100.0, 4, 100, "")
    assert _crosstalk_check(ok, res) == ""
    late = Fit("crosstalk", {**base, "delay_px": max(CROSSTALK_DELAYS)}, -100.0, 3, 100, "")
    assert "largest the search tries" in _crosstalk_check(late, res)
    long = Fit("crosstalk", {**base, "tail_px": max(CROSSTALK_TAILS)}, -100.0, 3, 100, "")
    assert "tail" in _crosstalk_check(long, res)
    big = Fit("crosstalk", {**base, "alpha": -0.02}, -100.0, 2, 100, "")
    assert "coupling" in _crosstalk_check(big, res)


def test_apply_of_the_fitted_form_renders_the_echo():
    """The plugin's apply with the fitted parameters (what ``diagnose --apply`` writes) adds the fitted template."""
    from detector import registry
    from detector.effects.base import build_effects

    res = _stars_residuals(-2e-3, 2, True, 1, 0.0)
    fit = registry()["crosstalk"].signature.fit(res, "crosstalk")
    (eff,) = build_effects({"crosstalk": fit.params}, res.sensor)
    assert (eff.params.delay_px, eff.params.tail_px) == (fit.params.get("delay_px", 0), fit.params.get("tail_px", 0))
    sig = crosstalk_signal(res)
    out = sig.copy()
    eff.apply(None, None, out)
    np.testing.assert_allclose(out - sig, np.asarray(fit.delta_adu), atol=1e-3)


def test_echo_of_the_sources_above_a_varying_sky_is_found():
    """Crosstalk that echoes the sources' signal above the channel's background (a coupling that is not linear
    down to the sky, or measured on bright sources), on a sky with a 10x gradient across the frame: the
    signature couples the sources without the background light (:func:`crosstalk_signal`) and recovers the
    layout, the delay and the coefficient within 4 standard errors; the sky's echo it leaves out would be a
    structure of 2e-3 x 1800 ADU x (n - 1) had it been in the template."""
    from helpers import small_sensor

    from detector import registry

    h, w, n, mirrored, delay, alpha = 256, 240, 3, True, 3, 2e-3
    sensor = small_sensor(width=w, height=h, bias_adu=100.0)
    rng = np.random.default_rng(7)
    yy, xx = np.mgrid[0:h, 0:w]
    sky = (200.0 + 1800.0 * xx / w).astype(np.float32)
    stars = np.zeros(sky.shape)
    for _ in range(60):
        y0, x0 = rng.uniform(4, h - 4), rng.uniform(4, w - 4)
        stars += rng.uniform(2e3, 4e4) * np.exp(-((yy - y0) ** 2 + (xx - x0) ** 2) / (2 * 1.3 ** 2))
    stars = stars.astype(np.float32)
    photo = sky + stars
    echo = stars.copy()
    channel_crosstalk(echo, n, alpha, mirrored, delay, 0.0)
    echo -= stars
    model = photo + np.float32(sensor.bias_adu)
    var = (photo / sensor.gain_e_per_adu + (4.0 / sensor.gain_e_per_adu) ** 2).astype(np.float32)
    data = (model + echo + rng.normal(0, 1, sky.shape) * np.sqrt(var)).astype(np.float32)
    none = SpikeStats(0, 0, 0, 0, 0)
    res = Residuals(data, model, var, np.ones(sky.shape, bool), photo, np.zeros(sky.shape, np.float32),
                    np.arange(h, dtype=float), np.arange(w, dtype=float), sensor, 10.0, none, none,
                    background_adu=(sky + np.float32(sensor.bias_adu)).astype(np.float32), light_source="sky")
    np.testing.assert_allclose(crosstalk_signal(res), stars, atol=1e-2)
    fit = registry()["crosstalk"].signature.fit(res, "crosstalk")
    p = fit.params
    assert (p["n_channels"], p["mirrored"], p.get("delay_px", 0)) == (n, mirrored, delay)
    err = abs(p["alpha"]) / np.sqrt(-fit.delta_m2lnl)
    assert abs(p["alpha"] - alpha) < 4 * err + 0.05 * alpha
    assert fit.delta_bic < -100 and _crosstalk_check(fit, res) == ""
