"""Sequential ray tracing of the Newtonian (primary -> diagonal -> corrector -> detector) in drjit.

The mirrors and lenses are intersected analytically (conic primary, plane diagonal with its elliptical
outline, spherical lens surfaces) in double precision: exact surfaces, exact normals, and optical path
lengths good to far below a wavelength over the 2 m path (float32 would round them to 0.1 um). The
mechanical obstructions (tube front, annular vanes, spider slabs, the diagonal's body, focuser tube,
camera housing) are exact solids intersected as intervals along each ray (``obstruct="analytic"``, the
fast default), or Mitsuba's BVH of the same parts as meshes (``obstruct="mesh"``: any geometry, used to
cross-check the analytic solids). Everything for one batch fuses into one LLVM kernel.

Refraction: vector Snell's law, the same relations as Mitsuba's ``dielectric`` plugin
(``mi.fresnel``/``mi.refract``; Born & Wolf, Principles of Optics, 1.5). Each glass-air surface
transmits T = 1 - R_AR of its anti-reflection coating (``[corrector] ar_reflectance``, default 0.5 %),
or, for ``ar_reflectance = "uncoated"`` and at cemented glass-glass surfaces, the unpolarised Fresnel
transmittance T = 1 - (r_s^2 + r_p^2) / 2. The glass indices enter the kernel as opaque values, so one
compiled kernel serves every wavelength (and every field angle).

Precision. Positions, directions and optical paths (:meth:`SequentialTracer.trace`, the PSF, the spot
diagrams, gradients) are float64 throughout. Counting where rays are lost (:meth:`SequentialTracer.loss_counts`
with ``single=True``, the vignetting map's path) may run the same kernel in float32: 16 rays per AVX-512
instruction instead of 8. Its positions agree with float64 to 0.3 um on the detector (ART and bare designs,
0-1.5 deg), far inside a pixel; a ray changes fate only where it passes within ~0.1 um of an edge, a few rays
per million (tests/optics/test_vignetting.py: a map agrees with the float64 code's to 5 rays in 200 000 per
field, 0.02 of its binomial error).

Frame and focal-plane coordinates: see :mod:`optics.layout`.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from .design import PERTURBATION_NAMES, Design
from .layout import Layout, make_layout

# where a ray was lost (0 = reached the detector)
OK, ENTRANCE, PRIMARY_MISS, TO_DIAGONAL, DIAGONAL_MISS, FOCUSER, LENS, DETECTOR_MISS = range(8)
LOSS_NAMES = {OK: "detector", ENTRANCE: "blocked before the primary (tube front, vanes, spider, diagonal)",
              PRIMARY_MISS: "outside the primary", TO_DIAGONAL: "blocked between primary and diagonal",
              DIAGONAL_MISS: "missed the diagonal", FOCUSER: "blocked in the focuser or housing",
              LENS: "outside a corrector lens or totally reflected", DETECTOR_MISS: "outside the detector"}
BATCH = 1 << 21
SQRT2 = math.sqrt(2.0)


def _design_parameter(name: str) -> bool:
    """Design parameters the kernel can take as drjit values (for gradients)."""
    parts = name.split(".")
    return name in ("primary.conic", "corrector.back_focus_mm") or (
        len(parts) == 4 and parts[:2] == ["corrector", "surfaces"] and parts[2].isdigit()
        and parts[3] in ("radius_mm", "thickness_mm"))


class _Pose:
    """Rigid placement of a part: local -> world is p -> pivot + shift + R (p - pivot), R = R1 R2 with
    R_k the right-handed rotation by angle_k [deg] about the unit axis_k (Rodrigues' formula), the shift
    a sum of (unit axis, length [mm]) terms. Angles and lengths are drjit values (possibly with
    gradients) or None (left out)."""

    def __init__(self, pivot, rots, shifts):
        self.pivot, self.rots, self.shifts = pivot, rots, shifts

    @classmethod
    def make(cls, pivot, rots, shifts):
        rots = [(a, ang) for a, ang in rots if ang is not None]
        shifts = [(a, s) for a, s in shifts if s is not None]
        return cls(pivot, rots, shifts) if rots or shifts else None

    @staticmethod
    def _rot(v, axis, ang_deg, sign):
        import drjit as dr

        a = ang_deg * (sign * math.pi / 180.0)
        co, si = dr.cos(a), dr.sin(a)
        k = type(v)(*axis)
        return v * co + dr.cross(k, v) * si + k * (dr.dot(k, v) * (1.0 - co))

    def to_world_dir(self, v):
        for axis, ang in reversed(self.rots):
            v = self._rot(v, axis, ang, 1.0)
        return v

    def to_local_dir(self, v):
        for axis, ang in self.rots:
            v = self._rot(v, axis, ang, -1.0)
        return v

    def _offset(self, A3):
        off = A3(*self.pivot)
        for axis, s in self.shifts:
            off = off + A3(*axis) * s
        return off

    def to_world(self, p):
        A3 = type(p)
        return self._offset(A3) + self.to_world_dir(p - A3(*self.pivot))

    def to_local(self, p):
        A3 = type(p)
        return A3(*self.pivot) + self.to_local_dir(p - self._offset(A3))


@dataclass
class TraceResult:
    """Per-ray results (numpy). Positions in mm in the focal-plane frame of :mod:`optics.layout`."""

    px: np.ndarray          # pupil coordinates in the primary's rim plane [mm]
    py: np.ndarray
    u: np.ndarray           # detector-plane position [mm]
    v: np.ndarray
    du: np.ndarray          # direction cosines at the detector (w along the beam)
    dv: np.ndarray
    dw: np.ndarray
    opl: np.ndarray         # optical path length from the plane wave through the origin [mm]
    transmission: np.ndarray  # transmittance of the corrector surfaces (AR coating or Fresnel) [1]
    lost: np.ndarray        # uint8 loss code (0 = reached the detector)

    @property
    def ok(self) -> np.ndarray:
        return self.lost == OK


def direction(field_deg) -> np.ndarray:
    """Propagation direction of light from a star at field angles (theta_x, theta_y) [deg]."""
    tx, ty = (math.tan(math.radians(a)) for a in field_deg)
    d = -np.array([tx, ty, 1.0])
    return d / np.linalg.norm(d)


def pupil_grid(n: int, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Square grid of n x n points over [-radius, radius]^2 (cell centres), all kept."""
    c = (np.arange(n) + 0.5) / n * 2 - 1
    X, Y = np.meshgrid(c * radius, c * radius, indexing="xy")
    return X.ravel(), Y.ravel()


def pupil_uniform(n: int, radius: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``n`` stratified points uniform over the disk of ``radius``: the R2 low-discrepancy sequence
    (Roberts 2018) with a seeded Cranley-Patterson shift, mapped to the disk by r = R sqrt(u)."""
    g = 1.32471795724474602596
    k = np.arange(n, dtype=np.float64)
    shift = np.random.default_rng(seed).random(2)
    u = (shift[0] + k / g) % 1.0
    w = (shift[1] + k / g ** 2) % 1.0
    r = radius * np.sqrt(u)
    return r * np.cos(2 * np.pi * w), r * np.sin(2 * np.pi * w)


def pupil_uniform_dr(n: int, radius: float, seed: int = 0, single: bool = False, start: int = 0):
    """:func:`pupil_uniform` computed by drjit, points ``start`` .. ``start + n - 1`` of the sequence, as
    evaluated drjit arrays (float32 when ``single``): no numpy arrays and no transfer. The sequence's
    fractions and the radius are the same float64 operations as numpy's (correctly rounded division,
    square root, exact x - floor(x)), so they agree bit for bit; the angle's cosine and sine are drjit's,
    within 1 ulp of numpy's (float64), which rounding to float32 hides almost always (tests/optics/
    test_sequential.py: within 2e-13 mm in float64)."""
    import drjit as dr
    from drjit.llvm.ad import Float64, UInt32

    g = dr.opaque(Float64, 1.32471795724474602596)      # opaque: a true division, as numpy's k / g
    shift = np.random.default_rng(seed).random(2)
    k = Float64(dr.arange(UInt32, n)) + float(start) if start else Float64(dr.arange(UInt32, n))
    a = dr.opaque(Float64, shift[0]) + k / g
    b = dr.opaque(Float64, shift[1]) + k / (g * g)
    u = a - dr.floor(a)
    w = b - dr.floor(b)
    r = radius * dr.sqrt(u)
    s, c = dr.sincos((2 * np.pi) * w)
    x, y = r * c, r * s
    if single:
        from drjit.llvm.ad import Float

        x, y = Float(x), Float(y)
    dr.eval(x, y)
    return x, y


class SequentialTracer:
    """Trace ray bundles through a :class:`Design`.

    Parameters
    ----------
    design : Design
    mi : module
        Mitsuba with an llvm variant set (``optics.llvm.init_mitsuba``); drjit carries the rays.
    obstruct : {"analytic", "mesh", "none"}
        How mechanical obstructions are tested (module docstring).
    """

    def __init__(self, design: Design, mi, obstruct: str = "analytic"):
        if obstruct not in ("analytic", "mesh", "none"):
            raise ValueError(f"obstruct must be 'analytic', 'mesh' or 'none', not {obstruct!r}")
        self.design = design
        self.layout: Layout = make_layout(design)
        self.mi = mi
        self.obstruct = obstruct
        self._scene = None
        if obstruct == "mesh":
            from .meshes import telescope_parts
            from .mitsuba_scene import build_scene

            self._scene = build_scene(mi, telescope_parts(self.layout, optics_surfaces=False))

    # ------------------------------------------------------------------------------------------------
    def trace(self, field_deg, px, py, wavelength_nm: float = 550.0) -> TraceResult:
        """Trace rays through pupil points (``px``, ``py``) [mm] of the primary's rim plane from a star at
        ``field_deg`` = (theta_x, theta_y) [deg], in batches of 2**21 rays."""
        px = np.asarray(px, dtype=np.float64).ravel()
        py = np.asarray(py, dtype=np.float64).ravel()
        parts = [self._trace_batch(field_deg, px[i:i + BATCH], py[i:i + BATCH], wavelength_nm)
                 for i in range(0, len(px), BATCH)] or [self._trace_batch(field_deg, px, py, wavelength_nm)]
        out = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
        return TraceResult(px=px, py=py, **out)

    def paths(self, field_deg, px, py, wavelength_nm: float = 550.0) -> tuple[np.ndarray, np.ndarray]:
        """Every ray's vertices for drawing: ``(points[n_rays, n_vertices, 3], lost[n_rays])`` from the
        entrance through the primary, the diagonal and each lens to the detector plane [mm]."""
        import drjit as dr

        res = self._trace_dr(field_deg, np.asarray(px, float).ravel(), np.asarray(py, float).ravel(),
                             wavelength_nm, keep_path=True)
        dr.eval(res)
        nv = sum(1 for k in res if k.startswith("path") and k.endswith("_x"))
        n = len(np.asarray(px).ravel())
        pts = np.stack([np.stack([np.broadcast_to(np.asarray(res[f"path{k}_{c}"].numpy()), (n,)) for c in "xyz"], -1)
                        for k in range(nv)], 1)
        return pts, np.asarray(res["lost"].numpy()).astype(np.uint8)

    def count(self, field_deg, px, py, wavelength_nm: float = 550.0) -> int:
        """Number of rays that reach the detector (no per-ray transfer back to numpy)."""
        return int(self.loss_counts(field_deg, px, py, wavelength_nm)[OK])

    def loss_counts(self, field_deg, px, py, wavelength_nm: float = 550.0, single: bool = False) -> np.ndarray:
        """How many rays end with each loss code (index = code, 0 = reached the detector).

        ``px``, ``py``: numpy arrays (traced in batches of 2**21, copied to drjit batch by batch) or drjit
        arrays already in memory, e.g. from :func:`pupil_uniform_dr` (one kernel over all of them, no
        transfer: the vignetting map's path). ``single``: the kernel in float32 (module docstring,
        "Precision"); the drjit arrays must then be float32 too."""
        import drjit as dr
        from drjit.llvm.ad import UInt32

        total = np.zeros(len(LOSS_NAMES), dtype=np.int64)
        if _is_dr(px):
            res = self._trace_dr(field_deg, px, py, wavelength_nm, single=single)
            counts = dr.zeros(UInt32, len(LOSS_NAMES))
            dr.scatter_add(counts, UInt32(1), res["lost"])
            return total + np.asarray(counts.numpy(), dtype=np.int64)
        px = np.asarray(px, dtype=np.float64).ravel()
        py = np.asarray(py, dtype=np.float64).ravel()
        for i in range(0, len(px), BATCH):
            res = self._trace_dr(field_deg, px[i:i + BATCH], py[i:i + BATCH], wavelength_nm, single=single)
            counts = dr.zeros(UInt32, len(LOSS_NAMES))
            dr.scatter_add(counts, UInt32(1), res["lost"])
            total += np.asarray(counts.numpy(), dtype=np.int64)
        return total

    def loss_counts_fields(self, fields, px, py, wavelength_nm: float = 550.0, single: bool = False,
                           sync_every: int = 16, progress=None) -> np.ndarray:
        """:meth:`loss_counts` for many fields over the same pupil points (drjit arrays, e.g. from
        :func:`pupil_uniform_dr`): ``counts[k, code]``. One compiled kernel per field adds into one counter
        array (field k's eight counters at an opaque offset 8k: the same kernel for every field), and the
        kernels are queued without waiting for each other; the process waits for them every ``sync_every``
        fields (``progress(done)`` is then called) and once at the end."""
        import drjit as dr
        from drjit.llvm.ad import UInt32

        counts = dr.zeros(UInt32, len(LOSS_NAMES) * len(fields))
        for k, field in enumerate(fields):
            res = self._trace_dr(field, px, py, wavelength_nm, single=single)
            dr.scatter_add(counts, UInt32(1), res["lost"] + dr.opaque(UInt32, len(LOSS_NAMES) * k))
            dr.eval(counts)
            if (k + 1) % sync_every == 0 or k + 1 == len(fields):
                dr.sync_thread()
                if progress:
                    progress(k + 1)
        return np.asarray(counts.numpy(), dtype=np.int64).reshape(len(fields), len(LOSS_NAMES))

    def _trace_batch(self, field_deg, px, py, wavelength_nm):
        import drjit as dr

        res = self._trace_dr(field_deg, px, py, wavelength_nm)
        dr.eval(res)
        out = {k: np.asarray(v.numpy()) for k, v in res.items()}
        out["lost"] = out["lost"].astype(np.uint8)
        return out

    # ------------------------------------------------------------------------------------------------
    def _params(self, params, F=None):
        """Perturbations and design parameters that enter the kernel as drjit values.

        Returns ``(pert, dpar)``: ``pert`` maps :data:`optics.design.PERTURBATION_NAMES` to drjit Float64
        values (only the non-zero ones of the design, opaque, plus every entry of ``params``), ``dpar`` the
        design parameters of ``params`` (:data:`DESIGN_PARAMETERS`). Both empty for the nominal design:
        then the kernel is exactly the unperturbed one."""
        import drjit as dr
        from drjit.llvm.ad import Float64

        pert = {k: dr.opaque(F or Float64, v) for k, v in self.design.perturbation.model_dump().items() if v}
        dpar = {}
        for k, v in (params or {}).items():
            if k in PERTURBATION_NAMES:
                pert[k] = v
            elif _design_parameter(k):
                dpar[k] = v
            else:
                raise ValueError(f"unknown parameter {k!r}: a perturbation ({', '.join(PERTURBATION_NAMES)}) "
                                 "or a design parameter (primary.conic, corrector.back_focus_mm, "
                                 "corrector.surfaces.N.radius_mm, corrector.surfaces.N.thickness_mm)")
        return pert, dpar

    def _lens_geometry(self, dpar, pert):
        """Vertex x [mm] and radius [mm] of each corrector surface (floats, or drjit values when a design
        parameter or the corrector spacing is varied)."""
        L = self.layout
        c = self.design.corrector
        if not L.lenses:
            return []
        if not any(k.startswith("corrector.") for k in dpar) and "corrector_spacing_mm" not in pert:
            return [(s.x_mm, s.radius_mm) for s in L.lenses]
        n = len(c.surfaces)
        bf = dpar.get("corrector.back_focus_mm", c.back_focus_mm)
        if "corrector_spacing_mm" in pert:
            bf = bf + pert["corrector_spacing_mm"]
        th = [dpar.get(f"corrector.surfaces.{i}.thickness_mm", c.surfaces[i].thickness_mm) for i in range(n)]
        rad = [dpar.get(f"corrector.surfaces.{i}.radius_mm", c.surfaces[i].radius_mm) for i in range(n)]
        out = []
        x = L.x_detector - bf
        for i in range(n - 2, -1, -1):
            x = x - th[i]
        for i in range(n):
            out.append((x, rad[i]))
            x = x + th[i]
        return out

    def _trace_dr(self, field_deg, px, py, wavelength_nm, keep_path=False, params=None, soft_eps=None,
                  single=False):
        """The trace as drjit arrays.

        ``field_deg``: (theta_x, theta_y) for all rays, or an (n, 2) array, one field per ray.
        ``params``: drjit Float64 values (e.g. with gradients enabled) of perturbations and design
        parameters overriding the design's (:meth:`_params`). ``soft_eps`` [mm]: the optical apertures
        (primary rim, diagonal outline, lens rims, sensor edges) weight a ray by the logistic function of
        its margin inside the edge over ``soft_eps`` (key ``"soft"``) instead of stopping it, so that the
        throughput and the moments are differentiable in the perturbations; so do, with
        ``obstruct="analytic"``, the tube front, the vanes and the focuser bore on the way back from the
        primary and behind the diagonal (:meth:`_margin_tube_side`, :meth:`_margin_focuser`). The incoming
        bundle's obstructions do not move with the optics and stay hard. ``single``: the whole kernel in
        float32 (the counting path of :meth:`loss_counts`; module docstring, "Precision")."""
        import drjit as dr
        from drjit.llvm.ad import UInt32

        L = self.layout
        F, A3 = _types(single)
        pert, dpar = self._params(params, F)
        fd = None if _is_dr(field_deg) else np.asarray(field_deg, dtype=float)
        if fd is None:
            # drjit directions per ray (built inside the kernel by the caller, e.g. optics.gradients)
            d = field_deg
            fd = np.zeros((0, 2))
            dz_np = None
        elif fd.ndim == 1:
            d_np = direction(fd)
            # opaque: the field changes from call to call, the compiled kernel must not
            d = A3(*[dr.opaque(F, float(c)) for c in d_np])
            dz_np = d_np[2]
        else:
            t = np.tan(np.radians(fd))
            d_np = -np.stack([t[:, 0], t[:, 1], np.ones(len(t))], -1)
            d_np /= np.linalg.norm(d_np, axis=1, keepdims=True)
            d = A3(*[to_dr(d_np[:, i], single) for i in range(3)])
            dz_np = d_np[:, 2]
        z_rim = float(L.primary_sag(L.r_primary))
        # for leaving out parts no live ray can reach (:meth:`_blocked_tube_side`): a bound on the bundle's
        # slope, the same for every field the sensor sees (its corner's), so that one compiled kernel
        # serves them all; fields beyond it get every check
        nominal_primary = not any(k.startswith("primary") for k in [*pert, *dpar])
        beam_tan = None
        if nominal_primary and len(fd):
            field_tan = np.max(np.hypot(*np.tan(np.radians(fd.reshape(-1, 2))).T))
            sensor_tan = math.hypot(*L.detector_half) / L.focal_length * (1.0 + 1e-9)
            beam_tan = sensor_tan if field_tan <= sensor_tan else None
        px = px if _is_dr(px) else to_dr(px, single)
        py = py if _is_dr(py) else to_dr(py, single)
        p_rim = A3(px, py, F(z_rim))
        z_start = L.tube_top + 1.0
        if dz_np is None:
            s0 = (z_start - z_rim) / (-d.z)
        else:
            s0 = dr.opaque(F, (z_start - z_rim) / (-dz_np)) if fd.ndim == 1 else \
                to_dr((z_start - z_rim) / (-dz_np), single)
        o = p_rim - d * s0
        opl = dr.dot(o, d)                       # plane wave: zero on the plane through the origin
        n_rays = dr.width(px)
        lost = dr.zeros(UInt32, n_rays)
        trans = dr.full(F, 1.0, n_rays)
        soft = dr.full(F, 1.0, n_rays) if soft_eps else None

        def kill(mask, code):
            nonlocal lost
            lost = dr.select((lost == 0) & mask, UInt32(code), lost)

        def aperture(margin, code):
            """A ray ``margin`` [mm] inside an optical aperture's edge (negative: outside)."""
            nonlocal soft
            if soft_eps:
                soft = soft * (1.0 / (1.0 + dr.exp(-dr.clip(margin / soft_eps, -60.0, 60.0))))
            else:
                kill(margin < 0, code)

        # -- primary (conic: c(x^2+y^2) + (1+k)c z^2 - 2z = 0, c = 1/(2f)), in its own (perturbed) frame ----
        pose_p = _Pose.make((0.0, 0.0, 0.0),
                            [((1.0, 0.0, 0.0), pert.get("primary_tilt_x_deg")),
                             ((0.0, 1.0, 0.0), pert.get("primary_tilt_y_deg"))],
                            [((1.0, 0.0, 0.0), pert.get("primary_decenter_x_mm")),
                             ((0.0, 1.0, 0.0), pert.get("primary_decenter_y_mm"))])
        ol, dl = (pose_p.to_local(o), pose_p.to_local_dir(d)) if pose_p else (o, d)
        c = 1.0 / (2.0 * L.focal_length)
        k1 = 1.0 + dpar["primary.conic"] if "primary.conic" in dpar else 1.0 + L.conic
        A = c * (dl.x * dl.x + dl.y * dl.y + k1 * dl.z * dl.z)
        B = 2.0 * (c * (ol.x * dl.x + ol.y * dl.y + k1 * ol.z * dl.z) - dl.z)
        C = c * (ol.x * ol.x + ol.y * ol.y + k1 * ol.z * ol.z) - 2.0 * ol.z
        disc = B * B - 4.0 * A * C
        q = -0.5 * (B + dr.copysign(dr.sqrt(_max(disc, 0.0)), B))
        t1 = dr.select(dr.abs(A) > 1e-18, q / A, dr.inf)
        t2 = C / q
        big = 1e30
        t1 = dr.select(t1 > 1e-9, t1, big)
        t2 = dr.select(t2 > 1e-9, t2, big)
        t = _min(t1, t2)
        kill((disc < 0) | (t >= big), PRIMARY_MISS)
        p1l = ol + dl * t
        if soft_eps:
            aperture(L.r_primary - dr.sqrt(p1l.x * p1l.x + p1l.y * p1l.y), PRIMARY_MISS)
        else:
            kill(p1l.x * p1l.x + p1l.y * p1l.y > L.r_primary ** 2, PRIMARY_MISS)
        p1 = pose_p.to_world(p1l) if pose_p else p1l
        if self.obstruct == "analytic":
            kill(self._blocked_tube_side(o, d, t, beam_tan=beam_tan), ENTRANCE)
        elif self.obstruct == "mesh":
            kill(self._blocked_mesh(o, d, t), ENTRANCE)
        opl += t
        n = dr.normalize(A3(-c * p1l.x, -c * p1l.y, 1.0 - c * k1 * p1l.z))
        if pose_p:
            n = pose_p.to_world_dir(n)
        d1 = d - 2.0 * dr.dot(d, n) * n

        # -- diagonal (plane through its centre, elliptical outline), tilted about its axes ---------------
        cen = A3(*[F(v) for v in L.diag_centre])
        pose_d = _Pose.make(L.diag_centre,
                            [((1.0 / SQRT2, 0.0, 1.0 / SQRT2), pert.get("diagonal_tilt_x_deg")),
                             ((0.0, 1.0, 0.0), pert.get("diagonal_tilt_y_deg"))], [])
        nd = A3(*[F(v) for v in L.diag_normal])
        if pose_d:
            nd = pose_d.to_world_dir(nd)
        denom = dr.dot(d1, nd)
        t = dr.dot(cen - p1, nd) / denom
        kill((t <= 0) | (denom >= 0), DIAGONAL_MISS)
        p2 = p1 + d1 * t
        rel = pose_d.to_local(p2) - cen if pose_d else p2 - cen
        qa = (rel.x + rel.z) * (1.0 / math.sqrt(2.0))
        if soft_eps:
            # distance inside the ellipse, to first order: (1 - rho^2) b / 2
            aperture((1.0 - (qa / L.diag_a) ** 2 - (rel.y / L.diag_b) ** 2) * (0.5 * L.diag_b), DIAGONAL_MISS)
        else:
            kill((qa / L.diag_a) ** 2 + (rel.y / L.diag_b) ** 2 > 1.0, DIAGONAL_MISS)
        if self.obstruct == "analytic" and soft_eps:
            aperture(self._margin_tube_side(p1, d1, t), TO_DIAGONAL)
        elif self.obstruct == "analytic":
            z_max, x_max = self._return_leg_bounds(pert, nominal_primary)
            kill(self._blocked_tube_side(p1, d1, t, incoming=False, z_max=z_max, x_max=x_max), TO_DIAGONAL)
        elif self.obstruct == "mesh":
            kill(self._blocked_mesh(p1, d1, t), TO_DIAGONAL)
        opl += t
        d2 = d1 - 2.0 * dr.dot(d1, nd) * nd

        # -- corrector lenses on the focuser axis (y = 0, z = z_axis, direction +x), in the cell's frame -----
        geo = self._lens_geometry(dpar, pert)
        pose_c = None
        if geo:
            x_mid = 0.5 * (L.lenses[0].x_mm + L.lenses[-1].x_mm)
            pose_c = _Pose.make((x_mid, 0.0, L.z_axis),
                                [((0.0, 0.0, 1.0), pert.get("corrector_tilt_x_deg")),
                                 ((0.0, 1.0, 0.0), pert.get("corrector_tilt_y_deg"))],
                                [((0.0, 0.0, 1.0), pert.get("corrector_decenter_x_mm")),
                                 ((0.0, 1.0, 0.0), pert.get("corrector_decenter_y_mm"))])
        p, dcur = (pose_c.to_local(p2), pose_c.to_local_dir(d2)) if pose_c else (p2, d2)
        n_medium, n_medium_py = 1.0, 1.0
        chain = [p2]
        coat = self.design.corrector
        t_coated = 1.0 - coat.ar_reflectance if coat.coated else None
        for s, (x_s, r_s) in zip(L.lenses, geo):
            # opaque: a new wavelength changes the indices, not the compiled kernel
            n_after_py = float(_index(s.after, wavelength_nm))
            n_after = dr.opaque(F, n_after_py)
            # every way of being lost at this surface has the same code: one mask, one update of ``lost``
            if s.radius_mm == 0.0:
                t = (x_s - p.x) / dcur.x
                hit = p + dcur * t
                normal = A3(F(-1.0), F(0.0), F(0.0))
                lens_lost = t <= 0
            else:
                centre = A3(F(x_s + r_s), F(0.0), F(L.z_axis))
                oc = p - centre
                b = dr.dot(oc, dcur)
                cc = dr.dot(oc, oc) - r_s * r_s
                disc = b * b - cc
                t = -b - math.copysign(1.0, s.radius_mm) * dr.sqrt(_max(disc, 0.0))
                hit = p + dcur * t
                normal = (hit - centre) * (1.0 / r_s)
                lens_lost = (disc < 0) | (t <= 0)
            if soft_eps:
                aperture(s.semi_diameter_mm - dr.sqrt(hit.y * hit.y + (hit.z - L.z_axis) ** 2), LENS)
            else:
                lens_lost |= hit.y * hit.y + (hit.z - L.z_axis) ** 2 > s.semi_diameter_mm ** 2
            opl += n_medium * t
            # the ratio of indices as one opaque value: no division per ray
            dcur, tr, tir = _refract(dcur, normal, n_medium, n_after, dr.opaque(F, n_medium_py / n_after_py))
            kill(lens_lost | tir, LENS)
            coated = t_coated is not None and "air" in (s.before.lower(), s.after.lower())
            trans *= t_coated if coated else tr          # cemented glass-glass surfaces: Fresnel
            p, n_medium, n_medium_py = hit, n_after, n_after_py
            chain.append(pose_c.to_world(hit) if pose_c else hit)
        if pose_c:
            p, dcur = pose_c.to_world(p), pose_c.to_world_dir(dcur)
        # -- detector plane x = x_detector (+ piston), tilted about its centre ---------------------------
        x_det = L.x_detector
        if "sensor_piston_um" in pert:
            x_det = x_det + pert["sensor_piston_um"] * 1e-3
        pose_s = _Pose.make((L.x_detector, 0.0, L.z_axis),
                            [((0.0, 0.0, 1.0), pert.get("sensor_tilt_x_deg")),
                             ((0.0, 1.0, 0.0), pert.get("sensor_tilt_y_deg"))], [])
        if pose_s:
            ndet = pose_s.to_world_dir(A3(F(1.0), F(0.0), F(0.0)))
            centre = A3(x_det, F(0.0), F(L.z_axis))
            t = dr.dot(centre - p, ndet) / dr.dot(dcur, ndet)
        else:
            t = (x_det - p.x) / dcur.x
        kill(t <= 0, DETECTOR_MISS)
        p3 = p + dcur * t
        opl += n_medium * t
        chain.append(p3)
        if self.obstruct == "analytic" and soft_eps:
            aperture(self._margin_focuser(chain), FOCUSER)
        elif self.obstruct == "analytic":
            static = not (pose_c or pose_s or "sensor_piston_um" in pert) and all(
                isinstance(x, float) and isinstance(r, float) for x, r in geo)
            kill(self._blocked_focuser(chain, self._chain_x_bounds(pert) if static else None), FOCUSER)
        elif self.obstruct == "mesh":
            kill(self._blocked_mesh_chain(chain), FOCUSER)
        if pose_s:
            rel = pose_s.to_local(p3 - A3(x_det - L.x_detector, F(0.0), F(0.0)))
            u = rel.z - L.z_axis
            v = rel.y
            dloc = pose_s.to_local_dir(dcur)
            du, dv, dw = dloc.z, dloc.y, dloc.x
        else:
            u = p3.z - L.z_axis
            v = p3.y
            du, dv, dw = dcur.z, dcur.y, dcur.x
        hu, hv = L.detector_half
        if soft_eps:
            aperture(_min(hu - dr.abs(u), hv - dr.abs(v)), DETECTOR_MISS)
        else:
            kill((dr.abs(u) > hu) | (dr.abs(v) > hv), DETECTOR_MISS)
        out = {"u": u, "v": v, "du": du, "dv": dv, "dw": dw, "opl": opl,
               "transmission": trans, "lost": lost}
        if soft_eps:
            out["soft"] = soft
        if keep_path:
            for k, pt in enumerate([o, p1, *chain]):
                out[f"path{k}_x"], out[f"path{k}_y"], out[f"path{k}_z"] = pt.x, pt.y, pt.z
        return out

    # -- analytic obstructions ---------------------------------------------------------------------------
    def _return_leg_bounds(self, pert, nominal_primary: bool) -> tuple[float, float | None]:
        """Bounds [mm] on the height z and on x of every ray between the primary and the diagonal that is
        still alive there: its ends are on the primary (z <= rim sag + radius whatever the primary's tilt;
        |x| <= the rim radius for the unperturbed primary) and inside the diagonal's outline (z, x within
        centre + a / sqrt2, or + a when the diagonal is tilted); 1 mm of margin. The tube front, vanes and
        spider above the height, and the focuser bore beyond x, cannot stop such a ray: the kernel leaves
        them out, with the same loss codes and less work."""
        L = self.layout
        tilted = "diagonal_tilt_x_deg" in pert or "diagonal_tilt_y_deg" in pert
        half = L.diag_a if tilted else L.diag_a / SQRT2
        z_max = max(L.diag_centre[2] + half, float(L.primary_sag(L.r_primary)) + L.r_primary) + 1.0
        x_max = max(L.diag_centre[0] + half, L.r_primary) + 1.0 if nominal_primary else None
        return z_max, x_max

    def _blocked_tube_side(self, o, d, t_end, incoming: bool = True, z_max: float | None = None,
                           x_max: float | None = None, beam_tan: float | None = None):
        """Mechanical parts inside the tube along a straight piece of ray: the tube front and the annular
        vanes (the ray's radius where it crosses each plane), the spider, the focuser bore where it
        reaches into the tube, and (``incoming``) the diagonal's body seen from the sky side.

        Parts no live ray can reach are left out of the kernel (the same loss codes, less work): above
        ``z_max`` or beyond ``x_max`` [mm] (:meth:`_return_leg_bounds`), and, for the incoming bundle of
        slope at most ``beam_tan`` (tan of the field angle) that reaches the unperturbed primary inside its
        rim, openings wider than the bundle where it crosses them (radius <= R + z beam_tan at height z):
        the vanes are sized not to vignette the sensor's field, so within it they never stop a ray."""
        import drjit as dr

        L = self.layout
        blocked = dr.zeros(_Bool(), dr.width(o.x))
        inv_dz = 1.0 / d.z          # one division for every plane z = const on this piece
        z_max = math.inf if z_max is None else z_max

        def beam_inside(r_open, z):
            return incoming and beam_tan is not None and L.r_primary + beam_tan * z + 1.0 < r_open

        for z, r in [(L.tube_top, L.r_tube), *[(zv, L.r_vane) for zv in L.vane_z]]:
            if z > z_max or beam_inside(r, z):
                continue
            tz = (z - o.z) * inv_dz
            x = o.x + d.x * tz
            y = o.y + d.y * tz
            blocked |= (tz > 1e-9) & (tz < t_end) & (x * x + y * y > r * r)
        if incoming:
            blocked |= self._hits_diagonal_body(o, d, t_end, inv_dz)
        if L.spider_z[0] <= z_max:
            blocked |= self._blocked_spider(o, d, t_end, inv_dz)
        x_in = L.focuser_start_x
        if x_in < L.r_tube and not beam_inside(x_in, L.z_axis + L.r_focuser) and not (
                x_max is not None and x_max < x_in):
            lo, hi = _cylinder_interval(o.y, o.z - L.z_axis, d.y, d.z, L.r_focuser)
            lo, hi = _slab(lo, hi, o.x, d.x, x_in, L.r_tube)
            blocked |= _max(lo, 0.0) < _min(hi, t_end)
        return blocked

    def _margin_tube_side(self, o, d, t_end):
        """Soft-edge version of the way back from the primary to the diagonal (``soft_eps``): the smallest
        margin [mm] inside the tube front's and the annular vanes' openings where the ray crosses them.
        The spider is left out on this leg: the incoming bundle already carries its (fixed) shadow, and
        the returning rays cross the vanes' thin slabs again close to where they passed them."""
        import drjit as dr

        L = self.layout
        m = dr.full(type(o.x), 1e30, dr.width(o.x))
        for z, r in [(L.tube_top, L.r_tube), *[(zv, L.r_vane) for zv in L.vane_z]]:
            tz = (z - o.z) / d.z
            x = o.x + d.x * tz
            y = o.y + d.y * tz
            inside = (tz > 1e-9) & (tz < t_end)
            m = _min(m, dr.select(inside, r - dr.sqrt(x * x + y * y), 1e30))
        return m

    def _margin_focuser(self, chain):
        """Soft-edge version of :meth:`_blocked_focuser`: the smallest margin [mm] inside the bore."""
        import drjit as dr

        L = self.layout
        m = dr.full(type(chain[0].x), 1e30, dr.width(chain[0].x))
        for a, b in itertools.pairwise(chain):
            dd = b - a
            for xq in (L.focuser_start_x, L.x_housing):
                s = (xq - a.x) / dd.x
                y = a.y + dd.y * s
                z = a.z + dd.z * s - L.z_axis
                m = _min(m, dr.select((s > 0) & (s <= 1), L.r_focuser - dr.sqrt(y * y + z * z), 1e30))
        return m

    def _hits_diagonal_body(self, o, d, t_end, inv_dz=None):
        """The diagonal with its holder: inside the vertical cylinder r < b about the ellipse centre, above
        the mirror plane and below the holder's top cap (a closed solid, so any overlap blocks)."""

        L = self.layout
        cx, _, cz = L.diag_centre
        lo, hi = _cylinder_interval(o.x - cx, o.y, d.x, d.y, L.diag_b)
        # z <= holder_top
        lo, hi = _clip_linear(lo, hi, o.z - L.holder_top, d.z, upper=0.0, inv_b=inv_dz)
        # above the plane: (z - cz) - (x - cx) >= 0
        lo, hi = _clip_linear(lo, hi, -((o.z - cz) - (o.x - cx)), -(d.z - d.x), upper=0.0)
        lo = _max(lo, 0.0)
        hi = _min(hi, t_end)
        return lo < hi

    def _blocked_spider(self, o, d, t_end, inv_dz=None):
        """The spider's vanes: each a box, the intersection of three slabs (along the vane
        a = x ca + y sa in [0.9 b, R_tube], across it h = -x sa + y ca in +-w/2, and z in the vanes'
        depth); the z slab is the same for every vane and is found once."""
        import drjit as dr

        L = self.layout
        blocked = dr.zeros(_Bool(), dr.width(o.x))
        z0, z1 = L.spider_z
        big = dr.zeros(type(o.x), dr.width(o.x)) + 1e30
        lo_z, hi_z = _slab(-big, big, o.z, d.z, z0, z1, inv_dz)
        lo_z, hi_z = _max(lo_z, 0.0), _min(hi_z, t_end)
        for ang in L.spider_angles_deg:
            ca, sa = math.cos(math.radians(ang)), math.sin(math.radians(ang))
            lo, hi = _slab(lo_z, hi_z, o.x * ca + o.y * sa, d.x * ca + d.y * sa, 0.9 * L.diag_b, L.r_tube)
            lo, hi = _slab(lo, hi, -o.x * sa + o.y * ca, -d.x * sa + d.y * ca, -L.spider_half_width,
                           L.spider_half_width)
            blocked |= lo < hi
        return blocked

    def _chain_x_bounds(self, pert) -> list[tuple[float, float]]:
        """Where along x [mm] each vertex of a live ray's chain (diagonal, every lens surface, detector) can
        lie in the unperturbed corrector and sensor: inside the diagonal's outline (its tilt allowed for),
        within each lens surface's sag at its clear semi-diameter, on the detector plane; 1 mm of margin."""
        L = self.layout
        tilted = "diagonal_tilt_x_deg" in pert or "diagonal_tilt_y_deg" in pert
        half = L.diag_a if tilted else L.diag_a / SQRT2
        out = [(L.diag_centre[0] - half - 1.0, L.diag_centre[0] + half + 1.0)]
        for s in L.lenses:
            r, h = abs(s.radius_mm), s.semi_diameter_mm
            sag = r - math.sqrt(max(r * r - h * h, 0.0)) if r else 0.0
            out.append((s.x_mm - sag - 1.0, s.x_mm + sag + 1.0))
        out.append((L.x_detector - 1.0, L.x_detector + 1.0))
        return out

    def _blocked_focuser(self, chain, x_bounds=None):
        """The folded beam must pass the focuser bore (radius r_f about the focuser axis) where it starts
        at the tube wall and where it enters the camera housing. ``chain`` lists the ray's vertices from
        the diagonal to the detector; each straight piece is checked where it crosses those two planes.
        Between them the distance to the axis along a straight piece is convex, so the two ends decide.
        ``x_bounds`` (:meth:`_chain_x_bounds`): a piece whose ends cannot straddle a plane is not checked
        against it (the same result, less work)."""
        import drjit as dr

        L = self.layout
        blocked = dr.zeros(_Bool(), dr.width(chain[0].x))
        x0 = L.focuser_start_x
        for k, (a, b) in enumerate(itertools.pairwise(chain)):
            planes = [xq for xq in (x0, L.x_housing) if x_bounds is None
                      or min(x_bounds[k][0], x_bounds[k + 1][0]) <= xq <= max(x_bounds[k][1], x_bounds[k + 1][1])]
            if not planes:
                continue
            dd = b - a
            inv = 1.0 / dd.x
            for xq in planes:
                s = (xq - a.x) * inv
                y = a.y + dd.y * s
                z = a.z + dd.z * s - L.z_axis
                blocked |= (s > 0) & (s <= 1) & (y * y + z * z > L.r_focuser ** 2)
        return blocked

    # -- mesh obstructions (Mitsuba BVH) -----------------------------------------------------------------
    def _blocked_mesh(self, o, d, t_end):

        mi = self.mi
        eps = 1e-3
        ray = mi.Ray3f(mi.Point3f(mi.Float(o.x + d.x * eps), mi.Float(o.y + d.y * eps), mi.Float(o.z + d.z * eps)),
                       mi.Vector3f(mi.Float(d.x), mi.Float(d.y), mi.Float(d.z)))
        ray.maxt = mi.Float(_max(t_end - 2 * eps, 0.0))
        return _Bool()(self._scene.ray_test(ray))

    def _blocked_mesh_chain(self, points):
        import drjit as dr

        blocked = dr.zeros(_Bool(), dr.width(points[0].x))
        for a, b in itertools.pairwise(points):
            seg = b - a
            length = dr.norm(seg)
            blocked |= self._blocked_mesh(a, seg / length, length)
        return blocked


# ---- small drjit helpers ---------------------------------------------------------------------------------
def _is_dr(x) -> bool:
    import drjit as dr

    return dr.is_array_v(x)


def _types(single: bool = False):
    """(Float, Array3) drjit types of the kernel: float32 (``single``) or float64."""
    from drjit.llvm.ad import Array3f, Array3f64, Float, Float64

    return (Float, Array3f) if single else (Float64, Array3f64)


def to_dr(a, single: bool = False):
    """A drjit Float64 (``single``: Float32) copy of the numpy array ``a``. drjit maps numpy memory without copying, and the
    kernel's IR records the buffer's alignment (``align 128`` or ``align 1``), so an unlucky numpy
    allocation changes the kernel's hash and costs a recompilation. The copy helps for numpy's buffers; for
    repeated kernels with many inputs (the AD kernels of :mod:`optics.gradients`) the per-ray inputs are
    built inside the kernel instead (counters and gathers carry no alignment)."""
    import drjit as dr

    F = _types(single)[0]
    return dr.copy(F(np.ascontiguousarray(a, dtype=np.float32 if single else np.float64)))


def _max(a, b):
    """max(a, b) as a compare and a select. ``dr.maximum`` lowers to LLVM's NaN-propagating
    ``llvm.maximum``, several instructions per lane on x86; the results differ only where an argument is
    NaN (never on the rays the kernels keep). Either argument may be a Python number."""
    import drjit as dr

    if not dr.is_array_v(a):
        a, b = b, a
    return dr.select(a > b, a, b)


def _min(a, b):
    """min(a, b) as a compare and a select (see :func:`_max`)."""
    import drjit as dr

    if not dr.is_array_v(a):
        a, b = b, a
    return dr.select(a < b, a, b)


def _Bool():
    from drjit.llvm.ad import Bool

    return Bool


def _index(material, wavelength_nm):
    from .glass import index

    return index(material, wavelength_nm)


def _refract(d, n, n1: float, n2: float, eta=None):
    """Refract unit direction ``d`` at a surface with unit normal ``n`` (either orientation) from index
    ``n1`` into ``n2``. Returns (new direction, Fresnel transmittance (unpolarised), total internal
    reflection mask). Snell in vector form: t = eta d + (eta cos_i - cos_t) m with m facing the ray."""
    import drjit as dr

    cos_i = -dr.dot(d, n)
    m = dr.select(cos_i < 0, -n, n)
    cos_i = dr.abs(cos_i)
    eta = n1 / n2 if eta is None else eta
    sin2_t = eta * eta * (1.0 - cos_i * cos_i)
    tir = sin2_t > 1.0
    cos_t = dr.sqrt(_max(1.0 - sin2_t, 0.0))
    t = d * eta + m * (eta * cos_i - cos_t)
    rs = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)
    rp = (n2 * cos_i - n1 * cos_t) / (n2 * cos_i + n1 * cos_t)
    trans = dr.select(tir, 0.0, 1.0 - 0.5 * (rs * rs + rp * rp))
    return t, trans, tir


