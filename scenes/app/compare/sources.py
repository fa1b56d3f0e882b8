"""Candidates that belong to a scene's sources, not to the detector: an object's light curve.

The detector catalogue's signatures see pixels; a tumbling or glinting object shows as a streak whose flux
varies along its length, which only the object's track can turn into time. For every object of the model's
TRUTH table (``t0_s``, ``t1_s``: when it is at the streak's ends), the flux along the track in 1-px bins,
data against model over the model's background (:func:`scenes.app.compare.statistics.background_adu`), is
fitted by a sinusoidal modulation ``D_k = M_k (1 + L) (1 + a sin(2 pi (t_k / P + phi)))`` (L the object's
flux scale, profiled): linear in ``(a cos 2 pi phi, a sin 2 pi phi)`` for each period P of a logarithmic
grid (a Lomb-Scargle periodogram weighted by the model's variance; Lomb 1976, Ap&SS 39, 447; Scargle 1982,
ApJ 263, 835), the best P refined. It is ranked with the catalogue's candidates by
``delta_BIC = delta chi^2 + 3 ln n`` (amplitude, phase, period). ``--apply`` writes the fitted
``light_curve`` into the object's ``[[objects]]`` table (:mod:`scenes.objects.lightcurve`, same phase
convention).
"""

from __future__ import annotations

import numpy as np

from detector.signatures import Fit, Residuals

from .statistics import background_adu, track_band

#: name of the candidate (not a detector effect: ``apply_candidate`` writes it into ``[[objects]]``)
LIGHT_CURVE = "light_curve"
#: half-width of the band around the track that holds the streak's light [px]
HALF_WIDTH_PX = 6.0
#: shortest period tried, in bins of the track (Nyquist: 2; a PSF spreads light over a few bins)
MIN_PERIOD_BINS = 4.0
#: periods tried on the logarithmic grid (then refined around the best)
N_PERIODS = 400
#: parameters the light curve adds to a steady object (amplitude, phase, period): the ``k`` of its delta BIC; the
#: fit needs more bins along the track than these and the profiled flux scale (its significance is then the
#: delta BIC's and the held-out score's, as every candidate's)
LIGHT_CURVE_PARAMETERS = 3


def track_profile(res: Residuals, row, bg: np.ndarray) -> dict | None:
    """Flux per 1-px bin along an object's track: data, model (both over the model's background ``bg``),
    the model's variance, the time of each bin [s], and the band's box with the bin of each of its pixels
    (-1 outside the band)."""
    t0, t1 = float(row["t0_s"]), float(row["t1_s"])
    band = track_band(res.data_adu.shape, row, HALF_WIDTH_PX)
    if not (np.isfinite(t0) and np.isfinite(t1) and t1 > t0) or band is None:
        return None
    if band["length"] <= LIGHT_CURVE_PARAMETERS + 1:  # no bin left to test the fit on
        return None
    box, along, length = band["box"], band["along"], band["length"]
    n = int(np.floor(length))
    inside = (np.abs(band["across"]) <= HALF_WIDTH_PX) & (along >= 0) & (along < n) & res.fit[box]
    bins = np.where(inside, np.floor(along).astype(int), -1)
    sel = bins >= 0
    d = np.bincount(bins[sel], (res.data_adu[box] - bg[box])[sel], n)
    m = np.bincount(bins[sel], (res.model_adu[box] - bg[box])[sel], n)
    v = np.bincount(bins[sel], res.var_adu2[box][sel], n)
    ok = (v > 0) & (m > 3 * np.sqrt(np.maximum(v, 1e-30)))
    if ok.sum() <= LIGHT_CURVE_PARAMETERS + 1:
        return None
    t = t0 + (np.arange(n) + 0.5) / length * (t1 - t0)
    return {"d": d, "m": m, "v": v, "t": t, "ok": ok, "box": box, "bins": bins, "dt_bin": (t1 - t0) / length}


