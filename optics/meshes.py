"""Triangle meshes of the telescope (numpy, exportable through trimesh to PLY/GLB).

Every part is a :class:`Part`: vertices [mm], triangles, optional analytic vertex normals (mirrors and
lenses carry them: a faceted paraboloid without them gives an on-axis spot of hundreds of microns) and a
material tag (``mirror``, ``black``, ``glass``, ``detector``) that the Mitsuba scene maps to a BSDF.
Meshes are used for the mechanical obstruction tests (Mitsuba's BVH) and for the non-sequential
straylight tracing; the sequential tracer intersects the mirrors and lenses analytically.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .layout import Layout


@dataclass
class Part:
    name: str
    vertices: np.ndarray            # (N, 3) float64 [mm]
    faces: np.ndarray               # (M, 3) int
    material: str                   # mirror | black | glass | detector
    normals: np.ndarray | None = None
    meta: dict = field(default_factory=dict)


# ---- primitive builders (pure numpy) -----------------------------------------------------------------
def _grid_faces(n_rows: int, n_cols: int, wrap: bool) -> np.ndarray:
    """Two triangles per cell of a (n_rows x n_cols) vertex grid, optionally wrapping in columns."""
    cols = n_cols if wrap else n_cols - 1
    r, c = np.meshgrid(np.arange(n_rows - 1), np.arange(cols), indexing="ij")
    a = r * n_cols + c
    b = r * n_cols + (c + 1) % n_cols
    d = (r + 1) * n_cols + c
    e = (r + 1) * n_cols + (c + 1) % n_cols
    return np.concatenate([np.stack([a, b, e], -1).reshape(-1, 3), np.stack([a, e, d], -1).reshape(-1, 3)])


def annulus(r_in: float, r_out: float, z: float, n_phi: int = 128, n_r: int = 2):
    """Flat ring (or disk when ``r_in`` = 0) in the plane z = const."""
    phi = np.linspace(0, 2 * np.pi, n_phi, endpoint=False)
    r = np.linspace(max(r_in, 1e-6), r_out, n_r)
    R, P = np.meshgrid(r, phi, indexing="ij")
    v = np.stack([R * np.cos(P), R * np.sin(P), np.full_like(R, z)], -1).reshape(-1, 3)
    return v, _grid_faces(n_r, n_phi, True)


def cylinder_z(radius: float, z0: float, z1: float, n_phi: int = 128, n_z: int = 2, hole=None):
    """Open cylinder about the z axis; ``hole=(z_c, r_h)`` removes the faces around the +x direction
    within r_h of height z_c (the side opening for the focuser)."""
    phi = np.linspace(0, 2 * np.pi, n_phi, endpoint=False)
    z = np.linspace(z0, z1, n_z)
    Z, P = np.meshgrid(z, phi, indexing="ij")
    v = np.stack([radius * np.cos(P), radius * np.sin(P), Z], -1).reshape(-1, 3)
    f = _grid_faces(n_z, n_phi, True)
    if hole is not None:
        zc, rh = hole
        cen = v[f].mean(axis=1)
        keep = ~((cen[:, 0] > 0) & (cen[:, 1] ** 2 + (cen[:, 2] - zc) ** 2 < rh ** 2))
        f = f[keep]
    return v, f


def box(lo, hi):
    """Closed axis-aligned box between corners ``lo`` and ``hi``."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    v = np.array([[lo[0] if i & 1 == 0 else hi[0], lo[1] if i & 2 == 0 else hi[1],
                   lo[2] if i & 4 == 0 else hi[2]] for i in range(8)])
    f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    return v, f


def _rotate_z(v: np.ndarray, angle_rad: float) -> np.ndarray:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return v @ np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]])


def _merge(*pieces):
    verts, faces, off = [], [], 0
    for v, f in pieces:
        verts.append(v)
        faces.append(f + off)
        off += len(v)
    return np.concatenate(verts), np.concatenate(faces)


