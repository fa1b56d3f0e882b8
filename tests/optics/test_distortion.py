"""SIP distortion fits checked with astropy's WCS, not against stored numbers."""

import numpy as np
import pytest

from optics import load_design
from optics.distortion import fit_sip, image_positions, sip_cards, sip_wcs
from optics.sequential import SequentialTracer

PITCH_UM = 3.76


@pytest.fixture(scope="module")
def art(mi):
    return SequentialTracer(load_design("art"), mi)


@pytest.fixture(scope="module")
def art_sip(art):
    """Order 7: the corrector's small (0.075 % at 2 deg) distortion has a seventh-order part that order 5
    leaves as 0.03 px rms (0.1 um; the default of cached_sip, more than good enough for astrometry)."""
    return fit_sip(art, PITCH_UM, order=7, grid=11)


def _probe_fields(design, n=25, seed=7):
    """Random field angles whose images fall on the detector (not the fit grid)."""
    rng = np.random.default_rng(seed)
    f = design.primary.focal_length_mm
    u = rng.uniform(-0.97, 0.97, n) * design.focal_plane.width_mm / 2
    v = rng.uniform(-0.97, 0.97, n) * design.focal_plane.height_mm / 2
    return np.stack([np.degrees(np.arctan(-u / f)), np.degrees(np.arctan(-v / f))], -1)


def test_sip_wcs_maps_traced_stars_to_their_sky_positions(art, art_sip):
    """Stars at known field angles around a pointing: the RA---TAN-SIP WCS built from the fitted cards
    must put each traced image (chief ray, pixel) on the star's sky position to < 0.05 px."""
    assert art_sip["rms_px"] < 0.01
    fields = _probe_fields(art.design)
    pos = image_positions(art, fields)                          # mm, detector frame
    pix = pos / (PITCH_UM * 1e-3) + np.array([art_sip["CRPIX1"], art_sip["CRPIX2"]]) - 1   # 0-based
    crval = (120.95, -29.25)
    w = sip_wcs(art_sip, crval_deg=crval)
    ra, dec = w.all_pix2world(pix[:, 0], pix[:, 1], 0)
    # the truth: the ideal gnomonic image of each field angle through the same WCS without distortion
    f = art.design.primary.focal_length_mm
    ideal = -f * np.tan(np.radians(fields)) / (PITCH_UM * 1e-3) + np.array([art_sip["CRPIX1"], art_sip["CRPIX2"]]) - 1
    tan = sip_wcs({k: v for k, v in sip_cards(art_sip).items() if not k.startswith(("A", "B"))}, crval_deg=crval)
    ra0, dec0 = tan.all_pix2world(ideal[:, 0], ideal[:, 1], 0)
    # sky offsets in pixels (CD scale)
    scale_deg = abs(art_sip["CD1_1"])
    err_px = np.hypot((ra - ra0) * np.cos(np.radians(dec0)), dec - dec0) / scale_deg
    assert err_px.max() < 0.02, err_px.max()
    # and the way back: sky -> pixel with the WCS (forward SIP inverted iteratively) ...
    xb, yb = w.all_world2pix(ra0, dec0, 0, tolerance=1e-6)
    assert np.max(np.hypot(xb - pix[:, 0], yb - pix[:, 1])) < 0.02
    # ... and with the reverse polynomials AP, BP of the cards alone: x = X + sum AP_p_q X^p Y^q
    X, Y = (ideal - np.array([art_sip["CRPIX1"], art_sip["CRPIX2"]]) + 1).T
    def rev(name):
        return sum(v * X ** int(k.split("_")[1]) * Y ** int(k.split("_")[2]) for k, v in art_sip.items()
                   if k.startswith(name + "_") and k != name + "_ORDER")
    xr = X + rev("AP") + art_sip["CRPIX1"] - 1
    yr = Y + rev("BP") + art_sip["CRPIX2"] - 1
    assert np.max(np.hypot(xr - pix[:, 0], yr - pix[:, 1])) < 0.02


def test_corrector_distortion_and_focal_length(art, art_sip):
    """The linear SIP terms hold the effective focal length: it must equal the paraxial one, h / tan(theta)
    of the chief ray at 0.05 deg; the non-linear distortion (what a linear fit leaves) is whole pixels,
    so the fit has something to resolve."""
    pos = image_positions(art, [(0.0, 0.05)])
    efl_paraxial = -pos[0, 1] / np.tan(np.radians(0.05))
    assert art_sip["effective_focal_length_mm"] == pytest.approx(efl_paraxial, rel=2e-5)
    assert abs(efl_paraxial - 960.0) > 1.0                      # the corrector changes the scale
    with pytest.warns(RuntimeWarning, match="raise the order"):
        linear = fit_sip(art, PITCH_UM, order=1, grid=9)
    assert linear["rms_px"] > 1.0
    assert art_sip["A_ORDER"] == 7 and "AP_9_0" in art_sip
    assert set(sip_cards(art_sip)) <= {k for k in art_sip if k.isupper()}


