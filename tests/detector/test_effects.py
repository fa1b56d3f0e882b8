"""Each optional effect against an independent result: analytic laws, scaling, large-frame statistics."""

import numpy as np
import pytest
from helpers import small_sensor
from scipy import stats

from detector import Detector, build_effects, make_sensor
from detector.effects.blooming import bleed_columns
from detector.effects.readout import channel_crosstalk, ktc_noise_e


def small(**kw):
    return small_sensor("ml11002", **kw)


# zero strength is the identity for every registered effect: tests/detector/test_effect_contract.py


def test_prnu_map_has_mean_one_and_the_given_std():
    s = small(dark_current_e_per_s=0.0)
    m = Detector(s, build_effects({"prnu": {"sigma": 0.02}}, s)).expose(1000.0, 1.0, 1, noiseless=True) / 1000.0
    n = m.size
    assert abs(m.mean() - 1) < 5 * 0.02 / np.sqrt(n)
    assert abs(m.std() - 0.02) < 5 * 0.02 / np.sqrt(2 * n)


def test_prnu_adds_quadratic_variance():
    """Var = S + (sigma S)^2 + ... : fixed-pattern noise grows linearly with signal (Janesick 2007 ch. 8)."""
    s = small(dark_current_e_per_s=0.0, read_noise_e=0.0, gain_e_per_adu=1.0)
    S, p = 10000.0, 0.01
    f = Detector(s, build_effects({"prnu": {"sigma": p}}, s)).expose(S, 1.0, 2).astype(float)
    exp = S + (p * S) ** 2 + 1 / 12
    assert abs(f.var() - exp) < 5 * exp * np.sqrt(2 / f.size)


def test_dsnu_lognormal_keeps_the_mean_dark_current():
    s = small(dark_current_e_per_s=2.0)
    m = Detector(s, build_effects({"dsnu": {"sigma": 0.5}}, s)).expose(0.0, 100.0, 1, noiseless=True)
    assert abs(m.mean() / 200.0 - 1) < 5 * 0.5 / np.sqrt(m.size)
    assert abs(m.std() / 200.0 - 0.5) < 0.01
    assert m.min() > 0
    # lognormal skewness (e^{s2}+2) sqrt(e^{s2}-1) for std 0.5 at mean 1
    s2 = np.log1p(0.25)
    assert abs(stats.skew(m.ravel()) - (np.exp(s2) + 2) * np.sqrt(np.exp(s2) - 1)) < 0.1


def test_hot_pixels_rates_and_weibull_law():
    """Excess e- = r t with r = B g / t2; t2 follows the Weibull law (KS test)."""
    s = make_sensor("ml11002", {"dark_current_e_per_s": 0.0})
    eff = build_effects({"hot_pixels": {"count": 4000, "weibull_shape": 0.7, "scale_s": 500.0}}, s)
    det = Detector(s, eff)
    tab = det.truth(60.0, 1)["HOTPIX"]
    assert len(tab) == 4000
    assert stats.kstest(tab["t_double_s"], stats.weibull_min(0.7, scale=500.0).cdf).pvalue > 1e-3
    np.testing.assert_allclose(tab["rate_e_per_s"], s.bias_adu * s.gain_e_per_adu / tab["t_double_s"], rtol=1e-5)
    roi = make_sensor("ml11002", {"dark_current_e_per_s": 0.0, "width": 960, "height": 960, "x0": 0, "y0": 0})
    det_roi = Detector(roi, build_effects({"hot_pixels": {"count": 4000, "weibull_shape": 0.7, "scale_s": 500.0}}, roi))
    img = det_roi.expose(0.0, 60.0, 1, noiseless=True)
    t_roi = det_roi.truth(60.0, 1)["HOTPIX"]
    np.testing.assert_allclose(img[t_roi["y"], t_roi["x"]], t_roi["rate_e_per_s"] * 60.0, rtol=1e-5)
    assert np.count_nonzero(img) == len(t_roi)


