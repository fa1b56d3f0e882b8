"""Null frames from an independent camera chain: the false-alarm rate of the whole diagnosis.

A *null* frame holds nothing the model scene lacks. It is made without newtsim's detector chain:
``newtsim render SCENE --noiseless`` writes the expected electrons of every output pixel, and the
independent textbook chain (``../shared/tools/textbook_chain.py``, no code shared with newtsim: Poisson
charge, full-well clip, Gaussian read noise, gain, bias, rounding, ADC range) turns them into a measured
frame. The diagnosis (:func:`scenes.app.compare.run_diagnose`, what ``newtsim diagnose --json`` runs) is then
asked about that frame against the SAME scene; anything it names is a false alarm (or a difference between
the textbook camera and newtsim's model of it, worth understanding).

Per frame the record keeps every significant name, the verdict, ``residual_morphology.significant`` and the
raw statistics the judge thresholds on (per candidate: ``delta_bic``, ``heldout_delta``, the shares, the
gates' verdicts; for the morphology its ``significance_sigma``), so that a significance level can be set
from their null distribution.

The matrix (:func:`null_cases`): both cameras (``ml11002``, ``imx411``); bias, dark (10 s and 300 s),
flat, and star frames under a dark and a bright sky; windows of 256-512 pixels at random places and the
binned full sensors (ML11002 binned 4 and 8, IMX411 binned 8 and 16 in average mode); and series of 3-5 null
frames (:func:`null_series`: a clean flat series of a linear camera at several levels, a dark series at
several exposure times, a sky series at several pointings) diagnosed with ``--series``. Every frame has its
own seed drawn from the run's seed: a report draws a fresh run seed.

One convention differs between the two programs and is converted here, nothing else: newtsim's noiseless
frame of a camera binning by *average* holds the mean charge of the binned pixels, the textbook chain reads
the binned pixel's total charge (it averages after its draws); the harness hands it ``b^2`` times the
noiseless frame (:func:`textbook_frame`).

``run_nulls(n, seed, workdir, workers=2, judge=None)`` returns one dict per frame or series;
``examples/diagnose/null_calibration.py`` runs it and writes the JSONL and the summary (docs/null_calibration.md).
"""

from __future__ import annotations

import copy
import json
import math
import os
import runpy
import time
import traceback
from collections import Counter, defaultdict
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import tomli_w

#: the independent textbook camera chain (shared with no newtsim code)
def _find_chain() -> Path:
    """``NEWTSIM_TEXTBOOK_CHAIN`` or the first ``shared/tools/textbook_chain.py`` beside a parent folder of
    the package (``../shared`` of the checkout)."""
    if os.environ.get("NEWTSIM_TEXTBOOK_CHAIN"):
        return Path(os.environ["NEWTSIM_TEXTBOOK_CHAIN"])
    for parent in Path(__file__).resolve().parents:
        cand = parent / "shared" / "tools" / "textbook_chain.py"
        if cand.exists():
            return cand
    return Path("../shared/tools/textbook_chain.py")


TEXTBOOK_CHAIN = _find_chain()

#: star fields of the builtin catalogue (the hidden-effect suite's pointing, moved by up to POINTING_JITTER_DEG)
POINTING = {"ra_deg": 120.95115, "dec_deg": -29.25022, "epoch": "2023-02-01T22:00:00"}
POINTING_JITTER_DEG = 0.5
#: sky brightness [mag / arcsec^2]: a dark site, and a bright (moonlit, urban) sky
SKY_MAG = {"dark": 21.0, "bright": 17.5}
#: the bright sky's rate [e-/s per unbinned pixel] (render's SKYRATE at SKY_MAG["bright"]), and the share of
#: an output pixel's range it may fill
SKY_RATE_BRIGHT = {"ml11002": 500.0, "imx411": 155.0}
BRIGHT_SKY_FILL = 0.3
#: window sides [sensor pixels] (the smallest that keep every statistic representative)
WINDOWS = (256, 256, 256, 384, 512)
#: binned full sensors: (camera, binning, mode), the coarser first (visited twice as often: the finer
#: IMX411 frame, 2.4 Mpixel, takes 5x the time of the rest)
FULL = {"ml11002": ((8, "sum"), (4, "sum")), "imx411": ((16, "average"), (8, "average"))}
#: frame types of the matrix
FRAMES = ("bias", "dark_short", "dark_long", "flat", "stars_dark", "stars_bright")
#: series of null frames, one in every SERIES_EVERY single frames (at least one of each kind in a full run)
SERIES_EVERY = 20
SERIES_KINDS = ("flat", "dark", "sky")

