"""Candidates of the telescope's alignment: ``misalignment`` and ``defocus`` fitted to the stars' second moments.

What is measured
    For every isolated, unsaturated catalogue star of the model's TRUTH table, the centroid and the
    *unweighted* second central moments (Mxx, Myy, Mxy) [output px^2] inside a circular aperture, in the
    measured frame and in the model's mean frame, each over its background: the model's background frame
    (:func:`.statistics.background_adu`) and, in the measured frame, what it holds beyond that where the
    model has no source (a quadratic surface, :func:`sky_surface`; a local annulus would hold the star's own
    wings, more of them in a star the perturbation widens). Unweighted moments, because only they add
    under convolution (the measured star is the optical spot convolved with seeing, diffraction, the pixel
    and charge diffusion), which is what the alignment fit's model assumes (:mod:`optics.alignment`:
    ``M = m_optics(p) + s I``). The aperture (radius :data:`APERTURE_SIGMA` times the larger of the two
    stars' rms sizes, :data:`MIN_RADIUS_PX` to :data:`MAX_RADIUS_PX`) is the same in both frames; it trades
    noise (the moments' error grows as r^3) against truncation (the wings it cuts shrink the measured change:
    a diagonal tilted 0.1 deg on 9 um pixels comes out 10 % low at 4 sigma, 5.5 % at 6, 4.5 % at 8 with twice
    the error). The error of each moment is the pixel noise propagated through the unweighted sum,
    ``var(Mxx) = sum_i ((x_i - cx)^2 - Mxx)^2 var_i / F^2`` (var_i the model's variance of pixel i, F the
    star's flux), plus that of the background level.

From pixels to the optics' focal plane
    The scene reads the optics' focal plane (u, v) [mm] (:mod:`optics.layout`; origin on the optical axis,
    the sensor's centre) as sensor pixels x = s_x u / pitch, y = s_y v / pitch about the sensor's centre
    ((W - 1) / 2, (H - 1) / 2), with s_y = :data:`scenes.projection.FOCAL_PLANE_Y_SIGN` = -1 and s_x =
    -parity (= +1 for the default ``parity = -1``; :func:`scenes.projection.sip_from_optics`, and the
    stamps' row flip of :mod:`scenes.image.gridpsf`). An output pixel (x_o, y_o) of a window at (x0, y0)
    binned by b is the sensor pixel (x0 + b x_o + (b - 1) / 2, ...). So

        u = s_x (x_s - (W - 1) / 2) p,   v = s_y (y_s - (H - 1) / 2) p,
        muu = Mxx (b p)^2,   mvv = Myy (b p)^2,   muv = s_x s_y Mxy (b p)^2,

    and the star's field angles are theta = atan(-(u, v) / f) (the image of field theta lies at -f tan theta,
    :mod:`optics.distortion`). :func:`pixel_to_focal` does this; ``tests/scenes/test_diagnose_optics.py``
    checks it against the render (a perturbed frame's fitted sign, and the model frame's cross moments
    against the traced ones).

What is fitted
    With ``[psf] model = "optics"`` the model frame already holds the nominal optics' PSF, drawn through the
    same grid interpolation, pixel integration and aperture as the measured star. The fit is then given

        M_fit = M_data - M_model + m_design(theta) + c,

    the measured moments less the model's, on top of the design's own traced moments at the star and the
    model's median isotropic rest c (pixel, seeing, diffraction): the model frame calibrates everything the
    render adds that is not a perturbation (the grid's bilinear blend, the aperture's truncation). With any
    other PSF model the model frame holds no optics and ``M_fit = M_data``: the measured stars against the
    traced design, the seeing/pixel/PSF-model part the fit's isotropic nuisance. The centroids are not
    fitted: the frame's WCS (TAN, or the chief-ray SIP of the *scene's* design) puts both frames' stars
    where the scene says, so their positions carry the pointing and the plate solution, not the optics of
    the measured telescope.

    :func:`optics.alignment.rank_perturbations` fits each family of perturbations alone (defocus, sensor
    tilt, diagonal tilt, primary tilt and decentre) with its isotropic nuisance, against the
    nuisance-only fit (:data:`FAMILIES`). The reference a family must beat is the better of that fit (the
    design as it is) and the scene's own PSF (the model frame's moments plus the isotropic nuisance,
    :func:`model_psf_chi2`): a Gaussian-PSF scene and a frame made with it agree, and the traced design's
    field curvature, absent from such a frame, must not come out as a defocus. Each family becomes a candidate: ``defocus`` (``sensor_piston_um``) and
    ``misalignment`` (the others; the family in ``variant``), with ``delta_m2lnl = -(chi^2_ref - chi^2) / q`` and
    ``k`` = the family's parameters, ``n`` = the fitted moments; ``q = max(1, chi^2 / dof)`` of the best
    family: scatter no family explains (blends, the model's own systematics) makes every drop less
    significant and every error larger by sqrt(q). ``params``: the ``[perturbation]`` names with the
    fitted values (the design's own perturbation included: they are the values to write) and ``errors``
    (same names).

Pixels
    The moments' likelihood (three numbers per star, a few hundred stars) cannot be ranked against the pixel
    candidates' (millions of pixels): ``psf_blur`` or ``jitter`` would always win on a misaligned frame, since
    the pixels see the changed stars too. So, given the comparison's model frame and a scene whose PSF is the
    optics' grid, the best :data:`PIXEL_FAMILIES` families (those whose moments' drop is significant) are
    scored on the pixels: the model's sources drawn again with the PSF of the design perturbed by the fitted
    values (:class:`PixelPredictor`: the scene's cube, each stamp changed by the change of the geometric spot,
    through the render's own grid blend, pixel integration and detector chain), and the candidate's
    ``delta_adu`` is that frame less the model's. Its ``delta_m2lnl`` is the pixels' Gaussian -2 ln L with the
    global levels refitted (:func:`detector.signatures.pixel_score`, what every pixel candidate is scored
    with), ``n`` the fitted pixels, and its held-out score the same number: the parameters come from the
    moments, not from these pixels' likelihood. The best family's amplitude is then refined on the pixels
    (one scale along the fitted direction, :meth:`PixelPredictor.score`): the moments' aperture cuts the
    wings of a widened star, the pixels keep all of it. A scene with a Gaussian or Moffat PSF has no optics
    in its model frame to perturb: its candidates keep the moments' likelihood.

    A blur, a jitter or an elongation of the PSF adds the same second moments to every star. When the stars'
    change of moments is far from uniform over the field and an optics family fits it far better, those
    candidates are marked implausible (:func:`field_pattern_check`, called by ``run_diagnose``): their pixel
    fit follows the changed stars, not the effect.

Runtime: one trace per iteration of each family's fit (Chebyshev nodes over the stars' field, forward-mode
AD; :func:`optics.alignment.fit_perturbations`), about 10-40 s for the whole ranking on 2 cores; each pixel
prediction 1-2 s on a 2048 x 2048 frame (75 spot traces, one render of the sources, the detector's moments), six
or seven of them.
"""

