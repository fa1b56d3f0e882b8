"""Ghosts: out-of-focus images of the sources formed by a double reflection, and their diagnosis in forms
the plugin's default does not assume.

Physics
-------
Light reflected twice (sensor surface -> filter, window or cover glass; the two faces of a filter or of a
corrector lens) reaches the focal plane as an out-of-focus image of every bright source with a fraction
``alpha`` (the product of the two surfaces' reflectances, ~1e-4..1e-2) of its flux (Gross, *Handbook of
Optical Systems* vol. 5, 2012, ch. 40 "ghost images"; Abd El-Maksoud & Sasian 2009, Proc. SPIE 7428,
doi:10.1117/12.828564, "Paraxial ghost image analysis"). Its position is to first order a linear map of
the source position ``x`` about a fixed point ``c``:

    x' = c + m (x - c)

* ``m = -1``: a point reflection through ``c`` (a curved surface pair about the optical axis; the field
  flattener ghost of HST/WFPC2 lies on the line through the CCD centre and the star, WFPC2 Instrument
  Handbook section 5.9); ``c`` is the sensor centre for centred optics and moves off it when the optics
  are decentred or tilted;
* ``m = +1``: a copy shifted by a fixed vector ``d`` (a double reflection in a near-parallel plate with a
  small wedge, or a tilted window/filter: "the relative position of these ghosts does not vary much over
  the field", WFPC2 Handbook 5.9; the offset ghost of OmegaCAM's dewar window).

The ghost is defocused by the extra optical path ``2 t / n`` of the reflection pair (``t`` the surface
separation, ``n`` the index), so its profile is the beam's cross-section at the sensor: a uniform disc of
radius ``2 t / (2 n N)`` for an f/``N`` beam, an **annulus** when the beam has a central obscuration (a
Newtonian's secondary: inner/outer radius = the linear obscuration ratio; the "doughnut" ghosts of WFPC2's
WFC and of the Calypso HRCam, Truax 2000, Calypso ER-107), or a blurred disc (aberrations, a thick stack):
``profile`` = "disc", "annulus" (``inner_ratio``) or "gauss" (``radius_px`` then the Gaussian's sigma). For
any real plate (t >~ 0.3 mm) at f/2.4..f/10 the disc is several pixels or more across: a **sharp** copy of
the sources is not a ghost (a latent image, crosstalk).

Diagnosis (:class:`GhostSignature`)
-----------------------------------
The plugin's own form (through the axis, a disc) is fitted as before (:func:`image_plane._ghost_variants`).
Beside it the geometry is **found from the data**: the level-profiled residual ``r`` (weight ``w = 1/var``)
is cross-correlated with the model's source image ``S`` (the model's light without its background) blurred
by a probe profile ``K`` (the matched filter ``G = K * S``), under the two map families at once, in Fourier
space (Wiener-Khinchin; one set of padded transforms serves both):

* shift ``d`` (m = +1): ``num(d) = sum_x w r(x) G(x - d)``, a cross-correlation;
* point reflection about ``c`` (m = -1): ``num(u) = sum_x w r(x) G(u - x)`` with ``u = 2 c``, a convolution;

and ``den = sum_x w G(.)^2`` the same way with ``w`` and ``G^2``, so that at every geometry the amplitude is
``alpha = num / den`` and the chi2 it removes ``num^2 / den`` (the weighted least squares of one template:
the matched filter, Turin 1960, IRE Trans. Inf. Theory 6, 311). The sources' own cores are masked in the
scan (a PSF mismatch there is not a ghost). ``z = num / sqrt(den)`` is N(0, 1) per geometry under the null;
its scatter over the map (robust: MAD) is the empirical null (Efron 2004, JASA 99, 96) and the peak must
exceed the Bonferroni threshold of the number of independent geometries searched (the look-elsewhere
effect, Gross & Vitells 2010, Eur. Phys. J. C 70, 525) at a global false-alarm probability
:data:`SCAN_GLOBAL_P`. At the found geometry the profile (disc, annulus and its obscuration ratio, Gaussian;
the radius) and ``alpha`` are fitted by the linear machinery (:class:`~detector.signatures.LinearSignature`),
the global levels jointly. The searched parameters are counted in the BIC: the offset (2), the radius (1),
the profile's form (1) and the map family (1) beside ``alpha``; a 2-D scan of ``N`` independent cells has an
expected null maximum of ``~2 ln N`` in chi2, below the ``2 ln n`` the BIC charges for the offset
(``N <~ 4 n``). The general form wins over the plugin's only when it pays for them.

Plausibility (:meth:`GhostSignature.plausible`): ``0 < alpha <= 0.1``; the profile must be defocused (rms
radius at least :data:`GHOST_MIN_RMS_PSF` times the sources' own);
and a ghost must sit where the map puts it for most of the bright sources whose ghost the fit predicts
detectably, not rest on one source.

Coordinates are sensor pixels (``ys``, ``xs``: the output pixel centres, spacing = binning); the optical
axis is at the sensor centre.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
import scipy.fft
import scipy.special
import scipy.stats
from astropy.nddata.utils import NoOverlapError, extract_array, overlap_slices
from pydantic import Field
from scipy import ndimage, signal

from ..signatures import Fit, LinearSignature, Residuals, Variant, fit_linear, search_sample
from ..significance import EXPLAINS_MOST, FOOTPRINT_SIGMA, FRAME_FALSE_ALARM
from .base import Effect, EffectParams, Stage, Tile, register_effect
from .image_plane import (
    FIT_FFT_WORKERS,
    _ghost_variants,
    _has_structure,
    _photo_sensor_coords,
    _sensor_centre,
    _store,
    disc_kernel,
    ghost_image,
    inverse_rfft2,
)

# --- pure functions: the ghost's map and profile ----------------------------------------------------------------

PROFILES = ("disc", "annulus", "gauss")


def ghost_kernel(profile: str, radius_px: float, inner_ratio: float = 0.0) -> np.ndarray:
    """Normalised ghost profile [1 per px] on a pixel grid: a uniform "disc" of ``radius_px``, an "annulus"
    from ``inner_ratio * radius_px`` to ``radius_px`` (a defocused pupil with a central obscuration), or a
    "gauss" of sigma ``radius_px``; discs and annuli antialiased by 4x4 supersampling."""
    if profile == "disc" or (profile == "annulus" and inner_ratio <= 0):
        return disc_kernel(radius_px)
    if profile == "gauss":
        s = max(float(radius_px), 0.3)
        half = int(np.ceil(4 * s)) + 1
        t = np.arange(-half, half + 1, dtype=np.float64)
        g = np.exp(-0.5 * (t / s) ** 2)
        k = np.outer(g, g)
        return (k / k.sum()).astype(np.float32)
    if profile != "annulus":
        raise ValueError(f"unknown ghost profile {profile!r}")
    r = max(float(radius_px), 0.5)
    ri = float(inner_ratio) * r
    half = int(np.ceil(r)) + 1
    n, m = 4, 2 * half + 1
    c = (np.arange(m * n) + 0.5) / n - (half + 0.5)
    rr = c[:, None] ** 2 + c[None, :] ** 2
    inside = (rr <= r * r) & (rr >= ri * ri)
    k = inside.reshape(m, n, m, n).mean(axis=(1, 3))
    return (k / k.sum()).astype(np.float32)


def kernel_rms_px(profile: str, radius_px: float, inner_ratio: float = 0.0) -> float:
    """rms radius [px] of a ghost profile: ``r / sqrt 2`` (disc), ``sqrt((r^2 + r_in^2) / 2)`` (annulus),
    ``sqrt 2 sigma`` (Gaussian)."""
    if profile == "gauss":
        return float(np.sqrt(2.0) * radius_px)
    ri = inner_ratio * radius_px if profile == "annulus" else 0.0
    return float(np.sqrt((radius_px ** 2 + ri ** 2) / 2.0))


def kernel_transfer(profile: str, radius_px: float, inner_ratio: float, fx: np.ndarray, fy: np.ndarray
                    ) -> np.ndarray:
    """Fourier transform (transfer function) of a normalised ghost profile at frequencies [cycles/px]:
    a disc of radius ``a`` has ``2 J1(2 pi a f) / (2 pi a f)`` (the Airy form, Bracewell 2000, ch. 12), an
    annulus the area-weighted difference of two discs, a Gaussian ``exp(-2 pi^2 sigma^2 f^2)``."""
    f = np.sqrt(fx * fx + fy * fy)

    def disc(a):
        q = 2 * np.pi * max(a, 1e-6) * f
        with np.errstate(invalid="ignore", divide="ignore"):
            h = np.where(q > 1e-8, 2 * scipy.special.j1(q) / np.where(q > 1e-8, q, 1.0), 1.0)
        return h

    if profile == "gauss":
        return np.exp(-2 * np.pi ** 2 * radius_px ** 2 * f * f)
    if profile == "annulus" and inner_ratio > 0:
        ro, ri = float(radius_px), float(inner_ratio) * float(radius_px)
        return (ro * ro * disc(ro) - ri * ri * disc(ri)) / (ro * ro - ri * ri)
    return disc(float(radius_px))


def _axis_source(n: int, positions: np.ndarray, offset: float, step: float) -> np.ndarray:
    """Fractional source index along one axis for output pixels at ``positions`` [sensor px]: ``offset``
    is the source's sensor coordinate as a function of the output's (already applied by the caller)."""
    return (positions - offset) / step


def map_sources(image: np.ndarray, ys: np.ndarray, xs: np.ndarray, mode: str, centre_y_px: float = 0.0,
                centre_x_px: float = 0.0, shift_dy_px: float = 0.0, shift_dx_px: float = 0.0,
                magnification: float = -1.0) -> np.ndarray:
    """The image moved by the ghost's map ``x' = c + m (x - c)`` [same unit, flux kept]: "mirror" (``m`` =
    ``magnification``, about the point (``centre_y_px``, ``centre_x_px``) [sensor px]) or "shift" (``m = +1``:
    ``x' = x + d``, ``d`` = (``shift_dy_px``, ``shift_dx_px``) [sensor px]).

    ``ys``, ``xs``: sensor coordinates of the output pixel centres (spacing = binning). The map is separable,
    so each axis is resampled linearly on its own (pixels as boxes, as :func:`image_plane.shift`); light
    mapped from outside the window is unknown and left out (0)."""
    step_y = float(ys[1] - ys[0]) if ys.size > 1 else 1.0
    step_x = float(xs[1] - xs[0]) if xs.size > 1 else 1.0
    if mode == "shift":
        sy, sx = ys - shift_dy_px, xs - shift_dx_px  # the source of the output at x' is x' - d
        jac = 1.0
    elif mode == "mirror":
        m = float(magnification)
        sy, sx = centre_y_px + (ys - centre_y_px) / m, centre_x_px + (xs - centre_x_px) / m
        jac = 1.0 / (m * m)  # the ghost's area grows as m^2: its surface brightness falls as 1/m^2
    else:
        raise ValueError(f"unknown ghost mode {mode!r}")
    out = _resample_axis(image, (sy - ys[0]) / step_y, 0)
    out = _resample_axis(out, (sx - xs[0]) / step_x, 1)
    return (out * np.float32(jac)).astype(image.dtype, copy=False) if jac != 1.0 else out


def _resample_axis(a: np.ndarray, p: np.ndarray, axis: int) -> np.ndarray:
    """``a`` sampled at fractional indices ``p`` along ``axis`` (linear; 0 outside ``[0, n - 1]``)."""
    n = a.shape[axis]
    ok = (p >= 0) & (p <= n - 1)
    i0 = np.clip(np.floor(p).astype(int), 0, max(n - 2, 0))
    f = np.clip(p - i0, 0.0, 1.0).astype(np.float32)
    i1 = np.minimum(i0 + 1, n - 1)
    shape = [1, 1]
    shape[axis] = -1
    f = f.reshape(shape)
    okr = ok.reshape(shape)
    out = np.take(a, i0, axis=axis) * (1 - f) + np.take(a, i1, axis=axis) * f
    return np.where(okr, out, 0).astype(a.dtype, copy=False)


def ghost_general(image: np.ndarray, ys: np.ndarray, xs: np.ndarray, yc: float, xc: float, mode: str,
                  centre_dy_px: float, centre_dx_px: float, shift_dy_px: float, shift_dx_px: float, profile: str,
                  radius_px: float, inner_ratio: float, magnification: float = -1.0) -> np.ndarray:
    """Unit-strength ghost of every source of ``image`` [same unit]: mapped (:func:`map_sources`, the mirror
    about the sensor centre (``yc``, ``xc``) moved by (``centre_dy_px``, ``centre_dx_px``)) and spread over the
    profile (:func:`ghost_kernel`, ``radius_px`` in sensor px). The image's diffuse level (its median: the
    sky, which extends beyond the window) has a uniform ghost; only the rest is mapped, so the light that
    the map brings from outside the window is the diffuse level, not nothing."""
    step = float(xs[1] - xs[0]) if xs.size > 1 else 1.0
    sub = image[:: max(1, image.shape[0] // 512), :: max(1, image.shape[1] // 512)]
    base = np.float32(np.median(sub)) if sub.size else np.float32(0)
    moved = map_sources(image - base, ys, xs, mode, yc + centre_dy_px, xc + centre_dx_px, shift_dy_px, shift_dx_px,
                        magnification)
    k = ghost_kernel(profile, radius_px / step, inner_ratio)
    return (signal.oaconvolve(moved, k, mode="same") + base).astype(image.dtype)


# --- the geometry scan ---------------------------------------------------------------------------------------------

#: probe profiles (disc radii [sensor px]) of the geometry scan: matched filters from a small to a wide ghost
GHOST_PROBE_RADII_PX = (4.0, 12.0, 35.0)
#: the scan's arrays are binned to at most this many pixels a side (and by up to a quarter of the probe radius)
SCAN_MAX_SIDE = 768
#: global false-alarm probability of the scan's peak over every geometry, probe and map family searched: the
#: frame search's (FRAME_FALSE_ALARM)
SCAN_GLOBAL_P = FRAME_FALSE_ALARM
#: a model source pixel brighter than this many noise sigmas is a source core, masked in the scan
CORE_SIGMA = FOOTPRINT_SIGMA
#: the other map family's peak is fitted as well when its z is at least this share of the best one's
SECOND_FAMILY_Z = 0.9


def source_image(res: Residuals) -> np.ndarray:
    """The model's sources [ADU]: its light before the response minus its background's light, >= 0."""
    s = np.asarray(res.photo_field, np.float32) - res.background_photo_adu
    return np.maximum(s, 0).astype(np.float32)


def _residual_maps(res: Residuals) -> tuple[np.ndarray, np.ndarray]:
    """(w r, w) on the frame [1/ADU, 1/ADU^2]: the level-profiled residual times its weight and the weight,
    zero off the fitted pixels."""
    idx, r, w = res.flat_profiled()
    rw = np.zeros(res.data_adu.size, np.float64)
    ww = np.zeros(res.data_adu.size, np.float64)
    rw[idx] = r * w
    ww[idx] = w
    return rw.reshape(res.data_adu.shape), ww.reshape(res.data_adu.shape)


def _bin_sum(a: np.ndarray, q: int) -> np.ndarray:
    if q == 1:
        return a
    h, w = (a.shape[0] // q) * q, (a.shape[1] // q) * q
    return a[:h, :w].reshape(h // q, q, w // q, q).sum(axis=(1, 3))


def psf_rms_px(src: np.ndarray, n_sources: int = 25, half: int = 8) -> float:
    """The sources' rms radius [output px]: median over the brightest isolated peaks of the model's source
    image of ``sqrt(sum S r^2 / sum S)`` within ``half`` px (0 when there are none)."""
    peaks = bright_sources(src, n_sources, half)
    out = []
    t = np.arange(-half, half + 1, dtype=np.float64)
    r2 = t[:, None] ** 2 + t[None, :] ** 2
    for y, x, _ in peaks:
        st = src[y - half:y + half + 1, x - half:x + half + 1].astype(np.float64)
        if st.shape != r2.shape or st.sum() <= 0:
            continue
        out.append(np.sqrt(float((st * r2).sum() / st.sum())))
    return float(np.median(out)) if out else 0.0


def bright_sources(src: np.ndarray, n: int, border: int = 0) -> list[tuple[int, int, float]]:
    """The ``n`` brightest local maxima of the source image (5x5 neighbourhoods) at least ``border`` px from
    the edges: (row, column, summed 5x5 flux [ADU]), brightest first."""
    if not src.size or float(src.max()) <= 0:
        return []
    mx = ndimage.maximum_filter(src, size=5, mode="constant")
    flux = ndimage.uniform_filter(src.astype(np.float64), size=5, mode="constant") * 25
    pk = (src == mx) & (src > 0)
    if border:
        pk[:border] = pk[-border:] = False
        pk[:, :border] = pk[:, -border:] = False
    ys, xs = np.nonzero(pk)
    if not ys.size:
        return []
    f = flux[ys, xs]
    order = np.argsort(f)[::-1][:n]
    return [(int(ys[i]), int(xs[i]), float(f[i])) for i in order]


def scan_geometry(rw: np.ndarray, w: np.ndarray, src: np.ndarray, step: float, probe_radii_px=GHOST_PROBE_RADII_PX,
                  psf_rms: float = 1.0, workers: int | None = None) -> dict | None:
    """The ghost geometry that best explains the residual, searched over both map families (see the module
    docstring). Inputs on the output pixel grid: ``rw`` = w r and ``w`` (0 where not fitted or masked),
    ``src`` the model's sources; ``step`` the output pixel [sensor px]; ``psf_rms`` the sources' rms radius
    [output px].

    Returns the best peak as a dict: ``mode`` ("mirror" or "shift"), ``lag`` (the integer lag on the output
    grid: ``u = 2 c`` in array indices for a mirror, the shift ``d`` for a shift), ``z`` (its matched-filter
    significance over the map's robust scatter), ``threshold`` (the Bonferroni threshold over ``trials``
    independent geometries), ``probe_px`` (the probe radius [sensor px]), ``alpha`` (num / den), and
    ``found`` (z >= threshold). None when nothing can be searched."""
    h, wd = rw.shape
    best, trials, scans = None, 0.0, []
    for radius in probe_radii_px:
        r_out = radius / step  # output px
        q = int(max(1, min(max(1, int(r_out // 4)), 64)))
        q = max(q, int(math.ceil(max(h, wd) / SCAN_MAX_SIDE)))
        if min(h, wd) // q < 8:
            continue
        rwb, wb = _bin_sum(rw, q), _bin_sum(w, q)
        sb = _bin_sum(src.astype(np.float64), q) / (q * q)
        hb, wbw = rwb.shape
        # the padded grid holds the correlation's lags and the probe's spill beyond the frame without aliasing
        spill = int(np.ceil(r_out / q + 3 * psf_rms / q)) + 2
        shape = (scipy.fft.next_fast_len(2 * hb + 2 * spill, real=True),
                 scipy.fft.next_fast_len(2 * wbw + 2 * spill, real=True))
        fy = np.fft.fftfreq(shape[0])[:, None]
        fx = np.fft.rfftfreq(shape[1])[None, :]
        hk = kernel_transfer("disc", r_out / q, 0.0, fx, fy)
        f_s = scipy.fft.rfft2(sb, s=shape, workers=workers)
        # G = K * S, periodic on the padded grid: the probe's light beyond the frame's edges is kept (it wraps
        # to the far end of the grid, where no lag reads anything else), so a shifted or mirrored G is the
        # probe around the moved sources, as the ghost is
        g = np.maximum(scipy.fft.irfft2(f_s * hk, s=shape, workers=workers), 0)
        f_g = scipy.fft.rfft2(g, workers=workers)
        f_g2 = scipy.fft.rfft2(g * g, workers=workers)
        f_rw = scipy.fft.rfft2(rwb, s=shape, workers=workers)
        f_w = scipy.fft.rfft2(wb, s=shape, workers=workers)
        full = float(np.sum(wb * g[:hb, :wbw] ** 2))
        if full <= 0:
            continue
        rms = max(1.0, math.hypot(r_out / math.sqrt(2), psf_rms) / q)  # coherence radius of z [scan px]
        for mode in ("shift", "mirror"):
            if mode == "shift":
                num = scipy.fft.irfft2(f_rw * np.conj(f_g), s=shape, workers=workers)
                den = scipy.fft.irfft2(f_w * np.conj(f_g2), s=shape, workers=workers)
                ly = np.fft.fftfreq(shape[0], 1.0 / shape[0]).astype(int)[:, None]  # signed lags
                lx = np.fft.fftfreq(shape[1], 1.0 / shape[1]).astype(int)[None, :]
                # a copy must clear its own source: a shift below the probe's and the PSF's reach is a halo
                dmin = (r_out + 3 * psf_rms) + 2
                valid = (np.hypot(ly * q, lx * q) > dmin) & (np.abs(ly) < hb) & (np.abs(lx) < wbw)
            else:
                num = scipy.fft.irfft2(f_rw * f_g, s=shape, workers=workers)
                den = scipy.fft.irfft2(f_w * f_g2, s=shape, workers=workers)
                ly = np.arange(shape[0])[:, None]
                lx = np.arange(shape[1])[None, :]
                valid = (ly <= 2 * (hb - 1)) & (lx <= 2 * (wbw - 1))
            # every geometry whose ghost falls on the frame at all (its template's norm there above the FFT's
            # round-off): the z is normalised by that norm, and the global false alarm counts every one searched
            valid = valid & (den > np.finfo(np.float64).eps * full)
            nv = int(valid.sum())
            if nv < 16:
                continue
            z = np.where(valid, num / np.sqrt(np.maximum(den, 1e-300)), np.nan)
            zv = z[valid]
            med = float(np.median(zv))
            sig = 1.4826 * float(np.median(np.abs(zv - med)))
            if not sig > 0:
                continue
            trials += nv / (np.pi * rms * rms)
            zn = np.where(valid, (z - med) / sig, -np.inf)
            k = int(np.argmax(zn))
            iy, ix = np.unravel_index(k, zn.shape)
            scans.append(dict(mode=mode, z=float(zn[iy, ix]), q=q, probe_px=float(radius),
                              lag_b=(int(ly[iy, 0]), int(lx[0, ix])),
                              alpha=float(num[iy, ix] / den[iy, ix])))
    if not scans:
        return None
    thr = float(scipy.stats.norm.isf(SCAN_GLOBAL_P / max(trials, 1.0)))
    peaks = []
    for mode in ("shift", "mirror"):
        of_mode = [s for s in scans if s["mode"] == mode]
        if not of_mode:
            continue
        p = max(of_mode, key=lambda s: s["z"])
        q = p["q"]
        ly, lx = p["lag_b"]
        if mode == "shift":
            p["lag"] = (ly * q, lx * q)
        else:  # binned u_b -> full u: block centres map as u = q u_b + (q - 1)
            p["lag"] = (ly * q + q - 1, lx * q + q - 1)
        peaks.append(p)
    peaks.sort(key=lambda s: -s["z"])
    best = peaks[0]
    return dict(best, threshold=thr, trials=float(trials), found=bool(best["z"] >= thr), scans=scans, peaks=peaks)


def refine_lag(rw: np.ndarray, w: np.ndarray, g_ext: np.ndarray, pad: int, mode: str, lag: tuple[int, int],
               reach: int) -> tuple[tuple[int, int], float, float]:
    """The integer lag within ``reach`` of ``lag`` that maximises ``num / sqrt(den)`` on the full grid, by
    direct sums over the overlapping slices: (lag, num, den). ``g_ext`` is the probe template ``K * S`` on the
    frame padded by ``pad`` px on every side (the probe's light beyond the edges kept)."""
    h, wd = rw.shape
    he, we = g_ext.shape
    # shift: T(y) = g_ext(y - d + pad); mirror: T(y) = g_ext(u - y + pad) = gf(y - (u + pad + 1 - he)), gf flipped:
    # both are a plain shift s of an array a, T(y) = a(y - s)
    a = g_ext[::-1, ::-1] if mode == "mirror" else g_ext
    seen: dict = {}

    def score(dy, dx):
        if (dy, dx) not in seen:
            sy = dy + pad + 1 - he if mode == "mirror" else dy - pad
            sx = dx + pad + 1 - we if mode == "mirror" else dx - pad
            y0, y1 = max(0, sy), min(h, sy + he)
            x0, x1 = max(0, sx), min(wd, sx + we)
            num = den = 0.0
            if y1 > y0 and x1 > x0:
                t = a[y0 - sy:y1 - sy, x0 - sx:x1 - sx]
                num = float(np.sum(rw[y0:y1, x0:x1] * t))
                den = float(np.sum(w[y0:y1, x0:x1] * t * t))
            seen[(dy, dx)] = (num / np.sqrt(den) if den > 0 else -np.inf, num, den)
        return seen[(dy, dx)]

    # hill-climb on the 3x3 neighbourhood (the matched filter's surface is smooth on the probe's scale)
    cur = tuple(lag)
    for _ in range(4 * reach + 4):
        nbrs = [(cur[0] + i, cur[1] + j) for i in (-1, 0, 1) for j in (-1, 0, 1)
                if abs(cur[0] + i - lag[0]) <= reach and abs(cur[1] + j - lag[1]) <= reach]
        nxt = max(nbrs, key=lambda d: score(*d)[0])
        if nxt == cur:
            break
        cur = nxt
    z, num, den = score(*cur)
    return cur, num, den


# --- the signature ---------------------------------------------------------------------------------------------

#: profile grid of the fit at the found geometry: outer radii [sensor px], annulus obscuration ratios
GHOST_RADII_PX = (3.0, 4.5, 7.0, 10.0, 15.0, 22.0, 33.0, 50.0, 75.0)
GHOST_INNER_RATIOS = (0.3, 0.5, 0.7)
#: a ghost is defocused: its profile's rms radius is at least this many times the sources' own (a sharp copy
#: of the sources, the PSF's own size, is a latent image or an electronic crosstalk)
GHOST_MIN_RMS_PSF = 2.0
#: the map must be confirmed by the bright sources whose ghost the fit predicts detectably (local chi2 gain
#: >= GHOST_SOURCE_CHI2, a part of the detected ghost at FOOTPRINT_SIGMA: 9): this share of them showing it,
#: asked when a real ghost would fail the count with less than FRAME_FALSE_ALARM (:func:`confirmation_miss`)
GHOST_SOURCE_CHI2 = FOOTPRINT_SIGMA ** 2
GHOST_CONFIRMED_SHARE = EXPLAINS_MOST  # most of them
#: about the copy that carries the most of the claim, the fitted ghost must take this share of the residual's
#: excess chi2 there (what remains looks like noise): a trail or a glint that a copy lands on keeps most of
#: its excess outside the ghost's round profile (0.28 for a satellite trail; 0.98 for a real ghost)
GHOST_STAMP_SHARE = EXPLAINS_MOST
#: bright sources the map is checked on
GHOST_CHECK_SOURCES = 40
#: parameters the free form chooses beside alpha: the offset (2), the radius, the profile's form, the family
FREE_EXTRA_K = 5


def _geometry_params(res: Residuals, mode: str, lag: tuple[int, int]) -> dict:
    """The map's parameters [sensor px] from an integer lag on the output grid."""
    b = _step(res)
    yc, xc = _sensor_centre(res)
    if mode == "shift":
        return {"mode": "shift", "shift_dy_px": round(lag[0] * b, 3), "shift_dx_px": round(lag[1] * b, 3),
                "centre_dy_px": 0.0, "centre_dx_px": 0.0}
    # u = 2 c in array indices: c [sensor] = ys[0] + b u / 2
    cy = float(res.ys[0]) + b * lag[0] / 2.0
    cx = float(res.xs[0]) + b * lag[1] / 2.0
    return {"mode": "mirror", "centre_dy_px": round(cy - yc, 3), "centre_dx_px": round(cx - xc, 3),
            "shift_dy_px": 0.0, "shift_dx_px": 0.0}


class _Convolver:
    """Convolutions of one mapped image with many profiles, through its padded spectrum (computed once)."""

    def __init__(self, image: np.ndarray, pad: int, workers: int | None):
        self.shape0 = image.shape
        self.pad = pad
        self.shape = tuple(scipy.fft.next_fast_len(n + 2 * pad, real=True) for n in image.shape)
        big = np.zeros(self.shape, np.float32)  # single precision: the templates are float32 anyway
        big[pad:pad + image.shape[0], pad:pad + image.shape[1]] = image
        self.workers = workers
        self.spec = scipy.fft.rfft2(big, workers=workers)
        self.fy = np.fft.fftfreq(self.shape[0])[:, None]
        self.fx = np.fft.rfftfreq(self.shape[1])[None, :]

    def __call__(self, profile: str, radius_out_px: float, inner_ratio: float) -> np.ndarray:
        h = kernel_transfer(profile, radius_out_px, inner_ratio, self.fx, self.fy).astype(np.float32)
        out = inverse_rfft2(self.spec * h, self.shape, self.workers)
        p = self.pad
        return np.maximum(out[p:p + self.shape0[0], p:p + self.shape0[1]], 0).astype(np.float32)


def _step(res: Residuals) -> float:
    """The output pixel [sensor px]."""
    return float(res.xs[1] - res.xs[0]) if res.xs.size > 1 else float(res.sensor.binning)


def _free_variants(res: Residuals, geometry: dict, stage: str, around: dict | None = None):
    """Variants of the free form at a found geometry: "radius" (discs over GHOST_RADII_PX), then "form"
    (annuli and Gaussians about the best disc's radius ``around``)."""
    step = _step(res)
    if stage == "radius":
        shapes = [("disc", r, 0.0) for r in GHOST_RADII_PX]
    else:
        r0 = around["radius_px"]
        shapes = [("annulus", r0 * f, e) for f in (0.8, 1.0, 1.25, 1.6) for e in GHOST_INNER_RATIOS]
        shapes += [("gauss", r0 * f, 0.0) for f in (0.35, 0.5, 0.7)]
    for profile, radius, inner in shapes:
        if radius / step < 0.5 or radius > 2000:
            continue
        yield _variant(geometry, profile, radius, inner, step)


def _variant(geometry: dict, profile: str, radius: float, inner: float, step: float) -> Variant:
    """The free form's variant of one profile (``radius`` [sensor px]) at one geometry (its template built
    once, when first asked for)."""
    conv = geometry["_conv"]
    cache: dict = {}

    def maps():
        if "t" not in cache:
            cache["t"] = [conv(profile, radius / step, inner)]
        return cache["t"]

    def to_params(c):
        if not 0 < c[0] <= 0.1:
            return None
        p = {"alpha": float(c[0]), "radius_px": round(float(radius), 3), "profile": profile,
             "inner_ratio": float(inner)}
        p.update({k: v for k, v in geometry.items() if not k.startswith("_")})
        return p

    label = f"{geometry['mode']} {profile} {radius:.3g} px" + (f" inner {inner:g}" if inner else "")
    return Variant(maps, to_params, label)


def _ghost_words(p: dict, res) -> str:
    prof = {"disc": f"discs of {p['radius_px']:.3g} px", "gauss": f"Gaussian blobs of {p['radius_px']:.3g} px",
            "annulus": f"rings of {p.get('inner_ratio', 0) * p['radius_px']:.3g}-{p['radius_px']:.3g} px"}
    what = prof.get(p.get("profile", "disc"), prof["disc"])
    mode = p.get("mode", "mirror")
    if mode == "shift":
        where = (f"shifted by ({p['shift_dx_px']:+.4g}, {p['shift_dy_px']:+.4g}) px from every bright source: a "
                 "ghost of a double reflection in a near-parallel plate (filter, window, cover glass)")
    elif p.get("centre_dx_px", 0.0) or p.get("centre_dy_px", 0.0):
        where = (f"opposite the sources through a point ({p['centre_dx_px']:+.4g}, {p['centre_dy_px']:+.4g}) px "
                 "from the sensor centre: ghost reflections about a decentred axis")
    else:
        where = "opposite the sources across the axis: ghost reflections"
    return f"faint {what}, {p['alpha']:.2g} of their flux, {where}"


class GhostSignature(LinearSignature):
    """The plugin's form (through the axis, a disc: ``image_plane._ghost_variants``) and, beside it, the
    free form whose geometry is found by :func:`scan_geometry` (module docstring). The one with the better
    delta BIC (each counting its own parameters) is the fit."""

    def __init__(self):
        super().__init__(_ghost_variants, explain=_ghost_words, extra_k=1,
                         pattern="faint out-of-focus copies of the bright sources: mirrored through a point or "
                                 "shifted by a fixed vector")
        self.free = LinearSignature(lambda res: (), explain=_ghost_words, extra_k=FREE_EXTRA_K)

    def fit(self, res: Residuals, name: str) -> Fit | None:
        axis = super().fit(res, name)
        free = self._fit_free(res, name)
        if free is None:
            return axis
        if axis is None or free.delta_bic < axis.delta_bic:
            return free
        return axis

    def refit(self, fit: Fit, res: Residuals, name: str) -> Fit | None:
        if fit is not None and fit.state.get("free"):
            out = self.free.refit(fit, res, name)
            if out is not None:
                out.state.update({k: v for k, v in fit.state.items() if k != "variant"})
            return out
        return super().refit(fit, res, name)

    def _fit_free(self, res: Residuals, name: str) -> Fit | None:
        """The free form: the scan's best geometry of each map family fitted (profile and alpha); of those,
        the ones whose map the bright sources confirm (:meth:`_sources_check`) first, then by delta BIC."""
        if not _has_structure(res):
            return None
        src = source_image(res)
        if not np.any(src > 0):
            return None
        step = _step(res)
        rw, w = _residual_maps(res)
        psf = psf_rms_px(src)
        # the sources' own cores are not searched: a PSF or flux mismatch there is not a ghost
        core = ndimage.binary_dilation(src * np.sqrt(np.maximum(w, 0)) > CORE_SIGMA, iterations=2)
        rw_s, w_s = np.where(core, 0.0, rw), np.where(core, 0.0, w)
        scan = scan_geometry(rw_s, w_s, src, step, psf_rms=psf, workers=FIT_FFT_WORKERS)
        if scan is None or not scan["found"]:
            return None
        fits = []
        for peak in scan["peaks"]:
            # the other map family too when the scan can hardly tell them apart (one bright source's copy
            # reached by a mirror and by a shift alike), or when the sources refused every map fitted so far
            # (the scan's best family put the top copy right and the others wrong): the sources' check decides
            confirmed = any(not f.state["why_not"] for f in fits)
            if peak["z"] < scan["threshold"] or (confirmed and peak["z"] < SECOND_FAMILY_Z * scan["peaks"][0]["z"]):
                continue
            fit = self._fit_at(res, name, src, rw_s, w_s, peak, step)
            if fit is None:
                continue
            fit.state.update(free=True, psf_rms_px=psf * step, scan={"z": peak["z"], "threshold": scan["threshold"],
                                                                     "trials": scan["trials"]})
            fit.note = (f"{fit.note} (scan z {peak['z']:.3g} > {scan['threshold']:.3g} over {scan['trials']:.3g} "
                        "geometries)")
            fit.state["why_not"] = self._sources_check(fit, res, src, step)
            fits.append(fit)
        if not fits:
            return None
        return min(fits, key=lambda f: (bool(f.state["why_not"]), f.delta_bic))

    def _fit_at(self, res: Residuals, name: str, src: np.ndarray, rw_s: np.ndarray, w_s: np.ndarray, peak: dict,
                step: float) -> Fit | None:
        """Profile and alpha fitted at one scan peak (refined on the full grid when the scan was binned)."""
        mode, lag = peak["mode"], peak["lag"]
        if peak["q"] > 1:
            k = disc_kernel(peak["probe_px"] / step)
            pad = k.shape[0] // 2
            g = signal.oaconvolve(np.pad(src, pad), k, mode="same")
            lag, _, _ = refine_lag(rw_s, w_s, g, pad, mode, lag, peak["q"])
        geometry = _geometry_params(res, mode, lag)
        yc, xc = _sensor_centre(res)
        smap = map_sources(src, res.ys, res.xs, mode, yc + geometry["centre_dy_px"], xc + geometry["centre_dx_px"],
                           geometry["shift_dy_px"], geometry["shift_dx_px"])
        if not np.any(smap > 0):
            return None
        pad = int(np.ceil(max(GHOST_RADII_PX) * 2 / step)) + 2
        geometry["_conv"] = _Convolver(smap, pad, FIT_FFT_WORKERS)
        ctx = search_sample(res)
        best = self._best(res, ctx, _free_variants(res, geometry, "radius"))
        if best is None:
            return None
        best = self._best(res, ctx, [best[0], *_free_variants(res, geometry, "form", best[3])]) or best
        # the geometry again with the fitted profile as the matched filter (the probe was only a disc), and the
        # winning profile refitted there when it moved
        p0 = best[3]
        k = ghost_kernel(p0["profile"], p0["radius_px"] / step, p0["inner_ratio"])
        pad = k.shape[0] // 2
        lag2, _, _ = refine_lag(rw_s, w_s, signal.oaconvolve(np.pad(src, pad), k, mode="same"), pad, mode, lag, 2)
        if tuple(lag2) != tuple(lag):
            geometry2 = _geometry_params(res, mode, lag2)
            smap2 = map_sources(src, res.ys, res.xs, mode, yc + geometry2["centre_dy_px"],
                                xc + geometry2["centre_dx_px"], geometry2["shift_dy_px"], geometry2["shift_dx_px"])
            geometry2["_conv"] = _Convolver(smap2, geometry["_conv"].pad, FIT_FFT_WORKERS)
            again = _variant(geometry2, p0["profile"], p0["radius_px"], p0["inner_ratio"], step)
            moved = self._best(res, ctx, [again])
            if moved is not None and moved[1] < best[1]:
                best = moved
        v, d, c, params = best
        idx, _, wf = res.flat_profiled()
        if not ctx["full"]:
            c_all, d_all = fit_linear(res, lambda i: v.values(i, res.data_adu.shape), idx, res.flat()[1], wf)
            p_all = v.to_params(c_all)
            if p_all is None:
                return None
            c, d, params = c_all, d_all, p_all
        return self.free._finish(res, name, v, c, d, params)

    # -- plausibility --------------------------------------------------------------------------------------------
    def plausible(self, fit: Fit, res: Residuals) -> str:
        p = fit.params
        if not 0 < p.get("alpha", 0) <= 0.1:
            return f"alpha = {p.get('alpha', 0):.3g} is no ghost (a double reflection returns 0 to 10 % of the light)"
        step = _step(res)
        src = source_image(res)
        psf = fit.state.get("psf_rms_px")
        if psf is None:
            psf = psf_rms_px(src) * step
            fit.state["psf_rms_px"] = psf
        rms = kernel_rms_px(p.get("profile", "disc"), p["radius_px"], p.get("inner_ratio", 0.0))
        need = GHOST_MIN_RMS_PSF * psf
        if rms < need:
            return (f"the copies are sharp (profile rms radius {rms:.3g} px < {need:.3g} px, the sources' own "
                    f"{psf:.3g} px): a ghost is defocused by its extra reflection path; a sharp copy of the sources "
                    "is a latent (persistent) image or electronic crosstalk")
        if "why_not" in fit.state:
            return fit.state["why_not"]
        return self._sources_check(fit, res, src, step)

    def _sources_check(self, fit: Fit, res: Residuals, src: np.ndarray, step: float) -> str:
        """Whether the ghost sits where the map puts it for the bright sources, not on one source only.

        Each bright source whose ghost lands on the frame has its own copy ``T_i`` (:func:`_own_copy`: its stamp
        of the source image, mapped and spread over the fitted profile) and its own amplitude ``num_i / den_i``
        with ``num_i = sum w (r - alpha (T - T_i)) T_i`` (the residual with every other copy taken out at the
        fitted fraction: a neighbour's copy that lands on the same blob shows what the blob leaves once the top
        copy has taken it, not the blob) and ``den_i = sum w T_i^2``; ``alpha^2 den_i`` is the chi2 gain the fit
        predicts there. (1) Leave the source with the largest predicted ghost out: the others together (``sum
        num / sum den``) must show the ghost too (:func:`_shows_ghost`: at least 0.3 alpha, or within 2 sigma of
        it); when they predict less than GHOST_SOURCE_CHI2 together, a free map rests on one source (its ghost
        can be put on any blob) and is not a ghost geometry the data can tell; the plugin's fixed map is then
        accepted. (2) About the strongest copy, the ghost takes at least GHOST_STAMP_SHARE of the residual's
        excess chi2 (what is left there looks like noise). (3) Of the sources each predicted detectable on its
        own, at least GHOST_CONFIRMED_SHARE show it (the same :func:`_shows_ghost`)."""
        p = fit.params
        alpha = float(p["alpha"])
        if fit.delta_adu is None or alpha <= 0:
            return ""
        template = np.asarray(fit.delta_adu, np.float64) / alpha
        rw, w = _residual_maps(res)
        yc, xc = _sensor_centre(res)
        mode = p.get("mode", "mirror")
        psf = fit.state.get("psf_rms_px", step)
        extent = p["radius_px"] * (2.5 if p.get("profile", "disc") == "gauss" else 1.0)
        reach = int(np.ceil((extent + 2 * psf) / step)) + 1
        kernel = ghost_kernel(p.get("profile", "disc"), p["radius_px"] / step, p.get("inner_ratio", 0.0))
        kernel = kernel.astype(np.float64)
        half = max(3, int(np.ceil(3 * psf / step)))  # a source's stamp: three rms radii
        h, wd = template.shape
        nums, dens, centres = [], [], []  # centres: each ghost's pixel
        for y, x, _ in bright_sources(src, GHOST_CHECK_SOURCES):
            sy, sx = res.ys[y], res.xs[x]
            if mode == "shift":
                gy, gx = sy + p.get("shift_dy_px", 0.0), sx + p.get("shift_dx_px", 0.0)
            else:
                cy, cx = yc + p.get("centre_dy_px", 0.0), xc + p.get("centre_dx_px", 0.0)
                gy, gx = 2 * cy - sy, 2 * cx - sx
            iy, ix = int(round((gy - res.ys[0]) / step)), int(round((gx - res.xs[0]) / step))
            if not (0 <= iy < h and 0 <= ix < wd):
                continue
            sl, own = _own_copy(src, y, x, iy, ix, half, kernel, mode)
            if own is None:
                continue
            den = float(np.sum(w[sl] * own * own))
            if den > 0:
                others = w[sl] * (template[sl] - own)
                nums.append(float(np.sum((rw[sl] - alpha * others) * own)))
                dens.append(den)
                centres.append((iy, ix))
        free = bool(fit.state.get("free"))
        if not dens:
            return "no bright source's ghost falls on the frame where this map puts it" if free else ""
        nums, dens = np.array(nums), np.array(dens)
        top = int(np.argmax(dens))
        rest_num, rest_den = float(nums.sum() - nums[top]), float(dens.sum() - dens[top])
        fit.state["sources"] = {"n": int(dens.size), "top_chi2": float(alpha ** 2 * dens[top]),
                                "rest_chi2": float(alpha ** 2 * rest_den),
                                "rest_alpha": rest_num / rest_den if rest_den > 0 else None}
        if alpha * alpha * rest_den < GHOST_SOURCE_CHI2:
            if free:
                return (f"its map rests on one source: the other {dens.size - 1} bright sources would show a ghost of "
                        f"chi2 {alpha * alpha * rest_den:.2g} together (< {GHOST_SOURCE_CHI2:g}), so a map that puts "
                        "that source's copy on any blob fits as well")
        else:
            a_rest, s_rest = rest_num / rest_den, 1.0 / np.sqrt(rest_den)
            if not _shows_ghost(a_rest, s_rest, alpha):
                return (f"carried by one source: the other bright sources show {a_rest:.2g} +- {s_rest:.1g} of their "
                        f"flux where the map puts their ghost, not the fitted {alpha:.2g}")
        # the strongest copy's stamp: its excess chi2 (sum w r^2 - n, with rw = w r) and what the ghost (every
        # copy there) takes of it
        iy, ix = centres[top]
        st = (slice(max(0, iy - reach), iy + reach + 1), slice(max(0, ix - reach), ix + reach + 1))
        ws, ts = w[st], template[st]
        excess = float(np.sum(np.where(ws > 0, rw[st] ** 2 / np.where(ws > 0, ws, 1.0), 0.0))) \
            - int(np.count_nonzero(ws))
        taken = 2 * alpha * float(np.sum(rw[st] * ts)) - alpha * alpha * float(np.sum(ws * ts * ts))
        if alpha * alpha * dens[top] >= GHOST_SOURCE_CHI2 and excess > 25 and taken < GHOST_STAMP_SHARE * excess:
            return (f"the structure under the strongest copy is not the ghost's profile: the fitted ghost takes "
                    f"{100 * max(taken, 0.0) / excess:.0f} % of the excess chi2 about it ({excess:.3g}); the rest "
                    "stays (a trail, a glint or a line that a copy of a source lands on)")
        single = alpha * alpha * dens >= GHOST_SOURCE_CHI2
        if single.any() and confirmation_miss(alpha * np.sqrt(dens[single])) < FRAME_FALSE_ALARM:
            ok = _shows_ghost(nums[single] / dens[single], 1.0 / np.sqrt(dens[single]), alpha)
            if ok.sum() < GHOST_CONFIRMED_SHARE * single.sum():
                return (f"only {int(ok.sum())} of the {int(single.sum())} bright sources whose ghost the fit predicts "
                        "show one where the map puts it: the pattern is not a ghost of the sources")
        return ""


def _own_copy(src: np.ndarray, y: int, x: int, iy: int, ix: int, half: int, kernel: np.ndarray, mode: str
              ) -> tuple[tuple[slice, slice], np.ndarray | None]:
    """(slice of the frame, values) of one source's ghost copy [per unit fraction]: the source image's stamp of
    ``half`` px about the source (``y``, ``x``; 0 beyond the frame), point-reflected for a mirror map, spread over
    the profile ``kernel`` (odd-sized, as :func:`ghost_kernel` makes it) and centred on its ghost's pixel (``iy``,
    ``ix``); clipped to the frame (None when nothing of it is left). Whole-pixel placement: the copy's sub-pixel
    position does not change what it measures."""
    stamp = extract_array(src, (2 * half + 1, 2 * half + 1), (y, x), mode="partial", fill_value=0.0)
    if mode != "shift":
        stamp = stamp[::-1, ::-1]
    copy = signal.oaconvolve(stamp, kernel, mode="full")
    try:
        frame, inside = overlap_slices(src.shape, copy.shape, (iy, ix), mode="partial")
    except NoOverlapError:
        return (slice(0, 0), slice(0, 0)), None
    return frame, copy[inside]


def _shows_ghost(a, s, alpha: float):
    """Whether sources whose own ghost amplitude is ``a`` (standard error ``s``) show the fitted ``alpha``: at least
    0.3 of it, or within 2 standard errors of it. Not both: the fraction is the product of two reflectances, which
    change across the band (an anti-reflection coating's by a factor of a few), so sources of other colours show
    the same ghost at a somewhat different fraction, which a bright source measures to better than 2 standard
    errors; a ghost carried by one source leaves the others near 0."""
    a, s = np.asarray(a, np.float64), np.asarray(s, np.float64)
    return (a >= 0.3 * alpha) | (a >= alpha - 2.0 * s)


def confirmation_miss(snr: np.ndarray) -> float:
    """The probability that a real ghost fails the confirmation count: its sources, each showing the fitted
    ghost with S/N ``snr`` (alpha / its standard error), miss it (their own amplitude below 0.3 alpha and more
    than 2 standard errors short of alpha) each with ``Phi(-max(2, 0.7 snr))``, independently; the count fails
    when fewer than GHOST_CONFIRMED_SHARE of them show it. The number of misses is Poisson-binomial (a sum of
    independent Bernoulli trials, computed exactly by convolution)."""
    p = scipy.stats.norm.sf(np.maximum(2.0, 0.7 * np.asarray(snr, np.float64)))
    dist = np.ones(1)
    for pi in p:  # the distribution of the number of misses
        dist = np.convolve(dist, [1.0 - pi, pi])
    n = len(p)
    misses = np.arange(n + 1)
    return float(dist[(n - misses) < GHOST_CONFIRMED_SHARE * n].sum())


# --- adapter ----------------------------------------------------------------------------------------------------

class GhostParams(EffectParams):
    alpha: float = Field(1e-3, ge=0, le=0.1, description="ghost energy / source energy [1]")
    radius_px: float = Field(10.0, gt=0, le=2000, description="radius of the defocused ghost disc (outer radius of "
                             "an annulus, sigma of a Gaussian) [sensor px]", json_schema_extra={"unit": "pixel"})
    mode: Literal["mirror", "shift"] = Field(
        "mirror", description="the ghost's map: 'mirror' (x' = c - (x - c), through the point c: the optical axis "
        "moved by centre_d*_px) or 'shift' (x' = x + d: a near-parallel plate)")
    centre_dx_px: float = Field(0.0, ge=-1e4, le=1e4, description="mirror centre's offset from the sensor centre "
                                "along the columns [sensor px]", json_schema_extra={"unit": "pixel"})
    centre_dy_px: float = Field(0.0, ge=-1e4, le=1e4, description="mirror centre's offset from the sensor centre "
                                "along the rows [sensor px]", json_schema_extra={"unit": "pixel"})
    shift_dx_px: float = Field(0.0, ge=-1e4, le=1e4, description="shift of the ghost from its source along the "
                               "columns, mode 'shift' [sensor px]", json_schema_extra={"unit": "pixel"})
    shift_dy_px: float = Field(0.0, ge=-1e4, le=1e4, description="shift of the ghost from its source along the "
                               "rows, mode 'shift' [sensor px]", json_schema_extra={"unit": "pixel"})
    profile: Literal["disc", "annulus", "gauss"] = Field(
        "disc", description="the defocused pupil's profile: a uniform disc, an annulus (central obscuration) or "
        "a Gaussian")
    inner_ratio: float = Field(0.0, ge=0, le=0.95, description="inner / outer radius of an annulus (the linear "
                               "obscuration ratio of the pupil) [1]", json_schema_extra={"unit": "1"})


@register_effect
class Ghost(Effect):
    """A defocused ghost of every source (a double reflection between two surfaces): ``alpha`` of the flux,
    mirrored through the optical axis (or a point off it) or shifted by a fixed vector, spread over a disc,
    an annulus or a Gaussian of ``radius_px``, added to the image (module docstring)."""

    name = "ghost"
    scaling = "signal"
    identity = {"alpha": 0.0}
    stages = (Stage.FIELD,)
    Params = GhostParams
    signature = GhostSignature()

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        p = self.params
        ys, xs, yc, xc = _photo_sensor_coords(tile)
        if (p.mode == "mirror" and p.centre_dx_px == 0 and p.centre_dy_px == 0 and p.profile == "disc"):
            g = ghost_image(data, ys, xs, yc, xc, p.radius_px)  # the plugin's original form, byte for byte
        else:
            g = ghost_general(data, ys, xs, yc, xc, p.mode, p.centre_dy_px, p.centre_dx_px, p.shift_dy_px,
                              p.shift_dx_px, p.profile, p.radius_px, p.inner_ratio)
        _store(data, data + np.float32(p.alpha) * g)
