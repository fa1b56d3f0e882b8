"""The linear fits' treatment of a template the global levels already hold (detector.signatures.fit_linear)."""

from __future__ import annotations

import numpy as np

from detector.sensor import make_sensor
from detector.signatures import Residuals, SpikeStats, fit_linear


def _ramp_dark_frame(seed=5):
    """A 200 x 300 lit window whose model's dark signal rises linearly along x (a dark-rate gradient, +-50 %
    across) with a faint DSNU in its map, and pure noise as the residual."""
    rng = np.random.default_rng(seed)
    s = make_sensor("ml11002", {"width": 300, "height": 200})
    h, w = s.output_shape
    ys, xs = np.arange(h, dtype=float), np.arange(w, dtype=float)
    dark = np.broadcast_to(200.0 * (1.0 + 0.5 * (2 * xs / (w - 1) - 1))[None, :], (h, w)).astype(np.float32)
    dark = (dark * (1.0 + 1e-4 * rng.normal(0, 1, (h, w)))).astype(np.float32)  # a faint DSNU in the map
    photo = np.full((h, w), 800.0, np.float32)
    model = (1000.0 + photo + dark / s.gain_e_per_adu).astype(np.float32)
    var = (25.0 + model - 1000.0).astype(np.float32)
    data = (model + rng.normal(0, 1, (h, w)) * np.sqrt(var)).astype(np.float32)
    return Residuals(data, model, var, np.ones((h, w), bool), photo, dark, ys, xs, s, 10.0,
                     SpikeStats(0, 0, 0, 0, 0), SpikeStats(0, 0, 0, 0, 0))


def test_a_template_the_levels_hold_gets_no_coefficient():
    """A linear term across the window is (but for the DSNU's 1e-4) the dark level's ramp: its coefficient would be
    the noise's, compensated by an opposite dark level; it is dropped (LEVEL_DEGENERACY, the levels' own rule)
    and the curvature beside it is fitted as usual."""
    res = _ramp_dark_frame()
    idx, _, w = res.flat_profiled()
    r = res.flat()[1]
    width = res.data_adu.shape[1]
    u = 2 * (idx % width) / (width - 1) - 1

    def values(i):
        uu = 2 * (np.asarray(i) % width) / (width - 1) - 1
        return np.stack([uu, uu * uu - 1 / 3])

    assert np.ptp(u) > 1.9  # the template itself is no constant: what holds it is the dark level's ramp
    c, d = fit_linear(res, values, idx, r, w)
    assert c[0] == 0.0
    assert np.isfinite(c[1]) and abs(c[1]) < 5.0  # noise only: a few ADU at most
    assert d <= 0.0


def test_a_row_constant_template_under_row_noise_is_fitted_not_dropped():
    """Row noise down-weights a template constant along the rows (the rows' offsets could make it), but the
    levels do not hold it: a real vertical ramp is fitted, its chi2 gain large, not counted dead."""
    rng = np.random.default_rng(7)
    s = make_sensor("ml11002", {"width": 1024, "height": 256})
    h, w = s.output_shape
    ys, xs = np.arange(h, dtype=float), np.arange(w, dtype=float)
    v = 2 * ys / (h - 1) - 1
    model = np.full((h, w), 1000.0, np.float32)
    var = np.full((h, w), 25.0, np.float32)
    data = (model + 6.0 * v[:, None] + rng.normal(0, 5.0, (h, w))).astype(np.float32)
    zero = np.zeros((h, w), np.float32)
    res = Residuals(data, model, var, np.ones((h, w), bool), zero, zero, ys, xs, s, 0.0,
                    SpikeStats(0, 0, 0, 0, 0), SpikeStats(0, 0, 0, 0, 0), row_var_adu2=50.0)
    idx, _, wts = res.flat_profiled()
    c, d = fit_linear(res, lambda i: (2 * (np.asarray(i) // w) / (h - 1) - 1)[None, :], idx, res.flat()[1], wts)
    # row noise of twice the pixel variance over 1024 columns leaves the ramp 1/2049 of its white-noise chi2
    # (~61 of ~126000): below LEVEL_DEGENERACY of its white-noise norm, yet a detection
    assert abs(c[0] - 6.0) < 2.0 and d < -30
