"""Image formation: pixel-integrated PSFs, stars, streaks, rolling shutter, tracking, TRUTH (physics, not snapshots)."""

import math

import numpy as np
import pytest
from astropy.io import fits
from astropy.wcs import WCS
from helpers import isolated_stars

from detector import DetectorError
from scenes.app.render import prepare, render
from scenes.image import (
    GAUSS_FWHM,
    SIDEREAL_RATE_DEG_S,
    GaussianPSF,
    MoffatPSF,
    Samples,
    render_samples,
)
from scenes.image.psf import TAIL_E, TAIL_REL_MAX, TAIL_SB_E
from scenes.image.signal import Trails, render_trails
from scenes.scene import load_scene

BASE = """
[telescope]
design = "art"
pixel_scale_arcsec = 1.0
[detector]
preset = "{preset}"
width = {w}
height = {h}
{detector_extra}
[pointing]
ra_deg = 120.0
dec_deg = -30.0
epoch = "2023-02-01T22:00:00"
[exposure]
time_s = {t}
{exposure_extra}
[sky]
background_mag_arcsec2 = 21.0
stars = {stars}
catalog = "stars.csv"
[psf]
fwhm_arcsec = 2.0
{psf_extra}
"""


def scene_file(tmp_path, *, preset="ml11002", w=256, h=256, t=1.0, stars=False, detector_extra="",
               exposure_extra="", psf_extra="", objects=(), star_rows=None):
    text = BASE.format(preset=preset, w=w, h=h, t=t, stars=str(stars).lower(), detector_extra=detector_extra,
                       exposure_extra=exposure_extra, psf_extra=psf_extra)
    for obj in objects:
        text += "[[objects]]\n" + "".join(f"{k} = {v!r}\n".replace("'", '"') for k, v in obj.items())
    (tmp_path / "stars.csv").write_text("ra,dec,mag\n" + "".join(f"{r},{d},{m}\n" for r, d, m in (star_rows or [])))
    p = tmp_path / "scene.toml"
    p.write_text(text)
    return str(p)


def sources_image(path, overrides=()):
    """Expected photo-electrons of the sources only (background removed), the truth and the setup."""
    sc = load_scene(path, list(overrides))
    setup = prepare(sc)
    sig = setup.signal_e
    img = sig.image(sc.sensor().shape).astype(np.float64) - sig.background_e
    return img, setup.truth, setup


def moments(img, weights_floor=0.0):
    yy, xx = np.indices(img.shape)
    m = np.where(img > weights_floor, img, 0.0)
    s = m.sum()
    cx, cy = (xx * m).sum() / s, (yy * m).sum() / s
    cxx = ((xx - cx) ** 2 * m).sum() / s
    cyy = ((yy - cy) ** 2 * m).sum() / s
    cxy = ((xx - cx) * (yy - cy) * m).sum() / s
    return s, cx, cy, cxx, cyy, cxy


def along_track_variance(img, direction):
    _, _, _, cxx, cyy, cxy = moments(img)
    ux, uy = direction / np.linalg.norm(direction)
    return ux * ux * cxx + uy * uy * cyy + 2 * ux * uy * cxy


# --------------------------------------------------------------------------- pixel-integrated PSFs
def _brute(psf_profile, x, y, offs, m):
    """Midpoint supersampling, m x m points per pixel, of a 2-D profile over the pixels ``offs`` x ``offs``."""
    sub = (np.arange(m) + 0.5) / m - 0.5
    fine = (offs[:, None] + sub[None, :]).ravel()
    img = psf_profile(fine[None, :] - x, fine[:, None] - y) / (m * m)
    n = offs.size
    return img.reshape(n, m, n, m).sum(axis=(1, 3))


def _richardson(profile, x, y, offs, m):
    """Brute force with Richardson extrapolation (midpoint error is O(h^2): 4/3 fine - 1/3 coarse)."""
    return (4 * _brute(profile, x, y, offs, 2 * m) - _brute(profile, x, y, offs, m)) / 3


