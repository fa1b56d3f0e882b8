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
from ..signatures import LinearSignature, Variant, fit_linear, light_law_check, light_law_untold, search_sample
from .base import Effect, EffectParams, Stage, Tile, register_effect


def elliptical_rho2(du_mm, dv_mm, r_corner_mm: float, axis_ratio: float = 1.0, angle_deg: float = 0.0):
    """rho^2 of the radial model about its centre (offsets ``du``, ``dv`` [mm]): ``(a^2 + (b / q)^2) / r_c^2``
    with ``a``, ``b`` the offsets along the major axis (at ``angle_deg`` from the columns) and across it, ``q``
    the axis ratio (1: circles). Elliptical contours are what a tilted sensor or an obstruction off the axis
    makes of a pupil's vignetting (the "cat's eye" of an off-axis pupil)."""
    if axis_ratio == 1.0:
        return (du_mm ** 2 + dv_mm ** 2) / r_corner_mm ** 2
    t = np.deg2rad(angle_deg)
    a = du_mm * np.cos(t) + dv_mm * np.sin(t)
    b = -du_mm * np.sin(t) + dv_mm * np.cos(t)
    return (a ** 2 + (b / axis_ratio) ** 2) / r_corner_mm ** 2


def radial_vignetting(u_mm: np.ndarray, v_mm: np.ndarray, r_corner_mm: float, a2: float, a4: float,
                      centre_mm: tuple[float, float] = (0.0, 0.0), profile_rho: list[float] | None = None,
                      profile_loss: list[float] | None = None, axis_ratio: float = 1.0,
                      angle_deg: float = 0.0) -> np.ndarray:
    """RI = 1 - a2 rho^2 - a4 rho^4, rho = |(u, v) - centre| / r_corner, clipped to [0, 1] [1]; or, with a
    tabulated profile, RI = 1 - L(rho), L piecewise linear through (0, 0) and (``profile_rho``,
    ``profile_loss``), constant beyond its last knot. ``axis_ratio`` < 1: elliptical contours
    (:func:`elliptical_rho2`)."""
    rho2 = elliptical_rho2(u_mm - centre_mm[0], v_mm - centre_mm[1], r_corner_mm, axis_ratio, angle_deg)
    if profile_rho:
        loss = np.interp(np.sqrt(rho2), [0.0, *profile_rho], [0.0, *profile_loss])
        return np.clip(1.0 - loss, 0.0, 1.0)
    return np.clip(1.0 - a2 * rho2 - a4 * rho2 * rho2, 0.0, 1.0)


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


#: knots of the free radial profile of the diagnosis (``form = "profile"``): equally spaced in rho up to the
#: window's farthest pixel from the centre; the loss is 0 at the centre and piecewise linear between them. A law
#: that saturates within the window (a Gaussian or cos^4 fall-off about a centre in it) is no polynomial of
#: rho^2; this form follows any radial law (five numbers, priced by the BIC), and the ring test of the data
#: (:func:`observed_rise`) still asks that the light never rise away from the centre
PROFILE_KNOTS = 5


def _hats(rho: np.ndarray, knots: np.ndarray) -> np.ndarray:
    """(knots, pixels) the piecewise-linear basis through (0, 0): hat k is 1 at knot k, 0 at its neighbours
    (the last one 1 beyond the last knot)."""
    grid = np.concatenate([[0.0], knots])
    out = np.empty((len(knots), rho.size))
    for k in range(1, len(grid)):
        left = np.clip((rho - grid[k - 1]) / (grid[k] - grid[k - 1]), 0.0, 1.0)
        right = np.clip((grid[k + 1] - rho) / (grid[k + 1] - grid[k]), 0.0, 1.0) if k + 1 < len(grid) else 1.0
        out[k - 1] = np.minimum(left, right)
    return out


