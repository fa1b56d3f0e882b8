"""newtsim compare / diagnose: a frame of the scene itself is explained to the noise; a hidden bias gradient
is named, fitted, applied, and the error falls; the JSON keeps the contract; the HTML report is one
self-contained file; bad measured frames and broken plugins give clear messages, never a traceback."""

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits
from click.testing import CliRunner
from helpers import SMALL_SKY_TOML, STREAK_TOML, star_field_toml

from detector import Effect, EffectParams, Stage, register_effect
from detector.effects import base as effects_base
from detector.errors import DetectorError
from detector.jsonable import jsonable
from detector.signatures import Signature
from scenes.app.cli import cli
from scenes.app.compare import run_compare, run_diagnose
from scenes.app.compare.report import write_report
from scenes.app.render import render
from scenes.scene import load_scene

# ML11002 (CCD) window of 512 x 512 around the pointing: two catalogue stars, faint model stars, one streak
SCENE = star_field_toml(512, STREAK_TOML)

BIAS_GRADIENT = {"gradient_x_adu": 150.0, "gradient_y_adu": -80.0}

# a small frame without sources for the error paths
SMALL = SMALL_SKY_TOML


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """Scene files and measured frames (rendered once for the module)."""
    d = tmp_path_factory.mktemp("compare")
    (d / "scene.toml").write_text(SCENE)
    table = "\n".join(f"{k} = {v}" for k, v in BIAS_GRADIENT.items())
    (d / "truth_bias.toml").write_text(SCENE + f"[effects.bias_gradient]\n{table}\n")
    (d / "small.toml").write_text(SMALL)
    render(load_scene(str(d / "scene.toml")), d / "noise.fits", seed=5)
    render(load_scene(str(d / "truth_bias.toml")), d / "bias.fits", seed=11)
    render(load_scene(str(d / "small.toml")), d / "small.fits", seed=3)
    return d


def invoke(*args):
    result = CliRunner().invoke(cli, [str(a) for a in args])
    assert "Traceback" not in (result.stderr or "")
    return result


def sigma_chi2(n: int) -> float:
    """Standard deviation of chi2/dof for n degrees of freedom."""
    return math.sqrt(2.0 / n)


# --- a frame with no hidden effect -------------------------------------------------------------------------------

def test_frame_of_the_scene_itself_is_explained_by_its_noise(frames, tmp_path):
    out = run_diagnose(load_scene(str(frames / "scene.toml")), frames / "noise.fits")
    base = out["baseline"]
    n = base["n_compared"]
    assert n > 0.99 * base["n_pixels"]
    assert abs(base["chi2_per_dof"] - 1) < 3 * sigma_chi2(n), base["chi2_per_dof"]
    assert base["misfit"] < 5
    # the contract: a frame with no hidden effect gives no significant candidate
    assert out["candidates"] and not out["significant"]
    assert all(c["delta_bic"] >= -10 for c in out["candidates"])
    assert "no missing effect" in out["verdict"]
    # every region agrees with the noise (12 overlapping regions: 5 sigma each)
    for name, r in base["regions"].items():
        assert abs(r["chi2_per_dof"] - 1) < 5 * sigma_chi2(r["n"]), (name, r)
    # measurement and model realisation: same level and scatter
    cmp = out["_compare"]
    m, mo = cmp["measured"], cmp["model"]
    assert abs(m["median"] - mo["median"]) < 0.1 * mo["robust_std"]
    assert abs(m["robust_std"] / mo["robust_std"] - 1) < 0.02
    # sources: the catalogue stars and the streak carry the model's flux and position
    assert cmp["stars"]["n"] >= 1
    assert abs(cmp["stars"]["median_flux_ratio"] - 1) < 0.02
    assert cmp["stars"]["median_offset_px"] < 0.1
    assert len(cmp["streaks"]) == 1 and abs(cmp["streaks"][0]["total_flux_ratio"] - 1) < 0.02
    # the outlier counts of data and model agree
    assert all(v["deviance"] < 10 for v in cmp["outliers"].values())
    # white residuals: flat power spectrum at 1, z distribution close to the unit normal
    assert abs(np.nanmedian(cmp["power"]["radial"]) - 1) < 0.15
    assert abs(cmp["distribution"]["skew"]) < 0.05 and abs(cmp["distribution"]["kurtosis"]) < 0.1
    # the report says so, and still shows where the residuals are largest
    page = write_report(cmp, tmp_path / "r.html", diagnosis=out).read_text()
    assert "no missing effect was found" in page and "Largest residuals" in page
    assert 'class="verdict ok"' in page