from __future__ import annotations

import math
import time

import numpy as np

from detector.signatures import Fit, Residuals
from detector.significance import DETECTION_SIGMA, STRONG_EVIDENCE

from .statistics import background_adu

#: the candidates' names (``--apply`` writes them into a design TOML: :mod:`.apply`)
MISALIGNMENT, DEFOCUS = "misalignment", "defocus"
OPTICS_CANDIDATES = (MISALIGNMENT, DEFOCUS)
#: measurable stars needed for a fit
MIN_STARS = 30
#: stars measured at most (brightest first)
MAX_STARS = 600
#: the aperture's radius in units of the star's rms size sqrt((Mxx + Myy) / 2), and its floor and ceiling [px]
APERTURE_SIGMA, MIN_RADIUS_PX, MAX_RADIUS_PX = 6.0, 4, 12
#: aperture [px] of the first pass that sizes the star (small: the moments of a wide aperture are dominated by the
#: error of the background level, sum r^2 / F per ADU)
FIRST_RADIUS_PX = 6
#: a star needs this signal-to-noise in its aperture, and no other source brighter than NEIGHBOUR_FRACTION of
#: it within its box
MIN_SNR, NEIGHBOUR_FRACTION = 50.0, 0.02
#: pupil rays per field point and wavelengths [nm] of the optics model (450-900 nm, the grid's band
#: optics.psf.DEFAULT_BAND_NM, sampled at three wavelengths), and field points per axis
N_RAYS, WAVELENGTHS_NM, NODES = 1000, (500.0, 650.0, 800.0), 6
#: families fitted (:data:`optics.alignment.FAMILIES`): the issue's perturbations. The corrector's (decentre, tilt,
#: spacing) are left out: a spacing error refocuses the field like a sensor piston (on a defocused ``art`` frame
#: both fit, the spacing slightly better), and a diagonal tilt mimics the corrector's decentre and tilt (the
#: beam turned at the diagonal moves corrector and sensor rigidly); pass ``families=`` to fit them
FAMILIES = ("defocus", "sensor_tilt", "diagonal_tilt", "primary_tilt", "primary_decenter")


# ---------------------------------------------------------------------------------------------- geometry
def focal_plane_axes(parity: int = -1) -> tuple[float, float]:
    """(s_x, s_y): sensor pixel offsets (x, y) = (s_x u, s_y v) / pitch (module notes)."""
    from scenes.projection import FOCAL_PLANE_Y_SIGN

    return -float(parity), float(FOCAL_PLANE_Y_SIGN)


def pixel_to_focal(x_out, y_out, sensor, parity: int = -1) -> tuple[np.ndarray, np.ndarray]:
    """Focal-plane position (u, v) [mm] of output pixel coordinates (0-based, binned, in the read-out window)."""
    sx, sy = focal_plane_axes(parity)
    b = sensor.binning
    p_mm = sensor.pixel_pitch_um * 1e-3
    xs = sensor.roi_x0 + b * np.asarray(x_out, float) + (b - 1) / 2.0
    ys = sensor.roi_y0 + b * np.asarray(y_out, float) + (b - 1) / 2.0
    return (sx * (xs - (sensor.sensor_width_px - 1) / 2.0) * p_mm,
            sy * (ys - (sensor.sensor_height_px - 1) / 2.0) * p_mm)


