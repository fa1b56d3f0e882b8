"""compare / diagnose of large frames in bounded memory (scenes.app.compare.fullframe, issue 12).

The large-frame path is forced on small windows (``large_px=0``, an explicit super-pixel side ``k``) and
checked against the full-resolution path on the same frame and against the statistics a correct noise model
must give (binned chi2/dof ~ 1 within its standard error sqrt(2/n))."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import tomllib
from astropy.io import fits
from helpers import STREAK_TOML, star_field_toml, write_scene

import scenes
from scenes.app.compare import run_compare, run_diagnose
from scenes.app.compare.fullframe import (
    BandReader,
    choose_binning,
    is_large,
    run_compare_large,
    run_diagnose_large,
)
from scenes.app.render import render
from scenes.scene import load_scene

DEFAULT = tomllib.loads((Path(scenes.__file__).parent / "data" / "default.toml").read_text())


def _default_window(size: int, corner: bool = False, drop: tuple[str, ...] = (), **effects) -> dict:
    """The built-in default scene (full IMX411 effects) on a ``size`` x ``size`` window; ``corner`` puts it
    at the bottom-right corner, where the default amplifier glow is."""
    t = copy.deepcopy(DEFAULT)
    t["detector"].update(width=size, height=size)
    if corner:
        t["detector"].update(x0=14192 - size, y0=0)
    for name in drop:
        t["effects"].pop(name)
    for name, table in effects.items():
        t["effects"][name] = table
    return t


def test_binning_choice_keeps_the_binned_frame_small_and_prefers_exact_divisors():
    # full IMX411: 10640 x 14192 -> 8 divides both sides, 1330 x 1774 = 2.36 Mpx <= 4 Mpx
    assert choose_binning((10640, 14192)) == 8
    k = choose_binning((1001, 1003), target_px=10_000)
    assert (1001 // k) * (1003 // k) <= 10_000 * 1.0 + 0 or k == 11
    assert choose_binning((512, 512), target_px=4_000_000) == 1


def test_band_reader_matches_astropy_on_a_scaled_uint16_file(tmp_path):
    rng = np.random.default_rng(1)
    img = rng.integers(0, 65535, size=(37, 53)).astype(np.uint16)
    path = tmp_path / "u16.fits"
    fits.PrimaryHDU(img).writeto(path)  # stored as int16 with BZERO = 32768
    rd = BandReader(path, (37, 53), 1)
    try:
        got = np.concatenate([rd.rows(0, 10), rd.rows(10, 37)])
    finally:
        rd.close()
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, img.astype(np.float32))


def test_wrong_size_is_one_line_naming_the_file(tmp_path):
    path = tmp_path / "small.fits"
    fits.PrimaryHDU(np.zeros((10, 12), np.uint16)).writeto(path)
    with pytest.raises(Exception) as err:
        BandReader(path, (20, 12), 1)
    assert "small.fits" in str(err.value) and "12x10" in str(err.value)


@pytest.fixture(scope="module")
def self_frame(tmp_path_factory):
    """A 1024 x 1024 dark-ish IMX411 window of the default scene with strong row noise, rendered by the scene
    itself (the model explains it)."""
    d = tmp_path_factory.mktemp("ff_self")
    table = _default_window(1024, row_noise={"sigma_e": 4.0})
    table["sky"]["background_mag_arcsec2"] = 22.0
    scene = write_scene(d / "scene.toml", table)
    render(load_scene(str(scene)), d / "frame.fits", seed=3, progress=False)
    return load_scene(str(scene)), d / "frame.fits"


def test_large_path_compare_agrees_with_full_resolution_and_its_binned_chi2_is_one(self_frame):
    scene, frame = self_frame
    assert not is_large(scene) and is_large(scene, 0)
    full = run_compare(scene, frame)["summary"]
    out = run_compare_large(scene, frame, k=8, sample_bands=4, sample_rows=64)
    large = out["summary"]
    # the same pixels compared at full resolution (spikes found by a cheaper local test: a few differ)
    assert abs(large["n_compared"] - full["n_compared"]) < 1e-3 * full["n_compared"]
    assert abs(large["chi2_per_dof"] - full["chi2_per_dof"]) < 3e-3
    assert abs(large["measured"]["mean"] - full["measured"]["mean"]) < 1e-3 * full["measured"]["mean"]
    assert abs(large["model_mean"]["mean"] - full["model_mean"]["mean"]) < 1e-4 * full["model_mean"]["mean"]
    # the binned frame's variance holds the row-noise covariance k^2 (k - 1) c of each super-pixel: with 4 e-
    # of row noise on a faint sky it is most of the variance. chi2/dof of the binned frame is then ~1 within
    # the standard error of a sum dominated by its 128 binned rows' offsets (share f of the variance):
    # var(chi2/n) = 2 (1 - f)^2 / n + 2 f^2 / rows + 4 f (1 - f) / n
    res_b = out["_residuals"]
    b = large["binned"]
    n = b["n_compared"]
    assert n > 0.95 * 128 * 128 and res_b.sensor.binning == 8 and res_b.pixel_sum == 64
    cov = 8 * 8 * 7 * res_b.row_var_adu2 / 8 ** 3  # k^2 (k - 1) c, with row_var_adu2 = k^3 c
    f = res_b.row_var_adu2 / float(np.median(res_b.var_adu2))
    sd = np.sqrt(2 * (1 - f) ** 2 / n + 2 * f ** 2 / 128 + 4 * f * (1 - f) / n)
    assert abs(b["chi2_per_dof"] - 1) < 4 * sd, (b, f, sd)
    # without that covariance the binned chi2/dof would be far off
    without = b["chi2_per_dof"] * float(np.median(res_b.var_adu2 / (res_b.var_adu2 - cov)))
    assert without - 1 > 8 * sd, (without, sd)
    # the sampling block says what was computed how
    s = large["sampling"]
    assert s["binning_k"] == 8 and s["binned_shape"] == [128, 128]
    assert len(s["bands"]) == 4 and s["sample_rows"] == 4 * 64
    assert {"chi2_per_dof", "profiles"} <= set(s["full_resolution"])
    for key in ("chi2_per_dof", "measured", "model", "model_mean", "regions", "outliers", "misfit"):
        assert key in large
    # a frame the model makes: the outlier counts of the sample agree with one realisation of the model
    assert all(v["deviance"] < 12 for v in large["outliers"].values())


def test_large_path_is_taken_above_the_threshold(self_frame):
    scene, frame = self_frame
    out = run_compare(scene, frame, large_px=1000)
    assert "sampling" in out["summary"]
    assert "sampling" not in run_compare(scene, frame)["summary"]


@pytest.mark.slow
def test_large_path_diagnosis_agrees_with_the_full_resolution_one_on_2048(tmp_path):
    """The default scene's 2048 x 2048 bottom-right corner, measured with amplifier glow and hot pixels the
    model lacks: both diagnoses name both, with the same parameters within their statistical errors."""
    meas = write_scene(tmp_path / "meas.toml", _default_window(2048, corner=True))
    model = write_scene(tmp_path / "model.toml", _default_window(2048, corner=True, drop=("amp_glow", "hot_pixels")))
    frame = tmp_path / "meas.fits"
    render(load_scene(str(meas)), frame, seed=11, progress=False)
    sc = load_scene(str(model))
    full = run_diagnose(sc, frame)
    large = run_diagnose_large(sc, frame, k=4, sample_bands=8, sample_rows=64)
    names_full = set(full["significant"])
    names_large = set(large["significant"])
    assert {"amp_glow", "hot_pixels"} <= names_full
    assert names_large == names_full, (names_full, names_large)
    cf = {c["effect"]: c for c in full["candidates"]}
    cl = {c["effect"]: c for c in large["candidates"]}
    assert cl["amp_glow"]["scale"] == "binned" and cl["hot_pixels"]["scale"] == "sample"
    # glow: the same corner; amplitude and e-folding length within 10 % (the full-resolution fit's own
    # statistical error is ~1-3 % here: ~1e4 pixels of the glow at 5-10 sigma each)
    pf, pl = cf["amp_glow"]["params"], cl["amp_glow"]["params"]
    assert pf["edge"] == pl["edge"] == "bottom-right"
    assert pl["amplitude_e_per_s"] == pytest.approx(pf["amplitude_e_per_s"], rel=0.1)
    assert pl["scale_px"] == pytest.approx(pf["scale_px"], rel=0.1)
    # a smooth fit the pixels deny (its shot noise) is not named: checked on the full-resolution sample
    for c in large["candidates"]:
        if c["scale"] == "binned" and c.get("sample_delta") is not None and c["sample_delta"] > 10:
            assert not c["significant"]
    # hot pixels: what the data determine is the rate of spikes beyond the model's (the extrapolation to
    # every hot pixel of a heavy-tailed law from a few dozen amplitudes is not: count and scale_s are
    # degenerate). The sample's excess, scaled by its fraction of the rows, agrees with the whole frame's
    # within 4 Poisson sigma of the sample's counts
    of, ol = full["baseline"]["outliers"]["single_pos"], large["baseline"]["outliers"]["single_pos"]
    frac = large["sampling"]["sample_fraction"]
    assert frac == pytest.approx(8 * 64 / 2048)
    rate_full = of["data"] - of["model"]
    rate_large = (ol["data"] - ol["model"]) / frac
    assert abs(rate_large - rate_full) < 4 * np.sqrt(ol["data"] + ol["model"] + 1) / frac, (of, ol)


def test_star_cut_outs_measure_the_stars_as_the_full_resolution_comparison(tmp_path):
    """Every catalogue star of the frame is measured in its cut-out (not only those of the band sample): the
    aperture photometry of the large path is the full-resolution one, star by star."""
    scene = tmp_path / "stars.toml"
    scene.write_text(star_field_toml(1024, "[effects.psf_blur]\nsigma_px = 0.8\n").replace("limit = 15.0", "limit = 17.0"))
    frame = tmp_path / "stars.fits"
    render(load_scene(str(scene)), frame, seed=4, progress=False)
    model = tmp_path / "model.toml"
    model.write_text(star_field_toml(1024).replace("limit = 15.0", "limit = 17.0"))
    sc = load_scene(str(model))
    full = run_compare(sc, frame)["stars"]
    large = run_compare_large(sc, frame, k=4, sample_bands=3, sample_rows=32)
    st = large["stars"]
    assert large["summary"]["sampling"]["cut_outs"]["stars"] >= st["n"] >= 8
    # the same stars (the cut-outs keep 6 px from the frame's edges, the full comparison 4 px)
    assert abs(st["n"] - full["n"]) <= max(1, 0.05 * full["n"])
    common = {(round(x, 3), round(y, 3)): i for i, (x, y) in enumerate(zip(full["x"], full["y"]))}
    pairs = [(common[(round(x, 3), round(y, 3))], j) for j, (x, y) in enumerate(zip(st["x"], st["y"]))
             if (round(x, 3), round(y, 3)) in common]
    assert len(pairs) >= st["n"] - 1
    i, j = np.array(pairs).T
    np.testing.assert_allclose(st["flux_ratio"][j], full["flux_ratio"][i], rtol=1e-4)
    np.testing.assert_allclose(st["size_data_px"][j], full["size_data_px"][i], rtol=1e-4)
    np.testing.assert_allclose(st["r_field"][j], full["r_field"][i], rtol=1e-6)
    # the blur the model lacks shows: the measured stars are wider than the model's
    assert st["median_size_ratio"] > 1.05


def test_memory_exhausted_is_one_line_naming_the_file(self_frame, monkeypatch):
    from detector.errors import DetectorError
    from scenes.app.compare import fullframe

    scene, frame = self_frame

    def boom(*a, **k):
        raise MemoryError("Unable to allocate 1.12 GiB for an array with shape (10640, 14192)")

    monkeypatch.setattr(fullframe, "run_pass", boom)
    for call in (lambda: run_compare(scene, frame, large_px=0), lambda: run_diagnose(scene, frame, large_px=0)):
        with pytest.raises(DetectorError) as err:
            call()
        msg = str(err.value)
        assert "\n" not in msg and "out of memory" in msg and str(frame) in msg


def test_streak_profiles_summed_band_by_band_are_the_full_resolution_ones(tmp_path):
    """A debris streak's flux and offset along its track, summed over the bands it crosses, equal those of the
    whole frame (sums add up)."""
    scene = tmp_path / "streak.toml"
    scene.write_text(star_field_toml(512, STREAK_TOML).replace("stars = true", "stars = false"))
    frame = tmp_path / "streak.fits"
    render(load_scene(str(scene)), frame, seed=2, progress=False)
    sc = load_scene(str(scene))
    full = run_compare(sc, frame)["streaks"]
    large = run_compare_large(sc, frame, k=4, sample_bands=2, sample_rows=32)["streaks"]
    assert len(full) == len(large) == 1
    f, g = full[0], large[0]
    assert g["length_px"] == pytest.approx(f["length_px"])
    assert g["total_flux_ratio"] == pytest.approx(f["total_flux_ratio"], rel=1e-5)
    np.testing.assert_allclose(g["flux_ratio"], f["flux_ratio"], rtol=1e-4)
    np.testing.assert_allclose(g["offset_px"], f["offset_px"], rtol=1e-3, atol=1e-4)


def test_coupling_effects_see_their_neighbours_rows_band_by_band(tmp_path):
    """With inter-pixel capacitance (a coupling effect with a halo of rows) the banded model is the whole-frame
    model: every band's coupling sees the neighbouring bands' rows."""
    from scenes.app.compare.model import build_model

    scene = tmp_path / "ipc.toml"
    scene.write_text(star_field_toml(512, "[effects.ipc]\nalpha = 0.03\n").replace("limit = 15.0", "limit = 18.0")
                     .replace("fwhm_arcsec = 3.0", "fwhm_arcsec = 1.5"))
    frame = tmp_path / "ipc.fits"
    render(load_scene(str(scene)), frame, seed=2, progress=False)
    sc = load_scene(str(scene))
    whole = build_model(sc, realisation=False)
    out = run_compare_large(sc, frame, k=4, sample_bands=2, sample_rows=32)
    k = 4
    binned = whole.mean_adu.astype(np.float64).reshape(128, k, 128, k).sum(axis=(1, 3))
    np.testing.assert_allclose(out["_residuals"].model_adu, binned, rtol=2e-6)


def test_cli_compare_and_diagnose_of_a_large_frame_write_the_contract_json_with_sampling(self_frame, tmp_path,
                                                                                          monkeypatch):
    import json

    from click.testing import CliRunner

    from scenes.app.cli import cli
    from scenes.app.compare import fullframe

    scene, frame = self_frame
    monkeypatch.setattr(fullframe, "LARGE_FRAME_PX", 1000)
    monkeypatch.setattr(fullframe, "BINNED_TARGET_PX", 256 * 256)  # k = 4: a fast test
    out = tmp_path / "cmp.json"
    r = CliRunner().invoke(cli, ["compare", scene.source, str(frame), "--json", str(out)])
    assert r.exit_code == 0, r.output
    j = json.loads(out.read_text())
    assert {"chi2_per_dof", "measured", "model", "regions", "sampling"} <= set(j)
    assert "large frame" in r.output
    out = tmp_path / "diag.json"
    r = CliRunner().invoke(cli, ["diagnose", scene.source, str(frame), "--json", str(out)])
    assert r.exit_code == 0, r.output
    j = json.loads(out.read_text())
    assert "chi2_per_dof" in j["baseline"] and "sampling" in j and isinstance(j["candidates"], list)
    for c in j["candidates"]:
        assert {"effect", "params", "chi2_per_dof", "delta_bic", "explanation", "scale"} <= set(c)
    # the scene explains its own frame: nothing significant (row noise included in the model)
    assert not j["significant"], j["verdict"]


@pytest.mark.parametrize("effect", [{"sky_gradient": {"gx_e_per_s_per_kpx": 3.0, "gy_e_per_s_per_kpx": -2.0}},
                                    {"psf_blur": {"sigma_px": 1.0}}])
def test_field_effects_band_by_band_give_the_whole_frame_model(tmp_path, effect):
    """A pointwise field effect (a sky gradient) applied band by band, and a convolution (a blur) on the whole
    image, give the model of the whole frame."""
    from scenes.app.compare.model import build_model

    table = _default_window(512)
    table["effects"] = dict(effect)
    scene = write_scene(tmp_path / "f.toml", table)
    frame = tmp_path / "f.fits"
    render(load_scene(str(scene)), frame, seed=2, progress=False)
    sc = load_scene(str(scene))
    whole = build_model(sc, realisation=False)
    out = run_compare_large(sc, frame, k=4, sample_bands=2, sample_rows=32)
    binned = whole.mean_adu.astype(np.float64).reshape(128, 4, 128, 4).sum(axis=(1, 3))
    np.testing.assert_allclose(out["_residuals"].model_adu, binned, rtol=2e-6)


def test_apply_on_the_large_path_adds_the_glow_and_refits_the_levels_on_the_binned_frame(tmp_path, monkeypatch):
    from scenes.app.compare import diagnose_round, fullframe

    monkeypatch.setattr(fullframe, "LARGE_FRAME_PX", 1000)
    monkeypatch.setattr(fullframe, "BINNED_TARGET_PX", 256 * 256)  # k = 3: a fast test
    meas = write_scene(tmp_path / "meas.toml", _default_window(768, corner=True))
    model = write_scene(tmp_path / "model.toml", _default_window(768, corner=True, drop=("amp_glow",)))
    frame = tmp_path / "meas.fits"
    render(load_scene(str(meas)), frame, seed=5, progress=False)
    out = diagnose_round(load_scene(str(model)), model, frame, apply_to=tmp_path / "next.toml")
    assert out["applied"]["effect"] == "amp_glow", out["verdict"]
    p = out["applied"]["params"]
    assert p["edge"] == "bottom-right"
    assert p["amplitude_e_per_s"] == pytest.approx(5.0, rel=0.1) and p["scale_px"] == pytest.approx(400, rel=0.1)
    nxt = tomllib.loads((tmp_path / "next.toml").read_text())
    assert nxt["effects"]["amp_glow"]["edge"] == "bottom-right"
    # the applied scene explains the frame: its diagnosis finds nothing significant
    again = diagnose_round(load_scene(str(tmp_path / "next.toml")), tmp_path / "next.toml", frame)
    assert not again["significant"], again["verdict"]


def test_light_curve_is_fitted_in_the_tracks_cut_out_as_at_full_resolution(tmp_path):
    """A tumbling object's light curve (tests/scenes/test_diagnose_light_curve.py) is named on the large path
    from the cut-out of its track, with the full-resolution fit's parameters."""
    from test_diagnose_light_curve import CURVE, _frames

    model, measured = _frames(tmp_path, CURVE)
    full = run_diagnose(model, measured)
    large = run_diagnose_large(model, measured, k=4, sample_bands=2, sample_rows=32)
    cf = next(c for c in full["candidates"] if c["effect"] == "light_curve")
    cl = next(c for c in large["candidates"] if c["effect"] == "light_curve")
    assert cl["scale"] == "cut-out" and cl["significant"] and cf["significant"]
    assert large["candidates"][0]["effect"] == "light_curve"
    assert cl["params"] == cf["params"]
    assert cl["delta_bic"] == pytest.approx(cf["delta_bic"], rel=1e-3)
