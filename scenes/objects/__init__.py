"""Debris and satellite objects of a scene: sky tracks (RA/Dec + rates, or TLE + SGP4) and brightness.

The renderer's entry points:

* :func:`object_from_table` / :func:`observer_from_table`: the scene's ``[[objects]]`` entries and its
  observer (ground site or spacecraft) -> validated objects, errors naming the key;
* :func:`object_track`: the object's track during the exposure (times, RA/Dec, range, phase angle, Earth
  shadow, elevation) with a cubic-spline interpolator (:meth:`Track.radec`);
* :func:`require_in_field` / :func:`in_field`, :func:`check_pointing_visible`: field and horizon tests;
* :meth:`Brightness.photon_rate` (``obj.brightness.photon_rate(track, ...)``): photons/s at the aperture
  through a band, per track sample; :func:`pixel_dwell_time_s` for SNR expectations;
* :func:`light_curve_from_table` / :class:`LightCurve`: the optional ``light_curve`` of an object (a
  modulation of its rate in time, mean 1 over a period).

Conventions, equations, references and validation numbers: ``docs/scenes_objects.md``.
"""

from .brightness import (
    M_SUN_V,
    PHASE_FUNCTIONS,
    SOLAR_CONSTANT_W_M2,
    T_SUN_K,
    Brightness,
    ab_photon_irradiance,
    lambertian_sphere_phase,
    phase_function,
    pixel_dwell_time_s,
    plate_phase,
    reflected_fraction,
    reflected_magnitude,
    solar_photon_irradiance,
    solar_spectral_irradiance,
    specular_sphere_phase,
    sphere_area_m2,
    sun_ab_magnitude,
    sunlit_fraction,
    tumbling_plate_phase,
)
from .config import brightness_from_table, object_from_table, observer_from_table
from .errors import ObjectError
from .frames import GroundSite, SpaceObserver, aberrate, offline_iers
from .lightcurve import LightCurve, light_curve_from_table
from .tle import Tle, load_tle, parse_tle, propagate_teme, tle_checksum
from .track import (
    FRAMES,
    RateObject,
    TleObject,
    Track,
    check_pointing_visible,
    in_field,
    object_track,
    pointing_elevation_deg,
    require_in_field,
)

__all__ = [
    "FRAMES",
    "M_SUN_V",
    "PHASE_FUNCTIONS",
    "SOLAR_CONSTANT_W_M2",
    "T_SUN_K",
    "Brightness",
    "GroundSite",
    "LightCurve",
    "ObjectError",
    "RateObject",
    "SpaceObserver",
    "Tle",
    "TleObject",
    "Track",
    "ab_photon_irradiance",
    "aberrate",
    "brightness_from_table",
    "check_pointing_visible",
    "in_field",
    "lambertian_sphere_phase",
    "light_curve_from_table",
    "load_tle",
    "object_from_table",
    "object_track",
    "observer_from_table",
    "offline_iers",
    "parse_tle",
    "phase_function",
    "pixel_dwell_time_s",
    "plate_phase",
    "pointing_elevation_deg",
    "propagate_teme",
    "reflected_fraction",
    "reflected_magnitude",
    "require_in_field",
    "solar_photon_irradiance",
    "solar_spectral_irradiance",
    "specular_sphere_phase",
    "sphere_area_m2",
    "sun_ab_magnitude",
    "sunlit_fraction",
    "tle_checksum",
    "tumbling_plate_phase",
]
