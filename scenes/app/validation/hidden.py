"""Prove the diagnosis on data with a hidden effect: the confusion matrix of ``newtsim diagnose``.

For every detector effect of the catalogue that has a diagnosis signature, a "measured" frame is made
from a model scene plus ONE effect the scene does not contain, in a *real-world* form that differs from
the plugin's own (functional form and amplitude: the real world never matches a plugin), e.g. a glow
falling as a power law from a point beyond the corner instead of the plugin's exponential edge, a
cos^4 vignetting about an off-axis centre instead of ``1 - a2 rho^2 - a4 rho^4``, a bias with a ripple
and an amplifier step, a cubic nonlinearity, a gamma-distributed DSNU with a low-frequency part, hot
pixels with a lognormal rate law, 1/f row noise, a Bayer CFA with a dye jitter and a drifting red response,
moonlight rising exponentially towards the Moon ... Every measured frame also carries the nuisances of a
real camera that the model only knows statistically or approximately:

* its own hardware: the measured sensor has another ``hardware_seed`` (hot pixels at other positions);
* cosmic rays of that frame (the model scene has ``[effects.cosmic_rays]``, so it knows their rate);
* a slightly wrong light level (flat screen or sky, 1-2 %), dark current (2-3 %) and bias (< 1 ADU).

The variants are Effects (:class:`detector.effects.Effect` subclasses, not registered: the diagnosis
never sees their names) added to the measured camera's chain, so each acts at its physical stage:
additive charge (glow, DSNU, hot pixels, hot columns) before the Poisson draw, so it carries shot noise;
read-out effects (nonlinearity, kTC, row noise) on the charge before read noise; ADU effects (bias
structure, crosstalk, amplifier gains) after the conversion, without shot noise.

Each frame is diagnosed against its model scene (:func:`scenes.app.compare.run_diagnose`); the first-ranked
significant candidate is compared with the hidden effect (a confusion matrix, "none" when nothing is
significant), the candidate is applied (:func:`scenes.app.compare.apply.apply_candidate`) and the frame
compared again with the new scene (:func:`scenes.app.compare.run_compare`). The null cases (no hidden effect,
one per base scene) must give no significant candidate.

The error is measured with the global levels profiled (:func:`detector.signatures.level_profiled`): the
bias offset, the light level and the dark level the model can only know to a few per cent are refitted
(as every reduction does with the overscan and a normalised flat) before ``chi2_per_dof`` and the
``misfit`` of :func:`scenes.app.compare.statistics.compare` are computed. The error of a case is
``chi2/dof - 1`` over the hidden effect's support (the pixels whose expected value it changes by more
than 0.2 sigma; all pixels for an effect that adds noise) for effects the model predicts pixel by pixel,
and the ``misfit`` (standardised excess of the pixel, outlier-count and row/column deviances) for effects
compared statistically (hot and dead pixels, column defects, cosmic rays). It must fall by at least half
once the candidate is applied. See docs/diagnose_validation.md.

Usage::

    python examples/diagnose/hidden_effects.py [OUT_DIR] [--effects a,b,...] [--no-null] [--keep]

writes ``OUT_DIR/confusion.md``, ``confusion.json`` and ``confusion.png`` (default OUT_DIR:
``hidden_effects_out``). The test ``tests/scenes/test_diagnose_hidden.py`` runs the same cases.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import tomli_w

from detector import Detector
from detector.effects.base import Effect, Stage, Tile
from detector.effects.blooming import bleed_columns
from detector.effects.cosmic_rays import CosmicRayParams, CosmicRays
from detector.effects.readout import K_BOLTZMANN, Q_ELECTRON
from detector.rng import generator

#: the detector effects whose diagnosis is proved here (catalogue effects with a signature)
EFFECTS = ("amp_glow", "bias_gradient", "blooming", "cfa", "column_defects", "cosmic_rays", "crosstalk", "dead_pixels",
           "dsnu", "gain_regions", "hot_pixels", "nonlinearity", "prnu", "reset_noise", "row_noise", "sky_gradient",
           "vignetting", "cti", "brighter_fatter", "ipc", "rts_noise")

#: the measured camera's hardware seed (the model scene keeps the preset's): other defect positions
MEASURED_HARDWARE_SEED = 77_123_401

# --- base scenes: each makes a class of effects observable ----------------------------------------------------

_NUISANCE = {"hot_pixels": {"count": 2000, "weibull_shape": 0.8, "scale_s": 600.0},
             "cosmic_rays": {"environment": "ground"}}

BASES: dict[str, dict] = {
    # a flat-field screen on a 512x512 window at the centre of the CCD: multiplicative pixel effects
    "flat": {"detector": {"preset": "ml11002", "width": 512, "height": 512},
             "exposure": {"time_s": 10.0, "frame": "light"},
             "sky": {"stars": False, "flat_e_per_s": 1500.0}},
    # the whole CCD binned 8x8 under a faint flat: effects laid out in sensor coordinates (vignetting,
    # amplifier regions)
    "flat_full": {"detector": {"preset": "ml11002", "binning": 8},
                  "exposure": {"time_s": 10.0, "frame": "light"},
                  "sky": {"stars": False, "flat_e_per_s": 30.0}},
    # a 300 s dark on a 512x512 window of the CCD: dark-current and read-out effects
    "dark": {"detector": {"preset": "ml11002", "width": 512, "height": 512},
             "exposure": {"time_s": 300.0, "frame": "dark"},
             "sky": {"stars": False}},
    # a 120 s dark on the 1024x1024 corner of the CMOS next to its read-out amplifier, binned 2x2: glow
    "dark_corner": {"detector": {"preset": "imx411", "width": 1024, "height": 1024, "x0": 13168, "y0": 0,
                                 "binning": 2},
                    "exposure": {"time_s": 120.0, "frame": "dark"},
                    "sky": {"stars": False}},
    # a 10 s dark on a 512x512 window of the CMOS (read noise 3.5 e-): pixel-level read-out effects (RTS)
    "dark_cmos": {"detector": {"preset": "imx411", "width": 512, "height": 512},
                  "exposure": {"time_s": 10.0, "frame": "dark"},
                  "sky": {"stars": False}},
    # bias frames of the whole CCD, binned 8x8: bias structure
    "bias_full": {"detector": {"preset": "ml11002", "binning": 8},
                  "exposure": {"time_s": 0.0, "frame": "bias"},
                  "sky": {"stars": False}},
    # a 10 s star field (stars to mag 15, a few saturated) on a 512x512 window: effects of bright sources
    "stars": {"detector": {"preset": "ml11002", "width": 512, "height": 512},
              "pointing": {"ra_deg": 120.95115, "dec_deg": -29.25022, "epoch": "2023-02-01T22:00:00"},
              "exposure": {"time_s": 10.0, "frame": "light", "tracking": "sidereal"},
              "sky": {"background_mag_arcsec2": 19.72, "stars": True, "star_mag_limit": 15.0},
              "psf": {"model": "gaussian", "fwhm_arcsec": 3.0}},
}


def model_scene(base: str, hidden: str | None = None) -> dict:
    """The model scene of a case: the base plus hot pixels and cosmic rays (the nuisances it knows of),
    without the hidden effect (the base scene never has a hot_pixels/cosmic_rays table hidden from it)."""
    d = copy.deepcopy(BASES[base])
    d["effects"] = {k: dict(v) for k, v in _NUISANCE.items() if k != hidden}
    return d


@dataclass
class Levels:
    """How far the measured camera's global levels are from the model's (the "slightly wrong" model)."""

    light: float = 0.015  #: relative error of the flat-screen or sky level [1]
    dark: float = -0.03  #: relative error of the dark current [1]
    bias_adu: float = 0.6  #: bias offset [ADU]


def measured_scene(base: str, levels: Levels) -> dict:
    """The measured camera's scene: the base with another hardware seed and slightly different levels."""
    from detector.presets import PRESETS

    d = copy.deepcopy(BASES[base])
    det = d["detector"]
    preset = PRESETS[det["preset"]]
    det["hardware_seed"] = MEASURED_HARDWARE_SEED
    det["dark_current_e_per_s"] = preset["dark_current_e_per_s"] * (1 + levels.dark)
    det["bias_adu"] = preset["bias_adu"] + levels.bias_adu
    sky = d["sky"]
    if sky.get("flat_e_per_s"):
        sky["flat_e_per_s"] = sky["flat_e_per_s"] * (1 + levels.light)
    elif sky.get("background_mag_arcsec2") is not None:
        sky["background_mag_arcsec2"] = sky["background_mag_arcsec2"] - 2.5 * np.log10(1 + levels.light)
    d["effects"] = copy.deepcopy(_NUISANCE)
    return d