def test_stuck_pixels_are_fixed_whatever_the_exposure():
    s = small(width=480, height=480, x0=0, y0=0)
    eff = {"hot_pixels": {"count": 20000, "stuck_fraction": 1.0, "stuck_value_adu": 4000}}
    det = Detector(s, build_effects(eff, s))
    t = det.truth(1.0, 1)["HOTPIX"]
    for texp in (1.0, 100.0):
        f = det.expose(0.0, texp, frame_seed=int(texp))
        assert (f[t["y"], t["x"]] == 4000).all()


def test_dead_pixels_and_columns_lose_photo_response_but_keep_dark():
    s = small(x0=0, y0=0)
    det = Detector(s, build_effects({"dead_pixels": {"count": 30000}, "column_defects": {"dead_columns": 400,
                                                                                        "hot_columns": 0}}, s))
    m = det.expose(1000.0, 10.0, 1, noiseless=True)
    tr = det.truth(10.0, 1)
    dead = tr["DEADPIX"]
    assert len(dead) > 0 and np.allclose(m[dead["y"], dead["x"]], 2.0)  # only 0.2 e-/s x 10 s of dark
    cols = tr["COLDEF"]["x"]
    assert len(cols) > 0 and np.allclose(m[:, cols], 2.0)


def test_hot_columns_add_rate_times_time():
    s = small(x0=0, y0=0, dark_current_e_per_s=0.0)
    det = Detector(s, build_effects({"column_defects": {"hot_columns": 600, "dead_columns": 0,
                                                        "hot_rate_e_per_s": 3.0}}, s))
    m = det.expose(0.0, 10.0, 1, noiseless=True)
    cols = det.truth(10.0, 1)["COLDEF"]["x"]
    assert len(cols) > 0 and np.allclose(m[:, cols], 30.0) and np.count_nonzero(m.sum(0)) == len(cols)


def test_measured_columns_sit_where_they_were_seen_and_act_in_the_mean_frame():
    """Columns found in a frame (``hot_at``, ``dead_at``: sensor columns) keep their measured rate and response;
    the rest of each population is drawn outside the read-out window; being the camera's own, they act in the
    model's mean frame (:meth:`Detector.moments`), while drawn positions (a realisation) are left out of it."""
    s = small(x0=100, y0=0, dark_current_e_per_s=0.0)
    eff = {"column_defects": {"hot_columns": 40, "hot_at": [105, 130], "hot_at_rate_e_per_s": [2.0, 0.5],
                              "dead_columns": 30, "dead_at": [150], "dead_at_response": [0.9]}}
    det = Detector(s, build_effects(eff, s))
    m = det.expose(1000.0, 10.0, 1, noiseless=True)
    assert np.allclose(m[:, 5], 20.0 + 1000.0) and np.allclose(m[:, 30], 5.0 + 1000.0)
    assert np.allclose(m[:, 50], 900.0) and np.allclose(m[:, 60], 1000.0)
    tr = det.truth(10.0, 1)["COLDEF"]
    assert sorted(tr["x_sensor"]) == [105, 130, 150]  # the drawn 67 others lie outside the window
    mean, _, _ = det.moments(1000.0, 10.0)
    assert mean[0, 50] < mean[0, 60] and mean[0, 5] > mean[0, 60]
    drawn = Detector(s, build_effects({"column_defects": {"hot_columns": 600, "hot_rate_e_per_s": 3.0}}, s))
    mean_d, _, _ = drawn.moments(1000.0, 10.0)
    assert np.ptp(mean_d[0]) == 0.0
    # a trap's column: the excess only over the rows on one side of the trap
    part = {"column_defects": {"hot_columns": 1, "hot_at": [110], "hot_at_rate_e_per_s": [2.0], "dead_columns": 0,
                               "hot_at_rows": [[0, 300]]}}
    m = Detector(s, build_effects(part, s)).expose(0.0, 10.0, 1, noiseless=True)
    assert np.allclose(m[:300, 10], 20.0) and np.allclose(m[300:, 10], 0.0)
    with pytest.raises(ValueError, match="hot_at_rows"):
        build_effects({"column_defects": {"hot_columns": 1, "hot_at": [1], "hot_at_rows": [[5, 2]]}}, s)
    with pytest.raises(ValueError, match="hot_at_rate_e_per_s"):
        build_effects({"column_defects": {"hot_columns": 2, "hot_at": [1, 2], "hot_at_rate_e_per_s": [1.0]}}, s)


