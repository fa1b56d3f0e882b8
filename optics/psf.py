"""Point-spread functions of the telescope: geometric spots and diffraction PSFs from the traced pupil.

Geometric spot
    Rays through a stratified sample of the entrance pupil (the primary's rim plane) are traced to the
    detector; the spot's centroid, RMS radius, full extents along and across the field direction, the
    encircled-energy curve and an effective FWHM follow from the ray hits, each ray weighted by its
    Fresnel transmittance.

Diffraction PSF (scalar Debye integral over the traced exit pupil)
    Near the image point P the field is a superposition of plane waves, one per ray, each with the
    ray's direction cosines k = (k_u, k_v) at the detector and the optical path it has accumulated
    (Born & Wolf, Principles of Optics, 8.8; Richards & Wolf 1959, doi:10.1098/rspa.1959.0200):

        U(P + x) = sum_k A(k) exp[i 2 pi / lambda (W(k) + k . x)] dk_u dk_v ,

    where the wavefront error of the ray that meets the detector plane at Q with optical path OPL(Q) is
    its phase carried back to P:

        W(k) = OPL(Q) - k . (Q - P)        (k: unit direction; Q - P lies in the detector plane).

    This is the reference-sphere OPD in the limit of a reference sphere of large radius centred on P:
    the exact sphere intersection adds (|Q - P|^2 - (k . (Q - P))^2) / 2R, a few nm for R ~ 300 mm and
    |Q - P| < 50 um, i.e. far below lambda/100. A ray stopped anywhere (secondary and its holder, spider,
    baffles, focuser, lens rims) has A = 0, so the obscuration, the spider and any vignetting come from
    the traced geometry. The amplitude conserves the energy of each ray tube:

        |A|^2 = T |d^2 p / d^2 k| / k_w,

    with T the corrector's Fresnel transmittance, p the pupil point and k_w the axial direction cosine
    (Debye obliquity; k_w > 0.979 at f/2.4).

    The sum is evaluated on a uniform grid of k, so that the Fourier sum separates into two matrix
    products (the matrix Fourier transform, Soummer et al. 2007, doi:10.1364/OE.15.015935): any output
    sampling, no zero padding and no wrap-around inside the stamp. The pupil points that exit along the
    grid directions are found by *ray aiming*: a coarse trace fits the smooth map p -> k with a
    2-D polynomial, Newton's method inverts it on the grid, and the traced directions of the aimed rays
    confirm it (``diagnostics["k_grid_error"]``, in units of the grid step). The intensity is computed
    at a Nyquist-sampled internal grid (spacing <= lambda / (4 NA)) and integrated over the output
    pixels of ``sampling_um``, so ``image`` holds the fraction of the energy falling in each output pixel.

Seeing and jitter
    Atmospheric seeing (Gaussian, or Moffat, I ~ (1 + r^2/alpha^2)^-beta with FWHM = 2 alpha
    sqrt(2^(1/beta) - 1), Moffat 1969; beta = 4.765 for Kolmogorov turbulence, Trujillo et al. 2001,
    doi:10.1046/j.1365-8711.2001.04937.x) and Gaussian pointing jitter (rms per axis) are convolved
    in angle, converted with the plate scale 206265 / f [arcsec/mm] of the design's focal length.

Metrics
    Centroid (first moments), encircled energy about the centroid (EE(r), EE50, EE80), an effective
    FWHM = 2 sqrt(A_half / pi) from the area A_half where the PSF exceeds half its peak (exact for a
    circular Gaussian; for the Airy core it is within 1 % of the profile FWHM), and the ellipticity
    1 - b/a from the second moments inside twice the EE80 radius.

Everything runs through :class:`optics.sequential.SequentialTracer`; this module never sets a Mitsuba
variant. Weights (e.g. a detector QE times a source spectrum) are the caller's: optics imports neither
``detector`` nor ``scenes``.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .sequential import (
    DETECTOR_MISS,
    DIAGONAL_MISS,
    OK,
    SequentialTracer,
    pupil_uniform,
)

MOFFAT_BETA_KOLMOGOROV = 4.765
_GAUSS_FWHM = 2.0 * math.sqrt(2.0 * math.log(2.0))     # FWHM / sigma of a Gaussian


# ---- small helpers -------------------------------------------------------------------------------------
def _as_wavelengths(wavelengths_nm, weights):
    """Wavelengths [nm] and weights normalised to sum 1 (equal weights when ``weights`` is None)."""
    lam = np.atleast_1d(np.asarray(wavelengths_nm, dtype=float))
    if lam.size == 0 or np.any(lam <= 0):
        raise ValueError("wavelengths_nm must hold positive wavelengths [nm]")
    w = np.ones_like(lam) if weights is None else np.atleast_1d(np.asarray(weights, dtype=float))
    if w.shape != lam.shape:
        raise ValueError(f"weights has {w.size} entries for {lam.size} wavelengths")
    if np.any(w < 0) or w.sum() <= 0:
        raise ValueError("weights must be >= 0 with a positive sum")
    return lam, w / w.sum()


def _tangential_axis(field_deg) -> np.ndarray:
    """Unit vector (u, v) along the field direction on the detector (the tangential direction); on axis,
    +v. The image of field (theta_x, theta_y) lies at -f (tan theta_x, tan theta_y)."""
    t = np.array([math.tan(math.radians(field_deg[0])), math.tan(math.radians(field_deg[1]))])
    n = np.hypot(*t)
    return np.array([0.0, 1.0]) if n < 1e-12 else t / n


def plate_scale_arcsec_per_um(tracer: SequentialTracer) -> float:
    """Plate scale 206265 / f of the design's focal length [arcsec/um]."""
    return tracer.design.plate_scale_arcsec_per_mm * 1e-3


def _quantile_radius(r, cdf, level):
    """Smallest radius where the (non-decreasing) curve ``cdf`` reaches ``level`` (linear interpolation)."""
    i = int(np.searchsorted(cdf, level))
    if i == 0:
        return float(r[0])
    if i >= len(r):
        return float("nan")
    c0, c1 = cdf[i - 1], cdf[i]
    return float(r[i - 1] + (r[i] - r[i - 1]) * (level - c0) / max(c1 - c0, 1e-300))


def encircled_energy_points(x, y, w, r):
    """EE(r): the weight of the points (x, y) within radius r of the origin over the total weight."""
    d = np.hypot(x, y)
    order = np.argsort(d)
    cum = np.concatenate([[0.0], np.cumsum(w[order])])
    return cum[np.searchsorted(d[order], r, side="right")] / cum[-1]


