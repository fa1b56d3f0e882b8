"""Object light curves (``[[objects]] light_curve``): the streak's flux follows the prescribed modulation."""

import math

import numpy as np
import pytest
from scipy import integrate, optimize

from detector import DetectorError
from scenes.app.render import prepare
from scenes.objects import LightCurve, light_curve_from_table
from scenes.scene import load_scene

SCENE = """
[telescope]
pixel_scale_arcsec = 1.0
[detector]
preset = "ml11002"
width = 320
height = 64
[pointing]
ra_deg = 120.0
dec_deg = -30.0
[exposure]
time_s = 10.0
[sky]
background_mag_arcsec2 = 21.0
[psf]
fwhm_arcsec = 2.0
[[objects]]
ra_deg = {ra}
dec_deg = -30.0
rate_ra_deg_s = -0.0075
rate_dec_deg_s = 0.0
photons = 1e7
{extra}
"""
V_PX_S = 0.0075 * 3600  # 27 px/s towards +x (west, roll 0)
T = 10.0


def streak(tmp_path, extra=""):
    ra0 = 120.0 + 135.0 / 3600 / math.cos(math.radians(30.0))  # starts ~135 px east of the centre: x ~ 24
    p = tmp_path / "s.toml"
    p.write_text(SCENE.format(ra=ra0, extra=extra))
    setup = prepare(load_scene(str(p)))
    img = setup.signal_e.image((64, 320)).astype(np.float64) - setup.signal_e.background_e
    return img, setup.truth[0]


def column_times(truth, x):
    """Time [s] at which the streak's centre crosses column x (constant speed along x, global shutter)."""
    return (x - truth["x0"]) / (truth["x1"] - truth["x0"]) * T


@pytest.mark.parametrize("lc", [LightCurve("sinusoid", 0.62, 3.68, 0.3), LightCurve("glint", 5.0, 2.0, 0.25, 0.1),
                                LightCurve("glint", 2.0, 1.0, 0.9, 0.4)])
def test_integral_is_exact_and_the_mean_over_a_period_is_one(lc):
    t = np.linspace(-3.0, 17.0, 23)
    quad = [integrate.quad(lambda x: float(lc.factor(np.array([x]))[0]), 0.0, ti, limit=500)[0] for ti in t]
    assert np.abs(lc.integral(t) - quad).max() < 1e-8
    per = integrate.quad(lambda x: float(lc.factor(np.array([x]))[0]), 0.7, 0.7 + lc.period_s, limit=500)[0]
    assert abs(per / lc.period_s - 1) < 1e-9
    lo = np.array([0.0, 1.3, 2.0])
    hi = lo + np.array([0.5, 1e-3, 3.0])
    assert np.allclose(lc.interval_mean(lo, hi), (lc.integral(hi) - lc.integral(lo)) / (hi - lo))
    assert np.all(lc.factor(np.linspace(0, 10, 1001)) >= 0)


def test_sinusoid_rms_is_amplitude_over_root_two():
    lc = LightCurve("sinusoid", 0.62, 3.68)
    f = lc.factor(np.linspace(0, 3.68, 100001)[:-1])
    assert abs(f.std() - 0.62 / math.sqrt(2)) < 1e-6 and abs(f.mean() - 1) < 1e-9


