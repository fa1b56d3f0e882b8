"""The mask of what a scene of point sources cannot model: extended sources (galaxies, nebulae) and
saturation bleeds.

* Extended sources: segments of a low-threshold detection (2 sigma, smoothed at twice the PSF) larger than
  ``min_psf_areas`` PSF areas (pi FWHM^2 / 4 each) whose light is not a star's: the segment's flux exceeds
  ``flux_excess`` x the PSF-fit flux of the stars inside it (a star's wings hold a fixed fraction of its
  light; a galaxy's do not). Masked with a margin of one FWHM.
* Bleeds: connected saturated pixels whose extent along the columns (or rows) is ``bleed_ratio`` x their width
  (charge spilling along the transfer direction, Janesick 2001, Scientific CCDs, sect. 5.3), with a
  margin of :data:`SATURATED_MARGIN_PX`.
* Saturated cores: every other group of saturated pixels (a saturated star's core, whatever its shape), with the
  same margin: a pixel at or above the saturation level (the header's ``SATURATE`` or the clip seen in the
  data, less 5 read-noise sigma) holds no measurement of the light, and its neighbours take the charge it
  blooms and sit in the non-linear range just below full well. The star itself stays in the catalogue (its
  flux is fitted from its unsaturated wings: :func:`.stars.photometry`), so the returned mask of the cores is
  kept apart (``info["core_mask"]``) from what removes sources.
* Sources broader than the frame's PSF (:func:`broad_sources`): a galaxy, an unresolved double or a nebulous
  object among the stars, which the scene's point sources cannot draw.
"""

from __future__ import annotations

import math

import numpy as np

#: margin [px] about saturated pixels (bleeds and cores), every pixel within it by a side or a corner (a square):
#: blooming spills charge into the adjacent pixel along the transfer direction (Janesick 2001, sect. 5.3) and
#: the pixels beside a clipped one sit near full well (non-linear); one more pixel for the clipped region's
#: position within its pixel (on the LCO 0.4 m frame the corner pixels of a diamond-shaped margin about its 3
#: saturated ones kept residuals of 48-75 sigma each)
SATURATED_MARGIN_PX = 2


def extended_and_bleeds(data, bkg, rms, fwhm_px: float, saturation: float | np.ndarray, star_xy_flux=None, *,
                        min_psf_areas: float = 40.0, flux_excess: float = 3.0, bleed_ratio: float = 3.0,
                        nsigma: float = 2.0) -> tuple[np.ndarray, dict]:
    """(mask, info): boolean mask of extended sources and bleeds (what removes the sources under it), and what was
    masked: ``info["extended"]``, ``info["bleeds"]``, ``info["saturated_cores"]`` (every other group of pixels at
    or above ``saturation``: centre and size), ``info["core_mask"]`` (those cores grown by SATURATED_MARGIN_PX,
    outside ``mask``: the caller masks them but keeps their stars) and ``info["masked_fraction"]`` (of both)."""
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
    cores = np.zeros((h, w), bool)
    info["saturated_cores"] = []
    if sat.any():
        lab, _ = ndimage.label(sat)
        g = SATURATED_MARGIN_PX
        for k, sl in enumerate(ndimage.find_objects(lab), start=1):
            hh, ww = sl[0].stop - sl[0].start, sl[1].stop - sl[1].start
            m = lab[sl] == k
            # the region grown by the margin (a square), within its box widened by the margin
            y0, x0 = max(sl[0].start - g, 0), max(sl[1].start - g, 0)
            box = (slice(y0, min(sl[0].stop + g, h)), slice(x0, min(sl[1].stop + g, w)))
            grown = np.zeros((box[0].stop - y0, box[1].stop - x0), bool)
            grown[sl[0].start - y0:sl[0].stop - y0, sl[1].start - x0:sl[1].stop - x0] = m
            grown = ndimage.binary_dilation(grown, structure=np.ones((3, 3), bool), iterations=g)
            if max(hh, ww) >= bleed_ratio * max(min(hh, ww), 1) and max(hh, ww) >= 6:
                mask[box] |= grown
                info["bleeds"].append({"x0": int(sl[1].start), "y0": int(sl[0].start), "width": int(ww), "height": int(hh)})
            else:
                cores[box] |= grown
                yc, xc = ndimage.center_of_mass(m)
                info["saturated_cores"].append({"x": float(sl[1].start + xc), "y": float(sl[0].start + yc),
                                                "saturated_px": int(m.sum())})
    info["core_mask"] = cores & ~mask
    info["masked_fraction"] = float((mask | cores).mean())
    return mask, info


