"""An object's light curve (a tumbling debris' flicker) hidden in a measured streak is named by the
diagnosis from the flux along the track, with its amplitude, period and phase; --apply writes it into the
object's table and the error falls; a steady object gives no light-curve candidate that is significant."""

import math

import pytest

from scenes.app.compare import run_compare, run_diagnose
from scenes.app.compare.apply import apply_candidate
from scenes.app.render import render
from scenes.scene import load_scene

SCENE = """
[detector]
preset = "ml11002"
width = 512
height = 512
[pointing]
ra_deg = 120.95115
dec_deg = -29.25022
epoch = "2023-02-01T22:00:00"
[exposure]
time_s = 10.0
frame = "light"
[sky]
background_mag_arcsec2 = 21.0
[psf]
model = "gaussian"
fwhm_arcsec = 4.0
[[objects]]
ra_deg = 120.90
dec_deg = -29.25022
rate_ra_deg_s = 0.0095
rate_dec_deg_s = 0.001
photons = 3e6
"""
CURVE = {"amplitude": 0.45, "period_s": 1.3, "phase": 0.3}


def _frames(tmp_path, curve):
    (tmp_path / "model.toml").write_text(SCENE)
    truth = SCENE + ("light_curve = { kind = \"sinusoid\", amplitude = %g, period_s = %g, phase = %g }\n"
                     % (curve["amplitude"], curve["period_s"], curve["phase"]) if curve else "")
    (tmp_path / "truth.toml").write_text(truth)
    render(load_scene(str(tmp_path / "truth.toml")), tmp_path / "m.fits", seed=4)
    return load_scene(str(tmp_path / "model.toml")), tmp_path / "m.fits"


def test_a_light_curve_is_named_with_its_period_amplitude_and_phase(tmp_path):
    model, measured = _frames(tmp_path, CURVE)
    out = run_diagnose(model, measured)
    best = out["candidates"][0]
    assert best["effect"] == "light_curve" and best["significant"], [(c["effect"], c["delta_bic"])
                                                                       for c in out["candidates"][:4]]
    lc = best["params"]["light_curve"]
    assert lc["period_s"] == pytest.approx(CURVE["period_s"], rel=0.01)
    assert lc["amplitude"] == pytest.approx(CURVE["amplitude"], abs=0.04)
    assert abs((lc["phase"] - CURVE["phase"] + 0.5) % 1.0 - 0.5) < 0.03  # phase in cycles, modulo 1
    new = apply_candidate(model, best, tmp_path / "round2.toml", measured)
    assert load_scene(str(new)).objects[0]["light_curve"]["kind"] == "sinusoid"
    before = out["baseline"]["chi2_per_dof"]
    after = run_compare(load_scene(str(new)), measured)["summary"]["chi2_per_dof"]
    assert before - 1 > 10 * math.sqrt(2 / 512 ** 2)
    assert after - 1 < 0.5 * (before - 1), (before, after)


def test_a_steady_object_gives_no_significant_light_curve(tmp_path):
    model, measured = _frames(tmp_path, None)
    out = run_diagnose(model, measured)
    lc = [c for c in out["candidates"] if c["effect"] == "light_curve"]
    assert lc and not lc[0]["significant"], lc[:1]
