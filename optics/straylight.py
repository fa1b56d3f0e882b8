"""Straylight: point-source transmittance (PST), focal-plane straylight maps and path analysis.

Definition (Breault, "Control of stray light", Handbook of Optics vol. I ch. 38)::

    PST(theta, phi) = E_det(theta, phi) / E_in                                                    (1)

``E_in`` is the irradiance of a collimated source (Sun, Moon, Earth limb) normal to its direction at the
entrance; ``E_det`` the irradiance on the detector averaged over its area; ``theta`` the angle between the
source and the optical axis (+z), ``phi`` its azimuth from +x (the focuser side: phi = 0 puts the
source on the focuser side, so its light falls on the opposite tube wall, the wall the detector sees
through the focuser).

Monte Carlo on the non-sequential model (:func:`optics.meshes.telescope_parts` in Mitsuba, materials
from :mod:`optics.bsdf`). The light reaching the detector is split into two disjoint classes by what
happens at its *first* interaction after entering the tube:

B (first event a scatter: paint, the mirrors' microroughness lobe; plus the direct view of the sky)
    Backward (reciprocal) tracing from the detector. By reciprocity the mean irradiance is
    ``E_det = 1/A integral_A integral_H L_in(x, w) cos(theta_x) dw dA``; points x are uniform on the
    detector and directions w come from a mixture of a cosine lobe and uniform area sampling of the
    focuser's inner opening (or of the last corrector surface), with the mixture pdf. At every vertex
    with a non-delta BSDF the collimated source is connected by next-event estimation (a shadow ray
    toward the source that must leave through the open front of the tube untouched)::

        X = sum_k  beta_k  f_k(w_k, w_src) |cos theta_src,k| V_k,    beta_0 = cos theta_x / p(w)     (2)

    (E_in = 1). Specular mirror bounces and the corrector's dielectric events continue by sampling.

F (first event a specular reflection or refraction: the primary's focused beam, ghosts)
    A collimated source seen through a mirror is a delta in direction, so no backward path can
    reach it; these paths (e.g. the out-of-field star image focused onto the focuser wall or the
    spider, the diagonal's scatter of the focused beam) are traced forward from the entrance: rays
    uniform over the tube's front opening, specular first event, then at every non-delta vertex a
    connection to a uniform point on the detector (light tracing, Veach 1997 ch. 10); detector hits
    are counted only after a delta event (the others were counted by the connection). Scatter
    directions off black paint are drawn from a mixture of the BSDF, a cone about -z that contains the
    field (paths the primary then images onto the detector), the same cone about -x (the detector
    sees the focuser's surroundings in the diagonal, reflected by the primary: the collimation view)
    and the first corrector lens (one-sample MIS, Veach 1997 ch. 9)::

        X = A_ent cos(theta) [ sum_k beta_k f_k cos(theta_det) / d_k^2 + 1{delta hit} beta / A_det ]   (3)

Both estimators are unbiased (mixture pdfs, unbiased Russian roulette); PST = <X_B> + <X_F> with
variance s_B^2 / n_B + s_F^2 / n_F from the per-path sample variances. A pilot run of each class
fixes the split of the ray budget (n_i ~ s_i / sqrt(cost_i), cost = ray casts per path); the pilot is
used for the allocation only, never in the estimate, so the data-dependent split cannot bias it.

For theta >= 90 degrees the source lies behind the plane of the aperture: no geometric path exists
in this model (closed tube, zero-thickness rim, no diffraction), PST = 0 exactly.

References: Breault (PST); Veach, "Robust Monte Carlo methods for light transport simulation", PhD
thesis, Stanford (1997): next-event estimation, light tracing, one-sample MIS (mixture) sampling;
Harvey-Shack and ABg scatter: :mod:`optics.bsdf`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from .design import Design, load_design
from .layout import make_layout

MIRROR, BLACK, GLASS, DETECTOR, NONE = range(5)
KIND = {"mirror": MIRROR, "black": BLACK, "glass": GLASS, "detector": DETECTOR}
EV_SPEC, EV_REFR, EV_SCATTER = range(3)
EV_NAMES = ("spec", "refr", "scatter")
BATCH = 1 << 20


# ---- results -----------------------------------------------------------------------------------------------
@dataclass
class PSTResult:
    """A PST curve: one value per angle, with its 1-sigma relative Monte Carlo error.

    ``pst_backward`` / ``pst_forward`` are the two path classes of the module docstring (B, F);
    ``rays`` the number of paths traced per angle (pilot included), ``time_s`` the wall time per angle.
    """

    design: str
    azimuth_deg: float
    wavelength_nm: float
    angle_deg: np.ndarray
    pst: np.ndarray
    rel_err: np.ndarray
    pst_backward: np.ndarray
    pst_forward: np.ndarray
    rays: np.ndarray
    time_s: np.ndarray
    timings: dict = field(default_factory=dict)

    @property
    def rays_per_s(self) -> float:
        t = float(np.sum(self.time_s))
        return float(np.sum(self.rays)) / t if t > 0 else 0.0

    def to_json(self) -> dict:
        """JSON-ready dict: the contract keys ``angle_deg``, ``pst``, ``rel_err`` plus the details."""
        return {"design": self.design, "azimuth_deg": self.azimuth_deg, "wavelength_nm": self.wavelength_nm,
                "angle_deg": [float(a) for a in self.angle_deg], "pst": [float(p) for p in self.pst],
                "rel_err": [float(e) for e in self.rel_err],
                "pst_backward": [float(p) for p in self.pst_backward],
                "pst_forward": [float(p) for p in self.pst_forward],
                "rays": [int(r) for r in self.rays], "rays_per_s": self.rays_per_s,
                "time_s": [float(t) for t in self.time_s], "timings": self.timings}


@dataclass
class _Tally:
    """Per-class accumulation over batches: sums for the mean and variance, path and map records."""

    n: int = 0
    nonzero: int = 0
    s1: float = 0.0
    s2: float = 0.0
    time_s: float = 0.0
    casts: int = 0
    paths: dict = field(default_factory=dict)      # label -> sum of contributions
    lit: dict = field(default_factory=dict)        # part -> sum (class B: NEE vertex; F: first vertex)
    seen: dict = field(default_factory=dict)       # part -> projected solid angle (critical objects)
    first_hit: dict = field(default_factory=dict)  # part -> number of entrance rays landing first there

    def add(self, x: np.ndarray):
        x = np.asarray(x, np.float64)
        self.n += len(x)
        self.nonzero += int(np.count_nonzero(x))
        self.s1 += float(x.sum())
        self.s2 += float((x * x).sum())

    @property
    def mean(self) -> float:
        return self.s1 / self.n if self.n else 0.0

    @property
    def var_mean(self) -> float:
        """Variance of the mean (unbiased sample variance / n)."""
        if self.n < 2:
            return 0.0
        m = self.mean
        return max(self.s2 / self.n - m * m, 0.0) * self.n / (self.n - 1) / self.n

    @property
    def std(self) -> float:
        return math.sqrt(self.var_mean * self.n) if self.n else 0.0


def _bump(d: dict, key, value):
    d[key] = d.get(key, 0.0) + value


def source_direction(theta_deg: float, azimuth_deg: float = 0.0) -> np.ndarray:
    """Unit vector toward a source ``theta_deg`` off the optical axis (+z) at azimuth ``azimuth_deg``
    from +x (the focuser side) [1]. The light travels along its negative."""
    t, p = math.radians(theta_deg), math.radians(azimuth_deg)
    return np.array([math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)])


def _as_design(design) -> Design:
    return design if isinstance(design, Design) else load_design(str(design))


# ---- the tracer --------------------------------------------------------------------------------------------
class StraylightTracer:
    """Non-sequential straylight Monte Carlo for one design at one wavelength.

    Parameters
    ----------
    design : Design or str
        Design object, built-in name or TOML path.
    mi : module
        Mitsuba with an llvm variant set (``optics.llvm.init_mitsuba``).
    wavelength_nm : float
        Wavelength [nm]: sets the mirrors' TIS and the glass indices.
    max_depth : int
        Longest path (surface interactions).
    rr_depth : tuple of int
        Russian roulette (unbiased: survivors are re-weighted by 1/q) starts after this many
        interactions, (backward, forward). Backward: q = min(throughput, 0.95). Forward:
        q = min(throughput / ``rr_forward_floor``, 0.95), so a path is thinned only once its
        throughput falls below the floor (two paint bounces), never after a single scatter: every forward
        detector hit carries A_ent cos(theta) / A_det ~ 90 times its throughput, and a roulette that
        boosted single-scatter paths to weight ~1 made those hits rare and heavy. Measured: forward
        roulette from 8 instead of 4 bounces, 10x more efficient at 5 degrees; the floor 0.05 instead
        of 1, 3-80x with a corrector at 3-20 degrees; backward from 3 instead of 5-8, 2x.
    rr_forward_floor : float
        See ``rr_depth``.
    lobe_min_prob : float
        Lower bound of the probability of sampling the mirrors' scatter lobe instead of their specular
        peak (:class:`optics.bsdf` ``Mirror``): explores mirror-scatter paths more often; no bias.
    disk_fraction : float
        Share of the detector's directions drawn toward the focuser opening / last corrector surface.
    batch : int
        Rays per wavefront (memory: about 300 bytes per ray).
    """

    def __init__(self, design, mi, wavelength_nm: float = 550.0, max_depth: int = 24, rr_depth=(3, 8),
                 rr_forward_floor: float = 0.05,
                 lobe_min_prob: float = 0.05, disk_fraction: float = 0.8, batch: int = BATCH):
        from .bsdf import make_bsdfs
        from .meshes import telescope_parts
        from .mitsuba_scene import build_scene, shape_ids

        self.design = _as_design(design)
        self.mi = mi
        self.wavelength_nm = float(wavelength_nm)
        self.max_depth = int(max_depth)
        self.rr_back, self.rr_fwd = (int(x) for x in rr_depth)
        self.rr_fwd_floor = float(rr_forward_floor)
        self.batch = int(batch)
        self.disk_fraction = float(disk_fraction)
        L = self.layout = make_layout(self.design)
        self.parts = telescope_parts(L)
        self.names = [p.name for p in self.parts]
        self.bsdfs = make_bsdfs(mi, self.design, self.parts, self.wavelength_nm, lobe_min_prob)
        self.scene = build_scene(mi, self.parts, self.bsdfs)
        ids = shape_ids(mi, self.scene)
        lut = np.full(max(ids) + 1, len(self.parts), dtype=np.uint32)
        for sid, name in ids.items():
            lut[sid] = self.names.index(name)
        kinds = np.array([KIND[p.material] for p in self.parts] + [NONE], dtype=np.uint32)
        self._lut = mi.UInt32(lut)
        self._kinds = mi.UInt32(kinds)
        self.n_parts = len(self.parts)
        # path codes: one symbol (part, event) per vertex, packed in a UInt64
        self.base = 3 * (self.n_parts + 1) + 1
        self.levels = max(1, int(63 // math.log2(self.base)))
        # geometry
        self.hu, self.hv = L.detector_half
        self.area_det = 4.0 * self.hu * self.hv
        self.area_ent = math.pi * L.r_tube ** 2
        if L.lenses:
            last = L.lenses[-1]
            self.disk_x, self.disk_r = last.x_mm, last.semi_diameter_mm
            first = L.lenses[0]
            self.lens_disk = (first.x_mm, first.semi_diameter_mm)
            # the detector as the corrector images it back into the unfolded primary's focal plane (the
            # bare focus, defocus_mm before the detector; EFL 956 vs 960 mm: same scale), a little larger
            # for the aberrations: aiming a scatter at it sends the ray through the lenses to the detector
            self.virtual_det = (L.x_detector - self.design.focal_plane.defocus_mm, 1.15 * self.hu, 1.15 * self.hv)
        else:
            self.disk_x, self.disk_r = L.focuser_start_x, L.r_focuser
            self.lens_disk = None
            self.virtual_det = None
        f = self.design.primary.focal_length_mm
        self.cone_cos = math.cos(1.15 * math.atan(math.hypot(self.hu, self.hv) / f) + 2e-3)

    # -- small helpers ---------------------------------------------------------------------------------------
    def _rng(self, n: int, key):
        ss = np.random.SeedSequence([int(k) & 0xFFFFFFFF for k in key])
        st, sq = ss.generate_state(2, np.uint64)
        return self.mi.PCG32(n, self.mi.UInt64(int(st)), self.mi.UInt64(int(sq)))

    def _part(self, si, active):
        import drjit as dr

        mi = self.mi
        sid = dr.reinterpret_array(mi.UInt32, si.shape)
        sid = dr.select(active, dr.minimum(sid, dr.width(self._lut) - 1), 0)
        pid = dr.gather(mi.UInt32, self._lut, sid, active)
        pid = dr.select(active, pid, self.n_parts)
        return pid, dr.gather(mi.UInt32, self._kinds, pid)

    def _vec(self, v):
        import drjit as dr

        return self.mi.Vector3f(*[dr.opaque(self.mi.Float, float(c)) for c in v])

    def _escapes(self, o, w, active):
        """Shadow test toward the source: nothing in the way and out through the tube's front opening."""
        import drjit as dr

        mi, L = self.mi, self.layout
        ray = mi.Ray3f(o, w)
        occluded = self.scene.ray_test(ray, active)
        wz = dr.maximum(w.z, 1e-12)
        t = (L.tube_top - o.z) / wz
        x, y = o.x + w.x * t, o.y + w.y * t
        front = (w.z > 0) & (x * x + y * y < L.r_tube ** 2)
        return active & ~occluded & front

    def _event(self, sampled_type):
        import drjit as dr

        mi = self.mi
        delta_r = (sampled_type & mi.UInt32(+mi.BSDFFlags.DeltaReflection)) != 0
        delta_t = (sampled_type & mi.UInt32(+mi.BSDFFlags.DeltaTransmission)) != 0
        return dr.select(delta_r, mi.UInt32(EV_SPEC), dr.select(delta_t, mi.UInt32(EV_REFR),
                                                                 mi.UInt32(EV_SCATTER)))

    def _push(self, code, depth, pid, ev):
        """Append the symbol (pid, ev) to a path code (saturates after ``levels`` vertices)."""
        mi = self.mi
        if depth >= self.levels:
            return code
        return code * mi.UInt64(self.base) + mi.UInt64(pid * 3 + ev + 1)

    def decode(self, code: int, forward: bool) -> list[tuple[str, str]]:
        """Path code -> [(part, event)] in the order the light travels (source first)."""
        out = []
        code = int(code)
        while code:
            sym = code % self.base - 1
            code //= self.base
            pid, ev = divmod(sym, 3)
            name = self.names[pid] if pid < self.n_parts else "?"
            out.append((name, EV_NAMES[ev]))
        out.reverse()                 # first pushed first
        return out if forward else out[::-1]

    def _record(self, tally, records, fwd: bool):
        """Fold (code, pid of the connected vertex, value) records of contributing lanes into the tally:
        contributions per scatter sequence (``paths``) and per surface lit by the source (``lit``)."""
        if not records:
            return
        codes = np.concatenate([r[0] for r in records])
        pids = np.concatenate([r[1] for r in records])
        vals = np.concatenate([r[2] for r in records])
        for (c, p), tot in _group_sum(codes, pids, vals).items():
            seq = self.decode(c, forward=fwd)
            if p < self.n_parts:                       # the vertex connected to the source / detector
                if fwd:
                    seq = seq + [(self.names[p], "scatter")]
                else:
                    seq = [(self.names[p], "scatter")] + seq
            label = " -> ".join(f"{n}({e})" for n, e in seq) if seq else "direct"
            _bump(tally.paths, label, tot)
            lit = seq[0][0] if seq else "detector (direct)"
            _bump(tally.lit, lit, tot)

    # -- class B: backward from the detector -----------------------------------------------------------------
    def backward(self, w_src, n: int, key, tally: _Tally, collect: bool = False, hist=None):
        """Trace ``n`` detector paths (class B), eq. (2), and add them to ``tally``. ``collect`` records
        scatter sequences and the detector's view (path analysis); ``hist`` (a dict with ``bins``,
        ``edges_u``, ``edges_v``) accumulates the contributions over the focal plane."""
        import drjit as dr

        mi, L = self.mi, self.layout
        t0 = time.perf_counter()
        rng = self._rng(n, key)
        ctx = mi.BSDFContext(mi.TransportMode.Radiance)
        ws = self._vec(w_src)
        u = (2.0 * rng.next_float32() - 1.0) * self.hu
        v = (2.0 * rng.next_float32() - 1.0) * self.hv
        p = mi.Point3f(L.x_detector, v, L.z_axis + u)
        n_det = mi.Vector3f(-1.0, 0.0, 0.0)
        pick_disk = rng.next_float32() < self.disk_fraction
        s2 = mi.Point2f(rng.next_float32(), rng.next_float32())
        rr = self.disk_r * dr.sqrt(s2.x)
        sp, cp = dr.sincos(2.0 * dr.pi * s2.y)
        q = mi.Point3f(self.disk_x, rr * cp, L.z_axis + rr * sp)
        d_disk = dr.normalize(q - p)
        d_cos = mi.Frame3f(n_det).to_world(mi.warp.square_to_cosine_hemisphere(s2))
        d = dr.select(pick_disk, d_disk, d_cos)
        cos_det = -d.x
        t = (self.disk_x - p.x) / dr.minimum(d.x, -1e-12)
        h = p + d * t
        inside = (d.x < 0) & (dr.square(h.y) + dr.square(h.z - L.z_axis) < self.disk_r ** 2)
        pdf_disk = dr.select(inside, t * t / (dr.pi * self.disk_r ** 2 * dr.maximum(-d.x, 1e-12)), 0.0)
        pdf = self.disk_fraction * pdf_disk + (1.0 - self.disk_fraction) * dr.maximum(cos_det, 0.0) / dr.pi
        beta = dr.select((cos_det > 0) & (pdf > 0), cos_det / pdf, 0.0)
        geom = mi.Float(beta)
        throughput = dr.full(mi.Float, 1.0, n)
        o = p + n_det * 1e-3
        # direct view of the source (zero-bounce next-event estimation)
        direct = dr.maximum(-ws.x, 0.0)
        vis0 = self._escapes(o, ws, direct > 0)
        X = dr.select(vis0, direct, 0.0)
        casts = int(dr.count(direct > 0)[0])
        records = []
        if collect:
            x0 = X.numpy()
            nz = np.nonzero(x0)[0]
            records.append((np.zeros(len(nz), np.uint64), np.full(len(nz), self.n_parts), x0[nz]))
        if hist is not None:
            self._hist_add(hist, u.numpy(), v.numpy(), X.numpy())
        ray = mi.Ray3f(o, d)
        active = beta > 0
        code = dr.zeros(mi.UInt64, n)
        spec_chain = dr.full(mi.Bool, True, n)
        bounces = dr.zeros(mi.UInt32, n)          # vertices off glass (the roulette's depth)
        for depth in range(self.max_depth):
            dr.eval(ray, active, beta, throughput, X, code, spec_chain, rng, bounces)
            n_act = int(dr.count(active)[0])
            if n_act == 0:
                break
            casts += n_act
            si = self.scene.ray_intersect(ray, active)
            valid = active & si.is_valid()
            pid, kind = self._part(si, valid)
            seen_mask = active & spec_chain
            live = valid & (kind != DETECTOR)
            bsdf = si.bsdf(ray)
            f = bsdf.eval(ctx, si, si.to_local(ws), live)[0]
            nee = live & (f > 0)
            vis = self._escapes(si.spawn_ray(ws).o, ws, nee)
            c = dr.select(vis, beta * f, 0.0)
            X += c
            code_before = code
            bs, w = bsdf.sample(ctx, si, rng.next_float32(), mi.Point2f(rng.next_float32(), rng.next_float32()),
                                live)
            w = w[0]
            ev = self._event(bs.sampled_type)
            code = dr.select(live, self._push(code, depth, pid, ev), code)
            spec_chain &= ev != EV_SCATTER
            beta *= w
            throughput *= w
            active = live & (beta > 0)
            bounces += dr.select(live & (kind != GLASS), 1, 0)
            if depth + 1 >= self.rr_back:
                # roulette off the corrector's glass only (see _roulette_mask)
                qs = dr.select(self._roulette_mask(kind, bounces, self.rr_back), dr.minimum(throughput, 0.95), 1.0)
                survive = rng.next_float32() < qs
                active &= survive
                beta = dr.select(survive, beta / qs, 0.0)
                throughput = dr.select(survive, throughput / qs, 0.0)
            ray = si.spawn_ray(si.to_world(bs.wo))
            dr.eval(ray, active, beta, throughput, X, code, spec_chain, rng, c, nee, pid, valid, seen_mask, bounces)
            casts += int(dr.count(nee)[0])
            if collect:
                self._census(tally.seen, pid, geom, seen_mask, valid)
            self._keep(c, code_before, pid, u, v, records if collect else None, hist)
        return self._finish(tally, X, casts, records, False, t0)

    def _census(self, seen, pid, geom, mask, valid):
        """Projected solid angle of the detector's view (directly or through specular events) per part."""
        m = mask.numpy()
        g = geom.numpy()
        vm = valid.numpy()
        sky = m & ~vm
        if sky.any():
            _bump(seen, "sky (out of the tube front)", float(g[sky].sum()))
        hit = m & vm
        if hit.any():
            sums = np.bincount(pid.numpy()[hit], weights=g[hit], minlength=self.n_parts + 1)
            for k in np.nonzero(sums)[0]:
                if k < self.n_parts:
                    _bump(seen, self.names[k], float(sums[k]))

    def _hist_add(self, hist, u, v, val):
        bins, eu, ev = hist["bins"], hist["edges_u"], hist["edges_v"]
        h, _, _ = np.histogram2d(v, u, bins=[ev, eu], weights=val)
        bins += h

    # -- class F (and plain forward Monte Carlo) ---------------------------------------------------------------
    def forward(self, w_src, n: int, key, tally: _Tally, plain: bool = False, collect: bool = False, hist=None):
        """Trace ``n`` rays from the source through the tube's front opening. ``plain=False``: class F of
        the module docstring (specular first event, detector connections, guided paint scatter);
        ``plain=True``: plain forward Monte Carlo (BSDF sampling only, count what lands on the detector)."""
        import drjit as dr

        mi, L = self.mi, self.layout
        t0 = time.perf_counter()
        rng = self._rng(n, key)
        ctx = mi.BSDFContext(mi.TransportMode.Importance)
        ctx0 = ctx if plain else mi.BSDFContext(mi.TransportMode.Importance, mi.BSDFFlags.Delta)
        cos_t = float(w_src[2])
        ws = self._vec(w_src)
        scale_hit = self.area_ent * cos_t / self.area_det
        scale_conn = self.area_ent * cos_t
        r = L.r_tube * dr.sqrt(rng.next_float32())
        sp, cp = dr.sincos(2.0 * dr.pi * rng.next_float32())
        q = mi.Point3f(r * cp, r * sp, L.tube_top)
        ray = mi.Ray3f(q + ws * 1.0, -ws)
        beta = dr.full(mi.Float, 1.0, n)
        throughput = dr.full(mi.Float, 1.0, n)
        X = dr.zeros(mi.Float, n)
        active = dr.full(mi.Bool, True, n)
        last_delta = dr.full(mi.Bool, True, n)
        code = dr.zeros(mi.UInt64, n)
        bounces = dr.zeros(mi.UInt32, n)          # vertices off glass (the roulette's depth)
        records = []
        casts = 0
        for depth in range(self.max_depth):
            dr.eval(ray, active, beta, throughput, X, code, last_delta, rng, bounces)
            n_act = int(dr.count(active)[0])
            if n_act == 0:
                break
            casts += n_act
            si = self.scene.ray_intersect(ray, active)
            valid = active & si.is_valid()
            pid, kind = self._part(si, valid)
            at_det = valid & (kind == DETECTOR) & (ray.d.x > 0)
            count = at_det if plain else at_det & last_delta & (depth >= 1)
            c_hit = dr.select(count, beta * scale_hit, 0.0)
            X += c_hit
            hit_u, hit_v = si.p.z - L.z_axis, si.p.y
            live = valid & (kind != DETECTOR)
            if depth == 0 and not plain:
                live &= (kind == MIRROR) | (kind == GLASS)
            bsdf = si.bsdf(ray)
            cx = ctx0 if depth == 0 else ctx
            code_before = code
            conn = not plain and depth >= 1
            if conn:
                # connection to a uniform point of the detector
                ud = (2.0 * rng.next_float32() - 1.0) * self.hu
                vd = (2.0 * rng.next_float32() - 1.0) * self.hv
                xd = mi.Point3f(L.x_detector, vd, L.z_axis + ud)
                dv = xd - si.p
                dist2 = dr.squared_norm(dv)
                dirc = dv * dr.rsqrt(dist2)
                cos_d = dirc.x
                fc = bsdf.eval(cx, si, si.to_local(dirc), live & (cos_d > 0))[0]
                m = live & (cos_d > 0) & (fc > 0)
                occl = self.scene.ray_test(si.spawn_ray_to(xd), m)
                cc = dr.select(m & ~occl, beta * fc * cos_d / dist2 * scale_conn, 0.0)
                X += cc
            s1 = rng.next_float32()
            s2 = mi.Point2f(rng.next_float32(), rng.next_float32())
            bs, w = bsdf.sample(cx, si, s1, s2, live)
            w = w[0]
            wo = si.to_world(bs.wo)
            ev = self._event(bs.sampled_type)
            if conn:
                wo, w, ev = self._guided(si, bsdf, cx, kind, live, wo, w, ev, rng)
            code = dr.select(live, self._push(code, depth, pid, ev), code)
            last_delta = ev != EV_SCATTER
            beta *= w
            throughput *= w
            active = live & (beta > 0)
            bounces += dr.select(live & (kind != GLASS), 1, 0)
            if depth + 1 >= self.rr_fwd:
                qs = dr.select(self._roulette_mask(kind, bounces, self.rr_fwd),
                               dr.minimum(throughput / self.rr_fwd_floor, 0.95), 1.0)
                survive = rng.next_float32() < qs
                active &= survive
                beta = dr.select(survive, beta / qs, 0.0)
                throughput = dr.select(survive, throughput / qs, 0.0)
            ray = si.spawn_ray(wo)
            extra = [c_hit, pid, valid, bounces] + ([cc, m, ud, vd] if conn else [])
            dr.eval(ray, active, beta, throughput, X, code, last_delta, rng, *extra)
            if conn:
                casts += int(dr.count(m)[0])
            if collect and depth == 0:
                vm = valid.numpy()
                cnt = np.bincount(pid.numpy()[vm], minlength=self.n_parts + 1)
                for k in np.nonzero(cnt)[0]:
                    _bump(tally.first_hit, self.names[k] if k < self.n_parts else "?", float(cnt[k]))
            kept = records if collect else None
            self._keep(c_hit, code_before, None, hit_u, hit_v, kept, hist)
            if conn:
                self._keep(cc, code_before, pid, ud, vd, kept, hist)
        return self._finish(tally, X, casts, records, True, t0)

    def _roulette_mask(self, kind, bounces, rr_depth):
        """Lanes where Russian roulette may act: at a vertex off glass, once the path has had ``rr_depth``
        such vertices. The corrector's refractions and Fresnel reflections are deterministic, lossless to
        1 % and come in chains of eight: counted as bounces they pushed forward paths past the roulette
        depth *inside* the lens stack, where a path that had scattered once (throughput ~1e-5) survived with
        q = throughput / floor and reached the detector with throughput 0.05, i.e. a hit of weight
        A_ent cos / A_det x 0.05 ~ 5 (the fireflies of the corrector design at 12 degrees)."""
        return (kind != GLASS) & (bounces >= rr_depth)

    def _keep(self, contrib, code, pid, u, v, records, hist):
        """Store the paths with a non-zero contribution: (scatter code, part id, value) in ``records`` for
        the path analysis (``pid`` None: the detector itself), and (u, v, value) in the map ``hist``."""
        if records is None and hist is None:
            return
        cn = contrib.numpy()
        nz = np.nonzero(cn)[0]
        if not len(nz):
            return
        if records is not None:
            parts = np.full(len(nz), self.n_parts) if pid is None else pid.numpy()[nz]
            records.append((code.numpy()[nz], parts, cn[nz]))
        if hist is not None:
            self._hist_add(hist, u.numpy()[nz], v.numpy()[nz], cn[nz])

    def _finish(self, tally, X, casts, records, fwd, t0):
        """Close one batch: per-path estimates into the tally, ray casts, path records, time."""
        xs = X.numpy()
        tally.add(xs)
        tally.casts += casts
        self._record(tally, records, fwd=fwd)
        tally.time_s += time.perf_counter() - t0
        return xs

    def _guided(self, si, bsdf, ctx, kind, live, wo_bsdf, w_bsdf, ev_bsdf, rng):
        """One-sample mixture (Veach 1997 ch. 9), weight f cos / (mixture pdf).

        Black paint: BSDF sampling; a cone about -z that holds the field (directions the primary then
        images onto the detector); the same cone about -x (from the focuser side toward the diagonal:
        the detector sees the focuser's surroundings in the diagonal's reflection in the primary, the
        collimation view); with a corrector, uniform area sampling of its first lens and of the
        *virtual detector* (the detector imaged back by the corrector into the bare focal plane).

        Mirrors, with a corrector only: BSDF sampling (specular peak or microroughness lobe) mixed with
        the virtual detector (share ``a_v``). Without lenses a lobe vertex is joined to the detector by the
        straight connection; through the corrector no straight connection exists, and the diagonal's lobe
        scatter of the focused beam (primary(spec) -> diagonal(scatter) -> lenses -> detector) was found
        only when the narrow lobe happened to point into the lenses 10 degrees off its peak: rare hits
        of weight ~90 x (lobe albedo / lobe probability), the fireflies of the corrector design. The
        delta peak keeps weight w / (1 - a_v) (no other strategy draws it)."""
        import drjit as dr

        mi, L = self.mi, self.layout
        paint = live & (kind == BLACK)
        if self.lens_disk is None:
            a_b, a_z, a_x, a_d, a_v = 0.4, 0.3, 0.3, 0.0, 0.0
        else:
            a_b, a_z, a_x, a_d, a_v = 0.3, 0.2, 0.2, 0.1, 0.2
        u = rng.next_float32()
        s2 = mi.Point2f(rng.next_float32(), rng.next_float32())
        local = mi.warp.square_to_uniform_cone(s2, self.cone_cos)
        wo_z = mi.Vector3f(local.x, local.y, -local.z)              # about -z
        wo_x = mi.Vector3f(-local.z, local.x, local.y)              # about -x
        wo = dr.select(u < a_z, wo_z, dr.select(u < a_z + a_x, wo_x, wo_bsdf))
        if self.lens_disk is not None:
            xl, rl = self._lens_target(si.p)
            rr = rl * dr.sqrt(s2.x)
            sp, cp = dr.sincos(2.0 * dr.pi * s2.y)
            ql = mi.Point3f(xl, rr * cp, L.z_axis + rr * sp)
            wo_disk = dr.normalize(ql - si.p)
            wo = dr.select((u >= a_z + a_x) & (u < a_z + a_x + a_d), wo_disk, wo)
            xv, hu, hv = self.virtual_det
            qv = mi.Point3f(xv, (2.0 * s2.y - 1.0) * hv, L.z_axis + (2.0 * s2.x - 1.0) * hu)
            wo_v = dr.normalize(qv - si.p)
            wo = dr.select((u >= a_z + a_x + a_d) & (u < a_z + a_x + a_d + a_v), wo_v, wo)
        wl = si.to_local(wo)
        f, p_b = bsdf.eval_pdf(ctx, si, wl, paint)
        f = f[0]
        cone_pdf = 1.0 / (2.0 * math.pi * (1.0 - self.cone_cos))
        pdf = (a_b * p_b + a_z * dr.select(-wo.z >= self.cone_cos, cone_pdf, 0.0)
               + a_x * dr.select(-wo.x >= self.cone_cos, cone_pdf, 0.0))
        if self.lens_disk is not None:
            pdf += a_d * self._disk_pdf(si.p, wo, xl, rl) + a_v * self._rect_pdf(si.p, wo)
        w_mix = dr.select(pdf > 0, f / pdf, 0.0)
        wo_out = dr.select(paint, wo, wo_bsdf)
        w_out = dr.select(paint, w_mix, w_bsdf)
        ev_out = dr.select(paint, mi.UInt32(EV_SCATTER), ev_bsdf)
        if self.virtual_det is not None:
            mirror = live & (kind == MIRROR)
            um = rng.next_float32()
            pick_v = um < a_v
            wo_m = dr.select(pick_v, wo_v, wo_bsdf)
            fm, pm = bsdf.eval_pdf(ctx, si, si.to_local(wo_m), mirror)
            pdf_m = a_v * self._rect_pdf(si.p, wo_m) + (1.0 - a_v) * pm
            delta = ~pick_v & (ev_bsdf != EV_SCATTER)
            w_m = dr.select(delta, w_bsdf / (1.0 - a_v), dr.select(pdf_m > 0, fm[0] / pdf_m, 0.0))
            ev_m = dr.select(pick_v, mi.UInt32(EV_SCATTER), ev_bsdf)
            wo_out = dr.select(mirror, wo_m, wo_out)
            w_out = dr.select(mirror, w_m, w_out)
            ev_out = dr.select(mirror, ev_m, ev_out)
        return wo_out, w_out, ev_out

    def _lens_target(self, p):
        """The lens disk a paint vertex aims at: the first lens from in front of the corrector; from inside
        the stack (the bore and cells between the lens groups, the lenses' ground edges) the last surface,
        through which the detector sees them."""
        import drjit as dr

        (x0, r0), (x1, r1) = self.lens_disk, (self.disk_x, self.disk_r)
        inside = p.x > x0 + 1.0
        return dr.select(inside, x1, x0), dr.select(inside, r1, r0)

    def _disk_pdf(self, p, wo, xl, rl):
        """Solid-angle pdf of uniform area sampling of the disk x = xl, radius rl (focuser axis) from p."""
        import drjit as dr

        t = (xl - p.x) / dr.select(dr.abs(wo.x) > 1e-12, wo.x, 1e-12)
        h = p + wo * t
        ins = (t > 0) & (dr.square(h.y) + dr.square(h.z - self.layout.z_axis) < rl * rl)
        return dr.select(ins, t * t / (dr.pi * rl * rl * dr.maximum(dr.abs(wo.x), 1e-12)), 0.0)

    def _rect_pdf(self, p, wo):
        """Solid-angle pdf of uniform area sampling of the virtual detector (a rectangle x = const)."""
        import drjit as dr

        xv, hu, hv = self.virtual_det
        t = (xv - p.x) / dr.select(dr.abs(wo.x) > 1e-12, wo.x, 1e-12)
        h = p + wo * t
        ins = (t > 0) & (dr.abs(h.y) < hv) & (dr.abs(h.z - self.layout.z_axis) < hu)
        return dr.select(ins, t * t / (4.0 * hu * hv * dr.maximum(dr.abs(wo.x), 1e-12)), 0.0)

    # -- one angle ---------------------------------------------------------------------------------------------
    def estimate(self, theta_deg: float, azimuth_deg: float = 0.0, rays: int = 2_000_000, seed: int = 0,
                 target_rel_err: float | None = None, collect: bool = False, hist=None) -> dict:
        """PST at one source direction: pilot runs of both classes, then the budget split by
        n_i ~ s_i / sqrt(cost_i) (or, with ``target_rel_err``, just enough rays for it, at most ``rays``).
        ``hist`` = (class B, class F) focal-plane histograms (see :func:`irradiance_map`).
        Returns a dict with pst, rel_err, the classes, rays, time and the tallies."""
        w_src = source_direction(theta_deg, azimuth_deg)
        t0 = time.perf_counter()
        if w_src[2] <= 1e-9:
            return {"pst": 0.0, "rel_err": 0.0, "pst_backward": 0.0, "pst_forward": 0.0, "rays": 0,
                    "time_s": 0.0, "casts": 0, "note": "source behind the aperture plane: no geometric path",
                    "tallies": (_Tally(), _Tally())}
        key0 = [seed, round(theta_deg * 1e4), round(azimuth_deg * 1e4) & 0xFFFFFFFF]
        n_pilot = int(min(max(rays // 32, 1 << 13), 1 << 17))
        pilot = (_Tally(), _Tally())
        self.backward(w_src, n_pilot, key0 + [0, 0], pilot[0])
        self.forward(w_src, n_pilot, key0 + [1, 0], pilot[1])
        # cost per path: ray casts (deterministic, unlike wall time, so a seed fixes the split)
        cost = [max(t.casts / t.n, 1e-3) for t in pilot]
        sig = [t.std for t in pilot]
        remaining = max(rays - 2 * n_pilot, 0)
        if target_rel_err is not None:
            mu = pilot[0].mean + pilot[1].mean
            if mu > 0:
                # least time for variance V: n_i = (s_i / sqrt(c_i)) sum_j s_j sqrt(c_j) / V
                v_target = (target_rel_err * mu) ** 2
                spread = sum(s * math.sqrt(c) for s, c in zip(sig, cost))
                need = [s / math.sqrt(c) * spread / v_target for s, c in zip(sig, cost)]
                remaining = min(remaining, sum(int(x * 1.1) + (1 << 14) for x in need))
        k = [s / math.sqrt(c) for s, c in zip(sig, cost)]
        if sum(k) == 0:
            k = [1.0, 1.0]
        # floors: a class whose pilot found light keeps a sizeable share (the forward class has rare,
        # heavy paths that a small pilot can miss); one that found none keeps a little, to look again
        floor = [0.1 if pilot[0].mean > 0 else 1 / 32, 0.25 if pilot[1].mean > 0 else 1 / 32]
        frac = [max(ki / sum(k), fl) for ki, fl in zip(k, floor)]
        frac = [f / sum(frac) for f in frac]
        n_main = [int(remaining * f) for f in frac]
        tallies = (_Tally(), _Tally())
        for cls, nm in enumerate(n_main):
            nm = max(nm, 1 << 12)
            done, b = 0, 0
            while done < nm:
                nb = min(self.batch, nm - done)
                h = hist[cls] if hist is not None else None
                if cls == 0:
                    self.backward(w_src, nb, key0 + [2, b], tallies[0], collect=collect, hist=h)
                else:
                    self.forward(w_src, nb, key0 + [3, b], tallies[1], collect=collect, hist=h)
                done += nb
                b += 1
        pst = tallies[0].mean + tallies[1].mean
        var = tallies[0].var_mean + tallies[1].var_mean
        total_rays = sum(t.n for t in pilot) + sum(t.n for t in tallies)
        return {"pst": pst, "rel_err": math.sqrt(var) / pst if pst > 0 else 0.0,
                "pst_backward": tallies[0].mean, "pst_forward": tallies[1].mean,
                "rel_err_backward": math.sqrt(tallies[0].var_mean) / pst if pst > 0 else 0.0,
                "rel_err_forward": math.sqrt(tallies[1].var_mean) / pst if pst > 0 else 0.0,
                "rays": total_rays, "rays_backward": tallies[0].n, "rays_forward": tallies[1].n,
                "time_s": time.perf_counter() - t0,
                "casts": sum(t.casts for t in pilot) + sum(t.casts for t in tallies), "tallies": tallies}


def _group_sum(codes, pids, vals) -> dict:
    """Sum ``vals`` per distinct (code, pid) pair."""
    keys = np.stack([codes.astype(np.uint64), pids.astype(np.uint64)], -1)
    uniq, inv = np.unique(keys, axis=0, return_inverse=True)
    sums = np.bincount(inv.ravel(), weights=vals, minlength=len(uniq))
    return {(int(c), int(p)): float(s) for (c, p), s in zip(uniq, sums)}


# ---- public API ------------------------------------------------------------------------------------------
_TRACERS: dict = {}


def get_tracer(design, mi, wavelength_nm: float = 550.0, **kw) -> StraylightTracer:
    """A cached :class:`StraylightTracer` (scene and BSDFs built once per design, wavelength and options)."""
    d = _as_design(design)
    key = (d.model_dump_json(), float(wavelength_nm), tuple(sorted(kw.items())), mi.variant())
    if key not in _TRACERS:
        _TRACERS.clear()                        # keep one scene in memory
        _TRACERS[key] = StraylightTracer(d, mi, wavelength_nm, **kw)
    return _TRACERS[key]


def pst_curve(design, mi, angles_deg, azimuth_deg: float = 0.0, rays: int = 2_000_000, seed: int = 0,
              wavelength_nm: float = 550.0, progress=None, target_rel_err: float | None = None) -> PSTResult:
    """Point-source transmittance, eq. (1), at each off-axis angle.

    Parameters
    ----------
    design : Design or str
        Design object, built-in name or TOML path.
    mi : module
        Mitsuba with an llvm variant set.
    angles_deg : sequence of float
        Off-axis angles theta of the collimated source [deg].
    azimuth_deg : float
        Azimuth of the source from +x, the focuser side [deg].
    rays : int
        Path budget per angle (both classes, pilot included).
    seed : int
        Root seed: the same seed gives the same numbers.
    wavelength_nm : float
        Wavelength [nm].
    progress : callable, optional
        ``progress(done, total)`` after each angle.
    target_rel_err : float, optional
        Stop an angle early once its budget is enough for this 1-sigma relative error (the amount of
        rays is fixed from the pilot, so the estimate stays unbiased).

    Returns
    -------
    PSTResult
    """
    d = _as_design(design)
    tr = get_tracer(d, mi, wavelength_nm)
    angles = np.asarray(list(angles_deg), dtype=float)
    out = {k: np.zeros(len(angles)) for k in ("pst", "rel_err", "pst_backward", "pst_forward", "rays", "time_s")}
    casts = 0
    for i, a in enumerate(angles):
        r = tr.estimate(float(a), azimuth_deg, rays, seed, target_rel_err=target_rel_err)
        for k, arr in out.items():
            arr[i] = r[k]
        casts += r["casts"]
        if progress is not None:
            progress(i + 1, len(angles))
    t = float(out["time_s"].sum())
    return PSTResult(design=d.name, azimuth_deg=float(azimuth_deg), wavelength_nm=float(wavelength_nm),
                     angle_deg=angles, pst=out["pst"], rel_err=out["rel_err"],
                     pst_backward=out["pst_backward"], pst_forward=out["pst_forward"],
                     rays=out["rays"].astype(np.int64), time_s=out["time_s"],
                     timings={"total_s": t, "ray_casts": int(casts),
                              "ray_casts_per_s": casts / t if t > 0 else 0.0})


def forward_plain(design, mi, angle_deg: float, azimuth_deg: float = 0.0, rays: int = 4_000_000, seed: int = 0,
                  wavelength_nm: float = 550.0) -> dict:
    """Plain forward Monte Carlo PST (rays uniform over the front opening, BSDF sampling, power counted
    where it lands on the detector): the reference the variance-reduced estimator is checked against."""
    tr = get_tracer(design, mi, wavelength_nm)
    w = source_direction(angle_deg, azimuth_deg)
    tally = _Tally()
    done, b = 0, 0
    while done < rays:
        nb = min(tr.batch, rays - done)
        tr.forward(w, nb, [seed, round(angle_deg * 1e4), 7, b], tally, plain=True)
        done += nb
        b += 1
    pst = tally.mean
    return {"pst": pst, "rel_err": math.sqrt(tally.var_mean) / pst if pst > 0 else float("inf"),
            "var": tally.var_mean, "rays": tally.n, "time_s": tally.time_s, "hits": tally.nonzero}


def efficiency_gain(design, mi, angle_deg: float, azimuth_deg: float = 0.0, rays: int = 2_000_000,
                    forward_rays: int = 8_000_000, seed: int = 0, wavelength_nm: float = 550.0) -> dict:
    """Variance-reduction gain at one angle: efficiency = 1 / (variance x time), ratio of the PST
    estimator of this module to plain forward Monte Carlo, both run here."""
    tr = get_tracer(design, mi, wavelength_nm)
    r = tr.estimate(angle_deg, azimuth_deg, rays, seed)
    f = forward_plain(design, mi, angle_deg, azimuth_deg, forward_rays, seed + 1, wavelength_nm)
    var_vr = (r["rel_err"] * r["pst"]) ** 2
    eff_vr = 1.0 / (var_vr * r["time_s"]) if var_vr > 0 else float("inf")
    eff_f = 1.0 / (f["var"] * f["time_s"]) if f["var"] > 0 else 0.0
    return {"angle_deg": angle_deg, "pst": r["pst"], "rel_err": r["rel_err"], "time_s": r["time_s"],
            "rays": r["rays"], "forward_pst": f["pst"], "forward_rel_err": f["rel_err"],
            "forward_time_s": f["time_s"], "forward_rays": f["rays"], "forward_hits": f["hits"],
            "gain": eff_vr / eff_f if eff_f > 0 else float("inf"),
            "agreement_sigma": abs(r["pst"] - f["pst"]) / math.sqrt(var_vr + f["var"])
            if var_vr + f["var"] > 0 else 0.0}


def irradiance_map(design, mi, angle_deg: float, azimuth_deg: float = 0.0, rays: int = 4_000_000,
                   bins=(64, 48), seed: int = 0, wavelength_nm: float = 550.0):
    """Straylight irradiance over the focal plane, ``E(u, v) / E_in`` [1], from the same estimator.

    Returns ``(map, extent)``: ``map[j, i]`` is the mean of E/E_in over the bin (u_i, v_j) (shape
    (nv, nu), rows along v = y, columns along u, the focal-plane coordinates of :mod:`optics.layout`);
    the mean of the map equals the PST; ``extent = (u_min, u_max, v_min, v_max)`` [mm], as for
    ``imshow(..., origin="lower", extent=extent)``.
    """
    tr = get_tracer(design, mi, wavelength_nm)
    nu, nv = int(bins[0]), int(bins[1])
    hists = tuple({"bins": np.zeros((nv, nu)), "edges_u": np.linspace(-tr.hu, tr.hu, nu + 1),
                   "edges_v": np.linspace(-tr.hv, tr.hv, nv + 1)} for _ in range(2))
    r = tr.estimate(angle_deg, azimuth_deg, rays, seed, hist=hists)
    emap = np.zeros((nv, nu))
    for h, t in zip(hists, r["tallies"]):
        if t.n:
            emap += h["bins"] / t.n * (nu * nv)      # sum over the bin / n  x  A_det / A_bin
    return emap, (-tr.hu, tr.hu, -tr.hv, tr.hv)


def plot_pst(results: dict, path, title: str | None = None):
    """Log PST against off-axis angle with 1-sigma error bars, one curve per design; angles where the PST
    is exactly zero (no geometric path) are marked at the bottom of the plot."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.0, 4.4), dpi=110)
    floor = None
    pos = [r.pst[r.pst > 0] for r in results.values()]
    if any(len(p) for p in pos):
        floor = min(p.min() for p in pos if len(p)) / 5
    markers = "osd^v<>"
    for i, (name, r) in enumerate(results.items()):
        ok = r.pst > 0
        ax.errorbar(r.angle_deg[ok], r.pst[ok], yerr=r.pst[ok] * r.rel_err[ok], marker=markers[i % 7], ms=4,
                    capsize=2, lw=1.2, label=name)
        if floor is not None and (~ok).any():
            ax.plot(r.angle_deg[~ok], np.full((~ok).sum(), floor), marker="v", ls="none",
                    color=ax.lines[-1].get_color(), alpha=0.6,
                    label="PST = 0 (no geometric path)" if i == len(results) - 1 else None)
    ax.set_yscale("log")
    ax.set_xlabel("off-axis angle of the source theta [deg]")
    ax.set_ylabel("PST = E_det / E_in")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def path_analysis(design, mi, angle_deg: float, azimuth_deg: float = 0.0, rays: int = 2_000_000, seed: int = 0,
                  wavelength_nm: float = 550.0, top: int = 12) -> dict:
    """Which surfaces carry the straylight at one source direction (FRED/ASAP-style).

    Returns a dict with ``pst``, ``rel_err`` and

    - ``sequences``: the scatter sequences in the order the light travels, e.g.
      ``"tube(scatter)"`` or ``"primary(spec) -> focuser(scatter)"``, best first, each with its share of the
      PST (``fraction``) and its ``pst``;
    - ``illuminated``: share of the PST per surface lit directly by the source (the first surface of each
      sequence), and ``directly_lit``: share of the power entering the front that lands first on each part;
    - ``critical``: share of the detector's view (projected solid angle, over pi) in which each surface
      appears, directly or through specular reflections (the surfaces the detector sees).
    """
    tr = get_tracer(design, mi, wavelength_nm)
    r = tr.estimate(angle_deg, azimuth_deg, rays, seed, collect=True)
    tb, tf = r["tallies"]
    pst = r["pst"]
    seqs = {}
    for t in (tb, tf):
        for k, v in t.paths.items():
            seqs[k] = seqs.get(k, 0.0) + v / t.n
    illum = {}
    for t in (tb, tf):
        for k, v in t.lit.items():
            illum[k] = illum.get(k, 0.0) + v / t.n
    ranked = sorted(seqs.items(), key=lambda kv: -kv[1])
    out_seq = [{"path": k, "fraction": v / pst if pst else 0.0, "pst": v} for k, v in ranked[:top]]
    rest = sum(v for _, v in ranked[top:])
    if rest:
        out_seq.append({"path": f"(other {len(ranked) - top} sequences)", "fraction": rest / pst, "pst": rest})
    nfirst = sum(tf.first_hit.values())
    lit = {k: v / nfirst for k, v in sorted(tf.first_hit.items(), key=lambda kv: -kv[1])} if nfirst else {}
    crit = {k: v / (math.pi * tb.n) for k, v in sorted(tb.seen.items(), key=lambda kv: -kv[1])} if tb.n else {}
    return {"design": tr.design.name, "angle_deg": angle_deg, "azimuth_deg": azimuth_deg, "pst": pst,
            "rel_err": r["rel_err"], "pst_backward": r["pst_backward"], "pst_forward": r["pst_forward"],
            "rays": r["rays"], "sequences": out_seq,
            "illuminated": {k: v / pst for k, v in sorted(illum.items(), key=lambda kv: -kv[1])} if pst else {},
            "directly_lit": lit, "critical": crit}
