"""The median-of-squares variance estimate and its standard error (detector.stats), shared by the judge's
noise-excess test and the variance signature's cells."""

import numpy as np
import pytest

from detector.stats import CHI2_1_MEDIAN, median_square_variance, median_square_variance_error


def test_chi2_1_median():
    from scipy.stats import chi2

    assert CHI2_1_MEDIAN == pytest.approx(chi2.ppf(0.5, 1), rel=1e-12)


def test_the_estimate_is_the_variance_and_its_error_its_scatter():
    rng = np.random.default_rng(5)
    var, n = 7.0, 4000
    est = np.array([median_square_variance(rng.normal(0.0, np.sqrt(var), n)) for _ in range(400)])
    assert est.mean() == pytest.approx(var, rel=0.02)
    assert est.std() == pytest.approx(median_square_variance_error(var, n), rel=0.15)
    # 2.72 times the variance of the mean of squares (var sqrt(2 / n))
    assert (median_square_variance_error(var, n) / (var * np.sqrt(2.0 / n))) ** 2 == pytest.approx(2.72, abs=0.01)
    assert median_square_variance_error(var, 0) == np.inf
    assert np.isnan(median_square_variance([]))
