"""Structure tests a candidate must pass before it is named (issue 10: a name is a claim about physics).

Each rule is checked on synthetic residuals whose answer is known independently: noise of any law is
zero-mean and its outliers have independent neighbours; a compressive response is not; a rigid shift moves
every region alike while a decentering distortion does not; a defective column spreads its excess along its
length while pixel clusters do not.
"""

from __future__ import annotations

import numpy as np
import pytest

from detector.effects import registry
from detector.effects.defects import ColumnSignature
from detector.effects.image_plane import _distortion_check, _offset_check, radial_distortion, shift, similarity
from detector.sensor import make_sensor
from detector.signatures import Residuals, SpikeStats, neighbour_correlation, tail_neighbour_correlation


def _res(data, model, var, photo, sensor, ys=None, xs=None) -> Residuals:
    h, w = data.shape
    return Residuals(data.astype(np.float32), model.astype(np.float32), var.astype(np.float32),
                     np.ones((h, w), bool), photo.astype(np.float32), np.zeros((h, w), np.float32),
                     np.arange(h, dtype=float) if ys is None else ys, np.arange(w, dtype=float) if xs is None else xs,
                     sensor, 10.0, SpikeStats(0, 0, 0, 0, 0), SpikeStats(0, 0, 0, 0, 0))


def _stars(shape, n, rng, sigma_px=1.5, peak=(2e3, 4e4)) -> np.ndarray:
    """Gaussian stars [ADU] at random positions on a zero background."""
    img = np.zeros(shape)
    yy, xx = np.mgrid[: shape[0], : shape[1]]
    for y0, x0, a in zip(rng.uniform(8, shape[0] - 8, n), rng.uniform(8, shape[1] - 8, n),
                         np.exp(rng.uniform(*np.log(peak), n))):
        sl = (slice(max(int(y0) - 8, 0), int(y0) + 9), slice(max(int(x0) - 8, 0), int(x0) + 9))
        img[sl] += a * np.exp(-((yy[sl] - y0) ** 2 + (xx[sl] - x0) ** 2) / (2 * sigma_px ** 2))
    return img


# ------------------------------------------------------------------------------------ noise is noise
@pytest.mark.parametrize("law", ["normal", "laplace", "student"])
def test_outliers_of_independent_noise_have_independent_neighbours(law):
    """Whatever its tail, independent pixel noise gives a tail-neighbour correlation of 0 +- a few / sqrt(n)."""
    rng = np.random.default_rng(3)
    shape = (256, 256)
    noise = {"normal": rng.normal(0, 1, shape), "laplace": rng.laplace(0, 1 / np.sqrt(2), shape),
             "student": rng.standard_t(3, shape) / np.sqrt(3)}[law] * 10.0
    s = make_sensor("ml11002", {"width": 256, "height": 256})
    model = np.full(shape, 1000.0)
    res = _res(model + noise, model, np.full(shape, 100.0), np.zeros(shape), s)
    rho, z, n, _ = tail_neighbour_correlation(res)
    assert n > 100 and abs(z) < 4, (rho, z, n)


def test_outliers_in_pairs_share_their_sign_with_a_neighbour():
    rng = np.random.default_rng(4)
    shape = (256, 256)
    data = 1000.0 + rng.normal(0, 10, shape)
    ys, xs = rng.integers(0, 255, 300), rng.integers(0, 256, 300)
    data[ys, xs] += 200.0
    data[ys + 1, xs] += 200.0  # vertical pairs (hot pixels in pairs, a structure two pixels tall)
    s = make_sensor("ml11002", {"width": 256, "height": 256})
    res = _res(data, np.full(shape, 1000.0), np.full(shape, 100.0), np.zeros(shape), s)
    rho, z, _, share = tail_neighbour_correlation(res)
    assert rho > 0.3 and z > 5 and share > 0.5


def test_a_hot_pixel_tail_read_through_ipc_stays_below_the_tail_bar():
    """Independent hot pixels (10-20 sigma) read through inter-pixel capacitance (each neighbour reads alpha of
    the pixel) correlate with their neighbours by at most alpha A / sqrt(1 + alpha^2 A^2); the bar is that at the
    tail's 30-sigma clip for the catalogue's CMOS coupling (IPCParams' alpha, 0.5 %): 0.148. Such a tail stays
    below it at that coupling and at 2 %, the top of what small-pixel CMOS sensors show; pixel pairs exceed it
    by far (above)."""
    from detector.effects.coupling import IPCParams, ipc
    from detector.signatures import max_tail_correlation

    assert max_tail_correlation() == pytest.approx(0.148, abs=1e-3)
    shape = (256, 256)
    s = make_sensor("ml11002", {"width": 256, "height": 256})
    for alpha in (IPCParams().alpha, 0.02):
        rng = np.random.default_rng(6)
        charge = np.full(shape, 1000.0)
        hot = rng.random(shape) < 0.003
        charge[hot] += rng.uniform(100.0, 200.0, int(hot.sum()))  # 10-20 sigma of the 10 ADU noise
        data = ipc(charge.astype(np.float32), alpha) + rng.normal(0, 10, shape)
        res = _res(data, np.full(shape, 1000.0), np.full(shape, 100.0), np.zeros(shape), s)
        rho, _, _, share = tail_neighbour_correlation(res)
        assert share > 0.5 and rho < max_tail_correlation(), (alpha, rho)


