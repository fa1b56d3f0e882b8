"""Sequential ray-tracing speed: newtsim (drjit, llvm) against batoid on the same job, same run.

Job (batoid's natural one): a collimated bundle at 0.5 deg off axis fills a 400 mm f/2.4 paraboloid
(metres in batoid, millimetres in newtsim), reflects, and is carried to the focal plane; the positions come
back as numpy arrays. newtsim does more on each ray than batoid here: it also folds the beam at the 45
degree diagonal (with its elliptical outline) before the focal plane, in double precision. A second
newtsim figure adds every mechanical obstruction (vanes, spider, diagonal body, focuser: the vignetting
job), and a third the corrector's lenses of the `art` design when it has them.

Prints JSON. Run: python benchmarks/bench_optics_trace.py [--rays N] [--repeat R]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))


def best_of(fn, repeat):
    fn()  # warm-up: kernel compilation, caches
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times), float(np.median(times))


def batoid_job(px_mm, py_mm, field_deg, f_mm):
    import batoid

    f = f_mm * 1e-3
    mirror = batoid.Paraboloid(2 * f)
    focal = batoid.Plane()
    th = math.radians(field_deg)
    vx, vz = -math.sin(th), -math.cos(th)
    x0 = px_mm * 1e-3
    y0 = py_mm * 1e-3
    z0 = np.full_like(x0, 1.0)

    def run():
        rv = batoid.RayVector(x0 - vx * 0, y0, z0, np.full_like(x0, vx), np.zeros_like(x0), np.full_like(x0, vz),
                              wavelength=550e-9)
        mirror.reflect(rv)
        focal.intersect(rv, coordSys=batoid.CoordSys(origin=[0, 0, f]))
        return rv.x, rv.y

    return run


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--rays", type=int, default=1 << 22)
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args(argv)

    from optics import load_design
    from optics.llvm import init_mitsuba
    from optics.sequential import SequentialTracer, pupil_uniform

    mi = init_mitsuba()
    n = args.rays
    px, py = pupil_uniform(n, 200.0, seed=0)
    field = 0.5
    out = {"rays": n, "field_deg": field, "cpus": os.cpu_count(), "machine": platform.machine()}

    try:
        run_b = batoid_job(px, py, field, 960.0)
        xb, _ = run_b()
        tb, tb_med = best_of(run_b, args.repeat)
        out["batoid"] = {"seconds": round(tb, 4), "median_s": round(tb_med, 4), "mrays_per_s": round(n / tb / 1e6, 2),
                         "version": __import__("batoid").__version__}
    except ImportError:
        out["batoid"] = {"error": "batoid not installed (pip install batoid)"}

    bare = load_design("bare")
    jobs = {"newtsim_folded_no_obstructions": SequentialTracer(bare, mi, obstruct="none"),
            "newtsim_vignetting_job": SequentialTracer(bare, mi, obstruct="analytic")}
    art = load_design("art")
    if art.corrector.enabled:
        jobs["newtsim_art_with_corrector"] = SequentialTracer(art, mi, obstruct="analytic")
    for name, tr in jobs.items():
        res = tr.trace((field, 0.0), px, py)
        t, t_med = best_of(lambda tr=tr: tr.trace((field, 0.0), px, py), args.repeat)
        tc, _ = best_of(lambda tr=tr: tr.count((field, 0.0), px, py), args.repeat)
        out[name] = {"seconds": round(t, 4), "median_s": round(t_med, 4), "mrays_per_s": round(n / t / 1e6, 2),
                     "count_only_mrays_per_s": round(n / tc / 1e6, 2), "reached_detector": round(float(res.ok.mean()), 4)}
        if "batoid" in out and "seconds" in out["batoid"]:
            out[name]["speed_vs_batoid"] = round(out["batoid"]["seconds"] / t, 2)
    # agreement on the image position (same physics): mean u of newtsim vs batoid's mean x (mm)
    if "seconds" in out.get("batoid", {}):
        r = jobs["newtsim_folded_no_obstructions"].trace((field, 0.0), px, py)
        out["centroid_check_mm"] = {"newtsim_u": round(float(r.u[r.ok].mean()), 5),
                                    "batoid_x": round(float(np.mean(xb) * 1e3), 5)}
    print(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
