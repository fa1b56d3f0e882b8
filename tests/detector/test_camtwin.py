"""The camera itself from its calibration frames (detector.characterize.camera_twin and the map effects),
the dark-rate population law, and the sanity checks of characterize.

Independent references: the parameters the synthetic frames were made with (plain numpy, not the code under
test), analytic standard errors, and on the real SBIG STL-1001E set the held-out frames themselves.
"""

from __future__ import annotations

import glob
import math
from pathlib import Path

import numpy as np
import pytest
from astropy.io import fits

from detector import Detector, DetectorError, build_effects, make_sensor
from detector.characterize import (
    bias_structure,
    camera_twin,
    characterize,
    clipped_stats,
    dark_rate_map,
    emit_population_dict,
    fit_rate_laws,
    write_twin,
)
from detector.effects.maps import draw_excess_rates, tail_probabilities

SBIG = Path(__file__).resolve().parents[2] / ".." / "shared" / "realdata" / "sbig_stl1001e_calib"


def _sbig():
    if not SBIG.is_dir():
        pytest.skip(f"../shared/realdata not found: {SBIG} (real SBIG STL-1001E calibration frames)")
    return SBIG


# ------------------------------------------------------------------------------------------------------------
# pure functions on synthetic arrays
# ------------------------------------------------------------------------------------------------------------

def test_bias_structure_is_noise_free():
    rng = np.random.default_rng(3)
    h, w, read = 400, 300, 6.0
    cols = rng.normal(0, 2.0, w)
    truth = 1000 + cols[None, :] + np.zeros((h, 1))
    master = truth + rng.normal(0, read / math.sqrt(2), (h, w))
    m, info = bias_structure(master.astype(np.float32), read, 2)
    # the map's error is the column means' noise, read/sqrt(2 h) ~ 0.2 ADU, not the master's 4.2 ADU
    assert np.std(m - truth) < 4 * read / math.sqrt(2 * h)
    assert not info["pixel_fixed_pattern_significant"]
    assert info["master_noise_adu"] == pytest.approx(read / math.sqrt(2))


def test_dark_rate_map_recovers_rates_and_dsnu():
    rng = np.random.default_rng(4)
    h, w, read, g = 300, 300, 5.0, 2.0
    bias = np.full((h, w), 500.0, np.float32)
    rate = 0.2 * (1 + 0.25 * rng.standard_normal((h, w)))  # DSNU 25 %, ADU/s
    hot = rng.random((h, w)) < 0.005
    rate[hot] = rng.uniform(2, 20, hot.sum())
    ts = np.array([10.0, 60.0, 300.0])
    darks = [(bias + rate * t + rng.normal(0, 1, (h, w)) * np.sqrt(read ** 2 + rate * t / g)).astype(np.float32)
             for t in ts]
    r, se, stuck, info = dark_rate_map(ts, darks, bias, 0.0, read, g, 65535.0)
    z = (r[hot] - rate[hot]) / se[hot]
    assert abs(np.mean(z)) < 0.2 and 0.8 < np.std(z) < 1.2  # hot pixels: unbiased, errors right
    assert info["dsnu_std_adu_per_s"] == pytest.approx(0.05, rel=0.05)  # measured DSNU, noise removed
    assert clipped_stats(r[~hot], 5.0)["std"] == pytest.approx(0.05, rel=0.06)  # the map has that spread
    assert not stuck.any()


def test_pareto_law_comes_back():
    rng = np.random.default_rng(5)
    x = draw_excess_rates(rng, 20000, "pareto", 0.5, 1.3, math.inf, 0, 1, [])
    f = fit_rate_laws(x, 0.5, 1000.0)
    assert abs(f["pareto"]["alpha"] - 1.3) < 4 * f["pareto"]["alpha_se"]
    assert f["preferred"] == "pareto" and f["pareto"]["ks"] < 0.02


def test_empirical_law_reproduces_the_tail():
    rng = np.random.default_rng(6)
    x = np.exp(rng.normal(0, 2, 30000)) + 1.0
    p = tail_probabilities(x.size)
    q = np.quantile(x, p)
    y = draw_excess_rates(rng, 30000, "empirical", q[0], 1, math.inf, 0, 1, list(q), list(p))
    for thr in (10.0, 100.0, 1000.0):
        n_x, n_y = (x > thr).sum(), (y > thr).sum()
        assert abs(n_y - n_x) < 4 * math.sqrt(n_x) + 0.05 * n_x, thr


# ------------------------------------------------------------------------------------------------------------
# the map effects through the detector chain
# ------------------------------------------------------------------------------------------------------------

