"""Measured calibration maps as effects: a master bias's structure, a dark-rate map and a flat's response.

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

``dark_map`` (DARK stage, adds to the expected electrons before the shot-noise draw): every pixel's dark
signal becomes ``R t`` [e-], R the map of per-pixel dark rates [e-/s] (hot and warm pixels at their real
positions with their measured rates, and the dark-signal non-uniformity of the bulk): it adds
``(R - I_d) t``, ``I_d`` the sensor's ``dark_current_e_per_s`` already in the mean. Pixels listed in the
optional ``STUCK`` table (x, y, value_adu; sensor pixels) are set to their value after the ADC in every
frame of non-zero exposure (stuck or saturated-from-the-start defects; Janesick 2007, ch. 7). With the
map's ``temperature_c`` and the sensor's, the rates scale as ``2^((T - T_map) / doubling_c)`` (the dark
current doubles every ~6-7 C in silicon CCDs near -10 C; Widenhorn et al. 2002, Proc. SPIE 4669, 193).

``noise_map`` (READ stage, new every frame): each read draws an extra Gaussian whose standard deviation
[e-] is the map's (a measured per-pixel temporal noise beyond the sensor's ``read_noise_e``; a CCD's binned
read gets the quadratic mean over its pixels). ``newtsim diagnose --apply`` writes one when the residual is
extra noise that no catalogue effect explains (a read noise that grows across the frame).

Uncertainty. A map measured from a few frames carries their noise. ``flat_map`` and ``dark_map`` accept
``sigma_hdu``, an HDU of the same file holding each pixel's standard error (flat: in units of the map;
dark: e-/s); the model of the mean frame (:meth:`detector.Detector.moments`) then adds that error to each
pixel's variance (``(sigma_F/mean F)^2 S^2`` and ``(sigma_R t)^2`` [e-^2]), so a comparison with a real frame
is not biased by the map's own noise (the variance of a product of independent estimates, to first order).

``dark_rate_tail`` (no map: a *population law*, for sensors without calibration frames): ``count`` pixels
of the full sensor, placed by the hardware seed, with an excess dark rate above ``floor_e_per_s`` drawn from
a Pareto law ``P(R > r) = (r / floor)^-alpha`` (truncated at ``max_e_per_s``), a lognormal truncated at the
floor, or an empirical quantile table measured by ``characterize``. The counts of pixels above a threshold
``thr`` then grow with exposure as ``count P(R > thr / t)`` (``~ t^alpha`` for the Pareto law), the growth
measured on real darks.

Geometry. A map is either the **full sensor** (``sensor_height_px x sensor_width_px``: the read-out window
``x0, y0, width, height`` is cut out of it) or the **read-out window** itself (``height x width``: a master
made from frames of the same window). Maps are unbinned sensor pixels; anything else is an error naming the
file, the key and the shapes expected.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from ..errors import DetectorError
from ..rng import standard_normal_f32
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


class SigmaMapParams(MapParams):
    sigma_hdu: int | str | None = Field(None, description="HDU of the same file with each pixel's standard error "
                                        "(added to the model's variance; default: none)")


class DarkMapParams(SigmaMapParams):
    stuck_hdu: int | str | None = Field(None, description="HDU of a table (x, y, value_adu) of stuck pixels "
                                        "(sensor pixels; default: none)")
    temperature_c: float | None = Field(None, ge=-150, le=100, description="temperature the map was measured at; "
                                        "with the sensor's temperature_c the rates scale as 2^(dT / doubling_c) [C]",
                                        json_schema_extra={"unit": "C"})
    doubling_c: float = Field(6.3, gt=0, le=50, description="temperature step that doubles the dark current [C]",
                              json_schema_extra={"unit": "C"})
    offset_e: float = Field(0.0, ge=-1e6, le=1e6, description="signal every frame of non-zero exposure has above the "
                            "bias frames (the darks' intercept minus the bias, e.g. dark current during read-out) [e-]",
                            json_schema_extra={"unit": "e-"})


class BiasMapParams(MapParams):
    scale: float = Field(1.0, ge=-100, le=100, description="factor on the structure (M - median M) [1]",
                         json_schema_extra={"unit": "1"})


class _MapEffect(Effect):
    """Common part of the map effects: ``self._map`` over the read-out window, cut to a tile."""

    _map: np.ndarray
    #: the model of the mean frame asks ``variance_e2`` of this effect (a map with a standard-error plane)
    adds_variance: bool = False

    def load(self) -> tuple[np.ndarray, str]:
        """(the whole map, finite-checked; the params key of its path) for error messages."""
        p, key = self.params, f"effects.{self.name}.path"
        full = read_map(p.path, p.hdu, key)
        _finite(full, p.path, key)
        return full, key

    def load_sigma(self, full_shape: tuple[int, int]) -> np.ndarray | None:
        """The standard-error plane (``sigma_hdu``) over the read-out window, or None."""
        p = self.params
        hdu = getattr(p, "sigma_hdu", None)
        if hdu is None:
            return None
        key = f"effects.{self.name}.sigma_hdu"
        sig = read_map(p.path, hdu, key)
        _finite(sig, p.path, key)
        if sig.shape != full_shape or np.any(sig < 0):
            raise DetectorError(f"standard-error plane of shape {sig.shape} (minimum {float(sig.min()):.3g})", key=key,
                                file=str(p.path), expected=f"values >= 0 of the map's shape {full_shape}")
        self.adds_variance = True
        return window_of(sig, self.sensor, p.path, key).astype(np.float32)

    def sigma_on_tile(self, tile: Tile) -> np.ndarray:
        s = self.sensor
        return self._sigma[tile.y0 - s.roi_y0:tile.y1 - s.roi_y0, tile.x0 - s.roi_x0:tile.x1 - s.roi_x0]

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
    field_kind = "additive"
    scaling = "none"
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
    field_kind = "multiplicative"
    scaling = "signal"
    no_identity = "a measured map: its identity is a map of ones (tests/detector/test_maps.py)"
    stages = (Stage.RESPONSE,)
    Params = SigmaMapParams
    signature = None

    def setup(self) -> None:
        (full, key), p = self.load(), self.params
        mean = float(np.mean(full))
        if not mean > 0 or np.any(full < 0):
            raise DetectorError(f"flat with mean {mean:.4g} and minimum {float(full.min()):.4g}", key=key,
                                file=str(p.path), expected="a flat field: values >= 0 with a positive mean")
        self._map = (window_of(full, self.sensor, p.path, key) / mean).astype(np.float32)
        sig = self.load_sigma(full.shape)
        self._sigma = None if sig is None else sig / np.float32(mean)

    def variance_e2(self, stage: Stage, tile: Tile, mean_e: np.ndarray) -> float | np.ndarray:
        """(sigma_F / mean F)^2 S^2 [e-^2]: the map's own error on the expected signal S [e-]."""
        if self._sigma is None:
            return 0.0
        return (self.sigma_on_tile(tile) * mean_e) ** 2

    def response(self, tile: Tile) -> np.ndarray:
        """F / mean(F) [1] on the tile's (unbinned) pixels."""
        return self.on_tile(tile)

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        data *= self.response(tile)


