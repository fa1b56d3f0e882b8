"""Additive or multiplicative on a uniform light, from the sources (issue 10, item 4: the residual's
dependence on the model's light).

On a sky frame the background is uniform, so a pattern on it is as well an added light as a change of the
response. The sources tell them apart: a response pattern scales them too, an added light does not. The
background's residual next to each source (its column's, row's or a local mean) predicts the source pixels'
residual under either law. Checked on synthetic star fields with a known law: a streak of added light
along the columns through the stars (a read-out smear) and shadows that dim the stars with the sky.

A row or column pattern is also described as periodic, with its period, when one frequency of its line profile
is a line above the noise and above its neighbours (a pick-up, a flicker through a rolling shutter), not when
its power is a red continuum (a drift, a random walk).
"""

from __future__ import annotations

import numpy as np
import pytest

from detector.morphology import _kind_from_sources
from detector.sensor import make_sensor
from detector.signatures import Residuals, SpikeStats


def _field(law: str, seed: int = 2):
    """A 256 x 256 sky of 300 ADU with 60 Gaussian stars (peaks 500-20000 ADU), the data carrying ``law``:
    "smear" adds 2e-3 of every column's star light to the whole column (less its mean); "shadow" multiplies sky and stars
    by 1 - 0.1 exp(-d^2 / 2 30^2) about 6 points (dust shadows). Poisson noise at gain 1."""
    rng = np.random.default_rng(seed)
    h = w = 256
    yy, xx = np.mgrid[:h, :w].astype(float)
    stars = np.zeros((h, w))
    for y0, x0, a in zip(rng.uniform(5, h - 5, 60), rng.uniform(5, w - 5, 60), np.exp(rng.uniform(np.log(500), np.log(2e4), 60))):
        stars += a * np.exp(-((yy - y0) ** 2 + (xx - x0) ** 2) / (2 * 1.3 ** 2))
    sky = np.full((h, w), 300.0)
    model = sky + stars
    if law == "smear":  # its mean is taken by the comparison's level fit: only the streaks remain
        smear = 2e-3 * stars.sum(axis=0)
        truth = model + (smear - smear.mean())[None, :]
    else:
        att = np.ones((h, w))
        for y0, x0 in rng.uniform(30, 226, (6, 2)):
            att -= 0.1 * np.exp(-((yy - y0) ** 2 + (xx - x0) ** 2) / (2 * 30.0 ** 2))
        truth = model * att
    data = rng.poisson(truth).astype(float)
    s = make_sensor("ml11002", {"width": w, "height": h})
    zero = SpikeStats(0, 0, 0, 0, 0)
    res = Residuals(data.astype(np.float32), model.astype(np.float32), np.maximum(model, 1).astype(np.float32),
                    np.ones((h, w), bool), model.astype(np.float32), np.zeros((h, w), np.float32),
                    np.arange(h, dtype=float), np.arange(w, dtype=float), s, 10.0, zero, zero,
                    background_adu=sky.astype(np.float32), light_source="sky")
    idx = np.arange(h * w)
    r, wt = (data - model).ravel(), 1.0 / np.maximum(model, 1).ravel()
    # the comparison's level fit: the background's mean residual is zero (what a frame-wide law cannot use)
    off = stars.ravel() * np.sqrt(wt) <= 5.0
    r -= np.sum(r[off] * wt[off]) / np.sum(wt[off])
    return res, idx, r, wt


def test_a_streak_of_added_light_through_the_stars_is_additive():
    assert _kind_from_sources(*_field("smear")) == "additive"


def test_shadows_that_dim_the_stars_too_are_multiplicative():
    assert _kind_from_sources(*_field("shadow")) == "multiplicative"


# ------------------------------------------------------------------------------------ periodic lines
def test_a_line_profile_with_a_sinusoid_has_its_period():
    """A pick-up of period 37.3 lines at 1.5 sigma amplitude in white noise: found within 2 %."""
    from detector.morphology import _line_period

    rng = np.random.default_rng(4)
    n = 600
    lm = 1.5 * np.sin(2 * np.pi * np.arange(n) / 37.3) + rng.standard_normal(n)
    assert _line_period(lm, np.ones(n)) == pytest.approx(37.3, rel=0.02)


def test_white_lines_and_a_random_walk_are_not_periodic():
    """White noise (a max of 300 chi2(2)/2 powers stays far below 30) and a random walk (a red continuum: its
    largest low frequency is not a line above its neighbours) give no period."""
    from detector.morphology import _line_period

    rng = np.random.default_rng(5)
    n = 400
    for _ in range(50):
        assert _line_period(rng.standard_normal(n), np.ones(n)) == 0.0
    walks = [np.cumsum(rng.standard_normal(n)) * 0.3 + rng.standard_normal(n) for _ in range(20)]
    assert sum(_line_period(w, np.ones(n)) > 0 for w in walks) <= 1


def test_a_streak_through_the_sources_gives_the_smear_fraction():
    """Column means of a read-out smear: each pixel holds the fraction of its column's source light that the
    data were given (2e-3), recovered within 5 %; a column pattern unrelated to the sources is not 'through
    the sources'."""
    from detector.morphology import _lines_through_sources

    res, idx, r, w = _field("smear")
    rm, wm = np.zeros(res.data_adu.shape), np.zeros(res.data_adu.shape)
    rm.ravel()[idx], wm.ravel()[idx] = r * w, w
    lw = wm.sum(axis=0)
    lm = rm.sum(axis=0) / lw
    ok = np.ones(lm.size, bool)
    excess = float(np.sum(lw * (lm - np.sum(lw * lm) / np.sum(lw)) ** 2) - lm.size)
    assert _lines_through_sources(res, lm, lw, ok, 0, excess) == pytest.approx(2e-3, rel=0.05)
    other = np.random.default_rng(1).permutation(lm)  # the same column offsets, in other columns
    assert _lines_through_sources(res, other, lw, ok, 0, excess) is None
