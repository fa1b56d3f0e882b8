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

Gain adopted for e- values: the header's ``EGAIN`` (or ``GAIN`` when it looks like e-/ADU), else the photon
transfer gain, else 1.0 with a warning.

Public API: :func:`characterize` (files in, dict out), :func:`emit_scene_dict` (dict in, scene tables out),
:func:`detector.calplots.write_plots` (dict in, PNG files out); the pure functions (:func:`clipped_stats`,
:func:`pair_noise`, :func:`normality_tests`, :func:`linear_fit`, :func:`fit_lifetimes`,
:func:`photon_transfer`, :func:`prnu_and_vignetting` ...) work on plain arrays. Memory: every dark, its
bias-subtracted copy and the master bias are held as float32 (about ``(2 n_exposures + 4) x 4`` bytes per
pixel); statistics use at most ``MAX_STAT_PIXELS`` pixels (a regular sub-grid).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import Iterable, Sequence

import numpy as np
from scipy import ndimage, stats

from .errors import DetectorError
from .fits_io import read_image
from .jsonable import jsonable

#: Above this many pixels, robust statistics use a regular sub-grid of the frame (speed, not accuracy).
MAX_STAT_PIXELS = 4_000_000
#: Pixels drawn for the normality tests (Shapiro-Wilk is defined up to 5000).
NORMALITY_SAMPLE = 5000
EXPTIME_KEYS = ("EXPTIME", "EXPOSURE")
TEMP_KEYS = ("CCD-TEMP", "CCDTEMP", "TEMPERAT", "DET-TEMP")


# ============================================================================================
# reading and validating frames
# ============================================================================================

@dataclass
class Frame:
    """One calibration frame as read from disk."""

    path: str
    data: np.ndarray  # float32, 2-D, ADU
    header: dict = field(repr=False)
    exptime_s: float | None
    saturation_adu: float
    temperature_c: float | None


def _card(header, keys: Iterable[str]):
    for k in keys:
        if k in header and header[k] is not None and not isinstance(header[k], bool):
            return k, header[k]
    return None, None


