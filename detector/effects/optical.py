"""Optical effects that act on the focal-plane illumination: vignetting.

The relative illumination RI(u, v) multiplies the expected photo-electrons of every source and of the
background (RESPONSE stage; dark signal is not vignetted). Focal-plane coordinates (u, v) [mm] are
measured from the sensor's centre (the optical axis) along the columns (u) and rows (v):
``u = (x - (W - 1)/2) * pitch``, ``v = (y - (H - 1)/2) * pitch`` for full-sensor pixel centres (x, y).

Two forms:

* ``map_file``: a FITS map with linear (u, v) axes in mm, as written by ``newtsim optics vignetting --fits``
  (the ray-traced vignetting of a design; ``optics`` writes it, ``detector`` only reads the file).
  Interpolated with a bicubic spline (bilinear for fewer than 4 samples per axis); outside the map
  the edge value is held.
* a radial polynomial ``RI = 1 - a2 rho^2 - a4 rho^4`` with rho = r / r_corner (r_corner: half the sensor's
  diagonal), the classic form of natural vignetting (cos^4 law expanded: Slater, Photographic Systems
  for Engineers, 1966; the a2 term dominates for small fields).

References: W. J. Smith, Modern Optical Engineering, 4th ed. (2008), sect. 9.5 (vignetting, cos^4 law).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pydantic import Field, model_validator

from ..errors import DetectorError
from ..signatures import (
    LINEAR_SEARCH_PIXELS,
    LinearSignature,
    Variant,
    fit_linear,
    light_law_check,
    light_law_untold,
    search_sample,
)
from ..significance import DETECTION_SIGMA
from .base import Effect, EffectParams, Stage, Tile, register_effect


def radial_vignetting(u_mm: np.ndarray, v_mm: np.ndarray, r_corner_mm: float, a2: float, a4: float,
                      centre_mm: tuple[float, float] = (0.0, 0.0), a2_cos2: float = 0.0,
                      a2_sin2: float = 0.0) -> np.ndarray:
    """RI = 1 - (a2 + a2_cos2 cos 2phi + a2_sin2 sin 2phi) rho^2 - a4 rho^4, rho = |(u, v) - centre| / r_corner,
    phi its azimuth from the columns' axis, clipped to [0, 1] [1]. The azimuthal terms make the fall-off
    elliptical (its rho^2 rate changing with direction, ``(du^2 - dv^2) a2_cos2 + 2 du dv a2_sin2``): the
    vignetting of an off-axis field, whose pupil is clipped by two apertures into a cat's eye (Smith 2008, Modern
    Optical Engineering, 4th ed., sect. 6.5), or of a sensor tilted to the optical axis."""
    du, dv = u_mm - centre_mm[0], v_mm - centre_mm[1]
    rho2 = (du ** 2 + dv ** 2) / r_corner_mm ** 2
    out = 1.0 - a2 * rho2 - a4 * rho2 * rho2
    if a2_cos2 or a2_sin2:
        out = out - (a2_cos2 * (du ** 2 - dv ** 2) + a2_sin2 * 2.0 * du * dv) / r_corner_mm ** 2
    return np.clip(out, 0.0, 1.0)


def read_vignetting_map(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(u_mm, v_mm, RI[v, u]) from a FITS map with linear axes CRVAL/CDELT/CRPIX in mm."""
    import warnings

    from astropy.io import fits

    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("error", message=".*truncated.*")  # a truncated map is an error, not zeros
            with fits.open(path, memmap=False) as hdul:
                h = hdul[0].header
                ri = np.asarray(hdul[0].data, dtype=np.float64)
    except Exception as exc:  # noqa: BLE001  (astropy raises OSError/ValueError/TypeError and the warning)
        raise DetectorError(f"cannot read vignetting map ({type(exc).__name__}: {str(exc).splitlines()[0]})",
                            key="effects.vignetting.map_file",
                            expected="a FITS map from 'newtsim optics vignetting --fits'", file=str(path)) from None
    if ri.ndim != 2 or not all(k in h for k in ("CRVAL1", "CDELT1", "CRVAL2", "CDELT2")):
        raise DetectorError("not a vignetting map (needs a 2-D image with CRVAL/CDELT axes in mm)",
                            key="effects.vignetting.map_file", expected="a FITS map from 'newtsim optics vignetting"
                            " --fits'", file=str(path))
    u = h["CRVAL1"] + (np.arange(ri.shape[1]) + 1 - h.get("CRPIX1", 1.0)) * h["CDELT1"]
    v = h["CRVAL2"] + (np.arange(ri.shape[0]) + 1 - h.get("CRPIX2", 1.0)) * h["CDELT2"]
    return u, v, ri


