"""Misalignment fit on a 2048 x 2048 star field: the joint fit and the ranking of perturbation families.

Job: art, a 2048 x 2048 pixel frame of 9 um pixels (18.4 mm square) at the centre of the focal plane
with ``--stars`` stars at random places; their measured positions and second moments are synthetic
(the diagonal tilted 0.1 deg about x, traced with an independent ray sample, plus an isotropic 3 um rest
and 1 um / 5 % noise), as the comparison's source measurements would give them. Timed: the joint
Gauss-Newton fit of the seven default perturbations (optics.alignment.fit_perturbations) and the ranking
of all eight families (rank_perturbations: nine fits). Reference in the same run: one plain evaluation of
the optics' moments at the 8 x 8 interpolation nodes (no derivatives). Goal: the fit under a minute.

Prints JSON. Run: python benchmarks/bench_alignment.py [--stars N]
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


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--stars", type=int, default=500)
    ap.add_argument("--design", default="art")
    args = ap.parse_args(argv)

    from optics import load_design
    from optics.alignment import _interpolation, fit_perturbations, rank_perturbations
    from optics.design import with_perturbation
    from optics.gradients import spot_moments
    from optics.llvm import init_mitsuba
    from optics.sequential import SequentialTracer

    mi = init_mitsuba()
    d = load_design(args.design)
    rng = np.random.default_rng(0)
    half = 1024 * 9e-3
    u, v = rng.uniform(-half, half, args.stars), rng.uniform(-half, half, args.stars)
    fields = np.degrees(np.arctan(-np.stack([u, v], -1) / d.primary.focal_length_mm))
    truth = {"diagonal_tilt_x_deg": 0.1}
    m = spot_moments(SequentialTracer(with_perturbation(d, **truth), mi), fields, n_rays=3000, seed=5)
    rest, sp = 3e-3 ** 2, 1e-3
    sm = 0.05 * (m.get("muu_mm2") + m.get("mvv_mm2")) / 2 + 0.05 * rest
    meas = {"cu_mm": m.get("cu_mm") + rng.normal(0, sp, len(u)), "cv_mm": m.get("cv_mm") + rng.normal(0, sp, len(u)),
            "muu_mm2": m.get("muu_mm2") + rest + rng.normal(0, 1, len(u)) * sm,
            "mvv_mm2": m.get("mvv_mm2") + rest + rng.normal(0, 1, len(u)) * sm,
            "muv_mm2": m.get("muv_mm2") + rng.normal(0, 1, len(u)) * sm}
    sigma = {"cu_mm": sp, "cv_mm": sp, "muu_mm2": sm, "mvv_mm2": sm, "muv_mm2": sm}
    tr = SequentialTracer(d, mi)
    nodes, _ = _interpolation(fields, 8)
    out = {"design": d.name, "stars": len(u), "frame_px": [2048, 2048], "pixel_um": 9.0, "truth": truth,
           "cpus": os.cpu_count(), "machine": platform.machine()}
    spot_moments(tr, nodes, n_rays=1500)
    t0 = time.perf_counter()
    spot_moments(tr, nodes, n_rays=1500)
    out["reference_plain_moments_64_nodes_s"] = round(time.perf_counter() - t0, 4)
    t0 = time.perf_counter()
    fit = fit_perturbations(d, mi, fields, meas, sigma, tracer=tr)
    out["joint_fit_s"] = round(time.perf_counter() - t0, 3)
    out["joint_fit_iterations"] = fit.iterations
    out["joint_fit"] = {n: [round(float(x), 5), round(float(e), 5)] for n, x, e in zip(fit.names, fit.values, fit.errors)}
    out["explanation"] = fit.explanation
    t0 = time.perf_counter()
    cands, _ = rank_perturbations(d, mi, fields, meas, sigma, tracer=tr)
    out["rank_families_s"] = round(time.perf_counter() - t0, 3)
    out["ranking"] = [[c.family, round(c.delta_chi2, 1)] for c in cands[:3]]
    out["goal_s"] = 60.0
    out["goal_met"] = out["joint_fit_s"] < 60 and out["rank_families_s"] < 60
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
