"""The thesis scenarios (examples/scenarios): measurement functions against analytic expectations, star
counting against the truth, a smoke test of the table, the photons -> electrons convention, and the
trail-rendering performance changes (coarser trailed-star sampling, batched segments) against the old way."""

import numpy as np
import pytest

from scenes.image import GAUSS_FWHM, GaussianPSF, gaussian_pixel_fractions
from scenes.image import build as image_build
from scenes.image import psf as image_psf
from scenes.image import signal as image_signal
from scenes.image.build import trail_step_px
from scenes.image.signal import Trails, render_trails
from scenes.render import prepare
from scenes.scene import load_scene


# -------------------------------------------------------------------- trail rendering (performance changes)
def test_trail_step_follows_the_psf_width():
    s = 3.09 / GAUSS_FWHM
    assert trail_step_px(GaussianPSF(3.09)) == pytest.approx(0.5 * s)
    assert trail_step_px(GaussianPSF(0.5)) == image_build.STEP_PX  # a sharp PSF keeps 0.25 pixel

    class Plain:  # a user PSF without describe(): the old spacing
        def radius_px(self, f):
            return np.full(np.shape(f), 5)

    assert trail_step_px(Plain()) == image_build.STEP_PX


STAR_SCENE = """
[telescope]
pixel_scale_arcsec = 1.0
[detector]
preset = "{preset}"
width = 320
height = 320
[pointing]
ra_deg = 120.0
dec_deg = -30.0
[exposure]
time_s = 2.0
tracking = "rate"
rate_ra_deg_s = 0.008558
rate_dec_deg_s = -0.005486
[sky]
background_mag_arcsec2 = 21.0
stars = true
catalog = "stars.csv"
[psf]
fwhm_arcsec = 3.0
"""


@pytest.mark.parametrize("preset", ["ml11002", "imx411"])
def test_trailed_stars_at_half_sigma_spacing_match_quarter_pixel(tmp_path, preset, monkeypatch):
    """Trailed stars sampled every sigma/2 instead of 0.25 pixel: same electrons, same image to 6e-3 of the
    peak (the midpoint rule at the ends of the path and of each row's window: 0.1 % global, 0.4 % rolling
    shutter measured), and along the middle of a global-shutter trail the same to 1e-6."""
    (tmp_path / "stars.csv").write_text("ra,dec,mag\n120.0,-30.0,9.0\n120.01,-29.99,11.0\n")
    p = tmp_path / "scene.toml"
    p.write_text(STAR_SCENE.format(preset=preset))
    out = {}
    for k in (0.0, image_build.STAR_STEP_SIGMA):
        monkeypatch.setattr(image_build, "STAR_STEP_SIGMA", k)
        setup = prepare(load_scene(str(p)))
        img = setup.signal_e.image(setup.detector.sensor.shape).astype(np.float64) - setup.signal_e.background_e
        out[k] = (img, setup.signal_e.n_samples, setup.truth)
    (a, na, truth), (b, nb, _) = out[0.0], out[image_build.STAR_STEP_SIGMA]
    assert nb < 0.6 * na
    assert abs(b.sum() / a.sum() - 1) < 1e-5
    assert np.abs(a - b).max() < 6e-3 * a.max()
    if preset == "ml11002":  # global shutter: away from the ends the sampled chain is the path integral
        t = truth[np.argmax(truth["flux_e"])]
        yy, xx = np.mgrid[0:320, 0:320]
        u = np.array([t["x1"] - t["x0"], t["y1"] - t["y0"]])
        L = float(np.hypot(*u))
        s = ((xx - t["x0"]) * u[0] + (yy - t["y0"]) * u[1]) / L
        mid = (s > 8) & (s < L - 8) & (np.abs((xx - t["x0"]) * u[1] - (yy - t["y0"]) * u[0]) / L < 6)
        assert np.abs(a - b)[mid].max() < 1e-6 * a.max()


def test_trails_rendered_in_chunks_and_bands_are_identical(monkeypatch):
    rng = np.random.default_rng(1)
    parts = []
    for k in range(30):
        t = np.arange(0, 0.6, 5e-4)
        x, y = rng.uniform(0, 200) + 80 * t, rng.uniform(0, 300) + 50 * t
        parts.append(Trails.from_samples(x, y, np.full(t.size, 3.0), t - 2.5e-4, t + 2.5e-4,
                                         np.full(t.size, 9 if k % 2 else 6), t // 0.05 + 100 * k))
    tr, psf = Trails.concat(parts), GaussianPSF(2.5)

    def frame(chunk, rows):
        monkeypatch.setattr(image_signal, "TRAIL_CHUNK_ELEMENTS", chunk)
        out = np.zeros((360, 300))
        for r in range(0, 360, rows):
            band_ = np.zeros((min(rows, 360 - r), 300))
            render_trails(tr, psf, band_, r, 0, 1e-3, 0.6)
            out[r:r + rows] = band_
        return out

    ref = frame(1 << 30, 360)
    for chunk, rows in ((200, 64), (1 << 19, 7), (5000, 240)):
        assert np.abs(frame(chunk, rows) - ref).max() <= 1e-12 * ref.max()


def test_pixel_fractions_take_the_edge_path_far_from_the_origin(monkeypatch):
    """Stamp offsets ``column - x`` at x ~ 7000 are consecutive only to ~1e-12: still one CDF per edge."""
    x = np.array([7000.3, 13001.77, 3.2])
    cols = np.rint(x).astype(np.int64)[:, None] + np.arange(-13, 14)
    d = cols - x[:, None]
    slow = image_psf.normal_interval_mass((d - 0.5) / 1.3, (d + 0.5) / 1.3)

    def refuse(*a):
        raise AssertionError("per-pixel path taken")

    monkeypatch.setattr(image_psf, "normal_interval_mass", refuse)
    fast = gaussian_pixel_fractions(d, 1.3)
    assert np.abs(fast - slow).max() < 1e-12
