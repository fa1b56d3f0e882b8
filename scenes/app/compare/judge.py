"""The judge: which candidate, if any, the diagnosis names. One judge for single frames, large frames and series.

Candidates come from three kinds of evidence, all :class:`Candidate` objects:

* ``parameter``: a number of the scene is wrong (the sources' zero point, the sky, the PSF's width, the bias,
  the dark current; :mod:`.parameters`): asked first, "is a number of the scene wrong?" before "is an
  effect missing?";
* ``effect``: a catalogue effect (or a user's plugin) fitted through its signature (:mod:`.candidates`,
  :mod:`.optics_candidates`, :mod:`.sources`);
* ``description``: the residual's own empirical map (:mod:`detector.morphology`), the catch-all a name must
  beat on held-out pixels.

Every threshold is a field of the :class:`~.policy.DiagnosisPolicy` the candidate carries; every reason a
candidate is not named is a gate code of :data:`GATES` (as photutils keeps its flags) with its one-line
reason. A candidate is *significant* when it fails no gate; the verdict names the best significant one, or
says that nothing is missing, or describes what no candidate explains.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from detector import registry
from detector.effects.base import Stage
from detector.signatures import Fit

from .policy import DEFAULT_POLICY, DiagnosisPolicy

#: every reason the judge may refuse a name: code -> what it means (the JSON's ``gates``)
GATES: dict[str, str] = {
    "bic": "its delta BIC is not below the policy's significance (significant_delta_bic)",
    "overfit": "it only hides a residual: noise that makes everything fit, or far more noise than the pixels show",
    "stars": "with it the bright stars' photometry is wrong: the light it moves belongs to something else",
    "implausible": "the fitted pattern is not physically this effect (its own structure test)",
    "bound": "a fitted parameter sits at its bound: the form cannot follow the data",
    "floor": "its size is beyond what physics allows for this effect (below the smallest finding, or more "
             "than any camera has)",
    "heldout": "it does not improve the pixels its fit did not see (significant_heldout)",
    "structure": "it removes too little of the frame's large-scale structure (min_explained)",
    "excess": "it removes too little of the frame's excess chi2 (min_excess_share)",
    "support": "it removes too little of the excess where it acts (min_support_share)",
    "catch_all": "the residual's empirical map predicts the held-out pixels better: a description, not this name",
    "dark": "its pixels are not hot in the user's dark frame",
    "kind": "it adds a field whatever the light, and the residual scales with the light (multiplicative)",
    "consistency": "series: one piece of hardware, but its strength differs between frames",
    "sample": "large frame: it worsens the full-resolution band sample",
    "tolerance": "a parameter within the policy's tolerance of the scene's value: not a finding",
    "nested": "beside a rival whose held-out test is blind it explains nothing, and the rival explains what it leaves",
    "richer": "a richer form of the image a simpler candidate makes (a drift's path beyond a smear) whose extra "
              "parameters remove no more than chance: the frame does not tell the two apart",
    "error": "its evidence could not be computed",
}


@dataclass
class Candidate:
    """One candidate fitted to the residuals, with what the judge asks of it.

    ``rejected``: the fit only hides a residual; ``implausible``: the fitted pattern is not physically this
    effect; ``heldout``: delta(-2 ln L) on pixels the fit did not see (None: not scored); ``explains``,
    ``excess_share``, ``support_share``: the shares of what is wrong that it removes (None: not measured);
    ``catch_all_delta``: its held-out score minus the catch-all's (None: not compared). ``codes`` holds the
    gate codes of ``rejected`` / ``implausible`` (set with :meth:`reject` and :meth:`refuse`).
    """

    fit: Fit
    chi2_per_dof: float
    seconds: float
    rejected: str = ""  #: why a candidate with a large delta BIC is not physical ("" if it is)
    implausible: str = ""  #: why the fitted pattern is not this effect ("" if it may be)
    heldout: float | None = None
    explains: float | None = None
    excess_share: float | None = None
    support_share: float | None = None
    catch_all_heldout: float | None = None  #: the catch-all's held-out score on the same folds
    kind: str = "effect"  #: "effect", "parameter" or "description"
    key: str | None = None  #: a parameter's scene key (``psf.fwhm_arcsec``)
    value: float | None = None  #: a parameter's new value
    #: a parameter the frame cannot tell apart from another scene number (a bias offset from a uniform dark
    #: charge on one dark frame): named after the significant effects, with the other key here
    ambiguous: str = ""
    #: a parameter whose evidence, once the best significant effect is in the model, is smaller than that
    #: effect's: still a finding, named after the effect (the next round refits it)
    deferred: str = ""
    policy: DiagnosisPolicy = DEFAULT_POLICY
    codes: dict = field(default_factory=dict)  #: gate code -> reason, for the gates set by the evidence
    #: the effects its signature says this frame cannot tell it from by physics (the same image at another
    #: stage: :meth:`detector.signatures.Signature.untold_from`)
    untold: tuple = ()
    #: its signature found, on the fitted pattern itself, that its law (added or multiplying the light) is its
    #: own and not the other's (:meth:`detector.signatures.Signature.law_told`): the morphology's kind, a
    #: description's, does not overrule it
    law_told: bool = False
    #: one held-out fold sees less than a detection of its change
    #: (:func:`detector.signatures.heldout_blind`): its held-out score tests it neither way
    heldout_blind: bool = False
    #: the side of the checkerboard's blocks its held-out score was taken on when the default ones were blind to
    #: it (:func:`detector.signatures.seeing_block`; None: the default blocks)
    heldout_block: int | None = None

    def __post_init__(self):
        if self.rejected and "overfit" not in self.codes and "stars" not in self.codes:
            self.codes.setdefault("overfit", self.rejected)
        if self.implausible:
            self.codes.setdefault(_implausible_code(self.implausible), self.implausible)

    def reject(self, code: str, why: str) -> None:
        """Refuse the candidate as a fit that only hides a residual (``code`` of :data:`GATES`)."""
        assert code in GATES, code
        if not self.rejected:
            self.rejected = why
        self.codes.setdefault(code, why)

    def refuse(self, code: str, why: str) -> None:
        """Refuse the candidate as not physically this effect (``code`` of :data:`GATES`)."""
        assert code in GATES, code
        if not self.implausible:
            self.implausible = why
        self.codes.setdefault(code, why)

    @property
    def catch_all_delta(self) -> float | None:
        """Its held-out score minus the catch-all's on the same folds (None: not compared)."""
        if self.heldout is None or self.catch_all_heldout is None:
            return None
        return round(float(self.heldout - self.catch_all_heldout), 4)

    @property
    def plausible(self) -> bool:
        return not self.implausible

    @property
    def contender(self) -> bool:
        """Significant by delta BIC and neither rejected nor implausible: worth a held-out score."""
        return (self.fit.delta_bic < self.policy.significant_delta_bic and not self.rejected
                and not self.implausible)

    @property
    def gates(self) -> list[str]:
        """The codes of every gate the candidate fails (empty: it is significant)."""
        return [code for code, _ in gate_reasons(self)]

    @property
    def significant(self) -> bool:
        return not gate_reasons(self)

    @property
    def score(self) -> float:
        """What the ranking sorts by: the held-out delta when there is one, else delta BIC."""
        return self.heldout if self.heldout is not None else self.fit.delta_bic

    def to_json(self) -> dict:
        f = self.fit
        reg = registry()
        reasons = gate_reasons(self)
        out = {"effect": f.effect, "params": f.params, "chi2_per_dof": self.chi2_per_dof,
               "delta_bic": f.delta_bic, "delta_m2lnl": f.delta_m2lnl, "k": f.k, "explanation": f.explanation,
               "kind": self.kind,
               "signature": type(reg[f.effect].signature).__name__ if f.effect in reg else "",
               "significant": not reasons, "gates": [c for c, _ in reasons],
               "gate_reasons": {c: why for c, why in reasons},
               "rejected": self.rejected, "plausible": self.plausible,
               "implausible_because": self.implausible, "heldout_delta": self.heldout,
               "catch_all_delta": self.catch_all_delta,
               "explains_structure": self.explains, "explains_excess": self.excess_share,
               "explains_where_it_acts": self.support_share, "variant": f.note,
               "seconds": self.seconds}
        if self.untold:
            out["same_image_as"] = list(self.untold)
        if self.heldout_blind:
            out["heldout_blind"] = True
        if self.heldout_block is not None:
            out["heldout_block_px"] = self.heldout_block
        if self.kind == "parameter":
            out["key"], out["value"] = self.key, self.value
            if self.ambiguous:
                out["cannot_tell_from"] = self.ambiguous
            if self.deferred:
                out["deferred"] = self.deferred
        return out