def _vignetting_variant(res, cx_mm: float, cy_mm: float, radius_mm: float | None = None, form: str = "poly",
                        axis_ratio: float = 1.0, angle_deg: float = 0.0):
    s = res.sensor
    pitch_mm = s.pixel_pitch_um * 1e-3
    u, v = _offsets_mm(res, cx_mm, cy_mm)
    r_corner = radius_mm or 0.5 * pitch_mm * float(np.hypot(s.sensor_width_px, s.sensor_height_px))
    photo = res.photo_adu
    w = photo.shape[1]
    label = f"{cx_mm}|{cy_mm}|{radius_mm or 0.0}|{form}|{axis_ratio}|{angle_deg}"
    q, ang = axis_ratio, angle_deg
    shape_p = {} if q == 1.0 else {"axis_ratio": round(float(q), 4), "angle_deg": round(float(ang) % 180.0, 2)}
    extra = 0 if q == 1.0 else 2  # an ellipse chooses two numbers more than a circle (counted in the BIC)
    if form == "profile":
        rho_max = float(np.sqrt(max(elliptical_rho2(a, b, r_corner, q, ang) for a in (u[0], u[-1])
                                    for b in (v[0], v[-1]))))
        knots = rho_max * np.arange(1, PROFILE_KNOTS + 1) / PROFILE_KNOTS

        def at_p(idx):
            y, x = np.divmod(idx, w)
            rho = np.sqrt(elliptical_rho2(u[x], v[y], r_corner, q, ang))
            return -photo.ravel()[idx].astype(np.float64) * _hats(rho, knots)

        def maps_p():
            rho = np.sqrt(elliptical_rho2(u[None, :], v[:, None], r_corner, q, ang))
            h = _hats(rho.ravel(), knots).reshape(len(knots), *rho.shape)
            return [(-photo * hk).astype(np.float32) for hk in h]

        def to_params_p(c):
            loss = [float(x) for x in c]
            if max(abs(x) for x in loss) > 1.0:
                return None
            p = {"profile_rho": [round(float(k), 5) for k in knots], "profile_loss": [round(x, 6) for x in loss]}
            if cx_mm or cy_mm:
                p.update(centre_x_mm=round(cx_mm, 3), centre_y_mm=round(cy_mm, 3))
            if radius_mm:
                p["radius_mm"] = round(float(radius_mm), 4)
            return p | shape_p

        return Variant(maps_p, to_params_p, label, at=at_p, extra_k=extra)

    def at(idx):
        y, x = np.divmod(idx, w)
        rho2 = elliptical_rho2(u[x], v[y], r_corner, q, ang)
        p = photo.ravel()[idx].astype(np.float64)
        return np.stack([-p * rho2, -p * rho2 * rho2])

    def maps():
        rho2 = elliptical_rho2(u[None, :], v[:, None], r_corner, q, ang).astype(np.float32)
        ph = photo.astype(np.float32)
        return [-ph * rho2, -ph * rho2 * rho2]

    def to_params(c):
        a2, a4 = (float(x) for x in c)
        ok = abs(a2) <= VIGNETTING_COEF_MAX and abs(a4) <= VIGNETTING_COEF_MAX and a2 + a4 < 1
        p = {"a2": round(a2, 6), "a4": round(a4, 6)}
        if cx_mm or cy_mm:
            p.update(centre_x_mm=round(cx_mm, 3), centre_y_mm=round(cy_mm, 3))
        if radius_mm:
            p["radius_mm"] = round(float(radius_mm), 4)
        return p | shape_p if ok else None

    return Variant(maps, to_params, label, at=at, extra_k=extra)


