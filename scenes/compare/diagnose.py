"""Which physical effect does the model lack? Fit every absent effect's signature and rank by delta BIC.

For each registered effect (built-in catalogue and user plugins) that the scene does not switch on and
that declares a ``signature`` (:mod:`detector.diagnosis`), the signature fits the effect's own parameters
to the residuals under the model's noise; the fitted parameters are validated by the plugin's parameter
model. Candidates are ranked by ``delta_BIC = delta(-2 ln L) + k ln n`` (Schwarz 1978); the contract's
significance threshold is ``delta_BIC < -10`` ("very strong" evidence, Kass & Raftery 1995, JASA 90, 773).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from detector import registry
from detector.diagnosis import Fit, Residuals

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
    the model's background, :func:`scenes.compare.analysis.star_photometry`) are measured wrong. A blur that
    lowers the pixel chi2 of a crowded field by spreading its sources towards what the model lacks (blends,
    unresolved stars) fails this; a real blur, elongation or shift leaves the stars right or makes them
    right."""
    from dataclasses import replace

    from .analysis import star_photometry

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
    from .sources import source_candidates as fits

    out = []
    t0 = time.perf_counter()
    for fit in fits(res, truth, scene):
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


def apply_candidate(scene, cand: dict, path: str | Path, measured: str | Path | None = None) -> Path:
    """Write ``scene`` with the candidate's effect and fitted parameters added (a new scene TOML).

    The diagnosis fits every candidate together with the global levels the model only knows roughly
    (:meth:`detector.diagnosis.Residuals.levels`: light, sky background, bias offset, dark level). The new
    scene therefore carries the levels that go with the effect: with ``measured`` given, the levels that
    frame measures are refitted with the new effect in the model (weighted least squares,
    :func:`refit_levels`) and written to the scene keys that hold them (``[sky] flat_e_per_s``,
    ``[sky] background_mag_arcsec2``, ``[detector] bias_adu``); each change is noted in the file's header
    comment. A multiplicative effect such as vignetting would otherwise lower the whole model."""
    import tomli_w

    data = scene.model_dump(mode="json", exclude_none=True, exclude_unset=True)
    if cand["effect"] == "light_curve":  # a source's property: into its [[objects]] table
        data["objects"][cand["params"]["object"]]["light_curve"] = cand["params"]["light_curve"]
        added = f"objects[{cand['params']['object']}].light_curve"
    else:
        data.setdefault("effects", {})[cand["effect"]] = cand["params"]
        added = f"[effects.{cand['effect']}]"
    p = Path(path)
    notes = []
    if measured is not None:
        data, notes = carry_levels(data, refit_levels(p, data, measured), scene)
    p.write_text(f"# written by newtsim diagnose --apply: added {added}\n"
                 f"# {cand['explanation']}\n" + "".join(f"# and {n}\n" for n in notes) + tomli_w.dumps(data))
    return p


#: level changes below these are not written back (relative for scales, ADU for the bias offset)
LEVEL_SCALE_TOL, LEVEL_OFFSET_TOL_ADU = 1e-4, 0.01


def refit_levels(path: Path, data: dict, measured) -> dict[str, float]:
    """The global levels the scene ``data`` (written to ``path``) needs to match ``measured``.

    A level is refitted from the frame that measures it, on the pixels where the model's sources add less
    than one sigma to its background (misplaced or mis-sized stars would pull a sky level): the light level
    (flat screen) or the sky level from a light frame, the bias offset and the dark level from a dark or bias frame (a light frame cannot
    separate a bias offset from its light: on a vignetted flat screen the least squares trade hundreds of
    ADU of bias against a per cent of light). Weighted least squares of the residual on those templates,
    degenerate ones dropped in :attr:`Residuals.LEVELS` order. Returns ``{level name: coefficient}``
    (scales are relative changes, the offset is in ADU)."""
    import tomli_w

    from detector.diagnosis import LEVEL_DEGENERACY, _at, _independent

    from ..scene import load_scene
    from .model import build_model, read_measurement, residuals

    path.write_text(tomli_w.dumps(data))
    sc = load_scene(str(path))
    model = build_model(sc, realisation=False)
    d, _ = read_measurement(measured, model)
    res = residuals(d, model)
    idx, r, w = res.flat()
    if res.background_adu is not None:  # the levels from the background's pixels: a misfit star is not sky
        sources = (res.model_adu - res.background_adu).ravel()[idx] * np.sqrt(w)
        keep = sources < 1.0
        idx, r, w = idx[keep], r[keep], w[keep]
    if not idx.size:
        return {}
    if sc.exposure.frame == "light":
        if sc.sky.flat_e_per_s:
            wanted = [0]  # the flat screen: the whole photo-signal
        elif sc.sky.background_mag_arcsec2 is not None:
            wanted = [1]  # the sky: the uniform part of the light
        else:
            return {}
    else:
        # a dark or bias frame: the bias offset. A uniform dark level is the same in one dark frame (it is
        # kept as the bias, as Residuals.levels does), and the dark template holds glow, DSNU and bias
        # structure too: scaling the dark current by its fit would be wrong
        wanted = [2]
    temps = res.level_templates()
    x = np.stack([_at(temps[i], res.data_adu.shape, idx) for i in wanted])
    xw = x * w
    g = xw @ x.T
    keep = _independent(g, tol=LEVEL_DEGENERACY)
    if not keep:
        return {}
    coef = np.linalg.solve(g[np.ix_(keep, keep)], (xw @ r)[keep])
    return {res.LEVELS[wanted[k]]: float(c) for k, c in zip(keep, coef)}


