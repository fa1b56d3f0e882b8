"""Straylight from the Sun and the Moon on the focal plane (``[effects.straylight]``).

Physics
    A bright source outside the field at off-axis angle theta and azimuth phi (telescope frame) sends
    light onto the detector by scattering in the tube, off the vanes and the mirrors. The point-source
    transmittance (Breault; :mod:`optics.straylight`)

        PST(theta, phi) = E_det / E_in                                                          (1)

    is the mean detector irradiance over the irradiance at the aperture, normal to the source. The
    photo-electron rate per pixel is therefore

        S(x, y) = N_in  PST(theta, phi; u, v)  A_pix          [e-/s/pixel],                      (2)

    with ``N_in = integral E_lambda(lambda) QE(lambda) lambda / (h c) dlambda`` the source's irradiance at
    the aperture counted as photo-electrons [e-/s/m^2] (the PST includes the mirrors' reflectance and all
    losses), ``A_pix`` the pixel area and PST(u, v) the focal-plane map whose mean is the PST
    (:func:`optics.straylight.irradiance_map`). The PST is taken as grey (the optics traces one wavelength,
    550 nm).

    * Sun: a 5772 K blackbody normalised to the solar constant 1361 W/m^2 at 1 au (IAU 2015 B3), scaled by
      (1 au / r)^2 at the observer's distance r.
    * Moon: the same solar spectrum scaled to the Moon's V magnitude (grey reflection),
      ``E_moon = E_sun(1 au) 10^(-0.4 (V_moon - V_sun))`` with V_sun = -26.76 (Willmer 2018) and the lunar
      phase law of Allen (1973, Astrophysical Quantities, 3rd ed., p. 144), as used by Krisciunas &
      Schaefer (1991, PASP 103, 1033):

          V_moon(alpha) = -12.73 + 0.026 |alpha| + 4e-9 alpha^4 + 5 log10(d / 384400 km)          (3)

      alpha the phase angle (Sun-Moon-observer) [deg], d the Moon's distance.

Geometry
    Sun and Moon from astropy's ``builtin`` ephemeris (ERFA epv00 and moon98; no download) at
    mid-exposure, geocentric, minus the observer's position (ground site or spacecraft, GCRS): geometric
    topocentric directions (aberration and light time, < 0.01 deg, are neglected). Off-axis angle and
    azimuth in the telescope frame: +z the optical axis, +x (the focuser side, azimuth 0) and +y the
    directions in which field angles theta_x, theta_y grow: at roll r, +x = cos(r) east - sin(r) north and
    +y = sin(r) east + cos(r) north (the scene's WCS reads the focal plane as x = u / pitch, y = -v / pitch,
    :mod:`scenes.projection`). A source below the horizon of a ground site, or hidden by the Earth from a
    spacecraft (for the Sun: the sunlit fraction of its disc), contributes nothing; so does a source behind
    the aperture plane (theta >= 90 deg: no geometric path into a closed tube). Neither atmospheric
    extinction nor the sunlit Earth (limb) is modelled.

PST sources (``pst``)
    a number (the same PST at every angle below 90 deg, uniform over the detector), a table
    ``[[theta_deg, pst], ...]`` (interpolated linearly in log PST between positive values, linearly
    otherwise, held beyond the ends; uniform over the detector), or ``"optics"``: the ray-traced focal-plane
    map of the scene's design at each source's (theta, phi), cached on disk by the design's hash
    (:mod:`optics.cache`; angles rounded to 0.1 deg and 1 deg for the cache key).

The chain's vignetting multiplies everything the scene hands it; the straylight map already is the
irradiance of the focal plane, so it is handed over divided by the vignetting map (the chain's product
restores it exactly). The render passes that map as data (``ri``: the relative illumination of the scene's
``[effects.vignetting]`` table, :func:`detector.effects.optical.relative_illumination`).

One name, two forms. ``[effects.straylight]`` with ``pst`` is this module's (the scene evaluates it: it needs
the ephemerides and the optics); with ``model = "field"``, ``"legendre"`` or ``"edge"`` it is the detector's smooth field
(:class:`detector.effects.sky.StraylightField`, the form diagnosis fits). A loaded scene routes the table
once (:func:`is_traced_straylight`): ``scene.parts.straylight`` holds this form, validated, and
``scene.parts.effect_tables`` the field form with the other registry effects.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import astropy.units as u
import numpy as np
from astropy.coordinates import get_body_barycentric
from pydantic import BaseModel, ConfigDict, Field, field_validator

from detector.config import validate
from optics import cache
from optics import straylight as optics_straylight
from optics.llvm import init_mitsuba

from .errors import SceneError
from .objects.brightness import M_SUN_V, solar_photon_irradiance, sunlit_fraction
from .objects.frames import (
    AU_KM,
    R_EARTH_KM,
    GroundSite,
    SpaceObserver,
    as_time,
    east_north,
    itrs_to_gcrs,
    offline_iers,
    radec_to_unit,
)

MOON_MEAN_DISTANCE_KM = 384400.0
MOON_V_FULL = -12.73  # Allen 1973, p. 144
PST_ANGLE_STEP_DEG = 0.1  # cache-key rounding of the off-axis angle ("optics")
PST_AZIMUTH_STEP_DEG = 1.0  # ... and of the azimuth
MIN_RI = 1e-3  # vignetting below this is not divided out


class StraylightCfg(BaseModel):
    """``[effects.straylight]`` keys (see the module notes)."""

    model_config = ConfigDict(extra="forbid")
    pst: float | list[tuple[float, float]] | Literal["optics"]
    sources: list[Literal["sun", "moon"]] = ["sun", "moon"]
    rays: int = Field(1_000_000, ge=10_000, le=1_000_000_000, description="optics: paths per source direction")
    bins: tuple[int, int] = Field((16, 12), description="optics: map bins along the columns (u) and rows (v)")
    seed: int = Field(0, ge=0, description="optics: Monte Carlo seed")

    @field_validator("pst")
    @classmethod
    def _pst(cls, v):
        if isinstance(v, float) and not 0 <= v <= 1:
            raise ValueError("a PST in [0, 1]")
        if isinstance(v, list):
            a = np.array(v, dtype=float).reshape(-1, 2)
            if len(a) < 1 or np.any(np.diff(a[:, 0]) <= 0) or a[0, 0] < 0 or a[-1, 0] > 180:
                raise ValueError("rows [theta_deg, pst] with theta increasing in [0, 180]")
            if np.any(a[:, 1] < 0) or np.any(a[:, 1] > 1):
                raise ValueError("PST values in [0, 1]")
        return v

    @field_validator("bins")
    @classmethod
    def _bins(cls, v):
        if not all(1 <= n <= 512 for n in v):
            raise ValueError("two counts from 1 to 512")
        return v


def is_traced_straylight(table) -> bool:
    """``[effects.straylight]`` is the scene's own (Sun and Moon through a PST) unless it says
    ``model = "field"`` or ``"legendre"`` (the detector's smooth-field forms,
    :class:`detector.effects.sky.StraylightField`)."""
    return not (isinstance(table, dict) and table.get("model") in ("field", "legendre", "edge"))


def straylight_config(table: dict, *, file: str | None = None) -> StraylightCfg:
    """Validate ``[effects.straylight]``; errors name ``effects.straylight.KEY`` and the file."""
    if not isinstance(table, dict):
        raise SceneError(f"{table!r}", key="effects.straylight", file=file, expected="a table")
    return validate(StraylightCfg, table, prefix="effects.straylight", file=file)


# ---------------------------------------------------------------------------------------------- physics
def moon_v_magnitude(phase_deg, distance_km=MOON_MEAN_DISTANCE_KM):
    """V magnitude of the Moon at phase angle ``phase_deg`` [deg] and distance ``distance_km``, eq. (3).

    Allen (1973), Astrophysical Quantities, 3rd ed., p. 144 (valid to ~150 deg); Krisciunas & Schaefer
    1991, PASP 103, 1033.
    """
    a = np.abs(np.asarray(phase_deg, dtype=float))
    return MOON_V_FULL + 0.026 * a + 4e-9 * a ** 4 + 5.0 * np.log10(np.asarray(distance_km) / MOON_MEAN_DISTANCE_KM)


def pst_from_table(table, theta_deg) -> np.ndarray:
    """PST at ``theta_deg`` from rows (theta_deg, pst): log-linear between positive values, else linear."""
    a = np.asarray(table, dtype=float).reshape(-1, 2)
    th = np.atleast_1d(np.asarray(theta_deg, dtype=float))
    if len(a) == 1:
        return np.full(th.shape, a[0, 1])
    t = np.clip(th, a[0, 0], a[-1, 0])
    i = np.clip(np.searchsorted(a[:, 0], t, side="right") - 1, 0, len(a) - 2)
    f = (t - a[i, 0]) / (a[i + 1, 0] - a[i, 0])
    p0, p1 = a[i, 1], a[i + 1, 1]
    pos = (p0 > 0) & (p1 > 0)
    lin = p0 + f * (p1 - p0)
    logi = np.exp(np.log(np.where(pos, p0, 1.0)) * (1 - f) + np.log(np.where(pos, p1, 1.0)) * f)
    return np.where(pos, logi, lin)


def telescope_axes(ra_deg: float, dec_deg: float, roll_deg: float) -> np.ndarray:
    """Rows: the telescope's +x (azimuth 0, focuser side), +y and +z (optical axis), GCRS components."""
    b = radec_to_unit(ra_deg, dec_deg)
    e, n = east_north(b)
    c, s = math.cos(math.radians(roll_deg)), math.sin(math.radians(roll_deg))
    return np.array([c * e - s * n, s * e + c * n, b])


