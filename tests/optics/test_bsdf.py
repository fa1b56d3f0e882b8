"""Scattering models of optics.bsdf: samplers against their pdfs (chi-square), energy, reciprocity."""

import math

import numpy as np
import pytest

from optics.bsdf import (
    MIRROR_LOBE_B,
    MIRROR_LOBE_G,
    abg_albedo,
    abg_effective_a,
    make_bsdfs,
    mirror_albedo_table,
    radial_lobe,
    register_bsdfs,
    tis_normal,
)

PAINT_ABG = {"type": "newtsim_black", "model": "abg", "reflectance": 0.04, "abg_a": 1e-3, "abg_b": 1e-3,
             "abg_g": 2.0}
PAINT_LAMB = {"type": "newtsim_black", "model": "lambertian", "reflectance": 0.04}
MIRROR = {"type": "newtsim_mirror", "reflectance": 0.92, "roughness_nm": 2.0, "wavelength_nm": 550.0}


@pytest.fixture(scope="module")
def mi_b(mi):
    register_bsdfs(mi)
    return mi


def _wi(theta_deg, below=False):
    t = math.radians(theta_deg)
    return [math.sin(t), 0.0, -math.cos(t) if below else math.cos(t)]


def _si(mi, wi, n):
    import drjit as dr

    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = mi.Vector3f(*[float(c) for c in wi])
    return si


def _polar_nodes(mi, b0, r_edges, psi, xg, wg, edge_margin):
    """Gauss-Legendre nodes in the projected plane, in polar coordinates about beta0: radial bins
    ``r_edges`` clipped at the unit disk's edge r_max(psi) (less ``edge_margin``), azimuths ``psi``.
    Returns radii R and weights W (nr, npsi, k), the directions wo and their cos theta_o."""
    bdot = b0[0] * np.cos(psi) + b0[1] * np.sin(psi)
    r_max = -bdot + np.sqrt(np.maximum(bdot ** 2 - b0 @ b0 + 1.0, 0.0))
    lo = np.minimum(r_edges[:-1, None], r_max[None])
    hi = np.maximum(np.minimum(r_edges[1:, None], r_max[None] * (1 - edge_margin)), lo)
    R = 0.5 * (hi - lo)[..., None] * xg + 0.5 * (hi + lo)[..., None]
    W = 0.5 * (hi - lo)[..., None] * wg
    P = np.broadcast_to(psi[None, :, None], R.shape)
    bx, by = b0[0] + R * np.cos(P), b0[1] + R * np.sin(P)
    cz = np.sqrt(np.clip(1 - bx * bx - by * by, 1e-12, 1.0))
    wo = mi.Vector3f(mi.Float(bx.ravel().astype(np.float32)), mi.Float(by.ravel().astype(np.float32)),
                     mi.Float(cz.ravel().astype(np.float32)))
    return R, W, wo, cz


def _glossy(mi):
    return mi.BSDFContext(mi.TransportMode.Radiance, mi.BSDFFlags.GlossyReflection)


# ---- chi-square: Mitsuba's own test on the sphere (broad lobes, any incidence, both sides) -------------------
CASES = [
    ("lambertian", PAINT_LAMB, 0.0, False, False),
    ("lambertian", PAINT_LAMB, 50.0, False, False),
    ("lambertian backside", PAINT_LAMB, 30.0, True, False),
    ("abg broad", dict(PAINT_ABG, abg_b=0.05), 0.0, False, False),
    ("abg broad", dict(PAINT_ABG, abg_b=0.05), 45.0, False, False),
    ("abg broad g=1.5", dict(PAINT_ABG, abg_b=0.1, abg_g=1.5), 70.0, False, False),
    ("abg broad backside", dict(PAINT_ABG, abg_b=0.05), 40.0, True, False),
    ("mirror lobe broad", dict(MIRROR, lobe_b=0.02, lobe_g=2.0), 0.0, False, True),
    ("mirror lobe broad", dict(MIRROR, lobe_b=0.02, lobe_g=3.0), 35.0, False, True),
    ("mirror lobe broad", dict(MIRROR, lobe_b=0.05, lobe_g=2.0), 75.0, False, True),
]


