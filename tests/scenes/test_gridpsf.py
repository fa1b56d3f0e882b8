"""The optics' PSF grid in the frames: exact pixel integration, centring, field interpolation, orientation."""

import math

import numpy as np
import pytest
from astropy.io import fits
from helpers import isolated_stars
from scipy.special import ndtr

from detector import DetectorError
from optics import load_design
from optics.psf import PSFGrid, detector_fields, write_psf_fits
from scenes.app.render import prepare, render
from scenes.image import GAUSS_FWHM, GaussianPSF
from scenes.image.gridpsf import GridPSF, gaussian_cell_kernel
from scenes.scene import load_scene

PITCH = 9.0  # um (ML11002)
F_MM = 960.0


def gaussian_cells(n, step_um, sigma_um, cx=0.0, cy=0.0):
    """Exact cell integrals of a unit Gaussian on an n x n grid of ``step_um`` cells centred on 0 (rows along v)."""
    e = (np.arange(n + 1) - n / 2) * step_um
    return np.diff(ndtr((e - cy) / sigma_um))[:, None] * np.diff(ndtr((e - cx) / sigma_um))[None, :]


def make_grid(images, step_um, fields):
    g = PSFGrid(images=np.asarray(images, dtype=float), pixel_um=step_um, fields_deg=np.asarray(fields, float),
                center_um=-F_MM * 1e3 * np.tan(np.radians(np.asarray(fields, float))), wavelengths_nm=[550.0],
                weights=[1.0], metrics=[{"fwhm_um": math.nan, "ee50_um": 0.0, "ee80_um": 0.0, "ellipticity": 0.0,
                                         "energy_in_stamp": 1.0, "centroid_um": [0.0, 0.0]} for _ in images],
                kind="geometric", design="test", plate_scale_arcsec_per_mm=206264.806 / F_MM)
    return g


def stamp(psf, x, y, w=None, centre=None):
    """The pixel-integrated PSF of one source at (x, y) on the pixels around it (or around ``centre``)."""
    w = int(psf.radius_px(np.ones(1))[0]) + 1 if w is None else w
    ix, iy = (round(x), round(y)) if centre is None else centre
    cols = np.arange(ix - w, ix + w + 1, dtype=float)
    rows = np.arange(iy - w, iy + w + 1, dtype=float)
    p = psf(np.array([x]), np.array([y]), (cols - x)[None, :], (rows - y)[None, :])[0]
    return p, cols, rows


def moments(p, cols, rows):
    s = p.sum()
    cx, cy = (p.sum(axis=0) * cols).sum() / s, (p.sum(axis=1) * rows).sum() / s
    return s, cx, cy, (p.sum(axis=0) * (cols - cx) ** 2).sum() / s, (p.sum(axis=1) * (rows - cy) ** 2).sum() / s


def one_plane(img, step_um, **kw):
    return GridPSF.from_grid(make_grid([img], step_um, [[0.0, 0.0]]), PITCH, F_MM, (50.0, 50.0), **kw)


# ------------------------------------------------------------------------------------------ one PSF
def test_aligned_star_equals_the_exact_pixel_integral_and_any_position_conserves_flux():
    """Cells of a quarter pixel holding exact Gaussian integrals: a star on a pixel centre gets exactly the sums of
    its 4 x 4 cells, i.e. the exact erf pixel integral (GaussianPSF); anywhere else the cubic F is within 1e-5 of
    it; every stamp holds all of the flux."""
    sig_um = 1.3 * PITCH
    psf = one_plane(gaussian_cells(96, PITCH / 4, sig_um), PITCH / 4)
    ref = GaussianPSF(GAUSS_FWHM * sig_um / PITCH)
    p, cols, rows = stamp(psf, 50.0, 47.0)
    exact = ref(np.array([50.0]), np.array([47.0]), (cols - 50.0)[None, :], (rows - 47.0)[None, :])[0]
    assert np.abs(p - exact).max() < 1e-12
    rng = np.random.default_rng(1)
    worst = 0.0
    for x, y in rng.uniform(30, 70, (20, 2)):
        p, cols, rows = stamp(psf, x, y)
        exact = ref(np.array([x]), np.array([y]), (cols - x)[None, :], (rows - y)[None, :])[0]
        worst = max(worst, np.abs(p - exact).max())
        assert abs(p.sum() - 1) < 1e-9 and p.min() >= 0
    assert worst < 5e-5, worst


