"""Measured calibration maps as effects: ``bias_map`` and ``flat_map`` (detector/effects/maps.py)."""

from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits

from detector import Detector, DetectorError, build_effects, make_sensor

GEOM = {"sensor_width_px": 200, "sensor_height_px": 160, "width": 64, "height": 48, "x0": 30, "y0": 20,
        "read_noise_e": 0.0, "dark_current_e_per_s": 0.0}
REALDATA = Path(__file__).resolve().parents[2].parent / "shared" / "realdata" / "sbig_stl1001e_calib"


def sensor(preset="ml11002", **kw):
    return make_sensor(preset, {**GEOM, **kw})


def pattern(shape, seed=0):
    """A known flat: a ramp, a sinusoid across the columns and pixel-to-pixel scatter (mean ~1)."""
    y, x = np.indices(shape)
    rng = np.random.default_rng(seed)
    return (1 + 0.1 * x / shape[1] - 0.05 * y / shape[0] + 0.03 * np.sin(x / 3.0)
            + 0.01 * rng.standard_normal(shape)).astype(np.float32)


def write(path, data, **cards):
    hdu = fits.PrimaryHDU(np.asarray(data))
    for k, v in cards.items():
        hdu.header[k] = v
    hdu.writeto(path, overwrite=True)
    return str(path)


def test_flat_map_reproduces_the_pattern_in_a_flat_frame(tmp_path):
    s = sensor()
    full = pattern((160, 200))
    f = write(tmp_path / "flat.fits", full)
    det = Detector(s, build_effects({"flat_map": {"path": f}}, s))
    level = 20000.0
    expect = level * full[20:68, 30:94] / full.mean()
    mu = det.expose(level, 1.0, 1, noiseless=True)  # expected electrons: the pattern exactly
    assert np.allclose(mu, expect, rtol=2e-6)
    adu = det.expose(level, 1.0, 7).astype(np.float64)  # one noisy frame: Poisson about the pattern
    e = (adu - s.bias_adu + 0.5) * s.gain_e_per_adu
    z = (e - expect) / np.sqrt(expect + s.gain_e_per_adu ** 2 / 12)
    n = z.size
    assert abs(z.mean()) < 4 / np.sqrt(n) and abs(z.std() - 1) < 0.05
    slope = np.polyfit(expect.ravel(), e.ravel(), 1)[0]  # the frame follows the pattern with slope 1
    assert abs(slope - 1) < 0.02


def test_window_cropping_picks_the_right_sub_array(tmp_path):
    """Maps coded by position: every window pixel gets the value of its own sensor pixel (x0 = 30, y0 = 20)."""
    y, x = np.indices((160, 200))
    code = 1.0 + x + 200.0 * y  # a unique value per sensor pixel
    s = sensor()
    flat = build_effects({"flat_map": {"path": write(tmp_path / "flat.fits", code)}}, s)[0]
    assert np.allclose(flat._map * code.mean(), code[20:68, 30:94], rtol=1e-6)
    bias_code = 0.01 * code  # 0..320 ADU: inside the ADC's range around bias_adu = 1000
    bias = build_effects({"bias_map": {"path": write(tmp_path / "bias.fits", bias_code)}}, s)[0]
    # through the chain's mean frame: the structure added at the ADU stage, bias_adu stays the level
    mean, _, _ = Detector(s, [bias]).moments(0.0, 0.0)
    # (no read noise in GEOM: the ADC's rounding is exact, detector.chain.rounded_moments)
    assert np.allclose(mean, np.rint(s.bias_adu + bias_code[20:68, 30:94] - np.median(bias_code)), atol=1e-3)
    # a window-sized map is the window itself
    fw = write(tmp_path / "win.fits", bias_code[20:68, 30:94])
    assert np.allclose(build_effects({"bias_map": {"path": fw}}, s)[0]._map,
                       bias_code[20:68, 30:94] - np.median(bias_code[20:68, 30:94]), atol=1e-4)


