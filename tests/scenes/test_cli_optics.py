"""`newtsim optics ...`: contract keys, cache, one-line errors."""

import json
import os
import subprocess
import sys

import pytest
from astropy.io import fits


def newtsim(*args, cache):
    env = {**os.environ, "NEWTSIM_CACHE_DIR": str(cache)}
    return subprocess.run([sys.executable, "-m", "scenes.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=600, env=env)


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