def off_axis(u_gcrs, axes) -> tuple[float, float]:
    """Off-axis angle theta and azimuth phi (from +x toward +y) [deg] of the direction ``u_gcrs``."""
    sx, sy, sz = axes @ np.asarray(u_gcrs, dtype=float)
    return math.degrees(math.atan2(math.hypot(sx, sy), sz)), math.degrees(math.atan2(sy, sx)) % 360.0


@dataclass
class Body:
    """A straylight source seen by the observer at mid-exposure."""

    name: str
    unit: np.ndarray  # topocentric direction, GCRS axes
    distance_km: float
    visible: float  # 1 visible, 0 below the horizon / behind the Earth (the Sun: sunlit fraction of its disc)
    electron_irradiance: float  # N_in [e-/s/m^2] at the aperture (0 when not visible)
    phase_deg: float = math.nan
    v_mag: float = math.nan
    elevation_deg: float = math.nan


def bodies(epoch, observer, wavelength_nm, qe, names=("sun", "moon")) -> dict[str, Body]:
    """Sun and Moon seen from ``observer`` (None: the geocentre) at the UTC time ``epoch``.

    ``wavelength_nm``, ``qe``: the sensor's QE curve, which turns irradiance into photo-electrons.
    """
    t = as_time(epoch).reshape(1)
    with offline_iers():
        earth = get_body_barycentric("earth", t, ephemeris="builtin").xyz.to_value(u.km).T[0]
        sun = get_body_barycentric("sun", t, ephemeris="builtin").xyz.to_value(u.km).T[0] - earth
        moon = get_body_barycentric("moon", t, ephemeris="builtin").xyz.to_value(u.km).T[0] - earth
    if isinstance(observer, (GroundSite, SpaceObserver)):
        obs = observer.posvel_gcrs(t)[0][0]
    else:
        obs = np.zeros(3)
    n_sun = solar_photon_irradiance(wavelength_nm, qe)  # e-/s/m^2 at 1 au
    out = {}
    for name in names:
        vec = (sun if name == "sun" else moon) - obs
        d = float(np.linalg.norm(vec))
        unit = vec / d
        visible, elev = 1.0, math.nan
        if isinstance(observer, GroundSite):
            el, _ = observer.altaz_deg(unit[None, :], itrs_to_gcrs(t))
            elev = float(el[0])
            visible = 1.0 if elev > 0 else 0.0
        elif isinstance(observer, SpaceObserver):
            if name == "sun":
                visible = float(sunlit_fraction(obs[None, :], sun[None, :])[0])
            else:  # the Moon hidden by the Earth's disc (it is always farther than the Earth)
                r = float(np.linalg.norm(obs))
                sep = math.degrees(math.acos(float(np.clip(-obs @ unit / r, -1, 1))))
                visible = 0.0 if sep < math.degrees(math.asin(min(R_EARTH_KM / r, 1.0))) else 1.0
        if name == "sun":
            body = Body("sun", unit, d, visible, visible * n_sun * (AU_KM / d) ** 2, elevation_deg=elev)
        else:
            to_sun, to_obs = sun - moon, obs - moon
            phase = math.degrees(math.acos(float(np.clip(to_sun @ to_obs / (np.linalg.norm(to_sun)
                                                                             * np.linalg.norm(to_obs)), -1, 1))))
            v = float(moon_v_magnitude(phase, d))
            body = Body("moon", unit, d, visible, visible * n_sun * 10 ** (-0.4 * (v - M_SUN_V)), phase, v, elev)
        out[name] = body
    return out


