"""newtsim diagnose on effects in forms it has not been told (issue 10; scenes/app/validation/unseen.py).

Catalogue effects in functional forms that neither the plugins nor ``hidden_effects.py`` use must be named
first (one of the case's accepted names, significant) and the error must fall by half after one apply; an
effect that no plugin models must get no significant plausible catalogue name, and the diagnosis's
``residual_morphology`` must describe it with the right kind (additive / multiplicative / redistributed) and
geometry; a frame with nothing hidden must give no significant candidate.

The unmarked tests run a fast subset (three catalogue forms, two effects in no plugin, one null frame:
about 1-2 min on 2 cores); the whole set (92 cases, ~12 min on 2 cores) is ``slow``. Cases that today's
diagnosis fails are ``xfail(strict=False)`` (a known limit): the baseline in
docs/diagnose_validation.md, section "Unseen forms and out-of-catalogue effects (issue 10)".
"""


import pytest
from helpers import shared_row

from detector.morphology import FAMILIES
from scenes.app.validation import unseen

NS = vars(unseen)
CASES = NS["CASES"]

#: the fast subset: the issue's own examples (a vignetting inside a window, a quadratic straylight), a
#: catalogue effect in another law, an out-of-catalogue multiplicative local pattern and a variance gradient,
#: one null frame
FAST = ("vig_gauss_window", "sky_quadratic", "rows_telegraph", "dust_donuts", "readnoise_gradient", "null_dark")

#: cases the diagnosis still fails (run of 2026-11-25 after issue 10's sixth round, seed 11; before and after in
#: docs/diagnose_validation.md)
FAILS_TODAY: set[str] = {
    # a probe added in the sixth round: an amplifier's undershoot trailing every star along its row is found
    # (light locked to the sources, one-sided, its map halves the error) but described as flux moved about
    # them, not taken: the kernel's few angular terms cannot hold a one-pixel-wide trail without a ring
    "amp_undershoot"}

ISSUE = "a known limit of the diagnosis (FAILS_TODAY, docs/diagnose_validation.md)"

_CACHE: dict = {}


def _row(name, tmp_path_factory):
    # keyed apart from the hidden-effect suite's rows (its null cases share the base names)
    return shared_row(_CACHE, ("unseen", name), tmp_path_factory, lambda d: NS["run_case"](name, d))


def _check(row):
    assert row.get("first") != "error", row.get("traceback")
    group = row["group"]
    if group == "catalogue":
        # the case is detectable at all: its exact template removes more chi2 than a BIC test of one amplitude
        # needs (2 ln N ~ 25) with room for a form to be found (a case below that measures nothing)
        assert row.get("truth_chi2") is None or row["truth_chi2"] > 100, row.get("truth_chi2")
        assert row["first"] in row["accept"], (row["case"], row["ranking"])
        assert row["first_delta_bic"] < -10
        # the error falls by at least half after one apply (or was within the noise: nothing to halve)
        assert NS["error_halved"](row), (row["metric"], row["before"], row.get("after"))
    elif group == "ooc":
        # no significant, plausible catalogue name: the honest answer is a description
        assert not row["confidently_wrong"], (row["case"], row["wrong_names"])
        morph = row["residual_morphology"] or {}
        assert row["morphology_match"], (row["case"], row["kind"], row["geometry"], morph)
        # the empirical map offered by the morphology still halves the error
        assert NS["error_halved"](row), (row["metric"], row["before"], row.get("after"))
    else:
        assert row["first_any"] == "none", row["ranking"]


def _param(names):
    return [pytest.param(n, marks=pytest.mark.xfail(strict=False, reason=ISSUE)) if n in FAILS_TODAY else n
            for n in names]


