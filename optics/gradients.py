"""Derivatives of the spot's moments and the throughput by automatic differentiation of the trace (drjit).

For stars at a set of field points, :func:`spot_moments` traces one stratified pupil bundle per field and
wavelength through :class:`optics.sequential.SequentialTracer` and returns, per field point,

    cu, cv      centroid [mm] (focal-plane u, v of :mod:`optics.layout`)
    muu, mvv, muv  second central moments [mm^2]
    rms         RMS spot radius sqrt(muu + mvv) [mm]
    throughput  fraction of the entrance bundle (the primary's clear aperture) reaching the sensor, times
                the corrector's surface transmittance [1]

each ray weighted by its transmittance, the wavelength's weight and, for the optical apertures (primary
rim, diagonal outline, lens rims, sensor edges), a soft edge: the logistic function 1 / (1 + exp(-m / eps))
of the ray's margin m [mm] inside the edge (``soft_eps_mm``). The soft edges make the throughput and the
moments differentiable in the perturbations (a hard edge has a zero derivative almost everywhere and a
jump where a ray crosses it); for an edge that is straight on the scale of eps and a uniform ray density
the smoothing has no first-order bias. The mechanical obstructions (spider, vanes, focuser bore) stay
hard: they do not move with the optics.

Jacobian in one pass (forward mode, "replicated tangents"): the bundle is replicated once per parameter,
every parameter is a drjit array over all rays carrying the tangent 1 on its own replica and 0 elsewhere,
and a single forward traversal gives d(moments)/d(parameter k) on replica k (drjit's AD, Jakob et al.
2022, "Dr.Jit: A Just-In-Time Compiler for Differentiable Rendering", doi:10.1145/3528223.3530099).

Parameters (``wrt``): every name of :data:`optics.design.PERTURBATION_NAMES` and the design parameters
``primary.conic``, ``corrector.back_focus_mm``, ``corrector.surfaces.N.radius_mm`` and
``corrector.surfaces.N.thickness_mm`` (N from 0; plane surfaces stay plane). Angles in degrees, lengths in
mm, ``sensor_piston_um`` in um: the Jacobian is in those units.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .design import PERTURBATION_NAMES, Design
from .sequential import SequentialTracer, _design_parameter

MOMENT_NAMES = ("cu_mm", "cv_mm", "muu_mm2", "mvv_mm2", "muv_mm2", "rms_mm", "throughput")
SOFT_EPS_MM = 1.0


@dataclass
class SpotMoments:
    """Moments per field point and, when asked, their Jacobian."""

    fields_deg: np.ndarray          # (n_fields, 2)
    values: np.ndarray              # (n_fields, 7) in the order of MOMENT_NAMES
    wrt: tuple                      # parameter names of the Jacobian's last axis
    jacobian: np.ndarray | None     # (n_fields, 7, n_wrt)
    at: dict                        # parameter values the moments were evaluated at

    def get(self, name: str) -> np.ndarray:
        return self.values[:, MOMENT_NAMES.index(name)]

    def to_json(self) -> dict:
        out = {"fields_deg": self.fields_deg.tolist(), "moments": list(MOMENT_NAMES),
               "values": self.values.tolist(), "wrt": list(self.wrt), "at": self.at}
        if self.jacobian is not None:
            out["jacobian"] = self.jacobian.tolist()
        return out


def parameter_value(design: Design, name: str) -> float:
    """Current value of a perturbation or design parameter of ``design`` (units of its name)."""
    if name in PERTURBATION_NAMES:
        return float(getattr(design.perturbation, name))
    if not _design_parameter(name):
        raise ValueError(f"unknown parameter {name!r}")
    obj = design
    for part in name.split("."):
        obj = obj[int(part)] if part.isdigit() else getattr(obj, part)
    return float(obj)


def spot_moments(tracer: SequentialTracer, fields_deg, wrt=(), *, at: dict | None = None, n_rays: int = 2000,
                 wavelengths_nm=(550.0,), weights=None, soft_eps_mm: float = SOFT_EPS_MM,
                 seed: int = 0) -> SpotMoments:
    """Spot moments at ``fields_deg`` ((n, 2) field angles [deg]) and their Jacobian with respect to the
    parameters ``wrt`` (module docstring), evaluated at the design's values overridden by ``at``.

    The same pupil points (``n_rays``, R2 sequence of ``seed``) serve every field, wavelength and
    parameter value: finite differences and fits see no sampling noise."""
    import drjit as dr
    from drjit.llvm.ad import Array3f64, Float64, UInt32

    fields = np.atleast_2d(np.asarray(fields_deg, dtype=float))
    nf = len(fields)
    wrt = tuple(wrt)
    at = dict(at or {})
    for k in (*wrt, *at):
        parameter_value(tracer.design, k)          # validates the name
    lam = np.atleast_1d(np.asarray(wavelengths_nm, dtype=float))
    wl = np.ones_like(lam) if weights is None else np.asarray(weights, dtype=float)
    wl = wl / wl.sum()
    n_rep = max(1, len(wrt))
    n_p = int(n_rays)
    n_tot = n_rep * nf * n_p
    # every per-ray input is computed inside the kernel from the ray index (see sequential.to_dr): the
    # pupil point (the R2 sequence of sequential.pupil_uniform), the field (gathered from nf values) and
    # the replica; the kernel is then the same from call to call and compiles once.
    idx = dr.arange(UInt32, n_tot)
    kk = Float64(idx % n_p)
    fi = (idx // n_p) % nf
    rep = idx // (nf * n_p)
    g = 1.32471795724474602596
    shift = np.random.default_rng(seed).random(2)
    a1 = dr.opaque(Float64, shift[0]) + kk * (1.0 / g)
    a2 = dr.opaque(Float64, shift[1]) + kk * (1.0 / g ** 2)
    a1, a2 = a1 - dr.floor(a1), a2 - dr.floor(a2)
    rad = tracer.layout.r_primary * dr.sqrt(a1)
    px, py = rad * dr.cos(2 * math.pi * a2), rad * dr.sin(2 * math.pi * a2)
    t = np.tan(np.radians(fields))
    dn = -np.stack([t[:, 0], t[:, 1], np.ones(nf)], -1)
    dn /= np.linalg.norm(dn, axis=1, keepdims=True)
    dirs = Array3f64(*[dr.gather(Float64, Float64(dn[:, i]), fi) for i in range(3)])
    # reference point per field (the ideal image -f tan(theta)) keeps the sums well conditioned
    f = tracer.layout.focal_length
    ref = -f * t
    ref_u = dr.gather(Float64, Float64(ref[:, 0]), fi)
    ref_v = dr.gather(Float64, Float64(ref[:, 1]), fi)

    params = {}
    for k in wrt:
        v = at.get(k, parameter_value(tracer.design, k))
        p = dr.opaque(Float64, v, n_tot)
        dr.enable_grad(p)
        params[k] = p
    for k, v in at.items():
        if k not in params:
            params[k] = dr.opaque(Float64, float(v))

    seeds = {name: dr.select(rep == k, 1.0, 0.0) for k, name in enumerate(wrt)}
    S = np.zeros((6, n_rep, nf))
    dS = np.zeros((6, n_rep, nf))
    for lam_k, w_k in zip(lam, wl):
        res = tracer._trace_dr(dirs, px, py, float(lam_k), params=params, soft_eps=soft_eps_mm)
        ok = res["lost"] == 0
        w = dr.select(ok, res["transmission"] * res["soft"], 0.0)
        u = dr.select(ok, res["u"] - ref_u, 0.0)
        v = dr.select(ok, res["v"] - ref_v, 0.0)
        terms = [w, w * u, w * v, w * u * u, w * v * v, w * u * v]
        grads = []
        if wrt:
            for name in wrt:
                dr.set_grad(params[name], seeds[name])
            dr.enqueue(dr.ADMode.Forward, *[params[n] for n in wrt])
            # keep the interior nodes' tangents (w is one: it feeds w u), drop the graph afterwards
            dr.traverse(dr.ADMode.Forward, flags=dr.ADFlag.ClearEdges | dr.ADFlag.ClearInput)
            grads = [dr.grad(t) for t in terms]
        dr.eval(*terms, *grads)              # one kernel: the trace, its tangents and the six per-ray terms
        # the block sums and the moment algebra are small: numpy (forward mode by hand, linear in the sums)
        S += w_k * np.stack([np.asarray(t.numpy()).reshape(n_rep, nf, n_p).sum(-1) for t in terms])
        if wrt:
            dS += w_k * np.stack([np.asarray(g.numpy()).reshape(n_rep, nf, n_p).sum(-1) for g in grads])
    s0, su, sv, suu, svv, suv = S
    d0, du, dv, duu, dvv, duv = dS
    cu, cv = su / s0, sv / s0
    muu = suu / s0 - cu * cu
    mvv = svv / s0 - cv * cv
    muv = suv / s0 - cu * cv
    rms = np.sqrt(muu + mvv)
    thr = s0 / n_p
    vals_rep = np.stack([cu, cv, muu, mvv, muv, rms, thr], -1)            # (rep, field, 7)
    jac = None
    if wrt:
        dcu = (du - cu * d0) / s0
        dcv = (dv - cv * d0) / s0
        dmuu = (duu - suu / s0 * d0) / s0 - 2 * cu * dcu
        dmvv = (dvv - svv / s0 * d0) / s0 - 2 * cv * dcv
        dmuv = (duv - suv / s0 * d0) / s0 - cu * dcv - cv * dcu
        drms = (dmuu + dmvv) / (2 * rms)
        G = np.stack([dcu, dcv, dmuu, dmvv, dmuv, drms, d0 / n_p], -1)    # (rep, field, 7)
        jac = np.transpose(G[:len(wrt)], (1, 2, 0)).copy()                 # (field, 7, wrt)
    vals = vals_rep[0].copy()
    vals[:, 0] += ref[:, 0]
    vals[:, 1] += ref[:, 1]
    used = {k: float(at.get(k, parameter_value(tracer.design, k))) for k in (*wrt, *at)}
    return SpotMoments(fields, vals, wrt, jac, used)


def finite_difference_jacobian(tracer: SequentialTracer, fields_deg, wrt, steps: dict, **kwargs) -> np.ndarray:
    """Central finite differences (f(x + h) - f(x - h)) / 2h of :func:`spot_moments`' values, the
    independent check of the AD Jacobian (same pupil points, so no sampling noise). ``steps``: h per name."""
    at = dict(kwargs.pop("at", None) or {})
    cols = []
    for name in wrt:
        x0 = at.get(name, parameter_value(tracer.design, name))
        h = steps[name]
        plus = spot_moments(tracer, fields_deg, at={**at, name: x0 + h}, **kwargs).values
        minus = spot_moments(tracer, fields_deg, at={**at, name: x0 - h}, **kwargs).values
        cols.append((plus - minus) / (2 * h))
    return np.stack(cols, -1)


def detector_field_points(design: Design, n: int = 3, fill: float = 0.9) -> np.ndarray:
    """An n x n grid of field angles [deg] covering ``fill`` of the sensor (images at -f tan(theta))."""
    f = design.primary.focal_length_mm
    hu, hv = design.focal_plane.width_mm / 2 * fill, design.focal_plane.height_mm / 2 * fill
    us = np.linspace(-hu, hu, n) if n > 1 else np.zeros(1)
    vs = np.linspace(-hv, hv, n) if n > 1 else np.zeros(1)
    U, V = np.meshgrid(us, vs, indexing="xy")
    return np.degrees(np.arctan(-np.stack([U.ravel(), V.ravel()], -1) / f))


def perturbation_names(design: Design) -> tuple:
    """The perturbations that apply to ``design`` (the corrector's only when it has one)."""
    return tuple(n for n in PERTURBATION_NAMES if design.corrector.enabled or not n.startswith("corrector_"))


def default_steps(names, design: Design | None = None) -> dict:
    """Central-difference steps small enough that the truncation error stays below 1e-3 of the soft-edged
    moments' derivatives (they curve on the scale of ``SOFT_EPS_MM``): 1e-5 deg, 1e-4 mm, 1e-2 um, and
    1e-6 relative (1e-6 absolute for the conic) for design parameters (needs ``design``)."""
    out = {}
    for n in names:
        if n.endswith("_deg"):
            out[n] = 1e-5
        elif n.endswith("_um"):
            out[n] = 1e-2
        elif n in PERTURBATION_NAMES:
            out[n] = 1e-4
        elif n == "primary.conic":
            out[n] = 1e-6
        else:
            out[n] = 1e-6 * abs(parameter_value(design, n)) if design is not None else 1e-4
    return out
