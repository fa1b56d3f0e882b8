"""Hidden-effect series: measured frame series with an effect the model scene lacks, for the series diagnosis.

Each case writes a model scene (``camera.toml``), the "measured" frames (rendered from a truth scene: the
model plus the hidden effect and the nuisances of a real camera: its own hardware seed, a lamp or sky a per
cent off, a dark current a few per cent off) and a series file (``series.toml``). Used by
tests/scenes/test_diagnose_series.py, benchmarks/bench_series.py and ``python -m
scenes.app.validation.series_cases OUT`` (which also diagnoses them and prints a table).

The cases are the pairs one frame cannot tell apart (issue "series diagnosis"):

* ``nonlinearity``: a flat series at six levels with a compressive response ``S (1 - beta S / FW)``, beta =
  0.04 (2 % at half full well), and a lamp 1 % brighter than the model's; ``flat_null`` without it;
* ``dark_gradient`` / ``bias_ramp``: dark series at four exposure times with a dark-current gradient (grows
  with exposure) or a bias ramp of 80 and 50 ADU across the sensor (does not); ``dark_null``;
* ``glow`` / ``straylight``: sky frames at the right edge of the sensor with an amplifier glow (the same in
  every frame) or a straylight gradient that changes direction from frame to frame (the pointing moves);
  ``sky_null``.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import tomli_w

from scenes.app.render import render
from scenes.scene import load_scene

#: the window of the small cases [sensor pixels]
SIZE = 192


@dataclass
class SeriesCase:
    name: str
    model: dict  #: the model scene
    frames: list[dict]  #: per frame: {"set": {...}, "truth": {effect: params}} (truth: the hidden effects)
    truth_changes: dict = field(default_factory=dict)  #: nuisances of the measured camera (merged into model)
    expect: str | None = None  #: the effect the diagnosis should name (None: nothing)
    expect_params: dict = field(default_factory=dict)  #: fitted parameter -> true value (within 20 %)
    must_not: tuple[str, ...] = ()  #: effects that must not be named


def _merge(base: dict, changes: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in changes.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else copy.deepcopy(v)
    return out


def _flat(size: int) -> dict:
    return {"detector": {"preset": "ml11002", "width": size, "height": size},
            "exposure": {"time_s": 1.0, "frame": "light"}, "sky": {"stars": False, "flat_e_per_s": 5000.0}}


def _dark(size: int) -> dict:
    return {"detector": {"preset": "ml11002", "width": size, "height": size, "dark_current_e_per_s": 0.5},
            "exposure": {"time_s": 10.0, "frame": "dark"}, "sky": {"stars": False}}


def _sky(size: int) -> dict:
    # a window at the right edge of the sensor, where an amplifier glows
    return {"detector": {"preset": "ml11002", "width": size, "height": size, "x0": 4008 - size, "y0": 1300},
            "exposure": {"time_s": 30.0, "frame": "light", "tracking": "sidereal"},
            "sky": {"stars": False, "background_mag_arcsec2": 20.5}}


FLAT_TIMES = (1.0, 2.0, 3.0, 4.0, 6.0, 8.0)
DARK_TIMES = (10.0, 30.0, 60.0, 120.0)
#: straylight in four frames: the gradient turns with the pointing [e-/s/pixel per 1000 px]
STRAY = ({"gx": 40.0, "gy": 0.0}, {"gx": 0.0, "gy": 40.0}, {"gx": -30.0, "gy": 25.0}, {"gx": 20.0, "gy": -35.0})


def cases(size: int = SIZE) -> list[SeriesCase]:
    flat_frames = [{"set": {"exposure.time_s": t}} for t in FLAT_TIMES]
    dark_frames = [{"set": {"exposure.time_s": t}} for t in DARK_TIMES]
    sky_frames = [{"set": {"pointing.ra_deg": 120.0 + 3 * i}} for i in range(4)]
    lamp = {"sky": {"flat_e_per_s": 5050.0}}
    warm = {"detector": {"dark_current_e_per_s": 0.51}}
    sky_off = {"sky": {"background_mag_arcsec2": 20.49}}
    glow = {"amp_glow": {"model": "edge", "edge": "right", "amplitude_e_per_s": 3.0, "scale_px": 120.0}}
    out = [
        SeriesCase("nonlinearity", _flat(size), [{**f, "truth": {"nonlinearity": {"beta": 0.04}}} for f in flat_frames],
                   lamp, "nonlinearity", {"beta": 0.04}),
        SeriesCase("flat_null", _flat(size), [{**f, "truth": {}} for f in flat_frames], lamp),
        SeriesCase("dark_gradient", _dark(size),
                   [{**f, "truth": {"dark_gradient": {"gradient_x_e_per_s": 0.4, "gradient_y_e_per_s": -0.25}}}
                    for f in dark_frames], warm, "dark_gradient", {"gradient_x_e_per_s": 0.4},
                   must_not=("bias_gradient",)),
        SeriesCase("bias_ramp", _dark(size),
                   [{**f, "truth": {"bias_gradient": {"gradient_x_adu": 80.0, "gradient_y_adu": -50.0,
                                                      "quadratic_adu": 0.0}}} for f in dark_frames],
                   warm, "bias_gradient", {"gradient_x_adu": 80.0}, must_not=("dark_gradient",)),
        SeriesCase("dark_null", _dark(size), [{**f, "truth": {}} for f in dark_frames], warm),
        SeriesCase("glow", _sky(size), [{**f, "truth": glow} for f in sky_frames], sky_off, "amp_glow",
                   must_not=("straylight", "sky_gradient")),
        SeriesCase("straylight", _sky(size),
                   [{**f, "truth": {"straylight": {"model": "field", **g}}} for f, g in zip(sky_frames, STRAY)],
                   sky_off, "straylight|sky_gradient", must_not=("amp_glow",)),
        SeriesCase("sky_null", _sky(size), [{**f, "truth": {}} for f in sky_frames], sky_off),
    ]
    return out


def write_case(case: SeriesCase, folder: str | Path, seed: int = 1000) -> Path:
    """Render the case's measured frames and write its model scene and series file; returns the series."""
    d = Path(folder)
    d.mkdir(parents=True, exist_ok=True)
    (d / "camera.toml").write_text(tomli_w.dumps(case.model))
    frames = []
    for i, fr in enumerate(case.frames):
        truth = _merge(case.model, case.truth_changes)
        truth = _merge(truth, {"detector": {"hardware_seed": 777}})
        if fr["truth"]:
            truth.setdefault("effects", {}).update(copy.deepcopy(fr["truth"]))
        tp = d / f"truth_{i}.toml"
        tp.write_text(tomli_w.dumps(truth))
        sets = [f"{k}={json.dumps(v) if isinstance(v, str) else v}" for k, v in fr["set"].items()]
        out = d / f"frame_{i}.fits"
        render(load_scene(str(tp), sets), out, seed=seed + i, progress=False)
        frames.append({"file": out.name, "set": fr["set"], "label": f"{case.name}_{i}"})
    series = d / "series.toml"
    series.write_text(tomli_w.dumps({"scene": "camera.toml", "frames": frames}))
    return series