def encircled_energy_image(img, dx, cx, cy, r, total=1.0):
    """EE(r) of a pixel image about (cx, cy) (offsets from the image centre, same unit as ``dx``).

    Each pixel's energy counts with the fraction of it inside the circle, approximated by the linear ramp
    clip((r - d + dx/2) / dx, 0, 1) of the distance d of its centre (second-order accurate for a smooth
    image). Divided by ``total`` (the energy of the whole PSF, which may exceed the stamp's)."""
    ny, nx = img.shape
    xs = (np.arange(nx) - (nx - 1) / 2) * dx - cx
    ys = (np.arange(ny) - (ny - 1) / 2) * dx - cy
    d = np.hypot(*np.meshgrid(xs, ys, indexing="xy")).ravel()
    e = img.ravel()
    order = np.argsort(d)
    d, e = d[order], e[order]
    s_e = np.concatenate([[0.0], np.cumsum(e)])
    s_ed = np.concatenate([[0.0], np.cumsum(e * d)])
    h = dx / 2
    lo = np.searchsorted(d, r - h, side="left")
    hi = np.searchsorted(d, r + h, side="left")
    partial = ((r + h) * (s_e[hi] - s_e[lo]) - (s_ed[hi] - s_ed[lo])) / (2 * h)
    return (s_e[lo] + partial) / total


def effective_fwhm(img, dx, upsample: int = 4) -> float:
    """FWHM = 2 sqrt(A / pi) of the area A where the image exceeds half its maximum [unit of ``dx``].

    The region above a quarter of the peak is resampled ``upsample`` times finer with cubic splines
    (scipy.ndimage.zoom), so the area is not quantised to whole pixels."""
    from scipy import ndimage

    peak = img.max()
    if peak <= 0:
        return float("nan")
    ys, xs = np.nonzero(img > 0.25 * peak)
    y0, y1 = max(ys.min() - 2, 0), min(ys.max() + 3, img.shape[0])
    x0, x1 = max(xs.min() - 2, 0), min(xs.max() + 3, img.shape[1])
    cut = img[y0:y1, x0:x1]
    fine = ndimage.zoom(cut, upsample, order=3, grid_mode=True, mode="nearest") if upsample > 1 else cut
    area = np.count_nonzero(fine >= 0.5 * fine.max()) * (dx / upsample) ** 2
    return 2.0 * math.sqrt(area / math.pi)


def second_moment_shape(img, dx, cx, cy, radius):
    """Ellipticity 1 - b/a and position angle [deg from +u toward +v] from the intensity-weighted second
    moments inside ``radius`` about (cx, cy) (an unweighted aperture: Airy wings make untruncated second
    moments diverge logarithmically)."""
    ny, nx = img.shape
    xs = (np.arange(nx) - (nx - 1) / 2) * dx - cx
    ys = (np.arange(ny) - (ny - 1) / 2) * dx - cy
    X, Y = np.meshgrid(xs, ys, indexing="xy")
    m = (X * X + Y * Y <= radius * radius) & (img > 0)
    w = img[m]
    if w.sum() <= 0:
        return float("nan"), float("nan")
    qxx = np.sum(w * X[m] ** 2) / w.sum()
    qyy = np.sum(w * Y[m] ** 2) / w.sum()
    qxy = np.sum(w * X[m] * Y[m]) / w.sum()
    ev = np.linalg.eigvalsh(np.array([[qxx, qxy], [qxy, qyy]]))
    e = 1.0 - math.sqrt(max(ev[0], 0.0) / ev[1]) if ev[1] > 0 else float("nan")
    return float(e), float(math.degrees(0.5 * math.atan2(2 * qxy, qxx - qyy)))


