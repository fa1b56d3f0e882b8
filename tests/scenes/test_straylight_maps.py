"""Straylight of the Sun and the Moon in the frames: ephemeris, photometry, geometry, scaling, the PST map."""

import math
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits

from detector import DetectorError
from scenes.app.render import prepare, render
from scenes.objects import solar_spectral_irradiance
from scenes.objects.frames import east_north, radec_to_unit, unit_to_radec
from scenes.scene import load_scene
from scenes.straylight import (
    bodies,
    moon_v_magnitude,
    off_axis,
    pst_from_table,
    telescope_axes,
)

H, C = 6.62607015e-34, 299792458.0
SMALL = ["detector.preset='ml11002'", "detector.width=64", "detector.height=64", "effects={}"]
TLE = Path(__file__).parent / "data" / "iss_20191209.tle"


def sun_radec(epoch):
    s = bodies(epoch, None, np.array([400.0, 900.0]), np.array([0.5, 0.5]), ("sun",))["sun"]
    return unit_to_radec(s.unit)


def pointing_from(ra, dec, theta_deg, toward="east"):
    """RA/Dec of the direction ``theta_deg`` from (ra, dec) along the local east (or north) great circle."""
    u = radec_to_unit(ra, dec)
    e, n = east_north(u)
    d = e if toward == "east" else n
    t = math.radians(theta_deg)
    return unit_to_radec(math.cos(t) * u + math.sin(t) * d)


def straylight_e(scene):
    """Straylight electrons per (unbinned) pixel over the exposure, the whole window, and the header cards."""
    setup = prepare(scene)
    s = scene.sensor()
    h, w = s.shape
    return setup.straylight(s.roi_y0, s.roi_y0 + h, s.roi_x0, s.roi_x0 + w), setup.source_cards


# ------------------------------------------------------------------------------------------ ephemeris
@pytest.mark.parametrize("epoch", ["2023-02-01T22:00:00", "2023-06-21T12:00:00", "2024-10-15T03:30:00"])
def test_sun_direction_matches_the_almanac_low_precision_formula(epoch):
    """The Astronomical Almanac's low-precision solar coordinates (good to 0.01 deg, 1950-2050), ecliptic of date
    precessed to J2000 by the general precession (5029.0966" per century): within 0.02 deg (the test bound of the
    brief is 0.1 deg)."""
    from astropy.time import Time

    n = Time(epoch, scale="utc").tt.jd - 2451545.0
    g = math.radians((357.528 + 0.9856003 * n) % 360)
    lam = 280.460 + 0.9856474 * n + 1.915 * math.sin(g) + 0.020 * math.sin(2 * g)
    lam0 = math.radians(lam - 5029.0966 / 3600 * n / 36525.0)
    eps0 = math.radians(23.4392911)
    ra = math.degrees(math.atan2(math.cos(eps0) * math.sin(lam0), math.cos(lam0))) % 360
    dec = math.degrees(math.asin(math.sin(eps0) * math.sin(lam0)))
    ra_s, dec_s = sun_radec(epoch)
    sep = math.degrees(math.acos(float(radec_to_unit(ra, dec) @ radec_to_unit(float(ra_s), float(dec_s)))))
    assert sep < 0.02, sep


def test_sun_at_the_solstice_and_its_distance_at_perihelion_and_aphelion():
    """December solstice 2023-12-22 03:27 UTC: Dec = -23.44 deg; 2023 perihelion (Jan 4 16:17 UTC) 0.983296 au,
    aphelion (Jul 6 20:07 UTC) 1.016681 au (USNO)."""
    _, dec = sun_radec("2023-12-22T03:27:00")
    assert abs(dec + 23.436) < 0.01
    lam, qe = np.array([400.0, 900.0]), np.array([0.5, 0.5])
    au = 149597870.7
    for epoch, r in (("2023-01-04T16:17:00", 0.983296), ("2023-07-06T20:07:00", 1.016681)):
        assert abs(bodies(epoch, None, lam, qe, ("sun",))["sun"].distance_km / au - r) < 2e-5


def test_moon_phase_law_reproduces_allens_table():
    """Allen (1973) phase law: magnitudes relative to full Moon, 0.23 at 10 deg ... 5.9 at 150 deg (the formula
    is a fit to this table: within 0.1 mag)."""
    table = {10: 0.23, 20: 0.51, 40: 1.06, 60: 1.62, 90: 2.63, 110: 3.48, 130: 4.44, 150: 5.9}
    for a, dm in table.items():
        assert abs(moon_v_magnitude(a) - moon_v_magnitude(0.0) - dm) < 0.1, a
    assert moon_v_magnitude(0.0) == pytest.approx(-12.73)
    assert moon_v_magnitude(0.0, 2 * 384400.0) == pytest.approx(-12.73 + 5 * math.log10(2))


