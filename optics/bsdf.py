"""Surface scattering models for the straylight tracer, as Mitsuba 3 BSDF plugins written in Python.

Three materials cover the telescope (the parts' material tags of :mod:`optics.meshes`):

``newtsim_black`` (black paint, two-sided)
    Either Lambertian, ``f = rho / pi``, or the ABg model (the scatter fit of FRED, ASAP and Zemax)

        f(beta - beta0) = A / (B + |beta - beta0|**g)                                              (1)

    with ``beta`` the projection of the scattered direction on the surface plane (its direction cosines
    in the tangent plane) and ``beta0`` that of the specular direction. ``A`` is clipped so that the
    total hemispherical reflectance (largest at normal incidence, see below) does not exceed the paint's
    reflectance ``rho``.

``newtsim_mirror`` (aluminised mirror, one-sided; the back is black)
    A specular reflection plus a microroughness lobe around it (Harvey-Shack / Rayleigh-Rice form):

        f_lobe = R c cos(theta_i) cos(theta_o) g_n(|beta + beta_i|),   c = (4 pi sigma / lambda)**2    (2)

    ``g_n`` is the ABg/K-correlation profile ``1 / (G_n (B + x**g))``, ``G_n`` chosen so that at normal
    incidence the lobe carries exactly ``R TIS``; at other incidences it carries
    ``a(theta_i) ~= R TIS(theta_i)``, ``TIS = (4 pi sigma cos theta_i / lambda)^2``
    (Bennett & Porteus 1961); the specular part carries ``R - a(theta_i)``, so the mirror reflects R in
    total. The cos(theta_i) cos(theta_o) factor of the Rayleigh-Rice relation (Stover, *Optical
    Scattering*, 3rd ed., ch. 4) makes (2) reciprocal.

glass
    Mitsuba's own ``dielectric`` with the glass index at the wavelength (:mod:`optics.glass`), so ghost
    reflections arise naturally; the detector is a black absorber (``diffuse`` with zero reflectance;
    the tracer stops paths there).

Why projected coordinates: ``d^2 beta = cos(theta_o) d omega``, so a BRDF that depends only on
``|beta - beta0|`` (Harvey's shift invariance, Harvey 1976; Krywonos, Harvey & Choi, JOSA A 28, 1121
(2011), doi:10.1364/JOSAA.28.001121) integrates, weighted by cos(theta_o), as a plain 2-D density on the
unit disk. Both lobes are sampled exactly that way: an isotropic radial offset around ``beta0`` drawn
from a tabulated inverse CDF (the sampler's pdf is returned exactly, piecewise constant in x^2 on 2048
bins), offsets that land outside the unit disk are evanescent and return a zero weight.

References: Breault, "Control of stray light", Handbook of Optics vol. I ch. 38 (ABg, PST); Stover,
*Optical Scattering: Measurement and Analysis*, 3rd ed., SPIE Press (2012) (Rayleigh-Rice, ABg, TIS);
Harvey, "Light-scattering characteristics of optical surfaces", PhD thesis, Univ. of Arizona (1976)
(shift-invariant scatter in direction-cosine space).

Only entry points (and the test fixture) set Mitsuba's variant; :func:`register_bsdfs` needs a module
whose variant is set and registers the plugins once per variant.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

#: Shoulder B [1] of the mirrors' microroughness lobe, the profile 1 / (B + x**g) of eq. (2) in the offset
#: x = |beta - beta0| of direction cosines: B = l**g with a shoulder at l = 0.01 (0.6 degree), typical of
#: polished and overcoated aluminium optics (Stover, Optical Scattering, 3rd ed., SPIE Press 2012, ch. 4).
#: The default of the design key ``[coatings] mirror_lobe_b``.
MIRROR_LOBE_B = 1.0e-4
#: Slope g [1] of the mirrors' microroughness lobe (Harvey log-log slope -g beyond the shoulder; -2 for
#: the K-correlation PSD of polished glass). The default of the design key ``[coatings] mirror_lobe_g``.
MIRROR_LOBE_G = 2.0
N_BINS = 2048
N_ALBEDO = 128


# ---- pure numpy: the radial profile, its table, and hemispherical integrals ------------------------------
@dataclass(frozen=True)
class RadialLobe:
    """Profile ``p(x) = 1 / (B + x**g)`` of the offset ``x = |beta - beta0|`` on the disk x <= 2.

    Tabulated in ``s = x**2`` (the area element of the disk is ``pi ds``): bin edges ``s_edges`` (uniform in
    log(s + s0), so the shoulder at ``s ~ B**(2/g)`` and the tail are both resolved), bin masses
    ``mass[k] = integral of pi p ds`` (16-point Gauss-Legendre per bin) and their sum ``total`` = G.

    Parameters
    ----------
    B : float
        Shoulder parameter [1] (``x**g`` units).
    g : float
        Slope (the Harvey log-log slope is -g).
    """

    B: float
    g: float
    s_max: float = 4.0
    n_bins: int = N_BINS

    @functools.cached_property
    def _table(self):
        B, g = self.B, self.g
        s0 = max(1e-3 * B ** (2.0 / g), 1e-14)
        h = np.linspace(math.log(s0), math.log(self.s_max + s0), self.n_bins + 1)
        s = np.exp(h) - s0
        s[0] = 0.0
        s[-1] = self.s_max
        xg, wg = np.polynomial.legendre.leggauss(16)
        a, b = s[:-1, None], s[1:, None]
        nodes = 0.5 * (b - a) * xg[None, :] + 0.5 * (a + b)
        mass = (0.5 * (b - a) * (wg[None, :] * np.pi / (B + nodes ** (g / 2)))).sum(axis=1)
        return s0, s, mass

    @property
    def s0(self) -> float:
        return self._table[0]

    @property
    def s_edges(self) -> np.ndarray:
        return self._table[1]

    @property
    def mass(self) -> np.ndarray:
        return self._table[2]

    @property
    def total(self) -> float:
        """G: integral of ``1 / (B + x**g)`` over the disk x <= 2 [1]."""
        return float(self.mass.sum())

    def integral(self, x_max: float, cos_weighted: bool = False) -> float:
        """Integral of ``1 / (B + x**g)`` over the disk x <= ``x_max`` [1]; with ``cos_weighted`` the
        integrand carries ``sqrt(1 - x**2)`` (cos theta_o at normal incidence, needs x_max <= 1)."""
        from scipy.integrate import quad

        B, g = self.B, self.g
        shoulder = B ** (2.0 / g)
        pts = [p for p in (shoulder, 10 * shoulder, 100 * shoulder) if p < x_max ** 2]
        if cos_weighted:
            def fn(s):
                return np.pi * math.sqrt(max(1.0 - s, 0.0)) / (B + s ** (g / 2))
        else:
            def fn(s):
                return np.pi / (B + s ** (g / 2))
        val, _ = quad(fn, 0.0, x_max ** 2, points=pts or None, limit=400)
        return float(val)

    @functools.cached_property
    def norm_cos(self) -> float:
        """G_n: integral of ``cos(theta_o) / (B + x**g)`` over the unit disk (normal incidence) [1].
        Normalising the mirror lobe by it makes the lobe carry exactly R TIS at normal incidence."""
        return self.integral(1.0, cos_weighted=True)

    def density(self, s):
        """Mirror-lobe profile ``1 / (G_n (B + s**(g/2)))`` [1/unit beta area] (see :attr:`norm_cos`)."""
        return 1.0 / (self.norm_cos * (self.B + np.asarray(s, float) ** (self.g / 2)))

    def mean_over_disk(self, beta0: np.ndarray, func, n_psi: int = 32) -> np.ndarray:
        """Integral over the lobe (normalised density, offsets x <= 2) of ``func(beta)`` restricted to the
        unit disk, for each centre ``beta0`` (shape (n, 2)); ``func`` takes an (..., 2) array."""
        s_mid = 0.5 * (self.s_edges[:-1] + self.s_edges[1:])
        w = self.mass / self.total
        psi = (np.arange(n_psi) + 0.5) / n_psi * 2 * np.pi
        off = np.sqrt(s_mid)[:, None, None] * np.stack([np.cos(psi), np.sin(psi)], -1)[None]
        beta0 = np.asarray(beta0, float).reshape(-1, 2)
        out = np.empty(len(beta0))
        for i0 in range(0, len(beta0), 16):
            beta = beta0[i0:i0 + 16, None, None, :] + off[None]
            inside = (beta ** 2).sum(-1) < 1.0
            val = np.where(inside, func(np.where(inside[..., None], beta, 0.0)), 0.0)
            out[i0:i0 + 16] = (val.mean(axis=2) * w).sum(axis=1)
        return out


@functools.lru_cache(maxsize=64)
def radial_lobe(b: float, g: float) -> RadialLobe:
    """Cached :class:`RadialLobe` (its table is built once per parameter pair)."""
    return RadialLobe(float(b), float(g))


def tis_normal(roughness_nm: float, wavelength_nm: float) -> float:
    """Total integrated scatter at normal incidence, ``(4 pi sigma / lambda)^2`` [1], capped at 1
    (Bennett & Porteus, JOSA 51, 123 (1961), doi:10.1364/JOSA.51.000123)."""
    return min((4 * math.pi * roughness_nm / wavelength_nm) ** 2, 1.0)


def _cos_o(beta):
    return np.sqrt(np.maximum(1.0 - (beta ** 2).sum(-1), 0.0))


@functools.lru_cache(maxsize=32)
def mirror_albedo_table(reflectance: float, roughness_nm: float, wavelength_nm: float,
                        lobe_b: float = MIRROR_LOBE_B, lobe_g: float = MIRROR_LOBE_G,
                        n: int = N_ALBEDO) -> np.ndarray:
    """Hemispherical reflectance ``a(cos theta_i)`` of the mirror's lobe (2) on ``n`` nodes of cos theta_i
    in [0, 1] [1]. Numerical quadrature in beta (radial bins of the lobe table, 64 azimuths)."""
    lobe = radial_lobe(lobe_b, lobe_g)
    c = tis_normal(roughness_nm, wavelength_nm)
    mu = np.linspace(0.0, 1.0, n)
    beta0 = np.stack([np.sqrt(1 - mu ** 2), np.zeros_like(mu)], -1)
    return reflectance * c * mu * (lobe.total / lobe.norm_cos) * lobe.mean_over_disk(beta0, _cos_o)


@functools.lru_cache(maxsize=32)
def abg_effective_a(reflectance: float, a: float, b: float, g: float) -> float:
    """ABg ``A`` clipped so that the hemispherical reflectance at normal incidence (the largest: the
    profile is radially decreasing, so the unit disk centred on its peak holds the most) is <= rho."""
    raw = a * radial_lobe(b, g).integral(1.0)
    return a if raw <= reflectance or raw == 0 else a * reflectance / raw


def abg_albedo(reflectance: float, a: float, b: float, g: float, theta_i_rad) -> np.ndarray:
    """Hemispherical reflectance of the (clipped) ABg paint at incidence ``theta_i_rad`` [1]."""
    lobe = radial_lobe(b, g)
    a_eff = abg_effective_a(reflectance, a, b, g)
    th = np.atleast_1d(np.asarray(theta_i_rad, float))
    beta0 = np.stack([np.sin(th), np.zeros_like(th)], -1)
    return a_eff * lobe.total * lobe.mean_over_disk(beta0, lambda beta: np.ones(beta.shape[:-1]))


def mirror_brdf(wi, wo, reflectance: float, roughness_nm: float, wavelength_nm: float,
                lobe_b: float = MIRROR_LOBE_B, lobe_g: float = MIRROR_LOBE_G) -> np.ndarray:
    """Scatter BRDF (2) of the mirror lobe [1/sr] for unit vectors in the local frame (z = normal),
    ``wi`` toward the source, ``wo`` toward the viewer (numpy; the delta peak excluded)."""
    wi, wo = np.asarray(wi, float), np.asarray(wo, float)
    lobe = radial_lobe(lobe_b, lobe_g)
    c = tis_normal(roughness_nm, wavelength_nm)
    s = ((wo[..., :2] + wi[..., :2]) ** 2).sum(-1)
    ok = (wi[..., 2] > 0) & (wo[..., 2] > 0)
    return np.where(ok, reflectance * c * wi[..., 2] * wo[..., 2] * lobe.density(s), 0.0)


def abg_brdf(wi, wo, reflectance: float, a: float, b: float, g: float) -> np.ndarray:
    """ABg paint BRDF (1) [1/sr] with the clipped A (numpy, two-sided)."""
    wi, wo = np.asarray(wi, float), np.asarray(wo, float)
    a_eff = abg_effective_a(reflectance, a, b, g)
    s = ((wo[..., :2] + wi[..., :2]) ** 2).sum(-1)
    ok = wi[..., 2] * wo[..., 2] > 0
    return np.where(ok, a_eff / (b + s ** (g / 2)), 0.0)


# ---- Mitsuba plugins ----------------------------------------------------------------------------------------
_CLASSES: dict[str, tuple] = {}


def _plugin_classes(mi):
    """The two BSDF classes for the current variant (``mi.BSDF`` depends on it)."""
    key = mi.variant()
    if key in _CLASSES:
        return _CLASSES[key]
    import drjit as dr

    class _Lobe:
        """drjit side of a :class:`RadialLobe`: sample an offset, and its exact pdf."""

        def __init__(self, lobe: RadialLobe):
            self.lobe = lobe
            self.B = float(lobe.B)
            self.g = float(lobe.g)
            self.inv_norm = 1.0 / lobe.norm_cos
            s = lobe.s_edges
            self.h0 = math.log(lobe.s0)
            self.dh = (math.log(lobe.s_max + lobe.s0) - self.h0) / lobe.n_bins
            self.log_s0 = math.log(lobe.s0)
            self.s_lo = mi.Float(s[:-1].astype(np.float32))
            self.ds = mi.Float(np.diff(s).astype(np.float32))
            p = lobe.mass / lobe.total
            self.dens = mi.Float((p / (np.pi * np.diff(s))).astype(np.float32))   # density per beta area
            self.distr = mi.DiscreteDistribution(mi.Float(p.astype(np.float32)))
            self.n = lobe.n_bins

        def sample(self, u1, u2, active):
            idx, ure, _ = self.distr.sample_reuse_pmf(u1, active)
            s = dr.gather(mi.Float, self.s_lo, idx, active) + ure * dr.gather(mi.Float, self.ds, idx, active)
            x = dr.sqrt(dr.maximum(s, 0.0))
            sp, cp = dr.sincos(2.0 * dr.pi * u2)
            return x * cp, x * sp, dr.gather(mi.Float, self.dens, idx, active)

        def pdf(self, s, active):
            """Sampler density on the beta plane at squared offset ``s``."""
            k = mi.Int32(dr.floor((dr.log(s + self.lobe.s0) - self.h0) / self.dh))
            k = mi.UInt32(dr.clip(k, 0, self.n - 1))
            return dr.select(active & (s <= self.lobe.s_max), dr.gather(mi.Float, self.dens, k, active), 0.0)

        def profile(self, s):
            """Mirror-lobe profile ``1 / (G_n (B + s**(g/2)))`` (:attr:`RadialLobe.norm_cos`)."""
            return self.inv_norm / (self.B + dr.power(dr.maximum(s, 0.0), self.g * 0.5))

    def _flip(v, flip):
        return mi.Vector3f(v.x, v.y, dr.select(flip, -v.z, v.z))

    class _Plugin(mi.BSDF):
        """What both plugins share: eval_pdf from eval and pdf; no differentiable parameters."""

        def eval_pdf(self, ctx, si, wo, active=True):
            return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

        def traverse(self, callback):
            pass

        def parameters_changed(self, keys):
            pass

    class BlackPaint(_Plugin):
        """Two-sided black paint: Lambertian (``model='lambertian'``, ``reflectance``) or ABg
        (``model='abg'``, ``abg_a``, ``abg_b``, ``abg_g`` with A clipped to keep the albedo <= reflectance)."""

        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            self.model = str(props.get("model", "lambertian"))
            self.rho = float(props.get("reflectance", 0.04))
            if self.model not in ("lambertian", "abg"):
                raise ValueError(f"newtsim_black: model must be 'lambertian' or 'abg', not {self.model!r}")
            if self.model == "abg":
                a, b, g = (float(props.get(k, d)) for k, d in (("abg_a", 1e-3), ("abg_b", 1e-3), ("abg_g", 2.0)))
                self.a_eff = abg_effective_a(self.rho, a, b, g)
                self.lobe = _Lobe(radial_lobe(b, g))
                self.abg_b, self.abg_g = b, g
                flags = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide | mi.BSDFFlags.BackSide
            else:
                flags = mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide | mi.BSDFFlags.BackSide
            self.m_components = [flags]
            self.m_flags = flags

        def _enabled(self, ctx):
            t = mi.BSDFFlags.GlossyReflection if self.model == "abg" else mi.BSDFFlags.DiffuseReflection
            return ctx.is_enabled(t, 0)

        def _abg(self, wi, wo):
            s = dr.square(wo.x + wi.x) + dr.square(wo.y + wi.y)
            return self.a_eff / (self.abg_b + dr.power(s, self.abg_g * 0.5))

        def sample(self, ctx, si, sample1, sample2, active=True):
            flip = mi.Frame3f.cos_theta(si.wi) < 0
            wi = _flip(si.wi, flip)
            bs = dr.zeros(mi.BSDFSample3f)
            if not self._enabled(ctx):
                return bs, mi.Spectrum(0.0)
            if self.model == "lambertian":
                wo = mi.warp.square_to_cosine_hemisphere(sample2)
                pdf = mi.warp.square_to_cosine_hemisphere_pdf(wo)
                weight = mi.Float(self.rho)
                bs.sampled_type = mi.UInt32(+mi.BSDFFlags.DiffuseReflection)
            else:
                dx, dy, p_beta = self.lobe.sample(sample1, sample2.x, active)
                bx, by = dx - wi.x, dy - wi.y
                b2 = bx * bx + by * by
                ok = b2 < 1.0
                cos_o = dr.safe_sqrt(1.0 - b2)
                wo = mi.Vector3f(bx, by, cos_o)
                pdf = dr.select(ok, p_beta * cos_o, 0.0)
                weight = dr.select(ok & (p_beta > 0), self._abg(wi, wo) / p_beta, 0.0)
                bs.sampled_type = mi.UInt32(+mi.BSDFFlags.GlossyReflection)
            valid = active & (mi.Frame3f.cos_theta(wi) > 0) & (pdf > 0)
            bs.wo = _flip(wo, flip)
            bs.pdf = dr.select(valid, pdf, 0.0)
            bs.eta = 1.0
            bs.sampled_component = mi.UInt32(0)
            return bs, mi.Spectrum(dr.select(valid, weight, 0.0))

        def eval(self, ctx, si, wo, active=True):
            if not self._enabled(ctx):
                return mi.Spectrum(0.0)
            flip = mi.Frame3f.cos_theta(si.wi) < 0
            wi, wo = _flip(si.wi, flip), _flip(wo, flip)
            ok = active & (wi.z > 0) & (wo.z > 0)
            f = self.rho / dr.pi if self.model == "lambertian" else self._abg(wi, wo)
            return mi.Spectrum(dr.select(ok, f * wo.z, 0.0))

        def pdf(self, ctx, si, wo, active=True):
            if not self._enabled(ctx):
                return mi.Float(0.0)
            flip = mi.Frame3f.cos_theta(si.wi) < 0
            wi, wo = _flip(si.wi, flip), _flip(wo, flip)
            ok = active & (wi.z > 0) & (wo.z > 0)
            if self.model == "lambertian":
                p = wo.z / dr.pi
            else:
                s = dr.square(wo.x + wi.x) + dr.square(wo.y + wi.y)
                p = self.lobe.pdf(s, ok) * wo.z
            return dr.select(ok, p, 0.0)

        def to_string(self):
            if self.model == "lambertian":
                return f"BlackPaint[lambertian, reflectance={self.rho}]"
            return f"BlackPaint[abg, A_eff={self.a_eff:.4g}, B={self.abg_b}, g={self.abg_g}, albedo<={self.rho}]"

    class Mirror(_Plugin):
        """One-sided mirror: delta reflection (component 0) + microroughness lobe (component 1), eq. (2).

        Properties: ``reflectance`` R, ``roughness_nm`` sigma, ``wavelength_nm`` lambda, ``lobe_b``,
        ``lobe_g`` (profile), ``lobe_min_prob`` (lower bound of the probability of sampling the lobe;
        the default, 0, samples it with probability ~ TIS; raising it explores scatter paths more often
        without changing expectations)."""

        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            self.R = float(props.get("reflectance", 0.92))
            self.sigma = float(props.get("roughness_nm", 2.0))
            self.lam = float(props.get("wavelength_nm", 550.0))
            self.lobe_b = float(props.get("lobe_b", MIRROR_LOBE_B))
            self.lobe_g = float(props.get("lobe_g", MIRROR_LOBE_G))
            self.p_min = float(props.get("lobe_min_prob", 0.0))
            self.c = tis_normal(self.sigma, self.lam)
            self.lobe = _Lobe(radial_lobe(self.lobe_b, self.lobe_g))
            alb = mirror_albedo_table(self.R, self.sigma, self.lam, self.lobe_b, self.lobe_g)
            self.albedo = mi.Float(alb.astype(np.float32))
            self.n_alb = len(alb)
            spec = mi.BSDFFlags.DeltaReflection | mi.BSDFFlags.FrontSide
            glossy = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide
            self.m_components = [spec, glossy]
            self.m_flags = spec | glossy

        def lobe_albedo(self, cos_i):
            """Hemispherical reflectance of the lobe at cos(theta_i) (linear interpolation of the table)."""
            x = dr.clip(cos_i, 0.0, 1.0) * (self.n_alb - 1)
            k = mi.UInt32(dr.clip(dr.floor(x), 0, self.n_alb - 2))
            t = x - mi.Float(k)
            return dr.lerp(dr.gather(mi.Float, self.albedo, k), dr.gather(mi.Float, self.albedo, k + 1), t)

        def _lobe_prob(self, ctx, cos_i):
            has_spec = ctx.is_enabled(mi.BSDFFlags.DeltaReflection, 0)
            has_lobe = ctx.is_enabled(mi.BSDFFlags.GlossyReflection, 1) and self.c > 0
            if not has_lobe:
                return None if not has_spec else mi.Float(0.0)
            if not has_spec:
                return mi.Float(1.0)
            return dr.clip(self.c * cos_i * cos_i, self.p_min, 1.0)

        def _f_lobe(self, wi, wo):
            s = dr.square(wo.x + wi.x) + dr.square(wo.y + wi.y)
            return self.R * self.c * wi.z * wo.z * self.lobe.profile(s)

        def sample(self, ctx, si, sample1, sample2, active=True):
            wi = si.wi
            cos_i = mi.Frame3f.cos_theta(wi)
            active = active & (cos_i > 0)
            bs = dr.zeros(mi.BSDFSample3f)
            p_lobe = self._lobe_prob(ctx, cos_i)
            if p_lobe is None:
                return bs, mi.Spectrum(0.0)
            pick_lobe = sample1 < p_lobe
            # lobe: reuse sample1 rescaled to [0, 1)
            u1 = dr.select(pick_lobe, sample1 / dr.maximum(p_lobe, 1e-30),
                           (sample1 - p_lobe) / dr.maximum(1.0 - p_lobe, 1e-30))
            u1 = dr.clip(u1, 0.0, 0.99999994)
            dx, dy, p_beta = self.lobe.sample(u1, sample2.x, active & pick_lobe)
            bx, by = dx - wi.x, dy - wi.y
            b2 = bx * bx + by * by
            cos_o = dr.safe_sqrt(1.0 - b2)
            wo_lobe = mi.Vector3f(bx, by, cos_o)
            lobe_ok = (b2 < 1.0) & (p_beta > 0)
            pdf_lobe = p_lobe * p_beta * cos_o
            w_lobe = dr.select(lobe_ok, self._f_lobe(wi, wo_lobe) / dr.maximum(p_lobe * p_beta, 1e-30), 0.0)
            # specular
            wo_spec = mi.Vector3f(-wi.x, -wi.y, wi.z)
            spec_amp = self.R - self.lobe_albedo(cos_i)     # the lobe's energy leaves the peak
            w_spec = spec_amp / dr.maximum(1.0 - p_lobe, 1e-30)
            bs.wo = dr.select(pick_lobe, wo_lobe, wo_spec)
            bs.pdf = dr.select(pick_lobe, dr.select(lobe_ok, pdf_lobe, 0.0), 1.0 - p_lobe)
            bs.eta = 1.0
            bs.sampled_type = dr.select(pick_lobe, mi.UInt32(+mi.BSDFFlags.GlossyReflection),
                                        mi.UInt32(+mi.BSDFFlags.DeltaReflection))
            bs.sampled_component = dr.select(pick_lobe, mi.UInt32(1), mi.UInt32(0))
            weight = dr.select(pick_lobe, w_lobe, w_spec)
            valid = active & (bs.pdf > 0)
            return bs, mi.Spectrum(dr.select(valid, weight, 0.0))

        def eval(self, ctx, si, wo, active=True):
            if not (ctx.is_enabled(mi.BSDFFlags.GlossyReflection, 1) and self.c > 0):
                return mi.Spectrum(0.0)
            wi = si.wi
            ok = active & (wi.z > 0) & (wo.z > 0)
            return mi.Spectrum(dr.select(ok, self._f_lobe(wi, wo) * wo.z, 0.0))

        def pdf(self, ctx, si, wo, active=True):
            wi = si.wi
            p_lobe = self._lobe_prob(ctx, mi.Frame3f.cos_theta(wi))
            if p_lobe is None or not ctx.is_enabled(mi.BSDFFlags.GlossyReflection, 1):
                return mi.Float(0.0)
            ok = active & (wi.z > 0) & (wo.z > 0)
            s = dr.square(wo.x + wi.x) + dr.square(wo.y + wi.y)
            return dr.select(ok, p_lobe * self.lobe.pdf(s, ok) * wo.z, 0.0)

        def to_string(self):
            return (f"Mirror[R={self.R}, sigma={self.sigma} nm, lambda={self.lam} nm, TIS0={self.c:.3g}, "
                    f"lobe B={self.lobe_b}, g={self.lobe_g}]")

    _CLASSES[key] = (BlackPaint, Mirror)
    return _CLASSES[key]


_REGISTERED: set[str] = set()


def register_bsdfs(mi) -> None:
    """Register ``newtsim_black`` and ``newtsim_mirror`` with Mitsuba (idempotent, once per variant)."""
    key = mi.variant()
    if key is None:
        raise RuntimeError("register_bsdfs: set a Mitsuba variant first (optics.llvm.init_mitsuba)")
    if key in _REGISTERED:
        return
    black, mirror = _plugin_classes(mi)
    mi.register_bsdf("newtsim_black", lambda props: black(props))
    mi.register_bsdf("newtsim_mirror", lambda props: mirror(props))
    _REGISTERED.add(key)


def black_dict(coatings) -> dict:
    """``mi.load_dict`` description of the design's black paint (``coatings`` of a Design)."""
    d = {"type": "newtsim_black", "model": coatings.black_model, "reflectance": float(coatings.black_reflectance)}
    if coatings.black_model == "abg":
        d.update(abg_a=float(coatings.abg_a), abg_b=float(coatings.abg_b), abg_g=float(coatings.abg_g))
    return d


