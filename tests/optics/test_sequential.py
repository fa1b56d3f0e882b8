"""Sequential tracer: checked against geometry and first-order optics, not snapshots."""

import math

import numpy as np
import pytest

from optics import load_design
from optics.layout import make_layout
from optics.sequential import (
    DIAGONAL_MISS,
    OK,
    SequentialTracer,
    _refract,
    pupil_grid,
    pupil_uniform,
    pupil_uniform_dr,
    to_dr,
)
from optics.vignetting import two_circle_fraction


@pytest.fixture(scope="module")
def bare():
    return load_design("bare")


def test_paraboloid_on_axis_is_a_point_with_equal_paths(mi, bare):
    """A paraboloid images an on-axis star perfectly: every ray meets the focus with the same optical path."""
    tr = SequentialTracer(bare, mi, obstruct="none")
    px, py = pupil_uniform(20000, tr.layout.r_primary, seed=3)
    r = tr.trace((0.0, 0.0), px, py)
    ok = r.ok
    assert ok.mean() > 0.99
    assert np.max(np.hypot(r.u[ok], r.v[ok])) < 1e-6          # mm
    assert np.ptp(r.opl[ok]) < 1e-7                            # mm: well below 1e-4 wave


def test_on_axis_obstruction_is_secondary_plus_spider(mi, bare):
    """Fraction blocked = (d_sec/D)^2 + vanes x width x (R - r_sec) / (pi R^2) (shadows do not overlap)."""
    tr = SequentialTracer(bare, mi)
    px, py = pupil_uniform(1 << 20, tr.layout.r_primary, seed=1)
    thru = tr.count((0.0, 0.0), px, py) / len(px)
    D, m = bare.primary.diameter_mm, bare.secondary.minor_axis_mm
    sp = bare.spider
    spider = sp.vanes * sp.width_mm * (D - m) / 2 / (math.pi * D * D / 4)
    expected = 1 - (m / D) ** 2 - spider
    assert thru == pytest.approx(expected, abs=0.002)


def test_analytic_obstructions_agree_with_mitsuba_meshes(mi, bare):
    px, py = pupil_uniform(1 << 19, make_layout(bare).r_primary, seed=2)
    a = SequentialTracer(bare, mi, obstruct="analytic")
    m = SequentialTracer(bare, mi, obstruct="mesh")
    for field in [(0.0, 0.0), (0.8, -0.3), (1.2, 0.9)]:
        ra, rm = a.trace(field, px, py), m.trace(field, px, py)
        assert abs(ra.ok.mean() - rm.ok.mean()) < 0.004, field
        assert np.mean(ra.lost != rm.lost) < 0.01, field


@pytest.mark.parametrize("field_deg", [0.5, 1.0, 1.5, 2.5, 3.5])
def test_diagonal_vignetting_follows_the_two_circle_formula(mi, bare, field_deg):
    """The converging cone (radius D d / 2f) at the diagonal, centred h (1 - d/f) off axis, against the
    diagonal's projected circle (radius minor/2): overlap fraction (field along y, the untilted
    direction; no mechanical obstructions). The formula treats the 45-degree flat as a circular stop at
    one height; the real footprint spans +-70 mm in height, which costs about 2.5 % at 2.5-3.5 deg."""
    tr = SequentialTracer(bare, mi, obstruct="none")
    f, d = bare.primary.focal_length_mm, bare.secondary.distance_to_focus_mm
    D, m = bare.primary.diameter_mm, bare.secondary.minor_axis_mm
    px, py = pupil_uniform(1 << 19, D / 2, seed=4)
    r = tr.trace((0.0, field_deg), px, py)
    captured = 1 - np.mean(r.lost == DIAGONAL_MISS)
    h = f * math.tan(math.radians(field_deg))
    expected = two_circle_fraction(D * d / (2 * f), m / 2, h * (1 - d / f))
    assert captured == pytest.approx(expected, abs=0.03)


