"""The frame's stars with photutils: background, detection, the PSF (FWHM, Moffat beta, ellipticity and their
variation over the field) and PSF-fit photometry.

* Background and its noise: ``photutils.background.Background2D`` (sigma-clipped medians in boxes, median
  filtered), sources masked.
* Detection: ``photutils.segmentation.detect_sources`` on the background-subtracted frame convolved with a
  Gaussian of the PSF's size, threshold ``nsigma`` x the background noise (Bertin & Arnouts 1996).
* PSF: elliptical Moffat fits (Moffat 1969; Trujillo et al. 2001, FWHM = 2 alpha sqrt(2^(1/beta) - 1)) of
  isolated, unsaturated stars, sampled on 3 x 3 sub-pixels (the scene integrates its PSF over pixels); the
  medians, and the FWHM as a quadratic function of the position (its variation over the field).
* Photometry: every star fitted with that PSF (flux, centre and local background free, saturated pixels
  left out), so the catalogue's fluxes are the total fluxes of the scene's own PSF (no aperture correction).
"""

from __future__ import annotations

import math
import warnings

import numpy as np


def moffat_alpha(fwhm_px: float, beta: float) -> float:
    return fwhm_px / (2.0 * math.sqrt(2.0 ** (1.0 / beta) - 1.0))


def subsamples(fwhm_px: float) -> int:
    """Sub-pixels per axis that integrate a PSF of ``fwhm_px`` over a pixel to better than ~0.5 %: 3 for a
    well-sampled PSF, more for an undersampled one (about 6 per FWHM)."""
    return int(np.clip(math.ceil(6.0 / max(fwhm_px, 0.5)), 3, 9))


def _sub(n: int = 3) -> np.ndarray:
    return (np.arange(n) + 0.5) / n - 0.5


def moffat_pixels(dx, dy, ax, ay, theta, beta, sub: int = 3) -> np.ndarray:
    """Pixel-averaged elliptical Moffat of unit total flux at offsets (dx, dy) [px] from its centre."""
    c, s = math.cos(theta), math.sin(theta)
    out = 0.0
    for ox in _sub(sub):
        for oy in _sub(sub):
            x, y = dx + ox, dy + oy
            u, v = x * c + y * s, -x * s + y * c
            out = out + (1 + (u / ax) ** 2 + (v / ay) ** 2) ** (-beta)
    return out / sub ** 2 * (beta - 1) / (math.pi * ax * ay)


