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
from scipy.ndimage import binary_dilation

from ..signatures import (
    Fit,
    LinearSignature,
    Signature,
    VarianceSignature,
    Variant,
    ml_variance_scale,
)
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


# --- diagnosis signatures (detector.signatures) -------------------------------------------------------------

class RowOffsetSignature(Signature):
    """Row noise: the means of the residual rows scatter more than the pixel noise allows (ML of the extra
    variance of the row means; each output row of a CMOS with ``b x b`` sum binning adds ``b^3`` row
    offsets worth of variance, one of a binned CCD row one).

    Physically, row offsets are independent from row to row (a new offset per row read: Janesick 2007,
    Photon Transfer, ch. 10) and leave the column means alone. A fit whose row offsets form a smooth curve
    (a polynomial of the row index takes most of their excess variance), or that comes with an equal
    scatter of the column means, is a 2-D pattern (a gradient, a radial fall-off) seen through the rows:
    :meth:`plausible` says so."""

    kind = "rows"
    pattern = "row means scatter beyond the pixel noise"
    #: a row-offset fit is a smooth curve when a polynomial of this degree in the row index takes more than
    #: SMOOTH_FRACTION of the row means' excess chi2
    SMOOTH_DEGREE, SMOOTH_FRACTION = 4, 0.8
    #: ... or a pattern of the whole frame when the column means' excess variance is this fraction of the rows'
    COLUMN_FRACTION = 0.5
    #: ... or a drift when the extra row offsets (the smooth curve removed) keep this lag-1 autocorrelation: row
    #: noise draws a new offset for every row read (Janesick 2007, ch. 10); a 1/f (pink) part correlates
    #: neighbours far less (0.44 for the hidden-effect suite's pink row noise; 0.75 for a bias random walk)
    MAX_LAG1 = 0.6

    @staticmethod
    def line_means(res, axis: int = 1):
        """Means of the level-profiled residual along ``axis`` (1: row means, 0: column means) over the
        fitted pixels away from spikes, their variances [ADU^2] and which lines have enough pixels."""
        keep = res.fit & ~binary_dilation(~res.fit, structure=np.ones((3, 3), bool), iterations=2)
        cnt = keep.sum(axis=axis)
        ok = cnt > 1
        level, level_var = res.level_maps()  # the global levels refitted (detector.signatures.Residuals.levels)
        r = np.where(keep, res.data_adu - res.model_adu - level, 0.0).sum(axis=axis)[ok] / cnt[ok]
        v = np.where(keep, res.var_adu2 + level_var, 0.0).sum(axis=axis)[ok] / cnt[ok] ** 2
        return r.astype(np.float64), v.astype(np.float64), ok

    def fit(self, res, name):
        # the pixels next to a spike (a cosmic-ray track's diffusion halo, a hot pixel's neighbours) are not
        # part of the row level: leave them out of the row means
        r, v, ok = self.line_means(res)
        if ok.sum() < 8:
            return None
        theta, d = ml_variance_scale(r, v, np.ones_like(v, np.float64), z_cap=1e6)
        if theta <= 0:
            return None
        b = res.sensor.binning
        per_row = b ** 3 if res.sensor.kind != "ccd" and res.sensor.binning_mode == "sum" else 1
        sigma_e = float(np.sqrt(theta / per_row)) * res.gain
        return Fit(name, {"sigma_e": round(sigma_e, 4)}, d, 1, int(ok.sum()),
                   f"every row offset by its own amount, {sigma_e:.3g} e- rms: row (banding) noise",
                   extra_var_adu2=theta)

    def score(self, fit, res):
        """Gaussian delta(-2 ln L) of the row means of ``res`` with the fit's extra variance per row mean."""
        r, v, ok = self.line_means(res)
        if not ok.any():
            return 0.0
        theta = float(np.asarray(fit.extra_var_adu2, np.float64).ravel()[0])
        return float(np.sum(np.log1p(theta / v) + r * r / (v + theta) - r * r / v))

    def plausible(self, fit, res) -> str:
        r, v, ok = self.line_means(res)
        theta = float(np.asarray(fit.extra_var_adu2, np.float64).ravel()[0])
        n = r.size
        if n >= 3 * (self.SMOOTH_DEGREE + 1):
            x = np.linspace(-1.0, 1.0, n)
            basis = np.polynomial.legendre.legvander(x, self.SMOOTH_DEGREE)
            wts = 1.0 / (v + theta)
            coef = np.linalg.lstsq(basis * np.sqrt(wts)[:, None], r * np.sqrt(wts), rcond=None)[0]
            excess = float(np.sum(r * r / v) - n)
            smooth = float(np.sum((basis @ coef) ** 2 / v))
            if excess > 0 and smooth > self.SMOOTH_FRACTION * excess:
                return (f"the row offsets form a smooth curve (a degree-{self.SMOOTH_DEGREE} polynomial of the row "
                        f"takes {100 * min(smooth / excess, 1):.0f} % of their excess): a large-scale 2-D pattern "
                        "seen through the rows, not independent row noise")
            # independent from row to row: the lag-1 autocorrelation of what the smooth curve leaves (whitened)
            # (of the extra offsets: the pixel noise of the row means, white, dilutes it by (chi2/n - 1) / (chi2/n))
            u = (r - basis @ coef) * np.sqrt(wts)
            rho1 = float(np.dot(u[1:], u[:-1]) / max(np.dot(u, u), 1e-300))
            ratio = float(np.sum(r * r / v)) / n
            rho_extra = rho1 * ratio / (ratio - 1) if ratio > 1 else 0.0
            if rho_extra > self.MAX_LAG1 and rho1 * np.sqrt(n) > 5:
                return (f"the row offsets are correlated from one row to the next (lag-1 correlation {rho_extra:.2f} "
                        f"of the extra offsets, {rho1 * np.sqrt(n):.0f} sigma): a level drifting during the read-out "
                        "or a slow pickup, not independent row noise")
        rc, vc, okc = self.line_means(res, axis=0)
        if okc.sum() >= 8:
            theta_c, _ = ml_variance_scale(rc, vc, np.ones_like(vc), z_cap=1e6)
            if theta_c > self.COLUMN_FRACTION * theta:
                return (f"the column means scatter as much as the row means ({np.sqrt(max(theta_c, 0)):.3g} vs "
                        f"{np.sqrt(theta):.3g} ADU rms): a 2-D pattern, not row offsets")
        return ""


