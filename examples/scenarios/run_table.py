"""Render the 15 validation scenarios and the two real-vs-synthetic cases, and print the thesis's Annex VII
table: per frame the std, median and mean [ADU], the stars visible (matched-filter detection above
5 sigma, matched to TRUTH), their median SNR, and the target's (the object's) SNR in an aperture along its
path. Measurements: ``scenes.app.metrics`` (numpy/scipy; definitions in docs/scenarios.md).

    python examples/scenarios/run_table.py                       # all 17 frames -> out/scenarios/
    python examples/scenarios/run_table.py --only s07 s13        # some of them
    python examples/scenarios/run_table.py --no-cases            # the 15 scenarios only (skip the full frames)
    python examples/scenarios/run_table.py --set detector.width=512 --set detector.height=512   # quick look

Writes ``table.md`` and ``table.json`` in ``--out`` (and the FITS frames in ``--out``/fits unless
``--discard-fits``).

The thesis's own tables side by side (``thesis_tables.toml``: its Tables 10-15, 17-22, 26 and 31, each row
with the scenario file and the overrides that state the thesis's settings)::

    python examples/scenarios/run_table.py --thesis                          # every row -> thesis.md/.json
    python examples/scenarios/run_table.py --thesis --tables 10 11 13        # some tables
    python examples/scenarios/run_table.py --thesis --set detector.width=512 --set detector.height=512

prints, per row and quantity, the thesis's value, newtsim's and their relative difference (counts of
stars and outliers scaled to the full sensor by area when a window is rendered).
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
THESIS = "see --thesis (thesis_tables.toml)"
THESIS_FILE = HERE / "thesis_tables.toml"
#: the quantities a thesis row may give, and the key of newtsim's measurement for each
QUANTITIES = {"std": "std", "median": "median", "mean": "mean", "std_background": "std_clipped",
              "stars_visible": "stars_visible", "star_snr_median": "star_snr_median", "target_snr": "target_snr",
              "outliers_5sigma": "outliers_5sigma"}
#: counts that scale with the frame's area (a window's count is scaled to the full sensor)
COUNTS = ("stars_visible", "outliers_5sigma")
THESIS_TABLES = (10, 11, 12, 13, 14, 15, 17, 18, 19, 20, 21, 22, 26, 31)
CATEGORY = {"bias": "bias", "dark": "darks", "empty_sky": "empty sky", "stars": "stars", "object": "objects",
            "sidereal_cosmics": "sidereal + cosmics (+ straylight)", "tracking": "tracking", "full": "full",
            "navstar71": "real vs synthetic (Tables 25, 27)", "navstar67": "real vs synthetic (Tables 30, 32)"}


def scenario_files(only=(), cases: bool = True) -> list[Path]:
    files = sorted(HERE.glob("s[0-9][0-9]_*.toml")) + ([HERE / f"{c}.toml" for c in CASES] if cases else [])
    return [f for f in files if not only or any(o in f.stem for o in only)]


def category(name: str) -> str:
    key = name.split("_", 1)[1].rsplit("_", 1)[0] if name[:1] == "s" and name[1:3].isdigit() else name.split("_")[0]
    return CATEGORY.get(key, key)


def load_thesis(path: Path = THESIS_FILE) -> list[dict]:
    """The thesis's values (``thesis_tables.toml``), checked: every row names its tables (among
    :data:`THESIS_TABLES`), an existing scenario file and known quantities with numbers (or a string such as
    ``"<1"`` where the thesis gives none)."""
    import tomllib

    data = tomllib.loads(Path(path).read_text())
    rows = data["row"]
    defaults = data.get("defaults", {}).get("scenario_set", [])
    for i, r in enumerate(rows):
        if r.get("defaults"):
            r["set"] = list(defaults) + list(r.get("set", []))
        where = f"{path}: row {i + 1} ({r.get('label')!r})"
        if not r.get("tables") or not set(r["tables"]) <= set(THESIS_TABLES):
            raise ValueError(f"{where}: tables {r.get('tables')} not among {THESIS_TABLES}")
        if not (HERE / f"{r['scenario']}.toml").is_file():
            raise ValueError(f"{where}: no scenario file {r['scenario']}.toml")
        for part in ("values", "real"):
            for k, v in r.get(part, {}).items():
                if k not in QUANTITIES or not isinstance(v, (int, float, str)):
                    raise ValueError(f"{where}: {part}.{k} = {v!r} (expected one of {sorted(QUANTITIES)}: a number)")
        if not r.get("values"):
            raise ValueError(f"{where}: no values")
    return rows


def _scene_with_object(path: Path, obj: dict | None):
    """The scene file, or (``obj``) a temporary copy beside it with ``obj`` merged into its first object."""
    import contextlib
    import tempfile

    import tomli_w
    import tomllib

    if not obj:
        return contextlib.nullcontext(path)

    @contextlib.contextmanager
    def tmp():
        data = tomllib.loads(path.read_text())
        data["objects"][0].update(obj)
        fd, name = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".toml", dir=path.parent)
        try:
            with open(fd, "w") as f:
                f.write(tomli_w.dumps(data))
            yield Path(name)
        finally:
            Path(name).unlink(missing_ok=True)

    return tmp()


def compare_row(t: dict, out_dir: Path | None, overrides=(), nsigma: float = 5.0, keep: bool = False) -> dict:
    """Render one thesis row's frame (its scenario, its overrides, then ``overrides``) and compare."""
    path = HERE / f"{t['scenario']}.toml"
    with _scene_with_object(path, t.get("object")) as p:
        row = table_row(p, out_dir, list(t.get("set", [])) + list(overrides), nsigma, keep, outliers=True)
    row["scenario"] = t["scenario"]
    area = row.pop("_area_ratio")
    out = {"tables": t["tables"], "label": t["label"], "scenario": t["scenario"], "frame": row["frame"],
           "window_area_ratio": area, "set": t.get("set", []) + list(overrides), "object": t.get("object"),
           "quantities": []}
    for q, tv in t["values"].items():
        nv = row.get(QUANTITIES[q])
        if q in COUNTS and nv is not None and area != 1:
            nv = nv * area  # a window's count, scaled to the thesis's full frame
        rel = (nv / tv - 1) if isinstance(tv, (int, float)) and tv and nv is not None and math.isfinite(nv) \
            else None
        if isinstance(tv, str) and tv.startswith("<") and nv is not None:
            rel = None
        real = t.get("real", {}).get(q)
        out["quantities"].append({"quantity": q, "thesis": tv, "newtsim": nv, "rel_diff": rel, "real": real,
                                  "over_10_percent": bool(rel is not None and abs(rel) > 0.10)})
    return out