@register_effect
class DarkMap(_MapEffect):
    """A measured dark-rate map: every pixel's dark signal is R t [e-], R the map [e-/s] (DARK stage).

    Hot and warm pixels sit at their measured positions with their measured rates; the optional ``STUCK``
    table sets stuck pixels after the ADC (frames of non-zero exposure only).
    """

    name = "dark_map"
    field_kind = "additive"
    scaling = "exposure"
    no_identity = "a measured map: its zero is a map of zeros (tests/detector/test_camtwin.py)"
    stages = (Stage.DARK, Stage.DIGITAL)
    Params = DarkMapParams
    signature = None

    def setup(self) -> None:
        (full, key), p = self.load(), self.params
        self._map = window_of(full, self.sensor, p.path, key).astype(np.float32)  # [e-/s]
        self._sigma = self.load_sigma(full.shape)
        self.temperature_factor = 1.0
        t_sensor = getattr(self.sensor, "temperature_c", None)
        if p.temperature_c is not None and t_sensor is not None:
            # dark current doubles every doubling_c degrees (Widenhorn et al. 2002, Proc. SPIE 4669, 193)
            self.temperature_factor = float(2.0 ** ((t_sensor - p.temperature_c) / p.doubling_c))
            self._map *= np.float32(self.temperature_factor)
            if self._sigma is not None:
                self._sigma *= np.float32(self.temperature_factor)
        self._stuck = None
        if p.stuck_hdu is not None:
            from astropy.io import fits

            skey = f"effects.{self.name}.stuck_hdu"
            try:
                with fits.open(p.path) as hdul:
                    tab = hdul[p.stuck_hdu].data
                    xs, ys, v = (np.asarray(tab[c]) for c in ("x", "y", "value_adu"))
            except (KeyError, IndexError, TypeError, AttributeError):
                raise DetectorError(f"no table HDU {p.stuck_hdu!r} with columns x, y, value_adu", key=skey,
                                    file=str(p.path), expected="a FITS table (x, y, value_adu) of stuck pixels") from None
            self._stuck = (ys.astype(np.int64), xs.astype(np.int64), v.astype(np.float32))

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        t = np.float32(tile.exptime_s)
        if stage is Stage.DARK:
            if t:
                data += (self.on_tile(tile) - np.float32(self.sensor.dark_current_e_per_s)) * t \
                    + np.float32(self.params.offset_e)
            return
        if self._stuck is None or not t:
            return
        from .common import in_tile

        ys, xs, v = self._stuck
        sel, r, c = in_tile(tile, ys, xs)
        data[r, c] = np.minimum(v[sel], np.float32(self.sensor.adc_max_adu))

    def variance_e2(self, stage: Stage, tile: Tile, mean_e: np.ndarray) -> float | np.ndarray:
        """(sigma_R t)^2 [e-^2]: the map's own error on the dark signal."""
        if self._sigma is None or stage is not Stage.DARK:
            return 0.0
        return (self.sigma_on_tile(tile) * np.float32(tile.exptime_s)) ** 2


