"""The thesis's CMOS real-vs-synthetic case, Navstar 71, on the full IMX411 (14192 x 10640, 151 Mpixel):
the whole scene rendered to a FITS file, against the plain-numpy detector chain on the same frame size
measured in the same run.

newtsim job: ``examples/scenarios/navstar71_imx411.toml`` as it is: 2 s, rate tracking on the satellite
(the stars trail ~91 unbinned pixels), 2x2 binning, stars to G = 16 (~22,700 on the frame: bundled Gaia to
G = 10, the seeded faint-star model beyond), one object, ray-traced vignetting (traced once and cached
before the timed jobs) and the default scene's detector effects, FITS written with its TRUTH table.

Reference: the plain-numpy chain of ``bench_detector_fullframe.py`` (Poisson, Gaussian read noise,
gain/bias, rounding to uint16, astropy FITS; one generator, one thread), imported from there, on the
unbinned 151-Mpixel frame. Each job runs in its own process (its own peak RSS from ``wait4``); both
import the code of this checkout. Prints JSON.

    nice python benchmarks/bench_navstar71.py [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
from bench_detector_fullframe import (  # the reference chain, the job runner, the optional planted slowdown
    PLANT,
    REFERENCE,
    run,
)

SCENE = ROOT / "examples" / "scenarios" / "navstar71_imx411.toml"

NEWTSIM = PLANT + r'''
import sys, time
from scenes.scene import load_scene
from scenes.app.render import render
scene = load_scene(sys.argv[2])
t0, c0 = time.perf_counter(), time.process_time()
info = render(scene, sys.argv[1], progress=False)
print(info["sources"]["stars"], info["shape"])
print(time.perf_counter() - t0, time.process_time() - c0)
'''

GOAL = {"time_ratio_max": 1.5, "peak_rss_gib_max": 3.0}


def warm_optics_cache() -> None:
    """Ray-trace the scene's vignetting map once (cached), so the timed job only reads it."""
    from optics.design import load_design
    from optics.vignetting import cached_map_fits
    from scenes.scene import load_scene

    cached_map_fits(load_design(load_scene(str(SCENE)).telescope.design))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=None, help="folder for the FITS files (default: a temporary folder)")
    a = ap.parse_args()
    os.environ["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + [p for p in [os.environ.get("PYTHONPATH")] if p])
    sys.path.insert(0, str(ROOT))
    warm_optics_cache()
    rows, cols = 10640, 14192
    with tempfile.TemporaryDirectory(dir=a.out) as tmp:
        ref = run(REFERENCE, rows, cols, os.path.join(tmp, "ref.fits"))
        new = run(NEWTSIM, os.path.join(tmp, "navstar71.fits"), SCENE)
    ratio = new["inner_s"] / ref["inner_s"]
    result = {
        "benchmark": "navstar71_fullframe",
        "scene": str(SCENE.relative_to(ROOT)),
        "frame": [rows, cols], "mpixel": round(rows * cols / 1e6, 1), "output_binned": [rows // 2, cols // 2],
        "cpus": os.cpu_count(),
        "reference_plain_numpy": ref, "newtsim_navstar71": new,
        "time_ratio_newtsim_over_reference": round(ratio, 3),
        "cpu_ratio_newtsim_over_reference": round(new["inner_cpu_s"] / ref["inner_cpu_s"], 3),
        "goal": GOAL,
        "pass": bool(ratio <= GOAL["time_ratio_max"] and new["peak_rss_gib"] <= GOAL["peak_rss_gib_max"]),
    }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
