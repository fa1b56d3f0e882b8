"""Calibration-frame characterisation: bias, darks, hot pixels and a flat pair measured from FITS files.

The reference thesis (sections 3.6.5 and 3.7.1) derives its detector model from calibration frames of the
real camera; this module does the same analysis as a tool and returns a JSON-serialisable dict, from which
:func:`emit_scene_dict` writes the ``[detector]`` / ``[effects]`` tables of a scene that reproduces the
camera, and :mod:`detector.calplots` draws the figures.

What is measured, and how
-------------------------
* **Bias** (>= 1 frame, 2 or more for the read noise). Level: median and sigma-clipped mean of the master
  bias (mean of the bias frames). Read noise (temporal): the difference of two bias frames removes the fixed
  pattern, ``sigma_read = std(b1 - b2) / sqrt(2)`` (sigma-clipped at 5 sigma; also the MAD estimate).
  Single-frame std = temporal + fixed pattern, so ``sigma_fp = sqrt(sigma_1^2 - sigma_read^2)``. Normality of
  the pair difference: Shapiro-Wilk, Jarque-Bera and Kolmogorov-Smirnov (against a normal of the fitted mean
  and std) on 5000 pixels drawn at random; integer ADU are dithered by U(-1/2, 1/2) first, otherwise the ADC's
  quantisation alone makes every test of a continuous law reject.
* **Darks** (grouped by exposure time, frames of equal time averaged). Per exposure: median, mean of the
  inliers (3-sigma clipping), mean of all pixels. Thesis regression ``mean_ADU(t) = B + r t`` by ordinary
  least squares over the exposures, standard errors from the residuals; ``r`` in ADU/s and, times the gain,
  e-/s. Predicted vs measured for every exposure, leave-one-out predictions and a hold-out test (fit on some
  exposures, predict the others, the mean level and the count of pixels above a threshold).
* **Hot pixels**. Outliers: pixels of the bias-subtracted (master bias, pixel by pixel) longest dark more
  than ``hot_sigma`` robust sigma above the frame's centre. For every outlier a straight-line fit of its
  value against exposure time over all darks (saturated points dropped) gives its rate; its *excess* rate is
  that minus the frame's mean dark rate. Time-to-double (our reading of the thesis's eq. 38)::

      t_double = B / r

  where ``B`` is the bias level in ADU and ``r`` the pixel's dark rate in ADU/s in excess of the mean dark
  rate (the rate the pixel's defect adds; the ``hot_pixels`` effect adds ``r_e = B g / t_double`` e-/s): the
  exposure at which the pixel's value has doubled its zero-exposure level. Weibull (``scipy.stats.weibull_min``,
  loc = 0) and exponential laws are fitted to the ``t_double`` values by maximum likelihood and compared by
  AIC. Classes: *stuck* (does not grow with time: already at least half its longest-exposure level at the
  shortest exposure, or high in the master bias and unchanged in every dark), *transient* (high only in the
  longest dark although it should then show in the second-longest: a cosmic-ray hit), *hot* (the rest, with
  a positive excess rate). The fitted law describes the *detected* population: ``t_double`` values above the
  detection limit (reported) are missing, so the law depends on the longest exposure and on ``hot_sigma``.
* **Flat pair** (optional, Janesick, *Photon Transfer*, SPIE 2007, ch. 4-5). Mean signal ``S`` (bias
  subtracted) and the variance of the pair difference (the second flat scaled to the first's mean, which
  removes PRNU and illumination): ``K = S / (var(diff)/2 - sigma_read^2)`` e-/ADU; the spread of K over 4x4
  tiles gives its standard error. PRNU: spatial std of the mean flat divided by a Gaussian-smoothed version
  of itself (so large-scale vignetting is not PRNU), with the temporal noise subtracted in quadrature.
  Vignetting: median of corner boxes over the centre box of the smoothed flat.

Gain adopted for e- values: the photon-transfer gain of a flat pair (a header value that differs beyond 3 standard
errors is flagged), else the header's ``EGAIN`` (or ``GAIN`` when it looks like e-/ADU), else
1.0 with a warning.

Public API: :func:`characterize` (files in, dict out), :func:`emit_scene_dict` (dict in, scene tables out),
:func:`detector.calplots.write_plots` (dict in, PNG files out); the pure functions (:func:`clipped_stats`,
:func:`pair_noise`, :func:`normality_tests`, :func:`linear_fit`, :func:`fit_lifetimes`,
:func:`photon_transfer`, :func:`prnu_and_vignetting` ...) work on plain arrays.

Memory (issue 12: a full 14192 x 10640 IMX411 set of 7 frames in at most 3 GiB): the frames are read band
by band (:mod:`detector.calbands`, row bands of ``BAND_PIXELS`` pixels); the robust statistics use at most
``MAX_STAT_PIXELS`` pixels of every frame (a regular sub-grid, :func:`detector.stats.subsample`, gathered
in the first pass: the very values the whole-frame code used); counts, outliers, column and row medians and
the smoothing of the flat are exact over all pixels (the smoothing on bands with a halo of ``4 sigma``
rows). The master bias and the camera twin's per-pixel maps live in float32 temporary files and are written
to FITS band by band. A frame of at most ``BAND_PIXELS`` pixels is one band: the same arithmetic as the
whole-frame code.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterable, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from astropy.io import fits
from scipy import ndimage, stats

from .calbands import BandStore, FitsRows, Gather, Sampler, as_rows, band_rows, bands, halo_rows
from .errors import DetectorError
from .fits_io import read_image
from .jsonable import jsonable
from .stats import MAX_STAT_PIXELS, clipped_stats, mad_std, subsample

#: Pixels drawn for the normality tests (Shapiro-Wilk is defined up to 5000).
NORMALITY_SAMPLE = 5000
EXPTIME_KEYS = ("EXPTIME", "EXPOSURE")
TEMP_KEYS = ("CCD-TEMP", "CCDTEMP", "TEMPERAT", "DET-TEMP")


# ============================================================================================
# reading and validating frames
# ============================================================================================

@dataclass
class Frame:
    """One calibration frame: its header values and its pixels, in memory (``data``) or read by rows (``src``)."""

    path: str
    data: np.ndarray | None  # float32, 2-D, ADU (None when read band by band)
    header: dict = field(repr=False)
    exptime_s: float | None
    saturation_adu: float
    temperature_c: float | None
    src: object = field(default=None, repr=False)  # a rows(a, b) source (detector.calbands.FitsRows)
    shape: tuple = ()
    checks: dict = field(default_factory=dict, repr=False)  # filled by the first pass (sanity checks)

    def rows(self, a: int, b: int) -> np.ndarray:
        """Rows ``a:b`` as float32 [ADU]."""
        if self.src is None:
            return self.data[a:b]
        return self.src.rows(a, b).astype(np.float32)

    def close(self) -> None:
        if self.src is not None and hasattr(self.src, "close"):
            self.src.close()


def _card(header, keys: Iterable[str]):
    for k in keys:
        if k in header and header[k] is not None and not isinstance(header[k], bool):
            return k, header[k]
    return None, None


def _header_values(name: str, header, role: str, need_exptime: bool):
    exptime = None
    key, val = _card(header, EXPTIME_KEYS)
    if key is None:
        if need_exptime:
            raise DetectorError(f"{role} frame has no exposure time", key="EXPTIME", file=name,
                                expected="header card EXPTIME (or EXPOSURE) in seconds")
    else:
        try:
            exptime = float(val)
        except (TypeError, ValueError):
            raise DetectorError(f"exposure time {val!r} is not a number", key=key, file=name,
                                expected="a number of seconds >= 0") from None
        if not math.isfinite(exptime) or exptime < 0:
            raise DetectorError(f"exposure time {val!r}", key=key, file=name, expected="a number of seconds >= 0")
    _, t = _card(header, TEMP_KEYS)
    try:
        temp = float(t) if t is not None else None
    except (TypeError, ValueError):
        temp = None
    return exptime, temp


def _nonfinite_error(name: str, role: str, arr: np.ndarray, row0: int = 0, count: int | None = None):
    finite = np.isfinite(arr)
    bad = np.argwhere(~finite)[0]
    n = int((~finite).sum()) if count is None else count
    raise DetectorError(f"{role} image has {n} non-finite pixels, first at (x={bad[1]}, y={bad[0] + row0})",
                        file=name, expected="finite pixel values")


def read_frame(path, *, role: str = "frame", need_exptime: bool = False) -> Frame:
    """Read and validate one FITS calibration frame, whole, into memory (small frames; see :func:`open_frame`).

    Checks: the file exists and is a readable FITS file, holds a 2-D image (the first HDU with one), all
    pixels finite, and (``need_exptime``) an ``EXPTIME`` or ``EXPOSURE`` card >= 0 s. Every failure is a
    :class:`DetectorError` naming the file (and the header key).

    Parameters
    ----------
    path : str or Path
    role : str
        "bias", "dark" or "flat", used in messages.
    need_exptime : bool
        Whether a missing exposure time is an error.
    """
    name = str(path)
    data, hdr = read_image(path, role=role, dtype=None)
    header = dict(hdr)
    if data.dtype.kind not in "iuf":
        raise DetectorError(f"{role} image has data type {data.dtype}", file=name, expected="numbers")
    arr = data.astype(np.float32)
    if not np.isfinite(arr).all():
        _nonfinite_error(name, role, arr)
    exptime, temp = _header_values(name, header, role, need_exptime)
    sat = _saturation_adu(header, data)
    return Frame(name, arr, header, exptime, sat, temp, shape=arr.shape)


def open_frame(path, *, role: str = "frame", need_exptime: bool = False) -> Frame:
    """Open one FITS calibration frame for reading band by band (:class:`detector.calbands.FitsRows`).

    The header is checked here (2-D image, numeric type, exposure time); the pixels (finite values) in the
    first pass of :func:`characterize`. Same errors as :func:`read_frame`.
    """
    name = str(path)
    src = FitsRows(path, role=role)
    try:
        header = dict(src.header)
        if src.dtype.kind not in "iuf":
            raise DetectorError(f"{role} image has data type {src.dtype}", file=name, expected="numbers")
        exptime, temp = _header_values(name, header, role, need_exptime)
        sat = _saturation_adu(header, np.zeros(0, src.dtype))
    except BaseException:
        src.close()
        raise
    return Frame(name, None, header, exptime, sat, temp, src=src, shape=src.shape)


def _saturation_adu(header, raw: np.ndarray) -> float:
    """The value at which the ADC saturates: SATURATE or DATAMAX if given, else the integer type's maximum."""
    for k in ("SATURATE", "DATAMAX"):
        if k in header:
            try:
                v = float(header[k])
                if v > 0:
                    return v
            except (TypeError, ValueError):
                pass
    if raw.dtype.kind in "iu":
        bitpix = abs(int(header.get("BITPIX", 8 * raw.dtype.itemsize)))
        bzero = float(header.get("BZERO", 0) or 0)
        if bitpix == 16 and bzero == 32768:
            return 65535.0
        return float(np.iinfo(raw.dtype).max)
    return math.inf


def read_frames(paths: Sequence, role: str, *, need_exptime: bool, shape: tuple | None = None,
                shape_file: str | None = None, lazy: bool = False) -> list[Frame]:
    """Read (or, ``lazy``, open for band reading) several frames of one role; all of ``shape`` (or the first's)."""
    out = []
    try:
        for p in paths:
            f = (open_frame if lazy else read_frame)(p, role=role, need_exptime=need_exptime)
            out.append(f)
            if shape is None:
                shape, shape_file = f.shape, f.path
            elif tuple(f.shape) != tuple(shape):
                raise DetectorError(f"{role} frame is {f.shape[1]}x{f.shape[0]} pixels but {shape_file} is "
                                    f"{shape[1]}x{shape[0]}", file=f.path, expected="frames of one size")
    except BaseException:
        for f in out:
            f.close()
        raise
    return out


def header_gain(frames: Sequence[Frame]) -> tuple[float | None, str | None, str | None]:
    """Gain [e-/ADU] from ``EGAIN`` (or ``E-GAIN``, or ``GAIN`` when in (0, 100]): (value, card, file)."""
    for f in frames:
        for k in ("EGAIN", "E-GAIN", "GAIN"):
            if k in f.header:
                try:
                    g = float(f.header[k])
                except (TypeError, ValueError):
                    continue
                if math.isfinite(g) and 0 < g <= (1000 if k != "GAIN" else 100):
                    return g, k, f.path
    return None, None, None


# ============================================================================================
# pure statistics
# ============================================================================================

def pair_noise(a: np.ndarray, b: np.ndarray, sigma: float = 5.0) -> dict:
    """Temporal noise of one frame from the difference of two frames of the same kind [ADU].

    ``sigma_frame = std(a - b) / sqrt(2)``: the fixed pattern, identical in both, cancels (Janesick 2007,
    ch. 4). The second frame is not rescaled (bias frames). Robust: sigma-clipped std and MAD.
    """
    d = a.astype(np.float64) - b.astype(np.float64)
    cs = clipped_stats(d, sigma=sigma)
    return {"sigma_adu": cs["std"] / math.sqrt(2), "sigma_mad_adu": mad_std(d) / math.sqrt(2),
            "sigma_unclipped_adu": float(subsample(d).std()) / math.sqrt(2), "diff_mean_adu": cs["mean"],
            "n": cs["n"], "n_rejected": cs["n_rejected"]}


def normality_tests(sample: np.ndarray, rng: np.random.Generator, dither: bool = True) -> dict:
    """Shapiro-Wilk, Jarque-Bera and Kolmogorov-Smirnov tests of a sample against a normal law.

    Parameters
    ----------
    sample : array
        At most 5000 values (Shapiro-Wilk's range).
    rng : numpy.random.Generator
        For the dither.
    dither : bool
        Add U(-1/2, 1/2) (integer ADU data): the ADC quantisation is otherwise rejected, not the noise law.

    The KS test uses the sample's own mean and std (a Lilliefors situation: its p-value is conservative).
    """
    x = np.asarray(sample, dtype=np.float64)
    if dither:
        x = x + rng.uniform(-0.5, 0.5, size=x.size)
    mu, sd = float(x.mean()), float(x.std(ddof=1))
    out: dict = {"n": int(x.size), "dithered": bool(dither), "mean": mu, "std": sd,
                 "skewness": float(stats.skew(x)), "excess_kurtosis": float(stats.kurtosis(x))}
    if x.size >= 3:
        w, p = stats.shapiro(x)
        out["shapiro_wilk"] = {"statistic": float(w), "p_value": float(p)}
    jb = stats.jarque_bera(x)
    out["jarque_bera"] = {"statistic": float(jb.statistic), "p_value": float(jb.pvalue)}
    ks = stats.kstest(x, "norm", args=(mu, sd))
    out["kolmogorov_smirnov"] = {"statistic": float(ks.statistic), "p_value": float(ks.pvalue)}
    return out