# --- the real-world variants ------------------------------------------------------------------------------------

class RealWorld(Effect):
    """Base of a real-world variant: an Effect acting at its physical stage, not registered in the catalogue."""

    name = "real_world"
    #: True when the change is a fixed pattern drawn per pixel (a DSNU map, with or without large scales): a frame
    #: made without the map shows its white part only as the law of its pixel values, an excess scatter, and its
    #: large scales as a template (:func:`scatter_sigma`), not as the exact template its truth chi2 assumes known
    pixel_scatter = False

    def __init__(self, sensor, **params):
        super().__init__(SimpleNamespace(**params), sensor)

    def describe_truth(self) -> dict:
        return dict(vars(self.params))


def _uv(tile: Tile) -> tuple[np.ndarray, np.ndarray]:
    """Normalised sensor coordinates u (columns), v (rows) in [0, 1] of the tile's current pixels."""
    ys, xs = tile.pixel_centres()
    s = tile.sensor
    return xs / (s.sensor_width_px - 1), ys / (s.sensor_height_px - 1)


def low_frequency_map(seed: int, u: np.ndarray, v: np.ndarray, rms: float, n_waves: int = 12,
                      max_cycles: float = 6.0) -> np.ndarray:
    """A smooth random field of ``rms`` on sensor coordinates: a sum of plane waves of random direction, phase
    and up to ``max_cycles`` cycles across the sensor (continuous across tiles and windows)."""
    rng = np.random.default_rng(seed)
    k = rng.uniform(0.5, max_cycles, n_waves) * 2 * np.pi
    ang = rng.uniform(0, np.pi, n_waves)
    ph = rng.uniform(0, 2 * np.pi, n_waves)
    out = np.zeros((v.size, u.size))
    for kk, a, p in zip(k, ang, ph):
        out += np.cos(kk * (np.cos(a) * u[None, :] + np.sin(a) * v[:, None]) + p)
    return (out * rms / np.sqrt(n_waves / 2)).astype(np.float32)


class PowerLawGlow(RealWorld):
    """Amplifier glow as a power law of the distance to a point just beyond the corner of the sensor,
    ``A (1 + (d/d0)^2)^(-p/2)`` [e-/s], plus a faint Gaussian halo (not the plugin's exponential edge)."""

    name = "rw_glow"
    stages = (Stage.DARK,)

    def apply(self, stage, tile, data):
        p, s = self.params, self.sensor
        ys, xs = tile.pixel_centres()
        xc, yc = s.sensor_width_px - 1 + p.beyond_px, -p.beyond_px
        d2 = (xs[None, :] - xc) ** 2 + (ys[:, None] - yc) ** 2
        rate = p.amplitude_e_per_s * (1 + d2 / p.d0_px ** 2) ** (-p.index / 2)
        rate += p.halo_e_per_s * np.exp(-d2 / (2 * p.halo_sigma_px ** 2))
        data += (rate * tile.exptime_s).astype(np.float32)


class RippleStepBias(RealWorld):
    """Bias structure [ADU]: a ramp along the rows, a long-period ripple along the columns and a step
    between the two output amplifiers (left/right halves), not the plugin's ramps and bowl."""

    name = "rw_bias"
    stages = (Stage.ADU,)

    def apply(self, stage, tile, data):
        p = self.params
        u, v = _uv(tile)
        shape = (p.ramp_y_adu * (v - 0.5))[:, None] + (p.ripple_adu * np.sin(2 * np.pi * p.ripple_cycles * u + 0.7)
                                                        + p.step_adu * (u >= 0.5))[None, :]
        data += shape.astype(np.float32)  # per read-out value (a CMOS bins after this stage, a CCD before)


class LossyBleed(RealWorld):
    """Blooming of a sensor with a partial anti-blooming drain: charge above ``threshold`` x full well spills
    along the column, ``up_fraction`` of it upwards, after the drain removed ``drain`` of the excess."""

    name = "rw_bleed"
    stages = (Stage.FIELD,)

    def apply(self, stage, tile, data):
        p = self.params
        thr = np.float32(p.threshold * self.sensor.full_well_e)
        excess = np.maximum(data - thr, 0)
        data -= np.float32(p.drain) * excess
        bleed_columns(data, float(thr), p.up_fraction)


