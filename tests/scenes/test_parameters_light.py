"""A zero point scales a star's whole light; a PSF change moves it (scenes.app.compare.parameters.light_moved)."""

import numpy as np
import pytest
from helpers import gaussian_stars as _stars


def _residuals(data, model, background, noise=3.0):
    from types import SimpleNamespace

    return SimpleNamespace(data_adu=data, model_adu=model, background_adu=background, photo_adu=model - background,
                           var_adu2=np.full(data.shape, noise ** 2), fit=np.ones(data.shape, bool),
                           without_sources_adu=background, saturated=np.zeros(data.shape, bool))


def test_light_moved_into_far_wings_is_not_a_zero_point():
    """A blur with far wings keeps each star's light: its cores fit a zero point of ~0.75, their whole light (an
    aperture with a background ring, as photometry measures it) 1; a real zero point scales both."""
    from scenes.app.compare.parameters import enclosed_ratio, light_moved
    from scenes.app.compare.policy import DEFAULT_POLICY

    fluxes = np.geomspace(2e4, 4e5, 6)
    sky = 100.0
    model = _stars(1.5, fluxes, shape=(160, 240), spacing=60) + sky
    bg = np.full(model.shape, sky)
    wings = 0.75 * _stars(1.5, fluxes, (160, 240), 60) + 0.25 * _stars(6.0, fluxes, (160, 240), 60) + sky
    rng = np.random.default_rng(3)
    moved = _residuals(wings + rng.normal(0, 3, model.shape), model, bg)
    ratio, err, grow = enclosed_ratio(moved)
    assert ratio == pytest.approx(1.0, abs=0.02) and grow == 16
    assert "moved out of them" in light_moved(moved, 0.75, DEFAULT_POLICY)
    darker = _residuals(0.75 * (model - sky) + sky + rng.normal(0, 3, model.shape), model, bg)
    assert enclosed_ratio(darker)[0] == pytest.approx(0.75, abs=0.01)
    assert light_moved(darker, 0.75, DEFAULT_POLICY) == ""


def test_the_psf_width_scan_gives_its_standard_error():
    """The PSF's width is refitted when its likelihood scan measures it (no count of stars): -2 ln L rising as
    (ln x / 0.02)^2 has a standard error 0.02 in ln x, wherever the scan's lowest point is; a flat scan none."""
    from scenes.app.compare.parameters import PSF_STEPS, width_error

    x = np.sort(np.array((1.0, *PSF_STEPS)))
    y = (np.log(x) / 0.02) ** 2
    assert width_error(x, y, int(np.argmin(y))) == pytest.approx(0.02, rel=1e-6)
    y_edge = (np.log(x / 1.4) / 0.02) ** 2
    assert width_error(x, y_edge, int(np.argmin(y_edge))) == pytest.approx(0.02, rel=1e-6)
    assert width_error(x, np.zeros_like(x), 0) == np.inf


def test_a_level_a_later_significant_effect_explains_is_that_effects_doing():
    """A glow in one corner of a dark frame raises the fitted dark level x 1.19, beyond the scene's tolerance. The
    first significant effect in the judge's order (hot pixels: a few spikes, scored by their delta BIC) does not
    move that level, the second (the glow) does: the level is the glow's doing whichever comes first (the
    large-frame path, which fits the pixel-scale effects apart, asked the glow; the full-resolution path asked
    the hot pixels alone and named the dark level)."""
    from helpers import residuals_of, small_sensor

    from detector.signatures import Fit
    from scenes.app.compare.judge import Candidate
    from scenes.app.compare.parameters import _param_candidate, explained_away, level_fit
    from scenes.app.compare.policy import DEFAULT_POLICY

    shape = (96, 128)
    s = small_sensor(width=shape[1], height=shape[0], bias_adu=100.0)
    rng = np.random.default_rng(5)
    y, x = np.mgrid[: shape[0], : shape[1]]
    dark_adu = 20.0 + 10.0 * x / shape[1]  # a dark with a column ramp: told from a bias offset
    glow = 40.0 * np.exp(-((shape[0] - y) + (shape[1] - x)) / 12.0)
    model = s.bias_adu + dark_adu
    var = np.full(shape, 4.0)
    data = model + glow + rng.normal(0, 2.0, shape)
    res = residuals_of(data, model, var, np.zeros(shape), s)
    res.dark_e = (dark_adu * res.gain).astype(np.float32)
    coef, stat = level_fit(res)["dark_scale"]
    assert coef > DEFAULT_POLICY.parameter_scale_tolerance and stat > 100
    assert abs(level_fit(res, glow)["dark_scale"][0]) <= DEFAULT_POLICY.parameter_scale_tolerance
    level = _param_candidate(res, "dark_level", "detector.dark_current_e_per_s", 1.0 + coef, stat, "the dark", "",
                             DEFAULT_POLICY, 0.0, "dark_scale")
    spikes = np.zeros(shape)
    spikes[10, 10] = spikes[50, 70] = 500.0
    hot = Candidate(Fit("hot_pixels", {}, -1e5, 2, res.n_fit, "spikes", delta_adu=spikes), 1.0, 0.0)
    glowing = Candidate(Fit("amp_glow", {}, -5e3, 3, res.n_fit, "glow", delta_adu=glow), 1.0, 0.0)
    assert level.significant and hot.significant and glowing.significant
    explained_away([level], [hot, glowing], res, None)
    assert not level.significant and "amp_glow" in level.codes["tolerance"], level.codes