# ------------------------------------------------------------------------------------ zero mean
def _prnu_case(compress: float, seed: int = 5):
    """A star field with a white PRNU of 2 % (data) and optionally a compressive response
    ``S (1 - compress S / S_max)`` the model lacks."""
    rng = np.random.default_rng(seed)
    shape = (256, 256)
    photo = _stars(shape, 120, rng) + 50.0
    s = make_sensor("ml11002", {"width": 256, "height": 256, "bias_adu": 0})
    truth = photo * (1 + 0.02 * rng.standard_normal(shape))
    truth = truth * (1 - compress * photo / photo.max())
    var = photo / s.gain_e_per_adu + 4.0
    data = truth + rng.normal(0, np.sqrt(var))
    return _res(data, photo, var, photo, s)


def test_a_real_prnu_is_zero_mean_and_plausible():
    res = _prnu_case(0.0)
    sig = registry()["prnu"].signature
    fit = sig.fit(res, "prnu")
    assert fit is not None and fit.delta_bic < -100
    assert sig.zero_mean(fit, res) == ""
    assert fit.params["sigma"] == pytest.approx(0.02, rel=0.25)


@pytest.mark.parametrize("pattern,plausible", [("columns", True), ("rows", True), ("blobs", False)])
def test_a_prnu_may_have_column_and_row_components_but_not_blobs(pattern, plausible):
    """EMVA 1288 splits a fixed pattern into row, column and pixel variances: a flat whose response varies by
    whole columns (or rows) correlates neighbours along one axis only and is a PRNU; the same variance in
    blobs a few pixels wide correlates them both ways and is a structure, not a non-uniformity."""
    from scipy import ndimage

    rng = np.random.default_rng(9)
    shape = (256, 256)
    s = make_sensor("ml11002", {"width": 256, "height": 256, "bias_adu": 0})
    photo = np.full(shape, 4000.0)
    if pattern == "columns":
        resp = 1 + 0.01 * rng.standard_normal((1, shape[1])) + np.zeros(shape)
    elif pattern == "rows":
        resp = 1 + 0.01 * rng.standard_normal((shape[0], 1)) + np.zeros(shape)
    else:
        resp = 1 + ndimage.gaussian_filter(rng.standard_normal(shape), 1.5) * 0.01 / 0.19
    var = photo / s.gain_e_per_adu + 4.0
    data = photo * resp + rng.normal(0, np.sqrt(var))
    res = _res(data, photo, var, photo, s)
    sig = registry()["prnu"].signature
    fit = sig.fit(res, "prnu")
    assert fit is not None and fit.delta_bic < -100
    why = sig.plausible(fit, res)
    assert (why == "") == plausible, why


@pytest.mark.parametrize("pattern,white", [("white", True), ("wave", False)])
def test_a_weak_scatter_shared_by_neighbours_is_a_structure_not_a_prnu(pattern, white):
    """A wave of a few pixels' period (tree rings, fringes) too weak to lift the whole variance's neighbour
    correlation to its bar still puts most of its own excess variance in what adjacent pixels share; a white
    PRNU of the same excess shares none of it (the random-forms case tree_rings-320774075127429310: 0.24 % rings of
    8.7 px period on a binned flat, 5 % of the variance, named a 1.3 % PRNU)."""
    rng = np.random.default_rng(21)
    shape = (256, 256)
    s = make_sensor("ml11002", {"width": 256, "height": 256, "bias_adu": 0})
    photo = np.full(shape, 4000.0)
    var = photo / s.gain_e_per_adu + 4.0
    rel = 0.25 * np.sqrt(var[0, 0]) / photo[0, 0]  # the pattern's rms: 6 % of the pixels' variance
    if pattern == "white":
        resp = 1 + rel * rng.standard_normal(shape)
    else:
        yy, xx = np.mgrid[: shape[0], : shape[1]]
        resp = 1 + rel * np.sqrt(2) * np.sin(2 * np.pi * (0.8 * xx + 0.6 * yy) / 8.7 + 0.4)
    data = photo * resp + rng.normal(0, np.sqrt(var))
    res = _res(data, photo, var, photo, s)
    sig = registry()["prnu"].signature
    fit = sig.fit(res, "prnu")
    assert fit is not None and fit.delta_bic < -10  # significant (DESIGN: delta BIC below -10)
    rho, _ = neighbour_correlation(res)
    assert rho < sig.MAX_NEIGHBOUR_CORRELATION  # the whole variance's bar does not see it
    why = sig.white(fit, res)
    assert (why == "") == white, why
    assert (sig.plausible(fit, res) == "") == white


@pytest.mark.parametrize("where,uniform", [("everywhere", True), ("one quarter", False)])
def test_a_scatter_follows_its_template_over_the_frame(where, uniform):
    """The cells' excess variances over the template's prediction scatter about their mean beyond their own
    errors (their chi2 at CELL_SIGMA) when the scatter sits in one part of the frame; a white noise (reset
    noise: a uniform template) spread over the whole frame passes."""
    rng = np.random.default_rng(12)
    shape = (256, 256)
    s = make_sensor("ml11002", {"width": 256, "height": 256, "bias_adu": 0})
    model = np.full(shape, 100.0)
    var = np.full(shape, 9.0)
    extra = np.full(shape, 3.0)
    if where == "one quarter":
        extra[:] = 0.0
        extra[:128, :128] = 6.0
    data = model + rng.normal(0, np.sqrt(var)) + extra * rng.standard_normal(shape)
    res = _res(data, model, var, np.zeros(shape), s)
    sig = registry()["reset_noise"].signature
    fit = sig.fit(res, "reset_noise")
    assert fit is not None and fit.delta_bic < -100
    why = sig.uniformity(fit, res)
    assert (why == "") == uniform, why