# ------------------------------------------------------------------------------------------ focal plane
def _optics_map(design, theta_deg: float, phi_deg: float, cfg: StraylightCfg) -> tuple[np.ndarray, tuple]:
    """Ray-traced PST map (rows along v, columns along u) and its extent [mm], from the optics cache."""
    th = round(theta_deg / PST_ANGLE_STEP_DEG) * PST_ANGLE_STEP_DEG
    ph = (round(phi_deg / PST_AZIMUTH_STEP_DEG) * PST_AZIMUTH_STEP_DEG) % 360.0
    settings = {"theta_deg": round(th, 6), "phi_deg": round(ph, 6), "rays": cfg.rays, "bins": list(cfg.bins),
                "seed": cfg.seed, "wavelength_nm": 550.0}

    def compute():
        emap, ext = optics_straylight.irradiance_map(design, init_mitsuba(), th, ph, rays=cfg.rays, bins=tuple(cfg.bins),
                                   seed=cfg.seed)
        return {"map": np.asarray(emap).tolist(), "extent": list(ext)}

    data, _ = cache.cached_json("straylight-map", design, settings, compute)
    return np.asarray(data["map"], dtype=float), tuple(data["extent"])


def bilinear(uc, vc, values):
    """``f(v, u)``: bilinear interpolation of ``values[v, u]`` given at bin centres ``uc``, ``vc``
    (increasing), edge values held outside; any order of the query points (a Monte Carlo map is not
    smooth enough for splines, which would overshoot)."""
    m = np.asarray(values, dtype=float)

    def frac_index(c, q):
        t = np.interp(q, c, np.arange(len(c), dtype=float)) if len(c) > 1 else np.zeros(np.shape(q))
        i0 = np.clip(np.floor(t).astype(np.int64), 0, max(len(c) - 2, 0))
        i1 = np.minimum(i0 + 1, len(c) - 1)
        return i0, i1, t - i0

    def f(v, u):
        j0, j1, fv = frac_index(np.asarray(vc, float), np.asarray(v, float))
        i0, i1, fu = frac_index(np.asarray(uc, float), np.asarray(u, float))
        rows0 = m[j0][:, i0] * (1 - fu) + m[j0][:, i1] * fu
        rows1 = m[j1][:, i0] * (1 - fu) + m[j1][:, i1] * fu
        return rows0 * (1 - fv)[:, None] + rows1 * fv[:, None]

    return f