def _fit_period(prof: dict, period: float) -> tuple[float, np.ndarray]:
    """Weighted least squares of the flux on (M, M sin, M cos) at ``period``: (chi2, coefficients)."""
    ok = prof["ok"]
    m, d, w, t = prof["m"][ok], prof["d"][ok], 1.0 / prof["v"][ok], prof["t"][ok]
    ph = 2 * np.pi * t / period
    x = np.stack([m, m * np.sin(ph), m * np.cos(ph)])
    xw = x * w
    c = np.linalg.solve(xw @ x.T + 1e-12 * np.eye(3), xw @ d)
    r = d - c @ x
    return float(np.dot(r * r, w)), c


def light_curve_fit(res: Residuals, row, index: int, bg: np.ndarray | None = None) -> Fit | None:
    """The sinusoidal light curve of object ``index`` (its TRUTH ``row``), or None without a usable track;
    ``bg`` the model's background (:func:`background_adu`, computed when not given)."""
    bg = background_adu(res) if bg is None else bg
    prof = track_profile(res, row, bg)
    if prof is None:
        return None
    ok = prof["ok"]
    m, d, w = prof["m"][ok], prof["d"][ok], 1.0 / prof["v"][ok]
    scale = float(np.dot(m * d, w) / np.dot(m * m, w))  # the constant-brightness fit (flux scale only)
    chi2_0 = float(np.dot((d - scale * m) ** 2, w))
    span = prof["t"][ok][-1] - prof["t"][ok][0]
    periods = np.geomspace(MIN_PERIOD_BINS * prof["dt_bin"], 2.0 * span, N_PERIODS)
    chi2 = np.array([_fit_period(prof, p)[0] for p in periods])
    j = int(np.argmin(chi2))
    lo, hi = periods[max(j - 1, 0)], periods[min(j + 1, len(periods) - 1)]
    fine = np.linspace(lo, hi, 41)
    chi2_fine = np.array([_fit_period(prof, p)[0] for p in fine])
    period = float(fine[int(np.argmin(chi2_fine))])
    best, c = _fit_period(prof, period)
    if c[0] <= 0:
        return None
    a = float(np.hypot(c[1], c[2]) / c[0])
    if not 0 < a <= 1:
        return None
    phase = float(np.arctan2(c[2], c[1]) / (2 * np.pi)) % 1.0
    curve = {"kind": "sinusoid", "amplitude": round(a, 4), "period_s": round(period, 5), "phase": round(phase, 4)}
    # the mean change of the model: every pixel of the band times the fitted modulation of its bin
    box, bins = prof["box"], prof["bins"]
    sel = bins >= 0
    mod = c[0] * (1 + a * np.sin(2 * np.pi * (prof["t"] / period + phase))) - 1.0
    delta = np.zeros(res.data_adu.shape, np.float32)
    patch = np.zeros(bins.shape, np.float32)
    patch[sel] = ((res.model_adu[box] - bg[box])[sel] * mod[bins[sel]]).astype(np.float32)
    delta[box] = patch
    n = int(ok.sum())
    name = str(row["name"].decode() if isinstance(row["name"], bytes) else row["name"]).strip()
    words = (f"the streak of {name or f'objects[{index}]'} brightens and fades by {100 * a / np.sqrt(2):.2g} % rms "
             f"with a {period:.3g} s period along its track: a tumbling or glinting object (a light curve)")
    return Fit(LIGHT_CURVE, {"object": index, "light_curve": curve}, best - chi2_0, LIGHT_CURVE_PARAMETERS, n, words,
               delta_adu=delta, note=f"period {period:.4g} s")


def light_curve_candidates(res: Residuals, truth, scene):
    """The light-curve fits of the scene's objects that do not have a light curve yet (a generator: each
    fit is made when it is asked for)."""
    if truth is None or len(truth) == 0 or "t0_s" not in truth.dtype.names:
        return
    kind = np.char.strip(np.asarray(truth["kind"]).astype(str))
    bg = None
    for row in truth[kind == "object"]:
        i = int(row["source_id"])
        if i < len(scene.objects) and "light_curve" not in scene.objects[i]:
            bg = background_adu(res) if bg is None else bg
            fit = light_curve_fit(res, row, i, bg)
            if fit is not None:
                yield fit
