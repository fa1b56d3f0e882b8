"""Raw frames and calibration frames: prescan/overscan trimming and the camera from whatever is given.

* Overscan: ``BIASSEC`` (the overscan) and ``TRIMSEC``/``DATASEC`` (the light-sensitive pixels) when the header
  has them; otherwise found from the data: a block of at least 4 edge columns (or rows) whose level is
  flat (no light: the column-to-column spread of their medians is below the noise) and clearly below the
  image's (Howell 2006, Handbook of CCD Astronomy, sect. 4.3). The overscan's median is the bias level of
  that very frame, its robust spread the read noise in ADU.
* Bias frames: the master (median) bias level, the read noise from a pair difference
  (sigma_read = std(B1 - B2) / sqrt 2, Janesick 2007, eq. 4.3), else from one frame's robust std.
* Darks: the dark rate (median(D - bias) / t) [ADU/s] and a dark-rate map.
* Flats: the flat's level; with two flats of the same level, the photon-transfer gain
  K = S / (var(F1 - F2)/2 - sigma_read^2) (Janesick 2007, eq. 4.7, the pair difference removing the flat
  pattern); with one flat, the gain from the local variance of a high-passed flat (an upper bound: the pixel
  response non-uniformity adds to it), stated as such. The normalised flat (a ``flat_map``) when given.
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from detector.stats import mad_std
from scenes.measured import parse_section, read_hdu, section_text

from .header import Value


def robust_std(x) -> float:
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    return float(mad_std(x, max_n=None)) if x.size else math.nan


def find_overscan(data: np.ndarray, header=None, min_cols: int = 4, max_frac: float = 0.25) -> dict | None:
    """The overscan/prescan of a raw frame: ``{"trim": FITS section of the data, "bias": section, "level_adu",
    "noise_adu", "source"}``, or None. Header cards first (BIASSEC with TRIMSEC/DATASEC), else the data."""
    h, w = data.shape
    if header is not None and "BIASSEC" in header:
        try:
            brows, bcols = parse_section(str(header["BIASSEC"]))
            trim_card = next((c for c in ("TRIMSEC", "DATASEC") if c in header), None)
            if trim_card is not None:
                trows, tcols = parse_section(str(header[trim_card]))
            else:  # the data are the columns (or rows) beside the overscan
                if bcols.start > w // 2:
                    trows, tcols = slice(0, h), slice(0, bcols.start)
                elif bcols.stop < w // 2:
                    trows, tcols = slice(0, h), slice(bcols.stop, w)
                else:
                    trows, tcols = slice(0, h), slice(0, w)
            trows = slice(max(0, trows.start), min(h, trows.stop))
            tcols = slice(max(0, tcols.start), min(w, tcols.stop))
            block = data[brows, bcols]
            if block.size:
                return {"trim": section_text(trows, tcols), "bias_section": section_text(brows, bcols),
                        "level_adu": float(np.median(block)), "noise_adu": _block_noise(block),
                        "source": "header", "card": f"BIASSEC/{trim_card or 'derived'}"}
        except ValueError:
            pass
    # from the data: flat, dark edge columns (then rows)
    best = None
    for axis in (1, 0):
        n = data.shape[axis]
        prof = np.median(data, axis=1 - axis)  # per column (axis=1) or row
        core = prof[int(0.3 * n): int(0.7 * n)]
        level, spread = float(np.median(core)), robust_std(np.diff(core)) / math.sqrt(2) + 1e-9
        noise = robust_std(data[:, int(0.3 * n): int(0.7 * n)] if axis == 1 else data[int(0.3 * n): int(0.7 * n)])
        for side in ("low", "high"):
            seq = prof if side == "low" else prof[::-1]
            k = 0
            while k < int(max_frac * n) and seq[k] < level - max(5 * spread, 3 * noise / math.sqrt(data.shape[1 - axis])) \
                    and seq[k] < level - 0.02 * abs(level):
                k += 1
            if k >= min_cols:
                block_idx = np.arange(k) if side == "low" else np.arange(n - k, n)
                # keep the flattest part (leave 1 transition column on the data side)
                vals = prof[block_idx]
                flat = np.abs(vals - np.median(vals)) < max(5 * robust_std(vals), 3.0)
                # no light: the strip's noise is the read noise alone (well below the image's, which holds the
                # shot noise) and its level far below the image's on that scale (a vignetted edge is neither)
                strip = data[:, block_idx] if axis == 1 else data[block_idx, :]
                snoise = _block_noise(strip if axis == 1 else strip.T)
                quiet = snoise < 0.5 * noise and level - float(np.median(vals)) > 10 * snoise
                if flat.sum() >= min_cols - 1 and quiet:
                    if side == "low":
                        ds, bs = slice(k + 1 if k + 1 < n else k, n), slice(0, k)
                    else:
                        ds, bs = slice(0, n - k - 1), slice(n - k, n)
                    full = slice(0, data.shape[1 - axis])
                    trows, tcols = (full, ds) if axis == 1 else (ds, full)
                    brows, bcols = (full, bs) if axis == 1 else (bs, full)
                    block = data[brows, bcols]
                    cand = {"trim": section_text(trows, tcols), "bias_section": section_text(brows, bcols),
                            "level_adu": float(np.median(block)), "noise_adu": _block_noise(block),
                            "source": "measured", "card": None, "n": k}
                    if best is None or k > best["n"]:
                        best = cand
    return best


def _block_noise(block: np.ndarray) -> float:
    """Read noise [ADU] of an overscan block: robust std after each column's median is removed (the column
    offsets of a prescan are a fixed pattern, not noise)."""
    return robust_std(block - np.median(block, axis=0, keepdims=True))


def _read(path, role):
    data, header = read_hdu(path, None, role=role, key=f"--{role}", dtype=np.float64)
    return data, header


def _trim(data, trim: str | None):
    if not trim:
        return data
    rows, cols = parse_section(trim)
    return data[rows, cols]


def camera_from_calibration(bias=(), dark=(), flat=(), *, trim: str | None = None, shape=None,
                            header_gain: float | None = None) -> dict:
    """The camera's numbers from the calibration frames given (any may be missing). Returns a dict of
    :class:`Value` (``bias_adu``, ``read_noise_adu``, ``dark_rate_adu_s``, ``gain_e_per_adu``, ``flat``: the
    normalised flat map or None, ``bias_map``, ``dark_rate_map``) and ``missing``: one line per value that
    could not be measured and why."""
    out: dict = {"missing": [], "notes": []}
    biases = [_trim(_read(p, "bias")[0], trim) for p in bias]
    for b in biases:
        if shape is not None and b.shape != tuple(shape):
            raise _shape_error(bias[0], "bias", b.shape, shape)
    if biases:
        master = np.median(np.stack(biases), axis=0) if len(biases) > 1 else biases[0]
        out["bias_adu"] = Value(float(np.median(master)), "measured", note=f"median of the master of {len(biases)} bias frame(s)")
        if len(biases) >= 2:
            rn = robust_std(biases[0] - biases[1]) / math.sqrt(2)
            out["read_noise_adu"] = Value(rn, "measured", note="pair difference of two bias frames / sqrt 2")
            fp = math.sqrt(max(robust_std(master) ** 2 - rn ** 2 / len(biases), 0.0))
            out["bias_pattern_adu"] = fp
        else:
            out["read_noise_adu"] = Value(robust_std(master), "measured",
                                          note="robust std of one bias frame (fixed pattern included: an upper bound)")
        out["bias_map"] = master.astype(np.float32)
    else:
        out["missing"].append("bias: no bias frame - the bias level from the overscan, the darks or the header; "
                              "read noise from an overscan, a dark pair or assumed")
    darks = []
    for p in dark:
        d, hd = _read(p, "dark")
        d = _trim(d, trim)
        if shape is not None and d.shape != tuple(shape):
            raise _shape_error(p, "dark", d.shape, shape)
        t = number_or(hd.get("EXPTIME", hd.get("EXPOSURE")), None)
        darks.append((d, t, hd))
    if darks:
        base = out.get("bias_adu")
        ts = [t for _, t, _ in darks if t is not None]
        if base is None:
            if len(set(ts)) >= 2:  # two exposure times: level = bias + rate t
                lv = [float(np.median(d)) for d, t, _ in darks if t is not None]
                slope, icpt = np.polyfit(ts, lv, 1)
                out["bias_adu"] = Value(float(icpt), "measured", note="intercept of the dark level against exposure time")
                out["dark_rate_adu_s"] = Value(max(float(slope), 0.0), "measured", note="slope of the dark level against time")
            else:
                d, t, _ = darks[0]
                out["bias_adu"] = Value(float(np.percentile(d, 5)), "measured",
                                        note="no bias frame: 5th percentile of the dark (dark current of the bulk not separated)")
                out["dark_rate_adu_s"] = Value(0.0, "assumed", note="one dark and no bias: the dark current cannot be told "
                                               "from the bias level")
        else:
            rates = [(float(np.median(d)) - base.value) / t for d, t, _ in darks if t]
            if rates:
                out["dark_rate_adu_s"] = Value(max(float(np.median(rates)), 0.0), "measured",
                                               note=f"median (dark - bias) / t over {len(rates)} dark(s)")
                rn = out["read_noise_adu"].value if "read_noise_adu" in out else robust_std(biases[0])
                out["dark_rate_map"] = dark_rate_map([(b, 0.0) for b in biases] + [(d, t) for d, t, _ in darks if t], rn)
        if "read_noise_adu" not in out:
            same = {}
            for d, t, _ in darks:
                same.setdefault(t, []).append(d)
            pair = next((v for v in same.values() if len(v) >= 2), None)
            if pair is not None:
                out["read_noise_adu"] = Value(robust_std(pair[0] - pair[1]) / math.sqrt(2), "measured",
                                              note="pair difference of two darks of the same time / sqrt 2 (dark shot noise included)")
    else:
        out["missing"].append("dark: no dark frame - dark current from the header or assumed 0 (a cooled CCD has almost none)")
    flats = []
    for p in flat:
        f, hf = _read(p, "flat")
        f = _trim(f, trim)
        if shape is not None and f.shape != tuple(shape):
            raise _shape_error(p, "flat", f.shape, shape)
        flats.append((f, hf))
    if flats:
        b = out["bias_adu"].value if "bias_adu" in out else None
        if b is None:
            out["missing"].append("flat gain: no bias or dark - the flat's level above the bias is unknown; gain from the "
                                  "flats' header or assumed")
        else:
            f1 = flats[0][0] - b
            s = float(np.median(f1))
            rn = out["read_noise_adu"].value if "read_noise_adu" in out else 0.0
            if len(flats) >= 2:
                f2 = flats[1][0] - b
                r = f2 * (np.median(f1) / np.median(f2))  # equal levels: the pair difference has no flat pattern
                var = robust_std(f1 - r) ** 2 / 2
                k = s / max(var - rn ** 2, 1e-9)
                n = f1.size
                se = k * math.sqrt(2.0 / (n / 4))  # a robust variance over n/4 effective samples (2/N per variance)
                out["gain_e_per_adu"] = Value(k, "measured", note=f"photon transfer of a flat pair at {s:.0f} ADU "
                                              f"(Janesick 2007, eq. 4.7), standard error {se:.2g}")
                out["gain_se"] = se
            else:
                hp = f1[1:-1, 1:-1] - 0.25 * (f1[:-2, 1:-1] + f1[2:, 1:-1] + f1[1:-1, :-2] + f1[1:-1, 2:])
                var = robust_std(hp) ** 2 / 1.25  # var of x - mean of 4 neighbours = 1.25 var(x)
                k = s / max(var - rn ** 2, 1e-9)
                out["gain_e_per_adu"] = Value(k, "measured", note=f"one flat at {s:.0f} ADU: local variance of the "
                                              "high-passed flat (pixel response non-uniformity included: a lower bound "
                                              "on the gain)")
            norm = f1 / np.mean(f1)
            # each pixel's standard error (in units of the map): Poisson and read noise of the one flat
            k_adopt = float(out["gain_e_per_adu"].value)
            sig = np.sqrt(np.clip(f1, 1.0, None) / k_adopt + rn ** 2) / np.mean(f1)
            out["flat"] = [norm.astype(np.float32), sig.astype(np.float32)]
            out["flat_level_adu"] = s
            if header_gain is not None and "gain_se" in out:
                k, se = out["gain_e_per_adu"].value, out["gain_se"]
                if abs(k - header_gain) > 3 * se:
                    out["notes"].append(f"photon-transfer gain {k:.3g} +- {se:.2g} e-/ADU differs from the header's "
                                        f"{header_gain:.3g} beyond 3 standard errors: the measured one is adopted")
    else:
        out["missing"].append("flat: no flat frame - gain from the header or the sky noise, no flat-field map "
                              "(vignetting and pixel response left to the diagnosis)")
    return out


def dark_rate_map(frames, read_noise_adu: float) -> list[np.ndarray]:
    """Per-pixel dark rate [ADU/s] and its standard error: the least-squares slope of each pixel's value against
    exposure time over bias (t = 0) and dark frames, se = sigma_read / sqrt(sum (t - mean t)^2) (a straight-line
    fit with the read noise as the per-frame error; the dark shot noise of a hot pixel is left out)."""
    t = np.array([tt for _, tt in frames], float)
    tm = t.mean()
    sxx = float(np.sum((t - tm) ** 2))
    num = sum((tt - tm) * d for d, tt in frames)
    slope = num / sxx
    se = np.full(slope.shape, read_noise_adu / math.sqrt(sxx), np.float32)
    return [slope.astype(np.float32), se]


def number_or(v, default):
    from .header import number

    f = number(v)
    return default if f is None else f


def _shape_error(path, role, got, want):
    from detector.errors import DetectorError

    return DetectorError(f"{role} frame is {got[1]}x{got[0]} pixels", key=f"--{role}", file=str(path),
                         expected=f"{want[1]}x{want[0]} as the light frame (after trimming)")


def suppress():
    return warnings.catch_warnings()


def characterize_subset(bias=(), dark=(), flat=()) -> dict:
    """What any subset of bias, dark and flat frames measures (:func:`camera_from_calibration` on the frames'
    own size, the first one's header for the gain), with ``not_measured``: one line per quantity the missing
    frames leave unmeasured. The full analysis (:func:`detector.characterize.characterize`) needs bias frames
    and darks at two exposure times or more."""
    from .header import header_gain

    allp = list(bias) + list(dark) + list(flat)
    data, header = read_hdu(allp[0], None, role="calibration", key="--bias/--dark/--flat", dtype=np.float64)
    hg = header_gain(header)
    for p in allp[1:]:  # the first header with a gain card
        if hg.value:
            break
        hg = header_gain(read_hdu(p, None, role="calibration", dtype=np.float32)[1])
    cam = camera_from_calibration(bias, dark, flat, shape=data.shape, header_gain=hg.value)
    gain_v = cam.get("gain_e_per_adu") if "gain_se" in cam else (hg if hg.value else cam.get("gain_e_per_adu"))
    out = {"frame": {"width": int(data.shape[1]), "height": int(data.shape[0]), "n_bias": len(bias),
                     "n_dark": len(dark), "n_flat": len(flat)},
           "header_gain": hg.to_json(), "warnings": list(cam["notes"])}
    for k in ("bias_adu", "read_noise_adu", "dark_rate_adu_s", "gain_e_per_adu"):
        if k in cam:
            out[k] = cam[k].to_json()
    if gain_v is not None and gain_v.value:
        out["gain"] = {"adopted_e_per_adu": float(gain_v.value), "source": gain_v.source + (f" ({gain_v.card})" if gain_v.card else ""),
                       "photon_transfer_se": cam.get("gain_se")}
        if "read_noise_adu" in cam:
            out["read_noise_e"] = float(cam["read_noise_adu"].value) * float(gain_v.value)
        if "dark_rate_adu_s" in cam:
            out["dark_current_e_per_s"] = float(cam["dark_rate_adu_s"].value) * float(gain_v.value)
    lines = []
    if not bias:
        lines.append("no bias frame: no master bias, bias structure or read noise from a bias pair"
                     + (" (bias level from the darks' intercept)" if len({_exptime(p) for p in dark}) >= 2 else ""))
    elif len(bias) < 2:
        lines.append("one bias frame: the read noise includes the fixed pattern (two bias frames separate them)")
    if not dark:
        lines.append("no dark frame: no dark current, no hot pixels")
    elif len({_exptime(p) for p in dark}) < 2:
        lines.append("darks at one exposure time: no dark-rate fit, no hot-pixel growth (darks at two times or more)")
    if not flat:
        lines.append("no flat frame: no photon-transfer gain, no PRNU or vignetting")
    elif len(flat) < 2:
        lines.append("one flat: no photon-transfer gain from a pair (the single-flat estimate includes the PRNU)")
    if gain_v is None or not gain_v.value:
        lines.append("no gain (no flat pair, no EGAIN/GAIN card): values stay in ADU")
    out["not_measured"] = lines
    return out


def _exptime(path):
    _, h = read_hdu(path, None, role="dark", dtype=np.float32)
    return number_or(h.get("EXPTIME", h.get("EXPOSURE")), None)


def edge_rolloff(data: np.ndarray, trim: str, bias_section: str, bias_adu: float, max_cols: int = 64,
                 min_excess: float = 0.01) -> dict | None:
    """The columns (or rows) of the trimmed data next to the prescan/overscan whose sky level departs from the
    frame's: a raw CCD's first columns after the serial prescan (the HSC cutout's: +1015, +510, +307, ... ADU
    over a 640 ADU sky, decaying over about 15 columns, each with the shot noise of its own level, so charge
    and not a bias offset: an edge effect the scene has no model of). Walking away from the boundary, a
    column belongs to the roll-off while its median departs from the reference (the median of the next
    ``max_cols`` lines) by more than 5 standard errors and more than ``min_excess`` of the level above the
    bias ``bias_adu`` (the overscan's); the walk stops at the first line that does not. Returns ``{"axis": "columns"|"rows",
    "side": "low"|"high", "n": lines, "excess_adu": [...], "reference_adu"}`` or None."""
    brows, bcols = parse_section(bias_section)
    trows, tcols = parse_section(trim)
    if bcols.stop <= tcols.start or bcols.start >= tcols.stop:
        axis, side = 1, "low" if bcols.stop <= tcols.start else "high"
    elif brows.stop <= trows.start or brows.start >= trows.stop:
        axis, side = 0, "low" if brows.stop <= trows.start else "high"
    else:
        return None
    img = data if axis == 1 else data.T
    img = img if side == "low" else img[:, ::-1]
    n = img.shape[1]
    if n < 3 * 8:
        return None
    prof = np.nanmedian(img, axis=0)
    far = prof[min(max_cols, n // 3): min(2 * max_cols, n)]
    ref = float(np.median(far))
    se = robust_std(np.diff(img[:, min(max_cols, n // 3):min(2 * max_cols, n)], axis=1)) / math.sqrt(2) \
        * 1.2533 / math.sqrt(max(np.isfinite(img[:, 0]).sum(), 1))
    thresh = max(5 * se, min_excess * max(ref - bias_adu, 0.0))
    k = 0
    while k < min(max_cols, n // 3) and abs(prof[k] - ref) > thresh:
        k += 1
    if k == 0:
        return None
    return {"axis": "columns" if axis == 1 else "rows", "side": side, "n": k,
            "excess_adu": [round(float(v - ref), 2) for v in prof[:k]], "reference_adu": ref,
            "threshold_adu": thresh}


def scale_std(x) -> float:
    """A robust standard deviation that does not step with integer data: the biweight scale (Beers, Flynn &
    Gebhardt 1990; astropy ``biweight_scale``, c = 9), outliers (cosmic rays, faint stars) weighted down. The MAD
    of integer differences moves in steps of 1.48 ADU, 7 % of a 15 ADU noise."""
    from astropy.stats import biweight_scale

    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    if x.size < 10:
        return math.nan
    if x.size > 2_000_000:
        x = x[:: x.size // 2_000_000]
    return float(biweight_scale(x, c=9.0))


def sky_pixels(data: np.ndarray, bkg: np.ndarray, rms: np.ndarray, bad: np.ndarray | None = None,
               nsigma: float = 3.0, grow: int = 3) -> np.ndarray:
    """Source-free sky: finite pixels outside the segments of a ``nsigma`` detection (photutils, 3 px
    Gaussian kernel), grown by ``grow`` pixels so that the stars' wings are out too."""
    from scipy import ndimage

    from .stars import detect

    ok = np.isfinite(data) if bad is None else np.isfinite(data) & ~bad
    seg, _ = detect(data, bkg, rms, fwhm_px=3.0, nsigma=nsigma, mask=~ok)
    if seg is None:
        return ok
    return ok & ~ndimage.binary_dilation(seg.data > 0, iterations=grow)


def white_noise(data: np.ndarray, sky: np.ndarray, lag: int = 1) -> dict:
    """The white (pixel-to-pixel) noise [ADU] of the sky: the robust std of the differences of pixels ``lag``
    apart along the rows and along the columns, both of them source-free sky, / sqrt 2 (var(a - b) = 2 var for
    independent pixels: the gradient, the vignetting, the column or row pattern and the sky's structure cancel in
    a neighbour's difference, which the spread about a smoothed background keeps). ``lag = 2`` on a colour
    (Bayer) frame: the neighbours of the same cell. Returns ``{"x_adu", "y_adu", "adu"}`` (the smaller: a
    column pattern enters the row-wise differences, a row noise the column-wise ones) and ``"n"``."""
    out = {"lag": lag}
    n = 0
    for name, a, b, sa, sb in (("x_adu", data[:, :-lag], data[:, lag:], sky[:, :-lag], sky[:, lag:]),
                               ("y_adu", data[:-lag], data[lag:], sky[:-lag], sky[lag:])):
        ok = sa & sb
        out[name] = scale_std((a - b)[ok]) / math.sqrt(2)
        n = max(n, int(ok.sum()))
    vals = [v for v in (out["x_adu"], out["y_adu"]) if math.isfinite(v)]
    out["adu"] = min(vals) if vals else math.nan
    out["n"] = n
    return out


def cfa_photon_transfer(data: np.ndarray, sky: np.ndarray, max_rel_se: float = 0.3) -> dict | None:
    """Photon transfer within one colour (Bayer) frame: the four cells see the same sky through different
    filters, so their sky levels differ while the bias, the read noise and the gain are the same. Each cell's
    white variance (neighbours of the same cell, :func:`white_noise` on the cell's plane) against its level is
    the photon-transfer line var = RN^2 + (L - B) / K (Janesick 2007, eq. 4.7): its slope is 1 / K whatever the
    bias. Returns ``{"gain_e_per_adu", "gain_se", "intercept_adu2", "levels_adu", "variances_adu2"}`` or None
    when the cells' levels do not spread enough for a slope known to ``max_rel_se``."""
    lv, var, se = [], [], []
    for r in (0, 1):
        for c in (0, 1):
            plane, ok = data[r::2, c::2], sky[r::2, c::2]
            if ok.sum() < 200:
                return None
            wn = white_noise(plane, ok, 1)
            v = float(np.mean([wn["x_adu"] ** 2, wn["y_adu"] ** 2]))
            lv.append(float(np.median(plane[ok])))
            var.append(v)
            se.append(v * math.sqrt(2.0 / max(wn["n"], 1)) * 1.1)  # a variance from n differences (biweight ~ 1.1)
    L, V, S = np.array(lv), np.array(var), np.array(se)
    if np.ptp(L) <= 0:
        return None
    wts = 1.0 / S ** 2
    M = np.stack([np.ones_like(L), L], axis=1)
    cov = np.linalg.inv(M.T @ (M * wts[:, None]))
    a, b = cov @ (M.T @ (wts * V))
    chi2 = float(np.sum(wts * (V - a - b * L) ** 2))
    b_se = math.sqrt(cov[1, 1] * max(1.0, chi2 / 2))  # 4 cells, 2 parameters: the scatter about the line counts
    if not (b > 0 and b_se < max_rel_se * b):
        return None
    return {"gain_e_per_adu": float(1.0 / b), "gain_se": float(b_se / b ** 2), "intercept_adu2": float(a),
            "levels_adu": [round(x, 2) for x in lv], "variances_adu2": [round(x, 2) for x in var]}
