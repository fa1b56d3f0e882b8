"""Straylight (PST): the variance-reduced estimator against plain forward Monte Carlo and physical laws."""

import math
import os
import re
from pathlib import Path

import numpy as np
import pytest
import tomllib

from optics import load_design
from optics.design import BUILTIN, Design
from optics.straylight import (
    PSTResult,
    forward_plain,
    get_tracer,
    irradiance_map,
    path_analysis,
    plot_pst,
    pst_curve,
)


def _variant(name: str, base: str = "art", **coatings) -> Design:
    data = load_design(base).model_dump()
    data["name"] = name
    data["coatings"].update(coatings)
    return Design.model_validate(data)


def _with_corrector(base: str = "art") -> Design:
    data = load_design(base).model_dump()
    data["name"] = "art_test_corrector"
    data["corrector"] = {"enabled": True, "back_focus_mm": 30.0, "ar_reflectance": "uncoated", "surfaces": [
        {"radius_mm": 150.0, "thickness_mm": 8.0, "material": "N-BK7", "semi_diameter_mm": 40.0},
        {"radius_mm": -400.0, "thickness_mm": 20.0, "material": "air", "semi_diameter_mm": 40.0},
        {"radius_mm": -200.0, "thickness_mm": 5.0, "material": "N-F2", "semi_diameter_mm": 38.0},
        {"radius_mm": 0.0, "thickness_mm": 0.0, "material": "air", "semi_diameter_mm": 38.0}]}
    return Design.model_validate(data)


def _diff_sigma(a, b):
    return abs(a["pst"] - b["pst"]) / math.hypot(a["pst"] * a["rel_err"], b["pst"] * b["rel_err"])


#: a path label's tail of refractions through the corrector (art's light reaches the detector that way)
LENS_TAIL = r"( -> lens_surface_\d\(refr\))*"


def _pst_of(pa, pattern: str) -> float:
    """Summed PST of the path-analysis sequences whose label matches ``pattern`` (whole label)."""
    return sum(s["pst"] for s in pa["sequences"] if re.fullmatch(pattern, s["path"]))


# ---- the estimator is unbiased: agreement with plain forward Monte Carlo -----------------------------------------
@pytest.mark.parametrize("base, min_gain", [("bare", 20.0), ("art", 1.5)])
def test_agrees_with_plain_forward_monte_carlo(mi, base, min_gain):
    """A rough mirror (20 nm, TIS 21 %) and a bright paint (50 %) make plain forward tracing converge; at
    10 degrees the primary is lit (mirror scatter, class B), its focused beam falls on paint (class F),
    the tube wall is lit: all path classes take part. The variance reduction gains ~100x without a
    corrector; with art's corrector a forward path that scatters in front of the lenses cannot be joined
    to the detector by a straight connection through glass, so it gains only a few times."""
    bright = _variant("bright", base=base, mirror_roughness_nm=20.0, black_reflectance=0.5)
    get_tracer(bright, mi).estimate(10.0, 0.0, rays=1 << 14, seed=9)         # compile the kernels first:
    forward_plain(bright, mi, 10.0, 0.0, rays=1 << 14, seed=9)               # the gain compares run times
    vr = get_tracer(bright, mi).estimate(10.0, 0.0, rays=1 << 19, seed=1)
    fw = forward_plain(bright, mi, 10.0, 0.0, rays=3_000_000, seed=2)
    assert vr["pst_backward"] > 0 and vr["pst_forward"] > 0
    assert _diff_sigma(vr, fw) < 3.0
    assert vr["pst"] == pytest.approx(fw["pst"], rel=0.15 if base == "art" else 0.08)
    gain = (fw["rel_err"] ** 2 * fw["time_s"]) / (vr["rel_err"] ** 2 * vr["time_s"])
    assert gain > min_gain


def test_direct_view_of_the_source_through_the_focuser(mi):
    """Without a corrector (bare: a short 90 mm focuser), a source on the side opposite to the focuser
    (azimuth 180) at 52 degrees shines straight down the focuser onto the detector: the zero-bounce term
    carries it and forward tracing agrees. In art the corrector's stack fills a 0.26 m long bore and only
    passes light within a few degrees of its axis: no path without a scatter reaches the detector (all
    of the far smaller PST is scattered light)."""
    pa = path_analysis("bare", mi, 52.0, 180.0, rays=1 << 18, seed=0)
    direct = {s["path"]: s["fraction"] for s in pa["sequences"]}.get("direct", 0.0)
    assert direct > 0.9
    assert pa["pst"] > 1e-2
    fw = forward_plain("bare", mi, 52.0, 180.0, rays=1_000_000, seed=3)
    assert _diff_sigma(pa, fw) < 3.0
    corrected = path_analysis("art", mi, 52.0, 180.0, rays=1 << 18, seed=0, top=100)
    assert all("(scatter)" in s["path"] for s in corrected["sequences"] if not s["path"].startswith("(other"))
    assert corrected["pst"] < 1e-3 * pa["pst"]


