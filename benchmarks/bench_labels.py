"""Labels of a rendered frame: render with and without ``--labels`` in the same run; score throughput.

Job: an IMX411 frame (``--size`` pixels square window, 0 = the full 14208 x 10656 sensor) of the Navstar 71
field with catalogue stars to ``--mag`` and ``--objects`` streaks, rendered to FITS plain (the reference)
and with the labels in every format (COCO, SatNet, YOLO, FITS LABELS + LABELCAT), ``--repeats`` times each,
alternating, after one warm-up render (PSF tables, imports), the fastest of each kept. Reported: the wall
times, their ratio (goal <= 1.3), the process's peak RSS (goal <= 3 GiB for the full frame), the number of
labels, and the label pass alone (stamps + labels on the prepared frame) with BLAS limited to one thread
(as ``frame_labels`` does) and with the BLAS default (the code before: the reference of that fix).

Score: ``--score-frames`` copies of the frame's object labels against detections made from them (endpoints
jittered by 0.3 px, each detected with the probability of a logistic in SNR centred on the objects' median
SNR, 5 false alarms per frame), scored with the Newton/IRLS logistic fit and with the reference (the
Nelder-Mead fit it replaced, below) in the same run: frames/s of each and their SNR50.

Prints JSON. Run: python benchmarks/bench_labels.py [--size 2048] [--objects 20] [--mag 14]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))


def nelder_mead_logistic_fit(snr, hit):
    """The reference: the scorer's former fit (Nelder-Mead on (SNR50, log w), no gradient)."""
    import math

    from scipy.optimize import minimize

    snr, hit = np.asarray(snr, float), np.asarray(hit, float)
    ok = np.isfinite(snr)
    snr, hit = snr[ok], hit[ok]
    if snr.size < 3 or hit.all() or not hit.any():
        return math.nan, math.nan

    def nll(p):
        s50, lw = p
        z = (snr - s50) / math.exp(lw)
        return float(np.sum(np.logaddexp(0, -z) * hit + np.logaddexp(0, z) * (1 - hit)))

    x0 = [float(np.median(snr)), math.log(max(np.std(snr) / 4, 1e-3))]
    r = minimize(nll, x0, method="Nelder-Mead", options={"xatol": 1e-6, "fatol": 1e-9, "maxiter": 4000})
    return float(r.x[0]), float(math.exp(r.x[1]))


