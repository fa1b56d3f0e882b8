"""The newtsim command line: the contract's verbs, one-line errors, no tracebacks for user mistakes."""

import subprocess
import sys

import pytest
from astropy.io import fits

from scenes.app.cli import expand_multi_file_options


def newtsim(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "scenes.app.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, timeout=300)


def test_help_lists_the_contract_verbs():
    r = newtsim("--help")
    assert r.returncode == 0
    for verb in ("render", "compare", "diagnose", "characterize", "optics"):
        assert verb in r.stdout


def test_render_with_overrides_seed_and_png(tmp_path):
    out = tmp_path / "f.fits"
    r = newtsim("render", "default", "-o", out, "--seed", 42, "--set", "detector.width=480",
                "--set", "detector.height=240", "--set", "exposure.time_s=5")
    assert r.returncode == 0, r.stderr
    h = fits.getheader(out)
    assert h["SEED"] == 42 and h["EXPTIME"] == 5.0 and h["NAXIS1"] == 480
    assert (tmp_path / "f.png").stat().st_size > 1000


@pytest.mark.parametrize("args, needle", [
    (["render", "nosuch.toml", "-o", "x.fits"], "nosuch.toml"),
    (["render", "default", "-o", "x.fits", "--set", "exposure.time_s=-2"], "exposure.time_s"),
    (["render", "default", "-o", "x.fits", "--set", "effects.hot_pixels.count=-5"], "effects.hot_pixels.count"),
    (["render", "default", "-o", "x.fits", "--set", "effects.warp_drive.on=true"], "effects.warp_drive"),
    (["render", "default", "-o", "x.fits", "--set", "telescope.design=nosuch"], "telescope.design"),
    (["render", "default", "-o", "no/such/dir/x.fits", "--set", "detector.width=240", "--set",
      "detector.height=240"], "no/such/dir"),
    (["characterize", "--bias", "a.fits", "b.fits", "--dark", "c.fits"], "a.fits"),
])
def test_user_errors_are_one_line_without_traceback(tmp_path, args, needle):
    r = newtsim(*args, cwd=tmp_path)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr and needle in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert not list(tmp_path.glob("*.fits")) and not list(tmp_path.glob(".*.part"))


def test_multi_file_options_expand():
    argv = ["characterize", "--bias", "a", "b", "--dark", "c", "d", "e", "--json", "o.json"]
    assert expand_multi_file_options(argv) == ["characterize", "--bias", "a", "--bias", "b", "--dark", "c",
                                               "--dark", "d", "--dark", "e", "--json", "o.json"]