# ---- the telescope ------------------------------------------------------------------------------------
def primary_surface(L: Layout, n_r: int = 96, n_phi: int = 256) -> Part:
    """Conic primary with analytic normals (gradient of z - sag(r))."""
    r = L.r_primary * np.sqrt(np.linspace(0.0, 1.0, n_r))
    phi = np.linspace(0, 2 * np.pi, n_phi, endpoint=False)
    R, P = np.meshgrid(r, phi, indexing="ij")
    Z = L.primary_sag(R)
    v = np.stack([R * np.cos(P), R * np.sin(P), Z], -1).reshape(-1, 3)
    c = 1.0 / (2.0 * L.focal_length)
    dzdr = c * R / np.sqrt(np.maximum(1 - (1 + L.conic) * c * c * R * R, 1e-12))
    n = np.stack([-dzdr * np.cos(P), -dzdr * np.sin(P), np.ones_like(R)], -1).reshape(-1, 3)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return Part("primary", v, _grid_faces(n_r, n_phi, True), "mirror", n)


def diagonal_surface(L: Layout, n_r: int = 24, n_phi: int = 128) -> Part:
    """The elliptical flat: its projection along z is a circle of radius b centred on the ellipse centre."""
    cx, cy, cz = L.diag_centre
    r = L.diag_b * np.sqrt(np.linspace(0.0, 1.0, n_r))
    phi = np.linspace(0, 2 * np.pi, n_phi, endpoint=False)
    R, P = np.meshgrid(r, phi, indexing="ij")
    x = cx + R * np.cos(P)
    y = cy + R * np.sin(P)
    z = cz + (x - cx)                       # plane n.(P - C) = 0 with n = (1, 0, -1)/sqrt2
    v = np.stack([x, y, z], -1).reshape(-1, 3)
    n = np.tile(np.asarray(L.diag_normal), (len(v), 1))
    return Part("diagonal", v, _grid_faces(n_r, n_phi, True), "mirror", n)


def holder(L: Layout, n_phi: int = 96) -> Part:
    """Cylinder of the diagonal's radius from its oblique back up to a top cap (the diagonal's body)."""
    cx, cy, cz = L.diag_centre
    phi = np.linspace(0, 2 * np.pi, n_phi, endpoint=False)
    x = cx + L.diag_b * np.cos(phi)
    y = cy + L.diag_b * np.sin(phi)
    lower = np.stack([x, y, cz + (x - cx)], -1)
    upper = np.stack([x, y, np.full_like(x, L.holder_top)], -1)
    v = np.concatenate([lower, upper])
    f = _grid_faces(2, n_phi, True)
    cap_v, cap_f = annulus(0.0, L.diag_b, L.holder_top, n_phi)
    cap_v[:, 0] += cx
    v, f = _merge((v, f), (cap_v, cap_f))
    return Part("holder", v, f, "black")


def spider(L: Layout) -> list[Part]:
    parts = []
    z0, z1 = L.spider_z
    for k, ang in enumerate(L.spider_angles_deg):
        v, f = box((L.diag_b * 0.9, -L.spider_half_width, z0), (L.r_tube, L.spider_half_width, z1))
        v = _rotate_z(v, math.radians(ang))          # centred on the tube axis
        parts.append(Part(f"spider_{k}", v, f, "black"))
    return parts


def merge_full_bands(part):
    """The same surface with fewer triangles: on a (rows x columns) grid mesh such as the tube of
    :func:`optics.meshes.cylinder_z`, runs of complete bands between rows (no face removed, e.g. away from
    the focuser's opening) are planar strips at each column, so they are replaced by one band from the
    run's first to its last row. The polyhedral surface is unchanged (same vertices, same jagged edge of
    the opening); ray casting inside the 4-mm-faceted tube gets about 3x faster. Parts that are not such
    a grid come back unchanged."""
    v, f = part.vertices, part.faces
    zs = np.unique(np.round(v[:, 2], 9))
    n_rows = len(zs)
    if n_rows < 3 or len(v) % n_rows:
        return part
    n_cols = len(v) // n_rows
    grid = v.reshape(n_rows, n_cols, 3)
    if not np.allclose(grid[:, :, 2], zs[:, None]) or not np.allclose(grid[:, :, :2], grid[:1, :, :2]):
        return part
    row = f // n_cols
    band = row.min(axis=1)
    if np.any(row.max(axis=1) - band != 1):
        return part
    counts = np.bincount(band, minlength=n_rows - 1)
    full = counts == 2 * n_cols
    keep = ~full[band]
    new_faces = [f[keep]]
    k = 0
    cols = np.arange(n_cols)
    while k < n_rows - 1:
        if not full[k]:
            k += 1
            continue
        start = k
        while k < n_rows - 1 and full[k]:
            k += 1
        a = start * n_cols + cols
        b = start * n_cols + (cols + 1) % n_cols
        d = k * n_cols + cols
        e = k * n_cols + (cols + 1) % n_cols
        new_faces.append(np.concatenate([np.stack([a, b, e], -1), np.stack([a, e, d], -1)]))
    return Part(part.name, v, np.concatenate(new_faces), part.material, part.normals, dict(part.meta))


