"""Alignment from the stars: fit the ``[perturbation]`` of a design to measured star moments over the field.

Model
    For a star at field angles theta the optics give (:func:`optics.gradients.spot_moments`) the spot's
    centroid (cu, cv) and second central moments (muu, mvv, muv) as functions of the perturbations p. A
    measured star is the optical spot convolved with everything else (seeing, diffraction, pixel, charge
    diffusion, jitter); second moments add under convolution, so, for an isotropic rest,

        Muu = muu(p) + s,   Mvv = mvv(p) + s,   Muv = muv(p)          (s >= 0: one nuisance, [mm^2])

    and the ellipticity components are e1 = (Muu - Mvv) / (Muu + Mvv), e2 = 2 Muv / (Muu + Mvv). The
    positions carry the pointing and the plate solution: the measured (cu, cv) are compared after a
    similarity transform (shift, rotation, scale: four more nuisances, linear), so only the field-dependent
    part of a perturbation's image motion (differential distortion) informs the fit.

Fit
    The optics is traced at ``nodes`` x ``nodes`` Chebyshev nodes over the stars' field and its moments
    and Jacobian interpolated to every star (tensor-product Lagrange polynomials; the moments are smooth
    in the field angle); every star is a residual. Gauss-Newton with Levenberg-Marquardt damping (Madsen, Nielsen
    & Tingleff 2004, "Methods for non-linear least squares problems", sect. 3.2) on the normalised
    residuals, the Jacobian of the optics from drjit's forward-mode AD (one traversal per iteration),
    the nuisances' columns analytic. Parameter errors from the Fisher matrix F = J^T W J at the solution
    (Cramer-Rao bound; covariance F^-1); when no measurement errors are given, they are taken as the
    residuals' RMS (errors scaled by sqrt(chi^2 / dof)).

Explanation
    The most significant perturbation (|value| / error) is described in optical words: which way the part
    is off, and the field pattern its fitted value produces (where the spot grows: from the model's
    change of the RMS spot over the field, fitted with a plane a + b u + c v).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from .design import Design, with_perturbation
from .gradients import MOMENT_NAMES, spot_moments
from .sequential import SequentialTracer

QUANTITIES = ("cu_mm", "cv_mm", "muu_mm2", "mvv_mm2", "muv_mm2", "e1", "e2")
ALIGNMENT_PARAMETERS = ("sensor_piston_um", "sensor_tilt_x_deg", "sensor_tilt_y_deg", "diagonal_tilt_x_deg",
                        "diagonal_tilt_y_deg", "primary_tilt_x_deg", "primary_tilt_y_deg")
CORRECTOR_PARAMETERS = ("corrector_decenter_x_mm", "corrector_decenter_y_mm", "corrector_tilt_x_deg",
                        "corrector_tilt_y_deg", "corrector_spacing_mm")
NUISANCES = ("shift_u_mm", "shift_v_mm", "rotation_rad", "scale", "extra_moment_mm2")


#: one family per physical cause (the candidates of :func:`rank_perturbations`)
FAMILIES = {
    "defocus": ("sensor_piston_um",),
    "sensor_tilt": ("sensor_tilt_x_deg", "sensor_tilt_y_deg"),
    "diagonal_tilt": ("diagonal_tilt_x_deg", "diagonal_tilt_y_deg"),
    "primary_tilt": ("primary_tilt_x_deg", "primary_tilt_y_deg"),
    "primary_decenter": ("primary_decenter_x_mm", "primary_decenter_y_mm"),
    "corrector_decenter": ("corrector_decenter_x_mm", "corrector_decenter_y_mm"),
    "corrector_tilt": ("corrector_tilt_x_deg", "corrector_tilt_y_deg"),
    "corrector_spacing": ("corrector_spacing_mm",),
}


def default_parameters(design: Design) -> tuple:
    """Focus, sensor tilt, diagonal tilt and primary tilt: a set the stars can tell apart. Left out:
    the primary's decentre (on the field a shift, absorbed by the pointing, plus the beam's decentre in
    the corrector) and the corrector's decentre and tilt, which a diagonal tilt mimics (turning the beam
    at the diagonal = moving corrector and sensor rigidly about it): fit those one family at a time with
    :func:`rank_perturbations`."""
    return ALIGNMENT_PARAMETERS


@dataclass
class AlignmentFit:
    """Result of :func:`fit_perturbations` (values in the units of the ``[perturbation]`` names)."""

    names: tuple
    values: np.ndarray
    errors: np.ndarray
    covariance: np.ndarray
    nuisances: dict
    chi2: float
    dof: int
    iterations: int
    seconds: float
    explanation: str
    explanations: dict
    fields_deg: np.ndarray          # the field points (interpolation nodes) where the optics was traced
    n_stars: int
    #: correlation of each fitted perturbation with the isotropic rest ``extra_moment_mm2`` (Fisher matrix): near
    #: +-1 the moments cannot tell the perturbation from a change of the seeing (a defocus, mostly)
    rest_correlation: np.ndarray | None = None

    @property
    def significance(self) -> np.ndarray:
        return np.abs(self.values) / np.where(self.errors > 0, self.errors, np.inf)

    def params(self) -> dict:
        return {n: float(v) for n, v in zip(self.names, self.values)}

    def significant(self, threshold: float = 3.0) -> dict:
        """The perturbations fitted at more than ``threshold`` errors from zero: name -> (value, error)."""
        return {n: (float(v), float(e)) for n, v, e, z in zip(self.names, self.values, self.errors,
                                                              self.significance) if z > threshold}

    def to_json(self) -> dict:
        return {"params": self.params(), "errors": {n: float(e) for n, e in zip(self.names, self.errors)},
                "significance": {n: float(z) for n, z in zip(self.names, self.significance)},
                "correlation": _correlation(self.covariance).round(4).tolist(), "nuisances": self.nuisances,
                "chi2": self.chi2, "dof": self.dof, "iterations": self.iterations,
                "seconds": round(self.seconds, 3), "explanation": self.explanation,
                "explanations": self.explanations, "n_stars": self.n_stars,
                "fields_deg": self.fields_deg.round(5).tolist()}


def _correlation(cov):
    d = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    return cov / np.outer(d, d)


def _interpolation(fstar, nodes: int):
    """Chebyshev nodes (nodes x nodes field points [deg]) spanning the stars' field and the matrix
    W (n_stars, nodes^2) of tensor Lagrange weights: value at each star = W @ values at the nodes."""
    lo, hi = fstar.min(0), fstar.max(0)
    pad = np.maximum(0.02 * (hi - lo), 1e-4)
    lo, hi = lo - pad, hi + pad
    k = np.arange(nodes)
    cheb = np.cos((2 * k + 1) * np.pi / (2 * nodes))[::-1] if nodes > 1 else np.zeros(1)
    ax = [0.5 * (lo[i] + hi[i]) + 0.5 * (hi[i] - lo[i]) * cheb for i in range(2)]

    def lagrange(xn, x):
        L = np.ones((len(x), len(xn)))
        for j in range(len(xn)):
            for m in range(len(xn)):
                if m != j:
                    L[:, j] *= (x - xn[m]) / (xn[j] - xn[m])
        return L

    Lx, Ly = lagrange(ax[0], fstar[:, 0]), lagrange(ax[1], fstar[:, 1])
    W = (Lx[:, :, None] * Ly[:, None, :]).reshape(len(fstar), -1)
    X, Y = np.meshgrid(ax[0], ax[1], indexing="ij")
    return np.stack([X.ravel(), Y.ravel()], -1), W


def _model(m_values, jac, nuis, fields_u, fields_v, keys):
    """Predicted quantities (dict of arrays) and their derivatives with respect to (perturbations,
    nuisances) from the optics' moments ``m_values`` (n, 7) and Jacobian (n, 7, p)."""
    du, dv, rot, scale, s = nuis
    cu, cv, muu, mvv, muv = (m_values[:, i] for i in range(5))
    J = {MOMENT_NAMES[i]: jac[:, i, :] for i in range(5)}
    n = len(cu)
    one, zero = np.ones(n), np.zeros(n)
    pred, dp, dn = {}, {}, {}
    # similarity transform of the positions about the field centre (small rotation and scale)
    pred["cu_mm"] = cu + du + scale * cu - rot * cv
    pred["cv_mm"] = cv + dv + scale * cv + rot * cu
    dp["cu_mm"] = J["cu_mm"] * (1 + scale) - rot * J["cv_mm"]
    dp["cv_mm"] = J["cv_mm"] * (1 + scale) + rot * J["cu_mm"]
    dn["cu_mm"] = np.stack([one, zero, -cv, cu, zero], -1)
    dn["cv_mm"] = np.stack([zero, one, cu, cv, zero], -1)
    Muu, Mvv, Muv = muu + s, mvv + s, muv
    pred["muu_mm2"], pred["mvv_mm2"], pred["muv_mm2"] = Muu, Mvv, Muv
    dp["muu_mm2"], dp["mvv_mm2"], dp["muv_mm2"] = J["muu_mm2"], J["mvv_mm2"], J["muv_mm2"]
    dn["muu_mm2"] = np.stack([zero, zero, zero, zero, one], -1)
    dn["mvv_mm2"] = dn["muu_mm2"]
    dn["muv_mm2"] = np.zeros((n, 5))
    T = Muu + Mvv
    dT = J["muu_mm2"] + J["mvv_mm2"]
    pred["e1"] = (Muu - Mvv) / T
    pred["e2"] = 2 * Muv / T
    dp["e1"] = ((J["muu_mm2"] - J["mvv_mm2"]) * T[:, None] - (Muu - Mvv)[:, None] * dT) / (T ** 2)[:, None]
    dp["e2"] = (2 * J["muv_mm2"] * T[:, None] - 2 * Muv[:, None] * dT) / (T ** 2)[:, None]
    dn["e1"] = np.stack([zero, zero, zero, zero, -2 * (Muu - Mvv) / T ** 2], -1)
    dn["e2"] = np.stack([zero, zero, zero, zero, -4 * Muv / T ** 2], -1)
    return ({k: pred[k] for k in keys}, {k: dp[k] for k in keys}, {k: dn[k] for k in keys})


