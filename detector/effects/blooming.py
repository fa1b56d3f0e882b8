"""Blooming: charge above the full well spills along the column into the neighbouring pixels.

In a CCD without anti-blooming drain the potential barrier between pixels of a column is lower than the
channel stops between columns, so the excess charge of a saturated pixel flows up and down its column
(Janesick, *Scientific Charge-Coupled Devices*, SPIE 2001, sec. 3.2.5 "blooming"). The excess is conserved:
it fills the next pixels of the column to the full well, outward from the saturated run, until it is used
up or leaves the sensor. Applied once per frame to the whole expected photo-electron image (stage FIELD),
so bleed trails cross the row bands of the tiled chain without seams.
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from ..signatures import LinearSignature, Variant, fit_variant, search_sample
from .base import Effect, EffectParams, Stage, Tile, register_effect


def _fill(seg: np.ndarray, amount: float, fw: float) -> float:
    """Fill ``seg`` (a view, in spill order) up to ``fw`` with ``amount``; return what is left over."""
    if amount <= 0 or seg.size == 0:
        return amount
    room = np.cumsum(np.maximum(fw - seg, 0.0))
    k = int(np.searchsorted(room, amount))
    if k >= seg.size:
        seg[:] = np.maximum(seg, fw)
        return amount - float(room[-1])
    seg[:k] = np.maximum(seg[:k], fw)
    seg[k] += amount - (float(room[k - 1]) if k else 0.0)
    return 0.0


def bleed_columns(image_e: np.ndarray, full_well_e: float, up_fraction: float = 0.5) -> float:
    """Spill the charge above ``full_well_e`` along each column, in place. Returns the charge lost [e-]
    off the top and bottom of the image. ``up_fraction`` of each run's excess goes towards higher rows."""
    lost = 0.0
    cols = np.nonzero((image_e > full_well_e).any(axis=0))[0]
    for c in cols:
        col = image_e[:, c].astype(np.float64)
        over = np.nonzero(col > full_well_e)[0]
        breaks = np.nonzero(np.diff(over) > 1)[0] + 1
        for run in np.split(over, breaks):
            excess = float(np.sum(col[run] - full_well_e))
            col[run] = full_well_e
            up_seg, down_seg = col[run[-1] + 1:], col[:run[0]][::-1]
            left = _fill(up_seg, excess * up_fraction, full_well_e)
            left = _fill(down_seg, excess * (1.0 - up_fraction) + left, full_well_e)
            lost += _fill(up_seg, left, full_well_e)  # what the lower part could not take goes up
        image_e[:, c] = col
    return lost


def soft_bleed_columns(image_e: np.ndarray, threshold_e: float, length_px: float, up_fraction: float = 0.5
                       ) -> float:
    """The soft bleed, in place: the charge above ``threshold_e`` [e-] in every pixel leaves it and is
    deposited along its column with a geometric (discrete exponential) profile of e-folding length
    ``length_px`` [px], ``up_fraction`` [1] of it towards higher rows. Returns the charge lost [e-] off the
    top and bottom of the image.

    The profile is that of a spill in which every pixel the charge reaches keeps the same share ``1 - q``
    of what arrives and passes the rest on (``q = exp(-1 / length_px)``): the k-th pixel away receives
    ``(1 - q) q^(k - 1)`` of the spill. A pixel pushed over its full well by the deposit is clipped by the
    chain: the overflow (anti-blooming) drain takes what a full pixel cannot hold (Janesick, *Scientific
    Charge-Coupled Devices*, SPIE 2001, sec. 3.2.5: blooming, and the lateral overflow drain of an
    anti-blooming sensor), so, unlike the charge-conserving fill of :func:`bleed_columns`, a trail grows
    with the logarithm of the excess (``length_px ln(excess / full well)``), not in proportion to it.
    The profile is cut at ``8 length_px`` (3e-4 of the spill) and renormalised."""
    excess = np.maximum(image_e - np.float32(threshold_e), 0)
    cols = np.nonzero(excess.any(axis=0))[0]
    if cols.size == 0 or length_px <= 0:
        return 0.0
    ex = excess[:, cols].astype(np.float64)
    q = float(np.exp(-1.0 / length_px))
    n = min(int(np.ceil(8 * length_px)), image_e.shape[0] - 1)
    w = (1 - q) * q ** np.arange(n)
    w /= w.sum()
    out = -ex
    for k in range(1, n + 1):  # k pixels away: up (higher rows) and down
        out[k:] += up_fraction * w[k - 1] * ex[:-k]
        out[:-k] += (1 - up_fraction) * w[k - 1] * ex[k:]
    image_e[:, cols] += out.astype(image_e.dtype)
    return float(-out.sum())  # the spill's charge that found no pixel of the image


