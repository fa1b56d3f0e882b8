"""A periodic pattern that no plugin models is described as periodic, and its description predicts pixels it
was not made from (detector.morphology ``describe`` and ``_periodic_map``; detector.signatures
``periodic_line_peak`` and ``line_gains``; issue 23: "a name must beat a description").

The defects this guards against: a pattern of a few pixels' period averages out in the morphology's blocks
and raised the pixel chi2 as added noise would, so the description was "extra noise" and a noise name
(reset noise, DSNU) tied with it; the periodic map made from one fold of the held-out checkerboard kept the
copies of the pattern the fold's mask makes (they change sign on the other fold) and half its amplitude; a
PRNU's line-wise gains took a pattern repeating across the columns for independent column gains.

Independent references: a sinusoid's exact chi2 (``N A^2 / 2 sigma^2``), the Gaussian held-out score of the
truth itself on the other fold, and white noise (no period flagged).
"""

from __future__ import annotations

import numpy as np

from detector.morphology import _periodic_map, describe
from detector.sensor import make_sensor
from detector.signatures import (
    Residuals,
    SpikeStats,
    checkerboard,
    line_gains,
    periodic_line_peak,
)

N = 256
SIG = 10.0  # [ADU]


def _res(extra: np.ndarray, seed: int = 1) -> Residuals:
    rng = np.random.default_rng(seed)
    s = make_sensor("imx411", {"width": N, "height": N})
    model = np.full((N, N), 1000.0)
    data = model + rng.normal(0.0, SIG, (N, N)) + extra
    f32 = np.float32
    return Residuals(data.astype(f32), model.astype(f32), np.full((N, N), SIG ** 2, f32), np.ones((N, N), bool),
                     np.full((N, N), 100.0, f32), np.zeros((N, N), f32), np.arange(N, dtype=float),
                     np.arange(N, dtype=float), s, 2.0, SpikeStats(0, 0, 0, 0, 0), SpikeStats(0, 0, 0, 0, 0))


def _wave(period_px: float, angle_deg: float, amp: float) -> np.ndarray:
    yy, xx = np.mgrid[0:N, 0:N].astype(float)
    a = np.radians(angle_deg)
    return amp * np.sin(2 * np.pi * (xx * np.cos(a) + yy * np.sin(a)) / period_px + 0.7)


def test_fine_periodic_pattern_is_periodic_not_noise():
    """A sinusoid of period 3.8 px (finer than the morphology's 5 px blocks: no block-scale mean) at 0.4 sigma
    (chi2 ~ 5200, the pixel chi2 beyond its dof ~ 14 sigma of a noise excess: the added-noise branch) is a
    periodic pattern of that period, not extra noise."""
    m = describe(_res(_wave(3.8, 44.0, 0.4 * SIG)))
    assert m["significant"]
    assert m["geometry"][0] == "periodic", m["explanation"]
    assert abs(m["scale_px"] - 3.8) < 0.1
    assert m["empirical"] is not None and m["empirical"]["kind"] == "additive"


def test_white_noise_is_not_periodic():
    """Pure white noise: nothing significant (no period is read into the noise)."""
    assert not describe(_res(np.zeros((N, N)), seed=5))["significant"]


def test_periodic_map_from_one_fold_predicts_the_other():
    """The periodic map made from the black squares of the held-out checkerboard predicts the white ones: the
    chi2 it removes there is at least 80 % of what the truth itself removes (the fold's mask copies of the
    pattern and its halved amplitude would leave less than half), and the fold map is the truth's amplitude."""
    truth = _wave(4.4, 0.0, 0.5 * SIG)
    res = _res(truth, seed=2)
    r = (res.data_adu - res.model_adu).astype(float)
    black = checkerboard((N, N))
    w = np.where(black, 1.0 / SIG ** 2, 0.0)
    amap = np.asarray(_periodic_map(np.where(black, r, 0.0), w, np.zeros((N, N)), "additive")["map"], float)
    held = ~black
    gain_map = float(np.sum(r[held] ** 2 - (r[held] - amap[held]) ** 2)) / SIG ** 2
    gain_truth = float(np.sum(r[held] ** 2 - (r[held] - truth[held]) ** 2)) / SIG ** 2
    assert gain_map > 0.8 * gain_truth, (gain_map, gain_truth)
    assert abs(float(np.std(amap)) / float(np.std(truth)) - 1.0) < 0.1


