"""cti, brighter_fatter, ipc, rts_noise, persistence: physics checks against independent results."""

import numpy as np
import pytest
from astropy.io import fits

from detector import Detector, build_effects, make_sensor
from detector.effects.coupling import bf_area_coefficients, brighter_fatter, ipc
from detector.effects.cti import cti_transfer, fluence_10mev_p_cm2
from detector.effects.persistence import persistence_charge
from detector.effects.rts import rts_offsets, telegraph_sequence
from detector.errors import DetectorError


def _ccd(**kw):
    return make_sensor("ml11002", {"width": 200, "height": 300, "x0": 1000, "y0": 0, **kw})


def _cmos(**kw):
    return make_sensor("imx411", {"width": 256, "height": 512, "x0": 3000, "y0": 2000, **kw})


# --- cti ------------------------------------------------------------------------------------------------------

def direct_column(q_e, rho, tau_s, dwell_s, beta, well_e, overscan):
    """Trap-by-trap, level-by-level simulation of one column, written independently of ``cti_transfer``:
    every pixel has its own traps, whose occupancy is a list of volume levels ``[top, fill of each species]``
    (fill: fraction of the ``rho_k`` traps per unit volume that hold an electron; ArCTIc's watermarks,
    Massey et al. 2014). At each step every pixel releases into the packet it holds (a fraction
    ``1 - exp(-t_d / tau)`` of every filled trap), then the packet, of volume ``(n / w)^beta``, fills every trap
    below its volume (part-way, the same fraction everywhere, if it has too few electrons); then every
    packet moves one pixel towards row 0, and the packet leaving pixel 0 is read. Returns the read packets
    (image rows, then the overscan) and the charge left in the traps."""
    n_pix = len(q_e)
    rho, decay = np.asarray(rho, float), np.exp(-dwell_s / np.asarray(tau_s, float))
    levels = [[] for _ in range(n_pix)]  # per pixel: [top volume, fills], tops increasing from volume 0
    packets = np.array(q_e, float)
    read = []
    for _ in range(n_pix + overscan):
        for p in range(n_pix):
            lv, lo, released = levels[p], 0.0, 0.0
            for lev in lv:
                out = lev[1] * (1 - decay)
                lev[1] = lev[1] - out
                released += (lev[0] - lo) * (rho * out).sum()
                lo = lev[0]
            n = packets[p] + released
            vol = min(max(n, 0.0) / well_e, 1.0) ** beta
            # split the level that the volume falls in, add an empty level up to it if above all
            lo = 0.0
            for k, lev in enumerate(lv):
                if lo < vol < lev[0]:
                    lv.insert(k, [vol, lev[1].copy()])
                    break
                lo = lev[0]
            if not lv or lv[-1][0] < vol:
                lv.append([vol, np.zeros_like(rho)])
            want, lo = 0.0, 0.0
            for lev in lv:
                if lev[0] > vol:
                    break
                want += (lev[0] - lo) * (rho * (1 - lev[1])).sum()
                lo = lev[0]
            f = min(1.0, n / want) if want > 0 else 0.0
            if f == 1.0:  # all full below the packet's volume: one level
                levels[p] = lv = [[vol, np.ones_like(rho)]] + [lev for lev in lv if lev[0] > vol]
            else:
                for lev in lv:
                    if lev[0] <= vol:
                        lev[1] = lev[1] + f * (1 - lev[1])
            packets[p] = n - f * want
        read.append(packets[0])
        packets = np.append(packets[1:], 0.0)
    left = packets.sum()  # released into the packets that entered behind the column and are not read yet
    for lv in levels:
        lo_left = 0.0
        for lev in lv:
            left += (lev[0] - lo_left) * (rho * lev[1]).sum()
            lo_left = lev[0]
    return np.array(read), left


CTI_ARGS = dict(rho=[0.2, 0.5], tau_s=[2e-4, 3e-3], dwell_s=5e-4, beta=0.478, well_e=50000.0)


