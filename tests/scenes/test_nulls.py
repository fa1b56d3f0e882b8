"""The null-frame harness (scenes.app.validation.nulls): textbook-chain frames diagnosed against their own
scene; the Wilson interval and the thresholds read from the null distribution."""

import math

import numpy as np
import pytest

from scenes.app.validation import nulls


def test_wilson_interval_of_no_false_alarm_in_300():
    """0 of 300: the 95 % Wilson interval is [0, z^2 / (n + z^2)] = [0, 1.26 %] (Wilson 1927)."""
    lo, hi = nulls.wilson(0, 300)
    z2 = 1.959964 ** 2
    assert lo == pytest.approx(0.0, abs=1e-12) and hi == pytest.approx(z2 / (300 + z2), rel=1e-9)
    lo, hi = nulls.wilson(3, 300)
    assert lo < 0.01 < hi


def test_thresholds_hold_the_rate_on_their_null():
    """The thresholds set from a null sample hold its false-alarm rate at rate / margin."""
    rng = np.random.default_rng(1)
    ex = [{"min_dbic_gated": float(v), "min_heldout_gated": float(h), "morph_sigma": float(m)}
          for v, h, m in zip(-rng.exponential(8, 4000), -rng.exponential(5, 4000), rng.normal(0, 1, 4000))]
    t = nulls.thresholds(ex)
    assert np.mean([e["min_dbic_gated"] < t["min_dbic_gated"] for e in ex]) <= 0.005 + 1e-9
    assert np.mean([e["morph_sigma"] > t["morph_sigma"] for e in ex]) <= 0.005 + 1e-9
    assert t["min_dbic_gated"] == pytest.approx(-8 * math.log(1 / 0.005), rel=0.15)


def test_matrix_covers_both_cameras_every_frame_type_and_series():
    cases = nulls.null_cases(60, seed=3)
    singles = [c for c in cases if c["kind"] == "single"]
    assert {c["camera"] for c in singles} == {"ml11002", "imx411"}
    assert {c["frame"] for c in singles} == set(nulls.FRAMES)
    assert {c["geometry"] for c in singles} >= {"window", "full_bin8", "full_bin16", "full_bin4"}
    assert {c["frame"] for c in cases if c["kind"] == "series"} == {"series_flat", "series_dark", "series_sky"}
    assert len({c.get("seed") for c in singles}) == len(singles)  # a seed per frame
    assert nulls.null_cases(60, seed=3) == cases and nulls.null_cases(60, seed=4) != cases


@pytest.mark.skipif(not nulls.TEXTBOOK_CHAIN.exists(), reason=f"textbook chain not found: {nulls.TEXTBOOK_CHAIN}")
def test_a_textbook_null_dark_names_nothing(tmp_path):
    """A 300 s dark of a 128x128 IMX411 window through the textbook chain (its level half-way between two
    codes: the case that was named column_defects at delta BIC -5500): nothing named, the residual is noise,
    and the record holds the statistics the calibration needs."""
    case = {"id": "t0", "kind": "single", "class": "imx411/dark_long/window", "camera": "imx411",
            "frame": "dark_long", "geometry": "window", "seed": 11,
            "scene": {"detector": {"preset": "imx411", "width": 128, "height": 128, "x0": 4000, "y0": 3000},
                      "exposure": {"time_s": 300.0, "frame": "dark"}, "sky": {"stars": False}}}
    (rec,) = nulls.run_nulls(1, 0, tmp_path, workers=1, cases=[case])
    assert rec["error"] == "", rec.get("traceback")
    assert rec["significant"] == [] and not rec["morph_significant"]
    assert abs(rec["chi2_per_dof"] - 1) < 0.03
    assert rec["candidates"] and all("delta_bic" in c and "heldout_delta" in c for c in rec["candidates"])
    assert "significance_sigma" in rec["morphology"]
    s = nulls.summarise([rec])
    assert s["n"] == 1 and s["false_alarms"] == 0 and "min_dbic_gated" in s["distribution"]


@pytest.mark.skipif(not nulls.TEXTBOOK_CHAIN.exists(), reason=f"textbook chain not found: {nulls.TEXTBOOK_CHAIN}")
def test_a_textbook_binned_bias_has_no_rts_steps_of_one_code(tmp_path):
    """A 16 x 16 average-binned IMX411 bias through the textbook chain (record f0013 of the null run of seed
    2744798417): its noise is below one ADC code, and the one-frame RTS likelihood took the neighbouring codes
    of the core for steps of exactly one code (delta BIC -29, 0.44 % of the pixels). Steps are claimed only beyond
    the neighbouring codes (detector.effects.rts.RTS_MIN_CODED_STEP): nothing is named."""
    case = {"id": "f0013", "kind": "single", "class": "imx411/bias/bin16", "camera": "imx411", "frame": "bias",
            "geometry": "full_bin16", "seed": 1849678985,
            "scene": {"detector": {"preset": "imx411", "binning": 16, "binning_mode": "average"},
                      "sky": {"stars": False}, "exposure": {"time_s": 0.0, "frame": "bias"}}}
    (rec,) = nulls.run_nulls(1, 0, tmp_path, workers=1, cases=[case])
    assert rec["error"] == "", rec.get("traceback")
    assert rec["significant"] == []
    assert not any(c["effect"] == "rts_noise" and c["delta_bic"] < 0 for c in rec["candidates"])