def _ktc_params(theta: float, res) -> dict | None:
    # one reset per read: a CCD reads a binned pixel once, a CMOS sums (or averages) b^2 reads digitally
    s = res.sensor
    reads = 1.0 if s.kind == "ccd" else float(s.binning ** 2)
    sigma_e2 = theta * res.gain ** 2 * (reads if s.binning_mode == "average" else 1.0 / reads)
    t_k = res.sensor.temperature_c + 273.15
    c_ff = sigma_e2 * Q_ELECTRON ** 2 / (K_BOLTZMANN * t_k) * 1e15
    return {"capacitance_ff": float(f"{c_ff:.5g}")} if 0 < c_ff <= 1e4 else None  # significant digits: > 0


def _bias_variants(res):
    s = res.sensor
    f = np.float32(res.adu_sum)
    u = (res.xs / max(s.sensor_width_px - 1, 1) - 0.5).astype(np.float32)
    v = (res.ys / max(s.sensor_height_px - 1, 1) - 0.5).astype(np.float32)
    # the ramps are a row and a column (they broadcast); the bowl is 2-D
    unit = [(f * u)[None, :], (f * v)[:, None],
            bias_shape_adu(res.ys, res.xs, s.sensor_height_px, s.sensor_width_px, 0.0, 0.0, 1.0) * f]

    def to_params(c):
        # a bias structure cannot take the bias below zero: |shape| at the sensor's corners <= the bias level
        worst = abs(c[0]) / 2 + abs(c[1]) / 2 + abs(c[2])
        return ({"gradient_x_adu": round(float(c[0]), 4), "gradient_y_adu": round(float(c[1]), 4),
                 "quadratic_adu": round(float(c[2]), 4)} if worst <= s.bias_adu else None)

    yield Variant(unit, to_params)


def _bias_words(p, res) -> str:
    parts = [f"{p['gradient_x_adu']:+.3g} ADU across the columns", f"{p['gradient_y_adu']:+.3g} ADU across the rows",
             f"{p['quadratic_adu']:+.3g} ADU bowl at the corners"]
    return "an additive offset independent of the signal, " + ", ".join(parts) + ": bias structure"


