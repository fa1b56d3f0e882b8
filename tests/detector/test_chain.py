"""The always-on chain against analytic means and variances (thesis eqs. 30-34; Janesick 2007)."""

import numpy as np
import pytest

from detector import Detector, DetectorError, build_effects, make_sensor


def sensor(**kw):
    base = {"width": 960, "height": 960, "read_noise_e": 5.0, "gain_e_per_adu": 2.0, "bias_adu": 1000.0,
            "dark_current_e_per_s": 0.5}
    base.update(kw)
    return make_sensor(kw.pop("preset", "ml11002"), {k: v for k, v in base.items() if k != "preset"})


def moments(frame):
    f = frame.astype(np.float64)
    return f.mean(), f.var(ddof=1)


def check_within(value, expected, sigma, n=5.0):
    assert abs(value - expected) < n * sigma, f"{value} vs {expected} +- {sigma}"


def test_mean_and_variance_match_the_linear_camera_model():
    """E[ADU] = B + (S + D t)/g (the ADC rounds: mid-tread); Var = (S + D t + sr^2)/g^2 + 1/12 (EMVA 1288 eq. 4)."""
    s = sensor()
    g, S, t = 2.0, 300.0, 10.0
    f = Detector(s).expose(S, t, frame_seed=11)
    mean, var = moments(f)
    mu_e = S + 0.5 * t
    n = f.size
    exp_mean = 1000 + mu_e / g
    exp_var = (mu_e + 25.0) / g ** 2 + 1 / 12
    check_within(mean, exp_mean, np.sqrt(exp_var / n))
    check_within(var, exp_var, exp_var * np.sqrt(2 / n))


def test_photon_transfer_gives_back_gain_and_read_noise():
    """Var_ADU = mu_ADU / g + (sr/g)^2: the slope of the photon-transfer curve is 1/g (Janesick 2007 ch. 2)."""
    s = sensor(dark_current_e_per_s=0.0, read_noise_e=6.0, gain_e_per_adu=1.5)
    det = Detector(s)
    mus, vars_ = [], []
    for i, S in enumerate([200.0, 1000.0, 3000.0, 8000.0]):
        a = det.expose(S, 1.0, frame_seed=100 + i).astype(np.float64)
        b = det.expose(S, 1.0, frame_seed=200 + i).astype(np.float64)
        mus.append(0.5 * (a.mean() + b.mean()) - 1000)
        vars_.append(np.var(a - b) / 2 - 1 / 12)  # pair difference removes any fixed pattern
    slope, intercept = np.polyfit(mus, vars_, 1)
    assert abs(1 / slope - 1.5) / 1.5 < 0.01
    assert abs(np.sqrt(intercept) * 1.5 - 6.0) < 0.3


def test_full_well_clips_before_read_noise_and_adc_saturates():
    s = sensor(full_well_e=20000.0, dark_current_e_per_s=0.0, read_noise_e=8.0, gain_e_per_adu=1.0)
    f = Detector(s).expose(50000.0, 1.0, frame_seed=1).astype(np.float64)
    # every pixel sits at the full well, and read noise still spreads it: clipping came first
    assert abs(f.mean() - (1000 + 20000)) < 0.1
    assert abs(f.std() - np.sqrt(64 + 1 / 12)) < 0.2
    s2 = sensor(full_well_e=200000.0, gain_e_per_adu=1.0, dark_current_e_per_s=0.0)
    f2 = Detector(s2).expose(150000.0, 1.0, frame_seed=1)
    assert f2.max() == 65535 and (f2 == 65535).all()


def test_dark_frame_gives_dark_rate():
    s = sensor(dark_current_e_per_s=2.0, read_noise_e=3.0)
    means = [Detector(s).expose(0.0, t, frame_seed=int(t)).mean() for t in (0.0, 30.0, 60.0, 120.0)]
    slope = np.polyfit([0, 30, 60, 120], means, 1)[0]
    assert abs(slope * 2.0 - 2.0) < 0.02  # e-/s, gain 2 e-/ADU