def test_compressed_star_cores_are_not_a_prnu():
    """Cores read low: the scatter the PRNU fit wants is a mean deficit, which the zero-mean rule names."""
    res = _prnu_case(0.08)
    sig = registry()["prnu"].signature
    fit = sig.fit(res, "prnu")
    assert fit is not None
    why = sig.zero_mean(fit, res)
    assert "below the model" in why


# ------------------------------------------------------------------------------------ rigid or not
def _star_frame(transform, seed=6):
    """A 256 x 256 window at the centre of the ML11002 with stars moved by ``transform(model, ys, xs, yc, xc)``."""
    rng = np.random.default_rng(seed)
    s = make_sensor("ml11002", {"width": 256, "height": 256})
    h, w = 256, 256
    y0, x0 = (s.sensor_height_px - h) // 2, (s.sensor_width_px - w) // 2
    ys, xs = np.arange(y0, y0 + h, dtype=float), np.arange(x0, x0 + w, dtype=float)
    yc, xc = (s.sensor_height_px - 1) / 2, (s.sensor_width_px - 1) / 2
    photo = _stars((h, w), 250, rng) + 20.0
    var = photo / s.gain_e_per_adu + 9.0
    moved = transform(photo.astype(np.float32), ys, xs, yc, xc).astype(np.float64)
    data = moved + rng.normal(0, np.sqrt(var))
    return _res(data, photo, var, photo, s, ys, xs)


def test_a_rigid_shift_is_a_pointing_offset():
    res = _star_frame(lambda p, ys, xs, yc, xc: shift(p, 0.6, -0.4))
    sig = registry()["pointing_offset"].signature
    fit = sig.fit(res, "pointing_offset")
    assert fit.params["dx_px"] == pytest.approx(0.6, abs=0.05) and fit.params["dy_px"] == pytest.approx(-0.4, abs=0.05)
    assert _offset_check(fit, res) == ""


def test_a_decentering_distortion_is_not_a_pointing_offset_and_is_fitted_as_one():
    p1, p2 = 2e-5, -1e-5  # up to ~2 px at the window's corners
    res = _star_frame(lambda p, ys, xs, yc, xc: radial_distortion(p, ys, xs, yc, xc, 0.0, p1_per_px=p1,
                                                                   p2_per_px=p2))
    off = registry()["pointing_offset"].signature.fit(res, "pointing_offset")
    assert "varies across the field" in _offset_check(off, res)
    dist = registry()["distortion"].signature.fit(res, "distortion")
    assert dist.params["p1_per_px"] == pytest.approx(p1, rel=0.1)
    assert dist.params["p2_per_px"] == pytest.approx(p2, rel=0.1)
    assert dist.delta_bic < off.delta_bic
    assert _distortion_check(dist, res) == ""  # beyond what a shift, rotation and scale change do


def test_a_radial_distortion_keeps_the_simpler_form():
    """Nested forms: a pure radial distortion is fitted with k alone (the decentering terms stay 0)."""
    k = 2e-8
    res = _star_frame(lambda p, ys, xs, yc, xc: radial_distortion(p, ys, xs, yc, xc, k))
    fit = registry()["distortion"].signature.fit(res, "distortion")
    assert fit.params["k_per_px2"] == pytest.approx(k, rel=0.1)
    assert fit.params["p1_per_px"] == 0.0 and fit.params["p2_per_px"] == 0.0 and fit.k == 1
    assert _distortion_check(fit, res) == ""  # r^3 is not a plate-scale change (r) over the window


def test_a_rotated_and_scaled_field_is_a_pointing_offset_not_a_distortion():
    """A small shift with a rotation (0.1 deg: 0.3 px at the window's corners, three times the shift) and a
    plate-scale change about the sensor centre: the similarity transform WCSs hold (Calabretta & Greisen
    2002). pointing_offset fits it (its chained similarity form) and passes its field-variation test; a
    distortion's terms, which take part of it (the decentering terms hold a shift and a rotation's share), add
    nothing significant beyond the similarity while the similarity adds to them: refused (the nested test)."""
    rot, sc = 0.1, 5e-4
    res = _star_frame(lambda p, ys, xs, yc, xc: similarity(p, ys, xs, yc, xc, 0.05, -0.03, rot, sc))
    off = registry()["pointing_offset"].signature.fit(res, "pointing_offset")
    assert off.k == 4
    assert off.params["rot_deg"] == pytest.approx(rot, rel=0.1) and off.params["scale"] == pytest.approx(sc, abs=1e-4)
    assert off.params["dx_px"] == pytest.approx(0.05, abs=0.03) and off.params["dy_px"] == pytest.approx(-0.03, abs=0.03)
    assert _offset_check(off, res) == ""
    dist = registry()["distortion"].signature.fit(res, "distortion")
    assert dist is not None and dist.delta_bic < -10 and off.delta_bic < dist.delta_bic
    assert "a shift, rotation and plate-scale change of the field fit the" in _distortion_check(dist, res)