def test_bare_paraboloid_chief_ray_is_gnomonic(mi):
    """A paraboloid with the stop on its vertex sends the chief ray along the field angle through the
    vertex, so it lands at exactly -f tan(theta): no distortion at all."""
    bare = SequentialTracer(load_design("bare"), mi)
    sip = fit_sip(bare, PITCH_UM, order=3, grid=5, method="chief")
    assert sip["max_distortion_px"] < 1e-3
    coeffs = [v for k, v in sip.items() if k[:2] in ("A_", "B_") and k not in ("A_ORDER", "B_ORDER")]
    assert max(abs(c) for c in coeffs) < 1e-6
    assert sip["effective_focal_length_mm"] == pytest.approx(960.0, rel=1e-6)


@pytest.mark.filterwarnings("ignore:SIP order 3")   # the corners' vignetting bends the centroid by 0.2 px
def test_coma_centroid_shift_is_a_scale_change(mi):
    """Third-order coma images each pupil zone rho (fraction of the rim) as a circle whose centre lies
    2 theta f rho^2 / (16 N^2) beyond the chief ray; averaged over the annular pupil (obstruction eps)
    the centroid moves out by theta f (1 + eps^2) / (16 N^2): a scale change, i.e. a longer effective
    focal length f (1 + (1 + eps^2) / (16 N^2)) = 972 mm for the bare ART paraboloid."""
    design = load_design("bare")
    bare = SequentialTracer(design, mi)
    sip = fit_sip(bare, PITCH_UM, order=3, grid=5, method="centroid")
    eps = design.secondary.minor_axis_mm / design.primary.diameter_mm
    expected = 960.0 * (1 + (1 + eps ** 2) / (16 * design.f_number ** 2))
    assert sip["effective_focal_length_mm"] == pytest.approx(expected, rel=1e-3)


def test_bad_arguments(art):
    with pytest.raises(ValueError):
        fit_sip(art, PITCH_UM, order=0)
    with pytest.raises(ValueError, match="method"):
        image_positions(art, [(0.0, 0.0)], method="median")


def test_cached_sip_returns_the_fit_and_reuses_it(mi, art, tmp_path, monkeypatch):
    """The scenes package's entry point: fit_sip's dict for (design, pitch, shape, order), from the cache
    on the second call; the IMX411's 14192 x 10640 pixels put CRPIX on the sensor's centre."""
    from optics import distortion
    from optics.distortion import cached_sip

    monkeypatch.setenv("NEWTSIM_CACHE_DIR", str(tmp_path))
    shape = (10640, 14192)
    sip = cached_sip("art", PITCH_UM, shape)
    assert sip["A_ORDER"] == 5 and sip["CRPIX1"] == (14192 + 1) / 2 and sip["CRPIX2"] == (10640 + 1) / 2
    assert sip["rms_px"] < 0.05 and sip["reverse_rms_px"] < 0.01
    assert sip == fit_sip(art, PITCH_UM, order=5, grid=9, shape=shape)
    assert len(list(tmp_path.glob("sip-*.json"))) == 1
    # the second call is read from the file: no fit at all
    monkeypatch.setattr(distortion, "fit_sip", lambda *a, **k: pytest.fail("fit_sip called again"))
    again = cached_sip(art.design, PITCH_UM, shape)
    assert again == sip
    sip_wcs(again)                              # usable as it comes back


def test_a_moved_image_is_a_shift_not_a_distortion(mi):
    """A diagonal tilted 0.1 deg throws the whole image 90 px (0.8 mm on 9 um pixels) along v: SIP has no constant term, so fit_sip
    fits the shift, reports it (``shift_px``) and removes it. The shift is where the on-axis star's chief ray
    lands (traced independently, to 0.05 px), the polynomials keep only the distortion about the moved axis (fit
    residual < 0.05 px), and the nominal design has no shift at all."""
    from optics.design import with_perturbation

    d = load_design("bare")
    nominal = fit_sip(SequentialTracer(d, mi), 9.0, order=3, grid=7)
    assert np.hypot(*nominal["shift_px"]) < 1e-6
    tracer = SequentialTracer(with_perturbation(d, diagonal_tilt_x_deg=0.1), mi)
    sip = fit_sip(tracer, 9.0, order=3, grid=7)
    axis_px = image_positions(tracer, np.zeros((1, 2)))[0] / 9e-3
    assert abs(axis_px[1]) > 50 and np.allclose(sip["shift_px"], axis_px, atol=0.05), (sip["shift_px"], axis_px)
    assert sip["rms_px"] < 0.05
