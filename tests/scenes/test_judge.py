"""The one judge of the diagnosis (issue 23): its policy, its gates, the scene's parameters first, the floors,
and the three paths (single frame, large frame, series) sharing it.

The frames with a wrong number of the scene are made by the independent textbook camera chain
(../shared/tools/textbook_chain.py: Poisson, read noise, gain, bias, rounding; it shares no code with
newtsim) from ``newtsim render --noiseless`` of the scene with that number changed; the diagnosis runs
against the scene with the number it states.
"""

from __future__ import annotations

import json
import runpy
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits
from helpers import gaussian_stars, residuals_of, star_field_toml, write_scene

from detector import DetectorError
from detector.signatures import Fit
from scenes.app.compare import fullframe, judge, run, series
from scenes.app.compare.floors import FLOORS, floor_reason
from scenes.app.compare.judge import GATES, Candidate, gate_reasons, rank, verdict
from scenes.app.compare.policy import (
    AUDIT_MARKER,
    DEFAULT_POLICY,
    DOC_PATH,
    DiagnosisPolicy,
    load_policy,
    markdown_table,
)
from scenes.app.render import render
from scenes.scene import load_scene

TEXTBOOK = Path(__file__).resolve().parents[3] / "shared" / "tools" / "textbook_chain.py"


def textbook_frame(scene_path: Path, out: Path, seed: int, sets: list[str] | None = None) -> Path:
    """A measured frame from the textbook chain: the scene's (with ``sets``) noiseless render, drawn."""
    if not TEXTBOOK.is_file():
        pytest.skip(f"the independent textbook chain is absent ({TEXTBOOK})")
    chain = runpy.run_path(str(TEXTBOOK))
    mu = out.with_name(out.stem + "_mu.fits")
    render(load_scene(str(scene_path), sets or []), mu, seed=seed, noiseless=True, progress=False)
    with fits.open(mu) as hl:
        hdu = next(h for h in hl if h.data is not None and h.data.ndim == 2)
        data = chain["measure"](hdu.data, hdu.header, seed)
        hdr = hdu.header.copy()
    for k in ("BSCALE", "BZERO", "BUNIT", "NOISELES"):
        hdr.remove(k, ignore_missing=True)
    fits.PrimaryHDU(data, header=hdr).writeto(out, overwrite=True)
    return out


# --- the policy ---------------------------------------------------------------------------------------------

def test_policy_fields_documented_and_docs_current():
    table = markdown_table()
    for name, value in DEFAULT_POLICY.to_json().items():
        assert f"`{name}`" in table and isinstance(value, (int, float))
    head = DOC_PATH.read_text().partition(AUDIT_MARKER)[0]  # the generated threshold audit follows the table
    assert head.rstrip("\n") == table.rstrip("\n"), \
        "docs/diagnosis_policy.md is stale: python -m scenes.app.compare.policy"
    assert DEFAULT_POLICY.significant_delta_bic == -10.0  # the DESIGN contract


def test_policy_file_overrides_and_errors(tmp_path):
    p = tmp_path / "p.toml"
    p.write_text("[policy]\nsignificant_delta_bic = -25\nheldout_candidates = 4\n")
    pol = load_policy(p)
    assert pol.significant_delta_bic == -25.0 and pol.heldout_candidates == 4
    assert pol.min_explained == DEFAULT_POLICY.min_explained
    (tmp_path / "bad.toml").write_text("significant_bic = -25\n")
    with pytest.raises(DetectorError) as e:
        load_policy(tmp_path / "bad.toml")
    assert "bad.toml" in str(e.value) and "significant_bic" in str(e.value) and "significant_delta_bic" in str(e.value)
    (tmp_path / "bad2.json").write_text(json.dumps({"heldout_candidates": 2.5}))
    with pytest.raises(DetectorError, match="whole number"):
        load_policy(tmp_path / "bad2.json")



def test_retired_policy_fields_still_load_with_a_warning(tmp_path):
    """A policy file (or a ``policy`` table of an older ``diagnose --json``) naming a field that a test's own
    statistic replaced still loads: the field is ignored with a warning saying what replaced it."""
    from scenes.app.compare.policy import RETIRED

    assert {"stars_min", "stars_ok_ln", "psf_min_stars", "noise_floor_fraction"} <= set(RETIRED)
    for key in RETIRED:
        assert key not in DEFAULT_POLICY.to_json()
        (tmp_path / f"{key}.json").write_text(json.dumps({"policy": {key: 1, "heldout_candidates": 4}}))
        with pytest.warns(UserWarning, match=key):
            pol = load_policy(tmp_path / f"{key}.json")
        assert pol.heldout_candidates == 4

# --- the gates ----------------------------------------------------------------------------------------------

def _cand(name="x", d=-100.0, heldout=None, **kw) -> Candidate:
    return Candidate(Fit(name, {}, d, 1, 10_000, "why"), 1.0, 0.0, heldout=heldout, **kw)


def test_gates_name_every_refusal_and_follow_the_policy():
    assert _cand(d=-100).gates == []
    assert _cand(d=-5).gates == ["bic"]
    strict = DiagnosisPolicy(significant_delta_bic=-200.0)
    assert _cand(d=-100, policy=strict).gates == ["bic"]
    c = _cand(heldout=-50.0, explains=0.2)
    assert c.gates == ["structure"] and not c.significant
    c = _cand(heldout=+3.0)
    assert c.gates == ["heldout"]
    c = _cand(heldout=-45.0, catch_all_heldout=-100.0)  # predicts 45 % of what the description does
    assert c.gates == ["catch_all"]
    c = _cand(heldout=-80.0, catch_all_heldout=-100.0)
    assert c.gates == []
    c = _cand()
    c.refuse("floor", "too small")
    c.reject("overfit", "hides")
    assert set(c.gates) == {"floor", "overfit"} and all(g in GATES for g in c.gates)
    j = c.to_json()
    assert j["kind"] == "effect" and j["gates"] == c.gates and "catch_all_delta" in j and not j["significant"]


def test_parameters_rank_before_effects_and_carry_key_and_value():
    eff = _cand("vignetting", d=-1e4, heldout=-9e3)
    par = Candidate(Fit("zero_point", {}, -50.0, 1, 10_000, "the sources are x 1.6"), 1.0, 0.0, kind="parameter",
                    key="sky.source_flux_scale", value=1.6)
    out = rank([eff, par])
    assert out[0] is par and out[1] is eff
    j = par.to_json()
    assert j["kind"] == "parameter" and j["key"] == "sky.source_flux_scale" and j["value"] == 1.6
    assert "sky.source_flux_scale -> 1.6" in verdict(out) and "vignetting" in verdict(out)
    par.codes["tolerance"] = "within"
    assert not par.significant and par.gates == ["tolerance"]
    assert verdict(rank([eff, par])).startswith("most likely missing: vignetting")


def test_three_paths_share_one_judge():
    """The single-frame, large-frame and series paths rank, judge and describe with the same functions, so
    the same evidence gets the same verdict whichever path made it."""
    for mod in (run, fullframe, series):
        assert mod.rank is judge.rank and mod.verdict is judge.verdict and mod.judge_json is judge.judge_json
    cands = [_cand("a", d=-300, heldout=-200), _cand("b", d=-400, heldout=-5.0), _cand("c", d=-2)]
    ranked = rank(cands)
    assert [c.fit.effect for c in ranked] == ["a", "b", "c"]
    out = judge.judge_json(ranked, DEFAULT_POLICY)
    assert out["significant"] == ["a"] and out["policy"]["significant_heldout"] == DEFAULT_POLICY.significant_heldout
    assert set(out["gate_codes"]) == set(GATES)
    assert gate_reasons(ranked[1])[0][0] == "heldout"