_SENSOR = {"ml11002": (4008, 2672, 50000.0, 1.4), "imx411": (14192, 10640, 80000.0, 1.22)}


def _charge_cap_e(camera: str, binning: int, mode: str) -> float:
    """The largest mean charge per unbinned pixel [e-] that stays in the ADC's range and below the full
    well (a CCD sums b^2 pixels in its serial register before its one read; a CMOS digitises every pixel)."""
    _, _, fw, gain = _SENSOR[camera]
    top_e = 65535 * gain * 0.85
    if camera == "ml11002":
        return min(fw, top_e / binning ** 2) * 0.8 - 1000.0 * gain / binning ** 2
    return min(fw, top_e - 500 * gain) * 0.8


def single_case(index: int, rng: np.random.Generator) -> dict:
    """The ``index``-th null frame of the matrix: camera x frame type x geometry cycle through their values
    (every class is visited before any repeats), the window's size and place, the light level, the pointing
    and the frame seed drawn from ``rng``."""
    cameras = ("ml11002", "imx411")
    geoms = ("window", "full_a", "window", "full_a", "full_b")
    k = index
    camera = cameras[k % 2]
    frame = FRAMES[(k // 2) % len(FRAMES)]
    geom = geoms[(k // (2 * len(FRAMES))) % len(geoms)]
    sw, sh, fw, gain = _SENSOR[camera]
    det: dict = {"preset": camera}
    if geom == "window":
        side = int(rng.choice(WINDOWS))
        det.update(width=side, height=side, x0=int(rng.integers(0, sw - side)), y0=int(rng.integers(0, sh - side)))
        binning, mode = 1, "sum"
    else:
        binning, mode = FULL[camera][0 if geom == "full_a" else 1]
        det["binning"] = binning
        if mode != "sum":
            det["binning_mode"] = mode
    scene: dict = {"detector": det, "sky": {"stars": False}}
    if frame == "bias":
        scene["exposure"] = {"time_s": 0.0, "frame": "bias"}
    elif frame.startswith("dark"):
        scene["exposure"] = {"time_s": 10.0 if frame == "dark_short" else 300.0, "frame": "dark"}
    elif frame == "flat":
        t = 10.0
        level = float(rng.uniform(0.05, 1.0)) * _charge_cap_e(camera, binning, mode)
        scene["exposure"] = {"time_s": t, "frame": "light"}
        scene["sky"] = {"stars": False, "flat_e_per_s": round(level / t, 3)}
    else:
        sky = frame.split("_")[1]
        # the bright sky at most BRIGHT_SKY_FILL of the charge an output pixel can hold (a binned CCD pixel
        # sums b^2 of them); the dark sky in the same time
        t = round(min(30.0, BRIGHT_SKY_FILL * _charge_cap_e(camera, binning, mode) / SKY_RATE_BRIGHT[camera]), 3)
        scene["exposure"] = {"time_s": t, "frame": "light", "tracking": "sidereal"}
        scene["pointing"] = {"ra_deg": round(POINTING["ra_deg"] + float(rng.uniform(-1, 1)) * POINTING_JITTER_DEG, 5),
                             "dec_deg": round(POINTING["dec_deg"] + float(rng.uniform(-1, 1)) * POINTING_JITTER_DEG, 5),
                             "epoch": POINTING["epoch"]}
        scene["sky"] = {"stars": True, "star_mag_limit": 15.0, "background_mag_arcsec2": SKY_MAG[sky]}
        scene["psf"] = {"model": "gaussian", "fwhm_arcsec": round(float(rng.uniform(2.5, 4.0)), 3)}
    label = f"{camera}/{frame}/{geom if geom == 'window' else f'bin{binning}'}"
    return {"id": f"f{index:04d}", "kind": "single", "class": label, "camera": camera, "frame": frame,
            "geometry": "window" if geom == "window" else f"full_bin{binning}", "scene": scene,
            "seed": int(rng.integers(1, 2 ** 31 - 1))}


def null_series(index: int, rng: np.random.Generator) -> dict:
    """The ``index``-th null series: a clean flat series at several levels (ML11002 and IMX411 windows), a
    dark series at several exposure times, or a sky series at several pointings; 3-5 frames, each with its
    own seed."""
    kind = SERIES_KINDS[index % len(SERIES_KINDS)]
    camera = ("ml11002", "imx411")[(index // len(SERIES_KINDS)) % 2]
    sw, sh, fw, gain = _SENSOR[camera]
    side = 192
    det = {"preset": camera, "width": side, "height": side, "x0": int(rng.integers(0, sw - side)),
           "y0": int(rng.integers(0, sh - side))}
    n = int(rng.integers(3, 6))
    if kind == "flat":
        rate = round(float(rng.uniform(0.3, 0.6)) * fw / 8.0, 3)  # 8 s reach 30-60 % of the full well
        base = {"detector": det, "exposure": {"time_s": 1.0, "frame": "light"},
                "sky": {"stars": False, "flat_e_per_s": rate}}
        times = sorted(float(t) for t in rng.choice([1.0, 2.0, 3.0, 4.0, 6.0, 8.0], n, replace=False))
        sets = [{"exposure.time_s": t} for t in times]
    elif kind == "dark":
        base = {"detector": det, "exposure": {"time_s": 10.0, "frame": "dark"}, "sky": {"stars": False}}
        times = sorted(float(t) for t in rng.choice([10.0, 30.0, 60.0, 120.0, 300.0], n, replace=False))
        sets = [{"exposure.time_s": t} for t in times]
    else:
        base = {"detector": det, "exposure": {"time_s": 30.0, "frame": "light", "tracking": "sidereal"},
                "sky": {"stars": False, "background_mag_arcsec2": float(rng.choice(list(SKY_MAG.values())))}}
        ra0 = float(rng.uniform(0, 300))
        sets = [{"pointing.ra_deg": round(ra0 + 3.0 * i, 4)} for i in range(n)]
    return {"id": f"s{index:03d}", "kind": "series", "class": f"series/{camera}/{kind}", "camera": camera,
            "frame": f"series_{kind}", "geometry": "window", "scene": base, "sets": sets,
            "seeds": [int(s) for s in rng.integers(1, 2 ** 31 - 1, n)]}


def null_cases(n: int, seed: int) -> list[dict]:
    """``n`` null frames and ``max(1, n // SERIES_EVERY)`` null series (at least one of each kind when n
    allows), every one with its own seed drawn from ``seed``."""
    rng = np.random.default_rng(seed)
    singles = [single_case(i, rng) for i in range(n)]
    n_series = max(1, n // SERIES_EVERY) if n >= 6 else 0
    return singles + [null_series(i, rng) for i in range(n_series)]


# --- one frame ------------------------------------------------------------------------------------------------

_CHAIN: dict = {}


def textbook_frame(expected_path: Path, out: Path, seed: int) -> None:
    """The measured frame from newtsim's noiseless one through the textbook chain (loaded once per process
    with runpy; its ``main`` is called as its command line would be). An average-binned frame's mean charge
    is handed over as the binned pixel's total (the textbook chain's convention)."""
    from astropy.io import fits

    if "main" not in _CHAIN:
        _CHAIN.update(runpy.run_path(str(TEXTBOOK_CHAIN), run_name="textbook_chain"))
    src = expected_path
    with fits.open(expected_path) as hl:
        hdr = hl[0].header
        if str(hdr.get("BINMODE", "sum")).strip().lower() == "average" and int(hdr.get("XBINNING", 1)) > 1:
            n = int(hdr["XBINNING"]) * int(hdr["YBINNING"])
            src = expected_path.with_name(expected_path.stem + "_sum.fits")
            fits.PrimaryHDU((hl[0].data.astype(np.float64) * n).astype(np.float32), header=hdr).writeto(src, overwrite=True)
    _CHAIN["main"]([str(src), str(out), "--seed", str(seed)])


def _render_null(scene_dict: dict, folder: Path, name: str, seed: int, sets: tuple[str, ...] = ()) -> tuple[Path, Path]:
    """Write the scene, render it noiseless and draw the measured frame: (scene path, measured path)."""
    from scenes.app.render import render
    from scenes.scene import load_scene

    folder.mkdir(parents=True, exist_ok=True)
    sp = folder / f"{name}.toml"
    sp.write_text(tomli_w.dumps(scene_dict))
    exp = folder / f"{name}_expected.fits"
    render(load_scene(str(sp), list(sets)), exp, seed=seed, noiseless=True, progress=False, workers=1)
    meas = folder / f"{name}_measured.fits"
    textbook_frame(exp, meas, seed)
    for p in folder.glob(f"{name}_expected*.fits"):
        p.unlink()
    return sp, meas


#: candidate keys recorded (the raw statistics the judge thresholds on, and its gates' verdicts)
CANDIDATE_KEYS = ("effect", "kind", "delta_bic", "delta_m2lnl", "k", "heldout_delta", "explains_structure",
                  "explains_excess", "explains_where_it_acts", "chi2_per_dof", "significant", "rejected",
                  "plausible", "implausible_because", "params", "variant")
MORPH_KEYS = ("significant", "significance_sigma", "kind", "geometry", "scale_px", "amplitude", "unit", "explanation")


def diagnose_frame(scene_path: Path, measured: Path) -> dict:
    """The default judge: ``newtsim diagnose --json`` on one frame (:func:`scenes.app.compare.run_diagnose`)."""
    from scenes.app.compare import run_diagnose
    from scenes.scene import load_scene

    out = run_diagnose(load_scene(str(scene_path)), measured, workers=1)
    out.pop("_compare", None)
    return out


def diagnose_series(series_path: Path) -> dict:
    """The default judge of a series: ``newtsim diagnose --series`` (:func:`scenes.app.compare.series.run_series_diagnose`)."""
    from scenes.app.compare.series import load_series, run_series_diagnose

    out = run_series_diagnose(load_series(series_path), workers=1)
    out.pop("_compare", None)
    return out


def summarise_diagnosis(d: dict) -> dict:
    """The record's part from a diagnosis JSON: names, verdict, morphology and every candidate's statistics."""
    morph = d.get("residual_morphology") or {}
    return {"significant": list(d.get("significant") or []), "verdict": d.get("verdict", ""),
            "morph_significant": bool(morph.get("significant", False)),
            "morphology": {k: morph.get(k) for k in MORPH_KEYS if k in morph},
            "chi2_per_dof": (d.get("baseline") or {}).get("chi2_per_dof"),
            "candidates": [{k: c.get(k) for k in CANDIDATE_KEYS if k in c} for c in d.get("candidates", [])]}


def run_case(case: dict, workdir: str | Path, judge: Callable | None = None,
             series_judge: Callable | None = None) -> dict:
    """Make one null frame (or series), diagnose it, return its record (``error`` set when it failed)."""
    folder = Path(workdir) / case["id"]
    rec = {k: case[k] for k in ("id", "kind", "class", "camera", "frame", "geometry")}
    rec["seed"] = case.get("seed", case.get("seeds"))
    rec["scene"] = case["scene"]
    t0 = time.perf_counter()
    try:
        if case["kind"] == "single":
            sp, meas = _render_null(case["scene"], folder, "null", case["seed"])
            d = (judge or diagnose_frame)(sp, meas)
            rec["shape"] = _shape(meas)
        else:
            frames = []
            folder.mkdir(parents=True, exist_ok=True)
            (folder / "camera.toml").write_text(tomli_w.dumps(case["scene"]))
            for i, (st, sd) in enumerate(zip(case["sets"], case["seeds"])):
                sets = tuple(f"{k}={v}" for k, v in st.items())
                _, meas = _render_null(case["scene"], folder, f"frame{i}", sd, sets)
                (folder / f"frame{i}.toml").unlink()
                frames.append({"file": meas.name, "set": st, "label": f"{case['id']}_{i}"})
            series = folder / "series.toml"
            series.write_text(tomli_w.dumps({"scene": "camera.toml", "frames": frames}))
            d = (series_judge or diagnose_series)(series)
            rec["shape"] = _shape(folder / frames[0]["file"])
            rec["n_frames"] = len(frames)
        rec.update(summarise_diagnosis(d))
        rec["error"] = ""
    except Exception as exc:  # noqa: BLE001  (a failing frame is recorded, the run goes on)
        rec["error"] = f"{type(exc).__name__}: {exc}"
        rec["traceback"] = traceback.format_exc(limit=6)
    rec["seconds"] = round(time.perf_counter() - t0, 2)
    for p in folder.glob("*measured.fits"):
        p.unlink()  # the frames can be remade from the record's scene and seed
    return rec


def _shape(path: Path) -> list[int]:
    from astropy.io import fits

    return list(fits.getdata(path).shape)


def _init_worker():
    os.environ.setdefault("OMP_NUM_THREADS", "1")


def run_nulls(n: int, seed: int, workdir: str | Path, workers: int = 2, judge: Callable | None = None,
              series_judge: Callable | None = None, cases: list[dict] | None = None,
              on_record: Callable[[dict], None] | None = None) -> list[dict]:
    """Make and diagnose ``n`` null frames (and ``n // SERIES_EVERY`` null series) drawn from ``seed`` in
    ``workers`` processes; one record per frame/series (:func:`run_case`), in the order of :func:`null_cases`.

    ``judge(scene_path, measured_path) -> diagnosis dict`` (default :func:`diagnose_frame`, i.e. ``newtsim
    diagnose --json``) and ``series_judge(series_path) -> dict`` (default :func:`diagnose_series`) must be
    picklable (module-level functions) when ``workers > 1``. ``on_record`` sees every record as it arrives."""
    todo = cases if cases is not None else null_cases(n, seed)
    Path(workdir).mkdir(parents=True, exist_ok=True)
    out: dict[str, dict] = {}
    if workers <= 1:
        for c in todo:
            out[c["id"]] = r = run_case(c, workdir, judge, series_judge)
            if on_record:
                on_record(r)
    else:
        # series first (the longest jobs), then the frames
        order = sorted(todo, key=lambda c: c["kind"] != "series")
        with ProcessPoolExecutor(max_workers=workers, initializer=_init_worker) as ex:
            futs = {ex.submit(run_case, c, workdir, judge, series_judge): c["id"] for c in order}
            from concurrent.futures import as_completed
            for f in as_completed(futs):
                out[futs[f]] = r = f.result()
                if on_record:
                    on_record(r)
    return [out[c["id"]] for c in todo]


# --- the summary ----------------------------------------------------------------------------------------------

def wilson(k: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion k/n at ``z`` (95 %: z = 1.96; Wilson 1927, JASA 22, 209)."""
    if n == 0:
        return 0.0, 1.0
    p = k / n
    den = 1 + z * z / n
    c = (p + z * z / (2 * n)) / den
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return max(0.0, c - h), min(1.0, c + h)


def false_alarm(rec: dict) -> bool:
    """A null record is a false alarm when anything is named significant or the morphology is significant."""
    return bool(rec.get("significant")) or bool(rec.get("morph_significant"))


def passes_gates(c: dict) -> bool:
    """Whether a candidate passes every gate of the current judge other than the two thresholds the
    calibration sets (delta BIC, held-out delta): not rejected, plausible, and its shares not refused (the
    shares' thresholds as the judge holds them)."""
    from scenes.app.compare.policy import DEFAULT_POLICY as P

    MIN_EXPLAINED, MIN_EXCESS_SHARE, MIN_SUPPORT_SHARE = P.min_explained, P.min_excess_share, P.min_support_share

    if c.get("rejected") or not c.get("plausible", True):
        return False
    for key, lim in (("explains_structure", MIN_EXPLAINED), ("explains_excess", MIN_EXCESS_SHARE),
                     ("explains_where_it_acts", MIN_SUPPORT_SHARE)):
        if c.get(key) is not None and c[key] < lim:
            return False
    return True


#: signatures judged by counts or column statistics (no held-out score): their delta BIC is all there is
COUNT_KINDS = ("CountSignature", "ColumnSignature")


def extremes(rec: dict) -> dict:
    """Per record: the most negative delta BIC and held-out delta among all candidates and among those that
    pass the gates (:func:`passes_gates`), and the morphology's significance."""
    cands = rec.get("candidates") or []
    gated = [c for c in cands if passes_gates(c)]

    def lo(cs, key):
        v = [c[key] for c in cs if c.get(key) is not None and np.isfinite(c[key])]
        return float(min(v)) if v else float("nan")  # nothing to compare: not a value of the distribution

    counts = [c for c in gated if c.get("kind") in COUNT_KINDS]
    return {"min_dbic_all": lo(cands, "delta_bic"), "min_dbic_gated": lo(gated, "delta_bic"),
            "min_dm2lnl_gated": lo(gated, "delta_m2lnl"), "min_heldout_gated": lo(gated, "heldout_delta"),
            "min_dbic_counts_gated": lo(counts, "delta_bic"),
            "morph_sigma": float((rec.get("morphology") or {}).get("significance_sigma") or 0.0)}


def summarise(records: list[dict]) -> dict:
    """False-alarm rate (Wilson 95 %), per class and per camera/frame type, the names that fire, and the
    null distribution of the judge's statistics with the thresholds that hold the rate at 1 %."""
    ok = [r for r in records if not r.get("error")]
    k = sum(false_alarm(r) for r in ok)
    out: dict = {"n": len(ok), "errors": len(records) - len(ok), "false_alarms": k,
                 "rate": k / max(len(ok), 1), "wilson95": wilson(k, len(ok)),
                 "names": Counter(n for r in ok for n in (r.get("significant") or [])[:1]),
                 "names_any": Counter(n for r in ok for n in r.get("significant") or []),
                 "morph": sum(bool(r.get("morph_significant")) for r in ok)}
    groups: dict = defaultdict(list)
    for r in ok:
        groups[(r["camera"], r["frame"])].append(r)
        groups[("geometry", r["geometry"])].append(r)
        groups[("kind", r["kind"])].append(r)
    out["groups"] = {f"{a}/{b}": {"n": len(v), "false_alarms": sum(false_alarm(r) for r in v),
                                  "names": Counter(n for r in v for n in (r.get("significant") or [])[:1]),
                                  "morph": sum(bool(r.get("morph_significant")) for r in v)}
                     for (a, b), v in sorted(groups.items())}
    ex = [extremes(r) for r in ok]
    qs = (0.5, 0.9, 0.95, 0.99, 1.0)
    dist = {}
    for key in ("min_dbic_all", "min_dbic_gated", "min_dm2lnl_gated", "min_dbic_counts_gated", "min_heldout_gated"):
        v = np.array([e[key] for e in ex]) if ex else np.zeros(0)
        v = v[np.isfinite(v)]
        dist[key] = {f"q{int(q * 100)}": float(np.quantile(v, 1 - q)) if v.size else float("nan") for q in qs}
        dist[key]["n"] = int(v.size)  # lower tail: most negative
    v = np.array([e["morph_sigma"] for e in ex]) if ex else np.zeros(1)
    dist["morph_sigma"] = {f"q{int(q * 100)}": float(np.quantile(v, q)) for q in qs}
    dist["morph_sigma"]["n"] = int(v.size)
    out["distribution"] = dist
    out["thresholds"] = thresholds(ex)
    # the closest calls: the gated candidates with the lowest delta BIC over all null frames
    calls = [(c["delta_bic"], r["id"], r["class"], c["effect"]) for r in ok for c in r.get("candidates") or []
             if passes_gates(c) and c.get("delta_bic") is not None and c["delta_bic"] < 0]
    out["closest"] = sorted(calls)[:8]
    return out


def thresholds(ex: list[dict], rate: float = 0.01, margin: float = 2.0) -> dict:
    """Thresholds that hold the null false-alarm rate at ``rate`` with a margin: the (1 - rate / margin)
    quantile of each per-frame extreme (a frame passing a threshold stricter than its null's 0.5 % tail), i.e.
    a candidate must reach below it; the morphology's sigma above it. With n null frames the quantile rests on
    n rate / margin frames: read it with the Wilson interval of the rate."""
    if not ex:
        return {}
    q = rate / margin
    out = {}
    for key in ("min_dbic_gated", "min_heldout_gated"):
        v = np.array([e[key] for e in ex])
        v = v[np.isfinite(v)]
        out[key] = float(min(np.quantile(v, q), 0.0)) if v.size else float("nan")
    out["morph_sigma"] = float(np.quantile(np.array([e["morph_sigma"] for e in ex]), 1 - q))
    out["rate"], out["margin"], out["n"] = rate, margin, len(ex)
    return out


def markdown(summary: dict, title: str = "") -> str:
    """The summary as markdown tables (docs/null_calibration.md)."""
    lo, hi = summary["wilson95"]
    lines = [f"### {title}" if title else "",
             f"{summary['false_alarms']} false alarms in {summary['n']} null frames and series "
             f"({100 * summary['rate']:.1f} %, Wilson 95 % interval {100 * lo:.1f}-{100 * hi:.1f} %; "
             f"{summary['errors']} failed); significant morphology in {summary['morph']}.",
             "", "First names that fired: " + (", ".join(f"`{k}` {v}" for k, v in summary["names"].most_common())
                                               or "none") + ".", "",
             "| class | n | false alarms | first names | morphology |", "|---|---|---|---|---|"]
    for g, v in summary["groups"].items():
        lines.append(f"| {g} | {v['n']} | {v['false_alarms']} | "
                     + (", ".join(f"{k} {c}" for k, c in v["names"].most_common()) or "-") + f" | {v['morph']} |")
    lines += ["", "Null distribution of the per-frame extremes (lower tail for delta BIC and held-out delta: "
              "the value that qN % of the frames stay above):", "",
              "| statistic | frames | q50 | q90 | q95 | q99 | worst |", "|---|---|---|---|---|---|---|"]
    for key, d in summary["distribution"].items():
        lines.append(f"| {key} | {d['n']} | " + " | ".join(f"{d[k]:.4g}" for k in ("q50", "q90", "q95", "q99", "q100"))
                     + " |")
    if summary.get("closest"):
        lines += ["", "Closest calls (gated candidates with delta BIC < 0): " + "; ".join(
            f"{e} {d:.3g} ({i}, {c})" for d, i, c, e in summary["closest"]) + "."]
    t = summary.get("thresholds") or {}
    if t:
        lines += ["", f"Thresholds at the {100 * (1 - t['rate'] / t['margin']):.1f} % null quantile (rate "
                  f"{100 * t['rate']:.0f} %, margin {t['margin']:.0f}x, n = {t['n']}): delta BIC < "
                  f"{t['min_dbic_gated']:.4g}, held-out delta < {t['min_heldout_gated']:.4g}, morphology sigma > "
                  f"{t['morph_sigma']:.4g}."]
    return "\n".join(lines) + "\n"


def write_jsonl(records: list[dict], path: str | Path) -> None:
    from detector.jsonable import jsonable

    with open(path, "w") as fh:
        for r in records:
            fh.write(json.dumps(jsonable(copy.deepcopy(r)), default=str) + "\n")


def read_jsonl(path: str | Path) -> list[dict]:
    return [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]