def fit_perturbations(design: Design, mi, fields_deg, measured: dict, sigma: dict | None = None, *,
                      params=None, nodes: int = 8, n_rays: int = 1500, wavelengths_nm=(550.0,), weights=None,
                      max_iter: int = 15, tracer: SequentialTracer | None = None,
                      explain_top: bool = True) -> AlignmentFit:
    """Fit perturbations of ``design`` to measured stars.

    Parameters
    ----------
    design : Design
        The nominal telescope (its own ``[perturbation]``, if any, is the starting point).
    mi : module
        Mitsuba with an llvm variant (``optics.llvm.init_mitsuba``).
    fields_deg : (n, 2) array
        Field angles (theta_x, theta_y) [deg] of the n stars (from their catalogue positions).
    measured : dict of (n,) arrays
        Any of ``cu_mm``, ``cv_mm`` (image position on the focal plane, u = sensor x, v = sensor y [mm],
        origin at the sensor's centre), ``muu_mm2``, ``mvv_mm2``, ``muv_mm2`` (second central moments
        [mm^2]) and ``e1``, ``e2`` (ellipticity components, dimensionless). Pixel quantities convert with
        the pixel pitch: mm = px * pitch_um / 1000, mm^2 = px^2 * (pitch_um / 1000)^2.
    sigma : dict of arrays or scalars, optional
        1-sigma errors of the measured quantities per star (same keys). Missing: from the cells' scatter,
        and the errors are scaled by sqrt(chi^2 / dof).
    params : sequence of str, optional
        ``[perturbation]`` names to fit (default :func:`default_parameters`); e.g. ``("sensor_piston_um",)``
        for a defocus-only fit, ``()`` for the nuisances alone (the reference of :func:`rank_perturbations`).
    nodes : int
        Field points per axis (Chebyshev nodes over the stars' field) where the optics is traced; the
        moments and their Jacobian are interpolated to each star (tensor Lagrange, degree nodes - 1).
    n_rays, wavelengths_nm, weights
        The optics model's pupil sample and band (:func:`optics.gradients.spot_moments`).

    Returns
    -------
    AlignmentFit
        ``values``, ``errors`` (Fisher), ``covariance``, ``nuisances``, ``chi2``/``dof``, ``explanation``
        (one line), ``explanations`` (one per parameter), ``significance``.
    """
    t0 = time.perf_counter()
    names = tuple(default_parameters(design) if params is None else params)
    keys = [k for k in QUANTITIES if k in measured]
    if not keys:
        raise ValueError(f"measured: no known quantity (expected some of {', '.join(QUANTITIES)})")
    fstar = np.atleast_2d(np.asarray(fields_deg, float))
    n_stars = len(fstar)
    M = {k: np.asarray(measured[k], float).ravel() for k in keys}
    S = {}
    for k in keys:
        if sigma is not None and k in sigma:
            S[k] = np.broadcast_to(np.asarray(sigma[k], float), (n_stars,)).copy()
        else:
            S[k] = np.full(n_stars, np.nan)
    # the optics model at Chebyshev nodes over the stars' field, interpolated to every star (degree
    # nodes - 1 per axis: the moments vary smoothly over the field)
    F, W = _interpolation(fstar, nodes)
    tr = tracer or SequentialTracer(design, mi)
    x = np.array([float(getattr(design.perturbation, n)) for n in names])
    nuis = np.zeros(5)
    nuis[4] = _initial_extra_moment(M)
    kw = {"n_rays": n_rays, "wavelengths_nm": wavelengths_nm, "weights": weights}

    def residuals(x, nuis):
        m = spot_moments(tr, F, names, at=dict(zip(names, x)), **kw)
        jac = m.jacobian if names else np.zeros((len(F), 7, 0))
        vals = W @ m.values
        jst = np.einsum("sn,nqp->sqp", W, jac)
        pred, dp, dn = _model(vals, jst, nuis, None, None, keys)
        r, Jp, Jn = [], [], []
        for k in keys:
            s = S[k]
            scale = np.where(np.isfinite(s) & (s > 0), s, _robust_scale(M[k] - pred[k]))
            r.append((M[k] - pred[k]) / scale)
            Jp.append(dp[k] / scale[:, None])
            Jn.append(dn[k] / scale[:, None])
        return np.concatenate(r), np.vstack(Jp), np.vstack(Jn)

    lam = 1e-3
    npar = len(names)
    r, Jp, Jn = residuals(x, nuis)
    chi2 = float(r @ r)
    it = 0
    for it in range(1, max_iter + 1):
        J = np.hstack([Jp, Jn])
        A = J.T @ J
        g = J.T @ r
        D = np.diag(np.where(np.diag(A) > 0, np.diag(A), 1.0))
        accepted = False
        for _ in range(8):
            try:
                step = np.linalg.solve(A + lam * D, g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            x_new = x + step[:npar]
            n_new = nuis + step[npar:]
            n_new[4] = max(n_new[4], 0.0)
            x_new = _clip_to_bounds(names, x_new)
            r_new, Jp_new, Jn_new = residuals(x_new, n_new)
            chi2_new = float(r_new @ r_new)
            if chi2_new <= chi2:
                small = np.all(np.abs(step) <= 1e-4 * (np.abs(np.concatenate([x[:npar], nuis])) + 1e-9)) or \
                    chi2 - chi2_new < 1e-6 * max(chi2, 1e-30)
                x, nuis, r, Jp, Jn, chi2 = x_new, n_new, r_new, Jp_new, Jn_new, chi2_new
                lam = max(lam / 10, 1e-9)
                accepted = True
                break
            lam *= 10
        if not accepted or small:
            break
    J = np.hstack([Jp, Jn])
    dof = max(len(r) - J.shape[1], 1)
    fisher = J.T @ J
    cov = np.linalg.pinv(fisher)
    if sigma is None or any(k not in sigma for k in keys):
        cov = cov * max(chi2 / dof, 1e-30)
    errs = np.sqrt(np.clip(np.diag(cov)[:len(names)], 0, None))
    expl = {n: explain(n, v, e) for n, v, e in zip(names, x, errs)}
    z = np.abs(x) / np.where(errs > 0, errs, np.inf)
    top = int(np.argmax(z)) if len(z) else None
    if top is None or z[top] < 3.0:
        summary = "no significant misalignment: every fitted perturbation is within 3 sigma of zero"
    else:
        summary = explain(names[top], x[top], errs[top], tr, F, kw) if explain_top else expl[names[top]]
    k_rest = len(names) + NUISANCES.index("extra_moment_mm2")
    d = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    rest_corr = cov[:len(names), k_rest] / (d[:len(names)] * d[k_rest]) if cov.shape[0] > k_rest else None
    return AlignmentFit(names, x, errs, cov[:len(names), :len(names)],
                        dict(zip(NUISANCES, map(float, nuis))), chi2, dof, it, time.perf_counter() - t0,
                        summary, expl, F, n_stars, rest_corr)


def _robust_scale(res):
    """The residuals' scale when no errors are given: 1.4826 MAD, floored (a perfect model must not
    divide by zero)."""
    mad = 1.4826 * np.median(np.abs(res - np.median(res)))
    rms = math.sqrt(np.mean(res ** 2)) if len(res) else 0.0
    return np.full(len(res), max(mad, 1e-3 * rms, 1e-12))


def _initial_extra_moment(M):
    if "muu_mm2" in M and "mvv_mm2" in M:
        return float(max(0.5 * np.min(M["muu_mm2"] + M["mvv_mm2"]) * 0.5, 0.0))
    return 0.0


_BOUNDS = {"_deg": 2.0, "_um": 5000.0, "_mm": 10.0}


def _clip_to_bounds(names, x):
    lim = np.array([next(v for k, v in _BOUNDS.items() if n.endswith(k)) for n in names])
    return np.clip(x, -lim, lim)


# ---- optical words -------------------------------------------------------------------------------------
_EDGE = {(1, 0): "right (+x) edge", (-1, 0): "left (-x) edge", (0, 1): "top (+y) edge", (0, -1): "bottom (-y) edge"}


def _pattern(name, value, tracer, fields, kw):
    """How this perturbation at ``value`` changes the RMS spot [mm] at the field's centre and at the middle
    of each edge (a 3 x 3 grid over ``fields``' extent): ``{"centre": d, "right (+x) edge": d, ...}``."""
    from pydantic import ValidationError

    try:
        pert = with_perturbation(tracer.design, **{name: float(value)})
    except ValidationError:          # beyond the table's bounds: no pattern to describe
        return None
    lo, hi = fields.min(0), fields.max(0)
    mid = 0.5 * (lo + hi)
    pts = np.array([mid, [lo[0], mid[1]], [hi[0], mid[1]], [mid[0], lo[1]], [mid[0], hi[1]]])
    base = spot_moments(tracer, pts, **kw)
    moved = spot_moments(SequentialTracer(pert, tracer.mi), pts, **kw)
    d = moved.get("rms_mm") - base.get("rms_mm")
    out = {"centre": float(d[0])}
    for k in range(1, 5):
        # the image of field (theta_x, theta_y) lies at -f tan(theta): name the sensor edge by its image
        u, v = base.get("cu_mm")[k] - base.get("cu_mm")[0], base.get("cv_mm")[k] - base.get("cv_mm")[0]
        edge = _EDGE[(int(np.sign(u)), 0)] if abs(u) > abs(v) else _EDGE[(0, int(np.sign(v)))]
        out[edge] = float(d[k])
    return out


def _pattern_words(pat) -> str:
    if pat is None:
        return ""
    centre = pat["centre"]
    edges = {k: v for k, v in pat.items() if k != "centre"}
    top = max(edges, key=edges.get)
    if edges[top] <= 0 and centre <= 0:
        return "the spots shrink (the perturbation compensates another)"
    grow = [k for k, v in edges.items() if v > 0.5 * edges[top] and v > 1.3 * max(centre, 0)]
    if centre > 0.6 * edges[top]:
        return f"over the whole field, most at the {top}"
    if len(grow) >= 2:
        return "growing towards the " + " and ".join(e.replace(" edge", "") for e in grow) + " edges"
    return f"growing towards the {top}"


def explain(name: str, value: float, error: float, tracer=None, fields=None, kw=None) -> str:
    """One line in optical words for a fitted perturbation ``value`` +- ``error`` (units of ``name``)."""
    mag = abs(value)
    pm = f"{mag:.3g} +- {error:.2g}"
    part = name.split("_")[0]
    growth = _pattern_words(_pattern(name, value, tracer, fields, kw or {})) \
        if tracer is not None and fields is not None else ""
    if name == "sensor_piston_um":
        where = "beyond focus (too far from the mirror)" if value > 0 else "inside focus (too close to the mirror)"
        return f"sensor {pm} um {where}: defocus blur {growth or 'over the whole field'}"
    if name.startswith("sensor_tilt"):
        axis = name[-5]
        return (f"sensor tilted {value:+.3g} +- {error:.2g} deg about its {axis} axis: focus varies across the field, blur "
                f"{growth or 'towards opposite edges'}")
    if name.endswith("_deg"):
        axis = name[-5]
        what = {"primary": "primary mirror", "diagonal": "diagonal", "corrector": "corrector"}[part]
        kind = "coma" if part in ("primary", "diagonal") else "coma and astigmatism"
        return f"{what} tilted {value:+.3g} +- {error:.2g} deg about {axis}: {kind} {growth or 'over the field'}"
    if "decenter" in name:
        axis = name.split("_")[-2]
        what = {"primary": "primary mirror", "corrector": "corrector"}.get(part, part)
        return f"{what} decentred {value:+.3g} +- {error:.2g} mm along {axis}: coma {growth or 'over the field'}"
    if name == "corrector_spacing_mm":
        way = "too far from" if value > 0 else "too close to"
        return f"corrector {pm} mm {way} the sensor: field-dependent blur (spacing error) {growth}".rstrip()
    return f"{name} = {value:.3g} +- {error:.2g}"


# ---- which perturbation? -------------------------------------------------------------------------------
@dataclass
class Candidate:
    """One family's fit in :func:`rank_perturbations`."""

    family: str
    fit: AlignmentFit
    delta_chi2: float       # chi^2(no perturbation) - chi^2(this family)
    p_value: float          # of delta_chi2 under "no perturbation" (chi^2 with len(params) dof)

    def to_json(self) -> dict:
        return {"family": self.family, "delta_chi2": self.delta_chi2, "p_value": self.p_value,
                **self.fit.to_json()}


def rank_perturbations(design: Design, mi, fields_deg, measured: dict, sigma: dict | None = None, *,
                       families=None, significance: float = 1e-4, **kw) -> tuple[list, AlignmentFit]:
    """Fit each family of perturbations alone (:data:`FAMILIES`; the corrector's only for a design with
    one) and rank them by the chi^2 they remove: ``(candidates best first, the fit with no perturbation)``.

    A family whose chi^2 drop has a p-value below ``significance`` (chi^2 distribution with as many degrees
    of freedom as the family has parameters, Wilks 1938, doi:10.1214/aoms/1177732360) is a detection; with
    ``sigma=None`` the chi^2 are in units of the no-perturbation fit's residual variance. Keyword
    arguments go to :func:`fit_perturbations` (``nodes``, ``n_rays``, ``wavelengths_nm``, ...)."""
    from scipy.stats import chi2 as chi2_dist

    fams = families or [f for f in FAMILIES if design.corrector.enabled or not f.startswith("corrector")]
    tracer = kw.pop("tracer", None) or SequentialTracer(design, mi)
    base = fit_perturbations(design, mi, fields_deg, measured, sigma, params=(), tracer=tracer,
                             explain_top=False, **kw)
    scale = 1.0 if sigma is not None else max(base.chi2 / base.dof, 1e-30)
    out = []
    for fam in fams:
        fit = fit_perturbations(design, mi, fields_deg, measured, sigma, params=FAMILIES[fam], tracer=tracer,
                                explain_top=False, **kw)
        dchi = (base.chi2 - fit.chi2) / scale
        out.append(Candidate(fam, fit, float(dchi), float(chi2_dist.sf(max(dchi, 0.0), len(FAMILIES[fam])))))
    out.sort(key=lambda c: -c.delta_chi2)
    if out and out[0].p_value < significance:
        top = out[0].fit
        i = int(np.argmax(top.significance))
        top.explanation = explain(top.names[i], top.values[i], top.errors[i], tracer, top.fields_deg,
                                  {"n_rays": kw.get("n_rays", 1500), "wavelengths_nm": kw.get("wavelengths_nm", (550.0,)),
                                   "weights": kw.get("weights")})
    return out, base