@pytest.mark.parametrize("preset, mode", [("ml11002", "sum"), ("imx411", "sum"), ("imx411", "average")])
def test_binning_ccd_block_mean_cmos_per_pixel(tmp_path, preset, mode):
    rng = np.random.default_rng(2)
    m = 1000 + 5 * rng.standard_normal((160, 200))
    f = write(tmp_path / "b.fits", m.astype(np.float32))
    s = sensor(preset, binning=2, binning_mode=mode)
    det = Detector(s, build_effects({"bias_map": {"path": f}}, s))
    mean, _, _ = det.moments(0.0, 0.0)
    st = (m.astype(np.float32).astype(np.float64) - np.median(m.astype(np.float32)))[20:68, 30:94]
    blocks = st.reshape(24, 2, 32, 2)
    # no read noise (GEOM): every rounding of the ADC is exact (detector.chain.rounded_moments)
    if s.kind == "ccd":  # one read per binned pixel: bias_adu + the block mean of the structure, rounded once
        expect = np.rint(s.bias_adu + blocks.mean(axis=(1, 3)))
    else:  # every pixel read with its own bias and rounded, then summed (or averaged and rounded) digitally
        expect = np.rint(s.bias_adu + blocks).sum(axis=(1, 3))
        if mode == "average":  # four codes average to k + 1/2 a quarter of the time: a transition, half-way
            q = expect / 4
            expect = np.where(np.abs(q - np.floor(q) - 0.5) < 1e-6, q, np.rint(q))
    # an input that falls on a code transition (float32 ties) reads either code: half-way on average
    off = np.abs(mean - expect)
    assert off.max() <= 0.5 + 1e-3 and np.mean(off < 1e-3) > 0.99


def test_wrong_shape_names_the_file_the_key_and_the_shapes(tmp_path):
    f = write(tmp_path / "small.fits", np.ones((10, 12), np.float32))
    s = sensor()
    for name in ("bias_map", "flat_map"):
        with pytest.raises(DetectorError) as e:
            build_effects({name: {"path": f}}, s, file="scene.toml")
        msg = str(e.value)
        assert "small.fits" in msg and f"effects.{name}.path" in msg
        assert "10 x 12" in msg and "160 x 200" in msg and "48 x 64" in msg
    with pytest.raises(DetectorError, match="not found"):
        build_effects({"flat_map": {"path": str(tmp_path / "nope.fits")}}, s)
    bad = write(tmp_path / "neg.fits", -np.ones((160, 200), np.float32))
    with pytest.raises(DetectorError, match="effects.flat_map.path"):
        build_effects({"flat_map": {"path": bad}}, s)
    with pytest.raises(DetectorError, match="effects.bias_map.hdu"):
        build_effects({"bias_map": {"path": f, "hdu": 3}}, s)


def test_hdu_and_scale(tmp_path):
    m = np.zeros((48, 64), np.float32)
    m[:, 10] = 8.0  # a hot column in the master bias
    hdul = fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(m, name="MASTER")])
    hdul.writeto(tmp_path / "mb.fits")
    s = sensor()
    eff = build_effects({"bias_map": {"path": str(tmp_path / "mb.fits"), "hdu": "MASTER", "scale": 0.5}}, s)[0]
    assert np.allclose(eff._map[:, 10], 4.0) and np.allclose(np.delete(eff._map, 10, axis=1), 0.0)


def test_scene_paths_resolve_like_the_catalogue(tmp_path, monkeypatch):
    """[effects.flat_map] path relative to the scene file, rendered from another working directory."""
    from scenes.app.render import render
    from scenes.scene import load_scene

    (tmp_path / "cal").mkdir()
    full = pattern((160, 200), seed=4)
    write(tmp_path / "cal" / "flat.fits", full)
    scene = tmp_path / "cal" / "s.toml"
    scene.write_text("[detector]\npreset = 'ml11002'\n" + "".join(f"{k} = {v}\n" for k, v in GEOM.items())
                     + "[sky]\nflat_e_per_s = 1000.0\n[effects.flat_map]\npath = 'flat.fits'\n")
    monkeypatch.chdir(tmp_path)
    sc = load_scene(str(Path("cal") / "s.toml"))
    assert sc.effects["flat_map"]["path"] == str(tmp_path / "cal" / "flat.fits")
    render(sc, tmp_path / "f.fits", seed=1, noiseless=True, progress=False)
    img = fits.getdata(tmp_path / "f.fits")
    assert np.allclose(img / img.mean(), full[20:68, 30:94] / full[20:68, 30:94].mean(), rtol=1e-5)