def moments_to_focal(mxx, myy, mxy, sensor, parity: int = -1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Second moments [output px^2] -> (muu, mvv, muv) [mm^2] (module notes)."""
    sx, sy = focal_plane_axes(parity)
    s2 = (sensor.binning * sensor.pixel_pitch_um * 1e-3) ** 2
    return np.asarray(mxx) * s2, np.asarray(myy) * s2, sx * sy * np.asarray(mxy) * s2


def field_angles_deg(u_mm, v_mm, focal_length_mm: float) -> np.ndarray:
    """(n, 2) field angles [deg] of stars imaged at (u, v) [mm]: theta = atan(-(u, v) / f)."""
    return np.degrees(np.arctan(-np.stack([np.asarray(u_mm, float), np.asarray(v_mm, float)], -1) / focal_length_mm))


# ---------------------------------------------------------------------------------------------- measurement
def _disk(r: int, r_out: int):
    yy, xx = np.mgrid[-r_out:r_out + 1, -r_out:r_out + 1]
    rr = np.hypot(xx, yy)
    return yy, xx, rr


def unweighted_moments(img: np.ndarray, var: np.ndarray | None, xx, yy, ap) -> dict | None:
    """Flux, centroid and unweighted second central moments of ``img`` (background-free) over the aperture
    mask ``ap``, with their errors from the per-pixel variance ``var`` (None: no errors)."""
    w = np.where(ap, img, 0.0)
    f = float(w.sum())
    if not f > 0:
        return None
    cx, cy = float((w * xx).sum() / f), float((w * yy).sum() / f)
    dx, dy = xx - cx, yy - cy
    mxx, myy, mxy = (float((w * dx * dx).sum() / f), float((w * dy * dy).sum() / f), float((w * dx * dy).sum() / f))
    out = {"flux": f, "cx": cx, "cy": cy, "mxx": mxx, "myy": myy, "mxy": mxy}
    if var is not None:
        v = np.where(ap, var, 0.0)
        out["var_flux"] = float(v.sum())
        out["var_mxx"] = float(((dx * dx - mxx) ** 2 * v).sum() / f ** 2)
        out["var_myy"] = float(((dy * dy - myy) ** 2 * v).sum() / f ** 2)
        out["var_mxy"] = float(((dx * dy - mxy) ** 2 * v).sum() / f ** 2)
    return out


def measure_stars(res: Residuals, truth, *, max_stars: int = MAX_STARS) -> dict:
    """Moments of the isolated, unsaturated catalogue stars in the measured frame and in the model (module
    notes). Returns ``{"n", "x", "y", "data": {...}, "model": {...}, "err": {...}, "radius_px", "rejected"}``
    (arrays over the measured stars; moments in output px^2)."""
    empty = {"n": 0, "rejected": {}}
    if truth is None or len(truth) == 0 or "kind" not in truth.dtype.names:
        return empty
    kind = np.char.strip(np.asarray(truth["kind"]).astype(str))
    st = truth[kind == "star"]
    if len(st) == 0:
        return empty
    h, w = res.data_adu.shape
    rbox = MAX_RADIUS_PX + 2
    inside = (st["x"] > rbox) & (st["x"] < w - 1 - rbox) & (st["y"] > rbox) & (st["y"] < h - 1 - rbox)
    rejected = {"edge": int((~inside).sum())}
    st = st[inside]
    st = st[np.argsort(-st["flux_e"])]
    # neighbours: any source (stars and objects' mid-points) within the box brighter than a fraction
    from scipy.spatial import cKDTree

    xy_all = np.stack([truth["x"], truth["y"]], -1)
    ok_all = np.isfinite(xy_all).all(1)
    tree = cKDTree(xy_all[ok_all])
    flux_all = np.asarray(truth["flux_e"], float)[ok_all]
    bg = background_adu(res)
    sky = sky_surface(res, bg)
    yy, xx, rr = _disk(0, rbox)
    rows = []
    counts = {"neighbour": 0, "flagged": 0, "faint": 0, "bad": 0}
    for s_ in st:
        if len(rows) >= max_stars:
            break
        x, y = float(s_["x"]), float(s_["y"])
        near = tree.query_ball_point([x, y], r=math.sqrt(2) * rbox + 1)
        if sum(1 for j in near if flux_all[j] > NEIGHBOUR_FRACTION * float(s_["flux_e"])) > 1:
            counts["neighbour"] += 1
            continue
        xi, yi = round(x), round(y)
        sl = (slice(yi - rbox, yi + rbox + 1), slice(xi - rbox, xi + rbox + 1))
        if not res.fit[sl][rr <= rbox].all():  # saturated, flagged (hot pixels, defects) or an outlier (a cosmic ray)
            counts["flagged"] += 1
            continue
        d_img = (res.data_adu[sl] - bg[sl]).astype(np.float64)
        m_img = (res.model_adu[sl] - bg[sl]).astype(np.float64)
        var = res.var_adu2[sl].astype(np.float64)
        meas = _measure_pair(d_img - sky(xi, yi)[0], m_img, var, xx + (xi - x), yy + (yi - y), rr, sky(xi, yi)[1])
        if meas is None:
            counts["bad"] += 1
            continue
        d, m, r, ann_var = meas
        if d["flux"] < MIN_SNR * math.sqrt(d["var_flux"]) or m["flux"] < MIN_SNR * math.sqrt(d["var_flux"]):
            counts["faint"] += 1
            continue
        rows.append((x, y, d, m, r, ann_var))
    rejected.update(counts)
    if not rows:
        return {**empty, "rejected": rejected}
    out = {"n": len(rows), "x": np.array([r[0] for r in rows]), "y": np.array([r[1] for r in rows]),
           "radius_px": np.array([r[4] for r in rows]), "rejected": rejected, "data": {}, "model": {}, "err": {}}
    for k in ("flux", "cx", "cy", "mxx", "myy", "mxy"):
        out["data"][k] = np.array([r[2][k] for r in rows])
        out["model"][k] = np.array([r[3][k] for r in rows])
    for k in ("mxx", "myy", "mxy"):
        out["err"][k] = np.sqrt(np.array([r[2]["var_" + k] + (r[5][k] if k != "mxy" else 0.0) for r in rows]))
    return out


def sky_surface(res: Residuals, bg: np.ndarray, step: int = 4):
    """What the measured frame holds beyond the model's background where the model has no source: a quadratic
    surface in (x, y) fitted (3-sigma clipped least squares) to ``data - bg`` on every ``step``-th row and column
    of the pixels where the model's sources add less than 0.05 sigma. Returns ``f(x, y) -> (level [ADU], its
    standard error [ADU])``.

    A global surface rather than each star's annulus: an annulus holds the star's own wings, more of them in
    a star the perturbation widens, and taking them off with the sky shrinks the measured change of its
    moments (a diagonal tilted 0.1 deg came out 10 % low on 9 um pixels)."""
    h, w = res.data_adu.shape
    ys, xs = np.mgrid[0:h:step, 0:w:step]
    d = (res.data_adu[::step, ::step] - bg[::step, ::step]).astype(np.float64)
    src = (res.model_adu[::step, ::step] - bg[::step, ::step]) / np.sqrt(np.maximum(res.var_adu2[::step, ::step], 1e-12))
    keep = res.fit[::step, ::step] & (src < 0.05)
    xn, yn, z = (xs[keep] / max(w, 1) - 0.5).ravel(), (ys[keep] / max(h, 1) - 0.5).ravel(), d[keep].ravel()

    def design(x, y):
        x, y = np.atleast_1d(x), np.atleast_1d(y)
        return np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], -1)

    if z.size < 50:
        return lambda x, y: (0.0, 0.0)
    A = design(xn, yn)
    ok = np.ones(z.size, bool)
    for _ in range(4):
        coef, *_ = np.linalg.lstsq(A[ok], z[ok], rcond=None)
        r = z - A @ coef
        sd = float(np.std(r[ok]))
        new = np.abs(r) <= 3 * max(sd, 1e-12)
        if (new == ok).all():
            break
        ok = new
    cov = sd ** 2 * np.linalg.pinv(A[ok].T @ A[ok])

    def at(x, y):
        a = design(np.asarray(x, float) / max(w, 1) - 0.5, np.asarray(y, float) / max(h, 1) - 0.5)
        return float((a @ coef)[0]), float(np.sqrt(max((a @ cov @ a.T)[0, 0], 0.0)))
    return at


def _measure_pair(d_img, m_img, var, xx, yy, rr, level_err: float = 0.0):
    """Moments of one star in data and model (both over their background already) with a common aperture.
    ``xx``, ``yy``: pixel offsets from the star's TRUTH position; ``rr`` the distance from the box centre;
    ``level_err`` the error [ADU] of the data's background level."""
    r = FIRST_RADIUS_PX
    sizes = []
    for img in (d_img, m_img):   # first pass: the star's size
        mo = unweighted_moments(img, None, xx, yy, rr <= r)
        if mo is None or not (mo["mxx"] > 0 and mo["myy"] > 0):
            return None
        sizes.append(math.sqrt(0.5 * (mo["mxx"] + mo["myy"])))
    r = int(np.clip(math.ceil(APERTURE_SIGMA * max(sizes)), MIN_RADIUS_PX, MAX_RADIUS_PX))
    ap = rr <= r
    d = unweighted_moments(d_img, var, xx, yy, ap)
    m = unweighted_moments(m_img, None, xx, yy, ap)
    if d is None or m is None:
        return None
    # the level's error moves Mxx by sum_ap((x - cx)^2 - Mxx) / F per ADU
    dx, dy = xx - d["cx"], yy - d["cy"]
    lv_var = {"mxx": (level_err * float(np.where(ap, dx * dx - d["mxx"], 0).sum()) / d["flux"]) ** 2,
              "myy": (level_err * float(np.where(ap, dy * dy - d["myy"], 0).sum()) / d["flux"]) ** 2}
    return d, m, r, lv_var


