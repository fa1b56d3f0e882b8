"""Read-out electronics: row noise, kTC reset noise, bias structure and inter-channel crosstalk.

References
----------
* J. R. Janesick, *Photon Transfer*, SPIE Press (2007), ch. 4 (read noise, kTC reset noise), ch. 9.
* Reference thesis eq. 33 (reset noise sigma = sqrt(k T C) / q).
* EMVA Standard 1288 Release 4.0, sec. 4.3 / 8.3: row and column (spatial) noise.
* A. C. Moore et al., SPIE 5499 (2004); LSST Camera crosstalk papers (e.g. Snyder et al., JATIS 2021):
  electronic crosstalk between read-out channels as a linear coupling coefficient.
* L. M. Freyhammer et al., Exp. Astron. 12, 147 (2001), "On cross-talk among the amplifiers of CCDs":
  crosstalk of either sign, delayed behind the aggressor's pixel by the read-out electronics (the causal
  kernel of :func:`crosstalk_kernel`); G. M. Bernstein et al., PASP 129, 114502 (2017) (DECam).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Annotated

import numpy as np
from pydantic import AfterValidator, Field
from scipy.ndimage import binary_dilation

from ..rng import standard_normal_f32
from ..signatures import (
    Fit,
    LinearSignature,
    Signature,
    VarianceSignature,
    Variant,
    fit_linear,
    ml_variance_scale,
    offset_response_untold,
    periodic_line_peak,
    search_sample,
    template_at,
)
from ..significance import DETECTION_SIGMA, EXPLAINS_MOST
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


def bias_profile_adu(xs: np.ndarray, width: int, coeffs) -> np.ndarray:
    """A fixed bias pattern along the serial direction [ADU]: the cosine series ``sum_k c_k cos(k pi t)``,
    ``k = 1 .. len(coeffs)``, of the column's position ``t = x / (width - 1)`` in [0, 1] (a DCT-II basis: any
    smooth profile of the column index, mean zero over the sensor). The clocking of the serial register and
    the output amplifier's settling repeat at every row, so their pattern depends on the column only and is
    the same every frame (the "bias structure" a master bias removes: Howell 2006, Handbook of CCD Astronomy,
    sect. 4.2; Janesick 2001, Scientific CCDs, sect. 3.6)."""
    t = xs.astype(np.float64) / max(width - 1, 1)
    k = np.arange(1, len(coeffs) + 1, dtype=np.float64)
    return (np.asarray(coeffs, np.float64) @ np.cos(np.pi * k[:, None] * t[None, :])).astype(np.float32)


def bias_field_adu(ys: np.ndarray, xs: np.ndarray, height: int, width: int, coeffs, box=None) -> np.ndarray:
    """A fixed 2-D bias pattern [ADU] on sensor coordinates: the cosine series
    ``sum_jk C_jk cos(j pi v) cos(k pi u)`` of the pixel's position in the box ``(x0, y0, x1, y1)`` [sensor px]
    (default the sensor), ``u = (x - x0) / (x1 - x0)``, ``v = (y - y0) / (y1 - y0)`` in [0, 1], held at the box's
    edge beyond it (a 2-D DCT-II basis: any smooth field; a window fits the field it sees, not an extrapolation
    over the sensor), ``C`` (rows j, columns k) the coefficients, ``C_00`` left out (the mean is the bias
    level's). The read-out's offset drifts during the
    read of a frame (the output amplifier and the reference warming as the rows are read: a pattern along the
    rows) while the serial clocking repeats every row (along the columns); together, and with an amplifier
    whose warm-up spreads into the array, they leave a smooth 2-D structure that is the same in every bias
    frame, which a master bias removes (Howell 2006, Handbook of CCD Astronomy, sect. 4.2; Janesick 2001,
    Scientific CCDs, sect. 3.6)."""
    c = np.array(coeffs, np.float64)
    if c.size == 0:
        return np.zeros((ys.size, xs.size), np.float32)
    c[0, 0] = 0.0
    x0, y0, x1, y1 = box if box else (0.0, 0.0, width - 1.0, height - 1.0)
    v = np.clip((ys.astype(np.float64) - y0) / max(y1 - y0, 1.0), 0.0, 1.0)
    u = np.clip((xs.astype(np.float64) - x0) / max(x1 - x0, 1.0), 0.0, 1.0)
    cy = np.cos(np.pi * v[:, None] * np.arange(c.shape[0])[None, :])
    cx = np.cos(np.pi * np.arange(c.shape[1])[:, None] * u[None, :])
    return (cy @ c @ cx).astype(np.float32)


def _rectangular_coefficients(v: list[list[float]]) -> list[list[float]]:
    if v and (any(len(row) != len(v[0]) for row in v) or not v[0]):
        raise ValueError(f"a smooth field's coefficients must be a rectangular array (rows of equal, non-zero "
                         f"length), got rows of lengths {[len(row) for row in v]}")
    return v


def _field_box(v: list[float]) -> list[float]:
    if v and (len(v) != 4 or v[2] <= v[0] or v[3] <= v[1]):
        raise ValueError(f"a field's box must be empty or (x0, y0, x1, y1) with x1 > x0, y1 > y0 [px], got {v}")
    return v


#: the cosine-series coefficients C_jk of a smooth field (:func:`bias_field_adu`), validated rectangular
FieldCoefficients = Annotated[list[list[float]], AfterValidator(_rectangular_coefficients)]
#: the box (x0, y0, x1, y1) [sensor px] a field's cosines run over, validated empty or ordered
FieldBox = Annotated[list[float], AfterValidator(_field_box)]


def field_coefficients(unit: str, what: str):
    """The parameter declaration of a smooth field's coefficients in ``unit`` (``what``: the field's meaning),
    shared by the bias structure and the dark-rate field (one basis, :func:`bias_field_adu`)."""
    return Field(default_factory=list, max_length=16,
                 description=f"2-D cosine-series coefficients C_jk (rows j, columns k; C_00 ignored) of {what}, "
                 "sum_jk C_jk cos(j pi v) cos(k pi u), u, v in [0, 1] across field_box_px (default the sensor: "
                 f"u = x / (W - 1), v = y / (H - 1)) [{unit}] (bias_field_adu)",
                 json_schema_extra={"unit": unit})


def field_box(coefficients_key: str):
    """The parameter declaration of the box a smooth field's coefficients (``coefficients_key``) run over."""
    return Field(default_factory=list, max_length=4,
                 description=f"the box (x0, y0, x1, y1) [sensor px] over which {coefficients_key}'s cosines run from "
                 "0 to pi (held at its edge beyond it; empty: the sensor)",
                 json_schema_extra={"unit": "pixel"})


