"""Tests of the calibration-frame characterisation (detector.characterize) and its plots.

Every check compares with a number obtained independently of the code under test: the parameters the
frames were simulated with (through newtsim's own detector chain), analytic noise formulas, a plain numpy
computation on the real frames, or the facts stated in ../shared/realdata/PROVENANCE.md.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits

from detector import Detector, DetectorError, build_effects, make_sensor, registry
from detector.characterize import (
    characterize,
    clipped_stats,
    emit_scene_dict,
    fit_lifetimes,
    read_frame,
)

REALDATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "realdata"
SBIG = REALDATA / "sbig_stl1001e_calib"
DARK_TIMES = (10.0, 30.0, 60.0, 150.0, 300.0)

# the simulated camera: ML11002 preset, 512 x 512, 8 e- read noise, 2 e-/ADU, 1.5 e-/s dark current
READ_E, GAIN, DARK_E_S, BIAS = 8.0, 2.0, 1.5, 1000.0


def _sbig_or_skip() -> Path:
    if not SBIG.is_dir():
        pytest.skip(f"../shared/realdata not found: {SBIG} (real SBIG STL-1001E calibration frames)")
    return SBIG


def _write(path: Path, data: np.ndarray, exptime: float | None, **cards) -> str:
    h = fits.Header()
    if exptime is not None:
        h["EXPTIME"] = exptime
    for k, v in cards.items():
        h[k] = v
    fits.writeto(path, data, h, overwrite=True)
    return str(path)


def _simulate(det: Detector, folder: Path, flats: bool, **cards) -> tuple[list, list, list]:
    """Two biases, darks at DARK_TIMES, optionally a flat pair (20000 e-), written as FITS with EXPTIME."""
    folder.mkdir(parents=True, exist_ok=True)
    bias = [_write(folder / f"bias{k}.fits", det.expose(0.0, 0.0, 100 + k), 0.0, **cards) for k in range(2)]
    darks = [_write(folder / f"dark{int(t)}.fits", det.expose(0.0, t, 200 + int(t)), t, **cards) for t in DARK_TIMES]
    flat = [_write(folder / f"flat{k}.fits", det.expose(20000.0, 1.0, 300 + k), 1.0, **cards) for k in range(2)] \
        if flats else []
    return bias, darks, flat


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    s = make_sensor("ml11002", {"width": 512, "height": 512, "read_noise_e": READ_E, "gain_e_per_adu": GAIN,
                                "dark_current_e_per_s": DARK_E_S})
    b, d, f = _simulate(Detector(s, []), tmp_path_factory.mktemp("synth"), flats=True)
    return characterize(b, d, f)


HOT = {"count": 3000, "law": "weibull", "weibull_shape": 1.5, "scale_s": 400.0, "stuck_fraction": 0.02}


@pytest.fixture(scope="module")
def synth_hot(tmp_path_factory):
    if "hot_pixels" not in registry():
        pytest.skip("the hot_pixels effect (detector/effects/defects.py) is not registered yet")
    s = make_sensor("ml11002", {"sensor_width_px": 512, "sensor_height_px": 512, "read_noise_e": READ_E,
                                "gain_e_per_adu": GAIN, "dark_current_e_per_s": DARK_E_S})
    det = Detector(s, build_effects({"hot_pixels": HOT}, s))
    b, d, _ = _simulate(det, tmp_path_factory.mktemp("synth_hot"), flats=False, EGAIN=GAIN)
    truth = det.truth(0.0, 0)["HOTPIX"]
    return characterize(b, d), truth, tmp_path_factory


@pytest.fixture(scope="module")
def sbig():
    folder = _sbig_or_skip()
    bias = sorted(folder.glob("bias-*.FIT"))
    darks = sorted(folder.glob("darks-*.FIT"))
    flats = sorted(folder.glob("flat-*.FIT"))
    assert len(bias) == 2 and len(darks) == 5 and len(flats) == 2
    return characterize(bias, darks, flats, holdout_exposures=[300.0]), bias, darks, flats


# ---------------------------------------------------------------------------------------------------------
# (1) synthetic frames from the detector chain
# ---------------------------------------------------------------------------------------------------------

def test_synthetic_read_noise_and_bias(synth):
    b = synth["bias"]
    # temporal read noise in ADU plus the ADC's quantisation noise (uniform, variance 1/12 ADU^2)
    expected = math.sqrt((READ_E / GAIN) ** 2 + 1 / 12)
    assert abs(b["read_noise_adu"] - expected) < 4 * b["read_noise_se_adu"]
    # the ADC rounds (mid-tread): the mean of rint(B + noise) is B
    assert abs(b["level_mean_adu"] - BIAS) < 0.05
    assert b["fixed_pattern_std_adu"] < 0.5  # no fixed pattern simulated
    # Gaussian read noise: no normality test rejects at the 0.1 % level
    for test in ("shapiro_wilk", "jarque_bera", "kolmogorov_smirnov"):
        assert b["normality"][test]["p_value"] > 1e-3, test
    assert b["normality"]["n"] == 5000


def test_synthetic_gain_by_photon_transfer(synth):
    g = synth["gain"]
    assert g["source"] == "photon transfer (flat pair)" and g["header_e_per_adu"] is None
    assert abs(g["photon_transfer_e_per_adu"] - GAIN) < 4 * g["photon_transfer_se"]
    # read noise in electrons through the measured gain
    assert synth["bias"]["read_noise_e"] == pytest.approx(READ_E, rel=0.02)


def test_synthetic_dark_rate(synth):
    d = synth["dark"]
    rate_adu = DARK_E_S / GAIN
    # independent standard error of the OLS slope: per-exposure mean errors sigma_t / sqrt(N)
    t = np.array(DARK_TIMES)
    sig = np.sqrt((READ_E / GAIN) ** 2 + 1 / 12 + rate_adu * t / GAIN) / math.sqrt(512 * 512)
    w = (t - t.mean()) / np.sum((t - t.mean()) ** 2)
    se_theory = float(np.sqrt(np.sum(w ** 2 * sig ** 2)))
    se = math.hypot(d["dark_current_adu_per_s_se"], se_theory)
    assert abs(d["dark_current_adu_per_s"] - rate_adu) < 4 * se
    assert d["dark_current_e_per_s"] == pytest.approx(DARK_E_S, rel=0.02)
    # no defects simulated: no hot pixel and no significant DSNU
    assert synth["hot_pixels"]["n_hot"] <= 2 and synth["hot_pixels"]["n_stuck"] == 0
    assert not d["dsnu"]["significant"] or d["dsnu"]["sigma_rel"] < 0.01
    # hold-out (default: the longest exposure) and leave-one-out predict the dark signal to 1 %
    (pred,) = d["holdout"]["predictions"]
    assert pred["exposure_s"] == 300.0
    assert abs(pred["dark_signal_adu"]["rel_error"]) < 0.01
    assert len(d["leave_one_out"]) == 5
    assert all(abs(x["dark_signal_rel_error"]) < 0.02 for x in d["leave_one_out"])


def test_synthetic_flat_has_no_prnu_and_no_vignetting(synth):
    f = synth["flat"]
    # simulated: uniform illumination, no PRNU effect; the temporal noise alone is 0.5 % of the signal
    assert f["prnu"]["temporal_rel_std"] > 0.004
    assert f["prnu_rel"] < 0.002
    assert f["vignetting"]["corner_over_centre_mean"] == pytest.approx(1.0, abs=0.002)
    # 20000 e- at 2 e-/ADU, plus 1.5 e- of dark current
    assert f["signal_adu"] == pytest.approx((20000 + DARK_E_S) / GAIN, rel=0.005)


def test_result_is_strict_json(synth):
    json.dumps(synth, allow_nan=False)


def test_plots_are_written(synth, tmp_path):
    from detector.calplots import write_plots

    made = write_plots(json.loads(json.dumps(synth)), tmp_path / "plots")
    names = sorted(Path(p).name for p in made)
    assert names == ["bias_noise.png", "dark_current.png", "photon_transfer.png"]  # no hot pixel: no histogram
    for p in made:
        assert Path(p).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# ---------------------------------------------------------------------------------------------------------
# (2) hot pixels with a Weibull time-to-double, simulated by the hot_pixels effect
# ---------------------------------------------------------------------------------------------------------

def test_hot_pixels_weibull_comes_back(synth_hot):
    res, truth, _ = synth_hot
    hp = res["hot_pixels"]
    stuck_true = int(np.count_nonzero(truth["kind"] == b"stuck"))
    growing_true = truth.size - stuck_true
    assert res["gain"]["source"].startswith("header EGAIN")
    assert abs(hp["n_stuck"] - stuck_true) <= 2
    assert abs(hp["n_hot"] - growing_true) <= 0.02 * growing_true
    w = hp["fits"]["weibull"]
    assert hp["fits"]["preferred"] == "weibull"
    assert abs(w["shape"] - HOT["weibull_shape"]) < 4 * w["shape_se"]
    assert abs(w["scale_s"] - HOT["scale_s"]) < 4 * w["scale_se_s"]
    # against the maximum-likelihood fit of the true times-to-double: only measurement noise in between
    ideal = fit_lifetimes(truth["t_double_s"][truth["kind"] != b"stuck"])["weibull"]
    assert w["shape"] == pytest.approx(ideal["shape"], rel=0.02)
    assert w["scale_s"] == pytest.approx(ideal["scale_s"], rel=0.02)
    # hold-out at 300 s: the count of pixels > 1000 ADU above bias from the law fitted on 10..150 s
    c = res["dark"]["holdout"]["predictions"][0]["count_above_bias_adu"]["1000"]
    assert c["tau_within_detection_limit"]
    assert abs(c["t_double_law"] - c["measured"]) < 4 * math.sqrt(c["measured"]) + 0.03 * c["measured"]


def test_emitted_scene_reproduces_the_camera(synth_hot):
    res, truth, factory = synth_hot
    scene = emit_scene_dict(res)
    det = dict(scene["detector"])
    preset = det.pop("preset")
    assert preset == "ml11002" and det["kind"] == "ccd"
    assert (det["sensor_width_px"], det["sensor_height_px"], det["width"], det["height"]) == (512, 512, 512, 512)
    assert det["gain_e_per_adu"] == GAIN  # from EGAIN
    assert det["bias_adu"] == pytest.approx(BIAS, abs=0.1)
    assert det["read_noise_e"] == pytest.approx(READ_E, rel=0.02)
    assert det["dark_current_e_per_s"] == pytest.approx(DARK_E_S, rel=0.01)
    hot = scene["effects"]["hot_pixels"]
    assert hot["count"] == res["hot_pixels"]["n_hot"] + res["hot_pixels"]["n_stuck"]
    assert hot["law"] == "weibull" and hot["stuck_value_adu"] == 65535.0
    # the scene is valid for the detector model, and re-simulating it gives the same camera back
    s = make_sensor(preset, det)
    again = Detector(s, build_effects(scene["effects"], s))
    b, d, _ = _simulate(again, factory.mktemp("roundtrip"), flats=False, EGAIN=det["gain_e_per_adu"])
    res2 = characterize(b, d, holdout_exposures=[])
    assert res2["bias"]["level_mean_adu"] == pytest.approx(res["bias"]["level_mean_adu"], abs=0.05)
    assert res2["bias"]["read_noise_adu"] == pytest.approx(res["bias"]["read_noise_adu"], rel=0.01)
    assert res2["dark"]["dark_current_adu_per_s"] == pytest.approx(res["dark"]["dark_current_adu_per_s"], rel=0.01)
    n1 = res["hot_pixels"]["n_hot"] + res["hot_pixels"]["n_stuck"]
    n2 = res2["hot_pixels"]["n_hot"] + res2["hot_pixels"]["n_stuck"]
    assert abs(n2 - n1) <= 0.02 * n1


# ---------------------------------------------------------------------------------------------------------
# (3) the real SBIG STL-1001E set
# ---------------------------------------------------------------------------------------------------------

def test_sbig_bias_and_read_noise(sbig):
    res, bias, _, _ = sbig
    b = res["bias"]
    # independent: plain numpy on the two frames
    b0, b1 = (fits.getdata(p).astype(np.float64) for p in bias)
    d = b0 - b1
    d = d[np.abs(d - np.median(d)) < 5 * 1.4826 * np.median(np.abs(d - np.median(d)))]
    read_np = d.std() / math.sqrt(2)
    assert 6.4 < read_np < 6.8  # PROVENANCE: pair-difference noise 6.6 ADU
    assert b["read_noise_adu"] == pytest.approx(read_np, rel=0.02)
    # in e- with the adopted gain: the flats' photon-transfer gain (1.93 e-/ADU), the header's EGAIN 2.06 is flagged
    assert b["read_noise_e"] == pytest.approx(read_np * res["gain"]["adopted_e_per_adu"], rel=0.02)
    assert res["gain"]["adopted_e_per_adu"] == pytest.approx(1.93, abs=0.02)
    assert b["level_median_adu"] == pytest.approx(np.median(b0), abs=1.0)
    assert abs(b["level_median_adu"] - 991) <= 1
    # single-frame std 8.0 ADU > 6.6 ADU: a fixed pattern; mostly columns on this CCD
    assert b["single_frame_std_unclipped_adu"] == pytest.approx(b0.std(), rel=1e-6)
    assert 2.0 < b["fixed_pattern_std_adu"] < 5.0
    assert b["column_pattern_std_adu"] > 3 * b["row_pattern_std_adu"]
    for test in ("shapiro_wilk", "jarque_bera", "kolmogorov_smirnov"):
        assert 0.0 <= b["normality"][test]["p_value"] <= 1.0


def test_sbig_dark_current_and_holdout(sbig):
    res, _, darks, _ = sbig
    d = res["dark"]
    assert d["exposures_s"] == list(DARK_TIMES)
    assert d["dark_current_adu_per_s"] == pytest.approx(0.18, rel=0.2)  # PROVENANCE: about 0.18 ADU/s
    assert d["dark_current_e_per_s"] == pytest.approx(d["dark_current_adu_per_s"] * res["gain"]["adopted_e_per_adu"])
    # the line's intercept is the bias level (within 2 ADU)
    assert abs(d["intercept_minus_bias_adu"]) < 2.0
    # hold-out: fit 10, 30, 60, 150 s, predict 300 s
    ho = d["holdout"]
    assert ho["fit_exposures_s"] == [10.0, 30.0, 60.0, 150.0] and ho["exposures_s"] == [300.0]
    (p,) = ho["predictions"]
    measured_300 = clipped_stats(fits.getdata(SBIG / "darks-expos300s-Neg10-Vis.00000000.DARK.FIT"), 3.0)["mean"]
    assert p["mean_adu"]["measured"] == pytest.approx(measured_300)
    assert abs(p["mean_adu"]["rel_error"]) < 0.10
    assert abs(p["dark_signal_adu"]["rel_error"]) < 0.10  # the stronger statement: bias-free signal
    # pixels > 1000 ADU above bias (PROVENANCE: 45, 275, 568, 1149, 3805) grow with exposure
    counts = [r["count_above_bias_adu"]["1000"] for r in d["per_exposure"]]
    assert counts == sorted(counts)
    for c, ref in zip(counts, (45, 275, 568, 1149, 3805)):
        assert abs(c - ref) <= 0.05 * ref + 3
    c300 = p["count_above_bias_adu"]["1000"]
    assert c300["measured"] == counts[-1]
    assert abs(c300["rel_error_per_pixel"]) < 0.10
    assert c300["tau_within_detection_limit"] and abs(c300["rel_error_t_double_law"]) < 0.15


def test_sbig_hot_pixels(sbig):
    res, *_ = sbig
    hp = res["hot_pixels"]
    assert hp["n_hot"] > 1000
    assert hp["n_hot"] + hp["n_stuck_outliers"] + hp["n_transient"] + hp["n_not_growing"] == hp["n_outliers"]
    assert hp["n_stuck"] >= hp["n_stuck_in_bias"]
    assert hp["n_transient"] > 0  # cosmic-ray hits in the 300 s dark
    f = hp["fits"]
    for law in ("weibull", "exponential"):
        assert math.isfinite(f[law]["aic"]) and f[law]["scale_s"] > 0
    assert f["preferred"] == ("weibull" if f["weibull"]["aic"] < f["exponential"]["aic"] else "exponential")
    # t_double = B / r: the brightest hot pixel
    top = next(x for x in hp["brightest"] if x["class"] == "hot")
    excess = top["rate_adu_per_s"] - hp["mean_rate_adu_per_s"]
    assert top["t_double_s"] == pytest.approx(hp["bias_level_adu"] / excess)


def test_sbig_flats(sbig):
    res, *_ = sbig
    g, f = res["gain"], res["flat"]
    # the camera's own photon transfer is adopted (1.93 e-/ADU), and the header's EGAIN = 2.06, more than 3
    # standard errors away, is flagged rather than hidden
    assert g["source"] == "photon transfer (flat pair)" and g["header_e_per_adu"] == 2.06
    assert g["adopted_e_per_adu"] == g["photon_transfer_e_per_adu"] == pytest.approx(2.06, rel=0.10)
    if abs(g["photon_transfer_e_per_adu"] - 2.06) > 3 * g["photon_transfer_se"]:
        assert any("differs from the photon-transfer gain" in w for w in res["warnings"])
    assert res["bias"]["read_noise_e"] == pytest.approx(res["bias"]["read_noise_adu"] * g["adopted_e_per_adu"])
    assert f["median_raw_adu"][0] == pytest.approx(19690, abs=50)  # PROVENANCE
    assert f["vignetting"]["corner_over_centre_mean"] == pytest.approx(0.94, abs=0.02)  # PROVENANCE
    assert 0.0 < f["prnu_rel"] < 0.02
    assert any("flats at" in w for w in res["warnings"])  # -5 C against -10 C


def test_sbig_emitted_scene(sbig):
    res, *_ = sbig
    scene = emit_scene_dict(res)
    det = dict(scene["detector"])
    assert det.pop("preset") == "ml11002"
    assert det["kind"] == "ccd" and det["sensor_width_px"] == det["sensor_height_px"] == 1024
    g = res["gain"]["adopted_e_per_adu"]  # the photon-transfer gain of the flats, not the header's 2.06
    assert det["pixel_pitch_um"] == 24.0 and det["gain_e_per_adu"] == pytest.approx(g, abs=1e-4)
    assert det["bias_adu"] == pytest.approx(991.8, abs=1.0)
    assert det["dark_current_e_per_s"] == pytest.approx(res["dark"]["dark_current_adu_per_s"] * g, rel=1e-3)
    s = make_sensor("ml11002", det)  # validates every field
    assert s.shape == (1024, 1024)
    if "hot_pixels" in registry():
        build_effects(scene["effects"], s)
    assert scene["exposure"] == {"time_s": 300.0, "frame": "dark"}
    with pytest.raises(DetectorError, match="preset"):
        emit_scene_dict(res, preset_hint="nope")


# ---------------------------------------------------------------------------------------------------------
# (4) bad input: one clear DetectorError naming the file (and the key)
# ---------------------------------------------------------------------------------------------------------

@pytest.fixture
def small(tmp_path):
    rng = np.random.default_rng(1)

    def frame(name, t, shape=(64, 64), **cards):
        return _write(tmp_path / name, (1000 + rng.normal(0, 5, shape)).astype(np.uint16), t, **cards)

    return tmp_path, frame


def test_mixed_sizes(small):
    _, frame = small
    b = [frame("b0.fits", 0.0), frame("b1.fits", 0.0)]
    bad = frame("odd.fits", 10.0, shape=(64, 32))
    with pytest.raises(DetectorError) as e:
        characterize(b, [frame("d10.fits", 10.0), bad])
    assert "odd.fits" in str(e.value) and "32x64" in str(e.value)


def test_missing_exptime(small):
    _, frame = small
    b = [frame("b0.fits", 0.0), frame("b1.fits", 0.0)]
    with pytest.raises(DetectorError) as e:
        characterize(b, [frame("noexp.fits", None)])
    assert "noexp.fits" in str(e.value) and "EXPTIME" in str(e.value)
    # EXPOSURE is accepted instead of EXPTIME
    assert read_frame(frame("alt.fits", None, EXPOSURE=12.5), need_exptime=True).exptime_s == 12.5


def test_truncated_and_corrupt_files(small):
    folder, frame = small
    good = frame("b0.fits", 0.0)
    raw = Path(good).read_bytes()
    (folder / "trunc.fits").write_bytes(raw[: len(raw) - 3000])
    (folder / "header_only.fits").write_bytes(raw[:1000])
    (folder / "junk.fits").write_bytes(b"not a fits file" * 300)
    for name in ("trunc.fits", "header_only.fits", "junk.fits", "missing.fits"):
        with pytest.raises(DetectorError) as e:
            characterize([good, str(folder / name)], [frame("d.fits", 10.0)])
        assert name in str(e.value), name


def test_non_finite_and_not_an_image(small):
    folder, frame = small
    a = np.full((16, 16), 1000.0, np.float32)
    a[3, 5] = np.nan
    nan = _write(folder / "nan.fits", a, 10.0)
    with pytest.raises(DetectorError, match=r"nan\.fits.*non-finite.*x=5, y=3"):
        read_frame(nan, role="dark", need_exptime=True)
    cube = _write(folder / "cube.fits", np.zeros((3, 8, 8), np.uint16), 10.0)
    with pytest.raises(DetectorError, match=r"cube\.fits"):
        read_frame(cube)
    with pytest.raises(DetectorError, match="flat"):
        characterize([frame("b0.fits", 0.0)], [frame("d.fits", 10.0)], [frame("f.fits", 1.0)])
    with pytest.raises(DetectorError, match="holdout_exposures"):
        characterize([frame("b0.fits", 0.0), frame("b1.fits", 0.0)],
                     [frame("d1.fits", 10.0), frame("d2.fits", 20.0), frame("d3.fits", 40.0)],
                     holdout_exposures=[15.0])