@pytest.mark.parametrize("name,props,theta,below,glossy", CASES, ids=[f"{c[0]}-{c[2]:g}" for c in CASES])
def test_sampler_matches_pdf_chi2_sphere(mi_b, name, props, theta, below, glossy):
    from mitsuba.chi2 import BSDFAdapter, ChiSquareTest, SphericalDomain

    mi = mi_b
    ctx = _glossy(mi) if glossy else None
    sample_func, pdf_func = BSDFAdapter(props["type"], props, wi=_wi(theta, below), ctx=ctx)
    chi2 = ChiSquareTest(domain=SphericalDomain(), sample_func=sample_func, pdf_func=pdf_func,
                         sample_dim=3, sample_count=400_000, res=61, ires=6, seed=7)
    assert chi2.run(0.01, test_count=len(CASES), quiet=True), chi2.messages


# ---- chi-square in the projected plane for the real, narrow lobes ---------------------------------------------
def _chi2_projected(mi, bsdf, theta_deg, ctx, shoulder, n=1 << 20, seed=3):
    """Bin samples in log-radius and azimuth of beta - beta0 and compare with the pdf integrated per bin."""
    import drjit as dr
    from scipy import stats

    wi = _wi(theta_deg)
    si = _si(mi, wi, n)
    rng = mi.PCG32(n, seed)
    bs, w = bsdf.sample(ctx, si, rng.next_float32(), mi.Point2f(rng.next_float32(), rng.next_float32()))
    ok = (w[0] > 0).numpy()
    wo = np.stack([bs.wo.x.numpy(), bs.wo.y.numpy()], -1)[ok]
    off = wo + np.array(wi[:2])
    x = np.hypot(off[:, 0], off[:, 1])
    psi = np.arctan2(off[:, 1], off[:, 0])
    r_edges = np.concatenate([[0.0], np.geomspace(0.05 * shoulder, 2.0, 48)])
    p_edges = np.linspace(-np.pi, np.pi, 13)
    obs, _, _ = np.histogram2d(x, psi, bins=[r_edges, p_edges])
    # expected: integrate the pdf in the beta plane (pdf_omega / cos theta_o) over each bin, radially with
    # 8-point Gauss-Legendre up to the unit disk's edge r_max(psi), in azimuth with 64 midpoints (the edge
    # moves fast with psi when beta0 is near it)
    k, kp = 8, 64
    xg, wg = np.polynomial.legendre.leggauss(k)
    psi_mid = (p_edges[:-1, None] + np.diff(p_edges)[:, None] * ((np.arange(kp) + 0.5) / kp)[None]).ravel()
    b0 = -np.array(wi[:2])
    R, W, wo2, cz = _polar_nodes(mi, b0, r_edges, psi_mid, xg, wg, 1e-6)          # (nr, npsi, k)
    si2 = _si(mi, wi, R.size)
    pdf = bsdf.pdf(ctx, si2, wo2).numpy().reshape(R.shape) / cz
    dr.eval()
    dpsi = np.diff(p_edges)[0] / kp
    mass = (pdf * R * W).sum(-1).reshape(len(r_edges) - 1, len(p_edges) - 1, kp).sum(-1) * dpsi
    exp = mass * n
    outside_obs = n - obs.sum()
    outside_exp = n - exp.sum()
    o = np.concatenate([obs.ravel(), [outside_obs]])
    e = np.concatenate([exp.ravel(), [outside_exp]])
    # pool bins with small expectations (sorted), as Mitsuba's chi2 does
    order = np.argsort(e)
    o, e = o[order], e[order]
    po, pe, acc_o, acc_e = [], [], 0.0, 0.0
    for oi, ei in zip(o, e):
        acc_o += oi
        acc_e += ei
        if acc_e >= 5:
            po.append(acc_o)
            pe.append(acc_e)
            acc_o = acc_e = 0.0
    if acc_e > 0:
        po[-1] += acc_o
        pe[-1] += acc_e
    po, pe = np.array(po), np.array(pe)
    chi2 = float(((po - pe) ** 2 / pe).sum())
    return stats.chi2.sf(chi2, len(po) - 1)


@pytest.mark.parametrize("theta", [0.0, 20.0, 60.0])
def test_design_mirror_lobe_sampler_chi2(mi_b, theta):
    mi = mi_b
    bsdf = mi.load_dict(MIRROR)
    p = _chi2_projected(mi, bsdf, theta, _glossy(mi), shoulder=MIRROR_LOBE_B ** (1 / MIRROR_LOBE_G))
    assert p > 0.001


@pytest.mark.parametrize("theta", [0.0, 45.0, 80.0])
def test_design_abg_paint_sampler_chi2(mi_b, theta):
    mi = mi_b
    bsdf = mi.load_dict(PAINT_ABG)
    p = _chi2_projected(mi, bsdf, theta, mi.BSDFContext(), shoulder=math.sqrt(1e-3))
    assert p > 0.001