#: a vignetting map whose spline has at most this many coefficients along u is evaluated as two matrix products
#: (the bicubic spline of a traced map: 9 x 9; fitpack's grid evaluation costs ~3 times more on a 240 x 14192
#: band); a finer map keeps fitpack's evaluation (the dense design matrix would grow with it)
SEPARABLE_MAP_COEFS = 32


def map_interpolator(u: np.ndarray, v: np.ndarray, ri: np.ndarray):
    """A callable (v_mm 1-D, u_mm 1-D) -> RI on that grid, edge values held outside the map."""
    from scipy.interpolate import BSpline, RectBivariateSpline

    if len(u) == 1 and len(v) == 1:
        return lambda vv, uu: np.full((len(vv), len(uu)), ri[0, 0])
    ku = min(3, len(u) - 1) if len(u) >= 4 else min(1, len(u) - 1)
    kv = min(3, len(v) - 1) if len(v) >= 4 else min(1, len(v) - 1)
    if len(u) == 1:
        return lambda vv, uu: np.repeat(np.interp(vv, v, ri[:, 0])[:, None], len(uu), axis=1)
    if len(v) == 1:
        return lambda vv, uu: np.repeat(np.interp(uu, u, ri[0, :])[None, :], len(vv), axis=0)
    spl = RectBivariateSpline(v, u, ri, kx=kv, ky=ku)
    tv, tu, c = spl.tck
    coef = c.reshape(len(tv) - kv - 1, len(tu) - ku - 1)
    if coef.shape[1] > SEPARABLE_MAP_COEFS:
        def f(vv, uu):
            return spl(np.clip(vv, v[0], v[-1]), np.clip(uu, u[0], u[-1]), grid=True)

        return f

    def separable(vv, uu):
        """The same tensor-product spline as ``spl(vv, uu, grid=True)``: sum_kl c_kl B_k(v) B_l(u) as two
        products with the B-spline design matrices (equal to ~1e-15 relative, docs/performance.md)."""
        vv, uu = np.clip(np.ravel(vv), v[0], v[-1]), np.clip(np.ravel(uu), u[0], u[-1])
        rows = BSpline.design_matrix(vv, tv, kv).toarray() @ coef  # (len(vv), coefficients along u)
        return rows @ BSpline.design_matrix(uu, tu, ku).toarray().T

    return separable


#: centre offsets of the radial model tried by the diagnosis, fractions of the half-diagonal (a decentred or
#: tilted secondary moves the vignetting centre off the optical axis)
_CENTRE_GRID = (-0.2, -0.1, 0.0, 0.1, 0.2)


#: the largest |a2|, |a4| of the radial model [1]: the illumination is clipped to [0, 1] and the fitted form must
#: take light away over the pixels it is seen on (_vignetting_check), so the bound only keeps the numbers finite;
#: a fall-off that saturates inside a window (a cos^4 or Lorentzian law about a window-scale radius) needs
#: |a4| > 1 (a2 = 0.77, a4 = -1.09 for a 22 % deep cos^4 in a 256 px window)
VIGNETTING_COEF_MAX = 16.0


