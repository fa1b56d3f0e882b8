"""Field distortion of the telescope as a SIP polynomial (for astropy WCS ``RA---TAN-SIP``).

Physics
    A perfect camera maps a star at field angles (theta_x, theta_y) to the gnomonic (TAN) position

        (u, v)_ideal = -f (tan theta_x, tan theta_y)                       [mm, detector frame]

    (the image is inverted: (u, v) = (0, 0) is the optical axis, see :mod:`optics.layout`). A bare
    paraboloid with the stop at the mirror has none: the chief ray meets the vertex and leaves at the
    field angle. A field corrector adds radial distortion (odd powers of the field, third and fifth
    order) and changes the effective focal length. The traced image position of a star is
    the centroid of its ray bundle through the real (obstructed) pupil, which is what a centroiding
    astrometric pipeline measures; but vignetting at the edge of the field moves it by pixels in ways no
    low-order polynomial follows, so the default is the chief ray through the vertex of the primary (the
    aperture stop), traced without obstructions since the diagonal hides it.

SIP convention (Shupe et al. 2005, ADASS XIV, ASP Conf. Ser. 347, 491)
    With pixel offsets (x, y) = pixel - CRPIX from the optical axis, the forward polynomials give the
    "focal-plane" (ideal, undistorted) pixel offsets

        x_ideal = x + sum_{p,q} A_p_q x^p y^q,     y_ideal = y + sum_{p,q} B_p_q x^p y^q,

    and CD maps (x_ideal, y_ideal) to intermediate world coordinates. Here CD is the ideal gnomonic
    camera of focal length f and pixel pitch: CD = -(pitch / f) (180/pi) I [deg/pixel] (the minus sign is
    the image inversion), so ``x_ideal = -f tan(theta_x) / pitch`` by construction. The reverse
    polynomials AP_p_q, BP_p_q map ideal offsets back to pixel offsets (x = x_ideal + AP(x_ideal,
    y_ideal)). Both are fitted by linear least squares over a grid of traced field points, with all terms
    1 <= p + q <= order: the linear terms absorb the difference between the effective focal length and f.
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from .design import Design
from .sequential import SequentialTracer, pupil_grid


def _terms(order: int):
    return [(p, q) for p in range(order + 1) for q in range(order + 1 - p) if p + q >= 1]


def _fit_poly(x, y, target, order: int, scale: float):
    """Least-squares coefficients {(p, q): c} of sum c x^p y^q ~ target (columns scaled by ``scale``)."""
    terms = _terms(order)
    A = np.stack([(x / scale) ** p * (y / scale) ** q for p, q in terms], axis=-1)
    c, *_ = np.linalg.lstsq(A, target, rcond=None)
    return {t: float(ci / scale ** (t[0] + t[1])) for t, ci in zip(terms, c, strict=True)}


def _fit_shift(x, y, xi, yi, order: int, scale: float) -> tuple[float, float]:
    """The constant (c_x, c_y) [px] of a fit ``(x, y) - (xi, yi) ~ c + poly(xi, yi)`` (no constant in poly): the
    image's shift on the axis, zero for a centred design."""
    terms = _terms(order)
    M = np.stack([np.ones_like(xi)] + [(xi / scale) ** p * (yi / scale) ** q for p, q in terms], axis=-1)
    cx, *_ = np.linalg.lstsq(M, x - xi, rcond=None)
    cy, *_ = np.linalg.lstsq(M, y - yi, rcond=None)
    return float(cx[0]), float(cy[0])


def _eval_poly(coef: dict, x, y):
    return sum(c * x ** p * y ** q for (p, q), c in coef.items())


def _wide_detector_tracer(tracer: SequentialTracer, obstruct: str) -> SequentialTracer:
    """The same telescope with a large detector, so field points at the sensor's edge are not cut."""
    data = tracer.design.model_dump()
    fp = data["focal_plane"]
    fp["width_mm"], fp["height_mm"] = 1.5 * fp["width_mm"], 1.5 * fp["height_mm"]
    return SequentialTracer(Design.model_validate(data), tracer.mi, obstruct=obstruct)


