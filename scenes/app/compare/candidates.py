"""Which physical effect does the model lack? Fit every absent effect's signature and rank by delta BIC.

For each registered effect (built-in catalogue and user plugins) that the scene does not switch on and
that declares a ``signature`` (:mod:`detector.signatures`), the signature fits the effect's own parameters
to the residuals under the model's noise; the fitted parameters are validated by the plugin's parameter
model. Candidates are ranked by ``delta_BIC = delta(-2 ln L) + k ln n`` (Schwarz 1978); the contract's
significance threshold is ``delta_BIC < -10`` ("very strong" evidence, Kass & Raftery 1995, JASA 90, 773).
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from types import EllipsisType

import numpy as np

from detector import registry
from detector.effects.ghosts import psf_rms_px, source_image
from detector.flux_law import Slope, change_slope, flux_law
from detector.morphology import block_chi2
from detector.noise_law import noise_law, noise_share
from detector.signatures import (
    NEAR_SATURATION_SHARE,
    Fit,
    Residuals,
    dither_codes,
    frame_at,
    heldout_blind,
    heldout_delta,
    seeing_block,
)
from detector.significance import DETECTION_SIGMA, FOOTPRINT_SIGMA, MIN_TEST_PIXELS, STRONG_EVIDENCE
from detector.stats import median_square_variance, median_square_variance_error

from .floors import floor_reason, signal_range_floor
from .judge import Candidate, field_origin, indistinguishable, rank, verdict
from .policy import DEFAULT_POLICY, DiagnosisPolicy
from .sources import light_curve_candidates
from .statistics import star_photometry

__all__ = ["Candidate", "candidates", "indistinguishable", "rank", "verdict"]

#: a candidate with delta BIC at or above this is not significant (DESIGN.md contract; the policy's default)
SIGNIFICANT_DELTA_BIC = DEFAULT_POLICY.significant_delta_bic
#: a noise-only candidate leaving chi2/dof below this makes the model's variance more than the policy's
#: ``noise_excess_factor`` times the variance the residual shows (:func:`overfit`)
OVERFIT_CHI2_PER_DOF = 1.0 / DEFAULT_POLICY.noise_excess_factor


def at_bound(cls, params: dict) -> str:
    """"" or which fitted parameter sits at a bound of the effect's parameter model (the form cannot follow
    the data any further: the effect, if there, is not of this form)."""
    props = cls.Params.model_json_schema().get("properties", {})
    for key, value in params.items():
        sch = props.get(key)
        if sch is None or isinstance(value, bool) or not isinstance(value, (int, float)):
            continue
        if sch.get("bound_reachable") or sch.get("periodic"):
            # a bound that is a physical state (a drift that starts or ends at rest), or an angle's (an axis at
            # 179.9 deg is one at -0.1 deg): not a limit of form
            continue
        alts = [sch, *sch.get("anyOf", [])]
        if any(a.get("type") == "integer" for a in alts):
            continue  # a count or a grid (amplifiers, channels) is a choice of form: its smallest value is a form too

        for a in alts:
            for bkey in ("minimum", "maximum", "exclusiveMinimum", "exclusiveMaximum"):
                bound = a.get(bkey)
                if bound is None or not np.isfinite(bound) or bound == 0:
                    continue  # a zero lower bound is where an absent effect sits, not a pinned fit
                if abs(value - bound) <= 1e-3 * abs(bound):
                    return f"the fitted {key} = {value:.4g} sits at its bound {bound:.4g}: the form cannot follow the data"
    return ""


def robust_excess_var(res: Residuals) -> tuple[float, float]:
    """(the data's variance beyond the model's, the model's) [ADU^2], medians over the fitted pixels with
    the levels refitted: ``median(r^2) / m - median(v)`` (:func:`detector.stats.median_square_variance`; ``m``
    the median of chi2 with 1 dof, 0.4549), which
    sources the model misplaces (a few per cent of the pixels) cannot inflate, unlike a mean.

    Read values on the ADC's integer codes make ``r`` a lattice of spacing 1 ADU (offset by the model's mean):
    its median snaps to a lattice point, off by up to half a code, which at a noise of a few ADU is an error of
    several ADU^2 in the variance (a 6 ADU noise: +-5 ADU^2, the whole of a 0.5 x read noise excess). The values
    are then spread uniformly over their code first (a fixed-seed dither, Widrow & Kollar 2008, Quantization
    Noise, ch. 19: a dithered quantizer's output is continuous) and the dither's variance 1/12 ADU^2 taken off."""
    def compute():
        idx, r, w = res.flat_profiled()
        v = float(np.median(1.0 / w)) if w.size else 0.0
        q2 = 0.0
        if r.size:
            r, q2 = dither_codes(res, idx, r)
        return (median_square_variance(r) - v - q2 if r.size else 0.0, v)
    return res.memo("robust_excess", compute)


def robust_excess_error(var_adu2: float, n: int) -> float:
    """The standard error [ADU^2] of :func:`robust_excess_var`'s excess over ``n`` pixels whose residual variance
    is ``var_adu2``: the median-of-squares estimate's (:func:`detector.stats.median_square_variance_error`,
    2.33 var / sqrt(n)). Infinite without pixels."""
    return median_square_variance_error(var_adu2, n)


def overfit(fit: Fit, chi2_per_dof: float, res: Residuals | None = None,
            policy: DiagnosisPolicy = DEFAULT_POLICY) -> str:
    """Why a candidate that only adds variance is not the missing effect ("" when it may be): it claims far
    more variance than the residual shows (a structured residual, e.g. misplaced stars, taken for noise), by the
    policy's ``noise_excess_factor`` F asked two ways:

    * over the whole frame: the model's variance with the claim ``v + c`` more than F times the residual's own
      ``v + e`` (its mean square), i.e. chi2/dof after the claim below ``1 / F`` (chi2/dof ~ (v + e) / (v + c));
      a right noise model leaves ~1 within a few sqrt(2/n);
    * against the bulk of the pixels: the claim more than F times the variance the bulk shows beyond the model's
      (median squared residual, which misplaced sources cannot inflate), or than DETECTION_SIGMA standard errors
      of that excess (:func:`robust_excess_error`) where the bulk shows none it can resolve."""
    if fit.delta_adu is not None or fit.extra_var_adu2 is None:
        return ""
    bar = 1.0 / policy.noise_excess_factor
    if chi2_per_dof < bar:
        return (f"adds so much noise that chi2/dof falls to {chi2_per_dof:.3g} (< 1/{policy.noise_excess_factor:g}): "
                "it absorbs a structured residual, it does not explain it")
    if res is not None:
        excess, v = robust_excess_var(res)
        floor = DETECTION_SIGMA * robust_excess_error(v + max(excess, 0.0), res.flat_profiled()[0].size)
        claimed = float(np.median(np.asarray(fit.extra_var_adu2, np.float64)))
        if claimed > policy.noise_excess_factor * max(excess, floor):
            return (f"claims {claimed:.3g} ADU^2 of noise where the bulk of the pixels shows {max(excess, 0):.3g} "
                    f"beyond the model's {v:.3g}: a structured residual taken for noise")
    return ""


def chi2_after(res: Residuals, fit: Fit) -> float:
    """chi2/dof over the fitted pixels once the candidate's mean change and added variance are in the model,
    with the global levels refitted to what is left (they were fitted jointly with every candidate: a
    candidate's templates may carry part of a level, e.g. gain regions summing to the light level)."""
    idx, r, _ = res.flat()
    if fit.delta_adu is not None:
        r = r - frame_at(fit.delta_adu, idx)
    r, w = res.project(r), res.levels()["w"]
    if fit.extra_var_adu2 is not None:
        extra = np.broadcast_to(np.asarray(fit.extra_var_adu2, np.float64), res.data_adu.shape).ravel()[idx]
        w = 1.0 / (1.0 / w + extra)
    return float(np.dot(r * r, w) / max(idx.size, 1))


def photometry_worsening(before: dict, after: dict) -> tuple[float, float, int]:
    """(median, standard error, count) of the change of ``|ln(data/model flux)|`` star by star, over the stars
    measured in both photometries (:func:`scenes.app.compare.statistics.star_photometry`, matched by their
    catalogue position): a paired difference, so the stars' own scatter about the model cancels. The standard
    error of a median, ``sqrt(pi/2) sigma / sqrt(n)`` with the robust sigma (1.4826 MAD) of the differences
    (Kenney & Keeping 1962, Mathematics of Statistics, sect. 13.13); infinite below three stars."""
    if not before.get("n", 0) or not after.get("n", 0):
        return 0.0, float("inf"), 0
    ab = {(float(x), float(y)): abs(np.log(max(f, 1e-6))) for x, y, f in zip(before["x"], before["y"],
                                                                        before["flux_ratio"])}
    d = np.array([abs(np.log(max(f, 1e-6))) - ab[(float(x), float(y))]
                  for x, y, f in zip(after["x"], after["y"], after["flux_ratio"]) if (float(x), float(y)) in ab])
    d = d[np.isfinite(d)]
    if d.size < 3:  # two differences give their mean and no check of their own scatter (a MAD of 0 if alike)
        return (float(np.median(d)) if d.size else 0.0), float("inf"), int(d.size)
    med = float(np.median(d))
    sigma = 1.4826 * float(np.median(np.abs(d - med)))
    return med, float(np.sqrt(np.pi / 2) * sigma / np.sqrt(d.size)), int(d.size)


def stars_check(res: Residuals, fit: Fit, truth, policy: DiagnosisPolicy = DEFAULT_POLICY) -> str:
    """Why a candidate that reshapes sources (an image-plane transform) is not physical ("" when it may be):
    with it in the model, the catalogue stars the model already measures right (aperture photometry over
    the model's background, :func:`scenes.app.compare.statistics.star_photometry`) are measured wrong: their
    median ``|ln(data/model flux)|`` grows by more than the policy's ``stars_worse_ln``, and the stars' own
    change (:func:`photometry_worsening`) is a worsening beyond DETECTION_SIGMA of its standard error (a few
    stars, or stars whose photometry scatters, cannot show one). A blur that lowers the pixel chi2 of a
    crowded field by spreading its sources towards what the model lacks (blends, unresolved stars) fails this;
    a real blur, elongation or shift leaves the stars right or makes them right."""
    if truth is None or fit.delta_adu is None:
        return ""
    # the same for every candidate of this comparison
    before = res.memo("stars_before", lambda: star_photometry(res, truth, max_stars=300))
    if not before.get("n", 0):
        return ""
    moved = replace(res, model_adu=(res.model_adu + fit.delta_adu).astype(np.float32), _flat={})
    after = star_photometry(moved, truth, max_stars=300)
    if not after.get("n", 0):
        return ""
    b = float(np.nanmedian(np.abs(np.log(np.clip(before["flux_ratio"], 1e-6, None)))))
    a = float(np.nanmedian(np.abs(np.log(np.clip(after["flux_ratio"], 1e-6, None)))))
    worse, err, _ = photometry_worsening(before, after)
    if a > b + policy.stars_worse_ln and worse > DETECTION_SIGMA * err:
        return (f"makes the bright stars' photometry wrong: median data/model flux {before['median_flux_ratio']:.3g} "
                f"-> {after['median_flux_ratio']:.3g} over {after['n']} stars (|ln| worse by {worse:.3g} +- "
                f"{err:.2g} star by star); the light it moves belongs to sources the model lacks (blends, "
                "unresolved stars), not to a wider PSF")
    return ""


#: how far from a saturated pixel [output pixels] the light of its source and its bleed still differ from an
#: unsaturated star's: a saturated star's wings out to a few FWHM and its bleed's spill beside the trail
SATURATED_REACH_PX = 10
#: the fewest compared pixels beyond that reach on which the change is refitted (fewer: not tested)
AWAY_MIN_PIXELS = MIN_TEST_PIXELS
#: standard errors by which the refitted amplitude must fall short of the share (one-sided 0.13 % for a change
#: that does act on every source): one side of a test of a change already significant, FOOTPRINT_SIGMA
AWAY_SIGMA = FOOTPRINT_SIGMA


def saturated_reach(res: Residuals) -> tuple[np.ndarray, int] | None:
    """(the pixels within SATURATED_REACH_PX of a saturated one, the number of saturated sources), or None when
    no pixel is saturated (NEAR_SATURATION_SHARE of the ceiling) in the data or in the model: a source the model
    fills to its wells is a saturated source though the data plateau lower (a sensor whose wells spill below
    the nominal full well: its charge bleeds from there)."""
    from scipy import ndimage

    model = np.broadcast_to(res.model_adu, res.data_adu.shape)
    sat = res.saturated | (model >= NEAR_SATURATION_SHARE * res.saturation_ceiling_adu)
    if not sat.any():
        return None
    near = ndimage.binary_dilation(sat, np.ones((3, 3), bool), iterations=SATURATED_REACH_PX)
    return near, int(ndimage.label(sat)[1])


def away_from_saturation(res: Residuals, fit: Fit, policy: DiagnosisPolicy = DEFAULT_POLICY) -> str:
    """Why an image-plane transform (a blur, a smear, a drift) is not a change of every source's image ("" when
    it may be): refitted on the pixels away from the saturated sources (SATURATED_REACH_PX), its own change
    keeps less than the policy's ``parameter_explained_share`` of its amplitude, beyond AWAY_SIGMA standard errors
    (tested with at least AWAY_MIN_PIXELS pixels there; saturated: NEAR_SATURATION_SHARE of the ceiling). A
    motion of the image or a wider PSF acts on every source alike; a change carried by the saturated ones is
    their bleeding (blooming) or their non-linear cores, which a smear along the columns imitates. The saturated
    sources' reach (:func:`saturated_reach`) is found once per frame and kept with its residuals."""
    if fit.delta_adu is None or np.size(fit.delta_adu) < 2:
        return ""
    reach = res.memo("saturated_reach", lambda: saturated_reach(res))
    if reach is None:
        return ""
    near, n_sat = reach
    idx, r, w = res.flat_profiled()
    keep = ~near.ravel()[idx]
    if keep.sum() < AWAY_MIN_PIXELS:
        return ""
    d = res.project(frame_at(fit.delta_adu, idx))[keep]
    info = float(np.dot(d * d, w[keep]))
    if info <= 0:
        return ""
    amp, err = float(np.dot(d * r[keep], w[keep])) / info, 1.0 / np.sqrt(info)
    share = policy.parameter_explained_share
    if amp < share and share - amp > AWAY_SIGMA * err:
        return (f"away from the {n_sat} saturated sources (beyond {SATURATED_REACH_PX} px) the "
                f"same change keeps x {amp:.3g} +- {err:.2g} of its amplitude: the sources' change is carried by the "
                "saturated ones (their bleeding or cores), not a change of every source's image")
    return ""


def grows_with_flux(res: Residuals, fit: Fit, slope: Slope | None | EllipsisType = ...) -> str:
    """"" or the evidence that a change of the sources' images grows with their flux: the optics, the pointing and
    the PSF of the scene change every source by the same shape, ``F x s(x, y)`` for a source of flux F, so the
    change refitted source by source keeps one amplitude at every flux (power 0 of the flux,
    :mod:`detector.flux_law`); amplitudes that grow as the flux itself (power 1) are a change that grows with the
    source's own charge: brighter-fatter (Antilogus et al. 2014, JINST 9 C03048, eq. 4) or a non-linear core,
    which a blur imitates on the bright sources only. Said only when the measured power excludes 0 by
    DETECTION_SIGMA standard errors and lies nearer 1 (:func:`detector.flux_law.flux_law`). ``slope``: the
    change's :func:`detector.flux_law.change_slope`, when the caller has it."""
    slope = change_slope(res, fit.delta_adu) if slope is ... else slope
    if flux_law(slope, own=0.0, other=1.0):
        return (f"the change grows with the sources' flux: refitted source by source it goes as {slope.describe()}, "
                "where the optics, a motion or the scene's PSF change every source alike (flux^0)")
    return ""


def flux_law_refusal(res: Residuals, fit: Fit) -> str:
    """Why an image-plane transform (a blur, a smear, a shift, a distortion) is not a change of every source's
    image ("" when it may be): its change refitted source by source follows another power of the flux than the
    optics' and the pointing's 0, nearer 1 or -1 and excluding 0 by DETECTION_SIGMA standard errors (a power
    within 0.5 of 0 passes): 1, a change that grows with the source's own charge (:func:`grows_with_flux`); -1,
    a change of one size at every source whatever its flux (charge a trap takes from each, a background misfit
    about the sources)."""
    slope = change_slope(res, fit.delta_adu)
    why = grows_with_flux(res, fit, slope)
    if why:
        return why + ": brighter-fatter or a non-linear core, not a change of the image"
    if flux_law(slope, own=0.0, other=-1.0):
        return (f"the change is of one size at every source whatever its flux: refitted source by source it goes as "
                f"{slope.describe()}, where the optics or a motion change every source alike (flux^0): charge "
                "taken or given in fixed amounts (traps, a background misfit about the sources), not a change of the "
                "image")
    return ""


def _fit_signature(res: Residuals, name: str, cls) -> tuple[Fit | None, BaseException | None, float]:
    """One effect's signature fitted to ``res`` and validated by its parameter model: (fit or None, the
    exception it raised or None, seconds). Pure in ``res`` (its memo only gains values), so effects may be
    fitted concurrently."""
    t0 = time.perf_counter()
    try:
        fit = cls.signature.fit(res, name)
        if fit is not None:
            cls.Params.model_validate(fit.params)
        return fit, None, time.perf_counter() - t0
    except Exception as exc:  # noqa: BLE001  (a plugin that raises is reported, the others still run)
        return None, exc, time.perf_counter() - t0


def _in_order(fn, items: list, threads: int):
    """``fn(item)`` of every item, yielded in ``items``' order as they are ready; with ``threads`` > 1 (and more
    than one item) they run in a thread pool of that many threads."""
    if threads <= 1 or len(items) <= 1:
        yield from map(fn, items)
        return
    with ThreadPoolExecutor(max_workers=threads) as pool:
        yield from pool.map(fn, items)


def fit_signatures(res: Residuals, todo: list[tuple[str, type]], threads: int = 1, then=None):
    """(name, effect class, :func:`_fit_signature`, ``then(name, cls, fit, seconds)`` or None) of every (name,
    effect class) in ``todo``, in its order. With ``threads`` > 1 the fits (and ``then``, a pure reading of one fit:
    the first judgement of :func:`candidates`) run in a thread pool (numpy and scipy release the GIL in their array
    work); the statistics they share are computed first, so every fit reads the same memoised values and the
    results are the same bytes as one after another."""
    res.levels()  # shared by every fit: computed once, before any thread reads it
    res.flat()
    res.flat_profiled()

    def one(item):
        fit, exc, seconds = _fit_signature(res, *item)
        ok = exc is None and fit is not None and np.isfinite(fit.delta_m2lnl)
        return (fit, exc, seconds), (then(*item, fit, seconds) if ok and then is not None else None)

    for (name, cls), (got, judged) in zip(todo, _in_order(one, todo, threads)):
        yield name, cls, got, judged


def _first_judgement(res: Residuals, name: str, cls, fit: Fit, seconds: float, truth,
                     policy: DiagnosisPolicy) -> Candidate:
    """One fitted signature as a :class:`Candidate` with the gates that read its fit alone: overfit, the stars'
    photometry, saturation and the flux law for a transform, its plausibility, the physical floor, and its hooks
    (the law it tells, the names it cannot tell from). Pure in ``res`` (its memo only gains values)."""
    chi2 = chi2_after(res, fit)
    c = Candidate(fit, chi2, seconds, policy=policy)
    why = overfit(fit, chi2, res, policy)
    if why:
        c.reject("overfit", why)
    elif getattr(cls.signature, "kind", "") == "transform":
        why = stars_check(res, fit, truth, policy)
        if why:
            c.reject("stars", why)
        else:
            why = away_from_saturation(res, fit, policy)
            if why:
                c.refuse("implausible", why)
            elif c.contender:
                why = flux_law_refusal(res, fit)
                if why:
                    c.refuse("implausible", why)
    why = implausibility(cls, fit, res)
    if why and fit.state.get("richer_than"):  # a richer form the frame does not tell from a simpler one
        c.refuse("richer", why)
        c.untold = tuple(fit.state["richer_than"])
    elif why:
        c.refuse("bound" if "sits at its bound" in why else "implausible", why)
    why = floor_reason(name, fit.params, res.sensor, policy, res.exptime_s) or signal_range_floor(name, res, policy,
                                                                                                  fit.params)
    if why:
        c.refuse("floor", why)
    if hasattr(cls.signature, "law_told"):
        try:
            c.law_told = bool(cls.signature.law_told(fit, res))
        except Exception:  # noqa: BLE001  (a plugin's hook that raises claims nothing)
            c.law_told = False
    if c.contender and hasattr(cls.signature, "untold_from"):
        try:
            c.untold = tuple(cls.signature.untold_from(fit, res))
        except Exception:  # noqa: BLE001  (a plugin's hook that raises claims nothing)
            c.untold = ()
    return c


def candidates(res: Residuals, present: set[str], progress=None, truth=None,
               policy: DiagnosisPolicy = DEFAULT_POLICY, threads: int = 1) -> tuple[list[Candidate], list[dict]]:
    """Fit every absent effect with a signature. Returns (candidates best first, problems). With the model's
    TRUTH table, image-plane candidates must keep the catalogue stars' photometry (:func:`stars_check`).
    ``threads`` fits and first judges that many signatures at once (:func:`fit_signatures`; the same result)."""
    out, problems = [], []
    todo = [(name, cls) for name, cls in sorted(registry().items())
            if name not in present and cls.signature is not None]

    def then(name, cls, fit, seconds):
        return _first_judgement(res, name, cls, fit, seconds, truth, policy)

    for name, cls, (fit, exc, seconds), judged in fit_signatures(res, todo, threads, then):
        if progress is not None:
            progress(name)
        if exc is not None:
            problems.append({"effect": name, "error": f"{type(exc).__name__}: {exc}"})
            continue
        if judged is not None:
            out.append(judged)
    judge_evidence(res, out, policy, progress, threads)
    return rank(out, res.light_source), problems


def judge_evidence(res: Residuals, cands: list[Candidate], policy: DiagnosisPolicy = DEFAULT_POLICY,
                   progress=None, threads: int = 1) -> None:
    """The evidence the judge weighs for every candidate of one frame: the shares of what is wrong it
    removes and its held-out score. The same for every path that has the frame's residuals."""
    structure_shares(res, cands, policy, threads)
    excess_shares(res, cands, policy)
    support_shares(res, cands, policy)
    score_heldout(res, cands, progress=progress, policy=policy, threads=threads)


def implausibility(cls, fit: Fit, res: Residuals) -> str:
    """"" or why the fitted pattern is not physically the effect: its signature's own structure test
    (:meth:`detector.signatures.Signature.plausible`), then a parameter pinned at its bound, then the shot noise
    an added field must (charge) or must not (an offset of the read-out) carry (:func:`noise_law_refusal`)."""
    try:
        why = cls.signature.plausible(fit, res) if hasattr(cls.signature, "plausible") else ""
    except Exception as exc:  # noqa: BLE001  (a plugin's check that raises does not stop the diagnosis)
        why = f"its plausibility check failed ({type(exc).__name__}: {exc})"
    return why or at_bound(cls, fit.params) or noise_law_refusal(cls, fit, res)


def noise_law_refusal(cls, fit: Fit, res: Residuals) -> str:
    """Why an added field is not of its origin ("" when it may be): the frame's pixel-to-pixel noise, once the
    fitted change is taken off (:func:`detector.noise_law.noise_share`), carries the shot noise of that change as
    charge would, where the candidate is an offset of the read-out (a bias structure, which adds none), or carries
    none of it, where the candidate is charge (dark charge, added light): the share excludes the candidate's law (1
    for charge, 0 for an offset) by DETECTION_SIGMA standard errors and agrees with the other
    (:func:`detector.noise_law.noise_law`). Asked of a fit significant by its delta BIC (STRONG_EVIDENCE) that
    changes the mean: on one dark frame a dark-rate field and a bias structure of the same shape differ in
    nothing else."""
    origin = field_origin(cls)
    if not origin or fit.delta_adu is None or np.size(fit.delta_adu) < 2 or not fit.delta_bic < -STRONG_EVIDENCE:
        return ""
    try:
        share = noise_share(res.data_adu - res.model_adu - fit.delta_adu, res.var_adu2, res.fit, fit.delta_adu,
                            res.poisson_adu)
    except (ValueError, FloatingPointError, np.linalg.LinAlgError):  # a change not of the frame's shape: no test
        return ""
    charge = 0.0 if origin == "offset" else 1.0
    if not noise_law(share, own=charge, other=1.0 - charge):
        return ""
    if origin == "offset":
        return (f"the change carries the shot noise of charge ({share.describe()}): dark charge or light, not an "
                "offset of the read-out, which adds no noise")
    return (f"the change carries no shot noise ({share.describe()}), where {origin} charge carries its own: an "
            "offset of the read-out, not charge")


def excess_shares(res: Residuals, cands: list[Candidate], policy: DiagnosisPolicy = DEFAULT_POLICY) -> None:
    """For every pixel candidate (a mean change or an added variance), the share of the frame's excess chi2
    (levels refitted) it removes, where that excess is large (the policy's ``excess_sigma``)."""
    n = res.n_fit
    excess = res.chi2_profiled() - n
    significant = n > 0 and excess / np.sqrt(2 * n) >= policy.excess_sigma
    for c in cands:
        own = own_pixels(res, c.fit)
        if own is not None:  # a signature fitted on pixels of its own is asked there (as in support_share)
            _, _, r0, r1, w = own
            before, m = float(np.dot(r0 * r0, w)), r0.size
            if before - m >= policy.excess_sigma * np.sqrt(2 * m):
                c.excess_share = round((before - float(np.dot(r1 * r1, w))) / (before - m), 4)
        elif significant and (c.fit.delta_adu is not None or c.fit.extra_var_adu2 is not None) \
                and np.isfinite(c.chi2_per_dof):
            c.excess_share = round(float((excess + n - c.chi2_per_dof * n) / excess), 4)


def own_pixels(res: Residuals, fit: Fit):
    """(index, mean change, residual before and after, weights) on the pixels a signature fits on its own
    (``support_pixels``: a colour mosaic of tens of per cent makes every other pixel an outlier of the grey
    comparison), or None for a signature judged on the compared pixels."""
    if fit.delta_adu is None:
        return None
    own = getattr(getattr(registry().get(fit.effect), "signature", None), "support_pixels", None)
    return None if own is None else own(res, fit)


def support_share(res: Residuals, fit: Fit, policy: DiagnosisPolicy = DEFAULT_POLICY) -> float | None:
    """The share of the excess chi2 (levels refitted) over the pixels ``fit`` acts on that it removes: those
    whose weighted squared mean change ``delta^2 w`` is among the largest, carrying the policy's
    ``support_mass`` of its sum. None when the fit changes no mean or the excess there is not significant
    (``support_sigma``). A signature fitted on pixels of its own (``support_pixels``: a colour mosaic of tens
    of per cent makes every other pixel an outlier of the grey comparison) is asked on those pixels: on the
    compared ones alone it would be judged where it is weakest."""
    if fit.delta_adu is None:
        return None
    sig = getattr(registry().get(fit.effect), "signature", None)
    if getattr(sig, "support_pixels", None) is not None:
        got = own_pixels(res, fit)
        if got is None:
            return None
        idx, d, r0, r1, w = got
        return _support(d, r0, r1, w, w, policy)
    idx, r0, w = res.flat_profiled()
    if idx.size < 64:
        return None
    d = frame_at(fit.delta_adu, idx) if np.size(fit.delta_adu) > 1 else \
        np.full(idx.size, float(np.asarray(fit.delta_adu).ravel()[0]))
    r1 = res.project(res.flat()[1] - d)
    w1 = w
    if fit.extra_var_adu2 is not None:
        e = np.broadcast_to(np.asarray(fit.extra_var_adu2, np.float64), res.data_adu.shape).ravel()[idx]
        w1 = 1.0 / np.maximum(1.0 / w + e, 0.1 / w)
    return _support(d, r0, r1, w, w1, policy)


def _support(d: np.ndarray, r0: np.ndarray, r1: np.ndarray, w: np.ndarray, w1: np.ndarray,
             policy: DiagnosisPolicy) -> float | None:
    """:func:`support_share` on given pixels: the mean change ``d``, the residual before and after (levels
    refitted), their weights."""
    if d.size < 64:
        return None
    q = d * d * w
    total = float(q.sum())
    if total <= 0:
        return None
    sub = np.sort(q[:: max(1, d.size // 200_000)])[::-1]
    cum = np.cumsum(sub)
    thr = float(sub[min(int(np.searchsorted(cum, policy.support_mass * cum[-1])), sub.size - 1)])
    on = q >= thr
    n_on = int(on.sum())
    if n_on < 16:
        return None
    before = float(np.dot(r0[on] ** 2, w[on])) - n_on
    if before < policy.support_sigma * np.sqrt(2 * n_on):
        return None
    after = float(np.dot(r1[on] ** 2, w1[on])) - n_on
    return round(float((before - after) / before), 4)


def support_shares(res: Residuals, cands: list[Candidate], policy: DiagnosisPolicy = DEFAULT_POLICY) -> None:
    """:func:`support_share` of every contender (significant by delta BIC, plausible, not rejected)."""
    for c in cands:
        if c.contender and c.fit.delta_adu is not None:
            c.support_share = support_share(res, c.fit, policy)


def structure_share(res: Residuals, delta: np.ndarray, policy: DiagnosisPolicy = DEFAULT_POLICY,
                    blocks: tuple[float, int] | None = None, extra_var_adu2=None) -> float | None:
    """The share of the frame's significant large-scale structure (block chi2 beyond its dof,
    :func:`detector.morphology.block_chi2`) that the mean change ``delta`` removes; None when the structure is
    not significant or ``delta`` is a pattern of a few pixels (a CFA, a blur, a shift: not judged by the block
    means). ``blocks``: the frame's ``block_chi2(res)`` when the caller has it. ``extra_var_adu2``: the
    candidate's added variance, which the block means left carry (a white response pattern's block means are
    its own scatter, averaged: the pattern a PRNU's low-frequency map comes with)."""
    chi2, n = block_chi2(res) if blocks is None else blocks
    if n == 0 or (chi2 - n) / np.sqrt(2 * n) < policy.structure_sigma:
        return None
    idx, _, w = res.flat_profiled()
    if large_scale_share(res, delta, idx, w) < 0.5:
        return None
    after, _ = block_chi2(res, delta, extra_var_adu2)
    return round(float(np.clip((chi2 - after) / (chi2 - n), -1.0, 1.0)), 4)


def structure_shares(res: Residuals, cands: list[Candidate], policy: DiagnosisPolicy = DEFAULT_POLICY,
                     threads: int = 1) -> None:
    """:func:`structure_share` of every candidate with a mean change that is significant by delta BIC;
    ``threads`` of them at once (:func:`_in_order`; the same result: the statistics they share are computed
    first)."""
    blocks = block_chi2(res)
    reg = registry()
    todo = []
    for c in cands:
        if c.fit.delta_adu is not None and c.fit.delta_bic < policy.significant_delta_bic:
            # (a variance candidate's scatter is in its blocks' variances: a mean change that only comes with
            # added charge's shot noise, a glow's, is judged on its mean change alone, as before)
            sig = reg[c.fit.effect].signature if c.fit.effect in reg else None
            todo.append((c, c.fit.extra_var_adu2 if getattr(sig, "kind", "") == "variance" else None))
    if len(todo) > 1 and threads > 1 and _on_usable(res):
        _usable_levels(res)  # shared by every share: computed once, before any thread reads it
    shares = _in_order(lambda t: structure_share(res, t[0].fit.delta_adu, policy, blocks, t[1]), todo, threads)
    for (c, _), share in zip(todo, shares):
        if share is not None:
            c.explains = share


def large_scale_share(res: Residuals, delta: np.ndarray, idx: np.ndarray, w: np.ndarray) -> float:
    """The share of a candidate's own mean change (its chi2 over the fitted pixels) that survives averaging
    into the blocks of :func:`detector.morphology.block_chi2`: ~1 for a smooth pattern, ~0 for a pattern of
    a few pixels.

    A property of the pattern, so measured on pixels chosen without looking at the residual: the usable
    pixels (:attr:`detector.signatures.Residuals.usable`) when the fitted ones leave some out. The fitted
    pixels exclude the residual's own local outliers, and a strong pixel pattern's deep pixels are such
    outliers (a mosaic's dim dye: whole colour planes, kept only where a smooth drift brings them near the
    model); sampled there, a period-2 pattern aliases into the block means and looks large-scale."""
    if _on_usable(res):
        return _large_scale_share_usable(res, delta)
    # both sides with the global levels refitted: a pattern's mean (a bias bowl's constant part) is a level
    d = res.project(frame_at(delta, idx))
    total = float(np.dot(d * d, w))
    if total <= 0:
        return 0.0
    zero = replace(res, data_adu=(res.model_adu + np.broadcast_to(delta, res.data_adu.shape)).astype(np.float32),
                   _flat=res.shared_levels())  # the same fitted pixels and templates: only the data changed
    big, _ = block_chi2(zero)
    return big / total


def _large_scale_share_usable(res: Residuals, delta: np.ndarray) -> float:
    """:func:`large_scale_share` on the usable pixels: the frame made of the model plus ``delta`` alone, its
    global levels refitted, compared pixel by pixel and in blocks (the level templates gathered once per
    comparison, :meth:`detector.signatures.Residuals.memo`)."""
    zero = replace(res, data_adu=(res.model_adu + np.broadcast_to(delta, res.data_adu.shape)).astype(np.float32),
                   fit=res.usable, _flat=dict(_usable_levels(res)))
    total = zero.chi2_profiled()
    if total <= 0:
        return 0.0
    big, _ = block_chi2(zero)
    return big / total


def _on_usable(res: Residuals) -> bool:
    """Is :func:`large_scale_share` measured on the usable pixels (the fitted ones leave some out)?"""
    return res.usable is not None and res.usable.shape == res.fit.shape and bool((res.usable & ~res.fit).any())


def _usable_levels(res: Residuals) -> dict:
    """The global levels' templates gathered on the usable pixels (:meth:`detector.signatures.Residuals.memo`,
    once per comparison)."""
    return res.memo("usable_levels", lambda: replace(res, data_adu=res.model_adu, fit=res.usable,
                                                      _flat={}).shared_levels())


def coherence_px(res: Residuals) -> int:
    """The residual's coherence length [output px]: about twice the sources' rms radius
    (:func:`detector.effects.ghosts.psf_rms_px` of the model's sources), at least 2 px (pixel-independent noise
    with a one-pixel margin); the smallest held-out block that keeps the folds apart."""
    rms = psf_rms_px(source_image(res)) if res.photo_adu is not None and res.photo_adu.size else 0.0
    return max(2, int(np.ceil(2.0 * rms)))


def score_heldout(res: Residuals, cands: list[Candidate], progress=None,
                  policy: DiagnosisPolicy = DEFAULT_POLICY, threads: int = 1) -> None:
    """The held-out delta of the contenders (at most the policy's ``heldout_candidates``, best delta BIC
    first); ``threads`` scores that many at once (the same result)."""
    reg = registry()
    todo = [c for c in sorted((c for c in cands if c.contender), key=lambda c: c.fit.delta_bic)
            [:policy.heldout_candidates] if c.fit.effect in reg and hasattr(reg[c.fit.effect].signature, "score")]
    for c, got in _score_all(res, todo, reg, None, threads):
        if got is not None:
            c.heldout, c.heldout_blind = got
        if progress is not None:
            progress(f"{c.fit.effect} (held out)")
    # the best-fitting contender's change carried by too few pixels for the default blocks (one fold sees less
    # than a detection of it): every contender with a held-out score (the variance-only ones too) is scored
    # again, on the largest blocks both folds see that change on (detector.signatures.seeing_block), so their
    # held-out scores (and the catch-all's) share one layout; a candidate that cannot be scored there keeps its
    # default-block score (and heldout_block None). The blocks are no smaller than the residual's coherence
    # length (about twice the sources' rms radius, detector.effects.ghosts.psf_rms_px; 2 px without sources):
    # a held-out pixel with training pixels within the PSF is not held out from a PSF-scale mismatch
    scored = [c for c in cands if c.heldout is not None]
    best = min((c for c in scored if c.fit.delta_adu is not None), key=lambda c: c.fit.delta_bic, default=None)
    block = None
    if best is not None and best.heldout_blind:
        block = seeing_block(best.fit, res, coherence_px(res))
    if block is not None:
        res.forget("heldout_folds")
        for c, got in _score_all(res, scored, reg, block, threads):
            if got is not None and got[0] is not None:
                (c.heldout, c.heldout_blind), c.heldout_block = got, block
    res.forget("heldout_folds")  # the folds every candidate shared (detector.signatures.heldout_delta)


def _score_all(res: Residuals, todo: list[Candidate], reg: dict, block: int | None, threads: int):
    """(candidate, :func:`_heldout_of`) of every candidate in ``todo``, in its order. The first is scored alone
    (it builds the folds every candidate shares), the others ``threads`` at a time (:func:`_in_order`)."""
    def score(c: Candidate):
        return _heldout_of(c, reg[c.fit.effect].signature, res, block)

    if todo:
        yield todo[0], score(todo[0])
        yield from zip(todo[1:], _in_order(score, todo[1:], threads))


def _heldout_of(c: Candidate, sig, res: Residuals, block: int | None = None) -> tuple[float | None, bool] | None:
    """``c``'s held-out delta on blocks of ``block`` pixels (default: the layout's) and whether the test is blind
    to its change; None (and ``c`` refused) when it cannot be scored. Its time is added to ``c.seconds``."""
    t0 = time.perf_counter()
    try:
        h = heldout_delta(sig, res, c.fit.effect, c.fit, block)
        return h, h is not None and heldout_blind(c.fit, res, block)
    except Exception as exc:  # noqa: BLE001
        c.refuse("error", f"cannot be scored on held-out pixels ({type(exc).__name__}: {exc})")
        return None
    finally:
        c.seconds += time.perf_counter() - t0


def source_candidates(res: Residuals, truth, scene, policy: DiagnosisPolicy = DEFAULT_POLICY) -> list[Candidate]:
    """Candidates of the scene's sources (an object's light curve, :mod:`.sources`), as :class:`Candidate`;
    ``seconds`` is each one's fit and chi2."""
    out = []
    t0 = time.perf_counter()
    for fit in light_curve_candidates(res, truth, scene):
        chi2 = chi2_after(res, fit)
        out.append(Candidate(fit, chi2, time.perf_counter() - t0, policy=policy))
        t0 = time.perf_counter()
    return out


def nested_fit(res: Residuals, given: Fit, name: str) -> Fit | None:
    """``name``'s signature fitted again with ``given``'s mean change already in the model (the data less that
    change, the global levels refitted as before): what it explains that ``given`` leaves."""
    sig = getattr(registry().get(name), "signature", None)
    if sig is None or given.delta_adu is None:
        return None
    left = replace(res, data_adu=(res.data_adu - given.delta_adu).astype(np.float32), _flat=res.shared_levels())
    try:
        fit = sig.fit(left, name)
    except Exception:  # noqa: BLE001  (a signature that cannot refit tells nothing)
        return None
    return fit if fit is not None and np.isfinite(fit.delta_m2lnl) else None


def explains_beside(res: Residuals, c: Candidate, o: Candidate, policy: DiagnosisPolicy = DEFAULT_POLICY) -> str:
    """"" unless nesting tells ``c`` from ``o`` in ``c``'s favour, else the one-line reason for ``o``'s refusal:
    ``c`` fitted again with ``o``'s change in the model still explains significantly what ``o`` leaves (delta BIC
    below the policy's significance), and ``o`` fitted again beside ``c`` explains nothing significant (or
    nothing at all). Both significant beside the other, or neither: the pixels do not decide."""
    c_left = nested_fit(res, o.fit, c.fit.effect)
    if c_left is None or c_left.delta_bic >= policy.significant_delta_bic:
        return ""
    o_left = nested_fit(res, c.fit, o.fit.effect)
    if o_left is not None and o_left.delta_bic < policy.significant_delta_bic:
        return ""
    return (f"beside {c.fit.effect} it explains nothing significant"
            + (f" (delta BIC {o_left.delta_bic:.4g})" if o_left is not None else "")
            + f", while {c.fit.effect} explains what it leaves (delta BIC {c_left.delta_bic:.4g})")


def blind_rivals(res: Residuals, cands: list[Candidate], policy: DiagnosisPolicy = DEFAULT_POLICY) -> None:
    """A contender whose held-out test is blind (:attr:`Candidate.heldout_blind`: one fold sees less than a
    detection of its change) and that fits as well as the first significant effect or better
    (:func:`.judge.blind_rival`), or, when no effect is significant, the blind contender that fits best, is
    told from the others by nesting (:func:`explains_beside`): when it explains significantly what each of them
    (the first name and the other scored contenders) leaves and none explains anything beside it, they are
    refused (gate ``nested``) and it is judged on its delta BIC (its held-out score, no test of it, cleared). A
    compressive response taking charge from the bright stars' cores leaves each star's flux short, which no
    brighter-fatter widening (each star's flux kept) or jitter (every star widened alike) makes; they add nothing
    beside it. A rival that nesting does not tell from it (neither explains significantly what the other leaves),
    whose own held-out score is blind too and whose delta BIC is no better but within the twins' tolerance, is
    not refused but left its twin (:func:`.judge.blind_rival` lists it; a rival beyond the tolerance is no twin and
    keeps the decision open): the few pixels carrying both changes decide nothing between them, and
    the better fit goes first, as twins do (:func:`.judge.rank`). Otherwise the tie stays
    (:func:`.judge.indistinguishable`), or nothing is named: a blind candidate with no rival to be told from is
    not tested at all."""
    from .judge import blind_rival, rank

    ranked = rank(cands, res.light_source)
    sig = [c for c in ranked if c.significant and c.kind == "effect"]
    scored = [c for c in ranked if c.kind == "effect" and c.contender and c.fit.delta_adu is not None
              and not c.significant and c.heldout is not None]
    if sig:
        blind = [c for c in scored if c.heldout_blind and blind_rival(sig[0], c)]
    else:
        blind = sorted((c for c in scored if c.heldout_blind), key=lambda c: c.fit.delta_bic)[:1]
        if blind and blind[0].fit.delta_bic > min(c.fit.delta_bic for c in scored):
            return  # a better fit that is not blind failed its held-out test: nothing to decide
    for c in sorted(blind, key=lambda c: c.fit.delta_bic):
        others = [o for o in sig[:1] + scored if o is not c and o.fit.delta_adu is not None]
        if not others:
            continue
        reasons = [explains_beside(res, c, o, policy) for o in others]
        # a twin: no better a fit, within the twins' tolerance, its own held-out score blind (blind_rival)
        if all(why or (o.fit.delta_bic >= c.fit.delta_bic and blind_rival(c, o))
               for o, why in zip(others, reasons)):
            for o, why in zip(others, reasons):
                if why:
                    o.refuse("nested", why)
            c.heldout = None
            return
