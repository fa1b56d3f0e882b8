"""Apparent sky tracks of debris and satellites during an exposure (thesis sec. 3.4.2).

Two kinds of object:

* :class:`RateObject`, given by its position and on-sky rates at the exposure start (the scene contract's
  ``ra_deg``, ``dec_deg``, ``rate_ra_deg_s``, ``rate_dec_deg_s``). ``rate_ra_deg_s`` is the rate along the
  east direction on the sky, d(RA)/dt x cos(Dec), as the rates of astronomical rate tracking and of
  satellite astrometry are quoted (so the speed on the sky is the hypot of the two rates). The object
  moves at a constant angular speed along the great circle tangent to those rates; after ``t`` seconds it
  is ``hypot(rate_ra, rate_dec) * t`` degrees away (d(RA)/dt = rate_ra / cos(Dec) at the start). Its
  coordinates are taken in the frame of the scene's WCS (the star catalogue's ICRS), no correction added.
* :class:`TleObject`, propagated with SGP4 (TEME) and seen by an observer: a ground site (geodetic
  latitude, longitude, height), a spacecraft given by its own TLE, or the geocentre (``observer=None``).

Frames of a TLE object's track (``frame``), all with GCRS (= ICRS-aligned) axes, observer-centric:

``"geometric"``
    Direction of the object at the sample time from the observer at the same time. No light-time, no
    aberration.
``"apparent"``
    What the observer sees: the object at the retarded time t - tau with tau = |r_obj(t - tau) -
    r_obs(t)| / c (iterated in the GCRS, a local inertial frame, three iterations: converged to < 1 ns),
    then stellar aberration by the observer's velocity relative to the geocentre (diurnal, <= 0.32"; or
    orbital, ~5" for a LEO spacecraft). This is the frame of astropy's ``GCRS(obsgeoloc, obsgeovel)``.
    Light-time moves a LEO object by v_perp tau / R = v_perp / c, i.e. ~5" at 7.5 km/s, whatever its
    range.
``"astrometric"`` (default)
    The position in the star catalogue's frame: the light-time-corrected direction with the Earth's
    annual aberration taken back out, u = aberrate(u_lt, -V_earth). Stars reach the observer aberrated by
    V_earth + v_obs, the object (which moves with the Earth) only by v_obs: relative to the stars an Earth
    satellite is displaced by up to 20.5" (annual aberration, V_earth / c), while the observer's own
    velocity shifts stars and object alike. Place these positions with the same ICRS WCS as catalogue
    stars: it is what a plate solution against a star catalogue measures for the object.

Not modelled: atmospheric refraction (common to stars and objects in the field; the horizon test uses
the geometric elevation), the Sun's light deflection of the background stars (< 0.02" at > 30 deg from the
Sun), the geodesic precession between GCRS and ICRS axes (~1.9"/century), and the ~1e-9 second-order
difference between composing the two aberrations and one aberration with the summed velocity. SGP4's
own error (~1 km at epoch, growing ~1-3 km/day for LEO; Vallado et al. 2006) dominates all of these.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import CubicSpline

from .brightness import Brightness, sunlit_fraction
from .errors import ObjectError
from .frames import (
    AU_KM,
    C_KM_S,
    R_EARTH_KM,
    GroundSite,
    SpaceObserver,
    aberrate,
    angle_between_deg,
    apply,
    as_time,
    earth_barycentric_velocity_km_s,
    east_north,
    itrs_to_gcrs,
    offline_iers,
    radec_to_unit,
    sun_geocentric_km,
    teme_to_gcrs,
    unit_to_radec,
)
from .tle import Tle, propagate_teme

FRAMES = ("astrometric", "apparent", "geometric")
MIN_RAY_ALTITUDE_KM = 100.0  # a line of sight from a spacecraft passing lower than this is blocked by the Earth
MAX_AUTO_SAMPLES = 2001


@dataclass(frozen=True)
class RateObject:
    """An object given by RA/Dec [deg] and on-sky rates [deg/s] at the exposure start.

    ``rate_ra_deg_s`` = d(RA)/dt x cos(Dec) (east rate on the sky), ``rate_dec_deg_s`` = d(Dec)/dt.
    """

    ra_deg: float
    dec_deg: float
    rate_ra_deg_s: float = 0.0
    rate_dec_deg_s: float = 0.0
    brightness: Brightness = field(default_factory=Brightness)
    key: str = "objects[0]"
    name: str | None = None


@dataclass(frozen=True)
class TleObject:
    """An object given by a two-line element set, propagated with SGP4."""

    tle: Tle
    brightness: Brightness = field(default_factory=Brightness)
    key: str = "objects[0]"
    name: str | None = None


SpaceObject = RateObject | TleObject


@dataclass
class Track:
    """An object's sampled sky track during an exposure, with a cubic-spline interpolator.

    Arrays have one value per sample time ``t_s`` [s from the exposure start]. Quantities an object of its
    kind does not have are None (e.g. ``range_km`` of a RA/Dec + rate object given without ``range_km``).

    Attributes
    ----------
    t_s, ra_deg, dec_deg : sample times [s]; position [deg] in ``frame`` (GCRS/ICRS axes)
    frame : ``"astrometric"``, ``"apparent"``, ``"geometric"`` or ``"catalog"`` (RA/Dec + rate objects)
    exposure_time_s : the exposure [s]; the samples span [0, t_s[-1]] with t_s[-1] >= exposure_time_s
    epoch_isot : exposure start (UTC, ISO)
    range_km : observer-object distance [km]
    phase_angle_deg : Sun-object-observer angle [deg]
    sun_distance_au : object-Sun distance [au]
    sunlit_fraction : fraction of the solar disc not hidden by the Earth (1 = fully lit)
    elevation_deg, azimuth_deg : geometric elevation and azimuth (north through east) at a ground site
    object_gcrs_km, observer_gcrs_km : geocentric GCRS positions (object at the retarded time) (N, 3)
    sun_dir, observer_dir : unit vectors from the object to the Sun and to the observer (N, 3)
    """

    t_s: np.ndarray
    ra_deg: np.ndarray
    dec_deg: np.ndarray
    frame: str
    exposure_time_s: float
    epoch_isot: str
    range_km: np.ndarray | None = None
    phase_angle_deg: np.ndarray | None = None
    sun_distance_au: np.ndarray | None = None
    sunlit_fraction: np.ndarray | None = None
    elevation_deg: np.ndarray | None = None
    azimuth_deg: np.ndarray | None = None
    object_gcrs_km: np.ndarray | None = None
    observer_gcrs_km: np.ndarray | None = None
    sun_dir: np.ndarray | None = None
    observer_dir: np.ndarray | None = None
    key: str = "objects[0]"
    _spline: CubicSpline = field(init=False, repr=False)
    _range_spline: CubicSpline | None = field(init=False, repr=False, default=None)

    def __post_init__(self):
        if self.sunlit_fraction is None:
            self.sunlit_fraction = np.ones_like(self.t_s)
        # interpolate unit vectors, not angles: no wrap at RA 0/360, no trouble at the poles
        self._spline = CubicSpline(self.t_s, radec_to_unit(self.ra_deg, self.dec_deg), axis=0)
        if self.range_km is not None:
            self._range_spline = CubicSpline(self.t_s, self.range_km)

    def _times(self, t_s) -> np.ndarray:
        t = np.asarray(t_s, dtype=float)
        tol = 1e-9 * max(1.0, self.t_s[-1])
        if np.any(t < self.t_s[0] - tol) or np.any(t > self.t_s[-1] + tol):
            raise ValueError(f"{self.key}: times outside the sampled span [{self.t_s[0]}, {self.t_s[-1]}] s "
                             "(sample a longer span with object_track(..., t_end_s=...))")
        return np.clip(t, self.t_s[0], self.t_s[-1])

    def unit_vector(self, t_s) -> np.ndarray:
        """Unit direction vectors (..., 3) at times ``t_s`` [s] (cubic spline through the samples)."""
        s = self._spline(self._times(t_s))
        return s / np.linalg.norm(s, axis=-1, keepdims=True)

    def radec(self, t_s) -> tuple[np.ndarray, np.ndarray]:
        """RA and Dec [deg] at times ``t_s`` [s] (cubic spline; thesis sec. 3.4.2)."""
        return unit_to_radec(self.unit_vector(t_s))

    def rates_deg_s(self, t_s) -> tuple[np.ndarray, np.ndarray]:
        """On-sky rates [deg/s] at ``t_s``: d(RA)/dt cos(Dec) (east) and d(Dec)/dt (north)."""
        t = self._times(t_s)
        s, ds = self._spline(t), self._spline(t, 1)
        norm = np.linalg.norm(s, axis=-1, keepdims=True)
        uvec = s / norm
        du = (ds - np.sum(uvec * ds, axis=-1, keepdims=True) * uvec) / norm
        east, north = east_north(uvec)
        return np.degrees(np.sum(du * east, axis=-1)), np.degrees(np.sum(du * north, axis=-1))

    def speed_deg_s(self, t_s) -> np.ndarray:
        """Angular speed on the sky [deg/s] at ``t_s``."""
        return np.hypot(*self.rates_deg_s(t_s))

    def range_at(self, t_s) -> np.ndarray | None:
        """Range [km] at ``t_s`` (cubic spline), or None when unknown."""
        if self._range_spline is None:
            return None if self.range_km is None else np.full(np.shape(t_s), float(self.range_km[0]))
        return self._range_spline(self._times(t_s))

    def interp(self, values, t_s) -> np.ndarray:
        """Linear interpolation of any per-sample quantity (e.g. a photon rate) to ``t_s``."""
        return np.interp(self._times(t_s), self.t_s, np.asarray(values, dtype=float))

    def summary(self) -> dict:
        """A JSON-ready record of the track (for the FITS truth table / the resolved scene)."""
        out = {"key": self.key, "frame": self.frame, "epoch": self.epoch_isot,
               "exposure_time_s": self.exposure_time_s,
               "ra_deg": [float(self.ra_deg[0]), float(self.ra_deg[-1])],
               "dec_deg": [float(self.dec_deg[0]), float(self.dec_deg[-1])],
               "speed_deg_s": float(np.median(self.speed_deg_s(self.t_s)))}
        for name in ("range_km", "phase_angle_deg", "elevation_deg"):
            v = getattr(self, name)
            if v is not None:
                out[name] = [float(v[0]), float(v[-1])]
        return out


# -------------------------------------------------------------------------------------------- building
def _sample_times(exposure_time_s, n_samples, t_end_s, key) -> np.ndarray:
    if not (isinstance(exposure_time_s, (int, float)) and math.isfinite(exposure_time_s) and exposure_time_s > 0):
        raise ObjectError(f"exposure time {exposure_time_s!r} s for the track of {key}", key="exposure.time_s",
                          expected="an exposure time > 0 s for a frame with moving objects")
    t_end = float(exposure_time_s if t_end_s is None else t_end_s)
    if not t_end >= exposure_time_s:
        raise ValueError(f"t_end_s = {t_end_s} must be >= the exposure time {exposure_time_s}")
    if n_samples is None:
        n_samples = min(MAX_AUTO_SAMPLES, max(9, math.ceil(t_end) + 1))
    if int(n_samples) < 4:
        raise ValueError(f"n_samples = {n_samples}: at least 4 samples are needed for the cubic spline")
    return np.linspace(0.0, t_end, int(n_samples))


def _rate_track(obj: RateObject, t0, ts, observer, exposure_time_s, file) -> Track:
    p0 = radec_to_unit(obj.ra_deg, obj.dec_deg)
    east, north = east_north(p0)
    w = obj.rate_ra_deg_s * east + obj.rate_dec_deg_s * north  # deg/s, tangent to the sky at p0
    omega = np.radians(np.linalg.norm(w))
    d = w / np.linalg.norm(w) if omega > 0 else east
    u = np.cos(omega * ts)[:, None] * p0 + np.sin(omega * ts)[:, None] * d
    ra, dec = unit_to_radec(u)
    b = obj.brightness
    const = (lambda v: None if v is None else np.full(ts.shape, float(v)))
    track = Track(ts, ra, dec, "catalog", float(exposure_time_s), t0.isot, range_km=const(b.range_km),
                  phase_angle_deg=const(b.phase_angle_deg),
                  sun_distance_au=const(b.sun_distance_au) if b.phase_angle_deg is not None else None, key=obj.key)
    if isinstance(observer, GroundSite):
        t = t0 + _seconds(ts)
        track.elevation_deg, track.azimuth_deg = observer.altaz_deg(u, itrs_to_gcrs(t))
        _check_elevation(track, observer, obj.key, file)
    elif isinstance(observer, SpaceObserver):
        t = t0 + _seconds(ts)
        r_obs, _ = observer.posvel_gcrs(t)
        _check_earth_blocking(r_obs, u * 1e9, ts, obj.key, observer, file)  # a direction: a ray to "infinity"
    return track


def _seconds(ts):
    import astropy.units as u

    return np.asarray(ts) * u.s


def _check_elevation(track: Track, site: GroundSite, key: str, file):
    el = track.elevation_deg
    if np.any(el < 0):
        k = int(np.argmin(el))
        raise ObjectError(f"below the horizon of site {site.name!r} (lat {site.lat_deg:g}, lon {site.lon_deg:g}) "
                          f"during the exposure: elevation {el[0]:.2f} deg at the start, {el[-1]:.2f} deg at the "
                          f"end, minimum {el[k]:.2f} deg at t = {track.t_s[k]:.2f} s", key=key, file=file,
                          expected="an object above the horizon (elevation >= 0 deg) for the whole exposure")


def _check_earth_blocking(r_obs, rel, ts, key, observer, file):
    rel2 = np.sum(rel * rel, axis=-1)
    s = np.clip(-np.sum(r_obs * rel, axis=-1) / rel2, 0.0, 1.0)
    closest = np.linalg.norm(r_obs + s[:, None] * rel, axis=-1) - R_EARTH_KM
    if np.any(closest < MIN_RAY_ALTITUDE_KM):
        k = int(np.argmin(closest))
        where = (f"passes only {closest[k]:.0f} km above the surface" if closest[k] >= 0
                 else "passes through the Earth")
        raise ObjectError(f"hidden by the Earth as seen from {observer.name!r}: the line of sight {where} "
                          f"at t = {ts[k]:.2f} s", key=key, file=file,
                          expected=f"a line of sight passing more than {MIN_RAY_ALTITUDE_KM:g} km above the Earth")


def _tle_track(obj: TleObject, t0, ts, observer, exposure_time_s, frame, light_time, file) -> Track:
    t = t0 + _seconds(ts)
    m_teme = teme_to_gcrs(t)
    n = ts.size
    if isinstance(observer, GroundSite):
        r_obs, v_obs = observer.posvel_gcrs(t)
    elif isinstance(observer, SpaceObserver):
        r_obs, v_obs = observer.posvel_gcrs(t, m_teme)
    else:
        r_obs, v_obs = np.zeros((n, 3)), np.zeros((n, 3))
    key = f"{obj.key}.tle"
    jd1, jd2 = t.jd1, t.jd2
    sat = obj.tle.satrec()
    r_teme, _ = propagate_teme(obj.tle, jd1, jd2, key=key, file=file, satrec=sat)
    r_obj = apply(m_teme, r_teme)
    if light_time and frame != "geometric":
        # TEME turns only with precession-nutation: the matrix at t serves for t - tau (tau ~ ms)
        for _ in range(3):
            tau = np.linalg.norm(r_obj - r_obs, axis=-1) / C_KM_S
            r_teme, _ = propagate_teme(obj.tle, jd1, jd2 - tau / 86400.0, key=key, file=file, satrec=sat)
            r_obj = apply(m_teme, r_teme)
    rel = r_obj - r_obs
    rng = np.linalg.norm(rel, axis=-1)
    u = rel / rng[:, None]
    if frame == "apparent":
        u = aberrate(u, v_obs)
    elif frame == "astrometric":
        u = aberrate(u, -earth_barycentric_velocity_km_s(t))
    ra, dec = unit_to_radec(u)
    sun = sun_geocentric_km(t)
    to_sun = sun - r_obj
    sun_dist = np.linalg.norm(to_sun, axis=-1)
    track = Track(ts, ra, dec, frame, float(exposure_time_s), t0.isot, range_km=rng,
                  phase_angle_deg=angle_between_deg(to_sun, -rel), sun_distance_au=sun_dist / AU_KM,
                  sunlit_fraction=sunlit_fraction(r_obj, sun), object_gcrs_km=r_obj, observer_gcrs_km=r_obs,
                  sun_dir=to_sun / sun_dist[:, None], observer_dir=-rel / rng[:, None],
                  key=obj.key)
    if isinstance(observer, GroundSite):
        track.elevation_deg, track.azimuth_deg = observer.altaz_deg(rel, itrs_to_gcrs(t))
        _check_elevation(track, observer, obj.key, file)
    elif isinstance(observer, SpaceObserver):
        _check_earth_blocking(r_obs, rel, ts, obj.key, observer, file)
    return track


def object_track(obj: SpaceObject, pointing_epoch, exposure_time_s: float, observer=None,
                 n_samples: int | None = None, *, frame: str = "astrometric", light_time: bool = True,
                 t_end_s: float | None = None, file: str | None = None) -> Track:
    """The object's sky track during the exposure, sampled in time, with a cubic-spline interpolator.

    Physics: a TLE object is propagated with SGP4 at each sample (TEME), rotated to the GCRS, seen from the
    observer at the retarded time (light-time) and, depending on ``frame``, aberrated by the observer's
    velocity (``"apparent"``) or with the annual aberration removed (``"astrometric"``, the star
    catalogue's frame; see the module notes). A RA/Dec + rate object moves at constant angular speed along
    a great circle. The samples are joined by a cubic spline through unit vectors (thesis sec. 3.4.2).

    Parameters
    ----------
    obj : :class:`RateObject` or :class:`TleObject`
    pointing_epoch : exposure start, ISO UTC string or astropy Time
    exposure_time_s : exposure time [s] (> 0)
    observer : :class:`~scenes.objects.frames.GroundSite`, :class:`~scenes.objects.frames.SpaceObserver`
        or None (geocentre; no horizon test)
    n_samples : number of sample times, evenly spaced over [0, t_end_s]; default one per second, at least 9
        (the spline error is then < 0.01" for any Earth satellite; see docs/scenes_objects.md)
    frame : ``"astrometric"`` (default), ``"apparent"`` or ``"geometric"`` (TLE objects)
    light_time : apply the light-time correction (``apparent`` and ``astrometric``)
    t_end_s : sample until this time [s] (>= exposure time), e.g. exposure + rolling-shutter readout time
    file : scene file name for error messages

    Raises
    ------
    ObjectError
        Exposure time <= 0; SGP4 failure (a decayed satellite); an object below the horizon of a ground
        site at any sample; an object hidden by the Earth from a spacecraft.

    References
    ----------
    Vallado, Crawford, Hujsak & Kelso 2006, AIAA 2006-6753 (SGP4, TEME); Explanatory Supplement to the
    Astronomical Almanac, 3rd ed. 2013, ch. 7 (light-time, aberration); Montenbruck & Gill 2000, Satellite
    Orbits, sec. 3.4 (Earth shadow).
    """
    if frame not in FRAMES:
        raise ValueError(f"frame {frame!r}: expected one of {FRAMES}")
    ts = _sample_times(exposure_time_s, n_samples, t_end_s, obj.key)
    with offline_iers():
        t0 = as_time(pointing_epoch, file=file)
        if isinstance(obj, RateObject):
            return _rate_track(obj, t0, ts, observer, exposure_time_s, file)
        if isinstance(obj, TleObject):
            return _tle_track(obj, t0, ts, observer, exposure_time_s, frame, light_time, file)
    raise TypeError(f"object_track: expected a RateObject or TleObject, got {type(obj).__name__}")


# --------------------------------------------------------------------------------------- field and horizon
def _dense_unit_vectors(track: Track, step_deg: float) -> np.ndarray:
    u = radec_to_unit(track.ra_deg, track.dec_deg)
    path = float(np.sum(angle_between_deg(u[:-1], u[1:])))
    n = int(min(200000, max(4 * len(track.t_s), math.ceil(path / max(step_deg, 1e-9)) + 1)))
    return track.unit_vector(np.linspace(track.t_s[0], track.t_s[-1], n))


def in_field(track: Track, field, *, shape: tuple[int, int] | None = None, margin_px: float = 0.0) -> bool:
    """True if the object is inside the field at any time of its sampled span.

    ``field`` is an astropy WCS (with ``pixel_shape`` set, or ``shape`` = (ny, nx) given; a margin in
    pixels, e.g. the PSF radius, widens it) or a tuple ``(ra_deg, dec_deg, radius_deg)``. The spline is
    evaluated densely enough (steps of a tenth of the field) that a fast object crossing the field between
    two samples is still found.
    """
    if isinstance(field, tuple | list) and len(field) == 3:
        ra0, dec0, radius = (float(x) for x in field)
        u = _dense_unit_vectors(track, radius / 10.0)
        return bool(np.any(angle_between_deg(u, radec_to_unit(ra0, dec0)) <= radius))
    wcs = field
    if shape is None:
        if wcs.pixel_shape is None:
            raise ValueError("in_field: the WCS has no pixel_shape; pass shape=(ny, nx)")
        nx, ny = wcs.pixel_shape
    else:
        ny, nx = shape
    from astropy.wcs.utils import proj_plane_pixel_scales

    scale_deg = float(np.max(np.abs(proj_plane_pixel_scales(wcs.celestial))))
    u = _dense_unit_vectors(track, scale_deg * min(nx, ny) / 10.0)
    center = radec_to_unit(*wcs.wcs.crval)
    near = angle_between_deg(u, center) < 80.0  # the gnomonic projection is meaningless far from CRVAL
    if not np.any(near):
        return False
    ra, dec = unit_to_radec(u[near])
    x, y = wcs.world_to_pixel_values(ra, dec)
    inside = ((x >= -0.5 - margin_px) & (x <= nx - 0.5 + margin_px)
              & (y >= -0.5 - margin_px) & (y <= ny - 0.5 + margin_px))
    return bool(np.any(inside))


def require_in_field(track: Track, field, index: int, *, shape=None, margin_px: float = 0.0,
                     file: str | None = None) -> None:
    """Raise :class:`ObjectError` naming ``objects[index]`` when the object never enters the field."""
    if in_field(track, field, shape=shape, margin_px=margin_px):
        return
    if isinstance(field, tuple | list):
        ra0, dec0 = field[0], field[1]
    else:
        ra0, dec0 = field.wcs.crval
    sep = angle_between_deg(radec_to_unit(track.ra_deg, track.dec_deg), radec_to_unit(ra0, dec0))
    raise ObjectError(f"object {index} stays outside the field for the whole exposure (from RA {track.ra_deg[0]:.4f} "
                      f"Dec {track.dec_deg[0]:.4f} to RA {track.ra_deg[-1]:.4f} Dec {track.dec_deg[-1]:.4f} deg; "
                      f"closest {sep.min():.3f} deg from the field centre)", key=f"objects[{index}]", file=file,
                      expected="an object that crosses the field during the exposure")


def pointing_elevation_deg(ra_deg: float, dec_deg: float, epoch, exposure_time_s: float,
                           site: GroundSite) -> tuple[float, float]:
    """Geometric elevation [deg] of a fixed RA/Dec direction at a ground site, at the start and end."""
    import astropy.units as u

    with offline_iers():
        t = as_time(epoch) + np.array([0.0, max(float(exposure_time_s), 0.0)]) * u.s
        vec = np.repeat(radec_to_unit(ra_deg, dec_deg)[None, :], 2, axis=0)
        el, _ = site.altaz_deg(vec, itrs_to_gcrs(t))
    return float(el[0]), float(el[1])


def check_pointing_visible(ra_deg: float, dec_deg: float, epoch, exposure_time_s: float, site: GroundSite, *,
                           file: str | None = None) -> None:
    """Raise :class:`ObjectError` (key ``pointing``) if the field centre is below the site's horizon."""
    e0, e1 = pointing_elevation_deg(ra_deg, dec_deg, epoch, exposure_time_s, site)
    if min(e0, e1) < 0:
        raise ObjectError(f"the pointing RA {ra_deg:g} Dec {dec_deg:g} is below the horizon of site {site.name!r} "
                          f"(lat {site.lat_deg:g}, lon {site.lon_deg:g}) at {as_time(epoch).isot}: elevation "
                          f"{e0:.2f} deg at the start, {e1:.2f} deg at the end", key="pointing", file=file,
                          expected="a pointing above the horizon (elevation >= 0 deg) during the exposure")