class TrapColumns(RealWorld):
    """Hot columns of a CCD: a charge trap in the column leaks into every pixel transferred through it (the
    rows between it and the serial register), at a lognormal rate per column (not the plugin's whole
    columns at one rate)."""

    name = "rw_columns"
    stages = (Stage.DARK,)

    def setup(self):
        p, s = self.params, self.sensor
        rng = generator(s.hardware_seed, self.name)
        lo, hi = s.roi_x0, s.roi_x0 + s.roi_shape[0]
        self.cols = rng.choice(np.arange(lo, hi), p.n_columns, replace=False)
        self.trap_row = rng.integers(s.roi_y0 + s.roi_shape[1] // 3, s.roi_y0 + s.roi_shape[1], p.n_columns)
        self.rate = p.median_rate_e_per_s * np.exp(p.sigma_ln * rng.standard_normal(p.n_columns))

    def apply(self, stage, tile, data):
        ys, xs = tile.pixel_centres()
        for c, t, r in zip(self.cols, self.trap_row, self.rate):
            j = np.nonzero(np.abs(xs - c) < tile.bin / 2 + 1e-9)[0]
            if j.size:
                data[ys < t, j[0]] += np.float32(r * tile.exptime_s)

    def describe_truth(self):
        return {**vars(self.params), "rates_e_per_s": [round(float(r), 3) for r in self.rate]}


class AlphaBlobs(CosmicRays):
    """Alpha particles from a radioactive window: short, dense blobs (a second population of tracks)."""

    name = "rw_alpha"


class CouplingMatrixCrosstalk(RealWorld):
    """Crosstalk between ``n`` read-out channels with a coupling that falls with the channel distance
    (``alpha / 2.5^(|i - j| - 1)``), not mirrored: not the plugin's single coefficient."""

    name = "rw_crosstalk"
    stages = (Stage.ADU,)

    def apply(self, stage, tile, data):
        p = self.params
        rows, cols = data.shape
        wc = cols // p.n_channels
        view = data[:, :wc * p.n_channels].reshape(rows, p.n_channels, wc)
        src = view.copy()
        for i in range(p.n_channels):
            for j in range(p.n_channels):
                if i != j:
                    view[:, i] += np.float32(p.alpha / 2.5 ** (abs(i - j) - 1)) * src[:, j]


class VariableDeadPixels(RealWorld):
    """Dead and weak pixels with a uniform spread of residual response in [0, max_response], a fifth of them
    in pairs (not the plugin's single response)."""

    name = "rw_dead"
    stages = (Stage.RESPONSE,)

    def setup(self):
        from detector.effects.common import hardware_positions

        p, s = self.params, self.sensor
        self.ys, self.xs, rng = hardware_positions(s, self.name, p.count)
        self.resp = rng.uniform(0, p.max_response, self.ys.size).astype(np.float32)
        self.pair = rng.random(self.ys.size) < 0.2

    def apply(self, stage, tile, data):
        from detector.effects.common import in_tile

        sel, r, c = in_tile(tile, self.ys, self.xs)
        data[r, c] *= self.resp[sel]
        pr = self.pair[sel] & (c + 1 < data.shape[1])
        data[r[pr], c[pr] + 1] *= self.resp[sel][pr]


class GammaDSNU(RealWorld):
    """DSNU with a gamma law of relative std ``sigma`` and a smooth low-frequency part of ``lf_rms`` (not the
    plugin's white lognormal map)."""

    name = "rw_dsnu"
    pixel_scatter = True
    stages = (Stage.DARK,)

    def apply(self, stage, tile, data):
        p = self.params
        k = 1 / p.sigma ** 2
        m = tile.hardware_map(self.name, lambda rng, shape: rng.gamma(k, 1 / k, shape).astype(np.float32))
        u, v = _uv(tile)
        lf = low_frequency_map(self.sensor.hardware_seed + 1, u, v, p.lf_rms)
        dark = np.float32(self.sensor.dark_current_e_per_s * tile.exptime_s)
        data += dark * (m * (1 + lf) - 1)


class DriftingGainRegions(RealWorld):
    """Amplifier gains of a 2x2 read-out whose column boundary is off the centre and whose gain drifts
    linearly across each amplifier (not the plugin's uniform grid regions)."""

    name = "rw_gains"
    stages = (Stage.ADU,)

    def apply(self, stage, tile, data):
        p = self.params
        u, v = _uv(tile)
        ix = (u >= p.split_u).astype(int)
        iy = (v >= 0.5).astype(int)
        g = np.asarray(p.gains).reshape(2, 2)[iy[:, None], ix[None, :]]
        g = g * (1 + p.drift * (u[None, :] - 0.5))
        data *= g.astype(np.float32)


class LognormalHotPixels(RealWorld):
    """Hot pixels whose excess dark rates follow a lognormal law (median, sigma of ln) instead of the
    plugin's Weibull law of time-to-double."""

    name = "rw_hot"
    stages = (Stage.DARK,)

    def setup(self):
        from detector.effects.common import hardware_positions

        p = self.params
        self.ys, self.xs, rng = hardware_positions(self.sensor, self.name, p.count)
        self.rate = (p.median_e_per_s * np.exp(p.sigma_ln * rng.standard_normal(self.ys.size))).astype(np.float32)

    def apply(self, stage, tile, data):
        from detector.effects.common import in_tile

        sel, r, c = in_tile(tile, self.ys, self.xs)
        data[r, c] += self.rate[sel] * np.float32(tile.exptime_s)


class CubicNonlinearity(RealWorld):
    """Response ``S' = S (1 - gamma (S / FW)^2)``: cubic, not the plugin's quadratic."""

    name = "rw_nonlinearity"
    stages = (Stage.READ,)

    def apply(self, stage, tile, data):
        fw = self.sensor.full_well_e * tile.bin ** 2
        x = data / np.float32(fw)
        data *= 1 - np.float32(self.params.gamma) * x * x


class LowFrequencyPRNU(RealWorld):
    """PRNU with a white Gaussian part and a smooth low-frequency part (coating and thickness variations)."""

    name = "rw_prnu"
    stages = (Stage.RESPONSE,)
    #: drawn per pixel as a DSNU is (its smooth part a template, :func:`scatter_sigma`)
    pixel_scatter = True

    def apply(self, stage, tile, data):
        p = self.params
        white = tile.hardware_map(self.name, lambda rng, shape: rng.standard_normal(shape, dtype=np.float32))
        u, v = _uv(tile)
        lf = low_frequency_map(self.sensor.hardware_seed + 2, u, v, p.lf_rms, max_cycles=p.lf_cycles)
        data *= 1 + np.float32(p.white) * white + lf


class VariableKTC(RealWorld):
    """kTC reset noise of sense nodes whose capacitance varies from pixel to pixel (lognormal spread), so
    the noise variance is not the same everywhere (the plugin: one capacitance)."""

    name = "rw_ktc"
    stages = (Stage.READ,)
    stochastic = True

    def apply(self, stage, tile, data):
        p = self.params
        t_k = self.sensor.temperature_c + 273.15
        c = tile.hardware_map(self.name, lambda rng, shape: (p.capacitance_ff * np.exp(
            p.spread_ln * rng.standard_normal(shape))).astype(np.float32))
        if tile.bin > 1:
            b = tile.bin
            c = c.reshape(c.shape[0] // b, b, c.shape[1] // b, b).mean(axis=(1, 3))
        sigma = np.sqrt(K_BOLTZMANN * t_k * c * 1e-15) / Q_ELECTRON
        data += (tile.rng(self.name).standard_normal(data.shape) * sigma).astype(np.float32)


class PinkRowNoise(RealWorld):
    """Row noise with a 1/f spectrum along the read-out (correlated neighbouring rows) plus a white part
    (the plugin: white offsets only)."""

    name = "rw_rows"
    stages = (Stage.READ,)
    stochastic = True

    def prepare_frame(self, exptime_s, frame_seed):
        p, s = self.params, self.sensor
        n = s.sensor_height_px
        rng = generator(frame_seed, self.name)
        f = np.fft.rfftfreq(n)
        amp = np.zeros_like(f)
        amp[1:] = f[1:] ** -0.5
        spec = amp * (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size))
        pink = np.fft.irfft(spec, n)
        pink *= p.pink_e / pink.std()
        return (pink + p.white_e * rng.standard_normal(n)).astype(np.float32)

    def apply(self, stage, tile, data):
        off = tile.state[self.name]
        ys, _ = tile.pixel_centres()
        data += off[np.floor(ys).astype(int)][:, None]


class OffCentreCos4Vignetting(RealWorld):
    """Relative illumination ``cos^4(atan(r / F))`` about a centre off the optical axis (a tilted or
    decentred secondary), F the effective distance of the exit pupil: not the plugin's polynomial."""

    name = "rw_vignetting"
    stages = (Stage.RESPONSE,)

    def apply(self, stage, tile, data):
        p, s = self.params, self.sensor
        ys, xs = tile.pixel_centres()
        pitch = s.pixel_pitch_um * 1e-3
        u = (xs - (s.sensor_width_px - 1) / 2) * pitch - p.centre_x_mm
        v = (ys - (s.sensor_height_px - 1) / 2) * pitch - p.centre_y_mm
        r = np.hypot(u[None, :], v[:, None])
        data *= (np.cos(np.arctan(r / p.pupil_mm)) ** 4).astype(np.float32)


class DyeCFA(RealWorld):
    """A Bayer colour filter array whose dyes are not uniform: the four cell responses (by sensor row and column
    parity) times a per-pixel dye-thickness jitter (``jitter`` rms, hardware) and a red response drifting by
    ``red_drift`` across the sensor (a filter-thickness gradient): not the plugin's four constants."""

    name = "rw_cfa"
    stages = (Stage.RESPONSE,)

    def apply(self, stage, tile, data):
        p = self.params
        ys, xs = tile.pixel_centres()  # unbinned at this stage
        py, px = ys.astype(int) % 2, xs.astype(int) % 2
        resp = np.asarray(p.response, np.float64).reshape(2, 2)[py[:, None], px[None, :]]
        u, _ = _uv(tile)
        red = (py[:, None] == p.red_cell[0]) & (px[None, :] == p.red_cell[1])
        resp = resp * np.where(red, 1 + p.red_drift * (u[None, :] - 0.5), 1.0)
        dye = tile.hardware_map(self.name, lambda rng, shape: rng.standard_normal(shape, dtype=np.float32))
        data *= (resp * (1 + p.jitter * dye)).astype(np.float32)


class MoonlitSky(RealWorld):
    """Scattered moonlight rising towards the Moon as ``R0 exp(-(d - d0) / D)`` [e-/s/pixel], ``d`` the distance to
    a point ``d0`` beyond the sensor centre in the direction ``angle_deg`` (a plane to first order, with the
    curvature of the exponential), minus its value at the centre: the model's sky level is the one measured
    on the frame (as for the real-data scenes). ``R0 = g D / 1000`` makes the gradient ``g`` [e-/s/pixel per
    1000 px] at the centre. Added to the light, absent when no light reaches the sensor."""

    name = "rw_sky"
    stages = (Stage.FIELD,)

    def apply(self, stage, tile, data):
        if not data.any():
            return
        p, s = self.params, self.sensor
        ys, xs = tile.pixel_centres()
        a = np.radians(p.angle_deg)
        xm = (s.sensor_width_px - 1) / 2 + p.distance_px * np.cos(a)
        ym = (s.sensor_height_px - 1) / 2 + p.distance_px * np.sin(a)
        d = np.hypot(xs[None, :] - xm, ys[:, None] - ym)
        r0 = p.gradient_e_per_s_per_kpx * p.scale_px / 1000.0
        rate = r0 * (np.exp(-(d - p.distance_px) / p.scale_px) - 1.0)
        data += (rate * tile.exptime_s).astype(np.float32)
        np.maximum(data, 0, out=data)


class TwoSpeciesCTI(RealWorld):
    """CTI with two trap species whose release times (1.6 and 22 parallel transfers) and well-fill power
    (0.6) differ from the plugin's single-species templates (ACS-like 0.74 / 7.7 / 37 transfers, beta 0.478)."""

    stages = (Stage.COUPLING,)
    halo_rows = None

    def couple(self, tile, charge_e, pad_top, pad_bottom, mean_only=False):
        from detector.effects.cti import cti_transfer

        p = self.params
        dwell = 4008 / 8e6
        return cti_transfer(charge_e, p.density, [t * dwell for t in p.release_transfers], dwell, p.beta,
                            self.sensor.full_well_e, first_transfers=tile.y0 - pad_top + 1).astype(np.float32)


def _flux_kernel(q, k, c):
    """Charge moved by boundaries shifting with the potential ``k (x) q`` (any kernel), charge conserved."""
    from scipy.ndimage import correlate

    phi = correlate(q, k.astype(np.float32), mode="nearest")
    out = q.copy()
    f = (q[:, :-1] + q[:, 1:]) * (phi[:, :-1] - phi[:, 1:]) * np.float32(0.25 * c)
    out[:, :-1] -= f
    out[:, 1:] += f
    f = (q[:-1] + q[1:]) * (phi[:-1] - phi[1:]) * np.float32(0.25 * c)
    out[:-1] -= f
    out[1:] += f
    return out


class PowerLawBrighterFatter(RealWorld):
    """Brighter-fatter with a 5x5 power-law potential ``(r + 0.4)^-3`` and 30 % stronger coupling along the
    columns than along the rows (the plugin: a 3x3 isotropic exponential kernel)."""

    stages = (Stage.COUPLING,)
    halo_rows = 3

    def couple(self, tile, charge_e, pad_top, pad_bottom, mean_only=False):
        y, x = np.mgrid[-2:3, -2:3]
        k = (np.hypot(1.3 * y, x) + 0.4) ** -3.0
        k /= k[2, 2]
        # strength from the nearest-neighbour (along the row) area coefficient: a_01 = c (Laplacian k)_01
        c = self.params.a10_per_e / (k[2, 2] + k[2, 4] + k[1, 3] + k[3, 3] - 4 * k[2, 3])
        return _flux_kernel(np.asarray(charge_e, np.float32), k, c)


def couple_3x3(charge_e, kernel) -> np.ndarray:
    """Inter-pixel coupling [e-] by a 3x3 kernel of the fractions each pixel's charge is seen in its neighbours
    (``out[i, j] = sum k[a, b] q[i + a - 1, j + b - 1]``), its centre set to 1 less their sum (the total is
    conserved), edges extended."""
    from scipy.ndimage import correlate

    k = np.array(kernel, np.float32)
    k[1, 1] = 0.0
    k[1, 1] = 1.0 - k.sum()
    return correlate(np.asarray(charge_e, np.float32), k, mode="nearest")


class AnisotropicIPC(RealWorld):
    """Inter-pixel capacitance stronger along rows (1.3 %) than columns (0.9 %), with 0.1 % diagonals (the
    plugin: the same coupling in both directions)."""

    stages = (Stage.COUPLING,)
    halo_rows = 1
    coupling_order = 2

    def couple(self, tile, charge_e, pad_top, pad_bottom, mean_only=False):
        p = self.params
        return couple_3x3(charge_e, [[p.diag, p.ay, p.diag], [p.ax, 0.0, p.ax], [p.diag, p.ay, p.diag]])


class ExponentialRTS(RealWorld):
    """Three-level RTS of 0.4 % of the pixels, exponential amplitudes (mean 25 e-), time constants
    log-uniform in 5-60 us (the plugin: log-normal amplitudes, 10 us - 100 ms), CDS interval 4 us."""

    stages = (Stage.READ,)

    def setup(self):
        p, s = self.params, self.sensor
        rng = generator(MEASURED_HARDWARE_SEED, "real_rts")
        n = s.sensor_width_px * s.sensor_height_px
        k = rng.binomial(n, p.fraction)
        flat = np.unique(rng.integers(0, n, k))
        self.rows, self.cols = flat // s.sensor_width_px, flat % s.sensor_width_px
        self.amp = rng.exponential(p.mean_e, flat.size)
        self.t0 = np.exp(rng.uniform(np.log(5e-6), np.log(6e-5), flat.size))
        self.t1 = np.exp(rng.uniform(np.log(5e-6), np.log(6e-5), flat.size))

    def apply(self, stage, tile, data):
        from detector.effects.rts import rts_offsets

        sel = (self.rows >= tile.y0) & (self.rows < tile.y1) & (self.cols >= tile.x0) & (self.cols < tile.x1)
        if sel.any():
            off = rts_offsets(tile.rng("real_rts"), self.amp[sel], self.t0[sel], self.t1[sel], 3, 4e-6)
            np.add.at(data, (self.rows[sel] - tile.y0, self.cols[sel] - tile.x0), off.astype(np.float32))


# --- the cases --------------------------------------------------------------------------------------------------

@dataclass
class Case:
    """One hidden effect: the base scene that makes it observable and its real-world variant."""

    effect: str
    base: str
    description: str
    make: object  #: callable(sensor) -> list of Effect instances added to the measured camera
    levels: Levels = field(default_factory=Levels)


def _alpha_and_muons(sensor):
    muons = CosmicRays(CosmicRayParams(environment="ground", flux_per_cm2_s=0.04), sensor)
    alphas = AlphaBlobs(CosmicRayParams(environment="ground", particle="alpha", energy_mev=5.0,
                                        flux_per_cm2_s=0.25, depletion_um=10.0), sensor)
    return [muons, alphas]


CASES: dict[str, Case] = {c.effect: c for c in [
    Case("amp_glow", "dark_corner", "power-law glow (index 1.5) from a point 40 px beyond the corner + Gaussian halo",
         lambda s: [PowerLawGlow(s, amplitude_e_per_s=0.6, d0_px=80.0, index=1.5, beyond_px=40.0,
                                 halo_e_per_s=0.01, halo_sigma_px=500.0)]),
    Case("bias_gradient", "bias_full", "bias ramp along rows + sinusoidal ripple along columns + amplifier step",
         lambda s: [RippleStepBias(s, ramp_y_adu=4.0, ripple_adu=1.2, ripple_cycles=0.7, step_adu=0.8)]),
    Case("blooming", "stars", "bleeding above 0.9 full well, 75 % upwards, 20 % of the excess drained",
         lambda s: [LossyBleed(s, threshold=0.9, up_fraction=0.75, drain=0.2)], Levels(0.01, 0.02, -0.4)),
    Case("cfa", "flat", "Bayer cells 1.05/0.80/0.60/1.02 with a 0.2 % per-pixel dye jitter and the red cell's "
         "response drifting 3 % across the sensor",
         lambda s: [DyeCFA(s, response=[1.05, 0.80, 0.60, 1.02], jitter=0.002, red_cell=(1, 0), red_drift=0.03)],
         Levels(0.012, -0.02, 0.4)),
    Case("column_defects", "dark", "8 trap columns (partial, from the trap to the register), lognormal rates",
         lambda s: [TrapColumns(s, n_columns=8, median_rate_e_per_s=0.08, sigma_ln=0.6)]),
    Case("cosmic_rays", "dark", "muons at 0.04 /cm2/s (altitude) plus 5 MeV alpha blobs at 0.25 /cm2/s (window)",
         _alpha_and_muons),
    Case("crosstalk", "stars", "4 unmirrored channels, coupling 2e-3 to the neighbour, falling 2.5x per channel",
         lambda s: [CouplingMatrixCrosstalk(s, n_channels=4, alpha=2e-3)], Levels(-0.012, 0.02, 0.3)),
    Case("dead_pixels", "flat", "12000 dead/weak pixels, response uniform in [0, 0.4], 20 % in pairs",
         lambda s: [VariableDeadPixels(s, count=12000, max_response=0.4)]),
    Case("dsnu", "dark", "gamma-law DSNU, sigma 0.45, with a 10 % low-frequency part",
         lambda s: [GammaDSNU(s, sigma=0.45, lf_rms=0.10)], Levels(0.0, 0.025, -0.5)),
    Case("gain_regions", "flat_full", "2x2 amplifiers, column split at 47 %, gains +-1 %, 0.3 % drift",
         lambda s: [DriftingGainRegions(s, gains=[1.009, 0.993, 0.996, 1.006], split_u=0.47, drift=0.003)],
         Levels(-0.018, 0.02, 0.5)),
    Case("hot_pixels", "dark", "30000 hot pixels with lognormal rates (median 0.4 e-/s, sigma_ln 1.2)",
         lambda s: [LognormalHotPixels(s, count=30000, median_e_per_s=0.4, sigma_ln=1.2)]),
    Case("nonlinearity", "stars", "cubic response deficit, 6 % at full well",
         lambda s: [CubicNonlinearity(s, gamma=0.06)], Levels(0.012, -0.02, 0.4)),
    Case("prnu", "flat", "white PRNU 0.8 % + 0.4 % rms low-frequency pattern",
         lambda s: [LowFrequencyPRNU(s, white=0.008, lf_rms=0.004, lf_cycles=24.0)], Levels(0.013, -0.02, 0.5)),
    Case("reset_noise", "dark", "kTC of 0.6 fF nodes with a 25 % lognormal spread of capacitance",
         lambda s: [VariableKTC(s, capacitance_ff=0.6, spread_ln=0.25)], Levels(0.0, 0.02, -0.6)),
    Case("row_noise", "dark", "1/f row noise 3 e- rms + white 1.5 e-",
         lambda s: [PinkRowNoise(s, pink_e=3.0, white_e=1.5)], Levels(0.0, -0.02, 0.7)),
    Case("sky_gradient", "stars", "moonlight rising towards 120 deg as exp(-d / 8000 px) from a point 12000 px "
         "beyond the centre, 6 e-/s per pixel per 1000 px at the centre (5 % of the sky across the window)",
         lambda s: [MoonlitSky(s, gradient_e_per_s_per_kpx=6.0, scale_px=8000.0, distance_px=12000.0,
                               angle_deg=120.0)],
         Levels(0.01, -0.02, 0.3)),
    Case("cti", "stars", "two trap species (0.15 and 0.25 traps/px) releasing in 1.6 and 22 transfers, well-fill "
         "power 0.6",
         lambda s: [TwoSpeciesCTI(s, density=[0.15, 0.25], release_transfers=[1.6, 22.0], beta=0.6)],
         Levels(0.01, -0.02, 0.3)),
    Case("brighter_fatter", "stars", "5x5 power-law potential (r + 0.4)^-3, 30 % stronger along columns, "
         "a_10 ~ 2e-6 /e-",
         lambda s: [PowerLawBrighterFatter(s, a10_per_e=2e-6)], Levels(0.012, -0.02, 0.4)),
    Case("ipc", "stars", "anisotropic IPC: 1.3 % along rows, 0.9 % along columns, 0.1 % diagonals",
         lambda s: [AnisotropicIPC(s, ax=0.013, ay=0.009, diag=0.001)], Levels(-0.01, 0.02, 0.3)),
    Case("rts_noise", "dark_cmos", "three-level RTS of 0.4 % of the pixels, exponential amplitudes (mean 25 e-), "
         "time constants 5-60 us",
         lambda s: [ExponentialRTS(s, fraction=0.004, mean_e=25.0)], Levels(0.0, 0.02, -0.4)),
    Case("vignetting", "flat_full", "cos^4(atan(r/70 mm)) about a centre offset by (2.5, -1.5) mm",
         lambda s: [OffCentreCos4Vignetting(s, pupil_mm=70.0, centre_x_mm=2.5, centre_y_mm=-1.5)],
         Levels(0.012, -0.02, -0.5)),
]}

#: the null cases: every base scene with its nuisances and nothing hidden
NULLS: dict[str, Levels] = {b: Levels(0.015 * (-1) ** i, 0.03 * (-1) ** (i + 1), 0.6 * (-1) ** i)
                            for i, b in enumerate(BASES)}


# --- making a measured frame --------------------------------------------------------------------------------------

def write_scene(d: dict, path: Path) -> Path:
    path.write_text(tomli_w.dumps(d))
    return path


def measured_setup(base: str, levels: Levels, scene_path: Path, workers: int | None = None):
    """(scene, render setup) of the measured camera on ``base`` with ``levels``, its scene written to
    ``scene_path``."""
    from scenes.app.render import prepare
    from scenes.scene import load_scene

    scene = load_scene(str(write_scene(measured_scene(base, levels), scene_path)))
    return scene, prepare(scene, workers=workers)


def with_effects(setup, added: list) -> Detector:
    """The setup's detector with the real-world effects ``added`` after its own."""
    return Detector(setup.detector.sensor, setup.detector.effects + added, workers=setup.detector.workers)


def make_frame(base: str, extra, levels: Levels, out: Path, seed: int = 11, workers: int | None = None) -> dict:
    """Render the measured frame: the measured camera (its hardware, its levels, its cosmic rays and hot
    pixels) plus the ``extra`` real-world effects (callable(sensor) -> list of Effects), to ``out``."""
    from detector.fits_io import primary_header, table_hdu, write_streamed
    from scenes.app.render import header_cards, scene_hdu

    scene, setup = measured_setup(base, levels, out.with_suffix(".measured.toml"), workers)
    sensor = setup.detector.sensor
    added = list(extra(sensor)) if extra is not None else []
    det = with_effects(setup, added)
    state = det.frame_state(setup.exptime_s, seed)
    dtype = np.uint16 if sensor.bit_depth <= 16 else np.uint32
    header = primary_header(sensor.output_shape, dtype, header_cards(setup, seed, False))
    header["HIDDEN"] = (",".join(e.name for e in added) or "none", "real-world effects added (truth)")
    ext = [scene_hdu(scene)] + [table_hdu(n, t) for n, t in det.truth(setup.exptime_s, seed, state).items()]
    write_streamed(out, header, det.iter_frame(setup.signal_e, setup.exptime_s, seed, state=state),
                   sensor.output_shape, dtype, ext)
    white = bool(added) and all(getattr(e, "pixel_scatter", False) for e in added)
    support, truth_chi2, scatter, change = effect_support(setup, det, added, white=white, with_change=True)
    return {"measured": str(out), "support": support, "truth_chi2": truth_chi2, "scatter_sigma": scatter,
            "truth_change_adu": change,
            "truth": [dict(type=type(e).__name__, **_jsonable(e.describe_truth()))
                      for e in added if isinstance(e, RealWorld)]}


def change_chi2(base: str, levels: Levels, extra_a, extra_b, out: Path, workers: int | None = None) -> float:
    """How detectable the difference of two sets of real-world effects is on ``base`` (callables(sensor) ->
    list of Effects, as :func:`make_frame` takes): ``sum((m_a - m_b)^2 / v0)`` over every pixel, the expected
    frames with each and the measured camera's variance, as :func:`effect_support`'s truth chi2. ``out`` names
    the scene file written for it."""
    _, setup = measured_setup(base, levels, out, workers)
    sensor = setup.detector.sensor
    _, v0, _ = setup.detector.moments(setup.signal_e, setup.exptime_s)
    m_a, m_b = (with_effects(setup, list(extra(sensor))).moments(setup.signal_e, setup.exptime_s)[0]
                for extra in (extra_a, extra_b))
    return float(np.sum((m_a - m_b) ** 2 / v0, dtype=np.float64))


#: a pixel belongs to a hidden effect's support where it changes the expected frame by this many sigma
SUPPORT_SIGMA = 0.2


def scatter_sigma(change: np.ndarray, var: np.ndarray) -> float:
    """How many standard deviations one frame sees a fixed pattern by when it does not have the pattern's map
    [sigma]: its large scales (the change smoothed over WHITE_SCALE output pixels, the scale below which the
    diagnosis's variance fits take structure for scatter) as a template, sqrt(sum(smooth^2 / v)) less the white
    part's expected leakage into the smoothed map (below); the rest,
    drawn independently per pixel (a DSNU, EMVA 1288 Release 4.0 sect. 8), only as the variance sum(white^2 / v)
    it adds to the chi2 of n pixels, whose own scatter is sqrt(2 n): sum(white^2 / v) / sqrt(2 n). The larger of
    the two. The pattern's exact template chi2 (the truth chi2) is what its map, or a second frame of the same
    sensor, would give; and even a scatter seen in one frame, when it is proportional to a uniform dark signal,
    is a read noise's too (only another exposure or dark level, or the law's shape, tells them apart)."""
    from detector.signatures import WHITE_SCALE, local_mean

    change = np.asarray(change, np.float64)
    var = np.asarray(var, np.float64)
    local = local_mean(change, 1.0 / var)  # the diagnosis's own local mean (every pixel counts here)
    smooth = local - local.mean()  # a global level is the profiled levels' (bias, dark), not the pattern's
    white = change - local
    # a white pattern's own noise leaks into the smoothed map: G keeps sum(k^2) = 1 / (4 pi s^2) of an i.i.d.
    # variance and the rest is left with 1 - 1 / (4 pi s^2) (the centre weight 1 / (2 pi s^2) counted), so the
    # smoothed map holds sum(white^2 / v) / (4 pi s^2 - 1) with no large scale present: that expected leakage is
    # not a template
    chi2_white = float(np.sum(white * white / var))
    leak = chi2_white / (4.0 * np.pi * WHITE_SCALE ** 2 - 1.0)
    as_template = float(np.sqrt(max(float(np.sum(smooth * smooth / var)) - leak, 0.0)))
    as_scatter = chi2_white / float(np.sqrt(2.0 * change.size))
    return max(as_template, as_scatter)


def effect_support(setup, det: Detector, added: list, white: bool = False, with_change: bool = False) -> tuple:
    """Where the hidden effect acts: output pixels whose expected value it changes by more than
    SUPPORT_SIGMA model sigmas (every pixel for an effect that adds noise or scatter, or for none); how
    detectable it is whatever the diagnosis: the chi2 that its exact template (the change of the expected
    frame, amplitude known) removes on a noise-free frame, sum((m1 - m0)^2 / v0) over every pixel (None for
    an effect that adds noise or scatter). Fitting that template's amplitude alone needs about 2 ln(N) of it
    to pass a BIC test; a diagnosis that must also find the form's shape needs more. With ``white`` (a pattern
    drawn per pixel, :attr:`RealWorld.pixel_scatter`), also how many sigma one frame sees it by without its map
    (:func:`scatter_sigma`; None otherwise). With ``with_change``, the change of the expected frame ``m1 - m0``
    [ADU] too (None where there is no chi2), for :func:`truth_chi2_after_levels`."""
    shape = det.sensor.output_shape
    if not added or any(e.stochastic or e.stages == (Stage.CHARGE,) for e in added):
        return (np.ones(shape, bool), None, None) + ((None,) if with_change else ())
    m0, v0, _ = setup.detector.moments(setup.signal_e, setup.exptime_s)
    m1, _, _ = det.moments(setup.signal_e, setup.exptime_s)
    z2 = (m1 - m0) ** 2 / v0
    sup = z2 > SUPPORT_SIGMA ** 2
    out = ((sup if sup.any() else np.ones(shape, bool)), float(np.sum(z2, dtype=np.float64)),
           scatter_sigma(m1 - m0, v0) if white else None)
    return out + (((m1 - m0).astype(np.float32),) if with_change else ())


def truth_chi2_after_levels(res, change_adu) -> float | None:
    """The chi2 the hidden effect's exact change ``change_adu`` [ADU] (:func:`effect_support`) keeps on the
    pixels the diagnosis fits once the global levels a model only knows to a few per cent (the light, the sky,
    the dark; :meth:`detector.signatures.Residuals.level_templates`) have taken what they can of it:
    ``sum w (P d)^2`` over the fitted pixels, ``P`` the residuals' level projection. What truth chi2 counts
    but no diagnosis can see (a near-uniform compression of a bright sky is a sky level; saturated pixels are
    not fitted) is left out. None without a change."""
    if change_adu is None:
        return None
    idx, _, w = res.flat()
    d = res.project(np.asarray(change_adu, np.float64).ravel()[idx])
    return float(np.dot(d * d, w))


def _jsonable(d: dict) -> dict:
    return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in d.items()}


