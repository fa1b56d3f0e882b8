"""A dark-current gradient: the dark rate changing across the sensor because its temperature does.

Dark current is thermally generated, ``D(T) ~ T^3 exp(-E_g / 2kT)`` for the depletion (mid-gap) component,
which doubles every ~6-7 K near room temperature (Janesick 2001, Scientific CCDs, sect. 7.2, eq. 7.4;
Widenhorn et al. 2002, J. Appl. Phys. 92, 7434). A cold finger at one side of the die, or a warm read-out
amplifier, leaves a temperature gradient of a few tenths of a kelvin to a few kelvin across the sensor.

Three forms, which add:

* the linear ramp (``gradient_x_e_per_s``, ``gradient_y_e_per_s``): to first order in ``dT`` the dark rate
  changes by ``dD = D ln2 dT / T_2`` (``T_2`` the doubling interval), a ramp of the dark rate [e-/s];
* the exponential law (``temperature_x_k``, ``temperature_y_k``): a linear temperature field
  ``T = tx u + ty v`` [K] (``u, v`` in -0.5..0.5 across the sensor) changes the dark rate by
  ``D0 (2^(T / T_2) - 1)``, ``D0`` the sensor's dark rate and ``T_2`` from the sensor's temperature
  (:func:`doubling_interval_k`): a ramp with curvature along the gradient, its curvature fixed by its slope
  and level (``d^2D/dT^2 = (ln2 / T_2) dD/dT``);
* a smooth field of any low order (``field_e_per_s``): the 2-D cosine series of
  :func:`detector.effects.readout.bias_field_adu` over the sensor [e-/s], a die's temperature field with more
  than one heat source or sink; in the diagnosis offered on frames without light, in the same basis as a bias
  structure of that frame, so that on one dark the forms do not decide between them, the dark charge's shot
  noise does (a bias frame, or a dark of another exposure, tells them apart).

Unlike a bias ramp (an offset of the read-out, the same in every frame) it grows with exposure time and
carries its shot noise, which tells the two apart in a dark series (``newtsim diagnose --series``). On one
dark frame the exponential form's rank-one curvature (along the gradient, tied to its slope) against a
bias's ramps and centred bowl, and the dark charge's shot noise, are what tell them apart.
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from ..signatures import LinearSignature, Variant, dark_field_untold, fit_linear, profiled_chi2, search_sample
from .base import Effect, EffectParams, Stage, Tile, register_effect
from .readout import (
    FieldBox,
    FieldCoefficients,
    bias_field_adu,
    cosine_field_variants,
    field_box,
    field_coefficients,
    field_on_window,
    sensor_box,
    sensor_scale_orders,
    window_box,
)

#: silicon band gap [eV] near room temperature (Sze & Ng 2007, Physics of Semiconductor Devices, 3rd ed.,
#: Table 1.2 / Appendix G: 1.12 eV at 300 K)
SILICON_GAP_EV = 1.12
#: Boltzmann constant [eV/K] (CODATA 2018, exact)
BOLTZMANN_EV_PER_K = 8.617333262e-5
#: the largest temperature difference across a sensor's die a temperature gradient may explain [K] (a cooled
#: sensor's die spans a few cm on one cold plate: a few kelvin at most, 20 K is already generous)
MAX_TEMPERATURE_SPAN_K = 20.0

# --- pure functions ---------------------------------------------------------------------------------------

def sensor_uv(ys: np.ndarray, xs: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Sensor coordinates [1] in -0.5 .. 0.5 from the first to the last row/column (0 at the centre)."""
    u = (np.asarray(xs, np.float64) / max(width - 1, 1) - 0.5).astype(np.float32)
    v = (np.asarray(ys, np.float64) / max(height - 1, 1) - 0.5).astype(np.float32)
    return u, v


