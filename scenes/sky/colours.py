"""Stellar colours and temperatures: colour -> Teff relations and the mean dwarf sequence.

Physics
-------
Each star is rendered as a blackbody (``scenes.sky.starflux``), so it needs one temperature. It is derived
from the catalogue colour:

* Gaia BP-RP: interpolation (in log Teff) of the mean dwarf colour-temperature sequence of Pecaut &
  Mamajek (2013, ApJS 208, 9, Table 5), in the updated online version "A Modern Mean Dwarf Stellar Color and
  Effective Temperature Sequence" (E. Mamajek, v2024.05.15, Bp-Rp column from Gaia DR2 photometry).
  The table gives Bp-Rp from B9V (-0.12 mag, 10700 K) to M8V (4.86 mag, 2570 K). For the hotter O9V-B8V rows
  (no Bp-Rp in the table) Bp-Rp is extrapolated from B-V with the B9V-A0V slope,
  ``BP-RP = -0.120 + 1.19 (B-V + 0.070)``. Outside the sequence the colour is clipped (2570-33300 K).
* Johnson B-V (Hipparcos stars without Gaia photometry): Ballesteros (2012, EPL 97, 34008),
  ``T = 4600 K [1 / (0.92 (B-V) + 1.7) + 1 / (0.92 (B-V) + 0.62)]``, a blackbody-based relation, so it is
  the temperature of the blackbody with that colour (5778 K for the Sun's B-V = 0.65).
* No colour: ``FALLBACK_TEFF_K``, the temperature of BP-RP = 1.0 (a K0V dwarf, ~5260 K), near the median
  colour of field stars (1.15 for the built-in catalogue's G < 10 stars, 1.26 for the faint-star model at
  the galactic pole). Few stars need it: the built-in catalogue has BP-RP or B-V for 99.9 % of its stars.

Reddening is not removed: the temperature is that of the *observed* colour, which is what shapes the
spectrum across the detector's band.

The same dwarf sequence gives the synthetic faint stars their colours (``scenes.sky.starcounts``):
absolute magnitude M_V -> G-V and BP-RP. The values are copied from the table cited above.
"""

from __future__ import annotations

import numpy as np

# Pecaut & Mamajek (2013) / Mamajek online table v2024.05.15:  SpT, Teff [K], M_V, B-V, G-V, Bp-Rp
# (Bp-Rp of O9V..B8V: extrapolated from B-V, see the module docstring).
_SEQUENCE = [
    ("O9V", 33300, -4.20, -0.312, 0.010, None),
    ("B0V", 31400, -3.90, -0.301, 0.010, None),
    ("B1V", 26000, -3.00, -0.278, 0.000, None),
    ("B2V", 20600, -1.80, -0.215, 0.015, None),
    ("B3V", 17000, -1.20, -0.178, 0.010, None),
    ("B5V", 15700, -0.85, -0.156, 0.013, None),
    ("B8V", 12300, 0.00, -0.109, 0.020, None),
    ("B9V", 10700, 0.50, -0.070, 0.020, -0.120),
    ("A0V", 9700, 0.99, 0.000, 0.015, -0.037),
    ("A2V", 8840, 1.35, 0.070, 0.000, 0.068),
    ("A5V", 8100, 2.01, 0.160, -0.015, 0.194),
    ("A7V", 7760, 2.23, 0.210, -0.030, 0.263),
    ("F0V", 7220, 2.57, 0.295, -0.060, 0.377),
    ("F2V", 6820, 2.97, 0.370, -0.080, 0.490),
    ("F5V", 6550, 3.37, 0.440, -0.110, 0.587),
    ("F8V", 6180, 4.05, 0.530, -0.127, 0.694),
    ("G0V", 5930, 4.48, 0.595, -0.155, 0.784),
    ("G2V", 5770, 4.80, 0.650, -0.155, 0.823),
    ("G5V", 5660, 4.98, 0.680, -0.160, 0.850),
    ("G8V", 5480, 5.30, 0.730, -0.200, 0.900),
    ("K0V", 5290, 5.78, 0.816, -0.210, 0.983),
    ("K2V", 5100, 6.07, 0.884, -0.250, 1.100),
    ("K3V", 4870, 6.53, 0.990, -0.310, 1.190),
    ("K5V", 4440, 7.28, 1.150, -0.430, 1.430),
    ("K7V", 4090, 8.20, 1.340, -0.590, 1.700),
    ("M0V", 3850, 8.80, 1.420, -0.690, 1.840),
    ("M1V", 3660, 9.64, 1.485, -0.810, 2.090),
    ("M2V", 3560, 10.21, 1.505, -0.925, 2.230),
    ("M3V", 3430, 11.15, 1.530, -1.100, 2.500),
    ("M4V", 3210, 12.61, 1.650, -1.400, 2.940),
    ("M5V", 3060, 14.15, 1.830, -1.700, 3.350),
    ("M6V", 2810, 16.32, 2.010, -2.370, 4.160),
    ("M7V", 2680, 17.70, 2.120, -2.980, 4.650),
    ("M8V", 2570, 18.60, 2.150, -3.110, 4.860),
]

