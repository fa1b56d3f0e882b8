"""SIP distortion in the frames' WCS: the file's own WCS, the traced chief rays and the rendered stars agree."""

import numpy as np
import pytest
from astropy.io import fits
from astropy.wcs import WCS
from helpers import isolated_stars

from detector import DetectorError
from scenes.app.render import prepare, render
from scenes.image import frame_wcs
from scenes.projection import REVERSE_WARN_PX, Sip, fit_reverse, sip_from_optics
from scenes.scene import load_scene

CORNER = ["detector.preset='imx411'", "detector.width=1024", "detector.height=1024", "detector.x0=0",
          "detector.y0=0", "effects={}", "sky.stars=true", "sky.star_mag_limit=16", "psf.fwhm_arcsec=3.0"]


def _linear(hdr):
    """The header's WCS without its SIP terms (the ideal gnomonic camera)."""
    w = WCS(hdr)
    w.sip = None
    w.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    return w


@pytest.mark.parametrize("binning", [1, 2])
def test_optics_sip_frame_matches_the_traced_chief_rays(tmp_path, optics_sip, mi, binning):
    """distortion = 'optics', a 1024^2 window in the IMX411's corner (~40 px of distortion): the file's WCS maps
    TRUTH ra/dec onto TRUTH x, y; the traced chief ray of every star lands there too; isolated stars'
    centroids sit on it; the reverse polynomials invert the forward ones."""
    from optics import load_design
    from optics.distortion import image_positions
    from optics.sequential import SequentialTracer

    sc = load_scene("default", CORNER + ["telescope.distortion='optics'", f"detector.binning={binning}"])
    render(sc, tmp_path / "f.fits", seed=1, noiseless=True, progress=False)
    with fits.open(tmp_path / "f.fits") as hd:
        hdr = hd[0].header
        t = hd["TRUTH"].data
    assert hdr["CTYPE1"] == "RA---TAN-SIP" and hdr["A_ORDER"] == 7 and hdr["AP_ORDER"] == 9 and hdr["SIPSRC"] == "optics"
    assert len(t) > 50
    w = WCS(hdr)
    x, y = w.all_world2pix(t["ra_deg"], t["dec_deg"], 0, tolerance=1e-9)
    assert np.abs(x - t["x"]).max() < 0.02 and np.abs(y - t["y"]).max() < 0.02
    # stars cover the whole window although the pointing (optical axis) lies outside it
    assert t["x"].min() < 100 and t["x"].max() > 1024 / binning - 100 and t["y"].min() < 100
    # independent: trace the chief ray of each star's field angles (from the ideal camera, no SIP)
    X, Y = _linear(hdr).wcs_world2pix(t["ra_deg"], t["dec_deg"], 0)
    cx, cy = hdr["CRPIX1"] - 1, hdr["CRPIX2"] - 1
    design = load_design("art")
    pitch_mm, f = 3.76e-3, design.primary.focal_length_mm
    fields = np.stack([np.degrees(np.arctan(-(X - cx) * binning * pitch_mm / f)),
                       np.degrees(np.arctan((Y - cy) * binning * pitch_mm / f))], -1)
    uv = image_positions(SequentialTracer(design, mi), fields)
    xs, ys = uv[:, 0] / pitch_mm / binning + cx, -uv[:, 1] / pitch_mm / binning + cy  # y = -v / pitch
    assert np.hypot(X - t["x"], Y - t["y"]).min() > 10 / binning  # the distortion is large here ...
    assert np.abs(xs - t["x"]).max() < 0.05 and np.abs(ys - t["y"]).max() < 0.05  # ... and followed
    # rendered stars: centroids on the WCS positions, all their light
    st = isolated_stars(tmp_path / "f.fits", 3.0 / hdr["PIXSCALE"])
    assert len(st["cx"]) >= 5
    assert np.abs(st["cx"] - st["x"]).max() < 0.03 and np.abs(st["cy"] - st["y"]).max() < 0.03
    assert np.abs(st["sum"] / st["flux"] - 1).max() < 0.01
    # the reverse polynomials (AP, BP) of the header undo A, B over the frame
    gx, gy = np.meshgrid(np.linspace(0, hdr["NAXIS1"] - 1, 21), np.linspace(0, hdr["NAXIS2"] - 1, 21))
    fx, fy = w.sip_pix2foc(gx.ravel(), gy.ravel(), 0)
    bx, by = w.sip_foc2pix(fx, fy, 0)
    assert np.hypot(bx - gx.ravel(), by - gy.ravel()).max() < REVERSE_WARN_PX
    assert hdr["SIPRMAX"] < REVERSE_WARN_PX and hdr["SIPFRMS"] < 0.02  # the optics' own forward-fit residual


