"""Row noise in the candidates' likelihood: generalised least squares with each row's shared offset.

The Woodbury form (``detector.signatures``: ``x' V^-1 y = x' W y - sum_i g_i U_i(x) U_i(y)``) against the
dense covariance ``V = D + c 1 1'`` solved directly, and its purpose: on residuals that are only the model's
own row noise, a template with a row-mean component (a gradient along the columns) gains chi2(1), not the
row offsets' hundreds; a real gradient is still found.
"""

from __future__ import annotations

import numpy as np
import pytest

from detector.sensor import make_sensor
from detector.signatures import Fit, Residuals, SpikeStats, fit_linear, gls_quadratic, lstsq_delta, pixel_score


def _res(r, var, row_var):
    h, w = r.shape
    s = make_sensor("imx411", {"width": w, "height": h})
    z = np.zeros((h, w), np.float32)
    return Residuals((r + 100).astype(np.float32), np.full((h, w), 100, np.float32), var.astype(np.float32),
                     np.ones((h, w), bool), z, z, np.arange(h, dtype=float), np.arange(w, dtype=float), s, 1.0,
                     SpikeStats(0, 0, 0, 0, 0), SpikeStats(0, 0, 0, 0, 0), row_var_adu2=row_var)


def _dense_gls(r, var, row_var, temps):
    """Direct GLS: V = diag(var) + c (same row), solved densely (an independent implementation)."""
    h, w = r.shape
    rows = np.repeat(np.arange(h), w)
    v = np.diag(var.ravel()) + row_var * (rows[:, None] == rows[None, :])
    vi = np.linalg.inv(v)
    t = np.atleast_2d(temps)
    a, b = t @ vi @ t.T, t @ vi @ r.ravel()
    c = np.linalg.solve(a, b)
    return c, -(b @ c), float(r.ravel() @ vi @ r.ravel())


def test_woodbury_matches_the_dense_covariance():
    rng = np.random.default_rng(1)
    h, w, c_row = 12, 10, 3.0
    var = rng.uniform(1, 4, (h, w))
    r = rng.normal(0, 1, (h, w)) * np.sqrt(var) + rng.normal(0, np.sqrt(c_row), (h, 1))
    temps = np.stack([np.linspace(-1, 1, h)[:, None] * np.ones((1, w)), rng.normal(size=(h, w))]).reshape(2, -1)
    c_dense, d_dense, q_dense = _dense_gls(r, var, c_row, temps)
    rows = np.repeat(np.arange(h), w)
    assert gls_quadratic(r.ravel(), 1 / var.ravel(), rows, c_row) == pytest.approx(q_dense, rel=1e-9)
    c2, d2, _ = lstsq_delta(r.ravel(), 1 / var.ravel(), temps, None, rows, c_row)
    assert np.allclose(c2, c_dense, rtol=1e-8) and d2 == pytest.approx(d_dense, rel=1e-8)
    # fit_linear profiles the frame's global levels out: the dense GLS with them as nuisance templates
    res = _res(r, var, c_row)
    idx = np.arange(h * w)
    n = res.level_values(idx)
    assert n.size  # (a bias offset at least)
    c_all, d_all, _ = _dense_gls(r, var, c_row, np.vstack([temps, n]))
    _, d_levels, _ = _dense_gls(r, var, c_row, n)
    c3, d3 = fit_linear(res, lambda i: temps[:, i], idx, r.ravel(), 1 / var.ravel())
    assert np.allclose(c3, c_all[:2], rtol=1e-7) and d3 == pytest.approx(d_all - d_levels, rel=1e-7)


def test_row_offsets_are_not_a_gradient_but_a_gradient_is_found():
    """512 x 512 of white noise (var 100) plus the model's own row noise (c = 13, a row mean's white noise
    is 0.2): a gradient along the columns gains ~chi2(1) with the rows' covariance, hundreds without it."""
    rng = np.random.default_rng(4)
    h = w = 512
    var = np.full((h, w), 100.0)
    grad = np.linspace(-0.5, 0.5, h)[:, None] * np.ones((1, w))
    gains, plain = [], []
    for seed in range(6):
        g = np.random.default_rng(seed)
        r = g.normal(0, 10, (h, w)) + g.normal(0, np.sqrt(13.0), (h, 1))
        res = _res(r, var, 13.0)
        gains.append(-pixel_score(Fit("g", {}, 0.0, 1, h * w, "", delta_adu=fit_linear(
            res, lambda i: grad.ravel()[i][None, :], *res.flat())[0][0] * grad), res))
        plain.append(-pixel_score(Fit("g", {}, 0.0, 1, h * w, "", delta_adu=fit_linear(
            _res(r, var, 0.0), lambda i: grad.ravel()[i][None, :], *res.flat())[0][0] * grad), _res(r, var, 0.0)))
    assert np.mean(gains) < 6 and max(gains) < 15  # chi2(1): mean 1
    assert np.mean(plain) > 50  # the diagonal likelihood takes the row offsets for a gradient
    # a real gradient of 3 ADU across the frame: 3 sigma of the row offsets over 512 rows, clearly found
    r = rng.normal(0, 10, (h, w)) + rng.normal(0, np.sqrt(13.0), (h, 1)) + 3.0 * grad
    res = _res(r, var, 13.0)
    c, d = fit_linear(res, lambda i: grad.ravel()[i][None, :], *res.flat())
    assert c[0] == pytest.approx(3.0, abs=1.0) and -d > 25


