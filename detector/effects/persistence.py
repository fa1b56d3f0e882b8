"""Persistence (residual image): charge of an earlier, bright exposure reappearing in the next frames.

Physics: charge above a threshold (a saturated star, a sunlit satellite) is trapped, at the Si/SiO2
interface of a front-illuminated CCD (residual bulk image: Janesick, *Scientific Charge-Coupled Devices*,
SPIE 2001, sec. 7.3) or in the traps of a pixel's photodiode and transfer gate (image lag and persistence
of CMOS sensors; the same law is used for the HgCdTe arrays of HST WFC3/IR, Smith et al. 2008, SPIE 7021,
70210J), and released exponentially afterwards. A trapped charge ``N = f max(Q_prev - Q_th, 0)`` [e-] at the
end of the earlier exposure, released with time constant ``tau``, adds to an exposure of length ``T``
starting ``t0`` after it::

    P = N [exp(-t0 / tau) - exp(-(t0 + T) / tau)]          [e-]

a mean charge (stage DARK: it carries its own shot noise). Several earlier frames add (superposition).
For a rolling shutter each row of both frames is shifted by the same row time, so ``t0`` is the same for
every row.

Sequences: the earlier frame is a FITS file written by newtsim (or a camera) in ADU; its charge is
``(ADU - BIAS) x GAIN`` from its own header cards (defaults: this sensor's). In a ``newtsim batch`` time
sequence each frame names its predecessor, e.g. ``set = { "effects.persistence.previous_frame" =
"frame_003.fits", "effects.persistence.time_since_s" = 5.0 }`` (the frames must then be rendered in order).
``time_since_s`` is from the *end* of the earlier exposure to the *start* of this one.

Defaults: persistence is not characterised for the IMX411 or the ML11002 (KAI-11002 interline CCDs show
image lag below 10 e-, ON Semiconductor data sheet); the defaults (``f = 1e-3`` of the charge above half
the full well, ``tau = 10 s``) are assumed orders of magnitude: measure them with a saturated flat followed
by darks. Sequence-only: one frame cannot tell persistence from a faint source at the same place, so the
single-frame diagnosis does not offer it (``signature = None``); the series diagnosis of a sequence sees a
source fading exponentially at a fixed place.
"""

from __future__ import annotations

import numpy as np
from pydantic import Field, model_validator

from ..errors import DetectorError
from .base import Effect, EffectParams, Stage, Tile, register_effect


def persistence_charge(previous_e: np.ndarray, fraction: float, threshold_e: float, tau_s: float,
                       time_since_s: float, exptime_s: float) -> np.ndarray:
    """Charge [e-] released into an exposure by the trapped charge of an earlier frame (module docstring).

    Parameters
    ----------
    previous_e : array [e-]   charge of the earlier frame's pixels
    fraction : float [1]      trapped fraction of the charge above ``threshold_e``
    threshold_e : float [e-]  charge above which traps fill
    tau_s : float [s]         release time constant
    time_since_s : float [s]  end of the earlier exposure to the start of this one
    exptime_s : float [s]     this exposure's length
    """
    trapped = np.maximum(np.asarray(previous_e, np.float32) - np.float32(threshold_e), 0) * np.float32(fraction)
    w = np.exp(-time_since_s / tau_s) - np.exp(-(time_since_s + exptime_s) / tau_s)
    return trapped * np.float32(w)


class PersistenceParams(EffectParams):
    previous_frame: str | list[str] = Field(..., description="the earlier frame(s): FITS file(s) in ADU")
    time_since_s: float | list[float] = Field(..., description="end of each earlier exposure to the start of "
                                                                "this one [s]")
    fraction: float = Field(1e-3, ge=0, le=1, description="trapped fraction of the charge above threshold [1]")
    threshold_e: float | None = Field(None, ge=0, description="charge above which traps fill (default: half "
                                                              "the full well) [e-]")
    tau_s: float = Field(10.0, gt=0, le=1e6, description="release time constant [s]")

    @model_validator(mode="after")
    def _check(self):
        f = [self.previous_frame] if isinstance(self.previous_frame, str) else self.previous_frame
        t = [self.time_since_s] if isinstance(self.time_since_s, (int, float)) else self.time_since_s
        if len(f) != len(t):
            raise ValueError("one time_since_s per previous_frame")
        if any(x < 0 for x in t):
            raise ValueError("time_since_s must be >= 0")
        return self


@register_effect
class Persistence(Effect):
    """Persistence: a fraction f of an earlier frame's charge above threshold_e is trapped and released with
    time constant tau; an exposure of T s starting t0 s after it collects f (Q - Q_th) [exp(-t0/tau) -
    exp(-(t0+T)/tau)] (Smith et al. 2008 SPIE 7021). previous_frame: FITS in ADU (its BIAS/GAIN cards),
    time_since_s: from its end to this frame's start. Details: detector/effects/persistence.py."""

    name = "persistence"
    scaling = "frame"
    no_identity = "needs a previous frame; fraction = 0 is checked in tests/detector/test_sensor_physics.py"
    stages = (Stage.DARK,)
    Params = PersistenceParams

    def setup(self) -> None:
        from ..fits_io import read_image

        p, s = self.params, self.sensor
        files = [p.previous_frame] if isinstance(p.previous_frame, str) else list(p.previous_frame)
        times = [p.time_since_s] if isinstance(p.time_since_s, (int, float)) else list(p.time_since_s)
        if s.binning != 1:
            raise DetectorError("persistence with binning", key="effects.persistence",
                                expected="detector.binning = 1 (the earlier frame is read per sensor pixel)")
        thr = self.threshold_e()
        # only the pixels above the threshold matter: keep them (window flat index, charge [e-]), not the frame
        self.frames = []
        for f, t in zip(files, times):
            data, hdr = read_image(f, key="effects.persistence.previous_frame", role="previous frame", dtype=None)
            if data.shape != s.shape:
                raise DetectorError(f"previous frame has shape {data.shape}", key="effects.persistence.previous_frame",
                                    file=f, expected=f"{s.shape} (rows, cols) like this frame's window")
            bias, gain = float(hdr.get("BIAS", s.bias_adu)), float(hdr.get("GAIN", s.gain_e_per_adu))
            idx = np.flatnonzero(data > thr / gain + bias)
            charge = (data.ravel()[idx].astype(np.float64) - bias) * gain
            self.frames.append((idx, charge.astype(np.float32), float(t)))
            del data

    def threshold_e(self) -> float:
        p = self.params
        return p.threshold_e if p.threshold_e is not None else 0.5 * self.sensor.full_well_e

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        p, s = self.params, self.sensor
        if p.fraction == 0:
            return
        w = s.shape[1]
        r0, r1 = tile.y0 - s.roi_y0, tile.y1 - s.roi_y0
        for idx, charge, t0 in self.frames:
            a, b = np.searchsorted(idx, [r0 * w, r1 * w])
            if b > a:
                add = persistence_charge(charge[a:b], p.fraction, self.threshold_e(), p.tau_s, t0, tile.exptime_s)
                rel = idx[a:b] - r0 * w
                data[rel // w, rel % w] += add  # distinct pixels: a plain fancy-index add