def read_frame(path, *, role: str = "frame", need_exptime: bool = False) -> Frame:
    """Read and validate one FITS calibration frame.

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
    finite = np.isfinite(arr)
    if not finite.all():
        bad = np.argwhere(~finite)[0]
        raise DetectorError(f"{role} image has {int((~finite).sum())} non-finite pixels, first at "
                            f"(x={bad[1]}, y={bad[0]})", file=name, expected="finite pixel values")
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
    sat = _saturation_adu(header, data)
    _, t = _card(header, TEMP_KEYS)
    try:
        temp = float(t) if t is not None else None
    except (TypeError, ValueError):
        temp = None
    return Frame(name, arr, header, exptime, sat, temp)


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
                shape_file: str | None = None) -> list[Frame]:
    """Read several frames of one role; all must have ``shape`` (or the first frame's shape)."""
    out = []
    for p in paths:
        f = read_frame(p, role=role, need_exptime=need_exptime)
        if shape is None:
            shape, shape_file = f.data.shape, f.path
        elif f.data.shape != tuple(shape):
            raise DetectorError(f"{role} frame is {f.data.shape[1]}x{f.data.shape[0]} pixels but {shape_file} is "
                                f"{shape[1]}x{shape[0]}", file=f.path, expected="frames of one size")
        out.append(f)
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

def _flat_sample(x: np.ndarray, max_n: int = MAX_STAT_PIXELS) -> np.ndarray:
    x = np.asarray(x).ravel()
    if x.size > max_n:
        x = x[:: int(math.ceil(x.size / max_n))]
    return x


def _truncation_factor(k: float) -> float:
    """Variance of a unit normal truncated to +-k sigma (to undo the bias of a clipped std)."""
    if not math.isfinite(k):
        return 1.0
    p = 2 * stats.norm.cdf(k) - 1
    return 1 - 2 * k * stats.norm.pdf(k) / p


def clipped_stats(x, sigma: float = 3.0, maxiters: int = 20, max_n: int = MAX_STAT_PIXELS) -> dict:
    """Sigma-clipped statistics of an array (clipping about the median).

    The first pass uses the MAD as the spread, the next ones the std of the inliers, until no pixel changes.
    ``std`` is divided by the square root of the variance of a normal truncated at +-``sigma``, so for normal
    data it estimates the normal's sigma (a 3-sigma clip alone would underestimate it by 1.3 %).

    Returns
    -------
    dict with ``mean``, ``median``, ``std`` [units of x], ``n`` (inliers), ``n_rejected``, ``lo``, ``hi``
    (the final clipping bounds).
    """
    v = _flat_sample(x, max_n)
    v = v.astype(np.float32 if v.dtype.itemsize <= 4 else np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return {"mean": math.nan, "median": math.nan, "std": math.nan, "n": 0, "n_rejected": 0,
                "lo": math.nan, "hi": math.nan}
    med = float(np.median(v))
    spread = 1.482602218505602 * float(np.median(np.abs(v - med)))
    if spread == 0:
        spread = float(v.std())
    keep = np.ones(v.size, bool)
    n_prev = -1
    lo = hi = med
    for _ in range(maxiters):
        lo, hi = med - sigma * spread, med + sigma * spread
        keep = (v >= lo) & (v <= hi)
        n = int(keep.sum())
        if n == n_prev or n < 2:
            break
        n_prev = n
        kept = v[keep]
        med = float(np.median(kept[:: max(1, kept.size // 250_000)]))  # a regular sub-grid: the bounds only
        spread = float(kept.std(dtype=np.float64))
        if spread == 0:
            break
    kept = v[keep] if keep.any() else v
    std = float(kept.std(ddof=1, dtype=np.float64)) if kept.size > 1 else 0.0
    return {"mean": float(kept.mean(dtype=np.float64)), "median": float(np.median(kept)),
            "std": std / math.sqrt(_truncation_factor(sigma)), "n": int(kept.size),
            "n_rejected": int(v.size - kept.size), "lo": float(lo), "hi": float(hi)}


def mad_std(x) -> float:
    """Normal-consistent median absolute deviation: 1.4826 median(|x - median(x)|)."""
    v = _flat_sample(x).astype(np.float64)
    return float(1.482602218505602 * np.median(np.abs(v - np.median(v))))


def pair_noise(a: np.ndarray, b: np.ndarray, sigma: float = 5.0) -> dict:
    """Temporal noise of one frame from the difference of two frames of the same kind [ADU].

    ``sigma_frame = std(a - b) / sqrt(2)``: the fixed pattern, identical in both, cancels (Janesick 2007,
    ch. 4). The second frame is not rescaled (bias frames). Robust: sigma-clipped std and MAD.
    """
    d = a.astype(np.float64) - b.astype(np.float64)
    cs = clipped_stats(d, sigma=sigma)
    return {"sigma_adu": cs["std"] / math.sqrt(2), "sigma_mad_adu": mad_std(d) / math.sqrt(2),
            "sigma_unclipped_adu": float(_flat_sample(d).std()) / math.sqrt(2), "diff_mean_adu": cs["mean"],
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
# bias
# ============================================================================================

def analyze_bias(frames: Sequence[Frame], rng: np.random.Generator) -> tuple[dict, np.ndarray, list[str]]:
    """Bias level, temporal read noise, fixed pattern and normality. Returns (result, master bias, warnings)."""
    warns: list[str] = []
    stack = [f.data for f in frames]
    master = np.mean(stack, axis=0, dtype=np.float64).astype(np.float32) if len(stack) > 1 else stack[0].copy()
    ms = clipped_stats(master, sigma=5.0)
    single = clipped_stats(frames[0].data, sigma=5.0)
    res: dict = {
        "n_frames": len(frames),
        "files": [f.path for f in frames],
        "level_median_adu": float(np.median(_flat_sample(master))),
        "level_mean_adu": ms["mean"],
        "level_mean_all_adu": float(_flat_sample(master).mean(dtype=np.float64)),
        "frame_medians_adu": [float(np.median(_flat_sample(f.data))) for f in frames],
        "single_frame_std_adu": single["std"],
        "single_frame_std_unclipped_adu": float(_flat_sample(frames[0].data).std(dtype=np.float64)),
    }
    for f in frames:
        if f.exptime_s is not None and f.exptime_s > 1.0:
            warns.append(f"{f.path}: bias frame has an exposure time of {f.exptime_s} s")
    if len(frames) >= 2:
        pairs = [(frames[i], frames[i + 1]) for i in range(0, len(frames) - 1, 2)]
        pn = [pair_noise(a.data, b.data) for a, b in pairs]
        var = float(np.mean([p["sigma_adu"] ** 2 for p in pn]))
        read = math.sqrt(var)
        res["read_noise_adu"] = read
        res["read_noise_mad_adu"] = float(np.sqrt(np.mean([p["sigma_mad_adu"] ** 2 for p in pn])))
        res["read_noise_unclipped_adu"] = float(np.sqrt(np.mean([p["sigma_unclipped_adu"] ** 2 for p in pn])))
        res["read_noise_se_adu"] = read / math.sqrt(2 * sum(p["n"] for p in pn))
        res["read_noise_method"] = "std(b1 - b2)/sqrt(2), 5-sigma clipped, over consecutive pairs"
        res["pair_difference_mean_adu"] = pn[0]["diff_mean_adu"]
        d = pairs[0][0].data.astype(np.float64) - pairs[0][1].data.astype(np.float64)
        cd = clipped_stats(d, sigma=5.0)
        dv = _flat_sample(d)
        dv = dv[(dv >= cd["lo"]) & (dv <= cd["hi"])]
        sample = rng.choice(dv, size=min(NORMALITY_SAMPLE, dv.size), replace=False)
        integer = bool(np.all(np.floor(frames[0].data[:8, :8]) == frames[0].data[:8, :8]))
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
    m64 = master.astype(np.float64)
    res["column_pattern_std_adu"] = float(clipped_stats(np.median(m64, axis=0), 5.0)["std"])
    res["row_pattern_std_adu"] = float(clipped_stats(np.median(m64, axis=1), 5.0)["std"])
    res["plot_data"]["single_frame_hist"] = _int_histogram(_flat_sample(frames[0].data), single["median"],
                                                           single["std"])
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

def _group_darks(frames: Sequence[Frame]) -> tuple[np.ndarray, list[np.ndarray], list[list[Frame]]]:
    by_t: dict[float, list[Frame]] = {}
    for f in frames:
        by_t.setdefault(float(f.exptime_s), []).append(f)
    ts = np.array(sorted(by_t))
    groups = [by_t[t] for t in ts]
    images = [np.mean([f.data for f in g], axis=0, dtype=np.float64).astype(np.float32) if len(g) > 1
              else g[0].data for g in groups]
    return ts, images, groups


def detect_outliers(x_long: np.ndarray, nsigma: float) -> tuple[np.ndarray, dict]:
    """Pixels of a bias-subtracted dark more than ``nsigma`` robust sigma above its clipped centre.

    Returns the flat indices and the detection statistics (centre, sigma and threshold, in ADU above bias).
    """
    cs = clipped_stats(x_long, sigma=3.0)
    thr = cs["median"] + nsigma * cs["std"]
    idx = np.flatnonzero(x_long.ravel() > thr)
    return idx, {"centre_adu": cs["median"], "robust_sigma_adu": cs["std"], "threshold_adu": float(thr),
                 "nsigma": nsigma}


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
    their level or more at the shortest exposure (they do not grow with time).
    """
    h, w = xs[-1].shape
    idx, det = detect_outliers(xs[-1], nsigma)
    det["exposure_s"] = float(ts[-1])
    n_t = len(ts)
    Y = np.stack([x.ravel()[idx] for x in xs], axis=1).astype(np.float64)  # (n_out, n_t)
    valid = np.ones_like(Y, bool) if sat_mask is None else ~np.stack([m.ravel()[idx] for m in sat_mask], axis=1)
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
    if master is not None:
        mcs = clipped_stats(master, sigma=3.0)
        cand = np.flatnonzero(master.ravel() > mcs["median"] + nsigma * mcs["std"])
        if cand.size:
            lvl = master.ravel()[cand].astype(np.float64)
            spread = np.max(np.abs(np.stack([x.ravel()[cand] for x in xs], axis=1)), axis=1)
            tol = np.maximum(5 * math.sqrt(1.5) * read_noise_adu, 0.1 * (lvl - bias_level_adu))
            keep = spread <= tol
            stuck_bias = cand[keep]
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
        raw_long = (xs[-1].ravel()[stuck_all] + (master.ravel()[stuck_all] if master is not None
                                                  else bias_level_adu)).astype(np.float64)
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


def _dark_table(ts, images, groups, master, thresholds, nsigma) -> tuple[list[dict], list[np.ndarray]]:
    rows, xs = [], []
    for t, img, g in zip(ts, images, groups):
        cs = clipped_stats(img, sigma=3.0)
        x = img - master
        xcs = clipped_stats(x, sigma=3.0)
        counts = {f"{thr:g}": int(np.count_nonzero(x > thr)) for thr in thresholds}
        temps = [f.temperature_c for f in g if f.temperature_c is not None]
        rows.append({"exposure_s": float(t), "n_frames": len(g), "files": [f.path for f in g],
                     "median_adu": float(np.median(_flat_sample(img))), "inlier_mean_adu": cs["mean"],
                     "inlier_std_adu": cs["std"], "mean_all_adu": float(_flat_sample(img).mean(dtype=np.float64)),
                     "n_clipped": cs["n_rejected"],
                     "dark_signal_inlier_mean_adu": xcs["mean"], "dark_robust_sigma_adu": xcs["std"],
                     "count_above_bias_adu": counts,
                     f"count_above_{nsigma:g}_sigma": int(np.count_nonzero(x > xcs["median"] + nsigma * xcs["std"])),
                     "temperature_c": float(np.mean(temps)) if temps else None})
        xs.append(x)
    return rows, xs


def _fit_levels(ts, rows, key="inlier_mean_adu", bias_level=None):
    y = [r[key] for r in rows]
    if len(ts) >= 2:
        return linear_fit(ts, y)
    # one exposure time: the line through the bias level (t = 0)
    f = linear_fit([0.0, ts[0]], [bias_level, y[0]])
    f["note"] = "one dark exposure time: line through the bias level at t = 0"
    return f


def holdout_prediction(ts, rows, xs, sat_masks, hold: Sequence[float], bias_level: float, read_noise_adu: float,
                       thresholds: Sequence[float], nsigma: float, master: np.ndarray | None = None) -> dict:
    """Fit the dark line (and the hot-pixel law) on the other exposures; predict the held-out ones.

    For every held-out exposure ``t_h``:

    * the mean level (inlier mean) ``a + r t_h`` against the measured one, and the dark signal ``r t_h``
      against ``mean(t_h) - a``;
    * the number of pixels more than ``thr`` ADU above the bias, three ways: per pixel (each pixel's own
      straight line, fitted on the other exposures, extrapolated); from the fitted time-to-double law
      (``N_hot F(tau) + stuck pixels above thr``, with ``tau = B / (thr / t_h - r)`` the largest ``t_double``
      that puts a pixel above ``thr``); and empirically (the fitted pixels with ``t_double < tau``). The
      last two only see the hot pixels detected in the longest fitted dark: ``tau_within_detection_limit``
      says whether ``tau`` lies inside that population (otherwise they undercount).
    """
    hold = sorted(float(h) for h in hold)
    fit_sel = np.array([not any(np.isclose(t, h) for h in hold) for t in ts])
    hold_sel = ~fit_sel
    if fit_sel.sum() < 2 or hold_sel.sum() < 1:
        return {"note": "hold-out needs at least two fitted and one held-out exposure time",
                "exposures_s": hold}
    tf = ts[fit_sel]
    rows_f = [r for r, s in zip(rows, fit_sel) if s]
    fit = _fit_levels(tf, rows_f)
    xs_f = [x for x, s in zip(xs, fit_sel) if s]
    sm_f = [m for m, s in zip(sat_masks, fit_sel) if s]
    hp = analyze_hot_pixels(tf, xs_f, sm_f, fit["slope"], bias_level, nsigma, read_noise_adu, keep_per_pixel=True,
                            master=master)
    pp = hp.pop("_per_pixel")
    preds = []
    for t, r, x, sm, s in zip(ts, rows, xs, sat_masks, hold_sel):
        if not s:
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
        # per-pixel extrapolation over all pixels, in chunks of rows
        n_pp_all = {thr: 0 for thr in thresholds}
        rows_per = max(1, 1_000_000 // x.shape[1])
        for r0 in range(0, x.shape[0], rows_per):
            Yc = np.stack([xx[r0:r0 + rows_per].ravel() for xx in xs_f], axis=1)
            vc = ~np.stack([mm[r0:r0 + rows_per].ravel() for mm in sm_f], axis=1)
            b, a, _ = masked_linear_fit(tf, Yc, vc)
            p = a + b * t
            p = np.where(np.isnan(p), np.inf, p)  # saturated in every fitted dark: above any threshold
            for thr in thresholds:
                n_pp_all[thr] += int(np.count_nonzero(p > thr))
        for thr in thresholds:
            n_pp = n_pp_all[thr]
            tau = bias_level / (thr / t - fit["slope"]) if thr / t > fit["slope"] else math.inf
            stuck_above = int(np.count_nonzero(pp["stuck"] & (pp["x_long"] > thr)))
            n_hot = hp["n_hot"]
            law = hp["fits"].get("preferred")
            model = n_hot * (lifetime_cdf(hp["fits"], tau) if law else math.nan) + stuck_above
            emp = int(np.count_nonzero(pp["hot"] & (pp["t_double_s"] < tau))) + stuck_above
            meas = r["count_above_bias_adu"].get(f"{thr:g}", int(np.count_nonzero(x > thr)))
            entry["count_above_bias_adu"][f"{thr:g}"] = {
                "measured": meas, "per_pixel_extrapolation": n_pp, "t_double_law": model,
                "t_double_empirical": emp, "tau_s": tau,
                "tau_within_detection_limit": bool(tau <= hp["t_double_detection_limit_s"]),
                "rel_error_per_pixel": (n_pp - meas) / meas if meas else math.nan,
                "rel_error_t_double_law": (model - meas) / meas if meas else math.nan}
        preds.append(entry)
    return {"exposures_s": [float(t) for t in ts[hold_sel]], "fit_exposures_s": tf.tolist(),
            "fit": {k: fit[k] for k in ("intercept", "slope", "intercept_se", "slope_se", "dof")},
            "hot_pixels_fit": {"n_hot": hp["n_hot"], "n_stuck": hp["n_stuck"], "fits": hp["fits"],
                               "detection": hp["detection"]},
            "predictions": preds}


def analyze_darks(frames: Sequence[Frame], master: np.ndarray, bias_res: dict, gain: float,
                  nsigma: float, thresholds: Sequence[float], holdout_exposures) -> tuple[dict, dict, list[str]]:
    """Dark level vs exposure (thesis regression), DSNU, hot pixels, leave-one-out and hold-out."""
    warns: list[str] = []
    ts, images, groups = _group_darks(frames)
    bias_level = bias_res["level_median_adu"]
    read = bias_res["read_noise_adu"]
    rows, xs = _dark_table(ts, images, groups, master, thresholds, nsigma)
    sat = [np.zeros(img.shape, bool) if not math.isfinite(min(f.saturation_adu for f in g))
           else img >= min(f.saturation_adu for f in g) - 0.5 for img, g in zip(images, groups)]
    fit = _fit_levels(ts, rows, "inlier_mean_adu", bias_level)
    if len(ts) < 2:
        warns.append("darks at one exposure time only: dark rate from the line through the bias level")
    fit_med = _fit_levels(ts, rows, "median_adu", bias_level)
    fit_all = _fit_levels(ts, rows, "mean_all_adu", bias_level)
    for r in rows:
        r["predicted_inlier_mean_adu"] = fit["intercept"] + fit["slope"] * r["exposure_s"]
        r["residual_adu"] = r["inlier_mean_adu"] - r["predicted_inlier_mean_adu"]
    rate, rate_se = fit["slope"], fit["slope_se"]
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
    n_pix = min(images[-1].size, MAX_STAT_PIXELS)
    var_se = xl["dark_robust_sigma_adu"] ** 2 * math.sqrt(2.0 / n_pix)
    res["dsnu"] = {"exposure_s": xl["exposure_s"], "dark_signal_adu": d_sig,
                   "spatial_std_adu": math.sqrt(var_dsnu) if var_dsnu > 0 else 0.0,
                   "sigma_rel": (math.sqrt(var_dsnu) / d_sig) if var_dsnu > 0 and d_sig > 0 else 0.0,
                   "spatial_var_adu2": var_dsnu, "spatial_var_se_adu2": var_se,
                   "significant": bool(var_dsnu > 3 * var_se),
                   "method": "robust std of (longest dark - master bias) with the temporal noise of both (read "
                             "noise, dark shot noise = signal/gain) removed in quadrature, over the dark signal"}
    hot = analyze_hot_pixels(ts, xs, sat, rate, bias_level, nsigma, read, master=master)
    # leave-one-out
    loo = []
    if len(ts) >= 3:
        for i in range(len(ts)):
            sel = np.arange(len(ts)) != i
            f = linear_fit(ts[sel], [rows[j]["inlier_mean_adu"] for j in np.flatnonzero(sel)])
            p = f["intercept"] + f["slope"] * ts[i]
            m = rows[i]["inlier_mean_adu"]
            loo.append({"exposure_s": float(ts[i]), "predicted_adu": p, "measured_adu": m,
                        "rel_error": (p - m) / m, "dark_signal_rel_error":
                        (f["slope"] * ts[i] - (m - f["intercept"])) / (m - f["intercept"])
                        if m != f["intercept"] else math.nan})
    res["leave_one_out"] = loo
    if holdout_exposures is None:
        holdout_exposures = [float(ts[-1])] if len(ts) >= 3 else []
    unknown = [h for h in holdout_exposures if not np.isclose(ts, float(h)).any()]
    if unknown:
        raise DetectorError(f"hold-out exposure(s) {unknown} s not among the darks",
                            key="holdout_exposures", expected="one of " + ", ".join(f"{t:g}" for t in ts))
    res["holdout"] = holdout_prediction(ts, rows, xs, sat, holdout_exposures, bias_level, read, thresholds,
                                        nsigma, master) if len(holdout_exposures) else {"note": "no hold-out"}
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
    frame and on ``tiles x tiles`` tiles (the tiles' spread gives the standard error).
    """
    a = f0.astype(np.float64) - master
    b = f1.astype(np.float64) - master

    def one(aa, bb):
        sa, sb = clipped_stats(aa, 5.0)["mean"], clipped_stats(bb, 5.0)["mean"]
        s = sa / sb
        d = aa - s * bb
        var = clipped_stats(d, 5.0)["std"] ** 2 / (1 + s * s)
        sig = 0.5 * (sa + s * sb)
        shot = var - read_noise_adu ** 2
        return sig, var, shot, s

    sig, var, shot, s = one(a, b)
    h, w = a.shape
    ks, pts = [], []
    for i in range(tiles):
        for j in range(tiles):
            sl = (slice(i * h // tiles, (i + 1) * h // tiles), slice(j * w // tiles, (j + 1) * w // tiles))
            ts_, tv, tsh, _ = one(a[sl], b[sl])
            pts.append([ts_, tv])
            if tsh > 0:
                ks.append(ts_ / tsh)
    K = sig / shot if shot > 0 else math.nan
    n = a.size
    se_stat = K * math.sqrt(2 / n) * var / shot if shot > 0 else math.nan
    se_tiles = float(np.std(ks, ddof=1) / math.sqrt(len(ks))) if len(ks) > 2 else math.nan
    return {"signal_adu": sig, "variance_adu2": var, "shot_variance_adu2": shot, "scale_second_flat": s,
            "gain_e_per_adu": K, "gain_se_statistical": se_stat, "gain_se_tiles": se_tiles,
            "gain_se": float(np.nanmax([se_stat, se_tiles])), "tile_gains": ks,
            "signal_e": sig * K if shot > 0 else math.nan,
            "plot_data": {"tiles_signal_variance": pts, "read_variance_adu2": read_noise_adu ** 2}}


def prnu_and_vignetting(mean_flat: np.ndarray, temporal_var_adu2: float, smooth_px: float = 16.0,
                        box_frac: float = 0.1) -> dict:
    """PRNU (small-scale fixed pattern of a bias-subtracted mean flat) and large-scale vignetting.

    The flat is divided by its Gaussian-smoothed self (sigma ``smooth_px`` pixels, outliers replaced by the
    median first): large-scale illumination and vignetting go, the pixel-to-pixel response stays.
    ``PRNU = sqrt(std(ratio)^2 - temporal_var / S^2)`` (EMVA 1288, the temporal noise of the averaged flat
    removed in quadrature); border of ``2 smooth_px`` excluded. Vignetting: medians of the smoothed flat in
    the four corner boxes (``box_frac`` of the frame's sides) over the centre box.
    """
    f = mean_flat.astype(np.float64)
    cs = clipped_stats(f, 5.0)
    clean = np.where((f < cs["lo"] - 5 * cs["std"]) | (f > cs["hi"] + 5 * cs["std"]), cs["median"], f)
    smooth = ndimage.gaussian_filter(clean, smooth_px, mode="nearest")
    b = int(2 * smooth_px)
    h, w = f.shape
    inner = (slice(b, h - b), slice(b, w - b)) if h > 4 * b and w > 4 * b else (slice(None), slice(None))
    ratio = f[inner] / smooth[inner]
    rs = clipped_stats(ratio, 5.0)
    S = cs["median"]
    var_rel = rs["std"] ** 2 - temporal_var_adu2 / (S * S)
    bh, bw = max(1, int(h * box_frac)), max(1, int(w * box_frac))
    cy, cx = h // 2 - bh // 2, w // 2 - bw // 2
    centre = float(np.median(smooth[cy:cy + bh, cx:cx + bw]))
    corners = {"first_row_first_col": smooth[:bh, :bw], "first_row_last_col": smooth[:bh, -bw:],
               "last_row_first_col": smooth[-bh:, :bw], "last_row_last_col": smooth[-bh:, -bw:]}
    ratios = {k: float(np.median(v)) / centre for k, v in corners.items()}
    step = max(1, max(h, w) // 64)
    return {"prnu_rel": math.sqrt(var_rel) if var_rel > 0 else 0.0, "ratio_std_raw": rs["std"],
            "temporal_rel_std": math.sqrt(temporal_var_adu2) / S, "smoothing_sigma_px": smooth_px,
            "vignetting": {"corner_over_centre": ratios,
                           "corner_over_centre_mean": float(np.mean(list(ratios.values()))),
                           "min_over_centre": float(smooth.min() / centre), "box_px": [bw, bh]},
            "plot_data": {"smooth_map_rel": (smooth[::step, ::step] / centre).tolist()}}


def analyze_flats(frames: Sequence[Frame], master: np.ndarray, bias_res: dict) -> tuple[dict, list[str]]:
    warns: list[str] = []
    if len(frames) != 2:
        raise DetectorError(f"{len(frames)} flat frames given", key="flat",
                            expected="exactly two flats of the same illumination and exposure")
    f0, f1 = frames
    read = bias_res["read_noise_adu"]
    pt = photon_transfer(f0.data, f1.data, master, read)
    mean_flat = 0.5 * (f0.data.astype(np.float64) + pt["scale_second_flat"] * f1.data.astype(np.float64)) - master
    temporal = pt["variance_adu2"] / 2 + read ** 2 / max(bias_res["n_frames"], 1)
    pv = prnu_and_vignetting(mean_flat, temporal)
    sat = min(f.saturation_adu for f in frames)
    raw_med = float(np.median(_flat_sample(f0.data)))
    if math.isfinite(sat) and raw_med > 0.8 * sat:
        warns.append(f"flats are at {raw_med:.0f} ADU, near saturation {sat:.0f}: photon transfer is biased")
    res = {"files": [f.path for f in frames], "exposure_s": [f.exptime_s for f in frames],
           "median_raw_adu": [raw_med, float(np.median(_flat_sample(f1.data)))],
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
                 count_thresholds_adu: Sequence[float] = (100.0, 1000.0), seed: int = 0) -> dict:
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

    Returns
    -------
    dict (JSON-serialisable): ``frame``, ``gain``, ``bias``, ``dark``, ``hot_pixels``, ``flat`` (or None),
    ``warnings``; ``*.plot_data`` entries feed :func:`detector.calplots.write_plots`.
    """
    bias_paths, dark_paths = list(bias_paths or []), list(dark_paths or [])
    flat_paths = list(flat_paths or [])
    if not bias_paths:
        raise DetectorError("no bias frame given", key="bias", expected="one or more bias FITS files")
    if not dark_paths:
        raise DetectorError("no dark frame given", key="dark", expected="one or more dark FITS files")
    rng = np.random.default_rng(seed)
    thresholds = [float(t) for t in count_thresholds_adu]
    bias = read_frames(bias_paths, "bias", need_exptime=False)
    shape, ref = bias[0].data.shape, bias[0].path
    darks = read_frames(dark_paths, "dark", need_exptime=True, shape=shape, shape_file=ref)
    flats = read_frames(flat_paths, "flat", need_exptime=False, shape=shape, shape_file=ref) if flat_paths else []
    warns: list[str] = []

    bias_res, master, w = analyze_bias(bias, rng)
    warns += w
    flat_res = None
    if flats:
        flat_res, w = analyze_flats(flats, master, bias_res)
        warns += w
    g_hdr, g_key, g_file = header_gain(bias + darks + flats)
    pt_gain = flat_res["photon_transfer"]["gain_e_per_adu"] if flat_res else math.nan
    if g_hdr is not None:
        gain, source = g_hdr, f"header {g_key} ({g_file})"
    elif flat_res and math.isfinite(pt_gain) and pt_gain > 0:
        gain, source = pt_gain, "photon transfer (flat pair)"
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
    dark_res, hot_res, w = analyze_darks(darks, master, bias_res, gain, hot_sigma, thresholds, holdout_exposures)
    warns += w
    if flat_res:
        ft = [t for t in flat_res["temperature_c"] if t is not None]
        if ft and dark_res["temperature_c"] is not None and abs(np.mean(ft) - dark_res["temperature_c"]) > 2:
            warns.append(f"flats at {np.mean(ft):.1f} C, darks at {dark_res['temperature_c']:.1f} C")
        flat_res["signal_e"] = flat_res["signal_adu"] * gain
    sats = {f.saturation_adu for f in bias + darks + flats}
    h, w_ = shape
    header0 = darks[-1].header
    integer = all(bool(np.all(f.data[:16, :16] == np.floor(f.data[:16, :16]))) for f in bias + darks)
    frame = {"width": int(w_), "height": int(h), "n_bias": len(bias), "n_dark": len(darks), "n_flat": len(flats),
             "integer_data": integer,
             "saturation_adu": float(min(sats)), "instrument": str(header0.get("INSTRUME", "")).strip() or None,
             "pixel_size_um": _pixel_size(header0), "binning": int(header0.get("XBINNING", 1) or 1),
             "bit_depth": _bit_depth(header0, min(sats))}
    result = {"frame": frame, "gain": gain_res, "bias": bias_res, "dark": dark_res, "hot_pixels": hot_res,
              "flat": flat_res, "warnings": warns}
    return jsonable(result)


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
    these frames). For integer frames the bias is the clipped mean + 1/2 ADU and the read noise has the
    quantisation variance (1/12 ADU^2) removed, because newtsim's ADC truncates and quantises again.
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
    # newtsim's ADC truncates (floor): a frame of bias B reads B - 1/2 on average, and the quantisation adds
    # 1/12 ADU^2 to the read variance; undo both so that a simulated frame reads what was measured
    bias_adu = float(b["level_mean_adu"]) + (0.5 if integer else 0.0)
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