def _crosstalk_variants(res):
    s = res.sensor
    sig = (res.model_adu - (s.bias_adu - 0.5) * res.adu_sum).astype(np.float32)
    for n in (2, 4, 8, 16):
        for mirrored in (True, False):
            t = sig.copy()
            channel_crosstalk(t, n, 1.0, mirrored)
            t -= sig

            def to_params(c, n=n, mirrored=mirrored):
                return ({"n_channels": n, "alpha": round(float(c[0]), 7), "mirrored": mirrored}
                        if abs(c[0]) <= 0.1 and c[0] != 0 else None)

            yield Variant([t], to_params, f"{n} channels{' mirrored' if mirrored else ''}")


_ROW_SIGNATURE = RowOffsetSignature()
_KTC_SIGNATURE = VarianceSignature(
    lambda res: np.ones(1), _ktc_params,
    lambda p, res: (f"white scatter independent of signal and exposure, as from a {p['capacitance_ff']:.3g} fF "
                    "sense node: kTC reset noise (or a read noise above the data sheet)"),
    pattern="extra variance constant over the frame")
_BIAS_SIGNATURE = LinearSignature(_bias_variants, _bias_words, pattern="additive ramps/bowl, independent of signal",
                                  extra_k=0)
#: the largest electronic crosstalk coefficient a camera shows [1]: measured coefficients are 1e-5 .. 1e-3
#: (LSST sensors, Snyder et al. 2021, JATIS 7, 048002; DECam, Bernstein et al. 2017, PASP 129, 114502)
CROSSTALK_MAX = 0.01


def _crosstalk_check(fit, res) -> str:
    """Crosstalk copies compact bright sources into the other channels, by a coefficient of at most ~1e-3:
    a coefficient of per cents is a structure of the light itself taken for copies; and on a flat-screen
    frame every channel's copy of the uniform light is uniform, a step between channels (a gain), not a copy
    of a source."""
    a = abs(fit.params["alpha"])
    if a > CROSSTALK_MAX:
        return (f"a coupling of {a:.3g} is {a / 1e-3:.0f} times the largest crosstalk measured in cameras "
                f"(~1e-3): a pattern of the light taken for copies of sources")
    if res.light_source == "flat":
        return ("on a flat-screen frame the copies of the uniform light are uniform per channel: a step between "
                "channels (gains), not crosstalk of sources")
    return ""


_CROSSTALK_SIGNATURE = LinearSignature(
    _crosstalk_variants,
    lambda p, res: (f"faint copies of bright sources in the other {p['n_channels'] - 1} read-out channels, "
                    f"{p['alpha']:.2g} of the source: crosstalk"),
    pattern="ghost copies of bright sources in other channels", check=_crosstalk_check)


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
    scaling = "none"
    identity = {"sigma_e": 0.0}
    stages = (Stage.READ,)
    Params = RowNoiseParams
    stochastic = True
    signature = _ROW_SIGNATURE

    def variance_e2(self, stage: Stage, tile: Tile, mean_e) -> float:
        return self.params.sigma_e ** 2

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
    scaling = "none"
    identity = {"correlated_double_sampling": True}
    stages = (Stage.READ,)
    Params = ResetNoiseParams
    stochastic = True
    signature = _KTC_SIGNATURE

    def variance_e2(self, stage: Stage, tile: Tile, mean_e) -> float:
        return self.sigma_e() ** 2

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
    scaling = "none"
    identity = {"gradient_x_adu": 0.0, "gradient_y_adu": 0.0, "quadratic_adu": 0.0}
    stages = (Stage.ADU,)
    Params = BiasGradientParams
    signature = _BIAS_SIGNATURE

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        p, s = self.params, self.sensor
        ys, xs = tile.pixel_centres()
        data += bias_shape_adu(ys, xs, s.sensor_height_px, s.sensor_width_px, p.gradient_x_adu,
                               p.gradient_y_adu, p.quadratic_adu)


class CrosstalkParams(EffectParams):
    n_channels: int = Field(4, ge=2, le=64, description="read-out channels (vertical stripes) across the sensor [channels]")
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
    scaling = "signal"
    identity = {"alpha": 0.0}
    stages = (Stage.ADU,)
    Params = CrosstalkParams
    signature = _CROSSTALK_SIGNATURE

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        channel_crosstalk(data, self.params.n_channels, self.params.alpha, self.params.mirrored)
