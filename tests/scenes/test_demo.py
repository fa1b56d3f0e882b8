"""``newtsim demo`` (scenes.app.demo, scenes.app.quicklook.write_png_insets): the round on a window of the
showcase names the effect hidden in the measured frame first and the error falls by at least half once it
is applied; the quick-look carries the streak and star insets at full resolution.

The showcase draws its vignetting, distortion and PSF from the ray-traced ART optics (cached on disk), so
these tests need Mitsuba (the ``mi`` fixture). The full-size demo (151 Mpixel frame + 1024 x 1024 round)
is ``slow``.
"""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits

from scenes.app.demo import HiddenRound, hidden_effect_round, insets_for, run_demo, showcase_frame, summary_lines
from scenes.app.quicklook import Inset, star_inset, streak_inset, write_png_insets
from scenes.scene import load_scene

#: a 256 x 256 window at the sensor's centre (as the demo's); the default gradient scaled by 1024 / 256 so that
#: it makes the same error as on the demo's 1024 x 1024 window (the chi2 excess grows as (gradient x side)^2)
SMALL = HiddenRound(width=256, height=256, params={"gx_e_per_s_per_kpx": -32.0, "gy_e_per_s_per_kpx": 24.0},
                    seed=11)


def _error(chi2_per_dof: float) -> float:
    """The error of a frame: chi2/dof - 1 (0 for a model that explains the frame to its noise)."""
    return chi2_per_dof - 1.0


def test_showcase_is_a_valid_full_frame_scene_with_what_the_brief_lists():
    sc = load_scene("showcase")
    s = sc.sensor()
    assert s.output_shape == (10640, 14192)  # the full IMX411, no binning
    assert sc.telescope.design == "art" and sc.telescope.distortion == "optics"
    assert sc.sky.stars and sc.exposure.tracking == "sidereal" and 2.0 <= sc.exposure.time_s <= 5.0
    assert sc.effects["vignetting"]["map_file"] == "optics"
    for name in ("hot_pixels", "cosmic_rays", "prnu", "dsnu", "amp_glow"):
        assert name in sc.effects
    assert len(sc.objects) == 1 and "rate_ra_deg_s" in sc.objects[0]
    # the round's hidden effect is one the showcase lacks
    assert HiddenRound().hidden not in sc.effects
    # the default scene is untouched: an empty sky
    assert not load_scene("default").sky.stars


def test_insets_are_picked_from_the_truth_table():
    truth = np.zeros(4, dtype=[("x", "f8"), ("y", "f8"), ("x0", "f8"), ("y0", "f8"), ("x1", "f8"), ("y1", "f8"),
                               ("flux_e", "f8"), ("kind", "S9"), ("mag", "f8"), ("name", "S32")])
    truth["kind"] = [b"object", b"star", b"star", b"star"]
    truth["name"][0] = b"debris"
    truth["x0"][0], truth["y0"][0], truth["x1"][0], truth["y1"][0] = 100, 100, 900, 500
    truth["x"][1:], truth["y"][1:] = [700, 300, 320], [200, 700, 710]
    truth["flux_e"] = [1e6, 5e4, 9e4, 1e3]
    truth["mag"][1:] = [11.0, 10.5, 15.0]
    s = streak_inset(truth, (800, 1000), half_px=50, at=0.5)
    assert (s.x0, s.y0, s.x1, s.y1) == (450, 250, 550, 350)  # centred on the path's midpoint (500, 300)
    assert "894 px long" in s.label  # |(800, 400)|
    # star 3 is 1.1 % of star 2 within 60 px: star 2 is not isolated, so the fainter isolated star 1 is picked
    t = star_inset(truth, (800, 1000), half_px=10, avoid=s)
    assert (t.x0 + t.x1) / 2 == 700 and (t.y0 + t.y1) / 2 == 200
    # ... unless the brighter one's neighbour is fainter than 1 %
    truth["flux_e"][3] = 500.0
    assert star_inset(truth, (800, 1000), half_px=10, avoid=s).x0 == 290
    # a box near the edge is shifted inside the frame
    truth["x0"][0], truth["x1"][0] = 0, 0
    assert streak_inset(truth, (800, 1000), half_px=50).x0 == 0


def test_quicklook_with_insets_has_the_right_size(tmp_path):
    img = np.random.default_rng(1).normal(1000, 10, (600, 800)).astype(np.float32)
    img[300:304, 100:700] += 500  # a streak
    fits.PrimaryHDU(img).writeto(tmp_path / "f.fits")
    insets = [Inset("streak", 350, 250, 450, 350), Inset("star", 10, 10, 42, 42, color="tab:cyan", percentile=100)]
    png = write_png_insets(tmp_path / "f.fits", tmp_path / "f.png", insets, width_in=10.0, dpi=100)
    import matplotlib.image as mpimg

    h, w = mpimg.imread(png).shape[:2]
    main_w = 10.0 * 2 / (2 + 600 / 800)  # the main panel's width: the inset column as tall as it
    assert w == 1000 and h == round((main_w * 600 / 800 + 0.7) * 100)