# --- the diagnosis of one case --------------------------------------------------------------------------------------

def error_of(cmp: dict, support: np.ndarray | None = None) -> dict:
    """The error of a comparison with the global levels profiled (:func:`detector.signatures.level_profiled`):
    ``chi2_minus_1`` = chi2/dof - 1 over the fitted pixels of the hidden effect's ``support`` (all by
    default), and the ``misfit`` of the whole frame (:func:`scenes.app.compare.statistics.compare`); the raw
    (unprofiled) chi2/dof and misfit of the comparison for reference."""
    from detector.signatures import level_profiled
    from scenes.app.compare.statistics import compare

    res = level_profiled(cmp["_residuals"])
    out = compare(res)
    sel = res.fit if support is None else res.fit & support
    z2 = (res.data_adu - res.model_adu) ** 2 / res.var_adu2
    return {"chi2_minus_1": float(z2[sel].mean() - 1) if sel.any() else 0.0, "n_support": int(sel.sum()),
            "misfit": out["misfit"], "raw_chi2_per_dof": cmp["chi2_per_dof"], "raw_misfit": cmp["misfit"]}


#: effects the model compares statistically (outlier counts): their error is the misfit, the others' chi2 - 1
STATISTICAL = {"cosmic_rays", "hot_pixels", "dead_pixels", "column_defects", "rts_noise"}