# ---------------------------------------------------------------------------------------------- the fit
def fit_inputs(stars: dict, sensor, design, parity: int, optics_psf: bool, nominal=None) -> tuple:
    """(field angles [deg], measured moments {muu_mm2, mvv_mm2, muv_mm2}, their sigma) for
    :func:`optics.alignment.rank_perturbations` (module notes). ``nominal``: the design's traced moments at
    the stars (an :class:`optics.gradients.SpotMoments`), needed when ``optics_psf``."""
    u, v = pixel_to_focal(stars["x"], stars["y"], sensor, parity)
    fields = field_angles_deg(u, v, design.primary.focal_length_mm)
    d = moments_to_focal(stars["data"]["mxx"], stars["data"]["myy"], stars["data"]["mxy"], sensor, parity)
    e = moments_to_focal(stars["err"]["mxx"], stars["err"]["myy"], stars["err"]["mxy"], sensor, parity)
    keys = ("muu_mm2", "mvv_mm2", "muv_mm2")
    measured = dict(zip(keys, d))
    if optics_psf:
        m = moments_to_focal(stars["model"]["mxx"], stars["model"]["myy"], stars["model"]["mxy"], sensor, parity)
        m0 = [nominal.get(k) for k in keys]
        rest = float(np.median(0.5 * (m[0] + m[1] - m0[0] - m0[1])))
        rest = max(rest, (sensor.binning * sensor.pixel_pitch_um * 1e-3) ** 2 / 12.0)
        measured = {k: d[i] - m[i] + m0[i] + (rest if i < 2 else 0.0) for i, k in enumerate(keys)}
    sigma = {k: np.abs(e[i]) for i, k in enumerate(keys)}
    return fields, measured, sigma