def test_cli_window_that_does_not_fit_is_one_line_and_exit_2_before_any_render(tmp_path):
    out = tmp_path / "out"
    p = subprocess.run([sys.executable, "-m", "scenes.app.cli", "demo", "-o", str(out), "--window", "20000"],
                       check=False, capture_output=True, text=True, timeout=120)
    assert p.returncode == 2
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and "detector.x0" in lines[0] and "showcase.toml" in lines[0], p.stderr
    assert not out.exists()  # nothing written


@pytest.fixture(scope="module")
def small_round(tmp_path_factory):
    pytest.importorskip("mitsuba", reason="Mitsuba 3 is not installed: the showcase's optics are ray-traced")
    from optics.llvm import init_mitsuba

    init_mitsuba()
    out = tmp_path_factory.mktemp("demo_round")
    return out, hidden_effect_round(out, SMALL)


def test_round_names_the_hidden_effect_first_and_the_error_halves(small_round):
    out, r = small_round
    assert r["named_first"] == SMALL.hidden and r["named_first_significant"], r["ranking"]
    assert r["delta_bic"] < -10
    # the fitted gradient is the hidden one (to 15 %: the stars and the streak share the window)
    for k, v in SMALL.params.items():
        assert r["fitted_params"][k] == pytest.approx(v, rel=0.15), r["fitted_params"]
    # the window is centred on the sensor, where the plane adds no mean light
    assert r["window"] == {"width": 256, "height": 256, "x0": 7096 - 128, "y0": 5320 - 128}
    assert r["applied"]["effect"] == SMALL.hidden
    assert _error(r["chi2_per_dof_before"]) > 0.3
    assert _error(r["chi2_per_dof_after"]) <= 0.5 * _error(r["chi2_per_dof_before"]), r
    # the files of the round: the measured frame, the diagnosis JSON, the report, the applied scene
    for key in ("measured", "diagnosis", "report", "applied_scene", "applied_report"):
        assert (out / r["files"][key].split("/")[-1]).is_file(), key
    js = json.loads((out / "round_diagnosis.json").read_text())
    assert js["candidates"][0]["effect"] == SMALL.hidden and js["demo"]["hidden"] == SMALL.hidden
    assert SMALL.hidden in load_scene(r["files"]["applied_scene"]).effects
    lines = summary_lines(None, r)
    assert lines[0].startswith(f"hidden in the measured frame: {SMALL.hidden}")
    assert lines[1].startswith(f"diagnose names: {SMALL.hidden} (delta BIC -")
    assert "after --apply" in lines[2]


def test_showcase_window_quicklook_has_the_streak_and_a_star(small_round, tmp_path):
    # a 2048 x 1024 window of the showcase about the streak, rendered by the demo's own frame step
    sets = ["detector.width=2048", "detector.height=1024", "detector.x0=3800", "detector.y0=3400",
            "sky.star_mag_limit=13"]
    summary = showcase_frame(tmp_path, overrides=sets)
    assert summary["sources"]["objects"] == 1 and summary["sources"]["stars"] > 5
    # the stars on the frame, split into the catalogue's (Gaia) and the faint-star model's
    src = summary["sources"]
    assert src["catalogue_stars"] > 0 and src["catalogue_stars"] + src["model_stars"] == src["stars"]
    labels = [i["label"] for i in summary["insets"]]
    assert labels[0].startswith("streak: debris") and labels[1].startswith("star")
    import matplotlib.image as mpimg

    h, w = mpimg.imread(summary["png"]).shape[:2]
    assert w == 1430 and 500 < h < 1000  # 13 in x 110 dpi; the height follows the window's aspect
    # the streak inset holds the streak: its median is above the frame's
    with fits.open(summary["path"]) as hd:
        data = hd[0].data.astype(float)
    s = summary["insets"][0]
    assert np.percentile(data[s["y0"]:s["y1"], s["x0"]:s["x1"]], 99) > np.percentile(data, 99)
    assert [vars(i) for i in insets_for(summary["path"])] == summary["insets"]


@pytest.mark.slow
def test_full_demo(tmp_path, mi):
    res = run_demo(tmp_path)
    assert res["frame"]["shape"] == [10640, 14192]
    assert (tmp_path / "demo.fits").is_file() and (tmp_path / "demo.png").is_file()
    r = res["round"]
    assert r["named_first"] == r["hidden"]
    assert _error(r["chi2_per_dof_after"]) <= 0.5 * _error(r["chi2_per_dof_before"])
    assert len(res["lines"]) == 4


def test_the_frame_line_names_catalogue_and_model_stars_as_the_readme_does():
    """README's demo output: "11059 stars (235 Gaia catalogue, 10824 faint-star model)", not 11,059 "catalogue
    stars" (235 are Gaia stars, 10,824 stars of the seeded faint-star model)."""
    frame = {"path": "out/demo.fits", "shape": [10640, 14192], "exptime_s": 3.0, "png": "out/demo.png",
             "sources": {"stars": 11059, "objects": 1, "catalogue_stars": 235, "model_stars": 10824}}
    line = summary_lines(frame, None)[0]
    readme = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    assert "11059 stars (235 Gaia catalogue, 10824 faint-star model)" in line and line in readme