def diagnose_frame(model_toml: Path, measured: Path, hidden: str | None, apply_dir: Path | None = None,
                   support: np.ndarray | None = None, workers: int | None = None) -> dict:
    """Diagnose ``measured`` against ``model_toml``; apply the best significant candidate and compare again."""
    from scenes.app.compare import run_compare, run_diagnose
    from scenes.app.compare.apply import apply_candidate
    from scenes.scene import load_scene

    t0 = time.perf_counter()
    out = run_diagnose(load_scene(str(model_toml)), measured, workers=workers)
    seconds = time.perf_counter() - t0
    cands = out["candidates"]
    best = next((c for c in cands if c["significant"]), None)
    metric = "misfit" if (hidden or (best or {}).get("effect")) in STATISTICAL else "chi2_minus_1"
    row = {"hidden": hidden or "none", "first": best["effect"] if best else "none",
           "params": best["params"] if best else None, "delta_bic": best["delta_bic"] if best else None,
           "variant": best["variant"] if best else None,
           "ranking": [(c["effect"], round(c["delta_bic"], 1)) for c in cands[:5]],
           "significant": out["significant"], "seconds": round(seconds, 2), "metric": metric,
           "before": error_of(out["_compare"], support)}
    row["hidden_rank"] = next((i + 1 for i, c in enumerate(cands) if c["effect"] == hidden and c["significant"]),
                              None)
    if best is not None and apply_dir is not None:
        new = apply_candidate(load_scene(str(model_toml)), best, apply_dir / f"{model_toml.stem}.applied.toml")
        row["after"] = error_of(run_compare(load_scene(str(new)), measured, workers=workers), support)
        b, a = row["before"][metric], row["after"][metric]
        row["error_before"], row["error_after"] = b, a
        row["error_ratio"] = a / b if b > 0 else float("nan")
    return row


