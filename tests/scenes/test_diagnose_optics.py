"""The telescope's alignment diagnosed from the stars: ``misalignment`` / ``defocus`` candidates of ``newtsim diagnose``.

Frames of the ML11002 full field (binned 2 x 2) behind an ``art`` telescope with a perturbed design and the optics'
PSF (``[psf] model = "optics"``, a cube traced for the perturbed design: tests/scenes/optics_frames.py), diagnosed
against the nominal scene: the perturbation is named first (slow matrix: first of the whole ranking, every catalogue
candidate included, the optics candidates scored on the pixels) and its value recovered within 20 % or twice its
error; the nominal frame shows no significant misalignment (docs/optics.md, "Matrix of perturbed frames"). The pixel <-> focal-plane
mapping is checked against the render's own conventions (the PSF grid's node positions, the sign of the cross
moment in the model frame).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from optics_frames import design_file, scene_table, trace_cube, write_catalogue, write_toml

from scenes.app.compare import optics_candidates as oc
from scenes.scene import load_scene

OPTICS = set(oc.OPTICS_CANDIDATES)


def _recovered(value, error, truth):
    return abs(value - truth) <= max(0.2 * abs(truth), 2 * error)


# ------------------------------------------------------------------------------------------ geometry, no optics
def test_pixel_mapping_puts_the_grid_nodes_at_their_field_angles():
    """The render places a PSF grid node of field (theta_x, theta_y) at the ideal pixel axis + (-f tan theta_x,
    +f tan theta_y) / pitch (scenes.image.gridpsf); pixel_to_focal and field_angles_deg invert exactly that, for a
    binned window off the sensor's centre too."""
    from optics.psf import PSFGrid
    from scenes.image.gridpsf import GridPSF

    sc = load_scene("default", ["detector.preset='ml11002'", "detector.width=1200", "detector.height=800",
                                "detector.x0=2000", "detector.y0=1500", "detector.binning=2", "effects={}"])
    s = sc.sensor()
    f = 960.0
    fields = np.array([[th_x, th_y] for th_y in (-0.4, 0.0, 0.3) for th_x in (-0.5, 0.0, 0.6)])
    img = np.zeros((9, 9, 9))
    img[:, 4, 4] = 1.0
    grid = PSFGrid(images=img, pixel_um=3.0, fields_deg=fields, center_um=np.zeros((9, 2)), wavelengths_nm=[550.0],
                   weights=[1.0], metrics=[{"fwhm_um": 1.0, "ee50_um": 0.0, "ee80_um": 0.0, "ellipticity": 0.0,
                                            "energy_in_stamp": 1.0, "centroid_um": [0.0, 0.0]}] * 9,
                   kind="geometric", design="t", plate_scale_arcsec_per_mm=206264.806 / f)
    ax = (s.sensor_width_px - 1) / 2.0 - s.roi_x0
    ay = (s.sensor_height_px - 1) / 2.0 - s.roi_y0
    g = GridPSF.from_grid(grid, s.pixel_pitch_um, f, (ax, ay))
    # node positions in unbinned window pixels -> output (binned) pixels -> field angles
    X, Y = np.meshgrid(g.node_x, g.node_y)
    b = s.binning
    u, v = oc.pixel_to_focal((X.ravel() - (b - 1) / 2.0) / b, (Y.ravel() - (b - 1) / 2.0) / b, s)
    back = oc.field_angles_deg(u, v, f)
    # pixel x grows with -theta_x (the inverted image), row y with +theta_y (rows read -v)
    want = np.array([[tx, ty] for ty in sorted(set(fields[:, 1])) for tx in sorted(set(fields[:, 0]), reverse=True)])
    assert np.allclose(back, want, atol=1e-9)
    # the sensor's centre is the optical axis; rows grow towards -v (FOCAL_PLANE_Y_SIGN), columns towards +u
    xo = ((s.sensor_width_px - 1) / 2 - s.roi_x0 - (b - 1) / 2) / b
    yo = ((s.sensor_height_px - 1) / 2 - s.roi_y0 - (b - 1) / 2) / b
    uc, vc = oc.pixel_to_focal(np.array([xo, xo + 1, xo]), np.array([yo, yo, yo + 1]), s)
    assert np.allclose(uc, [0, 2 * 9e-3, 0], atol=1e-12) and np.allclose(vc, [0, 0, -2 * 9e-3], atol=1e-12)
    assert oc.moments_to_focal(1.0, 2.0, 0.5, s)[2] == pytest.approx(-0.5 * (2 * 9e-3) ** 2)


