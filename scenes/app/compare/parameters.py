"""Is a number of the scene wrong? Parameter candidates: the scene's own keys, refitted on the measured frame.

Before "an effect is missing" the judge asks whether a number the scene states is off. The comparison
already refits the global levels a model only knows to a few per cent (:meth:`Residuals.levels
<detector.signatures.Residuals.levels>`: the whole light, the background's light, a bias offset, the dark
level); a level far from its scene value is not a nuisance to absorb silently but a finding, reported as a
candidate of kind ``parameter`` that names the scene key it changes and its new value, and written by
``--apply``:

* the sources' zero point ``sky.source_flux_scale`` (the whole light's level: the sources scale with it,
  the background with it and its own level), the sky ``sky.background_mag_arcsec2``, a flat screen's
  ``sky.flat_e_per_s``;
* the bias ``detector.bias_adu`` and the dark current ``detector.dark_current_e_per_s``;
* the PSF's width ``psf.fwhm_arcsec`` (narrower as well as wider) and a Moffat PSF's ``psf.beta``: the
  scene re-rendered at a few values and the best value interpolated (:func:`psf_candidates`).

The evidence of a level is its likelihood-ratio statistic: the chi2 the frame loses when that level is held
at the scene's value, the others refitted, ``coef^2 / var(coef)`` (weighted least squares); its delta BIC
charges one parameter. A parameter is a finding only beyond the policy's physical tolerance (gate
``tolerance``): a lamp or a transparency known to a few per cent is not an error of the scene.
"""

from __future__ import annotations

import time

import numpy as np

from detector.signatures import Fit, Residuals, frame_at, pixel_score
from detector.significance import DETECTION_SIGMA, FOOTPRINT_SIGMA, MIN_TEST_PIXELS

from .apply import bias_per_output_adu
from .candidates import away_from_saturation, grows_with_flux
from .judge import Candidate
from .policy import DEFAULT_POLICY, DiagnosisPolicy

#: fractional steps of the PSF's width tried first (the best is then interpolated and refined once)
PSF_STEPS = (0.8, 0.9, 1.1, 1.25)


def level_fit(res: Residuals, delta_adu=None) -> dict[str, tuple[float, float]]:
    """{level name: (coefficient, its chi2 statistic coef^2 / var(coef))} of the global levels: as the
    comparison fitted them, or refitted once ``delta_adu`` (a candidate's mean change [ADU]) is in the model
    (weighted least squares on the comparison's weights; the same normal matrix either way)."""
    lv = res.levels()
    if not lv["keep"]:
        return {}
    idx, r, _ = res.flat()
    n = res.level_values(idx)
    nw = n * lv["w"]
    try:
        cov = np.linalg.inv(nw @ n.T)
    except np.linalg.LinAlgError:
        return {}
    coef = lv["coef"] if delta_adu is None else cov @ (nw @ (r - frame_at(delta_adu, idx)))
    return {name: (float(c), float(c * c / cov[i, i]) if cov[i, i] > 0 else 0.0)
            for i, (name, c) in enumerate(zip(lv["names"], coef))}


#: how far beyond a source's footprint (its model light above 3 sigma of the noise) its whole light is summed
#: [output pixels], the widest first: a blur's far wings hold light tens of pixels out
ENCLOSED_GROW_PX = (16, 8, 4)
#: the ring beyond that aperture whose median residual is the local background: from this far out, this wide [px]
RING_GAP_PX, RING_WIDTH_PX = 2, 6
#: the fewest fitted pixels of that ring (MIN_TEST_PIXELS), and the largest share of the frame the apertures may
#: cover (beyond, the next narrower aperture is taken)
RING_MIN_PIXELS = MIN_TEST_PIXELS
APERTURE_MAX_SHARE = 0.5
#: standard errors by which the enclosed light's ratio must differ from the zero point's for the test to speak
ENCLOSED_SIGMA = DETECTION_SIGMA


