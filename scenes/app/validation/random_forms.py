"""Generality of ``newtsim diagnose`` measured on random functional forms of its catalogue's effects (issue 23).

The fixed suites (:mod:`.hidden`, :mod:`.unseen`) hold one or two forms per effect, chosen by hand, and the
diagnosis has been developed while looking at them. This module draws hidden effects procedurally, from a
seed, so that a report can be made on forms nobody has looked at:

* **smooth fields** of random form (a radial law of random order about a random centre with a random axis
  ratio and angle; a Legendre polynomial of random order; a sum of a few long plane waves; a power law of the
  distance to a point beyond the window; a glow along an edge; an exponential plane) acting as a relative
  illumination (vignetting), an additive light (straylight, sky gradient), a dark rate (dark gradient, glow)
  or a bias structure [ADU];
* **kernels**: a PSF broadening (elliptical Gaussian, Moffat, exponential, core plus wing), an elongation,
  an inter-pixel capacitance (3x3, asymmetric), a brighter-fatter potential (exponential, Gaussian, power law,
  Coulomb, anisotropic, optionally growing with the charge; a real sensor's: area coefficients falling with the
  distance, a pixel-area change at full well of at most BF_MAX_AREA_CHANGE), a crosstalk delayed and smeared;
* **laws**: a non-linearity (knee, gamma, polynomial, tanh) of random strength at full well; hot-pixel rate
  laws (lognormal, Pareto, exponential, Weibull, two populations); DSNU and PRNU laws; RTS with two traps or
  three states; row noise (1/f, telegraph, heavy-tailed); reset noise (Laplace, alternate columns, varying
  capacitance);
* **profiles**: CTI trails (one species, exponential; or five species weighted as a power law of their release
  time: a power-law trail) read out in the parallel or the serial direction; bleeds (lossy, sideways, soft);
* **densities**: dead pixels and clusters, hot pixels, charged-particle tracks, hot, leaking and weak columns;
* **geometry**: image motion (sine, random walk, acceleration, arc), offsets with rotation or scale, Brown
  distortion, ghosts;
* **periodic patterns** (out of the catalogue: the right answer is a description): a sine, square or
  triangle wave of random period, phase and orientation, or rings about a far point, acting on the
  response, the dark, the light or the bias;
* **other forms out of the catalogue** (their classes are :mod:`.unseen`'s, their parameters drawn): a
  read-out smear of a CCD (a share of each column's light along it), a satellite trail, tree rings of the
  silicon (at least four periods across the window).

Amplitudes are log-uniform between a strong value and one near the detection threshold, in units of the
frame's own noise (the pixel noise of the base scene: shot noise of the light and the dark, read noise), so
that "near threshold" means the same on every base; each case also records ``truth_chi2``, the chi2 its exact
template removes from a noise-free frame (:func:`.hidden.effect_support`). A kernel acts as the continuous
kernel does (its transfer function, :func:`blur_transfer`), whatever its width.

A drawn form may hold a part that is a catalogue effect of its own (a near-round blur's elongation): the part's
names are accepted too when the frame sees the part alone (its chi2 against the draw without it, at least
:data:`SEEN_CHI2`, recorded as ``parts_chi2``).

Each drawn case records its family, the accepted catalogue name(s) (or, out of the catalogue, the expected
morphology ``kind`` and ``geometry`` words, as :mod:`.unseen` does), the base scene and its camera (ML11002 CCD
or IMX411 CMOS), the case seed, the parameters drawn and the class that acts; the case is rebuilt from
``(family, case_seed)`` alone. The real-world effects act at their physical stage (:class:`.hidden.RealWorld`),
the frames are made and diagnosed as :mod:`.unseen` does (``run_diagnose``, ``apply_best`` with the measured
frame, the same error metric and the same "confidently wrong" rule).

A report draws a FRESH master seed (``os.urandom``) unless ``--seed`` is given, prints it and appends it to
``OUT/seeds.jsonl``; figures are reported only from seeds never used while developing. Usage::

    python examples/diagnose/random_forms.py OUT [-n 200] [--seed S] [--workers 2] [--families a,b]
    python examples/diagnose/random_forms.py OUT --case FAMILY:CASE_SEED     # rebuild and rerun one case
    python examples/diagnose/random_forms.py OUT --draw-only -n 20          # print the draws, run nothing

writes ``OUT/random_forms.md`` and ``OUT/random_forms.json`` (and ``OUT/rows/*.json`` as cases finish).
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import multiprocessing as mp
import os
import sys
import tempfile
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy import ndimage, optimize

from detector.effects.base import Stage
from detector.effects.blooming import bleed_columns
from detector.presets import PRESETS
from detector.significance import DETECTION_SIGMA
from scenes.app.compare.policy import DEFAULT_POLICY

from . import unseen as U

HE = U.HE
RealWorld, Levels = HE["RealWorld"], HE["Levels"]
BASES = U.BASES

#: the sky's photo-electron rate of the light bases [e-/s per unbinned pixel] (the model scene's uniform
#: background, ``prepare(scene).signal_e.background_e / exptime``, measured once on 2026-11-29)
SKY_E_PER_S = {"stars": 64.69, "stars_imx": 20.05, "stars_bright": 315.4, "sky_imx_bin": 20.05,
               "stars_imx_sharp": 20.05}


def _small(name: str, d: dict) -> dict:
    """A quarter-size copy of the base scene ``name`` (same camera, exposure, light, binning; about 256 output
    pixels on a side instead of 512): 512x512 windows become the central 256x256 ones, the CMOS amplifier corner
    (1024 px binned 2) its 512 px next to the corner, the binned whole CCD (binned 8) its central 2048x1336 px,
    the binned 4096 px CMOS corner its 2048 px corner. The diagnosis of a frame costs about its pixel count:
    a few hundred cases fit in well under an hour on two processes."""
    import copy

    d = copy.deepcopy(d)
    det = d["detector"]
    if det.get("width") == 512 and "binning" not in det:
        det.update(width=256, height=256)
    elif name == "dark_corner":
        det.update(width=512, height=512, x0=det["x0"] + 512)
    elif det["preset"] == "ml11002" and det.get("binning") == 8:
        det.update(width=2048, height=1336)
    elif det["preset"] == "imx411" and det.get("binning") == 8:
        det.update(width=2048, height=2048)
    else:
        raise ValueError(f"base {name}: no small form")
    return d


#: the small bases, ``<base>_s`` (added to the bases :func:`.hidden.model_scene` and ``measured_scene`` read; the
#: fixed suites' cases were made before and do not use them)
SMALL = {f"{b}_s": _small(b, d) for b, d in list(U.BASES.items())}
BASES.update(SMALL)

#: the families whose effect needs the full 512 px star windows (saturated stars, a few in a 512 window)
FULL_SIZE_FAMILIES = ("blooming",)


def parent(base: str) -> str:
    """The base scene a small base is cut from (itself for a full-size base)."""
    return base[:-2] if base.endswith("_s") and base[:-2] in BASES else base


# --- the base scenes' numbers ----------------------------------------------------------------------------------

def base_info(base: str) -> dict:
    """Camera, binning, exposure, light and dark per output pixel [e-] and the pixel noise [e-] of ``base``:
    sigma^2 = light + dark + read^2 (x bin^2 reads for a CMOS, which bins after the read-out; one read for a
    CCD, which bins the charge)."""
    from detector.presets import PRESETS

    d = BASES[base]
    det = d["detector"]
    pre = PRESETS[det["preset"]]
    b = int(det.get("binning", 1))
    t = float(d["exposure"]["time_s"])
    cmos = det["preset"] == "imx411"
    frame = d["exposure"]["frame"]
    light_rate = float(d["sky"].get("flat_e_per_s") or SKY_E_PER_S.get(parent(base), 0.0)) if frame == "light" else 0.0
    light = light_rate * t * b * b
    dark = pre["dark_current_e_per_s"] * t * b * b
    read2 = pre["read_noise_e"] ** 2 * (b * b if cmos else 1)
    return {"camera": det["preset"], "cmos": cmos, "bin": b, "time_s": t, "light_rate": light_rate,
            "light_e": light, "dark_e": dark, "dark_rate": pre["dark_current_e_per_s"],
            "noise_e": math.sqrt(light + dark + read2), "gain": pre["gain_e_per_adu"],
            "full_well_e": pre["full_well_e"], "read_noise_e": pre["read_noise_e"],
            "out_shape": (int(det.get("height", pre["sensor_height_px"])) // b,
                          int(det.get("width", pre["sensor_width_px"])) // b)}


def small_info(base: str) -> dict:
    """:func:`base_info` of the small form of ``base``, the window a drawn case's frame has (:func:`draw_case`)."""
    return base_info(f"{base}_s")


def _loguniform(rng, lo: float, hi: float) -> tuple[float, float]:
    """A value log-uniform in [lo, hi] and its position t in [0, 1] (1: hi)."""
    t = float(rng.uniform())
    return float(lo * (hi / lo) ** t), t


# --- smooth fields ---------------------------------------------------------------------------------------------

def _legendre(n: int, z: np.ndarray) -> np.ndarray:
    return np.polynomial.legendre.legval(z, [0] * n + [1])


