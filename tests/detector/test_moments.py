"""The model of the mean frame and its variance (Detector.moments) against Monte-Carlo frames of the chain."""

import numpy as np
import pytest

from detector import Detector, build_effects
from detector.sensor import make_sensor


def _detector(preset, effects=None, **over):
    base = {"width": 64, "height": 64, "dark_current_e_per_s": 2.0, "read_noise_e": 3.0, "gain_e_per_adu": 1.5}
    base.update(over)
    s = make_sensor(preset, base)
    return Detector(s, build_effects(effects or {}, s), workers=1)


def _monte_carlo(det, signal, t, n):
    frames = np.stack([det.expose(signal, t, seed).astype(np.float64) for seed in range(n)])
    return frames.mean(0), frames.var(0, ddof=1)


@pytest.mark.parametrize("preset,binning", [("ml11002", 1), ("ml11002", 2), ("imx411", 2)])
def test_moments_match_monte_carlo(preset, binning):
    """Per-pixel mean and variance of 400 frames agree with the analytic moments within their sampling error."""
    eff = {"row_noise": {"sigma_e": 4.0}, "bias_gradient": {"gradient_x_adu": 30.0}, "nonlinearity": {"beta": 0.05}}
    det = _detector(preset, eff, binning=binning)
    ramp = np.linspace(50, 3000, 64, dtype=np.float32)[None, :] * np.ones((64, 1), np.float32)
    n = 300
    mc_mean, mc_var = _monte_carlo(det, ramp, 10.0, n)
    mean, var, flag = det.moments(ramp, 10.0)
    assert not flag.any()
    assert mean.shape == mc_mean.shape == det.sensor.output_shape
    # mean: standard error sqrt(var/n); compare the average normalised error and its spread
    z = (mc_mean - mean) / np.sqrt(var / n)
    assert abs(z.mean()) < 0.15 and 0.8 < z.std() < 1.2
    # variance: the sample variance of n Gaussian draws has relative std sqrt(2/(n-1)); the row noise makes
    # pixels of a row correlated, so test the average ratio
    ratio = mc_var / var
    assert abs(ratio.mean() - 1) < 0.03
    assert ratio.std() < 2.5 * np.sqrt(2 / (n - 1))


def test_saturated_pixels_are_flagged_and_clipped():
    det = _detector("ml11002")
    s = det.sensor
    sig = np.full((64, 64), 10.0, np.float32)
    sig[10:20, 10:20] = 5 * s.full_well_e
    mean, var, flag = det.moments(sig, 1.0)
    assert flag[10:20, 10:20].all() and not flag[30:, 30:].any()
    assert mean.max() <= s.adc_max_adu


def test_moments_ignore_cosmic_rays_and_are_seed_independent():
    det = _detector("ml11002", {"cosmic_rays": {"environment": "leo"}, "hot_pixels": {"count": 200000}})
    a = det.moments(100.0, 30.0, frame_seed=1)
    b = det.moments(100.0, 30.0, frame_seed=2)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    # hot pixels are a hardware pattern a real camera does not share: compared by counts, not in the mean
    assert a[0].max() - a[0].min() < 1e-3


def test_hardware_patterns_enter_as_variance():
    """PRNU and DSNU are the camera's own realisation: the model keeps their mean (1) and adds their spatial
    variance, (sigma_prnu S)^2 + (sigma_dsnu D)^2, which the spatial variance of one frame must match."""
    det = _detector("ml11002", {"prnu": {"sigma": 0.03}, "dsnu": {"sigma": 0.5, "law": "normal"}},
                    width=512, height=512, dark_current_e_per_s=20.0)
    signal = 4000.0
    mean, var, _ = det.moments(signal, 10.0)
    s = det.sensor
    expected_var = (signal + 200 + (0.03 * signal) ** 2 + (0.5 * 200) ** 2 + s.read_noise_e ** 2) / s.gain_e_per_adu ** 2
    assert np.allclose(var, expected_var + 1 / 12, rtol=1e-4)
    assert np.allclose(mean, s.bias_adu + (signal + 200) / s.gain_e_per_adu, rtol=1e-5)
    frame = det.expose(signal, 10.0, 3).astype(np.float64)
    assert abs(frame.var() / var.mean() - 1) < 0.02  # 262144 pixels: sampling error 0.3 %


@pytest.mark.parametrize("eff", [{"gain_regions": {"nx": 2, "ny": 1, "gains": [1.0, 1.25]}},
                                 {"nonlinearity": {"beta": 0.3}},
                                 {"nonlinearity": {"beta": 0.0, "gamma": 0.8}}])
def test_deterministic_responses_scale_the_variance_by_their_slope(eff):
    """Var f(S) = f'(S)^2 Var S (delta method): a gain region of 1.25 makes the noise 1.56 times larger, a
    response compressed near full well makes it quieter. Monte-Carlo frames of the chain against the model's
    variance, column by column (each column one signal level)."""
    det = _detector("ml11002", eff, dark_current_e_per_s=0.0, read_noise_e=2.0, gain_e_per_adu=1.0)
    fw = det.sensor.full_well_e
    ramp = np.linspace(0.05, 0.9, 64, dtype=np.float32)[None, :] * np.ones((64, 1), np.float32) * np.float32(fw)
    n = 60
    _, mc_var = _monte_carlo(det, ramp, 1.0, n)
    _, var, flag = det.moments(ramp, 1.0)
    plain = _detector("ml11002", None, dark_current_e_per_s=0.0, read_noise_e=2.0, gain_e_per_adu=1.0)
    _, var0, _ = plain.moments(ramp, 1.0)
    ok = ~flag.any(0)
    # per column: 64 pixels x (n - 1) dof, relative error sqrt(2 / (64 (n - 1)))
    ratio = (mc_var.mean(0) / var.mean(0))[ok]
    assert np.all(np.abs(ratio - 1) < 5 * np.sqrt(2 / (64 * (n - 1))))
    # and the effect is real: the unscaled variance is wrong somewhere by more than the test's resolution
    assert np.max(np.abs(mc_var.mean(0) / var0.mean(0) - 1)[ok]) > 0.15