def enclosed_ratio(res: Residuals) -> tuple[float, float, int] | None:
    """(data over model, its standard error, the aperture's growth [px]) of the sources' whole light: summed
    over every unsaturated source's footprint grown by the widest of ENCLOSED_GROW_PX that fits (its ring has
    RING_MIN_PIXELS fitted pixels, the apertures cover at most APERTURE_MAX_SHARE of the frame), with the
    median residual of the ring beyond it as the local background (aperture photometry with a background
    annulus; the model at the scene's levels). None: no source, or no aperture that fits."""
    from scipy import ndimage

    source = res.model_adu - res.without_sources_adu
    core = source > FOOTPRINT_SIGMA * np.sqrt(np.maximum(res.var_adu2, 1e-12))
    if not core.any():
        return None
    saturated = res.saturated
    r = (res.data_adu - res.model_adu).astype(np.float64)
    box = np.ones((3, 3), bool)
    for grow in ENCLOSED_GROW_PX:
        ap = ndimage.binary_dilation(core, box, iterations=grow)
        if saturated.any():  # every source whose aperture holds a saturated pixel is left out, its ring too
            lab, n = ndimage.label(ndimage.binary_dilation(ap, box, iterations=RING_GAP_PX + RING_WIDTH_PX), box)
            bad = np.unique(lab[saturated & (lab > 0)])
            drop = np.isin(lab, bad[bad > 0])
        else:
            drop = np.zeros_like(ap)
        inner = ndimage.binary_dilation(ap, box, iterations=RING_GAP_PX)
        ring = ndimage.binary_dilation(inner, box, iterations=RING_WIDTH_PX) & ~inner & res.fit & ~drop
        use = ap & res.fit & ~drop
        if ring.sum() < RING_MIN_PIXELS or ap.mean() > APERTURE_MAX_SHARE or not use.any():
            continue
        b = float(np.median(r[ring]))
        total = float(np.sum(source[use], dtype=np.float64))
        if total <= 0:
            return None
        n_ap = int(use.sum())
        # the ring median's error: 1.25 x the mean's (Gaussian), per pixel of the ring
        var_b = (1.2533 ** 2) * float(np.mean(res.var_adu2[ring])) / ring.sum()
        err = float(np.sqrt(np.sum(res.var_adu2[use], dtype=np.float64) + n_ap ** 2 * var_b)) / total
        return 1.0 + float(np.sum(r[use] - b)) / total, err, grow
    return None


def light_moved(res: Residuals, f: float, policy: DiagnosisPolicy) -> str:
    """"" or why a zero point ``f`` (the sources x f, fitted where their light is: their cores) is not a finding:
    a zero point scales a source's whole light, a wider PSF or a blur with far wings moves it out of the core
    and keeps it. When the sources' whole light (:func:`enclosed_ratio`) is within the policy's scale tolerance
    of the scene's and ENCLOSED_SIGMA standard errors from x f, the light is moved, not missing (gate
    ``tolerance``: the zero point agrees with the scene's)."""
    got = enclosed_ratio(res)
    if got is None:
        return ""
    ratio, err, grow = got
    tol = policy.parameter_scale_tolerance
    if abs(ratio - 1) <= tol and abs(ratio - f) > ENCLOSED_SIGMA * err:
        return (f"the sources' whole light (within {grow} px of each, local background from a ring beyond) is x "
                f"{ratio:.4g} +- {err:.2g} the scene's, within the {100 * tol:g} % a scene may be off: the x {f:.4g} "
                "of their cores is light moved out of them (a PSF change), not a zero point")
    return ""


def _param_candidate(res: Residuals, name: str, key: str, value: float, stat: float, explanation: str,
                     within: str, policy: DiagnosisPolicy, seconds: float, level: str = "") -> Candidate:
    n = max(res.n_fit, 2)
    fit = Fit(name, {"key": key, "value": value}, -stat, 1, n, explanation, state={"level": level})
    chi2 = float(res.chi2_profiled() / max(res.n_fit, 1))
    c = Candidate(fit, chi2, seconds, kind="parameter", key=key, value=value, policy=policy)
    if within:
        c.codes["tolerance"] = within
    return c


