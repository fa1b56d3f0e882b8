"""Where the model fails: statistics of the normalised residuals ``z = (data - model) / sigma_model``.

Everything here is a pure function of a :class:`detector.signatures.Residuals` (and the model's truth
table), returning plain dicts and small arrays that the JSON, the HTML report and the ledger use:

* ``chi2_per_dof`` over the pixels the model predicts deterministically (DESIGN.md contract), with the
  pixels it can only predict statistically (spikes, outlier columns, saturation) compared by their counts;
* global statistics (median, mean, std, robust std) of the measurement and of one model realisation
  (the thesis's Annex VII columns);
* per region (centre, edges, corners, quadrants, radial zones), row and column profiles, the residual
  power spectrum, the histogram and QQ of z;
* per source: aperture photometry, centroid and size of catalogue stars; streak profiles along the track;
* a ``misfit`` score: the standardised excess of every deviance (pixels, outlier counts), ~1 for a model
  that explains the frame, so rounds of diagnose/apply can be compared on one number.
"""

from __future__ import annotations

import numpy as np
from scipy import stats as sstats

from detector.signatures import Residuals, two_sample_count_gain
from detector.stats import mad_std

#: block size target for the residual map in the report (pixels per side of the small map)
MAP_SIDE = 256
#: side [pixels] of the central cut-out of the z map whose full-resolution spectrum is searched for peaks
PEAK_SIDE = 512


def robust_std(x: np.ndarray) -> float:
    """1.4826 x median absolute deviation of every value: the std of a Gaussian, insensitive to outliers.

    Integer-valued data (ADU) are read as grouped data, each code spread evenly over +-1/2 about it (a fixed
    low-discrepancy offset per value, the golden-ratio sequence): the statistic is then continuous in the
    data's level, where the plain median absolute deviation jumps by whole codes (a robust std of ~13 codes
    moved by 8 % between two frames of one scene)."""
    v = np.asarray(x, np.float64).ravel()
    if v.size and np.all(v == np.rint(v)):
        v = v + (np.arange(v.size) * 0.6180339887498949) % 1.0 - 0.5
    return mad_std(v, max_n=None)