def test_streak_columns_follow_the_sinusoid(tmp_path):
    """Per-column flux of the streak: a fitted sinusoid recovers P, a and phi; Lomb-Scargle finds P."""
    from astropy.timeseries import LombScargle

    a, period, phase = 0.62, 3.68, 0.3
    img, t = streak(tmp_path, f'light_curve = {{ kind = "sinusoid", amplitude = {a}, period_s = {period}, '
                              f'phase = {phase} }}')
    flat, t0 = streak(tmp_path)
    col, col0 = img.sum(axis=0), flat.sum(axis=0)
    x = np.arange(img.shape[1])
    inner = (x > t["x0"] + 6) & (x < t["x1"] - 6)  # away from the ends (the PSF's reach)
    tt = column_times(t, x[inner])
    ratio = col[inner] / col0[inner]  # modulation alone: the constant streak's profile divided out

    def model(tt, a_, p_, ph_):
        return 1 + a_ * np.sin(2 * np.pi * (tt / p_ + ph_))

    (a_fit, p_fit, ph_fit), _ = optimize.curve_fit(model, tt, ratio, p0=[0.5, 3.5, 0.25])
    # smoothing by the PSF (sigma 0.85 px) and the pixel box over a 99 px period: < 0.2 % on the amplitude
    assert abs(a_fit / a - 1) < 3e-3 and abs(p_fit / period - 1) < 1e-3
    assert abs((ph_fit - phase + 0.5) % 1.0 - 0.5) < 2e-3
    freq, power = LombScargle(tt, ratio).autopower(minimum_frequency=0.05, maximum_frequency=2.0,
                                                    samples_per_peak=50)
    assert abs(1 / freq[np.argmax(power)] / period - 1) < 0.01
    # flux: the constant total times the mean of f over the exposure (the whole streak is on the window)
    lc = LightCurve("sinusoid", a, period, phase)
    mean_f = float(lc.integral(np.array([T]))[0]) / T
    assert abs(img.sum() / (flat.sum() * mean_f) - 1) < 1e-6
    assert abs(t["flux_e"] / (t0["flux_e"] * mean_f) - 1) < 1e-6


def test_glints_flash_at_their_times_and_conserve_the_mean(tmp_path):
    amp, period, width, phase = 20.0, 3.0, 0.08, 0.2
    img, t = streak(tmp_path, f'light_curve = {{ kind = "glint", amplitude = {amp}, period_s = {period}, '
                              f'width_s = {width}, phase = {phase} }}')
    flat, _ = streak(tmp_path)
    col = img.sum(axis=0)
    # flashes at t_k = (k + phase) P = 0.6, 3.6, 6.6, 9.6 s: column peaks there (+- 0.5 px)
    x_expect = t["x0"] + np.array([0.6, 3.6, 6.6]) * (t["x1"] - t["x0"]) / T
    for xe in x_expect:
        j = round(xe)
        seg = col[j - 8:j + 9]
        assert abs(j - 8 + int(np.argmax(seg)) - xe) <= 0.6
    lc = LightCurve("glint", amp, period, phase, width)
    mean_f = float(lc.integral(np.array([T]))[0]) / T
    assert abs(img.sum() / (flat.sum() * mean_f) - 1) < 1e-6
    # the base level between flashes: 1 / (1 + A sqrt(2 pi) w / P) of the constant streak
    xm = round(t["x0"] + 2.1 * (t["x1"] - t["x0"]) / T)
    assert abs(col[xm] / flat.sum(axis=0)[xm] * (1 + amp * math.sqrt(2 * math.pi) * width / period) - 1) < 1e-3


@pytest.mark.parametrize("table, key", [
    ({"kind": "wobble", "amplitude": 0.1, "period_s": 1.0}, "light_curve.kind"),
    ({"kind": "sinusoid", "amplitude": 1.5, "period_s": 1.0}, "light_curve.amplitude"),
    ({"kind": "sinusoid", "amplitude": 0.5}, "light_curve.period_s"),
    ({"kind": "sinusoid", "amplitude": 0.5, "period_s": 1.0, "width_s": 0.1}, "light_curve.width_s"),
    ({"kind": "glint", "amplitude": 5.0, "period_s": 1.0, "width_s": 0.6}, "light_curve.width_s"),
])
def test_bad_light_curves_name_their_key(tmp_path, table, key):
    with pytest.raises(DetectorError) as e:
        light_curve_from_table(table, "objects[0].light_curve", file="s.toml")
    assert key in str(e.value) and "expected" in str(e.value)
    p = tmp_path / "s.toml"
    p.write_text(SCENE.format(ra=120.0, extra="light_curve = { kind = 'sinusoid', amplitude = 2.0, period_s = 1.0 }"))
    with pytest.raises(DetectorError, match=r"objects\[0\].light_curve.amplitude"):
        load_scene(str(p))
