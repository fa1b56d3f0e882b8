"""Image-plane effects hidden in a star field are named and their parameters recovered (Gauss-Newton
through the transformation), and the error falls to the noise once they are applied."""

import pytest

from scenes.compare import diagnose, run_compare, run_diagnose
from scenes.render import render
from scenes.scene import load_scene

BASE = """
[telescope]
design = "art"
[detector]
preset = "ml11002"
width = 384
height = 384
[pointing]
ra_deg = 120.95115
dec_deg = -29.25022
epoch = "2023-02-01T22:00:00"
[exposure]
time_s = 10.0
frame = "light"
tracking = "sidereal"
[sky]
background_mag_arcsec2 = 19.72
stars = true
star_mag_limit = 15.0
[psf]
model = "gaussian"
fwhm_arcsec = 3.0
"""

CASES = {
    "psf_blur": ({"sigma_px": 0.7}, {"sigma_px": (0.7, 0.05)}),
    "pointing_offset": ({"dx_px": 0.4, "dy_px": -0.25}, {"dx_px": (0.4, 0.03), "dy_px": (-0.25, 0.03)}),
    "jitter": ({"sigma_major_px": 1.2, "sigma_minor_px": 0.3, "angle_deg": 35.0},
               {"sigma_major_px": (1.2, 0.1), "angle_deg": (35.0, 5.0)}),
    # a 6-px trail at 30 deg: a box, told from the Gaussian smear of jitter (which must not take it, and
    # whose own case above must not be taken by the drift: every case asserts its effect ranks first)
    "pointing_drift": ({"dx_px": 5.2, "dy_px": 3.0}, {"dx_px": (5.2, 0.2), "dy_px": (3.0, 0.2)}),
}


@pytest.mark.parametrize("effect", sorted(CASES))
def test_hidden_image_plane_effect_is_found_and_the_error_falls(tmp_path, effect):
    hidden, expect = CASES[effect]
    (tmp_path / "model.toml").write_text(BASE)
    table = "\n".join(f"{k} = {v}" for k, v in hidden.items())
    (tmp_path / "truth.toml").write_text(BASE + f"[effects.{effect}]\n{table}\n")
    render(load_scene(str(tmp_path / "truth.toml")), tmp_path / "m.fits", seed=3)
    out = run_diagnose(load_scene(str(tmp_path / "model.toml")), tmp_path / "m.fits")
    best = out["candidates"][0]
    assert best["effect"] == effect and best["significant"], [(c["effect"], c["delta_bic"]) for c in out["candidates"][:3]]
    for k, (value, tol) in expect.items():
        assert abs(best["params"][k] - value) < tol, (k, best["params"])
    diagnose.apply_candidate(load_scene(str(tmp_path / "model.toml")), best, tmp_path / "round2.toml")
    after = run_compare(load_scene(str(tmp_path / "round2.toml")), tmp_path / "m.fits")["summary"]["chi2_per_dof"]
    before = out["baseline"]["chi2_per_dof"]
    assert after - 1 < 0.05 * (before - 1)
