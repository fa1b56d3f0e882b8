"""Perturbations of the design as data: the ``[perturbation]`` table, checked against first-order optics."""

import math

import numpy as np
import pytest

from optics import OpticsError, load_design
from optics.cache import cache_key
from optics.design import PERTURBATION_NAMES, with_perturbation
from optics.sequential import SequentialTracer, pupil_uniform


@pytest.fixture(scope="module")
def bare():
    return load_design("bare")


def _spot(mi, design, field=(0.0, 0.0), n=20000, obstruct="analytic"):
    px, py = pupil_uniform(n, design.primary.diameter_mm / 2, seed=1)
    r = SequentialTracer(design, mi, obstruct=obstruct).trace(field, px, py)
    return r


def test_defocus_blurs_to_aperture_times_piston_over_focal_length(mi, bare):
    """A sensor dz behind focus sees the cone's cross-section: outer diameter D dz / f (geometric optics).
    Exactly, the marginal ray from the rim (R, sag(R)) crosses the axis at f, so 2 R dz / (f - sag(R))."""
    dz_mm = 0.5
    r = _spot(mi, with_perturbation(bare, sensor_piston_um=dz_mm * 1e3))
    diameter = 2 * np.max(np.hypot(r.u[r.ok], r.v[r.ok]))     # about the (unmoved) chief-ray image
    D, f = bare.primary.diameter_mm, bare.primary.focal_length_mm
    R = D / 2
    exact = 2 * R * dz_mm / (f - R * R / (4 * f))
    assert diameter == pytest.approx(exact, rel=2e-3)
    assert diameter == pytest.approx(D * dz_mm / f, rel=0.015)


def test_primary_tilt_moves_the_image_by_twice_the_tilt(mi, bare):
    """Tilting the primary by a turns the reflected beam by 2a: the image moves by f tan(2a) ~ 2 f a.
    The chief ray (through the vertex) lands there exactly; the centroid adds the comatic offset of the
    equivalent 2a field (sagittal coma, < 1 %)."""
    f = bare.primary.focal_length_mm
    a = 0.05
    expect = 2 * f * math.radians(a)
    rx = _spot(mi, with_perturbation(bare, primary_tilt_x_deg=a))
    ry = _spot(mi, with_perturbation(bare, primary_tilt_y_deg=a))
    w = rx.transmission * rx.ok
    assert np.average(rx.v, weights=w) == pytest.approx(-expect, rel=0.01)   # about +x: toward -v
    assert abs(np.average(rx.u, weights=w)) < 1e-3 * expect
    w = ry.transmission * ry.ok
    assert np.average(ry.u, weights=w) == pytest.approx(expect, rel=0.01)    # about +y: toward +u
    chief = SequentialTracer(with_perturbation(bare, primary_tilt_x_deg=a), mi, obstruct="none").trace(
        (0.0, 0.0), [0.0], [0.0])
    assert chief.v[0] == pytest.approx(-f * math.tan(2 * math.radians(a)), rel=1e-4)


def test_decentred_primary_moves_the_image_with_its_axis(mi, bare):
    """A paraboloid shifted sideways by s still images an on-axis star perfectly, on its shifted axis."""
    r = _spot(mi, with_perturbation(bare, primary_decenter_x_mm=2.0, primary_decenter_y_mm=-1.0),
              obstruct="none")
    ok = r.ok
    assert np.ptp(r.u[ok]) < 1e-6 and np.ptp(r.v[ok]) < 1e-6
    assert np.mean(r.u[ok]) == pytest.approx(2.0, abs=1e-6)
    assert np.mean(r.v[ok]) == pytest.approx(-1.0, abs=1e-6)


def test_diagonal_tilt_turns_the_folded_beam_by_twice_the_tilt(mi, bare):
    """A flat tilted by b about an axis in its surface turns the reflected beam by 2b: the image moves by
    2 b d (d: diagonal-to-focus distance) when the axis is perpendicular to the plane of incidence, and
    2 b cos(45 deg) d when it lies in it. About the major axis (in the plane of incidence, through the
    axis point): along v, sqrt2 b d.
    About the minor axis through the ellipse's centre, which sits ``offset_mm`` = s from the axis point
    along the major axis, the mirror also moves s b along its normal, which shifts the image by sqrt2 s b:
    along u, b (2 d + sqrt2 s)."""
    b = 0.05
    d = bare.secondary.distance_to_focus_mm
    ry = _spot(mi, with_perturbation(bare, diagonal_tilt_y_deg=b), obstruct="none")
    rx = _spot(mi, with_perturbation(bare, diagonal_tilt_x_deg=b), obstruct="none")
    # the chief ray meets the diagonal at its axis point, distance d from the focus
    s = bare.secondary.offset_mm
    assert abs(np.median(ry.u[ry.ok])) == pytest.approx(math.radians(b) * (2 * d + math.sqrt(2) * s), rel=2e-3)
    assert abs(np.median(rx.v[rx.ok])) == pytest.approx(math.sqrt(2) * d * math.radians(b), rel=2e-3)