def test_a_residual_that_scales_with_the_light_refuses_added_fields():
    """A multiplicative residual (a certain finding of the morphology) is no added light, charge or bias
    pattern: those are refused with the ``kind`` gate; a response (vignetting) and the parameters are not; an
    uncertain or additive morphology refuses nothing (additive is the absence of a finding)."""
    mult = {"significant": True, "kind": "multiplicative", "kind_certain": True}
    for m, refused in ((mult, True), ({**mult, "kind_certain": False}, False),
                       ({**mult, "kind": "additive"}, False), ({**mult, "significant": False}, False)):
        cands = [_cand(n, d=-1e4, heldout=-9e3) for n in ("straylight", "sky_gradient", "bias_gradient",
                                                          "dark_gradient", "amp_glow", "vignetting", "prnu")]
        judge.kind_gate(cands, m)
        got = {c.fit.effect for c in cands if "kind" in c.gates}
        assert got == ({"straylight", "sky_gradient", "bias_gradient", "dark_gradient", "amp_glow"} if refused else set())
    out = rank(cands)
    assert out[0].fit.effect in ("straylight", "vignetting")
    c = [_cand("straylight", d=-1e4, heldout=-9e3), _cand("vignetting", d=-9e3, heldout=-5e3)]
    judge.kind_gate(c, mult)
    assert rank(c)[0].fit.effect == "vignetting" and "kind" in GATES
    for mod in (run, fullframe, series):
        assert mod.kind_gate is judge.kind_gate


# --- the physical floors ------------------------------------------------------------------------------------

def test_floors(tmp_path):
    sensor = load_scene(str(write_scene(tmp_path / "s.toml", detector={"preset": "imx411", "width": 256,
                                                                        "height": 256}))).sensor()
    assert set(FLOORS) >= {"nonlinearity", "hot_pixels", "dead_pixels", "column_defects", "cosmic_rays"}
    assert "at full well" in floor_reason("nonlinearity", {"beta": 2.4e-4}, sensor)  # the flat series' 0.024 %
    assert floor_reason("nonlinearity", {"beta": 0.01}, sensor) == ""
    assert "columns" in floor_reason("column_defects", {"hot_columns": 1802, "dead_columns": 2966}, sensor)
    assert floor_reason("column_defects", {"hot_columns": 3, "dead_columns": 1}, sensor) == ""
    assert "less than one electron" in floor_reason("column_defects", {"hot_columns": 172, "hot_rate_e_per_s": 0.0,
                                                                       "dead_columns": 0}, sensor, exptime_s=10.0)
    assert floor_reason("column_defects", {"hot_columns": 8, "hot_rate_e_per_s": 0.08, "dead_columns": 0}, sensor,
                        exptime_s=300.0) == ""
    assert "not cosmic rays" in floor_reason("cosmic_rays", {"flux_per_cm2_s": 100 / 60}, sensor)
    assert floor_reason("cosmic_rays", {"flux_per_cm2_s": 2 / 60}, sensor) == ""
    assert floor_reason("hot_pixels", {"count": 0.1 * 14192 * 10640}, sensor) != ""
    # a window's defects are a count: 17 of its 256 columns (6.6 %, 943 on the sensor) is what a sensor of 5 %
    # defective columns shows about once in seven windows (binomial); 60 of 256 (23 %) no camera shows
    assert floor_reason("column_defects", {"hot_columns": 943, "hot_rate_e_per_s": 0.1, "dead_columns": 0}, sensor,
                        exptime_s=300.0) == ""
    assert "from the window's count" in floor_reason("column_defects", {"hot_columns": 3326, "dead_columns": 0},
                                                      sensor)
    assert floor_reason("vignetting", {"a2": 0.3}, sensor) == ""
    # the textbook null's kTC of 1.07e-13 fF (4e-6 e-) is no finding; a 1 fF node's 12 e- is
    assert "read noise" in floor_reason("reset_noise", {"capacitance_ff": 1.0661e-13}, sensor)
    assert floor_reason("reset_noise", {"capacitance_ff": 1.0}, sensor) == ""


def test_a_response_law_is_judged_within_the_frames_signal_range():
    """A non-linearity is judged by what it changes between the frame's median and its 99.9th percentile
    signal (per sensor pixel), not by its size extrapolated to full well: on a uniform dark of 67 e- (a
    133 000 e- well, the real SBIG dark that a gamma of 1.027 once 'fitted') nothing is measured; a gamma law
    compresses every decade of signal alike, so on a star frame reaching 3.6 % of the well (sky 100 e-, peaks
    2870 e- of 80 000) a gamma of 0.995 changes the response by 1.7 % there and is measured, while a quadratic
    deficit of 1 % at full well changes it by 0.035 % and is not. Sum binning: charge per sensor pixel."""
    from types import SimpleNamespace

    from scenes.app.compare.floors import response_ratio, signal_range_floor

    def res(photo_adu, dark_e, pixel_sum=1, fw=133_000.0):
        photo = np.broadcast_to(np.asarray(photo_adu, np.float32), (64, 64))
        return SimpleNamespace(fit=np.ones((64, 64), bool), photo_adu=photo,
                               dark_e=np.full((64, 64), dark_e, np.float32), gain=1.5, pixel_sum=pixel_sum,
                               sensor=SimpleNamespace(full_well_e=fw))

    gamma = {"gamma": 1.027, "gamma_reference": 67.0 / 133_000}
    assert "extrapolation" in signal_range_floor("nonlinearity", res(0.0, 67.0), params=gamma)
    assert signal_range_floor("prnu", res(0.0, 67.0), params=gamma) == ""
    # stars: 99.8 % of the pixels at the sky's 100 e-, the brightest 0.2 % at 2870 e- (3.6 % of an 80 000 e- well)
    light_e = np.full(64 * 64, 100.0)
    light_e[:9] = 2870.0
    stars = res(light_e.reshape(64, 64) / 1.5, 0.0, fw=80_000.0)
    g = {"gamma": 0.995, "gamma_reference": 100.0 / 80_000}
    change = float(response_ratio(g, 2870 / 80_000) / response_ratio(g, 100 / 80_000) - 1)
    assert abs(change - (28.7 ** -0.005 - 1)) < 1e-9  # the power law: (top / median)^(gamma - 1) - 1, -1.7 %
    assert signal_range_floor("nonlinearity", stars, params=g) == ""
    assert "extrapolation" in signal_range_floor("nonlinearity", stars, params={"beta": 0.01})
    # binned 4x4 (sum): 16 pixels' charge in one output pixel is judged per sensor pixel
    assert signal_range_floor("nonlinearity", res(light_e.reshape(64, 64) * 16 / 1.5, 0.0, pixel_sum=16, fw=80_000.0),
                              params=g) == ""


# --- the scene's numbers, on textbook frames -------------------------------------------------------------------