#: aperture radius of the size measurement [FWHM]: at least 95 % of a Moffat's light (beta >= 2.5) lies within it
SIZE_APERTURE_FWHM = 2.5
#: the smallest size aperture [px] (an undersampled PSF: the pixels' own width)
SIZE_APERTURE_MIN_PX = 3.0
#: S/N of the aperture flux above which a star joins the reference population: its size's own noise, of order
#: 1 / (S/N) of the size (2 %), no more than the PSF's spread over a field
SIZE_REFERENCE_SNR = 50.0
#: the fewest reference stars for a population to test against: the robust spread (1.4826 MAD) of 8 normal values
#: has a relative standard error of about 40 %, which a 5-sigma cut tolerates
SIZE_MIN_REFERENCE = 8
#: a source broader than the reference median by more than this many standard deviations (the population's
#: robust spread and the source's own measurement error in quadrature): a one-sided Gaussian tail of 2.9e-7,
#: so a frame of 10^4 ordinary stars expects 0.003 false ones
SIZE_NSIGMA = 5.0
#: and broader by at least this factor (second-moment radius): beyond the PSF's variation over a field of a
#: corrected telescope (under 10 %); an equal pair d apart adds d^2 / 8 to the mean of the two axes' variances,
#: so this is a pair 0.8 FWHM apart for a Gaussian PSF (d = sqrt(8 (1.2^2 - 1)) sigma), about 1.2 FWHM in the
#: aperture's moments of a Moffat (its wings weigh in the second moment)
SIZE_FACTOR = 1.2


def source_sizes(data, bkg, rms, seg, cols, fwhm_px: float, saturation: float | np.ndarray,
                 gain: float | None = None) -> dict:
    """Second-moment radius ``sqrt((Mxx + Myy) / 2)`` [px] of every detected source, in a circular aperture of
    :data:`SIZE_APERTURE_FWHM` FWHM about its centroid, background subtracted, with its standard error from the
    pixels' noise (the background's and the source's Poisson variance ``I / gain``; the centroid's error
    neglected). A source whose aperture holds a non-finite pixel, a saturated pixel or a pixel of another
    segment is not measured (``ok`` false): a clipped core's moments are not its PSF's, a neighbour's
    light is not its own."""
    h, w = data.shape
    n = len(cols.get("x_centroid", []))
    out = {k: np.full(n, np.nan) for k in ("x", "y", "size_px", "size_err_px", "snr")}
    out["ok"] = np.zeros(n, bool)
    if n == 0:
        return out
    r = max(SIZE_APERTURE_FWHM * fwhm_px, SIZE_APERTURE_MIN_PX)
    R = math.ceil(r)
    satmap = np.broadcast_to(np.asarray(saturation, float), data.shape)
    sub = data - bkg
    lab = seg.data
    off = np.arange(-R, R + 1)
    for i in range(n):
        x, y = float(cols["x_centroid"][i]), float(cols["y_centroid"][i])
        out["x"][i], out["y"][i] = x, y
        if not (math.isfinite(x) and math.isfinite(y)):
            continue
        xi, yi = round(x), round(y)
        if xi < R or yi < R or xi >= w - R or yi >= h - R:
            continue
        sl = (slice(yi - R, yi + R + 1), slice(xi - R, xi + R + 1))
        yy, xx = np.meshgrid(yi + off, xi + off, indexing="ij")
        ap = (xx - x) ** 2 + (yy - y) ** 2 <= r * r
        st, raw = sub[sl], data[sl]
        if (not np.all(np.isfinite(raw[ap])) or np.any(raw[ap] >= satmap[sl][ap])
                or np.any((lab[sl][ap] > 0) & (lab[sl][ap] != int(cols["label"][i])))):
            continue
        z = st[ap]
        f = float(z.sum())
        if f <= 0:
            continue
        cx, cy = float((z * xx[ap]).sum() / f), float((z * yy[ap]).sum() / f)
        rho2 = ((xx[ap] - cx) ** 2 + (yy[ap] - cy) ** 2) / 2.0
        s2 = float((z * rho2).sum() / f)
        if s2 <= 0:
            continue
        var = rms[sl][ap] ** 2 + (np.clip(z, 0, None) / gain if gain else 0.0)
        se_s2 = math.sqrt(float((var * (rho2 - s2) ** 2).sum())) / f
        out["size_px"][i] = math.sqrt(s2)
        out["size_err_px"][i] = se_s2 / (2 * math.sqrt(s2))
        out["snr"][i] = f / math.sqrt(float(var.sum()))
        out["ok"][i] = True
    return out