def carry_levels(data: dict, levels: dict[str, float], scene) -> tuple[dict, list[str]]:
    """Write refitted global levels into the keys of the scene ``data`` (a dump of ``scene``) that hold
    them. Returns (scene data, notes)."""
    notes, sensor = [], scene.sensor()
    sky, det = data.setdefault("sky", {}), data.setdefault("detector", {})
    c = levels.get("light_scale", 0.0)
    if abs(c) > LEVEL_SCALE_TOL and sky.get("flat_e_per_s") and 1 + c > 0:
        sky["flat_e_per_s"] = round(float(sky["flat_e_per_s"]) * (1 + c), 6)
        notes.append(f"the flat-screen level refitted: flat_e_per_s x {1 + c:.5f}")
    c = levels.get("background_scale", 0.0)
    if abs(c) > LEVEL_SCALE_TOL and 1 + c > 0.05:
        mag = scene.sky.background_mag_arcsec2
        sky["background_mag_arcsec2"] = round(float(mag) - 2.5 * float(np.log10(1 + c)), 5)
        notes.append(f"the sky level refitted: x {1 + c:.5f} ({mag:.4g} -> {sky['background_mag_arcsec2']:.5g} "
                     "mag/arcsec^2)")
    c = levels.get("offset_adu", 0.0) / bias_per_output_adu(sensor)
    if abs(c) > LEVEL_OFFSET_TOL_ADU:
        det["bias_adu"] = round(max(float(sensor.bias_adu) + c, 0.0), 3)
        notes.append(f"the bias level refitted: {sensor.bias_adu:.4g} -> {det['bias_adu']:.6g} ADU")
    return data, notes


def bias_per_output_adu(sensor) -> float:
    """Output ADU per ADU of ``bias_adu``: a CMOS sums (or averages) ``b^2`` digitised reads, each with the
    bias; a CCD reads a binned pixel once (and an average divides that by ``b^2``)."""
    b2 = sensor.binning ** 2
    if sensor.binning_mode == "sum":
        return float(b2) if sensor.kind != "ccd" else 1.0
    return 1.0 if sensor.kind != "ccd" else 1.0 / b2


# --- the ledger of rounds ------------------------------------------------------------------------------------

def ledger_path(scene_path: str | Path) -> Path:
    p = Path(scene_path)
    return p.with_name(p.stem + ".ledger.json")


def update_ledger(scene_path: str | Path, new_scene: str | Path | None, measured: str, compare_summary: dict,
                  best: dict | None) -> tuple[Path, list[dict]]:
    """Append this round to the ledger of the scene (continuing the input scene's ledger, if any) and write
    it next to the new scene (or the input scene when nothing is applied). Returns (path, rounds)."""
    src = ledger_path(scene_path)
    rounds = json.loads(src.read_text())["rounds"] if src.is_file() else []
    # the rounds of this measurement, up to (not including) a re-run of this scene
    rounds = [r for r in rounds if r.get("measured") == str(measured)]
    rounds = [r for r in rounds if r["scene"] != str(scene_path)]
    rounds.append({"round": len(rounds) + 1, "scene": str(scene_path), "measured": str(measured),
                   "chi2_per_dof": compare_summary["chi2_per_dof"], "misfit": compare_summary["misfit"],
                   "applied": best["effect"] if best else None, "params": best["params"] if best else None,
                   "delta_bic": best["delta_bic"] if best else None})
    out = ledger_path(new_scene) if new_scene else src
    out.write_text(json.dumps({"rounds": rounds}, indent=2) + "\n")
    return out, rounds


def plot_ledger(rounds: list[dict], path: str | Path) -> Path:
    """chi2/dof and misfit round by round, each point labelled with the effect added after it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = [r["round"] for r in rounds]
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.4), dpi=90)
    for a, key, label in ((ax[0], "chi2_per_dof", "chi2 / dof"), (ax[1], "misfit", "misfit (standardised)")):
        a.plot(n, [max(r[key], 1e-3) for r in rounds], "o-")
        a.set_yscale("log")
        a.set_xlabel("round")
        a.set_ylabel(label)
        for r in rounds:
            if r.get("applied"):
                a.annotate(f"+{r['applied']}", (r["round"], max(r[key], 1e-3)), fontsize=7, xytext=(3, 3),
                           textcoords="offset points")
    ax[0].axhline(1.0, color="grey", lw=0.8, ls="--")
    fig.suptitle("compare / diagnose / apply: the error round by round", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return Path(path)
