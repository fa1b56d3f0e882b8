"""Real data as ONE series: the SBIG STL-1001E bias, darks and flats diagnosed together, round by round.

The camera is characterised from its two bias frames and its darks at 10, 30, 60 and 300 s (as in
``real_sbig.py``, the 150 s dark held out of the characterisation); the series is then every frame of the
set: 2 bias (0 s), 5 darks (10 - 300 s) and 2 flats (23 s, the flat screen at the first flat's mean level),
each with its own exposure in the series file. ``newtsim diagnose --series`` is run until nothing
significant is left, each round applying the best candidate to the one scene that serves all nine frames.

Usage::

    python examples/diagnose/real_sbig_series.py [OUT_DIR] [--rounds N]

Writes ``OUT_DIR/series_round{k}.toml`` (the series files), ``camera_round{k}.toml`` (the scenes), the
diagnosis JSON and report of every round, the ledger and ``summary.json``. Reads
``../shared/realdata/sbig_stl1001e_calib`` relative to the project root (never copied).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import tomli_w

sys.path.insert(0, str(Path(__file__).resolve().parent))
from real_sbig import DATA, camera_scene, files, flat_scene


def series_table(camera_file: str, flat_rate: float) -> dict:
    frames = [{"file": f, "label": f"bias {i}", "set": {"exposure.frame": "bias", "exposure.time_s": 0.0}}
              for i, f in enumerate(files("bias-*.FIT"))]
    for f in files("darks-*.FIT"):
        t = float(Path(f).name.split("expos")[1].split("s-")[0])
        frames.append({"file": f, "label": f"dark {t:g} s", "set": {"exposure.frame": "dark", "exposure.time_s": t}})
    for i, f in enumerate(files("flat-*.FIT")):
        frames.append({"file": f, "label": f"flat {i}", "set": {"exposure.frame": "light", "exposure.time_s": 23.0,
                                                               "sky.flat_e_per_s": flat_rate}})
    return {"scene": camera_file, "frames": frames}


def main(argv=None) -> int:
    from scenes.app.compare.series import apply_series, load_series, public_json, run_series_diagnose, series_ledger
    from scenes.app.compare.series_report import write_series_report

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", nargs="?", default="out/realdata/sbig_series")
    ap.add_argument("--rounds", type=int, default=4)
    args = ap.parse_args(argv)
    if not DATA.is_dir():
        print(f"real data not found at {DATA}: nothing to do", file=sys.stderr)
        return 1
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    camera = camera_scene()
    flat = flat_scene(camera, files("flat-*.FIT")[0])
    (out / "camera_round1.toml").write_text(tomli_w.dumps(camera))
    series = out / "series_round1.toml"
    series.write_text(tomli_w.dumps(series_table("camera_round1.toml", flat["sky"]["flat_e_per_s"])))
    for stale in out.glob("*.ledger.json"):
        stale.unlink()
    rows = []
    for k in range(1, args.rounds + 1):
        t0 = time.perf_counter()
        ser = load_series(series)
        d = run_series_diagnose(ser)
        nxt = out / f"camera_round{k + 1}.toml" if k < args.rounds else None
        applied, new_series, best = apply_series(ser, d, nxt)
        if new_series is not None:
            new_series = new_series.rename(out / f"series_round{k + 1}.toml")
        d["applied"] = {"effect": best["effect"], "params": best["params"]} if applied else None
        d["ledger"] = series_ledger(ser, d, new_series, best if applied else None)
        pub = public_json(d)
        (out / f"series_round{k}.json").write_text(json.dumps(pub, indent=1))
        write_series_report(pub, out / f"series_round{k}.html", d["_compare"]["_compares"])
        b = pub["baseline"]
        row = {"round": k, "chi2_per_dof": b["chi2_per_dof"], "chi2_per_dof_levels": b["chi2_per_dof_levels"],
               "misfit": b["misfit"], "verdict": pub["verdict"], "applied": pub["applied"],
               "top": [(c["effect"], c["delta_bic"], c["heldout_delta"], c["significant"]) for c in pub["candidates"][:5]],
               "frames": [(f["label"], f["chi2_per_dof"], f["misfit"]) for f in pub["frames"]],
               "seconds": round(time.perf_counter() - t0, 1)}
        rows.append(row)
        print(f"round {k}: chi2/dof {b['chi2_per_dof']:.4g} (levels refitted {b['chi2_per_dof_levels']:.4g}), misfit "
              f"{b['misfit']:.4g}; {pub['verdict']}" + (f"; applies {best['effect']} {best['params']}" if applied else ""),
              flush=True)
        if not applied:
            break
        series = new_series
    (out / "summary.json").write_text(json.dumps(rows, indent=1, default=float))
    print(f"wrote {out}/summary.json and every round's series, scene, JSON, report and the ledger")
    return 0


if __name__ == "__main__":
    sys.exit(main())
