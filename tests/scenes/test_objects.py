"""Debris/satellite objects: tracks (RA/Dec + rates, TLE + SGP4), frames, brightness, errors.

Every check is against physics or an independent computation (hand-made TEME -> Earth-fixed rotation with
the IAU 1982 GMST, numerical integration of a Lambertian sphere), never a stored snapshot. No network.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import astropy.units as u
import numpy as np
import pytest
from astropy.time import Time

from scenes.objects import (
    M_SUN_V,
    Brightness,
    GroundSite,
    ObjectError,
    RateObject,
    SpaceObserver,
    TleObject,
    ab_photon_irradiance,
    check_pointing_visible,
    in_field,
    lambertian_sphere_phase,
    load_tle,
    object_from_table,
    object_track,
    observer_from_table,
    offline_iers,
    parse_tle,
    phase_function,
    pixel_dwell_time_s,
    plate_phase,
    propagate_teme,
    require_in_field,
    solar_photon_irradiance,
    solar_spectral_irradiance,
    specular_sphere_phase,
    sun_ab_magnitude,
    sunlit_fraction,
    tle_checksum,
    tumbling_plate_phase,
)
from scenes.objects.frames import (
    AU_KM,
    C_KM_S,
    angle_between_deg,
    apply,
    radec_to_unit,
    teme_to_gcrs,
)
from scenes.photometry import ab_electron_rate
from scenes.projection import tan_wcs

DATA = Path(__file__).parent / "data"
ISS_FILE = DATA / "iss_20191209.tle"
SYNTH_FILE = DATA / "synthetic.tle"
EPOCH = "2019-12-09T20:00:00"  # ISS 37 deg high over the test site, 0.65 d after the element epoch
SITE = GroundSite(15.0, 6.0, 300.0, "testsite")
ARCSEC = 1.0 / 3600.0


@pytest.fixture(scope="module")
def iss():
    return TleObject(load_tle(ISS_FILE), Brightness(photons=1000.0))


def _u(track):
    return radec_to_unit(track.ra_deg, track.dec_deg)


def _fix_checksum(line: str) -> str:
    return line[:68] + str(tle_checksum(line))


# ------------------------------------------------------------------------------------------ RA/Dec + rates
@pytest.mark.parametrize("dec_deg", [-29.24, 80.0])
def test_rate_track_moves_rate_times_t_along_a_great_circle(dec_deg):
    rra, rdec = 0.008558, -0.005486  # the scene contract's example (deg/s, rate_ra = dRA/dt cos Dec)
    obj = RateObject(120.96, dec_deg, rra, rdec, Brightness(photons=13836.0))
    tr = object_track(obj, "2023-02-01T22:00:00", 20.0, None, 9)
    dist = angle_between_deg(_u(tr), radec_to_unit(120.96, dec_deg))
    np.testing.assert_allclose(dist, math.hypot(rra, rdec) * tr.t_s, rtol=1e-9, atol=1e-12)
    # the convention: the RA change is rate_ra / cos(Dec) per second, the Dec change rate_dec
    ra, dec = tr.radec(np.array([1e-3]))
    assert abs((ra[0] - 120.96) / 1e-3 - rra / math.cos(math.radians(dec_deg))) < 1e-6
    assert abs((dec[0] - dec_deg) / 1e-3 - rdec) < 1e-6
    e, n = tr.rates_deg_s(np.array([0.0, 10.0, 20.0]))
    np.testing.assert_allclose(np.hypot(e, n), math.hypot(rra, rdec), rtol=1e-6)
    assert abs(e[0] - rra) < 1e-8 and abs(n[0] - rdec) < 1e-8
    assert tr.frame == "catalog" and tr.range_km is None


def test_rate_track_crosses_ra_zero_without_a_jump():
    tr = object_track(RateObject(359.999, 0.0, 0.01, 0.0, Brightness(photons=1.0)), EPOCH, 1.0, None, 5)
    ra, _ = tr.radec(np.linspace(0, 1, 11))
    step = np.diff(np.unwrap(np.radians(ra)))
    assert np.all(np.degrees(step) > 0) and np.all(np.degrees(step) < 0.002)


# ------------------------------------------------------------------------------------------ TLE tracks
def test_spline_error_far_below_a_pixel(iss):
    ref = object_track(iss, EPOCH, 30.0, SITE, 301)  # propagated every 0.1 s
    coarse = object_track(iss, EPOCH, 30.0, SITE)  # default: one sample per second
    err_arcsec = angle_between_deg(coarse.unit_vector(ref.t_s), _u(ref)) / ARCSEC
    assert len(coarse.t_s) == 31
    assert err_arcsec.max() < 0.01  # ART pixel: 1.93" (CCD), 0.79" (CMOS)
    np.testing.assert_allclose(coarse.range_at(ref.t_s), ref.range_km, atol=1e-4)


def _gmst82_rad(jd_ut1):
    """IAU 1982 GMST (Aoki et al. 1982; Vallado 2013, eq. 3-47), an independent implementation."""
    t = (jd_ut1 - 2451545.0) / 36525.0
    g = 67310.54841 + (876600.0 * 3600.0 + 8640184.812866) * t + 0.093104 * t ** 2 - 6.2e-6 * t ** 3
    return (g % 86400.0) / 86400.0 * 2.0 * np.pi


def _by_hand_altaz(tle, times, site):
    """Elevation, azimuth [deg] and range [km]: SGP4 TEME -> Earth-fixed by GMST 1982 -> WGS84 ENU."""
    with offline_iers():
        jd_ut1 = times.ut1.jd1 + times.ut1.jd2
    _, r, _ = tle.satrec().sgp4_array(times.jd1, times.jd2)
    g = _gmst82_rad(jd_ut1)
    pef = np.stack([np.cos(g) * r[:, 0] + np.sin(g) * r[:, 1], -np.sin(g) * r[:, 0] + np.cos(g) * r[:, 1],
                    r[:, 2]], axis=-1)
    a, f = 6378.137, 1.0 / 298.257223563
    e2 = f * (2.0 - f)
    lat, lon, h = math.radians(site.lat_deg), math.radians(site.lon_deg), site.alt_m / 1e3
    big_n = a / math.sqrt(1.0 - e2 * math.sin(lat) ** 2)
    site_xyz = np.array([(big_n + h) * math.cos(lat) * math.cos(lon), (big_n + h) * math.cos(lat) * math.sin(lon),
                         (big_n * (1.0 - e2) + h) * math.sin(lat)])
    rho = pef - site_xyz
    east = np.array([-math.sin(lon), math.cos(lon), 0.0])
    north = np.array([-math.sin(lat) * math.cos(lon), -math.sin(lat) * math.sin(lon), math.cos(lat)])
    up = np.array([math.cos(lat) * math.cos(lon), math.cos(lat) * math.sin(lon), math.sin(lat)])
    rng = np.linalg.norm(rho, axis=1)
    el = np.degrees(np.arcsin(rho @ up / rng))
    az = np.degrees(np.arctan2(rho @ east, rho @ north)) % 360.0
    return el, az, rng


def test_iss_from_a_ground_site_matches_an_independent_computation(iss):
    from astropy.coordinates import GCRS, AltAz, SkyCoord

    tr = object_track(iss, EPOCH, 10.0, SITE, 11, frame="geometric")
    times = Time(EPOCH, scale="utc") + tr.t_s * u.s
    el, az, rng = _by_hand_altaz(iss.tle, times, SITE)
    assert 30.0 < el.min()  # a real pass
    # polar motion (~0.3") and the 2-3 m site shift it causes are all that separates the two
    assert np.abs(tr.elevation_deg - el).max() < 1e-3
    assert np.abs((tr.azimuth_deg - az) * np.cos(np.radians(el))).max() < 1e-3
    assert np.abs(tr.range_km - rng).max() < 0.01
    # the GCRS RA/Dec, taken through astropy's own GCRS -> AltAz chain, lands on the hand-made alt/az
    # (that chain adds the diurnal aberration, <= 0.32", absent from the geometric frame)
    with offline_iers():
        loc = SITE.location()
        pos, vel = loc.get_gcrs_posvel(times)
        c = SkyCoord(tr.ra_deg * u.deg, tr.dec_deg * u.deg, frame=GCRS(obstime=times, obsgeoloc=pos, obsgeovel=vel))
        aa = c.transform_to(AltAz(obstime=times, location=loc))
    sep = angle_between_deg(radec_to_unit(aa.az.deg, aa.alt.deg), radec_to_unit(az, el))
    assert sep.max() < 1e-3


def test_light_time_and_aberration_have_their_expected_sizes(iss):
    geo = object_track(iss, EPOCH, 10.0, SITE, 11, frame="geometric")
    app_nolt = object_track(iss, EPOCH, 10.0, SITE, 11, frame="apparent", light_time=False)
    app = object_track(iss, EPOCH, 10.0, SITE, 11, frame="apparent")
    ast_nolt = object_track(iss, EPOCH, 10.0, SITE, 11, frame="astrometric", light_time=False)
    times = Time(EPOCH, scale="utc") + geo.t_s * u.s
    los = _u(geo)

    def perp(v):
        return np.linalg.norm(v - np.sum(v * los, axis=1, keepdims=True) * los, axis=1)

    # light-time: the object is seen where it was tau = R/c earlier: a shift v_perp * tau / R = v_perp / c
    v_sat = np.gradient(geo.object_gcrs_km, geo.t_s, axis=0)
    lt_shift = angle_between_deg(_u(app), _u(app_nolt))
    np.testing.assert_allclose(lt_shift, np.degrees(perp(v_sat) / C_KM_S), rtol=0.02)
    assert 4.0 * ARCSEC < lt_shift.min() and lt_shift.max() < 5.5 * ARCSEC
    # diurnal aberration (the site's rotation velocity): |v_perp| / c <= 0.32"
    _, v_site = SITE.posvel_gcrs(times)
    diurnal = angle_between_deg(_u(app_nolt), los)
    np.testing.assert_allclose(diurnal, np.degrees(perp(v_site) / C_KM_S), rtol=0.01)
    assert diurnal.max() < 0.33 * ARCSEC
    # annual aberration taken out for the catalogue frame: |V_earth,perp| / c, at most 20.5"
    from scenes.objects.frames import earth_barycentric_velocity_km_s

    annual = angle_between_deg(_u(ast_nolt), los)
    np.testing.assert_allclose(annual, np.degrees(perp(earth_barycentric_velocity_km_s(times)) / C_KM_S), rtol=0.01)
    assert annual.max() < 20.6 * ARCSEC


def test_geostationary_object_is_fixed_in_hour_angle():
    geo = TleObject(load_tle(SYNTH_FILE, "SYNTH-GEO"), Brightness(diameter_m=2.0, albedo=0.2))
    site = GroundSite(30.0, 112.0, 1000.0, "geo-site")  # the satellite sits over longitude 102 E
    tr = object_track(geo, "2019-12-10T00:00:00", 600.0, site, 61, frame="geometric")
    assert tr.elevation_deg.min() > 45.0
    assert np.ptp(tr.elevation_deg) < 0.01 and np.ptp(tr.azimuth_deg) < 0.01
    # hour angle = sidereal time - RA constant <=> RA advances at the sidereal rate
    sidereal_deg_s = 360.98564736629 / 86400.0
    d_ra = (tr.ra_deg[-1] - tr.ra_deg[0]) % 360.0
    assert abs(d_ra - sidereal_deg_s * 600.0) < 0.01
    assert 35000.0 < tr.range_km.min() < 38000.0


def test_space_based_observer_light_time_and_aberration():
    geo = TleObject(load_tle(SYNTH_FILE, "SYNTH-GEO"), Brightness(photons=1.0))
    sboc = SpaceObserver(load_tle(SYNTH_FILE, "SYNTH-SBOC"), "SBOC")
    epoch = "2019-12-10T00:00:00"
    app = object_track(geo, epoch, 10.0, sboc, 5, frame="apparent")
    app_nolt = object_track(geo, epoch, 10.0, sboc, 5, frame="apparent", light_time=False)
    geom = object_track(geo, epoch, 10.0, sboc, 5, frame="geometric")
    # the light-time iteration converged: the object at t - R/c is R away from the observer at t
    times = Time(epoch, scale="utc") + app.t_s * u.s
    m = teme_to_gcrs(times)
    r_teme, _ = propagate_teme(geo.tle, times.jd1, times.jd2 - app.range_km / C_KM_S / 86400.0)
    r_obs, v_obs = sboc.posvel_gcrs(times)
    np.testing.assert_allclose(np.linalg.norm(apply(m, r_teme) - r_obs, axis=1), app.range_km, atol=1e-5)
    assert 0.12 < (app.range_km / C_KM_S).min()  # ~0.13 s to GEO
    # aberration from the spacecraft's ~7.5 km/s: ~5", first order |v_perp| / c
    los = _u(geom)
    vperp = np.linalg.norm(v_obs - np.sum(v_obs * los, axis=1, keepdims=True) * los, axis=1)
    ab = angle_between_deg(_u(app_nolt), los)
    np.testing.assert_allclose(ab, np.degrees(vperp / C_KM_S), rtol=0.01)
    assert ab.max() < 5.3 * ARCSEC and np.linalg.norm(v_obs, axis=1).min() > 7.0


def test_space_observer_sees_no_object_behind_the_earth():
    geo = TleObject(load_tle(SYNTH_FILE, "SYNTH-GEO"), Brightness(photons=1.0), key="objects[1]")
    sboc = SpaceObserver(load_tle(SYNTH_FILE, "SYNTH-SBOC"), "SBOC")
    with pytest.raises(ObjectError, match=r"objects\[1\].*hidden by the Earth as seen from 'SBOC'"):
        object_track(geo, "2019-12-10T04:00:00", 10.0, sboc)


def test_track_summary_is_json():
    tr = object_track(RateObject(10.0, 20.0, 0.01, 0.0, Brightness(photons=1.0)), EPOCH, 2.0)
    assert json.loads(json.dumps(tr.summary()))["frame"] == "catalog"


# ------------------------------------------------------------------------------------------ errors
def test_bad_tle_lines_are_named():
    l1, l2 = load_tle(ISS_FILE).line1, load_tle(ISS_FILE).line2
    with pytest.raises(ObjectError, match=r"objects\[0\]\.tle.*line 1: checksum"):
        parse_tle([l1[:68] + str((int(l1[68]) + 1) % 10), l2], key="objects[0].tle")
    with pytest.raises(ObjectError, match="line 2 has 68 characters.*69 characters"):
        parse_tle([l1, l2[:68]], key="objects[0].tle")
    bad = _fix_checksum(l2[:8] + " 5x.6439" + l2[16:])
    with pytest.raises(ObjectError, match=r"columns 9-16 \(inclination"):
        parse_tle([l1, bad], key="objects[0].tle")
    with pytest.raises(ObjectError, match="catalogue numbers differ"):
        parse_tle([l1, _fix_checksum(l2[:2] + "25545" + l2[7:])])
    with pytest.raises(ObjectError, match="got 1 non-empty lines"):
        parse_tle(l1)


def test_decayed_satellite_is_reported():
    decay = TleObject(load_tle(SYNTH_FILE, "SYNTH-DECAY"), Brightness(photons=1.0), key="objects[2]")
    with pytest.raises(ObjectError, match=r"objects\[2\]\.tle.*has decayed: SGP4 error 1 .*\+2\.000 days"):
        object_track(decay, "2019-12-11T12:00:00", 1.0, None)
    with pytest.raises(ObjectError, match="has decayed: SGP4 error 6"):
        load_tle(SYNTH_FILE, 90004)


def test_object_below_the_horizon_names_the_site_and_elevation(iss):
    far = GroundSite(-15.0, 186.0, 0.0, "antipode")
    with pytest.raises(ObjectError, match=r"objects\[0\]': below the horizon of site 'antipode'.*elevation -\d+"):
        object_track(iss, EPOCH, 2.0, far)
    rate = RateObject(0.0, -89.0, 0.0, 0.0, Brightness(photons=1.0), key="objects[4]")
    with pytest.raises(ObjectError, match=r"objects\[4\]': below the horizon of site 'north'"):
        object_track(rate, EPOCH, 2.0, GroundSite(60.0, 0.0, 0.0, "north"))


def test_pointing_below_the_horizon():
    check_pointing_visible(0.0, 89.0, EPOCH, 2.0, GroundSite(60.0, 0.0, 0.0, "north"))
    with pytest.raises(ObjectError, match=r"key 'pointing'.*below the horizon of site 'north'.*elevation"):
        check_pointing_visible(0.0, -89.0, EPOCH, 2.0, GroundSite(60.0, 0.0, 0.0, "north"))


@pytest.mark.parametrize("t_exp", [0.0, -1.0])
def test_exposure_time_must_be_positive(iss, t_exp):
    with pytest.raises(ObjectError, match=r"key 'exposure.time_s'.*> 0 s"):
        object_track(iss, EPOCH, t_exp, SITE)


def test_in_field_and_the_outside_error():
    wcs = tan_wcs(120.95115, -29.25022, 0.0, 0.79, (1000, 1500))
    crossing = object_track(RateObject(120.96, -29.24, 0.008558, -0.005486, Brightness(photons=1.0)),
                            EPOCH, 2.0, None)
    assert in_field(crossing, wcs, shape=(1000, 1500))
    assert in_field(crossing, (120.95115, -29.25022, 0.2))
    far = object_track(RateObject(130.0, -29.0, 0.01, 0.0, Brightness(photons=1.0)), EPOCH, 2.0)
    assert not in_field(far, wcs, shape=(1000, 1500))
    with pytest.raises(ObjectError, match=r"objects\[3\].*object 3 stays outside the field"):
        require_in_field(far, wcs, 3, shape=(1000, 1500))
    # a fast object crosses the field between two samples: still found
    fast = object_track(RateObject(120.95115, -31.25022, 0.0, 1.0, Brightness(photons=1.0)), EPOCH, 4.0, None, 4)
    assert angle_between_deg(_u(fast), radec_to_unit(120.95115, -29.25022)).min() > 0.6  # no sample inside
    assert in_field(fast, (120.95115, -29.25022, 0.05))
    assert in_field(fast, tan_wcs(120.95115, -29.25022, 0.0, 0.79, (100, 100)), shape=(100, 100))


def test_scene_tables_and_their_errors():
    obj = object_from_table({"ra_deg": 120.96, "dec_deg": -29.24, "rate_ra_deg_s": 0.008558,
                             "rate_dec_deg_s": -0.005486, "photons": 13836}, 0)
    assert isinstance(obj, RateObject) and obj.brightness.kind == "photons"
    obj = object_from_table({"tle_file": SYNTH_FILE.name, "satellite": "synth-geo", "diameter_m": 1.0,
                             "albedo": 0.1}, 1, base_dir=DATA)
    assert isinstance(obj, TleObject) and obj.tle.norad_id == "90002"
    obj = object_from_table({"tle": ISS_FILE.read_text(), "mag": 3.0, "mag_system": "solar_v"}, 2)
    assert obj.tle.name == "ISS (ZARYA)"
    cases = [
        ({"ra_deg": 1.0, "dec_deg": 2.0, "photons": 1, "colour": 1}, r"objects\[5\]\.colour.*unknown key"),
        ({"ra_deg": 1.0, "dec_deg": 2.0}, r"objects\[5\]'.*no brightness"),
        ({"ra_deg": 1.0, "dec_deg": 2.0, "photons": 1, "mag": 3}, "several brightnesses"),
        ({"ra_deg": 1.0, "dec_deg": 2.0, "diameter_m": 1.0, "range_km": 1e3, "phase_angle_deg": 0},
         r"objects\[5\]\.albedo.*missing"),
        ({"ra_deg": 1.0, "dec_deg": 2.0, "diameter_m": 1.0, "albedo": 0.1}, r"objects\[5\]\.range_km"),
        ({"ra_deg": 1.0, "dec_deg": 2.0, "area_m2": 1.0, "albedo": 0.1, "range_km": 1e3, "phase_angle_deg": 0,
          "phase_function": "lambert"}, r"phase_function.*one of lambertian"),
        ({"ra_deg": 1.0, "dec_deg": 200.0, "photons": 1}, r"objects\[5\]\.dec_deg.*\[-90.0, 90.0\]"),
        ({"ra_deg": 1.0, "dec_deg": 2.0, "photons": 1, "tle_file": "x.tle"}, "both RA/Dec keys and a TLE"),
        ({"tle_file": str(SYNTH_FILE), "photons": 1}, "holds 4 element sets.*satellite"),
        ({"tle_file": str(SYNTH_FILE), "satellite": 12345, "photons": 1}, r"objects\[5\]\.satellite.*one of"),
        ({"tle": ["1 x", "2 y"], "photons": 1}, r"objects\[5\]\.tle.*69 characters"),
        ({"tle": ISS_FILE.read_text(), "photons": 1, "range_km": 5.0}, "computed from the orbit"),
    ]
    for table, pattern in cases:
        with pytest.raises(ObjectError, match=pattern):
            object_from_table(table, 5, base_dir=DATA)
    assert observer_from_table(None) is None
    site = observer_from_table({"name": "ART", "lat_deg": 38.96, "lon_deg": -6.02, "alt_m": 330.0})
    assert isinstance(site, GroundSite) and site.name == "ART"
    sc = observer_from_table({"tle_file": str(SYNTH_FILE), "satellite": "SYNTH-SBOC", "name": "SBOC"})
    assert isinstance(sc, SpaceObserver)
    with pytest.raises(ObjectError, match=r"observer\.lat_deg.*\[-90.0, 90.0\]"):
        observer_from_table({"lat_deg": 95.0, "lon_deg": 0.0})
    with pytest.raises(ObjectError, match="both a ground site and a TLE"):
        observer_from_table({"lat_deg": 5.0, "lon_deg": 0.0, "tle": ISS_FILE.read_text()})


# ------------------------------------------------------------------------------------------ brightness
def _sphere_grid(n=400):
    th = (np.arange(n) + 0.5) * np.pi / n
    ph = (np.arange(2 * n) + 0.5) * np.pi / n
    tt, pp = np.meshgrid(th, ph, indexing="ij")
    normals = np.stack([np.sin(tt) * np.cos(pp), np.sin(tt) * np.sin(pp), np.cos(tt)], axis=-1)
    d_omega = np.sin(tt) * (np.pi / n) ** 2
    return normals, d_omega


def test_phase_functions_integrate_to_the_intercepted_fraction():
    phi = np.linspace(0.0, np.pi, 20001)
    weight = 2.0 * np.pi * np.sin(phi)
    assert abs(np.trapezoid(lambertian_sphere_phase(phi) * weight, phi) - 1.0) < 1e-6
    assert abs(np.trapezoid(specular_sphere_phase(phi) * weight, phi) - 1.0) < 1e-6
    assert abs(np.trapezoid(phase_function("mixed", phi, specular_fraction=0.3) * weight, phi) - 1.0) < 1e-6
    assert abs(np.trapezoid(tumbling_plate_phase(phi) * weight, phi) - 0.5) < 1e-6  # mean cross-section A/2
    # geometric albedo p = pi F(0) rho: 2/3 rho (Lambert sphere), rho/4 (specular sphere)
    assert abs(np.pi * lambertian_sphere_phase(0.0) - 2.0 / 3.0) < 1e-12
    assert abs(np.pi * specular_sphere_phase(0.0) - 0.25) < 1e-12


@pytest.mark.parametrize("phase_deg", [0.0, 30.0, 90.0, 150.0])
def test_lambert_sphere_phase_function_against_a_surface_integral(phase_deg):
    # a unit-radius Lambertian sphere, unit irradiance, reflectance 1: I = (1/pi) sum max(0,n.s) max(0,n.o) dA;
    # with A = pi (cross-section) the phase function is I / A
    normals, d_omega = _sphere_grid()
    phi = math.radians(phase_deg)
    s, o = np.array([0.0, 0.0, 1.0]), np.array([math.sin(phi), 0.0, math.cos(phi)])
    intensity = np.sum(np.maximum(normals @ s, 0) * np.maximum(normals @ o, 0) * d_omega) / np.pi
    assert abs(intensity / np.pi - lambertian_sphere_phase(phi)) < 2e-5
    # the randomly tumbling two-sided plate is the orientation average of plate_phase (A = the plate area)
    avg = np.sum(plate_phase(normals, s, o) * d_omega) / (4.0 * np.pi)
    assert abs(avg - tumbling_plate_phase(phi)) < 2e-5


def test_magnitude_of_a_known_case():
    # 1 m^2 cross-section Lambertian sphere, albedo 0.1, 1000 km, full phase, Sun at 1 au
    b = Brightness(area_m2=1.0, albedo=0.1, phase_function="lambertian", range_km=1000.0, phase_angle_deg=0.0)
    tr = object_track(RateObject(10.0, 10.0, 0.1, 0.0, b), EPOCH, 1.0, None, 4)
    mag = b.magnitude(tr)
    # independent: the sphere's surface integral; by hand rho A (2 / (3 pi)) / R^2 = 0.1 * 0.21221 / 1e12
    # = 2.12e-14 -> m = -26.76 + 34.18 = 7.42
    normals, d_omega = _sphere_grid(300)
    radius_m = math.sqrt(1.0 / math.pi)
    z = np.array([0.0, 0.0, 1.0])
    intensity = 0.1 / np.pi * radius_m ** 2 * np.sum(np.maximum(normals @ z, 0) ** 2 * d_omega)
    expected = M_SUN_V - 2.5 * math.log10(intensity / 1e6 ** 2)
    assert abs(mag[0] - expected) < 0.005
    assert 7.35 < mag[0] < 7.5
    # a 1 m diameter sphere at 36000 km and 90 deg phase: 16.7, the usual faint GEO debris
    b2 = Brightness(diameter_m=1.0, albedo=0.1, range_km=36000.0, phase_angle_deg=90.0)
    tr2 = object_track(RateObject(10.0, 10.0, 0.004, 0.0, b2), EPOCH, 1.0, None, 4)
    assert 16.5 < b2.magnitude(tr2)[0] < 17.0


def test_photon_rates_are_consistent_between_the_three_specifications():
    lam = np.linspace(400.0, 720.0, 321)
    band = np.exp(-0.5 * ((lam - 551.0) / (88.0 / 2.3548)) ** 2)  # a V-like band
    area = 0.1  # m^2
    geom = {"range_km": 1000.0, "phase_angle_deg": 40.0}
    size = Brightness(diameter_m=2.0, albedo=0.2, **geom)
    tr = object_track(RateObject(10.0, 10.0, 0.1, 0.0, size), EPOCH, 2.0, None, 5)
    n_size = size.photon_rate(tr, aperture_area_m2=area, wavelength_nm=lam, throughput=band)
    # a solar-V magnitude equal to the size model's V magnitude gives the same photons
    v = Brightness(mag=float(size.magnitude(tr)[0]), mag_system="solar_v")
    np.testing.assert_allclose(v.photon_rate(tr, aperture_area_m2=area, wavelength_nm=lam, throughput=band), n_size)
    # AB magnitudes follow scenes.photometry exactly
    ab = Brightness(mag=12.0)
    n_ab = ab.photon_rate(tr, aperture_area_m2=area, wavelength_nm=lam, throughput=band)
    np.testing.assert_allclose(n_ab, ab_electron_rate(12.0, area, 1.0, lam, band), rtol=1e-12)
    # photons: the total spread over the exposure
    assert np.allclose(Brightness(photons=13836.0).photon_rate(tr, aperture_area_m2=area, wavelength_nm=lam,
                                                              throughput=band), 13836.0 / 2.0)
    # solar light: 1361 W/m^2 in total; the blackbody Sun in the V-like band is within 0.1 mag of the
    # measured m_AB(V) = -26.77 (Willmer 2018)
    wide = np.geomspace(10.0, 1e5, 200001)
    assert abs(np.trapezoid(solar_spectral_irradiance(wide), wide) - 1361.0) < 0.5
    assert abs(sun_ab_magnitude(lam, band) - (-26.77)) < 0.1
    assert abs(solar_photon_irradiance(lam, band, sun_ab_mag=-26.77) / ab_photon_irradiance(-26.77, lam, band)
               - 1.0) < 1e-12


def test_earth_shadow():
    sun = np.array([[AU_KM, 0.0, 0.0]])
    assert sunlit_fraction(np.array([[-7000.0, 0.0, 0.0]]), sun)[0] == 0.0
    assert sunlit_fraction(np.array([[7000.0, 0.0, 0.0]]), sun)[0] == 1.0
    assert sunlit_fraction(np.array([[0.0, 7000.0, 0.0]]), sun)[0] == 1.0
    y = np.linspace(6300.0, 6450.0, 301)
    f = sunlit_fraction(np.stack([np.full_like(y, -7000.0), y, np.zeros_like(y)], axis=-1), np.repeat(sun, 301, 0))
    assert f[0] == 0.0 and f[-1] == 1.0 and np.all(np.diff(f) >= 0) and np.any((f > 0.1) & (f < 0.9))


def test_object_in_the_earth_shadow_sends_no_light(iss):
    size = TleObject(iss.tle, Brightness(diameter_m=10.0, albedo=0.2))
    tr = object_track(size, EPOCH, 2.0, SITE, 5)
    assert np.all(tr.sunlit_fraction == 0.0)  # 20:00 UTC over the Sahel: the ISS is eclipsed
    lam = np.linspace(400.0, 900.0, 101)
    assert np.all(size.brightness.photon_rate(tr, aperture_area_m2=0.1, wavelength_nm=lam, throughput=1.0) == 0)
    assert np.all(np.isinf(size.brightness.magnitude(tr)))
    assert np.all((tr.phase_angle_deg > 0) & (tr.phase_angle_deg < 180))


def test_pixel_dwell_time():
    rate = math.hypot(0.008558, 0.005486)  # deg/s: 36.6"/s
    assert abs(pixel_dwell_time_s(rate, 0.79) - 0.79 / (rate * 3600.0)) < 1e-12  # 21.6 ms
    assert abs(pixel_dwell_time_s(rate, 0.79, psf_fwhm_arcsec=2.0) - 2.79 / (rate * 3600.0)) < 1e-12
    assert pixel_dwell_time_s(1e-6, 0.79, exposure_time_s=2.0) == 2.0
    assert pixel_dwell_time_s(0.0, 0.79, exposure_time_s=2.0) == 2.0
