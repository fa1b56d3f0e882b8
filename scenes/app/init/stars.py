"""The frame's stars with photutils: background, detection, the PSF (FWHM, Moffat beta, ellipticity and their
variation over the field) and PSF-fit photometry.

* Background and its noise: ``photutils.background.Background2D`` (sigma-clipped medians in boxes, median
  filtered), sources masked.
* Detection: ``photutils.segmentation.detect_sources`` on the background-subtracted frame convolved with a
  Gaussian of the PSF's size, threshold ``nsigma`` x the background noise (Bertin & Arnouts 1996).
* PSF: elliptical Moffat fits (Moffat 1969; Trujillo et al. 2001, FWHM = 2 alpha sqrt(2^(1/beta) - 1)) of
  isolated, unsaturated stars, sampled on 3 x 3 sub-pixels (the scene integrates its PSF over pixels); the
  medians, and the FWHM as a quadratic function of the position (its variation over the field).
* Photometry: every star fitted with the scene's own PSF (the round Moffat, filtered by the elongation's
  covariance when the scene carries ``[effects.psf_elongation]``; flux, centre and local background free,
  weighted by the model's variance), so the catalogue's fluxes are the total fluxes of the scene's own stars
  (no aperture correction). A saturated star is fitted from its unsaturated wings alone (the clipped pixels
  left out, as photutils' PSF photometry with a mask; Stetson 1987, DAOPHOT), its centre started at its
  clipped plateau's centroid, its neighbours' models subtracted and the background held at the sky measured
  with every star's model removed.
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
                                  "fwhm", "elongation", "bbox_xmin", "bbox_xmax", "bbox_ymin", "bbox_ymax",
                                  "max_value_xindex", "max_value_yindex"])
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


def _moffat_value(dx, dy, alpha: float, beta: float, sub: int = 3):
    """:func:`_moffat_and_grad`'s value alone (the models drawn, not fitted)."""
    p = 0.0
    for ox in _sub(sub):
        for oy in _sub(sub):
            x, y = dx + ox, dy + oy
            p = p + (1 + (x * x + y * y) / alpha ** 2) ** (-beta)
    return (beta - 1) / (math.pi * alpha ** 2) * p / (sub * sub)


def elongation_cov_px2(psf: dict, fwhm_px: float) -> np.ndarray:
    """The measured elliptical PSF as the round one of FWHM ``fwhm_px`` (the quadratic mean of the axes) plus a
    second-moment change ``dC`` [output px^2, (x, y)]: the Gaussian-equivalent variances of the major and minor
    axes (FWHM^2 / (8 ln 2)) about the round one's, rotated to the major axis. What the scene renders as
    ``[effects.psf_elongation]`` (its ``dcxx, dcyy, dcxy`` are this x binning^2, in sensor pixels)."""
    k = 8.0 * math.log(2.0)
    d1 = (psf["fwhm_major_px"] ** 2 - fwhm_px ** 2) / k
    d2 = (psf["fwhm_minor_px"] ** 2 - fwhm_px ** 2) / k
    c, s = math.cos(math.radians(psf["pa_major_deg"])), math.sin(math.radians(psf["pa_major_deg"]))
    return np.array([[d1 * c * c + d2 * s * s, (d1 - d2) * s * c], [(d1 - d2) * s * c, d1 * s * s + d2 * c * c]])