# --- the command line: compare ----------------------------------------------------------------------------------

def _check_self_contained_report(page: str) -> None:
    assert page.lstrip().lower().startswith("<!doctype html>") and page.rstrip().endswith("</html>")
    assert "chi2" in page and "data:image/png;base64" in page
    # self-contained: every image is embedded, nothing is fetched
    srcs = re.findall(r'(?:src|href)="([^"#][^"]*)"', page)
    assert srcs and all(s.startswith("data:image/png;base64,") for s in srcs), srcs[:3]
    assert "<link" not in page and "<script" not in page
    for section in ("zmap", "regions", "profiles", "power", "distribution", "adu", "stats", "outliers",
                    "stars", "streaks"):
        assert f'id="{section}"' in page, section
    assert "could not be drawn" not in page
    assert "block mean of" in page and "median" in page and "robust std" in page


def test_cli_compare_writes_the_contract_json_and_a_self_contained_report(frames, tmp_path):
    js, rep = tmp_path / "c.json", tmp_path / "c.html"
    r = invoke("compare", frames / "scene.toml", frames / "noise.fits", "--json", js, "--report", rep)
    assert r.exit_code == 0, r.output
    assert "chi2/dof" in r.stderr
    data = json.loads(js.read_text())
    assert math.isfinite(data["chi2_per_dof"]) and abs(data["chi2_per_dof"] - 1) < 0.02
    assert {"centre", "edges", "corners", "quadrant_lower_left", "radial_4"} <= set(data["regions"])
    for reg in data["regions"].values():
        assert {"n", "chi2_per_dof", "mean_z", "mean_residual_adu"} <= set(reg)
    assert data["report"] == str(rep)
    _check_self_contained_report(rep.read_text())
    # global statistics of measurement and model (the contract; the thesis's Annex VII columns)
    for who in ("measured", "model"):
        assert isinstance(data[who], dict), f"JSON key {who!r} is {data[who]!r}, not the statistics"
        for key in ("median", "mean", "std", "robust_std"):
            assert math.isfinite(data[who][key]), (who, key)
    assert abs(data["measured"]["robust_std"] / data["model"]["robust_std"] - 1) < 0.02


# --- the command line: diagnose, apply, ledger --------------------------------------------------------------------

def test_hidden_bias_gradient_is_named_applied_and_the_error_falls(frames, tmp_path):
    measured = (frames / "bias.fits").resolve()
    new, js1, js2, rep = tmp_path / "round2.toml", tmp_path / "d1.json", tmp_path / "d2.json", tmp_path / "d1.html"
    r = invoke("diagnose", frames / "scene.toml", measured, "--json", js1, "--apply", new, "--report", rep)
    assert r.exit_code == 0, r.output
    d1 = json.loads(js1.read_text())
    best = d1["candidates"][0]
    assert best["effect"] == "bias_gradient" and best["delta_bic"] < -10 and best["significant"]
    for key, value in BIAS_GRADIENT.items():
        assert abs(best["params"][key] / value - 1) < 0.15, (key, best["params"])
    assert "bias_gradient" in d1["verdict"]
    # the new scene loads and carries the fitted effect
    assert "[effects.bias_gradient]" in new.read_text()
    sc = load_scene(str(new))
    assert "bias_gradient" in sc.effects
    assert sc.effects["bias_gradient"]["gradient_x_adu"] == pytest.approx(best["params"]["gradient_x_adu"])
    page = rep.read_text()
    assert 'id="diagnosis"' in page and "bias_gradient" in page and 'class="sig"' in page
    assert 'id="ledger"' in page
    # round 2: the error falls by more than half
    r = invoke("diagnose", new, measured, "--json", js2)
    assert r.exit_code == 0, r.output
    d2 = json.loads(js2.read_text())
    before, after = d1["baseline"]["chi2_per_dof"], d2["baseline"]["chi2_per_dof"]
    assert before - 1 > 10 * sigma_chi2(d1["baseline"]["n_compared"])
    assert abs(after - 1) <= 0.5 * (before - 1), (before, after)
    assert d2["baseline"]["misfit"] < 0.1 * d1["baseline"]["misfit"]
    assert not d2["significant"]
    # the ledger: two rounds of this measurement, the first one adding the bias gradient
    ledger = json.loads(Path(d2["ledger"]["path"]).read_text())
    assert len(ledger["rounds"]) == 2 == len(d2["ledger"]["rounds"])
    first, second = ledger["rounds"]
    assert first["applied"] == "bias_gradient" and second["applied"] is None
    assert first["chi2_per_dof"] == pytest.approx(before) and second["chi2_per_dof"] == pytest.approx(after)


