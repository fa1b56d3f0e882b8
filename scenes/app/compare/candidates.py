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
from detector.signatures import Fit, Residuals

from .sources import light_curve_candidates
from .statistics import star_photometry

#: a candidate with delta BIC at or above this is not significant (DESIGN.md contract)
SIGNIFICANT_DELTA_BIC = -10.0
#: chi2/dof after (levels refitted) below which a candidate that only adds variance is rejected: it explains
#: a structured residual by making the model's noise so large that everything fits (a correct noise model
#: leaves chi2/dof ~ 1, within a few sqrt(2/n))
OVERFIT_CHI2_PER_DOF = 0.5


@dataclass
class Candidate:
    fit: Fit
    chi2_per_dof: float
    seconds: float
    rejected: str = ""  #: why a candidate with a large delta BIC is not physical ("" if it is)

    @property
    def significant(self) -> bool:
        return self.fit.delta_bic < SIGNIFICANT_DELTA_BIC and not self.rejected

    def to_json(self) -> dict:
        f = self.fit
        return {"effect": f.effect, "params": f.params, "chi2_per_dof": self.chi2_per_dof,
                "delta_bic": f.delta_bic, "delta_m2lnl": f.delta_m2lnl, "k": f.k, "explanation": f.explanation,
                "kind": type(registry()[f.effect].signature).__name__ if f.effect in registry() else "",
                "significant": self.significant, "rejected": self.rejected, "variant": f.note,
                "seconds": self.seconds}


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
        r = r - np.asarray(fit.delta_adu, np.float64).ravel()[idx]
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
        out.append(Candidate(fit, chi2, seconds, why))
    return rank(out), problems


def rank(cands: list[Candidate]) -> list[Candidate]:
    """Best first: the accepted candidates by delta BIC, then the rejected ones by delta BIC."""
    return sorted(cands, key=lambda c: (bool(c.rejected), c.fit.delta_bic))


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


def verdict(cands: list[Candidate]) -> str:
    """One sentence for the report."""
    sig = [c for c in cands if c.significant]
    if not sig:
        return "no missing effect was found: no candidate improves the fit significantly (delta BIC < -10)"
    best = sig[0].fit
    return f"most likely missing: {best.effect} (delta BIC {best.delta_bic:.4g}): {best.explanation}"