def test_cells_coarser_than_pixels_are_integrated_without_a_box_blur():
    """Cells 1.5 pixels wide (a coarse cube): the rendered star keeps the Gaussian's second moment + 1/12 (a
    box-overlap rebinning would add cell^2/12 = 0.19 px^2) and its flux."""
    sig_um = 2.0 * PITCH
    psf = one_plane(gaussian_cells(40, 1.5 * PITCH, sig_um), 1.5 * PITCH)
    for x, y in ((50.3, 49.8), (50.0, 50.0), (49.55, 50.45)):
        s, cx, cy, vx, vy = moments(*stamp(psf, x, y))
        assert abs(s - 1) < 1e-9
        assert abs(vx / (2.0 ** 2 + 1 / 12) - 1) < 3e-3 and abs(vy / (2.0 ** 2 + 1 / 12) - 1) < 3e-3
        assert abs(cx - x) < 2e-3 and abs(cy - y) < 2e-3


def test_an_asymmetric_psf_is_drawn_with_its_centroid_on_the_position():
    """A comatic-like stamp (core plus an offset halo, centroid 3.6 um off the stamp centre): recentred, so the
    rendered centroid is the source position for any sub-pixel phase; the FWHM of a fitted profile is kept."""
    step = PITCH / 3
    img = 0.7 * gaussian_cells(90, step, 6.0) + 0.3 * gaussian_cells(90, step, 14.0, cx=12.0, cy=-4.0)
    psf = one_plane(img, step)
    rng = np.random.default_rng(2)
    for x, y in rng.uniform(40, 60, (12, 2)):
        s, cx, cy, _, _ = moments(*stamp(psf, x, y))
        assert abs(s - 1) < 1e-9
        assert abs(cx - x) < 1e-3 and abs(cy - y) < 1e-3


def test_star_fwhm_in_the_frame_is_the_grids_fwhm():
    """Fit a pixel-integrated Gaussian (free position, FWHM, amplitude) to rendered stars of a Gaussian grid:
    the FWHM found is the grid's (the pixel convolution is in the model), at any phase."""
    from scipy.optimize import least_squares

    sig_um = 1.1 * PITCH
    psf = one_plane(gaussian_cells(64, PITCH / 5, sig_um), PITCH / 5)
    for x, y in ((50.0, 50.0), (50.37, 49.71)):
        p, cols, rows = stamp(psf, x, y)

        def resid(q, p=p, cols=cols, rows=rows):
            g = GaussianPSF(q[2])(np.array([q[0]]), np.array([q[1]]), (cols - q[0])[None, :], (rows - q[1])[None, :])
            return (q[3] * g[0] - p).ravel()

        fit = least_squares(resid, [round(x), round(y), 2.0, 1.0], xtol=1e-12, ftol=1e-12)
        assert abs(fit.x[2] / (GAUSS_FWHM * sig_um / PITCH) - 1) < 1e-4


def test_jitter_and_seeing_add_their_variance():
    """Gaussian jitter s_j and seeing (FWHM w): per-axis variance grows by s_j^2 + (w / 2.3548)^2, flux kept."""
    sig = 1.2
    img = gaussian_cells(60, PITCH / 4, sig * PITCH)
    _, _, _, v0, _ = moments(*stamp(one_plane(img, PITCH / 4), 50.2, 50.1))
    psf = one_plane(img, PITCH / 4, jitter_px=0.7, seeing_fwhm_px=1.5)
    s, _, _, vx, vy = moments(*stamp(psf, 50.2, 50.1))
    add = 0.7 ** 2 + (1.5 / GAUSS_FWHM) ** 2
    assert abs(s - 1) < 1e-9
    assert abs((vx - v0) / add - 1) < 2e-3 and abs((vy - v0) / add - 1) < 2e-3
    for sc in (0.3, 0.7, 0.99, 1.0, 2.5):  # the discrete kernel's variance is sigma^2 (in cells)
        k = gaussian_cell_kernel(sc)
        d = np.arange(k.size) - k.size // 2
        assert abs(k.sum() - 1) < 1e-14 and abs((k * d * d).sum() / sc ** 2 - 1) < 1e-6 and k.min() >= 0


# ---------------------------------------------------------------------------------------- the field
def field_grid(sig_px, nx=3, ny=3, step_um=PITCH / 4, n=72):
    """A grid of Gaussians whose width is ``sig_px[j, i]`` [pixels] at field point (i, j) of detector_fields."""
    fields = detector_fields(load_design("art"), nx, ny)
    imgs = [gaussian_cells(n, step_um, s * PITCH) for s in np.ravel(sig_px)]
    g = make_grid(imgs, step_um, fields)
    for m, s in zip(g.metrics, np.ravel(sig_px)):
        m["fwhm_um"] = GAUSS_FWHM * s * PITCH
    return g


