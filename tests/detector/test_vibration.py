"""Sinusoidal vibration (jitter's second form): the J0 transfer function against a shift-and-add of the
sinusoidal path, its arcsine variance, and the diagnosis telling an oscillation from a one-way drift."""

import numpy as np
import pytest

from detector.effects import image_plane as ip


def _gauss(shape, x, y, sigma):
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
    return np.exp(-0.5 * ((xx - x) ** 2 + (yy - y) ** 2) / sigma ** 2) / (2 * np.pi * sigma ** 2)


@pytest.mark.parametrize("a", [(2.0, 0.0), (1.2, -1.6), (0.0, 3.5)])
def test_vibration_kernel_equals_a_shift_and_add_along_the_sine(a):
    """Mean of 4000 analytic Gaussians at a sin(2 pi t) (one whole period, midpoint rule): no FFT."""
    n, sigma, c = 81, 1.5, 40.0
    out = ip.vibration_smear(_gauss((n, n), c, c, sigma), *a)
    t = (np.arange(4000) + 0.5) / 4000
    ref = sum(_gauss((n, n), c + a[0] * np.sin(2 * np.pi * ti), c + a[1] * np.sin(2 * np.pi * ti), sigma) for ti in t)
    ref /= t.size
    assert np.max(np.abs(out - ref)) < 1e-3 * ref.max()
    # moments: flux kept, covariance + a a^T / 2 (arcsine variance A^2 / 2)
    yy, xx = np.mgrid[0:n, 0:n]
    f = out.sum()
    cxx = (out * (xx - c) ** 2).sum() / f
    cyy = (out * (yy - c) ** 2).sum() / f
    assert f == pytest.approx(1.0, abs=1e-6)
    assert cxx == pytest.approx(sigma ** 2 + a[0] ** 2 / 2, rel=1e-3)
    assert cyy == pytest.approx(sigma ** 2 + a[1] ** 2 / 2, rel=1e-3)


def test_the_diagnosis_names_an_oscillation_jitter_and_a_trail_drift(tmp_path):
    """A star field shaken back and forth (1.6 px either way along 60 deg) is fitted by jitter's vibration form
    (amplitude and direction recovered) and beats the drift's box; the drift trail of the drift tests stays
    a drift (test_drift_path)."""
    from test_drift_path import _residuals

    from detector.effects.base import registry

    res = _residuals(tmp_path, "[effects.jitter]\nsigma_major_px = 0.0\nsigma_minor_px = 0.0\nangle_deg = 60.0\n"
                               "vibration_px = 1.6\n")
    jit = registry()["jitter"].signature.fit(res, "jitter")
    drift = registry()["pointing_drift"].signature.fit(res, "pointing_drift")
    assert jit.params["vibration_px"] == pytest.approx(1.6, abs=0.1), jit.params
    assert abs((jit.params["angle_deg"] - 60.0 + 90) % 180 - 90) < 3, jit.params
    assert "vibration" in jit.explanation
    assert drift is None or jit.delta_bic < drift.delta_bic - 100, (jit.delta_bic, drift and drift.delta_bic)
