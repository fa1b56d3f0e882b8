"""pointing_drift along a second-order path (accel along the track, sagitta across): the kernel against an
independent shift-and-add, its moments against the analytic ones, the straight drift unchanged, and the
diagnosis recovering the path (and preferring it to a Gaussian smear)."""

import numpy as np
import pytest

from detector import Detector, build_effects, make_sensor
from detector.effects import image_plane as ip
from detector.effects.image_plane import DriftParams


def _gauss(shape, x, y, sigma, flux=1.0):
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
    g = np.exp(-0.5 * ((xx - x) ** 2 + (yy - y) ** 2) / sigma ** 2)
    return flux * g / (2 * np.pi * sigma ** 2)


def _path(t, d, accel, sagitta):
    """The path written out independently: d t + (accel |d| d_hat + 4 sagitta n_hat)(t^2 - 1/12),
    n_hat = d_hat rotated +90 deg."""
    d = np.asarray(d, float)
    length = np.hypot(*d)
    u = d / length
    n = np.array([-u[1], u[0]])
    q = accel * length * u + 4 * sagitta * n
    return np.outer(t, d) + np.outer(t * t - 1 / 12, q)  # (nt, 2) as (x, y)


def _moments(img):
    yy, xx = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    f = img.sum()
    cx, cy = (img * xx).sum() / f, (img * yy).sum() / f
    c = np.array([[(img * (xx - cx) ** 2).sum(), (img * (xx - cx) * (yy - cy)).sum()],
                  [(img * (xx - cx) * (yy - cy)).sum(), (img * (yy - cy) ** 2).sum()]]) / f
    return f, cx, cy, c


PATHS = [((5.0, 2.0), 1.0, 0.0), ((3.0, -4.0), -0.6, 0.8), ((0.0, 7.0), 0.3, -1.2), ((6.0, 0.0), 0.0, 1.5)]


@pytest.mark.parametrize("d,accel,sag", PATHS)
def test_path_kernel_equals_a_shift_and_add_along_the_path(d, accel, sag):
    """A narrow Gaussian source smeared by the Fourier path kernel equals the mean of 4000 copies of the
    analytic Gaussian centred at p(t_k) (midpoint rule in time): an independent implementation, no FFT."""
    n, sigma, c = 81, 1.5, 40.0
    img = _gauss((n, n), c, c, sigma)
    out = ip.drift_smear(img, *d, accel, sag)
    t = (np.arange(4000) + 0.5) / 4000 - 0.5
    ref = np.zeros_like(img)
    for px, py in _path(t, d, accel, sag):
        ref += _gauss((n, n), c + px, c + py, sigma)
    ref /= t.size
    assert np.max(np.abs(out - ref)) < 1e-3 * ref.max()


def test_the_conventions_accel_dwells_at_the_start_and_sagitta_turns_counter_clockwise():
    """accel = +1 starts at rest: the trail is brightest at its -d end; sagitta > 0: the trail's middle lies
    on the -n_hat side of the chord joining its ends (the path turns towards +n_hat)."""
    n, c = 121, 60.0
    img = _gauss((n, n), c, c, 1.0)
    out = ip.drift_smear(img, 12.0, 0.0, 1.0, 0.0)
    row = out[60]
    assert row[60 - 3] > 1.5 * row[60 + 6]  # the -x side (start, at rest) brighter than the +x side
    assert np.argmax(row) < 60 - 2  # peak near the start p(-1/2) = -4 px
    out = ip.drift_smear(img, 12.0, 0.0, 0.0, 2.0)  # n_hat = +y: ends at y = +4/3 px, middle at -2/3 px
    yy = (np.arange(n) - c)[54:67]  # centroids within 6 px of the trail (the band limit rings faintly)
    mid, end = out[54:67, 60], out[54:67, 60 + 5]
    assert np.sum(yy * mid) / np.sum(mid) == pytest.approx(-2 / 3, abs=0.1)
    assert np.sum(yy * end) / np.sum(end) > 0.5  # towards the ends, on +n_hat: the chord at +4/3 px


@pytest.mark.parametrize("d,accel,sag", PATHS + [((4.3, -2.7), 0.9, 0.4)])
def test_moments_of_the_path_kernel(d, accel, sag):
    """Flux and centroid unchanged (the path's time-mean is the origin); the covariance adds the path's:
    along d |d|^2 (1/12 + accel^2 / 180), across 16 sagitta^2 / 180, between 4 accel |d| sagitta / 180
    (uniform t on [-1/2, 1/2]: var t = 1/12, var t^2 = 1/80 - 1/144 = 1/180, cov(t, t^2) = 0)."""
    img = _gauss((129, 129), 64.0, 64.0, 2.0, 1e5).astype(np.float64)
    f0, cx0, cy0, c0 = _moments(img)
    f, cx, cy, c = _moments(ip.drift_smear(img, *d, accel, sag))
    assert abs(f - f0) < 1e-8 * f0
    assert abs(cx - cx0) < 1e-4 and abs(cy - cy0) < 1e-4
    length = np.hypot(*d)
    u = np.array(d) / length
    nrm = np.array([-u[1], u[0]])
    r = np.stack([u, nrm], axis=1)
    local = np.array([[length ** 2 * (1 / 12 + accel ** 2 / 180), 4 * accel * length * sag / 180],
                      [4 * accel * length * sag / 180, 16 * sag ** 2 / 180]])
    assert np.allclose(c - c0, r @ local @ r.T, atol=1e-4)


