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

#: the reference job: the plain-numpy chain on the same expected signal, FITS written
REFERENCE_JOB = r'''
import numpy as np
from astropy.io import fits
def reference_job(rows, cols, out):
    rng = np.random.default_rng(1)
    signal = np.full((rows, cols), {signal}, dtype=np.float32)
    e = rng.poisson(signal).astype(np.float64)
    e += rng.normal(0.0, 3.5, size=e.shape)
    adu = np.clip(np.round(e / 1.22 + 500.0), 0, 65535).astype(np.uint16)
    fits.PrimaryHDU(adu).writeto(out, overwrite=True)
'''.replace("{signal}", str(SIGNAL_E))

REFERENCE = REFERENCE_JOB + r'''
import sys, time
rows, cols, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
t0, c0 = time.perf_counter(), time.process_time()
reference_job(rows, cols, out)
print(time.perf_counter() - t0, time.process_time() - c0)
'''

#: first lines of every newtsim job: the optional planted slowdown (NEWTSIM_BENCH_SLOW, benchmarks/stages.py)
PLANT = f"import sys; sys.path.insert(0, {os.path.dirname(os.path.abspath(__file__))!r}); from stages import plant; plant()\n"

#: the newtsim job's scene overrides: the frame size and every detector effect of the catalogue on
NEWTSIM_SCENE = r'''
from scenes.scene import load_scene
from scenes.app.render import render
def newtsim_scene(path, rows, cols):
    return load_scene(path, [
        "detector.width=%d" % cols, "detector.height=%d" % rows, "exposure.seed=1",
        "sky.background_mag_arcsec2=19.72",
        "effects.prnu.sigma=0.01", "effects.dsnu.sigma=0.3", "effects.hot_pixels.count=20000",
        "effects.dead_pixels.count=2000", "effects.column_defects.hot_columns=4", "effects.row_noise.sigma_e=1.0",
        "effects.reset_noise.capacitance_ff=0.5", "effects.nonlinearity.beta=0.01", "effects.blooming.up_fraction=0.5",
        "effects.gain_regions.nx=2", "effects.amp_glow.model='edge'", "effects.bias_gradient.gradient_x_adu=4.0",
        "effects.cosmic_rays.flux_per_cm2_s=5.0", "effects.crosstalk.alpha=0.0005"])
'''

NEWTSIM = PLANT + NEWTSIM_SCENE + r'''
import sys, time
rows, cols, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
scene = newtsim_scene(sys.argv[4], rows, cols)
t0, c0 = time.perf_counter(), time.process_time()
render(scene, out, progress=False)
print(time.perf_counter() - t0, time.process_time() - c0)
'''

#: ``--repeat N``: both jobs in one interpreter, alternated N times (reference, newtsim, reference, ...), the least
#: wall and CPU time of each over the N turns. One start-up for all; the least of many short turns is what a
#: loaded, shared machine scatters least (the quick check of benchmarks/run.py)
ALTERNATED = PLANT + REFERENCE_JOB + NEWTSIM_SCENE + r'''
import json, os, sys, time
rows, cols, folder, n = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], int(sys.argv[5])
scene = newtsim_scene(sys.argv[4], rows, cols)
times = {"reference": [], "newtsim": []}
for i in range(n):
    for job in times:
        t0, c0, u0 = time.perf_counter(), time.process_time(), os.times().user
        if job == "reference":
            reference_job(rows, cols, os.path.join(folder, "ref.fits"))
        else:
            render(scene, os.path.join(folder, "newtsim.fits"), progress=False)
        times[job].append([time.perf_counter() - t0, time.process_time() - c0, os.times().user - u0])
print(json.dumps(times))
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


def alternated(rows: int, cols: int, folder: str, scene: str, n: int) -> tuple[dict, dict, dict]:
    """Both jobs alternated ``n`` times in one fresh interpreter: each one's least wall, CPU and user CPU time
    (``inner_s``, ``inner_cpu_s``, ``inner_user_s``: the system time of writing files and first touching memory
    left out), the process's peak memory, and every turn's [wall, cpu, user]."""
    proc = subprocess.Popen([sys.executable, "-c", ALTERNATED, str(rows), str(cols), folder, scene, str(n)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)
    out, err = proc.stdout.read().decode(), proc.stderr.read().decode()
    if status != 0:
        raise RuntimeError(f"job failed:\n{err}")
    turns = json.loads(out.strip().splitlines()[-1])
    peak = round(usage.ru_maxrss / 2 ** 20, 3)
    best = {job: {"inner_s": round(min(t[0] for t in ts), 3), "inner_cpu_s": round(min(t[1] for t in ts), 3),
                  "inner_user_s": round(min(t[2] for t in ts), 3), "peak_rss_gib": peak} for job, ts in turns.items()}
    return best["reference"], best["newtsim"], turns


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=10640)
    ap.add_argument("--cols", type=int, default=14192)
    ap.add_argument("--out", default=None, help="folder for the FITS files (default: a temporary folder)")
    ap.add_argument("--repeat", type=int, default=1,
                    help="> 1: both jobs alternated in one process, the least time of each (peak memory shared)")
    a = ap.parse_args()
    here = os.path.dirname(os.path.abspath(__file__))
    scene = os.path.join(here, "..", "examples", "scenes", "empty_sky_imx411.toml")
    with tempfile.TemporaryDirectory(dir=a.out) as tmp:
        if a.repeat > 1:
            ref, new, turns = alternated(a.rows, a.cols, tmp, scene, a.repeat)
        else:
            ref = run(REFERENCE, a.rows, a.cols, os.path.join(tmp, "ref.fits"))
            new = run(NEWTSIM, a.rows, a.cols, os.path.join(tmp, "newtsim.fits"), scene)
            turns = None
    result = {
        "benchmark": "detector_fullframe", "repeat": a.repeat, "turns": turns,
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
