"""The catch-all: the residual's own empirical map as the alternative every name must beat.

:func:`detector.morphology.describe` describes a significant residual and builds its empirical map (a smooth
field, line profiles, a periodic pattern, compact features, a kernel about the sources, extra noise). Here
that map is a candidate like any other: fitted on one fold of the held-out checkerboard and scored on the
other (:func:`detector.signatures.heldout_delta`), so a physical candidate's held-out score can be set
against the description's on the same folds. A name that predicts the unseen pixels worse than a
description of the residual (beyond the policy's ``min_catch_all_share``) is not named: the verdict is the
description.
"""

from __future__ import annotations

import numpy as np

from detector.morphology import describe
from detector.signatures import Fit, Residuals, Signature, heldout_delta, pixel_score


def empirical_fit(res: Residuals, morph: dict | None = None) -> Fit | None:
    """The empirical map of ``res``'s residual as a :class:`Fit` (mean change [ADU] or added variance
    [ADU^2]); None when the residual is not significant or has no map."""
    m = describe(res) if morph is None else morph
    emp = m.get("empirical")
    if not m.get("significant") or not emp or emp.get("map") is None:
        return None
    shape = res.data_adu.shape
    mp = np.broadcast_to(np.asarray(emp["map"], np.float32), shape)
    if emp["kind"] == "noise":
        return Fit("catch_all", {}, 0.0, 1, res.n_fit, m.get("explanation", ""), extra_var_adu2=mp)
    if emp["kind"] == "multiplicative":
        delta = (mp * res.photo_adu).astype(np.float32)
    else:
        delta = np.asarray(mp, np.float32)
    return Fit("catch_all", {}, 0.0, 1, res.n_fit, m.get("explanation", ""), delta_adu=delta)


class CatchAll(Signature):
    """The description as a signature: fit = the empirical map of the fold's residual; score = the pixels'
    Gaussian delta -2 ln L (:func:`detector.signatures.pixel_score`)."""

    kind = "description"

    def fit(self, res: Residuals, name: str) -> Fit | None:
        return empirical_fit(res)

    def score(self, fit: Fit, res: Residuals) -> float | None:
        return pixel_score(fit, res)


def catch_all_heldout(res: Residuals, block: int | None = None, threads: int = 1) -> float | None:
    """The catch-all's held-out delta -2 ln L on the checkerboard folds every candidate is scored on (blocks of
    ``block`` pixels; default: :func:`detector.signatures.default_block`) (0 when neither fold's residual is
    significant: the description predicts nothing). ``threads`` > 1: the two folds at once (the same result)."""
    h = heldout_delta(CatchAll(), res, "catch_all", block=block, threads=threads)
    return None if h is None else float(h)


def compare_with_catch_all(res: Residuals, cands: list, morph: dict, threads: int = 1) -> float | None:
    """Set the catch-all's held-out score on every effect candidate with a held-out score (its
    ``catch_all_delta`` follows), when the frame's residual is significant: on the blocks that candidate was
    scored on (its ``heldout_block``; the catch-all is computed only on the blocks some candidate uses). Returns
    the catch-all's score on the blocks the candidates were compared on (the finer blocks when any candidate
    was re-scored on them; None: not computed). ``threads``: see :func:`catch_all_heldout`."""
    if not morph.get("significant"):
        return None
    scored = [c for c in cands if c.heldout is not None and c.kind == "effect"]
    if not scored:
        return None
    by_block: dict = {}  # a candidate scored on smaller blocks is compared on the same folds
    for c in scored:
        if c.heldout_block not in by_block:
            by_block[c.heldout_block] = catch_all_heldout(res, c.heldout_block, threads)
        c.catch_all_heldout = by_block[c.heldout_block]
    res.forget("heldout_folds")
    finer = [b for b in by_block if b is not None]
    return by_block[finer[0] if finer else None]


def outliers_after_catch_all(res: Residuals, cands: list, morph: dict, empirical: dict | None) -> None:
    """Judge the outlier-count candidates (hot and dead pixels, columns, cosmic rays: their signature's
    ``outlier_count``) on what remains once the
    catch-all has taken the structured residual: the outlier statistics recomputed against the model plus
    the residual's empirical map; a count candidate that is no longer significant there was counting the
    pattern's pixels (a ghost's or a PRNU's low-frequency part's, a periodic pattern's), not defects (gate
    ``catch_all``)."""
    from dataclasses import replace

    from detector import registry
    from detector.signatures import spike_stats

    def counted(c) -> bool:
        sig = getattr(registry().get(c.fit.effect), "signature", None)
        if not (c.contender and getattr(sig, "outlier_count", False)):
            return False
        # a description that is a map of the frame's columns themselves (each column's own mean) is the column
        # outliers' own image, not a pattern that made them: nothing to ask of the columns once it is taken
        return not (sig.kind == "columns" and (empirical or {}).get("form") == "columns")

    counts = [c for c in cands if counted(c)]
    if not counts or not morph.get("significant") or not empirical or empirical.get("map") is None:
        return
    fit = empirical_fit(res, {**morph, "empirical": empirical})
    if fit is None or fit.delta_adu is None:
        return
    model = (res.model_adu + fit.delta_adu).astype(np.float32)
    usable = res.outlier_usable
    spikes, _ = spike_stats(res.data_adu, model, res.var_adu2, usable, res.gain)
    after = replace(res, model_adu=model, data_spikes=spikes, _flat={})
    for c in counts:
        sig = registry()[c.fit.effect].signature
        again = sig.fit(after, c.fit.effect)
        if again is None or again.delta_bic >= c.policy.significant_delta_bic:
            c.refuse("catch_all", "once the residual's described pattern (" + morph.get("explanation", "")[:120]
                     + ") is in the model, the outliers are as many as the model expects: it counted the "
                     "pattern's pixels, not defects")
