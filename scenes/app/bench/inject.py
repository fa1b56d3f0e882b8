"""Synthetic streaks and points injected into a measured frame (``newtsim inject``; docs/detection_bench.md).

How survey pipelines measure their completeness (the fake-source injection of e.g. Bosch et al. 2018, PASJ
70, S5, section 4.6; Trailblazer-style streak archives): draw a source of known position and flux into the
measured pixels through the frame's own WCS, PSF, gain and noise, and leave every other pixel alone.

The model, per injected object j with path p_j(t) on the detector (t in [0, T], T the exposure time) and
flux F_j [e-] over the exposure at its mean brightness:

    E_ij = F_j sum_k  w_k f_j(t_k) PSF(i - p_j(t_k)),      w_k = 1 / K (K samples, <= 0.25 px or sigma / 2 apart)

with f_j the light curve's interval mean over sample k (:class:`scenes.objects.lightcurve.LightCurve`, mean 1
over a period, so F_j is the mean-brightness flux) and PSF the pixel-integrated circular Gaussian of the
frame's FWHM (measured on its stars with photutils' ``fit_fwhm``, or given), truncated at 3 FWHM from the
path and renormalised to 1 there (the footprint keeps all the flux). A Bayer frame's PSF is multiplied by the
colour-filter weights of the frame's own stars (the relative response of the four CFA pixels to a typical
star, whose mean over a 2 x 2 cell is 1): the object is drawn with the colour of the frame's median star.

The frame receives the injected light's own shot noise, not its mean: with N_i ~ Poisson(sum_j E_ij) and g
the gain [e-/ADU],

    out_i = Q( in_i + N_i / g )  clipped to the saturation level,

Q the frame's data type (integers: rounded to the nearest count, a quantisation variance of 1/12 ADU^2 per
pixel at most; floats: the frame's precision). Pixels already at or above the saturation level and NaN pixels
are left as they are. Every pixel outside the footprints (sum_j E_ij = 0 there) is the input's, bit for bit,
and every other HDU of the file is left untouched.

Labels: per object the endpoints (the whole path and its visible part), the flux (total and on the frame), and
the matched-filter SNR against the frame's own noise, sigma_i^2 = (g rms_i)^2 + E_i with rms_i the frame's
background rms (photutils ``Background2D``, per CFA plane on a Bayer frame):

    SNR = sqrt( sum_i E_i^2 / sigma_i^2 ),    peak SNR = max_i E_i / sigma_i.

An object partly off the frame is clipped, never dropped silently: its label holds the whole path, the visible
part and the visible flux.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import tomllib
from astropy.io import fits
from astropy.wcs import WCS, FITSFixedWarning
from scipy.optimize import brentq
from scipy.special import erf

from detector.errors import DetectorError
from scenes.objects.frames import east_north, radec_to_unit, unit_to_radec
from scenes.objects.lightcurve import LightCurve, light_curve_from_table

__all__ = ["BAYER_PATTERNS", "Frame", "InjectError", "Injected", "Obj", "Result", "background", "cfa_weights",
           "expected_stamp", "inject", "inject_file", "injected_hdu", "linear_path", "measure_psf", "objects_from_toml",
           "random_objects", "read_frame", "snr_of", "source_stamps", "unlit_edges"]

BAYER_PATTERNS = ("RGGB", "GRBG", "GBRG", "BGGR")
#: header gains outside this range are not e-/ADU (a camera's gain *setting*, e.g. the Seestar's GAIN = 80)
PLAUSIBLE_GAIN = (0.05, 30.0)
#: the PSF footprint reaches this many FWHM from the path (a Gaussian at 3 FWHM is 7 sigma: 1e-11 of its peak)
FOOTPRINT_FWHM = 3.0
UNLIT_SIGMA = 10.0  # an edge block this many pixel-noise sigma below the frame's level is not lit (overscan)
STEP_PX = 0.25  # longest step between two samples of a path [px]
MIN_STARS = 5  # stars needed to measure the PSF
#: narrower fits are not stars: a point source lit within one pixel fits a Gaussian of FWHM 0.6-0.95 px (hot
#: pixels, cosmic rays: the SBIG darks of ../shared/realdata), a sampled star's profile is wider
MIN_FWHM_PX = 1.0
STAR_SIGMA = 10.0  # a star for the PSF peaks at this many background sigma at least
FWHM_TO_SIGMA = 1.0 / (2.0 * math.sqrt(2.0 * math.log(2.0)))
EXPTIME_KEYS = ("EXPTIME", "EXPOSURE", "EXP_TIME", "ITIME")
SATURATION_KEYS = ("SATURATE", "SATURATA", "SATURATB", "SATLEVEL", "DATAMAX")


class InjectError(DetectorError):
    """A frame or an option that cannot be used for an injection (one line, exit status 2)."""

    exit_status = 2


# ----------------------------------------------------------------------------------------------------- frame
@dataclass
class Frame:
    """The image HDU of a measured frame and what an injection needs from it (each value with its source)."""

    path: str
    hdu: int
    data: np.ndarray  # the HDU's physical values (BZERO/BSCALE applied) as float64
    dtype: np.dtype  # the values' type as astropy hands it (uint16 for BITPIX 16 + BZERO 32768, >i2, >f4...)
    header: fits.Header
    wcs: WCS | None
    bayer: str | None
    exptime_s: float
    gain_e_per_adu: float
    saturation_adu: float
    pixel_scale_arcsec: float | None
    sources: dict = field(default_factory=dict)  # value -> "header KEY" | "given" | "measured" | "assumed" | "type"
    warnings: list = field(default_factory=list)
    raw: np.ndarray | None = None  # the HDU's values as astropy hands them (the bits kept outside the footprints)

    @property
    def name(self) -> str:
        return f"{self.path}[{self.hdu}]"

    @property
    def shape(self) -> tuple[int, int]:
        return self.data.shape


def _image_hdus(hdul) -> list[int]:
    return [i for i, h in enumerate(hdul) if h.is_image and h.header.get("NAXIS", 0) == 2
            and h.header.get("NAXIS1", 0) > 0 and h.header.get("NAXIS2", 0) > 0]


def _wcs_of(header, hdul) -> WCS | None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FITSFixedWarning)
        try:
            w = WCS(header, fobj=hdul)
        except Exception:  # noqa: BLE001  (astropy raises many types for a malformed WCS: it is no WCS, and the error below says what to give)
            return None
    return w.celestial if w.has_celestial else None


def _bayer_of(header) -> str | None:
    for key in ("BAYERPAT", "COLORTYP", "CFA-PAT", "CFAPAT", "FILTER"):
        v = str(header.get(key, "")).strip().upper()
        if v in BAYER_PATTERNS:
            x_off, y_off = int(header.get("XBAYROFF", 0)) % 2, int(header.get("YBAYROFF", 0)) % 2
            if x_off:
                v = v[1] + v[0] + v[3] + v[2]
            if y_off:
                v = v[2:] + v[:2]
            return v
    return None


def read_frame(path, hdu=None, *, gain=None, saturation=None, exptime=None, pixel_scale=None,
               bayer=None) -> tuple[fits.HDUList, Frame]:
    """Open ``path`` and describe its image HDU (``hdu``: index or EXTNAME; default: the first 2-D image
    with a celestial WCS, else the first 2-D image). The HDU list stays open for :func:`inject`."""
    try:
        hdul = fits.open(path)
    except (OSError, ValueError) as exc:
        raise InjectError(f"cannot read it as FITS ({exc})", file=str(path)) from None
    images = _image_hdus(hdul)
    if not images:
        hdul.close()
        raise InjectError("no 2-D image HDU", file=str(path), expected="a FITS frame with a 2-D image")
    if hdu is None:
        with_wcs = [i for i in images if _wcs_of(hdul[i].header, hdul) is not None]
        index = (with_wcs or images)[0]
    else:
        try:
            index = int(hdu)
        except (TypeError, ValueError):
            names = [str(h.name).upper() for h in hdul]
            if str(hdu).upper() not in names:
                hdul.close()
                raise InjectError(f"no HDU named {hdu!r}", file=str(path), key="--hdu",
                                  expected="one of " + ", ".join(names[i] for i in images)) from None
            index = names.index(str(hdu).upper())
        if index not in images:
            hdul.close()
            raise InjectError(f"HDU {hdu} holds no 2-D image", file=str(path), key="--hdu",
                              expected="one of " + ", ".join(map(str, images)))
    h = hdul[index]
    header = h.header
    raw = h.data
    data = np.asarray(raw, dtype=np.float64)
    sources, notes = {}, []

    w = _wcs_of(header, hdul)
    if pixel_scale is not None:
        scale, sources["pixel_scale"] = float(pixel_scale), "given"
    elif w is not None:
        scale = float(np.sqrt(abs(np.linalg.det(w.pixel_scale_matrix))) * 3600.0)
        sources["pixel_scale"] = "WCS"
    else:
        scale = None

    if gain is not None:
        g, sources["gain"] = float(gain), "given"
    else:
        g = None
        for key in ("EGAIN", "GAIN", "CCDGAIN"):
            v = header.get(key, hdul[0].header.get(key))
            if isinstance(v, (int, float)) and PLAUSIBLE_GAIN[0] <= float(v) <= PLAUSIBLE_GAIN[1]:
                g, sources["gain"] = float(v), f"header {key}"
                break
            if isinstance(v, (int, float)):
                notes.append(f"header {key} = {v} is not a gain in e-/ADU ({PLAUSIBLE_GAIN[0]}..{PLAUSIBLE_GAIN[1]})")
        if g is None and all(isinstance(header.get(k), (int, float)) for k in ("GAINA", "GAINB")):
            g = 0.5 * (float(header["GAINA"]) + float(header["GAINB"]))
            sources["gain"] = "header GAINA/GAINB (mean of the two amplifiers)"
        if g is None:
            g, sources["gain"] = 1.0, "assumed"
            notes.append(f"{path}[{index}]: no gain in the header; 1 e-/ADU assumed (give --gain)")

    if exptime is not None:
        t, sources["exptime"] = float(exptime), "given"
    else:
        t = None
        for key in EXPTIME_KEYS:
            v = header.get(key, hdul[0].header.get(key))
            if isinstance(v, (int, float)) and v > 0:
                t, sources["exptime"] = float(v), f"header {key}"
                break
        if t is None:
            t, sources["exptime"] = 1.0, "assumed"
            notes.append(f"{path}[{index}]: no exposure time in the header; 1 s assumed (give --exptime)")

    dtype = np.dtype(raw.dtype)
    type_max = float(np.iinfo(dtype).max) if dtype.kind in "iu" else math.inf
    if saturation is not None:
        sat, sources["saturation"] = float(saturation), "given"
    else:
        vals = {k: header[k] for k in SATURATION_KEYS if isinstance(header.get(k), (int, float))}
        if vals:
            key = min(vals, key=vals.get)
            sat, sources["saturation"] = min(float(vals[key]), type_max), f"header {key}"
        else:
            sat = type_max
            sources["saturation"] = "data type" if math.isfinite(sat) else "none (floating-point frame)"

    if bayer is None:
        pattern = _bayer_of(header)
        sources["bayer"] = "header" if pattern else "none"
    else:
        pattern = None if str(bayer).lower() == "none" else str(bayer).upper()
        if pattern is not None and pattern not in BAYER_PATTERNS:
            hdul.close()
            raise InjectError(f"{bayer!r}", key="--bayer", expected="RGGB, GRBG, GBRG, BGGR or none")
        sources["bayer"] = "given"
    frame = Frame(str(path), index, data, dtype, header, w, pattern, t, g, sat, scale, sources, notes, raw)
    return hdul, frame


# ------------------------------------------------------------------------------------------------ background
def _box(shape) -> int:
    return int(np.clip(min(shape) // 4, 8, 64))


def unlit_edges(data: np.ndarray) -> np.ndarray:
    """Pixels that cannot receive light: blocks of columns (rows) at the frame's edges whose median lies more
    than UNLIT_SIGMA pixel-noise sigma below the rest of the frame's median (a raw frame's prescan and
    overscan at the bias level: the HSC and DECam cutouts of ../shared/realdata), at most a quarter of the
    frame per side. The pixel noise is the robust sigma of the differences of neighbouring pixels / sqrt 2 (a
    gradient or stars do not inflate it). A frame with no light at all (a bias) has no such block."""
    out = np.zeros(data.shape, dtype=bool)
    finite = np.isfinite(data)
    if finite.sum() < 16:
        return out
    d = np.diff(np.where(finite, data, np.nanmedian(data)), axis=1)
    noise = 1.4826 * float(np.median(np.abs(d - np.median(d)))) / math.sqrt(2.0)
    if not noise > 0:
        return out
    for axis in (0, 1):  # axis 0: column medians (blocks of columns), 1: row medians
        med = np.nanmedian(np.where(finite, data, np.nan), axis=axis)
        n = med.size
        level = float(np.nanmedian(med))
        dark = med < level - UNLIT_SIGMA * noise
        for side in (np.arange(n), np.arange(n)[::-1]):
            k = 0
            while k < n // 4 and dark[side[k]]:
                k += 1
            if k:
                idx = side[:k]
                if axis == 0:
                    out[:, idx] = True
                else:
                    out[idx, :] = True
    return out


def _background2d(data, bad, **kw):
    from photutils.background import Background2D

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            return Background2D(data, _box(data.shape), mask=bad, filter_size=(3, 3), **kw)
        except ValueError:  # too much masked for the boxes: boxes with up to 90 % of their pixels masked
            return Background2D(data, _box(data.shape), mask=bad, filter_size=(3, 3), exclude_percentile=90.0,
                                **kw)


def _background_plane(data: np.ndarray, mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Background2D's background, and the pixel noise: Background2D's robust (MAD) rms of the differences of
    neighbouring pixels over sqrt 2. A gradient, a broad trail or a read-out ramp inside a box is structure,
    not noise: on the DECam cutout of ../shared/realdata the box rms of data - background is 140-250 ADU,
    the pixel noise 27-31 ADU (sky 8200 e- at 4 e-/ADU: 23 ADU of shot noise). Neighbour-correlated noise
    (a resampled frame) would be underestimated by this estimator."""
    from photutils.background import MADStdBackgroundRMS

    bad = ~np.isfinite(data) if mask is None else (~np.isfinite(data) | mask)
    clean = np.where(np.isfinite(data), data, 0.0)
    b = np.asarray(_background2d(clean, bad).background, dtype=np.float64)
    diff = np.empty_like(clean)
    diff[:, :-1] = (clean[:, 1:] - clean[:, :-1]) / math.sqrt(2.0)
    diff[:, -1] = diff[:, -2] if clean.shape[1] > 1 else 0.0
    dbad = bad.copy()
    dbad[:, :-1] |= bad[:, 1:]
    rms = np.asarray(_background2d(diff, dbad, bkg_rms_estimator=MADStdBackgroundRMS()).background_rms,
                     dtype=np.float64)
    return b, rms


