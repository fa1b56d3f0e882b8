"""The periodogram test of the residual morphology (detector.morphology: ``_peak``, ``row_power_factor``,
``describe``) on noise whose pixels of one row share an offset (row noise, a model's ``row_var_adu2``).

The defect this guards against: the whitened map ``z = r sqrt(w)`` is white pixel by pixel only; the row
offsets put all their power into the ``fx = 0`` column of the periodogram, ``g ~ (1 + (n_x - 1) rho) /
(1 - rho)`` times the white level (``rho = c w``), and the strongest of its ~256 bins (an exponential's
maximum, ~9 x its median) was taken for a single spatial frequency ``g x 9`` times the median power: a
``periodic`` pattern (a "line at 28.9 sensor rows", 1018 x the median, on the 8 x 8-binned null comparison
of the full IMX411 frame; a "period 11.1 px" line 95 x the median on a 1024^2 window of the ``default``
scene at full resolution). The period moved with the seed and vanished with ``row_noise`` off.

Independent references: the mean power of the ``fx = 0`` column of Monte-Carlo realisations (Wiener-Khinchin
for independent rows) against the closed form; white noise's periodogram maximum over ~3e4 bins (~15 x the
median, below the bar periodic_bar derives from the bins searched and FRAME_FALSE_ALARM, 25); a weak pick-up across the columns is still found at its period, and
a row pattern above the row noise still as rows.
"""

from __future__ import annotations

import numpy as np
import pytest

from detector.morphology import _peak, describe, periodic_bar, row_power_factor
from detector.sensor import make_sensor
from detector.signatures import Residuals, SpikeStats

N = 256
#: the pixels' own noise and the row offsets' variance [ADU^2]: rho = 0.13 as on the binned full IMX411 frame
OWN_VAR, ROW_VAR = 2260.0, 344.0


def _frame(seed: int, row_var: float = ROW_VAR, extra: np.ndarray | None = None) -> Residuals:
    """A null residual: a flat model of 1000 ADU, data = model + own noise + one offset per row (+ extra)."""
    rng = np.random.default_rng(seed)
    s = make_sensor("imx411", {"width": N, "height": N})
    model = np.full((N, N), 1000.0)
    data = model + rng.normal(0.0, np.sqrt(OWN_VAR), (N, N)) + rng.normal(0.0, np.sqrt(row_var), (N, 1))
    if extra is not None:
        data = data + extra
    var = np.full((N, N), OWN_VAR + row_var)  # a pixel's variance includes its row's offset
    f32 = np.float32
    return Residuals(data.astype(f32), model.astype(f32), var.astype(f32), np.ones((N, N), bool),
                     np.full((N, N), 100.0, f32), np.zeros((N, N), f32), np.arange(N, dtype=float),
                     np.arange(N, dtype=float), s, 2.0, SpikeStats(0, 0, 0, 0, 0), SpikeStats(0, 0, 0, 0, 0),
                     row_var_adu2=row_var)


def test_row_power_factor_matches_monte_carlo():
    """The closed form against the mean periodogram of 40 realisations (uneven weights, a masked patch)."""
    rng = np.random.default_rng(3)
    h, wd, c = 128, 128, 0.4
    own = rng.uniform(1.0, 4.0, (h, wd))
    w = 1.0 / (own + c)
    w[40:60, 30:90] = 0.0
    col0, rest = [], []
    for _ in range(40):
        r = rng.normal(0.0, np.sqrt(own)) + rng.normal(0.0, np.sqrt(c), (h, 1))
        z = np.where(w > 0, r * np.sqrt(w), 0.0)
        p = np.abs(np.fft.rfft2(z)) ** 2
        col0.append(p[1:, 0].mean())
        rest.append(p[1:, 1:].mean())
    measured = np.mean(col0) / np.mean(rest)
    g = row_power_factor(w, c)
    assert g == pytest.approx(1 + 127 * 0.4 / 2.5, rel=0.5)  # ~ (1 + (n_x - 1) rho) / (1 - rho), order of
    assert measured == pytest.approx(g, rel=0.05)
    # the residual in ADU (not whitened), as the periodic empirical map weighs it
    colA, restA = [], []
    for _ in range(40):
        r = np.where(w > 0, rng.normal(0.0, np.sqrt(own)) + rng.normal(0.0, np.sqrt(c), (h, 1)), 0.0)
        p = np.abs(np.fft.rfft2(r)) ** 2
        colA.append(p[1:, 0].mean())
        restA.append(p[1:, 1:].mean())
    assert np.mean(colA) / np.mean(restA) == pytest.approx(row_power_factor(w, c, whitened=False), rel=0.05)
    assert row_power_factor(w, 0.0) == 1.0


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_row_noise_alone_is_no_periodic_pattern(seed):
    """The model's own row noise, nothing missing: the morphology says noise (before the fix the fx = 0
    column's strongest bin stood at ~250 x the median: 'periodic')."""
    res = _frame(seed)
    zp = (res.data_adu - res.model_adu) / np.sqrt(res.var_adu2)
    _, raw, _ = _peak(zp - zp.mean())
    assert raw > periodic_bar(zp.shape)  # the mechanism is there: the unweighted periodogram is fooled
    m = describe(res)
    assert not m["significant"], m["explanation"]
    assert "periodic" not in m["geometry"]


def test_white_noise_contrast_is_unchanged():
    """No row noise declared: the factor is 1 and the contrast the white periodogram's (~15 x the median)."""
    res = _frame(4, row_var=0.0)
    zp = (res.data_adu - res.model_adu) / np.sqrt(res.var_adu2)
    period, contrast, _ = _peak(zp)
    assert 8 < contrast < periodic_bar(zp.shape)
    assert not describe(res)["significant"]


def test_a_weak_pickup_over_row_noise_is_still_periodic():
    """A sinusoid across the columns (pick-up at 7 px, amplitude 3 ADU: 6 % of a pixel's sigma, far too weak
    to move the block chi2) over the same row noise: 'periodic', at its period (the fx != 0 frequencies keep
    their white null)."""
    xx = np.ones((N, 1)) * np.arange(N, dtype=float)[None, :]
    m = describe(_frame(5, extra=3.0 * np.sin(2 * np.pi * xx / 7.0)))
    assert m["significant"] and m["geometry"] == ["periodic"], m["explanation"]
    assert m["scale_px"] == pytest.approx(7.0, rel=0.03)


def test_a_row_pattern_above_the_row_noise_is_still_found():
    """A sinusoid along the rows (pick-up at 23 rows, 20 ADU, beyond the 18.5 ADU row offsets): the row
    family, not lost to the row noise's null."""
    yy = np.arange(N, dtype=float)[:, None] * np.ones((1, N))
    m = describe(_frame(5, extra=20.0 * np.sin(2 * np.pi * yy / 23.0)))
    assert m["significant"] and "rows" in m["geometry"], m["explanation"]
