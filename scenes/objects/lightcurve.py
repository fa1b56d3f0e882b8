"""Light curves of debris and satellites: brightness modulated in time during the exposure.

A tumbling object's brightness changes as it turns (Santoni et al. 2013, Adv. Space Res. 51, 1599; the
light curves of rocket bodies and defunct satellites in Schildknecht 2007, A&A Rev. 14, 41): a smooth
periodic modulation for a diffuse body, sharp periodic glints for flat specular facets (solar panels,
insulation foil) flashing the Sun at the observer. An ``[[objects]]`` entry takes an optional
``light_curve`` table; the object's photon rate of :meth:`Brightness.photon_rate` is multiplied by a factor
f(t) (t in seconds from the exposure start):

``kind = "sinusoid"`` (``amplitude`` a in [0, 1], ``period_s`` P, ``phase`` phi in cycles)
    f(t) = 1 + a sin(2 pi (t / P + phi)),        rms of f: a / sqrt(2),

``kind = "glint"`` (``amplitude`` A >= 0: flash peak over the base level, ``period_s`` P, ``width_s`` w:
Gaussian sigma of a flash, ``phase`` phi: the first flash at t = phi P)
    f(t) = (1 + A sum_k exp(-(t - t_k)^2 / (2 w^2))) / (1 + A sqrt(2 pi) w / P),   t_k = (k + phi) P.

**Convention (flux conservation):** the mean of f over one period is exactly 1, so the brightness keys
(``photons``, ``mag``, size) give the **mean** brightness; the electrons of an exposure of T seconds are the
constant-brightness electrons times the mean of f over the recorded interval, (1/T) integral_0^T f dt,
which is 1 for a whole number of periods and within a / (pi T / P) (sinusoid) of 1 otherwise.

Each sample of a streak stands for the light of an interval [t_lo, t_hi] (``scenes.image.build``); it
gets the **interval mean** of f, (H(t_hi) - H(t_lo)) / (t_hi - t_lo), with H the exact antiderivative
(below), so the samples add up to the integral of rate x f whatever their spacing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import erf

from .errors import ObjectError
from .validate import number as _num

KINDS = ("sinusoid", "glint")
KEYS = {"sinusoid": ("kind", "amplitude", "period_s", "phase"),
        "glint": ("kind", "amplitude", "period_s", "width_s", "phase")}
#: samples per period (sinusoid) or per flash sigma (glint) at least, so a rolling shutter's row windows
#: see the time structure (the interval means already conserve the flux)
SAMPLES_PER_PERIOD = 32
SAMPLES_PER_WIDTH = 2


@dataclass(frozen=True)
class LightCurve:
    """A brightness modulation f(t) with mean 1 over a period (see the module notes).

    Parameters
    ----------
    kind : ``"sinusoid"`` or ``"glint"``
    amplitude : sinusoid: relative amplitude a in [0, 1] [1]; glint: flash peak over the base level A [1]
    period_s : period P [s]
    phase : phase phi [cycles, 0..1): sinusoid f = 1 + a sin(2 pi (t/P + phi)); glint flashes at (k + phi) P
    width_s : glint: Gaussian sigma of a flash [s] (<= P / 2)
    """

    kind: str
    amplitude: float
    period_s: float
    phase: float = 0.0
    width_s: float = 0.0

    @property
    def _norm(self) -> float:
        """Glint: the mean of the unnormalised 1 + A sum_k g over a period, 1 + A sqrt(2 pi) w / P."""
        return 1.0 + self.amplitude * math.sqrt(2.0 * math.pi) * self.width_s / self.period_s

    def _flash_terms(self, t: np.ndarray, fn) -> tuple[np.ndarray, np.ndarray]:
        """(sum of fn(t - t_k) over the flashes within 10 sigma of ``t``, index m of the last flash t_m <= t)."""
        p, w = self.period_s, self.width_s
        u = t / p - self.phase
        m = np.floor(u)
        r = (u - m) * p  # time since the last flash, [0, P)
        k = math.ceil(10.0 * w / p) + 1
        out = np.zeros_like(r)
        for j in range(-k, k + 2):
            out += fn(r - j * p)
        return out, m

    def factor(self, t_s) -> np.ndarray:
        """f(t) at times ``t_s`` [s from the exposure start] [1]."""
        t = np.asarray(t_s, dtype=float)
        if self.kind == "sinusoid":
            return 1.0 + self.amplitude * np.sin(2.0 * math.pi * (t / self.period_s + self.phase))
        w = self.width_s
        g, _ = self._flash_terms(t, lambda d: np.exp(-0.5 * (d / w) ** 2))
        return (1.0 + self.amplitude * g) / self._norm

    def integral(self, t_s) -> np.ndarray:
        """H(t) = integral_0^t f dt' [s] (exact; H(t + P) = H(t) + P)."""
        t = np.asarray(t_s, dtype=float)
        p = self.period_s
        if self.kind == "sinusoid":
            c = p / (2.0 * math.pi)
            th = 2.0 * math.pi * self.phase
            return t + self.amplitude * c * (math.cos(th) - np.cos(2.0 * math.pi * t / p + th))
        half = math.sqrt(math.pi / 2.0) * self.width_s  # a flash's integral from its peak to infinity
        s2 = math.sqrt(2.0) * self.width_s

        def flashes(x):  # antiderivative of sum_k g(x - t_k): 2 half per whole period + the nearby erf terms
            g, m = self._flash_terms(x, lambda d: half * erf(d / s2))
            return m * 2.0 * half + g

        return (t + self.amplitude * (flashes(t) - flashes(np.zeros(1)))) / self._norm

    def interval_mean(self, t_lo, t_hi) -> np.ndarray:
        """Mean of f over each interval [t_lo, t_hi] [1] (f itself where the interval is empty)."""
        lo, hi = np.asarray(t_lo, dtype=float), np.asarray(t_hi, dtype=float)
        width = hi - lo
        wide = width > 1e-12 * max(self.period_s, 1.0)
        mean = (self.integral(hi) - self.integral(lo)) / np.where(wide, width, 1.0)
        return np.where(wide, mean, self.factor(0.5 * (lo + hi)))

    def max_step_s(self) -> float:
        """Longest sample interval that resolves the curve in time [s] (rolling-shutter row windows)."""
        if self.kind == "sinusoid":
            return self.period_s / SAMPLES_PER_PERIOD
        return min(self.period_s / SAMPLES_PER_PERIOD, self.width_s / SAMPLES_PER_WIDTH)

    def to_table(self) -> dict:
        d = {"kind": self.kind, "amplitude": self.amplitude, "period_s": self.period_s, "phase": self.phase}
        if self.kind == "glint":
            d["width_s"] = self.width_s
        return d