#: spill thresholds (fractions of the full well) and upward shares tried by the diagnosis
_THRESHOLDS = (0.8, 0.85, 0.9, 0.95, 1.0)
_UP_FRACTIONS = (0.0, 0.25, 0.5, 0.75, 1.0)
#: e-folding lengths of the soft (exponential) bleed tried by the diagnosis [sensor px]
_SOFT_LENGTHS = (1.0, 2.0, 4.0, 8.0)


def _blooming_variants(res):
    """Bleed trails of the model's own charge: the photo-signal *before* the full-well clip (the model's
    ``photo_field_adu``) spilled along the columns, minus the clipped charge the model has. Variants over
    the spill threshold and the upward share; the fitted amplitude (1 for charge conservation) absorbs a
    drain that removes part of the excess."""
    photo = res.photo_field_adu
    if photo is None:
        return
    g = np.float32(res.gain)
    fw_sensor = res.sensor.full_well_e
    fw = np.float32(fw_sensor * res.pixel_sum)
    charge = photo.astype(np.float32) * g
    if not (charge > fw * min(_THRESHOLDS)).any():
        return
    clipped = np.minimum(charge, fw)
    for thr in _THRESHOLDS:
        for up in _UP_FRACTIONS:
            bled = charge.copy()
            bleed_columns(bled, float(thr * fw), up)
            t = (np.minimum(bled, fw) - clipped) / g

            def to_params(c, thr=thr, up=up):
                if not 0.3 < c[0] < 3:
                    return None
                p = {"up_fraction": up}
                if thr < 1:
                    p["threshold_e"] = round(thr * fw_sensor, 1)
                return p

            yield Variant([t], to_params, f"threshold {thr:g} FW, {100 * up:.0f} % up")
    soft = _soft_bleed_variant(res, charge, clipped, g, fw, fw_sensor)
    if soft is not None:
        yield soft