# ---------------------------------------------------------------------------------------------- geometry
@pytest.mark.parametrize("roll", [0.0, 30.0, -90.0])
def test_azimuth_frame_is_the_frame_of_the_optics_field_angles(roll):
    """A star at (theta, phi) in the telescope frame images at -f tan(theta_x, theta_y) (optics) i.e. at pixel
    (u, -v) / pitch (scenes): exactly where the frame's own TAN WCS puts it, for any roll."""
    from scenes.projection import tan_wcs

    ra0, dec0 = 120.9, -29.3
    axes = telescope_axes(ra0, dec0, roll)
    w = tan_wcs(ra0, dec0, roll, 2.0, (1001, 1001))
    rng = np.random.default_rng(4)
    for _ in range(10):
        d = radec_to_unit(ra0 + rng.uniform(-0.3, 0.3), dec0 + rng.uniform(-0.3, 0.3))
        theta, phi = off_axis(d, axes)
        tx, ty = math.tan(math.radians(theta)) * math.cos(math.radians(phi)), \
            math.tan(math.radians(theta)) * math.sin(math.radians(phi))
        scale = 2.0 / 206264.806  # rad per pixel
        u, v = -tx / scale, -ty / scale  # the optics' image, in pixels
        x, y = w.wcs_world2pix(*unit_to_radec(d), 0)
        assert abs((500 + u) - x) < 1e-6 and abs((500 - v) - y) < 1e-6


# ------------------------------------------------------------------------------------------ photometry
def test_sun_straylight_is_solar_irradiance_times_pst_and_scales_with_both(tmp_path):
    """S = N_in PST A_pix T with N_in from the solar constant's blackbody through the QE (computed here), uniform;
    doubling the PST doubles it; perihelion / aphelion = (1.016681 / 0.983296)^2; a table is log-interpolated."""
    ratios = []
    for epoch in ("2023-01-04T16:17:00", "2023-07-06T20:07:00"):
        ra, dec = pointing_from(*sun_radec(epoch), 45.0)
        base = SMALL + [f"pointing.ra_deg={float(ra)}", f"pointing.dec_deg={float(dec)}", f"pointing.epoch='{epoch}'",
                        "exposure.time_s=10.0"]
        e1, cards = straylight_e(load_scene("default", base + ["effects.straylight={pst=1e-8, sources=['sun']}"]))
        e2, _ = straylight_e(load_scene("default", base + ["effects.straylight={pst=2e-8, sources=['sun']}"]))
        table = "effects.straylight={pst=[[30.0, 1e-6], [60.0, 1e-8]], sources=['sun']}"
        e3, c3 = straylight_e(load_scene("default", base + [table]))
        assert cards["SUNTHETA"][0] == pytest.approx(45.0, abs=1e-3) and np.ptp(e1) == 0
        assert np.allclose(e2, 2 * e1, rtol=1e-12)
        assert c3["SUNPST"][0] == pytest.approx(1e-7, rel=1e-4) and np.allclose(e3, 10 * e1, rtol=1e-4)
        ratios.append(e1[0, 0])
    s = load_scene("default", SMALL).sensor()
    lam = np.linspace(s.qe_wavelength_nm[0], s.qe_wavelength_nm[-1], 4001)
    n_in = np.trapezoid(solar_spectral_irradiance(lam) * s.qe_at(lam) * lam * 1e-9 / (H * C), lam)  # 1 au
    expect = n_in / 0.983296 ** 2 * 1e-8 * (s.pixel_pitch_um * 1e-6) ** 2 * 10.0
    assert ratios[0] == pytest.approx(expect, rel=2e-3)
    assert ratios[0] / ratios[1] == pytest.approx((1.016681 / 0.983296) ** 2, rel=1e-4)


def test_moon_straylight_follows_its_magnitude(tmp_path):
    """Moonlight = sunlight x 10^(-0.4 (V_moon + 26.76)): two epochs' ratio follows the two V magnitudes."""
    out = []
    for epoch in ("2023-02-05T18:00:00", "2023-02-12T18:00:00"):  # near full, then near last quarter
        m = bodies(epoch, None, np.array([400.0, 900.0]), np.array([0.5, 0.5]), ("moon",))["moon"]
        ra, dec = pointing_from(*unit_to_radec(m.unit), 30.0, "north")
        sc = load_scene("default", SMALL + [f"pointing.ra_deg={float(ra)}", f"pointing.dec_deg={float(dec)}",
                                            f"pointing.epoch='{epoch}'", "exposure.time_s=0.0001",
                                            "effects.straylight={pst=1e-6, sources=['moon']}"])
        e, cards = straylight_e(sc)
        out.append((e[0, 0], cards["MOONVMAG"][0], cards["MONPHI"][0], cards["MOONPHAS"][0]))
    assert out[0][3] < 20 and 60 < out[1][3] < 110
    assert out[0][0] / out[1][0] == pytest.approx(10 ** (-0.4 * (out[0][1] - out[1][1])), rel=2e-3)
    assert all(abs(o[2] - 270.0) < 1e-3 for o in out)  # south of the pointing = -y, azimuth 270 at roll 0