# ---- physics --------------------------------------------------------------------------------------------------------
def test_vanes_lower_pst_where_the_tube_wall_is_lit(mi):
    """At 45 degrees the straylight is the lit tube wall seen through the focuser and the corrector; the
    vanes shade part of it."""
    with_v = get_tracer("art", mi).estimate(45.0, rays=1 << 20, seed=0)
    without = get_tracer("art_no_vanes", mi).estimate(45.0, rays=1 << 20, seed=0)
    assert with_v["pst"] < 0.8 * without["pst"]
    assert (without["pst"] - with_v["pst"]) > 5 * math.hypot(with_v["pst"] * with_v["rel_err"],
                                                            without["pst"] * without["rel_err"])


def test_pst_scales_with_paint_reflectance(mi):
    """At 45 degrees the light reaching the detector scattered off the Lambertian paint once (tube ->
    corrector: ~90 %) or twice (tube -> tube, tube -> focuser, ...): PST = a rho + b rho^2. So the
    single-scatter part of 6 % paint is three times that of 2 % paint, the double-scatter part nine
    times, and the total in between."""
    def parts(rho):
        pa = path_analysis(_variant(f"paint{rho}", black_reflectance=rho), mi, 45.0, rays=1 << 18, seed=4, top=400)
        assert not pa["sequences"][-1]["path"].startswith("(other")
        n_paint = [len(re.findall(r"(?<!primary)(?<!diagonal)\(scatter\)", s["path"])) for s in pa["sequences"]]
        one = sum(s["pst"] for s, k in zip(pa["sequences"], n_paint, strict=True) if k == 1)
        two = sum(s["pst"] for s, k in zip(pa["sequences"], n_paint, strict=True) if k == 2)
        return pa["pst"], one, two

    lo, hi = parts(0.02), parts(0.06)
    assert hi[1] / lo[1] == pytest.approx(3.0, rel=0.05)
    assert hi[2] / lo[2] == pytest.approx(9.0, rel=0.25)
    # the total follows a rho + b rho^2 with b / a from the 2 % run's own split
    b_over_a = lo[2] / lo[1] / 0.02
    assert hi[0] / lo[0] == pytest.approx(3.0 * (1 + 0.06 * b_over_a) / (1 + 0.02 * b_over_a), rel=0.05)
    assert hi[0] / lo[0] > 3.0


def test_first_order_primary_scatter_estimate(mi):
    """Where the primary is directly lit, its scatter seen through the diagonal and the corrector is
    PST ~ BRDF(theta) cos(theta) pi / (4 N^2) x R_diagonal x T_corrector x (lit fraction of the primary),
    N = EFL / D the image-side f-number, T = (1 - R_AR)^8 of the coated lens surfaces, BRDF of the mirror
    lobe from the source toward the focus."""
    from optics.bsdf import mirror_brdf
    from optics.distortion import image_positions
    from optics.sequential import SequentialTracer

    d = load_design("art")
    theta = 5.0
    pa = path_analysis(d, mi, theta, rays=1 << 19, seed=2, top=100)
    mc = _pst_of(pa, r"primary\(scatter\) -> diagonal\(spec\)" + LENS_TAIL)
    t = math.radians(theta)
    c = d.coatings
    brdf = float(mirror_brdf(np.array([math.sin(t), 0.0, math.cos(t)]), np.array([0.0, 0.0, 1.0]),
                             c.mirror_reflectance, c.mirror_roughness_nm, 550.0, c.mirror_lobe_b, c.mirror_lobe_g))
    # behind the corrector the cone toward the primary has the f-number EFL / D (sine condition, on axis);
    # the effective focal length from the chief ray of a small field
    efl = -image_positions(SequentialTracer(d, mi), [(0.0, 0.05)])[0, 1] / math.tan(math.radians(0.05))
    n = efl / d.primary.diameter_mm
    t_lens = (1 - d.corrector.ar_reflectance) ** len(d.corrector.surfaces)
    r = d.primary.diameter_mm / 2
    lit = pa["directly_lit"]["primary"] / (r * r / d.tube.inner_diameter_mm ** 2 * 4)   # of the primary's area
    estimate = brdf * math.cos(t) * math.pi / (4 * n * n) * c.mirror_reflectance * t_lens * lit
    assert 0.3 < lit < 1.0
    assert mc == pytest.approx(estimate, rel=0.1)


