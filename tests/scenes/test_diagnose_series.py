"""Series diagnosis (``newtsim diagnose --series``): what one frame cannot tell apart, a series can.

The hidden-effect series of :mod:`scenes.app.validation.series_cases`: a flat series with a non-linearity
(named, beta within 20 %), a dark series with a dark-current gradient versus one with a bias ramp (told
apart), sky frames with a fixed glow versus a straylight gradient that turns with the pointing (told
apart), and null series (nothing named). Plus the command line's contract and its one-line errors.
"""

import json
import subprocess
import sys

import numpy as np
import pytest
import tomli_w

from detector import registry
from detector.effects.thermal import gradient_rate
from scenes.app.compare.series import load_series, run_series_diagnose
from scenes.app.validation.series_cases import cases, judge, write_case

CASES = {c.name: c for c in cases()}


def newtsim(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "scenes.app.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, timeout=600)


@pytest.fixture(scope="module")
def series_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("series")


def _case(series_dir, name):
    folder = series_dir / name
    if not (folder / "series.toml").is_file():
        write_case(CASES[name], folder)
    return folder / "series.toml"


@pytest.mark.parametrize("name", list(CASES))
def test_hidden_effect_series_is_told_apart(name, series_dir):
    case = CASES[name]
    d = run_series_diagnose(load_series(_case(series_dir, name)))
    row = judge(case, d)
    assert row["ok"], row
    if case.expect is None:
        return
    # the winner is shared hardware (or, for straylight, fitted frame by frame) and beats its rival on the
    # frames it was not fitted on
    best = next(c for c in d["candidates"] if c["effect"] == row["named"])
    assert best["heldout_delta"] is None or best["heldout_delta"] < -10
    assert best["shared"] == (registry()[best["effect"]].scaling != "frame")
    assert d["separation"]["best"] == best["effect"]


def test_one_frame_of_the_dark_series_cannot_tell_bias_from_dark(series_dir):
    """The reason for the series: on its longest dark alone, a bias ramp and a dark-current gradient are the
    same pattern (both fit; the single-frame diagnosis cannot name the right one with confidence)."""
    from scenes.app.compare import run_diagnose

    ser = load_series(_case(series_dir, "dark_gradient"))
    fr = ser.frames[-1]
    d = run_diagnose(fr.scene, fr.file)
    fits = {c["effect"]: c for c in d["candidates"]}
    assert fits["bias_gradient"]["delta_bic"] < -10 and fits["dark_gradient"]["delta_bic"] < -10
    ratio = fits["bias_gradient"]["delta_m2lnl"] / fits["dark_gradient"]["delta_m2lnl"]
    assert 0.8 < ratio < 1.25  # nearly the same improvement: one frame cannot tell them apart


def test_every_effect_declares_how_it_scales_across_frames():
    for name, cls in registry().items():
        if cls.__module__.startswith("detector."):
            assert cls.scaling in ("exposure", "signal", "none", "frame"), name


def test_dark_gradient_rate_is_the_linearised_ramp():
    # zero at the centre, +-(gx + gy)/2 at the corners, linear in between
    ys, xs = np.array([0.0, 50.0, 100.0]), np.array([0.0, 100.0, 200.0])
    m = gradient_rate(ys, xs, 101, 201, 0.4, -0.2)
    assert m[1, 1] == pytest.approx(0.0, abs=1e-7)
    assert m[0, 0] == pytest.approx(-0.2 + 0.1) and m[2, 2] == pytest.approx(0.2 - 0.1)
    assert m[1, 2] - m[1, 1] == pytest.approx(0.2)


def test_cli_diagnose_series_contract_apply_and_ledger(series_dir, tmp_path):
    series = _case(series_dir, "bias_ramp")
    out, apply_to, report = tmp_path / "d.json", tmp_path / "next.toml", tmp_path / "d.html"
    r = newtsim("diagnose", "--series", series, "--json", out, "--apply", apply_to, "--report", report)
    assert r.returncode == 0, r.stderr
    d = json.loads(out.read_text())
    for key in ("baseline", "candidates", "verdict", "frames", "separation", "residual_morphology", "ledger",
                "calibration", "shared_levels"):
        assert key in d, key
    assert len(d["frames"]) == 4 and all("chi2_per_dof" in f and "exposure_s" in f for f in d["frames"])
    assert {"effect", "params", "delta_bic", "heldout_delta", "plausible", "scaling", "shared"} <= set(d["candidates"][0])
    assert d["applied"]["effect"] == "bias_gradient"
    assert "[effects.bias_gradient]" in apply_to.read_text()
    nxt = tmp_path / "next.series.toml"
    assert nxt.is_file() and (tmp_path / "next.series.ledger.json").is_file()
    assert "What told the candidates apart" in report.read_text()
    # the next round: nothing significant left, the series' error has fallen
    r2 = newtsim("diagnose", "--series", nxt, "--json", tmp_path / "d2.json")
    assert r2.returncode == 0, r2.stderr
    d2 = json.loads((tmp_path / "d2.json").read_text())
    assert not d2["significant"]
    rounds = d2["ledger"]["rounds"]
    assert len(rounds) == 2 and rounds[1]["chi2_per_dof"] < rounds[0]["chi2_per_dof"]


def test_cli_compare_series_lists_every_frame(series_dir, tmp_path):
    r = newtsim("compare", "--series", _case(series_dir, "dark_null"), "--json", "-")
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    assert d["baseline"]["n_frames"] == 4 and len(d["frames"]) == 4
    assert d["calibration"]["dark_regression"]["measured_rate_e_per_s"] > 0


def _write(path, table):
    path.write_text(tomli_w.dumps(table))
    return path


@pytest.mark.parametrize("mutate, needle", [
    (lambda t: t.update(frames=t["frames"][:1]), "frames"),
    (lambda t: t["frames"][1].update(file="nosuch.fits"), "frames[1].file"),
    (lambda t: t["frames"][1].update(set={"detector.width": 96}), "frames[1]"),
    (lambda t: t.update(levels={"light_scale": "sometimes"}), "levels.light_scale"),
    (lambda t: t.update(colour="blue"), "colour"),
    (lambda t: t["frames"][0].update(set={"exposure.time_s": -3}), "frames[0].set.exposure.time_s"),
    (lambda t: t.update(frames="x"), "frames"),
])
def test_series_errors_are_one_line_naming_the_key(series_dir, tmp_path, mutate, needle):
    import tomllib

    src = _case(series_dir, "dark_null")
    table = tomllib.loads(src.read_text())
    table["scene"] = str(src.parent / table["scene"])
    for f in table["frames"]:
        f["file"] = str(src.parent / f["file"]) if f["file"] != "nosuch.fits" else f["file"]
    mutate(table)
    bad = _write(tmp_path / "bad.toml", table)
    r = newtsim("diagnose", "--series", bad)
    assert r.returncode == 2, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and needle in lines[0] and "Traceback" not in r.stderr, r.stderr


def test_series_and_positional_arguments_exclude_each_other(tmp_path):
    r = newtsim("diagnose", "a.toml", "b.fits", "--series", "s.toml")
    assert r.returncode == 2 and "not both" in r.stderr


def test_calibration_pairs_measure_gain_and_read_noise_as_characterize_does(tmp_path):
    """Two bias frames and two flats at one level in a series: the read noise from the bias pair and the
    gain by photon transfer from the flat pair (characterize's own functions) recover the camera's."""
    from scenes.app.compare.series import run_series_compare
    from scenes.app.validation.series_cases import SeriesCase, _flat

    model = _flat(160)
    frames = [{"set": {"exposure.frame": "bias", "exposure.time_s": 0.0}, "truth": {}} for _ in range(2)]
    frames += [{"set": {"exposure.time_s": 4.0}, "truth": {}} for _ in range(2)]
    series = write_case(SeriesCase("pairs", model, frames), tmp_path)
    cal = run_series_compare(load_series(series))["calibration"]
    s = load_series(series).frames[0].scene.sensor()
    (rn,), (pt,) = cal["read_noise"], cal["photon_transfer"]
    assert rn["measured_e"] == pytest.approx(s.read_noise_e, rel=0.05)
    assert pt["measured_gain_e_per_adu"] == pytest.approx(s.gain_e_per_adu, rel=0.05)


def test_a_camera_number_the_calibration_frames_contradict_is_named_and_applied(tmp_path):
    """The scene's own numbers first, on a series too (issue 23): bias pairs and flat pairs of a camera whose gain
    is 1.25x and read noise 1.5x what the scene states name ``detector.gain_e_per_adu`` and
    ``detector.read_noise_e`` with the measured values (photon transfer, bias difference), and ``--apply``
    writes them; the same frames of the scene's own camera name neither."""
    from scenes.app.compare.series import apply_series
    from scenes.app.validation.series_cases import SeriesCase, _flat
    from scenes.scene import load_scene

    model = _flat(160)
    frames = [{"set": {"exposure.frame": "bias", "exposure.time_s": 0.0}, "truth": {}} for _ in range(2)]
    frames += [{"set": {"exposure.time_s": 4.0}, "truth": {}} for _ in range(2)]
    off = write_case(SeriesCase("camera", model, frames, {"detector": {"gain_e_per_adu": 1.75, "read_noise_e": 16.5}}),
                     tmp_path / "off")
    d = run_series_diagnose(load_series(off))
    params = {c["key"]: c for c in d["candidates"] if c.get("kind") == "parameter"}
    assert params["detector.gain_e_per_adu"]["significant"] and params["detector.read_noise_e"]["significant"]
    assert params["detector.gain_e_per_adu"]["value"] == pytest.approx(1.75, rel=0.05)
    assert params["detector.read_noise_e"]["value"] == pytest.approx(16.5, rel=0.05)
    assert d["candidates"][0].get("kind") == "parameter"
    scene, nxt, _ = apply_series(load_series(off), d, tmp_path / "round2.toml")
    det = load_scene(str(scene)).sensor()
    assert det.gain_e_per_adu == pytest.approx(1.75, rel=0.05) and det.read_noise_e == pytest.approx(16.5, rel=0.05)
    assert load_series(nxt).frames[0].scene.sensor().gain_e_per_adu == pytest.approx(det.gain_e_per_adu)
    same = write_case(SeriesCase("camera", model, frames), tmp_path / "same")
    d0 = run_series_diagnose(load_series(same))
    assert not any(c["significant"] for c in d0["candidates"] if c.get("kind") == "parameter")


def test_aligned_pairs_variants_by_label_never_different_bases_by_position():
    """Two frames offered a smooth field over different boxes (labels naming the box) are not paired by
    position: only the variants under one label are, in the first frame's order."""
    from detector.signatures import Variant
    from scenes.app.compare.series import _aligned

    def v(label):
        return Variant([np.ones((2, 2), np.float32)], lambda c: {}, label=label)

    a = [v("linear ramp"), v("2-D field of 3 x 3 cosine terms over x 0..9, y 0..9 px")]
    b = [v("2-D field of 3 x 3 cosine terms over x 0..19, y 0..19 px"), v("linear ramp")]
    got = _aligned([a, b], [None, None])
    assert [[x.label for x in fr] for fr in got] == [["linear ramp"], ["linear ramp"]]
    assert _aligned([a[1:], b[:1]], [None, None]) is None
