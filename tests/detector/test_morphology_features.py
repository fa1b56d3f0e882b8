"""Compact features of a whitened residual (detector.morphology.compact_features): the ``rings`` and ``blobs``
words of the ``residual_morphology`` vocabulary (issue 10).

Independent references: white Gaussian noise has no feature above the detection threshold (its band-passed
maximum over ~10^3 independent samples is ~4 sigma, far below FEATURE_PEAK = 8); a synthetic annulus is a ring
whose half-peak cut encloses the hole of radius ~ R - 1.2 sigma_r; a Gaussian blob has no hole; a smooth field
(a plane) is removed by the difference of Gaussians."""

import numpy as np
import pytest

from detector.morphology import FEATURE_PEAK, compact_features

N = 256


def _grid():
    return np.mgrid[0:N, 0:N].astype(np.float64)


def _noise(seed):
    return np.random.default_rng(seed).standard_normal((N, N))


def _ring(cy, cx, radius, width, amp):
    yy, xx = _grid()
    return amp * np.exp(-0.5 * ((np.hypot(yy - cy, xx - cx) - radius) / width) ** 2)


def _blob(cy, cx, sigma, amp):
    yy, xx = _grid()
    return amp * np.exp(-0.5 * ((yy - cy) ** 2 + (xx - cx) ** 2) / sigma ** 2)


OK = np.ones((N, N), bool)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_white_noise_has_no_feature(seed):
    f = compact_features(_noise(seed), OK)
    assert f["n_rings"] == f["n_blobs"] == f["n_srings"] == 0
    assert f["peak_sigma"] < FEATURE_PEAK


def test_a_smooth_plane_is_no_feature():
    yy, xx = _grid()
    f = compact_features(_noise(4) + 0.05 * (yy + 2 * xx), OK)  # 38 sigma across the frame
    assert f["n_rings"] == f["n_blobs"] == 0


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_an_annulus_is_a_ring_of_its_radius(sign):
    """A dust donut's shadow (negative) or a bright ring (positive), radius 30 px, width 3 px, 1.5 sigma/px:
    a ring whose filled area's radius lies between the inner and outer half-peak radii (~26.5 and ~33.5)."""
    f = compact_features(_noise(5) + sign * _ring(128, 120, 30.0, 3.0, 1.5), OK)
    assert f["n_rings"] >= 1 and f["n_blobs"] == 0
    assert 24.0 <= f["ring_radius_px"] <= 38.0
    assert f["rings"] > 0.5  # the ring takes most of the band-passed structure


def test_a_gaussian_blob_is_a_blob_not_a_ring():
    f = compact_features(_noise(6) + _blob(100, 150, 3.0, 4.0), OK)
    assert f["n_blobs"] == 1 and f["n_rings"] == 0
    assert 2.0 <= f["blob_radius_px"] <= 8.0


def test_rings_about_sources_are_their_own_family_and_blobs_near_sources_are_not_blobs():
    on_source = np.zeros((N, N), bool)
    for cy, cx in ((60, 60), (190, 70)):
        on_source[cy - 1:cy + 2, cx - 1:cx + 2] = True
    z = _noise(7) + _ring(60, 60, 9.0, 1.0, 3.0) + _ring(190, 70, 9.0, 1.0, 3.0)
    z += _blob(60, 185, 2.0, 6.0)  # a blob 5 px from a third source: a source's residual, not a free blob
    on_source[64:67, 184:187] = True
    f = compact_features(z, OK, on_source)
    assert f["n_srings"] == 2 and f["n_rings"] == 0
    assert f["n_blobs"] == 0
    assert 7.0 <= f["sring_radius_px"] <= 13.0


def test_masked_pixels_do_not_make_features():
    """A band of masked pixels (a bleeding column) in noise: the normalised convolution makes no edge."""
    ok = OK.copy()
    ok[:, 100:104] = False
    z = np.where(ok, _noise(8), 0.0)
    f = compact_features(z, ok)
    assert f["n_rings"] == f["n_blobs"] == 0
