"""Observers, frame rotations and the vector geometry of satellite astrometry (offline astropy only).

Frames. Every vector here is geocentric with GCRS axes (which are aligned with the ICRS to well below a
milliarcsecond: the GCRS is "kinematically non-rotating", IAU 2000 Resolution B1.3). SGP4 gives TEME
vectors (True Equator, Mean Equinox of date; Vallado et al. 2006, AIAA 2006-6753, sec. 3.4); astropy's
``TEME -> ITRS -> GCRS`` chain (GMST 1982 + polar motion, then the IAU 2006/2000A CIO-based rotation) maps
them. A geocentric ``TEME -> GCRS`` or ``ITRS -> GCRS`` transform of a position is a pure rotation (astropy
adds aberration only when it changes the origin, which never happens here), so each is computed once per
sample time as a 3x3 matrix by transforming the three basis vectors.

Earth orientation. UT1-UTC and polar motion come from the IERS tables bundled with astropy
(``astropy-iers-data``); :func:`offline_iers` forbids astropy from downloading newer ones. Past the end of
the bundled IERS-A predictions astropy keeps the last values and warns: UT1 may then be off by up to ~0.9 s,
which rotates a ground site by up to 0.9 s x 15"/s = 13.5" about the pole, i.e. moves it by up to ~0.4 km
(equator) in the GCRS: for a LEO object at 500 km range that is up to ~3 arcmin on the sky. Satellite
positions themselves are insensitive to UT1 (TEME -> GCRS depends only on TT through GMST - ERA).

Ephemerides. The Sun and the Earth's barycentric velocity come from astropy's ``builtin`` ephemeris
(ERFA ``epv00``, a VSOP87-based series good to ~10 km and ~mm/s over 1900-2100): no download.
"""

from __future__ import annotations

import contextlib
import math
import warnings
from dataclasses import dataclass

import numpy as np

from .errors import ObjectError
from .tle import Tle, propagate_teme

C_KM_S = 299792.458  # speed of light [km/s] (exact)
AU_KM = 149597870.7  # astronomical unit [km] (IAU 2012 Resolution B2)
R_EARTH_KM = 6378.137  # WGS84 equatorial radius [km]
R_SUN_KM = 695700.0  # nominal solar radius [km] (IAU 2015 Resolution B3)


@contextlib.contextmanager
def offline_iers():
    """Use only the IERS tables bundled with astropy (no download; warn, not fail, past their end)."""
    from astropy.utils import iers

    with iers.conf.set_temp("auto_download", False), iers.conf.set_temp("iers_degraded_accuracy", "warn"), \
            warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*(dubious year|leap-second).*")
        yield


def as_time(epoch, *, key: str = "pointing.epoch", file: str | None = None):
    """An astropy UTC :class:`~astropy.time.Time` from an ISO string or a Time (scalar)."""
    from astropy.time import Time

    if isinstance(epoch, Time):
        return epoch.utc
    try:
        return Time(str(epoch), scale="utc")
    except ValueError:
        raise ObjectError(f"epoch {epoch!r} is not a time", key=key, file=file,
                          expected="an ISO UTC time like 2023-02-01T22:00:00") from None


# ---------------------------------------------------------------------------------------------- vectors
def radec_to_unit(ra_deg, dec_deg) -> np.ndarray:
    """Unit vectors (..., 3) for right ascension and declination [deg]."""
    ra, dec = np.radians(ra_deg), np.radians(dec_deg)
    return np.stack([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)], axis=-1)


def unit_to_radec(vec) -> tuple[np.ndarray, np.ndarray]:
    """Right ascension in [0, 360) and declination [deg] of vectors (..., 3) (any length)."""
    v = np.asarray(vec, dtype=float)
    ra = np.degrees(np.arctan2(v[..., 1], v[..., 0])) % 360.0
    dec = np.degrees(np.arctan2(v[..., 2], np.hypot(v[..., 0], v[..., 1])))
    return ra, dec


