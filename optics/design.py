"""Telescope design files (TOML): geometry is data, not code (DESIGN.md convention 7).

``load_design("art")`` reads a built-in design from ``optics/designs/``; any other string is a path.
Inconsistent designs get an :class:`OpticsError` naming the file and the field.
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path
from typing import Literal

import tomllib
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from .bsdf import MIRROR_LOBE_B, MIRROR_LOBE_G

BUILTIN = Path(__file__).with_name("designs")


class OpticsError(ValueError):
    """A user error in a design file: names the file and the field."""


class _Table(BaseModel):
    model_config = ConfigDict(extra="forbid")


class Primary(_Table):
    diameter_mm: float = Field(gt=0, le=20_000)
    focal_length_mm: float = Field(gt=0, le=200_000)
    conic: float = Field(-1.0, ge=-10, le=10)


class Secondary(_Table):
    """Flat elliptical diagonal at 45 degrees; the folded beam leaves toward +x (the focuser side)."""
    minor_axis_mm: float = Field(ge=0)
    distance_to_focus_mm: float = Field(gt=0, description="diagonal centre (on the axis) to the detector")
    offset_mm: float = Field(0.0, description="shift of the ellipse centre along its major axis, away "
                             "from the focuser and toward the primary")
    holder_length_mm: float = Field(40.0, ge=0, description="cylindrical holder behind the diagonal")


class Spider(_Table):
    vanes: int = Field(4, ge=0, le=16)
    width_mm: float = Field(2.0, ge=0, description="vane thickness across the beam")
    depth_mm: float = Field(25.0, gt=0, description="vane extent along the optical axis")
    angle_deg: float = Field(0.0, description="azimuth of the first vane from +x (focuser side)")


class Tube(_Table):
    inner_diameter_mm: float = Field(gt=0)
    length_mm: float = Field(gt=0, description="primary vertex to the tube front")
    focuser_diameter_mm: float = Field(90.0, gt=0, description="side opening and focuser tube bore")
    cell_depth_mm: float = Field(60.0, ge=0, description="primary cell: back plate this far below the vertex")


class Baffle(_Table):
    vanes: int = Field(0, ge=0, le=200)
    vane_inner_diameter_mm: float = Field(gt=0)
    zone_start_mm: float | None = Field(None, gt=0, description="lowest vane height above the primary "
                                        "vertex (default: just above the spider)")


class Coatings(_Table):
    mirror_reflectance: float = Field(0.92, ge=0, le=1)
    mirror_roughness_nm: float = Field(2.0, ge=0, le=1000)
    black_model: Literal["lambertian", "abg"] = "lambertian"
    black_reflectance: float = Field(0.04, ge=0, le=1)
    abg_a: float = Field(0.001, ge=0)
    abg_b: float = Field(0.001, gt=0)
    abg_g: float = Field(2.0, gt=0, le=10)
    mirror_lobe_b: float = Field(MIRROR_LOBE_B, gt=0, description="shoulder B of the mirrors' "
                                 "microroughness lobe 1 / (B + x**g) (optics.bsdf eq. 2)")
    mirror_lobe_g: float = Field(MIRROR_LOBE_G, gt=0, le=10, description="slope g of that lobe")


class FocalPlane(_Table):
    width_mm: float = Field(gt=0)
    height_mm: float = Field(gt=0)
    housing_mm: float = Field(120.0, gt=0, description="side of the square camera housing around the sensor")
    defocus_mm: float = Field(0.0, description="detector (with the corrector) moved away from the diagonal")


class Surface(_Table):
    """One refracting surface of the corrector, listed from the diagonal toward the detector."""
    radius_mm: float = Field(0.0, description="vertex radius of curvature, + when the centre lies toward "
                             "the detector; 0 = plane")
    thickness_mm: float = Field(ge=0, description="axial distance to the next surface")
    material: str = Field("air", description="medium after this surface: 'air' or a glass of optics.glass")
    semi_diameter_mm: float = Field(40.0, gt=0)


#: Reflectance of one anti-reflection-coated lens surface (a broadband multilayer: 0.2-1 % over 450-900 nm)
AR_REFLECTANCE = 0.005


class Corrector(_Table):
    """Refractive field corrector in the focuser; the last surface is ``back_focus_mm`` before the detector.

    ``ar_reflectance`` is each glass-air surface's reflectance with its anti-reflection coating [1],
    taken as independent of angle and wavelength (rays meet art's surfaces at up to 36 degrees, where a
    broadband multilayer's reflectance may double: below a percent of throughput per surface);
    ``"uncoated"`` uses the bare glass's Fresnel reflectance instead (4-6 % per surface: eight uncoated
    surfaces transmit only ~0.68).
    """
    enabled: bool = False
    surfaces: list[Surface] = []
    back_focus_mm: float = Field(30.0, gt=0)
    ar_reflectance: float | Literal["uncoated"] = Field(AR_REFLECTANCE, description="reflectance per "
                                                        "coated surface [1], or 'uncoated' (Fresnel)")

    @property
    def coated(self) -> bool:
        return self.ar_reflectance != "uncoated"


class Perturbation(_Table):
    """Misalignments of the optics relative to the nominal design (all zero by default).

    Frame of :mod:`optics.layout`: x toward the focuser, z up the tube, y completing the right-handed
    frame; the sensor's axes are x = u (along z) and y = v (along y). Rotations are right-handed about
    the named axis through the part's pivot:

    * primary: decentre along frame x/y; tilt about frame x/y through the vertex (an on-axis star's
      image moves by f tan(2 tilt), the reflected beam turns by twice the tilt);
    * diagonal: tilt about its major axis (``_x``, in the x-z plane, seen from the sky along x) and about
      its minor axis (``_y``, frame y) through the ellipse's centre; ``_y`` changes the fold angle (the
      image moves along u), ``_x`` throws the beam sideways (along v);
    * sensor: piston along the beam (+ = away from the mirror, i.e. farther from the diagonal), tilt
      about the sensor's x (u) and y (v) axes through its centre;
    * corrector (designs with a corrector only): decentre along the sensor's x/y, tilt about them
      through the middle of the lens stack, and ``corrector_spacing_mm``: the corrector-to-sensor
      spacing (back focus) grows by this much (the whole lens group moves toward the diagonal).
    """
    primary_decenter_x_mm: float = Field(0.0, ge=-50, le=50)
    primary_decenter_y_mm: float = Field(0.0, ge=-50, le=50)
    primary_tilt_x_deg: float = Field(0.0, ge=-5, le=5)
    primary_tilt_y_deg: float = Field(0.0, ge=-5, le=5)
    diagonal_tilt_x_deg: float = Field(0.0, ge=-5, le=5)
    diagonal_tilt_y_deg: float = Field(0.0, ge=-5, le=5)
    sensor_piston_um: float = Field(0.0, ge=-20_000, le=20_000)
    sensor_tilt_x_deg: float = Field(0.0, ge=-10, le=10)
    sensor_tilt_y_deg: float = Field(0.0, ge=-10, le=10)
    corrector_decenter_x_mm: float = Field(0.0, ge=-20, le=20)
    corrector_decenter_y_mm: float = Field(0.0, ge=-20, le=20)
    corrector_tilt_x_deg: float = Field(0.0, ge=-10, le=10)
    corrector_tilt_y_deg: float = Field(0.0, ge=-10, le=10)
    corrector_spacing_mm: float = Field(0.0, ge=-20, le=20)

    @property
    def is_zero(self) -> bool:
        return not any(self.model_dump().values())


#: names of the perturbation parameters, in the order of :class:`Perturbation`
PERTURBATION_NAMES = tuple(Perturbation.model_fields)
CORRECTOR_PERTURBATIONS = tuple(n for n in PERTURBATION_NAMES if n.startswith("corrector_"))


class Design(_Table):
    """A Newtonian telescope: see DESIGN.md, "Design file"."""

    name: str = "custom"
    primary: Primary
    secondary: Secondary
    spider: Spider = Spider()
    tube: Tube
    baffle: Baffle
    coatings: Coatings = Coatings()
    focal_plane: FocalPlane
    corrector: Corrector = Corrector()
    perturbation: Perturbation = Perturbation()

    @model_validator(mode="after")
    def _consistent(self):
        p, s, t = self.primary, self.secondary, self.tube
        if s.minor_axis_mm >= p.diameter_mm:
            raise ValueError("secondary.minor_axis_mm must be smaller than primary.diameter_mm")
        if t.inner_diameter_mm < p.diameter_mm:
            raise ValueError("tube.inner_diameter_mm must be at least primary.diameter_mm")
        if s.distance_to_focus_mm >= p.focal_length_mm:
            raise ValueError("secondary.distance_to_focus_mm must be shorter than primary.focal_length_mm")
        if s.distance_to_focus_mm < t.inner_diameter_mm / 2:
            raise ValueError("secondary.distance_to_focus_mm puts the focus inside the tube wall "
                             f"(needs >= tube radius {t.inner_diameter_mm / 2} mm)")
        sp = self.spider
        if sp.vanes and sp.width_mm >= p.diameter_mm:
            raise ValueError(f"spider.width_mm ({sp.width_mm}) is wider than the aperture (primary.diameter_mm "
                             f"{p.diameter_mm})")
        ring = math.pi / 4 * (p.diameter_mm ** 2 - s.minor_axis_mm ** 2)
        if sp.vanes and sp.vanes * sp.width_mm * (p.diameter_mm - s.minor_axis_mm) / 2 >= ring:
            raise ValueError(f"spider: {sp.vanes} vanes of {sp.width_mm} mm cover the whole aperture (expected "
                             "vanes much narrower than the annulus between the secondary and the primary's rim)")
        if self.baffle.vanes and self.baffle.vane_inner_diameter_mm < p.diameter_mm:
            raise ValueError("baffle.vane_inner_diameter_mm closes the aperture (must be >= primary.diameter_mm)")
        if self.baffle.vane_inner_diameter_mm > t.inner_diameter_mm:
            raise ValueError("baffle.vane_inner_diameter_mm must not exceed tube.inner_diameter_mm")
        if self.baffle.zone_start_mm is not None and self.baffle.zone_start_mm >= t.length_mm:
            raise ValueError("baffle.zone_start_mm must lie inside the tube (< tube.length_mm)")
        if p.focal_length_mm - s.distance_to_focus_mm + s.minor_axis_mm > t.length_mm:
            raise ValueError("tube.length_mm too short: the diagonal sticks out of the tube front")
        if self.focal_plane.housing_mm <= t.focuser_diameter_mm:
            raise ValueError(f"focal_plane.housing_mm ({self.focal_plane.housing_mm}) must exceed "
                             f"tube.focuser_diameter_mm ({t.focuser_diameter_mm}): the housing's front plate "
                             "holds the focuser tube")
        if t.focuser_diameter_mm >= t.inner_diameter_mm:
            raise ValueError("tube.focuser_diameter_mm must be smaller than tube.inner_diameter_mm")
        c = self.corrector
        if not c.enabled:
            for name in CORRECTOR_PERTURBATIONS:
                if getattr(self.perturbation, name):
                    raise ValueError(f"perturbation.{name}: the design has no corrector (corrector.enabled "
                                     "is false); expected 0 or no entry")
        if c.enabled:
            if not c.surfaces:
                raise ValueError("corrector.surfaces: an enabled corrector needs at least one surface")
            from .glass import GLASSES
            for i, srf in enumerate(c.surfaces):
                if srf.material.lower() != "air" and srf.material.upper() not in GLASSES:
                    raise ValueError(f"corrector.surfaces.{i}.material: unknown glass '{srf.material}' "
                                     f"(known: air, {', '.join(sorted(GLASSES))})")
            if isinstance(c.ar_reflectance, float) and not 0.0 <= c.ar_reflectance < 1.0:
                raise ValueError(f"corrector.ar_reflectance: {c.ar_reflectance} is not in [0, 1) "
                                 "(or 'uncoated')")
            # the stack ends back_focus_mm before the detector, which sits defocus_mm beyond the bare focus
            stack = sum(srf.thickness_mm for srf in c.surfaces[:-1]) + c.back_focus_mm
            x_det = s.distance_to_focus_mm + self.focal_plane.defocus_mm
            if x_det - stack <= s.minor_axis_mm / 2:
                raise ValueError(
                    f"corrector: surfaces plus back_focus_mm ({stack:.1f} mm) reach past the diagonal: the "
                    f"first surface would sit {x_det - stack:.1f} mm from the optical axis, inside the "
                    f"diagonal's half-width {s.minor_axis_mm / 2:.1f} mm (detector at "
                    "secondary.distance_to_focus_mm + focal_plane.defocus_mm = "
                    f"{x_det:.1f} mm)")
            _check_lens_edges(c.surfaces)
        return self

    # --- first-order quantities ---------------------------------------------------------------------
    @property
    def f_number(self) -> float:
        return self.primary.focal_length_mm / self.primary.diameter_mm

    @property
    def plate_scale_arcsec_per_mm(self) -> float:
        return 180 / math.pi * 3600 / self.primary.focal_length_mm

    def pixel_scale_arcsec(self, pitch_um: float) -> float:
        """Angular size of a pixel of ``pitch_um`` [arcsec/pixel] on the optical axis."""
        return self.plate_scale_arcsec_per_mm * pitch_um * 1e-3

    @property
    def collecting_area_m2(self) -> float:
        """Clear aperture: primary minus the secondary's shadow and the spider vanes [m^2]."""
        p, s, sp = self.primary, self.secondary, self.spider
        ring = math.pi / 4 * (p.diameter_mm ** 2 - s.minor_axis_mm ** 2)
        vanes = sp.vanes * sp.width_mm * (p.diameter_mm - s.minor_axis_mm) / 2
        return (ring - vanes) * 1e-6

    @property
    def mirror_throughput(self) -> float:
        """Primary and diagonal reflectances together [1]."""
        return self.coatings.mirror_reflectance ** 2

    def corrector_transmission(self, wavelength_nm: float = 550.0) -> float:
        """Transmission of the corrector's surfaces at normal incidence [1] (1 without a corrector):
        prod (1 - R_AR) over the glass-air surfaces when coated, prod (1 - ((n1 - n2)/(n1 + n2))^2) over
        all surfaces when uncoated (and at cemented glass-glass surfaces) - what
        :class:`optics.sequential.SequentialTracer` multiplies along an axial ray; glass absorption is
        not modelled. For art: 0.995^8 = 0.961."""
        c = self.corrector
        if not c.enabled:
            return 1.0
        from .glass import index

        t, before = 1.0, "air"
        for srf in c.surfaces:
            after = srf.material
            if c.coated and "air" in (before.lower(), after.lower()):
                t *= 1.0 - c.ar_reflectance
            else:
                n1, n2 = float(index(before, wavelength_nm)), float(index(after, wavelength_nm))
                t *= 1.0 - ((n1 - n2) / (n1 + n2)) ** 2
            before = after
        return t