#: points per axis of the grid over the window on which a fitted 2-D field is bounded and described
BIAS_FIELD_GRID = 65


#: span of an exponential crosstalk tail [e-folding lengths]: lags beyond it carry < e^-5 = 0.7 % of the echo
TAIL_SPAN = 5.0


def crosstalk_kernel(delay_px: int = 0, tail_px: float = 0.0) -> np.ndarray:
    """Causal impulse response [1 per read-out pixel] of inter-channel crosstalk along the read-out order,
    normalised to a sum of 1 (so that ``alpha`` stays the integrated coupling).

    The victim's amplifier sees the aggressor's signal through a shared supply, reference or clock line with
    a settling time: the echo arrives ``delay_px`` read-out pixels after the aggressor's pixel and, with
    ``tail_px > 0``, decays as ``exp(-m / tail_px)`` over the following lags ``m`` (a single-pole RC
    response), truncated after :data:`TAIL_SPAN` e-folding lengths. ``delay_px = 0, tail_px = 0`` is the
    instantaneous coupling (a delta at lag 0). Delayed and negative (undershoot) crosstalk between CCD
    amplifiers: Freyhammer et al. 2001, Exp. Astron. 12, 147; coefficients of either sign in large mosaics:
    Bernstein et al. 2017, PASP 129, 114502 (DECam); Snyder et al. 2021, JATIS 7, 048002 (LSST).
    Returns weights for lags ``0 .. len - 1`` [read-out pixels]."""
    d = int(delay_px)
    if d < 0 or tail_px < 0:
        raise ValueError("crosstalk delay and tail must be >= 0")
    if tail_px <= 0:
        k = np.zeros(d + 1)
        k[d] = 1.0
        return k
    m = np.arange(int(np.ceil(TAIL_SPAN * tail_px)) + 1, dtype=np.float64)
    w = np.exp(-m / tail_px)
    return np.concatenate([np.zeros(d), w / w.sum()])