def _offsets_mm(res, cx_mm: float, cy_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """The read-out window's columns and rows [mm] from a radial model's centre (``cx_mm``, ``cy_mm`` off the
    sensor's centre): the 1-D ``u`` of ``res.xs`` and ``v`` of ``res.ys``."""
    s = res.sensor
    pitch_mm = s.pixel_pitch_um * 1e-3
    u = (np.asarray(res.xs, np.float64) - (s.sensor_width_px - 1) / 2.0) * pitch_mm - cx_mm
    v = (np.asarray(res.ys, np.float64) - (s.sensor_height_px - 1) / 2.0) * pitch_mm - cy_mm
    return u, v


def _pixels_at(res, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rows, columns, minus the photo-signal [ADU, float64]) at flat pixel indices ``idx``, kept on ``res`` for
    the last index array asked (a centre search evaluates hundreds of variants on the same search sample)."""
    key = (idx.__array_interface__["data"][0], idx.shape, idx.strides)
    got = res._flat.get("vignetting_pixels")
    if got is None or got[1] != key:
        y, x = np.divmod(idx, res.photo_adu.shape[1])
        got = (idx, key, y, x, -(res.photo_adu.ravel()[idx].astype(np.float64)))
        res._flat["vignetting_pixels"] = got  # ``idx`` itself kept: its memory cannot hold another array meanwhile
    return got[2], got[3], got[4]


def _vignetting_variant(res, cx_mm: float, cy_mm: float, radius_mm: float | None = None, elliptical: bool = False,
                        quartic: bool = False):
    """The radial polynomial about a centre (``a2``, ``a4``); ``elliptical``: with the azimuthal terms of its rho^2
    rate (``a2_cos2``, ``a2_sin2``: :func:`radial_vignetting`); ``quartic``: ``a4`` alone, ``a2 = 0``, the
    polynomial's boundary of its own bound ``a2 >= 0``. A fall-off steeper than rho^4 (a power law, the onset of a
    mechanical vignetting) has its unbounded least squares at ``a2 < 0``, a light that rises from the centre, which
    the bound refuses; the least squares under the bound then lies on it (a quadratic objective's minimum over a
    half-plane, Lawson & Hanson 1974, Solving Least Squares Problems, ch. 23: non-negative least squares)."""
    s = res.sensor
    pitch_mm = s.pixel_pitch_um * 1e-3
    u, v = _offsets_mm(res, cx_mm, cy_mm)
    r_corner = radius_mm or 0.5 * pitch_mm * float(np.hypot(s.sensor_width_px, s.sensor_height_px))
    photo = res.photo_adu

    def terms(uu, vv, p):
        rho2 = (uu ** 2 + vv ** 2) / r_corner ** 2
        if quartic:
            return [-p * rho2 * rho2]
        out = [-p * rho2, -p * rho2 * rho2]
        if elliptical:
            out += [-p * (uu ** 2 - vv ** 2) / r_corner ** 2, -p * 2.0 * uu * vv / r_corner ** 2]
        return out

    u2, v2 = u ** 2, v ** 2  # squared before the gather: the same numbers as u[x] ** 2

    def at(idx):
        y, x, neg_p = _pixels_at(res, idx)
        rho2 = (u2[x] + v2[y]) / r_corner ** 2
        first = neg_p * rho2  # -p * rho2 (and -p * rho2 * rho2 = first * rho2): as terms() evaluates them
        if quartic:
            return np.stack([first * rho2])
        out = [first, first * rho2]
        if elliptical:
            uu, vv = u[x], v[y]
            out += [neg_p * (u2[x] - v2[y]) / r_corner ** 2, neg_p * 2.0 * uu * vv / r_corner ** 2]
        return np.stack(out)

    def maps():
        return [t.astype(np.float32) for t in terms(u[None, :], v[:, None], photo.astype(np.float64))]

    def to_params(c):
        a2, a4 = (0.0, float(c[0])) if quartic else (float(x) for x in c[:2])
        quad = float(np.hypot(c[2], c[3])) if elliptical else 0.0  # the rho^2 rate's azimuthal amplitude
        ok = (abs(a2) + quad <= VIGNETTING_COEF_MAX and abs(a4) <= VIGNETTING_COEF_MAX and a2 + quad + a4 < 1)
        # an elliptical fall-off (a cat's eye, a tilt) loses light in every direction: its rho^2 rate along the
        # least-losing axis, a2 - quad, is not negative (a saddle gains light along one axis, which the rings of
        # observed_rise, averaging over azimuth, do not see)
        ok = ok and a2 - quad >= 0.0
        # on the bound a2 = 0 the loss is the rho^4 term's: a4 <= 0 would brighten the field everywhere
        ok = ok and (a4 > 0.0 if quartic else True)
        p = {"a2": round(a2, 6), "a4": round(a4, 6)}
        if elliptical:
            p.update(a2_cos2=round(float(c[2]), 6), a2_sin2=round(float(c[3]), 6))
        if cx_mm or cy_mm:
            p.update(centre_x_mm=round(cx_mm, 3), centre_y_mm=round(cy_mm, 3))
        if radius_mm:
            p["radius_mm"] = round(float(radius_mm), 4)
        return p if ok else None

    return Variant(maps, to_params, f"{cx_mm}|{cy_mm}|{radius_mm or 0.0}" + ("|elliptical" if elliptical else "")
                   + ("|quartic" if quartic else ""), at=at)


def _window_geometry_mm(res) -> tuple[float, float, float]:
    """(centre x, centre y, half-diagonal) of the read-out window [mm from the sensor centre]."""
    s = res.sensor
    pitch_mm = s.pixel_pitch_um * 1e-3
    w, h = s.roi_shape
    cx = (s.roi_x0 + w / 2.0 - s.sensor_width_px / 2.0) * pitch_mm
    cy = (s.roi_y0 + h / 2.0 - s.sensor_height_px / 2.0) * pitch_mm
    return cx, cy, 0.5 * pitch_mm * float(np.hypot(w, h))


def _half_diagonal_mm(res) -> float:
    s = res.sensor
    return 0.5 * s.pixel_pitch_um * 1e-3 * float(np.hypot(s.sensor_width_px, s.sensor_height_px))


def _vignetting_variants(res):
    if not np.any(res.photo_adu > 0):
        return
    rc = _half_diagonal_mm(res)
    for fx in _CENTRE_GRID:
        for fy in _CENTRE_GRID:
            for quartic in (False, True):
                yield _vignetting_variant(res, fx * rc, fy * rc, quartic=quartic)
    # a window much smaller than the sensor: a fall-off on the window's own scale (a shadow of the tube or
    # a baffle, a filter's edge, vignetting about a centre far off the optical axis), about centres around it
    wx, wy, rw = _window_geometry_mm(res)
    if rw < 0.5 * rc:
        for fx in (-1.0, -0.5, 0.0, 0.5, 1.0):
            for fy in (-1.0, -0.5, 0.0, 0.5, 1.0):
                for quartic in (False, True):
                    yield _vignetting_variant(res, wx + fx * rw, wy + fy * rw, 2 * rw, quartic=quartic)


#: farthest centre offset the refinement may reach [fraction of the half-diagonal]: the grid's edge, plus a step
_CENTRE_MAX = 0.25
#: the centre refinement stops at this step [fraction of the half-diagonal] (0.02 mm on the ML11002)
_CENTRE_TOL = 0.001


def _vignetting_refine(best, res):
    """The circular fall-off's centre, then an elliptical one's (with the azimuthal terms of its rho^2 rate, no
    direction gaining light), each refined from the grid's best by a pattern search (compass search: the 8 neighbours at
    the step, moved to the best, the step halved when none is better; Kolda, Lewis & Torczon 2003, SIAM
    Rev. 45, 385) on the search sample, down to :data:`_CENTRE_TOL`; a centre off by a grid step leaves a
    gradient a bias or glow candidate would take next."""
    cx, cy, radius = (float(x) for x in best.label.split("|")[:3])
    radius = radius or None
    quartic = best.label.endswith("|quartic")
    rc = _half_diagonal_mm(res)
    ctx, shape = search_sample(res), res.data_adu.shape
    if radius is None:
        ox, oy, reach = 0.0, 0.0, _CENTRE_MAX * rc
    else:  # the window's own scale: centres within a window half-diagonal of its edge
        ox, oy, rw = _window_geometry_mm(res)
        reach = 1.5 * rw

    def score(x, y, elliptical):
        if max(abs(x - ox), abs(y - oy)) > reach:  # a centre far off the field makes a plane, not vignetting
            return np.inf
        v = _vignetting_variant(res, x, y, radius, elliptical, quartic=quartic and not elliptical)
        c, d = fit_linear(res, lambda i: v.values(i, shape), ctx["idx"], ctx["r"], ctx["w"])
        return d if v.to_params(c) is not None else np.inf

    def search(cx, cy, elliptical):
        here, step = score(cx, cy, elliptical), 0.05 * rc
        for _ in range(60):
            if step < _CENTRE_TOL * rc:
                break
            trials = [(score(cx + dx, cy + dy, elliptical), cx + dx, cy + dy) for dx in (-step, 0.0, step)
                      for dy in (-step, 0.0, step) if dx or dy]
            d, x, y = min(trials)
            if d < here:
                here, cx, cy = d, x, y
            else:
                step /= 2
        return cx, cy

    cx, cy = search(cx, cy, False)
    yield _vignetting_variant(res, cx, cy, radius, quartic=quartic)
    # ... and an elliptical fall-off (two more coefficients, which the BIC weighs), its centre searched from the
    # circular one's or the field's (the grid's middle), whichever fits better: an elliptical fall-off puts the
    # best circular centre off its own, on the far side of a ridge of the elliptical fit's chi2
    start = min([(cx, cy), (ox, oy)], key=lambda c: score(*c, True))
    yield _vignetting_variant(res, *search(*start, True), radius, elliptical=True)


def _rho2_max(res, p: dict) -> float:
    """The largest rho^2 of the radial model over the read-out window: its farthest pixel from the fitted
    centre, in units of the model's radius (the sensor's half-diagonal, or ``radius_mm``)."""
    s = res.sensor
    pitch_mm = s.pixel_pitch_um * 1e-3
    u, v = _offsets_mm(res, p.get("centre_x_mm", 0.0), p.get("centre_y_mm", 0.0))
    r_corner = p.get("radius_mm") or 0.5 * pitch_mm * float(np.hypot(s.sensor_width_px, s.sensor_height_px))
    return float((np.max(u * u) + np.max(v * v)) / r_corner ** 2)


def _loss_at_edge(p: dict, res) -> float:
    """The fitted loss at the sensor's corner (rho = 1), or for a window-scale fit at the window's farthest pixel
    (the polynomial beyond the window is not measured)."""
    x = min(_rho2_max(res, p), 1.0) if "radius_mm" in p else 1.0
    return _a2_major(p) * x + p["a4"] * x * x


def _a2_major(p: dict) -> float:
    """The rho^2 rate along the axis that loses the most light: ``a2`` plus the azimuthal terms' amplitude
    ``hypot(a2_cos2, a2_sin2)`` (:func:`radial_vignetting`; ``a2`` for a circular fall-off)."""
    return p["a2"] + float(np.hypot(p.get("a2_cos2", 0.0), p.get("a2_sin2", 0.0)))


#: rings of equal pixel count about the fitted centre in which the observed light is measured [rings]
VIGNETTING_RINGS = 16
#: the chi2 by which the observed ring profile must depart from a non-increasing light before a vignetting is
#: refused: the statistic of an isotonic fit (a chi-bar-squared, Robertson, Wright & Dykstra 1988, Order
#: Restricted Statistical Inference, ch. 2), at the detection bar of a chi2: DETECTION_SIGMA^2 = 25 (the
#: chi-bar-squared's tail beyond it is below 1e-5 for 16 rings, about 4.5 sigma)
VIGNETTING_RISE_CHI2 = DETECTION_SIGMA ** 2
#: the size of that rise, as a share of the ring profile's own span (brightest to faintest ring), below which a
#: significant rise is the fitted form's shortfall, not light added away from the centre: a fall-off about a
#: centre found within the refinement's tolerance, elliptical to the draws' axis ratio 0.6, flattens its central
#: rings by a few per cent of its depth (1.3 % on a 23 % deep Gaussian of axis ratio 0.71, where the test's chi2
#: was 112 against the profile's 2.0e6), while a light that rises away from the centre rises by a large part of
#: it; on a strong fall-off the chi2 alone grows with the signal and refuses every mismatch of form
VIGNETTING_RISE_SHARE = 0.1


def _ring_profile(u: np.ndarray, v: np.ndarray, cols: np.ndarray, rows: np.ndarray, q: np.ndarray,
                  wq: np.ndarray) -> tuple[float, float]:
    """(chi2 from a non-increasing profile, the rise's share of the span) of the relative residuals ``q``
    (inverse variances ``wq``) in rings of equal pixel count of the squared distance from the centre at which
    ``u``, ``v`` [mm] are measured (the pixels at ``cols``, ``rows``)."""
    from scipy.optimize import isotonic_regression

    t = u[cols] ** 2 + v[rows] ** 2
    edges = np.quantile(t, np.linspace(0, 1, VIGNETTING_RINGS + 1))
    ring = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, VIGNETTING_RINGS - 1)
    wk = np.bincount(ring, wq, VIGNETTING_RINGS)
    keep = wk > 0
    mk = np.bincount(ring, wq * q, VIGNETTING_RINGS)[keep] / wk[keep]
    iso = isotonic_regression(mk, weights=wk[keep], increasing=False).x
    span = float(mk.max() - mk.min())
    gain = float(np.max(mk - np.minimum.accumulate(mk)))  # the largest rise over a ring nearer the centre
    return float(np.sum(wk[keep] * (mk - iso) ** 2)), (gain / span if span > 0 else 0.0)


def _rises(rise: tuple[float, float]) -> bool:
    """A ring profile that rises away from its centre: beyond VIGNETTING_RISE_CHI2 and by more than
    VIGNETTING_RISE_SHARE of its span."""
    return rise[0] > VIGNETTING_RISE_CHI2 and rise[1] > VIGNETTING_RISE_SHARE


def observed_rise(p: dict, res) -> tuple[float, float]:
    """How much the observed light, in rings of rho^2 about a centre, departs from a light that never
    rises away from that centre: (the chi2 between the rings' level-profiled relative residuals and their
    non-increasing isotonic fit (``scipy.optimize.isotonic_regression``, weights the rings' inverse
    variances), the rise's size as a share of the rings' span: the largest gain of a ring over a ring nearer
    the centre, over the brightest minus the faintest ring). Measured on the data, not on the fitted
    polynomial: a polynomial fitted to a monotone fall-off that saturates (a cos^4, a Lorentzian, a
    Gaussian) turns over by up to 40 % of its depth.

    The centre is the fitted one, or, when the light rises away from it, the centre about which it rises
    least, searched over the centres the fit itself may take (:func:`_vignetting_variants`' grid, then a
    compass search as :func:`_vignetting_refine` within its reach): the question is whether the light falls
    away from some centre, not from the polynomial's. A fall-off the circular polynomial cannot follow (an
    elliptical one, a cos^4 about a centre off the window) puts its best polynomial centre where the light
    still rises, while the rings about the fall-off's own centre fall (every ray from it falls, so does every
    ring's mean); a light with a minimum inside the field, or steps, rises away from every centre."""
    idx, r, w = res.flat_profiled()
    shape = res.data_adu.shape
    photo = np.broadcast_to(res.photo_adu, shape).ravel()[idx].astype(np.float64)
    ok = (photo > 0) & (w > 0)
    if ok.sum() < 10 * VIGNETTING_RINGS:
        return 0.0, 0.0
    cols, rows = idx[ok] % shape[1], idx[ok] // shape[1]
    q = r[ok] / photo[ok]  # relative residual: the light's change [1]
    wq = w[ok] * photo[ok] ** 2  # its inverse variance

    def on_all(cx, cy):
        return _ring_profile(*_offsets_mm(res, cx, cy), cols, rows, q, wq)

    cx, cy = p.get("centre_x_mm", 0.0), p.get("centre_y_mm", 0.0)
    best = on_all(cx, cy)
    if not _rises(best):
        return best
    # the search runs on a regular subsample of at most LINEAR_SEARCH_PIXELS pixels (the chi2 scaled to all of
    # them, as a linear signature's search); the centre it settles on is measured on every pixel
    step_px = max(1, int(np.ceil(q.size / LINEAR_SEARCH_PIXELS)))
    sub = slice(0, None, step_px)

    def at(cx, cy):
        chi2, share = _ring_profile(*_offsets_mm(res, cx, cy), cols[sub], rows[sub], q[sub], wq[sub])
        return chi2 * step_px, share

    def result(cx, cy):
        return on_all(cx, cy) if step_px > 1 else at(cx, cy)

    rc = _half_diagonal_mm(res)
    if "radius_mm" in p:  # the window's own scale: centres about the window, as the fit's grid and refinement
        ox, oy, rw = _window_geometry_mm(res)
        grid = [(ox + fx * rw, oy + fy * rw) for fx in (-1.0, -0.5, 0.0, 0.5, 1.0) for fy in (-1.0, -0.5, 0.0, 0.5, 1.0)]
        reach, step = 1.5 * rw, 0.25 * rw
    else:
        ox, oy = 0.0, 0.0
        grid = [(fx * rc, fy * rc) for fx in _CENTRE_GRID for fy in _CENTRE_GRID]
        reach, step = _CENTRE_MAX * rc, 0.05 * rc
    first = best
    best = at(cx, cy)
    for gx, gy in grid:
        trial = at(gx, gy)
        if not _rises(trial):
            return result(gx, gy)
        if trial[0] < best[0]:
            best, cx, cy = trial, gx, gy
    for _ in range(60):  # compass search (Kolda, Lewis & Torczon 2003) on the rise's chi2
        if step < _CENTRE_TOL * rc:
            break
        trials = [(at(cx + dx, cy + dy), cx + dx, cy + dy) for dx in (-step, 0.0, step) for dy in (-step, 0.0, step)
                  if (dx or dy) and max(abs(cx + dx - ox), abs(cy + dy - oy)) <= reach]
        for trial, x, y in trials:
            if not _rises(trial):
                return result(x, y)
        if trials and min(t[0][0] for t in trials) < best[0]:
            best, cx, cy = min(trials, key=lambda t: t[0][0])
        else:
            step /= 2
    out = result(cx, cy)
    return out if out[0] < first[0] else first


