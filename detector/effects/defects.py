"""Sparse hardware defects: hot/warm/stuck pixels and column defects.

Hot pixels follow the reference thesis (eqs. 35-40): every defect has a *time-to-double* ``t2``, the
exposure after which its value has doubled its zero-exposure level, i.e. ``B + r t2 = 2 B`` with ``B`` the
bias [ADU] and ``r`` the defect's excess dark rate [ADU/s], so ``r_e = B g / t2`` electrons per second
(``g`` the gain in e-/ADU). ``t2`` is drawn from a Weibull law (shape ``k``, scale ``lambda``; the
exponential law is ``k = 1``), the distribution measured on the calibration darks (``characterize`` fits
the same law, eq. 38). Defects with ``t2`` below ``hot_threshold_s`` are *hot*, the others *warm*; a
fraction are *stuck*: their value is fixed whatever the exposure.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from .base import Effect, EffectParams, Stage, Tile, register_effect
from .common import hardware_positions, in_tile, output_xy, roi_mask


# --- pure functions ---------------------------------------------------------------------------------------

def draw_time_to_double(rng: np.random.Generator, n: int, law: str, shape: float, scale_s: float) -> np.ndarray:
    """Times-to-double [s] from a Weibull(shape k, scale lambda) law; ``exponential`` forces k = 1 (eq. 39-40)."""
    k = 1.0 if law == "exponential" else shape
    return scale_s * rng.weibull(k, size=n)


def hot_rate_e_per_s(t_double_s: np.ndarray, bias_adu: float, gain_e_per_adu: float) -> np.ndarray:
    """Excess dark current [e-/s] of a defect that doubles the bias level ``B`` after ``t2`` (eq. 38)."""
    return bias_adu * gain_e_per_adu / np.maximum(t_double_s, 1e-9)


# --- adapters ----------------------------------------------------------------------------------------------

class HotPixelParams(EffectParams):
    count: int = Field(1000, ge=0, le=10_000_000, description="defective pixels on the full sensor [pixels]")
    law: Literal["weibull", "exponential"] = "weibull"
    weibull_shape: float = Field(0.8, gt=0.05, le=20, description="Weibull shape k of time-to-double [1]")
    scale_s: float = Field(600.0, gt=0, le=1e9, description="Weibull scale lambda of time-to-double [s]")
    stuck_fraction: float = Field(0.0, ge=0, le=1, description="fraction of defects stuck at a fixed value [1]")
    stuck_value_adu: float | None = Field(None, ge=0, description="value of stuck pixels (default: ADC maximum) [ADU]")
    hot_threshold_s: float = Field(60.0, gt=0, description="t2 below which a defect is labelled hot, else warm [s]")


@register_effect
class HotPixels(Effect):
    """Hot, warm and stuck pixels with a Weibull (or exponential) law of time-to-double (thesis eqs. 35-40).

    Each defect adds ``r_e t`` electrons to the mean before the shot-noise draw (so it carries its own
    Poisson noise), with ``r_e = B g / t2`` (see module docstring). Stuck pixels are set to a fixed ADU value
    after the ADC. Positions and ``t2`` from the hardware seed: the same defects every frame.
    FITS table ``HOTPIX``: x, y, kind, t_double_s, rate_e_per_s.
    """

    name = "hot_pixels"
    stages = (Stage.DARK, Stage.DIGITAL)
    Params = HotPixelParams

    def setup(self) -> None:
        p, s = self.params, self.sensor
        self.ys, self.xs, rng = hardware_positions(s, self.name, p.count)
        n = self.ys.size
        self.t2 = draw_time_to_double(rng, n, p.law, p.weibull_shape, p.scale_s)
        self.rate = hot_rate_e_per_s(self.t2, s.bias_adu, s.gain_e_per_adu).astype(np.float32)
        self.stuck = rng.random(n) < p.stuck_fraction
        self.stuck_value = float(s.adc_max_adu if p.stuck_value_adu is None else min(p.stuck_value_adu, s.adc_max_adu))

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        sel, r, c = in_tile(tile, self.ys, self.xs)
        if stage is Stage.DARK:
            data[r, c] += self.rate[sel] * np.float32(tile.exptime_s)  # positions are distinct
        else:
            st = self.stuck[sel]
            data[r[st], c[st]] = self.stuck_value

    def truth(self, state=None) -> dict[str, np.ndarray]:
        m = roi_mask(self.sensor, self.ys, self.xs)
        x, y = output_xy(self.sensor, self.ys[m], self.xs[m])
        kind = np.where(self.stuck[m], "stuck", np.where(self.t2[m] < self.params.hot_threshold_s, "hot", "warm"))
        t = np.zeros(int(m.sum()), dtype=[("x", "i4"), ("y", "i4"), ("x_sensor", "i4"), ("y_sensor", "i4"),
                                            ("kind", "S5"), ("t_double_s", "f8"), ("rate_e_per_s", "f8")])
        t["x"], t["y"], t["x_sensor"], t["y_sensor"] = x, y, self.xs[m], self.ys[m]
        t["kind"], t["t_double_s"], t["rate_e_per_s"] = kind, self.t2[m], self.rate[m]
        return {"HOTPIX": t}


class ColumnDefectParams(EffectParams):
    hot_columns: int = Field(5, ge=0, le=100_000, description="columns with excess dark current [columns]")
    hot_rate_e_per_s: float = Field(5.0, ge=0, le=1e6, description="excess dark current of a hot column [e-/s]")
    dead_columns: int = Field(2, ge=0, le=100_000, description="columns without photo-response [columns]")


@register_effect
class ColumnDefects(Effect):
    """Hot and dead columns: a charge trap or a leaky transfer gate affects a whole column (Janesick 2007,
    ch. 8, "column defects"; common in CCDs, also in CMOS column amplifiers). Hot columns add
    ``hot_rate_e_per_s t`` electrons to the mean of every pixel of the column; dead columns lose their
    photo-response. Columns from the hardware seed; table ``COLDEF``.
    """

    name = "column_defects"
    stages = (Stage.RESPONSE, Stage.DARK)
    Params = ColumnDefectParams

    def setup(self) -> None:
        from ..rng import generator

        p, w = self.params, self.sensor.sensor_width_px
        rng = generator(self.sensor.hardware_seed, self.name)
        cols = rng.permutation(w)[: min(w, p.hot_columns + p.dead_columns)]
        self.hot, self.dead = np.sort(cols[: p.hot_columns]), np.sort(cols[p.hot_columns:])

    def _local(self, tile: Tile, cols: np.ndarray) -> np.ndarray:
        c = cols[(cols >= tile.x0) & (cols < tile.x1)]
        return (c - tile.x0) // tile.bin

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        if stage is Stage.RESPONSE:
            data[:, self._local(tile, self.dead)] = 0.0
        else:
            data[:, self._local(tile, self.hot)] += np.float32(self.params.hot_rate_e_per_s * tile.exptime_s)

    def truth(self, state=None) -> dict[str, np.ndarray]:
        s = self.sensor
        cols = np.concatenate([self.hot, self.dead])
        kind = np.array(["hot"] * self.hot.size + ["dead"] * self.dead.size, dtype="S4")
        inside = (cols >= s.roi_x0) & (cols < s.roi_x0 + s.roi_shape[0])
        t = np.zeros(int(inside.sum()), dtype=[("x", "i4"), ("x_sensor", "i4"), ("kind", "S4"), ("rate_e_per_s", "f8")])
        t["x_sensor"], t["kind"] = cols[inside], kind[inside]
        t["x"] = (cols[inside] - s.roi_x0) // s.binning
        t["rate_e_per_s"] = np.where(kind[inside] == b"hot", self.params.hot_rate_e_per_s, 0.0)
        return {"COLDEF": t}