def _clip_linear(lo, hi, a, b, upper: float = 0.0, inv_b=None):
    """Intersect the t-interval [lo, hi] with {t : a + b t <= upper} (``inv_b``: 1 / b when known)."""
    import drjit as dr

    t = (upper - a) * inv_b if inv_b is not None else (upper - a) / b
    parallel = dr.abs(b) < 1e-15
    new_lo = dr.select(parallel, dr.select(a <= upper, lo, 1e30), dr.select(b < 0, _max(lo, t), lo))
    new_hi = dr.select(parallel, dr.select(a <= upper, hi, -1e30), dr.select(b > 0, _min(hi, t), hi))
    return new_lo, new_hi


def _slab(lo, hi, c0, cd, c_lo: float, c_hi: float, inv=None):
    """Intersect the t-interval [lo, hi] with the slab c_lo <= c0 + cd t <= c_hi (``inv``: 1 / cd when
    known): the two half-spaces of :func:`_clip_linear` with one division."""
    import drjit as dr

    inv = 1.0 / cd if inv is None else inv
    ta = (c_lo - c0) * inv
    tb = (c_hi - c0) * inv
    parallel = dr.abs(cd) < 1e-15
    inside = (c0 >= c_lo) & (c0 <= c_hi)
    new_lo = dr.select(parallel, dr.select(inside, lo, 1e30), _max(lo, _min(ta, tb)))
    new_hi = dr.select(parallel, dr.select(inside, hi, -1e30), _min(hi, _max(ta, tb)))
    return new_lo, new_hi


def _cylinder_interval(qx, qy, dx, dy, r):
    """t-interval where (qx + t dx)^2 + (qy + t dy)^2 <= r^2 (empty: lo > hi)."""
    import drjit as dr

    A = dx * dx + dy * dy
    B = qx * dx + qy * dy
    C = qx * qx + qy * qy - r * r
    disc = B * B - A * C
    root = dr.sqrt(_max(disc, 0.0))
    small = A < 1e-18
    inv_a = 1.0 / A
    lo = dr.select(small, dr.select(C <= 0, -1e30, 1e30), (-B - root) * inv_a)
    hi = dr.select(small, dr.select(C <= 0, 1e30, -1e30), (-B + root) * inv_a)
    lo = dr.select(~small & (disc < 0), 1e30, lo)
    hi = dr.select(~small & (disc < 0), -1e30, hi)
    return lo, hi


def make_tracer(design: Design | str, mi, obstruct: str = "analytic") -> SequentialTracer:
    """Convenience: a tracer from a design object or a built-in name/path."""
    from .design import as_design

    return SequentialTracer(as_design(design), mi, obstruct)