def _vignetting_check(fit, res) -> str:
    """Vignetting takes light away towards the edge of the field: the fitted relative illumination
    ``1 - a2 rho^2 - a4 rho^4`` must lose light somewhere away from its centre (along the axis that loses the
    most: an elliptical fall-off's rate ``a2 + hypot(a2_cos2, a2_sin2)``), and the
    observed light must not rise away from every centre the fit may take (:func:`observed_rise` beyond
    VIGNETTING_RISE_CHI2 and by more than VIGNETTING_RISE_SHARE of the profile's span). A pattern that brightens away from its centre where it is observed is an added
    light or a flat-field error."""
    p = fit.params
    a2, a4 = _a2_major(p), p["a4"]  # along the axis that loses the most (an elliptical fall-off's major one)
    if a2 <= 0 and a4 <= 0:
        return (f"the fitted form gains light away from its centre everywhere (a2 = {a2:+.3g}, a4 = {a4:+.3g}): "
                "vignetting only takes light away (an added light or a flat-field error)")
    # a fitted polynomial that turns over within or beyond the window is the form's shortfall on a fall-off that
    # saturates (a cos^4, a Gaussian about a centre off the window's: the loss at the sensor's corner came out
    # negative for a 20 % deep cos^4): the data's own ring profile decides
    rise, share = observed_rise(p, res)
    if _rises((rise, share)):
        return (f"the observed light rises away from every centre the fit may take (rings of rho^2 about the least "
                f"rising: chi2 {rise:.3g} from a never-rising profile, more than {VIGNETTING_RISE_CHI2:g}, by "
                f"{100 * share:.3g} % of the rings' "
                f"span, more than {100 * VIGNETTING_RISE_SHARE:g} %): vignetting only takes light away (an "
                "added light or a flat-field error)")
    # a response of this shape against an added light of the same shape: the sources tell
    return light_law_check(fit, res, multiplicative=True)


