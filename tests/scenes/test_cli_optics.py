"""`newtsim optics ...`: contract keys, cache, one-line errors."""

import json
import math
import os
import subprocess
import sys

import pytest
from astropy.io import fits


def newtsim(*args, cache):
    env = {**os.environ, "NEWTSIM_CACHE_DIR": str(cache)}
    return subprocess.run([sys.executable, "-m", "scenes.app.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=600, env=env, check=False)


@pytest.fixture
def cache(tmp_path):
    pytest.importorskip("mitsuba")
    return tmp_path / "cache"


def test_vignetting_json_plot_fits_and_cache(tmp_path, cache):
    args = ["optics", "vignetting", "bare", "--grid", 3, "--rays", 20000, "--json", tmp_path / "v.json",
            "--plot", tmp_path / "v.png", "--fits", tmp_path / "v.fits"]
    r = newtsim(*args, cache=cache)
    assert r.returncode == 0, r.stderr
    j = json.loads((tmp_path / "v.json").read_text())
    assert j["relative_illumination"][1][1] == pytest.approx(1.0)
    assert 0.75 < j["on_axis_throughput"] < 0.85 and not j["cached"]
    assert len(j["field_x_deg"]) == 3 and len(j["field_y_deg"]) == 3
    assert (tmp_path / "v.png").stat().st_size > 10_000
    assert fits.getdata(tmp_path / "v.fits").shape == (3, 3)
    r2 = newtsim(*args, cache=cache)
    assert r2.returncode == 0 and json.loads((tmp_path / "v.json").read_text())["cached"]


def test_layout_writes_a_drawing_and_a_glb(tmp_path, cache):
    r = newtsim("optics", "layout", "art", "--plot", tmp_path / "l.png", "--export", tmp_path / "t.glb", cache=cache)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "l.png").stat().st_size > 10_000 and (tmp_path / "t.glb").stat().st_size > 10_000


@pytest.mark.parametrize("args, needle", [
    (["optics", "vignetting", "no_such_design"], "no_such_design"),
    (["optics", "pst", "bare", "--angles", "ten,twenty"], "--angles"),
    (["optics", "pst", "bare", "--angles", "0,400"], "--angles"),
    (["optics", "layout", "bare"], "--plot"),
    (["optics", "psf", "bare", "--field-deg", "0", "0", "--band", "imx411", "--wavelength-nm", "500"], "--band"),
])
def test_user_errors_are_one_line(args, needle, cache):
    r = newtsim(*args, cache=cache)
    assert r.returncode == 2
    assert needle in r.stderr and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


def test_psf_json_fits_geometric_and_cache(tmp_path, cache):
    """`optics psf`: the contract keys; the bare paraboloid's on-axis diffraction PSF is centred on the
    axis with an Airy-sized core (FWHM ~ lambda N = 1.3 um) and its geometric spot a point; coma at 0.1 deg
    has the sagittal width 2 theta f / (16 N^2) (Schroeder 6.2, +2 % fifth order at f/2.4); the FITS
    image reads back with optics.psf.read_psf_fits; a repeat comes from the cache."""
    from optics.psf import read_psf_fits

    args = ["optics", "psf", "bare", "--field-deg", 0, 0, "--wavelength-nm", 550, "--json", tmp_path / "p.json"]
    r = newtsim(*args, "--fits", tmp_path / "p.fits", cache=cache)
    assert r.returncode == 0, r.stderr
    j = json.loads((tmp_path / "p.json").read_text())
    for key in ("ee_radius_um", "ee", "fwhm_um", "centroid_um"):
        assert key in j
    assert abs(j["centroid_um"][0]) < 0.05 and abs(j["centroid_um"][1]) < 0.05
    assert 1.0 < j["fwhm_um"] < 1.5
    assert 0.9 < j["ee"][-1] <= 1.0 and len(j["ee"]) == len(j["ee_radius_um"])
    grid = read_psf_fits(tmp_path / "p.fits")
    assert grid.images.shape == (1, 97, 97) and grid.pixel_um == 1.0
    assert grid.images.sum() == pytest.approx(1.0, abs=1e-5)
    r2 = newtsim(*args, cache=cache)
    assert r2.returncode == 0 and json.loads((tmp_path / "p.json").read_text())["cached"]

    theta = 0.1
    r = newtsim("optics", "psf", "bare", "--field-deg", 0, theta, "--geometric", "--json", tmp_path / "g.json",
                cache=cache)
    assert r.returncode == 0, r.stderr
    g = json.loads((tmp_path / "g.json").read_text())
    for key in ("rms_spot_um", "extent_tangential_um", "extent_sagittal_um", "ee_radius_um", "ee", "fwhm_um",
                "centroid_um"):
        assert key in g
    unit = math.radians(theta) * 960.0 / (16 * 2.4 ** 2) * 1e3
    assert g["extent_sagittal_um"] == pytest.approx(2 * unit * 1.02, rel=0.02)
    assert g["extent_tangential_um"] > 1.4 * g["extent_sagittal_um"]
    assert g["centroid_um"][1] == pytest.approx(-960e3 * math.tan(math.radians(theta)), abs=2 * unit)


def test_psf_band_is_weighted_by_the_detector_qe(tmp_path, cache):
    """`--band imx411`: the preset's QE band (400-1000 nm), weights normalised; the corrected art design
    keeps the polychromatic spot in the sensor's corner within a few pixels (RMS diameter 27 um: the
    band's ends lie outside the corrector's 450-900 nm design band)."""
    r = newtsim("optics", "psf", "art", "--field-deg", 1.55, 1.16, "--band", "imx411", "--geometric",
                "--json", tmp_path / "b.json", cache=cache)
    assert r.returncode == 0, r.stderr
    j = json.loads((tmp_path / "b.json").read_text())
    assert len(j["wavelengths_nm"]) >= 5 and sum(j["weights"]) == pytest.approx(1.0, abs=1e-5)
    assert min(j["wavelengths_nm"]) < 500 and max(j["wavelengths_nm"]) > 900
    assert 2 * j["rms_spot_um"] < 30.0


def test_psf_and_vignetting_honour_the_perturbation_table(tmp_path, cache):
    """A design TOML with a [perturbation] table: the geometric spot moves by f tan(2 tilt) for a primary
    tilt, the JSON reports the perturbation, and the cache keeps the nominal and perturbed designs apart."""
    import tomli_w

    from optics import load_design

    data = load_design("bare").model_dump(exclude_none=True)
    data["perturbation"] = {"primary_tilt_y_deg": 0.05}
    path = tmp_path / "tilted.toml"
    path.write_text(tomli_w.dumps(data))
    out = {}
    for name in ("bare", path):
        r = newtsim("optics", "psf", name, "--field-deg", 0, 0, "--geometric", "--json", "-", cache=cache)
        assert r.returncode == 0, r.stderr
        out[str(name)] = json.loads(r.stdout)
    nominal, tilted = out["bare"], out[str(path)]
    assert nominal["perturbation"] == {} and tilted["perturbation"] == {"primary_tilt_y_deg": 0.05}
    assert not tilted["cached"]
    shift_mm = (tilted["centroid_um"][0] - nominal["centroid_um"][0]) / 1e3
    assert shift_mm == pytest.approx(960.0 * math.tan(math.radians(0.1)), rel=0.01)
    r = newtsim("optics", "vignetting", path, "--grid", 3, "--rays", 20000, "--json", "-", cache=cache)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["perturbation"] == {"primary_tilt_y_deg": 0.05}
    path.write_text(tomli_w.dumps({**data, "perturbation": {"primary_tilt_q_deg": 1.0}}))
    r = newtsim("optics", "psf", path, "--field-deg", 0, 0, "--geometric", cache=cache)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1
    assert "perturbation.primary_tilt_q_deg" in r.stderr and str(path) in r.stderr


@pytest.mark.parametrize("args, needle", [
    (["optics", "optimize", "art", "--goal", "baffle", "-o", "x.toml"], "--angles"),
    (["optics", "optimize", "bare", "--goal", "corrector", "-o", "x.toml"], "corrector"),
    (["optics", "optimize", "art", "--goal", "baffle", "--angles", "0,500", "-o", "x.toml"], "--angles"),
])
def test_optimize_user_errors_are_one_line(args, needle, cache, tmp_path):
    r = newtsim(*args, cache=cache)
    assert r.returncode == 2, r.stderr
    assert needle in r.stderr and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


def test_optimize_corrector_writes_design_json_and_plot(tmp_path, cache):
    out = tmp_path / "opt.toml"
    r = newtsim("optics", "optimize", "art", "--goal", "corrector", "-o", out, "--json", tmp_path / "o.json",
                "--plot", tmp_path / "o.png", "--band", "none", "--rays", 300, "--iterations", 4, "--grid", 2,
                cache=cache)
    assert r.returncode == 0, r.stderr
    j = json.loads((tmp_path / "o.json").read_text())
    assert j["goal"] == "corrector" and j["mean_after_um"] <= j["mean_before_um"]
    assert (tmp_path / "o.png").stat().st_size > 10_000
    from optics import load_design

    assert load_design(str(out)).corrector.enabled