def test_optics_sip_is_binned_and_mirrored_into_the_scene_axes():
    """The optics' WCS (CD = -s I: pixels (u, v) / pitch) and the scene's (east left, north up) see the same
    star at x_s = x_o and y_s = 2 c_y - y_o, for a distortion with terms of both parities in y; binning b
    divides the offsets from the axis by b."""
    from optics.distortion import sip_wcs

    rng = np.random.default_rng(5)
    sc = load_scene("default", ["detector.preset='ml11002'", "effects={}"])
    sensor = sc.sensor()
    h, w = sensor.sensor_height_px, sensor.sensor_width_px
    s = 2e-3  # deg / pixel
    fit = {"CRPIX1": (w + 1) / 2, "CRPIX2": (h + 1) / 2, "CD1_1": -s, "CD1_2": 0.0, "CD2_1": 0.0, "CD2_2": -s,
           "A_ORDER": 3, "B_ORDER": 3, "A_1_0": 0.01, "A_0_2": 3e-7, "A_1_1": -2e-7, "A_3_0": 4e-11, "A_1_2": 2e-11,
           "B_0_1": 0.01, "B_2_0": 1e-7, "B_0_2": 2.5e-7, "B_2_1": 4e-11, "B_0_3": -3e-11}
    ow = sip_wcs(fit, crval_deg=(sc.pointing.ra_deg, sc.pointing.dec_deg))
    sip = sip_from_optics(fit, sensor)
    xo, yo = rng.uniform(0, w - 1, 50), rng.uniform(0, h - 1, 50)
    ra, dec = ow.all_pix2world(xo, yo, 0)
    for b in (1, 2, 4):
        sb = load_scene("default", ["detector.preset='ml11002'", "effects={}", f"detector.binning={b}"]).sensor()
        sw = frame_wcs(sc, sb, s * 3600, distortion=sip)
        xs, ys = sw.all_world2pix(ra, dec, 0, tolerance=1e-10)
        c = ((w - 1) / 2, (h - 1) / 2)
        assert np.abs(xs - ((xo - c[0]) / b + (w / b - 1) / 2)).max() < 1e-6
        assert np.abs(ys - ((c[1] - yo) / b + (h / b - 1) / 2)).max() < 1e-6


def _invert(sip, X, Y):
    """Pixel offsets whose ideal offsets are (X, Y): Newton on x + A(x, y) = X, y + B(x, y) = Y."""
    x, y = X.copy(), Y.copy()
    for _ in range(30):
        u, v = sip.forward(x, y)
        e = 1e-3
        ux, vx = sip.forward(x + e, y)
        uy, vy = sip.forward(x, y + e)
        j11, j12, j21, j22 = (ux - u) / e, (uy - u) / e, (vx - v) / e, (vy - v) / e
        det = j11 * j22 - j12 * j21
        dx, dy = ((X - u) * j22 - (Y - v) * j12) / det, ((Y - v) * j11 - (X - u) * j21) / det
        x, y = x + dx, y + dy
    return x, y