def _implausible_code(why: str) -> str:
    return "bound" if "sits at its bound" in why else "implausible"


def gate_reasons(c: Candidate) -> list[tuple[str, str]]:
    """Every gate ``c`` fails, as (code, one-line reason), in the order the judge asks them."""
    p = c.policy
    out = list(c.codes.items())
    said = {why for _, why in out}
    if c.rejected and c.rejected not in said:  # set directly by an older caller: still a gate
        out.append(("overfit", c.rejected))
    if c.implausible and c.implausible not in said:
        out.append((_implausible_code(c.implausible), c.implausible))
    if c.fit.delta_bic >= p.significant_delta_bic and "tolerance" not in c.codes:
        out.insert(0, ("bic", f"delta BIC {c.fit.delta_bic:.4g} is not below {p.significant_delta_bic:g}"))
    if out:
        return out
    if c.heldout is not None and c.heldout >= p.significant_heldout:
        out.append(("heldout", (f"held-out delta {c.heldout:.4g} is not below {p.significant_heldout:g}: it does "
                                "not improve the pixels it was not fitted on")))
    if c.explains is not None and c.explains < p.min_explained:
        out.append(("structure", f"it removes only {100 * c.explains:.0f} % of the large-scale structure"))
    if c.excess_share is not None and c.excess_share < p.min_excess_share:
        out.append(("excess", f"it removes only {100 * c.excess_share:.2g} % of the excess chi2"))
    if c.support_share is not None and c.support_share < p.min_support_share:
        out.append(("support", (f"it removes only {100 * c.support_share:.2g} % of the excess chi2 where it acts: "
                                "what is wrong there is something else, or more")))
    ca = c.catch_all_heldout
    if ca is not None and ca < 0 and c.heldout is not None and c.heldout > p.min_catch_all_share * ca:
        out.append(("catch_all", (f"on the same held-out pixels it predicts {100 * c.heldout / ca:.0f} % of what the "
                                  f"residual's empirical map predicts (held-out {c.heldout:.4g} vs {ca:.4g}; at least "
                                  f"{100 * p.min_catch_all_share:.0f} % needed): a description, not this name")))
    return out