def test_dark_map_effect(tmp_path):
    rng = np.random.default_rng(7)
    R = rng.uniform(0.5, 5.0, (64, 64)).astype(np.float32)
    sig = np.full_like(R, 0.1)
    stuck = fits.BinTableHDU.from_columns([fits.Column("x", "J", array=[3]), fits.Column("y", "J", array=[5]),
                                           fits.Column("value_adu", "E", array=[4000.0])], name="STUCK")
    p = tmp_path / "d.fits"
    fits.HDUList([fits.PrimaryHDU(R), fits.ImageHDU(sig, name="SIGMA"), stuck]).writeto(p)
    s = make_sensor("ml11002", {"sensor_width_px": 64, "sensor_height_px": 64, "dark_current_e_per_s": 1.0,
                                "gain_e_per_adu": 2.0, "bias_adu": 100.0})
    det = Detector(s, build_effects({"dark_map": {"path": str(p), "sigma_hdu": "SIGMA", "stuck_hdu": "STUCK",
                                                  "offset_e": 4.0}}, s))
    mu = det.expose(0.0, 100.0, 1, noiseless=True)
    exp = R * 100 + 4.0
    exp[5, 3] = mu[5, 3]  # noiseless: electrons before the ADC, stuck acts after it
    np.testing.assert_allclose(mu, exp, rtol=1e-5)
    mean, var, _ = det.moments(0.0, 100.0)
    assert mean[5, 3] == 4000.0  # stuck value
    # variance: shot (R t + offset) + read^2 + the map's error (0.1 x 100)^2, in ADU^2, + 1/12
    v = (R[0, 0] * 100 + 4 + s.read_noise_e ** 2 + 100.0) / 4 + 1 / 12
    assert var[0, 0] == pytest.approx(v, rel=1e-4)
    # a bias frame (0 s) has no dark signal and no stuck value
    assert np.all(det.expose(0.0, 0.0, 1, noiseless=True) == 0)


def test_flat_map_sigma_and_column_offsets(tmp_path):
    F = np.full((32, 32), 2.0, np.float32)
    p = tmp_path / "f.fits"
    fits.HDUList([fits.PrimaryHDU(F), fits.ImageHDU(np.full_like(F, 0.02), name="SIGMA")]).writeto(p)
    s = make_sensor("ml11002", {"sensor_width_px": 32, "sensor_height_px": 32, "gain_e_per_adu": 1.0,
                                "dark_current_e_per_s": 0.0})
    det = Detector(s, build_effects({"flat_map": {"path": str(p), "sigma_hdu": "SIGMA"}}, s))
    _, var, _ = det.moments(np.full((32, 32), 10000.0, np.float32), 1.0)
    # relative error 0.02 / mean 2.0 = 1 %: (0.01 x 10000)^2 added to the shot noise 10000
    assert var[0, 0] == pytest.approx(10000 + 100 ** 2 + s.read_noise_e ** 2 + 1 / 12, rel=1e-4)
    s2 = make_sensor("ml11002", {"sensor_width_px": 4096, "sensor_height_px": 8})
    eff = build_effects({"column_offsets": {"sigma_adu": 3.0}}, s2)[0]
    assert np.std(eff.offsets) == pytest.approx(3.0, rel=4 / math.sqrt(2 * 4096))


# ------------------------------------------------------------------------------------------------------------
# sanity checks (issue 16): one DetectorError each
# ------------------------------------------------------------------------------------------------------------

@pytest.fixture
def frames(tmp_path):
    rng = np.random.default_rng(1)

    def make(name, t, value=1000.0, noise=5.0, shape=(64, 64)):
        h = fits.Header()
        if t is not None:
            h["EXPTIME"] = t
        data = np.clip(value + rng.normal(0, noise, shape), 0, 65535).astype(np.uint16)
        fits.writeto(tmp_path / name, data, h, overwrite=True)
        return str(tmp_path / name)

    return make


def test_sanity_checks(frames):
    b = [frames("b0.fits", 0.0), frames("b1.fits", 0.0)]
    d = [frames("d10.fits", 10.0, 1010), frames("d20.fits", 20.0, 1020)]
    cases = [
        (dict(bias_paths=[b[0], b[0]], dark_paths=d), "same pixels"),
        (dict(bias_paths=b, dark_paths=[frames("sat.fits", 10.0, 65535, 0.0), d[1]]), "saturated"),
        (dict(bias_paths=b, dark_paths=[d[0], frames("d10b.fits", 10.0, 1010)]), "at least two different"),
        (dict(bias_paths=b, dark_paths=[frames("z0.fits", 0.0), frames("z1.fits", 0.0)]), "at least two different"),
        (dict(bias_paths=b, dark_paths=d, flat_paths=[frames("f1.fits", 1.0, 20000, 100),
                                                      frames("f2.fits", 2.0, 20000, 100)]), "different exposure"),
        (dict(bias_paths=[frames("be.fits", 5.0), b[1]], dark_paths=d), "bias frame has an exposure time"),
        (dict(bias_paths=[frames("zero.fits", 0.0, 0.0, 0.0), b[1]], dark_paths=d), "constant"),
        (dict(bias_paths=b, dark_paths=d, hot_sigma=-3), "sigma"),
        (dict(bias_paths=b, dark_paths=d, hot_sigma=1000), "sigma"),
    ]
    for kw, msg in cases:
        with pytest.raises(DetectorError, match=msg):
            characterize(**kw)
    # a good set passes and negative dark current is a warning
    neg = [frames("n10.fits", 10.0, 1000), frames("n20.fits", 20.0, 995)]
    res = characterize(b, neg, holdout_exposures=[])
    assert any("negative dark current" in w for w in res["warnings"])


