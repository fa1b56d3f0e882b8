"""Render the 15 validation scenarios and the two real-vs-synthetic cases, and print the thesis's Annex VII
table: per frame the std, median and mean [ADU], the stars visible (matched-filter detection above
5 sigma, matched to TRUTH), their median SNR, and the target's (the object's) SNR in an aperture along its
path. Measurements: ``scenes.app.metrics`` (numpy/scipy; definitions in docs/scenarios.md).

    python examples/scenarios/run_table.py                       # all 17 frames -> out/scenarios/
    python examples/scenarios/run_table.py --only s07 s13        # some of them
    python examples/scenarios/run_table.py --no-cases            # the 15 scenarios only (skip the full frames)
    python examples/scenarios/run_table.py --set detector.width=512 --set detector.height=512   # quick look

Writes ``table.md`` and ``table.json`` in ``--out`` (and the FITS frames in ``--out``/fits unless
``--discard-fits``). The thesis's own Annex VII numbers are not in this repository: that column says so.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import warnings
from pathlib import Path

import numpy as np
from astropy.io import fits

from scenes.app.render import render
from scenes.scene import load_scene

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from scenes.app.metrics import measure_frame

CASES = ("navstar71_imx411", "navstar67_ml11002")
THESIS = "n/a: thesis table not in repo"
CATEGORY = {"bias": "bias", "dark": "darks", "empty_sky": "empty sky", "stars": "stars", "object": "objects",
            "sidereal_cosmics": "sidereal + cosmics (+ straylight)", "tracking": "tracking", "full": "full",
            "navstar71": "real vs synthetic (Tables 25, 27)", "navstar67": "real vs synthetic (Tables 30, 32)"}


def scenario_files(only=(), cases: bool = True) -> list[Path]:
    files = sorted(HERE.glob("s[0-9][0-9]_*.toml")) + ([HERE / f"{c}.toml" for c in CASES] if cases else [])
    return [f for f in files if not only or any(o in f.stem for o in only)]


def category(name: str) -> str:
    key = name.split("_", 1)[1].rsplit("_", 1)[0] if name[:1] == "s" and name[1:3].isdigit() else name.split("_")[0]
    return CATEGORY.get(key, key)


def table_row(path: Path, out_dir: Path | None, overrides=(), nsigma: float = 5.0, keep: bool = True) -> dict:
    """Render one scene file and measure its frame: the table's row (a dict)."""
    import tempfile

    scene = load_scene(str(path), list(overrides))
    with tempfile.TemporaryDirectory() as tmp:
        fits_path = (out_dir / f"{path.stem}.fits") if keep and out_dir is not None else Path(tmp) / "frame.fits"
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", fits.verify.VerifyWarning)
            info = render(scene, fits_path, progress=False)
        render_s = time.perf_counter() - t0
        with fits.open(fits_path) as hdul:
            header = hdul[0].header
            img = np.asarray(hdul[0].data)
            truth = np.asarray(hdul["TRUTH"].data) if "TRUTH" in hdul else None
            t0 = time.perf_counter()
            m = measure_frame(img, header, truth, nsigma=nsigma)
            measure_s = time.perf_counter() - t0
    exp = scene.exposure
    s = scene.sensor()
    row = {"scenario": path.stem, "category": category(path.stem), "sensor": s.name,
           "frame": f"{info['shape'][1]}x{info['shape'][0]}" + (f" b{s.binning}" if s.binning > 1 else ""),
           "roi": s.roi_shape != (s.sensor_width_px, s.sensor_height_px), "frame_type": exp.frame,
           "exptime_s": info["exptime_s"], "tracking": exp.tracking if exp.frame == "light" else "-",
           "seed": info["seed"], **m, "thesis": THESIS, "render_s": round(render_s, 2),
           "measure_s": round(measure_s, 2), "fits": str(fits_path) if keep and out_dir is not None else None}
    return row


def _fmt(v, nd=1) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return f"{v:.{nd}f}" if isinstance(v, float) else str(v)


def markdown(rows: list[dict], nsigma: float) -> str:
    head = ["scenario", "category", "frame", "t [s]", "tracking", "std", "clipped std", "median", "mean",
            f"stars visible (>{nsigma:g} sigma) / in TRUTH", "median star SNR", "target SNR", "thesis (Annex VII)"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        stars = f"{r['stars_visible']} / {r['stars_truth']}" if r["stars_truth"] else "-"
        lines.append("| " + " | ".join([r["scenario"], r["category"], r["frame"] + (" (ROI)" if r["roi"] else ""),
                                        _fmt(r["exptime_s"], 1), r["tracking"], _fmt(r["std"], 2),
                                        _fmt(r["std_clipped"], 2), _fmt(r["median"], 1),
                                        _fmt(r["mean"], 2), stars, _fmt(r["star_snr_median"], 1),
                                        _fmt(r["target_snr"], 1), r["thesis"]]) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="+", default=(), help="scenario names (or parts of them) to run")
    ap.add_argument("--no-cases", action="store_true", help="skip the two full-frame real-vs-synthetic cases")
    ap.add_argument("--out", default="out/scenarios", help="folder for table.md, table.json and fits/")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a key in every scene")
    ap.add_argument("--nsigma", type=float, default=5.0, help="detection threshold [sigma] (default 5)")
    ap.add_argument("--discard-fits", action="store_true", help="do not keep the rendered frames")
    a = ap.parse_args(argv)
    files = scenario_files(a.only, not a.no_cases)
    if not files:
        ap.error(f"no scenario matches {a.only}")
    out = Path(a.out)
    fits_dir = out / "fits"
    fits_dir.mkdir(parents=True, exist_ok=True)
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    rows = []
    with Progress(TextColumn("[bold]scenarios[/bold] {task.description}"), BarColumn(),
                  TextColumn("{task.completed}/{task.total}"), TimeElapsedColumn(), transient=True) as prog:
        task = prog.add_task("", total=len(files))
        for f in files:
            prog.update(task, description=f.stem)
            rows.append(table_row(f, fits_dir, a.set, a.nsigma, keep=not a.discard_fits))
            prog.advance(task)
    md = markdown(rows, a.nsigma)
    meta = {"nsigma": a.nsigma, "overrides": a.set, "aperture": "radius 1.0 FWHM around the path, annulus 2.5-4.0 FWHM",
            "detection": f"PSF-matched Gaussian filter > {a.nsigma:g} sigma, regions matched to TRUTH",
            "thesis": THESIS}
    (out / "table.md").write_text(md)
    (out / "table.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=2, default=float))
    print(md)
    print(f"wrote {out / 'table.md'} and {out / 'table.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