def background(data: np.ndarray, bayer: str | None = None, mask: np.ndarray | None = None):
    """The frame's background and background rms [ADU] per pixel (photutils ``Background2D``, sigma-clipped
    boxes of a quarter of the frame's side, 8 to 64 px; the rms the pixel noise of :func:`_background_plane`),
    the unlit edges (:func:`unlit_edges`) and ``mask``
    left out; a Bayer frame per CFA plane (the four colours have their own levels and noise)."""
    m = unlit_edges(data) if mask is None else (unlit_edges(data) | mask)
    if bayer is None:
        return _background_plane(data, m)
    bkg, rms = np.empty_like(data), np.empty_like(data)
    for dy in (0, 1):
        for dx in (0, 1):
            b, r = _background_plane(data[dy::2, dx::2], m[dy::2, dx::2])
            bkg[dy::2, dx::2], rms[dy::2, dx::2] = b, r
    return bkg, rms


# ------------------------------------------------------------------------------------------------------- PSF
def _bin2(a: np.ndarray) -> np.ndarray:
    h, w = (a.shape[0] // 2) * 2, (a.shape[1] // 2) * 2
    a = a[:h, :w]
    return a[0::2, 0::2] + a[0::2, 1::2] + a[1::2, 0::2] + a[1::2, 1::2]


def _stars(img: np.ndarray, sig: np.ndarray, peak_ok: np.ndarray, fwhm_guess: float):
    """Isolated stars of a background-subtracted image: (x, y) of peaks above STAR_SIGMA sigma, away from the
    edges and from each other, below half the saturation level."""
    from photutils.detection import find_peaks

    border = int(max(6, math.ceil(3 * fwhm_guess)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        tab = find_peaks(np.nan_to_num(img / sig), STAR_SIGMA, box_size=5, border_width=border)
    if tab is None or len(tab) == 0:
        return np.zeros((0, 2))
    xy = np.column_stack([np.asarray(tab["x_peak"]), np.asarray(tab["y_peak"])]).astype(float)
    keep = peak_ok[xy[:, 1].astype(int), xy[:, 0].astype(int)]
    # hot pixels and cosmic rays: a star lights its four neighbours too
    iy, ix = xy[:, 1].astype(int), xy[:, 0].astype(int)
    neigh = np.min([img[iy + dy, ix + dx] / sig[iy, ix] for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0))], axis=0)
    keep &= neigh > 0.2 * STAR_SIGMA
    xy = xy[keep]
    if len(xy) > 1:
        d = np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1])
        np.fill_diagonal(d, np.inf)
        xy = xy[d.min(axis=1) > 4 * fwhm_guess + 4]
    return xy[:200]


