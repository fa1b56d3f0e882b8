"""Benchmark: the ``pointing_drift`` candidate's fit (a straight drift, then the second-order path) on a
512x512 star field, beside today's straight-only fit and the ``jitter`` fit measured in the same run.

The "measured" frame is a 10 s ML11002 star field (``tests/helpers.star_field_toml``) with a hidden
accelerating, bowed drift (``[effects.pointing_drift]`` dx 5, dy 2, accel 0.8, sagitta 0.6 px). Printed as
JSON: ``drift_s`` (the candidate as registered), ``reference.straight_s`` (the straight drift alone: the
candidate before the path parameters), ``reference.jitter_s`` (the Gaussian smear it competes with), with
each fit's delta BIC and parameters.

Usage: ``python benchmarks/bench_drift_path.py [--size 512]``.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=int, default=512)
    args = ap.parse_args(argv)
    from helpers import star_field_toml

    from detector.effects import image_plane as ip
    from detector.effects.base import registry
    from scenes.app.compare import run_compare
    from scenes.app.render import render
    from scenes.scene import load_scene

    base = star_field_toml(args.size)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        (tmp / "model.toml").write_text(base)
        (tmp / "truth.toml").write_text(base + "[effects.pointing_drift]\ndx_px = 5.0\ndy_px = 2.0\n"
                                        "accel = 0.8\nsagitta_px = 0.6\n")
        render(load_scene(str(tmp / "truth.toml")), tmp / "m.fits", seed=3)
        res = run_compare(load_scene(str(tmp / "model.toml")), tmp / "m.fits")["_residuals"]
        straight = ip.TransformSignature(lambda r: ip._drift_start(r)[:2], ip._drift_transform, ip._drift_params, [0.02, 0.02],
                                         explain=ip._drift_words)
        out = {"size": args.size}
        for key, sig in (("straight", straight), ("drift", registry()["pointing_drift"].signature),
                         ("jitter", registry()["jitter"].signature)):
            t0 = time.perf_counter()
            fit = sig.fit(res, key)
            dt = time.perf_counter() - t0
            out[key] = {"s": round(dt, 3), "delta_bic": None if fit is None else round(fit.delta_bic, 1),
                        "params": None if fit is None else fit.params}
    print(json.dumps({"drift_s": out["drift"]["s"], "reference": {"straight_s": out["straight"]["s"],
                      "jitter_s": out["jitter"]["s"]}, "fits": out}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