SEQ_SPT = tuple(row[0] for row in _SEQUENCE)
SEQ_TEFF_K = np.array([row[1] for row in _SEQUENCE], dtype=float)
SEQ_MV = np.array([row[2] for row in _SEQUENCE], dtype=float)
SEQ_B_V = np.array([row[3] for row in _SEQUENCE], dtype=float)
SEQ_G_V = np.array([row[4] for row in _SEQUENCE], dtype=float)
SEQ_BP_RP = np.array([row[5] if row[5] is not None else -0.120 + 1.19 * (row[3] + 0.070) for row in _SEQUENCE],
                     dtype=float)

#: BP-RP given to stars without any colour, and its temperature (a K0V dwarf)
FALLBACK_BP_RP = 1.0
#: colour of the red giants (red clump / K giants) in the faint-star model [mag] (Gaia DR2 HRD, A&A 616, A10)
GIANT_BP_RP = 1.20


def teff_from_bp_rp(bp_rp) -> np.ndarray:
    """Effective temperature [K] from the Gaia BP-RP colour [mag] (dwarf sequence, Pecaut & Mamajek 2013).

    Piecewise-linear interpolation of log10(Teff) in the mean dwarf sequence; colours outside the sequence
    (-0.41 .. 4.86 mag) are clipped to its ends; NaN colours give ``FALLBACK_TEFF_K``.

    Parameters
    ----------
    bp_rp : array_like
        G_BP - G_RP [mag].

    Returns
    -------
    numpy.ndarray
        Teff [K], same shape as ``bp_rp``.
    """
    c = np.asarray(bp_rp, dtype=float)
    c = np.where(np.isfinite(c), c, FALLBACK_BP_RP)
    return 10 ** np.interp(c, SEQ_BP_RP, np.log10(SEQ_TEFF_K))


def teff_from_b_v(b_v) -> np.ndarray:
    """Blackbody temperature [K] from Johnson B-V [mag]: Ballesteros (2012, EPL 97, 34008).

    ``T = 4600 K [1 / (0.92 (B-V) + 1.7) + 1 / (0.92 (B-V) + 0.62)]``. B-V is clipped to [-0.4, 2.0]
    (the formula's poles are at B-V = -0.67 and -1.85); NaN gives ``FALLBACK_TEFF_K``.

    Parameters
    ----------
    b_v : array_like
        B - V [mag].
    """
    bv = np.asarray(b_v, dtype=float)
    t = 4600.0 * (1.0 / (0.92 * np.clip(bv, -0.4, 2.0) + 1.7) + 1.0 / (0.92 * np.clip(bv, -0.4, 2.0) + 0.62))
    return np.where(np.isfinite(bv), t, FALLBACK_TEFF_K)


def bp_rp_from_teff(teff_k) -> np.ndarray:
    """Inverse of :func:`teff_from_bp_rp` on the dwarf sequence (BP-RP [mag] from Teff [K])."""
    lt = np.log10(np.asarray(teff_k, dtype=float))
    return np.interp(lt, np.log10(SEQ_TEFF_K[::-1]), SEQ_BP_RP[::-1])


def dwarf_colours_from_mv(mv) -> tuple[np.ndarray, np.ndarray]:
    """(G-V, BP-RP) [mag] of a main-sequence star of absolute magnitude ``mv`` [mag] (clipped to O9V..M8V)."""
    m = np.asarray(mv, dtype=float)
    return np.interp(m, SEQ_MV, SEQ_G_V), np.interp(m, SEQ_MV, SEQ_BP_RP)


def g_minus_v_from_bp_rp(bp_rp) -> np.ndarray:
    """G - V [mag] from BP-RP: Riello et al. (2021, A&A 649, A3), Appendix C (valid -0.5 < BP-RP < 2.75)."""
    c = np.clip(np.asarray(bp_rp, dtype=float), -0.5, 2.75)
    return -0.02704 + 0.01424 * c - 0.2156 * c ** 2 + 0.01426 * c ** 3


FALLBACK_TEFF_K = float(teff_from_bp_rp(FALLBACK_BP_RP))