def test_gain_regions_scale_signal_per_region():
    s = small(x0=0, y0=0, width=4008, height=240, read_noise_e=0.0, dark_current_e_per_s=0.0, gain_e_per_adu=1.0)
    det = Detector(s, build_effects({"gain_regions": {"nx": 2, "ny": 1, "gains": [1.0, 1.1]}}, s))
    f = det.expose(5000.0, 1.0, 1).astype(float) - 1000
    left, right = f[:, :2004].mean(), f[:, 2004:].mean()
    assert abs(right / left - 1.1) < 0.002


def test_nonlinearity_follows_the_quadratic_law():
    s = small(read_noise_e=0.0, dark_current_e_per_s=0.0, gain_e_per_adu=1.0, full_well_e=50000.0)
    det = Detector(s, build_effects({"nonlinearity": {"beta": 0.05}}, s))
    for S in (10000.0, 40000.0):
        f = det.expose(S, 1.0, 1).astype(float)
        expect = 1000 + S * (1 - 0.05 * S / 50000.0) - 0.5
        assert abs(f.mean() - expect) < 5 * np.sqrt(S / f.size) + 0.5


def test_row_noise_variance_of_row_means():
    s = small(read_noise_e=0.0, dark_current_e_per_s=0.0, gain_e_per_adu=1.0, width=2000, height=2000)
    det = Detector(s, build_effects({"row_noise": {"sigma_e": 6.0}}, s))
    f = det.expose(100.0, 1.0, 1).astype(float)
    rm = f.mean(axis=1)
    exp = 36.0 + (100 + 1 / 12) / f.shape[1]
    assert abs(rm.var(ddof=1) - exp) < 5 * exp * np.sqrt(2 / rm.size)


def test_ktc_noise_formula_and_effect():
    # sqrt(k T C)/q at 300 K and 1 fF is 12.7 e- (Janesick 2007, eq. 4.?; the classic kTC number)
    assert abs(ktc_noise_e(300.0, 1e-15) - 12.7) < 0.1
    s = small(read_noise_e=0.0, dark_current_e_per_s=0.0, gain_e_per_adu=1.0)
    det = Detector(s, build_effects({"reset_noise": {"capacitance_ff": 1.0, "temperature_k": 300.0}}, s))
    f = det.expose(100.0, 1.0, 1).astype(float)
    exp = 100 + ktc_noise_e(300.0, 1e-15) ** 2 + 1 / 12
    assert abs(f.var() - exp) < 5 * exp * np.sqrt(2 / f.size)


def test_bias_gradient_ramp():
    s = make_sensor("ml11002", {"read_noise_e": 0.0, "dark_current_e_per_s": 0.0, "height": 240})
    det = Detector(s, build_effects({"bias_gradient": {"gradient_x_adu": 20.0}}, s))
    f = det.expose(0.0, 0.0, 1).astype(float)
    col = f.mean(axis=0)
    slope = np.polyfit(np.arange(col.size), col, 1)[0]
    assert abs(slope * (s.sensor_width_px - 1) - 20.0) < 0.2


def test_crosstalk_ghost_is_alpha_times_source_and_mirrored():
    a = np.zeros((4, 40), dtype=np.float32)
    a[:, 2] = 1000.0  # source in channel 0 at local column 2
    channel_crosstalk(a, 4, 0.01, mirrored=True)
    assert np.allclose(a[:, 10 + 7], 10.0)  # channel 1 is mirrored: column 9 - 2
    assert np.allclose(a[:, 20 + 2], 10.0) and np.allclose(a[:, 30 + 7], 10.0)
    assert np.isclose(a.sum(), 4 * 1000 * 1.03)


