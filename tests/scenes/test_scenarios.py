"""The thesis scenarios (examples/scenarios): measurement functions against analytic expectations, star
counting against the truth, a smoke test of the table, the photons -> electrons convention, and the
trail-rendering performance changes (coarser trailed-star sampling, batched segments) against the old way."""

import math
import sys
from pathlib import Path

import numpy as np
import pytest

from detector import make_sensor
from optics.design import load_design
from scenes.app.render import prepare
from scenes.image import GAUSS_FWHM, GaussianPSF, gaussian_pixel_fractions
from scenes.image import build as image_build
from scenes.image import psf as image_psf
from scenes.image import signal as image_signal
from scenes.image.build import band, trail_step_px
from scenes.image.signal import Trails, render_trails
from scenes.objects.brightness import solar_photon_irradiance
from scenes.scene import load_scene
from scenes.sky.starflux import star_electron_rate, star_photon_rate

SCENARIOS = Path(__file__).resolve().parents[2] / "examples" / "scenarios"
sys.path.insert(0, str(SCENARIOS))
import run_table

from scenes.app.metrics import (
    analytic_snr,
    detect,
    frame_stats,
    match_regions,
    measure_frame,
    path_photometry,
)


def gaussian_image(shape, sources, fwhm_px):
    """Expected electrons of point sources ``(x, y, flux_e)``: exact pixel integrals of a Gaussian."""
    psf = GaussianPSF(fwhm_px)
    img = np.zeros(shape)
    ys, xs = np.arange(shape[0]), np.arange(shape[1])
    for x, y, f in sources:
        ex, ey = psf.factors(np.array([x]), np.array([y]), (xs - x)[None, :], (ys - y)[None, :])
        img += f * ey[0][:, None] * ex[0][None, :]
    return img


# ------------------------------------------------------------------------------------------ measurements
def test_aperture_snr_agrees_with_the_ccd_equation():
    """Measured SNR of a Gaussian star = N / sqrt(N + n_ap (B + R^2)(1 + n_ap / n_ann)), and its flux
    scatters over realisations by 1 / SNR (Howell 2006 eq. 4.4, the thesis's SNR with the annulus term)."""
    rng = np.random.default_rng(7)
    shape, (x, y), flux_e, fwhm = (61, 61), (30.3, 29.8), 3000.0, 3.0
    bkg_e, read_e, gain, bias = 50.0, 4.0, 1.5, 500.0
    mu = gaussian_image(shape, [(x, y, flux_e)], fwhm) + bkg_e
    r_ap, r_in, r_out = 3.0, 7.5, 12.0
    snr, flux = [], []
    for _ in range(400):
        img = (rng.poisson(mu) + rng.normal(0.0, read_e, shape)) / gain + bias
        p = path_photometry(img, x, y, x, y, r_ap, r_in, r_out, gain)
        snr.append(p["snr"])
        flux.append(p["flux_e"])
    yy, xx = np.mgrid[0:61, 0:61]
    ap = np.hypot(xx - x, yy - y) <= r_ap
    d = np.hypot(xx - x, yy - y)
    n_ap, n_ann = int(ap.sum()), int(((d >= r_in) & (d <= r_out)).sum())
    n_in = float((mu - bkg_e)[ap].sum())  # electrons of the star inside the aperture
    expect = analytic_snr(n_in, n_ap * (1 + n_ap / n_ann), bkg_e, read_e)
    assert p["n_ap"] == n_ap and p["n_ann"] == n_ann
    assert abs(np.median(snr) / expect - 1) < 0.03
    flux = np.array(flux)
    assert abs(flux.mean() - n_in) < 4 * flux.std() / math.sqrt(flux.size)
    assert abs(flux.std() / flux.mean() * expect - 1) < 0.12  # the SNR is the flux's real scatter
    # without the background-estimate term it is the thesis's CCD equation
    assert analytic_snr(n_in, n_ap, bkg_e, read_e) == pytest.approx(n_in / math.sqrt(n_in + n_ap * (bkg_e + 16.0)))


def test_streak_aperture_collects_the_streak():
    """A streak of N e- along a segment: the stadium aperture of radius 1 FWHM holds erf(1.665) of it."""
    psf_fwhm = 2.5
    pts = [(20 + 0.1 * k, 40 + 0.05 * k, 20.0) for k in range(400)]  # 40 x 20 px streak, 8000 e-
    mu = gaussian_image((80, 100), pts, psf_fwhm)
    p = path_photometry(mu + 100.0, 20.05, 40.025, 59.95, 59.975, psf_fwhm, 3 * psf_fwhm, 5 * psf_fwhm, 1.0)
    across = math.erf(GAUSS_FWHM / math.sqrt(2))  # the part within +-r across the track
    assert abs(p["flux_e"] / 8000.0 - across) < 0.01
    assert p["background_adu"] == pytest.approx(100.0)


def test_star_counting_against_truth():
    """Bright stars are all found, faint ones (well below the threshold) not, hot pixels are spurious."""
    rng = np.random.default_rng(3)
    fwhm, bkg_e, read_e = 3.0, 100.0, 5.0
    grid = [(32 + 64 * i, 32 + 64 * j) for i in range(8) for j in range(8)]
    bright = [(x + 0.3, y - 0.2, 4000.0) for x, y in grid[:32]]  # matched-filter S/N ~ 80
    faint = [(x - 0.1, y + 0.4, 15.0) for x, y in grid[32:]]  # ~0.3: invisible
    mu = gaussian_image((512, 512), bright + faint, fwhm) + bkg_e
    img = rng.poisson(mu) + rng.normal(0, read_e, mu.shape)
    hot = [(16 + 64 * i, 48) for i in range(8)]  # between the stars
    for x, y in hot:
        img[y, x] += 3000.0
    labels, n, _ = detect(img, fwhm, 5.0)
    truth = bright + faint
    xs, ys, fl = (np.array([s[k] for s in truth]) for k in range(3))
    m = match_regions(labels, n, xs, ys, xs, ys, fl)
    assert sorted(m["matched"].tolist()) == list(range(32))
    assert m["spurious"] == len(hot)