def test_row_offsets_that_repeat_are_a_periodic_pattern_not_row_noise():
    """Row noise draws a new offset for every row read: white from row to row. The same rms of row offsets as
    a square wave of period 4.6 rows (a pickup) is refused as row noise (a spectral line far above its
    neighbours); drawn independently it is accepted. The false-alarm rate of the line test on white offsets
    of 64-2672 rows, measured: at most 1 in 2000 (the bound of PERIODIC_FALSE_ALARM is for an exactly known
    level; the level here is estimated from 32 neighbours)."""
    from detector.effects.readout import RowOffsetSignature

    rng = np.random.default_rng(4)
    h, w, amp = 334, 120, 3.0
    y = np.arange(h)
    periodic = amp * np.sign(np.sin(2 * np.pi * y / 4.6))
    sig = RowOffsetSignature()
    for offsets, periodic_expected in ((periodic, True), (rng.normal(0, amp, h), False)):
        r = rng.normal(0, 5.0, (h, w)) + offsets[:, None]
        res = _res(r, np.full((h, w), 25.0), 0.0)
        fit = sig.fit(res, "row_noise")
        assert fit is not None and fit.delta_bic < -100
        why = sig.plausible(fit, res)
        assert ("period" in why) == periodic_expected, why
    flags = sum(RowOffsetSignature.periodic_peak(rng.normal(size=334)) is not None for _ in range(500))
    assert flags <= 2


def _power_law_series(n, alpha, rng):
    f = np.fft.rfftfreq(n)
    f[0] = f[1]
    x = np.fft.irfft((rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size)) * f ** (-alpha / 2), n)
    return x / x.std()


def test_flicker_row_offsets_are_told_from_a_drifting_level_by_their_spectral_law():
    """Correlated row offsets: a read chain's 1/f (flicker) noise has spectral index ~1, a level drifting as a
    random walk ~2 (its Whittle index); the row-noise plausibility tells them apart by the Whittle likelihoods of
    the two laws (drift_law_gain: negative for the drift)."""
    from detector.effects.readout import RowOffsetSignature as R

    rng = np.random.default_rng(35)
    n = 2048
    x = np.linspace(-1, 1, n)
    basis = np.polynomial.legendre.legvander(x, R.SMOOTH_DEGREE)
    for make, lo, hi, drift in ((lambda: _power_law_series(n, 1.0, rng), 0.7, 1.3, False),
                                (lambda: np.cumsum(rng.standard_normal(n)) / 20.0, 1.8, 2.5, True)):
        u = 3.0 * make() + rng.standard_normal(n)  # the extra offsets over the row means' pixel noise
        u = u - basis @ np.linalg.lstsq(basis, u, rcond=None)[0]
        alpha = R.spectral_index(u, float(np.mean(u * u)))
        assert lo < alpha < hi
        assert (R.drift_law_gain(u, float(np.mean(u * u))) < 0) == drift


def test_a_flicker_row_noise_with_a_large_smooth_part_is_row_noise_but_a_smooth_curve_is_not():
    """A row noise with a flicker (1/f) part: a polynomial of the row takes a large share of its excess (its
    lowest frequencies), yet the rows beyond that curve still scatter far above the pixel noise (a chi2 test,
    DETECTION_SIGMA): row noise. The same rms as a smooth curve (a parabola along the columns) leaves nothing
    beyond the curve: a 2-D pattern seen through the rows, refused."""
    from detector.effects.readout import RowOffsetSignature as R

    rng = np.random.default_rng(40)
    h, w = 1024, 96
    y = np.linspace(-1, 1, h)
    smooth = 2.0 * (y ** 2 - np.mean(y ** 2)) / np.std(y ** 2)
    x = np.linspace(-1, 1, h)
    basis = np.polynomial.legendre.legvander(x, R.SMOOTH_DEGREE)
    # a pink series whose smooth part holds most of its variance (the old share rule refused it)
    for seed in range(50):
        pink = 2.0 * _power_law_series(h, 1.0, np.random.default_rng(seed))
        share = np.sum((basis @ np.linalg.lstsq(basis, pink, rcond=None)[0]) ** 2) / np.sum(pink ** 2)
        if share > 0.5:
            break
    assert share > 0.5
    sig = R()
    for offsets, row_noise in ((pink, True), (smooth, False)):
        r = rng.normal(0, 5.0, (h, w)) + offsets[:, None]
        res = _res(r, np.full((h, w), 25.0), 0.0)
        fit = sig.fit(res, "row_noise")
        assert fit is not None and fit.delta_bic < -100
        why = sig.plausible(fit, res)
        assert ("smooth curve" not in why) == row_noise, why
