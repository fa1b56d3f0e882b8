"""Pixel response: PRNU, DSNU, dead pixels, amplifier gain regions, nonlinearity.

References
----------
* EMVA Standard 1288, Release 4.0 (2021), sections 4.1-4.3 and 8: linear camera model, PRNU and DSNU
  as spatial standard deviations, linearity error.
* J. R. Janesick, *Photon Transfer*, SPIE Press (2007), chapters 5-8: fixed pattern noise, PRNU,
  dark FPN, nonlinearity.
* Reference thesis, section 3.6 (fixed-pattern components of the detector model).
"""

from __future__ import annotations

from itertools import pairwise
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from ..rng import standard_normal_f32
from ..signatures import (
    DEFECT_K,
    LINE_WINDOW,
    GroupSignature,
    LinearSignature,
    VarianceSignature,
    Variant,
    frame_fraction,
    group_excess,
    group_price,
    on_source,
    outlier_pixels,
    spread_check,
)
from ..significance import DETECTION_SIGMA, MAX_DEFECT_FRACTION
from ..stats import CHI2_1_MEDIAN, median_square_variance_error
from .base import Effect, EffectParams, Stage, Tile, register_effect
from .common import hardware_positions, in_tile, output_xy, roi_mask

# --- pure functions ---------------------------------------------------------------------------------------

def prnu_map(rng: np.random.Generator, shape: tuple[int, int], sigma: float) -> np.ndarray:
    """Photo-response map with mean 1 and spatial std ``sigma`` (EMVA 1288 PRNU), clipped at 0 [1]."""
    m = standard_normal_f32(rng, shape)
    m *= np.float32(sigma)
    m += np.float32(1.0)
    np.maximum(m, 0, out=m)
    return m


def dsnu_map(rng: np.random.Generator, shape: tuple[int, int], sigma: float, law: str) -> np.ndarray:
    """Dark-current multiplier per pixel, mean 1 and std ``sigma`` [1].

    ``lognormal`` (default) keeps every pixel's dark current positive and gives the skewed tail measured
    on real sensors (Janesick 2007, ch. 7); ``normal`` is the EMVA 1288 Gaussian approximation.
    """
    z = standard_normal_f32(rng, shape)
    if law == "normal":
        z *= np.float32(sigma)
        z += np.float32(1.0)
        return np.maximum(z, 0, out=z)
    s2 = np.log1p(sigma * sigma)  # lognormal with E = 1, Var = sigma^2
    z *= np.float32(np.sqrt(s2))
    z += np.float32(-s2 / 2)
    return np.exp(z, out=z)


def quadratic_nonlinearity(signal_e: np.ndarray, beta: float, full_well_e: float, beta2: float = 0.0) -> None:
    """In place: ``S' = S (1 - beta x - beta2 x^2)``, ``x = S / FW``: a response ``beta + beta2`` low at full
    well (EMVA 1288 sec. 8.2). ``beta`` is a deficit growing linearly with the signal; ``beta2`` one growing as
    its square, which stays small up to a good fraction of the well and then bends: the leading term of a soft
    saturation (a response ``a tanh(x / a)`` has ``beta2 = 1 / (3 a^2)``; the potential well's capacitance falling
    as it fills, Janesick 2007, Photon Transfer, ch. 11)."""
    if beta or beta2:
        x = signal_e * np.float32(1.0 / full_well_e)
        f = x * np.float32(-beta2) - np.float32(beta) if beta2 else np.float32(-beta)
        f = f * x
        f += np.float32(1.0)
        signal_e *= f


def knee_nonlinearity(signal_e: np.ndarray, deficit: float, knee_e: float) -> None:
    """In place: ``S' = S - deficit (S - K)`` above the knee ``K`` [e-], ``S`` below it: a response linear up
    to a signal where its slope changes by ``deficit`` (0.2: the slope falls to 80 %; negative: it rises), then
    linear again. Where the sense node's or the output amplifier's gain changes with the signal at one level
    (the storage well's capacitance stepping as it fills, a source follower leaving its linear range) the
    response bends over a narrow range of the signal rather than along the whole well: a piecewise-linear
    (knee) response (Janesick 2007, Photon Transfer, ch. 11: non-linearity near full well; EMVA 1288 R4.0
    sec. 8.2 measures the deviation from a straight line whatever its form; multi-slope CMOS pixels set such
    knees on purpose)."""
    if deficit:
        above = np.maximum(signal_e - np.float32(knee_e), np.float32(0.0))
        signal_e -= np.float32(deficit) * above


#: signal [fraction of the full well] where a power-law response equals the linear one (its reference)
POWER_LAW_REFERENCE = 0.5

#: the knees [fraction of the full well] the diagnosis tries for a piecewise-linear response: the upper part of
#: the well, where a sense node or an amplifier leaves its linear range (below 0.2 the knee would be a change of
#: gain over the whole frame's sources, the quadratic and power laws' domain; above 0.8 it meets the clip at full
#: well that blooming and saturation act on)
KNEE_FRACTIONS = (0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8)


def power_law_nonlinearity(signal_e: np.ndarray, gamma: float, reference_e: float) -> None:
    """In place: ``S' = S (S / S_ref)^(gamma - 1)``, a power-law (gamma) response that equals the linear one
    at ``S_ref`` [e-] and departs from it logarithmically on both sides (``S' / S - 1 ~ (gamma - 1)
    ln(S / S_ref)``): the response of a sensor read through a compressive (or expansive) transfer, e.g. a
    logarithmic or partially logarithmic CMOS pixel (Janesick 2007 ch. 11: non-linearity measured over the
    whole signal range; EMVA 1288 sec. 8.2 reports its deviation from a straight line). Where the signal is
    zero or negative the pixel is left as it is."""
    if gamma != 1.0:
        x = np.maximum(signal_e, np.float32(1e-3)) / np.float32(reference_e)
        f = np.power(x, np.float32(gamma - 1.0), dtype=np.float32)
        np.multiply(signal_e, f, out=signal_e, where=signal_e > 0)