def broad_sources(data, bkg, rms, seg, cols, fwhm_px: float, saturation: float | np.ndarray,
                  gain: float | None = None) -> tuple[np.ndarray, dict]:
    """(mask, info): the sources significantly broader than the frame's point sources.

    The reference is the frame's own bright stars: the sources of :func:`source_sizes` measured at S/N above
    :data:`SIZE_REFERENCE_SNR` (isolated and unsaturated by that measurement); their median size ``m`` and robust
    spread ``s`` (1.4826 x the median absolute deviation: the PSF's variation over the field and the pixel
    phase of an undersampled PSF included). A source is broad when its size exceeds ``m`` by
    :data:`SIZE_NSIGMA` x sqrt(s^2 + its own error^2) AND by the factor :data:`SIZE_FACTOR`: a galaxy, an
    unresolved double or a nebulous object, which the scene's PSF cannot draw. Each is masked (its detection
    segment grown by the mask's margin, at least :data:`SATURATED_MARGIN_PX`, one FWHM on a wider PSF) and
    listed; with fewer than :data:`SIZE_MIN_REFERENCE` reference stars nothing is tested."""
    from scipy import ndimage

    h, w = data.shape
    mask = np.zeros((h, w), bool)
    sz = source_sizes(data, bkg, rms, seg, cols, fwhm_px, saturation, gain)
    ref = sz["ok"] & (sz["snr"] >= SIZE_REFERENCE_SNR)
    info: dict = {"n_reference": int(ref.sum()), "sources": []}
    if ref.sum() < SIZE_MIN_REFERENCE:
        info["note"] = f"{int(ref.sum())} reference stars (fewer than {SIZE_MIN_REFERENCE}): not tested"
        return mask, info
    m = float(np.median(sz["size_px"][ref]))
    s = 1.4826 * float(np.median(np.abs(sz["size_px"][ref] - m)))
    info.update(reference_size_px=m, reference_spread_px=s, aperture_px=max(SIZE_APERTURE_FWHM * fwhm_px,
                                                                             SIZE_APERTURE_MIN_PX))
    sig = np.sqrt(s * s + np.nan_to_num(sz["size_err_px"], nan=np.inf) ** 2)
    excess = (sz["size_px"] - m) / np.where(sig > 0, sig, np.inf)
    broad = sz["ok"] & (sz["size_px"] > SIZE_FACTOR * m) & (excess > SIZE_NSIGMA)
    margin = max(SATURATED_MARGIN_PX, math.ceil(fwhm_px))
    lab = seg.data
    areas = np.bincount(lab.ravel())
    labels = [int(cols["label"][i]) for i in np.flatnonzero(broad)]
    if labels:
        mask = ndimage.binary_dilation(np.isin(lab, labels), iterations=margin)
    for i, label in zip(np.flatnonzero(broad), labels):
        info["sources"].append({"x": float(sz["x"][i]), "y": float(sz["y"][i]), "size_px": float(sz["size_px"][i]),
                                "size_ratio": float(sz["size_px"][i] / m), "excess_sigma": float(excess[i]),
                                "snr": float(sz["snr"][i]), "area_px": int(areas[label])})
    return mask, info
