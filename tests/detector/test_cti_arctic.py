"""CTI against ArCTIc (arcticpy), the code the field uses for HST and Euclid: the references in
tests/data/peers/arctic/arctic_refs.npz were made by make_arctic_refs.py there, in ArCTIc's own environment
(HST ACS trap species, instant capture, express 0, empty traps before the first transfer, no pruning).

Agreement asked for (issue 25): within 2 % on every case, for the charge a source loses, every trail pixel out
to 20 px and the tail beyond. A trail pixel that crosses zero on a background is held to 2 % of the first
trail pixel instead of its own value."""

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from detector.effects.cti import cloud_volume_fraction, cti_species_changes, cti_transfer

REFS = Path(__file__).resolve().parents[1] / "data" / "peers" / "arctic" / "arctic_refs.npz"
CASES = {"parallel_points": (True, False), "serial_points": (False, True), "parallel_stars": (True, False),
         "serial_stars": (False, True), "both_stars": (True, True)}
POINT_ROW = 100  # the packets' row in the point cases (make_arctic_refs.point_columns)
#: the references never change silently: a new file from make_arctic_refs.py needs a new hash here
REFS_SHA256 = "0d9def84dd6563ed1022a5c955cb8d9d816e7f7eff0e83debfb1fef72eabd0f7"


@pytest.fixture(scope="module")
def refs():
    d = np.load(REFS)
    return {k: d[k] for k in d.files if k != "meta"}, json.loads(str(d["meta"]))


def _newtsim(img, parallel, serial, meta, express):
    args = (meta["density_per_px"], meta["release_timescale_transfers"], meta["dwell_time_transfers"],
            meta["well_fill_power"], meta["full_well_depth_e"])
    out = img
    if parallel:
        out = cti_transfer(out, *args, express=express, notch_e=meta["well_notch_depth_e"])
    if serial:
        out = cti_transfer(out.T, *args, express=express, notch_e=meta["well_notch_depth_e"]).T
    return out


def _point_errors(d_new, d_ref):
    """Relative errors of (loss, trail pixels 1-20, tail beyond 20) per column; ``d`` = output - input with
    the packets at POINT_ROW, read-out towards row 0."""
    r = POINT_ROW
    loss = np.abs(d_new[r] - d_ref[r]) / np.abs(d_ref[r])
    scale = np.maximum(np.abs(d_ref[r + 1:r + 21]), np.abs(d_ref[r + 1]))  # a zero-crossing pixel: 1st pixel
    trail = np.abs(d_new[r + 1:r + 21] - d_ref[r + 1:r + 21]) / np.where(
        np.abs(d_ref[r + 1:r + 21]) > 0.02 * np.abs(d_ref[r + 1]), np.abs(d_ref[r + 1:r + 21]), scale)
    tail_ref, tail_new = d_ref[r + 21:].sum(axis=0), d_new[r + 21:].sum(axis=0)
    tail = np.abs(tail_new - tail_ref) / np.abs(tail_ref)
    return loss, trail.max(axis=0), tail


def test_references_are_arctic_express_0_with_the_stated_parameters(refs):
    data, meta = refs
    assert hashlib.sha256(REFS.read_bytes()).hexdigest() == REFS_SHA256
    assert meta["express"] == 0 and meta["empty_traps_for_first_transfers"] and meta["prune_frequency"] == 0
    assert meta["density_per_px"] == [0.6, 1.6, 1.4] and meta["release_timescale_transfers"] == [0.74, 7.7, 37.0]
    assert meta["arcticpy_version"] and set(CASES) == {k[:-3] for k in data if k.endswith("_in")}


@pytest.mark.parametrize("case", CASES)
def test_exact_mode_equals_arctic(refs, case):
    """express=0 follows every pixel's traps, as ArCTIc with express 0: the same numbers to rounding."""
    data, meta = refs
    img, ref = data[case + "_in"], data[case + "_out"]
    out = _newtsim(img, *CASES[case], meta, express=0)
    d_new, d_ref = out - img, ref - img
    assert np.abs(d_new - d_ref).max() < 1e-9 * np.abs(d_ref).max()
    if "points" in case:
        if case.startswith("serial"):
            d_new, d_ref = d_new.T, d_ref.T
        for err in _point_errors(d_new, d_ref):
            assert np.all(err < 0.02), err
    else:
        assert abs(d_new.sum() / d_ref.sum() - 1) < 0.02


