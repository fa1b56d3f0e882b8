"""A baseline streak detector built from existing libraries (``newtsim detect``; docs/detection_bench.md).

It is a baseline, not the best detector: it shows the loop (render or inject -> detect -> score) end to end.

1. **Background**: photutils ``Background2D`` (sigma-clipped boxes; per CFA plane on a Bayer frame), and the
   significance image z = (data - background) / rms.
2. **Matched filter across the track**: z convolved with a circular Gaussian of the PSF's FWHM (measured on
   the frame's stars, or given; 2.5 px when neither), normalised to unit noise by its own robust sigma:
   for a streak of per-pixel amplitude A over noise sigma the filtered peak is ~ A / sigma x sqrt(2 sqrt(pi)
   s), s the Gaussian's sigma (Kay 1998, vol. II ch. 4: the matched filter's gain).
3. **Segmentation** (photutils ``detect_sources``) of the filtered image above ``SEG_SIGMA``: each segment's
   second moments give its axis and elongation; elongated, long segments are streak candidates.
4. **Line finder for faint streaks**: scikit-image's probabilistic Hough transform
   (``probabilistic_hough_line``) on the filtered image thresholded at ``HOUGH_SIGMA``, with the compact
   bright segments (stars) masked; each line is a streak candidate.
5. **Verification and endpoints**: candidates on the same line are merged; along each line the mean of z over
   a band of +-1 FWHM gives the profile; the track is the run where the smoothed profile stays above half its
   median plateau (a uniform trail convolved with the PSF falls to half its level exactly at its end, so these
   are the visible ends of the trail); its score is the integrated SNR of the band, sum(z) / sqrt(n), and a
   streak is kept when it exceeds ``MIN_SNR``.

Output (``write_detections``): a COCO results JSON (``image_id``, ``file_name``, ``category_id`` 1, ``bbox``,
``score`` and the endpoints ``x0, y0, x1, y1``), or an ECSV table with one row per detection (``file_name``,
``hdu``, ``kind``, ``x0, y0, x1, y1``, ``x, y``, ``score``, ``length_px``). Coordinates: 0-based pixel
centres, as the labels; both read by ``newtsim score``.
"""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.special import erf

__all__ = ["Detection", "detect_file", "detect_image", "write_detections"]

SEG_SIGMA = 3.0  # segmentation threshold on the filtered image [its sigma]
HOUGH_SIGMA = 2.0  # Hough input: filtered pixels above this [sigma]
MIN_ELONGATION = 3.0  # a streak segment's major / minor axis (second moments)
MIN_LENGTH_FWHM = 4.0  # a streak is at least this many FWHM long (and MIN_LENGTH_PX)
MIN_LENGTH_PX = 12.0
MIN_SNR = 7.0  # integrated SNR of a kept streak (band of +-1 FWHM about its line)
MERGE_ANGLE_DEG = 4.0
WING_RATIO = 0.25
NEAR_UNLIT_PX = 10
STAR_ROUNDNESS = 0.5  # a peak whose ring one FWHM out varies less than this (min / max) is a star
SATURATED_PX = 5  # + 4 FWHM: the reach of a saturated star's bleed and halo masked for the line finder
BRIGHT_STAR_SIGMA = 200.0  # a peak of a round segment above this (filtered image) is a star in any case
DEFAULT_FWHM_PX = 2.5
FWHM_TO_SIGMA = 1.0 / 2.3548200450309493


@dataclass
class Detection:
    """One detection: endpoints (a point: both at its centre) [px, 0-based centres], score (integrated SNR)."""

    kind: str
    x0: float
    y0: float
    x1: float
    y1: float
    score: float
    file: str = ""
    hdu: int = 0

    @property
    def x(self) -> float:
        return 0.5 * (self.x0 + self.x1)

    @property
    def y(self) -> float:
        return 0.5 * (self.y0 + self.y1)

    @property
    def length_px(self) -> float:
        return math.hypot(self.x1 - self.x0, self.y1 - self.y0)

    def bbox(self, pad: float) -> list[float]:
        xa, xb = sorted((self.x0, self.x1))
        ya, yb = sorted((self.y0, self.y1))
        return [xa - pad + 0.5, ya - pad + 0.5, xb - xa + 2 * pad, yb - ya + 2 * pad]


def _robust_sigma(a: np.ndarray) -> float:
    a = a[np.isfinite(a)]
    if a.size == 0:
        return 1.0
    med = np.median(a)
    return float(1.4826 * np.median(np.abs(a - med))) or float(np.std(a)) or 1.0