def level_candidates(res: Residuals, scene, policy: DiagnosisPolicy = DEFAULT_POLICY) -> list[Candidate]:
    """The global levels as parameter candidates (module docstring): one per level the frame measures."""
    t0 = time.perf_counter()
    stats = level_fit(res)
    if not stats:
        return []
    sensor = scene.sensor()
    out = []
    tol = policy.parameter_scale_tolerance
    has_sources = bool(np.any(res.model_adu - (res.background_adu if res.background_adu is not None
                                                  else res.model_adu) > 0))
    light = stats.get("light_scale")
    bg = stats.get("background_scale")

    def scale_words(f: float) -> str:
        return f"x {f:.4g}" + ("" if abs(f - 1) <= tol else f" (beyond the {100 * tol:g} % the scene may be off)")

    def within_scale(f: float, what: str) -> str:
        return "" if abs(f - 1) > tol else f"{what} x {f:.4g} is within the {100 * tol:g} % a scene may be off"

    if light is not None and scene.exposure.frame == "light":
        c, stat = light
        f = 1.0 + c
        if scene.sky.flat_e_per_s:
            v = float(scene.sky.flat_e_per_s) * f
            out.append(_param_candidate(
                res, "flat_level", "sky.flat_e_per_s", round(v, 6), stat,
                f"the flat screen's light is {scale_words(f)} the scene's: {scene.sky.flat_e_per_s:.5g} -> "
                f"{v:.5g} e-/pixel/s", within_scale(f, "the flat level"), policy, 0.0, "light_scale"))
        elif has_sources and f > 0:
            v = float(scene.sky.source_flux_scale) * f
            within = within_scale(f, "the sources' flux") or light_moved(res, f, policy)
            out.append(_param_candidate(
                res, "zero_point", "sky.source_flux_scale", round(v, 6), stat,
                f"the sources are {scale_words(f)} as bright as the scene's (the photometric zero point, "
                f"{-2.5 * np.log10(f):+.3f} mag)", within, policy, 0.0, "light_scale"))
        elif not has_sources and scene.sky.background_mag_arcsec2 is not None and f > 0:
            bg, light = (c, stat), None  # no source: the whole light is the sky
    if bg is not None and scene.exposure.frame == "light" and scene.sky.background_mag_arcsec2 is not None \
            and not scene.sky.flat_e_per_s:
        c, stat = bg
        f = 1.0 + c + (light[0] if light is not None else 0.0)  # the background follows the whole light too
        if f > 0.02:
            mag = float(scene.sky.background_mag_arcsec2)
            v = mag - 2.5 * float(np.log10(f))
            out.append(_param_candidate(
                res, "sky_level", "sky.background_mag_arcsec2", round(v, 5), stat,
                f"the sky is {scale_words(f)} the scene's: {mag:.4g} -> {v:.4g} mag/arcsec^2",
                within_scale(f, "the sky"), policy, 0.0,
                "background_scale" if light is not None else "light_scale"))
    if "offset_adu" in stats:
        c, stat = stats["offset_adu"]
        d = c / bias_per_output_adu(sensor)
        v = max(float(sensor.bias_adu) + d, 0.0)
        within = "" if abs(d) > policy.parameter_bias_tolerance_adu else \
            f"the bias is off by {d:+.3g} ADU, within the {policy.parameter_bias_tolerance_adu:g} ADU a bias drifts"
        out.append(_param_candidate(res, "bias_level", "detector.bias_adu", round(v, 3), stat,
                                    f"the bias is {d:+.4g} ADU from the scene's: {sensor.bias_adu:.5g} -> {v:.5g} ADU",
                                    within, policy, 0.0, "offset_adu"))
    if "dark_scale" in stats and "dark_map" not in scene.effects:  # a measured dark map holds the dark itself
        c, stat = stats["dark_scale"]
        f = 1.0 + c
        if f > 0:
            v = float(sensor.dark_current_e_per_s) * f
            out.append(_param_candidate(
                res, "dark_level", "detector.dark_current_e_per_s", float(f"{v:.6g}"), stat,
                f"the dark current is {scale_words(f)} the scene's: {sensor.dark_current_e_per_s:.4g} -> "
                f"{v:.4g} e-/s", within_scale(f, "the dark current"), policy, 0.0, "dark_scale"))
    # a level the frame cannot measure apart from another (its template was dropped as degenerate): one dark
    # frame cannot tell a bias offset from a uniform dark charge
    lv = res.levels()
    allowed = {res.LEVELS[i] for i in range(len(res.LEVELS)) if i not in res.levels_not_fitted()}
    dropped = allowed - set(lv["names"])
    twin = {"offset_adu": ("dark_scale", "detector.dark_current_e_per_s"),
            "dark_scale": ("offset_adu", "detector.bias_adu")}
    for c in out:
        level = c.fit.state.get("level")
        if level in twin and twin[level][0] in dropped and scene.exposure.time_s > 0 and level != "dark_scale" \
                or level in twin and level == "dark_scale" and "offset_adu" in dropped:
            c.ambiguous = twin[level][1]
    # an ambiguous level is a finding only if every reading of it is: when its twin's reading is within the
    # twin's tolerance, the frame agrees with the scene's own numbers (a dark 2 % off, read as a bias offset,
    # is 17 ADU on a binned 300 s dark)
    dark = res.level_templates()[3]
    dark_adu = float(np.mean(np.broadcast_to(dark, res.data_adu.shape)[res.fit])) if res.n_fit else 0.0
    for c in out:
        level = c.fit.state.get("level")
        if not c.ambiguous or "tolerance" in c.codes or level not in stats or dark_adu <= 0:
            continue
        coef = stats[level][0]
        as_dark = coef / dark_adu  # an offset read as a dark level [1]
        as_bias = coef * dark_adu / bias_per_output_adu(sensor)  # a dark level read as a bias offset [ADU per read]
        if level == "offset_adu" and abs(as_dark) <= tol:
            c.codes["tolerance"] = (f"read as a dark current (which this frame cannot tell from a bias offset) it "
                                    f"is x {1 + as_dark:.4g}, within the {100 * tol:g} % a scene may be off")
        elif level == "dark_scale" and abs(as_bias) <= policy.parameter_bias_tolerance_adu:
            c.codes["tolerance"] = (f"read as a bias offset (which this frame cannot tell from a dark current) it is "
                                    f"{as_bias:+.3g} ADU, within the {policy.parameter_bias_tolerance_adu:g} ADU a "
                                    "bias drifts")
    for c in out:
        c.seconds = (time.perf_counter() - t0) / len(out)
    return out