def test_amp_glow_peak_and_time_scaling():
    s = small(x0=0, y0=0, dark_current_e_per_s=0.0)
    src = {"x_frac": 0.0, "y_frac": 0.0, "amplitude_e_per_s": 2.0, "sigma_x_px": 100.0, "sigma_y_px": 50.0}
    det = Detector(s, build_effects({"amp_glow": {"sources": [src]}}, s))
    m10 = det.expose(0.0, 10.0, 1, noiseless=True)
    m20 = det.expose(0.0, 20.0, 1, noiseless=True)
    assert abs(m10[0, 0] - 20.0) < 1e-4
    assert abs(m10[50, 0] / m10[0, 0] - np.exp(-0.5)) < 1e-5  # one sigma along y
    np.testing.assert_allclose(m20, 2 * m10, rtol=1e-6)
    edge = Detector(s, build_effects({"amp_glow": {"model": "edge", "edge": "left", "amplitude_e_per_s": 1.0,
                                                   "scale_px": 30.0}}, s)).expose(0.0, 1.0, 1, noiseless=True)
    assert abs(edge[100, 30] / edge[100, 0] - np.exp(-1)) < 1e-5


def test_amp_glow_emitter_is_a_point_source_irradiance():
    """A point emitter of intensity I at a height h off the sensor plane: E(r) = I h / (r^2 + h^2)^1.5 (inverse
    square times the cosine of incidence), I / h^2 below it, at r = h 2^-1.5 of that, and its flux through the
    whole plane 2 pi I (the half space it faces), which a 4001 x 4001 px plane holds to 1 - h/2000 (the tail
    beyond a radius R carries 2 pi I h / R)."""
    from detector.effects.glow import emitter_rate

    h, peak = 20.0, 3.0
    ys = xs = np.arange(-2000.0, 2001.0)
    out = np.zeros((ys.size, xs.size), np.float32)
    emitter_rate(ys, xs, 0.0, 0.0, peak, h, out)
    assert out[2000, 2000] == pytest.approx(peak, rel=1e-6)
    assert out[2000, 2020] == pytest.approx(peak * 2 ** -1.5, rel=1e-6)
    assert out[2000 + 12, 2000 + 16] == pytest.approx(peak / (1 + 400 / h ** 2) ** 1.5, rel=1e-6)
    flux = out.sum(dtype=np.float64) / (2 * np.pi * peak * h * h)  # in units of 2 pi I
    assert flux == pytest.approx(1 - h / 2000, abs=2e-3)
    s = small(x0=0, y0=0, dark_current_e_per_s=0.0)
    emitter = {"x_frac": 0.0, "y_frac": 0.0, "amplitude_e_per_s": 2.0, "height_px": 25.0}
    det = Detector(s, build_effects({"amp_glow": {"model": "emitter", "emitters": [emitter]}}, s))
    m10, m20 = det.expose(0.0, 10.0, 1, noiseless=True), det.expose(0.0, 20.0, 1, noiseless=True)
    assert m10[0, 0] == pytest.approx(20.0, rel=1e-5) and m10[0, 25] == pytest.approx(20.0 * 2 ** -1.5, rel=1e-5)
    np.testing.assert_allclose(m20, 2 * m10, rtol=1e-6)