def run_case(effect: str | None, workdir: Path, seed: int = 11, base: str | None = None,
             workers: int | None = None) -> dict:
    """Make the measured frame of ``effect`` (None: the null case of ``base``) and diagnose it."""
    workdir.mkdir(parents=True, exist_ok=True)
    if effect is None:
        case_base, make, levels, tag = base, None, NULLS[base], f"null_{base}"
    else:
        c = CASES[effect]
        case_base, make, levels, tag = c.base, c.make, c.levels, effect
    model = write_scene(model_scene(case_base, effect), workdir / f"{tag}.model.toml")
    info = make_frame(case_base, make, levels, workdir / f"{tag}.fits", seed=seed, workers=workers)
    row = diagnose_frame(model, Path(info["measured"]), effect, apply_dir=workdir, support=info["support"],
                         workers=workers)
    row.update(case=tag, base=case_base, truth=info["truth"], truth_chi2=info["truth_chi2"],
               description=CASES[effect].description if effect else "no hidden effect",
               levels=vars(levels))
    return row


# --- the matrix ---------------------------------------------------------------------------------------------------

def run_matrix(effects=EFFECTS, nulls=tuple(BASES), workdir: Path | None = None, progress=None, seed: int = 11,
               workers: int | None = None) -> list[dict]:
    """Every case (and null case) diagnosed; ``progress(label)`` is called before each."""
    tmp = None
    if workdir is None:
        tmp = tempfile.TemporaryDirectory()
        workdir = Path(tmp.name)
    rows = []
    try:
        for e in effects:
            if progress:
                progress(e)
            rows.append(run_case(e, workdir / e, seed=seed, workers=workers))
        for b in nulls:
            if progress:
                progress(f"null ({b})")
            rows.append(run_case(None, workdir / f"null_{b}", seed=seed, base=b, workers=workers))
    finally:
        if tmp is not None:
            tmp.cleanup()
    return rows


