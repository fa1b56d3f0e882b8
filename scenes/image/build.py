"""From a scene to source samples and the truth table: stars from the catalogue, objects from their tracks.

Stars (``[sky] stars = true``): :func:`scenes.sky.stars_in_field` gives the stars of a cone around the
pointing (the window's half-diagonal, plus the path of the boresight and the largest stamp), with their
ICRS positions at the epoch; :func:`scenes.sky.star_electron_rate` their photo-electron rates through the
mirrors and the sensor's QE (thesis eqs. 5-9); the file's WCS their pixel positions (``all_world2pix``).
Under sidereal tracking a star is one static sample of ``rate x T`` electrons. Under ``rate`` or ``none``
tracking it trails: its path is sampled in time like an object's.

Objects (``[[objects]]``): :func:`scenes.objects.object_from_table` and :func:`object_track` give the sky
track over ``[0, T + (H - 1) tau]`` (long enough for the last row of a rolling shutter); the track is
carried into the t = 0 frame (:class:`scenes.image.motion.Boresight`), checked against the field
(:func:`scenes.objects.require_in_field`: an object that never enters the window is an error naming
``objects[i]``), and sampled at equal time steps of at most 0.25 pixel of motion. The photo-electron rate
is :meth:`Brightness.photon_rate` through QE x mirror reflectance; a ``photons`` object (photons at the
aperture, no spectrum given) is converted with the band efficiency of a solar spectrum over the QE table's
wavelength range. An object's ``light_curve`` (:mod:`scenes.objects.lightcurve`) multiplies each sample's
electrons by the mean of the curve over the sample's interval, and the samples are then at most
``LightCurve.max_step_s`` apart (so a rolling shutter's row windows see the curve's time structure).

Energy: each sample carries rate x dt of the interval it stands for, so the samples of a source add up to
the electrons it sends during the time its light is recorded; the truth's ``flux_e`` is that total for the
part of the path whose centre lies on the window (see ``docs/scenes.md``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..objects import (
    Track,
    check_pointing_visible,
    in_field,
    light_curve_from_table,
    object_track,
    require_in_field,
)
from ..objects.brightness import solar_photon_irradiance
from ..objects.frames import GroundSite, angle_between_deg, radec_to_unit, unit_to_radec
from ..projection import Sip, axis_crpix, tan_wcs
from ..scene import Scene, SceneError
from ..sky import star_electron_rate, stars_in_field
from .gridpsf import optics_psf
from .motion import (
    Boresight,
    StarPaths,
    sample_times,
    units_to_pixel,
    window_overlap,
    world_to_pixel,
)
from .psf import psf_from_config
from .signal import Samples, SourceSignal, Trails

#: the TRUTH extension: one row per source (positions in 0-based pixels of the written, binned frame); an
#: object's (x0, y0) and (x1, y1) are where it is at t0_s and t1_s [s from the exposure start], the first and
#: last moments it is seen on the frame (NaN for stars)
TRUTH_DTYPE = [("ra_deg", "f8"), ("dec_deg", "f8"), ("x", "f8"), ("y", "f8"), ("x0", "f8"), ("y0", "f8"),
               ("x1", "f8"), ("y1", "f8"), ("flux_e", "f8"), ("kind", "S9"), ("mag", "f8"), ("source_id", "i8"),
               ("name", "S32"), ("t0_s", "f8"), ("t1_s", "f8")]
STEP_PX = 0.25  # largest motion between two samples of a path [pixels]
STAR_STEP_SIGMA = 0.5  # trailed stars: sample spacing up to this many PSF core rms (see trail_step_px)
SEGMENT_STAMPS = 2.0  # motion per trail segment, in stamp widths (2w + 1)
MAX_TRAIL_SAMPLES = 10_000_000  # trailed-star samples per frame (memory: ~100 bytes each while building)
#: time samples a light curve may ask for per object (a 1 ms glint in 100 s would ask for 2e5: each sample
#: still carries the exact mean of the curve over its slice, so fewer samples keep the flux, not the shape)
MAX_CURVE_SAMPLES = 100_000
WAVELENGTH_STEP_NM = 5.0


@dataclass
class SourceModel:
    """The sources of a frame: the detector's signal callable, the truth table and bookkeeping."""

    signal: SourceSignal
    truth: np.ndarray
    counts: dict = field(default_factory=dict)
    cards: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)
    #: the samples of each TRUTH row's source alone, in TRUTH order (:class:`Samples` or :class:`Trails`, or
    #: a callable returning one, built when asked): what the labels render source by source
    per_source: list = field(default_factory=list)
    psf: object = None


