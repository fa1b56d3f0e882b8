"""Sky-to-pixel projection: the frame's WCS (gnomonic TAN; SIP distortion comes with the optics).

FITS WCS conventions (Greisen & Calabretta 2002, A&A 395, 1061; Calabretta & Greisen 2002, A&A 395, 1077):
CRPIX is 1-based, so the centre of an ``nx x ny`` frame is ``((nx + 1) / 2, (ny + 1) / 2)``.
"""

from __future__ import annotations

import numpy as np
from astropy.wcs import WCS


def tan_wcs(ra_deg: float, dec_deg: float, roll_deg: float, scale_arcsec: float, shape: tuple[int, int]) -> WCS:
    """A TAN WCS centred on the frame, ``scale_arcsec`` per (output) pixel, north rotated by ``roll_deg``.

    East is to the left (``CD1_1 < 0``) for roll 0, as on the sky seen through a telescope with an even
    number of mirrors.
    """
    ny, nx = shape
    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    w.wcs.crval = [ra_deg, dec_deg]
    w.wcs.crpix = [(nx + 1) / 2.0, (ny + 1) / 2.0]
    s = scale_arcsec / 3600.0
    c, si = np.cos(np.radians(roll_deg)), np.sin(np.radians(roll_deg))
    w.wcs.cd = np.array([[-s * c, s * si], [s * si, s * c]])
    w.wcs.radesys = "ICRS"
    return w
