"""Sky-to-pixel projection: the frame's WCS, gnomonic TAN plus optional SIP distortion (thesis sect. 3.8).

FITS WCS conventions (Greisen & Calabretta 2002, A&A 395, 1061; Calabretta & Greisen 2002, A&A 395, 1077):
CRPIX is 1-based. The pointing (CRVAL) is the telescope's optical axis, which falls on the centre of the
full sensor, ``((W - 1) / 2, (H - 1) / 2)`` in 0-based sensor pixels; a read-out window (ROI) and binning
move CRPIX, not CRVAL (:func:`axis_crpix`). East is to the left (``CD1_1 < 0``) and north up for roll 0,
the sky as a telescope with two mirrors shows it; ``[telescope] parity = +1`` gives the mirror image
(det CD > 0, east to the right; :func:`tan_wcs`).

SIP distortion (Shupe et al. 2005, ASP Conf. Ser. 347, 491). With pixel offsets (x, y) = pixel - CRPIX,
the forward polynomials give the undistorted ("ideal") offsets that the CD matrix maps to the sky,

    X = x + sum_{p,q} A_p_q x^p y^q,        Y = y + sum_{p,q} B_p_q x^p y^q,       1 <= p + q <= order.

A :class:`Sip` holds them in **unbinned sensor pixels about the optical axis** (scene pixel axes); a frame
binned by b uses offsets x_b = x / b, so its coefficients are A_p_q b^(p + q - 1) (the ideal offsets scale
the same way), with CD b times larger; a read-out window only moves CRPIX. The reverse polynomials AP, BP
(x = X + AP(X, Y), y = Y + BP(X, Y)) that the standard asks for are fitted here by linear least squares
on a grid (thesis Algorithm 1, :func:`fit_reverse`); the rendering itself inverts the forward polynomials
iteratively (astropy ``all_world2pix``), so the frame's sources sit where its own forward SIP puts them.

From the optics. :func:`optics.distortion.fit_sip` works in the optics' focal-plane frame (u, v), with
pixel offsets (u, v) / pitch and CD = -(pitch / f) I: a star at field angles (theta_x, theta_y) images
at -f (tan theta_x, tan theta_y), theta_x towards east and theta_y towards north. Read as pixels (x, y) =
(u, v) / pitch that is the mirror image of the sky (det CD > 0); the scene's camera reads the focal plane
as x = u / pitch, y = -v / pitch (:data:`FOCAL_PLANE_Y_SIGN`), which keeps the standard orientation. The
same star then has y = -y_optics, so :func:`sip_from_optics` takes A_p_q -> (-1)^q A_p_q and
B_p_q -> (-1)^(q + 1) B_p_q (exact; the ``art`` and ``bare`` designs are symmetric about the u axis, so
for them only the sign convention changes, not the distortion).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import numpy as np
from astropy.wcs import WCS
from astropy.wcs import Sip as _AstropySip

from detector.effects.image_plane import decentering_shift

from .errors import SceneError

SIP_MAX_ORDER = 9
#: the scene reads the optics' focal plane (u, v) as pixel offsets (u / pitch, FOCAL_PLANE_Y_SIGN v / pitch)
FOCAL_PLANE_Y_SIGN = -1.0
REVERSE_GRID = 48  # points per axis of the reverse fit (Algorithm 1)
REVERSE_WARN_PX = 0.01  # largest acceptable reverse residual [pixel]
RADIAL_K_MAX = 1e-4  # bound of radial_k_per_px2 [px^-2] (that of the detector's distortion effect)
DECENTERING_MAX = 1e-3  # bound of decentering_p1/p2_per_px [px^-1] (that of the detector's distortion effect)
RADIAL_ORDER = 7  # least SIP order a radial term is fitted with (terms r^3, r^5, r^7 of 1 / (1 + k r^2))
RADIAL_MIN_FACTOR = 0.5  # 1 + k r^2 must stay above this over the fitted area (no fold-over)
_COEF = re.compile(r"^(a|b)_(\d)_(\d)$")


def poly_terms(order: int) -> list[tuple[int, int]]:
    """Exponents (p, q) of the SIP terms x^p y^q with 1 <= p + q <= order."""
    return [(p, q) for p in range(order + 1) for q in range(order + 1 - p) if p + q >= 1]


def eval_poly(coef: dict, x, y):
    """sum c x^p y^q over ``coef`` = {(p, q): c} (0 for an empty dict)."""
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    out = np.zeros(np.broadcast(x, y).shape)
    for (p, q), c in coef.items():
        if c:
            out = out + c * x ** p * y ** q
    return out


@dataclass(frozen=True)
class Sip:
    """Forward SIP polynomials A, B in unbinned sensor pixels about the optical axis (see the module notes).

    Parameters
    ----------
    order : polynomial order (1..9) of A and B
    a, b : {(p, q): coefficient [pixel^(1 - p - q)]}, 1 <= p + q <= order
    reverse_order : order of the fitted reverse polynomials AP, BP (default ``order + 2``, at most 9)
    source : where the coefficients come from (``"scene"`` or ``"optics"``), for the FITS header
    info : fit statistics of the optics (``rms_px``, ``max_distortion_px``, ...), informative only
    """

    order: int
    a: dict
    b: dict
    reverse_order: int | None = None
    source: str = "scene"
    info: dict = field(default_factory=dict, compare=False)

    @property
    def rev_order(self) -> int:
        return int(self.reverse_order or min(self.order + 2, SIP_MAX_ORDER))

    def forward(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Ideal offsets (X, Y) = (x + A(x, y), y + B(x, y)) [pixel] of offsets ``x, y`` from CRPIX."""
        return np.asarray(x, float) + eval_poly(self.a, x, y), np.asarray(y, float) + eval_poly(self.b, x, y)

    def binned(self, binning: int) -> Sip:
        """The same distortion in pixels ``binning`` times larger: A_p_q b^(p + q - 1)."""
        if binning == 1:
            return self
        s = float(binning)
        a = {k: v * s ** (k[0] + k[1] - 1) for k, v in self.a.items()}
        b = {k: v * s ** (k[0] + k[1] - 1) for k, v in self.b.items()}
        return Sip(self.order, a, b, self.reverse_order, self.source, self.info)

    def max_shift_px(self, x_range, y_range, n: int = 33) -> float:
        """Largest |ideal - pixel| offset [pixel] over the rectangle ``x_range`` x ``y_range`` (offsets)."""
        xs = np.linspace(*x_range, n)
        ys = np.linspace(*y_range, n)
        X, Y = np.meshgrid(xs, ys)
        u, v = self.forward(X, Y)
        return float(np.max(np.hypot(u - X, v - Y)))


