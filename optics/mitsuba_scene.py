"""Mitsuba scenes from :mod:`optics.meshes` parts (built from numpy arrays: the fastest path).

Needs a Mitsuba module whose variant the caller has set (:func:`optics.llvm.init_mitsuba`).
"""

from __future__ import annotations

import numpy as np

from .meshes import Part


def to_mitsuba_mesh(mi, part: Part, bsdf=None):
    """A ``mi.Mesh`` with the part's vertices, faces and (analytic) vertex normals; ``bsdf`` optional."""
    props = mi.Properties()
    if bsdf is not None:
        props["bsdf"] = bsdf
    has_n = part.normals is not None
    mesh = mi.Mesh(part.name, len(part.vertices), len(part.faces), props=props, has_vertex_normals=has_n)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(np.ascontiguousarray(part.vertices, dtype=np.float32).ravel())
    params["faces"] = mi.UInt32(np.ascontiguousarray(part.faces, dtype=np.uint32).ravel())
    if has_n:
        params["vertex_normals"] = mi.Float(np.ascontiguousarray(part.normals, dtype=np.float32).ravel())
    params.update()
    return mesh


def build_scene(mi, parts: list[Part], bsdfs: dict | None = None):
    """A Mitsuba scene of ``parts``; ``bsdfs`` maps a part's material tag (or its name) to a BSDF object.

    Returns ``(scene, names)``: ``names[i]`` is the part name of the shape whose registry id is the key
    ``ids[i]`` so surface hits can be mapped back to parts (see :func:`shape_ids`).
    """
    bsdfs = bsdfs or {}
    meshes = {}
    for p in parts:
        bsdf = bsdfs.get(p.name, bsdfs.get(p.material))
        meshes[p.name] = to_mitsuba_mesh(mi, p, bsdf)
    scene = mi.load_dict({"type": "scene", **meshes})
    return scene


def shape_ids(mi, scene) -> dict[int, str]:
    """Registry id of each shape (what ``dr.reinterpret_array(mi.UInt32, si.shape)`` returns) -> name."""
    import drjit as dr

    out = {}
    for shape in scene.shapes():
        sid = int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(shape))[0])
        out[sid] = shape.id()
    return out