def model_psf_chi2(stars: dict, sigma: dict, sensor, parity: int) -> float:
    """chi^2 of the measured moments against the model frame's (the scene's own PSF) plus one isotropic
    nuisance s (weighted least squares), with the errors ``sigma`` of :func:`fit_inputs` [mm^2]: the
    reference a perturbation must beat besides the unperturbed design. A scene whose PSF is not the optics'
    (a Gaussian) and a frame made with it agree; the traced design would not, and a 'defocus' flattening
    the design's field curvature would otherwise be found in every such frame."""
    d = moments_to_focal(stars["data"]["mxx"], stars["data"]["myy"], stars["data"]["mxy"], sensor, parity)
    m = moments_to_focal(stars["model"]["mxx"], stars["model"]["myy"], stars["model"]["mxy"], sensor, parity)
    w = [1.0 / np.maximum(sigma[k], 1e-30) ** 2 for k in ("muu_mm2", "mvv_mm2", "muv_mm2")]
    r = [d[i] - m[i] for i in range(3)]
    s = float((np.sum(w[0] * r[0]) + np.sum(w[1] * r[1])) / (np.sum(w[0]) + np.sum(w[1])))
    return float(np.sum(w[0] * (r[0] - s) ** 2) + np.sum(w[1] * (r[1] - s) ** 2) + np.sum(w[2] * r[2] ** 2))


