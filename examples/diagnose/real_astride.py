"""Real data: the ASTRiDE satellite-streak frame (YSTAR, SAAO, 2002-07-26) against a scene set up from it.

The frame (``../shared/realdata/streak/astride_long.fits``, never copied) is a 512 x 512 cutout of a
2048 x 2048 Apogee CCD frame, R band, 60 s, already bias/dark-subtracted and flat-fielded, with a TAN WCS
of 3.04"/px and a satellite streak. Everything the scene needs is read or measured from the file:

* **geometry**: plate scale and roll from the CD matrix, the full sensor and the read-out window from
  ``LTV1/LTV2`` (the WCS reference pixel is the full frame's centre, i.e. the optical axis); the header's
  CD matrix has det > 0 (east to the right, a mirror image), which the scene's WCS cannot represent
  (``scenes.projection.tan_wcs`` always has det < 0): the scene keeps the header's sky position and north
  direction at the frame centre and its frame is the east-west mirror of the header's sky (stated in the
  output as ``parity``);
* **detector**: a CCD described by overrides: window, bias 0 (the data are bias-subtracted), no dark
  (the "bias" frame applied was a 60 s dark), read noise assumed (15 e-, typical of the camera class),
  gain from the sky noise (var = S/g + (RN/g)^2 + 1/12);
* **band**: Bessell R x a front-illuminated CCD QE, scaled by the zero point: the frame holds no catalogue
  star (the built-in catalogue stops at G = 10), so the zero point is calibrated from the frame's own star
  counts against the Galaxy model's counts (``expected_synthetic_count``), i.e. statistically;
* **sky** from the frame's median (as AB mag/arcsec^2 through the calibrated band), **PSF** (Moffat FWHM,
  beta) from elliptical Moffat fits of isolated stars, **stars**: the built-in catalogue plus the faint
  population at the epoch, down to the frame's detection limit;
* **the streak** as one object: start and end from a fit of the streak's line and ends, rates from them
  and the exposure time, photons from its measured flux (through a trial render of the same scene).

Then compare / diagnose / apply, round by round. Usage::

    python examples/diagnose/real_astride.py [OUT_DIR] [--rounds N] [--write-scene]

writes ``OUT_DIR`` (default ``out/realdata/astride``): the measured setup (``setup.json``), the scene of
every round, the diagnosis JSON, the ledger, the streak profile (data vs model), the HTML report when
``scenes.app.compare.report`` exists, and ``summary.json``. ``--write-scene`` also refreshes the committed
``examples/diagnose/scenes/astride.toml``.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import sys
import warnings
from pathlib import Path

import numpy as np

from detector.jsonable import jsonable
from detector.stats import mad_std

ROOT = Path(__file__).resolve().parents[2]
REALDATA = ROOT.parent / "shared" / "realdata"
DATA = REALDATA / "streak" / "astride_long.fits"
SCENE = ROOT / "examples" / "diagnose" / "scenes" / "astride.toml"

#: assumed read noise of the Apogee camera [e-] (not measurable from one calibrated frame)
READ_NOISE_E = 15.0
#: rough ends of the streak (ASTRiDE's two segments: x 20..184, y 323..338 and x 182..342, y 309..324)
STREAK_GUESS = ((20.0, 331.0), (342.0, 316.0))
#: Bessell (1990, PASP 102, 1181) R transmission [nm, 1]
BESSELL_R = ([550, 560, 570, 580, 590, 600, 620, 640, 660, 680, 700, 720, 740, 760, 780, 800, 850, 900],
             [0.0, 0.23, 0.74, 0.91, 0.97, 1.0, 0.96, 0.9, 0.81, 0.72, 0.61, 0.51, 0.40, 0.30, 0.21, 0.14, 0.03, 0.0])
#: a front-illuminated CCD's QE on the same grid (the ml11002 preset's curve, linearly interpolated)
CCD_QE = ([350, 400, 450, 500, 550, 600, 650, 700, 750, 800, 850, 900, 950, 1000],
          [0.10, 0.30, 0.45, 0.50, 0.48, 0.43, 0.37, 0.30, 0.23, 0.17, 0.11, 0.07, 0.04, 0.02])


# ============================================================================ generic frame measurements
def robust_std(x) -> float:
    """1.4826 x the median absolute deviation of every value (:func:`detector.stats.mad_std`)."""
    return mad_std(x, max_n=None)


def read_frame(path) -> tuple[np.ndarray, object]:
    """The frame as float64 and its header (the image HDU's cards over the primary's)."""
    from detector.fits_io import read_image

    return read_image(path, role="measured")


def background_map(img: np.ndarray, size: int = 31) -> np.ndarray:
    from scipy import ndimage

    return ndimage.median_filter(img, size=size, mode="nearest")


def detect_sources(img: np.ndarray, bg: np.ndarray, sigma: float, nsigma: float = 5.0, smooth: float = 1.0,
                   min_pixels: int = 3) -> dict:
    """Connected pixels of the (Gaussian-smoothed) background-subtracted image above ``nsigma`` x the
    smoothed noise. Returns arrays x, y (intensity-weighted centroids, 0-based), flux (sum over the
    segment, ADU), peak (ADU above background), npix, and the label image."""
    from scipy import ndimage

    s = img - bg
    sm = ndimage.gaussian_filter(s, smooth) if smooth > 0 else s
    noise = sigma / (2 * math.sqrt(math.pi) * smooth) if smooth > 0 else sigma  # white noise through the filter
    lab, n = ndimage.label(sm > nsigma * noise)
    idx = np.arange(1, n + 1)
    if n == 0:
        return {"x": np.zeros(0), "y": np.zeros(0), "flux": np.zeros(0), "peak": np.zeros(0), "npix": np.zeros(0),
                "labels": lab}
    cm = np.array(ndimage.center_of_mass(np.clip(s, 0, None), lab, idx))
    return {"x": cm[:, 1], "y": cm[:, 0], "flux": np.asarray(ndimage.sum(s, lab, idx)),
            "peak": np.asarray(ndimage.maximum(s, lab, idx)), "npix": np.asarray(ndimage.sum(np.ones_like(s), lab, idx)),
            "labels": lab}


def _moffat(p, yy, xx):
    a, x0, y0, sx, sy, th, beta, b = p
    c, s = math.cos(th), math.sin(th)
    u = (xx - x0) * c + (yy - y0) * s
    v = -(xx - x0) * s + (yy - y0) * c
    return a * (1 + (u / sx) ** 2 + (v / sy) ** 2) ** (-beta) + b


def fit_psf(img: np.ndarray, bg: np.ndarray, det: dict, *, peak_range=(100.0, 1e9), radius: int = 9,
            exclude=None, max_stars: int = 40, saturation: float = np.inf) -> dict:
    """Elliptical Moffat fits of isolated, unsaturated stars: median FWHM (major, minor) [px], position angle
    of the major axis [deg from +x], beta, and the quadrature-mean FWHM sqrt((a^2 + b^2)/2) (the isotropic
    PSF with the same second moment). Single-pixel events (FWHM < 1.2 px: cosmic rays, hot pixels) are
    rejected and counted."""
    from scipy import optimize

    h, w = img.shape
    lab = det["labels"]
    order = np.argsort(-det["peak"])
    rows, sharp = [], 0
    for i in order:
        if not (peak_range[0] <= det["peak"][i] <= peak_range[1]):
            continue
        x, y = det["x"][i], det["y"][i]
        xi, yi = round(x), round(y)
        if xi < radius or yi < radius or xi >= w - radius or yi >= h - radius:
            continue
        if exclude is not None and exclude(x, y):
            continue
        sl = (slice(yi - radius, yi + radius + 1), slice(xi - radius, xi + radius + 1))
        if img[sl].max() >= saturation:
            continue
        other = (lab[sl] > 0) & (lab[sl] != i + 1)
        if other.any():
            continue
        st = img[sl] - bg[sl]
        yy, xx = np.mgrid[sl]
        p0 = [det["peak"][i], x, y, 2.5, 2.5, 0.0, 3.0, 0.0]
        lo = [0, x - 3, y - 3, 0.2, 0.2, -math.pi, 1.05, -50]
        hi = [1e7, x + 3, y + 3, 30, 30, math.pi, 30, 50]
        try:
            r = optimize.least_squares(lambda p, yy=yy, xx=xx, st=st: (_moffat(p, yy, xx) - st).ravel(), p0,
                                       bounds=(lo, hi))
        except ValueError:
            continue
        a, x0, y0, sx, sy, th, beta, _b = r.x
        k = 2 * math.sqrt(2 ** (1 / beta) - 1)
        fa, fb = sx * k, sy * k
        if min(fa, fb) < 1.2:
            sharp += 1
            continue
        major, minor = max(fa, fb), min(fa, fb)
        pa = math.degrees(th if fa >= fb else th + math.pi / 2) % 180.0
        rows.append((x0, y0, major, minor, pa, beta, det["peak"][i]))
        if len(rows) >= max_stars:
            break
    if not rows:
        raise RuntimeError("no isolated star to measure the PSF on")
    a = np.array(rows)
    major, minor = float(np.median(a[:, 2])), float(np.median(a[:, 3]))
    # position angle: circular median on 0..180
    ang = np.radians(2 * a[:, 4])
    pa = float(np.degrees(np.arctan2(np.median(np.sin(ang)), np.median(np.cos(ang)))) / 2 % 180)
    return {"n": len(rows), "fwhm_major_px": major, "fwhm_minor_px": minor, "pa_major_deg": pa,
            "beta": float(np.median(a[:, 5])), "fwhm_px": float(math.sqrt((major ** 2 + minor ** 2) / 2)),
            "fwhm_spread_px": float(robust_std(np.sqrt((a[:, 2] ** 2 + a[:, 3] ** 2) / 2))),
            "single_pixel_events": sharp, "stars": a}


def aperture_flux(img: np.ndarray, x, y, r: float, r_in: float, r_out: float) -> tuple[np.ndarray, np.ndarray]:
    """Circular-aperture flux [ADU] with the median of an annulus as the local sky; and that sky."""
    h, w = img.shape
    R = math.ceil(r_out)
    yy, xx = np.mgrid[-R:R + 1, -R:R + 1]
    out, sky = np.full(len(x), np.nan), np.full(len(x), np.nan)
    for k, (xc, yc) in enumerate(zip(x, y)):
        xi, yi = round(xc), round(yc)
        if xi < R or yi < R or xi >= w - R or yi >= h - R:
            continue
        st = img[yi - R:yi + R + 1, xi - R:xi + R + 1]
        rr = np.hypot(xx + xi - xc, yy + yi - yc)
        s = float(np.median(st[(rr >= r_in) & (rr <= r_out)]))
        out[k], sky[k] = float(np.sum(st[rr <= r] - s)), s
    return out, sky


def wcs_geometry(header) -> dict:
    """Plate scale [arcsec/px], roll [deg] (direction of north, the scene's convention: CD2_1 = s sin r,
    CD2_2 = s cos r), parity (sign of det CD: the scene's WCS has -1), and the CD matrix."""
    from astropy.wcs import WCS

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        w = WCS(header)
    cd = w.wcs.cd if w.wcs.has_cd() else w.wcs.get_pc() * w.wcs.cdelt[:, None]
    det = float(np.linalg.det(cd))
    scale = math.sqrt(abs(det)) * 3600.0
    roll = math.degrees(math.atan2(cd[1, 0], cd[1, 1]))
    return {"scale_arcsec": scale, "roll_deg": roll, "parity": int(np.sign(det)), "cd": cd.tolist(),
            "crval": [float(v) for v in w.wcs.crval], "crpix": [float(v) for v in w.wcs.crpix], "wcs": w}


def scene_wcs(scene_dict: dict, base_dir: Path):
    """The WCS that the scene gives its frame (written pixels, 0-based via astropy's origin argument)."""
    from optics.design import load_design
    from scenes.app.render import resolve_distortion
    from scenes.image.build import frame_wcs

    sc = load_scene_dict(scene_dict, base_dir / "_wcs_probe.toml")
    sensor = sc.sensor()
    design = load_design(sc.telescope.design)
    scale = sc.telescope.pixel_scale_arcsec or design.pixel_scale_arcsec(sensor.pixel_pitch_um)
    return frame_wcs(sc, sensor, scale, distortion=resolve_distortion(sc, sensor, design))


def load_scene_dict(scene_dict: dict, path: Path):
    """Write a scene dict as TOML and load (validate) it."""
    import tomli_w

    from scenes.scene import load_scene

    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(tomli_w.dumps(scene_dict))
    return load_scene(str(path))


def sky_mag_arcsec2(sky_e_per_s: float, scene_dict: dict) -> float:
    """AB mag/arcsec^2 that gives ``sky_e_per_s`` per pixel through the scene's band, mirrors and area."""
    from optics.design import load_design
    from scenes.photometry import sky_electron_rate_per_pixel

    d = load_design(scene_dict["telescope"]["design"])
    det = scene_dict["detector"]
    zero = sky_electron_rate_per_pixel(0.0, scene_dict["telescope"]["pixel_scale_arcsec"], d.collecting_area_m2,
                                       d.mirror_throughput, det["qe_wavelength_nm"], det["qe"])
    return float(-2.5 * math.log10(max(sky_e_per_s, 1e-12) / zero))


def star_rate_e_s(mag_g, scene_dict: dict, teff_k: float = 5000.0) -> np.ndarray:
    """Photo-electron rate of a star of Gaia G ``mag_g`` through the scene's band (blackbody ``teff_k``)."""
    from optics.design import load_design
    from scenes.catalog import star_electron_rate

    d = load_design(scene_dict["telescope"]["design"])
    det = scene_dict["detector"]
    return np.asarray(star_electron_rate(np.atleast_1d(mag_g), np.full(np.size(mag_g), teff_k),
                                         det["qe_wavelength_nm"], det["qe"], d.collecting_area_m2,
                                         optics_throughput=d.mirror_throughput), float)


def band_table(filter_curve, qe_curve, step: float = 25.0) -> tuple[list[float], list[float]]:
    """Filter x QE on a common grid [nm] (the scene's ``qe`` table, before the zero-point scale)."""
    lo = max(filter_curve[0][0], qe_curve[0][0])
    hi = min(filter_curve[0][-1], qe_curve[0][-1])
    lam = np.arange(lo, hi + 0.5 * step, step)
    t = np.interp(lam, *filter_curve) * np.interp(lam, *qe_curve)
    return [float(v) for v in lam], [float(v) for v in t]


def count_zero_point(flux_e: np.ndarray, ra: float, dec: float, area_deg2: float, scene_dict: dict,
                     ranks=(5, 40), exptime_s: float = 1.0) -> dict:
    """Zero point from star counts: the n-th brightest measured star is matched to the magnitude G_n at
    which the Galaxy model (:func:`scenes.sky.starcounts.expected_synthetic_count`) expects n - 1/2 stars
    in the frame's area; the band's scale is the median of measured / model electrons over ``ranks``
    (complete, Poisson-limited part of the counts). Returns the scale and its 16-84 % spread."""
    from scenes.sky.starcounts import expected_synthetic_count

    radius = math.sqrt(area_deg2 / math.pi)
    g = np.arange(4.0, 22.01, 0.25)
    n = np.array([expected_synthetic_count(ra, dec, radius, -2.0, gi) for gi in g])
    f = np.sort(np.asarray(flux_e, float)[np.isfinite(flux_e) & (flux_e > 0)])[::-1]
    k = np.arange(1, f.size + 1)
    sel = (k >= ranks[0]) & (k <= min(ranks[1], f.size))
    gk = np.interp(np.log(k[sel] - 0.5), np.log(np.maximum(n, 1e-9)), g)
    model_e = star_rate_e_s(gk, scene_dict) * exptime_s
    ratio = f[sel] / model_e
    lo, med, hi = np.percentile(ratio, [16, 50, 84])
    return {"scale": float(med), "scale_16": float(lo), "scale_84": float(hi), "n_used": int(sel.sum()),
            "g_of_rank": {int(kk): float(gg) for kk, gg in zip(k[sel][::5], gk[::5])},
            "model_counts": {float(gi): float(ni) for gi, ni in zip(g[::4], n[::4])}}


def limiting_mag(scene_dict: dict, sigma_adu: float, gain: float, fwhm_px: float, exptime_s: float,
                 nsigma: float = 3.0) -> float:
    """G at which a star's peak pixel (Gaussian of ``fwhm_px``) is ``nsigma`` x the sky noise."""
    peak_frac = 1.0 / (2 * math.pi * (fwhm_px / 2.3548) ** 2)
    e1 = float(star_rate_e_s(0.0, scene_dict)[0]) * exptime_s * peak_frac / gain  # ADU at G = 0
    return float(2.5 * math.log10(e1 / (nsigma * sigma_adu)))


# ============================================================================ the streak
def streak_line(img: np.ndarray, sky: float, guess=STREAK_GUESS, half: int = 10, iters: int = 3) -> dict:
    """Centre line y = a + b x of the streak from per-column centroids (robust, iterated)."""
    (xa, ya), (xb, yb) = guess
    b = (yb - ya) / (xb - xa)
    a = ya - b * xa
    xs = np.arange(int(xa) + 5, int(xb) - 4)
    for _ in range(iters):
        cy = []
        for x in xs:
            yc = a + b * x
            y0, y1 = round(yc) - half, round(yc) + half + 1
            col = np.clip(img[y0:y1, x] - sky, 0, None)
            cy.append(np.sum(col * np.arange(y0, y1)) / max(np.sum(col), 1e-9))
        cy = np.asarray(cy)
        ok = np.abs(cy - (a + b * xs)) < 4
        for _ in range(3):
            p = np.polyfit(xs[ok], cy[ok], 1)
            r = cy - np.polyval(p, xs)
            ok = np.abs(r) < 3 * robust_std(r[ok]) + 0.5
        b, a = float(p[0]), float(p[1])
    r = cy - (a + b * xs)
    return {"a": a, "b": b, "x": xs, "offset_px": r, "wobble_rms_px": robust_std(r[ok])}


def streak_columns(img: np.ndarray, line: dict, x_range=(0, 400), half: float = 9.0, side=(13.0, 20.0),
                   sky_cols: int = 15) -> dict:
    """Per column: flux within ``half`` px of the line (local sky from the side bands), peak (3-px
    running mean across the track) and cross-track rms width. Columns are along x (the streak is within
    5 deg of the rows, so the cross-track distance is |y - line| cos(angle))."""
    a, b = line["a"], line["b"]
    cosang = 1.0 / math.sqrt(1 + b * b)
    xs = np.arange(*x_range)
    flux, peak, width, skyl, noise2 = (np.full(xs.size, np.nan) for _ in range(5))
    h, w = img.shape
    for k, x in enumerate(xs):
        yc = a + b * x
        y = np.arange(max(0, int(yc - side[1] - 1)), min(h, int(yc + side[1] + 2)))
        d = (y - yc) * cosang
        col = img[y, x]
        sband = (np.abs(d) >= side[0]) & (np.abs(d) <= side[1])
        core = np.abs(d) <= half
        # local sky: median of the side bands over 15 columns (a star in a side band moves it little)
        xb = np.arange(max(0, x - sky_cols // 2), min(w, x + sky_cols // 2 + 1))
        block = img[np.ix_(y[sband], xb)]
        s = float(np.median(block))
        noise2[k] = robust_std(block) ** 2 * int(core.sum())
        c = col[core] - s
        flux[k], skyl[k] = float(c.sum()), s
        peak[k] = float(np.max(np.convolve(c, np.ones(3) / 3, mode="same")))
        wpos = np.clip(c, 0, None)
        if wpos.sum() > 0:
            m = np.sum(wpos * d[core]) / wpos.sum()
            width[k] = float(math.sqrt(np.sum(wpos * (d[core] - m) ** 2) / wpos.sum()))
    return {"x": xs, "flux": flux, "peak": peak, "width": width, "sky": skyl, "noise2": noise2}


def fit_streak_ends(cols: dict, mask=None) -> dict:
    """Ends of the streak: per-column flux = A [Phi((x - x0)/s) - Phi((x - x1)/s)] (a box seen through the
    PSF), fitted by least squares over the unmasked columns."""
    from scipy import optimize
    from scipy.special import ndtr

    x, f = cols["x"].astype(float), cols["flux"]
    ok = np.isfinite(f) if mask is None else np.isfinite(f) & ~mask

    def model(p):
        A, x0, x1, s = p
        return A * (ndtr((x - x0) / s) - ndtr((x - x1) / s))

    above = x[ok & (f > 0.5 * np.nanmedian(f[ok & (f > np.nanpercentile(f, 60))]))]
    p0 = [float(np.nanmedian(f[ok & (f > np.nanpercentile(f, 60))])), float(above.min()), float(above.max()), 2.0]
    r = optimize.least_squares(lambda p: (model(p) - f)[ok], p0,
                               bounds=([0, x.min(), x.min(), 0.3], [1e6, x.max(), x.max(), 20]))
    A, x0, x1, s = r.x
    return {"amplitude_adu_per_col": float(A), "x0": float(x0), "x1": float(x1), "edge_sigma_px": float(s)}


def gap_profile(cols: dict, x0: float, x1: float, bin_px: int = 4, mask=None) -> dict:
    """Binned profiles along the streak (flux and peak per column, cross-track width), normalised by their
    medians over the streak; the deepest dip of the peak (surface brightness) and where it is."""
    x = cols["x"]
    inside = (x >= x0 + 3) & (x <= x1 - 3)
    if mask is not None:
        inside &= ~mask
    edges = np.arange(x0 + 3, x1 - 3 + 1e-9, bin_px)
    centres, fl, pk, wd = [], [], [], []
    for lo, hi in itertools.pairwise(edges):
        m = inside & (x >= lo) & (x < hi)
        if m.sum() < max(2, bin_px // 2):
            continue
        centres.append(0.5 * (lo + hi))
        fl.append(np.nanmean(cols["flux"][m]))
        pk.append(np.nanmean(cols["peak"][m]))
        wd.append(np.nanmean(cols["width"][m]))
    c, fl, pk, wd = map(np.asarray, (centres, fl, pk, wd))
    fl_n, pk_n = fl / np.nanmedian(fl), pk / np.nanmedian(pk)
    j = int(np.nanargmin(pk_n))
    return {"x": c, "flux_rel": fl_n, "peak_rel": pk_n, "width_px": wd, "dip_x": float(c[j]),
            "dip_peak_rel": float(pk_n[j]), "dip_flux_rel": float(fl_n[j]), "dip_width_px": float(wd[j]),
            "median_width_px": float(np.nanmedian(wd)), "flux_scatter_rel": robust_std(fl_n)}


def light_curve(cols: dict, x0: float, x1: float, mask, exptime_s: float) -> dict:
    """Is the streak's brightness constant? Per-column flux along the track: intrinsic rms (the noise of a
    column sum taken out) and the strongest period (Lomb-Scargle) in columns and, through the streak's
    speed, in seconds of the exposure's time (start at ``x0``)."""
    from astropy.timeseries import LombScargle

    x, f = cols["x"], cols["flux"]
    sel = (x >= x0 + 3) & (x <= x1 - 3) & ~mask & np.isfinite(f)
    xx, ff = x[sel].astype(float), f[sel]
    noise2 = float(np.nanmedian(cols["noise2"][sel]))
    freq = np.linspace(1.0 / 150.0, 0.45, 4000)
    ls = LombScargle(xx, ff - ff.mean())
    p = ls.power(freq)
    j = int(np.argmax(p))
    return {"noise_rel": math.sqrt(noise2) / float(ff.mean()), "mean_adu_per_column": float(ff.mean()), "rms_rel": float(np.std(ff) / ff.mean()),
            "intrinsic_rms_rel": float(math.sqrt(max(np.var(ff) - noise2, 0.0)) / ff.mean()),
            "period_columns": float(1.0 / freq[j]), "period_s": float(exptime_s / (x1 - x0) / freq[j]),
            "false_alarm_probability": float(ls.false_alarm_probability(p[j]))}


def measure_streak(img: np.ndarray, sky: float, exptime_s: float) -> dict:
    """Line, ends, flux, wobble and the profile along the streak (the gap between ASTRiDE's segments)."""
    line = streak_line(img, sky)
    cols = streak_columns(img, line)
    # stars on the streak (a compact peak > 2.5 x the streak's median peak): their columns are left out
    on = np.isfinite(cols["flux"]) & (cols["flux"] > 0.3 * np.nanmax(cols["flux"]))
    hot = np.flatnonzero(on & (cols["peak"] > 2.5 * np.nanmedian(cols["peak"][on])))
    mask = np.zeros(cols["x"].size, bool)
    for j in hot:
        mask |= np.abs(cols["x"] - cols["x"][j]) <= 6
    ends = fit_streak_ends(cols, mask)
    x0, x1 = ends["x0"], ends["x1"]
    inside = (cols["x"] >= x0 + 3) & (cols["x"] <= x1 - 3) & ~mask
    per_col = float(np.nanmean(cols["flux"][inside]))
    length_x = x1 - x0
    gap = gap_profile(cols, x0, x1, mask=mask)
    return {"line": {"a": line["a"], "b": line["b"], "wobble_rms_px": line["wobble_rms_px"]},
            "start_xy": [x0, line["a"] + line["b"] * x0], "end_xy": [x1, line["a"] + line["b"] * x1],
            "length_px": float(length_x * math.sqrt(1 + line["b"] ** 2)), "edge_sigma_px": ends["edge_sigma_px"],
            "flux_adu": per_col * length_x, "flux_per_column_adu": per_col, "gap": gap,
            "stars_on_streak_x": [float(v) for v in cols["x"][hot]], "light_curve": light_curve(cols, x0, x1, mask, exptime_s),
            "columns": cols, "star_mask": mask, "offset_profile": (line["x"], line["offset_px"])}


def streak_object(scene_dict: dict, start_xy, end_xy, exptime_s: float, base_dir: Path) -> dict:
    """RA/Dec of the start and the on-sky rates (dRA/dt cos Dec, dDec/dt) that carry the object from the
    start pixel to the end pixel in ``exptime_s`` along a great circle, through the scene's own WCS."""
    import astropy.units as u
    from astropy.coordinates import SkyCoord

    w = scene_wcs(scene_dict, base_dir)
    (ra0, dec0), (ra1, dec1) = w.all_pix2world([start_xy, end_xy], 0)
    c0, c1 = SkyCoord(ra0 * u.deg, dec0 * u.deg), SkyCoord(ra1 * u.deg, dec1 * u.deg)
    sep = c0.separation(c1).deg
    pa = c0.position_angle(c1).rad
    rate = sep / exptime_s
    return {"ra_deg": float(ra0), "dec_deg": float(dec0), "rate_ra_deg_s": float(rate * math.sin(pa)),
            "rate_dec_deg_s": float(rate * math.cos(pa))}


def calibrate_photons(scene_dict: dict, measured_e: float, base_dir: Path) -> float:
    """Photons at the aperture that give ``measured_e`` electrons on the frame (a trial render of the scene
    with 1e6 photons; its TRUTH flux_e scales linearly)."""
    from scenes.app.render import prepare

    trial = json.loads(json.dumps(scene_dict))
    trial["objects"][0]["photons"] = 1e6
    trial["sky"]["stars"] = False
    sc = load_scene_dict(trial, base_dir / "_photons_probe.toml")
    setup = prepare(sc, workers=1)
    kind = np.char.strip(np.asarray(setup.truth["kind"]).astype(str))
    flux = float(setup.truth["flux_e"][kind == "object"][0])
    return 1e6 * measured_e / flux


# ============================================================================ the scene
def full_sensor(header, shape) -> dict:
    """Full sensor and read-out window from the IRAF section cards (LTV) and the WCS reference pixel, which
    is the full frame's centre (the optical axis) for this camera."""
    h, w = shape
    x0, y0 = round(-float(header.get("LTV1", 0.0))), round(-float(header.get("LTV2", 0.0)))
    cx, cy = float(header["CRPIX1"]) + x0, float(header["CRPIX2"]) + y0  # 1-based, full frame
    return {"sensor_width_px": round(2 * cx - 1), "sensor_height_px": round(2 * cy - 1),
            "width": w, "height": h, "x0": x0, "y0": y0}


def pointing_for_centre(geom: dict, ra_c: float, dec_c: float, sensor: dict) -> tuple[float, float]:
    """Optical axis (CRVAL) that puts the window's centre at (ra_c, dec_c) in the scene's WCS (standard
    parity, roll ``geom['roll_deg']``, scale ``geom['scale_arcsec']``)."""
    from scipy import optimize

    from scenes.projection import tan_wcs

    W, H = sensor["sensor_width_px"], sensor["sensor_height_px"]
    xc = sensor["x0"] + (sensor["width"] - 1) / 2.0  # window centre, full-sensor 0-based
    yc = sensor["y0"] + (sensor["height"] - 1) / 2.0

    def miss(p):
        w = tan_wcs(p[0], p[1], geom["roll_deg"], geom["scale_arcsec"], (H, W))
        ra, dec = w.all_pix2world([[xc, yc]], 0)[0]
        return [((ra - ra_c + 180) % 360 - 180) * math.cos(math.radians(dec_c)) * 3600, (dec - dec_c) * 3600]

    r = optimize.least_squares(miss, [ra_c, dec_c], xtol=1e-14, ftol=1e-14)
    return float(r.x[0] % 360), float(r.x[1])


def exposure_start(header) -> str:
    """UTC start of the exposure: the header's JD is the end of the exposure (DATE-OBS has a two-digit
    century bug, '26/07/102')."""
    import astropy.units as u
    from astropy.time import Time

    t = Time(float(header["JD"]), format="jd", scale="utc") - float(header["EXPTIME"]) * u.s
    return t.utc.isot[:19]


def measure(path=DATA, work: Path | None = None, read_noise_e: float = READ_NOISE_E) -> tuple[dict, dict]:
    """Measure the frame and set up the scene. Returns (scene dict, measurements)."""
    work = Path(work or ROOT / "out" / "realdata" / "astride")
    work.mkdir(parents=True, exist_ok=True)
    img, header = read_frame(path)
    h, w = img.shape
    t = float(header["EXPTIME"])
    sky = float(np.median(img))
    sigma = robust_std(img)
    var = sigma ** 2 - 1.0 / 12.0  # integer data: quantisation
    # var = S/g + (RN/g)^2  ->  var g^2 - S g - RN^2 = 0
    gain = (sky + math.sqrt(sky ** 2 + 4 * var * read_noise_e ** 2)) / (2 * var)
    bg = background_map(img)
    det = detect_sources(img, bg, sigma, nsigma=5.0)
    line0 = streak_line(img, sky)

    def on_streak(x, y):
        return STREAK_GUESS[0][0] - 12 < x < STREAK_GUESS[1][0] + 12 and abs(y - (line0["a"] + line0["b"] * x)) < 14

    psf = fit_psf(img, bg, det, peak_range=(60.0, 1e9), exclude=on_streak)
    geom = wcs_geometry(header)
    sensor = full_sensor(header, img.shape)
    ra_c, dec_c = geom["wcs"].all_pix2world([[(w - 1) / 2.0, (h - 1) / 2.0]], 0)[0]
    if geom["parity"] < 0:
        ra_p, dec_p = geom["crval"]
        parity_note = "standard parity: pointing = CRVAL"
    else:  # mirror image: keep the header's sky at the window centre, north up as in the header
        ra_p, dec_p = pointing_for_centre(geom, ra_c, dec_c, sensor)
        parity_note = ("det CD > 0 in the header (east to the right): the scene's WCS (det < 0) keeps the window "
                       "centre's sky and north, its east-west axis is mirrored")
    band = band_table(BESSELL_R, CCD_QE)
    scene = {
        "telescope": {"design": "art", "pixel_scale_arcsec": round(geom["scale_arcsec"], 5)},
        "detector": {"preset": "ml11002", "name": "ystar-apogee", "kind": "ccd", "shutter": "global",
                     "line_time_s": 0.0, "pixel_pitch_um": 14.0, **sensor, "bit_depth": 16,
                     "gain_e_per_adu": round(gain, 4), "bias_adu": 0.0, "read_noise_e": read_noise_e,
                     "dark_current_e_per_s": 0.0, "full_well_e": 200000.0, "temperature_c": -17.0,
                     "qe_wavelength_nm": band[0], "qe": band[1]},
        "pointing": {"ra_deg": round(ra_p, 7), "dec_deg": round(dec_p, 7), "roll_deg": round(geom["roll_deg"], 5),
                     "epoch": exposure_start(header)},
        "exposure": {"time_s": t, "frame": "light", "tracking": "sidereal", "seed": 1},
        "sky": {"background_mag_arcsec2": 20.0, "stars": True, "star_mag_limit": 17.0, "star_seed": 0,
                "catalog": "builtin"},
        "psf": {"model": "moffat", "fwhm_arcsec": round(psf["fwhm_px"] * geom["scale_arcsec"], 3),
                "beta": round(min(max(psf["beta"], 1.5), 50.0), 3)},
    }
    # zero point from the star counts (no catalogue star in the frame)
    stars_ok = (det["npix"] >= 5) & ~np.array([on_streak(x, y) for x, y in zip(det["x"], det["y"])])
    fl, _ = aperture_flux(img, det["x"][stars_ok], det["y"][stars_ok], 2.0 * psf["fwhm_px"], 3.0 * psf["fwhm_px"],
                          4.5 * psf["fwhm_px"])
    area = (w * geom["scale_arcsec"] / 3600) * (h * geom["scale_arcsec"] / 3600)
    zp = count_zero_point(fl * gain, ra_c, dec_c, area, scene, exptime_s=t)
    scale = zp["scale"]
    qe = [round(q * scale, 6) for q in band[1]]
    if max(qe) > 1:
        raise RuntimeError(f"zero point needs a band peak of {max(qe):.2f} > 1: use a larger telescope design")
    scene["detector"]["qe"] = qe
    scene["sky"]["star_mag_limit"] = round(limiting_mag(scene, sigma, gain, psf["fwhm_px"], t, nsigma=2.0), 2)
    sky_e = sky * gain / t
    scene["sky"]["background_mag_arcsec2"] = round(sky_mag_arcsec2(sky_e, scene), 4)
    # the streak: geometry, then photons from its measured flux
    streak = measure_streak(img, sky, t)
    obj = streak_object(scene, streak["start_xy"], streak["end_xy"], t, work)
    scene["objects"] = [{"name": "astride-streak", **{k: round(v, 9) for k, v in obj.items()}, "photons": 1e6}]
    photons = calibrate_photons(scene, streak["flux_adu"] * gain, work)
    scene["objects"][0]["photons"] = float(f"{photons:.6g}")
    # sky: the model's own median (faint stars, PSF wings) is taken out of the measured one (one iteration)
    from scenes.app.compare import build_model

    sc = load_scene_dict(scene, work / "_sky_probe.toml")
    model = build_model(sc, workers=1, realisation=False)
    excess_e = (float(np.median(model.mean_adu)) - sky) * gain / t
    scene["sky"]["background_mag_arcsec2"] = round(sky_mag_arcsec2(sky_e - excess_e, scene), 4)
    meas = {"frame": str(path), "shape": [h, w], "exptime_s": t, "epoch_start": scene["pointing"]["epoch"],
            "sky_median_adu": sky, "sky_robust_std_adu": sigma, "read_noise_e_assumed": read_noise_e,
            "gain_e_per_adu": gain, "sky_e_per_s": sky_e, "sky_mag_arcsec2": scene["sky"]["background_mag_arcsec2"],
            "n_detected_5sigma": int(det["x"].size), "psf": {k: v for k, v in psf.items() if k != "stars"},
            "wcs": {k: v for k, v in geom.items() if k != "wcs"}, "window": sensor,
            "header_centre_radec": [float(ra_c), float(dec_c)], "pointing": [ra_p, dec_p], "parity_note": parity_note,
            "zero_point": {**zp, "band_peak": max(qe)}, "star_mag_limit": scene["sky"]["star_mag_limit"],
            "streak": {k: v for k, v in streak.items() if k not in ("columns", "star_mask", "offset_profile")},
            "streak_object": scene["objects"][0], "header_wind_kmh": header.get("WINDSPD"),
            "header_fwhm_px": [header.get("FWHMH"), header.get("FWHMV")]}
    return scene, meas


def frame_catalogue(img: np.ndarray, det: dict, scene_dict: dict, meas: dict, csv_path: Path,
                    exclude=None, sharp_max: float = 0.25) -> dict:
    """The frame's own star list as a user catalogue (CSV: ra_deg, dec_deg, mag_g, teff_k, source_id).

    Positions: the detections' centroids through the scene's WCS; magnitudes: aperture fluxes (radius 2.5
    FWHM, local sky from an annulus) through the calibrated band at Teff 5000 K. Sharp events (peak / flux
    > ``sharp_max``: cosmic rays, hot pixels) and sources on the streak are left out. This is circular for the
    stars' positions and fluxes (they come from the frame), so it tests the rest of the model: PSF shape,
    noise, sky, streak, detector.
    """
    gain, t, fwhm = meas["gain_e_per_adu"], meas["exptime_s"], meas["psf"]["fwhm_px"]
    keep = (det["npix"] >= 3) & (det["peak"] / np.maximum(det["flux"], 1e-9) < sharp_max)
    if exclude is not None:
        keep &= ~np.array([exclude(x, y) for x, y in zip(det["x"], det["y"])], bool)
    x, y = det["x"][keep], det["y"][keep]
    fl, _ = aperture_flux(img, x, y, 2.5 * fwhm, 3.5 * fwhm, 5.0 * fwhm)
    ok = np.isfinite(fl) & (fl > 0)
    x, y, fl = x[ok], y[ok], fl[ok]
    rate0 = float(star_rate_e_s(0.0, scene_dict)[0])
    g = -2.5 * np.log10(fl * gain / (rate0 * t))
    w = scene_wcs(scene_dict, csv_path.parent)
    ra, dec = w.all_pix2world(x, y, 0)
    lines = ["ra_deg,dec_deg,mag_g,teff_k,source_id"]
    lines += [f"{a:.8f},{d:.8f},{m:.4f},5000,{i + 1}" for i, (a, d, m) in enumerate(zip(ra, dec, g))]
    csv_path.parent.mkdir(parents=True, exist_ok=True)
    csv_path.write_text("\n".join(lines) + "\n")
    return {"n": int(x.size), "g_min": float(g.min()), "g_max": float(g.max()), "path": str(csv_path)}


def frame_catalogue_scene(scene: dict, meas: dict, img: np.ndarray, out: Path, name: str, exclude=None) -> dict:
    """Scene B: scene A with the frame's own star list instead of the built-in catalogue, and its sky
    re-levelled against the model's median."""
    from scenes.app.compare import build_model

    bg = background_map(img)
    det = detect_sources(img, bg, meas["sky_robust_std_adu"], nsigma=5.0)
    csv = out / f"{name}_frame_stars.csv"
    info = frame_catalogue(img, det, scene, meas, csv, exclude=exclude)
    sb = json.loads(json.dumps(scene))
    sb["sky"].update(catalog=csv.name, star_mag_limit=round(min(25.0, info["g_max"] + 0.5), 2))
    sc = load_scene_dict(sb, out / f"_{name}_sky_probe.toml")
    model = build_model(sc, workers=1, realisation=False)
    gain, t = meas["gain_e_per_adu"], meas["exptime_s"]
    sky_e = (sky_e_from_mag(sb, sb["sky"]["background_mag_arcsec2"])
             - (float(np.median(model.mean_adu)) - meas["sky_median_adu"]) * gain / t)
    sb["sky"]["background_mag_arcsec2"] = round(sky_mag_arcsec2(sky_e, sb), 4)
    return sb, info


def sky_e_from_mag(scene_dict: dict, mag: float) -> float:
    """Sky electrons per second and pixel for ``mag`` AB mag/arcsec^2 through the scene's band."""
    return float(10 ** (-0.4 * (mag - sky_mag_arcsec2(1.0, scene_dict))))


# ============================================================================ checks against the frame
def catalogue_check(header, img: np.ndarray, epoch: str, mag_limit: float = 10.0) -> list[dict]:
    """The built-in catalogue's stars that the header's own WCS puts on the frame, with the flux measured
    there (a 9 x 9 box minus the median): a bright catalogue star with no flux means the WCS is wrong."""
    from scenes.catalog import stars_in_field

    geom = wcs_geometry(header)
    w = geom["wcs"]
    h, wd = img.shape
    ra_c, dec_c = w.all_pix2world([[(wd - 1) / 2.0, (h - 1) / 2.0]], 0)[0]
    st = stars_in_field(ra_c, dec_c, radius_deg=0.75 * math.hypot(h, wd) * geom["scale_arcsec"] / 3600,
                        mag_limit=mag_limit, epoch=epoch, catalog="builtin", seed=0)
    cat = st.source != "synthetic"
    x, y = w.all_world2pix(st.ra_deg[cat], st.dec_deg[cat], 0)
    sky, out = float(np.median(img)), []
    for xi, yi, m in zip(x, y, st.mag_g[cat]):
        if 4 <= xi < wd - 4 and 4 <= yi < h - 4:
            xr, yr = round(xi), round(yi)
            out.append({"mag_g": float(m), "x": float(xi), "y": float(yi),
                        "flux_adu": float(np.sum(img[yr - 4:yr + 5, xr - 4:xr + 5] - sky))})
    return out


def source_maps(cmp: dict) -> tuple[np.ndarray, np.ndarray]:
    """(sources-only model [ADU], the model's background [ADU]) of a comparison. The model's ``photo_adu``
    holds every photo-electron, sky included; the background is the chain's mean frame without the sources
    (:func:`scenes.app.compare.statistics.background_adu`: the sky through vignetting and every other effect)."""
    from scenes.app.compare.statistics import background_adu

    res = cmp["_residuals"]
    bg = np.asarray(background_adu(res), np.float64)
    return res.model_adu - bg, bg


def star_check(cmp: dict, radius: float = 4.0, min_snr: float = 10.0, max_stars: int = 400,
               kinds=("star",)) -> dict:
    """Aperture photometry, centroids and second moments of the model's catalogue stars in data and model,
    with the model's whole background (sky included) subtracted from both (compare the analysis's own
    ``stars``, which keeps the sky in the aperture). Stars with a saturated (measured) or flagged (model)
    pixel in the aperture, or another model source brighter than 5 % of theirs within 2.5 radii, are left out.

    Returns medians: flux ratio data/model, centroid offset [px], sigma_x and sigma_y [px] of data and
    model, and ``sigma_xy_ratio`` = (sigma_y / sigma_x)_data / (sigma_y / sigma_x)_model (1: the model's
    PSF shape; > 1: stars elongated along the columns)."""
    res, model = cmp["_residuals"], cmp["_model"]
    truth = model.setup.truth
    if truth is None or len(truth) == 0:
        return {"n": 0}
    kind = np.char.strip(np.asarray(truth["kind"]).astype(str))
    allsrc = truth[kind != "object"]
    st = truth[np.isin(kind, kinds)]
    src, bg = source_maps(cmp)
    h, w = res.data_adu.shape
    # S/N against the sky's noise (the model's variance of star pixels may hold hardware-pattern terms)
    sky_var = float(np.median(res.var_adu2[res.fit & (src < 0.5 * np.sqrt(res.var_adu2))]))
    from scenes.app.compare.model import saturation_adu

    sat = saturation_adu(model.sensor)
    R = math.ceil(radius)
    yy, xx = np.mgrid[-R:R + 1, -R:R + 1]
    ap = xx ** 2 + yy ** 2 <= radius ** 2
    rows = []
    for i in np.argsort(-st["flux_e"]):
        x, y = float(st["x"][i]), float(st["y"][i])
        xi, yi = round(x), round(y)
        if xi < R or yi < R or xi >= w - R or yi >= h - R:
            continue
        near = np.hypot(allsrc["x"] - x, allsrc["y"] - y)
        if np.any((near > 0.3) & (near < 2.5 * radius) & (allsrc["flux_e"] > 0.05 * st["flux_e"][i])):
            continue
        sl = (slice(yi - R, yi + R + 1), slice(xi - R, xi + R + 1))
        if (res.data_adu[sl][ap] >= sat).any() or model.flag[sl][ap].any():
            continue
        m = src[sl] * ap
        d = (res.data_adu[sl] - bg[sl]) * ap
        var = float(res.var_adu2[sl][ap].sum())
        fm = float(m.sum())
        if fm < min_snr * math.sqrt(sky_var * ap.sum()):
            continue
        mom = []
        for img in (d, m):
            wgt = np.clip(img, 0, None)
            t = max(wgt.sum(), 1e-9)
            cx, cy = (wgt * xx).sum() / t, (wgt * yy).sum() / t
            mom += [cx, cy, math.sqrt((wgt * (xx - cx) ** 2).sum() / t), math.sqrt((wgt * (yy - cy) ** 2).sum() / t)]
        rows.append([float(st["mag"][i]), x, y, float(d.sum()) / fm, math.sqrt(var) / fm, mom[0] - mom[4],
                     mom[1] - mom[5], mom[2], mom[3], mom[6], mom[7]])
        if len(rows) >= max_stars:
            break
    if not rows:
        return {"n": 0}
    a = np.array(rows)
    med = lambda k: float(np.median(a[:, k]))
    out = {"n": len(rows), "median_flux_ratio": med(3), "median_offset_px": float(np.median(np.hypot(a[:, 5], a[:, 6]))),
           "mean_offset_px": [float(a[:, 5].mean()), float(a[:, 6].mean())],
           "sigma_x_data_px": med(7), "sigma_y_data_px": med(8), "sigma_x_model_px": med(9), "sigma_y_model_px": med(10),
           "sigma_xy_ratio": float(np.median((a[:, 8] / a[:, 7]) / (a[:, 10] / a[:, 9]))),
           "size_ratio": float(np.median(np.hypot(a[:, 7], a[:, 8]) / np.hypot(a[:, 9], a[:, 10]))),
           "table": a}
    if len(rows) >= 5:
        out["flux_ratio_vs_mag_slope"] = float(np.polyfit(a[:, 0], a[:, 3], 1)[0])
    return out


def star_rows(stars: dict) -> dict:
    """The headline numbers of :func:`star_check` for the round table (keys ``row_*``)."""
    return {"row_star_n": stars.get("n", 0), "row_star_flux_ratio": stars.get("median_flux_ratio"),
            "row_star_offset_px": stars.get("median_offset_px"), "row_star_size_ratio": stars.get("size_ratio"),
            "row_star_sigma_xy_ratio": stars.get("sigma_xy_ratio")}


def streak_model_profile(cmp: dict, meas_streak: dict, bin_px: int = 4) -> dict:
    """Data and model along the streak in ``bin_px``-column bins: flux within 9 px of the line and peak
    (surface brightness), each with the model's sky replaced by its median; data / model ratios. The gap
    between ASTRiDE's two segments is a dip of the peak ratio (the light is spread, not lost)."""
    res = cmp["_residuals"]
    line = meas_streak["line"]
    bg = res.model_adu - res.photo_adu
    data = res.data_adu - bg + float(np.median(bg))
    cols_d = streak_columns(data, line)
    cols_m = streak_columns(res.photo_adu + float(np.median(bg)), line)
    x0, x1 = meas_streak["start_xy"][0], meas_streak["end_xy"][0]
    stars = np.zeros(cols_d["x"].size, bool)
    for xs in meas_streak.get("stars_on_streak_x", []):
        stars |= np.abs(cols_d["x"] - xs) <= 6
    edges = np.arange(x0 + 2, x1 - 2 + 1e-9, bin_px)
    xs, fd, fm, pd, pm = [], [], [], [], []
    for lo, hi in itertools.pairwise(edges):
        m = (cols_d["x"] >= lo) & (cols_d["x"] < hi) & ~stars
        if m.sum() < bin_px // 2:
            continue
        xs.append(0.5 * (lo + hi))
        fd.append(float(np.nanmean(cols_d["flux"][m])))
        fm.append(float(np.nanmean(cols_m["flux"][m])))
        pd.append(float(np.nanmean(cols_d["peak"][m])))
        pm.append(float(np.nanmean(cols_m["peak"][m])))
    fd, fm, pd, pm = map(np.asarray, (fd, fm, pd, pm))
    ratio = fd / np.where(fm > 0, fm, np.nan)
    pratio = pd / np.where(pm > 0, pm, np.nan)
    j = int(np.nanargmin(pratio))
    return {"x": np.asarray(xs), "data": fd, "model": fm, "ratio": ratio, "peak_ratio": pratio,
            "min_peak_ratio": float(pratio[j]), "min_peak_ratio_x": float(xs[j]),
            "median_ratio": float(np.nanmedian(ratio)), "ratio_rms": robust_std(ratio[np.isfinite(ratio)])}


# ============================================================================ rounds
def rounds(scene: dict, measured: str, out: Path, name: str, n_rounds: int, extra=None, prefer=()) -> list[dict]:
    """compare/diagnose/apply until no candidate is significant (at most ``n_rounds``), with this script's
    own checks (``extra``) in every round's JSON and table row; ``prefer``: effects applied before the
    ranking's best when significant (``newtsim diagnose --prefer``)."""
    from scenes.app.compare.run import run_rounds

    return run_rounds(scene, measured, out, name, n_rounds, workers=2, extra=extra, prefer=tuple(prefer),
                      log=lambda line: print(line, flush=True))


def on_streak_test(meas: dict):
    """A function (x, y) -> True for positions within 14 px of the measured streak (between its ends)."""
    line, (x0, _), (x1, _) = meas["streak"]["line"], meas["streak"]["start_xy"], meas["streak"]["end_xy"]
    return lambda x, y: x0 - 12 < x < x1 + 12 and abs(y - (line["a"] + line["b"] * x)) < 14


def print_table(name: str, table: list[dict]) -> None:
    print(f"\n{name}: round  chi2/dof   misfit  stars(n, flux, offset px, size)  y/x shape  streak peak-ratio "
          "min (x)  best candidates (dBIC)")
    for r in table:
        print(f"{'':{len(name)}}  {r['round']:5d}  {r['chi2_per_dof']:8.4g}  {r['misfit']:7.4g}  "
              f"{r.get('row_star_n', 0):3d} {_f(r.get('row_star_flux_ratio'))} {_f(r.get('row_star_offset_px'))} "
              f"{_f(r.get('row_star_size_ratio'))}  "
              f"{_f(r.get('row_star_sigma_xy_ratio'))}  {_f(r.get('row_streak_min_peak_ratio'))} "
              f"({_f(r.get('row_streak_min_peak_x'))})  "
              + ", ".join(f"{e} {d:.3g}" for e, d, _ in r["candidates"][:3]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", nargs="?", default="out/realdata/astride")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--write-scene", action="store_true", help="refresh examples/diagnose/scenes/astride.toml")
    args = ap.parse_args(argv)
    if not DATA.is_file():
        print(f"real data not found at {DATA}: nothing to do", file=sys.stderr)
        return 1
    out = Path(args.out).resolve()  # absolute: the scenes name their catalogue relative to themselves
    out.mkdir(parents=True, exist_ok=True)
    scene, meas = measure(DATA, out)
    img, header = read_frame(DATA)
    meas["catalogue_check"] = catalogue_check(header, img, scene["pointing"]["epoch"])
    if args.write_scene:
        import tomli_w

        SCENE.parent.mkdir(parents=True, exist_ok=True)
        SCENE.write_text("# written by examples/diagnose/real_astride.py --write-scene: every value measured from\n"
                         "# ../shared/realdata/streak/astride_long.fits or stated there as an assumption\n"
                         + tomli_w.dumps(scene))
    zp, st = meas["zero_point"], meas["streak"]
    print(f"setup: gain {meas['gain_e_per_adu']:.3g} e-/ADU (RN {READ_NOISE_E} e- assumed), sky "
          f"{meas['sky_median_adu']:.1f} ADU = {meas['sky_mag_arcsec2']:.2f} mag/arcsec2 (AB, calibrated band), "
          f"PSF FWHM {meas['psf']['fwhm_major_px']:.2f} x {meas['psf']['fwhm_minor_px']:.2f} px (major axis at "
          f"{meas['psf']['pa_major_deg']:.0f} deg), beta {meas['psf']['beta']:.1f}; band scale {zp['scale']:.3g} "
          f"({zp['scale_16']:.3g}-{zp['scale_84']:.3g}) from star counts; G limit {meas['star_mag_limit']}")
    print(f"streak: {st['length_px']:.1f} px from ({st['start_xy'][0]:.1f}, {st['start_xy'][1]:.1f}) to "
          f"({st['end_xy'][0]:.1f}, {st['end_xy'][1]:.1f}), {st['flux_adu']:.4g} ADU, wobble {st['line']['wobble_rms_px']:.2f}"
          f" px rms; gap at x = {st['gap']['dip_x']:.0f}: peak {st['gap']['dip_peak_rel']:.2f}, flux "
          f"{st['gap']['dip_flux_rel']:.2f} of the median, width {st['gap']['dip_width_px']:.2f} px (median "
          f"{st['gap']['median_width_px']:.2f}); light curve rms {st['light_curve']['intrinsic_rms_rel']:.2f} "
          f"(noise {st['light_curve']['noise_rel']:.2f}), period {st['light_curve']['period_s']:.2f} s "
          f"(FAP {st['light_curve']['false_alarm_probability']:.1e})")
    print("catalogue stars the header's WCS puts on the frame: "
          + (", ".join(f"G {c['mag_g']:.2f} at ({c['x']:.0f}, {c['y']:.0f}): {c['flux_adu']:.0f} ADU"
                       for c in meas["catalogue_check"]) or "none"), flush=True)

    def extra(cmp):
        prof = streak_model_profile(cmp, meas["streak"])
        stars = star_check(cmp)
        return {"streak_profile": prof, "star_check": {k: v for k, v in stars.items() if k != "table"},
                **star_rows(stars), "row_streak_min_peak_ratio": prof["min_peak_ratio"],
                "row_streak_min_peak_x": prof["min_peak_ratio_x"], "row_streak_ratio_rms": prof["ratio_rms"],
                "row_streak_median_ratio": prof["median_ratio"]}

    summary = {"setup": meas}
    summary["builtin"] = rounds(scene, str(DATA), out, "astride_builtin", args.rounds, extra=extra)
    sb, info = frame_catalogue_scene(scene, meas, img, out, "astride", exclude=on_streak_test(meas))
    summary["frame_catalogue"] = {"catalogue": info, "rounds": rounds(sb, str(DATA), out, "astride_framecat",
                                                                      args.rounds, extra=extra)}
    (out / "setup.json").write_text(json.dumps(jsonable(meas), indent=1, default=str))
    (out / "summary.json").write_text(json.dumps(jsonable(summary), indent=1, default=str))
    print_table("builtin catalogue", summary["builtin"])
    print_table("frame's own stars", summary["frame_catalogue"]["rounds"])
    print(f"wrote {out}/summary.json, setup.json and the per-round scenes, JSON, ledgers and reports")
    return 0


def _f(v) -> str:
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v:.3g}"


if __name__ == "__main__":
    sys.exit(main())
