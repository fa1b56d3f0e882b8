"""Read-out electronics: row noise, kTC reset noise, bias structure and inter-channel crosstalk.

References
----------
* J. R. Janesick, *Photon Transfer*, SPIE Press (2007), ch. 4 (read noise, kTC reset noise), ch. 9.
* Reference thesis eq. 33 (reset noise sigma = sqrt(k T C) / q).
* EMVA Standard 1288 Release 4.0, sec. 4.3 / 8.3: row and column (spatial) noise.
* A. C. Moore et al., SPIE 5499 (2004); LSST Camera crosstalk papers (e.g. Snyder et al., JATIS 2021):
  electronic crosstalk between read-out channels as a linear coupling coefficient.
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from .base import Effect, EffectParams, Stage, Tile, register_effect

K_BOLTZMANN = 1.380649e-23  # J/K
Q_ELECTRON = 1.602176634e-19  # C


# --- pure functions ---------------------------------------------------------------------------------------

def ktc_noise_e(temperature_k: float, capacitance_f: float) -> float:
    """kTC reset noise [e- rms] of a sense node of capacitance ``C`` [F] at ``T`` [K]: sqrt(k T C) / q (eq. 33)."""
    return float(np.sqrt(K_BOLTZMANN * temperature_k * capacitance_f) / Q_ELECTRON)


def bias_shape_adu(ys: np.ndarray, xs: np.ndarray, height: int, width: int, gx: float, gy: float, q: float
                   ) -> np.ndarray:
    """Bias structure [ADU] on sensor coordinates: linear ramps (total ``gx``, ``gy`` across the sensor,
    zero at the centre) plus a radial bowl worth ``q`` at the corners."""
    u = (xs / max(width - 1, 1) - 0.5)[None, :]
    v = (ys / max(height - 1, 1) - 0.5)[:, None]
    out = gx * u + gy * v
    if q:
        out = out + q * (u * u + v * v) / 0.5
    return np.broadcast_to(out, (ys.size, xs.size)).astype(np.float32)


def channel_crosstalk(data: np.ndarray, n_channels: int, alpha: float, mirrored: bool) -> None:
    """In place: every channel (vertical stripe) receives ``alpha`` times the signal of every other channel.

    Channels are ``n_channels`` equal stripes of columns; with ``mirrored`` every second channel is read
    from the other side, so the coupled image appears mirrored (as on multi-amplifier CCDs). Works on the
    bias-free signal [ADU]; ``alpha`` [1] is the victim/source coupling.
    """
    rows, cols = data.shape
    wc = cols // n_channels
    if n_channels < 2 or alpha == 0 or wc == 0:
        return
    used = wc * n_channels
    view = data[:, :used].reshape(rows, n_channels, wc)
    oriented = view.copy()
    if mirrored:
        oriented[:, 1::2] = oriented[:, 1::2, ::-1]
    total = oriented.sum(axis=1)  # (rows, wc): every channel in read-out order
    for j in range(n_channels):
        others = total - oriented[:, j]
        if mirrored and j % 2:
            others = others[:, ::-1]
        view[:, j] += np.float32(alpha) * others


# --- adapters ----------------------------------------------------------------------------------------------

class RowNoiseParams(EffectParams):
    sigma_e: float = Field(2.0, ge=0, le=1e4, description="std of the per-row offset, new every frame [e-]")


@register_effect
class RowNoise(Effect):
    """Correlated row (banding) noise: every read-out row gets one Gaussian offset per frame.

    Typical of column-parallel CMOS read-out where a row shares its reference and supply (EMVA 1288 R4.0
    sec. 8.3, row/column noise; Janesick 2007 ch. 9). Frame seed.
    """

    name = "row_noise"
    stages = (Stage.READ,)
    Params = RowNoiseParams

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        if self.params.sigma_e:
            off = tile.rng(self.name).standard_normal(data.shape[0], dtype=np.float32) * np.float32(self.params.sigma_e)
            data += off[:, None]


class ResetNoiseParams(EffectParams):
    capacitance_ff: float = Field(2.0, gt=0, le=1e4, description="sense-node capacitance [fF]")
    temperature_k: float | None = Field(None, gt=0, le=500, description="node temperature (default: sensor) [K]")
    correlated_double_sampling: bool = Field(False, description="CDS removes kTC noise (then the effect is the identity)")


@register_effect
class ResetNoise(Effect):
    """kTC reset noise: resetting the sense node leaves a charge uncertainty sqrt(k T C)/q (thesis eq. 33).

    Present in every read that follows a reset without correlated double sampling (3T pixels, CCD output
    without CDS); CDS subtracts it exactly. Added once per read-out pixel (per binned pixel on a CCD).
    """

    name = "reset_noise"
    stages = (Stage.READ,)
    Params = ResetNoiseParams

    def sigma_e(self) -> float:
        p = self.params
        if p.correlated_double_sampling:
            return 0.0
        t = p.temperature_k if p.temperature_k is not None else self.sensor.temperature_c + 273.15
        return ktc_noise_e(t, p.capacitance_ff * 1e-15)

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        sigma = self.sigma_e()
        if sigma:
            n = tile.rng(self.name).standard_normal(data.shape, dtype=np.float32)
            n *= np.float32(sigma)
            data += n


class BiasGradientParams(EffectParams):
    gradient_x_adu: float = Field(5.0, ge=-1e4, le=1e4, description="bias change across the sensor width [ADU]")
    gradient_y_adu: float = Field(0.0, ge=-1e4, le=1e4, description="bias change across the sensor height [ADU]")
    quadratic_adu: float = Field(0.0, ge=-1e4, le=1e4, description="bias bowl: corner minus centre [ADU]")


@register_effect
class BiasGradient(Effect):
    """Spatial structure of the bias level: linear ramps and a radial bowl [ADU], the same every frame.

    Seen in bias frames of large CMOS and CCD sensors (amplifier warm-up, reference-voltage drop along the
    column bus; Janesick 2007 ch. 9). Deterministic, zero at the sensor centre.
    """

    name = "bias_gradient"
    stages = (Stage.ADU,)
    Params = BiasGradientParams

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        p, s = self.params, self.sensor
        ys, xs = tile.pixel_centres()
        data += bias_shape_adu(ys, xs, s.sensor_height_px, s.sensor_width_px, p.gradient_x_adu,
                               p.gradient_y_adu, p.quadratic_adu)


class CrosstalkParams(EffectParams):
    n_channels: int = Field(4, ge=2, le=64, description="read-out channels (vertical stripes) across the sensor")
    alpha: float = Field(1e-3, ge=-0.1, le=0.1, description="coupling coefficient victim/source [1]")
    mirrored: bool = Field(True, description="every second channel read from the other side")


@register_effect
class Crosstalk(Effect):
    """Electronic crosstalk between read-out channels: a bright source in one channel leaves a faint
    (possibly mirrored) ghost of ``alpha`` times its signal in every other channel.

    Linear coupling model of multi-channel read-out (LSST crosstalk, Snyder et al. JATIS 7, 2021; Moore et
    al. SPIE 5499). Channels are stripes of the read-out window; parts of channels outside a region of
    interest do not couple.
    """

    name = "crosstalk"
    stages = (Stage.ADU,)
    Params = CrosstalkParams

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        channel_crosstalk(data, self.params.n_channels, self.params.alpha, self.params.mirrored)