def raw_field(spec: dict, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The unnormalised field of ``spec`` at window fractions x (columns, 1-D) and y (rows, 1-D): a 2-D array."""
    X, Y = x[None, :], y[:, None]
    form = spec["form"]
    if form == "radial":
        dx, dy = X - spec["cu"], Y - spec["cv"]
        c, s = math.cos(spec["theta"]), math.sin(spec["theta"])
        rho = np.hypot(c * dx + s * dy, (-s * dx + c * dy) / spec["q"])
        law = spec["law"]
        if law == "power":
            return rho ** spec["p"]
        if law == "gauss":
            return 1 - np.exp(-rho ** 2 / (2 * spec["s"] ** 2))
        if law == "cos4":
            return 1 - np.cos(np.arctan(rho / spec["s"])) ** 4
        if law == "lorentz":
            return rho ** 2 / (rho ** 2 + spec["s"] ** 2)
        return sum(cf * rho ** (2 * k + 2) for k, cf in enumerate(spec["coef"]))  # "poly": even powers
    if form == "poly":
        out = np.zeros((y.size, x.size))
        for (i, j), cf in zip(spec["terms"], spec["coef"]):
            out += cf * _legendre(i, 2 * X - 1) * _legendre(j, 2 * Y - 1)
        return out
    if form == "waves":
        out = np.zeros((y.size, x.size))
        for k, a, ph in zip(spec["cycles"], spec["angle"], spec["phase"]):
            out += np.cos(2 * np.pi * k * (math.cos(a) * X + math.sin(a) * Y) + ph)
        return out
    if form == "point":
        d2 = (X - spec["pu"]) ** 2 + (Y - spec["pv"]) ** 2
        return (1 + d2 / spec["d0"] ** 2) ** (-spec["index"] / 2)
    if form == "edge":
        along, across = {"left": (Y, X), "right": (Y, 1 - X), "bottom": (X, Y), "top": (X, 1 - Y)}[spec["edge"]]
        return np.exp(-across / spec["lam"]) * np.exp(-(along - spec["pos"]) ** 2 / (2 * spec["sigma"] ** 2))
    if form == "plane":
        return math.cos(spec["angle"]) * X + math.sin(spec["angle"]) * Y + 0 * Y
    if form == "thermal":  # a temperature plane with the dark current doubling every t2 (an exponential plane)
        return np.exp2(spec["dk"] * (math.cos(spec["angle"]) * X + math.sin(spec["angle"]) * Y)) + 0 * Y
    if form == "step":
        return (math.cos(spec["angle"]) * X + math.sin(spec["angle"]) * Y >= spec["at"]).astype(float) + 0 * Y
    raise ValueError(f"field form {form!r}")


def normalise(spec: dict, n: int = 65) -> dict:
    """``spec`` with ``lo``, ``hi``: the field's extremes over an n x n grid of the window, so that
    :func:`field_shape` runs from 0 to 1 over it."""
    g = np.linspace(0, 1, n)
    f = raw_field(spec, g, g)
    lo, hi = float(f.min()), float(f.max())
    if not hi > lo:
        raise ValueError(f"flat field {spec}")
    return {**spec, "lo": lo, "hi": hi, "mean": float(np.mean((f - lo) / (hi - lo)))}


def field_shape(spec: dict, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The field normalised to [0, 1] over the window (0 where the raw field is least)."""
    return (raw_field(spec, x, y) - spec["lo"]) / (spec["hi"] - spec["lo"])


def _window_fractions(tile):
    x, y, w, h = U._win(tile)
    return x / max(w - 1, 1), y / max(h - 1, 1)


class _FieldBase(RealWorld):
    """A smooth field of :func:`field_shape` (``spec``) of ``amp``: see the subclasses for the role."""

    def values(self, tile) -> np.ndarray:
        u, v = _window_fractions(tile)
        return field_shape(self.params.spec, u, v)


class ResponseField(_FieldBase):
    """Relative illumination ``1 - depth g`` (vignetting, a multiplicative fall-off): RESPONSE stage."""

    name = "rf_response_field"
    stages = (Stage.RESPONSE,)

    def apply(self, stage, tile, data):
        data *= (1 - self.params.amp * self.values(tile)).astype(np.float32)


class LightField(_FieldBase):
    """Additive light ``amp g`` [e-/s per unbinned pixel] on the photo-signal (straylight, a sky gradient)."""

    name = "rf_light_field"
    stages = (Stage.FIELD,)

    def apply(self, stage, tile, data):
        if not data.any():
            return
        data += (self.params.amp * self.values(tile) * tile.exptime_s * tile.bin ** 2).astype(np.float32)


class DarkField(_FieldBase):
    """Additive dark rate ``amp g`` [e-/s per unbinned pixel] (a dark gradient, a glow): DARK stage."""

    name = "rf_dark_field"
    stages = (Stage.DARK,)

    def apply(self, stage, tile, data):
        data += (self.params.amp * self.values(tile) * tile.exptime_s * tile.bin ** 2).astype(np.float32)


class BiasField(_FieldBase):
    """Bias structure ``amp (g - <g>)`` [ADU per read-out value], peak to peak ``amp``, of zero mean over the
    window: ADU stage. The scene's bias level is what a bias frame's mean measures; a structure is the departure
    from it (a field of non-zero mean is a bias structure and a wrong bias level, two findings)."""

    name = "rf_bias_field"
    stages = (Stage.ADU,)

    def apply(self, stage, tile, data):
        data += (self.params.amp * (self.values(tile) - self.params.spec.get("mean", 0.5))).astype(np.float32)


# --- periodic patterns (out of the catalogue) ---------------------------------------------------------------------

def periodic_wave(p, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """A zero-mean periodic wave of unit amplitude at window pixel coordinates x, y [sensor px] (1-D): a
    "sine", "square" or "triangle" wave along ``angle`` of period ``period_px``, or "rings" of that period
    about the point (``cu``, ``cv``) [window fractions, far off the window]."""
    X, Y = x[None, :], y[:, None]
    if p.waveform == "rings":
        w, h = p.window
        ph = np.hypot(X - p.cu * w, Y - p.cv * h) / p.period_px
    else:
        ph = (math.cos(p.angle) * X + math.sin(p.angle) * Y) / p.period_px
    ph = 2 * np.pi * ph + p.phase
    if p.waveform == "square":
        return np.sign(np.sin(ph))
    if p.waveform == "triangle":
        return 2 / np.pi * np.arcsin(np.sin(ph))
    return np.sin(ph)


class PeriodicPattern(RealWorld):
    """A periodic pattern (:func:`periodic_wave`) of amplitude ``amp`` acting as the subclass's ``role``:
    "response" (``1 + amp wave``), "dark" or "light" (``amp (1 + wave)`` [e-/s per unbinned pixel]) or "bias"
    (``amp wave`` [ADU]). Fringes, a pickup, a flickering lamp, tree rings: no plugin models them."""

    name = "rf_periodic"
    role = "response"
    stages = (Stage.RESPONSE,)

    def apply(self, stage, tile, data):
        p = self.params
        x, y, _w, _h = U._win(tile)
        wave = periodic_wave(p, x, y)
        if self.role == "response":
            data *= (1 + p.amp * wave).astype(np.float32)
        elif self.role == "bias":
            data += (p.amp * wave).astype(np.float32)
        elif self.role == "dark" or data.any():
            data += (p.amp * (1 + wave) * tile.exptime_s * tile.bin ** 2).astype(np.float32)


class PeriodicDark(PeriodicPattern):
    """:class:`PeriodicPattern` on the dark rate (DARK stage)."""

    role, stages = "dark", (Stage.DARK,)


class PeriodicBias(PeriodicPattern):
    """:class:`PeriodicPattern` on the bias [ADU] (ADU stage)."""

    role, stages = "bias", (Stage.ADU,)


class PeriodicLight(PeriodicPattern):
    """:class:`PeriodicPattern` on the light (FIELD stage)."""

    role, stages = "light", (Stage.FIELD,)


# --- kernels ------------------------------------------------------------------------------------------------------

#: sub-pixel steps per pixel on which :func:`blur_transfer` samples a kernel: the sampled kernel's transfer function
#: differs from the continuous one by its alias at 16 cycles/px, below 3e-4 for the narrowest draws (an "exp" kernel
#: of 0.15 px: (1 + (2 pi 0.15 x 16)^2)^-1.5; a Gaussian's is exp(-2 pi^2 (0.045 x 16)^2) ~ 4e-5)
BLUR_OVERSAMPLE = 16


def _blur_half(law: str, size_px: float) -> int:
    """The kernel's half width [px]: 4 scale lengths (8 for the heavy-tailed laws), at most 12 px."""
    return int(min(12, math.ceil(4 * size_px * (2 if law in ("moffat", "exp") else 1)) + 1))


def _blur_profile(law: str, size_px: float, q: float, theta: float, beta: float, x: np.ndarray,
                  y: np.ndarray) -> np.ndarray:
    """The continuous kernel's profile (unnormalised) at offsets (``x``, ``y``) [px]: "gauss" (sigma ``size_px``
    along the major axis at ``theta``, ``q`` the axis ratio), "moffat" (FWHM 2.355 ``size_px``, ``beta``), "exp"
    (exp(-r / size)); "wing" is the Gaussian of its halo."""
    c, s = math.cos(theta), math.sin(theta)
    a, b = c * x + s * y, (-s * x + c * y) / q
    r2 = a * a + b * b
    if law == "moffat":
        fwhm = 2.355 * size_px
        alpha = fwhm / (2 * math.sqrt(2 ** (1 / beta) - 1))
        return (1 + r2 / alpha ** 2) ** (-beta)
    if law == "exp":
        return np.exp(-np.sqrt(r2) / size_px)
    return np.exp(-r2 / (2 * size_px ** 2))


def blur_transfer(law: str, size_px: float, q: float, theta: float, beta: float, wing: float,
                  shape: tuple[int, int]) -> np.ndarray:
    """The transfer function of a normalised continuous kernel on the ``rfft2`` frequencies of an image of
    ``shape``: "gauss" (sigma ``size_px`` along the major axis at ``theta``, ``q`` the axis ratio), "moffat" (FWHM
    2.355 ``size_px``, ``beta``), "exp" (exp(-r / size)), "wing" (a delta core plus ``wing`` of the light in a
    Gaussian of ``size_px``: a scattering halo), within :func:`_blur_half`. Its Fourier integral, a direct sum over
    :data:`BLUR_OVERSAMPLE` sub-pixel steps (two matrix products: the profile is not separable once rotated). The
    image's samples are the pixel-integrated light, so multiplying their spectrum by it blurs that light by the
    continuous kernel, as a change of the PSF does, whatever the kernel's width: the kernel's own samples at the
    pixel centres do not (a Gaussian of 0.26 px sampled there keeps 2 % of its variance, at axis ratio 0.47
    0.001 %)."""
    half = _blur_half(law, size_px)
    t = np.arange(-half * BLUR_OVERSAMPLE, half * BLUR_OVERSAMPLE + 1) / BLUR_OVERSAMPLE
    k = _blur_profile(law, size_px, q, theta, beta, t[None, :], t[:, None])
    fy, fx = np.fft.fftfreq(shape[0]), np.fft.rfftfreq(shape[1])
    ey = np.exp(-2j * np.pi * fy[:, None] * t[None, :])
    ex = np.exp(-2j * np.pi * fx[:, None] * t[None, :])
    h = ey @ k @ ex.T / k.sum()
    if law == "wing":
        h = (1 - wing) + wing * h
    return h


class KernelBlur(RealWorld):
    """The image blurred by a continuous kernel (a PSF broadening, an elongation): its spectrum multiplied by
    :func:`blur_transfer` on the edge-extended image; FIELD stage, flux kept."""

    name = "rf_blur"
    stages = (Stage.FIELD,)

    def apply(self, stage, tile, data):
        p = self.params
        h = _blur_half(p.law, p.size_px)
        big = np.pad(np.asarray(data, np.float64), h, mode="edge")
        transfer = blur_transfer(p.law, p.size_px, p.q, p.theta, p.beta, p.wing, big.shape)
        out = np.fft.irfft2(np.fft.rfft2(big) * transfer, s=big.shape)[h:-h, h:-h]
        data[...] = np.maximum(out, 0)


class RandomIPC(RealWorld):
    """Inter-pixel capacitance with a 3x3 kernel of four unequal nearest-neighbour couplings and diagonals
    (``left``, ``right``, ``up``, ``down``, ``diag``; :func:`.hidden.couple_3x3`): COUPLING stage."""

    name = "rf_ipc"
    stages = (Stage.COUPLING,)
    halo_rows = 1
    coupling_order = 2

    def couple(self, tile, charge_e, pad_top, pad_bottom, mean_only=False):
        p = self.params
        return HE["couple_3x3"](charge_e, [[p.diag, p.up, p.diag], [p.right, 0.0, p.left], [p.diag, p.down, p.diag]])


def bf_kernel(law: str, half: int, scale: float, aniso: float) -> np.ndarray:
    """A brighter-fatter potential on (2 half + 1)^2 pixels, 1 at the centre: "exp" exp(-r / scale), "gauss"
    (sigma ``scale``), "power" (r + 0.5)^-scale, "coulomb" 1 / sqrt(r^2 + scale^2); ``aniso`` stretches the
    distance along the columns (r = hypot(aniso y, x)). The law less its value at r = half + 1, clipped at 0: a
    potential that falls to zero at the edge of its support (cut there with a step, its Laplacian, the area
    coefficients, would be largest at the step: :func:`bf_physical`)."""
    t = np.arange(-half, half + 1, dtype=float)
    r = np.hypot(aniso * t[:, None], t[None, :])
    if law == "exp":
        f = lambda r: np.exp(-r / scale)  # noqa: E731
    elif law == "gauss":
        f = lambda r: np.exp(-r * r / (2 * scale ** 2))  # noqa: E731
    elif law == "power":
        f = lambda r: (r + 0.5) ** -scale  # noqa: E731
    else:
        f = lambda r: 1 / np.sqrt(r * r + scale ** 2)  # noqa: E731
    k = np.maximum(f(r) - f(half + 1.0), 0.0)
    return k / k[half, half]


class RandomBF(RealWorld):
    """Brighter-fatter: pixel boundaries shifting with the potential :func:`bf_kernel` of the collected charge
    (:func:`.unseen._bf_moved`, charge conserved), nearest-neighbour area coefficient ``a10_per_e``, growing with
    the charge when ``q_nl_frac`` is set (Astier et al. 2019, A&A 629, A36): COUPLING stage."""

    name = "rf_bf"
    stages = (Stage.COUPLING,)
    halo_rows = 5
    coupling_order = 0

    def couple(self, tile, charge_e, pad_top, pad_bottom, mean_only=False):
        p = self.params
        k = bf_kernel(p.law, p.half, p.scale, p.aniso)
        lap = U._lap10(k)
        q_nl = p.q_nl_frac * self.sensor.full_well_e if p.q_nl_frac else None
        return U._bf_moved(np.asarray(charge_e, np.float32), k, p.a10_per_e / lap, q_nl)


# --- laws -----------------------------------------------------------------------------------------------------------

def nl_response(law: str, x: np.ndarray, prm: dict) -> np.ndarray:
    """The response S'/FW of a signal x = S/FW: "knee" (slope ``slope`` above ``knee``), "gamma" (x (x / s0)^(g -
    1)), "poly" (x (1 - sum c_k x^k), k = 1..), "tanh" (a tanh(x / a))."""
    x = np.asarray(x, np.float64)
    if law == "knee":
        return x - (1 - prm["slope"]) * np.maximum(x - prm["knee"], 0)
    if law == "gamma":
        return x * (np.maximum(x, 1e-12) / prm["s0"]) ** (prm["g"] - 1)
    if law == "poly":
        return x * (1 - sum(c * x ** (k + 1) for k, c in enumerate(prm["coef"])))
    return prm["a"] * np.tanh(x / prm["a"])


def nl_params(law: str, loss: float, rng) -> dict:
    """Parameters of ``law`` whose response at full well is ``1 - loss`` (a compression of ``loss``)."""
    if law == "knee":
        knee = float(rng.uniform(0.3, 0.8))
        return {"knee": knee, "slope": 1 - loss / (1 - knee)}
    if law == "gamma":
        s0 = float(rng.uniform(0.05, 0.3))
        return {"s0": s0, "g": 1 + math.log(1 - loss) / math.log(1 / s0)}
    if law == "poly":
        w = rng.dirichlet(np.ones(int(rng.integers(1, 5))))
        return {"coef": [float(loss * v) for v in w]}
    a = optimize.brentq(lambda a: 1 - a * math.tanh(1 / a) - loss, 0.05, 1e5)
    return {"a": float(a)}


class RandomNonlinearity(RealWorld):
    """A compressive response :func:`nl_response` of the collected charge (READ stage, before the read noise)."""

    name = "rf_nonlinearity"
    stages = (Stage.READ,)

    def apply(self, stage, tile, data):
        fw = np.float64(self.sensor.full_well_e * tile.bin ** 2)
        data[...] = (nl_response(self.params.law, np.maximum(data, 0) / fw, self.params.prm) * fw).astype(np.float32)


def _window_pixels(sensor, rng, density: float):
    """Sensor (rows, cols) of ``density`` x the window's pixels, drawn uniformly in the read-out window."""
    w, h = sensor.roi_shape
    n = int(rng.binomial(w * h, min(density, 1.0)))
    flat = np.unique(rng.integers(0, w * h, n))
    return flat // w + sensor.roi_y0, flat % w + sensor.roi_x0


def _add_at(tile, data, rows, cols, values, multiply=False):
    sel = (rows >= tile.y0) & (rows < tile.y1) & (cols >= tile.x0) & (cols < tile.x1)
    if not sel.any():
        return
    b = tile.bin
    r, c = (rows[sel] - tile.y0) // b, (cols[sel] - tile.x0) // b
    v = np.asarray(values)[sel].astype(np.float32)
    if multiply:
        data[r, c] *= v
    else:
        np.add.at(data, (r, c), v)


def rate_law(law: str, rng, n: int, median: float, spread: float) -> np.ndarray:
    """``n`` rates of median about ``median``: "lognormal" (sigma_ln ``spread``), "pareto" (index 1 / spread),
    "exponential", "weibull" (shape 1 / spread), "bimodal" (two lognormal populations 10x apart)."""
    if law == "lognormal":
        return median * np.exp(spread * rng.standard_normal(n))
    if law == "pareto":
        a = 1 / spread
        return median / 2 ** (1 / a) * (1 - rng.random(n)) ** (-1 / a)
    if law == "exponential":
        return rng.exponential(median / math.log(2), n)
    if law == "weibull":
        k = 1 / spread
        return median / math.log(2) ** (1 / k) * rng.weibull(k, n)
    hi = rng.random(n) < 0.2
    return median * np.where(hi, 10.0, 1.0) * np.exp(0.3 * rng.standard_normal(n))


class RandomHotPixels(RealWorld):
    """Hot pixels at ``density`` of the window's pixels (the case's own positions), rates of :func:`rate_law`
    [e-/s], optionally in vertical pairs sharing the rate: DARK stage."""

    name = "rf_hot"
    stages = (Stage.DARK,)

    def setup(self):
        p = self.params
        rng = np.random.default_rng(p.seed)
        self.rows, self.cols = _window_pixels(self.sensor, rng, p.density)
        self.rate = rate_law(p.law, rng, self.rows.size, p.median_e_per_s, p.spread)

    def apply(self, stage, tile, data):
        for dy in range(2 if self.params.pairs else 1):
            _add_at(tile, data, self.rows + dy, self.cols, self.rate * tile.exptime_s)


class RandomDeadPixels(RealWorld):
    """Dead or weak pixels at ``density`` of the window's pixels, in ``size`` x ``size`` clusters, residual
    response uniform in [0, ``max_response``] ("uniform") or ``max_response`` for all ("fixed"): RESPONSE stage."""

    name = "rf_dead"
    stages = (Stage.RESPONSE,)

    def setup(self):
        p = self.params
        rng = np.random.default_rng(p.seed)
        self.rows, self.cols = _window_pixels(self.sensor, rng, p.density)
        n = self.rows.size
        self.resp = rng.uniform(0, p.max_response, n) if p.law == "uniform" else np.full(n, p.max_response)

    def apply(self, stage, tile, data):
        for dy in range(self.params.size):
            for dx in range(self.params.size):
                _add_at(tile, data, self.rows + dy, self.cols + dx, self.resp, multiply=True)


class WindowGains(RealWorld):
    """Amplifier gains of strips along ``axis`` ("x": columns, "y": rows) with boundaries at window fractions
    ``splits``, gains ``gains``, tanh transitions of ``width_px`` [sensor px] and a linear ``drift`` across the
    window: ADU stage."""

    name = "rf_gains"
    stages = (Stage.ADU,)

    def apply(self, stage, tile, data):
        p = self.params
        x, y, w, h = U._win(tile)
        coord, size = (x, w) if p.axis == "x" else (y, h)
        g = np.full(coord.shape, p.gains[0], float)
        for b, g0, g1 in zip(p.splits, p.gains[:-1], p.gains[1:]):
            g += (g1 - g0) * 0.5 * (1 + np.tanh((coord - b * size) / max(p.width_px, 1e-3)))
        g *= 1 + p.drift * (coord / size - 0.5)
        data *= (g[None, :] if p.axis == "x" else g[:, None]).astype(np.float32)


# --- profiles -------------------------------------------------------------------------------------------------------

class RandomCTI(RealWorld):
    """Charge-transfer inefficiency of trap species of release times ``release_transfers`` and densities
    ``densities`` [traps/px], well-fill power ``beta``, capture ``capture`` (:func:`.unseen._cti_columns`, one pass
    per species), in the "parallel" read-out (trails along the columns) or the "serial" register (trails along
    the rows, transfers counted from column 0): COUPLING stage, charge conserved."""

    name = "rf_cti"
    stages = (Stage.COUPLING,)
    halo_rows = None
    coupling_order = 1

    def couple(self, tile, charge_e, pad_top, pad_bottom, mean_only=False):
        p, s = self.params, self.sensor
        serial = p.direction == "serial"
        img = np.array(charge_e, np.float64)
        img = img.T.copy() if serial else img
        first = tile.x0 + 1 if serial else tile.y0 - pad_top + 1
        for tau, dens in zip(p.release_transfers, p.densities):
            img = U._cti_columns(img, np.full(img.shape[1], dens), math.exp(-1 / tau), p.beta,
                                 s.full_well_e, first, capture=p.capture)
        return (img.T if serial else img).astype(np.float32)


class RandomBleed(RealWorld):
    """Blooming above ``threshold`` x full well: ``drain`` of the excess removed, ``side`` of it into the two
    neighbouring columns, the rest filled along the column (``up_fraction`` upwards; or, ``soft``, spread with an
    exponential profile of ``length_px``): FIELD stage."""

    name = "rf_bleed"
    stages = (Stage.FIELD,)

    def apply(self, stage, tile, data):
        p = self.params
        thr = np.float32(p.threshold * self.sensor.full_well_e)
        excess = np.maximum(data - thr, 0)
        if not excess.any():
            return
        data -= np.float32(p.drain + p.side) * excess
        side = np.float32(p.side) * excess
        data[:, 1:] += side[:, :-1] / 2
        data[:, :-1] += side[:, 1:] / 2
        if p.soft:
            rest = np.maximum(data - thr, 0)
            data -= rest
            n = int(6 * p.length_px) + 1
            k = np.exp(-np.arange(1, n + 1) / p.length_px)
            kern = np.concatenate([(1 - p.up_fraction) * k[::-1] / k.sum(), [0.0], p.up_fraction * k / k.sum()])
            data += ndimage.convolve1d(rest, kern.astype(np.float32), axis=0, mode="constant")
        else:
            bleed_columns(data, float(thr), p.up_fraction)


# --- the families -----------------------------------------------------------------------------------------------------

@dataclass
class Draw:
    """What a family draws: the base scene, the effects (class name, parameters), the accepted names (or the
    expected morphology), the strength position t in [0, 1] (1: the strongest of the family's range)."""

    base: str
    effects: list  #: [(class name, params dict)]
    description: str
    strength: float
    accept: tuple = ()
    kind: str | None = None
    geometry: tuple = ()
    #: parts of the drawn effect that are catalogue effects of their own: (names, effects without the part); the
    #: names are right too when the part alone is seen (:func:`part_seen`)
    parts: tuple = ()
    #: the drawn effect's own scale of the frame's mean light (a mosaic's mean response): with the case's light
    #: level, a scene parameter (:attr:`RandomCase.accept`)
    light_scale: float = 1.0


def _choice(rng, seq):
    return seq[int(rng.integers(len(seq)))]


def _radial_spec(rng, centre=(0.15, 0.85)) -> dict:
    law = _choice(rng, ["power", "gauss", "cos4", "lorentz", "poly"])
    spec = {"form": "radial", "cu": float(rng.uniform(*centre)), "cv": float(rng.uniform(*centre)),
            "q": float(rng.uniform(0.6, 1.0)), "theta": float(rng.uniform(0, np.pi)), "law": law}
    if law == "power":
        spec["p"] = float(rng.uniform(1.5, 6.0))
    elif law == "poly":
        spec["coef"] = [float(v) for v in rng.dirichlet(np.ones(int(rng.integers(1, 4))))]
    else:
        spec["s"] = float(rng.uniform(0.3, 1.5))
    return spec


def _poly_spec(rng, order_lo=2, order_hi=4) -> dict:
    n = int(rng.integers(order_lo, order_hi + 1))
    terms = [(i, j) for i in range(n + 1) for j in range(n + 1 - i) if i + j > 0]
    coef = rng.standard_normal(len(terms)) / np.array([1 + 0.5 * (i + j) for i, j in terms])
    return {"form": "poly", "order": n, "terms": terms, "coef": [float(c) for c in coef]}


def _waves_spec(rng, max_cycles=1.5) -> dict:
    n = int(rng.integers(1, 4))
    return {"form": "waves", "cycles": [float(v) for v in rng.uniform(0.2, max_cycles, n)],
            "angle": [float(v) for v in rng.uniform(0, np.pi, n)], "phase": [float(v) for v in rng.uniform(0, 2 * np.pi, n)]}


def _point_spec(rng, outside=True, d0=(0.05, 0.6)) -> dict:
    if outside:
        side = int(rng.integers(4))
        a, b = float(rng.uniform(-0.3, 1.3)), float(rng.uniform(1.05, 1.8))
        pu, pv = [(a, b), (a, 1 - b), (b, a), (1 - b, a)][side]
    else:
        pu, pv = float(rng.uniform(0.1, 0.9)), float(rng.uniform(0.1, 0.9))
    return {"form": "point", "pu": pu, "pv": pv, "d0": float(rng.uniform(*d0)), "index": float(rng.uniform(1.0, 3.5))}


def _edge_spec(rng) -> dict:
    return {"form": "edge", "edge": _choice(rng, ["left", "right", "top", "bottom"]), "pos": float(rng.uniform(0, 1)),
            "sigma": float(rng.uniform(0.1, 0.6)), "lam": float(rng.uniform(0.03, 0.25))}


def _plane_spec(rng) -> dict:
    return {"form": "plane", "angle": float(rng.uniform(0, 2 * np.pi))}


def _sigma_amp(rng, info, lo, hi):
    """An amplitude [e- per output pixel] log-uniform in [lo, hi] x the base's pixel noise, and its position."""
    k, t = _loguniform(rng, lo, hi)
    return k * info["noise_e"], t, k


def _per_s_per_px(info, e_out):
    """e- per output pixel -> e-/s per unbinned pixel."""
    return e_out / (info["time_s"] * info["bin"] ** 2)


def fam_vignetting(rng):
    base = _choice(rng, ["flat", "flat_full", "flat_imx", "flat_imx_bin", "stars", "stars_imx", "stars_bright"])
    info = base_info(base)
    spec = normalise(_radial_spec(rng))
    # the depth in units of the light's relative noise, capped at 30 % (a strong vignetting)
    e, t, k = _sigma_amp(rng, info, 0.05, 30.0)
    depth = min(e / info["light_e"], 0.3)
    return Draw(base, [("ResponseField", {"spec": spec, "amp": depth})],
                f"{spec['law']} radial fall-off about ({spec['cu']:.2f}, {spec['cv']:.2f}), axis ratio {spec['q']:.2f}, "
                f"{100 * depth:.3g} % deep ({k:.3g} sigma)", t, accept=("vignetting",))


def _light_draw(rng, forms, accept, label):
    base = _choice(rng, ["stars", "stars_imx", "stars_bright", "sky_imx_bin"])
    info = base_info(base)
    form = _choice(rng, forms)
    spec = {"point": lambda: _point_spec(rng), "radial": lambda: _radial_spec(rng, (-0.3, 1.3)),
            "poly": lambda: _poly_spec(rng, 2, 3), "waves": lambda: _waves_spec(rng, 1.2),
            "edge": lambda: _edge_spec(rng), "plane": lambda: _plane_spec(rng)}[form]()
    spec = normalise(spec)
    e, t, k = _sigma_amp(rng, info, 0.03, 10.0)
    amp = _per_s_per_px(info, e)
    return Draw(base, [("LightField", {"spec": spec, "amp": amp})],
                f"{label}: additive light, {form} field, {amp:.3g} e-/s/px peak to peak ({k:.3g} sigma, "
                f"{100 * amp / info['light_rate']:.3g} % of the sky)", t, accept=accept)


def fam_straylight(rng):
    return _light_draw(rng, ["point", "radial", "poly", "waves", "edge"], ("straylight", "sky_gradient"), "straylight")


def fam_sky_gradient(rng):
    return _light_draw(rng, ["plane"], ("sky_gradient", "straylight"), "sky gradient")


#: the temperature spans across the whole sensor a dark gradient is drawn from [K]: from a tenth of a kelvin to
#: the most a cooled die on one cold plate shows (detector.effects.thermal.MAX_TEMPERATURE_SPAN_K): a dark-rate
#: pattern beyond that is not a temperature gradient but a glow or a light leak, and is not drawn as one
DARK_SPAN_K = (0.1, 20.0)


def fam_dark_gradient(rng):
    """A dark-current pattern a temperature difference across the die makes: its size is physical (the dark
    rate at the sensor's temperature, doubling every T_2 K, over a drawn span of DARK_SPAN_K across the
    sensor, of which the window sees its share), its form a plane, an exponential plane or a quadratic."""
    from detector.effects.thermal import doubling_interval_k
    from detector.presets import PRESETS

    # not the IMX411 corner window: at its 0.002 e-/s a temperature gradient is below the read noise in any
    # exposure of the bases (drawn there, every case would be undetectable by construction)
    base = _choice(rng, ["dark", "dark_full"])
    info = small_info(base)
    pre = PRESETS[info["camera"]]
    form = _choice(rng, ["plane", "thermal", "poly"])
    span_k, t = _loguniform(rng, *DARK_SPAN_K)
    # the span as the judge measures it, corner to corner (|dT_x| + |dT_y| across the sensor's width and
    # height), split at a random angle; the window sees the part of it its width and height cover
    a = float(rng.uniform(0, 2 * np.pi))
    w_k = span_k * math.cos(a) / (abs(math.cos(a)) + abs(math.sin(a)))
    h_k = span_k * math.sin(a) / (abs(math.cos(a)) + abs(math.sin(a)))
    h, w = info["out_shape"]
    fx = min(1.0, w * info["bin"] / pre["sensor_width_px"])
    fy = min(1.0, h * info["bin"] / pre["sensor_height_px"])
    t2 = doubling_interval_k(float(pre.get("temperature_c", -10.0)))
    gx, gy = w_k * fx / t2, h_k * fy / t2  # doublings across the window's width and height
    dk = abs(gx) + abs(gy)  # doublings corner to corner of the window
    spec = {"plane": lambda: {"form": "plane", "angle": math.atan2(gy, gx)}, "poly": lambda: _poly_spec(rng, 2, 2),
            "thermal": lambda: {"form": "thermal", "angle": math.atan2(gy, gx), "dk": math.hypot(gx, gy)}}[form]()
    spec = normalise(spec)
    amp = info["dark_rate"] * (2.0 ** dk - 1.0)  # peak-to-peak change of the dark rate in the window [e-/s]
    k = amp * info["time_s"] * info["bin"] ** 2 / info["noise_e"]
    accept = ("dark_gradient",) if form != "poly" else ("dark_gradient", "amp_glow")
    return Draw(base, [("DarkField", {"spec": spec, "amp": amp})],
                f"dark rate: {form} field, {amp:.3g} e-/s/px peak to peak ({span_k:.3g} K across the sensor, "
                f"{k:.3g} sigma)", t, accept=accept)


def fam_amp_glow(rng):
    """An amplifier glow: light of the read-out amplifier at the sensor's edge, so drawn only on the base whose
    window holds a sensor corner with its amplifier (the IMX411 corner window, sensor edges at its right and
    bottom): a power law of the distance to a point at or just beyond that corner or one of its two edges, or
    an edge glow along one of them."""
    base = "dark_corner"
    info = base_info(base)
    form = _choice(rng, ["point", "edge"])
    if form == "point":
        # the window's right edge (u = 1) and first row (v = 0) are the sensor's edges
        where = _choice(rng, ["corner", "right", "bottom"])
        pu = float(rng.uniform(1.0, 1.15)) if where != "bottom" else float(rng.uniform(0.2, 1.0))
        pv = float(rng.uniform(-0.15, 0.0)) if where != "right" else float(rng.uniform(0.0, 0.8))
        spec = {"form": "point", "pu": pu, "pv": pv, "d0": float(rng.uniform(0.03, 0.3)),
                "index": float(rng.uniform(1.0, 3.5))}
    else:
        spec = {**_edge_spec(rng), "edge": _choice(rng, ["right", "bottom"])}
    spec = normalise(spec)
    e, t, k = _sigma_amp(rng, info, 0.1, 30.0)
    amp = _per_s_per_px(info, e)
    return Draw(base, [("DarkField", {"spec": spec, "amp": amp})],
                f"glow: {form} field, {amp:.3g} e-/s/px at its peak in the window ({k:.3g} sigma)", t,
                accept=("amp_glow", "dark_gradient") if form == "point" and spec["d0"] > 0.25 else ("amp_glow",))


def fam_bias_gradient(rng):
    base = _choice(rng, ["bias_full", "bias_imx"])
    info = base_info(base)
    form = _choice(rng, ["plane", "poly", "waves", "radial", "step"])
    spec = {"plane": lambda: _plane_spec(rng), "poly": lambda: _poly_spec(rng, 1, 3), "waves": lambda: _waves_spec(rng, 2.5),
            "radial": lambda: _radial_spec(rng),
            "step": lambda: {"form": "step", "angle": float(_choice(rng, [0.0, np.pi / 2])),
                             "at": float(rng.uniform(0.2, 0.8))}}[form]()
    spec = normalise(spec)
    e, t, k = _sigma_amp(rng, info, 0.03, 5.0)
    reads = info["bin"] ** 2 if info["cmos"] else 1
    amp = e / info["gain"] / reads
    return Draw(base, [("BiasField", {"spec": spec, "amp": amp})],
                f"bias structure: {form} field, {amp:.3g} ADU peak to peak per read ({k:.3g} sigma)", t,
                accept=("bias_gradient",))


def fam_prnu(rng):
    base = _choice(rng, ["flat", "flat_imx"])
    info = base_info(base)
    rel, t = _loguniform(rng, 0.1, 3.0)
    k = rel
    white = rel / math.sqrt(info["light_e"])
    form = _choice(rng, ["lf", "columns", "lognormal"])
    parts = ()
    if form == "lf":
        lf = white * float(rng.uniform(0.2, 2.0))
        eff = ("LowFrequencyPRNU", {"white": white, "lf_rms": lf, "lf_cycles": float(rng.uniform(2, 30))})
        # its low-frequency part is a smooth response field of its own (the PRNU's large scales: EMVA 1288
        # Release 4.0, sect. 8.3, its spectrogram), the field a vignetting fit takes: that name is right too when
        # the frame sees the part alone (the parts rule every drawn form follows, as a DSNU's large scales)
        accept = ("prnu",)
        parts = ((("vignetting",), [("LowFrequencyPRNU", {**eff[1], "lf_rms": 0.0})]),)
        desc = f"white PRNU {100 * white:.3g} % + low-frequency {100 * lf:.3g} %"
    elif form == "columns":
        col = white * float(rng.uniform(0.3, 2.0))
        eff = ("ColumnPRNU", {"law": "columns", "col_rms": col, "white": white})
        accept, desc = ("prnu", "column_defects"), f"PRNU column pattern {100 * col:.3g} % + white {100 * white:.3g} %"
    else:
        eff = ("ColumnPRNU", {"law": "lognormal", "col_rms": 0.0, "white": white})
        accept, desc = ("prnu",), f"lognormal PRNU {100 * white:.3g} %"
    return Draw(base, [eff], f"{desc} ({k:.3g} x the shot noise)", t, accept=accept, parts=parts)


def fam_dsnu(rng):
    base = _choice(rng, ["dark", "dark_full", "dark_corner"])
    info = base_info(base)
    sigma, t = _loguniform(rng, 0.05, 0.8) if not info["cmos"] else _loguniform(rng, 0.3, 3.0)
    law = _choice(rng, ["uniform", "student"] + (["gamma"] if base == "dark" else []))
    parts = ()
    if law == "gamma":
        lf_rms = float(rng.uniform(0, 0.15))
        eff = ("GammaDSNU", {"sigma": sigma, "lf_rms": lf_rms})
        # the smooth part is a field of dark rate of its own: the DSNU spans every spatial scale and its large
        # scales are a dark-rate non-uniformity (EMVA 1288 Release 4.0, sect. 8.3; judge.same_dark_field), which
        # is what a frame whose white part sits under its read noise shows: dark_gradient is right too when the
        # frame sees that part alone (the parts rule every drawn form follows)
        parts = ((("dark_gradient",), [("GammaDSNU", {"sigma": sigma, "lf_rms": 0.0})]),) if lf_rms > 0 else ()
    else:
        eff = ("LawDSNU", {"law": law, "sigma": sigma})
    return Draw(base, [eff], f"{law} DSNU, relative std {sigma:.3g}", t, accept=("dsnu",), parts=parts)


def fam_hot_pixels(rng):
    base = _choice(rng, ["dark", "dark_full", "dark_corner"])
    info = base_info(base)
    density, t1 = _loguniform(rng, 3e-5, 3e-3)
    k, t2 = _loguniform(rng, 1.0, 50.0)
    median = _per_s_per_px(info, k * info["noise_e"])
    law = _choice(rng, ["lognormal", "pareto", "exponential", "weibull", "bimodal"])
    prm = {"density": density, "law": law, "median_e_per_s": median, "spread": float(rng.uniform(0.4, 1.2)),
           "pairs": bool(rng.random() < 0.25), "seed": int(rng.integers(2 ** 31))}
    return Draw(base, [("RandomHotPixels", prm)], f"hot pixels ({law}, density {density:.2g}, median {k:.3g} sigma"
                f"{', vertical pairs' if prm['pairs'] else ''})", 0.5 * (t1 + t2), accept=("hot_pixels",))


def fam_dead_pixels(rng):
    base = _choice(rng, ["flat", "flat_imx"])
    density, t = _loguniform(rng, 3e-5, 1e-2)
    size = int(_choice(rng, [1, 1, 2, 3]))
    law = _choice(rng, ["uniform", "fixed"])
    prm = {"density": density, "size": size, "law": law, "max_response": float(rng.uniform(0.0, 0.8)),
           "seed": int(rng.integers(2 ** 31))}
    return Draw(base, [("RandomDeadPixels", prm)], f"dead/weak pixels ({size}x{size}, density {density:.2g}, response "
                f"{law} up to {prm['max_response']:.2f})", t, accept=("dead_pixels",))


def fam_column_defects(rng):
    form = _choice(rng, ["trap", "leak", "weak"])
    n, t1 = _loguniform(rng, 2, 20)
    n = round(n)
    if form == "weak":
        base = _choice(rng, ["flat", "flat_imx"])
        info = base_info(base)
        k, t2 = _loguniform(rng, 0.5, 20.0)
        resp = max(1 - k / math.sqrt(info["light_e"]), 0.05)
        eff = ("WeakColumns", {"n_columns": n, "response": resp})
        desc = f"{n} columns of response {resp:.3g}"
    else:
        base = "dark"  # a leak grows along the sensor's column: the CMOS amplifier corner holds its first 5 %
        info = base_info(base)
        k, t2 = _loguniform(rng, 0.1, 5.0)
        rate = _per_s_per_px(info, k * info["noise_e"])
        eff = (("TrapColumns", {"n_columns": n, "median_rate_e_per_s": rate, "sigma_ln": float(rng.uniform(0.2, 1.0))})
               if form == "trap" else ("LeakColumns", {"n_columns": n, "rate_e_per_s": 2 * rate}))
        desc = f"{n} {form} columns, {k:.3g} sigma per pixel"
    return Draw(base, [eff], desc, 0.5 * (t1 + t2), accept=("column_defects",))


#: the extra particle flux a cosmic-ray case draws, in units of the model's environment (ground muons): from a
#: few times (altitude, a radioactive window or housing) to 40x, below the judge's physical ceiling (50x,
#: ``max_cosmic_rate_factor``); a "rate" beyond is a pattern of bright pixels, not particles
COSMIC_FACTOR = (3.0, 40.0)


def fam_cosmic_rays(rng):
    """Extra particle tracks at a physical rate: ``factor`` x the ground muon flux over the window's area and
    the exposure (the count Poisson-drawn, at least one track), straight tracks of random length and deposit."""
    from detector.cosmics import ENVIRONMENTS
    from detector.presets import PRESETS

    base = _choice(rng, ["dark", "dark_full", "dark_corner", "dark_cmos"])
    info = small_info(base)
    factor, t = _loguniform(rng, *COSMIC_FACTOR)
    h, w = info["out_shape"]
    pitch_cm = PRESETS[info["camera"]]["pixel_pitch_um"] * 1e-4
    area_cm2 = h * w * info["bin"] ** 2 * pitch_cm ** 2
    mean = factor * ENVIRONMENTS["ground"].flux_per_cm2_s * area_cm2 * info["time_s"]
    n = max(1, int(rng.poisson(mean)))
    lmin = float(rng.uniform(1, 5))
    prm = {"n": n, "lmin": lmin, "lmax": lmin + float(rng.uniform(2, 50)),
           "e_per_px": float(np.exp(rng.uniform(np.log(60), np.log(800))))}
    return Draw(base, [("SegmentTracks", prm)], f"{prm['n']} tracks of {prm['lmin']:.0f}-{prm['lmax']:.0f} px, "
                f"{prm['e_per_px']:.0f} e-/px ({factor:.3g}x the ground flux)", t, accept=("cosmic_rays",))


def fam_rts_noise(rng):
    base = _choice(rng, ["dark_cmos", "dark_corner"])
    form = _choice(rng, ["twotrap", "threestate", "exponential"])
    frac, t = _loguniform(rng, 3e-4, 6e-3)
    amp = float(np.exp(rng.uniform(np.log(10), np.log(60))))
    if form == "twotrap":
        eff = ("TwoTrapRTS", {"fraction": frac, "mean1_e": amp, "mean2_e": amp * float(rng.uniform(0.2, 0.8)),
                              "tau_med_s": float(np.exp(rng.uniform(np.log(5e-6), np.log(5e-5)))),
                              "tau_sigma_ln": float(rng.uniform(0.3, 1.5)), "cds_s": 4e-6})
    elif form == "threestate":
        eff = ("ThreeStateRTS", {"fraction": frac, "amp_lo_e": 0.5 * amp, "amp_hi_e": 1.5 * amp,
                                 "mid": float(rng.uniform(0.2, 0.8)), "tau_lo_s": 3e-6, "tau_hi_s": 6e-5, "cds_s": 4e-6})
    else:
        eff = ("ExponentialRTS", {"fraction": frac, "mean_e": amp})
    return Draw(base, [eff], f"{form} RTS in {100 * frac:.2g} % of the pixels, amplitudes ~{amp:.0f} e-", t,
                accept=("rts_noise",))


def fam_reset_noise(rng):
    base = _choice(rng, ["dark", "dark_cmos", "dark_corner"])
    info = base_info(base)
    form = _choice(rng, ["laplace", "alternate", "ktc"])
    k, t = _loguniform(rng, 0.3, 2.0)
    sig = k * info["read_noise_e"]
    if form == "ktc":
        # kT/C noise sigma = sqrt(k T C) / q: the capacitance for ``sig`` at 250 K
        c_ff = (sig * 1.602e-19) ** 2 / (1.380649e-23 * 250.0) * 1e15
        eff = ("VariableKTC", {"capacitance_ff": c_ff, "spread_ln": float(rng.uniform(0.05, 0.5))})
    else:
        eff = ("ShapedReadNoise", {"law": form, "sigma_e": sig})
    return Draw(base, [eff], f"extra read-out noise ({form}), {sig:.3g} e- ({k:.3g} x the read noise)", t,
                accept=("reset_noise",))


def fam_row_noise(rng):
    base = _choice(rng, ["dark", "dark_cmos", "dark_corner"])
    info = base_info(base)
    form = _choice(rng, ["pink", "telegraph", "student"])
    k, t = _loguniform(rng, 0.03, 1.0)
    s = k * info["read_noise_e"]
    if form == "pink":
        eff = ("PinkRowNoise", {"pink_e": s, "white_e": s * float(rng.uniform(0, 1))})
    elif form == "telegraph":
        eff = ("TelegraphRows", {"law": "telegraph", "fraction": float(rng.uniform(0.03, 0.3)), "jump_e": 3 * s,
                                 "white_e": 0.3 * s, "period_rows": 1.0})
    else:
        eff = ("TelegraphRows", {"law": "student", "fraction": 0.0, "jump_e": s, "white_e": 0.0, "period_rows": 1.0})
    return Draw(base, [eff], f"row offsets ({form}), {s:.3g} e- ({k:.3g} x the read noise)", t, accept=("row_noise",))


#: boundaries of drawn gain strips lie at least this many tanh lengths apart (a transition spans ~4 of them from
#: 2 % to 98 %): strips narrower than their transitions are no amplifier layout
GAIN_STRIP_WIDTHS = 6.0


def fam_gain_regions(rng):
    base = _choice(rng, ["flat_full", "flat_imx_bin", "flat", "flat_imx"])
    info = base_info(base)
    n = int(rng.integers(1, 4))
    k, t = _loguniform(rng, 0.05, 5.0)
    dev = k / math.sqrt(info["light_e"])
    gains = [1.0 + dev * float(rng.uniform(0.4, 1.0)) * (-1) ** i for i in range(n + 1)]
    axis = _choice(rng, ["x", "y"])
    splits = sorted(float(v) for v in rng.uniform(0.15, 0.85, n))
    width = float(np.exp(rng.uniform(0, np.log(40))))
    drift = float(rng.uniform(-1, 1) * dev * 0.3)
    # an amplifier's region is far wider than its gain's settling: boundaries at least GAIN_STRIP_WIDTHS
    # transition lengths apart (and a tenth of the window). Splits that break it are drawn again (after the
    # draws above, so that a case that keeps the rule is the case it always was), as many as fit in 0.15-0.85
    small = small_info(base)
    size = small["out_shape"][1 if axis == "x" else 0] * small["bin"]
    gap = max(0.1, GAIN_STRIP_WIDTHS * width / size)
    n = min(n, 1 + int(0.7 / gap))
    for _ in range(1000):
        if len(splits) == n and all(b - a >= gap for a, b in zip(splits[:-1], splits[1:])):
            break
        splits = sorted(float(v) for v in rng.uniform(0.15, 0.85, n))
    gains = gains[:n + 1]
    prm = {"axis": axis, "splits": splits, "gains": gains, "width_px": width, "drift": drift}
    return Draw(base, [("WindowGains", prm)], f"{n + 1} amplifier strips along {prm['axis']}, gains +-{100 * dev:.3g} %, "
                f"transitions {prm['width_px']:.3g} px", t, accept=("gain_regions",))


def fam_cfa(rng):
    base = _choice(rng, ["flat", "flat_imx"])
    dev, t = _loguniform(rng, 0.003, 0.4)
    resp = [float(1 - dev * v) for v in rng.uniform(0, 1, 4)]
    resp[int(rng.integers(4))] = 1.0
    cell = int(_choice(rng, [1, 1, 2]))
    # the responses' drift across the columns (a filter's thickness gradient) is the form's secondary feature:
    # a fraction of the mosaic's own contrast (a 2 % drift under a 0.1 % mosaic is a response gradient, not a
    # mosaic: the label would be wrong), as the gain strips' drift is of theirs
    prm = {"cell": cell, "response": resp, "column_drift": float(rng.uniform(-1, 1) * dev * 0.3)}
    return Draw(base, [("QuadBayer", prm)], f"CFA of {2 * cell}x{2 * cell} cells, responses "
                f"{'/'.join(f'{r:.3f}' for r in resp)}", t, accept=("cfa",), light_scale=float(np.mean(resp)))


def fam_nonlinearity(rng):
    base = _choice(rng, ["stars", "stars_bright", "stars_imx"])
    loss, t = _loguniform(rng, 0.002, 0.12)
    law = _choice(rng, ["knee", "gamma", "poly", "tanh"])
    prm = nl_params(law, loss, rng)
    return Draw(base, [("RandomNonlinearity", {"law": law, "prm": prm})],
                f"{law} non-linearity, {100 * loss:.3g} % compression at full well", t, accept=("nonlinearity",))


def fam_cti(rng):
    base = _choice(rng, ["stars", "stars_bright"])
    direction = _choice(rng, ["parallel", "serial"])
    total, t = _loguniform(rng, 0.01, 0.5)
    law = _choice(rng, ["exp", "power"])
    if law == "exp":
        taus, dens = [float(np.exp(rng.uniform(0, np.log(40))))], [total]
    else:
        taus = [1.0, 3.0, 10.0, 30.0, 100.0]
        w = np.array(taus) ** -float(rng.uniform(0.2, 1.2))
        dens = [float(total * v / w.sum()) for v in w]
    prm = {"direction": direction, "release_transfers": taus, "densities": dens, "beta": float(rng.uniform(0.3, 1.0)),
           "capture": float(rng.uniform(0.3, 1.0))}
    return Draw(base, [("RandomCTI", prm)], f"{direction} CTI, {law} trail, {total:.3g} traps/px, beta {prm['beta']:.2f}",
                t, accept=("cti",))


def fam_blooming(rng):
    base = _choice(rng, ["stars", "stars_bright"])
    thr, t = _loguniform(rng, 0.7, 0.999)
    t = 1 - t  # a lower threshold bleeds more
    soft = bool(rng.random() < 0.4)
    prm = {"threshold": thr, "drain": float(rng.uniform(0, 0.5)), "side": float(rng.uniform(0, 0.3)),
           "up_fraction": float(rng.uniform(0.1, 0.9)), "soft": soft, "length_px": float(rng.uniform(1.5, 8))}
    return Draw(base, [("RandomBleed", prm)], f"{'soft ' if soft else ''}bleed above {thr:.3f} FW, drain "
                f"{prm['drain']:.2f}, sideways {prm['side']:.2f}", t, accept=("blooming",))


def fam_crosstalk(rng):
    base = _choice(rng, ["stars", "stars_imx", "stars_bright"])
    a, t = _loguniform(rng, 2e-4, 5e-3)
    prm = {"n_channels": int(rng.integers(2, 5)), "alpha": a * float(_choice(rng, [1, 1, -1])),
           "delay_px": int(rng.integers(0, 4)), "mirrored": bool(rng.random() < 0.5)}
    return Draw(base, [("DelayedCrosstalk", prm)], f"{prm['n_channels']} channels, coupling {prm['alpha']:.2g}, delay "
                f"{prm['delay_px']} px{', mirrored' if prm['mirrored'] else ''}", t, accept=("crosstalk",))


def fam_ipc(rng):
    base = _choice(rng, ["stars_imx_sharp", "stars_imx_sharp", "stars_imx", "stars"])
    a, t = _loguniform(rng, 1e-3, 2.5e-2)
    asym = float(rng.uniform(0, 0.6))
    v = a * (1 + asym * rng.uniform(-1, 1, 4))
    prm = {"left": float(v[0]), "right": float(v[1]), "up": float(v[2]), "down": float(v[3]),
           "diag": float(a * rng.uniform(0, 0.15))}
    return Draw(base, [("RandomIPC", prm)], f"IPC {100 * a:.3g} % (asymmetry {asym:.2f})", t, accept=("ipc",))


#: the largest pixel-area change at full well a drawn brighter-fatter sensor may have, ``|a_00| x full well``:
#: the thickest deep-depleted CCDs measured reach ~0.16-0.2 (the plugin's GalSim-matched LSST ITL default,
#: a_00 = -1.6e-6 /e- at 100 ke-; the e2v 250 flats of Astier et al. 2019, A&A 629, A36), about twice that
#: leaves room for a strong draw. Above it a "sensor" moves a saturated star's charge pixels away (a_00 x full
#: well of -45 was drawn: 45 times a pixel's own area, the stars then fitted 20x fainter)
BF_MAX_AREA_CHANGE = 0.3


def potential_area_coefficients(k: np.ndarray, c: float) -> np.ndarray:
    """The area coefficients ``a_ij = c Laplacian(k)`` of a potential ``k`` [per e-], on the kernel's support
    plus one pixel (the Laplacian of the truncated kernel reaches one pixel beyond it): Antilogus et al. 2014,
    JINST 9, C03048; centre ``a_00``."""
    p = np.pad(np.asarray(k, float), 2)
    return c * (p[2:, 1:-1] + p[:-2, 1:-1] + p[1:-1, 2:] + p[1:-1, :-2] - 4 * p[1:-1, 1:-1])


def bf_physical(a: np.ndarray) -> bool:
    """Whether area coefficients ``a`` (:func:`potential_area_coefficients`, centred) are a real sensor's: the
    four nearest positive, every other one but ``a_00`` positive or zero and no larger than the smaller nearest
    one (measured coefficients are positive and fall with the distance: Astier et al. 2019, their Fig. 11). A
    smooth potential truncated at its support breaks this (the Laplacian of the step at its edge exceeds the one
    at one pixel), as does a potential flat at one pixel (a negative a_11 or a_01)."""
    h = a.shape[0] // 2
    near = min(a[h, h + 1], a[h + 1, h])
    far = a.copy()
    far[h, h] = 0
    far[h, h - 1:h + 2] = far[h - 1:h + 2, h] = 0
    return bool(near > 0 and far.min() >= 0 and far.max() <= near)


def fam_brighter_fatter(rng):
    base = _choice(rng, ["stars", "stars_bright", "stars_imx"])
    lo, hi0 = 1.5e-7, 3e-6
    a10, t = _loguniform(rng, lo, hi0)
    full_well = PRESETS[BASES[base]["detector"]["preset"]]["full_well_e"]
    for _ in range(200):
        law = _choice(rng, ["exp", "gauss", "power", "coulomb"])
        scale = {"exp": lambda: rng.uniform(0.4, 1.5), "gauss": lambda: rng.uniform(0.45, 0.7),
                 "power": lambda: rng.uniform(1.0, 4.0), "coulomb": lambda: rng.uniform(0.3, 1.0)}[law]()
        prm = {"law": law, "half": int(rng.integers(2, 5)), "scale": float(scale), "aniso": float(rng.uniform(0.75, 1.35)),
               "a10_per_e": a10, "q_nl_frac": float(rng.uniform(0.3, 1.0)) if rng.random() < 0.3 else 0.0}
        k = bf_kernel(prm["law"], prm["half"], prm["scale"], prm["aniso"])
        a = potential_area_coefficients(k, 1.0)
        lap10 = a[a.shape[0] // 2, a.shape[0] // 2 + 1]
        if lap10 <= 0:
            continue
        a /= lap10  # per unit a_10
        # the range's top where the pixel-area change at full well reaches BF_MAX_AREA_CHANGE (a coupling that
        # grows with the charge counted at full well: 1 + 1 / q_nl_frac); the strength t keeps its place
        growth = 1 + 1 / prm["q_nl_frac"] if prm["q_nl_frac"] else 1.0
        hi = min(hi0, BF_MAX_AREA_CHANGE / (abs(a[a.shape[0] // 2, a.shape[0] // 2]) * full_well * growth))
        if bf_physical(a) and hi > 2 * lo:
            break
    else:
        raise RuntimeError("no physical brighter-fatter potential in 200 draws")
    prm["a10_per_e"] = a10 = float(lo * (hi / lo) ** t)
    return Draw(base, [("RandomBF", prm)], f"brighter-fatter, {law} potential over {2 * prm['half'] + 1}^2 px, a_10 "
                f"{a10:.2g} /e-", t, accept=("brighter_fatter",))


def _blur_draw(rng, elongated):
    base = _choice(rng, ["stars", "stars_imx", "stars_bright", "stars_imx_sharp"])
    size, t = _loguniform(rng, 0.15, 1.5)
    law = _choice(rng, ["gauss", "moffat", "exp", "wing"])
    q = float(rng.uniform(0.3, 0.65)) if elongated else float(rng.uniform(0.85, 1.0))
    prm = {"law": law, "size_px": size, "q": q, "theta": float(rng.uniform(0, np.pi)),
           "beta": float(rng.uniform(1.8, 5.0)), "wing": float(rng.uniform(0.05, 0.4))}
    if law == "wing":
        prm["size_px"] = size * 4
    accept = ("psf_elongation", "jitter", "psf_blur") if elongated else ("psf_blur",)
    # a near-round kernel's elongation (its covariance's anisotropic part) is a psf_elongation of its own: its
    # names are right too when the frame sees it, against the round kernel of the same covariance trace
    parts = () if elongated else ((("psf_elongation", "jitter"), [("KernelBlur", round_kernel(prm))]),)
    return Draw(base, [("KernelBlur", prm)], f"{law} blur of {prm['size_px']:.3g} px, axis ratio {q:.2f}", t,
                accept=accept, parts=parts)


def round_kernel(prm: dict) -> dict:
    """The round kernel of :func:`blur_transfer`'s law with the same covariance trace as ``prm``'s (the profile is
    stretched by ``size`` along the major axis and ``q size`` across: its covariance ``size^2 diag(1, q^2)``
    times the law's own)."""
    return {**prm, "q": 1.0, "size_px": prm["size_px"] * math.sqrt((1 + prm["q"] ** 2) / 2)}


def fam_psf_blur(rng):
    return _blur_draw(rng, False)


def fam_psf_elongation(rng):
    return _blur_draw(rng, True)


#: the longest image motion [output px] the draws label a smear rather than a trail: a box this short has an rms of
#: 0.43 px (L / sqrt(12)), ~1.5 times the pixel's own box (1 / sqrt(12) px), so its profile across the pixel
#: grid is the pixel's and the PSF's, and only its second moments (an elongation) are measured; its transfer
#: function sinc(pi f L) departs from the Gaussian of its variance by (pi f L)^4 / 180, 0.17 at the Nyquist
#: frequency. A label of what one frame tells, not a threshold of the judge (whose drift, jitter and elongation
#: are told apart by the nested test of their fits, frame by frame): its value is the one the development draws
#: were labelled with (the judge's former DRIFT_MIN_LENGTH), so the accepted names of a case do not change
SMEAR_MAX_TRAIL_PX = 1.5


def fam_jitter(rng):
    base = _choice(rng, ["stars", "stars_imx", "stars_bright"])
    law = _choice(rng, ["sine", "walk"])
    amp, t = _loguniform(rng, 0.2, 2.5) if law == "sine" else _loguniform(rng, 0.03, 0.25)
    prm = {"law": law, "amp_px": amp, "angle_deg": float(rng.uniform(0, 180)), "seed": int(rng.integers(2 ** 31))}
    accept = ("jitter", "psf_elongation") + (("psf_blur",) if law == "walk" else ())
    # a walk that wanders as far as SMEAR_MAX_TRAIL_PX is a drifting pointing (a path); a walk that stays shorter,
    # or an oscillation sweeping a chord (2 amp) shorter, is a smear no shape test separates from image motion of
    # another law, a drift among them (the rule of fam_pointing_drift, both ways). A longer oscillation has the
    # arcsine profile of a sine, which a drift's box does not
    if law == "walk" or 2 * amp < SMEAR_MAX_TRAIL_PX:
        accept += ("pointing_drift",)
    return Draw(base, [("MotionPath", prm)], f"{law} image motion, {amp:.3g} px", t, accept=accept)


def fam_pointing_drift(rng):
    base = _choice(rng, ["stars", "stars_imx", "stars_bright"])
    law = _choice(rng, ["accel", "arc"])
    length, t = _loguniform(rng, 0.5, 8.0)
    a = float(rng.uniform(0, 2 * np.pi))
    prm = {"law": law, "dx": length * math.cos(a), "dy": length * math.sin(a), "amp_px": length,
           "sag_px": length * float(rng.uniform(0.05, 0.3)), "angle_deg": math.degrees(a)}
    # a trail shorter than SMEAR_MAX_TRAIL_PX is a smear no shape test separates from image motion of another law
    # (a box of 1.5 px has the rms of a 0.43 px jitter): an image-motion name is right for it
    accept = ("pointing_drift",) + (("jitter", "psf_elongation") if length < SMEAR_MAX_TRAIL_PX else ())
    return Draw(base, [("MotionPath", prm)], f"{law} drift of {length:.3g} px", t, accept=accept)


def fam_pointing_offset(rng):
    base = _choice(rng, ["stars", "stars_imx", "stars_bright"])
    r, t = _loguniform(rng, 0.03, 1.0)
    a = float(rng.uniform(0, 2 * np.pi))
    prm = {"dx": r * math.cos(a), "dy": r * math.sin(a), "rot_deg": float(rng.uniform(-0.02, 0.02)),
           "scale": float(rng.uniform(-2e-4, 2e-4))}
    return Draw(base, [("AffineOffset", prm)], f"offset {r:.3g} px with rotation {prm['rot_deg']:.3g} deg and scale "
                f"{prm['scale']:.2g}", t, accept=("pointing_offset",))


def fam_distortion(rng):
    base = _choice(rng, ["stars", "stars_imx", "stars_bright"])
    law = _choice(rng, ["tangential", "r5"])
    corner, t = _loguniform(rng, 0.03, 0.8)  # the displacement at the window corner [px]
    rc = 362.0
    if law == "tangential":
        a = float(rng.uniform(0, 2 * np.pi))
        p = corner / (3 * rc * rc)
        prm = {"law": law, "p1": p * math.cos(a), "p2": p * math.sin(a), "k2": 0.0}
    else:
        prm = {"law": law, "p1": 0.0, "p2": 0.0, "k2": float(_choice(rng, [1, -1])) * corner / rc ** 5}
    return Draw(base, [("BrownDistortion", prm)], f"{law} distortion, {corner:.3g} px at the corners", t,
                accept=("distortion",))


#: the largest offset of a drawn ghost [fraction of the window's side]: a shift by d (a mirror through a point d
#: from the centre moves the image by 2 d) leaves at least 1 - 2 GHOST_MAX_OFFSET of the window's sources' ghosts
#: in it. The frame holds only its window's sources, so a ghost that falls outside it is no case (offsets of
#: +-120 px, drawn for 512 px windows, left 0-6 % of the ghosts of a mirror in the 256 px windows: truth chi2 0)
GHOST_MAX_OFFSET = 0.23


def fam_ghost(rng):
    base = _choice(rng, ["stars", "stars_imx", "stars_bright"])
    # from a stray reflection of AR-coated surfaces (1e-3 of the flux) to a sensor's cover-glass ghost of a few per
    # cent: spread over 3-15 px about the faint stars of these windows, 1e-2 was the draws' strongest and left a
    # truth chi2 of at most ~50 (12 draws), no strong case; "from strong to near the threshold" needs the few %
    alpha, t = _loguniform(rng, 1e-3, 5e-2)
    r_out = float(rng.uniform(3, 15))
    side = min(small_info(base)["out_shape"])
    prm = {"geometry": _choice(rng, ["shift", "mirror"]), "dx": float(rng.uniform(-1, 1) * GHOST_MAX_OFFSET * side),
           "dy": float(rng.uniform(-1, 1) * GHOST_MAX_OFFSET * side), "shape": _choice(rng, ["annulus", "gauss"]),
           "r_in": r_out * float(rng.uniform(0.3, 0.7)), "r_out": r_out, "alpha": alpha}
    return Draw(base, [("ShiftedGhost", prm)], f"{prm['geometry']} ghost ({prm['shape']} {r_out:.3g} px), {alpha:.2g} "
                "of the flux", t, accept=("ghost",))


def fam_periodic(rng):
    """Out of the catalogue: a periodic pattern; the answer must be a description of the right kind."""
    role = _choice(rng, ["response", "dark", "bias", "light"])
    base = _choice(rng, {"response": ["flat", "flat_imx", "flat_full"], "dark": ["dark", "dark_corner"],
                         "bias": ["bias_full", "bias_imx"], "light": ["stars", "stars_imx"]}[role])
    info = base_info(base)
    waveform = _choice(rng, ["sine", "sine", "square", "triangle", "rings"])
    # at least 8 periods across the small window (a pattern, not a smooth field)
    out_shape = base_info(f"{base}_s" if f"{base}_s" in BASES else base)["out_shape"]
    period_out = float(np.exp(rng.uniform(np.log(3.0), np.log(min(out_shape) / 8))))
    b = info["bin"]
    h, w = (n * b for n in out_shape)
    angle = float(_choice(rng, [0.0, np.pi / 2, float(rng.uniform(0, np.pi))]))
    k, t = _loguniform(rng, 0.05, 5.0)
    e = k * info["noise_e"]
    if role == "response":
        amp = e / info["light_e"]
    elif role == "bias":
        amp = e / info["gain"] / (b * b if info["cmos"] else 1)
    else:
        amp = _per_s_per_px(info, e) / 2
    prm = {"waveform": waveform, "period_px": period_out * b, "angle": angle,
           "phase": float(rng.uniform(0, 2 * np.pi)), "amp": amp, "window": [w, h],
           "cu": float(rng.uniform(-1.5, 2.5)), "cv": float(_choice(rng, [-1.0, 2.0]) * rng.uniform(1.0, 1.5))}
    geometry = ["periodic"]
    if waveform == "rings":
        geometry += ["rings", "radial"]
    elif abs(math.cos(angle)) > 0.97:
        geometry.append("columns")
    elif abs(math.sin(angle)) > 0.97:
        geometry.append("rows")
    kind = "multiplicative" if role == "response" else "additive"
    cls = {"response": "PeriodicPattern", "dark": "PeriodicDark", "bias": "PeriodicBias", "light": "PeriodicLight"}[role]
    return Draw(base, [(cls, prm)], f"periodic {waveform} ({role}), period {period_out:.3g} px, angle "
                f"{math.degrees(angle):.0f} deg, {k:.3g} sigma", t, kind=kind, geometry=tuple(geometry))


# out of the catalogue: forms no plugin models, whose answer must be a description of the right kind. Not drawn,
# because one frame cannot tell them from a catalogue effect (a series can): a bias drifting during the read-out,
# a bias structure along the rows in one frame (the hidden-effect suite classes a bias step as bias_gradient for
# that reason); a persistent image of a dithered field, a shifted copy of the sources as sharp as the ghosts the
# ghost family draws (3-15 px)

def fam_smear(rng):
    """Out of the catalogue: light collected while a CCD's rows are shifted out with the shutter open (every
    pixel gets a share of its column's light, :class:`.unseen.ReadoutSmear`); a CMOS read by rows does not smear."""
    base = _choice(rng, ["stars", "stars_bright"])
    rows = base_info(f"{base}_s")["out_shape"][0]
    total, t = _loguniform(rng, 3e-4, 0.1)  # the share of each source's light spread along its column
    return Draw(base, [("ReadoutSmear", {"frac_per_row": total / rows})], f"read-out smear, {100 * total:.2g} % of "
                "each source along its column", t, kind="additive", geometry=("columns", "sources"))


def fam_trail(rng):
    """Out of the catalogue: an unmodelled satellite trail across the window (:class:`.unseen.SatelliteTrail`)."""
    base = _choice(rng, ["stars", "stars_imx", "stars_bright"])
    info = base_info(base)
    k, t = _loguniform(rng, 0.3, 30.0)
    sigma = float(rng.uniform(0.8, 3.0))
    u0, u1 = sorted(float(v) for v in rng.uniform(0, 1, 2))
    prm = {"u0": u0, "v0": float(rng.uniform(0, 1)), "u1": u1, "v1": float(rng.uniform(0, 1)),
           "e_per_px": k * info["noise_e"] * math.sqrt(2 * math.pi) * sigma, "sigma_px": sigma}
    return Draw(base, [("SatelliteTrail", prm)], f"satellite trail, {k:.3g} sigma at its centre, {sigma:.2g} px wide",
                t, kind="additive", geometry=("local", "streak"))


def fam_tree_rings(rng):
    """Out of the catalogue: tree rings of a CCD's silicon, arcs about a point off the sensor
    (:class:`.unseen.TreeRings`)."""
    base = _choice(rng, ["flat", "flat_full"])
    amp, t = _loguniform(rng, 3e-4, 1e-2)
    # at least 4 periods across the small window (rings, not a smooth field), at least 4 output pixels each
    small = small_info(base)
    lo, hi = 4.0 * small["bin"], min(small["out_shape"]) * small["bin"] / 4.0
    prm = {"amp": amp, "period_px": float(np.exp(rng.uniform(np.log(lo), np.log(hi)))),
           "cu": float(_choice(rng, [rng.uniform(-1.0, -0.3), rng.uniform(1.3, 2.0)])),
           "cv": float(rng.uniform(-1.0, 2.0))}
    # arcs about a point far off the window are near-straight stripes across it: seen along the columns (rows)
    # when the point lies along x (y) from the sensor's middle, within the periodic family's 0.97 of the axis
    info = base_info(base)
    h, w = (n * info["bin"] for n in info["out_shape"])
    dx, dy = (prm["cu"] - 0.5) * w, (prm["cv"] - 0.5) * h
    geometry = ["rings", "periodic", "radial"]
    if abs(dx) > 0.97 * math.hypot(dx, dy):
        geometry.append("columns")
    elif abs(dy) > 0.97 * math.hypot(dx, dy):
        geometry.append("rows")
    return Draw(base, [("TreeRings", prm)], f"tree rings, {100 * amp:.2g} % with a period of {prm['period_px']:.0f} px "
                f"about ({prm['cu']:.2g}, {prm['cv']:.2g})", t, kind="multiplicative", geometry=tuple(geometry))


#: family -> (catalogue effect (the confusion matrix's row; None out of the catalogue), drawer)
FAMILIES: dict[str, tuple] = {
    "vignetting": ("vignetting", fam_vignetting), "straylight": ("straylight", fam_straylight),
    "sky_gradient": ("sky_gradient", fam_sky_gradient), "dark_gradient": ("dark_gradient", fam_dark_gradient),
    "amp_glow": ("amp_glow", fam_amp_glow), "bias_gradient": ("bias_gradient", fam_bias_gradient),
    "prnu": ("prnu", fam_prnu), "dsnu": ("dsnu", fam_dsnu), "hot_pixels": ("hot_pixels", fam_hot_pixels),
    "dead_pixels": ("dead_pixels", fam_dead_pixels), "column_defects": ("column_defects", fam_column_defects),
    "cosmic_rays": ("cosmic_rays", fam_cosmic_rays), "rts_noise": ("rts_noise", fam_rts_noise),
    "reset_noise": ("reset_noise", fam_reset_noise), "row_noise": ("row_noise", fam_row_noise),
    "gain_regions": ("gain_regions", fam_gain_regions), "cfa": ("cfa", fam_cfa),
    "nonlinearity": ("nonlinearity", fam_nonlinearity), "cti": ("cti", fam_cti), "blooming": ("blooming", fam_blooming),
    "crosstalk": ("crosstalk", fam_crosstalk), "ipc": ("ipc", fam_ipc),
    "brighter_fatter": ("brighter_fatter", fam_brighter_fatter), "psf_blur": ("psf_blur", fam_psf_blur),
    "psf_elongation": ("psf_elongation", fam_psf_elongation), "jitter": ("jitter", fam_jitter),
    "pointing_drift": ("pointing_drift", fam_pointing_drift), "pointing_offset": ("pointing_offset", fam_pointing_offset),
    "distortion": ("distortion", fam_distortion), "ghost": ("ghost", fam_ghost),
    "periodic": (None, fam_periodic), "smear": (None, fam_smear), "trail": (None, fam_trail),
    "tree_rings": (None, fam_tree_rings),
}

#: the classes a drawn effect names (this module's, :mod:`.unseen`'s and :mod:`.hidden`'s real-world effects)
CLASSES = {n: c for n, c in {**HE, **vars(U), **globals()}.items()
           if isinstance(c, type) and issubclass(c, RealWorld) and c is not RealWorld}


def real_world(effects: list, sensor) -> list:
    """The real-world effects of a draw's ``[(class name, parameters)]`` on ``sensor``."""
    return [CLASSES[cls](sensor, **prm) for cls, prm in effects]


@dataclass
class RandomCase:
    """One drawn case: rebuilt from (``family``, ``case_seed``) alone."""

    family: str
    case_seed: int
    draw: Draw
    levels: Levels = field(default_factory=Levels)

    @property
    def name(self) -> str:
        return f"{self.family}-{self.case_seed}"

    @property
    def effect(self) -> str | None:
        return FAMILIES[self.family][0]

    @property
    def camera(self) -> str:
        return BASES[self.draw.base]["detector"]["preset"]

    @property
    def frame_seed(self) -> int:
        return int(self.case_seed % 2_147_483_647)

    def make(self, sensor):
        return real_world(self.draw.effects, sensor)

    @property
    def accept(self) -> tuple:
        """The draw's accepted names, and the flat's level when the drawn effect with the case's light level
        moves the frame's mean light beyond what a scene may be off (the policy's
        ``parameter_scale_tolerance``): a refitted level far from 1 is a finding the judge names first, as a
        scene parameter (issue 23), and the drawn effect after it."""
        d = self.draw
        scale = d.light_scale * (1 + self.levels.light)
        beyond = d.light_scale != 1.0 and abs(scale - 1) > DEFAULT_POLICY.parameter_scale_tolerance
        flat = bool(BASES[d.base]["sky"].get("flat_e_per_s"))  # the light is a flat screen's (sky.flat_e_per_s)
        return tuple(d.accept) + (("flat_level",) if beyond and flat else ())

    def record(self) -> dict:
        d = self.draw
        return {"case": self.name, "family": self.family, "case_seed": self.case_seed, "effect": self.effect,
                "base": d.base, "camera": self.camera, "description": d.description, "strength_t": d.strength,
                "accept": list(self.accept), "kind": d.kind, "geometry": list(d.geometry),
                "effects": [[c, _jsonable(p)] for c, p in d.effects], "levels": vars(self.levels)}

    def unseen_case(self):
        """The case as :mod:`.unseen` runs it (catalogue: ``accept``; out of the catalogue: kind, geometry)."""
        d = self.draw
        return U.UnseenCase(self.name, d.base, d.description, self.make, accept=self.accept, effect=self.effect,
                            strength="strong" if d.strength >= 0.5 else "weak", kind=d.kind, geometry=d.geometry,
                            levels=self.levels)


def _jsonable(v):
    if isinstance(v, dict):
        return {k: _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, np.generic):
        return v.item()
    return v


def draw_case(family: str, case_seed: int) -> RandomCase:
    """The case of ``family`` drawn from ``case_seed`` (every number of the case comes from this seed), on the
    small form of its base scene (:data:`SMALL`) unless the family needs the full size (the families that size
    their effect physically, by the window's area or its share of the sensor, use the small form's numbers:
    :func:`small_info`)."""
    if family not in FAMILIES:
        raise KeyError(f"family {family!r}: expected one of {', '.join(FAMILIES)}")
    rng = np.random.default_rng([case_seed, 23])
    d = FAMILIES[family][1](rng)
    if family not in FULL_SIZE_FAMILIES:
        d.base = f"{d.base}_s"
    return RandomCase(family, int(case_seed), d, draw_levels(rng))


def draw_levels(rng) -> Levels:
    """The global levels a case's measured frame has off the model's: the light 1-1.5 % one way, the dark 2-3 %
    the other, the bias 0.3-0.6 ADU either way (what a model of a real camera has wrong)."""
    sgn = float(_choice(rng, [-1.0, 1.0]))
    return Levels(light=sgn * float(rng.uniform(0.010, 0.015)), dark=-sgn * float(rng.uniform(0.02, 0.03)),
                  bias_adu=float(_choice(rng, [-1.0, 1.0])) * float(rng.uniform(0.3, 0.6)))


def draw_cases(master_seed: int, n: int, families=None) -> list[RandomCase]:
    """``n`` cases from ``master_seed``: the families in a random order, cycled (each about n / len equally
    often), each case with its own seed spawned from the master's (:class:`numpy.random.SeedSequence`)."""
    fams = list(families or FAMILIES)
    ss = np.random.SeedSequence(master_seed)
    rng = np.random.default_rng(ss.spawn(1)[0])
    order = [fams[i] for i in rng.permutation(len(fams))]
    seeds = [int(c.generate_state(1, np.uint64)[0] >> np.uint64(2)) for c in ss.spawn(n + 1)[1:]]
    return [draw_case(order[i % len(order)], seeds[i]) for i in range(n)]


def fresh_seed() -> int:
    """A master seed nobody has used: 62 bits from ``os.urandom`` mixed with the clock."""
    return (int.from_bytes(os.urandom(8), "little") ^ time.time_ns()) & ((1 << 62) - 1)


# --- running ------------------------------------------------------------------------------------------------------

#: the bases the outlier-count families (:data:`.unseen.STATISTICAL`) draw their cases on
NULL_MISFIT_BASES = ("dark_s", "dark_cmos_s", "dark_corner_s", "flat_s", "flat_imx_s")


def misfit_null(n_per_base: int, seed: int, workdir: Path, progress=None) -> list[dict]:
    """The profiled misfit and chi2/dof - 1 (:func:`error_of`) of null frames: each base of
    :data:`NULL_MISFIT_BASES` rendered ``n_per_base`` times with a random case's level offsets (light, dark,
    bias: :func:`draw_levels`) and nothing hidden, compared with
    its model scene. ``progress(i, n)`` after each frame."""
    from scenes.app.compare import run_compare
    from scenes.scene import load_scene

    rng = np.random.default_rng(seed)
    rows, n = [], n_per_base * len(NULL_MISFIT_BASES)
    workdir.mkdir(parents=True, exist_ok=True)
    for base in NULL_MISFIT_BASES:
        model = HE["write_scene"](HE["model_scene"](base, None), workdir / f"{base}.model.toml")
        for _ in range(n_per_base):
            frame_seed = int(rng.integers(1, 2**31 - 1))
            info = HE["make_frame"](base, None, draw_levels(rng), workdir / f"{base}.fits", seed=frame_seed, workers=1)
            e = HE["error_of"](run_compare(load_scene(str(model)), info["measured"], workers=1), None)
            rows.append({"base": base, "frame_seed": frame_seed, "misfit": e["misfit"],
                         "chi2_minus_1": e["chi2_minus_1"], "n_support": e["n_support"]})
            if progress is not None:
                progress(len(rows), n)
    return rows


def run_case(case: RandomCase, workdir: Path, workers: int | None = None) -> dict:
    """Make the measured frame of ``case`` and diagnose it as :func:`.unseen.diagnose_case` does."""
    workdir.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    uc = case.unseen_case()
    parts, seen = {}, ()
    for i, (names, alt) in enumerate(case.draw.parts):
        parts[" ".join(names)] = chi2 = part_seen(case, alt, workdir / f"{case.name}.part{i}.toml", workers)
        seen += tuple(names) if chi2 >= SEEN_CHI2 else ()
    uc = replace(uc, accept=tuple(uc.accept) + seen)
    model = HE["write_scene"](HE["model_scene"](uc.base, uc.effect), workdir / f"{case.name}.model.toml")
    info = HE["make_frame"](uc.base, uc.make, uc.levels, workdir / f"{case.name}.fits", seed=case.frame_seed,
                            workers=workers)
    row = U.diagnose_case(uc, model, Path(info["measured"]), info["support"], workdir, workers=workers,
                          truth_change_adu=info.get("truth_change_adu"))
    row.update(case.record())
    if parts:
        row.update(accept=list(uc.accept), parts_chi2=parts)
    row.update(label=case.effect or f"ooc:{case.family}", truth_chi2=info["truth_chi2"],
               scatter_sigma=info.get("scatter_sigma"),
               case_seconds=round(time.perf_counter() - t0, 1))
    return row


#: a part of a drawn effect is seen when its exact template's chi2 reaches this: the report's bar of what one frame
#: can see at all (DETECTION_SIGMA squared, :func:`_detectability`)
SEEN_CHI2 = DETECTION_SIGMA ** 2


def part_seen(case: RandomCase, without: list, out: Path, workers: int | None = None) -> float:
    """The chi2 of a part of ``case``'s drawn effect (:attr:`Draw.parts`): the expected frames with the drawn
    effects and with ``without`` (the draw less that part) apart, on the case's base and levels."""
    return HE["change_chi2"](case.draw.base, case.levels, case.make, lambda sensor: real_world(without, sensor),
                             out, workers=workers)


def _run_one(args):
    family, case_seed, workdir, workers = args
    case = draw_case(family, case_seed)
    try:
        return run_case(case, Path(workdir), workers=workers)
    except Exception as exc:  # noqa: BLE001 - a case that fails is reported, the others go on
        import traceback

        return {**case.record(), "group": "catalogue" if case.effect else "ooc", "label": case.effect or
                f"ooc:{family}", "first": "error", "error": f"{type(exc).__name__}: {exc}",
                "traceback": traceback.format_exc()[-2000:], "confidently_wrong": False}


def run_cases(cases: list[RandomCase], workdir: Path, workers: int = 2, progress=None) -> list[dict]:
    """Every case, ``workers`` processes at a time (each renders and diagnoses on one thread)."""
    jobs = [(c.family, c.case_seed, str(workdir / c.name), 1 if workers > 1 else None) for c in cases]
    if workers <= 1:
        rows = []
        for j in jobs:
            rows.append(_run_one(j))
            if progress:
                progress(rows[-1])
        return rows
    rows = {}
    with ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("fork")) as pool:
        futs = {pool.submit(_run_one, j): f"{j[0]}-{j[1]}" for j in jobs}
        for f in as_completed(futs):
            rows[futs[f]] = f.result()
            if progress:
                progress(rows[futs[f]])
    return [rows[c.name] for c in cases]


# --- the report -----------------------------------------------------------------------------------------------------

def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """The Wilson score interval of a proportion k / n (95 % for z = 1.96; Wilson 1927, JASA 22, 209)."""
    if n == 0:
        return (float("nan"), float("nan"))
    p = k / n
    den = 1 + z * z / n
    c = (p + z * z / (2 * n)) / den
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return (max(0.0, c - h), min(1.0, c + h))


def _frac(rows, pred) -> dict:
    k = sum(bool(pred(r)) for r in rows)
    lo, hi = wilson(k, len(rows))
    return {"n": k, "of": len(rows), "rate": k / len(rows) if rows else float("nan"), "lo": lo, "hi": hi}


def _figures(rows: list[dict]) -> dict:
    ok = [r for r in rows if r.get("first") != "error"]
    cat = [r for r in ok if r.get("group") == "catalogue"]
    ooc = [r for r in ok if r.get("group") == "ooc"]
    seen = [r for r in cat if _detectability(r) not in UNSEEN]
    return {"named_first": _frac(cat, lambda r: r.get("named_first")),
            # the cases one frame can see at all (an exact template's chi2 >= 25, a pattern drawn per pixel at
            # DETECTION_SIGMA without its map) or whose effect is a noise: "from strong to near the threshold", without the draws
            # below any threshold
            "named_first_seen": _frac(seen, lambda r: r.get("named_first")),
            # the same, with the template's chi2 left once the frame's global levels took what they can of it on
            # the pixels the diagnosis fits (.hidden.truth_chi2_after_levels; rows without it count as before)
            "named_first_seen_levels": _frac([r for r in cat if _detectability(r, after_levels=True) not in UNSEEN],
                                              lambda r: r.get("named_first")),
            "confidently_wrong": _frac(cat + ooc, lambda r: r.get("confidently_wrong")),
            "confidently_wrong_strict": _frac(cat, lambda r: r.get("confidently_wrong_strict")),
            "ambiguous_right": _frac(cat, lambda r: r.get("cannot_tell_apart") and not r.get("named_first")
                                     and set(r["cannot_tell_apart"]) & set(r.get("accept", []))),
            "missed": _frac(cat, lambda r: r.get("first") == "none"),
            "described_right_kind": _frac(ooc, lambda r: r.get("morphology_match")),
            # the same on the forms one frame can see once its global levels took what they can (a read-out smear
            # under a bright sky is mostly a uniform light: 0.73 % of each column's light left a chi2 of 26)
            "described_seen_levels": _frac([r for r in ooc if _detectability(r, after_levels=True) not in UNSEEN],
                                           lambda r: r.get("morphology_match")),
            "error_halved": _frac(cat + ooc, U.error_halved),
            "errors": len(rows) - len(ok)}


#: the detectability classes below any single-frame threshold: an exact template's chi2 under 25 (DETECTION_SIGMA
#: squared), a pattern drawn per pixel seen by one frame without its map (its large scales as a template, the rest
#: as excess scatter: :func:`.hidden.scatter_sigma`) under DETECTION_SIGMA: its truth chi2 is the exact map's,
#: which one frame does not have
BELOW_TEMPLATE = "truth chi2 < 25"
BELOW_SCATTER = f"pixel pattern, < {DETECTION_SIGMA:g} sigma in one frame"
UNSEEN = (BELOW_TEMPLATE, BELOW_SCATTER)


def _detectability(r, after_levels: bool = False) -> str:
    tc = r.get("truth_chi2")
    if after_levels and r.get("truth_chi2_levels") is not None:
        tc = r["truth_chi2_levels"]
    ss = r.get("scatter_sigma")
    if ss is not None and ss < DETECTION_SIGMA:
        return BELOW_SCATTER
    if tc is None:
        return "noise or scatter (no template chi2)"
    return BELOW_TEMPLATE if tc < SEEN_CHI2 else ("25 <= truth chi2 < 1000" if tc < 1000 else "truth chi2 >= 1000")


def summary(rows: list[dict]) -> dict:
    """Overall figures and per family, camera, strength half and detectability, with Wilson intervals; the
    confusions (hidden -> wrong first name) with an example case each."""
    out = {"overall": _figures(rows)}
    for key, fn in (("family", lambda r: r["family"]), ("camera", lambda r: r["camera"]),
                    ("strength", lambda r: "strong half (t >= 0.5)" if r["strength_t"] >= 0.5 else "weak half"),
                    ("detectability", _detectability)):
        groups: dict = {}
        for r in rows:
            groups.setdefault(fn(r), []).append(r)
        out[f"by_{key}"] = {g: _figures(v) for g, v in sorted(groups.items())}
    conf, examples, missed = Counter(), {}, {}
    for r in rows:
        if r.get("first") == "error":
            continue
        if r.get("group") == "catalogue" and r.get("first") == "none":
            missed.setdefault(r["label"], []).append(r)
            continue
        if r.get("group") == "catalogue" and not r.get("named_first"):
            pair = (r["label"], r["first"] + ("" if r.get("confidently_wrong") else " (ambiguous)"))
        elif r.get("group") == "ooc" and r.get("confidently_wrong"):
            pair = (r["label"], ",".join(e for e, _ in r.get("wrong_names", [])) or r["first"])
        elif r.get("group") == "ooc" and not r.get("morphology_match"):
            mo = r.get("residual_morphology") or {}
            pair = (r["label"], "description: " + (f"{mo.get('kind')} / {mo.get('geometry')}" if mo.get("significant")
                                                   else "nothing significant"))
        else:
            continue
        conf[pair] += 1
        examples.setdefault(pair, r["case"])
    out["confusions"] = [{"hidden": h, "first": f, "count": n, "example": examples[(h, f)]}
                         for (h, f), n in conf.most_common()]
    # the misses, with the most detectable one as the example (a miss of a case no template could find is no news)
    out["missed"] = [{"hidden": h, "count": len(v), "example": max(v, key=lambda r: r.get("truth_chi2") or 0)["case"],
                      "example_truth_chi2": max(v, key=lambda r: r.get("truth_chi2") or 0).get("truth_chi2")}
                     for h, v in sorted(missed.items(), key=lambda kv: -len(kv[1]))]
    out["seconds"] = round(sum(r.get("case_seconds", 0) or 0 for r in rows), 1)
    return out


def _pct(d: dict) -> str:
    if not d["of"]:
        return "-"
    return f"{d['n']}/{d['of']} ({100 * d['rate']:.0f} %, {100 * d['lo']:.0f}-{100 * d['hi']:.0f})"


def markdown(rows: list[dict], summ: dict, meta: dict) -> str:
    o = summ["overall"]
    lines = [f"# Random forms, master seed {meta['seed']} ({meta['n']} cases, {meta['date']}, commit {meta['commit']})",
             "", "Figures with 95 % Wilson intervals.", "", "| metric | value |", "|---|---|",
             f"| named first (catalogue cases) | {_pct(o['named_first'])} |",
             (f"| named first, the catalogue cases one frame can see (an exact template's truth chi2 >= 25, a pattern "
              f"drawn per pixel >= {DETECTION_SIGMA:g} sigma without its map) or noise forms | "
              f"{_pct(o['named_first_seen'])} |"),
             (f"| named first, the same with the template's chi2 after the frame's global levels (on the fitted "
              f"pixels) >= 25 | {_pct(o['named_first_seen_levels'])} |"),
             f"| confidently wrong (catalogue + out-of-catalogue cases) | {_pct(o['confidently_wrong'])} |",
             (f"| wrong first counting the ones flagged as not told apart (catalogue) | "
              f"{_pct(o['confidently_wrong_strict'])} |"),
             f"| first not accepted but flagged as not told apart from an accepted name | {_pct(o['ambiguous_right'])} |",
             f"| catalogue effect missed (nothing significant) | {_pct(o['missed'])} |",
             f"| out of catalogue described with the right kind and geometry | {_pct(o['described_right_kind'])} |",
             (f"| out of catalogue described, the forms one frame can see after its global levels (truth chi2 >= 25) "
              f"| {_pct(o['described_seen_levels'])} |"),
             f"| error halved after one --apply | {_pct(o['error_halved'])} |",
             f"| cases that raised | {o['errors']} |", ""]
    for key, title in (("by_camera", "camera"), ("by_strength", "strength"), ("by_detectability", "detectability"),
                       ("by_family", "family")):
        lines += [f"## By {title}", "", (f"| {title} | named first | confidently wrong | missed | described (ooc) | "
                                          "error halved |"), "|---|---|---|---|---|---|"]
        for g, f in summ[key].items():
            lines.append(f"| {g} | {_pct(f['named_first'])} | {_pct(f['confidently_wrong'])} | {_pct(f['missed'])} | "
                         f"{_pct(f['described_right_kind'])} | {_pct(f['error_halved'])} |")
        lines.append("")
    lines += [("## Confusions (hidden -> first significant plausible name, or the description of an out-of-catalogue "
               "form that did not match), most frequent first"), "",
              "Rerun one with `python examples/diagnose/random_forms.py OUT --case FAMILY-CASE_SEED`.", "",
              "| hidden | first | count | example case |", "|---|---|---|---|"]
    lines += [f"| {c['hidden']} | {c['first']} | {c['count']} | `{c['example']}` |" for c in summ["confusions"]]
    lines += ["", "## Missed (a catalogue case with nothing significant), the most detectable one as the example", "",
              "| hidden | count | example case | its truth chi2 |", "|---|---|---|---|"]
    lines += [f"| {m['hidden']} | {m['count']} | `{m['example']}` | {U._f(m['example_truth_chi2'])} |"
              for m in summ["missed"]]
    lines += ["", "## Cases", "", ("| case | base | t | truth chi2 | description | first (delta BIC) | accepted / expected | "
                                   "wrong? | morphology | ratio |"), "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if r.get("first") == "error":
            lines.append(f"| {r['case']} | {r['base']} | - | - | {r['description']} | ERROR {r['error'][:80]} | - | - | - | - |")
            continue
        mo = r.get("residual_morphology") or {}
        mtxt = f"{mo.get('kind')} / {mo.get('geometry')}" + ("" if mo.get("significant") else " (n.s.)") if mo else "-"
        exp = ", ".join(r["accept"]) if r["accept"] else f"{r['kind']} / {', '.join(r['geometry'])}"
        first = f"{r['first']} ({U._f(r.get('first_delta_bic'))})" if r["first"] != "none" else "none"
        tcl = r.get("truth_chi2_levels")
        chi2 = (U._f(r.get("truth_chi2")) + ("" if tcl is None else f" ({U._f(tcl)} after levels)")
                + (f" (one frame {r['scatter_sigma']:.1f} sigma)" if r.get("scatter_sigma") is not None else ""))
        lines.append(f"| {r['case']} | {r['base']} | {r['strength_t']:.2f} | {chi2} | "
                     f"{r['description']} | {first} | {exp} | {'**yes**' if r.get('confidently_wrong') else 'no'} | "
                     f"{mtxt} | {U._f(r.get('error_ratio'))} |")
    return "\n".join(lines) + "\n"


def _commit() -> str:
    import subprocess

    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              cwd=Path(__file__).resolve().parent, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def report(rows: list[dict], out: Path, meta: dict) -> dict:
    """Write OUT/random_forms.md and OUT/random_forms.json."""
    from scenes.app.outputs import Outputs

    summ = summary(rows)
    md = markdown(rows, summ, meta)
    with Outputs() as outs:
        outs.file(out / "random_forms.md", "OUT").write_text(md)
        outs.file(out / "random_forms.json", "OUT").write_text(
            json.dumps({"meta": meta, "summary": summ, "cases": rows}, indent=1, default=float) + "\n")
    return summ


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out", nargs="?", default="random_forms_out")
    ap.add_argument("-n", type=int, default=200, help="number of cases (default 200)")
    ap.add_argument("--seed", type=int, default=None, help="master seed (default: a fresh one, printed)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--families", default="", help="comma-separated families (default: all; --list shows them)")
    ap.add_argument("--case", action="append", default=[], help="FAMILY-CASE_SEED: rerun that case (repeatable)")
    ap.add_argument("--keep", action="store_true", help="keep the frames and scenes in OUT/work")
    ap.add_argument("--draw-only", action="store_true", help="print the drawn cases, run nothing")
    ap.add_argument("--list", action="store_true", help="list the families and exit")
    ap.add_argument("--summarise", action="store_true", help="rebuild the report from OUT/rows/*.json")
    args = ap.parse_args(argv)
    if args.list:
        for f, (eff, fn) in FAMILIES.items():
            print(f"{f:16s} {eff or 'out of catalogue':16s} {(fn.__doc__ or '').strip().splitlines()[0] if fn.__doc__ else ''}")
        return 0
    fams = [f for f in args.families.split(",") if f]
    bad = [f for f in fams if f not in FAMILIES]
    if bad:
        print(f"random_forms: --families: unknown {', '.join(bad)} (expected: {', '.join(FAMILIES)})", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.summarise:
        rows = [json.loads(p.read_text()) for p in sorted((out / "rows").glob("*.json"))]
        if (out / "random_forms.json").exists():
            meta = json.loads((out / "random_forms.json").read_text())["meta"]
        elif (out / "seeds.jsonl").exists():  # a run still going (or stopped): its seed from the ledger
            meta = json.loads((out / "seeds.jsonl").read_text().splitlines()[-1])
        else:
            meta = {"seed": "?", "date": "?", "commit": _commit()}
        meta["n"] = len(rows)
        report(rows, out, meta)
        print((out / "random_forms.md").read_text().split("## By camera")[0])
        return 0
    if args.case:
        cases = []
        for c in args.case:
            fam, _, s = c.rpartition("-")
            if fam not in FAMILIES or not s.isdigit():
                print(f"random_forms: --case {c!r}: expected FAMILY-CASE_SEED (family one of {', '.join(FAMILIES)})",
                      file=sys.stderr)
                return 2
            cases.append(draw_case(fam, int(s)))
        seed = None
    else:
        seed = args.seed if args.seed is not None else fresh_seed()
        print(f"random_forms: master seed {seed}{' (fresh)' if args.seed is None else ''}", flush=True)
        cases = draw_cases(seed, args.n, fams or None)
    if args.draw_only:
        for c in cases:
            print(json.dumps(c.record(), default=float))
        return 0
    meta = {"seed": seed, "n": len(cases), "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "commit": _commit(), "workers": args.workers, "cases": [c.name for c in cases]}
    with open(out / "seeds.jsonl", "a") as ledger:
        ledger.write(json.dumps({k: meta[k] for k in ("seed", "n", "date", "commit")}) + "\n")
    (out / "rows").mkdir(exist_ok=True)
    t0 = time.perf_counter()
    done = {"n": 0}

    def progress(row):
        done["n"] += 1
        (out / "rows" / f"{row['case']}.json").write_text(json.dumps(row, indent=1, default=float) + "\n")
        print(f"[{done['n']}/{len(cases)}] {row['case']} ({row['base']}): first {row.get('first')}"
              f"{' WRONG' if row.get('confidently_wrong') else ''} ({time.perf_counter() - t0:.0f} s)", flush=True)

    tmp = None
    if args.keep:
        workdir = out / "work"
    else:
        tmp = tempfile.TemporaryDirectory()
        workdir = Path(tmp.name)
    try:
        rows = run_cases(cases, workdir, workers=args.workers, progress=progress)
    finally:
        if tmp is not None:
            tmp.cleanup()
    meta["wall_seconds"] = round(time.perf_counter() - t0, 1)
    report(rows, out, meta)
    print((out / "random_forms.md").read_text().split("## By camera")[0])
    print(f"wall {meta['wall_seconds']} s; wrote {out / 'random_forms.md'}, {out / 'random_forms.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