def image_positions(tracer: SequentialTracer, fields_deg, wavelength_nm: float = 550.0, n_rays: int = 20000,
                    method: str = "chief") -> np.ndarray:
    """Traced image position (u, v) [mm] of stars at ``fields_deg`` (an (n, 2) array of field angles
    [deg]): the chief ray (``method="chief"``: through the primary's vertex, the aperture stop, traced
    without obstructions), or (``method="centroid"``) the transmission-weighted centroid of a bundle of
    about ``n_rays`` rays on a square pupil grid through the tracer's (obstructed) pupil."""
    if method not in ("centroid", "chief"):
        raise ValueError(f"method must be 'centroid' or 'chief', not {method!r}")
    obstruct = "none" if method == "chief" else ("analytic" if tracer.obstruct == "mesh" else tracer.obstruct)
    wide = _wide_detector_tracer(tracer, obstruct)
    z_rim = float(wide.layout.primary_sag(wide.layout.r_primary))
    if method == "centroid":
        # a square grid (not random points): the centroid then varies smoothly with the field
        R = wide.layout.r_primary
        px, py = pupil_grid(max(8, int(math.sqrt(4 * n_rays / math.pi))), R)
        inside = np.hypot(px, py) <= R
        px, py = px[inside], py[inside]
    out = np.full((len(fields_deg), 2), np.nan)
    for i, f in enumerate(np.asarray(fields_deg, dtype=float)):
        if method == "chief":
            # pupil coordinates live in the rim plane: the ray through the vertex crosses it at z_rim tan(theta)
            px = np.array([z_rim * math.tan(math.radians(f[0]))])
            py = np.array([z_rim * math.tan(math.radians(f[1]))])
        r = wide.trace((float(f[0]), float(f[1])), px, py, wavelength_nm=wavelength_nm)
        ok = r.ok
        if ok.any():
            t = r.transmission[ok]
            out[i] = (np.sum(t * r.u[ok]) / t.sum(), np.sum(t * r.v[ok]) / t.sum())
    return out


