"""Ray-trace reference from batoid: the ART design (field corrector included) and the bare Newtonian.

Run in its own environment (batoid is only in newtsim's ``bench`` extra):

    python3 -m venv /work/peerenv/batoid && /work/peerenv/batoid/bin/pip install batoid
    /work/peerenv/batoid/bin/python tests/data/peers/batoid/make_ray_reference.py

The telescope is built in batoid from the design files themselves (``optics/designs/art.toml`` and
``bare.toml``, read with tomllib; nothing of newtsim is imported), following the frame of
``optics/layout.py``'s docstring: the primary's vertex at the origin, +z toward the sky, the 45-degree
diagonal folding the beam toward +x. Units: millimetres (batoid is unit-agnostic in length; wavelengths
are in metres for its Sellmeier media).

- primary: ``batoid.Paraboloid(R = 2 f)`` (``batoid.Quadric(R, conic)`` for conic != -1) at the origin;
- diagonal: a ``batoid.Plane`` through the ellipse centre (-o/sqrt2, 0, f - d - o/sqrt2), o the offset, its
  normal (1, 0, -1)/sqrt2;
- corrector: ``batoid.Sphere`` surfaces (or planes) on the focuser axis (y = 0, z = f - d), vertices placed
  back from the detector by ``back_focus_mm`` and the thicknesses, glasses as ``batoid.SellmeierMedium``
  with the SCHOTT catalogue coefficients (below);
- detector: the plane x = d + defocus; (u, v) = (z - (f - d), y).

Rays: a plane wave from a star at field angles (theta_x, theta_y), direction -(tan theta_x, tan theta_y,
1) normalised, through pupil points (px, py) of the primary's rim plane (z = sag at the rim), started on the
plane z = tube length + 1 mm with t = (start point) . (direction): t then equals the optical path from the
wavefront through the origin. The chief ray is the pupil centre (the primary is the stop); then an 8 x 8 grid of cell centres inside the
rim and 12 marginal rays at 0.999 of the rim radius. A ray counts as
reaching the detector when it lands inside the primary's rim, the diagonal's ellipse, every lens's clear
semi-diameter and the detector's outline (batoid itself traces through unbounded surfaces; mechanical
obstructions such as the spider are not modelled, as in newtsim's ``obstruct="none"``).
"""

import json
import math
import platform
from pathlib import Path

import batoid
import numpy as np
import tomllib

ROOT = Path(__file__).resolve().parents[4]
OUT = Path(__file__).with_name("rays.json")
FIELDS_DEG = [(0.0, 0.0), (0.7, 0.0), (0.0, 1.0), (1.2, 0.9)]
WAVELENGTHS_NM = {"art": [450.0, 650.0, 850.0], "bare": [550.0]}
GRID_N = 8          # pupil grid: n x n cell centres over the primary's square, those inside the rim kept
RIM_N, RIM_FRACTION = 12, 0.999   # and rays just inside the rim (the marginal rays), 12 azimuths
# SCHOTT optical glass data sheets (Sellmeier B1, B2, B3, C1, C2, C3; C in um^2)
SCHOTT = {
    "N-FK51A": (0.971247817, 0.216901417, 0.904651666, 0.00472301995, 0.0153575612, 168.68133),
    "N-BAK4": (1.28834642, 0.132817724, 0.945395373, 0.00779980626, 0.0315631177, 105.965875),
    "N-SF5": (1.52481889, 0.187085527, 1.42729015, 0.011254756, 0.0588995392, 129.141675),
    "N-BK7": (1.03961212, 0.231792344, 1.01046945, 0.00600069867, 0.0200179144, 103.560653),
}
AIR = batoid.ConstMedium(1.0)


def medium(name):
    return AIR if name.lower() == "air" else batoid.SellmeierMedium(list(SCHOTT[name.upper()]))


