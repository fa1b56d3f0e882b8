"""``newtsim inject``: objects drawn into measured frames (scenes/app/bench/inject.py).

Physics checked on every frame (a constructed one always; the real frames of ../shared/realdata when present):

- flux: aperture photometry of (out - in) over each object's footprint, times the gain, recovers the injected
  electrons within 2 % (the expected Poisson error of 5e4 e- is 0.45 %);
- shot noise: the variance of (out - in) about its expectation E/g is E/g^2 (Poisson electrons converted
  with the gain) within 5 %: the mean of (out - in - E/g)^2 / (E/g^2) over the footprints' pixels with
  E/g^2 >= 20 ADU^2 and over 12 or more draws of the noise (>= 8000 pixel-draws: 1.6 % statistical error);
- nothing else changes: every pixel outside the footprints and every other HDU is the input's, bit for bit.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
from astropy.io import fits
from astropy.wcs import WCS

from scenes.app.bench.inject import (
    InjectError,
    Obj,
    background,
    inject,
    inject_file,
    linear_path,
    read_frame,
)
from scenes.objects.lightcurve import LightCurve

FLUX_E = 5.0e4  # a point's electrons; a streak gets at least FLUX_PER_PX_E per pixel of its length
FLUX_PER_PX_E = 2.0e3
DRAWS = 12  # draws of the shot noise at least, and more until MIN_PIXELS pixel-draws enter the variance
MIN_PIXELS = 8000


def _objects(frame) -> list[Obj]:
    """Four streaks, a point and a point with a light curve, on a grid that keeps them apart, plus a streak
    leaving the frame (clipped)."""
    h, w = frame.shape
    t = frame.exptime_s
    cells = [(0.25, 0.25), (0.75, 0.25), (0.25, 0.75), (0.75, 0.75)]
    half = 0.12 * min(h, w)
    objs = []
    for i, (fx, fy) in enumerate(cells):
        xc, yc = fx * (w - 1), fy * (h - 1)
        ang = 0.4 + 0.7 * i
        dx, dy = half * math.cos(ang), half * math.sin(ang)
        flux = max(FLUX_E, FLUX_PER_PX_E * 2 * half)
        objs.append(Obj(f"s{i}", "streak", linear_path(xc - dx, yc - dy, xc + dx, yc + dy, t), flux))
    xc, yc = 0.5 * (w - 1), 0.5 * (h - 1)
    objs.append(Obj("p0", "point", linear_path(xc, yc, xc, yc, t), FLUX_E,
                    light_curve=LightCurve("sinusoid", 0.5, t / 3.3)))
    objs.append(Obj("edge", "streak", linear_path(-0.1 * w, 0.5 * (h - 1), 0.1 * w, 0.5 * (h - 1), t), FLUX_E))
    return objs


def _footprint_mask(res, shape):
    masks = []
    for d in res.injected:
        m = np.zeros(shape, dtype=bool)
        m[d.row0:d.row0 + d.stamp_e.shape[0], d.col0:d.col0 + d.stamp_e.shape[1]] = d.stamp_e > 0
        masks.append(m)
    return masks


def check_frame(frame, *, psf="measured"):
    """Inject DRAWS times (new shot noise each time) and check flux, variance and the untouched pixels."""
    bkg_rms = background(frame.data, frame.bayer)
    try:
        first = inject(frame, _objects(frame), psf=psf, seed=0, bkg_rms=bkg_rms)
    except InjectError as exc:
        assert "--psf" in str(exc)
        psf = "3px"
        first = inject(frame, _objects(frame), psf=psf, seed=0, bkg_rms=bkg_rms)
    fwhm = f"{first.summary['fwhm_px']}px"
    g = frame.gain_e_per_adu
    shape = frame.shape
    masks = _footprint_mask(first, shape)
    union = np.any(masks, axis=0)
    live = np.isfinite(frame.data) & (frame.data < frame.saturation_adu)
    # flux and clipping bookkeeping (objects on disjoint footprints)
    sums = np.zeros(len(masks))
    num = den = 0.0
    expected = sum(np.pad(d.stamp_e, ((d.row0, shape[0] - d.row0 - d.stamp_e.shape[0]),
                                      (d.col0, shape[1] - d.col0 - d.stamp_e.shape[1]))) for d in first.injected)
    k = draws = 0
    while draws < DRAWS or (den < MIN_PIXELS and draws < 6 * DRAWS):
        k, draws = draws, draws + 1
        res = first if k == 0 else inject(frame, _objects(frame), psf=fwhm, seed=k, bkg_rms=bkg_rms)
        out = res.pixels.astype(np.float64)
        raw = frame.raw if frame.raw is not None else frame.data
        outside = ~union
        assert np.array_equal(res.pixels[outside], np.asarray(raw)[outside], equal_nan=True), \
            "a pixel outside the footprints changed"
        diff = np.where(live, out - frame.data, 0.0)
        assert np.all(out[live & (out >= frame.saturation_adu)] == frame.saturation_adu)
        ok = live & (out < frame.saturation_adu)
        sums += [np.sum(diff[m & ok]) * g for m in masks]
        # each pixel's (out - in - E/g)^2 over its Poisson variance E/g^2 (equal weights: a bright point's few
        # pixels do not dominate); pixels with E/g^2 >= 20 ADU^2, where the integer frames' rounding (<= 1/12
        # ADU^2) is below 0.4 % of the variance
        sel = ok & union & (expected / g ** 2 >= 20.0)
        num += np.sum((diff[sel] - expected[sel] / g) ** 2 / (expected[sel] / g ** 2))
        den += np.count_nonzero(sel)
    sums /= draws
    truth = np.array([np.sum(expected[m & live]) for m in masks])
    labels = {lab.row: lab for lab in first.labels.labels}
    assert len(labels) == len(first.injected) == 6
    np.testing.assert_allclose(sums, truth, rtol=0.02, err_msg=f"{frame.name}: flux by aperture photometry")
    assert den >= MIN_PIXELS
    assert num / den == pytest.approx(1.0, abs=0.05), f"{frame.name}: variance of (out - in) over E/g^2"
    edge = first.summary["objects"][-1]
    assert edge["clipped"] and edge["flux_visible_e"] < 0.8 * edge["flux_e"]
    assert edge["visible_x0"] >= -0.5 and edge["visible_x1"] <= 0.1 * shape[1] + 0.5
    for row, d in enumerate(first.injected):
        assert labels[row].flux_e == pytest.approx(float(d.stamp_e.sum()), rel=1e-6)
    first.summary["check"] = {"flux_ratio": (sums / truth).tolist(), "variance_ratio": num / den,
                              "pixel_draws": den, "draws": draws}
    return first


# ------------------------------------------------------------------------------------------ constructed frame
def _constructed(tmp_path, dtype="uint16", bayer=None, with_wcs=True, stars=40, name="frame.fits"):
    rng = np.random.default_rng(5)
    h, w = 200, 240
    yy, xx = np.mgrid[:h, :w]
    img = 1000.0 + rng.normal(0.0, 10.0, (h, w))
    sigma = 2.2 / 2.3548
    for _ in range(stars):
        x0, y0 = rng.uniform(10, w - 10), rng.uniform(10, h - 10)
        img += 3000.0 * np.exp(-((xx - x0) ** 2 + (yy - y0) ** 2) / (2 * sigma ** 2))
    img[5, 7] = 65535
    hdr = fits.Header()
    if with_wcs:
        wcs = WCS(naxis=2)
        wcs.wcs.ctype = ["RA---TAN", "DEC--TAN"]
        wcs.wcs.crval = [150.0, 20.0]
        wcs.wcs.crpix = [w / 2, h / 2]
        wcs.wcs.cd = [[-1.0 / 3600, 0.0], [0.0, 1.0 / 3600]]
        hdr.update(wcs.to_header())
    hdr["EXPTIME"] = 30.0
    hdr["GAIN"] = 2.0
    if bayer:
        hdr["BAYERPAT"] = bayer
    data = np.rint(img).astype(dtype) if dtype != "float32" else img.astype(np.float32)
    other = fits.ImageHDU(rng.normal(size=(20, 30)).astype(np.float32), name="OTHER")
    path = tmp_path / name
    fits.HDUList([fits.PrimaryHDU(data, hdr), other]).writeto(path)
    return path


@pytest.mark.parametrize("dtype,bayer", [("uint16", None), ("int16", None), ("float32", None), ("uint16", "RGGB")])
def test_constructed_frame_flux_variance_untouched(tmp_path, dtype, bayer):
    path = _constructed(tmp_path, dtype, bayer)
    hdul, frame = read_frame(path)
    with hdul:
        assert frame.gain_e_per_adu == 2.0 and frame.sources["gain"] == "header GAIN"
        res = check_frame(frame)
    if bayer is None:  # the PSF measured on the frame's own stars (FWHM 2.2 px drawn)
        assert res.summary["fwhm_px"] == pytest.approx(2.2, rel=0.08)
    assert res.pixels.dtype == frame.dtype


def test_inject_file_keeps_other_hdus_and_labels_snr(tmp_path):
    path = _constructed(tmp_path)
    out = tmp_path / "out.fits"
    s = inject_file(path, out, random=(8, (15.0, 40.0), (0.5, 3.0)), seed=11, labels=("fits", "coco"),
                    label_paths={"coco": tmp_path / "out.coco.json"})
    with fits.open(path) as a, fits.open(out) as b:
        assert a[0].header["BITPIX"] == b[0].header["BITPIX"] and a[0].header.get("BZERO") == b[0].header.get("BZERO")
        assert np.array_equal(a["OTHER"].data, b["OTHER"].data) and a["OTHER"].header == b["OTHER"].header
        assert [h.name for h in b][2:] == ["TRUTH", "LABELS", "LABELCAT"]
        snr = b["TRUTH"].data["snr"]
    assert len(s["objects"]) == 8 and np.all((snr > 15.0 - 1e-6) & (snr < 40.0 + 1e-6))
    # the same seed writes the same bytes
    out2 = tmp_path / "out2.fits"
    inject_file(path, out2, random=(8, (15.0, 40.0), (0.5, 3.0)), seed=11)
    with fits.open(out) as b, fits.open(out2) as c:
        assert np.array_equal(b[0].data, c[0].data)
    from pycocotools.coco import COCO

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert len(COCO(str(tmp_path / "out.coco.json")).getAnnIds()) == 8


def test_objects_toml_sky_path_and_saturation(tmp_path):
    """An object given on the sky lands where the WCS puts it; a bright one is clipped at the saturation."""
    path = _constructed(tmp_path)
    toml = tmp_path / "objects.toml"
    toml.write_text('[[objects]]\nname = "sky"\nra_deg = 150.0\ndec_deg = 20.0\nrate_ra_deg_s = 0.0\n'
                    'rate_dec_deg_s = 0.0005\nflux_e = 2e7\n')
    out = tmp_path / "out.fits"
    s = inject_file(path, out, toml, psf="2.0", seed=1)
    o = s["objects"][0]
    # CRPIX (w/2, h/2) is 1-based: pixel (119, 99) 0-based at the start; 0.0005 deg/s x 30 s = 54 px north (+y)
    assert (o["x0"], o["y0"]) == pytest.approx((119.0, 99.0), abs=1e-6)
    assert (o["x1"], o["y1"]) == pytest.approx((119.0, 99.0 + 54.0), abs=0.05)
    with fits.open(out) as b:
        assert b[0].data.max() == 65535 and s["saturated_px"] > 0


def test_clear_errors(tmp_path):
    no_wcs = _constructed(tmp_path, with_wcs=False, name="nowcs.fits")
    with pytest.raises(InjectError, match="no celestial WCS.*--pixel-scale"):
        inject_file(no_wcs, tmp_path / "o.fits", random=(2, (10.0, 20.0), (1.0, 2.0)), seed=1)
    no_stars = _constructed(tmp_path, stars=0, name="nostars.fits")
    with pytest.raises(InjectError, match="no stars to measure the PSF.*--psf"):
        inject_file(no_stars, tmp_path / "o.fits", random=(2, (10.0, 20.0), (1.0, 2.0)), seed=1)
    s = inject_file(no_wcs, tmp_path / "o.fits", random=(2, (10.0, 20.0), (1.0, 2.0)), seed=1, pixel_scale=1.0)
    assert len(s["objects"]) == 2


# ----------------------------------------------------------------------------------------------- real frames
REAL = [
    "sbig_stl1001e_calib/bias-Neg10-Vis.00000000.BIAS.FIT",
    "sbig_stl1001e_calib/bias-Neg10-Vis.00000001.BIAS.FIT",
    "sbig_stl1001e_calib/darks-expos10s-Neg10-Vis.00000000.DARK.FIT",
    "sbig_stl1001e_calib/darks-expos30s-Neg10-Vis.00000000.DARK.FIT",
    "sbig_stl1001e_calib/darks-expos60s-Neg10-Vis.00000000.DARK.FIT",
    "sbig_stl1001e_calib/darks-expos150s-Neg10-Vis.00000000.DARK.FIT",
    "sbig_stl1001e_calib/darks-expos300s-Neg10-Vis.00000000.DARK.FIT",
    "sbig_stl1001e_calib/flat-expos23s-Neg5-Vis.00000000.FIT",
    "sbig_stl1001e_calib/flat-expos23s-Neg5-Vis.00000001.FIT",
    "seestar_s50/Light_NGC7023_10.0s_IRCUT_20240730-224436.fit",
    "seestar_s50/Light_NGC7023_10.0s_IRCUT_20240730-224448.fit",
    "seestar_s50/Light_NGC7023_20.0s_IRCUT_20250630-023420.fit",
    "starfield/panoptes_solved.fits.fz",
    "starfield/ccdproc_sip-wcs.fit",
    "streak/astride_long.fits",
    "streaks_trailblazer/cutout_HSCA21787010.fits",
    "streaks_trailblazer/cutout_bi327715.fits",
    "streaks_trailblazer/cutout_m20211212UT_image0110.new.fits",
    "streaks_trailblazer/cutout_c4d_200306_000415_ori.fits.fz",
    "streaks_trailblazer/cutout_lbcb.20210407.120357.fits",
]
DEFAULT_RUN = {"streak/astride_long.fits", "streaks_trailblazer/cutout_c4d_200306_000415_ori.fits.fz"}


def _check_real(realdata, rel, hdu=None):
    path = realdata / rel
    if not path.exists():
        pytest.skip(f"{path} not found")
    hdul, frame = read_frame(path, hdu)
    with hdul:
        if frame.wcs is None:  # the SBIG calibration frames and the 2025 Seestar frame: pixels only
            with pytest.raises(InjectError, match="no celestial WCS"):
                inject_file(path, "/nonexistent/never.fits", random=(1, (10.0, 20.0), (0.0, 0.0)), seed=1)
            frame.pixel_scale_arcsec = 1.0
        check_frame(frame)


@pytest.mark.parametrize("rel", sorted(DEFAULT_RUN))
def test_real_frames_default(realdata, rel):
    _check_real(realdata, rel)


def test_real_decam_streak_ccd(realdata):
    """The DECam CCD with the real streak (HDU 33, S28): chosen by name, the 69 others untouched."""
    _check_real(realdata, "streaks_trailblazer/cutout_c4d_200306_000415_ori.fits.fz", hdu="S28")


@pytest.mark.slow
@pytest.mark.parametrize("rel", [r for r in REAL if r not in DEFAULT_RUN])
def test_real_frames_all(realdata, rel):
    _check_real(realdata, rel)


def test_cli_inject_and_detect(tmp_path):
    """The commands: a frame without a WCS is one stderr line naming the file and what to give, exit 2;
    an injection and a detection write their files."""
    import subprocess
    import sys

    def run(*args):
        return subprocess.run([sys.executable, "-m", "scenes.app.cli", *map(str, args)], capture_output=True,
                              text=True, cwd=tmp_path, check=False)

    no_wcs = _constructed(tmp_path, with_wcs=False, name="nowcs.fits")
    r = run("inject", no_wcs, "-o", tmp_path / "o.fits", "--random", "2", "--snr", "10:20", "--rate", "1:2")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1
    assert "nowcs.fits[0]: no celestial WCS" in r.stderr and "--pixel-scale" in r.stderr
    assert not (tmp_path / "o.fits").exists()
    path = _constructed(tmp_path)
    r = run("inject", path, "-o", tmp_path / "inj.fits", "--random", "3", "--snr", "40:60", "--rate", "1:3",
            "--seed", "2", "--labels", "coco,fits")
    assert r.returncode == 0, r.stderr
    r = run("detect", tmp_path / "inj.fits", "-o", tmp_path / "det.ecsv")
    assert r.returncode == 0, r.stderr
    from scenes.app.bench.score import score_files

    assert score_files(tmp_path / "det.ecsv", tmp_path / "inj.fits", kinds=("injected",))["labels"] == 3
