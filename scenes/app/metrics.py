"""Measurements of a synthetic frame for the scenario table (thesis Annex VII style), numpy/scipy only.

* frame statistics: mean, median, std of the ADU frame;
* a background and noise map: sigma-clipped median and MAD of boxes, interpolated (SExtractor-like);
* visible stars: matched-filter detection above ``nsigma`` (the background-subtracted frame smoothed with
  the PSF's Gaussian, thresholded at ``nsigma`` times the filtered noise), connected regions matched to the
  ``TRUTH`` table: a region holding the position of at least one true star is one visible star (its
  brightest); regions without one are spurious (hot pixels, cosmic rays, the object);
* aperture photometry along a path (a point: circle; a streak or a trail: the stadium around the segment
  from ``(x0, y0)`` to ``(x1, y1)``) with the background from a surrounding stadium annulus, and its SNR
  from the CCD equation written in the frame's own units (Howell 2006, "Handbook of CCD Astronomy", eq. 4.4;
  Merline & Howell 1995):

      F = sum_ap (ADU - b),       var(F) = F / g + n_ap s_b^2 (1 + n_ap / n_ann),      SNR = F / sqrt(var(F))

  with g the electrons per ADU of the written frame (``GAIN``; x b^2 for an average-binned frame), b and
  s_b^2 the background level and its per-pixel variance (read noise, dark and sky shot noise, all in one)
  measured in the annulus. In electrons, for a source of N e- on a background of B e- and read noise R e-
  per pixel, this is the thesis's SNR = N / sqrt(N + n_ap (B + R^2)) plus the background-estimate term.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from detector.stats import clipped_median_std


# ------------------------------------------------------------------------------------------ statistics
def frame_stats(img: np.ndarray, rows_per_block: int = 512) -> dict:
    """Mean, median, std and 4-sigma-clipped std [ADU] of a frame, in row blocks (no full-frame float64 copy).

    The clipped std (every 4th pixel of every 4th row) is the noise of the frame's core, blind to hot
    pixels and sources: the detector docs' "clipped std"."""
    n = img.size
    s = 0.0
    for r in range(0, img.shape[0], rows_per_block):
        s += float(np.sum(img[r:r + rows_per_block], dtype=np.float64))
    mean = s / n
    ss = 0.0
    for r in range(0, img.shape[0], rows_per_block):
        d = img[r:r + rows_per_block].astype(np.float64) - mean
        ss += float(np.dot(d.ravel(), d.ravel()))
    if img.dtype.kind in "ui":  # exact median from the histogram of integer values
        counts = np.bincount(img.ravel())
        cum = np.cumsum(counts)
        lo = int(np.searchsorted(cum, (n - 1) // 2, side="right"))
        hi = int(np.searchsorted(cum, n // 2, side="right"))
        median = 0.5 * (lo + hi)
    else:
        median = float(np.median(img))
    core = clipped_median_std(img[::4, ::4], nsigma=4.0)[1]  # the Gaussian core, blind to hot pixels and sources
    return {"mean": mean, "median": median, "std": math.sqrt(ss / n), "std_clipped": core}


def background_map(img: np.ndarray, box: int | None = 64, nsigma: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """Background level and per-pixel noise maps (float32, the frame's shape) from clipped box statistics.

    Each ``box`` x ``box`` cell gets its sigma-clipped median and clipped std; the cell grids are
    median-filtered (3 x 3, against cells dominated by a bright star) and interpolated bilinearly to every
    pixel (edges held). ``box=None``: 64 pixels, larger on big frames so that there are <= ~2048 cells.
    """
    h, w = img.shape
    box = box or max(64, int(math.sqrt(h * w / 2048)))
    ny, nx = max(1, h // box), max(1, w // box)
    by, bx = h // ny, w // nx
    cells = np.asarray(img[:ny * by, :nx * bx], dtype=np.float32).reshape(ny, by, nx, bx).swapaxes(1, 2)
    cells = cells.reshape(ny, nx, by * bx)
    med = np.empty((ny, nx))
    sig = np.empty((ny, nx))
    for j in range(ny):
        for i in range(nx):
            med[j, i], sig[j, i], _ = clipped_median_std(cells[j, i], nsigma)
    if ny >= 3 and nx >= 3:
        med = ndimage.median_filter(med, size=3, mode="nearest")
        sig = ndimage.median_filter(sig, size=3, mode="nearest")
    return _upsample(med, (h, w), (by, bx)), _upsample(sig, (h, w), (by, bx))


def _upsample(grid: np.ndarray, shape: tuple[int, int], cell: tuple[int, int]) -> np.ndarray:
    gy = (np.arange(shape[0]) + 0.5) / cell[0] - 0.5
    gx = (np.arange(shape[1]) + 0.5) / cell[1] - 0.5
    gy = np.clip(gy, 0, grid.shape[0] - 1)
    gx = np.clip(gx, 0, grid.shape[1] - 1)
    # separable bilinear interpolation: rows first, then columns
    j0 = np.minimum(np.floor(gy).astype(int), grid.shape[0] - 1)
    j1 = np.minimum(j0 + 1, grid.shape[0] - 1)
    ty = (gy - j0)[:, None]
    rows = grid[j0] * (1 - ty) + grid[j1] * ty  # (h, nx)
    i0 = np.minimum(np.floor(gx).astype(int), grid.shape[1] - 1)
    i1 = np.minimum(i0 + 1, grid.shape[1] - 1)
    tx = gx - i0
    return (rows[:, i0] * (1 - tx) + rows[:, i1] * tx).astype(np.float32)


# ------------------------------------------------------------------------------------------- detection
def detect(img: np.ndarray, fwhm_px: float, nsigma: float = 5.0, bkg=None, box: int | None = None
           ) -> tuple[np.ndarray, int, np.ndarray]:
    """Matched-filter detection: label map of the regions above ``nsigma``, their number, the filtered frame.

    The background-subtracted frame is convolved with a normalised Gaussian of the PSF's width; for white
    noise of rms s per pixel the filtered noise is s sqrt(sum k^2), so a pixel is detected when the
    filtered value exceeds nsigma s sqrt(sum k^2) (the point-source matched filter's significance). Outside
    the frame the subtracted image counts as zero (edge pixels are not weighted twice, which would raise
    the filtered noise there).
    """
    level, noise = bkg if bkg is not None else background_map(img, box)
    sigma = max(fwhm_px, 0.5) / (2.0 * math.sqrt(2.0 * math.log(2.0)))
    sub = np.asarray(img, dtype=np.float32) - level
    filt = ndimage.gaussian_filter(sub, sigma, mode="constant", truncate=4.0)  # zero outside: no edge noise boost
    k = np.zeros((2 * int(4 * sigma + 0.5) + 1,) * 2)
    k[k.shape[0] // 2, k.shape[1] // 2] = 1.0
    k = ndimage.gaussian_filter(k, sigma, mode="constant", truncate=4.0)
    gain_noise = math.sqrt(float(np.sum(k * k)))
    mask = filt > nsigma * gain_noise * np.maximum(noise, 1e-12)
    labels, n = ndimage.label(mask)
    return labels, int(n), filt


def match_regions(labels: np.ndarray, n_regions: int, x0, y0, x1, y1, flux, grow: int = 1) -> dict:
    """Detected regions touched by the true sources' paths; each region stands for its brightest source.

    Source ``k`` moves from ``(x0[k], y0[k])`` to ``(x1[k], y1[k])`` (0-based pixel centres; the same point for
    a static source); its path is sampled every <= 0.5 pixel and every region containing a sample (regions
    dilated by ``grow`` pixels) is touched by it. A region belongs to the brightest source touching it; a
    source owning at least one region is visible (a trail broken into pieces by the noise is one visible
    star). Returns ``matched`` (indices of the visible sources), ``regions`` (the labels touched by any
    source) and ``spurious`` (regions touched by none: hot pixels, cosmic rays, unknown sources).
    """
    lab = ndimage.grey_dilation(labels, size=2 * grow + 1) if grow > 0 else labels
    h, w = labels.shape
    x0, y0, x1, y1 = (np.atleast_1d(np.asarray(v, dtype=float)) for v in (x0, y0, x1, y1))
    n = np.ceil(np.hypot(x1 - x0, y1 - y0) / 0.5).astype(np.int64) + 1
    src = np.repeat(np.arange(x0.size), n)
    t = (np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)) / np.maximum(np.repeat(n - 1, n), 1)
    ix = np.rint(x0[src] + t * (x1 - x0)[src]).astype(np.int64)
    iy = np.rint(y0[src] + t * (y1 - y0)[src]).astype(np.int64)
    inside = (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
    hit = np.zeros(ix.size, dtype=np.int64)
    hit[inside] = lab[iy[inside], ix[inside]]
    touched = hit > 0
    fl = np.asarray(flux, dtype=float)
    reg, k = hit[touched], src[touched]
    order = np.lexsort((-fl[k], reg))  # by region, brightest source first
    reg, k = reg[order], k[order]
    first = np.r_[True, reg[1:] != reg[:-1]] if reg.size else np.zeros(0, bool)
    regions = reg[first]
    return {"matched": np.unique(k[first]), "regions": regions, "spurious": int(n_regions - regions.size)}


# ------------------------------------------------------------------------------------------ photometry
def segment_distance(xx, yy, x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
    """Distance of points (xx, yy) from the segment (x0, y0)-(x1, y1) (a point when both ends coincide)."""
    dx, dy = x1 - x0, y1 - y0
    L2 = dx * dx + dy * dy
    if L2 == 0:
        return np.hypot(xx - x0, yy - y0)
    t = np.clip(((xx - x0) * dx + (yy - y0) * dy) / L2, 0.0, 1.0)
    return np.hypot(xx - (x0 + t * dx), yy - (y0 + t * dy))


def path_photometry(img: np.ndarray, x0: float, y0: float, x1: float, y1: float, r_ap: float, r_in: float,
                    r_out: float, gain_e_per_adu: float, mask: np.ndarray | None = None) -> dict:
    """Aperture photometry along a path and its SNR (module docstring), in the frame's ADU.

    Parameters
    ----------
    img : the frame [ADU]
    x0, y0, x1, y1 : ends of the path [pixels, 0-based centres]; equal for a point source
    r_ap : aperture radius around the path [pixels]
    r_in, r_out : background annulus radii around the path [pixels]
    gain_e_per_adu : electrons per ADU of the frame [e-/ADU]
    mask : pixels to leave out of the background annulus (other sources), same shape as ``img``

    Returns
    -------
    dict with ``flux_adu``, ``flux_e``, ``background_adu`` (per pixel), ``noise_adu`` (per pixel),
    ``n_ap``, ``n_ann``, ``snr`` (NaN when the aperture or the annulus is empty)
    """
    h, w = img.shape
    pad = r_out + 1
    xa, xb = int(max(0, math.floor(min(x0, x1) - pad))), int(min(w, math.ceil(max(x0, x1) + pad) + 1))
    ya, yb = int(max(0, math.floor(min(y0, y1) - pad))), int(min(h, math.ceil(max(y0, y1) + pad) + 1))
    nan = {"flux_adu": math.nan, "flux_e": math.nan, "background_adu": math.nan, "noise_adu": math.nan,
           "n_ap": 0, "n_ann": 0, "snr": math.nan}
    if xb <= xa or yb <= ya:
        return nan
    cut = np.asarray(img[ya:yb, xa:xb], dtype=np.float64)
    yy, xx = np.mgrid[ya:yb, xa:xb]
    d = segment_distance(xx, yy, x0, y0, x1, y1)
    ap = d <= r_ap
    ann = (d >= r_in) & (d <= r_out)
    if mask is not None:
        ann &= ~mask[ya:yb, xa:xb]
    if not ap.any() or ann.sum() < 8:
        return nan
    b, s_b, n_ann = clipped_median_std(cut[ann])
    n_ap = int(ap.sum())
    flux = float(np.sum(cut[ap] - b))
    var = max(flux, 0.0) / gain_e_per_adu + n_ap * s_b ** 2 * (1.0 + n_ap / max(n_ann, 1))
    return {"flux_adu": flux, "flux_e": flux * gain_e_per_adu, "background_adu": b, "noise_adu": s_b,
            "n_ap": n_ap, "n_ann": n_ann, "snr": flux / math.sqrt(var) if var > 0 else math.nan}


def analytic_snr(signal_e: float, n_pix: float, background_e: float, read_noise_e: float) -> float:
    """The CCD equation (thesis; Howell 2006 eq. 4.4): N / sqrt(N + n_pix (B + R^2)), all in electrons."""
    return signal_e / math.sqrt(signal_e + n_pix * (background_e + read_noise_e ** 2))


# ------------------------------------------------------------------------------------------ one frame
def frame_gain(header) -> float:
    """Electrons per ADU of the written frame: GAIN, times b^2 for an average-binned frame."""
    g = float(header.get("GAIN", 1.0))
    b = int(header.get("XBINNING", 1))
    return g * b * b if str(header.get("BINMODE", "sum")).strip() == "average" and b > 1 else g


def measure_frame(img: np.ndarray, header, truth: np.ndarray | None, nsigma: float = 5.0, box: int | None = None,
                  ap_fwhm: float = 1.0, ann_fwhm: tuple[float, float] = (2.5, 4.0)) -> dict:
    """The scenario-table row of one frame: statistics, visible stars, median star SNR, target SNR.

    Apertures are ``ap_fwhm`` x FWHM around the path (93.8 % of a Gaussian point source), the background
    annulus from ``ann_fwhm[0]`` to ``ann_fwhm[1]`` x FWHM; FWHM from the header (``PSFFWHM`` / ``PIXSCALE``).
    Light frames without sources get only the statistics.
    """
    row = frame_stats(img)
    row.update({"stars_truth": 0, "stars_visible": 0, "spurious": 0, "star_snr_median": math.nan,
                "target_snr": math.nan, "target_flux_e": math.nan})
    if truth is None or len(truth) == 0 or str(header.get("FRAMETYP", "light")) != "light":
        return row
    fwhm = float(header.get("PSFFWHM", 2.5)) / float(header.get("PIXSCALE", 1.0))
    gain = frame_gain(header)
    bkg = background_map(img, box)
    labels, n, _ = detect(img, fwhm, nsigma, bkg=bkg)
    kind = np.char.strip(np.asarray(truth["kind"]).astype(str))
    stars = np.flatnonzero(kind != "object")
    r_ap = max(1.5, ap_fwhm * fwhm)
    r_in, r_out = max(r_ap + 2, ann_fwhm[0] * fwhm), max(r_ap + 5, ann_fwhm[1] * fwhm)
    occupied = labels > 0  # detected sources stay out of the background annuli
    row["stars_truth"] = int(stars.size)
    t = truth[stars]
    m = match_regions(labels, n, t["x0"], t["y0"], t["x1"], t["y1"], t["flux_e"])
    row["stars_visible"] = int(m["matched"].size)
    snr = np.array([path_photometry(img, *(float(t[k][i]) for k in ("x0", "y0", "x1", "y1")), r_ap, r_in, r_out,
                                    gain, occupied)["snr"] for i in m["matched"]])
    snr = snr[np.isfinite(snr)]
    row["star_snr_median"] = float(np.median(snr)) if snr.size else math.nan
    objects = np.flatnonzero(kind == "object")
    found = set(m["regions"].tolist())
    if objects.size:  # the first object is the target
        o = truth[objects[0]]
        p = path_photometry(img, float(o["x0"]), float(o["y0"]), float(o["x1"]), float(o["y1"]), r_ap, r_in, r_out,
                            gain, occupied)
        row["target_snr"], row["target_flux_e"] = p["snr"], p["flux_e"]
        o_all = truth[objects]
        found |= set(match_regions(labels, n, o_all["x0"], o_all["y0"], o_all["x1"], o_all["y1"], o_all["flux_e"]
                                   )["regions"].tolist())
    row["spurious"] = int(n - len(found))
    return row
