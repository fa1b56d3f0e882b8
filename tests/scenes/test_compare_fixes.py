"""newtsim compare, fixes of the analysis: the sources' flux over the model's whole background, the WCS
check about the optical axis, the full-resolution residual spectrum, the two-sample outlier counts, the
chi2/dof with the global levels refitted, row-noise error bars and the saturation level of binned frames.
Each test checks against a value derived independently of the code under test."""

import re
from types import SimpleNamespace

import numpy as np
import pytest
from astropy.io import fits
from helpers import SMALL_SKY_TOML as SMALL
from helpers import STREAK_TOML, star_field_toml

from detector import Detector
from detector.sensor import make_sensor
from detector.signatures import SpikeStats
from scenes.app.compare import run_compare
from scenes.app.compare.model import build_model, read_measurement, saturation_adu
from scenes.app.compare.report import section_verdict, write_report
from scenes.app.compare.statistics import misfit, outlier_counts
from scenes.app.render import render
from scenes.scene import load_scene

SCENE = star_field_toml(512, STREAK_TOML)

# --- saturation of binned frames ------------------------------------------------------------------------------


@pytest.mark.parametrize("preset, overrides, expected", [
    # CCD, unbinned: the full well, 1000 + 50000 / 1.4 ADU, less 5 x 11 / 1.4 ADU of read noise
    ("ml11002", {}, 1000 + 50000 / 1.4 - 5 * 11 / 1.4),
    # CCD 2x2: the charge of 4 pixels (200 ke-) is read once, so the ADC maximum clips it (not 4 x 65535)
    ("ml11002", {"binning": 2}, 65535 - 5 * 11 / 1.4),
    # CCD 2x2 average: the clipped read divided by 4
    ("ml11002", {"binning": 2, "binning_mode": "average"}, (65535 - 5 * 11 / 1.4) / 4),
    # CMOS 2x2 with a small well: 4 digital reads of 500 + 10000 / 1.22 ADU each, read noise counted 4 times
    ("imx411", {"binning": 2, "full_well_e": 10000.0}, 4 * (500 + 10000 / 1.22) - 5 * 2 * 3.5 / 1.22),
    # CMOS 2x2 with the preset's well: every read at the ADC maximum, the sum clipped again at it
    ("imx411", {"binning": 2}, 65535 - 5 * 2 * 3.5 / 1.22),
    # CMOS 2x2 average: one read's level
    ("imx411", {"binning": 2, "binning_mode": "average"}, 65535 - 5 * 2 * 3.5 / 1.22 / 4),
])
def test_saturation_level_of_ccd_and_cmos_binning(preset, overrides, expected):
    s = make_sensor(preset, {"width": 32, "height": 32, **overrides})
    assert saturation_adu(s) == pytest.approx(expected, abs=0.01)
    # and the chain's own overexposed frame sits at or just above it (within 6 read-noise sigma)
    frame = Detector(s, workers=1).expose(1e7, 1.0, 3).astype(np.float64)
    margin = 5 * s.read_noise_e / s.gain_e_per_adu * (1 if s.kind == "ccd" else s.binning)
    margin /= s.binning ** 2 if s.binning_mode == "average" else 1  # 5 read-noise sigma of an output pixel
    assert saturation_adu(s) - 0.2 * margin <= frame.min() <= frame.max() <= saturation_adu(s) + 2.2 * margin


# --- the WCS check about the optical axis ----------------------------------------------------------------------

WINDOW = """
[detector]
preset = "ml11002"
width = 128
height = 128
x0 = 40
y0 = 2400
binning = {b}
[exposure]
time_s = 2.0
[sky]
stars = false
background_mag_arcsec2 = 20.0
"""