@pytest.mark.parametrize("background_e", [0.0, 300.0])
def test_cti_trail_and_charge_conservation_match_a_trap_by_trap_column(background_e):
    n, over = 64, 32
    q = np.full(n, background_e)
    q[30] += 20000.0
    q[48] += 3000.0
    direct, left = direct_column(q, CTI_ARGS["rho"], CTI_ARGS["tau_s"], CTI_ARGS["dwell_s"], CTI_ARGS["beta"],
                                 CTI_ARGS["well_e"], over)
    col = np.concatenate([q, np.zeros(over)])[:, None]
    args = (CTI_ARGS["rho"], CTI_ARGS["tau_s"], CTI_ARGS["dwell_s"], CTI_ARGS["beta"], CTI_ARGS["well_e"])
    exact, trapped = cti_transfer(col, *args, return_trapped=True, express=0)
    exact = exact[:, 0]
    # charge conserved exactly by both (image + overscan + traps, or packets not read yet, = collected)
    assert abs(exact.sum() + trapped[0] - q.sum()) < 1e-9 * q.sum()
    assert abs(direct.sum() + left - q.sum()) < 1e-9 * q.sum()
    # every pixel's traps followed (express=0): the same column as the trap-by-trap simulation
    assert np.allclose(exact, direct, rtol=1e-9, atol=1e-9)
    # one pool per column (express=1): the stars' loss and their trails (15 rows behind) within a few per cent
    fast = cti_transfer(col, *args, express=1)[:, 0]
    for row in (30, 48):
        loss_f, loss_d = q[row] - fast[row], q[row] - direct[row]
        assert loss_d > 5 and abs(loss_f - loss_d) < 0.03 * loss_d, (loss_f, loss_d)
        trail_f, trail_d = fast[row + 1:row + 16] - background_e, direct[row + 1:row + 16] - background_e
        assert trail_d.sum() > 5
        assert abs(trail_f.sum() - trail_d.sum()) < 0.03 * abs(trail_d.sum()) + 0.2
        assert np.all(np.abs(trail_f - trail_d) < 0.05 * np.abs(trail_d) + 0.2), np.c_[trail_f, trail_d]


def test_cti_trail_grows_with_signal_and_falls_with_background():
    def star_loss(star_e, bg_e):
        col = np.full((400, 1), bg_e)
        col[300] += star_e
        out = cti_transfer(col, [0.05], [2e-3], 5e-4, 0.478, 50000.0)
        return star_e + bg_e - out[300, 0]

    assert star_loss(20000, 0) > star_loss(2000, 0) > 0
    # traps pre-filled by the sky: only rho [(n_star/w)^beta - (n_sky/w)^beta] per pixel is left to capture
    assert star_loss(20000, 2000) < 0.8 * star_loss(20000, 0)


def test_cti_full_frame_and_identity_and_cmos_refused():
    s = _ccd(read_noise_e=0.0)
    star = np.full(s.shape, 50.0, np.float32)
    star[200, 100] = 30000.0
    plain = Detector(s, []).expose(star, 1.0, 3)
    zero = Detector(s, build_effects({"cti": {"density_per_px": [0.0], "release_time_s": [1e-3]}}, s)).expose(star, 1.0, 3)
    assert np.array_equal(plain, zero)
    d1 = Detector(s, build_effects({"cti": {"density_per_px": [0.5], "release_time_s": [2e-3]}}, s), workers=1)
    d2 = Detector(s, build_effects({"cti": {"density_per_px": [0.5], "release_time_s": [2e-3]}}, s), workers=2)
    a = d1.expose(star, 1.0, 3)
    assert np.array_equal(a, d2.expose(star, 1.0, 3))
    # same seeds: the difference is the CTI alone; the trail is above the star (away from row 0), not below
    diff = a[:, 100].astype(float) - plain[:, 100].astype(float)
    assert diff[200] < -30 and diff[201:215].sum() > 30 and abs(diff[190:200].sum()) < 5, diff[195:215]
    with pytest.raises(DetectorError, match="CCD"):
        build_effects({"cti": {}}, _cmos())


def test_cti_dose_model_is_linear_in_days_and_falls_with_shielding():
    f1, f2 = fluence_10mev_p_cm2(100), fluence_10mev_p_cm2(200)
    assert f1 > 0 and abs(f2 / f1 - 2) < 1e-12
    assert fluence_10mev_p_cm2(100, shielding_mm_al=20) < f1
    s = make_sensor("ml11002", {})
    e = build_effects({"cti": {"days_in_orbit": 365}}, s)[0]
    expect = 1e-12 * 81.0 * fluence_10mev_p_cm2(365)
    assert abs(sum(e.density) - expect) < 1e-9 * expect