def test_error_bars_shrink_as_one_over_sqrt_n(mi):
    tr = get_tracer("art", mi)
    small = tr.estimate(30.0, rays=1 << 17, seed=5)
    big = tr.estimate(30.0, rays=1 << 19, seed=6)
    n_small = small["rays_backward"] + small["rays_forward"]
    n_big = big["rays_backward"] + big["rays_forward"]
    expected = math.sqrt(n_big / n_small)
    assert small["rel_err"] / big["rel_err"] == pytest.approx(expected, rel=0.2)
    assert _diff_sigma(small, big) < 4


def test_same_seed_same_numbers(mi):
    tr = get_tracer("art", mi)
    a = tr.estimate(20.0, rays=1 << 17, seed=11)
    b = tr.estimate(20.0, rays=1 << 17, seed=11)
    c = tr.estimate(20.0, rays=1 << 17, seed=12)
    assert a["pst"] == b["pst"] and a["rel_err"] == b["rel_err"]
    assert c["pst"] != a["pst"] and _diff_sigma(a, c) < 4


def test_source_behind_the_aperture_plane_gives_zero(mi):
    r = pst_curve("art", mi, [90.0, 100.0, 120.0], rays=1 << 16)
    assert np.all(r.pst == 0) and np.all(r.rel_err == 0)


# ---- maps, path analysis, API ---------------------------------------------------------------------------------------
def test_irradiance_map_averages_to_the_pst_and_shows_the_gradient(mi):
    """3 degrees: the source's image falls just off the detector's -u edge onto the focuser wall, so the
    straylight is brighter on that side."""
    rays, seed = 1 << 19, 3
    emap, extent = irradiance_map("art", mi, 3.0, 0.0, rays=rays, bins=(24, 18), seed=seed)
    r = get_tracer("art", mi).estimate(3.0, 0.0, rays=rays, seed=seed)
    assert emap.shape == (18, 24)
    hu, hv = load_design("art").focal_plane.width_mm / 2, load_design("art").focal_plane.height_mm / 2
    assert extent == pytest.approx((-hu, hu, -hv, hv))
    assert emap.mean() == pytest.approx(r["pst"], rel=1e-5)        # same paths, binned
    assert emap[:, :8].mean() > 1.3 * emap[:, -8:].mean()


def test_path_analysis_is_consistent(mi):
    pa = path_analysis("art", mi, 45.0, rays=1 << 18, seed=1, top=5)
    assert sum(s["fraction"] for s in pa["sequences"]) == pytest.approx(1.0, rel=1e-6)
    assert sum(pa["illuminated"].values()) == pytest.approx(1.0, rel=1e-6)
    assert sum(pa["directly_lit"].values()) == pytest.approx(1.0, rel=1e-6)
    # the lit tube wall, seen through the corrector (every lens surface refracts once)
    assert re.fullmatch(r"tube\(scatter\)" + LENS_TAIL, pa["sequences"][0]["path"])
    assert pa["sequences"][0]["path"].count("(refr)") == 8
    assert max(pa["illuminated"], key=pa["illuminated"].get) == "tube"
    crit = pa["critical"]
    assert all(0 <= v <= 1.0 for v in crit.values())
    # the detector sees the corrector's last surface first, the diagonal through the lenses and the
    # primary through the diagonal; the lens edges and cells, closed solids, are seen too
    assert crit["lens_surface_7"] == max(crit.values())
    assert crit["diagonal"] > crit["primary"] > 0
    assert crit["lens_edge_3"] > 0


def test_pst_curve_contract_progress_and_plot(mi, tmp_path):
    calls = []
    r = pst_curve("art", mi, [10.0, 95.0], rays=1 << 17, seed=0, progress=lambda d, t: calls.append((d, t)))
    assert isinstance(r, PSTResult)
    j = r.to_json()
    for key in ("angle_deg", "pst", "rel_err", "rays", "rays_per_s", "time_s", "timings"):
        assert key in j
    assert j["angle_deg"] == [10.0, 95.0]
    assert j["pst"][0] > 0 and j["pst"][1] == 0 and 0 < j["rel_err"][0] < 0.1
    assert calls == [(1, 2), (2, 2)]
    png = plot_pst({"art": r}, tmp_path / "pst.png")
    assert Path(png).stat().st_size > 1000