@pytest.mark.parametrize("b", [1, 2])
def test_wcs_check_of_a_window_far_from_the_axis(tmp_path, b):
    scene_path = tmp_path / "window.toml"
    scene_path.write_text(WINDOW.format(b=b))
    scene = load_scene(str(scene_path))
    render(scene, tmp_path / "own.fits", seed=2)  # the frame carries the scene's own WCS
    model = build_model(scene, realisation=False)
    # the window is ~1900 px (unbinned) from the sensor's centre: the old check measured that distance
    _, notes = read_measurement(tmp_path / "own.fits", model)
    assert notes["wcs_offset_px"] < 0.01 and not notes["warnings"], notes
    # a true shift of the measured WCS by 5 output pixels along the columns is still reported
    with fits.open(tmp_path / "own.fits") as hd:
        hd[0].header["CRPIX1"] += 5.0
        hd.writeto(tmp_path / "shifted.fits")
    _, notes = read_measurement(tmp_path / "shifted.fits", model)
    assert notes["wcs_offset_px"] == pytest.approx(5.0, abs=0.01)
    assert any("5.0 px" in w for w in notes["warnings"]), notes


# --- sources over the model's whole background -----------------------------------------------------------------

def _field(stars: bool, streak: bool) -> str:
    """test_compare's scene (ML11002 512 x 512, two catalogue stars) with 2 s and an 8" PSF, so that a star
    stays below the full well; its object moves faster and is brighter (a 17-px streak)."""
    base, obj = SCENE.split("[[objects]]")
    for old, new in (("time_s = 10.0", "time_s = 2.0"), ("fwhm_arcsec = 3.0", "fwhm_arcsec = 8.0"),
                     ("stars = true", f"stars = {str(stars).lower()}")):
        assert old in base
        base = base.replace(old, new)
    for old, new in (("0.0008", "0.004"), ("-0.0005", "-0.0025"), ("200000", "4e6")):
        assert old in obj
        obj = obj.replace(old, new)
    return base + ("[[objects]]" + obj if streak else "")


def test_sources_scaled_by_one_percent_give_a_flux_ratio_of_one_percent(tmp_path):
    """The measured frame: a noisy sky-only frame plus 1 % of the sources' expected electrons (the noiseless
    renders of the scene with and without its sources). The ratio must be 0.01; with only bias and dark
    subtracted (the sky left in both apertures) it was 0.04 for the streak and 0.03 for the star."""
    (tmp_path / "full.toml").write_text(_field(stars=True, streak=True))
    (tmp_path / "sky.toml").write_text(_field(stars=False, streak=False))
    full, sky = load_scene(str(tmp_path / "full.toml")), load_scene(str(tmp_path / "sky.toml"))
    render(full, tmp_path / "full_e.fits", seed=1, noiseless=True)
    render(sky, tmp_path / "sky_e.fits", seed=1, noiseless=True)
    render(sky, tmp_path / "sky.fits", seed=7)
    src_e = fits.getdata(tmp_path / "full_e.fits").astype(np.float64) - fits.getdata(tmp_path / "sky_e.fits")
    with fits.open(tmp_path / "sky.fits") as hd:
        hd[0].data = (hd[0].data + 0.01 * src_e / hd[0].header["GAIN"]).astype(np.float32)
        hd.writeto(tmp_path / "dim.fits")
    cmp = run_compare(full, tmp_path / "dim.fits")
    (streak,) = cmp["streaks"]
    assert streak["total_flux_ratio"] == pytest.approx(0.01, abs=0.002), streak
    # the catalogue stars the model does not clip at the full well (a clipped model star is brighter in 1 %)
    st, flag = cmp["stars"], cmp["_model"].flag
    clean = [i for i, (x, y) in enumerate(zip(st["x"], st["y"]))
             if not flag[round(y) - 4:round(y) + 5, round(x) - 4:round(x) + 5].any()]
    assert clean
    for i in clean:
        assert abs(st["flux_ratio"][i] - 0.01) < 4 * st["flux_ratio_err"][i] + 1e-4, (st["flux_ratio"][i], i)


# --- outlier counts: two Poisson samples -----------------------------------------------------------------------

