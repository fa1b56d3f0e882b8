"""Image-plane effects (psf_blur, jitter, pointing_drift, pointing_offset, distortion, ghost): exact physics checks."""

import numpy as np
import pytest

from detector import Detector, build_effects, make_sensor
from detector.effects import image_plane as ip


def _star(shape=(129, 129), x=64.0, y=64.0, sigma=2.0, flux=1e5):
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
    g = np.exp(-0.5 * ((xx - x) ** 2 + (yy - y) ** 2) / sigma ** 2)
    return (flux * g / g.sum()).astype(np.float32)


def _moments(img):
    yy, xx = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    f = img.sum()
    cx, cy = (img * xx).sum() / f, (img * yy).sum() / f
    cxx = (img * (xx - cx) ** 2).sum() / f
    cyy = (img * (yy - cy) ** 2).sum() / f
    cxy = (img * (xx - cx) * (yy - cy)).sum() / f
    return f, cx, cy, cxx, cyy, cxy


def test_blur_adds_its_variance_and_keeps_the_flux():
    img = _star(sigma=2.0)
    out = ip.blur(img, 1.5)
    f, cx, cy, cxx, cyy, _ = _moments(out)
    assert np.isclose(f, img.sum(), rtol=1e-5)
    assert np.isclose(cxx, 4.0 + 2.25, rtol=0.01) and np.isclose(cyy, 4.0 + 2.25, rtol=0.01)


@pytest.mark.parametrize("angle", [30.0, 90.0])
def test_elongated_blur_has_the_rotated_covariance(angle):
    img = _star(sigma=1.5)
    out = ip.blur(img, 3.0, 1.0, angle)
    _, _, _, cxx, cyy, cxy = _moments(out)
    c, s = np.cos(np.radians(angle)), np.sin(np.radians(angle))
    r = np.array([[c, -s], [s, c]])
    cov = r @ np.diag([9.0, 1.0]) @ r.T + 2.25 * np.eye(2)
    assert np.allclose([cxx, cyy, cxy], [cov[0, 0], cov[1, 1], cov[0, 1]], atol=0.05)


def test_a_filter_of_a_length_with_a_large_prime_factor_is_the_edge_extended_linear_convolution():
    """2 x 1031 (an image of 2048 padded by 7 on each side) is transformed on 2160 = 2^4 3^3 5 samples, the far
    sides extended by more edge values: the result is still the edge-extended image's linear convolution
    (a sampled Gaussian of sigma 1.5 px through ``scipy.ndimage``, mode "nearest"), and the extension
    is the same filter on a shorter image (to the transforms' rounding)."""
    from scipy import ndimage

    rng = np.random.default_rng(5)
    img = rng.gamma(2.0, 50.0, (40, 2048))
    img[:, :3] += 1e4  # a bright edge: what wraps round a periodic transform would show
    sigma = 1.5
    spectra: dict = {}
    out = ip.blur(img, sigma, spectra=spectra, workers=1)
    assert [v[1] for k, v in spectra.items() if k[0] != "out"] == [(54, 2160)]  # 40 + 2 x 7 = 54 = 2 x 3^3
    assert np.allclose(out, ip.blur(img, sigma), rtol=1e-12, atol=0)  # numpy's transforms (the rendering's)
    ref = ndimage.gaussian_filter(img, sigma, mode="nearest", truncate=8.0)
    assert np.max(np.abs(out - ref)) < 2e-3 * np.max(np.abs(ref))  # the sampled kernel vs the exact transfer
    inner = ip.blur(img[:, :2042], sigma)  # 2042 + 2 x 7 = 2056 = 2^3 257: extended to 2160 too
    assert np.allclose(inner[:, :1900], out[:, :1900], rtol=0, atol=1e-8 * np.max(img))  # transform rounding


