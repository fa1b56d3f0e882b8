"""The sensor description: a preset plus overrides, region of interest, binning and seeds.

All geometric quantities are in sensor pixels (0-based, ``x`` = column, ``y`` = row) unless named
``binned``. A region of interest (ROI) is a window of the full sensor; hardware defects are drawn in full
sensor coordinates so the same pixel carries the same defect whatever the ROI.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from .config import validate
from .errors import DetectorError
from .presets import PRESETS


class SensorConfig(BaseModel):
    """A fully resolved sensor. Units are in the field names."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = "custom"
    kind: Literal["cmos", "ccd"]
    sensor_width_px: int = Field(gt=0, le=100_000)
    sensor_height_px: int = Field(gt=0, le=100_000)
    pixel_pitch_um: float = Field(gt=0, le=100)
    shutter: Literal["rolling", "global"]
    line_time_s: float = Field(ge=0, le=1.0, description="rolling-shutter row delay (thesis eq. 10) [s]")
    bit_depth: int = Field(ge=8, le=32)
    gain_e_per_adu: float = Field(gt=0, le=1000)
    bias_adu: float = Field(ge=0)
    read_noise_e: float = Field(ge=0, le=1000)
    dark_current_e_per_s: float = Field(ge=0, le=1e6)
    full_well_e: float = Field(gt=0, le=1e8)
    temperature_c: float = Field(ge=-273.15, le=150)
    qe_wavelength_nm: list[float]
    qe: list[float]
    # region of interest (sensor pixels); None = full sensor, ROI centred when x0/y0 are not given
    width: int | None = Field(default=None, gt=0)
    height: int | None = Field(default=None, gt=0)
    x0: int | None = Field(default=None, ge=0)
    y0: int | None = Field(default=None, ge=0)
    binning: int = Field(default=1, ge=1, le=16)
    binning_mode: Literal["sum", "average"] = "sum"
    hardware_seed: int = Field(default=20230201, ge=0, description="seed of the fixed hardware pattern")

    @model_validator(mode="after")
    def _check(self):
        if len(self.qe) != len(self.qe_wavelength_nm) or len(self.qe) < 2:
            raise ValueError("qe and qe_wavelength_nm must have the same length (>= 2)")
        if any(q < 0 or q > 1 for q in self.qe):
            raise ValueError("qe values must lie in [0, 1]")
        if self.bias_adu >= 2 ** self.bit_depth:
            raise ValueError(f"bias_adu {self.bias_adu} does not fit in {self.bit_depth} bits")
        w, h = self.roi_shape
        if self.roi_x0 + w > self.sensor_width_px or self.roi_y0 + h > self.sensor_height_px:
            raise ValueError(f"region of interest {w}x{h} at ({self.roi_x0},{self.roi_y0}) does not fit the "
                             f"{self.sensor_width_px}x{self.sensor_height_px} sensor")
        if w % self.binning or h % self.binning:
            raise ValueError(f"region of interest {w}x{h} is not a multiple of binning {self.binning}")
        return self

    # --- derived geometry -------------------------------------------------------------------------
    @property
    def roi_shape(self) -> tuple[int, int]:
        """(width, height) of the read-out window in sensor pixels."""
        return (self.width or self.sensor_width_px, self.height or self.sensor_height_px)

    @property
    def roi_x0(self) -> int:
        w = self.width or self.sensor_width_px
        return self.x0 if self.x0 is not None else (self.sensor_width_px - w) // 2

    @property
    def roi_y0(self) -> int:
        h = self.height or self.sensor_height_px
        return self.y0 if self.y0 is not None else (self.sensor_height_px - h) // 2

    @property
    def shape(self) -> tuple[int, int]:
        """Unbinned (rows, cols) of the read-out window."""
        w, h = self.roi_shape
        return (h, w)

    @property
    def output_shape(self) -> tuple[int, int]:
        """(rows, cols) of the frame written to disk, after binning."""
        h, w = self.shape
        return (h // self.binning, w // self.binning)

    @property
    def adc_max_adu(self) -> int:
        return 2 ** self.bit_depth - 1

    def summed_bias_saturates(self) -> str | None:
        """Why every pixel of the digital frame saturates, or None. A CMOS bins after the ADC: in "sum" mode
        an output pixel adds the bias of ``binning**2`` pixels, and when that sum alone reaches the ADC's
        maximum (the IMX411 at 16 x 16: 256 x 500 = 128,000 ADU > 65,535) nothing of the signal is left."""
        b = self.binning
        if self.kind != "cmos" or b == 1 or self.binning_mode != "sum" or b * b * self.bias_adu < self.adc_max_adu:
            return None
        top = int((self.adc_max_adu / self.bias_adu) ** 0.5) if self.bias_adu > 0 else b
        return (f"binning {b}x{b} in 'sum' mode adds the bias of {b * b} pixels ({b * b} x {self.bias_adu:g} = "
                f"{b * b * self.bias_adu:,.0f} ADU), above the {self.bit_depth}-bit maximum {self.adc_max_adu:,} ADU: "
                f"every pixel of the frame saturates; use detector.binning_mode = 'average', a binning of at most "
                f"{top}, or a lower bias_adu")

    @property
    def row_time_s(self) -> float:
        """Delay between the exposure starts of consecutive read-out rows (0 for a global shutter)."""
        return self.line_time_s if self.shutter == "rolling" else 0.0

    def qe_at(self, wavelength_nm) -> np.ndarray:
        """Quantum efficiency (electrons per photon) interpolated linearly, 0 outside the table."""
        return np.interp(wavelength_nm, self.qe_wavelength_nm, self.qe, left=0.0, right=0.0)


def make_sensor(preset: str = "imx411", overrides: dict | None = None, *, file: str | None = None,
                prefix: str = "detector") -> SensorConfig:
    """Build a :class:`SensorConfig` from a preset name and a dict of overrides.

    Parameters
    ----------
    preset : {"imx411", "ml11002"}
    overrides : dict
        Any :class:`SensorConfig` field (``gain_e_per_adu``, ``width``, ``binning`` ...).
    file, prefix : str
        Used in error messages (``scene.toml: key 'detector.gain_e_per_adu' ...``).
    """
    if preset not in PRESETS:
        raise DetectorError(f"unknown preset {preset!r}", key=f"{prefix}.preset",
                            expected=" or ".join(repr(p) for p in PRESETS), file=file)
    data = dict(PRESETS[preset])
    data.update(overrides or {})
    try:
        return validate(SensorConfig, data, prefix=prefix, file=file)
    except DetectorError as exc:
        if exc.key == prefix:  # a model-level check: report the message it raised
            raise DetectorError(exc.expected or exc.message, key=prefix, file=file) from None
        raise