# --- brighter-fatter ---------------------------------------------------------------------------------------------

def test_bf_flat_covariances_follow_the_kernel_area_coefficients():
    rng = np.random.default_rng(4)
    mu, a10, scale = 10000.0, 2e-6, 0.5
    q = rng.poisson(mu, size=(1024, 1024)).astype(np.float32)
    out = brighter_fatter(q, a10, scale).astype(np.float64)[2:-2, 2:-2]
    d = out - out.mean()
    c = a10 / bf_area_coefficients(scale)[(1, 0)]
    # independent prediction: the discrete Laplacian of the 3x3 kernel exp(-r/scale), built with np.roll
    k = np.zeros((7, 7))
    for (i, j) in [(i, j) for i in (-1, 0, 1) for j in (-1, 0, 1)]:
        k[3 + i, 3 + j] = np.exp(-np.hypot(i, j) / scale)
    lap = np.roll(k, 1, 0) + np.roll(k, -1, 0) + np.roll(k, 1, 1) + np.roll(k, -1, 1) - 4 * k
    err = 1.0 / (mu * np.sqrt(d.size))  # standard error of Cov / mu^2
    for (dy, dx) in [(0, 1), (1, 0), (1, 1), (0, 2)]:
        cov = np.mean(d[:d.shape[0] - dy, :d.shape[1] - dx] * d[dy:, dx:])
        pred = c * lap[3 + dy, 3 + dx]
        assert abs(cov / mu ** 2 - pred) < 0.1 * abs(pred) + 4 * err, ((dy, dx), cov / mu ** 2, pred)
    var_pred = mu + c * lap[3, 3] * mu ** 2
    assert abs(d.var() / var_pred - 1) < 0.03, (d.var(), var_pred)


def test_bf_conserves_charge_and_widens_bright_stars():
    y, x = np.mgrid[:41, :41] - 20.0
    prof = np.exp(-(x * x + y * y) / (2 * 1.3 ** 2))
    prof /= prof.sum()
    widths = []
    for flux in (1e3, 1e5, 4e5):
        img = (flux * prof).astype(np.float32)
        out = brighter_fatter(img, 1e-6, 0.5).astype(np.float64)
        assert abs(out.sum() - img.sum()) < 1e-5 * img.sum()
        widths.append(np.sqrt((out * (x * x + y * y)).sum() / out.sum()))
    assert widths[0] < widths[1] < widths[2]
    assert (widths[2] - widths[0]) / widths[0] > 0.005


def test_bf_and_ipc_identity_at_zero_and_same_bytes_on_one_and_two_workers():
    s = _cmos()
    sig = np.full(s.shape, 3000.0, np.float32)
    plain = Detector(s, []).expose(sig, 1.0, 9)
    for eff in ({"brighter_fatter": {"a10_per_e": 0.0}}, {"ipc": {"alpha": 0.0}}, {"rts_noise": {"fraction": 0.0}}):
        assert np.array_equal(plain, Detector(s, build_effects(eff, s)).expose(sig, 1.0, 9)), eff
    on = {"brighter_fatter": {"a10_per_e": 5e-7}, "ipc": {"alpha": 0.01}, "rts_noise": {"fraction": 0.01}}
    a = Detector(s, build_effects(on, s), workers=1).expose(sig, 1.0, 9)
    assert np.array_equal(a, Detector(s, build_effects(on, s), workers=2).expose(sig, 1.0, 9))
    assert not np.array_equal(a, plain)


def test_coupling_across_tile_borders_matches_the_whole_frame():
    """The tiled chain (neighbour rows as halo) gives what the coupling of the whole frame gives."""
    s = _cmos()
    det = Detector(s, build_effects({"brighter_fatter": {"a10_per_e": 1e-6}, "ipc": {"alpha": 0.02}}, s))
    tiles = det.tiles(1.0, 5)
    sig = np.full(s.shape, 8000.0, np.float32)
    charge = np.concatenate([det.charge_tile(sig, t) for t in tiles])
    whole = ipc(brighter_fatter(charge, 1e-6, 0.5), 0.02)
    y0 = s.roi_y0
    for i, t in enumerate(tiles):
        above = charge[:t.y0 - y0][-3:] if i else None
        below = charge[t.y1 - y0:][:3] if i + 1 < len(tiles) else None
        got = det.couple(t, charge[t.y0 - y0:t.y1 - y0], above, below)
        assert np.allclose(got, whole[t.y0 - y0:t.y1 - y0], rtol=1e-6, atol=1e-3)