def test_a_transform_refit_on_the_same_pixels_keeps_the_form_and_its_fit():
    """TransformSignature.refit (the held-out folds' fit): started from the in-sample parameters of the chosen
    nested form, refitted on the given pixels; on the same pixels it returns that form and that fit."""
    res = _star_frame(lambda p, ys, xs, yc, xc: similarity(p, ys, xs, yc, xc, 0.2, -0.1, 0.05, 0.0))
    sig = registry()["pointing_offset"].signature
    fit = sig.fit(res, "pointing_offset")
    again = sig.refit(fit, res, "pointing_offset")
    assert again.k == fit.k and set(again.params) == set(fit.params)
    assert again.params["rot_deg"] == pytest.approx(fit.params["rot_deg"], rel=0.02)
    assert again.delta_m2lnl == pytest.approx(fit.delta_m2lnl, rel=1e-3)


def _lopsided(p, frac=0.4, length_px=1.5, angle_deg=20.0):
    """Every source with a one-sided exponential tail (``frac`` of its light, mean length ``length_px``
    along ``angle_deg``): a coma-like PSF, built independently of the diagnosis (sum of shifted copies)."""
    t = np.linspace(0, 6 * length_px, 49)[1:]
    wts = np.exp(-t / length_px)
    wts /= wts.sum()
    c, s_ = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
    out = (1 - frac) * p.astype(np.float64)
    for ti, wi in zip(t, wts):
        out += frac * wi * shift(p, ti * c, ti * s_)
    return out


def test_lopsided_sources_are_not_a_pointing_offset():
    """A one-sided tail moves every centroid by frac x length (0.6 px here), which a shift fits in part; the
    skew change of the profiles left after it tells a coma-like PSF from a rigid offset (a pure shift of the
    same size is not flagged: test_a_rigid_shift_is_a_pointing_offset)."""
    res = _star_frame(lambda p, ys, xs, yc, xc: _lopsided(p))
    off = registry()["pointing_offset"].signature.fit(res, "pointing_offset")
    assert np.hypot(off.params["dx_px"], off.params["dy_px"]) > 0.3  # the shift does fit the centroids
    assert "lopsided" in _offset_check(off, res)
    shifted = _star_frame(lambda p, ys, xs, yc, xc: shift(p, 0.56, 0.2))
    fit = registry()["pointing_offset"].signature.fit(shifted, "pointing_offset")
    assert _offset_check(fit, shifted) == ""


def test_misfit_sources_do_not_make_columns_outliers_but_a_faint_column_is_found():
    """A column is an outlier by the median of its pixels: the few pixels of a misfit star (a wider PSF) leave
    their columns normal, while a column 0.5 sigma hot along its 512 rows (9 sigma in its median) is found."""
    from detector.signatures import spike_stats

    from scipy import ndimage

    rng = np.random.default_rng(3)
    model = _stars((512, 512), 150, rng, sigma_px=1.2) + 100.0
    wide = ndimage.gaussian_filter(model - 100.0, 0.8) + 100.0  # the same stars, their PSF 1.44 px rms
    var = model + 25.0
    data = wide + rng.normal(0, np.sqrt(var))
    data[:, 300] += 0.5 * np.sqrt(var[:, 300])
    stats, _ = spike_stats(data, model, var, np.ones(data.shape, bool), 1.0)
    assert stats.hot_cols + stats.cold_cols == 1 and stats.col_z[300] > 6


# ------------------------------------------------------------------------------------ columns
def test_column_excess_in_short_runs_is_clusters_not_a_column():
    rng = np.random.default_rng(7)
    var = np.full((512, 6), 100.0)
    d = rng.normal(0, 10, (512, 6))
    clusters = d.copy()
    for j in range(6):
        for y in rng.integers(0, 500, 2):
            clusters[y:y + 3, j] -= 3000.0  # 3 x 3 dead clusters crossing the column
    share, run = ColumnSignature.short_run_share(clusters, var)
    assert share > 0.9 and run == 3
    hot = d + np.linspace(0, 90, 512)[:, None]  # a leak growing along the column: most pixels below 5 sigma
    assert ColumnSignature.short_run_share(hot, var)[0] < 0.2
    whole = d - 60.0  # a dead column: every pixel 6 sigma low, one run
    share, run = ColumnSignature.short_run_share(whole, var)
    assert share < 0.05 and run > 100


def test_a_columns_excess_is_taken_over_its_rows_other_pixels(monkeypatch):
    """The stretches and runs of the outlier columns are measured against each row's other pixels: a level the
    frame's fitted levels leave in every pixel (0.9 sigma low, as bright misfit stars can leave the light level)
    and a row pattern are in no column's excess; a column 0.6 sigma hot keeps its own; a row without a usable
    pixel is no reference (NaN)."""
    rng = np.random.default_rng(21)
    h, w = 256, 64
    sensor = make_sensor("ml11002", {"width": w, "height": h, "gain_e_per_adu": 1.0, "read_noise_e": 5.0})
    model, var = np.full((h, w), 1000.0), np.full((h, w), 100.0)
    rows = 5.0 * np.sin(2 * np.pi * np.arange(h) / 50.0)[:, None]
    data = model - 9.0 + rows + rng.normal(0, 10.0, (h, w))
    data[:, 40] += 6.0
    data[7] = np.nan
    res = _res(data, model, var, model - 1000.0, sensor)
    monkeypatch.setattr(Residuals, "level_maps", lambda self: (np.zeros(self.data_adu.shape, np.float32), None))
    d = ColumnSignature._excess_over_row_median(res, np.array([40, 20]))
    assert np.isnan(d[7]).all()
    d = np.delete(d, 7, axis=0)
    assert abs(d[:, 0].mean() - 6.0) < 3 * 10 / np.sqrt(h) and abs(d[:, 1].mean()) < 3 * 10 / np.sqrt(h)
    assert abs(np.corrcoef(d[:, 1], np.delete(rows[:, 0], 7))[0, 1]) < 0.2  # the row pattern is in no column


