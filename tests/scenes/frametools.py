"""Helpers shared by the frame tests: measure isolated stars of a noiseless frame against its own WCS."""

import math

import numpy as np
from astropy.io import fits
from astropy.wcs import WCS


def isolated_stars(path, fwhm_px: float, min_flux_e: float = 2e3, radius_fwhm: float = 5.0) -> dict:
    """Centroids and sums of the isolated bright stars of a noiseless frame (sky and dark removed).

    A star is kept when its box of half-width r = radius_fwhm x FWHM + 1 lies inside the frame and no other
    TRUTH source brighter than 1e-4 of it lies within 3 r. Returns arrays ``cx, cy`` (measured first
    moments), ``x, y`` (the file's WCS applied to the TRUTH ra/dec), ``tx, ty`` (TRUTH x, y), ``sum`` and
    ``flux`` (TRUTH flux_e), in pixels of the written frame.
    """
    with fits.open(path) as hd:
        img = hd[0].data.astype(np.float64)
        hdr = hd[0].header
        t = hd["TRUTH"].data
    b = hdr["XBINNING"]
    img = img - (hdr["SKYRATE"] * b * b + hdr["DARKCUR"] * b * b) * hdr["EXPTIME"]
    xw, yw = WCS(hdr).all_world2pix(t["ra_deg"], t["dec_deg"], 0, tolerance=1e-9)
    r = math.ceil(radius_fwhm * fwhm_px) + 1
    out = {k: [] for k in ("cx", "cy", "x", "y", "tx", "ty", "sum", "flux")}
    for i in np.argsort(-t["flux_e"]):
        xi, yi, f = t["x"][i], t["y"][i], t["flux_e"][i]
        if not (r + 1 < xi < img.shape[1] - r - 2 and r + 1 < yi < img.shape[0] - r - 2) or f < min_flux_e:
            continue
        d = np.hypot(t["x"] - xi, t["y"] - yi)
        if np.any((d > 0) & (d < 3 * r) & (t["flux_e"] > 1e-4 * f)):
            continue
        ix, iy = round(xi), round(yi)
        stamp = img[iy - r:iy + r + 1, ix - r:ix + r + 1]
        yy, xx = np.mgrid[iy - r:iy + r + 1, ix - r:ix + r + 1]
        s = stamp.sum()
        for k, v in (("cx", (xx * stamp).sum() / s), ("cy", (yy * stamp).sum() / s), ("x", xw[i]), ("y", yw[i]),
                     ("tx", xi), ("ty", yi), ("sum", s), ("flux", f)):
            out[k].append(v)
    return {k: np.array(v) for k, v in out.items()}