def test_express_pools_approach_arctic_as_express_grows(refs):
    """express=E follows E pools per column (exact to first order in the CTI): on stars the charge lost and
    every pixel agree with ArCTIc within 2 % already at E=1; on isolated packets (the worst case: 3.6 traps per
    pixel take 14 % of a 100 e- packet) the error falls as 1/E."""
    data, meta = refs
    img, ref = data["parallel_stars_in"], data["parallel_stars_out"]
    d_ref = ref - img
    d1 = _newtsim(img, True, False, meta, express=1) - img
    assert abs(d1.sum() / d_ref.sum() - 1) < 0.02
    assert np.abs(d1 - d_ref).max() < 0.02 * np.abs(d_ref).max()
    img, ref = data["parallel_points_in"], data["parallel_points_out"]
    worst = []
    for e in (1, 8):
        errs = _point_errors(_newtsim(img, True, False, meta, express=e) - img, ref - img)
        worst.append(max(float(np.max(x)) for x in errs))
    assert worst[1] < 0.5 * worst[0] and worst[1] < 0.03, worst


@pytest.mark.parametrize("express, levels", [(0, None), (1, None), (3, None), (1, 3), (0, 3)])
def test_charge_is_conserved(express, levels):
    """What the image loses is in the traps at the end of the read-out (the overscan's charge); also when
    the volume levels kept per pool are few and adjacent ones are merged."""
    rng = np.random.default_rng(5)
    img = rng.poisson(40.0, (90, 7)).astype(np.float64)
    img[30, 2] += 30000.0
    img[60, 5] += 800.0
    out, trapped = cti_transfer(img, [0.3, 0.8], [1.5, 12.0], 1.0, 0.5, 80000.0, first_transfers=20,
                                return_trapped=True, express=express, max_watermarks=levels)
    assert np.allclose(out.sum(axis=0) + trapped, img.sum(axis=0), rtol=1e-12, atol=1e-9)
    assert np.all(trapped > 0) and out[30, 2] < img[30, 2] and out[31:40, 2].sum() > img[31:40, 2].sum()


def test_weak_cti_express_agrees_with_exact():
    """At a realistic trap density (0.1 per pixel) the single pool (express=1) is within 0.5 % of the exact
    mode on a star's loss and trail, with a window offset (the packets cross pixels below the window)."""
    img = np.full((120, 3), 30.0)
    img[80] += [300.0, 5000.0, 60000.0]
    args = ([0.017, 0.045, 0.038], [0.74, 7.7, 37.0], 1.0, 0.478, 84700.0)
    ex = cti_transfer(img, *args, first_transfers=31, express=0) - img
    e1 = cti_transfer(img, *args, first_transfers=31, express=1) - img
    assert np.all(np.abs(e1[80] - ex[80]) < 0.005 * np.abs(ex[80]))
    assert np.all(np.abs(e1[81:101] - ex[81:101]).sum(axis=0) < 0.005 * np.abs(ex[81:101]).sum(axis=0))


def test_species_shares_are_each_species_alone_to_first_order():
    """The diagnosis's templates (one pass, three release times): each species' share of the change equals the
    change that species makes alone within the second order of the density (0.01 traps per pixel each: a
    species sees packets the others changed by ~1e-4 of their charge), and the shares add up to the change of
    all three together exactly."""
    rng = np.random.default_rng(8)
    img = rng.poisson(200.0, (160, 40)).astype(np.float64)
    img[40, 5:9] += [300.0, 5000.0, 30000.0, 60000.0]
    taus, dens, first = [0.74, 7.7, 37.0], [0.01] * 3, 25
    ch = cti_species_changes(img, dens, taus, 1.0, 0.478, 84700.0, first)
    together = cti_transfer(img, dens, taus, 1.0, 0.478, 84700.0, first) - img
    assert np.allclose(ch.sum(axis=0), together, rtol=1e-12, atol=1e-9)
    for k, tau in enumerate(taus):
        alone = cti_transfer(img, [0.01], [tau], 1.0, 0.478, 84700.0, first) - img
        assert np.abs(ch[k] - alone).max() < 1e-3 * np.abs(alone).max()
        assert np.abs(ch[k, 41:61, 5:9] - alone[41:61, 5:9]).sum() < 1e-3 * np.abs(alone[41:61, 5:9]).sum()