def causal_filter(x: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """``sum_m kernel[m] x[..., p - m]`` along the last axis (zero before the first pixel): the echo of a
    signal read in the order of the last axis through the impulse response ``kernel`` [same units as x]."""
    out = np.zeros_like(x)
    n = x.shape[-1]
    for m, k in enumerate(np.asarray(kernel, np.float64)):
        if k and m < n:
            out[..., m:] += x.dtype.type(k) * x[..., : n - m]
    return out


def channel_crosstalk(data: np.ndarray, n_channels: int, alpha: float, mirrored: bool, delay_px: int = 0,
                      tail_px: float = 0.0) -> None:
    """In place: every channel (vertical stripe) receives ``alpha`` times the signal of every other channel.

    Channels are ``n_channels`` equal stripes of columns; with ``mirrored`` every second channel is read
    from the other side, so the coupled image appears mirrored (as on multi-amplifier CCDs). Works on the
    bias-free signal [ADU]; ``alpha`` [1] is the victim/source coupling (negative: an undershoot). With
    ``delay_px`` [read-out pixels] or ``tail_px`` [read-out pixels] the echo is the aggressor's signal
    through the causal kernel :func:`crosstalk_kernel` along each row in read-out order (the channels are
    read in step; the echo does not cross to the next row).
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
    if delay_px or tail_px:
        oriented = causal_filter(oriented, crosstalk_kernel(delay_px, tail_px))
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
    Photon Transfer, ch. 10) and leave the column means alone. A fit whose row offsets are a smooth curve
    (once a polynomial of the row index is taken off, the rows scatter no more than the pixel noise allows),
    or that comes with an equal scatter of the column means, is a 2-D pattern (a gradient, a radial
    fall-off) seen through the rows: :meth:`plausible` says so. A row noise with a flicker (1/f) part has a
    smooth part of its own, so the curve's share of the excess decides nothing: what is left beyond it does."""

    kind = "rows"
    pattern = "row means scatter beyond the pixel noise"
    #: a row-offset fit is a smooth curve when a polynomial of this degree in the row index is significant (its
    #: chi2 DETECTION_SIGMA standard errors above its dof) and, taken off, leaves the row means' chi2 within
    #: DETECTION_SIGMA standard errors of theirs (chi2 tests of the curve and of the rows beyond it; a weak white
    #: row noise has no curve and is not refused as one)
    SMOOTH_DEGREE = 4
    #: ... or a pattern of the whole frame when the column means' excess variance is this fraction of the rows'
    #: (row offsets leave the column means alone; a ratio of per-line variances, not a share of one whole, so not
    #: EXPLAINS_MOST: for a symmetric 2-D patch it is the frame's width over its height)
    COLUMN_FRACTION = 0.5
    #: ... or a drift when the extra row offsets (the smooth curve removed) correlate from row to row beyond
    #: their noise (lag-1 correlation DETECTION_SIGMA standard errors, 1 / sqrt(rows), above zero: row noise draws
    #: a new offset for every row read, Janesick 2007, ch. 10) and their spectrum follows a level drifting as a
    #: random walk (1/f^2) rather than the read chain's flicker noise (Janesick 2007, Photon Transfer, ch. 7:
    #: flicker noise of the output amplifier, power ~ 1/f): the two laws compared by their Whittle likelihoods
    #: (:meth:`drift_law_gain`), each with its amplitude fitted, so the data say which law, with no bar between
    #: the two indices; a pink row noise correlates neighbours (0.44 for the hidden-effect suite's) and is
    #: nearer 1/f

    @staticmethod
    def _whittle(u: np.ndarray, ratio: float):
        """The Whittle negative log-likelihood ``nll(log A, alpha)`` of the periodogram of the whitened extra row
        offsets ``u``: each ordinate I_k exponential about ``A k^-alpha + c`` (Whittle 1953; ``c`` the white pixel
        noise of the row means, 1 / ``ratio`` of their variance), over the frequencies above the removed smooth
        curve's (k > 8); and a starting log-amplitude. None with fewer than 16 frequencies or no excess."""
        n = u.size
        power = np.abs(np.fft.rfft(u - u.mean())) ** 2 / n
        k = np.arange(power.size, dtype=np.float64)
        sel = k > 8
        if sel.sum() < 16 or ratio <= 1:
            return None
        ik, kk = power[sel], k[sel]
        c = float(np.mean(power[1:])) / ratio
        lk = np.log(kk / kk[0])

        def nll(p):
            m = np.exp(p[0] - p[1] * lk) + c
            return float(np.sum(np.log(m) + ik / m))

        return nll, float(np.log(max(float(np.mean(ik[:8])) - c, 1e-6 * c)))

    @classmethod
    def spectral_index(cls, u: np.ndarray, ratio: float) -> float | None:
        """alpha: the power of the extra row offsets falls as 1/f^alpha (the Whittle maximum-likelihood index of
        :meth:`_whittle`). None with fewer than 16 frequencies or no excess."""
        from scipy.optimize import minimize

        got = cls._whittle(u, ratio)
        if got is None:
            return None
        nll, a0 = got
        best = min((minimize(nll, [a0, al], method="Nelder-Mead", options={"xatol": 1e-4, "fatol": 1e-3}) for al in
                    (0.5, 1.0, 2.0)), key=lambda o: o.fun)
        return float(best.x[1])

    @classmethod
    def drift_law_gain(cls, u: np.ndarray, ratio: float) -> float | None:
        """Whittle -2 ln L of a drifting level's spectrum (1/f^2, a random walk) less that of a flicker noise's
        (1/f, the read chain's), each with its amplitude fitted (:meth:`_whittle`): negative when the extra row
        offsets follow the drift's law. Two laws of one parameter each: the likelier is the data's, no bar
        between them. None with fewer than 16 frequencies or no excess."""
        from scipy.optimize import minimize_scalar

        got = cls._whittle(u, ratio)
        if got is None:
            return None
        nll, a0 = got
        fits = [minimize_scalar(lambda la, al=al: nll((la, al)), bracket=(a0 - 1.0, a0 + 1.0)).fun
                for al in (1.0, 2.0)]
        return 2.0 * float(fits[1] - fits[0])

    @staticmethod
    def periodic_peak(u: np.ndarray) -> tuple[float, float] | None:
        """(period [rows], ratio) of the strongest frequency of the whitened row offsets ``u`` when it stands
        above its neighbours' spectral level beyond the frame's false-alarm probability
        (:func:`detector.signatures.periodic_line_peak`): row noise is white from row to row, a pickup or a
        clock's interference repeats."""
        return periodic_line_peak(u)

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
        r, v, _ = self.line_means(res)
        theta = float(np.asarray(fit.extra_var_adu2, np.float64).ravel()[0])
        n = r.size
        if n >= 3 * (self.SMOOTH_DEGREE + 1):
            x = np.linspace(-1.0, 1.0, n)
            basis = np.polynomial.legendre.legvander(x, self.SMOOTH_DEGREE)
            wts = 1.0 / (v + theta)
            coef = np.linalg.lstsq(basis * np.sqrt(wts)[:, None], r * np.sqrt(wts), rcond=None)[0]
            curve, k_curve = basis @ coef, self.SMOOTH_DEGREE + 1
            curve_sigma = (float(np.sum(curve ** 2 / v)) - k_curve) / np.sqrt(2.0 * k_curve)
            rest_sigma = (float(np.sum((r - curve) ** 2 / v)) - (n - k_curve)) / np.sqrt(2.0 * (n - k_curve))
            if curve_sigma >= DETECTION_SIGMA and rest_sigma < DETECTION_SIGMA:
                return (f"the row offsets form a smooth curve (a degree-{self.SMOOTH_DEGREE} polynomial of the row "
                        f"taken off, the rows scatter as the pixel noise allows: {rest_sigma:.2g} sigma of excess): a "
                        "large-scale 2-D pattern seen through the rows, not independent row noise")
            # independent from row to row: the lag-1 autocorrelation of what the smooth curve leaves (whitened)
            # (of the extra offsets: the pixel noise of the row means, white, dilutes it by (chi2/n - 1) / (chi2/n))
            u = (r - curve) * np.sqrt(wts)
            rho1 = float(np.dot(u[1:], u[:-1]) / max(np.dot(u, u), 1e-300))
            ratio = float(np.sum(r * r / v)) / n
            rho_extra = rho1 * ratio / (ratio - 1) if ratio > 1 else 0.0
            if rho1 * np.sqrt(n) > DETECTION_SIGMA:
                drift = self.drift_law_gain(u, ratio)
                alpha = None if drift is None else self.spectral_index(u, ratio)
                if drift is None or drift < 0:
                    return (f"the row offsets are correlated from one row to the next (lag-1 correlation {rho_extra:.2f} "
                            f"of the extra offsets, {rho1 * np.sqrt(n):.0f} sigma"
                            + (f"; their spectrum falls as 1/f^{alpha:.2g}, a drift's 1/f^2 likelier than a flicker "
                               f"noise's 1/f by {-drift:.3g} in -2 ln L" if alpha is not None else "") + "): a level drifting during the read-out "
                            "or a slow pickup, not row noise")
            peak = self.periodic_peak(u)
            if peak is not None:
                period, ratio = peak
                return (f"the row offsets repeat with a period of {period:.3g} rows (that frequency {ratio:.3g} x its "
                        "neighbours' spectral level): a periodic pattern (a pickup, a clock's interference), not "
                        "independent row noise")
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
    unlit = _unlit(res)
    if not unlit and (np.any(res.photo_adu > 0) or res.exptime_s <= 0):
        return  # a frame with light: a smooth pattern is the light's (sky, straylight, a response) or charge's
    # on a frame without light or dark charge a pattern along the columns can only be the read-out's: the
    # serial direction's fixed pattern, in cosine series of growing order (chosen by BIC)
    top = max(BIAS_PROFILE_ORDERS)
    rows = [(f * bias_profile_adu(res.xs, s.sensor_width_px, np.eye(top)[k]))[None, :] for k in range(top)]
    for order in BIAS_PROFILE_ORDERS if unlit else ():

        def with_profile(c):
            p = to_params(c[:3])
            if p is None:
                return None
            coeffs = [float(f"{ck:.4g}") for ck in c[3:]]
            # the profile's extremes at the sensor's columns are bounded by the bias too
            if float(np.max(np.abs(bias_profile_adu(np.linspace(0, s.sensor_width_px - 1, 257), s.sensor_width_px,
                                                     coeffs)))) > s.bias_adu:
                return None
            return dict(p, column_profile_adu=coeffs)

        yield Variant(unit + rows[:order], with_profile, label=f"column profile of {order} cosine terms")
    # ... and on a frame without light a smooth 2-D structure (the read's drift along the rows with the serial
    # pattern, an amplifier's warm-up spreading into the array), in 2-D cosine series of growing order (chosen by
    # BIC), over the window the frame sees (the part of the field the data constrains: cosines over the sensor
    # seen through a window are nearly collinear, their coefficients ill-conditioned): on an exposed dark the
    # basis the dark-rate field of a temperature gradient is offered in (detector.effects.thermal), so that on
    # one dark frame the two differ only by the dark charge's shot noise and neither is preferred for its form
    # (a bias frame, or a dark of another exposure, tells them apart); both are sensor-scale fields, as smooth
    # through a window as the window's share of the sensor makes them (sensor_scale_orders)
    box = window_box(res)

    def with_field(coef):
        if float(np.max(np.abs(field_on_window(coef, box, res)))) > s.bias_adu:  # bounded by the bias too
            return None
        return {"gradient_x_adu": 0.0, "gradient_y_adu": 0.0, "quadratic_adu": 0.0,
                "field_adu": [[float(v) for v in row] for row in coef], "field_box_px": box}

    yield from cosine_field_variants(res, f, box, with_field,
                                     orders=sensor_scale_orders(res) if res.exptime_s > 0 else None)


def sensor_box(s) -> list[float]:
    """The sensor's box ``(x0, y0, x1, y1)`` [sensor px], first to last pixel centre."""
    return [0.0, 0.0, s.sensor_width_px - 1.0, s.sensor_height_px - 1.0]


def sensor_scale_orders(res, orders=None) -> tuple[int, ...]:
    """The orders of a window's cosine series (:func:`cosine_field_variants`, default BIAS_FIELD_ORDERS) for a
    sensor-scale field (a read-out drift, a die's temperature field): a series of N terms over the sensor has
    N - 1 half cycles across it, of which a window spanning the share ``f`` of the sensor (the larger of its two
    axes) sees (N - 1) f; the window's series needs ceil((N - 1) f) + 1 terms (2 at least: ramps and their
    cross term). Over a window's own box a larger order would take a glow's corner or a local blob as a smooth
    field."""
    orders = BIAS_FIELD_ORDERS if orders is None else orders
    s = res.sensor
    share = max(float(np.ptp(res.xs)) / max(s.sensor_width_px - 1, 1), float(np.ptp(res.ys)) / max(s.sensor_height_px - 1, 1))
    return tuple(sorted({min(n, int(np.ceil((n - 1) * share)) + 1) for n in orders}))


def window_box(res) -> list[float]:
    """The box ``(x0, y0, x1, y1)`` [sensor px] of the pixel centres the residuals ``res`` cover (its window)."""
    return [float(res.xs.min()), float(res.ys.min()), float(res.xs.max()), float(res.ys.max())]


def field_on_window(coef, box, res) -> np.ndarray:
    """:func:`bias_field_adu` of coefficients ``coef`` over the box ``box`` [sensor px] on a BIAS_FIELD_GRID x
    BIAS_FIELD_GRID grid spanning the window the residuals cover (the part of the field the data constrains)."""
    s = res.sensor
    grid = np.linspace(0, 1, BIAS_FIELD_GRID)
    ys = float(res.ys.min()) + grid * float(res.ys.max() - res.ys.min())
    xs = float(res.xs.min()) + grid * float(res.xs.max() - res.xs.min())
    return bias_field_adu(ys, xs, s.sensor_height_px, s.sensor_width_px, coef, box)


def cosine_field_variants(res, unit, box, to_params, orders=None):
    """Variants of a smooth 2-D field: :func:`bias_field_adu`'s cosine series over the box ``(x0, y0, x1, y1)``
    [sensor px], ``order x order`` terms (``C_00`` left out: the level's) for each order of ``orders`` (default
    BIAS_FIELD_ORDERS), times ``unit`` (ADU per unit coefficient: a scalar, or a map that broadcasts), the
    coefficients rounded to 4 significant digits and passed as an ``order x order`` array to ``to_params``
    (its parameters, or None out of bounds). The one smooth-field basis of the additive fields that differ by
    their physics only (a bias structure, a dark-rate field)."""
    width = res.data_adu.shape[1]
    orders = BIAS_FIELD_ORDERS if orders is None else orders
    v = np.clip((res.ys - box[1]) / max(box[3] - box[1], 1.0), 0.0, 1.0)
    u = np.clip((res.xs - box[0]) / max(box[2] - box[0], 1.0), 0.0, 1.0)
    cv = np.cos(np.pi * v[:, None] * np.arange(max(orders))).astype(np.float32)
    cu = np.cos(np.pi * u[:, None] * np.arange(max(orders))).astype(np.float32)
    unit = np.asarray(unit, np.float32)
    for order in orders:
        terms = [(j, k) for j in range(order) for k in range(order) if j or k]

        def maps(terms=terms):
            return [(unit * (cv[:, j, None] * cu[None, :, k])).astype(np.float32) for j, k in terms]

        def at(idx, terms=terms):
            y, x = np.divmod(idx, width)
            scale = template_at(unit, res.data_adu.shape, idx) if unit.ndim else float(unit)
            return np.stack([scale * cv[y, j] * cu[x, k] for j, k in terms])

        def params(c, order=order, terms=terms):
            coef = np.zeros((order, order))
            for (j, k), ck in zip(terms, c):
                coef[j, k] = float(f"{ck:.4g}")
            return to_params(coef)

        yield Variant(maps, params, at=at, label=f"2-D field of {order} x {order} cosine terms over x {box[0]:g}.."
                      f"{box[2]:g}, y {box[1]:g}..{box[3]:g} px")  # the box in the label: one basis, one name


#: orders of the bias pattern along the serial direction the bias fit tries on unlit frames [cosine terms]
BIAS_PROFILE_ORDERS = (8, 16, 32)
#: orders of the smooth 2-D bias structure the bias fit tries on unlit frames [cosine terms per axis]: 3 (a
#: bowl, a saddle, ramps), 5 and 8 (up to two and three and a half cycles along each axis: a fixed oblique wave)
BIAS_FIELD_ORDERS = (3, 5, 8)


def _unlit(res) -> bool:
    """No light and less dark charge than one read noise anywhere: what varies is the read-out's."""
    return not np.any(res.photo_adu > 0) and float(np.max(res.dark_e, initial=0.0)) < res.sensor.read_noise_e


def _bias_words(p, res) -> str:
    parts = [f"{p['gradient_x_adu']:+.3g} ADU across the columns", f"{p['gradient_y_adu']:+.3g} ADU across the rows",
             f"{p['quadratic_adu']:+.3g} ADU bowl at the corners"]
    field = p.get("field_adu") or []
    if field:
        shape = field_on_window(field, p.get("field_box_px") or sensor_box(res.sensor), res)  # what it bounds
        return (f"an additive offset independent of the signal, a smooth 2-D pattern of {float(np.ptp(shape)):.3g} ADU "
                f"peak to peak across the window ({len(field)} x {len(field)} cosine terms: the read-out's drift and "
                "fixed pattern): bias structure")
    prof = p.get("column_profile_adu") or []
    if prof:
        u = np.linspace(0, res.sensor.sensor_width_px - 1, 257)
        shape = bias_profile_adu(u, res.sensor.sensor_width_px, prof)
        parts.append(f"a fixed pattern along the columns of {float(np.ptp(shape)):.3g} ADU peak to peak "
                     f"({len(prof)} cosine terms: the serial register's or output amplifier's pattern)")
    return "an additive offset independent of the signal, " + ", ".join(parts) + ": bias structure"


_ROW_SIGNATURE = RowOffsetSignature()


#: the share of the claimed excess variance that one spatial frequency may hold before the excess is a pattern,
#: not white noise: white noise puts ~1e-4 of its power in the strongest of the ~1e5 frequencies of a 512 x 512
#: cut; a pick-up wave puts all of its own there (most of it: EXPLAINS_MOST, the policy's share for "the
#: effect's doing")
KTC_PERIODIC_SHARE = EXPLAINS_MOST


def _ktc_check(fit, res) -> str:
    """Reset noise adds the same white noise to every read, so the camera's measured read noise (its bias
    frames) already holds most of it (Janesick 2001, Scientific CCDs, sect. 3.3: kTC noise is the reset
    component of the read noise): a part of the read noise is at most the whole of it, so on a lit frame an
    extra white noise above the camera's read noise itself (the data's read noise then more than sqrt(2) times
    the one its bias frames measure) is not reset noise but the light's own pixel-to-pixel scatter (a PRNU,
    which a uniform light cannot tell from it). The bound assumes the scene's read noise is the one the camera's
    bias frames measure (a data-sheet figure after correlated double sampling would not hold the reset noise of a
    read-out without it, which can exceed it several times: sqrt(kT/C) is 13 e- at 1 fF). kTC noise is
    thermal and white: an excess whose power sits in one spatial frequency (significant on its own, the
    morphology's periodic_bar, and holding KTC_PERIODIC_SHARE of the excess) is a periodic pattern
    (electronic pick-up), not reset noise."""
    from ..morphology import periodic_bar, periodic_line

    theta0 = float(fit.state.get("theta", 0.0))
    v = float(np.median(1.0 / np.maximum(res.flat_profiled()[2], 1e-30))) if res.n_fit else 0.0
    if theta0 > 0 and v > 0:
        period, contrast, share = periodic_line(res)
        excess = theta0 / (theta0 + v)  # the claimed excess's share of the pixels' variance
        if contrast >= periodic_bar(res.data_adu.shape) and share >= KTC_PERIODIC_SHARE * excess:
            return (f"the extra scatter sits in one spatial frequency (period {period:.3g} px, {contrast:.3g} x the "
                    f"median power, {100 * share:.2g} % of the power against the {100 * excess:.2g} % the excess "
                    "claims): a periodic pattern (electronic pick-up), not white kTC noise")
    if not np.any(res.photo_adu > 0) or res.sensor.read_noise_e <= 0:
        return ""
    theta = float(fit.state.get("theta", 0.0))
    s = res.sensor
    reads = 1.0 if s.kind == "ccd" else float(s.binning ** 2)
    sigma_e = float(np.sqrt(max(theta, 0.0) * res.gain ** 2 * (reads if s.binning_mode == "average" else 1.0 / reads)))
    if sigma_e > s.read_noise_e:  # the reset part of the read noise is at most the whole of it
        return (f"an extra white noise of {sigma_e:.3g} e- rms per read, {sigma_e / s.read_noise_e:.2g} x the camera's "
                f"read noise ({s.read_noise_e:.3g} e-): a reset noise is a part of the read noise its bias frames "
                "measure, not more than all of it; on a lit frame it is the light's own scatter (PRNU), which a "
                "uniform light cannot tell from it")
    return ""


_KTC_SIGNATURE = VarianceSignature(
    lambda res: np.ones(1), _ktc_params,
    lambda p, res: (f"white scatter independent of signal and exposure, as from a {p['capacitance_ff']:.3g} fF "
                    "sense node: kTC reset noise (or a read noise above the data sheet)"),
    pattern="extra variance constant over the frame", check=_ktc_check)
_BIAS_SIGNATURE = LinearSignature(_bias_variants, _bias_words, pattern="additive ramps/bowl, independent of signal",
                                  extra_k=0)
#: an offset of the read-out and a response to a light of one level (a flat) of the same shape are one image
_BIAS_SIGNATURE.untold = offset_response_untold(("vignetting",))
#: the largest electronic crosstalk coefficient a camera shows [1]: measured coefficients are 1e-5 .. 1e-3
#: (LSST sensors, Snyder et al. 2021, JATIS 7, 048002; DECam, Bernstein et al. 2017, PASP 129, 114502)
CROSSTALK_MAX = 0.01
#: the largest |coefficient| the fit returns at all (the plugin's bound) [1]
CROSSTALK_FIT_MAX = 0.1
#: the channel counts the crosstalk search tries: the read-out window split into this many equal stripes
#: [channels] (every count up to 8, and 16: multi-output CCDs and CMOS read 2, 4, 8 or 16 ports; odd
#: counts cost nothing to try)
CROSSTALK_CHANNELS = (2, 3, 4, 5, 6, 7, 8, 16)
#: narrowest channel the search tries [output pixels]
CROSSTALK_MIN_WIDTH = 16
#: delays of the echo [read-out pixels] and e-folding lengths of its exponential tail [read-out pixels] the
#: search tries (the tail refined continuously between the grid's neighbours); a fit at the largest of either
#: is flagged (the echo may come later or last longer than the family reaches). Delays up to 7 read-out pixels:
#: the range searched is not a physical bound (an echo coupled between channels whose read-out paths differ in
#: latency by a few clock cycles lands that many pixels from its source); with delays up to 3 only, an echo
#: delayed by 2 and smeared over the next two pixels fitted best at 3 and was refused at the bound. Tails up to 4
#: read-out pixels for the same reason: an echo delayed by 1 and spread over three lags (0.6, 0.3, 0.1) fits best
#: as an undelayed tail of 2.5 px (one parameter fewer), which a grid ending at 2 px refused at its bound
CROSSTALK_DELAYS = (0, 1, 2, 3, 4, 5, 6, 7)
CROSSTALK_TAILS = (0.0, 0.25, 0.5, 1.0, 2.0, 4.0)
#: layouts (the best by their delays alone) whose every kernel (delays and tails) is tried [layouts]
CROSSTALK_TOP_LAYOUTS = 2


def crosstalk_signal(res) -> np.ndarray:
    """The model's signal [ADU] whose echoes the diagnosis looks for: the bias-free signal (what
    :class:`Crosstalk` acts on) without the background light (:attr:`~detector.signatures.Residuals.
    background_photo_adu`: the sky or the flat screen).

    The background's echo carries no copy of anything: a uniform background sends the same ``(n - 1) alpha``
    times its level into every channel, a global level the comparison already profiles; only its slow
    variation (a vignetted sky, a per cent of it, times ``alpha`` ~1e-3) would be left, far below the noise.
    The sources' echoes are the crosstalk's signature. Coupling the sources alone is also the form that holds
    when the coupling is not linear down to the background: crosstalk measured on bright sources
    (Freyhammer et al. 2001, Exp. Astron. 12, 147) or applied above a threshold of the aggressor's signal
    (an echo of the signal above the channel's background) has no echo of the sky, while the plugin's
    linear form echoes it as a level; both are this template to within the levels."""
    bg = res.background_photo_adu
    return (res.model_adu - res.sensor.bias_adu * res.adu_sum - bg).astype(np.float32)


class CrosstalkLayout:
    """The model's signal ``sig`` [ADU] read as ``n`` channels (equal stripes of columns, every second one read
    from the other side when ``mirrored``): the sum of all channels in read-out order, and the crosstalk
    templates at lag ``m`` [read-out pixels] gathered at flat pixel indices: at a pixel of channel ``j`` read
    at position ``p``, ``sum_{i != j} sig_i(p - m)`` (0 for ``p < m``). A kernel's template is
    ``kernel @ taps`` (the same as :func:`channel_crosstalk` with ``alpha = 1``, minus ``sig``)."""

    def __init__(self, sig: np.ndarray, n: int, mirrored: bool):
        self.sig, self.n, self.mirrored = sig, int(n), bool(mirrored)
        h, w = sig.shape
        self.width, self.wc = w, w // self.n
        view = sig[:, : self.wc * self.n].reshape(h, self.n, self.wc)
        if mirrored:
            self.total = view[:, 0::2].sum(axis=1) + view[:, 1::2, ::-1].sum(axis=1)
        else:
            self.total = view.sum(axis=1)
        self._padded: dict[int, np.ndarray] = {}

    def _others(self, lags: int) -> np.ndarray:
        """``sum_{i != j} sig_i`` of every channel ``j`` in read-out order, ``lags`` zeros before each row's
        first pixel: (rows, n, lags + wc), float32 (one fancy index per lag then reads a lag's template)."""
        if lags not in self._padded:
            h = self.sig.shape[0]
            own = self.sig[:, : self.wc * self.n].reshape(h, self.n, self.wc).copy()
            if self.mirrored:
                own[:, 1::2] = own[:, 1::2, ::-1]
            out = np.zeros((h, self.n, lags + self.wc), np.float32)
            out[:, :, lags:] = self.total[:, None, :] - own
            self._padded = {lags: out}
        return self._padded[lags]

    def taps(self, idx: np.ndarray, lags: int) -> np.ndarray:
        """The echo templates of lags ``0 .. lags - 1`` at flat pixel indices ``idx``: (lags, pixels), float64."""
        lags = max(int(lags), 1)
        others = self._others(lags).ravel()
        y, x = np.divmod(np.asarray(idx, np.int64), self.width)
        wc, row = self.wc, self.n * (lags + self.wc)
        valid = x < wc * self.n
        j = np.minimum(x // wc, self.n - 1)
        q = x - j * wc
        p = np.where((j % 2 == 1) & self.mirrored, wc - 1 - q, q)
        # where lag 0 of each pixel sits in ``others``; lag m is m places before it (the zeros: p < m)
        # (a pixel beyond the last whole channel reads the first row's leading zeros: no coupling there)
        base = np.where(valid, y * row + j * (lags + wc) + lags + p, lags - 1)
        out = np.empty((lags, idx.size))
        for m in range(lags):
            out[m] = others[base - m]
        return out


def profiled_normal(res, t: np.ndarray, idx: np.ndarray, r: np.ndarray, w: np.ndarray):
    """The normal equations ``(A, b)`` of templates ``t`` (templates, pixels) at flat pixels ``idx`` with the
    global levels profiled out (Frisch-Waugh-Lovell, as :func:`detector.signatures.fit_linear`):
    ``A = T'WT - T'WN (N'WN)^-1 N'WT``, ``b = T'Wr - T'WN (N'WN)^-1 N'Wr``. Any combination ``K @ t`` then
    fits with coefficient ``K'b / K'AK`` and delta chi2 ``-(K'b)^2 / K'AK``."""
    n = res.level_values(idx)
    tw = t * w
    a, b = tw @ t.T, tw @ r
    raw = np.diag(a).copy()
    if n.size:
        nw = n * w
        nn = nw @ n.T
        tn = tw @ n.T
        a = a - tn @ np.linalg.solve(nn, tn.T)
        b = b - tn @ np.linalg.solve(nn, nw @ r)
    return a, b, raw


@dataclass
class CrosstalkVariant(Variant):
    """A crosstalk template of one layout and kernel (its form, for the refinement and the parameters)."""

    n: int = 2
    mirrored: bool = False
    delay: int = 0
    tail: float = 0.0


def crosstalk_params(c: float, n: int, mirrored: bool, delay: int = 0, tail: float = 0.0) -> dict | None:
    """The plugin's parameters of a fitted coefficient ``c`` (None outside the plugin's bounds); the delay and
    the tail only when the echo has them (the instantaneous form keeps the plugin's original keys)."""
    c = float(np.ravel(c)[0])
    if not (abs(c) <= CROSSTALK_FIT_MAX and c != 0):
        return None
    p = {"n_channels": int(n), "alpha": round(c, 7), "mirrored": bool(mirrored)}
    if delay:
        p["delay_px"] = int(delay)
    if tail:
        p["tail_px"] = round(float(tail), 3)
    return p


def crosstalk_variant(res, n: int, mirrored: bool, delay: int = 0, tail: float = 0.0,
                      layout: CrosstalkLayout | None = None, sig: np.ndarray | None = None) -> CrosstalkVariant:
    """The template of one crosstalk form: its map built by the plugin's own :func:`channel_crosstalk` (with
    ``alpha = 1``) when the winner needs it, its values at pixels gathered from the lags of ``layout`` (or of a
    layout built for the call and dropped: a search over many forms keeps no frame-sized array per form)."""
    if sig is None:
        sig = crosstalk_signal(res) if layout is None else layout.sig
    kern = crosstalk_kernel(delay, tail)
    cache: dict = {}

    def maps():
        if "t" not in cache:
            t = sig.copy()
            channel_crosstalk(t, n, 1.0, mirrored, delay, tail)
            t -= sig
            cache["t"] = [t]
        return cache["t"]

    def at(idx):
        if "t" in cache:  # the map exists: read it (the same numbers the final fit and the apply use)
            return cache["t"][0].ravel()[idx].astype(np.float64)[None, :]
        lay = layout if layout is not None else CrosstalkLayout(sig, n, mirrored)
        return (kern @ lay.taps(idx, kern.size))[None, :]

    label = f"{n} channels{' mirrored' if mirrored else ''}"
    if delay:
        label += f", echo delayed {delay} px"
    if tail:
        label += f", tail {tail:.2g} px"
    return CrosstalkVariant(maps, lambda c: crosstalk_params(c, n, mirrored, delay, tail), label, at,
                            n=n, mirrored=mirrored, delay=delay, tail=tail)


def _crosstalk_layouts(res):
    """The channel layouts the search tries (count, mirrored), narrowest channels excluded."""
    w = res.data_adu.shape[1]
    return [(n, m) for n in CROSSTALK_CHANNELS if w // n >= CROSSTALK_MIN_WIDTH for m in (True, False)]


def _crosstalk_variants(res):
    """The instantaneous form of every layout (the series' first pass; :meth:`CrosstalkSignature.fit`
    searches layouts and kernels together on a single frame)."""
    sig = crosstalk_signal(res)
    for n, mirrored in _crosstalk_layouts(res):
        yield crosstalk_variant(res, n, mirrored, sig=sig)


def _crosstalk_kernels(v, res):
    """Every delay and tail of the best layout (the series' refinement)."""
    lay = CrosstalkLayout(crosstalk_signal(res), v.n, v.mirrored)
    for d in CROSSTALK_DELAYS:
        for t in CROSSTALK_TAILS:
            if d or t:
                yield crosstalk_variant(res, v.n, v.mirrored, d, t, layout=lay)


def crosstalk_k(delay: int, tail: float) -> int:
    """Parameters a crosstalk form adds to its coefficient and its layout choice: one for a delay, one for a
    tail (the instantaneous form is the nested model without them)."""
    return int(bool(delay)) + int(bool(tail))


class CrosstalkSignature(LinearSignature):
    """Crosstalk between read-out channels: every channel receives ``alpha`` times the other channels' signal
    in read-out order through a causal kernel (:func:`crosstalk_kernel`: a delay of 0 .. 7 read-out pixels and
    an optional exponential tail), ``alpha`` of either sign.

    The single-frame fit searches every layout (:data:`CROSSTALK_CHANNELS`, mirrored or not) and kernel
    (:data:`CROSSTALK_DELAYS` x :data:`CROSSTALK_TAILS`) at once: the templates of lags ``0 .. L`` are
    gathered once per layout on the search sample and their level-profiled normal equations
    (:func:`profiled_normal`) give every kernel's fit as ``K'b / K'AK``; the tail of the best is refined
    continuously; the winner's map is the plugin's own :func:`channel_crosstalk` and it is refitted as any
    linear variant. Parameters counted in the BIC: ``alpha``, the layout (one choice), and one more each for
    a delay and a tail when the form has them (:func:`crosstalk_k`); the search compares forms by that
    penalised delta BIC, so the instantaneous form of the plugin wins unless a delay or a tail pays for itself.
    """

    def fit(self, res, name):
        from scipy import optimize

        ctx = search_sample(res)
        idx, r, w = ctx["idx"], ctx["r"], ctx["w"]
        if not idx.size:
            return None
        sig = crosstalk_signal(res)
        ln_n = float(np.log(max(res.n_fit, 2)))
        lags = max(CROSSTALK_DELAYS) + crosstalk_kernel(0, max(CROSSTALK_TAILS)).size

        def padded(kern, size):
            out = np.zeros(size)
            out[: min(kern.size, size)] = kern[:size]
            return out

        kernels = [(d, t, crosstalk_kernel(d, t)) for d in CROSSTALK_DELAYS for t in CROSSTALK_TAILS]

        def gain(a, b, raw, kern):
            den = float(kern @ a @ kern)
            if den <= 1e-9 * max(float(kern * kern @ raw), 1e-300):
                return None
            num = float(kern @ b)
            return num / den, -num * num / den * ctx["scale"]

        def search(lay, nab, kerns, best):
            for d, t, kern in kerns:
                g = gain(*nab, padded(kern, nab[1].size))
                if g is None or crosstalk_params(g[0], lay.n, lay.mirrored, d, t) is None:
                    continue
                score = g[1] + crosstalk_k(d, t) * ln_n
                if best is None or score < best[0]:
                    best = (score, lay.n, lay.mirrored, d, t, lay, nab)
            return best

        # every layout with the delays alone (lags 0 .. max delay), then every kernel for the best layouts: the
        # layout decides where the echoes land, the kernel only how they spread along a row
        short = max(CROSSTALK_DELAYS) + 1
        screen = []
        for n, mirrored in _crosstalk_layouts(res):
            lay = CrosstalkLayout(sig, n, mirrored)
            nab = profiled_normal(res, lay.taps(idx, short), idx, r, w)
            found = search(lay, nab, [k for k in kernels if not k[1]], None)
            if found is not None:
                screen.append(found)
        screen.sort(key=lambda f: f[0])
        best = screen[0] if screen else None
        for found in screen[:CROSSTALK_TOP_LAYOUTS]:
            lay = found[5]
            best = search(lay, profiled_normal(res, lay.taps(idx, lags), idx, r, w), kernels, best)
        if best is None:
            return None
        _, n, mirrored, d, t, _lay, nab = best
        if t:  # the tail between its grid neighbours (the smallest tried: down to half of it)
            i = CROSSTALK_TAILS.index(t)
            lo = CROSSTALK_TAILS[i - 1] if i > 1 else t / 2
            hi = CROSSTALK_TAILS[min(i + 1, len(CROSSTALK_TAILS) - 1)]

            def m2l(x):
                g = gain(*nab, padded(crosstalk_kernel(d, x), lags))
                return g[1] if g is not None else 0.0

            opt = optimize.minimize_scalar(m2l, bounds=(lo, hi), method="bounded", options={"xatol": 1e-3})
            if m2l(float(opt.x)) < m2l(t):
                t = round(float(opt.x), 3)
        v = crosstalk_variant(res, n, mirrored, d, t, sig=sig)
        v.maps()  # the winner's map: the plugin's own function (its values are read from it from now on)
        values = (lambda i: v.values(i, res.data_adu.shape))
        if ctx["full"]:
            c, dm2 = fit_linear(res, values, idx, r, w)
        else:
            fidx, _, fw = res.flat_profiled()
            c, dm2 = fit_linear(res, values, fidx, res.flat()[1], fw)
        params = v.to_params(c)
        if params is None:
            return None
        return self._finish(res, name, v, c, dm2, params)

    def _finish(self, res, name, v, c, d, params):
        fit = super()._finish(res, name, v, c, d, params)
        return replace(fit, k=fit.k + crosstalk_k(getattr(v, "delay", 0), getattr(v, "tail", 0.0)))


def _crosstalk_check(fit, res) -> str:
    """Crosstalk copies compact bright sources into the other channels, by a coefficient of at most ~1e-3:
    a coefficient of per cents is a structure of the light itself taken for copies; and on a flat-screen
    frame every channel's copy of the uniform light is uniform, a step between channels (a gain), not a copy
    of a source. A delay or a tail at the largest the search tries means the echo's form lies beyond the
    family (or the pattern is not an echo): flagged, as a parameter at its bound."""
    p = fit.params
    a = abs(p["alpha"])
    if a > CROSSTALK_MAX:
        return (f"a coupling of {a:.3g} is {a / 1e-3:.0f} times the largest crosstalk measured in cameras "
                f"(~1e-3): a pattern of the light taken for copies of sources")
    if res.light_source == "flat":
        return ("on a flat-screen frame the copies of the uniform light are uniform per channel: a step between "
                "channels (gains), not crosstalk of sources")
    if p.get("delay_px", 0) >= max(CROSSTALK_DELAYS):
        return (f"the echo's fitted delay of {p['delay_px']} read-out pixels sits at the largest the search tries: "
                "the form cannot follow the data further (a later echo, or not an echo of the sources)")
    if p.get("tail_px", 0.0) >= max(CROSSTALK_TAILS) * (1 - 1e-3):
        return (f"the echo's fitted tail of {p['tail_px']:.3g} read-out pixels sits at the largest the search tries: "
                "a smear longer than a settling tail (not an echo of the sources)")
    return ""


def _crosstalk_words(p, res) -> str:
    form = ""
    if p.get("delay_px") or p.get("tail_px"):
        parts = ([f"delayed by {p['delay_px']} read-out px"] if p.get("delay_px") else []) + \
                ([f"with a {p['tail_px']:.2g} px tail"] if p.get("tail_px") else [])
        form = ", " + " ".join(parts)
    sign = " (an undershoot)" if p["alpha"] < 0 else ""
    return (f"faint copies of bright sources in the other {p['n_channels'] - 1} read-out channels, "
            f"{p['alpha']:.2g} of the source{sign}{form}: crosstalk")


_CROSSTALK_SIGNATURE = CrosstalkSignature(
    _crosstalk_variants, _crosstalk_words, pattern="ghost copies of bright sources in other channels",
    refine=_crosstalk_kernels, check=_crosstalk_check)


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
            n = standard_normal_f32(tile.rng(self.name), data.shape)
            n *= np.float32(sigma)
            data += n


class BiasGradientParams(EffectParams):
    gradient_x_adu: float = Field(5.0, ge=-1e4, le=1e4, description="bias change across the sensor width [ADU]")
    gradient_y_adu: float = Field(0.0, ge=-1e4, le=1e4, description="bias change across the sensor height [ADU]")
    quadratic_adu: float = Field(0.0, ge=-1e4, le=1e4, description="bias bowl: corner minus centre [ADU]")
    column_profile_adu: list[float] = Field(default_factory=list, max_length=64,
                                            description="cosine-series coefficients c_k of a fixed pattern along "
                                            "the serial direction, sum_k c_k cos(k pi x / (W - 1)) [ADU]")
    field_adu: FieldCoefficients = field_coefficients("ADU", "a smooth fixed pattern")
    field_box_px: FieldBox = field_box("field_adu")


@register_effect
class BiasGradient(Effect):
    """Spatial structure of the bias level: linear ramps and a radial bowl [ADU], the same every frame.

    Seen in bias frames of large CMOS and CCD sensors (amplifier warm-up, reference-voltage drop along the
    column bus; Janesick 2007 ch. 9). Deterministic, zero at the sensor centre. ``column_profile_adu`` adds
    a fixed pattern of any smooth shape along the serial direction (:func:`bias_profile_adu`), ``field_adu`` a
    smooth 2-D one (:func:`bias_field_adu`).
    """

    name = "bias_gradient"
    field_kind = "additive"
    scaling = "none"
    identity = {"gradient_x_adu": 0.0, "gradient_y_adu": 0.0, "quadratic_adu": 0.0}
    stages = (Stage.ADU,)
    Params = BiasGradientParams
    signature = _BIAS_SIGNATURE

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        p, s = self.params, self.sensor
        ys, xs = tile.pixel_centres()
        # without a row term every row is the same (gx u + 0 v = gx u exactly): one row, broadcast
        rows = ys[:1] if not (p.gradient_y_adu or p.quadratic_adu) and ys.size else ys
        data += bias_shape_adu(rows, xs, s.sensor_height_px, s.sensor_width_px, p.gradient_x_adu,
                               p.gradient_y_adu, p.quadratic_adu)
        if p.column_profile_adu:
            data += bias_profile_adu(xs, s.sensor_width_px, p.column_profile_adu)[None, :]
        if p.field_adu:
            data += bias_field_adu(ys, xs, s.sensor_height_px, s.sensor_width_px, p.field_adu, p.field_box_px or None)


class CrosstalkParams(EffectParams):
    n_channels: int = Field(4, ge=2, le=64, description="read-out channels (vertical stripes) across the sensor [channels]")
    alpha: float = Field(1e-3, ge=-0.1, le=0.1, description="coupling coefficient victim/source [1]")
    mirrored: bool = Field(True, description="every second channel read from the other side")
    delay_px: int = Field(0, ge=0, le=64, description="delay of the echo after the aggressor's pixel, in read-out "
                          "order [read-out pixels]")
    tail_px: float = Field(0.0, ge=0, le=64, description="e-folding length of the echo's exponential tail "
                           "(0: none) [read-out pixels]")


@register_effect
class Crosstalk(Effect):
    """Electronic crosstalk between read-out channels: a bright source in one channel leaves a faint
    (possibly mirrored) ghost of ``alpha`` times its signal in every other channel.

    Linear coupling model of multi-channel read-out (LSST crosstalk, Snyder et al. JATIS 7, 2021; Moore et
    al. SPIE 5499). Channels are stripes of the read-out window; parts of channels outside a region of
    interest do not couple. ``alpha`` may be negative (an undershoot); with ``delay_px`` / ``tail_px`` the
    echo follows the aggressor's pixel through a causal kernel in read-out order (:func:`crosstalk_kernel`:
    the victim amplifier's settling through the shared supply or clock; Freyhammer et al. 2001, Exp. Astron.
    12, 147). The defaults (0, 0) are the instantaneous coupling, unchanged.
    """

    name = "crosstalk"
    scaling = "signal"
    identity = {"alpha": 0.0}
    stages = (Stage.ADU,)
    Params = CrosstalkParams
    signature = _CROSSTALK_SIGNATURE

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        p = self.params
        channel_crosstalk(data, p.n_channels, p.alpha, p.mirrored, p.delay_px, p.tail_px)