@dataclass
class _Frame:
    """Geometry and photometry shared by the stars and the objects of one frame."""

    wcs: object  # unbinned window WCS (SIP included)
    boresight: Boresight
    shape: tuple[int, int]  # unbinned (rows, cols)
    binning: int
    row_time_s: float
    exptime_s: float
    scale_arcsec: float
    psf: object
    wavelength_nm: np.ndarray
    qe: np.ndarray
    mirror: float
    area_m2: float
    linear_wcs: object = None  # the same without SIP (for coarse field tests far from the frame)
    max_shift_px: float = 0.0  # largest SIP displacement over the window (and its margin) [pixels]

    @property
    def t_end_s(self) -> float:
        return self.exptime_s + (self.shape[0] - 1) * self.row_time_s

    @property
    def centre_radec(self) -> tuple[float, float]:
        """Sky position of the window's centre at t = 0 [deg] (the pointing is the optical axis)."""
        h, w = self.shape
        ra, dec = self.wcs.all_pix2world([(w - 1) / 2.0], [(h - 1) / 2.0], 0)
        return float(ra[0]), float(dec[0])

    @property
    def half_diagonal_deg(self) -> float:
        """Largest angle from the window's centre to its corners [deg] (distortion included)."""
        h, w = self.shape
        ra, dec = self.wcs.all_pix2world([-0.5, w - 0.5, -0.5, w - 0.5], [-0.5, -0.5, h - 0.5, h - 0.5], 0)
        c = radec_to_unit(*self.centre_radec)
        return float(np.max(angle_between_deg(radec_to_unit(ra, dec), c)))

    def inside(self, x, y) -> np.ndarray:
        h, w = self.shape
        return (x >= -0.5) & (x < w - 0.5) & (y >= -0.5) & (y < h - 0.5)

    def reaches(self, x, y, w) -> np.ndarray:
        """The stamp of half-width ``w`` around (x, y) touches the window."""
        h, wd = self.shape
        ix, iy = np.rint(x), np.rint(y)
        return (ix + w >= 0) & (ix - w < wd) & (iy + w >= 0) & (iy - w < h)

    def recorded(self, t_lo, t_hi, y) -> np.ndarray:
        """Fraction of each sample interval inside the exposure window of the (continuous) row ``y``."""
        return window_overlap(t_lo, t_hi, y, self.row_time_s, self.exptime_s)

    def output_xy(self, x, y):
        """Unbinned window pixels -> pixels of the written (binned) frame (0-based centres)."""
        b = self.binning
        return (np.asarray(x) - (b - 1) / 2.0) / b, (np.asarray(y) - (b - 1) / 2.0) / b


def band(sensor, step_nm: float = WAVELENGTH_STEP_NM) -> tuple[np.ndarray, np.ndarray]:
    """The sensor's QE on a fine wavelength grid (linear interpolation of its table) [nm], [e-/photon]."""
    lo, hi = float(sensor.qe_wavelength_nm[0]), float(sensor.qe_wavelength_nm[-1])
    lam = np.linspace(lo, hi, round((hi - lo) / step_nm) + 1)
    return lam, sensor.qe_at(lam)


