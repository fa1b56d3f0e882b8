"""Scene files, overrides and the empty-sky render path (bias, dark, flat, sky)."""

import numpy as np
import pytest
from astropy.io import fits
from astropy.wcs import WCS
from astropy.wcs.utils import proj_plane_pixel_scales

from detector import DetectorError
from optics.design import load_design
from scenes.app.render import render
from scenes.photometry import ab_electron_rate, sky_electron_rate_per_pixel
from scenes.scene import apply_overrides, load_scene, parse_value

SMALL = ["detector.width=480", "detector.height=480"]


def write_scene(tmp_path, text):
    p = tmp_path / "scene.toml"
    p.write_text(text)
    return p


def test_ab_zero_point_is_1000_photons_per_cm2_s_angstrom_at_550nm():
    """AB: f_nu = 3631 Jy gives f_nu/(h lambda) = 996 photons/s/cm^2/A at 550 nm (Oke & Gunn 1983)."""
    lam = np.linspace(549.5, 550.5, 3)
    rate = ab_electron_rate(0.0, 1e-4, 1.0, lam, np.ones(3))  # 1 cm^2, 1 nm of band
    assert abs(rate / 10 - 996) < 5
    # flat QE over 500-600 nm: integral dlambda/lambda = ln(1.2): 1.0e10 photons/s/m^2 at mag 0
    lam = np.linspace(500, 600, 1001)
    assert abs(ab_electron_rate(0.0, 1.0, 1.0, lam, np.ones_like(lam)) / (3631e-26 / 6.62607015e-34 * np.log(1.2)) - 1) < 1e-4
    # five magnitudes are a factor of 100
    assert np.isclose(ab_electron_rate(5.0, 1, 1, lam, np.ones_like(lam)) * 100, ab_electron_rate(0.0, 1, 1, lam, np.ones_like(lam)))


def test_parse_and_override():
    assert parse_value("150") == 150 and parse_value("1.5e3") == 1500.0 and parse_value("true") is True
    assert parse_value("'abc'") == "abc" and parse_value("gaia") == "gaia" and parse_value("[1, 2]") == [1, 2]
    d = apply_overrides({"exposure": {"time_s": 1}}, ["exposure.time_s=150", "effects.prnu.sigma=0.02"], file="f")
    assert d == {"exposure": {"time_s": 150}, "effects": {"prnu": {"sigma": 0.02}}}


@pytest.mark.parametrize("override, key", [
    ("exposure.time_s=-1", "exposure.time_s"),
    ("exposure.frame=flatfield", "exposure.frame"),
    ("detector.gain_e_per_adu=0", "detector.gain_e_per_adu"),
    ("detector.preset=nosuch", "detector.preset"),
    ("sky.colour=1", "sky.colour"),
    ("pointing.epoch=yesterday", "pointing"),
])
def test_errors_name_file_key_and_expectation(tmp_path, override, key):
    p = write_scene(tmp_path, "[exposure]\ntime_s = 1.0\n")
    with pytest.raises(DetectorError) as e:
        load_scene(str(p), [override])
    assert str(p) in str(e.value) and key in str(e.value) and "expected" in str(e.value)


def test_bad_toml_and_missing_file(tmp_path):
    p = write_scene(tmp_path, "[exposure\ntime_s = 1\n")
    with pytest.raises(DetectorError, match="not valid TOML"):
        load_scene(str(p))
    with pytest.raises(DetectorError, match="not found"):
        load_scene(str(tmp_path / "nope.toml"))


def test_bias_frame_statistics(tmp_path):
    """A bias: zero exposure, no light: mean B (the ADC rounds), std sqrt(sr^2/g^2 + 1/12) (thesis Table 10 style)."""
    sc = load_scene("default", SMALL + ["exposure.frame=bias", "effects={}"])
    render(sc, tmp_path / "b.fits", seed=3, progress=False)
    with fits.open(tmp_path / "b.fits") as h:
        d, hdr = h[0].data.astype(float), h[0].header
    assert hdr["EXPTIME"] == 0 and hdr["FRAMETYP"] == "bias"
    assert abs(d.mean() - 500) < 0.05
    assert abs(d.std() - np.sqrt((3.5 / 1.22) ** 2 + 1 / 12)) < 0.05