def kind_gate(cands: list[Candidate], morphology: dict | None) -> None:
    """Refuse (``kind``) every additive field (:attr:`detector.effects.base.Effect.field_kind`) when the
    residual's morphology found, with certainty, that the residual scales with the light: a multiplicative
    residual is a positive finding (the structure follows the model's light, the stars in the dim part are
    dimmer: :func:`detector.morphology.describe`), which no added charge or ADU pattern makes. The converse
    is not asked: "additive" is what the morphology says when it finds no such scaling, an absence of
    evidence, not a finding. A candidate whose own shape was tested under both laws and found added
    (:attr:`Candidate.law_told`) keeps its law: that test is on its fitted pattern, the morphology's on a
    description."""
    m = morphology or {}
    if not (m.get("significant") and m.get("kind") == "multiplicative" and m.get("kind_certain")):
        return
    reg = registry()
    for c in cands:
        cls = reg.get(c.fit.effect)
        if c.kind == "effect" and cls is not None and cls.field_kind == "additive" and c.contender and not c.law_told:
            c.refuse("kind", (f"{c.fit.effect} adds a field whatever the light, but the residual scales with "
                              "the light (the morphology's multiplicative fit): a response, not added light"))


def _of_light(c: Candidate) -> bool:
    """The candidate multiplies the light only: its effect acts at the RESPONSE stage and nowhere else
    (vignetting, PRNU, a mosaic, dead pixels, a flat map; not column defects, which add dark charge too)."""
    cls = registry().get(c.fit.effect)
    return cls is not None and set(cls.stages) == {Stage.RESPONSE}


def _multiplies(c: Candidate) -> bool:
    """The candidate multiplies the signal: a response of the light (:func:`_of_light`) or a multiplicative
    field at another stage (an amplifier's gain regions)."""
    cls = registry().get(c.fit.effect)
    return _of_light(c) or (cls is not None and c.kind == "effect" and cls.field_kind == "multiplicative")


