"""Where a source is on the detector at time t: telescope tracking, sky-to-pixel, exposure windows.

Tracking (``[exposure] tracking``) moves the boresight b(t) during the exposure:

``"sidereal"``
    the mount follows the sky: b(t) = b(0), stars stay put;
``"rate"``
    the boresight moves at constant angular speed along the great circle tangent to the on-sky rates
    (``rate_ra_deg_s`` = dRA/dt cos Dec, ``rate_dec_deg_s`` = dDec/dt), exactly as a RA/Dec + rate object
    of :mod:`scenes.objects` moves: an object given the tracking's rates stays fixed in the frame;
``"none"``
    the drive is off (an equatorial mount parked: hour angle and declination fixed), so the boresight's
    RA grows at the sidereal rate, RA(t) = RA(0) + 360 deg t / 86164.0905 s, Dec constant, and the stars
    trail westwards at 15.04 cos(Dec) arcsec/s.

The camera keeps its position angle relative to the local north of the boresight (``pointing.roll_deg``),
so the frame at time t is the TAN projection about b(t) with the same roll. With M(t) = [east, north,
b](t) the local triad, a sky direction u lands at time t where the t = 0 frame puts Q(t)^T u, with
Q(t) = M(t) M(0)^T: one WCS (the file's, SIP included once the optics provides it) serves all times, and
sky-to-pixel is always astropy's ``all_world2pix``.

Exposure windows: row ``r`` (0-based in the read-out window, unbinned) of a rolling-shutter sensor
integrates ``[r tau, r tau + T]`` (thesis eq. 10; tau = ``SensorConfig.row_time_s``, 0 for a global
shutter), so the light of a moving source reaches the frame during ``[0, T + (H - 1) tau]``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline

from ..objects.frames import east_north, radec_to_unit, unit_to_radec

SIDEREAL_DAY_S = 86164.0905  # mean sidereal day [s] (IERS Conventions 2010)
SIDEREAL_RATE_DEG_S = 360.0 / SIDEREAL_DAY_S


@dataclass(frozen=True)
class Boresight:
    """The telescope's pointing during the exposure (see the module notes).

    Parameters
    ----------
    ra_deg, dec_deg : pointing at the exposure start [deg]
    tracking : ``"sidereal"``, ``"rate"`` or ``"none"``
    rate_ra_deg_s, rate_dec_deg_s : on-sky rates of ``"rate"`` tracking [deg/s] (rate_ra = dRA/dt cos Dec)
    """

    ra_deg: float
    dec_deg: float
    tracking: str = "sidereal"
    rate_ra_deg_s: float = 0.0
    rate_dec_deg_s: float = 0.0

    @property
    def moving(self) -> bool:
        """True when stars move on the detector during the exposure."""
        if self.tracking == "none":
            return True
        return self.tracking == "rate" and (self.rate_ra_deg_s != 0 or self.rate_dec_deg_s != 0)

    @property
    def speed_deg_s(self) -> float:
        """Angular speed of the boresight on the sky [deg/s]."""
        if self.tracking == "none":
            return SIDEREAL_RATE_DEG_S * math.cos(math.radians(self.dec_deg))
        if self.tracking == "rate":
            return math.hypot(self.rate_ra_deg_s, self.rate_dec_deg_s)
        return 0.0

    def unit(self, t_s) -> np.ndarray:
        """Boresight unit vectors (n, 3) at times ``t_s`` [s]."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        p0 = radec_to_unit(self.ra_deg, self.dec_deg)
        if not self.moving:
            return np.repeat(p0[None, :], t.size, axis=0)
        if self.tracking == "none":
            return radec_to_unit(self.ra_deg + SIDEREAL_RATE_DEG_S * t, np.full(t.shape, self.dec_deg))
        east, north = east_north(p0)
        w = self.rate_ra_deg_s * east + self.rate_dec_deg_s * north
        omega = math.radians(float(np.linalg.norm(w)))
        d = w / np.linalg.norm(w)
        return np.cos(omega * t)[:, None] * p0 + np.sin(omega * t)[:, None] * d

    def triad(self, t_s) -> np.ndarray:
        """M(t) (n, 3, 3): columns east, north, boresight."""
        b = self.unit(t_s)
        e, n = east_north(b)
        return np.stack([e, n, b], axis=-1)

    def to_initial_frame(self, u, t_s) -> np.ndarray:
        """Q(t)^T u: the direction that the t = 0 frame maps where the frame at ``t_s`` maps ``u``.

        ``u`` (..., 3) broadcasts against the times (n,): shapes (n, 3) or (n, m, 3) -> same shape.
        """
        u = np.asarray(u, dtype=float)
        if not self.moving:
            return u
        m0 = self.triad(0.0)[0]  # (3, 3)
        mt = self.triad(t_s)  # (n, 3, 3)
        q_t = np.einsum("ij,njk->nik", m0, np.transpose(mt, (0, 2, 1)))  # Q^T = M0 M(t)^T
        if u.ndim == 2:
            return np.einsum("nij,nj->ni", q_t, u)
        return np.einsum("nij,nmj->nmi", q_t, u)