def test_periodic_line_peak_flags_a_period_not_white_lines():
    """A line profile with a sinusoid of period 4.4 lines at 1 sigma is periodic; 200 white profiles give at
    most one flag (the false-alarm probability is one-sided 5 sigma per profile)."""
    rng = np.random.default_rng(3)
    k = np.arange(N)
    assert periodic_line_peak(rng.normal(size=N) + np.sqrt(2) * np.sin(2 * np.pi * k / 4.4)) is not None
    assert sum(periodic_line_peak(rng.normal(size=N)) is not None for _ in range(200)) <= 1


def test_line_gains_refuse_a_periodic_column_pattern():
    """Column gains that repeat every 4.4 columns are a periodic pattern seen through the columns, not a PRNU's
    independent column gains; independent gains of the same rms are found."""
    light = np.full((N, N), 1000.0)
    k = np.arange(N)
    periodic = light * (0.02 * np.sin(2 * np.pi * k / 4.4))[None, :]
    assert line_gains(_res(periodic, seed=4), light, axis=1) is None
    rng = np.random.default_rng(6)
    white = light * (0.02 * np.sqrt(0.5) * rng.normal(size=N))[None, :]
    got = line_gains(_res(white, seed=4), light, axis=1)
    assert got is not None and abs(got["sigma"] / (0.02 * np.sqrt(0.5)) - 1.0) < 0.25


def test_outlier_columns_are_asked_again_after_a_periodic_description():
    """The judge asks outlier counts again once the description is in the model (``outlier_count``: hot pixels'
    counts and the column defects' outlier columns alike). A flat (1000 ADU) whose column response is a square
    wave of period 18 columns, 1.5 % deep, is described as periodic with a map that is not the columns' own
    (form ``columns``, of which the columns are not asked: it is their own image), so the column defects would
    be judged on what the periodic map leaves; the map takes the pattern (what it leaves is the noise)."""
    from dataclasses import replace

    from detector import registry
    from detector.morphology import _line_map
    from detector.signatures import CountSignature

    assert registry()["column_defects"].signature.outlier_count and CountSignature.outlier_count
    k = np.arange(N)
    light = np.full((N, N), 1000.0)
    truth = light * (0.015 * np.sign(np.sin(2 * np.pi * (k + 0.5) / 18.0)))[None, :]
    res = replace(_res(truth, seed=7), photo_adu=light.astype(np.float32), light_source="flat", _flat={})
    m = describe(res)
    assert "periodic" in m["geometry"] and m["empirical"].get("form") != "columns", m["explanation"]
    emp = m["empirical"]
    delta = np.asarray(emp["map"], float) * (light if emp["kind"] == "multiplicative" else 1.0)
    r = (res.data_adu - res.model_adu).astype(float)
    left = float(np.mean(((r - r.mean()) - (delta - delta.mean())) ** 2)) / SIG ** 2
    # a square wave holds 8 / pi^2 (1 + 1/9 + 1/25) of its power (1.5 sigma)^2 in the three peaks the map keeps
    kept = 8.0 / np.pi ** 2 * (1.0 + 1.0 / 9.0 + 1.0 / 25.0)
    assert left < 1.0 + (1.0 - kept) * 1.5 ** 2 + 0.02, left
    assert _line_map(r, np.full((N, N), 1.0), light, "additive", axis=0)["form"] == "columns"


def test_periodic_bar_is_the_frame_false_alarm_of_the_bins_searched():
    """The bar of a periodogram peak over the median power, from the number of frequencies searched: the
    strongest of n exponential bins passes c x median with probability ~ n 2^-c (Monte Carlo of white noise on
    a 64 x 64 cut: 2112 bins, bar log2(2112 / 1e-3) = 21.0; the bar a factor 10 lower in false alarm sits
    log2(10) higher)."""
    import pytest

    from detector.morphology import periodic_bar, periodic_contrast, tested_frequencies
    from detector.significance import FRAME_FALSE_ALARM

    assert tested_frequencies((64, 64)) == 64 * 33
    assert periodic_bar((64, 64)) == pytest.approx(np.log2(64 * 33 / FRAME_FALSE_ALARM))
    assert periodic_bar((668, 1002)) == pytest.approx(26.97, abs=0.01)  # a 512 x 512 cut
    assert periodic_contrast(10 * 2112) - periodic_contrast(2112) == pytest.approx(np.log2(10.0))
    # the exceedance of a lower bar (c = 12, where n 2^-c = 0.52) by the strongest white-noise bin: 1 - e^-0.52
    rng = np.random.default_rng(5)
    hits = 0
    for _ in range(200):
        p = np.abs(np.fft.rfft2(rng.standard_normal((64, 64)))) ** 2
        p = p.ravel()[1:]
        hits += p.max() / np.median(p) > 12.0
    assert hits / 200 == pytest.approx(1 - np.exp(-2112 * 2.0 ** -12), abs=0.1)