def test_outlier_counts_are_compared_as_two_poisson_samples():
    """5 hot pixels in the data, none in the model realisation: 2 x 5 ln 2 = 6.93 (the one-sample deviance
    against an expectation of 0 was 75); 30 against 20: 2 [30 ln(60/50) + 20 ln(40/50)] = 2.013; equal: 0."""
    data, model = SpikeStats(5, 30, 7, 0, 0), SpikeStats(0, 20, 7, 0, 0)
    out = outlier_counts(SimpleNamespace(data_spikes=data, model_spikes=model))
    assert out["single_pos"]["deviance"] == pytest.approx(10 * np.log(2), rel=1e-9)
    assert out["cluster_pos"]["deviance"] == pytest.approx(2 * (30 * np.log(1.2) + 20 * np.log(0.8)), rel=1e-9)
    assert out["single_neg"]["deviance"] == 0 == out["hot_cols"]["deviance"]
    assert misfit(100.0, 100, out) == pytest.approx((10 * np.log(2) - 1 + 2.0134 - 1) / np.sqrt(2), abs=1e-3)


# --- row profiles of a model with row noise ----------------------------------------------------------------------

ROWS = """
[detector]
preset = "{preset}"
width = 256
height = 256
binning = {b}
[exposure]
time_s = 5.0
[sky]
stars = false
background_mag_arcsec2 = 20.0
[effects.row_noise]
sigma_e = 20.0
"""


@pytest.mark.parametrize("preset, b", [("ml11002", 1), ("imx411", 2)])
def test_row_profile_of_a_model_with_row_noise_is_noise(tmp_path, preset, b):
    """A frame of the scene itself: its row means scatter as the model says (chi2/dof 1 within 5 sigma), the
    row noise included (20 e- rms per read-out row; the per-pixel errors alone gave 142 and 216)."""
    (tmp_path / "rows.toml").write_text(ROWS.format(preset=preset, b=b))
    scene = load_scene(str(tmp_path / "rows.toml"))
    render(scene, tmp_path / "rows.fits", seed=9)
    prof = run_compare(scene, tmp_path / "rows.fits")["profiles"]
    for key in ("row", "column"):
        n = prof[key]["z"].size
        assert abs(prof[key]["chi2_per_dof"] - 1) < 5 * np.sqrt(2 / n), (key, prof[key]["chi2_per_dof"])


# --- chi2/dof with the global levels refitted --------------------------------------------------------------------

def test_a_brighter_sky_is_a_level_not_a_misfit(tmp_path):
    """The measured sky is 10 % brighter than the scene's (0.1035 mag): the raw chi2/dof is far above 1,
    with the levels refitted it is 1 and the fitted background level is +10 %."""
    (tmp_path / "scene.toml").write_text(SCENE)
    mag = 19.72 + 2.5 * np.log10(1 / 1.1)
    (tmp_path / "bright.toml").write_text(SCENE.replace("background_mag_arcsec2 = 19.72",
                                                        f"background_mag_arcsec2 = {mag:.6f}"))
    render(load_scene(str(tmp_path / "bright.toml")), tmp_path / "bright.fits", seed=4)
    cmp = run_compare(load_scene(str(tmp_path / "scene.toml")), tmp_path / "bright.fits")
    s = cmp["summary"]
    assert s["chi2_per_dof"] > 2
    assert abs(s["chi2_per_dof_levels"] - 1) < 5 * np.sqrt(2 / s["n_compared"]), s["chi2_per_dof_levels"]
    assert s["levels"]["background_scale"] == pytest.approx(0.10, abs=0.003), s["levels"]
    page = write_report(cmp, tmp_path / "r.html").read_text()
    shown = re.search(r"With the global levels refitted: chi2/dof = ([0-9.]+) \(([^)]*)\)", page)
    assert shown and float(shown[1]) == pytest.approx(s["chi2_per_dof_levels"], rel=1e-3)
    # the factor on the model's level and the change it makes [ADU], never a percentage of a level near zero
    factor = re.search(r"background x ([0-9.]+) \[\+([0-9.]+) ADU at the mean pixel\]", shown[2])
    assert factor and float(factor[1]) == pytest.approx(1 + s["levels"]["background_scale"], rel=1e-3), shown[2]
    assert float(factor[2]) > 0 and "%" not in shown[2]


