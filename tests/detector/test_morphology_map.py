"""The empirical map of compact features (detector.morphology): the per-source profile of a ring moved around the
sources, and the matched-filter selection of the features significant on their own.

Independent checks: the profile's fitted ring fraction and core deficit against the known ones, within the
standard errors of weighted least squares computed here from templates built with another convolution
(scipy.ndimage.correlate, direct sums); the selection against white noise (its false alarms are rare by
construction, MAP_FALSE_ALARM per frame and scale) and against a blob of known matched-filter S/N.
"""

import math

import numpy as np
from scipy import ndimage as ndi

from detector.morphology import MAP_GROW_SIGMA, _seed_sigma, _significant_features, _source_profile_map, matched_snr

N = 192
SIG_ADU = 5.0


def _stars(seed: int, n: int = 40) -> np.ndarray:
    """Gaussian stars (sigma 1.2 px) of 2e3-2e5 ADU at random places [ADU]."""
    rng = np.random.default_rng(seed)
    img = np.zeros((N, N))
    yy, xx = np.mgrid[0:N, 0:N]
    for _ in range(n):
        cy, cx = rng.uniform(12, N - 12, 2)
        f = 10 ** rng.uniform(3.3, 5.3)
        img += f * np.exp(-0.5 * ((yy - cy) ** 2 + (xx - cx) ** 2) / 1.2 ** 2) / (2 * math.pi * 1.2 ** 2)
    return img


def _annulus(k: int, n: int) -> np.ndarray:
    t = np.arange(-n, n + 1)
    rr = np.hypot(t[:, None], t[None, :])
    return ((np.abs(rr - k) < 0.5) if k else (rr < 0.5)).astype(np.float64)


def test_source_profile_recovers_a_ring_around_known_sources():
    """3 % of every star's light moved from its core to a ring of 6 px: the fitted profile holds +3 % in the
    ring's annuli and -3 % at the core, within 4 standard errors, and the map leaves white noise."""
    src = _stars(1)
    frac, radius, n = 0.03, 6, 10
    ring = _annulus(radius, n)
    kernel = frac * ring / ring.sum() - frac * _annulus(0, n)
    truth = ndi.correlate(src, kernel, mode="constant")
    rng = np.random.default_rng(2)
    r = truth + rng.normal(0.0, SIG_ADU, src.shape)
    w = np.full(src.shape, 1.0 / SIG_ADU ** 2)
    amap, c = _source_profile_map(r, w, src, float(n))
    assert c.size == n + 1
    # the standard errors of the ring's and the core's fractions: (a^T G^-1 a)^1/2, G from direct sums
    temps = np.stack([ndi.correlate(src, _annulus(k, n), mode="constant").ravel() for k in range(n + 1)])
    cov = np.linalg.inv((temps / SIG_ADU ** 2) @ temps.T)
    a_ring = np.array([_annulus(k, n).sum() if k == radius else 0.0 for k in range(n + 1)])
    a_core = np.eye(n + 1)[0]
    se_ring, se_core = math.sqrt(a_ring @ cov @ a_ring), math.sqrt(a_core @ cov @ a_core)
    assert abs(float(a_ring @ c) - frac) < 4 * se_ring, (a_ring @ c, se_ring)
    assert abs(float(c[0]) + frac) < 4 * se_core, (c[0], se_core)
    assert se_ring < 0.1 * frac  # a measurement, not an upper limit
    # what the map leaves is the noise: chi2 / n within 5 sigma of 1 (n + 1 fitted parameters aside)
    z2 = float(np.mean(((r - amap) / SIG_ADU) ** 2))
    assert abs(z2 - 1.0) < 5 * math.sqrt(2.0 / r.size) + (n + 1) / r.size
    # and it is the ring: the truth is recovered to a small fraction of itself
    assert float(np.sqrt(np.mean((amap - truth) ** 2))) < 0.05 * float(np.sqrt(np.mean(truth ** 2)))


def test_matched_filter_is_unit_normal_on_white_noise():
    rng = np.random.default_rng(3)
    r = rng.normal(0.0, SIG_ADU, (N, N))
    w = np.full(r.shape, 1.0 / SIG_ADU ** 2)
    snr = matched_snr(r, w, 2.0)
    assert abs(float(np.std(snr)) - 1.0) < 0.1
    assert abs(float(np.mean(snr))) < 0.1


def test_significant_features_none_in_white_noise():
    """White noise seeds no feature (the threshold is a false alarm of 1e-3 per frame and scale)."""
    w = np.full((N, N), 1.0 / SIG_ADU ** 2)
    found = sum(int(_significant_features(np.random.default_rng(s).normal(0.0, SIG_ADU, (N, N)), w, None,
                                          (1.0, 2.0)).any()) for s in range(4, 9))
    assert found == 0