def rss_gib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=2048, help="square window [px]; 0: the full sensor")
    ap.add_argument("--objects", type=int, default=20)
    ap.add_argument("--mag", type=float, default=14.0)
    ap.add_argument("--score-frames", type=int, default=50)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args(argv)

    from threadpoolctl import threadpool_limits

    import scenes.app.bench.score as score_mod
    from scenes.app.bench.frame import frame_labels, noise_model, source_stamps
    from scenes.app.bench.labels import labels_from_sources
    from scenes.app.bench.score import Item, score
    from scenes.app.render import prepare, render
    from scenes.scene import load_scene

    rng = np.random.default_rng(1)
    objs = "".join(f"""
[[objects]]
ra_deg = {120.95115 + rng.uniform(-0.15, 0.15):.6f}
dec_deg = {-29.25022 + rng.uniform(-0.15, 0.15):.6f}
rate_ra_deg_s = {rng.uniform(-0.002, 0.002):.6f}
rate_dec_deg_s = {rng.uniform(-0.002, 0.002):.6f}
photons = {rng.uniform(2e4, 2e5):.0f}
outside = "skip"
""" for _ in range(args.objects))
    size = "" if args.size == 0 else f"width = {args.size}\nheight = {args.size}\n"
    text = f"""
[detector]
preset = "imx411"
{size}
[pointing]
ra_deg = 120.95115
dec_deg = -29.25022
epoch = "2023-02-01T22:00:00"
[exposure]
time_s = 10.0
frame = "light"
tracking = "sidereal"
[sky]
background_mag_arcsec2 = 19.72
stars = true
star_mag_limit = {args.mag}
[psf]
model = "gaussian"
fwhm_arcsec = 3.0
""" + objs
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        (d / "s.toml").write_text(text)
        sc = load_scene(str(d / "s.toml"))
        paths = {"coco": d / "l.coco.json", "satnet": d / "l.satnet.json", "yolo": d / "l.yolo.txt"}
        render(sc, d / "warm.fits", seed=1, progress=False, workers=args.workers)
        plain, lab = [], []
        for _ in range(args.repeats):
            t = time.perf_counter()
            render(sc, d / "plain.fits", seed=1, progress=False, workers=args.workers)
            plain.append(time.perf_counter() - t)
            t = time.perf_counter()
            summ = render(sc, d / "lab.fits", seed=1, progress=False, workers=args.workers,
                          labels=["coco", "satnet", "yolo", "fits"], label_paths=paths)
            lab.append(time.perf_counter() - t)
        rss = rss_gib()
        doc = json.loads(paths["coco"].read_text())
        setup = prepare(sc, args.workers)
        passes = {"blas_one_thread": [], "blas_default": []}
        for _ in range(args.repeats):
            t = time.perf_counter()
            frame_labels(setup)
            passes["blas_one_thread"].append(time.perf_counter() - t)
            t = time.perf_counter()
            with threadpool_limits(limits=None):  # the former code path: BLAS threads as configured
                labels_from_sources(source_stamps(setup), noise_model(setup), setup.detector.sensor.output_shape)
            passes["blas_default"].append(time.perf_counter() - t)
    anns = [a for a in doc["annotations"] if a["kind"] == "object"]
    s50_true = float(np.median([a["snr"] for a in anns]))
    labels, dets = [], []
    for f in range(args.score_frames):
        im = f"f{f}"
        for a in anns:
            labels.append(Item(im, a["x0"], a["y0"], a["x1"], a["y1"], 1.0, None, (0, 0), {k: a[k] for k in (
                "x", "y", "snr", "mag", "rate_arcsec_s", "length_px")}))
            if rng.random() < 1 / (1 + np.exp(-(a["snr"] - s50_true) / (0.2 * s50_true))):
                j = rng.normal(0, 0.3, 4)
                dets.append(Item(im, a["x0"] + j[0], a["y0"] + j[1], a["x1"] + j[2], a["y1"] + j[3], rng.random()))
        for _ in range(5):
            x, y = rng.uniform(0, 1000, 2)
            dets.append(Item(im, x, y, x + 5, y, rng.random()))
    images = {f"f{f}": (args.size or 10656, args.size or 14208) for f in range(args.score_frames)}
    t = time.perf_counter()
    res = score(labels, dets, mode="endpoints", images=images)
    t_score = time.perf_counter() - t
    newton = score_mod.logistic_fit
    score_mod.logistic_fit = nelder_mead_logistic_fit  # the reference, same data, same run
    try:
        t = time.perf_counter()
        ref = score(labels, dets, mode="endpoints", images=images)
        t_ref = time.perf_counter() - t
    finally:
        score_mod.logistic_fit = newton
    print(json.dumps({
        "job": f"IMX411 {args.size or 'full'} frame, stars to G={args.mag}, {args.objects} objects",
        "labels": summ.get("labels"), "repeats": args.repeats,
        "render_s": round(min(plain), 3), "render_with_labels_s": round(min(lab), 3),
        "ratio": round(min(lab) / min(plain), 3), "render_all_s": [round(v, 3) for v in plain],
        "render_with_labels_all_s": [round(v, 3) for v in lab], "peak_rss_gib": round(rss, 3),
        "label_pass_s": round(min(passes["blas_one_thread"]), 3),
        "label_pass_blas_default_s": round(min(passes["blas_default"]), 3),
        "score_frames": args.score_frames, "score_labels": len(labels),
        "score_s": round(t_score, 3), "score_frames_per_s": round(args.score_frames / t_score, 2),
        "score_reference_nelder_mead_s": round(t_ref, 3),
        "score_reference_frames_per_s": round(args.score_frames / t_ref, 2),
        "score_speedup": round(t_ref / t_score, 1),
        "snr50": res["snr50"], "snr50_reference": ref["snr50"], "snr50_injected": s50_true,
        "completeness": res["completeness"],
        "machine": platform.machine(), "cpus": os.cpu_count(), "load_avg_1min": round(os.getloadavg()[0], 1)}, indent=1))


if __name__ == "__main__":
    main()