def thesis_markdown(comps: list[dict]) -> str:
    head = ["tables", "thesis row", "newtsim frame", "quantity", "thesis", "newtsim", "newtsim/thesis - 1",
            "real frame"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for c in comps:
        for q in c["quantities"]:
            nv = q["newtsim"]
            nd = 0 if q["quantity"] in COUNTS else 2
            lines.append("| " + " | ".join([", ".join(str(x) for x in c["tables"]), c["label"], c["frame"],
                                            q["quantity"], str(q["thesis"]), _fmt(None if nv is None else
                                                                                   float(nv), nd),
                                            "-" if q["rel_diff"] is None else f"{100 * q['rel_diff']:+.0f} %",
                                            "-" if q["real"] is None else str(q["real"])]) + " |")
    return "\n".join(lines) + "\n"


def table_row(path: Path, out_dir: Path | None, overrides=(), nsigma: float = 5.0, keep: bool = True,
              outliers: bool = False) -> dict:
    """Render one scene file and measure its frame: the table's row (a dict). ``outliers``: also the count
    of pixels more than 5 clipped sigma above the median (thesis section 3.7.1's outliers) and the ratio of
    the full sensor's area to the rendered window's (``_area_ratio``)."""
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
            if outliers:
                m["outliers_5sigma"] = int(np.count_nonzero(img.astype(np.float64) - m["median"]
                                                             > 5 * m["std_clipped"]))
            measure_s = time.perf_counter() - t0
    exp = scene.exposure
    s = scene.sensor()
    row = {"scenario": path.stem, "category": category(path.stem), "sensor": s.name,
           "frame": f"{info['shape'][1]}x{info['shape'][0]}" + (f" b{s.binning}" if s.binning > 1 else ""),
           "roi": s.roi_shape != (s.sensor_width_px, s.sensor_height_px), "frame_type": exp.frame,
           "exptime_s": info["exptime_s"], "tracking": exp.tracking if exp.frame == "light" else "-",
           "seed": info["seed"], **m, "thesis": THESIS, "render_s": round(render_s, 2),
           "measure_s": round(measure_s, 2), "fits": str(fits_path) if keep and out_dir is not None else None}
    if outliers:
        w, h = s.roi_shape
        row["_area_ratio"] = (s.sensor_width_px * s.sensor_height_px) / (w * h)
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
    ap.add_argument("--thesis", action="store_true",
                    help="the thesis's Tables 10-15, 17-22, 26, 31 side by side (thesis_tables.toml)")
    ap.add_argument("--tables", nargs="+", type=int, default=(), help="with --thesis: only these table numbers")
    a = ap.parse_args(argv)
    if a.thesis:
        return thesis_main(a)
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


def thesis_main(a) -> int:
    rows = [t for t in load_thesis() if (not a.tables or set(t["tables"]) & set(a.tables))
            and (not a.only or any(o in t["scenario"] for o in a.only))]
    if not rows:
        raise SystemExit(f"no thesis row matches tables {list(a.tables)} / {list(a.only)}")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    comps = []
    t0 = time.perf_counter()
    with Progress(TextColumn("[bold]thesis rows[/bold] {task.description}"), BarColumn(),
                  TextColumn("{task.completed}/{task.total}"), TimeElapsedColumn(), transient=True) as prog:
        task = prog.add_task("", total=len(rows))
        for t in rows:
            prog.update(task, description=t["label"][:40])
            try:
                comps.append(compare_row(t, out / "fits", a.set, a.nsigma, keep=False))
            except Exception as exc:  # noqa: BLE001 -- one row's failure (a scene error) does not lose the others
                print(f"{t['label']}: {type(exc).__name__}: {exc}", file=sys.stderr)
                comps.append({"tables": t["tables"], "label": t["label"], "scenario": t["scenario"], "frame": "-",
                              "error": f"{type(exc).__name__}: {exc}", "quantities": []})
            prog.advance(task)
    md = thesis_markdown(comps)
    (out / "thesis.md").write_text(md)
    (out / "thesis.json").write_text(json.dumps({"overrides": a.set, "nsigma": a.nsigma, "rows": comps,
                                                 "wall_s": round(time.perf_counter() - t0, 1)},
                                                indent=2, default=float))
    print(md)
    print(f"wrote {out / 'thesis.md'} and {out / 'thesis.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