def rank(cands: list[Candidate], light_source: str = "") -> list[Candidate]:
    """Best first: significant parameters of the scene (a number of the scene that is wrong comes before an
    effect that is missing), then the significant effects by their held-out score (delta BIC where there is
    none), then the others that are plausible and not rejected, then the implausible and the rejected, each
    by delta BIC. Twins (as good on held-out pixels) go by delta BIC (fewer parameters for the same fit
    first); on a flat-screen frame (``light_source`` "flat"), whose uniform light cannot tell a response from
    added charge, what multiplies the signal (a response, a gain) comes first."""
    def key(c):
        sig = c.significant
        tier = ((0 if not (c.ambiguous or c.deferred) else 1.5) if c.kind == "parameter" else 1) if sig else \
            2 if c.plausible and not c.rejected else 3
        return tier, c.score if sig else c.fit.delta_bic

    out = sorted(cands, key=key)
    sig = [c for c in out if c.significant and c.kind != "parameter"]
    twins = indistinguishable(sig, out)
    if twins:
        flat = light_source == "flat"
        group = sorted([sig[0], *[c for c in twins if c.significant]],
                       key=lambda c: (flat and not _multiplies(c), c.fit.delta_bic))
        group += [c for c in twins if not c.significant]  # the same image, its own score short of the bar
        params = [c for c in out if c.significant and c.kind == "parameter" and not (c.ambiguous or c.deferred)]
        rest = [c for c in out if c not in group and c not in params]
        out = params + group + rest
    return out


def field_origin(cls) -> str:
    """What an effect class's additive field is: "dark" charge (a glow, a dark-rate gradient), "light" (straylight,
    a sky gradient), an "offset" of the read-out (a bias structure: added in ADU whatever the exposure), or ""
    (not an additive field of one of these)."""
    if cls is None or cls.field_kind != "additive":
        return ""
    stages = tuple(cls.stages)
    if stages == (Stage.ADU,) and cls.scaling == "none":
        return "offset"
    return {(Stage.DARK,): "dark", (Stage.FIELD,): "light"}.get(stages, "")


def _charge_origin(c: Candidate) -> str:
    """"dark" for an additive field of dark charge (a glow, a dark-rate gradient), "light" for an additive field
    of light (straylight, a sky gradient), "" otherwise."""
    origin = field_origin(registry().get(c.fit.effect)) if c.kind == "effect" else ""
    return origin if origin in ("dark", "light") else ""


def same_charge(a: Candidate, b: Candidate) -> bool:
    """A field of dark charge and a field of light put the same charge in the same pixels of an exposed frame:
    both grow with the exposure, and only the pixels' response to light (a flat field) or a dark frame of the
    same exposure tells them apart, neither of which one light frame holds. Their fitted forms may differ (a
    glow's Gaussian from an edge, a straylight's smooth series); the charge's origin is not in the data."""
    return {_charge_origin(a), _charge_origin(b)} == {"dark", "light"}


def same_scatter(a: Candidate, b: Candidate) -> bool:
    """Two effects that add zero-mean scatter whose variances are proportional over the frame are the same
    likelihood on it, whatever their physics: a DSNU adds (sigma D)^2 with D the dark signal, growing with the
    exposure and the dark current; a reset or read noise adds a constant (Janesick 2007, Photon Transfer, ch. 7
    and 11: the dark-signal non-uniformity is a fixed pattern proportional to the dark signal, the read noise is
    not). Where the dark signal is uniform the two laws are one constant, and only a frame of another exposure
    (or another dark signal) tells them apart: not a tie the held-out scores need to find.

    Proportional on this frame: the frame cannot tell the two laws apart. Data of variance ``V_a`` scored
    against ``V_b`` (the amplitude refitted, ``c``) lose ``E[delta(-2 ln L)] = sum(V_a/V_b - 1 - ln(V_a/V_b))
    ~ 1/2 sum(((v_a - c v_b) / V)^2)`` (Kullback & Leibler 1951 for two normals of one mean), ``V`` the pixel's
    whole variance; with ``V >= v_a`` this is at most ``1/2 n rms^2`` of the ratio ``v_a / v_b`` relative to its
    mean over the ``n`` pixels. The laws are the same when even that bound is within one unit of -2 ln L (one
    standard deviation of a chi2 of one parameter): float32 templates of one map (rms ~1e-7) always, a DSNU
    and a read noise on a dark signal varying by 1 % over a 256 x 256 frame (rms 2 %, a bound of 13) not."""
    va, vb = a.fit.extra_var_adu2, b.fit.extra_var_adu2
    if va is None or vb is None or a.fit.delta_adu is not None or b.fit.delta_adu is not None:
        return False
    va, vb = np.asarray(va, np.float64), np.asarray(vb, np.float64)
    if va.ndim == 0 or vb.ndim == 0 or va.shape != vb.shape:
        return False
    both = (va > 0) & (vb > 0)
    if both.sum() < 100:
        return False
    ratio = va[both] / vb[both]
    rms = float(np.std(ratio)) / float(np.mean(ratio))
    return 0.5 * ratio.size * rms * rms <= 1.0


