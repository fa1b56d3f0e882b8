"""Sequential ray-tracing speed: newtsim's vignetting map against batoid on the same rays, same run.

The job is `newtsim optics vignetting DESIGN --grid 9 --rays 2400000 --no-cache`: 82 field points (the axis
and a 9 x 9 grid spanning the sensor) of 2.4 M pupil rays each, 196.8 M rays, every one traced through the
primary, the diagonal, the corrector (when the design has one) and every mechanical obstruction, and counted
by where it was lost. At that size tracing, not start-up, is timed (the map's own function,
:func:`optics.vignetting.vignetting_map`, after a small warm-up map has compiled the kernels; no result
cache is involved).

The reference: batoid (its own environment, ``--batoid-python``, default ``$NEWTSIM_BATOID_PYTHON`` or
/work/peerenv/batoid/bin/python) traces the same pupil points at the same 82 fields through the same
telescope built from the design file (benchmarks/batoid_vignetting_job.py: primary, diagonal, lenses,
detector plane, and the optical apertures counted; batoid has no mechanical obstructions, so newtsim does
more work per ray). For the bare design also batoid's lightest job on the same rays, the previous
benchmark's reference: the paraboloid alone to its focal plane (``batoid_paraboloid_bare``). Both sides
report wall seconds and process CPU seconds (user + system over all threads);
on a shared machine the CPU ratio is the steadier one.

``--before ROOT`` (repeatable) also times a checkout of an older newtsim (e.g. ``git worktree add /tmp/old
<commit>``) on the same job in the same run: the before/after table of docs/performance.md.

Prints JSON. Run: python benchmarks/bench_optics_trace.py [--designs bare,art] [--grid 9] [--rays 2400000]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
BATOID_PYTHON = os.environ.get("NEWTSIM_BATOID_PYTHON", "/work/peerenv/batoid/bin/python")


def worker(design: str, grid: int, rays: int) -> dict:
    """Time one vignetting map in this process (the newtsim on ``sys.path``)."""
    import resource
    import time

    from optics import load_design
    from optics.llvm import init_mitsuba
    from optics.sequential import SequentialTracer
    from optics.vignetting import vignetting_map

    def cpu():
        r = resource.getrusage(resource.RUSAGE_SELF)
        return r.ru_utime + r.ru_stime

    tracer = SequentialTracer(load_design(design), init_mitsuba(), obstruct="analytic")
    vignetting_map(tracer, 2, 1000, 550.0, 0)               # warm-up: compiles (or loads) the kernels
    w0, c0 = time.perf_counter(), cpu()
    res = vignetting_map(tracer, grid, rays, 550.0, 0)
    wall, cpu_s = time.perf_counter() - w0, cpu() - c0
    n = rays * (grid * grid + 1)
    return {"seconds": round(wall, 4), "cpu_s": round(cpu_s, 4), "rays": n, "mrays_per_s": round(n / wall / 1e6, 2),
            "on_axis_throughput": res.on_axis_throughput, "throughput": res.throughput.round(6).tolist(),
            "peak_rss_gib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20, 3)}


def run_worker(root: Path, design: str, grid: int, rays: int) -> dict:
    env = {**os.environ, "PYTHONPATH": str(root)}
    p = subprocess.run([sys.executable, str(HERE / "bench_optics_trace.py"), "--worker", design, "--grid", str(grid),
                        "--rays", str(rays)], cwd=root, env=env, capture_output=True, text=True, check=False)
    if p.returncode:
        return {"error": p.stderr.strip()[-600:]}
    return json.loads(p.stdout[p.stdout.find("{"):])


def rays_file(design: str, grid: int, rays: int, tmp: str) -> str:
    """The pupil points and fields of the map, as the vignetting map makes them, for batoid."""
    from optics import load_design
    from optics.layout import make_layout
    from optics.llvm import init_mitsuba
    from optics.sequential import pupil_uniform_dr
    from optics.vignetting import map_fields

    init_mitsuba()
    layout = make_layout(load_design(design))
    fields = map_fields(layout, (grid, grid))[0]
    px, py = pupil_uniform_dr(rays, layout.r_primary, 0, single=True)
    path = os.path.join(tmp, f"rays_{design}.npz")
    np.savez(path, px=px.numpy().astype(np.float64), py=py.numpy().astype(np.float64), fields=np.asarray(fields))
    return path


def run_batoid(design: str, path: str, job: str = "telescope") -> dict:
    if not os.path.exists(BATOID_PYTHON):
        return {"error": f"no batoid environment at {BATOID_PYTHON} (set NEWTSIM_BATOID_PYTHON)"}
    p = subprocess.run([BATOID_PYTHON, str(HERE / "batoid_vignetting_job.py"), design, path, job], cwd=ROOT,
                       capture_output=True, text=True, check=False)
    if p.returncode:
        return {"error": p.stderr.strip()[-600:]}
    return json.loads(p.stdout[p.stdout.find("{"):])


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--designs", default="bare,art")
    ap.add_argument("--grid", type=int, default=9)
    ap.add_argument("--rays", type=int, default=2_400_000, help="rays per field point")
    ap.add_argument("--before", action="append", default=[], help="root of an older newtsim to time too")
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        print(json.dumps(worker(args.worker, args.grid, args.rays)))
        return None

    out = {"job": f"vignetting map, grid {args.grid} (+ axis), {args.rays} rays per field", "cpus": os.cpu_count(),
           "machine": platform.machine(), "load_avg_1min": round(os.getloadavg()[0], 2)}
    with tempfile.TemporaryDirectory() as tmp:
        for design in args.designs.split(","):
            path = rays_file(design, args.grid, args.rays, tmp)
            b = run_batoid(design, path)
            bp = run_batoid(design, path, "paraboloid") if design == "bare" else {}
            runs = {"newtsim": run_worker(ROOT, design, args.grid, args.rays)}
            for i, root in enumerate(args.before):
                runs[f"before{i + 1}"] = run_worker(Path(root).resolve(), design, args.grid, args.rays)
                runs[f"before{i + 1}"]["root"] = str(root)
            for name, r in runs.items():
                if "seconds" in r and "seconds" in b:
                    r["speed_vs_batoid"] = round(b["seconds"] / r["seconds"], 2)
                    r["cpu_speed_vs_batoid"] = round(b["cpu_s"] / r["cpu_s"], 2)
                if "seconds" in r and "seconds" in bp:
                    r["speed_vs_batoid_paraboloid"] = round(bp["seconds"] / r["seconds"], 2)
                    r["cpu_speed_vs_batoid_paraboloid"] = round(bp["cpu_s"] / r["cpu_s"], 2)
                key = f"newtsim_vignetting_{design}" if name == "newtsim" else f"{name}_vignetting_{design}"
                out[key] = {k: v for k, v in r.items() if k != "throughput"}
            if "throughput" in runs["newtsim"]:
                ref = np.asarray(runs["newtsim"]["throughput"])
                for name, r in runs.items():
                    if name != "newtsim" and "throughput" in r:
                        out[f"{name}_vignetting_{design}"]["max_abs_throughput_change"] = float(
                            np.abs(np.asarray(r["throughput"]) - ref).max())
            out[f"batoid_{design}"] = {k: v for k, v in b.items() if k != "through_optical_apertures"}
            if bp:
                out[f"batoid_paraboloid_{design}"] = {k: v for k, v in bp.items() if k != "through_optical_apertures"}
    print(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