def _rings(period_px: float, cy: float, cx: float, amp: float) -> np.ndarray:
    yy, xx = np.mgrid[0:N, 0:N].astype(float)
    return amp * np.sin(2 * np.pi * np.hypot(yy - cy, xx - cx) / period_px)


def test_rings_longer_than_a_few_blocks_are_periodic_with_their_period():
    """Arcs of rings (tree rings) of period 40 px about a centre off the frame, at 0.25 sigma (chi2 ~ 2000, 3 % of the
    pixel chi2): the block-scale smoothing of the first periodogram
    takes periods of more than a few blocks (5 px) out and the smooth basis does not follow rings, so no family
    held a quarter of the excess and the largest share (columns, 2 %) was the description. The unsmoothed
    periodogram finds the period (within its bin, 256 / 6 px) and its band-passed map takes most of the excess:
    the exact ring pattern's chi2 (sum of its square over the variance) is the independent reference."""
    truth = _rings(40.0, -180.0, 420.0, 0.25 * SIG)
    m = describe(_res(truth, seed=3))
    assert m["significant"]
    assert m["geometry"][0] == "periodic", m["explanation"]
    assert abs(m["scale_px"] - 40.0) < 4.0
    emp = m["empirical"]
    assert emp is not None and emp["kind"] == "additive"
    exact = float(np.sum(truth ** 2)) / SIG ** 2
    got = float(np.sum(truth ** 2 - (truth - emp["map"]) ** 2)) / SIG ** 2  # the map's gain on the truth itself
    assert got > 0.5 * exact, (got, exact)


def test_rings_of_five_cycles_across_the_window_are_periodic_not_columns():
    """Arcs of tree rings 56 px apart (4.6 cycles across the 256 px window) about a centre off a corner, 0.3 % of a
    flat's light (multiplicative): the unsmoothed periodogram once left out everything below 6 cycles, and so the
    pattern itself; the description was its 3 % share of column means ("column gains"). Only what the smooth basis
    holds (SMOOTH_ORDER cycles) is left out: the period is found within its bin and the map takes most of the
    exact pattern's chi2 (the independent reference)."""
    truth = _rings(56.0, -400.0, -150.0, 0.35 * SIG)
    m = describe(_res(truth, seed=4))
    assert m["significant"]
    assert m["geometry"][0] == "periodic", m["explanation"]
    assert abs(m["scale_px"] - 56.0) < 256 / 4.6 - 256 / 5.6  # one frequency bin
    exact = float(np.sum(truth ** 2)) / SIG ** 2
    got = float(np.sum(truth ** 2 - (truth - m["empirical"]["map"]) ** 2)) / SIG ** 2
    assert got > 0.5 * exact, (got, exact)


def test_a_smooth_random_field_is_not_periodic():
    """A Gaussian random field with its power spread over 3 to 10 cycles across the frame (a flat-field's large
    scales, a PRNU's low-frequency part) at 0.3 sigma: its periodogram's largest bin passes the white-noise bar,
    but the radius it sits at stands no higher than the radii beside it (a continuum, no period): not periodic."""
    for seed in range(3):
        rng = np.random.default_rng(40 + seed)
        f = np.fft.fft2(rng.standard_normal((N, N)))
        fy, fx = np.fft.fftfreq(N)[:, None] * N, np.fft.fftfreq(N)[None, :] * N
        band = (np.hypot(fy, fx) >= 3) & (np.hypot(fy, fx) <= 10)
        field = np.real(np.fft.ifft2(f * band))
        field *= 0.3 * SIG / field.std()
        m = describe(_res(field, seed=50 + seed))
        assert m["significant"] and "periodic" not in m["geometry"], m["explanation"]