def fit_reverse(sip: Sip, x_range, y_range, order: int | None = None, n: int = REVERSE_GRID
                ) -> tuple[dict, dict, float, float]:
    """Reverse SIP polynomials by least squares on a grid (thesis sect. 3.8, Algorithm 1).

    On an ``n x n`` grid of pixel offsets (x, y) spanning ``x_range`` x ``y_range`` the forward
    polynomials give the ideal offsets (X, Y); AP and BP are the least-squares solutions of

        x - X = sum AP_p_q X^p Y^q,       y - Y = sum BP_p_q X^p Y^q,        1 <= p + q <= order,

    with the columns scaled by the largest |offset| (conditioning). Returns ``(ap, bp, rms_px, max_px)``,
    the residuals |(X + AP, Y + BP) - (x, y)| over the grid [pixel].
    """
    order = int(order or sip.rev_order)
    xs = np.linspace(x_range[0], x_range[1], n)
    ys = np.linspace(y_range[0], y_range[1], n)
    x, y = (g.ravel() for g in np.meshgrid(xs, ys))
    X, Y = sip.forward(x, y)
    terms = poly_terms(order)
    scale = max(float(np.max(np.abs(X))), float(np.max(np.abs(Y))), 1.0)
    M = np.stack([(X / scale) ** p * (Y / scale) ** q for p, q in terms], axis=-1)
    sol, *_ = np.linalg.lstsq(M, np.stack([x - X, y - Y], axis=-1), rcond=None)
    ap = {t: float(c / scale ** (t[0] + t[1])) for t, c in zip(terms, sol[:, 0])}
    bp = {t: float(c / scale ** (t[0] + t[1])) for t, c in zip(terms, sol[:, 1])}
    res = np.hypot(X + eval_poly(ap, X, Y) - x, Y + eval_poly(bp, X, Y) - y)
    return ap, bp, float(np.sqrt(np.mean(res ** 2))), float(res.max())