@pytest.mark.parametrize("fwhm", [0.7, 1.5, 3.0])
def test_gaussian_pixel_integral_is_exact(fwhm):
    psf = GaussianPSF(fwhm)
    x, y = 0.37, -0.21
    offs = np.arange(-8, 9, dtype=float)
    exact = psf(np.array([x]), np.array([y]), (offs - x)[None, :], (offs - y)[None, :])[0]
    s = fwhm / GAUSS_FWHM

    def prof(dx, dy):
        return np.exp(-(dx * dx + dy * dy) / (2 * s * s)) / (2 * np.pi * s * s)

    brute = _richardson(prof, x, y, offs, 128)
    assert np.abs(exact - brute).max() < 2e-7
    assert abs(exact.sum() - 1) < 1e-9
    # a centre-sampled PSF would be wrong by far more for an undersampled star: the integral matters
    centre = prof(offs[None, :] - x, offs[:, None] - y)
    assert np.abs(centre - exact).max() > (2e-3 if fwhm > 2 else 1e-2)


@pytest.mark.parametrize("fwhm, beta", [(0.8, 4.765), (2.5, 4.765), (1.5, 2.5)])
def test_moffat_pixel_integral_error_bound(fwhm, beta):
    psf = MoffatPSF(fwhm, beta)
    x, y = -0.31, 0.44
    offs = np.arange(-6, 7, dtype=float)
    gl = psf(np.array([x]), np.array([y]), (offs - x)[None, :], (offs - y)[None, :])[0]
    brute = _richardson(lambda dx, dy: psf.profile(dx * dx + dy * dy), x, y, offs, 256)
    assert np.abs(gl - brute).max() < 1e-6  # the documented bound (relative to the source's flux)
    # normalisation: the stamp holds all but the analytic tail beyond its half-width (square > circle)
    tail_circle = (1 + 6.5 ** 2 / psf.alpha_px ** 2) ** (1 - beta)
    assert 0 <= 1 - gl.sum() <= tail_circle


def test_moffat_with_jitter_matches_a_numerical_convolution():
    from scipy.signal import fftconvolve

    fwhm, beta, jit = 2.0, 3.0, 0.6
    psf = MoffatPSF(fwhm, beta, jitter_px=jit)
    offs = np.arange(-10, 11, dtype=float)
    got = psf(np.array([0.2]), np.array([-0.1]), (offs - 0.2)[None, :], (offs + 0.1)[None, :])[0]

    def reference(m):  # Moffat on a fine grid (1/m pixel, 6 pixels of margin) convolved with the jitter by FFT
        big = np.arange(-16, 17, dtype=float)
        sub = (np.arange(m) + 0.5) / m - 0.5
        fine = (big[:, None] + sub[None, :]).ravel()
        mof = MoffatPSF(fwhm, beta).profile((fine[None, :] - 0.2) ** 2 + (fine[:, None] + 0.1) ** 2) / m ** 2
        k = np.arange(-6 * m, 6 * m + 1) / m
        g = np.exp(-(k[None, :] ** 2 + k[:, None] ** 2) / (2 * jit ** 2))
        conv = fftconvolve(mof, g / g.sum(), mode="same").reshape(big.size, m, big.size, m).sum(axis=(1, 3))
        return conv[6:-6, 6:-6]

    conv = (4 * reference(32) - reference(16)) / 3  # Richardson: midpoint errors are O(h^2)
    assert np.abs(got - conv).max() < 1e-5 * got.max()


@pytest.mark.parametrize("psf", [GaussianPSF(2.0), MoffatPSF(2.0), MoffatPSF(2.0, beta=2.2), MoffatPSF(2.5, beta=1.8)])
def test_stamp_radius_keeps_the_lost_tail_below_the_bound(psf):
    for flux in (1e2, 1e5, 1e8):
        w = int(psf.radius_px(np.array([flux]))[0])
        assert w >= 4 * psf.fwhm_px
        offs = np.arange(-w, w + 1, dtype=float)
        frac = psf(np.zeros(1), np.zeros(1), offs[None, :], offs[None, :])[0]
        lost = 1 - frac.sum()
        quad = 1e-6 if isinstance(psf, MoffatPSF) else 1e-12  # the cubature's own (documented) error
        assert lost <= TAIL_REL_MAX
        if abs(lost) <= max(TAIL_E / flux, 1e-9) * 1.001 + quad:
            continue
        # a wide-winged Moffat's faint halo: left out only where its surface brightness at the edge (the
        # profile at the stamp's half-width) is below TAIL_SB_E electrons per pixel
        assert isinstance(psf, MoffatPSF) and (flux * psf.profile((w - 1.0) ** 2) <= TAIL_SB_E or w == 512)


