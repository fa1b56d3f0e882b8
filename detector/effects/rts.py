"""Random telegraph signal (RTS) noise of CMOS pixels: a single oxide trap in the pixel's source-follower
transistor captures and emits one carrier, switching the pixel's output between discrete levels.

Physics (Kirton & Uren 1989, Adv. Phys. 38, 367; for image-sensor pixels Wang, Rao, Mierop & Theuwissen
2006, IEDM, "Random telegraph signal in CMOS image sensor pixels"; Chao et al. 2019, IEEE J. Electron
Devices Soc. 7, 227, statistics of RTN in small-pixel stacked CIS): the trap is a two-state Markov process
with exponentially distributed dwell times, mean ``tau_0`` (empty) and ``tau_1`` (filled). It is filled a
fraction ``p_1 = tau_1 / (tau_0 + tau_1)`` of the time. The exact transition over an interval ``dt``::

    P(1 | 0, dt) = p_1 (1 - exp(-dt / tau_c)),  P(0 | 1, dt) = p_0 (1 - exp(-dt / tau_c)),
    1 / tau_c = 1 / tau_0 + 1 / tau_1

A pixel is read by correlated double sampling (reset sample, then signal sample ``cds_interval_s`` later):
its RTS offset is ``A [s(t_sig) - s(t_rst)]``, three levels ``-A, 0, +A`` (``levels = 3``); with
``levels = 2`` the offset is ``A s(t_sig)`` (an RTS that CDS does not cancel, e.g. a dark-current RTS,
two levels ``0, A``).

Population (hardware seed, fixed per chip): a fraction ``fraction`` of the pixels carries a trap; its
amplitude ``A`` [e-] is log-normal (median ``amplitude_e``, log-sigma ``amplitude_sigma_ln``: the
long-tailed amplitude distributions of Wang et al. 2006 and Chao et al. 2019); ``tau_0`` and ``tau_1`` are
log-uniform between ``tau_min_s`` and ``tau_max_s`` (McWhorter: traps at depths uniformly distributed in
the oxide have log-uniform time constants). State (frame seed): each frame the trap state at the row's read
time is drawn from the stationary law and the second sample from the transition above, so consecutive
frames of a sequence are independent draws and a sequence shows blinking pixels; a run of frames in the
same state follows the geometric law ``P(k) = p^(k-1) (1 - p)`` (the frame-sampled form of the exponential
dwell law). A rolling shutter samples each row at its own time, but with frames independent the row time
does not change the law, so it is not used.

Defaults for the IMX411: no RTS statistics are published for it; the defaults (0.05 % of the pixels,
median 3 e- (its read noise is 3.5 e- at gain 0), log-sigma 0.7, time constants 10 us - 100 ms, CDS
interval 5 us) follow the orders of magnitude of Wang et al. 2006 and Chao et al. 2019 for small-pixel CIS.
A CCD's output amplifier has one transistor for all pixels: RTS pixels do not exist there (the effect still
runs if asked, modelling whatever population is given).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from ..rng import generator
from ..signatures import CountSignature
from .base import Effect, EffectParams, Stage, Tile, register_effect


def telegraph_transition(rng: np.random.Generator, state: np.ndarray, tau0_s, tau1_s, dt_s: float) -> np.ndarray:
    """The states ``dt_s`` later of two-state Markov traps now in ``state`` (0/1), exactly (module docstring)."""
    tau0, tau1 = np.asarray(tau0_s, np.float64), np.asarray(tau1_s, np.float64)
    p1 = tau1 / (tau0 + tau1)
    mix = 1.0 - np.exp(-dt_s * (1.0 / tau0 + 1.0 / tau1))
    p_next1 = np.where(state == 1, 1.0 - (1.0 - p1) * mix, p1 * mix)
    return (rng.random(np.shape(state)) < p_next1).astype(np.int8)


def telegraph_sequence(rng: np.random.Generator, tau0_s: float, tau1_s: float, times_s: np.ndarray) -> np.ndarray:
    """States (0/1) of one trap at increasing ``times_s``, starting from the stationary law (exact chain)."""
    p1 = tau1_s / (tau0_s + tau1_s)
    out = np.empty(len(times_s), np.int8)
    s = np.int8(rng.random() < p1)
    out[0] = s
    for i in range(1, len(times_s)):
        s = telegraph_transition(rng, np.array([s]), tau0_s, tau1_s, float(times_s[i] - times_s[i - 1]))[0]
        out[i] = s
    return out


def rts_offsets(rng: np.random.Generator, amplitude_e, tau0_s, tau1_s, levels: int, cds_interval_s: float
                ) -> np.ndarray:
    """One frame's RTS offsets [e-] of a set of trap pixels (stationary first sample; module docstring)."""
    tau0, tau1 = np.asarray(tau0_s, np.float64), np.asarray(tau1_s, np.float64)
    p1 = tau1 / (tau0 + tau1)
    s_rst = (rng.random(p1.shape) < p1).astype(np.int8)
    s_sig = telegraph_transition(rng, s_rst, tau0, tau1, cds_interval_s)
    amp = np.asarray(amplitude_e, np.float64)
    return amp * (s_sig - s_rst) if levels == 3 else amp * s_sig