def _psf_and_grad(gx, gy, cx, cy, alpha: float, beta: float, sub: int, cov: np.ndarray | None, extra=None):
    """The scene's PSF (pixel-averaged circular Moffat, then, when ``cov`` is given, filtered by the Gaussian of
    covariance ``cov`` as ``[effects.psf_elongation]`` renders it: ``H(f) = min(exp(-2 pi^2 f^T C f), 50)``, a
    capped deconvolution along a narrowing axis; then, when ``extra = (transfer, pad)`` is given, by that
    effect's further transfer function, e.g. its displaced halo,
    :func:`detector.effects.image_plane.displaced_halo_transfer`) of unit flux, and its derivatives with respect
    to the centre, on the stamps of pixel coordinates ``gx, gy`` (n, H, W) centred at ``cx, cy`` (n,).

    The filter acts on each star's stamp extended by the elongation's reach (4 sigma of its largest axis), where
    the Moffat is evaluated exactly, and by half the extra filter's reach in zeros (the FFT is cyclic: light
    moved by less than the stamp plus twice that margin does not wrap onto the stamp), then cropped: the star as the scene draws it, less the extra filter's share
    of the Moffat's far wings beyond the stamp (PANOPTES: 18 % of the 7 % beyond 7 px) (the filter commutes with
    the shift, so the centre derivatives are the filtered ones)."""
    if cov is None and extra is None:
        return _moffat_and_grad(gx - cx[:, None, None], gy - cy[:, None, None], alpha, beta, sub)
    from detector.effects.image_plane import ELONGATION_MAX_GAIN

    n = np.shape(cx)[0]
    if n > FILTER_CHUNK:  # the extended stamps of every star at once: memory bounded by chunks
        parts = [_psf_and_grad(gx[i:i + FILTER_CHUNK], gy[i:i + FILTER_CHUNK], cx[i:i + FILTER_CHUNK],
                               cy[i:i + FILTER_CHUNK], alpha, beta, sub, cov, extra) for i in range(0, n, FILTER_CHUNK)]
        return tuple(np.concatenate([p[k] for p in parts]) for k in range(3))
    cov = np.zeros((2, 2)) if cov is None else cov
    ev = np.linalg.eigvalsh(cov)
    pc = math.ceil(4 * math.sqrt(max(float(np.max(np.abs(ev))), 0.0))) + 1
    # a cyclic filter of reach r moves no light of the stamp back onto it when the zeros about it are r / 2 wide
    pe = int(math.ceil(extra[1] / 2)) if extra is not None else 0
    pad = pc + pe
    H, W = np.shape(gy)[1], np.shape(gx)[2]  # the grids may be broadcast: (n, 1, W) and (n, H, 1)
    ex = gx[:, :1, :1] + np.arange(-pc, W + pc)[None, None, :]
    ey = gy[:, :1, :1] + np.arange(-pc, H + pc)[None, :, None]
    P, dPx, dPy = _moffat_and_grad(ex - cx[:, None, None], ey - cy[:, None, None], alpha, beta, sub)
    if pe:  # the extra filter's reach: zeros (no wrap-around of the halo), the Moffat's far wings left out
        P, dPx, dPy = (np.pad(a, ((0, 0), (pe, pe), (pe, pe))) for a in (P, dPx, dPy))
    fy = np.fft.fftfreq(H + 2 * pad)[:, None]
    fx = np.fft.rfftfreq(W + 2 * pad)[None, :]
    q = cov[0, 0] * fx * fx + 2 * cov[0, 1] * fx * fy + cov[1, 1] * fy * fy
    tf = np.minimum(np.exp(-2 * np.pi ** 2 * q), ELONGATION_MAX_GAIN)
    if extra is not None:
        tf = tf * extra[0](fx, fy)
    shape = (H + 2 * pad, W + 2 * pad)
    out = [np.fft.irfft2(np.fft.rfft2(a, axes=(-2, -1)) * tf, s=shape, axes=(-2, -1))[:, pad:pad + H, pad:pad + W]
           for a in (P, dPx, dPy)]
    return out[0], out[1], out[2]


def _filter_image(img: np.ndarray, cov: np.ndarray | None, extra=None) -> np.ndarray:
    """``img`` filtered by the elongation's Gaussian of covariance ``cov`` (capped as the effect's) and the extra
    filter ``(transfer, pad)``, the frame's edges extended (:func:`detector.effects.image_plane.fourier_filter`)."""
    from detector.effects.image_plane import ELONGATION_MAX_GAIN, fourier_filter

    cov = np.zeros((2, 2)) if cov is None else np.asarray(cov, float)
    ev = np.linalg.eigvalsh(cov)
    pad = math.ceil(4 * math.sqrt(max(float(np.max(np.abs(ev))), 0.0))) + 1 + (int(extra[1]) if extra is not None else 0)

    def transfer(fx, fy):
        q = cov[0, 0] * fx * fx + 2 * cov[0, 1] * fx * fy + cov[1, 1] * fy * fy
        tf = np.minimum(np.exp(-2 * np.pi ** 2 * q), ELONGATION_MAX_GAIN)
        return tf * extra[0](fx, fy) if extra is not None else tf

    return fourier_filter(img, pad, transfer)


#: stars filtered at once by :func:`_psf_and_grad` (their extended stamps held in memory together)
FILTER_CHUNK = 400


#: a star found in the residual: its matched-filter S/N at least this ...
RESIDUAL_STAR_SNR = 5.0
#: ... and its light at least this share of the model's light there (a bright star's model misfits its own core,
#: wings or halo by a part of its light: 13-20 % on the PANOPTES frame's brightest; a missed neighbour is light
#: the model does not have at all)
RESIDUAL_STAR_MODEL_SHARE = 0.3


