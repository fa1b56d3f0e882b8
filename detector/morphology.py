"""What the residual of a frame looks like, in words and numbers: the description of a missing effect.

When no effect of the catalogue explains a residual (or to check that the one named does), the residual
itself is described by the questions an instrument scientist asks of it:

* **kind**: ``additive`` (the same in ADU wherever the light is), ``multiplicative`` (proportional to the
  model's light: a response, a transmission), ``redistributed`` (light moved around the sources, their
  fluxes kept: a PSF change, a ghost ring) or ``mixed``. Told apart by weighted least squares of the
  binned residual on smooth maps ``A(x, y)`` and ``M(x, y) L(x, y)`` (``L`` the model's light) and, where
  the light is uniform and the two are the same, by the sources: a multiplicative error scales with the
  stars' light too. When the data cannot tell them apart the block says so (``kind_certain`` false).
* **geometry** (a fixed vocabulary): ``gradient`` (a smooth large-scale field: a plane, a quadratic),
  ``radial`` (a function of the distance to a centre, fitted), ``rows`` / ``columns`` (offsets of whole
  lines beyond a smooth field), ``periodic`` (a peak of the power spectrum: fringes, a 2 x 2 mosaic),
  ``sources`` (the excess sits on the sources), ``local`` (a few compact blocks of the block map), ``rings``
  (annuli: a dust donut's shadow, a diffraction or ghost ring; rings about the sources make the pattern
  ``redistributed``), ``blobs`` (compact features off the sources: glints, a latent image), both from the
  band-passed whitened pixel map (:func:`compact_features`), ``streak`` (one straight line segment: a trail;
  :func:`straight_line`), ``noise`` (extra pixel-to-pixel variance without
  a mean pattern). Each family's share of the structured chi2 is reported;
  the geometry lists those that take a sizeable share.
* **scale_px**, **amplitude** (with its unit) and an **explanation** naming the nearest physical families.

Significance: the block map's chi2 beyond its degrees of freedom, in standard deviations
(``(chi2 - n) / sqrt(2 n)``), and the pixel chi2 for added noise. The smooth fit of the described family is
also returned (``empirical``) so the caller can offer it as an empirical map when no catalogue effect fits.
"""

from __future__ import annotations

import hashlib
import math

import numpy as np
import scipy.fft
from scipy import ndimage as ndi
from scipy.ndimage import gaussian_filter

from .effects.image_plane import FIT_FFT_WORKERS  # the one thread setting of the diagnosis's transforms
from .signatures import Residuals, frame_at
from .significance import (
    DETECTION_SIGMA,
    EXPLAINS_MOST,
    FOOTPRINT_SIGMA,
    FRAME_FALSE_ALARM,
    STRONG_EVIDENCE,
    STRUCTURE_SIGMA,
    TRAIL_MIN_FWHM,
)
from .stats import median_square_variance

#: the residual is structured when the block chi2 (or the pixel chi2 for added noise) exceeds its degrees of
#: freedom by this many standard deviations
SIGNIFICANT_SIGMA = STRUCTURE_SIGMA
#: a family is part of the geometry when it takes at least this share of the structured chi2
GEOMETRY_SHARE = 0.25
#: blocks across the shorter side of the frame for the binned maps
BLOCKS = 48
#: a compact feature is detected above this many (robust) standard deviations of the band-passed z map and kept
#: when its peak reaches FEATURE_PEAK of them
FEATURE_DETECT, FEATURE_PEAK = DETECTION_SIGMA, STRUCTURE_SIGMA
#: smoothing scales [output px] of the compact-feature search (a difference of Gaussians s - 6 s each)
FEATURE_SCALES = (1.0, 2.0, 4.0, 8.0)
#: order of the 2-D Legendre basis of the smooth fields (the ``gradient`` family and the kind test)
SMOOTH_ORDER = 3

FAMILIES = {
    ("additive", "gradient"): "straylight or scattered light, a sky or bias gradient, amplifier glow",
    ("additive", "radial"): "glow or straylight centred on a point, a defocused ghost",
    ("additive", "rows"): "row (banding) noise, a bias drifting during the read-out",
    ("additive", "columns"): "column offsets, hot columns, a bias pattern of the read-out, a read-out smear",
    ("additive", "periodic"): "electronic pick-up (a pattern noise), fringing of a sky line",
    ("additive", "local"): "glints, ghosts, hot spots, light leaks",
    ("additive", "streak"): "a satellite or debris trail the scene lacks (add it as a streak of the scene), a "
                            "meteor or an aircraft, a saturated source's bleed, one bright row or column",
    ("multiplicative", "streak"): "the shadow of a scratch or a fibre on a window or filter",
    ("additive", "blobs"): "satellite glints, a persistent (latent) image, hot spots, ghosts of bright sources",
    ("additive", "rings"): "defocused ghosts (out-of-focus reflections of bright sources), halos",
    ("multiplicative", "rings"): "dust shadows (donuts: out-of-focus images of the pupil) on a window or filter",
    ("multiplicative", "blobs"): "dust or stains on a window, filter or the sensor's cover glass",
    ("redistributed", "rings"): "a diffraction or ghost ring around the sources (light moved out of the cores)",
    ("additive", "sources"): "sources the model lacks (faint stars, a missing object) or misplaced sources, an "
                             "amplifier's undershoot or overshoot trailing them",
    ("additive", "noise"): "read noise or kTC noise above the model, a noise gradient",
    ("multiplicative", "gradient"): "a flat-field error, vignetting off the model's centre",
    ("multiplicative", "radial"): "vignetting, a filter's or corrector's radial transmission",
    ("multiplicative", "rows"): "a row-wise response pattern (a rolling-shutter flicker)",
    ("multiplicative", "columns"): "a column-wise response pattern (column gains)",
    ("multiplicative", "periodic"): "fringing (thin-film interference), tree rings of the silicon, a colour filter "
                                    "mosaic",
    ("multiplicative", "local"): "dust shadows (donuts) on a window or filter",
    ("multiplicative", "sources"): "a photometric (zero-point) or non-linearity error of the sources",
    ("multiplicative", "noise"): "pixel response non-uniformity (PRNU) above the model",
    ("redistributed", "sources"): "a PSF change (focus, seeing, jitter), a diffraction or ghost ring",
}