class NoiseMapParams(MapParams):
    pass


@register_effect
class NoiseMap(_MapEffect):
    """A measured map of extra read noise: each read draws an extra Gaussian of the map's sigma [e-] (READ
    stage, new every frame). The per-pixel temporal noise of a CMOS (EMVA 1288 R4, sect. 8.2: the spatial
    distribution of the temporal noise; its noisy-pixel tail) or a read noise that changes across a CCD's
    output (a gradient from the amplifier), measured as the standard deviation of each pixel over a stack of
    bias frames minus the sensor's ``read_noise_e`` in quadrature. A CCD that bins in charge reads each binned
    pixel once: it gets the quadratic mean of the map over its b x b sensor pixels; a CMOS reads every pixel."""

    name = "noise_map"
    scaling = "none"
    no_identity = "a measured map: its zero is a map of zeros (tests/detector/test_plausibility.py)"
    stages = (Stage.READ,)
    Params = NoiseMapParams
    stochastic = True
    signature = None

    def setup(self) -> None:
        (full, key), p = self.load(), self.params
        if np.any(full < 0):
            raise DetectorError(f"negative values (minimum {float(full.min()):.3g})", key=key, file=str(p.path),
                                expected="a map of standard deviations >= 0 [e-]")
        self._map = window_of(full, self.sensor, p.path, key).astype(np.float32)  # [e-] per read

    def variance_on_tile(self, tile: Tile) -> np.ndarray:
        """The extra read variance [e-^2] of the tile's current pixels (one read per binned CCD pixel)."""
        return block_mean(self.on_tile(tile).astype(np.float64) ** 2, tile.bin).astype(np.float32)

    def variance_e2(self, stage: Stage, tile: Tile, mean_e: np.ndarray) -> float | np.ndarray:
        return self.variance_on_tile(tile)

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        n = standard_normal_f32(tile.rng(self.name), data.shape)
        n *= np.sqrt(self.variance_on_tile(tile))
        data += n


# --- the dark-rate population law (no map) -------------------------------------------------------------------

