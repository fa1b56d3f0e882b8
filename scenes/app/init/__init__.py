"""``newtsim init``: a scene from a user's own frame, calibration frames and header.

* :mod:`.header` the header's conventions (gain, binning, temperature, pixel size, date, site, filter, window,
  bit depth and saturation)
* :mod:`.wcs`    the WCS (TAN, TAN-SIP, TPV; CD or PC + CDELT) as pointing, roll, scale, parity and SIP
* :mod:`.calib`  overscan trimming and the camera from any subset of bias, dark and flat frames
* :mod:`.stars`  photutils background, detection, PSF (FWHM, beta, variation) and PSF-fit photometry
* :mod:`.mask`   extended sources and saturation bleeds
* :mod:`.optics` a lens / refractor / reflector as a design
* :mod:`.writer` the commented scene and its files
* :mod:`.build`  :func:`init_scene`, which does it all
"""

from .build import InitResult, init_scene
from .writer import scene_text, write_file

__all__ = ["InitResult", "init_scene", "scene_text", "write_file"]