@dataclass
class StraylightSignal:
    """Straylight photo-electrons per unbinned pixel over the exposure, ``signal(y0, y1, x0, x1)``.

    Sensor coordinates in (absolute rows/columns); float64 out. ``uniform_e`` is the part with a uniform
    PST; ``maps`` are ``(interpolator(v_mm, u_mm), e_per_unit_pst)`` of the ray-traced maps; ``ri`` the
    chain's vignetting (divided out, module notes).
    """

    width: int
    height: int
    pitch_um: float
    uniform_e: float = 0.0
    maps: list = field(default_factory=list)
    ri: object = None

    def __call__(self, y0: int, y1: int, x0: int, x1: int) -> np.ndarray:
        out = np.full((y1 - y0, x1 - x0), self.uniform_e)
        ys, xs = np.arange(y0, y1, dtype=float), np.arange(x0, x1, dtype=float)
        if self.maps:
            p = self.pitch_um * 1e-3
            u = (xs - (self.width - 1) / 2.0) * p
            v = -(ys - (self.height - 1) / 2.0) * p  # the scene reads the focal plane as y = -v / pitch
            for interp, scale in self.maps:
                out += scale * interp(v, u)
        if self.ri is not None:
            out /= np.maximum(self.ri(ys, xs), MIN_RI)
        return out