def test_the_set_is_as_large_as_the_issue_asks():
    """>= 40 cases; every catalogue effect with a signature in >= 2 forms; >= 6 effects in no plugin with an
    expected kind and geometry from the vocabulary; a null frame for every base; both cameras; strong and
    weak amplitudes; full (binned) sensors and windows."""
    import detector

    with_signature = {n for n, e in detector.registry().items() if getattr(e, "signature", None)}
    cat = [c for c in CASES.values() if c.group == "catalogue"]
    ooc = [c for c in CASES.values() if c.group == "ooc"]
    assert len(cat) + len(ooc) >= 40
    for name in with_signature:
        assert sum(c.effect == name for c in cat) >= 2, name
    assert len(ooc) >= 6
    vocab = {g for _k, g in FAMILIES} - {"noise"}  # the morphology's geometry words
    for c in ooc:
        assert c.kind in ("additive", "multiplicative", "redistributed", "mixed") and set(c.geometry) <= vocab
    # every base scene has its null case (the random-forms generator adds quarter-size "_s" copies of the bases
    # to the same table when it is imported in the same process; they have their own draws)
    assert {c.base for c in CASES.values() if c.group == "null"} == {b for b in NS["BASES"] if not b.endswith("_s")}
    presets = {NS["BASES"][c.base]["detector"]["preset"] for c in cat}
    assert presets == {"ml11002", "imx411"}
    assert {c.strength for c in cat} == {"strong", "weak"}
    assert any(NS["BASES"][c.base]["detector"].get("binning", 1) > 1 for c in cat)


@pytest.mark.parametrize("name", _param(FAST))
def test_unseen_fast(name, tmp_path_factory):
    _check(_row(name, tmp_path_factory))


@pytest.mark.slow
@pytest.mark.parametrize("name", _param([n for n in CASES if n not in FAST]))
def test_unseen_full_set(name, tmp_path_factory):
    _check(_row(name, tmp_path_factory))


@pytest.mark.slow
@pytest.mark.xfail(strict=False, reason=ISSUE)
def test_unseen_goals(tmp_path_factory):
    """The issue's goals on the whole set: named first >= 95 %, confidently wrong 0, every out-of-catalogue case
    described, the error halved everywhere, null frames clean."""
    rows = [_row(n, tmp_path_factory) for n in CASES]
    s = NS["summary"](rows)
    assert s["named_first"]["rate"] >= 0.95, s["named_first"]
    assert s["confidently_wrong"]["n"] == 0, s["confidently_wrong"]
    assert s["morphology_match"]["n"] == s["morphology_match"]["of"], s["morphology_match"]
    assert s["error_halved"]["n"] == s["error_halved"]["of"], s["error_halved"]
    assert s["null_clean"]["n"] == s["null_clean"]["of"], s["null_clean"]


# --- the real-world forms of the pixel-coupling, CTI, RTS and straylight cases: checked against their laws --------

def _tile(sensor, exptime_s=10.0, seed=3):
    from detector.effects.base import Tile

    w, h = sensor.roi_shape
    return Tile(sensor, 0, sensor.roi_y0, sensor.roi_y0 + h, sensor.roi_x0, sensor.roi_x0 + w, exptime_s, seed)


def _star(n=31, flux_e=1e5, sigma=1.2):
    import numpy as np

    t = np.arange(n) - n // 2
    g = np.exp(-(t[:, None] ** 2 + t[None, :] ** 2) / (2 * sigma ** 2))
    return (flux_e * g / g.sum()).astype(np.float32)


def _r2(img):
    import numpy as np

    n = img.shape[0]
    t = np.arange(n) - n // 2
    return float((img * (t[:, None] ** 2 + t[None, :] ** 2)).sum() / img.sum())


def test_brighter_fatter_forms_conserve_charge_and_widen_faster_than_linear_when_nonlinear():
    """Both forms move charge (total kept to float32 precision) outwards from a bright star; the widening of the
    linear (Coulomb) form grows as the flux, the charge-dependent (Gaussian) form's faster."""
    from tests.helpers import small_sensor

    s = small_sensor(width=31, height=31)
    tile = _tile(s)
    for cls, kw, superlinear in ((NS["CoulombBF"], {"a10_per_e": 2e-7, "r0_px": 0.5}, False),
                                 (NS["GaussianNonlinearBF"], {"a10_per_e": 2e-7, "sigma_px": 0.6, "q_nl_frac": 0.5},
                                  True)):
        eff = cls(s, **kw)
        widen = []
        for flux in (2e5, 4e5):
            q = _star(flux_e=flux)
            out = eff.couple(tile, q, 0, 0)
            assert abs(float(out.sum()) / float(q.sum()) - 1) < 1e-5
            widen.append(_r2(out) - _r2(q))
        assert widen[0] > 0
        ratio = widen[1] / widen[0]
        assert (ratio > 2.2) if superlinear else (abs(ratio - 2) < 0.1), (cls.__name__, ratio)