# ------------------------------------------------------------------------------------ glow forms
def _dark_with_glow(params, seed=8, exptime_s=120.0):
    """A 256 x 256 dark window at the ML11002's bottom-left corner (sensor px) with the plugin's glow added to
    the data only (Poisson), against a model without it."""
    from detector.effects.base import build_effects
    from detector.effects.glow import bivariate_normal_rate, emitter_rate

    rng = np.random.default_rng(seed)
    s = make_sensor("ml11002", {"width": 256, "height": 256, "x0": 0, "y0": 0})
    (glow,) = build_effects({"amp_glow": params}, s)
    ys, xs = np.arange(256, dtype=float), np.arange(256, dtype=float)
    rate = np.zeros((256, 256), np.float32)
    for g in glow.params.sources if glow.params.model == "gaussian" else ():  # the thesis' law (Annex V)
        bivariate_normal_rate(ys, xs, g.x_frac * (s.sensor_width_px - 1), g.y_frac * (s.sensor_height_px - 1),
                              g.amplitude_e_per_s, g.sigma_x_px, g.sigma_y_px, g.rho, rate)
    for g in glow.params.emitters if glow.params.model == "emitter" else ():  # a point emitter off the plane
        emitter_rate(ys, xs, g.x_frac * (s.sensor_width_px - 1), g.y_frac * (s.sensor_height_px - 1),
                     g.amplitude_e_per_s, g.height_px, rate)
    dark_e = np.full((256, 256), 20.0)
    g = s.gain_e_per_adu
    model = 1000.0 + dark_e / g
    var = dark_e / g ** 2 + (s.read_noise_e / g) ** 2
    data = 1000.0 + rng.poisson(dark_e + rate * exptime_s) / g + rng.normal(0, s.read_noise_e / g, (256, 256))
    res = Residuals(data.astype(np.float32), model.astype(np.float32), var.astype(np.float32), np.ones((256, 256), bool),
                    np.zeros((256, 256), np.float32), dark_e.astype(np.float32), ys, xs, s, exptime_s,
                    SpikeStats(0, 0, 0, 0, 0), SpikeStats(0, 0, 0, 0, 0))
    return res


def test_the_thesis_bivariate_normal_glow_is_recovered():
    """A glow source of the thesis' form (Annex V) inside the window is fitted as one: its centre within a
    tenth of the window, its std within 35 %, its rate within 25 %."""
    src = {"x_frac": 120 / 4007, "y_frac": 60 / 2671, "amplitude_e_per_s": 0.5, "sigma_x_px": 50.0,
           "sigma_y_px": 50.0}
    res = _dark_with_glow({"model": "gaussian", "sources": [src]})
    sig = registry()["amp_glow"].signature
    fit = sig.fit(res, "amp_glow")
    assert fit is not None and fit.delta_bic < -1000 and sig.plausible(fit, res) == ""
    g = fit.params["sources"][0]
    assert abs(g["x_frac"] * 4007 - 120) < 26 and abs(g["y_frac"] * 2671 - 60) < 26
    assert g["sigma_x_px"] == pytest.approx(50.0, rel=0.35)
    assert g["amplitude_e_per_s"] == pytest.approx(0.5, rel=0.25)


def test_a_point_emitter_glow_beyond_the_corner_is_recovered_as_one():
    """An amplifier 30 px beyond the window's corner (the sensor's), 40 px off the sensor plane: the irradiance law
    (1 + r^2/h^2)^-1.5, whose r^-3 wings a Gaussian source does not follow, is fitted as an emitter: its position
    within 15 px, its height within 25 %, its rate within 25 %."""
    em = {"x_frac": -30 / 4007, "y_frac": -30 / 2671, "amplitude_e_per_s": 1.0, "height_px": 40.0}
    res = _dark_with_glow({"model": "emitter", "emitters": [em]})
    sig = registry()["amp_glow"].signature
    fit = sig.fit(res, "amp_glow")
    assert fit is not None and fit.delta_bic < -1000 and sig.plausible(fit, res) == ""
    assert fit.params["model"] == "emitter", fit.params
    g = fit.params["emitters"][0]
    assert abs(g["x_frac"] * 4007 + 30) < 15 and abs(g["y_frac"] * 2671 + 30) < 15
    assert g["height_px"] == pytest.approx(40.0, rel=0.25)
    assert g["amplitude_e_per_s"] == pytest.approx(1.0, rel=0.25)


def test_no_glow_gives_no_significant_glow():
    res = _dark_with_glow({"model": "gaussian", "sources": [{"amplitude_e_per_s": 0.0}]}, seed=9)
    fit = registry()["amp_glow"].signature.fit(res, "amp_glow")
    assert fit is None or fit.delta_bic > -10