# ---- energy ---------------------------------------------------------------------------------------------------
def _albedo_by_quadrature(mi, bsdf, theta_deg, ctx, shoulder, n_r=160, n_psi=720):
    """Integral of eval (= f cos theta_o) over the hemisphere, done in the projected plane (d^2 beta =
    cos theta_o d omega) in polar coordinates about beta0: log-spaced radial bins with 8-point
    Gauss-Legendre each, clipped at the unit disk's edge r_max(psi), and ``n_psi`` azimuths."""
    wi = _wi(theta_deg)
    b0 = -np.array(wi[:2])
    edges = np.concatenate([[0.0], np.geomspace(1e-3 * shoulder, 2.0, n_r)])
    xg, wg = np.polynomial.legendre.leggauss(8)
    psi = (np.arange(n_psi) + 0.5) / n_psi * 2 * np.pi
    R, W, wo, cz = _polar_nodes(mi, b0, edges, psi, xg, wg, 1e-7)
    si = _si(mi, wi, R.size)
    f = bsdf.eval(ctx, si, wo)[0].numpy().reshape(R.shape) / cz        # f = eval / cos theta_o
    return float((f * R * W).sum() * (2 * np.pi / n_psi))


def _mean_weight(mi, bsdf, theta_deg, ctx=None, n=1 << 20, seed=1):
    ctx = ctx or mi.BSDFContext()
    si = _si(mi, _wi(theta_deg), n)
    rng = mi.PCG32(n, seed)
    bs, w = bsdf.sample(ctx, si, rng.next_float32(), mi.Point2f(rng.next_float32(), rng.next_float32()))
    w = w[0].numpy()
    return float(w.mean()), float(w.std() / math.sqrt(n)), bs, w


@pytest.mark.parametrize("theta", [0.0, 40.0, 75.0])
def test_lambertian_albedo_is_reflectance(mi_b, theta):
    mi = mi_b
    b = mi.load_dict(PAINT_LAMB)
    assert _albedo_by_quadrature(mi, b, theta, mi.BSDFContext(), shoulder=1.0, n_r=40) == \
        pytest.approx(0.04, rel=2e-3)
    _, _, _, w = _mean_weight(mi, b, theta)
    assert np.allclose(w, 0.04)


@pytest.mark.parametrize("theta", [0.0, 30.0, 60.0, 85.0])
def test_abg_albedo_bounded_by_paint_reflectance(mi_b, theta):
    mi = mi_b
    b = mi.load_dict(PAINT_ABG)
    quad = _albedo_by_quadrature(mi, b, theta, mi.BSDFContext(), shoulder=math.sqrt(1e-3))
    ref = float(abg_albedo(0.04, 1e-3, 1e-3, 2.0, math.radians(theta))[0])
    assert quad == pytest.approx(ref, rel=0.01)
    assert quad <= 0.04
    m, s, _, _ = _mean_weight(mi, b, theta)            # sampling weights average to the albedo
    assert m == pytest.approx(ref, abs=4 * s + 1e-4 * ref)


def test_abg_is_clipped_to_the_paint_reflectance(mi_b):
    """A very bright ABg fit (A = 1) is scaled down: albedo = rho at normal incidence, below elsewhere."""
    mi = mi_b
    props = dict(PAINT_ABG, abg_a=1.0)
    assert abg_effective_a(0.04, 1.0, 1e-3, 2.0) < 1.0
    b = mi.load_dict(props)
    assert _albedo_by_quadrature(mi, b, 0.0, mi.BSDFContext(), shoulder=0.03) == pytest.approx(0.04, rel=0.01)
    for th in (30.0, 70.0):
        assert _albedo_by_quadrature(mi, b, th, mi.BSDFContext(), shoulder=0.03) < 0.04