def test_a_refitted_level_near_zero_is_a_factor_and_adu_not_a_percentage():
    """A 0.1 s dark holds ~0.01 ADU of dark signal: a refitted dark level of -106 (a 0.8-ADU change) printed
    as a percentage read "dark -10692.3 %". The box prints the factor and the change in ADU."""
    result = {"chi2_per_dof": 1.2, "n_compared": 10_000, "n_statistical": 0, "misfit": 1.0, "chi2_per_dof_levels": 1.0,
              "levels": {"offset_adu": 0.42, "dark_scale": -106.923}, "levels_adu": {"dark_scale": -0.8}}
    box = section_verdict(result, None)
    assert "bias offset +0.42 ADU" in box and "dark x -105.9 [-0.8 ADU at the mean pixel]" in box, box
    assert "%" not in box.split("With the global levels refitted")[1].split("</p>")[0]


# --- the full-resolution residual spectrum -----------------------------------------------------------------------

def test_a_checkerboard_response_is_the_top_peak_of_the_full_resolution_spectrum(tmp_path):
    """A 2 x 2 response pattern (+-a of the photo-signal, 0.5 sigma a pixel) puts the Nyquist frequency (0.5,
    0.5) on top, at ~N a^2 / (sigma^2 ln 2) = 2.4e4 x the median power (median of an exponential: ln 2);
    the frame of the scene itself has no peak above ~25 x the median."""
    (tmp_path / "sky.toml").write_text(SMALL)  # ML11002 256 x 256, sky only
    scene = load_scene(str(tmp_path / "sky.toml"))
    render(scene, tmp_path / "own.fits", seed=5)
    model = build_model(scene, realisation=False)
    with fits.open(tmp_path / "own.fits") as hd:
        yy, xx = np.indices(hd[0].data.shape)
        a = 0.5 * np.median(np.sqrt(model.var_adu2)) / np.median(model.photo_adu)  # 0.5 sigma on the sky
        bump = a * model.photo_adu * np.where((xx + yy) % 2, -1.0, 1.0)
        hd[0].data = (hd[0].data + bump).astype(np.float32)
        hd.writeto(tmp_path / "cfa.fits")
    own = run_compare(scene, tmp_path / "own.fits")["summary"]["power_peaks"]
    assert own["side"] == 256 and own["peaks"][0]["power_ratio"] < 30, own["peaks"][0]
    cmp = run_compare(scene, tmp_path / "cfa.fits")
    top = cmp["summary"]["power_peaks"]["peaks"][0]
    assert (top["fx"], top["fy"]) == (0.5, 0.5)
    assert top["power_ratio"] == pytest.approx(256 ** 2 * 0.25 / np.log(2), rel=0.15)
    # the report's table has it on top, highlighted
    page = write_report(cmp, tmp_path / "r.html").read_text()
    assert re.search(r'<tr class="flag"><td class="num">0.5</td><td class="num">0.5</td>', page)


def test_the_realisations_outliers_counted_beside_the_datas_are_the_serial_ones(tmp_path):
    """:func:`residuals` counts the model realisation's outliers in a thread while the data's are counted
    (:func:`data_and_realisation_spikes`, which the large-frame path's sample calls too): the same statistics as
    counting them alone, whatever the threads."""
    import pickle

    from detector.signatures import spike_stats
    from scenes.app.compare.model import residuals

    scene_path = tmp_path / "field.toml"
    scene_path.write_text(star_field_toml(96))
    scene = load_scene(str(scene_path))
    render(scene, tmp_path / "data.fits", seed=3)
    for workers in (1, 2):
        model = build_model(scene, workers=workers)
        assert model.spikes is None and model.realisation is not None  # counted with the data's
        data, _ = read_measurement(tmp_path / "data.fits", model)
        res = residuals(data, model)
        real, s = model.realisation, model.sensor
        alone = spike_stats(real, model.mean_adu, model.var_adu2, ~model.flag & (real < saturation_adu(s)),
                            s.gain_e_per_adu)[0]
        assert pickle.dumps(res.model_spikes) == pickle.dumps(alone)  # every count, index and group
        assert res.model_spikes.counts() == alone.counts()