def _label(label: str) -> tuple[float, float, float | None, str, float, float]:
    """(cx, cy, radius or None, form, axis ratio, angle) of a variant's label ("cx|cy|radius[|form|q|angle]")."""
    x = label.split("|")
    return (float(x[0]), float(x[1]), float(x[2]) or None, (x[3] if len(x) > 3 else "poly"),
            float(x[4]) if len(x) > 4 else 1.0, float(x[5]) if len(x) > 5 else 0.0)


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
            yield _vignetting_variant(res, fx * rc, fy * rc)
            yield _vignetting_variant(res, fx * rc, fy * rc, form="profile")
    # a window much smaller than the sensor: a fall-off on the window's own scale (a shadow of the tube or
    # a baffle, a filter's edge, vignetting about a centre far off the optical axis), about centres around it
    wx, wy, rw = _window_geometry_mm(res)
    if rw < 0.5 * rc:
        for fx in (-1.0, -0.5, 0.0, 0.5, 1.0):
            for fy in (-1.0, -0.5, 0.0, 0.5, 1.0):
                yield _vignetting_variant(res, wx + fx * rw, wy + fy * rw, 2 * rw)
                yield _vignetting_variant(res, wx + fx * rw, wy + fy * rw, 2 * rw, form="profile")


#: farthest centre offset the refinement may reach [fraction of the half-diagonal]: the grid's edge, plus a step
_CENTRE_MAX = 0.25
#: the centre refinement stops at this step [fraction of the half-diagonal] (0.02 mm on the ML11002)
_CENTRE_TOL = 0.001


def _vignetting_refine(best, res):
    """The centre refined from the grid's best by a pattern search (compass search: the 8 neighbours at
    the step, moved to the best, the step halved when none is better; Kolda, Lewis & Torczon 2003, SIAM
    Rev. 45, 385) on the search sample, down to :data:`_CENTRE_TOL`; a centre off by a grid step leaves a
    gradient a bias or glow candidate would take next."""
    cx, cy, radius, form, _, _ = _label(best.label)
    rc = _half_diagonal_mm(res)
    ctx, shape = search_sample(res), res.data_adu.shape
    if radius is None:
        ox, oy, reach = 0.0, 0.0, _CENTRE_MAX * rc
    else:  # the window's own scale: centres within a window half-diagonal of its edge
        ox, oy, rw = _window_geometry_mm(res)
        reach = 1.5 * rw

    def score(x, y):
        if max(abs(x - ox), abs(y - oy)) > reach:  # a centre far off the field makes a plane, not vignetting
            return np.inf
        v = _vignetting_variant(res, x, y, radius, form)
        c, d = fit_linear(res, lambda i: v.values(i, shape), ctx["idx"], ctx["r"], ctx["w"])
        return d if v.to_params(c) is not None else np.inf

    here, step = score(cx, cy), 0.05 * rc
    for _ in range(60):
        if step < _CENTRE_TOL * rc:
            break
        trials = [(score(cx + dx, cy + dy), cx + dx, cy + dy) for dx in (-step, 0.0, step)
                  for dy in (-step, 0.0, step) if dx or dy]
        d, x, y = min(trials)
        if d < here:
            here, cx, cy = d, x, y
        else:
            step /= 2
    yield _vignetting_variant(res, cx, cy, radius, form)

    # the elliptical form about that centre: a grid of axis ratios and angles, then the same compass search
    # over (centre, axis ratio, angle)
    def score_e(x, y, q, a):
        if max(abs(x - ox), abs(y - oy)) > reach or not _AXIS_RATIO_MIN <= q < 1.0:
            return np.inf
        v = _vignetting_variant(res, x, y, radius, form, q, a)
        c, d = fit_linear(res, lambda i: v.values(i, shape), ctx["idx"], ctx["r"], ctx["w"])
        return d if v.to_params(c) is not None else np.inf

    # from the refined centre and from a 3 x 3 grid over the region the centre may reach (a fall-off of
    # elliptical contours draws a circle's centre away from its own)
    starts = [(cx, cy)] + [(ox + fx * reach, oy + fy * reach) for fx in (-0.5, 0.0, 0.5) for fy in (-0.5, 0.0, 0.5)]
    here, cx, cy, q, a = min((score_e(x0, y0, q_, a_), x0, y0, q_, a_) for x0, y0 in starts
                             for q_ in _AXIS_RATIOS for a_ in _ANGLES_DEG)
    if not np.isfinite(here):
        return
    step = 1.0  # in units of (0.05 half-diagonals of the reach, 0.1 in the axis ratio, 15 deg)
    unit = 0.05 * reach / _CENTRE_MAX if radius is None else 0.05 * reach
    for _ in range(80):
        if step < 0.02:
            break
        trials = []
        for dx, dy, dq, da in ((1, 0, 0, 0), (-1, 0, 0, 0), (0, 1, 0, 0), (0, -1, 0, 0), (0, 0, 1, 0),
                               (0, 0, -1, 0), (0, 0, 0, 1), (0, 0, 0, -1)):
            x, y, q_, a_ = cx + dx * step * unit, cy + dy * step * unit, q + dq * step * 0.1, a + da * step * 15.0
            trials.append((score_e(x, y, q_, a_), x, y, q_, a_))
        d, x, y, q_, a_ = min(trials)
        if d < here:
            here, cx, cy, q, a = d, x, y, q_, a_
        else:
            step /= 2
    yield _vignetting_variant(res, cx, cy, radius, form, q, a % 180.0)