def _dark_pattern_field(c: Candidate) -> bool:
    """A fixed pattern of the dark charge fitted as added scatter (a DSNU: a hardware pattern with a variance
    signature) whose fit carries a large-scale part: a mean change of dark charge besides its scatter. (A glow or
    a dark-rate gradient also carries a variance, the shot noise of its charge, but is no pattern.)"""
    cls = registry().get(c.fit.effect)
    return (c.kind == "effect" and cls is not None and cls.pattern and tuple(cls.stages) == (Stage.DARK,)
            and getattr(cls.signature, "kind", "") == "variance" and c.fit.delta_adu is not None)


def same_dark_field(a: Candidate, b: Candidate) -> bool:
    """``a``, a DSNU fitted with a large-scale part, and ``b``, an additive field of dark charge (a glow, a
    dark-rate gradient), put the same dark charge in the same pixels: the dark-signal non-uniformity spans every
    spatial scale (EMVA 1288 Release 4.0, sect. 8.3: its spectrogram; Janesick 2007, Photon Transfer, ch. 7), and
    its large scales are a field of dark rate. When the DSNU's general form (a cosine series times the dark
    signal) comes first, the data say that a smooth dark charge is there, not which of the two names it has;
    when a dark field's own form comes first (better on held-out pixels), it is a form the data prefer, and the
    held-out scores alone decide whether the DSNU ties with it (not symmetric)."""
    return _dark_pattern_field(a) and _charge_origin(b) == "dark"


def _read_out_offset(c: Candidate) -> bool:
    """An additive field of the read-out (a bias structure): added in ADU whatever the exposure."""
    return c.kind == "effect" and field_origin(registry().get(c.fit.effect)) == "offset"


def dark_or_offset(a: Candidate, b: Candidate) -> bool:
    """One is a field of dark charge (a dark-rate field, a glow), the other an offset of the read-out (a bias
    structure): on one dark frame the same smooth field in the same basis, told apart only by the dark charge's
    shot noise; a bias frame (where the dark field is zero) or a dark of another exposure (where it scales with
    the time) tells them."""
    return ((_charge_origin(a) == "dark" and _read_out_offset(b))
            or (_charge_origin(b) == "dark" and _read_out_offset(a)))


def same_image(a: Candidate, b: Candidate) -> bool:
    """One of the two says, by its own physics, that this frame cannot tell it from the other (the same image
    made at another stage: a coupling of the pixels' charge and a blur of the light; a field of charge whose shot
    noise the frame cannot measure and an offset of the read-out; :attr:`Candidate.untold`)."""
    return b.fit.effect in a.untold or a.fit.effect in b.untold


#: why the data cannot tell the first name from a twin, in the order the verdict says them: each a predicate of
#: (first, twin) and its reason; the last (None) takes the twins whose held-out scores are as good
def same_light(a: Candidate, b: Candidate) -> bool:
    """One acts on the light only (a response: vignetting) and the other adds to the frame (light: straylight, a
    sky gradient; dark charge: a dark-rate field, a glow; or an offset of the read-out: a bias structure): the
    pair :func:`detector.signatures.light_law_evidence` weighs, the same image on a frame whose light is one level
    (their :attr:`Candidate.untold` says when the frame does not tell them)."""
    def adds(c):
        return _charge_origin(c) in ("light", "dark") or _read_out_offset(c)

    return (_of_light(a) and adds(b)) or (_of_light(b) and adds(a))


