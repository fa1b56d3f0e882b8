"""Brightness of debris and satellites: reflected sunlight, phase functions, photons at the aperture.

An object of cross-section (or plate area) ``A`` and reflectance (albedo) ``rho`` at range ``R`` from the
observer and distance ``r`` from the Sun sends the observer the fraction

    f = rho * A * F(phi) / R^2 * (1 au / r)^2                                            (McCue et al. 1971)

of the solar flux at 1 au, where ``F(phi)`` [1/sr] is the phase function at the phase angle ``phi``
(Sun-object-observer). ``F`` is normalised so that its integral over the sphere is the intercepted fraction
of the incident light: 1 for spheres (so the Bond albedo equals ``rho``), 1/2 for a randomly tumbling plate
(whose mean cross-section is A/2, Cauchy's theorem). Hence the magnitude (Hejduk 2011; McCue, Williams &
Morford 1971, Planet. Space Sci. 19, 851):

    m = m_sun - 2.5 log10( rho A F(phi) / R^2 )                          (thesis Annex III, eqs. 14-21)

Phase functions (reflectance rho; Hejduk 2011, AMOS conf., "Specular and diffuse components in spherical
satellite photometric modeling"; Cognion 2013, AMOS conf.):

* Lambertian (diffuse) sphere: F = 2 / (3 pi^2) [ (pi - phi) cos(phi) + sin(phi) ]  (F(0) = 2/(3 pi):
  geometric albedo p = pi F(0) rho = 2 rho / 3, Russell 1916, ApJ 43, 173);
* specular (mirror) sphere: F = 1 / (4 pi), isotropic (geometric albedo rho / 4);
* ``mixed``: beta F_specular + (1 - beta) F_diffuse, beta the specular fraction (Hejduk 2011);
* flat Lambertian plate of normal n (two-sided): F = max(0, (n.s)(n.o)) / pi for unit vectors to the Sun
  ``s`` and to the observer ``o``;
* tumbling plate (normal isotropic, two-sided): the orientation average of the plate,
  <F> = 1 / (3 pi^2) [ (pi - phi) cos(phi) + sin(phi) ], half the diffuse sphere's F with A the plate area
  (the sphere's surface elements are a one-sided plate averaged over all orientations).

Solar spectrum: a 5772 K blackbody scaled to the total solar irradiance 1361 W/m^2 at 1 au (IAU 2015
Resolution B3 nominal values, Prsa et al. 2016, AJ 152, 41). In a V-like band it is ~6 % fainter than the
measured Sun (it gives m_AB = -26.70 in a V-like band where the Sun is -26.77, Willmer 2018, ApJS 236, 47); pass the Sun's
measured AB magnitude in the band (``sun_ab_mag``) when that matters.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..photometry import AB_ZERO_JY, H_PLANCK, JY
from .errors import ObjectError
from .frames import R_EARTH_KM, R_SUN_KM

SOLAR_CONSTANT_W_M2 = 1361.0  # total solar irradiance at 1 au (IAU 2015 B3)
T_SUN_K = 5772.0  # nominal solar effective temperature (IAU 2015 B3)
M_SUN_V = -26.76  # apparent V magnitude of the Sun, Vega system (Willmer 2018, ApJS 236, 47, table 3)
C_M_S = 299792458.0
K_BOLTZMANN = 1.380649e-23  # J/K
SIGMA_SB = 5.670374419e-8  # W m^-2 K^-4

PHASE_FUNCTIONS = ("lambertian", "diffuse", "specular", "mixed", "tumbling_plate", "plate")
PLATE_NORMALS = ("sun", "observer", "bisector")


# ------------------------------------------------------------------------------------------ phase laws
def lambertian_sphere_phase(phase_rad):
    """Diffuse (Lambertian) sphere phase function F(phi) [1/sr], integral over the sphere = 1.

    F = 2 / (3 pi^2) [ (pi - phi) cos(phi) + sin(phi) ]   (Russell 1916; McCue et al. 1971; Hejduk 2011)
    """
    p = np.clip(np.asarray(phase_rad, dtype=float), 0.0, np.pi)
    return 2.0 / (3.0 * np.pi ** 2) * ((np.pi - p) * np.cos(p) + np.sin(p))


def specular_sphere_phase(phase_rad):
    """Specular (mirror) sphere phase function [1/sr]: 1 / (4 pi) at every phase angle (Hejduk 2011)."""
    return np.full_like(np.asarray(phase_rad, dtype=float), 1.0 / (4.0 * np.pi))


def tumbling_plate_phase(phase_rad):
    """Randomly tumbling two-sided Lambertian plate, orientation-averaged [1/sr], integral = 1/2.

    <max(0, (n.s)(n.o))> / pi over isotropic n = 1 / (3 pi^2) [ (pi - phi) cos(phi) + sin(phi) ].
    """
    return 0.5 * lambertian_sphere_phase(phase_rad)


def plate_phase(normal, sun_dir, obs_dir, *, two_sided: bool = True):
    """Flat Lambertian plate of unit normal ``normal`` [1/sr]: (n.s)(n.o) / pi when lit and seen, else 0.

    ``sun_dir`` and ``obs_dir`` are unit vectors from the object to the Sun and to the observer (..., 3).
    A two-sided plate shows its lit face whenever the Sun and the observer are on the same side.
    """
    n, s, o = (np.asarray(x, dtype=float) for x in (normal, sun_dir, obs_dir))
    ns, no = np.sum(n * s, axis=-1), np.sum(n * o, axis=-1)
    prod = ns * no if two_sided else np.maximum(ns, 0.0) * np.maximum(no, 0.0)
    return np.maximum(prod, 0.0) / np.pi


def phase_function(kind: str, phase_rad, *, specular_fraction: float = 0.0):
    """Phase function [1/sr] of a sphere or tumbling-plate model at ``phase_rad`` (see the module notes)."""
    if kind in ("lambertian", "diffuse"):
        return lambertian_sphere_phase(phase_rad)
    if kind == "specular":
        return specular_sphere_phase(phase_rad)
    if kind == "mixed":
        b = float(specular_fraction)
        return b * specular_sphere_phase(phase_rad) + (1.0 - b) * lambertian_sphere_phase(phase_rad)
    if kind == "tumbling_plate":
        return tumbling_plate_phase(phase_rad)
    raise ValueError(f"phase function {kind!r} needs geometry (use plate_phase) or is unknown")


# -------------------------------------------------------------------------------------------- shadow
def sunlit_fraction(r_obj_km, r_sun_km):
    """Fraction of the solar disc seen from the object past the Earth (1 sunlit, 0 umbra), shape (N,).

    Conical shadow with penumbra by the overlap of two discs (Montenbruck & Gill 2000, "Satellite Orbits",
    sec. 3.4.2): apparent radii a (Sun), b (Earth, a sphere of 6378.137 km, no atmosphere) and their
    separation c as seen from the object.
    """
    r = np.atleast_2d(np.asarray(r_obj_km, dtype=float))
    d_sun = np.atleast_2d(np.asarray(r_sun_km, dtype=float)) - r
    dist_sun, dist_earth = np.linalg.norm(d_sun, axis=-1), np.linalg.norm(r, axis=-1)
    a = np.arcsin(np.clip(R_SUN_KM / dist_sun, -1, 1))
    b = np.arcsin(np.clip(R_EARTH_KM / dist_earth, -1, 1))
    cosc = np.sum(-r * d_sun, axis=-1) / (dist_sun * dist_earth)
    c = np.arccos(np.clip(cosc, -1.0, 1.0))
    out = np.ones_like(c)
    umbra = c <= b - a
    annular = c < a - b
    partial = (~umbra) & (~annular) & (c < a + b)
    out[umbra] = 0.0
    out[annular] = 1.0 - (b[annular] / a[annular]) ** 2
    if np.any(partial):
        ap, bp, cp = a[partial], b[partial], c[partial]
        x = (cp ** 2 + ap ** 2 - bp ** 2) / (2.0 * cp)
        y = np.sqrt(np.maximum(ap ** 2 - x ** 2, 0.0))
        area = (ap ** 2 * np.arccos(np.clip(x / ap, -1, 1)) + bp ** 2 * np.arccos(np.clip((cp - x) / bp, -1, 1))
                - cp * y)
        out[partial] = 1.0 - area / (np.pi * ap ** 2)
    return np.clip(out, 0.0, 1.0)


# ---------------------------------------------------------------------------------------- the Sun's light
def solar_spectral_irradiance(wavelength_nm):
    """Solar spectral irradiance at 1 au [W m^-2 nm^-1]: a 5772 K blackbody normalised to 1361 W/m^2.

    E(lambda) = S0 * pi B_lambda(T) / (sigma T^4)  (the normalisation makes the integral over all
    wavelengths exactly S0; Prsa et al. 2016, AJ 152, 41).
    """
    lam = np.asarray(wavelength_nm, dtype=float) * 1e-9
    x = H_PLANCK * C_M_S / (lam * K_BOLTZMANN * T_SUN_K)
    b_lam = 2.0 * H_PLANCK * C_M_S ** 2 / lam ** 5 / np.expm1(x)  # W m^-2 sr^-1 m^-1
    return SOLAR_CONSTANT_W_M2 * np.pi * b_lam / (SIGMA_SB * T_SUN_K ** 4) * 1e-9


def _band(wavelength_nm, throughput, what="band"):
    lam = np.asarray(wavelength_nm, dtype=float)
    thr = np.broadcast_to(np.asarray(throughput, dtype=float), lam.shape)
    if lam.ndim != 1 or lam.size < 2 or np.any(np.diff(lam) <= 0) or np.any(lam <= 0):
        raise ValueError(f"{what}: wavelength_nm must be increasing positive values (got shape {lam.shape})")
    if np.any(thr < 0) or not np.any(thr > 0):
        raise ValueError(f"{what}: throughput must be >= 0 and not all zero")
    return lam, thr


def ab_photon_irradiance(mag, wavelength_nm, throughput):
    """Photons s^-1 m^-2 through the band from a flat-spectrum source of AB magnitude ``mag``.

    N = 3631 Jy 10^(-0.4 m) / h * integral T(lambda) / lambda dlambda  (Oke & Gunn 1983; as
    :func:`scenes.photometry.ab_electron_rate` with the band's throughput in place of the QE).
    """
    lam, thr = _band(wavelength_nm, throughput)
    return AB_ZERO_JY * JY * 10 ** (-0.4 * np.asarray(mag, dtype=float)) / H_PLANCK * np.trapezoid(thr / lam, lam)


def solar_photon_irradiance(wavelength_nm, throughput, *, sun_ab_mag: float | None = None) -> float:
    """Solar photons s^-1 m^-2 at 1 au through the band (``throughput`` dimensionless, per wavelength).

    The blackbody Sun by default, N = integral E(lambda) T(lambda) lambda / (h c) dlambda; or, when the
    Sun's measured AB magnitude in this band is given, the AB formula with it.
    """
    lam, thr = _band(wavelength_nm, throughput)
    if sun_ab_mag is not None:
        return float(ab_photon_irradiance(sun_ab_mag, lam, thr))
    e = solar_spectral_irradiance(lam)  # W m^-2 nm^-1
    return float(np.trapezoid(e * thr * lam * 1e-9 / (H_PLANCK * C_M_S), lam))


def sun_ab_magnitude(wavelength_nm, throughput) -> float:
    """AB magnitude of the (blackbody) Sun at 1 au in the band, photon-counting convention."""
    lam, thr = _band(wavelength_nm, throughput)
    return float(-2.5 * np.log10(solar_photon_irradiance(lam, thr) / ab_photon_irradiance(0.0, lam, thr)))


# ------------------------------------------------------------------------------------------ magnitudes
def sphere_area_m2(diameter_m: float) -> float:
    """Cross-section pi d^2 / 4 [m^2] of a sphere of diameter ``diameter_m`` [m]."""
    return math.pi * diameter_m ** 2 / 4.0


def reflected_fraction(area_m2, albedo, phase_value_sr, range_km, sun_distance_au=1.0):
    """Flux at the observer over the solar flux at 1 au [1]: rho A F / R^2 * (1 au / r)^2 (McCue et al. 1971).

    Parameters
    ----------
    area_m2 : cross-section of the sphere, or the plate's area [m^2]
    albedo : reflectance rho [1]
    phase_value_sr : phase function value F(phi) [1/sr]
    range_km : object-observer distance [km]
    sun_distance_au : object-Sun distance [au]
    """
    r_m = np.asarray(range_km, dtype=float) * 1e3
    return albedo * area_m2 * np.asarray(phase_value_sr, dtype=float) / r_m ** 2 / np.asarray(sun_distance_au) ** 2


def reflected_magnitude(fraction, m_sun: float = M_SUN_V):
    """Magnitude m = m_sun - 2.5 log10(fraction) [mag]; +inf for an unlit or unseen object."""
    f = np.asarray(fraction, dtype=float)
    with np.errstate(divide="ignore"):
        return np.where(f > 0, m_sun - 2.5 * np.log10(np.where(f > 0, f, 1.0)), np.inf)


def pixel_dwell_time_s(rate_deg_s, pixel_scale_arcsec: float, psf_fwhm_arcsec: float = 0.0,
                       exposure_time_s: float | None = None):
    """Time [s] the image of a moving point source spends on one pixel (thesis Annex VI).

    A source moving at angular rate ``omega`` relative to the detector crosses a pixel of angular size ``p``
    in p / omega; a PSF of FWHM ``w`` lights the pixel for about (p + w) / omega. The result is capped by
    the exposure time (a source slower than a pixel per exposure stays on it the whole time). The signal of
    a streak pixel is the photon rate times this time, against background and dark accumulated over the
    whole exposure: the SNR of a streak grows only with the dwell time (Shell 2010, Proc. SPIE 7826;
    Schildknecht 2007, A&A Rev. 14, 41).

    Parameters
    ----------
    rate_deg_s : angular rate on the detector [deg/s] (object rate minus tracking rate)
    pixel_scale_arcsec : pixel scale [arcsec/pixel]
    psf_fwhm_arcsec : PSF FWHM [arcsec], 0 for the pure pixel-crossing time
    exposure_time_s : cap [s]; none if omitted
    """
    rate_arcsec_s = np.abs(np.asarray(rate_deg_s, dtype=float)) * 3600.0
    with np.errstate(divide="ignore"):
        t = (pixel_scale_arcsec + psf_fwhm_arcsec) / rate_arcsec_s
    if exposure_time_s is not None:
        t = np.minimum(t, exposure_time_s)
    return t


# --------------------------------------------------------------------------------- object brightness spec
@dataclass(frozen=True)
class Brightness:
    """How bright an object is: exactly one of ``photons``, ``mag`` or a size (diameter or area + albedo).

    Attributes
    ----------
    photons : total photons at the aperture over the exposure (the scene contract's ``photons``)
    mag : magnitude, constant over the exposure, in ``mag_system``: ``"ab"`` (AB in the simulation band,
        as the stars of :mod:`scenes.photometry`) or ``"solar_v"`` (Johnson V, Vega, of a grey reflector of
        sunlight: photons = Sun's photons in the band x 10^(-0.4 (mag - M_SUN_V)))
    diameter_m / area_m2 : sphere diameter [m] (cross-section pi d^2 / 4), or area [m^2] (cross-section of a
        sphere, area of a plate)
    albedo : reflectance [1]
    phase_function : one of ``PHASE_FUNCTIONS``
    specular_fraction : beta of the ``mixed`` model [1]
    plate_normal : for ``plate``: ``"sun"`` (sun-pointing panel), ``"observer"``, ``"bisector"`` (specular
        glint geometry) or a GCRS unit vector (3 numbers, inertially fixed)
    range_km, phase_angle_deg, sun_distance_au : geometry for objects without an orbit (RA/Dec + rates)
    """

    photons: float | None = None
    mag: float | None = None
    mag_system: str = "ab"
    diameter_m: float | None = None
    area_m2: float | None = None
    albedo: float | None = None
    phase_function: str = "lambertian"
    specular_fraction: float = 0.0
    plate_normal: str | tuple = "sun"
    range_km: float | None = None
    phase_angle_deg: float | None = None
    sun_distance_au: float = 1.0
    key: str = field(default="objects[0]", compare=False)

    @property
    def kind(self) -> str:
        return "photons" if self.photons is not None else "mag" if self.mag is not None else "size"

    @property
    def cross_section_m2(self) -> float | None:
        return self.area_m2 if self.area_m2 is not None else (
            sphere_area_m2(self.diameter_m) if self.diameter_m is not None else None)

    def phase_values(self, track) -> np.ndarray:
        """F [1/sr] at the track's samples (needs its phase angle, or Sun/observer directions for plates)."""
        if track.phase_angle_deg is None:
            raise ObjectError("the object's phase angle is unknown (no orbit)", key=f"{self.key}.phase_angle_deg",
                              expected="phase_angle_deg and range_km for a size-based object given by RA/Dec")
        phi = np.radians(track.phase_angle_deg)
        if self.phase_function != "plate":
            return phase_function(self.phase_function, phi, specular_fraction=self.specular_fraction)
        if isinstance(self.plate_normal, str):  # depends on the phase angle only
            c = np.cos(phi / 2.0) ** 2 if self.plate_normal == "bisector" else np.cos(phi)
            return np.maximum(c, 0.0) / np.pi
        if track.sun_dir is None:
            raise ObjectError("a fixed plate normal needs the Sun and observer directions (an orbit)",
                              key=f"{self.key}.plate_normal", expected="'sun', 'observer' or 'bisector'")
        n = np.asarray(self.plate_normal, dtype=float)
        return plate_phase(n / np.linalg.norm(n), track.sun_dir, track.observer_dir)

    def reflected_fraction(self, track) -> np.ndarray:
        """Flux at the observer / solar flux at 1 au at each track sample, Earth shadow included."""
        area = self.cross_section_m2
        if track.range_km is None:
            raise ObjectError("the object's range is unknown (no orbit)", key=f"{self.key}.range_km",
                              expected="range_km and phase_angle_deg for a size-based object given by RA/Dec")
        sun_au = track.sun_distance_au if track.sun_distance_au is not None else self.sun_distance_au
        f = reflected_fraction(area, self.albedo, self.phase_values(track), track.range_km, sun_au)
        return f * track.sunlit_fraction

    def magnitude(self, track, m_sun: float = M_SUN_V) -> np.ndarray:
        """Magnitude at each sample [mag] (``m_sun`` the Sun's in the wanted band; V by default).

        Constant for ``mag``; for ``photons`` there is no band-free magnitude (NaN).
        """
        n = len(track.t_s)
        if self.kind == "mag":
            return np.full(n, float(self.mag))
        if self.kind == "photons":
            return np.full(n, np.nan)
        return reflected_magnitude(self.reflected_fraction(track), m_sun)

    def photon_rate(self, track, *, aperture_area_m2: float, wavelength_nm, throughput,
                    exposure_time_s: float | None = None, sun_ab_mag: float | None = None) -> np.ndarray:
        """Photons per second [1/s] entering an aperture of ``aperture_area_m2`` at each track sample.

        Parameters
        ----------
        track : the object's :class:`~scenes.objects.track.Track`
        aperture_area_m2 : clear collecting area [m^2] (used by ``mag`` and size-based objects)
        wavelength_nm, throughput : the band [nm] and its dimensionless response; pass 1 (or a filter curve)
            for photons, QE x mirror reflectance for photo-electrons
        exposure_time_s : for ``photons`` objects: the time over which the total is spread [s]
            (default: the track's exposure time)
        sun_ab_mag : the Sun's AB magnitude in the band, instead of the 5772 K blackbody
        """
        n = len(track.t_s)
        if self.kind == "photons":
            t_exp = track.exposure_time_s if exposure_time_s is None else exposure_time_s
            return np.full(n, float(self.photons) / t_exp)
        if self.kind == "mag" and self.mag_system == "ab":
            return np.full(n, float(ab_photon_irradiance(self.mag, wavelength_nm, throughput)) * aperture_area_m2)
        sun = solar_photon_irradiance(wavelength_nm, throughput, sun_ab_mag=sun_ab_mag) * aperture_area_m2
        if self.kind == "mag":  # solar_v: grey reflector of sunlight of V magnitude mag
            return np.full(n, sun * 10 ** (-0.4 * (float(self.mag) - M_SUN_V)))
        return sun * self.reflected_fraction(track)
