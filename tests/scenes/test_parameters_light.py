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