def test_significant_features_finds_a_blob_of_known_snr_and_leaves_the_sources():
    """A Gaussian blob (s = 2 px) of matched-filter S/N 9 (above the seed threshold, below the morphology's
    FEATURE_PEAK on a difference of Gaussians) is found, grown to its 2-sigma contour; the same blob within
    3 s of a source's core is the source's."""
    s, target = 2.0, 9.0
    assert _seed_sigma(N * N, s) < target
    amp = target * SIG_ADU / math.sqrt(math.pi * s * s)  # S/N = A sqrt(sum g^2) / sigma
    yy, xx = np.mgrid[0:N, 0:N]
    blob = amp * np.exp(-0.5 * ((yy - 60) ** 2 + (xx - 130) ** 2) / s ** 2)
    r = np.random.default_rng(5).normal(0.0, SIG_ADU, (N, N)) + blob
    w = np.full(r.shape, 1.0 / SIG_ADU ** 2)
    found = _significant_features(r, w, None, (1.0, 2.0)) > 0
    assert found[60, 130]
    _, n = ndi.label(found)
    assert n == 1
    # the footprint reaches where the blob's matched S/N (9 exp(-d^2 / 4 s^2)) falls to ~MAP_GROW_SIGMA
    d_edge = 2 * s * math.sqrt(math.log(target / MAP_GROW_SIGMA))
    assert abs(math.sqrt(found.sum() / math.pi) - d_edge) < 2.5
    core = np.zeros(r.shape, bool)
    core[60, 125] = True  # a source's core 5 px away (< 3 s)
    assert not (_significant_features(r, w, core, (1.0, 2.0)) > 0).any()


def test_a_trail_passing_a_source_keeps_its_pixels_away_from_it():
    """A straight trail (S/N ~ 9 per matched filter) across the frame that passes 3 px from a source's core is
    mapped along its length; only the pixels by the source are left to it."""
    yy, xx = np.mgrid[0:N, 0:N]
    d = np.abs((yy - 40) - 0.5 * (xx - 20)) / math.hypot(1.0, 0.5)  # distance to the line y = 40 + (x - 20) / 2
    trail = 6.0 * SIG_ADU * np.exp(-0.5 * (d / 1.2) ** 2)
    r = np.random.default_rng(8).normal(0.0, SIG_ADU, (N, N)) + trail
    w = np.full(r.shape, 1.0 / SIG_ADU ** 2)
    core = np.zeros(r.shape, bool)
    core[40 + 50 + 3, 120] = True  # by the trail at x = 120 (the line is at y = 90 there)
    found = _significant_features(r, w, core, (1.0, 2.0)) > 0
    on_line = d < 1.0
    far = ~ndi.binary_dilation(core, iterations=6)
    assert found[on_line & far].mean() > 0.8
    assert not found[ndi.binary_dilation(core, iterations=3)].any()  # within 3 s of the core at s = 1


def test_the_catch_all_does_not_see_the_held_out_fold():
    """The catch-all (the residual's empirical map) is cross-validated like every candidate: fitted on one fold of
    the checkerboard, scored on the other. A blob of known template chi2 on a flat frame: the map fitted on one
    fold does not follow the other fold's noise (the feature's unfitted core is filled from the fold's own
    spikes only, not from the held-out pixels), and the held-out score it reaches is at most what the exact template itself removes, within
    5 of its standard deviations (a description cannot predict unseen pixels better than the truth but by
    noise; a map copying the held-out residual would reach the whole residual's chi2 in its footprint)."""
    from helpers import residuals_of, small_sensor

    from detector.signatures import _folds, checkerboard
    from scenes.app.compare.catch_all import CatchAll, catch_all_heldout

    n = 128
    sensor = small_sensor(width=n, height=n, bias_adu=100.0)
    rng = np.random.default_rng(5)
    yy, xx = np.mgrid[0:n, 0:n]
    photo = np.full((n, n), 300.0)
    var = np.full((n, n), 300.0 / sensor.gain_e_per_adu + 9.0)
    blob = 60.0 * np.exp(-((yy - 60.0) ** 2 + (xx - 70.0) ** 2) / (2 * 6.0 ** 2))
    model = photo + sensor.bias_adu
    data = model + blob + rng.normal(0.0, 1.0, (n, n)) * np.sqrt(var)
    res = residuals_of(data, model, var, photo, sensor)
    truth_chi2 = float(np.sum(blob ** 2 / var))
    fa, fb = _folds(res, checkerboard(res.data_adu.shape))
    fit = CatchAll().fit(fa, "catch_all")
    assert fit is not None
    held = fb.fit & (np.abs(fit.delta_adu) > 0)
    assert held.any()
    # the map's error at those pixels does not follow their noise (a copy of the residual would, to a level)
    noise = (res.data_adu - res.model_adu - blob)[held]
    err = (np.asarray(fit.delta_adu) - blob)[held]
    assert np.corrcoef(noise, err)[0, 1] < 0.5
    ca = catch_all_heldout(res)
    assert ca is not None and ca < 0
    assert -ca < truth_chi2 + 5 * 2 * np.sqrt(truth_chi2), (ca, truth_chi2)