def _plate_design(bare, **corrector):
    """bare with a 10 mm N-BK7 plate (two plane surfaces) in the focuser; ``corrector`` keys added."""
    from optics.design import Design

    data = bare.model_dump()
    data["corrector"] = {"enabled": True, "back_focus_mm": 40.0, **corrector, "surfaces": [
        {"radius_mm": 0.0, "thickness_mm": 10.0, "material": "N-BK7", "semi_diameter_mm": 45.0},
        {"radius_mm": 0.0, "thickness_mm": 0.0, "material": "air", "semi_diameter_mm": 45.0}]}
    return Design.model_validate(data)


def test_plate_shifts_the_focus_by_t_times_one_minus_one_over_n(mi, bare):
    """A plane-parallel plate of thickness t and index n moves the focus away by t (1 - 1/n) (paraxial)."""
    from optics.glass import index

    t = 10.0
    tr = SequentialTracer(_plate_design(bare), mi, obstruct="none")
    px, py = pupil_grid(41, 20.0)                           # a slow paraxial sub-bundle
    keep = np.hypot(px, py) < 20
    r = tr.trace((0.0, 0.0), px[keep], py[keep], wavelength_nm=587.56)
    ok = r.ok
    # where the rays cross the axis: back along the ray from the detector plane
    s = -r.u[ok] / r.du[ok]
    shift = np.median(s * r.dw[ok])
    n = index("N-BK7", 587.56)
    assert shift == pytest.approx(t * (1 - 1 / n), rel=0.01)


def test_refraction_matches_snell_and_mitsuba_fresnel(mi):
    import drjit as dr
    from drjit.llvm.ad import Array3f64, Float64

    theta = np.radians(np.array([0.0, 10.0, 30.0, 50.0]))
    d = Array3f64(Float64(np.sin(theta)), Float64(0 * theta), Float64(-np.cos(theta)))
    n = Array3f64(Float64(0 * theta), Float64(0 * theta), Float64(1 + 0 * theta))
    t, trans, tir = _refract(d, n, 1.0, 1.5)
    sin_t = np.asarray(t.x.numpy())
    assert np.allclose(sin_t, np.sin(theta) / 1.5, atol=1e-12)
    F, *_ = mi.fresnel(mi.Float(np.cos(theta).astype(np.float32)), mi.Float(1.5))
    assert np.allclose(np.asarray(trans.numpy()), 1 - np.asarray(F.numpy()), atol=1e-6)
    _, _, tir = _refract(d, n, 1.5, 1.0)
    assert list(np.asarray(tir.numpy())) == [False, False, False, True]
    dr.eval()


def test_unknown_obstruction_mode_is_refused(mi, bare):
    with pytest.raises(ValueError, match="obstruct"):
        SequentialTracer(bare, mi, obstruct="maybe")


def test_loss_codes_are_counted(mi, bare):
    tr = SequentialTracer(bare, mi)
    px, py = pupil_uniform(4096, 200.0, seed=0)
    r = tr.trace((0.0, 0.0), px, py)
    assert set(np.unique(r.lost)) <= set(range(8))
    assert (r.lost == OK).sum() == tr.count((0.0, 0.0), px, py)


def test_pupil_points_made_by_drjit_are_numpys(mi):
    """The vignetting map's pupil points, made in drjit, are pupil_uniform's: the same float64 fractions and
    radii, the angle's cosine and sine within 1 ulp (2e-13 mm on a 200 mm radius), identical once rounded
    to float32; a chunk starting at ``start`` continues the same sequence."""
    px, py = pupil_uniform(300_000, 200.0, seed=7)
    x, y = pupil_uniform_dr(300_000, 200.0, seed=7)
    assert np.abs(x.numpy() - px).max() < 2e-13 and np.abs(y.numpy() - py).max() < 2e-13
    xs, ys = pupil_uniform_dr(300_000, 200.0, seed=7, single=True)
    assert np.array_equal(xs.numpy(), px.astype(np.float32)) and np.array_equal(ys.numpy(), py.astype(np.float32))
    xc, _ = pupil_uniform_dr(1000, 200.0, seed=7, start=123_456)
    assert np.abs(xc.numpy() - px[123_456:124_456]).max() < 2e-13