_VIGNETTING_SIGNATURE = LinearSignature(
    _vignetting_variants,
    lambda p, res: (f"light falling off towards the corners, {100 * _loss_at_edge(p, res):.3g} % at "
                    + ("the window's farthest pixel from its centre, " if "radius_mm" in p else "the corner, ")
                    + "proportional to the signal"
                    + (f", centred at ({p['centre_x_mm']:+.3g}, {p['centre_y_mm']:+.3g}) mm off the axis"
                       if "centre_x_mm" in p else "") + ": vignetting"),
    pattern="multiplicative radial fall-off of the light", extra_k=3, refine=_vignetting_refine, of_light=True,
    check=_vignetting_check)
#: a response to the light and added light or dark charge of the same shape are one image where the light is one
#: level (and an offset of the read-out, where the response's shot noise does not tell it either)
_VIGNETTING_SIGNATURE.untold = light_law_untold(("straylight", "sky_gradient", "dark_gradient", "amp_glow"),
                                                multiplicative=True, offsets=("bias_gradient",))
#: the variant of a label ("cx|cy|radius"), on any frame: a series refines the centre on one frame and fits
#: that one form on every frame (scenes.app.compare.series)
_VIGNETTING_SIGNATURE.rebuild = lambda label, res: _vignetting_variant(
    res, *(float(x) for x in label.split("|")[:2]), float(label.split("|")[2]) or None,
    elliptical=label.endswith("|elliptical"), quartic=label.endswith("|quartic"))