# --- the PSF ----------------------------------------------------------------------------------------------------

def scene_with(scene, values: dict):
    """A copy of ``scene`` with dotted keys set (``{"psf.fwhm_arcsec": 2.1}``), validated as a scene file is."""
    from scenes.scene import Scene, check_scene, validate

    data = scene.model_dump(mode="json", exclude_none=True, exclude_unset=True)
    for dotted, v in values.items():
        node = data
        *path, last = dotted.split(".")
        for k in path:
            node = node.setdefault(k, {})
        node[last] = v
    data["source"] = scene.source
    new = validate(Scene, data, file=str(scene.source))
    check_scene(new)
    return new


#: frames with more output pixels than this re-render the PSF's values on a central window of this size only
#: (the width is one number of the whole frame; the window's stars measure it and keep the cost bounded)
PSF_WINDOW_PX = 1024


def _psf_window(scene, res: Residuals) -> tuple[dict, tuple[slice, slice]]:
    """The scene keys of a central window of at most PSF_WINDOW_PX output pixels a side, and its slices."""
    h, w = res.data_adu.shape
    if h <= PSF_WINDOW_PX and w <= PSF_WINDOW_PX:
        return {}, (slice(0, h), slice(0, w))
    s = scene.sensor()
    b = s.binning
    nh, nw = min(h, PSF_WINDOW_PX), min(w, PSF_WINDOW_PX)
    oy, ox = (h - nh) // 2, (w - nw) // 2
    keys = {"detector.width": nw * b, "detector.height": nh * b, "detector.x0": s.roi_x0 + ox * b,
            "detector.y0": s.roi_y0 + oy * b}
    return keys, (slice(oy, oy + nh), slice(ox, ox + nw))


def _psf_delta(scene, res: Residuals, model, key: str, value: float) -> tuple[float, Fit] | None:
    """delta(-2 ln L) of the scene with ``key`` = ``value`` against the scene's model, on the comparison's
    fitted pixels with the levels refitted (:func:`detector.signatures.pixel_score`); on a large frame, on
    a central window (:func:`_psf_window`: the change is zero elsewhere)."""
    from .model import build_model

    window, (sy, sx) = _psf_window(scene, res)
    other = build_model(scene_with(scene, {key: value, **window}), realisation=False)
    delta = np.zeros(res.data_adu.shape, np.float32)
    extra = np.zeros(res.data_adu.shape, np.float32)
    delta[sy, sx] = other.mean_adu.astype(np.float64) - model.mean_adu[sy, sx]
    extra[sy, sx] = other.var_adu2.astype(np.float64) - model.var_adu2[sy, sx]
    fit = Fit("psf", {}, 0.0, 1, res.n_fit, "", delta_adu=delta, extra_var_adu2=extra)
    s = pixel_score(fit, res)
    return (None if s is None else float(s)), fit


def width_error(x: np.ndarray, y: np.ndarray, i: int) -> float:
    """The standard error of ln(value) of a re-rendered scene number from its likelihood scan: ``y`` the
    delta -2 ln L at the factors ``x`` (sorted), ``i`` the lowest. A parabola in ln x through the three scan
    points about the lowest (the two at the scan's end when it is there) has curvature ``a``, and -2 ln L
    grows by 1 at one standard error: ``1 / sqrt(a)`` (Wilks 1938; infinite when the scan is not curved,
    the frame's sources do not measure the number)."""
    j = min(max(i, 1), x.size - 2)
    a = float(np.polyfit(np.log(x[j - 1:j + 2]), y[j - 1:j + 2], 2)[0])
    return 1.0 / np.sqrt(a) if a > 0 else float("inf")


