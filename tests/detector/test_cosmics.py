"""Cosmic rays: Bethe energy loss, shielding, incidence law, hit statistics, rasterisation, chain use.

Independent reference numbers
-----------------------------
* NIST PSTAR (Berger, Coursey, Zucker & Chang, NIST SRD 124; ICRU Report 49, 1993): electronic stopping
  power [MeV cm^2/g] and CSDA range [g/cm^2] of protons in Si, Al and Cu (table values quoted below).
* PDG "Atomic and nuclear properties of materials": minimum ionisation <-dE/dx>_min = 1.664 (Si),
  1.615 (Al), 1.403 (Cu) MeV cm^2/g, reached near beta gamma ~ 3.5.
* 3.6 eV per electron-hole pair in Si: a minimum-ionising particle frees 1.664 * 2.329 MeV/cm / 3.6 eV
  = 107.6 e-/um on average.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from detector import Detector, DetectorError, build_effects, make_sensor
from detector import cosmics as cr
from detector.effects.base import Stage, Tile

# (material, kinetic energy [MeV], PSTAR electronic stopping power [MeV cm^2/g])
PSTAR_STOPPING = [
    ("Si", 10.0, 34.58), ("Si", 100.0, 5.836), ("Si", 1000.0, 1.801), ("Si", 10000.0, 1.830),
    ("Al", 10.0, 33.75), ("Al", 100.0, 5.676), ("Al", 1000.0, 1.749),
    ("Cu", 10.0, 27.08), ("Cu", 100.0, 4.850), ("Cu", 1000.0, 1.521),
]
# (material, kinetic energy [MeV], PSTAR CSDA range [g/cm^2])
PSTAR_RANGE = [
    ("Si", 10.0, 0.1665), ("Si", 100.0, 9.737), ("Si", 1000.0, 400.7),
    ("Al", 10.0, 0.1705), ("Al", 30.0, 1.180), ("Al", 100.0, 10.01),
    ("Cu", 10.0, 0.2199), ("Cu", 100.0, 11.85),
]
# PDG minimum ionisation [MeV cm^2/g]
PDG_MIN = {"Si": 1.664, "Al": 1.615, "Cu": 1.403}


# --- energy loss ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("mat,energy,pstar", PSTAR_STOPPING)
def test_bethe_matches_pstar(mat, energy, pstar):
    s = float(cr.bethe_mass_stopping_power(energy, mat))
    assert s == pytest.approx(pstar, rel=0.01)


def test_linear_stopping_power_is_density_times_mass_stopping_power():
    # 100 MeV proton in Si: 5.836 MeV cm^2/g (PSTAR) * 2.329 g/cm^3 = 13.59 MeV/cm
    assert float(cr.stopping_power_mev_per_cm(100.0, "Si")) == pytest.approx(5.836 * 2.329, rel=0.01)


@pytest.mark.parametrize("mat", ["Si", "Al", "Cu"])
def test_minimum_ionisation(mat):
    mu = cr.PARTICLES["muon"]
    bg = np.logspace(0, 1.5, 3000)
    t = mu.mass_mev * (np.sqrt(1 + bg * bg) - 1)
    s = cr.bethe_mass_stopping_power(t, mat, 1, mu.mass_mev)
    i = int(np.argmin(s))
    assert s[i] == pytest.approx(PDG_MIN[mat], rel=0.005)
    assert 3.0 <= bg[i] <= 3.6
    # the density effect is what flattens the relativistic rise (PDG fig. 34.2)
    s_nodelta = cr.bethe_mass_stopping_power(t[-1], mat, 1, mu.mass_mev, with_density_effect=False)
    assert s_nodelta > s[-1] * 1.05


def test_mip_electrons_per_micron():
    mu = cr.PARTICLES["muon"]
    t_min = mu.mass_mev * (np.sqrt(1 + 3.5 ** 2) - 1)  # beta gamma = 3.5
    dep, travelled = cr.deposit_in_layer(t_min, 1e-4, "Si", particle=mu)  # 1 um of Si
    assert travelled == pytest.approx(1e-4)
    e_per_um = float(cr.electrons_from_energy(dep))
    assert e_per_um == pytest.approx(1.664 * 2.329 * 1e-4 * 1e6 / 3.6, rel=0.01)  # 107.6 e-/um
    assert 105 < e_per_um < 110


def test_charge_scales_as_z_squared():
    # an alpha has z = 2: four times the loss of a proton of the same velocity (Bethe, PDG eq. 34.5)
    p, a = cr.PARTICLES["proton"], cr.PARTICLES["alpha"]
    t_p = 100.0
    t_a = t_p * a.mass_mev / p.mass_mev
    ratio = cr.bethe_mass_stopping_power(t_a, "Si", 2, a.mass_mev) / cr.bethe_mass_stopping_power(t_p, "Si")
    assert float(ratio) == pytest.approx(4.0, rel=0.002)  # Tmax differs slightly with the mass


# --- ranges and shielding -------------------------------------------------------------------------------------

@pytest.mark.parametrize("mat,energy,pstar", PSTAR_RANGE)
def test_csda_range_matches_pstar(mat, energy, pstar):
    assert float(cr.csda_range_g_cm2(energy, mat)) == pytest.approx(pstar, rel=0.03)


@pytest.mark.parametrize("energy,thickness,mat", [(50.0, 2.699 * 0.5, "Al"), (200.0, 8.96 * 2.0, "Cu"),
                                                   (100.0, 2.329e-3, "Si")])
def test_range_table_agrees_with_direct_integration(energy, thickness, mat):
    e_table = float(cr.residual_energy_mev(energy, thickness, mat))
    e_ivp = cr.slow_down_ivp_mev(energy, thickness, mat)
    assert e_table == pytest.approx(e_ivp, rel=1e-3)
    assert energy - e_table == pytest.approx(energy - e_ivp, rel=5e-3)  # the energy lost, too


def test_shield_stops_protons_below_the_range_energy():
    # 10 mm Al = 2.699 g/cm^2; PSTAR: R(45 MeV) = 2.427, R(50 MeV) = 2.928 g/cm^2 => cut-off ~ 47.7 MeV
    out = cr.residual_energy_mev(np.array([20.0, 45.0, 47.0, 49.0, 60.0, 1000.0]), 2.699, "Al")
    assert np.all(out[:3] == 0)
    assert np.all(out[3:] > 0)
    # PSTAR: R(60) = 4.050 => residual range 1.351 g/cm^2 lies between R(30) = 1.180 and R(35) = 1.552
    assert 30.0 < out[4] < 35.0
    # above the range the loss equals thickness x mean stopping power: 1 GeV loses ~ 2.699 * 1.75 MeV
    assert 1000.0 - out[5] == pytest.approx(2.699 * 1.749, rel=0.02)


def test_particle_stopping_in_the_layer_deposits_its_energy():
    # a 1 MeV proton has a CSDA range of ~ 16 um in Si (PSTAR 3.835e-3 g/cm^2 = 16.5 um; ours is shorter
    # because the low-energy power law is approximate), far less than a 100 um path
    dep, travelled = cr.deposit_in_layer(np.array([1.0]), np.array([100e-4]), "Si")
    assert dep[0] == pytest.approx(1.0)
    assert 10e-4 < travelled[0] < 18e-4


# --- samplers --------------------------------------------------------------------------------------------------

def test_cosine_law_incidence_chi_square():
    rng = np.random.default_rng(11)
    c = cr.sample_cos_theta(rng, 200_000)
    edges = np.linspace(0, 1, 21)
    observed, _ = np.histogram(c, edges)
    expected = c.size * np.diff(edges ** 2)  # P(cos theta < c) = c^2 for a flux through a plane
    chi2 = np.sum((observed - expected) ** 2 / expected)
    assert stats.chi2.sf(chi2, df=edges.size - 2) > 1e-3
    # mean cos(theta) = 2/3 for the cosine law (1/2 for an isotropic flux on a sphere)
    assert c.mean() == pytest.approx(2 / 3, abs=0.003)


def test_cosine_law_clamps_grazing_tracks():
    c = cr.sample_cos_theta(np.random.default_rng(1), 100_000, theta_max_deg=60.0)
    assert c.min() == pytest.approx(0.5)
    assert np.mean(c == c.min()) == pytest.approx(0.25, abs=0.01)  # P(cos < 0.5) = 0.25


def test_power_law_spectrum_ks():
    e_min, e_max, g = 100.0, 1e5, 2.7
    e = cr.sample_power_law_mev(np.random.default_rng(5), 50_000, e_min, e_max, g)
    a = 1 - g

    def cdf(x):
        return (x ** a - e_min ** a) / (e_max ** a - e_min ** a)

    assert stats.kstest(e, cdf).pvalue > 1e-3
    assert np.median(e) == pytest.approx(e_min * 2 ** (1 / (g - 1)), rel=0.02)


# --- rasterisation and diffusion ---------------------------------------------------------------------------------

def test_rasterisation_by_hand():
    # a horizontal segment from pixel centre 0 to pixel centre 2: lengths 0.5, 1, 0.5 inside pixels 0, 1, 2
    idx, rows, cols, q = cr.rasterise_segments([0.0], [0.0], [2.0], [0.0], [100.0])
    got = {int(c): v for c, v in zip(cols, q)}
    assert got == pytest.approx({0: 25.0, 1: 50.0, 2: 25.0})
    assert set(rows) == {0}
    # a point deposits everything in one pixel
    _, rows, cols, q = cr.rasterise_segments([3.2], [4.7], [3.2], [4.7], [7.0])
    assert list(rows) == [5] and list(cols) == [3] and q.tolist() == [7.0]


def test_rasterisation_conserves_charge_and_matches_fine_sampling():
    rng = np.random.default_rng(2)
    n = 200
    x0, y0 = rng.uniform(0, 50, n), rng.uniform(0, 50, n)
    ang, length = rng.uniform(0, 2 * np.pi, n), rng.exponential(6.0, n)
    x1, y1 = x0 + length * np.cos(ang), y0 + length * np.sin(ang)
    q = rng.uniform(100, 5000, n)
    idx, rows, cols, e = cr.rasterise_segments(x0, y0, x1, y1, q)
    np.testing.assert_allclose(np.bincount(idx, e, minlength=n), q, rtol=1e-12)
    # brute force: 20000 equally spaced sub-samples per segment (0.0003 px steps)
    img = np.zeros((80, 80))
    np.add.at(img, (rows + 10, cols + 10), e)
    ref = np.zeros((80, 80))
    m = 20000
    t = (np.arange(m) + 0.5) / m
    for i in range(n):
        xs, ys = x0[i] + t * (x1[i] - x0[i]), y0[i] + t * (y1[i] - y0[i])
        np.add.at(ref, (np.floor(ys + 0.5).astype(int) + 10, np.floor(xs + 0.5).astype(int) + 10), q[i] / m)
    assert np.abs(img - ref).max() < 1e-3 * q.max()


def test_diffusion_kernel():
    k = cr.diffusion_kernel(0.8)
    assert k.sum() == pytest.approx(1.0, abs=1e-15)
    x = np.arange(k.size) - k.size // 2
    # a Gaussian integrated over unit pixels has variance sigma^2 + 1/12
    assert np.sum(k * x * x) == pytest.approx(0.8 ** 2 + 1 / 12, rel=2e-3)
    assert cr.diffusion_kernel(0.0).tolist() == [1.0]


@pytest.mark.parametrize("sigma", [0.0, 0.5, 2.0])
def test_add_charge_conserves_and_paths_agree(sigma):
    rng = np.random.default_rng(4)
    k = cr.diffusion_kernel(sigma)
    r = k.size // 2
    h, w = 60, 70
    for n in (2, 20, 5000):  # scatter-add, histogram and convolution branches
        rows = rng.integers(r, h - r, n)
        cols = rng.integers(r, w - r, n)
        q = rng.uniform(1, 100, n)
        img = np.zeros((h, w))
        cr.add_charge(img, rows, cols, q, k)
        assert img.sum() == pytest.approx(q.sum(), rel=1e-12)
        ref = np.zeros((h, w))
        for dy in range(-r, r + 1):
            for dx in range(-r, r + 1):
                np.add.at(ref, (rows + dy, cols + dx), q * k[dy + r] * k[dx + r])
        np.testing.assert_allclose(img, ref, rtol=1e-9, atol=1e-9)


# --- the effect ---------------------------------------------------------------------------------------------------

def _sensor(**kw):
    return make_sensor("imx411", {"width": 256, "height": 256, **kw})


def _effect(params, sensor=None):
    s = sensor or _sensor()
    return build_effects({"cosmic_rays": params}, s)[0]


def test_hit_count_is_poisson_with_mean_flux_area_time():
    s = _sensor()
    eff = _effect({"flux_per_cm2_s": 100.0, "energy_mev": 1000.0}, s)
    area_cm2 = (256 * 3.76e-4) ** 2
    mu = 100.0 * area_cm2 * 20.0  # 1.85 hits per frame
    assert eff.expected_hits(20.0) == pytest.approx(mu)
    counts = np.array([eff.prepare_frame(20.0, seed).tracks.size for seed in range(600)])
    assert abs(counts.mean() - mu) < 4 * np.sqrt(mu / counts.size)
    assert counts.var(ddof=1) / counts.mean() == pytest.approx(1.0, abs=0.25)  # Poisson dispersion


def test_environment_presets():
    s = _sensor()
    ground = _effect({}, s)
    assert ground.flux_per_cm2_s == pytest.approx(1 / 60)  # PDG: ~ 1 muon cm^-2 min^-1 at sea level
    assert ground.particle.name == "muon"
    assert _effect({"environment": "saa"}, s).flux_per_cm2_s == 1100.0  # Miles et al. 2021
    assert _effect({"environment": "leo", "flux_per_cm2_s": 3.0}, s).flux_per_cm2_s == 3.0  # override
    for env in cr.ENVIRONMENTS.values():
        assert env.source and env.flux_per_cm2_s > 0


def test_normal_incidence_mip_charge_and_track_geometry():
    # theta_max = 0 forces normal incidence: a point deposit of d * 107.6 e-/um for a MIP muon
    s = _sensor()
    mu = cr.PARTICLES["muon"]
    eff = _effect({"flux_per_cm2_s": 200.0, "particle": "muon", "theta_max_deg": 0.0, "depletion_um": 10.0,
                   "energy_mev": float(mu.mass_mev * (np.sqrt(1 + 3.5 ** 2) - 1))}, s)
    t = eff.prepare_frame(30.0, 1).tracks
    assert t.size > 0
    np.testing.assert_allclose(t["electrons"], 10 * 107.6, rtol=0.01)
    np.testing.assert_allclose(t["x_end_sensor"], t["x_sensor"])
    # oblique tracks: projected length = d tan(theta) / pitch
    eff = _effect({"flux_per_cm2_s": 200.0, "energy_mev": 1000.0, "depletion_um": 15.0}, s)
    t = eff.prepare_frame(30.0, 2).tracks
    length = np.hypot(t["x_end_sensor"] - t["x_sensor"], t["y_end_sensor"] - t["y_sensor"])
    np.testing.assert_allclose(length, 15.0 * np.tan(np.radians(t["theta_deg"])) / 3.76, rtol=1e-6)
    # charge grows with the path d / cos(theta) (the 1 GeV proton barely slows in 15 um)
    per_um = t["electrons"] * np.cos(np.radians(t["theta_deg"])) / 15.0
    np.testing.assert_allclose(per_um, per_um[0], rtol=1e-4)


def test_shielding_in_the_effect():
    s = _sensor()
    base = {"flux_per_cm2_s": 300.0, "particle": "proton", "theta_max_deg": 0.0, "shielding_material": "aluminium",
            "shielding_mm": 10.0}
    # 40 MeV protons cannot cross 2.699 g/cm^2 of Al (PSTAR range 1.97 g/cm^2): no hits
    assert _effect({**base, "energy_mev": 40.0}, s).prepare_frame(20.0, 1).tracks.size == 0
    # 60 MeV protons come out with 32.4 MeV: PSTAR residual range R(60) - 2.699 = 1.351 g/cm^2, which
    # log-interpolates between R(30) = 1.180 and R(35) = 1.552 to 32.37 MeV
    t = _effect({**base, "energy_mev": 60.0}, s).prepare_frame(20.0, 1).tracks
    assert t.size > 0
    np.testing.assert_allclose(t["energy_mev"], 32.37, rtol=0.01)
    np.testing.assert_allclose(t["energy_incident_mev"], 60.0)
    # the slowed protons ionise more: PSTAR Si S(32.4 MeV) / S(60 MeV) = 13.82 / 8.561 = 1.615
    unshielded = {k: v for k, v in base.items() if not k.startswith("shield")}
    t60 = _effect({**unshielded, "energy_mev": 60.0}, s).prepare_frame(20.0, 1).tracks
    assert t["electrons"].mean() / t60["electrons"].mean() == pytest.approx(13.82 / 8.561, rel=0.01)
    # 10 mm of copper (8.96 g/cm^2): 100 MeV protons (PSTAR range 11.85 g/cm^2) come out with 44.6 MeV
    # (residual 2.89 g/cm^2 between R(40) = 2.389 and R(45) = 2.936)
    tc = _effect({**base, "shielding_material": "copper", "energy_mev": 100.0}, s).prepare_frame(20.0, 1).tracks
    assert tc.size > 0
    np.testing.assert_allclose(tc["energy_mev"], 44.6, rtol=0.02)
    # oblique incidence crosses shield / cos(theta): more protons stop, and the survivors are slower
    oblique = _effect({**base, "theta_max_deg": 89.0, "energy_mev": 60.0}, s)
    obl = oblique.prepare_frame(4000.0, 1).tracks
    n_in = oblique.expected_hits(4000.0)  # 1114 particles reach the shield
    cos_cut = 2.699 / 4.050  # PSTAR: stopped when 2.699 / cos(theta) > R(60) = 4.050 g/cm^2
    assert obl.size / n_in == pytest.approx(1 - cos_cut ** 2, abs=0.07)  # P(cos theta > c) = 1 - c^2, 3 sigma
    assert np.all(np.cos(np.radians(obl["theta_deg"])) > cos_cut * 0.98)
    assert np.all(obl["energy_mev"] <= 32.4 * 1.001)


def test_parameter_validation():
    s = _sensor()
    with pytest.raises(DetectorError):
        _effect({"depletion_um": -1.0}, s)
    with pytest.raises(DetectorError):
        _effect({"shielding_mm": 2.0}, s)  # a thickness without a material
    with pytest.raises(DetectorError):
        _effect({"environment": "moon"}, s)
    with pytest.raises(DetectorError):
        _effect({"energy_min_mev": 1e5, "energy_max_mev": 1e4}, s)
    with pytest.raises(DetectorError):
        _effect({"environment": "leo", "energy_max_mev": 300.0}, s)  # below the preset's 355 MeV lower end
    # a frame expecting absurdly many hits is refused with a clear message instead of exhausting memory
    full = make_sensor("imx411")
    with pytest.raises(DetectorError, match="hits expected"):
        _effect({"flux_per_cm2_s": 1e5}, full).prepare_frame(1000.0, 1)


def _whole_tile(s, state, exptime_s, seed, name="cosmic_rays"):
    h, w = s.shape
    return Tile(s, 0, s.roi_y0, s.roi_y0 + h, s.roi_x0, s.roi_x0 + w, exptime_s, seed, state={name: state})


def test_charge_conservation_through_apply():
    # a tile 200 px larger than the read-out window on every side holds every track (projected lengths
    # are at most d tan(89 deg) / pitch = 152 px): the charge added equals the electrons deposited
    s = _sensor()
    for sigma in (0.0, 0.5, 2.0):
        eff = _effect({"flux_per_cm2_s": 500.0, "environment": "leo", "diffusion_sigma_px": sigma}, s)
        st = eff.prepare_frame(10.0, 9)
        assert st.tracks.size > 20
        m = 200
        tile = Tile(s, 0, s.roi_y0 - m, s.roi_y0 + 256 + m, s.roi_x0 - m, s.roi_x0 + 256 + m, 10.0, 9,
                    state={"cosmic_rays": st})
        img = np.zeros(tile.shape, np.float32)
        eff.apply(Stage.CHARGE, tile, img)
        assert img.sum(dtype=np.float64) == pytest.approx(st.tracks["electrons"].sum(), rel=1e-5)
        assert img.min() >= 0


def test_tiles_reproduce_the_whole_frame():
    # band tiles (rows 0-99, 100-199, 200-255) add exactly what one whole-frame tile adds: continuity
    s = _sensor()
    eff = _effect({"flux_per_cm2_s": 800.0, "environment": "leo", "diffusion_sigma_px": 1.0}, s)
    st = eff.prepare_frame(10.0, 4)
    whole = _whole_tile(s, st, 10.0, 4)
    ref = np.zeros(whole.shape, np.float32)
    eff.apply(Stage.CHARGE, whole, ref)
    bands = np.zeros_like(ref)
    for i, (r0, r1) in enumerate([(0, 100), (100, 200), (200, 256)]):
        t = Tile(s, i, s.roi_y0 + r0, s.roi_y0 + r1, s.roi_x0, s.roi_x0 + 256, 10.0, 4, state={"cosmic_rays": st})
        part = np.zeros(t.shape, np.float32)
        eff.apply(Stage.CHARGE, t, part)
        bands[r0:r1] = part
    np.testing.assert_allclose(bands, ref, rtol=1e-5, atol=1e-3)
    assert ref.sum() > 0


def test_zero_flux_is_identity():
    s = _sensor()
    frame0 = Detector(s, []).expose(50.0, 5.0, frame_seed=8)
    frame1 = Detector(s, build_effects({"cosmic_rays": {"flux_per_cm2_s": 0.0}}, s)).expose(50.0, 5.0, frame_seed=8)
    assert np.array_equal(frame0, frame1)
    det = Detector(s, build_effects({"cosmic_rays": {"environment": "saa"}}, s))
    assert np.array_equal(det.expose(50.0, 0.0, frame_seed=8), Detector(s, []).expose(50.0, 0.0, frame_seed=8))


def test_same_seed_same_bytes():
    s = _sensor()
    det = Detector(s, build_effects({"cosmic_rays": {"flux_per_cm2_s": 300.0}}, s))
    a, b = det.expose(10.0, 10.0, frame_seed=5), det.expose(10.0, 10.0, frame_seed=5)
    assert a.tobytes() == b.tobytes()
    assert not np.array_equal(a, det.expose(10.0, 10.0, frame_seed=6))
    ta, tb = det.truth(10.0, 5)["COSMICS"], det.truth(10.0, 5)["COSMICS"]
    assert ta.tobytes() == tb.tobytes()


def test_through_the_real_chain():
    s = make_sensor("imx411", {"width": 960, "height": 960})
    effects = build_effects({"cosmic_rays": {"flux_per_cm2_s": 50}}, s)
    det = Detector(s, effects)
    frame = det.expose(0.0, 10.0, frame_seed=3)
    truth = det.truth(10.0, 3)["COSMICS"]
    # mean number of hits F A t = 50 * (960 * 3.76e-4)^2 * 10 = 65.2
    assert abs(truth.size - 65.2) < 4 * np.sqrt(65.2)
    ref = Detector(s, []).expose(0.0, 10.0, frame_seed=3)  # the same noise without the cosmics
    diff = frame.astype(np.int64) - ref.astype(np.int64)
    # the charge the effect meant to add, from its own per-frame state
    st = effects[0].prepare_frame(10.0, 3)
    expected = np.zeros(s.shape, np.float32)
    effects[0].apply(Stage.CHARGE, _whole_tile(s, st, 10.0, 3), expected)
    # the frame differs from the cosmic-free one by exactly that charge, to the ADU quantisation
    g = s.gain_e_per_adu
    assert np.all(np.abs(diff * g - expected) <= g + 1e-3)
    # every track shows at its truth position (nearest pixel to the midpoint of the projected segment)
    for t in truth:
        xm, ym = 0.5 * (t["x"] + t["x_end"]), 0.5 * (t["y"] + t["y_end"])
        ix, iy = int(np.floor(xm + 0.5)), int(np.floor(ym + 0.5))
        if 2 <= ix < 958 and 2 <= iy < 958 and t["electrons"] > 200:
            assert diff[iy - 1:iy + 2, ix - 1:ix + 2].max() * g > 30
    # no charge far from the tracks
    far = np.ones(s.shape, bool)
    for t in truth:
        x0, x1 = sorted((t["x"], t["x_end"]))
        y0, y1 = sorted((t["y"], t["y_end"]))
        far[max(int(y0) - 4, 0):int(y1) + 6, max(int(x0) - 4, 0):int(x1) + 6] = False
    assert np.all(diff[far] == 0)
    # thread count does not change a byte
    f1 = Detector(s, effects, workers=1).expose(0.0, 10.0, frame_seed=3)
    f2 = Detector(s, effects, workers=2).expose(0.0, 10.0, frame_seed=3)
    assert f1.tobytes() == f2.tobytes() == frame.tobytes()


def test_truth_coordinates_follow_binning():
    s = make_sensor("ml11002", {"width": 200, "height": 100, "binning": 2, "x0": 10, "y0": 20})
    eff = build_effects({"cosmic_rays": {"flux_per_cm2_s": 500.0}}, s)[0]
    st = eff.prepare_frame(10.0, 1)
    t = eff.truth(st)["COSMICS"]
    assert t.size == st.tracks.size > 0
    # output pixel k of a 2x2-binned frame is centred on sensor coordinate x0 + 2k + 0.5
    np.testing.assert_allclose(t["x"], (st.tracks["x_sensor"] - 10.5) / 2)
    np.testing.assert_allclose(t["y"], (st.tracks["y_sensor"] - 20.5) / 2)
    assert np.all((t["x"] > -0.6) & (t["x"] < 100) & (t["y"] > -0.6) & (t["y"] < 50))
    assert eff.truth(None)["COSMICS"].size == 0
