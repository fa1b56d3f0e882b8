"""cfa and sky_gradient hidden in a "measured" frame are named first by the diagnosis, with their parameters
recovered; the look-alikes (vignetting, bias_gradient, amp_glow) do not take them."""

import numpy as np
import pytest
from helpers import star_field_toml

from scenes.app.compare import run_diagnose
from scenes.app.render import render
from scenes.scene import load_scene

#: a flat-field screen on a window with an odd column origin (the CFA pattern follows the sensor parity)
FLAT = """
[telescope]
design = "art"
[detector]
preset = "ml11002"
width = 256
height = 256
x0 = 1001
y0 = 700
[exposure]
time_s = 10.0
frame = "light"
[sky]
stars = false
flat_e_per_s = 1500.0
"""

# STARS: the star field of the image-plane cases (tests/scenes/test_diagnose_image_plane.py)
STARS = star_field_toml(384)


def _diagnose(tmp_path, base, table):
    (tmp_path / "model.toml").write_text(base)
    (tmp_path / "truth.toml").write_text(base + table)
    render(load_scene(str(tmp_path / "truth.toml")), tmp_path / "m.fits", seed=3)
    return run_diagnose(load_scene(str(tmp_path / "model.toml")), tmp_path / "m.fits")["candidates"]


def test_hidden_cfa_is_named_first_with_its_relative_responses(tmp_path):
    truth = np.array([1.05, 0.8, 0.6, 1.02])
    cands = _diagnose(tmp_path, FLAT, f"[effects.cfa]\nresponse = {truth.tolist()}\n")
    best = cands[0]
    assert best["effect"] == "cfa" and best["significant"], [(c["effect"], c["delta_bic"]) for c in cands[:3]]
    # the light level is fitted with every candidate: the responses come back relative, of mean 1
    assert np.allclose(best["params"]["response"], truth / truth.mean(), rtol=0.01), best["params"]
    assert best["params"]["pattern"] == "GBRG"  # greens on the main diagonal, the lowest (red) in cell 10


def test_a_sky_gradient_on_a_flat_screen_is_not_plausible(tmp_path):
    """A flat-field screen blocks the sky: a plane of added light on a flat frame fits, but is not named as sky
    light (issue 10's plausibility); on a sky frame it is (below)."""
    cands = _diagnose(tmp_path, FLAT, "[effects.sky_gradient]\ngx_e_per_s_per_kpx = 40.0\ngy_e_per_s_per_kpx = -25.0\n")
    sky = next(c for c in cands if c["effect"] == "sky_gradient")
    assert sky["delta_bic"] < -10 and not sky["plausible"] and "flat-field screen" in sky["implausible_because"]
    assert not sky["significant"]


@pytest.mark.parametrize("base,gx,gy", [(STARS, 3.0, -5.0)], ids=["stars"])
def test_hidden_sky_gradient_is_named_first_not_vignetting(tmp_path, base, gx, gy):
    cands = _diagnose(tmp_path, base, f"[effects.sky_gradient]\ngx_e_per_s_per_kpx = {gx}\n"
                                      f"gy_e_per_s_per_kpx = {gy}\n")
    best = cands[0]
    assert best["effect"] == "sky_gradient" and best["significant"], [(c["effect"], c["delta_bic"]) for c in cands[:4]]
    p = best["params"]
    assert abs(p["gx_e_per_s_per_kpx"] - gx) < 0.1 * np.hypot(gx, gy), p
    assert abs(p["gy_e_per_s_per_kpx"] - gy) < 0.1 * np.hypot(gx, gy), p
    # vignetting (radial, multiplicative) is far behind; bias_gradient (a plane and a bowl in ADU) fits the plane
    # as well on one light frame and loses by its extra parameter (its bowl finds nothing)
    bic = {c["effect"]: c["delta_bic"] for c in cands}
    assert bic.get("vignetting", 0.0) > best["delta_bic"] + 30