#: the gates that weigh how much of what is wrong a candidate removes (not whether its form is this effect's): a
#: rival refused by these alone still says something is there that its form predicts
SHARE_GATES = frozenset({"structure", "excess", "support"})


def better_rival(first: Candidate, c: Candidate) -> bool:
    """``c`` predicts the pixels neither fit saw better than ``first`` does (its held-out score significant and at
    least as good, on the same folds), and was refused only for the share of what is wrong it removes
    (:data:`SHARE_GATES`), not for its form: the held-out pixels, the judge's one test of a form against another,
    prefer ``c``, and ``first``'s own shares do not tell its form from ``c``'s. Naming ``first`` alone would be a
    claim the data do not make: a tie, with ``first`` still the one that passes every gate."""
    if c.heldout is None or first.heldout is None or c.heldout >= c.policy.significant_heldout:
        return False
    if c.heldout_block != first.heldout_block or not c.contender:
        return False
    gates = set(c.gates)
    return bool(gates) and gates <= SHARE_GATES and c.heldout <= first.heldout


def closer_rival(first: Candidate, c: Candidate) -> bool:
    """``c`` fits the frame better than ``first`` (a lower delta BIC), predicts the pixels neither fit saw as
    well as ``first`` within the scores' own scatter (:func:`twin_tolerance`, on the same folds), and fails no
    gate but the held-out significance bar that ``first`` clears. That bar says whether a name is earned, not
    which of two forms the pixels prefer: the pixels both fits saw prefer ``c``'s form, and the held-out ones
    cannot tell the two apart. A tie, with ``first`` still the one that passes every gate."""
    if not c.contender or c.heldout is None or first.heldout is None or c.heldout_block != first.heldout_block:
        return False
    if c.fit.delta_bic >= first.fit.delta_bic or c.gates != ["heldout"]:
        return False
    return c.heldout - first.heldout <= twin_tolerance(first.heldout, first.policy)


def richer_rival(first: Candidate, c: Candidate) -> bool:
    """``c`` is a richer form of ``first``'s image (refused by gate ``richer`` alone: a drift's path whose profile
    is a smear's within the noise, ``first`` among the forms it nests, :attr:`Candidate.untold`) and fits the frame
    as well (its delta BIC within the twins' tolerance): the simpler form is named, and the richer one the frame
    cannot exclude is said with it."""
    if c.gates != ["richer"] or first.fit.effect not in c.untold:
        return False
    return c.fit.delta_bic - first.fit.delta_bic <= twin_tolerance(first.fit.delta_bic, first.policy)


TWIN_REASONS = (
    (same_charge, "the same charge in the same pixels, whose origin (dark or light) only a dark frame of the same "
                  "exposure tells"),
    (same_dark_field,  # not symmetric: a dark field first ties with a DSNU by the held-out scores alone
     "the same dark charge in a smooth pattern: a DSNU's large scales are a field of dark rate (a glow or a "
     "dark-rate gradient is one too), whatever form each fit gives it"),
    (same_scatter, "the same added variance in every pixel of this frame (a DSNU's grows as the dark signal "
                   "squared, a PRNU's as the light squared, a read noise's is constant: laws that agree where that "
                   "signal is uniform; a frame of another exposure or level tells them apart)"),
    (lambda a, b: same_image(a, b) and same_light(a, b),
     "the same smooth pattern, added to the frame (light, dark charge or an offset of the read-out) or multiplying "
     "the light (a response), which only sources bright enough above a light of one level would tell: a flat field "
     "taken through the same optics (a dark or a bias frame, for dark charge or an offset) tells which"),
    (dark_or_offset, ("the same smooth field, of dark charge or an offset of the read-out, whose shot noise does "
                      "not tell them apart here; a bias frame (where dark charge is zero) or a dark of another "
                      "exposure (where it scales with the time) does")),
    (richer_rival, "a richer form of the same image (a drift's path beyond a smear) whose profile the frame does "
                   "not tell from the simpler form: a longer trail or brighter sources would"),
    (same_image, "the same small kernel on the same pixels, whose stage (the pixels' charge or the light) only a "
                 "coupled noise or a charge not of light would tell, neither measurable in this frame"),
    (lambda a, b: better_rival(a, b),
     "it predicts the held-out pixels better, but removes too little of what is wrong where it acts or overall: the "
     "held-out pixels prefer its form, the shares do not single out the first's"),
    (closer_rival,
     "it fits the frame better, and predicts the held-out pixels as well within their scatter; only the held-out "
     "significance bar, which the first clears, separates them: the data do not prefer the first's form"),
    (lambda a, b: b.heldout_blind and not b.significant,
     "it fits the frame as well or better, and the held-out test cannot weigh it: the few bright pixels that carry "
     "its change lie in one fold of the checkerboard, the other sees less than a detection of it"),
    (None, "their held-out scores are as good"),
)