# ------------------------------------------------------------------------------------ mosaics
@pytest.mark.parametrize("period", [2, 4, 8])
def test_the_mosaic_period_is_found(period):
    """A Bayer (period 2) or quad-Bayer (period 4) response on a flat is fitted with its own period and cells."""
    from detector.effects.colour import cfa_response

    rng = np.random.default_rng(10 + period)
    s = make_sensor("ml11002", {"width": 128, "height": 128, "bias_adu": 0})
    shape = (128, 128)
    ys, xs = np.arange(128.0), np.arange(128.0)
    resp = [0.62, 1.0, 0.98, 0.75]
    photo = np.full(shape, 5000.0)
    truth = photo * cfa_response(ys, xs, resp, 1, period=period)
    var = photo / s.gain_e_per_adu + 4.0
    res = _res(truth + rng.normal(0, np.sqrt(var)), photo, var, photo, s)
    fit = registry()["cfa"].signature.fit(res, "cfa")
    assert fit.params.get("period", 2) == period
    mean = np.mean(resp)
    assert np.allclose(fit.params["response"], np.asarray(resp) / mean, atol=0.01)


def test_a_white_noise_far_above_the_read_noise_on_a_lit_frame_is_not_reset_noise():
    """On a uniform flat a PRNU and an extra white noise are one variance; reset noise is part of the read noise
    the camera's bias frames measure, so 40x that read noise is the light's scatter (the PRNU is kept)."""
    rng = np.random.default_rng(12)
    s = make_sensor("imx411", {"width": 256, "height": 256, "bias_adu": 0})
    shape = (256, 256)
    photo = np.full(shape, 30000.0 / s.gain_e_per_adu)
    var = photo / s.gain_e_per_adu + (s.read_noise_e / s.gain_e_per_adu) ** 2
    data = photo * (1 + 0.002 * rng.standard_normal(shape)) + rng.normal(0, np.sqrt(var))
    res = _res(data, photo, var, photo, s)
    ktc = registry()["reset_noise"].signature
    fit = ktc.fit(res, "reset_noise")
    assert fit is not None and fit.delta_bic < -100
    assert "read noise" in ktc.plausible(fit, res)
    prnu = registry()["prnu"].signature
    assert prnu.plausible(prnu.fit(res, "prnu"), res) == ""


@pytest.mark.parametrize("ratio", [0.6, 1.6])
def test_a_reset_noise_is_at_most_the_read_noise_it_is_part_of(ratio):
    """An extra white noise on a faint flat (100 e-): below the camera's read noise it may be its reset part;
    above all of it (the data's read noise then more than sqrt(2) times the bias frames') it is not."""
    rng = np.random.default_rng(21)
    s = make_sensor("imx411", {"width": 256, "height": 256, "bias_adu": 0})
    shape = (256, 256)
    g = s.gain_e_per_adu
    photo = np.full(shape, 100.0 / g)
    var = photo / g + (s.read_noise_e / g) ** 2
    data = photo + rng.normal(0, np.sqrt(var)) + rng.normal(0, ratio * s.read_noise_e / g, shape)
    res = _res(data, photo, var, photo, s)
    ktc = registry()["reset_noise"].signature
    fit = ktc.fit(res, "reset_noise")
    assert fit is not None and fit.delta_bic < -10
    refused = "a part of the read noise" in ktc.plausible(fit, res)
    assert refused == (ratio > 1)


def test_the_distortion_at_sample_pixels_is_the_full_frame_there():
    rng = np.random.default_rng(13)
    img = rng.uniform(0, 100, (64, 80)).astype(np.float32)
    ys, xs = np.arange(100.0, 164.0), np.arange(300.0, 380.0)
    full = radial_distortion(img, ys, xs, 500.0, 600.0, 3e-7, p1_per_px=2e-4, p2_per_px=-1e-4)
    idx = np.sort(rng.choice(img.size, 500, replace=False))
    at = radial_distortion(img, ys, xs, 500.0, 600.0, 3e-7, p1_per_px=2e-4, p2_per_px=-1e-4, at=idx)
    assert np.array_equal(at, full.ravel()[idx])


def test_a_faint_hot_column_with_hot_pixels_in_it_is_a_column():
    """Clipped at 5 sigma, two bright hot pixels do not outweigh a column 2 sigma hot over its length."""
    rng = np.random.default_rng(14)
    var = np.full((1000, 4), 100.0)
    d = rng.normal(0, 10, (1000, 4)) + 20.0
    d[[100, 600], :] += 50000.0
    assert ColumnSignature.short_run_share(d, var)[0] > 0.5  # unclipped, the hot pixels dominate
    assert ColumnSignature.short_run_share(d, var, clip=5.0)[0] < 0.1


def test_outlier_columns_of_integer_data_between_two_codes():
    """A frame of integer ADU whose noise (2.9 ADU) spans few codes and whose level falls half-way between two
    (a 300 s IMX411 dark): no column is an outlier (the columns' medians would jump between 500 and 501,
    18 of their standard errors apart), the columns' statistics are unit normal; a column 0.5 sigma high along
    its length is found."""
    from detector.signatures import line_sigma, spike_stats

    rng = np.random.default_rng(8)
    sd = 2.9
    data = np.rint(500.5 + sd * rng.standard_normal((512, 512)))
    model = np.full(data.shape, 500.5)
    var = np.full(data.shape, sd ** 2 + 1 / 12)
    stats, _ = spike_stats(data, model, var, np.ones(data.shape, bool), 1.0)
    assert stats.hot_cols == 0 and stats.cold_cols == 0
    assert 0.85 < np.nanstd(stats.col_z) < 1.15
    data[:, 200] = np.rint(500.5 + 0.5 * sd + sd * rng.standard_normal(512))
    stats, _ = spike_stats(data, model, var, np.ones(data.shape, bool), 1.0)
    assert stats.col_z[200] > line_sigma(stats.col_z.size) and stats.hot_cols == 1


