"""Photometry: magnitudes to photo-electrons through the band, aperture, mirrors and QE.

AB magnitudes (Oke & Gunn 1983, ApJ 266, 713): f_nu = 3631 Jy x 10^(-0.4 m). The photon flux per unit
wavelength is f_nu / (h lambda), so the photo-electron rate of a source of magnitude ``m`` collected by an
area ``A`` with mirror throughput ``T`` and quantum efficiency ``QE(lambda)`` is

    N_e = A T 10^(-0.4 m) * 3631 Jy / h * integral QE(lambda) / lambda dlambda          (thesis eqs. 5-9)

for a flat-spectrum (AB) source. The sky background is the same with ``m`` per square arcsecond times the
pixel's solid angle (thesis eqs. 26-29).
"""

from __future__ import annotations

import numpy as np

JY = 1e-26  # W m^-2 Hz^-1
H_PLANCK = 6.62607015e-34  # J s
AB_ZERO_JY = 3631.0


def ab_electron_rate(mag: float, area_m2: float, throughput: float, wavelength_nm, qe) -> float:
    """Photo-electrons per second [e-/s] from a flat-spectrum source of AB magnitude ``mag``.

    Parameters
    ----------
    mag : AB magnitude [mag]
    area_m2 : clear collecting area [m^2]
    throughput : optical transmission, mirrors and filters [1]
    wavelength_nm, qe : the detector's QE curve [nm], [e-/photon]
    """
    lam = np.asarray(wavelength_nm, dtype=float)
    band = np.trapezoid(np.asarray(qe, dtype=float) / lam, lam)  # integral QE dlambda / lambda  [1]
    f_nu = AB_ZERO_JY * JY * 10 ** (-0.4 * mag)
    return float(area_m2 * throughput * f_nu / H_PLANCK * band)


def sky_electron_rate_per_pixel(mag_arcsec2: float, pixel_scale_arcsec: float, area_m2: float, throughput: float,
                                wavelength_nm, qe) -> float:
    """Sky background [e-/s/pixel] for a surface brightness in AB mag/arcsec^2 (thesis eqs. 26-29)."""
    return ab_electron_rate(mag_arcsec2, area_m2, throughput, wavelength_nm, qe) * pixel_scale_arcsec ** 2