def build(design):
    """(list of (name, optic, check), detector x, z of the focuser axis, rim sag, tube length)."""
    p, s, fp, t = design["primary"], design["secondary"], design["focal_plane"], design["tube"]
    f, d, off = p["focal_length_mm"], s["distance_to_focus_mm"], s.get("offset_mm", 0.0)
    k = p.get("conic", -1.0)
    z_axis = f - d
    x_det = d + fp.get("defocus_mm", 0.0)
    R = p["diameter_mm"] / 2
    b = s["minor_axis_mm"] / 2
    a = b * math.sqrt(2)
    items = []
    # batoid's Quadric divides by 1 + conic: the paraboloid has its own class
    surf = batoid.Paraboloid(2 * f) if k == -1.0 else batoid.Quadric(2 * f, k)
    prim = batoid.Mirror(surf, inMedium=AIR, outMedium=AIR, name="primary",
                         coordSys=batoid.CoordSys())
    items.append(("primary", prim, lambda rv: np.hypot(rv.x, rv.y) <= R))
    centre = np.array([-off / math.sqrt(2), 0.0, z_axis - off / math.sqrt(2)])
    # local z = the diagonal's normal (1, 0, -1)/sqrt2; local x = (-1, 0, -1)/sqrt2 lies along the major axis
    diag = batoid.Mirror(batoid.Plane(), inMedium=AIR, outMedium=AIR, name="diagonal",
                         coordSys=batoid.CoordSys(origin=centre, rot=batoid.RotY(math.radians(135.0))))
    items.append(("diagonal", diag, lambda rv: (rv.x / a) ** 2 + (rv.y / b) ** 2 <= 1.0))
    c = design.get("corrector", {})
    if c.get("enabled", False) and c.get("surfaces"):
        surfs = c["surfaces"]
        x = x_det - c["back_focus_mm"] - sum(sf["thickness_mm"] for sf in surfs[:-1])
        before = "air"
        for i, sf in enumerate(surfs):
            surf = batoid.Plane() if sf["radius_mm"] == 0 else batoid.Sphere(sf["radius_mm"])
            cs = batoid.CoordSys(origin=[x, 0.0, z_axis], rot=batoid.RotY(math.radians(90.0)))
            items.append((f"lens{i}", batoid.RefractiveInterface(surf, inMedium=medium(before),
                                                                 outMedium=medium(sf["material"]),
                                                                 coordSys=cs, name=f"lens{i}"),
                          lambda rv, h=sf["semi_diameter_mm"]: np.hypot(rv.x, rv.y) <= h))
            before = sf["material"]
            x += sf["thickness_mm"]
    det = batoid.Detector(batoid.Plane(), name="detector",
                          coordSys=batoid.CoordSys(origin=[x_det, 0.0, z_axis], rot=batoid.RotY(math.radians(90.0))))
    hu, hv = fp["width_mm"] / 2, fp["height_mm"] / 2
    # detector local frame: x_local = -(global z - z_axis) = -u, y_local = y = v
    items.append(("detector", det, lambda rv: (np.abs(rv.x) <= hu) & (np.abs(rv.y) <= hv)))
    c_rim = 1.0 / (2 * f)
    z_rim = c_rim * R * R / (1 + math.sqrt(max(1 - (1 + k) * c_rim ** 2 * R * R, 0.0)))
    return items, z_axis, z_rim, t["length_mm"]


def trace(design, field_deg, px, py, lam_nm):
    items, z_axis, z_rim, tube = build(design)
    tx, ty = (math.tan(math.radians(v)) for v in field_deg)
    dvec = -np.array([tx, ty, 1.0])
    dvec /= np.linalg.norm(dvec)
    s0 = (tube + 1.0 - z_rim) / (-dvec[2])
    ox, oy, oz = px - dvec[0] * s0, py - dvec[1] * s0, np.full_like(px, z_rim) - dvec[2] * s0
    t0 = ox * dvec[0] + oy * dvec[1] + oz * dvec[2]
    rv = batoid.RayVector(ox, oy, oz, np.full_like(px, dvec[0]), np.full_like(px, dvec[1]),
                          np.full_like(px, dvec[2]), t=t0, wavelength=lam_nm * 1e-9)
    ok = np.ones(len(px), bool)
    for _, optic, inside in items:
        rv = optic.trace(rv)
        ok &= inside(rv) & ~rv.failed
    g = rv.toCoordSys(batoid.CoordSys())
    return {"u_mm": (g.z - z_axis).tolist(), "v_mm": g.y.tolist(), "du": g.vz.tolist(), "dv": g.vy.tolist(),
            "dw": g.vx.tolist(), "opl_mm": g.t.tolist(), "reaches_detector": ok.tolist()}


def main():
    c = (np.arange(GRID_N) + 0.5) / GRID_N * 2 - 1
    out = {"peer": "batoid", "version": batoid.__version__, "python": platform.python_version(),
           "numpy": np.__version__,
           "command": "/work/peerenv/batoid/bin/python tests/data/peers/batoid/make_ray_reference.py",
           "units": "mm; directions are unit vectors (du, dv along u, v; dw along the folded beam, +x)",
           "glass": "SCHOTT Sellmeier coefficients, batoid.SellmeierMedium", "designs": {}}
    for name in ("art", "bare"):
        design = tomllib.loads((ROOT / "optics" / "designs" / f"{name}.toml").read_text())
        R = design["primary"]["diameter_mm"] / 2
        X, Y = np.meshgrid(c * R, c * R, indexing="xy")
        keep = np.hypot(X, Y) <= R
        rim = np.radians(np.arange(RIM_N) * 360.0 / RIM_N + 10.0)
        px = np.concatenate([[0.0], X[keep], RIM_FRACTION * R * np.cos(rim)])   # first ray: the chief ray
        py = np.concatenate([[0.0], Y[keep], RIM_FRACTION * R * np.sin(rim)])
        cases = []
        for fd in FIELDS_DEG:
            for lam in WAVELENGTHS_NM[name]:
                cases.append({"field_deg": list(fd), "wavelength_nm": lam, **trace(design, fd, px, py, lam)})
        out["designs"][name] = {"design_file": f"optics/designs/{name}.toml", "px_mm": px.tolist(),
                                "py_mm": py.tolist(), "cases": cases}
    OUT.write_text(json.dumps(out) + "\n")


if __name__ == "__main__":
    main()