def measure_psf(frame: Frame, bkg: np.ndarray, rms: np.ndarray) -> tuple[float, int]:
    """The frame's FWHM [px] from its own stars: a circular Gaussian fitted to each isolated unsaturated star
    (photutils ``fit_fwhm``), the median over the stars; a Bayer frame is measured on its 2 x 2 sums (one
    colour cell a pixel) and the FWHM doubled. Returns (FWHM [px], number of stars); raises
    :class:`InjectError` when fewer than MIN_STARS stars are found."""
    from photutils.psf import fit_fwhm

    img = frame.data - bkg
    ok = np.isfinite(img) & (frame.data < 0.5 * frame.saturation_adu)
    sig = rms.copy()
    factor = 1.0
    if frame.bayer is not None:
        img, sig, factor = _bin2(np.nan_to_num(img)), np.sqrt(_bin2(rms ** 2)), 2.0
        ok = _bin2(ok.astype(float)) == 4
    fwhm, n = 3.0, 0
    for _ in range(2):
        xy = _stars(img, sig, ok, fwhm)
        n = len(xy)
        if n < MIN_STARS:
            break
        half = int(np.clip(math.ceil(1.5 * fwhm), 2, 12))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                f = np.asarray(fit_fwhm(np.nan_to_num(img), xypos=xy, fit_shape=2 * half + 1), dtype=float)
            except Exception:  # noqa: BLE001  (a fit photutils cannot do is a star not measured)
                f = np.zeros(0)
        f = f[np.isfinite(f) & (f * factor > MIN_FWHM_PX) & (f < 40.0)]
        n = len(f)
        if n < MIN_STARS:
            break
        fwhm = float(np.median(f))
    if n < MIN_STARS:
        raise InjectError(f"no stars to measure the PSF from: {n} isolated unsaturated stars above "
                          f"{STAR_SIGMA:g} sigma (need {MIN_STARS})", file=frame.name,
                          expected="a frame with stars, or --psf FWHM_ARCSEC (or --psf 3.2px)")
    return fwhm * factor, n