def test_cli_exit_2_one_line(frames, capsys):
    from scenes.app.cli import main

    b = frames("b0.fits", 0.0)
    with pytest.raises(SystemExit) as e:
        main(["characterize", "--bias", b, b, "--dark", frames("d1.fits", 10.0), frames("d2.fits", 20.0)])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "same pixels" in err[0] and "b0.fits" in err[0]


# ------------------------------------------------------------------------------------------------------------
# the real SBIG STL-1001E: fit on bias + 10/60/300 s, predict 30 s and 150 s; predict a flat
# ------------------------------------------------------------------------------------------------------------

def _stats(x):
    med = float(np.median(x))
    return med, clipped_stats(x, 3.0)["std"], [int(np.count_nonzero(x - med > t)) for t in (100, 200, 1000)]


@pytest.fixture(scope="module")
def twin_scenes(tmp_path_factory):
    import tomli_w

    d = _sbig()
    out = tmp_path_factory.mktemp("twin")
    bias = sorted(glob.glob(str(d / "bias*")))
    darks = [str(d / f"darks-expos{t}s-Neg10-Vis.00000000.DARK.FIT") for t in (10, 60, 300)]
    res = characterize(bias, darks, holdout_exposures=[])
    maps, info = camera_twin(res, bias, darks)
    (out / "cam.toml").write_text(tomli_w.dumps(write_twin(out / "cam.toml", res, maps, info)))
    (out / "pop.toml").write_text(tomli_w.dumps(emit_population_dict(res, info)))
    return out, info


@pytest.mark.realdata
@pytest.mark.parametrize("kind,tol", [("cam", 0.10), ("pop", 0.20)])
def test_sbig_predicts_held_out_darks(twin_scenes, kind, tol):
    from scenes.app.render import render
    from scenes.scene import load_scene

    out, _ = twin_scenes
    for t in (30, 150):
        render(load_scene(str(out / f"{kind}.toml"), [f"exposure.time_s={t}"]), str(out / f"{kind}{t}.fits"), seed=5)
        sim = _stats(fits.getdata(out / f"{kind}{t}.fits").astype(np.float64))
        meas = _stats(fits.getdata(SBIG / f"darks-expos{t}s-Neg10-Vis.00000000.DARK.FIT").astype(np.float64))
        assert abs(sim[0] - meas[0]) <= 1.0, (kind, t, sim, meas)
        assert sim[1] == pytest.approx(meas[1], rel=0.05), (kind, t, sim, meas)
        for a, b in zip(sim[2], meas[2]):
            assert a == pytest.approx(b, rel=tol), (kind, t, sim, meas)


@pytest.mark.realdata
def test_sbig_twin_maps_and_laws(twin_scenes):
    out, info = twin_scenes
    with fits.open(out / "cam_dark.fits") as h:
        assert {"SIGMA", "STUCK", "DEFECTS"} <= {x.name for x in h}
        tab = h["DEFECTS"].data
        # every defect's rate is its map value, at its real position
        assert np.allclose(h[0].data[tab["y"], tab["x"]], tab["rate_e_per_s"], rtol=1e-5)
    laws = info["dark"]["rate_laws_adu_per_s"]
    assert laws["preferred"] in ("pareto", "lognormal", "weibull_t2") and laws["delta_aic"][laws["preferred"]] == 0


@pytest.mark.realdata
def test_sbig_second_flat_from_the_first(tmp_path):
    import tomli_w

    from scenes.app.compare import run_compare
    from scenes.scene import load_scene

    d = _sbig()
    bias = sorted(glob.glob(str(d / "bias*")))
    darks = sorted(glob.glob(str(d / "darks*")))
    flats = sorted(glob.glob(str(d / "flat*")))
    res = characterize(bias, darks, holdout_exposures=[])
    maps, info = camera_twin(res, bias, darks, [flats[0]])
    sc = write_twin(tmp_path / "fl.toml", res, maps, info)
    t, S = info["flat"]["exposure_s"], info["flat"]["signal_adu"]
    sc["exposure"] = {"time_s": t, "frame": "light"}
    sc["sky"] = {"flat_e_per_s": S * info["gain_e_per_adu"] / t, "stars": False}
    (tmp_path / "fl.toml").write_text(tomli_w.dumps(sc))
    r = run_compare(load_scene(str(tmp_path / "fl.toml"), []), flats[1])
    assert r["chi2_per_dof"] == pytest.approx(1.0, abs=0.10)
