"""The diagnosis policy: every threshold the judge uses, as one named, documented field.

A name is a claim about physics, and the judge (:mod:`.judge`) makes it only when the evidence passes the
thresholds held here. Each field says what it thresholds, its unit and *why it has its value*: the DESIGN
contract, a calibration (the false-alarm rate of the whole chain on null frames made by an independent
textbook camera chain, docs/null_calibration.md), or physics (what no real camera does). None was set by
looking at one case.

``newtsim diagnose --policy FILE`` reads a TOML or JSON table of overrides (``[policy]`` or top level):
unknown keys and values of the wrong type are refused with the file, the key and what was expected.
Every ``diagnose --json`` records the policy it used (``policy``, :meth:`DiagnosisPolicy.to_json`);
docs/diagnosis_policy.md is generated from this module (:func:`markdown_table`;
``python -m scenes.app.compare.policy`` rewrites it and a test checks that it is up to date).
"""

from __future__ import annotations

import json
import math
import sys
import warnings
from dataclasses import MISSING, asdict, dataclass, field, fields, replace
from pathlib import Path

from detector.errors import DetectorError
from detector.significance import (
    DETECTION_SIGMA,
    EXPLAINS_MOST,
    MAX_DEFECT_FRACTION,
    SCALE_TOLERANCE,
    STRONG_EVIDENCE,
    STRUCTURE_SIGMA,
)

#: why a field has its value: the DESIGN contract, the null calibration, physics, a property of the test, or a
#: budget (a cost of the search, not a threshold: how many contenders are scored)
BASES = ("contract", "calibration", "physics", "statistics", "budget")
#: fields that ask the same question share one value (the significance levels, EXPLAINS_MOST and SCALE_TOLERANCE
#: of detector/significance.py): a refitted scale of the scene or of its noise is a finding beyond SCALE_TOLERANCE's
#: relative change (parameter_scale_tolerance, noise_scale_tolerance); a candidate may worsen the sources'
#: photometry by as much and no more (stars_worse_ln)
#: ... and this: a non-linearity is a finding when the response law departs from a line by this fraction, at full
#: well or within the frame's own range (min_nonlinearity_at_full_well, min_nonlinearity_in_range): 0.1 %, the
#: linearity error a photon-transfer measurement resolves (Janesick 2007, Photon Transfer, ch. 5; EMVA 1288
#: release 4.0, sect. 6.9)
LINEARITY_RESOLVED = 0.001


def _f(default, unit: str, basis: str, doc: str):
    assert basis in BASES, basis
    return field(default=default, metadata={"unit": unit, "basis": basis, "doc": doc})


#: fields of earlier policies that no longer exist: a policy file naming one still loads (the field ignored,
#: with a warning saying what replaced it)
RETIRED: dict[str, str] = {
    "stars_ok_ln": "the photometry test asks the stars' own worsening to be significant (DETECTION_SIGMA of its "
                   "standard error, candidates.photometry_worsening) instead of an absolute bar",
    "stars_min": "the photometry test's standard error (candidates.photometry_worsening) says when there are "
                 "too few stars to show a worsening",
    "psf_min_stars": "the PSF's width is refitted when its likelihood scan's standard error resolves "
                     "psf_width_tolerance at DETECTION_SIGMA (parameters.width_error), not from a count of stars",
    "noise_floor_fraction": "the floor of the noise-excess test is DETECTION_SIGMA standard errors of the bulk's "
                            "excess variance (candidates.robust_excess_error), not a fraction of the model's",
    "overfit_chi2_per_dof": "a noise-only candidate's chi2/dof bar is 1 / noise_excess_factor: the model's whole "
                            "variance with the claim at most that factor times the residual's (candidates.overfit)",
    "min_nonlinearity_signal_fraction": "a non-linearity is judged by its change within the frame's own signal "
                                        "range (min_nonlinearity_in_range) however high the frame reaches in the "
                                        "well (floors.signal_range_floor), not spared it above a fraction of the "
                                        "full well",
}