def psf_candidates(res: Residuals, scene, model, policy: DiagnosisPolicy = DEFAULT_POLICY,
                   truth=None) -> list[Candidate]:
    """The PSF's FWHM (and a Moffat's beta) refitted by re-rendering the scene at a few values: the delta
    -2 ln L at each, a parabola through the best three, one more render at its minimum. Only for a light
    frame with stars and an analytic PSF (``gaussian`` or ``moffat``), when its sources measure the number
    well enough that a change of the policy's ``psf_width_tolerance`` is DETECTION_SIGMA standard errors of
    the scan (:func:`width_error`)."""
    if scene.exposure.frame != "light" or not scene.sky.stars or scene.psf.model not in ("gaussian", "moffat"):
        return []
    if truth is None or len(truth) == 0:
        return []
    t0 = time.perf_counter()
    out = []
    params = [("psf_width", "psf.fwhm_arcsec", float(scene.psf.fwhm_arcsec), policy.psf_width_tolerance,
               "the PSF's FWHM")]
    if scene.psf.model == "moffat":
        params.append(("psf_profile", "psf.beta", float(scene.psf.beta), policy.psf_width_tolerance,
                       "the Moffat PSF's beta (its wings)"))
    for name, key, v0, tol, what in params:
        xs, ys = [1.0], [0.0]
        for s in PSF_STEPS:
            d, _ = _psf_delta(scene, res, model, key, v0 * s)
            if d is None:
                break
            xs.append(s)
            ys.append(d)
        if len(xs) < 3:
            continue
        order = np.argsort(xs)
        x, y = np.asarray(xs)[order], np.asarray(ys)[order]
        i = int(np.argmin(y))
        if width_error(x, y, i) * DETECTION_SIGMA > np.log1p(tol):
            continue  # too few or too faint sources: a change of the tolerance would not be detected
        if 0 < i < x.size - 1:
            a, b, c = np.polyfit(np.log(x[i - 1:i + 2]), y[i - 1:i + 2], 2)
            best = float(np.exp(-b / (2 * a))) if a > 0 else float(x[i])
            best = float(np.clip(best, x[i - 1], x[i + 1]))
        else:
            best = float(x[i])  # at the edge of the steps: take it (the next round goes further)
        d, fit = _psf_delta(scene, res, model, key, v0 * best)
        if d is None or d > y[i]:
            best = float(x[i])
            d, fit = _psf_delta(scene, res, model, key, v0 * best)
        value = round(v0 * best, 4)
        within = "" if abs(best - 1) > tol else f"{what} x {best:.4g} is within the {100 * tol:g} % of the scene's"
        n = max(res.n_fit, 2)
        change = (("narrower" if best < 1 else "wider") if key == "psf.fwhm_arcsec" else
                  ("stronger wings" if best < 1 else "weaker wings"))
        fit = Fit(name, {"key": key, "value": value}, d, 1, n,
                  f"{what} is x {best:.4g} the scene's ({change}): {v0:.4g} -> "
                  f"{value:.4g}", delta_adu=fit.delta_adu, extra_var_adu2=fit.extra_var_adu2,
                  state={"scene_value": v0})
        cand = Candidate(fit, float((res.chi2_profiled() + d) / max(res.n_fit, 1)), 0.0, kind="parameter",
                         key=key, value=value, policy=policy)
        if within:
            cand.codes["tolerance"] = within
        else:
            # a number of the scene acts on every source: not a change the saturated ones carry (their bleed)
            why = away_from_saturation(res, fit, policy)
            if why:
                cand.refuse("implausible", why)
            elif (best > 1) == (key == "psf.fwhm_arcsec"):  # a widening: is it every star's, or the bright ones'?
                why = grows_with_flux(res, fit)  # the charge the stars collect pushing itself out
                cand.deferred = why and why + ": named after the effects"
        out.append(cand)
    for c in out:
        c.seconds = (time.perf_counter() - t0) / len(out)
    return out


def parameter_candidates(res: Residuals, scene, model=None, truth=None,
                         policy: DiagnosisPolicy = DEFAULT_POLICY, problems: list | None = None) -> list[Candidate]:
    """Every parameter candidate of one frame: the levels, and the PSF when the model can be re-rendered."""
    out = level_candidates(res, scene, policy)
    if model is not None:
        try:
            out += psf_candidates(res, scene, model, policy, truth)
        except Exception as exc:  # noqa: BLE001  (a failed re-render is reported, the diagnosis goes on)
            if problems is not None:
                problems.append({"effect": "psf_width", "error": f"{type(exc).__name__}: {exc}"})
    return out


def _level_shift(c: Candidate, coefs: dict[str, float], res: Residuals, scene) -> float | None:
    """A level candidate's deviation from the scene's value once another candidate is in the model: the
    relative change of a scale, or the bias change in ADU per read (None: not a level candidate)."""
    level = c.fit.state.get("level")
    if not level or level not in coefs:
        return None
    if level == "offset_adu":
        return coefs[level] / bias_per_output_adu(scene.sensor())
    if c.fit.effect == "sky_level" and level == "background_scale":
        return coefs[level] + coefs.get("light_scale", 0.0)
    return coefs[level]


