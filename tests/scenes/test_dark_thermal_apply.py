"""``newtsim diagnose --apply`` round-trips the exponential dark-current gradient: a dark rendered with a
temperature gradient (scene TOML ``[effects.dark_gradient] temperature_x_k``, ...) is diagnosed as
``dark_gradient`` in its exponential form, the written scene carries the fitted temperatures, and its noiseless
render adds ``D0 (2^(T / T_2) - 1) t`` (evaluated here) to the dark."""

from __future__ import annotations

import json

import numpy as np
import pytest
from astropy.io import fits
from click.testing import CliRunner
from helpers import write_scene

from detector import make_sensor
from detector.effects.thermal import doubling_interval_k
from scenes.app.cli import cli
from scenes.app.render import render
from scenes.scene import load_scene

DARK = {"detector": {"preset": "ml11002", "binning": 8}, "exposure": {"time_s": 600.0, "frame": "dark"},
        "sky": {"stars": False}}
TRUTH = {"temperature_x_k": 4.0, "temperature_y_k": -2.0, "gradient_x_e_per_s": 0.0}


def test_diagnose_apply_round_trips_the_temperature_gradient(tmp_path):
    scene = write_scene(tmp_path / "scene.toml", DARK)
    truth = write_scene(tmp_path / "truth.toml", DARK, effects={"dark_gradient": TRUTH})
    render(load_scene(str(truth)), tmp_path / "dark.fits", seed=7, progress=False)
    new, js = tmp_path / "next.toml", tmp_path / "d.json"
    r = CliRunner().invoke(cli, ["diagnose", str(scene), str(tmp_path / "dark.fits"), "--json", str(js),
                                 "--apply", str(new)])
    assert r.exit_code == 0, r.output
    best = json.loads(js.read_text())["candidates"][0]
    assert best["effect"] == "dark_gradient", best
    p = best["params"]
    assert p["temperature_x_k"] == pytest.approx(4.0, rel=0.1) and p["temperature_y_k"] == pytest.approx(-2.0, rel=0.1)
    assert "[effects.dark_gradient]" in new.read_text() and "temperature_x_k" in new.read_text()
    sc = load_scene(str(new))
    assert sc.effects["dark_gradient"]["temperature_x_k"] == pytest.approx(p["temperature_x_k"])
    # the applied scene's noiseless dark against the formula at the fitted temperatures
    render(sc, tmp_path / "applied.fits", seed=1, noiseless=True, progress=False)
    render(load_scene(str(scene)), tmp_path / "base.fits", seed=1, noiseless=True, progress=False)
    got = fits.getdata(tmp_path / "applied.fits").astype(float) - fits.getdata(tmp_path / "base.fits").astype(float)
    s = make_sensor("ml11002", {"binning": 8})
    h, w = s.output_shape
    b = s.binning
    ys, xs = np.arange(h * b, dtype=float), np.arange(w * b, dtype=float)
    tf = (p["temperature_x_k"] * (xs / (s.sensor_width_px - 1) - 0.5)[None, :]
          + p["temperature_y_k"] * (ys / (s.sensor_height_px - 1) - 0.5)[:, None])
    rate = s.dark_current_e_per_s * (2.0 ** (tf / doubling_interval_k(s.temperature_c)) - 1)
    expect = (rate * 600.0).reshape(h, b, w, b).sum(axis=(1, 3))
    assert got.shape == expect.shape
    np.testing.assert_allclose(got, expect, atol=5e-3 * np.abs(expect).max())