def fit_sip(tracer: SequentialTracer, pitch_um: float, order: int = 3, grid: int = 9, *,
            wavelength_nm: float = 550.0, shape: tuple | None = None, n_rays: int = 20000,
            method: str = "chief", reverse_order: int | None = None) -> dict:
    """Fit SIP distortion polynomials to traced image positions over the detector.

    Parameters
    ----------
    tracer : SequentialTracer
    pitch_um : float
        Pixel pitch [um]; the polynomials are in pixel units.
    order : int
        SIP order of the forward polynomials A, B (default 3: the cubic radial distortion). The ``art``
        corrector's distortion is small (0.075 % at 2 deg) but not purely cubic: on the IMX411 (3.76 um)
        order 3 leaves 0.033 px rms, order 5 0.028 px and order 7 0.003 px (even orders add nothing: the
        distortion is radial, odd in the field). A warning is issued when the forward residual exceeds
        0.05 px.
    grid : int
        grid x grid field points whose ideal images span the detector (1 % beyond its edges).
    wavelength_nm : float
        Wavelength of the traced bundles [nm].
    shape : (ny, nx), optional
        Sensor size in pixels (sets CRPIX); default width_mm / pitch and height_mm / pitch rounded.
    n_rays : int
        Rays per field point for the centroid.
    method : {"chief", "centroid"}
        Image position = the chief ray (through the vertex of the primary, the aperture stop; traced
        without obstructions: the diagonal hides it), a smooth function of the field; or the centroid
        of the obstructed bundle, which vignetting at the field's edge bends by a few pixels in ways a
        polynomial does not follow (for ``art``: up to 4 px in the corners).
    reverse_order : int, optional
        Order of AP, BP (default ``order + 2``: the inverse of a distortion with strong fifth-order
        terms needs higher powers).

    Returns
    -------
    dict
        FITS-ready cards ``A_ORDER``, ``A_p_q``, ``B_ORDER``, ``B_p_q``, ``AP_ORDER``, ``AP_p_q``,
        ``BP_ORDER``, ``BP_p_q``, ``CRPIX1``, ``CRPIX2``, ``CD1_1``, ``CD1_2``, ``CD2_1``, ``CD2_2``
        (upper case), and the fit quality in lower case: ``rms_px`` and ``max_px`` (forward residuals),
        ``reverse_rms_px``, ``reverse_max_px``, ``max_distortion_px`` (largest traced - ideal offset),
        ``effective_focal_length_mm`` (from the linear terms), ``focal_length_mm``, ``pitch_um``,
        ``order``, ``field_x_deg``, ``field_y_deg``. :func:`sip_cards` keeps the cards only.
    """
    if order < 1 or grid < 3:
        raise ValueError("order must be >= 1 and grid >= 3")
    design = tracer.design
    f = design.primary.focal_length_mm
    hu, hv = design.focal_plane.width_mm / 2, design.focal_plane.height_mm / 2
    pitch_mm = pitch_um * 1e-3
    if shape is None:
        shape = (round(2 * hv / pitch_mm), round(2 * hu / pitch_mm))
    crpix = ((shape[1] + 1) / 2.0, (shape[0] + 1) / 2.0)
    # field points whose ideal images span the detector (and 1 % beyond)
    gu = np.linspace(-1.01 * hu, 1.01 * hu, grid)
    gv = np.linspace(-1.01 * hv, 1.01 * hv, grid)
    U, V = np.meshgrid(gu, gv, indexing="xy")
    fields = np.stack([np.degrees(np.arctan(-U.ravel() / f)), np.degrees(np.arctan(-V.ravel() / f))], -1)
    pos = image_positions(tracer, fields, wavelength_nm, n_rays, method)
    ok = np.all(np.isfinite(pos), axis=1)
    if ok.sum() < len(_terms(order + 1)) + 2:
        raise ValueError(f"only {ok.sum()} of {len(pos)} field points reach the detector: cannot fit SIP")
    x, y = pos[ok, 0] / pitch_mm, pos[ok, 1] / pitch_mm                  # traced pixel offsets
    xi = -f * np.tan(np.radians(fields[ok, 0])) / pitch_mm                # ideal pixel offsets
    yi = -f * np.tan(np.radians(fields[ok, 1])) / pitch_mm
    scale = max(np.abs(x).max(), np.abs(y).max())
    # a perturbed design moves its whole image (a decentred primary, a tilted diagonal: the pointing changes);
    # SIP has no constant term, so the shift is fitted, reported (``shift_px``, traced - ideal on the axis) and
    # removed: what the polynomials keep is the distortion about the moved axis, the shift itself is pointing,
    # which a plate solution absorbs (CRVAL). For the nominal design it is zero (the unfolded system is
    # rotationally symmetric, the mapping odd in the field) and nothing changes.
    shift = _fit_shift(x, y, xi, yi, order, scale)
    x, y = x - shift[0], y - shift[1]
    A = _fit_poly(x, y, xi - x, order, scale)
    B = _fit_poly(x, y, yi - y, order, scale)
    ro = reverse_order or order + 2
    AP = _fit_poly(xi, yi, x - xi, ro, scale)
    BP = _fit_poly(xi, yi, y - yi, ro, scale)
    fwd = np.hypot(x + _eval_poly(A, x, y) - xi, y + _eval_poly(B, x, y) - yi)
    rev = np.hypot(xi + _eval_poly(AP, xi, yi) - x, yi + _eval_poly(BP, xi, yi) - y)
    if np.sqrt(np.mean(fwd ** 2)) > 0.05:
        warnings.warn(f"SIP order {order}: forward residual {np.sqrt(np.mean(fwd ** 2)):.3f} px rms over the "
                      f"detector; raise the order", RuntimeWarning, stacklevel=2)
    cd = -(pitch_mm / f) * 180.0 / math.pi
    out = {"CRPIX1": crpix[0], "CRPIX2": crpix[1], "CD1_1": cd, "CD1_2": 0.0, "CD2_1": 0.0, "CD2_2": cd,
           "A_ORDER": order, "B_ORDER": order, "AP_ORDER": ro, "BP_ORDER": ro}
    for name, coef in (("A", A), ("B", B), ("AP", AP), ("BP", BP)):
        for (p, q), c in coef.items():
            out[f"{name}_{p}_{q}"] = c
    # linear terms: x_ideal ~ (1 + A_1_0) x  ->  f_eff = f / (1 + A_1_0)
    out.update({
        "rms_px": float(np.sqrt(np.mean(fwd ** 2))), "max_px": float(fwd.max()),
        "reverse_rms_px": float(np.sqrt(np.mean(rev ** 2))), "reverse_max_px": float(rev.max()),
        "max_distortion_px": float(np.max(np.hypot(x - xi, y - yi))),
        "effective_focal_length_mm": float(f / (1.0 + 0.5 * (A.get((1, 0), 0.0) + B.get((0, 1), 0.0)))),
        "focal_length_mm": float(f), "pitch_um": float(pitch_um), "order": int(order),
        "n_points": int(ok.sum()), "wavelength_nm": float(wavelength_nm), "method": method,
        "shift_px": [float(shift[0]), float(shift[1])],
        "field_x_deg": fields[:, 0].reshape(grid, grid).tolist(),
        "field_y_deg": fields[:, 1].reshape(grid, grid).tolist(),
    })
    return out