def _line_band(shape, p0, p1, half_width: float, extend: float):
    """Pixel indices (rows, cols) within half_width of the segment p0-p1 prolonged by ``extend`` at both ends,
    and their coordinate t along the line (0 at p0) [px]."""
    (x0, y0), (x1, y1) = p0, p1
    L = math.hypot(x1 - x0, y1 - y0)
    ux, uy = (x1 - x0) / L, (y1 - y0) / L
    xs = [x0 - extend * ux, x1 + extend * ux]
    ys = [y0 - extend * uy, y1 + extend * uy]
    pad = half_width + 1
    c0, c1 = max(0, math.floor(min(xs) - pad)), min(shape[1], math.ceil(max(xs) + pad) + 1)
    r0, r1 = max(0, math.floor(min(ys) - pad)), min(shape[0], math.ceil(max(ys) + pad) + 1)
    if c1 <= c0 or r1 <= r0:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    rr, cc = np.mgrid[r0:r1, c0:c1]
    dx, dy = cc - x0, rr - y0
    t = dx * ux + dy * uy
    d = np.abs(-dx * uy + dy * ux)
    sel = (d <= half_width) & (t >= -extend) & (t <= L + extend)
    return rr[sel], cc[sel], t[sel]


def _axis(zs: np.ndarray, p0, p1, half: float):
    """The line through the light near p0-p1: weighted principal axis of the smoothed significance ``zs`` > 1
    within ``half`` px of the segment; (p0, p1, cross-track FWHM [px]) or None."""
    rr, cc, t = _line_band(zs.shape, p0, p1, half, 0.0)
    if t.size < 3:
        return None
    w = np.where(zs[rr, cc] > 1.0, zs[rr, cc], 0.0)
    if w.sum() <= 0:
        return None
    xc, yc = (w * cc).sum() / w.sum(), (w * rr).sum() / w.sum()
    cxx = (w * (cc - xc) ** 2).sum() / w.sum()
    cyy = (w * (rr - yc) ** 2).sum() / w.sum()
    cxy = (w * (cc - xc) * (rr - yc)).sum() / w.sum()
    ev, vec = np.linalg.eigh(np.array([[cxx, cxy], [cxy, cyy]]))
    ux, uy = vec[:, 1]
    L = math.hypot(p1[0] - p0[0], p1[1] - p0[1])
    width = 2.3548 * math.sqrt(max(ev[0], 0.0))
    return (xc - 0.5 * L * ux, yc - 0.5 * L * uy), (xc + 0.5 * L * ux, yc + 0.5 * L * uy), width


def _refine(z: np.ndarray, zs: np.ndarray, p0, p1, fwhm: float):
    """The candidate's line re-fitted to the light about it, its visible ends and integrated SNR:
    (q0, q1, snr, cross-track FWHM) or None. The along-track profile: the mean of z over the band |d| <= the
    cross-track FWHM (at least the PSF's), in 1 px bins of t, boxcar-smoothed over one FWHM."""
    h, w = z.shape
    width = fwhm
    for _ in range(2):
        ax = _axis(zs, p0, p1, 1.5 * width + 1.0)
        if ax is None:
            return None
        p0, p1, wd = ax
        width = max(fwhm, min(wd, 6.0 * fwhm + 10.0))
    L = math.hypot(p1[0] - p0[0], p1[1] - p0[1])
    if L < 1:
        return None
    ext = max(h, w)  # follow the line to the frame's edges: the candidate may be only part of the trail
    rr, cc, t = _line_band(z.shape, p0, p1, width, ext)
    if t.size == 0:
        return None
    tb = np.floor(t).astype(int)
    lo = tb.min()
    idx = tb - lo
    vals_all = z[rr, cc]
    fin = np.isfinite(vals_all)
    n = np.bincount(idx[fin], minlength=idx.max() + 1)
    s = np.bincount(idx[fin], weights=vals_all[fin], minlength=idx.max() + 1)
    good = n > 0
    prof = np.where(good, s / np.maximum(n, 1), 0.0)
    k = max(1, round(0.5 * fwhm))
    kernel = np.ones(2 * k + 1)
    smooth = np.convolve(prof * good, kernel, "same") / np.maximum(np.convolve(good.astype(float), kernel, "same"), 1)
    a, b = max(math.floor(-lo), 0), min(math.ceil(L - lo), len(smooth) - 1)
    if b <= a:
        return None
    plateau = float(np.median(smooth[a:b + 1]))
    if plateau <= 0:
        return None
    above = smooth >= 0.5 * plateau
    mid = round(0.5 * (a + b))
    gap = math.ceil(2 * fwhm)
    if not above[mid]:
        cand = np.flatnonzero(above[a:b + 1])
        if cand.size == 0:
            return None
        mid = a + int(cand[np.argmin(np.abs(cand + a - mid))])
    i0 = i1 = mid
    j, miss = i0, 0
    # the run of 'above' about the middle, gaps up to 2 FWHM (light curves); bins without data (stars) neutral
    while j - 1 >= 0 and miss <= gap:
        j -= 1
        if good[j]:
            i0, miss = (j, 0) if above[j] else (i0, miss + 1)
    j, miss = i1, 0
    while j + 1 < len(above) and miss <= gap:
        j += 1
        if good[j]:
            i1, miss = (j, 0) if above[j] else (i1, miss + 1)
    t0, t1 = i0 + lo + 0.5, i1 + lo + 0.5  # the bins' centres [px along the line from p0]
    ux, uy = (p1[0] - p0[0]) / L, (p1[1] - p0[1]) / L
    q0 = (p0[0] + t0 * ux, p0[1] + t0 * uy)
    q1 = (p0[0] + t1 * ux, p0[1] + t1 * uy)
    sel = (t >= t0) & (t <= t1) & fin
    # integrated SNR with the median bin for the mean: a line through one bright star scores low
    snr = float(np.median(prof[i0:i1 + 1][good[i0:i1 + 1]]) * math.sqrt(max(int(sel.sum()), 1)))
    return q0, q1, snr, width


