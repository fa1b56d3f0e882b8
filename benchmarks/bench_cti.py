"""CTI cost on a full ML11002 frame (4008 x 2672): the well-fill model (occupancy per volume level, express 1
and 2) against the previous implementation (one trap pool per species, commit bd80916, copied below), same
run, same process, same input.

Two measurements: the CTI function alone on a full frame of charge (a 100 e- sky with Poisson noise and 400
stars), and a whole exposure of the full frame by the detector chain with cti on (Detector.expose: charge,
CTI, read-out, ADU), the previous function swapped in for the reference. CPU time (user + system) is the
figure to trust on a shared machine; wall time is given too. Prints JSON.

    python benchmarks/bench_cti.py [--repeat N]
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

import detector.effects.cti as cti_mod
from detector import Detector, build_effects, make_sensor


def previous_cti_transfer(image_e, density_per_px, release_time_s, transfer_s: float, beta: float,
                          well_e: float, first_transfers: int = 1, return_trapped: bool = False, **_ignored):
    """The previous implementation (commit bd80916): one pool per species, capture compared with the
    species' total trapped charge."""
    rho = np.asarray(density_per_px, np.float64)[:, None]
    decay = np.exp(-float(transfer_s) / np.asarray(release_time_s, np.float64))[:, None]
    img = np.array(image_e, dtype=np.float64)
    ny, nx = img.shape
    trapped = np.zeros((rho.shape[0], nx))
    inv_w = 1.0 / float(well_e)
    for j in range(ny):
        n = img[j]
        rel = trapped * (1.0 - decay)
        trapped -= rel
        n += rel.sum(axis=0)
        target = (rho * (j + first_transfers)) * np.power(np.maximum(n, 0.0) * inv_w, beta)[None, :]
        cap = np.maximum(target - trapped, 0.0)
        tot = cap.sum(axis=0)
        over = tot > n
        if over.any():
            cap[:, over] *= (n[over] / tot[over])[None, :]
            tot = cap.sum(axis=0)
        trapped += cap
        n -= tot
    return (img, trapped.sum(axis=0)) if return_trapped else img


def timed(fn, *args, **kw):
    c0, w0 = time.process_time(), time.perf_counter()
    out = fn(*args, **kw)
    return out, time.process_time() - c0, time.perf_counter() - w0


def frame_charge(shape, rng):
    """A 100 e- sky (Poisson) with 400 Gaussian stars of 1e3-1e5 e- (sigma 1.5 px)."""
    img = rng.poisson(100.0, shape).astype(np.float64)
    ys, xs = rng.uniform(5, shape[0] - 5, 400), rng.uniform(5, shape[1] - 5, 400)
    flux = 10 ** rng.uniform(3, 5, 400)
    for y, x, f in zip(ys, xs, flux):
        y0, x0 = int(y) - 5, int(x) - 5
        yy, xx = np.mgrid[y0:y0 + 11, x0:x0 + 11]
        img[y0:y0 + 11, x0:x0 + 11] += f / (2 * np.pi * 1.5**2) * np.exp(-((yy - y) ** 2 + (xx - x) ** 2) / 4.5)
    return img


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=1, help="repeat each timing, keep the fastest")
    a = ap.parse_args()
    sensor = make_sensor("ml11002", {})
    rng = np.random.default_rng(1)
    charge = frame_charge(sensor.shape, rng)
    dwell = cti_mod.ML11002_PARALLEL_TRANSFER_S
    dens = [0.1 * r for r in cti_mod.ACS_RELATIVE_DENSITY]
    taus = [t * dwell for t in cti_mod.ACS_RELEASE_TRANSFERS]
    args = (charge, dens, taus, dwell, 0.478, sensor.full_well_e)

    def best(fn, **kw):
        runs = [timed(fn, *args, **kw) for _ in range(a.repeat)]
        return runs[0][0], min(r[1] for r in runs), min(r[2] for r in runs)

    old, old_cpu, old_wall = best(previous_cti_transfer)
    new1, new1_cpu, new1_wall = best(cti_mod.cti_transfer, express=1)
    _, new2_cpu, new2_wall = best(cti_mod.cti_transfer, express=2)
    loss_old, loss_new = float((charge - old).sum()), float((charge - new1).sum())

    # whole exposure through the detector chain, cti on (defaults: 0.1 traps/px, HST ACS species)
    signal = (charge / 1.0).astype(np.float32)
    det = Detector(sensor, build_effects({"cti": {}}, sensor), workers=1)
    def best_frame(d):
        runs = [timed(d.expose, signal, 1.0, 3) for _ in range(a.repeat)]
        return min(r[1] for r in runs), min(r[2] for r in runs)

    keep = cti_mod.cti_transfer
    try:
        cti_mod.cti_transfer = previous_cti_transfer
        fr_old_cpu, fr_old_wall = best_frame(det)
    finally:
        cti_mod.cti_transfer = keep
    fr_new_cpu, fr_new_wall = best_frame(det)
    fr_plain_cpu, fr_plain_wall = best_frame(Detector(sensor, [], workers=1))

    result = {
        "benchmark": "cti",
        "frame": list(sensor.shape), "species": {"density_per_px": dens, "release_time_s": taus},
        "cti_function": {
            "previous_cpu_s": round(old_cpu, 3), "previous_wall_s": round(old_wall, 3),
            "well_fill_express1_cpu_s": round(new1_cpu, 3), "well_fill_express1_wall_s": round(new1_wall, 3),
            "well_fill_express2_cpu_s": round(new2_cpu, 3), "well_fill_express2_wall_s": round(new2_wall, 3),
            "cpu_ratio_express1": round(new1_cpu / old_cpu, 2), "cpu_ratio_express2": round(new2_cpu / old_cpu, 2),
            "charge_lost_e": {"previous": round(loss_old, 1), "well_fill_express1": round(loss_new, 1)},
        },
        "full_frame_exposure": {
            "without_cti_cpu_s": round(fr_plain_cpu, 3), "without_cti_wall_s": round(fr_plain_wall, 3),
            "previous_cti_cpu_s": round(fr_old_cpu, 3), "previous_cti_wall_s": round(fr_old_wall, 3),
            "well_fill_cti_cpu_s": round(fr_new_cpu, 3), "well_fill_cti_wall_s": round(fr_new_wall, 3),
            "cpu_ratio": round(fr_new_cpu / fr_old_cpu, 2), "wall_ratio": round(fr_new_wall / fr_old_wall, 2),
        },
        "goal": {"full_frame_with_cti_time_ratio_max": 2.0},
        "pass": bool(fr_new_cpu / fr_old_cpu <= 2.0),
        "cpus": os.cpu_count(), "load_average_1min": round(os.getloadavg()[0], 2),
    }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