def background(data: np.ndarray, mask: np.ndarray | None = None, box: int | None = None):
    """(background map, noise map) [ADU] by photutils' Background2D."""
    from astropy.stats import SigmaClip
    from photutils.background import Background2D, MedianBackground

    h, w = data.shape
    box = box or int(max(16, min(128, min(h, w) // 8)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        bkg = Background2D(data, (min(box, h), min(box, w)), mask=mask, filter_size=(3, 3),
                           sigma_clip=SigmaClip(sigma=3.0), bkg_estimator=MedianBackground())
    return np.asarray(bkg.background, float), np.asarray(bkg.background_rms, float)


def deblend_segments(conv: np.ndarray, seg, npix: int, star_fwhm_px: float, max_fwhm: float = 2.5,
                     max_elongation: float = 2.5, max_pieces: int = 3):
    """Multi-threshold deblending of the segments (SExtractor's: Bertin & Arnouts 1996, sect. 2.3; photutils'
    ``deblend_sources``, 32 exponential levels, contrast 0.001): two stars closer than the detection's
    footprint are two sources, not one with their mean centre and summed flux (an undersampled star field's
    bright stars swallow their neighbours at the detection threshold). A segment stays whole unless every
    piece is star-like (second-moment FWHM at most ``max_fwhm`` x the stars' and elongation at most
    ``max_elongation``) and there are at most ``max_pieces``: a galaxy, a nebula or a streak is one source
    (the mask's business), not a cluster of stars."""
    from photutils.segmentation import SourceCatalog, deblend_sources

    areas = np.bincount(seg.data.ravel())
    labels = [int(k) for k in seg.labels if areas[k] >= 2 * npix]
    if not labels:
        return seg
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        child = deblend_sources(conv, seg, npix, labels=labels, n_levels=32, contrast=0.001, progress_bar=False)
        t = SourceCatalog(conv, child).to_table(columns=["label", "fwhm", "elongation"])
    fw = np.asarray(getattr(t["fwhm"], "value", t["fwhm"]), float)
    el = np.asarray(t["elongation"], float)
    bad_child = np.zeros(int(child.data.max()) + 1, bool)
    bad_child[np.asarray(t["label"], int)] = ~((fw <= max_fwhm * star_fwhm_px) & (el <= max_elongation))
    parent, kid = seg.data.ravel(), child.data.ravel()
    on = parent > 0
    n_kids = np.zeros(int(parent.max()) + 1, int)
    pairs = np.unique(np.stack([parent[on], kid[on]]), axis=1)
    np.add.at(n_kids, pairs[0], 1)
    revert = np.zeros_like(n_kids, bool)
    np.logical_or.at(revert, pairs[0], bad_child[pairs[1]])
    split = (n_kids > 1) & (n_kids <= max_pieces) & ~revert
    if not split.any():
        return seg
    out = np.where(split[parent], kid + parent.max(), parent).reshape(seg.data.shape)
    from photutils.segmentation import SegmentationImage

    img = SegmentationImage(out.astype(np.int64))
    img.relabel_consecutive()
    return img


def detect(data: np.ndarray, bkg: np.ndarray, rms: np.ndarray, fwhm_px: float = 3.0, nsigma: float = 5.0,
           npix: int = 5, mask: np.ndarray | None = None, deblend: bool = False):
    """Segmentation of the background-subtracted frame (photutils), its SourceCatalog table as arrays;
    ``deblend``: blended segments split (:func:`deblend_segments`)."""
    from astropy.convolution import Gaussian2DKernel, convolve
    from photutils.segmentation import SourceCatalog, detect_sources

    sub = data - bkg
    sig = max(fwhm_px, 1.0) / 2.3548
    kern = Gaussian2DKernel(sig, x_size=int(4 * sig) * 2 + 3)
    kern.normalize()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        conv = convolve(np.where(mask, 0.0, sub) if mask is not None else sub, kern, normalize_kernel=False)
        noise = rms * math.sqrt(float(np.sum(kern.array ** 2)))
        seg = detect_sources(conv, nsigma * noise, n_pixels=npix, mask=mask)
    if seg is None:
        return None, {}
    if deblend:
        seg = deblend_segments(conv, seg, npix, max(fwhm_px, 1.0))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cat = SourceCatalog(sub, seg, convolved_data=conv, mask=mask)
        t = cat.to_table(columns=["label", "x_centroid", "y_centroid", "segment_flux", "max_value", "area",
                                  "fwhm", "elongation", "bbox_xmin", "bbox_xmax", "bbox_ymin", "bbox_ymax"])
    cols = {k: np.asarray(t[k].value if hasattr(t[k], "value") else t[k], float) for k in t.colnames}
    return seg, cols


def fit_psf_stars(data, bkg, seg, cols, saturation: float | np.ndarray, max_stars: int = 30, radius: int | None = None,
                  min_snr: float = 30.0, rms: np.ndarray | None = None) -> dict:
    """Elliptical Moffat fits of isolated, unsaturated, bright stars: medians of FWHM (quadratic mean of the
    axes), beta, ellipticity, position angle; per star rows; FWHM over the field (quadratic fit)."""
    from scipy import optimize

    h, w = data.shape
    fw0 = float(np.nanmedian(cols["fwhm"])) if len(cols.get("fwhm", [])) else 3.0
    # candidates of the stars' own size: cosmic rays and hot pixels (sharp) and blends or galaxies (wide) out
    typical = np.isfinite(cols["fwhm"]) & (cols["fwhm"] > 0.6 * fw0) & (cols["fwhm"] < 1.8 * fw0)
    R = radius or int(np.clip(round(3 * fw0), 5, 25))
    order = np.argsort(-cols["max_value"])
    rows, sharp = [], 0
    lab = seg.data
    for i in order:
        x, y = cols["x_centroid"][i], cols["y_centroid"][i]
        if not np.isfinite(x) or not np.isfinite(y) or not typical[i]:
            continue
        xi, yi = round(x), round(y)
        if xi < R or yi < R or xi >= w - R or yi >= h - R:
            continue
        sl = (slice(yi - R, yi + R + 1), slice(xi - R, xi + R + 1))
        st = data[sl]
        if not np.all(np.isfinite(st)) or np.any(st >= (saturation[sl] if np.ndim(saturation) else saturation)):
            continue
        other = (lab[sl] > 0) & (lab[sl] != int(cols["label"][i]))
        if other.any():
            continue
        b = bkg[sl]
        z = st - b
        noise = float(np.median(rms[sl])) if rms is not None else 1.0
        if cols["max_value"][i] < min_snr * noise:
            continue
        yy, xx = np.mgrid[sl]
        peak = float(z.max())

        nsub = subsamples(fw0)

        def model(p, xx=xx, yy=yy, nsub=nsub):
            f, x0, y0, ax, ay, th, beta, c = p
            return f * moffat_pixels(xx - x0, yy - y0, ax, ay, th, beta, sub=nsub) + c

        a0 = moffat_alpha(max(fw0, 1.5), 3.0)
        p0 = [max(float(z.sum()), peak), x, y, a0, a0, 0.0, 3.0, 0.0]
        lo = [0, x - 2, y - 2, 0.2, 0.2, -math.pi, 1.1, -10 * noise - abs(peak)]
        hi = [1e12, x + 2, y + 2, 50, 50, math.pi, 20, 10 * noise + abs(peak)]
        try:
            sigma = math.sqrt(noise ** 2 + 1e-9)
            r = optimize.least_squares(lambda p, z=z, s=sigma: ((model(p) - z) / s).ravel(),
                                       p0, bounds=(lo, hi), max_nfev=120, x_scale="jac")
        except ValueError:
            continue
        f, x0, y0, ax, ay, th, beta, c = r.x
        k = 2 * math.sqrt(2 ** (1 / beta) - 1)
        fa, fb = ax * k, ay * k
        if min(fa, fb) < 1.0:
            sharp += 1
            continue
        major, minor = max(fa, fb), min(fa, fb)
        pa = math.degrees(th if fa >= fb else th + math.pi / 2) % 180.0
        rows.append((x0, y0, math.sqrt((fa ** 2 + fb ** 2) / 2), major, minor, pa, beta, f))
        if len(rows) >= max_stars:
            break
    if len(rows) < 3:
        return {"n": len(rows), "ok": False}
    a = np.array(rows)
    out = {"n": len(rows), "ok": True, "fwhm_px": float(np.median(a[:, 2])), "beta": float(np.median(a[:, 6])),
           "fwhm_major_px": float(np.median(a[:, 3])), "fwhm_minor_px": float(np.median(a[:, 4])),
           "ellipticity": float(np.median(1 - a[:, 4] / a[:, 3])), "single_pixel_events": sharp,
           "fwhm_spread_px": float(np.std(a[:, 2])), "rows": a}
    ang = np.radians(2 * a[:, 5])
    out["pa_major_deg"] = float(np.degrees(np.arctan2(np.median(np.sin(ang)), np.median(np.cos(ang)))) / 2 % 180)
    # variation over the field: FWHM = c0 + c1 x + c2 y + c3 r^2 (x, y in units of the half-size)
    if len(rows) >= 8:
        xn, yn = (a[:, 0] - (w - 1) / 2) / (w / 2), (a[:, 1] - (h - 1) / 2) / (h / 2)
        M = np.stack([np.ones_like(xn), xn, yn, xn ** 2 + yn ** 2], axis=1)
        c, *_ = np.linalg.lstsq(M, a[:, 2], rcond=None)
        out["field"] = {"fwhm_centre_px": float(c[0]), "per_half_width_x_px": float(c[1]),
                        "per_half_height_y_px": float(c[2]), "at_corner_minus_centre_px": float(2 * c[3]),
                        "rms_about_fit_px": float(np.std(a[:, 2] - M @ c))}
    return out


def _moffat_and_grad(dx, dy, alpha: float, beta: float, sub: int = 3):
    """Pixel-averaged circular Moffat of unit flux and its derivatives with respect to the centre (cx, cy), at
    offsets ``dx = x - cx``, ``dy = y - cy`` (any shape), by ``sub`` x ``sub`` sub-pixel sampling."""
    k = (beta - 1) / (math.pi * alpha ** 2)
    p = gx = gy = 0.0
    for ox in _sub(sub):
        for oy in _sub(sub):
            x, y = dx + ox, dy + oy
            q = 1 + (x * x + y * y) / alpha ** 2
            v = q ** (-beta)
            d = 2 * beta * v / q / alpha ** 2  # -dP/dr^2 x 2, per unit k
            p = p + v
            gx = gx + d * x
            gy = gy + d * y
    n = sub * sub
    return k * p / n, k * gx / n, k * gy / n


def photometry(data, bkg, cols, fwhm_px: float, beta: float, saturation: float | np.ndarray, rms: np.ndarray,
               keep: np.ndarray | None = None, max_sources: int = 20000, iterations: int = 8) -> dict:
    """PSF-fit fluxes [ADU] (total flux of the scene's circular Moffat), centres, local background, S/N.

    Every star at once: weighted Gauss-Newton on (flux, x, y, background) with the analytic derivatives of the
    pixel-averaged Moffat, saturated and non-finite pixels weighted 0; steps limited to 1 px."""
    ax = moffat_alpha(fwhm_px, beta)
    R = int(np.clip(round(2.5 * fwhm_px), 4, 30))
    idx = np.flatnonzero(keep if keep is not None else np.ones(len(cols["x_centroid"]), bool))
    idx = idx[np.isfinite(cols["x_centroid"][idx]) & np.isfinite(cols["y_centroid"][idx])]
    idx = idx[np.argsort(-cols["segment_flux"][idx])][:max_sources]
    empty = {k: np.zeros(0) for k in ("i", "x", "y", "flux_adu", "flux_err_adu", "bkg_adu", "chi2_dof", "saturated")}
    if idx.size == 0:
        return empty
    pad = np.pad(data - bkg, R + 1, constant_values=np.nan)
    padraw = np.pad(data, R + 1, constant_values=np.nan)
    padn = np.pad(rms, R + 1, mode="edge")
    x0 = cols["x_centroid"][idx]
    y0 = cols["y_centroid"][idx]
    xi, yi = np.round(x0).astype(int), np.round(y0).astype(int)
    off = np.arange(-R, R + 1)
    YY = yi[:, None, None] + off[None, :, None] + R + 1
    XX = xi[:, None, None] + off[None, None, :] + R + 1
    z = pad[YY, XX]
    raw = padraw[YY, XX]
    if np.ndim(saturation):  # a clip per pixel (a colour frame divided by its cells' responses)
        satv = np.pad(np.asarray(saturation, float), R + 1, constant_values=np.inf)[YY, XX]
    else:
        satv = saturation
    ok = np.isfinite(z) & (raw < satv)
    n2 = np.median(padn[YY, XX].reshape(len(idx), -1), axis=1) ** 2
    zc = np.where(ok, z, 0.0)
    wgt = ok / (n2[:, None, None] + 0.02 * np.clip(zc, 0, None) + 1e-12)
    gx = (xi[:, None, None] + off[None, None, :]).astype(float)
    gy = (yi[:, None, None] + off[None, :, None]).astype(float)
    f = np.maximum(cols["segment_flux"][idx], 1.0).astype(float)
    cx, cy, c = x0.astype(float), y0.astype(float), np.zeros(len(idx))
    for _ in range(iterations):
        P, dPx, dPy = _moffat_and_grad(gx - cx[:, None, None], gy - cy[:, None, None], ax, beta, subsamples(fwhm_px))
        m = f[:, None, None] * P + c[:, None, None]
        r = zc - m
        J = np.stack([P, f[:, None, None] * dPx, f[:, None, None] * dPy, np.ones_like(P)], axis=-1)
        Jw = J * wgt[..., None]
        A = np.einsum("nyxi,nyxj->nij", Jw, J) + 1e-9 * np.eye(4)
        b = np.einsum("nyxi,nyx->ni", Jw, r)
        step = np.linalg.solve(A, b[..., None])[..., 0]
        f = np.maximum(f + step[:, 0], 0.0)
        cx = cx + np.clip(step[:, 1], -1, 1)
        cy = cy + np.clip(step[:, 2], -1, 1)
        c = c + step[:, 3]
    cx = np.clip(cx, x0 - 2.5, x0 + 2.5)
    cy = np.clip(cy, y0 - 2.5, y0 + 2.5)
    P, _, _ = _moffat_and_grad(gx - cx[:, None, None], gy - cy[:, None, None], ax, beta, subsamples(fwhm_px))
    res = (zc - f[:, None, None] * P - c[:, None, None]) ** 2 * wgt
    npx = ok.reshape(len(idx), -1).sum(axis=1)
    err = np.sqrt(n2 / np.maximum((P ** 2 * ok).reshape(len(idx), -1).sum(axis=1), 1e-12))
    sat = ((~ok) & np.isfinite(raw)).reshape(len(idx), -1).any(axis=1)
    # a saturated star: its wings alone under-determine the flux; the aperture sum (clipped core included) is
    # a lower bound, taken when larger
    r_ap = max(3.0 * fwhm_px, 4.0)
    inap = ((gx - cx[:, None, None]) ** 2 + (gy - cy[:, None, None]) ** 2 <= r_ap ** 2) & np.isfinite(z)
    ap_sum = (np.where(inap, z, 0.0) - np.where(inap, c[:, None, None], 0.0)).reshape(len(idx), -1).sum(axis=1)
    f = np.where(sat, np.maximum(f, ap_sum), f)
    good = npx >= 9
    return {"i": idx[good], "x": cx[good], "y": cy[good], "flux_adu": f[good], "flux_err_adu": err[good],
            "bkg_adu": c[good], "chi2_dof": (res.reshape(len(idx), -1).sum(axis=1) / np.maximum(npx - 4, 1))[good],
            "saturated": sat[good]}