def optics_candidates(res: Residuals, truth, scene, *, mi=None, families=None, progress=None,
                      model=None) -> tuple[list, list]:
    """The ``misalignment`` / ``defocus`` candidates of a comparison (module notes), as
    :class:`scenes.app.compare.candidates.Candidate`, and the problems (a list of ``{"effect", "error"}``)
    when they cannot be fitted (no Mitsuba, too few stars). With the comparison's ``model``
    (:class:`.model.ModelFrame`) and a scene whose PSF is the optics' grid, the best families are scored on the
    pixels (module notes, "Pixels"); without it, by the moments alone."""

    from .candidates import Candidate, chi2_after, excess_shares, structure_shares

    if scene.exposure.frame != "light" or not scene.sky.stars or scene.sky.flat_e_per_s is not None:
        return [], []
    name = f"{MISALIGNMENT}/{DEFOCUS}"
    t0 = time.perf_counter()
    stars = measure_stars(res, truth)
    if stars["n"] < MIN_STARS:
        return [], [{"effect": name, "error": f"skipped: {stars['n']} measurable catalogue stars (isolated, "
                     f"unsaturated, S/N > {MIN_SNR:g}), {MIN_STARS} needed to fit the optics' alignment "
                     f"(rejected: {stars['rejected']})"}]
    try:
        from optics.design import OpticsError, load_design

        if mi is None:
            from optics.llvm import init_mitsuba

            mi = init_mitsuba()
        design = load_design(scene.telescope.design)
    except (ImportError, OpticsError) as exc:
        return [], [{"effect": name, "error": f"skipped: the optics cannot be traced ({exc})"}]
    from optics.alignment import explain, rank_perturbations
    from optics.gradients import spot_moments
    from optics.sequential import SequentialTracer

    if progress is not None:
        progress("misalignment/defocus")
    sensor = scene.sensor()
    parity = int(scene.telescope.parity)
    optics_psf = scene.psf.model == "optics"
    tracer = SequentialTracer(design, mi)
    kw = {"n_rays": N_RAYS, "wavelengths_nm": WAVELENGTHS_NM, "nodes": NODES}
    nominal = None
    if optics_psf:
        u, v = pixel_to_focal(stars["x"], stars["y"], sensor, parity)
        nominal = spot_moments(tracer, field_angles_deg(u, v, design.primary.focal_length_mm), n_rays=N_RAYS,
                               wavelengths_nm=WAVELENGTHS_NM)
    fields, measured, sigma = fit_inputs(stars, sensor, design, parity, optics_psf, nominal)
    cands, base = rank_perturbations(design, mi, fields, measured, sigma, families=families or FAMILIES,
                                     tracer=tracer, **kw)
    best = cands[0].fit if cands else base
    q = max(1.0, best.chi2 / max(best.dof, 1))
    # the reference: the better of the design as it is (the nuisance-only fit) and the scene's own PSF (the
    # model frame's moments plus the isotropic nuisance): a perturbation must explain the stars better than both
    own = model_psf_chi2(stars, sigma, sensor, parity)
    ref = min(base.chi2, own)
    n = 3 * stars["n"]
    note_psf = ("" if optics_psf else
                "; the scene's PSF is not the optics' ([psf] model = 'optics'), so --apply changes only its "
                + ("SIP distortion" if scene.telescope.distortion == "optics" else
                   "design file (no distortion = 'optics', no optics PSF: the frame does not change)"))
    out = []
    seconds = (time.perf_counter() - t0) / max(len(cands), 1)
    explained = {}
    uniform = uniform_change_chi2(stars, sigma, sensor, parity)
    pixels, pixel_problem = None, ""
    if model is not None and any((ref - c.fit.chi2) / q > STRONG_EVIDENCE for c in cands):
        try:
            pixels = PixelPredictor.build(model, scene, design, mi)
        except (OSError, ValueError, KeyError) as exc:
            pixel_problem = f"not scored on the pixels ({exc})"
    scored = 0
    for c in cands:
        fit = c.fit
        drop = (ref - fit.chi2) / q
        values, errs = np.array(fit.values, float), fit.errors * math.sqrt(q)
        t1 = time.perf_counter()
        delta, m2l, scale = None, None, 1.0
        if pixels is not None and drop > STRONG_EVIDENCE and scored < PIXEL_FAMILIES:
            # a prediction of every pixel: scored like the pixel candidates (their -2 ln L, levels refitted);
            # the best family's amplitude refined on the pixels (the moments' aperture cuts the wings)
            delta, m2l, scale = pixels.score(res, fit.names, values, refine=scored == 0)
            scored += 1
            values, errs = values * scale, errs * abs(scale)
        z = values / np.where(errs > 0, errs, np.inf)
        i = int(np.argmax(np.abs(z)))
        effect = DEFOCUS if c.family == "defocus" else MISALIGNMENT
        if effect not in explained and drop > STRONG_EVIDENCE:   # the best of each kind: with the field pattern
            words = explain(fit.names[i], values[i], errs[i], tracer, fit.fields_deg,
                            {"n_rays": N_RAYS, "wavelengths_nm": WAVELENGTHS_NM})
        else:
            words = explain(fit.names[i], values[i], errs[i])
        explained.setdefault(effect, True)
        words += (f" ({c.family.replace('_', ' ')} fitted to the second moments of {stars['n']} stars: chi2 drop "
                  f"{drop:.4g} for {len(fit.names)} parameter{'s' if len(fit.names) > 1 else ''}"
                  + (f", errors x {math.sqrt(q):.3g} for the unexplained scatter" if q > 1.05 else "") + ")" + note_psf)
        if delta is not None:
            words += (f"; its pixel prediction (the model's sources drawn with the perturbed design's PSF) changes "
                      f"-2 ln L by {m2l:.4g}" + (f", with the amplitude {scale:.3g} times the moments' fit that the "
                                                 "pixels prefer" if scale != 1.0 else ""))
        params = {k: round(float(v), 6) for k, v in zip(fit.names, values)}
        params["errors"] = {k: round(float(e), 6) for k, e in zip(fit.names, errs)}
        state = {"nuisances": fit.nuisances, "chi2": fit.chi2, "dof": fit.dof, "n_stars": stars["n"],
                 "chi2_design": base.chi2, "chi2_scene_psf": own, "scale": q, "moments_delta_m2lnl": -float(drop),
                 "chi2_uniform": uniform[0], "dof_uniform": uniform[1], "pixel_scale": scale,
                 "rest_correlation": None if fit.rest_correlation is None else
                 [round(float(r), 4) for r in fit.rest_correlation],
                 "moments_values": {k: float(v) for k, v in zip(fit.names, fit.values)}}
        f = Fit(effect, params, -float(drop), len(fit.names), n, words, note=c.family, state=state)
        if delta is not None:
            f.delta_adu, f.delta_m2lnl, f.n = delta, float(m2l), int(res.n_fit)
        cand = Candidate(f, chi2_after(res, f), seconds + time.perf_counter() - t1)
        if f.delta_adu is not None:
            # its parameters come from the stars' moments, not from a fit to these pixels (at most one amplitude
            # is refined on them): the pixel delta is a prediction of pixels the fit did not see, as the pixel
            # candidates' held-out score is
            cand.heldout = f.delta_m2lnl
        out.append(cand)
    structure_shares(res, [c for c in out if c.fit.delta_adu is not None])
    excess_shares(res, [c for c in out if c.fit.delta_adu is not None])
    if pixel_problem:
        for c in out:
            c.fit.explanation += f"; {pixel_problem}"
    return out, []


#: the pixel candidates that change every star's shape in the same way over the whole frame
UNIFORM_PSF = ("psf_blur", "jitter", "psf_elongation")


def uniform_change_chi2(stars: dict, sigma: dict, sensor, parity: int) -> tuple[float, int]:
    """(chi^2, dof) of the stars' change of second moments (data - model) [mm^2] fitted by one constant
    change (dMuu, dMvv, dMuv) over the field (weighted means): what a blur, a jitter or an elongation of the
    PSF makes (the same kernel convolved with every star adds the same second moments, whatever the star)."""
    d = moments_to_focal(stars["data"]["mxx"], stars["data"]["myy"], stars["data"]["mxy"], sensor, parity)
    m = moments_to_focal(stars["model"]["mxx"], stars["model"]["myy"], stars["model"]["mxy"], sensor, parity)
    chi2 = 0.0
    for i, k in enumerate(("muu_mm2", "mvv_mm2", "muv_mm2")):
        w = 1.0 / np.maximum(sigma[k], 1e-30) ** 2
        r = d[i] - m[i]
        c = float(np.sum(w * r) / np.sum(w))
        chi2 += float(np.sum(w * (r - c) ** 2))
    return chi2, 3 * int(stars["n"]) - 3