def tube_grid(L: Layout) -> Part:
    """The tube wall as the full (rows x columns) grid of ~4 mm facets, with the focuser's opening."""
    # fine facets (about 4 x 4 mm) so the side opening's jagged edge stays within ~2 mm of the circle
    n_phi = int(2 * math.pi * L.r_tube / 4.0)
    v, f = cylinder_z(L.r_tube, L.tube_bottom, L.tube_top, n_phi=n_phi,
                      n_z=int(max(2, (L.tube_top - L.tube_bottom) / 4.0)), hole=(L.z_axis, L.r_focuser))
    return Part("tube", v, f, "black")


def tube(L: Layout) -> Part:
    """The tube wall: :func:`tube_grid` with its complete bands merged (same surface, far fewer triangles)."""
    return merge_full_bands(tube_grid(L))


def vanes(L: Layout) -> list[Part]:
    return [Part(f"vane_{k}", *annulus(L.r_vane, L.r_tube, z, 192), "black") for k, z in enumerate(L.vane_z)]


def cell(L: Layout) -> list[Part]:
    """Mirror cell: back plate plus the primary's edge (a cylinder from the rim down)."""
    back = Part("cell", *annulus(0.0, L.r_tube, L.tube_bottom, 128), "black")
    rim = L.primary_sag(L.r_primary)
    edge = Part("primary_edge", *cylinder_z(L.r_primary, rim - L.primary_edge_depth, rim, 128), "black")
    ring = Part("cell_ring", *annulus(L.r_primary, L.r_tube, rim - L.primary_edge_depth, 128), "black")
    return [back, edge, ring]


def focuser(L: Layout) -> list[Part]:
    """Focuser tube along +x from inside the tube wall to the camera housing, then the housing box."""
    n_phi = 96
    phi = np.linspace(0, 2 * np.pi, n_phi, endpoint=False)
    x0 = L.focuser_start_x
    X, P = np.meshgrid(np.array([x0, L.x_housing]), phi, indexing="ij")
    v = np.stack([X, L.r_focuser * np.cos(P), L.z_axis + L.r_focuser * np.sin(P)], -1).reshape(-1, 3)
    tube_part = Part("focuser", v, _grid_faces(2, n_phi, True), "black")
    h = L.housing_half
    depth = max(L.x_detector - L.x_housing + 15.0, 20.0)
    hv, hf = box((L.x_housing, -h, L.z_axis - h), (L.x_housing + depth, h, L.z_axis + h))
    # open the front face where the focuser enters: drop the two front triangles, add a plate with a hole
    front = (hv[hf][:, :, 0] == L.x_housing).all(axis=1)
    hf = hf[~front]
    ring_v, ring_f = _square_plate_with_hole(h, L.r_focuser, n=48)
    ring_v = np.stack([np.full(len(ring_v), L.x_housing), ring_v[:, 0], L.z_axis + ring_v[:, 1]], -1)
    hv, hf = _merge((hv, hf), (ring_v, ring_f))
    return [tube_part, Part("housing", hv, hf, "black")]


def _square_plate_with_hole(half: float, r_hole: float, n: int = 48):
    """Square of side 2*half with a central circular hole (2-D vertices, triangles)."""
    phi = np.linspace(0, 2 * np.pi, n, endpoint=False)
    inner = np.stack([r_hole * np.cos(phi), r_hole * np.sin(phi)], -1)
    # project each inner vertex radially onto the square's border
    scale = half / np.maximum(np.abs(np.cos(phi)), np.abs(np.sin(phi)))
    outer = np.stack([scale * np.cos(phi), scale * np.sin(phi)], -1)
    v = np.concatenate([inner, outer])
    return v, _grid_faces(2, n, True)


def detector_part(L: Layout) -> Part:
    hu, hv = L.detector_half
    v = np.array([[L.x_detector, -hv, L.z_axis - hu], [L.x_detector, hv, L.z_axis - hu],
                  [L.x_detector, hv, L.z_axis + hu], [L.x_detector, -hv, L.z_axis + hu]])
    return Part("detector", v, np.array([[0, 1, 2], [0, 2, 3]]), "detector")