def _final(z: np.ndarray, q0, q1, width: float, fwhm: float):
    """A kept candidate's ends and width from the trail fit (:func:`_fit_trail`), clipped to the frame, and
    its halo: (q0, q1, width, halo) or None when the fitted trail is off the frame."""
    for _ in range(2):  # the second fit on the band about the first one's trail
        fit = _fit_trail(z, q0, q1, width * FWHM_TO_SIGMA, fwhm * FWHM_TO_SIGMA)
        if fit is None:
            break
        q0, q1, sigma, _ = fit
        width = max(fwhm, sigma / FWHM_TO_SIGMA)
    vis = _clip_to_frame(q0, q1, z.shape)
    if vis is None:
        return None
    q0, q1 = vis
    return q0, q1, width, max(width, _halo(z, q0, q1, width))


def _trail_model(params, xx, yy):
    """A straight trail of peak A (significance units) from (x0, y0) to (x1, y1) through a circular Gaussian
    PSF of sigma s: A exp(-d^2 / 2 s^2) [erf(t / sqrt2 s) - erf((t - L) / sqrt2 s)] / 2 (t along, d across)."""
    x0, y0, x1, y1, amp, sig = params
    L = math.hypot(x1 - x0, y1 - y0) or 1e-9
    ux, uy = (x1 - x0) / L, (y1 - y0) / L
    t = (xx - x0) * ux + (yy - y0) * uy
    d = -(xx - x0) * uy + (yy - y0) * ux
    r = math.sqrt(2.0) * sig
    return amp * np.exp(-0.5 * (d / sig) ** 2) * 0.5 * (erf(t / r) - erf((t - L) / r))


def _fit_trail(z: np.ndarray, q0, q1, sigma: float, psf_sigma: float):
    """Least-squares fit of :func:`_trail_model` to z about the segment (unit noise): the matched-filter
    estimate of the ends, the width and the amplitude. Returns (q0, q1, sigma, SNR = A sqrt(sum g^2)) or
    None when the fit fails."""
    from scipy.optimize import least_squares

    reach = max(4.0 * sigma, 3.0)
    L = math.hypot(q1[0] - q0[0], q1[1] - q0[1])
    rr, cc, _ = _line_band(z.shape, q0, q1, reach, max(reach + 5.0, 0.25 * L))
    v = z[rr, cc]
    fin = np.isfinite(v)
    rr, cc, v = rr[fin], cc[fin], v[fin]
    if v.size < 10:
        return None
    xx, yy = cc.astype(float), rr.astype(float)
    g0 = _trail_model((q0[0], q0[1], q1[0], q1[1], 1.0, sigma), xx, yy)
    amp0 = float(np.sum(g0 * v) / max(np.sum(g0 * g0), 1e-12))
    if not amp0 > 0:
        return None
    start = np.array([q0[0], q0[1], q1[0], q1[1], amp0, sigma])
    lo = [-np.inf, -np.inf, -np.inf, -np.inf, 0.0, 0.5 * psf_sigma]
    hi = [np.inf, np.inf, np.inf, np.inf, np.inf, max(3.0 * sigma, 2.0 * psf_sigma)]
    start[5] = min(max(start[5], lo[5] * 1.01), hi[5] * 0.99)
    try:
        res = least_squares(lambda p: _trail_model(p, xx, yy) - v, start, bounds=(lo, hi), max_nfev=60,
                            x_scale=[1.0, 1.0, 1.0, 1.0, max(amp0, 1e-3), max(sigma, 0.5)])
    except (ValueError, FloatingPointError):
        return None
    x0, y0, x1, y1, amp, sig = res.x
    if not (np.all(np.isfinite(res.x)) and amp > 0):
        return None
    # a fit that wandered far from the candidate's line is not a refinement of it
    if math.hypot(0.5 * (x0 + x1) - 0.5 * (q0[0] + q1[0]), 0.5 * (y0 + y1) - 0.5 * (q0[1] + q1[1])) > 0.5 * L + 3 * sigma:
        return None
    g = _trail_model((x0, y0, x1, y1, 1.0, sig), xx, yy)
    return (x0, y0), (x1, y1), float(sig), float(amp * math.sqrt(np.sum(g * g)))


