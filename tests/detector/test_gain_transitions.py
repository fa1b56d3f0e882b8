"""Gain strips whose gains settle over tens of lines (tanh ramps) are steps, not a smooth response
(detector.effects.pixel_response.transitions_beat_curve, asked by the gain-regions plausibility check when a
staircase of found boundaries describes a line profile no better than a curve of as many parameters).

Independent references: the line profiles are drawn from their closed forms (two tanh ramps of one width on a
uniform signal; a quadratic fall-off of a vignetting; a cosine of a flat-field pattern) with Gaussian noise of the
stated variance, and the boundaries handed over are where a staircase segmentation would put them (several close
ones along each ramp)."""

import numpy as np
import pytest

from detector.effects.pixel_response import transitions_beat_curve

N = 512
SIGNAL = 2.0e6  # [ADU] a line sum of a flat
SIGMA = 1.0e3  # [ADU] the noise of a line sum (shot noise of 4e6 e- at gain 2 e-/ADU)


def _profile(rel: np.ndarray, seed: int):
    """(rc, sc, wc, centres) of line sums whose residual is ``rel`` times the signal, plus noise."""
    rng = np.random.default_rng(seed)
    centres = np.arange(N, dtype=np.float64) + 0.5
    sc = np.full(N, SIGNAL)
    rc = rel * sc + rng.normal(0.0, SIGMA, N)
    return rc, sc, np.full(N, SIGMA ** -2), centres


def test_two_wide_ramps_are_transitions():
    """Gains +0.4 % then -0.3 % reached over 22-line tanh ramps at lines 170 and 350 (each ramp ~ 40 sigma of a
    line sum), found as staircases of three boundaries each."""
    x = np.arange(N) + 0.5
    rel = 0.004 * 0.5 * (1 + np.tanh((x - 170) / 22.0)) - 0.007 * 0.5 * (1 + np.tanh((x - 350) / 22.0))
    rc, sc, wc, c = _profile(rel, 1)
    assert transitions_beat_curve(rc, sc, wc, c, [150.0, 170.0, 190.0, 330.0, 350.0, 372.0])


@pytest.mark.parametrize("kind", ["quadratic", "cosine"])
def test_a_smooth_response_is_no_transition(kind):
    """A vignetting's quadratic fall-off of 1 % to the edges, and a flat-field cosine of 0.3 % over 1.3 cycles:
    smooth, so a Legendre curve of as many parameters describes them at least as well as ramps do."""
    u = (np.arange(N) + 0.5) / N * 2 - 1
    rel = -0.01 * u ** 2 if kind == "quadratic" else 0.003 * np.cos(2 * np.pi * 1.3 * u / 2)
    for seed in range(3):
        rc, sc, wc, c = _profile(rel, 10 + seed)
        assert not transitions_beat_curve(rc, sc, wc, c, [60.0, 120.0, 400.0, 450.0])


@pytest.mark.parametrize("cycles", [3, 4, 6, 8])
def test_a_periodic_response_is_no_transition(cycles):
    """A sinusoid of 0.3 % over 3 to 8 cycles (tree rings, fringes through the line sums), with boundaries at its
    zero crossings: ramps can draw it only as wide as a third of their spacing, leaving no plateau."""
    u = (np.arange(N) + 0.5) / N
    rel = 0.003 * np.sin(2 * np.pi * cycles * u)
    zeros = [float(z) for z in (np.arange(1, 2 * cycles) * N / (2 * cycles))]
    for seed in range(3):
        rc, sc, wc, c = _profile(rel, 20 + seed)
        assert not transitions_beat_curve(rc, sc, wc, c, zeros)


def test_a_bump_is_no_transition():
    """A Gaussian bump of 0.4 % and 40 lines sigma (a dust shadow's, a coating's local change): two ramps up and
    down as wide as their spacing, no plateau between them."""
    x = np.arange(N) + 0.5
    rel = 0.004 * np.exp(-0.5 * ((x - 250) / 40.0) ** 2)
    for seed in range(3):
        rc, sc, wc, c = _profile(rel, 30 + seed)
        assert not transitions_beat_curve(rc, sc, wc, c, [200.0, 215.0, 285.0, 300.0])