def _mean_flip_probability(tau_min_s: float, tau_max_s: float, cds_interval_s: float) -> float:
    """Per-pixel probability of a downward CDS step ``P(s_rst = 1, s_sig = 0) = p_1 p_0 (1 - exp(-dt/tau_c))``,
    averaged over log-uniform time constants (a 64 x 64 grid in log tau)."""
    t = np.exp(np.linspace(np.log(tau_min_s), np.log(tau_max_s), 64))
    t0, t1 = np.meshgrid(t, t)
    p1 = t1 / (t0 + t1)
    return float((p1 * (1 - p1) * (1.0 - np.exp(-cds_interval_s * (1 / t0 + 1 / t1)))).mean())


def _rts_counts(res):
    """Three-level RTS makes isolated pixels step *down* as often as up, independently of light: negative
    single spikes where no light falls (a dead pixel cannot show there), with as many positive ones. The
    count compared is the unlit negative spikes plus the positive ones up to the same excess (so that a
    population of hot pixels alone, positive only, gives no RTS candidate). Fraction and median amplitude
    from the negative spikes, for the plugin's default time constants and amplitude spread."""
    from math import erfc, log, sqrt

    from ..signatures import SPIKE_SIGMA
    from .pixel_response import _lit

    d, m = res.data_spikes, res.model_spikes
    if not d.single_neg_index.size:
        return None
    dark_d = ~_lit(res, d.single_neg_index)
    neg_d = int(dark_d.sum())
    neg_m = int((~_lit(res, m.single_neg_index)).sum()) if m.single_neg_index.size else m.single_neg
    if neg_d <= neg_m + 2:
        return None
    pos_d = min(d.single_pos, m.single_pos + (neg_d - neg_m))
    idx = d.single_neg_index[dark_d]
    g = res.gain
    steps_e = (res.model_adu.ravel()[idx] - res.data_adu.ravel()[idx]).astype(np.float64) * g
    amp = float(np.median(steps_e))
    thr_e = SPIKE_SIGMA * float(np.median(np.sqrt(res.var_adu2.ravel()[idx]))) * g
    p = RTSParams()
    visible = 0.5 * erfc((log(thr_e) - log(max(amp, 1e-3))) / (p.amplitude_sigma_ln * sqrt(2)))
    per_px = _mean_flip_probability(p.tau_min_s, p.tau_max_s, p.cds_interval_s) * max(visible, 0.05)
    n_dark = max(int((res.photo_adu <= 0).sum()), 1) if (res.photo_adu <= 0).any() else res.data_adu.size
    # a binned output pixel holds binning^2 sensor pixels, each of which may carry a trap: the fraction is per
    # sensor pixel (an RTS step of one of them is still an isolated spike of the output pixel)
    frac = min((neg_d - neg_m) / (per_px * n_dark * res.sensor.binning ** 2), 0.1)
    return ({"fraction": float(f"{frac:.3g}"), "amplitude_e": round(amp, 2)}, neg_d + pos_d,
            neg_m + m.single_pos, 2)


_RTS_SIGNATURE = CountSignature(
    _rts_counts,
    lambda p, res: (f"isolated pixels stepping up and down by ~{p['amplitude_e']:.3g} e- where no light falls "
                    f"({100 * p['fraction']:.2g} % of the pixels): random telegraph noise"),
    pattern="isolated positive and negative spikes in equal numbers, independent of light")