def surface_sag(radius_mm: float, h_mm: float) -> float:
    """Sag [mm] of a spherical surface of vertex radius ``radius_mm`` (0 = plane) at height ``h_mm``:
    z = R - sign(R) sqrt(R^2 - h^2) (positive toward the detector for R > 0)."""
    if radius_mm == 0.0:
        return 0.0
    return radius_mm - math.copysign(math.sqrt(radius_mm ** 2 - h_mm ** 2), radius_mm)


def _check_lens_edges(surfaces: list[Surface]) -> None:
    """Each surface's semi-diameter fits its sphere, and no glass or air space has a negative thickness
    at the rim of the larger of its two surfaces (the lenses would intersect)."""
    for i, srf in enumerate(surfaces):
        if srf.radius_mm and srf.semi_diameter_mm >= abs(srf.radius_mm):
            raise ValueError(f"corrector.surfaces.{i}.semi_diameter_mm ({srf.semi_diameter_mm}) must be smaller "
                             f"than |radius_mm| ({abs(srf.radius_mm)})")
    for i, (a, b) in enumerate(itertools.pairwise(surfaces)):
        h = min(a.semi_diameter_mm, b.semi_diameter_mm)
        edge = a.thickness_mm - surface_sag(a.radius_mm, h) + surface_sag(b.radius_mm, h)
        if edge < 0:
            what = "air" if a.material.lower() == "air" else a.material
            raise ValueError(f"corrector.surfaces.{i}.thickness_mm: the {what} space between surfaces {i} and "
                             f"{i + 1} is {edge:.2f} mm thick at height {h:.1f} mm (surfaces intersect)")