def test_blooming_conserves_charge_and_bleeds_excess_over_full_well():
    img = np.zeros((200, 5))
    img[100, 2] = 10_000.0
    bleed_columns(img, 1000.0)
    assert img.sum() == 10_000.0 and img.max() <= 1000.0
    col = img[:, 2]  # 9000 e- of excess, half up and half down: 4 full pixels and a half-filled one each way
    assert (col[96:105] == 1000.0).all() and col[95] == col[105] == 500.0
    assert np.count_nonzero(col) == 11 and not img[:, [0, 1, 3, 4]].any()
    # through the chain: a saturated spot becomes a vertical trail of full-well pixels
    s = small(x0=0, y0=0, full_well_e=20000.0, read_noise_e=0.0, dark_current_e_per_s=0.0)
    sig = np.zeros(s.shape, dtype=np.float32)
    sig[300, 300] = 20000.0 * 41
    m = Detector(s, build_effects({"blooming": {}}, s)).expose(sig, 1.0, 1, noiseless=True)
    assert np.isclose(m.sum(), sig.sum()) and (m[280:321, 300] == 20000.0).all()


def test_radial_vignetting_follows_its_polynomial_and_spares_the_dark_signal():
    from detector.effects.optical import radial_vignetting

    s = small()
    det = Detector(s, build_effects({"vignetting": {"a2": 0.2, "a4": 0.05}}, s))
    img = det.expose(1000.0, 1.0, frame_seed=1, noiseless=True)   # e-: photo (vignetted) + dark (not)
    pitch = s.pixel_pitch_um * 1e-3
    ys = np.arange(s.roi_y0, s.roi_y0 + s.height) - (s.sensor_height_px - 1) / 2
    xs = np.arange(s.roi_x0, s.roi_x0 + s.width) - (s.sensor_width_px - 1) / 2
    r_c = 0.5 * pitch * np.hypot(s.sensor_width_px, s.sensor_height_px)
    ri = radial_vignetting(xs[None, :] * pitch, ys[:, None] * pitch, r_c, 0.2, 0.05)
    dark = s.dark_current_e_per_s * 1.0
    assert np.allclose(img, 1000.0 * ri + dark, rtol=1e-5)
    assert radial_vignetting(np.array(r_c), np.array(0.0), r_c, 0.2, 0.05) == pytest.approx(0.75)


def test_vignetting_map_file_is_interpolated_and_errors_name_the_file(tmp_path):
    from astropy.io import fits

    from detector import DetectorError

    s = small()
    u = np.linspace(-20, 20, 5)
    v = np.linspace(-15, 15, 4)
    ri = 1 - 0.001 * (u[None, :] ** 2 + v[:, None] ** 2)     # quadratic: a cubic spline reproduces it
    h = fits.Header({"CRVAL1": u[0], "CDELT1": u[1] - u[0], "CRPIX1": 1.0,
                     "CRVAL2": v[0], "CDELT2": v[1] - v[0], "CRPIX2": 1.0})
    fits.PrimaryHDU(ri.astype(np.float32), h).writeto(tmp_path / "m.fits")
    eff = build_effects({"vignetting": {"map_file": str(tmp_path / "m.fits")}}, s)[0]
    ys, xs = np.array([0.0, s.sensor_height_px / 2 - 0.5]), np.array([0.0, s.sensor_width_px / 2 - 0.5])
    got = eff.ri(ys, xs)
    pitch = s.pixel_pitch_um * 1e-3
    uu = (xs - (s.sensor_width_px - 1) / 2) * pitch
    vv = (ys - (s.sensor_height_px - 1) / 2) * pitch
    want = 1 - 0.001 * (uu[None, :] ** 2 + vv[:, None] ** 2)
    assert np.allclose(got, want, atol=1e-5)
    with pytest.raises(DetectorError, match="nope.fits"):
        build_effects({"vignetting": {"map_file": str(tmp_path / "nope.fits")}}, s)
    (tmp_path / "bad.fits").write_text("not a fits file")
    with pytest.raises(DetectorError, match="bad.fits"):
        build_effects({"vignetting": {"map_file": str(tmp_path / "bad.fits")}}, s)


