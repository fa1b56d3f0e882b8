"""A dark-current gradient: the dark rate changing across the sensor because its temperature does.

Dark current is thermally generated, ``D(T) ~ T^3 exp(-E_g / 2kT)`` for the depletion (mid-gap) component,
which doubles every ~6-7 K near room temperature (Janesick 2001, Scientific CCDs, sect. 7.2, eq. 7.4;
Widenhorn et al. 2002, J. Appl. Phys. 92, 7434). A cold finger at one side of the die, or a warm read-out
amplifier, leaves a temperature gradient of a few tenths of a kelvin to a few kelvin across the sensor; to
first order in ``dT`` the dark rate changes by ``dD = D ln2 dT / T_2`` (``T_2`` the doubling interval), a
linear ramp of the dark rate [e-/s] across the sensor. Unlike a bias ramp (an offset of the read-out, the
same in every frame) it grows with exposure time and carries its shot noise, which is what tells the two
apart in a dark series (``newtsim diagnose --series``): on one dark frame they are nearly the same pattern.
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from ..signatures import LinearSignature, Variant
from .base import Effect, EffectParams, Stage, Tile, register_effect

# --- pure functions ---------------------------------------------------------------------------------------

def sensor_uv(ys: np.ndarray, xs: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Sensor coordinates [1] in -0.5 .. 0.5 from the first to the last row/column (0 at the centre)."""
    u = (np.asarray(xs, np.float64) / max(width - 1, 1) - 0.5).astype(np.float32)
    v = (np.asarray(ys, np.float64) / max(height - 1, 1) - 0.5).astype(np.float32)
    return u, v


def gradient_rate(ys: np.ndarray, xs: np.ndarray, height: int, width: int, gx: float, gy: float) -> np.ndarray:
    """The dark-rate change [e-/s/pixel] on the grid of sensor rows ``ys`` and columns ``xs``:
    ``gx u + gy v``, ``gx`` / ``gy`` the change across the sensor width / height, zero at the centre."""
    u, v = sensor_uv(ys, xs, height, width)
    return (np.float32(gx) * u[None, :] + np.float32(gy) * v[:, None]).astype(np.float32)


# --- diagnosis signature (detector.signatures) ------------------------------------------------------------

def _variants(res):
    s = res.sensor
    unit = np.float32(res.exptime_s * res.pixel_sum / res.gain)  # ADU per (e-/s) of dark rate
    u, v = sensor_uv(res.ys, res.xs, s.sensor_height_px, s.sensor_width_px)

    def to_params(c):
        if not (abs(c[0]) <= 1e6 and abs(c[1]) <= 1e6) or res.exptime_s <= 0:
            return None
        return {"gradient_x_e_per_s": round(float(c[0]), 6), "gradient_y_e_per_s": round(float(c[1]), 6)}

    yield Variant([(unit * u)[None, :], (unit * v)[:, None]], to_params)


def _check(fit, res) -> str:
    """A temperature gradient modulates the sensor's dark current: it cannot take the dark rate below zero
    at a corner (the change at the corners, ``(|gx| + |gy|) / 2``, stays below the sensor's dark rate plus
    the measured dark level)."""
    p, s = fit.params, res.sensor
    corner = (abs(p["gradient_x_e_per_s"]) + abs(p["gradient_y_e_per_s"])) / 2
    mean_rate = float(np.median(res.dark_e)) / max(res.exptime_s * res.pixel_sum, 1e-12) if res.dark_e.size else 0.0
    base = max(s.dark_current_e_per_s, mean_rate)
    if corner > 1.5 * base + 1e-9:
        return (f"the dark rate would change by {corner:.3g} e-/s at the corners, more than the sensor's dark rate "
                f"({base:.3g} e-/s): a temperature gradient cannot do that; an offset ramp (bias) or a light taken "
                "for dark current")
    return ""


_SIGNATURE = LinearSignature(
    _variants,
    lambda p, res: (f"dark rate changing by {p['gradient_x_e_per_s']:+.3g} e-/s across the columns and "
                    f"{p['gradient_y_e_per_s']:+.3g} e-/s across the rows, growing with exposure: a dark-current "
                    "gradient (a temperature gradient across the sensor)"),
    pattern="additive ramp of dark charge growing with exposure", extra_k=0, adds_charge=True, check=_check)


# --- adapter -----------------------------------------------------------------------------------------------

class DarkGradientParams(EffectParams):
    gradient_x_e_per_s: float = Field(0.05, ge=-1e6, le=1e6,
                                      description="dark-rate change across the sensor width [e-/s/pixel]")
    gradient_y_e_per_s: float = Field(0.0, ge=-1e6, le=1e6,
                                      description="dark-rate change across the sensor height [e-/s/pixel]")


@register_effect
class DarkGradient(Effect):
    """Dark-current gradient across the sensor (a temperature gradient over the die, Janesick 2001 eq. 7.4,
    linearised): adds ``(gx u + gy v) t`` [e-] to the dark charge, ``u, v`` in -0.5..0.5 across the sensor,
    never taking the pixel's dark charge below zero. Grows with exposure time; its shot noise is drawn with
    the rest of the dark charge."""

    name = "dark_gradient"
    scaling = "exposure"
    identity = {"gradient_x_e_per_s": 0.0, "gradient_y_e_per_s": 0.0}
    stages = (Stage.DARK,)
    signature = _SIGNATURE
    Params = DarkGradientParams

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        p, s = self.params, self.sensor
        if not tile.exptime_s or (p.gradient_x_e_per_s == 0 and p.gradient_y_e_per_s == 0):
            return
        ys, xs = tile.pixel_centres()
        m = gradient_rate(ys, xs, s.sensor_height_px, s.sensor_width_px, p.gradient_x_e_per_s, p.gradient_y_e_per_s)
        m *= np.float32(tile.exptime_s)
        data += m
        np.maximum(data, 0, out=data)