def _matrix(coef: dict, order: int) -> np.ndarray:
    m = np.zeros((order + 1, order + 1))
    for (p, q), c in coef.items():
        m[p, q] = c
    return m


def axis_crpix(sensor, binned: bool = True) -> tuple[float, float]:
    """1-based CRPIX of the optical axis (the full sensor's centre) in the read-out window, binned or not."""
    b = sensor.binning if binned else 1
    cx = (sensor.sensor_width_px - 1) / 2.0 - sensor.roi_x0
    cy = (sensor.sensor_height_px - 1) / 2.0 - sensor.roi_y0
    return (cx - (b - 1) / 2.0) / b + 1.0, (cy - (b - 1) / 2.0) / b + 1.0


def tan_wcs(ra_deg: float, dec_deg: float, roll_deg: float, scale_arcsec: float, shape: tuple[int, int],
            crpix: tuple[float, float] | None = None, sip: Sip | None = None, margin_px: float = 16.0,
            parity: int = -1) -> WCS:
    """A TAN (or TAN-SIP) WCS, ``scale_arcsec`` per pixel, north rotated by ``roll_deg``.

    Parameters
    ----------
    ra_deg, dec_deg : the optical axis (CRVAL) [deg]
    roll_deg : position angle of the camera [deg]
    scale_arcsec : pixel scale of this frame (binning included) [arcsec/pixel]
    shape : (rows, cols) of the frame
    crpix : 1-based position of the optical axis; default the frame's centre
    sip : forward distortion **in this frame's pixels** (already :meth:`Sip.binned`); the reverse
        polynomials are fitted over the frame plus ``margin_px`` (:func:`fit_reverse`)
    parity : sign of det(CD) [1]: -1 (default) the sky as seen looking up, +1 its east-west mirror image

    With s the scale and r the roll, the CD matrix (Calabretta & Greisen 2002, eq. 1; CDELT1 = -p s and
    CROTA2 = -r in the older notation) is

        CD = s [[p cos r, -p sin r], [sin r, cos r]],      det CD = p s^2,      p = parity,

    so north points along (sin r, cos r) in pixels for either parity (``roll_deg`` is where north is) and
    east along p (cos r, -sin r): to the left (``CD1_1 < 0``) for p = -1 and roll 0, as on the sky seen
    through a telescope with an even number of mirrors; to the right for p = +1 (an odd number of
    reflections, a diagonal, or a camera reading its columns in reverse: a FITS header with det CD > 0).
    p = +1 mirrors the sky's east-west axis (the first intermediate world coordinate), not the pixels: for
    roll 0 that is x -> 2 CRPIX1 - x. With ``sip`` the WCS has CTYPE ``RA---TAN-SIP`` and carries the fitted reverse
    residuals as ``wcs.sip_reverse_rms_px`` / ``wcs.sip_reverse_max_px`` (attributes, not cards).
    """
    ny, nx = shape
    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    w.wcs.crval = [ra_deg, dec_deg]
    w.wcs.crpix = list(crpix) if crpix is not None else [(nx + 1) / 2.0, (ny + 1) / 2.0]
    s = scale_arcsec / 3600.0
    c, si = np.cos(np.radians(roll_deg)), np.sin(np.radians(roll_deg))
    if parity not in (-1, 1):
        raise ValueError(f"parity {parity!r}: -1 or +1")
    w.wcs.cd = np.array([[parity * s * c, -parity * s * si], [s * si, s * c]])
    w.wcs.radesys = "ICRS"
    w.pixel_shape = (nx, ny)
    if sip is not None:
        x0, y0 = w.wcs.crpix[0] - 1.0, w.wcs.crpix[1] - 1.0  # 0-based axis
        xr = (-0.5 - margin_px - x0, nx - 0.5 + margin_px - x0)
        yr = (-0.5 - margin_px - y0, ny - 0.5 + margin_px - y0)
        ap, bp, rms, mx = fit_reverse(sip, xr, yr)
        ro = sip.rev_order
        w.wcs.ctype = ["RA---TAN-SIP", "DEC--TAN-SIP"]
        w.sip = _AstropySip(_matrix(sip.a, sip.order), _matrix(sip.b, sip.order), _matrix(ap, ro),
                            _matrix(bp, ro), w.wcs.crpix)
        w.sip_reverse_rms_px, w.sip_reverse_max_px = rms, mx
    return w