# --- bad input -------------------------------------------------------------------------------------------------

def _write(path, data):
    fits.writeto(path, np.asarray(data), overwrite=True)
    return path


def test_measured_frame_of_the_wrong_size_is_one_line_naming_file_and_size(frames):
    r = invoke("compare", frames / "small.toml", frames / "noise.fits")
    assert r.exit_code == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert "noise.fits" in lines[0] and "512x512" in lines[0] and "expected 256x256" in lines[0]


@pytest.mark.parametrize("case, needle", [
    ("missing", "not found"),
    ("constant", "constant"),
    ("saturated_adc", "saturated"),
    ("all_at_adc_max", "(constant|saturated)"),
])
def test_unusable_measured_frames_give_a_clear_error(frames, tmp_path, case, needle):
    good = fits.getdata(frames / "small.fits").astype(np.int64)
    rng = np.random.default_rng(1)
    path = tmp_path / f"{case}.fits"
    if case == "constant":
        _write(path, np.full(good.shape, 1000, np.uint16))
    elif case == "saturated_adc":  # 90 % of the pixels at the ADC maximum
        _write(path, np.where(rng.random(good.shape) < 0.9, 65535, good).astype(np.uint16))
    elif case == "all_at_adc_max":
        _write(path, np.full(good.shape, 65535, np.uint16))
    r = invoke("compare", frames / "small.toml", path)
    assert r.exit_code == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and path.name in lines[0] and re.search(needle, lines[0]), r.stderr


def test_frame_saturated_at_the_full_well_gives_a_clear_error(frames, tmp_path):
    path = tmp_path / "overexposed.fits"
    render(load_scene(str(frames / "small.toml"), ["sky.flat_e_per_s=1e6"]), path, seed=4)
    with pytest.raises(DetectorError, match="saturated"):
        run_compare(load_scene(str(frames / "small.toml")), path)


_BROKEN = "_test_broken_signature"


class _RaisingSignature(Signature):
    def fit(self, res, name):
        raise RuntimeError("this plugin's signature is broken")


def test_a_plugin_whose_signature_raises_is_listed_and_the_diagnosis_completes(frames, tmp_path):
    @register_effect
    class Broken(Effect):
        name = _BROKEN
        stages = (Stage.ADU,)
        Params = EffectParams
        signature = _RaisingSignature()

        def apply(self, stage, tile, data):
            pass

    try:
        js = tmp_path / "d.json"
        r = invoke("diagnose", frames / "small.toml", frames / "small.fits", "--json", js)
        assert r.exit_code == 0, r.output
        out = json.loads(js.read_text())
        problems = {p["effect"]: p["error"] for p in out["problems"]}
        assert "RuntimeError" in problems[_BROKEN] and "broken" in problems[_BROKEN]
        assert out["candidates"] and _BROKEN not in [c["effect"] for c in out["candidates"]]
        assert "bias_gradient" in [c["effect"] for c in out["candidates"]]
        assert not out["significant"] and "no missing effect" in out["verdict"]
    finally:
        effects_base._REGISTRY.pop(_BROKEN, None)
    assert _BROKEN not in effects_base._REGISTRY


# --- the report on its own ------------------------------------------------------------------------------------------

def test_report_survives_a_json_round_trip_missing_parts_and_nans(frames, tmp_path):
    cmp = run_compare(load_scene(str(frames / "small.toml")), frames / "small.fits")
    assert cmp["stars"]["n"] == 0 and cmp["streaks"] == []
    plain = json.loads(json.dumps(jsonable({k: v for k, v in cmp.items() if not k.startswith("_")})))
    plain["z_map"][0][0] = None  # NaN after the round trip
    plain["profiles"]["row"]["chi2_per_dof"] = None
    plain["distribution"].pop("model_hist")
    page = write_report(plain, tmp_path / "plain.html", title="round trip").read_text()
    assert "<title>round trip</title>" in page and "data:image/png;base64" in page
    assert "could not be drawn" not in page
    assert 'id="stars"' not in page and 'id="streaks"' not in page and 'id="diagnosis"' not in page
    assert 'id="zmap"' in page and 'id="stats"' in page
    # almost nothing: still a page, which says that nothing could be compared
    page = write_report({"chi2_per_dof": float("nan"), "n_compared": 0}, tmp_path / "empty.html").read_text()
    assert "No pixel could be compared" in page and 'class="verdict bad"' in page
    with pytest.raises(DetectorError, match="no_such_dir"):
        write_report(plain, tmp_path / "no_such_dir" / "r.html")