def relative_illumination(params: VignettingParams, sensor):
    """The vignetting's relative illumination as a function ``ri(ys, xs)`` [1] of full-sensor pixel centres
    (rows, columns; 2-D out): the FITS map of ``params.map_file`` (bilinear, :func:`map_interpolator`) or
    the radial polynomial (:func:`radial_vignetting`). The data a consumer of the focal plane's light
    (the scene's straylight, which is already focal-plane irradiance) needs, without the effect."""
    interp = None
    if params.map_file:
        path = Path(params.map_file)
        if not path.is_file():
            raise DetectorError("vignetting map not found", key="effects.vignetting.map_file",
                                expected="an existing FITS map", file=str(path))
        interp = map_interpolator(*read_vignetting_map(path))
    pitch_mm = sensor.pixel_pitch_um * 1e-3
    r_corner = params.radius_mm or 0.5 * pitch_mm * float(np.hypot(sensor.sensor_width_px, sensor.sensor_height_px))

    def ri(ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
        u = (xs - (sensor.sensor_width_px - 1) / 2.0) * pitch_mm
        v = (ys - (sensor.sensor_height_px - 1) / 2.0) * pitch_mm
        if interp is not None:
            return interp(v, u)
        return radial_vignetting(u[None, :], v[:, None], r_corner, params.a2, params.a4,
                                 (params.centre_x_mm, params.centre_y_mm), params.a2_cos2, params.a2_sin2)

    return ri


class VignettingParams(EffectParams):
    map_file: str | None = Field(None, description="FITS map from 'newtsim optics vignetting --fits' (or, in a "
                                 "scene, 'optics': ray-trace the scene's telescope design)")
    a2: float = Field(0.0, ge=-VIGNETTING_COEF_MAX, le=VIGNETTING_COEF_MAX,
                      description="radial model: loss at the corner from the rho^2 term", json_schema_extra={"unit": "1"})
    a4: float = Field(0.0, ge=-VIGNETTING_COEF_MAX, le=VIGNETTING_COEF_MAX, description="radial model: rho^4 term",
                      json_schema_extra={"unit": "1"})
    a2_cos2: float = Field(0.0, ge=-VIGNETTING_COEF_MAX, le=VIGNETTING_COEF_MAX,
                           description="radial model: the rho^2 loss's change with azimuth, cos(2 phi) part (an "
                           "elliptical fall-off, axes along the columns and rows)", json_schema_extra={"unit": "1"})
    a2_sin2: float = Field(0.0, ge=-VIGNETTING_COEF_MAX, le=VIGNETTING_COEF_MAX,
                           description="radial model: the rho^2 loss's change with azimuth, sin(2 phi) part (an "
                           "elliptical fall-off, axes at 45 degrees)", json_schema_extra={"unit": "1"})
    centre_x_mm: float = Field(0.0, ge=-100, le=100, description="radial model: centre offset along columns",
                               json_schema_extra={"unit": "mm"})
    centre_y_mm: float = Field(0.0, ge=-100, le=100, description="radial model: centre offset along rows",
                               json_schema_extra={"unit": "mm"})
    radius_mm: float | None = Field(None, gt=0, le=500, description="radial model: the radius where rho = 1 "
                                    "(default: the sensor's half-diagonal)", json_schema_extra={"unit": "mm"})

    @model_validator(mode="after")
    def _one_form(self):
        if self.map_file and (self.a2 or self.a4 or self.a2_cos2 or self.a2_sin2):
            raise ValueError("give either map_file or the radial coefficients a2/a4, not both")
        return self


@register_effect
class Vignetting(Effect):
    """Relative illumination of the focal plane: a ray-traced map or a radial polynomial (multiplies light)."""

    name = "vignetting"
    field_kind = "multiplicative"
    scaling = "signal"
    identity = {"a2": 0.0, "a4": 0.0}
    stages = (Stage.RESPONSE,)
    Params = VignettingParams
    signature = _VIGNETTING_SIGNATURE

    def setup(self) -> None:
        self._ri = relative_illumination(self.params, self.sensor)

    def ri(self, ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
        """Relative illumination at full-sensor pixel centres (rows ``ys``, columns ``xs``) [1]."""
        return self._ri(ys, xs)

    def apply(self, stage: Stage, tile: Tile, data: np.ndarray) -> None:
        ys, xs = tile.pixel_centres()
        data *= self.ri(ys, xs).astype(np.float32)