def test_sources_below_the_horizon_or_behind_the_earth_give_nothing(tmp_path):
    """A ground site at night: the Sun 45 deg off-axis but below the horizon adds nothing (the geocentre sees it);
    at noon it does. A spacecraft in the Earth's shadow sees no Sun."""
    site = "observer={lat_deg=43.6, lon_deg=1.44, alt_m=150.0}"
    for epoch, up in (("2023-06-21T23:00:00", False), ("2023-06-21T12:00:00", True)):
        ra, dec = pointing_from(*sun_radec(epoch), 45.0)
        base = SMALL + [f"pointing.ra_deg={float(ra)}", f"pointing.dec_deg={float(dec)}", f"pointing.epoch='{epoch}'",
                        "effects.straylight={pst=1e-8, sources=['sun']}"]
        e_site, _ = straylight_e(load_scene("default", base + [site]))
        e_geo, _ = straylight_e(load_scene("default", base))
        assert e_geo.min() > 0
        assert (e_site.min() > 0) == up and (up or e_site.max() == 0)
    # the ISS on 2019-12-09: find a time in the Earth's umbra (sun direction behind the Earth, within its radius)
    from scenes.objects import observer_from_table
    from scenes.objects.frames import as_time

    obs = observer_from_table({"tle_file": str(TLE)})
    lam, qe = np.array([400.0, 900.0]), np.array([0.5, 0.5])
    seen = set()
    for minutes in range(0, 95, 5):
        epoch = as_time("2019-12-09T12:00:00") + minutes * 60 / 86400 * __import__("astropy.units").units.day
        r = obs.posvel_gcrs(epoch.reshape(1))[0][0]
        s = bodies(epoch, obs, lam, qe, ("sun",))["sun"]
        umbra = r @ s.unit < 0 and np.linalg.norm(np.cross(r, s.unit)) < 6378.137 - 50
        lit = r @ s.unit > 0
        if umbra:
            assert s.electron_irradiance == 0
            seen.add("umbra")
        elif lit:
            assert s.electron_irradiance > 0
            seen.add("lit")
    assert seen == {"umbra", "lit"}


def test_straylight_is_not_vignetted_twice(tmp_path):
    """The PST map is already the focal plane's irradiance: with the chain's vignetting on, the straylight part of
    the noiseless frame stays uniform (the sky part is darkened)."""
    epoch = "2023-02-01T22:00:00"
    ra, dec = pointing_from(*sun_radec(epoch), 50.0)
    base = ["detector.preset='ml11002'", "detector.width=400", "detector.height=400", "detector.x0=0", "detector.y0=0",
            f"pointing.ra_deg={float(ra)}", f"pointing.dec_deg={float(dec)}", f"pointing.epoch='{epoch}'",
            "effects={vignetting={a2=0.3}}", "detector.dark_current_e_per_s=0"]
    for name, extra in (("a", []), ("b", ["effects.straylight={pst=1e-7, sources=['sun']}"])):
        render(load_scene("default", base + extra), tmp_path / f"{name}.fits", seed=1, noiseless=True, progress=False)
    a, b = (fits.getdata(tmp_path / f"{n}.fits").astype(float) for n in "ab")
    d = b - a
    assert a[0, 0] < 0.95 * a[-1, -1]  # the sky is vignetted toward the corner (0, 0)
    assert np.ptp(d) < 1e-5 * d.mean() + 1e-2 and d.mean() > 1
    assert "straylight" in fits.getheader(tmp_path / "b.fits")["EFFECTS"]