def test_sensor_tilt_is_a_piston_growing_with_height(mi, bare):
    """A sensor tilted by t about its x (u) axis lies -v tan(t) along the beam from the nominal plane at
    height v: the star imaged there gets the spot of that piston (the local plane's extra tilt changes
    its size by 1 - cos t ~ 1.5e-4), and a star on the tilt axis (v = 0) is not changed."""
    t = 1.0
    field = (0.0, -0.6)   # images at v = +f tan(0.6 deg) ~ 10 mm
    r0 = _spot(mi, bare, field)
    v0 = np.median(r0.v[r0.ok])
    r1 = _spot(mi, with_perturbation(bare, sensor_tilt_x_deg=t), field)
    r2 = _spot(mi, with_perturbation(bare, sensor_piston_um=-1e3 * v0 * math.tan(math.radians(t))), field)
    rms = lambda r: math.sqrt(np.var(r.u[r.ok]) + np.var(r.v[r.ok]))
    assert rms(r1) == pytest.approx(rms(r2), rel=2e-3)
    assert rms(r1) - rms(r0) > 10 * abs(rms(r1) - rms(r2))      # the tilt did change the spot
    on_axis = (0.6, 0.0)
    assert rms(_spot(mi, with_perturbation(bare, sensor_tilt_x_deg=t), on_axis)) == pytest.approx(
        rms(_spot(mi, bare, on_axis)), rel=1e-3)


def test_zero_perturbation_gives_identical_results_and_hash(mi, bare):
    zero = with_perturbation(bare, **{k: 0.0 for k in PERTURBATION_NAMES if not k.startswith("corrector_")})
    a, b = _spot(mi, bare, (0.7, 0.3), n=5000), _spot(mi, zero, (0.7, 0.3), n=5000)
    for k in ("u", "v", "du", "dv", "opl", "transmission", "lost"):
        assert np.array_equal(getattr(a, k), getattr(b, k)), k
    assert cache_key("psfgrid", zero, {}) == cache_key("psfgrid", bare, {})
    assert cache_key("psfgrid", with_perturbation(bare, sensor_piston_um=40), {}) != cache_key("psfgrid", bare, {})


def test_perturbation_table_is_validated(tmp_path):
    import tomli_w

    data = load_design("bare").model_dump(exclude_none=True)
    data["perturbation"] = {"sensor_piston_um": 40.0, "diagonal_tilt_z_deg": 0.1}
    path = tmp_path / "p.toml"
    path.write_text(tomli_w.dumps(data))
    with pytest.raises(OpticsError) as exc:
        load_design(str(path))
    msg = str(exc.value)
    assert str(path) in msg and "perturbation.diagonal_tilt_z_deg" in msg and "\n" not in msg
    data["perturbation"] = {"corrector_tilt_x_deg": 0.1}       # bare has no corrector
    path.write_text(tomli_w.dumps(data))
    with pytest.raises(OpticsError, match="corrector_tilt_x_deg"):
        load_design(str(path))
    data["perturbation"] = {"sensor_piston_um": -40.0, "primary_tilt_x_deg": 0.02}
    path.write_text(tomli_w.dumps(data))
    d = load_design(str(path))
    assert d.perturbation.sensor_piston_um == -40.0 and not d.perturbation.is_zero


def test_corrector_perturbations_move_and_blur_the_art_image(mi):
    """art: a decentred corrector moves the image along the decentre; a larger back focus defocuses."""
    art = load_design("art")
    r0 = _spot(mi, art, n=5000)
    r1 = _spot(mi, with_perturbation(art, corrector_decenter_x_mm=0.5), n=5000)
    r2 = _spot(mi, with_perturbation(art, corrector_spacing_mm=0.5), n=5000)
    c = lambda r: (np.average(r.u, weights=r.ok * r.transmission), np.average(r.v, weights=r.ok * r.transmission))
    assert c(r1)[0] - c(r0)[0] > 1e-3 and abs(c(r1)[1] - c(r0)[1]) < 1e-4
    rms = lambda r: np.sqrt(np.var(r.u[r.ok]) + np.var(r.v[r.ok]))
    assert rms(r2) > 1.5 * rms(r0)
