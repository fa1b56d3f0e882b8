"""Optical glasses: refractive index from the Sellmeier equation.

n^2(lambda) - 1 = sum_i B_i lambda^2 / (lambda^2 - C_i),   lambda in micrometres.

Coefficients: SCHOTT optical glass data sheets (2017 catalogue) for the N- glasses; Malitson,
J. Opt. Soc. Am. 55, 1205 (1965), doi:10.1364/JOSA.55.001205, for fused silica. Tests check the
catalogue's n_d (587.56 nm) and Abbe numbers V_d = (n_d - 1)/(n_F - n_C).
"""

from __future__ import annotations

import numpy as np

#: name -> (B1, B2, B3, C1, C2, C3), C in um^2
GLASSES: dict[str, tuple[float, float, float, float, float, float]] = {
    "N-BK7": (1.03961212, 0.231792344, 1.01046945, 0.00600069867, 0.0200179144, 103.560653),
    "N-BAK4": (1.28834642, 0.132817724, 0.945395373, 0.00779980626, 0.0315631177, 105.965875),
    "N-SK16": (1.34317774, 0.241144399, 0.994317969, 0.00704687339, 0.0229005, 92.7508526),
    "N-FK51A": (0.971247817, 0.216901417, 0.904651666, 0.00472301995, 0.0153575612, 168.68133),
    "N-F2": (1.39757037, 0.159201403, 1.2686543, 0.00995906143, 0.0546931752, 119.248346),
    "N-SF5": (1.52481889, 0.187085527, 1.42729015, 0.011254756, 0.0588995392, 129.141675),
    "FUSED_SILICA": (0.6961663, 0.4079426, 0.8974794, 0.0684043 ** 2, 0.1162414 ** 2, 9.896161 ** 2),
}


def index(material: str, wavelength_nm):
    """Refractive index of ``material`` ('air' -> 1) at ``wavelength_nm`` [nm] (scalar or array)."""
    if material.lower() == "air":
        return np.ones_like(np.asarray(wavelength_nm, dtype=float)) if np.ndim(wavelength_nm) else 1.0
    try:
        b1, b2, b3, c1, c2, c3 = GLASSES[material.upper()]
    except KeyError:
        raise KeyError(f"unknown glass '{material}' (known: air, {', '.join(sorted(GLASSES))})") from None
    lam2 = (np.asarray(wavelength_nm, dtype=float) * 1e-3) ** 2
    n = np.sqrt(1 + b1 * lam2 / (lam2 - c1) + b2 * lam2 / (lam2 - c2) + b3 * lam2 / (lam2 - c3))
    return float(n) if np.ndim(n) == 0 else n