def field_pattern_check(cands: list, optical: list) -> None:
    """A uniform change of the PSF (:data:`UNIFORM_PSF`) that is significant only because the stars changed
    shape is not plausible when that change varies over the field the way a perturbation of the optics
    predicts: a blur or a jitter adds the same second moments to every star, so a constant change must fit
    the stars' moment changes (``chi2_uniform`` within 5 sqrt(2 dof) of its dof), and an optics candidate
    scored on the pixels must not fit them far better (a chi^2 lower by more than 10 q, q its scatter scale).
    Marks those candidates ``implausible`` in place."""
    best = next((c for c in optical if c.fit.delta_adu is not None
                 and c.fit.delta_bic < c.policy.significant_delta_bic), None)
    if best is None:
        return
    st = best.fit.state
    u, dof, q = st.get("chi2_uniform"), st.get("dof_uniform"), st.get("scale", 1.0)
    if u is None or dof is None or dof <= 0:
        return
    varies = u - dof > DETECTION_SIGMA * math.sqrt(2.0 * dof)
    explained = (u - st["chi2"]) / q > STRONG_EVIDENCE
    if not (varies and explained):
        return
    family = best.fit.note.replace("_", " ")
    why = (f"the stars' change of shape varies over the field: one change of their second moments for all "
           f"(what a uniform blur, jitter or elongation makes) leaves chi2 {u:.4g} for {dof} dof, the "
           f"{family} of the optics fits them with chi2 {st['chi2']:.4g}")
    for c in cands:
        if c.fit.effect in UNIFORM_PSF and not c.implausible:
            c.implausible = why


# ---------------------------------------------------------------------------------------------- pixels
#: rays per wavelength of each geometric spot of the pixel prediction, and the families (best by the moments'
#: chi^2 drop, significant ones only) that get one
PIXEL_RAYS, PIXEL_FAMILIES = 10000, 3
#: the best family's amplitude refined on the pixels: at most REFINE_STEPS parabola steps, scales within SCALE_RANGE
#: (every family's amplitude correlates with the moments' isotropic rest, -0.93 to -0.99 on the test frames: the
#: moments alone take part of a defocus for seeing, 28 % of a 70 um one)
REFINE_STEPS, SCALE_RANGE = 3, (0.5, 2.0)


def scale_search(at, steps: int = None, bounds: tuple = None) -> tuple[float, tuple]:
    """The scale s minimising ``at(s)[1]`` (a -2 ln L) near 1: s = 0.9, 1, 1.1, then the vertex of a parabola
    through the three best so far (within ``bounds``, at most twice their span beyond them; a step beyond
    the best end when they hold no minimum), ``steps`` times or until it moves by less than 0.01. Returns
    (s, at(s))."""
    steps = REFINE_STEPS if steps is None else steps
    lo, hi = SCALE_RANGE if bounds is None else bounds
    tried = {sc: at(sc) for sc in (1.0, 0.9, 1.1)}
    for _ in range(steps):
        xs = sorted(sorted(tried, key=lambda k: tried[k][1])[:3])
        y = [tried[x][1] for x in xs]
        a2, a1, _ = np.linalg.solve(np.vander(np.asarray(xs), 3), y)
        span = xs[-1] - xs[0]
        if a2 > 0:
            nxt = -a1 / (2 * a2)
        else:
            nxt = xs[0] - span if y[0] < y[-1] else xs[-1] + span
        nxt = float(np.clip(nxt, max(lo, xs[0] - 2 * span), min(hi, xs[-1] + 2 * span)))
        if min(abs(nxt - k) for k in tried) < 0.01:
            break
        tried[nxt] = at(nxt)
    best = min(tried, key=lambda k: tried[k][1])
    return best, tried[best]


