"""Measured calibration maps as effects: a master bias's structure and a master flat's response.

A camera's fixed patterns can be *measured* rather than drawn: the master bias (mean of many bias frames,
Janesick 2007, Photon Transfer, ch. 9; Howell 2006, Handbook of CCD Astronomy, sect. 4.3) holds the bias
structure (column offsets, ramps, amplifier patterns) with the read noise averaged down by 1/sqrt(N); the
normalised master flat (Howell 2006, sect. 4.4) holds the pixel response non-uniformity and the vignetting
and dust of the optical path. Applying them to a synthetic frame reproduces that camera's patterns exactly
(``signature = None``: there is nothing to fit, the map is the measurement).

``bias_map`` (ADU stage, where the bias is not yet added): adds scale x (M - median(M)) [ADU], M the map
and the median over the whole map, so ``[detector] bias_adu`` stays the level and the map gives the
structure. A CCD that bins in charge reads each binned pixel once: it gets the mean of the map over its
b x b sensor pixels (the binned read's bias, as ``bias_gradient`` takes the bias shape at the binned
pixel's centre). A CMOS reads every pixel and bins digitally after the ADC: each pixel gets its own
bias, and the binning sums (or averages) them with the signal.

``flat_map`` (RESPONSE stage, multiplies the expected photo-electrons of every pixel; the dark signal is
not affected): multiplies by F / mean(F), F the map, the mean over the whole map (a flat normalised to mean
1). It acts on unbinned pixels before any binning, so a binned frame sees the (signal-weighted) average of
the flat over each b x b block, as it sees PRNU.

Geometry. A map is either the **full sensor** (``sensor_height_px x sensor_width_px``: the read-out window
``x0, y0, width, height`` is cut out of it) or the **read-out window** itself (``height x width``: a master
made from frames of the same window). Maps are unbinned sensor pixels; anything else is an error naming the
file, the key and the shapes expected.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pydantic import Field

from ..errors import DetectorError
from .base import Effect, EffectParams, Stage, Tile, register_effect


def read_map(path: str | Path, hdu: int | str | None, key: str) -> np.ndarray:
    """The 2-D image of ``path`` (HDU ``hdu``, or the first image) as float64; errors name file and key."""
    from astropy.io import fits

    from ..fits_io import read_image

    if hdu is None:
        data, _ = read_image(path, key=key, role="calibration map")
        return np.asarray(data, dtype=np.float64)
    p = Path(path)
    if not p.is_file():
        raise DetectorError("calibration map not found", key=key, file=str(p), expected="an existing FITS file")
    try:
        with fits.open(p) as hdul:
            data = hdul[hdu].data
    except (KeyError, IndexError):
        raise DetectorError(f"no HDU {hdu!r}", key=key.rsplit(".", 1)[0] + ".hdu", file=str(p),
                            expected="an HDU index or EXTNAME of the file") from None
    except (OSError, ValueError, TypeError) as exc:
        raise DetectorError(f"cannot be read as FITS ({type(exc).__name__}: {exc})", key=key, file=str(p),
                            expected="a FITS image") from None
    if data is None or np.ndim(data) != 2:
        raise DetectorError(f"HDU {hdu!r} holds no 2-D image (shape {np.shape(data)})", key=key, file=str(p),
                            expected="a 2-D image")
    return np.asarray(data, dtype=np.float64)


def window_of(full: np.ndarray, sensor, path, key: str) -> np.ndarray:
    """The read-out window's part of a full-sensor or window-sized map (rows, cols of the window)."""
    (h, w), y0, x0 = sensor.shape, sensor.roi_y0, sensor.roi_x0
    full_shape = (sensor.sensor_height_px, sensor.sensor_width_px)
    if full.shape == full_shape:
        return full[y0:y0 + h, x0:x0 + w]
    if full.shape == (h, w):
        return full
    raise DetectorError(f"map of shape {full.shape[0]} x {full.shape[1]} (rows x cols) does not match the sensor",
                        key=key, file=str(path), expected=f"the full sensor {full_shape[0]} x {full_shape[1]} or the "
                        f"read-out window {h} x {w} (rows x cols, unbinned)")