def _clip_to_frame(q0, q1, shape):
    """The part of segment q0-q1 inside the frame [-0.5, w - 0.5] x [-0.5, h - 0.5] (Liang-Barsky), or None."""
    h, w = shape
    (x0, y0), (x1, y1) = q0, q1
    dx, dy = x1 - x0, y1 - y0
    a, b = 0.0, 1.0
    for p, q in ((-dx, x0 + 0.5), (dx, w - 0.5 - x0), (-dy, y0 + 0.5), (dy, h - 0.5 - y0)):
        if p == 0:
            if q < 0:
                return None
            continue
        r = q / p
        if p < 0:
            a = max(a, r)
        else:
            b = min(b, r)
    if a > b:
        return None
    return (x0 + a * dx, y0 + a * dy), (x0 + b * dx, y0 + b * dy)


def _halo(z: np.ndarray, q0, q1, width: float) -> float:
    """Half-width [px] of the trail's light across the track: the distance from the line out to which the
    mean z of 1 px bins of |d| stays >= 1 (a bright trail's halo; a faint one: about its FWHM)."""
    L = math.hypot(q1[0] - q0[0], q1[1] - q0[1])
    if L < 1:
        return width
    reach = 10.0 * width + 20.0
    rr, cc, t = _line_band(z.shape, q0, q1, reach, 0.0)
    if t.size == 0:
        return width
    ux, uy = (q1[0] - q0[0]) / L, (q1[1] - q0[1]) / L
    d = np.abs(-(cc - q0[0]) * uy + (rr - q0[1]) * ux)
    v = z[rr, cc]
    fin = np.isfinite(v)
    db = np.floor(d[fin]).astype(int)
    n = np.bincount(db)
    s = np.bincount(db, weights=v[fin])
    mean = np.where(n > 0, s / np.maximum(n, 1), 0.0)
    below = np.flatnonzero(mean < 1.0)
    return float(below[0]) if below.size else reach


def _artefact(q0, q1, width: float, ramp_zone: np.ndarray) -> bool:
    """A line along one column or row: within 0.5 deg and narrower than 3 px (a bad column or row), or within
    RAMP_DEG and RAMP_PX of the prescan/overscan (a read-out ramp): not a trail."""
    ang = math.degrees(math.atan2(q1[1] - q0[1], q1[0] - q0[0])) % 90.0
    off = min(ang, 90.0 - ang)
    if off < 0.5 and width < 3.0:
        return True
    xm, ym = round(0.5 * (q0[0] + q1[0])), round(0.5 * (q0[1] + q1[1]))
    h, w = ramp_zone.shape
    return off < RAMP_DEG and bool(ramp_zone[min(max(ym, 0), h - 1), min(max(xm, 0), w - 1)])


def _in_wings(q0, q1, kept, fwhm: float) -> bool:
    """A candidate with 80 % of its length within a kept trail's halo (:func:`_halo`) + 2 FWHM (and a score below
    WING_RATIO of it: the caller's choice of ``kept``): that trail's wings (a bright trail's halo)."""
    n = max(2, int(math.hypot(q1[0] - q0[0], q1[1] - q0[1])))
    xs, ys = np.linspace(q0[0], q1[0], n), np.linspace(q0[1], q1[1], n)
    for _, k0, k1, width_k in kept:
        L = math.hypot(k1[0] - k0[0], k1[1] - k0[1])
        ux, uy = (k1[0] - k0[0]) / L, (k1[1] - k0[1]) / L
        d = np.abs(-(xs - k0[0]) * uy + (ys - k0[1]) * ux)
        if np.mean(d <= width_k + 2.0 * fwhm) >= 0.8:
            return True
    return False