def _bin(img, m):
    """Sum m x m blocks (integrate internal samples over output pixels)."""
    if m == 1:
        return img
    ny, nx = img.shape
    return img.reshape(ny // m, m, nx // m, m).sum(axis=(1, 3))


# ---- geometric spot ------------------------------------------------------------------------------------
def _trace_spot(tracer, field_deg, n_rays, lam, w, seed):
    """Ray hits (u, v) [mm] and weights of a (poly)chromatic spot: each wavelength carries its weight
    spread over its rays, times each ray's Fresnel transmittance."""
    R = tracer.layout.r_primary
    px, py = pupil_uniform(int(n_rays), R, seed=seed)
    us, vs, ws = [], [], []
    throughput = 0.0
    for lam_i, w_i in zip(lam, w, strict=True):
        r = tracer.trace(field_deg, px, py, wavelength_nm=float(lam_i))
        ok = r.ok
        t = r.transmission[ok]
        us.append(r.u[ok])
        vs.append(r.v[ok])
        ws.append(w_i * t / len(px))
        throughput += w_i * t.sum() / len(px)
    return np.concatenate(us), np.concatenate(vs), np.concatenate(ws), throughput


def spot_metrics(u_mm, v_mm, weight, field_deg, n_radii: int = 200) -> dict:
    """Metrics of a geometric spot from ray hits ``u_mm``, ``v_mm`` [mm] with ``weight``.

    Returns (lengths in um): ``centroid_um`` [u, v]; ``rms_spot_um`` = sqrt(<|r - c|^2>), the RMS
    *radius* about the centroid (``rms_spot_diameter_um`` is twice it); ``extent_tangential_um`` and
    ``extent_sagittal_um``, the full extents (max - min) of the hits projected on the field direction
    t = (tan theta_x, tan theta_y)/|.| (on axis: +v) and on the perpendicular; ``ee_radius_um`` /
    ``ee`` (encircled energy about the centroid), ``ee50_um``, ``ee80_um``; ``fwhm_um``, the effective
    FWHM of the hit density (histogram smoothed by a Gaussian of one bin, bin = RMS radius / 8).
    """
    if len(u_mm) == 0 or weight.sum() <= 0:
        raise ValueError(f"no ray reached the detector at field {tuple(field_deg)} deg")
    w = weight / weight.sum()
    u = np.asarray(u_mm) * 1e3
    v = np.asarray(v_mm) * 1e3
    cu, cv = float(np.sum(w * u)), float(np.sum(w * v))
    du, dv = u - cu, v - cv
    rms = math.sqrt(float(np.sum(w * (du * du + dv * dv))))
    t = _tangential_axis(field_deg)
    proj_t = u * t[0] + v * t[1]
    proj_s = -u * t[1] + v * t[0]
    r = np.hypot(du, dv)
    radii = np.linspace(0.0, float(r.max()) * 1.02 + 1e-9, n_radii)
    ee = encircled_energy_points(du, dv, w, radii)
    # effective FWHM of the hit density
    from scipy import ndimage

    b = max(rms / 8, 1e-4)
    half = float(r.max()) + 4 * b
    nb = int(min(2 * math.ceil(half / b) + 1, 1025))
    b = 2 * half / nb
    hist, _, _ = np.histogram2d(dv, du, bins=nb, range=[[-half, half], [-half, half]], weights=w)
    fwhm = effective_fwhm(ndimage.gaussian_filter(hist, 1.0), b)
    return {
        "centroid_um": [cu, cv],
        "rms_spot_um": rms,
        "rms_spot_diameter_um": 2 * rms,
        "extent_tangential_um": float(np.ptp(proj_t)),
        "extent_sagittal_um": float(np.ptp(proj_s)),
        "ee_radius_um": radii.tolist(),
        "ee": ee.tolist(),
        "ee50_um": _quantile_radius(radii, ee, 0.5),
        "ee80_um": _quantile_radius(radii, ee, 0.8),
        "fwhm_um": fwhm,
        "n_rays": len(u),
    }


def geometric_spot(tracer: SequentialTracer, field_deg=(0.0, 0.0), n_rays: int = 20000,
                   wavelength_nm=550.0, weights=None, seed: int = 0) -> dict:
    """Geometric spot of a star at ``field_deg`` = (theta_x, theta_y) [deg].

    Parameters
    ----------
    tracer : SequentialTracer
        Its obstruction mode decides which rays are stopped (``"none"``: the full pupil).
    field_deg : (float, float)
        Field angles [deg]; the ideal image lies at (u, v) = -f (tan theta_x, tan theta_y).
    n_rays : int
        Rays launched per wavelength, stratified over the primary (R2 sequence, seeded).
    wavelength_nm : float or sequence of float
        Wavelength(s) [nm]; several give a polychromatic spot.
    weights : sequence of float, optional
        Relative weight of each wavelength (e.g. QE x photon spectrum); equal when omitted.
    seed : int
        Shift of the stratified pupil sample (same seed, same spot).

    Returns
    -------
    dict
        :func:`spot_metrics` keys (``rms_spot_um``, ``extent_tangential_um``, ``extent_sagittal_um``,
        ``centroid_um``, ``ee_radius_um``, ``ee``, ``fwhm_um``, ...) plus ``throughput`` (weighted
        fraction of the launched rays that reach the detector, times T) and ``field_deg``.

    Notes
    -----
    Third-order coma of a paraboloid with the stop at the mirror (f/N, field angle theta [rad]): every
    pupil zone images as a circle; the marginal zone's circle has radius theta f / (16 N^2) and its
    centre lies 2 theta f / (16 N^2) from the chief ray, so the spot is 2 theta f / (16 N^2) wide
    (sagittal full extent) and 3 theta f / (16 N^2) long (tangential full extent). Schroeder,
    Astronomical Optics (2000), 6.2.
    """
    lam, w = _as_wavelengths(wavelength_nm, weights)
    u, v, ww, thr = _trace_spot(tracer, field_deg, n_rays, lam, w, seed)
    out = spot_metrics(u, v, ww, field_deg)
    out["throughput"] = float(thr)
    out["field_deg"] = [float(field_deg[0]), float(field_deg[1])]
    out["wavelengths_nm"] = lam.tolist()
    out["weights"] = w.tolist()
    return out


# ---- diffraction ----------------------------------------------------------------------------------------
def _poly_terms(deg):
    """Exponents (i, j) of the monomials x^i y^j of total degree <= deg."""
    return [(i, j) for i in range(deg + 1) for j in range(deg + 1 - i)]


def _powers(x, deg):
    p = [np.ones_like(x)]
    for _ in range(deg):
        p.append(p[-1] * x)
    return p


@dataclass
class _PupilMap:
    """Polynomial map from normalised pupil coordinates (px, py)/R to exit directions (k_u, k_v)."""

    R: float
    deg: int
    cu: np.ndarray
    cv: np.ndarray

    def design(self, x, y):
        px, py = _powers(x, self.deg), _powers(y, self.deg)
        return np.stack([px[i] * py[j] for i, j in _poly_terms(self.deg)], axis=-1)

    def k(self, x, y):
        px, py = _powers(x, self.deg), _powers(y, self.deg)
        ku, kv = np.zeros_like(x), np.zeros_like(x)
        for (i, j), a, b in zip(_poly_terms(self.deg), self.cu, self.cv, strict=True):
            m = px[i] * py[j]
            ku += a * m
            kv += b * m
        return ku, kv

    def jac(self, x, y):
        """d(k_u, k_v)/d(x, y) (normalised pupil coordinates)."""
        px, py = _powers(x, self.deg), _powers(y, self.deg)
        out = [np.zeros_like(x) for _ in range(4)]
        for (i, j), a, b in zip(_poly_terms(self.deg), self.cu, self.cv, strict=True):
            if i:
                m = i * px[i - 1] * py[j]
                out[0] += a * m
                out[2] += b * m
            if j:
                m = j * px[i] * py[j - 1]
                out[1] += a * m
                out[3] += b * m
        return tuple(out)

    def invert(self, ku, kv, iterations: int = 5):
        """Pupil points (normalised) that exit along (ku, kv): Newton's method from the linear map."""
        z = np.zeros(1)
        a, b, c, d = self.jac(z, z)
        k0u, k0v = self.k(z, z)
        det = a * d - b * c
        x = (d * (ku - k0u) - b * (kv - k0v)) / det
        y = (-c * (ku - k0u) + a * (kv - k0v)) / det
        for _ in range(iterations):
            fu, fv = self.k(x, y)
            a, b, c, d = self.jac(x, y)
            det = a * d - b * c
            ru, rv = fu - ku, fv - kv
            x = x - (d * ru - b * rv) / det
            y = y - (-c * ru + a * rv) / det
        return x, y


def _fit_pupil_map(tracer_free: SequentialTracer, field_deg, lam, n: int = 48, deg: int = 5) -> tuple:
    """Trace an n x n grid over the primary (no mechanical obstructions) and fit k(p); also return the
    geometric centroid [mm] of the rays that reach the detector plane."""
    from .sequential import pupil_grid

    R = tracer_free.layout.r_primary
    px, py = pupil_grid(n, R)
    inside = np.hypot(px, py) <= R
    px, py = px[inside], py[inside]
    r = tracer_free.trace(field_deg, px, py, wavelength_nm=float(lam))
    use = np.isin(r.lost, [OK, DETECTOR_MISS, DIAGONAL_MISS]) & np.isfinite(r.du) & np.isfinite(r.dv)
    if use.sum() < 50:
        raise ValueError(f"field {tuple(field_deg)} deg: too few rays reach the detector plane to map the pupil")
    x, y = px[use] / R, py[use] / R
    mp = _PupilMap(R, deg, np.zeros(0), np.zeros(0))
    A = mp.design(x, y)
    coef = np.linalg.lstsq(A, np.stack([r.du[use], r.dv[use]], axis=-1), rcond=None)[0]
    mp.cu, mp.cv = coef[:, 0], coef[:, 1]
    det = (r.lost == OK)
    centre = (float(np.mean(r.u[det])), float(np.mean(r.v[det]))) if det.any() else \
        (float(np.mean(r.u[use])), float(np.mean(r.v[use])))
    kspan = (float(np.ptp(r.du[use])), float(np.ptp(r.dv[use])),
             float(0.5 * (r.du[use].min() + r.du[use].max())), float(0.5 * (r.dv[use].min() + r.dv[use].max())))
    return mp, centre, kspan


def _free_tracer(tracer: SequentialTracer) -> SequentialTracer:
    if tracer.obstruct == "none":
        return tracer
    return SequentialTracer(tracer.design, tracer.mi, obstruct="none")


def _mft_intensity(amp, phase, ku, kv, lam_mm, xs_mm):
    """|sum_jk A exp(i phase + i 2 pi / lambda (ku_k x + kv_j y))|^2 on the grid xs x xs (rows: y = v),
    normalised so that the sum over the whole plane times the sample area is 1 (Parseval)."""
    field = amp * np.exp(1j * phase)
    Eu = np.exp(2j * np.pi / lam_mm * np.outer(xs_mm, ku))        # (n_out, n_k)
    Ev = np.exp(2j * np.pi / lam_mm * np.outer(xs_mm, kv))
    U = Ev @ field @ Eu.T
    dk = ku[1] - ku[0]
    dx = xs_mm[1] - xs_mm[0]
    norm = (dk / lam_mm) ** 2 * dx * dx / np.sum(amp * amp)
    return (U.real ** 2 + U.imag ** 2) * norm


def _mono_diffraction(tracer, field_deg, mapping, kspan, centre_mm, lam_nm, n_pupil, xs_mm):
    """Energy fraction per internal sample (grid ``xs_mm`` about ``centre_mm``, rows along v) at one
    wavelength, the transmitted pupil area [mm^2] and diagnostics."""
    lam_mm = lam_nm * 1e-6
    span = max(kspan[0], kspan[1])
    # the sum repeats every lambda / dk: keep that period longer than the computed window
    window_mm = (xs_mm[-1] - xs_mm[0]) * 1.05
    n_pupil = max(int(n_pupil), math.ceil(window_mm * span / lam_mm))
    dk = span / n_pupil
    ng = n_pupil + 4
    j = (np.arange(ng) - (ng - 1) / 2) * dk
    ku, kv = kspan[2] + j, kspan[3] + j
    KU, KV = np.meshgrid(ku, kv, indexing="xy")                  # [row = v, col = u]
    x, y = mapping.invert(KU.ravel(), KV.ravel())
    R = mapping.R
    aim = np.nonzero(np.isfinite(x) & np.isfinite(y) & (np.hypot(x, y) <= 1.0 + 4.0 / n_pupil))[0]
    r = tracer.trace(field_deg, x[aim] * R, y[aim] * R, wavelength_nm=float(lam_nm))
    ok = r.ok
    sel = aim[ok]
    a, b, c, d = mapping.jac(x[sel], y[sel])
    jac_p_per_k = R * R / np.abs(a * d - b * c)                 # |d^2 p / d^2 k| [mm^2]
    amp = np.zeros(KU.size)
    phase = np.zeros(KU.size)
    amp[sel] = np.sqrt(r.transmission[ok] * jac_p_per_k / r.dw[ok])
    # wavefront error: the ray's phase carried back to the reference point P (module docstring)
    w_mm = r.opl[ok] - (r.du[ok] * (r.u[ok] - centre_mm[0]) + r.dv[ok] * (r.v[ok] - centre_mm[1]))
    w_mm = w_mm - np.average(w_mm, weights=amp[sel] ** 2) if sel.size else w_mm
    phase[sel] = 2 * np.pi / lam_mm * w_mm
    k_err = float(max(np.max(np.abs(r.du[ok] - KU.ravel()[sel]), initial=0.0),
                      np.max(np.abs(r.dv[ok] - KV.ravel()[sel]), initial=0.0)) / dk)
    amp2, ph2 = amp.reshape(KU.shape), phase.reshape(KU.shape)
    # phase steps between neighbouring grid samples (> pi: the pupil is undersampled)
    both_u = (amp2[:, 1:] > 0) & (amp2[:, :-1] > 0)
    both_v = (amp2[1:, :] > 0) & (amp2[:-1, :] > 0)
    step = max(np.max(np.abs(np.diff(ph2, axis=1))[both_u], initial=0.0),
               np.max(np.abs(np.diff(ph2, axis=0))[both_v], initial=0.0))
    if sel.size == 0:
        raise ValueError(f"field {tuple(field_deg)} deg: no ray reaches the detector at {lam_nm} nm")
    frac = _mft_intensity(amp2, ph2, ku - kspan[2], kv - kspan[3], lam_mm, xs_mm)
    area = float(np.sum(r.transmission[ok] * jac_p_per_k) * dk * dk)
    rms_w = float(np.sqrt(np.average(w_mm ** 2, weights=amp[sel] ** 2)) / lam_mm)
    diag = {"wavelength_nm": float(lam_nm), "k_grid_error": k_err, "max_phase_step_rad": float(step),
            "alias_free_window_um": float(lam_mm / dk * 1e3), "rms_wavefront_waves": rms_w,
            "pupil_samples": int(sel.size), "n_pupil": int(n_pupil)}
    return frac, area, diag


@dataclass
class PSFResult:
    """A PSF stamp and its metrics (lengths in um, detector frame (u, v) of :mod:`optics.layout`).

    ``image[i, j]`` is the fraction of the total energy falling in the output pixel centred at
    ``center_um + ((j - (n-1)/2) pixel_um, (i - (n-1)/2) pixel_um)`` (rows along v, columns along u),
    renormalised so that the stamp sums to 1; ``energy_in_stamp`` is the fraction before that
    renormalisation (the rest lies in the wings outside the stamp). The encircled energy ``ee`` is
    relative to the *total* energy.
    """

    image: np.ndarray
    pixel_um: float
    center_um: tuple
    field_deg: tuple
    wavelengths_nm: list
    weights: list
    kind: str
    centroid_um: list
    ee_radius_um: np.ndarray
    ee: np.ndarray
    fwhm_um: float
    ee50_um: float
    ee80_um: float
    ellipticity: float
    position_angle_deg: float
    energy_in_stamp: float
    seeing_fwhm_arcsec: float = 0.0
    seeing_profile: str = "gaussian"
    jitter_rms_arcsec: float = 0.0
    geometric: dict | None = None
    diagnostics: dict = field(default_factory=dict)
    design: str = ""
    plate_scale_arcsec_per_mm: float = float("nan")

    def to_json(self) -> dict:
        """Plain-JSON dict: the contract keys (``ee_radius_um``, ``ee``, ``fwhm_um``, ``centroid_um``;
        for geometric PSFs also ``rms_spot_um``, ``extent_tangential_um``, ``extent_sagittal_um``) and
        the other metrics. The image itself is not included (see :func:`write_psf_fits`)."""
        out = {
            "kind": self.kind,
            "field_deg": [float(a) for a in self.field_deg],
            "wavelengths_nm": [float(a) for a in self.wavelengths_nm],
            "weights": [float(a) for a in self.weights],
            "pixel_um": float(self.pixel_um),
            "center_um": [float(a) for a in self.center_um],
            "centroid_um": [float(a) for a in self.centroid_um],
            "fwhm_um": float(self.fwhm_um),
            "ee50_um": float(self.ee50_um),
            "ee80_um": float(self.ee80_um),
            "ellipticity": float(self.ellipticity),
            "position_angle_deg": float(self.position_angle_deg),
            "energy_in_stamp": float(self.energy_in_stamp),
            "seeing_fwhm_arcsec": float(self.seeing_fwhm_arcsec),
            "seeing_profile": self.seeing_profile,
            "jitter_rms_arcsec": float(self.jitter_rms_arcsec),
            "ee_radius_um": [float(a) for a in self.ee_radius_um],
            "ee": [float(a) for a in self.ee],
        }
        if self.geometric is not None:
            for k in ("rms_spot_um", "rms_spot_diameter_um", "extent_tangential_um", "extent_sagittal_um",
                      "throughput", "n_rays"):
                out[k] = self.geometric[k]
            out["geometric_centroid_um"] = self.geometric["centroid_um"]
        if self.diagnostics:
            out["diagnostics"] = self.diagnostics
        return out


def seeing_kernel(dx_um: float, n: int, fwhm_um: float = 0.0, profile: str = "gaussian",
                  beta: float = MOFFAT_BETA_KOLMOGOROV, jitter_sigma_um: float = 0.0) -> np.ndarray:
    """Convolution kernel (n x n, odd n, sum 1) of seeing and jitter sampled at ``dx_um``.

    Gaussian seeing: sigma = FWHM / 2.3548. Moffat seeing: I ~ (1 + r^2/alpha^2)^-beta with
    alpha = FWHM / (2 sqrt(2^(1/beta) - 1)). Jitter: a Gaussian of rms ``jitter_sigma_um`` per axis;
    for Gaussian seeing the two combine in quadrature, for Moffat seeing the jitter is convolved."""
    c = (np.arange(n) - (n - 1) / 2) * dx_um
    X, Y = np.meshgrid(c, c, indexing="xy")
    r2 = X * X + Y * Y

    def gauss(sig):
        # integrate over the sample (error functions) so that narrow kernels stay normalised and centred
        from scipy.special import erf

        e = lambda t: erf(t / (math.sqrt(2) * sig))
        g1 = 0.5 * (e(c + dx_um / 2) - e(c - dx_um / 2))
        return np.outer(g1, g1)

    if profile not in ("gaussian", "moffat"):
        raise ValueError(f"seeing profile must be 'gaussian' or 'moffat', not {profile!r}")
    if fwhm_um > 0 and profile == "moffat":
        alpha = fwhm_um / (2 * math.sqrt(2 ** (1 / beta) - 1))
        k = (1 + r2 / alpha ** 2) ** (-beta)
        k /= k.sum()
        if jitter_sigma_um > 0:
            from scipy.signal import fftconvolve

            k = fftconvolve(k, gauss(jitter_sigma_um), mode="same")
    else:
        sig = math.hypot(fwhm_um / _GAUSS_FWHM, jitter_sigma_um)
        k = gauss(sig) if sig > 0 else (r2 == 0).astype(float)
    return k / k.sum()


def compute_psf(tracer: SequentialTracer, field_deg=(0.0, 0.0), wavelengths_nm=(550.0,), weights=None,
                geometric: bool = False, n_pupil: int = 256, sampling_um: float = 1.0, size_px: int = 97,
                seeing_fwhm_arcsec: float = 0.0, jitter_rms_arcsec: float = 0.0,
                seeing_profile: str = "gaussian", moffat_beta: float = MOFFAT_BETA_KOLMOGOROV,
                n_rays: int = 20000, oversample: int | None = None, seed: int = 0) -> PSFResult:
    """PSF of a star at ``field_deg`` (diffraction from the traced pupil, or geometric).

    Parameters
    ----------
    tracer : SequentialTracer
        The telescope; its obstruction mode decides which rays are stopped (``"analytic"`` for the real
        obscuration, spider and vignetting).
    field_deg : (float, float)
        Field angles (theta_x, theta_y) [deg].
    wavelengths_nm : sequence of float
        Wavelengths [nm]; one for a monochromatic PSF.
    weights : sequence of float, optional
        Relative weight of each wavelength (the caller's QE x spectrum); equal when omitted. Each
        wavelength's PSF is scaled by its weight times its transmitted energy (Fresnel losses).
    geometric : bool
        Rays only: the image is the histogram of ray hits and the metrics come from the rays
        (:func:`spot_metrics`), unless seeing or jitter are set (then EE, FWHM and centroid come from
        the convolved image).
    n_pupil : int
        Pupil samples across the beam (diffraction). The sum repeats after lambda / dk =
        n_pupil lambda / (2 NA) (~350 um at 550 nm, n_pupil = 256); n_pupil is raised where needed so
        that this period exceeds the computed window (stamp plus the seeing margin). Aberrations must keep
        the phase step between samples below pi (``diagnostics["max_phase_step_rad"]``; a warning
        otherwise: use more samples or ``geometric=True``).
    sampling_um : float
        Output pixel size [um]; the intensity is integrated over each output pixel.
    size_px : int
        Stamp size (``size_px`` x ``size_px`` output pixels), centred on the geometric centroid of the
        unobstructed bundle at the most heavily weighted wavelength (``center_um``).
    seeing_fwhm_arcsec, jitter_rms_arcsec : float
        Seeing FWHM and pointing jitter (rms per axis) [arcsec]; 0 = none.
    seeing_profile : {"gaussian", "moffat"}
    moffat_beta : float
        Moffat exponent (4.765: Kolmogorov turbulence).
    n_rays : int
        Rays per wavelength of the geometric spot.
    oversample : int, optional
        Internal samples per output pixel and axis; default: enough for Nyquist sampling of the
        intensity at the shortest wavelength (spacing <= lambda / (4 NA)).
    seed : int
        Pupil sample shift of the geometric spot (the diffraction PSF has no randomness).

    Returns
    -------
    PSFResult
    """
    lam, w = _as_wavelengths(wavelengths_nm, weights)
    if size_px < 3:
        raise ValueError("size_px must be at least 3")
    if sampling_um <= 0:
        raise ValueError("sampling_um must be positive")
    if seeing_profile not in ("gaussian", "moffat"):
        raise ValueError(f"seeing_profile must be 'gaussian' or 'moffat', not {seeing_profile!r}")
    if seeing_fwhm_arcsec < 0 or jitter_rms_arcsec < 0:
        raise ValueError("seeing_fwhm_arcsec and jitter_rms_arcsec must be >= 0")
    field_deg = (float(field_deg[0]), float(field_deg[1]))
    scale = plate_scale_arcsec_per_um(tracer)                       # arcsec per um
    seeing_um = seeing_fwhm_arcsec / scale
    jitter_um = jitter_rms_arcsec / scale
    blur = seeing_um > 0 or jitter_um > 0
    # margin for the convolution kernel (computed, then cropped after the convolution)
    reach_um = (5.0 if seeing_profile == "gaussian" else 8.0) * seeing_um + 5.0 * jitter_um
    pad_px = math.ceil(reach_um / sampling_um) if blur else 0
    n_tot = size_px + 2 * pad_px
    diags = []
    free = _free_tracer(tracer)
    iref = int(np.argmax(w))
    geo = None
    if geometric:
        u, v, ww, thr = _trace_spot(tracer, field_deg, n_rays, lam, w, seed)
        geo = spot_metrics(u, v, ww, field_deg)
        geo["throughput"] = float(thr)
        centre_mm = (geo["centroid_um"][0] * 1e-3, geo["centroid_um"][1] * 1e-3)
        m = 1
        half = n_tot * sampling_um / 2 * 1e-3
        hist, _, _ = np.histogram2d(v - centre_mm[1], u - centre_mm[0], bins=n_tot,
                                    range=[[-half, half], [-half, half]], weights=ww)
        internal = hist / ww.sum()
        dx_int = sampling_um
    else:
        internal = None
        maps, centres = [], []
        for lam_i in lam:
            mp, cen_i, ks = _fit_pupil_map(free, field_deg, lam_i)
            maps.append((mp, ks))
            centres.append(cen_i)
        centre_mm = centres[iref]
        # Nyquist for the intensity: dx <= lambda / (4 NA); NA from the traced beam
        na = max(0.5 * max(ks[0], ks[1]) for _, ks in maps)
        m = oversample or max(1, math.ceil(sampling_um * 4 * na / (lam.min() * 1e-3)))
        dx_int = sampling_um / m
        xs_mm = (np.arange(n_tot * m) - (n_tot * m - 1) / 2) * dx_int * 1e-3
        total_w = 0.0
        for lam_i, w_i, (mp, ks) in zip(lam, w, maps, strict=True):
            if w_i == 0:
                continue
            frac, area, dg = _mono_diffraction(tracer, field_deg, mp, ks, centre_mm, lam_i, n_pupil, xs_mm)
            diags.append(dg)
            contrib = w_i * area * frac
            internal = contrib if internal is None else internal + contrib
            total_w += w_i * area
        internal = internal / total_w
        worst = max(diags, key=lambda d: d["max_phase_step_rad"])
        if worst["max_phase_step_rad"] > math.pi:
            warnings.warn(f"field {field_deg} deg: the pupil grid (n_pupil={n_pupil}) undersamples the "
                          f"wavefront (phase steps up to {worst['max_phase_step_rad']:.2f} rad between samples "
                          f"at {worst['wavelength_nm']:.0f} nm); raise n_pupil or use geometric=True",
                          RuntimeWarning, stacklevel=2)
    total_energy = 1.0
    if blur:
        from scipy.signal import fftconvolve

        kn = 2 * math.ceil(reach_um / dx_int) + 1
        kern = seeing_kernel(dx_int, kn, seeing_um, seeing_profile, moffat_beta, jitter_um)
        internal = fftconvolve(internal, kern, mode="same")
        internal = np.maximum(internal, 0.0)
    crop = pad_px * m
    if crop:
        internal = internal[crop:-crop, crop:-crop]
    image_int = internal
    dx_int_um = dx_int
    out = _bin(image_int, m)
    in_stamp = float(out.sum()) / total_energy
    # metrics on the internal (finer) grid
    n_int = image_int.shape[0]
    c = (np.arange(n_int) - (n_int - 1) / 2) * dx_int_um
    e_sum = image_int.sum()
    ox = float(np.sum(image_int.sum(axis=0) * c) / e_sum)
    oy = float(np.sum(image_int.sum(axis=1) * c) / e_sum)
    cen = [centre_mm[0] * 1e3 + ox, centre_mm[1] * 1e3 + oy]
    rmax = n_int * dx_int_um / 2 - max(abs(ox), abs(oy))
    radii = np.linspace(0.0, max(rmax, dx_int_um), 200)
    if geometric and not blur:
        ee_r, ee = np.asarray(geo["ee_radius_um"]), np.asarray(geo["ee"])
        fwhm, cen = geo["fwhm_um"], list(geo["centroid_um"])
        ee50, ee80 = geo["ee50_um"], geo["ee80_um"]
    else:
        ee_r = radii
        ee = encircled_energy_image(image_int, dx_int_um, ox, oy, radii, total=total_energy)
        fwhm = effective_fwhm(image_int, dx_int_um)
        ee50, ee80 = _quantile_radius(ee_r, ee, 0.5), _quantile_radius(ee_r, ee, 0.8)
    ap = 2 * ee80 if np.isfinite(ee80) else rmax
    ell, pa = second_moment_shape(image_int, dx_int_um, ox, oy, ap)
    return PSFResult(
        image=out / out.sum(), pixel_um=float(sampling_um), center_um=(centre_mm[0] * 1e3, centre_mm[1] * 1e3),
        field_deg=field_deg, wavelengths_nm=lam.tolist(), weights=w.tolist(),
        kind="geometric" if geometric else "diffraction", centroid_um=cen, ee_radius_um=np.asarray(ee_r),
        ee=np.asarray(ee), fwhm_um=float(fwhm), ee50_um=float(ee50), ee80_um=float(ee80), ellipticity=ell,
        position_angle_deg=pa, energy_in_stamp=in_stamp, seeing_fwhm_arcsec=float(seeing_fwhm_arcsec),
        seeing_profile=seeing_profile, jitter_rms_arcsec=float(jitter_rms_arcsec), geometric=geo,
        diagnostics={"oversample": m, "per_wavelength": diags} if diags else {"oversample": m},
        design=tracer.design.name, plate_scale_arcsec_per_mm=tracer.design.plate_scale_arcsec_per_mm)


# ---- PSF grids, FITS and plots --------------------------------------------------------------------------
@dataclass
class PSFGrid:
    """PSF stamps over the field: ``images[k]`` is the PSF of ``fields_deg[k]`` (each sums to 1), all with
    the same ``pixel_um`` sampling, centred on ``center_um[k]`` (detector frame, um)."""

    images: np.ndarray
    pixel_um: float
    fields_deg: np.ndarray
    center_um: np.ndarray
    wavelengths_nm: list
    weights: list
    metrics: list
    kind: str = "diffraction"
    seeing_fwhm_arcsec: float = 0.0
    seeing_profile: str = "gaussian"
    jitter_rms_arcsec: float = 0.0
    design: str = ""
    plate_scale_arcsec_per_mm: float = float("nan")

    def nearest(self, field_deg) -> int:
        """Index of the grid field closest to ``field_deg`` [deg]."""
        d = np.hypot(self.fields_deg[:, 0] - field_deg[0], self.fields_deg[:, 1] - field_deg[1])
        return int(np.argmin(d))


def detector_fields(design, nx: int = 3, ny: int = 3, fill: float = 0.95) -> np.ndarray:
    """(nx * ny, 2) field angles [deg] whose ideal images span ``fill`` of the detector (corners
    included): theta = atan(-(u, v) / f), rows from -v to +v."""
    f = design.primary.focal_length_mm
    u = np.linspace(-1, 1, nx) * fill * design.focal_plane.width_mm / 2 if nx > 1 else np.zeros(1)
    v = np.linspace(-1, 1, ny) * fill * design.focal_plane.height_mm / 2 if ny > 1 else np.zeros(1)
    U, V = np.meshgrid(u, v, indexing="xy")
    return np.stack([np.degrees(np.arctan(-U.ravel() / f)), np.degrees(np.arctan(-V.ravel() / f))], -1)


_GRID_KEYS = ("fwhm_um", "ee50_um", "ee80_um", "ellipticity", "energy_in_stamp")


def _metrics_of(res: PSFResult) -> dict:
    m = {k: float(getattr(res, k)) for k in _GRID_KEYS}
    m["centroid_um"] = [float(a) for a in res.centroid_um]
    if res.geometric is not None:
        m["rms_spot_um"] = float(res.geometric["rms_spot_um"])
    return m


def psf_grid(tracer: SequentialTracer, fields_deg=None, **kwargs) -> PSFGrid:
    """PSFs at several field points (:func:`compute_psf` for each; keyword arguments are passed on).

    ``fields_deg`` is an (n, 2) list of (theta_x, theta_y) [deg]; default :func:`detector_fields`
    (3 x 3 over the detector, corners included)."""
    fields = detector_fields(tracer.design) if fields_deg is None else np.asarray(fields_deg, dtype=float)
    fields = fields.reshape(-1, 2)
    results = [compute_psf(tracer, field_deg=tuple(f), **kwargs) for f in fields]
    r0 = results[0]
    return PSFGrid(images=np.stack([r.image for r in results]), pixel_um=r0.pixel_um, fields_deg=fields,
                   center_um=np.array([r.center_um for r in results]), wavelengths_nm=r0.wavelengths_nm,
                   weights=r0.weights, metrics=[_metrics_of(r) for r in results], kind=r0.kind,
                   seeing_fwhm_arcsec=r0.seeing_fwhm_arcsec, seeing_profile=r0.seeing_profile,
                   jitter_rms_arcsec=r0.jitter_rms_arcsec, design=tracer.design.name,
                   plate_scale_arcsec_per_mm=tracer.design.plate_scale_arcsec_per_mm)


#: Default band of :func:`cached_psf_grid` [nm] (equal weights): the IMX411's 450-900 nm sensitivity. The
#: scenes package passes its detector's QE x source spectrum instead (optics does not import detector).
DEFAULT_BAND_NM = (450.0, 500.0, 550.0, 600.0, 650.0, 700.0, 800.0, 900.0)


def cached_psf_grid(design, pitch_um: float, nx: int = 3, ny: int = 3, *, oversample: int = 3,
                    stamp_px: int = 21, wavelengths_nm=DEFAULT_BAND_NM, weights=None, n_pupil: int = 256,
                    use_cache: bool = True) -> Path:
    """Path of a FITS cube of diffraction PSFs over the detector, ray-traced on first use and cached.

    The entry point for the scenes package: it starts Mitsuba itself (``optics.llvm.init_mitsuba``) when
    the cache misses. The file lives in :func:`optics.cache.cache_dir` under a key that hashes the
    design's content and every setting below, and reads back with :func:`read_psf_fits` as a
    :class:`PSFGrid`.

    Parameters
    ----------
    design : Design or str
        The telescope (a built-in name such as ``"art"`` or a design TOML path also works).
    pitch_um : float
        Detector pixel pitch [um]. The stamps are sampled at ``pitch_um / oversample`` (FITS card
        ``PIXUM``), each sample holding the PSF's energy fraction inside it, so summing
        ``oversample x oversample`` blocks gives the energy per detector pixel for a star whose image
        lies at a block's centre.
    nx, ny : int
        Field points across the detector's width and height (:func:`detector_fields`: their ideal images
        span 95 % of the detector, corners included; ``fields_deg`` of the grid, rows from -v to +v).
    oversample : int
        Samples per detector pixel and axis (odd: a sample is centred on the stamp centre pixel's centre).
    stamp_px : int
        Stamp side in detector pixels (the file's planes are ``stamp_px * oversample`` samples square).
    wavelengths_nm, weights : sequence of float
        The band [nm] and relative weights (the caller's QE x photon spectrum; equal weights if None).
    n_pupil : int
        Pupil samples across the beam (:func:`compute_psf`).
    use_cache : bool
        False recomputes and overwrites the cached file.

    Returns
    -------
    pathlib.Path
        FITS file of :func:`write_psf_fits`: a cube of ``nx * ny`` planes (each sums to 1), stamp
        ``k`` centred at ``center_um[k]`` (detector frame, um; the PSF's own centroid is
        ``metrics[k]["centroid_um"]``), field angles ``fields_deg[k]`` [deg].
    """
    from . import cache
    from .design import as_design

    d = as_design(design)
    if pitch_um <= 0 or nx < 1 or ny < 1 or oversample < 1 or stamp_px < 3:
        raise ValueError("cached_psf_grid: pitch_um > 0, nx, ny, oversample >= 1 and stamp_px >= 3 needed")
    lam, w = _as_wavelengths(wavelengths_nm, weights)
    settings = {"pitch_um": float(pitch_um), "nx": int(nx), "ny": int(ny), "oversample": int(oversample),
                "stamp_px": int(stamp_px), "wavelengths_nm": lam.tolist(), "weights": w.tolist(),
                "n_pupil": int(n_pupil), "kind": "diffraction"}

    def write(path):
        from .llvm import init_mitsuba

        # traced with a detector 1.5 times the focal plane (as optics.distortion's SIP): a perturbed design
        # moves its image (a diagonal tilted 0.1 deg on art: 1.5 mm), and the grid's corner points, at 95 % of
        # the focal plane, would lose their rays past its edge. The field points and the cache key stay the
        # design's; for the nominal design nothing changes (its spots lie far inside the edge).
        data = d.model_dump()
        data["focal_plane"]["width_mm"] *= 1.5
        data["focal_plane"]["height_mm"] *= 1.5
        tracer = SequentialTracer(type(d).model_validate(data), init_mitsuba(), obstruct="analytic")
        grid = psf_grid(tracer, detector_fields(d, nx, ny), wavelengths_nm=lam, weights=w,
                        sampling_um=pitch_um / oversample, size_px=stamp_px * oversample, n_pupil=n_pupil)
        write_psf_fits(grid, path)

    return cache.cached_file("psfgrid", d, settings, ".fits", write, use_cache=use_cache)


def _as_grid(obj) -> PSFGrid:
    if isinstance(obj, PSFGrid):
        return obj
    if isinstance(obj, PSFResult):
        return PSFGrid(images=obj.image[None], pixel_um=obj.pixel_um, fields_deg=np.array([obj.field_deg]),
                       center_um=np.array([obj.center_um]), wavelengths_nm=obj.wavelengths_nm,
                       weights=obj.weights, metrics=[_metrics_of(obj)], kind=obj.kind,
                       seeing_fwhm_arcsec=obj.seeing_fwhm_arcsec, seeing_profile=obj.seeing_profile,
                       jitter_rms_arcsec=obj.jitter_rms_arcsec, design=obj.design,
                       plate_scale_arcsec_per_mm=obj.plate_scale_arcsec_per_mm)
    raise TypeError(f"expected a PSFResult or PSFGrid, not {type(obj).__name__}")


def write_psf_fits(result_or_grid, path, overwrite: bool = True) -> Path:
    """Write a PSF (2-D image) or a PSF grid (cube, one plane per field point) to FITS.

    Primary HDU: float32 image/cube, each plane summing to 1 (BUNIT 'fraction'); header cards PIXUM
    (sampling [um]), NFIELD, FLDX_k / FLDY_k (field angles [deg]) and CENU_k / CENV_k (stamp centres on
    the detector [um]) for k = 1..NFIELD, NWAVE, WAVE_i [nm] and WGHT_i, KIND, SEEING [arcsec], SEEPROF,
    JITTER [arcsec], PLATESC [arcsec/mm]. Extension ``FIELDS``: one row per field with the same field
    and centre columns and the metrics (FWHM, EE50, EE80, ellipticity, centroid, energy in stamp)."""
    from astropy.io import fits

    g = _as_grid(result_or_grid)
    data = g.images.astype(np.float32)
    hdu = fits.PrimaryHDU(data[0] if len(data) == 1 else data)
    h = hdu.header
    h["BUNIT"] = ("fraction", "energy fraction per pixel, planes sum to 1")
    h["PIXUM"] = (float(g.pixel_um), "PSF sampling [um]")
    h["KIND"] = (g.kind, "diffraction or geometric")
    h["DESIGN"] = g.design
    h["PLATESC"] = (float(g.plate_scale_arcsec_per_mm), "plate scale [arcsec/mm]")
    h["SEEING"] = (float(g.seeing_fwhm_arcsec), "seeing FWHM [arcsec]")
    h["SEEPROF"] = (g.seeing_profile, "seeing profile")
    h["JITTER"] = (float(g.jitter_rms_arcsec), "pointing jitter rms per axis [arcsec]")
    h["NFIELD"] = (len(g.fields_deg), "field points (cube planes)")
    for k, (f, c) in enumerate(zip(g.fields_deg, g.center_um, strict=True), start=1):
        h[f"FLDX{k}"] = (float(f[0]), f"field {k} theta_x [deg]")
        h[f"FLDY{k}"] = (float(f[1]), f"field {k} theta_y [deg]")
        h[f"CENU{k}"] = (float(c[0]), f"stamp {k} centre u [um]")
        h[f"CENV{k}"] = (float(c[1]), f"stamp {k} centre v [um]")
    h["NWAVE"] = (len(g.wavelengths_nm), "wavelengths")
    for i, (lam, w) in enumerate(zip(g.wavelengths_nm, g.weights, strict=True), start=1):
        h[f"WAVE{i}"] = (float(lam), "wavelength [nm]")
        h[f"WGHT{i}"] = (float(w), "relative weight")
    cols = [fits.Column(name="FIELD_X_DEG", format="D", array=g.fields_deg[:, 0]),
            fits.Column(name="FIELD_Y_DEG", format="D", array=g.fields_deg[:, 1]),
            fits.Column(name="CENTER_U_UM", format="D", array=g.center_um[:, 0]),
            fits.Column(name="CENTER_V_UM", format="D", array=g.center_um[:, 1]),
            fits.Column(name="CENTROID_U_UM", format="D", array=[m["centroid_um"][0] for m in g.metrics]),
            fits.Column(name="CENTROID_V_UM", format="D", array=[m["centroid_um"][1] for m in g.metrics])]
    for key in _GRID_KEYS:
        cols.append(fits.Column(name=key.upper(), format="D", array=[m[key] for m in g.metrics]))
    table = fits.BinTableHDU.from_columns(cols, name="FIELDS")
    path = Path(path)
    fits.HDUList([hdu, table]).writeto(path, overwrite=overwrite)
    return path


def read_psf_fits(path) -> PSFGrid:
    """Read a file written by :func:`write_psf_fits` (a single PSF comes back as a grid of one)."""
    from astropy.io import fits

    with fits.open(path) as hdul:
        h = hdul[0].header
        data = np.asarray(hdul[0].data, dtype=np.float64)
        t = hdul["FIELDS"].data
        images = data[None] if data.ndim == 2 else data
        n = int(h["NFIELD"])
        metrics = []
        for row in t:
            m = {k: float(row[k.upper()]) for k in _GRID_KEYS}
            m["centroid_um"] = [float(row["CENTROID_U_UM"]), float(row["CENTROID_V_UM"])]
            metrics.append(m)
        return PSFGrid(
            images=images, pixel_um=float(h["PIXUM"]),
            fields_deg=np.array([[h[f"FLDX{k}"], h[f"FLDY{k}"]] for k in range(1, n + 1)], dtype=float),
            center_um=np.array([[h[f"CENU{k}"], h[f"CENV{k}"]] for k in range(1, n + 1)], dtype=float),
            wavelengths_nm=[float(h[f"WAVE{i}"]) for i in range(1, int(h["NWAVE"]) + 1)],
            weights=[float(h[f"WGHT{i}"]) for i in range(1, int(h["NWAVE"]) + 1)],
            metrics=metrics, kind=str(h["KIND"]), seeing_fwhm_arcsec=float(h["SEEING"]),
            seeing_profile=str(h["SEEPROF"]), jitter_rms_arcsec=float(h["JITTER"]), design=str(h["DESIGN"]),
            plate_scale_arcsec_per_mm=float(h["PLATESC"]))


def plot_psf_grid(grid, path, floor: float = 1e-4, dpi: int = 64) -> Path:
    """PNG of the PSF stamps, log-stretched (log10 of I / I_max down to ``floor``), each labelled with its
    field angles, FWHM and EE80. Field points on a regular grid are placed by field position (top row =
    largest theta_y). Uses matplotlib's Agg canvas directly (no global backend change)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    g = _as_grid(grid)
    fx, fy = np.round(g.fields_deg[:, 0], 6), np.round(g.fields_deg[:, 1], 6)
    ux, uy = np.unique(fx), np.unique(fy)
    n = len(g.images)
    if len(ux) * len(uy) == n:
        ncol, nrow = len(ux), len(uy)
        pos = [(len(uy) - 1 - int(np.searchsorted(uy, b)), int(np.searchsorted(ux, a)))
               for a, b in zip(fx, fy, strict=True)]
    else:
        ncol = math.ceil(math.sqrt(n))
        nrow = math.ceil(n / ncol)
        pos = [(k // ncol, k % ncol) for k in range(n)]
    fig = Figure(figsize=(2.3 * ncol, 2.5 * nrow))
    FigureCanvasAgg(fig)
    half = g.images.shape[-1] * g.pixel_um / 2
    for k, (r, c) in enumerate(pos):
        ax = fig.add_subplot(nrow, ncol, r * ncol + c + 1)
        img = g.images[k]
        ax.imshow(np.log10(np.maximum(img / img.max(), floor)), origin="lower", cmap="magma", vmin=math.log10(floor),
                  vmax=0, extent=(-half, half, -half, half), interpolation="nearest")
        m = g.metrics[k]
        ax.set_title(f"({g.fields_deg[k, 0]:+.2f}, {g.fields_deg[k, 1]:+.2f}) deg\n"
                     f"FWHM {m['fwhm_um']:.1f} um, r(EE80) {m['ee80_um']:.1f} um", fontsize=7)
        ax.tick_params(labelsize=6)
        if r == nrow - 1:
            ax.set_xlabel("u [um]", fontsize=7)
        if c == 0:
            ax.set_ylabel("v [um]", fontsize=7)
    lam = ", ".join(f"{a:.0f}" for a in g.wavelengths_nm)
    fig.suptitle(f"{g.design or 'PSF'} {g.kind} PSF, log10(I/Imax) >= {math.log10(floor):.0f}; lambda = {lam} nm",
                 fontsize=8)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=dpi)
    return path
