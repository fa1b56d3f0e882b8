"""Image formation: stars and debris streaks as PSF-integrated point samples on the detector.

* :mod:`scenes.image.psf`: Gaussian and Moffat PSFs integrated exactly (or to a bounded error) over the
  pixels (thesis eqs. 4, 48, 51-52), and the hook for other PSFs (``psf(x, y, dx, dy)``);
* :mod:`scenes.image.gridpsf`: the optics' PSF grid (``[psf] model = "optics"``) through that hook: exact
  pixel integration of the cube's cells, centroid-centred stamps, bilinear interpolation over the field;
* :mod:`scenes.image.motion`: telescope tracking (sidereal, rate, none), sky-to-pixel at any time through
  the file's WCS, rolling-shutter exposure windows (thesis eq. 10);
* :mod:`scenes.image.signal`: the y-sorted sample list and the thread-safe tile callable
  ``signal(y0, y1, x0, x1)`` that the detector chain consumes;
* :mod:`scenes.image.build`: a scene's stars (``scenes.sky``) and objects (``scenes.objects``) to samples
  and the TRUTH table.

Equations, conventions and validation numbers: ``docs/scenes.md``.
"""

from .build import TRUTH_DTYPE, SourceModel, band, build_sources, frame_wcs
from .motion import (
    SIDEREAL_RATE_DEG_S,
    Boresight,
    sample_times,
    window_overlap,
    world_to_pixel,
)
from .psf import (
    GAUSS_FWHM,
    MOFFAT_BETA_KOLMOGOROV,
    GaussianPSF,
    MoffatPSF,
    PixelPSF,
    gaussian_pixel_fractions,
    normal_interval_mass,
    psf_from_config,
)
from .signal import Samples, SourceSignal, render_samples

__all__ = [
    "GAUSS_FWHM", "MOFFAT_BETA_KOLMOGOROV", "SIDEREAL_RATE_DEG_S", "TRUTH_DTYPE", "Boresight", "GaussianPSF",
    "MoffatPSF", "PixelPSF", "Samples", "SourceModel", "SourceSignal", "band", "build_sources", "frame_wcs",
    "gaussian_pixel_fractions", "normal_interval_mass", "psf_from_config", "render_samples", "sample_times",
    "window_overlap", "world_to_pixel",
]