RAMP_PX = 20  # a column/row-aligned line this close to the prescan/overscan is a read-out ramp
RAMP_DEG = 5.0


def _in_wings(q0, q1, kept, fwhm: float) -> bool:
    """A candidate parallel to a kept trail (within MERGE_ANGLE_DEG), within 4 of its widths + 2 FWHM of its
    line and below WING_RATIO of its score: the wings of that trail (a bright trail's PSF halo)."""
    for _, k0, k1, width_k in kept:
        if _same_line((k0, k1), (q0, q1), 4.0 * width_k + 2.0 * fwhm) and _overlap((k0, k1), (q0, q1), fwhm):
            return True
    return False


def _segments(zf: np.ndarray, fwhm: float):
    """Segments of the filtered image above SEG_SIGMA: (streak candidates as (p0, p1), compact masks)."""
    from photutils.segmentation import detect_sources

    npix = max(5, math.ceil(0.5 * fwhm * fwhm))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        seg = detect_sources(zf, SEG_SIGMA, npix)
    lines, compact = [], np.zeros(zf.shape, dtype=bool)
    if seg is None:
        return lines, compact
    lab = seg.data
    for i, sl in enumerate(ndimage.find_objects(lab)):
        if sl is None:
            continue
        m = lab[sl] == i + 1
        yy, xx = np.nonzero(m)
        yy, xx = yy + sl[0].start, xx + sl[1].start
        wgt = np.maximum(zf[yy, xx], 0.0)
        wsum = wgt.sum()
        if wsum <= 0:
            continue
        xc, yc = (wgt * xx).sum() / wsum, (wgt * yy).sum() / wsum
        cxx = (wgt * (xx - xc) ** 2).sum() / wsum
        cyy = (wgt * (yy - yc) ** 2).sum() / wsum
        cxy = (wgt * (xx - xc) * (yy - yc)).sum() / wsum
        ev, evec = np.linalg.eigh(np.array([[cxx, cxy], [cxy, cyy]]))
        ux, uy = evec[:, 1]
        t = (xx - xc) * ux + (yy - yc) * uy
        length = t.max() - t.min()
        elong = math.sqrt(ev[1] / max(ev[0], 1e-6))
        long_enough = length >= max(MIN_LENGTH_PX, MIN_LENGTH_FWHM * fwhm)
        if elong >= MIN_ELONGATION and long_enough:
            lines.append(((xc + t.min() * ux, yc + t.min() * uy), (xc + t.max() * ux, yc + t.max() * uy)))
        else:
            compact[yy, xx] = True
    return lines, _star_mask(zf, compact, fwhm)


