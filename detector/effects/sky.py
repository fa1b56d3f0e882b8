"""Light the scene's uniform background lacks: ``sky_gradient`` (a plane) and ``straylight`` (a smooth field).

The night sky is not uniform across a field: the scattered light of the Moon falls off with the angular
distance from it, twilight with the solar depression along the vertical, airglow grows with the airmass
towards the horizon (van Rhijn 1921; Krisciunas & Schaefer 1991, PASP 103, 1033, for the moonlit sky).
Over a telescope's field of a degree or less these are smooth, and to first order a plane,

    B(x, y) = B_0 + g_x (x - x_c) / 1000 + g_y (y - y_c) / 1000        [e-/s per pixel]

with (x, y) sensor pixels, (x_c, y_c) the sensor centre, and ``g_x``, ``g_y`` the change of the rate per
1000 sensor pixels. ``B_0`` is the scene's background; the effect adds the ramps (zero at the sensor
centre, so windows and binning see the same sky) as photo-electrons ``t (g . (x - x_c)) / 1000``.

It is light: added to the photo-signal where the scene's light enters (stage FIELD, before the optics'
image-plane effects and the pixel response, so vignetting, PRNU and a CFA act on it as on the sky), with
its shot noise, and absent when no light reaches the sensor (dark and bias frames: an expected photo-signal
zero everywhere). That, and its form (a plane, proportional to the exposure time), tell it from a bias
gradient (ADU, in bias frames too), an amplifier glow (dark charge, localised at an edge) and vignetting
(a radial, multiplicative loss of every source's light).

``straylight`` with ``model = "field"``: light scattered into the field by the telescope (baffles, tube,
spider, the mirror's roughness: a PST map of the Sun or the Moon at some angle, docs/optics_straylight.md)
is smooth over the sensor and, to second order about the sensor centre,

    S(x, y) = g_x X + g_y Y + g_xx X^2 + g_xy X Y + g_yy Y^2,   X = (x - x_c) / 1000, Y = (y - y_c) / 1000

[e-/s per pixel]: light with its shot noise, growing with the exposure, absent in darks. It is the form the
diagnosis fits when a field-wide additive light is missing and the scene's straylight source is unknown;
the scene's own ray-traced straylight (``[effects.straylight]`` with ``pst = ...``: the Sun and the Moon
through the design's PST, :mod:`scenes.straylight`) is the physical model to move to once the source is
known. (Mitigation of straylight: Breault 1995, Handbook of Optics vol. I, ch. 38.)

The second-order field is the leading part of a smooth field; a scattered light from outside the field (a
point source beyond an edge, a ring of the baffles, a moonlit tube) is smooth but not a quadric, and a
quadric fitted to a cubic field fails where it acts most (its corners). ``model = "legendre"`` is the field
as a series of products of Legendre polynomials over the read-out window,

    S(x, y) = sum_{1 <= i + j <= n} c_ij P_i(u) P_j(v),   u, v in [-1, 1] across the window's width and height

[e-/s per pixel], of an order ``n`` the diagnosis chooses by BIC (Schwarz 1978: each order's templates pay
``ln N`` each) from 2 to ``MAX_FIELD_ORDER``: the form of any smooth field of light, whatever its source, to
the order the frame's pixels support (the residual's own smooth description uses the same basis,
:mod:`detector.morphology`).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from ..signatures import LinearSignature, Variant, light_law_check, light_law_told, light_law_untold
from .base import Effect, EffectParams, Stage, Tile, register_effect
from .glow import edge_rate, edge_variant

#: the gradient's length unit: the rates change per this many sensor pixels
KPX = 1000.0
#: bound of either gradient [e-/s/pixel per 1000 px]
MAX_GRADIENT = 1e5


def sky_ramp_e(ys: np.ndarray, xs: np.ndarray, yc: float, xc: float, gx_e_per_s_per_kpx: float,
               gy_e_per_s_per_kpx: float, exptime_s: float) -> np.ndarray:
    """Photo-electrons [e-] of the sky gradient at sensor rows ``ys``, columns ``xs`` (pixel centres): the
    plane ``t (g_x (x - x_c) + g_y (y - y_c)) / 1000``, zero at (x_c, y_c); shape (len(ys), len(xs))."""
    rate = (gx_e_per_s_per_kpx * (np.asarray(xs, np.float64) - xc) / KPX)[None, :] \
        + (gy_e_per_s_per_kpx * (np.asarray(ys, np.float64) - yc) / KPX)[:, None]
    return (rate * exptime_s).astype(np.float32)


def _sensor_centre(sensor) -> tuple[float, float]:
    return (sensor.sensor_height_px - 1) / 2.0, (sensor.sensor_width_px - 1) / 2.0


# --- diagnosis: two ramps of light, proportional to the exposure time --------------------------------------------

def _sky_variants(res):
    if res.exptime_s <= 0 or not np.any(res.photo_adu > 0):  # no light reached the sensor: no sky
        return
    yc, xc = _sensor_centre(res.sensor)
    f = res.adu_per_rate / KPX  # ADU per output pixel per (e-/s/pixel per 1000 px)
    tx = (f * (res.xs - xc)).astype(np.float32)[None, :]
    ty = (f * (res.ys - yc)).astype(np.float32)[:, None]

    def to_params(c):
        gx, gy = (float(x) for x in c)
        ok = max(abs(gx), abs(gy)) <= MAX_GRADIENT
        return {"gx_e_per_s_per_kpx": round(gx, 6), "gy_e_per_s_per_kpx": round(gy, 6)} if ok else None

    yield Variant([tx, ty], to_params, "plane")


def _sky_words(p, res) -> str:
    gx, gy = p["gx_e_per_s_per_kpx"], p["gy_e_per_s_per_kpx"]
    ang = float(np.degrees(np.arctan2(gy, gx))) % 360.0
    return (f"additive light rising linearly across the field, {np.hypot(gx, gy):.3g} e-/s per pixel per 1000 px "
            f"towards {ang:.0f} deg (from +x), growing with exposure, in the light only: a sky gradient "
            "(moonlight, twilight, airglow)")


_SKY_SIGNATURE = LinearSignature(_sky_variants, _sky_words, pattern="additive plane of light (with its shot noise)",
                                 extra_k=0, adds_charge=True, check=lambda fit, res: sky_light_check(fit, res))
#: an added light and a response to the light of the same shape are one image where the light is one level
_SKY_SIGNATURE.untold = light_law_untold(("vignetting",), multiplicative=False)
_SKY_SIGNATURE.told = light_law_told(multiplicative=False)


# --- adapter -------------------------------------------------------------------------------------------------


class SkyGradientParams(EffectParams):
    gx_e_per_s_per_kpx: float = Field(
        1.0, ge=-MAX_GRADIENT, le=MAX_GRADIENT, description="change of the sky rate along the columns (+x) per 1000 sensor pixels, "
        "zero at the sensor centre [e-/s/pixel per 1000 px]", json_schema_extra={"unit": "electron / (s pixel kpixel)"})
    gy_e_per_s_per_kpx: float = Field(
        0.0, ge=-MAX_GRADIENT, le=MAX_GRADIENT, description="change of the sky rate along the rows (+y) per 1000 sensor pixels, "
        "zero at the sensor centre [e-/s/pixel per 1000 px]", json_schema_extra={"unit": "electron / (s pixel kpixel)"})


@register_effect
class SkyGradient(Effect):
    """A linear gradient of the sky light across the field (moonlit sky, twilight, airglow): photo-electrons
    ``t (g_x (x - x_c) + g_y (y - y_c)) / 1000`` added to the light, zero at the sensor centre.

    Light only: nothing is added when the frame receives no light (a dark or bias frame, an expected
    photo-signal of zero everywhere); where the plane would take the light below zero it is clipped at zero.
    """

    name = "sky_gradient"
    field_kind = "additive"
    scaling = "frame"
    identity = {"gx_e_per_s_per_kpx": 0.0, "gy_e_per_s_per_kpx": 0.0}
    stages = (Stage.FIELD,)
    Params = SkyGradientParams
    signature = _SKY_SIGNATURE

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        if not data.any():  # shutter closed: no light, no sky
            return
        ys, xs = tile.pixel_centres()
        yc, xc = _sensor_centre(self.sensor)
        p = self.params
        data += sky_ramp_e(ys, xs, yc, xc, p.gx_e_per_s_per_kpx, p.gy_e_per_s_per_kpx, tile.exptime_s)
        np.maximum(data, 0, out=data)


# --- straylight as a smooth field of light ------------------------------------------------------------------------

#: bound of the straylight field's coefficients [e-/s/pixel per 1000 px (squared)]
MAX_FIELD = 1e5


def straylight_field_e(ys: np.ndarray, xs: np.ndarray, yc: float, xc: float, c: dict, exptime_s: float) -> np.ndarray:
    """Photo-electrons [e-] of the second-order straylight field at sensor rows ``ys``, columns ``xs`` (the
    module's polynomial, zero at the sensor centre ``(x_c, y_c)``); shape (len(ys), len(xs))."""
    x = ((np.asarray(xs, np.float64) - xc) / KPX)[None, :]
    y = ((np.asarray(ys, np.float64) - yc) / KPX)[:, None]
    rate = c["gx"] * x + c["gy"] * y + c["gxx"] * x * x + c["gxy"] * x * y + c["gyy"] * y * y
    return (rate * exptime_s).astype(np.float32)


_FIELD_KEYS = ("gx", "gy", "gxx", "gxy", "gyy")


def _field_words(p, res) -> str:
    s = res.sensor
    yc, xc = _sensor_centre(s)
    w, h = s.roi_shape
    ys = np.array([s.roi_y0, s.roi_y0 + h - 1, s.roi_y0, s.roi_y0 + h - 1, s.roi_y0 + h / 2.0])
    xs = np.array([s.roi_x0, s.roi_x0, s.roi_x0 + w - 1, s.roi_x0 + w - 1, s.roi_x0 + w / 2.0])
    if p.get("model") == "edge":
        return (f"an additive light entering from the sensor's {p['edge']} {'corner' if '-' in p['edge'] else 'edge'}, "
                f"{p['amplitude_e_per_s'] * res.exptime_s:.3g} e- per sensor pixel there, falling off over "
                f"{p['scale_px']:.3g} px (e-folding), growing with exposure, in the light only: straylight (a lit "
                "baffle or housing edge, a light leak)")
    if p.get("model") == "legendre":
        vv, uu = window_uv(s, np.linspace(s.roi_y0, s.roi_y0 + h - 1, 33), np.linspace(s.roi_x0, s.roi_x0 + w - 1, 33))
        vals = (legendre_field_rate(vv, uu, p["order"], p["coef"]) * res.exptime_s).ravel().tolist()
        what = f"from its faintest to its brightest part (a Legendre series of order {p['order']})"
    else:
        vals = [float(straylight_field_e(np.array([y]), np.array([x]), yc, xc, p, res.exptime_s)[0, 0])
                for y, x in zip(ys, xs)]
        what = "from its faintest to its brightest corner, curved"
    return (f"a smooth additive light across the field, {max(vals) - min(vals):.3g} e- per sensor pixel {what}, "
            "growing with exposure, in the light only: straylight (or a sky gradient that is not a plane)")


def sky_light_check(fit, res) -> str:
    """Light from the sky (a gradient, straylight of the Sun or the Moon) cannot reach the sensor through a
    flat-field screen, which blocks the sky: a smooth pattern of a flat is a response (vignetting, a flat field)."""
    if getattr(res, "light_source", "") == "flat":
        return ("the frame's light is a flat-field screen, which blocks the sky: no sky light or straylight reaches "
                "the sensor; a smooth pattern on a flat is a response (vignetting, a flat-field error)")
    # an added light of this shape against a response of the same shape: the sources tell (not a flat screen)
    return light_law_check(fit, res, multiplicative=False)


_field_check = sky_light_check

#: highest order of the Legendre field the diagnosis tries (its BIC picks the order; 6: 27 templates, a field
#: with up to three extrema across the window)
MAX_FIELD_ORDER = 6


def legendre_terms(order: int) -> list[tuple[int, int]]:
    """The (i, j) of the products P_i(u) P_j(v) with 1 <= i + j <= order, in the order of the coefficients."""
    return [(i, j) for i in range(order + 1) for j in range(order + 1 - i) if i + j >= 1]


def window_uv(sensor, ys: np.ndarray, xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sensor rows ``ys`` and columns ``xs`` (pixel centres) as (v, u) in [-1, 1] across the read-out window
    (its first pixel's outer edge at -1, its last pixel's at +1)."""
    w, h = sensor.roi_shape
    u = 2.0 * (np.asarray(xs, np.float64) + 0.5 - sensor.roi_x0) / w - 1.0
    v = 2.0 * (np.asarray(ys, np.float64) + 0.5 - sensor.roi_y0) / h - 1.0
    return v, u


def legendre_field_rate(v: np.ndarray, u: np.ndarray, order: int, coef) -> np.ndarray:
    """The field ``sum c_ij P_i(u) P_j(v)`` [the coefficients' unit] on the grid of 1-D ``v`` (rows) and ``u``
    (columns); shape (len(v), len(u))."""
    pu = np.polynomial.legendre.legvander(np.asarray(u, np.float64), order)
    pv = np.polynomial.legendre.legvander(np.asarray(v, np.float64), order)
    out = np.zeros((pv.shape[0], pu.shape[0]))
    for (i, j), c in zip(legendre_terms(order), coef):
        out += float(c) * pv[:, j][:, None] * pu[:, i][None, :]
    return out


def _legendre_variant(res, order: int, f: float, pu: np.ndarray, pv: np.ndarray):
    terms = legendre_terms(order)
    w = res.data_adu.shape[1]

    def at(idx):
        y, x = np.divmod(np.asarray(idx), w)
        return np.stack([f * pv[y, j] * pu[x, i] for i, j in terms])

    def maps():
        return [(f * pv[:, j][:, None] * pu[:, i][None, :]).astype(np.float32) for i, j in terms]

    def to_params(c):
        vals = [float(v) for v in c]
        if max(abs(v) for v in vals) > MAX_FIELD:
            return None
        return {"model": "legendre", "order": order, "coef": [round(v, 8) for v in vals]}

    return Variant(maps, to_params, f"legendre {order}", at=at)


def _legendre_variants(res):
    """The Legendre fields of orders 2 to MAX_FIELD_ORDER over the window (the signature's BIC picks one)."""
    if res.exptime_s <= 0 or not np.any(res.photo_adu > 0):
        return
    f = res.adu_per_rate  # ADU per output pixel per e-/s/pixel
    v, u = window_uv(res.sensor, res.ys, res.xs)
    pu = np.polynomial.legendre.legvander(u, MAX_FIELD_ORDER)
    pv = np.polynomial.legendre.legvander(v, MAX_FIELD_ORDER)
    for order in range(2, MAX_FIELD_ORDER + 1):
        yield _legendre_variant(res, order, f, pu, pv)
    side = max(res.sensor.sensor_width_px, res.sensor.sensor_height_px)
    for where in EDGES:
        for frac in EDGE_SCALES:
            yield _edge_variant(res, where, frac * side, f)


#: the edges and corners a straylight may enter from, and its e-folding distances tried [fractions of the
#: sensor's longer side]: a lit baffle, a housing edge or a light leak puts light along one side of the sensor
#: that falls off into the field, over a few per cent of it to all of it (not localised like an amplifier's
#: glow, ``amp_glow``'s GLOW_MAX_SCALE); a falling exponential is no low-order Legendre series
EDGES = ("left", "right", "top", "bottom", "bottom-left", "bottom-right", "top-left", "top-right")
EDGE_SCALES = tuple(np.geomspace(0.02, 1.0, 7))


def _edge_variant(res, where: str, scale: float, f: float) -> Variant:
    return edge_variant(res, where, scale, f, MAX_FIELD, f"edge {where}|{scale:.6g}")


_FIELD_SIGNATURE = LinearSignature(_legendre_variants, lambda p, res: _field_words(p, res),
                                   pattern="additive smooth field of light (a Legendre series of the order the "
                                   "frame supports), with its shot noise",
                                   extra_k=1, adds_charge=True, check=_field_check)
_FIELD_SIGNATURE.untold = light_law_untold(("vignetting",), multiplicative=False)
_FIELD_SIGNATURE.told = light_law_told(multiplicative=False)


class StraylightFieldParams(EffectParams):
    model: Literal["field", "legendre", "edge"] = Field(
        "field", description="the smooth-field form: 'field' the second-order polynomial about the sensor centre "
        "(gx ... gyy), 'legendre' the Legendre series of ``order`` over the read-out window (``coef``), 'edge' a "
        "light entering from an edge or corner of the sensor falling as exp(-d / scale_px) (``edge``, "
        "``amplitude_e_per_s``, ``scale_px``); the scene's ray-traced form has pst = ... instead")
    edge: str = Field("left", description="the sensor edge or corner the light enters from (model 'edge'): left, "
                      "right, top, bottom or a corner such as bottom-left")
    amplitude_e_per_s: float = Field(0.0, ge=0, le=1e6, description="the light at that edge (model 'edge') "
                                     "[e-/s/pixel]", json_schema_extra={"unit": "electron / (s pixel)"})
    scale_px: float = Field(100.0, gt=0, le=1e6, description="e-folding distance from that edge (model 'edge') "
                            "[sensor px]", json_schema_extra={"unit": "pixel"})
    order: int = Field(2, ge=1, le=12, description="order of the Legendre series (model 'legendre') [1]")
    coef: list[float] = Field(default_factory=list, description="coefficients of P_i(u) P_j(v), 1 <= i + j <= order, "
                              "i outer (model 'legendre') [e-/s/pixel]",
                              json_schema_extra={"unit": "electron / (s pixel)"})
    gx: float = Field(0.0, ge=-MAX_FIELD, le=MAX_FIELD, description="linear term along the columns "
                      "[e-/s/pixel per 1000 px]", json_schema_extra={"unit": "electron / (s pixel kpixel)"})
    gy: float = Field(0.0, ge=-MAX_FIELD, le=MAX_FIELD, description="linear term along the rows "
                      "[e-/s/pixel per 1000 px]", json_schema_extra={"unit": "electron / (s pixel kpixel)"})
    gxx: float = Field(0.0, ge=-MAX_FIELD, le=MAX_FIELD, description="quadratic term x^2 "
                       "[e-/s/pixel per (1000 px)^2]", json_schema_extra={"unit": "electron / (s pixel kpixel2)"})
    gxy: float = Field(0.0, ge=-MAX_FIELD, le=MAX_FIELD, description="cross term x y "
                       "[e-/s/pixel per (1000 px)^2]", json_schema_extra={"unit": "electron / (s pixel kpixel2)"})
    gyy: float = Field(0.0, ge=-MAX_FIELD, le=MAX_FIELD, description="quadratic term y^2 "
                       "[e-/s/pixel per (1000 px)^2]", json_schema_extra={"unit": "electron / (s pixel kpixel2)"})


@register_effect
class StraylightField(Effect):
    """Straylight as a smooth second-order field of light about the sensor centre (the diagnosis's form);
    ``[effects.straylight]`` with ``pst = ...`` is the scene's ray-traced straylight of the Sun and the Moon.

    Light only, like ``sky_gradient``; where the field would take the light below zero it is clipped at zero.
    """

    name = "straylight"
    field_kind = "additive"
    scaling = "frame"
    identity = {"model": "field"}
    stages = (Stage.FIELD,)
    Params = StraylightFieldParams
    signature = _FIELD_SIGNATURE

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        if not data.any():  # shutter closed: no light
            return
        ys, xs = tile.pixel_centres()
        yc, xc = _sensor_centre(self.sensor)
        p = self.params
        if p.model == "legendre":
            v, u = window_uv(self.sensor, ys, xs)
            data += (legendre_field_rate(v, u, p.order, p.coef) * tile.exptime_s).astype(np.float32)
        elif p.model == "edge":
            t = np.zeros(data.shape, np.float32)
            edge_rate(ys, xs, self.sensor.sensor_height_px, self.sensor.sensor_width_px, p.edge,
                      p.amplitude_e_per_s * tile.exptime_s, p.scale_px, t)
            data += t
        else:
            data += straylight_field_e(ys, xs, yc, xc, {k: getattr(p, k) for k in _FIELD_KEYS}, tile.exptime_s)
        np.maximum(data, 0, out=data)