def conditional_evidence(res: Residuals, other_adu, own_adu) -> tuple[float, float]:
    """What is left of a candidate's change of the model (``own_adu`` [ADU]) once another candidate's
    (``other_adu``) is in it: (its amplitude in the joint fit over its amplitude alone, the likelihood-ratio
    chi2 of its amplitude in the joint fit, ``coef^2 / var(coef)``). Both changes and the residual are
    taken with the global levels refitted (:meth:`Residuals.project`), by weighted least squares on the
    comparison's weights: the two changes as templates of free amplitude (their fitted shapes, linearised).
    A change the other one explains keeps little of its amplitude and evidence; one of another shape keeps
    both (a PSF too narrow at every flux against a brighter-fatter widening of the bright stars alone)."""
    idx, r, w = res.flat_profiled()
    a = res.project(frame_at(own_adu, idx))
    b = res.project(frame_at(other_adu, idx))
    aw, bw = a * w, b * w
    g = np.array([[aw @ a, aw @ b], [aw @ b, bw @ b]])
    y = np.array([aw @ r, bw @ r])
    if g[0, 0] <= 0:
        return 0.0, 0.0
    alone = y[0] / g[0, 0]
    try:
        cov = np.linalg.inv(g)
    except np.linalg.LinAlgError:
        return 0.0, 0.0
    coef = cov @ y
    if not (cov[0, 0] > 0 and alone != 0):
        return 0.0, 0.0
    return float(coef[0] / alone), float(coef[0] ** 2 / cov[0, 0])


def joint_psf_steps(movers: list[Candidate], res: Residuals) -> None:
    """The PSF's width and its Moffat beta, each fitted with the other held at the scene's value, are written
    together: both widen (or narrow) the sources' wings, so the pair overshoots (a round that widens the core
    x 1.25 and strengthens the wings x 0.8, the next undoing both). Each step is taken in the proportion the
    joint fit of the two changes gives it (:func:`conditional_evidence`: its amplitude beside the other's over
    its amplitude alone), in log space: x s becomes x s^share, share clipped to [0, 1]; a step with nothing
    left (share <= 0) is the other's doing (gate ``tolerance``). Changed in place."""
    live = [c for c in movers if c.significant and "scene_value" in c.fit.state]
    if len(live) != 2:
        return
    pairs = ((live[0], live[1]), (live[1], live[0]))
    # both shares from the changes as fitted, before either value is touched
    shares = [conditional_evidence(res, other.fit.delta_adu, c.fit.delta_adu)[0] for c, other in pairs]
    for (c, other), share in zip(pairs, shares):
        if share >= 1:
            continue
        v0 = c.fit.state["scene_value"]
        if share <= 0:
            c.codes["tolerance"] = (f"beside {other.key}'s change nothing of the change of {c.key} is left (joint "
                                    f"amplitude x {share:.3g}): the other one's doing")
            continue
        value = round(v0 * (c.value / v0) ** share, 4)
        c.fit.explanation += (f"; taken as {v0:.4g} -> {value:.4g} beside {other.key}'s change (the joint fit "
                              f"keeps x {share:.3g} of this step)")
        c.value = value
        c.fit.params["value"] = value


#: the scene key of the sky's level
SKY_KEY = "sky.background_mag_arcsec2"


def added_light(c: Candidate) -> bool:
    """The candidate adds a field of light over the image (an additive effect of the FIELD stage: straylight,
    a sky gradient), which a brighter sky cannot be told from where the field is uniform."""
    from detector import registry
    from detector.effects.base import Stage

    cls = registry().get(c.fit.effect)
    return c.kind == "effect" and cls is not None and cls.field_kind == "additive" and Stage.FIELD in cls.stages