def block_mean(a: np.ndarray, b: int) -> np.ndarray:
    """Mean over b x b blocks (the shape is a multiple of b)."""
    if b == 1:
        return a
    r, c = a.shape
    return a.reshape(r // b, b, c // b, b).mean(axis=(1, 3))


def _finite(m: np.ndarray, path, key: str) -> None:
    if not np.all(np.isfinite(m)):
        raise DetectorError(f"{int(np.sum(~np.isfinite(m)))} non-finite values", key=key, file=str(path),
                            expected="finite values")


class MapParams(EffectParams):
    path: str = Field(description="FITS map (master bias [ADU] or flat [1]), unbinned, full sensor or the read-out "
                      "window (in a scene: relative to the scene file)", json_schema_extra={"unit": "path"})
    hdu: int | str | None = Field(None, description="HDU index or EXTNAME (default: the first image)")


class BiasMapParams(MapParams):
    scale: float = Field(1.0, ge=-100, le=100, description="factor on the structure (M - median M) [1]",
                         json_schema_extra={"unit": "1"})


class _MapEffect(Effect):
    """Common part of the map effects: ``self._map`` over the read-out window, cut to a tile."""

    _map: np.ndarray

    def load(self) -> tuple[np.ndarray, str]:
        """(the whole map, finite-checked; the params key of its path) for error messages."""
        p, key = self.params, f"effects.{self.name}.path"
        full = read_map(p.path, p.hdu, key)
        _finite(full, p.path, key)
        return full, key

    def on_tile(self, tile: Tile) -> np.ndarray:
        """The window map's unbinned pixels of ``tile``."""
        s = self.sensor
        return self._map[tile.y0 - s.roi_y0:tile.y1 - s.roi_y0, tile.x0 - s.roi_x0:tile.x1 - s.roi_x0]


@register_effect
class BiasMap(_MapEffect):
    """A measured master bias's structure added at the ADU stage: scale x (M - median M) [ADU].

    CCD binning: the mean of the map over each binned pixel; CMOS: per pixel (binned digitally later).
    """

    name = "bias_map"
    no_identity = "a measured map: its zero is a map of zeros (tests/detector/test_maps.py)"
    stages = (Stage.ADU,)
    Params = BiasMapParams
    signature = None

    def setup(self) -> None:
        (full, key), p = self.load(), self.params
        win = window_of(full, self.sensor, p.path, key)
        self._map = ((win - float(np.median(full))) * p.scale).astype(np.float32)  # window, unbinned [ADU]

    def structure_adu(self, tile: Tile) -> np.ndarray:
        """The bias structure [ADU] on the tile's current pixels (binned for a CCD after charge binning)."""
        return block_mean(self.on_tile(tile), tile.bin).astype(np.float32)

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        data += self.structure_adu(tile)


@register_effect
class FlatMap(_MapEffect):
    """A measured flat field multiplying the light: F / mean(F) per unbinned pixel (RESPONSE stage)."""

    name = "flat_map"
    no_identity = "a measured map: its identity is a map of ones (tests/detector/test_maps.py)"
    stages = (Stage.RESPONSE,)
    Params = MapParams
    signature = None

    def setup(self) -> None:
        (full, key), p = self.load(), self.params
        mean = float(np.mean(full))
        if not mean > 0 or np.any(full < 0):
            raise DetectorError(f"flat with mean {mean:.4g} and minimum {float(full.min()):.4g}", key=key,
                                file=str(p.path), expected="a flat field: values >= 0 with a positive mean")
        self._map = (window_of(full, self.sensor, p.path, key) / mean).astype(np.float32)

    def response(self, tile: Tile) -> np.ndarray:
        """F / mean(F) [1] on the tile's (unbinned) pixels."""
        return self.on_tile(tile)

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        data *= self.response(tile)
