"""compare's full-resolution spectrum peaks (scenes.app.compare.statistics.spectrum_peaks) on noise whose
pixels of one row share an offset (the model's row noise, ``row_var_adu2``).

Independent reference: without the row offsets' null, the strongest bins of the ``fx = 0`` column stand at
~g x 9 times the median (an exponential's maximum over ~256 bins, g = (1 + (n_x - 1) rho) / (1 - rho) from
Wiener-Khinchin); with it, the table's top peak is white noise's (~15-25 x the median over ~1.3e5 bins), and a
real 2 x 2 pattern still tops it at its analytic ratio N^2 a^2 / ln 2 (N^2 pixels, a its amplitude in sigma).
"""

import numpy as np
import pytest

from scenes.app.compare.statistics import spectrum_peaks

N = 512
OWN_VAR, ROW_VAR = 36.0, 0.7  # [ADU^2]: rho = 0.019, as the default IMX411 scene at full resolution


def _z(seed, extra=0.0):
    rng = np.random.default_rng(seed)
    r = rng.normal(0.0, np.sqrt(OWN_VAR), (N, N)) + rng.normal(0.0, np.sqrt(ROW_VAR), (N, 1)) + extra
    var = OWN_VAR + ROW_VAR
    return r / np.sqrt(var), np.full((N, N), 1.0 / var)


@pytest.mark.parametrize("seed", [1, 2])
def test_row_noise_is_no_peak_once_weighed(seed):
    z, w = _z(seed)
    raw = spectrum_peaks(z)["peaks"][0]
    assert raw["fx"] == 0.0 and raw["power_ratio"] > 40  # the mechanism: the fx = 0 column on top
    top = spectrum_peaks(z, weights=w, row_var_adu2=ROW_VAR)["peaks"][0]
    assert top["power_ratio"] < 30, top


def test_a_checkerboard_still_tops_the_table():
    yy, xx = np.indices((N, N))
    a = 0.1  # [sigma]
    z, w = _z(3, extra=a * np.sqrt(OWN_VAR + ROW_VAR) * np.where((xx + yy) % 2, -1.0, 1.0))
    top = spectrum_peaks(z, weights=w, row_var_adu2=ROW_VAR)["peaks"][0]
    assert (top["fx"], top["fy"]) == (0.5, 0.5)
    assert top["power_ratio"] == pytest.approx(N * N * a * a / np.log(2), rel=0.2)