def _star_mask(zf: np.ndarray, compact: np.ndarray, fwhm: float) -> np.ndarray:
    """Discs over the stars of the non-elongated segments: each local maximum of the filtered image there
    that is round (the filtered image one FWHM away from the peak, in 8 directions: smallest / largest >
    STAR_ROUNDNESS; along a trail the two directions of the track stay high), of radius where a Gaussian of
    the PSF's width falls from the peak to HOUGH_SIGMA, plus two FWHM. A trail touching a star keeps its other
    pixels (a whole segment masked would take the trail with the star)."""
    from scipy.ndimage import map_coordinates

    out = np.zeros(zf.shape, dtype=bool)
    size = int(2 * math.ceil(fwhm) + 1)
    # the peaks of every segment: two stars close together make an elongated segment, and their peaks are
    # round as any star's; a trail's peaks are not (bright along the track only)
    peak = (zf == ndimage.maximum_filter(zf, size=size)) & (zf > SEG_SIGMA)
    py, px = np.nonzero(peak)
    if py.size == 0:
        return out
    ang = np.linspace(0.0, 2.0 * math.pi, 8, endpoint=False)
    # the ring about each peak's centroid (3 x 3 moments): about the peak pixel, a compact star off the pixel's
    # centre by half a pixel looks lopsided
    pad = np.pad(zf, 1, mode="edge")
    win = np.stack([pad[py + 1 + dy, px + 1 + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)], axis=1)
    win = np.maximum(win - win.min(axis=1, keepdims=True), 0.0) + 1e-12
    offs = np.array([(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1)], float)
    cy = py + (win * offs[:, 0]).sum(axis=1) / win.sum(axis=1)
    cx = px + (win * offs[:, 1]).sum(axis=1) / win.sum(axis=1)

    def ring(radius):
        sx = cx[:, None] + radius * np.cos(ang)[None, :]
        sy = cy[:, None] + radius * np.sin(ang)[None, :]
        v = map_coordinates(zf, [sy.ravel(), sx.ravel()], order=1, mode="nearest").reshape(sx.shape)
        return np.maximum(v, 1e-6)

    near, far = ring(fwhm), ring(3.0 * fwhm)
    # round one FWHM out and, three FWHM out, not bright in two opposite directions only (a trail wider than
    # the PSF stays bright along its track there: both ways, while across it fades; a star's neighbour is one
    # way); a very bright peak of a round segment is a star whatever its bleed or spikes
    both = np.minimum(far[:, :4], far[:, 4:])  # the two opposite directions of each of the 4 axes
    track = (both.max(axis=1) > HOUGH_SIGMA) & (far.min(axis=1) < STAR_ROUNDNESS * both.max(axis=1))
    round_ = (near.min(axis=1) / near.max(axis=1) > STAR_ROUNDNESS) & ~track
    round_ |= (zf[py, px] > BRIGHT_STAR_SIGMA) & compact[py, px]
    sigma = math.sqrt(2.0) * fwhm * FWHM_TO_SIGMA  # a star in the filtered image: the PSF smoothed by itself
    h, w = zf.shape
    for y, x, ok in zip(py, px, round_):
        if not ok:
            continue
        r = sigma * math.sqrt(2.0 * math.log(max(zf[y, x] / HOUGH_SIGMA, 1.0))) + 2.0 * fwhm
        ri = math.ceil(r)
        y0, y1, x0, x1 = max(0, y - ri), min(h, y + ri + 1), max(0, x - ri), min(w, x + ri + 1)
        yy, xx = np.ogrid[y0:y1, x0:x1]
        out[y0:y1, x0:x1] |= (yy - y) ** 2 + (xx - x) ** 2 <= r * r
    return out


def _mostly_in(mask: np.ndarray, p0, p1) -> bool:
    n = max(2, int(math.hypot(p1[0] - p0[0], p1[1] - p0[1])))
    xs = np.clip(np.rint(np.linspace(p0[0], p1[0], n)).astype(int), 0, mask.shape[1] - 1)
    ys = np.clip(np.rint(np.linspace(p0[1], p1[1], n)).astype(int), 0, mask.shape[0] - 1)
    return mask[ys, xs].mean() > 0.5


def _hough(zf: np.ndarray, compact: np.ndarray, fwhm: float, rng: np.random.Generator):
    from skimage.transform import probabilistic_hough_line

    binary = (zf > HOUGH_SIGMA) & ~ndimage.binary_dilation(compact, iterations=math.ceil(fwhm))
    length = int(max(MIN_LENGTH_PX, MIN_LENGTH_FWHM * fwhm, 0.06 * min(zf.shape)))
    theta = np.linspace(-np.pi / 2, np.pi / 2, 360, endpoint=False)
    segs = probabilistic_hough_line(binary, threshold=10, line_length=length, line_gap=math.ceil(2 * fwhm),
                                    theta=theta, rng=rng)
    return [((float(a[0]), float(a[1])), (float(b[0]), float(b[1]))) for a, b in segs]


def _same_line(a, b, distance_px: float) -> bool:
    (a0, a1), (b0, b1) = a, b
    ang_a = math.atan2(a1[1] - a0[1], a1[0] - a0[0])
    ang_b = math.atan2(b1[1] - b0[1], b1[0] - b0[0])
    dang = abs((ang_a - ang_b + math.pi / 2) % math.pi - math.pi / 2)
    if math.degrees(dang) > MERGE_ANGLE_DEG:
        return False
    La = math.hypot(a1[0] - a0[0], a1[1] - a0[1])
    ux, uy = (a1[0] - a0[0]) / La, (a1[1] - a0[1]) / La
    for p in (b0, b1, (0.5 * (b0[0] + b1[0]), 0.5 * (b0[1] + b1[1]))):
        if abs(-(p[0] - a0[0]) * uy + (p[1] - a0[1]) * ux) > distance_px:
            return False
    return True