# ------------------------------------------------------------------------------------ scene and optics
def sip_from_table(table: dict, *, file: str | None = None, allow_coefficients: bool = True) -> dict:
    """Validate a ``[telescope.sip]`` table; return ``{"order", "reverse_order", "a", "b"}``.

    Keys: ``order`` (1..9, required when coefficients are given), ``reverse_order`` (optional, 1..9,
    >= order), coefficients ``a_p_q`` / ``b_p_q`` (unbinned sensor pixels about the optical axis,
    1 <= p + q <= order), ``radial_k_per_px2``: a radial distortion ``r' = r (1 + k r^2)`` about the optical
    axis [sensor px^-2], and ``decentering_p1_per_px`` / ``decentering_p2_per_px``: Brown's (1966) decentering
    terms [sensor px^-1], composed with the rest (:func:`with_radial`; with them, ``distortion = 'sip'`` needs
    no coefficient). Errors name ``telescope.sip.KEY``. Returns ``{"order", "reverse_order", "a", "b",
    "radial_k", "decentering"}``.
    """

    table = dict(table or {})
    out = {"order": None, "reverse_order": None, "a": {}, "b": {}, "radial_k": 0.0, "decentering": (0.0, 0.0)}
    if "radial_k_per_px2" in table:
        v = table.pop("radial_k_per_px2")
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or abs(v) > RADIAL_K_MAX:
            raise SceneError(f"invalid value {v!r}", key="telescope.sip.radial_k_per_px2", file=file,
                             expected=f"a finite number [px^-2] in [-{RADIAL_K_MAX:g}, {RADIAL_K_MAX:g}]")
        out["radial_k"] = float(v)
    dec = []
    for key in ("decentering_p1_per_px", "decentering_p2_per_px"):
        v = table.pop(key, 0.0)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or abs(v) > DECENTERING_MAX:
            raise SceneError(f"invalid value {v!r}", key=f"telescope.sip.{key}", file=file,
                             expected=f"a finite number [px^-1] in [-{DECENTERING_MAX:g}, {DECENTERING_MAX:g}]")
        dec.append(float(v))
    out["decentering"] = (dec[0], dec[1])
    for key in ("order", "reverse_order"):
        if key in table:
            v = table.pop(key)
            if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= SIP_MAX_ORDER:
                raise SceneError(f"invalid value {v!r}", key=f"telescope.sip.{key}", file=file,
                                 expected=f"an integer from 1 to {SIP_MAX_ORDER}")
            out[key] = v
    for key, v in table.items():
        m = _COEF.match(key)
        if not m:
            raise SceneError("unknown key", key=f"telescope.sip.{key}", file=file,
                             expected="order, reverse_order, radial_k_per_px2, decentering_p1_per_px, "
                             "decentering_p2_per_px or coefficients a_p_q / b_p_q (e.g. a_3_0)")
        if not allow_coefficients:
            raise SceneError("coefficients given with distortion = 'optics'", key=f"telescope.sip.{key}",
                             file=file, expected="distortion = 'sip' for coefficients from the scene, or only "
                             "order / reverse_order with 'optics'")
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise SceneError(f"invalid value {v!r}", key=f"telescope.sip.{key}", file=file,
                             expected="a finite number [pixel^(1-p-q)]")
        p, q = int(m.group(2)), int(m.group(3))
        if p + q < 1:
            raise SceneError("a constant term", key=f"telescope.sip.{key}", file=file,
                             expected="terms with 1 <= p + q <= order (CRPIX absorbs a constant)")
        out[m.group(1)][(p, q)] = float(v)
    degree = max([p + q for p, q in list(out["a"]) + list(out["b"])], default=0)
    field_terms = bool(out["radial_k"] or any(out["decentering"]))
    if allow_coefficients and not (field_terms and not out["a"] and not out["b"]):
        if out["order"] is None:
            raise SceneError("missing", key="telescope.sip.order", file=file,
                             expected=f"the polynomial order (>= {max(degree, 1)})")
        if not out["a"] and not out["b"]:
            raise SceneError("no coefficient", key="telescope.sip", file=file,
                             expected="coefficients a_p_q / b_p_q, or distortion = 'none'")
        if degree > out["order"]:
            bad = next(f"{n}_{p}_{q}" for n in "ab" for p, q in out[n] if p + q == degree)
            raise SceneError(f"a term of degree {degree} with order = {out['order']}", key=f"telescope.sip.{bad}",
                             file=file, expected=f"p + q <= order, or order >= {degree}")
    if out["reverse_order"] is not None and out["order"] is not None and out["reverse_order"] < out["order"]:
        raise SceneError(f"reverse_order {out['reverse_order']} below order {out['order']}",
                         key="telescope.sip.reverse_order", file=file, expected=f">= {out['order']}")
    return out