@pytest.mark.parametrize("theta", [0.0, 30.0, 60.0, 80.0])
def test_mirror_conserves_energy_and_lobe_carries_tis(mi_b, theta):
    """Specular + lobe = R exactly; the lobe carries R TIS at normal incidence, and never more than
    R (4 pi sigma / lambda)^2 cos(theta_i) (its cos theta_i cos theta_o Rayleigh-Rice bound)."""
    mi = mi_b
    b = mi.load_dict(MIRROR)
    m, s, _, _ = _mean_weight(mi, b, theta)
    assert m == pytest.approx(0.92, abs=max(4 * s, 2e-4))
    c = tis_normal(2.0, 550.0)
    lobe = _albedo_by_quadrature(mi, b, theta, _glossy(mi), shoulder=0.01)
    mu = math.cos(math.radians(theta))
    table = np.interp(mu, np.linspace(0, 1, len(mirror_albedo_table(0.92, 2.0, 550.0))),
                      mirror_albedo_table(0.92, 2.0, 550.0))
    assert lobe == pytest.approx(table, rel=0.01)
    assert lobe <= 0.92 * c * mu * 1.001
    if theta == 0.0:
        assert lobe == pytest.approx(0.92 * c, rel=0.01)
    elif theta <= 60.0:
        assert lobe == pytest.approx(0.92 * c * mu * mu, rel=0.05)     # ~ R TIS(theta_i)


@pytest.mark.parametrize("props,glossy", [(PAINT_ABG, False), (dict(MIRROR, lobe_min_prob=0.3), True),
                                          (dict(MIRROR), False)], ids=["abg", "mirror-lobe", "mirror-mixed"])
def test_sampling_weight_is_eval_over_pdf(mi_b, props, glossy):
    mi = mi_b
    b = mi.load_dict(props)
    ctx = _glossy(mi) if glossy else mi.BSDFContext()
    for theta in (10.0, 50.0):
        _, _, bs, w = _mean_weight(mi, b, theta, ctx=ctx, n=1 << 18)
        si = _si(mi, _wi(theta), 1 << 18)
        e, p = b.eval_pdf(ctx, si, bs.wo)
        e, p = e[0].numpy(), p.numpy()
        smooth = (bs.sampled_type.numpy() & int(mi.BSDFFlags.Delta)) == 0
        ok = smooth & (w > 0)
        assert ok.sum() > 40
        assert np.allclose(w[ok], e[ok] / p[ok], rtol=0.02)          # 2 %: the table's bin edges
        assert np.allclose(bs.pdf.numpy()[ok], p[ok], rtol=0.02)


# ---- reciprocity -------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("props", [PAINT_LAMB, PAINT_ABG, dict(PAINT_ABG, abg_g=1.3), MIRROR,
                                   dict(MIRROR, lobe_b=1e-3, lobe_g=2.5)],
                         ids=["lambertian", "abg", "abg-g1.3", "mirror", "mirror-g2.5"])