def detect_image(data: np.ndarray, *, fwhm_px: float | None = None, bayer: str | None = None,
                 min_snr: float = MIN_SNR, points: bool = False, seed: int = 0, background=None,
                 saturation_adu: float = math.inf) -> list[Detection]:
    """The streaks (and with ``points`` the compact sources) of an image; the module notes. ``background``:
    (background, rms) [ADU] if already measured; pixels at ``saturation_adu`` and SATURATED_PX about them
    are a saturated star's (bleed, spikes, halo): no data for the line finder."""
    from .inject import background as measure_background
    from .inject import unlit_edges

    data = np.asarray(data, dtype=np.float64)
    fwhm = float(fwhm_px or DEFAULT_FWHM_PX)
    unlit = unlit_edges(data)
    # the prescan/overscan and the columns/rows beside it (read-out ramps, the HSC cutout's first 10 lit columns)
    near_unlit = ndimage.binary_dilation(unlit, iterations=NEAR_UNLIT_PX) if unlit.any() else unlit
    ramp_zone = ndimage.binary_dilation(unlit, iterations=RAMP_PX) if unlit.any() else unlit

    def significance(bkg_rms):
        bkg, rms = bkg_rms
        z = (data - bkg) / np.where(rms > 0, rms, np.inf)
        z = np.where(np.isfinite(z) & ~near_unlit, z, 0.0)
        zs = ndimage.gaussian_filter(z, fwhm / 2.3548, mode="constant")
        return z, zs, zs / _robust_sigma(zs[~near_unlit])

    z, zs, zf = significance(background if background is not None else measure_background(data, bayer))
    # second pass: the background again without the light found (a bright trail lifts the first one)
    lit = ndimage.binary_dilation(zf > SEG_SIGMA, iterations=math.ceil(2 * fwhm))
    if lit.any() and lit.mean() < 0.5:
        z, zs, zf = significance(measure_background(data, bayer, mask=lit))
    lines, compact = _segments(zf, fwhm)
    sat = np.isfinite(data) & (data >= saturation_adu)
    if sat.any():
        compact = compact | ndimage.binary_dilation(sat, iterations=int(SATURATED_PX + 4 * fwhm))
        lines = [ln for ln in lines if not _mostly_in(compact, *ln)]
    lines += _hough(zf, compact, fwhm, np.random.default_rng(seed))
    # verify each candidate along its line, without the stars' pixels (no data there: a line through a
    # bright star is not a trail); the best first, a candidate mostly inside a kept trail dropped
    stars = compact
    z_line = np.where(stars, np.nan, z)
    zs_line = np.where(stars, 0.0, zs)
    found = []
    for p0, p1 in lines:
        r = _refine(z_line, zs_line, p0, p1, fwhm)
        if r is None:
            continue
        q0, q1, snr, width = r
        if snr < min_snr or math.hypot(q1[0] - q0[0], q1[1] - q0[1]) < max(MIN_LENGTH_PX, MIN_LENGTH_FWHM * fwhm):
            continue
        if _artefact(q0, q1, width, ramp_zone):
            continue
        found.append((snr, q0, q1, width))
    found.sort(key=lambda f: -f[0])
    taken = np.zeros(z.shape, dtype=bool)
    kept = []
    def covered(q0, q1, snr) -> bool:
        """Mostly inside a kept trail's band, or in the halo of a much brighter kept trail."""
        if _in_wings(q0, q1, [k for k in kept if snr < WING_RATIO * k[0]], fwhm):
            return True
        n = max(2, int(math.hypot(q1[0] - q0[0], q1[1] - q0[1])))
        xs = np.clip(np.rint(np.linspace(q0[0], q1[0], n)).astype(int), 0, z.shape[1] - 1)
        ys = np.clip(np.rint(np.linspace(q0[1], q1[1], n)).astype(int), 0, z.shape[0] - 1)
        return taken[ys, xs].mean() > 0.5

    for snr, q0, q1, width in found:
        if covered(q0, q1, snr):
            continue
        fin = _final(z_line, q0, q1, width, fwhm)
        if fin is None:
            continue
        q0, q1, width, halo = fin
        if math.hypot(q1[0] - q0[0], q1[1] - q0[1]) < max(MIN_LENGTH_PX, MIN_LENGTH_FWHM * fwhm):
            continue
        if covered(q0, q1, snr):  # the fit moved it onto a kept trail
            continue
        kept.append((snr, q0, q1, halo))
        rr, cc, _ = _line_band(z.shape, q0, q1, 1.5 * width + fwhm, width)
        taken[rr, cc] = True
    out = [Detection("streak", q0[0], q0[1], q1[0], q1[1], snr) for snr, q0, q1, _ in kept]
    if points:
        lab, _n = ndimage.label(compact)
        for i, sl in enumerate(ndimage.find_objects(lab)):
            m = lab[sl] == i + 1
            yy, xx = np.nonzero(m)
            wgt = np.maximum(zf[sl][m], 0) + 1e-12
            xc = float((wgt * (xx + sl[1].start)).sum() / wgt.sum())
            yc = float((wgt * (yy + sl[0].start)).sum() / wgt.sum())
            vals = z[sl][m]
            out.append(Detection("point", xc, yc, xc, yc, float(vals.sum() / math.sqrt(vals.size))))
    return out