def test_bilinear_field_interpolation_is_continuous_and_a_mixture():
    """Between grid points the PSF is the bilinear blend: at a node its own width, half-way between two nodes
    the mixture variance (s_a^2 + s_b^2) / 2, continuous across the nodes, held beyond the outermost."""
    sig = np.array([[1.0, 1.5, 2.0], [1.2, 1.7, 2.2], [1.4, 1.9, 2.4]])
    psf = GridPSF.from_grid(field_grid(sig), PITCH, F_MM, (2003.5, 1335.5))
    nx, ny = psf.node_x, psf.node_y
    assert len(nx) == 3 and len(ny) == 3 and psf.describe()["interpolation"] == "bilinear"
    # orientation: plane row j = 0 is v < 0, i.e. y = -v / pitch above the axis
    assert np.all(psf.points[:3, 1] > 1335.5) and np.all(psf.points[[0, 3, 6], 0] < 2003.5)

    def var(x, y):
        return moments(*stamp(psf, x, y))[3] - 1 / 12

    for (i, j) in ((0, 0), (1, 2), (2, 1)):
        x, y = nx[i], ny[j]
        k = psf.plane[j, i]
        assert abs(var(x, y) / (np.ravel(sig)[k] ** 2) - 1) < 2e-3
    xm = 0.5 * (nx[0] + nx[1])
    ka, kb = psf.plane[1, 0], psf.plane[1, 1]
    assert abs(var(xm, ny[1]) / (0.5 * (np.ravel(sig)[ka] ** 2 + np.ravel(sig)[kb] ** 2)) - 1) < 2e-3
    e = 1e-4
    a, _, _ = stamp(psf, nx[1] - e, ny[1], centre=(2003, 1335))
    b, _, _ = stamp(psf, nx[1] + e, ny[1], centre=(2003, 1335))
    assert np.abs(a - b).max() < 20 * e * a.max()
    far, _, _ = stamp(psf, nx[2] + 300.0, ny[2] + 200.0)
    edge, _, _ = stamp(psf, nx[2], ny[2])
    assert np.abs(far - edge).max() < 1e-12


def grid_scene(tmp_path, grid, extra=()):
    path = tmp_path / "psf.fits"
    write_psf_fits(grid, path)
    (tmp_path / "scene.toml").write_text(f"[psf]\nmodel = 'optics'\ngrid_file = '{path.name}'\n")
    return load_scene(str(tmp_path / "scene.toml"), ["detector.preset='ml11002'", "effects={}", *extra])


def test_frame_with_an_optics_grid_puts_each_star_on_its_wcs_with_its_field_psf(tmp_path):
    """A 3 x 3 grid of Gaussians (widths growing across the field; the bottom row distinct) on the ML11002 full
    frame: isolated stars' centroids on the WCS (< 0.02 px), all their flux, and second moments equal to the
    blend the field position calls for (the orientation of the grid on the frame included)."""
    sig = np.array([[2.4, 2.4, 2.4], [1.0, 1.3, 1.6], [1.0, 1.3, 1.6]])  # row j = 0: v < 0, i.e. high y
    sc = grid_scene(tmp_path, field_grid(sig), ["sky.stars=true", "sky.star_mag_limit=13.5", "detector.binning=1"])
    render(sc, tmp_path / "f.fits", seed=1, noiseless=True, progress=False)
    hdr = fits.getheader(tmp_path / "f.fits")
    assert hdr["PSFMODEL"] == "optics"
    st = isolated_stars(tmp_path / "f.fits", 2.4 * GAUSS_FWHM, radius_fwhm=3.0, min_flux_e=5e3)
    assert len(st["cx"]) >= 10
    assert np.abs(st["cx"] - st["x"]).max() < 0.02 and np.abs(st["cy"] - st["y"]).max() < 0.02
    assert np.abs(st["sum"] / st["flux"] - 1).max() < 1e-3
    psf = prepare(sc).signal_e.psf
    img = fits.getdata(tmp_path / "f.fits").astype(float) - (hdr["SKYRATE"] + hdr["DARKCUR"]) * hdr["EXPTIME"]
    for x, y, f in zip(st["tx"], st["ty"], st["flux"]):
        planes, w = psf.field_weights(np.array([x]), np.array([y]))
        expect = float(np.sum(w[0] * np.ravel(sig)[planes[0]] ** 2)) + 1 / 12
        r = 9
        ix, iy = round(x), round(y)
        box = img[iy - r:iy + r + 1, ix - r:ix + r + 1] / f
        _, _, _, vx, vy = moments(box, np.arange(ix - r, ix + r + 1), np.arange(iy - r, iy + r + 1))
        assert abs(vx / expect - 1) < 0.02 and abs(vy / expect - 1) < 0.02, (x, y, vx, vy, expect)