def test_reciprocity(mi_b, props):
    """f(wi -> wo) = f(wo -> wi) (eval returns f cos theta_o)."""
    mi = mi_b
    b = mi.load_dict(props)
    rng = np.random.default_rng(5)
    n = 4096
    u = rng.random((2, n, 2))
    vec = []
    for k in range(2):
        ct = np.sqrt(u[k, :, 0])
        st = np.sqrt(1 - ct * ct)
        ph = 2 * np.pi * u[k, :, 1]
        vec.append(np.stack([st * np.cos(ph), st * np.sin(ph), ct], -1))
    a, c = vec
    # half of the pairs near the specular configuration, where the lobes live
    c[: n // 2] = np.stack([-a[: n // 2, 0], -a[: n // 2, 1], a[: n // 2, 2]], -1) + 0.02 * rng.normal(size=(n // 2, 3))
    c[:, 2] = np.abs(c[:, 2])
    c /= np.linalg.norm(c, axis=1, keepdims=True)

    def f(wi, wo):
        si = _si(mi, [0, 0, 1], n)
        si.wi = mi.Vector3f(*[mi.Float(wi[:, j].astype(np.float32)) for j in range(3)])
        wo_ = mi.Vector3f(*[mi.Float(wo[:, j].astype(np.float32)) for j in range(3)])
        return b.eval(mi.BSDFContext(), si, wo_)[0].numpy() / wo[:, 2]

    f1, f2 = f(a, c), f(c, a)
    assert np.count_nonzero(f1) > n // 2
    assert np.allclose(f1, f2, rtol=1e-4, atol=1e-9 * f1.max())


# ---- numpy side and plumbing -----------------------------------------------------------------------------------------
def test_radial_lobe_table_matches_the_analytic_g2_integral():
    """g = 2: integral of pi / (B + s) ds over s in [0, 4] = pi ln(1 + 4/B)."""
    for b in (1e-4, 1e-3, 0.05):
        lobe = radial_lobe(b, 2.0)
        assert lobe.total == pytest.approx(math.pi * math.log(1 + 4 / b), rel=1e-6)
        assert lobe.integral(1.0) == pytest.approx(math.pi * math.log(1 + 1 / b), rel=1e-6)


def test_tis_formula():
    assert tis_normal(2.0, 550.0) == pytest.approx((4 * math.pi * 2.0 / 550.0) ** 2)
    assert tis_normal(0.0, 550.0) == 0.0
    assert tis_normal(500.0, 550.0) == 1.0


def test_register_is_idempotent_and_make_bsdfs_maps_materials(mi_b):
    from optics import load_design
    from optics.design import Design
    from optics.glass import index
    from optics.layout import make_layout
    from optics.meshes import telescope_parts

    mi = mi_b
    register_bsdfs(mi)
    register_bsdfs(mi)
    data = load_design("bare").model_dump()
    data["corrector"] = {"enabled": True, "back_focus_mm": 40.0, "surfaces": [
        {"radius_mm": 300.0, "thickness_mm": 8.0, "material": "N-BK7", "semi_diameter_mm": 40.0},
        {"radius_mm": 0.0, "thickness_mm": 0.0, "material": "air", "semi_diameter_mm": 40.0}]}
    d = Design.model_validate(data)
    parts = telescope_parts(make_layout(d))
    b = make_bsdfs(mi, d, parts, 600.0)
    assert {"black", "mirror", "detector", "lens_surface_0", "lens_surface_1"} <= set(b)
    n = index("N-BK7", 600.0)

    def eta(obj):
        return float(str(obj).split("eta =")[1].split(",")[0])

    assert eta(b["lens_surface_0"]) == pytest.approx(n, rel=1e-5)           # air -> glass
    assert eta(b["lens_surface_1"]) == pytest.approx(1 / n, rel=1e-5)       # glass -> air
    assert "Mirror[" in str(b["mirror"]) and "lambertian" in str(b["black"])


@pytest.mark.parametrize("theta_deg", [0.0, 20.0])
def test_ar_coated_lens_surface_reflects_r_ar(mi_b, theta_deg):
    """The corrector's dielectric with an AR coating (optics.bsdf.lens_surface_dict): the reflected and
    transmitted energies are R_AR and 1 - R_AR at normal incidence (the same 0.5 % the sequential tracer
    takes off each surface), and conserve energy to the stated (R_AR - F0)(F - F0)/(F0 (1 - F0)) at
    20 degrees; bare glass reflects Fresnel's F. Stratified samples, importance transport (no eta^2)."""
    from optics.bsdf import lens_surface_dict

    mi = mi_b
    n, r_ar = 1.5, 0.005
    t = math.radians(theta_deg)
    cos_t = math.sqrt(1 - (math.sin(t) / n) ** 2)
    rs = (math.cos(t) - n * cos_t) / (math.cos(t) + n * cos_t)
    rp = (n * math.cos(t) - cos_t) / (n * math.cos(t) + cos_t)
    fresnel, f0 = 0.5 * (rs * rs + rp * rp), ((n - 1) / (n + 1)) ** 2
    N = 1 << 16
    ctx = mi.BSDFContext(mi.TransportMode.Importance)
    si = _si(mi, _wi(theta_deg), N)
    u = mi.Float(((np.arange(N) + 0.5) / N).astype(np.float32))
    for coating, expect_r in ((r_ar, r_ar * fresnel / f0), (None, fresnel)):
        bsdf = mi.load_dict(lens_surface_dict(1.0, n, coating))
        bs, w = bsdf.sample(ctx, si, u, mi.Point2f(0.5, 0.5))
        w = np.asarray(w[0].numpy(), dtype=float)
        up = np.asarray(bs.wo.z.numpy()) > 0
        reflected, transmitted = w[up].sum() / N, w[~up].sum() / N
        assert reflected == pytest.approx(expect_r, rel=2e-3, abs=1e-5)
        if coating is not None:
            assert transmitted == pytest.approx((1 - fresnel) * (1 - r_ar) / (1 - f0), rel=2e-3)
            excess = (r_ar - f0) * (fresnel - f0) / (f0 * (1 - f0))
            assert reflected + transmitted == pytest.approx(1 + excess, abs=1e-4)
            if theta_deg == 0.0:
                assert reflected == pytest.approx(r_ar, rel=2e-3)
                assert transmitted == pytest.approx(1 - r_ar, rel=1e-4)
        else:
            assert reflected + transmitted == pytest.approx(1.0, abs=1e-4)