# --- ipc -------------------------------------------------------------------------------------------------------

def test_ipc_flat_autocorrelation_matches_the_kernel():
    rng = np.random.default_rng(8)
    mu, a = 5000.0, 0.02
    q = rng.poisson(mu, size=(1024, 1024)).astype(np.float32)
    out = ipc(q, a).astype(np.float64)[1:-1, 1:-1]
    assert abs(out.mean() - q[1:-1, 1:-1].mean()) < 0.5  # signal conserved
    d = out - out.mean()
    var = d.var()
    rho10 = np.mean(d[:, :-1] * d[:, 1:]) / var
    rho01 = np.mean(d[:-1] * d[1:]) / var
    c = 1 - 4 * a
    pred = 2 * a * c / (c * c + 4 * a * a)  # Cov_10 = mu sum_j K_j K_j+e = 2 a c mu; Var = mu (c^2 + 4 a^2)
    err = 1.0 / np.sqrt(d.size)
    assert abs(rho10 - pred) < 4 * err and abs(rho01 - pred) < 4 * err, (rho10, rho01, pred)
    assert abs(var / (mu * (c * c + 4 * a * a)) - 1) < 0.01
    rho11 = np.mean(d[:-1, :-1] * d[1:, 1:]) / var
    assert abs(rho11 - 2 * a * a / (c * c + 4 * a * a)) < 4 * err


# --- rts -------------------------------------------------------------------------------------------------------

def _chi2_ok(obs, exp, dof_minus=1):
    from scipy import stats

    keep = exp > 5
    chi2 = float((((obs - exp) ** 2) / exp)[keep].sum())
    return stats.chi2.sf(chi2, keep.sum() - dof_minus) > 1e-3, chi2


def test_rts_dwell_times_follow_the_exponential_law():
    rng = np.random.default_rng(3)
    tau0, tau1, dt = 2e-3, 5e-3, 2e-5
    times = np.arange(200_000) * dt
    s = telegraph_sequence(rng, tau0, tau1, times)
    edges = np.flatnonzero(np.diff(s)) + 1
    runs = np.diff(edges)
    states = s[edges[:-1]]
    for state, tau in ((0, tau0), (1, tau1)):
        d = runs[states == state] * dt
        bins = np.linspace(0, 4 * tau, 21)
        obs, _ = np.histogram(d, bins)
        # the exact law of a chain sampled every dt: geometric, P(stay) = exp(-dt/tau) to O(dt^2)
        p_in = np.exp(-bins[:-1] / tau) - np.exp(-bins[1:] / tau)
        ok, chi2 = _chi2_ok(obs, p_in * d.size)
        assert ok, (state, chi2)
        assert abs(d.mean() / tau - 1) < 5 / np.sqrt(d.size)


def test_rts_frame_levels_match_the_markov_probabilities():
    rng = np.random.default_rng(5)
    n = 200_000
    tau0, tau1, cds = np.full(n, 1e-5), np.full(n, 3e-5), 1e-5
    off = rts_offsets(rng, np.full(n, 4.0), tau0, tau1, 3, cds)
    p1 = 0.75
    mix = 1 - np.exp(-cds * (1 / 1e-5 + 1 / 3e-5))
    p_up, p_down = (1 - p1) * p1 * mix, p1 * (1 - p1) * mix
    obs = np.array([(off < 0).sum(), (off == 0).sum(), (off > 0).sum()])
    exp = n * np.array([p_down, 1 - p_up - p_down, p_up])
    ok, chi2 = _chi2_ok(obs, exp)
    assert ok, (obs, exp, chi2)