#: axis ratios and major-axis angles [deg] of the elliptical forms tried about the refined centre, and the
#: smallest axis ratio the refinement may reach [1]
_AXIS_RATIOS = (0.8, 0.6, 0.4)
_ANGLES_DEG = (0.0, 45.0, 90.0, 135.0)
_AXIS_RATIO_MIN = 0.25


def _rho2_max(res, p: dict) -> float:
    """The largest rho^2 of the radial model over the read-out window: its farthest pixel from the fitted
    centre, in units of the model's radius (the sensor's half-diagonal, or ``radius_mm``)."""
    s = res.sensor
    pitch_mm = s.pixel_pitch_um * 1e-3
    u, v = _offsets_mm(res, p.get("centre_x_mm", 0.0), p.get("centre_y_mm", 0.0))
    r_corner = p.get("radius_mm") or 0.5 * pitch_mm * float(np.hypot(s.sensor_width_px, s.sensor_height_px))
    # a convex form's largest value over the window is at one of its corners
    return float(max(elliptical_rho2(x, y, r_corner, p.get("axis_ratio", 1.0), p.get("angle_deg", 0.0))
                     for x in (u[0], u[-1]) for y in (v[0], v[-1])))


def _loss_at_edge(p: dict, res) -> float:
    """The fitted loss at the sensor's corner (rho = 1), or for a window-scale fit at the window's farthest pixel
    (the polynomial beyond the window is not measured)."""
    if "profile_loss" in p:  # its last knot is the window's farthest pixel
        return float(p["profile_loss"][-1])
    x = min(_rho2_max(res, p), 1.0) if "radius_mm" in p else 1.0
    return p["a2"] * x + p["a4"] * x * x


#: rings of equal pixel count about the fitted centre in which the observed light is measured [rings]
VIGNETTING_RINGS = 16
#: the chi2 by which the observed ring profile must depart from a non-increasing light before a vignetting is
#: refused: the statistic of an isotonic fit (a chi-bar-squared, Robertson, Wright & Dykstra 1988, Order
#: Restricted Statistical Inference, ch. 2), whose tail beyond 25 is below 1e-5 for 16 rings (about 4.5 sigma)
VIGNETTING_RISE_CHI2 = 25.0
#: the size of that rise, as a share of the ring profile's own span (brightest to faintest ring), below which a
#: significant rise is the fitted form's shortfall, not light added away from the centre: a fall-off about a
#: centre found within the refinement's tolerance, elliptical to the draws' axis ratio 0.6, flattens its central
#: rings by a few per cent of its depth (1.3 % on a 23 % deep Gaussian of axis ratio 0.71, where the test's chi2
#: was 112 against the profile's 2.0e6), while a light that rises away from the centre rises by a large part of
#: it; on a strong fall-off the chi2 alone grows with the signal and refuses every mismatch of form
VIGNETTING_RISE_SHARE = 0.1