def test_streak_with_the_optics_psf_keeps_its_electrons(tmp_path):
    grid = field_grid(np.full((2, 2), 1.2), nx=2, ny=2)
    obj = "{ra_deg=120.95, dec_deg=-29.25, rate_ra_deg_s=-0.004, rate_dec_deg_s=0.003, photons=2e6}"
    sc = grid_scene(tmp_path, grid, ["detector.width=256", "detector.height=256", "pointing.ra_deg=120.95",
                                     "pointing.dec_deg=-29.25", "sky.stars=false", f"objects=[{obj}]",
                                     "detector.shutter='global'"])
    setup = prepare(sc)
    img = setup.signal_e.image(sc.sensor().shape).astype(float) - setup.signal_e.background_e
    o = setup.truth[0]
    assert abs(img.sum() / o["flux_e"] - 1) < 1e-3


def test_real_optics_grid_corner_psfs_land_on_their_corners(optics_psf_grid):
    """model = 'optics' with the design's own (traced) 2 x 2 grid on the full IMX411 sensor: the stamp drawn at
    each corner's grid point has that grid PSF's second moments (the art corrector is not symmetric along u, so
    a swapped grid would show), its centroid on the position and all its flux."""
    from optics.psf import read_psf_fits
    from scenes.image.gridpsf import optics_psf

    sc = load_scene("default", ["detector.preset='imx411'", "effects={}", "psf.model='optics'", "psf.grid=[2, 2]"])
    psf = optics_psf(sc, sc.sensor(), load_design("art"), 0.808)
    grid = read_psf_fits(optics_psf_grid(load_design("art"), 3.76, 2, 2))
    gv = []
    for k, (px, py) in enumerate(psf.points):
        s, cx, cy, vx, vy = moments(*stamp(psf, px, py))
        img = grid.images[k][::-1]  # rows along y = -v / pitch
        c = (np.arange(img.shape[0]) - (img.shape[0] - 1) / 2) * grid.pixel_um / 3.76
        mx, my = img.sum(axis=0), img.sum(axis=1)
        gvx = (mx * c * c).sum() - (mx * c).sum() ** 2
        gvy = (my * c * c).sum() - (my * c).sum() ** 2
        gv.append((gvx, gvy))
        assert abs(s - 1) < 1e-9 and abs(cx - px) < 0.01 and abs(cy - py) < 0.01  # ray histograms: spiky F
        assert abs(vx / (gvx + 1 / 12) - 1) < 0.01 and abs(vy / (gvy + 1 / 12) - 1) < 0.01, (k, vx, gvx, vy, gvy)
    # the corners differ by more than the tolerance (a swapped grid would show)
    assert max(abs(gv[0][0] / gv[1][0] - 1), abs(gv[0][1] / gv[1][1] - 1)) > 0.02, gv


@pytest.mark.parametrize("override, key", [
    (["psf.model='optics'", "psf.grid_file='nosuch.fits'"], "psf.grid_file"),
    (["psf.model='optics'", "psf.fwhm_arcsec=2.0"], "psf.fwhm_arcsec"),
    (["psf.seeing_fwhm_arcsec=2.0"], "psf.seeing_fwhm_arcsec"),
    (["psf.model='optics'", "psf.grid=[0, 3]"], "psf"),
])
def test_optics_psf_errors_name_the_key(tmp_path, override, key):
    p = tmp_path / "scene.toml"
    p.write_text("[psf]\n")
    with pytest.raises(DetectorError) as e:
        load_scene(str(p), override)
    assert f"key '{key}" in str(e.value) and "expected" in str(e.value) and "scene.toml" in str(e.value)


def test_optics_example_scene_renders(tmp_path, optics_sip, optics_psf_grid):
    """examples/scenes/optics_corner_imx411.toml: SIP from the optics in the header, the optics PSF, the Moon's
    straylight (the Sun is below La Palma's horizon), stars on the window."""
    from pathlib import Path

    path = Path(__file__).parents[2] / "examples" / "scenes" / "optics_corner_imx411.toml"
    render(load_scene(str(path)), tmp_path / "c.fits", seed=1, noiseless=True, progress=False)
    with fits.open(tmp_path / "c.fits") as hd:
        h, t = hd[0].header, hd["TRUTH"].data
    assert h["CTYPE1"] == "RA---TAN-SIP" and h["PSFMODEL"] == "optics" and "straylight" in h["EFFECTS"]
    assert h["MONSTRY"] > 0 and h["SUNSTRY"] == 0 and len(t) > 10