def test_empty_sky_level_matches_photometry(tmp_path):
    sc = load_scene("default", SMALL + ["effects={}", "exposure.time_s=10"])
    summary = render(sc, tmp_path / "s.fits", seed=1, progress=False, expected=True)
    design = load_design("art")
    s = sc.sensor()
    rate = sky_electron_rate_per_pixel(19.72, design.pixel_scale_arcsec(3.76), design.collecting_area_m2,
                                       design.mirror_throughput, s.qe_wavelength_nm, s.qe)
    assert np.isclose(summary["sky_e_per_s"], rate)
    with fits.open(tmp_path / "s.fits") as h:
        d = h[0].data.astype(float)
        exp = h["EXPECTED"].data
        np.testing.assert_allclose(exp, rate * 10 + 0.0022 * 10, rtol=1e-6)
        assert abs(d.mean() - (500 + exp.mean() / 1.22)) < 5 * d.std() / np.sqrt(d.size)
        w = WCS(h[0].header)
        assert np.allclose(w.wcs.crval, [120.95115, -29.25022])
        assert np.allclose(proj_plane_pixel_scales(w) * 3600, design.pixel_scale_arcsec(3.76), rtol=1e-9)


def test_noiseless_and_header_contract(tmp_path):
    sc = load_scene("default", SMALL + ["detector.binning=2", "sky.flat_e_per_s=100"])
    render(sc, tmp_path / "n.fits", seed=1, noiseless=True, progress=False)
    with fits.open(tmp_path / "n.fits") as h:
        hdr = h[0].header
        assert h[0].data.dtype.kind == "f" and h[0].data.dtype.itemsize == 4 and h[0].data.shape == (240, 240)
        for card in ("GAIN", "BIAS", "RDNOISE", "EXPTIME", "FULLWELL", "BITDEPTH", "ROWTIME", "CTYPE1", "SEED"):
            assert card in hdr, card
        assert hdr["ROWTIME"] == pytest.approx(2 * 4.7e-5) and hdr["BUNIT"] == "electron"
        assert "HOTPIX" in h and "SCENE" in h and "TRUTH" in h
        assert "prnu" in h["SCENE"].data["toml"][0]


def test_same_seed_same_bytes_and_fixed_pattern(tmp_path):
    sc = load_scene("default", SMALL)
    for name, seed in (("a", 5), ("b", 5), ("c", 6)):
        render(sc, tmp_path / f"{name}.fits", seed=seed, progress=False)
    a, b, c = (fits.getdata(tmp_path / f"{n}.fits") for n in "abc")
    assert a.tobytes() == b.tobytes() and a.tobytes() != c.tobytes()
    t = fits.getdata(tmp_path / "a.fits", "HOTPIX")
    hot = t[t["t_double_s"] < 20]  # > 61 e- (50 ADU) of excess in 2 s
    # the same hot pixels stand out in both frames (hardware seed), the noise differs (frame seed)
    assert hot.size and np.all(a[hot["y"], hot["x"]] > np.median(a) + 25) and np.all(c[hot["y"], hot["x"]] > np.median(c) + 25)


def test_ray_traced_vignetting_darkens_the_corner_by_the_optics_map(tmp_path, monkeypatch):
    """[effects.vignetting] map_file = "optics": the scene's design is ray-traced (cached) and the corner
    window of a flat illumination is dimmed by exactly the map's relative illumination there."""
    pytest.importorskip("mitsuba")
    monkeypatch.setenv("NEWTSIM_CACHE_DIR", str(tmp_path / "cache"))
    base = ["effects={}", "detector.width=64", "detector.height=64", "detector.x0=0", "detector.y0=0",
            "sky.flat_e_per_s=1000", "telescope.design=bare", "detector.dark_current_e_per_s=0"]
    plain = load_scene("default", base)
    vig = load_scene("default", base + ['effects.vignetting.map_file="optics"'])
    render(plain, tmp_path / "a.fits", seed=1, noiseless=True, progress=False)
    render(vig, tmp_path / "b.fits", seed=1, noiseless=True, progress=False)
    ratio = fits.getdata(tmp_path / "b.fits") / fits.getdata(tmp_path / "a.fits")
    cached = list((tmp_path / "cache").glob("vignetting-*.fits"))
    assert len(cached) == 1
    from optics.vignetting import read_fits

    _, _, ri = read_fits(cached[0])
    assert ratio[0, 0] == pytest.approx(ri[0, 0], abs=0.003)      # the map's corner sample is at the sensor corner
    assert ratio[0, 0] < 0.95 and ratio[-1, -1] > ratio[0, 0]      # darker toward the corner


def test_a_summed_binning_that_saturates_every_pixel_is_a_warning(tmp_path):
    """IMX411 binned 16x16 in "sum" mode: the summed bias (256 x 500 ADU) is above the 16-bit range; the render
    says so (summary warnings, printed by the CLI) instead of writing a saturated frame without a word."""
    scene = load_scene("examples/scenes/empty_sky_imx411.toml",
                       ["detector.binning=16", "detector.width=256", "detector.height=256"])
    info = render(scene, tmp_path / "b16.fits", seed=1, progress=False)
    assert (fits.getdata(tmp_path / "b16.fits") == 65535).all()
    assert any("every pixel of the frame saturates" in w and "'average'" in w for w in info["warnings"])