@pytest.mark.skipif(not REALDATA.is_dir(), reason="real SBIG calibration frames not found at ../shared/realdata")
def test_real_sbig_bias_frame_as_a_bias_map():
    """A measured 1024 x 1024 SBIG STL-1001E bias frame as the map of a sensor of that size."""
    path = REALDATA / "bias-Neg10-Vis.00000000.BIAS.FIT"
    raw = fits.getdata(path).astype(np.float64)
    s = make_sensor("ml11002", {"sensor_width_px": 1024, "sensor_height_px": 1024, "width": 256, "height": 128,
                                "x0": 512, "y0": 100, "bias_adu": 991.0, "read_noise_e": 0.0})
    det = Detector(s, build_effects({"bias_map": {"path": str(path)}}, s))
    mean, _, _ = det.moments(0.0, 0.0)
    assert np.allclose(mean - 991.0, raw[100:228, 512:768] - np.median(raw), atol=1e-3)


def test_registered_documented_and_constant_maps_are_the_identity(tmp_path):
    from detector import registry

    for name in ("bias_map", "flat_map"):
        cls = registry()[name]
        d = cls.describe()
        assert cls.signature is None and len(d["doc"]) > 40 and "path" in d["params"]["properties"]
    s = sensor(read_noise_e=3.0)
    const = write(tmp_path / "c.fits", np.full((160, 200), 7.0, np.float32))
    ref = Detector(s).expose(200.0, 10.0, frame_seed=5)
    out = Detector(s, build_effects({"bias_map": {"path": const}, "flat_map": {"path": const}}, s)).expose(
        200.0, 10.0, frame_seed=5)
    assert out.tobytes() == ref.tobytes()


@pytest.mark.parametrize("preset, binning", [("ml11002", 1), ("ml11002", 2), ("imx411", 2)])
def test_noise_map_adds_its_variance_per_read(tmp_path, preset, binning):
    """``noise_map``: the difference of two bias frames has variance 2 (sigma_map^2 + read^2) / g^2 per pixel
    (a CCD's binned read: the quadratic mean of the map over its pixels; a CMOS sums b^2 reads), as the model
    of the mean frame says; the map is a gradient from 0 to 8 e- across the columns."""
    s = sensor(preset, read_noise_e=2.0, bias_adu=500, binning=binning)
    x = np.linspace(0.0, 8.0, 200)[None, :].repeat(160, axis=0)
    f = write(tmp_path / "noise.fits", x.astype(np.float32))
    det = Detector(s, build_effects({"noise_map": {"path": f}}, s))
    _, var, _ = det.moments(0.0, 0.0)
    win = x[20:68, 30:94]
    b = binning
    blocks = (win ** 2).reshape(48 // b, b, 64 // b, b)
    g = s.gain_e_per_adu
    if s.kind == "ccd":
        expect = (blocks.mean(axis=(1, 3)) + 4.0) / g ** 2
    else:
        expect = (blocks.sum(axis=(1, 3)) + 4.0 * b * b) / g ** 2
    assert np.allclose(var, expect + np.asarray(var)[0, 0] - expect[0, 0], rtol=0.02)  # quantisation: a constant
    diffs = [det.expose(0.0, 0.0, 10 + k).astype(np.float64) - det.expose(0.0, 0.0, 50 + k) for k in range(40)]
    measured = np.var(np.stack(diffs), axis=0).mean(axis=0) / 2  # per column, 40 x rows samples
    np.testing.assert_allclose(measured, np.asarray(var).mean(axis=0), rtol=0.15)