def as_design(design: Design | str) -> Design:
    """``design`` itself, or the built-in design / design TOML it names (:func:`load_design`)."""
    return design if isinstance(design, Design) else load_design(str(design))


def load_design(name_or_path: str) -> Design:
    """A built-in design (``"art"``, ``"bare"``) or a design TOML file."""
    path = BUILTIN / f"{name_or_path}.toml"
    if not path.is_file():
        path = Path(name_or_path)
        if path.is_dir():
            raise OpticsError(f"{name_or_path}: is a directory (expected a design TOML or a built-in design)")
        if not path.is_file():
            builtin = ", ".join(sorted(p.stem for p in BUILTIN.glob("*.toml")))
            raise OpticsError(f"{name_or_path}: no such design (built-in: {builtin}, or a path to a design TOML)")
    try:
        data = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise OpticsError(f"{path}: cannot read design: {exc}") from None
    data.setdefault("name", path.stem)
    try:
        return Design.model_validate(data)
    except ValidationError as exc:
        e = exc.errors()[0]
        loc = ".".join(str(x) for x in e["loc"]) or "design"
        msg = e["msg"].removeprefix("Value error, ")
        if e.get("type") == "extra_forbidden" and e["loc"][:1] == ("perturbation",):
            msg = f"unknown perturbation (expected one of: {', '.join(PERTURBATION_NAMES)})"
        raise OpticsError(f"{path}: key '{loc}': {msg}") from None


def with_perturbation(design: Design, **values: float) -> Design:
    """A copy of ``design`` with the named ``[perturbation]`` entries replaced (others kept)."""
    data = design.model_dump()
    data["perturbation"] = {**data["perturbation"], **values}
    return Design.model_validate(data)
