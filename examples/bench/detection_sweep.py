"""The detection bench's worked example (docs/detection_bench.md, "Worked example"): a labelled dataset of
IMX411 windows swept over SNR and angular rate, rendered on Dask; the baseline detector on every frame; the
score, with the SNR of 50 % completeness per rate bin and its bootstrap error.

    python examples/bench/detection_sweep.py make  out/detsweep/sweep.toml --frames 1000
    newtsim batch out/detsweep/sweep.toml --workers 2                      # frames + dataset.coco.json
    python examples/bench/detection_sweep.py detect out/detsweep/frames --workers 2   # -> detections.json
    newtsim score out/detsweep/frames/detections.json out/detsweep/frames/dataset.coco.json --html r.html
    python examples/bench/detection_sweep.py report out/detsweep/frames --json out/detsweep/report.json

The sweep: every frame is a 256 x 256 window of the IMX411 behind the ART telescope (0.808"/px), 1 s,
sidereal tracking, stars to G = 16 (the thesis's Navstar 71 field: galactic plane), with OBJECTS_PER_FRAME
objects; each object's angular rate is log-uniform in RATE_RANGE (a trail of 12 to 250 px), its direction
uniform, its start uniform in the inner 200 x 200 px (it may leave the frame: clipped, labelled so), and its
photons set for a matched-filter SNR uniform in SNR_RANGE (from the sky-limited scaling SNR ~ photons /
sqrt(length) measured on one frame; the labels hold the exact SNR).
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT_SEED = 20261129
OBJECTS_PER_FRAME = 2
RATE_RANGE = (15.0, 250.0)  # [arcsec/s]
RATE_BINS = (15.0, 30.0, 60.0, 120.0, 250.0)  # [arcsec/s]: bins of the report
SNR_RANGE = (2.0, 30.0)
PIXEL_SCALE = 0.8078704911344607  # IMX411 behind ART [arcsec/px] (the frame's PIXSCALE)
#: photons for SNR 1 of a 1 px trail, sky-limited: a 20000-photon object at 36"/s (44.6 px) has SNR 63.2
PHOTONS_PER_SNR = 20000.0 / 63.16 / math.sqrt(44.56)
RA0, DEC0 = 120.95115, -29.25022
SIZE = 256


def objects_of_frame(rng: np.random.Generator) -> list[dict]:
    objs = []
    for k in range(OBJECTS_PER_FRAME):
        rate = math.exp(rng.uniform(math.log(RATE_RANGE[0]), math.log(RATE_RANGE[1])))  # [arcsec/s]
        snr = rng.uniform(*SNR_RANGE)
        theta = rng.uniform(0.0, 2.0 * math.pi)
        dx, dy = rng.uniform(-100.0, 100.0, 2)  # start offset from the window centre [px]
        length = rate / PIXEL_SCALE
        photons = PHOTONS_PER_SNR * snr * math.sqrt(length)
        cosd = math.cos(math.radians(DEC0))
        objs.append({
            "name": f"o{k}",
            "ra_deg": RA0 - dx * PIXEL_SCALE / 3600.0 / cosd,  # x grows westwards (east left) on the sky
            "dec_deg": DEC0 + dy * PIXEL_SCALE / 3600.0,
            "rate_ra_deg_s": rate * math.cos(theta) / 3600.0,
            "rate_dec_deg_s": rate * math.sin(theta) / 3600.0,
            "photons": round(photons, 1),
        })
    return objs


def make(out: Path, frames: int, seed: int = ROOT_SEED) -> None:
    """Write the batch file (one [[sweep]] over the objects array: one value per frame) and its scene."""
    import tomli_w

    out.parent.mkdir(parents=True, exist_ok=True)
    scene = {
        "telescope": {"design": "art"},
        "detector": {"preset": "imx411", "width": SIZE, "height": SIZE},
        "pointing": {"ra_deg": RA0, "dec_deg": DEC0, "roll_deg": 0.0, "epoch": "2023-02-01T22:00:00"},
        "exposure": {"time_s": 1.0, "frame": "light", "tracking": "sidereal", "seed": 1},
        "sky": {"background_mag_arcsec2": 19.72, "stars": True, "star_mag_limit": 16.0, "star_seed": 0,
                "catalog": "builtin"},
        "psf": {"model": "gaussian", "fwhm_arcsec": 2.5},
    }
    (out.parent / "scene.toml").write_text(tomli_w.dumps(scene))
    rng = np.random.default_rng(seed)
    batch = {
        "batch": {"scene": "scene.toml", "output_dir": str(out.parent / "frames"), "seed": seed,
                  "labels": ["coco"], "split": [0.8, 0.1, 0.1]},
        "sweep": [{"key": "objects", "values": [objects_of_frame(rng) for _ in range(frames)]}],
    }
    out.write_text(tomli_w.dumps(batch))
    print(f"wrote {out} ({frames} frames, {OBJECTS_PER_FRAME} objects each) and {out.parent / 'scene.toml'}")


def _detect_one(path: str) -> list[dict]:
    from scenes.app.bench.detect import detect_file

    dets, _ = detect_file(path, psf="3.094px")  # the scene's 2.5" FWHM (the frames' stars would give it too)
    return [{"file_name": d.file, "x0": d.x0, "y0": d.y0, "x1": d.x1, "y1": d.y1, "score": d.score, "kind": d.kind}
            for d in dets]


def detect(folder: Path, workers: int = 1) -> Path:
    """The baseline detector on every frame of the dataset -> detections.json (COCO results with endpoints)."""
    doc = json.loads((folder / "dataset.coco.json").read_text())
    ids = {im["file_name"]: im["id"] for im in doc["images"]}
    files = [str(folder / f) for f in ids]
    t0 = time.perf_counter()
    partial = folder / "detections.partial.jsonl"  # one line per frame as it is done (a long run's progress)
    found = []
    with open(partial, "w") as log:
        if workers > 1:
            from concurrent.futures import ProcessPoolExecutor

            with ProcessPoolExecutor(workers) as ex:
                for dets in ex.map(_detect_one, files, chunksize=4):
                    found.append(dets)
                    log.write(json.dumps(dets) + "\n")
                    log.flush()
        else:
            for f in files:
                found.append(_detect_one(f))
                log.write(json.dumps(found[-1]) + "\n")
                log.flush()
    dt = time.perf_counter() - t0
    rows = []
    for dets in found:
        for d in dets:
            x0, x1 = sorted((d["x0"], d["x1"]))
            y0, y1 = sorted((d["y0"], d["y1"]))
            rows.append({"image_id": ids[d["file_name"]], "category_id": 1, "bbox": [x0, y0, x1 - x0 + 1, y1 - y0 + 1],
                         **d})
    out = folder / "detections.json"
    out.write_text(json.dumps(rows) + "\n")
    print(f"wrote {out}: {len(rows)} detections in {len(files)} frames, {len(files) / dt:.2f} frames/s "
          f"({workers} worker(s))")
    return out


def report(folder: Path, gate_px: float = 3.0, n_boot: int = 200, seed: int = 0) -> dict:
    """SNR50 (logistic fit, bootstrap error) per rate bin, and the overall score."""
    from scenes.app.bench.score import load_detections, load_labels, logistic_fit, match, score

    labels, images = load_labels(folder / "dataset.coco.json")
    dets = load_detections(folder / "detections.json", images)
    overall = score(labels, dets, gate_px=gate_px, images=images)
    hit = np.zeros(len(labels), bool)
    by_img_l, by_img_d = {}, {}
    for i, it in enumerate(labels):
        by_img_l.setdefault(it.image, []).append(i)
    for j, it in enumerate(dets):
        by_img_d.setdefault(it.image, []).append(j)
    for im, li in by_img_l.items():
        dj = by_img_d.get(im, [])
        for a, _b, _ in match([labels[i] for i in li], [dets[j] for j in dj], "endpoints", gate_px):
            hit[li[a]] = True
    snr = np.array([it.props.get("snr") or np.nan for it in labels], float)
    rate = np.array([it.props.get("rate_arcsec_s") or np.nan for it in labels], float)
    rng = np.random.default_rng(seed)
    rows = []
    for lo, hi in itertools.pairwise(RATE_BINS):
        sel = np.flatnonzero((rate >= lo) & (rate < hi) & np.isfinite(snr))
        s50, width = logistic_fit(snr[sel], hit[sel])
        boot = []
        for _ in range(n_boot):
            k = rng.choice(sel, sel.size)
            b, _w = logistic_fit(snr[k], hit[k])
            if np.isfinite(b):
                boot.append(b)
        rows.append({"rate_lo": lo, "rate_hi": hi, "labels": int(sel.size), "matched": int(hit[sel].sum()),
                     "snr50": float(s50) if np.isfinite(s50) else None,
                     "width": float(width) if np.isfinite(width) else None,
                     "snr50_bootstrap_error": float(np.std(boot, ddof=1)) if len(boot) > 2 else None})
    out = {"gate_px": gate_px, "per_rate": rows,
           "overall": {k: overall[k] for k in ("labels", "detections", "matched", "completeness", "purity",
                                               "false_alarms_per_frame", "endpoint_rmse_px", "centre_rmse_px",
                                               "average_precision", "snr50")}}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    m = sub.add_parser("make")
    m.add_argument("out", type=Path)
    m.add_argument("--frames", type=int, default=1000)
    m.add_argument("--seed", type=int, default=ROOT_SEED)
    d = sub.add_parser("detect")
    d.add_argument("folder", type=Path)
    d.add_argument("--workers", type=int, default=1)
    r = sub.add_parser("report")
    r.add_argument("folder", type=Path)
    r.add_argument("--gate", type=float, default=3.0)
    r.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    if a.cmd == "make":
        make(a.out, a.frames, a.seed)
    elif a.cmd == "detect":
        detect(a.folder, a.workers)
    else:
        res = report(a.folder, a.gate)
        text = json.dumps(res, indent=1)
        if a.json:
            a.json.write_text(text + "\n")
        print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