def east_north(u) -> tuple[np.ndarray, np.ndarray]:
    """Local east and north unit vectors on the sky at directions ``u`` (..., 3) (towards +RA, +Dec)."""
    u = np.asarray(u, dtype=float)
    east = np.stack([-u[..., 1], u[..., 0], np.zeros_like(u[..., 0])], axis=-1)
    norm = np.linalg.norm(east, axis=-1, keepdims=True)
    east = np.where(norm > 1e-15, east / np.where(norm > 1e-15, norm, 1.0), np.array([0.0, 1.0, 0.0]))
    north = np.cross(u, east)
    return east, north


def angle_between_deg(a, b) -> np.ndarray:
    """Angle between vectors (..., 3) [deg] (atan2 form, accurate at all angles)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1)))


def aberrate(u, velocity_km_s) -> np.ndarray:
    """Direction seen by an observer moving at ``velocity_km_s`` for a geometric direction ``u`` (..., 3).

    Special-relativistic stellar aberration (Explanatory Supplement to the Astronomical Almanac, 3rd ed.
    2013, eq. 7.40; Kaplan et al. 1989, AJ 97, 1197, eq. 3.12):

        u' = [ u / gamma + beta + (u . beta) beta / (1 + 1/gamma) ] / (1 + u . beta),   beta = v / c

    To first order u' = u + beta - (u . beta) u, a shift of |beta| sin(theta) towards the apex (20.5" for
    the Earth's orbital 29.8 km/s, 0.32" for the equatorial rotation, ~5" for a LEO spacecraft). The inverse
    is the same formula with -v. Unit vectors in, unit vectors out.
    """
    u = np.asarray(u, dtype=float)
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    beta = np.asarray(velocity_km_s, dtype=float) / C_KM_S
    b2 = np.sum(beta * beta, axis=-1, keepdims=True)
    ginv = np.sqrt(1.0 - b2)
    ub = np.sum(u * beta, axis=-1, keepdims=True)
    out = (ginv * u + beta + ub * beta / (1.0 + ginv)) / (1.0 + ub)
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


# --------------------------------------------------------------------------------------- rotations (N,3,3)
def _rotation_to_gcrs(frame_cls, t) -> np.ndarray:
    """Matrices M (N, 3, 3) with ``v_gcrs = M @ v_frame`` at the times ``t`` for a geocentric frame."""
    import astropy.units as u
    from astropy.coordinates import GCRS, CartesianRepresentation

    t = t.reshape(-1)
    basis = np.broadcast_to(np.eye(3)[:, :, None], (3, 3, t.size)) * 1e4  # (component, basis vector, time)
    with offline_iers():
        c = frame_cls(CartesianRepresentation(basis * u.km), obstime=t)
        out = c.transform_to(GCRS(obstime=t)).cartesian.xyz.to_value(u.km) / 1e4
    return np.moveaxis(out, -1, 0)


def teme_to_gcrs(t) -> np.ndarray:
    """TEME -> GCRS rotation matrices (N, 3, 3) at the UTC times ``t``."""
    from astropy.coordinates import TEME

    return _rotation_to_gcrs(TEME, t)


def itrs_to_gcrs(t) -> np.ndarray:
    """ITRS -> GCRS rotation matrices (N, 3, 3) (Earth rotation with UT1, polar motion, precession-nutation)."""
    from astropy.coordinates import ITRS

    return _rotation_to_gcrs(ITRS, t)


def apply(m, v) -> np.ndarray:
    """``m @ v`` for stacks (N, 3, 3) x (N, 3)."""
    return np.einsum("nij,nj->ni", m, v)


def earth_barycentric_velocity_km_s(t) -> np.ndarray:
    """Barycentric velocity of the geocentre (N, 3) [km/s], ICRS axes (astropy ``builtin`` ephemeris)."""
    import astropy.units as u
    from astropy.coordinates import get_body_barycentric_posvel

    with offline_iers():
        _, vel = get_body_barycentric_posvel("earth", t.reshape(-1), ephemeris="builtin")
    return vel.xyz.to_value(u.km / u.s).T


def sun_geocentric_km(t) -> np.ndarray:
    """Geometric geocentric position of the Sun (N, 3) [km], GCRS axes (``builtin`` ephemeris)."""
    import astropy.units as u
    from astropy.coordinates import get_body_barycentric

    t = t.reshape(-1)
    with offline_iers():
        sun = get_body_barycentric("sun", t, ephemeris="builtin").xyz.to_value(u.km)
        earth = get_body_barycentric("earth", t, ephemeris="builtin").xyz.to_value(u.km)
    return (sun - earth).T


# --------------------------------------------------------------------------------------------- observers
@dataclass(frozen=True)
class GroundSite:
    """An observatory on the ground: geodetic WGS84 latitude and longitude [deg] (east positive), height [m].

    Refraction is not modelled (it moves stars and objects alike; the horizon test uses geometric
    elevation).
    """

    lat_deg: float
    lon_deg: float
    alt_m: float = 0.0
    name: str = "site"

    def __post_init__(self):
        checks = [("lat_deg", self.lat_deg, -90, 90), ("lon_deg", self.lon_deg, -360, 360),
                  ("alt_m", self.alt_m, -500, 1e5)]
        for key, val, lo, hi in checks:
            if not (isinstance(val, (int, float)) and math.isfinite(val) and lo <= val <= hi):
                raise ObjectError(f"site {self.name!r}: {key} = {val!r}", key=f"observer.{key}",
                                  expected=f"a number in [{lo}, {hi}]")

    def location(self):
        import astropy.units as u
        from astropy.coordinates import EarthLocation

        return EarthLocation.from_geodetic(self.lon_deg * u.deg, self.lat_deg * u.deg, self.alt_m * u.m)

    def posvel_gcrs(self, t) -> tuple[np.ndarray, np.ndarray]:
        """Site position [km] and velocity [km/s] (N, 3), geocentric GCRS, at UTC times ``t``."""
        import astropy.units as u

        with offline_iers():
            pos, vel = self.location().get_gcrs_posvel(t.reshape(-1))
        return pos.xyz.to_value(u.km).T, vel.xyz.to_value(u.km / u.s).T

    def itrs_km(self) -> np.ndarray:
        import astropy.units as u

        g = self.location().get_itrs().cartesian.xyz.to_value(u.km)
        return np.asarray(g, dtype=float)

    def enu_matrix(self) -> np.ndarray:
        """Rows: local east, north, up (geodetic normal) in ITRS components."""
        lat, lon = math.radians(self.lat_deg), math.radians(self.lon_deg)
        return np.array([[-math.sin(lon), math.cos(lon), 0.0],
                         [-math.sin(lat) * math.cos(lon), -math.sin(lat) * math.sin(lon), math.cos(lat)],
                         [math.cos(lat) * math.cos(lon), math.cos(lat) * math.sin(lon), math.sin(lat)]])

    def altaz_deg(self, vec_gcrs, m_itrs_to_gcrs) -> tuple[np.ndarray, np.ndarray]:
        """Geometric elevation and azimuth (north through east) [deg] of topocentric GCRS vectors (N, 3)."""
        v_itrs = np.einsum("nji,nj->ni", m_itrs_to_gcrs, vec_gcrs)  # transpose = inverse rotation
        enu = v_itrs @ self.enu_matrix().T
        el = np.degrees(np.arctan2(enu[:, 2], np.hypot(enu[:, 0], enu[:, 1])))
        az = np.degrees(np.arctan2(enu[:, 0], enu[:, 1])) % 360.0
        return el, az


@dataclass(frozen=True)
class SpaceObserver:
    """An observer in orbit (an SBOC-like space-based optical camera) given by its own element set."""

    tle: Tle
    name: str = "spacecraft"

    def posvel_gcrs(self, t, m_teme_to_gcrs=None) -> tuple[np.ndarray, np.ndarray]:
        """Position [km] and velocity [km/s] (N, 3), geocentric GCRS, at UTC times ``t``.

        The TEME velocity is rotated with the position's matrix: TEME turns only with precession-nutation,
        so the neglected term is ~1e-12 rad/s x 7000 km, far below a micrometre per second.
        """
        t = t.reshape(-1)
        m = teme_to_gcrs(t) if m_teme_to_gcrs is None else m_teme_to_gcrs
        r, v = propagate_teme(self.tle, t.jd1, t.jd2, key="observer.tle")
        return apply(m, r), apply(m, v)


Observer = GroundSite | SpaceObserver | None