def test_a_wide_winged_moffat_stamp_stays_small():
    """beta 1.8: keeping 0.5 e- of a 1e6 e- star took the largest stamp (512 px, a million pixels); its halo at
    0.01 e- per pixel is left out (at most 1e-3 of the flux): a stamp of 75 alpha, on the ladder 88."""
    psf = MoffatPSF(2.5, beta=1.8)
    w = int(psf.radius_px(np.array([1e6]))[0])
    assert w <= 2 * 80 * psf.alpha_px < 512
    assert (1 + w ** 2 / psf.alpha_px ** 2) ** (1 - psf.beta) <= TAIL_REL_MAX


@pytest.mark.parametrize("fwhm, beta, jitter", [(2.5, 1.8, 0.0), (1.2, 4.765, 0.0), (3.0, 2.5, 0.7)])
def test_moffat_far_rule_keeps_the_full_order_precision(fwhm, beta, jitter):
    """Beyond the core the pixel integrals take 2 Gauss-Legendre nodes per axis (MoffatPSF.far_rule): on a stamp
    reaching well beyond it they agree with the full order everywhere to the rule's tolerance of the flux."""
    psf = MoffatPSF(fwhm, beta, jitter_px=jitter)
    k, n_far = psf.far_rule
    assert 0 < k <= 64 and n_far == 2 < psf.order
    offs = np.arange(-(k + 20), k + 21, dtype=float)
    x, y = np.array([0.3]), np.array([-0.2])
    got = psf(x, y, (offs - 0.3)[None, :], (offs + 0.2)[None, :])[0]
    full = psf._stamp(x, y, (offs - 0.3)[None, :], (offs + 0.2)[None, :], psf.jitter_nodes)[0]
    assert np.abs(got - full).max() < 1e-7


