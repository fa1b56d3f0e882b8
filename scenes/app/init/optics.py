"""Optics of a scene from a lens, a refractor or a reflector: focal length, f-number, central obstruction.

The scene's geometry is a design TOML (``optics/designs/``); for a camera behind a lens or a refractor
the design written here is the equivalent clear aperture: a primary of diameter D = f / N and focal length f,
a central obstruction of diameter ``obstruction`` x D (0 for a lens or refractor), no spider. What it sets
are the first-order quantities a frame depends on: the plate scale (206265 / f arcsec/mm), the collecting
area pi/4 D^2 (1 - obstruction^2) and the diffraction limit. The diffraction core of an unobstructed circular
pupil has FWHM 1.029 lambda N (Airy; Born & Wolf 1999, sect. 8.5.2); the seeing and the optics' aberrations
(the measured Moffat, Racine 1996) dominate for every frame here, and the scene's PSF is that measured Moffat.
"""

from __future__ import annotations

import math


def airy_fwhm_arcsec(aperture_mm: float, wavelength_nm: float = 550.0) -> float:
    """FWHM of the Airy core, 1.029 lambda / D [arcsec]."""
    return 1.029 * wavelength_nm * 1e-9 / (aperture_mm * 1e-3) * 206264.806


def design_dict(focal_length_mm: float, f_number: float, obstruction: float = 0.0, *, sensor_mm=(36.0, 24.0),
                name: str = "lens") -> dict:
    """A design table (optics.design.Design) for a clear aperture of diameter f/N with a central obstruction."""
    if not 0 <= obstruction < 0.9:
        raise ValueError(f"obstruction {obstruction}: expected a fraction of the aperture diameter in [0, 0.9)")
    d = focal_length_mm / f_number
    tube = 1.2 * d + 20.0
    housing = max(30.0, 1.5 * max(sensor_mm))
    return {
        "name": name,
        "primary": {"diameter_mm": round(d, 4), "focal_length_mm": round(focal_length_mm, 4), "conic": -1.0},
        "secondary": {"minor_axis_mm": round(obstruction * d, 4),
                      "distance_to_focus_mm": round(max(tube / 2 + 1.0, min(0.3 * focal_length_mm, focal_length_mm - 1)), 4),
                      "offset_mm": 0.0},
        "spider": {"vanes": 0, "width_mm": 0.0},
        "tube": {"inner_diameter_mm": round(tube, 4), "length_mm": round(focal_length_mm + obstruction * d + 50.0, 4),
                 "focuser_diameter_mm": round(housing * 0.6, 3)},
        "baffle": {"vanes": 0, "vane_inner_diameter_mm": round(tube, 4)},
        "focal_plane": {"width_mm": round(sensor_mm[0], 4), "height_mm": round(sensor_mm[1], 4), "housing_mm": round(housing, 3)},
    }


def check_design(table: dict) -> None:
    from optics.design import Design

    Design.model_validate(table)


def collecting_area_m2(focal_length_mm: float, f_number: float, obstruction: float = 0.0) -> float:
    d = focal_length_mm / f_number * 1e-3
    return math.pi / 4 * d ** 2 * (1 - obstruction ** 2)