def frame_wcs(scene: Scene, sensor, pixel_scale_arcsec: float, binned: bool = True, distortion: Sip | None = None,
              margin_px: float = 16.0):
    """The frame's WCS: the written (binned) frame, or the unbinned read-out window.

    TAN about the pointing, which is the optical axis at the full sensor's centre (CRPIX moves with the
    window and the binning, :func:`scenes.projection.axis_crpix`), with the handedness of
    ``[telescope] parity``; with ``distortion`` (unbinned sensor
    pixels) the SIP terms in this frame's pixels and the reverse polynomials fitted over it
    (``margin_px`` beyond its edges, in its own pixels).
    """
    b = sensor.binning if binned else 1
    shape = sensor.output_shape if binned else sensor.shape
    p = scene.pointing
    sip = distortion.binned(b) if distortion is not None else None
    return tan_wcs(p.ra_deg, p.dec_deg, p.roll_deg, pixel_scale_arcsec * b, shape, crpix=axis_crpix(sensor, binned),
                   sip=sip, margin_px=margin_px, parity=scene.telescope.parity)


def _path_truth(fr: _Frame, x, y, t_lo, t_hi, e):
    """Recorded interval, flux and in-window mask of paths sampled on a time grid; arrays (S, m)."""
    rec = fr.recorded(t_lo, t_hi, y)
    inside = fr.inside(x, y) & (rec > 0)
    t0 = y * fr.row_time_s
    t_a = np.where(inside, np.maximum(t_lo, t0), np.inf).min(axis=0)
    t_b = np.where(inside, np.minimum(t_hi, t0 + fr.exptime_s), -np.inf).max(axis=0)
    flux = np.sum(np.where(inside, e * rec, 0.0), axis=0)
    return t_a, t_b, flux, inside.any(axis=0)


def trail_step_px(psf) -> float:
    """Sample spacing of trailed stars [px]: max(STEP_PX, STAR_STEP_SIGMA x sigma), sigma = FWHM / 2.3548.

    A chain of PSF samples at spacing h equals the continuous path integral of the pixel-integrated PSF up
    to a ripple of the amplitude of the PSF's Fourier transform at 1/h (Poisson summation): for a Gaussian
    exp(-2 pi^2 sigma^2 / h^2) = exp(-8 pi^2) ~ 1e-34 at h = sigma / 2; for a Moffat ~exp(-2 pi alpha / h),
    ~1e-16 at beta = 4.765 (alpha = 2.98 sigma).
    What remains is the midpoint rule at the ends of the path and of each row's exposure window: at most
    a box of h on the light of one interval, variance h^2 / 12 = sigma^2 / 48 (2 % of the PSF's variance).
    Objects keep STEP_PX (few samples, streak photometry). A PSF without ``describe()["fwhm_px"]``: STEP_PX.
    """
    fwhm = (psf.describe() if hasattr(psf, "describe") else {}).get("fwhm_px")
    if not fwhm or not np.isfinite(fwhm):
        return STEP_PX
    return max(STEP_PX, STAR_STEP_SIGMA * float(fwhm) / (2.0 * math.sqrt(2.0 * math.log(2.0))))


def trail_radius(psf, total_e, length_px) -> np.ndarray:
    """Stamp half-width [px] for a path of ``length_px`` pixels carrying ``total_e`` electrons.

    The tail criterion of the PSF (light lost outside the stamps <= max(0.5 e-, 1e-9 of the flux)) applied
    to the light of one stamp-length of the path, F (2 w_min + 1) / L: what a pixel of a streak sees.
    """
    w_min = int(np.max(psf.radius_px(np.array([1e-30]))))
    frac = np.minimum(1.0, (2 * w_min + 1) / np.maximum(np.asarray(length_px, dtype=float), 1e-9))
    return psf.radius_px(np.asarray(total_e, dtype=float) * frac)