def test_the_inverse_transform_in_two_passes_is_scipys_two_dimensional_one():
    """:func:`inverse_rfft2` (the diagnosis's inverse, one complex pass in place then one real pass) against
    ``scipy.fft.irfft2`` on even, odd and non-square grids, in both precisions: the same numbers to rounding,
    and the input recovered from its spectrum."""
    import scipy.fft

    rng = np.random.default_rng(8)
    for shape, dtype, tol in (((54, 2160), np.float64, 1e-13), ((33, 17), np.float64, 1e-13),
                              ((64, 50), np.float32, 1e-5)):
        img = rng.normal(size=shape).astype(dtype)
        spec = scipy.fft.rfft2(img) * rng.random((shape[0], shape[1] // 2 + 1)).astype(dtype)
        ref = scipy.fft.irfft2(spec, s=shape)
        out = ip.inverse_rfft2(spec.copy(), shape, 1)
        assert out.dtype == ref.dtype and out.shape == shape
        assert np.max(np.abs(out - ref)) < tol * np.max(np.abs(ref))
        back = ip.inverse_rfft2(scipy.fft.rfft2(img), shape, 2)
        assert np.max(np.abs(back - img)) < tol * np.max(np.abs(img))


def test_shift_moves_the_centroid():
    _, cx, cy, *_ = _moments(ip.shift(_star(), 1.3, -0.7))
    assert abs(cx - 65.3) < 1e-3 and abs(cy - 63.3) < 1e-3


def test_radial_distortion_moves_a_star_to_r_times_1_plus_k_r2():
    ys, xs = np.arange(200.0), np.arange(200.0)
    k = 2e-6
    img = _star((200, 200), x=170.0, y=100.0, sigma=1.5)  # r = 70 px from (100, 100)
    out = ip.radial_distortion(img, ys, xs, 100.0, 100.0, k)
    _, cx, cy, *_ = _moments(out)
    assert abs((cx - 100) - 70 * (1 + k * 70 ** 2)) < 0.02 and abs(cy - 100) < 1e-3


def test_ghost_is_reflected_through_the_axis_with_alpha_of_the_flux():
    ys, xs = np.arange(201.0), np.arange(201.0)
    img = _star((201, 201), x=150.0, y=120.0, sigma=1.0)
    g = ip.ghost_image(img, ys, xs, 100.0, 100.0, 6.0)
    f, cx, cy, *_ = _moments(g)
    assert np.isclose(f, img.sum(), rtol=1e-4)
    assert abs(cx - 50.0) < 0.05 and abs(cy - 80.0) < 0.05


def test_effects_run_in_the_chain_and_zero_strength_is_identity():
    s = make_sensor("ml11002", {"width": 128, "height": 128, "x0": 0, "y0": 0, "dark_current_e_per_s": 0.0})
    img = _star((128, 128), 40.0, 70.0, 1.5, 1e5)
    base = Detector(s, []).expose(img, 1.0, 1, noiseless=True)
    for name, params in {"psf_blur": {"sigma_px": 0.0}, "pointing_offset": {}, "distortion": {},
                         "ghost": {"alpha": 0.0}}.items():
        out = Detector(s, build_effects({name: params}, s)).expose(img, 1.0, 1, noiseless=True)
        assert np.allclose(out, base, atol=1e-2), name
    moved = Detector(s, build_effects({"pointing_offset": {"dx_px": 2.0}}, s)).expose(img, 1.0, 1, noiseless=True)
    assert abs(_moments(moved)[1] - 42.0) < 0.01


@pytest.mark.parametrize("dx,dy", [(6.0, 0.0), (4.3, -2.7), (0.0, 9.5)])
def test_drift_adds_the_box_variance_along_the_drift_and_keeps_flux_and_centroid(dx, dy):
    img = _star(sigma=2.0)
    f0, cx0, cy0, *_ = _moments(img)
    f, cx, cy, cxx, cyy, cxy = _moments(ip.drift_smear(img, dx, dy))
    assert abs(f - f0) < 1e-5 * f0
    assert abs(cx - cx0) < 1e-3 and abs(cy - cy0) < 1e-3
    # a uniform segment d adds the covariance d d^T / 12 (a box of length L has variance L^2 / 12)
    assert np.allclose([cxx, cyy, cxy], [4.0 + dx * dx / 12, 4.0 + dy * dy / 12, dx * dy / 12], atol=2e-3)


def test_drift_profile_is_a_box_not_a_gaussian():
    """A well-sampled source (1-px PSF) drifted by 8 px: flat top along the drift, nothing beyond its ends.
    (An undersampled source rings by a few per cent: the Fourier line kernel interpolates band-limited.)"""
    img = _star((161, 161), 80.0, 80.0, sigma=1.0)
    out = ip.drift_smear(img.astype(np.float64), 8.0, 0.0)
    row = out[80, 60:101]
    x = np.arange(60, 101) - 80.0
    inside = np.abs(x) <= 1  # 3 PSF sigma inside the ends
    assert np.ptp(row[inside]) < 0.01 * row[inside].mean()  # flat top
    assert np.all(row[np.abs(x) >= 8] < 0.01 * row.max())  # nothing beyond the ends (4 px + 4 PSF sigma)
    # a Gaussian of the same variance (jitter) peaks higher: the box is not a Gaussian smear
    gauss = ip.blur(img.astype(np.float64), np.sqrt(64 / 12), 0.0, 0.0)[80, 60:101]
    assert gauss.max() > 1.1 * row.max()


def test_drift_in_the_chain_zero_is_identity():
    s = make_sensor("ml11002", {"width": 128, "height": 128, "x0": 0, "y0": 0, "dark_current_e_per_s": 0.0})
    img = _star((128, 128), 40.0, 70.0, 1.5, 1e5)
    base = Detector(s, []).expose(img, 1.0, 1, noiseless=True)
    zero = Detector(s, build_effects({"pointing_drift": {"dx_px": 0.0, "dy_px": 0.0}}, s)).expose(img, 1.0, 1,
                                                                                              noiseless=True)
    assert np.allclose(zero, base, atol=1e-3)
    moved = Detector(s, build_effects({"pointing_drift": {"dx_px": 5.0, "dy_px": 0.0}}, s)).expose(img, 1.0, 1,
                                                                                               noiseless=True)
    assert np.isclose(_moments(moved)[3], _moments(base)[3] + 25 / 12, atol=0.01)


def test_a_pointing_offset_with_rotation_and_scale_moves_a_star_by_the_similarity_transform():
    """pointing_offset's similarity about the sensor centre: a star at p (from the centre) goes to
    (1 + scale) R(rot) p + d, its flux kept (bilinear: the pixel boxes' overlap)."""
    s = make_sensor("ml11002", {"width": 128, "height": 128, "x0": 0, "y0": 0, "dark_current_e_per_s": 0.0})
    yc, xc = (s.sensor_height_px - 1) / 2.0, (s.sensor_width_px - 1) / 2.0
    img = _star((128, 128), 40.0, 70.0, 1.5, 1e5)
    base = Detector(s, []).expose(img, 1.0, 1, noiseless=True)
    prm = {"dx_px": 0.3, "dy_px": -0.2, "rot_deg": 0.02, "scale": 3e-4}
    out = Detector(s, build_effects({"pointing_offset": prm}, s)).expose(img, 1.0, 1, noiseless=True)
    f0, cx0, cy0, *_ = _moments(base - np.median(base))
    f, cx, cy, *_ = _moments(out - np.median(out))
    a = np.radians(prm["rot_deg"])
    px, py = cx0 - xc, cy0 - yc  # about 2000 px from the centre: the rotation moves it by ~0.6 px
    ex = xc + (1 + prm["scale"]) * (np.cos(a) * px - np.sin(a) * py) + prm["dx_px"]
    ey = yc + (1 + prm["scale"]) * (np.sin(a) * px + np.cos(a) * py) + prm["dy_px"]
    assert abs(cx - ex) < 0.01 and abs(cy - ey) < 0.01 and abs(f - f0) < 1e-3 * f0



def test_the_core_with_wings_is_not_fitted_when_the_round_core_alone_is_no_candidate(monkeypatch):
    """psf_blur's joint form (core and halo) starts only from a round core that is a candidate alone: its core is
    the sources' widening less the wings' share, so without a widening core it would end refused; the start is
    then None (no fit, no Fourier transform of the frame) before anything of the residuals is read."""
    asked = []

    def no_core(res, name, sub):
        asked.append((name, tuple(sub)))
        return None

    monkeypatch.setattr(ip.PSFBlur.signature, "form_fit", no_core)
    assert ip._blur_start(object(), (0, 1, 2)) is None
    assert asked == [("psf_blur", (0,))]


def test_a_kept_transform_fit_is_fitted_once_per_frame_and_handed_out_as_copies(monkeypatch):
    """The pointing offset's fit (``keep``: the distortion's check asks for it too) is made once per frame's
    residuals; each caller gets a copy whose parameters and state it may change without changing the other's."""
    from detector.signatures import Fit

    class Res:  # the residuals' memo, nothing else
        def __init__(self):
            self.kept = {}

        def memo(self, key, compute):
            if key not in self.kept:
                self.kept[key] = compute()
            return self.kept[key]

    sig = ip.PointingOffset.signature
    assert sig.keep and not ip.PSFBlur.signature.keep
    made = []
    monkeypatch.setattr(sig, "_fit_all", lambda res, name: made.append(name) or Fit(
        name, {"dx_px": 0.1, "dy_px": 0.0}, -50.0, 2, 100, "why", state={"transform_theta": np.zeros(4)}))
    res = Res()
    a, b = sig.fit(res, "pointing_offset"), sig.fit(res, "pointing_offset")
    assert made == ["pointing_offset"] and a is not b and a.params == b.params
    a.params["dx_px"], a.state["extra"] = 9.0, 1
    assert b.params["dx_px"] == 0.1 and "extra" not in b.state
    sig.fit(Res(), "pointing_offset")  # another frame: fitted again
    assert made == ["pointing_offset"] * 2
