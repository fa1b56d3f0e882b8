"""Fixtures of the scenes tests: the optics' own SIP fit and PSF grid (cached on disk by the design's hash)."""

import pytest


@pytest.fixture
def optics_sip(mi):
    """``optics.distortion.cached_sip`` (design, pitch_um, shape, order) -> the ``fit_sip`` dict."""
    from optics.distortion import cached_sip

    return cached_sip


@pytest.fixture
def optics_psf_grid(mi):
    """``optics.psf.cached_psf_grid`` (design, pitch_um, nx, ny) -> Path of a PSF cube."""
    from optics.psf import cached_psf_grid

    return cached_psf_grid