def tail_probabilities(n: int, n_body: int = 40, n_tail: int = 40) -> np.ndarray:
    """Probabilities for a quantile table of ``n`` values: equally spaced up to 0.9, then ``1 - 10^-k`` down to
    ``1 / n`` (the tail, where the counts above high thresholds live, is resolved), then 1."""
    body = np.linspace(0.0, 0.9, n_body, endpoint=False)
    tail = 1.0 - np.logspace(-1.0, math.log10(max(1.0 / max(n, 1), 1e-9)), n_tail)
    return np.unique(np.concatenate([body, tail, [1.0]]))


def draw_excess_rates(rng: np.random.Generator, n: int, law: str, floor: float, alpha: float, max_rate: float,
                      log_mu: float, log_sigma: float, quantiles: list[float],
                      probabilities: list[float] | None = None) -> np.ndarray:
    """Excess dark rates [e-/s] above ``floor`` (inverse-CDF draws).

    ``pareto``: ``r = floor u^(-1/alpha)`` truncated at ``max_rate`` (``u`` uniform on the part of (0, 1] that
    stays below it); ``lognormal``: ``ln r ~ N(log_mu, log_sigma)`` conditioned on ``r > floor``;
    ``empirical``: linear interpolation of the quantile table ``quantiles`` (at ``probabilities``, default
    equally spaced ``0 .. 1``) in the logarithm of the rate.
    """
    from scipy import stats

    u = rng.random(n)
    if law == "pareto":
        umin = (max_rate / floor) ** (-alpha) if math.isfinite(max_rate) else 0.0
        return floor * (umin + u * (1 - umin)) ** (-1.0 / alpha)
    if law == "lognormal":
        p0 = stats.norm.cdf((math.log(floor) - log_mu) / log_sigma)
        return np.exp(log_mu + log_sigma * stats.norm.ppf(p0 + u * (1 - p0)))
    q = np.log(np.asarray(quantiles, dtype=np.float64))
    p = np.linspace(0, 1, q.size) if not probabilities else np.asarray(probabilities, dtype=np.float64)
    return np.exp(np.interp(u, p, q))


class DarkTailParams(EffectParams):
    count: int = Field(1000, ge=0, le=50_000_000, description="pixels of the full sensor with an excess dark rate "
                       "above floor_e_per_s [pixels]")
    law: Literal["pareto", "lognormal", "empirical"] = "pareto"
    floor_e_per_s: float = Field(1.0, gt=0, le=1e7, description="lower end of the excess rates [e-/s]",
                                 json_schema_extra={"unit": "e-/s"})
    alpha: float = Field(1.0, gt=0.05, le=20, description="Pareto index: P(R > r) = (r / floor)^-alpha [1]")
    max_e_per_s: float = Field(math.inf, gt=0, description="upper truncation of the Pareto law [e-/s]",
                               json_schema_extra={"unit": "e-/s"})
    log_mu: float = Field(0.0, ge=-50, le=50, description="lognormal: mean of ln(rate / (e-/s)) [1]")
    log_sigma: float = Field(1.0, gt=0, le=20, description="lognormal: std of ln(rate / (e-/s)) [1]")
    quantiles_e_per_s: list[float] = Field(default_factory=list, description="empirical: rates at the probabilities, "
                                           "increasing [e-/s]")
    probabilities: list[float] = Field(default_factory=list, description="empirical: probabilities of the quantiles, "
                                       "increasing from 0 to 1 (default: equally spaced) [1]")

    @model_validator(mode="after")
    def _check(self):
        if self.law == "empirical":
            q = self.quantiles_e_per_s
            if len(q) < 2 or any(not (math.isfinite(v) and v > 0) for v in q) or any(b < a for a, b in zip(q, q[1:])):
                raise ValueError("law 'empirical' needs quantiles_e_per_s: two or more finite rates > 0, increasing")
            pr = self.probabilities
            if pr and (len(pr) != len(q) or pr[0] != 0 or pr[-1] != 1 or any(b <= a for a, b in zip(pr, pr[1:]))):
                raise ValueError("probabilities must increase from 0 to 1, one per quantile")
        if self.max_e_per_s <= self.floor_e_per_s:
            raise ValueError("max_e_per_s must exceed floor_e_per_s")
        return self