def test_nonlinearity_power_law_follows_its_formula():
    """S' = S (S / S_ref)^(gamma - 1), S_ref = FW / 2: the same at S_ref, (gamma - 1) ln(S / S_ref) away."""
    from detector.effects.pixel_response import power_law_nonlinearity

    fw = 50000.0
    s = small(read_noise_e=0.0, dark_current_e_per_s=0.0, gain_e_per_adu=1.0, full_well_e=fw)
    det = Detector(s, build_effects({"nonlinearity": {"beta": 0.0, "gamma": 0.97}}, s))
    for S in (2500.0, 25000.0, 45000.0):
        f = det.expose(S, 1.0, 1).astype(float)
        expect = 1000 + S * (S / (fw / 2)) ** (0.97 - 1) - 0.5
        assert abs(f.mean() - expect) < 5 * np.sqrt(S / f.size) + 0.5
    x = np.array([0.0, -3.0, 25000.0], np.float32)
    power_law_nonlinearity(x, 0.9, 25000.0)
    assert x.tolist() == [0.0, -3.0, 25000.0]  # no signal, no change; the reference is a fixed point


def _flat_residuals(s, gain_map, seed: int):
    """Residuals of a flat of 5000 e- per sensor pixel on the 8x8-binned sensor ``s`` (bias 1000 ADU, gain 1), its
    light multiplied by ``gain_map`` (broadcasting), with its shot and read noise, against the flat's model."""
    from detector.signatures import Residuals, SpikeStats

    h, w = s.output_shape
    ys, xs = np.arange(h) * 8 + 3.5, np.arange(w) * 8 + 3.5
    rng = np.random.default_rng(seed)
    photo = np.full((h, w), 64 * 5000.0)
    var = photo + 25.0
    data = 1000 + photo * gain_map + rng.normal(0, 1, (h, w)) * np.sqrt(var)
    return Residuals(data.astype(np.float32), (1000 + photo).astype(np.float32), var.astype(np.float32),
                     np.ones((h, w), bool), photo.astype(np.float32), np.zeros((h, w), np.float32), ys, xs, s, 1.0,
                     SpikeStats(0, 0, 0, 0, 0), SpikeStats(0, 0, 0, 0, 0))


def test_gain_regions_boundary_found_where_the_amplifiers_meet():
    """A flat read by two amplifiers that meet at sensor column 1300 of a 4008-column sensor (not its middle):
    the diagnosis finds the boundary from the data (binary segmentation of the residual's column sums) and
    the two gains' ratio (1.004) within its statistical error; the effect then renders the same step there."""
    from detector import registry

    s = small(x0=0, y0=0, width=4008, height=64, binning=8, read_noise_e=5.0, dark_current_e_per_s=0.0,
              gain_e_per_adu=1.0)
    h, w = s.output_shape
    xs = np.arange(w) * 8 + 3.5
    gain = np.where(xs < 1300, 1.0, 1.004)[None, :] / (1.004 * (1 - 1300 / 4008) + 1300 / 4008)
    res = _flat_residuals(s, gain, seed=5)
    fit = registry()["gain_regions"].signature.fit(res, "gain_regions")
    assert fit.params.get("splits_x") and abs(fit.params["splits_x"][0] - 1300) <= 8
    g = fit.params["gains"]
    # the ratio's error: two means of ~n/2 pixels each at 1/sqrt(photo) relative noise
    se = np.sqrt(4 / (h * w * 64 * 5000.0))
    assert g[1] / g[0] == pytest.approx(1.004, abs=5 * se)
    assert fit.k == 2 + 1 + 1  # two gains, the grid chosen, the boundary found
    det = Detector(s, build_effects({"gain_regions": fit.params}, s))
    f = det.expose(500.0, 1.0, 1).astype(float) - s.bias_adu  # below the full well (ADU: the gains act there)
    step = xs > fit.params["splits_x"][0]
    assert f[:, step].mean() / f[:, ~step].mean() == pytest.approx(g[1] / g[0], rel=1e-3)