def global_stats(img: np.ndarray) -> dict:
    """The thesis's frame statistics (Annex VII): median, mean, std, plus a robust std [ADU]."""
    a = np.asarray(img, np.float64)
    sub = a.ravel()[:: max(1, a.size // 2_000_000)]
    return {"median": float(np.median(sub)), "mean": float(a.mean()), "std": float(a.std()),
            "robust_std": robust_std(sub), "min": float(a.min()), "max": float(a.max())}


def zmap(res: Residuals) -> np.ndarray:
    """Normalised residual of every pixel (0 where the model cannot compare pixel by pixel)."""
    z = (res.data_adu - res.model_adu) / np.sqrt(res.var_adu2)
    return np.where(res.fit, z, 0.0).astype(np.float32)


def _region_masks(shape: tuple[int, int]) -> dict[str, np.ndarray]:
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w]
    u, v = (xx + 0.5) / w - 0.5, (yy + 0.5) / h - 0.5
    edge = np.maximum(np.abs(u), np.abs(v)) > 0.4
    corner = (np.abs(u) > 0.4) & (np.abs(v) > 0.4)
    r = np.hypot(u, v) / np.hypot(0.5, 0.5)
    out = {"centre": (np.abs(u) < 1 / 6) & (np.abs(v) < 1 / 6), "edges": edge & ~corner, "corners": corner,
           "quadrant_lower_left": (u < 0) & (v < 0), "quadrant_lower_right": (u >= 0) & (v < 0),
           "quadrant_upper_left": (u < 0) & (v >= 0), "quadrant_upper_right": (u >= 0) & (v >= 0)}
    for i in range(5):
        out[f"radial_{i}"] = (r >= i / 5) & (r < (i + 1) / 5 if i < 4 else r <= 1.0001)
    return out


def region_table(res: Residuals, z: np.ndarray) -> dict[str, dict]:
    """chi2/dof, mean z and mean residual [ADU] per region (y = rows upward, x = columns rightward)."""
    r = res.data_adu - res.model_adu
    out = {}
    for name, m in _region_masks(z.shape).items():
        sel = m & res.fit
        n = int(sel.sum())
        if n == 0:
            continue
        zz = z[sel].astype(np.float64)
        out[name] = {"n": n, "chi2_per_dof": float(np.dot(zz, zz) / n), "mean_z": float(zz.mean()),
                     "mean_residual_adu": float(r[sel].mean()), "data_mean_adu": float(res.data_adu[sel].mean()),
                     "model_mean_adu": float(res.model_adu[sel].mean())}
    return out


def profiles(res: Residuals) -> dict:
    """Mean residual [ADU] per row and per column over the fitted pixels, and their z (standard errors).

    The variance of a row's mean over n pixels is ``sum(var) / n^2`` plus ``(1 - 1/n) c``, with ``c`` the
    covariance the pixels of a row share (``row_var_adu2`` of the model: row noise); a column's mean averages
    independent rows, so ``sum(var) / n^2`` (which holds the row noise's variance) is all of it."""
    out = {}
    r = np.where(res.fit, res.data_adu - res.model_adu, 0.0)
    v = np.where(res.fit, res.var_adu2, 0.0)
    row_cov = float(res.row_var_adu2)
    for axis, name in ((1, "row"), (0, "column")):
        n = res.fit.sum(axis=axis)
        mean = r.sum(axis=axis) / np.maximum(n, 1)
        shared = row_cov * (1 - 1 / np.maximum(n, 1)) if name == "row" else 0.0
        err = np.sqrt(v.sum(axis=axis) / np.maximum(n, 1) ** 2 + shared)
        zz = np.where(n > 0, mean / np.maximum(err, 1e-12), 0.0)
        out[name] = {"mean_residual_adu": mean.astype(np.float32), "z": zz.astype(np.float32),
                     "chi2_per_dof": float(np.mean(zz[n > 0] ** 2)) if (n > 0).any() else float("nan")}
    return out


def power_spectrum(z: np.ndarray, nbins: int = 40) -> dict:
    """Radially averaged power of z [1/pixel frequency] and the 1-D spectra along rows and columns.

    White noise gives a flat spectrum at 1 (Parseval: mean |FFT|^2 / N = var(z)); structure at large
    scales rises at low frequency, periodic patterns make peaks.
    """
    h, w = z.shape
    f = np.fft.rfft2(z - z.mean())
    p = (np.abs(f) ** 2) / z.size
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    fr = np.hypot(fy, fx)
    edges = np.linspace(0, 0.5 * np.sqrt(2), nbins + 1)
    idx = np.clip(np.digitize(fr.ravel(), edges) - 1, 0, nbins - 1)
    s = np.bincount(idx, p.ravel(), nbins)
    c = np.bincount(idx, minlength=nbins)
    radial = np.where(c > 0, s / np.maximum(c, 1), np.nan)
    rows = np.abs(np.fft.rfft(z.mean(axis=1) - z.mean())) ** 2 / h * w  # per-row means: white -> 1
    cols = np.abs(np.fft.rfft(z.mean(axis=0) - z.mean())) ** 2 / w * h
    return {"freq": 0.5 * (edges[1:] + edges[:-1]), "radial": radial,
            "row_freq": np.fft.rfftfreq(h), "row_power": rows, "col_freq": np.fft.rfftfreq(w), "col_power": cols,
            "low_freq_power": float(np.nanmean(radial[:3]))}


def source_mask(res: Residuals) -> np.ndarray:
    """Pixels where the model's sources add more than one sigma to its background (:func:`background_adu`)."""
    return (res.model_adu - background_adu(res)) > np.sqrt(res.var_adu2)


def spectrum_peaks(z: np.ndarray, side: int = PEAK_SIDE, n_peaks: int = 5, weights: np.ndarray | None = None,
                   row_var_adu2: float = 0.0) -> dict:
    """The strongest periodic patterns of z at full resolution, pixel-scale ones included (a Bayer mosaic
    at the Nyquist frequency (0.5, 0.5), which the block-averaged spectrum cannot show).

    The 2-D power of a central ``side`` x ``side`` cut-out of z (give it with 0 where nothing is compared),
    its 3 x 3 local maxima ranked by power over the median power. White noise: the strongest of ~1e5
    frequencies is ~15-25 x the median. Returns ``side`` and ``peaks``: ``[{"fx", "fy" [cycles/pixel],
    "power_ratio"}]``, best first (fx >= 0; fy >= 0 where fx is 0 or 0.5, which rfft2 holds twice).

    With the pixels' ``weights`` [1/ADU^2] (0 where z is 0) and the model's row covariance ``row_var_adu2``
    [ADU^2] (row noise), the ``fx = 0`` column is divided by the power the row offsets put there
    (:func:`detector.morphology.row_power_factor`): its ratios are then to the null too, and the row noise
    the model has is no peak.
    """
    from scipy import ndimage

    from detector.morphology import row_power_factor

    h, w = z.shape
    y0, x0 = max(0, (h - side) // 2), max(0, (w - side) // 2)
    cut = np.asarray(z[y0:y0 + side, x0:x0 + side], np.float64)
    p = np.abs(np.fft.rfft2(cut - cut.mean())) ** 2 / max(cut.size, 1)
    fy, fx = np.fft.fftfreq(cut.shape[0]), np.fft.rfftfreq(cut.shape[1])
    med = float(np.median(p))
    if weights is not None and row_var_adu2 > 0:
        p[:, 0] /= row_power_factor(np.asarray(weights[y0:y0 + side, x0:x0 + side], np.float64), row_var_adu2)
    p[0, 0] = 0.0
    p[np.ix_((fy < 0) & (fy > -0.5), (fx == 0) | (fx == 0.5))] = 0.0  # mirror images within those columns
    local = p == ndimage.maximum_filter(p, size=3, mode="wrap")
    best = np.argsort(-np.where(local, p, 0.0), axis=None)[:n_peaks]
    peaks = [{"fx": float(fx[j]), "fy": float(abs(fy[i]) if fy[i] == -0.5 else fy[i]),
              "power_ratio": float(p[i, j] / med) if med > 0 else float("nan")}
             for i, j in zip(*np.unravel_index(best, p.shape))]
    return {"side": int(min(cut.shape)), "peaks": peaks}


def distribution(res: Residuals, z: np.ndarray, realisation: np.ndarray | None) -> dict:
    """Histogram and QQ of z over the fitted pixels; histograms of measured and model-realisation ADU."""
    zz = z[res.fit]
    sub = zz[:: max(1, zz.size // 200_000)].astype(np.float64)
    q = np.linspace(0.001, 0.999, 99)
    edges = np.linspace(-8, 8, 81)
    out = {"z_edges": edges, "z_hist": np.histogram(zz, edges)[0],
           "qq_normal": sstats.norm.ppf(q), "qq_z": np.quantile(sub, q) if sub.size else np.zeros(q.size),
           "skew": float(sstats.skew(sub)) if sub.size > 2 else 0.0,
           "kurtosis": float(sstats.kurtosis(sub)) if sub.size > 3 else 0.0}
    lo, hi = np.percentile(res.data_adu[:: 7, :: 7], [0.1, 99.9])
    adu_edges = np.linspace(lo, hi + 1, 81)
    out["adu_edges"] = adu_edges
    out["data_hist"] = np.histogram(res.data_adu, adu_edges)[0]
    if realisation is not None:
        out["model_hist"] = np.histogram(realisation, adu_edges)[0]
    return out


def outlier_counts(res: Residuals) -> dict:
    """Measured against one model realisation's outlier counts. Both are Poisson draws, so ``deviance`` is the
    likelihood ratio of two Poisson samples, separate rates against a common one
    (:func:`detector.signatures.two_sample_count_gain`, sign flipped): ~chi2(1), mean ~1, when they agree."""
    d, m = res.data_spikes.counts(), res.model_spikes.counts()
    return {k: {"data": d[k], "model": m[k], "deviance": 0.0 - two_sample_count_gain(d[k], m[k])} for k in d}


# --- sources ---------------------------------------------------------------------------------------------------

def _moments(stamp: np.ndarray, yy: np.ndarray, xx: np.ndarray) -> tuple[float, float, float, float]:
    w = np.clip(stamp, 0, None)
    s = w.sum()
    if s <= 0:
        return np.nan, np.nan, np.nan, 0.0
    cx, cy = (w * xx).sum() / s, (w * yy).sum() / s
    r2 = ((w * ((xx - cx) ** 2 + (yy - cy) ** 2)).sum() / s)
    return float(cx), float(cy), float(np.sqrt(r2 / 2)), float(s)


def background_adu(res: Residuals) -> np.ndarray:
    """The model's mean frame without its sources [ADU]: sky (or flat screen) and straylight through the chain,
    dark signal and bias (``background_adu`` that :func:`scenes.app.compare.model.residuals` attaches). Without
    it, bias and dark plus the uniform part of the photo-signal (:meth:`Residuals.level_templates`)."""
    return res.without_sources_adu


def star_photometry(res: Residuals, truth: np.ndarray | None, radius_px: float = 4.0, max_stars: int = 2000) -> dict:
    """Aperture photometry of catalogue stars in measurement and model, the model's whole background
    (:func:`background_adu`, sky included) subtracted from both.

    For each star of the TRUTH table inside the frame (brightest first): flux ratio data/model in a circular
    aperture, centroid offset [px] and Gaussian-equivalent size sigma [px] of both; trends of the flux
    ratio with magnitude and with field radius (least-squares slopes).
    """
    if truth is None or len(truth) == 0 or "kind" not in truth.dtype.names:
        return {"n": 0}
    kind = np.char.strip(np.asarray(truth["kind"]).astype(str))
    st = truth[kind == "star"]
    if len(st) == 0:
        return {"n": 0}
    h, w = res.data_adu.shape
    rad = int(np.ceil(radius_px))
    inside = (st["x"] > rad) & (st["x"] < w - 1 - rad) & (st["y"] > rad) & (st["y"] < h - 1 - rad)
    st = st[inside]
    st = st[np.argsort(-st["flux_e"])][:max_stars]
    yy, xx = np.mgrid[-rad:rad + 1, -rad:rad + 1]
    ap = (xx ** 2 + yy ** 2) <= radius_px ** 2
    bg = background_adu(res)
    rows = []
    for s_ in st:
        xi, yi = round(float(s_["x"])), round(float(s_["y"]))
        sl = (slice(yi - rad, yi + rad + 1), slice(xi - rad, xi + rad + 1))
        d = (res.data_adu[sl] - bg[sl]) * ap
        m = (res.model_adu[sl] - bg[sl]) * ap
        var = (res.var_adu2[sl] * ap).sum()
        fd, fm = float(d.sum()), float(m.sum())
        if fm <= 3 * np.sqrt(var):
            continue
        cxd, cyd, sd, _ = _moments(d, yy, xx)
        cxm, cym, sm, _ = _moments(m, yy, xx)
        rows.append((s_["mag"] if "mag" in st.dtype.names else np.nan, s_["x"], s_["y"], fd / fm,
                     np.sqrt(var) / fm, cxd - cxm, cyd - cym, sd, sm))
    if not rows:
        return {"n": 0}
    a = np.array(rows, dtype=float)
    r_field = np.hypot(a[:, 1] - (w - 1) / 2, a[:, 2] - (h - 1) / 2) / np.hypot(w / 2, h / 2)
    out = {"n": len(rows), "mag": a[:, 0], "x": a[:, 1], "y": a[:, 2], "flux_ratio": a[:, 3], "flux_ratio_err": a[:, 4],
           "dx_px": a[:, 5], "dy_px": a[:, 6], "size_data_px": a[:, 7], "size_model_px": a[:, 8], "r_field": r_field,
           "median_flux_ratio": float(np.nanmedian(a[:, 3])),
           "median_offset_px": float(np.nanmedian(np.hypot(a[:, 5], a[:, 6]))),
           "mean_offset_px": [float(np.nanmean(a[:, 5])), float(np.nanmean(a[:, 6]))],
           "median_size_ratio": float(np.nanmedian(a[:, 7] / a[:, 8]))}
    if len(rows) >= 3:
        ok = np.isfinite(a[:, 3])
        out["flux_ratio_vs_radius_slope"] = float(np.polyfit(r_field[ok], a[ok, 3], 1)[0])
        if np.isfinite(a[:, 0]).sum() >= 3:
            okm = ok & np.isfinite(a[:, 0])
            out["flux_ratio_vs_mag_slope"] = float(np.polyfit(a[okm, 0], a[okm, 3], 1)[0])
    return out


def track_band(shape: tuple[int, int], row, half_width_px: float) -> dict | None:
    """The pixels around an object's straight track from (x0, y0) to (x1, y1) of its TRUTH ``row``: the
    bounding box (a pair of slices into a frame of ``shape``) and, on it, every pixel's distance ``along``
    the track from (x0, y0) and ``across`` it [px], and the track's ``length``; None when the box is empty."""
    h, w = shape
    p0, p1 = np.array([row["x0"], row["y0"]], float), np.array([row["x1"], row["y1"]], float)
    length = float(np.hypot(*(p1 - p0)))
    if length <= 0:
        return None
    t_hat = (p1 - p0) / length
    x0, x1 = int(max(0, min(p0[0], p1[0]) - half_width_px - 2)), int(min(w, max(p0[0], p1[0]) + half_width_px + 3))
    y0, y1 = int(max(0, min(p0[1], p1[1]) - half_width_px - 2)), int(min(h, max(p0[1], p1[1]) + half_width_px + 3))
    if x1 <= x0 or y1 <= y0:
        return None
    yy, xx = np.mgrid[y0:y1, x0:x1]
    along = (xx - p0[0]) * t_hat[0] + (yy - p0[1]) * t_hat[1]
    across = (xx - p0[0]) * -t_hat[1] + (yy - p0[1]) * t_hat[0]
    return {"box": (slice(y0, y1), slice(x0, x1)), "along": along, "across": across, "length": length}


def streak_profiles(res: Residuals, truth: np.ndarray | None, segments: int = 10, half_width_px: float = 6.0) -> list:
    """For each object (streak) of the TRUTH table: flux data/model and cross-track offset [px] along its
    length, in ``segments`` equal parts of the track from (x0, y0) to (x1, y1); the model's whole background
    (:func:`background_adu`) subtracted from data and model."""
    if truth is None or len(truth) == 0 or "x0" not in truth.dtype.names:
        return []
    kind = np.char.strip(np.asarray(truth["kind"]).astype(str))
    out = []
    bg = background_adu(res)
    for o in truth[kind != "star"]:
        band = track_band(res.data_adu.shape, o, half_width_px)
        if band is None or band["length"] < 2:
            continue
        box, along, across, length = band["box"], band["along"], band["across"], band["length"]
        sel = (np.abs(across) <= half_width_px) & (along >= 0) & (along <= length)
        seg = np.minimum((along / length * segments).astype(int), segments - 1)
        d = res.data_adu[box] - bg[box]
        m = res.model_adu[box] - bg[box]
        fd = np.bincount(seg[sel], d[sel], segments)
        fm = np.bincount(seg[sel], m[sel], segments)
        cd = np.bincount(seg[sel], (d * across)[sel], segments)
        cm = np.bincount(seg[sel], (m * across)[sel], segments)
        with np.errstate(invalid="ignore", divide="ignore"):
            name = o["name"] if "name" in truth.dtype.names else b""
            out.append({"name": (name.decode() if isinstance(name, bytes) else str(name)).strip(),
                        "length_px": length, "flux_ratio": fd / fm, "offset_px": cd / fd - cm / fm,
                        "total_flux_ratio": float(fd.sum() / fm.sum()) if fm.sum() > 0 else float("nan")})
    return out


# --- the whole comparison ----------------------------------------------------------------------------------------

def small_map(z: np.ndarray, side: int = MAP_SIDE) -> tuple[np.ndarray, int]:
    """Block mean of z with blocks of k x k so the map is about ``side`` pixels across; z of a block mean is
    rescaled by k (white noise keeps unit variance)."""
    k = max(1, int(np.ceil(max(z.shape) / side)))
    h, w = (z.shape[0] // k) * k, (z.shape[1] // k) * k
    m = z[:h, :w].reshape(h // k, k, w // k, k).mean(axis=(1, 3)) * k
    return m.astype(np.float32), k


def misfit(chi2: float, dof: int, counts: dict, extra: dict | None = None) -> float:
    """Standardised excess of the deviances: ``max(0, (chi2 - dof) / sqrt(2 dof))`` for the pixels plus, for
    each outlier class, ``max(0, (D - 1) / sqrt(2))`` (the two-sample count statistic of
    :func:`outlier_counts` is ~chi2(1): mean 1, variance 2), plus any ``extra`` standardised terms. ~0-2 when the model explains the frame."""
    total = max(0.0, (chi2 - dof) / np.sqrt(2 * max(dof, 1)))
    for c in counts.values():
        total += max(0.0, (c["deviance"] - 1) / np.sqrt(2))
    for v in (extra or {}).values():
        total += max(0.0, v)
    return float(total)


def level_fit(res: Residuals) -> dict:
    """chi2/dof with the global levels refitted (:func:`detector.signatures.level_profiled`: light, background,
    bias offset and dark level as nuisance parameters, their shot noise included; dof = pixels - levels) and
    the fitted levels: relative changes of the light, background and dark signal [1], the offset [ADU]; and
    ``levels_adu``: each fitted change at the mean fitted pixel [ADU] (what a relative change means when the
    model's level is near zero, e.g. the dark signal of a short exposure)."""
    lv = res.levels()
    dof = max(res.n_fit - len(lv["keep"]), 1)
    idx, shape = res.flat()[0], res.data_adu.shape
    temps = res.level_templates()
    delta = {}  # the fitted change at the mean fitted pixel [ADU]: readable where the model's level is ~0
    for name, c, i in zip(lv["names"], lv["coef"], lv["keep"]):
        t = np.asarray(temps[i])
        mean = float(t.ravel()[0]) if t.size == 1 else float(np.mean(np.broadcast_to(t, shape).ravel()[idx]))
        delta[name] = float(c) * mean
    return {"chi2_per_dof_levels": res.chi2_profiled() / dof,
            "levels": {name: float(c) for name, c in zip(lv["names"], lv["coef"])},
            "levels_adu": delta}


def compare(res: Residuals, truth=None, realisation: np.ndarray | None = None) -> dict:
    """All statistics of the comparison (JSON-able after :func:`detector.jsonable.jsonable`)."""
    z = zmap(res)
    n = res.n_fit
    chi2 = res.chi2()
    prof = profiles(res)
    counts = outlier_counts(res)
    rows_excess = (prof["row"]["chi2_per_dof"] - 1) * np.sqrt(len(prof["row"]["z"]) / 2)
    cols_excess = (prof["column"]["chi2_per_dof"] - 1) * np.sqrt(len(prof["column"]["z"]) / 2)
    zsmall, k = small_map(z)
    out = {
        "chi2_per_dof": chi2 / max(n, 1), "n_pixels": int(res.fit.size), "n_compared": n,
        "n_statistical": int(res.fit.size - n),
        "measured": global_stats(res.data_adu),
        "model": global_stats(realisation if realisation is not None else res.model_adu),
        "model_mean": global_stats(res.model_adu),
        "regions": region_table(res, z),
        "profiles": prof, "power": power_spectrum(zsmall), "distribution": distribution(res, z, realisation),
        "outliers": counts, "stars": star_photometry(res, truth), "streaks": streak_profiles(res, truth),
        "z_map": zsmall, "z_map_block": k,
    }
    used = res.fit & ~source_mask(res)
    out["power_peaks"] = spectrum_peaks(np.where(used, z, 0.0), weights=np.where(used, 1.0 / res.var_adu2, 0.0),
                                        row_var_adu2=res.row_var_adu2)
    out.update(level_fit(res))
    out["misfit"] = misfit(chi2, n, counts, {"rows": rows_excess, "columns": cols_excess})
    out["worst_regions"] = sorted(out["regions"], key=lambda r: -out["regions"][r]["chi2_per_dof"])[:3]
    return out


def summary(result: dict) -> dict:
    """The JSON of the contract: the headline numbers without the large arrays."""
    keep = ("chi2_per_dof", "chi2_per_dof_levels", "levels", "misfit", "n_pixels", "n_compared", "n_statistical", "measured", "model", "model_mean",
            "regions", "outliers", "worst_regions")
    out = {k: result[k] for k in keep if k in result}
    out["profiles"] = {k: {"chi2_per_dof": v["chi2_per_dof"]} for k, v in result["profiles"].items()}
    st = result.get("stars", {})
    out["stars"] = {k: v for k, v in st.items() if not isinstance(v, np.ndarray)}
    out["streaks"] = [{"name": s["name"], "length_px": s["length_px"], "total_flux_ratio": s["total_flux_ratio"]}
                      for s in result.get("streaks", [])]
    out["power_low_freq"] = result["power"]["low_freq_power"]
    if "power_peaks" in result:
        out["power_peaks"] = result["power_peaks"]
    out["distribution"] = {k: result["distribution"][k] for k in ("skew", "kurtosis")}
    return out