def explained_away(params: list[Candidate], effects: list[Candidate], res: Residuals, scene) -> None:
    """Gate (``tolerance``) the parameter candidates another candidate explains: a level that falls within
    the policy's tolerance once a significant effect (any of them, or the PSF's change) is in the model is that
    candidate's doing, not a wrong number of the scene (vignetting lowers a flat's mean; a narrower PSF
    makes the stars' peaks look brighter); a PSF change that the best significant effect explains (less than
    half its amplitude, or no significant evidence, left in a joint fit: :func:`conditional_evidence`) is that
    effect (a blur, an inter-pixel coupling); one that keeps its evidence beside the effect is a number of the
    scene, named first (the effect is asked again in the next round). The candidates explained are changed in place."""
    movers = [c for c in params if c.significant and c.fit.state.get("level") is None
              and c.fit.delta_adu is not None]
    named = [c for c in effects if c.significant and c.fit.delta_adu is not None]
    best = named[0] if named else None
    for p in movers:
        if best is None:
            continue
        share, left = conditional_evidence(res, best.fit.delta_adu, p.fit.delta_adu)
        need = -p.policy.significant_delta_bic + np.log(max(res.n_fit, 2))
        if left < need or share < 1 - p.policy.parameter_explained_share:
            p.codes["tolerance"] = (f"with {best.fit.effect} in the model the change of {p.key} keeps x {share:.3g} "
                                    f"of its own amplitude (chi2 {left:.4g}): the sources' shape is its doing")
            continue
        # both keep their evidence beside the other: the one with more of its own comes first, as a level's
        # (below): a brighter-fatter of another kernel than the plugin's leaves a widening the PSF's width
        # takes, but the widening's flux dependence is the effect's alone
        _, effect_left = conditional_evidence(res, p.fit.delta_adu, best.fit.delta_adu)
        if left < effect_left:
            p.deferred = (f"its evidence beside {best.fit.effect} (chi2 {left:.4g}) is smaller than "
                          f"{best.fit.effect}'s beside it ({effect_left:.4g}): named after it")
    joint_psf_steps(movers, res)
    # every significant effect is asked, not the first alone: which one comes first is the judge's order (a count
    # of hot pixels, scored by its delta BIC, before a glow scored held out), not which one moves a level; the
    # large-frame path, whose pixel-scale effects are fitted apart, asked the glow and the full-resolution path
    # asked the hot pixels, so the same dark level was the glow's doing on one path and a wrong scene on the other
    explainers = [c for c in movers if c.significant] + named
    own_fit = level_fit(res)
    own = {name: c for name, (c, _) in own_fit.items()}
    for e in explainers:
        with_e = level_fit(res, e.fit.delta_adu)
        coefs = {name: c for name, (c, _) in with_e.items()}
        for p in params:
            if not p.significant:
                continue
            shift = _level_shift(p, coefs, res, scene)
            before = _level_shift(p, own, res, scene)
            if shift is None or before is None:
                continue
            tol = (p.policy.parameter_bias_tolerance_adu if p.fit.state["level"] == "offset_adu"
                   else p.policy.parameter_scale_tolerance)
            if e is best and not p.deferred:
                # the level's evidence, alone or once the effect is in, smaller than the effect's own: the
                # effect comes first (a blur lowers the stars' peaks, a glow or a gradient moves a mean level;
                # a pattern that carries a mean of its own trades it with the level, so both are asked)
                name = p.fit.state["level"]
                left = min(with_e[name][1], own_fit[name][1]) if name in own_fit else with_e[name][1]
                if left < abs(e.fit.delta_m2lnl):
                    p.deferred = (f"its evidence (chi2 {left:.4g}, alone or with {e.fit.effect} in the model) is "
                                  f"smaller than {e.fit.effect}'s ({abs(e.fit.delta_m2lnl):.4g}): named after it")
            if abs(shift) <= tol or abs(shift) < (1 - p.policy.parameter_explained_share) * abs(before):
                now = f"{shift:+.3g} ADU" if p.fit.state["level"] == "offset_adu" else f"x {1 + shift:.4g}"
                p.codes["tolerance"] = (f"with {e.key or e.fit.effect} in the model this level is {now}: its change "
                                        "is that candidate's doing")
            elif e is best and p.key == SKY_KEY and shift > 0 and not p.ambiguous and added_light(e):
                # a smooth added light (straylight, a sky gradient) that the frame shows is light over the whole
                # field: its uniform part and a brighter sky are the same pixels (the plugin's field is fitted from
                # its faintest point, a real one need not be)
                p.ambiguous = f"{e.fit.effect}'s uniform part"


def apply_parameters(data: dict, cands: list[dict]) -> list[str]:
    """Write the significant parameter candidates (JSON dicts with ``key`` and ``value``) into the scene
    ``data``; returns one note per change."""
    notes = []
    for c in cands:
        node = data
        *path, last = c["key"].split(".")
        for k in path:
            node = node.setdefault(k, {})
        old = node.get(last)
        node[last] = c["value"]
        notes.append(f"{c['key']} {old if old is not None else '(default)'} -> {c['value']}: {c['explanation']}")
    return notes


def _inverse_variance_mean(values, se) -> tuple[float, float]:
    """The inverse-variance weighted mean of ``values`` with standard errors ``se``, and its standard error."""
    w = 1.0 / np.asarray(se, float) ** 2
    return float(np.sum(w * np.asarray(values, float)) / w.sum()), float(1.0 / np.sqrt(w.sum()))