def world_to_pixel(wcs, ra_deg, dec_deg) -> tuple[np.ndarray, np.ndarray]:
    """0-based pixel coordinates (x, y) through the full WCS (``all_world2pix``: SIP included)."""
    ra = np.asarray(ra_deg, dtype=float)
    dec = np.asarray(dec_deg, dtype=float)
    if ra.size == 0:
        return ra.copy(), dec.copy()
    x, y = wcs.all_world2pix(ra.ravel(), dec.ravel(), 0)
    return np.asarray(x).reshape(ra.shape), np.asarray(y).reshape(ra.shape)


def units_to_pixel(wcs, boresight: Boresight, u, t_s) -> tuple[np.ndarray, np.ndarray]:
    """Pixel positions at times ``t_s`` of sky directions ``u`` ((n, 3) one per time, or (n, m, 3))."""
    ra, dec = unit_to_radec(boresight.to_initial_frame(u, t_s))
    return world_to_pixel(wcs, ra, dec)


@dataclass
class StarPaths:
    """Pixel paths of many sources that move with the frame (stars under rate or no tracking).

    Positions are computed exactly (:func:`units_to_pixel`) at ``K`` knot times and joined by a cubic
    spline in time per source; the knots are spaced so that a source moves at most ``KNOT_PX`` pixels
    between them (the paths are nearly straight: the spline error is far below 1e-3 pixel).
    """

    t_knots: np.ndarray
    spline_x: CubicSpline
    spline_y: CubicSpline

    KNOT_PX = 32.0

    @classmethod
    def from_units(cls, wcs, boresight: Boresight, u: np.ndarray, t_end_s: float, speed_px_s: float) -> StarPaths:
        k = int(np.clip(math.ceil(speed_px_s * t_end_s / cls.KNOT_PX) + 1, 9, 513))
        tk = np.linspace(0.0, t_end_s, k)
        uu = np.broadcast_to(u[None, :, :], (k,) + u.shape)
        x, y = units_to_pixel(wcs, boresight, uu, tk)  # (k, m)
        return cls(tk, CubicSpline(tk, x, axis=0), CubicSpline(tk, y, axis=0))

    def on_grid(self, t_s) -> tuple[np.ndarray, np.ndarray]:
        """Positions (len(t), m) of every source at the times ``t_s``."""
        return self.spline_x(t_s), self.spline_y(t_s)

    def subset_on_grid(self, idx, t_s) -> tuple[np.ndarray, np.ndarray]:
        """Positions (len(t), len(idx)) of the sources ``idx`` only."""
        from scipy.interpolate import PPoly

        return tuple(PPoly(sp.c[:, :, idx], sp.x)(t_s) for sp in (self.spline_x, self.spline_y))

    def each_of(self, idx, t_s) -> tuple[np.ndarray, np.ndarray]:
        """Position of source ``idx[i]`` at its own time ``t_s[i]`` (len(idx),)."""
        t = np.asarray(t_s, dtype=float)
        cols = np.asarray(idx, dtype=np.int64)
        tk = self.t_knots
        j = np.clip(np.searchsorted(tk, t, side="right") - 1, 0, len(tk) - 2)
        d = t - tk[j]
        out = []
        for sp in (self.spline_x, self.spline_y):
            c = sp.c  # (4, k - 1, m)
            out.append(((c[0, j, cols] * d + c[1, j, cols]) * d + c[2, j, cols]) * d + c[3, j, cols])
        return out[0], out[1]


def sample_times(t_end_s: float, speed_px_s: float, step_px: float = 0.25, min_samples: int = 8
                 ) -> tuple[np.ndarray, float]:
    """Midpoints of ``N`` equal intervals covering ``[0, t_end_s]`` and their width ``dt``.

    ``N`` is the smallest number with speed x dt <= ``step_px`` (and at least ``min_samples``): each
    sample stands for the light of one interval (midpoint rule in time).
    """
    n = max(min_samples, math.ceil(speed_px_s * t_end_s / step_px * (1.0 + 1e-9)))
    dt = t_end_s / n
    return (np.arange(n) + 0.5) * dt, dt


def window_overlap(t_lo, t_hi, row, row_time_s: float, exptime_s: float) -> np.ndarray:
    """Fraction of ``[t_lo, t_hi]`` inside the exposure window ``[row tau, row tau + T]`` of ``row``."""
    t0 = np.asarray(row, dtype=float) * row_time_s
    width = np.asarray(t_hi) - np.asarray(t_lo)
    ov = np.minimum(t_hi, t0 + exptime_s) - np.maximum(t_lo, t0)
    return np.clip(ov, 0.0, None) / np.where(width > 0, width, 1.0)