def test_same_seed_same_bytes_on_one_thread_or_two():
    s = sensor(width=1200, height=1000)
    eff = {"prnu": {}, "dsnu": {}, "hot_pixels": {"count": 500}, "row_noise": {}, "reset_noise": {},
           "crosstalk": {}, "amp_glow": {}}
    a = Detector(s, build_effects(eff, s), workers=1).expose(120.0, 5.0, frame_seed=7)
    b = Detector(s, build_effects(eff, s), workers=2).expose(120.0, 5.0, frame_seed=7)
    c = Detector(s, build_effects(eff, s), workers=2).expose(120.0, 5.0, frame_seed=8)
    assert a.tobytes() == b.tobytes()
    assert a.tobytes() != c.tobytes()


def test_hardware_pattern_is_fixed_across_frames_and_rois():
    """The hardware seed fixes PRNU/hot pixels: the same pixel has the same response in every frame and ROI."""
    full = make_sensor("ml11002", {"dark_current_e_per_s": 0.0})
    eff = {"prnu": {"sigma": 0.05}, "hot_pixels": {"count": 20000}}
    big = Detector(full, build_effects(eff, full)).expose(1000.0, 10.0, frame_seed=1, noiseless=True)
    roi = make_sensor("ml11002", {"dark_current_e_per_s": 0.0, "width": 300, "height": 200, "x0": 1234, "y0": 777})
    small = Detector(roi, build_effects(eff, roi)).expose(1000.0, 10.0, frame_seed=99, noiseless=True)
    np.testing.assert_array_equal(small, big[777:977, 1234:1534])
    assert abs(big.mean() / 1000 - 1) < 0.01 + 20000 * 700 / big.size / 1000  # PRNU of mean 1 (+ hot pixels)


def test_ccd_charge_binning_reads_noise_once_cmos_digital_binning_four_times():
    S, g, rn = 400.0, 1.0, 10.0
    ccd = make_sensor("ml11002", {"width": 960, "height": 960, "binning": 2, "read_noise_e": rn, "gain_e_per_adu": g,
                                  "dark_current_e_per_s": 0.0})
    f = Detector(ccd).expose(S, 1.0, frame_seed=3).astype(float)
    assert f.shape == (480, 480)
    check_within(f.var(), 4 * S + rn ** 2 + 1 / 12, (4 * S + rn ** 2) * np.sqrt(2 / f.size))
    cmos = make_sensor("imx411", {"width": 960, "height": 960, "binning": 2, "read_noise_e": rn, "gain_e_per_adu": g,
                                  "dark_current_e_per_s": 0.0})
    f = Detector(cmos).expose(S, 1.0, frame_seed=3).astype(float)
    check_within(f.var(), 4 * (S + rn ** 2 + 1 / 12), 4 * (S + rn ** 2) * np.sqrt(2 / f.size))
    avg = make_sensor("imx411", {"width": 960, "height": 960, "binning": 2, "binning_mode": "average",
                                 "gain_e_per_adu": g, "dark_current_e_per_s": 0.0})
    f = Detector(avg).expose(S, 1.0, frame_seed=3).astype(float)
    assert abs(f.mean() - (500 + S)) < 0.2  # four rounded values averaged, rounded again: unbiased


def test_rolling_shutter_row_times():
    s = make_sensor("imx411", {"width": 64, "height": 960, "binning": 2})
    t = Detector(s).row_start_times_s()
    assert t.shape == (480,)
    np.testing.assert_allclose(np.diff(t), 2 * 4.7e-5)
    g = make_sensor("ml11002", {"width": 64, "height": 64})
    assert not Detector(g).row_start_times_s().any()


@pytest.mark.parametrize("bad", [np.nan, -1.0, np.inf])
def test_bad_signal_is_refused_with_the_pixel(bad):
    s = sensor(width=240, height=480)
    img = np.full(s.shape, 10.0, dtype=np.float32)
    img[300, 17] = bad
    with pytest.raises(DetectorError, match=r"x=17, y=300"):
        Detector(s).expose(img, 1.0, frame_seed=1)