def test_corrector_lens_stack_is_traced(mi):
    """With a corrector the detector sees the world through Mitsuba dielectrics: every path refracts
    through the lenses and ghost reflections between the (uncoated) surfaces appear."""
    pa = path_analysis(_with_corrector(), mi, 30.0, rays=1 << 18, seed=0, top=40)
    paths = [s["path"] for s in pa["sequences"]]
    assert pa["pst"] > 0 and pa["rel_err"] < 0.05
    assert "lens_surface_3(refr)" in paths[0]
    assert any("lens_surface_2(spec)" in p or "lens_surface_1(spec)" in p for p in paths)


def test_no_roulette_fireflies_in_the_lens_stack(mi):
    """Russian roulette acts only off glass: with art's eight corrector surfaces counted as bounces, forward
    paths crossed the roulette depth inside the stack and hit the detector with throughput 0.05 (weight ~5
    against a mean of 4e-4), so the 12-degree point was 30-60 % uncertain. Now no class-F path is heavy."""
    tr = get_tracer("art", mi)
    w = np.array([math.sin(math.radians(12.0)), 0.0, math.cos(math.radians(12.0))])
    from optics.straylight import _Tally

    t = _Tally()
    xs = tr.forward(w, 1 << 19, [3, 12], t)
    assert t.nonzero > 1000
    assert xs.max() < 2.0                 # the fireflies weighed 5.6
    assert math.sqrt(t.var_mean) / t.mean < 0.1


def test_merged_tube_is_the_same_surface(mi):
    """merge_full_bands keeps the surface: the same rays hit the same points."""
    import drjit as dr

    from optics.layout import make_layout
    from optics.meshes import merge_full_bands, tube_grid
    from optics.mitsuba_scene import build_scene

    part = tube_grid(make_layout(load_design("art")))
    merged = merge_full_bands(part)
    assert len(merged.faces) < len(part.faces) / 5
    rng = np.random.default_rng(0)
    n = 100_000
    o = np.stack([rng.uniform(-200, 200, n), rng.uniform(-200, 200, n), rng.uniform(-50, 1000, n)], -1)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ts = []
    for p in (part, merged):
        scene = build_scene(mi, [p])
        ray = mi.Ray3f(mi.Point3f(*[mi.Float(o[:, k].astype(np.float32)) for k in range(3)]),
                       mi.Vector3f(*[mi.Float(d[:, k].astype(np.float32)) for k in range(3)]))
        si = scene.ray_intersect(ray)
        ts.append(np.where(si.is_valid().numpy(), si.t.numpy(), np.inf))
        dr.eval()
    same = np.isclose(ts[0], ts[1], rtol=0.0, atol=1e-2)            # inf == inf: both miss
    assert same.mean() > 0.9995


@pytest.mark.parametrize("variant,changes", [
    ("art_no_vanes", {("baffle", "vanes"): 0}),
    ("art_abg_paint", {("coatings", "black_model"): "abg"}),
    ("art_bright_paint", {("coatings", "black_reflectance"): 0.10}),
])
def test_design_variants_differ_from_art_only_where_intended(variant, changes):
    base = tomllib.loads((BUILTIN / "art.toml").read_text())
    var = tomllib.loads((BUILTIN / f"{variant}.toml").read_text())
    for (table, key), value in changes.items():
        assert var[table][key] == value
        var[table][key] = base[table][key]
    assert var == base, f"{variant}.toml is out of date with art.toml"


# ---- slow cross-checks (about 30 s each): run with `pytest -m slow` or NEWTSIM_SLOW=1 ----------------------------
@pytest.fixture
def slow_enabled(request):
    expr = request.config.getoption("markexpr", "") or ""
    if "slow" in expr.replace("not slow", "") or os.environ.get("NEWTSIM_SLOW"):
        return
    pytest.skip("slow cross-check: run `pytest -m slow` (or set NEWTSIM_SLOW=1)")


@pytest.mark.slow
@pytest.mark.parametrize("theta", [5.0, 30.0])
def test_art_agrees_with_plain_forward_monte_carlo(mi, slow_enabled, theta):
    vr = get_tracer("art", mi).estimate(theta, rays=1 << 20, seed=1)
    fw = forward_plain("art", mi, theta, rays=16_000_000, seed=2)
    assert _diff_sigma(vr, fw) < 3.0


@pytest.mark.slow
def test_corrector_agrees_with_plain_forward_monte_carlo(mi, slow_enabled):
    d = _with_corrector()
    vr = get_tracer(d, mi).estimate(30.0, rays=1 << 20, seed=1)
    fw = forward_plain(d, mi, 30.0, rays=12_000_000, seed=2)
    assert _diff_sigma(vr, fw) < 3.0