def _blocks(a: np.ndarray, b: int, weights: np.ndarray | None = None) -> np.ndarray:
    h, w = (a.shape[0] // b) * b, (a.shape[1] // b) * b
    x = a[:h, :w].reshape(h // b, b, w // b, b)
    if weights is None:
        return x.sum(axis=(1, 3))
    return (x * weights[:h, :w].reshape(h // b, b, w // b, b)).sum(axis=(1, 3))


def _legendre_basis(ny: int, nx: int, order: int) -> np.ndarray:
    """Products P_i(u) P_j(v), 1 <= i + j <= order, on an ny x nx grid of u, v in [-1, 1]: (terms, ny, nx)."""
    u = np.polynomial.legendre.legvander(np.linspace(-1, 1, nx), order)
    v = np.polynomial.legendre.legvander(np.linspace(-1, 1, ny), order)
    return np.stack([v[:, j][:, None] * u[:, i][None, :] for i in range(order + 1) for j in range(order + 1)
                     if 1 <= i + j <= order])


def _wls(y: np.ndarray, w: np.ndarray, temps: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """Weighted least squares of y on temps (terms, n) with a free constant: (coefficients, delta chi2, fit)."""
    x = np.vstack([np.ones((1, y.size)), temps]) if temps.size else np.ones((1, y.size))
    sw = np.sqrt(w)
    c = np.linalg.lstsq((x * sw).T, y * sw, rcond=None)[0]
    fit = c @ x
    const = float(np.sum(w * y) / max(np.sum(w), 1e-300))
    chi0 = float(np.sum(w * (y - const) ** 2))
    return c[1:], float(np.sum(w * (y - fit) ** 2)) - chi0, fit - c[0]


def _radial(y, w, yy, xx, ny, nx):
    """Best radial fit (a + b rho^2 + c rho^4 about a grid-searched centre): (delta chi2, fit, centre)."""
    best = (0.0, np.zeros_like(y), (0.0, 0.0))
    scale = max(ny, nx)
    for cy in np.linspace(-0.5 * ny, 1.5 * ny, 9):
        for cx in np.linspace(-0.5 * nx, 1.5 * nx, 9):
            r2 = ((yy - cy) ** 2 + (xx - cx) ** 2) / scale ** 2
            _, d, fit = _wls(y, w, np.stack([r2, r2 * r2]))
            if d < best[0]:
                best = (d, fit, (cy, cx))
    return best


def _cut(z: np.ndarray) -> tuple[slice, slice] | None:
    """The central (at most 512 x 512) square of a map that the periodogram looks at; None below 16 x 16."""
    side = min(512, *z.shape)
    if side < 16:
        return None
    y0, x0 = (z.shape[0] - side) // 2, (z.shape[1] - side) // 2
    return slice(y0, y0 + side), slice(x0, x0 + side)


def tested_frequencies(shape: tuple[int, ...]) -> int:
    """The number of frequencies the periodogram of :func:`_peak` searches on a map of ``shape``: those of the
    rfft2 of its central cut (:func:`_cut`, at most 512 x 512)."""
    side = min(512, *shape)
    return side * (side // 2 + 1)


def periodic_contrast(n_frequencies: int, frames: int = 1) -> float:
    """The bar of a periodogram peak over the median power, significant on its own among ``n_frequencies``
    frequencies searched: a bin of a white noise's periodogram is exponential (chi2 with 2 dof), so P(bin > c x
    median) = 2^-c, and the strongest of n bins passes ``c = log2(n / FRAME_FALSE_ALARM)`` once in
    1 / FRAME_FALSE_ALARM frames (the look-elsewhere effect, as :func:`_peak_sigma`): 27.0 over the 131 584
    frequencies of a 512 x 512 cut, 25.0 over those of a 256 x 256 one. The strongest of ``frames`` frames' (a
    series' worst frame) passes it as rarely with ``n`` times ``frames`` frequencies."""
    return math.log2(max(int(n_frequencies), 1) * max(int(frames), 1) / FRAME_FALSE_ALARM)


def periodic_bar(shape: tuple[int, ...], frames: int = 1) -> float:
    """:func:`periodic_contrast` of the frequencies :func:`_peak` searches on a map of ``shape`` (in each of
    ``frames`` frames)."""
    return periodic_contrast(tested_frequencies(shape), frames)


def row_power_factor(w: np.ndarray, row_var_adu2: float, whitened: bool = True) -> float:
    """The expected periodogram power of the zero horizontal frequency (``fx = 0``: patterns constant along
    the rows) over that of every other frequency, for noise whose pixels of one row share an offset (row
    noise: covariance ``c = row_var_adu2`` [ADU^2] between any two pixels of a row, none between rows; the
    pixels' own variances ``1 / w`` include it).

    ``w`` [1/ADU^2] are the pixels' weights (inverse total variances, zero off the fitted pixels). In the
    whitened map ``z = r sqrt(w)`` a pixel is ``sqrt(w) (e + a_y)``, its own noise ``e`` (variance
    ``1/w - c``) plus its row's offset ``a_y`` (variance ``c``). A frequency with ``fx != 0`` sums the offsets
    of a row to nothing and sees ``sum (1 - c w)``; at ``fx = 0`` a row's sum ``S_y = sum_x z`` has variance
    ``n_y + c [(sum_x sqrt w)^2 - sum_x w]``. The periodogram's mean power is the sum of these variances
    (rows independent, Wiener-Khinchin), so

        g = (sum_y n_y + c sum_y [(sum_x sqrt w)^2 - sum_x w]) / (sum_y n_y - c sum w)

    (``(sum 1/w + c sum_y n_y (n_y - 1)) / (sum 1/w - c sum_y n_y)`` for the residual in ADU, not whitened).
    With ``n_x`` pixels per row and correlation ``rho = c w``: ``g ~ (1 + (n_x - 1) rho) / (1 - rho)``, 79 on
    the 512-wide cut of the 8 x 8-binned full IMX411 frame with 1 e- row noise (rho = 0.13)."""
    c = float(row_var_adu2)
    ok = w > 0
    n = ok.sum(axis=1).astype(np.float64)
    if c <= 0 or n.sum() == 0:
        return 1.0
    wg = np.where(ok, w, 0.0)
    if whitened:
        sq = np.sqrt(wg)
        num = float(n.sum()) + c * float(np.sum(sq.sum(axis=1) ** 2 - wg.sum(axis=1)))
        den = float(n.sum()) - c * float(wg.sum())
    else:
        white = float(np.sum(1.0 / w[ok]))
        num = white + c * float(np.sum(n * (n - 1.0)))
        den = white - c * float(n.sum())
    return num / max(den, 1e-3 * num)


def _cut_row_factor(wmap: np.ndarray, row_var_adu2: float) -> float:
    """:func:`row_power_factor` of the cut :func:`_peak` looks at (whitened map)."""
    sl = _cut(wmap)
    return 1.0 if sl is None else row_power_factor(wmap[sl], row_var_adu2)


#: cycles across the window below which the periodogram of the unsmoothed map (the wide search of
#: :func:`describe`, asked when no family holds the structure) leaves a frequency out as a smooth field's: twice
#: the cycles the smooth basis itself holds (a Legendre polynomial of order SMOOTH_ORDER has at most SMOOTH_ORDER
#: zeros, SMOOTH_ORDER / 2 cycles), so rings or fringes of 3 to 6 cycles across the window (tree rings 56 px apart
#: on a 256 px window) are periods, not a smooth field (the other searches leave out LINE_PERIOD_MIN_CYCLES)
WIDE_SMOOTH_CYCLES = float(SMOOTH_ORDER)


def _spectrum(z: np.ndarray, row_factor: float = 1.0, smooth_cycles: float | None = None):
    """The periodogram of the central cut of ``z`` divided by its expected shape under the null (the ``fx = 0``
    column by ``row_factor``, :func:`row_power_factor`), the lowest frequencies (smooth fields, ``smooth_cycles``
    across the cut or fewer; default LINE_PERIOD_MIN_CYCLES) zeroed: (power, |F| likewise scaled, fy, fx, side)."""
    if smooth_cycles is None:
        smooth_cycles = LINE_PERIOD_MIN_CYCLES
    sl = _cut(z)
    cut = np.nan_to_num(z[sl])
    side = cut.shape[0]
    fft = np.abs(np.fft.rfft2(cut - cut.mean()))
    fy = np.fft.fftfreq(side)[:, None]
    fx = np.fft.rfftfreq(side)[None, :]
    fft = np.where(np.hypot(fy, fx) > smooth_cycles / side, fft, 0.0)
    fft[:, 0] /= math.sqrt(max(row_factor, 1.0))
    return fft * fft, fft, fy, fx, side


def _peak(z: np.ndarray, row_factor: float = 1.0) -> tuple[float, float, float]:
    """(period [px], peak power over the median power, the share of the power in the peak) of the strongest
    spatial frequency of a map, the lowest frequencies (smooth fields) excluded. ``row_factor``: the expected
    power of the ``fx = 0`` column over the rest under the null (:func:`row_power_factor`: row noise puts its
    power there, a line along ``fy`` whose strongest bin is no period of anything)."""
    return _peak_of(_spectrum(z, row_factor) if _cut(z) is not None else None)


def _peak_of(spec) -> tuple[float, float, float]:
    """:func:`_peak` of a periodogram already taken (:func:`_spectrum`'s tuple; None: no cut, no peak)."""
    if spec is None:
        return 0.0, 0.0, 0.0
    p, _, fy, fx, side = spec
    f = np.hypot(fy, fx)
    k = int(np.argmax(p))
    med = float(np.median(p[p > 0])) if np.any(p > 0) else 0.0
    ky, kx = np.unravel_index(k, p.shape)
    near = p[max(ky - 1, 0):ky + 2, max(kx - 1, 0):kx + 2].sum()
    if ky in (0, 1, side - 1) or kx <= 1:  # and its mirror image across the axis
        near += p[(-ky - 1) % side:(-ky - 1) % side + 3, max(kx - 1, 0):kx + 2].sum() if ky else 0.0
    # (period, contrast over the median power, the peak's share of the whole power)
    return ((1.0 / float(f.ravel()[k]) if f.ravel()[k] > 0 else 0.0), (float(p.ravel()[k]) / med if med > 0 else 0.0),
            float(near / max(p.sum(), 1e-300)))


#: half-width [frequency bins] of the ring of a periodogram at the strongest frequency's radius
RING_BINS = 1.0


def ring_contrast(spec) -> float:
    """The strongest frequency's power over the median power of the frequencies at its radius (within RING_BINS):
    a period (a sinusoid, fringes, the arcs of rings about a far centre) puts its power into a few directions at
    its radius, the rest of that ring holding noise only; a smooth random field (a flat-field's large scales) fills
    every direction at every radius of its band, and its strongest bin is only the continuum's largest. Against the
    same bar as the whole periodogram's (:func:`periodic_bar`): the null is a spectrum white around each radius.
    ``spec``: the periodogram (:func:`_spectrum`'s tuple; None: no cut)."""
    if spec is None:
        return 0.0
    p, _, fy, fx, side = spec
    rad = np.hypot(fy, fx) * side  # [frequency bins]
    k = int(np.argmax(p))
    ring = (np.abs(rad - rad.ravel()[k]) <= RING_BINS) & (p > 0)
    med = float(np.median(p[ring])) if ring.any() else 0.0
    return float(p.ravel()[k]) / med if med > 0 else 0.0


def periodic_line(res) -> tuple[float, float, float]:
    """(period [px], contrast, share) of the strongest spatial frequency of a frame's whitened residual (the
    levels refitted, its smooth part at the block scale taken out): the peak's power over the median power
    (:func:`periodic_bar` of the frame's shape is significant on its own) and its share of the whole (high-passed) power. A
    white noise spreads its power over every frequency; a pick-up pattern puts it into one."""
    shape = res.data_adu.shape
    idx, r, w = res.flat_profiled()
    zmap = np.zeros(shape, np.float64)
    wmap = np.zeros(shape, np.float64)
    zmap.ravel()[idx] = r * np.sqrt(w)
    wmap.ravel()[idx] = w
    b = int(max(2, min(shape) // BLOCKS))
    zmap = zmap - block_smooth(res, zmap, b, keep=True)
    return _peak(zmap, _cut_row_factor(wmap, float(res.row_var_adu2)))


def block_smooth(res: Residuals, zmap: np.ndarray, b: int, keep: bool = False) -> np.ndarray:
    """``gaussian_filter(zmap, b, mode="nearest")`` (:func:`gaussian_nearest_fft`): a z map's smooth part at the
    block scale ``b`` [px], the part the periodic search takes out. The row-noise candidate's
    :func:`periodic_line` and :func:`describe` smooth the same z map of one comparison, and a Gaussian of tens of
    pixels over a whole frame costs seconds: with ``keep`` the map is kept with ``res`` (one, identified by the z
    map's bytes, ~0.02 s to hash); without, a kept map of the same z map is handed over (and no longer kept),
    else it is computed. The same numbers either way. Do not modify the returned array."""
    z = np.ascontiguousarray(zmap)
    key = (hashlib.blake2b(z.view(np.uint8).reshape(-1), digest_size=16).digest(), z.shape, z.dtype.str, int(b))
    kept = res.forget("morphology_block_smooth")
    if kept is not None and kept[0] == key:
        out = kept[1]
    else:
        out = gaussian_nearest_fft(z, b)
    if keep:
        res.memo("morphology_block_smooth", lambda: (key, out))
    return out


def gaussian_nearest_fft(z: np.ndarray, sigma_px: float, truncate: float = 4.0) -> np.ndarray:
    """``scipy.ndimage.gaussian_filter(z, sigma_px, mode="nearest", truncate=truncate)`` (the same sampled
    kernel, ``exp(-x^2 / 2 sigma^2)`` for ``|x| <= int(truncate sigma + 0.5)``, normalised to sum 1, applied
    along each axis in turn over the edge-extended array) done as a linear convolution in Fourier space: the
    same numbers to rounding (~1e-15 of the map's scale), in a fraction of the time for a wide kernel (a
    direct correlation costs the kernel's ~8 sigma taps per pixel and axis, the transform ~log of the row's
    length)."""
    sigma = float(sigma_px)
    r = int(truncate * sigma + 0.5)
    x = np.arange(-r, r + 1, dtype=np.float64)
    k = np.exp(-0.5 / sigma ** 2 * x ** 2)
    k /= k.sum()
    out = np.asarray(z, np.float64)
    for axis in range(out.ndim):
        n = out.shape[axis]
        length = scipy.fft.next_fast_len(n + 4 * r, real=True)  # the padded row (n + 2r) convolved with 2r + 1 taps
        pad = [(0, 0)] * out.ndim
        pad[axis] = (r, r)
        spec = scipy.fft.rfft(np.pad(out, pad, mode="edge"), length, axis=axis, workers=FIT_FFT_WORKERS)
        shape = [1] * out.ndim
        shape[axis] = spec.shape[axis]
        spec *= scipy.fft.rfft(k, length).reshape(shape)
        full = scipy.fft.irfft(spec, length, axis=axis, workers=FIT_FFT_WORKERS)
        keep = [slice(None)] * out.ndim
        keep[axis] = slice(2 * r, 2 * r + n)  # the full convolution's samples centred on the input's pixels
        out = full[tuple(keep)]
    return np.ascontiguousarray(out, dtype=z.dtype)


def _band(z: np.ndarray, ok: np.ndarray, s: float) -> np.ndarray:
    """The z map band-passed about the scale ``s`` [px]: a difference of Gaussians (s - 6 s) by normalised
    convolution over the fitted pixels (masked pixels neither pull the map to zero nor make edges), zero off them."""
    wt = ok.astype(np.float64)

    def smooth(sig):
        return gaussian_filter(z, sig, mode="nearest") / np.maximum(gaussian_filter(wt, sig, mode="nearest"), 1e-3)
    return np.where(ok, smooth(s) - smooth(6.0 * s), 0.0)


#: output pixels up to which compact features (rings, blobs) are searched at full resolution: the search
#: (four band-passes of the whitened map and a connected-region analysis) costs ~0.5 s on 512^2 and ~9 s on
#: 2048^2; bin a larger frame (``--set detector.binning=...``) to look for rings and blobs in it
FEATURE_MAX_PIXELS = 1_100_000


def compact_features(z: np.ndarray, ok: np.ndarray, on_source: np.ndarray | None = None,
                     scales=FEATURE_SCALES) -> dict:
    """Compact features of a whitened residual map: rings (annuli) and blobs, per smoothing scale.

    The map ``z`` (residual over its standard deviation, 0 off the fitted pixels ``ok``) is band-passed about
    each scale ``s`` (a difference of Gaussians s - 6 s, which removes smooth fields) and divided by its robust
    standard deviation (1.4826 MAD: any correlation of the noise is included); connected regions of one sign
    above FEATURE_DETECT whose peak reaches FEATURE_PEAK are features. The shape test is topological: a feature
    cut at half its own peak is a **ring** when the cut encloses a hole (``binary_fill_holes`` adds at least
    15 % of its filled area and at least pi s^2), the signature of an annulus (a dust donut's shadow: the
    defocused pupil with its central obstruction; a diffraction or ghost ring around a source); otherwise a
    **blob** (a glint, a latent image, a hot spot) when it is compact (at most 2 % of the frame) and not on a
    model source (``on_source``: pixels of the sources' cores; a residual sitting on them is the ``sources``
    geometry instead). A ring is ``on_source`` when its filled footprint holds a source core.

    Rings centred on sources form their own family, ``srings`` (a property of the sources' light, not a free
    ring like a dust donut). Returns, for each family ``f`` of "rings", "blobs", "srings": ``f`` (share),
    ``n_f``, ``<f without s>_radius_px`` (median), ``scale_f``, ``footprint[f]`` (bool map); and "peak_sigma"
    (the strongest kept feature's band-passed peak over the map's robust standard deviation);
    a share is the band-passed chi2 excess in the family's footprints over the whole frame's, at the scale
    where it is largest."""
    fams = ("rings", "blobs", "srings")
    best = {"peak_sigma": 0.0, "footprint": {f: np.zeros(z.shape, bool) for f in fams}}
    for f in fams:
        best.update({f: 0.0, f"n_{f}": 0, f"{f[:-1]}_radius_px": 0.0, f"scale_{f}": 0.0})
    n_ok = int(ok.sum())
    if n_ok < 256:
        return best
    per_scale = []
    for s in scales:
        if 24 * s > min(z.shape):
            break
        bm = _band(z, ok, s)
        v = bm[ok]
        sig = 1.4826 * float(np.median(np.abs(v - np.median(v))))
        if not sig > 0:
            continue
        q = (bm / sig) ** 2
        total = float(q[ok].sum()) - n_ok
        if total <= 0:
            continue
        foot = {f: np.zeros(z.shape, bool) for f in fams}
        radii = {f: [] for f in fams}
        peak = {f: 0.0 for f in fams}
        blobs, rings = [], []
        for sign in (1.0, -1.0):
            lab, n = ndi.label(sign * bm > FEATURE_DETECT * sig)
            if n == 0:
                continue
            peaks = ndi.maximum(sign * bm, lab, np.arange(1, n + 1))
            for i, (sl, pk) in enumerate(zip(ndi.find_objects(lab), peaks)):
                if pk < FEATURE_PEAK * sig:
                    continue
                mine = lab[sl] == i + 1
                if mine.sum() < math.pi * s * s:
                    continue
                pad = int(3 * s) + 2
                y0, y1 = max(sl[0].start - pad, 0), min(sl[0].stop + pad, z.shape[0])
                x0, x1 = max(sl[1].start - pad, 0), min(sl[1].stop + pad, z.shape[1])
                half, _ = ndi.label(sign * bm[y0:y1, x0:x1] > 0.5 * pk)
                core = half[lab[y0:y1, x0:x1] == i + 1]
                keep = np.isin(half, np.unique(core[core > 0]))
                filled = ndi.binary_fill_holes(keep)
                hole = int(filled.sum() - keep.sum())
                ring = hole >= 0.15 * filled.sum() and hole >= math.pi * s * s
                src = bool(on_source is not None and on_source[y0:y1, x0:x1][filled].any())
                rad = math.sqrt(filled.sum() / math.pi)
                if ring:
                    rings.append(("srings" if src else "rings", y0, y1, x0, x1, filled, rad, float(pk / sig)))
                    continue
                else:
                    # a blob near a source (within its own radius or 3 s: a source's ring cut by a mask, a
                    # source's halo) belongs to the sources; one cut by the frame's border cannot be told
                    near = ndi.binary_dilation(filled, iterations=int(max(rad, 3 * s)))
                    src = bool(on_source is not None and on_source[y0:y1, x0:x1][near].any())
                    edge = (y0 == 0 and filled[0].any()) or (y1 == z.shape[0] and filled[-1].any()) or \
                        (x0 == 0 and filled[:, 0].any()) or (x1 == z.shape[1] and filled[:, -1].any())
                    if src or edge or filled.sum() > 0.02 * z.size:
                        continue
                    blobs.append((y0, y1, x0, x1, filled, rad, float(pk / sig)))
        per_scale.append((s, q, total, foot, radii, peak, blobs, rings))
    # a feature and its band-passed echo: the difference of Gaussians turns a ring's interior into a blob of
    # the other sign (a coarse scale blurs the ring into a disc), and a blob's surround into a ring of the
    # other sign. The stronger of the two is the feature: a ring holding a stronger blob (at any scale) is
    # that blob's echo; a blob inside or on a ring it does not outshine is the ring's
    every_blob = [b for *_, blobs, _ in per_scale for b in blobs]

    def outshone(ring) -> bool:
        _, y0, y1, x0, x1, filled, _, pk = ring
        return any(bp > pk and _overlap((y0, y1, x0, x1, filled), (by0, by1, bx0, bx1, bf))
                   for by0, by1, bx0, bx1, bf, _, bp in every_blob)

    rings_any = np.zeros(z.shape, bool)
    for s, q, total, foot, radii, peak, blobs, rings in per_scale:
        for ring in rings:
            if outshone(ring):
                continue
            fam, y0, y1, x0, x1, filled, rad, pk = ring
            foot[fam][y0:y1, x0:x1] |= filled
            radii[fam].append(rad)
            peak[fam] = max(peak[fam], pk)
        rings_any |= foot["rings"] | foot["srings"]
    for s, q, total, foot, radii, peak, blobs, _ in per_scale:
        for y0, y1, x0, x1, filled, rad, pk in blobs:
            if rings_any[y0:y1, x0:x1][filled].any():
                continue
            foot["blobs"][y0:y1, x0:x1] |= filled
            radii["blobs"].append(rad)
            peak["blobs"] = max(peak["blobs"], pk)
        for fam in fams:
            share = max(float(q[foot[fam] & ok].sum()) - int((foot[fam] & ok).sum()), 0.0) / total
            if radii[fam] and share > best[fam]:
                best.update({fam: min(share, 1.0), f"n_{fam}": len(radii[fam]),
                             f"{fam[:-1]}_radius_px": float(np.median(radii[fam])), f"scale_{fam}": s})
                best["footprint"][fam] = foot[fam]
                best["peak_sigma"] = max(best["peak_sigma"], peak[fam])
    return best


def _overlap(a, b) -> bool:
    """Do two footprints ``(y0, y1, x0, x1, mask)`` (a mask over its own box) share a pixel?"""
    y0, y1, x0, x1 = max(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), min(a[3], b[3])
    if y0 >= y1 or x0 >= x1:
        return False
    return bool((a[4][y0 - a[0]:y1 - a[0], x0 - a[2]:x1 - a[2]] & b[4][y0 - b[0]:y1 - b[0], x0 - b[2]:x1 - b[2]]).any())


def block_chi2(res: Residuals, delta_adu: np.ndarray | None = None,
               extra_var_adu2: np.ndarray | float | None = None) -> tuple[float, int]:
    """(chi2, number) of the weighted block means of the level-profiled residual (minus ``delta_adu``): the
    large-scale structure a mean pattern leaves, blind to pixel-to-pixel noise. With ``extra_var_adu2`` (a
    candidate's added pixel variance [ADU^2], its positive part) the block means' variances include it
    (``sum w^2 e / (sum w)^2``): a white pixel pattern's block means scatter by its own variance too, which is
    the candidate's scatter, not a structure it leaves."""
    shape = res.data_adu.shape
    idx, r, w = res.flat_profiled()
    if delta_adu is not None:
        r = res.project(r - frame_at(delta_adu, idx))
    if idx.size < 64:
        return 0.0, 0
    rmap = np.zeros(shape, np.float64)
    wmap = np.zeros(shape, np.float64)
    rmap.ravel()[idx] = r
    wmap.ravel()[idx] = w
    b = int(max(2, min(shape) // BLOCKS))
    sw = _blocks(wmap, b)
    ok = sw > 0
    mean = _blocks(rmap, b, wmap)[ok] / sw[ok]
    var_b = 1.0 / sw[ok] + float(res.row_var_adu2) / b  # a block mean shares the offsets of its b rows
    if extra_var_adu2 is not None:
        emap = np.zeros(shape, np.float64)
        emap.ravel()[idx] = np.maximum(frame_at(np.broadcast_to(extra_var_adu2, shape), idx), 0.0)
        var_b = var_b + _blocks(emap * wmap * wmap, b)[ok] / sw[ok] ** 2
    wb = 1.0 / var_b
    return float(np.sum(mean * mean * wb)), int(ok.sum())


def describe(res: Residuals, delta_adu: np.ndarray | None = None, frames: int = 1) -> dict:
    """The morphology of the level-profiled residual of ``res`` (minus ``delta_adu``, a candidate's mean
    change, when given): the contract's ``residual_morphology`` block, plus ``shares`` (each family's share
    of the structured chi2), ``significance_sigma`` and ``empirical`` (``{"kind", "map"}``: the smooth fit of
    the described pattern on the output pixels [ADU for additive, relative for multiplicative], or None).
    ``frames``: the frames of a series this one is among, whose worst description stands for the series: the
    searches whose bar is a false-alarm rate (a period, a streak) then count every frame's trials."""
    shape = res.data_adu.shape
    idx, r, w = res.flat_profiled()
    if delta_adu is not None:
        r = res.project(r - frame_at(delta_adu, idx))
    out = {"significant": False, "kind": "additive", "kind_certain": True, "geometry": [], "scale_px": 0.0,
           "amplitude": 0.0, "unit": "ADU", "explanation": "the residual looks like noise", "shares": {},
           "significance_sigma": 0.0, "empirical": None}
    if idx.size < 64:
        return out
    rmap = np.zeros(shape, np.float64)
    wmap = np.zeros(shape, np.float64)
    rmap.ravel()[idx] = r
    wmap.ravel()[idx] = w
    light = np.asarray(res.photo_adu, np.float64)
    b = int(max(2, min(shape) // BLOCKS))
    sw = _blocks(wmap, b)
    ok = sw > 0
    if ok.sum() < 16:
        return out
    mean = np.where(ok, _blocks(rmap, b, wmap) / np.where(ok, sw, 1), 0.0)  # weighted block means [ADU]
    lb = np.where(ok, _blocks(light, b, wmap) / np.where(ok, sw, 1), 0.0)  # the light there [ADU]
    ny, nx = mean.shape
    yy, xx = np.mgrid[0:ny, 0:nx].astype(np.float64)
    # the variance of a block mean: its pixels' own, plus the row offsets (row noise) its b rows share
    row_var = float(res.row_var_adu2)
    y, wb = mean[ok], 1.0 / (1.0 / sw[ok] + row_var / b)
    zb = y * np.sqrt(wb)
    nb = y.size
    block_excess = float(np.sum(zb * zb) - nb)
    block_sigma = block_excess / math.sqrt(2 * nb)
    # added noise: the pixel chi2 beyond the block means' share
    pix_chi2 = float(np.sum(r * r * w))
    noise_excess = pix_chi2 - idx.size - max(block_excess, 0.0) * 1.0
    noise_sigma = noise_excess / math.sqrt(2 * idx.size)
    out["significance_sigma"] = round(max(block_sigma, noise_sigma), 2)
    # compact features (rings, blobs) of the whitened pixel map: a few of them are significant on their own
    # even when the frame's chi2 dilutes them (a glint, a latent image)
    okp = wmap > 0
    zp = np.where(okp, rmap * np.sqrt(wmap), 0.0)
    on_source = None
    if res.background_adu is not None:
        srcmap = np.asarray(res.model_adu, np.float64) - res.background_adu
        on_source = srcmap > SOURCE_KERNEL_CORE_SIGMA * np.sqrt(np.maximum(np.asarray(res.var_adu2, np.float64), 1e-12))
    if zp.size <= FEATURE_MAX_PIXELS:
        feats = compact_features(zp, okp, on_source)
    else:  # the band-passed search costs ~9 s on 2048^2: larger frames keep the block-map families only
        feats = compact_features(np.zeros((16, 16)), np.zeros((16, 16), bool))
    # rings about the sources: at least two, and twice as many as the free ones
    rings_on_src = feats["n_srings"] >= 2 and feats["n_srings"] >= 2 * feats["n_rings"]
    n_feat = feats["n_rings"] + feats["n_blobs"] + (feats["n_srings"] if rings_on_src else 0)
    gain = res.gain
    if max(block_sigma, noise_sigma) < SIGNIFICANT_SIGMA:
        if n_feat and feats["peak_sigma"] >= FEATURE_PEAK:
            out["significant"] = True
            out["significance_sigma"] = round(max(out["significance_sigma"], feats["peak_sigma"]), 2)
            out.update(_compact_only(res, feats, rmap, light))
            out["empirical"] = _feature_map(feats, rmap, wmap, light,
                                            "additive" if out["kind"] == "redistributed" else out["kind"], res)
            # features strung along one straight line are a streak (a faint trail found piece by piece) when the
            # line's own map takes most (EXPLAINS_MOST) of the chi2 the features' map takes
            line = straight_line(rmap, wmap) if out["kind"] == "additive" else None
            if is_streak(line, frames):
                smap = _streak_map(line, shape)
                if out["empirical"] is None or _map_gain(smap, rmap, wmap, light) >= \
                        EXPLAINS_MOST * _map_gain(out["empirical"], rmap, wmap, light):
                    amp, unit, desc = _streak_words(line, gain)
                    geometry = ["streak"] + [g for g in out["geometry"] if g != "streak"]
                    share = min(1.0, line["chi2"] / max(pix_chi2 - idx.size, 1e-300))
                    out.update(geometry=geometry, scale_px=round(line["fwhm_px"], 2), amplitude=round(amp, 4),
                               unit=unit, explanation=_words("additive", geometry, desc), empirical=smap,
                               shares={**out["shares"], "streak": round(share, 3)})
            return out
        # one spatial frequency far above the rest: a pick-up or fringe pattern too weak to move the chi2. The
        # fx = 0 column is measured against the power the model's row noise puts there (row_power_factor)
        zhp = zp - block_smooth(res, zp, b, keep=True)
        period, contrast, _ = _peak(zhp, _cut_row_factor(wmap, row_var))
        if contrast >= periodic_bar(zhp.shape, frames):
            out["significant"] = True
            out["significance_sigma"] = round(max(out["significance_sigma"], _peak_sigma(contrast, zhp)), 2)
            out.update(_periodic_only(res, period, contrast, zhp, wmap))
            out["empirical"] = _periodic_map(rmap, wmap, light, out["kind"], row_var)
            return out
        # light locked to the sources in a shape no ring or blob has (a trail, a one-sided halo): the residual
        # stacked about them, as a kernel of their light; or light along the columns through them (a read-out
        # smear), whose outlier columns the fitted pixels leave out. A smear's columns pass through its sources,
        # so the kernel about them sees a piece of it too: when both are there, the description is the one
        # whose map takes more chi2 from the fitted pixels (the kernel's own pixels are a subset of them)
        ker = source_kernel(res, rmap, wmap) if zp.size <= FEATURE_MAX_PIXELS else None
        if ker is not None and ker["sigma"] >= SIGNIFICANT_SIGMA:
            out["significant"] = True
            out["significance_sigma"] = round(max(out["significance_sigma"], ker["sigma"]), 2)
            out.update(_kernel_words(ker))
            out["empirical"] = {"kind": "additive", "map": ker["map"]}
        else:
            # a straight line significant on its own among every line searched (:func:`streak_bar`: at most once
            # in 1 / FRAME_FALSE_ALARM frames of white noise), standing alone and elongated (:func:`is_streak`): a
            # faint trail (a satellite, debris) whose chi2 the frame's own dilutes. Searched with the rows' own
            # offsets taken out where the model has row noise (the search's weights hold the pixels' variance
            # only: row offsets are lines too, and lines a degree or two off the rows add them up), against the
            # frame's own scatter and without its outliers (:func:`_line_search_map`); a line along a pixel axis
            # is one row or column, which the line families judge
            line = straight_line(_line_search_map(rmap, wmap, row_var), wmap)
            if is_streak(line, frames) and not along_pixel_axis(line):
                amp, unit, desc = _streak_words(line, gain)
                share = min(1.0, line["chi2"] / max(pix_chi2 - idx.size, 1e-300))
                geometry = ["streak", "local"]
                out.update(significant=True, kind="additive", kind_certain=True, geometry=geometry,
                           significance_sigma=round(max(out["significance_sigma"], streak_sigma(line)), 2),
                           scale_px=round(line["fwhm_px"], 2), amplitude=round(amp, 4), unit=unit,
                           explanation=_words("additive", geometry, desc), shares={"streak": round(share, 3)},
                           empirical=_streak_map(line, shape))
        cols = _columns_through_sources(res)
        if cols and (not out["significant"] or _map_gain(cols["empirical"], rmap, wmap, light)
                     > _map_gain(out["empirical"], rmap, wmap, light)):
            out.update(cols, shares={})
        return out
    out["significant"] = True
    if block_sigma < SIGNIFICANT_SIGMA:
        # no mean pattern at the block scale, but a pattern finer than a block (a pick-up or fringes of a few
        # pixels' period) averages out in the blocks and raises the pixel chi2 as extra scatter would: when
        # one spatial frequency stands out of the periodogram and the pattern it carries takes a good share
        # (GEOMETRY_SHARE) of the excess pixel chi2, the residual is that periodic pattern, not added noise
        zhp = zp - block_smooth(res, zp, b, keep=True)
        period, contrast, _ = _peak(zhp, _cut_row_factor(wmap, row_var))
        if contrast >= periodic_bar(zhp.shape):
            desc = _periodic_only(res, period, contrast, zhp, wmap)
            pmap = _periodic_map(rmap, wmap, light, desc["kind"], row_var)
            if _map_gain(pmap, rmap, wmap, light) >= GEOMETRY_SHARE * max(noise_excess, 0.0):
                out["significance_sigma"] = round(max(out["significance_sigma"], _peak_sigma(contrast, zhp)), 2)
                out.update(desc)
                out["empirical"] = pmap
                return out
    if block_sigma < SIGNIFICANT_SIGMA:  # extra scatter, no mean pattern: where is it?
        z2 = np.where(wmap > 0, rmap * rmap * wmap, np.nan)
        vb = np.nanmean(z2[: (shape[0] // b) * b, : (shape[1] // b) * b].reshape(ny, b, nx, b), axis=(1, 3))
        okv = np.isfinite(vb)
        tv = _legendre_basis(ny, nx, 1)[:, okv]
        # a plane of the blocks' mean z^2, weighted by their errors (the mean of n values of chi2 with 1 dof has
        # variance 2 / n, times its level squared): a gradient of the noise when the plane is significant and
        # its change across the frame is a good part of the extra variance itself
        npb = np.maximum(_blocks((wmap > 0).astype(np.float64), b), 1.0)[okv]
        level = float(np.nanmean(vb))
        _, dgrad, fitv = _wls(vb[okv], npb / (2 * level * level), tv)
        varies = -dgrad > 25 and float(np.ptp(fitv)) > 0.5 * max(level - 1.0, 1e-9)
        geom = ["noise", "gradient"] if varies else ["noise"]
        extra = max(median_square_variance(r) - float(np.median(1 / w)), 0.0)
        if varies:  # where the noise is largest (the plane's highest block), not the frame's median
            extra = max(extra, (float(np.max(fitv)) - 1.0) * float(np.median(1 / w)))
        lsub, zsub = light.ravel()[idx][:200000], (r * r * w)[:200000]
        kind = "multiplicative" if np.ptp(lsub) > 0 and np.ptp(zsub) > 0 \
            and np.corrcoef(lsub, zsub)[0, 1] > 0.3 else "additive"
        out.update(kind=kind, geometry=geom, scale_px=float(min(shape)), amplitude=round(math.sqrt(extra) * gain, 4),
                   unit="e- rms", explanation=_words(kind, geom, f"extra pixel-to-pixel noise of "
                                                     f"{math.sqrt(extra) * gain:.3g} e- rms"
                                                     + (" where it is largest, varying across the frame"
                                                        if "gradient" in geom else "")))
        if kind == "additive":
            # the empirical map: the extra variance [ADU^2] of each block (its mean z^2 beyond 1, times its
            # pixels' model variance), smoothed over a block, or the frame's own where it does not vary
            vmod = np.where(wmap > 0, 1.0 / np.where(wmap > 0, wmap, 1.0), np.nan)
            vm = np.nanmean(vmod[: ny * b, : nx * b].reshape(ny, b, nx, b), axis=(1, 3))
            ex = np.where(okv, (vb - 1.0) * vm, 0.0) if varies else np.where(okv, extra, 0.0)
            wts = okv.astype(float)
            sm = gaussian_filter(ex * wts, 1.0, mode="nearest") / np.maximum(gaussian_filter(wts, 1.0, mode="nearest"),
                                                                           1e-9)
            out["empirical"] = {"kind": "noise", "map": np.maximum(_upsample(sm, b, shape), 0.0)}
        return out

    # --- kind: additive A(x, y), multiplicative M(x, y) L, or both (block level) --------------------------------
    basis = _legendre_basis(ny, nx, SMOOTH_ORDER)[:, ok]
    lmean = float(np.sum(lb[ok] * wb) / np.sum(wb)) if np.any(lb[ok]) else 0.0
    has_light = lmean > 0
    _, d_add, _ = _wls(y, wb, basis)
    kind_certain = True
    if has_light:
        lrel = lb[ok] / lmean
        mtemps = np.vstack([lrel[None, :], basis * lrel])
        _, d_mul, _ = _wls(y, wb, mtemps)
        _, d_both, _ = _wls(y, wb, np.vstack([basis, mtemps]))
        light_contrast = float(np.sqrt(np.sum(wb * (lrel - 1) ** 2) / np.sum(wb)))
        if light_contrast < 0.05:  # uniform light: A and M L cannot be told apart at large scales
            kind_certain = False
            kind = _kind_from_sources(res, idx, r, w)
            if kind is None and res.light_source == "flat":
                # a flat screen's frame: its light (tens of ke-) dominates the signal, and a structure in it is
                # far more often the light's transmission (dust, fringes, vignetting) than added light; a prior
                # only, the block says the data cannot tell them apart (kind_certain false)
                kind = "multiplicative"
            if kind is None:
                # by BIC: the multiplicative basis has one template more (the light itself)
                kind = "additive" if d_add <= d_mul + math.log(max(nb, 2)) else "multiplicative"
            else:
                kind_certain = True
        else:
            k_terms = basis.shape[0]
            ln = math.log(max(nb, 2))
            bic = {"additive": d_add + k_terms * ln, "multiplicative": d_mul + (k_terms + 1) * ln,
                   "mixed": d_both + (2 * k_terms + 1) * ln}
            kind = min(bic, key=bic.get)
            if kind == "mixed" and min(bic["additive"], bic["multiplicative"]) - bic["mixed"] < STRONG_EVIDENCE:
                kind = "additive" if bic["additive"] <= bic["multiplicative"] else "multiplicative"
    else:
        kind = "additive"
    # redistributed: the excess sits on the sources and their fluxes add up
    src = _source_share(res, idx, r, w)
    if src is not None and src["share"] > 0.6:
        if src["flux_kept"]:
            kind = "redistributed"
        elif kind not in ("multiplicative",):
            kind = "additive"
    # --- geometry on the block map (the kind's own normalisation) -----------------------------------------------
    if kind == "multiplicative" and has_light:
        yg, wg = y / np.maximum(lb[ok], 1e-9), wb * np.maximum(lb[ok], 1e-9) ** 2
    else:
        yg, wg = y, wb
    total = float(np.sum(wg * (yg - np.sum(wg * yg) / np.sum(wg)) ** 2))
    shares = {}
    _, d_grad, fit_grad = _wls(yg, wg, basis)
    _, d_plane, _ = _wls(yg, wg, _legendre_basis(ny, nx, 1)[:, ok])
    d_rad, fit_rad, centre = _radial(yg, wg, yy[ok], xx[ok], ny, nx)
    shares["gradient"] = -d_grad / max(total, 1e-300)
    shares["radial"] = -d_rad / max(total, 1e-300)
    # lines beyond the smooth field (pixel level: one row or column is one line)
    lines, line_profiles = {}, {}
    for name, axis in (("rows", 1), ("columns", 0)):
        cnt = (wmap > 0).sum(axis=axis)
        okl = cnt > 2
        if okl.sum() < 8:
            continue
        lm = (rmap * wmap).sum(axis=axis)[okl] / np.maximum(wmap.sum(axis=axis)[okl], 1e-300)
        lw = 1.0 / (1.0 / wmap.sum(axis=axis)[okl] + (row_var if axis == 1 else row_var / max(shape[0], 1)))
        x = np.linspace(-1, 1, lm.size)
        _, _, lfit = _wls(lm, lw, np.polynomial.legendre.legvander(x, 4)[:, 1:].T)
        rest = lm - lfit - np.sum(lw * (lm - lfit)) / np.sum(lw)
        lines[name] = float(np.sum(lw * rest * rest) - okl.sum())
        line_profiles[name] = (lm, lw, okl)
    pixel_total = max(pix_chi2 - idx.size, 1e-300)
    for name, ex in lines.items():
        shares[name] = max(ex, 0.0) / pixel_total
    # periodic: the strongest frequency of the pixel z-map once its smooth part (a block-scale Gaussian) and,
    # where they dominate, the line patterns are taken out
    if max(shares.get("rows", 0.0), shares.get("columns", 0.0)) < GEOMETRY_SHARE:
        zmap = np.where(wmap > 0, rmap * np.sqrt(wmap), 0.0)
        zmap = zmap - block_smooth(res, zmap, b)
        period, contrast, peak_share = _peak(zmap, _cut_row_factor(wmap, row_var))
    else:
        period, contrast, peak_share = 0.0, 0.0, 0.0
    # a periodic pattern puts a large share of the (high-passed) power into one frequency, far above the rest
    shares["periodic"] = min(1.0, 2 * peak_share) if contrast > 50 else 0.0
    if src is not None:
        shares["sources"] = src["share"]
    # local: what the smooth field leaves in a few blocks
    resid = (yg - (fit_grad if d_grad <= d_rad else fit_rad)) * np.sqrt(wg)
    resid -= np.mean(resid)
    strong = np.abs(resid) > DETECTION_SIGMA
    shares["local"] = float(np.sum(resid[strong] ** 2) / max(total, 1e-300)) if strong.sum() <= 0.1 * nb else 0.0
    # rings and blobs: the share of the band-passed structure in their footprints (compact_features)
    if feats["n_rings"]:
        shares["rings"] = feats["rings"]
    if feats["n_blobs"]:
        shares["blobs"] = feats["blobs"]
    line = straight_line(rmap, wmap)
    if is_streak(line):
        shares["streak"] = line["chi2"] / pixel_total
    if rings_on_src and kind != "redistributed":
        # rings centred on the sources are a property of the sources' light (a diffraction or ghost ring: the
        # point-spread function), light moved around them whatever the fitted fluxes absorbed
        kind, kind_certain = "redistributed", True
    wide_map = None
    if max(shares.values()) < GEOMETRY_SHARE:
        # the search above takes the block-scale smooth part out first, and with it every period longer than a
        # few blocks (tree rings, fringes tens of pixels apart), and its share is of the whole power, noise
        # included, where the other families' are of the excess chi2. When no family takes GEOMETRY_SHARE of the
        # structure (the description would be a family that holds less), the periodogram of the unsmoothed map
        # (the smooth fields' few cycles left out, :func:`_spectrum`) is asked: a peak significant on its own
        # (:func:`periodic_bar`), with the share of the excess chi2 its band-passed map takes (:func:`_periodic_map`)
        spec = _spectrum(zp, _cut_row_factor(wmap, row_var), WIDE_SMOOTH_CYCLES) if _cut(zp) is not None else None
        wide_period, wide_contrast, _ = _peak_of(spec)
        bar = periodic_bar(shape)
        if wide_contrast >= bar and ring_contrast(spec) >= bar:
            # (_relative: other kinds map as additive)
            wide_map = _periodic_map(rmap, wmap, light, kind, row_var, WIDE_SMOOTH_CYCLES)
            wide_share = _map_gain(wide_map, rmap, wmap, light) / pixel_total
            if wide_share >= GEOMETRY_SHARE:
                shares["periodic"], period = wide_share, wide_period
            else:
                wide_map = None
    shares = {k: round(float(min(max(v, 0.0), 1.0)), 3) for k, v in shares.items()}
    geometry = [k for k, v in sorted(shares.items(), key=lambda kv: -kv[1]) if v >= GEOMETRY_SHARE]
    if "radial" in geometry or "gradient" in geometry:
        # a plane (and a radial field about a far centre, which is nearly one) is a gradient; a field is radial
        # when a function of the distance to a centre near the frame takes nearly as much as the whole smooth
        # basis and clearly more than a plane
        near = -0.5 * ny <= centre[0] <= 1.5 * ny and -0.5 * nx <= centre[1] <= 1.5 * nx
        radial = d_rad <= 0.85 * d_grad and d_plane > 0.9 * d_grad and near
        geometry = [g for g in geometry if g not in ("radial", "gradient")]
        geometry.insert(0, "radial" if radial else "gradient")
    if not geometry:
        geometry = [max(shares, key=shares.get)] if shares else ["local"]
    if wide_map is not None and geometry[0] == "periodic":
        geometry[1:1] = [g for g in _periodic_axes(wide_map["map"], wmap) if g not in geometry]
    if rings_on_src and kind == "redistributed":
        # the same ring repeated about the sources is the pattern, whatever share of the frame's structure it
        # takes; the compact block excess ("local") is those rings seen at block scale
        geometry = [g for g in geometry if g not in ("local", "rings", "sources")]
        geometry[:0] = ["sources", "rings"]
    if kind == "redistributed" and "sources" not in geometry:
        geometry.insert(0, "sources")
    if "streak" in geometry and geometry[0] in ("local", "blobs") and kind == "additive":
        # a trail is a few blocks of the block map and a string of blobs too: the straight line is the description
        # when its map (a profile across it and an extent: a few numbers) takes most (EXPLAINS_MOST) of the chi2
        # their map takes from the fitted pixels (the residual itself, smoothed: it follows the noise there too)
        other = _block_map(mean, lb, ok, b, shape, False) if geometry[0] == "local" else \
            _feature_map(feats, rmap, wmap, light, kind, res)
        if other is None or _map_gain(_streak_map(line, shape), rmap, wmap, light) >= \
                EXPLAINS_MOST * _map_gain(other, rmap, wmap, light):
            geometry = ["streak"] + [g for g in geometry if g != "streak"]
    # scale and amplitude
    main = geometry[0]
    smooth_fit = fit_grad if d_grad <= d_rad else fit_rad
    line_period, through = 0.0, None
    if main in ("rows", "columns") and main in line_profiles:
        line_period = _line_period(*line_profiles[main][:2])
        if line_period and "periodic" not in geometry:
            geometry.insert(1, "periodic")
        through = _lines_through_sources(res, *line_profiles[main], axis=1 if main == "rows" else 0,
                                         excess=lines.get(main, 0.0))
        if through is not None and "sources" not in geometry:
            geometry.insert(1, "sources")
    if main == "periodic":
        scale = period
    elif main in ("rows", "columns"):
        scale = line_period or 1.0
    elif main == "radial":  # the rms radius of the pattern about its centre (its departure from its edge value)
        rr2 = (yy[ok] - centre[0]) ** 2 + (xx[ok] - centre[1]) ** 2
        amp_r = np.abs(fit_rad - fit_rad[np.argmax(rr2)])
        scale = float(b * np.sqrt(np.sum(amp_r * rr2) / max(np.sum(amp_r), 1e-300)))
    elif main == "rings":
        scale = feats["ring_radius_px"]
    elif main == "sources" and rings_on_src:
        scale = feats["sring_radius_px"]
    elif main == "blobs":
        scale = feats["blob_radius_px"]
    elif main == "local":
        scale = float(b * math.sqrt(max(strong.sum(), 1)))
    elif main == "streak":
        scale = line["fwhm_px"]
    else:
        scale = float(b * max(ny, nx))
    periodic_map = None
    if (main == "periodic" or line_period) and kind in ("additive", "multiplicative", "mixed"):
        # a pattern of lines with a period is mapped by its frequencies, as any periodic pattern: the map then
        # holds its form between the lines it was made from (a fold's rows predict the other fold's)
        periodic_map = wide_map if wide_map is not None else _periodic_map(rmap, wmap, light, kind, row_var)
    if main in ("rings", "blobs") or (main == "sources" and rings_on_src):
        fam = "srings" if main == "sources" else main
        amp, unit, desc = _feature_amplitude(res, feats, fam, rmap, light, kind == "multiplicative" and has_light)
    elif main == "streak":
        amp, unit, desc = _streak_words(line, gain)
    elif periodic_map is not None and main == "periodic":
        # the band-passed pattern itself: a sinusoid of amplitude sqrt(2) x its rms
        pm = periodic_map["map"][wmap > 0] if np.any(wmap > 0) else periodic_map["map"]
        a = math.sqrt(2.0) * float(np.sqrt(np.mean(np.square(pm, dtype=np.float64))))
        if periodic_map["kind"] == "multiplicative":
            amp, unit = a * 100, "%"
            desc = f"a wave of {amp:.3g} % of the light in amplitude"
        else:
            amp, unit = a * gain, "e-"
            desc = f"a wave of {amp:.3g} e- ({a:.3g} ADU) in amplitude"
    elif main in ("rows", "columns") and main in line_profiles:
        # the lines' own scatter beyond their noise (what a smooth fit of the blocks does not see) [ADU rms]
        lm, lw, okl = line_profiles[main]
        mu = float(np.sum(lw * lm) / np.sum(lw))
        rms = math.sqrt(max(float(np.sum(lw * (lm - mu) ** 2) / np.sum(lw)) - okl.sum() / float(np.sum(lw)), 0.0))
        if kind == "multiplicative" and has_light:
            amp, unit = rms / max(lmean, 1e-300) * 100, "%"
            desc = f"{amp:.3g} % rms of the light from one {main[:-1]} to the next"
        else:
            amp, unit = rms * gain, "e-"
            desc = f"{amp:.4g} e- ({rms:.4g} ADU) rms from one {main[:-1]} to the next"
        if line_period:
            desc += f", period {line_period:.3g} {main}"
        if through is not None:
            desc += (f", following the sources: each pixel holds {through:.3g} of its {main[:-1]}'s source light "
                     f"(light smeared along the {main} through the sources: a read-out smear, row-shift time over "
                     "exposure, or a bleed)")
    elif kind == "multiplicative" and has_light:
        amp, unit = float(np.ptp(smooth_fit)) * 100, "%"
        desc = f"{amp:.3g} % peak-to-peak of the light"
    else:
        amp, unit = float(np.ptp(smooth_fit)) * gain, "e-"
        desc = f"{amp:.4g} e- ({amp / gain:.4g} ADU) peak-to-peak"
    if main == "radial":
        desc += f" about (x, y) = ({(centre[1] + 0.5) * b:.0f}, {(centre[0] + 0.5) * b:.0f}) output px"
    if main == "periodic":
        desc += f", period {period:.3g} px"
    desc += _feature_words(feats, geometry, rings_on_src)
    certain = "" if kind_certain else " (additive and multiplicative cannot be told apart on this uniform light)"
    out.update(kind=kind, kind_certain=kind_certain, geometry=geometry, scale_px=round(scale, 2),
               amplitude=round(amp, 4), unit=unit, shares=shares,
               explanation=_words(kind, geometry, desc) + certain)
    if main in ("gradient", "radial", "local", "rings", "blobs") and kind in ("additive", "multiplicative", "mixed"):
        # the empirical map: the block means themselves, smoothed over a block (normalised convolution
        # over the blocks with data), not a parametric form: it follows whatever shape the pattern has
        # at scales of a block and more. Relative to the light for a multiplicative pattern [1], else [ADU]
        out["empirical"] = _block_map(mean, lb, ok, b, shape, kind == "multiplicative" and has_light)
        if main == "local" and zp.size <= FEATURE_MAX_PIXELS:
            # a local pattern thinner than a block (a trail, glints): the features' own map when it explains more
            fmap = _feature_map(feats, rmap, wmap, light, "additive" if kind == "redistributed" else kind, res)
            if fmap is not None and _map_gain(fmap, rmap, wmap, light) > _map_gain(out["empirical"], rmap, wmap,
                                                                                      light):
                out["empirical"] = fmap
    elif main == "streak":
        smap = _streak_map(line, shape)
        out["empirical"] = _relative(kind, smap["map"].astype(np.float64), light) if kind == "multiplicative" \
            and has_light else smap
    elif main in ("rows", "columns") and through is not None and not line_period:
        # light smeared along the lines through the sources: the smear itself (one fraction of each line's
        # source light), which predicts the lines' other pixels, when it takes more than the lines' own means
        # leave to chance (a line map follows each line's noise too)
        axis = 1 if main == "rows" else 0
        out["empirical"] = _smear_map(res, through, axis)
        lmap = _line_map(rmap, wmap, light, "additive", axis=axis)
        n_lines = float(np.sum(wmap.sum(axis=axis) > 0))  # the chi2 a line map takes from noise alone
        if _map_gain(lmap, rmap, wmap, light) - _map_gain(out["empirical"], rmap, wmap, light) > n_lines:
            out["empirical"] = lmap
    elif main in ("rows", "columns") and kind in ("additive", "multiplicative", "mixed") and not line_period:
        out["empirical"] = _line_map(rmap, wmap, light, kind, axis=1 if main == "rows" else 0)
    elif periodic_map is not None:
        out["empirical"] = periodic_map
    if out["empirical"] is None and n_feat:
        # light moved around the sources (rings on them) is mapped as what it adds and takes where it is
        out["empirical"] = _feature_map(feats, rmap, wmap, light, "additive" if kind == "redistributed" else kind,
                                        res)
    return out


#: a line pattern follows the sources when their light per line explains this share of the lines' excess
LINE_SOURCE_SHARE = EXPLAINS_MOST


def _lines_through_sources(res: Residuals, lm, lw, okl, axis: int, excess: float) -> float | None:
    """The fraction [1 per pixel] of each line's source light that the line's mean residual holds, when the
    sources' light per line (``axis`` 1: rows, 0: columns) explains LINE_SOURCE_SHARE of the lines' excess
    chi2 and the slope is significant (delta chi2 > 25): a streak through each source along its line (a
    read-out smear, Janesick 2001 sect. 5.4; a bleed). None otherwise."""
    if res.background_adu is None or excess <= 0:
        return None
    # the sources' light before the full-well clip (a saturated star smears all of its light), on every pixel
    s_line = res.source_light().sum(axis=axis)[okl]
    s_line = s_line - float(np.sum(lw * s_line) / np.sum(lw))  # a straight line with its intercept
    den = float(np.sum(lw * s_line * s_line))
    if den <= 0:
        return None
    mu = float(np.sum(lw * lm) / np.sum(lw))
    slope = float(np.sum(lw * (lm - mu) * s_line) / den)
    gain = slope * slope * den
    if gain < 25 or gain < LINE_SOURCE_SHARE * excess or slope <= 0:
        return None
    return slope


def _columns_through_sources(res: Residuals) -> dict:
    """The description of outlier columns that follow the sources' light (:func:`columns_follow_sources`): the
    fitted pixels leave those columns out (they are compared statistically), so the block maps do not see
    them. ``{}`` when there are none."""
    from scipy.stats import norm

    from .signatures import columns_follow_sources

    got = columns_follow_sources(res)
    if got is None or got["slope"] <= 0:
        return {}
    slope = _column_smear_slope(res)
    if slope <= 0:
        return {}
    rows = res.data_adu.shape[0]
    sigma = max(got["follow"], float(norm.isf(max(got["chance"], 1e-300))))
    geom = ["columns", "sources"]
    return {"significant": True, "significance_sigma": round(sigma, 2), "kind": "additive", "kind_certain": True,
            "geometry": geom, "scale_px": float(rows), "amplitude": round(100 * slope * rows, 4), "unit": "%",
            "explanation": _words("additive", geom, f"{got['cols'].size} columns above their neighbours where the "
                                  f"sources are, each column lifted by {100 * slope * rows:.2g} % of its "
                                  "sources' light spread along it (a streak through each source along the read-out)"),
            "empirical": _smear_map(res, slope, 0)}


#: pixels a column's median residual is taken from at most (every k-th row beyond that) [pixels]
SMEAR_MEDIAN_PIXELS = 4_000_000


def _column_smear_slope(res: Residuals) -> float:
    """The share of its column's source light (:meth:`Residuals.source_light`, before the full-well clip) that each
    pixel holds [1 per pixel]: the columns' median residuals over the pixels the outlier statistics see (robust to
    the spikes and to a source's own misfit pixels, a few of a column's) fitted by a straight line of the columns'
    source light (the intercept is the levels'). Not from the outlier statistic ``col_z``, which is clipped and
    taken against the running median of the neighbouring columns, which a source's smear lifts too."""
    use = res.outlier_usable
    step = max(1, math.ceil(use.size / SMEAR_MEDIAN_PIXELS))
    r = np.where(use[::step], res.data_adu[::step].astype(np.float64) - res.model_adu[::step], np.nan)
    with np.errstate(all="ignore"):
        med = np.nanmedian(r, axis=0) if np.isfinite(r).any() else np.full(r.shape[1], np.nan)
    f = res.source_light().sum(axis=0)
    ok = np.isfinite(med)
    if ok.sum() < 3:
        return 0.0
    fc = f[ok] - f[ok].mean()
    den = float(np.dot(fc, fc))
    return float(np.dot(fc, med[ok] - med[ok].mean()) / den) if den > 0 else 0.0


#: a line profile is periodic when one frequency holds this share of its power beyond the noise: most of it,
#: EXPLAINS_MOST (the bar of :data:`detector.effects.readout.KTC_PERIODIC_SHARE` for a claimed excess variance
#: that one frequency holds) ...
LINE_PERIOD_SHARE = EXPLAINS_MOST
#: ... and stands above the noise's mean power by the bar of a spectral line significant on its own among the
#: profile's frequencies searched (:func:`periodic_contrast`, over the median power: ln 2 times it over the
#: mean), and above the median power of its neighbouring frequencies on either side by the same bar (a line,
#: not a red continuum) ...
#: ... with at least this many cycles across the frame (fewer: a smooth curve, as the periodic maps take it)
LINE_PERIOD_MIN_CYCLES = 6


def _line_period(lm: np.ndarray, lw: np.ndarray) -> float:
    """The period [lines] of a row or column profile ``lm`` (weights ``lw`` [1/ADU^2]) when one frequency of at
    least LINE_PERIOD_MIN_CYCLES cycles holds LINE_PERIOD_SHARE of its power beyond the noise, stands
    :func:`periodic_contrast` (of the frequencies searched) above the noise's own median power and as many
    times above its neighbours' on both sides (a pick-up, a flicker through a rolling shutter, a periodic banding); 0 otherwise."""
    n = lm.size
    if n < 16:
        return 0.0
    z = (lm - np.sum(lw * lm) / np.sum(lw)) * np.sqrt(lw)  # whitened: white noise has power 1 per bin
    p = np.abs(np.fft.rfft(z)) ** 2 / n * 2
    p[:LINE_PERIOD_MIN_CYCLES] = 0.0
    k = int(np.argmax(p))
    excess = float(np.sum(np.maximum(p - 1.0, 0.0)))
    bar = periodic_contrast(p.size - LINE_PERIOD_MIN_CYCLES)  # over the median power
    over_mean = bar * math.log(2.0)  # the same bar over the mean (a unit exponential's median is ln 2)
    if p[k] < over_mean or excess <= 0 or (p[k] - 1.0) < LINE_PERIOD_SHARE * excess:
        return 0.0
    # a line, not a red continuum (a drift, a random walk: their power falls smoothly with frequency)
    sides = [p[max(LINE_PERIOD_MIN_CYCLES, k - 10): k - 1], p[k + 2: k + 11]]
    if any(sd.size and p[k] < bar * float(np.median(sd)) for sd in sides):
        return 0.0
    if 0 < k < p.size - 1 and min(p[k - 1], p[k + 1]) > 0:  # the peak between bins (a parabola in log power)
        a, b, c = np.log(p[k - 1]), np.log(p[k]), np.log(p[k + 1])
        k = k + 0.5 * (a - c) / (a - 2 * b + c) if (a - 2 * b + c) < 0 else k
    return round(n / k, 2)


#: longest side [px] of the map the straight-line search projects (block sums of the whitened pixel map): between
#: two angles STREAK_STEP_DEG apart a line moves by at most 1.1 bins at the map's edge
STREAK_MAP_PX = 256
#: angles [deg] of the coarse projection (refined ten times finer about the best)
STREAK_STEP_DEG = 0.5
#: band [map px] whose sum is the line's, and the flanks on either side (the same width again, two bins off) whose
#: mean is taken out: a smooth field and a ramp across the line cancel, a line a few pixels wide stands out
STREAK_BANDS = (1, 3)
#: half-width [output px] of the profile across the line measured at full resolution (at least this, or two
#: blocks of the search map)
STREAK_PROFILE_PX = 8


def straight_line(rmap: np.ndarray, wmap: np.ndarray) -> dict | None:
    """The strongest straight line of the whitened residual ``rmap sqrt(wmap)``: a trail (a satellite, debris, a
    meteor), a scratch's shadow, one bright row or column. The sums along every line of a block map (the Radon
    transform, by bincount of each pixel's offset ``x cos(t) + y sin(t)`` at every angle ``t``) over a band of 1
    or 3 bins, less the same number of pixels' share of its flanks (a smooth field cancels), over their noise:
    a unit normal deviate per line under white noise. The best line's angle is refined, then its profile across
    the line is measured on the output pixels (1 px bins out to STREAK_PROFILE_PX) and its extent along it.

    Returns None on a map without lines, else ``sigma`` (the best line's deviate, refined), ``sigma_searched``
    (its deviate on the coarse grid of angles, which :func:`streak_bar` is the bar of), ``next_sigma`` (the
    strongest parallel line beyond the profile's reach), ``n_tests`` (lines x bands searched: the look-elsewhere
    factor), ``chi2`` (what the profile across the line takes from the pixels beyond a constant and its noise),
    ``angle_deg`` (of the line, x towards y), ``through`` (x, y) [output px], ``theta`` [rad], ``rho_px`` and
    ``centre`` (the line's normal form about the frame's centre (y, x)), ``span`` and ``length_px`` (its extent
    along the line), ``fwhm_px``, ``peak_adu`` and ``profile`` (offsets [px] and mean residual [ADU] beyond the
    flanks' level)."""
    okp = wmap > 0
    if okp.sum() < 64:
        return None
    zp = np.where(okp, rmap * np.sqrt(np.where(okp, wmap, 0.0)), 0.0)
    s = max(1, math.ceil(max(zp.shape) / STREAK_MAP_PX))
    zs, ns = _blocks(zp, s), _blocks(okp.astype(np.float64), s)
    on = ns > 0
    ny, nx = zs.shape
    yy, xx = np.mgrid[0:ny, 0:nx].astype(np.float64)
    cy, cx = (ny - 1) / 2.0, (nx - 1) / 2.0
    x, y, zv, nv = xx[on] - cx, yy[on] - cy, zs[on], ns[on]
    rmax = int(math.ceil(math.hypot(ny, nx) / 2.0)) + 2 * max(STREAK_BANDS) + 2
    kernels = []
    for band in STREAK_BANDS:
        k_in = np.zeros(5 * band)
        k_in[2 * band:3 * band] = 1.0
        k_fl = np.zeros(5 * band)
        k_fl[:band], k_fl[4 * band:] = 1.0, 1.0
        kernels.append((k_in, k_fl))

    def deviates(theta, band):
        rho = np.rint(x * math.cos(theta) + y * math.sin(theta)).astype(np.int64) + rmax
        sz = np.bincount(rho, zv, 2 * rmax + 1)
        cnt = np.bincount(rho, nv, 2 * rmax + 1)
        k_in, k_fl = kernels[band]
        s_in, n_in = np.convolve(sz, k_in, "same"), np.convolve(cnt, k_in, "same")
        s_fl, n_fl = np.convolve(sz, k_fl, "same"), np.convolve(cnt, k_fl, "same")
        good = (n_in > 0) & (n_fl > 0)
        ratio = np.where(good, n_in / np.where(good, n_fl, 1.0), 0.0)
        return np.where(good, (s_in - ratio * s_fl) / np.sqrt(np.where(good, n_in + ratio * n_in, 1.0)), 0.0)

    def best_at(theta):
        top = (0.0, 0, 0)
        for bi in range(len(kernels)):
            t = deviates(theta, bi)
            i = int(np.argmax(np.abs(t)))
            if abs(t[i]) > abs(top[0]):
                top = (float(t[i]), i - rmax, bi)
        return top

    coarse = np.radians(np.arange(0.0, 180.0, STREAK_STEP_DEG))
    found = [(best_at(t), t) for t in coarse]
    (sig, _, _), theta = max(found, key=lambda f: abs(f[0][0]))
    sig_searched = abs(sig)  # the deviate the look-elsewhere bar is for (the refinement maximises it further)
    fine = theta + np.radians(np.arange(-1.0, 1.0001, 0.1) * STREAK_STEP_DEG)
    (sig, rho, band), theta = max(((best_at(t), t) for t in fine), key=lambda f: abs(f[0][0]))
    n_tests = coarse.size * (2 * rmax + 1) * len(STREAK_BANDS)
    # the strongest parallel line beyond the profile's reach: a trail is one line, a pattern of lines (banding,
    # pick-up, fringes) has neighbours as strong
    t_all = deviates(theta, band)
    far = np.abs(np.arange(t_all.size) - rmax - rho) > max(2 * STREAK_BANDS[band], math.ceil(STREAK_PROFILE_PX / s))
    next_sigma = float(np.max(np.abs(t_all[far]))) if far.any() else 0.0
    # the profile across the line on the output pixels (offsets d from it, positions t along it)
    ct, st = math.cos(theta), math.sin(theta)
    ocy, ocx = (cy + 0.5) * s - 0.5, (cx + 0.5) * s - 0.5
    half = max(STREAK_PROFILE_PX, 2 * s)
    iy, ix = np.nonzero(okp)
    d = (ix - ocx) * ct + (iy - ocy) * st - rho * s
    near = np.abs(d) <= half + 0.5
    iy, ix, d = iy[near], ix[near], d[near]
    if d.size < 16:
        return None
    rr, ww = rmap[iy, ix], wmap[iy, ix]
    sgn = 1.0 if sig >= 0 else -1.0
    # extent along the line: the run of positions whose summed signal in the line's core stands out most (the
    # largest S / sqrt(N) over every span of bins of the profile's width: the segment a trail draws)
    along = (ix - ocx) * (-st) + (iy - ocy) * ct
    core = np.abs(d) <= 1.5 * s
    span = (-np.inf, np.inf)
    if core.sum() >= 16:
        lo_t = float(along[core].min())
        tb = np.floor((along[core] - lo_t) / half).astype(np.int64)
        cs = np.concatenate([[0.0], np.cumsum(np.bincount(tb, sgn * rr[core] * ww[core]))])
        cn = np.concatenate([[0.0], np.cumsum(np.bincount(tb, ww[core]))])
        ds, dn = cs[None, :] - cs[:, None], cn[None, :] - cn[:, None]
        score = np.where(dn > 0, ds / np.sqrt(np.where(dn > 0, dn, 1.0)), -np.inf)
        a, b2 = np.unravel_index(int(np.argmax(score)), score.shape)
        if b2 > a:
            span = (float(lo_t + a * half), float(lo_t + b2 * half))
    within = (along >= span[0]) & (along <= span[1])
    bins = np.rint(d[within]).astype(np.int64) + half
    nb = 2 * half + 1
    sw = np.bincount(bins, ww[within], nb)
    swr = np.bincount(bins, ww[within] * rr[within], nb)
    okb = sw > 0
    prof = np.where(okb, swr / np.where(okb, sw, 1.0), 0.0)  # mean residual [ADU] at each offset
    offs = np.arange(nb) - half
    flank = okb & (np.abs(offs) >= half / 2.0)
    const = float(swr[flank].sum() / max(sw[flank].sum(), 1e-300)) if flank.any() else 0.0
    # what the profile across the line takes beyond a constant (its degrees of freedom taken out)
    chi2 = float(np.sum(np.where(okb, swr * swr / np.where(okb, sw, 1.0), 0.0)) - swr.sum() ** 2 / max(sw.sum(), 1e-300)
                 - (okb.sum() - 1))
    excess = (prof - const) * sgn
    peak = float(np.max(excess[okb])) if okb.any() else 0.0
    above = okb & (excess > 0.5 * peak) if peak > 0 else np.zeros(nb, bool)
    fwhm = float(offs[above].max() - offs[above].min() + 1) if above.any() else 0.0
    return {"sigma": float(abs(sig)), "sigma_searched": float(sig_searched), "next_sigma": next_sigma,
            "n_tests": int(n_tests), "chi2": max(chi2, 0.0),
            "angle_deg": float((math.degrees(theta) + 90.0) % 180.0),
            "through": (float(ocx + rho * s * ct), float(ocy + rho * s * st)), "theta": float(theta),
            "rho_px": float(rho * s), "centre": (float(ocy), float(ocx)), "span": span,
            "length_px": float(span[1] - span[0]) if np.isfinite(span[0]) else 0.0, "fwhm_px": fwhm,
            "peak_adu": peak * sgn, "profile": (offs, np.where(okb, prof - const, 0.0))}


def _streak_words(line: dict, gain: float) -> tuple[float, str, str]:
    """(amplitude [e-], unit, words) of a straight streak (:func:`straight_line`)."""
    amp = line["peak_adu"] * gain
    x, y = line["through"]
    return amp, "e-", (f"a straight streak of {amp:.3g} e- per pixel at its centre, {line['fwhm_px']:.2g} px wide "
                       f"(FWHM), {line['length_px']:.0f} px long at {line['angle_deg']:.0f} deg (from x towards y) "
                       f"through (x, y) = ({x:.0f}, {y:.0f}) output px, {line['sigma']:.1f} sigma along the line")


def streak_bar(n_tests: int, frames: int = 1) -> float:
    """The deviate the best of ``n_tests`` lines passes at most once in 1 / FRAME_FALSE_ALARM frames of white noise
    (two sided: a bright trail or a dark one; a Bonferroni bound), or the best of ``frames`` frames' lines once in
    1 / FRAME_FALSE_ALARM series."""
    from scipy.stats import norm

    return float(norm.isf(0.5 * FRAME_FALSE_ALARM / max(n_tests, 1) / max(int(frames), 1)))


def streak_sigma(line: dict) -> float:
    """The significance [Gaussian sigma, one-sided] of the best line's coarse-grid deviate among the ``n_tests``
    lines searched, two-sided (the look-elsewhere effect, as :func:`streak_bar`)."""
    from scipy.stats import norm

    log10_p = (math.log10(2.0 * max(int(line["n_tests"]), 1))
               + float(norm.logsf(line["sigma_searched"])) / math.log(10.0))
    return sigma_of_log10_p(min(log10_p, 0.0))


def _line_search_map(rmap: np.ndarray, wmap: np.ndarray, row_var: float) -> np.ndarray:
    """The residual [ADU] the faint-streak search projects: less its row means where the model has row noise
    (``row_var`` > 0: :func:`_without_row_means`), its whitened values clipped at DETECTION_SIGMA of their robust
    scale (:func:`detector.stats.median_square_variance`: a few outlying pixels, hot ones or a heavy-tailed
    pattern's, do not make a line; a faint trail is well inside it) and scaled to the clipped values' own
    variance where it exceeds the model's (a line must stand out of the scatter the frame has, an unmodelled DSNU's
    or PRNU's too, not only of the model's)."""
    r = _without_row_means(rmap, wmap) if row_var > 0 else rmap
    on = wmap > 0
    if not on.any():
        return r
    sw = np.sqrt(np.where(on, wmap, 0.0))
    z = r * sw
    z = np.clip(z / math.sqrt(max(median_square_variance(z[on]), 1e-30)), -DETECTION_SIGMA, DETECTION_SIGMA)
    # the line sums scatter as the clipped values do: their variance (a heavy-tailed law keeps more than a normal
    # one's inside the clip), not below the model's
    z = z / math.sqrt(max(float(np.mean(np.square(z[on]))), 1.0))
    return np.where(on, z / np.where(on, sw, 1.0), 0.0)


def _without_row_means(rmap: np.ndarray, wmap: np.ndarray) -> np.ndarray:
    """``rmap`` less each row's weighted mean on its fitted pixels (0 elsewhere): the row offsets out."""
    sw = wmap.sum(axis=1)
    mean = np.where(sw > 0, (rmap * wmap).sum(axis=1) / np.where(sw > 0, sw, 1.0), 0.0)
    return np.where(wmap > 0, rmap - mean[:, None], 0.0)


#: a line within this angle [deg] of a pixel axis is one row or column (the line families', whose statistics hold
#: the row noise): twice the coarse search's step, a line that crosses the frame's 256 map pixels within ~4 of one
STREAK_AXIS_DEG = 2 * STREAK_STEP_DEG


def along_pixel_axis(line: dict) -> bool:
    """The line runs along a row or a column (within STREAK_AXIS_DEG)."""
    a = float(line["angle_deg"]) % 90.0
    return min(a, 90.0 - a) < STREAK_AXIS_DEG


#: a streak stands alone: the strongest line parallel to it beyond its profile is not significant on its own
#: (streak_bar) or is below this fraction of its deviate; a pattern of lines (banding, pick-up, fringes) has
#: neighbours as strong as its best line, a trail has none
STREAK_ALONE = 0.5
#: a streak is elongated: its extent along the line at least a trail's length in its FWHM across it
#: (TRAIL_MIN_FWHM; a compact residual, a star's misfit, is a blob whatever line passes through it)
STREAK_ELONGATION = TRAIL_MIN_FWHM


def is_streak(line: dict | None, frames: int = 1) -> bool:
    """A straight line significant among every line searched (in each of ``frames`` frames: :func:`streak_bar`),
    alone (STREAK_ALONE) and elongated (STREAK_ELONGATION)."""
    if line is None:
        return False
    bar = streak_bar(line["n_tests"], frames)
    return (line["sigma_searched"] >= bar and line["next_sigma"] < max(bar, STREAK_ALONE * line["sigma"])
            and line["length_px"] >= STREAK_ELONGATION * max(line["fwhm_px"], 1.0))


def _streak_map(line: dict, shape: tuple[int, int]) -> dict:
    """The empirical map of a straight streak: the measured profile across the line [ADU] wherever the line's
    extent reaches (its span, plus a profile's half-width at either end), 0 elsewhere."""
    offs, prof = line["profile"]
    half = int(offs.max())
    ct, st = math.cos(line["theta"]), math.sin(line["theta"])
    ocy, ocx = line["centre"]
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
    d = (xx - ocx) * ct + (yy - ocy) * st - line["rho_px"]
    t = (xx - ocx) * (-st) + (yy - ocy) * ct
    amap = np.zeros(shape, np.float64)
    near = (np.abs(d) <= half + 0.5) & (t >= line["span"][0] - half) & (t <= line["span"][1] + half)
    amap[near] = prof[np.rint(d[near]).astype(np.int64) + half]
    return {"kind": "additive", "map": amap.astype(np.float32), "form": "streak"}


def _block_map(mean: np.ndarray, lb: np.ndarray, ok: np.ndarray, b: int, shape: tuple[int, int],
               relative: bool) -> dict:
    """The empirical map of a pattern at the block scale: the block means themselves, smoothed over a block
    (normalised convolution over the blocks with data), not a parametric form: it follows whatever shape the
    pattern has at scales of a block and more. Relative to the light (``relative``) [1], else [ADU]."""
    ek = "multiplicative" if relative else "additive"
    vals = np.where(ok, mean / np.maximum(lb, 1e-9) if relative else mean, 0.0)
    wts = ok.astype(float)
    sm = gaussian_filter(vals * wts, 1.0, mode="nearest") / np.maximum(gaussian_filter(wts, 1.0, mode="nearest"), 1e-9)
    return {"kind": ek, "map": _upsample(sm, b, shape)}


def _map_gain(emp: dict, rmap: np.ndarray, wmap: np.ndarray, light: np.ndarray) -> float:
    """The chi2 an empirical map (``{"kind", "map"}``) removes from the residual ``rmap`` (weights ``wmap``)."""
    m = np.asarray(emp["map"], np.float64)
    if emp.get("kind") == "multiplicative":
        m = m * light
    elif emp.get("kind") not in ("additive", None):
        return 0.0
    return float(np.sum(wmap * (rmap * rmap - (rmap - m) ** 2)))


def _relative(kind: str, amap: np.ndarray, light: np.ndarray) -> dict:
    """``{"kind", "map"}`` of an empirical map [ADU per output pixel]: relative to the light for a
    multiplicative pattern where there is light, else additive [ADU]."""
    if kind == "multiplicative" and np.any(light > 0):
        rel = amap / np.maximum(light, 1e-9 * max(float(np.max(light)), 1e-30))
        return {"kind": "multiplicative", "map": np.where(light > 0, rel, 0.0).astype(np.float32)}
    return {"kind": "additive", "map": amap.astype(np.float32)}


def _line_map(rmap: np.ndarray, wmap: np.ndarray, light: np.ndarray, kind: str, axis: int) -> dict:
    """The empirical map of a row (``axis`` 1) or column (``axis`` 0) pattern: each line's weighted mean
    residual [ADU], broadcast along it (relative to the line's mean light when multiplicative). Each mean
    ``m`` (variance ``1 / sum w``) is weighted by the Wiener factor ``max(0, 1 - var / m^2)``, as the periodic
    map's frequencies are (:func:`_periodic_map`): a line the pattern does not lift above its noise carries
    noise only, and a map of it would predict nothing on the line's other pixels."""
    sw = wmap.sum(axis=axis)
    means = np.where(sw > 0, (rmap * wmap).sum(axis=axis) / np.where(sw > 0, sw, 1.0), 0.0)
    var = 1.0 / np.where(sw > 0, sw, np.inf)
    means = means * np.clip(1.0 - var / np.maximum(means * means, 1e-300), 0.0, 1.0)
    amap = np.broadcast_to(means[:, None] if axis == 1 else means[None, :], rmap.shape)
    return {**_relative(kind, np.asarray(amap, np.float64), light), "form": "rows" if axis == 1 else "columns"}


def _smear_map(res: Residuals, slope: float, axis: int) -> dict:
    """The empirical map of light smeared along the lines through the sources (:func:`_lines_through_sources`):
    every pixel holds ``slope`` of its line's source light [ADU], less its mean over the frame (the levels take
    that). One number for the whole frame, so it holds between the lines it was measured on."""
    s_line = res.source_light().sum(axis=axis)
    amap = np.broadcast_to((s_line - s_line.mean())[:, None] if axis == 1 else (s_line - s_line.mean())[None, :],
                           res.data_adu.shape)
    return {"kind": "additive", "map": (slope * amap).astype(np.float32)}


#: the empirical map of a periodic pattern keeps the Fourier components within this radius [frequency bins] of
#: the strongest peaks (and their mirror images): the pattern and a slow change of its phase (a bow)
PERIODIC_KEEP_BINS = 3
#: ... of at most this many peaks (fringes or pick-up with harmonics)
PERIODIC_PEAKS = 3


def _periodic_axes(pmap: np.ndarray, wmap: np.ndarray) -> list[str]:
    """``["rows"]`` when a periodic map is constant along the rows (its wave vector along y: the row means hold
    most, EXPLAINS_MOST, of its variance on the fitted pixels), ``["columns"]`` likewise, else ``[]``: a wave
    along an axis is a pattern of lines too (a pick-up of the line rate, a banding)."""
    on = wmap > 0
    m = np.where(on, np.asarray(pmap, np.float64), 0.0)
    n_on = on.sum()
    total = float(np.sum(m * m) / max(n_on, 1))
    out = []
    for name, axis in (("rows", 1), ("columns", 0)):
        cnt = on.sum(axis=axis)
        means = m.sum(axis=axis) / np.maximum(cnt, 1)
        if total > 0 and float(np.sum(cnt * means * means) / max(n_on, 1)) > EXPLAINS_MOST * total:
            out.append(name)
    return out


def _periodic_map(rmap: np.ndarray, wmap: np.ndarray, light: np.ndarray, kind: str, row_var: float = 0.0,
                  min_cycles: float = LINE_PERIOD_MIN_CYCLES) -> dict:
    """The empirical map of a periodic pattern: the residual [ADU] band-passed around its strongest spatial
    frequencies (a smooth part, below ``min_cycles`` cycles across the frame, left out), on the whole
    frame; the ``fx = 0`` column weighed against the power row noise (``row_var`` [ADU^2]) puts there
    (:func:`row_power_factor`).

    The frequencies are taken one at a time, each from what the ones before leave (CLEAN: Roberts, Lehar &
    Dreher 1987, AJ 93, 968): the periodogram of a residual with unfitted pixels (masked sources, the other
    fold of a held-out split) holds every pattern's copies shifted by the mask's own frequencies, which are no
    pattern (on the other pixels they have the opposite sign); taking a component out with its mask takes its
    copies out too. Each kept frequency is weighted by the Wiener factor ``max(0, 1 - N / P)`` (``P`` its power, ``N`` the
    noise's mean power: the median power over ln 2, an exponential law's, times the row-noise factor at
    ``fx = 0``), the least-squares linear estimate of a pattern from pixels with noise (Wiener 1949; Press et
    al., Numerical Recipes, sect. 13.3); a band-pass of the fitted pixels holds the pattern times their share
    of the frame, which the component is divided by."""
    on = wmap > 0
    r = np.where(on, rmap - (rmap[on].mean() if np.any(on) else 0.0), 0.0)
    fill = max(float(on.mean()), 1e-3)
    g_row = row_power_factor(wmap, row_var, whitened=False)
    fy = np.fft.fftfreq(r.shape[0])[:, None]
    fx = np.fft.rfftfreq(r.shape[1])[None, :]
    low = np.hypot(fy * r.shape[0], fx * r.shape[1]) < min_cycles
    iy, ix = np.mgrid[: low.shape[0], : low.shape[1]]
    amap = np.zeros(r.shape, np.float64)
    for _ in range(PERIODIC_PEAKS):
        f = np.fft.rfft2(r)
        p = np.abs(f) ** 2
        p[:, 0] /= g_row
        p = np.where(low, 0.0, p)
        ky, kx = np.unravel_index(int(np.argmax(p)), p.shape)
        med = float(np.median(p[p > 0])) if np.any(p > 0) else 0.0
        if p[ky, kx] <= 0:
            break
        dy = np.minimum(np.abs(iy - ky), r.shape[0] - np.abs(iy - ky))
        near = (dy <= PERIODIC_KEEP_BINS) & (np.abs(ix - kx) <= PERIODIC_KEEP_BINS)
        if kx <= PERIODIC_KEEP_BINS:  # its mirror image across the rfft's axis
            my = (-ky) % r.shape[0]
            dym = np.minimum(np.abs(iy - my), r.shape[0] - np.abs(iy - my))
            near |= (dym <= PERIODIC_KEEP_BINS) & (ix <= PERIODIC_KEEP_BINS - kx)
        noise = med / math.log(2.0)
        wiener = np.clip(1.0 - noise / np.where(p > 0, p, np.inf), 0.0, 1.0)
        comp = np.fft.irfft2(np.where(near & ~low, f * wiener, 0.0), s=r.shape) / fill
        amap += comp
        r = np.where(on, r - comp, 0.0)
    return _relative(kind, amap, light)


#: false alarms per frame and smoothing scale of the matched filter that decides which compact features the
#: empirical map carries (:func:`_significant_features`): a seed is a peak the noise reaches this rarely (the
#: frame search's FRAME_FALSE_ALARM)
MAP_FALSE_ALARM = FRAME_FALSE_ALARM
#: a seeded feature is grown down to where its matched-filter S/N falls to this many sigma (below it the
#: feature is not told from the noise): a part of a detected whole, FOOTPRINT_SIGMA (as a spike's group is grown,
#: :data:`detector.signatures.GROW_SIGMA`)
MAP_GROW_SIGMA = FOOTPRINT_SIGMA
#: the per-source profile of the empirical map extends at most this far [output px]
PROFILE_MAX_PX = 32


def _seed_sigma(n_pix: int, s: float) -> float:
    """The matched-filter S/N [sigma] that white noise exceeds ``MAP_FALSE_ALARM`` times per frame among the
    ``n_pix / (4 pi s^2)`` independent positions of a Gaussian of ``s`` px (two-sided: bright and dark
    features): the look-elsewhere-corrected seed threshold of :func:`_significant_features`."""
    from scipy.stats import norm

    n_indep = max(n_pix / (4.0 * math.pi * s * s), 1.0)
    return float(norm.isf(0.5 * MAP_FALSE_ALARM / n_indep))


def matched_snr(rmap: np.ndarray, wmap: np.ndarray, s: float, exclude: np.ndarray | None = None) -> np.ndarray:
    """The S/N of a Gaussian feature of ``s`` px centred on each pixel: ``sum g r w / sqrt(sum g^2 w)``
    (the weighted least-squares amplitude over its error; ``r`` the residual [ADU], ``w`` its inverse
    variance, 0 off the fitted pixels), its smooth part (a Gaussian of 6 ``s``) removed and divided by its
    robust standard deviation (1.4826 MAD over the fitted pixels off ``exclude``: correlated noise included).
    Pixels where less than half the filter's weight has data are 0."""
    # off the frame there is no data (w = 0): zero padding, so that the border's pixels are not counted twice
    g1 = gaussian_filter(rmap * wmap, s, mode="constant") * (2.0 * math.pi * s * s)
    g2 = gaussian_filter(wmap, s / math.sqrt(2.0), mode="constant") * (math.pi * s * s)
    ok = wmap > 0
    typical = float(np.median(g2[ok])) if ok.any() else 0.0
    good = g2 > 0.5 * typical
    snr = np.where(good, g1 / np.sqrt(np.where(good, g2, 1.0)), 0.0)
    gw = good.astype(np.float64)
    snr = snr - np.where(good, gaussian_filter(snr, 6.0 * s, mode="constant")
                         / np.maximum(gaussian_filter(gw, 6.0 * s, mode="constant"), 1e-6), 0.0)
    sel = ok & good & (~exclude if exclude is not None else True)
    if sel.sum() < 64:
        return np.zeros_like(snr)
    v = snr[sel]
    sig = 1.4826 * float(np.median(np.abs(v - np.median(v))))
    return np.where(good, snr / sig, 0.0) if sig > 0 else np.zeros_like(snr)


#: a feature whose extent (its bounding box's diagonal) is this many times its scale is long (a trail)
MAP_LONG_SPAN = 12.0


def _significant_features(rmap: np.ndarray, wmap: np.ndarray, exclude: np.ndarray | None,
                          scales=FEATURE_SCALES) -> np.ndarray:
    """Where compact features significant on their own are, and at which scale: a map of the finest scale
    ``s`` [px] at which each pixel's feature is significant (0 off the features). At each scale ``s`` the matched-filter
    S/N (:func:`matched_snr`) seeds a feature above :func:`_seed_sigma` (a false alarm of MAP_FALSE_ALARM per
    frame) and the feature is grown to where its S/N of the same sign falls below MAP_GROW_SIGMA; pixels
    within 3 ``s`` of ``exclude`` (the sources' cores: a misfit source is another family) neither seed nor
    are mapped, and a compact feature that reaches them is the source's (one longer than MAP_LONG_SPAN x
    ``s``, a trail passing a star, keeps its other pixels);
    the scales are those of the morphology's own search (:func:`compact_features`)."""
    out = np.zeros(rmap.shape, np.float64)
    n_ok = int((wmap > 0).sum())
    for s in scales:
        if 24 * s > min(rmap.shape) or n_ok < 256:
            break
        # a blob within 3 s of a source's core belongs to the source (as in compact_features)
        near = ndi.binary_dilation(exclude, iterations=max(round(3 * s), 1)) if exclude is not None else None
        snr = matched_snr(rmap, wmap, s, near)
        t = _seed_sigma(n_ok, s)
        for sign in (1.0, -1.0):
            lab, n = ndi.label(sign * snr > MAP_GROW_SIGMA)
            if n == 0:
                continue
            idx = np.arange(1, n + 1)
            # seeded away from the sources' cores; a long feature (a trail) that passes near a source keeps
            # its other pixels: only those near the sources are left to them
            far = sign * snr if near is None else np.where(near, -np.inf, sign * snr)
            seeded = ndi.maximum(far, lab, idx) > t
            if near is not None:
                # a compact feature by a source belongs to the source; one far longer than its scale (a trail
                # passing a star) keeps its pixels away from the sources
                touches = ndi.maximum(near.astype(np.int8), lab, idx) > 0
                span = np.array([math.hypot(sl[0].stop - sl[0].start, sl[1].stop - sl[1].start)
                                 for sl in ndi.find_objects(lab)])
                seeded &= ~touches | (span > MAP_LONG_SPAN * s)
            if seeded.any():
                new = np.isin(lab, idx[seeded]) & (out == 0)
                if near is not None:
                    new &= ~near
                out[new] = s
    return out


def _source_profile_map(rmap: np.ndarray, wmap: np.ndarray, srcmap: np.ndarray, r_max: float
                        ) -> tuple[np.ndarray, np.ndarray]:
    """The per-source profile of a residual that follows the sources' light: ``S * K``, ``S`` the model's
    source light [ADU] and ``K = sum_k c_k A_k`` a radial kernel, ``A_k`` the 1 px wide annulus of radius ``k``
    (``k = 0``: the pixel itself) out to ``r_max`` (at most PROFILE_MAX_PX), the ``c_k`` by weighted least
    squares of the residual on the templates ``S * A_k`` over the fitted pixels: the mean residual profile
    around the stars per unit of their light, scaled by each star's flux (a ring, a halo, light taken from the
    cores). Returns (the map [ADU], the profile ``c_k`` [1 per annulus pixel])."""
    from scipy.signal import fftconvolve

    n = int(min(max(math.ceil(r_max), 2), PROFILE_MAX_PX))
    ann = _kernel_basis(n, harmonics=0)
    ok = wmap > 0
    x = np.empty((n + 1, int(ok.sum())), np.float32)  # the templates on the fitted pixels only
    for k, a in enumerate(ann):
        x[k] = fftconvolve(srcmap, a, mode="same")[ok]
    w = wmap[ok]
    g = (x * w) @ x.T.astype(np.float64)
    c = np.zeros(n + 1)
    keep = np.diag(g) > 0
    if keep.any():
        c[keep] = np.linalg.lstsq(g[np.ix_(keep, keep)], ((x[keep] * w) @ rmap[ok]).astype(np.float64),
                                  rcond=None)[0]
    kernel = sum(ck * a for ck, a in zip(c, ann))
    return fftconvolve(srcmap, kernel, mode="same"), c


def _feature_map(feats: dict, rmap: np.ndarray, wmap: np.ndarray, light: np.ndarray, kind: str,
                 res: Residuals | None = None) -> dict | None:
    """The empirical map of compact features (rings, blobs): a measurement of the residual where it is told
    from the noise, 0 elsewhere [ADU, or relative to the light when multiplicative].

    * Rings about the sources (``srings``: light moved around every source) are mapped as the per-source
      profile (:func:`_source_profile_map`, out to twice the rings' radius and their scale): the mean residual
      profile around the stars scaled by each star's light, which holds the faint stars' rings too.
    * Every other compact feature is mapped where it is significant on its own: the footprints
      :func:`compact_features` found (none: a line, a trail, is no blob), and every feature whose matched-filter
      S/N seeds above a false alarm of
      MAP_FALSE_ALARM per frame and scale, grown to where it falls below MAP_GROW_SIGMA sigma
      (:func:`_significant_features`; off the sources' cores when they are known). There the map is the
      residual smoothed at half the scale at which each feature is significant (normalised convolution over
      the fitted pixels: a feature found only at a coarse scale is not mapped with its noise); the pixels the
      comparison left to statistics (the spikes a glint's or a latent image's core makes) take their own
      residual, unless saturated: the feature is mapped where it is brightest, not interpolated from its wings
      (only the spikes of ``res.train`` on a held-out fold: the other fold's pixels are the ones it is scored on).
    """
    foot = feats["footprint"]["rings"] | feats["footprint"]["blobs"] | feats["footprint"]["srings"]
    scale = max([feats.get(f"scale_{f}", 1.0) for f in ("rings", "blobs", "srings") if feats[f"n_{f}"]] or [1.0])
    ok = (wmap > 0).astype(np.float64)
    amap = np.zeros(rmap.shape, np.float64)
    on_source = None
    rings_on_src = feats["n_srings"] >= 2 and feats["n_srings"] >= 2 * feats["n_rings"]
    if res is not None and res.background_adu is not None:
        srcmap = np.asarray(res.model_adu, np.float64) - res.background_adu
        on_source = srcmap > SOURCE_KERNEL_CORE_SIGMA * np.sqrt(np.maximum(np.asarray(res.var_adu2, np.float64), 1e-12))
        if rings_on_src:
            r_max = 2.0 * feats["sring_radius_px"] + 2.0 * feats["scale_srings"]
            amap, _ = _source_profile_map(rmap, wmap, np.where(np.isfinite(srcmap), srcmap, 0.0), r_max)
            foot = feats["footprint"]["rings"] | feats["footprint"]["blobs"]
    rest = np.where(ok > 0, rmap - amap, 0.0)
    # the scale [px] each mapped pixel is smoothed at: half the finest matched-filter scale at which its feature
    # is significant (a Gaussian feature of that scale is broadened by 12 %, its noise averaged over ~pi s^2 / 4
    # pixels), half the found features' scale in their grown footprints
    at = _significant_features(rest, wmap, on_source)
    if foot.any():
        fp = ndi.binary_dilation(foot, iterations=max(round(2 * scale), 1))
        at = np.where(fp & ((at == 0) | (at > scale)), scale, at)
    if on_source is not None and rings_on_src:
        at[ndi.binary_dilation(on_source, iterations=max(round(2 * scale), 1))] = 0.0
    grown = at > 0
    if grown.any():
        # a feature's interior (the core the comparison left to statistics) and the spike pixels at its edge
        filled = ndi.binary_fill_holes(ndi.binary_dilation(grown))
        at = np.where(filled & ~grown, ndi.maximum_filter(at, size=3), at)
        at = np.where(filled & (at == 0), scale, at)  # an interior farther than 1 px from a feature's pixels
        grown = filled
        sm = np.zeros(rmap.shape, np.float64)
        for sc in np.unique(at[grown]):
            sig = max(0.5 * float(sc), 0.5)
            here = grown & (at == sc)
            sm[here] = (gaussian_filter(rest, sig, mode="nearest")
                        / np.maximum(gaussian_filter(ok, sig, mode="nearest"), 1e-6))[here]
        if res is not None:
            s = res.sensor
            level, _ = res.level_maps()
            raw = res.data_adu.astype(np.float64) - res.model_adu - level - amap
            cap_adu = min(float(s.adc_max_adu), s.bias_adu + s.full_well_e * res.pixel_sum / res.gain)
            core = (grown & (ok == 0) & np.isfinite(raw) & (res.data_adu < 0.95 * cap_adu)
                    & (res.model_adu < 0.95 * cap_adu))
            if res.train is not None:
                # on a held-out fold the pixels of the other fold are not fitted either (``ok`` is 0 there):
                # they are the pixels the map will be scored on, not spikes left to statistics, and copying
                # their residual would make the description predict them exactly (a leak of the test fold)
                core &= res.train
            sm = np.where(core, raw, sm)
        amap = amap + np.where(grown, sm, 0.0)
    if not np.any(amap):
        return None
    return _relative(kind, amap, light)


def _feature_words(feats: dict, geometry: list[str], on_sources: bool = False) -> str:
    """``; 3 rings (median radius 9.7 px) ...`` for the rings and blobs named in ``geometry``."""
    words = []
    if "rings" in geometry and on_sources:
        words.append(f"{feats['n_srings']} ring(s) of median radius {feats['sring_radius_px']:.3g} px centred on "
                     "sources")
    elif "rings" in geometry:
        words.append(f"{feats['n_rings']} ring(s) of median radius {feats['ring_radius_px']:.3g} px")
    if "blobs" in geometry:
        words.append(f"{feats['n_blobs']} compact blob(s) of median radius {feats['blob_radius_px']:.3g} px "
                     "off the sources")
    return ("; " + ", ".join(words)) if words else ""


def _feature_amplitude(res: Residuals, feats: dict, fam: str, rmap: np.ndarray, light: np.ndarray,
                       relative: bool) -> tuple[float, str, str]:
    """(amplitude, unit, words) of the strongest feature of family ``fam``: the residual smoothed at the
    feature's scale, its largest absolute value in the footprints [e-], or relative to the light there [%]."""
    foot = feats["footprint"][fam]
    sm = gaussian_filter(rmap, max(feats[f"scale_{fam}"], 1.0), mode="nearest")
    off = ~(feats["footprint"]["rings"] | feats["footprint"]["blobs"] | feats["footprint"]["srings"])
    ref = float(np.median(sm[off])) if off.any() else 0.0  # the level around the features (a refitted level)
    peak_adu = float(np.max(np.abs(sm[foot] - ref))) if foot.any() else 0.0
    if relative:
        amp = 100 * peak_adu / max(float(np.median(light[foot])) if foot.any() else 0.0, 1e-9)
        return amp, "%", f"{amp:.3g} % of the light at the strongest {fam[-5:-1]}"
    amp = peak_adu * res.gain
    return amp, "e-", f"{amp:.4g} e- per pixel at the strongest {fam[-5:-1]}"


def _compact_only(res: Residuals, feats: dict, rmap: np.ndarray, light: np.ndarray) -> dict:
    """The description when only compact features stand out (the frame's chi2 dilutes them): geometry
    ``rings`` and / or ``blobs`` by their shares; kind ``redistributed`` for rings centred on the sources,
    else ``multiplicative`` on a flat screen's frame (a prior, ``kind_certain`` false), else ``additive``
    (light added where the model has none: the features sit off the sources); the amplitude is the strongest
    feature's peak residual smoothed at its scale [e-] (or relative to the light [%] when multiplicative)."""
    on_src = feats["n_srings"] >= 2 and feats["n_srings"] >= 2 * feats["n_rings"]
    fams = sorted((f for f in ("rings", "blobs") if feats[f"n_{f}"]), key=lambda f: -feats[f])
    certain = True
    if on_src:
        kind, geometry = "redistributed", ["sources", "rings"] + [f for f in fams if f != "rings"]
    elif res.light_source == "flat":
        kind, geometry, certain = "multiplicative", fams, False
    else:
        kind, geometry = "additive", fams
    main = geometry[0] if geometry[0] != "sources" else "srings"
    amp, unit, desc = _feature_amplitude(res, feats, main, rmap, light, kind == "multiplicative")
    desc += _feature_words(feats, geometry, on_src)
    extra = "" if certain else " (additive and multiplicative cannot be told apart on this uniform light)"
    shares = {f: round(float(feats[f]), 3) for f in fams}
    return {"kind": kind, "kind_certain": certain, "geometry": geometry,
            "scale_px": round(float(feats[f"{main[:-1]}_radius_px"]), 2), "amplitude": round(amp, 4), "unit": unit,
            "shares": shares, "explanation": _words(kind, geometry, desc) + extra}


def _peak_sigma(contrast: float, z: np.ndarray) -> float:
    """The significance [Gaussian sigma] of a periodogram peak ``contrast`` times the median power, among the
    frequencies of the (at most 512 x 512) cut :func:`_peak` searches: a bin of white noise's periodogram is
    exponential, P(> c median) = 2^-c, times the number of bins searched (the look-elsewhere effect)."""
    return sigma_of_log10_p(math.log10(tested_frequencies(z.shape)) - contrast * math.log10(2.0))


#: the largest significance reported [sigma]: a tail probability below 1e-300 (a double's range) is reported as this
SIGMA_CAP = 37.0


def sigma_of_log10_p(log10_p: float) -> float:
    """The one-sided Gaussian sigma of a tail probability ``10 ** log10_p`` (SIGMA_CAP beyond a double's range)."""
    from scipy.stats import norm

    return float(norm.isf(10.0 ** min(log10_p, 0.0))) if log10_p > -300 else SIGMA_CAP


def _periodic_only(res: Residuals, period: float, contrast: float, zhp: np.ndarray, wmap: np.ndarray) -> dict:
    """The description when only a periodogram peak stands out: geometry ``periodic``; kind ``multiplicative``
    on a flat screen's frame (a prior, ``kind_certain`` false: fringes), else ``additive`` (pick-up); the
    amplitude of the sinusoid the peak holds (``A = 2 |F| / N`` for N pixels) [e-] at the frame's typical
    noise."""
    g = _cut_row_factor(wmap, res.row_var_adu2)
    _, f, fy, fx, side = _spectrum(zhp, g)
    ky, kx = np.unravel_index(int(np.argmax(f)), f.shape)
    if kx == 0:  # the sinusoid's amplitude itself, not its ratio to the null
        f[:, 0] *= math.sqrt(max(g, 1.0))
    amp_sigma = 2.0 * float(f[ky, kx]) / (side * side)
    sig_adu = float(np.median(1.0 / np.sqrt(wmap[wmap > 0]))) if np.any(wmap > 0) else 0.0
    amp = amp_sigma * sig_adu * res.gain
    angle = float(np.degrees(np.arctan2(float(fy[ky, 0]), float(fx[0, kx]))))  # of the wave vector (x, y)
    flat = res.light_source == "flat"
    kind = "multiplicative" if flat else "additive"
    desc = (f"a sinusoid of {amp:.3g} e- amplitude, period {period:.3g} px, wave vector at {angle:.0f} deg (a single "
            f"spatial frequency {contrast:.0f} x the median power)")
    extra = " (additive and multiplicative cannot be told apart on this uniform light)" if flat else ""
    return {"kind": kind, "kind_certain": not flat, "geometry": ["periodic"], "scale_px": round(period, 2),
            "amplitude": round(amp, 4), "unit": "e-", "shares": {"periodic": 1.0},
            "explanation": _words(kind, ["periodic"], desc) + extra}


def _upsample(blocks: np.ndarray, b: int, shape: tuple[int, int]) -> np.ndarray:
    """A block map to every output pixel (bilinear through the block centres, edges held)."""
    ny, nx = blocks.shape
    yc, xc = (np.arange(ny) + 0.5) * b - 0.5, (np.arange(nx) + 0.5) * b - 0.5
    y, x = np.arange(shape[0]), np.arange(shape[1])
    tmp = np.stack([np.interp(x, xc, row) for row in blocks])
    return np.stack([np.interp(y, yc, tmp[:, j]) for j in range(shape[1])], axis=1).astype(np.float32)


def _source_share(res: Residuals, idx, r, w) -> dict | None:
    """The share of the pixel chi2 excess on the sources, and whether their fluxes are kept (the residual
    sums to little over them: light moved, not added or lost)."""
    if res.background_adu is None:
        return None
    srcl = (np.asarray(res.model_adu, np.float64) - res.background_adu).ravel()[idx]
    on = srcl * np.sqrt(w) > 2.0
    if on.sum() < 50:
        return None
    z2 = r * r * w
    excess_on, excess_all = float(np.sum(z2[on]) - on.sum()), float(np.sum(z2) - idx.size)
    if excess_all <= 0:
        return None
    s, sa = float(np.sum(r[on])), float(np.sum(np.abs(r[on])))
    return {"share": max(excess_on, 0.0) / excess_all, "flux_kept": abs(s) < 0.15 * sa}


#: smoothing scale of the local additive estimate around a source [px] (a few PSF widths: beyond the core)
KIND_LOCAL_SIGMA_PX = 6.0


def _local_estimates(res: Residuals, idx, r, w, on) -> dict:
    """What the background's residual is at the source pixels ``idx[on]``, from the pixels off the sources
    [ADU]: the frame's mean, the mean of the pixel's own column, of its own row (a streak or band through the
    source) and a Gaussian-weighted local mean (KIND_LOCAL_SIGMA_PX): the candidate local offsets ``a``."""
    shape = res.data_adu.shape
    rm = np.zeros(shape)
    wm = np.zeros(shape)
    off = idx[~on]
    rm.ravel()[off] = r[~on] * w[~on]
    wm.ravel()[off] = w[~on]
    y, x = np.divmod(idx[on], shape[1])
    out = {"frame": np.full(int(on.sum()), float(rm.sum() / max(wm.sum(), 1e-300)))}
    for name, axis, at in (("column", 0, x), ("row", 1, y)):
        num, den = rm.sum(axis=axis), wm.sum(axis=axis)
        out[name] = np.where(den[at] > 0, num[at] / np.maximum(den[at], 1e-300), 0.0)
    num = gaussian_filter(rm, KIND_LOCAL_SIGMA_PX, mode="nearest")
    den = gaussian_filter(wm, KIND_LOCAL_SIGMA_PX, mode="nearest")
    out["local"] = (num / np.maximum(den, 1e-300)).ravel()[idx[on]]
    return out


def _kind_from_sources(res: Residuals, idx, r, w) -> str | None:
    """On a uniform light: does the residual scale with the sources' light too (multiplicative) or not?
    None when there are too few sources to tell.

    The background's residual next to a source, ``a`` (off-source pixels: the frame's, the source's column's
    or row's, or a local mean, whichever predicts the source pixels best), predicts the source pixels' residual
    as ``a`` if the pattern is added light or offset, and as ``a (1 + S / B)`` if it multiplies the light (``S``
    the source's model light, ``B`` the background's): a streak of added light through a star does not scale
    with the star, a dust shadow on it does."""
    if res.background_adu is None:
        return None
    srcl = (np.asarray(res.model_adu, np.float64) - res.background_adu).ravel()[idx]
    on = srcl * np.sqrt(w) > SOURCE_KERNEL_CORE_SIGMA
    if on.sum() < 200:
        return None
    bg = np.maximum(np.asarray(res.background_photo_adu, np.float64).ravel()[idx][on], 1e-9)
    ro, wo, gain = r[on], w[on], 1.0 + srcl[on] / bg
    best = None
    for a in _local_estimates(res, idx, r, w, on).values():
        c_add = float(np.sum((ro - a) ** 2 * wo))
        c_mul = float(np.sum((ro - a * gain) ** 2 * wo))
        if best is None or min(c_add, c_mul) < min(best):
            best = (c_add, c_mul)
    c_add, c_mul = best
    if abs(c_mul - c_add) < 25:
        return None
    return "multiplicative" if c_mul < c_add else "additive"


#: half size of the kernel stacked about the sources [output px] (a trail or halo a few PSF widths long) ...
SOURCE_KERNEL_HALF = 6
#: ... fitted on at most this many pixels next to the sources (a regular subsample beyond) [pixels]
SOURCE_KERNEL_PIXELS = 60_000
#: a source pixel: its model light this many sigma above the noise (a source's footprint, FOOTPRINT_SIGMA)
SOURCE_KERNEL_CORE_SIGMA = FOOTPRINT_SIGMA


#: angular harmonics of the kernel's annuli: 0 (a ring, a halo), 1 (one-sided: a trail, a coma), 2 (an
#: elongation along an axis)
SOURCE_KERNEL_HARMONICS = 2


def _kernel_basis(h: int, harmonics: int = SOURCE_KERNEL_HARMONICS) -> list[np.ndarray]:
    """The kernel's basis on offsets ``|dy|, |dx| <= h``: the source's own pixel, then for every 1 px annulus
    (radius 1 .. h) the harmonics ``cos m theta``, ``sin m theta`` for m = 0 .. ``harmonics`` (0: the radial
    annuli alone)."""
    dy, dx = np.mgrid[-h: h + 1, -h: h + 1].astype(np.float64)
    r = np.hypot(dy, dx)
    th = np.arctan2(dy, dx)
    ring = np.rint(r)
    out = [(r == 0).astype(np.float64)]
    for i in range(1, h + 1):
        on = (ring == i).astype(np.float64)
        out.append(on)
        for m in range(1, harmonics + 1):
            out += [on * np.cos(m * th), on * np.sin(m * th)]
    return out


def source_kernel(res: Residuals, rmap: np.ndarray, wmap: np.ndarray) -> dict | None:
    """The residual about the sources as a kernel of their light: ``r(p) = sum_o K(o) S(p - o)`` over offsets
    ``|o| <= SOURCE_KERNEL_HALF`` (``S`` the sources' model light before the full-well clip, or the signal the
    model records, clipped, whichever the residual follows better [ADU]), ``K`` in
    1 px annuli times angular harmonics 0 .. 2 (:func:`_kernel_basis`: smooth enough to be read, any shape a
    trail, a one-sided halo, a ring or an elongation has), fitted by weighted least squares on the fitted
    pixels next to the sources: the stacked residual profile of the sources per unit of their light. Its
    chi2 gain against its k parameters gives ``sigma`` = (delta chi2 - k) / sqrt(2 k); ``map`` is ``S``
    convolved with ``K`` [ADU]; ``of`` which ``S``. None without sources."""
    if res.background_adu is None:
        return None
    # the light the optics spread (before the full-well clip) or the signal the read-out recorded (an
    # amplifier's echo follows what it read): whichever the residual follows better
    light = res.source_light()
    recorded = np.clip(np.asarray(res.model_adu, np.float64) - res.background_adu, 0.0, None)
    fits = []
    for tag, src in (("light", light), ("recorded signal", recorded)):
        f = _kernel_fit(res, rmap, wmap, src)
        if f is not None:
            fits.append(dict(f, of=tag))
    return max(fits, key=lambda f: f["dchi2"]) if fits else None


def _kernel_fit(res: Residuals, rmap: np.ndarray, wmap: np.ndarray, src: np.ndarray) -> dict | None:
    """:func:`source_kernel` for one source image ``src`` [ADU]."""
    from scipy.signal import fftconvolve

    sd = np.sqrt(np.maximum(np.asarray(res.var_adu2, np.float64), 1e-12))
    core = src > SOURCE_KERNEL_CORE_SIGMA * sd
    h = SOURCE_KERNEL_HALF
    basis = _kernel_basis(h)
    k = len(basis)
    if core.sum() < 20:
        return None
    near = ndi.binary_dilation(core, structure=np.ones((3, 3), bool), iterations=h) & (wmap > 0)
    pix = np.flatnonzero(near)
    if pix.size < 10 * k:
        return None
    if pix.size > SOURCE_KERNEL_PIXELS:
        pix = pix[:: math.ceil(pix.size / SOURCE_KERNEL_PIXELS)]
    x = np.stack([fftconvolve(src, bk, mode="same").ravel()[pix] for bk in basis], axis=1)
    wv, rv = wmap.ravel()[pix], rmap.ravel()[pix]
    sw = np.sqrt(wv)
    coef, *_ = np.linalg.lstsq(x * sw[:, None], rv * sw, rcond=1e-10)
    dchi2 = float(np.sum(wv * rv * rv) - np.sum(wv * (rv - x @ coef) ** 2))
    kern = np.tensordot(coef, np.stack(basis), axes=1)
    kmap = fftconvolve(src, kern, mode="same").astype(np.float32)
    return {"kernel": kern, "dchi2": dchi2, "k": k, "sigma": (dchi2 - k) / math.sqrt(2 * k), "map": kmap}


def _kernel_words(ker: dict) -> dict:
    """The description of a kernel about the sources (:func:`source_kernel`): its net share of the sources'
    light (flux kept: redistributed; else added or taken: additive), its one-sided part (the signed first
    moment of the light it moves: a trail toward an angle), its axis (the non-radial part's extent along the
    rows or the columns) and its size. The source's own pixel (a photometric scale) is not a shape."""
    kern = ker["kernel"]
    h = kern.shape[0] // 2
    dy, dx = np.mgrid[-h: h + 1, -h: h + 1].astype(np.float64)
    rr = np.rint(np.hypot(dy, dx))
    c = kern.copy()
    c[h, h] = 0.0
    mass = float(np.abs(c).sum())
    if mass <= 0:
        return {}
    net = float(kern.sum())
    kind = "redistributed" if abs(net) < 0.25 * mass else "additive"
    # the non-radial part: each annulus less its mean (a ring or halo is radial)
    ring_mean = np.zeros_like(c)
    for i in range(1, h + 1):
        on = rr == i
        ring_mean[on] = c[on].mean()
    nr = np.abs(c - ring_mean)
    vx, vy = float(np.sum(nr * dx * dx)), float(np.sum(nr * dy * dy))
    geometry = ["sources"]
    if vx > 2 * vy:
        geometry.append("rows")
    elif vy > 2 * vx:
        geometry.append("columns")
    # the signed first moment [px per unit of moved light]: toward where light is added, away from where taken
    mx, my = float(np.sum(c * dx) / mass), float(np.sum(c * dy) / mass)
    one_sided = math.hypot(mx, my)
    where = ""
    if one_sided > 0.5:
        ang = math.degrees(math.atan2(my, mx))
        where = (f"; one-sided: light gained toward {ang:.0f} deg and lost on the opposite side (a trail, a coma, "
                 "an amplifier's overshoot or undershoot along the read-out)")
    size = float(np.sqrt(np.sum(np.abs(c) * (dx * dx + dy * dy)) / mass))
    sense = "moved about them (flux kept)" if kind == "redistributed" else ("added next to them" if net > 0 else
                                                                          "taken from next to them")
    axis = {"rows": ", along the rows", "columns": ", along the columns"}.get(geometry[-1], "")
    desc = (f"{100 * mass:.3g} % of the sources' light {sense} within {h} px{axis}, rms distance {size:.2g} px"
            f"{where}; stacked over every source, following their {ker.get('of', 'light')} ({ker['sigma']:.0f} sigma)")
    # flux kept is what the level-profiled residual shows, but a loss in proportion to the sources' light is
    # partly taken by the refitted light level (the sources' flux scale and the frame's light level are nearly
    # one parameter on a star field): "kept" is not certain
    certain = kind != "redistributed"
    doubt = "" if certain else (" (whether the sources' flux is kept or partly taken cannot be told: the refitted "
                                "light level takes a loss in proportion to their light)")
    return {"kind": kind, "kind_certain": certain, "geometry": geometry, "scale_px": round(size, 2),
            "amplitude": round(100 * (mass if kind == "redistributed" else net), 4), "unit": "% of the sources' light",
            "shares": {"sources": 1.0}, "explanation": _words(kind, geometry, desc) + doubt}


def _words(kind: str, geometry: list[str], desc: str) -> str:
    fam = [FAMILIES.get((kind, g)) for g in geometry if FAMILIES.get((kind, g))]
    article = "an" if kind[0] in "aeiou" else "a"
    head = f"{article} {kind} pattern ({', '.join(geometry)}): {desc}"
    return head + (f"; nearest physical families: {fam[0]}" if fam else "")