def doubling_interval_k(temperature_c: float, gap_ev: float = SILICON_GAP_EV) -> float:
    """The temperature interval [K] over which the (depletion, mid-gap) dark current doubles at
    ``temperature_c`` [deg C]: ``T_2 = ln 2 / (d ln D / dT)`` with ``D ~ T^3 exp(-E_g / 2kT)`` (Janesick 2001,
    Scientific CCDs, sect. 7.2, eq. 7.4; Widenhorn et al. 2002, J. Appl. Phys. 92, 7434), so
    ``d ln D / dT = 3 / T + E_g / (2 k T^2)``, ``T`` [K], ``E_g`` the band gap [eV] (silicon 1.12 eV).
    About 6.1 K at -20 C, 7.0 K at 0 C, 8.1 K at +20 C (the measured 6-7 K near room temperature mixes in
    the diffusion component, ``E_g / kT``, which doubles faster)."""
    t = float(temperature_c) + 273.15
    if t <= 0:
        raise ValueError(f"temperature {temperature_c} C is not above absolute zero")
    return float(np.log(2.0) / (3.0 / t + gap_ev / (2.0 * BOLTZMANN_EV_PER_K * t * t)))


def thermal_exponent(u, v, tx_k: float, ty_k: float, t2_k: float):
    """The exponent ``x = ln2 (tx u + ty v) / T_2`` of the dark current's doubling law at sensor fractions
    ``u``, ``v`` (-0.5 .. 0.5, broadcasting; float64): the dark rate there is ``D0 e^x``."""
    return (np.log(2.0) / t2_k) * (tx_k * np.asarray(u, np.float64) + ty_k * np.asarray(v, np.float64))


def thermal_rate(ys: np.ndarray, xs: np.ndarray, height: int, width: int, dark_e_per_s: float,
                 tx_k: float, ty_k: float, t2_k: float) -> np.ndarray:
    """The dark-rate change [e-/s/pixel] of a linear temperature field on the grid of sensor rows ``ys`` and
    columns ``xs``: ``D0 (2^((tx u + ty v) / T_2) - 1)``, ``tx`` / ``ty`` the temperature difference [K] across
    the sensor width / height, ``D0`` the dark rate at the centre [e-/s], ``T_2`` the doubling interval [K]."""
    u, v = sensor_uv(ys, xs, height, width)
    return (dark_e_per_s * np.expm1(thermal_exponent(u[None, :], v[:, None], tx_k, ty_k, t2_k))).astype(np.float32)


def gradient_rate(ys: np.ndarray, xs: np.ndarray, height: int, width: int, gx: float, gy: float) -> np.ndarray:
    """The dark-rate change [e-/s/pixel] on the grid of sensor rows ``ys`` and columns ``xs``:
    ``gx u + gy v``, ``gx`` / ``gy`` the change across the sensor width / height, zero at the centre."""
    u, v = sensor_uv(ys, xs, height, width)
    return (np.float32(gx) * u[None, :] + np.float32(gy) * v[:, None]).astype(np.float32)


# --- diagnosis signature (detector.signatures) ------------------------------------------------------------

#: Gauss-Newton iterations of the exponential form on the search sample, and its convergence [K]
GN_ITERATIONS = 8
GN_TOL_K = 1e-3
#: the largest temperature difference the search explores [K] (beyond: not a temperature gradient)
GN_MAX_K = 60.0


def _gauss_newton(res, model, linear: Variant, slope_per_k: float) -> np.ndarray:
    """Temperatures (tx, ty) [K] minimising the level-profiled chi2 of ``r - m(t)`` on the search sample:
    Gauss-Newton from the linear ramp's fit (``t0 = g / slope_per_k``, ``slope_per_k = D0 ln2 / T_2``), step
    halving while the chi2 does not fall, at most GN_ITERATIONS steps; zeros when the start is not finite."""
    ctx = search_sample(res)
    idx, r, w = ctx["idx"], ctx["r"], ctx["w"]
    g, _ = fit_linear(res, lambda i: linear.values(i, res.data_adu.shape), idx, r, w)
    t = np.clip(np.asarray(g, np.float64) / slope_per_k, -GN_MAX_K, GN_MAX_K)
    if not np.all(np.isfinite(t)):
        return np.zeros(2)
    chi = profiled_chi2(res, idx, r - model(t, idx, False)[0], w)
    for _ in range(GN_ITERATIONS):
        m0 = model(t, idx, False)[0]
        step, _ = fit_linear(res, lambda i, t=t: model(t, i)[1], idx, r - m0, w)
        accepted = False
        for _half in range(6):  # step halving: the exponential is convex along the gradient
            t_new = np.clip(t + step, -GN_MAX_K, GN_MAX_K)
            chi_new = profiled_chi2(res, idx, r - model(t_new, idx, False)[0], w)
            if chi_new <= chi:
                accepted = True
                break
            step = step / 2
        if not accepted:
            break
        t, chi = t_new, chi_new
        if np.max(np.abs(step)) < GN_TOL_K:
            break
    return t