def test_scene_sip_table_moves_the_stars_where_the_polynomial_says(tmp_path):
    """distortion = 'sip' with a [telescope.sip] table (unbinned sensor pixels about the axis): TRUTH x, y of a
    binned corner window equal the Newton inversion of the table's polynomial of the ideal positions."""
    coef = {"a_2_0": 2e-7, "a_3_0": -3e-11, "a_1_2": -3e-11, "b_2_1": -3e-11, "b_0_3": -3e-11, "b_1_1": 1e-7}
    table = "{order=3, " + ", ".join(f"{k}={v}" for k, v in coef.items()) + "}"
    ov = CORNER + ["telescope.distortion='sip'", f"telescope.sip={table}", "detector.binning=2", "sky.star_mag_limit=14"]
    sc = load_scene("default", ov)
    setup = prepare(sc)
    t = setup.truth
    assert len(t) > 5
    sip = Sip(3, {(int(k[2]), int(k[4])): v for k, v in coef.items() if k[0] == "a"},
              {(int(k[2]), int(k[4])): v for k, v in coef.items() if k[0] == "b"})
    sensor = sc.sensor()
    lin = frame_wcs(sc, sensor, setup.pixel_scale_arcsec, binned=False)
    X, Y = lin.wcs_world2pix(t["ra_deg"], t["dec_deg"], 0)
    cx, cy = lin.wcs.crpix[0] - 1, lin.wcs.crpix[1] - 1
    xu, yu = _invert(sip, X - cx, Y - cy)
    xb, yb = (xu + cx - 0.5) / 2, (yu + cy - 0.5) / 2  # unbinned window -> binned frame
    assert np.hypot(xu - (X - cx), yu - (Y - cy)).max() > 5  # the table moves stars by pixels
    assert np.abs(xb - t["x"]).max() < 1e-4 and np.abs(yb - t["y"]).max() < 1e-4
    # the written header is the same distortion (binned coefficients) and maps the truth back
    render(sc, tmp_path / "s.fits", seed=1, noiseless=True, progress=False)
    hdr = fits.getheader(tmp_path / "s.fits")
    assert hdr["A_3_0"] == pytest.approx(-3e-11 * 4) and hdr["B_1_1"] == pytest.approx(1e-7 * 2)
    x, y = WCS(hdr).all_world2pix(t["ra_deg"], t["dec_deg"], 0, tolerance=1e-9)
    assert np.abs(x - t["x"]).max() < 1e-4 and np.abs(y - t["y"]).max() < 1e-4


def test_reverse_fit_recovers_a_known_inverse():
    """Algorithm 1 on a distortion whose inverse is known in closed form to first order: x + k x^2 has
    the inverse X - k X^2 + 2 k^2 X^3 - ...; the order-5 fit reproduces the series and the residual is tiny."""
    k = 1e-5
    sip = Sip(2, {(2, 0): k}, {})
    ap, bp, rms, mx = fit_reverse(sip, (-300, 300), (-200, 200), order=5)
    assert mx < 1e-6 and rms < mx + 1e-12
    assert ap[(2, 0)] == pytest.approx(-k, rel=1e-4) and ap[(3, 0)] == pytest.approx(2 * k * k, rel=1e-2)
    assert max(abs(v) for v in bp.values()) < 1e-12


@pytest.mark.parametrize("override, key", [
    (["telescope.distortion='sip'", "telescope.sip={order=3, c_1_1=1e-7}"], "telescope.sip.c_1_1"),
    (["telescope.distortion='sip'", "telescope.sip={a_2_0=1e-7}"], "telescope.sip.order"),
    (["telescope.distortion='sip'", "telescope.sip={order=2, a_3_0=1e-9}"], "telescope.sip.a_3_0"),
    (["telescope.distortion='sip'", "telescope.sip={order=10, a_3_0=1e-9}"], "telescope.sip.order"),
    (["telescope.distortion='sip'", "telescope.sip={order=3, a_3_0='x'}"], "telescope.sip.a_3_0"),
    (["telescope.distortion='sip'", "telescope.sip={order=3, a_0_0=1.0}"], "telescope.sip.a_0_0"),
    (["telescope.distortion='sip'", "telescope.sip={order=3, reverse_order=2, a_3_0=1e-9}"],
     "telescope.sip.reverse_order"),
    (["telescope.distortion='sip'"], "telescope.sip"),
    (["telescope.sip={order=3, a_3_0=1e-9}"], "telescope.distortion"),
    (["telescope.distortion='optics'", "telescope.sip={order=5, a_3_0=1e-9}"], "telescope.sip.a_3_0"),
    (["telescope.distortion='tan'"], "telescope.distortion"),
])
def test_sip_errors_name_file_key_and_expectation(tmp_path, override, key):
    p = tmp_path / "scene.toml"
    p.write_text("[telescope]\ndesign = 'art'\n")
    with pytest.raises(DetectorError) as e:
        load_scene(str(p), override)
    msg = str(e.value)
    assert f"key '{key}'" in msg and "expected" in msg and "scene.toml" in msg, msg