def sip_cards(sip: dict) -> dict:
    """The FITS cards of a :func:`fit_sip` result (upper-case keys) without the fit statistics."""
    return {k: v for k, v in sip.items() if k.isupper()}


def sip_wcs(sip: dict, crval_deg=(0.0, 0.0), roll_deg: float = 0.0):
    """An astropy WCS (``RA---TAN-SIP`` / ``DEC--TAN-SIP``) from :func:`fit_sip` cards, pointing the
    optical axis at ``crval_deg`` = (RA, Dec) [deg], the CD matrix rotated by ``roll_deg``."""
    from astropy.io import fits
    from astropy.wcs import WCS

    h = fits.Header()
    h["NAXIS"] = 2
    h["CTYPE1"], h["CTYPE2"] = "RA---TAN-SIP", "DEC--TAN-SIP"
    h["CUNIT1"], h["CUNIT2"] = "deg", "deg"
    h["CRVAL1"], h["CRVAL2"] = float(crval_deg[0]), float(crval_deg[1])
    cards = sip_cards(sip)
    c, s = math.cos(math.radians(roll_deg)), math.sin(math.radians(roll_deg))
    cd = np.array([[cards["CD1_1"], cards["CD1_2"]], [cards["CD2_1"], cards["CD2_2"]]])
    cd = np.array([[c, -s], [s, c]]) @ cd
    cards["CD1_1"], cards["CD1_2"], cards["CD2_1"], cards["CD2_2"] = cd.ravel().tolist()
    for k, v in cards.items():
        h[k] = v
    return WCS(h)


def cached_sip(design, pitch_um: float, shape: tuple[int, int], order: int = 5) -> dict:
    """SIP distortion of ``design`` for a sensor of ``shape`` = (ny, nx) pixels of ``pitch_um`` [um]:
    :func:`fit_sip` (chief rays, 550 nm, a 9 x 9 field grid, reverse order ``order + 2``), cached.

    The entry point for the scenes package: it starts Mitsuba itself (``optics.llvm.init_mitsuba``) when
    the cache misses; the result is stored as JSON in :func:`optics.cache.cache_dir` under a key that
    hashes the design's content, ``pitch_um``, ``shape`` and ``order``.

    Parameters
    ----------
    design : Design or str
        The telescope (or a built-in design name / design TOML path).
    pitch_um : float
        Pixel pitch [um].
    shape : (int, int)
        Sensor size (ny, nx) in pixels: CRPIX = ((nx + 1) / 2, (ny + 1) / 2), the optical axis on the
        sensor's centre.
    order : int
        Order of the forward polynomials A, B (5 for ``art``: its corrector's distortion has a strong
        fifth-order part; see :func:`fit_sip`).

    Returns
    -------
    dict
        What :func:`fit_sip` returns: FITS cards ``A_p_q``, ``B_p_q``, ``AP_p_q``, ``BP_p_q``, the
        ``*_ORDER`` cards, ``CRPIX1/2``, ``CD1_1`` ... (upper case; :func:`sip_cards` keeps only these,
        :func:`sip_wcs` builds the astropy WCS) and the fit statistics (lower case, e.g. ``rms_px``).
    """
    from . import cache
    from .design import as_design

    d = as_design(design)
    shape = (int(shape[0]), int(shape[1]))
    settings = {"pitch_um": float(pitch_um), "shape": list(shape), "order": int(order), "grid": 9,
                "wavelength_nm": 550.0, "method": "chief"}
    if any(d.perturbation.model_dump().values()):
        settings["shift"] = "removed"   # fits before the image's shift was removed are not reused

    def compute():
        from .llvm import init_mitsuba

        return fit_sip(SequentialTracer(d, init_mitsuba()), pitch_um, order=order, grid=9, shape=shape)

    out, _ = cache.cached_json("sip", d, settings, compute)
    return out