def test_tiles_are_independent_and_add_up_to_the_whole_frame():
    rng = np.random.default_rng(3)
    n = 400
    y = np.sort(rng.uniform(-5, 250, n))
    s = Samples(rng.uniform(-5, 130, n), y, rng.uniform(1, 1e4, n), np.full(n, -np.inf), np.full(n, np.inf),
                rng.choice([6, 9, 14], n))
    psf = GaussianPSF(2.2)
    whole = render_samples(s, psf, 0, 240, 0, 128)
    bands = np.vstack([render_samples(s, psf, r, min(r + 37, 240), 0, 128) for r in range(0, 240, 37)])
    np.testing.assert_allclose(bands, whole, rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize("row_time", [0.0, 2e-3])
def test_trail_segments_as_matrix_products_equal_point_stamps(row_time):
    """Separable PSF: segments rendered as EY^T diag(e f) EX equal the same samples drawn one by one, per band."""
    t = (np.arange(2000) + 0.5) * 5e-4  # 1 s of a path at 200 px/s (0.1 px per sample), two sources
    parts = []
    for k, (x0, y0, vx, vy) in enumerate([(20.0, 30.0, 180.0, 85.0), (120.0, 200.0, -60.0, -190.0)]):
        x, y = x0 + vx * t, y0 + vy * t
        e = np.full(t.size, 3.0)
        parts.append(Trails.from_samples(x, y, e, t - 2.5e-4, t + 2.5e-4, np.full(t.size, 9), t // 0.05 + 100 * k))
    tr = Trails.concat(parts)
    pts = tr.as_samples()
    psf = GaussianPSF(2.4)
    ref = render_samples(pts, psf, 0, 240, 0, 256, row_time, 0.6)
    got = np.zeros((240, 256))
    for r in range(0, 240, 50):
        band = np.zeros((min(r + 50, 240) - r, 256))
        render_trails(tr, psf, band, r, 0, row_time, 0.6)
        got[r:r + band.shape[0]] = band
    np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-10)
    if row_time == 0:  # global shutter: the builder only makes samples inside [0, T]; all of them count
        assert abs(ref.sum() / (2 * 2000 * 3.0) - 1) < 1e-9


# ------------------------------------------------------------------------------------ stars in frames
@pytest.mark.parametrize("overrides", [
    ["detector.preset='imx411'"],
    ["detector.preset='imx411'", "detector.binning=2"],
    ["psf.model='moffat'"],
])
def test_star_centroids_sit_on_the_wcs_and_conserve_energy(tmp_path, overrides):
    """Noiseless frame: isolated stars' centroids vs the file's WCS (< 0.03 pixel), sums vs flux_e (< 1 %)."""
    sc = load_scene("default", ["detector.width=512", "detector.height=512", "effects={}", "sky.stars=true",
                                "sky.star_mag_limit=15", "psf.fwhm_arcsec=3.0", "detector.preset='ml11002'"]
                    + overrides)
    render(sc, tmp_path / "f.fits", seed=1, noiseless=True, progress=False)
    with fits.open(tmp_path / "f.fits") as hd:
        hdr = hd[0].header
        t = hd["TRUTH"].data
        assert hd["TRUTH"].header["NSTARS"] == len(t) == hdr["NSTARS"]
    xw, yw = WCS(hdr).all_world2pix(t["ra_deg"], t["dec_deg"], 0)
    assert np.allclose(xw, t["x"], atol=1e-6) and np.allclose(yw, t["y"], atol=1e-6)
    st = isolated_stars(tmp_path / "f.fits", 3.0 / hdr["PIXSCALE"])
    assert len(st["cx"]) >= 5
    assert np.abs(st["cx"] - st["x"]).max() < 0.03 and np.abs(st["cy"] - st["y"]).max() < 0.03
    assert np.abs(st["sum"] / st["flux"] - 1).max() < 0.01


def test_sidereal_round_rate_trailed_and_none_trails_west(tmp_path):
    """Sidereal: round stars; 'rate': trails of rate x T / scale, opposite to the tracking; 'none': sidereal drift."""
    stars = [(120.0, -30.0, 9.0), (120.03, -29.97, 9.5)]
    p = scene_file(tmp_path, stars=True, t=2.0, star_rows=stars)
    s2 = (2.0 / GAUSS_FWHM) ** 2 + 1 / 12  # pixel-integrated Gaussian variance [px^2]
    img, truth, _ = sources_image(p)
    win = img[100:156, 100:156]  # the star at the pointing centre (127.5, 127.5)
    _, _, _, cxx, cyy, cxy = moments(win)
    assert abs(cxx / s2 - 1) < 1e-3 and abs(cyy / s2 - 1) < 1e-3 and abs(cxy) < 1e-4
    # rate tracking at 18"/s east: stars trail 36 pixels towards +x (west, east being -x)
    img, truth, _ = sources_image(p, ["exposure.tracking='rate'", "exposure.rate_ra_deg_s=0.005"])
    win = img[100:156, 70:200]
    length = math.sqrt(12 * (along_track_variance(win, np.array([1.0, 0.0])) - s2))
    assert abs(length / 36.0 - 1) < 0.01
    row = truth[np.argmin(np.hypot(truth["x0"] - 127.5, truth["y0"] - 127.5))]
    assert abs(row["x1"] - row["x0"] - 36.0) < 0.05 and abs(row["y1"] - row["y0"]) < 0.05
    # drive off: drift at 15.04"/s cos(dec), westwards (+x)
    img, truth, _ = sources_image(p, ["exposure.tracking='none'"])
    expect = SIDEREAL_RATE_DEG_S * 3600 * math.cos(math.radians(30.0)) * 2.0
    row = truth[np.argmin(np.hypot(truth["x0"] - 127.5, truth["y0"] - 127.5))]
    assert abs((row["x1"] - row["x0"]) / expect - 1) < 1e-3 and abs(row["y1"] - row["y0"]) < 0.01 * expect
    win = img[100:156, 100:190]
    length = math.sqrt(12 * (along_track_variance(win, np.array([1.0, 0.0])) - s2))
    assert abs(length / expect - 1) < 0.01


def test_rate_tracking_on_an_object_makes_it_round_and_the_stars_trail(tmp_path):
    obj = {"ra_deg": 120.0, "dec_deg": -30.0, "rate_ra_deg_s": 0.003, "rate_dec_deg_s": 0.004, "photons": 1e6}
    p = scene_file(tmp_path, stars=True, star_rows=[(120.02, -30.01, 10.0)], objects=[obj],
                   exposure_extra="tracking = 'rate'\nrate_ra_deg_s = 0.003\nrate_dec_deg_s = 0.004")
    img, truth, _ = sources_image(p)
    s2 = (2.0 / GAUSS_FWHM) ** 2 + 1 / 12
    o = truth[truth["kind"] == b"object"][0]
    assert abs(o["x1"] - o["x0"]) < 1e-3 and abs(o["y1"] - o["y0"]) < 1e-3
    _, _, _, cxx, cyy, _ = moments(img[108:148, 108:148])
    assert abs(cxx / s2 - 1) < 2e-3 and abs(cyy / s2 - 1) < 2e-3
    star = truth[truth["kind"] != b"object"][0]
    assert abs(math.hypot(star["x1"] - star["x0"], star["y1"] - star["y0"]) - 18.0) < 0.05  # 5"/s x 1 s / 1"


def test_field_dependent_psf_hook(tmp_path):
    """Any object with __call__(x, y, dx, dy) and radius_px(flux) replaces the scene's PSF (e.g. optics PSFs)."""

    class FieldPSF:  # a Gaussian whose width grows across the field, as an optics PSF cube would supply
        fwhm_px = 2.0

        def sigma(self, x):
            return 0.6 + np.asarray(x) / 200.0

        def __call__(self, x, y, dx, dy):
            from scenes.image import gaussian_pixel_fractions

            s = self.sigma(x)
            ex = np.array([gaussian_pixel_fractions(d[None, :], si)[0] for d, si in zip(dx, s)])
            ey = np.array([gaussian_pixel_fractions(d[None, :], si)[0] for d, si in zip(dy, s)])
            return ey[:, :, None] * ex[:, None, :]

        def radius_px(self, flux_e):
            return np.full(np.shape(flux_e), 12, dtype=np.int64)

        def describe(self):
            return {"model": "field-gaussian", "fwhm_px": self.fwhm_px}

    # two stars at x ~ 30 and x ~ 220 (1"/pixel, east = -x)
    dra = 97.5 / 3600 / math.cos(math.radians(30.0))
    p = scene_file(tmp_path, stars=True, star_rows=[(120.0 + dra, -30.0, 10.0), (120.0 - dra, -30.0, 10.0)])
    sc = load_scene(p)
    setup = prepare(sc, psf=FieldPSF())
    img = setup.signal_e.image(sc.sensor().shape) - setup.signal_e.background_e
    assert setup.source_cards["PSFMODEL"][0] == "field-gaussian"
    for row in setup.truth:
        ix, iy = round(row["x"]), round(row["y"])
        _, _, _, cxx, cyy, _ = moments(img[iy - 12:iy + 13, ix - 12:ix + 13].astype(float))
        s = float(FieldPSF().sigma(row["x"]))
        assert abs(cxx / (s * s + 1 / 12) - 1) < 1e-3 and abs(cyy / (s * s + 1 / 12) - 1) < 1e-3


# ------------------------------------------------------------------------------------------- streaks
@pytest.mark.parametrize("psf_extra", ["", "model = 'moffat'"])
def test_streak_energy_and_length(tmp_path, psf_extra):
    """Global shutter: the streak holds rate x T electrons and is rate x T / scale long."""
    obj = {"ra_deg": 120.01, "dec_deg": -30.005, "rate_ra_deg_s": -0.006, "rate_dec_deg_s": 0.008, "photons": 2e6}
    p = scene_file(tmp_path, objects=[obj], psf_extra=psf_extra)
    img, truth, setup = sources_image(p)
    o = truth[0]
    assert o["kind"] == b"object" and o["name"] == b"objects[0]"
    assert abs(img.sum() / o["flux_e"] - 1) < 1e-3
    expect = math.hypot(0.006, 0.008) * 3600 * 1.0  # 36 pixels at 1"/pixel over 1 s
    assert abs(math.hypot(o["x1"] - o["x0"], o["y1"] - o["y0"]) / expect - 1) < 1e-3
    if not psf_extra:  # the second moment along the track: L^2/12 + sigma^2 + 1/12
        s2 = (2.0 / GAUSS_FWHM) ** 2 + 1 / 12
        length = math.sqrt(12 * (along_track_variance(img, np.array([o["x1"] - o["x0"], o["y1"] - o["y0"]])) - s2))
        assert abs(length / expect - 1) < 0.01
    # every sample stands for <= 0.25 pixel of motion
    assert setup.source_cards["NSAMPLES"][0] >= expect / 0.25
    # moving west (rate_ra < 0) and north: east is -x and north +y for roll 0
    assert o["x1"] > o["x0"] and o["y1"] > o["y0"]


def test_photons_object_gets_the_solar_band_efficiency(tmp_path):
    """photons at the aperture -> electrons: x <QE x mirrors> weighted by a solar photon spectrum."""
    from optics.design import load_design
    from scenes.objects import solar_spectral_irradiance

    obj = {"ra_deg": 120.0, "dec_deg": -30.0, "photons": 1e6}
    p = scene_file(tmp_path, objects=[obj])
    img, truth, setup = sources_image(p)
    lam = np.linspace(350, 1050, 1401)
    n_ph = solar_spectral_irradiance(lam) * lam  # photon spectrum (arbitrary units)
    eff = np.trapezoid(n_ph * setup.detector.sensor.qe_at(lam), lam) / np.trapezoid(n_ph, lam)
    eff *= load_design("art").mirror_throughput
    assert abs(truth[0]["flux_e"] / (1e6 * eff) - 1) < 1e-3
    assert abs(img.sum() / truth[0]["flux_e"] - 1) < 1e-3


def test_rolling_shutter_shears_a_streak_moving_along_x(tmp_path):
    """Row r integrates [r tau, r tau + T]: an x-moving source's row centroid shifts by -v tau per row."""
    v, tau = 50.0, 1e-3  # px/s (east = -x at 1"/pixel), s per row
    obj = {"ra_deg": 120.0, "dec_deg": -30.0, "rate_ra_deg_s": v / 3600, "photons": 1e6}
    p = scene_file(tmp_path, preset="imx411", detector_extra=f"line_time_s = {tau}", objects=[obj])
    img, truth, _ = sources_image(p)
    o = truth[0]
    rows = np.arange(round(o["y"]) - 3, round(o["y"]) + 4)
    xs = np.arange(img.shape[1])
    cx = [(img[r] * xs).sum() / img[r].sum() for r in rows]
    slope = np.polyfit(rows, cx, 1)[0]
    assert abs(slope / (-v * tau) - 1) < 0.01
    # row r: x_c = x_start - v (r tau + T/2)
    assert abs(cx[3] - (127.5 - v * (rows[3] * tau + 0.5))) < 0.02
    assert abs(img.sum() / o["flux_e"] - 1) < 1e-3
    g_img, g_truth, _ = sources_image(p, ["detector.shutter='global'"])
    assert abs(o["flux_e"] / g_truth[0]["flux_e"] - 1) < 1e-4  # no stretch along x
    gx = [(g_img[r] * xs).sum() / g_img[r].sum() for r in rows]
    assert abs(np.polyfit(rows, gx, 1)[0]) < 1e-4  # float32 rounding only


def test_rolling_shutter_stretches_a_streak_moving_along_y(tmp_path):
    """Moving with the read-out (v_y > 0): recorded for T / (1 - v tau), length and flux x 1 / (1 - v tau)."""
    v, tau, t = 100.0, 2e-3, 0.5
    obj = {"ra_deg": 120.0, "dec_deg": -30.0, "rate_dec_deg_s": v / 3600, "photons": 1e6}
    p = scene_file(tmp_path, preset="imx411", t=t, detector_extra=f"line_time_s = {tau}", objects=[obj])
    img, truth, _ = sources_image(p)
    _, g_truth, _ = sources_image(p, ["detector.shutter='global'"])
    o, g = truth[0], g_truth[0]
    k = 1 / (1 - v * tau)
    assert abs(o["flux_e"] / g["flux_e"] / k - 1) < 2e-3
    assert abs(img.sum() / o["flux_e"] - 1) < 1e-3
    assert abs((o["y1"] - o["y0"]) / (v * t * k) - 1) < 5e-3
    assert abs(o["y0"] - (127.5 + v * 127.5 * tau * k)) < 0.3  # recorded from t_a = y_s tau / (1 - v tau)
    s2 = (2.0 / GAUSS_FWHM) ** 2 + 1 / 12
    var_y = along_track_variance(img, np.array([0.0, 1.0]))
    assert abs(var_y / (k ** 2 * ((v * t) ** 2 / 12 + s2)) - 1) < 0.01


def test_static_star_is_the_same_under_rolling_and_global_shutter(tmp_path):
    p = scene_file(tmp_path, preset="imx411", stars=True, star_rows=[(120.0, -30.0, 10.0)],
                   detector_extra="line_time_s = 0.01")
    a, ta, _ = sources_image(p)
    b, tb, _ = sources_image(p, ["detector.shutter='global'"])
    np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9)
    assert ta[0]["flux_e"] == tb[0]["flux_e"]


# ------------------------------------------------------------------------------------ errors, seeds
def test_object_outside_the_field_names_its_index(tmp_path):
    inside = {"ra_deg": 120.0, "dec_deg": -30.0, "photons": 1e5}
    outside = {"ra_deg": 125.0, "dec_deg": -30.0, "rate_ra_deg_s": 0.001, "photons": 1e5}
    p = scene_file(tmp_path, objects=[inside, outside])
    with pytest.raises(DetectorError) as e:
        prepare(load_scene(p))
    assert "objects[1]" in str(e.value) and "outside the field" in str(e.value) and "scene.toml" in str(e.value)


@pytest.mark.parametrize("override, key", [
    ("exposure.rate_ra_deg_s=0.01", "exposure.rate_ra_deg_s"),
    ("exposure.tracking='drift'", "exposure.tracking"),
    ("sky.star_mag_limit=26", "sky.star_mag_limit"),
    ("psf.model='airy'", "psf.model"),
    ("psf.beta=1.0", "psf.beta"),
    ("psf.fwhm_arcsec=0", "psf.fwhm_arcsec"),
    ("sky.catalog='nosuch.csv'", "sky.catalog"),
    ("objects=[{ra_deg=1.0, dec_deg=2.0, photons=1.0, colour=3}]", "objects[0].colour"),
    ("objects=[{ra_deg=1.0, dec_deg=2.0}]", "objects[0]"),
    ("observer={lat_deg=100.0, lon_deg=0.0}", "observer.lat_deg"),
])
def test_scene_errors_name_the_key(tmp_path, override, key):
    p = scene_file(tmp_path, stars=True)
    with pytest.raises(DetectorError) as e:
        load_scene(p, [override])
    assert key in str(e.value) and "expected" in str(e.value) and "scene.toml" in str(e.value)


def test_catalog_path_is_relative_to_the_scene_file(tmp_path, monkeypatch):
    p = scene_file(tmp_path, stars=True, star_rows=[(120.0, -30.0, 11.0)])
    monkeypatch.chdir("/")
    sc = load_scene(p)
    assert sc.sky.catalog == str(tmp_path / "stars.csv")
    img, truth, _ = sources_image(p)
    assert len(truth) == 1 and truth[0]["kind"] == b"star" and abs(img.sum() / truth[0]["flux_e"] - 1) < 1e-3


def test_same_seed_same_bytes_with_stars_and_streaks(tmp_path):
    obj = {"ra_deg": 120.0, "dec_deg": -30.0, "rate_ra_deg_s": 0.004, "rate_dec_deg_s": -0.002, "mag": 9.0}
    p = scene_file(tmp_path, preset="imx411", stars=True, w=480, h=480, star_rows=[(120.01, -30.01, 9.0)],
                   objects=[obj])
    sc = load_scene(p, ["sky.catalog='builtin'", "sky.star_mag_limit=16"])
    for name, seed, workers in (("a", 5, 1), ("b", 5, 2), ("c", 6, 2)):
        render(sc, tmp_path / f"{name}.fits", seed=seed, progress=False, workers=workers)
    a, b, c = (fits.getdata(tmp_path / f"{n}.fits") for n in "abc")
    assert a.tobytes() == b.tobytes() and a.tobytes() != c.tobytes()
    ta, tc = fits.getdata(tmp_path / "a.fits", "TRUTH"), fits.getdata(tmp_path / "c.fits", "TRUTH")
    assert len(ta) == len(tc) > 10 and np.array_equal(ta["ra_deg"], tc["ra_deg"])  # the sky does not change
    sc2 = load_scene(p, ["sky.catalog='builtin'", "sky.star_mag_limit=16", "sky.star_seed=1"])
    render(sc2, tmp_path / "d.fits", seed=5, progress=False)
    td = fits.getdata(tmp_path / "d.fits", "TRUTH")
    assert not np.array_equal(np.sort(td["ra_deg"]), np.sort(ta["ra_deg"]))


@pytest.mark.parametrize("name, kinds", [("stars_imx411", {"synthetic"}), ("streak_ml11002", {"object", "synthetic"})])
def test_example_scenes_render(tmp_path, name, kinds):
    from pathlib import Path

    path = Path(__file__).parents[2] / "examples" / "scenes" / f"{name}.toml"
    sc = load_scene(str(path), ["detector.width=512", "detector.height=512"])
    render(sc, tmp_path / "e.fits", seed=1, noiseless=True, progress=False)
    t = fits.getdata(tmp_path / "e.fits", "TRUTH")
    assert kinds <= {k.strip() for k in t["kind"]}
    assert np.all(t["flux_e"] >= 0) and np.all(np.isfinite(t["x"]))