def test_a_strong_mosaic_is_judged_where_it_acts_on_its_own_pixels():
    """A 12 % Bayer mosaic on a bright flat under a 3 % column drift: the grey comparison flags the dim cells
    as outliers, so on the compared pixels alone the drift dominates and the mosaic would "remove only a few
    per cent of what is wrong where it acts" (5 % here, with one diagonal's cells flagged). Judged on its own pixels (every unsaturated light pixel) it
    removes most of it (the drift is a tenth of the mosaic's contrast), so the support gate lets it stand."""
    from helpers import residuals_of

    from detector import make_sensor, registry
    from scenes.app.compare.candidates import support_share
    from scenes.app.compare.policy import DEFAULT_POLICY

    h = w = 128
    s = make_sensor("ml11002", {"width": w, "height": h, "gain_e_per_adu": 1.0, "read_noise_e": 5.0})
    rng = np.random.default_rng(2)
    photo = np.full((h, w), 20000.0)
    yy, xx = np.mgrid[:h, :w]
    resp = np.array([[0.940, 1.000], [0.996, 0.879]])[yy % 2, xx % 2]
    drift = 1 + 0.03 * (xx / (w - 1) - 0.5)
    truth = photo * resp * drift / resp.mean()
    var = photo + 25.0
    data = 1000 + truth + rng.normal(0, 1, (h, w)) * np.sqrt(truth + 25.0)
    res = residuals_of(data, 1000 + photo, var, photo, s)
    res.fit[yy % 2 == xx % 2] = False  # one diagonal's cells: outliers of the grey comparison's 3x3 medians
    fit = registry()["cfa"].signature.fit(res, "cfa")
    assert fit is not None and fit.params["response"][3] / fit.params["response"][0] == pytest.approx(0.879 / 0.94,
                                                                                                     abs=0.01)
    assert support_share(res, fit) > DEFAULT_POLICY.min_support_share


def test_a_mosaic_sampled_where_the_residual_was_small_is_still_a_pattern_of_a_few_pixels():
    """The fitted pixels leave out the residual's local outliers: a strong mosaic's dim colour planes, kept only
    where a drift brings them near the model. Sampled there, the period-2 pattern aliases into the block means
    and would look large-scale; measured on the usable pixels it is the pattern of a few pixels it is, and its
    structure share is not judged (a mosaic is not judged by the block means)."""
    from detector.sensor import make_sensor
    from detector.signatures import Residuals, SpikeStats
    from scenes.app.compare.candidates import large_scale_share, structure_share

    s = make_sensor("imx411", {"width": 256, "height": 256, "bias_adu": 0})
    shape = (256, 256)
    rng = np.random.default_rng(4)
    photo = np.full(shape, 20000.0, np.float32)
    resp = np.array([[1.11, 0.85], [0.99, 1.05]])[np.arange(256)[:, None] % 2, np.arange(256)[None, :] % 2]
    drift = 1 - 0.1 * (np.arange(256)[None, :] / 256 - 0.5)
    var = (photo / s.gain_e_per_adu + 4.0).astype(np.float32)
    data = (photo * resp * drift + rng.normal(0, np.sqrt(var))).astype(np.float32)
    delta = (photo * (resp - 1)).astype(np.float32)
    # the residual's outliers (beyond 5 sigma of the model) left out of the fitted pixels, as spike_stats does
    fit = np.abs(data - photo) < 5 * np.sqrt(var)
    usable = np.ones(shape, bool)
    res = Residuals(data, photo, var, fit, photo, np.zeros(shape, np.float32), np.arange(256.0), np.arange(256.0),
                    s, 10.0, SpikeStats(0, 0, 0, 0, 0), SpikeStats(0, 0, 0, 0, 0), usable=usable)
    assert 0.2 < fit.mean() < 0.8
    idx, _, w = res.flat_profiled()
    assert large_scale_share(res, delta, idx, w) < 0.5
    assert structure_share(res, delta) is None