@pytest.mark.parametrize("name", ["bare", "art"])
def test_float32_counting_kernel_agrees_with_float64(mi, name):
    """loss_counts from drjit arrays (one kernel, no transfer) equals the numpy-batch path for the same
    float64 points; the float32 kernel changes the fate of at most a few rays in 10^5 that graze an edge, and
    its landing points stay within 0.5 um of float64's (module docstring, "Precision")."""
    import drjit as dr

    tr = SequentialTracer(load_design(name), mi)
    px, py = pupil_uniform(100_000, tr.layout.r_primary, seed=4)
    for field in [(0.0, 0.0), (0.9, -0.6)]:
        c64 = tr.loss_counts(field, px, py)
        assert np.array_equal(tr.loss_counts(field, to_dr(px), to_dr(py)), c64)
        c32 = tr.loss_counts(field, to_dr(px, True), to_dr(py, True), single=True)
        assert c32.sum() == c64.sum() and np.abs(c32 - c64).max() <= 3
        a = tr._trace_dr(field, px, py, 550.0)
        b = tr._trace_dr(field, px, py, 550.0, single=True)
        dr.eval(a, b)
        ok = (a["lost"].numpy() == OK) & (b["lost"].numpy() == OK)
        assert ok.sum() > 50_000
        for k in ("u", "v"):
            assert np.abs(a[k].numpy()[ok] - b[k].numpy()[ok]).max() < 5e-4      # mm


def test_fields_queued_in_one_kernel_count_as_one_by_one(mi):
    """loss_counts_fields (the vignetting map's path: every field's kernel queued, one counter array) gives
    each field's loss_counts, and fields on both sides of the axis and on it replay one compiled kernel."""
    import drjit as dr

    tr = SequentialTracer(load_design("art"), mi)
    px, py = pupil_uniform_dr(20_000, tr.layout.r_primary, seed=2, single=True)
    fields = [(0.0, 0.0), (-0.7, 0.4), (0.7, -0.4), (0.0, 1.1)]
    tr.loss_counts_fields(fields[:1], px, py, single=True)          # compile
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()
        counts = tr.loss_counts_fields(fields, px, py, single=True, sync_every=3)
        hashes = {k["hash"] for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT}
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert len(hashes) == 1
    for f, c in zip(fields, counts):
        assert np.array_equal(c, tr.loss_counts(f, px, py, single=True))
    assert np.all(counts.sum(axis=1) == 20_000)


def test_coated_and_uncoated_lens_surfaces(mi, bare):
    """Each glass-air surface transmits 1 - R_AR with its coating (0.5 % by default), or the Fresnel
    transmittance 1 - ((n - 1)/(n + 1))^2 of bare glass at (near-)normal incidence."""
    from optics.glass import index

    px, py = pupil_grid(21, 15.0)                           # a slow paraxial sub-bundle
    keep = np.hypot(px, py) < 15
    coated = SequentialTracer(_plate_design(bare), mi, obstruct="none").trace((0.0, 0.0), px[keep], py[keep])
    assert np.allclose(coated.transmission[coated.ok], 0.995 ** 2, rtol=1e-12)
    r3 = SequentialTracer(_plate_design(bare, ar_reflectance=0.03), mi, obstruct="none").trace(
        (0.0, 0.0), px[keep], py[keep])
    assert np.allclose(r3.transmission[r3.ok], 0.97 ** 2, rtol=1e-12)
    uncoated = _plate_design(bare, ar_reflectance="uncoated")
    bare_glass = SequentialTracer(uncoated, mi, obstruct="none").trace((0.0, 0.0), px[keep], py[keep],
                                                                      wavelength_nm=587.56)
    n = index("N-BK7", 587.56)
    fresnel = 1 - ((n - 1) / (n + 1)) ** 2
    assert np.allclose(bare_glass.transmission[bare_glass.ok], fresnel ** 2, rtol=2e-5)
    # the design's own number for the photometry: the same products along the axis
    assert _plate_design(bare).corrector_transmission() == pytest.approx(0.995 ** 2)
    assert uncoated.corrector_transmission(587.56) == pytest.approx(fresnel ** 2, rel=1e-12)
    assert bare.corrector_transmission() == 1.0
    assert load_design("art").corrector_transmission() == pytest.approx(0.995 ** 8)