def test_ipc_forms_read_the_given_fractions_in_the_neighbours():
    """A single charged pixel is read in its neighbours with the kernel's fractions (right / left / up / down,
    the signal-dependent coupling alpha(Q) = a0 + (a1 - a0) Q / FW), the total conserved."""
    import numpy as np

    from tests.helpers import small_sensor

    s = small_sensor(preset="imx411", width=9, height=9)
    tile = _tile(s)
    q = np.zeros((9, 9), np.float32)
    q[4, 4] = 4e4
    out = NS["AsymmetricIPC"](s, left=0.004, right=0.012, up=0.009, down=0.005, diag=0.001).couple(tile, q, 0, 0)
    assert np.allclose([out[4, 5], out[4, 3], out[5, 4], out[3, 4], out[5, 5]] / q[4, 4],
                       [0.012, 0.004, 0.009, 0.005, 0.001], rtol=1e-5)
    assert abs(out.sum() / q.sum() - 1) < 1e-6
    alpha = 0.0015 + (0.005 - 0.0015) * 4e4 / s.full_well_e
    out = NS["SignalDependentIPC"](s, a0=0.0015, a1=0.005).couple(tile, q, 0, 0)
    assert np.allclose(out[[3, 5, 4, 4], [4, 4, 3, 5]] / q[4, 4], alpha, rtol=1e-5)
    assert abs(out[4, 4] / q[4, 4] - (1 - 4 * alpha)) < 1e-6 and abs(out.sum() / q.sum() - 1) < 1e-6


def test_cti_forms_trail_behind_the_source_and_scale_with_their_laws():
    """A bright pixel leaves a trail on the rows read after it (higher rows), decaying by exp(-1 / release) per
    row; the column-dependent form's trail follows its column's density; the constant-fraction form loses the
    same fraction of a packet at every signal (beta = 1)."""
    import numpy as np

    from tests.helpers import small_sensor

    s = small_sensor(width=8, height=60)
    tile = _tile(s)
    q = np.zeros((60, 8), np.float32)
    q[10, :] = 2e4
    eff = NS["ColumnCTI"](s, density=0.05, col_sigma_ln=0.5, trend=0.8, release_transfers=3.0, beta=0.35)
    out = eff.couple(tile, q, 0, 0)
    trail = out[11:30].astype(float)
    assert (trail[:5] > 0).all() and (out[:10] == 0).all()
    assert np.allclose(trail[2] / trail[1], np.exp(-1 / 3.0), rtol=1e-3)
    lost = q[10] - out[10]
    colf = np.exp(0.5 * np.random.default_rng(s.hardware_seed + 17).standard_normal(s.sensor_width_px) - 0.125)
    _ys, xs = tile.pixel_centres()
    rho = colf[xs.astype(int)] * (1 + 0.8 * (xs / (s.sensor_width_px - 1) - 0.5))
    assert np.allclose(lost / lost.mean(), rho / rho.mean(), rtol=1e-4)  # no trap full: capture ~ density
    lin = NS["LinearSlowCaptureCTI"](s, density=0.01, capture=0.5, release_transfers=12.0)
    frac = [float(1 - lin.couple(tile, q * f, 0, 0)[10, 0] / (q[10, 0] * f)) for f in (0.1, 1.0)]
    assert frac[0] > 0 and abs(frac[1] / frac[0] - 1) < 1e-6