def indistinguishable(sig: list[Candidate], cands: list[Candidate] = ()) -> list[Candidate]:
    """The significant candidates after the first whose held-out score is as good as the first's (within the
    policy's twin fraction, and within the scores' own scatter ~ sqrt(2 |score|)), and those that put the same
    charge in the same pixels by another origin (:func:`same_charge`), the same smooth dark charge under a DSNU's
    large scales and a dark field (:func:`same_dark_field`) or add the same scatter
    (:func:`same_scatter`); then, of ``cands``, the contenders
    (significant by delta BIC, plausible, not rejected) that make the same image as the first in this frame
    (:func:`same_image`): a form of the same image whose held-out score falls short does not make the data
    tell the two stages apart; for the two laws of a light pattern (:func:`same_light`) the plausible ones
    whose own delta BIC falls short too (:func:`_other_law`); the contenders refused only for their shares
    whose held-out score is better than the first's (:func:`better_rival`); and those refused only by the
    held-out bar that fit better and predict as well (:func:`closer_rival`)."""
    if not sig:
        return []
    best = sig[0].heldout
    tol = twin_tolerance(best, sig[0].policy) if best is not None else 0.0
    out = [c for c in sig[1:] if (best is not None and c.heldout is not None and c.heldout - best <= tol)
           or same_charge(sig[0], c) or same_dark_field(sig[0], c) or same_scatter(sig[0], c)
           or same_image(sig[0], c)]
    out += [c for c in cands if c.kind != "parameter" and c is not sig[0] and c not in out and not c.significant
            and ((c.contender or _other_law(sig[0], c)) and same_image(sig[0], c)
                 or _other_origin(sig[0], c)
                 or c.contender and blind_rival(sig[0], c) or better_rival(sig[0], c)
                 or closer_rival(sig[0], c) or richer_rival(sig[0], c))]
    return out


def _other_law(first: Candidate, c: Candidate) -> bool:
    """``c`` is the other law of ``first``'s light pattern (:func:`same_light`), plausible and not rejected:
    ``first``'s own evidence (its :attr:`Candidate.untold`, the same fitted shape under both laws) is what
    says the frame does not tell an added light from a response, whatever ``c``'s own form pays for its
    parameters (a Legendre series of 14 terms short of the BIC bar where the two-term fall-off passes it)."""
    return same_light(first, c) and c.plausible and not c.rejected


def _other_origin(first: Candidate, c: Candidate) -> bool:
    """``c`` puts ``first``'s charge in the same pixels by the other origin (:func:`same_charge`: dark charge or
    light), plausible and not rejected: the charge's origin is not in one exposed frame, whatever ``c``'s own
    form pays for its parameters (a straylight series short of the BIC bar where a glow's point emitter passes
    it, on a sky of one level). As :func:`_other_law` for the two laws of a light pattern."""
    return same_charge(first, c) and c.plausible and not c.rejected


def twin_tolerance(best: float, policy) -> float:
    """How far a score (a -2 ln L change) may lie from the best one's ``best`` and still tie with it: the policy's
    ``twin_fraction`` of it, or two standard deviations of a chi2 difference of that size (sqrt(2 |best|)),
    whichever is larger."""
    return max(policy.twin_fraction * abs(best), 2 * np.sqrt(2 * abs(best)))