def named(diagnosis: dict) -> str | None:
    sig = diagnosis.get("significant") or []
    return sig[0] if sig else None


def judge(case: SeriesCase, diagnosis: dict) -> dict:
    """Whether the diagnosis of the case is right: the expected effect named first (or nothing for a null),
    its parameters within 20 %, none of ``must_not`` named first."""
    first = named(diagnosis)
    want = case.expect.split("|") if case.expect else [None]
    ok = first in want
    params = {}
    if ok and case.expect_params:
        cand = next(c for c in diagnosis["candidates"] if c["effect"] == first)
        for k, v in case.expect_params.items():
            got = cand["params"].get(k)
            params[k] = got
            ok = ok and got is not None and abs(got - v) <= 0.2 * abs(v)
    return {"case": case.name, "expect": case.expect, "named": first, "ok": bool(ok and first not in case.must_not),
            "params": params, "verdict": diagnosis["verdict"]}


def main(argv: list[str] | None = None) -> int:
    from scenes.app.compare.series import load_series, run_series_diagnose

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--cases", default="", help="comma-separated case names (default: all)")
    ap.add_argument("--single", action="store_true",
                    help="also diagnose the last frame of every series alone (what one frame names)")
    args = ap.parse_args(argv)
    chosen = [c for c in cases() if not args.cases or c.name in args.cases.split(",")]
    rows = []
    for case in chosen:
        t0 = time.perf_counter()
        series = write_case(case, args.out / case.name)
        d = run_series_diagnose(load_series(series))
        row = judge(case, d)
        row["seconds"] = round(time.perf_counter() - t0, 1)
        if args.single:
            from scenes.app.compare import run_diagnose

            last = load_series(series).frames[-1]
            one = run_diagnose(last.scene, last.file)
            row["single_frame"] = {"frame": last.label, "named": named(one), "cannot_tell_from": one["indistinguishable"],
                                   "verdict": one["verdict"]}
        rows.append(row)
        print(f"{case.name:14s} expect {case.expect or 'nothing':22s} named {row['named'] or 'nothing':16s} "
              f"{'ok' if row['ok'] else 'WRONG'} {row['params']} ({row['seconds']} s)"
              + (f"; one frame alone: {row['single_frame']['named'] or 'nothing'}"
                 + (f" (cannot tell from {', '.join(row['single_frame']['cannot_tell_from'])})"
                    if row["single_frame"]["cannot_tell_from"] else "") if args.single else ""), flush=True)
    (args.out / "series_cases.json").write_text(json.dumps(rows, indent=1))
    return 0 if all(r["ok"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
