"""Benchmark: the ``misalignment`` / ``defocus`` candidates of ``newtsim diagnose`` on a 2048 x 2048 star field.

A 2048 x 2048 window (unbinned, 9 um) in the middle of the ML11002 behind ``art`` with the diagonal tilted by
0.1 deg about x, ``[psf] model = "optics"`` (5 x 5 PSF cubes of the perturbed and the nominal design,
tests/scenes/optics_frames.py), ~400 catalogue stars of G 11-13 in 2 s; the nominal scene is the model.
Printed as JSON:

* ``misalignment_s``: :func:`scenes.app.compare.optics_candidates.optics_candidates` (what ``diagnose`` adds),
  split into ``measure_s`` (the stars' moments in both frames) and the fits (every family of
  :data:`FAMILIES` with its reference fit, and the pixel predictions of the best families, ``pixels_s``, with
  the best one's amplitude refined on the pixels); goal < 60 s on 2 cores;
* ``reference.render_s``: one plain render of the model scene (:func:`scenes.app.render.render`, noisy ADU
  frame) in the same run, and ``compare_s``, the comparison the candidates start from;
* the result: ``n_stars``, the family named first, its value and error against the truth;
* ``setup_s``: tracing the two PSF cubes (once; cached in ``--workdir``).

Usage: ``python benchmarks/bench_misalignment.py [--workdir DIR]``.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "scenes"))

TRUTH = {"diagonal_tilt_x_deg": 0.1}
SIZE = 2048


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--workdir", default=None)
    args = ap.parse_args(argv)
    from optics_frames import H_PX, W_PX, design_file, scene_table, trace_cube, write_catalogue, write_toml

    from optics import load_design
    from optics.llvm import init_mitsuba
    from scenes.app.compare import optics_candidates as oc
    from scenes.app.compare.run import run_compare
    from scenes.app.render import render
    from scenes.scene import load_scene

    tmp = tempfile.TemporaryDirectory() if args.workdir is None else None
    work = Path(tmp.name if tmp else args.workdir)
    work.mkdir(parents=True, exist_ok=True)
    mi = init_mitsuba()
    t0 = time.perf_counter()
    nom, pert = work / "nominal_5.fits", work / "perturbed_5.fits"
    dp = design_file(work, TRUTH, "perturbed")
    if not nom.exists():
        trace_cube(mi, load_design("art"), nom, 5)
    if not pert.exists():
        trace_cube(mi, load_design(str(dp)), pert, 5)
    setup_s = time.perf_counter() - t0
    cat = write_catalogue(work / "stars.csv", nx=50, ny=32)
    win = {"width": SIZE, "height": SIZE, "binning": 1}
    x0, y0 = (W_PX - SIZE) // 2, (H_PX - SIZE) // 2
    model_t = scene_table("art", str(nom), str(cat), **win)
    model_t["detector"].update(x0=x0, y0=y0)
    meas_t = scene_table(str(dp), str(pert), str(cat), **win)
    meas_t["detector"].update(x0=x0, y0=y0)
    model_p, meas_p = write_toml(work / "model.toml", model_t), write_toml(work / "measured.toml", meas_t)
    render(load_scene(str(meas_p)), work / "measured.fits", seed=5, progress=False)
    t0 = time.perf_counter()
    render(load_scene(str(model_p)), work / "reference.fits", seed=6, progress=False)
    render_s = time.perf_counter() - t0
    sc = load_scene(str(model_p))
    t0 = time.perf_counter()
    cmp = run_compare(sc, work / "measured.fits")
    compare_s = time.perf_counter() - t0
    res, truth = cmp["_residuals"], cmp["_model"].setup.truth
    t0 = time.perf_counter()
    stars = oc.measure_stars(res, truth)
    measure_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    cands, problems = oc.optics_candidates(res, truth, sc, mi=mi, model=cmp["_model"])
    total_s = time.perf_counter() - t0
    name = next(iter(TRUTH))
    best = cands[0].fit if cands else None
    out = {"job": "misalignment/defocus candidates, 2048x2048 ML11002 window, art diagonal tilted 0.1 deg",
           "misalignment_s": round(total_s, 2), "measure_s": round(measure_s, 3),
           "fits_s": round(total_s - measure_s, 2),
           "pixels_s": round(sum(c.seconds for c in cands if c.fit.delta_adu is not None), 2),
           "pixel_scored": [c.fit.note for c in cands if c.fit.delta_adu is not None], "compare_s": round(compare_s, 2),
           "reference": {"render_s": round(render_s, 2)}, "ratio_to_render": round(total_s / render_s, 2),
           "setup_s": round(setup_s, 1), "n_stars": stars["n"], "problems": problems,
           "truth": TRUTH, "first": best.note if best else None,
           "value": best.params.get(name) if best else None,
           "error": best.params["errors"].get(name) if best else None,
           "delta_bic": round(best.delta_bic, 1) if best else None,
           "ranking": [(c.fit.note, round(c.fit.delta_bic, 1)) for c in cands],
           "goal_s": 60.0}
    print(json.dumps(out, indent=1))
    if tmp:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
