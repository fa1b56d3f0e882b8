"""Benchmark: ``newtsim diagnose --series`` of ten 2048x2048 frames against the whole effect catalogue.

The series is the flat series of :mod:`scenes.app.validation.series_cases` ("nonlinearity": a flat screen
at ten exposure levels, a compressive response beta = 0.04 and a lamp 1 % off) on a 2048x2048 window of the
ML11002, rendered in a subprocess. Printed as JSON:

* ``series_diagnose_s``: the wall time of :func:`scenes.app.compare.series.run_series_diagnose` (the ten
  models, the joint fits of every candidate, the held-out scores, the separation), and its peak memory;
* references from the same run: ``reference.render_s``, the ten frames' plain render (subprocess), and
  ``reference.single_diagnose_s``, one single-frame :func:`scenes.app.compare.run_diagnose` of the last frame.

Usage: ``python benchmarks/bench_series.py [--size 2048] [--frames 10] [--workdir DIR]``. Goal:
``series_diagnose_s`` < 300 s on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _case(size: int, n: int):
    from scenes.app.validation.series_cases import cases

    case = next(c for c in cases(size) if c.name == "nonlinearity")
    times = [1.0 + 7.0 * i / max(n - 1, 1) for i in range(n)]
    case.frames = [{"set": {"exposure.time_s": round(t, 3)}, "truth": case.frames[0]["truth"]} for t in times]
    return case


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=int, default=2048)
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--workdir", default=None)
    ap.add_argument("--child-make", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child_make:
        from scenes.app.validation.series_cases import write_case

        write_case(_case(args.size, args.frames), args.child_make)
        return 0
    tmp = tempfile.TemporaryDirectory() if args.workdir is None else None
    work = Path(tmp.name if tmp else args.workdir)
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    subprocess.run([sys.executable, __file__, "--size", str(args.size), "--frames", str(args.frames),
                    "--child-make", str(work)], check=True)
    render_s = time.perf_counter() - t0

    from scenes.app.compare import run_diagnose
    from scenes.app.compare.series import load_series, run_series_diagnose

    series = load_series(work / "series.toml")
    t0 = time.perf_counter()
    d = run_series_diagnose(series)
    series_s = time.perf_counter() - t0
    rss_series = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    last = series.frames[-1]
    t0 = time.perf_counter()
    run_diagnose(last.scene, last.file)
    single_s = time.perf_counter() - t0
    best = next((c for c in d["candidates"] if c["significant"]), None)
    out = {"size": args.size, "frames": args.frames, "series_diagnose_s": round(series_s, 1),
           "peak_rss_mb": round(rss_series), "named": best["effect"] if best else None,
           "params": best["params"] if best else None,
           "reference": {"render_s": round(render_s, 1), "single_diagnose_s": round(single_s, 1)},
           "ratio_to_single": round(series_s / single_s, 2), "goal_s": 300, "ok": series_s < 300}
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