def test_four_amplifier_strips_at_unequal_places_are_found_as_three_boundaries():
    """A flat read by four amplifiers whose strips meet at sensor columns 700, 1900 and 3100 (not the sensor's
    equal quarters; gains 1, 1.005, 0.996, 1.003): three boundaries are found within two binned columns of where
    the strips meet, the gains' ratios within their statistical error, and the further boundaries the search may
    try (MAX_FOUND_SPLITS) do not pay their BIC parameter on a frame of four strips."""
    from detector import registry
    from detector.effects.pixel_response import MAX_FOUND_SPLITS

    assert MAX_FOUND_SPLITS >= 3
    s = small(x0=0, y0=0, width=4008, height=64, binning=8, read_noise_e=5.0, dark_current_e_per_s=0.0,
              gain_e_per_adu=1.0)
    h, w = s.output_shape
    xs = np.arange(w) * 8 + 3.5
    cuts, gains = [700, 1900, 3100], [1.0, 1.005, 0.996, 1.003]
    gain = np.asarray(gains)[np.searchsorted(cuts, xs)][None, :]
    res = _flat_residuals(s, gain / gain.mean(), seed=7)
    fit = registry()["gain_regions"].signature.fit(res, "gain_regions")
    splits = fit.params.get("splits_x")
    assert splits and len(splits) == 3, fit.params
    assert all(abs(a - b) <= 16 for a, b in zip(splits, cuts)), splits
    g = np.asarray(fit.params["gains"])
    se = np.sqrt(2 * 4 / (h * w * 64 * 5000.0))  # a ratio of two strips' means, ~n/4 pixels each
    assert g[1:] / g[0] == pytest.approx(np.asarray(gains[1:]), abs=5 * se)


def test_a_smooth_periodic_response_is_no_staircase_of_gain_regions():
    """A response that varies as a sine along x (0.3 %, period 1600 sensor columns: tree rings of the silicon, a
    fringe) is fitted by a staircase of found boundaries; a smooth curve of the columns with as many parameters
    describes the profile better and the steps add nothing to it, so the fit is refused. The four strips of the test
    above pass the same check, as do two strips with a wide transition under a drift."""
    from detector import registry

    s = small(x0=0, y0=0, width=4008, height=64, binning=8, read_noise_e=5.0, dark_current_e_per_s=0.0,
              gain_e_per_adu=1.0)
    xs = np.arange(s.output_shape[1]) * 8 + 3.5
    sig = registry()["gain_regions"].signature
    res = _flat_residuals(s, (1 + 0.003 * np.sin(2 * np.pi * xs / 1600.0))[None, :], seed=8)
    fit = sig.fit(res, "gain_regions")
    assert fit is not None and "smooth curve" in sig.plausible(fit, res), fit.params
    gain = np.asarray([1.0, 1.005, 0.996, 1.003])[np.searchsorted([700, 1900, 3100], xs)][None, :]
    res = _flat_residuals(s, gain / gain.mean(), seed=7)
    assert sig.plausible(sig.fit(res, "gain_regions"), res) == ""
    # two strips 2.8 % apart meeting over 80 columns, under a 0.3 % drift: a staircase of many boundaries fits
    # the transition and the drift, a curve fits them better, but the step stays on top of any curve
    gain = (1 + 0.028 * 0.5 * (1 + np.tanh((xs - 2000) / 40.0)) + 0.003 * xs / 4008)[None, :]
    res = _flat_residuals(s, gain / gain.mean(), seed=9)
    assert sig.plausible(sig.fit(res, "gain_regions"), res) == ""


def _field_residuals(s, photo, measured_photo, seed: int):
    """Residuals of a frame whose model light is ``photo`` [e- per output pixel] and whose measured light is
    ``measured_photo`` (bias 1000 ADU, gain 1, read noise 5 e- per sensor pixel of the 8x8 bin), with its shot noise."""
    from detector.signatures import Residuals, SpikeStats

    h, w = s.output_shape
    ys, xs = np.arange(h) * 8 + 3.5, np.arange(w) * 8 + 3.5
    rng = np.random.default_rng(seed)
    var = measured_photo + 64 * 25.0
    data = 1000 + measured_photo + rng.normal(0, 1, (h, w)) * np.sqrt(var)
    return Residuals(data.astype(np.float32), (1000 + photo).astype(np.float32), (photo + 64 * 25.0).astype(np.float32),
                     np.ones((h, w), bool), photo.astype(np.float32), np.zeros((h, w), np.float32), ys, xs, s, 1.0,
                     SpikeStats(0, 0, 0, 0, 0), SpikeStats(0, 0, 0, 0, 0))