def mirror_dict(coatings, wavelength_nm: float, lobe_min_prob: float = 0.0) -> dict:
    """``mi.load_dict`` description of the design's mirror coating at ``wavelength_nm`` [nm]."""
    return {"type": "newtsim_mirror", "reflectance": float(coatings.mirror_reflectance),
            "roughness_nm": float(coatings.mirror_roughness_nm), "wavelength_nm": float(wavelength_nm),
            "lobe_b": float(coatings.mirror_lobe_b), "lobe_g": float(coatings.mirror_lobe_g),
            "lobe_min_prob": float(lobe_min_prob)}


def lens_surface_dict(n_before: float, n_after: float, ar_reflectance: float | None) -> dict:
    """``mi.load_dict`` description of one corrector surface: Mitsuba's ``dielectric`` (exterior = the
    medium before it), with an anti-reflection coating of reflectance ``ar_reflectance`` at normal
    incidence on a glass-air surface (``None``: bare glass).

    The coating scales the Fresnel reflectance F(theta) and transmittance 1 - F(theta) by R_AR / F(0)
    and (1 - R_AR) / (1 - F(0)) (the dielectric's ``specular_reflectance`` and ``specular_transmittance``
    factors), F(0) = ((n1 - n2) / (n1 + n2))^2: exact at normal incidence, energy-conserving to
    (R_AR - F(0)) (F(theta) - F(0)) / (F(0) (1 - F(0))), -0.4 % at the 36 degrees of art's steepest
    incidence, and the same R_AR that :class:`optics.sequential.SequentialTracer` takes off each
    surface's throughput. Glass-glass (cemented) surfaces keep their small Fresnel reflectance."""
    d = {"type": "dielectric", "int_ior": float(n_after), "ext_ior": float(n_before)}
    f0 = ((n_before - n_after) / (n_before + n_after)) ** 2
    if ar_reflectance is not None and 1.0 in (n_before, n_after) and f0 > 0:
        d["specular_reflectance"] = float(ar_reflectance / f0)
        d["specular_transmittance"] = float((1.0 - ar_reflectance) / (1.0 - f0))
    return d


def make_bsdfs(mi, design, parts, wavelength_nm: float = 550.0, lobe_min_prob: float = 0.0) -> dict:
    """BSDF objects for :func:`optics.mitsuba_scene.build_scene`: by material tag (``black``, ``mirror``,
    ``detector``) and, for each corrector surface, by part name (a ``dielectric`` whose exterior, the side
    the analytic normals point to (-x), is the medium before the surface)."""
    from .glass import index

    register_bsdfs(mi)
    c = design.coatings
    out = {"black": mi.load_dict(black_dict(c)),
           "mirror": mi.load_dict(mirror_dict(c, wavelength_nm, lobe_min_prob)),
           "detector": mi.load_dict({"type": "diffuse", "reflectance": {"type": "uniform", "value": 0.0}})}
    ar = design.corrector.ar_reflectance if design.corrector.coated else None
    for p in parts:
        if p.material == "glass":
            n_before = float(index(p.meta.get("before", "air"), wavelength_nm))
            n_after = float(index(p.meta.get("after", "air"), wavelength_nm))
            out[p.name] = mi.load_dict(lens_surface_dict(n_before, n_after, ar))
    return out