def test_unweighted_moments_of_a_pixelated_gaussian_and_their_noise():
    """A pixel-integrated Gaussian of sigma 1.3 px: Mxx = sigma^2 + 1/12 (the pixel's box); the propagated errors
    match the scatter of 400 noisy realisations within 15 %."""
    from scipy.special import ndtr

    sig, r = 1.3, 8
    e = np.arange(-r, r + 2) - 0.5
    px = np.diff(ndtr((e - 0.2) / sig))
    py = np.diff(ndtr((e + 0.1) / sig))
    img = 5e4 * py[:, None] * px[None, :]
    yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
    ap = np.hypot(xx, yy) <= r
    mo = oc.unweighted_moments(img, np.full(img.shape, 100.0), xx, yy, ap)
    assert mo["mxx"] == pytest.approx(sig ** 2 + 1 / 12, rel=2e-3) and abs(mo["mxy"]) < 1e-6
    rng = np.random.default_rng(2)
    draws = np.array([[oc.unweighted_moments(img + rng.normal(0, 10.0, img.shape), None, xx, yy, ap)[k]
                       for k in ("mxx", "myy", "mxy")] for _ in range(400)])
    for i, k in enumerate(("mxx", "myy", "mxy")):
        assert draws[:, i].std() == pytest.approx(math.sqrt(mo["var_" + k]), rel=0.15), k


def test_too_few_stars_is_a_problem_not_a_candidate():
    """A light frame without measurable catalogue stars: no candidate, one line in ``problems`` (the frame's pixels
    are not even looked at)."""
    sc = load_scene("default", ["detector.preset='ml11002'", "detector.width=64", "detector.height=64", "effects={}",
                                "exposure.frame='light'", "sky.stars=true"])
    cands, problems = oc.optics_candidates(None, np.zeros(0, dtype=[("kind", "S9")]), sc)
    assert cands == [] and problems[0]["effect"] == "misalignment/defocus"
    assert problems[0]["error"].startswith("skipped: 0 measurable catalogue stars")


def test_apply_writes_a_perturbed_design_beside_the_new_scene(tmp_path):
    from optics.design import load_design
    from scenes.app.compare.apply import apply_candidate

    sc = load_scene("default", ["detector.preset='ml11002'", "detector.width=64", "detector.height=64"])
    cand = {"effect": "misalignment", "explanation": "diagonal tilted +0.1 +- 0.01 deg about x: coma",
            "params": {"diagonal_tilt_x_deg": 0.1, "diagonal_tilt_y_deg": -0.02,
                       "errors": {"diagonal_tilt_x_deg": 0.01, "diagonal_tilt_y_deg": 0.01}}}
    out = apply_candidate(sc, cand, tmp_path / "round2.toml")
    new = load_scene(str(out))
    assert Path(new.telescope.design) == tmp_path / "round2_design.toml"
    d = load_design(new.telescope.design)
    assert d.perturbation.diagonal_tilt_x_deg == 0.1 and d.perturbation.diagonal_tilt_y_deg == -0.02
    base = load_design("art")
    assert d.model_dump(exclude={"perturbation", "name"}) == base.model_dump(exclude={"perturbation", "name"})
    assert "[perturbation]" in out.read_text().splitlines()[0]


# ------------------------------------------------------------------------------------------ frames (Mitsuba)
@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    return tmp_path_factory.mktemp("optdiag")


def _frame(mi, work: Path, perturbation: dict | None, nodes: int, seed: int = 11, stamp: int = 21) -> tuple[Path, Path]:
    """(nominal model scene, measured frame of the perturbed telescope); cubes reused within the module. ``stamp``:
    the cubes' stamp [9 um pixels] (21 cuts the wings of a perturbed star: optics_frames.trace_cube)."""
    from optics import load_design
    from scenes.app.render import render

    cat = work / "stars.csv"
    if not cat.exists():
        write_catalogue(cat)
    sfx = f"{nodes}" if stamp == 21 else f"{nodes}s{stamp}"
    nom = work / f"nominal_{sfx}.fits"
    if not nom.exists():
        trace_cube(mi, load_design("art"), nom, nodes, stamp)
    model = write_toml(work / f"model_{sfx}.toml", scene_table("art", str(nom), str(cat)))
    tag = "nominal" if not perturbation else "_".join(f"{k}_{v:g}" for k, v in perturbation.items())
    if not perturbation:
        design, cube = "art", nom
    else:
        design = design_file(work, perturbation, tag)
        cube = work / f"{tag}_{sfx}.fits"
        if not cube.exists():
            trace_cube(mi, load_design(str(design)), cube, nodes, stamp)
    meas = write_toml(work / f"meas_{tag}_{sfx}.toml", scene_table(str(design), str(cube), str(cat)))
    out = work / f"meas_{tag}_{sfx}_{seed}.fits"
    render(load_scene(str(meas)), out, seed=seed, progress=False)
    return model, out