def test_rts_pixels_are_fixed_by_the_hardware_seed_and_blink_with_the_frame_seed():
    s = _cmos(read_noise_e=0.0)
    eff = {"rts_noise": {"fraction": 0.01, "amplitude_e": 20.0, "levels": 2, "tau_min_s": 1e-3, "tau_max_s": 1e-2}}
    det = Detector(s, build_effects(eff, s))
    frames = [det.expose(0.0, 0.0, seed).astype(float) for seed in range(6)]
    lit = [f > s.bias_adu + 5 for f in frames]
    rows, cols, *_ = det.effects[0].population(s.roi_y0, s.roi_y0 + s.shape[0])
    inside = (cols >= s.roi_x0) & (cols < s.roi_x0 + s.shape[1])
    pop = np.zeros(s.shape, bool)
    pop[rows[inside] - s.roi_y0, cols[inside] - s.roi_x0] = True
    for m in lit:
        assert not (m & ~pop).any()  # only population pixels ever light up
    assert 0.2 * pop.sum() < lit[0].sum() < 0.8 * pop.sum()
    assert (lit[0] != lit[1]).sum() > 0.1 * pop.sum()  # they blink from frame to frame
    # frames are independent draws (runs of frames in one state are geometric): a pixel is on in two
    # consecutive frames as often as in two frames further apart
    on = np.array([m[pop] for m in lit])
    lag1 = np.mean([(on[i] & on[i + 1]).mean() for i in range(5)])
    lag_far = np.mean([(on[i] & on[j]).mean() for i in range(6) for j in range(i + 2, 6)])
    assert abs(lag1 - lag_far) < 0.04, (lag1, lag_far)


# --- persistence -------------------------------------------------------------------------------------------------

def test_persistence_decays_exponentially_and_is_the_identity_at_zero(tmp_path):
    s = _cmos(dark_current_e_per_s=0.0)
    prev = np.full(s.shape, s.bias_adu, np.uint16)
    prev[100:120, 50:70] = 65535  # saturated
    path = tmp_path / "prev.fits"
    fits.PrimaryHDU(prev, header=fits.Header({"BIAS": s.bias_adu, "GAIN": s.gain_e_per_adu})).writeto(path)
    tau, f, texp = 7.0, 2e-3, 3.0
    q_prev = (65535 - s.bias_adu) * s.gain_e_per_adu
    got = []
    for t0 in (0.0, 5.0, 10.0, 20.0):
        det = Detector(s, build_effects({"persistence": {"previous_frame": str(path), "time_since_s": t0,
                                                         "fraction": f, "tau_s": tau}}, s))
        img = det.expose(0.0, texp, 1, noiseless=True)
        expect = f * (q_prev - 0.5 * s.full_well_e) * (np.exp(-t0 / tau) - np.exp(-(t0 + texp) / tau))
        assert abs(img[110, 60] - expect) < 1e-4 * expect + 1e-3
        assert img[10, 10] == 0.0  # below the threshold: nothing
        got.append(img[110, 60])
    ratios = np.array(got[1:]) / got[0]
    assert np.allclose(ratios, np.exp(-np.array([5.0, 10.0, 20.0]) / tau), rtol=1e-4)
    assert np.allclose(persistence_charge(np.array([1e5]), 0.0, 1e3, 5.0, 0.0, 1.0), 0.0)
    plain = Detector(s, []).expose(0.0, texp, 4)
    zero = Detector(s, build_effects({"persistence": {"previous_frame": str(path), "time_since_s": 1.0,
                                                      "fraction": 0.0}}, s)).expose(0.0, texp, 4)
    assert np.array_equal(plain, zero)


def test_persistence_wrong_shape_is_one_clear_error(tmp_path):
    s = _cmos()
    path = tmp_path / "small.fits"
    fits.PrimaryHDU(np.zeros((10, 10), np.uint16)).writeto(path)
    with pytest.raises(DetectorError, match="previous frame"):
        build_effects({"persistence": {"previous_frame": str(path), "time_since_s": 1.0}}, s)


def test_model_of_the_mean_frame_couples_the_mean_charge():
    """Detector.moments (compare/diagnose) applies the coupling effects to the mean charge."""
    s = _ccd(dark_current_e_per_s=0.0)
    sig = np.full(s.shape, 100.0, np.float32)
    sig[150, 60] = 20000.0
    eff = {"cti": {"density_per_px": [0.3], "release_time_s": [1.5e-3]}}
    mean, var, _ = Detector(s, build_effects(eff, s)).moments(sig, 1.0)
    expect = cti_transfer(sig, [0.3], [1.5e-3], 5.01e-4, 0.478, s.full_well_e, first_transfers=s.roi_y0 + 1)
    expect_adu = expect / s.gain_e_per_adu + s.bias_adu
    assert np.allclose(mean, expect_adu, atol=0.05)
    assert mean[151:160, 60].sum() > mean[141:150, 60].sum() + 5  # the trail, above the star