def test_rts_forms_step_both_ways_with_their_variance():
    """Zero-mean CDS offsets; the three-state trap, sampled far apart (CDS interval >> dwell times), gives
    independent states of the stationary law pi_i ~ tau_i: Var = 2 A^2 Var_pi(level); the two-trap pixel steps
    up and down by more than one amplitude."""
    import numpy as np

    from tests.helpers import small_sensor

    s = small_sensor(preset="imx411", width=400, height=400)
    tile = _tile(s)
    eff = NS["ThreeStateRTS"](s, fraction=0.05, amp_lo_e=20.0, amp_hi_e=20.0, mid=0.45, tau_lo_s=1e-6,
                              tau_hi_s=1e-5, cds_s=1.0)
    sel = (eff.rows >= tile.y0) & (eff.rows < tile.y1) & (eff.cols >= tile.x0) & (eff.cols < tile.x1)
    data = np.zeros(tile.shape, np.float32)
    eff.apply(None, tile, data)
    off = data[eff.rows[sel] - tile.y0, eff.cols[sel] - tile.x0]
    lv = np.array([0.0, 1.0, 0.45])
    pi = eff.pi[sel]
    var = 2 * 400.0 * float(np.mean((pi * lv ** 2).sum(1) - (pi * lv).sum(1) ** 2))
    n = off.size
    assert n > 5000 and abs(off.mean()) < 5 * np.sqrt(var / n)
    assert abs(off.var() / var - 1) < 0.1
    eff2 = NS["TwoTrapRTS"](s, fraction=0.05, mean1_e=60.0, mean2_e=25.0, tau_med_s=1.5e-5, tau_sigma_ln=1.0,
                            cds_s=4e-6)
    data[:] = 0
    eff2.apply(None, tile, data)
    assert data.min() < 0 < data.max() and abs(float(data.sum())) < 5 * float(np.sqrt((data ** 2).sum()))


def test_straylight_forms_add_light_only_and_reach_their_levels():
    """The Harvey halo gives ``near_e_per_s`` at the window corner nearest to its source and falls away from it;
    the baffle arc peaks on its ring; neither adds anything to a frame without light."""
    import numpy as np

    from tests.helpers import small_sensor

    s = small_sensor(width=64, height=48)
    tile = _tile(s, exptime_s=10.0)
    halo = NS["HarveyHalo"](s, pu=1.25, pv=1.35, d0_px=60.0, index=2.2, near_e_per_s=3.0)
    data = np.ones(tile.shape, np.float32)
    halo.apply(None, tile, data)
    assert abs(data[-1, -1] - 1 - 30.0) < 1e-3 and data[0, 0] - 1 < 0.5 * (data[-1, -1] - 1)
    arc = NS["BaffleArc"](s, cu=-0.5, cv=1.3, radius_frac=1.1, width_frac=0.2, peak_e_per_s=0.03)
    data = np.ones(tile.shape, np.float32)
    arc.apply(None, tile, data)
    assert data.max() - 1 <= 0.3 + 1e-6 and data.max() - 1 > 0.2
    for eff in (halo, arc):
        dark = np.zeros(tile.shape, np.float32)
        eff.apply(None, tile, dark)
        assert not dark.any()


def test_rts_fraction_is_per_sensor_pixel_on_a_binned_frame():
    """The RTS signature estimates the fraction of *sensor* pixels with a trap: the same steps on an output frame
    binned b x b (b^2 sensor pixels per output pixel) mean a b^2 times smaller fraction."""
    from detector.effects.rts import rts_population

    f1, f2 = rts_population(2e-4, 1)["fraction"], rts_population(2e-4, 2)["fraction"]
    assert 0 < f1 < 0.1 and abs(f2 / f1 - 0.25) < 0.01


# --- the sixth round's probes: each form against its law ------------------------------------------------------

