"""Labels of a rendered frame: render with and without ``--labels`` in the same run; score throughput.

Job: an IMX411 frame (``--size`` pixels square window, 0 = the full 14208 x 10656 sensor) of the Navstar 71
field with catalogue stars to ``--mag`` and ``--objects`` streaks, rendered to FITS twice, once plain (the
reference) and once with the labels in every format (COCO, SatNet, YOLO, FITS LABELS). Reported: both
wall times, their ratio (goal <= 1.3), the process's peak RSS after each (goal <= 3 GiB for the full
frame), the number of labels. Score: ``--score-frames`` copies of the frame's COCO labels scored against
detections made from them (endpoints jittered by 0.3 px, 20 % dropped, 5 false alarms per frame): frames/s.

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


def rss_gib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=2048, help="square window [px]; 0: the full sensor")
    ap.add_argument("--objects", type=int, default=20)
    ap.add_argument("--mag", type=float, default=14.0)
    ap.add_argument("--score-frames", type=int, default=200)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args(argv)

    from scenes.app.bench.score import Item, score
    from scenes.app.render import render
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
        t = time.perf_counter()
        render(sc, d / "plain.fits", seed=1, progress=False, workers=args.workers)
        t_plain = time.perf_counter() - t
        rss_plain = rss_gib()
        paths = {"coco": d / "l.coco.json", "satnet": d / "l.satnet.json", "yolo": d / "l.yolo.txt"}
        t = time.perf_counter()
        summ = render(sc, d / "lab.fits", seed=1, progress=False, workers=args.workers,
                      labels=["coco", "satnet", "yolo", "fits"], label_paths=paths)
        t_lab = time.perf_counter() - t
        rss_lab = rss_gib()
        doc = json.loads(paths["coco"].read_text())
    anns = doc["annotations"]
    labels, dets = [], []
    for f in range(args.score_frames):
        im = f"f{f}"
        for a in anns:
            if a["kind"] != "object":
                continue
            labels.append(Item(im, a["x0"], a["y0"], a["x1"], a["y1"], 1.0, None, (0, 0), {k: a[k] for k in (
                "x", "y", "snr", "mag", "rate_arcsec_s", "length_px")}))
            if rng.random() > 0.2:
                j = rng.normal(0, 0.3, 4)
                dets.append(Item(im, a["x0"] + j[0], a["y0"] + j[1], a["x1"] + j[2], a["y1"] + j[3], rng.random()))
        for _ in range(5):
            x, y = rng.uniform(0, 1000, 2)
            dets.append(Item(im, x, y, x + 5, y, rng.random()))
    t = time.perf_counter()
    res = score(labels, dets, mode="endpoints", images={f"f{f}": (args.size or 10656, args.size or 14208)
                                                        for f in range(args.score_frames)})
    t_score = time.perf_counter() - t
    print(json.dumps({
        "job": f"IMX411 {args.size or 'full'} frame, stars to G={args.mag}, {args.objects} objects",
        "labels": summ.get("labels"), "render_s": round(t_plain, 3), "render_with_labels_s": round(t_lab, 3),
        "ratio": round(t_lab / t_plain, 3), "peak_rss_gib_after_plain": round(rss_plain, 3),
        "peak_rss_gib_after_labels": round(rss_lab, 3),
        "score_frames": args.score_frames, "score_s": round(t_score, 3),
        "score_frames_per_s": round(args.score_frames / t_score, 1), "completeness": res["completeness"],
        "machine": platform.machine(), "cpus": os.cpu_count()}, indent=1))


if __name__ == "__main__":
    main()