def test_shape_and_parameter_errors_name_the_key():
    s = sensor(width=240, height=240)
    with pytest.raises(DetectorError, match="shape"):
        Detector(s).expose(np.zeros((10, 10)), 1.0, frame_seed=1)
    with pytest.raises(DetectorError, match="exposure.time_s"):
        Detector(s).expose(1.0, -1.0, frame_seed=1)
    with pytest.raises(DetectorError, match="detector.gain_e_per_adu.*> 0"):
        make_sensor("imx411", {"gain_e_per_adu": -1})
    with pytest.raises(DetectorError, match="does not fit"):
        make_sensor("ml11002", {"width": 5000})
    with pytest.raises(DetectorError, match="effects.prnu.sigma"):
        build_effects({"prnu": {"sigma": 7}}, s)
    with pytest.raises(DetectorError, match="unknown effect 'foo'"):
        build_effects({"foo": {}}, s)


@pytest.mark.parametrize("sigma", [0.05, 0.18, 0.4, 1.0, 3.0])
def test_rounded_moments_are_those_of_the_rounded_gaussian(sigma):
    """rint(N(mu, sigma^2)): the exact moments for narrow inputs (the output follows the nearest code, its
    variance depends on where mu falls between codes: Widrow & Kollar 2008 ch. 5), Sheppard's (mu, sigma^2 +
    1/12) for wide ones; checked against one million draws at four places between codes."""
    from detector.chain import rounded_moments

    rng = np.random.default_rng(5)
    mu = np.array([500.0, 500.25, 500.5, 500.8], np.float32)
    m, v = rounded_moments(mu, np.full(4, sigma ** 2, np.float32))
    for i, x in enumerate(mu):
        q = np.rint(x + sigma * rng.standard_normal(1_000_000))
        se_m, se_v = q.std() / 1e3, max(q.var(), 1e-4) * np.sqrt(2 / 1e6) * 2
        check_within(m[i], q.mean(), max(se_m, 1e-6))
        check_within(v[i], q.var(), max(se_v, 2e-5))
    if sigma >= 1.0:
        assert np.allclose(m, mu, atol=1e-5) and np.allclose(v, sigma ** 2 + 1 / 12, rtol=1e-5)


def test_average_binned_cmos_moments_follow_the_chain():
    """An IMX411 dark averaged 16 x 16: 0.18 ADU of read noise per output pixel, rounded again after the
    average; the level (500.49 ADU) falls near a code transition. The chain's frame and the model's moments
    agree in mean and variance (0.25 ADU^2; Sheppard's model, sigma^2 + 1/12, would say 0.116)."""
    s = make_sensor("imx411", {"width": 1920, "height": 1920, "binning": 16, "binning_mode": "average",
                               "dark_current_e_per_s": 0.002})
    det = Detector(s)
    f = det.expose(0.0, 300.0, frame_seed=4).astype(np.float64)
    mean, var, _ = det.moments(0.0, 300.0)
    n = f.size
    check_within(f.mean(), float(mean.mean()), np.sqrt(var.mean() / n))
    check_within(f.var(), float(var.mean()), var.mean() * np.sqrt(2 / n) + 2e-3)
    sheppard = (16 * 3.5 / 1.22) ** 2 / 16 ** 4 + (1 / 12) / 16 ** 2 + 1 / 12
    assert abs(var.mean() - sheppard) > 0.1


def test_summed_bias_above_the_adc_range_is_named():
    """An IMX411 binned 16x16 in "sum" mode: the digital sum of 256 biases (128,000 ADU) exceeds the 16-bit
    ADC range, so every output pixel saturates; the sensor says why (the render prints it as a warning)."""
    s = make_sensor("imx411", {"binning": 16, "width": 256, "height": 256})
    why = s.summed_bias_saturates()
    assert why and "128,000 ADU" in why and "65,535" in why and "'average'" in why and "at most 11" in why
    frame = Detector(s).expose(10.0, 1.0, frame_seed=1)
    assert frame.shape == (16, 16) and (frame == 65535).all()  # what the words explain
    assert make_sensor("imx411", {"binning": 11, "width": 242, "height": 242}).summed_bias_saturates() is None
    assert make_sensor("imx411", {"binning": 16, "binning_mode": "average"}).summed_bias_saturates() is None
    assert make_sensor("ml11002", {"binning": 16, "width": 256, "height": 256}).summed_bias_saturates() is None
