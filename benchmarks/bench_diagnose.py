"""Benchmark: ``newtsim diagnose`` of a 2048x2048 frame against the whole effect catalogue.

The frame is a 10 s star field on a 2048x2048 window of the ML11002 (stars to mag 15, hot pixels and cosmic
rays in the scene), "measured" with another hardware seed, levels a few per cent off and a hidden real-world
vignetting (``scenes/app/validation/hidden.py``). Printed as JSON:

* ``diagnose_s``: the whole :func:`scenes.app.compare.run_diagnose` wall time, split into ``model_s`` (the
  scene's mean, variance and one realisation), ``compare_s`` (residual statistics) and ``candidates_s``
  (every absent effect fitted), with ``per_effect_s`` for each candidate;
* references measured in the same run on the same machine: ``reference.render_s``, one plain
  ``newtsim render`` of the model scene (a subprocess), and ``reference.numpy_pass_s``, one numpy pass over
  the frame (the chi2 of the residuals: ``sum(((data - model) / sqrt(var))**2)``);
* ``peak_rss_mb``: peak resident memory of the process that ran the diagnosis (the frame and the reference
  render run in subprocesses), and of the render subprocess.

Usage: ``python benchmarks/bench_diagnose.py [--size 2048] [--workdir DIR]``. Goal: ``diagnose_s`` < 60 s on
2 cores.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import runpy
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "scenes" / "app" / "validation" / "hidden.py"  # run as a fresh namespace: its BASES are extended


def _scene(ns: dict, size: int) -> dict:
    import copy

    base = copy.deepcopy(ns["BASES"]["stars"])
    base["detector"].update(width=size, height=size)
    ns["BASES"]["bench"] = base
    return ns["model_scene"]("bench")


def _make_measured(size: int, out: Path) -> None:
    """Child process: render the measured frame (keeps the parent's peak memory the diagnosis's own)."""
    ns = runpy.run_path(str(EXAMPLE))
    _scene(ns, size)
    ns["make_frame"]("bench", lambda s: [ns["OffCentreCos4Vignetting"](s, pupil_mm=70.0, centre_x_mm=2.5,
                                                                        centre_y_mm=-1.5)],
                     ns["Levels"](), out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=int, default=2048, help="window side [pixels]")
    ap.add_argument("--workdir", default=None)
    ap.add_argument("--child-make", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child_make:
        _make_measured(args.size, Path(args.child_make))
        return 0

    tmp = None
    if args.workdir is None:
        tmp = tempfile.TemporaryDirectory()
        work = Path(tmp.name)
    else:
        work = Path(args.workdir)
        work.mkdir(parents=True, exist_ok=True)
    ns = runpy.run_path(str(EXAMPLE))
    model_toml = ns["write_scene"](_scene(ns, args.size), work / "model.toml")
    measured = work / "measured.fits"
    t0 = time.perf_counter()
    subprocess.run([sys.executable, __file__, "--size", str(args.size), "--child-make", str(measured)], check=True,
                   capture_output=True)
    make_s = time.perf_counter() - t0

    # reference 1: one plain `newtsim render` of the same frame, in a subprocess
    t0 = time.perf_counter()
    subprocess.run(["newtsim", "render", str(model_toml), "-o", str(work / "ref.fits"), "--seed", "1"], check=True,
                   capture_output=True)
    render_s = time.perf_counter() - t0
    render_rss_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024

    # the diagnosis, in this process
    from scenes.app.compare import run_diagnose
    from scenes.scene import load_scene

    # per-effect time from the progress callback (called after every fit, also the ones that find nothing)
    stamps: list[tuple[str, float]] = []
    t_diag = time.perf_counter()
    out = run_diagnose(load_scene(str(model_toml)), measured,
                       progress=lambda name: stamps.append((name, time.perf_counter())))
    diagnose_s = time.perf_counter() - t_diag
    rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    secs = out["baseline"]["seconds"]

    # reference 2: one numpy pass over the frame (the residual chi2) on the same arrays
    res = out["_compare"]["_residuals"]
    t0 = time.perf_counter()
    z = (res.data_adu - res.model_adu) / np.sqrt(res.var_adu2)
    chi2 = float(np.dot(z.ravel(), z.ravel()))
    numpy_s = time.perf_counter() - t0

    # the first fit starts when the candidates start (run_diagnose's "seconds" are the candidates')
    start = t_diag + diagnose_s - out["seconds"]
    per_effect = {}
    for name, t in stamps:
        per_effect[name] = round(t - start, 3)
        start = t
    cands = out["candidates"]
    best = next((c for c in cands if c["significant"]), None)
    result = {
        "benchmark": "diagnose",
        "frame": {"shape": list(res.data_adu.shape), "pixels": int(res.data_adu.size), "fitted_pixels": res.n_fit,
                  "scene": "ml11002 star field 10 s, hot pixels + cosmic rays; hidden: off-centre cos^4 vignetting"},
        "machine": {"cpus": os.cpu_count(), "load_avg_1min": round(os.getloadavg()[0], 2)},
        "diagnose_s": round(diagnose_s, 2),
        "model_s": round(secs["model"], 2),
        "compare_s": round(secs["compare"], 2),
        "candidates_s": round(out["seconds"], 2),
        "per_effect_s": dict(sorted(per_effect.items(), key=lambda kv: -kv[1])),
        "candidates": len(cands), "problems": out["problems"],
        "first": best["effect"] if best else "none",
        "reference": {"render_s": round(render_s, 2), "numpy_pass_s": round(numpy_s, 4), "chi2": chi2},
        "ratio_to_render": round(diagnose_s / render_s, 2),
        "peak_rss_mb": round(rss_mb, 1), "render_peak_rss_mb": round(render_rss_mb, 1),
        "make_measured_s": round(make_s, 2),
        "goal_s": 60.0, "within_goal": diagnose_s < 60.0,
    }
    print(json.dumps(result, indent=2))
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