def residual_stars(data, bkg, phot: dict, fwhm_px: float, beta: float, cov: np.ndarray | None, rms: np.ndarray,
                   gain: float | None = None, saturation: float | np.ndarray = np.inf, extra=None,
                   mask: np.ndarray | None = None, iterations: int = 8) -> dict:
    """Stars the detection missed, found in the frame's residual once every fitted star's model (the scene's PSF)
    is subtracted: the iterative form of PSF photometry (photutils' ``IterativePSFPhotometry``; Stetson 1987,
    PASP 99, 191, DAOPHOT's second pass of FIND on the subtracted frame), which finds the neighbours a
    segment kept whole with a brighter star (a faint star a few pixels from a saturated one, whose segment the
    deblending does not split) and fits them.

    The residual is filtered by the PSF's Gaussian-equivalent kernel (a matched filter: S/N = sum K r /
    sqrt(sum K^2 var), var = rms^2 + model / gain); a peak (the largest within one FWHM) is a star when its S/N
    is at least :data:`RESIDUAL_STAR_SNR`, its filtered light at least :data:`RESIDUAL_STAR_MODEL_SHARE` of the
    filtered model there, it lies outside ``mask`` and more than 1.5 FWHM from every fitted star (a misfit core
    is not a star); then it is fitted (flux, centre, local background) on the residual with the scene's PSF and
    kept at a flux S/N of 5. The stars within reach of a new one are fitted again with it subtracted (the
    saturated ones, fitted from their wings, are kept). Returns ``phot`` with the new stars appended and
    ``"added"``: their count."""
    from scipy import ndimage

    h, w = data.shape
    n0 = len(phot["x"])
    out = {k: np.asarray(v).copy() for k, v in phot.items()}
    out["added"] = 0
    if n0 == 0:
        return out
    ax, sub = moffat_alpha(fwhm_px, beta), subsamples(fwhm_px)
    R = int(np.clip(round(2.5 * fwhm_px), 4, 30))
    Rm = int(np.clip(max(SKY_STAR_RADIUS_PX // 2, round(8 * fwhm_px)), 8, SKY_STAR_RADIUS_PX))
    S = _render_stars(phot, np.ones(n0, bool), (h, w), Rm, ax, beta, sub, cov, extra)
    satmap = np.broadcast_to(np.asarray(saturation, float), data.shape)
    bad = ~np.isfinite(data) | ndimage.binary_dilation(np.isfinite(data) & (data >= satmap), iterations=2)
    if mask is not None:
        bad |= mask
    r = np.where(bad, 0.0, data - bkg - S)
    var = np.where(bad, 0.0, rms ** 2 + (np.clip(S, 0, None) / gain if gain else 0.0))
    sg = fwhm_px / (2.0 * math.sqrt(2.0 * math.log(2.0)))
    num = ndimage.gaussian_filter(r, sg, mode="constant")
    den = np.sqrt(np.maximum(ndimage.gaussian_filter(var, sg / math.sqrt(2.0), mode="constant"), 1e-12)
                  / (4 * math.pi * sg * sg))
    snr = num / den
    mod = ndimage.gaussian_filter(np.where(bad, 0.0, S), sg, mode="constant")
    size = 2 * int(math.ceil(fwhm_px)) + 1
    # the pixels beside a left-out one (a saturated core's edge: its filtered residual is not a star's) neither are
    # peaks nor hide one
    snr = np.where(ndimage.binary_dilation(bad, iterations=1), -np.inf, snr)
    peak = (snr >= RESIDUAL_STAR_SNR) & (snr == ndimage.maximum_filter(snr, size=size)) & \
        (num >= RESIDUAL_STAR_MODEL_SHARE * mod)
    py, px = np.nonzero(peak)
    if px.size:
        from scipy.spatial import cKDTree

        d, _ = cKDTree(np.c_[phot["x"], phot["y"]]).query(np.c_[px, py])
        keep = (d > 1.5 * fwhm_px) & (px >= 2) & (py >= 2) & (px < w - 2) & (py < h - 2)
        px, py = px[keep], py[keep]
    if px.size == 0:
        return out
    f0 = np.maximum(num[py, px] * 4 * math.pi * sg * sg, 1.0)
    new = _fit_stars(np.where(bad, np.nan, data - bkg - S), data, satmap, rms, px.astype(float), py.astype(float), f0,
                     R, ax, beta, sub, gain, cov, iterations, extra=extra)
    ok = (new["flux_adu"] > 5 * new["flux_err_adu"]) & (new["npx"] >= 9) & \
        (np.hypot(new["x"] - px, new["y"] - py) < 1.5 * fwhm_px)
    if not ok.any():
        return out
    add = {"x": new["x"][ok], "y": new["y"][ok], "flux_adu": new["flux_adu"][ok]}
    # the stars within reach of a new one (not saturated): fitted again with every model subtracted but their own
    S_all = S + _render_stars(add, np.ones(int(ok.sum()), bool), (h, w), Rm, ax, beta, sub, cov, extra)
    sat = np.asarray(phot.get("saturated", np.zeros(n0, bool)), bool)
    dmin = np.min(np.hypot(out["x"][:, None] - add["x"][None, :], out["y"][:, None] - add["y"][None, :]), axis=1)
    near = (dmin < 2 * R) & ~sat & (out["x"] >= 0) & (out["x"] <= w - 1) & (out["y"] >= 0) & (out["y"] <= h - 1)
    if near.any():
        again = _fit_stars(data - bkg - S_all, data, satmap, rms, out["x"][near], out["y"][near], out["flux_adu"][near],
                           R, ax, beta, sub, gain, cov, iterations, x_start=(out["x"][near], out["y"][near]), own=True,
                           extra=extra)
        for key in ("x", "y", "flux_adu", "flux_err_adu", "bkg_adu", "chi2_dof"):
            if key in out:
                out[key][near] = again[key]
    n = int(ok.sum())
    for key in out:
        if key == "added":
            continue
        if key in new:
            out[key] = np.concatenate([out[key], np.asarray(new[key])[ok].astype(out[key].dtype)])
        elif key == "saturated":
            out[key] = np.concatenate([out[key], np.zeros(n, bool)])
        elif key == "i":
            out[key] = np.concatenate([out[key], np.full(n, -1, dtype=out[key].dtype)])
        else:
            out[key] = np.concatenate([out[key], np.zeros(n, out[key].dtype)])
    out["added"] = n
    return out


#: the half-width [px] of the stars' models subtracted before the sky is measured (their wings beyond it fall
#: below the sky's noise for all but the brightest; a saturated star's reach, SATURATED_MAX_RADIUS_PX, the same)
SKY_STAR_RADIUS_PX = 40


def sky_without_stars(data, phot: dict, fwhm_px: float, beta: float, cov: np.ndarray | None, extra=None,
                      mask: np.ndarray | None = None):
    """The frame's background (photutils ``Background2D``, :func:`background`) once the scene's own stars
    (``phot``: flux x the scene's PSF, its elongation ``cov`` and further filter ``extra``) are subtracted, with
    ``mask`` and the non-finite pixels left out: the light the scene's sky has to supply. The background of the
    frame itself holds the stars' wings and halos between the masked sources (a Moffat of beta 1.8 has 4 % of
    its light beyond 7 FWHM), which the scene's stars already carry: counted twice, the model's sky is too bright
    (the PANOPTES frame: by 4.7 ADU, 0.36 sigma of its sky noise, on every pixel)."""
    h, w = data.shape
    R = int(np.clip(max(SKY_STAR_RADIUS_PX, round(8 * fwhm_px)), 8, 2 * SKY_STAR_RADIUS_PX))
    S = _render_stars(phot, np.ones(len(phot["x"]), bool), (h, w), R, moffat_alpha(fwhm_px, beta), beta,
                      subsamples(fwhm_px), cov, extra)
    bad = ~np.isfinite(data) | (mask if mask is not None else False)
    return background(data - S, mask=bad)[0]


#: the halo is written into the scene when it lowers the frame's chi2 by more than the BIC's price of its four
#: parameters (4 ln N; Schwarz 1978, Ann. Stat. 6, 461) plus this margin ...
HALO_MIN_DELTA_CHI2 = 25.0
#: ... and by at least this fraction of that chi2 (a PSF that is not quite a Moffat leaves a residual that any
#: extra freedom lowers a little: the halo must explain a material part of the frame's misfit) ...
HALO_MIN_GAIN = 0.02
#: ... and carries at least this share of the light [1]
HALO_MIN_FRAC = 0.02
#: the fewest stars the halo is fitted on
HALO_MIN_STARS = 8
#: the largest region [px per side] the halo is fitted on (the frame's centre): the fit filters it many times
HALO_MAX_SIDE_PX = 1024


def fit_psf_halo(data, bkg, phot: dict, fwhm_px: float, beta: float, cov: np.ndarray | None, rms: np.ndarray,
                 gain: float | None = None, saturation: float | np.ndarray = np.inf,
                 mask: np.ndarray | None = None) -> dict | None:
    """The PSF's displaced halo, measured on the whole frame: the share ``halo_frac`` of every star's light that
    lies in a round Gaussian of rms ``halo_sigma_px`` centred ``(halo_dx_px, halo_dy_px)`` from the star
    (:func:`detector.effects.image_plane.displaced_halo_transfer`: the flare of a fast lens off its axis), which
    the scene renders as ``[effects.psf_elongation]``'s halo.

    The stars as fitted (``phot``: the Moffat, elongated by ``cov``) make the model ``S`` of the frame's sources;
    the halo moves ``halo_frac`` of it into ``K * S`` (``K`` the halo's kernel), so the frame's residual above
    the background is fitted, by weighted least squares (weights 1 / (rms^2 + S / gain), the compare's), with
    ``a (K * S - S) + c S + b``: the halo's share ``a``, a common flux scale ``c`` (the stars are then measured
    again with the halo) and a sky offset ``b`` solved linearly for each kernel; the kernel's (sigma, dx, dy)
    from a grid in units of the FWHM (sigma 0.75-4 FWHM, the centre 0-3 FWHM away in 8 directions), refined
    by a simplex. Pixels at the saturation level and their 2-px surroundings, non-finite ones and ``mask`` (the
    scene's: extended sources, bleeds) left out; at
    most the central :data:`HALO_MAX_SIDE_PX` square. The halo is kept when it lowers the chi2 by more than
    ``4 ln N`` (the BIC) plus :data:`HALO_MIN_DELTA_CHI2`, by :data:`HALO_MIN_GAIN` of it, and carries at
    least :data:`HALO_MIN_FRAC` of the light. Returns ``None`` with fewer than :data:`HALO_MIN_STARS` stars, else
    the fit (``kept``)."""
    from scipy import ndimage, optimize

    from detector.effects.image_plane import displaced_halo_transfer, fourier_filter

    x, y, f = (np.asarray(phot[k], float) for k in ("x", "y", "flux_adu"))
    if x.size < HALO_MIN_STARS:
        return None
    h, w = data.shape
    y0, x0 = max(0, (h - HALO_MAX_SIDE_PX) // 2), max(0, (w - HALO_MAX_SIDE_PX) // 2)
    region = (slice(y0, min(h, y0 + HALO_MAX_SIDE_PX)), slice(x0, min(w, x0 + HALO_MAX_SIDE_PX)))
    hh, ww = data[region].shape
    ax, sub = moffat_alpha(fwhm_px, beta), subsamples(fwhm_px)
    R = int(np.clip(round(4 * fwhm_px), 8, 30))
    inside = (x > x0 - R) & (x < x0 + ww + R) & (y > y0 - R) & (y < y0 + hh + R)
    fit = {"x": x[inside] - x0, "y": y[inside] - y0, "flux_adu": f[inside]}
    S = _render_stars(fit, np.ones(int(inside.sum()), bool), (hh, ww), R, ax, beta, sub, cov)
    d = data[region]
    satmap = np.broadcast_to(np.asarray(saturation, float), data.shape)[region]
    bad = ~np.isfinite(d) | ndimage.binary_dilation(np.isfinite(d) & (d >= satmap), iterations=2)
    if mask is not None:
        bad |= mask[region]
    r = np.where(bad, 0.0, d - bkg[region] - S)
    wt = np.where(bad, 0.0, 1.0 / np.maximum(rms[region] ** 2 + (np.clip(S, 0, None) / gain if gain else 0.0), 1e-12))
    n_px = int((~bad).sum())
    one = np.ones_like(S)
    spectra: dict = {}

    def solve(T):
        A = np.array([[np.sum(a * b * wt) for b in T] for a in T])
        v = np.array([np.sum(a * r * wt) for a in T])
        c = np.linalg.solve(A + 1e-12 * np.eye(len(T)), v)
        return c, float(np.sum((r - sum(ci * t for ci, t in zip(c, T))) ** 2 * wt))

    c0, chi0 = solve([S, one])

    def halo_chi2(p):
        sig, dx, dy = float(p[0]), float(p[1]), float(p[2])
        if sig <= 0.2 or sig > 12 * fwhm_px or math.hypot(dx, dy) > 8 * fwhm_px:
            return None, math.inf
        transfer, pad = displaced_halo_transfer(1.0, sig, dx, dy)
        K = fourier_filter(S, pad, lambda fx, fy: transfer(fx, fy), spectra)
        return solve([K - S, S, one])

    best = (math.inf, None, None)
    for sf in (0.75, 1.5, 2.5, 4.0):
        for df in (0.0, 0.75, 1.5, 3.0):
            for k in range(8 if df else 1):
                p = (sf * fwhm_px, df * fwhm_px * math.cos(k * math.pi / 4), df * fwhm_px * math.sin(k * math.pi / 4))
                c, chi = halo_chi2(p)
                if chi < best[0]:
                    best = (chi, p, c)
    res = optimize.minimize(lambda p: halo_chi2(p)[1], np.array(best[1]), method="Nelder-Mead",
                            options={"xatol": 0.02, "fatol": 1e-3 * max(chi0, 1.0), "maxfev": 120,
                                     "initial_simplex": np.array(best[1]) + np.array(
                                         [[0, 0, 0], [0.25 * fwhm_px, 0, 0], [0, 0.5 * fwhm_px, 0], [0, 0, 0.5 * fwhm_px]])})
    c, chi1 = halo_chi2(res.x)
    if not chi1 < best[0]:
        chi1, c, p = best[0], best[2], np.array(best[1])
    else:
        p = res.x
    frac = float(c[0])
    delta = chi0 - chi1
    kept = bool(delta > 4 * math.log(max(n_px, 2)) + HALO_MIN_DELTA_CHI2 and delta > HALO_MIN_GAIN * chi0
                and HALO_MIN_FRAC <= frac <= 0.8)
    return {"kept": kept, "halo_frac": frac, "halo_sigma_px": float(p[0]), "halo_dx_px": float(p[1]),
            "halo_dy_px": float(p[2]), "chi2_without_halo": chi0, "chi2_with_halo": chi1, "n_pixels": n_px,
            "delta_chi2": delta, "flux_scale_without_halo": 1.0 + float(c0[0]), "n_stars": int(inside.sum())}


#: the largest fit window of a saturated star [px, half-size]
SATURATED_MAX_RADIUS_PX = 40


def photometry(data, bkg, cols, fwhm_px: float, beta: float, saturation: float | np.ndarray, rms: np.ndarray,
               keep: np.ndarray | None = None, max_sources: int = 20000, iterations: int = 8,
               gain: float | None = None, cov_px2: np.ndarray | None = None,
               extra=None) -> dict:
    """PSF-fit fluxes [ADU] (total flux of the scene's PSF), centres, local background, S/N.

    The PSF is the scene's: the circular Moffat (``fwhm_px``, ``beta``), filtered by the elongation covariance
    ``cov_px2`` when the scene carries one (:func:`elongation_cov_px2`, :func:`_psf_and_grad`), and given the
    elongation's further filter ``extra = (transfer, pad)`` (its displaced halo, :func:`fit_psf_halo`), so the fluxes
    are those that minimise the compare's chi2 of each star with the scene's own PSF.

    Every star at once: weighted Gauss-Newton on (flux, x, y, background) with the analytic derivatives of the
    pixel-averaged PSF, steps limited to 1 px. Weights: the model's own variance, the background noise plus the
    star's Poisson variance ``m / gain`` [ADU^2] at the current model (iteratively reweighted: the weights of
    the compare's chi2, not of the data's fluctuations); without ``gain``, the background noise alone.

    Saturated stars (a pixel of the window at or above ``saturation``): their flux is fitted from their
    unsaturated wings with the same PSF, the saturated pixels left out (as photutils' PSF photometry with a
    mask), in a window grown to the saturated core's radius plus 3 FWHM (at most
    :data:`SATURATED_MAX_RADIUS_PX`), the other stars' fitted models first subtracted from it, so that the model
    star, clipped at the same level, reproduces the wings. The aperture sum (clipped core included) is a lower
    bound of such a flux and is taken when the wing fit falls below it."""
    ax = moffat_alpha(fwhm_px, beta)
    sub = subsamples(fwhm_px)
    R = int(np.clip(round(2.5 * fwhm_px), 4, 30))
    idx = np.flatnonzero(keep if keep is not None else np.ones(len(cols["x_centroid"]), bool))
    idx = idx[np.isfinite(cols["x_centroid"][idx]) & np.isfinite(cols["y_centroid"][idx])]
    idx = idx[np.argsort(-cols["segment_flux"][idx])][:max_sources]
    empty = {k: np.zeros(0) for k in ("i", "x", "y", "flux_adu", "flux_err_adu", "bkg_adu", "chi2_dof", "saturated")}
    if idx.size == 0:
        return empty
    h, w = data.shape
    satmap = (np.broadcast_to(np.asarray(saturation, float), data.shape) if np.ndim(saturation)
              else np.full(data.shape, float(saturation)))
    sub_img = data - bkg
    x0 = cols["x_centroid"][idx].astype(float)
    y0 = cols["y_centroid"][idx].astype(float)
    f0 = np.maximum(cols["segment_flux"][idx], 1.0).astype(float)
    first = _fit_stars(sub_img, data, satmap, rms, x0, y0, f0, R, ax, beta, sub, gain, cov_px2, iterations, extra=extra)
    if "max_value_xindex" in cols:
        # a segment whose brightest pixel lies away from its centroid (a blend the deblending kept whole has
        # its centroid between its sources, beyond the fit's reach): fitted again from that pixel, the better
        # fit kept (a cosmic ray or a hot pixel in the segment is the worse one); a saturated peak (anywhere on
        # the clipped plateau) is not a start
        px = np.asarray(cols["max_value_xindex"][idx], float)
        py = np.asarray(cols["max_value_yindex"][idx], float)
        okp = np.isfinite(px) & np.isfinite(py)
        pxi = np.clip(np.where(okp, px, 0), 0, w - 1).astype(int)
        pyi = np.clip(np.where(okp, py, 0), 0, h - 1).astype(int)
        away = np.flatnonzero(okp & (np.hypot(px - x0, py - y0) > 1.5) & ~(data[pyi, pxi] >= satmap[pyi, pxi]))
        if away.size:
            alt = _fit_stars(sub_img, data, satmap, rms, px[away], py[away], f0[away], R, ax, beta, sub, gain,
                             cov_px2, iterations, extra=extra)
            better = (alt["chi2_dof"] < first["chi2_dof"][away]) & (alt["npx"] >= 9)
            for key in first:
                first[key][away[better]] = alt[key][better]
            x0, y0 = x0.copy(), y0.copy()
            x0[away[better]], y0[away[better]] = px[away][better], py[away][better]
    # a saturated star: a saturated pixel within its core (a neighbour's saturated pixels in a window are only
    # left out of that window's fit)
    satpix = np.isfinite(data) & (data >= satmap)
    r_core = max(1.5, 0.75 * fwhm_px)
    sat = np.zeros(idx.size, bool)
    if satpix.any():
        from scipy import ndimage

        lab, _ = ndimage.label(satpix)
        area = np.bincount(lab.ravel())
        core_area = np.zeros(idx.size)
        core_label = np.zeros(idx.size, int)
        k = math.ceil(r_core)
        for dy in range(-k, k + 1):
            for dx in range(-k, k + 1):
                if dx * dx + dy * dy > r_core * r_core:
                    continue
                yy = np.clip(np.round(first["y"]).astype(int) + dy, 0, h - 1)
                xx = np.clip(np.round(first["x"]).astype(int) + dx, 0, w - 1)
                a_here = area[lab[yy, xx]] * (lab[yy, xx] > 0)
                core_label = np.where(a_here > core_area, lab[yy, xx], core_label)
                core_area = np.maximum(core_area, a_here)
        sat = core_area > 0
        if sat.any():
            # a saturated star's centre: the centroid of its clipped plateau (a symmetric PSF clips a disc
            # about its centre), where the detection's centroid of a blend or of a bright star's segment
            # with its neighbours may lie pixels away
            labels = np.unique(core_label[sat])
            com = np.array(ndimage.center_of_mass(satpix, lab, labels)).reshape(-1, 2)
            where = np.searchsorted(labels, core_label[sat])
            first["y"][sat], first["x"][sat] = com[where, 0], com[where, 1]
            x0, y0 = x0.copy(), y0.copy()
            x0[sat], y0[sat] = com[where, 1], com[where, 0]
    if sat.any():
        # the saturated stars again, in windows that reach beyond their clipped cores into their wings, every
        # other star's fitted model subtracted (each star's own previous model added back to its window)
        R_sat = int(np.clip(math.ceil(math.sqrt(float(core_area[sat].max()) / math.pi) + 3.0 * fwhm_px), R,
                            SATURATED_MAX_RADIUS_PX))
        # the sky under them: the frame's background again, every star's fitted model subtracted first (the
        # wings of a saturated star, out to SATURATED_MAX_RADIUS_PX, raise a box median far beyond its core),
        # the saturated pixels masked; then their fits with the background held at that sky
        for _ in range(2):
            others = _render_stars(first, ~sat, (h, w), R, ax, beta, sub, cov_px2, extra)
            wide = others + _render_stars(first, sat, (h, w), SATURATED_MAX_RADIUS_PX, ax, beta, sub, cov_px2, extra)
            sky, _ = background(data - wide, mask=satpix | ~np.isfinite(data))
            total = others + _render_stars(first, sat, (h, w), R_sat, ax, beta, sub, cov_px2, extra)
            sub_img = data - sky
            second = _fit_stars(sub_img - total, data, satmap, rms, first["x"][sat], first["y"][sat],
                                first["flux_adu"][sat], R_sat, ax, beta, sub, gain, cov_px2, 2 * iterations,
                                x_start=(x0[sat], y0[sat]), own=True, fixed_background=True, extra=extra)
            for key in ("x", "y", "flux_adu", "flux_err_adu", "bkg_adu", "chi2_dof", "npx", "ap_sum"):
                first[key][sat] = second[key]
            first["flux_adu"][sat] = np.maximum(second["flux_adu"], second["ap_sum"])
        total = (_render_stars(first, ~sat, (h, w), R, ax, beta, sub, cov_px2, extra)
                 + _render_stars(first, sat, (h, w), R_sat, ax, beta, sub, cov_px2, extra))
        # the stars within reach of a saturated one, refitted with its (new) model subtracted
        near = ~sat & (np.min(np.hypot(first["x"][:, None] - first["x"][sat][None, :],
                                       first["y"][:, None] - first["y"][sat][None, :]), axis=1) < R + R_sat)
        if near.any():
            third = _fit_stars(sub_img - total, data, satmap, rms, first["x"][near], first["y"][near],
                               first["flux_adu"][near], R, ax, beta, sub, gain, cov_px2, iterations,
                               x_start=(x0[near], y0[near]), own=True, extra=extra)
            for key in ("x", "y", "flux_adu", "flux_err_adu", "bkg_adu", "chi2_dof", "npx"):
                first[key][near] = third[key]
    good = first["npx"] >= 9
    return {"i": idx[good], "x": first["x"][good], "y": first["y"][good], "flux_adu": first["flux_adu"][good],
            "flux_err_adu": first["flux_err_adu"][good], "bkg_adu": first["bkg_adu"][good],
            "chi2_dof": first["chi2_dof"][good], "saturated": sat[good]}


def _fit_stars(z_img, raw_img, satmap, rms, x0, y0, f0, R: int, ax: float, beta: float, sub: int, gain, cov,
               iterations: int, x_start=None, own: bool = False, fixed_background: bool = False, extra=None) -> dict:
    """Weighted Gauss-Newton fits of (flux, x, y, background) of every star at once in windows of half-size
    ``R`` (see :func:`photometry`); non-finite and saturated pixels weight 0. ``own``: ``z_img`` has every
    star's model subtracted, and each star's own (``f0`` at ``x0, y0``) is added back to its window.
    ``fixed_background``: the local background held at 0 (``z_img`` is above the sky already): a wing-only fit
    cannot tell a flat background from the far wings of its star."""
    pad = np.pad(z_img, R + 1, constant_values=np.nan)
    padraw = np.pad(raw_img, R + 1, constant_values=np.nan)
    padn = np.pad(rms, R + 1, mode="edge")
    padsat = np.pad(satmap, R + 1, constant_values=np.inf)
    xc0, yc0 = x_start if x_start is not None else (x0, y0)
    xi, yi = np.round(x0).astype(int), np.round(y0).astype(int)
    off = np.arange(-R, R + 1)
    YY = yi[:, None, None] + off[None, :, None] + R + 1
    XX = xi[:, None, None] + off[None, None, :] + R + 1
    z = pad[YY, XX]
    gx = (xi[:, None, None] + off[None, None, :]).astype(float)
    gy = (yi[:, None, None] + off[None, :, None]).astype(float)
    if own:
        z = z + np.asarray(f0, float)[:, None, None] * _psf_and_grad(gx, gy, np.asarray(x0, float),
                                                                     np.asarray(y0, float), ax, beta, sub, cov, extra)[0]
    raw = padraw[YY, XX]
    ok = np.isfinite(z) & (raw < padsat[YY, XX])
    n = len(x0)
    n2 = np.median(padn[YY, XX].reshape(n, -1), axis=1) ** 2
    zc = np.where(ok, z, 0.0)
    f = np.asarray(f0, float).copy()
    cx, cy, c = np.asarray(x0, float).copy(), np.asarray(y0, float).copy(), np.zeros(n)

    def weights(P):
        star = np.clip(f[:, None, None] * P, 0.0, None)
        poisson = star / gain if gain else 0.0
        return ok / (n2[:, None, None] + poisson + 1e-12)

    for _ in range(iterations):
        P, dPx, dPy = _psf_and_grad(gx, gy, cx, cy, ax, beta, sub, cov, extra)
        wgt = weights(P)
        r = zc - (f[:, None, None] * P + c[:, None, None])
        J = np.stack([P, f[:, None, None] * dPx, f[:, None, None] * dPy] + ([] if fixed_background else [np.ones_like(P)]),
                     axis=-1)
        Jw = J * wgt[..., None]
        A = np.einsum("nyxi,nyxj->nij", Jw, J)
        b = np.einsum("nyxi,nyx->ni", Jw, r)
        # the normal equations scaled to a unit diagonal before the small damping (the Poisson weights of a
        # bright star make them tiny: an absolute damping would shrink its steps)
        d = np.sqrt(np.maximum(np.einsum("nii->ni", A), 1e-300))
        As = A / (d[:, :, None] * d[:, None, :]) + 1e-9 * np.eye(J.shape[-1])
        step = np.linalg.solve(As, (b / d)[..., None])[..., 0] / d
        f = np.maximum(f + step[:, 0], 0.0)
        # the centre held within 2.5 px of the detection's at every step (a clip after the fit would leave a
        # flux fitted at another place: a star beyond the frame's edge, whose wing alone is in it)
        cx = np.clip(cx + np.clip(step[:, 1], -1, 1), xc0 - 2.5, xc0 + 2.5)
        cy = np.clip(cy + np.clip(step[:, 2], -1, 1), yc0 - 2.5, yc0 + 2.5)
        if not fixed_background:
            c = c + step[:, 3]
    P, _, _ = _psf_and_grad(gx, gy, cx, cy, ax, beta, sub, cov, extra)
    wgt = weights(P)
    res = (zc - f[:, None, None] * P - c[:, None, None]) ** 2 * wgt
    npx = ok.reshape(n, -1).sum(axis=1)
    err = np.sqrt(1.0 / np.maximum((P ** 2 * wgt).reshape(n, -1).sum(axis=1), 1e-30))
    sat = ((~ok) & np.isfinite(raw)).reshape(n, -1).any(axis=1)
    # the aperture sum (clipped core included): a lower bound of a saturated star's flux
    r_ap = max(3.0 * math.sqrt(2.0 ** (1.0 / beta) - 1.0) * 2.0 * ax, 4.0)
    inap = ((gx - cx[:, None, None]) ** 2 + (gy - cy[:, None, None]) ** 2 <= r_ap ** 2) & np.isfinite(z)
    ap_sum = (np.where(inap, z, 0.0) - np.where(inap, c[:, None, None], 0.0)).reshape(n, -1).sum(axis=1)
    return {"x": cx, "y": cy, "flux_adu": f, "flux_err_adu": err, "bkg_adu": c,
            "chi2_dof": res.reshape(n, -1).sum(axis=1) / np.maximum(npx - 4, 1), "saturated": sat, "npx": npx,
            "ap_sum": ap_sum}


#: the drawn models average a pixel's sub-samples out to this many FWHM plus this margin [px] from the star's
#: centre; beyond, a pixel's centre value differs from its average by less than 1e-5 of the peak
WING_SAMPLED_FWHM = 2.0
WING_SAMPLED_MARGIN_PX = 6


def _render_stars(fit: dict, use: np.ndarray, shape, R: int, ax: float, beta: float, sub: int, cov,
                  extra=None) -> np.ndarray:
    """The fitted models (flux x PSF, no background) of the stars ``use`` on an image of ``shape``."""
    if cov is not None or extra is not None:
        # the stars' round Moffats, then the elongation and the extra filter on the whole image, as the renderer
        # applies [effects.psf_elongation] (the filters are linear and commute with the shifts)
        img = _render_stars(fit, use, shape, R, ax, beta, sub, None)
        return _filter_image(img, cov, extra)
    h, w = shape
    out = np.zeros((h + 2 * R + 2, w + 2 * R + 2))
    sel = np.flatnonzero(use)
    if sel.size == 0:
        return out[R + 1:R + 1 + h, R + 1:R + 1 + w]
    off = np.arange(-R, R + 1)
    # the pixel average (sub x sub samples) where the Moffat curves within a pixel; beyond it the centre value
    # (the average's correction there is below 1e-5 of the peak for FWHM 1-8 px and beta 1.3-1000)
    fwhm = 2 * ax * math.sqrt(2 ** (1 / beta) - 1)
    K = int(min(R, np.ceil(WING_SAMPLED_FWHM * fwhm) + WING_SAMPLED_MARGIN_PX))
    inner = slice(R - K, R + K + 1)
    for chunk in np.array_split(sel, max(1, sel.size // 2000)):
        xi, yi = np.round(fit["x"][chunk]).astype(int), np.round(fit["y"][chunk]).astype(int)
        gx = (xi[:, None, None] + off[None, None, :]).astype(float)
        gy = (yi[:, None, None] + off[None, :, None]).astype(float)
        dx, dy = gx - fit["x"][chunk][:, None, None], gy - fit["y"][chunk][:, None, None]
        P = _moffat_value(dx, dy, ax, beta, 1) if K < R and sub > 1 else _moffat_value(dx, dy, ax, beta, sub)
        if K < R and sub > 1:
            P[:, inner, inner] = _moffat_value(dx[:, :, inner], dy[:, inner, :], ax, beta, sub)
        YY = np.broadcast_to(yi[:, None, None] + off[None, :, None] + R + 1, P.shape)
        XX = np.broadcast_to(xi[:, None, None] + off[None, None, :] + R + 1, P.shape)
        inside = (YY >= 0) & (YY < out.shape[0]) & (XX >= 0) & (XX < out.shape[1])
        np.add.at(out, (YY[inside], XX[inside]), (fit["flux_adu"][chunk][:, None, None] * P)[inside])
    return out[R + 1:R + 1 + h, R + 1:R + 1 + w]
