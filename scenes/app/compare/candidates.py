"""Which physical effect does the model lack? Fit every absent effect's signature and rank by delta BIC.

For each registered effect (built-in catalogue and user plugins) that the scene does not switch on and
that declares a ``signature`` (:mod:`detector.signatures`), the signature fits the effect's own parameters
to the residuals under the model's noise; the fitted parameters are validated by the plugin's parameter
model. Candidates are ranked by ``delta_BIC = delta(-2 ln L) + k ln n`` (Schwarz 1978); the contract's
significance threshold is ``delta_BIC < -10`` ("very strong" evidence, Kass & Raftery 1995, JASA 90, 773).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from detector import registry
from detector.effects.base import Stage
from detector.morphology import block_chi2
from detector.signatures import Fit, Residuals, frame_at, heldout_delta

from .sources import light_curve_candidates
from .statistics import star_photometry

#: a candidate with delta BIC at or above this is not significant (DESIGN.md contract)
SIGNIFICANT_DELTA_BIC = -10.0
#: chi2/dof after (levels refitted) below which a candidate that only adds variance is rejected: it explains
#: a structured residual by making the model's noise so large that everything fits (a correct noise model
#: leaves chi2/dof ~ 1, within a few sqrt(2/n))
OVERFIT_CHI2_PER_DOF = 0.5


#: a candidate must improve the pixels its fit did not see by at least this much (delta -2 ln L, summed
#: over the two folds of :func:`detector.signatures.heldout_delta`) to be significant
SIGNIFICANT_HELDOUT = -10.0
#: candidates (plausible, not rejected, delta BIC below the threshold) scored on held-out pixels, best first
HELDOUT_CANDIDATES = 8
#: where the frame has a significant large-scale structure, a candidate that changes the mean must remove at
#: least this share of it to be named: one that takes a corner of a pattern it does not share is not it
MIN_EXPLAINED = 0.5
#: large-scale structure is significant when the block chi2 exceeds its dof by this many standard deviations
STRUCTURE_SIGMA = 8.0
#: where the frame's excess chi2 is this many standard deviations above its dof (significant), a pixel candidate
#: must remove at least MIN_EXCESS_SHARE of it to be named: a trace of a big pattern is not the missing effect
#: (an amplifier undershoot trailing every star was named a non-linearity that removed 1 % of the excess)
EXCESS_SIGMA, MIN_EXCESS_SHARE = 5.0, 0.02


#: a candidate that changes the mean must remove at least this share of the excess chi2 over the pixels it acts
#: on (where that excess is significant): an effect that leaves most of what is wrong where it acts is not
#: what is wrong there (a shift that takes the centroid of a one-sided tail, a bowl under a few dust shadows)
MIN_SUPPORT_SHARE = 0.5
#: the pixels a candidate acts on: the largest of its weighted squared changes, which carry this share of them
SUPPORT_MASS = 0.9
#: the excess over those pixels is significant at this many standard deviations of its chi2
SUPPORT_SIGMA = 8.0


@dataclass
class Candidate:
    """One effect fitted to the residuals, with what the ranking asks of it.

    ``rejected``: the fit only hides a residual (noise that makes everything fit, a blur that spoils the
    stars' photometry); ``implausible``: the fitted pattern is not physically this effect (its signature's
    structure test, a parameter at its bound); ``heldout``: delta(-2 ln L) on pixels the fit did not see
    (None: not scored: compared by counts, or not a contender). A significant candidate passes all three.
    """

    fit: Fit
    chi2_per_dof: float
    seconds: float
    rejected: str = ""  #: why a candidate with a large delta BIC is not physical ("" if it is)
    implausible: str = ""  #: why the fitted pattern is not this effect ("" if it may be)
    heldout: float | None = None
    #: share of the frame's large-scale structure (block chi2 beyond its dof) the candidate's mean change
    #: removes; None when there is no such structure or the candidate changes no mean
    explains: float | None = None

    @property
    def plausible(self) -> bool:
        return not self.implausible

    @property
    def contender(self) -> bool:
        """Significant by delta BIC and neither rejected nor implausible: worth a held-out score."""
        return self.fit.delta_bic < SIGNIFICANT_DELTA_BIC and not self.rejected and not self.implausible

    #: share of the frame's whole excess chi2 (levels refitted) the candidate removes, where that excess is
    #: large; None otherwise (or for candidates compared by counts)
    excess_share: float | None = None

    #: share of the excess chi2 over the pixels the candidate acts on that it removes (None: not measured)
    support_share: float | None = None

    @property
    def significant(self) -> bool:
        return (self.contender and (self.heldout is None or self.heldout < SIGNIFICANT_HELDOUT)
                and (self.explains is None or self.explains >= MIN_EXPLAINED)
                and (self.excess_share is None or self.excess_share >= MIN_EXCESS_SHARE)
                and (self.support_share is None or self.support_share >= MIN_SUPPORT_SHARE))

    @property
    def score(self) -> float:
        """What the ranking sorts by: the held-out delta when there is one, else delta BIC."""
        return self.heldout if self.heldout is not None else self.fit.delta_bic

    def to_json(self) -> dict:
        f = self.fit
        return {"effect": f.effect, "params": f.params, "chi2_per_dof": self.chi2_per_dof,
                "delta_bic": f.delta_bic, "delta_m2lnl": f.delta_m2lnl, "k": f.k, "explanation": f.explanation,
                "kind": type(registry()[f.effect].signature).__name__ if f.effect in registry() else "",
                "significant": self.significant, "rejected": self.rejected, "plausible": self.plausible,
                "implausible_because": self.implausible, "heldout_delta": self.heldout,
                "explains_structure": self.explains, "explains_excess": self.excess_share,
                "explains_where_it_acts": self.support_share, "variant": f.note,
                "seconds": self.seconds}


def at_bound(cls, params: dict) -> str:
    """"" or which fitted parameter sits at a bound of the effect's parameter model (the form cannot follow
    the data any further: the effect, if there, is not of this form)."""
    props = cls.Params.model_json_schema().get("properties", {})
    for key, value in params.items():
        sch = props.get(key)
        if sch is None or isinstance(value, bool) or not isinstance(value, (int, float)):
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


#: a noise-only candidate may claim at most this many times the variance the data show beyond the model's
#: (robustly, from the median squared residual) and never less than this fraction of the model's variance
NOISE_EXCESS_FACTOR, NOISE_FLOOR_FRACTION = 3.0, 0.05


def robust_excess_var(res: Residuals) -> tuple[float, float]:
    """(the data's variance beyond the model's, the model's) [ADU^2], medians over the fitted pixels with
    the levels refitted: ``median(r^2) / 0.4549 - median(v)`` (0.4549 = median of chi2 with 1 dof), which
    sources the model misplaces (a few per cent of the pixels) cannot inflate, unlike a mean."""
    if "robust_excess" not in res._flat:
        _, r, w = res.flat_profiled()
        v = float(np.median(1.0 / w)) if w.size else 0.0
        res._flat["robust_excess"] = (float(np.median(r * r)) / 0.4549 - v if r.size else 0.0, v)
    return res._flat["robust_excess"]


def overfit(fit: Fit, chi2_per_dof: float, res: Residuals | None = None) -> str:
    """Why a candidate that only adds variance is not the missing effect ("" when it may be): it brings
    chi2/dof far below 1, or it claims far more variance than the bulk of the pixels shows (a structured
    residual, e.g. misplaced stars, taken for noise)."""
    if fit.delta_adu is not None or fit.extra_var_adu2 is None:
        return ""
    if chi2_per_dof < OVERFIT_CHI2_PER_DOF:
        return (f"adds so much noise that chi2/dof falls to {chi2_per_dof:.3g} (< {OVERFIT_CHI2_PER_DOF}): it "
                "absorbs a structured residual, it does not explain it")
    if res is not None:
        excess, v = robust_excess_var(res)
        claimed = float(np.median(np.asarray(fit.extra_var_adu2, np.float64)))
        if claimed > NOISE_EXCESS_FACTOR * max(excess, NOISE_FLOOR_FRACTION * v):
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


#: a candidate that moves light around the sources may worsen the bright stars' aperture photometry by at
#: most this much in median |ln(data / model flux)| (and must leave it below STARS_OK_LN)
STARS_WORSE_LN, STARS_OK_LN = 0.1, 0.2
#: bright stars needed for that test
STARS_MIN = 10


def stars_check(res: Residuals, fit: Fit, truth) -> str:
    """Why a candidate that reshapes sources (an image-plane transform) is not physical ("" when it may be):
    with it in the model, the catalogue stars the model already measures right (aperture photometry over
    the model's background, :func:`scenes.app.compare.statistics.star_photometry`) are measured wrong. A blur that
    lowers the pixel chi2 of a crowded field by spreading its sources towards what the model lacks (blends,
    unresolved stars) fails this; a real blur, elongation or shift leaves the stars right or makes them
    right."""
    if truth is None or fit.delta_adu is None:
        return ""
    if "stars_before" not in res._flat:  # the same for every candidate of this comparison
        res._flat["stars_before"] = star_photometry(res, truth, max_stars=300)
    before = res._flat["stars_before"]
    if before.get("n", 0) < STARS_MIN:
        return ""
    moved = replace(res, model_adu=(res.model_adu + fit.delta_adu).astype(np.float32), _flat={})
    after = star_photometry(moved, truth, max_stars=300)
    if after.get("n", 0) < STARS_MIN:
        return ""
    b = float(np.nanmedian(np.abs(np.log(np.clip(before["flux_ratio"], 1e-6, None)))))
    a = float(np.nanmedian(np.abs(np.log(np.clip(after["flux_ratio"], 1e-6, None)))))
    if a > b + STARS_WORSE_LN and a > STARS_OK_LN:
        return (f"makes the bright stars' photometry wrong: median data/model flux {before['median_flux_ratio']:.3g} "
                f"-> {after['median_flux_ratio']:.3g} over {after['n']} stars; the light it moves belongs to sources "
                "the model lacks (blends, unresolved stars), not to a wider PSF")
    return ""


def candidates(res: Residuals, present: set[str], progress=None, truth=None) -> tuple[list[Candidate], list[dict]]:
    """Fit every absent effect with a signature. Returns (candidates best first, problems). With the model's
    TRUTH table, image-plane candidates must keep the catalogue stars' photometry (:func:`stars_check`)."""
    out, problems = [], []
    for name, cls in sorted(registry().items()):
        if name in present or cls.signature is None:
            continue
        t0 = time.perf_counter()
        try:
            fit = cls.signature.fit(res, name)
            if fit is not None:
                cls.Params.model_validate(fit.params)
        except Exception as exc:  # noqa: BLE001  (a plugin that raises is reported, the others still run)
            problems.append({"effect": name, "error": f"{type(exc).__name__}: {exc}"})
            continue
        finally:
            if progress is not None:
                progress(name)
            seconds = time.perf_counter() - t0
        if fit is None or not np.isfinite(fit.delta_m2lnl):
            continue
        chi2 = chi2_after(res, fit)
        why = overfit(fit, chi2, res)
        if not why and getattr(cls.signature, "kind", "") == "transform":
            why = stars_check(res, fit, truth)
        out.append(Candidate(fit, chi2, seconds, why, implausibility(cls, fit, res)))
    structure_shares(res, out)
    excess_shares(res, out)
    support_shares(res, out)
    score_heldout(res, out, progress=progress)
    return rank(out, res.light_source), problems


def implausibility(cls, fit: Fit, res: Residuals) -> str:
    """"" or why the fitted pattern is not physically the effect: its signature's own structure test
    (:meth:`detector.signatures.Signature.plausible`), then a parameter pinned at its bound."""
    try:
        why = cls.signature.plausible(fit, res) if hasattr(cls.signature, "plausible") else ""
    except Exception as exc:  # noqa: BLE001  (a plugin's check that raises does not stop the diagnosis)
        why = f"its plausibility check failed ({type(exc).__name__}: {exc})"
    return why or at_bound(cls, fit.params)


def excess_shares(res: Residuals, cands: list[Candidate]) -> None:
    """For every pixel candidate (a mean change or an added variance), the share of the frame's excess chi2
    (levels refitted) it removes, where that excess is large (EXCESS_SIGMA)."""
    n = res.n_fit
    excess = res.chi2_profiled() - n
    if n == 0 or excess / np.sqrt(2 * n) < EXCESS_SIGMA:
        return
    for c in cands:
        if (c.fit.delta_adu is not None or c.fit.extra_var_adu2 is not None) and np.isfinite(c.chi2_per_dof):
            c.excess_share = round(float((excess + n - c.chi2_per_dof * n) / excess), 4)


def support_share(res: Residuals, fit: Fit) -> float | None:
    """The share of the excess chi2 (levels refitted) over the pixels ``fit`` acts on that it removes: those
    whose weighted squared mean change ``delta^2 w`` is among the largest, carrying SUPPORT_MASS of its sum.
    None when the fit changes no mean or the excess there is not significant (SUPPORT_SIGMA)."""
    if fit.delta_adu is None:
        return None
    idx, r0, w = res.flat_profiled()
    if idx.size < 64:
        return None
    d = frame_at(fit.delta_adu, idx) if np.size(fit.delta_adu) > 1 else \
        np.full(idx.size, float(np.asarray(fit.delta_adu).ravel()[0]))
    q = d * d * w
    total = float(q.sum())
    if total <= 0:
        return None
    sub = np.sort(q[:: max(1, idx.size // 200_000)])[::-1]
    cum = np.cumsum(sub)
    thr = float(sub[min(int(np.searchsorted(cum, SUPPORT_MASS * cum[-1])), sub.size - 1)])
    on = q >= thr
    n_on = int(on.sum())
    if n_on < 16:
        return None
    before = float(np.dot(r0[on] ** 2, w[on])) - n_on
    if before < SUPPORT_SIGMA * np.sqrt(2 * n_on):
        return None
    r1 = res.project(res.flat()[1] - d)
    w1 = w
    if fit.extra_var_adu2 is not None:
        e = np.broadcast_to(np.asarray(fit.extra_var_adu2, np.float64), res.data_adu.shape).ravel()[idx]
        w1 = 1.0 / np.maximum(1.0 / w + e, 0.1 / w)
    after = float(np.dot(r1[on] ** 2, w1[on])) - n_on
    return round(float((before - after) / before), 4)


def support_shares(res: Residuals, cands: list[Candidate]) -> None:
    """:func:`support_share` of every contender (significant by delta BIC, plausible, not rejected)."""
    for c in cands:
        if c.contender and c.fit.delta_adu is not None:
            c.support_share = support_share(res, c.fit)


def structure_shares(res: Residuals, cands: list[Candidate]) -> None:
    """For every candidate with a mean change, the share of the frame's significant large-scale structure
    (block chi2 beyond its dof, :func:`detector.morphology.block_chi2`) that it removes."""
    chi2, n = block_chi2(res)
    if n == 0 or (chi2 - n) / np.sqrt(2 * n) < STRUCTURE_SIGMA:
        return
    idx, _, w = res.flat_profiled()
    for c in cands:
        if c.fit.delta_adu is not None and c.fit.delta_bic < SIGNIFICANT_DELTA_BIC:
            if large_scale_share(res, c.fit.delta_adu, idx, w) < 0.5:
                continue  # a pattern of a few pixels (a CFA, a blur, a shift): not judged by the block means
            after, _ = block_chi2(res, c.fit.delta_adu)
            c.explains = round(float(np.clip((chi2 - after) / (chi2 - n), -1.0, 1.0)), 4)


def large_scale_share(res: Residuals, delta: np.ndarray, idx: np.ndarray, w: np.ndarray) -> float:
    """The share of a candidate's own mean change (its chi2 over the fitted pixels) that survives averaging
    into the blocks of :func:`detector.morphology.block_chi2`: ~1 for a smooth pattern, ~0 for a pattern of
    a few pixels."""
    # both sides with the global levels refitted: a pattern's mean (a bias bowl's constant part) is a level
    d = res.project(frame_at(delta, idx))
    total = float(np.dot(d * d, w))
    if total <= 0:
        return 0.0
    zero = replace(res, data_adu=(res.model_adu + np.broadcast_to(delta, res.data_adu.shape)).astype(np.float32),
                   _flat=res.shared_levels())  # the same fitted pixels and templates: only the data changed
    big, _ = block_chi2(zero)
    return big / total


def score_heldout(res: Residuals, cands: list[Candidate], progress=None) -> None:
    """The held-out delta of the contenders (at most HELDOUT_CANDIDATES, best delta BIC first)."""
    reg = registry()
    for c in sorted((c for c in cands if c.contender), key=lambda c: c.fit.delta_bic)[:HELDOUT_CANDIDATES]:
        sig = reg[c.fit.effect].signature if c.fit.effect in reg else None
        if sig is None or not hasattr(sig, "score"):
            continue
        t0 = time.perf_counter()
        try:
            c.heldout = heldout_delta(sig, res, c.fit.effect, c.fit)
        except Exception as exc:  # noqa: BLE001
            c.implausible = f"cannot be scored on held-out pixels ({type(exc).__name__}: {exc})"
        c.seconds += time.perf_counter() - t0
        if progress is not None:
            progress(f"{c.fit.effect} (held out)")
    res._flat.pop("heldout_folds", None)  # the folds every candidate shared (detector.signatures._folds)


def _of_light(c: Candidate) -> bool:
    """The candidate multiplies the light only: its effect acts at the RESPONSE stage and nowhere else
    (vignetting, PRNU, a mosaic, dead pixels, a flat map; not column defects, which add dark charge too)."""
    cls = registry().get(c.fit.effect)
    return cls is not None and set(cls.stages) == {Stage.RESPONSE}


def rank(cands: list[Candidate], light_source: str = "") -> list[Candidate]:
    """Best first: the significant candidates by their held-out score (delta BIC where there is none), then
    the others that are plausible and not rejected, then the implausible and the rejected, each by delta
    BIC. Twins (as good on held-out pixels) go by delta BIC (fewer parameters for the same fit first); on a
    flat-screen frame (``light_source`` "flat"), whose uniform light cannot tell a response from added charge,
    a response comes first: a flat's pattern is far more often the optics' or the pixels' response
    (vignetting, dust, a mosaic) than a light the screen lets through or a glow as bright as its light."""
    out = sorted(cands, key=lambda c: (0 if c.significant else 1 if c.plausible and not c.rejected else 2,
                                       c.score if c.significant else c.fit.delta_bic))
    sig = [c for c in out if c.significant]
    twins = indistinguishable(sig)
    if twins:
        flat = light_source == "flat"
        group = sorted([sig[0], *twins], key=lambda c: (flat and not _of_light(c), c.fit.delta_bic))
        rest = [c for c in out if c not in group]
        out = group + rest
    return out


def source_candidates(res: Residuals, truth, scene) -> list[Candidate]:
    """Candidates of the scene's sources (an object's light curve, :mod:`.sources`), as :class:`Candidate`;
    ``seconds`` is each one's fit and chi2."""
    out = []
    t0 = time.perf_counter()
    for fit in light_curve_candidates(res, truth, scene):
        chi2 = chi2_after(res, fit)
        out.append(Candidate(fit, chi2, time.perf_counter() - t0))
        t0 = time.perf_counter()
    return out


#: a significant candidate whose score is within this fraction of the best one's (both held-out scores,
#: of a different effect) cannot be told apart from it on this frame
TWIN_FRACTION = 0.02


def indistinguishable(sig: list[Candidate]) -> list[Candidate]:
    """The significant candidates after the first whose held-out score is as good as the first's (within
    TWIN_FRACTION, and within the scores' own scatter ~ sqrt(2 |score|)): a multiplicative fall-off and an
    additive light on a uniform flat, kTC noise and a symmetric DSNU on one dark."""
    if len(sig) < 2 or sig[0].heldout is None:
        return []
    best = sig[0].heldout
    tol = max(TWIN_FRACTION * abs(best), 2 * np.sqrt(2 * abs(best)))
    return [c for c in sig[1:] if c.heldout is not None and c.heldout - best <= tol]


def verdict(cands: list[Candidate], morphology: dict | None = None) -> str:
    """One sentence for the report: the most likely missing effect (significant, plausible, better on
    held-out pixels), or that no catalogue effect explains the residual and what the residual looks like."""
    sig = [c for c in cands if c.significant]
    if sig:
        best = sig[0]
        held = f", held-out {best.heldout:.4g}" if best.heldout is not None else ""
        twins = indistinguishable(sig)
        also = (f"; the data cannot tell it apart from {', '.join(c.fit.effect for c in twins)} (their held-out "
                "scores are as good)") if twins else ""
        return (f"most likely missing: {best.fit.effect} (delta BIC {best.fit.delta_bic:.4g}{held}): "
                f"{best.fit.explanation}{also}")
    named = [c for c in cands if c.fit.delta_bic < SIGNIFICANT_DELTA_BIC]
    why = ""
    if named:
        c = named[0]
        reason = c.rejected or c.implausible or (
            f"it removes only {100 * c.explains:.0f} % of the large-scale structure" if c.explains is not None
            and c.explains < MIN_EXPLAINED else
            f"it removes only {100 * c.excess_share:.2g} % of the excess chi2" if c.excess_share is not None
            and c.excess_share < MIN_EXCESS_SHARE else
            f"it removes only {100 * c.support_share:.2g} % of the excess chi2 where it acts: what is wrong there is "
            "something else, or more" if c.support_share is not None and c.support_share < MIN_SUPPORT_SHARE
            else f"it does not improve the pixels it was not fitted on (held-out "
            f"{c.heldout:.3g})" if c.heldout is not None else "")
        why = f" ({c.fit.effect} fits but is not credible: {reason})" if reason else ""
    if morphology and morphology.get("significant"):
        return ("no catalogue effect explains the residual" + why + "; what is missing looks like "
                + morphology["explanation"])
    return "no missing effect was found: no candidate improves the fit significantly (delta BIC < -10)" + why
