"""Light of the sky that the scene's uniform background lacks: ``sky_gradient``.

The night sky is not uniform across a field: the scattered light of the Moon falls off with the angular
distance from it, twilight with the solar depression along the vertical, airglow grows with the airmass
towards the horizon (van Rhijn 1921; Krisciunas & Schaefer 1991, PASP 103, 1033, for the moonlit sky).
Over a telescope's field of a degree or less these are smooth, and to first order a plane,

    B(x, y) = B_0 + g_x (x - x_c) / 1000 + g_y (y - y_c) / 1000        [e-/s per pixel]

with (x, y) sensor pixels, (x_c, y_c) the sensor centre, and ``g_x``, ``g_y`` the change of the rate per
1000 sensor pixels. ``B_0`` is the scene's background; the effect adds the ramps (zero at the sensor
centre, so windows and binning see the same sky) as photo-electrons ``t (g . (x - x_c)) / 1000``.

It is light: added to the photo-signal where the scene's light enters (stage FIELD, before the optics'
image-plane effects and the pixel response, so vignetting, PRNU and a CFA act on it as on the sky), with
its shot noise, and absent when no light reaches the sensor (dark and bias frames: an expected photo-signal
zero everywhere). That, and its form (a plane, proportional to the exposure time), tell it from a bias
gradient (ADU, in bias frames too), an amplifier glow (dark charge, localised at an edge) and vignetting
(a radial, multiplicative loss of every source's light).
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from ..signatures import LinearSignature, Variant
from .base import Effect, EffectParams, Stage, Tile, register_effect

#: the gradient's length unit: the rates change per this many sensor pixels
KPX = 1000.0
#: bound of either gradient [e-/s/pixel per 1000 px]
MAX_GRADIENT = 1e5


def sky_ramp_e(ys: np.ndarray, xs: np.ndarray, yc: float, xc: float, gx_e_per_s_per_kpx: float,
               gy_e_per_s_per_kpx: float, exptime_s: float) -> np.ndarray:
    """Photo-electrons [e-] of the sky gradient at sensor rows ``ys``, columns ``xs`` (pixel centres): the
    plane ``t (g_x (x - x_c) + g_y (y - y_c)) / 1000``, zero at (x_c, y_c); shape (len(ys), len(xs))."""
    rate = (gx_e_per_s_per_kpx * (np.asarray(xs, np.float64) - xc) / KPX)[None, :] \
        + (gy_e_per_s_per_kpx * (np.asarray(ys, np.float64) - yc) / KPX)[:, None]
    return (rate * exptime_s).astype(np.float32)


def _sensor_centre(sensor) -> tuple[float, float]:
    return (sensor.sensor_height_px - 1) / 2.0, (sensor.sensor_width_px - 1) / 2.0


# --- diagnosis: two ramps of light, proportional to the exposure time --------------------------------------------

def _sky_variants(res):
    if res.exptime_s <= 0 or not np.any(res.photo_adu > 0):  # no light reached the sensor: no sky
        return
    yc, xc = _sensor_centre(res.sensor)
    f = res.exptime_s * res.pixel_sum / res.gain / KPX  # ADU per output pixel per (e-/s/pixel per 1000 px)
    tx = (f * (res.xs - xc)).astype(np.float32)[None, :]
    ty = (f * (res.ys - yc)).astype(np.float32)[:, None]

    def to_params(c):
        gx, gy = (float(x) for x in c)
        ok = max(abs(gx), abs(gy)) <= MAX_GRADIENT
        return {"gx_e_per_s_per_kpx": round(gx, 6), "gy_e_per_s_per_kpx": round(gy, 6)} if ok else None

    yield Variant([tx, ty], to_params, "plane")


def _sky_words(p, res) -> str:
    gx, gy = p["gx_e_per_s_per_kpx"], p["gy_e_per_s_per_kpx"]
    ang = float(np.degrees(np.arctan2(gy, gx))) % 360.0
    return (f"additive light rising linearly across the field, {np.hypot(gx, gy):.3g} e-/s per pixel per 1000 px "
            f"towards {ang:.0f} deg (from +x), growing with exposure, in the light only: a sky gradient "
            "(moonlight, twilight, airglow)")


_SKY_SIGNATURE = LinearSignature(_sky_variants, _sky_words, pattern="additive plane of light (with its shot noise)",
                                 extra_k=0, adds_charge=True)


# --- adapter -------------------------------------------------------------------------------------------------


class SkyGradientParams(EffectParams):
    gx_e_per_s_per_kpx: float = Field(
        1.0, ge=-MAX_GRADIENT, le=MAX_GRADIENT, description="change of the sky rate along the columns (+x) per 1000 sensor pixels, "
        "zero at the sensor centre [e-/s/pixel per 1000 px]", json_schema_extra={"unit": "electron / (s pixel kpixel)"})
    gy_e_per_s_per_kpx: float = Field(
        0.0, ge=-MAX_GRADIENT, le=MAX_GRADIENT, description="change of the sky rate along the rows (+y) per 1000 sensor pixels, "
        "zero at the sensor centre [e-/s/pixel per 1000 px]", json_schema_extra={"unit": "electron / (s pixel kpixel)"})


@register_effect
class SkyGradient(Effect):
    """A linear gradient of the sky light across the field (moonlit sky, twilight, airglow): photo-electrons
    ``t (g_x (x - x_c) + g_y (y - y_c)) / 1000`` added to the light, zero at the sensor centre.

    Light only: nothing is added when the frame receives no light (a dark or bias frame, an expected
    photo-signal of zero everywhere); where the plane would take the light below zero it is clipped at zero.
    """

    name = "sky_gradient"
    identity = {"gx_e_per_s_per_kpx": 0.0, "gy_e_per_s_per_kpx": 0.0}
    stages = (Stage.FIELD,)
    Params = SkyGradientParams
    signature = _SKY_SIGNATURE

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        if not data.any():  # shutter closed: no light, no sky
            return
        ys, xs = tile.pixel_centres()
        yc, xc = _sensor_centre(self.sensor)
        p = self.params
        data += sky_ramp_e(ys, xs, yc, xc, p.gx_e_per_s_per_kpx, p.gy_e_per_s_per_kpx, tile.exptime_s)
        np.maximum(data, 0, out=data)
