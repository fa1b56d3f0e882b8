"""The sensor-physics effects from scene files: a user mistake is one line and exit 2, a CCD renders CTI."""

from pathlib import Path

import numpy as np
from astropy.io import fits
from click.testing import CliRunner

from scenes.app.cli import cli

SCENE = Path(__file__).resolve().parents[2] / "examples" / "scenes" / "empty_sky_imx411.toml"


def test_cti_on_a_cmos_scene_is_one_clear_error_and_no_output(tmp_path):
    out = tmp_path / "x.fits"
    r = CliRunner().invoke(cli, ["render", str(SCENE), "-o", str(out), "--set", "detector.width=64",
                                 "--set", "detector.height=64", "--set", "effects.cti.beta=0.5"])
    assert r.exit_code == 2
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and "key 'effects.cti'" in lines[0] and "CCD" in lines[0], r.output
    assert "Traceback" not in r.output and not out.exists()


def test_ccd_scene_with_cti_and_a_persistence_sequence_renders(tmp_path):
    first, second = tmp_path / "a.fits", tmp_path / "b.fits"
    base = ["--set", "detector.preset='ml11002'", "--set", "detector.width=128", "--set", "detector.height=128",
            "--set", "exposure.seed=3"]
    r = CliRunner().invoke(cli, ["render", str(SCENE), "-o", str(first), *base,
                                 "--set", "effects.cti.density_per_px=[0.2]", "--set", "effects.cti.release_time_s=[0.002]"])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(cli, ["render", str(SCENE), "-o", str(second), *base,
                                 "--set", f"effects.persistence.previous_frame='{first}'",
                                 "--set", "effects.persistence.time_since_s=2.0"])
    assert r.exit_code == 0, r.output
    assert fits.getdata(second).shape == (128, 128) and np.isfinite(fits.getdata(first)).all()
