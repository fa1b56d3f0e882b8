"""Full IMX411 frame (14192 x 10640, 151 Mpixel): newtsim's detector chain with every detector effect on,
FITS writing included, against the plain-numpy chain measured in the same run.

Reference (issue 2): Poisson + normal read noise + gain/bias + rounding to uint16 + writing the FITS, with
one single-threaded numpy generator, on the same expected signal. Each job runs in its own process so its
peak resident memory (ru_maxrss) is its own. Prints JSON.

    python benchmarks/bench_detector_fullframe.py [--rows N] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

SIGNAL_E = 46.7  # ~ the 2 s sky background of the default scene [e-]

REFERENCE = r'''
import sys, time, numpy as np
from astropy.io import fits
rows, cols, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
t0, c0 = time.perf_counter(), time.process_time()
rng = np.random.default_rng(1)
signal = np.full((rows, cols), {signal}, dtype=np.float32)
e = rng.poisson(signal).astype(np.float64)
e += rng.normal(0.0, 3.5, size=e.shape)
adu = np.clip(np.round(e / 1.22 + 500.0), 0, 65535).astype(np.uint16)
fits.PrimaryHDU(adu).writeto(out, overwrite=True)
print(time.perf_counter() - t0, time.process_time() - c0)
'''.replace("{signal}", str(SIGNAL_E))

#: first lines of every newtsim job: the optional planted slowdown (NEWTSIM_BENCH_SLOW, benchmarks/stages.py)
PLANT = f"import sys; sys.path.insert(0, {os.path.dirname(os.path.abspath(__file__))!r}); from stages import plant; plant()\n"

NEWTSIM = PLANT + r'''
import sys, time
from scenes.scene import load_scene
from scenes.app.render import render
rows, cols, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
sets = ["detector.width=%d" % cols, "detector.height=%d" % rows, "exposure.seed=1",
        "sky.background_mag_arcsec2=19.72",
        # every detector effect of the catalogue on
        "effects.prnu.sigma=0.01", "effects.dsnu.sigma=0.3", "effects.hot_pixels.count=20000",
        "effects.dead_pixels.count=2000", "effects.column_defects.hot_columns=4", "effects.row_noise.sigma_e=1.0",
        "effects.reset_noise.capacitance_ff=0.5", "effects.nonlinearity.beta=0.01", "effects.blooming.up_fraction=0.5",
        "effects.gain_regions.nx=2", "effects.amp_glow.model='edge'", "effects.bias_gradient.gradient_x_adu=4.0",
        "effects.cosmic_rays.flux_per_cm2_s=5.0", "effects.crosstalk.alpha=0.0005"]
scene = load_scene(sys.argv[4], sets)
t0, c0 = time.perf_counter(), time.process_time()
render(scene, out, progress=False)
print(time.perf_counter() - t0, time.process_time() - c0)
'''


def run(code: str, *args) -> dict:
    """Run ``code`` in a fresh interpreter; return its wall time, CPU time (user + system) and peak RSS, and the
    timed part's wall and CPU time (``inner_s``, ``inner_cpu_s``: the last line the code prints)."""
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-c", code, *map(str, args)], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    out, err = proc.stdout.read().decode(), proc.stderr.read().decode()
    if status != 0:
        raise RuntimeError(f"job failed:\n{err}")
    inner = [float(x) for x in out.strip().splitlines()[-1].split()]  # timed part: wall [, CPU of all threads]
    res = {"wall_s": round(wall, 2), "inner_s": round(inner[0], 3),
           "cpu_s": round(usage.ru_utime + usage.ru_stime, 2), "peak_rss_gib": round(usage.ru_maxrss / 2 ** 20, 3)}
    if len(inner) > 1:
        res["inner_cpu_s"] = round(inner[1], 3)
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=10640)
    ap.add_argument("--cols", type=int, default=14192)
    ap.add_argument("--out", default=None, help="folder for the FITS files (default: a temporary folder)")
    a = ap.parse_args()
    here = os.path.dirname(os.path.abspath(__file__))
    scene = os.path.join(here, "..", "examples", "scenes", "empty_sky_imx411.toml")
    with tempfile.TemporaryDirectory(dir=a.out) as tmp:
        ref = run(REFERENCE, a.rows, a.cols, os.path.join(tmp, "ref.fits"))
        new = run(NEWTSIM, a.rows, a.cols, os.path.join(tmp, "newtsim.fits"), scene)
    result = {
        "benchmark": "detector_fullframe",
        "frame": [a.rows, a.cols], "mpixel": round(a.rows * a.cols / 1e6, 1), "cpus": os.cpu_count(),
        "reference_plain_numpy": ref, "newtsim_all_effects": new,
        "time_ratio_newtsim_over_reference": round(new["inner_s"] / ref["inner_s"], 3),
        "cpu_ratio_newtsim_over_reference": round(new["inner_cpu_s"] / ref["inner_cpu_s"], 3),
        "goal": {"time_ratio_max": 1.0, "peak_rss_gib_max": 3.0},
        "pass": bool(new["inner_s"] <= ref["inner_s"] and new["peak_rss_gib"] <= 3.0),
    }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