def cfa_weights(frame: Frame, bkg: np.ndarray, fwhm_px: float) -> tuple[np.ndarray, str]:
    """The relative response of the four CFA pixels [(0,0), (0,1), (1,0), (1,1)] to the frame's stars (the
    median over stars of each parity's share of the star's light, times 4: mean 1 over a cell), and how it
    was found. Equal weights when the frame has no usable stars."""
    img = frame.data - bkg
    b = _bin2(np.nan_to_num(img))
    mad = float(np.median(np.abs(b - np.median(b)))) * 1.4826
    ok = _bin2((np.isfinite(frame.data) & (frame.data < 0.5 * frame.saturation_adu)).astype(float)) == 4
    xy = _stars(b, np.full_like(b, max(mad, 1e-12)), ok, fwhm_px / 2.0)
    r = int(max(2, math.ceil(fwhm_px)))
    shares = []
    for xb, yb in xy:
        x, y = int(2 * xb), int(2 * yb)
        cut = img[max(0, y - 2 * r):y + 2 * r + 2, max(0, x - 2 * r):x + 2 * r + 2]
        y0, x0 = max(0, y - 2 * r), max(0, x - 2 * r)
        s = np.array([np.nansum(cut[(dy - y0) % 2::2, (dx - x0) % 2::2]) for dy in (0, 1) for dx in (0, 1)])
        if s.sum() > 0 and np.all(s > 0):
            shares.append(s / s.sum())
    if len(shares) < MIN_STARS:
        return np.ones(4), "equal (no stars to measure the colour from)"
    return 4.0 * np.median(np.array(shares), axis=0) / np.median(np.array(shares), axis=0).sum(), \
        f"median colour of {len(shares)} stars"


# --------------------------------------------------------------------------------------------------- objects
@dataclass
class Obj:
    """One object to inject: its path on the detector (0-based pixels, pixel centres at integers) as a
    function of time, its brightness (``flux_e`` over the exposure at mean brightness, or a target ``snr``)
    and an optional light curve."""

    name: str
    kind: str  # "streak" or "point"
    path: object  # callable t_s (array) -> (x, y) arrays
    flux_e: float | None = None
    snr: float | None = None
    light_curve: LightCurve | None = None
    ends_sky: tuple | None = None  # ((ra0, dec0), (ra1, dec1)) [deg] when given on the sky


def linear_path(x0, y0, x1, y1, t_s):
    """A path from (x0, y0) at t = 0 to (x1, y1) at t = t_s, at constant speed [px]."""
    def path(t):
        u = np.asarray(t, dtype=float) / t_s
        return x0 + (x1 - x0) * u, y0 + (y1 - y0) * u
    return path


def _sky_path(wcs: WCS, ra_deg, dec_deg, rate_ra_deg_s, rate_dec_deg_s):
    """The great-circle path of an object at (ra, dec) moving at the on-sky rates (rate_ra = dRA/dt cos Dec, as
    in ``scenes.objects``), through the frame's WCS (SIP/TPV distortion included: astropy's all_world2pix)."""
    u0 = radec_to_unit(ra_deg, dec_deg)
    east, north = east_north(u0)
    v = math.radians(rate_ra_deg_s) * east + math.radians(rate_dec_deg_s) * north
    omega = float(np.linalg.norm(v))
    d = v / omega if omega > 0 else np.zeros(3)

    def sky(t):
        t = np.atleast_1d(np.asarray(t, dtype=float))
        u = np.cos(omega * t)[:, None] * u0 + np.sin(omega * t)[:, None] * d
        return unit_to_radec(u)

    def path(t):
        ra, dec = sky(t)  # [deg]
        x, y = wcs.all_world2pix(ra, dec, 0)
        return np.asarray(x, dtype=float), np.asarray(y, dtype=float)

    return path, omega