class RTSParams(EffectParams):
    fraction: float = Field(5e-4, ge=0, le=0.1, description="fraction of the pixels with an RTS trap [1]")
    amplitude_e: float = Field(3.0, gt=0, le=1e4, description="median RTS amplitude [e-]")
    amplitude_sigma_ln: float = Field(0.7, ge=0, le=3, description="log-normal sigma of the amplitude [1]")
    tau_min_s: float = Field(1e-5, gt=0, le=1e4, description="shortest mean dwell time [s]")
    tau_max_s: float = Field(0.1, gt=0, le=1e5, description="longest mean dwell time [s]")
    levels: Literal[2, 3] = Field(3, description="3: CDS difference (-A, 0, +A); 2: state at read (0, A)")
    cds_interval_s: float = Field(5e-6, gt=0, le=1.0, description="reset-to-signal sampling interval [s]")

    @model_validator(mode="after")
    def _check(self):
        if self.tau_max_s < self.tau_min_s:
            raise ValueError("tau_max_s must be >= tau_min_s")
        return self


#: rows per hardware band of the RTS population (sensor rows)
_RTS_BAND = 240


@register_effect
class RTSNoise(Effect):
    """Random telegraph signal: a fraction of the pixels (hardware seed) has a two-state source-follower
    trap with exponential dwell times (log-uniform means) and a log-normal amplitude; read by CDS it gives
    offsets -A, 0, +A (levels = 3) or 0, A (levels = 2), drawn anew every frame (frame seed): a sequence
    shows blinking pixels (Kirton & Uren 1989; Wang et al. 2006 IEDM). Details: detector/effects/rts.py."""

    name = "rts_noise"
    scaling = "none"
    identity = {"fraction": 0.0}
    stages = (Stage.READ,)
    Params = RTSParams
    stochastic = True
    signature = _RTS_SIGNATURE

    def population(self, y0: int, y1: int) -> tuple[np.ndarray, ...]:
        """(rows, cols, amplitude_e, tau0_s, tau1_s) of the trap pixels in sensor rows [y0, y1), drawn per
        band of the full sensor from the hardware seed (independent of the window and the tiles)."""
        s, p = self.sensor, self.params
        out = []
        for b in range(y0 // _RTS_BAND, (y1 - 1) // _RTS_BAND + 1):
            key = ("rts", b)
            if key not in self._bands:
                rows = min(_RTS_BAND, s.sensor_height_px - b * _RTS_BAND)
                rng = generator(s.hardware_seed, self.name, b)
                n = rng.binomial(rows * s.sensor_width_px, p.fraction)
                flat = np.sort(rng.choice(rows * s.sensor_width_px, size=n, replace=False))
                amp = p.amplitude_e * np.exp(p.amplitude_sigma_ln * rng.standard_normal(n))
                lo, hi = np.log(p.tau_min_s), np.log(p.tau_max_s)
                t0, t1 = np.exp(rng.uniform(lo, hi, n)), np.exp(rng.uniform(lo, hi, n))
                self._bands[key] = (b * _RTS_BAND + flat // s.sensor_width_px, flat % s.sensor_width_px, amp, t0, t1)
            out.append(self._bands[key])
        cat = [np.concatenate([o[i] for o in out]) for i in range(5)]
        keep = (cat[0] >= y0) & (cat[0] < y1)
        return tuple(c[keep] for c in cat)

    def setup(self) -> None:
        self._bands: dict = {}

    def variance_e2(self, stage: Stage, tile: Tile, mean_e):
        """Mean RTS variance per pixel [e-^2] (fraction x the offset's variance, for the model of a frame)."""
        p = self.params
        a2 = p.amplitude_e ** 2 * np.exp(2 * p.amplitude_sigma_ln ** 2)  # E[A^2] of the log-normal
        # expectation over the log-uniform time constants (a 64 x 64 grid in log tau)
        t = np.exp(np.linspace(np.log(p.tau_min_s), np.log(p.tau_max_s), 64))
        t0, t1 = np.meshgrid(t, t)
        p1 = t1 / (t0 + t1)
        if p.levels == 3:
            per = 2.0 * p1 * (1 - p1) * (1.0 - np.exp(-p.cds_interval_s * (1 / t0 + 1 / t1)))
        else:
            per = p1 * (1 - p1)
        return p.fraction * a2 * float(per.mean())

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        if self.params.fraction == 0:
            return
        rows, cols, amp, t0, t1 = self.population(tile.y0, tile.y1)
        keep = (cols >= tile.x0) & (cols < tile.x1)
        if not keep.any():
            return
        rows, cols, amp, t0, t1 = rows[keep], cols[keep], amp[keep], t0[keep], t1[keep]
        off = rts_offsets(tile.rng(self.name), amp, t0, t1, self.params.levels, self.params.cds_interval_s)
        b = tile.bin
        np.add.at(data, ((rows - tile.y0) // b, (cols - tile.x0) // b), off.astype(np.float32))
