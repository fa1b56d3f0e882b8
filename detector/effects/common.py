"""Helpers shared by the sparse-defect effects: positions drawn once on the full sensor."""

from __future__ import annotations

import numpy as np

from ..rng import generator
from ..sensor import SensorConfig
from .base import Tile


def draw_positions(rng: np.random.Generator, count: int, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """``count`` distinct pixel positions drawn uniformly on a ``height x width`` sensor, sorted by index.

    Uniform sampling without replacement by rejection of duplicates (count << pixels in practice).
    """
    n = height * width
    count = int(min(count, n))
    picked = np.unique(rng.integers(0, n, size=count, dtype=np.int64))
    while picked.size < count:
        more = rng.integers(0, n, size=count - picked.size, dtype=np.int64)
        picked = np.unique(np.concatenate([picked, more]))
    picked = rng.permutation(picked)[:count]
    picked.sort()
    return picked // width, picked % width


def hardware_positions(sensor: SensorConfig, name: str, count: int) -> tuple[np.ndarray, np.ndarray, np.random.Generator]:
    """Positions of ``count`` defects of stream ``name`` on the full sensor (hardware seed).

    Also returns the generator, positioned after the draw, for the defects' other properties.
    """
    rng = generator(sensor.hardware_seed, name)
    ys, xs = draw_positions(rng, count, sensor.sensor_height_px, sensor.sensor_width_px)
    return ys, xs, rng


def in_tile(tile: Tile, ys: np.ndarray, xs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Indices of the sensor positions inside ``tile`` and their (row, col) in the tile's current array."""
    sel = np.nonzero((ys >= tile.y0) & (ys < tile.y1) & (xs >= tile.x0) & (xs < tile.x1))[0]
    return sel, (ys[sel] - tile.y0) // tile.bin, (xs[sel] - tile.x0) // tile.bin


def roi_mask(sensor: SensorConfig, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """Which sensor positions fall inside the read-out window."""
    w, h = sensor.roi_shape
    return (ys >= sensor.roi_y0) & (ys < sensor.roi_y0 + h) & (xs >= sensor.roi_x0) & (xs < sensor.roi_x0 + w)


def output_xy(sensor: SensorConfig, ys: np.ndarray, xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """0-based (x, y) of sensor pixels in the written (binned) frame."""
    b = sensor.binning
    return (xs - sensor.roi_x0) // b, (ys - sensor.roi_y0) // b