@dataclass(frozen=True)
class DiagnosisPolicy:
    """Every threshold of the diagnosis's judge (see the module docstring). Frozen: a policy is a value."""

    # -- what "significant" means: one meaning for single frames, large frames and series ------------------------
    significant_delta_bic: float = _f(
        -STRONG_EVIDENCE, "delta BIC", "contract",
        "a candidate is significant only below this delta BIC (DESIGN.md; 'very strong' evidence, Kass & Raftery "
        "1995, JASA 90, 773)")
    significant_heldout: float = _f(
        -40.0, "delta -2 ln L", "calibration",
        "a candidate must improve the pixels its fit did not see (summed over the two folds) by at least this "
        "much. Set on 169 textbook null frames and series (docs/null_calibration.md, both cameras, every frame "
        "class), whose most negative held-out delta of a candidate past every other gate was -29.9 (IMX411 "
        "binned 8x8, three ADC codes of noise); confirmed on 315 more from a fresh seed: -32.8 apart from one "
        "kTC noise of 4e-6 e- at -40.6, now below the noise floor (min_extra_noise_fraction)")
    heldout_candidates: int = _f(
        8, "candidates", "budget",
        "contenders (best delta BIC first) scored on held-out pixels: the cost of the cross-validation")
    twin_fraction: float = _f(
        0.05, "1", "calibration",
        "a second significant candidate whose held-out score is within this fraction of the best's (or within "
        "2 sqrt(2|score|), the score's own scatter) cannot be told apart from it. On 440 development random forms "
        "(docs/diagnose_validation.md) the right name trailed a wrong first one by at most 4.4 % of its held-out "
        "score in 25 of the 33 cases where both were significant, and by 19 % or more in the others: forms that "
        "differ by less explain the same pixels")

    # -- a name must take what is wrong, not a corner of it ---------------------------------------------------------
    structure_sigma: float = _f(
        STRUCTURE_SIGMA, "sigma", "calibration",
        "the frame's large-scale structure (block chi2 beyond its dof) is significant above this many standard "
        "deviations of its chi2")
    min_explained: float = _f(
        EXPLAINS_MOST, "1", "physics",
        "where that structure is significant, a candidate changing the mean must remove at least this share "
        "of it: the missing effect explains most of what is wrong, not a corner of it")
    excess_sigma: float = _f(
        DETECTION_SIGMA, "sigma", "statistics",
        "the frame's whole excess chi2 (levels refitted) is significant above this many standard deviations")
    min_excess_share: float = _f(
        0.02, "1", "physics",
        "where that excess is significant, a pixel candidate must remove at least this share of it")
    min_support_share: float = _f(
        EXPLAINS_MOST, "1", "physics",
        "a candidate that changes the mean must remove at least this share of the excess chi2 over the pixels "
        "it acts on (where that excess is significant)")
    support_mass: float = _f(
        0.9, "1", "statistics",
        "the pixels a candidate acts on: its largest weighted squared changes, carrying this share of their sum")
    support_sigma: float = _f(
        STRUCTURE_SIGMA, "sigma", "statistics",
        "the excess over those pixels is significant above this many standard deviations of its chi2")

    # -- a fit that only hides a residual -------------------------------------------------------------------------
    noise_excess_factor: float = _f(
        3.0, "1", "statistics",
        "a noise-only candidate may claim at most this many times the variance the bulk of the pixels shows "
        "beyond the model's (median squared residual), or than DETECTION_SIGMA standard errors of that excess "
        "where the bulk shows none it resolves (candidates.robust_excess_error); nor make the model's whole "
        "variance this many times the residual's (chi2/dof below its inverse; candidates.overfit)")
    stars_worse_ln: float = _f(
        SCALE_TOLERANCE, "|ln flux ratio|", "physics",
        "a candidate reshaping the sources may worsen the bright stars' median |ln(data/model flux)| by at "
        "most this much (SCALE_TOLERANCE: a flux error the size of a zero point that is itself a finding), the "
        "stars' own change being a worsening beyond DETECTION_SIGMA of its standard error "
        "(candidates.photometry_worsening)")
    sample_worse: float = _f(
        STRONG_EVIDENCE, "delta -2 ln L", "contract",
        "large frames: a candidate fitted on the binned frame must not worsen the full-resolution band sample "
        "by more than this (the delta BIC scale)")
    consistency_factor: float = _f(
        3.0, "1", "physics",
        "series: one piece of hardware fitted frame by frame may not differ in strength by more than this "
        "factor between frames")

    # -- a name must beat a description ---------------------------------------------------------------------------
    min_catch_all_share: float = _f(
        EXPLAINS_MOST, "1", "physics",
        "a physical candidate is named only when, on the same held-out folds, it predicts at least this share "
        "of what the residual's empirical map (the catch-all description) predicts: the missing effect "
        "explains most of what is wrong, as min_explained asks of the large-scale structure")

    # -- is a number of the scene wrong? (parameter candidates) ----------------------------------------------------
    parameter_scale_tolerance: float = _f(
        SCALE_TOLERANCE, "1", "physics",
        "a refitted scale of the scene (the sources' zero point, the sky, the dark current) is a finding when "
        "it differs from 1 by more than this: a model knows its lamp, transparency and temperature to a few "
        "per cent (the validation's measured cameras differ by 1.5-3 %), a zero point 10 % off is an error of "
        "the scene; the default is also the dark level's prior width (a fraction of it) in the share of a dark "
        "frame's one level between bias and dark (model.level_sd)")
    parameter_bias_tolerance_adu: float = _f(
        2.0, "ADU", "physics",
        "a refitted bias offset is a finding beyond this many ADU per read: a bias drifts by a fraction of an "
        "ADU to an ADU between frames (and a rounding convention is 0.5 ADU); the default is also the bias's prior "
        "width by which a dark frame's one level is shared between bias and dark for its shot noise (model.level_sd)")
    psf_width_tolerance: float = _f(
        math.sqrt(1.0 + SCALE_TOLERANCE) - 1.0, "1", "physics",
        "a refitted PSF FWHM is a finding when it differs from the scene's by more than this fraction: a PSF "
        "conserves the flux, so its peak goes as 1 / FWHM^2 and a FWHM off by this much changes every star's "
        "peak by SCALE_TOLERANCE, a scale error that is itself a finding (sqrt(1 + SCALE_TOLERANCE) - 1, 4.9 %; "
        "a Moffat's beta is held to the same fraction)")
    noise_scale_tolerance: float = _f(
        SCALE_TOLERANCE, "1", "physics",
        "a gain or read noise refitted from the residual's variance is a finding beyond this relative change")

    # -- physical effect-size floors ------------------------------------------------------------------------------
    min_nonlinearity_at_full_well: float = _f(
        LINEARITY_RESOLVED, "1", "physics",
        "a non-linearity smaller than this at full well (0.1 %) is not a finding: photon-transfer curves of "
        "scientific CCD/CMOS measure 0.1-1 % at best (Janesick 2007, Photon Transfer, ch. 5)")
    min_nonlinearity_in_range: float = _f(
        LINEARITY_RESOLVED, "1", "physics",
        "a non-linearity is a finding when, within the frame's own signal range (its median to its brightest "
        "fitted pixel), the fitted law changes the response by at least this fraction (0.1 %, the linearity error "
        "a photon-transfer measurement resolves, Janesick 2007 ch. 5; EMVA 1288 release 4.0 sect. 6.9), however "
        "high the frame reaches in the well; its size at full well, beyond that range, is an extrapolation the "
        "pixels cannot check, so the frame's range is what is asked, and a power law is referenced at the frame's median signal (a real "
        "SBIG dark: gamma 1.027 from 67 e- of a 133 000 e- well, referenced at half the well, lowered the whole "
        "dark by 16 % when rendered)")
    min_extra_noise_fraction: float = _f(
        0.1, "1", "physics",
        "an extra white read-out noise (kTC, a read noise above the data sheet) smaller than this fraction of the "
        "camera's read noise (rms, per read) is not a finding: it adds 1 % to the read noise's variance, which a "
        "camera characterisation measures to a few per cent (EMVA 1288 dark noise); the one false alarm of 315 "
        "textbook nulls was such a noise, 4e-6 e- (docs/null_calibration.md)")
    max_cosmic_rate_factor: float = _f(
        50.0, "1", "physics",
        "cosmic rays at more than this many times the physical flux of the scene's environment are not cosmic "
        "rays (sea-level muons ~1 /cm^2/min, PDG; natural radioactivity of a camera's window and housing adds "
        "events, a few times the muon rate at most; a rate 100x the physical one is a pattern of bright pixels, "
        "not particles)")
    max_defect_fraction: float = _f(
        MAX_DEFECT_FRACTION, "1", "physics",
        "hot or dead pixels (or columns) on more than this fraction of the sensor are not defects: camera data "
        "sheets (EMVA 1288) give 1e-5 to 1e-3 of the pixels and a grade-2 CCD a few tens of its thousands of "
        "columns; the count is extrapolated from the frame to the sensor, so the floor leaves a margin")
    parameter_explained_share: float = _f(
        EXPLAINS_MOST, "1", "physics",
        "a level candidate whose deviation shrinks by more than this share once the best significant effect is "
        "in the model is that effect's doing (its form differs from the plugin's, so some remains): the "
        "effect is named first and the next round refits the number")
    hot_in_dark_fraction: float = _f(
        EXPLAINS_MOST, "1", "physics",
        "when the scene has the user's dark, a hot-pixel candidate needs at least this share of its pixels hot "
        "in that dark (a hot pixel is hot in every frame): most of the pixels it claims (EXPLAINS_MOST)")

    def to_json(self) -> dict:
        """The values, by name (every ``diagnose --json`` records them under ``policy``)."""
        return asdict(self)

    def with_overrides(self, table: dict, file: str = "<policy>") -> DiagnosisPolicy:
        """A copy with ``table``'s values; an unknown key or a value of the wrong type is a one-line error; a
        retired field (:data:`RETIRED`) is ignored with a warning that names what replaced it."""
        known = {f.name: f for f in fields(self)}
        changes = {}
        for key, value in table.items():
            if key in RETIRED and key not in known:
                warnings.warn(f"{file}: policy field {key!r} is retired and ignored: {RETIRED[key]}", stacklevel=2)
                continue
            if key not in known:
                close = sorted(known, key=lambda k: -_similarity(k, key))[:3]
                raise DetectorError(f"unknown policy field {key!r}", file=file, key=key,
                                    expected="one of the DiagnosisPolicy fields (docs/diagnosis_policy.md), e.g. "
                                    + ", ".join(close))
            want = type(known[key].default)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or (want is int and
                                                                                  not float(value).is_integer()):
                raise DetectorError(f"policy field {key} = {value!r} is not a number", file=file, key=key,
                                    expected=f"a {'whole number' if want is int else 'number'} "
                                    f"[{known[key].metadata['unit']}]")
            changes[key] = want(value)
        return replace(self, **changes)


