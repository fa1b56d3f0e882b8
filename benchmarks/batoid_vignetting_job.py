"""batoid's side of bench_optics_trace.py: the vignetting job's rays through the same telescope in batoid.

Runs in batoid's own environment (never newtsim's), started by bench_optics_trace.py:

    /work/peerenv/batoid/bin/python benchmarks/batoid_vignetting_job.py DESIGN RAYS.npz [telescope|paraboloid]

RAYS.npz holds the pupil points ``px``, ``py`` [mm] of the primary's rim plane and the field angles
``fields`` [deg] (n, 2), the very rays newtsim's vignetting map traces. The telescope is built by
tests/data/peers/batoid/make_ray_reference.py (:func:`build`: primary, diagonal, corrector lenses when the
design has them, detector plane, from the design TOML; nothing of newtsim imported), and each field's bundle
is started on the plane z = tube length + 1 mm as there. Timed per field: making the RayVector, tracing it
surface by surface and counting the rays inside every optical aperture (primary rim, diagonal outline, lens
rims; the sensor's edge left out, as in the vignetting map). batoid models no mechanical obstructions
(spider, vanes, tube, focuser): newtsim does that work on top. Prints JSON: wall seconds and the process's
CPU seconds (user + system, all threads: batoid's OpenMP threads included).

``paraboloid``: batoid's lightest job on the same rays instead (the previous benchmark's reference): reflect
off the paraboloid alone and intersect its focal plane, positions back as numpy arrays, no diagonal, no
lenses, no aperture counted.
"""

from __future__ import annotations

import importlib.util
import json
import math
import resource
import sys
import time
from pathlib import Path

import batoid
import numpy as np
import tomllib

ROOT = Path(__file__).resolve().parents[1]


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    name, rays_file = argv[0], argv[1]
    job = argv[2] if len(argv) > 2 else "telescope"
    spec = importlib.util.spec_from_file_location(
        "make_ray_reference", ROOT / "tests" / "data" / "peers" / "batoid" / "make_ray_reference.py")
    ref = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ref)
    design = tomllib.loads((ROOT / "optics" / "designs" / f"{name}.toml").read_text())
    items, _, z_rim, tube = ref.build(design)
    # the sensor's edge is not a loss of the vignetting map
    steps = [(optic, None if oname == "detector" else inside) for oname, optic, inside in items]
    f = design["primary"]["focal_length_mm"]
    mirror, focal, focus = batoid.Paraboloid(2 * f), batoid.Plane(), batoid.CoordSys(origin=[0, 0, f])
    data = np.load(rays_file)
    px, py, fields = data["px"], data["py"], data["fields"]
    n = len(px)
    z_rim_arr = np.full(n, z_rim)
    wall = cpu = 0.0
    through = []
    for fd in fields:
        tx, ty = (math.tan(math.radians(v)) for v in fd)
        d = -np.array([tx, ty, 1.0])
        d /= np.linalg.norm(d)
        s0 = (tube + 1.0 - z_rim) / (-d[2])
        t_wall, t_cpu = time.perf_counter(), _cpu()
        rv = batoid.RayVector(px - d[0] * s0, py - d[1] * s0, z_rim_arr - d[2] * s0, np.full(n, d[0]),
                              np.full(n, d[1]), np.full(n, d[2]), wavelength=550e-9)
        if job == "paraboloid":
            mirror.reflect(rv)
            focal.intersect(rv, coordSys=focus)
            _ = rv.x, rv.y
            count = n
        else:
            ok = np.ones(n, bool)
            for optic, inside in steps:
                rv = optic.trace(rv)
                ok &= ~rv.failed if inside is None else inside(rv) & ~rv.failed
            count = int(np.count_nonzero(ok))
        wall += time.perf_counter() - t_wall
        cpu += _cpu() - t_cpu
        through.append(count / n)
    out = {"version": batoid.__version__, "design": name, "job": job, "rays": n * len(fields), "fields": len(fields),
           "seconds": round(wall, 4), "cpu_s": round(cpu, 4), "mrays_per_s": round(n * len(fields) / wall / 1e6, 2),
           "through_optical_apertures": [round(t, 6) for t in through]}
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