def linear_fit(t, y) -> dict:
    """Ordinary least squares ``y = a + b t`` with standard errors from the residuals.

    Returns ``intercept``, ``slope``, ``intercept_se``, ``slope_se``, ``cov`` (2x2, [a, b]), ``dof``,
    ``residual_std``. With 2 points the standard errors are NaN.
    """
    t = np.asarray(t, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    n = t.size
    if n < 2 or np.ptp(t) == 0:
        raise ValueError("a straight-line fit needs at least two different abscissae")
    A = np.vstack([np.ones(n), t]).T
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    resid = y - A @ coef
    dof = n - 2
    s2 = float(resid @ resid / dof) if dof > 0 else math.nan
    cov = s2 * np.linalg.inv(A.T @ A)
    return {"intercept": float(coef[0]), "slope": float(coef[1]), "intercept_se": float(math.sqrt(cov[0, 0])),
            "slope_se": float(math.sqrt(cov[1, 1])), "cov": cov.tolist(), "dof": dof,
            "residual_std": math.sqrt(s2) if dof > 0 else math.nan}


def masked_linear_fit(t: np.ndarray, Y: np.ndarray, valid: np.ndarray | None = None
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Straight-line fits of many pixels at once: ``Y[i, j] = a_i + b_i t[j]`` over the ``valid`` points.

    Returns slope ``b``, intercept ``a`` (NaN where fewer than two valid points at different times) and the
    number of points used.
    """
    t = np.asarray(t, dtype=np.float64)
    Y = np.asarray(Y, dtype=np.float64)
    w = np.ones_like(Y) if valid is None else valid.astype(np.float64)
    n = w.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        tm = (w * t).sum(axis=1) / n
        ym = (w * Y).sum(axis=1) / n
        dt = (t[None, :] - tm[:, None]) * w
        stt = (dt * dt).sum(axis=1)
        sty = (dt * (Y - ym[:, None])).sum(axis=1)
        ok = (n >= 2) & (stt > 0)
        slope = np.where(ok, sty / np.where(ok, stt, 1.0), np.nan)
        icpt = np.where(ok, ym - slope * tm, np.nan)
    return slope, icpt, n.astype(int)


def fit_lifetimes(t_double_s: np.ndarray) -> dict:
    """Maximum-likelihood Weibull (loc = 0) and exponential fits of times-to-double [s], compared by AIC.

    Weibull ``f(t) = (k/l) (t/l)^(k-1) exp(-(t/l)^k)`` (``scipy.stats.weibull_min``, shape k, scale l);
    exponential = Weibull with k = 1. Standard errors are the asymptotic ones of the maximum-likelihood
    estimators (Cohen 1965): ``var(k) = 0.608 k^2 / n``, ``var(l) = 1.109 l^2 / (n k^2)``; ``var(l) = l^2/n``
    for the exponential. ``AIC = 2 p - 2 ln L`` (p = 2 and 1 parameters); the preferred law has the
    lower AIC. Each fit also carries a Kolmogorov-Smirnov p-value against its own fitted law.
    """
    x = np.asarray(t_double_s, dtype=np.float64)
    x = x[np.isfinite(x) & (x > 0)]
    n = int(x.size)
    out: dict = {"n": n}
    if n < 5:
        out["note"] = "fewer than 5 values: no fit"
        return out
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        k, _, lam = stats.weibull_min.fit(x, floc=0)
    ll_w = float(np.sum(stats.weibull_min.logpdf(x, k, 0, lam)))
    scale_e = float(x.mean())
    ll_e = float(np.sum(stats.expon.logpdf(x, 0, scale_e)))
    aic_w, aic_e = 4 - 2 * ll_w, 2 - 2 * ll_e
    out["weibull"] = {"shape": float(k), "scale_s": float(lam), "shape_se": float(math.sqrt(0.6079 * k * k / n)),
                      "scale_se_s": float(math.sqrt(1.1087 * lam * lam / (n * k * k))), "loglik": ll_w,
                      "aic": aic_w, "ks_p_value": float(stats.kstest(x, "weibull_min", args=(k, 0, lam)).pvalue)}
    out["exponential"] = {"scale_s": scale_e, "scale_se_s": scale_e / math.sqrt(n), "loglik": ll_e, "aic": aic_e,
                          "ks_p_value": float(stats.kstest(x, "expon", args=(0, scale_e)).pvalue)}
    out["preferred"] = "weibull" if aic_w < aic_e else "exponential"
    out["delta_aic_exponential_minus_weibull"] = aic_e - aic_w
    return out


def lifetime_cdf(fits: dict, t_s: float, law: str | None = None) -> float:
    """CDF of the fitted (preferred, or ``law``) time-to-double distribution at ``t_s``."""
    law = law or fits.get("preferred")
    if law == "weibull":
        w = fits["weibull"]
        return float(stats.weibull_min.cdf(t_s, w["shape"], 0, w["scale_s"]))
    if law == "exponential":
        return float(stats.expon.cdf(t_s, 0, fits["exponential"]["scale_s"]))
    return math.nan


# ============================================================================================
# band passes
# ============================================================================================

class _Bands:
    """Row bands of one frame shape and the progress callback: ``for r0, r1 in bands.run("label")``."""

    def __init__(self, shape, band_pixels: int | None = None, progress=None):
        self.shape = tuple(shape)
        self.rows = band_rows(self.shape, band_pixels)
        self.progress = progress
        self.n = int(math.ceil(self.shape[0] / self.rows))

    def run(self, label: str):
        if self.progress:
            self.progress(label, 0, self.n)
        for k, (r0, r1) in enumerate(bands(self.shape, self.rows)):
            yield r0, r1
            if self.progress:
                self.progress(label, k + 1, self.n)


def _mean32(arrs: Sequence[np.ndarray]) -> np.ndarray:
    """Pixel mean of frames as float32 (float64 accumulation), or the one frame itself."""
    if len(arrs) == 1:
        return arrs[0]
    return np.mean(arrs, axis=0, dtype=np.float64).astype(np.float32)


def _group_by_time(frames: Sequence[Frame]) -> tuple[np.ndarray, list[list[Frame]]]:
    by_t: dict[float, list[Frame]] = {}
    for f in frames:
        by_t.setdefault(float(f.exptime_s), []).append(f)
    ts = np.array(sorted(by_t))
    return ts, [by_t[t] for t in ts]


def _tiles(shape, tiles: int = 4) -> list[tuple[int, int, int, int]]:
    h, w = shape
    return [(i * h // tiles, (i + 1) * h // tiles, j * w // tiles, (j + 1) * w // tiles)
            for i in range(tiles) for j in range(tiles)]


def _first_pass(bias, darks, flats, groups, B: _Bands, thresholds) -> dict:
    """One pass over every frame: regular subsamples (the robust statistics), finiteness, the checks of
    :func:`sanity_checks`, the master bias (to a float32 band store), its row medians, and the counts of
    bias-subtracted dark pixels above the fixed thresholds."""
    frames = list(bias) + list(darks) + list(flats)
    shape = B.shape
    h, w = shape
    S4, S1 = Sampler(shape), Sampler(shape, 1_000_000)
    tiles = _tiles(shape) if flats else []
    # the 16 tiles' subsamples together hold as many values as the frame's (small frames: every pixel)
    St = [Sampler(shape, MAX_STAT_PIXELS // max(len(tiles), 1), region=t) for t in tiles]
    G = Gather()
    master = BandStore(shape, np.float32)
    row_med = np.empty(h, np.float64)
    roles = [("bias", bias), ("dark", darks), ("flat", flats)]
    same = {id(f): [True] * len(fr) for _, fr in roles for f in fr}
    lo = {id(f): math.inf for f in frames}
    hi = {id(f): -math.inf for f in frames}
    counts = [{thr: 0 for thr in thresholds} for _ in groups]
    for r0, r1 in B.run("read frames, master bias"):
        raw = {id(f): f.rows(r0, r1) for f in frames}
        for k, f in enumerate(frames):
            a = raw[id(f)]
            if a.dtype.kind == "f" and not np.isfinite(a).all():
                _nonfinite_error(f.path, f.checks.get("role", "frame"), a, r0)
            G.add(f"s{k}", S4.take(r0, a))
            G.add(f"q{k}", S1.take(r0, a))
            lo[id(f)] = min(lo[id(f)], float(a.min()))
            hi[id(f)] = max(hi[id(f)], float(a.max()))
            if r0 == 0:
                f.checks["head"] = a[:16, :16].copy()
        for _, fr in roles:
            for i, a in enumerate(fr):
                for j in range(i + 1, len(fr)):
                    if same[id(a)][j]:
                        same[id(a)][j] = bool(np.array_equal(raw[id(a)], raw[id(fr[j])]))
        m = _mean32([raw[id(f)] for f in bias])
        master.write(r0, m)
        row_med[r0:r1] = np.median(m.astype(np.float64), axis=1)
        for k, f in enumerate(flats):
            for t, s in enumerate(St):
                G.add(f"t{k}_{t}", s.take(r0, raw[id(f)]))
        for t, s in enumerate(St):
            G.add(f"tm_{t}", s.take(r0, m))
        for gi, g in enumerate(groups):
            x = _mean32([raw[id(f)] for f in g]) - m
            for thr in thresholds:
                counts[gi][thr] += int(np.count_nonzero(x > thr))
        del raw
    for _, fr in roles:
        for i, a in enumerate(fr):
            a.checks["identical_to"] = next((fr[j].path for j in range(i + 1, len(fr)) if same[id(a)][j]), None)
    for k, f in enumerate(frames):
        q = G.get(f"q{k}")
        f.checks["saturated_fraction"] = float(np.mean(q >= f.saturation_adu - 0.5)) \
            if math.isfinite(f.saturation_adu) and q.size else 0.0
        f.checks["constant"] = lo[id(f)] == hi[id(f)]
        f.checks["first_value"] = lo[id(f)]
    samples = {id(f): G.get(f"s{k}").astype(np.float32) for k, f in enumerate(frames)}
    return {"samples": samples, "master": master, "row_median": row_med, "counts": counts, "tiles": tiles,
            "tile_samples": [[G.get(f"t{k}_{t}").astype(np.float32) for t in range(len(tiles))]
                             for k in range(len(flats))],
            "tile_master": [G.get(f"tm_{t}").astype(np.float32) for t in range(len(tiles))]}


def _column_medians(store: BandStore, block: int = 512) -> np.ndarray:
    """Median of every column of a float32 band store (column blocks through a read-only memory map)."""
    h, w = store.shape
    store._f.flush()
    out = np.empty(w, np.float64)
    for c0 in range(0, w, block):
        # a fresh map per block: the pages it touches leave the resident set when it is dropped
        mm = np.memmap(store._f, dtype=store.dtype, mode="r", shape=store.shape)
        out[c0:c0 + block] = np.median(np.asarray(mm[:, c0:c0 + block], dtype=np.float64), axis=0)
        del mm
    return out


# ============================================================================================
# bias
# ============================================================================================

def analyze_bias(frames: Sequence[Frame], rng: np.random.Generator, samples: dict | None = None,
                 column_median=None, row_median=None) -> tuple[dict, np.ndarray | None, list[str]]:
    """Bias level, temporal read noise, fixed pattern and normality. Returns (result, master bias, warnings).

    In memory (frames with ``data``): as written. Band by band (:func:`characterize`): ``samples`` maps each
    frame's ``id`` to its regular subsample (:func:`detector.stats.subsample`, the values every statistic
    here uses), ``column_median`` and ``row_median`` are the master's column and row medians; the master
    itself is then not returned (None).
    """
    warns: list[str] = []
    master = None
    if samples is None:
        master = _mean32([f.data for f in frames]).copy()
        samples = {id(f): subsample(f.data) for f in frames}
        m64 = master.astype(np.float64)
        column_median, row_median = np.median(m64, axis=0), np.median(m64, axis=1)
        del m64
    ms_v = _mean32([samples[id(f)] for f in frames])  # the master's subsample
    s0 = samples[id(frames[0])]
    ms = clipped_stats(ms_v, sigma=5.0)
    single = clipped_stats(s0, sigma=5.0)
    res: dict = {
        "n_frames": len(frames),
        "files": [f.path for f in frames],
        "level_median_adu": float(np.median(ms_v)),
        "level_mean_adu": ms["mean"],
        "level_mean_all_adu": float(ms_v.mean(dtype=np.float64)),
        "frame_medians_adu": [float(np.median(samples[id(f)])) for f in frames],
        "single_frame_std_adu": single["std"],
        "single_frame_std_unclipped_adu": float(s0.std(dtype=np.float64)),
    }
    for f in frames:
        if f.exptime_s is not None and f.exptime_s > 1.0:
            warns.append(f"{f.path}: bias frame has an exposure time of {f.exptime_s} s")
    if len(frames) >= 2:
        pairs = [(frames[i], frames[i + 1]) for i in range(0, len(frames) - 1, 2)]
        pn = [pair_noise(samples[id(a)], samples[id(b)]) for a, b in pairs]
        var = float(np.mean([p["sigma_adu"] ** 2 for p in pn]))
        read = math.sqrt(var)
        res["read_noise_adu"] = read
        res["read_noise_mad_adu"] = float(np.sqrt(np.mean([p["sigma_mad_adu"] ** 2 for p in pn])))
        res["read_noise_unclipped_adu"] = float(np.sqrt(np.mean([p["sigma_unclipped_adu"] ** 2 for p in pn])))
        n_pix = frames[0].shape[0] * frames[0].shape[1]
        # the pair noise's n counts the subsample: the standard error is that of the sample used
        res["read_noise_se_adu"] = read / math.sqrt(2 * sum(p["n"] for p in pn))
        res["read_noise_method"] = "std(b1 - b2)/sqrt(2), 5-sigma clipped, over consecutive pairs"
        if n_pix > MAX_STAT_PIXELS:
            res["read_noise_method"] += f" (regular subsample of {MAX_STAT_PIXELS} pixels at most)"
        res["pair_difference_mean_adu"] = pn[0]["diff_mean_adu"]
        d = samples[id(pairs[0][0])].astype(np.float64) - samples[id(pairs[0][1])].astype(np.float64)
        cd = clipped_stats(d, sigma=5.0)
        dv = subsample(d)
        dv = dv[(dv >= cd["lo"]) & (dv <= cd["hi"])]
        sample = rng.choice(dv, size=min(NORMALITY_SAMPLE, dv.size), replace=False)
        head = frames[0].data[:8, :8] if frames[0].data is not None else frames[0].checks["head"][:8, :8]
        integer = bool(np.all(np.floor(head) == head))
        res["normality"] = normality_tests(sample, rng, dither=integer)
        res["normality"]["data"] = "pair difference b1 - b2 [ADU], 5-sigma clipped, random subsample"
        fp2 = single["std"] ** 2 - read ** 2
        res["fixed_pattern_std_adu"] = math.sqrt(fp2) if fp2 > 0 else 0.0
        # plot data: histograms and QQ points
        srt = np.sort(sample)
        q = np.linspace(0.5, srt.size - 0.5, 201) / srt.size
        osr = np.quantile(srt, q)
        res["plot_data"] = {
            "pair_diff_hist": _int_histogram(dv, cd["median"], cd["std"]),
            "qq": {"theoretical": stats.norm.ppf(q).tolist(), "sample_adu": osr.tolist()},
        }
    else:
        read = single["std"]
        res["read_noise_adu"] = read
        res["read_noise_se_adu"] = math.nan
        res["read_noise_method"] = "single-frame std (one bias frame: temporal and fixed pattern not separated)"
        res["fixed_pattern_std_adu"] = math.nan
        res["plot_data"] = {}
        warns.append("one bias frame: the read noise includes the bias fixed pattern (give two bias frames)")
    res["column_pattern_std_adu"] = float(clipped_stats(np.asarray(column_median), 5.0)["std"])
    res["row_pattern_std_adu"] = float(clipped_stats(np.asarray(row_median), 5.0)["std"])
    res["plot_data"]["single_frame_hist"] = _int_histogram(s0, single["median"], single["std"])
    res["plot_data"]["single_frame_mean_std"] = [single["mean"], single["std"]]
    temps = [f.temperature_c for f in frames if f.temperature_c is not None]
    res["temperature_c"] = float(np.mean(temps)) if temps else None
    return res, master, warns


def _int_histogram(v: np.ndarray, centre: float, sigma: float, nsig: float = 5.0, max_bins: int = 120) -> dict:
    """Histogram over centre +- nsig sigma, bins of whole ADU (or wider) centred on integers."""
    sigma = sigma if sigma > 0 else 1.0
    half = max(nsig * sigma, 3.0)
    width = max(1.0, math.ceil(2 * half / max_bins))
    lo = math.floor(centre - half) - 0.5
    nb = int(math.ceil(2 * half / width)) + 1
    edges = lo + width * np.arange(nb + 1)
    counts, _ = np.histogram(v, bins=edges)
    return {"edges": edges.tolist(), "counts": counts.tolist(), "n_total": int(np.size(v))}


# ============================================================================================
# darks and hot pixels
# ============================================================================================

def detect_outliers(x_long: np.ndarray, nsigma: float) -> tuple[np.ndarray, dict]:
    """Pixels of a bias-subtracted dark more than ``nsigma`` robust sigma above its clipped centre.

    Returns the flat indices and the detection statistics (centre, sigma and threshold, in ADU above bias).
    """
    det = _detection(x_long, nsigma)
    return np.flatnonzero(x_long.ravel() > det["threshold_adu"]), det


def _detection(sample: np.ndarray, nsigma: float) -> dict:
    """Detection threshold from (a regular subsample of) the longest bias-subtracted dark."""
    cs = clipped_stats(sample, sigma=3.0)
    thr = cs["median"] + nsigma * cs["std"]
    return {"centre_adu": cs["median"], "robust_sigma_adu": cs["std"], "threshold_adu": float(thr),
            "nsigma": nsigma}


class _OutlierGather:
    """The pixels :func:`analyze_hot_pixels` needs, gathered band by band.

    Outliers: pixels of the longest dark of ``sel`` (exposure indices) above ``threshold``; with their values
    in every selected dark, their saturation flags and their master-bias values. Candidates stuck in the
    bias: master above ``master_threshold``, with their values in the selected darks.
    """

    def __init__(self, sel: Sequence[int], threshold: float, master_threshold: float | None, width: int):
        self.sel, self.thr, self.mthr, self.w = list(sel), threshold, master_threshold, width
        self.idx, self.Y, self.sat, self.m = [], [], [], []
        self.cand, self.cand_x, self.cand_m = [], [], []

    def add(self, r0: int, xs: Sequence[np.ndarray], sats: Sequence[np.ndarray] | None, master: np.ndarray | None):
        xl = xs[self.sel[-1]]
        hit = np.flatnonzero(xl.ravel() > self.thr)
        off = r0 * self.w
        self.idx.append(hit + off)
        self.Y.append(np.stack([xs[j].ravel()[hit] for j in self.sel], axis=1))
        self.sat.append(np.stack([sats[j].ravel()[hit] for j in self.sel], axis=1) if sats is not None
                        else np.zeros((hit.size, len(self.sel)), bool))
        self.m.append(master.ravel()[hit] if master is not None else np.zeros(hit.size, np.float32))
        if master is not None and self.mthr is not None:
            c = np.flatnonzero(master.ravel() > self.mthr)
            self.cand.append(c + off)
            self.cand_x.append(np.stack([xs[j].ravel()[c] for j in self.sel], axis=1))
            self.cand_m.append(master.ravel()[c])

    def result(self) -> dict:
        n = len(self.sel)
        cat = lambda p, shape, dt: np.concatenate(p) if p else np.zeros(shape, dt)
        return {"idx": cat(self.idx, 0, np.int64), "Y": cat(self.Y, (0, n), np.float32),
                "sat": cat(self.sat, (0, n), bool), "master": cat(self.m, 0, np.float32),
                "cand": cat(self.cand, 0, np.int64), "cand_x": cat(self.cand_x, (0, n), np.float32),
                "cand_master": cat(self.cand_m, 0, np.float32), "has_master": self.mthr is not None}


def analyze_hot_pixels(ts: np.ndarray, xs: Sequence[np.ndarray], sat_mask: Sequence[np.ndarray] | None,
                       mean_rate_adu_s: float, bias_level_adu: float, nsigma: float = 5.0,
                       read_noise_adu: float = 0.0, keep_per_pixel: bool = False,
                       master: np.ndarray | None = None) -> dict:
    """Outliers of the longest dark, their rates, classes and the time-to-double law.

    Parameters
    ----------
    ts : array [s]
        Distinct dark exposure times, increasing.
    xs : list of 2-D arrays [ADU]
        Bias-subtracted darks (pixel by pixel), one per time.
    sat_mask : list of 2-D bool arrays or None
        Pixels at the ADC saturation in each dark (dropped from the rate fits).
    mean_rate_adu_s : float [ADU/s]
        The frame's mean dark rate; a defect's excess rate is its own rate minus this.
    bias_level_adu : float [ADU]
        ``B`` of ``t_double = B / r``.
    nsigma : float
        Detection threshold in robust sigma of the longest dark.
    read_noise_adu : float [ADU]
        Temporal read noise (for the transient test).
    master : 2-D array [ADU], optional
        The master bias. With it, pixels stuck at a high value in the bias frames *and* every dark (invisible
        once the bias is subtracted) are found too: master bias more than ``nsigma`` robust sigma above the
        bias level, and raw values in the darks within ``max(5 sqrt(1.5) sigma_read, 10 %)`` of it.

    Stuck pixels are the union of these and of the outliers of the longest dark that are already at half
    their level or more at the shortest exposure (they do not grow with time). The work is done by
    :func:`hot_pixels_from_gathered` (which :func:`characterize` feeds band by band).
    """
    h, w = xs[-1].shape
    det = _detection(xs[-1], nsigma)
    mthr = None
    if master is not None:
        mcs = clipped_stats(master, sigma=3.0)
        mthr = mcs["median"] + nsigma * mcs["std"]
    g = _OutlierGather(range(len(xs)), det["threshold_adu"], mthr, w)
    g.add(0, xs, sat_mask, master)
    return hot_pixels_from_gathered(ts, g.result(), det, (h, w), mean_rate_adu_s, bias_level_adu, nsigma,
                                    read_noise_adu, keep_per_pixel)


def hot_pixels_from_gathered(ts, g: dict, det: dict, shape, mean_rate_adu_s: float, bias_level_adu: float,
                             nsigma: float, read_noise_adu: float, keep_per_pixel: bool = False) -> dict:
    """:func:`analyze_hot_pixels` on the pixels :class:`_OutlierGather` collected (see there)."""
    h, w = shape
    det = dict(det)
    det["exposure_s"] = float(ts[-1])
    idx = g["idx"]
    n_t = len(ts)
    Y = g["Y"].astype(np.float64)  # (n_out, n_t)
    valid = ~g["sat"]
    x_long = Y[:, -1]
    stuck = np.zeros(idx.size, bool)
    transient = np.zeros(idx.size, bool)
    if n_t >= 2 and ts[0] <= 0.5 * ts[-1]:
        stuck = Y[:, 0] >= 0.5 * x_long
    if n_t >= 2:
        # expected at the second-longest exposure if the pixel grew linearly from zero
        sig2 = math.sqrt(1.5 * read_noise_adu ** 2 + max(mean_rate_adu_s * ts[-2], 0.0) + 1.0)
        pred2 = x_long * ts[-2] / ts[-1]
        transient = ~stuck & (pred2 > 5 * sig2 + 3 * det["robust_sigma_adu"]) & (Y[:, -2] < 0.3 * pred2)
    if n_t >= 2:
        rate, icpt, npts = masked_linear_fit(ts, Y, valid)
        # a pixel saturated from the second exposure on: rate from the first valid point (through zero)
        one = np.isnan(rate) & valid.any(axis=1)
        if one.any():
            j = np.argmax(valid[one], axis=1)
            rate[one] = Y[one, j] / np.maximum(ts[j], 1e-9)
    else:
        rate = x_long / max(ts[-1], 1e-9)
        icpt = np.zeros_like(rate)
        npts = np.ones(idx.size, int)
    # stuck in the bias frames too: high raw value that the darks do not change
    stuck_bias = np.zeros(0, np.int64)
    keep = np.zeros(0, bool)
    if g["has_master"] and g["cand"].size:
        lvl = g["cand_master"].astype(np.float64)
        spread = np.max(np.abs(g["cand_x"]), axis=1)
        tol = np.maximum(5 * math.sqrt(1.5) * read_noise_adu, 0.1 * (lvl - bias_level_adu))
        keep = spread <= tol
        stuck_bias = g["cand"][keep]
        stuck |= np.isin(idx, stuck_bias)
    excess = rate - mean_rate_adu_s
    hot = ~stuck & ~transient & np.isfinite(excess) & (excess > 0)
    t2 = np.full(idx.size, np.nan)
    t2[hot] = bias_level_adu / excess[hot]
    fits = fit_lifetimes(t2[hot])
    sat_any = (~valid).any(axis=1)
    # detection limit in t_double: the smallest detectable excess rate at the longest exposure
    r_min = (det["threshold_adu"] - mean_rate_adu_s * ts[-1]) / ts[-1]
    r_min = max(r_min, det["robust_sigma_adu"] / ts[-1])
    stuck_all = np.union1d(idx[stuck], stuck_bias)
    res: dict = {
        "detection": det,
        "n_outliers": int(idx.size),
        "n_hot": int(hot.sum()),
        "n_stuck": int(stuck_all.size),
        "n_stuck_in_bias": int(stuck_bias.size),
        "n_stuck_outliers": int(stuck.sum()),
        "n_transient": int(transient.sum()),
        "n_not_growing": int((~stuck & ~transient & ~hot).sum()),
        "n_saturated_somewhere": int(sat_any.sum()),
        "fraction_of_pixels": float(idx.size / (h * w)),
        "t_double_definition": ("t_double = B / r where B is the bias level in ADU and r the pixel's dark rate "
                                "in ADU/s in excess of the mean dark rate (straight-line fit of the pixel's "
                                "bias-subtracted value against exposure time over all darks): the exposure "
                                "at which the pixel's value doubles its zero-exposure level (thesis eq. 38, "
                                "our reading)"),
        "bias_level_adu": float(bias_level_adu),
        "mean_rate_adu_per_s": float(mean_rate_adu_s),
        "t_double_detection_limit_s": float(bias_level_adu / r_min) if r_min > 0 else math.inf,
        "fits": fits,
    }
    if hot.any():
        tt = t2[hot]
        res["t_double_s"] = _summary(tt)
        res["excess_rate_adu_per_s"] = _summary(excess[hot])
        lo, hi = math.log10(tt.min()), math.log10(tt.max())
        if hi - lo < 0.5:
            lo, hi = lo - 0.25, hi + 0.25
        edges = np.logspace(lo, hi, 41)
        counts, _ = np.histogram(tt, bins=edges)
        res["plot_data"] = {"t_double_hist": {"edges": edges.tolist(), "counts": counts.tolist()}}
    if stuck_all.size:
        # raw value in the longest dark: bias-subtracted value + master (the bias level without a master)
        vals = {}
        m_out = g["master"] if g["has_master"] else np.full(idx.size, bias_level_adu, np.float32)
        for i, v in zip(idx[stuck], (g["Y"][stuck, -1] + m_out[stuck]).astype(np.float64)):
            vals[int(i)] = v
        if keep.size:
            for i, v in zip(g["cand"][keep], (g["cand_x"][keep, -1] + g["cand_master"][keep]).astype(np.float64)):
                vals.setdefault(int(i), v)
        raw_long = np.array([vals[int(i)] for i in stuck_all], np.float64)
        res["stuck_raw_level_adu"] = _summary(raw_long)
    order = np.argsort(-np.nan_to_num(rate, nan=-np.inf))[:20]
    cls = np.where(stuck, "stuck", np.where(transient, "transient", np.where(hot, "hot", "not_growing")))
    res["brightest"] = [{"x": int(idx[i] % w), "y": int(idx[i] // w), "class": str(cls[i]),
                         "rate_adu_per_s": float(rate[i]), "value_longest_adu": float(x_long[i]),
                         "t_double_s": float(t2[i]), "points_fitted": int(npts[i])} for i in order]
    if keep_per_pixel:
        res["_per_pixel"] = {"index": idx, "t_double_s": t2, "hot": hot, "stuck": stuck, "x_long": x_long,
                             "rate": rate, "intercept": icpt, "shape": (h, w)}
    return res


def _summary(v: np.ndarray) -> dict:
    v = np.asarray(v, dtype=np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return {"n": 0}
    p = np.percentile(v, [0, 5, 50, 95, 100])
    return {"n": int(v.size), "min": float(p[0]), "p5": float(p[1]), "median": float(p[2]), "p95": float(p[3]),
            "max": float(p[4]), "mean": float(v.mean())}


def _fit_levels(ts, rows, key="inlier_mean_adu", bias_level=None):
    y = [r[key] for r in rows]
    if len(ts) >= 2:
        return linear_fit(ts, y)
    # one exposure time: the line through the bias level (t = 0)
    f = linear_fit([0.0, ts[0]], [bias_level, y[0]])
    f["note"] = "one dark exposure time: line through the bias level at t = 0"
    return f


def _sat_level(g: Sequence[Frame]) -> float:
    return min(f.saturation_adu for f in g)


def _dark_row(t, g, img_s, x_s, count_thr: dict, nsigma) -> dict:
    cs = clipped_stats(img_s, sigma=3.0)
    xcs = clipped_stats(x_s, sigma=3.0)
    temps = [f.temperature_c for f in g if f.temperature_c is not None]
    return {"exposure_s": float(t), "n_frames": len(g), "files": [f.path for f in g],
            "median_adu": float(np.median(img_s)), "inlier_mean_adu": cs["mean"],
            "inlier_std_adu": cs["std"], "mean_all_adu": float(img_s.mean(dtype=np.float64)),
            "n_clipped": cs["n_rejected"],
            "dark_signal_inlier_mean_adu": xcs["mean"], "dark_robust_sigma_adu": xcs["std"],
            "count_above_bias_adu": {f"{thr:g}": int(n) for thr, n in count_thr.items()},
            f"count_above_{nsigma:g}_sigma": None, "_xcs": xcs,
            "temperature_c": float(np.mean(temps)) if temps else None}


def _holdout_setup(ts, rows, hold, bias_level, read_noise_adu, nsigma, x_samples, master_thr):
    """The fit on the exposures not held out, and the outlier gather of its longest exposure."""
    hold = sorted(float(h) for h in hold)
    fit_sel = np.array([not any(np.isclose(t, h) for h in hold) for t in ts])
    if fit_sel.sum() < 2 or (~fit_sel).sum() < 1:
        return None
    tf = ts[fit_sel]
    fit = _fit_levels(tf, [r for r, s in zip(rows, fit_sel) if s])
    sel = list(np.flatnonzero(fit_sel))
    det = _detection(x_samples[sel[-1]], nsigma)
    return {"hold": hold, "fit_sel": fit_sel, "tf": tf, "fit": fit, "sel": sel, "det": det,
            "n_pp": {float(t): {} for t, s in zip(ts, fit_sel) if not s}}


def _holdout_band(H: dict, xs, sats, thresholds) -> None:
    """Per-pixel extrapolation of one band (each pixel's line on the fitted darks) to the held-out exposures."""
    xs_f = [xs[j] for j in H["sel"]]
    sm_f = [sats[j] for j in H["sel"]]
    w = xs_f[0].shape[1]
    rows_per = max(1, 1_000_000 // w)
    for r0 in range(0, xs_f[0].shape[0], rows_per):
        Yc = np.stack([xx[r0:r0 + rows_per].ravel() for xx in xs_f], axis=1)
        vc = ~np.stack([mm[r0:r0 + rows_per].ravel() for mm in sm_f], axis=1)
        b, a, _ = masked_linear_fit(H["tf"], Yc, vc)
        for t, acc in H["n_pp"].items():
            p = a + b * t
            p = np.where(np.isnan(p), np.inf, p)  # saturated in every fitted dark: above any threshold
            for thr in thresholds:
                acc[thr] = acc.get(thr, 0) + int(np.count_nonzero(p > thr))


def _holdout_result(H, ts, rows, g_res, shape, bias_level, read_noise_adu, thresholds, nsigma) -> dict:
    fit, tf = H["fit"], H["tf"]
    hp = hot_pixels_from_gathered(tf, g_res, H["det"], shape, fit["slope"], bias_level, nsigma, read_noise_adu,
                                  keep_per_pixel=True)
    pp = hp.pop("_per_pixel")
    preds = []
    for t, r, s in zip(ts, rows, H["fit_sel"]):
        if s:
            continue
        pred_level = fit["intercept"] + fit["slope"] * t
        meas_level = r["inlier_mean_adu"]
        pred_sig = fit["slope"] * t
        meas_sig = meas_level - fit["intercept"]
        se = math.sqrt(max(fit["cov"][0][0] + 2 * t * fit["cov"][0][1] + t * t * fit["cov"][1][1], 0.0)) \
            if fit["dof"] > 0 else math.nan
        entry = {"exposure_s": float(t),
                 "mean_adu": {"predicted": pred_level, "predicted_se": se, "measured": meas_level,
                              "rel_error": (pred_level - meas_level) / meas_level},
                 "dark_signal_adu": {"predicted": pred_sig, "measured": meas_sig,
                                     "rel_error": (pred_sig - meas_sig) / meas_sig if meas_sig else math.nan},
                 "count_above_bias_adu": {}}
        for thr in thresholds:
            n_pp = H["n_pp"][float(t)][thr]
            tau = bias_level / (thr / t - fit["slope"]) if thr / t > fit["slope"] else math.inf
            stuck_above = int(np.count_nonzero(pp["stuck"] & (pp["x_long"] > thr)))
            n_hot = hp["n_hot"]
            law = hp["fits"].get("preferred")
            model = n_hot * (lifetime_cdf(hp["fits"], tau) if law else math.nan) + stuck_above
            emp = int(np.count_nonzero(pp["hot"] & (pp["t_double_s"] < tau))) + stuck_above
            meas = r["count_above_bias_adu"][f"{thr:g}"]
            entry["count_above_bias_adu"][f"{thr:g}"] = {
                "measured": meas, "per_pixel_extrapolation": n_pp, "t_double_law": model,
                "t_double_empirical": emp, "tau_s": tau,
                "tau_within_detection_limit": bool(tau <= hp["t_double_detection_limit_s"]),
                "rel_error_per_pixel": (n_pp - meas) / meas if meas else math.nan,
                "rel_error_t_double_law": (model - meas) / meas if meas else math.nan}
        preds.append(entry)
    return {"exposures_s": [float(t) for t, s in zip(ts, H["fit_sel"]) if not s], "fit_exposures_s": tf.tolist(),
            "fit": {k: fit[k] for k in ("intercept", "slope", "intercept_se", "slope_se", "dof")},
            "hot_pixels_fit": {"n_hot": hp["n_hot"], "n_stuck": hp["n_stuck"], "fits": hp["fits"],
                               "detection": hp["detection"]},
            "predictions": preds}


def analyze_darks(groups, ts, P: dict, bias_res: dict, gain: float, nsigma: float, thresholds: Sequence[float],
                  holdout_exposures, B: _Bands, master_sample: np.ndarray) -> tuple[dict, dict, list[str]]:
    """Dark level vs exposure (thesis regression), DSNU, hot pixels, leave-one-out and hold-out.

    The statistics come from the regular subsamples of the first pass (``P``); the counts above the
    thresholds, the outliers and the hold-out's per-pixel extrapolation from one more pass over the darks.
    """
    warns: list[str] = []
    S = P["samples"]
    bias_level = bias_res["level_median_adu"]
    read = bias_res["read_noise_adu"]
    img_s = [_mean32([S[id(f)] for f in g]) for g in groups]
    x_s = [im - master_sample for im in img_s]
    rows = [_dark_row(t, g, im, x, c, nsigma) for t, g, im, x, c in zip(ts, groups, img_s, x_s, P["counts"])]
    fit = _fit_levels(ts, rows, "inlier_mean_adu", bias_level)
    if len(ts) < 2:
        warns.append("darks at one exposure time only: dark rate from the line through the bias level")
    fit_med = _fit_levels(ts, rows, "median_adu", bias_level)
    fit_all = _fit_levels(ts, rows, "mean_all_adu", bias_level)
    for r in rows:
        r["predicted_inlier_mean_adu"] = fit["intercept"] + fit["slope"] * r["exposure_s"]
        r["residual_adu"] = r["inlier_mean_adu"] - r["predicted_inlier_mean_adu"]
    rate, rate_se = fit["slope"], fit["slope_se"]
    if holdout_exposures is None:
        holdout_exposures = [float(ts[-1])] if len(ts) >= 3 else []
    unknown = [h for h in holdout_exposures if not np.isclose(ts, float(h)).any()]
    if unknown:
        raise DetectorError(f"hold-out exposure(s) {unknown} s not among the darks",
                            key="holdout_exposures", expected="one of " + ", ".join(f"{t:g}" for t in ts))
    # the pass over the darks: counts above n sigma, outliers of the longest dark, hold-out extrapolation
    mcs = clipped_stats(master_sample, sigma=3.0)
    mthr = mcs["median"] + nsigma * mcs["std"]
    det = _detection(x_s[-1], nsigma)
    h, w = B.shape
    main = _OutlierGather(range(len(ts)), det["threshold_adu"], mthr, w)
    H = _holdout_setup(ts, rows, holdout_exposures, bias_level, read, nsigma, x_s, mthr) \
        if len(holdout_exposures) else None
    hold_g = _OutlierGather(H["sel"], H["det"]["threshold_adu"], mthr, w) if H else None
    n_sig = [0] * len(ts)
    sat_lvl = [_sat_level(g) for g in groups]
    for r0, r1 in B.run("darks: outliers and hold-out"):
        m = P["master"].rows(r0, r1)
        imgs = [_mean32([f.rows(r0, r1) for f in g]) for g in groups]
        xs = [im - m for im in imgs]
        sats = [np.zeros(im.shape, bool) if not math.isfinite(s) else im >= s - 0.5 for im, s in zip(imgs, sat_lvl)]
        del imgs
        for j, (x, r) in enumerate(zip(xs, rows)):
            n_sig[j] += int(np.count_nonzero(x > r["_xcs"]["median"] + nsigma * r["_xcs"]["std"]))
        main.add(r0, xs, sats, m)
        if H:
            hold_g.add(r0, xs, sats, m)
            _holdout_band(H, xs, sats, thresholds)
    for r, n in zip(rows, n_sig):
        r[f"count_above_{nsigma:g}_sigma"] = n
        del r["_xcs"]
    res: dict = {
        "exposures_s": ts.tolist(),
        "per_exposure": rows,
        "fit": {**{k: fit[k] for k in ("intercept", "slope", "intercept_se", "slope_se", "dof", "residual_std")},
                "model": "inlier_mean_ADU(t) = intercept + slope * t (ordinary least squares over exposures)"},
        "dark_current_adu_per_s": rate,
        "dark_current_adu_per_s_se": rate_se,
        "dark_current_e_per_s": rate * gain,
        "dark_current_e_per_s_se": rate_se * gain,
        "intercept_minus_bias_adu": fit["intercept"] - bias_res["level_mean_adu"],
        "rate_from_median_adu_per_s": fit_med["slope"],
        "rate_from_mean_all_pixels_adu_per_s": fit_all["slope"],
    }
    # DSNU from the longest dark: spatial variance left after read noise (frame and master bias) and shot noise
    xl = rows[-1]
    d_sig = xl["dark_signal_inlier_mean_adu"]
    var_model = (read ** 2 + max(d_sig, 0) / gain) / xl["n_frames"] + read ** 2 / max(bias_res["n_frames"], 1)
    var_dsnu = xl["dark_robust_sigma_adu"] ** 2 - var_model
    n_pix = min(h * w, MAX_STAT_PIXELS)
    var_se = xl["dark_robust_sigma_adu"] ** 2 * math.sqrt(2.0 / n_pix)
    res["dsnu"] = {"exposure_s": xl["exposure_s"], "dark_signal_adu": d_sig,
                   "spatial_std_adu": math.sqrt(var_dsnu) if var_dsnu > 0 else 0.0,
                   "sigma_rel": (math.sqrt(var_dsnu) / d_sig) if var_dsnu > 0 and d_sig > 0 else 0.0,
                   "spatial_var_adu2": var_dsnu, "spatial_var_se_adu2": var_se,
                   "significant": bool(var_dsnu > 3 * var_se),
                   "method": "robust std of (longest dark - master bias) with the temporal noise of both (read "
                             "noise, dark shot noise = signal/gain) removed in quadrature, over the dark signal"}
    hot = hot_pixels_from_gathered(ts, main.result(), det, B.shape, rate, bias_level, nsigma, read)
    # leave-one-out
    loo = []
    if len(ts) >= 3:
        for i in range(len(ts)):
            sel = np.arange(len(ts)) != i
            f = linear_fit(ts[sel], [rows[j]["inlier_mean_adu"] for j in np.flatnonzero(sel)])
            p = f["intercept"] + f["slope"] * ts[i]
            m_ = rows[i]["inlier_mean_adu"]
            loo.append({"exposure_s": float(ts[i]), "predicted_adu": p, "measured_adu": m_,
                        "rel_error": (p - m_) / m_, "dark_signal_rel_error":
                        (f["slope"] * ts[i] - (m_ - f["intercept"])) / (m_ - f["intercept"])
                        if m_ != f["intercept"] else math.nan})
    res["leave_one_out"] = loo
    if not len(holdout_exposures):
        res["holdout"] = {"note": "no hold-out"}
    elif H is None:
        res["holdout"] = {"note": "hold-out needs at least two fitted and one held-out exposure time",
                          "exposures_s": sorted(float(x) for x in holdout_exposures)}
    else:
        res["holdout"] = _holdout_result(H, ts, rows, hold_g.result(), B.shape, bias_level, read, thresholds,
                                         nsigma)
    res["plot_data"] = {"t": ts.tolist(), "inlier_mean": [r["inlier_mean_adu"] for r in rows],
                        "median": [r["median_adu"] for r in rows], "mean_all": [r["mean_all_adu"] for r in rows],
                        "counts": {f"{thr:g}": [r["count_above_bias_adu"][f"{thr:g}"] for r in rows]
                                   for thr in thresholds}}
    temps = [r["temperature_c"] for r in rows if r["temperature_c"] is not None]
    res["temperature_c"] = float(np.mean(temps)) if temps else None
    return res, hot, warns


# ============================================================================================
# flats: photon transfer, PRNU, vignetting
# ============================================================================================

def photon_transfer(f0: np.ndarray, f1: np.ndarray, master: np.ndarray, read_noise_adu: float,
                    tiles: int = 4) -> dict:
    """Gain from a flat pair by photon transfer (Janesick 2007, eq. 4.7): ``K = S / (var(diff)/2 - s_r^2)``.

    ``S`` is the mean bias-subtracted signal [ADU]; the second flat is scaled to the first's mean before the
    difference, which cancels PRNU and illumination and leaves ``2 (S/K + s_r^2)``. Computed on the whole
    frame and on ``tiles x tiles`` tiles (the tiles' spread gives the standard error). Every statistic is
    taken on the regular subsample (at most ``MAX_STAT_PIXELS`` values for the frame, that divided by the
    number of tiles for each tile) (:func:`detector.stats.subsample`) of the frame or tile, so the work is
    done by :func:`photon_transfer_samples` on those subsamples.
    """
    a = f0.astype(np.float64) - master
    b = f1.astype(np.float64) - master
    tl = _tiles(a.shape, tiles)
    nt = MAX_STAT_PIXELS // len(tl)
    return photon_transfer_samples(subsample(a), subsample(b),
                                   [subsample(a[y0:y1, x0:x1], nt) for y0, y1, x0, x1 in tl],
                                   [subsample(b[y0:y1, x0:x1], nt) for y0, y1, x0, x1 in tl], a.size, read_noise_adu)


def photon_transfer_samples(a: np.ndarray, b: np.ndarray, ta: Sequence[np.ndarray], tb: Sequence[np.ndarray],
                            n_pixels: int, read_noise_adu: float) -> dict:
    """:func:`photon_transfer` on the regular subsamples of the two bias-subtracted flats (``a``, ``b``, float64)
    and of their tiles (``ta``, ``tb``); ``n_pixels`` the frame's pixel count (statistical error)."""

    def one(aa, bb):
        sa, sb = clipped_stats(aa, 5.0)["mean"], clipped_stats(bb, 5.0)["mean"]
        s = sa / sb
        d = aa - s * bb
        var = clipped_stats(d, 5.0)["std"] ** 2 / (1 + s * s)
        sig = 0.5 * (sa + s * sb)
        shot = var - read_noise_adu ** 2
        return sig, var, shot, s

    sig, var, shot, s = one(a, b)
    ks, pts = [], []
    for aa, bb in zip(ta, tb):
        ts_, tv, tsh, _ = one(aa, bb)
        pts.append([ts_, tv])
        if tsh > 0:
            ks.append(ts_ / tsh)
    K = sig / shot if shot > 0 else math.nan
    n = n_pixels
    se_stat = K * math.sqrt(2 / n) * var / shot if shot > 0 else math.nan
    se_tiles = float(np.std(ks, ddof=1) / math.sqrt(len(ks))) if len(ks) > 2 else math.nan
    return {"signal_adu": sig, "variance_adu2": var, "shot_variance_adu2": shot, "scale_second_flat": s,
            "gain_e_per_adu": K, "gain_se_statistical": se_stat, "gain_se_tiles": se_tiles,
            "gain_se": float(np.nanmax([se_stat, se_tiles])), "tile_gains": ks,
            "signal_e": sig * K if shot > 0 else math.nan,
            "plot_data": {"tiles_signal_variance": pts, "read_variance_adu2": read_noise_adu ** 2}}


def _smoothed_bands(rows_fn, shape, smooth_px: float, B: _Bands, label: str):
    """Yield ``(r0, r1, f, smooth)`` band by band: ``f`` the rows ``r0:r1`` of the image ``rows_fn(a, b)``
    gives, ``smooth`` those rows of its Gaussian smoothing (sigma ``smooth_px``, mode "nearest"), computed on
    the band plus :func:`detector.calbands.halo_rows` rows either side: the same values as filtering the
    whole image (the filter never reaches past the halo)."""
    h = shape[0]
    halo = halo_rows(smooth_px)
    for r0, r1 in B.run(label):
        a, b = max(0, r0 - halo), min(h, r1 + halo)
        f, clean = rows_fn(a, b)
        sm = ndimage.gaussian_filter(clean, smooth_px, mode="nearest")
        yield r0, r1, f[r0 - a:r1 - a], sm[r0 - a:r1 - a]


def prnu_and_vignetting(mean_flat, temporal_var_adu2: float, smooth_px: float = 16.0, box_frac: float = 0.1,
                        *, sample: np.ndarray | None = None, B: _Bands | None = None) -> dict:
    """PRNU (small-scale fixed pattern of a bias-subtracted mean flat) and large-scale vignetting.

    The flat is divided by its Gaussian-smoothed self (sigma ``smooth_px`` pixels, outliers replaced by the
    median first): large-scale illumination and vignetting go, the pixel-to-pixel response stays.
    ``PRNU = sqrt(std(ratio)^2 - temporal_var / S^2)`` (EMVA 1288, the temporal noise of the averaged flat
    removed in quadrature); border of ``2 smooth_px`` excluded. Vignetting: medians of the smoothed flat in
    the four corner boxes (``box_frac`` of the frame's sides) over the centre box.

    ``mean_flat`` is a 2-D array or a ``rows(a, b)`` source of float64 rows; ``sample`` its regular
    subsample (computed when not given); ``B`` the bands (one band for an array).
    """
    src = as_rows(mean_flat)
    h, w = src.shape
    B = B or _Bands((h, w), band_pixels=h * w)
    if sample is None:
        sample = subsample(np.asarray(src.rows(0, h), dtype=np.float64))
    cs = clipped_stats(sample, 5.0)

    def rows_fn(a, b):
        f = np.asarray(src.rows(a, b), dtype=np.float64)
        return f, np.where((f < cs["lo"] - 5 * cs["std"]) | (f > cs["hi"] + 5 * cs["std"]), cs["median"], f)

    bd = int(2 * smooth_px)
    inner = (bd, h - bd, bd, w - bd) if h > 4 * bd and w > 4 * bd else (0, h, 0, w)
    S_in = Sampler((h, w), region=inner)
    bh, bw = max(1, int(h * box_frac)), max(1, int(w * box_frac))
    cy, cx = h // 2 - bh // 2, w // 2 - bw // 2
    boxes = {"centre": (cy, cy + bh, cx, cx + bw), "first_row_first_col": (0, bh, 0, bw),
             "first_row_last_col": (0, bh, w - bw, w), "last_row_first_col": (h - bh, h, 0, bw),
             "last_row_last_col": (h - bh, h, w - bw, w)}
    G = Gather()
    step = max(1, max(h, w) // 64)
    thumb, smin = [], math.inf
    for r0, r1, f, sm in _smoothed_bands(rows_fn, (h, w), smooth_px, B, "flat: PRNU and vignetting"):
        G.add("ratio", S_in.take(r0, f) / S_in.take(r0, sm))
        for k, (y0, y1, x0, x1) in boxes.items():
            a, b = max(y0, r0), min(y1, r1)
            if a < b:
                G.add(k, sm[a - r0:b - r0, x0:x1].flatten())
        smin = min(smin, float(sm.min()))
        first = (-r0) % step
        thumb.append(sm[first::step, ::step].copy())  # a copy: a view would keep the whole band alive
    rs = clipped_stats(G.get("ratio"), 5.0)
    S = cs["median"]
    var_rel = rs["std"] ** 2 - temporal_var_adu2 / (S * S)
    centre = float(np.median(G.get("centre")))
    ratios = {k: float(np.median(G.get(k))) / centre for k in boxes if k != "centre"}
    return {"prnu_rel": math.sqrt(var_rel) if var_rel > 0 else 0.0, "ratio_std_raw": rs["std"],
            "temporal_rel_std": math.sqrt(temporal_var_adu2) / S, "smoothing_sigma_px": smooth_px,
            "vignetting": {"corner_over_centre": ratios,
                           "corner_over_centre_mean": float(np.mean(list(ratios.values()))),
                           "min_over_centre": float(smin / centre), "box_px": [bw, bh]},
            "plot_data": {"smooth_map_rel": (np.concatenate(thumb) / centre).tolist()}}


class _MeanFlatRows:
    """Rows of the bias-subtracted mean flat ``0.5 (f0 + s f1) - master`` [ADU, float64]."""

    def __init__(self, f0: Frame, f1: Frame, master, s: float):
        self.f0, self.f1, self.master, self.s = f0, f1, master, s
        self.shape = tuple(f0.shape)

    def rows(self, a, b):
        # 0.5 (f0 + s f1) - master, in place (the same operations in the same order)
        out = self.f0.rows(a, b).astype(np.float64)
        t = self.f1.rows(a, b).astype(np.float64)
        t *= self.s
        out += t
        del t
        out *= 0.5
        out -= self.master.rows(a, b)
        return out


def analyze_flats(frames: Sequence[Frame], P: dict, bias_res: dict, B: _Bands,
                  master_sample: np.ndarray) -> tuple[dict, list[str]]:
    """Photon transfer (from the first pass's subsamples), PRNU and vignetting (one band pass)."""
    warns: list[str] = []
    if len(frames) != 2:
        raise DetectorError(f"{len(frames)} flat frames given", key="flat",
                            expected="exactly two flats of the same illumination and exposure")
    f0, f1 = frames
    read = bias_res["read_noise_adu"]
    S = P["samples"]
    a = S[id(f0)].astype(np.float64) - master_sample
    b = S[id(f1)].astype(np.float64) - master_sample
    ta = (t.astype(np.float64) - m for t, m in zip(P["tile_samples"][0], P["tile_master"]))
    tb = (t.astype(np.float64) - m for t, m in zip(P["tile_samples"][1], P["tile_master"]))
    pt = photon_transfer_samples(a, b, ta, tb, f0.shape[0] * f0.shape[1], read)
    s = pt["scale_second_flat"]
    mf_sample = 0.5 * (S[id(f0)].astype(np.float64) + s * S[id(f1)].astype(np.float64)) - master_sample
    temporal = pt["variance_adu2"] / 2 + read ** 2 / max(bias_res["n_frames"], 1)
    pv = prnu_and_vignetting(_MeanFlatRows(f0, f1, P["master"], s), temporal, sample=mf_sample, B=B)
    sat = min(f.saturation_adu for f in frames)
    raw_med = float(np.median(S[id(f0)]))
    if math.isfinite(sat) and raw_med > 0.8 * sat:
        warns.append(f"flats are at {raw_med:.0f} ADU, near saturation {sat:.0f}: photon transfer is biased")
    res = {"files": [f.path for f in frames], "exposure_s": [f.exptime_s for f in frames],
           "median_raw_adu": [raw_med, float(np.median(S[id(f1)]))],
           "signal_adu": pt["signal_adu"], "photon_transfer": pt, "prnu_rel": pv["prnu_rel"],
           "prnu": {k: v for k, v in pv.items() if k not in ("vignetting",)},
           "vignetting": pv["vignetting"],
           "temperature_c": [f.temperature_c for f in frames],
           "note": "dark signal of the flats is not subtracted (only the master bias)"}
    return res, warns


# ============================================================================================
# top level
# ============================================================================================

def characterize(bias_paths: Sequence, dark_paths: Sequence, flat_paths: Sequence | None = None, *,
                 holdout_exposures: Sequence[float] | None = None, hot_sigma: float = 5.0,
                 count_thresholds_adu: Sequence[float] = (100.0, 1000.0), seed: int = 0,
                 band_pixels: int | None = None, progress=None) -> dict:
    """Characterise a camera from its calibration frames (thesis sections 3.6.5 and 3.7.1).

    Parameters
    ----------
    bias_paths : list of paths
        Bias frames (>= 1; >= 2 for the temporal read noise).
    dark_paths : list of paths
        Dark frames with ``EXPTIME``/``EXPOSURE`` [s]; two or more exposure times for the dark-rate fit,
        three or more for leave-one-out and hold-out predictions.
    flat_paths : list of two paths, optional
        A flat pair for photon transfer (gain), PRNU and vignetting.
    holdout_exposures : list of float [s], optional
        Dark exposure times left out of a second fit and predicted from it. Default: the longest one
        (when there are three or more exposure times). ``[]`` switches the hold-out off.
    hot_sigma : float
        Hot-pixel detection threshold in robust sigma of the longest bias-subtracted dark.
    count_thresholds_adu : list of float [ADU]
        Thresholds above the bias (pixel by pixel) for the per-exposure pixel counts.
    seed : int
        Seed of the normality tests' subsample and dither.
    band_pixels : int, optional
        Pixels per row band (default :data:`detector.calbands.BAND_PIXELS`; a frame no larger is one band).
    progress : callable(label, done, total), optional
        Called as every band pass advances (the CLI draws a progress bar).

    Returns
    -------
    dict (JSON-serialisable): ``frame``, ``gain``, ``bias``, ``dark``, ``hot_pixels``, ``flat`` (or None),
    ``warnings``; ``*.plot_data`` entries feed :func:`detector.calplots.write_plots`.

    Memory: the frames are read band by band (:class:`detector.calbands.FitsRows`); what is kept is one
    regular subsample of every frame (at most ``MAX_STAT_PIXELS`` values each), the master bias in a float32
    temporary file, the outlier pixels and per-band temporaries; running out of memory anyway is a
    :class:`DetectorError`.
    """
    bias_paths, dark_paths = list(bias_paths or []), list(dark_paths or [])
    flat_paths = list(flat_paths or [])
    if not bias_paths:
        raise DetectorError("no bias frame given", key="bias", expected="one or more bias FITS files")
    if not dark_paths:
        raise DetectorError("no dark frame given", key="dark", expected="one or more dark FITS files")
    check_sigma(hot_sigma)
    if flat_paths and len(flat_paths) != 2:
        raise DetectorError(f"{len(flat_paths)} flat frames given", key="flat",
                            expected="exactly two flats of the same illumination and exposure")
    try:
        with open_frame_sets(bias_paths, dark_paths, flat_paths) as (bias, darks, flats):
            return _characterize(bias, darks, flats, holdout_exposures, hot_sigma, count_thresholds_adu, seed,
                                 _Bands(bias[0].shape, band_pixels, progress))
    except MemoryError:
        raise DetectorError("out of memory while characterising the frames", key="bias/dark/flat",
                            file=bias_paths[0],
                            expected="more free memory, or fewer/smaller frames (see docs/detector.md)") from None


@contextmanager
def open_frame_sets(bias_paths, dark_paths, flat_paths):
    """The bias, dark and flat frames opened lazily (read band by band), darks and flats checked against the
    first bias's shape; yields (bias, darks, flats) and closes every frame on the way out."""
    opened: list[Frame] = []
    try:
        bias = read_frames(bias_paths, "bias", need_exptime=False, lazy=True)
        opened += bias
        shape, ref = bias[0].shape, bias[0].path
        darks = read_frames(dark_paths, "dark", need_exptime=True, shape=shape, shape_file=ref, lazy=True)
        opened += darks
        flats = read_frames(flat_paths, "flat", need_exptime=False, shape=shape, shape_file=ref, lazy=True) \
            if flat_paths else []
        opened += flats
        yield bias, darks, flats
    finally:
        for f in opened:
            f.close()


def _characterize(bias, darks, flats, holdout_exposures, hot_sigma, count_thresholds_adu, seed, B: _Bands) -> dict:
    rng = np.random.default_rng(seed)
    thresholds = [float(t) for t in count_thresholds_adu]
    for role, fr in (("bias", bias), ("dark", darks), ("flat", flats)):
        for f in fr:
            f.checks["role"] = role
    # darks without two exposure times are refused before reading any pixel
    _check_dark_times(darks)
    ts, groups = _group_by_time(darks)
    P = _first_pass(bias, darks, flats, groups, B, thresholds)
    try:
        sanity_checks(bias, darks, flats)
        warns: list[str] = []
        bias_res, _, w = analyze_bias(bias, rng, P["samples"], _column_medians(P["master"]), P["row_median"])
        warns += w
        master_s = _mean32([P["samples"][id(f)] for f in bias])
        flat_res = None
        if flats:
            flat_res, w = analyze_flats(flats, P, bias_res, B, master_s)
            warns += w
        g_hdr, g_key, g_file = header_gain(bias + darks + flats)
        pt_gain = flat_res["photon_transfer"]["gain_e_per_adu"] if flat_res else math.nan
        pt_se = flat_res["photon_transfer"]["gain_se"] if flat_res else math.nan
        if flat_res and math.isfinite(pt_gain) and pt_gain > 0:
            # the camera's own photon transfer (Janesick 2007, eq. 4.7) over a header's nominal value; a header
            # value beyond 3 standard errors of it is said, never hidden
            gain, source = pt_gain, "photon transfer (flat pair)"
            if g_hdr is not None and math.isfinite(pt_se) and abs(pt_gain - g_hdr) > 3 * pt_se:
                warns.append(f"header {g_key} = {g_hdr:g} e-/ADU ({g_file}) differs from the photon-transfer gain "
                             f"{pt_gain:.4g} +- {pt_se:.2g} e-/ADU by {abs(pt_gain - g_hdr) / pt_se:.1f} standard "
                             "errors: the measured gain is adopted")
        elif g_hdr is not None:
            gain, source = g_hdr, f"header {g_key} ({g_file})"
        else:
            gain, source = 1.0, "default 1.0"
            warns.append("no gain in the headers (EGAIN/GAIN) and no flat pair: gain set to 1.0 e-/ADU, so every "
                         "value in e- is really in ADU")
        gain_res = {"adopted_e_per_adu": gain, "source": source, "header_e_per_adu": g_hdr, "header_card": g_key,
                    "photon_transfer_e_per_adu": pt_gain if flat_res else None,
                    "photon_transfer_se": flat_res["photon_transfer"]["gain_se"] if flat_res else None}
        if flat_res and g_hdr is not None and math.isfinite(pt_gain):
            gain_res["photon_transfer_over_header"] = pt_gain / g_hdr
        bias_res["read_noise_e"] = bias_res["read_noise_adu"] * gain
        bias_res["read_noise_se_e"] = bias_res["read_noise_se_adu"] * gain
        dark_res, hot_res, w = analyze_darks(groups, ts, P, bias_res, gain, hot_sigma, thresholds,
                                             holdout_exposures, B, master_s)
        warns += w
    finally:
        P["master"].close()
    if flat_res:
        ft = [t for t in flat_res["temperature_c"] if t is not None]
        if ft and dark_res["temperature_c"] is not None and abs(np.mean(ft) - dark_res["temperature_c"]) > 2:
            warns.append(f"flats at {np.mean(ft):.1f} C, darks at {dark_res['temperature_c']:.1f} C")
        flat_res["signal_e"] = flat_res["signal_adu"] * gain
    sats = {f.saturation_adu for f in bias + darks + flats}
    h, w_ = B.shape
    header0 = darks[-1].header
    integer = all(bool(np.all(f.checks["head"] == np.floor(f.checks["head"]))) for f in bias + darks)
    frame = {"width": int(w_), "height": int(h), "n_bias": len(bias), "n_dark": len(darks), "n_flat": len(flats),
             "integer_data": integer,
             "saturation_adu": float(min(sats)), "instrument": str(header0.get("INSTRUME", "")).strip() or None,
             "pixel_size_um": _pixel_size(header0), "binning": int(header0.get("XBINNING", 1) or 1),
             "bit_depth": _bit_depth(header0, min(sats)), "band_rows": B.rows}
    result = {"frame": frame, "gain": gain_res, "bias": bias_res, "dark": dark_res, "hot_pixels": hot_res,
              "flat": flat_res, "warnings": warns}
    warns += physical_warnings(result)
    return jsonable(result)


#: the range of ``hot_sigma`` that makes sense: below 2 sigma the normal bulk itself is flagged
SIGMA_RANGE = (2.0, 100.0)


def check_sigma(hot_sigma: float) -> None:
    """``hot_sigma`` within :data:`SIGMA_RANGE` (a threshold of 2 sigma already flags 2.3 % of a normal bulk)."""
    lo, hi = SIGMA_RANGE
    if not (isinstance(hot_sigma, (int, float)) and math.isfinite(hot_sigma) and lo <= hot_sigma <= hi):
        raise DetectorError(f"outlier threshold {hot_sigma!r} sigma", key="sigma",
                            expected=f"a number of robust sigma in [{lo:g}, {hi:g}]")


def _check_dark_times(darks: Sequence[Frame]) -> None:
    t_pos = sorted({float(f.exptime_s) for f in darks if f.exptime_s and f.exptime_s > 0})
    if len(t_pos) < 2:
        all_t = sorted({float(f.exptime_s) for f in darks})
        raise DetectorError(f"darks at {', '.join(f'{t:g}' for t in all_t)} s only", key="dark",
                            expected="darks of at least two different exposure times > 0 s")


def _frame_checks(f: Frame) -> dict:
    """The pass-1 checks of a frame held in memory (:func:`read_frame`)."""
    if "saturated_fraction" not in f.checks:
        q = subsample(f.data, 1_000_000)
        f.checks["saturated_fraction"] = float(np.mean(q >= f.saturation_adu - 0.5)) \
            if math.isfinite(f.saturation_adu) else 0.0
        f.checks["constant"] = bool(np.ptp(f.data) == 0)
        f.checks["first_value"] = float(f.data.flat[0])
    return f.checks


def sanity_checks(bias: Sequence[Frame], darks: Sequence[Frame], flats: Sequence[Frame]) -> None:
    """Refuse calibration sets that cannot give a meaningful answer; one :class:`DetectorError` each.

    Identical frames (the same data twice: the pair difference would be 0), constant frames (an all-zero
    or blank bias), frames mostly (> 50 %) at the ADC saturation, bias frames with an exposure time
    (> 0.01 s), darks without two different exposure times > 0 s, flats of different exposure times.
    Frames read band by band carry these facts from the first pass (``Frame.checks``).
    """
    groups = {"bias": bias, "dark": darks, "flat": flats}
    for role, frames in groups.items():
        for i, a in enumerate(frames):
            ident = a.checks.get("identical_to", "?")
            if ident == "?":  # frames in memory
                ident = next((b.path for b in frames[i + 1:] if a.data.shape == b.data.shape
                              and np.array_equal(a.data, b.data)), None)
            if ident is not None:
                raise DetectorError(f"{role} frame has the same pixels as {ident}", file=a.path,
                                    expected=f"independent {role} exposures (not the same frame twice)")
            c = _frame_checks(a) if a.data is not None else a.checks
            sf = c["saturated_fraction"]
            if sf > 0.5:
                raise DetectorError(f"{role} frame is saturated ({100 * sf:.0f} % of pixels at "
                                    f"{a.saturation_adu:g} ADU)", file=a.path,
                                    expected=f"a {role} frame below the ADC saturation")
            if c["constant"]:
                raise DetectorError(f"{role} frame is constant ({c['first_value']:g} ADU everywhere)",
                                    file=a.path, expected=f"a real {role} exposure (pixels that vary)")
    for f in bias:
        if f.exptime_s is not None and f.exptime_s > 0.01:
            raise DetectorError(f"bias frame has an exposure time of {f.exptime_s:g} s", key="EXPTIME", file=f.path,
                                expected="a bias frame: exposure time 0 s (use it as a dark with --dark)")
    _check_dark_times(darks)
    if flats:
        tf = {f.exptime_s for f in flats}
        if len(tf) > 1:
            raise DetectorError(f"flats of different exposure times ({', '.join(f'{t}' for t in tf)} s)", key="flat",
                                expected="two flats of the same exposure time and illumination")


def physical_warnings(result: dict) -> list[str]:
    """Results outside physical ranges, one sentence each (they go into ``warnings`` of the JSON)."""
    out = []
    b, d, fr = result["bias"], result["dark"], result["frame"]
    if not b.get("read_noise_adu", 0) > 0:
        out.append(f"read noise {b.get('read_noise_adu')} ADU is not positive: the bias frames carry no temporal noise")
    if d["dark_current_adu_per_s"] < 0:
        out.append(f"negative dark current ({d['dark_current_e_per_s']:.4g} e-/s): the darks' level falls with "
                   "exposure (saturated, mislabelled or bias-shifted frames?); the emitted scene uses 0")
    elif d["dark_current_adu_per_s_se"] and d["dark_current_adu_per_s"] < 2 * d["dark_current_adu_per_s_se"]:
        out.append("dark current not significant (below 2 standard errors)")
    hp = result["hot_pixels"]
    n_pix = fr["width"] * fr["height"]
    if hp.get("n_outliers", 0) > 0.1 * n_pix:
        out.append(f"{hp['n_outliers']} outliers ({100 * hp['n_outliers'] / n_pix:.1f} % of the pixels): not a defect "
                   "population (threshold too low, or a gradient/glow in the darks)")
    f = result.get("flat")
    if f:
        k = result["gain"].get("photon_transfer_e_per_adu")
        if k is None or not (isinstance(k, (int, float)) and math.isfinite(k) and k > 0):
            out.append("photon-transfer gain not positive/finite: the flat pair's difference is not shot-noise "
                       "limited (identical, saturated or too faint flats?)")
        if f.get("prnu_rel", 0) > 0.1:
            out.append(f"PRNU {f['prnu_rel']:.3f} above 10 %: not a pixel response (dust, structure?)")
        v = f.get("vignetting", {}).get("corner_over_centre_mean")
        if v is not None and v > 1.1:
            out.append(f"corners {v:.3f} x the centre: brighter corners are not vignetting")
    return out


def _pixel_size(header) -> float | None:
    for k in ("XPIXSZ", "PIXSIZE1", "PIXSIZE"):
        if k in header:
            try:
                v = float(header[k])
                b = float(header.get("XBINNING", 1) or 1)
                return v / b if v > 0 else None
            except (TypeError, ValueError):
                pass
    return None


def _bit_depth(header, saturation) -> int:
    if math.isfinite(saturation) and saturation > 0:
        return int(max(8, min(32, math.ceil(math.log2(saturation + 1)))))
    return 16


# ============================================================================================
# scene emission
# ============================================================================================

def emit_scene_dict(result: dict, preset_hint: str | None = None) -> dict:
    """A TOML-ready scene fragment whose detector reproduces the characterised camera.

    ``[detector]`` starts from a preset (``preset_hint``, or ``"ml11002"``, the CCD preset, by default) and
    overrides what was measured: frame size (``sensor_width_px``/``height`` and ``width``/``height``), pixel
    pitch (header ``XPIXSZ``), gain, bias, read noise, dark current, temperature, bit depth, and a full well no
    lower than the ADC range (``(saturation - bias) x gain``; the full well itself is not measurable from
    these frames). For integer frames the bias is the clipped mean (newtsim's ADC rounds: no offset) and the read
    noise has the quantisation variance (1/12 ADU^2) removed, because newtsim's ADC quantises again.
    ``[exposure]`` is a dark at the longest exposure. ``[effects.hot_pixels]`` carries the count of hot and
    stuck pixels, the preferred time-to-double law and the stuck pixels' median level; ``[effects.dsnu]`` the
    dark-current non-uniformity (only when significant at 3 sigma).

    Parameters
    ----------
    result : dict
        What :func:`characterize` returned (or its JSON read back).
    preset_hint : {"ml11002", "imx411"}, optional
    """
    from .presets import PRESETS

    preset = preset_hint or "ml11002"
    if preset not in PRESETS:
        raise DetectorError(f"unknown preset {preset!r}", key="preset",
                            expected=" or ".join(repr(p) for p in PRESETS))
    base = PRESETS[preset]
    fr, g, b, d, hp = result["frame"], result["gain"], result["bias"], result["dark"], result["hot_pixels"]
    gain = float(g["adopted_e_per_adu"])
    integer = bool(fr.get("integer_data", True))
    # newtsim's ADC rounds (a mid-tread quantiser, detector.chain.adc): a frame of bias B reads B on average,
    # and the quantisation adds 1/12 ADU^2 to the read variance; undo that so a simulated frame reads what was
    # measured
    bias_adu = float(b["level_mean_adu"])
    read_adu2 = float(b["read_noise_adu"]) ** 2 - (1.0 / 12.0 if integer else 0.0)
    read_e = math.sqrt(max(read_adu2, 0.0)) * gain
    det: dict = {"preset": preset}
    if preset == "ml11002":
        det["kind"] = "ccd"
        det["shutter"] = "global"
        det["line_time_s"] = 0.0
    det["sensor_width_px"] = int(fr["width"])
    det["sensor_height_px"] = int(fr["height"])
    det["width"] = int(fr["width"])
    det["height"] = int(fr["height"])
    if fr.get("pixel_size_um"):
        det["pixel_pitch_um"] = float(fr["pixel_size_um"])
    bit_depth = int(fr.get("bit_depth") or base["bit_depth"])
    det["bit_depth"] = bit_depth
    det["gain_e_per_adu"] = round(gain, 4)
    det["bias_adu"] = round(bias_adu, 2)
    det["read_noise_e"] = round(read_e, 3)
    det["dark_current_e_per_s"] = max(0.0, round(float(d["dark_current_e_per_s"]), 5))
    sat = fr.get("saturation_adu")
    adc_well = ((min(float(sat), 2 ** bit_depth - 1) if sat else 2 ** bit_depth - 1) - bias_adu) * gain
    det["full_well_e"] = round(max(float(base["full_well_e"]), adc_well), 0)
    if d.get("temperature_c") is not None:
        det["temperature_c"] = round(float(d["temperature_c"]), 2)
    if fr.get("instrument"):
        det["name"] = str(fr["instrument"])
    scene: dict = {"detector": det,
                   "exposure": {"time_s": float(max(d["exposures_s"])), "frame": "dark"},
                   "effects": {}}
    fits = hp.get("fits", {})
    law = fits.get("preferred")
    n_def = int(hp.get("n_hot", 0)) + int(hp.get("n_stuck", 0))
    if n_def > 0 and law:
        hot = {"count": n_def, "law": law}
        if law == "weibull":
            hot["weibull_shape"] = round(float(fits["weibull"]["shape"]), 4)
            hot["scale_s"] = round(float(fits["weibull"]["scale_s"]), 3)
        else:
            hot["scale_s"] = round(float(fits["exponential"]["scale_s"]), 3)
        hot["stuck_fraction"] = round(int(hp.get("n_stuck", 0)) / n_def, 5)
        lvl = (hp.get("stuck_raw_level_adu") or {}).get("median")
        if hp.get("n_stuck") and lvl is not None:
            hot["stuck_value_adu"] = round(float(lvl), 1)
        scene["effects"]["hot_pixels"] = hot
    sig = float(d.get("dsnu", {}).get("sigma_rel") or 0.0)
    if sig > 0 and d.get("dsnu", {}).get("significant", True):
        scene["effects"]["dsnu"] = {"sigma": round(min(sig, 5.0), 4), "law": "lognormal"}
    return scene


# ============================================================================================
# the camera itself: per-pixel maps (the "digital twin")
# ============================================================================================

def _robust_mean_1d(a: np.ndarray, axis: int, centre: float, sigma: float, nsig: float = 5.0) -> np.ndarray:
    """Mean along ``axis`` of the values within ``centre +- nsig sigma`` (the level where none is)."""
    keep = np.abs(a - centre) <= nsig * sigma
    n = keep.sum(axis=axis)
    s = np.where(keep, a, 0.0).sum(axis=axis, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, s / np.maximum(n, 1), centre)



def _robust_sums(a: np.ndarray, axis: int, centre: float, sigma: float, nsig: float = 5.0):
    """Sum and count along ``axis`` of the values within ``centre +- nsig sigma`` (see :func:`_robust_mean_1d`)."""
    keep = np.abs(a - centre) <= nsig * sigma
    return np.where(keep, a, 0.0).sum(axis=axis, dtype=np.float64), keep.sum(axis=axis)


def _out(shape, like_array: bool, dtype=np.float32):
    """Where a per-pixel map goes: an in-memory array (array inputs) or a :class:`BandStore`."""
    return np.empty(shape, dtype) if like_array else BandStore(shape, dtype)


def _write_rows(dst, r0: int, band: np.ndarray) -> None:
    if isinstance(dst, np.ndarray):
        dst[r0:r0 + band.shape[0]] = band
    else:
        dst.write(r0, band)


def bias_structure(master, read_noise_adu: float, n_bias: int, nsigma: float = 5.0, *,
                   B: _Bands | None = None, sample: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """Noise-free estimate of the bias structure [ADU] from a master bias (Janesick 2007, ch. 9).

    ``B(y, x) = L + c(x) + r(y)``: ``L`` the clipped level, ``c`` the clipped column means of ``M - L``,
    ``r`` the clipped row means of ``M - L - c`` (5 sigma, sigma = the master's noise ``sigma_read /
    sqrt(n_bias)``; each mean averages over a whole column or row, so its noise is negligible). Pixels
    whose master value departs from ``B`` by more than ``nsigma`` noise sigma keep their master value
    (bias defects). The pixel-level fixed pattern left, ``var(M - B) - sigma_read^2 / n_bias`` over the
    inliers, is added back shrunk by ``sqrt(var_fp / var(M - B))`` when it is significant: a map with the
    measured fixed-pattern spread whose noise does not inflate a rendered frame's spread.

    ``master`` is a 2-D array (the map is returned as a float32 array) or a ``rows(a, b)`` source read in
    the bands ``B`` (the map is returned as a float32 :class:`BandStore`); ``sample`` the master's regular
    subsample (computed from an array when not given). Three passes: column means, row means and the
    residual's subsample, the map.
    """
    src = as_rows(master)
    shape = tuple(src.shape)
    h, w = shape
    is_arr = isinstance(master, np.ndarray)
    B = B or _Bands(shape, band_pixels=h * w)
    m_rows = lambda a, b: np.asarray(src.rows(a, b), dtype=np.float64)
    if sample is None:
        sample = subsample(m_rows(0, h))
    noise = read_noise_adu / math.sqrt(max(n_bias, 1))
    level = clipped_stats(np.asarray(sample, np.float64), 5.0)["mean"]
    s_c, n_c = np.zeros(w), np.zeros(w, np.int64)
    for r0, r1 in B.run("bias structure: columns"):
        s, n = _robust_sums(m_rows(r0, r1) - level, 0, 0.0, max(noise, 1e-6) * 3)
        s_c += s
        n_c += n
    with np.errstate(invalid="ignore", divide="ignore"):
        col = np.where(n_c > 0, s_c / np.maximum(n_c, 1), 0.0)
    row = np.empty(h)
    Sm = Sampler(shape)
    G = Gather()
    for r0, r1 in B.run("bias structure: rows"):
        m = m_rows(r0, r1)
        row[r0:r1] = _robust_mean_1d(m - level - col[None, :], 1, 0.0, max(noise, 1e-6) * 3)
        G.add("resid", Sm.take(r0, m - (level + col[None, :] + row[r0:r1, None])))
    rs = clipped_stats(G.get("resid"), 5.0)
    var_fp = rs["std"] ** 2 - noise ** 2
    n_pix = min(h * w, MAX_STAT_PIXELS)
    significant = var_fp > 3 * rs["std"] ** 2 * math.sqrt(2.0 / n_pix)
    out = _out(shape, is_arr)
    n_def = 0
    for r0, r1 in B.run("bias structure: map"):
        m = m_rows(r0, r1)
        struct = level + col[None, :] + row[r0:r1, None]
        resid = m - struct
        o = struct.copy()
        inl = np.abs(resid) <= nsigma * max(rs["std"], noise)
        if significant:
            o[inl] += resid[inl] * math.sqrt(var_fp) / rs["std"]
        o[~inl] = m[~inl]
        n_def += int((~inl).sum())
        o32 = o.astype(np.float32)
        _write_rows(out, r0, o32)
        G.add("map", Sm.take(r0, o32))
    # the column offsets as a population: a normal core and the outlier columns' quantiles
    cc = clipped_stats(col, 3.0)
    core2 = cc["std"] ** 2 - noise ** 2 / h
    out_cols = np.abs(col - cc["median"]) > 5 * cc["std"]
    msample = G.get("map")
    info = {"level_adu": level, "column_std_adu": float(np.std(col)),
            "column_core_std_adu": math.sqrt(core2) if core2 > 0 else 0.0,
            "column_outlier_fraction": float(out_cols.mean()),
            "column_outlier_quantiles_adu": np.quantile(col[out_cols], np.linspace(0, 1, 33)).round(3).tolist()
            if out_cols.sum() >= 2 else [], "row_std_adu": float(np.std(row)),
            "master_noise_adu": noise, "residual_std_adu": rs["std"],
            "pixel_fixed_pattern_std_adu": math.sqrt(var_fp) if var_fp > 0 else 0.0,
            "pixel_fixed_pattern_significant": bool(significant), "n_bias_defects": n_def,
            "map_median_adu": float(np.median(msample)),
            "method": "level + clipped column means + clipped row means; defects kept; pixel pattern shrunk"}
    if not is_arr:
        out.sample = msample
    return out, info


def dark_rate_map(ts: np.ndarray, darks, bias_map, offset_adu: float, read_noise_adu: float, gain: float,
                  sat_adu: float, nsigma: float = 5.0, *, B: _Bands | None = None,
                  samples: Sequence[np.ndarray] | None = None, bias_sample: np.ndarray | None = None,
                  hot_floor=None) -> tuple:
    """Per-pixel dark rates [ADU/s] and their standard errors from darks of several exposures.

    Each pixel's line through its bias, ``y(t) = B(y, x) + offset + r t``, fitted by weighted least squares
    over the unsaturated darks: ``r = sum w t (y - B - o) / sum w t^2`` with ``w = 1 / sigma_t^2``,
    ``sigma_t^2 = sigma_read^2 + r_bar t / g`` (read and shot noise, ADU^2; Janesick 2007, ch. 7), and
    ``se(r) = 1 / sqrt(sum w t^2)`` (the pixel's own shot noise is used for its error). The intercept is the
    noise-free bias structure (:func:`bias_structure`), so the rate's noise is the darks' alone.

    The bulk (pixels within ``nsigma`` clipped standard deviations of the median rate) is shrunk towards the median by
    ``s = sqrt((V - N) / V)`` (``V`` the bulk's clipped variance, ``N`` the mean squared standard error):
    the map then has the *measured* dark-signal non-uniformity, not that plus its noise; outliers (hot and
    warm pixels) keep their measured rates.

    ``darks`` and ``bias_map`` are 2-D arrays (the maps come back as arrays) or ``rows(a, b)`` sources read
    in the bands ``B`` (the maps come back as :class:`BandStore`; ``samples``/``bias_sample`` are then
    their regular subsamples). Two passes: the rates and their errors (to a float64 temporary file), then
    the shrunk map, the stuck pixels and, with ``hot_floor`` (callable(info) -> excess-rate floor
    [ADU/s]), the table of pixels above it.

    Returns
    -------
    rate_adu_s, se_adu_s : 2-D float32 arrays (or stores)
    stuck : 2-D bool array (above ``nsigma`` in the longest dark, at least half of that already in the
        shortest, and the same value, within 5 sqrt(2) sigma_read or 5 %, in every dark: stuck pixels);
        for sources, the (y, x) positions and their median raw value over the darks
    info : dict (with sources: ``_hot`` the pixels above the floor: y, x, rate, se)
    """
    ts = np.asarray(ts, dtype=np.float64)
    srcs = [as_rows(d) for d in darks]
    bsrc = as_rows(bias_map)
    shape = tuple(bsrc.shape)
    h, w = shape
    is_arr = isinstance(bias_map, np.ndarray)
    B = B or _Bands(shape, band_pixels=h * w)
    if samples is None:
        samples = [subsample(np.asarray(d)) for d in darks]
    if bias_sample is None:
        bias_sample = subsample(np.asarray(bias_map))
    r_bar = np.median([(np.median(s) - np.median(bias_sample) - offset_adu) / t for s, t in zip(samples, ts)])
    Sm = Sampler(shape)
    G = Gather()
    tmp_rate = BandStore(shape, np.float64)
    tmp_se = BandStore(shape, np.float64)
    n_allsat = 0
    try:
        for r0, r1 in B.run("dark rates: fit"):
            bm = bsrc.rows(r0, r1)
            ds = [s.rows(r0, r1) for s in srcs]
            num = np.zeros(bm.shape, np.float64)
            den = np.zeros(bm.shape, np.float64)
            for d, t in zip(ds, ts):
                wt = 1.0 / (read_noise_adu ** 2 + max(r_bar, 0.0) * t / gain + 1.0 / 12.0)
                ok = d < sat_adu - 0.5
                y = d.astype(np.float64) - bm - offset_adu
                num += np.where(ok, wt * t * y, 0.0)
                den += np.where(ok, wt * t * t, 0.0)
            with np.errstate(invalid="ignore", divide="ignore"):
                rate = np.where(den > 0, num / np.where(den > 0, den, 1.0), np.nan)
            del num, den
            allsat = ~np.isfinite(rate)
            rate[allsat] = (sat_adu - bm[allsat] - offset_adu) / ts.min()  # saturated in every dark: a lower limit
            n_allsat += int(allsat.sum())
            se2 = np.zeros_like(rate)
            for d, t in zip(ds, ts):
                var = read_noise_adu ** 2 + np.maximum(rate, 0.0) * t / gain + 1.0 / 12.0
                ok = d < sat_adu - 0.5
                se2 += np.where(ok, t * t / var, 0.0)
            with np.errstate(divide="ignore"):
                se = np.where(se2 > 0, 1.0 / np.sqrt(se2), np.inf)
            tmp_rate.write(r0, rate)
            tmp_se.write(r0, se)
            G.add("rate", Sm.take(r0, rate))
            G.add("se", Sm.take(r0, se))
        rs_, ses = G.get("rate"), G.get("se")
        med = float(np.median(rs_))
        noise2 = float(np.median(ses) ** 2)
        spread0 = clipped_stats(rs_, 3.0)["std"]  # DSNU and noise together
        lim = nsigma * max(spread0, 1e-12)
        cs = clipped_stats(rs_[np.abs(rs_ - med) <= lim], nsigma)
        V = cs["std"] ** 2
        s = math.sqrt(max(V - noise2, 0.0) / V) if V > 0 else 0.0
        info = {"median_rate_adu_per_s": med, "bulk_clipped_std_adu_per_s": cs["std"],
                "noise_std_adu_per_s": math.sqrt(noise2), "dsnu_std_adu_per_s": math.sqrt(max(V - noise2, 0.0)),
                "dsnu_sigma_rel": math.sqrt(max(V - noise2, 0.0)) / med if med > 0 else 0.0,
                "bulk_shrink_factor": s, "n_saturated_in_every_dark": n_allsat, "offset_adu": offset_adu,
                "exposures_s": ts.tolist(),
                "method": "weighted line through the bias structure per pixel; bulk shrunk to the measured DSNU"}
        floor = hot_floor(info) if hot_floor else None
        out_r, out_se = _out(shape, is_arr), _out(shape, is_arr)
        stuck_arr = np.zeros(shape, bool) if is_arr else None
        sy, sx, sv, hy, hx, hr, hs = [], [], [], [], [], [], []
        n_bulk, total, total32 = 0, 0.0, 0.0
        high_thr = nsigma * math.sqrt(read_noise_adu ** 2 + max(r_bar, 0) * ts[-1] / gain) + med * ts[-1]
        for r0, r1 in B.run("dark rates: map"):
            rate = tmp_rate.rows(r0, r1)
            bulk = np.abs(rate - med) <= lim
            n_bulk += int(bulk.sum())
            o = rate.copy()
            o[bulk] = med + s * (rate[bulk] - med)
            total += float(o.sum())
            o32 = o.astype(np.float32)
            total32 += float(o32.sum(dtype=np.float64))
            se32 = tmp_se.rows(r0, r1).astype(np.float32)
            _write_rows(out_r, r0, o32)
            _write_rows(out_se, r0, se32)
            G.add("map", Sm.take(r0, o32))
            # stuck: high, already there at the shortest exposure, and the same value in every dark
            bm = bsrc.rows(r0, r1)
            ds = [sr.rows(r0, r1) for sr in srcs]
            x0 = ds[0].astype(np.float64) - bm - offset_adu
            xl = ds[-1].astype(np.float64) - bm - offset_adu
            stack = np.stack([d.astype(np.float32) for d in ds])
            spread = stack.max(axis=0) - stack.min(axis=0)
            high = xl > high_thr
            st = high & (x0 >= 0.5 * xl) & (ts[0] <= 0.5 * ts[-1]) \
                & (spread <= np.maximum(5 * math.sqrt(2) * read_noise_adu, 0.05 * xl))
            if is_arr:
                stuck_arr[r0:r1] = st
            else:
                yy, xx = np.nonzero(st)
                sy.append(yy + r0)
                sx.append(xx)
                sv.append(np.median(stack[:, yy, xx], axis=0) if yy.size else np.zeros(0, np.float32))
                if floor is not None:
                    hot = ((o32.astype(np.float64) - med) > floor) & ~st
                    yy, xx = np.nonzero(hot)
                    hy.append(yy + r0)
                    hx.append(xx)
                    hr.append(o32[yy, xx])
                    hs.append(se32[yy, xx])
            del stack
        info["mean_rate_adu_per_s"] = total / (h * w)
        info["map_mean_adu_per_s"] = total32 / (h * w)
        info["n_bulk"] = n_bulk
        info["n_outliers"] = h * w - n_bulk
        cat = lambda p, dt: np.concatenate(p).astype(dt) if p else np.zeros(0, dt)
        if is_arr:
            info["n_stuck"] = int(stuck_arr.sum())
            return out_r, out_se, stuck_arr, info
        info["n_stuck"] = int(sum(len(v) for v in sy))
        out_r.sample = G.get("map")
        stuck = {"y": cat(sy, np.int64), "x": cat(sx, np.int64), "value_adu": cat(sv, np.float32)}
        info["_hot"] = {"y": cat(hy, np.int64), "x": cat(hx, np.int64), "rate": cat(hr, np.float32),
                        "se": cat(hs, np.float32)}
        return out_r, out_se, stuck, info
    finally:
        tmp_rate.close()
        tmp_se.close()


def flat_response(flats, bias_map, dark_adu, read_noise_adu: float, gain: float, n_bias: int,
                  smooth_px: float = 16.0, *, B: _Bands | None = None, samples=None, bias_sample=None,
                  dark_sample=None) -> tuple:
    """Per-pixel response (PRNU x vignetting) of a flat (or flat pair), its standard error and the vignetting.

    ``F = mean_k(f_k s_k) - B - D`` (``s_k`` scales every flat to the first's median, ``B`` the bias
    structure, ``D`` the dark signal of the flat's exposure), normalised to mean 1; its standard error per
    pixel ``sqrt(S/g + sigma_read^2) / sqrt(n) / mean`` (shot and read noise of the ``n`` flats, Janesick
    2007, ch. 4). The vignetting is ``F`` Gaussian-smoothed (sigma ``smooth_px``, outliers replaced by the
    median first), the per-pixel response ``F / vignetting``.

    Arrays in, arrays out; ``rows(a, b)`` sources in (with their regular subsamples), :class:`BandStore`
    out, in two passes (the mean, then the maps with the smoothing on bands with a halo).
    """
    fsrc = [as_rows(f) for f in flats]
    bsrc, dsrc = as_rows(bias_map), as_rows(dark_adu)
    shape = tuple(bsrc.shape)
    h, w = shape
    is_arr = isinstance(bias_map, np.ndarray)
    B = B or _Bands(shape, band_pixels=h * w)
    if samples is None:
        samples = [subsample(np.asarray(f)) for f in flats]
        bias_sample, dark_sample = subsample(np.asarray(bias_map)), subsample(np.asarray(dark_adu))
    meds = []
    for s in samples:
        x = s.astype(np.float64) - bias_sample - dark_sample
        meds.append(float(np.median(x)))
    ref = meds[0]
    nf = len(flats)

    def mean_rows(a, b):
        bm, dk = bsrc.rows(a, b), dsrc.rows(a, b)
        acc = np.zeros(bm.shape, np.float64)
        for fs, med in zip(fsrc, meds):
            acc += (fs.rows(a, b).astype(np.float64) - bm - dk) * (ref / med)
        return acc / nf

    def mean_sample():
        acc = np.zeros(bias_sample.shape, np.float64)
        for s, med in zip(samples, meds):
            acc += (s.astype(np.float64) - bias_sample - dark_sample) * (ref / med)
        return acc / nf

    if is_arr:
        mean = float(mean_rows(0, h).mean())
    else:
        tot = 0.0
        for r0, r1 in B.run("flat response: mean"):
            tot += float(mean_rows(r0, r1).sum())
        mean = tot / (h * w)
    if not mean > 0:
        raise DetectorError(f"bias-subtracted flat has mean {mean:.4g} ADU", key="flat",
                            expected="flats with light (mean above the bias)")
    cs = clipped_stats(np.maximum(mean_sample() / mean, 0.0), 5.0)

    def rows_fn(a, b):
        F = np.maximum(mean_rows(a, b) / mean, 0.0)
        return F, np.where(np.abs(F - cs["median"]) > 5 * cs["std"] + 0.05, cs["median"], F)

    outF, outS, outV = _out(shape, is_arr), _out(shape, is_arr), _out(shape, is_arr)
    Sm = Sampler(shape)
    G = Gather()
    for r0, r1, F, vig in _smoothed_bands(rows_fn, shape, smooth_px, B, "flat response: maps"):
        sig = np.sqrt(np.maximum(mean_rows(r0, r1), 0) / gain + read_noise_adu ** 2 * (1 + 1 / max(n_bias, 1))) \
            / math.sqrt(nf)
        _write_rows(outF, r0, F.astype(np.float32))
        _write_rows(outS, r0, (sig / mean).astype(np.float32))
        _write_rows(outV, r0, vig.astype(np.float32))
        G.add("sig", Sm.take(r0, sig))
        G.add("resp", Sm.take(r0, F / vig))
    info = {"signal_adu": mean, "n_flats": nf, "smoothing_sigma_px": smooth_px,
            "relative_se_median": float(np.median(G.get("sig")) / mean),
            "response_std": clipped_stats(G.get("resp"), 5.0)["std"]}
    return outF, outS, outV, info


def fit_rate_laws(excess: np.ndarray, floor: float, bias_level_adu: float) -> dict:
    """Laws of the excess dark rates above ``floor`` (one unit throughout), compared by AIC and KS.

    * ``pareto``: ``P(R > r) = (r / floor)^-alpha``, MLE ``alpha = n / sum ln(r / floor)`` (Clauset, Shalizi
      & Newman 2009, SIAM Rev. 51, 661, eq. 3.1); ``se = alpha / sqrt(n)``.
    * ``lognormal`` truncated at the floor: MLE of (mu, sigma) of ``ln r`` (numerical).
    * ``weibull_t2``: the thesis's law (eqs. 38-40), a Weibull of ``t2 = B / r`` truncated to ``t2 <
      B / floor`` (numerical MLE of shape and scale).
    * ``empirical``: 65 quantiles (no AIC: it is the data).

    KS: the one-sample statistic of the rates against each fitted truncated law.
    """
    from scipy import optimize

    r = np.asarray(excess, dtype=np.float64)
    r = r[np.isfinite(r) & (r > floor)]
    n = r.size
    out: dict = {"n": int(n), "floor": floor}
    if n < 20:
        out["note"] = "fewer than 20 rates above the floor: no fit"
        return out
    lr = np.log(r)
    lf = math.log(floor)
    alpha = n / float(np.sum(lr - lf))
    ll_p = float(n * math.log(alpha) + n * alpha * lf - (alpha + 1) * lr.sum())
    cdf_p = lambda x: 1 - (np.asarray(x) / floor) ** (-alpha)
    out["pareto"] = {"alpha": alpha, "alpha_se": alpha / math.sqrt(n), "loglik": ll_p, "aic": 2 - 2 * ll_p,
                     "ks": float(stats.kstest(r, cdf_p).statistic)}

    def nll_ln(p):
        mu, ls = p
        if abs(ls) > 10:
            return 1e300
        s = math.exp(ls)
        tail = stats.norm.logsf((lf - mu) / s)
        return -float(np.sum(stats.norm.logpdf(lr, mu, s) - lr) - n * tail)

    res = optimize.minimize(nll_ln, [float(lr.mean()), math.log(max(lr.std(), 0.1))], method="Nelder-Mead",
                            options={"xatol": 1e-6, "fatol": 1e-6, "maxiter": 4000})
    mu, s = float(res.x[0]), math.exp(float(res.x[1]))
    p0 = stats.norm.cdf((lf - mu) / s)
    cdf_l = lambda x: (stats.norm.cdf((np.log(x) - mu) / s) - p0) / max(1 - p0, 1e-300)
    out["lognormal"] = {"log_mu": mu, "log_sigma": s, "loglik": -float(res.fun), "aic": 4 + 2 * float(res.fun),
                        "ks": float(stats.kstest(r, cdf_l).statistic)}
    t2 = bias_level_adu / r
    tmax = bias_level_adu / floor
    lt = np.log(t2)

    def nll_w(p):
        if abs(p[0]) > 10 or abs(p[1]) > 60:
            return 1e300
        k, lam = math.exp(p[0]), math.exp(p[1])
        with np.errstate(all="ignore"):
            z = (t2 / lam) ** k
            logF = float(np.log(max(-np.expm1(-np.float64(tmax / lam) ** k), 1e-300)))
            ll = np.sum(math.log(k) - math.log(lam) + (k - 1) * (lt - math.log(lam)) - z) - n * logF
        # density of r from that of t2: |dt2/dr| = t2 / r
        v = -float(ll + np.sum(lt - lr))
        return v if math.isfinite(v) else 1e300

    res = optimize.minimize(nll_w, [0.0, float(np.median(lt))], method="Nelder-Mead",
                            options={"xatol": 1e-6, "fatol": 1e-6, "maxiter": 4000})
    k, lam = math.exp(float(res.x[0])), math.exp(float(res.x[1]))
    Fm = -math.expm1(-(tmax / lam) ** k)
    cdf_w = lambda x: 1 - (-np.expm1(-((bias_level_adu / np.asarray(x)) / lam) ** k)) / Fm
    out["weibull_t2"] = {"shape": k, "scale_s": lam, "loglik": -float(res.fun), "aic": 4 + 2 * float(res.fun),
                         "ks": float(stats.kstest(r, cdf_w).statistic)}
    laws = ("pareto", "lognormal", "weibull_t2")
    best = min(laws, key=lambda k_: out[k_]["aic"])
    out["preferred"] = best
    out["delta_aic"] = {k_: out[k_]["aic"] - out[best]["aic"] for k_ in laws}
    from .effects.maps import tail_probabilities

    pr = tail_probabilities(n)
    out["empirical_probabilities"] = pr.tolist()
    out["empirical_quantiles"] = np.quantile(r, pr).tolist()
    return out


class _Scaled:
    """Rows of a float32 store times a float32 factor (after an optional cap): ``min(x, cap) * factor``."""

    def __init__(self, src, factor: float, cap: float | None = None):
        self.src, self.f, self.cap = src, np.float32(factor), cap
        self.shape = tuple(src.shape)
        self.dtype = np.dtype(np.float32)

    def rows(self, a, b):
        x = self.src.rows(a, b)
        if self.cap is not None:
            x = np.minimum(x, self.cap).astype(np.float32)
        return x * self.f

    def __array__(self, dtype=None, copy=None):
        a = self.rows(0, self.shape[0])
        return a if dtype is None else a.astype(dtype)


class _GroupMean:
    """Rows of the pixel mean of frames of one exposure (float32), as :func:`_mean32`."""

    def __init__(self, frames: Sequence[Frame]):
        self.frames = list(frames)
        self.shape = tuple(frames[0].shape)

    def rows(self, a, b):
        return _mean32([f.rows(a, b) for f in self.frames])


def _sample_frames(frames: Sequence[Frame], B: _Bands, label: str) -> dict:
    """Regular subsamples of frames (id -> float32 values) in one band pass; also checks finiteness."""
    S = Sampler(B.shape)
    G = Gather()
    for r0, r1 in B.run(label):
        for k, f in enumerate(frames):
            a = f.rows(r0, r1)
            if a.dtype.kind == "f" and not np.isfinite(a).all():
                _nonfinite_error(f.path, f.checks.get("role", "frame"), a, r0)
            G.add(str(k), S.take(r0, a))
    return {id(f): G.get(str(k)).astype(np.float32) for k, f in enumerate(frames)}


def camera_twin(result: dict, bias_paths: Sequence, dark_paths: Sequence, flat_paths: Sequence | None = None,
                *, nsigma: float = 5.0, hot_threshold_s: float = 60.0, band_pixels: int | None = None,
                progress=None) -> tuple[dict, dict]:
    """The camera itself from its calibration frames: per-pixel maps and the defect table.

    Parameters
    ----------
    result : dict
        What :func:`characterize` returned for the same frames (read noise, gain, levels).
    bias_paths, dark_paths, flat_paths : lists of paths
    band_pixels, progress : as for :func:`characterize`

    Returns
    -------
    (maps, info): ``maps`` holds the 2-D float32 maps, each as a ``rows(a, b)`` source kept on disk
    (:class:`detector.calbands.BandStore`; ``np.asarray(maps[k])`` loads one): ``bias_adu`` (absolute,
    :func:`bias_structure`), ``dark_rate_e_per_s`` and ``dark_rate_se_e_per_s`` (:func:`dark_rate_map`),
    with flats ``flat``, ``flat_se`` and ``vignetting`` (:func:`flat_response`), and the tables ``defects``
    (x, y, kind, rate_e_per_s, rate_se_e_per_s, t_double_s) and ``stuck`` (x, y, value_adu); ``info`` the
    JSON numbers, with the population law of the excess rates (:func:`fit_rate_laws`). The frames are read
    band by band; running out of memory is a :class:`DetectorError`.
    """
    try:
        with open_frame_sets(bias_paths, dark_paths, flat_paths) as (bias, darks, flats):
            return _camera_twin(result, bias, darks, flats, nsigma, hot_threshold_s,
                                _Bands(bias[0].shape, band_pixels, progress))
    except MemoryError:
        raise DetectorError("out of memory while building the camera's maps", key="--emit-scene",
                            file=str(bias_paths[0]),
                            expected="more free memory, or fewer/smaller frames (see docs/detector.md)") from None


def _camera_twin(result, bias, darks, flats, nsigma, hot_threshold_s, B: _Bands):
    g = float(result["gain"]["adopted_e_per_adu"])
    read = float(result["bias"]["read_noise_adu"])
    shape = B.shape
    nb = len(bias)
    S = _sample_frames(bias + darks + flats, B, "camera: read frames")

    class _Master:
        shape = B.shape

        def rows(self, a, b):
            return np.mean([f.rows(a, b) for f in bias], axis=0, dtype=np.float64)

    m_sample = np.mean([S[id(f)] for f in bias], axis=0, dtype=np.float64)
    bmap, binfo = bias_structure(_Master(), read, nb, nsigma, B=B, sample=m_sample)
    ts, groups = _group_by_time(darks)
    imgs = [_GroupMean(gr) for gr in groups]
    img_s = [_mean32([S[id(f)] for f in gr]) for gr in groups]
    sat = min(f.saturation_adu for f in darks)
    if not math.isfinite(sat):
        sat = max(float(s.max()) for s in img_s) + 1
        for r0, r1 in B.run("darks: maximum"):
            sat = max(sat, max(float(im.rows(r0, r1).max()) for im in imgs) + 1)
    offset = float(result["dark"]["intercept_minus_bias_adu"]) if len(ts) >= 2 else 0.0
    if abs(offset) > 3 * read:
        offset = 0.0

    def hot_floor(info):
        return max(nsigma * max(info["dsnu_std_adu_per_s"], info["noise_std_adu_per_s"]), 1e-6)

    rate, se, stuck, dinfo = dark_rate_map(ts, imgs, bmap, offset, read, g, sat, nsigma, B=B, samples=img_s,
                                           bias_sample=bmap.sample, hot_floor=hot_floor)
    hotp = dinfo.pop("_hot")
    maps: dict = {"bias_adu": bmap, "dark_rate_e_per_s": _Scaled(rate, g),
                  "dark_rate_se_e_per_s": _Scaled(se, g, cap=1e6), "_stores": [bmap, rate, se]}
    maps["stuck"] = {"x": stuck["x"].astype(np.int32), "y": stuck["y"].astype(np.int32),
                     "value_adu": stuck["value_adu"].astype(np.float32)}
    med = dinfo["median_rate_adu_per_s"]
    floor = hot_floor(dinfo)
    excess = hotp["rate"].astype(np.float64) - med
    Bl = float(result["bias"]["level_median_adu"])
    t2 = Bl / excess
    maps["defects"] = {"x": hotp["x"].astype(np.int32), "y": hotp["y"].astype(np.int32),
                       "kind": np.where(t2 < hot_threshold_s, "hot", "warm"),
                       "rate_e_per_s": (hotp["rate"] * g).astype(np.float64),
                       "rate_se_e_per_s": (hotp["se"] * g).astype(np.float64), "t_double_s": t2}
    dinfo["excess_floor_adu_per_s"] = floor
    dinfo["n_hot"] = int(np.count_nonzero(t2 < hot_threshold_s))
    dinfo["n_warm"] = int(np.count_nonzero(t2 >= hot_threshold_s))
    dinfo["rate_laws_adu_per_s"] = fit_rate_laws(excess, floor, Bl)
    dinfo["map_mean_e_per_s"] = dinfo.pop("map_mean_adu_per_s") * g
    info = {"bias": binfo, "dark": dinfo, "gain_e_per_adu": g, "shape": list(shape), "band_rows": B.rows}
    if flats:
        tf = flats[0].exptime_s or 0.0
        dark_src = _Scaled(rate, tf)
        F, Fse, vig, finfo = flat_response(flats, bmap, dark_src, read, g, nb, B=B,
                                           samples=[S[id(f)] for f in flats], bias_sample=bmap.sample,
                                           dark_sample=rate.sample * np.float32(tf))
        maps.update({"flat": F, "flat_se": Fse, "vignetting": vig})
        maps["_stores"] += [F, Fse, vig]
        finfo["exposure_s"] = tf
        finfo["files"] = [f.path for f in flats]
        h, w = shape
        bh, bw = max(1, h // 10), max(1, w // 10)
        boxes = [(h // 2 - bh // 2, h // 2 + bh // 2 + 1, w // 2 - bw // 2, w // 2 + bw // 2 + 1),
                 (0, bh, 0, bw), (0, bh, w - bw, w), (h - bh, h, 0, bw), (h - bh, h, w - bw, w)]
        vals = [[] for _ in boxes]
        for r0, r1 in B.run("flat response: vignetting"):
            v = vig.rows(r0, r1)
            for k, (y0, y1, x0, x1) in enumerate(boxes):
                a, b = max(y0, r0), min(y1, r1)
                if a < b:
                    vals[k].append(v[a - r0:b - r0, x0:x1].flatten())
        med_box = [np.median(np.concatenate(v)) for v in vals]  # float32, as the whole-frame code had
        finfo["vignetting_corner_over_centre"] = float(np.mean(med_box[1:]) / float(med_box[0]))
        info["flat"] = finfo
    return maps, jsonable(info)


def _image_header(shape, extname: str | None, cards: dict | None = None) -> fits.Header:
    """Header of a float32 image HDU (primary when ``extname`` is None)."""
    h = fits.Header()
    if extname is None:
        h["SIMPLE"] = True
    else:
        h["XTENSION"] = "IMAGE"
    h["BITPIX"] = -32
    h["NAXIS"] = 2
    h["NAXIS1"] = int(shape[1])
    h["NAXIS2"] = int(shape[0])
    if extname is None:
        h["EXTEND"] = True
    else:
        h["PCOUNT"] = 0
        h["GCOUNT"] = 1
        h["EXTNAME"] = extname
    for k, v in (cards or {}).items():
        if k == "COMMENT":
            h.add_comment(v)
        else:
            h[k] = v
    return h


def write_image_hdus(path, images: Sequence[tuple], tables: Sequence = (), band_rows_: int = 512) -> None:
    """Write a FITS file of float32 images read band by band (``(extname or None, source, cards)``; the
    first is the primary), followed by table HDUs; atomic (a temporary file renamed when complete)."""
    import os
    import tempfile

    from .fits_io import BLOCK, _extension_bytes

    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            for name, src, cards in images:
                src = as_rows(src)
                f.write(_image_header(src.shape, name, cards).tostring().encode("ascii"))
                n = 0
                for r0 in range(0, src.shape[0], band_rows_):
                    raw = np.asarray(src.rows(r0, r0 + band_rows_), dtype=np.float32).astype(">f4").tobytes()
                    f.write(raw)
                    n += len(raw)
                f.write(b"\0" * (-n % BLOCK))
            f.write(_extension_bytes(list(tables)))
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_twin(out_toml, result: dict, maps: dict, info: dict, preset_hint: str | None = None) -> dict:
    """Write the camera's maps as FITS files beside ``out_toml`` and return the scene (a TOML-ready dict).

    Files: ``<stem>_bias.fits`` (the bias structure [ADU]), ``<stem>_dark.fits`` (dark rate [e-/s]; HDUs
    ``SIGMA`` its standard error, ``STUCK`` and ``DEFECTS`` tables), with flats ``<stem>_flat.fits``
    (response, mean 1; ``SIGMA``; ``VIGNETTING``). The scene: :func:`emit_scene_dict`'s detector with the
    dark current set to the map's mean, and the effects ``bias_map``, ``dark_map`` (and ``flat_map``)
    instead of the population's ``hot_pixels`` and ``dsnu``. Paths in the scene are relative to it. The
    images are written band by band from the maps (arrays or ``rows(a, b)`` sources).
    """
    out = Path(out_toml)
    stem = out.with_suffix("")
    scene = emit_scene_dict(result, preset_hint)
    scene["effects"] = {}

    def write(suffix, images, tables=()):
        p = Path(f"{stem}_{suffix}.fits")
        write_image_hdus(p, images, tables)
        return p.name

    scene["effects"]["bias_map"] = {"path": write("bias", [(None, maps["bias_adu"], {
        "BUNIT": "adu", "COMMENT": "bias structure: level + column + row means (+ defects), newtsim characterize"})])}
    st = maps["stuck"]
    d = maps["defects"]
    tables = [fits.BinTableHDU.from_columns([fits.Column("x", "J", array=st["x"]), fits.Column("y", "J", array=st["y"]),
                                             fits.Column("value_adu", "E", array=st["value_adu"])], name="STUCK"),
              fits.BinTableHDU.from_columns([
                  fits.Column("x", "J", array=d["x"]), fits.Column("y", "J", array=d["y"]),
                  fits.Column("kind", "5A", array=np.asarray(d["kind"], dtype="S5")),
                  fits.Column("rate_e_per_s", "D", array=d["rate_e_per_s"]),
                  fits.Column("rate_se_e_per_s", "D", array=d["rate_se_e_per_s"]),
                  fits.Column("t_double_s", "D", array=d["t_double_s"])], name="DEFECTS")]
    scene["effects"]["dark_map"] = {"path": write("dark", [(None, maps["dark_rate_e_per_s"], {"BUNIT": "electron/s"}),
                                                           ("SIGMA", maps["dark_rate_se_e_per_s"], None)], tables),
                                    "sigma_hdu": "SIGMA", "stuck_hdu": "STUCK",
                                    "offset_e": round(float(info["dark"]["offset_adu"]) * float(info["gain_e_per_adu"]), 4)}
    if result["dark"].get("temperature_c") is not None:
        scene["effects"]["dark_map"]["temperature_c"] = round(float(result["dark"]["temperature_c"]), 2)
    if "flat" in maps:
        scene["effects"]["flat_map"] = {"path": write("flat", [(None, maps["flat"], None),
                                                               ("SIGMA", maps["flat_se"], None),
                                                               ("VIGNETTING", maps["vignetting"], None)]),
                                        "sigma_hdu": "SIGMA"}
    bmed = info["bias"].get("map_median_adu")
    if bmed is None:
        bmed = float(np.median(np.asarray(maps["bias_adu"])))
    mean_e = info["dark"].get("map_mean_e_per_s")
    if mean_e is None:
        mean_e = float(np.mean(np.asarray(maps["dark_rate_e_per_s"])))
    integer = bool(result["frame"].get("integer_data", True))
    scene["detector"]["bias_adu"] = round(float(bmed), 3)  # the ADC rounds: no offset (detector.chain.adc)
    scene["detector"]["dark_current_e_per_s"] = round(float(mean_e), 6)
    return scene


def emit_population_dict(result: dict, info: dict, preset_hint: str | None = None) -> dict:
    """The statistical description of the camera (no maps): for sensors like it without calibration frames.

    :func:`emit_scene_dict`'s detector; ``dsnu`` with the per-pixel rate map's non-uniformity (its spread
    grows as ``sigma I_d t``, the measured growth); ``dark_rate_tail`` with the measured excess-rate law
    (the empirical quantiles, whose counts above any threshold grow with exposure as measured; the
    parametric fits and their AIC are in the JSON); ``hot_pixels`` keeps only the stuck pixels.
    """
    scene = emit_scene_dict(result, preset_hint)
    d = info["dark"]
    g = float(info["gain_e_per_adu"])
    eff: dict = {}
    if d["dsnu_sigma_rel"] > 0:
        eff["dsnu"] = {"sigma": round(min(d["dsnu_sigma_rel"], 5.0), 4), "law": "normal"}
    laws = d["rate_laws_adu_per_s"]
    if laws.get("empirical_quantiles"):
        q = [round(v * g, 6) for v in laws["empirical_quantiles"]]
        eff["dark_rate_tail"] = {"count": int(laws["n"]), "law": "empirical", "floor_e_per_s": round(q[0], 6),
                                 "quantiles_e_per_s": q, "probabilities": laws["empirical_probabilities"]}
    b = info["bias"]
    if b.get("column_core_std_adu") is not None:
        eff["column_offsets"] = {"sigma_adu": round(b["column_core_std_adu"], 4),
                                 "outlier_fraction": round(b["column_outlier_fraction"], 6),
                                 **({"outlier_quantiles_adu": b["column_outlier_quantiles_adu"]}
                                    if b["column_outlier_fraction"] > 0 else {})}
    if d["n_stuck"]:
        hp = result["hot_pixels"]
        lvl = (hp.get("stuck_raw_level_adu") or {}).get("median")
        eff["hot_pixels"] = {"count": int(d["n_stuck"]), "stuck_fraction": 1.0,
                             **({"stuck_value_adu": round(float(lvl), 1)} if lvl is not None else {})}
    scene["detector"]["dark_current_e_per_s"] = round(d["median_rate_adu_per_s"] * g, 6)
    scene["detector"]["bias_adu"] = round(float(info["bias"]["level_adu"])
                                          + (0.5 if result["frame"].get("integer_data", True) else 0.0), 3)
    scene["effects"] = eff
    return scene