def sip_from_optics(fit: dict, sensor, *, reverse_order: int | None = None, parity: int = -1) -> Sip:
    """A :class:`Sip` in scene pixel axes from an :func:`optics.distortion.fit_sip` result.

    The fit's CRPIX must be the centre of the full sensor (the optical axis); its pixel offsets are
    (u, v) / pitch, turned into scene offsets (x, y) = (s_x u, s_y v) / pitch with s_y =
    :data:`FOCAL_PLANE_Y_SIGN` and s_x = -parity (a mirrored camera, ``parity = +1``, reads the focal plane's
    u axis reversed). The ideal offsets transform the same way, X = s_x (u + A(u, v)), so

        A'_p_q = s_x^(p + 1) s_y^q A_p_q,        B'_p_q = s_x^p s_y^(q + 1) B_p_q

    (for parity -1: A_p_q (-1)^q, B_p_q (-1)^(q+1), the module notes).
    """
    cx, cy = (sensor.sensor_width_px + 1) / 2.0, (sensor.sensor_height_px + 1) / 2.0
    if abs(float(fit["CRPIX1"]) - cx) > 1e-6 or abs(float(fit["CRPIX2"]) - cy) > 1e-6:
        raise ValueError(f"optics SIP fitted about CRPIX ({fit['CRPIX1']}, {fit['CRPIX2']}), not the sensor centre "
                         f"({cx}, {cy}): fit it with shape = (sensor_height_px, sensor_width_px)")
    order = int(fit["A_ORDER"])
    a, b = {}, {}
    sy, sx = FOCAL_PLANE_Y_SIGN, -float(parity)
    for key, v in fit.items():
        m = re.match(r"^(A|B)_(\d+)_(\d+)$", key)
        if not m:
            continue
        p, q = int(m.group(2)), int(m.group(3))
        if m.group(1) == "A":
            a[(p, q)] = float(v) * sx ** (p + 1) * sy ** q
        else:
            b[(p, q)] = float(v) * sx ** p * sy ** (q + 1)
    info = {k: fit[k] for k in ("rms_px", "max_px", "max_distortion_px", "effective_focal_length_mm",
                                "wavelength_nm", "method") if k in fit}
    return Sip(order, a, b, reverse_order, "optics", info)