class PixelPredictor:
    """The mean frame [ADU] of the model's sources drawn with the PSF of a perturbed design (module notes,
    "Pixels"). Built once per comparison; :meth:`delta` per perturbation. ``None`` from :meth:`build` when the
    scene's PSF is not the optics' grid (a Gaussian or Moffat scene: the model frame holds no optics to perturb).

    The scene's PSF cube (its ``grid_file`` or the cached grid of its design) is kept, and each stamp changed by
    the perturbation's change of the *geometric* spot at the same field point, wavelengths and weights:

        I_p = I_0 + (G_p - G_0),

    G the histogram of the traced rays (same pupil samples for both designs, so their sampling noise largely
    cancels), each centred on its own centroid as the render centres every stamp. Diffraction changes little
    with a perturbation at f/2.4 (the Airy core, 1.6 um at 550 nm, is a fraction of a cell): the difference
    of the geometric spots is the difference of the PSFs. The new grid goes through the render's own path
    (:meth:`scenes.image.gridpsf.GridPSF.from_grid` with the scene's seeing, jitter and distortion, the same
    bilinear blend, pixel integration and detector chain :meth:`detector.Detector.moments`), so the prediction
    differs from the model frame by the perturbation alone.
    """

    def __init__(self, model, design, mi, grid, psf0, n_rays: int = PIXEL_RAYS):
        from scenes.image.gridpsf import recentre

        self.model, self.design, self.mi, self.grid, self.psf0, self.n_rays = model, design, mi, grid, psf0, n_rays
        img = np.clip(np.asarray(grid.images, float), 0.0, None)
        self.base = recentre(img / img.sum(axis=(1, 2), keepdims=True))
        self._nominal = None
        self._reference = None

    @classmethod
    def build(cls, model, scene, design, mi):
        from optics.psf import cached_psf_grid, read_psf_fits
        from scenes.image.gridpsf import GridPSF

        if model is None or scene.psf.model != "optics":
            return None
        psf0 = getattr(model.setup.signal_e, "psf", None)
        if not isinstance(psf0, GridPSF):
            return None
        cfg = scene.psf
        pitch = float(model.sensor.pixel_pitch_um)
        path = cfg.grid_file if cfg.grid_file is not None else cached_psf_grid(design, pitch, int(cfg.grid[0]),
                                                                                int(cfg.grid[1]))
        return cls(model, design, mi, read_psf_fits(path), psf0)

    def spots(self, design) -> np.ndarray:
        """Geometric stamps (K, N, N) of ``design`` at the grid's fields, cells and band, each about its centroid."""
        from optics.sequential import SequentialTracer, pupil_uniform

        g = self.grid
        data = design.model_dump()
        fp = data["focal_plane"]   # a detector that does not cut moved images (as optics.distortion's)
        fp["width_mm"], fp["height_mm"] = 1.5 * fp["width_mm"], 1.5 * fp["height_mm"]
        tracer = SequentialTracer(type(design).model_validate(data), self.mi, obstruct="analytic")
        lam = np.asarray(g.wavelengths_nm, float)
        w = np.asarray(g.weights, float) if g.weights is not None and len(g.weights) else np.ones(lam.size)
        w = w / w.sum()
        n = self.base.shape[-1]
        half = n * float(g.pixel_um) * 5e-4
        fields = np.asarray(g.fields_deg, float).reshape(-1, 2)
        kf = len(fields)
        # the same pupil points for every field, wavelength and design (their sampling noise cancels in the
        # difference); one trace per field and wavelength (the field is opaque: one kernel for all)
        px, py = pupil_uniform(int(self.n_rays), tracer.layout.r_primary, seed=0)
        m = px.size
        us, vs, ws = (np.zeros((kf, m * len(lam))) for _ in range(3))
        for k, f in enumerate(fields):
            for j, (lam_i, w_i) in enumerate(zip(lam, w, strict=True)):
                r = tracer.trace((float(f[0]), float(f[1])), px, py, wavelength_nm=float(lam_i))
                sl = slice(j * m, (j + 1) * m)
                us[k, sl], vs[k, sl] = np.where(r.ok, r.u, 0.0), np.where(r.ok, r.v, 0.0)
                ws[k, sl] = w_i * np.where(r.ok, r.transmission, 0.0) / m
        out = np.zeros((kf, n, n))
        for k in range(kf):
            u, v, ww = us[k], vs[k], ws[k]
            tot = float(ww.sum())
            if not tot > 0:
                raise ValueError(f"no ray of the perturbed design reaches the focal plane at field {tuple(fields[k])} deg")
            cu, cv = float(np.sum(ww * u) / tot), float(np.sum(ww * v) / tot)
            h, _, _ = np.histogram2d(v - cv, u - cu, bins=n, range=[[-half, half], [-half, half]], weights=ww)
            out[k] = h / tot
        return out

    def psf(self, values: dict):
        """The scene's GridPSF with the perturbation ``values`` ([perturbation] names, totals)."""
        from dataclasses import replace

        from optics.design import with_perturbation
        from scenes.image.gridpsf import GridPSF

        if self._nominal is None:
            self._nominal = self.spots(self.design)
        pert = self.spots(with_perturbation(self.design, **values))
        images = np.clip(self.base + pert - self._nominal, 0.0, None)
        p0 = self.psf0
        s = self.model.sensor
        ax = (s.sensor_width_px - 1) / 2.0 - s.roi_x0
        ay = (s.sensor_height_px - 1) / 2.0 - s.roi_y0
        return GridPSF.from_grid(replace(self.grid, images=images), float(s.pixel_pitch_um),
                                 self.design.primary.focal_length_mm, (ax, ay), jitter_px=p0.jitter_px,
                                 seeing_fwhm_px=p0.seeing_fwhm_px, to_ideal=p0.to_ideal)

    def mean(self, psf) -> np.ndarray:
        """The model's mean frame [ADU] with its sources drawn with ``psf``."""
        from dataclasses import replace

        m = self.model
        out, _, _ = m.setup.detector.moments(replace(m.setup.signal_e, psf=psf), m.setup.exptime_s)
        return np.asarray(out, np.float64)

    def score(self, res: Residuals, names, values, refine: bool = False) -> tuple[np.ndarray, float, float]:
        """(mean frame change [ADU], its pixel delta(-2 ln L), scale s) of the perturbation ``s * values``.
        Without ``refine`` s = 1; with it, s maximises the pixel likelihood along ``values`` (s = 0.9, 1, 1.1,
        then the vertex of a parabola through the three best, at most :data:`REFINE_STEPS` times, within
        :data:`SCALE_RANGE`): the moments' aperture cuts the wings of a widened star and their isotropic nuisance
        takes the uniform part of a defocus; the pixels keep all of it."""
        from detector.signatures import Fit, pixel_score

        def at(sc):
            d = self.delta({k: float(v) * sc for k, v in zip(names, values)})
            return d, float(pixel_score(Fit("", {}, 0.0, 0, 0, "", delta_adu=d), res))

        sc, (d, m2l) = scale_search(at) if refine else (1.0, at(1.0))
        return d, m2l, sc

    def delta(self, values: dict) -> np.ndarray:
        """Mean frame change [ADU] (output pixels) of the perturbation ``values`` ([perturbation] names, totals),
        against the design's own perturbation drawn through the same path (zero for no change, exactly)."""
        if self._reference is None:
            self._reference = self.mean(self.psf(self.design.perturbation.model_dump()))
        return (self.mean(self.psf(values)) - self._reference).astype(np.float32)
