"""The sensor-physics effects' cost: a full IMX411 frame (14192 x 10640) with the CMOS-applicable new
effects (brighter_fatter, ipc, rts_noise, persistence) against the same frame without them, same run; and a
full ML11002 frame (4008 x 2672) with and without cti.

Each render runs in its own process (wall time, CPU time, peak RSS its own), FITS writing included; the
frame without the effects is rendered first and is the persistence effect's previous frame. Prints JSON.
Goal (issue 17): IMX411 time ratio <= 1.5. The JSON also gives the CPU-time ratio (user + system, all
threads), which does not depend on what else the machine runs.

    python benchmarks/bench_sensor_physics.py [--rows N] [--cols N] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_detector_fullframe import run  # noqa: E402  (same process runner as the full-frame benchmark)

RENDER = r'''
import sys, time, json
from scenes.scene import load_scene
from scenes.app.render import render
out, scene_path, sets = sys.argv[1], sys.argv[2], json.loads(sys.argv[3])
scene = load_scene(scene_path, sets)
t0, c0 = time.perf_counter(), time.process_time()
render(scene, out, progress=False)
print(time.perf_counter() - t0, time.process_time() - c0)
'''


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=10640)
    ap.add_argument("--cols", type=int, default=14192)
    ap.add_argument("--out", default=None, help="folder for the FITS files (default: a temporary folder)")
    a = ap.parse_args()
    here = os.path.dirname(os.path.abspath(__file__))
    scene = os.path.join(here, "..", "examples", "scenes", "empty_sky_imx411.toml")
    window = [f"detector.width={a.cols}", f"detector.height={a.rows}", "exposure.seed=1"]
    with tempfile.TemporaryDirectory(dir=a.out) as tmp:
        base_fits = os.path.join(tmp, "base.fits")
        base = run(RENDER, base_fits, scene, json.dumps(window))
        new_sets = window + ["effects.brighter_fatter.a10_per_e=1e-7", "effects.ipc.alpha=0.005",
                             "effects.rts_noise.fraction=0.0005",
                             f"effects.persistence.previous_frame='{base_fits}'",
                             "effects.persistence.time_since_s=5.0"]
        new = run(RENDER, os.path.join(tmp, "new.fits"), scene, json.dumps(new_sets))
        ccd = ["detector.preset='ml11002'", "exposure.seed=1"]
        ccd_base = run(RENDER, os.path.join(tmp, "ccd.fits"), scene, json.dumps(ccd))
        ccd_cti = run(RENDER, os.path.join(tmp, "ccd_cti.fits"), scene,
                      json.dumps(ccd + ["effects.cti.days_in_orbit=1000"]))
    ratio = new["inner_s"] / base["inner_s"]
    result = {
        "benchmark": "sensor_physics",
        "imx411": {"frame": [a.rows, a.cols], "mpixel": round(a.rows * a.cols / 1e6, 1),
                   "without_new_effects": base, "with_bf_ipc_rts_persistence": new,
                   "time_ratio": round(ratio, 3),
                   # the CPU time (all threads) is the figure to trust on a shared, loaded machine
                   "cpu_ratio": round(new["cpu_s"] / base["cpu_s"], 3)},
        "ml11002_cti": {"frame": [2672, 4008], "without_cti": ccd_base, "with_cti": ccd_cti,
                        "cti_extra_s": round(ccd_cti["inner_s"] - ccd_base["inner_s"], 2)},
        "cpus": os.cpu_count(), "load_average_1min": round(os.getloadavg()[0], 2),
        "goal": {"time_ratio_max": 1.5},
        "pass": bool(ratio <= 1.5),
    }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