def test_a_glow_wider_than_the_edge_laws_longest_is_no_glow():
    """An amplifier glow is localised (GLOW_MAX_SCALE of the sensor, the edge law's longest e-folding): a
    bivariate-normal source wider than that is a field-wide gradient, whose nearly flat template trades its
    level against the dark and bias levels (a 60 000 px "glow" of 5.6e3 e- saturated a binned dark's model)."""
    from helpers import residuals_of, small_sensor

    from detector.effects.glow import GLOW_MAX_SCALE, _gauss_variant

    s = small_sensor("ml11002", 64, 64)
    z = np.zeros((64, 64))
    res = residuals_of(z, z, z + 1.0, z, s)
    side = max(s.sensor_width_px, s.sensor_height_px)
    assert _gauss_variant(res, 0.0, 0.0, 0.9 * GLOW_MAX_SCALE * side).to_params([1.0]) is not None
    assert _gauss_variant(res, 0.0, 0.0, 1.1 * GLOW_MAX_SCALE * side).to_params([1.0]) is None


def test_columns_that_repeat_with_a_period_are_no_column_defects():
    """Defective columns sit at random columns: a response that repeats every 3.3 columns (a square wave, 2 %)
    gives column means with a significant period, read as a periodic pattern; ten weak columns at random
    positions give none."""
    from helpers import residuals_of, small_sensor

    from detector.effects.defects import ColumnSignature

    rng = np.random.default_rng(5)
    s = small_sensor("ml11002", 256, 128)
    model = np.full((128, 256), 20000.0)
    var = model / 1.5 + 10.0
    wave = np.where((np.arange(256) / 3.3) % 1.0 < 0.5, 1.0, 0.98)
    weak = np.ones(256)
    weak[rng.choice(256, 10, replace=False)] = 0.98
    for response, periodic in ((wave, True), (weak, False)):
        data = model * response[None, :] + rng.standard_normal(model.shape) * np.sqrt(var)
        peak = ColumnSignature._column_period(residuals_of(data, model, var, model, s))
        assert (peak is not None) == periodic, peak
        if periodic:
            assert abs(peak[0] - 3.3) < 0.1, peak


def test_a_dsnu_with_a_large_scale_part_scatters_as_its_own_signal():
    """A DSNU (30 % white) with a smooth part of 10 % rms on a uniform dark: where the dark is 10 % brighter its
    pixels scatter 21 % more (the variance goes as the dark signal squared). The cells are judged against the
    signal with the fit's own smooth part, on the residual that part leaves: the scatter is uniform (against the
    model's flat dark the cells' chi2 was 415 for 15 dof, 1.1 to 2.2 x the fit's)."""
    rng = np.random.default_rng(31)
    shape = (256, 256)
    s = make_sensor("ml11002", {"width": 256, "height": 256, "bias_adu": 0})
    dark = np.full(shape, 400.0)  # [ADU], the model's
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]] / shape[0]
    lf = np.cos(2 * np.pi * (0.8 * xx + 0.3 * yy) + 0.4) + np.cos(2 * np.pi * (-0.4 * xx + 0.9 * yy) + 2.0)
    lf = 0.10 * lf / lf.std()
    var = np.full(shape, 16.0) + dark / s.gain_e_per_adu
    truth = dark * (1 + lf) * (1 + 0.3 * rng.standard_normal(shape))
    data = truth + rng.normal(0, np.sqrt(var))
    none = SpikeStats(0, 0, 0, 0, 0)
    res = Residuals(data.astype(np.float32), dark.astype(np.float32), var.astype(np.float32), np.ones(shape, bool),
                    np.zeros(shape, np.float32), (dark * s.gain_e_per_adu).astype(np.float32),
                    np.arange(256.0), np.arange(256.0), s, 10.0, none, none, light_source="none")
    dsnu = registry()["dsnu"].signature
    fit = dsnu.fit(res, "dsnu")
    assert fit is not None and "low-frequency" in fit.note, None if fit is None else fit.note
    assert dsnu.uniformity(fit, res) == ""
    assert dsnu.check(fit, res) == ""  # its large scales keep the rate above zero (+-30 %)


def _dark_dsnu(glow_peak_e: float, seed: int = 32):
    """A 256 x 256 dark of 20 e- per pixel with a 30 % DSNU (a model without it), plus a point glow of
    ``glow_peak_e`` at the window's corner: the irradiance of a point emitter 40 px above the sensor plane,
    ``(1 + (d / 40 px)^2)^-1.5`` (shot noise drawn). ``(residuals, the DSNU signature)``."""
    rng = np.random.default_rng(seed)
    shape = (256, 256)
    s = make_sensor("ml11002", {"width": 256, "height": 256, "bias_adu": 0})
    g = s.gain_e_per_adu
    dark_e = np.full(shape, 20.0)
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
    glow = glow_peak_e * (1 + (xx ** 2 + yy ** 2) / 40.0 ** 2) ** -1.5
    var = (dark_e / g + (s.read_noise_e / g) ** 2).astype(np.float32)
    charge = rng.poisson(dark_e * np.maximum(1 + 0.3 * rng.standard_normal(shape), 0) + glow)
    data = charge / g + rng.normal(0, s.read_noise_e / g, shape)
    none = SpikeStats(0, 0, 0, 0, 0)
    res = Residuals(data.astype(np.float32), (dark_e / g).astype(np.float32), var, np.ones(shape, bool),
                    np.zeros(shape, np.float32), dark_e.astype(np.float32), np.arange(256.0), np.arange(256.0), s,
                    100.0, none, none, light_source="none")
    return res, registry()["dsnu"].signature