def blind_rival(first: Candidate, c: Candidate) -> bool:
    """``c`` fits the frame as well as ``first`` or better (its delta BIC within the twins' tolerance of
    :func:`indistinguishable`, or below) but was not named because its held-out score is no test of it
    (:attr:`Candidate.heldout_blind`): a fold of the checkerboard sees less than a detection of its change, so
    the fit on that fold is noise, and its failure on the other fold says nothing of the effect. Only the
    held-out pixels could have told the two apart, and for ``c`` they cannot: a tie, not a name for ``first``."""
    if not c.heldout_blind or c.fit.delta_bic >= c.policy.significant_delta_bic:
        return False
    best = first.fit.delta_bic
    tol = twin_tolerance(best, first.policy)
    return c.fit.delta_bic - best <= tol


def verdict(cands: list[Candidate], morphology: dict | None = None) -> str:
    """One sentence for the report: the scene's wrong numbers and the most likely missing effect (significant,
    better on held-out pixels than the catch-all), or that nothing is missing, or what the residual looks
    like when no candidate explains it."""
    sig = [c for c in cands if c.significant]
    params = [c for c in sig if c.kind == "parameter" and not (c.ambiguous or c.deferred)]
    later = [c for c in sig if c.kind == "parameter" and (c.ambiguous or c.deferred)]
    effects = [c for c in sig if c.kind != "parameter"]
    head = ""
    if params:
        head = "the scene's numbers are off: " + "; ".join(
            f"{c.key} -> {c.value:.5g} ({c.fit.explanation}"
            + (f"; the frame cannot tell it apart from {c.ambiguous}" if c.ambiguous else "") + ")" for c in params)
    if effects:
        best = effects[0]
        held = f", held-out {best.heldout:.4g}" if best.heldout is not None else ""
        also, left = "", indistinguishable(effects, cands)
        for told, why in TWIN_REASONS:
            group = [c for c in left if told is None or told(best, c)]
            left = [c for c in left if c not in group]
            if group:
                also += (f"; {'nor' if also else 'the data cannot tell it apart'} from "
                         f"{', '.join(c.fit.effect for c in group)}: {why}")
        text = (f"most likely missing: {best.fit.effect} (delta BIC {best.fit.delta_bic:.4g}{held}): "
                f"{best.fit.explanation}{also}")
        if later:
            text += "; then the scene's " + "; ".join(
                f"{c.key} -> {c.value:.5g} ({c.ambiguous and 'the frame cannot tell it apart from ' + c.ambiguous or c.deferred})"
                for c in later)
        return f"{head}; then {text}" if head else text
    if later:
        tail = "the scene's numbers are off: " + "; ".join(
            f"{c.key} -> {c.value:.5g} ({c.fit.explanation}"
            + (f"; the frame cannot tell it apart from {c.ambiguous}" if c.ambiguous else "") + ")" for c in later)
        head = f"{head}; {tail}" if head else tail
    if head:
        return head
    policy = cands[0].policy if cands else DEFAULT_POLICY
    named = [c for c in cands if c.fit.delta_bic < policy.significant_delta_bic and c.kind != "parameter"]
    why = ""
    if named:
        c = named[0]
        reasons = gate_reasons(c)
        why = f" ({c.fit.effect} fits but is not credible: {reasons[0][1]} [{reasons[0][0]}])" if reasons else ""
        if c.heldout_blind and reasons and reasons[0][0] == "heldout":
            why = (f" ({c.fit.effect} fits best, but the held-out pixels cannot test it: one fold of the checkerboard "
                   "sees less than a detection of its change; nor do the pixels tell it from the other candidates "
                   "when each is fitted beside it)")
    if morphology and morphology.get("significant"):
        return ("no catalogue effect explains the residual" + why + "; what is missing looks like "
                + morphology["explanation"])
    return ("no missing effect was found: no candidate improves the fit significantly (delta BIC < "
            f"{policy.significant_delta_bic:g})" + why)


def judge_json(cands: list[Candidate], policy: DiagnosisPolicy) -> dict:
    """The judge's part of every ``diagnose --json`` (single, large, series): the policy, the gate registry,
    the significant names and the twins."""
    sig = [c for c in cands if c.significant]
    return {"policy": policy.to_json(), "gate_codes": GATES,
            "significant": [c.fit.effect for c in sig],
            "indistinguishable": [c.fit.effect for c in indistinguishable([c for c in sig if c.kind != "parameter"],
                                                                          cands)]}