def _soft_bleed_variant(res, charge, clipped, g, fw, fw_sensor):
    """The soft bleed's best variant (:func:`soft_bleed_columns`), searched coordinate-wise on the search
    sample (length at threshold 1 FW and half up, then the upward share, then the threshold: 12 fits, not the
    100 of the whole grid). Only the columns holding charge above the lowest threshold change: the templates
    live on those columns, evaluated at the sample's pixels through ``at`` (the full map is built for the
    winner only)."""
    b = res.sensor.binning
    width = charge.shape[1]
    cols = np.nonzero((charge > fw * min(_THRESHOLDS)).any(axis=0))[0]
    where = np.full(width, -1)
    where[cols] = np.arange(cols.size)
    sub_charge, sub_clipped = charge[:, cols], clipped[:, cols]
    ctx = search_sample(res)
    iy, ix = np.divmod(ctx["idx"], width)
    on_cols = where[ix] >= 0
    sample_y, sample_j = iy[on_cols], where[ix[on_cols]]

    def variant(length, thr, up):
        bled = sub_charge.copy()
        soft_bleed_columns(bled, float(thr * fw), length / b, up)
        sub = (np.minimum(bled, fw) - sub_clipped) / g

        def to_params(c):
            if not 0.3 < c[0] < 3:
                return None
            return {"up_fraction": up, "threshold_e": round(thr * fw_sensor, 1), "length_px": length}

        def at(idx):
            idx = np.asarray(idx)
            if idx is ctx["idx"] or (idx.size == ctx["idx"].size and np.array_equal(idx, ctx["idx"])):
                out = np.zeros(idx.size)
                out[on_cols] = sub[sample_y, sample_j]
                return out[None, :]
            y, x = np.divmod(idx, width)
            j = where[x]
            return np.where(j >= 0, sub[y, np.maximum(j, 0)], 0.0)[None, :]

        def maps():
            t = np.zeros(charge.shape, np.float32)
            t[:, cols] = sub
            return [t]

        return Variant(maps, to_params, f"soft, {length:g} px, threshold {thr:g} FW, {100 * up:.0f} % up", at=at)

    tried: dict = {}

    def chi2(length, thr, up):
        key = (length, thr, up)
        if key not in tried:
            v = variant(*key)
            c, d = fit_variant(res, v, ctx["idx"], ctx["r"], ctx["w"])
            tried[key] = (d if v.to_params(c) is not None else np.inf, v)
        return tried[key][0]

    length = min(_SOFT_LENGTHS, key=lambda x: chi2(x, 1.0, 0.5))
    up = min(_UP_FRACTIONS, key=lambda u: chi2(length, 1.0, u))
    thr = min(_THRESHOLDS, key=lambda t: chi2(length, t, up))
    d, v = tried[(length, thr, up)]
    return v if np.isfinite(d) else None


def _blooming_words(p, res) -> str:
    up = f"{100 * p['up_fraction']:.0f} % upwards"
    start = f", from {p['threshold_e']:.3g} e-" if p.get("threshold_e") is not None else ""
    if p.get("length_px", 0.0):
        return (f"charge spilling along the columns of saturated sources with an exponential profile of "
                f"{p['length_px']:.3g} px ({up}{start}), the overflow drained: blooming of an anti-blooming sensor "
                "(a soft bleed)")
    return f"charge spilling along the columns of saturated sources ({up}{start}): blooming"


_BLOOMING_SIGNATURE = LinearSignature(
    _blooming_variants,
    _blooming_words,
    pattern="column trails of excess charge at saturated sources", extra_k=2)


class BloomingParams(EffectParams):
    threshold_e: float | None = Field(None, gt=0, description="charge a pixel holds before spilling (default: full well) [e-]")
    up_fraction: float = Field(0.5, ge=0, le=1, description="share of the excess flowing towards higher rows [1]")
    length_px: float = Field(0.0, ge=0, le=100, description="e-folding length of a soft bleed's exponential profile "
                             "along the column (0: the charge-conserving fill up to the full well) [px]",
                             json_schema_extra={"unit": "pixel"})


@register_effect
class Blooming(Effect):
    """Blooming along columns of the expected charge above the full well, charge-conserving (see module);
    with ``length_px`` > 0 the soft bleed of :func:`soft_bleed_columns` (an exponential profile along the
    column, the overflow drained)."""

    name = "blooming"
    scaling = "signal"
    identity = {"threshold_e": 1e7}
    stages = (Stage.FIELD,)
    signature = _BLOOMING_SIGNATURE
    Params = BloomingParams

    def leaves_uniform(self, level_e: float) -> bool:
        """No pixel of a uniform image at or below the threshold spills: the image is left as it is."""
        return level_e <= (self.params.threshold_e or self.sensor.full_well_e)

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        fw = self.params.threshold_e or self.sensor.full_well_e
        if self.params.length_px > 0:
            soft_bleed_columns(data, fw, self.params.length_px, self.params.up_fraction)
        else:
            bleed_columns(data, fw, self.params.up_fraction)