def with_radial(sip: Sip | None, k_per_px2: float, x_range, y_range, n: int = REVERSE_GRID, *,
                file: str | None = None, decentering: tuple[float, float] = (0.0, 0.0)) -> Sip:
    """``sip`` (None: no distortion) composed with a radial distortion ``r' = r (1 + k r^2)`` about the axis
    and Brown's decentering terms ``decentering = (p1, p2)`` [px^-1] (content moved by ``dx = p1 (r^2 + 2 x^2)
    + 2 p2 x y``, ``dy = p2 (r^2 + 2 y^2) + 2 p1 x y``; their first-order inverse is subtracted from ``p'`` as
    :func:`detector.effects.image_plane.radial_distortion` does).

    The radial term moves the image content at radius ``r`` from the optical axis to ``r (1 + k r^2)``
    [sensor px] (k > 0 pincushion), after the distortion ``sip`` describes: the recorded pixel offset ``p``
    holds what ``sip`` put at ``p' = p / (1 + k |p|^2)`` (the first-order inverse of ``r' = r (1 + k r^2)``,
    the mapping :func:`detector.effects.image_plane.radial_distortion` resamples with), so the forward
    polynomials of the whole are

        (X, Y) = p' + (A(p'), B(p')),        p' = p / (1 + k |p|^2),

    fitted by linear least squares on an ``n x n`` grid of offsets over ``x_range`` x ``y_range`` (unbinned
    sensor pixels from the axis) at order ``max(sip.order, 7)`` (at most 9): the rational factor's
    expansion ``1 - u + u^2 - u^3 ...`` (``u = k r^2``) has the odd degrees 3, 5, 7. The fit's residuals
    [px] are in ``info`` (``radial_fit_rms_px``, ``radial_fit_max_px``).
    """
    xs = np.linspace(x_range[0], x_range[1], n)
    ys = np.linspace(y_range[0], y_range[1], n)
    x, y = (g.ravel() for g in np.meshgrid(xs, ys))
    f = 1.0 + k_per_px2 * (x * x + y * y)
    if f.min() < RADIAL_MIN_FACTOR:
        r = float(np.sqrt(np.max(x * x + y * y)))
        raise SceneError(f"radial distortion k = {k_per_px2:g} px^-2 folds the field over at {r:.0f} px from the axis",
                         key="telescope.sip.radial_k_per_px2", file=file, expected=f"|k| r^2 below {1 - RADIAL_MIN_FACTOR:g} "
                         f"over the frame (|k| < {(1 - RADIAL_MIN_FACTOR) / r ** 2:.3g} px^-2 here)")
    xp, yp = x / f, y / f
    p1, p2 = decentering
    if p1 or p2:
        dx, dy = decentering_shift(x, y, p1, p2)
        xp, yp = xp - dx, yp - dy
    if sip is not None:
        X, Y = sip.forward(xp, yp)
        order, rev, source, info = max(sip.order, RADIAL_ORDER), sip.reverse_order, sip.source, dict(sip.info)
    else:
        X, Y = xp, yp
        order, rev, source, info = RADIAL_ORDER, None, "scene", {}
    order = min(order, SIP_MAX_ORDER)
    terms = poly_terms(order)
    scale = max(float(np.max(np.abs(x))), float(np.max(np.abs(y))), 1.0)
    M = np.stack([(x / scale) ** p * (y / scale) ** q for p, q in terms], axis=-1)
    sol, *_ = np.linalg.lstsq(M, np.stack([X - x, Y - y], axis=-1), rcond=None)
    a = {t: float(c / scale ** (t[0] + t[1])) for t, c in zip(terms, sol[:, 0])}
    b = {t: float(c / scale ** (t[0] + t[1])) for t, c in zip(terms, sol[:, 1])}
    res = np.hypot(x + eval_poly(a, x, y) - X, y + eval_poly(b, x, y) - Y)
    if p1 or p2:
        info.update(decentering_p1_per_px=float(p1), decentering_p2_per_px=float(p2))
    info.update(radial_k_per_px2=float(k_per_px2), radial_fit_rms_px=float(np.sqrt(np.mean(res ** 2))),
                radial_fit_max_px=float(res.max()))
    if rev is not None and rev < order:
        rev = order
    return Sip(order, a, b, rev, source, info)