def test_match_regions_a_broken_trail_is_one_star():
    labels = np.zeros((20, 60), dtype=np.int64)
    labels[10, 5:15] = 1  # two pieces of one trail from x = 5 to x = 40
    labels[10, 25:40] = 2
    labels[3, 50] = 3  # a hot pixel
    labels[16, 30:33] = 4  # a faint star sitting below the trail
    m = match_regions(labels, 4, [5.0, 31.0], [10.0, 16.0], [40.0, 31.0], [10.0, 16.0], [1000.0, 10.0])
    assert m["matched"].tolist() == [0, 1] and m["regions"].tolist() == [1, 2, 4] and m["spurious"] == 1


def test_frame_stats_exact():
    a = np.random.default_rng(1).integers(400, 600, size=(300, 201)).astype(np.uint16)
    s = frame_stats(a, rows_per_block=64)
    assert s["mean"] == pytest.approx(a.mean(dtype=np.float64), rel=1e-12)
    assert s["std"] == pytest.approx(a.std(dtype=np.float64), rel=1e-10)
    assert s["median"] == np.median(a)


def test_smoke_one_scenario_renders_and_gives_a_row():
    """s11 (stars, the streaking object, cosmic rays) on a 512 x 512 window: one table row."""
    path = SCENARIOS / "s11_sidereal_cosmics_imx411.toml"
    row = run_table.table_row(path, None, ["detector.width=512", "detector.height=512"], keep=False)
    assert row["scenario"] == "s11_sidereal_cosmics_imx411" and row["frame"] == "512x512" and row["roi"]
    assert 500 < row["median"] < 560 and abs(row["mean"] - row["median"]) < 20 and row["std_clipped"] > 5
    assert row["stars_truth"] > 10 and 0.7 * row["stars_truth"] <= row["stars_visible"] <= row["stars_truth"]
    assert row["star_snr_median"] > 5
    assert 15 < row["target_snr"] < 35  # 13836 photons x 0.40, 91-pixel streak on a 19.72 mag sky
    md = run_table.markdown([row], 5.0)
    assert md.count("\n") == 3 and run_table.THESIS in md


def test_scenario_files_load_and_cover_the_categories():
    files = run_table.scenario_files()
    assert len(files) == 17
    scenes = {f.stem: load_scene(str(f)) for f in files}
    cats = {run_table.category(n) for n in scenes}
    for c in ("bias", "darks", "empty sky", "stars", "objects", "tracking", "full"):
        assert c in cats
    nav = scenes["navstar71_imx411"]
    assert nav.exposure.tracking == "rate" and nav.sensor().binning == 2 and nav.sensor().roi_shape == (14192, 10640)
    assert nav.objects[0]["photons"] == 13836 and nav.sky.star_mag_limit == 16.0 and "vignetting" in nav.effects


def test_measure_frame_without_sources_has_statistics_only():
    img = np.full((64, 64), 500, dtype=np.uint16)
    row = measure_frame(img, {"FRAMETYP": "bias"}, None)
    assert row["median"] == 500 and row["std"] == 0 and math.isnan(row["target_snr"])


# ------------------------------------------------------------------------- photons -> electrons convention
@pytest.mark.parametrize("preset, lo, hi", [("imx411", 0.39, 0.41), ("ml11002", 0.215, 0.23)])
def test_solar_band_efficiency(preset, lo, hi):
    """Photo-electrons per photon at the aperture for sunlight (5772 K) over the QE table's band, mirrors
    (0.92^2) and QE included: 0.400 (IMX411) and 0.223 (ML11002); the star and object code paths agree."""
    sensor = make_sensor(preset, {})
    design = load_design("art")
    lam, qe = band(sensor)
    eff = solar_photon_irradiance(lam, qe * design.mirror_throughput) / solar_photon_irradiance(lam, np.ones_like(lam))
    assert lo < eff < hi
    star = star_electron_rate(12.0, 5772.0, lam, qe, 1.0, design.mirror_throughput) / star_photon_rate(
        12.0, 5772.0, lam, np.ones_like(lam), 1.0)
    assert star == pytest.approx(eff, rel=1e-9)


@pytest.mark.parametrize("preset", ["imx411", "ml11002"])
def test_photons_object_truth_flux_is_photons_times_efficiency(tmp_path, preset):
    """A tracked 'photons' object inside the frame: TRUTH flux_e = photons x <QE x mirrors>_sun."""
    text = f"""
[detector]
preset = "{preset}"
width = 256
height = 256
[exposure]
time_s = 2.0
tracking = "rate"
rate_ra_deg_s = 0.008558
rate_dec_deg_s = -0.005486
[[objects]]
ra_deg = 120.951
dec_deg = -29.2502
rate_ra_deg_s = 0.008558
rate_dec_deg_s = -0.005486
photons = 100000
"""
    p = tmp_path / "s.toml"
    p.write_text(text)
    setup = prepare(load_scene(str(p)))
    sensor = make_sensor(preset, {})
    lam, qe = band(sensor)
    eff = solar_photon_irradiance(lam, qe * 0.92 ** 2) / solar_photon_irradiance(lam, np.ones_like(lam))
    assert setup.truth["flux_e"][0] == pytest.approx(1e5 * eff, rel=1e-6)


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