@pytest.fixture(scope="module")
def star_scene(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("judge_stars")
    p = d / "stars.toml"
    p.write_text(star_field_toml(384))
    return p


def _first(out: dict) -> dict:
    return next(c for c in out["candidates"] if c["significant"])


@pytest.fixture(scope="module")
def zero_point_round(star_scene):
    """A textbook frame whose sources are 1.6 x the scene's, and its diagnosis (made once: the zero-point test
    reads it, the apply test applies it)."""
    meas = textbook_frame(star_scene, star_scene.with_name("zp.fits"), 5, ["sky.source_flux_scale=1.6"])
    return meas, run.run_diagnose(load_scene(str(star_scene)), meas)


def test_zero_point_named_first_with_its_value(zero_point_round):
    _, out = zero_point_round
    first = _first(out)
    assert first["kind"] == "parameter" and first["key"] == "sky.source_flux_scale"
    assert first["value"] == pytest.approx(1.6, rel=0.05)
    assert out["policy"] == DEFAULT_POLICY.to_json()
    # the sky, which the frame has right, is not named
    assert "sky_level" not in out["significant"]


def _without_seconds(x):
    if isinstance(x, dict):
        return {k: _without_seconds(v) for k, v in x.items() if k != "seconds" and not k.startswith("_")}
    if isinstance(x, list):
        return [_without_seconds(v) for v in x]
    return x


def test_fits_made_in_threads_give_the_same_diagnosis(star_scene):
    """The signatures, the held-out scores and the catch-all's two folds fitted two at a time, and the residual's
    description made while the scene's parameters are fitted, give the bytes they give one after another (they
    share only the residuals' memoised statistics). A wider PSF: several effects contend."""
    sc = load_scene(str(star_scene))
    meas = textbook_frame(star_scene, star_scene.with_name("threads.fits"), 9,
                          [f"psf.fwhm_arcsec={1.2 * sc.psf.fwhm_arcsec}"])
    one = run.run_diagnose(sc, meas, workers=1)
    two = run.run_diagnose(sc, meas, workers=2)
    assert json.dumps(_without_seconds(one), sort_keys=True, default=str) == \
        json.dumps(_without_seconds(two), sort_keys=True, default=str)
    assert sum(c["heldout_delta"] is not None for c in one["candidates"]) >= 2  # the threads had work to share
    assert one["catch_all_heldout"] is not None  # its two folds fitted at once, beside the parameters' fits


@pytest.mark.parametrize("on_usable", [False, True])
def test_structure_shares_in_threads_are_the_serial_ones(on_usable):
    """The shares of the frame's large-scale structure that several smooth candidates remove, computed two at a
    time, are the values computed one after another (on the fitted pixels, and on the usable ones when the
    fitted pixels leave some out: the level templates they share are gathered before the threads start);
    a pattern of single pixels is judged by no block means (None)."""
    from dataclasses import replace

    from detector import make_sensor
    from scenes.app.compare.candidates import structure_shares

    rng = np.random.default_rng(3)
    h, w = 256, 320
    yy, xx = np.mgrid[0:h, 0:w] / 256.0
    sky = 2000.0
    model = np.full((h, w), sky)
    field = 1.0 - 0.04 * ((xx - 0.6) ** 2 + (yy - 0.5) ** 2)  # a vignetting the model lacks
    data = rng.normal(model * field, np.sqrt(model + 25.0))
    sensor = make_sensor("ml11002", {"width": w, "height": h, "gain_e_per_adu": 1.0, "read_noise_e": 5.0,
                                     "bias_adu": 0})
    res = residuals_of(data, model, model + 25.0, model, sensor)
    if on_usable:
        fit = np.ones((h, w), bool)
        fit[::7, ::5] = False
        res = replace(res, usable=np.ones((h, w), bool), fit=fit, _flat={})
    deltas = [model * (field - 1), model * 0.8 * (field - 1), 30.0 * xx, -20.0 * yy * yy,
              np.where((np.arange(w) % 2 == 0)[None, :], 5.0, -5.0) * np.ones((h, 1))]

    def shares(threads):
        cands = [Candidate(Fit(f"c{i}", {}, -1000.0, 2, h * w, "why", delta_adu=d.astype(np.float32)), 1.0, 0.0)
                 for i, d in enumerate(deltas)]
        fresh = replace(res, _flat={})
        structure_shares(fresh, cands, DEFAULT_POLICY, threads)
        return [c.explains for c in cands]

    one, two = shares(1), shares(2)
    assert one == two
    assert one[0] > 0.9 and one[-1] is None, one


def test_narrower_psf_named_first_with_its_value(star_scene):
    sc = load_scene(str(star_scene))
    fwhm = sc.psf.fwhm_arcsec
    meas = textbook_frame(star_scene, star_scene.with_name("psf.fits"), 6, [f"psf.fwhm_arcsec={0.8 * fwhm}"])
    out = run.run_diagnose(sc, meas)
    first = _first(out)
    assert first["kind"] == "parameter" and first["key"] == "psf.fwhm_arcsec"
    assert first["value"] == pytest.approx(0.8 * fwhm, rel=0.05)
    # the stars' peaks look brighter under a narrower PSF: that is the PSF's doing, not the zero point's
    assert "zero_point" not in out["significant"]


def test_wider_psf_named_before_an_effect_that_widens_some_stars(star_scene):
    """A PSF too narrow at every flux is the scene's width, not a brighter-fatter widening of the bright stars
    (a real DSLR frame's route, docs/your_camera.md): whatever effect ranks best, the width keeps its
    evidence beside it in the joint fit and is named first, with its value."""
    sc = load_scene(str(star_scene))
    fwhm = sc.psf.fwhm_arcsec
    meas = textbook_frame(star_scene, star_scene.with_name("wide.fits"), 9, [f"psf.fwhm_arcsec={1.2 * fwhm}"])
    out = run.run_diagnose(sc, meas)
    first = _first(out)
    assert first["kind"] == "parameter" and first["key"] == "psf.fwhm_arcsec"
    assert first["value"] == pytest.approx(1.2 * fwhm, rel=0.05)
    width = next(c for c in out["candidates"] if c.get("key") == "psf.fwhm_arcsec")
    assert "tolerance" not in width["gates"]


def test_conditional_evidence_tells_a_width_from_a_widening_of_the_bright_stars():
    """The joint fit of two changes of the model (the parameter test beside the best effect): stars too narrow
    at every flux keep the width's change whole beside a change that widens the bright stars only (what
    brighter-fatter does), while that change keeps little beside the width; a change that is the same
    shape as another keeps nothing of its amplitude beside it."""
    from detector.sensor import make_sensor
    from scenes.app.compare.parameters import conditional_evidence

    h = w = 120
    rng = np.random.default_rng(3)
    yy, xx = np.mgrid[:h, :w]
    ys, xs = rng.uniform(8, h - 8, 40), rng.uniform(8, w - 8, 40)
    flux = 10 ** rng.uniform(3, 5.5, 40)  # e- = ADU at gain 1

    def stars(sig, bright_extra=0.0):
        img = np.zeros((h, w))
        for y, x, f in zip(ys, xs, flux):
            s = sig + bright_extra * (f > 10 ** 4.8)
            img += f * np.exp(-((yy - y) ** 2 + (xx - x) ** 2) / (2 * s * s)) / (2 * np.pi * s * s)
        return img

    sky, rn = 100.0, 3.0
    model = stars(1.5) + sky
    truth = stars(1.8) + sky
    var = model + rn ** 2
    data = truth + rng.normal(0, np.sqrt(truth + rn ** 2))
    sensor = make_sensor("ml11002", {"width": w, "height": h, "gain_e_per_adu": 1.0, "read_noise_e": rn,
                                     "bias_adu": 0})
    res = residuals_of(data, model, var, model - sky, sensor)
    width = truth - model  # the width's change
    bright = stars(1.5, 0.3) - stars(1.5)  # the bright stars widened alone
    share, left = conditional_evidence(res, bright, width)
    assert share > 0.8 and left > 1000
    share_b, _ = conditional_evidence(res, width, bright)
    assert share_b < 0.5
    same, left_same = conditional_evidence(res, 1.1 * width, width)
    assert abs(same) < 1e-6 or left_same < 1


def test_a_blur_whose_change_is_not_the_same_at_every_flux_is_refused():
    """An image-plane transform (a blur) changes every source by the same shape: refitted source by source its
    amplitude is one at every flux. A widening in proportion to each source's flux (brighter-fatter to first
    order, F^2 x a shape: Antilogus et al. 2014) fitted as a blur gives amplitudes growing as flux^1, a change of
    one size at every source (charge traps take or give) amplitudes falling as flux^-1: both refused; a widening
    of every source alike passes (detector.flux_law)."""
    from detector.sensor import make_sensor
    from scenes.app.compare.candidates import flux_law_refusal

    fluxes = np.geomspace(2e4, 4e5, 12)  # e- = ADU at gain 1
    sky, rn = 100.0, 3.0
    model = gaussian_stars(1.5, fluxes) + sky
    blur = gaussian_stars(1.8, fluxes) + sky - model  # the change a blur fit proposes: every source widened alike

    def per_source(scale):
        out = np.zeros_like(model)
        for i, f in enumerate(fluxes):
            solo = np.where(np.arange(fluxes.size) == i, f, 0.0)
            out += (gaussian_stars(1.8, solo) - gaussian_stars(1.5, solo)) * scale(f)
        return out

    h, w = model.shape
    sensor = make_sensor("ml11002", {"width": w, "height": h, "gain_e_per_adu": 1.0, "read_noise_e": rn,
                                     "bias_adu": 0})
    rng = np.random.default_rng(5)
    for change, refused in ((blur, ""), (per_source(lambda f: f / fluxes[-1]), "grows with the sources' flux"),
                            (per_source(lambda f: fluxes[0] / f), "of one size at every source")):
        truth = model + change
        data = truth + rng.normal(0, np.sqrt(truth + rn ** 2))
        res = residuals_of(data, model, model + rn ** 2, model - sky, sensor)
        fit = Fit("psf_blur", {"sigma_px": 1.0}, -1e4, 1, int(res.fit.sum()), "", delta_adu=blur.astype(np.float32))
        why = flux_law_refusal(res, fit)
        assert (why == "") == (refused == "") and refused in why, why


def test_apply_writes_the_parameters(star_scene, zero_point_round, tmp_path):
    sc = load_scene(str(star_scene))
    meas, out = zero_point_round
    new, best = run.apply_best(sc, out, tmp_path / "round2.toml", meas)
    assert best["kind"] == "parameter"
    again = load_scene(str(new))
    assert again.sky.source_flux_scale == pytest.approx(1.6, rel=0.05)
    after = run.run_diagnose(again, meas)
    assert after["baseline"]["chi2_per_dof"] < 0.5 * out["baseline"]["chi2_per_dof"]
    assert not any(c["kind"] == "parameter" for c in after["candidates"] if c["significant"])


def test_textbook_imx411_long_dark_is_clean(tmp_path):
    """Every IMX411 300 s dark of the textbook chain was named column_defects (issue 23): a third of the
    sensor's columns by 0.0003 e-/s is beyond the physical floor."""
    p = write_scene(tmp_path / "dark.toml", detector={"preset": "imx411", "width": 256, "height": 256},
                    exposure={"time_s": 300.0, "frame": "dark"})
    meas = textbook_frame(p, tmp_path / "dark.fits", 11)
    out = run.run_diagnose(load_scene(str(p)), meas)
    assert out["significant"] == [], out["verdict"]
    assert not out["residual_morphology"]["significant"]
    assert np.isfinite(out["baseline"]["chi2_per_dof"])


def test_hot_pixels_must_be_hot_in_the_users_dark(tmp_path):
    """With the user's dark in the scene, bright isolated pixels the dark does not have are not hot pixels."""
    from types import SimpleNamespace

    from scenes.app.compare.floors import hot_in_dark

    dark = np.full((64, 64), 0.02, np.float32)
    hot = [(5, 7), (20, 30), (40, 2), (60, 60)]
    for y, x in hot:
        dark[y, x] = 50.0
    fits.PrimaryHDU(dark).writeto(tmp_path / "dark.fits")
    p = write_scene(tmp_path / "s.toml", detector={"preset": "ml11002", "width": 64, "height": 64},
                    effects={"dark_map": {"path": "dark.fits"}})
    sc = load_scene(str(p))

    def res_with(points):
        idx = np.array([y * 64 + x for y, x in points])
        return SimpleNamespace(data_spikes=SimpleNamespace(single_pos_index=idx), sensor=sc.sensor(),
                               data_adu=np.zeros((64, 64), np.float32))

    assert hot_in_dark(res_with(hot), sc) == ""
    why = hot_in_dark(res_with([(1, 1), (2, 50), (33, 33), (5, 7)]), sc)
    assert "25 %" in why and "dark.fits" in why
    no_dark = load_scene(str(write_scene(tmp_path / "n.toml", detector={"preset": "ml11002", "width": 64,
                                                                         "height": 64})))
    assert hot_in_dark(res_with([(1, 1)]), no_dark) == ""


def test_empirical_apply_into_another_folder(tmp_path):
    """``diagnose --apply OUT`` with OUT in another folder than the working directory, when the answer is an
    empirical map (a residual no catalogue effect explains: a compact blob of light on a dark): the map is
    written beside OUT and the scene names it where it is (it crashed with 'calibration map file not found')."""
    import subprocess
    import sys

    p = write_scene(tmp_path / "dark.toml", detector={"preset": "ml11002", "width": 192, "height": 192},
                    exposure={"time_s": 60.0, "frame": "dark"})
    meas = textbook_frame(p, tmp_path / "dark.fits", 3)
    with fits.open(meas) as hl:
        data, hdr = hl[0].data.astype(np.float64), hl[0].header
    yy, xx = np.mgrid[0:192, 0:192]
    # a compact glow no plugin has (3 px: far finer than a smooth field of 8 x 8 cosines over the window resolves)
    data += 60.0 * np.exp(-((yy - 70) ** 2 + (xx - 120) ** 2) / (2 * 3.0 ** 2))
    fits.PrimaryHDU(np.rint(data).astype(np.uint16), header=hdr).writeto(meas, overwrite=True)
    out_dir = tmp_path / "rounds"
    out_dir.mkdir()
    work = tmp_path / "elsewhere"
    work.mkdir()
    r = subprocess.run([sys.executable, "-m", "scenes.app.cli", "diagnose", str(p), str(meas), "--apply",
                        str(out_dir / "round2.toml"), "--json", str(out_dir / "d.json")], cwd=work,
                       capture_output=True, text=True, timeout=600, check=False)
    assert r.returncode == 0, r.stderr
    d = json.loads((out_dir / "d.json").read_text())
    assert d["applied"] is not None, d["verdict"]
    new = load_scene(str(out_dir / "round2.toml"))
    maps = [t["path"] for t in new.effects.values() if isinstance(t, dict) and "path" in t]
    assert maps and all(Path(m).is_file() and Path(m).parent == out_dir.resolve() for m in maps)
    assert not list(work.iterdir())  # nothing written where the command ran


def test_large_frame_path_names_the_same_parameter(star_scene):
    """The bounded-memory path of large frames (forced here on a small one) hands its evidence to the same
    judge: the same zero point, the same policy, the same keys."""
    sc = load_scene(str(star_scene))
    meas = textbook_frame(star_scene, star_scene.with_name("zp_large.fits"), 9, ["sky.source_flux_scale=1.6"])
    out = run.run_diagnose(sc, meas, large_px=10_000)
    assert "sampling" in out  # the large-frame path
    first = _first(out)
    assert first["kind"] == "parameter" and first["key"] == "sky.source_flux_scale"
    assert first["value"] == pytest.approx(1.6, rel=0.05)
    assert out["policy"] == DEFAULT_POLICY.to_json() and set(out["gate_codes"]) == set(GATES)


def test_a_psf_change_carries_the_sources_scale_that_goes_with_it(tmp_path):
    """A Moffat's beta moves each star's light between its core and its wings; the diagnosis scores a beta with
    the sources' and the sky's levels profiled, so ``--apply`` of it refits both with the new PSF and writes the
    sources' scale (a real DSLR round wrote beta 1.79 -> 1.43 alone: its next compare was worse, 4.29 -> 4.42,
    against 3.59 with the levels refitted). Here the frame's stars are 1.25 x the scene's under a beta 0.8 x
    its own: the applied scene holds that scale (the sky within 1 %), and the compare's own level fit finds
    nothing more to take."""
    from scenes.app.compare.apply import apply_candidate

    p = tmp_path / "moffat.toml"
    p.write_text(star_field_toml(256).replace('model = "gaussian"', 'model = "moffat"\nbeta = 2.5'))
    sc = load_scene(str(p))
    meas = textbook_frame(p, tmp_path / "m.fits", 7, ["psf.beta=2.0", "sky.source_flux_scale=1.25"])
    cand = {"kind": "parameter", "key": "psf.beta", "value": 2.0, "explanation": "beta x 0.8"}
    again = load_scene(str(apply_candidate(sc, cand, tmp_path / "applied.toml", meas)))
    assert again.psf.beta == 2.0
    assert again.sky.source_flux_scale == pytest.approx(1.25, rel=0.02)
    assert again.sky.background_mag_arcsec2 == pytest.approx(sc.sky.background_mag_arcsec2, abs=0.011)
    cmp = run.run_compare(again, meas)
    assert abs(cmp["levels"]["light_scale"]) < 0.01
def _saturated_res(change_away: bool, plateau: bool = False):
    """A 64 x 64 light frame with 3 x 3 saturated pixels at (6, 6), a 50 ADU bump of the residual beside them
    (at (10, 10): their bleeding) and, when ``change_away``, the same bump at (46, 46), far from them. With
    ``plateau`` the model fills those pixels to the ceiling and the data hold them at 85 % of it (wells that
    spill below the nominal full well)."""
    from detector import make_sensor
    from detector.signatures import Residuals, SpikeStats

    s = make_sensor("ml11002", {"width": 64, "height": 64})
    yy, xx = np.mgrid[:64, :64]

    def bump(y, x):
        return 50.0 * np.exp(-((yy - y) ** 2 + (xx - x) ** 2) / (2 * 2.0 ** 2))

    model = np.full((64, 64), 1000.0)
    data = model + bump(10, 10) + (bump(46, 46) if change_away else 0.0)
    data = data + np.random.default_rng(4).normal(0.0, 10.0, data.shape)
    data[5:8, 5:8] = 7e4  # above any ceiling of a 16-bit read-out
    if plateau:
        ceiling = min(s.adc_max_adu, s.bias_adu + s.full_well_e / s.gain_e_per_adu)
        model[5:8, 5:8] = ceiling
        data[5:8, 5:8] = 0.85 * ceiling
    fit = np.ones((64, 64), bool)
    fit[5:8, 5:8] = False
    f32, z = (lambda a: np.asarray(a, np.float32)), np.zeros((64, 64), np.float32)
    res = Residuals(f32(data), f32(model), np.full((64, 64), 100.0, np.float32), fit, f32(model - 100.0), z,
                    np.arange(64.0), np.arange(64.0), s, 10.0, SpikeStats(0, 0, 0, 0, 0), SpikeStats(0, 0, 0, 0, 0))
    return res, (bump(10, 10) + bump(46, 46)).astype(np.float32)


def test_a_transform_carried_by_the_saturated_sources_is_refused_away_from_them():
    """A change proposed for every source (two bumps) that the data show only beside the saturated pixels keeps
    about 0 of its amplitude beyond SATURATED_REACH_PX of them, more than AWAY_SIGMA errors short of the
    policy's share: refused as their bleeding; the same change seen away from them too is not."""
    from scenes.app.compare.candidates import away_from_saturation

    for change_away in (False, True):
        res, delta = _saturated_res(change_away)
        assert res.data_adu.max() >= 0.9 * res.saturation_ceiling_adu
        fit = Fit("jitter", {}, -500.0, 2, int(res.fit.sum()), "", delta_adu=delta)
        why = away_from_saturation(res, fit, DEFAULT_POLICY)
        assert (why == "") == change_away, why
        if not change_away:
            assert "1 saturated sources" in why


def test_a_source_the_model_saturates_is_saturated_though_the_data_plateau_lower():
    """Wells that spill below the nominal full well hold a bright source's core under the saturated share of the
    ceiling in the data, while the model fills it: the source is a saturated one for the test of image-plane
    transforms (its bleeding is not a smear of every source), and a change seen away from it too is not refused."""
    from scenes.app.compare.candidates import away_from_saturation, saturated_reach

    for change_away in (False, True):
        res, delta = _saturated_res(change_away, plateau=True)
        assert not res.saturated.any() and saturated_reach(res)[1] == 1
        fit = Fit("jitter", {}, -500.0, 2, int(res.fit.sum()), "", delta_adu=delta)
        assert (away_from_saturation(res, fit, DEFAULT_POLICY) == "") == change_away


def test_a_reachable_bound_is_not_a_pinned_fit():
    """A drift from rest has accel = +1, a bound its schema marks ``bound_reachable`` (a physical state of the
    path): not "at its bound"; a chord at its +-1000 px limit is."""
    from detector import registry
    from scenes.app.compare.candidates import at_bound

    cls = registry()["pointing_drift"]
    assert cls.Params.model_json_schema()["properties"]["accel"].get("bound_reachable") is True
    assert at_bound(cls, {"dx_px": 5.0, "dy_px": 1.0, "accel": 1.0}) == ""
    assert at_bound(cls, {"dx_px": 5.0, "dy_px": 1.0, "accel": -1.0}) == ""
    assert "dx_px" in at_bound(cls, {"dx_px": 1000.0, "dy_px": 1.0, "accel": 0.5})


def test_constant_fraction_cti_is_not_a_pinned_fit():
    """A well-fill power of 1 is the classical constant-fraction CTI (a packet's volume in proportion to its
    charge), a physical state the schema marks ``bound_reachable``: a cti fit there is not "at its bound"."""
    from detector import registry
    from scenes.app.compare.candidates import at_bound

    cls = registry()["cti"]
    assert cls.Params.model_json_schema()["properties"]["beta"].get("bound_reachable") is True
    assert at_bound(cls, {"density_per_px": [0.2], "release_time_s": [0.004], "beta": 1.0}) == ""


def test_an_axis_near_its_angle_bound_is_not_a_pinned_fit():
    """An angle is periodic: a jitter axis or a coma tail fitted at 179.9 deg is one at -0.1 deg, not a fit pinned
    at the schema's +-180; a magnitude at its bound still is."""
    from detector import registry
    from scenes.app.compare.candidates import at_bound

    jitter, elong = registry()["jitter"], registry()["psf_elongation"]
    assert at_bound(jitter, {"sigma_major_px": 1.0, "sigma_minor_px": 0.2, "angle_deg": 179.95}) == ""
    assert at_bound(elong, {"tail_frac": 0.3, "tail_angle_deg": -179.99}) == ""
    assert "sigma_major_px" in at_bound(jitter, {"sigma_major_px": 50.0, "angle_deg": 10.0})


def test_a_glow_and_a_light_are_the_same_charge_on_a_light_frame():
    """A field of dark charge (amp_glow) and a field of light (straylight) put the same charge in the same pixels
    of an exposed frame: named as not told apart whatever their held-out scores (their forms differ, their
    origin is not in the data); a bias ramp (added at read-out, no shot noise) is not that twin."""
    from scenes.app.compare.judge import indistinguishable, same_charge, verdict

    glow = Candidate(Fit("amp_glow", {}, -1751.0, 6, 10_000, "a glow"), 1.0, 0.0, heldout=-1789.0)
    light = Candidate(Fit("straylight", {}, -1371.0, 6, 10_000, "a light"), 1.0, 0.0, heldout=-1376.0)
    ramp = Candidate(Fit("bias_gradient", {}, -896.0, 3, 10_000, "a ramp"), 1.0, 0.0, heldout=-857.0)
    assert same_charge(glow, light) and not same_charge(glow, ramp) and not same_charge(light, ramp)
    assert [c.fit.effect for c in indistinguishable([glow, light, ramp])] == ["straylight"]
    assert "cannot tell it apart from straylight: the same charge" in verdict([glow, light, ramp])


def test_a_dsnu_and_a_read_noise_are_the_same_scatter_where_the_dark_is_uniform():
    """A DSNU adds (sigma D)^2, a read noise a constant (Janesick 2007): on a frame of uniform dark signal D their
    added variances are proportional, the same likelihood, named as not told apart whatever their held-out scores;
    where D varies over the frame (a glow, a temperature gradient) their laws differ and they are not twins."""
    from scenes.app.compare.judge import indistinguishable, same_scatter, verdict

    shape = (64, 64)
    dark = np.full(shape, 15.0)
    ramp = np.broadcast_to(np.linspace(5.0, 40.0, shape[1]), shape)
    read = Candidate(Fit("reset_noise", {}, -160.0, 1, 4096, "a read noise", extra_var_adu2=np.full(shape, 4.0)),
                     1.0, 0.0, heldout=-150.0)
    for d, twins in ((dark, True), (ramp, False)):
        dsnu = Candidate(Fit("dsnu", {}, -151.0, 2, 4096, "a dsnu", extra_var_adu2=0.04 * d ** 2 / 1.4 ** 2),
                         1.0, 0.0, heldout=-60.0)
        assert same_scatter(read, dsnu) == twins
        assert ([c.fit.effect for c in indistinguishable([read, dsnu])] == ["dsnu"]) == twins
    # proportional to what the frame can tell: a 0.2 % spread of the ratio over 4096 pixels is at most 0.008 of
    # -2 ln L (no frame tells the laws apart), a 6 % spread up to 7 (the laws differ)
    x = np.broadcast_to(np.linspace(-1.0, 1.0, shape[1]), shape)
    for spread, twins in ((0.001, True), (0.05, False)):
        var = 0.04 * (dark * (1 + spread * x)) ** 2
        dsnu = Candidate(Fit("dsnu", {}, -151.0, 2, 4096, "a dsnu", extra_var_adu2=var), 1.0, 0.0, heldout=-60.0)
        assert same_scatter(read, dsnu) == twins, spread
    assert "cannot tell it apart from dsnu: the same added variance" in verdict([read, Candidate(
        Fit("dsnu", {}, -151.0, 2, 4096, "a dsnu", extra_var_adu2=0.04 * dark ** 2), 1.0, 0.0, heldout=-60.0)])


def test_a_dsnu_with_large_scales_and_a_dark_field_are_the_same_dark_charge():
    """A DSNU whose fit carries a large-scale part (a mean change of dark charge) and an additive field of dark
    charge (a dark-rate gradient, a glow) put the same dark charge in the same pixels (EMVA 1288 sect. 8.3: the
    DSNU spans every spatial scale): named as not told apart whatever their held-out scores; a white DSNU (no
    mean change) is no such twin, nor is a bias structure (added at read-out); a dark field whose own form comes
    first (better on held-out pixels) is a form the data prefer, tied with the DSNU only by the held-out scores."""
    from scenes.app.compare.judge import indistinguishable, same_dark_field, verdict

    shape = (64, 64)
    field = np.broadcast_to(np.linspace(-3.0, 3.0, shape[1]), shape).astype(np.float32)
    var = np.full(shape, 2.0, np.float32)
    dsnu = Candidate(Fit("dsnu", {}, -2400.0, 20, 4096, "a dsnu with large scales", delta_adu=field,
                         extra_var_adu2=var), 1.0, 0.0, heldout=-2300.0)
    white = Candidate(Fit("dsnu", {}, -2400.0, 2, 4096, "a white dsnu", extra_var_adu2=var), 1.0, 0.0, heldout=-2300.0)
    dark = Candidate(Fit("dark_gradient", {}, -1600.0, 2, 4096, "a dark-rate field", delta_adu=field), 1.0, 0.0,
                     heldout=-1600.0)
    bias = Candidate(Fit("bias_gradient", {}, -1500.0, 3, 4096, "a bias ramp", delta_adu=field), 1.0, 0.0,
                     heldout=-1500.0)
    assert same_dark_field(dsnu, dark) and not same_dark_field(dark, dsnu)
    assert not same_dark_field(white, dark) and not same_dark_field(dsnu, bias)
    glow = Candidate(Fit("amp_glow", {}, -3000.0, 6, 4096, "a glow", delta_adu=field, extra_var_adu2=var), 1.0, 0.0,
                     heldout=-3000.0)  # its charge's shot noise: a variance too, but no pattern
    assert indistinguishable([glow, dsnu]) == [] and not same_dark_field(glow, dark)
    assert [c.fit.effect for c in indistinguishable([dsnu, dark, bias])] == ["dark_gradient"]
    assert "cannot tell it apart from dark_gradient: the same dark charge in a smooth pattern" in verdict(
        [dsnu, dark, bias])


def test_an_ipc_the_frame_cannot_tell_from_a_blur_is_named_with_it():
    """An IPC whose own physics says this frame cannot tell it from a blur of the light (``untold``) is named
    with psf_blur as not told apart, even when the blur's form scores short of the held-out bar (a contender:
    significant by delta BIC, plausible); an IPC the frame does tell (no ``untold``) is named alone, and a blur
    refused as implausible is no twin."""
    from scenes.app.compare.judge import indistinguishable, rank, same_image, verdict

    def pair(untold=("psf_blur",), blur_why=""):
        ipc = Candidate(Fit("ipc", {}, -46.8, 2, 10_000, "a coupling"), 1.0, 0.0, heldout=-59.5, untold=untold)
        blur = Candidate(Fit("psf_blur", {}, -54.9, 2, 10_000, "a blur"), 1.0, 0.0, heldout=-35.7,
                         implausible=blur_why)
        return ipc, blur

    ipc, blur = pair()
    assert ipc.significant and not blur.significant and blur.contender and same_image(ipc, blur)
    assert indistinguishable([ipc], [ipc, blur]) == [blur]
    assert [c.fit.effect for c in rank([blur, ipc])] == ["ipc", "psf_blur"]
    assert "cannot tell it apart from psf_blur: the same small kernel" in verdict([ipc, blur])
    ipc, blur = pair(untold=())
    assert indistinguishable([ipc], [ipc, blur]) == [] and "psf_blur" not in verdict([ipc, blur])
    ipc, blur = pair(blur_why="not a blur")
    assert indistinguishable([ipc], [ipc, blur]) == []


def test_a_dark_field_whose_shot_noise_cannot_speak_ties_with_a_bias_structure():
    """A bias structure first and a dark-rate field whose own shot noise this frame cannot measure (``untold``)
    are named as not told apart, with the reason that a bias frame or another exposure tells them, even when
    the held-out scores prefer the first's form (the forms differ, the origin of the field is not in the data);
    a dark field the frame does tell (no ``untold``) is no twin."""
    from scenes.app.compare.judge import indistinguishable, verdict

    def pair(untold=("bias_gradient",)):
        bias = Candidate(Fit("bias_gradient", {}, -264.6, 6, 16_000, "a bias structure"), 1.0, 0.0, heldout=-287.2)
        dark = Candidate(Fit("dark_gradient", {}, -221.6, 5, 16_000, "a dark-rate field"), 1.0, 0.0, heldout=-234.0,
                         untold=untold)
        return bias, dark

    bias, dark = pair()
    assert bias.significant and dark.significant
    assert indistinguishable([bias, dark], [bias, dark]) == [dark]
    assert "cannot tell it apart from dark_gradient: the same smooth field, of dark charge or an offset" in \
        verdict([bias, dark])
    bias, dark = pair(untold=())
    assert indistinguishable([bias, dark], [bias, dark]) == []


def test_a_response_and_an_added_light_the_frame_cannot_tell_are_named_together_and_a_told_law_passes_the_kind_gate():
    """A vignetting whose own law this frame does not tell from an added light (``untold``: one light level)
    is named with straylight as the same smooth pattern of the light (also when straylight's own form is short of
    the BIC bar, not when it is refused); an added light whose own shape the
    frame finds added (``law_told``) is not refused by the morphology's multiplicative kind, one that is not
    told is."""
    from scenes.app.compare.judge import indistinguishable, kind_gate, same_light, verdict

    vig = Candidate(Fit("vignetting", {}, -160.0, 5, 10_000, "a fall-off"), 1.0, 0.0, heldout=-70.0,
                    untold=("straylight", "sky_gradient"))
    stray = Candidate(Fit("straylight", {}, -100.0, 6, 10_000, "an added light"), 1.0, 0.0, heldout=-20.0)
    assert same_light(vig, stray) and indistinguishable([vig], [vig, stray]) == [stray]
    assert "cannot tell it apart from straylight: the same smooth pattern, added to the frame" in verdict([vig, stray])
    # a bias structure first (an offset of the read-out) whose offset this flat does not tell from a response of
    # the same shape (its untold): named with the vignetting, also when the vignetting's own form is short of the
    # BIC bar (a drawn 0.15 % cos4 fall-off on a binned flat, vignetting-3589686496556373386)
    bias = Candidate(Fit("bias_gradient", {}, -60.0, 3, 10_000, "an offset"), 1.0, 0.0, heldout=-63.0,
                     untold=("vignetting",))
    short = Candidate(Fit("vignetting", {}, -7.8, 5, 10_000, "a fall-off"), 1.0, 0.0)
    assert same_light(bias, short) and indistinguishable([bias], [bias, short]) == [short]
    assert "cannot tell it apart from vignetting: the same smooth pattern" in verdict([bias, short])
    # the added light's own form short of the BIC bar (its 14 Legendre terms pay more than the fall-off's two):
    # the first's shape still does not tell the laws, so it is still named with it; refused, it is no twin
    weak = Candidate(Fit("straylight", {}, -7.4, 15, 10_000, "an added light"), 1.0, 0.0)
    assert not weak.contender and indistinguishable([vig], [vig, weak]) == [weak]
    refused = Candidate(Fit("straylight", {}, -7.4, 15, 10_000, "an added light"), 1.0, 0.0,
                        implausible="a response, not added light")
    assert indistinguishable([vig], [vig, refused]) == []
    told_vig = Candidate(Fit("vignetting", {}, -160.0, 5, 10_000, "a fall-off"), 1.0, 0.0, heldout=-70.0)
    assert indistinguishable([told_vig], [told_vig, weak]) == []
    morph = {"significant": True, "kind": "multiplicative", "kind_certain": True}
    told = Candidate(Fit("straylight", {}, -300.0, 6, 10_000, "an added light"), 1.0, 0.0, law_told=True)
    untold = Candidate(Fit("sky_gradient", {}, -300.0, 2, 10_000, "a gradient"), 1.0, 0.0)
    kind_gate([told, untold], morph)
    assert "kind" not in told.codes and "kind" in untold.codes


def test_a_response_applied_refits_the_stars_with_the_sky(star_scene, tmp_path):
    """A response to the light (here a non-linearity, whose power law about a reference is a gain there) scales
    the stars as it scales the sky: --apply refits the sources' scale with the sky level (as the diagnosis
    profiled them). An additive candidate leaves the sources' scale alone (misplaced stars would pull it)."""
    from scenes.app.compare.apply import apply_candidate

    sc = load_scene(str(star_scene))
    brighter = ["sky.source_flux_scale=1.05", f"sky.background_mag_arcsec2={sc.sky.background_mag_arcsec2 - 0.053}"]
    meas = textbook_frame(star_scene, tmp_path / "bright.fits", 8, brighter)
    nl = {"effect": "nonlinearity", "kind": "effect", "params": {"beta": 0.0, "gamma": 1.0}, "explanation": "test"}
    new = load_scene(str(apply_candidate(sc, nl, tmp_path / "nl.toml", meas)))
    assert new.sky.source_flux_scale == pytest.approx(1.05, rel=0.01)
    dg = {"effect": "dark_gradient", "kind": "effect", "params": {}, "explanation": "test"}
    add = load_scene(str(apply_candidate(sc, dg, tmp_path / "dg.toml", meas)))
    assert add.sky.source_flux_scale == 1.0 and add.sky.background_mag_arcsec2 < sc.sky.background_mag_arcsec2


def test_a_change_seen_by_one_fold_only_is_not_tested_by_the_held_out_pixels():
    """Cross-validation weighs a fit only where both folds see its change: a compressive response taking 3 %
    of the cores of two bright stars (peaks 55 000 e-, shot noise ~ 235 e-) that both lie in one 32 x 32 block
    of the checkerboard leaves the other fold with less than a detection (chi2 < DETECTION_SIGMA^2) of it,
    while the same change on stars spread over the frame is seen by both folds."""
    from types import SimpleNamespace

    from detector.signatures import HELDOUT_BLOCK, fold_detections, heldout_blind
    from detector.significance import DETECTION_SIGMA

    shape = (256, 256)
    var = np.full(shape, 200.0 + 3.5 ** 2, np.float32)
    res = SimpleNamespace(fit=np.ones(shape, bool), var_adu2=var, row_var_adu2=0.0,
                          data_adu=np.zeros(shape, np.float32))

    def cores(positions):
        d = np.zeros(shape, np.float32)
        for y, x in positions:
            var[y - 1:y + 2, x - 1:x + 2] = 55_000.0
            d[y - 1:y + 2, x - 1:x + 2] = -0.03 * 55_000.0
        return Fit("nonlinearity", {}, -200.0, 1, 65536, "a compression", delta_adu=d)

    one_block = cores([(10, 10), (20, 22)])  # both in the first block (HELDOUT_BLOCK px a side)
    assert max(y for y, _ in [(10, 10), (20, 22)]) + 1 < HELDOUT_BLOCK
    seen = fold_detections(one_block, res)
    assert min(seen) < DETECTION_SIGMA ** 2 < max(seen) and heldout_blind(one_block, res)
    var[...] = 200.0 + 3.5 ** 2
    spread = cores([(10, 10), (10, 42), (100, 150), (100, 182)])  # two blocks of each colour
    assert min(fold_detections(spread, res)) > DETECTION_SIGMA ** 2 and not heldout_blind(spread, res)
    assert fold_detections(Fit("x", {}, -1.0, 1, 10, ""), res) is None


def test_a_change_in_one_block_is_held_out_on_blocks_both_folds_see():
    """A compressive response (a tanh law, 12 % low at 0.85 of the full well) in the core of a star window's one
    bright star falls in one block of the default checkerboard: one fold sees less than a detection of it and the
    held-out score does not test it. On the largest smaller blocks both folds see it on
    (:func:`detector.signatures.seeing_block`), the law fitted on one part of the core predicts the other; on the
    same window without the response nothing is fitted that both folds could see, so no smaller blocks are used."""
    from detector.effects import registry as effects
    from detector.sensor import make_sensor
    from detector.signatures import default_block, heldout_blind, heldout_delta, seeing_block
    from scenes.app.compare.policy import DEFAULT_POLICY

    sensor = make_sensor("ml11002")
    g, fw = sensor.gain_e_per_adu, sensor.full_well_e
    yy, xx = np.mgrid[:128, :128]
    q = np.full((128, 128), 2000.0)  # sky [e-]
    for y0, x0, peak in ((40.3, 50.6, 0.85), (90.2, 100.7, 0.1), (20.5, 110.2, 0.05)):  # peaks [full well]
        q += peak * fw * np.exp(-((yy - y0) ** 2 + (xx - x0) ** 2) / (2 * 1.3 ** 2))
    sig = effects()["nonlinearity"].signature

    def window(a, seed):
        measured_e = a * np.tanh(q / fw / a) * fw if a else q
        var_e = q + 100.0
        noise = np.random.default_rng(seed).standard_normal(q.shape) * np.sqrt(var_e)
        return residuals_of((measured_e + noise) / g + sensor.bias_adu, q / g + sensor.bias_adu, var_e / g ** 2,
                            q / g, sensor)

    res = window(1.5, 1)
    fit = sig.fit(res, "nonlinearity")
    assert fit.delta_bic < DEFAULT_POLICY.significant_delta_bic and heldout_blind(fit, res)
    block = seeing_block(fit, res)
    assert block is not None and block < default_block(res.data_adu.shape) and not heldout_blind(fit, res, block)
    assert heldout_delta(sig, res, "nonlinearity", fit, block) < DEFAULT_POLICY.significant_heldout
    for seed in (2, 3):
        null = window(None, seed)
        fit = sig.fit(null, "nonlinearity")
        assert fit.delta_bic > DEFAULT_POLICY.significant_delta_bic and seeing_block(fit, null) is None
    # the judge scores every contender again on those blocks (their held-out scores, compared, share one layout)
    from scenes.app.compare.candidates import candidates

    others = set(effects()) - {"nonlinearity", "brighter_fatter"}
    cands, _ = candidates(window(1.5, 1), others)
    scored = [c for c in cands if c.heldout is not None]
    assert {c.fit.effect for c in scored} == {"nonlinearity", "brighter_fatter"}
    assert {c.heldout_block for c in scored} == {block} and all(not c.heldout_blind for c in scored)
    # no block below the residual's coherence length (twice the stars' rms radius, sqrt(2) 1.3 px: 4 px): a
    # held-out pixel with training pixels within the PSF is not held out from a PSF-scale mismatch
    from scenes.app.compare.candidates import coherence_px

    assert coherence_px(res) == 4 and block >= 4
    assert seeing_block(sig.fit(res, "nonlinearity"), res, 2 * block) is None  # the floor stops the halving


def test_a_rival_whose_held_out_test_is_blind_ties_with_the_first_name():
    """A brighter-fatter named on its held-out score is not named alone when a non-linearity fits the frame
    better in-sample but could not be tested on held-out pixels (its change seen by one fold only): the verdict
    says the data cannot tell them apart; a blind rival that fits clearly worse, or one whose held-out test was
    not blind, is no tie."""
    from scenes.app.compare.judge import blind_rival, indistinguishable, rank, verdict

    bf = Candidate(Fit("brighter_fatter", {}, -38.4, 2, 65536, "wider bright stars"), 1.0, 0.0, heldout=-60.5)
    nl = Candidate(Fit("nonlinearity", {}, -54.6, 1, 65536, "a compression"), 1.0, 0.0, heldout=1500.0,
                   heldout_blind=True)
    assert bf.significant and not nl.significant and nl.contender and blind_rival(bf, nl)
    assert indistinguishable([bf], [bf, nl]) == [nl]
    assert [c.fit.effect for c in rank([nl, bf])][:2] == ["brighter_fatter", "nonlinearity"]
    assert "cannot tell it apart from nonlinearity: it fits the frame as well or better" in verdict([bf, nl])
    nl.heldout_blind = False
    assert indistinguishable([bf], [bf, nl]) == []
    strong = Candidate(Fit("brighter_fatter", {}, -240.0, 2, 65536, "wider bright stars"), 1.0, 0.0, heldout=-250.0)
    worse = Candidate(Fit("nonlinearity", {}, -24.0, 1, 65536, "a compression"), 1.0, 0.0,
                      heldout=1500.0, heldout_blind=True)
    # delta BIC -12.9 against -217.8: beyond the twins' tolerance 2 sqrt(2 x 217.8)
    assert worse.contender and not blind_rival(strong, worse)


def test_a_blind_candidate_alone_is_described_as_untested_not_as_failed():
    """With nothing significant, a candidate that fits best but whose held-out test is blind is not called
    "not credible" by its held-out score: the verdict says the held-out pixels cannot test it."""
    from scenes.app.compare.judge import verdict

    nl = Candidate(Fit("nonlinearity", {}, -150.0, 1, 65536, "a compression"), 1.0, 0.0, heldout=2705.0,
                   heldout_blind=True)
    assert not nl.significant and "cannot test it" in verdict([nl])
    nl.heldout_blind = False
    assert "not credible: held-out delta 2705" in verdict([nl])


def test_a_dark_field_first_ties_with_a_dsnu_by_its_held_out_score_not_by_their_charge():
    """A dark field whose own form comes first, tied with a DSNU with large scales by the held-out scores only,
    is reported so (the held-out scores' reason), not as the same dark charge whatever each fit's form
    (:func:`scenes.app.compare.judge.same_dark_field` is not symmetric)."""
    from scenes.app.compare.judge import verdict

    field = np.broadcast_to(np.linspace(-3.0, 3.0, 64), (64, 64)).astype(np.float32)
    var = np.full((64, 64), 2.0, np.float32)
    dark = Candidate(Fit("dark_gradient", {}, -2400.0, 2, 4096, "a dark-rate field", delta_adu=field), 1.0, 0.0,
                     heldout=-2300.0)
    dsnu = Candidate(Fit("dsnu", {}, -2390.0, 20, 4096, "a dsnu with large scales", delta_adu=field,
                         extra_var_adu2=var), 1.0, 0.0, heldout=-2299.0)
    text = verdict([dark, dsnu])
    assert "cannot tell it apart from dsnu" in text and "held-out scores are as good" in text, text
    assert "the same dark charge in a smooth pattern" not in text, text


def test_the_held_out_default_block_is_the_layout_in_use():
    """Under row noise the folds are bands of whole rows, and their default height (at least 8 bands) is set by
    the frame's rows alone: a tall narrow frame keeps 32-row bands, where the checkerboard's default (at least 8
    blocks a side) would be 16; the finer-block search starts from that same default (one helper)."""
    from types import SimpleNamespace

    from detector.signatures import default_block, heldout_mask, layout_block

    tall = SimpleNamespace(data_adu=np.zeros((4096, 128), np.float32), row_var_adu2=1.0)
    assert layout_block(tall) == 32 and default_block(tall.data_adu.shape) == 16
    assert np.array_equal(heldout_mask(tall), heldout_mask(tall, 32))
    assert layout_block(SimpleNamespace(data_adu=tall.data_adu, row_var_adu2=0.0)) == 16


def test_the_catch_all_is_scored_on_the_blocks_the_candidates_were_compared_on(monkeypatch):
    """Every contender re-scored on finer blocks is set against the catch-all on those same folds; the reported
    catch-all score is that one, and the default-block catch-all, compared with nobody, is not computed."""
    from types import SimpleNamespace

    from scenes.app.compare import catch_all as ca

    asked = []
    monkeypatch.setattr(ca, "catch_all_heldout",
                        lambda res, block=None, threads=1: asked.append(block) or -10.0 * (block or 1))
    res = SimpleNamespace(forget=lambda key: None)
    cands = [SimpleNamespace(heldout=-5.0, kind="effect", heldout_block=4, catch_all_heldout=None) for _ in range(2)]
    assert ca.compare_with_catch_all(res, cands, {"significant": True}) == -40.0
    assert asked == [4] and all(c.catch_all_heldout == -40.0 for c in cands)


def test_a_rival_refused_for_its_shares_that_predicts_the_held_out_pixels_better_ties_with_the_first():
    """A name that passes every gate is not named alone when a rival predicts the held-out pixels better and was
    refused only for the share of what is wrong it removes (where it acts, overall, the large scales): the held-out
    pixels prefer the rival's form, so the verdict says the data cannot tell them apart. A rival refused for its form
    (implausible), or whose held-out score is worse, is no tie."""
    from scenes.app.compare.judge import better_rival, indistinguishable, rank, verdict

    gain = Candidate(Fit("gain_regions", {}, -5000.0, 6, 65536, "gain steps"), 1.0, 0.0, heldout=-4900.0)
    vig = Candidate(Fit("vignetting", {}, -6000.0, 6, 65536, "a fall-off"), 1.0, 0.0, heldout=-5900.0,
                    support_share=0.2)
    assert gain.significant and not vig.significant and vig.gates == ["support"] and better_rival(gain, vig)
    assert indistinguishable([gain], [gain, vig]) == [vig]
    assert [c.fit.effect for c in rank([vig, gain])][:2] == ["gain_regions", "vignetting"]
    assert "cannot tell it apart from vignetting: it predicts the held-out pixels better" in verdict([gain, vig])
    worse = Candidate(Fit("vignetting", {}, -6000.0, 6, 65536, "a fall-off"), 1.0, 0.0, heldout=-4000.0,
                      support_share=0.2)
    assert not better_rival(gain, worse) and indistinguishable([gain], [gain, worse]) == []
    vig.refuse("implausible", "not this effect's form")
    assert not better_rival(gain, vig) and indistinguishable([gain], [gain, vig]) == []


def test_a_rival_that_fits_better_and_predicts_as_well_but_misses_the_held_out_bar_ties_with_the_first():
    """closer_rival: a rival with a lower delta BIC whose held-out score is within the scores' scatter of the
    first's (2 sqrt(2 |score|)) and that fails only the held-out bar is a tie, listed after the first (which
    stays first: it passes every gate); one whose held-out score is further off, or that fits worse, or fails
    another gate, is none. The numbers (delta BIC -40.3 and -56.8) are a 0.07 px tangential distortion against a uniform shift."""
    from scenes.app.compare.judge import closer_rival, indistinguishable, rank, verdict

    shift = Candidate(Fit("pointing_offset", {}, -62.5, 2, 65536, "a shift"), 1.0, 0.0, heldout=-41.1)
    dist = Candidate(Fit("distortion", {}, -101.2, 4, 65536, "a distortion"), 1.0, 0.0, heldout=-34.8)
    assert shift.significant and dist.gates == ["heldout"] and closer_rival(shift, dist)
    assert indistinguishable([shift], [shift, dist]) == [dist]
    assert [c.fit.effect for c in rank([dist, shift])][:2] == ["pointing_offset", "distortion"]
    assert "cannot tell it apart from distortion: it fits the frame better" in verdict([shift, dist])
    far = Candidate(Fit("distortion", {}, -101.2, 4, 65536, "a distortion"), 1.0, 0.0, heldout=-10.0)
    worse_fit = Candidate(Fit("distortion", {}, -79.4, 4, 65536, "a distortion"), 1.0, 0.0, heldout=-34.8)
    assert not closer_rival(shift, far) and not closer_rival(shift, worse_fit)
    dist.refuse("implausible", "not this effect's form")
    assert not closer_rival(shift, dist) and indistinguishable([shift], [shift, dist]) == []


def test_a_blind_candidate_told_from_all_but_a_blind_twin_is_judged_on_its_fit(monkeypatch):
    """blind_rivals: the blind best fit that nesting tells from the first name, tied by nesting with a blind
    rival that fits no better, is judged on its delta BIC (the first refused ``nested``, the twin kept); a rival
    whose held-out score is a test (not blind) and that nesting does not tell from it leaves it unjudged."""
    from types import SimpleNamespace

    from scenes.app.compare import candidates as C

    change = np.zeros((4, 4))

    def cand(name, m2lnl, heldout, blind):
        return Candidate(Fit(name, {}, m2lnl, 1, 10_000, "why", delta_adu=change), 1.0, 0.0, heldout=heldout,
                         heldout_blind=blind)

    told = {("nonlinearity", "psf_blur"): "beside nonlinearity it explains nothing significant"}
    monkeypatch.setattr(C, "explains_beside", lambda res, c, o, policy=None: told.get((c.fit.effect, o.fit.effect), ""))
    res = SimpleNamespace(light_source="")
    for twin_blind, named in ((True, True), (False, False)):
        blur, nl, bf = cand("psf_blur", -53, -43, True), cand("nonlinearity", -86, -36, True), \
            cand("brighter_fatter", -80, 104, twin_blind)
        C.blind_rivals(res, [blur, nl, bf])
        assert nl.significant is named and ("nested" in blur.gates) is named
        assert "nested" not in bf.gates