def confusion(rows: list[dict]) -> dict:
    """Confusion matrix (hidden x first significant candidate) and the headline numbers."""
    hidden = [r["hidden"] for r in rows]
    labels = sorted(set(hidden) - {"none"}) + ["none"]
    found = sorted({r["first"] for r in rows} - set(labels))
    cols = labels[:-1] + found + ["none"]
    m = np.zeros((len(labels), len(cols)), int)
    for r in rows:
        m[labels.index(r["hidden"]), cols.index(r["first"])] += 1
    eff = [r for r in rows if r["hidden"] != "none"]
    nulls = [r for r in rows if r["hidden"] == "none"]
    falls = [r for r in eff if r["first"] == r["hidden"]]
    return {"rows": labels, "cols": cols, "matrix": m.tolist(),
            "accuracy": sum(r["first"] == r["hidden"] for r in eff) / max(len(eff), 1),
            "null_clean": sum(r["first"] == "none" for r in nulls), "n_null": len(nulls),
            "error_halved": sum(r.get("error_ratio", 1.0) <= 0.5 for r in falls), "n_identified": len(falls)}


def markdown(rows: list[dict], conf: dict) -> str:
    short = {c: c.replace("_", " ") for c in conf["cols"]}
    lines = ["| hidden \\ first | " + " | ".join(short[c] for c in conf["cols"]) + " |",
             "|---|" + "---|" * len(conf["cols"])]
    for name, row in zip(conf["rows"], conf["matrix"]):
        lines.append(f"| **{name}** | " + " | ".join(str(v) if v else "." for v in row) + " |")
    n_eff = sum(r["hidden"] != "none" for r in rows)
    n_ok = sum(r["first"] == r["hidden"] for r in rows if r["hidden"] != "none")
    headline = (f"first-rank accuracy {100 * conf['accuracy']:.0f} % ({n_ok}/{n_eff}); null cases without a "
                f"significant candidate: {conf['null_clean']}/{conf['n_null']}; error halved after apply: "
                f"{conf['error_halved']}/{conf['n_identified']}")
    lines += ["", headline, "",
              "| case | scene | first | delta BIC | runner-up | metric | error before | after | ratio | fitted |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        runner = next((f"{e} ({d:.3g})" for e, d in r["ranking"] if e != r["first"]), "-")
        m = r["metric"]
        fmt = (lambda x: f"{x:.3g}" if x is not None else "-")
        lines.append(f"| {r['case']} | {r['base']} | {r['first']} | {fmt(r['delta_bic'])} | {runner} | {m} | "
                     f"{fmt(r['before'][m])} | {fmt(r.get('after', {}).get(m))} | {fmt(r.get('error_ratio'))} | "
                     f"{json.dumps(r['params']) if r['params'] else '-'} |")
    return "\n".join(lines) + "\n"


def heat_map(conf: dict, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    m = np.asarray(conf["matrix"])
    fig, ax = plt.subplots(figsize=(0.45 * m.shape[1] + 3, 0.4 * m.shape[0] + 2), dpi=100)
    ax.imshow(m, cmap="Blues", vmin=0, vmax=max(1, m.max()))
    ax.set_xticks(range(m.shape[1]), conf["cols"], rotation=60, ha="right", fontsize=8)
    ax.set_yticks(range(m.shape[0]), conf["rows"], fontsize=8)
    for (i, j), v in np.ndenumerate(m):
        if v:
            ax.text(j, i, str(v), ha="center", va="center", fontsize=8, color="white" if v > m.max() / 2 else "k")
    ax.set_xlabel("first significant candidate")
    ax.set_ylabel("hidden effect")
    ax.set_title(f"newtsim diagnose on hidden real-world effects: accuracy {100 * conf['accuracy']:.0f} %, "
                 f"null clean {conf['null_clean']}/{conf['n_null']}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out", nargs="?", default="hidden_effects_out")
    ap.add_argument("--effects", default=",".join(EFFECTS), help="comma-separated hidden effects")
    ap.add_argument("--no-null", action="store_true", help="skip the null cases")
    ap.add_argument("--keep", action="store_true", help="keep the frames and scenes in OUT/work")
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--half", choices=("all", "tuning", "heldback"), default="all",
                    help="run the cases of one half of the suite only (scenes/app/validation/halves.py: the tuning "
                         "half may be looked at while changing the diagnosis, the held-back half is only reported)")
    args = ap.parse_args(argv)
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    effects = [e for e in args.effects.split(",") if e]
    unknown = [e for e in effects if e not in CASES]
    if unknown:
        print(f"hidden_effects: --effects: no case for {', '.join(unknown)} (expected one of: {', '.join(CASES)})",
              file=sys.stderr)
        return 2
    nulls = () if args.no_null else tuple(BASES)
    if args.half != "all":
        from .halves import half_of

        effects = [e for e in effects if half_of(e) == args.half]
        nulls = tuple(b for b in nulls if half_of(f"null_{b}") == args.half)
    with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                  TimeElapsedColumn()) as bar:
        task = bar.add_task("diagnose", total=len(effects) + len(nulls))
        state = {"n": 0}

        def progress(label):
            bar.update(task, completed=state["n"], description=f"diagnose: {label}")
            state["n"] += 1

        rows = run_matrix(effects, nulls, workdir=out / "work" if args.keep else None, progress=progress,
                          seed=args.seed)
        bar.update(task, completed=state["n"])
    conf = confusion(rows)
    conf["half"] = args.half
    md = (f"Half of the suite: {args.half}\n\n" if args.half != "all" else "") + markdown(rows, conf)
    (out / "confusion.md").write_text(md)
    (out / "confusion.json").write_text(json.dumps({"confusion": conf, "cases": rows}, indent=1, default=float) + "\n")
    heat_map(conf, out / "confusion.png")
    print(md)
    print(f"wrote {out / 'confusion.md'}, {out / 'confusion.json'}, {out / 'confusion.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