def test_one_kernel_serves_every_wavelength_and_field(mi):
    """The glass indices and the field direction are opaque drjit values: tracing the corrected design
    at new wavelengths and fields replays the same compiled kernel (same hash), not a new one each."""
    import drjit as dr

    tr = SequentialTracer(load_design("art"), mi)
    px, py = pupil_uniform(512, tr.layout.r_primary, seed=5)
    tr.trace((0.1, 0.2), px, py, wavelength_nm=480.0)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()                                   # clear
        results = [tr.trace((0.1 * k, 0.2), px, py, wavelength_nm=lam)
                   for k, lam in enumerate((450.0, 633.0, 900.0))]
        hashes = {k["hash"] for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT}
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert len(hashes) == 1
    # ... and the indices did change: the 450 and 900 nm images of the same rays differ
    assert not np.allclose(results[0].u[results[0].ok][:50], results[2].u[results[2].ok][:50])


def test_housing_sits_behind_the_whole_lens_stack(bare):
    """The camera housing's front plate (where the focuser bore ends) lies beyond every lens vertex and
    rim and before the detector; the focuser bore starts in front of the first lens."""
    L = make_layout(load_design("art"))
    assert L.lenses
    stack_end = max(max(s.x_mm, s.x_edge_mm) for s in L.lenses)
    assert stack_end < L.x_housing < L.x_detector
    assert L.focuser_start_x < min(L.lenses[0].x_mm, L.lenses[0].x_edge_mm)
    Lb = make_layout(bare)
    assert Lb.r_tube < Lb.x_housing < Lb.x_detector


def test_lens_meshes_are_closed_solids_of_the_right_volume():
    """Each corrector lens (two caps and its edge) is a closed, watertight solid for the straylight
    tracer, with the volume of the lens: pi h^2 t_edge - V_cap(back) + V_cap(front), t_edge the edge
    thickness and V_cap = pi s (3 h^2 + s^2) / 6 the (signed) volume between a spherical cap of sag s and
    its base of radius h (the semi-diameter); the cells close the bore around each lens."""
    import trimesh

    from optics.design import surface_sag
    from optics.meshes import lens_parts

    L = make_layout(load_design("art"))
    parts = {p.name: p for p in lens_parts(L, n_r=48, n_phi=180)}
    for k in range(len(L.lenses) // 2):
        front, back = L.lenses[2 * k], L.lenses[2 * k + 1]
        pieces = [parts[f"lens_surface_{2 * k}"], parts[f"lens_surface_{2 * k + 1}"], parts[f"lens_edge_{k}"]]
        m = trimesh.util.concatenate([trimesh.Trimesh(p.vertices, p.faces, process=False) for p in pieces])
        m.merge_vertices(digits_vertex=5)
        m.update_faces(m.nondegenerate_faces())
        m.fix_normals()
        assert m.is_watertight, k
        h = front.semi_diameter_mm
        assert back.semi_diameter_mm == h
        s_f, s_b = surface_sag(front.radius_mm, h), surface_sag(back.radius_mm, h)
        cap_f, cap_b = (math.pi * s * (3 * h * h + s * s) / 6 for s in (s_f, s_b))
        volume = math.pi * h * h * (back.x_mm + s_b - front.x_mm - s_f) - cap_b + cap_f
        assert m.volume == pytest.approx(volume, rel=1e-3), k          # 180-gon: -0.02 %
        cell = parts[f"lens_cell_{k}"]
        r = np.hypot(cell.vertices[:, 1], cell.vertices[:, 2] - L.z_axis)
        assert r.min() == pytest.approx(h, rel=1e-6) and r.max() == pytest.approx(L.r_focuser, rel=1e-6)