def calibration_candidates(calibration: dict, sensor, n_fit: int, chi2_per_dof: float, scene=None,
                           policy: DiagnosisPolicy = DEFAULT_POLICY) -> list[Candidate]:
    """A series' own calibration measurements (:func:`.series.calibration`) as parameter candidates: what a
    calibration set measures that one frame cannot, each against the scene's number:

    * the gain ``detector.gain_e_per_adu`` by photon transfer of two flats taken alike (Janesick 2007 eq. 4.7;
      pairs combined by inverse variance);
    * the read noise ``detector.read_noise_e`` from the difference of two bias frames (its standard error
      sigma / sqrt(2 (n - 1)) for n pixels of a normal difference), in e- through the measured gain when the
      flats measure one;
    * the dark current ``detector.dark_current_e_per_s`` from the darks' mean level (fitted pixels, spikes left
      out) against exposure time (EMVA 1288 sect. 8.1; the slope's error from the means' own errors), scaled as
      the measured slope over the model's. Means, not the table's medians: a median of integer ADU jumps
      between codes (a 10-300 s IMX411 dark of 0.66 e-: a null series named a dark current x 2.5).

    The evidence of each is ``((measured - scene) / se)^2`` (a Wald statistic, one parameter); a value within
    the policy's scale tolerance of the scene's is not a finding (gate ``tolerance``). ``chi2_per_dof``: the
    series' (a number of the camera changes the variance more than the mean: not re-rendered here)."""
    t0 = time.perf_counter()
    tol = policy.parameter_scale_tolerance
    n = max(n_fit, 2)
    rows: list[tuple[str, str, float, float, float, str, str]] = []
    g_adopted = float(sensor.gain_e_per_adu)
    pt = [e for e in calibration.get("photon_transfer", [])
          if np.isfinite(e.get("gain_se", np.nan)) and e["gain_se"] > 0 and np.isfinite(e["measured_gain_e_per_adu"])]
    if pt:
        g_adopted, se = _inverse_variance_mean([e["measured_gain_e_per_adu"] for e in pt], [e["gain_se"] for e in pt])
        frames = ", ".join("/".join(e["frames"]) for e in pt)
        rows.append(("gain", "detector.gain_e_per_adu", float(sensor.gain_e_per_adu), g_adopted, se,
                     "e-/ADU", f"the photon transfer of the flats {frames}"))
    rn = [e for e in calibration.get("read_noise", []) if np.isfinite(e["measured_e"]) and e.get("n_pixels", 0) > 1]
    if rn:
        # the pair's noise is measured in ADU: in e- through the gain the flats measured, when they did
        meas = np.array([e["measured_e"] * g_adopted / float(sensor.gain_e_per_adu) for e in rn])
        v, se = _inverse_variance_mean(meas, meas / np.sqrt(2 * (np.array([e["n_pixels"] for e in rn]) - 1)))
        frames = ", ".join("/".join(e["frames"]) for e in rn)
        rows.append(("read_noise", "detector.read_noise_e", float(sensor.read_noise_e), v, se,
                     "e-", f"the difference of the bias frames {frames}"))
    dk = calibration.get("dark_regression")
    if dk and "dark_map" not in (scene.effects if scene is not None else {}):  # a measured map holds the dark
        se = dk.get("measured_mean_rate_se_e_per_s", np.nan)
        mod, meas = dk.get("model_mean_rate_e_per_s", np.nan), dk.get("measured_mean_rate_e_per_s", np.nan)
        rate = float(sensor.dark_current_e_per_s)
        if np.isfinite(se) and se > 0 and mod > 0 and rate > 0:
            f = meas / mod
            rows.append(("dark_level", "detector.dark_current_e_per_s", rate, rate * f, rate * se / mod, "e-/s",
                         f"the darks' level against exposure time ({', '.join(dk['frames'])})"))
    out = []
    for name, key, v0, v, se, unit, source in rows:
        stat = ((v - v0) / se) ** 2
        f = v / v0 if v0 > 0 else np.inf
        within = "" if abs(f - 1) > tol else (f"the measured {name.replace('_', ' ')} is x {f:.4g} the scene's, "
                                               f"within the {100 * tol:g} % a scene may be off")
        fit = Fit(name, {"key": key, "value": float(f"{v:.6g}")}, -stat, 1, n,
                  f"{source} gives {v:.4g} +- {se:.2g} {unit}: x {f:.4g} the scene's {v0:.4g} {unit}")
        c = Candidate(fit, float(chi2_per_dof), (time.perf_counter() - t0) / max(len(rows), 1), kind="parameter", key=key,
                      value=float(f"{v:.6g}"), policy=policy)
        if within:
            c.codes["tolerance"] = within
        out.append(c)
    return out
