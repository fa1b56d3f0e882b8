"""Gradient of the PSF moments at 9 field points (drjit forward-mode AD) against the plain forward trace.

Job: the art design (with its corrector), a 3 x 3 grid of field points over 90 % of the IMX411 sensor,
``--rays`` pupil rays per field; the spot moments (centroid, second moments, RMS spot, throughput) and
their Jacobian with respect to all 14 perturbations of ``[perturbation]`` (optics.gradients.spot_moments,
one forward traversal with replicated tangents). Reference in the same run: the same moments without
derivatives (one ray bundle per field, no replication), i.e. the plain forward trace. Also the cost of
the Jacobian by central finite differences (28 plain evaluations), which the AD replaces.

The first call of each kind compiles its LLVM kernel (``cold_s``; drjit keeps compiled kernels on disk,
so a second process starts warm); the goal (< 1 s on 2 cores) is for one warm gradient evaluation.

Prints JSON. Run: python benchmarks/bench_optics_gradients.py [--rays N] [--repeat R] [--design art]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))


def timed(fn, repeat):
    t0 = time.perf_counter()
    fn()
    cold = time.perf_counter() - t0
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return {"cold_s": round(cold, 4), "best_s": round(min(times), 4), "median_s": round(float(np.median(times)), 4)}


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--rays", type=int, default=2000)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--design", default="art")
    args = ap.parse_args(argv)

    from optics import load_design
    from optics.gradients import (
        default_steps,
        detector_field_points,
        finite_difference_jacobian,
        perturbation_names,
        spot_moments,
    )
    from optics.llvm import init_mitsuba
    from optics.sequential import SequentialTracer

    mi = init_mitsuba()
    d = load_design(args.design)
    tr = SequentialTracer(d, mi)
    fields = detector_field_points(d, 3)
    wrt = perturbation_names(d)
    out = {"design": d.name, "fields": len(fields), "rays_per_field": args.rays, "parameters": len(wrt),
           "cpus": os.cpu_count(), "machine": platform.machine()}
    out["plain_forward"] = timed(lambda: spot_moments(tr, fields, n_rays=args.rays), args.repeat)
    out["ad_gradient"] = timed(lambda: spot_moments(tr, fields, wrt, n_rays=args.rays), args.repeat)
    t0 = time.perf_counter()
    finite_difference_jacobian(tr, fields, wrt, default_steps(wrt, d), n_rays=args.rays)
    out["finite_difference_jacobian_s"] = round(time.perf_counter() - t0, 4)
    out["ad_over_plain"] = round(out["ad_gradient"]["median_s"] / out["plain_forward"]["median_s"], 2)
    out["goal_s"] = 1.0
    out["goal_met"] = out["ad_gradient"]["median_s"] < 1.0
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