# ------------------------------------------------------------------------------------------- PST maps
def test_optics_map_lands_on_the_frame_in_the_right_orientation_and_is_cached(tmp_path, monkeypatch, mi):
    """pst = 'optics' with a stand-in map (a gradient along u and v): pixel (x, y) sees the map at (u, v) =
    ((x - cx) p, -(y - cy) p); the mean PST goes into the cards; the second render reads the cache."""
    import optics.straylight as osl

    monkeypatch.setenv("NEWTSIM_CACHE_DIR", str(tmp_path / "cache"))
    calls = []
    hu, hv = 26.7, 20.0

    def fake_map(design, mi_, angle_deg, azimuth_deg=0.0, rays=0, bins=(16, 12), seed=0, **kw):
        calls.append((angle_deg, azimuth_deg))
        nu, nv = bins
        u = -hu + (np.arange(nu) + 0.5) * 2 * hu / nu
        v = -hv + (np.arange(nv) + 0.5) * 2 * hv / nv
        return 1e-7 * (1 + 0.5 * u[None, :] / hu) * (1 + 0.25 * v[:, None] / hv), (-hu, hu, -hv, hv)

    monkeypatch.setattr(osl, "irradiance_map", fake_map)
    epoch = "2023-02-01T22:00:00"
    ra, dec = pointing_from(*sun_radec(epoch), 40.0)
    base = ["detector.preset='ml11002'", "effects={}", "detector.binning=1", f"pointing.ra_deg={float(ra)}",
            f"pointing.dec_deg={float(dec)}", f"pointing.epoch='{epoch}'",
            "effects.straylight={pst='optics', sources=['sun'], bins=[16, 12]}"]
    e, cards = straylight_e(load_scene("default", base))
    assert len(calls) == 1 and calls[0][0] == pytest.approx(40.0, abs=0.051)
    e_ref, _ = straylight_e(load_scene("default", base[:-1] + ["effects.straylight={pst=1e-7, sources=['sun']}"]))
    s = load_scene("default", base).sensor()
    p = s.pixel_pitch_um * 1e-3
    cx, cy = (s.sensor_width_px - 1) / 2, (s.sensor_height_px - 1) / 2
    for y, x in ((100, 200), (2500, 3900), (1335, 2003), (40, 3000)):
        u, v = (x - cx) * p, -(y - cy) * p  # inside the map's outer bin centres: bilinear is exact here
        assert e[y, x] / e_ref[0, 0] == pytest.approx((1 + 0.5 * u / hu) * (1 + 0.25 * v / hv), rel=1e-9)
    assert cards["SUNPST"][0] == pytest.approx(1e-7, rel=1e-9) and cards["STRAYPST"][0] == "optics"
    straylight_e(load_scene("default", base))
    assert len(calls) == 1  # from the cache


def test_traced_pst_map_of_the_design(tmp_path, monkeypatch, mi):
    """pst = 'optics' traced for real (100k paths): the frame's straylight is N_in x the traced map x A_pix x T,
    with the map's mean in the cards, and a second render is served from the cache."""
    monkeypatch.setenv("NEWTSIM_CACHE_DIR", str(tmp_path / "cache"))
    epoch = "2023-02-01T22:00:00"
    ra, dec = pointing_from(*sun_radec(epoch), 60.0)
    base = ["detector.preset='imx411'", "effects={}", "detector.binning=16", f"pointing.ra_deg={float(ra)}",
            f"pointing.dec_deg={float(dec)}", f"pointing.epoch='{epoch}'"]
    traced = "effects.straylight={pst='optics', rays=100000, sources=['sun']}"
    e, cards = straylight_e(load_scene("default", base + [traced]))
    pst = cards["SUNPST"][0]
    assert 0 < pst < 1e-2 and len(list((tmp_path / "cache").glob("straylight-map-*.json"))) == 1
    e_ref, _ = straylight_e(load_scene("default", base + [f"effects.straylight={{pst={pst}, sources=['sun']}}"]))
    assert e.mean() == pytest.approx(e_ref.mean(), rel=0.05)  # bilinear map over the sensor vs its bin mean
    assert e.std() > 0.05 * e.mean()  # not uniform


def test_table_interpolation_and_errors(tmp_path):
    t = [[10.0, 1e-4], [50.0, 1e-8], [80.0, 0.0]]
    assert pst_from_table(t, [10.0, 30.0, 50.0, 65.0, 90.0, 0.0]) == pytest.approx([1e-4, 1e-6, 1e-8, 5e-9, 0.0, 1e-4])
    for override, key in (("effects.straylight={pst=2.0}", "effects.straylight.pst"),
                          ("effects.straylight={pst=[[50.0, 1e-6], [10.0, 1e-8]]}", "effects.straylight.pst"),
                          ("effects.straylight={pst=1e-6, sources=['earth']}", "effects.straylight.sources"),
                          ("effects.straylight={pst=1e-6, rayz=10}", "effects.straylight.rayz"),
                          ("effects.straylight={sources=['sun']}", "effects.straylight.pst")):
        p = tmp_path / "scene.toml"
        p.write_text("[telescope]\ndesign = 'art'\n")
        with pytest.raises(DetectorError) as e:
            load_scene(str(p), [override])
        assert f"key '{key}" in str(e.value) and "scene.toml" in str(e.value) and "expected" in str(e.value)