def test_a_dsnu_whose_large_scales_take_the_dark_rate_below_zero_is_a_charge_on_top_of_it():
    """A DSNU multiplies each pixel's rate by a non-negative factor. Its large-scale part may follow a smooth field
    of rate (a DSNU alone: plausible), but a point glow of 40x the dark at the corner, which the frame's dark level
    takes the mean of, leaves a field below minus the dark rate over most of the window: added charge, not DSNU."""
    res, dsnu = _dark_dsnu(0.0)
    fit = dsnu.fit(res, "dsnu")
    assert fit is not None and dsnu.plausible(fit, res) == ""
    res, dsnu = _dark_dsnu(800.0)
    fit = dsnu.fit(res, "dsnu")
    assert fit is not None and "low-frequency" in fit.note, None if fit is None else fit.note
    assert "below zero" in dsnu.plausible(fit, res)


def _star_field_residuals(rng, log_flux: tuple[float, float], h: int = 128, w: int = 256):
    """(residuals of a 300 ADU sky with 12 Gaussian stars of 10^log_flux ADU at random places, every pixel fitted,
    the sky its background; the stars' image [ADU])."""
    import dataclasses

    from helpers import residuals_of, small_sensor

    sky = np.full((h, w), 300.0)
    yy, xx = np.mgrid[0:h, 0:w]
    stars = np.zeros((h, w))
    for cy, cx, f in zip(rng.uniform(5, h - 5, 12), rng.uniform(5, w - 5, 12), 10 ** rng.uniform(*log_flux, 12)):
        stars += f * np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * 1.5 ** 2)) / (2 * np.pi * 1.5 ** 2)
    model = sky + stars
    res = residuals_of(model, model, model + 25.0, model, small_sensor("ml11002", w, h))
    return dataclasses.replace(res, background_adu=sky.astype(np.float32)), stars


def test_outlier_columns_at_the_bright_sources_columns_are_no_column_defects():
    """Smear (the shutter open while the rows are shifted) lifts every column by a share of its light: its outlier
    columns are the columns of the brightest sources (their ranks in the columns' source light no uniform draw)
    and the other columns' means rise with their source light too; the check says so. Ten hot columns at random
    places of the same frame pass, also when one of them sits on the brightest source's column (the other columns
    are as they were), as do columns on a frame without sources (no source light to rank)."""
    import dataclasses

    from detector.effects.defects import ColumnSignature
    from detector.signatures import SpikeStats, line_sigma

    rng = np.random.default_rng(12)
    base, stars = _star_field_residuals(rng, (4, 6))
    w = stars.shape[1]
    flux = stars.sum(axis=0)

    def judged(col_z):
        res = dataclasses.replace(base, data_spikes=SpikeStats(0, 0, 0, 0, 0, col_z=col_z))
        assert np.any(np.abs(col_z) > line_sigma(w))  # outlier columns to judge
        return ColumnSignature._at_source_columns(res)

    smear = rng.standard_normal(w) + 15.0 * flux / flux.max()  # the brightest column 15 standard errors up
    why = judged(smear)
    assert "follow the sources' light" in why and "not defective columns" in why, why
    hot = rng.standard_normal(w)
    hot[rng.choice(w, 9, replace=False)] += 12.0
    hot[np.argmax(flux)] += 12.0
    assert judged(hot) == ""
    dark = dataclasses.replace(base, background_adu=base.model_adu)  # a frame without sources
    assert ColumnSignature._at_source_columns(dataclasses.replace(dark, data_spikes=SpikeStats(0, 0, 0, 0, 0,
                                                                                                col_z=smear))) == ""


def test_columns_through_the_sources_are_described_as_a_streak_with_their_share_of_the_light():
    """The morphology's fitted pixels leave outlier columns out, so it describes columns that follow the
    sources from the column statistics: additive, columns and sources, with the share of each column's source
    light that its pixels hold (1e-4 per row here, 1.28 % over the 128 rows) measured within 10 % from the
    columns' median residuals (the smear in the data, with its noise)."""
    import dataclasses

    from detector.morphology import _columns_through_sources
    from detector.signatures import SpikeStats

    rng = np.random.default_rng(13)
    base, stars = _star_field_residuals(rng, (5, 6))
    h, w = stars.shape
    err = np.full(w, np.sqrt(325.0 / h))  # the standard error of a column's mean [ADU]
    smear = 1e-4 * stars.sum(axis=0)  # [ADU per pixel]
    col_z = smear / err + rng.standard_normal(w)
    data = base.model_adu + smear[None, :] + rng.standard_normal((h, w)) * np.sqrt(base.var_adu2)
    res = dataclasses.replace(base, data_adu=data.astype(np.float32),
                              data_spikes=SpikeStats(0, 0, 0, 0, 0, col_z=col_z, col_err_adu=err))
    out = _columns_through_sources(res)
    assert out["significant"] and out["kind"] == "additive" and out["geometry"] == ["columns", "sources"], out
    assert out["amplitude"] == pytest.approx(100 * 1e-4 * h, rel=0.1)
    assert _columns_through_sources(dataclasses.replace(res, background_adu=res.model_adu)) == {}