def light_curve_from_table(table, prefix: str, *, file=None) -> LightCurve | None:
    """The :class:`LightCurve` of an ``objects[i].light_curve`` table (None when absent); errors name the key."""
    if table is None:
        return None
    if not isinstance(table, dict):
        raise ObjectError(f"{table!r}", key=prefix, file=file,
                          expected='a table like { kind = "sinusoid", amplitude = 0.4, period_s = 3.68 }')
    kind = table.get("kind")
    if kind not in KINDS:
        raise ObjectError(f"{kind!r}" if "kind" in table else "missing", key=f"{prefix}.kind", file=file,
                          expected="'sinusoid' or 'glint'")
    extra = sorted(set(table) - set(KEYS[kind]))
    if extra:
        raise ObjectError(f"unknown key {extra[0]!r} for kind = {kind!r}", key=f"{prefix}.{extra[0]}", file=file,
                          expected="one of " + ", ".join(KEYS[kind]))
    period = _num(table, "period_s", prefix, file, 0.0, 1e7, lo_open=True, required=True)
    phase = _num(table, "phase", prefix, file, 0.0, 1.0, default=0.0)
    if kind == "sinusoid":
        amp = _num(table, "amplitude", prefix, file, 0.0, 1.0, required=True)
        return LightCurve(kind, amp, period, phase)
    amp = _num(table, "amplitude", prefix, file, 0.0, 1e6, required=True)
    width = _num(table, "width_s", prefix, file, 0.0, period / 2.0, lo_open=True, required=True)
    return LightCurve(kind, amp, period, phase, width)