def test_small_packet_after_a_big_one_refills_the_levels_it_reaches():
    """The bug this model fixes: 20 transfers after a bright packet, the traps it filled (release time 5
    transfers) hold e^-4 = 2 % of their charge; a fainter packet refills the levels it reaches almost as on an
    empty column. Comparing its reach with the *total* trapped charge (the old model) made it lose only 0.74x
    of that (the bright packet's high, emptied levels counted as if they were within its reach)."""
    def loss(faint_e, bright_e, express):
        col = np.zeros((60, 1))
        col[20, 0] = bright_e
        col[40, 0] = faint_e
        return faint_e - cti_transfer(col, [1.0], [5.0], 1.0, 0.5, 1e5, express=express)[40, 0]

    for express in (0, 1):
        for faint in (100.0, 1000.0):
            ratio = loss(faint, 50000.0, express) / loss(faint, 0.0, express)
            assert 0.9 < ratio < 1.0, (express, faint, ratio)


def test_cloud_volume_is_arctic_fill_law():
    v = cloud_volume_fraction(np.array([-5.0, 0.0, 10.0, 1000.0, 84700.0, 1e6]), 84700.0, 0.478, notch_e=10.0)
    assert v[0] == v[1] == v[2] == 0.0 and v[4] == v[5] == 1.0
    assert np.isclose(v[3], ((1000.0 - 10.0) / (84700.0 - 10.0)) ** 0.478)


def test_exact_mode_on_a_large_window_is_one_clear_error():
    """express=0 follows (rows + y0) x cols trap pools: a full frame is refused with the key and the way out."""
    from detector import build_effects, make_sensor
    from detector.errors import DetectorError

    with pytest.raises(DetectorError, match="express"):
        build_effects({"cti": {"express": 0}}, make_sensor("ml11002", {}))
    small = make_sensor("ml11002", {"width": 40, "height": 30, "x0": 100, "y0": 10})
    assert build_effects({"cti": {"express": 0}}, small)


@pytest.mark.parametrize("express", [0, 2])
def test_the_chain_applies_the_function_with_the_window_offset(express):
    """Detector.moments couples the mean charge: the window's rows cross y0 + j + 1 pixels."""
    from detector import Detector, build_effects, make_sensor

    s = make_sensor("ml11002", {"width": 20, "height": 40, "x0": 300, "y0": 25, "dark_current_e_per_s": 0.0})
    sig = np.full(s.shape, 80.0, np.float32)
    sig[12, 5] = 20000.0
    eff = {"cti": {"density_per_px": [0.4, 0.2], "release_time_s": [1e-3, 6e-3], "express": express}}
    mean = Detector(s, build_effects(eff, s)).moments(sig, 1.0)[0]
    expect = cti_transfer(sig, [0.4, 0.2], [1e-3, 6e-3], 5.01e-4, 0.478, s.full_well_e,
                          first_transfers=s.roi_y0 + 1, express=express)
    assert np.allclose(mean, expect / s.gain_e_per_adu + s.bias_adu, atol=0.05)  # the ADC rounds: no offset
    assert mean[13:20, 5].sum() > mean[5:12, 5].sum() + 5  # the trail, away from the register


def test_species_faster_than_a_transfer_release_everything_and_stay_finite():
    """A species with tau << t_d gives back at the next transfer all it took: the next pixel gets most of the
    loss (the rest it passes on, recaptured and released again)."""
    col = np.zeros((50, 2))
    col[10] = [5000.0, 50.0]
    for express in (0, 1):
        out, trapped = cti_transfer(col, [0.5], [1e-6], 1.0, 0.5, 1e5, express=express, return_trapped=True)
        assert np.all(np.isfinite(out)) and np.allclose(out.sum(axis=0) + trapped, col.sum(axis=0))
        loss = col[10] - out[10]
        assert np.all(loss > 0) and np.all(out[11] > 0.5 * loss) and np.all(out[14:].sum(axis=0) < 0.1 * loss)