def test_probe_forms_follow_their_laws():
    """Read-out smear: every pixel gains frac x its column's light; flicker: rows modulated by 1 + a sin; tree
    rings: a response of mean ~1 and amplitude a; undershoot: a source loses alpha of its light to its right, none
    to its left; satellite trail: e_per_px per pixel of its length; bias step: step_adu above the row fraction."""
    import numpy as np

    from tests.helpers import small_sensor

    s = small_sensor(width=64, height=48)
    tile = _tile(s)
    img = np.full(tile.shape, 100.0, np.float32)
    img[20:24, 30] += 5000.0
    smear = img.copy()
    NS["ReadoutSmear"](s, frac_per_row=1e-3).apply(None, tile, smear)
    assert np.allclose(smear - img, 1e-3 * img.sum(axis=0)[None, :], rtol=1e-5)
    flick = np.ones(tile.shape, np.float32)
    NS["Flicker"](s, amp=0.01, period_rows=12.0).apply(None, tile, flick)
    assert abs(float(np.ptp(flick[:, 0])) / 2 - 0.01) < 1e-3 and np.ptp(flick, axis=1).max() < 1e-6
    rings = np.ones(tile.shape, np.float32)
    NS["TreeRings"](s, amp=0.004, period_px=10.0, cu=-0.4, cv=1.3).apply(None, tile, rings)
    assert abs(float(rings.mean()) - 1) < 1e-3 and abs(float(np.ptp(rings)) / 2 - 0.004) < 3e-4
    star = np.full(tile.shape, 50.0, np.float32)
    star[24, 20] += 1e4
    under = star.copy()
    NS["AmplifierUndershoot"](s, alpha=0.01, tail_px=2.0).apply(None, tile, under)
    assert abs(float((star - under)[24, 21:].sum()) - 100.0) < 1e-2 and not (star - under)[24, :21].any()
    trail = np.zeros((200, 200), np.float32)
    NS["SatelliteTrail"](s, u0=0.0, v0=0.5, u1=1.0, v1=0.5, e_per_px=400.0, sigma_px=1.2).apply(None, tile, trail)
    assert abs(float(trail[:, 100].sum()) - 400.0) < 1.0
    bias = np.zeros(tile.shape, np.float32)
    NS["BiasJump"](s, step_adu=1.5, at=0.4).apply(None, tile, bias)
    assert set(np.unique(bias).tolist()) <= {0.0, 1.5} and bias[-1, 0] == 1.5


def test_error_halved_within_the_noise_rule():
    """Nothing to halve is not a failure: an error before within the noise passes (chi2/dof: 3 standard
    deviations; the misfit: below the 99th percentile of null frames' misfit, NULL_MISFIT); beyond it, only a
    ratio <= 0.5 passes."""
    eh = NS["error_halved"]
    n = 20000
    sd = (2 / n) ** 0.5
    assert eh({"metric": "chi2_minus_1", "before": {"chi2_minus_1": 2.9 * sd, "n_support": n}})
    assert not eh({"metric": "chi2_minus_1", "before": {"chi2_minus_1": 3.1 * sd, "n_support": n}})
    assert eh({"metric": "chi2_minus_1", "error_ratio": 0.5, "before": {"chi2_minus_1": 1.0, "n_support": n}})
    # one cosmic-ray track against a model without: a two-sample Poisson deviance of 1.39, misfit 0.27
    assert eh({"metric": "misfit", "error_ratio": 1.0, "before": {"misfit": 0.27}})
    bar = NS["NULL_MISFIT"]
    assert eh({"metric": "misfit", "error_ratio": 1.0, "before": {"misfit": 0.99 * bar}})
    assert not eh({"metric": "misfit", "error_ratio": 0.9, "before": {"misfit": 1.01 * bar}})
    assert eh({"metric": "misfit", "error_ratio": 0.4, "before": {"misfit": 2 * bar}})


def test_null_frames_misfit_is_mostly_below_the_within_noise_bar(tmp_path):
    """NULL_MISFIT is the 99th percentile of null frames' misfit (300 frames in its calibration): two null frames
    of each outlier-count base are below it, and the misfit of a null is not zero (ten positive parts)."""
    import numpy as np

    from scenes.app.validation.random_forms import misfit_null

    rows = misfit_null(2, 3603, tmp_path)
    m = np.array([r["misfit"] for r in rows])
    assert len(rows) == 10 and (m < NS["NULL_MISFIT"]).all() and np.median(m) > 0.1, m
