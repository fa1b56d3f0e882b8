"""Stage-by-stage profile of one render: CPU seconds (of the calling threads), thread wall seconds and calls of
every detector stage and effect, the scene's signal (``_photo``), FITS writing, and the peak resident memory.

Each timed callable is wrapped (a module attribute or a class method, looked up at call time by the code
that calls it) so the time summed over the worker threads is attributed to it; an outer stage includes
its inner ones (``charge_tile`` contains ``shot_noise``). Run on any scene file with overrides:

    PYTHONPATH=$PWD python benchmarks/stages.py SCENE.toml [--set key=value ...] [--json OUT]

The same wrapping plants an artificial slowdown for the benchmark check (:func:`plant`, environment
variable ``NEWTSIM_BENCH_SLOW="module:attribute[*factor]"``, e.g. ``detector.chain:shot_noise*2``: the
callable's work is done ``factor`` times, so that stage costs ``factor`` times as much).
"""

from __future__ import annotations

import argparse
import functools
import importlib
import json
import os
import resource
import sys
import threading
import time
from collections import defaultdict
from pathlib import Path

#: the detector chain's own stages (module:attribute); the effects' apply/couple/prepare_frame are added
CHAIN = ["detector.chain:shot_noise", "detector.chain:read_noise", "detector.chain:adc", "detector.chain:bin_sum", "detector.chain:bin_sum_digital",
         "detector.chain:Detector._photo", "detector.chain:Detector.charge_tile",
         "detector.chain:Detector.finish_tile", "detector.chain:Detector.field_signal",
         "detector.chain:Detector.frame_state", "detector.chain:Detector.couple",
         "detector.fits_io:write_streamed", "scenes.app.render:prepare"]


def _resolve(spec: str):
    mod, _, attr = spec.partition(":")
    owner = importlib.import_module(mod)
    parts = attr.split(".")
    for p in parts[:-1]:
        owner = getattr(owner, p)
    return owner, parts[-1]


def wrap(spec: str, make):
    """Replace ``module:attr[.attr]`` by ``make(original)``; returns the original."""
    owner, name = _resolve(spec)
    fn = owner.__dict__[name] if isinstance(owner, type) else getattr(owner, name)
    new = functools.wraps(fn)(make(fn))
    setattr(owner, name, new)
    return fn


def plant(spec: str | None = None) -> str | None:
    """Slow one stage down: ``module:attr*factor`` (default factor 2) runs the callable ``factor`` times
    (``factor - 1`` extra calls on copies of nothing: the same arguments; the last result is returned).
    Reads ``NEWTSIM_BENCH_SLOW`` when ``spec`` is None. A benchmark's child process calls this first."""
    spec = os.environ.get("NEWTSIM_BENCH_SLOW") if spec is None else spec
    if not spec:
        return None
    target, _, factor = spec.partition("*")
    extra = max(0, round(float(factor or 2.0)) - 1)

    def make(fn):
        def slow(*a, **k):
            for _ in range(extra):
                fn(*a, **k)
            return fn(*a, **k)
        return slow

    wrap(target, make)
    return spec


class Profile:
    """Wall time summed over the calling threads (``seconds``) and CPU time of the calling thread (``cpu``,
    ``time.thread_time``: what a loaded machine does not inflate) of every wrapped callable."""

    def __init__(self):
        self.seconds = defaultdict(float)
        self.cpu = defaultdict(float)
        self.calls = defaultdict(int)
        self.lock = threading.Lock()

    def timer(self, label):
        def make(fn):
            def timed(*a, **k):
                t0, c0 = time.perf_counter(), time.thread_time()
                try:
                    return fn(*a, **k)
                finally:
                    dt, dc = time.perf_counter() - t0, time.thread_time() - c0
                    with self.lock:
                        self.seconds[label] += dt
                        self.cpu[label] += dc
                        self.calls[label] += 1
            return timed
        return make

    def install(self):
        for spec in CHAIN:
            wrap(spec, self.timer(spec.split(":")[1]))
        from detector.effects.base import registry

        for name, cls in registry().items():
            for meth in ("apply", "couple", "prepare_frame"):
                if meth in cls.__dict__:
                    wrap(f"{cls.__module__}:{cls.__name__}.{meth}", self.timer(f"effect {name}.{meth}"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--set", action="append", default=[], help="scene override key=value (repeatable)")
    ap.add_argument("--out", default="/tmp/newtsim_stages.fits")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    from scenes.app.render import render
    from scenes.scene import load_scene

    prof = Profile()
    prof.install()
    scene = load_scene(a.scene, a.set)
    t0 = time.perf_counter()
    c0 = time.process_time()
    render(scene, a.out, progress=False)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    rows = sorted(prof.cpu.items(), key=lambda kv: -kv[1])
    out = {"scene": a.scene, "sets": a.set, "wall_s": round(wall, 3), "cpu_s": round(cpu, 3),
           "peak_rss_gib": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20, 3),
           "stages_cpu_s": {k: round(v, 3) for k, v in rows},
           "stages_thread_wall_s": {k: round(prof.seconds[k], 3) for k, _ in rows}, "calls": dict(prof.calls)}
    text = json.dumps(out, indent=1)
    if a.json:
        Path(a.json).write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