def region_index(ys: np.ndarray, xs: np.ndarray, nx: int, ny: int, height: int, width: int,
                 splits_y=None, splits_x=None) -> tuple[np.ndarray, np.ndarray]:
    """Amplifier region (row index, column index) of sensor coordinates on an ``ny x nx`` grid: equal
    segments, or those between the boundaries ``splits_y`` / ``splits_x`` [sensor pixels] where given."""
    iy = (np.searchsorted(np.asarray(splits_y, float), ys, side="right") if splits_y is not None
          else np.minimum((ys * ny // height).astype(int), ny - 1))
    ix = (np.searchsorted(np.asarray(splits_x, float), xs, side="right") if splits_x is not None
          else np.minimum((xs * nx // width).astype(int), nx - 1))
    return iy, ix


# --- diagnosis signatures (detector.signatures) -------------------------------------------------------------

def _prnu_params(theta: float, res) -> dict | None:
    sigma = float(np.sqrt(theta))
    return {"sigma": float(f"{sigma:.6g}")} if 0 < sigma <= 0.5 else None


def _dsnu_params(theta: float, res, law: str = "lognormal") -> dict | None:
    sigma = float(np.sqrt(theta))
    return {"sigma": float(f"{sigma:.6g}"), "law": law} if 0 < sigma <= 5 else None


def _pixels_per_output(res) -> float:
    """Sensor pixels whose patterns average into one output pixel's relative scatter (b^2 when binned)."""
    return float(res.sensor.binning ** 2)


def _prnu_template(res):
    """Variance [ADU^2] of a unit-sigma response map: (photo)^2, divided by the b^2 pixels a binned output
    pixel sums or averages (their maps are independent)."""
    return res.photo_adu.astype(np.float64) ** 2 / _pixels_per_output(res)


def _dsnu_template(res):
    return (res.dark_e.astype(np.float64) / res.gain) ** 2 / _pixels_per_output(res)


def _dsnu_lognormal_k3(theta: float, res, idx) -> np.ndarray:
    """Third cumulant [ADU^3] of a lognormal DSNU of relative variance theta: (3 + s^2) s^4 D^3 per sensor
    pixel (skewness (3 + s^2) s), summed over the b^2 pixels of an output pixel: (3 + theta) theta^2 t^1.5 / b
    with t the variance template."""
    d = res.dark_e.ravel()[idx].astype(np.float64) / res.gain
    b = res.sensor.binning
    return (3 + theta) * theta ** 2 * (d * d / (b * b)) ** 1.5 / b


def _dsnu_check(fit, res) -> str:
    """A DSNU multiplies each pixel's dark current by a non-negative factor: its large-scale part (the fit's smooth
    part, a field of dark rate: EMVA 1288 Release 4.0, sect. 8.3) cannot take the dark rate below
    zero within the window, the bar a dark-rate field is held to (:func:`.thermal.base_rate`, the larger of the
    sensor's, the model's and the frame's own measured dark rate). A field that does is charge added on top of
    the dark current (a glow) or an offset taken for it, not a non-uniformity of the pixels' rates."""
    smooth = fit.state.get("smooth_adu")
    if smooth is None or res.exptime_s <= 0 or not np.any(res.fit):
        return ""
    from .thermal import base_rate

    unit = res.adu_per_rate  # ADU per (e-/s) of dark rate per sensor pixel
    lowest = float(np.min(np.broadcast_to(smooth, res.data_adu.shape)[np.broadcast_to(res.fit, res.data_adu.shape)]))
    base = base_rate(res)
    if base + lowest / unit > 0:
        return ""
    return (f"its large-scale part would take the dark rate below zero within the window (its lowest point "
            f"{-lowest / unit:.3g} e-/s below the mean, more than the frame's rate of {base:.3g} e-/s): a pixel's "
            "dark current is its rate times a non-negative factor; charge added on top of the dark current (a glow) "
            "or an offset, not a non-uniformity of the rates")


def _lit(res, index: np.ndarray) -> np.ndarray:
    """Which of these pixels receive enough light that losing it is a 5-sigma deficit (a dead pixel can only
    be seen where light falls: it loses its photo-response, not its dark signal or bias)."""
    from ..signatures import SPIKE_SIGMA

    if index.size == 0:
        return np.zeros(0, bool)
    p = res.photo_adu.ravel()[index]
    return p > SPIKE_SIGMA * np.sqrt(res.var_adu2.ravel()[index])


#: the largest group of dark pixels taken for one defect [pixels]: sensors have isolated dead pixels and small
#: clusters of them (EMVA 1288 release 4.0 sect. 8.4, defect pixels; Janesick 2007 ch. 8, "clusters"); a larger
#: dark patch (dust, a shadow) is a structure of the light
MAX_DEAD_CLUSTER_PX = 25
#: the largest cluster side the plugin draws [pixels]
MAX_DEAD_CLUSTER_SIDE = 4


def _dead_defects(res, groups: np.ndarray) -> np.ndarray:
    """The groups of dark pixels that may be dead or weak defects: small, seen whole (not touching a saturated
    or flagged pixel), where light falls (a defect loses its photo-response only), not on the model's sources."""
    if groups.size == 0:
        return groups
    ok = ((groups["n"] <= MAX_DEAD_CLUSTER_PX) & ~groups["edge"] & _lit(res, groups["peak"])
          & ~on_source(res, groups["peak"]))
    return groups[ok]


def _dead_groups(res):
    """Dead and weak pixels (isolated or in clusters) from the chi2 their groups of dark pixels carry beyond
    what the model's realisation makes (:func:`detector.signatures.group_gain`); the response of each from its
    deficit against the model's photo-signal, the cluster side from the groups' sizes."""
    npx = outlier_pixels(res)
    gd = _dead_defects(res, res.data_spikes.neg_groups)
    gm = _dead_defects(res, res.model_spikes.neg_groups)
    got = group_excess(gd, gm, DEFECT_K, npx)
    if got is None:
        return None
    delta, n_data, n_model = got
    kept = gd[group_price(gd, DEFECT_K, npx) < 0]  # the groups group_gain kept
    idx = kept["peak"]
    photo = res.photo_adu.ravel()[idx].astype(np.float64)
    ratio = np.clip(1.0 + (res.data_adu.ravel()[idx] - res.model_adu.ravel()[idx]) / photo, 0.0, 0.99)
    err = np.sqrt(res.var_adu2.ravel()[idx]) / photo  # one pixel's response error [1]
    side = int(np.clip(round(float(np.sqrt(np.median(kept["n"])))), 1, MAX_DEAD_CLUSTER_SIDE))
    params = {"count": round((n_data - n_model) / frame_fraction(res)), "cluster_px": side}
    if ratio.size >= 3 and np.std(ratio) > 3 * float(np.median(err)):
        # the responses differ beyond their errors: a range (uniform law) from the lowest to the highest
        params.update(response=round(float(ratio.min()), 4), response_max=round(max(float(ratio.max()),
                                                                                    float(ratio.min()) + 1e-3), 4))
    else:
        params["response"] = round(float(np.median(ratio)), 4)
    return params, delta, n_data, n_model, 2 + ("response_max" in params) + (side > 1)


def _dead_words(p, res):
    resp = (f"response {p['response']:.2g}" if "response_max" not in p else
            f"responses {p['response']:.2g} to {p['response_max']:.2g}")
    unit = "pixels" if p.get("cluster_px", 1) == 1 else f"clusters of {p['cluster_px']}x{p['cluster_px']} pixels"
    return f"pixels far below their neighbours ({p['count']} {unit} on the sensor, {resp}): dead or weak pixels"


_REGION_GRIDS = ((2, 1), (1, 2), (2, 2), (4, 1), (1, 4), (4, 2), (2, 4), (4, 4), (8, 1), (1, 8))


def _gain_signal(res) -> np.ndarray:
    """What an amplifier's gain multiplies [ADU]: the converted charge (light and dark), not the bias or its
    structure (on a bias frame gain regions change nothing)."""
    return (res.charge_e / np.float32(res.gain)).astype(np.float32)


def _gain_variants(res):
    s = res.sensor
    sig = _gain_signal(res)
    w = res.data_adu.shape[1]
    for nx, ny in _REGION_GRIDS:
        iy, ix = region_index(res.ys, res.xs, nx, ny, s.sensor_height_px, s.sensor_width_px)
        k = iy[:, None] * nx + ix[None, :]
        # the regions the window holds: every pair of a row's and a column's region (the same sorted values as
        # np.unique(k), from the 1-D indices); their pixel counts, the products of the rows' and columns'
        present = np.unique(np.unique(iy)[:, None] * nx + np.unique(ix)[None, :])
        if present.size < 2:
            continue
        npx = np.array([np.count_nonzero(iy == j // nx) * np.count_nonzero(ix == j % nx) for j in present], float)

        def at(idx, iy=iy, ix=ix, nx=nx, present=present):
            y, x = np.divmod(idx, w)
            kk = iy[y] * nx + ix[x]
            sv = sig.ravel()[idx].astype(np.float64)
            return np.stack([np.where(kk == j, sv, 0.0) for j in present])

        def maps(k=k, present=present):
            return [np.where(k == j, sig, np.float32(0)) for j in present]

        def to_params(c, nx=nx, ny=ny, present=present, npx=npx):
            # relative gains: a common factor is the light level (refitted with the levels), so the gains are
            # normalised to a pixel-weighted mean of 1
            g = np.ones(nx * ny)
            g[present] += c
            g = g / (np.dot(g[present], npx) / npx.sum())
            return {"nx": nx, "ny": ny, "gains": [round(float(x), 6) for x in g]} if (g > 0).all() else None

        yield Variant(maps, to_params, f"{nx}x{ny}", at=at)
    yield from _gain_split_variants(res, sig)


#: boundaries found from the data: at most this many along an axis (a sensor read by up to 8 amplifiers along a
#: side, as LSST's CCDs are, 2 x 8 segments; each further boundary is a variant of its own, scored by the BIC with
#: one parameter per boundary, so a sensor of fewer strips keeps its fewer), each at least this share of the frame from
#: an edge (a segment that holds fewer lines holds fewer pixels than an anomalous-pixel population may,
#: MAX_DEFECT_FRACTION: at the frame's edge it is an edge effect, a glow along it, a shadow), and at least
#: LINE_WINDOW lines from another: a step of the line means that persists over that many lines is a level of the
#: neighbourhood to the column (row) statistic, which compares each line with the running median of its
#: LINE_WINDOW neighbours (a region, an amplifier's strip), where a narrower group of lines stands out of it as
#: outlier lines (column defects)
MAX_FOUND_SPLITS = 7
MIN_SEGMENT_SHARE = MAX_DEFECT_FRACTION


def _best_split(rc: np.ndarray, sc: np.ndarray, wc: np.ndarray, fixed: list[int], lo: int,
                gap: int | None = None) -> int | None:
    """The boundary (index of the first line after it) that, added to ``fixed``, most lowers the weighted
    least-squares misfit of a piecewise-constant ratio ``rc / sc`` (line sums of the residual and of the
    signal, weights ``wc`` = sc^2 / var): binary segmentation (Scott & Knott 1974). Each segment [a, b)
    explains ``(sum sc rc wc)^2 / sum sc^2 wc`` of the misfit; a new boundary j changes only the segment that
    holds it, so every j is scored at once from prefix sums. None when no boundary at least ``lo`` lines from
    the edges and ``gap`` (default ``lo``) from ``fixed`` explains anything."""
    gap = lo if gap is None else gap
    n = rc.size
    ss = np.concatenate([[0.0], np.cumsum(sc * sc * wc)])
    sr = np.concatenate([[0.0], np.cumsum(sc * rc * wc)])

    def explained(a, b):
        s2, s1 = ss[b] - ss[a], sr[b] - sr[a]
        return np.where(s2 > 0, s1 * s1 / np.where(s2 > 0, s2, 1.0), 0.0)

    j = np.arange(lo, n - lo + 1)
    if fixed:
        j = j[np.min(np.abs(j[:, None] - np.asarray(fixed)[None, :]), axis=1) >= gap]
    if j.size == 0:
        return None
    cuts = np.asarray(sorted([0, n, *fixed]))
    seg = np.searchsorted(cuts, j, side="right") - 1  # the segment [cuts[seg], cuts[seg + 1]) that holds j
    a, b = cuts[seg], cuts[seg + 1]
    gain = explained(a, j) + explained(j, b) - explained(a, b)
    k = int(np.argmax(gain))
    return int(j[k]) if gain[k] > 0 else None


def _gain_split_variants(res, sig: np.ndarray):
    """Gain regions whose boundaries are not the sensor's equal segments: a sensor read by amplifiers over
    unequal parts, or a window that sees one boundary at its own place. The boundaries along each axis are
    found from the data (binary segmentation of the residual's line sums over the signal's, up to
    :data:`MAX_FOUND_SPLITS`), each counted as one parameter in the BIC; the gains are then fitted as for the
    sensor's grid."""
    if res.flat()[0].size == 0:
        return
    for axis in ("x", "y"):
        n = res.data_adu.shape[1 if axis == "x" else 0]
        lo = max(int(np.ceil(MIN_SEGMENT_SHARE * n)), 2)
        if n < 2 * lo:
            continue
        rc, sc, wc = _line_profile(res, sig, axis)
        cuts: list[int] = []
        for _ in range(MAX_FOUND_SPLITS):
            j = _best_split(rc, sc, wc, cuts, lo, min(lo, LINE_WINDOW))
            if j is None:
                break
            cuts = sorted([*cuts, j])
            centres = res.xs if axis == "x" else res.ys
            bounds = [float(0.5 * (centres[c - 1] + centres[c])) for c in cuts]
            yield _split_variant(res, sig, axis, bounds)


def _line_profile(res, sig: np.ndarray, axis: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(residual, signal, weight) per column (``axis`` "x") or row of the fitted pixels: the line sums of the
    residual [ADU] and of the signal ``sig`` [ADU], and the inverse of the line's summed variance [ADU^-2]."""
    idx, r, w = res.flat()
    h, wd = res.data_adu.shape
    y, x = np.divmod(idx, wd)
    pos, n = (x, wd) if axis == "x" else (y, h)
    rc = np.bincount(pos, r, n)
    sc = np.bincount(pos, sig.ravel()[idx].astype(np.float64), n)
    vc = np.bincount(pos, 1.0 / w, n)
    return rc, sc, np.where(vc > 0, 1.0 / np.maximum(vc, 1e-30), 0.0)


def _gain_check(fit, res) -> str:
    """Read-out regions change the gain in steps where their amplifiers meet: along each axis the regions
    divide, the steps (one gain per region, and each boundary found from the data a parameter too) must
    describe the residual's line profile (line sums of the residual against the signal's, weighted by their
    variance) unless a smooth curve of the line's position with as many parameters (a Legendre series) does
    better by more than DETECTION_SIGMA^2 in chi2 and the steps, added to that curve, remove less than
    DETECTION_SIGMA^2 more (no discontinuity at the detection bar). A smooth or periodic response (vignetting,
    a flat-field pattern, tree rings of the silicon) is fitted by a staircase of many narrow strips, better by
    a curve, and the steps add nothing to it; a step with wide transitions and a drift, which a staircase of
    many boundaries fits, keeps its discontinuity on top of any curve; where the two describe the profile alike
    (a weak step) at the sensor's own region boundaries, both stay and the judge says it cannot tell them apart.
    A boundary found from the data (``splits_x`` / ``splits_y``) is a claim of a discontinuity where the sensor's
    layout puts none, so a tie goes to the description: its steps must describe the profile better than the curve
    or add DETECTION_SIGMA^2 to it (a staircase of three close boundaries fits a weak PRNU's large scales about as
    well as the curve does, and adds nothing to it; a weak single step beats the curve)."""
    p = fit.params
    s = res.sensor
    if not p or res.flat()[0].size == 0:
        return ""
    sig = _gain_signal(res)
    iy, ix = region_index(res.ys, res.xs, p["nx"], p["ny"], s.sensor_height_px, s.sensor_width_px,
                          p.get("splits_y"), p.get("splits_x"))
    fitted = _fitted_regions(res, sig, iy, ix, p["nx"])
    law = _gain_law(*fitted) or _gain_noise(*fitted, p["gains"])
    if law:
        return law
    for axis, line_region, found in (("x", ix, p.get("splits_x") or []), ("y", iy, p.get("splits_y") or [])):
        regions = np.unique(line_region)
        if regions.size < 2:
            continue
        rc, sc, wc = _line_profile(res, sig, axis)
        ok = (wc > 0) & (sc != 0)
        k = regions.size + len(found)
        if ok.sum() <= 2 * k:
            continue
        sw = np.sqrt(wc[ok])

        def misfit(a):
            return float(np.sum(np.square(_line_fit_residual(a, rc[ok], sw))))

        centres = (res.xs if axis == "x" else res.ys)[ok]
        u = 2.0 * (centres - centres.min()) / max(float(np.ptp(centres)), 1e-9) - 1.0
        curve = sc[ok][:, None] * np.polynomial.legendre.legvander(u, k - 1)
        stepped = sc[ok][:, None] * (line_region[ok][:, None] == regions[None, :])
        steps, smooth = misfit(stepped), misfit(curve)
        added = smooth - misfit(np.hstack([curve, stepped[:, 1:]]))  # what the steps add to the curve
        if added >= DETECTION_SIGMA ** 2:
            continue
        if found and steps >= smooth and transitions_beat_curve(rc[ok], sc[ok], wc[ok], centres, found):
            continue  # a staircase following wide transitions (ramps of tens of lines), not a smooth response
        if found and steps >= smooth:
            return (f"along {axis} the steps at {len(found)} boundary(ies) found from the data describe the signal's "
                    f"profile no better than a smooth curve of the line's position with as many parameters ({k}; chi2 "
                    f"{steps:.4g} against {smooth:.4g} of the line sums) and add {added:.3g} to it, less than "
                    f"{DETECTION_SIGMA:g}^2: no discontinuity the data show where the sensor's layout puts none; a "
                    "smooth response (vignetting, a flat-field pattern) described by a staircase, not read-out regions")
        if steps - smooth > DETECTION_SIGMA ** 2:
            return (f"along {axis} a smooth curve of the line's position with as many parameters ({k}) describes the "
                    f"signal's profile better than the steps between the {regions.size} regions (chi2 "
                    f"{smooth:.4g} against {steps:.4g} of the line sums), and the steps add {added:.3g} to it, less "
                    f"than {DETECTION_SIGMA:g}^2: a smooth or periodic response (vignetting, a flat-field pattern), "
                    "not read-out regions, whose gains change in steps")
    return ""


def _line_fit_residual(a: np.ndarray, rc: np.ndarray, sw: np.ndarray) -> np.ndarray:
    """The weighted residual ``sw (rc - a coef)`` of line sums ``rc`` (weights ``sw^2``) after the least-squares
    fit of the templates ``a`` (one per column): its square summed is the fit's chi2."""
    coef = np.linalg.lstsq(a * sw[:, None], rc * sw, rcond=None)[0]
    return sw * (rc - a @ coef)


#: transitions of read-out regions are at least this many ramp widths apart: halfway between two, each tanh ramp
#: has settled to within 1 - tanh(2) = 3.6 % of its step, a plateau. A smooth or periodic response drawn as ramps
#: (a sinusoid, a bump) needs ramps as wide as a third of their spacing or more. From the profile's ends a ramp is
#: one width at least (its centre and most of it on the frame: the plateau beyond may lie outside the window)
TRANSITION_PLATEAU_WIDTHS = 4.0


def transitions_beat_curve(rc: np.ndarray, sc: np.ndarray, wc: np.ndarray, centres: np.ndarray,
                           found: list) -> bool:
    """Whether boundaries ``found`` from the data, read as a few localised transitions of one common width between
    plateaus (a gain that settles over some lines: a tanh ramp), describe a line profile better than a smooth curve
    of the line's position with as many parameters.

    ``rc``: the line sums of the residual [ADU], ``sc``: of the signal [ADU], ``wc``: their inverse variances,
    ``centres``: the lines' positions [px], ``found``: the boundaries [px, the same coordinates]. A staircase of
    close boundaries is how the segmentation follows one wide transition, and the curve it is weighed against then
    has the staircase's many parameters and follows it too. Grouped into ``m`` transitions (split at the ``m - 1``
    widest gaps between the found boundaries, m = 1 ... the number found), the transition model has m + 1 gains, m
    positions and a width, and the Legendre curve as many terms (2 m + 2). The ramps must leave plateaus
    (TRANSITION_PLATEAU_WIDTHS widths apart, a width from the ends: read-out regions have a gain each), describe the
    profile (a chi2 within DETECTION_SIGMA standard deviations, sqrt(2 dof), of its dof) and beat the curve
    by DETECTION_SIGMA^2 plus 2 ln of the groupings tried (the best of n tries gains ~2 ln n by chance, as a BIC
    counts a choice). A smooth response (vignetting, a flat-field pattern) has no localised transition: a curve of
    as many parameters describes it as well, or ramps follow it only as wide as their spacing."""
    from scipy.optimize import least_squares

    f = np.sort(np.asarray(found, np.float64))
    if f.size == 0 or centres.size < 2:
        return False
    sw = np.sqrt(wc)
    lo, hi = float(centres.min()), float(centres.max())
    u = 2.0 * (centres - lo) / max(hi - lo, 1e-9) - 1.0
    spacing = float(np.median(np.diff(np.sort(centres))))
    bar = DETECTION_SIGMA ** 2 + 2.0 * np.log(f.size)

    def width_of(p: np.ndarray) -> float:  # p = (positions, ln width)
        return float(np.exp(np.clip(p[-1], -10.0, 10.0)))

    def ramps(p: np.ndarray) -> np.ndarray:  # one gain per plateau, times the signal
        return sc[:, None] * np.column_stack([np.ones_like(centres)]
                                             + [0.5 * (1.0 + np.tanh((centres - b) / width_of(p))) for b in p[:-1]])

    widest = np.argsort(np.diff(f))[::-1]
    for m in range(1, f.size + 1):
        k = 2 * m + 2
        if rc.size <= 2 * k:
            break
        groups = np.split(f, np.sort(widest[: m - 1] + 1))
        width0 = max(spacing, float(np.mean([np.ptp(g) for g in groups])) / 2.0)
        p0 = np.r_[[g.mean() for g in groups], np.log(width0)]
        got = least_squares(lambda p: _line_fit_residual(ramps(p), rc, sw), p0)
        if not np.all(np.isfinite(got.x)):
            continue
        pos, width = np.sort(got.x[:-1]), width_of(got.x)
        if pos[0] - lo < width or hi - pos[-1] < width or np.any(np.diff(pos) < TRANSITION_PLATEAU_WIDTHS * width):
            continue  # no plateau between the ramps: a smooth or periodic change, not regions' gains
        dof = rc.size - k
        if 2.0 * float(got.cost) > dof + DETECTION_SIGMA * np.sqrt(2.0 * dof):
            continue  # the ramps do not describe the profile (its chi2 beyond its noise): better than a curve is moot
        curve = float(np.sum(np.square(_line_fit_residual(sc[:, None] * np.polynomial.legendre.legvander(u, k - 1),
                                                           rc, sw))))
        if curve - 2.0 * float(got.cost) >= bar:
            return True
    return False


def _fitted_regions(res, sig: np.ndarray, iy: np.ndarray, ix: np.ndarray, nx: int):
    """(region, signal [ADU], residual, weight) of each fitted pixel: the region from the row and column region
    indices ``iy`` / ``ix`` (``nx`` column regions), the signal an amplifier read from ``sig``."""
    idx, r, w = res.flat()
    y, x = np.divmod(idx, res.data_adu.shape[1])
    return iy[y] * nx + ix[x], sig.ravel()[idx].astype(np.float64), r, w


def _gain_law(reg: np.ndarray, sv: np.ndarray, r: np.ndarray, w: np.ndarray) -> str:
    """A gain multiplies the signal: within each region the residual follows the signal its amplifier read
    (``sv``; the stars as the sky), so one factor per region must take more chi2 from the fitted pixels than one
    offset per region (as many parameters). Where the offsets take more by DETECTION_SIGMA^2, the steps are light
    or an offset added in strips (a satellite trail along the rows, a bias offset per amplifier), not gains. On a
    uniform light (a flat, a sky without sources) the two are one template and nothing is refused. "" or why."""
    n = int(reg.max()) + 1

    def taken(t):  # sum over the regions of the chi2 one coefficient of template t takes: (sum w t r)^2 / sum w t^2
        num, den = np.bincount(reg, w * t * r, n), np.bincount(reg, w * t * t, n)
        return float(np.sum(np.where(den > 0, num * num / np.where(den > 0, den, 1.0), 0.0)))

    mul, add = taken(sv), taken(np.ones_like(sv))
    if add - mul <= DETECTION_SIGMA ** 2:
        return ""
    return (f"the steps do not scale with the signal: one offset per region takes {add:.4g} of the chi2, one gain "
            f"per region {mul:.4g}, less by more than {DETECTION_SIGMA:g}^2: light or an offset added in strips (a "
            "trail along the lines, a bias offset per amplifier), not gains, which multiply the sources as the sky")


#: the fewest pixels a region's variance ratio is read from [pixels]: the median of fewer scatters by more than
#: 2.33 / sqrt(64) = 29 % of itself (:func:`detector.stats.median_square_variance_error`), which dwarfs the few per
#: cent a gain's g^2 changes it by, and the asymptotic error of a sample median is no longer its error
GAIN_NOISE_MIN_PIXELS = 64


def _gain_noise(reg: np.ndarray, sv: np.ndarray, r: np.ndarray, w: np.ndarray, gains) -> str:
    """An amplifier's gain converts everything it reads, the noise with the signal (the plugin multiplies the frame
    in ADU, read and shot noise included): the pixels' variance in region k is g_k^2 times the model's. Each
    region's variance ratio (the median of w r^2 over its pixels, less its own gain template, over the median of a
    chi2_1 variable: robust to hot pixels and cosmic rays) is fitted by one common scale times g_k^2 and by one
    common scale alone. Where the constant fits better by more than DETECTION_SIGMA^2, the noise refutes the
    gains: steps of a level of the signal (an offset in strips, a dark or bias pattern), read by one gain. A
    weak true gain step changes the variance too little to tell, and nothing is refused. "" or why."""
    g = np.asarray(gains, np.float64).ravel()
    n = g.size
    num, den = np.bincount(reg, w * sv * r, n), np.bincount(reg, w * sv * sv, n)
    a = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
    q = w * (r - a[reg] * sv) ** 2
    ratio, se = np.zeros(n), np.zeros(n)
    for k in range(n):
        qk = q[reg == k]
        if qk.size >= GAIN_NOISE_MIN_PIXELS:
            ratio[k] = float(np.median(qk)) / CHI2_1_MEDIAN
            se[k] = median_square_variance_error(ratio[k], qk.size)
    ok = se > 0
    if ok.sum() < 2:
        return ""
    wt = 1.0 / se[ok] ** 2
    v, t = ratio[ok], g[ok] ** 2

    def misfit(tpl):
        c = float(np.sum(wt * tpl * v) / np.sum(wt * tpl * tpl))
        return float(np.sum(wt * (v - c * tpl) ** 2))

    by_gain, level = misfit(t), misfit(np.ones_like(t))
    if by_gain - level <= DETECTION_SIGMA ** 2:
        return ""
    return (f"the noise does not follow the gains: an amplifier's gain scales the variance it reads by g^2 "
            f"({t.min() / t.max():.3g} between the regions for gains {g.min():.4g} to {g.max():.4g}), the pixels' "
            f"variance ratios are {', '.join(f'{u:.3f}' for u in v)} (chi2 {by_gain:.3g} by the gains against "
            f"{level:.3g} by one level, more by {DETECTION_SIGMA:g}^2): steps of a level of the signal, not gains")


def _split_variant(res, sig: np.ndarray, axis: str, bounds: list[float]) -> Variant:
    h, wd = res.data_adu.shape
    line = np.searchsorted(np.asarray(bounds), res.xs if axis == "x" else res.ys, side="right")  # region per line
    k = np.broadcast_to(line[None, :] if axis == "x" else line[:, None], (h, wd))
    n_reg = len(bounds) + 1
    present = np.arange(n_reg)

    def at(idx):
        yy, xx = np.divmod(idx, wd)
        kk = k[yy, xx]
        sv = sig.ravel()[idx].astype(np.float64)
        return np.stack([np.where(kk == j, sv, 0.0) for j in present])

    def maps():
        return [np.where(k == j, sig, np.float32(0)) for j in present]

    npx = np.bincount(line, minlength=n_reg).astype(float) * (h if axis == "x" else wd)  # pixels per region

    def to_params(c):
        g = 1.0 + np.asarray(c, float)
        g = g / (np.dot(g, npx) / npx.sum())
        if not (g > 0).all():
            return None
        out = {"nx": n_reg if axis == "x" else 1, "ny": n_reg if axis == "y" else 1,
               "gains": [round(float(v), 6) for v in g]}
        out["splits_x" if axis == "x" else "splits_y"] = [round(b, 2) for b in bounds]
        return out

    return Variant(maps, to_params, f"{len(bounds)} boundary(ies) along {axis} found at "
                   f"{', '.join(f'{b:.0f}' for b in bounds)} px", at=at, extra_k=len(bounds))


def _gain_words(p, res) -> str:
    g = np.asarray(p["gains"])
    return (f"steps of the signal between {p['ny']}x{p['nx']} read-out regions, gains {g.min():.4g} to "
            f"{g.max():.4g}: amplifier gain regions")


def _nonlin_variants(res):
    """One- and two-parameter response curves, the best kept (BIC): the quadratic deficit (a response falling
    linearly with the signal: most of the change near full well), the cubic one (a response falling as the
    square of the signal: a soft saturation, flat up to a good part of the well), both together, and the
    power law (a deviation growing with ln S: as much per decade of faint as of bright signal). Their
    derivatives at zero strength are the templates [ADU per unit coefficient]: ``-S^2 / FW / g``,
    ``-S^3 / FW^2 / g`` and ``S ln(S / S_ref) / g``."""
    fw = res.sensor.full_well_e * res.pixel_sum
    q = res.charge_e.astype(np.float64)
    t = (-(q ** 2) / fw / res.gain).astype(np.float32)
    t2 = (-(q ** 3) / fw ** 2 / res.gain).astype(np.float32)

    def ok(b):
        return -0.5 <= b <= 0.5

    def to_params(c):
        return {"beta": round(float(c[0]), 6)} if ok(c[0]) and c[0] != 0 else None

    yield Variant([t], to_params, label="quadratic")

    def to_cubic(c):
        return {"beta": 0.0, "beta2": round(float(c[0]), 6)} if ok(c[0]) and c[0] != 0 else None

    yield Variant([t2], to_cubic, label="cubic")

    def to_both(c):
        b1, b2 = float(c[0]), float(c[1])
        return {"beta": round(b1, 6), "beta2": round(b2, 6)} if ok(b1) and ok(b2) and ok(b1 + b2) and \
            (b1 or b2) else None

    yield Variant([t, t2], to_both, label="quadratic and cubic")
    # a knee: the slope changes at one signal (its position searched over KNEE_FRACTIONS: one more parameter);
    # the template is -max(S - K, 0) / g, the response's change per unit of the slope's deficit above K
    for kf in KNEE_FRACTIONS:
        hinge = (-np.maximum(q - kf * fw, 0.0) / res.gain).astype(np.float32)
        if not np.any(hinge[np.broadcast_to(res.fit, hinge.shape)]):
            continue

        def to_knee(c, kf=kf):
            d = float(c[0])
            return {"beta": 0.0, "knee": kf, "knee_deficit": round(d, 6)} if -0.9 <= d <= 0.9 and d != 0 else None

        yield Variant([hinge], to_knee, label=f"knee at {kf:g} of the full well", extra_k=1)
    pos = q > 0
    # the law is referenced at the frame's own median signal (it equals the linear response there): what the
    # frame measures is how the response changes across its signal, not its level at half the well, which a
    # frame of a few per cent of the well would only extrapolate (a real SBIG dark's gamma 1.027 from 67 e-,
    # referenced at half its 133 000 e- well, lowered the whole dark by 16 % when rendered)
    ref_frac = frame_reference_fraction(res)
    if ref_frac is None:
        return
    ref = ref_frac * fw
    t = np.zeros_like(q)
    t[pos] = q[pos] * np.log(q[pos] / ref) / res.gain

    def to_power(c):
        return {"beta": 0.0, "gamma": round(1.0 + float(c[0]), 6), "gamma_reference": float(f"{ref_frac:.6g}")} \
            if 0 < abs(c[0]) <= 0.5 else None

    yield Variant([t.astype(np.float32)], to_power, label="power law")


def frame_reference_fraction(res) -> float | None:
    """The frame's median signal per sensor pixel [fraction of the full well] over its fitted pixels with a
    positive charge: where the diagnosis references a power-law response (None: no charge)."""
    q = np.asarray(res.charge_e, np.float64)
    ok = np.broadcast_to(res.fit, q.shape) & (q > 0)
    if not ok.any():
        return None
    return float(np.median(q[ok])) / (res.sensor.full_well_e * res.pixel_sum)


def _nonlin_words(p, res) -> str:
    if p.get("knee_deficit"):
        d = p["knee_deficit"]
        return (f"response linear up to {p['knee']:.2g} of the full well, its slope {'lower' if d > 0 else 'higher'} "
                f"by {100 * abs(d):.2g} % above it ({100 * d * (1 - p['knee']):.2g} % "
                f"{'deficit' if d > 0 else 'excess'} at full well): nonlinearity (a knee)")
    if p.get("gamma", 1.0) != 1.0:
        g = p["gamma"]
        ref = p.get("gamma_reference", POWER_LAW_REFERENCE)
        return (f"response following a power law of the signal, gamma {g:.4g} ({'compressive' if g < 1 else 'expansive'}"
                f": {100 * abs(g - 1) * np.log(10):.2g} % per decade of signal, equal to the linear one at "
                f"{ref:.3g} of the full well): nonlinearity")
    b1, b2 = p.get("beta", 0.0), p.get("beta2", 0.0)
    total = b1 + b2
    law = ("growing as the square of the signal" if not b2 else "growing as the cube of the signal (a soft "
           "saturation)" if not b1 else f"of a quadratic ({100 * b1:.2g} %) and a cubic ({100 * b2:.2g} %) term")
    return (f"response {'deficit' if total > 0 else 'excess'} {law}, {100 * abs(total):.2g} % at full well: "
            "nonlinearity")

def _prnu_words(p, res) -> str:
    lines = [f"{what} gains of {100 * p[key]:.2g} % rms" for key, what in (("column_sigma", "column"),
                                                                         ("row_sigma", "row")) if p.get(key)]
    return (f"pixel-to-pixel scatter proportional to the signal, {100 * p['sigma']:.2g} % of it"
            + (f", with {' and '.join(lines)} (line-wise response: column amplifiers, row drivers)" if lines else "")
            + (f", with a low-frequency pattern of {100 * p['smooth_rms']:.2g} % rms (a flat-field map the white "
               "prnu model does not carry)" if "smooth_rms" in p else "")
            + ": photo-response non-uniformity (PRNU)")


_PRNU_SIGNATURE = VarianceSignature(
    _prnu_template, _prnu_params, _prnu_words,
    pattern="extra variance growing as the square of the photo-signal (and its large-scale pattern), with "
            "column and row gains",
    smooth=lambda res: res.photo_adu, lines=True, line_template=lambda res: res.photo_adu)

_DSNU_SIGNATURE = VarianceSignature(
    _dsnu_template, _dsnu_params,
    lambda p, res: (f"pixel-to-pixel scatter proportional to the dark signal, {100 * p['sigma']:.2g} % of it, "
                    f"{'skewed (lognormal)' if p['law'] == 'lognormal' else 'symmetric'}"
                    + (f", with a low-frequency pattern of {100 * p['smooth_rms']:.2g} % rms" if "smooth_rms" in p
                       else "") + ": dark-signal non-uniformity (DSNU)"),
    pattern="extra variance growing as the square of the dark signal, skewed",
    laws={"lognormal": _dsnu_lognormal_k3, "normal": None},
    smooth=lambda res: (res.dark_e / np.float32(res.gain)).astype(np.float32), lines=True, check=_dsnu_check)

_DEADPIXELS_SIGNATURE = GroupSignature(
    _dead_groups, _dead_words, pattern="pixels or small clusters far below their neighbours where light falls",
    check=spread_check("neg"))

_GAINREGIONS_SIGNATURE = LinearSignature(_gain_variants, _gain_words, pattern="signal steps between sensor regions",
                                         check=_gain_check)

_NONLINEARITY_SIGNATURE = LinearSignature(
    _nonlin_variants, _nonlin_words,
    pattern="residual proportional to the square of the collected charge (or to S ln S)", extra_k=0)


# --- adapters -----------------------------------------------------------------------------------------------

class PRNUParams(EffectParams):
    sigma: float = Field(0.01, ge=0, le=0.5, description="spatial std of the response, fraction of the mean [1]",
                         json_schema_extra={"unit": "1"})
    column_sigma: float = Field(0.0, ge=0, le=0.5, description="std of the columns' gains (one per column: a CMOS "
                                "sensor's column amplifiers), fraction of the mean [1]", json_schema_extra={"unit": "1"})
    row_sigma: float = Field(0.0, ge=0, le=0.5, description="std of the rows' gains (one per row), fraction of the "
                             "mean [1]", json_schema_extra={"unit": "1"})


@register_effect
class PRNU(Effect):
    """Photo-response non-uniformity: each pixel's sensitivity is 1 + sigma N(0,1), mean 1, times its column's
    gain 1 + column_sigma N(0,1) and its row's 1 + row_sigma N(0,1) (the pixel, column and row parts of a
    response's fixed pattern, EMVA 1288 Release 4.0 sect. 8.2; a CMOS sensor's column amplifiers, Janesick 2007
    ch. 8).

    Multiplies the expected photo-electrons before the shot-noise draw (EMVA 1288 eq. 4.3; Janesick 2007
    ch. 8). Fixed pattern: drawn from the hardware seed, the same every frame.
    """

    name = "prnu"
    scaling = "signal"
    identity = {"sigma": 0.0}
    stages = (Stage.RESPONSE,)
    Params = PRNUParams
    pattern = True
    signature = _PRNU_SIGNATURE

    def variance_e2(self, stage: Stage, tile: Tile, mean_e: np.ndarray) -> np.ndarray:
        p = self.params
        return (np.float32(np.sqrt(p.sigma ** 2 + p.column_sigma ** 2 + p.row_sigma ** 2)) * mean_e) ** 2

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        if self.params.sigma:
            data *= tile.hardware_map(self.name, lambda rng, shape: prnu_map(rng, shape, self.params.sigma))
        s = self.sensor
        if self.params.column_sigma:  # one gain per sensor column, the same for every tile and window
            g = line_gain_vector(s.hardware_seed, "prnu_columns", s.sensor_width_px, self.params.column_sigma)
            data *= g[tile.x0:tile.x1][None, :]
        if self.params.row_sigma:
            g = line_gain_vector(s.hardware_seed, "prnu_rows", s.sensor_height_px, self.params.row_sigma)
            data *= g[tile.y0:tile.y1][:, None]


def line_gain_vector(seed: int, name: str, n: int, sigma: float) -> np.ndarray:
    """The gains ``1 + sigma N(0, 1)`` (at least 0) of ``n`` sensor lines, drawn from the hardware seed."""
    from ..rng import generator

    return np.maximum(1.0 + sigma * generator(seed, name).standard_normal(n), 0.0).astype(np.float32)


class DSNUParams(EffectParams):
    sigma: float = Field(0.3, ge=0, le=5, description="spatial std of the dark current, fraction of its mean [1]",
                         json_schema_extra={"unit": "1"})
    law: Literal["lognormal", "normal"] = "lognormal"


@register_effect
class DSNU(Effect):
    """Dark-signal non-uniformity: each pixel's dark current is I_d m, m of mean 1 and std sigma.

    Adds ``I_d t (m - 1)`` electrons to the mean before the shot-noise draw, so the mean dark current of
    the frame stays the sensor's (EMVA 1288 sec. 4.3, DSNU; Janesick 2007 ch. 7). Hardware seed.
    """

    name = "dsnu"
    scaling = "exposure"
    identity = {"sigma": 0.0}
    stages = (Stage.DARK,)
    Params = DSNUParams
    pattern = True
    signature = _DSNU_SIGNATURE

    def variance_e2(self, stage: Stage, tile: Tile, mean_e: np.ndarray) -> np.ndarray:
        return (np.float32(self.params.sigma) * mean_e) ** 2

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        dark_e = self.sensor.dark_current_e_per_s * tile.exptime_s
        if self.params.sigma and dark_e:
            m = tile.hardware_map(self.name, lambda rng, shape: dsnu_map(rng, shape, self.params.sigma, self.params.law))
            excess = m - np.float32(1.0)  # one temporary: the same values as (m - 1) * dark_e
            excess *= np.float32(dark_e)
            data += excess


class DeadParams(EffectParams):
    count: int = Field(100, ge=0, le=10_000_000,
                       description="dead or weak defects (single pixels or clusters) on the full sensor [defects]")
    response: float = Field(0.0, ge=0, lt=1, description="residual response of a dead pixel; with response_max, "
                            "the lower end of the defects' responses [1]")
    response_max: float | None = Field(None, gt=0, lt=1, description="upper end of the defects' responses, each "
                                       "drawn uniform in [response, response_max] (None: all at response) [1]")
    cluster_px: int = Field(1, ge=1, le=MAX_DEAD_CLUSTER_SIDE,
                            description="side of a defect's square cluster of pixels (1: isolated pixels) [pixels]")

    @model_validator(mode="after")
    def _range(self):
        if self.response_max is not None and self.response_max <= self.response:
            raise ValueError(f"response_max ({self.response_max}) must exceed response ({self.response})")
        return self


@register_effect
class DeadPixels(Effect):
    """Dead (or weak) pixels: the photo-response of ``count`` defects drops to ``response`` (0 = no signal), or
    to a response drawn uniform in [``response``, ``response_max``] per defect; a defect is one pixel or a
    ``cluster_px`` x ``cluster_px`` cluster sharing one response (sensors have both: EMVA 1288 release 4.0
    sect. 8.4 counts defect pixels on flat fields; Janesick 2007 ch. 8, "dead pixels" and their clusters).

    They still carry dark current, bias and read noise, like a real dead photodiode read by a live amplifier.
    Positions (a cluster's lowest row and column) from the hardware seed; table ``DEADPIX`` in the FITS file,
    one row per pixel.
    """

    name = "dead_pixels"
    scaling = "signal"
    identity = {"count": 0}
    stages = (Stage.RESPONSE,)
    Params = DeadParams
    pattern = True
    signature = _DEADPIXELS_SIGNATURE

    def setup(self) -> None:
        p, s = self.params, self.sensor
        ys, xs, rng = hardware_positions(s, self.name, p.count)
        resp = (np.full(ys.size, p.response) if p.response_max is None else
                rng.uniform(p.response, p.response_max, ys.size))
        c = p.cluster_px
        dy, dx = (a.ravel() for a in np.mgrid[0:c, 0:c])
        ys, xs = (ys[:, None] + dy[None, :]).ravel(), (xs[:, None] + dx[None, :]).ravel()
        resp = np.repeat(resp, c * c)
        on = (ys < s.sensor_height_px) & (xs < s.sensor_width_px)
        # one entry per pixel (clusters drawn over one another keep the first defect's response)
        _, first = np.unique(ys[on].astype(np.int64) * s.sensor_width_px + xs[on], return_index=True)
        first = np.sort(first)  # in the order drawn
        self.ys, self.xs = ys[on][first], xs[on][first]
        self.response = resp[on][first].astype(np.float32)

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        sel, r, c = in_tile(tile, self.ys, self.xs)
        data[r, c] *= self.response[sel]

    def truth(self, state=None) -> dict[str, np.ndarray]:
        m = roi_mask(self.sensor, self.ys, self.xs)
        x, y = output_xy(self.sensor, self.ys[m], self.xs[m])
        t = np.zeros(int(m.sum()), dtype=[("x", "i4"), ("y", "i4"), ("x_sensor", "i4"), ("y_sensor", "i4"),
                                            ("response", "f4")])
        t["x"], t["y"], t["x_sensor"], t["y_sensor"] = x, y, self.xs[m], self.ys[m]
        t["response"] = self.response[m]
        return {"DEADPIX": t}


class GainRegionParams(EffectParams):
    nx: int = Field(2, ge=1, le=64, description="amplifier regions across the columns [regions]")
    ny: int = Field(1, ge=1, le=64, description="amplifier regions across the rows [regions]")
    sigma: float = Field(0.01, ge=0, le=0.5, description="std of the relative gains when drawn [1]")
    gains: list[float] | None = Field(None, description="explicit relative gains, row-major, ny*nx values [1]")
    splits_x: list[float] | None = Field(None, description="boundaries between the column regions, ascending, "
                                         "nx - 1 values (default: nx equal segments) [sensor pixels]")
    splits_y: list[float] | None = Field(None, description="boundaries between the row regions, ascending, "
                                         "ny - 1 values (default: ny equal segments) [sensor pixels]")

    @model_validator(mode="after")
    def _n(self):
        for name, n in (("splits_x", self.nx), ("splits_y", self.ny)):
            v = getattr(self, name)
            if v is not None and (len(v) != n - 1 or any(b <= a for a, b in pairwise(v))):
                raise ValueError(f"{name} needs {n - 1} ascending boundaries, got {v}")
        if self.gains is not None:
            if len(self.gains) != self.nx * self.ny:
                raise ValueError(f"gains needs nx*ny = {self.nx * self.ny} values, got {len(self.gains)}")
            if any(g <= 0 for g in self.gains):
                raise ValueError("gains must be > 0")
        return self


@register_effect
class GainRegions(Effect):
    """Amplifier gain regions: the sensor is read by ``ny x nx`` amplifiers whose conversion gains differ (equal
    segments of the sensor, or those between the boundaries ``splits_x`` / ``splits_y``).

    The signal in ADU (bias excluded) of region k is multiplied by g_k, drawn as 1 + sigma N(0,1) from the
    hardware seed or given explicitly. Shows as steps between quadrants/columns in flats (Janesick 2007
    ch. 9; multi-amplifier CCD/CMOS read-out, e.g. LSST's 16 channels per CCD).
    """

    name = "gain_regions"
    field_kind = "multiplicative"
    scaling = "signal"
    identity = {"sigma": 0.0}
    stages = (Stage.ADU,)
    Params = GainRegionParams
    signature = _GAINREGIONS_SIGNATURE

    def setup(self) -> None:
        p = self.params
        if p.gains is not None:
            g = np.asarray(p.gains, dtype=np.float64)
        else:
            from ..rng import generator
            g = 1.0 + p.sigma * generator(self.sensor.hardware_seed, self.name).standard_normal(p.nx * p.ny)
        self.gains = np.maximum(g, 1e-3).reshape(p.ny, p.nx)

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        ys, xs = tile.pixel_centres()
        s, p = self.sensor, self.params
        iy, ix = region_index(ys, xs, p.nx, p.ny, s.sensor_height_px, s.sensor_width_px, p.splits_y, p.splits_x)
        # one float32 gain per block of equal (row region, column region): the same products as the gathered map
        rcut = np.r_[0, np.flatnonzero(iy[1:] != iy[:-1]) + 1, iy.size]
        ccut = np.r_[0, np.flatnonzero(ix[1:] != ix[:-1]) + 1, ix.size]
        g32 = self.gains.astype(np.float32)
        for r0, r1 in pairwise(rcut):
            for c0, c1 in pairwise(ccut):
                data[r0:r1, c0:c1] *= g32[iy[r0], ix[c0]]


class NonlinearityParams(EffectParams):
    beta: float = Field(0.02, ge=-0.5, le=0.5, description="fractional response deficit at full well growing "
                        "linearly with the signal [1]")
    beta2: float = Field(0.0, ge=-0.5, le=0.5, description="fractional response deficit at full well growing as the "
                         "square of the signal (a soft saturation) [1]")
    gamma: float = Field(1.0, ge=0.5, le=1.5, description="exponent of a power-law response, equal to the linear "
                         "one at gamma_reference of the full well (1: none) [1]")
    gamma_reference: float = Field(POWER_LAW_REFERENCE, gt=0, le=1, description="signal where the power law equals "
                                   "the linear response, fraction of the full well (the diagnosis sets the frame's "
                                   "median signal) [1]", json_schema_extra={"unit": "1"})
    knee: float = Field(1.0, gt=0, le=1, description="signal where the response's slope changes, fraction of the "
                        "full well (a piecewise-linear response; 1: no knee) [1]", json_schema_extra={"unit": "1"})
    knee_deficit: float = Field(0.0, ge=-0.9, le=0.9, description="fractional fall of the response's slope above "
                                "the knee (negative: a rise) [1]")


@register_effect
class Nonlinearity(Effect):
    """Response nonlinearity of the read-out chain: with ``knee_deficit`` the piecewise-linear response of
    :func:`knee_nonlinearity` (a knee at ``knee`` of the full well), then S' = S (1 - beta x - beta2 x^2),
    x = S / FW, then, when ``gamma`` != 1,
    the power law S'' = S' (S' / S_ref)^(gamma - 1), S_ref ``gamma_reference`` of the full well (half by default;
    the diagnosis references it at the frame's median signal; :func:`power_law_nonlinearity`).

    A pixel at full well reads ``beta`` low (beta < 0: super-linear). Applied to the collected charge after
    the full-well clip and before read noise (EMVA 1288 sec. 8.2 linearity error; Janesick 2007 ch. 11).
    """

    name = "nonlinearity"
    scaling = "signal"
    identity = {"beta": 0.0, "beta2": 0.0, "gamma": 1.0, "knee_deficit": 0.0}
    stages = (Stage.READ,)
    Params = NonlinearityParams
    signature = _NONLINEARITY_SIGNATURE

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        fw = self.sensor.full_well_e * tile.bin ** 2
        knee_nonlinearity(data, self.params.knee_deficit, self.params.knee * fw)
        quadratic_nonlinearity(data, self.params.beta, fw, self.params.beta2)
        power_law_nonlinearity(data, self.params.gamma, self.params.gamma_reference * fw)