def test_gain_steps_must_scale_with_the_signal_on_a_star_field():
    """A gain multiplies what its amplifier reads, the stars as the sky: on a star field (a sky of 2000 e- per
    binned pixel, 300 stars of 10^4 to 10^6 e-) a strip of rows whose light is 0.4 % high is a gain region (one factor
    per region takes more chi2 than one offset), while a strip of rows with 8 e- per pixel of light added (a
    satellite trail's, the same on sky and stars) fits as steps too but is refused: the offsets take more by far
    more than DETECTION_SIGMA^2."""
    from detector import registry

    s = small(x0=0, y0=0, width=4008, height=2672, binning=8, read_noise_e=5.0, dark_current_e_per_s=0.0,
              gain_e_per_adu=1.0)
    h, w = s.output_shape
    rng = np.random.default_rng(3)
    photo = np.full((h, w), 2000.0)
    yy, xx = np.mgrid[0:h, 0:w]
    for y0, x0, f in zip(rng.uniform(0, h, 300), rng.uniform(0, w, 300), 10 ** rng.uniform(4, 6, 300)):
        photo += f / (2 * np.pi) * np.exp(-0.5 * ((yy - y0) ** 2 + (xx - x0) ** 2))
    strip = ((yy > 0.4 * h) & (yy < 0.6 * h)).astype(float)
    sig = registry()["gain_regions"].signature
    res = _field_residuals(s, photo, photo * (1 + 0.004 * strip), seed=4)
    fit = sig.fit(res, "gain_regions")
    assert fit is not None and fit.params.get("splits_y"), fit and fit.params
    assert sig.plausible(fit, res) == ""
    res = _field_residuals(s, photo, photo + 8.0 * strip, seed=4)
    fit = sig.fit(res, "gain_regions")
    assert fit is not None and "do not scale with the signal" in sig.plausible(fit, res), fit and fit.params


def test_a_narrow_amplifier_strip_is_a_gain_region_not_columns():
    """Three strips with the middle one 5 % of the frame wide (25 binned columns, 0.7 % low): a step of the column
    means that persists over more than LINE_WINDOW columns is a region; the two boundaries are found where the
    strip starts and ends (binary segmentation with boundaries LINE_WINDOW lines apart)."""
    from detector import registry
    from detector.effects.pixel_response import MIN_SEGMENT_SHARE
    from detector.signatures import LINE_WINDOW

    s = small(x0=0, y0=0, width=4008, height=64, binning=8, read_noise_e=5.0, dark_current_e_per_s=0.0,
              gain_e_per_adu=1.0)
    h, w = s.output_shape
    xs = np.arange(w) * 8 + 3.5
    lo, hi = 0.43 * 4008, 0.48 * 4008
    # wider than LINE_WINDOW lines, narrower than a segment at the frame's edge must be (its share, in lines)
    assert LINE_WINDOW < (hi - lo) / 8 < np.ceil(MIN_SEGMENT_SHARE * w)
    gain = np.where((xs > lo) & (xs < hi), 0.993, 1.0)[None, :]
    res = _flat_residuals(s, gain, seed=6)
    fit = registry()["gain_regions"].signature.fit(res, "gain_regions")
    splits = fit.params.get("splits_x")
    assert splits and len(splits) == 2, fit.params
    assert abs(splits[0] - lo) <= 16 and abs(splits[1] - hi) <= 16, splits  # within two binned columns
    g = fit.params["gains"]
    assert g[1] / g[0] == pytest.approx(0.993, abs=1e-3) and g[2] / g[0] == pytest.approx(1.0, abs=1e-3)