# ------------------------------------------------------------------------------------------------- stars
def _stars(scene: Scene, fr: _Frame, base_dir: Path | None) -> tuple[Samples | Trails, list, dict]:
    sky = scene.sky
    w_guess = int(fr.psf.radius_px(1e12).max()) if hasattr(fr.psf, "radius_px") else 64
    radius = fr.half_diagonal_deg + fr.boresight.speed_deg_s * fr.t_end_s + (w_guess + 2) * fr.scale_arcsec / 3600
    ra_c, dec_c = fr.centre_radec
    stars = stars_in_field(ra_c, dec_c, min(radius, 30.0), sky.star_mag_limit, scene.pointing.epoch,
                           catalog=sky.catalog, seed=sky.star_seed)
    synthetic = stars.source == "synthetic"
    counts = {"catalog": int(np.sum(~synthetic)), "synthetic": int(np.sum(synthetic))}
    if len(stars.ra_deg) == 0:
        return Samples.empty(), [], counts, []
    rate = np.atleast_1d(star_electron_rate(stars.mag_g, stars.teff_k, fr.wavelength_nm, fr.qe, fr.area_m2,
                                            optics_throughput=fr.mirror))
    total = rate * fr.exptime_s
    w = fr.psf.radius_px(total)
    kinds = np.where(stars.source == "synthetic", "synthetic", "star")
    if not fr.boresight.moving:
        x, y = world_to_pixel(fr.wcs, stars.ra_deg, stars.dec_deg)
        keep = fr.reaches(x, y, w) & (total > 0)
        inf = np.full(int(keep.sum()), np.inf)
        samples = Samples(x[keep], y[keep], total[keep], -inf, inf, w[keep])
        ins = keep & fr.inside(x, y)
        X, Y = fr.output_xy(x[ins], y[ins])
        rows = [{"ra_deg": stars.ra_deg[ins], "dec_deg": stars.dec_deg[ins], "x": X, "y": Y, "x0": X, "y0": Y,
                 "x1": X, "y1": Y, "flux_e": total[ins], "kind": kinds[ins], "mag": stars.mag_g[ins],
                 "source_id": stars.source_id[ins], "name": np.full(int(ins.sum()), "")}]
        one = np.flatnonzero(ins)
        per = [Samples(x[i:i + 1], y[i:i + 1], total[i:i + 1], -inf[:1], inf[:1], np.asarray(w)[i:i + 1]) for i in one]
        return samples, rows, counts, per
    # trailed stars: paths in the t = 0 frame, sampled in time

    u = radec_to_unit(stars.ra_deg, stars.dec_deg)
    speed = fr.boresight.speed_deg_s * 3600.0 / fr.scale_arcsec
    paths = StarPaths.from_units(fr.wcs, fr.boresight, u, fr.t_end_s, speed)
    xk, yk = paths.on_grid(paths.t_knots)  # (K, m)
    h, wd = fr.shape
    near = (xk.min(axis=0) - w <= wd) & (xk.max(axis=0) + w >= -1) & (yk.min(axis=0) - w <= h) & (
        yk.max(axis=0) + w >= -1)
    near &= total > 0
    idx = np.flatnonzero(near)
    vk = np.hypot(paths.spline_x(paths.t_knots, 1)[:, idx], paths.spline_y(paths.t_knots, 1)[:, idx])
    vmax = float(vk.max()) * 1.01 if idx.size else speed
    w = np.array(w)
    w[idx] = trail_radius(fr.psf, total[idx], vk.mean(axis=0) * fr.exptime_s)
    step = trail_step_px(fr.psf)
    ts, dt = sample_times(fr.t_end_s, vmax, step)
    if ts.size * idx.size > MAX_TRAIL_SAMPLES:
        raise SceneError(f"the trailed stars need {ts.size * idx.size:.3g} samples ({idx.size} stars x {ts.size} time "
                         f"steps of {step:.3g} pixel)", key="sky.star_mag_limit", file=scene.source,
                         expected=f"fewer than {MAX_TRAIL_SAMPLES:.0e}: a brighter star_mag_limit, a smaller window, a "
                         "shorter exposure or tracking = 'sidereal'")
    X, Y = paths.subset_on_grid(idx, ts)  # (S, n)
    t_lo, t_hi = (ts - dt / 2)[:, None], (ts + dt / 2)[:, None]
    E = np.broadcast_to(rate[idx][None, :] * dt, X.shape)
    t_a, t_b, flux, seen = _path_truth(fr, X, Y, t_lo, t_hi, E)
    ww = np.broadcast_to(w[idx][None, :], X.shape)
    keep = fr.reaches(X, Y, ww)
    if fr.row_time_s > 0:  # drop samples outside every window their stamp rows see
        keep &= (t_hi > (Y - ww) * fr.row_time_s) & (t_lo < (Y + ww) * fr.row_time_s + fr.exptime_s)
    tl, th = np.broadcast_to(t_lo, X.shape), np.broadcast_to(t_hi, X.shape)
    per_seg = np.maximum(1, np.floor(SEGMENT_STAMPS * (2 * w[idx] + 1) / max(vmax * dt, 1e-9))).astype(np.int64)
    key = np.arange(idx.size)[None, :] + idx.size * (np.arange(ts.size)[:, None] // per_seg[None, :])
    kt = keep.T  # star-major: each star's samples contiguous, so the grouping by segment gathers locally
    cols = [a.T[kt] for a in (X, Y, E, tl, th, ww, key)]
    trails = Trails.from_samples(*cols)
    ends = np.r_[0, np.cumsum(kt.sum(axis=1))]  # star k's samples: ends[k]:ends[k + 1] (star-major order)

    def one_star(k, cols=cols, ends=ends):
        return lambda: Trails.from_samples(*(c[ends[k]:ends[k + 1]] for c in cols))

    per = [one_star(k) for k in np.flatnonzero(seen)]
    j = idx[seen]
    xa, ya = paths.each_of(j, t_a[seen])
    xb, yb = paths.each_of(j, t_b[seen])
    xm, ym = paths.each_of(j, 0.5 * (t_a[seen] + t_b[seen]))
    (X0, Y0), (X1, Y1), (XM, YM) = fr.output_xy(xa, ya), fr.output_xy(xb, yb), fr.output_xy(xm, ym)
    rows = [{"ra_deg": stars.ra_deg[j], "dec_deg": stars.dec_deg[j], "x": XM, "y": YM, "x0": X0, "y0": Y0,
             "x1": X1, "y1": Y1, "flux_e": flux[seen], "kind": kinds[j], "mag": stars.mag_g[j],
             "source_id": stars.source_id[j], "name": np.full(j.size, "")}]
    return trails, rows, counts, per


# ----------------------------------------------------------------------------------------------- objects
def _photons_efficiency(fr: _Frame) -> float:
    """Photo-electrons per photon at the aperture for a solar spectrum over the QE table's range."""
    lam = fr.wavelength_nm
    return solar_photon_irradiance(lam, fr.qe * fr.mirror) / solar_photon_irradiance(lam, np.ones_like(lam))


def _objects(scene: Scene, fr: _Frame, base_dir: Path | None, observer) -> tuple[Trails, list, list]:
    parts, rows, per = [], [], []
    file = scene.source
    h, wd = fr.shape
    thr = fr.qe * fr.mirror  # photons -> photo-electrons
    for i, (table, obj) in enumerate(zip(scene.objects, scene.parts.objects)):  # parsed once, at loading
        track = object_track(obj, scene.pointing.epoch, fr.exptime_s, observer, t_end_s=fr.t_end_s, file=file)
        rate = obj.brightness.photon_rate(track, aperture_area_m2=fr.area_m2, wavelength_nm=fr.wavelength_nm,
                                          throughput=thr)
        if obj.brightness.kind == "photons":  # photons at the aperture: no band applied by photon_rate
            rate = rate * _photons_efficiency(fr)
        rate = np.asarray(rate, dtype=float)  # e-/s at the track samples
        mean_total = float(np.mean(rate)) * fr.exptime_s
        # the track in the t = 0 frame: the field test and the pixel path
        u0 = fr.boresight.to_initial_frame(track.unit_vector(track.t_s), track.t_s)
        d_ra, d_dec = unit_to_radec(u0)
        derot = Track(track.t_s, d_ra, d_dec, track.frame, track.exposure_time_s, track.epoch_isot, key=track.key)
        length_px = float(np.sum(angle_between_deg(u0[:-1], u0[1:]))) * 3600.0 / fr.scale_arcsec * (
            fr.exptime_s / fr.t_end_s)
        w = int(np.max(trail_radius(fr.psf, np.array([max(mean_total, 1e-30)]), length_px)))
        field, margin = fr.linear_wcs or fr.wcs, float(w) + fr.max_shift_px
        if table.get("outside") == "skip" and not in_field(derot, field, shape=(h, wd), margin_px=margin):
            continue  # a sequence frame after the object left the field: rendered without it
        require_in_field(derot, field, i, shape=(h, wd), margin_px=margin, file=file)

        def xy(t, track=track):
            t = np.atleast_1d(np.asarray(t, dtype=float))
            return units_to_pixel(fr.wcs, fr.boresight, track.unit_vector(t), t)

        t_start, t_stop = _near_interval(derot, fr, w)
        curve = light_curve_from_table(table.get("light_curve"), f"objects[{i}].light_curve", file=file)
        n_min = 8 if curve is None else min(MAX_CURVE_SAMPLES, max(8, math.ceil((t_stop - t_start) / curve.max_step_s())))
        # sample at <= STEP_PX of motion, refined until the largest step obeys it
        tc = np.linspace(t_start, t_stop, 257)
        xc, yc = xy(tc)
        speed = float(np.max(np.hypot(np.diff(xc), np.diff(yc)))) / max(tc[1] - tc[0], 1e-30) * 1.05
        for _ in range(12):
            n = max(n_min, math.ceil(speed * (t_stop - t_start) / STEP_PX))
            dt = (t_stop - t_start) / n
            ts = t_start + (np.arange(n) + 0.5) * dt
            x, y = xy(ts)
            step = float(np.max(np.hypot(np.diff(x), np.diff(y)), initial=0.0))
            if step <= STEP_PX:
                break
            speed *= 1.1 * step / STEP_PX
        e = track.interp(rate, ts) * dt
        t_lo, t_hi = ts - dt / 2, ts + dt / 2
        if curve is not None:  # the light of each interval: rate x the interval mean of the light curve
            e = e * curve.interval_mean(t_lo, t_hi)
        t_a, t_b, flux, seen = (v[0] if np.ndim(v) else v for v in
                                _path_truth(fr, x[:, None], y[:, None], t_lo[:, None], t_hi[:, None], e[:, None]))
        keep = fr.reaches(x, y, w)
        if fr.row_time_s > 0:
            keep &= (t_hi > (y - w) * fr.row_time_s) & (t_lo < (y + w) * fr.row_time_s + fr.exptime_s)
        per_seg = max(1, int(SEGMENT_STAMPS * (2 * w + 1) / max(step, 1e-9)))
        key = np.arange(ts.size) // per_seg
        parts.append(Trails.from_samples(x[keep], y[keep], e[keep], t_lo[keep], t_hi[keep], np.full(int(keep.sum()), w),
                                         key[keep]))
        per.append(parts[-1])
        if not seen:  # only the PSF wings reach the window
            t_a, t_b = t_start, t_stop
        tm = 0.5 * (t_a + t_b)
        (xa, xm, xb), (ya, ym, yb) = xy(np.array([t_a, tm, t_b]))
        X, Y = fr.output_xy(np.array([xa, xm, xb]), np.array([ya, ym, yb]))
        ra_m, dec_m = track.radec(np.array([tm]))
        if obj.brightness.kind == "photons":
            mag = math.nan
        else:  # the given mag (its own system), or the size model's V magnitude at the nearest track sample
            mag = float(obj.brightness.magnitude(track)[np.argmin(np.abs(track.t_s - tm))])
        rows.append({"ra_deg": ra_m, "dec_deg": dec_m, "x": X[1:2], "y": Y[1:2], "x0": X[0:1], "y0": Y[0:1],
                     "x1": X[2:3], "y1": Y[2:3], "flux_e": np.array([flux]), "kind": np.array(["object"]),
                     "mag": np.array([mag]), "source_id": np.array([i]), "name": np.array([obj.name or obj.key]),
                     "t0_s": np.array([t_a]), "t1_s": np.array([t_b])})
    return Trails.concat(parts), rows, per


def _near_interval(derot, fr: _Frame, w: int) -> tuple[float, float]:
    """The part of [0, T_end] during which the object is within reach of the window (coarse, padded)."""
    u = radec_to_unit(derot.ra_deg, derot.dec_deg)
    path = float(np.sum(angle_between_deg(u[:-1], u[1:])))
    reach_deg = fr.half_diagonal_deg + (w + 2) * fr.scale_arcsec / 3600.0
    n = int(min(200001, max(257, math.ceil(path / (reach_deg / 16.0)) + 1)))
    tc = np.linspace(0.0, fr.t_end_s, n)
    uc = derot.unit_vector(tc)
    ang = angle_between_deg(uc, radec_to_unit(*fr.centre_radec))
    near = np.flatnonzero(ang <= reach_deg * 1.05 + 1e-9)
    if near.size == 0:
        return 0.0, fr.t_end_s
    return float(tc[max(near[0] - 1, 0)]), float(tc[min(near[-1] + 1, n - 1)])


# ------------------------------------------------------------------------------------------------ driver
def _truth_table(rows: list) -> np.ndarray:
    n = sum(len(r["x"]) for r in rows)
    out = np.zeros(n, dtype=TRUTH_DTYPE)
    k = 0
    for r in rows:
        m = len(r["x"])
        for name in out.dtype.names:
            v = np.asarray(r.get(name, np.nan))
            if out.dtype[name].kind == "S":
                v = np.char.encode(v.astype(str), "ascii", "replace")
            out[name][k:k + m] = v
        k += m
    return out


def build_sources(scene: Scene, sensor, design, pixel_scale_arcsec: float, exptime_s: float, *,
                  background_e: float = 0.0, psf=None, distortion: Sip | None = None, extra=None) -> SourceModel:
    """Stars and objects of ``scene`` as the detector chain's signal callable, plus the TRUTH table.

    Parameters
    ----------
    scene : the validated scene
    sensor : its :class:`detector.SensorConfig`
    design : its optics design (``collecting_area_m2``, ``mirror_throughput``)
    pixel_scale_arcsec : unbinned plate scale [arcsec/pixel]
    exptime_s : exposure time T [s] (0 or a dark/bias frame: no sources)
    background_e : uniform expected signal (sky, flat screen) [e-/pixel]
    psf : a pixel-integrated PSF (the hook of ``scenes.image.psf``); default from the scene's ``[psf]``
        (``model = "optics"``: :func:`scenes.image.gridpsf.optics_psf`)
    distortion : the frame's SIP (:class:`scenes.projection.Sip`, unbinned sensor pixels), or None
    extra : an additional smooth signal ``extra(y0, y1, x0, x1)`` [e-/pixel] (straylight)

    Returns
    -------
    SourceModel
    """
    scene.parts  # noqa: B018  (a scene built in code is checked here: its short forms resolved, tables typed)
    cfg = scene.psf
    if psf is None and cfg.model == "optics":
        psf = optics_psf(scene, sensor, design, pixel_scale_arcsec, distortion)
    elif psf is None:
        psf = psf_from_config(cfg.model, cfg.fwhm_arcsec, cfg.beta, cfg.jitter_rms_arcsec, pixel_scale_arcsec)
    exp = scene.exposure
    bore = Boresight(scene.pointing.ra_deg, scene.pointing.dec_deg, exp.tracking, exp.rate_ra_deg_s,
                     exp.rate_dec_deg_s)
    lam, qe = band(sensor)
    w_max = int(np.max(psf.radius_px(np.array([1e12])))) if hasattr(psf, "radius_px") else 64
    wcs = frame_wcs(scene, sensor, pixel_scale_arcsec, binned=False, distortion=distortion, margin_px=w_max + 16.0)
    linear, shift = None, 0.0
    if distortion is not None:
        linear = frame_wcs(scene, sensor, pixel_scale_arcsec, binned=False)
        (h, wd), (cx, cy) = sensor.shape, axis_crpix(sensor, binned=False)
        shift = distortion.max_shift_px((-0.5 - cx + 1, wd - 0.5 - cx + 1), (-0.5 - cy + 1, h - 0.5 - cy + 1))
    fr = _Frame(wcs, bore, sensor.shape, sensor.binning, sensor.row_time_s, float(exptime_s), pixel_scale_arcsec, psf,
                lam, qe, design.mirror_throughput, design.collecting_area_m2, linear, shift)
    base_dir = Path(scene.source).parent if scene.source and scene.source != "<built-in>" else None
    parts, trails, rows, per = [], [], [], []
    counts = {"catalog": 0, "synthetic": 0, "objects": 0}
    light = exp.frame == "light" and scene.sky.flat_e_per_s is None
    if light and (scene.objects or scene.sky.stars):
        observer = scene.parts.observer
        if isinstance(observer, GroundSite):
            check_pointing_visible(bore.ra_deg, bore.dec_deg, scene.pointing.epoch, exptime_s, observer,
                                   file=scene.source)
        if scene.objects:
            t, r, p = _objects(scene, fr, base_dir, observer)
            trails.append(t)
            rows += r
            per += p
            counts["objects"] = len(scene.objects)
        if scene.sky.stars and exptime_s > 0:
            s, r, c, p = _stars(scene, fr, base_dir)
            (trails if isinstance(s, Trails) else parts).append(s)
            rows += r
            per += p
            counts.update(c)
    samples = Samples.concat(parts)
    truth = _truth_table(rows)
    kinds = truth["kind"]
    counts["stars_in_frame"] = int(np.sum(kinds != b"object"))
    desc = psf.describe() if hasattr(psf, "describe") else {"model": type(psf).__name__}
    signal = SourceSignal(samples, psf, float(background_e), sensor.roi_y0, sensor.roi_x0, sensor.row_time_s,
                          float(exptime_s), meta={"psf": desc, "counts": counts}, trails=Trails.concat(trails),
                          extra=extra)
    counts["samples"] = signal.n_samples
    cards = {
        "NOBJECTS": (counts["objects"], "debris/satellite objects in the scene"),
        "NSTARS": (counts["stars_in_frame"], "stars with their centre on the frame (TRUTH)"),
        "NSTARCAT": (counts["catalog"], "catalogue stars in the queried cone"),
        "NSTARSYN": (counts["synthetic"], "synthetic (model) stars in the queried cone"),
        "NSAMPLES": (counts["samples"], "PSF samples rendered (stars + streak points)"),
        "TRACKING": (exp.tracking, "sidereal, rate or none (parked)"),
        "PSFMODEL": (str(desc.get("model")), "point-spread function"),
        "PSFFWHM": (float(desc.get("fwhm_px", math.nan)) * pixel_scale_arcsec, "[arcsec] PSF FWHM"),
        "PSFJITTR": (float(desc.get("jitter_px", 0.0)) * pixel_scale_arcsec, "[arcsec] rms jitter per axis"),
    }
    if desc.get("model") == "moffat":
        cards["PSFBETA"] = (float(desc["beta"]), "Moffat beta")
    if exp.tracking == "rate":
        cards["TRKRA"] = (exp.rate_ra_deg_s, "[deg/s] tracking rate dRA/dt cos(Dec)")
        cards["TRKDEC"] = (exp.rate_dec_deg_s, "[deg/s] tracking rate dDec/dt")
    if scene.sky.stars:
        cards["STARLIM"] = (scene.sky.star_mag_limit, "[mag] faintest Gaia G rendered")
        cards["STARSEED"] = (scene.sky.star_seed, "seed of the synthetic faint stars")
        cards["CATALOG"] = (Path(scene.sky.catalog).name[:60], "star catalogue")
    return SourceModel(signal, truth, counts, cards, per_source=per, psf=psf)