def observed_rise(p: dict, res) -> tuple[float, float]:
    """How much the observed light, in rings of rho^2 about the fitted centre, departs from a light that never
    rises away from the centre: (the chi2 between the rings' level-profiled relative residuals and their
    non-increasing isotonic fit (``scipy.optimize.isotonic_regression``, weights the rings' inverse
    variances), the rise's size as a share of the rings' span: the largest gain of a ring over a ring nearer
    the centre, over the brightest minus the faintest ring). Measured on the data, not on the fitted
    polynomial: a polynomial fitted to a monotone fall-off that saturates (a cos^4, a Lorentzian, a
    Gaussian) turns over by up to 40 % of its depth."""
    from scipy.optimize import isotonic_regression

    idx, r, w = res.flat_profiled()
    shape = res.data_adu.shape
    photo = np.broadcast_to(res.photo_adu, shape).ravel()[idx].astype(np.float64)
    ok = (photo > 0) & (w > 0)
    if ok.sum() < 10 * VIGNETTING_RINGS:
        return 0.0, 0.0
    u, v = _offsets_mm(res, p.get("centre_x_mm", 0.0), p.get("centre_y_mm", 0.0))
    t = elliptical_rho2(u[idx[ok] % shape[1]], v[idx[ok] // shape[1]], 1.0, p.get("axis_ratio", 1.0),
                        p.get("angle_deg", 0.0))
    q = r[ok] / photo[ok]  # relative residual: the light's change [1]
    wq = w[ok] * photo[ok] ** 2  # its inverse variance
    edges = np.quantile(t, np.linspace(0, 1, VIGNETTING_RINGS + 1))
    ring = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, VIGNETTING_RINGS - 1)
    wk = np.bincount(ring, wq, VIGNETTING_RINGS)
    keep = wk > 0
    mk = np.bincount(ring, wq * q, VIGNETTING_RINGS)[keep] / wk[keep]
    iso = isotonic_regression(mk, weights=wk[keep], increasing=False).x
    span = float(mk.max() - mk.min())
    gain = float(np.max(mk - np.minimum.accumulate(mk)))  # the largest rise over a ring nearer the centre
    return float(np.sum(wk[keep] * (mk - iso) ** 2)), (gain / span if span > 0 else 0.0)


def _vignetting_check(fit, res) -> str:
    """Vignetting takes light away towards the edge of the field: the fitted relative illumination
    ``1 - a2 rho^2 - a4 rho^4`` must lose light somewhere away from its centre, and the
    observed light must not rise away from the fitted centre (:func:`observed_rise` beyond
    VIGNETTING_RISE_CHI2 and by more than VIGNETTING_RISE_SHARE of the profile's span). A pattern that brightens away from its centre where it is observed is an added
    light or a flat-field error."""
    p = fit.params
    if "profile_loss" in p and max(p["profile_loss"]) <= 0:
        return ("the fitted profile gains light away from its centre everywhere: vignetting only takes light away "
                "(an added light or a flat-field error)")
    a2, a4 = p.get("a2", 0.0), p.get("a4", 0.0)
    if "profile_loss" not in p and a2 <= 0 and a4 <= 0:
        return (f"the fitted form gains light away from its centre everywhere (a2 = {a2:+.3g}, a4 = {a4:+.3g}): "
                "vignetting only takes light away (an added light or a flat-field error)")
    # a fitted polynomial that turns over within or beyond the window is the form's shortfall on a fall-off that
    # saturates (a cos^4, a Gaussian about a centre off the window's: the loss at the sensor's corner came out
    # negative for a 20 % deep cos^4): the data's own ring profile decides
    rise, share = observed_rise(p, res)
    if rise > VIGNETTING_RISE_CHI2 and share > VIGNETTING_RISE_SHARE:
        return (f"the observed light rises away from the fitted centre (rings of rho^2: chi2 {rise:.3g} from a "
                f"never-rising profile, more than {VIGNETTING_RISE_CHI2:g}, by {100 * share:.3g} % of the rings' "
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
                       if "centre_x_mm" in p else "")
                    + (f", elliptical (axis ratio {p['axis_ratio']:.2f}, major axis at {p['angle_deg']:.0f} deg)"
                       if "axis_ratio" in p else "") + ": vignetting"),
    pattern="multiplicative radial fall-off of the light", extra_k=3, refine=_vignetting_refine, of_light=True,
    check=_vignetting_check)
