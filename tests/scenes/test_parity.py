"""Mirror parity of the frame's WCS (``[telescope] parity``): stars, streaks and the written header follow."""

import math

import numpy as np
import pytest
from astropy.io import fits
from astropy.wcs import WCS
from helpers import isolated_stars

from detector import DetectorError
from scenes.app.render import prepare, render
from scenes.projection import Sip, eval_poly, sip_from_optics, tan_wcs
from scenes.scene import load_scene

RA0, DEC0, SCALE = 120.0, -30.0, 1.0

SCENE = """
[telescope]
pixel_scale_arcsec = 1.0
{telescope}
[detector]
preset = "ml11002"
width = 256
height = 256
{detector}
[pointing]
ra_deg = 120.0
dec_deg = -30.0
roll_deg = {roll}
[exposure]
time_s = 1.0
[sky]
background_mag_arcsec2 = 21.0
stars = true
catalog = "stars.csv"
[psf]
fwhm_arcsec = 2.5
"""


def tan_xi_eta(ra, dec, ra0=RA0, dec0=DEC0):
    """Gnomonic standard coordinates [deg] (Calabretta & Greisen 2002, eqs. 54-55 for TAN about CRVAL)."""
    a, d, a0, d0 = (np.radians(v) for v in (ra, dec, ra0, dec0))
    cosc = np.sin(d0) * np.sin(d) + np.cos(d0) * np.cos(d) * np.cos(a - a0)
    xi = np.cos(d) * np.sin(a - a0) / cosc
    eta = (np.cos(d0) * np.sin(d) - np.sin(d0) * np.cos(d) * np.cos(a - a0)) / cosc
    return np.degrees(xi), np.degrees(eta)


def write(tmp_path, stars, *, telescope="", detector="", roll=0.0, objects=""):
    (tmp_path / "stars.csv").write_text("ra,dec,mag\n" + "".join(f"{r},{d},{m}\n" for r, d, m in stars))
    p = tmp_path / "scene.toml"
    p.write_text(SCENE.format(telescope=telescope, detector=detector, roll=roll) + objects)
    return str(p)


def test_tan_wcs_parity_flips_east_keeps_north():
    for roll in (0.0, 30.0, -115.0):
        a = tan_wcs(RA0, DEC0, roll, SCALE, (100, 100))
        b = tan_wcs(RA0, DEC0, roll, SCALE, (100, 100), parity=1)
        assert np.linalg.det(a.wcs.cd) < 0 < np.linalg.det(b.wcs.cd)
        north = [np.linalg.solve(w.wcs.cd, [0.0, 1.0]) for w in (a, b)]
        east = [np.linalg.solve(w.wcs.cd, [1.0, 0.0]) for w in (a, b)]
        assert np.allclose(north[0], north[1])  # roll_deg: where north points, either parity
        assert np.allclose(east[0], -east[1])
    with pytest.raises(ValueError):
        tan_wcs(RA0, DEC0, 0.0, SCALE, (10, 10), parity=0)


def test_star_east_of_the_pointing_lands_at_plus_x_by_the_same_amount(tmp_path):
    """TAN analytic: a star 60" east on the pointing's parallel at x = CRPIX -+ xi / scale, y = CRPIX + eta."""
    ra = RA0 + 60.0 / 3600 / math.cos(math.radians(DEC0))
    xi, eta = tan_xi_eta(ra, DEC0)
    cx = cy = 127.5  # optical axis at the window centre (0-based)
    out = {}
    for parity in (-1, 1):
        p = write(tmp_path, [(ra, DEC0, 10.0)], telescope=f"parity = {parity}")
        setup = prepare(load_scene(p))
        t = setup.truth[0]
        out[parity] = (t["x"], t["y"])
        assert abs((t["x"] - cx) - parity * xi * 3600 / SCALE) < 1e-6
        assert abs((t["y"] - cy) - eta * 3600 / SCALE) < 1e-6
        img = setup.signal_e.image((256, 256)).astype(float) - setup.signal_e.background_e
        _, xx = np.indices(img.shape)
        assert abs((img * xx).sum() / img.sum() - t["x"]) < 0.01  # the light is where the truth says
    assert abs(out[1][0] - cx + (out[-1][0] - cx)) < 1e-6 and abs(out[1][1] - out[-1][1]) < 1e-9
    assert out[1][0] - cx == pytest.approx(60.0, rel=2e-3)  # ~60 px east = +x


