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

from ..signatures import LinearSignature, Variant
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


#: spill thresholds (fractions of the full well) and upward shares tried by the diagnosis
_THRESHOLDS = (0.8, 0.85, 0.9, 0.95, 1.0)
_UP_FRACTIONS = (0.0, 0.25, 0.5, 0.75, 1.0)


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


_BLOOMING_SIGNATURE = LinearSignature(
    _blooming_variants,
    lambda p, res: (f"charge spilling along the columns of saturated sources ({100 * p['up_fraction']:.0f} % "
                    f"upwards{', from ' + format(p['threshold_e'], '.3g') + ' e-' if 'threshold_e' in p else ''}): "
                    "blooming"),
    pattern="column trails of excess charge at saturated sources", extra_k=2)


class BloomingParams(EffectParams):
    threshold_e: float | None = Field(None, gt=0, description="charge a pixel holds before spilling (default: full well) [e-]")
    up_fraction: float = Field(0.5, ge=0, le=1, description="share of the excess flowing towards higher rows [1]")


@register_effect
class Blooming(Effect):
    """Blooming along columns of the expected charge above the full well, charge-conserving (see module)."""

    name = "blooming"
    scaling = "signal"
    identity = {"threshold_e": 1e7}
    stages = (Stage.FIELD,)
    signature = _BLOOMING_SIGNATURE
    Params = BloomingParams

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        fw = self.params.threshold_e or self.sensor.full_well_e
        bleed_columns(data, fw, self.params.up_fraction)