#: a response to the light and an added light of the same shape are one image where the light is one level
_VIGNETTING_SIGNATURE.untold = light_law_untold(("straylight", "sky_gradient"), multiplicative=True)
#: the variant of a label ("cx|cy|radius"), on any frame: a series refines the centre on one frame and fits
#: that one form on every frame (scenes.app.compare.series)
_VIGNETTING_SIGNATURE.rebuild = lambda label, res: _vignetting_variant(res, *_label(label))


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
                                 (params.centre_x_mm, params.centre_y_mm), params.profile_rho, params.profile_loss,
                                 params.axis_ratio, params.angle_deg)

    return ri


class VignettingParams(EffectParams):
    map_file: str | None = Field(None, description="FITS map from 'newtsim optics vignetting --fits' (or, in a "
                                 "scene, 'optics': ray-trace the scene's telescope design)")
    a2: float = Field(0.0, ge=-VIGNETTING_COEF_MAX, le=VIGNETTING_COEF_MAX,
                      description="radial model: loss at the corner from the rho^2 term", json_schema_extra={"unit": "1"})
    a4: float = Field(0.0, ge=-VIGNETTING_COEF_MAX, le=VIGNETTING_COEF_MAX, description="radial model: rho^4 term",
                      json_schema_extra={"unit": "1"})
    centre_x_mm: float = Field(0.0, ge=-100, le=100, description="radial model: centre offset along columns",
                               json_schema_extra={"unit": "mm"})
    centre_y_mm: float = Field(0.0, ge=-100, le=100, description="radial model: centre offset along rows",
                               json_schema_extra={"unit": "mm"})
    radius_mm: float | None = Field(None, gt=0, le=500, description="radial model: the radius where rho = 1 "
                                    "(default: the sensor's half-diagonal)", json_schema_extra={"unit": "mm"})
    axis_ratio: float = Field(1.0, gt=0, le=1, description="radial model: minor over major axis of its elliptical "
                              "contours (1: circles)", json_schema_extra={"unit": "1"})
    angle_deg: float = Field(0.0, ge=-360, le=360, description="radial model: the major axis's angle from the "
                             "columns", json_schema_extra={"unit": "deg"})
    profile_rho: list[float] | None = Field(None, description="tabulated radial model: knots of rho (increasing, "
                                            "> 0), in units of the model's radius", json_schema_extra={"unit": "1"})
    profile_loss: list[float] | None = Field(None, description="tabulated radial model: the light lost at each "
                                             "knot (0 at the centre, piecewise linear between, constant beyond the "
                                             "last)", json_schema_extra={"unit": "1"})

    @model_validator(mode="after")
    def _one_form(self):
        if self.map_file and (self.a2 or self.a4 or self.profile_rho):
            raise ValueError("give either map_file or the radial model (a2/a4 or a profile), not both")
        if (self.profile_rho is None) != (self.profile_loss is None) or (
                self.profile_rho is not None and (len(self.profile_rho) != len(self.profile_loss)
                                                  or not self.profile_rho
                                                  or np.any(np.diff([0.0, *self.profile_rho]) <= 0))):
            raise ValueError("profile_rho and profile_loss: two lists of the same length, profile_rho increasing "
                             "from above 0")
        if self.profile_rho and (self.a2 or self.a4):
            raise ValueError("give either the polynomial a2/a4 or the tabulated profile, not both")
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