def lens_parts(L: Layout, n_r: int = 24, n_phi: int = 96) -> list[Part]:
    """The corrector's lenses as closed solids in their cells.

    Each surface is a spherical cap (``lens_surface_j``, glass, analytic normals pointing toward -x).
    Each lens (a surface entering glass and the next one) gets its ground and blackened edge
    (``lens_edge_k``, black): the cylinder of the larger clear semi-diameter between the two caps' rims
    plus a flat ring closing the step where the other cap is smaller, so caps and edge enclose the glass
    (a ray inside that misses the exit cap is absorbed at the edge). The lens cell (``lens_cell_k``,
    black) is a ring from the edge out to the focuser bore at the larger cap's rim: no light passes
    beside a lens, as in the sequential tracer, which stops rays outside a clear aperture."""
    parts = []
    phi = np.linspace(0, 2 * np.pi, n_phi, endpoint=False)
    for j, s in enumerate(L.lenses):
        r = s.semi_diameter_mm * np.sqrt(np.linspace(0.0, 1.0, n_r))
        R, P = np.meshgrid(r, phi, indexing="ij")
        if s.radius_mm == 0:
            sag = np.zeros_like(R)
            n = np.tile([-1.0, 0.0, 0.0], (R.size, 1))
        else:
            Rc = s.radius_mm
            sag = Rc - np.sign(Rc) * np.sqrt(np.maximum(Rc * Rc - R * R, 0.0))
            # (P - centre) / R points toward -x (the incoming light) for either sign of R
            n = np.stack([sag - Rc, R * np.cos(P), R * np.sin(P)], -1).reshape(-1, 3) / Rc
        v = np.stack([s.x_mm + sag, R * np.cos(P), L.z_axis + R * np.sin(P)], -1).reshape(-1, 3)
        parts.append(Part(f"lens_surface_{j}", v, _grid_faces(n_r, n_phi, True), "glass", n,
                          meta={"before": s.before, "after": s.after}))
    k = 0
    for front, back in itertools.pairwise(L.lenses):
        if front.after.lower() == "air":
            continue
        r_out = max(front.semi_diameter_mm, back.semi_diameter_mm)
        rims = [front.x_edge_mm, back.x_edge_mm]
        c, s_ = r_out * np.cos(phi), r_out * np.sin(phi)
        pieces = [(np.concatenate([np.stack([np.full_like(phi, x), c, L.z_axis + s_], -1) for x in rims]),
                   _grid_faces(2, n_phi, True))]
        pieces += [_ring_x(L, surf.semi_diameter_mm, r_out, x, n_phi) for surf, x in zip((front, back), rims, strict=True)
                   if surf.semi_diameter_mm < r_out - 1e-9]
        parts.append(Part(f"lens_edge_{k}", *_merge(*pieces), "black"))
        if r_out < L.r_focuser - 1e-9:
            x_cell = rims[0] if front.semi_diameter_mm >= back.semi_diameter_mm else rims[1]
            parts.append(Part(f"lens_cell_{k}", *_ring_x(L, r_out, L.r_focuser, x_cell, n_phi), "black"))
        k += 1
    return parts


def _ring_x(L: Layout, r_in: float, r_out: float, x: float, n_phi: int):
    """Flat ring about the focuser axis in the plane x = const (vertices, triangles)."""
    v, f = annulus(r_in, r_out, 0.0, n_phi)
    return np.stack([np.full(len(v), x), v[:, 0], L.z_axis + v[:, 1]], -1), f


def telescope_parts(L: Layout, optics_surfaces: bool = True) -> list[Part]:
    """All parts; ``optics_surfaces=False`` leaves out mirrors, lenses and the detector (obstructions only)."""
    parts = [holder(L), tube(L), *spider(L), *vanes(L), *cell(L), *focuser(L)]
    if optics_surfaces:
        parts = [primary_surface(L), diagonal_surface(L), *lens_parts(L), detector_part(L)] + parts
    return parts


def export(parts: list[Part], path: str | Path) -> Path:
    """Write the parts as one scene (GLB keeps the names) or one mesh (PLY, STL, OBJ) through trimesh."""
    import trimesh

    path = Path(path)
    meshes = {p.name: trimesh.Trimesh(p.vertices, p.faces, vertex_normals=p.normals, process=False)
              for p in parts}
    if path.suffix.lower() in (".glb", ".gltf"):
        trimesh.Scene(meshes).export(path)
    else:
        trimesh.util.concatenate(list(meshes.values())).export(path)
    return path
