"""The law of a response pattern's line gains: a gain for every column (a CMOS sensor's column amplifiers,
EMVA 1288 sect. 8.2) against a few deviating columns among identical ones (column defects)."""

from __future__ import annotations

import numpy as np

from detector.signatures import sparse_lines_gain


def _gauss_d(m, dn):
    """delta -2 ln L of the Gaussian random effect at its best variance (grid), as line_gains computes it."""
    best = 0.0
    for s2 in np.geomspace(1e-10, 1e-2, 400):
        best = min(best, float(np.sum(np.log1p(s2 * dn) + m * m / (s2 + 1.0 / dn) - m * m * dn)))
    return best


def test_a_few_weak_columns_are_a_sparse_set_and_column_gains_a_random_effect():
    rng = np.random.default_rng(23)
    n, err = 512, 1e-3
    dn = np.full(n, 1.0 / err ** 2)
    sparse = rng.normal(0, err, n)
    sparse[rng.choice(n, 12, replace=False)] -= 0.005  # twelve columns 0.5 % low, the rest alike
    gains = rng.normal(0, err, n) + rng.normal(0, 0.003, n)  # every column its own gain, 0.3 % rms
    pen = 2 * np.log(n)  # the sparse law's two parameters more (BIC)
    assert sparse_lines_gain(sparse, dn) + pen < _gauss_d(sparse, dn)
    assert sparse_lines_gain(gains, dn) + pen >= _gauss_d(gains, dn)