def _optics(mi, model: Path, measured: Path):
    from scenes.app.compare.run import run_compare

    sc = load_scene(str(model))
    cmp = run_compare(sc, measured)
    return oc.optics_candidates(cmp["_residuals"], cmp["_model"].setup.truth, sc, mi=mi)


def _check(cands, truth: dict):
    (name, value), = truth.items()
    first = cands[0].fit
    print(truth, "->", first.note, first.params, f"delta BIC {first.delta_bic:.1f}; next",
          [(c.fit.note, round(c.fit.delta_bic, 1)) for c in cands[1:3]], "stars", first.state["n_stars"])
    assert name in first.params, [(c.fit.note, round(c.fit.delta_bic, 1)) for c in cands]
    assert first.delta_bic < -10
    v, e = first.params[name], first.params["errors"][name]
    assert _recovered(v, e, value), (name, v, e, value)
    return first


def _diagnose(model, meas, monkeypatch, catalogue: bool):
    """run_diagnose, with the detector catalogue's candidates (``catalogue``) or without them (fast: the optics'
    candidates ranked through the same path)."""
    from scenes.app.compare import run

    if not catalogue:
        monkeypatch.setattr(run, "candidates", lambda *a, **k: ([], []))
    return run.run_diagnose(load_scene(str(model)), meas)


def test_sensor_tilt_is_diagnosed_and_applied(mi, workdir, monkeypatch):
    """The loop on one frame (a 3 x 3 PSF grid): diagnose names the sensor tilt first among the optics
    candidates, recovers it, and --apply writes the design that carries it."""
    from optics.design import load_design
    from scenes.app.compare.apply import apply_candidate

    truth = {"sensor_tilt_y_deg": 0.2}
    model, meas = _frame(mi, workdir, truth, 3)
    out = _diagnose(model, meas, monkeypatch, catalogue=False)
    optical = [c for c in out["candidates"] if c["effect"] in OPTICS]
    assert optical, out["problems"]
    best = optical[0]
    assert best["effect"] == "misalignment" and best["variant"] == "sensor_tilt", [(c["variant"], c["delta_bic"]) for c in optical]
    assert best["significant"] and best["delta_bic"] < -10
    v, e = best["params"]["sensor_tilt_y_deg"], best["params"]["errors"]["sensor_tilt_y_deg"]
    assert _recovered(v, e, 0.2), (v, e)
    assert best["explanation"].startswith("sensor tilted +0.") and "about its y axis" in best["explanation"]
    # scored on the pixels (the model's stars drawn with the perturbed design's PSF): most of the frame's excess
    # chi2 over the model goes away
    assert "pixel prediction" in best["explanation"] and best["heldout_delta"] == best["delta_m2lnl"]
    base = out["baseline"]["chi2_per_dof_levels"]
    assert base > 1.5 and best["chi2_per_dof"] - 1 < 0.2 * (base - 1), (base, best["chi2_per_dof"])
    new = apply_candidate(load_scene(str(model)), best, workdir / "round2.toml")
    d = load_design(load_scene(str(new)).telescope.design)
    assert d.perturbation.sensor_tilt_y_deg == pytest.approx(v)


def test_the_nominal_frame_shows_no_misalignment(mi, workdir):
    cands, problems = _optics(mi, *_frame(mi, workdir, None, 3, seed=12))
    assert not problems and cands
    assert all(c.fit.delta_bic > -10 for c in cands), [(c.fit.note, c.fit.delta_bic) for c in cands]


def test_a_gaussian_psf_frame_against_its_own_scene_is_not_misaligned(mi, workdir):
    """A scene with a Gaussian PSF and a frame made from it: the stars lack the traced design's field pattern
    (its field curvature), but they agree with the scene's own PSF, which every family must beat: nothing is
    significant (without that reference a 'defocus' of -39 +- 3 um came out at delta BIC -219)."""
    from scenes.app.render import render

    cat = workdir / "stars.csv"
    if not cat.exists():
        write_catalogue(cat)
    t = scene_table("art", "unused.fits", str(cat))
    t["psf"] = {"model": "gaussian", "fwhm_arcsec": 3.0}
    p = write_toml(workdir / "gaussian.toml", t)
    render(load_scene(str(p)), workdir / "gaussian.fits", seed=4, progress=False)
    cands, problems = _optics(mi, p, workdir / "gaussian.fits")
    assert not problems and cands
    assert all(c.fit.delta_bic > -10 for c in cands), [(c.fit.note, c.fit.delta_bic) for c in cands]
    assert "--apply changes only its design file" in cands[0].fit.explanation


#: the hidden matrix: diagonal tilt, primary decentre, defocus and sensor tilt, two amplitudes each
MATRIX = [{"sensor_piston_um": 40.0}, {"sensor_piston_um": 70.0}, {"diagonal_tilt_x_deg": 0.05},
          {"diagonal_tilt_x_deg": 0.1}, {"primary_decenter_x_mm": 0.5}, {"primary_decenter_x_mm": 1.0},
          {"sensor_tilt_x_deg": 0.1}, {"sensor_tilt_x_deg": -0.2}]