def _overlap(a, b, fwhm: float) -> bool:
    """True when segment b's projection on a's line overlaps a (within 2 FWHM)."""
    (a0, a1), (b0, b1) = a, b
    La = math.hypot(a1[0] - a0[0], a1[1] - a0[1])
    ux, uy = (a1[0] - a0[0]) / La, (a1[1] - a0[1]) / La
    tb = sorted(((p[0] - a0[0]) * ux + (p[1] - a0[1]) * uy) for p in (b0, b1))
    return tb[1] >= -2 * fwhm and tb[0] <= La + 2 * fwhm


def detect_file(path, *, hdu=None, psf=None, min_snr: float = MIN_SNR, points: bool = False, seed: int = 0,
                bayer=None) -> tuple[list[Detection], dict]:
    """Detect on the image HDU of a FITS frame (chosen as ``newtsim inject`` does). ``psf``: None or
    "measured" (the frame's stars, else DEFAULT_FWHM_PX), a FWHM in pixels ("3px") or arcsec. Returns the
    detections and a summary."""
    from .inject import InjectError, background, measure_psf, read_frame

    hdul, frame = read_frame(path, hdu, bayer=bayer)
    with hdul:
        bkg_rms = background(frame.data, frame.bayer)
        if psf is None or str(psf).lower() == "measured":
            try:
                fwhm, _ = measure_psf(frame, *bkg_rms)
                how = "measured"
            except InjectError:
                fwhm, how = DEFAULT_FWHM_PX, "default (no stars)"
        else:
            text = str(psf).lower()
            fwhm = float(text[:-2]) if text.endswith("px") else float(text) / (frame.pixel_scale_arcsec or math.nan)
            how = "given"
            if not fwhm > 0:
                raise InjectError(f"{psf!r}", key="--psf", expected="a FWHM in px (3px), or arcsec with a WCS")
        dets = detect_image(frame.data, fwhm_px=fwhm, bayer=frame.bayer, min_snr=min_snr, points=points,
                            seed=seed, background=bkg_rms, saturation_adu=frame.saturation_adu)
    for d in dets:
        d.file, d.hdu = Path(path).name, frame.hdu
    return dets, {"file": str(path), "hdu": frame.hdu, "fwhm_px": fwhm, "fwhm": how, "detections": len(dets),
                  "streaks": sum(d.kind == "streak" for d in dets)}


def write_detections(dets: list[Detection], path, *, image_ids: dict | None = None, fwhm_px: float = 2.5) -> None:
    """``dets`` as a COCO results JSON (``.json``) or an ECSV table (any other suffix). ``image_ids``: file
    name -> COCO image id (default: the order of the files, from 1)."""
    path = Path(path)
    files = list(dict.fromkeys(d.file for d in dets))
    ids = image_ids or {f: i + 1 for i, f in enumerate(files)}
    if path.suffix.lower() == ".json":
        rows = []
        for d in dets:
            rows.append({"image_id": int(ids.get(d.file, 1)), "category_id": 1, "bbox": d.bbox(fwhm_px),
                         "score": float(d.score), "kind": d.kind, "x0": d.x0, "y0": d.y0, "x1": d.x1, "y1": d.y1,
                         "x": d.x, "y": d.y, "file_name": d.file})
        path.write_text(json.dumps(rows, indent=1) + "\n")
        return
    from astropy.table import Table

    cols = ["file", "hdu", "kind", "x0", "y0", "x1", "y1", "score"]
    t = Table(rows=[[getattr(d, c) for c in cols] for d in dets] if dets else None,
              names=["file_name"] + cols[1:], dtype=[str, int, str, float, float, float, float, float])
    t["x"] = [d.x for d in dets]
    t["y"] = [d.y for d in dets]
    t["length_px"] = [d.length_px for d in dets]
    t.meta["comments"] = ["newtsim detect: 0-based pixel centres; score = integrated SNR along the track"]
    t.write(path, format="ascii.ecsv", overwrite=True)


def as_dicts(dets: list[Detection]) -> list[dict]:
    return [dict(asdict(d), x=d.x, y=d.y, length_px=d.length_px) for d in dets]