def test_flux_is_conserved_in_float32():
    """A sky of 100 e- and sources away from the edges (the edges are extended with their own values, so
    light near them is not conserved: the frame continues beyond them)."""
    rng = np.random.default_rng(4)
    img = np.full((200, 240), 100.0)
    for x, y, f in zip(rng.uniform(30, 210, 40), rng.uniform(30, 170, 40), rng.uniform(1e3, 1e5, 40)):
        img += _gauss(img.shape, x, y, rng.uniform(0.8, 2.0), f)
    img = img.astype(np.float32)
    out = ip.drift_smear(img, 7.5, 3.2, -0.8, 1.1)
    assert out.dtype == np.float32
    assert np.isclose(out.sum(dtype=np.float64), img.sum(dtype=np.float64), rtol=1e-5)


def test_straight_uniform_drift_is_bit_identical_to_the_box():
    """accel = sagitta = 0 is today's sinc(f . d) transfer, byte for byte (the same call)."""
    rng = np.random.default_rng(1)
    img = rng.uniform(0, 1e3, (96, 130)).astype(np.float32)
    for dx, dy in [(6.0, 0.0), (4.3, -2.7), (0.0, 9.5)]:
        pad = int(np.ceil(0.5 * max(abs(dx), abs(dy)))) + 2
        old = ip.fourier_filter(img, pad, lambda fx, fy, dx=dx, dy=dy: np.sinc(fx * dx + fy * dy))
        assert np.array_equal(ip.drift_smear(img, dx, dy), old)
        assert np.array_equal(ip.drift_smear(img, dx, dy, 0.0, 0.0), old)


def test_the_quadrature_converges_to_the_sinc_and_reversal_is_the_same_trail():
    """The Gauss-Legendre transfer of a straight path equals sinc(f . d) to 1e-12 (so the path reduces to
    the box continuously); (d, accel, sagitta) and (-d, -accel, -sagitta) are one path run backwards."""
    fy = np.fft.fftfreq(64)[:, None]
    fx = np.fft.rfftfreq(64)[None, :]
    transfer, _ = ip.drift_path_transfer(9.3, -4.1, 1e-14, 0.0)
    assert np.max(np.abs(transfer(fx, fy) - np.sinc(fx * 9.3 - fy * 4.1))) < 1e-12
    img = _gauss((101, 101), 50.0, 50.0, 1.5)
    a = ip.drift_smear(img, 5.0, 2.0, 0.7, 0.5)
    b = ip.drift_smear(img, -5.0, -2.0, -0.7, -0.5)
    assert np.max(np.abs(a - b)) < 1e-12 * a.max()


def test_params_default_to_a_straight_drift_and_keep_their_bounds():
    p = DriftParams(dx_px=3.0, dy_px=1.0)
    assert p.accel == 0.0 and p.sagitta_px == 0.0
    with pytest.raises(ValueError):
        DriftParams(dx_px=3.0, accel=1.5)


def test_the_adapter_applies_the_path_in_the_chain():
    s = make_sensor("ml11002", {"width": 128, "height": 128, "x0": 0, "y0": 0, "dark_current_e_per_s": 0.0})
    img = _gauss((128, 128), 40.0, 70.0, 1.5, 1e5).astype(np.float32)
    params = {"dx_px": 6.0, "dy_px": -2.0, "accel": 0.8, "sagitta_px": 0.7}
    det = Detector(s, build_effects({"pointing_drift": params}, s))
    whole = det.field_signal(img, 1.0, 1, det.frame_state(1.0, 1))
    assert np.allclose(whole, np.maximum(ip.drift_smear(img, 6.0, -2.0, 0.8, 0.7), 0), atol=1e-6 * img.max())
    _, cx, cy, _ = _moments(whole.astype(np.float64))
    assert np.isclose(cx, 40.0, atol=0.01) and np.isclose(cy, 70.0, atol=0.01)


def test_words_describe_the_path():
    words = ip._drift_words({"dx_px": 5.0, "dy_px": 0.0, "accel": 0.9, "sagitta_px": 0.6}, None)
    assert "dwelling at its 180 deg end" in words and "bowed by 0.6 px" in words and "counter-clockwise" in words
    words = ip._drift_words({"dx_px": 5.0, "dy_px": 0.0, "accel": 0.05, "sagitta_px": 0.01}, None)
    assert "uniformly" in words and "bowed" not in words


