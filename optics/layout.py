"""Where every part of the telescope sits: first-order layout derived from a :class:`Design`.

Frame (millimetres): the primary's vertex at the origin, +z up the tube toward the sky, the diagonal
folding the beam toward +x (the focuser side), +y completing a right-handed frame.

Focal-plane coordinates (u, v) [mm]: ``u = z - z_axis`` along the folded beam's "unfolded x", ``v = y``.
They equal the coordinates an unfolded primary-focus camera would see, so the image of a star at field
angle (theta_x, theta_y) sits near (u, v) = -f (tan theta_x, tan theta_y).

Pure Python and numpy: no Mitsuba here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .design import Design, surface_sag
from .glass import index as glass_index

SQRT2 = math.sqrt(2.0)


@dataclass(frozen=True)
class LensSurface:
    """A corrector surface on the focuser axis: vertex at ``x_mm``, radius (0 = plane), media around it."""

    x_mm: float
    radius_mm: float
    semi_diameter_mm: float
    before: str     # medium the light comes from
    after: str      # medium it enters

    def eta(self, wavelength_nm: float) -> float:
        """Relative index n_after / n_before [1]."""
        return glass_index(self.after, wavelength_nm) / glass_index(self.before, wavelength_nm)

    @property
    def x_edge_mm(self) -> float:
        """x of the surface's rim (vertex plus the sag at the clear semi-diameter) [mm]."""
        return self.x_mm + surface_sag(self.radius_mm, self.semi_diameter_mm)


@dataclass(frozen=True)
class Layout:
    """Positions and sizes of every part [mm] (see module docstring for the frame)."""

    design: Design
    focal_length: float
    conic: float
    r_primary: float          # clear semi-aperture of the primary
    primary_edge_depth: float  # mirror thickness below the rim
    z_axis: float             # height of the focuser axis (diagonal centre on the optical axis)
    diag_centre: tuple        # centre of the elliptical outline (x, y, z)
    diag_normal: tuple        # unit normal of the reflecting face (toward -z and +x)
    diag_b: float             # semi-minor axis (along y)
    diag_a: float             # semi-major axis (in the x-z plane)
    holder_top: float         # z of the holder's top cap
    spider_z: tuple           # (z_low, z_high) of the spider vanes
    spider_angles_deg: tuple
    spider_half_width: float
    r_tube: float
    tube_top: float
    tube_bottom: float        # cell back plate
    r_focuser: float
    x_housing: float          # front plate of the camera housing (focuser tube ends here)
    housing_half: float
    x_detector: float         # detector plane (x = const)
    detector_half: tuple      # (half width along u, half height along v)
    vane_z: tuple             # heights of the annular baffle vanes
    r_vane: float
    lenses: tuple             # LensSurface, in order from the diagonal

    @property
    def focuser_start_x(self) -> float:
        """Inner end of the focuser bore: at the tube wall, or further in when the corrector reaches in."""
        x_wall = math.sqrt(max(self.r_tube ** 2 - self.r_focuser ** 2, 0.0))
        if self.lenses:
            return min(x_wall, min(self.lenses[0].x_mm, self.lenses[0].x_edge_mm) - 5.0)
        return x_wall

    # ---- helpers -------------------------------------------------------------------------------------
    def primary_sag(self, r):
        """Height of the primary's surface at radius ``r`` [mm] (conic sag, R = 2f)."""
        c = 1.0 / (2.0 * self.focal_length)
        r2 = np.asarray(r, dtype=float) ** 2
        return c * r2 / (1.0 + np.sqrt(np.maximum(1.0 - (1.0 + self.conic) * c * c * r2, 0.0)))


def make_layout(design: Design) -> Layout:
    """Derive the telescope's layout from its design file."""
    p, s, sp, t, b = design.primary, design.secondary, design.spider, design.tube, design.baffle
    f = p.focal_length_mm
    d = s.distance_to_focus_mm
    z_axis = f - d
    bsemi = s.minor_axis_mm / 2.0
    asemi = bsemi * SQRT2
    off = s.offset_mm
    centre = (-off / SQRT2 * 1.0, 0.0, z_axis - off / SQRT2)
    normal = (1.0 / SQRT2, 0.0, -1.0 / SQRT2)
    holder_top = centre[2] + bsemi + s.holder_length_mm
    spider_z = (holder_top - sp.depth_mm, holder_top)
    angles = tuple(sp.angle_deg + 360.0 * k / sp.vanes for k in range(sp.vanes)) if sp.vanes else ()
    x_det = d + design.focal_plane.defocus_mm
    # corrector: surfaces listed from the diagonal; last one back_focus_mm before the detector
    lenses = []
    c = design.corrector
    if c.enabled and c.surfaces:
        x = x_det - c.back_focus_mm - sum(srf.thickness_mm for srf in c.surfaces[:-1])
        medium = "air"
        for srf in c.surfaces:
            lenses.append(LensSurface(x, srf.radius_mm, srf.semi_diameter_mm, medium, srf.material))
            medium = srf.material
            x += srf.thickness_mm
    r_tube = t.inner_diameter_mm / 2.0
    zone0 = b.zone_start_mm if b.zone_start_mm is not None else min(spider_z[1] + 20.0, t.length_mm - 1.0)
    vane_z = tuple(np.linspace(zone0, t.length_mm, b.vanes).tolist()) if b.vanes > 1 else \
        ((t.length_mm,) if b.vanes == 1 else ())
    housing_half = design.focal_plane.housing_mm / 2.0
    # the camera housing's front plate: behind the whole lens stack (vertices and rims), before the detector
    if lenses:
        stack_end = max(max(s.x_mm, s.x_edge_mm) for s in lenses)
        x_housing = stack_end + min(5.0, 0.5 * (x_det - stack_end))
    else:
        x_housing = x_det - min(40.0, 0.5 * (x_det - r_tube))
    x_housing = max(x_housing, r_tube + 5.0)
    return Layout(
        design=design, focal_length=f, conic=p.conic, r_primary=p.diameter_mm / 2.0,
        primary_edge_depth=p.diameter_mm / 8.0, z_axis=z_axis, diag_centre=centre, diag_normal=normal,
        diag_b=bsemi, diag_a=asemi, holder_top=holder_top, spider_z=spider_z, spider_angles_deg=angles,
        spider_half_width=sp.width_mm / 2.0, r_tube=r_tube, tube_top=t.length_mm,
        tube_bottom=-t.cell_depth_mm, r_focuser=t.focuser_diameter_mm / 2.0, x_housing=x_housing,
        housing_half=housing_half, x_detector=x_det,
        detector_half=(design.focal_plane.width_mm / 2.0, design.focal_plane.height_mm / 2.0),
        vane_z=vane_z, r_vane=b.vane_inner_diameter_mm / 2.0, lenses=tuple(lenses))
