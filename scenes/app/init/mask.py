"""The mask of what a scene of point sources cannot model: extended sources (galaxies, nebulae) and
saturation bleeds.

* Extended sources: segments of a low-threshold detection (2 sigma, smoothed at twice the PSF) larger than
  ``min_psf_areas`` PSF areas (pi FWHM^2 / 4 each) whose light is not a star's: the segment's flux exceeds
  ``flux_excess`` x the PSF-fit flux of the stars inside it (a star's wings hold a fixed fraction of its
  light; a galaxy's do not). Masked with a margin of one FWHM.
* Bleeds: connected saturated pixels whose extent along the columns (or rows) is ``bleed_ratio`` x their width
  (charge spilling along the transfer direction, Janesick 2001, Scientific CCDs, sect. 5.3), with a
  margin of 2 px.
"""

from __future__ import annotations

import numpy as np


def extended_and_bleeds(data, bkg, rms, fwhm_px: float, saturation: float | np.ndarray, star_xy_flux=None, *,
                        min_psf_areas: float = 40.0, flux_excess: float = 3.0, bleed_ratio: float = 3.0,
                        nsigma: float = 2.0) -> tuple[np.ndarray, dict]:
    """(mask, info): boolean mask of extended sources and bleeds, and what was masked."""
    from scipy import ndimage

    from .stars import detect

    h, w = data.shape
    mask = np.zeros((h, w), bool)
    info = {"extended": [], "bleeds": []}
    seg, cols = detect(data, bkg, rms, fwhm_px=2 * fwhm_px, nsigma=nsigma, npix=int(min_psf_areas))
    psf_area = np.pi * fwhm_px ** 2 / 4
    if seg is not None and len(cols):
        big = np.flatnonzero(cols["area"] > min_psf_areas * psf_area)
        sx, sy, sf = star_xy_flux if star_xy_flux is not None else (np.zeros(0), np.zeros(0), np.zeros(0))
        lab = seg.data
        for i in big:
            label = int(cols["label"][i])
            inside = np.zeros(0, bool)
            if sx.size:
                xi, yi = np.clip(np.round(sx).astype(int), 0, w - 1), np.clip(np.round(sy).astype(int), 0, h - 1)
                inside = lab[yi, xi] == label
            star_flux = float(sf[inside].sum()) if inside.size else 0.0
            seg_flux = float(cols["segment_flux"][i])
            if seg_flux > flux_excess * max(star_flux, 0.0):
                m = lab == label
                mask |= ndimage.binary_dilation(m, iterations=max(1, round(fwhm_px)))
                info["extended"].append({"x": float(cols["x_centroid"][i]), "y": float(cols["y_centroid"][i]),
                                         "area_px": int(cols["area"][i]), "segment_flux_adu": seg_flux,
                                         "stars_flux_adu": star_flux})
    sat = np.isfinite(data) & (data >= saturation)
    if sat.any():
        lab, _ = ndimage.label(sat)
        for k, sl in enumerate(ndimage.find_objects(lab), start=1):
            hh, ww = sl[0].stop - sl[0].start, sl[1].stop - sl[1].start
            if max(hh, ww) >= bleed_ratio * max(min(hh, ww), 1) and max(hh, ww) >= 6:
                m = lab[sl] == k
                region = np.zeros_like(mask)
                region[sl] = m
                mask |= ndimage.binary_dilation(region, iterations=2)
                info["bleeds"].append({"x0": int(sl[1].start), "y0": int(sl[0].start), "width": int(ww), "height": int(hh)})
    info["masked_fraction"] = float(mask.mean())
    return mask, info
