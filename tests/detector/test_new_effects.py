"""cfa and sky_gradient: physics checks against independent results (pointing_drift: test_image_plane.py)."""

import numpy as np
import pytest

from detector import Detector, build_effects, make_sensor
from detector.effects.colour import cfa_response

RESPONSE = [1.05, 0.8, 0.6, 1.02]


def _sensor(**kw):
    base = {"width": 256, "height": 256, "x0": 1000, "y0": 600, "dark_current_e_per_s": 0.0}
    return make_sensor("ml11002", {**base, **kw})


def _cells(img, y0, x0):
    """Pixels of an image grouped by the sensor parity (row, column) of their cell: dict (p, q) -> values."""
    ys = (y0 + np.arange(img.shape[0])) % 2
    xs = (x0 + np.arange(img.shape[1])) % 2
    return {(p, q): img[np.ix_(ys == p, xs == q)] for p in (0, 1) for q in (0, 1)}


# --- cfa ----------------------------------------------------------------------------------------------------

def test_cfa_flat_cell_means_are_in_the_ratio_of_the_responses_within_poisson_error():
    s = _sensor()
    flat_e = 4000.0
    det = Detector(s, build_effects({"cfa": {"response": RESPONSE}}, s))
    adu = det.expose(flat_e, 1.0, 5).astype(np.float64) - s.bias_adu
    g, rn = s.gain_e_per_adu, s.read_noise_e
    for (p, q), v in _cells(adu, s.roi_y0, s.roi_x0).items():
        expect = RESPONSE[2 * p + q] * flat_e / g - 0.5  # the ADC truncation lowers the mean by 1/2 ADU
        err = np.sqrt(RESPONSE[2 * p + q] * flat_e + rn ** 2 + g * g / 12) / g / np.sqrt(v.size)
        assert abs(v.mean() - expect) < 5 * err, ((p, q), v.mean(), expect, err)


@pytest.mark.parametrize("x0,y0", [(1001, 600), (1000, 601), (1003, 605)])
def test_cfa_window_origin_shifts_the_pattern_with_the_sensor_parity(x0, y0):
    s = _sensor(x0=x0, y0=y0, width=8, height=6)
    out = Detector(s, build_effects({"cfa": {"response": RESPONSE}}, s)).expose(100.0, 1.0, 1, noiseless=True)
    # window pixel (0, 0) is sensor pixel (y0, x0): its cell is (y0 mod 2, x0 mod 2)
    expect = np.array([[RESPONSE[2 * ((y0 + i) % 2) + (x0 + j) % 2] * 100.0 for j in range(8)] for i in range(6)])
    assert np.allclose(out, expect, rtol=1e-6)


def test_cfa_even_binning_gives_the_mean_response_and_odd_binning_the_cell_fractions():
    s2 = _sensor(binning=2, width=64, height=64)
    out = Detector(s2, build_effects({"cfa": {"response": RESPONSE}}, s2)).expose(100.0, 1.0, 1, noiseless=True)
    assert np.allclose(out, 4 * 100.0 * np.mean(RESPONSE), rtol=1e-6)  # 2x2 sum, uniform
    # 3x3 blocks from an odd origin: the block means of the unbinned response (independent brute force)
    s1 = _sensor(x0=1001, y0=603, width=63, height=63)
    fine = Detector(s1, build_effects({"cfa": {"response": RESPONSE}}, s1)).expose(1.0, 1.0, 1, noiseless=True)
    blocks = fine.reshape(21, 3, 21, 3).mean(axis=(1, 3))
    ys0, xs0 = 603 + 3 * np.arange(21), 1001 + 3 * np.arange(21)
    assert np.allclose(cfa_response(ys0, xs0, RESPONSE, b=3), blocks, rtol=1e-6)


def test_cfa_acts_on_light_not_on_dark_or_bias():
    s = _sensor(dark_current_e_per_s=2.0, width=16, height=16)
    with_cfa = Detector(s, build_effects({"cfa": {"response": RESPONSE}}, s)).expose(0.0, 100.0, 1, noiseless=True)
    assert np.allclose(with_cfa, 200.0)


# --- sky_gradient -------------------------------------------------------------------------------------------

def test_sky_gradient_column_means_follow_the_analytic_ramp_and_darks_have_none():
    s = _sensor(width=512, height=256)
    gx, gy, t, sky = 40.0, -25.0, 10.0, 300.0
    det = Detector(s, build_effects({"sky_gradient": {"gx_e_per_s_per_kpx": gx, "gy_e_per_s_per_kpx": gy}}, s))
    adu = det.expose(sky * t, t, 9).astype(np.float64) - s.bias_adu + 0.5
    g = s.gain_e_per_adu
    xs = s.roi_x0 + np.arange(512.0)
    ys = s.roi_y0 + np.arange(256.0)
    xc, yc = (s.sensor_width_px - 1) / 2, (s.sensor_height_px - 1) / 2
    ramp_e = t * (gx * (xs - xc) + gy * (ys.mean() - yc)) / 1000.0  # column means: rows averaged
    col = adu.mean(axis=0)
    err = np.sqrt((sky * t + ramp_e + s.read_noise_e ** 2) / g ** 2 + 1 / 12) / np.sqrt(256)
    chi2 = float(np.sum(((col - (sky * t + ramp_e) / g) / err) ** 2))
    assert chi2 < 512 + 5 * np.sqrt(2 * 512), chi2  # chi-square with 512 degrees of freedom
    # a fit of a line to the column means gives the slope back
    slope = np.polyfit(xs, col, 1)[0] * g * 1000 / t
    assert abs(slope - gx) < 0.05 * abs(gx)
    # a dark frame (no light) has no sky
    dark = det.expose(0.0, t, 9, noiseless=True)
    assert np.all(dark == 0.0)


def test_quad_bayer_cells_are_two_pixels_wide_and_bin_like_the_pixels():
    """Period 4 (each filter over 2 x 2 pixels): pixel (y, x) has cell ((y // 2) % 2, (x // 2) % 2); a binned
    pixel's response is the mean of its sensor pixels' (computed here pixel by pixel)."""
    resp = [0.62, 1.0, 0.98, 0.75]
    ys, xs = np.arange(-3, 13), np.arange(5, 21)
    one = cfa_response(ys, xs, resp, 1, period=4)
    r = np.asarray(resp).reshape(2, 2)
    assert np.allclose(one, r[(ys[:, None] // 2) % 2, (xs[None, :] // 2) % 2])
    for b in (2, 3, 4):
        y0s, x0s = np.arange(-3, 9, b), np.arange(1, 13, b)
        direct = np.array([[np.mean([r[(y // 2) % 2, (x // 2) % 2] for y in range(y0, y0 + b)
                                     for x in range(x0, x0 + b)]) for x0 in x0s] for y0 in y0s])
        assert np.allclose(cfa_response(y0s, x0s, resp, b, period=4), direct)
    assert np.allclose(cfa_response(np.arange(0, 16, 4), np.arange(0, 16, 4), resp, 4, period=4), np.mean(resp))