def _similarity(a: str, b: str) -> int:
    return len(set(a.split("_")) & set(b.split("_")))


#: the policy the judge uses unless told otherwise
DEFAULT_POLICY = DiagnosisPolicy()


def load_policy(path: str | Path | None) -> DiagnosisPolicy:
    """The default policy with the overrides of a TOML or JSON file (``[policy]`` table or top level)."""
    if path is None:
        return DEFAULT_POLICY
    p = Path(path)
    if not p.is_file():
        raise DetectorError("policy file not found", file=str(p), expected="a TOML or JSON table of policy fields")
    try:
        if p.suffix.lower() == ".json":
            table = json.loads(p.read_text())
        else:
            import tomllib
            table = tomllib.loads(p.read_text())
    except (ValueError, UnicodeDecodeError) as exc:
        raise DetectorError(f"cannot read the policy ({exc})", file=str(p), expected="TOML or JSON") from None
    if not isinstance(table, dict):
        raise DetectorError("the policy is not a table", file=str(p), expected="a table of policy fields")
    if isinstance(table.get("policy"), dict):
        table = table["policy"]
    return DEFAULT_POLICY.with_overrides(table, file=str(p))


def markdown_table(policy: DiagnosisPolicy = DEFAULT_POLICY) -> str:
    """docs/diagnosis_policy.md: every field, its value, unit, basis and meaning."""
    lines = ["# The diagnosis policy", "",
             "Generated from `scenes/app/compare/policy.py` (`python -m scenes.app.compare.policy`); do not edit.",
             "Every threshold the judge uses, its unit and the basis of its value: the DESIGN `contract`, a",
             "`calibration` on null frames of the independent textbook chain (docs/null_calibration.md),",
             "`physics` (what no real camera does) or `statistics` (a property of the test itself); a `budget` is",
             "a cost of the search (how many contenders are scored), not a threshold.",
             "`newtsim diagnose --policy FILE` overrides any of them; `diagnose --json` records the policy used.",
             "", "| field | value | unit | basis | meaning |", "|---|---|---|---|---|"]
    for f in fields(policy):
        v = getattr(policy, f.name)
        lines.append(f"| `{f.name}` | {v:g} | {f.metadata['unit']} | {f.metadata['basis']} | "
                     f"{f.metadata['doc']} |")
    lines.append("")
    lines.append(f"{len(fields(policy))} fields.")
    return "\n".join(lines) + "\n"


DOC_PATH = Path(__file__).resolve().parents[3] / "docs" / "diagnosis_policy.md"
#: the docs' generated threshold audit (examples/diagnose/threshold_audit.py --write) follows this line; the
#: policy's table is what precedes it
AUDIT_MARKER = "<!-- threshold audit: generated by examples/diagnose/threshold_audit.py --write; do not edit -->"

assert all(f.default is not MISSING for f in fields(DiagnosisPolicy))

if __name__ == "__main__":  # pragma: no cover - the docs generator
    old = DOC_PATH.read_text() if DOC_PATH.is_file() else ""
    tail = AUDIT_MARKER + old.partition(AUDIT_MARKER)[2] if AUDIT_MARKER in old else ""
    DOC_PATH.write_text(markdown_table() + ("\n" + tail if tail else ""))
    sys.stdout.write(f"wrote {DOC_PATH}\n")
