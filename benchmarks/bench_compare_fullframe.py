"""Benchmark: ``newtsim compare`` and ``newtsim diagnose`` of the full IMX411 frame (14192 x 10640) (issue 12).

Renders the built-in ``default`` scene once (``newtsim render default -o full.fits --no-png``: the reference,
timed in the same run), then runs ``newtsim compare default full.fits --json ...`` and ``newtsim diagnose
default full.fits --json ...`` on it, each in its own subprocess, one after the other (never two full-frame
jobs at once). Every step runs under a small wrapper process whose only child is the step, so
``resource.getrusage(RUSAGE_CHILDREN).ru_maxrss`` of the wrapper is that step's peak resident memory.
Printed as JSON:

* ``render_s`` / ``render_peak_rss_mb``: the reference;
* ``compare_s`` / ``compare_peak_rss_mb`` and ``diagnose_s`` / ``diagnose_peak_rss_mb``, with their ratios to
  the render time;
* ``goals``: compare <= 3 GiB and <= 3 x render; diagnose <= 3 GiB and <= 10 x render; ``ok`` for each;
* ``compare`` / ``diagnose``: the headline numbers of their JSON (chi2/dof, sampling, verdict).

Usage: ``python benchmarks/bench_compare_fullframe.py [--workdir DIR] [--skip-diagnose]``. Takes a few
minutes and ~2 GB of disk-backed memory per step; the frame (300 MB) is left in ``--workdir`` when given.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
GIB = 1024 ** 3

_WRAPPER = (
    "import resource, subprocess, sys, time\n"
    "t = time.perf_counter()\n"
    "p = subprocess.run(sys.argv[1:], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)\n"
    "dt = time.perf_counter() - t\n"
    "rss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss\n"
    "sys.stderr.write(p.stderr[-4000:])\n"
    "print(dt, rss * 1024, p.returncode)\n"
)


def step(args: list[str], cwd: Path) -> dict:
    """Run ``newtsim ARGS`` in a wrapper (in ``cwd``: diagnose writes its ledger beside the scene, here the
    built-in ``default``): wall time [s], peak RSS [bytes] and return code of the step alone."""
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    cmd = [sys.executable, "-c", _WRAPPER, sys.executable, "-m", "scenes.app.cli", *args]
    p = subprocess.run(cmd, check=False, capture_output=True, text=True, env=env, cwd=cwd)
    dt, rss, rc = p.stdout.split()[-3:]
    if int(rc) != 0:
        raise SystemExit(f"newtsim {' '.join(args)} failed ({rc}): {p.stderr[-2000:]}")
    return {"s": float(dt), "peak_rss_bytes": int(rss), "stderr_tail": p.stderr.strip().splitlines()[-1:]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--workdir", default=None)
    ap.add_argument("--skip-diagnose", action="store_true")
    args = ap.parse_args(argv)
    tmp = None
    if args.workdir is None:
        tmp = tempfile.TemporaryDirectory()
        work = Path(tmp.name)
    else:
        work = Path(args.workdir)
        work.mkdir(parents=True, exist_ok=True)
    frame = work / "full.fits"
    out: dict = {"frame": "default scene, full IMX411 14192 x 10640", "cpus": os.cpu_count()}
    r = step(["render", "default", "-o", str(frame), "--no-png"], work)
    out["render_s"], out["render_peak_rss_mb"] = r["s"], r["peak_rss_bytes"] / 2 ** 20
    c = step(["compare", "default", str(frame), "--json", str(work / "compare.json")], work)
    out["compare_s"], out["compare_peak_rss_mb"] = c["s"], c["peak_rss_bytes"] / 2 ** 20
    out["compare_over_render"] = c["s"] / r["s"]
    cj = json.loads((work / "compare.json").read_text())
    out["compare"] = {k: cj.get(k) for k in ("chi2_per_dof", "n_compared", "misfit", "outliers")}
    out["compare"]["sampling"] = {k: cj["sampling"][k] for k in ("binning_k", "binned_shape", "bands",
                                                                  "sample_fraction", "outlier_columns")}
    goals = {"compare_rss_le_3GiB": c["peak_rss_bytes"] <= 3 * GIB, "compare_le_3x_render": c["s"] <= 3 * r["s"]}
    if not args.skip_diagnose:
        time.sleep(1)
        d = step(["diagnose", "default", str(frame), "--json", str(work / "diagnose.json")], work)
        out["diagnose_s"], out["diagnose_peak_rss_mb"] = d["s"], d["peak_rss_bytes"] / 2 ** 20
        out["diagnose_over_render"] = d["s"] / r["s"]
        dj = json.loads((work / "diagnose.json").read_text())
        out["diagnose"] = {"verdict": dj["verdict"], "significant": dj["significant"],
                           "top": [(x["effect"], x["scale"], x["delta_bic"], x["significant"]) for x in dj["candidates"][:6]]}
        goals.update(diagnose_rss_le_3GiB=d["peak_rss_bytes"] <= 3 * GIB, diagnose_le_10x_render=d["s"] <= 10 * r["s"])
    out["goals"] = goals
    out["ok"] = all(goals.values())
    print(json.dumps(out, indent=1, default=str))
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
