"""Scene tables -> objects and observers, with errors that name the key and what was expected.

``[[objects]]`` entry (one of three positions, one of three brightness specifications)::

    # position: RA/Dec + on-sky rates at the exposure start (rate_ra_deg_s = d(RA)/dt * cos(Dec)) ...
    ra_deg = 120.96
    dec_deg = -29.24
    rate_ra_deg_s = 0.008558
    rate_dec_deg_s = -0.005486
    # ... or a TLE (two or three lines) ...
    tle = ["1 25544U ...", "2 25544 ..."]
    # ... or a TLE file (relative to the scene file) and a catalogue number or name
    tle_file = "catalog.tle"
    satellite = 25544
    # brightness: total photons at the aperture over the exposure ...
    photons = 13836
    # ... or a magnitude ("ab": AB in the simulation band like the stars; "solar_v": V of a sunlight reflector)
    mag = 9.5
    mag_system = "ab"
    # ... or a size: diameter_m (sphere) or area_m2, albedo, phase_function
    diameter_m = 1.0
    albedo = 0.1
    phase_function = "lambertian"   # "specular", "mixed" (+ specular_fraction), "tumbling_plate",
                                    # "plate" (+ plate_normal = "sun" | "observer" | "bisector" | [x, y, z])
    range_km = 1000.0               # RA/Dec objects given by size only (TLE objects get range and phase
    phase_angle_deg = 30.0          # from the orbit, the Sun and the observer)
    name = "debris 1"               # optional label
    # optional brightness modulation in time, mean 1 over a period (scenes.objects.lightcurve)
    light_curve = { kind = "sinusoid", amplitude = 0.62, period_s = 3.68, phase = 0.0 }
    # or { kind = "glint", amplitude = 20.0, period_s = 3.68, width_s = 0.05, phase = 0.0 }
    outside = "error"               # an object that never enters the field: "error" (a typo in its rates?)
                                    # or "skip" (render the frame without it; batch sequences set it)

``[observer]`` table (absent: the geocentre)::

    name = "ART"            # optional
    lat_deg = 38.96         # a ground site: geodetic latitude, east longitude [deg], height [m] ...
    lon_deg = -6.02
    alt_m = 330.0
    # ... or a spacecraft: tle = [...] or tle_file = "..." (+ satellite = ...)
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from .brightness import PHASE_FUNCTIONS, PLATE_NORMALS, Brightness
from .errors import ObjectError
from .frames import GroundSite, SpaceObserver
from .lightcurve import light_curve_from_table
from .tle import load_tle, parse_tle
from .track import RateObject, TleObject
from .validate import number as _num

RATE_KEYS = ("ra_deg", "dec_deg", "rate_ra_deg_s", "rate_dec_deg_s")
TLE_KEYS = ("tle", "tle_file", "satellite")
BRIGHTNESS_KEYS = ("photons", "mag", "mag_system", "diameter_m", "area_m2", "albedo", "phase_function",
                   "specular_fraction", "plate_normal", "range_km", "phase_angle_deg", "sun_distance_au")
OBJECT_KEYS = RATE_KEYS + TLE_KEYS + BRIGHTNESS_KEYS + ("name", "light_curve", "outside")
#: what an object that stays outside the field for the whole exposure does
OUTSIDE_CHOICES = ("error", "skip")
OBSERVER_KEYS = ("name", "lat_deg", "lon_deg", "alt_m", "tle", "tle_file", "satellite")
MAG_SYSTEMS = ("ab", "solar_v")


def _unknown(table: dict, allowed, prefix: str, file):
    extra = sorted(set(table) - set(allowed))
    if extra:
        raise ObjectError(f"unknown key {extra[0]!r}", key=f"{prefix}.{extra[0]}", file=file,
                          expected="one of " + ", ".join(allowed))


def _tle_from(table: dict, prefix: str, file, base_dir):
    if "tle" in table:
        if "tle_file" in table or "satellite" in table:
            bad = "tle_file" if "tle_file" in table else "satellite"
            raise ObjectError("given together with 'tle'", key=f"{prefix}.{bad}", file=file,
                              expected="either tle (the lines) or tle_file (+ satellite)")
        return parse_tle(table["tle"], key=f"{prefix}.tle", file=file)
    if "satellite" in table and "tle_file" not in table:
        raise ObjectError("'satellite' without 'tle_file'", key=f"{prefix}.satellite", file=file,
                          expected="tle_file = PATH together with satellite")
    path = table["tle_file"]
    if not isinstance(path, str):
        raise ObjectError(f"{path!r}", key=f"{prefix}.tle_file", file=file, expected="a file path string")
    p = Path(path)
    if not p.is_absolute() and base_dir is not None:
        p = Path(base_dir) / p
    sat = table.get("satellite")
    if sat is not None and not isinstance(sat, (int, str)):
        raise ObjectError(f"{sat!r}", key=f"{prefix}.satellite", file=file,
                          expected="a catalogue number or a satellite name")
    return load_tle(p, sat, key=f"{prefix}.tle_file", file=file)


def brightness_from_table(table: dict, prefix: str, *, file=None, has_orbit: bool) -> Brightness:
    """The :class:`Brightness` of an object table (``prefix`` like ``objects[0]``)."""
    given = [k for k in ("photons", "mag") if k in table] + (
        ["diameter_m/area_m2"] if ("diameter_m" in table or "area_m2" in table) else [])
    if len(given) != 1:
        raise ObjectError("no brightness given" if not given else f"several brightnesses given ({', '.join(given)})",
                          key=prefix, file=file, expected="exactly one of photons, mag, or diameter_m (or area_m2) "
                          "with albedo")
    kw: dict[str, Any] = {"key": prefix}
    if "photons" in table:
        kw["photons"] = _num(table, "photons", prefix, file, 0.0)
    elif "mag" in table:
        kw["mag"] = _num(table, "mag", prefix, file, -30.0, 40.0)
        system = table.get("mag_system", "ab")
        if system not in MAG_SYSTEMS:
            raise ObjectError(f"{system!r}", key=f"{prefix}.mag_system", file=file,
                              expected="'ab' (AB in the simulation band) or 'solar_v' (V of reflected sunlight)")
        kw["mag_system"] = system
    else:
        if "diameter_m" in table and "area_m2" in table:
            raise ObjectError("both diameter_m and area_m2 given", key=f"{prefix}.area_m2", file=file,
                              expected="one size: diameter_m (a sphere) or area_m2")
        kw["diameter_m"] = _num(table, "diameter_m", prefix, file, 0.0, 1e4, lo_open=True)
        kw["area_m2"] = _num(table, "area_m2", prefix, file, 0.0, 1e8, lo_open=True)
        kw["albedo"] = _num(table, "albedo", prefix, file, 0.0, 1.0, lo_open=True, required=True)
        pf = table.get("phase_function", "lambertian")
        if pf not in PHASE_FUNCTIONS:
            raise ObjectError(f"{pf!r}", key=f"{prefix}.phase_function", file=file,
                              expected="one of " + ", ".join(PHASE_FUNCTIONS))
        kw["phase_function"] = pf
        if "specular_fraction" in table:
            if pf != "mixed":
                raise ObjectError("only for phase_function = 'mixed'", key=f"{prefix}.specular_fraction", file=file,
                                  expected="phase_function = 'mixed' with specular_fraction in [0, 1]")
            kw["specular_fraction"] = _num(table, "specular_fraction", prefix, file, 0.0, 1.0)
        if "plate_normal" in table:
            if pf != "plate":
                raise ObjectError("only for phase_function = 'plate'", key=f"{prefix}.plate_normal", file=file,
                                  expected="phase_function = 'plate'")
            n = table["plate_normal"]
            vec_ok = (isinstance(n, list) and len(n) == 3 and all(isinstance(x, (int, float)) for x in n)
                      and any(x != 0 for x in n))
            if not (n in PLATE_NORMALS or vec_ok):
                raise ObjectError(f"{n!r}", key=f"{prefix}.plate_normal", file=file,
                                  expected="'sun', 'observer', 'bisector' or a GCRS vector [x, y, z]")
            if vec_ok and not has_orbit:
                raise ObjectError("a fixed normal needs an orbit (Sun and observer directions)",
                                  key=f"{prefix}.plate_normal", file=file, expected="'sun', 'observer' or 'bisector'")
            kw["plate_normal"] = tuple(float(x) for x in n) if vec_ok else n
        if not has_orbit:
            kw["range_km"] = _num(table, "range_km", prefix, file, 0.0, 1e10, lo_open=True, required=True)
            kw["phase_angle_deg"] = _num(table, "phase_angle_deg", prefix, file, 0.0, 180.0, required=True)
    if has_orbit:
        for k in ("range_km", "phase_angle_deg", "sun_distance_au"):
            if k in table:
                raise ObjectError("computed from the orbit for a TLE object", key=f"{prefix}.{k}", file=file,
                                  expected="no range_km/phase_angle_deg/sun_distance_au with tle or tle_file")
    else:
        kw.setdefault("range_km", _num(table, "range_km", prefix, file, 0.0, 1e10, lo_open=True))
        kw.setdefault("phase_angle_deg", _num(table, "phase_angle_deg", prefix, file, 0.0, 180.0))
        kw["sun_distance_au"] = _num(table, "sun_distance_au", prefix, file, 0.0, 1e3, lo_open=True, default=1.0)
    if "mag_system" in table and "mag" not in table:
        raise ObjectError("only with 'mag'", key=f"{prefix}.mag_system", file=file, expected="mag = ... with it")
    return Brightness(**{k: v for k, v in kw.items() if v is not None})


def object_from_table(table: dict, index: int, *, file: str | None = None, base_dir=None):
    """A :class:`RateObject` or :class:`TleObject` from the scene's ``objects[index]`` table.

    ``base_dir`` resolves a relative ``tle_file`` (pass the scene file's folder).
    """
    prefix = f"objects[{index}]"
    if not isinstance(table, dict):
        raise ObjectError(f"{table!r}", key=prefix, file=file, expected="a table ([[objects]])")
    _unknown(table, OBJECT_KEYS, prefix, file)
    name = table.get("name")
    if name is not None and not isinstance(name, str):
        raise ObjectError(f"{name!r}", key=f"{prefix}.name", file=file, expected="a string")
    has_rate = any(k in table for k in RATE_KEYS)
    has_tle = "tle" in table or "tle_file" in table
    if has_rate and has_tle:
        raise ObjectError("both RA/Dec keys and a TLE given", key=prefix, file=file,
                          expected="either ra_deg/dec_deg (+ rates) or tle / tle_file")
    if not has_rate and not has_tle:
        raise ObjectError("no position given", key=prefix, file=file,
                          expected="ra_deg and dec_deg (+ rate_ra_deg_s, rate_dec_deg_s), or tle, or tle_file")
    brightness = brightness_from_table(table, prefix, file=file, has_orbit=has_tle)
    light_curve_from_table(table.get("light_curve"), f"{prefix}.light_curve", file=file)
    if table.get("outside", "error") not in OUTSIDE_CHOICES:
        raise ObjectError(f"{table['outside']!r}", key=f"{prefix}.outside", file=file,
                          expected=" or ".join(repr(c) for c in OUTSIDE_CHOICES))
    if has_tle:
        return TleObject(_tle_from(table, prefix, file, base_dir), brightness, prefix, name)
    ra = _num(table, "ra_deg", prefix, file, 0.0, 360.0, required=True)
    dec = _num(table, "dec_deg", prefix, file, -90.0, 90.0, required=True)
    rra = _num(table, "rate_ra_deg_s", prefix, file, -180.0, 180.0, default=0.0)
    rdec = _num(table, "rate_dec_deg_s", prefix, file, -180.0, 180.0, default=0.0)
    return RateObject(ra % 360.0, dec, rra, rdec, brightness, prefix, name)


def observer_from_table(table: dict | None, *, file: str | None = None, base_dir=None, key: str = "observer"):
    """A :class:`GroundSite`, a :class:`SpaceObserver`, or None (no table: the geocentre)."""
    if table is None or table == {}:
        return None
    if not isinstance(table, dict):
        raise ObjectError(f"{table!r}", key=key, file=file, expected="a table [observer]")
    _unknown(table, OBSERVER_KEYS, key, file)
    name = table.get("name", "site")
    if not isinstance(name, str):
        raise ObjectError(f"{name!r}", key=f"{key}.name", file=file, expected="a string")
    ground = any(k in table for k in ("lat_deg", "lon_deg", "alt_m"))
    space = "tle" in table or "tle_file" in table
    if ground == space:
        raise ObjectError("both a ground site and a TLE given" if ground else "neither a site nor a TLE given",
                          key=key, file=file, expected="lat_deg, lon_deg (+ alt_m) for a ground site, or tle / "
                          "tle_file for a spacecraft")
    if space:
        return SpaceObserver(_tle_from(table, key, file, base_dir), table.get("name", "spacecraft"))
    return GroundSite(_num(table, "lat_deg", key, file, -90.0, 90.0, required=True),
                      _num(table, "lon_deg", key, file, -180.0, 360.0, required=True),
                      _num(table, "alt_m", key, file, -500.0, 1e5, default=0.0), name)