def _variants(res):
    """The linear ramp, then the exponential law fitted by Gauss-Newton on the search sample, started from the
    ramp (``t0 = g T_2 / (D0 ln 2)``) and offered as its linearisation about the converged temperatures
    ``t*``: templates the Jacobian ``J = dm/dt`` at ``t*`` and fixed part ``m(t*) - J t*``
    (:attr:`detector.signatures.Variant.fixed`), so the coefficients are the temperatures themselves and, at
    convergence, the fitted mean change is the exponential model ``m(t*)`` exactly, with 2 parameters like
    the ramp."""
    s = res.sensor
    unit = np.float32(res.adu_per_rate)  # ADU per (e-/s) of dark rate
    u, v = sensor_uv(res.ys, res.xs, s.sensor_height_px, s.sensor_width_px)

    def to_params(c):
        if not (abs(c[0]) <= 1e6 and abs(c[1]) <= 1e6) or res.exptime_s <= 0:
            return None
        return {"gradient_x_e_per_s": round(float(c[0]), 6), "gradient_y_e_per_s": round(float(c[1]), 6),
                "temperature_x_k": 0.0, "temperature_y_k": 0.0}

    linear = Variant([(unit * u)[None, :], (unit * v)[:, None]], to_params, label="linear ramp")
    yield linear
    if res.exptime_s > 0 and not np.any(res.photo_adu > 0):
        # on a frame without light, a smooth dark-rate field of any low-order shape (a die's temperature field
        # with more than one heat source or sink: not a plane, its curvature not the doubling law's), in the
        # basis a bias structure of the same frame is offered in (detector.effects.readout.cosine_field_variants,
        # over the window the frame sees): one dark frame tells the two only by the dark charge's shot noise, not
        # by their forms. (On a frame with light a smooth added field of any shape is the light's, the same charge.)
        box = window_box(res)
        yield from cosine_field_variants(res, unit, box, orders=sensor_scale_orders(res), to_params=lambda coef: {
            "gradient_x_e_per_s": 0.0, "gradient_y_e_per_s": 0.0, "temperature_x_k": 0.0, "temperature_y_k": 0.0,
            "field_e_per_s": [[float(x) for x in row] for row in coef], "field_box_px": box})
    d0 = float(s.dark_current_e_per_s)
    if res.exptime_s <= 0 or d0 <= 0:
        return
    t2 = doubling_interval_k(s.temperature_c)
    kappa = np.log(2.0) / t2  # [1/K]
    amp = float(unit) * d0  # ADU per unit of 2^(T/T_2) - 1
    width = res.data_adu.shape[1]
    u64, v64 = u.astype(np.float64), v.astype(np.float64)

    def model(t, idx, jacobian=True):  # (value, Jacobian (2, pixels)) [ADU], [ADU/K] at flat pixels idx
        uu, vv = u64[idx % width], v64[idx // width]
        x = thermal_exponent(uu, vv, t[0], t[1], t2)
        e = np.exp(x)
        if not jacobian:
            return amp * (e - 1.0), x, e
        ak = amp * kappa
        return amp * (e - 1.0), np.stack([ak * uu * e, ak * vv * e])

    state: dict = {}

    def solve() -> np.ndarray:
        """The converged temperatures t* [K] (computed once, when the variant is first evaluated: a series,
        which fits linear forms only, never pays for it)."""
        if "t" not in state:
            state["t"] = _gauss_newton(res, model, linear, d0 * kappa)
        return state["t"]

    def templates(idx):
        return model(solve(), idx)[1]

    def fixed(idx):  # m(t*) - J t* = amp (e - 1 - x e), x = kappa T*
        _, x, e = model(solve(), idx, jacobian=False)
        return amp * (e - 1.0 - x * e)

    def to_params_exp(c):
        if res.exptime_s <= 0 or not np.all(np.isfinite(c)) or np.max(np.abs(c)) > GN_MAX_K:
            return None
        return {"gradient_x_e_per_s": 0.0, "gradient_y_e_per_s": 0.0,
                "temperature_x_k": round(float(c[0]), 4), "temperature_y_k": round(float(c[1]), 4)}

    def maps():  # the Jacobian on the whole frame (float32, broadcast)
        t_star = solve()
        e = np.exp(thermal_exponent(u64[None, :], v64[:, None], t_star[0], t_star[1], t2)).astype(np.float32)
        a = np.float32(amp * kappa)
        return [a * u[None, :] * e, a * v[:, None] * e]

    yield Variant(maps, to_params_exp, label=f"exponential law (doubling every {t2:.2f} K)", at=templates, fixed=fixed)


def _check(fit, res) -> str:
    """A temperature gradient modulates the sensor's dark current: within the window the frame sees it cannot
    take the dark rate (:func:`base_rate`) below zero, and the temperature difference the doubling law needs
    for its lowest and highest rate there stays within MAX_TEMPERATURE_SPAN_K: for the linear ramp
    (:func:`ramp_span_k`) and a smooth field (:func:`field_span_k`) alike; in the exponential form (which never
    goes below zero) the temperature difference corner to corner, ``|tx| + |ty|``, stays within it. (The ramp
    is a first-order form of the doubling law: extrapolated beyond the window it is no longer the law, so the
    window, which the data constrain, is where it is tested.)"""
    p = fit.params
    span = abs(p.get("temperature_x_k", 0.0)) + abs(p.get("temperature_y_k", 0.0))
    if p.get("field_e_per_s"):
        span = field_span_k(p["field_e_per_s"], res, p.get("field_box_px") or None)
        if span is None:
            return ("the smooth dark-rate field would take the dark rate below zero within the window (its lowest "
                    f"point more than the dark rate, {base_rate(res):.3g} e-/s, below it): a temperature field "
                    "cannot do that; an offset structure (bias) or a light taken for dark current")
    gx, gy = p.get("gradient_x_e_per_s", 0.0), p.get("gradient_y_e_per_s", 0.0)
    if gx or gy:
        ramp = ramp_span_k(gx, gy, res)
        if ramp is None:
            return (f"the dark-rate ramp ({gx:+.3g}, {gy:+.3g} e-/s across the sensor) would take the dark rate "
                    f"below zero within the window (the frame's dark rate is {base_rate(res):.3g} e-/s): a "
                    "temperature gradient cannot do that; an offset ramp (bias) or a light taken for dark current")
        span = max(span, ramp)
    if span > MAX_TEMPERATURE_SPAN_K:
        return (f"the sensor would be {span:.3g} K warmer at one corner than at the opposite one, more than "
                f"{MAX_TEMPERATURE_SPAN_K:.0f} K across a sensor's die: not a temperature gradient; an offset "
                "ramp (bias) or a light taken for dark current")
    return ""


def frame_dark_rate(res) -> float:
    """A frame without light: its own mean dark rate [e-/s per sensor pixel], the model's median dark rate plus
    the residual's median (data - model on the fitted pixels) in dark rate; 0 on a frame with light (whose
    residual level is the light's too). A dark-rate field the model lacks raises the frame's mean dark rate by its
    own mean: the rate it modulates is the frame's, not the model's. (A bias offset moves the same median; one
    dark frame does not tell the two, a bias frame does.)"""
    if res.exptime_s <= 0 or not res.dark_e.size or np.any(res.photo_adu > 0) or not np.any(res.fit):
        return 0.0
    unit = res.exptime_s * res.pixel_sum / res.gain  # ADU per (e-/s) of dark rate per sensor pixel
    excess = float(np.median((res.data_adu - res.model_adu)[res.fit]))
    return float(np.median(res.dark_e)) / (res.exptime_s * res.pixel_sum) + excess / unit


def base_rate(res) -> float:
    """The dark rate [e-/s per sensor pixel] a temperature field modulates: the sensor's, or the frame's
    modelled median dark rate, or on a frame without light its measured one (:func:`frame_dark_rate`), whichever
    is the largest."""
    mean_rate = float(np.median(res.dark_e)) / max(res.exptime_s * res.pixel_sum, 1e-12) if res.dark_e.size else 0.0
    return max(float(res.sensor.dark_current_e_per_s), mean_rate, frame_dark_rate(res))


def ramp_span_k(gx: float, gy: float, res) -> float | None:
    """The temperature difference [K] the dark-rate ramp ``gx u + gy v`` [e-/s across the sensor's width and
    height] needs across the window the frame sees, about the dark rate ``D`` (:func:`base_rate`) at the window's
    mean: by the doubling law (Janesick 2001 eq. 7.4) ``T_2 log2((D + r_max) / (D + r_min))``, ``r`` the ramp at
    the window's corners less its mean there; None when it takes the rate to or below zero (``D + r_min <= 0``)."""
    s = res.sensor
    u, v = sensor_uv(np.array([res.ys.min(), res.ys.max()]), np.array([res.xs.min(), res.xs.max()]),
                     s.sensor_height_px, s.sensor_width_px)
    r = gx * np.asarray(u, np.float64)[None, :] + gy * np.asarray(v, np.float64)[:, None]
    r = r - r.mean()  # a plane's mean over a rectangle is its corners' mean
    base = base_rate(res)
    lo, hi = base + float(r.min()), base + float(r.max())
    if lo <= 0:
        return None if hi > lo else 0.0
    return doubling_interval_k(s.temperature_c) * float(np.log2(hi / lo))


def field_span_k(coef, res, box=None) -> float | None:
    """The temperature difference [K] a smooth dark-rate field ``F`` (cosine coefficients ``coef`` [e-/s] over the
    box ``box``, default the sensor) needs across the window the frame sees (on :func:`field_on_window`'s grid),
    on top of the dark rate ``D`` (:func:`base_rate`): by the doubling law (Janesick 2001 eq. 7.4)
    ``T_2 log2((D + F_max) / (D + F_min))``; None when the field takes the rate to or below zero
    (``D + F_min <= 0``: no temperature does that)."""
    s = res.sensor
    box = sensor_box(s) if box is None else box
    f, base = field_on_window(coef, box, res), base_rate(res)
    lo, hi = base + float(np.min(f)), base + float(np.max(f))
    if lo <= 0:
        return None if hi > lo else 0.0
    return doubling_interval_k(s.temperature_c) * float(np.log2(hi / lo))


def _explain(p: dict, res) -> str:
    tx, ty = p.get("temperature_x_k", 0.0), p.get("temperature_y_k", 0.0)
    words = []
    if p.get("field_e_per_s"):
        box = p.get("field_box_px") or sensor_box(res.sensor)
        ptp = float(np.ptp(field_on_window(p["field_e_per_s"], box, res)))
        n = len(p["field_e_per_s"])
        span = field_span_k(p["field_e_per_s"], res, box)
        words.append(f"a smooth dark-rate field of {ptp:.3g} e-/s peak to peak across the window ({n} x {n} cosine "
                     "terms; " + (f"{span:.3g} K across it at the doubling law)" if span is not None else
                                  "more than the dark rate: no temperature field)"))
    if tx or ty:
        t2 = doubling_interval_k(res.sensor.temperature_c)
        words.append(f"the sensor {abs(tx):.3g} K {'warmer' if tx >= 0 else 'cooler'} at the right edge, "
                     f"{abs(ty):.3g} K {'warmer' if ty >= 0 else 'cooler'} at the top (dark current doubling "
                     f"every {t2:.2g} K)")
    if p.get("gradient_x_e_per_s", 0.0) or p.get("gradient_y_e_per_s", 0.0) or not words:
        words.append(f"dark rate changing by {p.get('gradient_x_e_per_s', 0.0):+.3g} e-/s across the columns and "
                     f"{p.get('gradient_y_e_per_s', 0.0):+.3g} e-/s across the rows")
    return (", ".join(words) + ", growing with exposure: a dark-current gradient (a temperature gradient "
            "across the sensor)")


_SIGNATURE = LinearSignature(
    _variants, _explain,
    pattern="additive ramp of dark charge growing with exposure", extra_k=0, adds_charge=True, check=_check)
_SIGNATURE.untold = dark_field_untold(("bias_gradient",), ("vignetting",))


# --- adapter -----------------------------------------------------------------------------------------------

class DarkGradientParams(EffectParams):
    gradient_x_e_per_s: float = Field(0.05, ge=-1e6, le=1e6,
                                      description="dark-rate change across the sensor width [e-/s/pixel]")
    gradient_y_e_per_s: float = Field(0.0, ge=-1e6, le=1e6,
                                      description="dark-rate change across the sensor height [e-/s/pixel]")
    temperature_x_k: float = Field(0.0, ge=-100, le=100,
                                   description="temperature difference across the sensor width, right minus "
                                               "left [K] (exponential law, doubling every T_2)")
    temperature_y_k: float = Field(0.0, ge=-100, le=100,
                                   description="temperature difference across the sensor height, top minus "
                                               "bottom [K] (exponential law, doubling every T_2)")
    field_e_per_s: FieldCoefficients = field_coefficients("e-/s", "a smooth dark-rate field")
    field_box_px: FieldBox = field_box("field_e_per_s")


@register_effect
class DarkGradient(Effect):
    """Dark-current gradient across the sensor (a temperature gradient over the die, Janesick 2001 eq. 7.4):
    adds ``(gx u + gy v + D0 (2^((tx u + ty v) / T_2) - 1) + F(u, v)) t`` [e-] to the dark charge (``F`` the
    smooth field of ``field_e_per_s``), ``u, v`` in
    -0.5..0.5 across the sensor, ``D0`` the sensor's dark rate, ``T_2`` the doubling interval at the sensor's
    temperature (:func:`doubling_interval_k`), never taking the pixel's dark charge below zero. Grows with
    exposure time; its shot noise is drawn with the rest of the dark charge."""

    name = "dark_gradient"
    field_kind = "additive"
    scaling = "exposure"
    identity = {"gradient_x_e_per_s": 0.0, "gradient_y_e_per_s": 0.0, "temperature_x_k": 0.0,
                "temperature_y_k": 0.0}
    stages = (Stage.DARK,)
    signature = _SIGNATURE
    Params = DarkGradientParams

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        p, s = self.params, self.sensor
        linear = p.gradient_x_e_per_s != 0 or p.gradient_y_e_per_s != 0
        thermal = (p.temperature_x_k != 0 or p.temperature_y_k != 0) and s.dark_current_e_per_s > 0
        if not tile.exptime_s or not (linear or thermal or p.field_e_per_s):
            return
        ys, xs = tile.pixel_centres()
        m = gradient_rate(ys, xs, s.sensor_height_px, s.sensor_width_px, p.gradient_x_e_per_s, p.gradient_y_e_per_s)
        if p.field_e_per_s:
            m += bias_field_adu(ys, xs, s.sensor_height_px, s.sensor_width_px, p.field_e_per_s, p.field_box_px or None)
        if thermal:
            m += thermal_rate(ys, xs, s.sensor_height_px, s.sensor_width_px, s.dark_current_e_per_s,
                              p.temperature_x_k, p.temperature_y_k, doubling_interval_k(s.temperature_c))
        m *= np.float32(tile.exptime_s)
        data += m
        np.maximum(data, 0, out=data)
