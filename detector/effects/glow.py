"""Amplifier glow: light emitted by the read-out amplifier (or hot electronics) near an edge of the sensor.

The reference thesis (Annex V) models the glow of its CMOS as a sum of bivariate-normal maps fitted to
long darks; an exponential fall-off with the distance from an edge or a corner is the other common law
(e.g. the "amp glow" of Sony IMX CMOS sensors in long exposures). The third is the glow's own radiometry: the
amplifier is a small emitter at a height ``h`` above (or beside) the photosites, whose irradiance on the sensor
plane is ``I cos(theta) / R^2 = I h / (r^2 + h^2)^1.5`` (the inverse-square and cosine laws of a point source,
McCluney, Introduction to Radiometry and Photometry, 2nd ed. 2014, sect. 2.6). The glow adds to the dark signal
and grows linearly with exposure time [e-/s/pixel].
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from ..signatures import LinearSignature, Variant, dark_field_untold, fit_linear, search_sample
from .base import Effect, EffectParams, Stage, Tile, register_effect

# --- pure functions ---------------------------------------------------------------------------------------

def bivariate_normal_rate(ys: np.ndarray, xs: np.ndarray, x0: float, y0: float, peak: float, sx: float, sy: float,
                          rho: float, out: np.ndarray) -> None:
    """Add ``peak exp(-q/2)`` [e-/s] with q the bivariate-normal quadratic form (thesis Annex V) to ``out``.

    Only the window within 6 sigma of the centre is evaluated (the rest is below 1e-8 of the peak).
    """
    rsel = np.nonzero(np.abs(ys - y0) <= 6 * sy)[0]
    csel = np.nonzero(np.abs(xs - x0) <= 6 * sx)[0]
    if rsel.size == 0 or csel.size == 0:
        return
    r0, r1, c0, c1 = rsel[0], rsel[-1] + 1, csel[0], csel[-1] + 1
    u = ((xs[c0:c1] - x0) / sx)[None, :]
    v = ((ys[r0:r1] - y0) / sy)[:, None]
    q = (u * u - 2 * rho * u * v + v * v) / (1 - rho * rho)
    out[r0:r1, c0:c1] += (peak * np.exp(-0.5 * q)).astype(np.float32)


def emitter_rate(ys: np.ndarray, xs: np.ndarray, x0: float, y0: float, peak: float, height_px: float,
                 out: np.ndarray) -> None:
    """Add ``peak (1 + r^2 / h^2)^-1.5`` [e-/s] to ``out``: the irradiance of a point emitter at ``(x0, y0)`` [sensor
    px] a height ``h`` [px] off the sensor plane (``I h / (r^2 + h^2)^1.5``, ``peak = I / h^2`` below it), evaluated in
    float64 on the whole window (its r^-3 wings reach every pixel), in blocks of rows (EDGE_BLOCK_PIXELS)."""
    dx2 = ((np.asarray(xs, np.float64) - x0) / height_px) ** 2
    dy2 = ((np.asarray(ys, np.float64) - y0) / height_px) ** 2
    step = max(1, EDGE_BLOCK_PIXELS // max(1, dx2.size))
    for r in range(0, dy2.size, step):
        out[r:r + step] += (peak * (1.0 + np.add.outer(dy2[r:r + step], dx2)) ** -1.5).astype(np.float32)


def _exact_squares(v: np.ndarray) -> bool:
    """True when every value is a multiple of 1/2 of magnitude <= 2^24 (pixel centres, binned or not): its
    square and the sum of two such squares are exact in float64 (<= 2^51 quarters), so ``sqrt(a^2 + b^2)`` is
    the correctly rounded distance (libm's ``hypot`` is within 1 ulp of it: off by one ulp for ~0.6 % of an
    IMX411 frame's half-integer pairs, docs/performance.md)."""
    return bool(v.size == 0 or (np.max(np.abs(v)) <= 2.0 ** 24 and np.array_equal(2.0 * v, np.rint(2.0 * v))))


def edge_rate(ys: np.ndarray, xs: np.ndarray, height: int, width: int, where: str, peak: float, scale_px: float,
              out: np.ndarray, exact: bool | None = None) -> None:
    """Add ``peak exp(-d / L)`` [e-/s] with ``d`` the distance [px] to an edge or corner of the sensor.

    Evaluated in float64 and added as float32; along an edge the law depends on one coordinate, so it is
    evaluated once per row or column and broadcast; the operations run in place (the same values as the
    whole-array expression, without its temporaries). A corner's distance is ``sqrt(dy^2 + dx^2)`` when the
    squares are exact (:func:`_exact_squares`, tested here unless ``exact`` says so), else ``hypot``."""
    dx = {"left": xs, "right": (width - 1) - xs}
    dy = {"bottom": ys, "top": (height - 1) - ys}
    parts = where.split("-")
    if len(parts) == 2:  # a corner: "bottom-left" ...
        a, b = np.asarray(dy[parts[0]], dtype=np.float64), np.asarray(dx[parts[1]], dtype=np.float64)
        if exact if exact is not None else (_exact_squares(a) and _exact_squares(b)):  # correctly rounded
            d = np.add.outer(a * a, b * b)
            np.sqrt(d, out=d)
        else:
            d = np.hypot(a[:, None], b[None, :])
    elif where in dx:
        d = np.array(dx[where], dtype=np.float64)[None, :]
    else:
        d = np.array(dy[where], dtype=np.float64)[:, None]
    np.divide(d, -scale_px, out=d)  # -d / L
    np.exp(d, out=d)
    d *= peak
    np.add(out, d, out=out, dtype=np.float32)  # d rounded to float32, then added (as out += d.astype(float32))


#: pixels per block of the edge law in :meth:`AmpGlow.apply` (~0.5 MB of float64 distances: in the cache)
EDGE_BLOCK_PIXELS = 1 << 16


# --- diagnosis signature (detector.signatures) --------------------------------------------------------------

_EDGES = ("left", "right", "top", "bottom", "bottom-left", "bottom-right", "top-left", "top-right")
_SCALES = tuple(np.geomspace(0.005, 0.5, 9))  # e-folding lengths tried, fractions of the longer sensor side


def edge_distance(res, where: str, y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Distance [sensor px] of output pixels (row index y, column index x) to an edge or corner."""
    s = res.sensor
    ys, xs = res.ys[y], res.xs[x]
    dx = {"left": lambda: xs, "right": lambda: (s.sensor_width_px - 1) - xs}
    dy = {"bottom": lambda: ys, "top": lambda: (s.sensor_height_px - 1) - ys}
    parts = where.split("-")
    if len(parts) == 2:
        return np.hypot(dy[parts[0]](), dx[parts[1]]())
    return dx[where]() if where in dx else dy[where]()


def _edge_distance_at(res, where: str, idx) -> np.ndarray:
    """:func:`edge_distance` of the flat output pixels ``idx``, kept with ``res`` for the last (edge, index
    array) asked for: a search tries every e-folding length of one edge on the same pixels in a row. The index
    array is known by its memory (address, length, stride; the kept reference keeps that memory from being
    reused): the least squares pass a new view of the same sample each time."""
    kept = res.memo("edge_distance_at", dict)
    idx = np.asarray(idx)
    key = (where, idx.__array_interface__["data"][0], idx.shape, idx.strides, idx.dtype.str)
    last = kept.get("last")  # (key, index array, distances), replaced whole: safe for concurrent fits
    if last is None or last[0] != key:
        y, x = np.divmod(idx, res.data_adu.shape[1])
        last = (key, idx, edge_distance(res, where, y, x))
        kept["last"] = last
    return last[2]


def edge_variant(res, where: str, scale: float, unit: float, max_amplitude: float, label: str) -> Variant:
    """A field falling as ``exp(-d / scale)`` from the sensor's ``where`` (an edge or a corner, :func:`edge_rate`),
    ``unit`` [ADU] per e-/s of its amplitude: the one template of an amplifier glow and of a light entering from
    an edge; its amplitude [e-/s] is kept in (0, ``max_amplitude``]."""
    s = res.sensor

    def at(idx):
        return (unit * np.exp(-_edge_distance_at(res, where, idx) / scale))[None, :]

    def maps():
        t = np.zeros(res.data_adu.shape, np.float32)
        edge_rate(res.ys, res.xs, s.sensor_height_px, s.sensor_width_px, where, 1.0, scale, t)
        return [t * np.float32(unit)]

    def to_params(c):
        return ({"model": "edge", "edge": where, "amplitude_e_per_s": round(float(c[0]), 6),
                 "scale_px": round(float(scale), 1)} if 0 < c[0] <= max_amplitude else None)

    return Variant(maps, to_params, label, at=at)


def _glow_variant(res, where: str, scale: float) -> Variant:
    return edge_variant(res, where, scale, float(res.adu_per_rate), 1e6, f"{where}|{scale}")


def _from_edge(s, x0: float, y0: float) -> tuple[float, float]:
    """(distance outside the sensor, distance inside it from its nearest edge) [sensor px] of the point (x0, y0):
    one of the two is 0."""
    outside = float(np.hypot(max(-x0, x0 - (s.sensor_width_px - 1), 0.0), max(-y0, y0 - (s.sensor_height_px - 1), 0.0)))
    return outside, max(min(x0, s.sensor_width_px - 1 - x0, y0, s.sensor_height_px - 1 - y0), 0.0)


def _gauss_variant(res, x_frac: float, y_frac: float, sigma_px: float) -> Variant:
    """One bivariate-normal glow source (thesis Annex V, isotropic) centred at (x_frac, y_frac) of the sensor
    (outside it when beyond [0, 1]) with std ``sigma_px`` [sensor px]."""
    s = res.sensor
    unit = float(res.adu_per_rate)
    w = res.data_adu.shape[1]
    x0, y0 = x_frac * (s.sensor_width_px - 1), y_frac * (s.sensor_height_px - 1)

    def at(idx):
        y, x = np.divmod(idx, w)
        q = ((res.xs[x] - x0) ** 2 + (res.ys[y] - y0) ** 2) / (sigma_px * sigma_px)
        return (unit * np.exp(-0.5 * q))[None, :]

    def maps():
        t = np.zeros(res.data_adu.shape, np.float32)
        bivariate_normal_rate(res.ys, res.xs, x0, y0, 1.0, sigma_px, sigma_px, 0.0, t)
        return [t * np.float32(unit)]

    # a glow source sits at the sensor's edge, where the read-out amplifiers are (thesis sect. on amp-glow: "often
    # located at the edges of the image"): within twice its width inside the edge (the glow reaches the edge at
    # e^-2 of its peak at least), or outside it by at most its width (else it is a field-wide gradient). A bump
    # deep inside the sensor is a light leak, a hot spot or a source the model lacks, not an amplifier's glow
    outside, inside = _from_edge(s, x0, y0)

    # a glow is extended: no narrower than the shortest e-folding length the edge law tries (and 16 px); a
    # narrower bump is a source the model lacks
    narrowest = max(_SCALES[0] * max(s.sensor_width_px, s.sensor_height_px), 16.0)
    widest = GLOW_MAX_SCALE * max(s.sensor_width_px, s.sensor_height_px)

    def to_params(c):
        # ... and localised: no wider than the edge law's longest e-folding distance (GLOW_MAX_SCALE of the
        # sensor); a wider bump is a field-wide gradient (a flat one trades its level against the dark and bias
        # levels: a "glow" of 60 000 px and 5.6e3 e- whose apply saturated every pixel of a binned dark)
        if outside > sigma_px or inside > 2.0 * sigma_px or sigma_px < narrowest or sigma_px > widest:
            return None
        return ({"model": "gaussian", "sources": [{"x_frac": round(float(x_frac), 5), "y_frac": round(float(y_frac), 5),
                                                   "amplitude_e_per_s": round(float(c[0]), 6),
                                                   "sigma_x_px": round(float(sigma_px), 1),
                                                   "sigma_y_px": round(float(sigma_px), 1), "rho": 0.0}]}
                if 0 < c[0] <= 1e6 and -1 <= x_frac <= 2 and -1 <= y_frac <= 2 else None)

    return Variant(maps, to_params, f"g|{x_frac:.6g}|{y_frac:.6g}|{sigma_px:.6g}", at=at)


def _emitter_variant(res, x_frac: float, y_frac: float, height_px: float) -> Variant:
    """One point emitter (:func:`emitter_rate`) at (x_frac, y_frac) of the sensor (outside it when beyond [0, 1]),
    ``height_px`` [sensor px] off the sensor plane. Held to the Gaussian source's bounds with the height for the
    width: within two heights of the sensor's edge, inside or out (the amplifier sits at the die's edge; two heights
    away its irradiance is 9 % of the peak, as the Gaussian's two widths are 13.5 %), no lower than 16 px (a
    narrower bump is a source the model lacks) and no higher than GLOW_MAX_SCALE of the sensor (a field-wide
    gradient)."""
    s = res.sensor
    unit = float(res.adu_per_rate)
    w = res.data_adu.shape[1]
    x0, y0 = x_frac * (s.sensor_width_px - 1), y_frac * (s.sensor_height_px - 1)
    h2 = height_px * height_px

    def at(idx):
        y, x = np.divmod(idx, w)
        q = ((res.xs[x] - x0) ** 2 + (res.ys[y] - y0) ** 2) / h2
        return (unit * (1.0 + q) ** -1.5)[None, :]

    def maps():
        t = np.zeros(res.data_adu.shape, np.float32)
        emitter_rate(res.ys, res.xs, x0, y0, 1.0, height_px, t)
        return [t * np.float32(unit)]

    outside, inside = _from_edge(s, x0, y0)
    widest = GLOW_MAX_SCALE * max(s.sensor_width_px, s.sensor_height_px)

    def to_params(c):
        if outside > 2.0 * height_px or inside > 2.0 * height_px or not 16.0 <= height_px <= widest:
            return None
        return ({"model": "emitter", "emitters": [{"x_frac": round(float(x_frac), 5), "y_frac": round(float(y_frac), 5),
                                                   "amplitude_e_per_s": round(float(c[0]), 6),
                                                   "height_px": round(float(height_px), 1)}]}
                if 0 < c[0] <= 1e6 and -1 <= x_frac <= 2 and -1 <= y_frac <= 2 else None)

    return Variant(maps, to_params, f"e|{x_frac:.6g}|{y_frac:.6g}|{height_px:.6g}", at=at)


_SOURCE_VARIANTS = {"g": _gauss_variant, "e": _emitter_variant}


def _window(res) -> tuple[float, float, float, float]:
    """(x0, x1, y0, y1): the frame's extent in sensor pixels."""
    return float(res.xs[0]), float(res.xs[-1]), float(res.ys[0]), float(res.ys[-1])


#: glow sources tried: a 5 x 5 grid over the frame and half a frame beyond it on every side, with stds (a Gaussian
#: source) and heights (an emitter) of these fractions of the frame's diagonal (a localised glow seen from inside
#: the window or reaching into it)
_GAUSS_GRID = (-0.5, 0.0, 0.5, 1.0, 1.5)
_GAUSS_SIGMAS = (0.08, 0.15, 0.3, 0.55, 1.0)
_EMITTER_HEIGHTS = (0.04, 0.08, 0.15, 0.3, 0.55)


def _glow_variants(res):
    side = max(res.sensor.sensor_width_px, res.sensor.sensor_height_px)
    for where in _EDGES:
        for frac in _SCALES:
            yield _glow_variant(res, where, frac * side)
    s = res.sensor
    x0, x1, y0, y1 = _window(res)
    diag = float(np.hypot(x1 - x0, y1 - y0)) + 1.0
    for fy in _GAUSS_GRID:
        for fx in _GAUSS_GRID:
            xc, yc = x0 + fx * (x1 - x0), y0 + fy * (y1 - y0)
            xf, yf = xc / max(s.sensor_width_px - 1, 1), yc / max(s.sensor_height_px - 1, 1)
            for f in _GAUSS_SIGMAS:
                sigma = f * diag
                if sigma <= GLOW_MAX_SCALE * side:
                    yield _gauss_variant(res, xf, yf, sigma)
            for f in _EMITTER_HEIGHTS:
                if f * diag <= GLOW_MAX_SCALE * side:
                    yield _emitter_variant(res, xf, yf, f * diag)


def _glow_refine(best: Variant, res):
    kind = best.label.split("|")[0]
    if kind in _SOURCE_VARIANTS:
        # the source's centre and width (a Gaussian's std, an emitter's height), continuously (Nelder-Mead on the
        # search sample's delta chi2, the amplitude and the levels solved linearly at every step)
        from scipy.optimize import minimize

        _, xf, yf, sigma = best.label.split("|")
        make = _SOURCE_VARIANTS[kind]
        ctx = search_sample(res)

        def cost(p):
            v = make(res, p[0], p[1], float(np.exp(p[2])))
            c, d = fit_linear(res, lambda i: v.values(i, res.data_adu.shape), ctx["idx"], ctx["r"], ctx["w"])
            return d if v.to_params(c) is not None else 0.0

        s = res.sensor
        x0, x1, y0, y1 = _window(res)
        start = np.array([float(xf), float(yf), np.log(float(sigma))])
        simplex = np.array([start, start + [0.1 * (x1 - x0) / max(s.sensor_width_px - 1, 1), 0, 0],
                            start + [0, 0.1 * (y1 - y0) / max(s.sensor_height_px - 1, 1), 0], start + [0, 0, 0.2]])
        opt = minimize(cost, start, method="Nelder-Mead",
                       options={"initial_simplex": simplex, "maxfev": 80, "xatol": 1e-4, "fatol": 0.5})
        yield make(res, float(opt.x[0]), float(opt.x[1]), float(np.exp(opt.x[2])))
        return
    where, scale = best.label.split("|")
    for f in np.geomspace(0.6, 1.6, 9):
        yield _glow_variant(res, where, float(scale) * f)


def _rebuild(label: str, res) -> Variant:
    """The variant of a label ("edge|scale", "g|x_frac|y_frac|sigma" or "e|x_frac|y_frac|height"), on any frame (a
    series refines on one frame, fits on all)."""
    parts = label.split("|")
    if parts[0] in _SOURCE_VARIANTS:
        return _SOURCE_VARIANTS[parts[0]](res, float(parts[1]), float(parts[2]), float(parts[3]))
    return _glow_variant(res, parts[0], float(parts[1]))


#: an amplifier glow is localised: its e-folding distance is at most this fraction of the sensor's longer side
GLOW_MAX_SCALE = 0.25


def _glow_check(fit, res) -> str:
    """An amplifier (or hot-electronics) glow is a localised light near an edge or corner of the sensor: its
    charge at the edge stays below the full well, its e-folding distance is a small fraction of the sensor,
    and it reaches the read-out window from that edge (Janesick 2001, Scientific CCDs, sect. 5.9; the IMX411
    glows within a few hundred pixels of its amplifiers)."""
    p, s = fit.params, res.sensor
    if res.light_source == "flat":
        return ("a glow on a flat-screen frame cannot be told from the flat's own response (added charge and a "
                "response are one on a uniform light): a glow is dark charge, which the darks measure")
    if p.get("model") in ("gaussian", "emitter"):
        g = (p.get("sources") or p.get("emitters"))[0]
        peak_e = g["amplitude_e_per_s"] * res.exptime_s
        if peak_e > s.full_well_e:
            return (f"{peak_e:.3g} e- at the glow's centre, more than the full well ({s.full_well_e:.3g} e-): no glow is "
                    "that bright; a smooth light across the field taken for a glow")
        return ""  # (where the source sits and its width are the variants' own bounds: _gauss_variant)
    edge_e = p["amplitude_e_per_s"] * res.exptime_s
    if edge_e > s.full_well_e:
        return (f"{edge_e:.3g} e- at the edge, more than the full well ({s.full_well_e:.3g} e-): no glow is that "
                "bright; a smooth light across the field taken for a glow")
    longest = max(s.sensor_width_px, s.sensor_height_px)
    if p["scale_px"] > GLOW_MAX_SCALE * longest:
        return (f"e-folding distance {p['scale_px']:.0f} px, {100 * p['scale_px'] / longest:.0f} % of the sensor: a glow "
                "is localised near its amplifier, this is a field-wide gradient")
    return ""


def _glow_words(p, res) -> str:
    if p.get("model") == "emitter":
        g = p["emitters"][0]
        s = res.sensor
        x, y = g["x_frac"] * (s.sensor_width_px - 1), g["y_frac"] * (s.sensor_height_px - 1)
        return (f"additive glow from a point emitter at ({x:.0f}, {y:.0f}) sensor px, {g['height_px']:.0f} px off "
                f"the sensor plane (irradiance (1 + r^2/h^2)^-1.5), {g['amplitude_e_per_s'] * res.exptime_s:.3g} e- "
                "below it, growing with exposure: amplifier glow")
    if p.get("model") == "gaussian":
        g = p["sources"][0]
        s = res.sensor
        return (f"additive glow from a source at ({g['x_frac'] * (s.sensor_width_px - 1):.0f}, "
                f"{g['y_frac'] * (s.sensor_height_px - 1):.0f}) sensor px, {g['amplitude_e_per_s'] * res.exptime_s:.3g} "
                f"e- at its centre, std {g['sigma_x_px']:.0f} px (the thesis' bivariate-normal glow, Annex V), growing "
                "with exposure: amplifier glow")
    return (f"additive glow rising towards the {p['edge']} edge, {p['amplitude_e_per_s'] * res.exptime_s:.3g} "
            f"e- at the edge (e-folding {p['scale_px']:.0f} px), growing with exposure: amplifier glow")


#: the search chooses a form (an edge law, a Gaussian source or an emitter), where (an edge, or a centre: 2) and a
#: scale
_GLOW_SIGNATURE = LinearSignature(
    _glow_variants, _glow_words,
    pattern="additive glow decaying away from an edge, a corner, a source point or an emitter above the sensor",
    extra_k=3, refine=_glow_refine, form=lambda label: label.split("|")[0] if label[:2] in ("g|", "e|") else "edge",
    check=_glow_check)
#: dark charge and a response to a light of one level (a flat) of the same shape are one image
_GLOW_SIGNATURE.untold = dark_field_untold((), ("vignetting",))
_GLOW_SIGNATURE.rebuild = _rebuild


# --- adapter -----------------------------------------------------------------------------------------------

class GlowPoint(BaseModel):
    """Where a glow source (a Gaussian's centre, an emitter's foot) sits on the sensor plane."""

    model_config = ConfigDict(extra="forbid")
    x_frac: float = Field(1.0, ge=-1, le=2, description="centre or foot, fraction of the sensor width (0 = column 0)")
    y_frac: float = Field(0.0, ge=-1, le=2, description="centre or foot, fraction of the sensor height (0 = row 0)")


class GlowSource(GlowPoint):
    amplitude_e_per_s: float = Field(0.5, ge=0, le=1e6, description="glow rate at the centre [e-/s/pixel]")
    sigma_x_px: float = Field(500.0, gt=0, description="std along x [pixels]")
    sigma_y_px: float = Field(500.0, gt=0, description="std along y [pixels]")
    rho: float = Field(0.0, gt=-1, lt=1, description="correlation of the bivariate normal [1]")


class GlowEmitter(GlowPoint):
    amplitude_e_per_s: float = Field(0.5, ge=0, le=1e6, description="glow rate below the emitter [e-/s/pixel]")
    height_px: float = Field(100.0, gt=0, description="height of the emitter off the sensor plane [pixels]")


class AmpGlowParams(EffectParams):
    model: Literal["gaussian", "edge", "emitter"] = "gaussian"
    sources: list[GlowSource] = Field(default_factory=lambda: [GlowSource()])
    emitters: list[GlowEmitter] = Field(default_factory=lambda: [GlowEmitter()],
                                        description="emitter model: point emitters (irradiance (1 + r^2/h^2)^-1.5)")
    edge: Literal["left", "right", "top", "bottom", "bottom-left", "bottom-right", "top-left", "top-right"] = "bottom-right"
    amplitude_e_per_s: float = Field(0.5, ge=0, le=1e6, description="edge model: rate at the edge [e-/s/pixel]")
    scale_px: float = Field(300.0, gt=0, description="edge model: e-folding distance [pixels]")


@register_effect
class AmpGlow(Effect):
    """Amplifier glow: additive dark signal rising towards an edge or corner, proportional to exposure time.

    ``gaussian``: a sum of bivariate-normal glow maps (thesis Annex V); ``edge``: ``A exp(-d/L)`` with ``d``
    the distance to an edge or corner; ``emitter``: point emitters off the sensor plane, ``A (1 + r^2/h^2)^-1.5``
    (:func:`emitter_rate`). Adds ``rate x t`` to the mean before the shot-noise draw.
    """

    name = "amp_glow"
    field_kind = "additive"
    scaling = "exposure"
    identity = {"sources": [{"amplitude_e_per_s": 0.0}]}
    stages = (Stage.DARK,)
    signature = _GLOW_SIGNATURE
    Params = AmpGlowParams

    def rate_map(self, tile: Tile) -> np.ndarray:
        """Glow rate [e-/s] on the tile's pixels."""
        p, s = self.params, self.sensor
        ys, xs = tile.pixel_centres()
        out = np.zeros((ys.size, xs.size), dtype=np.float32)
        if p.model == "edge":
            edge_rate(ys, xs, s.sensor_height_px, s.sensor_width_px, p.edge, p.amplitude_e_per_s, p.scale_px, out)
        elif p.model == "emitter":
            for g in p.emitters:
                emitter_rate(ys, xs, g.x_frac * (s.sensor_width_px - 1), g.y_frac * (s.sensor_height_px - 1),
                             g.amplitude_e_per_s, g.height_px, out)
        else:
            for g in p.sources:
                bivariate_normal_rate(ys, xs, g.x_frac * (s.sensor_width_px - 1), g.y_frac * (s.sensor_height_px - 1),
                                      g.amplitude_e_per_s, g.sigma_x_px, g.sigma_y_px, g.rho, out)
        return out

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        if not tile.exptime_s:
            return
        t = np.float32(tile.exptime_s)
        p, s = self.params, self.sensor
        if p.model != "edge":
            m = self.rate_map(tile)
            m *= t
            data += m
            return
        # the edge law in blocks of rows that stay in the cache (its float64 distances are 8 bytes a pixel):
        # the same values as rate_map(tile) * t added, without a tile-sized temporary
        ys, xs = tile.pixel_centres()
        step = max(1, EDGE_BLOCK_PIXELS // max(1, xs.size))
        exact = _exact_squares(np.r_[ys, xs, ys - (s.sensor_height_px - 1), xs - (s.sensor_width_px - 1)])
        for r in range(0, ys.size, step):
            m = np.zeros((min(step, ys.size - r), xs.size), dtype=np.float32)
            edge_rate(ys[r:r + step], xs, s.sensor_height_px, s.sensor_width_px, p.edge, p.amplitude_e_per_s,
                      p.scale_px, m, exact)
            m *= t
            data[r:r + step] += m
