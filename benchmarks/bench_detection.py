"""The detection loop's throughput: render + labels on Dask, the baseline detector, the scorer (frames/s).

Job: ``--frames`` IMX411 windows of the worked example (examples/bench/detection_sweep.py: 256 x 256,
stars to G = 16, two objects per frame swept over SNR and angular rate), rendered with COCO labels by
``newtsim batch`` on a local Dask cluster of ``--workers`` processes; the baseline detector
(``scenes.app.bench.detect``) on every frame in ``--workers`` processes; the scorer on the whole set.

Reference, measured in the same run on the same frames: photutils alone (``Background2D`` + a Gaussian
matched filter + ``detect_sources``, the detector's first stage), so the detector's cost is reported as a
ratio to the libraries' floor on this (noisy, shared) machine.

Prints JSON. Run: python benchmarks/bench_detection.py [--frames 16] [--workers 2]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "examples" / "bench"))


def _reference(path: str) -> int:
    """photutils alone on one frame: background, matched filter, segmentation (the detector's floor)."""
    import warnings

    from astropy.io import fits
    from photutils.background import Background2D
    from photutils.segmentation import detect_sources
    from scipy import ndimage

    data = fits.getdata(path).astype(float)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        b = Background2D(data, 64, filter_size=(3, 3))
        z = (data - b.background) / b.background_rms
        zs = ndimage.gaussian_filter(z, 3.094 / 2.3548)
        seg = detect_sources(zs / np.std(zs), 3.0, 5)
    return 0 if seg is None else int(seg.max_label)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--keep", type=Path, default=None, help="render into this folder (kept) instead of a temporary one")
    a = ap.parse_args(argv)

    import detection_sweep as sweep

    tmp = tempfile.TemporaryDirectory() if a.keep is None else None
    base = Path(tmp.name) if tmp else a.keep
    batch_file = base / "sweep.toml"
    sweep.make(batch_file, a.frames)
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "scenes.app.cli", "batch", str(batch_file), "--workers", str(a.workers)],
                   check=True, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    t_render = time.perf_counter() - t0
    folder = base / "frames"
    files = sorted(str(p) for p in folder.glob("frame_*.fits"))

    with ProcessPoolExecutor(a.workers) as ex:
        list(ex.map(_reference, files[:a.workers]))  # warm the workers (imports)
        t0 = time.perf_counter()
        list(ex.map(_reference, files))
        t_ref = time.perf_counter() - t0
        list(ex.map(sweep._detect_one, files[:a.workers]))
        t0 = time.perf_counter()
        found = list(ex.map(sweep._detect_one, files))
        t_detect = time.perf_counter() - t0
    doc = json.loads((folder / "dataset.coco.json").read_text())
    ids = {im["file_name"]: im["id"] for im in doc["images"]}
    rows = [{"image_id": ids[d["file_name"]], "category_id": 1, **d} for dets in found for d in dets]
    (folder / "detections.json").write_text(json.dumps(rows))

    from scenes.app.bench.score import score_files

    t0 = time.perf_counter()
    res = score_files(folder / "detections.json", folder / "dataset.coco.json")
    t_score = time.perf_counter() - t0
    n = len(files)
    out = {
        "job": f"{n} IMX411 windows 256x256 (2 objects each), {a.workers} workers",
        "machine": {"cpus": os.cpu_count(), "load_avg": os.getloadavg(), "python": platform.python_version()},
        "render_labels_frames_per_s": n / t_render,
        "render_labels_note": "newtsim batch --workers N (a new local Dask cluster: its start-up included)",
        "detect_frames_per_s": n / t_detect,
        "reference_photutils_frames_per_s": n / t_ref,
        "detect_over_reference_time": t_detect / t_ref,
        "score_frames_per_s": n / t_score,
        "completeness": res["completeness"], "purity": res["purity"], "labels": res["labels"],
    }
    print(json.dumps(out, indent=1))
    if tmp:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