@pytest.mark.slow
@pytest.mark.parametrize("truth", MATRIX, ids=lambda t: "_".join(f"{k}={v:g}" for k, v in t.items()))
def test_the_perturbation_is_named_first_in_the_whole_ranking(mi, workdir, monkeypatch, truth):
    """Every catalogue candidate in the ranking (run_diagnose): the right perturbation is the first candidate of
    all, significant, and its value recovered within 20 % or 2 sigma; the uniform PSF changes (blur, jitter,
    elongation) that the changed stars also make lose to it. 5 x 5 cubes on 33-pixel stamps (a 21-pixel stamp cuts
    the wings of the perturbed star: the frame would show a smaller perturbation than the truth)."""
    model, meas = _frame(mi, workdir, truth, 5, stamp=33)
    out = _diagnose(model, meas, monkeypatch, catalogue=True)
    ranking = [(c["effect"], c["variant"], round(c["delta_bic"], 1), c["significant"]) for c in out["candidates"][:6]]
    print(truth, "ranking:", ranking)
    best = out["candidates"][0]
    (name, value), = truth.items()
    assert best["effect"] in OPTICS and name in best["params"] and best["significant"], ranking
    v, e = best["params"][name], best["params"]["errors"][name]
    print(truth, "->", best["variant"], v, "+-", e, "delta BIC", best["delta_bic"], "pixel scale",
          best["explanation"].split("amplitude ")[-1][:5] if "amplitude" in best["explanation"] else 1.0)
    assert _recovered(v, e, value), (name, v, e, value)
    assert out["verdict"].startswith(f"most likely missing: {best['effect']}")


@pytest.mark.slow
def test_the_nominal_frame_shows_no_misalignment_in_the_whole_ranking(mi, workdir, monkeypatch):
    model, meas = _frame(mi, workdir, None, 5, seed=12, stamp=33)
    out = _diagnose(model, meas, monkeypatch, catalogue=True)
    optical = [c for c in out["candidates"] if c["effect"] in OPTICS]
    assert optical and not any(c["significant"] for c in optical), [(c["variant"], c["delta_bic"]) for c in optical]
    assert all(c["delta_bic"] > -10 for c in optical)


def test_a_uniform_blur_loses_to_the_optics_when_the_stars_change_over_the_field():
    """field_pattern_check: a significant blur/jitter/elongation is implausible when one change of the stars'
    moments for the whole field fails (chi2 far above its dof) and the optics' family fits them far better; it
    stays plausible when the change is uniform (chi2 of the constant ~ dof) or the optics does no better."""
    from detector.signatures import Fit
    from scenes.app.compare.candidates import Candidate

    def cands():
        return [Candidate(Fit(n, {}, -1e6, 2, 10 ** 6, ""), 1.0, 0.0) for n in ("jitter", "psf_blur", "ipc")]

    def optical(chi2_uniform, chi2_family, dof=900):
        f = Fit("misalignment", {}, -2e6, 2, 10 ** 6, "", delta_adu=np.zeros((2, 2)), note="diagonal_tilt",
                state={"chi2_uniform": chi2_uniform, "dof_uniform": dof, "chi2": chi2_family, "scale": 2.0})
        return [Candidate(f, 1.0, 0.0)]

    c = cands()
    oc.field_pattern_check(c, optical(5000.0, 1800.0))
    assert [bool(x.implausible) for x in c] == [True, True, False]
    assert "varies over the field" in c[0].implausible
    for u, fam in ((950.0, 900.0), (5000.0, 4990.0)):   # uniform change; the optics no better than a constant
        c = cands()
        oc.field_pattern_check(c, optical(u, fam))
        assert not any(x.implausible for x in c)


@pytest.mark.parametrize("s0", [1.0, 1.07, 0.8, 1.45, 0.55])
def test_the_amplitude_search_finds_the_pixels_minimum(s0):
    """scale_search on a -2 ln L that is a parabola in the scale (what a small change of a perturbation's
    amplitude does to the pixels' chi2) finds its minimum within 1 %, also when it lies beyond the first bracket,
    in at most 6 evaluations; a minimum beyond the bounds stops at the bound."""
    calls = []

    def at(s):
        calls.append(s)
        return None, 1e6 * (s - s0) ** 2 - 5e6

    s, (_, m2l) = oc.scale_search(at)
    assert s == pytest.approx(s0, abs=0.01) and len(calls) <= 6, (s, calls)
    s, _ = oc.scale_search(lambda x: (None, (x - 3.0) ** 2), steps=10)
    assert s == oc.SCALE_RANGE[1]