def objects_from_toml(path, frame: Frame) -> list[Obj]:
    """The ``[[objects]]`` of an objects file (docs/detection_bench.md): pixel endpoints ``x0, y0, x1, y1``
    (a streak) or ``x, y`` (a point), or ``ra_deg, dec_deg`` with optional ``rate_ra_deg_s, rate_dec_deg_s``;
    ``flux_e`` or ``snr``; optional ``name`` and ``light_curve`` (as in a scene)."""
    try:
        doc = tomllib.loads(Path(path).read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise InjectError(f"cannot read it ({exc})", file=str(path)) from None
    rows = doc.get("objects")
    if not isinstance(rows, list) or not rows:
        raise InjectError("no [[objects]] tables", file=str(path), key="objects",
                          expected="one or more [[objects]] with x0, y0, x1, y1 (or ra_deg, dec_deg) and flux_e or snr")
    allowed = {"name", "x0", "y0", "x1", "y1", "x", "y", "ra_deg", "dec_deg", "rate_ra_deg_s", "rate_dec_deg_s",
               "flux_e", "snr", "light_curve"}
    out = []
    T = frame.exptime_s
    for i, r in enumerate(rows):
        key = f"objects[{i}]"
        extra = sorted(set(r) - allowed)
        if extra:
            raise InjectError(f"unknown key {extra[0]!r}", file=str(path), key=f"{key}.{extra[0]}",
                              expected="one of " + ", ".join(sorted(allowed)))

        def num(name, lo=-math.inf, hi=math.inf, key=key, r=r):
            v = r.get(name)
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not lo <= v <= hi:
                raise InjectError(f"{v!r}", file=str(path), key=f"{key}.{name}",
                                  expected=f"a number in [{lo:g}, {hi:g}]")
            return float(v)

        ends_sky = None
        if all(k in r for k in ("x0", "y0", "x1", "y1")):
            kind, p = "streak", linear_path(num("x0"), num("y0"), num("x1"), num("y1"), T)
        elif "x" in r and "y" in r:
            kind, p = "point", linear_path(num("x"), num("y"), num("x"), num("y"), T)
        elif "ra_deg" in r and "dec_deg" in r:
            if frame.wcs is None:
                raise InjectError("an object given on the sky needs the frame's WCS, and it has none",
                                  file=frame.name, key=f"{key}.ra_deg",
                                  expected="pixel positions x0, y0, x1, y1 (or x, y), or a frame with a WCS")
            ra, dec = num("ra_deg", 0, 360), num("dec_deg", -90, 90)
            rra = num("rate_ra_deg_s") if "rate_ra_deg_s" in r else 0.0
            rdec = num("rate_dec_deg_s") if "rate_dec_deg_s" in r else 0.0
            p, omega = _sky_path(frame.wcs, ra, dec, rra, rdec)
            kind = "streak" if omega > 0 else "point"
            ends_sky = ((ra, dec), None)
        else:
            raise InjectError("no position", file=str(path), key=key,
                              expected="x0, y0, x1, y1 (a streak), x, y (a point) or ra_deg, dec_deg")
        if ("flux_e" in r) == ("snr" in r):
            raise InjectError("give one of flux_e and snr", file=str(path), key=key,
                              expected="flux_e [e-] or snr (matched-filter SNR against the frame's noise)")
        flux = num("flux_e", 0.0) if "flux_e" in r else None
        snr = num("snr", 0.0) if "snr" in r else None
        lc = light_curve_from_table(r.get("light_curve"), f"{key}.light_curve", file=str(path))
        out.append(Obj(str(r.get("name", f"inj{i}")), kind, p, flux, snr, lc, ends_sky))
    return out


def random_objects(n: int, snr_range, rate_range_arcsec_s, frame: Frame, rng: np.random.Generator) -> list[Obj]:
    """``n`` objects with a matched-filter SNR uniform in ``snr_range`` and an angular rate uniform in
    ``rate_range_arcsec_s`` (0: a point); centres uniform on the frame, directions uniform in angle. A streak
    longer than the frame crosses it (clipped, labelled as such)."""
    if frame.pixel_scale_arcsec is None and max(rate_range_arcsec_s) > 0:
        raise InjectError("no WCS: the rates in arcsec/s need the pixel scale", file=frame.name, key="--rate",
                          expected="a frame with a WCS, or --pixel-scale ARCSEC")
    h, w = frame.shape
    out = []
    for i in range(n):
        snr = float(rng.uniform(*snr_range))
        rate = float(rng.uniform(*rate_range_arcsec_s))
        xc, yc = rng.uniform(-0.5, w - 0.5), rng.uniform(-0.5, h - 0.5)
        theta = rng.uniform(0.0, math.pi)
        length = rate * frame.exptime_s / frame.pixel_scale_arcsec if rate > 0 else 0.0
        dx, dy = 0.5 * length * math.cos(theta), 0.5 * length * math.sin(theta)
        kind = "streak" if length > 0 else "point"
        out.append(Obj(f"inj{i}", kind, linear_path(xc - dx, yc - dy, xc + dx, yc + dy, frame.exptime_s), None, snr))
    return out


# ----------------------------------------------------------------------------------------------- the drawing
def _samples(obj: Obj, t_s: float, sigma_px: float):
    """(x, y, weight) of the path's samples: K equal time slices of [0, T], each at its mid time, weighted by
    1/K times the light curve's mean over the slice (sum of weights = the mean of f over the exposure)."""
    xa, ya = obj.path(np.array([0.0, t_s]))
    mid = obj.path(np.array([0.5 * t_s]))
    length = math.hypot(mid[0][0] - xa[0], mid[1][0] - ya[0]) + math.hypot(xa[1] - mid[0][0], ya[1] - mid[1][0])
    k = max(1, math.ceil(length / min(STEP_PX, 0.5 * sigma_px)))
    if obj.light_curve is not None:
        k = max(k, math.ceil(t_s / obj.light_curve.max_step_s()))
    edges = np.linspace(0.0, t_s, k + 1)
    x, y = obj.path(0.5 * (edges[:-1] + edges[1:]))
    wgt = np.full(k, 1.0 / k)
    if obj.light_curve is not None:
        wgt = wgt * obj.light_curve.interval_mean(edges[:-1], edges[1:])
    return np.asarray(x, float), np.asarray(y, float), wgt


def expected_stamp(x: np.ndarray, y: np.ndarray, weight: np.ndarray, fwhm_px: float):
    """The expected electrons of unit flux along samples (x, y) of weights ``weight``: the sum of
    pixel-integrated circular Gaussians (erf differences over each pixel's edges), each truncated at
    FOOTPRINT_FWHM FWHM and renormalised to its weight. Returns (row0, col0, stamp) in frame pixels; the
    stamp may reach beyond the frame."""
    sigma = fwhm_px * FWHM_TO_SIGMA
    r = math.ceil(FOOTPRINT_FWHM * fwhm_px)
    ix, iy = np.rint(x).astype(np.int64), np.rint(y).astype(np.int64)
    col0, row0 = int(ix.min()) - r, int(iy.min()) - r
    ncol, nrow = int(ix.max()) + r + 1 - col0, int(iy.max()) + r + 1 - row0
    off = np.arange(-r, r + 2) - 0.5  # pixel edges about the sample's pixel
    stamp = np.zeros(nrow * ncol)
    s2 = math.sqrt(2.0) * sigma
    for a in range(0, len(x), 1024):
        sl = slice(a, a + 1024)
        ex = np.diff(erf((ix[sl, None] + off[None, :] - x[sl, None]) / s2), axis=1)
        ey = np.diff(erf((iy[sl, None] + off[None, :] - y[sl, None]) / s2), axis=1)
        ex /= ex.sum(axis=1, keepdims=True)
        ey /= ey.sum(axis=1, keepdims=True)
        block = weight[sl, None, None] * ey[:, :, None] * ex[:, None, :]
        rows = (iy[sl, None] - r - row0) + np.arange(2 * r + 1)[None, :]
        cols = (ix[sl, None] - r - col0) + np.arange(2 * r + 1)[None, :]
        flat = rows[:, :, None] * ncol + cols[:, None, :]
        stamp += np.bincount(flat.ravel(), weights=block.ravel(), minlength=nrow * ncol)
    return row0, col0, stamp.reshape(nrow, ncol)


def snr_of(e: np.ndarray, var0_e2: np.ndarray) -> tuple[float, float]:
    """(matched-filter SNR, peak SNR per pixel) of expected electrons ``e`` over a background variance
    ``var0_e2`` [e-^2]: sigma^2 = var0 + e (the source's own shot noise)."""
    var = var0_e2 + np.maximum(e, 0.0)
    return float(np.sqrt(np.sum(e * e / var))), float(np.max(e / np.sqrt(var))) if e.size else 0.0


def _visible_ends(x, y, shape):
    h, w = shape
    inside = (x >= -0.5) & (x <= w - 0.5) & (y >= -0.5) & (y <= h - 0.5)
    if not inside.any():
        return None
    k = np.flatnonzero(inside)
    return (float(x[k[0]]), float(y[k[0]]), float(x[k[-1]]), float(y[k[-1]])), int(k[0]), int(k[-1])


@dataclass
class Injected:
    """One injected object: what was drawn (the whole path, the flux) and its expected-electron stamp on the
    frame (the labels come from it: :func:`scenes.app.bench.labels.labels_from_sources`)."""

    obj: Obj
    row0: int
    col0: int
    stamp_e: np.ndarray  # expected electrons on the frame (the part of the footprint inside it)
    truth: dict  # the whole path (x0, y0 at t0_s; x1, y1 at t1_s), flux_e over the exposure, clipped
    visible: tuple  # (x0, y0, x1, y1, t0_s, t1_s) of the part of the path on the frame (NaN: none)


def _draw(obj: Obj, frame: Frame, fwhm_px: float, weights_cfa, var0_e2: np.ndarray,
          unlit: np.ndarray | None = None) -> Injected | None:
    """The object's expected electrons on the frame; its flux set from its target SNR if asked."""
    h, w = frame.shape
    x, y, wgt = _samples(obj, frame.exptime_s, fwhm_px * FWHM_TO_SIGMA)
    row0, col0, unit = expected_stamp(x, y, wgt, fwhm_px)
    if weights_cfa is not None:
        rr = (np.arange(unit.shape[0]) + row0) % 2
        cc = (np.arange(unit.shape[1]) + col0) % 2
        unit = unit * np.asarray(weights_cfa).reshape(2, 2)[rr[:, None], cc[None, :]]
    r0, c0 = max(row0, 0), max(col0, 0)
    r1, c1 = min(row0 + unit.shape[0], h), min(col0 + unit.shape[1], w)
    if r1 <= r0 or c1 <= c0:
        return None
    vis = unit[r0 - row0:r1 - row0, c0 - col0:c1 - col0]
    if unlit is not None:  # the prescan/overscan receives no light
        vis = np.where(unlit[r0:r1, c0:c1], 0.0, vis)
    var = var0_e2[r0:r1, c0:c1]
    if obj.flux_e is not None:
        flux = obj.flux_e
    else:
        def gap(logf):
            return snr_of(math.exp(logf) * vis, var)[0] - obj.snr

        lo, hi = -10.0, 60.0
        flux = math.exp(brentq(gap, lo, hi, xtol=1e-10)) if gap(lo) < 0 < gap(hi) else 0.0
    xa, ya = obj.path(np.array([0.0, frame.exptime_s]))
    ends = _visible_ends(x, y, frame.shape)
    if ends is not None:
        (vx0, vy0, vx1, vy1), k0, k1 = ends
        edges = np.linspace(0.0, frame.exptime_s, len(x) + 1)
        visible = (vx0, vy0, vx1, vy1, float(edges[k0]), float(edges[k1 + 1]))
    else:  # only the PSF's wings reach the frame
        visible = (math.nan,) * 6
    clipped = bool(ends is None or row0 < 0 or col0 < 0 or row0 + unit.shape[0] > h or col0 + unit.shape[1] > w)
    truth = {"name": obj.name, "kind": obj.kind, "x0": float(xa[0]), "y0": float(ya[0]), "x1": float(xa[1]),
             "y1": float(ya[1]), "t0_s": 0.0, "t1_s": frame.exptime_s, "flux_e": float(flux * unit.sum()),
             "clipped": clipped,
             "light_curve": obj.light_curve.to_table() if obj.light_curve is not None else None}
    return Injected(obj, r0, c0, flux * vis, truth, visible)


def source_stamps(done: list[Injected]):
    """The injected objects as :class:`scenes.app.bench.labels.SourceStamp` (row = the INJECTED table's
    row; endpoints and times those of the visible part of the path)."""
    from .labels import SourceStamp

    out = []
    for row, d in enumerate(done):
        vx0, vy0, vx1, vy1, t0, t1 = d.visible
        static = d.obj.kind == "point"
        xc, yc = (0.5 * (vx0 + vx1), 0.5 * (vy0 + vy1)) if np.isfinite(vx0) else (math.nan, math.nan)
        out.append(SourceStamp(d.stamp_e, d.row0, d.col0, row, "injected", xc, yc, vx0, vy0, vx1, vy1,
                               0.0 if static else t0, d.truth["t1_s"] if static else t1, d.truth["flux_e"],
                               math.nan, d.obj.name, row))
    return out


# -------------------------------------------------------------------------------------------------- inject
def _psf_fwhm_px(psf, frame: Frame, bkg, rms) -> tuple[float, str]:
    if psf is None or str(psf).lower() == "measured":
        fwhm, n = measure_psf(frame, bkg, rms)
        return fwhm, f"measured on {n} stars (photutils fit_fwhm, median)"
    text = str(psf).strip().lower()
    try:
        if text.endswith("px"):
            value = float(text[:-2])
            ok = value > 0
            if ok:
                return value, "given [px]"
        value = float(text.removesuffix("arcsec").removesuffix('"'))
        if not value > 0:
            raise ValueError
    except ValueError:
        raise InjectError(f"{psf!r}", key="--psf",
                          expected="measured, a FWHM > 0 in arcsec (2.5) or in pixels (3.2px)") from None
    if frame.pixel_scale_arcsec is None:
        raise InjectError("--psf in arcsec needs the pixel scale, and the frame has no WCS", file=frame.name,
                          key="--psf", expected="a FWHM in pixels (--psf 3.2px), or --pixel-scale ARCSEC")
    return value / frame.pixel_scale_arcsec, "given [arcsec]"


@dataclass
class Result:
    """An injection: the image HDU's new pixels (its own dtype), the injected objects, their labels."""

    pixels: np.ndarray
    injected: list
    labels: object  # scenes.app.bench.frame.FrameLabels
    summary: dict
    background_adu: np.ndarray
    rms_adu: np.ndarray


def inject(frame: Frame, objects: list[Obj], *, psf=None, seed: int | None = None, bkg_rms=None) -> Result:
    """Inject ``objects`` into ``frame`` (the module notes). ``bkg_rms``: (background, rms) [ADU] if
    already measured."""
    from .frame import FrameLabels
    from .labels import MASK_FRACTION_SIGMA, NoiseModel, labels_from_sources

    rng_noise = np.random.default_rng(np.random.SeedSequence(seed).spawn(1)[0])
    bkg, rms = bkg_rms if bkg_rms is not None else background(frame.data, frame.bayer)
    fwhm_px, psf_source = _psf_fwhm_px(psf, frame, bkg, rms)
    weights, colour = (None, "monochrome")
    if frame.bayer is not None:
        weights, colour = cfa_weights(frame, bkg, fwhm_px)
    g = frame.gain_e_per_adu
    sigma_e = rms * g
    unlit = unlit_edges(frame.data)
    unlit = unlit if unlit.any() else None
    done, dropped = [], []
    for obj in objects:
        d = _draw(obj, frame, fwhm_px, weights, sigma_e ** 2, unlit)
        (dropped if d is None else done).append(obj.name if d is None else d)
    h, w = frame.shape
    expected = np.zeros((h, w))
    for d in done:
        expected[d.row0:d.row0 + d.stamp_e.shape[0], d.col0:d.col0 + d.stamp_e.shape[1]] += d.stamp_e
    foot = expected > 0
    counts_e = rng_noise.poisson(expected[foot]).astype(np.float64)
    old = frame.data[foot]
    new = old + counts_e / g
    if frame.dtype.kind in "iu":
        new = np.maximum(np.rint(new), float(np.iinfo(frame.dtype).min))
    new = np.minimum(new, frame.saturation_adu)
    frozen = ~np.isfinite(old) | (old >= frame.saturation_adu)
    new[frozen] = old[frozen]
    out = frame.data.copy()
    out[foot] = new
    out = out.astype(frame.dtype)
    if frame.dtype.kind == "f":  # outside the footprints the input's own bits (no round trip through float64)
        out[~foot] = np.asarray(frame.raw if frame.raw is not None else frame.data)[~foot]
    sources = source_stamps(done)
    noise = NoiseModel.measured(sigma_e)
    labels = labels_from_sources(sources, noise, frame.shape, frame.wcs)
    fl = FrameLabels(labels, sources, frame.shape, frame.wcs, noise, MASK_FRACTION_SIGMA)
    by_row = {lab.row: lab for lab in labels}
    objects_out = []
    for row, d in enumerate(done):
        lab = by_row.get(row)
        rec = dict(d.truth)
        rec.update({f"visible_{k}": v for k, v in zip(("x0", "y0", "x1", "y1", "t0_s", "t1_s"), d.visible)})
        if lab is not None:
            rec.update(snr=lab.snr, snr_peak=lab.snr_peak, flux_visible_e=lab.flux_e, bbox=list(lab.bbox),
                       mask_pixels=lab.mask_pixels, rate_arcsec_s=lab.rate_arcsec_s, length_px=lab.length_px)
        objects_out.append(rec)
    summary = {
        "frame": frame.path, "hdu": frame.hdu, "shape": list(frame.shape), "dtype": str(frame.dtype),
        "gain_e_per_adu": g, "exptime_s": frame.exptime_s, "saturation_adu": frame.saturation_adu,
        "pixel_scale_arcsec": frame.pixel_scale_arcsec, "fwhm_px": fwhm_px, "psf": psf_source,
        "bayer": frame.bayer, "colour": colour, "cfa_weights": None if weights is None else [float(v) for v in weights],
        "background_rms_adu_median": float(np.nanmedian(rms)), "sources": dict(frame.sources),
        "footprint_px": int(foot.sum()), "unlit_px": 0 if unlit is None else int(unlit.sum()), "saturated_px": int(np.sum(new[~frozen] >= frame.saturation_adu)),
        "objects": objects_out, "off_frame": dropped,
        "warnings": list(frame.warnings) + [f"{n}: entirely off the frame, not injected" for n in dropped],
        "seed": seed,
    }
    return Result(out, done, fl, summary, bkg, rms)


#: the injected objects' table: the render's TRUTH columns (scenes.image.build.TRUTH_DTYPE; the whole path,
#: kind "injected") and what the injection adds (the visible part of the path, the SNR, the clipping)
EXTRA_COLUMNS = [("visible_x0", "f8"), ("visible_y0", "f8"), ("visible_x1", "f8"), ("visible_y1", "f8"),
                 ("visible_t0_s", "f8"), ("visible_t1_s", "f8"), ("flux_visible_e", "f8"), ("snr", "f8"),
                 ("snr_peak", "f8"), ("clipped", "?")]


def injected_hdu(res: Result, name: str = "TRUTH") -> fits.BinTableHDU:
    """The injected objects' table (``TRUTH`` when the frame has none, so that the frame with ``--labels
    fits`` is a labels file for ``newtsim score``; else ``INJECTED``): one row per injected object, its row
    the value of the ``LABELS`` image and the ``row`` of the label files."""
    from scenes.image.build import TRUTH_DTYPE

    objs = res.summary["objects"]
    rows = np.zeros(len(objs), dtype=list(TRUTH_DTYPE) + EXTRA_COLUMNS)
    for i, rec in enumerate(objs):
        vals = dict(rec, kind="injected", source_id=i, mag=math.nan,
                    x=0.5 * (rec["x0"] + rec["x1"]), y=0.5 * (rec["y0"] + rec["y1"]))
        if res.labels.wcs is not None:
            ra, dec = res.labels.wcs.all_pix2world([vals["x"]], [vals["y"]], 0)
            vals.update(ra_deg=float(ra[0]), dec_deg=float(dec[0]))
        else:
            vals.update(ra_deg=math.nan, dec_deg=math.nan)
        for col in rows.dtype.names:
            v = vals.get(col, math.nan)
            rows[col][i] = str(v).encode("ascii", "replace")[:32] if rows.dtype[col].kind == "S" else v
    hdu = fits.BinTableHDU(rows, name=name)
    hd, s = hdu.header, res.summary
    hd["INJECTED"] = (True, "rows are objects injected by newtsim inject")
    hd["INJHDU"] = (s["hdu"], "HDU the objects were injected into")
    hd["INJGAIN"] = (s["gain_e_per_adu"], "gain used [e-/ADU]")
    hd["INJFWHM"] = (s["fwhm_px"], "PSF FWHM used [px]")
    hd["INJEXPT"] = (s["exptime_s"], "exposure time used [s]")
    hd["INJSEED"] = (-1 if s["seed"] is None else s["seed"], "seed of the shot noise and random objects")
    hd["INJSAT"] = (s["saturation_adu"] if math.isfinite(s["saturation_adu"]) else -1.0,
                    "saturation level [ADU] (-1: none)")
    hd["COMMENT"] = "0-based pixel centres; x0..y1 the whole path, visible_* its part on the frame"
    hd["COMMENT"] = "snr: matched filter against the frame's background rms (photutils Background2D)"
    return hdu


def inject_file(frame_path, out_path, objects=None, *, random=None, hdu=None, psf=None, gain=None,
                saturation=None, exptime=None, pixel_scale=None, bayer=None, seed=None, labels=(),
                label_paths=None) -> dict:
    """Read ``frame_path``, inject, write ``out_path``: every HDU of the input (the image HDU's pixels changed
    in the footprints only), then an ``INJECTED`` table (and a ``LABELS`` image with ``labels`` holding
    "fits"); the other label formats to ``label_paths[format]``. ``objects``: an objects TOML, or None with
    ``random = (n, (snr_lo, snr_hi), (rate_lo, rate_hi) [arcsec/s])``. Returns the summary."""
    from detector.rng import fresh_seed

    from .formats import labels_hdu, labels_table_hdu
    from .frame import write_label_files

    seed = fresh_seed() if seed is None else int(seed)
    hdul, frame = read_frame(frame_path, hdu, gain=gain, saturation=saturation, exptime=exptime,
                             pixel_scale=pixel_scale, bayer=bayer)
    with hdul:
        if frame.wcs is None and frame.pixel_scale_arcsec is None:
            raise InjectError("no celestial WCS in the image HDU", file=frame.name,
                              expected="a frame with a WCS (TAN, TAN-SIP, TPV, CD or PC+CDELT), or --pixel-scale "
                                       "ARCSEC (objects then in pixels, rates through that scale)")
        if objects is not None:
            objs = objects_from_toml(objects, frame)
        else:
            n, snr_range, rate_range = random
            rng_obj = np.random.default_rng(np.random.SeedSequence(seed).spawn(2)[1])
            objs = random_objects(n, snr_range, rate_range, frame, rng_obj)
        res = inject(frame, objs, psf=psf, seed=seed)
        hdul[frame.hdu].data = res.pixels
        names = {h.name for h in hdul}
        clash = names & {"TRUTH", "LABELS", "LABELCAT"}
        hdul.append(injected_hdu(res, "INJECTED" if clash else "TRUTH"))
        if "fits" in labels and not clash:
            fl = res.labels
            hdul.append(labels_hdu(fl.sources, fl.labels, fl.shape, fl.mask_fraction_sigma))
            hdul.append(labels_table_hdu(fl.labels))
        elif "fits" in labels:
            res.summary["warnings"].append(f"{frame_path} already has {', '.join(sorted(clash))}: the injected "
                                           "objects are in INJECTED, their labels in the other --labels formats only")
        hdul.writeto(out_path, output_verify="silentfix", checksum=False)
        write_label_files(res.labels, {f: p for f, p in (label_paths or {}).items() if f in labels},
                          Path(out_path).name, {"seed": seed, "frame": str(frame_path), "hdu": frame.hdu})
    res.summary["output"] = str(out_path)
    return res.summary