# --- diagnosis -------------------------------------------------------------------------------------------------

def _residuals(tmp_path, effect_toml: str, size: int = 256):
    from helpers import star_field_toml

    from scenes.app.compare import run_compare
    from scenes.app.render import render
    from scenes.scene import load_scene

    base = star_field_toml(size)
    (tmp_path / "model.toml").write_text(base)
    (tmp_path / "truth.toml").write_text(base + effect_toml)
    render(load_scene(str(tmp_path / "truth.toml")), tmp_path / "m.fits", seed=3)
    return run_compare(load_scene(str(tmp_path / "model.toml")), tmp_path / "m.fits")["_residuals"]


@pytest.mark.parametrize("truth,tol", [
    ({"dx_px": 5.0, "dy_px": 2.0, "accel": 1.0, "sagitta_px": 0.0}, {"accel": 0.08, "sagitta_px": 0.1}),
    ({"dx_px": -1.5, "dy_px": 2.6, "accel": 0.0, "sagitta_px": 0.6}, {"accel": 0.15, "sagitta_px": 0.1}),
])
def test_the_diagnosis_recovers_the_path_and_prefers_it_to_jitter(tmp_path, truth, tol):
    """A star field trailed at constant acceleration from rest ((5, 2) px, the unseen-forms case) and one
    along a 3 px chord bowed by 0.6 px at 120 deg: the drift candidate recovers the path (up to the
    reversal (d, accel, sagitta) -> (-d, -accel, -sagitta)) and beats jitter's Gaussian smear in delta BIC."""
    from detector.effects.base import registry

    res = _residuals(tmp_path, "[effects.pointing_drift]\n" + "".join(f"{k} = {v}\n" for k, v in truth.items()))
    fit = registry()["pointing_drift"].signature.fit(res, "pointing_drift")
    jit = registry()["jitter"].signature.fit(res, "jitter")
    p = fit.params
    sign = 1.0 if p["dx_px"] * truth["dx_px"] + p["dy_px"] * truth["dy_px"] > 0 else -1.0
    assert abs(sign * p["dx_px"] - truth["dx_px"]) < 0.15 and abs(sign * p["dy_px"] - truth["dy_px"]) < 0.15, p
    for k, t in tol.items():
        assert abs(sign * p[k] - truth[k]) < t, (k, p)
    assert jit is None or fit.delta_bic < jit.delta_bic - 1000, (fit.delta_bic, jit and jit.delta_bic)
    assert fit.k == 4  # the path, not the straight drift, was the better form


def test_an_accelerating_trail_is_fitted_as_a_path_whatever_its_straight_trail_says(tmp_path):
    """A trail of 6 px that dwells at one end (accel 0.9): its straight box profile may fit worse than the jitter's
    Gaussian smear, yet the path (started from the straight trail, its 4 parameters weighed by the nested test
    against the smear) is fitted and is a drift (a random form's 6.37 px accelerating drift was named jitter when
    the path was tried only after a straight trail told from a smear)."""
    from detector.effects.base import registry

    res = _residuals(tmp_path, "[effects.pointing_drift]\ndx_px = 6.0\ndy_px = 1.0\naccel = 0.9\n", size=192)
    sig = registry()["pointing_drift"].signature
    fit = sig.fit(res, "pointing_drift")
    assert fit is not None and abs(fit.params.get("accel", 0.0)) > 0.3, None if fit is None else fit.params
    assert sig.plausible(fit, res) == ""


def test_the_fitted_path_round_trips_through_the_scene(tmp_path):
    """diagnose --apply writes the candidate's params into [effects.pointing_drift]; the scene read back
    holds the path and renders it: its noiseless frame is the model's smeared along the same path."""
    from astropy.io import fits
    from helpers import star_field_toml

    from scenes.app.compare.apply import apply_candidate
    from scenes.app.render import render
    from scenes.scene import load_scene

    (tmp_path / "model.toml").write_text(star_field_toml(128))
    model = load_scene(str(tmp_path / "model.toml"))
    params = {"dx_px": 4.2, "dy_px": -1.3, "accel": -0.7, "sagitta_px": 0.45}
    apply_candidate(model, {"effect": "pointing_drift", "params": params, "explanation": "a path"},
                    tmp_path / "round2.toml")
    scene = load_scene(str(tmp_path / "round2.toml"))
    assert scene.effects["pointing_drift"] == params
    render(model, tmp_path / "m.fits", seed=2, noiseless=True, progress=False)
    render(scene, tmp_path / "r.fits", seed=2, noiseless=True, progress=False)
    m, r = (fits.getdata(tmp_path / f).astype(np.float64) for f in ("m.fits", "r.fits"))
    # the noiseless frame holds the mean dark charge beside the light: a constant the smear keeps
    want = np.maximum(ip.drift_smear(m, 4.2, -1.3, -0.7, 0.45), 0)
    assert np.max(np.abs(r - want)) < 1e-3 * m.max()