@pytest.mark.parametrize("extra", [
    {"roll": 30.0},
    {"roll": -70.0, "detector": "binning = 2"},
    {"roll": 10.0, "telescope": 'distortion = "sip"\n[telescope.sip]\norder = 3\na_3_0 = 2e-7\nb_0_3 = 2e-7\n'
                                "a_1_2 = 1e-7\n"},
])
def test_written_header_recovers_the_rendered_centroids(tmp_path, extra):
    """parity = +1: det CD > 0 in the FITS header, and its all_world2pix gives the stars' measured centroids."""
    rng = np.random.default_rng(3)
    stars = [(RA0 + dx / 3600 / math.cos(math.radians(DEC0)), DEC0 + dy / 3600, 9.5)
             for dx, dy in rng.uniform(-95, 95, (9, 2))]
    tel = "parity = 1\n" + extra.get("telescope", "")
    p = write(tmp_path, stars, telescope=tel, detector=extra.get("detector", ""), roll=extra["roll"])
    render(load_scene(p, ["effects={}"]), tmp_path / "f.fits", seed=1, noiseless=True, progress=False)
    with fits.open(tmp_path / "f.fits") as h:
        hdr = h[0].header
    w = WCS(hdr)  # the header has PCi_j and CDELTi (astropy's to_header): CD = CDELT_i PC_ij
    cd = w.wcs.cd if w.wcs.has_cd() else w.wcs.cdelt[:, None] * w.wcs.get_pc()
    assert np.linalg.det(cd) > 0
    st = isolated_stars(tmp_path / "f.fits", 2.5 / hdr["PIXSCALE"])
    assert len(st["cx"]) >= 3
    assert np.abs(st["cx"] - st["x"]).max() < 0.05 and np.abs(st["cy"] - st["y"]).max() < 0.05


def test_streak_follows_the_parity(tmp_path):
    """An object moving west (rate_ra < 0) runs towards +x for parity -1 and towards -x for +1, same length."""
    obj = ('[[objects]]\nra_deg = 120.0\ndec_deg = -30.0\nrate_ra_deg_s = -0.006\nrate_dec_deg_s = 0.004\n'
           'photons = 1e6\n')
    rows = {}
    for parity in (-1, 1):
        p = write(tmp_path, [], telescope=f"parity = {parity}", objects=obj)
        t = prepare(load_scene(p, ["sky.stars=false"])).truth[0]
        rows[parity] = (t["x1"] - t["x0"], t["y1"] - t["y0"])
    assert rows[-1][0] > 0 > rows[1][0]
    assert rows[-1][0] == pytest.approx(-rows[1][0], abs=1e-6) and rows[-1][1] == pytest.approx(rows[1][1], abs=1e-6)


def test_optics_sip_of_a_mirrored_camera():
    """sip_from_optics with parity +1: scene ideal offsets = (s_x U, s_y V)(s_x x, s_y y), s_x = -1, s_y = -1."""

    class S:
        sensor_width_px, sensor_height_px = 100, 80

    fit = {"CRPIX1": 50.5, "CRPIX2": 40.5, "A_ORDER": 3, "A_2_0": 1e-4, "A_1_1": -2e-4, "A_0_2": 3e-5,
           "A_3_0": 1e-6, "A_1_2": 2e-6, "B_2_0": -5e-5, "B_0_2": 4e-4, "B_2_1": 3e-6, "B_0_3": -1e-6}
    A = {(int(k[2]), int(k[4])): v for k, v in fit.items() if k.startswith("A_") and k != "A_ORDER"}
    B = {(int(k[2]), int(k[4])): v for k, v in fit.items() if k.startswith("B_")}
    x, y = np.meshgrid(np.linspace(-40, 40, 7), np.linspace(-30, 30, 5))
    for parity, sx in ((-1, 1.0), (1, -1.0)):
        sip = sip_from_optics(fit, S(), parity=parity)
        u, v = sx * x, -y
        X, Y = sip.forward(x, y)
        assert np.allclose(X, sx * (u + eval_poly(A, u, v)), atol=1e-12)
        assert np.allclose(Y, -(v + eval_poly(B, u, v)), atol=1e-12)
    assert isinstance(sip, Sip)


def test_parity_errors_and_default(tmp_path):
    p = write(tmp_path, [])
    assert load_scene(p).telescope.parity == -1
    with pytest.raises(DetectorError, match="telescope.parity"):
        load_scene(p, ["telescope.parity=0"])
    with pytest.raises(DetectorError, match="telescope.parity"):
        load_scene(p, ["telescope.parity=1", "effects.straylight.pst='optics'"])