def straylight_signal(table: dict, scene, sensor, design, exptime_s: float, observer, *, ri=None,
                      wavelength_nm=None, qe=None) -> tuple[StraylightSignal, dict]:
    """The straylight of ``[effects.straylight]`` for a frame, and its FITS header cards.

    Parameters
    ----------
    table : the ``[effects.straylight]`` table, or its validated :class:`StraylightCfg` (``scene.parts.straylight``)
    scene, sensor, design : the scene, its :class:`detector.SensorConfig` and optics design
    exptime_s : exposure time [s]; the geometry is evaluated at mid-exposure
    observer : :class:`scenes.objects.GroundSite`, :class:`SpaceObserver` or None (geocentre)
    ri : the chain's vignetting ``ri(ys, xs)`` (sensor rows, columns), divided out; None without vignetting
    wavelength_nm, qe : band for N_in (default the sensor's QE table)
    """
    cfg = table if isinstance(table, StraylightCfg) else straylight_config(table, file=scene.source)
    lam = np.asarray(sensor.qe_wavelength_nm if wavelength_nm is None else wavelength_nm, dtype=float)
    q = np.asarray(sensor.qe if qe is None else qe, dtype=float)
    t_mid = as_time(scene.pointing.epoch) + 0.5 * exptime_s * u.s
    seen = bodies(t_mid, observer, lam, q, tuple(dict.fromkeys(cfg.sources)))
    axes = telescope_axes(scene.pointing.ra_deg, scene.pointing.dec_deg, scene.pointing.roll_deg)
    a_pix = (sensor.pixel_pitch_um * 1e-6) ** 2
    sig = StraylightSignal(sensor.sensor_width_px, sensor.sensor_height_px, sensor.pixel_pitch_um, ri=ri)
    cards = {}
    tag = {"sun": "SUN", "moon": "MON"}
    for name, body in seen.items():
        theta, phi = off_axis(body.unit, axes)
        e_per_pst = body.electron_irradiance * a_pix * exptime_s  # e-/pixel for PST = 1
        pst_mean = 0.0
        if e_per_pst > 0 and theta < 90.0:
            if cfg.pst == "optics":
                emap, (umin, umax, vmin, vmax) = _optics_map(design, theta, phi, cfg)
                nv, nu = emap.shape
                uc = umin + (np.arange(nu) + 0.5) * (umax - umin) / nu
                vc = vmin + (np.arange(nv) + 0.5) * (vmax - vmin) / nv
                sig.maps.append((bilinear(uc, vc, emap), e_per_pst))
                pst_mean = float(emap.mean())
            else:
                pst_mean = float(cfg.pst) if not isinstance(cfg.pst, list) else float(pst_from_table(cfg.pst, theta)[0])
                sig.uniform_e += e_per_pst * pst_mean
        k = tag[name]
        cards[f"{k}THETA"] = (round(theta, 4), f"[deg] {name} off-axis angle")
        cards[f"{k}PHI"] = (round(phi, 3), f"[deg] {name} azimuth from the focuser side")
        cards[f"{k}PST"] = (pst_mean, f"{name} PST (mean over the detector)")
        cards[f"{k}STRY"] = (e_per_pst * pst_mean / max(exptime_s, 1e-300) if exptime_s > 0 else 0.0,
                             f"[e-/s/pixel] {name} straylight")
        if name == "moon":
            cards["MOONPHAS"] = (round(body.phase_deg, 3), "[deg] Moon phase angle")
            cards["MOONVMAG"] = (round(body.v_mag, 3), "[mag] Moon V magnitude (Allen 1973)")
        if not body.visible:
            cards[f"{k}STRY"] = (0.0, f"[e-/s/pixel] {name} straylight ({name} not visible)")
    cards["STRAYPST"] = ("optics" if cfg.pst == "optics" else ("table" if isinstance(cfg.pst, list) else "value"),
                         "straylight PST source")
    return sig, cards