@register_effect
class DarkRateTail(Effect):
    """A population of hot and warm pixels whose excess dark rates follow a Pareto, lognormal or empirical law.

    Each pixel adds ``r t`` electrons to the mean before the shot-noise draw (its own Poisson noise);
    positions and rates from the hardware seed (the same pixels every frame). FITS table ``DARKPIX``.
    """

    name = "dark_rate_tail"
    scaling = "exposure"
    identity = {"count": 0}
    stages = (Stage.DARK,)
    Params = DarkTailParams
    pattern = True
    signature = None

    def setup(self) -> None:
        from .common import hardware_positions

        p = self.params
        self.ys, self.xs, rng = hardware_positions(self.sensor, self.name, p.count)
        self.rate = draw_excess_rates(rng, self.ys.size, p.law, p.floor_e_per_s, p.alpha, p.max_e_per_s, p.log_mu,
                                      p.log_sigma, p.quantiles_e_per_s,
                                       p.probabilities).astype(np.float32)

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        from .common import in_tile

        sel, r, c = in_tile(tile, self.ys, self.xs)
        data[r, c] += self.rate[sel] * np.float32(tile.exptime_s)

    def truth(self, state=None) -> dict[str, np.ndarray]:
        from .common import output_xy, roi_mask

        m = roi_mask(self.sensor, self.ys, self.xs)
        x, y = output_xy(self.sensor, self.ys[m], self.xs[m])
        t = np.zeros(int(m.sum()), dtype=[("x", "i4"), ("y", "i4"), ("rate_e_per_s", "f8")])
        t["x"], t["y"], t["rate_e_per_s"] = x, y, self.rate[m]
        return {"DARKPIX": t}


class ColumnOffsetParams(EffectParams):
    sigma_adu: float = Field(0.5, ge=0, le=1e4, description="std of the column offsets of the core [ADU]",
                             json_schema_extra={"unit": "adu"})
    outlier_fraction: float = Field(0.0, ge=0, le=1, description="fraction of columns drawn from the outlier "
                                    "table instead [1]")
    outlier_quantiles_adu: list[float] = Field(default_factory=list, description="outlier columns' offsets at "
                                               "equally spaced probabilities 0..1, increasing [ADU]")

    @model_validator(mode="after")
    def _check(self):
        q = self.outlier_quantiles_adu
        if self.outlier_fraction > 0 and (len(q) < 2 or any(b < a for a, b in zip(q, q[1:]))
                                          or not all(math.isfinite(v) for v in q)):
            raise ValueError("outlier_fraction > 0 needs outlier_quantiles_adu: two or more increasing finite values")
        return self


@register_effect
class ColumnOffsets(Effect):
    """A fixed bias offset per column [ADU] (the column pattern of a CCD's or column-parallel ADC's bias).

    Core columns ``N(0, sigma_adu)``; a fraction from a measured quantile table (the outlier columns a master
    bias shows; Janesick 2007, ch. 9). ADU stage, hardware seed: the same columns every frame. A CCD that
    bins in charge gets the mean of its b columns.
    """

    name = "column_offsets"
    scaling = "none"
    identity = {"sigma_adu": 0.0, "outlier_fraction": 0.0}
    stages = (Stage.ADU,)
    Params = ColumnOffsetParams
    pattern = True
    signature = None

    def setup(self) -> None:
        from ..rng import generator

        p, s = self.params, self.sensor
        rng = generator(s.hardware_seed, self.name)
        w = s.sensor_width_px
        off = rng.standard_normal(w) * p.sigma_adu
        if p.outlier_fraction > 0:
            sel = rng.random(w) < p.outlier_fraction
            q = np.asarray(p.outlier_quantiles_adu, dtype=np.float64)
            off[sel] = np.interp(rng.random(int(sel.sum())), np.linspace(0, 1, q.size), q)
        self.offsets = off.astype(np.float32)

    def variance_e2(self, stage: Stage, tile: Tile, mean_e: np.ndarray) -> float:
        return 0.0  # a fixed pattern of the bias, compared through the residual's column profile

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        off = self.offsets[tile.x0:tile.x1]
        if tile.bin > 1:
            off = off.reshape(-1, tile.bin).mean(axis=1)
        data += off[None, :]
